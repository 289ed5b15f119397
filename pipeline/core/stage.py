"""Stages: one CLI verb = one config class + a body that turns input files into an output directory.

:func:`run_stage` wraps every stage body the same way:

1. every input path must exist (:class:`InputMissingError` otherwise);
2. in mode ``new``, an output directory whose ``manifest.json`` records the same config hash, the same input
   hashes and output files that are all still there with the same sizes is *up to date*: the stage does no
   work and returns the existing manifest (like ``dvc repro``); any other existing output is an
   :class:`OutputExistsError` unless ``--overwrite`` or ``--resume`` is given;
3. the body writes into a crash-safe :class:`OutputDir` and returns a counts dict;
4. ``config.yaml`` (resolved config) and ``manifest.json`` (provenance) are written into the directory, which
   is then published under its final name.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from pipeline.core.artifacts import OutputDir, OutputMode, atomic_write_json, require_input
from pipeline.core.config import config_hash, dump_yaml, to_dict, validate_tree
from pipeline.core.errors import (
    ConfigError,
    ICrowdNavError,
    InputMissingError,
    OutputExistsError,
)
from pipeline.core.manifest import (
    CODE_PACKAGES,
    CONFIG_NAME,
    MANIFEST_NAME,
    FileRecord,
    Manifest,
    check_record,
    code_hash,
    collect_versions,
    git_info,
    hash_file,
    hash_tree,
)

log = logging.getLogger("icrowdnav")

_CODE_ROOT = Path(__file__).resolve().parent


@dataclass(frozen=True)
class Stage:
    """A pipeline stage.

    Attributes:
        name: The CLI verb and the section name in the YAML profiles.
        config_cls: The config dataclass (a ``BaseStageConfig`` subclass).
        help: One-line description for ``icrowdnav --help``.
        output_dir: Maps a config to the stage's output directory.
        inputs: Maps a config to the files/directories the stage reads.
        body: ``body(cfg, out_dir) -> counts``: writes every output into ``out_dir`` and returns summary
            numbers (int, float or str values).
        resumable: Whether the body can continue a partially written output (``--resume``).
        in_place: The body writes straight into the output directory instead of a staging copy, so a killed
            run keeps what it finished (recording); a new run into a missing directory then runs as
            ``resume``. Requires ``resumable``.
        code: The packages whose sources make up the stage's code hash (an output made by other code is stale).
        scaffold: File names an in-place body writes before any work (``seeds.json``): a run that created the
            output directory and failed holding nothing but these, empty files and empty folders leaves nothing.
    """

    name: str
    config_cls: type
    help: str
    output_dir: Callable[[Any], Path]
    inputs: Callable[[Any], list[Path]]
    body: Callable[[Any, Path], dict[str, Any]]
    resumable: bool = False
    in_place: bool = False
    code: tuple[str, ...] = CODE_PACKAGES
    scaffold: tuple[str, ...] = ()


def holds_work(out: Path, scaffold: tuple[str, ...] = ()) -> bool:
    """Whether an in-place output directory holds anything a resume could use: a non-empty file whose name is not
    in ``scaffold`` (``*.partial`` files count: ``icrowdnav recover`` salvages them)."""
    return any(p.is_file() and p.name not in scaffold and p.stat().st_size > 0 for p in out.rglob("*"))


def mode_of(cfg: Any) -> OutputMode:
    """Returns the output mode a config asks for: ``overwrite``, ``resume`` or ``new``.

    Args:
        cfg: A stage config (fields ``overwrite`` and ``resume``; missing ones count as false).

    Raises:
        ConfigError: Both ``overwrite`` and ``resume`` are set.
    """
    overwrite = bool(getattr(cfg, "overwrite", False))
    resume = bool(getattr(cfg, "resume", False))
    if overwrite and resume:
        raise ConfigError(
            "config keys 'overwrite' and 'resume' exclude each other: expected at most one to be true, "
            "got overwrite=true, resume=true"
        )
    if overwrite:
        return "overwrite"
    if resume:
        return "resume"
    return "new"


def _record_path(path: Path, data_dir: Path | None) -> str:
    """An input path as stored in a manifest: relative to ``data_dir`` when inside it, else as given."""
    if data_dir is not None:
        try:
            return path.resolve().relative_to(Path(data_dir).resolve()).as_posix()
        except ValueError:
            pass
    return path.as_posix()


def hash_inputs(paths: list[Path], data_dir: Path | None = None) -> list[FileRecord]:
    """Hashes the inputs of a stage; a directory contributes one record per file under it.

    Args:
        paths: Input files and directories (they must exist).
        data_dir: Paths inside it are recorded relative to it.

    Returns:
        Records sorted by path.
    """
    records: list[FileRecord] = []
    for p in paths:
        p = Path(p)
        shown = _record_path(p, data_dir)
        if p.is_dir():
            prefix = "" if shown in ("", ".") else shown.rstrip("/") + "/"
            records.extend(FileRecord(prefix + r.path, r.sha256, r.bytes) for r in hash_tree(p))
        else:
            records.append(FileRecord(shown, hash_file(p), p.stat().st_size))
    unique = {r.path: r for r in records}
    return [unique[k] for k in sorted(unique)]


def verify_inputs(paths: list[Path], records: list[FileRecord], data_dir: Path | None = None) -> None:
    """Checks every input directory that is a finished stage output against its ``manifest.json``: each file the
    manifest lists must be there with the recorded size and sha256 (the hashes are those :func:`hash_inputs` just
    computed, so this costs no extra read). A recording edited or damaged after its stage finished is refused by
    name here instead of being exported, trained on or evaluated.

    Raises:
        CorruptArtifactError: a listed file differs from its record, or the manifest is unreadable.
        InputMissingError: a listed file is missing.
    """
    by_path = {r.path: r for r in records}
    for p in paths:
        p = Path(p)
        mpath = p / MANIFEST_NAME
        if not (p.is_dir() and mpath.is_file() and (p / CONFIG_NAME).is_file()):
            continue
        manifest = Manifest.read(mpath)  # a damaged manifest: CorruptArtifactError naming it
        prefix = _record_path(p, data_dir).rstrip("/")
        redo = f"restore it or redo stage '{manifest.stage}' with --overwrite"
        for rec in manifest.outputs:
            got = by_path.get(f"{prefix}/{rec.path}" if prefix not in ("", ".") else rec.path)
            if got is None:
                raise InputMissingError(f"missing file {p / rec.path}: listed in {mpath}; {redo}")
            check_record(p / rec.path, rec, got.bytes, got.sha256, mpath, redo)


def _clean_counts(stage: str, counts: Any) -> dict[str, float | int | str]:
    """Checks a body's return value; numpy scalars are turned into Python numbers."""
    if counts is None:
        return {}
    if not isinstance(counts, dict):
        raise TypeError(f"stage '{stage}': body must return a dict of counts, got {type(counts).__name__}")
    out: dict[str, float | int | str] = {}
    for k, v in counts.items():
        if hasattr(v, "item") and callable(v.item) and not isinstance(v, int | float | str):
            v = v.item()
        if not isinstance(k, str) or not isinstance(v, int | float | str):
            raise TypeError(
                f"stage '{stage}': counts[{k!r}] must map a str to an int, float or str, got {v!r}"
            )
        out[k] = v
    return out


def staleness(stage: Stage, cfg: Any, out_dir: Path, inputs: list[FileRecord]) -> str | None:
    """Says why an existing output directory is not an up-to-date result of this config.

    Args:
        stage: The stage.
        cfg: Its config.
        out_dir: The existing output directory.
        inputs: Current input records (from :func:`hash_inputs`).

    Returns:
        None when the output is up to date, else a short reason.
    """
    manifest_path = out_dir / MANIFEST_NAME
    if not manifest_path.is_file():
        return f"it has no {MANIFEST_NAME}, so it is incomplete or was not made by this pipeline"
    try:
        old = Manifest.read(manifest_path)
    except ICrowdNavError as e:
        return str(e)
    if old.stage != stage.name:
        return f"it was made by stage '{old.stage}', not '{stage.name}'"
    if old.code_hash != code_hash(None, stage.code):
        return "the pipeline's code changed since it was made"
    new_hash = config_hash(cfg)
    if old.config_hash != new_hash:
        return f"the config changed: config_hash {old.config_hash[:12]} there, {new_hash[:12]} now"
    old_inputs = {r.path: r for r in old.inputs}
    new_inputs = {r.path: r for r in inputs}
    if old_inputs != new_inputs:
        changed = sorted(set(old_inputs) ^ set(new_inputs)) or sorted(
            p for p in new_inputs if old_inputs[p] != new_inputs[p]
        )
        return f"its inputs changed ({', '.join(changed[:3])}{' ...' if len(changed) > 3 else ''})"
    for rec in old.outputs:
        p = out_dir / rec.path
        if not p.is_file():
            return f"output file {rec.path} is missing"
        size = p.stat().st_size
        if size != rec.bytes:
            return f"output file {rec.path} has {size} bytes, expected {rec.bytes}"
    return None


def _check_writable(directory: Path) -> None:
    """Fail fast, before any work, when ``directory`` cannot be created or written; creates nothing (a run refused
    later, e.g. for a damaged input, leaves no empty folders): the nearest existing ancestor must be a writable
    directory."""
    existing = directory
    while not existing.exists() and existing.parent != existing:
        existing = existing.parent
    if not existing.is_dir():
        raise ConfigError(f"data directory not writable: cannot create {directory} (Not a directory: {existing})")
    directory = existing
    if not os.access(directory, os.W_OK | os.X_OK):
        raise ConfigError(f"directory not writable: {directory} (expected write permission for this user)")


def run_stage_ex(stage: Stage, cfg: Any, command: list[str] | None = None) -> tuple[Manifest, bool]:
    """Runs a stage like :func:`run_stage` and also says whether any work was done.

    Returns:
        ``(manifest, ran)``; ``ran`` is False when the existing output was up to date.
    """
    if not isinstance(cfg, stage.config_cls):
        raise TypeError(
            f"stage '{stage.name}': expected a {stage.config_cls.__name__}, got {type(cfg).__name__}"
        )
    validate_tree(cfg)
    mode = mode_of(cfg)
    atomic_resume = mode == "resume" and not stage.resumable
    if atomic_resume:
        # the stage publishes its output atomically, so a killed run left nothing partial: "continue" means keep
        # an up-to-date output and rebuild a missing or stale one (`make record ARGS=--resume` after a kill)
        mode = "new"
    input_paths = [Path(p) for p in stage.inputs(cfg)]
    for p in input_paths:
        require_input(p, f"input of stage '{stage.name}'")
    out = Path(stage.output_dir(cfg))
    _check_writable(out.parent)
    if stage.in_place and mode == "new" and not out.exists():
        mode = "resume"  # write in place from the start: a kill keeps every finished piece
    if mode == "resume" and out.is_dir():
        _check_writable(out)  # continuing writes into it (an unwritable one: a named error, not PermissionError)
    data_dir = getattr(cfg, "data_dir", None)
    inputs = hash_inputs(input_paths, data_dir)
    verify_inputs(input_paths, inputs, data_dir)

    if mode in ("new", "resume") and out.exists():
        # an up-to-date output is left byte for byte, with --resume too (its config.yaml is an input of the next
        # stage, which would rebuild); a stale or unfinished one is continued by a resume, else handled here
        reason = staleness(stage, cfg, out, inputs) if out.is_dir() else f"{out} is not a directory"
        if reason is None:
            log.info("%s: up to date (%s)", stage.name, out)
            return Manifest.read(out / MANIFEST_NAME), False
        if atomic_resume and out.is_dir():  # (an atomic stage's resume runs as "new")
            log.info("%s: --resume: rebuilding %s (%s)", stage.name, out, reason)
            mode = "overwrite"
        elif mode == "new" and (not out.is_dir() or any(out.iterdir())):
            resume_hint = " or --resume to continue it" if stage.resumable else ""
            raise OutputExistsError(
                f"output directory {out} already exists and is not up to date ({reason}); "
                f"pass --overwrite to replace it{resume_hint}"
            )

    chash = config_hash(cfg)
    params = to_dict(cfg)
    command = list(sys.argv) if command is None else list(command)
    t0 = time.monotonic()
    created = mode == "resume" and not out.exists()
    earlier = _begin_invocation(out) if mode == "resume" else (0.0, 0)
    try:
        return _run_body(stage, cfg, out, mode, chash, params, inputs, command, t0, earlier)
    except BaseException:
        if created and out.is_dir() and not holds_work(out, stage.scaffold):
            log.info("%s: failed before finishing any work; removing %s", stage.name, out)
            shutil.rmtree(out, ignore_errors=True)
            _ledger_path(out).unlink(missing_ok=True)
        raise


def _ledger_path(out: Path) -> Path:
    """Where an output written in place notes its running invocation (beside it, so it is never an output file)."""
    return out.parent / f".{out.name}.invocation.json"


def _last_write(out: Path, default: float) -> float:
    """The latest modification time (Unix seconds) of any file under ``out``; ``default`` when it holds none."""
    latest = default
    for dirpath, _, filenames in os.walk(out):
        for name in filenames:
            try:
                latest = max(latest, os.stat(os.path.join(dirpath, name)).st_mtime)
            except OSError:
                continue
    return latest


def _begin_invocation(out: Path) -> tuple[float, int]:
    """Notes this invocation of an output written in place and returns ``(wall_s, count)`` of the invocations
    that built it before: the ledger of one that never finished (killed, or failed) counts it from its start to its
    last write to ``out`` on top of the ones before it; otherwise an earlier finished run's manifest gives its
    totals; else ``(0.0, 0)``. An unreadable ledger is logged and its invocations are not counted."""
    ledger = _ledger_path(out)
    earlier: tuple[float, int] = (0.0, 0)
    try:
        data = json.loads(ledger.read_text(encoding="utf-8"))
        start = float(data["start_unix"])
        earlier = (float(data["earlier_s"]) + max(0.0, _last_write(out, start) - start), int(data["earlier_n"]) + 1)
    except FileNotFoundError:
        if (out / MANIFEST_NAME).is_file():
            try:
                m = Manifest.read(out / MANIFEST_NAME)
                earlier = (m.wall_total_s, m.invocations)
            except ICrowdNavError as e:
                log.warning("earlier invocations of %s not counted in its wall: %s", out, e)
    except (OSError, ValueError, KeyError, TypeError) as e:
        log.warning("earlier invocations of %s not counted in its wall: unreadable %s (%s)", out, ledger, e)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(ledger, {"start_unix": time.time(), "earlier_s": round(earlier[0], 3), "earlier_n": earlier[1]})
    return earlier


def code_state(packages: tuple[str, ...] = CODE_PACKAGES) -> tuple[str, bool, str]:
    """``(git commit, dirty, code hash)`` of the code running now (read when a run starts: one that spans commits
    must not record a later one)."""
    commit, dirty = git_info(_CODE_ROOT)
    return commit, dirty, code_hash(None, packages)


def finish_output(out: Path, name: str, cfg: Any, counts: Any, inputs: list[FileRecord], command: list[str],
                  t0: float, code: tuple[str, bool, str], earlier: tuple[float, int] = (0.0, 0), *,
                  params: dict[str, Any] | None = None, chash: str | None = None) -> Manifest:
    """Writes ``config.yaml`` and then ``manifest.json`` (last: a consumer refuses an output without one) into the
    finished output directory ``out`` — the provenance every stage writes, and a tool that writes an artefact
    outside the stage runner (``python -m rl.data_scale --save``) writes the same way.

    Args:
        name: the stage (or tool) that made it. cfg: its resolved config. counts: its summary numbers.
        inputs: the hashed inputs (:func:`hash_inputs`). command: its command line.
        t0: ``time.monotonic()`` at its start (the wall includes hashing the outputs).
        code: :func:`code_state` at its start. earlier: walls and count of the invocations before this one.
        params, chash: the config's dict and hash when the caller has them already.
    """
    counts = _clean_counts(name, counts)
    dump_yaml(cfg, out / CONFIG_NAME)
    seed = getattr(cfg, "seed", None)
    outputs = hash_tree(out)
    wall = round(time.monotonic() - t0, 3)  # the outputs' hashing included
    manifest = Manifest(
        stage=name,
        params=to_dict(cfg) if params is None else params,
        config_hash=config_hash(cfg) if chash is None else chash,
        seed=seed if isinstance(seed, int) and not isinstance(seed, bool) else None,
        inputs=inputs,
        outputs=outputs,
        counts=counts,
        created_utc=datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        git_commit=code[0],
        git_dirty=code[1],
        versions=collect_versions(),
        duration_s=wall,
        command=list(command),
        code_hash=code[2],
        wall_total_s=round(earlier[0] + wall, 3),
        invocations=earlier[1] + 1,
    )
    manifest.write(out / MANIFEST_NAME)
    return manifest


def _run_body(stage: Stage, cfg: Any, out: Path, mode: str, chash: str, params: dict, inputs: list[FileRecord],
              command: list[str], t0: float, earlier: tuple[float, int]) -> tuple[Manifest, bool]:
    """The body in its :class:`OutputDir`, then ``config.yaml`` and ``manifest.json`` (its wall adds ``earlier``:
    the walls and count of the invocations that built an output continued in place before this one)."""
    # the code that runs is the code at the start: a run that spans commits must not record a later one
    code = code_state(stage.code)
    with OutputDir(out, mode) as od:
        log.info("%s: running (mode %s) -> %s", stage.name, mode, out)
        counts = stage.body(cfg, od.path)
        manifest = finish_output(od.path, stage.name, cfg, counts, inputs, command, t0, code, earlier,
                                 params=params, chash=chash)
    _ledger_path(out).unlink(missing_ok=True)
    log.info("%s: done in %.1f s -> %s", stage.name, manifest.duration_s, out)
    return manifest, True


def run_stage(stage: Stage, cfg: Any, command: list[str] | None = None) -> Manifest:
    """Runs a stage: checks inputs, skips up-to-date outputs, runs the body crash-safely, writes provenance.

    Args:
        stage: The stage.
        cfg: Its config (an instance of ``stage.config_cls``; validated again here).
        command: The command line to record (default: ``sys.argv``).

    Returns:
        The manifest of the (new or up-to-date) output directory.

    Raises:
        InputMissingError: An input path does not exist.
        OutputExistsError: The output exists, is not up to date, and neither overwrite nor resume is set.
        ConfigError: Invalid config.

    ``resume`` on a stage that is not :attr:`Stage.resumable` (its output is published atomically, so a killed run
    left nothing partial) keeps an up-to-date output and (re)builds a missing or stale one.
    """
    return run_stage_ex(stage, cfg, command)[0]
