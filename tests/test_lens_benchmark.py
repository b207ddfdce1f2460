"""benchmarks/lens.py's own pieces: the capture it misstates and the ray error it reports."""

import json
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import lens  # noqa: E402


def test_the_misstated_capture_claims_the_lens_without_its_tangential_terms(tmp_path):
    (tmp_path / "transforms.json").write_text(json.dumps({"fl_x": 500.0, "k1": -0.0024, "k2": -0.021, "p1": 0.011,
                                                          "p2": 0.0096, "frames": [{"file_path": "images/a.png"}]}))
    lens.misstate_lens(tmp_path, lens.CLAIMED_LENS)
    written = json.loads((tmp_path / "transforms.json").read_text())
    assert [written[k] for k in ("k1", "k2", "p1", "p2")] == [-0.0024, -0.021, 0.0, 0.0]
    assert written["fl_x"] == 500.0 and written["frames"] == [{"file_path": "images/a.png"}]
    # a re-run leaves a capture that already claims it untouched, so Snakemake rebuilds nothing
    stamp = (tmp_path / "transforms.json").stat().st_mtime_ns
    lens.misstate_lens(tmp_path, lens.CLAIMED_LENS)
    assert (tmp_path / "transforms.json").stat().st_mtime_ns == stamp


def test_pixel_shift_is_where_the_wrong_lens_puts_a_pixel():
    """The corner pixel, its direction found through the true lens by OpenCV, projected through the
    claimed lens by OpenCV: the benchmark's largest shift is that corner's (within a pixel)."""
    intrinsics, size = np.array([524.0, 524.0, 302.5, 403.0]), (605, 806)
    assert max(lens.pixel_shift_px(intrinsics, size, lens.PHONE_LENS, lens.PHONE_LENS)) < 1e-3
    mean, largest = lens.pixel_shift_px(intrinsics, size, lens.PHONE_LENS, lens.CLAIMED_LENS)
    k = np.array([[524.0, 0, 302.0], [0, 524.0, 402.5], [0, 0, 1]])  # OpenCV's pixel centres are integers
    shifts = []
    for corner in ([0.0, 0.0], [604.0, 0.0], [0.0, 805.0], [604.0, 805.0]):
        converged = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        normalized = cv2.undistortPoints(np.array([[corner]]), k, np.array(lens.PHONE_LENS), None, np.eye(3),
                                         np.eye(3), converged)
        moved, _ = cv2.projectPoints(np.array([[*normalized[0, 0], 1.0]]), np.zeros(3), np.zeros(3), k,
                                     np.array(lens.CLAIMED_LENS, dtype=np.float64))
        shifts.append(float(np.linalg.norm(moved[0, 0] - corner)))
    assert 2.0 < mean < largest and abs(largest - max(shifts)) < 1.0
