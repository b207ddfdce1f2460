"""Comparing and aligning camera sets: perturbation (a testing aid), similarity alignment, pose errors.

Used by the COLMAP refinement (to map the refined cameras back into the capture's world frame) and
by tests and benchmarks (errors after removing a change of gauge).
"""

from __future__ import annotations

import numpy as np

from srfpipe import cameras


def perturb_poses(camera_to_world: np.ndarray, rot_deg: float, translation: float, seed: int) -> np.ndarray:
    """Testing aid: turn every camera by `rot_deg` about a random axis through its centre and move
    its centre by `translation` (world units) in a random direction."""
    import cv2

    rng = np.random.default_rng(seed)
    poses = np.array(camera_to_world, dtype=np.float64, copy=True)
    for pose in poses:
        axis = rng.normal(size=3)
        rotation, _ = cv2.Rodrigues(np.radians(rot_deg) * axis / np.linalg.norm(axis))
        pose[:3, :3] = pose[:3, :3] @ rotation
        direction = rng.normal(size=3)
        pose[:3, 3] += translation * direction / np.linalg.norm(direction)
    return poses


def similarity_align(source_points: np.ndarray, target_points: np.ndarray) -> np.ndarray:
    """4x4 similarity (Umeyama, via pycolmap) mapping `source_points` onto `target_points`."""
    import pycolmap

    sim = pycolmap.estimate_sim3d(np.asarray(source_points, np.float64), np.asarray(target_points, np.float64))
    if sim is None:
        raise RuntimeError("similarity alignment failed (degenerate camera centres)")
    return np.vstack([sim.matrix(), [0.0, 0.0, 0.0, 1.0]])


def _frame_points(camera_to_world: np.ndarray, length: float) -> np.ndarray:
    """Each camera's centre and the tips of its three axes at `length`: (4N, 3)."""
    centres = camera_to_world[:, :3, 3]
    tips = centres[:, None, :] + length * np.swapaxes(camera_to_world[:, :3, :3], 1, 2)
    return np.concatenate([centres, tips.reshape(-1, 3)])


def align_poses(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """4x4 similarity mapping the `source` cameras onto the `target` cameras.

    Fitted to the camera centres *and* their orientations (the tips of the camera axes, placed at
    the spread of the target centres, before the source is scaled to the target's size): centres
    alone pin the rotation down poorly when the cameras stand almost in one plane, as on one ring.
    """
    source = np.asarray(source, np.float64)
    target = np.asarray(target, np.float64)
    scale = similarity_align(source[:, :3, 3], target[:, :3, 3]) if len(source) >= 3 else np.eye(4)
    source_scale = np.cbrt(np.linalg.det(scale[:3, :3]))
    length = max(float(np.sqrt(((target[:, :3, 3] - target[:, :3, 3].mean(0)) ** 2).sum(1).mean())), 1e-9)
    return similarity_align(_frame_points(source, length / source_scale), _frame_points(target, length))


def pose_errors(estimate: np.ndarray, reference: np.ndarray, scene_size: float, align: bool = True) -> dict:
    """Mean rotation error (degrees) and camera-centre error relative to `scene_size`.

    With `align`, the estimate is first mapped onto the reference by the similarity that best
    aligns the cameras (`align_poses`), so a change of gauge (scale, rotation, shift) is not an error.
    """
    estimate = np.asarray(estimate, np.float64)
    reference = np.asarray(reference, np.float64)
    if align:
        estimate = cameras.transform_poses(align_poses(estimate, reference), estimate)
    relative = np.einsum("nji,njk->nik", estimate[:, :3, :3], reference[:, :3, :3])
    cos = np.clip((np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    rot = np.degrees(np.arccos(cos))
    trans = np.linalg.norm(estimate[:, :3, 3] - reference[:, :3, 3], axis=1) / scene_size
    return {"rot_err_deg": float(rot.mean()), "trans_err": float(trans.mean()),
            "rot_err_deg_max": float(rot.max()), "trans_err_max": float(trans.max())}


def up_alignment(camera_to_world: np.ndarray) -> np.ndarray:
    """4x4 rotation about the origin that turns the cameras' mean up vector to +z (`poses.up: auto`).

    A camera's up is -y in the project's OpenCV convention (+y points down the image). The rotation
    is the smallest one that does it (about the axis perpendicular to both), so a capture already
    upright is left as it is.
    """
    import cv2

    up = -np.asarray(camera_to_world, np.float64)[:, :3, 1].mean(0)
    length = float(np.linalg.norm(up))
    if length < 1e-6:
        raise ValueError("poses.up auto: the cameras' up vectors cancel out (cameras held every way up)")
    up /= length
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(up, z)
    sin, cos = float(np.linalg.norm(axis)), float(up @ z)
    rotation = np.eye(4)
    if sin < 1e-12:
        if cos < 0:
            rotation[:3, :3] = np.diag([1.0, -1.0, -1.0])  # upside down: half a turn about x
        return rotation
    rotation[:3, :3] = cv2.Rodrigues(axis / sin * np.arctan2(sin, cos))[0]
    return rotation
