"""Trainer, srf.zarr, query API and evaluation on a tiny analytic scene (quick settings)."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from srfpipe.config import section_defaults
from srfpipe.srf.data import split_views
from srfpipe.srf.io import read_curve, read_srf
from srfpipe.srf.query import SemanticRadianceField
from srfpipe.srf.synthetic import write_scene
from srfpipe.srf.trainer import learning_rate, train


def tiny_options(**overrides):
    options = section_defaults("train")
    options.update(iterations=30, rays_per_batch=256, default_cells=20, outer_resolution=12, hidden=32,
                   outer_samples=16, before_samples=8, checkpoint_every=10, log_every=5,
                   occupancy_update_every=8, occupancy_warmup=16, time_budget=0)
    options.update(overrides)
    return options


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scene")
    images, labels = write_scene(folder, views=10, width=32, height=24)
    return folder, images, labels


@pytest.fixture(scope="module")
def trained(scene):
    folder, images, labels = scene
    out = folder / "srf.zarr"
    train(images, labels, out, tiny_options(iterations=60, eval_every=30), holdout_every=5)
    return out


def test_split_holds_out_every_kth_view_and_rejects_bad_values():
    train_views, held = split_views(10, 4)
    assert held.tolist() == [0, 4, 8] and sorted(train_views.tolist() + held.tolist()) == list(range(10))
    with pytest.raises(ValueError, match="holdout_every"):
        split_views(10, 1)


def test_overfitting_one_tiny_image_raises_psnr(tmp_path):
    images, labels = write_scene(tmp_path, views=2, width=16, height=12)
    out = tmp_path / "srf.zarr"
    # two views, view 0 held out: every step trains on the same 192 pixels
    train(images, labels, out, tiny_options(iterations=150, rays_per_batch=192, lr_final=0.005,
                                            checkpoint_every=0), holdout_every=2)
    curve = read_curve(out)
    start, end = curve["psnr"][:2].mean(), curve["psnr"][-3:].mean()
    assert end > start + 8.0, (start, end)
    assert end > 24.0


def test_a_class_whose_masks_stay_under_the_threshold_is_learnt_from_their_probabilities(tmp_path):
    # soft masks (a blurred rim, a thin part's pixels half covered) say 0.45 where the leaves
    # are: composited at 0.5 they mark nothing, and heads trained on those bits never learn the class
    from srfpipe.artifacts import open_artifact
    from srfpipe.evaluate import world_from_scene_pose
    from srfpipe.srf.data import load_posed_images
    from srfpipe.srf.synthetic import CLASSES, write_labels

    images, labels = write_scene(tmp_path, views=2, width=16, height=12)
    label = np.asarray(open_artifact(labels)["label"][...])
    truth = label[..., None] == np.arange(1, len(CLASSES) + 1)
    probability = np.where(truth, np.array([255, 255, 115], np.uint8), 0).astype(np.uint8)  # leaf 0.45
    soft = write_labels(tmp_path / "soft.zarr", label, CLASSES, ["frame_00000", "frame_00001"], inputs=[images],
                        probability=probability)
    data = load_posed_images(images, soft, probability=True)
    assert data.probability.shape == (2, 12, 16, 3) and load_posed_images(images, soft).probability is None
    pose = world_from_scene_pose(data.world_from_scene, data.poses_scene[1].numpy())
    leaves = label[1] == 3
    assert leaves.sum() >= 20
    leaf_probability, colour_and_depth = {}, {}
    for targets in (None, "labels"):  # the default, and the composited bits
        out = tmp_path / f"srf-{targets}.zarr"
        # view 0 held out: every step trains on view 1's 192 pixels, as the overfitting test does
        options = tiny_options(iterations=300, rays_per_batch=192, lr_final=0.005, checkpoint_every=0,
                               **({"semantic_targets": targets} if targets else {}))
        train(images, soft, out, options, holdout_every=2)
        field = SemanticRadianceField.load(out, device="cpu")
        assert field.attrs["config"]["semantic_targets"] == (targets or "probabilities")
        assert field.attrs["config"]["semantic_positive_weight"] == (1.0 if targets else 2.0)
        rendered = field.render(pose, data.intrinsics[1].numpy(), 16, 12)
        leaf_probability[targets] = float(np.median(rendered["semantic"][..., 2][leaves]))
        colour_and_depth[targets] = (rendered["rgb"], rendered["depth"])
    # the heads read h.detach() and composite with detached weights (Eq. 3): what they learn from
    # cannot move the geometry or the colour
    assert np.allclose(colour_and_depth[None][0], colour_and_depth["labels"][0], atol=1e-5)
    assert np.allclose(colour_and_depth[None][1], colour_and_depth["labels"][1], rtol=1e-4, atol=1e-5)
    # a labels.zarr of an older composite holds no probabilities: asking for them names the file and writes nothing
    with pytest.raises(ValueError, match=r"labels\.zarr: train\.semantic_targets is probabilities.*re-run the composite"):
        train(images, labels, tmp_path / "old.zarr", tiny_options(semantic_targets="probabilities"), holdout_every=2)
    assert not (tmp_path / "old.zarr").exists()
    # the weighted BCE's optimum for y = 0.45, w = 2: 0.9 / 1.45 = 0.62; the bits' optimum: 0
    assert abs(leaf_probability[None] - 0.9 / 1.45) < 0.06 and leaf_probability["labels"] < 0.1, leaf_probability


def test_learning_rate_holds_then_decays_to_lr_final():
    assert learning_rate(0.0, 1e-2, 1e-3) == pytest.approx(1e-2)
    assert learning_rate(0.5, 1e-2, 1e-3) == pytest.approx(1e-2 * 0.1**0.5)
    # held for the first 80 % of the run, then the whole decay in the last 20 %
    assert learning_rate(0.8, 1e-2, 1e-3, hold=0.8) == pytest.approx(1e-2)
    assert learning_rate(0.9, 1e-2, 1e-3, hold=0.8) == pytest.approx(1e-2 * 0.1**0.5)
    assert learning_rate(1.0, 1e-2, 1e-3, hold=0.8) == pytest.approx(1e-3)
    assert learning_rate(1.5, 1e-2, 1e-3, hold=1.0) == pytest.approx(1e-2)  # hold 1: never decays


@pytest.fixture
def one_thread():
    # bit-identical results need a fixed reduction order: with several threads some CPU kernels
    # split their sums differently from run to run (differences of ~1e-7 even without a resume)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_resumed_run_ends_with_the_same_weights(scene, tmp_path, one_thread, device):
    _, images, labels = scene
    options = tiny_options(iterations=24, checkpoint_every=8, keep_checkpoints=True)
    full = tmp_path / "full.zarr"
    train(images, labels, full, options, holdout_every=5, checkpoints=tmp_path / "ckpt_full")

    # a run killed after step 16 leaves checkpoints 8 and 16 behind (the output never appears);
    # a first run with kept checkpoints produces exactly that folder
    interrupted = tmp_path / "resumed.zarr"
    ckpt = tmp_path / "ckpt_resumed"
    train(images, labels, tmp_path / "partial.zarr", options, holdout_every=5, checkpoints=ckpt)
    assert [p.name for p in sorted(ckpt.glob("step-*.pt"))] == ["step-000000008.pt", "step-000000016.pt"]
    train(images, labels, interrupted, options, holdout_every=5, checkpoints=ckpt)
    assert read_srf(interrupted)[1]["resumed_from_step"] == 16

    a, _ = read_srf(full)
    b, _ = read_srf(interrupted)
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys()
    if device.type == "cpu":
        for key in sa:
            assert torch.equal(sa[key], sb[key]), key
        return
    # CUDA sums a grid's gradients with atomic adds in no fixed order, so two runs of the same steps
    # differ in the last bits, and Adam turns a near-zero gradient's noise into a step of lr: the
    # resumed run must be the same model (it renders the same images), not the same bits
    from srfpipe.cameras import look_at

    pose, k = look_at((2.0, 0.5, 0.8), (0.0, 0.0, 0.35)), [30.0, 30.0, 16.0, 12.0]
    full_rgb = SemanticRadianceField.load(full, device=device).render(pose, k, 32, 24)["rgb"]
    resumed_rgb = SemanticRadianceField.load(interrupted, device=device).render(pose, k, 32, 24)["rgb"]
    agreement = -10 * np.log10(max(float(np.mean((full_rgb - resumed_rgb) ** 2)), 1e-12))
    print(f"resumed vs uninterrupted render on {device}: {agreement:.1f} dB")
    assert agreement > 30.0


def test_checkpoint_from_other_settings_is_not_resumed(scene, tmp_path):
    _, images, labels = scene
    ckpt = tmp_path / "ckpt"
    train(images, labels, tmp_path / "a.zarr", tiny_options(iterations=10, checkpoint_every=5,
                                                            keep_checkpoints=True),
          holdout_every=5, checkpoints=ckpt)
    train(images, labels, tmp_path / "b.zarr", tiny_options(iterations=10, seed=1, checkpoint_every=5),
          holdout_every=5, checkpoints=ckpt)
    assert read_srf(tmp_path / "b.zarr")[1]["resumed_from_step"] == 0


def test_a_changed_keep_checkpoints_still_resumes(scene, tmp_path):
    _, images, labels = scene
    ckpt = tmp_path / "ckpt"
    # a run killed after step 10 (kept: the folder it leaves), re-run without keep_checkpoints
    train(images, labels, tmp_path / "a.zarr", tiny_options(iterations=12, checkpoint_every=5, keep_checkpoints=True),
          holdout_every=5, checkpoints=ckpt)
    train(images, labels, tmp_path / "b.zarr", tiny_options(iterations=12, checkpoint_every=5, log_every=3),
          holdout_every=5, checkpoints=ckpt)
    assert read_srf(tmp_path / "b.zarr")[1]["resumed_from_step"] == 10
    assert not ckpt.exists()


@pytest.mark.parametrize("device", ["tpu", "cuda:7"])
def test_a_device_that_is_not_there_is_refused_naming_the_key(scene, tmp_path, device):
    _, images, labels = scene
    if device.startswith("cuda") and torch.cuda.device_count() > 7:
        pytest.skip("this machine has a GPU 7")
    with pytest.raises(ValueError, match=rf"train.device: .*{device}"):
        train(images, labels, tmp_path / "srf.zarr", tiny_options(device=device), holdout_every=5)
    assert not (tmp_path / "srf.zarr").exists()


def test_a_checkpoint_folder_that_is_a_file_or_negative_threads_are_refused_before_training(scene, tmp_path, capsys):
    from srfpipe.cli import main

    _, images, labels = scene
    blocker = tmp_path / "srf.ckpt"
    blocker.write_text("not a folder")
    with pytest.raises(ValueError, match=rf"{blocker}: the checkpoint folder is a file"):
        train(images, labels, tmp_path / "srf.zarr", tiny_options(), holdout_every=5)
    assert not (tmp_path / "srf.zarr").exists()
    args = ["train", "--images", str(images), "--labels", str(labels), "--out", str(tmp_path / "b.zarr"),
            "--options", json.dumps(tiny_options(checkpoint_every=0))]
    assert main(args + ["--threads", "-1"]) == 1
    assert "srfpipe train: error: --threads -1: " in capsys.readouterr().err


def test_checkpoints_of_another_run_at_later_steps_do_not_prune_this_runs(tmp_path):
    from srfpipe.srf.hooks import save_checkpoint

    # a run with other settings got further in the same folder (its checkpoints are never resumed)
    for step in (30, 40):
        save_checkpoint(tmp_path, {"step": step, "fingerprint": "other"})
    save_checkpoint(tmp_path, {"step": 10, "fingerprint": "this"})
    save_checkpoint(tmp_path, {"step": 20, "fingerprint": "this"})
    save_checkpoint(tmp_path, {"step": 25, "fingerprint": "this"})
    names = sorted(p.name for p in tmp_path.glob("step-*.pt"))
    assert names == ["step-000000020.pt", "step-000000025.pt", "step-000000030.pt", "step-000000040.pt"]


def test_a_checkpoint_of_this_run_that_does_not_fit_is_passed_over_naming_it(scene, tmp_path, caplog):
    _, images, labels = scene
    ckpt = tmp_path / "ckpt"
    options = tiny_options(iterations=12, checkpoint_every=5, keep_checkpoints=True)
    train(images, labels, tmp_path / "a.zarr", options, holdout_every=5, checkpoints=ckpt)
    # the right fingerprint, tensors of the wrong shape (another srfpipe version, or damaged)
    newest = ckpt / "step-000000010.pt"
    state = torch.load(newest, weights_only=True)
    name = next(iter(state["model"]))
    state["model"][name] = torch.zeros(3, 3)
    torch.save(state, newest)
    with caplog.at_level("WARNING", logger="srfpipe.train"):
        train(images, labels, tmp_path / "b.zarr", options, holdout_every=5, checkpoints=ckpt)
    assert read_srf(tmp_path / "b.zarr")[1]["resumed_from_step"] == 5
    assert any(str(newest) in r.getMessage() and "does not fit" in r.getMessage() for r in caplog.records)
    # none fits: a fresh run, from the fresh weights (not half of the checkpoint's)
    for path in ckpt.glob("step-*.pt"):
        state = torch.load(path, weights_only=True)
        del state["curve"]
        torch.save(state, path)
    train(images, labels, tmp_path / "c.zarr", options, holdout_every=5, checkpoints=ckpt)
    assert read_srf(tmp_path / "c.zarr")[1]["resumed_from_step"] == 0
    a, b = read_srf(tmp_path / "a.zarr")[0].state_dict(), read_srf(tmp_path / "c.zarr")[0].state_dict()
    assert all(torch.allclose(a[k], b[k], atol=1e-5) for k in a)


def test_a_checkpoint_write_cut_short_by_a_kill_leaves_nothing_after_the_run(scene, tmp_path):
    _, images, labels = scene
    ckpt = tmp_path / "ckpt"
    ckpt.mkdir()
    # SIGKILL inside torch.save, at a step this run does not write again (its time budget, or a
    # changed checkpoint_every, ended it elsewhere)
    (ckpt / "step-000000004.pt.tmp").write_bytes(b"\x80\x02half a checkpoint")
    train(images, labels, tmp_path / "srf.zarr", tiny_options(iterations=6, checkpoint_every=5), holdout_every=5,
          checkpoints=ckpt)
    assert not ckpt.exists()


def test_snapshots_hold_the_weights_at_each_mark_and_outlive_the_run(scene, tmp_path):
    _, images, labels = scene
    ckpt = tmp_path / "ckpt"
    # 1e-9 s: passed by the first step; 1e9 s: never reached
    out = tmp_path / "srf.zarr"
    train(images, labels, out, tiny_options(iterations=12, checkpoint_every=5, snapshot_seconds=[1e9, 1e-9]),
          holdout_every=5, checkpoints=ckpt)
    assert [p.name for p in ckpt.iterdir()] == ["snapshot-000000001.pt"]  # checkpoints removed, snapshot kept
    state = torch.load(ckpt / "snapshot-000000001.pt", weights_only=True)
    assert state["step"] == 1 and state["marks"] == [1e-9] and 0 < state["train_seconds"]
    model, attrs = read_srf(out)
    assert state["fingerprint"] == attrs["fingerprint"]
    model.load_state_dict(state["model"])  # the same layout as the final weights
    # a monitoring key: the run it belongs to keeps its identity (resumes still match)
    assert attrs["fingerprint"] == _fingerprint_without_snapshots(images, labels, tmp_path)
    # a new run with other settings in the same folder: the earlier run's snapshot is gone, so a
    # quality-against-time curve read from the folder holds this run only
    train(images, labels, out, tiny_options(iterations=12, seed=1, snapshot_seconds=[1e-9]),
          holdout_every=5, checkpoints=ckpt)
    snapshots = [torch.load(p, weights_only=True) for p in ckpt.glob("snapshot-*.pt")]
    assert [s["fingerprint"] for s in snapshots] == [read_srf(out)[1]["fingerprint"]] != [attrs["fingerprint"]]


def _fingerprint_without_snapshots(images, labels, tmp_path):
    out = tmp_path / "plain.zarr"
    train(images, labels, out, tiny_options(iterations=12, checkpoint_every=5), holdout_every=5,
          checkpoints=tmp_path / "plain.ckpt")
    return read_srf(out)[1]["fingerprint"]


def test_srf_zarr_round_trip_and_query_api(trained, device):
    srf = SemanticRadianceField.load(trained, device=device)
    assert srf.classes == ["apple", "branch", "leaf"]
    assert srf.scene_from_world.shape == (4, 4) and srf.bounds_world.shape == (2, 3)
    curve = read_curve(trained)
    assert len(curve["step"]) > 0 and np.all(np.isfinite(curve["loss"]))
    from srfpipe.cameras import look_at

    pose = look_at((2.0, 0.5, 0.8), (0.0, 0.0, 0.35))
    out = srf.render(pose, [30.0, 30.0, 16.0, 12.0], 32, 24)
    assert out["rgb"].shape == (24, 32, 3) and out["rgb"].dtype == np.float32
    assert out["semantic"].shape == (24, 32, 3)
    assert out["depth"].shape == (24, 32) and out["accumulation"].shape == (24, 32)
    assert 0 <= out["rgb"].min() and out["rgb"].max() <= 1
    points = np.random.default_rng(0).uniform(-0.5, 0.5, (1000, 3)) + [0, 0, 0.5]
    p = srf.semantic(points)
    assert p.shape == (1000, 3) and np.all((p >= 0) & (p <= 1))
    sigma = srf.density(np.vstack([points, [[50.0, 0.0, 0.0]]]))
    assert sigma.shape == (1001,) and np.all(sigma >= 0) and sigma[-1] == 0.0
    with pytest.raises(ValueError, match="NaN"):
        srf.density(np.array([[0.0, np.nan, 0.0]]))
    with pytest.raises(ValueError, match=r"\(M, 3\)"):
        srf.semantic(np.zeros((3, 2)))


def test_supersampled_render_is_the_area_mean_of_the_finer_render(trained, device):
    # a pixel integrates the light over its footprint: with supersample s, each pixel is the mean of
    # the s x s pixels of the same camera rendered s times finer (a downscaled image's area average)
    from srfpipe.cameras import look_at

    srf = SemanticRadianceField.load(trained, device=device)
    pose, k = look_at((2.0, 0.5, 0.8), (0.0, 0.0, 0.35)), np.array([30.0, 30.0, 16.0, 12.0])
    coarse = srf.render(pose, k, 32, 24, supersample=2)
    fine = srf.render(pose, 2 * k, 64, 48)
    for key in ("rgb", "semantic", "depth", "accumulation"):
        area_mean = fine[key].reshape(24, 2, 32, 2, *fine[key].shape[2:]).mean((1, 3))
        np.testing.assert_allclose(coarse[key], area_mean, atol=1e-5, err_msg=key)
    centre = srf.render(pose, k, 32, 24)
    assert np.abs(coarse["rgb"] - centre["rgb"]).max() > 1e-3  # not the centre rays again
    with pytest.raises(ValueError, match="supersample"):
        srf.render(pose, k, 32, 24, supersample=0)


def test_density_is_per_world_unit(trained, device):
    srf = SemanticRadianceField.load(trained, device=device)
    points = np.random.default_rng(1).uniform(-0.4, 0.4, (200, 3)) + [0, 0, 0.45]  # inside the bounds
    x = torch.as_tensor(points @ srf.scene_from_world[:3, :3].T + srf.scene_from_world[:3, 3]).float().to(device)
    with torch.no_grad():
        scene_sigma = srf.model.field.density(x)[0].cpu().numpy()
    assert np.allclose(srf.density(points), scene_sigma * srf.scale, rtol=1e-5)


def test_evaluate_writes_metrics_and_renders(scene, trained, tmp_path, device):
    from srfpipe.evaluate import evaluate

    _, images, labels = scene
    out = tmp_path / "eval"
    metrics = evaluate(images, labels, trained, out, {"holdout_every": 5}, device=device)
    saved = json.loads((out / "metrics.json").read_text())
    for key in ("psnr", "psnr_object", "ssim", "miou", "miou_gt", "iou", "iou_gt"):
        assert key in saved
    assert saved["views"] == 2 and 0 <= saved["miou"] <= 1 and -1 <= saved["ssim"] <= 1
    assert metrics["psnr"] == pytest.approx(saved["psnr"])
    assert sorted(p.name for p in (out / "renders").glob("*.png")) == ["frame_00000.png", "frame_00005.png"]
    # empty space costs no samples: the occupancy grid skipped some of the intervals placed on the rays
    assert 0 < saved["samples_skipped_fraction"] < 1
    assert saved["samples_per_ray"] == pytest.approx((1 - saved["samples_skipped_fraction"])
                                                     * saved["candidate_samples_per_ray"])
    # for the report: the metrics as a table and the training curve
    assert "PSNR (dB)" in (out / "metrics.html").read_text() and "frame_00005" in (out / "metrics.html").read_text()
    assert (out / "training_curve.svg").read_text().count("<polyline") >= 5
    with pytest.raises(ValueError, match="holdout_every"):
        evaluate(images, labels, trained, tmp_path / "eval2", {"holdout_every": 3}, device=device)


@pytest.mark.bad_input
def test_bad_inputs_name_the_file(scene, tmp_path):
    _, images, _ = scene
    from srfpipe.artifacts import ArtifactError

    with pytest.raises(ArtifactError, match="missing.zarr"):
        train(images, tmp_path / "missing.zarr", tmp_path / "x.zarr", tiny_options(), holdout_every=5)


@pytest.mark.workflow
def test_snakemake_tiny_orchard_to_srf_and_eval(workflow):
    from tests.conftest import TINY_ORCHARD

    scene = {**TINY_ORCHARD, "train": tiny_options(iterations=20, checkpoint_every=10, eval_every=10),
             "evaluate": {"holdout_every": 4}}
    workflow.write_scene("tiny", scene)
    workflow.run("results/tiny/eval")
    root = workflow.root / "results" / "tiny"
    srf = SemanticRadianceField.load(root / "srf.zarr", device="cpu")
    assert srf.classes and srf.attrs["holdout_every"] == 4 and srf.attrs["iterations_done"] == 20
    assert not (root / "srf.ckpt").exists(), "checkpoints are removed after a finished run"
    metrics = json.loads((root / "eval" / "metrics.json").read_text())
    assert metrics["views"] == len(srf.attrs["heldout_views"]) and np.isfinite(metrics["psnr"])
    assert 0 <= metrics["miou_gt"] <= 1 and len(list((root / "eval" / "renders").glob("*.png"))) == metrics["views"]
    for rule in ("train", "evaluate"):
        assert (workflow.root / "logs" / "tiny" / f"{rule}.log").exists()
    assert (workflow.root / "logs" / "tiny" / "train_metrics.jsonl").read_text().strip()


def test_zero_classes_train_colour_only_and_real_captures_get_appearance(tmp_path):
    from srfpipe.segment.composite import composite_masks

    images, _ = write_scene(tmp_path, views=6, width=24, height=16)
    labels = composite_masks(images, [], {}, tmp_path / "labels0.zarr", progress=False)
    out = tmp_path / "srf.zarr"
    summary = train(images, labels, out, tiny_options(iterations=40, checkpoint_every=0), holdout_every=3)
    model, attrs = read_srf(out)
    assert attrs["classes"] == [] and model.field.num_classes == 0
    assert summary["iterations"] == 40
    # the synthetic scene is generated (it has ground truth): no per-image appearance
    assert attrs["config"]["appearance_dim"] == 0 and model.field.appearance is None
    curve = read_curve(out)
    assert curve["psnr"][-1] > curve["psnr"][0] + 3
    field = SemanticRadianceField(model, attrs, torch.device("cpu"))
    pose = np.eye(4)
    render = field.render(pose, [20.0, 20.0, 12.0, 8.0], 24, 16)
    assert render["semantic"].shape == (16, 24, 0)
    assert np.isfinite(render["floater_samples"]).all()


def test_appearance_is_on_by_default_for_real_sequences_only():
    """Per-image appearance where a real capture's images form a sequence (a video: a new view
    borrows its neighbours' appearance); none for photos in no order (each code fits its photo
    alone: the bottle's gap 6.8 dB with, 4.7 without) or for a generated capture."""
    from srfpipe.srf.trainer import resolve_data_defaults

    real = camera_ring_data(100.0, n=24)
    real.bounds_source = "points"
    photos = camera_ring_data(100.0, n=24)
    photos.bounds_source = "points"
    # the same cameras, named in an order that has nothing to do with where they stand
    photos.names = [photos.names[i] for i in np.random.default_rng(0).permutation(24)]
    generated = camera_ring_data(100.0, n=24)
    generated.gt_label, generated.bounds_source = np.zeros((1, 2, 2)), "ground_truth"
    assert resolve_data_defaults({"appearance_dim": None}, real).appearance_dim == 8
    assert resolve_data_defaults({"appearance_dim": None}, photos).appearance_dim == 0
    assert resolve_data_defaults({"appearance_dim": None}, generated).appearance_dim == 0
    assert resolve_data_defaults({"appearance_dim": 4}, real).appearance_dim == 4
    assert resolve_data_defaults({"appearance_dim": 4}, photos).appearance_dim == 4
    # estimated bounds start clearer (less fog to fit the views with) than known ones
    assert resolve_data_defaults({"initial_opacity": None}, real).initial_opacity == 0.001
    assert resolve_data_defaults({"initial_opacity": None}, generated).initial_opacity == 0.01
    assert resolve_data_defaults({"initial_opacity": 0.05}, real).initial_opacity == 0.05


def test_distortion_loss_by_default_only_round_a_subject_in_a_scene():
    """train.distortion null: mip-NeRF 360's distortion loss where the cameras stand round their
    subject in a scene (every such panel capture gained), not for a forward-facing capture (the fern
    lost) or an empty backdrop (the small plant lost 5.5 dB); a weight given is kept."""
    from srfpipe.cameras import look_at
    from srfpipe.srf.trainer import SURROUNDING_SCENE_DISTORTION, resolve_data_defaults

    def looking_at_origin(angles_deg):
        data = camera_ring_data(100.0, n=len(angles_deg))
        data.poses_scene = torch.as_tensor(np.stack([look_at(3.0 * np.array([np.cos(a), np.sin(a), 0.5]), np.zeros(3))
                                                     for a in np.radians(angles_deg)]), dtype=torch.float32)
        return data

    orbit, facing = looking_at_origin(np.arange(0, 360, 30)), looking_at_origin(np.linspace(0, 20, 12))
    # a forward-facing rig with parallel axes (a camera array): its axes meet nowhere
    parallel = camera_ring_data(100.0, n=12)
    parallel.poses_scene = torch.eye(4).repeat(12, 1, 1)
    parallel.poses_scene[:, :2, 3] = torch.tensor([[x, y] for x in np.linspace(-1, 1, 4) for y in np.linspace(-0.5, 0.5, 3)])
    assert SURROUNDING_SCENE_DISTORTION > 0
    assert resolve_data_defaults({"distortion": None}, orbit).distortion == SURROUNDING_SCENE_DISTORTION
    assert resolve_data_defaults({"distortion": None}, facing).distortion == 0.0
    assert resolve_data_defaults({"distortion": None}, parallel).distortion == 0.0
    assert resolve_data_defaults({"distortion": 0.002}, orbit).distortion == 0.002
    orbit.background_empty = True
    assert resolve_data_defaults({"distortion": None}, orbit).distortion == 0.0


def test_the_background_model_reads_the_direction_alone_only_on_an_empty_backdrop():
    """train.background_sh_degree null: on an empty backdrop the background model is most of every
    view, and two bands interpolate it between the training views (the plant +3.2 dB held-out); in
    a scene it keeps the colour's bands (two cost the orchard 0.44 dB); a number given is kept."""
    from srfpipe.srf.trainer import EMPTY_BACKDROP_SH_DEGREE, resolve_data_defaults

    scene = camera_ring_data(100.0)
    assert resolve_data_defaults({"background_sh_degree": None}, scene).background_sh_degree == 4
    assert resolve_data_defaults({"background_sh_degree": None, "sh_degree": 3}, scene).background_sh_degree == 3
    scene.background_empty = True
    assert resolve_data_defaults({"background_sh_degree": None}, scene).background_sh_degree == EMPTY_BACKDROP_SH_DEGREE == 2
    assert resolve_data_defaults({"background_sh_degree": 4}, scene).background_sh_degree == 4


def test_a_background_learning_rate_scale_moves_the_background_model_alone():
    """train.background_lr_scale: the background colour model's parameters, and only those, go to an
    optimizer group of their own at that multiple of the field's rate; at 1 (a scene's) the groups
    are the ones without the key. By default 0.1 on an empty backdrop, 1 in a scene."""
    from srfpipe.srf.model import SRFModel, build_model_config
    from srfpipe.srf.trainer import EMPTY_BACKDROP_BACKGROUND_LR_SCALE, parameter_groups, resolve_data_defaults

    scene = camera_ring_data(100.0)
    assert resolve_data_defaults({}, scene).background_lr_scale == 1.0
    assert resolve_data_defaults({"background_lr_scale": 0.5}, scene).background_lr_scale == 0.5
    scene.background_empty = True
    assert resolve_data_defaults({}, scene).background_lr_scale == EMPTY_BACKDROP_BACKGROUND_LR_SCALE == 0.1
    scene.background_empty = False
    options = {**section_defaults("train"), "default_cells": 16, "outer_resolution": 8, "hidden": 16}
    model = SRFModel(build_model_config(options, scene.bounds_world, scene.scene_from_world, ["a"], 4))
    background = {id(p) for p in model.field.background_mlp.parameters()}
    for scale, apart in ((0.1, True), (1.0, False)):
        groups = parameter_groups(model, 10.0, background_lr_scale=scale)
        grouped = [id(p) for g in groups for p in g["params"]]
        assert sorted(grouped) == sorted(id(p) for p in model.parameters())  # each parameter once
        scales = {id(p): g["lr_scale"] for g in groups for p in g["params"]}
        assert all(scales[i] == scale for i in background)
        assert (sum(set(map(id, g["params"])) == background for g in groups) == 1) == apart
    # one Adam step at a tenth of the rate moves the background model a tenth as far
    moved = {}
    for scale in (1.0, 0.1):
        torch.manual_seed(0)
        model = SRFModel(build_model_config(options, scene.bounds_world, scene.scene_from_world, ["a"], 4))
        groups = parameter_groups(model, 10.0, background_lr_scale=scale)
        optimizer = torch.optim.Adam([{**g, "lr": 1e-2 * g["lr_scale"]} for g in groups])
        before = [p.detach().clone() for p in model.field.background_mlp.parameters()]
        directions = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
        model.field.background(directions).sum().backward()
        optimizer.step()
        moved[scale] = max(float((p - b).abs().max()) for p, b in zip(model.field.background_mlp.parameters(), before))
    assert moved[0.1] == pytest.approx(0.1 * moved[1.0], rel=1e-3)


def test_density_decay_fades_unsupported_density_and_nothing_else():
    """train.density_decay: the dense log-density grids, and only those, get Adam's decoupled weight
    decay; a cell that no ray reaches falls back towards the initial opacity by lr * decay a step,
    while the feature grid and a cell the loss holds up keep their values. Off (0) by default."""
    from srfpipe.srf.model import SRFModel, build_model_config
    from srfpipe.srf.trainer import parameter_groups

    assert section_defaults("train")["density_decay"] == 0.0
    scene = camera_ring_data(100.0)
    options = {**section_defaults("train"), "default_cells": 16, "outer_resolution": 8, "hidden": 16}
    model = SRFModel(build_model_config(options, scene.bounds_world, scene.scene_from_world, ["a"], 4))
    field = model.field
    sigma_tables = [p for g in (field.inner_sigma, field.outer_sigma) if g is not None for p in g.parameters()]
    assert not any("weight_decay" in g for g in parameter_groups(model, 10.0))
    groups = parameter_groups(model, 10.0, density_decay=0.05)
    assert sorted(id(p) for g in groups for p in g["params"]) == sorted(id(p) for p in model.parameters())
    decayed = [g for g in groups if g.get("weight_decay")]
    assert len(decayed) == 1 and {id(p) for p in decayed[0]["params"]} == {id(p) for p in sigma_tables}
    lr = 1e-2
    optimizer = torch.optim.Adam([{**g, "lr": lr * g["lr_scale"]} for g in groups], decoupled_weight_decay=True)
    table = sigma_tables[0]
    with torch.no_grad():
        for p in sigma_tables:
            p.fill_(3.0)  # a log-density well above the initial opacity's
    features = [p.detach().clone() for p in field.inner.parameters()]
    for _ in range(50):  # the loss reaches one cell's value (it wants it at 3) and no other
        optimizer.zero_grad()
        # the feature grid gets a zero gradient, so Adam steps it: only a decay could move it
        untouched = sum((p * 0).sum() for p in field.inner.parameters())
        ((table.view(-1)[0] - 3.0).pow(2) + untouched).backward()
        optimizer.step()
    values = table.detach().view(-1)
    assert float(values[0]) == pytest.approx(3.0, abs=0.1)
    assert float(values[-1]) == pytest.approx(3.0 * (1 - lr * 10.0 * 0.05) ** 50, rel=1e-4)
    assert float(values[-1]) < 2.4
    assert all(torch.equal(p, f) for p, f in zip(field.inner.parameters(), features))


def test_the_background_learning_rate_scale_starts_after_its_share_of_the_run(scene, tmp_path):
    """train.background_lr_after: through a real training step, the background colour model learns
    at the field's rate until that share of the run, then at background_lr_scale times it."""
    from srfpipe.settings import TrainSettings
    from srfpipe.srf import trainer

    folder, images, labels = scene
    assert section_defaults("train")["background_lr_after"] == 0.3
    settings = TrainSettings.from_options(tiny_options(iterations=10, checkpoint_every=0, background_lr_scale=0.1,
                                                       background_lr_after=0.5))
    run = trainer.start_run(images, labels, tmp_path / "srf.zarr", settings, 5, None)
    background = {id(p) for p in run.model.field.background_mlp.parameters()}
    field, = [g for g in run.optimizer.param_groups if g["lr_scale"] == 1.0]
    apart, = [g for g in run.optimizer.param_groups if {id(p) for p in g["params"]} == background]
    rates = []
    for step in range(10):
        trainer.training_step(run, step)
        run.step = step + 1
        rates.append(float(apart["lr"]) / float(field["lr"]))
    assert rates[:5] == pytest.approx([1.0] * 5) and rates[5:] == pytest.approx([0.1] * 5)


def test_background_penalty_only_where_the_capture_says_its_background_is_empty():
    """Masks name only the prompted objects: unless the scene says its background is empty, the
    opacity of unmasked rays is not penalised, whatever the box (a hull box included)."""
    from srfpipe.srf.trainer import EMPTY_BACKGROUND_OPACITY, resolve_data_defaults

    scene = camera_ring_data(100.0)
    scene.classes, scene.bounds_source = ["apple"], "mask_hull"
    assert resolve_data_defaults({"background_opacity": None}, scene).background_opacity == 0.0
    scene.background_empty = True
    assert resolve_data_defaults({"background_opacity": None}, scene).background_opacity == EMPTY_BACKGROUND_OPACITY
    # no backdrop colour recorded (labels.zarr of an older composite): every unmasked ray, as before
    assert resolve_data_defaults({"background_opacity": None}, scene).background_rays == "unmasked"
    scene.classes = []  # nothing marks what is not background
    assert resolve_data_defaults({"background_opacity": None}, scene).background_opacity == 0.0


def test_progress_bar_counts_seconds_of_a_time_budget():
    from srfpipe.srf.hooks import TrainingProgress

    bar = TrainingProgress(0, 3000, 0.0, time_budget=600)
    bar.advance(10, 12.5)
    assert bar.bar.total == 600 and bar.bar.n == pytest.approx(12.5) and bar.postfix["step"] == 10
    bar.advance(2000, 700.0)  # the last step may overrun the budget: the bar stops at 100 %
    assert bar.bar.n == 600
    bar.close()
    steps = TrainingProgress(5, 100, 0.0, time_budget=0)
    steps.advance(6, 1.0)
    assert steps.bar.total == 100 and steps.bar.n == 6
    steps.close()
    endless = TrainingProgress(0, 100, 0.0, time_budget=float("inf"))  # the config refuses it; the hook still counts steps
    endless.advance(7, 1.0)
    assert endless.bar.total == 100 and endless.bar.n == 7
    endless.close()


def camera_ring_data(focal: float, distance: float = 3.0, n: int = 8):
    """What `resolve_data_defaults` reads of a capture: a box of side 2 seen by n cameras on a ring
    at `distance` from its centre, looking at it, with focal length `focal` pixels."""
    from types import SimpleNamespace

    from srfpipe.cameras import look_at, scene_from_world_transform

    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    poses = np.stack([look_at(distance * np.array([np.cos(a), np.sin(a), 0.0]), np.zeros(3)) for a in angles])
    bounds = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    return SimpleNamespace(bounds_world=bounds, scene_from_world=scene_from_world_transform(*bounds),
                           poses_scene=torch.as_tensor(poses, dtype=torch.float32),
                           intrinsics=torch.tensor([[focal, focal, 64.0, 64.0]] * n), width=128, height=128,
                           bounds_source="config", gt_label=None, background_empty=False, classes=[],
                           backdrop=None, multihot=None, probability=None,
                           # frames of an orbit, named in the order they were taken (unpadded numbers)
                           names=[f"frame_{i + 1}" for i in range(n)])


@pytest.mark.parametrize("focal, cells, levels", [(200.0, 96, 1), (300.0, 192, 3), (3000.0, 192, 3),
                                                  (72.0, 48, 1), (20.0, 24, 1)])
def test_grid_follows_the_pixels_a_cell_covers(focal, cells, levels):
    """96 cells over a 2-unit box seen from 3 units: a cell spans focal/144 px. Images at 1-2 px per
    cell keep one 96-cell grid; sharp ones get three levels whose finest approaches a pixel (<= 192);
    a box small in the frame gets one cell per pixel (48 at 0.5 px per cell), at least 24."""
    from srfpipe.srf.trainer import pixels_per_cell, resolve_data_defaults

    data = camera_ring_data(focal)
    assert pixels_per_cell(data, 96) == pytest.approx(focal / 144.0, rel=1e-3)
    options = resolve_data_defaults(section_defaults("train"), data)
    assert (options.default_cells, options.grid_levels) == (cells, levels)
    assert options.features == (16 if levels == 1 else 8)
    chosen = resolve_data_defaults(dict(section_defaults("train"), default_cells=64), data)
    assert (chosen.default_cells, chosen.grid_levels) == (64, 1)  # the scene's own grid stays


def test_a_small_object_gets_its_share_of_every_batch_and_a_large_one_changes_nothing():
    """object_rays: when the classes' pixels are rare (a plant under 1 % of the frame), that share of
    each batch is drawn from them; when they are common, the batch is exactly the uniform one."""
    from types import SimpleNamespace

    from srfpipe.srf.trainer import object_pixels, sample_batch, step_generator

    n, h, w = 4, 40, 50
    multihot = torch.zeros(n, h, w, 1, dtype=torch.uint8)
    multihot[:, 20, 25] = 1  # one pixel a frame: 25 with the 2-pixel dilation, 1.25 % of the pixels
    data = SimpleNamespace(multihot=multihot, probability=None, height=h, width=w, labelled=None, backdrop=None,
                           images=torch.zeros(n, h, w, 3, dtype=torch.uint8),
                           poses_scene=torch.eye(4).repeat(n, 1, 1), intrinsics=torch.tensor([[40.0, 40.0, 25.0, 20.0]] * n))
    views = np.arange(n)
    focus = object_pixels(data, views, 0.1)
    assert focus is not None and [pool.numel() for pool in focus] == [n * 25]
    data.images[:, 18:23, 23:28] = 255  # the object and its 2-pixel margin are white
    rgb = sample_batch(data, views, 1000, step_generator(0, 5), torch.device("cpu"), focus, 0.1)[3]
    assert 0.1 <= float((rgb[:, 0] == 1).float().mean()) <= 0.13  # 100 drawn from it, a few more by chance
    uniform = sample_batch(data, views, 1000, step_generator(0, 5), torch.device("cpu"))[3]
    assert float((uniform[:, 0] == 1).float().mean()) < 0.03
    data.multihot[:, 10:30, 10:40] = 1  # the object fills 30 % of the frame: nothing to do
    assert object_pixels(data, views, 0.1) is None
    data.labelled = np.array([False] * n)  # no frame has masks: nothing to focus on
    data.multihot[:] = 0
    data.multihot[:, 20, 25] = 1
    assert object_pixels(data, views, 0.1) is None


def test_on_an_empty_backdrop_the_focus_finds_the_object_in_frames_without_masks_and_keeps_half_for_the_masks():
    """Labels on a few frames of a capture on an empty backdrop: the frames without masks (and the parts a
    partial mask misses) still get rays, from the pixels that are not the backdrop's colour; the masked
    pixels keep half the focused share however few frames have masks (else the heads see no positives)."""
    from types import SimpleNamespace

    from srfpipe.srf.trainer import object_pixels, sample_batch, step_generator

    n, h, w = 10, 40, 50
    images = torch.zeros(n, h, w, 3, dtype=torch.uint8)
    images[:, 10:30, 25] = 200  # a thin stem, 20 pixels tall, in every frame
    multihot = torch.zeros(n, h, w, 1, dtype=torch.uint8)
    multihot[0, 10:20, 25] = 1  # one frame has a mask, and it marks the stem's upper half only
    data = SimpleNamespace(multihot=multihot, probability=None, height=h, width=w,
                           labelled=np.array([True] + [False] * (n - 1)),
                           images=images, backdrop=None, poses_scene=torch.eye(4).repeat(n, 1, 1),
                           intrinsics=torch.tensor([[40.0, 40.0, 25.0, 20.0]] * n))
    views = np.arange(n)
    alone = object_pixels(data, views, 0.1)
    assert len(alone) == 1 and set((alone[0] // (h * w)).tolist()) == {0}  # no backdrop: the masked frame only
    data.backdrop = ([0.0, 0.0, 0.0], 8.0)
    masked, matter = object_pixels(data, views, 0.1)
    assert torch.equal(masked, alone[0])
    frame, pixel = matter // (h * w), matter % (h * w)
    stem = {v * w + 25 for v in range(10, 30)}
    for view in range(n):  # every frame's whole stem, the part its mask missed included
        assert stem <= set(pixel[frame == view].tolist())
    assert matter.numel() == n * (20 + 4) * 5  # with the 2-pixel margin, and nothing of the backdrop beyond it
    image = sample_batch(data, views, 2000, step_generator(0, 5), torch.device("cpu"), [masked, matter], 0.1)[2]
    assert float((image[-200:] == 0).float().mean()) >= 0.5  # of the 200 focused rays, the masks' 100 (+ 1 in 10)
    diluted = sample_batch(data, views, 2000, step_generator(0, 5), torch.device("cpu"), [matter], 0.1)[2]
    assert float((diluted[-200:] == 0).float().mean()) < 0.2  # one pool of all: 1 in 10 is of the masked frame


def test_pixel_jitter_sends_each_training_ray_through_a_random_point_of_its_own_pixel():
    """train.pixel_jitter: a pixel is the mean over its footprint, so the ray may pass anywhere in it
    (uniformly), never outside it; off, every ray passes through its pixel's centre. The pixels drawn
    are the same either way, and a seed repeats its rays."""
    from types import SimpleNamespace

    from srfpipe.srf.trainer import sample_batch, step_generator

    n, h, w = 3, 40, 50
    fx, fy, cx, cy = 40.0, 45.0, 25.0, 20.0
    data = SimpleNamespace(multihot=None, probability=None, height=h, width=w, labelled=None, backdrop=None,
                           images=torch.randint(0, 255, (n, h, w, 3), dtype=torch.uint8),
                           poses_scene=torch.eye(4).repeat(n, 1, 1), intrinsics=torch.tensor([[fx, fy, cx, cy]] * n))
    views = np.arange(n)

    def crossings(pixel_jitter):
        _, directions, _, rgb, _ = sample_batch(data, views, 4000, step_generator(0, 7), torch.device("cpu"),
                                                pixel_jitter=pixel_jitter)
        # identity poses: the camera frame is the world frame, so the ray meets the image plane here
        return directions[:, 0] / directions[:, 2] * fx + cx, directions[:, 1] / directions[:, 2] * fy + cy, rgb

    x0, y0, rgb0 = crossings(False)
    x, y, rgb = crossings(True)
    assert torch.equal(rgb, rgb0)  # the same pixels
    u, v = torch.floor(x0), torch.floor(y0)
    assert torch.allclose(x0 - u, torch.full_like(x0, 0.5), atol=1e-4)
    assert torch.allclose(y0 - v, torch.full_like(y0, 0.5), atol=1e-4)
    a, b = x - u, y - v  # where in its own pixel each jittered ray passes
    assert float(a.min()) >= -1e-4 and float(a.max()) <= 1 + 1e-4
    assert float(b.min()) >= -1e-4 and float(b.max()) <= 1 + 1e-4
    for offset in (a, b):  # uniform: each quarter of the pixel gets about a quarter of the rays
        counts = torch.histc(offset.clamp(0, 1), bins=4, min=0, max=1)
        assert float(counts.min()) > 0.2 * offset.numel()
    again = crossings(True)
    assert torch.equal(again[0], x) and torch.equal(again[1], y)


def test_supersampled_training_renders_each_pixel_as_evaluate_does_and_fits_its_mean():
    """train.supersample s: a pixel's s x s rays are evaluate's rays of that pixel (`image_rays`), in
    a row, and the photometric loss compares their mean with the pixel: rays that differ inside a
    pixel whose mean is its colour cost nothing, where one ray through its centre would be asked
    for the mean itself."""
    from types import SimpleNamespace

    from srfpipe.srf import losses
    from srfpipe.srf.data import image_rays
    from srfpipe.srf.trainer import loss_terms, sample_batch, step_generator
    from srfpipe.settings import TrainSettings

    n, h, w, s = 2, 12, 16, 2
    k = torch.tensor([20.0, 21.0, 8.0, 6.0])
    pose = torch.eye(4)
    pose[:3, 3] = torch.tensor([0.3, -0.2, 0.1])
    data = SimpleNamespace(multihot=None, probability=None, height=h, width=w, labelled=None, backdrop=None,
                           images=torch.randint(0, 255, (n, h, w, 3), dtype=torch.uint8),
                           poses_scene=pose.repeat(n, 1, 1), intrinsics=k.repeat(n, 1))
    origins, directions, image, rgb, _ = sample_batch(data, np.arange(n), 400, step_generator(0, 3),
                                                      torch.device("cpu"), supersample=s)
    assert directions.shape[0] == 400  # rays_per_batch rays: 100 pixels of 4
    every = image_rays(pose, k, w, h, s)[1].view(h * w, s * s, 3)
    for pixel in range(0, 400, s * s):
        row = directions[pixel:pixel + s * s]
        match = (every - row).abs().amax(dim=(1, 2)) < 1e-6  # the evaluate rays of one pixel, in their order
        assert int(match.sum()) == 1
        v, u = divmod(int(match.nonzero()), w)
        assert torch.equal(rgb[pixel:pixel + s * s], (data.images[image[pixel], v, u].float() / 255).expand(s * s, 3))

    settings = TrainSettings.from_options({"supersample": s, "lambda_sem": 0.0})
    target = torch.tensor([[0.2, 0.4, 0.6]]).repeat(s * s, 1)
    spread = target + torch.tensor([[0.1], [-0.1], [0.05], [-0.05]])  # a pixel's rays differ; their mean is its colour
    outputs = {"rgb": spread, "logits": torch.zeros(s * s, 0)}
    labels = torch.zeros(s * s, 0)
    assert float(loss_terms(settings, None, outputs, target, labels, None, None)["photometric"]) < 1e-12
    centre = settings.replace(supersample=1)
    assert float(loss_terms(centre, None, outputs, target, labels, None, None)["photometric"]) == pytest.approx(
        float(losses.photometric_loss(spread, target)))


def test_rays_per_batch_must_hold_whole_pixels_of_supersampled_rays():
    from srfpipe.config import ConfigError, validate_scene

    with pytest.raises(ConfigError, match="train.rays_per_batch 4098 must be a multiple of train.supersample"):
        validate_scene({"train": {"supersample": 2, "rays_per_batch": 4098}}, "scene.yaml")
    assert validate_scene({"train": {"supersample": 2, "rays_per_batch": 4096}}, "scene.yaml")["train"]["supersample"] == 2
    # settings changed after validation (replace) stop train() before it reads anything
    from srfpipe.settings import TrainSettings
    from srfpipe.srf.trainer import start_run

    settings = TrainSettings.from_options({"supersample": 2}).replace(rays_per_batch=4098)
    with pytest.raises(ValueError, match="train.rays_per_batch 4098 must be a multiple of train.supersample"):
        start_run(Path("missing/images.zarr"), None, Path("missing/srf.zarr"), settings, 8, None)
