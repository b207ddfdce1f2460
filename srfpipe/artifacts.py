"""Zarr artifacts: atomic creation, provenance, and checked opening.

Every stage writes exactly one Zarr group (a directory). Its root attributes carry one versioned
namespace::

    {"srfpipe": {"schema_version": 1, "stage": "downscale", "complete": true,
                 "config": {...values the stage used...},
                 "inputs": [{"path": "results/orchard/poses.zarr", "stage": "poses"}],
                 "versions": {"srfpipe": "0.1.0", "zarr": "3.1.6", ...},
                 "created": "2026-11-22T01:00:00+00:00", ...stage-specific keys...}}

An artifact is built in a hidden sibling directory and renamed into place only when the stage
finishes, so an interrupted stage never leaves anything that a later rule could mistake for done.
"""

from __future__ import annotations

import datetime as _dt
import errno
import functools
import os
import shutil
import socket
import subprocess
import sys
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import zarr

SCHEMA_VERSION = 1
NAMESPACE = "srfpipe"
_VERSIONED_PACKAGES = ("numpy", "zarr", "torch", "cv2", "pycolmap", "onnxruntime", "open3d")


class ArtifactError(RuntimeError):
    """An artifact is missing, incomplete, of the wrong stage or of an unknown schema version."""


@functools.lru_cache(maxsize=1)
def source_commit() -> str | None:
    """The git commit of the srfpipe source this process runs, "+dirty" when the package's tracked
    files differ from it; None outside a git checkout (an installed wheel). A version number alone
    cannot tell two builds of the same development version apart, and benchmark rows that were
    measured in different runs are compared by it."""
    package = Path(__file__).resolve().parent
    try:
        def git(*args: str) -> str:
            return subprocess.run(["git", "-C", str(package), *args], capture_output=True, text=True,
                                  timeout=10, check=True).stdout.strip()

        top = Path(git("rev-parse", "--show-toplevel")).resolve()
        if package.parent != top:  # srfpipe inside some other repository (e.g. a site-packages in one)
            return None
        commit = git("rev-parse", "--short=12", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no", "--", str(package))
    except (OSError, subprocess.SubprocessError):
        return None
    return commit + ("+dirty" if dirty else "")


def package_versions() -> dict[str, str]:
    """Versions of srfpipe and of the heavy libraries this process has imported."""
    from srfpipe import __version__

    versions = {"srfpipe": __version__, "python": sys.version.split()[0]}
    if commit := source_commit():
        versions["srfpipe_commit"] = commit
    for name in _VERSIONED_PACKAGES:
        module = sys.modules.get(name)
        if module is not None:
            versions[name] = str(getattr(module, "__version__", "unknown"))
    return versions


def _jsonable(value: Any) -> Any:
    """Convert numpy scalars/arrays and paths to plain JSON types (Zarr attributes are JSON)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, float) and not np.isfinite(value):
        raise ValueError(f"non-finite value {value!r} cannot be stored in artifact attributes")
    return value


def provenance(stage: str, config: dict | None, inputs: list[str | Path] | None, **extra) -> dict:
    """The `srfpipe` attribute namespace for a new artifact (complete=False until committed)."""
    recorded_inputs = []
    for path in inputs or []:
        entry: dict[str, Any] = {"path": str(path)}
        try:
            entry["stage"] = read_provenance(path).get("stage")
        except (ArtifactError, FileNotFoundError, ValueError, KeyError, OSError):
            pass  # a raw input (a capture folder, a model file) has no provenance of its own
        recorded_inputs.append(entry)
    return _jsonable(
        {
            "schema_version": SCHEMA_VERSION,
            "stage": stage,
            "complete": False,
            "config": config or {},
            "inputs": recorded_inputs,
            "versions": package_versions(),
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            **extra,
        }
    )


_DISK_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EIO, errno.EFBIG)


def _owner_tag() -> str:
    """host-pid: which process a hidden partial/old sibling belongs to."""
    return f"{socket.gethostname().replace('-', '_')}-{os.getpid()}"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_siblings(path: str | Path) -> list[Path]:
    """Delete hidden `.NAME.partial-*` / `.NAME.old-*` siblings of `path` left by a process of
    this host that no longer runs (killed with SIGKILL, out of memory, pre-empted): nothing reads
    them, and they would fill the disk. Another host's, or a live process's, are left alone."""
    path = Path(path)
    removed = []
    host = socket.gethostname().replace("-", "_")
    if not path.parent.is_dir():
        return removed
    for sibling in path.parent.glob(f".{path.name}.*-*"):
        kind, _, tag = sibling.name[len(path.name) + 2:].partition("-")
        parts = tag.split("-")
        if kind not in ("partial", "old") or len(parts) != 3 or parts[0] != host or not parts[1].isdigit():
            continue
        if not _pid_alive(int(parts[1])):
            shutil.rmtree(sibling, ignore_errors=True)
            removed.append(sibling)
    return removed


@contextmanager
def atomic_directory(path: str | Path) -> Iterator[Path]:
    """Yield a hidden temporary sibling of `path` to fill; it becomes `path` only on success.

    An older `path` is moved aside first and deleted after the rename, so a failed re-run leaves
    the previous output intact and an interrupted one leaves nothing that looks complete. The
    hidden names carry host and pid, so a later run removes those of a killed process.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_siblings(path)
    tmp = path.with_name(f".{path.name}.partial-{_owner_tag()}-{uuid.uuid4().hex[:8]}")
    tmp.mkdir()
    try:
        try:
            yield tmp
        except OSError as exc:
            if exc.filename is None and exc.errno in _DISK_ERRORS:  # zarr's stores name no file
                raise OSError(exc.errno, f"{exc.strerror or exc}: writing", str(path)) from exc
            raise
        old = None
        if path.exists():
            old = path.with_name(f".{path.name}.old-{_owner_tag()}-{uuid.uuid4().hex[:8]}")
            os.replace(path, old)
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


@contextmanager
def create_artifact(
    path: str | Path,
    stage: str,
    config: dict | None = None,
    inputs: list[str | Path] | None = None,
    **extra,
) -> Iterator[zarr.Group]:
    """Create a Zarr group at `path` atomically and yield it for writing.

    The group lives in a hidden sibling directory until the `with` block ends without an error;
    then it is marked complete and renamed to `path` (replacing an older artifact). On an error
    the partial directory is deleted and the error propagates.
    """
    with atomic_directory(path) as tmp:
        group = zarr.open_group(str(tmp), mode="w")
        group.attrs[NAMESPACE] = provenance(stage, config, inputs, **extra)
        yield group
        meta = dict(group.attrs[NAMESPACE])
        meta["complete"] = True
        group.attrs[NAMESPACE] = _jsonable(meta)


def update_attrs(group: zarr.Group, **values) -> None:
    """Merge stage-specific keys into the group's `srfpipe` namespace."""
    meta = dict(group.attrs[NAMESPACE])
    meta.update(_jsonable(values))
    group.attrs[NAMESPACE] = meta


def read_provenance(path: str | Path) -> dict:
    """The `srfpipe` namespace of an artifact, without checking it."""
    group = zarr.open_group(str(path), mode="r")
    return dict(group.attrs[NAMESPACE])


def open_artifact(path: str | Path, stage: str | tuple[str, ...] | None = None) -> zarr.Group:
    """Open a finished artifact read-only, with a clear error when it is not one.

    `stage` names the stage (or stages) expected to have written it.
    """
    path = Path(path)
    if not path.exists():
        raise ArtifactError(f"{path}: artifact does not exist")
    try:
        group = zarr.open_group(str(path), mode="r")
        meta = dict(group.attrs[NAMESPACE])
    except Exception as exc:  # zarr raises several types for a folder that is not a group
        raise ArtifactError(f"{path}: not a srfpipe Zarr artifact ({exc})") from exc
    if meta.get("schema_version") != SCHEMA_VERSION:
        written_by = (meta.get("versions") or {}).get("srfpipe", "an unknown srfpipe")
        raise ArtifactError(
            f"{path}: incompatible schema version: found {meta.get('schema_version')!r} (written by srfpipe "
            f"{written_by}), expected {SCHEMA_VERSION}; rebuild it with this srfpipe (delete it and re-run)"
        )
    if not meta.get("complete", False):
        raise ArtifactError(f"{path}: artifact is incomplete (its stage did not finish)")
    expected = (stage,) if isinstance(stage, str) else stage
    if expected is not None and meta.get("stage") not in expected:
        raise ArtifactError(f"{path}: written by stage {meta.get('stage')!r}, expected {expected}")
    return group


def meta(group: zarr.Group) -> dict:
    """The `srfpipe` namespace of an open group."""
    return dict(group.attrs[NAMESPACE])
