"""CPU ray-cast renderer for the procedural orchard (open3d `RaycastingScene`).

Per pixel: one primary ray (class label, z-depth, colour), then one shadow ray toward the sun
from every hit. Colour = albedo * (sky ambient + sun * max(0, n.l) * lit), gamma-encoded; misses
get a sky gradient. Every albedo is modulated by 3D value noise of the world hit position, so
the texture is fixed to the surface (multi-view consistent) and rich enough for SIFT matching.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from srfpipe.cameras import pixel_rays
from srfpipe.scenes.tree import Tree

# class values in the label images (paper order); the ground is background
BACKGROUND, APPLE, BRANCH, LEAF = 0, 1, 2, 3
MESH_CLASSES = {"apple": APPLE, "branch": BRANCH, "leaf": LEAF, "ground": BACKGROUND}

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


def _mix(a, b, t):
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
    grass = _mix([0.20, 0.36, 0.10], [0.36, 0.46, 0.16], fbm(x, 3.0, seed + 2))
    soil = _mix([0.30, 0.22, 0.14], [0.48, 0.38, 0.26], fbm(x, 4.0, seed + 3))
    albedo = _mix(grass, soil, patches)
    detail = fbm(x, 10.0, seed + 4, octaves=4, footprint=footprint)
    albedo = albedo * (0.4 + 1.2 * detail)[:, None]
    # blobs at several scales, so every distance from the cameras has features SIFT can match
    for k, (frequency, colour) in enumerate(GROUND_SPOTS):
        albedo = _mix(albedo, colour, spots(x, frequency, seed + 5 + k, 0.05, footprint))
    return albedo


def branch_albedo(x: np.ndarray, seed: int, footprint=None) -> np.ndarray:
    """Grey-brown bark with fine, high-contrast cracks, pale lichen and dark knots."""
    base = _mix([0.22, 0.15, 0.09], [0.42, 0.33, 0.24], fbm(x, 6.0, seed + 11, octaves=2))
    detail = fbm(x, 25.0, seed + 12, octaves=3, footprint=footprint)
    albedo = base * (0.4 + 1.2 * detail)[:, None]
    albedo = _mix(albedo, [0.62, 0.66, 0.52], spots(x, 14.0, seed + 13, 0.12, footprint))
    return _mix(albedo, [0.06, 0.04, 0.03], spots(x, 20.0, seed + 14, 0.08, footprint))


def leaf_albedo(x: np.ndarray, tint: np.ndarray, seed: int, footprint=None) -> np.ndarray:
    """Green, varied per leaf (tint in [0, 1] from dark bluish to light yellowish), faint veins."""
    base = _mix([0.07, 0.25, 0.05], [0.32, 0.52, 0.12], tint)
    detail = fbm(x, 40.0, seed + 21, octaves=2, footprint=footprint)
    return base * (0.7 + 0.6 * detail)[:, None]


def apple_albedo(x, ripeness, centre, seed: int, footprint=None) -> np.ndarray:
    """Red or yellow-green per apple, with streaks (noise stretched along the stalk axis) and dots."""
    local = (x - centre) * np.array([1.0, 1.0, 0.25], np.float32)  # streaks run top to bottom
    streak = fbm(local + centre, 35.0, seed + 31, octaves=2, footprint=footprint)
    red = np.clip(ripeness + 0.8 * (streak - 0.5), 0.0, 1.0)
    albedo = _mix([0.62, 0.68, 0.18], [0.70, 0.07, 0.06], red)
    dots = fbm(x, 150.0, seed + 32, octaves=1, footprint=footprint)
    return albedo * (0.8 + 0.4 * dots)[:, None]


# ----------------------------------------------------------------------------- renderer


@dataclass
class Render:
    rgb: np.ndarray  # (H, W, 3) uint8
    label: np.ndarray  # (H, W) uint8
    depth: np.ndarray  # (H, W) float32, z along the camera +z; 0 where the ray hits nothing


class OrchardRenderer:
    """Holds the raycasting scene of one tree; `render(camera_to_world, intrinsics, w, h)` per view."""

    def __init__(self, tree: Tree, seed: int, sun_direction: np.ndarray):
        import open3d as o3d

        self.tree = tree
        self.seed = seed
        self.sun = np.asarray(sun_direction, np.float64) / np.linalg.norm(sun_direction)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.class_of_geometry = {}
        self.name_of_geometry = {}
        for name in ("apple", "branch", "leaf", "ground"):
            mesh = getattr(tree, name)
            if len(mesh.triangles) == 0:
                continue
            gid = self.scene.add_triangles(
                o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                o3d.core.Tensor(mesh.triangles.astype(np.uint32)),
            )
            self.class_of_geometry[gid] = MESH_CLASSES[name]
            self.name_of_geometry[gid] = name
        self._o3d = o3d

    def _cast(self, origins: np.ndarray, directions: np.ndarray) -> dict:
        rays = np.concatenate([origins, directions], -1).astype(np.float32)
        result = self.scene.cast_rays(self._o3d.core.Tensor(rays))
        return {k: v.numpy() for k, v in result.items()}

    def _lit(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """1 where the sun is visible from the surface point, else 0."""
        origins = points + SHADOW_BIAS * normals
        directions = np.broadcast_to(self.sun.astype(np.float32), origins.shape)
        rays = np.concatenate([origins, directions], -1).astype(np.float32)
        occluded = self.scene.test_occlusions(self._o3d.core.Tensor(rays)).numpy()
        return (~occluded).astype(np.float32)

    def render(self, camera_to_world: np.ndarray, intrinsics: np.ndarray, width: int, height: int) -> Render:
        origins, directions = pixel_rays(camera_to_world, intrinsics, width, height)
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
        for g, cls in self.class_of_geometry.items():
            label[gid == g] = cls
        # z-depth: distance along the ray times the cosine to the optical axis
        depth = np.where(valid, t * (directions @ forward), 0.0).astype(np.float32)

        rgb = np.empty((len(t), 3), np.float32)
        rgb[~valid] = self._sky(directions[~valid])
        idx = np.nonzero(valid)[0]
        if len(idx):
            rgb[idx] = self._shade(origins[idx], directions[idx], t[idx], gid[idx], pid[idx],
                                   hit["primitive_normals"][idx], focal)
        encoded = np.clip(rgb, 0.0, 1.0) ** (1.0 / 2.2)
        return (encoded * 255.0 + 0.5).astype(np.uint8), label, depth

    def _sky(self, directions: np.ndarray) -> np.ndarray:
        elevation = np.clip(directions[:, 2], 0.0, 1.0) ** 0.6
        return _mix(SKY_HORIZON, SKY_ZENITH, elevation) ** 2.2  # stored linear, encoded later

    def _shade(self, origins, directions, t, gid, pid, normals, focal: float) -> np.ndarray:
        points = (origins + t[:, None] * directions).astype(np.float32)
        normals = normals.astype(np.float32)
        # pixel size on the surface; grazing views stretch it (geometric mean of the two axes)
        cosine = np.abs(np.sum(normals * directions, -1))
        footprint = (t / focal / np.sqrt(np.maximum(cosine, 0.05))).astype(np.float32)
        albedo = np.zeros_like(points)
        tree = self.tree
        for g, name in self.name_of_geometry.items():
            m = gid == g
            if not m.any():
                continue
            x = points[m]
            if name == "ground":
                albedo[m] = ground_albedo(x, self.seed, footprint[m])
            elif name == "branch":
                albedo[m] = branch_albedo(x, self.seed, footprint[m])
            elif name == "leaf":
                albedo[m] = leaf_albedo(x, tree.leaf_tint[pid[m] // 2], self.seed, footprint[m])
            elif name == "apple":
                k = pid[m] // tree.triangles_per_apple
                centre = tree.apple_centres[k].astype(np.float32)
                albedo[m] = apple_albedo(x, tree.apple_ripeness[k], centre, self.seed, footprint[m])
                # the analytic sphere normal: smooth shading instead of facets
                normals[m] = (x - centre) / tree.apple_radius
        # two-sided surfaces (leaves): shade the side facing the camera
        flip = np.sum(normals * directions, -1) > 0
        normals[flip] *= -1.0
        lambert = np.clip(normals @ self.sun.astype(np.float32), 0.0, None)
        lit = np.zeros(len(points), np.float32)
        facing = lambert > 0
        if facing.any():
            lit[facing] = self._lit(points[facing], normals[facing])
        # leaves let some light through, so their back sides are not black
        translucent = np.zeros(len(points), np.float32)
        for g, name in self.name_of_geometry.items():
            if name == "leaf":
                translucent[gid == g] = 0.12
        light = AMBIENT * (0.75 + 0.25 * normals[:, 2]) + SUN * lambert * lit + translucent
        return albedo * light[:, None]
