"""CPU ray-cast renderer for the procedural scenes (open3d `RaycastingScene`), and the orchard's materials.

A scene is a list of `Part`s (mesh, class value, material) under a `Lighting`; the orchard's are
built by `orchard_parts`, the plant's in `srfpipe.scenes.plant`.

Per pixel: one primary ray (class label, z-depth, colour), then one shadow ray toward the sun
from every hit. Colour = albedo * (sky ambient + sun * max(0, n.l) * lit), gamma-encoded; misses
get the lighting's background (the orchard's sky gradient). Every albedo is modulated by 3D value noise of the world hit position, so
the texture is fixed to the surface (multi-view consistent) and rich enough for SIFT matching.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from srfpipe.cameras import pixel_rays
from srfpipe.scenes.tree import UNIT_SPHERE, Mesh, Tree

# orchard class values in the label images (paper order); the ground is background
BACKGROUND, APPLE, BRANCH, LEAF = 0, 1, 2, 3

SKY_ZENITH = np.array([0.32, 0.52, 0.86])
SKY_HORIZON = np.array([0.80, 0.87, 0.95])
AMBIENT = 0.38
SUN = 0.85
RAYS_PER_CHUNK = 1 << 19
SHADOW_BIAS = 2e-3  # metres: start shadow rays just off the surface to avoid self-hits


# ----------------------------------------------------------------------------- value noise


def _hash01(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    """A float in [0, 1) per integer lattice point (a 32-bit integer hash, wraps on purpose)."""
    h = ix.astype(np.uint32) * np.uint32(0x8DA6B343)
    h ^= iy.astype(np.uint32) * np.uint32(0xD8163841)
    h ^= iz.astype(np.uint32) * np.uint32(0xCB1AB31F)
    h ^= np.uint32((seed * 0x9E3779B1) & 0xFFFFFFFF)
    h ^= h >> np.uint32(15)
    h *= np.uint32(0x2C1B3C6D)
    h ^= h >> np.uint32(12)
    h *= np.uint32(0x297A2D39)
    h ^= h >> np.uint32(15)
    return h.astype(np.float32) * np.float32(1.0 / 4294967296.0)


def value_noise(points: np.ndarray, frequency: float, seed: int) -> np.ndarray:
    """Smooth 3D value noise in [0, 1] at `points` (N, 3), one lattice cell = 1 / frequency metres."""
    p = np.asarray(points, np.float32) * np.float32(frequency)
    base = np.floor(p)
    f = p - base
    f = f * f * (3.0 - 2.0 * f)  # smoothstep: no visible lattice creases
    i = base.astype(np.int64)
    x0, y0, z0 = i[:, 0], i[:, 1], i[:, 2]
    fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
    out = np.zeros(len(p), np.float32)
    for dx in (0, 1):
        wx = fx if dx else 1.0 - fx
        for dy in (0, 1):
            wy = fy if dy else 1.0 - fy
            for dz in (0, 1):
                wz = fz if dz else 1.0 - fz
                out += wx * wy * wz * _hash01(x0 + dx, y0 + dy, z0 + dz, seed)
    return out


def fbm(points: np.ndarray, frequency: float, seed: int, octaves: int = 3, footprint=None) -> np.ndarray:
    """Fractal noise: octaves of value noise, each twice the frequency and half the weight; in [0, 1].

    `footprint` (N,) is the size of a pixel on the surface (metres). Octaves finer than about two
    pixels fade to their mean, a cheap texture level of detail: without it the distant ground
    would sparkle with aliasing that differs from view to view and misleads SIFT matching.
    """
    total = np.zeros(len(points), np.float32)
    weight, norm = 1.0, 0.0
    for k in range(octaves):
        freq = frequency * 2.0**k
        octave = value_noise(points, freq, seed + 101 * k)
        if footprint is not None:
            fade = np.clip((0.5 - freq * footprint) / 0.25, 0.0, 1.0).astype(np.float32)
            octave = 0.5 + fade * (octave - 0.5)
        total += weight * octave
        norm += weight
        weight *= 0.5
    return total / norm


# ----------------------------------------------------------------------------- materials


def mix_colours(a, b, t):
    t = np.asarray(t, np.float32)[:, None]
    return (1.0 - t) * np.asarray(a, np.float32) + t * np.asarray(b, np.float32)


def spots(x: np.ndarray, frequency: float, seed: int, coverage: float, footprint=None) -> np.ndarray:
    """Sharp-edged blobs (about 1 / (2 frequency) metres across) covering roughly `coverage` of the surface.

    Thresholded value noise: crisp, scale-distinct blobs are what SIFT detects and matches best.
    They fade out once smaller than about two pixels, like the fine noise octaves.
    """
    noise = value_noise(x, frequency, seed)
    threshold = 1.0 - 0.6 * coverage ** 0.5  # value noise piles up around 0.5: a rough inverse CDF
    mask = np.clip((noise - threshold) / 0.03, 0.0, 1.0)
    if footprint is not None:
        mask *= np.clip((0.25 - frequency * footprint) / 0.1, 0.0, 1.0)
    return mask.astype(np.float32)


# (frequency per metre, colour): clover and daisies, dry leaves, clods and pebbles
GROUND_SPOTS = [
    (2.5, [0.55, 0.62, 0.25]), (4.0, [0.12, 0.09, 0.05]), (7.0, [0.80, 0.74, 0.45]),
    (12.0, [0.07, 0.05, 0.03]), (20.0, [0.9, 0.88, 0.8]), (33.0, [0.10, 0.12, 0.04]),
]


def ground_albedo(x: np.ndarray, seed: int, footprint=None) -> np.ndarray:
    """Grass with bare-soil patches, fine speckle, pale flowers and dark clods."""
    patches = np.clip((fbm(x, 0.6, seed + 1) - 0.42) * 4.0, 0.0, 1.0)
    grass = mix_colours([0.20, 0.36, 0.10], [0.36, 0.46, 0.16], fbm(x, 3.0, seed + 2))
    soil = mix_colours([0.30, 0.22, 0.14], [0.48, 0.38, 0.26], fbm(x, 4.0, seed + 3))
    albedo = mix_colours(grass, soil, patches)
    detail = fbm(x, 10.0, seed + 4, octaves=4, footprint=footprint)
    albedo = albedo * (0.4 + 1.2 * detail)[:, None]
    # blobs at several scales, so every distance from the cameras has features SIFT can match
    for k, (frequency, colour) in enumerate(GROUND_SPOTS):
        albedo = mix_colours(albedo, colour, spots(x, frequency, seed + 5 + k, 0.05, footprint))
    return albedo


def branch_albedo(x: np.ndarray, seed: int, footprint=None) -> np.ndarray:
    """Grey-brown bark with fine, high-contrast cracks, pale lichen and dark knots."""
    base = mix_colours([0.22, 0.15, 0.09], [0.42, 0.33, 0.24], fbm(x, 6.0, seed + 11, octaves=2))
    detail = fbm(x, 25.0, seed + 12, octaves=3, footprint=footprint)
    albedo = base * (0.4 + 1.2 * detail)[:, None]
    albedo = mix_colours(albedo, [0.62, 0.66, 0.52], spots(x, 14.0, seed + 13, 0.12, footprint))
    return mix_colours(albedo, [0.06, 0.04, 0.03], spots(x, 20.0, seed + 14, 0.08, footprint))


def leaf_albedo(x: np.ndarray, tint: np.ndarray, seed: int, footprint=None) -> np.ndarray:
    """Green, varied per leaf (tint in [0, 1] from dark bluish to light yellowish), faint veins."""
    base = mix_colours([0.07, 0.25, 0.05], [0.32, 0.52, 0.12], tint)
    detail = fbm(x, 40.0, seed + 21, octaves=2, footprint=footprint)
    return base * (0.7 + 0.6 * detail)[:, None]


def apple_albedo(x, ripeness, centre, seed: int, footprint=None) -> np.ndarray:
    """Red or yellow-green per apple, with streaks (noise stretched along the stalk axis) and dots."""
    local = (x - centre) * np.array([1.0, 1.0, 0.25], np.float32)  # streaks run top to bottom
    streak = fbm(local + centre, 35.0, seed + 31, octaves=2, footprint=footprint)
    red = np.clip(ripeness + 0.8 * (streak - 0.5), 0.0, 1.0)
    albedo = mix_colours([0.62, 0.68, 0.18], [0.70, 0.07, 0.06], red)
    dots = fbm(x, 150.0, seed + 32, octaves=1, footprint=footprint)
    return albedo * (0.8 + 0.4 * dots)[:, None]


# ----------------------------------------------------------------------------- renderer


@dataclass
class Render:
    rgb: np.ndarray  # (H, W, 3) uint8
    label: np.ndarray  # (H, W) uint8
    depth: np.ndarray  # (H, W) float32, z along the camera +z; 0 where the ray hits nothing


@dataclass
class Part:
    """One surface of a scene: its mesh, class value in the label images, and material.

    `albedo(points, primitive_ids, footprint)` gives linear RGB (N, 3) at world hit points, where
    `footprint` is the size of a pixel on the surface (world units). Spheres given by
    `sphere_centres` (sphere k owning triangles [k*T, (k+1)*T), as `tree.spheres` builds them) are
    shaded with their analytic normals instead of facets. `translucency` lights back sides (leaves).
    """

    name: str
    mesh: Mesh
    label: int
    albedo: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
    sphere_centres: np.ndarray | None = None
    sphere_radius: float = 0.0
    translucency: float = 0.0


@dataclass
class Lighting:
    """A sun (or studio key light) with hard shadows, a sky-like ambient term, and what misses show.

    `background(directions)` is the linear RGB of rays that hit nothing; `shadow_bias` (world
    units) starts shadow rays just off the surface so it does not shadow itself.
    """

    sun: np.ndarray
    background: Callable[[np.ndarray], np.ndarray]
    ambient: float = AMBIENT
    sun_strength: float = SUN
    shadow_bias: float = SHADOW_BIAS


def light_direction(rng: np.random.Generator, elevation_range_deg: tuple[float, float]) -> np.ndarray:
    """Unit vector toward a light at any azimuth and an elevation drawn from the range (degrees)."""
    azimuth = rng.uniform(0, 2 * np.pi)
    elevation = np.radians(rng.uniform(*elevation_range_deg))
    horizontal = np.cos(elevation)
    return np.array([horizontal * np.cos(azimuth), horizontal * np.sin(azimuth), np.sin(elevation)])


def sky(directions: np.ndarray) -> np.ndarray:
    """The orchard's sky gradient, horizon to zenith, linear RGB."""
    elevation = np.clip(directions[:, 2], 0.0, 1.0) ** 0.6
    return mix_colours(SKY_HORIZON, SKY_ZENITH, elevation) ** 2.2  # stored linear, encoded later


class Renderer:
    """Holds the raycasting scene of some `Part`s; `render(camera_to_world, intrinsics, w, h)` per view."""

    def __init__(self, parts: list[Part], lighting: Lighting):
        import open3d as o3d

        self.lighting = lighting
        self.sun = np.asarray(lighting.sun, np.float64) / np.linalg.norm(lighting.sun)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.part_of_geometry: dict[int, Part] = {}
        for part in parts:
            if len(part.mesh.triangles) == 0:
                continue
            gid = self.scene.add_triangles(
                o3d.core.Tensor(part.mesh.vertices.astype(np.float32)),
                o3d.core.Tensor(part.mesh.triangles.astype(np.uint32)),
            )
            self.part_of_geometry[gid] = part
        self._o3d = o3d

    def _cast(self, origins: np.ndarray, directions: np.ndarray) -> dict:
        rays = np.concatenate([origins, directions], -1).astype(np.float32)
        result = self.scene.cast_rays(self._o3d.core.Tensor(rays))
        return {k: v.numpy() for k, v in result.items()}

    def _lit(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """1 where the sun is visible from the surface point, else 0."""
        origins = points + self.lighting.shadow_bias * normals
        directions = np.broadcast_to(self.sun.astype(np.float32), origins.shape)
        rays = np.concatenate([origins, directions], -1).astype(np.float32)
        occluded = self.scene.test_occlusions(self._o3d.core.Tensor(rays)).numpy()
        return (~occluded).astype(np.float32)

    def render(self, camera_to_world: np.ndarray, intrinsics: np.ndarray, width: int, height: int,
               distortion=None) -> Render:
        origins, directions = pixel_rays(camera_to_world, intrinsics, width, height, distortion)
        origins = origins.reshape(-1, 3)
        directions = directions.reshape(-1, 3)
        forward = np.asarray(camera_to_world, np.float64)[:3, 2]
        rgb = np.empty((len(origins), 3), np.uint8)
        label = np.empty(len(origins), np.uint8)
        depth = np.empty(len(origins), np.float32)
        # chunks bound the memory of the shading temporaries for large images
        for lo in range(0, len(origins), RAYS_PER_CHUNK):
            sl = slice(lo, lo + RAYS_PER_CHUNK)
            rgb[sl], label[sl], depth[sl] = self._render_rays(origins[sl], directions[sl], forward,
                                                              float(intrinsics[0]))
        shape = (height, width)
        return Render(rgb.reshape(*shape, 3), label.reshape(shape), depth.reshape(shape))

    def _render_rays(self, origins, directions, forward, focal: float):
        """Colour (uint8), class label and z-depth of unit-direction rays from one camera."""
        hit = self._cast(origins, directions)
        t = hit["t_hit"]
        gid = hit["geometry_ids"].astype(np.int64)
        pid = hit["primitive_ids"].astype(np.int64)
        valid = np.isfinite(t)

        label = np.zeros(len(t), np.uint8)
        for g, part in self.part_of_geometry.items():
            label[gid == g] = part.label
        # z-depth: distance along the ray times the cosine to the optical axis
        depth = np.where(valid, t * (directions @ forward), 0.0).astype(np.float32)

        rgb = np.empty((len(t), 3), np.float32)
        rgb[~valid] = self.lighting.background(directions[~valid])
        idx = np.nonzero(valid)[0]
        if len(idx):
            rgb[idx] = self._shade(origins[idx], directions[idx], t[idx], gid[idx], pid[idx],
                                   hit["primitive_normals"][idx], focal)
        encoded = np.clip(rgb, 0.0, 1.0) ** (1.0 / 2.2)
        return (encoded * 255.0 + 0.5).astype(np.uint8), label, depth

    def _shade(self, origins, directions, t, gid, pid, normals, focal: float) -> np.ndarray:
        points = (origins + t[:, None] * directions).astype(np.float32)
        normals = normals.astype(np.float32)
        # pixel size on the surface; grazing views stretch it (geometric mean of the two axes)
        cosine = np.abs(np.sum(normals * directions, -1))
        footprint = (t / focal / np.sqrt(np.maximum(cosine, 0.05))).astype(np.float32)
        albedo = np.zeros_like(points)
        translucent = np.zeros(len(points), np.float32)
        for g, part in self.part_of_geometry.items():
            m = gid == g
            if not m.any():
                continue
            x = points[m]
            albedo[m] = part.albedo(x, pid[m], footprint[m])
            if part.sphere_centres is not None:
                # the analytic sphere normal: smooth shading instead of facets
                centre = part.sphere_centres[pid[m] // len(UNIT_SPHERE.triangles)].astype(np.float32)
                normals[m] = (x - centre) / part.sphere_radius
            if part.translucency:
                translucent[m] = part.translucency
        # two-sided surfaces (leaves): shade the side facing the camera
        flip = np.sum(normals * directions, -1) > 0
        normals[flip] *= -1.0
        lambert = np.clip(normals @ self.sun.astype(np.float32), 0.0, None)
        lit = np.zeros(len(points), np.float32)
        facing = lambert > 0
        if facing.any():
            lit[facing] = self._lit(points[facing], normals[facing])
        light = (self.lighting.ambient * (0.75 + 0.25 * normals[:, 2])
                 + self.lighting.sun_strength * lambert * lit + translucent)
        return albedo * light[:, None]


def orchard_parts(tree: Tree, seed: int) -> list[Part]:
    """The tree's surfaces with the orchard materials; the ground is seen but labelled background."""

    def apple(x, pid, footprint):
        k = pid // tree.triangles_per_apple
        centre = tree.apple_centres[k].astype(np.float32)
        return apple_albedo(x, tree.apple_ripeness[k], centre, seed, footprint)

    return [
        Part("apple", tree.apple, APPLE, apple, tree.apple_centres, tree.apple_radius),
        Part("branch", tree.branch, BRANCH, lambda x, pid, fp: branch_albedo(x, seed, fp)),
        Part("leaf", tree.leaf, LEAF, lambda x, pid, fp: leaf_albedo(x, tree.leaf_tint[pid // 2], seed, fp),
             translucency=0.12),
        Part("ground", tree.ground, BACKGROUND, lambda x, pid, fp: ground_albedo(x, seed, fp)),
    ]


class OrchardRenderer(Renderer):
    """The renderer of one procedural apple tree under a sun and a sky."""

    def __init__(self, tree: Tree, seed: int, sun_direction: np.ndarray):
        self.tree = tree
        self.seed = seed
        super().__init__(orchard_parts(tree, seed), Lighting(np.asarray(sun_direction, np.float64), sky))
