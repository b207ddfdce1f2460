"""Security: no pickle where artifacts or checkpoints are read, ONNX models only from the path the
config names, nothing listening on a network port. (Dataset paths that leave the dataset folder
are refused: see test_bad_inputs.py and test_poses.py.)"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import REPO, snakemake_env

SCANNED = ["srfpipe", "benchmarks", "scripts", "workflow", "Snakefile"]
UNSAFE_MODULES = {"pickle", "cPickle", "_pickle", "dill", "cloudpickle", "shelve", "marshal", "joblib"}
LISTENING_MODULES = {"socketserver", "http.server", "xmlrpc.server", "asyncio.start_server"}


def _keyword(call: ast.Call, name: str):
    for keyword in call.keywords:
        if keyword.arg == name:
            return keyword.value.value if isinstance(keyword.value, ast.Constant) else "not a constant"
    return None


def unsafe_calls(source: str, filename: str = "<source>") -> list[str]:
    """Deserialisation that can run code, found in Python source (line: what)."""
    problems = []
    for node in ast.walk(ast.parse(source, filename)):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            for name in names:
                if name.split(".")[0] in UNSAFE_MODULES or name in LISTENING_MODULES:
                    problems.append(f"{filename}:{node.lineno}: imports {name}")
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        dotted = ast.unparse(func)
        last = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
        if dotted == "torch.load" and _keyword(node, "weights_only") is not True:
            problems.append(f"{filename}:{node.lineno}: torch.load without weights_only=True")
        if dotted in ("np.load", "numpy.load") and _keyword(node, "allow_pickle") not in (None, False):
            problems.append(f"{filename}:{node.lineno}: np.load with allow_pickle")
        if dotted in ("yaml.load", "yaml.unsafe_load", "yaml.full_load") or last == "read_pickle":
            problems.append(f"{filename}:{node.lineno}: {dotted}")
        if dotted in ("eval", "exec"):
            problems.append(f"{filename}:{node.lineno}: {dotted}")
        if last in ("listen", "serve_forever", "start_server", "HTTPServer"):
            problems.append(f"{filename}:{node.lineno}: {dotted} (listens on a port)")
    return problems


def python_sources() -> list[Path]:
    files = []
    for name in SCANNED:
        path = REPO / name
        files += [path] if path.is_file() else sorted(path.rglob("*.py")) + sorted(path.rglob("*.smk"))
    return files


def test_the_scanner_finds_what_it_looks_for():
    bad = ("import pickle\nimport torch, numpy as np, yaml\nfrom dill import loads\n"
           "torch.load(p)\ntorch.load(p, weights_only=False)\nnp.load(p, allow_pickle=True)\n"
           "yaml.load(s)\neval('1')\nsock.listen(5)\nimport http.server\n")
    assert len(unsafe_calls(bad)) == 9
    assert unsafe_calls("torch.load(p, weights_only=True)\nnp.load(p)\nnp.load(p, allow_pickle=False)\n"
                        "yaml.safe_load(s)\n") == []


def test_no_pickle_no_unsafe_loading_no_servers_in_the_code():
    problems = []
    for path in python_sources():
        source = path.read_text()
        if path.suffix == ".smk" or path.name == "Snakefile":
            # Snakemake files are Python plus rule blocks: scan their text for the names instead
            problems += [f"{path}: mentions {name}" for name in ("pickle", "torch.load", "allow_pickle=True")
                         if name in source]
            continue
        problems += unsafe_calls(source, str(path.relative_to(REPO)))
    assert not problems, "\n".join(problems)


def test_onnx_models_load_only_from_the_configured_path():
    """Only the segmentation back end creates onnxruntime sessions, from `segmentation.model`
    (resolve_model), and a path the config does not name is never searched for."""
    creators = []
    for path in (REPO / "srfpipe").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and ast.unparse(node.func).endswith(("InferenceSession", "onnx.load")):
                creators.append((path.relative_to(REPO).as_posix(), ast.unparse(node.args[0]) if node.args else ""))
    # train_builtin (the maintainers' script that makes the shipped model) checks the file it wrote
    assert sorted(creators) == [("srfpipe/segment/onnx_backend.py", "str(self.path)"),
                                ("srfpipe/segment/train_builtin.py", "str(path)")], creators

    from srfpipe.segment.onnx_backend import builtin_model_path, resolve_model

    assert resolve_model("builtin") == builtin_model_path()
    with pytest.raises(FileNotFoundError, match="nowhere.onnx: ONNX model file does not exist"):
        resolve_model("nowhere.onnx")


def _listening_inodes() -> set[str]:
    inodes = set()
    for table in ("tcp", "tcp6", "udp", "udp6"):
        path = Path("/proc/net") / table
        if not path.exists():
            continue
        for line in path.read_text().splitlines()[1:]:
            fields = line.split()
            # TCP state 0A is LISTEN; any bound UDP socket receives
            if table.startswith("udp") or fields[3] == "0A":
                inodes.add(fields[9])
    return inodes


def _socket_inodes(pid: int) -> set[str]:
    inodes = set()
    try:
        for fd in os.scandir(f"/proc/{pid}/fd"):
            target = os.readlink(fd.path)
            if target.startswith("socket:["):
                inodes.add(target[8:-1])
    except OSError:
        pass
    return inodes


@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="needs Linux /proc/net")
def test_training_and_segmentation_open_no_listening_socket(tmp_path):
    """Run two stages that load the heavy libraries (torch, onnxruntime) and watch their sockets."""
    from srfpipe.srf.synthetic import write_scene
    from tests.test_segment import red_blue_images, write_images

    images, labels = write_scene(tmp_path, views=6, width=24, height=16)
    options = ('{"iterations": 8, "rays_per_batch": 256, "default_cells": 16, "outer_resolution": 8, '
               '"hidden": 16, "checkpoint_every": 0, "time_budget": 0}')
    stages = [
        ["train", "--images", str(images), "--labels", str(labels), "--out", str(tmp_path / "srf.zarr"),
         "--holdout-every", "3", "--options", options],
        ["segment", "--images", str(write_images(tmp_path / "rb.zarr", red_blue_images(n=4, width=80, height=60))),
         "--prompt", "apple", "--out", str(tmp_path / "apple.zarr")],
    ]
    for args in stages:
        process = subprocess.Popen([sys.executable, "-m", "srfpipe.cli", *args], env=snakemake_env(),
                                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        seen = set()
        while process.poll() is None:
            seen |= _socket_inodes(process.pid) & _listening_inodes()
            time.sleep(0.05)
        assert process.returncode == 0, process.stderr.read()
        assert not seen, f"srfpipe {args[0]} listened on a socket"


@pytest.mark.workflow
@pytest.mark.bad_input
@pytest.mark.hostile
def test_capture_path_with_spaces_quotes_and_substitution_runs_no_shell(workflow):
    """A capture folder named `cap $(touch PWNED) 'q"` builds its poses: every path in every rule is
    quoted, so the shell runs no substitution and splits no argument."""
    from tests.test_poses import ring, write_nerfstudio

    capture = workflow.root / "data" / "cap $(touch PWNED) 'q\""
    write_nerfstudio(capture, ring(4))
    workflow.write_scene("odd", {"source": {"format": "nerfstudio", "path": str(capture)},
                                 "segmentation": {"prompts": []}})
    workflow.run("results/odd/poses.zarr")
    assert (workflow.root / "results" / "odd" / "poses.zarr").is_dir()
    assert not list(workflow.root.rglob("PWNED")) and not (REPO / "PWNED").exists()


@pytest.mark.workflow
@pytest.mark.bad_input
@pytest.mark.hostile
@pytest.mark.parametrize("name", ["..", "x;touch PWNED;y", "a.b", "c++"])
def test_scene_names_that_could_escape_results_are_refused(workflow, name):
    from tests.conftest import TINY_ORCHARD

    workflow.write_scene(name, TINY_ORCHARD)
    result = workflow.run("-n", check=False)
    assert result.returncode != 0
    assert f"scene name {name!r} may hold only letters, digits, '-' and '_'" in result.stdout + result.stderr
    assert not list(workflow.root.rglob("PWNED"))
