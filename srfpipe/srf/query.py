"""The paper's query interface (Sec. 2.4) on a trained srf.zarr, in world units, numpy in and out.

    srf = SemanticRadianceField.load("results/orchard/srf.zarr")       # CPU or CUDA ("auto")
    out = srf.render(camera_to_world, intrinsics, width, height)       # Render(P)
    p = srf.semantic(points_world)                                     # Semantic(x): (M, C) in [0, 1]
    sigma = srf.density(points_world)                                  # Occupancy(x): (M,) per world unit
    rgb = srf.radiance(points_world, directions_world)                 # c(x, d): (M, 3) emitted colour

Poses use the project convention (OpenCV camera frame, camera_to_world, see srfpipe.cameras).
Work is batched internally; NaN or infinite inputs raise ValueError.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


FAR_RADIUS = 1e9  # world units; see SemanticRadianceField._to_scene


def render_bytes_per_ray(classes: int) -> int:
    """Host memory a rendered ray holds: its origin and direction (float32, a device copy too), its
    outputs (rgb, logits, depth, accumulation, four sample counts) per chunk and concatenated."""
    return 2 * 24 + 2 * 4 * (3 + classes + 6)


def _points(points_world, name: str = "points_world") -> np.ndarray:
    points = np.asarray(points_world, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{name} must have shape (M, 3), got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{name} contains NaN or infinite coordinates")
    return points


class SemanticRadianceField:
    """A trained SRF: Render, Semantic and Occupancy (density) queries in world coordinates."""

    def __init__(self, model, attrs: dict, device, path: Path | None = None):
        self.model = model
        self.attrs = attrs
        self.device = device
        self.path = path
        self.classes: list[str] = [str(c) for c in attrs["classes"]]
        self.scene_from_world = np.asarray(attrs["scene_from_world"], dtype=np.float64)
        self.world_from_scene = np.asarray(attrs["world_from_scene"], dtype=np.float64)
        self.bounds_world = np.asarray(attrs["bounds_world"], dtype=np.float64)
        # where the classes are (older srf.zarr: the model's box); the occupancy cache covers it
        self.semantic_bounds_world = np.asarray(attrs.get("semantic_bounds_world") or attrs["bounds_world"],
                                                dtype=np.float64)
        self.scale = float(attrs["scene_scale"])  # scene units per world unit
        self.batch_size = 1 << 17

    @classmethod
    def load(cls, path, device="auto") -> "SemanticRadianceField":
        """Load srf.zarr onto `device` ("auto" = CUDA when available, else CPU)."""
        from srfpipe.device import choose_device
        from srfpipe.srf.io import read_srf

        device = choose_device(device)
        model, attrs = read_srf(path, device)
        return cls(model, attrs, device, Path(path))

    # ------------------------------------------------------------------ helpers

    def _to_scene(self, points_world: np.ndarray):
        import torch

        # Huge (finite) points would overflow float32 and poison the grid lookup: pull them in
        # along their direction to a radius where the contraction has saturated (2 - 1/r rounds
        # to 2 in float32), which gives the same answer.
        far = np.max(np.abs(points_world), axis=1) if len(points_world) else np.zeros(0)
        if np.any(far > FAR_RADIUS):
            points_world = points_world.copy()
            rows = far > FAR_RADIUS
            points_world[rows] = points_world[rows] / far[rows, None] * FAR_RADIUS
        p = points_world @ self.scene_from_world[:3, :3].T + self.scene_from_world[:3, 3]
        return torch.as_tensor(p, dtype=torch.float32, device=self.device)

    @property
    def camera_adjustment(self):
        """The (N, 6) pose corrections of train.camera_refinement, or None (srf.zarr cameras/adjustment)."""
        if not hasattr(self, "_camera_adjustment"):
            from srfpipe.srf.io import read_camera_adjustment

            self._camera_adjustment = None if self.path is None else read_camera_adjustment(self.path)
        return self._camera_adjustment

    def training_pose(self, index: int, camera_to_world) -> np.ndarray:
        """Training image `index`'s pose as the field learned it: `camera_to_world` with the
        correction of train.camera_refinement (unchanged without one)."""
        from srfpipe.srf.camera_refinement import refined_world_pose

        adjustment = self.camera_adjustment
        if adjustment is None:
            return np.asarray(camera_to_world, dtype=np.float64)
        return refined_world_pose(camera_to_world, adjustment[int(index)], self.scale)

    # ------------------------------------------------------------------ queries

    @property
    def has_appearance(self) -> bool:
        """Whether the field learned a per-image appearance embedding (a new view borrows the
        nearest training image's)."""
        return self.model.field.appearance is not None

    def render(self, camera_to_world, intrinsics, width: int, height: int, supersample: int = 1,
               exclude_view: int | None = None, appearance_view: int | None = None) -> dict:
        """Render(P): rgb (H, W, 3) float32 in [0, 1], semantic (H, W, C) probabilities,
        depth (H, W) distance along each ray in world units, accumulation (H, W) opacity.

        `supersample` s > 1: each pixel is the mean of s x s rays over its footprint, as a camera's
        pixel (and a downscaled image's, an area average) integrates the light over its area: thin
        structures a pixel wide then come out as the partial coverage they have in the image.
        `exclude_view`: a training image whose appearance embedding may not be borrowed (a training
        view rendered with the appearance a new view at its pose would get); `appearance_view`: a
        training image whose own appearance the view takes (that image's view as it trained)."""
        import torch

        from srfpipe.cameras import check_view, transform_poses
        from srfpipe.memory import check_allocation
        from srfpipe.srf.data import image_rays

        pose, k, width, height = check_view(camera_to_world, intrinsics, width, height)
        supersample = int(supersample)
        if supersample < 1:
            raise ValueError(f"supersample must be a positive integer, got {supersample}")
        rays = width * height * supersample**2
        check_allocation(rays * render_bytes_per_ray(len(self.classes)), "the image size",
                         f"rendering {width} x {height} pixels of {supersample**2} rays each")
        pose_scene = torch.as_tensor(transform_poses(self.scene_from_world, pose), dtype=torch.float32)
        origins, directions = image_rays(pose_scene, torch.as_tensor(k, dtype=torch.float32), width, height,
                                         supersample)
        if not bool(torch.isfinite(directions).all()):
            raise ValueError(f"intrinsics {k.tolist()} give non-finite ray directions (a focal length too small)")
        out = self.model.render_rays_chunked(origins.to(self.device), directions.to(self.device), 8192, exclude_view,
                                              appearance_view)

        def per_pixel(values, *channels):  # the mean over a pixel's supersample rays
            return values.numpy().reshape(height, width, supersample**2, *channels).mean(2).astype(np.float32)

        return {
            "rgb": per_pixel(out["rgb"].clamp(0, 1), 3),
            "semantic": per_pixel(out["logits"].sigmoid(), len(self.classes)),
            "depth": per_pixel(out["depth"] / self.scale),
            "accumulation": per_pixel(out["accumulation"]),
            # per pixel: samples with weight > 0.03, and those of them off the surface (floaters)
            "significant_samples": per_pixel(out["significant"]),
            "floater_samples": per_pixel(out["floaters"]),
            # per pixel: intervals the sampler placed, and those left after skipping empty space
            "candidate_samples": per_pixel(out["candidate_samples"]),
            "kept_samples": per_pixel(out["kept_samples"]),
        }

    def semantic(self, points_world: np.ndarray) -> np.ndarray:
        """Semantic(x): per-class probabilities sigmoid(s(x)) (M, C) float32."""
        import torch

        points = _points(points_world)
        out = np.empty((points.shape[0], len(self.classes)), dtype=np.float32)
        with torch.no_grad():
            for start in range(0, points.shape[0], self.batch_size):
                x = self._to_scene(points[start:start + self.batch_size])
                _, h = self.model.field.density(x)
                out[start:start + len(x)] = self.model.field.semantics(h, x).float().sigmoid().cpu().numpy()
        return out

    def density(self, points_world: np.ndarray) -> np.ndarray:
        """Occupancy(x): sigma (M,) float32 per *world* unit length (scene sigma times the scene
        scale), 0 outside the scene bounds and where no training camera saw (`empty_unseen`)."""
        import torch

        points = _points(points_world)
        out = np.empty(points.shape[0], dtype=np.float32)
        with torch.no_grad():
            for start in range(0, points.shape[0], self.batch_size):
                x = self._to_scene(points[start:start + self.batch_size])
                sigma, _ = self.model.field.density(x)
                sigma = sigma.float() * self.model.occupancy.seen(x)
                out[start:start + len(x)] = sigma.cpu().numpy() * self.scale
        inside = np.all((points >= self.bounds_world[0]) & (points <= self.bounds_world[1]), axis=1)
        out[~inside] = 0.0
        return out

    def _directions_to_scene(self, directions_world) -> "torch.Tensor":
        import torch

        d = np.asarray(directions_world, dtype=np.float64)
        if d.ndim != 2 or d.shape[1] != 3 or not np.all(np.isfinite(d)):
            raise ValueError(f"directions_world must be finite with shape (M, 3), got {d.shape}")
        d = d @ self.scene_from_world[:3, :3].T
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        if np.any(norm == 0):
            raise ValueError("directions must be non-zero")
        return torch.as_tensor(d / norm, dtype=torch.float32, device=self.device)

    def radiance(self, points_world: np.ndarray, directions_world: np.ndarray) -> np.ndarray:
        """c(x, d): the colour (M, 3) in [0, 1] emitted at world points toward the viewer looking
        along `directions_world` (with the mean appearance embedding, like a novel view)."""
        import torch

        points = _points(points_world)
        directions = self._directions_to_scene(directions_world)
        if len(directions) != len(points):
            raise ValueError(f"{len(points)} points but {len(directions)} directions")
        out = np.empty((points.shape[0], 3), dtype=np.float32)
        with torch.no_grad():
            for start in range(0, points.shape[0], self.batch_size):
                x = self._to_scene(points[start:start + self.batch_size])
                h = self.model.field.latent(x)
                colour = self.model.field.image_colour(self.model.field.color(h, directions[start:start + len(x)]), None)
                out[start:start + len(x)] = colour.float().cpu().numpy()
        return out

    def background(self, directions_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What a ray leaving the field sees: colour (M, 3) along world directions (sky) and the
        per-class background probabilities (C,)."""
        import torch

        directions = self._directions_to_scene(directions_world)
        with torch.no_grad():
            rgb = self.model.field.background(directions).float().cpu().numpy()
            prob = self.model.field.background_logits.float().sigmoid().cpu().numpy()
        return rgb, prob
