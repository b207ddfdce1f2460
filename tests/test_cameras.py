"""The camera convention: rays, projection, conversions and scene normalization."""

import numpy as np
import pytest

from srfpipe import cameras


def look_at(eye, target, up=(0, 0, 1)):
    forward = np.asarray(target, float) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, down, forward], axis=1)
    pose[:3, 3] = eye
    return pose


def test_centre_ray_looks_forward_and_projection_inverts_rays():
    pose = look_at(np.array([3.0, 0.0, 1.0]), [0.0, 0.0, 1.0])
    intrinsics = np.array([50.0, 50.0, 32.0, 24.0])
    origins, directions = cameras.pixel_rays(pose, intrinsics, 64, 48)
    # The ray between the four centre pixels points at the target.
    centre = directions[23:25, 31:33].reshape(-1, 3).mean(0)
    np.testing.assert_allclose(centre / np.linalg.norm(centre), [-1, 0, 0], atol=1e-9)
    points = origins + 2.5 * directions
    uv, depth = cameras.project_points(points.reshape(-1, 3), pose, intrinsics)
    u, v = np.meshgrid(np.arange(64) + 0.5, np.arange(48) + 0.5)
    np.testing.assert_allclose(uv, np.stack([u, v], -1).reshape(-1, 2), atol=1e-9)
    assert np.all(depth > 0)


def test_opengl_conversion_is_an_involution():
    pose = look_at(np.array([1.0, 2.0, 3.0]), [0.0, 0.0, 0.0])
    gl = cameras.opencv_to_opengl(pose)
    # OpenGL cameras look down -z: the forward direction is the negated third column.
    np.testing.assert_allclose(-gl[:3, 2], pose[:3, 2])
    np.testing.assert_allclose(cameras.opengl_to_opencv(gl), pose)


def test_normalization_round_trip_and_box():
    lo, hi = np.array([-1.0, -2.0, 0.0]), np.array([3.0, 2.0, 2.5])
    scene_from_world = cameras.scene_from_world_transform(lo, hi)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    scene = cameras.transform_points(scene_from_world, corners)
    assert np.all(np.abs(scene) <= 1 + 1e-12) and np.isclose(np.abs(scene).max(), 1)
    back = cameras.transform_points(np.linalg.inv(scene_from_world), scene)
    np.testing.assert_allclose(back, corners, atol=1e-12)
    pose = look_at(np.array([3.0, 0.0, 1.0]), [0.0, 0.0, 1.0])
    moved = cameras.transform_poses(scene_from_world, pose)
    assert cameras.check_rotation(moved[:3, :3]) is None


@pytest.mark.bad_input
def test_bad_bounds_and_rotations_are_named():
    with pytest.raises(ValueError, match="empty"):
        cameras.scene_from_world_transform([0, 0, 0], [1, 0, 1])
    assert "NaN" in cameras.check_rotation(np.full((3, 3), np.nan))
    assert "orthonormal" in cameras.check_rotation(np.diag([1.0, 2.0, 1.0]))
    assert "reflection" in cameras.check_rotation(np.diag([1.0, 1.0, -1.0]))


def test_intrinsics_scale_with_pixel_centres():
    scaled = cameras.scale_intrinsics(np.array([100.0, 100.0, 320.0, 240.0]), 0.25)
    np.testing.assert_allclose(scaled, [25.0, 25.0, 80.0, 60.0])


def test_rays_of_a_lens_pass_through_what_the_lens_projects_to_each_pixel():
    """pixel_rays with OpenCV distortion inverts cv2.projectPoints: the generator's lens renders
    exactly what a COLMAP OPENCV calibration describes."""
    import cv2

    width, height = 61, 81
    k = np.array([52.0, 52.0, 30.5, 40.5])
    distortion = np.array([-0.0024, -0.021, 0.011, 0.0096])  # a phone's strong tangential terms
    pose = np.eye(4)
    origins, directions = cameras.pixel_rays(pose, k, width, height, distortion)
    points = (directions / directions[..., 2:]).reshape(-1, 3) * 3.0  # depth 3 along each ray
    k_cv = cameras.intrinsic_matrix(k[0], k[1], k[2] - 0.5, k[3] - 0.5)
    projected, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), k_cv, distortion)
    v, u = np.mgrid[0:height, 0:width]
    np.testing.assert_allclose(projected.reshape(height, width, 2), np.stack([u, v], -1), atol=1e-6)
    pinhole = cameras.pixel_rays(pose, k, width, height)[1]
    assert np.degrees(np.arccos(np.clip((pinhole * directions).sum(-1), -1, 1))).max() > 0.5  # it matters


def test_sequence_fraction_tells_a_video_from_photos_in_no_order():
    """A walk's frames stand next to the frames named before and after them, frame_9 next to
    frame_10 (natural order, not the strings'); photos named in no such order score near chance."""
    from srfpipe.cameras import images_form_a_sequence, look_at, natural_order, sequence_fraction

    path = [look_at(np.array([0.3 * i, np.sin(0.2 * i), 1.0]), np.array([0.3 * i, 5.0, 0.0])) for i in range(30)]
    names = [f"frame_{i}" for i in range(30)]
    assert natural_order(["frame_10", "frame_9", "frame_1"]) == [2, 1, 0]
    assert sequence_fraction(names, np.stack(path)) == 1.0
    shuffled = np.random.default_rng(1).permutation(30)
    assert sequence_fraction([names[i] for i in shuffled], np.stack(path)) < 0.2
    assert images_form_a_sequence(names, np.stack(path))
    assert not images_form_a_sequence([names[i] for i in shuffled], np.stack(path))
    assert sequence_fraction(names[:2], np.stack(path[:2])) == 0.0  # two images make no sequence
