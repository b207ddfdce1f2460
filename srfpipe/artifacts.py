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

Integrity: when the stage finishes, every stored file but the root `zarr.json` (which holds these
attributes) is hashed into `srfpipe-manifest.json` at the group root (relative path -> size and
SHA-256; zarr ignores the file), and the attributes record the manifest's own digest::

    "integrity": {"algorithm": "sha256", "manifest": "srfpipe-manifest.json", "files": 41,
                  "bytes": 10485760, "manifest_sha256": "9f86d0..."}

`open_artifact`, which every next stage uses on its inputs, checks the files against it: a deleted
chunk (which zarr would read as the fill value), an extra chunk, a flipped bit or a truncated
`zarr.json` is refused with one line naming the array, the chunk and the stage to re-run.
Artifacts written before this have no `integrity` and open with a logged warning.
"""

from __future__ import annotations

import datetime as _dt
import errno
import functools
import hashlib
import json
import logging
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
import uuid
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import zarr

SCHEMA_VERSION = 1
NAMESPACE = "srfpipe"
_VERSIONED_PACKAGES = ("numpy", "zarr", "torch", "cv2", "pycolmap", "onnxruntime", "open3d")
MANIFEST_NAME = "srfpipe-manifest.json"
MANIFEST_FORMAT = "srfpipe-manifest-1"
INTEGRITY_ALGORITHM = "sha256"
_READ_BLOCK = 1 << 20  # files are hashed in 1 MB reads
_ZARR_JSON = "zarr.json"
FINGERPRINT_KEY = "manifest_sha256"  # an input's fingerprint in `inputs` (its integrity.manifest_sha256)

log = logging.getLogger(__name__)


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
    """The `srfpipe` attribute namespace for a new artifact (complete=False until committed).

    Each input that is itself a srfpipe artifact is recorded with its stage and its fingerprint
    (`manifest_sha256`, the digest of its integrity manifest), so a later stage that is given this
    artifact together with another one can tell whether that is the one it was built from
    (`require_input`). An input written before integrity was recorded gets no fingerprint."""
    recorded_inputs = []
    for path in inputs or []:
        entry: dict[str, Any] = {"path": str(path)}
        try:
            attrs = read_provenance(path)
            entry["stage"] = attrs.get("stage")
        except (ArtifactError, FileNotFoundError, ValueError, KeyError, OSError):
            pass  # a raw input (a capture folder, a model file) has no provenance of its own
        else:
            if digest := fingerprint(attrs):
                entry[FINGERPRINT_KEY] = digest
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


# What an earlier output of a stage holds at its top (any of them): a Zarr group (an artifact, even a
# damaged one or one of another schema), its manifest, eval/'s metrics, sim/'s manifest, a generated
# capture's ground truth, a video's frames record. Anything else at an output path is not replaced.
OUTPUT_MARKERS = (_ZARR_JSON, MANIFEST_NAME, "metrics.json", "scene.json", "ground_truth/scene.json", "frames.json")


def holds_output(path: str | Path) -> bool:
    """`path` is a folder holding a stage's output (one of OUTPUT_MARKERS at its top): what a
    finished stage leaves, since every stage writes its output atomically. An empty folder or a
    plain file at an output path is not one."""
    path = Path(path)
    return path.is_dir() and any(os.path.lexists(path / marker) for marker in OUTPUT_MARKERS)


def check_replaceable(path: str | Path) -> None:
    """Refuse (FileExistsError naming `path`) an output path that holds something no stage wrote:
    a plain file, or a folder that is not empty and holds none of OUTPUT_MARKERS (`--out data/`
    would otherwise be deleted and replaced by the artifact). A missing path, an empty folder and an
    earlier output (complete or not) may be replaced."""
    path = Path(path)
    if not os.path.lexists(path) or holds_output(path):
        return
    if path.is_dir():
        if not any(name != ".snakemake_timestamp" for name in os.listdir(path)):
            return
        what = "a folder that holds no srfpipe output"
    else:
        what = "a file, not a folder"
    raise FileExistsError(errno.EEXIST, f"the output path exists and is {what}; the stage would delete and "
                          "replace it: remove it yourself or choose another output path", str(path))


@contextmanager
def atomic_directory(path: str | Path) -> Iterator[Path]:
    """Yield a hidden temporary sibling of `path` to fill; it becomes `path` only on success.

    An older `path` is moved aside first and deleted after the rename, so a failed re-run leaves
    the previous output intact and an interrupted one leaves nothing that looks complete. The
    hidden names carry host and pid, so a later run removes those of a killed process. A `path`
    that holds something no stage wrote is refused (`check_replaceable`), never replaced.
    """
    path = Path(path)
    check_replaceable(path)
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


# ------------------------------------------------------------------------------------- integrity


def _stored_files(root: Path) -> dict[str, int]:
    """Relative POSIX path -> size of every file under `root`, except the root `zarr.json` (the
    attributes, rewritten while the stage runs) and the manifest itself."""
    found: dict[str, int] = {}
    top = str(root)
    for dirpath, _dirnames, filenames in os.walk(top):
        rel_dir = os.path.relpath(dirpath, top)
        prefix = "" if rel_dir == "." else rel_dir.replace(os.sep, "/") + "/"
        for name in filenames:
            rel = prefix + name
            if rel in (_ZARR_JSON, MANIFEST_NAME):
                continue
            try:
                found[rel] = os.stat(os.path.join(dirpath, name)).st_size
            except FileNotFoundError:  # removed while walking
                continue
    return found


_buffers = threading.local()


def _file_digest(file: str | Path, algorithm: str = INTEGRITY_ALGORITHM) -> str:
    """Hex digest of one file, read in 1 MB blocks (hashlib releases the GIL while it hashes)."""
    buffer = getattr(_buffers, "buffer", None)
    if buffer is None:
        buffer = _buffers.buffer = bytearray(_READ_BLOCK)
    view = memoryview(buffer)
    digest = hashlib.new(algorithm)
    with open(file, "rb", buffering=0) as handle:
        while n := handle.readinto(buffer):
            digest.update(view[:n])
    return digest.hexdigest()


def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of any file's bytes (an ONNX model, a simulator package's files), read as the
    integrity manifest reads an artifact's."""
    return _file_digest(path, "sha256")


def _digest_workers(total_bytes: int, n_files: int) -> int:
    """Threads for hashing: one for small artifacts, else up to 4 (never more than the CPUs)."""
    if total_bytes < (32 << 20) or n_files < 2:
        return 1
    return max(1, min(4, os.cpu_count() or 1, n_files))


def _digests(root: Path, sizes: dict[str, int], algorithm: str = INTEGRITY_ALGORITHM) -> dict[str, str]:
    """Relative path -> hex digest of the files named in `sizes` (largest first, over threads)."""
    order = sorted(sizes, key=lambda rel: -sizes[rel])
    workers = _digest_workers(sum(sizes.values()), len(order))
    if workers == 1:
        return {rel: _file_digest(root / rel, algorithm) for rel in order}
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="srfpipe-verify") as pool:
        return dict(zip(order, pool.map(lambda rel: _file_digest(root / rel, algorithm), order)))


def write_manifest(root: str | Path) -> dict:
    """Hash every stored file of the group at `root` into `srfpipe-manifest.json` there and
    return the `integrity` entry for its attributes (which digests the manifest itself)."""
    root = Path(root)
    sizes = _stored_files(root)
    digests = _digests(root, sizes)
    nodes = {}
    for rel in sizes:
        if rel.endswith("/" + _ZARR_JSON):
            try:
                node_type = json.loads((root / rel).read_bytes()).get("node_type")
            except (ValueError, AttributeError):
                node_type = None
            nodes[rel[: -len(_ZARR_JSON) - 1]] = node_type if node_type in ("array", "group") else "node"
    manifest = {
        "format": MANIFEST_FORMAT,
        "algorithm": INTEGRITY_ALGORITHM,
        "nodes": dict(sorted(nodes.items())),
        "files": {rel: {"bytes": sizes[rel], "digest": digests[rel]} for rel in sorted(sizes)},
    }
    data = (json.dumps(manifest, indent=0, sort_keys=False) + "\n").encode()
    (root / MANIFEST_NAME).write_bytes(data)
    return {
        "algorithm": INTEGRITY_ALGORITHM,
        "manifest": MANIFEST_NAME,
        "files": len(sizes),
        "bytes": int(sum(sizes.values())),
        "manifest_sha256": hashlib.sha256(data).hexdigest(),
    }


def _rerun(stage: Any) -> str:
    if isinstance(stage, str) and stage:
        return f"the artifact is damaged: delete it and re-run its stage {stage!r}"
    return "the artifact is damaged: delete it and re-run the stage that wrote it"


def _describe(path: Path, rel: str, nodes: dict[str, str]) -> tuple[str, str | None, str]:
    """(description, node, key) of a stored file: "array 'density' chunk c/0/3" or "the metadata
    file <path>/density/zarr.json of array 'density'"."""
    parts = rel.split("/")
    for i in range(len(parts) - 1, 0, -1):
        node = "/".join(parts[:i])
        if node in nodes:
            key = "/".join(parts[i:])
            kind = nodes[node]
            if key == _ZARR_JSON:
                return f"{kind} '{node}' metadata file {path / rel}", node, key
            if kind == "array":
                return f"array '{node}' chunk {key}", node, key
            return f"{kind} '{node}' file {key}", node, key
    return f"file {path / rel}", None, rel


def _damage(path: Path, problems: list[str], stage: Any) -> ArtifactError:
    more = len(problems) - 1
    also = f"; {more} more damaged file{'s' if more > 1 else ''}" if more else ""
    return ArtifactError(f"{path}: {problems[0]}{also}; {_rerun(stage)}")


def _read_manifest(path: Path, integrity: Any, stage: Any) -> dict:
    """The manifest of an artifact, checked against the digest its attributes recorded."""
    def refuse(problem: str) -> ArtifactError:
        return ArtifactError(f"{path}: {problem}; {_rerun(stage)}")

    if not isinstance(integrity, dict) or not isinstance(integrity.get("manifest_sha256"), str):
        raise refuse("its recorded integrity entry is invalid (no manifest_sha256)")
    if integrity.get("manifest", MANIFEST_NAME) != MANIFEST_NAME:
        raise refuse(f"its integrity entry names the manifest {integrity.get('manifest')!r}, not {MANIFEST_NAME}")
    file = path / MANIFEST_NAME
    try:
        data = file.read_bytes()
    except FileNotFoundError:
        raise refuse(f"the integrity manifest {file} is missing (deleted)") from None
    except OSError as exc:
        raise refuse(f"the integrity manifest {file} cannot be read ({exc.strerror or exc})") from None
    if hashlib.sha256(data).hexdigest() != integrity["manifest_sha256"]:
        raise refuse(f"the integrity manifest {file} does not match the digest recorded in zarr.json "
                     f"(changed or corrupt)")
    try:
        manifest = json.loads(data)
        algorithm = manifest["algorithm"]
        hashlib.new(algorithm)
        files, nodes = manifest["files"], manifest.get("nodes", {})
        valid = (isinstance(files, dict) and isinstance(nodes, dict)
                 and all(isinstance(e, dict) and isinstance(e.get("bytes"), int) and isinstance(e.get("digest"), str)
                         for e in files.values())
                 and not any(rel.startswith("/") or ".." in rel.split("/") for rel in files))
        if not valid:
            raise ValueError("unexpected layout")
    except (ValueError, KeyError, TypeError) as exc:
        raise refuse(f"the integrity manifest {file} is invalid ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    return manifest


def _outermost(nodes: set[str]) -> list[str]:
    """The nodes of `nodes` that lie inside none of the others, sorted."""
    return sorted(n for n in nodes if not any(n.startswith(other + "/") for other in nodes))


def verify_artifact(path: str | Path, attrs: dict | None = None) -> dict | None:
    """Check every stored file of an artifact against its manifest; raise ArtifactError naming the
    first damaged file (a missing or extra chunk, a changed size or digest). Returns
    {"files", "bytes", "seconds"}, or None for an artifact written before integrity was recorded
    (those are accepted with a logged warning, their zarr.json files only parsed)."""
    started = time.perf_counter()
    path = Path(path)
    attrs = read_provenance(path) if attrs is None else attrs
    stage = attrs.get("stage")
    integrity = attrs.get("integrity")
    if integrity is None:
        _warn_unverified(path, stage)
        _check_metadata_json(path, stage)
        return None
    manifest = _read_manifest(path, integrity, stage)
    expected = {rel: entry["bytes"] for rel, entry in manifest["files"].items()}
    nodes = manifest.get("nodes", {})
    found = _stored_files(path)

    problems: list[str] = []
    missing = sorted(set(expected) - set(found))
    gone_nodes = _outermost({rel[: -len(_ZARR_JSON) - 1] for rel in missing if rel.endswith("/" + _ZARR_JSON)})
    covered = set()
    for node in gone_nodes:
        inside = [rel for rel in missing if rel.startswith(node + "/")]
        covered.update(inside)
        others = len(inside) - 1
        also = f" and its {others} other file{'s' if others > 1 else ''}" if others else ""
        problems.append(f"{nodes.get(node, 'node')} '{node}' is missing (its metadata file {node}/zarr.json{also} "
                        f"deleted)")
    for rel in missing:
        if rel not in covered:
            problems.append(f"{_describe(path, rel, nodes)[0]} is missing (deleted or never written)")
    for rel in sorted(set(expected) & set(found)):
        if found[rel] != expected[rel]:
            problems.append(f"{_describe(path, rel, nodes)[0]} has {found[rel]} bytes, its stage wrote "
                            f"{expected[rel]} (truncated or overwritten)")
    # .DS_Store, ._name, .nfs1234: never a Zarr key, nothing reads them
    extra = [rel for rel in sorted(set(found) - set(expected)) if not rel.rsplit("/", 1)[-1].startswith(".")]
    new_nodes = _outermost({rel[: -len(_ZARR_JSON) - 1] for rel in extra if rel.endswith("/" + _ZARR_JSON)})
    covered = set()
    for node in new_nodes:
        inside = [rel for rel in extra if rel.startswith(node + "/")]
        covered.update(inside)
        try:
            kind = json.loads((path / node / _ZARR_JSON).read_bytes()).get("node_type")
        except (OSError, ValueError, AttributeError):
            kind = None
        others = len(inside) - 1
        also = f" and {others} other file{'s' if others > 1 else ''}" if others else ""
        problems.append(f"{kind if kind in ('array', 'group') else 'node'} '{node}' is not one its stage wrote "
                        f"(an extra {node}/zarr.json{also}: copied in or left by another build)")
    for rel in extra:
        if rel in covered:
            continue
        what, node, key = _describe(path, rel, nodes)
        if node is not None and nodes.get(node) == "array" and key != _ZARR_JSON:
            problems.append(f"array '{node}' has an extra chunk {key} that its stage did not write "
                            f"(copied in or left by another build)")
        else:
            problems.append(f"{what} is not one its stage wrote (an extra file: copied in or left by another build)")
    if problems:
        raise _damage(path, problems, stage)

    try:
        digests = _digests(path, expected, manifest["algorithm"])
    except OSError as exc:
        raise ArtifactError(f"{path}: cannot read {exc.filename or 'a file'} to verify it "
                            f"({exc.strerror or exc}); {_rerun(stage)}") from None
    for rel in sorted(expected):
        if digests[rel] != manifest["files"][rel]["digest"]:
            problems.append(f"{_describe(path, rel, nodes)[0]} does not match its recorded {manifest['algorithm']} "
                            f"digest (corrupt: changed on disk since its stage wrote it)")
    if problems:
        raise _damage(path, problems, stage)
    seconds = time.perf_counter() - started
    total = sum(expected.values())
    log.debug("%s: verified %d files, %d bytes in %.3f s", path, len(expected), total, seconds)
    return {"files": len(expected), "bytes": total, "seconds": seconds}


_warned_unverified: set[str] = set()


def _warn_unverified(path: Path, stage: Any) -> None:
    key = str(path.resolve())
    if key in _warned_unverified:
        return
    _warned_unverified.add(key)
    log.warning("%s: written before srfpipe recorded integrity digests, so its files are not verified "
                "(re-run its stage %r to get a checked artifact)", path, stage)


def _json_problem(file: Path) -> str | None:
    """Why `file` is not valid JSON (one line), or None when it is, or does not exist."""
    try:
        json.loads(file.read_bytes())
    except FileNotFoundError:
        return None
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, UnicodeDecodeError
        return f"{file}: invalid JSON ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__}): truncated or corrupt"
    except OSError as exc:
        return f"{file}: cannot be read ({exc.strerror or exc})"
    return None


def _check_metadata_json(path: Path, stage: Any) -> None:
    """Every node's zarr.json parses (the check an artifact without a manifest still gets)."""
    for dirpath, _dirnames, filenames in os.walk(path):
        if _ZARR_JSON in filenames:
            problem = _json_problem(Path(dirpath) / _ZARR_JSON)
            if problem:
                raise ArtifactError(f"{problem}; {_rerun(stage)}")


# -------------------------------------------------------------------------------------- artifacts


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
    then its files are hashed into the integrity manifest, it is marked complete and renamed to
    `path` (replacing an older artifact). On an error the partial directory is deleted and the
    error propagates.
    """
    with atomic_directory(path) as tmp:
        group = zarr.open_group(str(tmp), mode="w")
        group.attrs[NAMESPACE] = provenance(stage, config, inputs, **extra)
        yield group
        meta = dict(group.attrs[NAMESPACE])
        meta["complete"] = True
        meta["integrity"] = write_manifest(tmp)
        group.attrs[NAMESPACE] = _jsonable(meta)


def reseal_artifact(path: str | Path) -> dict:
    """Record the integrity of a finished artifact again, after it was edited in place on purpose
    (a test that adds an array, a migration). It vouches for whatever the files hold now: never
    use it to make a damaged artifact open."""
    path = Path(path)
    group = zarr.open_group(str(path), mode="r+")
    meta = dict(group.attrs[NAMESPACE])
    meta["integrity"] = write_manifest(path)
    group.attrs[NAMESPACE] = _jsonable(meta)
    return meta["integrity"]


def update_attrs(group: zarr.Group, **values) -> None:
    """Merge stage-specific keys into the group's `srfpipe` namespace."""
    meta = dict(group.attrs[NAMESPACE])
    meta.update(_jsonable(values))
    group.attrs[NAMESPACE] = meta


def _root_json_error(path: Path, stage: Any = None) -> ArtifactError | None:
    """A one-line error when the artifact's root zarr.json is truncated or corrupt."""
    problem = _json_problem(path / _ZARR_JSON)
    return ArtifactError(f"{problem}; {_rerun(stage)}") if problem else None


def read_provenance(path: str | Path) -> dict:
    """The `srfpipe` namespace of an artifact, without checking it."""
    try:
        group = zarr.open_group(str(path), mode="r")
    except Exception as exc:
        error = _root_json_error(Path(path))
        if error is not None:
            raise error from exc
        raise
    return dict(group.attrs[NAMESPACE])


def open_artifact(path: str | Path, stage: str | tuple[str, ...] | None = None, *, verify: bool = True) -> zarr.Group:
    """Open a finished artifact read-only, with a clear error when it is not one.

    `stage` names the stage (or stages) expected to have written it. Its files are verified
    against the integrity manifest its stage recorded (ArtifactError naming the damaged array and
    chunk); `verify=False` skips that, for an artifact this process has just written itself.
    """
    path = Path(path)
    expected = (stage,) if isinstance(stage, str) else stage
    if not path.exists():
        raise ArtifactError(f"{path}: artifact does not exist")
    try:
        group = zarr.open_group(str(path), mode="r")
        meta = dict(group.attrs[NAMESPACE])
    except Exception as exc:  # zarr raises several types for a folder that is not a group
        error = _root_json_error(path, expected[0] if expected and len(expected) == 1 else None)
        if error is not None:
            raise error from exc
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ArtifactError(f"{path}: not a srfpipe Zarr artifact ({reason})") from exc
    if meta.get("schema_version") != SCHEMA_VERSION:
        written_by = (meta.get("versions") or {}).get("srfpipe", "an unknown srfpipe")
        raise ArtifactError(
            f"{path}: incompatible schema version: found {meta.get('schema_version')!r} (written by srfpipe "
            f"{written_by}), expected {SCHEMA_VERSION}; rebuild it with this srfpipe (delete it and re-run)"
        )
    if not meta.get("complete", False):
        raise ArtifactError(f"{path}: artifact is incomplete (its stage did not finish)")
    if expected is not None and meta.get("stage") not in expected:
        raise ArtifactError(f"{path}: written by stage {meta.get('stage')!r}, expected {expected}")
    if verify:
        verify_artifact(path, meta)
    return group


def meta(group: zarr.Group) -> dict:
    """The `srfpipe` namespace of an open group."""
    return dict(group.attrs[NAMESPACE])


# ------------------------------------------------------------------------ inputs that belong together

# how a stage's artifact came from an input (for messages): "the images srf.zarr was trained on"
_BUILT = {"train": "trained on", "composite": "composited from", "segment": "segmented from",
          "distill": "distilled from", "downscale": "downscaled from", "package": "packaged from"}
_WHAT = {"downscale": "images", "composite": "labels", "segment": "masks", "train": "field",
         "distill": "occupancy cache", "poses": "poses"}


def fingerprint(artifact: str | Path | dict) -> str | None:
    """An artifact's fingerprint: the SHA-256 of its integrity manifest (`integrity.manifest_sha256`),
    which covers every stored file but the root attributes. `artifact` is a path or its `srfpipe`
    attributes; None for an artifact written before integrity was recorded."""
    attrs = read_provenance(artifact) if not isinstance(artifact, dict) else artifact
    integrity = attrs.get("integrity")
    digest = integrity.get(FINGERPRINT_KEY) if isinstance(integrity, dict) else None
    return digest if isinstance(digest, str) and digest else None


def _resolved(path: str | Path) -> Path:
    try:
        return Path(path).resolve()
    except (OSError, RuntimeError):
        return Path(os.path.abspath(path))


def require_input(artifact: str | Path, given: str | Path, stage: str) -> None:
    """Refuse `given` (an artifact of stage `stage`) when `artifact` records an input of that stage
    and `given` is not it: a stage that consumes `artifact` together with `given` (evaluate: srf.zarr
    with images.zarr) would otherwise mix two scenes without a word.

    The recorded inputs' fingerprints (see `provenance`) are compared with `given`'s: a different one
    raises ArtifactError, one line naming both files. An input recorded without a fingerprint (an
    artifact written before they were recorded) is compared by resolved path, and a different path
    only logs a warning (a copied or moved results folder is still the same artifact). Nothing is
    checked when `artifact` records no input of that stage, or when either cannot be read (the
    stage's own `open_artifact` reports that)."""
    artifact, given = Path(artifact), Path(given)
    try:
        attrs = read_provenance(artifact)
        given_attrs = read_provenance(given)
    except Exception:  # missing, not an artifact, damaged: open_artifact says so in its own words
        return
    if given_attrs.get("stage") != stage:
        return  # the wrong kind of artifact altogether: open_artifact(given, stage) refuses it
    recorded = [entry for entry in attrs.get("inputs") or []
                if isinstance(entry, dict) and entry.get("stage") == stage and isinstance(entry.get("path"), str)]
    if not recorded:
        return
    given_print = fingerprint(given_attrs)
    prints = [entry[FINGERPRINT_KEY] for entry in recorded if isinstance(entry.get(FINGERPRINT_KEY), str)]
    if given_print is not None and given_print in prints:
        return
    here = _resolved(given)
    unprinted = [entry["path"] for entry in recorded if not isinstance(entry.get(FINGERPRINT_KEY), str)]
    if any(_resolved(path) == here for path in unprinted):
        return
    what = _WHAT.get(stage, f"{stage} artifact")
    built = _BUILT.get(str(attrs.get("stage")), "built from")
    redo = "retrain" if attrs.get("stage") == "train" else f"rebuild {artifact.name} from it"
    if not unprinted:  # every candidate has a fingerprint, and none is this one's
        shown = "none" if given_print is None else given_print[:8] + ".."
        same_path = [entry for entry in recorded if _resolved(entry["path"]) == here]
        if same_path:
            raise ArtifactError(f"{given}: changed since {artifact.name} ({artifact}) was {built} it (fingerprint "
                                f"{shown}, {artifact.name} records {same_path[0][FINGERPRINT_KEY][:8]}..): {redo}")
        raise ArtifactError(f"{given}: not the {what} {artifact.name} ({artifact}) was {built} (fingerprint {shown}, "
                            f"{artifact.name} records {prints[0][:8]}..): pass the {given.name} of the same "
                            f"scene, or {redo}")
    log.warning("%s: %s (%s) was %s %s, not this file (recorded without a fingerprint, so only the paths "
                "can be compared): make sure both are of the same scene", given, artifact.name, artifact, built,
                " / ".join(unprinted))


def recorded_input(artifact: str | Path, stage: str) -> Path | None:
    """The path `artifact` records as its input of stage `stage` (the first), or None."""
    try:
        attrs = read_provenance(Path(artifact))
    except Exception:  # open_artifact reports an unreadable artifact in its own words
        return None
    for entry in attrs.get("inputs") or []:
        if isinstance(entry, dict) and entry.get("stage") == stage and isinstance(entry.get("path"), str):
            return Path(entry["path"])
    return None


def check_inputs_match(artifact: str | Path, given: dict[str, str | Path | None]) -> None:
    """`require_input(artifact, path, stage)` for each stage -> path of `given` (None: not given)."""
    for stage, path in given.items():
        if path is not None:
            require_input(artifact, path, stage)
