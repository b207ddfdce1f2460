"""Damaged artifacts are refused, not used (issue 32).

Every artifact records a manifest of its stored files (size and SHA-256 of each) when its stage
finishes; `open_artifact`, which every next stage uses, checks the files against it. A deleted
chunk would otherwise read as the fill value (zarr's answer to a missing chunk), a flipped bit as
a wrong weight; a truncated zarr.json would give a bare JSON error.
"""

from __future__ import annotations

import json
import logging
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import zarr

from srfpipe.artifacts import (
    MANIFEST_NAME,
    ArtifactError,
    create_artifact,
    open_artifact,
    read_provenance,
    reseal_artifact,
    verify_artifact,
)

pytestmark = [pytest.mark.bad_input, pytest.mark.hostile]

TABLE = np.arange(128, dtype=np.float32).reshape(8, 16) + 1.0  # no chunk all fill value: all are stored


def build(tmp_path: Path, name: str = "srf.zarr", stage: str = "train") -> Path:
    """A small artifact with a multi-chunk array (density/table: chunks c/0/0 .. c/3/0)."""
    path = tmp_path / name
    with create_artifact(path, stage, config={"x": 1}) as group:
        table = group.create_group("density").create_array("table", shape=TABLE.shape, chunks=(2, 16),
                                                            dtype=np.float32)
        table[...] = TABLE
        group.create_array("weights", data=np.random.default_rng(0).random((4, 4)))
    return path


def refused(path: Path, *patterns: str, stage: str | None = "train") -> str:
    """open_artifact(path) raises one line naming the artifact, matching every pattern."""
    with pytest.raises(ArtifactError) as err:
        open_artifact(path, stage=stage)
    message = str(err.value)
    assert "\n" not in message, f"not one line: {message!r}"
    assert str(path) in message, f"the error does not name {path}: {message}"
    for pattern in patterns:
        assert re.search(pattern, message), f"the error does not say {pattern!r}: {message}"
    return message


def flip_bit(file: Path, offset: int | None = None) -> None:
    data = bytearray(file.read_bytes())
    i = len(data) // 2 if offset is None else offset
    data[i] ^= 0x04
    file.write_bytes(bytes(data))


# ------------------------------------------------------------------------------------------ clean


def test_clean_artifact_opens_and_records_its_manifest(tmp_path):
    path = build(tmp_path)
    integrity = read_provenance(path)["integrity"]
    manifest = json.loads((path / MANIFEST_NAME).read_text())
    stored = sorted(p.relative_to(path).as_posix() for p in path.rglob("*") if p.is_file())
    assert sorted(manifest["files"]) == [p for p in stored if p not in ("zarr.json", MANIFEST_NAME)]
    assert [f"density/table/c/{i}/0" for i in range(4)] == [p for p in manifest["files"] if "/table/c/" in p]
    assert integrity["algorithm"] == "sha256" and integrity["files"] == len(manifest["files"])
    assert integrity["bytes"] == sum(e["bytes"] for e in manifest["files"].values())
    assert manifest["nodes"] == {"density": "group", "density/table": "array", "weights": "array"}
    group = open_artifact(path, stage="train")
    np.testing.assert_array_equal(group["density/table"][...], TABLE)
    assert verify_artifact(path)["files"] == integrity["files"]
    # zarr takes the manifest for no node: the group's members are its arrays and groups only
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # zarr notes the file it does not recognise
        assert sorted(name for name, _ in zarr.open_group(str(path), mode="r").members()) == ["density", "weights"]


def test_hidden_os_files_are_ignored(tmp_path):
    """.DS_Store and NFS .nfs* files are no Zarr keys: an artifact browsed in Finder still opens."""
    path = build(tmp_path)
    (path / ".DS_Store").write_bytes(b"finder")
    (path / "density" / "table" / ".DS_Store").write_bytes(b"finder")
    open_artifact(path, stage="train")


def test_verify_false_skips_the_check(tmp_path):
    path = build(tmp_path)
    (path / "density" / "table" / "c" / "2" / "0").unlink()
    group = open_artifact(path, stage="train", verify=False)
    # what a consumer would read without the check: the fill value, silently
    assert not group["density/table"][4:6].any()


# --------------------------------------------------------------------------------------- damaged


def test_deleted_chunk_is_refused_naming_array_and_chunk(tmp_path):
    path = build(tmp_path)
    (path / "density" / "table" / "c" / "2" / "0").unlink()
    message = refused(path, r"array 'density/table' chunk c/2/0 is missing", r"re-run its stage 'train'")
    assert "damaged" in message


def test_deleted_array_is_refused_naming_it(tmp_path):
    import shutil

    path = build(tmp_path)
    shutil.rmtree(path / "density" / "table")
    refused(path, r"array 'density/table' is missing", r"density/table/zarr.json", r"re-run its stage 'train'")


def test_flipped_bit_in_a_chunk_is_refused(tmp_path):
    path = build(tmp_path)
    flip_bit(path / "density" / "table" / "c" / "1" / "0")
    refused(path, r"array 'density/table' chunk c/1/0 does not match its recorded sha256", r"corrupt",
            r"re-run its stage 'train'")


def test_flipped_bit_in_a_weight_is_refused(tmp_path):
    path = build(tmp_path)
    chunk = next((path / "weights" / "c").rglob("*"))
    while chunk.is_dir():
        chunk = next(chunk.iterdir())
    flip_bit(chunk, offset=len(chunk.read_bytes()) - 3)
    refused(path, r"array 'weights' chunk c/0/0 does not match")


def test_truncated_chunk_is_refused(tmp_path):
    path = build(tmp_path)
    chunk = path / "density" / "table" / "c" / "3" / "0"
    chunk.write_bytes(chunk.read_bytes()[:5])
    refused(path, r"array 'density/table' chunk c/3/0 has 5 bytes, its stage wrote \d+ \(truncated")


def test_truncated_array_zarr_json_is_refused_naming_the_file(tmp_path):
    path = build(tmp_path)
    meta = path / "density" / "table" / "zarr.json"
    meta.write_bytes(meta.read_bytes()[:40])
    refused(path, re.escape(str(meta)), r"array 'density/table'", r"truncated")


def test_rewritten_array_zarr_json_of_the_same_size_is_refused(tmp_path):
    path = build(tmp_path)
    meta = path / "density" / "table" / "zarr.json"
    text = meta.read_text()
    meta.write_text(text.replace('"fill_value": 0.0', '"fill_value": 9.0'))
    assert meta.read_text() != text and len(meta.read_text()) == len(text)
    refused(path, re.escape(str(meta)), r"does not match its recorded sha256")


def test_extra_stray_chunk_is_refused(tmp_path):
    path = build(tmp_path)
    (path / "density" / "table" / "c" / "0" / "0").rename(path / "density" / "table" / "c" / "0" / "7")
    (path / "density" / "table" / "c" / "0" / "0").write_bytes((path / "density" / "table" / "c" / "0" / "7").read_bytes())
    refused(path, r"array 'density/table' has an extra chunk c/0/7 that its stage did not write")


def test_extra_array_is_refused(tmp_path):
    path = build(tmp_path)
    zarr.open_group(str(path), mode="r+").create_array("sneaked", data=np.ones(3))
    refused(path, r"array 'sneaked' is not one its stage wrote", r"sneaked/zarr.json")


@pytest.mark.parametrize("damage, problem", [
    ("delete", r"integrity manifest .*srfpipe-manifest.json is missing"),
    ("flip", r"integrity manifest .*does not match the digest recorded in zarr.json"),
    ("truncate", r"integrity manifest .*does not match the digest"),
])
def test_damaged_manifest_is_refused(tmp_path, damage, problem):
    path = build(tmp_path)
    manifest = path / MANIFEST_NAME
    if damage == "delete":
        manifest.unlink()
    elif damage == "flip":
        flip_bit(manifest)
    else:
        manifest.write_bytes(manifest.read_bytes()[:100])
    refused(path, problem, r"re-run its stage 'train'")


def test_invalid_manifest_that_matches_its_digest_is_refused(tmp_path):
    """A manifest whose digest was recorded but whose content is no manifest (a buggy writer)."""
    path = build(tmp_path)
    (path / MANIFEST_NAME).write_text('{"files": 3}')
    reseal = zarr.open_group(str(path), mode="r+")
    attrs = dict(reseal.attrs["srfpipe"])
    import hashlib

    attrs["integrity"] = {**attrs["integrity"], "manifest_sha256": hashlib.sha256(b'{"files": 3}').hexdigest()}
    reseal.attrs["srfpipe"] = attrs
    refused(path, r"integrity manifest .* is invalid")


def test_truncated_root_zarr_json_is_one_line_naming_the_file(tmp_path):
    path = build(tmp_path)
    root = path / "zarr.json"
    root.write_bytes(root.read_bytes()[:60])
    message = refused(path, re.escape(str(root)), r"invalid JSON", r"truncated or corrupt", r"re-run its stage 'train'")
    assert "Traceback" not in message
    with pytest.raises(ArtifactError) as err:
        read_provenance(path)
    assert str(root) in str(err.value) and "\n" not in str(err.value)


def test_every_stored_file_deleted_or_flipped_is_refused(tmp_path):
    """Each file of a real multi-array artifact, deleted and bit-flipped in turn: all refused."""
    path = build(tmp_path)
    files = sorted(json.loads((path / MANIFEST_NAME).read_text())["files"])
    assert len(files) >= 8
    for rel in files:
        file = path / rel
        original = file.read_bytes()
        file.unlink()
        refused(path, re.escape(rel.rsplit("/", 1)[-1]), "missing")
        file.write_bytes(original)
        flip_bit(file)
        refused(path, re.escape(rel.rsplit("/", 1)[-1]), "does not match")
        file.write_bytes(original)
        open_artifact(path, stage="train")


def test_several_problems_are_counted_in_one_line(tmp_path):
    path = build(tmp_path)
    for i in (0, 1, 3):
        (path / "density" / "table" / "c" / str(i) / "0").unlink()
    refused(path, r"chunk c/0/0 is missing", r"2 more damaged files")


# ----------------------------------------------------------------------------- older artifacts


def strip_integrity(path: Path) -> None:
    """Make `path` look written before integrity was recorded."""
    group = zarr.open_group(str(path), mode="r+")
    attrs = dict(group.attrs["srfpipe"])
    del attrs["integrity"]
    group.attrs["srfpipe"] = attrs
    (path / MANIFEST_NAME).unlink()


def test_artifact_without_integrity_opens_with_a_warning(tmp_path, caplog):
    path = build(tmp_path)
    strip_integrity(path)
    with caplog.at_level(logging.WARNING, logger="srfpipe.artifacts"):
        group = open_artifact(path, stage="train")
    np.testing.assert_array_equal(group["density/table"][...], TABLE)
    assert any(str(path) in r.getMessage() and "not verified" in r.getMessage() for r in caplog.records), caplog.text


def test_artifact_without_integrity_still_refuses_a_truncated_zarr_json(tmp_path):
    path = build(tmp_path)
    strip_integrity(path)
    meta = path / "weights" / "zarr.json"
    meta.write_bytes(meta.read_bytes()[:30])
    refused(path, re.escape(str(meta)), "invalid JSON")


def test_reseal_records_a_deliberate_edit(tmp_path):
    path = build(tmp_path)
    zarr.open_group(str(path), mode="r+").create_array("added", data=np.ones(3))
    with pytest.raises(ArtifactError):
        open_artifact(path)
    reseal_artifact(path)
    assert open_artifact(path)["added"][...].sum() == 3


# ------------------------------------------------------------------------------- a real stage


def test_stage_refuses_a_damaged_input_artifact(tmp_path):
    """downscale reads poses.zarr: a deleted chunk of it stops the stage with the clear error, and
    no images.zarr (nor a partial one) is written."""
    from srfpipe.images import downscale_images
    from srfpipe.poses import import_poses
    from tests.test_bad_inputs import capture

    root = capture(tmp_path / "cap")
    poses = import_poses({"format": "nerfstudio"}, root, {}, tmp_path / "poses.zarr", progress=False)
    manifest = json.loads((Path(poses) / MANIFEST_NAME).read_text())
    chunk = next(rel for rel in manifest["files"] if rel.startswith("camera_to_world/c/"))
    (Path(poses) / chunk).unlink()
    out = tmp_path / "images.zarr"
    with pytest.raises(ArtifactError) as err:
        downscale_images(poses, {"downscale": 1}, out, progress=False)
    message = str(err.value)
    assert "\n" not in message and str(poses) in message
    assert f"array 'camera_to_world' chunk {chunk.removeprefix('camera_to_world/')} is missing" in message
    assert "re-run its stage 'poses'" in message
    assert not out.exists() and not list(tmp_path.glob(".images.zarr.*"))


def test_cli_stage_reports_a_damaged_input_in_one_line(tmp_path):
    """`srfpipe downscale` on a damaged poses.zarr: exit 1, one error line, no traceback."""
    import subprocess
    import sys

    from srfpipe.poses import import_poses
    from tests.test_bad_inputs import capture

    root = capture(tmp_path / "cap")
    poses = Path(import_poses({"format": "nerfstudio"}, root, {}, tmp_path / "poses.zarr", progress=False))
    chunk = next(p for p in (poses / "camera_to_world" / "c").rglob("*") if p.is_file())
    flip_bit(chunk)
    out = tmp_path / "images.zarr"
    result = subprocess.run([sys.executable, "-m", "srfpipe.cli", "downscale", "--poses", str(poses), "--out", str(out)],
                            capture_output=True, text=True)
    assert result.returncode == 1, result.stderr
    errors = [line for line in result.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and "Traceback" not in result.stderr, result.stderr
    assert str(poses) in errors[0] and "array 'camera_to_world'" in errors[0] and "re-run its stage 'poses'" in errors[0]
    assert not out.exists()


# ------------------------------------------------------------- artifacts checked against each other


def downscaled(tmp_path: Path, name: str, seed: int) -> Path:
    """A tiny images.zarr-like artifact (stage downscale) whose content depends on `seed`."""
    path = tmp_path / name / "images.zarr"
    with create_artifact(path, "downscale", config={"downscale": 1}) as group:
        group.create_array("images", data=np.random.default_rng(seed).integers(0, 255, (2, 4, 4, 3), dtype=np.uint8))
    return path


def built_from(tmp_path: Path, name: str, *inputs: Path, stage: str = "train") -> Path:
    path = tmp_path / name
    with create_artifact(path, stage, config={}, inputs=list(inputs)) as group:
        group.create_array("weights", data=np.ones(3))
    return path


def mismatch(artifact: Path, given: Path, stage: str, *patterns: str) -> str:
    """require_input refuses `given` in one line naming both files."""
    from srfpipe.artifacts import require_input

    with pytest.raises(ArtifactError) as err:
        require_input(artifact, given, stage)
    message = str(err.value)
    assert "\n" not in message, f"not one line: {message!r}"
    assert str(given) in message and str(artifact) in message, message
    for pattern in patterns:
        assert re.search(pattern, message), f"the error does not say {pattern!r}: {message}"
    return message


def test_inputs_record_their_fingerprint(tmp_path):
    from srfpipe.artifacts import fingerprint

    images = downscaled(tmp_path, "a", 0)
    raw = tmp_path / "model.onnx"
    raw.write_bytes(b"not an artifact")
    srf = built_from(tmp_path, "srf.zarr", images, raw)
    recorded = read_provenance(srf)["inputs"]
    assert recorded[0] == {"path": str(images), "stage": "downscale",
                           "manifest_sha256": read_provenance(images)["integrity"]["manifest_sha256"]}
    assert fingerprint(images) == recorded[0]["manifest_sha256"] and fingerprint(srf) is not None
    assert recorded[1] == {"path": str(raw)}  # a raw input: neither stage nor fingerprint
    strip_integrity(images)  # an input written before integrity was recorded: no fingerprint
    assert "manifest_sha256" not in read_provenance(built_from(tmp_path, "old.zarr", images))["inputs"][0]


def test_an_input_of_another_scene_is_refused_naming_both(tmp_path):
    import shutil

    from srfpipe.artifacts import check_inputs_match, require_input

    a, b = downscaled(tmp_path, "a", 0), downscaled(tmp_path, "b", 1)
    srf = built_from(tmp_path, "srf.zarr", a)
    require_input(srf, a, "downscale")  # the images it was built from
    shutil.copytree(a, tmp_path / "copy" / "images.zarr")  # the same artifact elsewhere: the same fingerprint
    require_input(srf, tmp_path / "copy" / "images.zarr", "downscale")
    message = mismatch(srf, b, "downscale", r"not the images srf\.zarr .* was trained on",
                       r"fingerprint [0-9a-f]{8}\.\., srf\.zarr records [0-9a-f]{8}\.\.", "or retrain")
    assert message.startswith(f"{b}: ")
    with pytest.raises(ArtifactError, match=re.escape(str(b))):
        check_inputs_match(srf, {"downscale": b, "composite": None})
    # rebuilt in place since: the same path, other content
    downscaled(tmp_path, "a", 2)
    mismatch(srf, a, "downscale", "changed since srf.zarr .* was trained on it", "retrain")
    # nothing recorded of that stage, or the wrong kind of artifact: nothing to compare here
    require_input(srf, a, "composite")
    require_input(built_from(tmp_path, "none.zarr"), b, "downscale")


def test_an_input_recorded_without_fingerprint_is_compared_by_path_with_a_warning(tmp_path, caplog):
    from srfpipe.artifacts import require_input

    a, b = downscaled(tmp_path, "a", 0), downscaled(tmp_path, "b", 1)
    srf = built_from(tmp_path, "srf.zarr", a)
    group = zarr.open_group(str(srf), mode="r+")  # as written before fingerprints were recorded
    attrs = dict(group.attrs["srfpipe"])
    attrs["inputs"] = [{"path": str(a), "stage": "downscale"}]
    group.attrs["srfpipe"] = attrs
    with caplog.at_level(logging.WARNING, logger="srfpipe.artifacts"):
        require_input(srf, a, "downscale")
        assert not caplog.records
        require_input(srf, b, "downscale")  # only a warning: a moved results folder is no other scene
    assert len(caplog.records) == 1 and str(b) in caplog.text and str(a) in caplog.text, caplog.text


@pytest.fixture(scope="module")
def two_scenes(tmp_path_factory):
    """Two tiny synthetic captures (cameras at other distances) and a field trained briefly on the first."""
    from srfpipe.config import section_defaults
    from srfpipe.srf.synthetic import write_scene
    from srfpipe.srf.trainer import train

    root = tmp_path_factory.mktemp("two_scenes")
    a = write_scene(root / "a", views=4, width=16, height=12)
    b = write_scene(root / "b", views=4, width=16, height=12, radius=2.6)
    options = section_defaults("train")
    options.update(iterations=4, rays_per_batch=64, default_cells=12, outer_resolution=8, hidden=16,
                   outer_samples=8, before_samples=4, checkpoint_every=0, log_every=2, eval_every=0,
                   occupancy_update_every=2, occupancy_warmup=2, time_budget=0)
    srf = root / "a" / "srf.zarr"
    train(*a, srf, options, holdout_every=2)
    return root, a, b, srf, options


def test_evaluate_refuses_a_field_trained_on_another_scene(two_scenes):
    """issue 32: a field scored against a capture it never saw (mIoU 0.99 of nothing) is refused."""
    from srfpipe.evaluate import evaluate

    root, (images_a, labels_a), (images_b, labels_b), srf, _ = two_scenes
    options = {"holdout_every": 2, "train_views": 1, "supersample": 1}
    with pytest.raises(ArtifactError) as err:
        evaluate(images_b, labels_b, srf, root / "eval_b", options, device="cpu")
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{images_b}: not the images srf.zarr ({srf}) was trained on")
    assert not (root / "eval_b").exists()
    # the right images with the other scene's labels: refused too (srf.zarr records its labels)
    with pytest.raises(ArtifactError, match=re.escape(f"{labels_b}: not the labels srf.zarr ({srf})")):
        evaluate(images_a, labels_b, srf, root / "eval_ab", options, device="cpu")
    metrics = evaluate(images_a, labels_a, srf, root / "eval_a", options, device="cpu")
    assert metrics["views"] == 2 and (root / "eval_a" / "metrics.json").exists()


def test_train_refuses_labels_composited_from_other_images(two_scenes):
    from srfpipe.srf.data import load_posed_images
    from srfpipe.srf.trainer import train

    root, (images_a, labels_a), (images_b, labels_b), _, options = two_scenes
    with pytest.raises(ArtifactError) as err:
        train(images_a, labels_b, root / "mixed.zarr", options, holdout_every=2)
    message = str(err.value)
    assert "\n" not in message and str(images_a) in message and str(labels_b) in message
    assert "not the images labels.zarr" in message and "composited from" in message
    assert not (root / "mixed.zarr").exists()
    assert load_posed_images(images_b, labels_b).count == 4


def test_composite_refuses_masks_segmented_from_other_images(two_scenes):
    from srfpipe.segment.composite import composite_masks

    root, (images_a, _), (images_b, _), _, _ = two_scenes
    names = [f"frame_{i:05d}" for i in range(4)]  # the same frame names and size: only the content differs

    def masks(images: Path, name: str) -> Path:
        path = root / name / "apple.zarr"
        with create_artifact(path, "segment", inputs=[images], prompt="apple", threshold=0.5, names=names) as g:
            g.create_array("probability", data=np.full((4, 12, 16), 255, np.uint8))
        return path

    with pytest.raises(ArtifactError) as err:
        composite_masks(images_a, [masks(images_b, "masks_b")], {}, root / "labels_mixed.zarr", progress=False)
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{images_a}: not the images apple.zarr")
    assert "segmented from" in message and str(root / "masks_b" / "apple.zarr") in message
    composite_masks(images_a, [masks(images_a, "masks_a")], {}, root / "labels_a.zarr", progress=False)


def test_package_refuses_a_field_the_cache_was_not_distilled_from(two_scenes):
    """sim package: occupancy.zarr records the srf.zarr it was distilled from; another field, or the
    images of another scene with the right field, is refused before anything is written."""
    from srfpipe.sim.package import package

    root, (images_a, _), (images_b, labels_b), srf_a, options = two_scenes
    from srfpipe.srf.trainer import train

    srf_b = root / "b" / "srf.zarr"
    train(images_b, labels_b, srf_b, options, holdout_every=2)
    occupancy = built_from(root, "occupancy.zarr", srf_a, stage="distill")
    with pytest.raises(ArtifactError) as err:
        package(occupancy, srf_b, root / "sim_b", {})
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{srf_b}: not the field occupancy.zarr ({occupancy}) "
                                                      f"was distilled from")
    with pytest.raises(ArtifactError, match=re.escape(f"{images_b}: not the images srf.zarr ({srf_a}) was trained on")):
        package(occupancy, srf_a, root / "sim_ab", {}, images_path=images_b)
    # no field given: the images are still checked through the field the cache records
    with pytest.raises(ArtifactError, match=re.escape(f"{images_b}: not the images srf.zarr ({srf_a}) was trained on")):
        package(occupancy, None, root / "sim_nb", {}, images_path=images_b)
    assert not any((root / name).exists() for name in ("sim_b", "sim_ab", "sim_nb"))
