"""The ``icrowdnav`` command line: one verb per stage, plus utility verbs.

Usage::

    icrowdnav                                   # list the verbs
    icrowdnav <verb> --help                     # list every config key of a stage, with type, default and help
    icrowdnav <verb> [--profile P] [--data-dir D] [--config FILE] [--seed N] [--overwrite | --resume]
                     [--KEY=VALUE | --KEY VALUE | --BOOL_KEY | --no-BOOL_KEY ...]

``KEY`` is any dotted config key (``--sim.camera.width_px 320``, as in lerobot's draccus CLI); dashes may replace
underscores (``--max-episode-s 30``). Every user error (:class:`ICrowdNavError`) is printed as exactly one line
``error: <message>`` on stderr, with exit status 2. A stage run stopped by Ctrl-C or SIGTERM unwinds (its pool
stopped, an in-place output keeping what it finished: :mod:`pipeline.core.signals`) and says so in one ``error:``
line, exiting 130 or 143.

The values are decoded into the stage's config dataclass by draccus (:mod:`pipeline.core.config`), and the help
of each key comes from its field's comment or docstring as draccus reads it. The argv split itself
(:func:`parse_stage_args`) stays ours, because draccus's argparse front end (``draccus.parse``, draccus 0.10.0)
rejects spellings this grammar has always accepted: ``--max-episode-s 2.5`` ("unrecognized arguments"), a bare
``--record_video`` ("expected one argument"), ``--sim.weights.b 2`` into a dict field ("unrecognized
arguments"); it reads ``--config`` as an abbreviation of its own ``--config_path`` (one file decoded as the whole
config, without our ``common``/``<stage>`` sections and profiles); and its ``--help`` lists ``list``/``dict``
types without their items and nested sections under wrong names (``--camera`` for ``sim.camera``).

Verbs are resolved lazily from :data:`VERBS` (``"module.path:OBJECT"``): only the chosen verb's module is
imported (the verb list reads each verb's help line from its module's source: :func:`static_verb_help`). If the
object is a :class:`Stage` it is run as a stage; otherwise it must be a callable taking the remaining arguments
(``list[str]``) and returning an exit status.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import importlib.util
import logging
import sys
import typing
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from pipeline.core.config import (
    available_profiles,
    describe_fields,
    field_types,
    load_config,
    nested_dataclass,
    profiles_dir,
)
from pipeline.core.errors import ConfigError, StoppedError, reports_errors
from pipeline.core.signals import exit_code, signal_name, sigterm_raises
from pipeline.core.stage import Stage, mode_of, run_stage_ex

PROG = "icrowdnav"

VERBS: dict[str, str] = {
    "rollout": "pipeline.verbs.rollout:STAGE",
    "bench": "pipeline.verbs.bench:main",
    "record": "pipeline.verbs.record:STAGE",
    "export": "pipeline.verbs.export:STAGE",
    "pretrain": "pipeline.verbs.pretrain:STAGE",
    "pretrain-intention": "pipeline.verbs.pretrain_intention:STAGE",
    "train": "pipeline.verbs.train:STAGE",
    "train-all": "pipeline.verbs.train_all:main",
    "eval": "pipeline.verbs.eval:STAGE",
    "doctor": "pipeline.verbs.doctor:main",
    "recover": "pipeline.verbs.recover:main",
    "timings": "pipeline.verbs.timings:main",
}

_LOG_FORMAT = "%(asctime)s %(levelname).1s %(message)s"
_LOG_DATEFMT = "%H:%M:%S"
_BOOL_WORDS = frozenset({"true", "false", "1", "0", "yes", "no", "on", "off", "y", "n"})


def register_verb(name: str, target: str) -> None:
    """Registers (or replaces) a verb.

    Args:
        name: The verb as typed on the command line.
        target: ``"module.path:OBJECT"``; OBJECT is a :class:`Stage` or a ``callable(argv) -> int``.

    Raises:
        ValueError: ``target`` is not of the form ``module:object``.
    """
    module, sep, attr = target.partition(":")
    if not sep or not module or not attr:
        raise ValueError(f"verb '{name}': target must look like 'module.path:OBJECT', got {target!r}")
    VERBS[name] = target


def resolve_verb(name: str) -> Stage | Callable[[list[str]], int | None]:
    """Imports and returns the object a verb points to.

    Args:
        name: A key of :data:`VERBS`.

    Raises:
        ConfigError: Unknown verb, or its module does not exist (yet).
    """
    if name not in VERBS:
        raise ConfigError(
            f"unknown command '{name}'; available commands: {', '.join(sorted(VERBS)) or '(none)'}"
        )
    module_name, _, attr = VERBS[name].partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        # Only a missing target module is the user's concern; a missing dependency inside it is a bug/setup issue.
        if e.name is not None and (module_name == e.name or module_name.startswith(e.name + ".")):
            raise ConfigError(
                f"command '{name}' is not available: module {module_name} does not exist"
            ) from None
        raise
    try:
        obj = getattr(module, attr)
    except AttributeError:
        raise ConfigError(
            f"command '{name}' is not available: {module_name} has no attribute {attr}"
        ) from None
    if not isinstance(obj, Stage) and not callable(obj):
        raise TypeError(
            f"verb '{name}': {VERBS[name]} is neither a Stage nor callable, got {type(obj).__name__}"
        )
    return obj


def static_verb_help(target: str) -> str | None:
    """A verb's help line read from its module's source, without importing it: the ``help=`` string of
    ``OBJECT = Stage(...)``, or the first line of ``def OBJECT``'s docstring. ``None`` where the source does not
    say it literally (or cannot be found or parsed) — the caller then imports the module. Importing every verb's
    module to list them loads each stage's libraries (torch, pybullet, lerobot): ~10 s against ~0.4 s."""
    module_name, _, attr = target.partition(":")
    try:
        spec = importlib.util.find_spec(module_name)
        tree = ast.parse(Path(spec.origin).read_text()) if spec and spec.origin else None
    except (ImportError, ValueError, OSError, SyntaxError):
        return None
    for node in tree.body if tree is not None else ():
        if isinstance(node, ast.FunctionDef) and node.name == attr:
            doc = (ast.get_docstring(node) or "").strip()
            return doc.splitlines()[0] if doc else None
        if (isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == attr for t in node.targets)
                and isinstance(node.value, ast.Call) and isinstance(node.value.func, ast.Name)
                and node.value.func.id == "Stage"):
            for kw in node.value.keywords:
                if kw.arg == "help" and isinstance(kw.value, ast.Constant) and isinstance(kw.value.value, str):
                    return kw.value.value
    return None


def _verb_help(name: str) -> str:
    static = static_verb_help(VERBS[name])
    if static is not None:
        return static
    try:
        obj = resolve_verb(name)
    except Exception as e:  # listing must not fail because one verb's module is broken
        text = str(e).splitlines()[0] if str(e) else type(e).__name__
        return f"(unavailable: {text.split('is not available: ', 1)[-1]})"
    if isinstance(obj, Stage):
        return obj.help
    doc = (getattr(obj, "__doc__", None) or "").strip()
    return doc.splitlines()[0] if doc else ""


def format_verbs() -> str:
    """Returns the top-level help: usage and one line per verb."""
    lines = [
        f"usage: {PROG} <command> [--profile P] [--data-dir D] [--config FILE] [--seed N] "
        "[--overwrite | --resume] [--KEY VALUE ...]",
        f"       {PROG} <command> --help    lists every config key of a command",
        "",
        "commands:",
    ]
    width = max((len(v) for v in VERBS), default=0)
    for verb in sorted(VERBS):
        lines.append(f"  {verb:<{width}}  {_verb_help(verb)}")
    return "\n".join(lines)


def format_stage_help(stage: Stage) -> str:
    """Returns ``<verb> --help``: usage, the stage's help, profiles and every config key.

    Args:
        stage: The stage.
    """
    rows = describe_fields(stage.config_cls)
    lines = [
        f"usage: {PROG} {stage.name} [--profile P] [--config FILE] [--KEY VALUE ...]",
        "",
        stage.help,
        "",
        f"profiles ({profiles_dir()}): {', '.join(available_profiles()) or '(none)'}",
        "  --profile P    take defaults from section '" + stage.name + "' of the profile (default: default)",
        "  --config FILE  YAML file whose 'common' and '" + stage.name + "' sections override the profile",
        "",
        "config keys (--KEY VALUE or --KEY=VALUE; dashes may replace underscores; --BOOL alone means true):",
    ]
    key_w = max((len(r[0]) for r in rows), default=0) + 2
    type_w = max((len(r[1]) for r in rows), default=0)
    default_w = min(max((len(r[2]) for r in rows), default=0), 24)
    for key, tname, default, helptext in rows:
        if key == "resume" and not stage.resumable:
            helptext += " [this stage: atomic, so resume rebuilds a missing or stale output]"
        lines.append(
            f"  --{key:<{key_w}}{tname:<{type_w}}  default {default:<{default_w}}  {helptext}".rstrip()
        )
    return "\n".join(lines)


def _bool_keys(cls: type, prefix: str = "") -> tuple[set[str], set[str]]:
    """Returns (dotted keys of bool fields, dotted keys of all fields and sections) of a config class."""
    bools: set[str] = set()
    keys: set[str] = set()
    hints = field_types(cls)
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        key = f"{prefix}.{f.name}" if prefix else f.name
        keys.add(key)
        tp = hints[f.name]
        args = typing.get_args(tp)
        if tp is bool or (set(args) == {bool, type(None)}):
            bools.add(key)
        dc = nested_dataclass(tp)
        if dc is not None:
            sub_bools, sub_keys = _bool_keys(dc, key)
            bools |= sub_bools
            keys |= sub_keys
    return bools, keys


@dataclasses.dataclass
class StageArgs:
    """Parsed stage command line.

    Attributes:
        profile: Profile name.
        config_file: Optional ``--config`` file.
        overrides: Dotted key → raw string value.
        help: Whether ``--help`` was given.
    """

    profile: str = "default"
    config_file: Path | None = None
    overrides: dict[str, str] = dataclasses.field(default_factory=dict)
    help: bool = False


def parse_stage_args(stage: Stage, argv: Sequence[str]) -> StageArgs:
    """Parses ``[--profile P] [--config FILE] [--KEY VALUE | --KEY=VALUE | --FLAG | --no-FLAG ...]``.

    Args:
        stage: The stage (its config class tells which keys are booleans).
        argv: Arguments after the verb.

    Raises:
        ConfigError: A positional argument, or an option without its value.
    """
    bools, keys = _bool_keys(stage.config_cls)
    out = StageArgs()
    args = list(argv)
    i = 0
    while i < len(args):
        arg = args[i]
        i += 1
        if arg in ("-h", "--help"):
            out.help = True
            continue
        if not arg.startswith("--") or arg == "--":
            raise ConfigError(f"unexpected argument {arg!r}: expected --KEY VALUE or --KEY=VALUE")
        name, has_eq, value = arg[2:].partition("=")
        key = name.replace("-", "_")
        if not has_eq:
            next_is_value = i < len(args) and not args[i].startswith("--")
            if key in bools or (key.startswith("no_") and key[3:] in bools and key not in keys):
                if key not in bools:  # --no-flag
                    key, value = key[3:], "false"
                elif next_is_value and args[i].strip().lower() in _BOOL_WORDS:
                    value = args[i]
                    i += 1
                else:
                    value = "true"
            elif next_is_value:
                value = args[i]
                i += 1
            else:
                raise ConfigError(f"option --{name} needs a value: expected --{name} VALUE or --{name}=VALUE")
        if key == "profile":
            out.profile = value
        elif key == "config":
            out.config_file = Path(value)
        else:
            out.overrides[key] = value
    return out


def _summary(stage: Stage, out: Path, counts: dict[str, Any], ran: bool) -> str:
    parts = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in counts.items())
    status = "done" if ran else "up to date"
    return f"{stage.name}: {status} -> {out}" + (f" ({parts})" if parts else "")


def run_stage_cli(stage: Stage, argv: Sequence[str], command: list[str] | None = None) -> int:
    """Parses a stage's arguments, loads its config, runs it and prints a one-line summary.

    Args:
        stage: The stage.
        argv: Arguments after the verb.
        command: Command line to record in the manifest.

    Returns:
        The exit status (0).

    Raises:
        ICrowdNavError: Any user error (handled by :func:`main`).
    """
    parsed = parse_stage_args(stage, argv)
    if parsed.help:
        print(format_stage_help(stage))
        return 0
    cfg = load_config(stage.config_cls, stage.name, parsed.profile, parsed.overrides, parsed.config_file)
    out = Path(stage.output_dir(cfg))
    try:
        with sigterm_raises():
            manifest, ran = run_stage_ex(stage, cfg, command)
    except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM (sigterm_raises): one line saying what is left
        # an in-place stage writes into its output (kept); otherwise, and with --overwrite, a staging copy (removed)
        kept = (f"what it finished is kept in {out}; rerun with --resume to continue"
                if stage.in_place and mode_of(cfg) != "overwrite" else f"nothing was published to {out}")
        raise StoppedError(f"{stage.name} stopped by {signal_name(e)}: {kept}", exit_code(e)) from e
    print(_summary(stage, out, manifest.counts, ran))
    return 0


class _StderrHandler(logging.StreamHandler):  # type: ignore[type-arg]
    """Writes to whatever ``sys.stderr`` is at emit time (so redirected/captured stderr works)."""

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stderr
        super().emit(record)


def setup_logging(level: int = logging.INFO) -> None:
    """Sends the ``icrowdnav`` logger to stderr with a short format (idempotent).

    Args:
        level: Logging level.
    """
    logger = logging.getLogger("icrowdnav")
    logger.setLevel(level)
    logger.propagate = False  # lerobot configures the root logger on import; print each line once
    if not any(isinstance(h, _StderrHandler) for h in logger.handlers):
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter(_LOG_FORMAT, _LOG_DATEFMT))
        logger.addHandler(handler)


@reports_errors
def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``icrowdnav`` and ``python -m pipeline``.

    Args:
        argv: Arguments without the program name (default: ``sys.argv[1:]``).

    Returns:
        The exit status: 0 on success, 2 on a user error (one ``error:`` line on stderr), 130 on Ctrl-C and 143
        on SIGTERM during a stage (one ``error:`` line saying what is kept), 130 on Ctrl-C anywhere else.
    """
    args = list(sys.argv[1:] if argv is None else argv)
    setup_logging()
    if not args or args[0] in ("-h", "--help", "help"):
        print(format_verbs())
        return 0 if args else 2
    verb, rest = args[0], args[1:]
    try:
        target = resolve_verb(verb)
        if isinstance(target, Stage):
            return run_stage_cli(target, rest, [PROG, *args])
        status = target(rest)
        return 0 if status is None else int(status)
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
