"""The pure helpers of benchmarks/peers.py (srfpipe against nerfacto): clocks, crossing times,
metrics and camera axes. nerfstudio is not needed (nor imported)."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import peers  # noqa: E402

from srfpipe.srf import metrics  # noqa: E402


def test_iteration_clock_sums_running_means_window_by_window():
    rng = np.random.default_rng(0)
    durations = rng.uniform(0.3, 0.9, size=57)
    window = 20
    # nerfstudio's ITER_TRAIN_TIME: the mean of the last `window` durations, logged at every step
    means = [float(durations[max(0, k - window + 1): k + 1].mean()) for k in range(len(durations))]
    clock = peers.iteration_clock(list(range(len(means))), means, window)
    assert clock[0] == pytest.approx(durations[0])
    for step in (5, 19, 20, 39, 40, 56):
        assert clock[step] == pytest.approx(durations[: step + 1].sum(), rel=1e-12)
    with pytest.raises(ValueError, match="every step"):
        peers.iteration_clock([0, 2], [0.5, 0.5], window)


def test_crossing_time_interpolates_between_the_points_around_the_target():
    points = {60.0: 20.0, 120.0: 22.0, 300.0: 24.0}
    assert peers.crossing_time(points, 23.0) == (pytest.approx(210.0), "interpolated")
    assert peers.crossing_time(points, 24.0)[0] == pytest.approx(300.0)
    assert peers.crossing_time(points, 19.0) == (60.0, "upper bound: the first evaluated point")
    assert peers.crossing_time(points, 25.0) == (None, "not reached")


def test_refine_crossing_bisects_towards_the_first_point_at_the_target():
    def curve(t):  # rises, crosses 21 dB at t = 25
        return 20.0 + t / 25.0

    available = [float(t) for t in range(10, 301, 10)]
    points = {60.0: curve(60), 120.0: curve(120)}
    calls = peers.refine_crossing(available, points, 21.0, curve, max_evaluations=10)
    seconds, how = peers.crossing_time(points, 21.0)
    assert how == "interpolated" and seconds == pytest.approx(25.0)
    assert {20.0, 30.0} <= set(points) and calls <= 4  # log2 of the 5 candidates below 60 s, plus one
    # nothing to refine: no point reaches the target
    assert peers.refine_crossing(available, {60.0: 1.0}, 21.0, curve, 5) == 0


def test_image_metrics_pool_the_squared_error_like_srfpipe_evaluate():
    rng = np.random.default_rng(1)
    targets = [rng.integers(0, 256, (12, 16, 3), dtype=np.uint8) for _ in range(3)]
    renders = [np.clip(t / 255.0 + rng.normal(0, s, t.shape), 0, 1).astype(np.float32)
               for t, s in zip(targets, (0.01, 0.05, 0.1))]
    result = peers.image_metrics(renders, targets)
    squared = sum(((r.astype(np.float64) - t / 255.0) ** 2).sum() for r, t in zip(renders, targets))
    assert result["psnr"] == pytest.approx(-10 * np.log10(squared / (3 * 12 * 16 * 3)))
    assert result["ssim"] == pytest.approx(np.mean([metrics.ssim(r, t / 255.0) for r, t in zip(renders, targets)]))
    with pytest.raises(ValueError, match="differ"):
        peers.image_metrics([renders[0][:-1]], [targets[0]])


def test_opengl_axes_look_along_minus_z_and_keep_the_centre():
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 2.0, 3.0]
    gl = peers.opengl_from_opencv(pose)
    forward_cv = pose[:3, :3] @ [0, 0, 1]
    assert np.allclose(gl[:3, :3] @ [0, 0, -1], forward_cv) and np.allclose(gl[:3, :3] @ [0, 1, 0], -pose[:3, 1])
    assert np.allclose(gl[:3, 3], pose[:3, 3])


def test_snapshot_marks_hold_the_budgets_and_a_finer_grid_early():
    marks = peers.snapshot_marks([60, 120, 300, 600])
    assert {60.0, 120.0, 300.0, 600.0} <= set(marks) and marks == sorted(set(marks))
    assert marks[:3] == [10.0, 20.0, 30.0] and max(marks) == 600.0
    assert peers.nearest({"a": 58.0, "b": 61.0, "c": 90.0}, 60) == "b"


def test_pruning_keeps_only_the_evaluated_checkpoints(tmp_path):
    # a 10-minute nerfacto run saves ~60 MB every 20 steps: the panel keeps what it evaluated
    files = {}
    for step in range(0, 100, 20):
        path = tmp_path / f"step-{step:09d}.ckpt"
        path.write_bytes(b"x")
        files[str(path)] = step * 0.5
    kept = peers.prune_checkpoints(files, {"step-000000020.ckpt", "step-000000080.ckpt"})
    assert kept == ["step-000000020.ckpt", "step-000000080.ckpt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == kept
    assert Path(peers.by_name(files, "step-000000080.ckpt")).name == "step-000000080.ckpt"
