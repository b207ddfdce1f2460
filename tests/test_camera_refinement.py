"""train.camera_refinement: per-image pose corrections learnt with the field (srf/camera_refinement.py)."""

import numpy as np
import pytest
import torch

from srfpipe.srf.camera_refinement import (CameraRefinement, adjusted_poses, gauge_basis, refined_world_pose, skew,
                                           so3_exp)
from srfpipe.srf.data import rays_for_pixels
from srfpipe.srf.encodings import DenseGrid


def test_so3_exp_is_the_matrix_exponential_and_smooth_at_zero():
    w = torch.tensor([[0.3, -1.2, 0.5], [1e-7, 0.0, -2e-7], [0.0, 0.0, 0.0], [0.0, 3.0, 0.0]], dtype=torch.float64)
    rotation = so3_exp(w)
    assert torch.allclose(rotation, torch.linalg.matrix_exp(skew(w)), atol=1e-12)
    assert torch.allclose(rotation @ rotation.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(4, 3, 3))
    start = torch.zeros(3, requires_grad=True)
    so3_exp(start).sum().backward()  # the corrections start at zero: a finite gradient there
    assert torch.isfinite(start.grad).all()


def ring_poses(count: int, generator) -> torch.Tensor:
    poses = torch.eye(4, dtype=torch.float64).repeat(count, 1, 1)
    poses[:, :3, :3] = so3_exp(torch.randn(count, 3, generator=generator, dtype=torch.float64))
    poses[:, :3, 3] = 3.0 * torch.randn(count, 3, generator=generator, dtype=torch.float64)
    return poses


def test_moving_all_training_cameras_together_is_not_a_correction():
    """A turn, shift and scaling of every training camera at once (the refined frame drifting off the
    given one, in which held-out views are rendered) is what the gauge basis spans, to first order,
    and what the anchored corrections remove; one camera's own error is kept."""
    generator = torch.Generator().manual_seed(0)
    poses = ring_poses(40, generator)
    train_views = [i for i in range(40) if i % 8 != 3]
    basis = gauge_basis(poses, train_views).reshape(40, 6, 7)
    eps = 1e-4
    omega, tau, s = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64), torch.tensor([1.0, 0.2, -0.4], dtype=torch.float64), 0.7
    centroid = poses[train_views, :3, 3].mean(0)
    turn = so3_exp(eps * omega)
    moved = poses.clone()  # the similarity applied to every camera
    moved[:, :3, :3] = turn @ poses[:, :3, :3]
    moved[:, :3, 3] = centroid + (1 + eps * s) * (turn @ (poses[:, :3, 3] - centroid).T).T + eps * tau
    motion = eps * (basis @ torch.cat([tau, omega, torch.tensor([s], dtype=torch.float64)]))
    first_order = adjusted_poses(poses, motion)
    assert torch.allclose(first_order[train_views], moved[train_views], atol=1e-7)
    assert torch.count_nonzero(motion[[3, 11]]) == 0  # held-out views are not part of it

    cameras = CameraRefinement(poses.float(), train_views)
    own_error = torch.zeros(40, 6)
    own_error[2] = torch.tensor([0.01, -0.02, 0.0, 0.003, 0.0, -0.002])
    with torch.no_grad():
        cameras.adjustment.copy_((motion / eps * 0.01).float() + own_error)
    kept = cameras.corrections().detach()
    others = torch.ones(40, dtype=torch.bool)
    others[2] = False
    assert kept[others].abs().max() < 0.002  # the common motion is gone (its largest entry was ~0.1)
    assert torch.linalg.norm(kept[2] - own_error[2]) < 0.25 * torch.linalg.norm(own_error[2])
    assert torch.allclose(kept[[3, 11]], torch.zeros(2, 6))


def test_refined_rays_are_the_rays_of_the_refined_poses():
    generator = torch.Generator().manual_seed(0)
    poses = torch.eye(4).repeat(3, 1, 1)
    poses[:, :3, :3] = so3_exp(torch.randn(3, 3, generator=generator))
    poses[:, :3, 3] = torch.randn(3, 3, generator=generator)
    cameras = CameraRefinement(poses)
    with torch.no_grad():
        cameras.adjustment.copy_(0.05 * torch.randn(3, 6, generator=generator))
    image = torch.tensor([0, 2, 1, 2])
    u, v = torch.tensor([3, 10, 0, 7]), torch.tensor([5, 1, 8, 8])
    intrinsics = torch.tensor([20.0, 20.0, 8.0, 6.0]).expand(4, 4)
    origins, directions = rays_for_pixels(poses[image], intrinsics, u, v)
    refined = cameras(image, origins, directions)
    expected = rays_for_pixels(adjusted_poses(poses, cameras.adjustment.detach())[image], intrinsics, u, v)
    for got, want in zip(refined, expected):
        assert torch.allclose(got, want, atol=1e-5)
    # in the world: the scene frame's scale divides the translation (4 scene units per world unit)
    scene_from_world = np.diag([4.0, 4.0, 4.0, 1.0])
    world = np.linalg.inv(scene_from_world) @ poses[1].double().numpy()
    world[:3, :3] = poses[1, :3, :3].double().numpy()
    got = refined_world_pose(world, cameras.adjustment[1].detach().double().numpy(), 4.0)
    want = adjusted_poses(poses[1:2].double(), cameras.adjustment[1:2].detach().double())[0].numpy()
    assert np.allclose(got[:3, :3], want[:3, :3], atol=1e-6)
    assert np.allclose(4.0 * got[:3, 3], want[:3, 3], atol=1e-6)


def test_grid_features_have_a_gradient_in_the_position_when_the_rays_learn():
    """Camera refinement moves the samples: the trilinear grid must tell it which way (a central
    difference agrees)."""
    torch.manual_seed(0)
    grid = DenseGrid((5, 6, 7), features=3)
    u = torch.tensor([[0.13, -0.41, 0.52], [-0.77, 0.28, 0.05]], requires_grad=True)
    grid(u).sum().backward()
    eps = 1e-3
    for point in range(2):
        step = torch.zeros(2, 3)
        fd = []
        for axis in range(3):
            step.zero_()
            step[point, axis] = eps
            fd.append(float((grid(u.detach() + step).sum() - grid(u.detach() - step).sum()) / (2 * eps)))
        assert np.allclose(u.grad[point].numpy(), fd, rtol=1e-2, atol=1e-3), (u.grad[point], fd)


def test_the_photometric_loss_turns_a_wrong_camera_back(tmp_path):
    """View 3 is recorded 3 degrees off the camera that took it. Against a field trained on the
    right poses, the gradient of the colour error in the correction (through the sampled points
    and the grids) turns the camera back most of the way."""
    from srfpipe.srf.data import image_rays, load_posed_images
    from srfpipe.srf.io import read_srf
    from srfpipe.srf.synthetic import write_scene
    from srfpipe.srf.trainer import train

    from test_train import tiny_options

    images, labels = write_scene(tmp_path / "right", views=10, width=64, height=48)
    train(images, labels, tmp_path / "srf.zarr", tiny_options(iterations=500, rays_per_batch=1024,
                                                              checkpoint_every=0), holdout_every=5)
    model = read_srf(tmp_path / "srf.zarr")[0].train()
    model.requires_grad_(False)
    error = np.radians([3.0, 0.0, 0.0])
    wrong = load_posed_images(*write_scene(tmp_path / "wrong", views=10, width=64, height=48, pose_errors={3: error}))
    cameras = CameraRefinement(wrong.poses_scene)
    optimizer = torch.optim.Adam(cameras.parameters(), lr=1e-3)
    origins, directions = image_rays(wrong.poses_scene[3], wrong.intrinsics[3], wrong.width, wrong.height)
    target = wrong.images[3].reshape(-1, 3).float() / 255.0
    image = torch.full((origins.shape[0],), 3)
    losses = []
    for _ in range(300):
        rendered = model(*cameras(image, origins, directions))["rgb"]
        loss = ((rendered - target) ** 2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss))
    turn = cameras.adjustment[3, 3:].detach().double().numpy()
    left = np.linalg.norm(turn + error)
    print(f"correction of view 3: {np.degrees(turn).round(2)} deg, {np.degrees(left):.2f} deg of 3 left, "
          f"colour error {losses[0]:.4f} -> {losses[-1]:.4f}")
    assert left < 0.5 * np.linalg.norm(error)
    assert np.dot(turn, -error) / (np.linalg.norm(turn) * np.linalg.norm(error)) > 0.8
    assert np.mean(losses[-10:]) < 0.7 * losses[0]


def test_a_refined_run_records_its_corrections_and_renders_training_views_through_them(tmp_path):
    from srfpipe.srf.io import read_camera_adjustment, read_srf
    from srfpipe.srf.query import SemanticRadianceField
    from srfpipe.srf.synthetic import write_scene
    from srfpipe.srf.trainer import train

    from test_train import tiny_options

    images, labels = write_scene(tmp_path, views=10, width=32, height=24, pose_errors={3: [0.05, 0.0, 0.0]})
    out = tmp_path / "srf.zarr"
    options = tiny_options(iterations=30, camera_refinement=True, keep_checkpoints=True)
    train(images, labels, out, options, holdout_every=5, checkpoints=tmp_path / "ckpt")
    correction = read_camera_adjustment(out)
    # a run stopped after step 20 resumes with its cameras' corrections (and their Adam state)
    (tmp_path / "ckpt" / "step-000000030.pt").unlink(missing_ok=True)
    resumed = tmp_path / "resumed.zarr"
    train(images, labels, resumed, options, holdout_every=5, checkpoints=tmp_path / "ckpt")
    assert read_srf(resumed)[1]["resumed_from_step"] == 20
    assert np.allclose(read_camera_adjustment(resumed), correction, atol=1e-4)
    assert correction.shape == (10, 6) and np.isfinite(correction).all()
    assert not correction[[0, 5]].any() and correction[3].any()  # held-out views keep their given poses
    attrs = read_srf(out)[1]
    assert attrs["config"]["camera_refinement"] is True and attrs["camera_refinement"]["images"] == 8
    field = SemanticRadianceField.load(out, device="cpu")
    assert not np.allclose(field.training_pose(3, np.eye(4)), np.eye(4))
    assert np.allclose(field.training_pose(0, np.eye(4)), np.eye(4))
    # the generalization check renders the training views through the refined cameras
    from srfpipe.evaluate import evaluate

    metrics = evaluate(images, labels, out, tmp_path / "eval", {}, device="cpu")
    assert np.isfinite(metrics["train_view_psnr"]) and np.isfinite(metrics["psnr"])


def test_camera_refinement_auto_is_on_for_real_captures_only():
    from srfpipe.srf.trainer import resolve_data_defaults

    from test_train import camera_ring_data

    real = camera_ring_data(100.0)
    real.bounds_source = "points"
    generated = camera_ring_data(100.0)
    generated.gt_label, generated.bounds_source = np.zeros((1, 2, 2)), "ground_truth"
    assert resolve_data_defaults({"camera_refinement": "auto"}, real).camera_refinement is True
    assert resolve_data_defaults({"camera_refinement": "auto"}, generated).camera_refinement is False
    assert resolve_data_defaults({"camera_refinement": False}, real).camera_refinement is False


@pytest.mark.parametrize("value", ["on", 1])
def test_camera_refinement_rejects_values_outside_its_schema(value):
    from srfpipe.config import validate_scene

    with pytest.raises(Exception, match="camera_refinement"):
        validate_scene({"train": {"camera_refinement": value}})
