"""Where the field's grid lies: a box in the scene frame (the default), or a frustum in the
cameras' perspective for captures whose cameras all look one way (`train.grid_frame: perspective`).

A box grid in front of forward-facing cameras cuts the nearest leaves as coarsely as the box's far
end: on LLFF's fern, with the grid at its 192-cell cap, a cell spans 3.9 pixels at the near bound and
1.1 at the far end. The perspective grid is uniform in

    w = (p_x / p_z, p_y / p_z, ln p_z),     p = R (x - o)

with o the cameras' mean centre and R's third row their mean viewing axis (OpenCV axes). A cell is
then z * dw wide across and z * d(ln z) deep: a fixed number of pixels at every depth, and the same
shape near and far (NeRF's NDC keeps the first property; the log depth keeps the second, so the
space between the cameras and the subject costs cells in proportion to its depth ratio, not to its
disparity). Samples along a ray step uniformly in ln t (`sampling.generate_intervals`).

The grid's region is a truncated pyramid; `box_min`/`box_max` stay the scene-frame box around it
(what the sampler clips rays to), and points of that box outside the pyramid belong to the
contracted shell, as points outside the box do with the box grid.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn as nn

from srfpipe import cameras

# the grid covers the part of the box that at least this share of the training cameras sees: on
# the fern, a quarter gave a pyramid 1.82 wide in tangent (the cameras' baseline seen from the box's
# near end), so 1.94 pixels a cell at the 192-cell cap; a half gives 1.27 and 1.35 pixels
MIN_VIEWS = 0.5
# the fewest of the box's lattice points, seen so, that a perspective grid is laid out over
MIN_SEEN_POINTS = 8
# the cameras' unit viewing directions must average to at least this length (1: all parallel; a
# 90-degree fan gives 0.90, the fern's 0.99, a ring 0): every point the grid holds lies in front of them
MIN_AXIS_AGREEMENT = 0.7
# depth of the nearest point a perspective warp resolves, as a fraction of the grid's near depth:
# nearer points (and points behind the cameras) all map to this depth, deep in the contracted shell
MIN_DEPTH_FRACTION = 0.25
# the warped coordinates of a point far outside the grid are clamped here, so that mapping the
# contracted shell's outermost cells back to the scene stays finite in float32
MAX_TANGENT = 1.0e4
MAX_LOG_DEPTH_SPAN = 40.0


class PerspectiveWarp(nn.Module):
    """x (scene frame) <-> w = (p_x / p_z, p_y / p_z, ln p_z), p = R (x - o)."""

    def __init__(self, origin, rotation, min_depth: float, max_depth: float):
        super().__init__()
        # from the model config, not the weights
        self.register_buffer("origin", torch.as_tensor(origin, dtype=torch.float32).reshape(3).clone(),
                             persistent=False)
        self.register_buffer("rotation", torch.as_tensor(rotation, dtype=torch.float32).reshape(3, 3).clone(),
                             persistent=False)
        self.min_depth = float(min_depth)
        self.max_log_depth = math.log(float(max_depth)) + MAX_LOG_DEPTH_SPAN

    @classmethod
    def from_config(cls, config: dict) -> "PerspectiveWarp":
        return cls(config["origin"], config["rotation"], config["min_depth"], config["max_depth"])

    def depth(self, x: torch.Tensor) -> torch.Tensor:
        """p_z (M,): depth along the cameras' mean axis, at least min_depth."""
        return ((x.float() - self.origin) @ self.rotation[2]).clamp_min(self.min_depth)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p = (x.float() - self.origin) @ self.rotation.T
        z = p[:, 2:].clamp_min(self.min_depth)
        return torch.cat([p[:, :2] / z, torch.log(z)], dim=-1)

    def inverse(self, w: torch.Tensor) -> torch.Tensor:
        z = torch.exp(w[:, 2:].clamp(max=self.max_log_depth))
        p = torch.cat([w[:, :2].clamp(-MAX_TANGENT, MAX_TANGENT) * z, z], dim=-1)
        return p @ self.rotation + self.origin


def build_warp(config: dict | None) -> PerspectiveWarp | None:
    """The warp a model config names (None: the box grid)."""
    if not config:
        return None
    if config.get("type") != "perspective":
        raise ValueError(f"unknown grid warp {config.get('type')!r} (this srfpipe knows perspective)")
    return PerspectiveWarp.from_config(config)


def looks_one_way(poses_scene: np.ndarray) -> bool:
    """Whether the cameras (camera_to_scene (N, 4, 4)) all look one way, as a forward-facing capture's
    do: their viewing directions average to at least MIN_AXIS_AGREEMENT, and they do not stand round
    the point where their axes meet (`cameras.cameras_surround`). Parallel axes meet nowhere: such
    cameras look one way (`focus_point`'s stand-in point, as far ahead as they are spread, would put
    a symmetric rig's corners exactly 90 degrees apart). `train.grid_frame: auto` lays a
    perspective grid out for such cameras, a box grid for any other."""
    poses = np.asarray(poses_scene, dtype=np.float64)
    if float(np.linalg.norm(poses[:, :3, 2].mean(axis=0))) < MIN_AXIS_AGREEMENT:
        return False
    meeting = cameras.axes_meeting_point(poses)
    return meeting is None or not cameras.cameras_surround(poses, meeting)


def cameras_frame(poses_scene: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(origin (3,), rotation (3, 3)): the cameras' mean centre, and rows right, down, forward from
    their mean axes (OpenCV camera frames, camera_to_scene (N, 4, 4))."""
    poses = np.asarray(poses_scene, dtype=np.float64)
    forward = poses[:, :3, 2].mean(axis=0)
    agreement = float(np.linalg.norm(forward))
    if agreement < MIN_AXIS_AGREEMENT:
        raise ValueError("train.grid_frame perspective lays a grid out in the view of cameras that all look one way "
                         f"(a forward-facing capture); these cameras' viewing directions average to {agreement:.2f} "
                         "(1 when parallel): they stand round what they look at: use grid_frame: box")
    forward /= agreement
    right = poses[:, :3, 0].mean(axis=0)
    right -= (right @ forward) * forward
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return poses[:, :3, 3].mean(axis=0), np.stack([right, down, forward])


def seen_box_points(poses_scene, intrinsics, width: int, height: int, box_min, box_max,
                    min_views: float = MIN_VIEWS, samples: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """(points (M, 3), depths (M,)): the points of a `samples`^3 lattice over the box (scene frame)
    that at least `min_views` of the cameras see, in front of them, and their depths along the
    cameras' mean axis (`cameras_frame`): the part of the box a perspective grid covers."""
    poses = np.asarray(poses_scene, dtype=np.float64)
    k = np.asarray(intrinsics, dtype=np.float64)
    lo, hi = np.asarray(box_min, np.float64), np.asarray(box_max, np.float64)
    ticks = [np.linspace(a, b, samples) for a, b in zip(lo, hi)]
    points = np.stack(np.meshgrid(*ticks, indexing="ij"), -1).reshape(-1, 3)
    seen = sum(cameras.in_view(points, pose, k_i, width, height).astype(np.int64) for pose, k_i in zip(poses, k))
    origin, rotation = cameras_frame(poses)
    kept = points[seen >= max(min_views * len(poses), 1.0)]
    depth = (kept - origin) @ rotation[2]
    return kept[depth > 0], depth[depth > 0]


def perspective_fits(poses_scene, intrinsics, width: int, height: int, box_min, box_max) -> bool:
    """Whether a perspective grid can be laid out over the box: enough of it lies where the cameras
    look (`seen_box_points`). A box the views barely reach (bounds given in config beside the
    views) cannot hold one; `grid_frame: auto` then keeps the box grid."""
    return seen_box_points(poses_scene, intrinsics, width, height, box_min, box_max)[0].shape[0] >= MIN_SEEN_POINTS


def perspective_grid(poses_scene, intrinsics, width: int, height: int, box_min, box_max, cells: int,
                     cap: int, min_views: float = MIN_VIEWS, samples: int = 48) -> dict:
    """The perspective grid over the part of the box (scene frame) that at least `min_views` of the
    cameras see: its warp, its range in w, its points per axis, and the scene-frame box around it.

    Across, a cell spans one pixel at the cameras' median focal length, up to `cells` points on the
    wider axis; in depth it is as deep as it is wide (ln z steps of the same size), up to `cells`.
    Points seen by fewer cameras (the sides that only the outermost views reach) fall to the shell."""
    k = np.asarray(intrinsics, dtype=np.float64)
    kept, depth = seen_box_points(poses_scene, k, width, height, box_min, box_max, min_views, samples)
    if kept.shape[0] < MIN_SEEN_POINTS:
        raise ValueError(f"train.grid_frame perspective: fewer than {MIN_SEEN_POINTS} points of the scene box lie in "
                         f"front of the cameras in at least {min_views:.0%} of the views; use grid_frame: box")
    origin, rotation = cameras_frame(poses_scene)
    near, far = float(depth.min()), float(depth.max())
    warp = PerspectiveWarp(origin, rotation, MIN_DEPTH_FRACTION * near, far)
    w = warp(torch.from_numpy(kept).float()).double()
    w_min, w_max = w.min(0).values.numpy(), w.max(0).values.numpy()
    focal = float(torch.as_tensor(k[:, :2]).median())
    across = w_max[:2] - w_min[:2]
    # one pixel a cell across, at most `cells` points on the wider axis (and `cap` on any)
    cell = max(1.0 / focal, float(across.max()) / (min(cells, cap) - 1))
    counts = [int(min(max(math.ceil(e / cell - 1e-6) + 1, 2), cap)) for e in across]
    depth_span = float(w_max[2] - w_min[2])
    counts.append(int(min(max(math.ceil(depth_span / cell - 1e-6) + 1, 2), min(cells, cap))))
    log_step = depth_span / (counts[2] - 1)
    # the pyramid's corners bound it in the scene frame (it is convex)
    corners = torch.tensor(np.array(np.meshgrid(*np.stack([w_min, w_max]).T)).reshape(3, -1).T, dtype=torch.float32)
    corners_scene = warp.inverse(corners).double().numpy()
    median_depth = math.exp(float(np.median(w[:, 2].numpy())))
    return {
        "warp": {"type": "perspective", "origin": origin.tolist(), "rotation": rotation.tolist(),
                 "min_depth": warp.min_depth, "max_depth": far},
        "grid_min": w_min.tolist(), "grid_max": w_max.tolist(), "resolution": counts,
        "box_min": corners_scene.min(0), "box_max": corners_scene.max(0),
        "cell_across": cell, "log_step": log_step, "median_depth": median_depth,
        "pixels_per_cell": cell * focal,
    }
