"""Artifacts are written atomically and carry provenance."""

import subprocess
from pathlib import Path

import numpy as np
import pytest

import srfpipe
from srfpipe.artifacts import ArtifactError, create_artifact, open_artifact, read_provenance


def test_artifact_round_trip_with_provenance(tmp_path):
    path = tmp_path / "a.zarr"
    with create_artifact(path, "demo", config={"factor": 4}, inputs=[tmp_path / "raw"]) as group:
        group.create_array("x", data=np.arange(6).reshape(2, 3))
    group = open_artifact(path, stage="demo")
    meta = read_provenance(path)
    assert meta["complete"] and meta["stage"] == "demo" and meta["config"] == {"factor": 4}
    assert meta["versions"]["srfpipe"] and meta["inputs"][0]["path"].endswith("raw")
    np.testing.assert_array_equal(group["x"][:], np.arange(6).reshape(2, 3))


def test_provenance_names_the_source_commit(tmp_path):
    """Two builds of the same development version differ by their commit: the artifact says which."""
    repo = Path(srfpipe.__file__).resolve().parent.parent
    head = subprocess.run(["git", "-C", str(repo), "rev-parse", "--short=12", "HEAD"], capture_output=True, text=True)
    if head.returncode != 0:
        pytest.skip("srfpipe is not running from a git checkout")
    path = tmp_path / "a.zarr"
    with create_artifact(path, "demo", config={}, inputs=[]) as group:
        group.create_array("x", data=np.zeros(1))
    commit = read_provenance(path)["versions"]["srfpipe_commit"]
    assert commit.split("+")[0] == head.stdout.strip() and commit in (head.stdout.strip(), head.stdout.strip() + "+dirty")


def test_interrupted_stage_leaves_nothing(tmp_path):
    path = tmp_path / "a.zarr"
    with pytest.raises(KeyboardInterrupt):
        with create_artifact(path, "demo") as group:
            group.create_array("x", data=np.zeros(3))
            raise KeyboardInterrupt
    assert not path.exists()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.bad_input
def test_an_output_path_holding_something_else_is_refused_not_replaced(tmp_path):
    """`--out data/` (a folder of the user's) or `--out notes.txt` is refused, naming the path, and
    left as it was; an earlier artifact, an empty folder and a missing path are written over."""
    folder = tmp_path / "data"
    folder.mkdir()
    (folder / "keep.txt").write_text("precious")
    plain = tmp_path / "notes.zarr"
    plain.write_text("precious")
    for path in (folder, plain):
        with pytest.raises(FileExistsError, match=f"exists and is .*choose another output path.*{path.name}"):
            with create_artifact(path, "demo") as group:
                group.create_array("x", data=np.zeros(3))
    assert (folder / "keep.txt").read_text() == "precious" and plain.read_text() == "precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "notes.zarr"]  # no partial left
    empty = tmp_path / "empty.zarr"
    empty.mkdir()
    for path in (empty, empty, tmp_path / "new.zarr"):  # the second time over an earlier artifact
        with create_artifact(path, "demo") as group:
            group.create_array("x", data=np.ones(2))
        open_artifact(path, stage="demo")


@pytest.mark.bad_input
def test_wrong_stage_and_missing_artifact_are_clear(tmp_path):
    path = tmp_path / "a.zarr"
    with create_artifact(path, "poses"):
        pass
    with pytest.raises(ArtifactError, match="expected"):
        open_artifact(path, stage="downscale")
    with pytest.raises(ArtifactError, match="does not exist"):
        open_artifact(tmp_path / "missing.zarr")
    (tmp_path / "junk.zarr").mkdir()
    with pytest.raises(ArtifactError, match="junk.zarr"):
        open_artifact(tmp_path / "junk.zarr")


@pytest.mark.bad_input
def test_non_finite_attributes_are_refused(tmp_path):
    with pytest.raises(ValueError, match="non-finite"):
        with create_artifact(tmp_path / "a.zarr", "demo", config={"x": float("nan")}):
            pass
