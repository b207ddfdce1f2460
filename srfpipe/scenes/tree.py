"""Procedural apple-tree geometry: a branch skeleton, leaves, apples and the ground, as triangle meshes.

World frame: metres, z up, the trunk base at the origin (see `srfpipe.scenes.orchard`).
Everything here is plain numpy and deterministic given a `numpy.random.Generator`.

The skeleton is grown as a recursive tree of straight segments (trunk, scaffold branches, twigs);
each segment becomes a tube capped by a sphere so joints stay closed (a capsule). It is scaled so
the leaf canopy tops out at `tree_height`. Leaves are small diamond-shaped quads scattered along
the outer two branch levels; apples are spheres hung just below branches of the outer levels,
not touching each other or the wood, and leaves inside an apple are removed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

APPLE_RADIUS = 0.04  # metres: an ~8 cm apple
LEAF_LENGTH = 0.075  # metres
LEAF_WIDTH = 0.04
LEAF_SCATTER = 0.09  # how far (metres) a leaf centre strays from its twig
TUBE_SIDES = 8
TRUNK_RADIUS = 0.028  # trunk radius as a fraction of tree_height (7 cm for a 2.5 m tree)
UNIT_TRUNK_RADIUS = 0.04  # in the unit skeleton, before scaling
UNIT_TRUNK_LENGTH = 0.36
SCAFFOLD_LENGTH = 0.42  # first-level branches, unit skeleton
CANOPY_HALF_WIDTH = 0.5  # twig tips stay within this fraction of tree_height from the trunk axis
SPHERE_RINGS = 8  # latitude bands of the apple and joint spheres
SPHERE_SEGMENTS = 12


@dataclass
class Mesh:
    """An indexed triangle mesh, float32 vertices (V, 3) and int32 triangles (T, 3)."""

    vertices: np.ndarray
    triangles: np.ndarray

    @staticmethod
    def concatenate(meshes: list["Mesh"]) -> "Mesh":
        if not meshes:
            return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        vertices = np.concatenate([m.vertices for m in meshes]).astype(np.float32)
        triangles = np.concatenate([m.triangles + o for m, o in zip(meshes, offsets)]).astype(np.int32)
        return Mesh(vertices, triangles)


@dataclass
class Segment:
    start: np.ndarray
    end: np.ndarray
    radius: float
    level: int  # 0 = trunk


@dataclass
class Tree:
    """All geometry of one generated tree (world frame, metres)."""

    segments: list[Segment]
    branch: Mesh
    leaf: Mesh
    apple: Mesh
    ground: Mesh
    apple_centres: np.ndarray  # (A, 3)
    apple_radius: float
    apple_ripeness: np.ndarray  # (A,) 0 = yellow-green, 1 = red
    leaf_tint: np.ndarray  # (L,) per-leaf brightness/hue variation in [0, 1]
    triangles_per_apple: int
    info: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------- mesh primitives


def _orthonormal_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to `axis` and to each other."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(axis, u)


def tube(start: np.ndarray, end: np.ndarray, r0: float, r1: float, sides: int = TUBE_SIDES) -> Mesh:
    """An open tapered tube from `start` (radius r0) to `end` (radius r1)."""
    axis = end - start
    axis = axis / np.linalg.norm(axis)
    u, v = _orthonormal_basis(axis)
    angles = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
    ring = np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v
    vertices = np.concatenate([start + r0 * ring, end + r1 * ring])
    i = np.arange(sides)
    j = (i + 1) % sides
    triangles = np.concatenate([np.stack([i, j, j + sides], 1), np.stack([i, j + sides, i + sides], 1)])
    return Mesh(vertices.astype(np.float32), triangles.astype(np.int32))


def _unit_sphere(rings: int = SPHERE_RINGS, segments: int = SPHERE_SEGMENTS) -> Mesh:
    """A UV sphere of radius 1 with poles on z; same triangle count for every call."""
    theta = np.linspace(0.0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    body = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    vertices = np.concatenate([[[0.0, 0.0, 1.0]], body, [[0.0, 0.0, -1.0]]])
    tris = []
    s = segments
    for k in range(s):  # north cap
        tris.append([0, 1 + k, 1 + (k + 1) % s])
    for r in range(rings - 2):
        for k in range(s):
            a, b = 1 + r * s + k, 1 + r * s + (k + 1) % s
            c, d = a + s, b + s
            tris += [[a, c, d], [a, d, b]]
    south = len(vertices) - 1
    last = 1 + (rings - 2) * s
    for k in range(s):
        tris.append([south, last + (k + 1) % s, last + k])
    return Mesh(vertices.astype(np.float32), np.asarray(tris, np.int32))


UNIT_SPHERE = _unit_sphere()


def spheres(centres: np.ndarray, radius: float | np.ndarray) -> Mesh:
    """One UV sphere per centre; sphere k owns triangles [k*T, (k+1)*T)."""
    centres = np.asarray(centres, np.float32).reshape(-1, 3)
    radius = np.broadcast_to(np.asarray(radius, np.float32), (len(centres),))
    n_v, n_t = len(UNIT_SPHERE.vertices), len(UNIT_SPHERE.triangles)
    vertices = (UNIT_SPHERE.vertices[None] * radius[:, None, None] + centres[:, None]).reshape(-1, 3)
    triangles = (UNIT_SPHERE.triangles[None] + n_v * np.arange(len(centres))[:, None, None]).reshape(-1, 3)
    return Mesh(vertices.astype(np.float32), triangles.astype(np.int32))


def wood_mesh(segments: list["Segment"], taper: float = 0.85) -> Mesh:
    """A tube per segment tapering to `taper` times its radius, capped by a sphere so joints stay closed."""
    return Mesh.concatenate(
        [tube(s.start, s.end, s.radius, s.radius * taper) for s in segments]
        + [spheres(np.array([s.end for s in segments]), np.array([s.radius * taper for s in segments]))]
    )


def far_from(points: np.ndarray, centres: np.ndarray, distance: float) -> np.ndarray:
    """(P,) True where a point is more than `distance` from every centre (all True without centres)."""
    if len(points) == 0 or len(centres) == 0:
        return np.ones(len(points), bool)
    return np.linalg.norm(points[:, None] - centres[None], axis=-1).min(1) > distance


DIAMOND = ((-1.0, 0.0), (0.0, 1.0), (1.0, 0.0), (0.0, -1.0))  # leaf outline: (along, across) in half sizes


def leaves(centres: np.ndarray, normals: np.ndarray, directions: np.ndarray, length: float = LEAF_LENGTH,
           width: float = LEAF_WIDTH, outline=DIAMOND) -> Mesh:
    """Flat leaves, one convex `outline` each, fanned from its first point (the leaf's base).

    `outline` points are (along the blade, across it) in units of half the length and half the
    width; leaf k owns triangles [k*(P-2), (k+1)*(P-2)) for P outline points (2 for the diamond).
    """
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    d = directions - np.sum(directions * n, axis=1, keepdims=True) * n  # blade direction in the leaf plane
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    side = np.cross(n, d)
    half_l, half_w = 0.5 * length, 0.5 * width
    corners = np.stack([centres + along * half_l * d + across * half_w * side for along, across in outline], 1)
    points = len(outline)
    fan = np.array([[0, k, k + 1] for k in range(1, points - 1)])
    base = points * np.arange(len(centres))[:, None, None]
    triangles = (base + fan[None]).reshape(-1, 3)
    return Mesh(corners.reshape(-1, 3).astype(np.float32), triangles.astype(np.int32))


def ground_plane(half_size: float = 200.0) -> Mesh:
    """A square at z = 0; large enough that cameras on the rings never see its edge below the horizon."""
    h = half_size
    vertices = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]], np.float32)
    return Mesh(vertices, np.array([[0, 1, 2], [0, 2, 3]], np.int32))


# ----------------------------------------------------------------------------- skeleton


def tilted(direction: np.ndarray, angle: float, azimuth: float) -> np.ndarray:
    """Rotate `direction` away from itself by `angle`, towards the side given by `azimuth`."""
    u, v = _orthonormal_basis(direction)
    side = np.cos(azimuth) * u + np.sin(azimuth) * v
    out = np.cos(angle) * direction + np.sin(angle) * side
    return out / np.linalg.norm(out)


def grow_skeleton(rng: np.random.Generator, depth: int) -> list[Segment]:
    """Branch segments of a unit-scale tree: a trunk, then `depth` levels of children.

    Children sprout along the outer part of their parent at golden-angle azimuths (so they
    spread round the tree), tilt 35-60 degrees from the parent and are pulled slightly upward,
    like the open vase shape of a pruned apple tree.
    """
    trunk_dir = tilted(np.array([0.0, 0.0, 1.0]), rng.uniform(0.0, 0.08), rng.uniform(0, 2 * np.pi))
    segments = [Segment(np.zeros(3), UNIT_TRUNK_LENGTH * trunk_dir, UNIT_TRUNK_RADIUS, 0)]
    frontier = [segments[0]]
    golden = np.pi * (3.0 - np.sqrt(5.0))
    for level in range(1, depth + 1):
        next_frontier = []
        for parent in frontier:
            axis = parent.end - parent.start
            length = np.linalg.norm(axis)
            direction = axis / length
            n_children = 4 if level == 1 else int(rng.choice([2, 3, 3]))
            azimuth0 = rng.uniform(0, 2 * np.pi)
            for k in range(n_children):
                # the last child continues from the tip; the others sprout along the parent
                at = 1.0 if k == n_children - 1 else rng.uniform(0.55, 0.95)
                start = parent.start + at * axis
                tilt = rng.uniform(0.6, 1.05)
                child_dir = tilted(direction, tilt, azimuth0 + 2 * k * golden + rng.normal(0, 0.2))
                child_dir = child_dir + np.array([0.0, 0.0, 0.25])  # phototropism
                child_dir /= np.linalg.norm(child_dir)
                if level == 1:  # scaffold branches: a fixed share of the unit tree, whatever the trunk
                    child_len = SCAFFOLD_LENGTH * rng.uniform(0.85, 1.1)
                    radius = parent.radius * 0.55
                else:
                    child_len = 0.72 * length * rng.uniform(0.8, 1.1)
                    radius = parent.radius * 0.6
                child = Segment(start, start + child_len * child_dir, radius, level)
                segments.append(child)
                next_frontier.append(child)
        frontier = next_frontier
    return segments


def point_segment_distance(points: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Distances (P, S) from each point to each segment."""
    ab = ends - starts
    ap = points[:, None, :] - starts[None]
    t = np.clip(np.sum(ap * ab[None], -1) / np.maximum(np.sum(ab * ab, -1), 1e-12)[None], 0.0, 1.0)
    closest = starts[None] + t[..., None] * ab[None]
    return np.linalg.norm(points[:, None, :] - closest, axis=-1)


# ----------------------------------------------------------------------------- the whole tree


def _scatter_leaves(rng, segments, leaf_density: float, depth: int):
    """Leaf centres, normals and blade directions along the outer two branch levels."""
    outer = [s for s in segments if s.level >= max(1, depth - 1)]
    centres, normals, directions = [], [], []
    for seg in outer:
        axis = seg.end - seg.start
        length = np.linalg.norm(axis)
        # twigs carry more leaves than the branch they grow from
        per_metre = (220.0 if seg.level == depth else 90.0) * leaf_density
        n = rng.poisson(per_metre * length)
        if n == 0:
            continue
        t = rng.uniform(0.15, 1.0, n) ** 0.7
        scatter = rng.normal(0.0, LEAF_SCATTER / 1.7, (n, 3))
        centres.append(seg.start + t[:, None] * axis + scatter)
        # mostly facing up and out, with a lot of spread
        normal = rng.normal(0.0, 1.0, (n, 3)) + np.array([0.0, 0.0, 1.2])
        normals.append(normal)
        directions.append(scatter + 0.3 * axis / length + rng.normal(0, 0.3, (n, 3)))
    if not centres:
        empty = np.zeros((0, 3))
        return empty, empty, empty
    return np.concatenate(centres), np.concatenate(normals), np.concatenate(directions)


APPLE_TRY_BUDGET = 200_000  # _hang_apples, past this many tries (1000 apples' 200 each: fewer asked, unchanged) ...
APPLE_MAX_MISSES = 20_000  # ... gives up after this many in a row without room: the tree is full


def _hang_apples(rng, segments, n_apples: int, depth: int, radius: float) -> np.ndarray:
    """Apple centres hung just below points on outer branches, not touching wood or each other."""
    candidates = [s for s in segments if s.level >= max(1, depth - 1)] or segments[1:] or segments
    starts = np.array([s.start for s in segments])
    ends = np.array([s.end for s in segments])
    radii = np.array([s.radius for s in segments])
    lengths = np.array([np.linalg.norm(s.end - s.start) for s in candidates])
    weights = lengths / lengths.sum()
    centres: list[np.ndarray] = []
    misses = 0  # tries in a row that found no room: the tree is full (it holds a few hundred)
    for tries in range(200 * max(n_apples, 1)):
        if len(centres) >= n_apples or (tries >= APPLE_TRY_BUDGET and misses >= APPLE_MAX_MISSES):
            break
        misses += 1
        seg = candidates[rng.choice(len(candidates), p=weights)]
        point = seg.start + rng.uniform(0.3, 1.0) * (seg.end - seg.start)
        # a short stalk: the apple hangs below its branch, a little to one side
        sideways = rng.normal(0.0, 0.3 * radius, 2)
        stalk = rng.uniform(0.005, 0.03)
        offset = np.array([*sideways, -(radius + seg.radius + stalk)])
        centre = point + offset
        if centre[2] < 0.4 + radius:
            continue
        clearance = point_segment_distance(centre[None], starts, ends)[0] - radii
        if np.any(clearance < radius * 1.02):
            continue
        if centres and np.min(np.linalg.norm(np.array(centres) - centre, axis=1)) < 2.1 * radius:
            continue
        misses = 0
        centres.append(centre)
    return np.array(centres).reshape(-1, 3)


def _ripeness(rng: np.random.Generator, n: int) -> np.ndarray:
    """Per apple: mostly red (about 0.75..1), a third yellow-green (0..0.3); streaks mix them on the skin."""
    red = rng.random(n) < 0.65
    return np.where(red, rng.uniform(0.75, 1.0, n), rng.uniform(0.0, 0.3, n))


def build_tree(
    seed: int, n_apples: int, branch_depth: int, leaf_density: float, tree_height: float
) -> Tree:
    """Generate the full, deterministic tree geometry for one seed."""
    rng = np.random.default_rng(seed)
    segments = grow_skeleton(rng, branch_depth)
    # scale the skeleton so the canopy (twig tips plus leaf scatter) reaches tree_height
    top = max(s.end[2] for s in segments)
    scale = (tree_height - LEAF_SCATTER) / top
    for s in segments:
        # wood thickness follows the tree's size in metres, not the skeleton scale, so a shallow
        # (branch_depth 1-2) tree is not stretched into a stump of logs
        s.start, s.end = s.start * scale, s.end * scale
        s.radius *= TRUNK_RADIUS * tree_height / UNIT_TRUNK_RADIUS
    # keep the canopy within the camera rings' view: squeeze it horizontally if it spreads too far
    reach = max(np.linalg.norm(s.end[:2]) for s in segments)
    squeeze = min(1.0, CANOPY_HALF_WIDTH * tree_height / reach)
    for s in segments:
        s.start[:2] *= squeeze
        s.end[:2] *= squeeze
    # the trunk base sinks a little into the ground so there is no visible gap at z = 0
    segments[0].start = segments[0].start - np.array([0.0, 0.0, 0.05])

    branch = wood_mesh(segments)

    leaf_centres, leaf_normals, leaf_dirs = _scatter_leaves(rng, segments, leaf_density, branch_depth)
    apple_centres = _hang_apples(rng, segments, n_apples, branch_depth, APPLE_RADIUS)
    keep = leaf_centres[:, 2] > 0.05 if len(leaf_centres) else np.zeros(0, bool)
    # no leaf blade may pierce an apple: it would show as green speckles on the fruit
    keep &= far_from(leaf_centres, apple_centres, APPLE_RADIUS + 0.5 * LEAF_LENGTH)
    leaf_centres = leaf_centres[keep]
    leaf = leaves(leaf_centres, leaf_normals[keep], leaf_dirs[keep])
    apple = spheres(apple_centres, APPLE_RADIUS)

    return Tree(
        segments=segments,
        branch=branch,
        leaf=leaf,
        apple=apple,
        ground=ground_plane(),
        apple_centres=apple_centres,
        apple_radius=APPLE_RADIUS,
        apple_ripeness=_ripeness(rng, len(apple_centres)),
        leaf_tint=rng.uniform(0.0, 1.0, len(leaf_centres)),
        triangles_per_apple=len(UNIT_SPHERE.triangles),
        info={
            "n_segments": len(segments),
            "n_leaves": int(len(leaf_centres)),
            "n_apples": int(len(apple_centres)),
            "skeleton_scale": float(scale),
            "canopy_squeeze": float(squeeze),
        },
    )
