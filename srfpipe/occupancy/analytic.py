"""Analytic semantic fields: solid spheres and capsules of known density and class.

A real input type for `distill` (anything with `classes`, `bounds_world`, `density`, `semantic`):
the tests distill them and compare with the exact geometry, and a simulator can use one as a
stand-in scene whose answers are known in closed form.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Primitive:
    """A solid: a sphere (start == end) or a capsule (segment start-end swept by `radius`).

    `class_index` -1: matter of no class (a field without semantics, or the ground).
    """

    start: np.ndarray
    end: np.ndarray
    radius: float
    class_index: int

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Euclidean signed distance to the surface (negative inside), world units."""
        axis = self.end - self.start
        length2 = float(axis @ axis)
        rel = points - self.start
        if length2 == 0.0:
            nearest = rel
        else:
            t = np.clip(rel @ axis / length2, 0.0, 1.0)
            nearest = rel - t[:, None] * axis
        return np.linalg.norm(nearest, axis=-1) - self.radius


@dataclass
class AnalyticField:
    """A union of primitives with constant density `sigma` inside and zero outside.

    `semantic` is one-hot: probability 1 for the class of the (first) primitive containing the
    point, 0 everywhere else, including free space and primitives of no class (`class_name` None).
    `unit` names the world unit when known (distillation records it).
    """

    classes: list[str]
    bounds_world: np.ndarray
    sigma: float = 1000.0  # per world unit: opaque well inside one voxel
    primitives: list[Primitive] = field(default_factory=list)
    unit: str | None = None

    def _class_index(self, class_name: str | None) -> int:
        if class_name is None:
            return -1
        if class_name not in self.classes:
            raise ValueError(f"unknown class {class_name!r}; the field has {self.classes}")
        return self.classes.index(class_name)

    def add_sphere(self, centre, radius: float, class_name: str | None) -> "AnalyticField":
        c = np.asarray(centre, dtype=np.float64)
        self.primitives.append(Primitive(c, c.copy(), float(radius), self._class_index(class_name)))
        return self

    def add_capsule(self, start, end, radius: float, class_name: str | None) -> "AnalyticField":
        self.primitives.append(Primitive(np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64),
                                         float(radius), self._class_index(class_name)))
        return self

    def _owner(self, points_world) -> np.ndarray:
        """Index of the first primitive containing each point, -1 for none."""
        points = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        owner = np.full(len(points), -1, dtype=np.int64)
        for index, primitive in enumerate(self.primitives):
            inside = (owner < 0) & (primitive.signed_distance(points) <= 0)
            owner[inside] = index
        return owner

    def density(self, points_world) -> np.ndarray:
        return np.where(self._owner(points_world) >= 0, self.sigma, 0.0).astype(np.float32)

    def semantic(self, points_world) -> np.ndarray:
        owner = self._owner(points_world)
        probs = np.zeros((len(owner), len(self.classes)), dtype=np.float32)
        class_of = np.array([p.class_index for p in self.primitives] + [-1], dtype=np.int64)
        point_class = class_of[owner]  # owner -1 (free space) picks the appended -1
        hit = point_class >= 0
        probs[np.flatnonzero(hit), point_class[hit]] = 1.0
        return probs

    # Colours, so a simulator can render the stand-in scene (srfpipe.sim bakes any field with these)
    class_colours: dict = field(default_factory=lambda: {"apple": (0.8, 0.1, 0.1), "branch": (0.45, 0.3, 0.15),
                                                         "leaf": (0.2, 0.6, 0.2)})
    sky: tuple = (0.6, 0.75, 0.95)

    def radiance(self, points_world, directions_world=None) -> np.ndarray:
        """Colour (M, 3) of the primitive containing each point (grey for no class, black outside)."""
        owner = self._owner(points_world)
        table = np.array([self.class_colours.get(self.classes[p.class_index], (0.5, 0.5, 0.5))
                          if p.class_index >= 0 else (0.5, 0.5, 0.5) for p in self.primitives] + [(0.0, 0.0, 0.0)],
                         dtype=np.float32).reshape(-1, 3)
        return table[owner]

    def background(self, directions_world) -> tuple[np.ndarray, np.ndarray]:
        """The sky (a constant colour) and background class probabilities (0)."""
        n = len(np.asarray(directions_world).reshape(-1, 3))
        return np.tile(np.asarray(self.sky, np.float32), (n, 1)), np.zeros(len(self.classes), np.float32)

    def signed_distance(self, points_world, class_name: str | None = None) -> np.ndarray:
        """Exact signed distance to the union of primitives (of one class), for checking caches."""
        points = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        d = np.full(len(points), np.inf)
        for primitive in self.primitives:
            if class_name is None or (primitive.class_index >= 0 and self.classes[primitive.class_index] == class_name):
                d = np.minimum(d, primitive.signed_distance(points))
        return d
