"""Provenance records: what a stage read, what it wrote, with which config, code and library versions.

Every stage output directory holds a ``manifest.json`` (a :class:`Manifest`) next to its ``config.yaml``.
The manifest lists every output file with its sha256 and size, every input file with its sha256, the config
hash, the git commit of the code, the versions of the main libraries and the command line, so that any
number in the paper reproduction can be traced back to how it was made.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import importlib.metadata
import json
import os
import platform
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.core.artifacts import atomic_write_json
from pipeline.core.errors import CorruptArtifactError, InputMissingError

MANIFEST_NAME = "manifest.json"
_CHUNK_BYTES = 1 << 20

VERSIONED_PACKAGES: tuple[str, ...] = (
    "numpy",
    "scipy",
    "torch",
    "torchvision",
    "pybullet",
    "gymnasium",
    "stable-baselines3",
    "lerobot",
    "mcap",
    "datasets",
    "opencv-python-headless",
)


@dataclass(frozen=True)
class FileRecord:
    """One file: its path, content hash and size.

    Attributes:
        path: POSIX path, relative to the directory it was listed from (or as given, for inputs).
        sha256: Hex sha256 of the content.
        bytes: Size in bytes.
    """

    path: str
    sha256: str
    bytes: int

    def to_dict(self) -> dict[str, Any]:
        """Returns the record as a JSON-able dict."""
        return {"path": self.path, "sha256": self.sha256, "bytes": self.bytes}


def hash_file(path: Path) -> str:
    """Returns the hex sha256 of a file, read in 1 MiB chunks.

    Args:
        path: File to hash.

    Raises:
        InputMissingError: The file does not exist.
    """
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            while chunk := f.read(_CHUNK_BYTES):
                h.update(chunk)
    except FileNotFoundError:
        raise InputMissingError(f"cannot hash missing file: {path}") from None
    return h.hexdigest()


def hash_tree(
    root: Path, exclude: set[str] | frozenset[str] = frozenset({MANIFEST_NAME})
) -> list[FileRecord]:
    """Hashes every file under ``root``.

    Args:
        root: Directory to walk (symlinked directories are not followed; symlinked files are read through).
        exclude: Relative POSIX paths to leave out (by default the top-level ``manifest.json``).

    Returns:
        One record per file, sorted by path, with paths relative to ``root``.

    Raises:
        InputMissingError: ``root`` is not a directory.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputMissingError(f"cannot hash missing directory: {root}")
    records: list[FileRecord] = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames.sort()
        for name in filenames:
            full = Path(dirpath) / name
            rel = full.relative_to(root).as_posix()
            if rel in exclude or not full.is_file():
                continue
            records.append(FileRecord(path=rel, sha256=hash_file(full), bytes=full.stat().st_size))
    records.sort(key=lambda r: r.path)
    return records


@functools.lru_cache(maxsize=1)
def _collect_versions_cached() -> tuple[tuple[str, str], ...]:
    versions: dict[str, str] = {"python": platform.python_version(), "platform": platform.platform()}
    for name in VERSIONED_PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            continue
    return tuple(versions.items())


def collect_versions() -> dict[str, str]:
    """Returns the Python version, the platform and the installed versions of the main libraries.

    Library versions come from package metadata (nothing is imported); packages that are not installed are
    left out.
    """
    return dict(_collect_versions_cached())


def git_info(start: Path) -> tuple[str, bool]:
    """Returns the git commit and dirty flag of the repository containing ``start``.

    Args:
        start: A file or directory inside the work tree.

    Returns:
        ``(commit_hash, dirty)``; ``("unknown", False)`` when ``start`` is not in a git repository, the
        repository has no commit yet, or git is not installed.
    """
    where = Path(start)
    while not where.exists() and where != where.parent:
        where = where.parent
    if where.is_file():
        where = where.parent

    def _git(*args: str) -> str | None:
        try:
            proc = subprocess.run(
                ["git", "-C", str(where), *args], capture_output=True, text=True, timeout=30, check=False
            )
        except (OSError, subprocess.SubprocessError):
            return None
        return proc.stdout if proc.returncode == 0 else None

    commit = _git("rev-parse", "HEAD")
    if commit is None or not commit.strip():
        return "unknown", False
    status = _git("status", "--porcelain")
    return commit.strip(), bool(status and status.strip())


def _expect(cond: bool, path: Path, what: str) -> None:
    if not cond:
        raise CorruptArtifactError(f"corrupt manifest {path}: {what}")


def _records_from(value: Any, path: Path, key: str) -> list[FileRecord]:
    _expect(isinstance(value, list), path, f"field '{key}' must be a list, got {type(value).__name__}")
    records = []
    for i, item in enumerate(value):
        ok = (
            isinstance(item, dict)
            and isinstance(item.get("path"), str)
            and isinstance(item.get("sha256"), str)
            and isinstance(item.get("bytes"), int)
            and not isinstance(item.get("bytes"), bool)
        )
        _expect(ok, path, f"{key}[{i}] must be {{path: str, sha256: str, bytes: int}}, got {item!r}")
        records.append(FileRecord(path=item["path"], sha256=item["sha256"], bytes=item["bytes"]))
    return records


_OPTIONAL_FIELDS = ("code_hash", "wall_total_s", "invocations")  # absent from manifests of older code


@dataclass
class Manifest:
    """Provenance of one stage output directory (stored as ``manifest.json`` inside it).

    Attributes:
        stage: Name of the stage (its CLI verb).
        params: The resolved config (``to_dict`` of the stage config).
        config_hash: ``config_hash`` of the stage config.
        seed: The run's seed, if any.
        inputs: Input files; paths relative to the data dir when inside it, else as given.
        outputs: Output files, relative to the output directory (``manifest.json`` itself excluded).
        counts: Summary numbers returned by the stage (episodes, frames, success rate, ...).
        created_utc: ISO-8601 UTC time the manifest was written.
        git_commit: Commit of the code, or ``"unknown"``.
        git_dirty: Whether the work tree had uncommitted changes.
        versions: Python, platform and library versions.
        duration_s: Wall time of the invocation that finished the output, in seconds.
        wall_total_s: Wall time of every invocation that built the output (a ``--resume`` continues an output in
            place: each earlier invocation that finished counts its wall, a killed or failed one its time until its
            last write to the output, so this is a lower bound after a kill); ``duration_s`` for a one-run output.
        invocations: How many invocations built the output (1 unless resumed).
        command: The command line that ran the stage.
        code_hash: sha256 over the pipeline's own source files (:func:`code_hash`); a change makes outputs stale.
    """

    stage: str
    params: dict[str, Any]
    config_hash: str
    seed: int | None
    inputs: list[FileRecord] = field(default_factory=list)
    outputs: list[FileRecord] = field(default_factory=list)
    counts: dict[str, float | int | str] = field(default_factory=dict)
    created_utc: str = ""
    git_commit: str = "unknown"
    git_dirty: bool = False
    versions: dict[str, str] = field(default_factory=dict)
    duration_s: float = 0.0
    command: list[str] = field(default_factory=list)
    code_hash: str = ""
    wall_total_s: float = 0.0
    invocations: int = 1

    def __post_init__(self) -> None:
        self.wall_total_s = self.wall_total_s or self.duration_s  # not given: the one invocation's wall

    def to_dict(self) -> dict[str, Any]:
        """Returns the manifest as a JSON-able dict."""
        data = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        data["inputs"] = [r.to_dict() for r in self.inputs]
        data["outputs"] = [r.to_dict() for r in self.outputs]
        return data

    def write(self, path: Path) -> Path:
        """Writes the manifest atomically as JSON (indent 2, sorted keys).

        Args:
            path: Destination, normally ``<output_dir>/manifest.json``.

        Returns:
            ``path``.
        """
        return atomic_write_json(Path(path), self.to_dict())

    @classmethod
    def from_dict(cls, data: Any, path: Path) -> Manifest:
        """Builds a manifest from parsed JSON, checking every field.

        Args:
            data: Parsed JSON content.
            path: The file it came from (for error messages).

        Raises:
            CorruptArtifactError: A field is missing or has the wrong type.
        """
        _expect(isinstance(data, dict), path, f"expected a JSON object, got {type(data).__name__}")
        names = [f.name for f in dataclasses.fields(cls)]
        missing = [n for n in names if n not in data and n not in _OPTIONAL_FIELDS]
        _expect(not missing, path, f"missing field(s) {', '.join(missing)}")

        def typed(key: str, types: type | tuple[type, ...], desc: str) -> Any:
            value = data[key]
            bad_bool = isinstance(value, bool) and bool not in (
                types if isinstance(types, tuple) else (types,)
            )
            _expect(
                isinstance(value, types) and not bad_bool,
                path,
                f"field '{key}' must be {desc}, got {value!r} ({type(value).__name__})",
            )
            return value

        counts = typed("counts", dict, "an object")
        for k, v in counts.items():
            _expect(
                isinstance(v, int | float | str), path, f"counts['{k}'] must be a number or string, got {v!r}"
            )
        versions = typed("versions", dict, "an object")
        command = typed("command", list, "a list of strings")
        _expect(all(isinstance(c, str) for c in command), path, "field 'command' must be a list of strings")
        seed = data["seed"]
        _expect(
            seed is None or (isinstance(seed, int) and not isinstance(seed, bool)),
            path,
            f"field 'seed' must be an int or null, got {seed!r}",
        )
        duration_s = float(typed("duration_s", (int, float), "a number"))
        return cls(
            stage=typed("stage", str, "a string"),
            params=typed("params", dict, "an object"),
            config_hash=typed("config_hash", str, "a string"),
            seed=seed,
            inputs=_records_from(data["inputs"], path, "inputs"),
            outputs=_records_from(data["outputs"], path, "outputs"),
            counts=dict(counts),
            created_utc=typed("created_utc", str, "a string"),
            git_commit=typed("git_commit", str, "a string"),
            git_dirty=typed("git_dirty", bool, "a bool"),
            versions={str(k): str(v) for k, v in versions.items()},
            duration_s=duration_s,
            command=list(command),
            code_hash=str(data.get("code_hash", "")),
            # manifests written before these fields: one invocation, its own wall
            wall_total_s=float(typed("wall_total_s", (int, float), "a number")) if "wall_total_s" in data
            else duration_s,
            invocations=typed("invocations", int, "an int") if "invocations" in data else 1,
        )

    @classmethod
    def read(cls, path: Path) -> Manifest:
        """Reads and checks a ``manifest.json``.

        Args:
            path: The manifest file.

        Raises:
            InputMissingError: The file does not exist.
            CorruptArtifactError: The file is not valid JSON or a field is missing or mistyped.
        """
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise InputMissingError(f"missing manifest: {path}") from None
        except (UnicodeDecodeError, IsADirectoryError) as e:
            raise CorruptArtifactError(
                f"corrupt manifest {path}: cannot read it as UTF-8 text ({e})"
            ) from None
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise CorruptArtifactError(
                f"corrupt manifest {path}: invalid JSON at line {e.lineno} column {e.colno} ({e.msg})"
            ) from None
        return cls.from_dict(data, path)


CONFIG_NAME = "config.yaml"  # the resolved config, written next to every manifest by pipeline.core.stage

# (path, size, mtime_ns, inode, sha256 the manifest records) of every file verify_output found intact in this
# process; forked workers inherit it, so a checkpoint is hashed once per process tree, not once per worker
_VERIFIED: set[tuple[str, int, int, int, str]] = set()


def owning_manifest(path: Path) -> Path | None:
    """The ``manifest.json`` of the stage output directory that holds ``path``, or None.

    That is the nearest ``manifest.json`` in the parent directories of ``path`` that has a ``config.yaml`` beside it
    (every stage output directory has both, written by :func:`pipeline.core.stage.run_stage`; a ``manifest.json``
    of some other tool higher up is not taken for one). Symbolic links in ``path`` are kept, not resolved.
    """
    for d in Path(os.path.abspath(path)).parents:
        if (d / MANIFEST_NAME).is_file() and (d / CONFIG_NAME).is_file():
            return d / MANIFEST_NAME
    return None


def _listed(path: Path) -> tuple[Path, Manifest, FileRecord] | None:
    """(manifest path, manifest, the manifest's record of ``path``), or None when no manifest lists it."""
    mpath = owning_manifest(path)
    if mpath is None:
        return None
    rel = Path(os.path.abspath(path)).relative_to(mpath.parent).as_posix()
    manifest = Manifest.read(mpath)
    record = next((r for r in manifest.outputs if r.path == rel), None)
    return None if record is None else (mpath, manifest, record)


def check_record(path: Path, record: FileRecord, size: int, sha256: str | None, manifest_path: Path,
                 redo: str) -> None:
    """Compares a file's size and sha256 (None: not computed yet) with the record a manifest holds of it.

    Raises:
        CorruptArtifactError: naming the file, the manifest, the expected and the found value, and ``redo``.
    """
    if size != record.bytes:
        expected, found = f"{record.bytes} bytes", f"{size} bytes"
    elif sha256 is not None and sha256 != record.sha256:
        expected, found = f"sha256 {record.sha256[:16]}...", f"{sha256[:16]}... (same size: damaged bytes)"
    else:
        return
    raise CorruptArtifactError(f"corrupt file {path}: expected {expected} (recorded in {manifest_path}), found {found}; "
                               f"{redo}")


def verify_output(path: Path) -> FileRecord | None:
    """Checks a file that a stage wrote against its stage's ``manifest.json`` before the file is used.

    Every checkpoint load goes through this (:func:`pretrain.checkpoint.read_weights`): a file whose bytes were
    damaged after its stage finished — a bad copy, a disk error, an edit — is refused here with its name instead of
    loading garbage (a damaged tensor payload under an intact safetensors header loads without complaint).

    Only files that a manifest lists are verified, against the nearest manifest (:func:`owning_manifest`). Not
    verified (None is returned): a file outside any stage output (e.g. user-given pretrained weights); a file of an
    unfinished output, which has no manifest yet (a staging directory, or intermediate checkpoints such as
    ``imitation/<k>/`` while the stage runs); and resume state (``state/last.pt``, ``ppo/last.zip``, ``rl/state.pt``),
    which is read without calling this at all: a ``--resume`` run rewrites it in place before its stage writes a
    new manifest, so the old manifest's record of it is stale by design. A weights file rewritten in place by such a
    run drops the stale manifest first (:func:`release_output`), so it is never checked against an old record.

    The sha256 of a file is computed once per process (and per forked worker pool): an intact file is remembered by
    path, size, mtime, inode and the recorded hash (about 1 s per GB hashed; the manifest is read on every call).

    Args:
        path: The file about to be read.

    Returns:
        The manifest's record of the file when it was verified, None when no manifest lists it.

    Raises:
        InputMissingError: ``path`` does not exist.
        CorruptArtifactError: its size or sha256 differs from the manifest's record, or the manifest is unreadable.
    """
    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError:
        raise InputMissingError(f"missing file {path}") from None
    found = _listed(path)
    if found is None:
        return None
    mpath, _, record = found
    key = (os.path.abspath(path), st.st_size, st.st_mtime_ns, st.st_ino, record.sha256)
    if key in _VERIFIED:
        return record
    redo = "restore it from a good copy or redo its stage with --overwrite"
    check_record(path, record, st.st_size, None, mpath, redo)  # the size first: no hashing of a truncated file
    check_record(path, record, st.st_size, hash_file(path), mpath, redo)
    _VERIFIED.add(key)
    return record


def release_output(path: Path) -> Path | None:
    """Deletes the ``manifest.json`` that lists ``path``, because ``path`` is about to be rewritten in place.

    A ``--resume`` run writes straight into a finished output directory, whose old manifest then no longer
    describes it; without the manifest the directory counts as unfinished (which it is) until its stage writes a
    new one, and :func:`verify_output` does not check the rewritten file against the stale record. Called by the
    writer of checkpoint weights (:func:`pretrain.checkpoint.save_safetensors`) before it replaces a file.

    Returns:
        The manifest deleted, or None when no manifest lists ``path`` (the usual case: stages write into a fresh
        staging directory).
    """
    mpath = owning_manifest(path)
    if mpath is None:
        return None
    try:
        listed = _listed(path) is not None
    except CorruptArtifactError:
        listed = True  # unreadable: it describes nothing any more, and the stage writes a new one when it finishes
    if not listed:
        return None
    mpath.unlink(missing_ok=True)
    return mpath


CODE_PACKAGES = ("pipeline", "sim", "recorder", "pretrain", "rl")


@functools.lru_cache(maxsize=16)
def code_hash(root: Path | None = None, packages: tuple[str, ...] = CODE_PACKAGES) -> str:
    """sha256 over the sources of some of the pipeline's packages (``*.py`` and ``*.yaml``, sorted by path).

    A stage output made by other code is stale, like a DVC stage whose code dependency changed. Each stage hashes
    only the packages it runs (:attr:`pipeline.core.stage.Stage.code`), so editing ``pretrain/`` does not make a
    recording stale.
    """
    base = Path(root) if root is not None else Path(__file__).resolve().parents[2]
    h = hashlib.sha256()
    for pkg in packages:
        d = base / pkg
        if not d.is_dir():
            continue
        for p in sorted(list(d.rglob("*.py")) + list(d.rglob("*.yaml"))):
            if "__pycache__" in p.parts:
                continue
            h.update(p.relative_to(base).as_posix().encode())
            h.update(b"\0")
            h.update(p.read_bytes())
    return h.hexdigest()
