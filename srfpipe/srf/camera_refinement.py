"""Camera poses refined while training (`train.camera_refinement`): Nerfacto's SO3xR3 camera optimizer.

Each image i gets a correction delta_i = (t_i, w_i) in its own camera frame, zero at the start:

    P_i' = P_i [exp(w_i) | t_i]        (camera_to_scene, right-multiplied)

so a ray of image i keeps its pixel and turns with the camera: d' = R_i exp(w_i) R_i^T d and
o' = o + R_i t_i. A pose that COLMAP got slightly wrong blurs every view that disagrees with it,
and a field fits the disagreement with floaters that only the training views need; the corrections
take up what is the camera's. An L2 penalty on their size (Nerfacto's weights) is meant to keep them
to what the images ask for. Held-out views are rendered from their given poses, so a refined frame
that drifts off them costs held-out quality: on the bottle, corrections of 0.25 deg median cost 1.7 dB
(docs/benchmarks.md, captures), which is why the option is off by default.

The drift is a gauge freedom: moving, turning or scaling every training camera together (with the
field) changes no training ray's colour, so nothing but the penalty holds it. The corrections the rays
see are therefore the learned ones less their component along the 7 similarity motions of the training
cameras as a whole (`gauge_basis`): an orthogonal projection, fixed by the given poses, so the refined
cameras keep the given frame, in which the held-out views are rendered, on average.
"""

from __future__ import annotations

import torch
from torch import nn

# Nerfacto's camera optimizer (nerfstudio CameraOptimizerConfig, SO3xR3): Adam at 6e-4
# (train.camera_lr), decayed with the field's schedule, and these penalties on the mean size of the corrections
TRANSLATION_PENALTY = 1e-2  # per scene unit
ROTATION_PENALTY = 1e-3  # per radian
# below this angle exp(w) uses its Taylor series: sin(x)/x and (1 - cos x)/x^2 lose their digits
SMALL_ANGLE = 1e-4


def skew(w: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) cross-product matrices [w]_x."""
    x, y, z = w.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(w.shape[:-1] + (3, 3))


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula: (..., 3) axis-angle vectors -> (..., 3, 3) rotations, finite with finite
    gradients at w = 0 (the corrections' start)."""
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]
    small = theta2 < SMALL_ANGLE**2
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe2)
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe2)
    k = skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(k.shape)
    return eye + a * k + b * (k @ k)


def adjusted_poses(poses: torch.Tensor, adjustment: torch.Tensor) -> torch.Tensor:
    """(N, 4, 4) camera_to_scene poses with (N, 6) corrections (t, w) applied: P [exp(w) | t]."""
    out = poses.clone()
    rotation = poses[:, :3, :3]
    out[:, :3, :3] = rotation @ so3_exp(adjustment[:, 3:].to(poses.dtype))
    out[:, :3, 3] = poses[:, :3, 3] + torch.einsum("nij,nj->ni", rotation, adjustment[:, :3].to(poses.dtype))
    return out


def refined_world_pose(camera_to_world, adjustment, scene_scale: float):
    """A (4, 4) camera_to_world pose (numpy) with its (6,) correction applied; the correction's
    translation is in scene units (`scene_scale` of them per world unit)."""
    import numpy as np

    adjustment = torch.as_tensor(np.asarray(adjustment, dtype=np.float64))
    correction = np.eye(4)
    correction[:3, :3] = so3_exp(adjustment[3:]).numpy()
    correction[:3, 3] = adjustment[:3].numpy() / scene_scale
    return np.asarray(camera_to_world, dtype=np.float64) @ correction


def gauge_basis(poses: torch.Tensor, views) -> torch.Tensor:
    """(N * 6, 7): the corrections (t, w) of each image (rows in image order, zero outside `views`) that
    move the cameras `views` together by a similarity: a shift along each scene axis, a turn about
    each axis through the cameras' centroid, and a scaling about it. For camera i (rotation R_i,
    centre C_i, r_i = C_i - centroid), a world turn omega gives w_i = R_i^T omega, t_i = R_i^T (omega x r_i),
    a shift tau gives t_i = R_i^T tau, a scaling s gives t_i = s R_i^T r_i (to first order)."""
    poses = poses.double()
    rotation_t = poses[:, :3, :3].transpose(1, 2)  # R_i^T
    views = torch.as_tensor(views, dtype=torch.long)
    offsets = poses[:, :3, 3] - poses[views, :3, 3].mean(0)
    basis = torch.zeros(poses.shape[0], 6, 7, dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64)
    for k in range(3):
        basis[:, :3, k] = rotation_t @ eye[k]
        basis[:, 3:, 3 + k] = rotation_t @ eye[k]
        basis[:, :3, 3 + k] = torch.einsum("nij,nj->ni", rotation_t, torch.linalg.cross(eye[k].expand_as(offsets), offsets))
    basis[:, :3, 6] = torch.einsum("nij,nj->ni", rotation_t, offsets)
    outside = torch.ones(poses.shape[0], dtype=torch.bool)
    outside[views] = False
    basis[outside] = 0.0
    return basis.reshape(-1, 7)


class CameraRefinement(nn.Module):
    """The per-image corrections of one training run, applied to the rays of a batch. With
    `train_views`, the corrections of those views are kept free of a motion of them all (see
    `gauge_basis`); without, they are used as learned."""

    def __init__(self, poses_scene: torch.Tensor, train_views=None):
        super().__init__()
        self.register_buffer("rotation", poses_scene[:, :3, :3].float().clone(), persistent=False)
        self.adjustment = nn.Parameter(torch.zeros(poses_scene.shape[0], 6, device=poses_scene.device))
        self.anchored = train_views is not None and len(train_views) >= 3
        if self.anchored:
            basis = gauge_basis(poses_scene.detach().cpu(), train_views)
            # the projection's two factors: corrections - basis @ (pseudo-inverse @ corrections). The
            # pseudo-inverse is exactly zero on the other views' entries: a rounding-sized gradient
            # there would become a full step under Adam, which normalises gradients
            rows = basis.abs().sum(1) > 0
            solve = torch.zeros(7, basis.shape[0], dtype=basis.dtype)
            solve[:, rows] = torch.linalg.pinv(basis[rows])
            self.register_buffer("_basis", basis.float().to(poses_scene.device), persistent=False)
            self.register_buffer("_solve", solve.float().to(poses_scene.device), persistent=False)

    def corrections(self) -> torch.Tensor:
        """(N, 6) corrections (t, w) the rays see: the learned ones less their common similarity motion."""
        if not self.anchored:
            return self.adjustment
        flat = self.adjustment.reshape(-1)
        return (flat - self._basis @ (self._solve @ flat)).reshape(self.adjustment.shape)

    def forward(self, image: torch.Tensor, origins: torch.Tensor, directions: torch.Tensor):
        """The rays (origins, unit directions) of pixels of images `image`, through the refined cameras."""
        delta = self.corrections()[image]
        rotation = self.rotation[image]
        turn = rotation @ so3_exp(delta[:, 3:]) @ rotation.transpose(1, 2)
        directions = torch.einsum("rij,rj->ri", turn, directions)
        origins = origins + torch.einsum("rij,rj->ri", rotation, delta[:, :3])
        return origins, directions

    def penalty(self) -> torch.Tensor:
        """Nerfacto's regulariser: the mean translation and rotation of the corrections, weighted.
        The norms are smoothed at zero, where a plain norm's gradient is undefined."""
        tiny = torch.finfo(self.adjustment.dtype).tiny
        translation = torch.sqrt((self.adjustment[:, :3] ** 2).sum(-1) + tiny).mean()
        rotation = torch.sqrt((self.adjustment[:, 3:] ** 2).sum(-1) + tiny).mean()
        return TRANSLATION_PENALTY * translation + ROTATION_PENALTY * rotation

    def summary(self, images, scene_scale: float) -> dict:
        """The size of the corrections of `images`: median and largest rotation (degrees) and
        translation (world units), for the log and srf.zarr."""
        import math

        with torch.no_grad():
            delta = self.corrections()[torch.as_tensor(images, device=self.adjustment.device)].double().cpu()
            degrees = delta[:, 3:].norm(dim=-1) * 180.0 / math.pi
            world = delta[:, :3].norm(dim=-1) / scene_scale
        return {"images": int(delta.shape[0]),
                "rotation_deg_median": float(degrees.median()), "rotation_deg_max": float(degrees.max()),
                "translation_world_median": float(world.median()), "translation_world_max": float(world.max())}
