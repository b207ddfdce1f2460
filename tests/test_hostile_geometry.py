"""Hostile geometry and sizes: captures no camera could have taken, and settings or headers that ask
for more memory than the machine has, are refused at import with the frame (or key) and the reason,
before anything is allocated and without writing an artifact."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from srfpipe import cameras
from srfpipe.images import image_header_size
from srfpipe.memory import MemoryEstimateError
from srfpipe.poses import import_poses
from srfpipe.poses.geometry import lens_valid_fraction
from srfpipe.srf.model import build_model_config
from tests.test_bad_inputs import NERFSTUDIO, assert_refused
from tests.test_poses import edit_transforms, ring, write_nerfstudio

pytestmark = [pytest.mark.bad_input, pytest.mark.hostile]

OPTIONS = {"refine": "none", "min_images": 2}


def imported(tmp_path, **capture):
    root = write_nerfstudio(tmp_path / "cap", capture.pop("poses", ring(6)), **capture)
    out = tmp_path / "poses.zarr"
    return root, out, lambda: import_poses(NERFSTUDIO, root, OPTIONS, out, progress=False)


def test_a_sane_capture_imports(tmp_path):
    _, out, run = imported(tmp_path)
    run()
    assert out.exists()


@pytest.mark.parametrize("capture, problem", [
    ({"intrinsics": (1e-6, 1e-6, 16.0, 12.0)}, r"focal length fx = 1e-06 px .* over 170 degrees"),
    ({"intrinsics": (30.0, 31.0, 1e5, 12.0)}, r"principal point \(100000, 12\) lies far outside"),
    ({"distortion": (1e6, 0.0, 0.0, 0.0)}, r"maps \d+ % of the image's pixels outside it"),
    ({"distortion": (-5.0, 0.0, 0.0, 0.0)}, r"folds the lens over itself"),
])
def test_camera_no_lens_could_be_is_refused_naming_the_frame(tmp_path, capture, problem):
    root, out, run = imported(tmp_path, **capture)
    assert_refused(run, out, "frame_00000.png", problem)


def test_strong_but_real_phone_lens_is_accepted():
    """The fruit capture's calibration (large tangential terms) must stay importable."""
    assert lens_valid_fraction((620.0, 620.0, 302.5, 403.0), (-0.0024, -0.021, 0.011, 0.0096), (605, 806)) > 0.9


def test_colocated_cameras_are_refused(tmp_path):
    poses = ring(6)
    poses[:, :3, 3] = [1.0, 2.0, 3.0]  # every camera at one point, looking around
    root, out, run = imported(tmp_path, poses=poses)
    assert_refused(run, out, "transforms.json", r"all 6 cameras sit at one point")


def test_cameras_facing_away_from_the_bounds_are_refused(tmp_path):
    poses = ring(6) @ np.diag([-1.0, 1.0, -1.0, 1.0])  # turned 180 degrees about their y axis
    root, out, run = imported(tmp_path, poses=poses)
    out_bounds = tmp_path / "poses-bounds.zarr"
    call = lambda: import_poses(NERFSTUDIO, root, {**OPTIONS, "bounds": [[-1, -1, 0], [1, 1, 2]]}, out_bounds,  # noqa: E731
                                progress=False)
    assert_refused(call, out_bounds, "transforms.json", r"6 of 6 cameras see none of the scene bounds")


def test_degenerate_configured_bounds_are_refused(tmp_path):
    root, out, _ = imported(tmp_path)
    call = lambda: import_poses(NERFSTUDIO, root, {**OPTIONS, "bounds": [[0, 0, 0], [1, 1, 1e-9]]}, out,  # noqa: E731
                                progress=False)
    assert_refused(call, out, "transforms.json", r"scene bounds \(config\) .* are degenerate")


def png_header_only(path: Path, width: int, height: int) -> Path:
    """A PNG file whose header claims width x height pixels and whose data is a few bytes."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 16))
                     + chunk(b"IEND", b""))
    return path


def test_image_size_comes_from_the_header(tmp_path):
    assert image_header_size(png_header_only(tmp_path / "big.png", 16384, 12288)) == (16384, 12288)


def test_header_claiming_a_huge_image_is_refused_before_decoding(tmp_path):
    root = write_nerfstudio(tmp_path / "cap", ring(4))
    png_header_only(root / "images" / "frame_00001.png", 60000, 60000)
    edit_transforms(root, lambda d: (d.pop("w"), d.pop("h")))  # sizes from the images' headers
    out = tmp_path / "poses.zarr"
    assert_refused(lambda: import_poses(NERFSTUDIO, root, OPTIONS, out, progress=False), out,
                   "frame_00001.png", r"header claims 60000 x 60000 pixels")


def test_grid_larger_than_memory_is_refused_naming_the_key(monkeypatch):
    monkeypatch.setenv("SRFPIPE_MAX_MEMORY_GB", "1")
    bounds = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    scene = cameras.scene_from_world_transform(bounds[0], bounds[1])
    with pytest.raises(MemoryEstimateError, match=r"train.max_resolution: a 1024 x 1024 x 1024 grid .* needs about "
                                                  r"[\d.]+ GB, more than the 1 GB"):
        build_model_config({"max_resolution": 1024, "default_cells": 1024}, bounds, scene, ["a"], 4)
    config = build_model_config({"max_resolution": 64, "default_cells": 64}, bounds, scene, ["a"], 4)
    assert config["inner"]["resolution"] == [64, 64, 64]
    # a step's batch: every ray holds all its candidate intervals before the occupancy grid culls them
    with pytest.raises(MemoryEstimateError, match=r"train.rays_per_batch: a batch of 50000000 rays of \d+ candidate "
                                                  r"intervals each needs about [\d.]+ GB, more than the 1 GB"):
        build_model_config({"rays_per_batch": 50_000_000, "default_cells": 64}, bounds, scene, ["a"], 4)


def test_whole_grid_distance_larger_than_memory_is_refused_naming_the_key(monkeypatch):
    """package's whole-grid signed distance: a distance transform's working arrays are checked first."""
    from srfpipe.occupancy.distill import signed_distance_field
    from srfpipe.occupancy.grid import VoxelGrid

    monkeypatch.setenv("SRFPIPE_MAX_MEMORY_GB", "0.01")
    grid = VoxelGrid((0.0, 0.0, 0.0), 0.01, (100, 100, 100))
    occupied = np.zeros(grid.shape, dtype=bool)
    with pytest.raises(MemoryEstimateError, match=r"occupancy.voxels_across: the signed distance over the whole "
                                                  r"100 x 100 x 100 voxel grid .* needs about [\d.]+ GB"):
        signed_distance_field(occupied, grid, truncation=0.05)
    monkeypatch.setenv("SRFPIPE_MAX_MEMORY_GB", "1")
    assert signed_distance_field(occupied, grid, truncation=0.05).shape == grid.shape


def test_ray_cast_from_far_away_ends_and_hits(tmp_path):
    """An origin 1e300 away: t + a voxel's nudge equals t in floats, and the octree march used to
    loop forever (a hypothesis example found it); it marches from the box's entry point now."""
    from srfpipe.occupancy import AnalyticField, distill
    from srfpipe.occupancy.cache import OccupancyCache

    field = AnalyticField(["apple"], np.array([[-0.5] * 3, [0.5] * 3])).add_sphere([0.05, 0.0, 0.0], 0.3, "apple")
    cache = OccupancyCache.load(distill(field, tmp_path / "c.zarr", {"voxel_size": 1 / 32, "brick": 16, "avoid": [],
                                                                     "reach": []}, progress=False))
    origins = np.array([[-1e300, 0.0, 0.0], [-1e17, 0.01, 0.0], [-2.0, 0.0, 0.0], [0.9, 0.9, 0.9]])
    t, hit = cache.raycast(origins, np.tile([1.0, 0.0, 0.0], (4, 1)))
    assert hit.tolist() == [0, 0, 0, -1]
    assert t[2] == pytest.approx(1.75, abs=1 / 32) and t[1] == pytest.approx(1e17, rel=1e-12) and np.isinf(t[3])
