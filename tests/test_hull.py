"""Scene bounds from the masks: the visual hull of a small object seen by far cameras."""

import numpy as np

from srfpipe import cameras
from srfpipe.segment.hull import bounds_from_masks

RADIUS = 3.0  # a ball of radius 3 units at (10, -5, 2), cameras 300 units away: the frusta are useless
CENTRE = np.array([10.0, -5.0, 2.0])


def ring_cameras(views=16, distance=300.0, size=64, fov_deg=3.0):
    poses, intrinsics = [], []
    focal = 0.5 * size / np.tan(np.radians(fov_deg) / 2)
    for angle in np.linspace(0, 2 * np.pi, views, endpoint=False):
        eye = CENTRE + distance * np.array([np.cos(angle), np.sin(angle), 0.3])
        forward = (CENTRE - eye) / np.linalg.norm(CENTRE - eye)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([right, down, forward], axis=1)
        pose[:3, 3] = eye
        poses.append(pose)
        intrinsics.append([focal, focal, size / 2, size / 2])
    return np.array(poses), np.array(intrinsics), size


def ball_mask(pose, k, size):
    """Pixels whose ray hits the ball."""
    origins, directions = cameras.pixel_rays(pose, k, size, size)
    offset = origins - CENTRE
    b = (offset * directions).sum(-1)
    return b**2 - ((offset**2).sum(-1) - RADIUS**2) >= 0


def test_hull_of_a_small_far_object_is_tight_and_contains_it():
    poses, intrinsics, size = ring_cameras()
    masks = [ball_mask(p, k, size) for p, k in zip(poses, intrinsics)]
    assert all(m.any() for m in masks)
    # the poses' bounds from the frusta are loose: here a box 40x the ball's size
    loose = np.stack([CENTRE - 60.0, CENTRE + 60.0])
    box, record = bounds_from_masks(poses, intrinsics, masks, loose)
    assert np.all(box[0] <= CENTRE - RADIUS) and np.all(box[1] >= CENTRE + RADIUS), box
    true_volume = (2 * RADIUS) ** 3
    ratio = np.prod(box[1] - box[0]) / true_volume
    # a ring of views carves a ball loosely above and below, and the carve keeps every cell a
    # mask touches (a thin stalk must survive), so the box is looser than the ball's cube
    assert ratio <= 3.5, (ratio, box)
    assert record["volume_vs_poses_bounds"] < 0.01


def test_hull_tolerates_one_view_whose_mask_missed_the_object():
    poses, intrinsics, size = ring_cameras(views=20)
    masks = [ball_mask(p, k, size) for p, k in zip(poses, intrinsics)]
    masks[3] = np.zeros_like(masks[3])  # the segmenter failed on one frame
    box, _ = bounds_from_masks(poses, intrinsics, masks, np.stack([CENTRE - 60.0, CENTRE + 60.0]))
    assert np.all(box[0] <= CENTRE - 0.9 * RADIUS) and np.all(box[1] >= CENTRE + 0.9 * RADIUS), box


def test_empty_masks_keep_the_poses_bounds():
    poses, intrinsics, size = ring_cameras()
    masks = [np.zeros((size, size), bool) for _ in poses]
    assert bounds_from_masks(poses, intrinsics, masks, np.stack([CENTRE - 60.0, CENTRE + 60.0])) is None


def stick_mask(pose, k, size, start, end, radius):
    """Pixels whose ray passes within `radius` of the segment start-end (a thin stalk)."""
    origins, directions = cameras.pixel_rays(pose, k, size, size)
    samples = np.linspace(0.0, 1.0, 200)[:, None] * (end - start) + start  # points along the stalk
    uv, depth = cameras.project_points(samples, pose, k)
    mask = np.zeros((size, size), bool)
    focal = k[0]
    for (u, v), z in zip(uv, depth):
        r = max(focal * radius / z, 0.8)  # at least a line of pixels
        ys, xs = np.ogrid[:size, :size]
        mask |= (xs + 0.5 - u) ** 2 + (ys + 0.5 - v) ** 2 <= r * r
    return mask


def test_hull_keeps_a_stalk_thinner_than_its_cells_that_some_masks_miss():
    # a ball carried by a stalk 10 units long and 0.1 thick: under a pixel wide in these views
    # and thinner than a cell of either carve; the stalk drops out of every third view's mask
    poses, intrinsics, size = ring_cameras(views=20, size=96, fov_deg=5.0)
    tip = CENTRE + np.array([0.0, 0.0, RADIUS + 10.0])
    masks = []
    for i, (p, k) in enumerate(zip(poses, intrinsics)):
        mask = ball_mask(p, k, size)
        if i % 3:  # views 0, 3, 6, ... miss it
            mask |= stick_mask(p, k, size, CENTRE, tip, 0.05)
        masks.append(mask)
    box, record = bounds_from_masks(poses, intrinsics, masks, np.stack([CENTRE - 60.0, CENTRE + 60.0]))
    assert record["grid_spacing"] > 0.1  # the stalk is thinner than a cell of the finer carve
    assert box[1, 2] >= tip[2] - 0.5, (box, tip)  # the stalk's tip is inside the box
    assert np.prod(box[1] - box[0]) < 0.05 * 120.0**3  # and the box still hugs the object
