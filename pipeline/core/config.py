"""Typed stage configs: dataclasses filled from YAML profiles, an optional config file and CLI overrides.

A stage config is a dataclass deriving from :class:`BaseStageConfig`; it may nest other dataclasses
(``sim: SimConfig``), and any of them may define ``validate(self) -> None`` raising :class:`ConfigError`.
:func:`load_config` layers, lowest precedence first:

1. the dataclass defaults,
2. the ``common`` section of ``pipeline/profiles/<profile>.yaml`` (only keys the stage config has),
3. the ``<stage>`` section of that profile,
4. the ``common`` and ``<stage>`` sections of ``--config FILE``,
5. command-line overrides ``--sim.camera.width 64`` (dotted keys),

then calls every ``validate()`` (children first), so that every check fails before any work starts.

Supported field types: ``int``, ``float``, ``bool``, ``str``, ``Path``, ``Literal[...]``, enums, ``list[T]``,
``tuple[T, ...]``, ``tuple[T1, T2]``, ``T | None`` (and other unions), ``dict[str, T]``, ``Any`` and nested
dataclasses. YAML values must have the right type (numbers written as ``1e-3``, which YAML reads as strings,
are accepted for numeric fields). Command-line values are strings: they are parsed with ``yaml.safe_load``
and then checked, except for ``str``/``Path`` fields (taken verbatim), ``bool`` fields (``true/false/1/0/
yes/no``) and list/tuple fields, which also accept ``a,b,c``.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import inspect
import json
import os
import re
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TypeVar

import yaml

from pipeline.core.artifacts import atomic_write_text
from pipeline.core.errors import ConfigError, InputMissingError

T = TypeVar("T")

PROFILES_ENV = "ICROWDNAV_PROFILES_DIR"
COMMON_SECTION = "common"
CLI_SOURCE = "command line"
HASH_EXCLUDED_FIELDS: frozenset[str] = frozenset({"overwrite", "resume", "data_dir", "profile"})

_TRUE_WORDS = frozenset({"true", "1", "yes", "y", "on"})
_FALSE_WORDS = frozenset({"false", "0", "no", "n", "off"})
_NONE_WORDS = frozenset({"none", "null", "~"})


@dataclass
class BaseStageConfig:
    """Fields every stage has. Stage configs subclass this."""

    data_dir: Path = field(
        default=Path("data"), metadata={"help": "root directory of all pipeline inputs and outputs"}
    )
    profile: str = field(
        default="default",
        metadata={"help": "name of the YAML profile in pipeline/profiles/ the config came from"},
    )
    seed: int = field(
        default=0, metadata={"help": "random seed (non-negative); the same seed gives the same outputs"}
    )
    overwrite: bool = field(
        default=False,
        metadata={"help": "replace an existing output directory (the old one is kept until done)"},
    )
    resume: bool = field(
        default=False,
        metadata={"help": "continue a partially written output directory (resumable stages only)"},
    )

    def validate(self) -> None:
        """Checks the common fields.

        Raises:
            ConfigError: ``overwrite`` and ``resume`` are both set, or ``seed`` is negative.
        """
        if self.overwrite and self.resume:
            raise ConfigError(
                "config keys 'overwrite' and 'resume' exclude each other: expected at most one to be true, "
                "got overwrite=true, resume=true"
            )
        if self.seed < 0:
            raise ConfigError(f"config key 'seed': expected an int >= 0, got {self.seed}")


# ----------------------------------------------------------------------------------------------------------
# Type handling
# ----------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _CliText:
    """A raw command-line value, parsed according to the type of the field it lands in."""

    text: str


@functools.cache
def field_types(cls: type) -> dict[str, Any]:
    """Returns the resolved type annotations of a dataclass (works with ``from __future__ import annotations``).

    Args:
        cls: A dataclass.
    """
    try:
        return typing.get_type_hints(cls)
    except Exception as e:  # a NameError in an annotation is a bug in the config class
        raise TypeError(f"cannot resolve the type annotations of config class {cls.__qualname__}: {e}") from e


def _init_fields(cls: type) -> list[dataclasses.Field[Any]]:
    return [f for f in dataclasses.fields(cls) if f.init]


def _is_union(tp: Any) -> bool:
    return typing.get_origin(tp) in (typing.Union, types.UnionType)


def nested_dataclass(tp: Any) -> type | None:
    """Returns the dataclass in ``tp`` if ``tp`` is a dataclass or ``Dataclass | None``, else None.

    Args:
        tp: A type annotation.
    """
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return tp
    if _is_union(tp):
        arms = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(arms) == 1 and isinstance(arms[0], type) and dataclasses.is_dataclass(arms[0]):
            return arms[0]
    return None


def type_name(tp: Any) -> str:
    """Returns a short readable name of a config field type (``int``, ``list[float]``, ``str | None``).

    Args:
        tp: A type annotation.
    """
    if tp is type(None):
        return "None"
    if tp is Any:
        return "any"
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is Literal:
        return "{" + ", ".join(repr(a) for a in args) + "}"
    if _is_union(tp):
        return " | ".join(type_name(a) for a in args)
    if origin is typing.Annotated:
        return type_name(args[0])
    if origin is not None:
        base = getattr(origin, "__name__", str(origin))
        if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
            return f"tuple[{type_name(args[0])}, ...]"
        return f"{base}[{', '.join(type_name(a) for a in args)}]" if args else base
    if isinstance(tp, type):
        if issubclass(tp, Path):
            return "Path"
        if issubclass(tp, enum.Enum):
            return "{" + ", ".join(repr(m.value) for m in tp) + "}"
        return tp.__name__
    return str(tp)


def _expected(tp: Any) -> str:
    if typing.get_origin(tp) is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    return type_name(tp)


def _show(value: Any) -> str:
    if isinstance(value, _CliText):
        value = value.text
    text = repr(value)
    if len(text) > 80:
        text = text[:77] + "..."
    return f"{text} ({type(value).__name__})"


def _type_error(key: str, source: str, tp: Any, value: Any, note: str = "") -> ConfigError:
    return ConfigError(
        f"config key '{key}' in {source}: expected {_expected(tp)}, got {_show(value)}"
        + (f"; {note}" if note else "")
    )


def _yaml_scalar(text: str, key: str, source: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        problem = getattr(e, "problem", None) or type(e).__name__
        raise ConfigError(
            f"config key '{key}' in {source}: cannot parse {text!r} as a YAML value ({problem})"
        ) from None


def _coerce_cli(text: str, tp: Any, key: str, source: str, current: Any) -> Any:
    """Converts a command-line string for a field of type ``tp``."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    stripped = text.strip()
    if origin is typing.Annotated:
        return _coerce_cli(text, args[0], key, source, current)
    if tp is Any:
        return _yaml_scalar(text, key, source)
    if _is_union(tp):
        if type(None) in args and stripped.lower() in _NONE_WORDS:
            return None
        arms = [a for a in args if a is not type(None)]
        for arm in arms:
            try:
                return _coerce_cli(text, arm, key, source, current)
            except ConfigError:
                continue
        raise _type_error(key, source, tp, text)
    if origin is Literal:
        for option in args:
            if isinstance(option, bool):
                word = stripped.lower()
                if (option and word in _TRUE_WORDS) or (not option and word in _FALSE_WORDS):
                    return option
            elif stripped == str(option):
                return option
        raise _type_error(key, source, tp, text)
    if tp is bool:
        word = stripped.lower()
        if word in _TRUE_WORDS:
            return True
        if word in _FALSE_WORDS:
            return False
        raise _type_error(key, source, tp, text, "use true/false/1/0/yes/no")
    if tp is str:
        return text
    if isinstance(tp, type) and issubclass(tp, Path):
        return Path(text)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return _coerce(_yaml_scalar(text, key, source), tp, key, source)
    if origin in (list, tuple) or tp in (list, tuple):
        if stripped.startswith("["):
            return _coerce(_yaml_scalar(text, key, source), tp, key, source)
        items = [] if not stripped else [_CliText(part.strip()) for part in text.split(",")]
        return _coerce(items, tp, key, source)
    dc = nested_dataclass(tp)
    if dc is not None:
        parsed = _yaml_scalar(text, key, source)
        if isinstance(parsed, Mapping):
            return _build(dc, parsed, source, key, current if isinstance(current, dc) else None)
        raise _type_error(key, source, tp, text, "give a YAML mapping or set its keys one by one")
    return _coerce(_yaml_scalar(text, key, source), tp, key, source)


def _coerce(value: Any, tp: Any, key: str, source: str, current: Any = None) -> Any:
    """Checks/converts ``value`` for a field of type ``tp``; raises ConfigError naming ``key`` and ``source``."""
    if isinstance(value, _CliText):
        return _coerce_cli(value.text, tp, key, source, current)
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin is typing.Annotated:
        return _coerce(value, args[0], key, source, current)
    if _is_union(tp):
        if value is None:
            if type(None) in args:
                return None
            raise _type_error(key, source, tp, value)
        for arm in (a for a in args if a is not type(None)):
            try:
                return _coerce(value, arm, key, source, current)
            except ConfigError:
                continue
        raise _type_error(key, source, tp, value)
    if origin is Literal:
        for option in args:
            if value == option and type(value) is type(option):
                return option
        raise _type_error(key, source, tp, value)
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise _type_error(key, source, tp, value)
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        if isinstance(value, str):
            try:
                return int(value.strip())
            except ValueError:
                try:
                    as_float = float(value)
                except ValueError:
                    as_float = None
                if as_float is not None and as_float.is_integer():
                    return int(as_float)
        raise _type_error(key, source, tp, value)
    if tp is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):  # YAML reads 1e-3 (no dot) as a string
            try:
                return float(value.strip())
            except ValueError:
                pass
        raise _type_error(key, source, tp, value)
    if tp is str:
        if isinstance(value, str):
            return value
        raise _type_error(key, source, tp, value, "quote it in YAML")
    if isinstance(tp, type) and issubclass(tp, Path):
        if isinstance(value, str | os.PathLike):
            return Path(value)
        raise _type_error(key, source, tp, value)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        if isinstance(value, tp):
            return value
        for member in tp:
            if value == member.value and type(value) is type(member.value):
                return member
            if isinstance(value, str) and value == member.name:
                return member
        raise _type_error(key, source, tp, value)
    if origin is list or tp is list:
        if not isinstance(value, list | tuple):
            raise _type_error(key, source, tp, value)
        if not args:
            return list(value)
        return [_coerce(v, args[0], f"{key}[{i}]", source) for i, v in enumerate(value)]
    if origin is tuple or tp is tuple:
        if not isinstance(value, list | tuple):
            raise _type_error(key, source, tp, value)
        if not args:
            return tuple(value)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{key}[{i}]", source) for i, v in enumerate(value))
        if len(value) != len(args):
            raise _type_error(key, source, tp, value, f"it needs exactly {len(args)} items")
        return tuple(
            _coerce(v, a, f"{key}[{i}]", source) for i, (v, a) in enumerate(zip(value, args, strict=True))
        )
    if origin is dict or tp is dict:
        if not isinstance(value, Mapping):
            raise _type_error(key, source, tp, value)
        if not args:
            out = dict(value)
        else:
            key_tp, val_tp = args
            out = {
                _coerce(k, key_tp, f"{key}.<key {k!r}>", source): _coerce(v, val_tp, f"{key}.{k}", source)
                for k, v in value.items()
            }
        if source == CLI_SOURCE and isinstance(current, Mapping):
            # dotted keys into a dict field (`--teacher.net.heading best`) change those keys and keep the rest;
            # the whole field given as text (`--teacher.net '{...}'`) replaces it, as a YAML layer does
            return {**current, **out}
        return out
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if isinstance(value, Mapping):
            return _build(tp, value, source, key, current if isinstance(current, tp) else None)
        raise _type_error(key, source, tp, value, "give a mapping of its keys")
    if isinstance(tp, type):
        if isinstance(value, tp):
            return value
        raise _type_error(key, source, tp, value)
    raise TypeError(f"config key '{key}': unsupported field type {tp!r}")


def _field_default(f: dataclasses.Field[Any]) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def _build(cls: type[T], data: Mapping[str, Any], source: str, prefix: str, base: T | None) -> T:
    """Returns a new ``cls`` instance: ``base`` (or the defaults) with the keys in ``data`` applied."""
    where = f"'{prefix}'" if prefix else "top level"
    if not isinstance(data, Mapping):
        raise ConfigError(
            f"config section {where} in {source}: expected a mapping of keys, got {_show(data)}"
        )
    hints = field_types(cls)
    fields = {f.name: f for f in _init_fields(cls)}
    for k in data:
        if k not in fields:
            dotted = f"{prefix}.{k}" if prefix else str(k)
            raise ConfigError(
                f"unknown config key '{dotted}' in {source}; valid keys here: {', '.join(sorted(fields))}"
            )
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        key = f"{prefix}.{name}" if prefix else name
        current = getattr(base, name) if base is not None else _field_default(f)
        if name in data:
            value = data[name]
            dc = nested_dataclass(hints[name])
            if dc is not None and isinstance(value, Mapping):
                kwargs[name] = _build(dc, value, source, key, current if isinstance(current, dc) else None)
            else:
                kwargs[name] = _coerce(value, hints[name], key, source, current)
        elif current is dataclasses.MISSING:
            raise ConfigError(f"config key '{key}' is required but not set in {source} or any earlier layer")
        else:
            kwargs[name] = current
    try:
        obj = cls(**kwargs)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"config section {where} in {source}: {e}") from None
    for f in dataclasses.fields(cls):  # carry over non-init fields of the base
        if not f.init and base is not None and hasattr(base, f.name):
            object.__setattr__(obj, f.name, getattr(base, f.name))
    return obj


def from_dict(cls: type[T], data: Mapping[str, Any], source: str, prefix: str = "") -> T:
    """Builds a config dataclass from a (possibly partial, nested) dict, starting from the defaults.

    Every field of a config dataclass should have a default; a field without one must be set in ``data``.

    Args:
        cls: The dataclass.
        data: Keys to set; nested dataclasses take nested dicts, and keys not given keep their defaults.
        source: Where ``data`` came from (file name or ``"command line"``), for error messages.
        prefix: Dotted key of ``cls`` inside an enclosing config, for error messages.

    Returns:
        A new ``cls`` instance (not yet validated; see :func:`validate_tree`).

    Raises:
        ConfigError: Unknown key, wrong type, or a required key not set.
    """
    return _build(cls, data, source, prefix, None)


def apply_dict(cfg: T, data: Mapping[str, Any], source: str) -> T:
    """Returns a copy of ``cfg`` with the (possibly partial, nested) keys of ``data`` applied.

    Args:
        cfg: A config dataclass instance; it is not modified.
        data: Keys to set, as for :func:`from_dict`.
        source: Where ``data`` came from, for error messages.

    Raises:
        ConfigError: Unknown key or wrong type.
    """
    return _build(type(cfg), data, source, "", cfg)


def validate_tree(cfg: Any, prefix: str = "") -> None:
    """Calls ``validate()`` on every dataclass in ``cfg``, depth-first, children before their parent.

    Dataclasses inside lists, tuples and dict values are visited too. A ``ValueError`` raised by a
    ``validate()`` is turned into a :class:`ConfigError` naming the section.

    Args:
        cfg: The config dataclass instance.
        prefix: Dotted key of ``cfg``, for error messages.

    Raises:
        ConfigError: Some ``validate()`` rejected the config.
    """
    if not dataclasses.is_dataclass(cfg) or isinstance(cfg, type):
        return
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        key = f"{prefix}.{f.name}" if prefix else f.name
        if isinstance(value, list | tuple):
            for i, item in enumerate(value):
                validate_tree(item, f"{key}[{i}]")
        elif isinstance(value, dict):
            for k, item in value.items():
                validate_tree(item, f"{key}.{k}")
        else:
            validate_tree(value, key)
    validate = getattr(cfg, "validate", None)
    if callable(validate):
        try:
            validate()
        except ValueError as e:
            raise ConfigError(
                f"invalid config section {f'{prefix!r}' if prefix else 'top level'}: {e}"
            ) from None


# ----------------------------------------------------------------------------------------------------------
# Profiles and loading
# ----------------------------------------------------------------------------------------------------------


def profiles_dir(override: Path | None = None) -> Path:
    """Returns the directory holding the YAML profiles.

    Args:
        override: Use this directory instead.

    Returns:
        ``override`` if given, else ``$ICROWDNAV_PROFILES_DIR`` if set, else ``pipeline/profiles/``.
    """
    if override is not None:
        return Path(override)
    env = os.environ.get(PROFILES_ENV)
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[1] / "profiles"


def available_profiles(directory: Path | None = None) -> list[str]:
    """Returns the sorted names (file stems) of the ``*.yaml`` profiles.

    Args:
        directory: Profiles directory (default: :func:`profiles_dir`).
    """
    d = profiles_dir(directory)
    if not d.is_dir():
        return []
    return sorted(p.stem for p in d.glob("*.yaml") if p.is_file())


def read_yaml_mapping(path: Path, what: str) -> dict[str, Any]:
    """Reads a YAML file whose top level must be a mapping (an empty file counts as ``{}``).

    Args:
        path: The file.
        what: What it is (``"profile"``, ``"config file"``), for error messages.

    Raises:
        InputMissingError: The file does not exist.
        ConfigError: The file is not valid YAML or its top level is not a mapping.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputMissingError(f"missing {what}: {path}") from None
    except (IsADirectoryError, UnicodeDecodeError) as e:
        raise ConfigError(f"cannot read {what} {path}: {e}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        at = f" at line {mark.line + 1} column {mark.column + 1}" if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise ConfigError(f"malformed YAML in {what} {path}{at}: {problem}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(
            f"{what} {path}: expected a mapping of sections at the top level, got {_show(data)}"
        )
    return data


def _section(data: Mapping[str, Any], name: str, path: Path, what: str) -> dict[str, Any]:
    section = data.get(name)
    if section is None:
        return {}
    if not isinstance(section, dict):
        raise ConfigError(
            f"section '{name}' of {what} {path}: expected a mapping of config keys, got {_show(section)}"
        )
    return section


def _known_only(cls: type, data: Mapping[str, Any]) -> dict[str, Any]:
    """The keys of ``data`` that exist in ``cls`` (recursively for nested dataclasses)."""
    hints = field_types(cls)
    names = {f.name for f in _init_fields(cls)}
    out: dict[str, Any] = {}
    for k, v in data.items():
        if k not in names:
            continue
        dc = nested_dataclass(hints[k])
        out[k] = _known_only(dc, v) if dc is not None and isinstance(v, Mapping) else v
    return out


def parse_overrides(overrides: Mapping[str, str]) -> dict[str, Any]:
    """Turns ``{"sim.camera.width": "64"}`` into the nested dict ``{"sim": {"camera": {"width": <raw "64">}}}``.

    Dashes in keys are read as underscores and leading dashes are dropped (``--max-episode-s`` →
    ``max_episode_s``). The leaf values stay raw strings, to be parsed for the type of their field.

    Args:
        overrides: Dotted key → raw string value.

    Raises:
        ConfigError: A key is empty or malformed, or two keys conflict (``sim`` and ``sim.dt``).
    """
    nested: dict[str, Any] = {}
    for raw_key, value in overrides.items():
        key = raw_key.strip().lstrip("-").replace("-", "_")
        parts = key.split(".")
        if not key or any(not p for p in parts):
            raise ConfigError(
                f"malformed config key {raw_key!r} on the command line: expected e.g. sim.camera.width"
            )
        node = nested
        for i, part in enumerate(parts[:-1]):
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                whole = ".".join(parts[: i + 1])
                raise ConfigError(
                    f"conflicting command-line overrides: '{whole}' is set as a whole and '{key}' sets a key inside it"
                )
            node = child
        if isinstance(node.get(parts[-1]), dict):
            raise ConfigError(
                f"conflicting command-line overrides: '{key}' is set as a whole and keys inside it are set too"
            )
        node[parts[-1]] = _CliText(str(value))
    return nested


def load_config(
    cls: type[T],
    stage: str,
    profile: str = "default",
    overrides: Mapping[str, str] | None = None,
    config_file: Path | None = None,
    profiles_directory: Path | None = None,
) -> T:
    """Builds and validates a stage config from the layers described in the module docstring.

    Args:
        cls: The stage config dataclass (normally a :class:`BaseStageConfig` subclass).
        stage: Section name in the YAML files (the stage's CLI verb).
        profile: Profile name: ``<profiles_dir>/<profile>.yaml``.
        overrides: Dotted key → raw string value from the command line.
        config_file: Optional extra YAML file with ``common``/``<stage>`` sections.
        profiles_directory: Profiles directory (default: :func:`profiles_dir`).

    Returns:
        The validated config, with ``profile`` set to the profile name.

    Raises:
        ConfigError: Unknown profile, malformed YAML, unknown key, wrong type, or a failed ``validate()``.
        InputMissingError: ``config_file`` does not exist.
    """
    pdir = profiles_dir(profiles_directory)
    known = ", ".join(available_profiles(pdir)) or "(none)"
    if not profile or "/" in profile or "\\" in profile or profile.startswith("."):
        raise ConfigError(f"invalid profile name {profile!r}: expected one of {known}")
    profile_path = pdir / f"{profile}.yaml"
    if not profile_path.is_file():
        raise ConfigError(
            f"unknown profile '{profile}' (no file {profile_path}); available profiles: {known}"
        )
    cfg = from_dict(cls, {}, "defaults")
    layers: list[tuple[Path, str]] = [(profile_path, "profile")]
    if config_file is not None:
        config_file = Path(config_file)
        if not config_file.exists():
            raise InputMissingError(f"missing config file: {config_file}")
        layers.append((config_file, "config file"))
    for path, what in layers:
        data = read_yaml_mapping(path, what)
        common = _section(data, COMMON_SECTION, path, what)
        if common:
            cfg = apply_dict(cfg, _known_only(cls, common), f"{path} (section '{COMMON_SECTION}')")
        section = _section(data, stage, path, what)
        if section:
            cfg = apply_dict(cfg, section, f"{path} (section '{stage}')")
    if overrides:
        cfg = apply_dict(cfg, parse_overrides(overrides), CLI_SOURCE)
    if any(f.name == "profile" for f in dataclasses.fields(cfg)):
        object.__setattr__(cfg, "profile", profile)  # also works for frozen configs
    validate_tree(cfg)
    return cfg


# ----------------------------------------------------------------------------------------------------------
# Serialisation
# ----------------------------------------------------------------------------------------------------------


def to_plain(value: Any) -> Any:
    """Converts a config value to plain JSON/YAML data (paths → str, tuples → lists, enums → values)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, enum.Enum):
        return to_plain(value.value)
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, list | tuple):
        return [to_plain(v) for v in value]
    if isinstance(value, Mapping):
        return {str(k): to_plain(v) for k, v in value.items()}
    return value


def to_dict(cfg: Any) -> dict[str, Any]:
    """Returns a config dataclass as a nested dict of plain JSON/YAML-able values.

    Args:
        cfg: A config dataclass instance.
    """
    if not dataclasses.is_dataclass(cfg) or isinstance(cfg, type):
        raise TypeError(f"to_dict: expected a dataclass instance, got {type(cfg).__name__}")
    return to_plain(cfg)


def config_hash(cfg: Any) -> str:
    """Returns the sha256 hex of the canonical JSON of ``to_dict(cfg)``.

    The top-level fields ``overwrite`` and ``resume`` (how to treat an existing output), ``data_dir`` (where
    it lives: manifests record paths relative to it, so a moved data directory stays up to date) and ``profile``
    (a name; the values it set are in the hash) are left out.

    Args:
        cfg: A config dataclass instance.
    """
    data = {k: v for k, v in to_dict(cfg).items() if k not in HASH_EXCLUDED_FIELDS}
    canonical = json.dumps(data, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(canonical.encode("utf-8")).hexdigest()


def dump_yaml(cfg: Any, path: Path) -> Path:
    """Writes the resolved config as YAML, atomically.

    Args:
        cfg: A config dataclass instance.
        path: Destination file.

    Returns:
        ``path``.
    """
    header = f"# resolved {type(cfg).__name__}; config_hash {config_hash(cfg)}\n"
    body = yaml.safe_dump(to_dict(cfg), sort_keys=False, default_flow_style=None, allow_unicode=True)
    return atomic_write_text(Path(path), header + body)


def _format_default(value: Any) -> str:
    if value is dataclasses.MISSING:
        return "(required)"
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, enum.Enum):
        return repr(value.value)
    return repr(value)


def describe_fields(cls: type, prefix: str = "", instance: Any = None) -> list[tuple[str, str, str, str]]:
    """Lists every leaf config key of ``cls``, recursing into nested dataclasses.

    Args:
        cls: The config dataclass.
        prefix: Dotted prefix of ``cls``.
        instance: Instance to read defaults from (default: the field defaults).

    Returns:
        ``(dotted key, type name, default repr, help)`` per key, in declaration order.
    """
    hints = field_types(cls)
    rows: list[tuple[str, str, str, str]] = []
    for f in _init_fields(cls):
        key = f"{prefix}.{f.name}" if prefix else f.name
        default = getattr(instance, f.name) if instance is not None else _field_default(f)
        tp = hints[f.name]
        if isinstance(tp, type) and dataclasses.is_dataclass(tp):
            rows.extend(describe_fields(tp, key, default if isinstance(default, tp) else None))
            continue
        help_ = str(f.metadata.get("help", "")) or _field_comments(cls).get(f.name, "")
        rows.append((key, type_name(tp), _format_default(default), help_))
    return rows


@functools.cache
def _field_comments(cls: type) -> dict[str, str]:
    """``{field: comment}`` from trailing ``# comments`` on field lines of a dataclass's source (as draccus does).

    Config dataclasses document each field with a comment on its line; ``--help`` shows it.
    """
    out: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            src = inspect.getsource(klass)
        except (OSError, TypeError):
            continue
        for m in re.finditer(r"^\s+(\w+)\s*:[^#\n]*#\s*(.+)$", src, re.MULTILINE):
            out[m.group(1)] = m.group(2).strip()
    return out


_RUN_NAME = re.compile(r"^[A-Za-z0-9][\w.-]*$")


def check_run_name(name: str, key: str = "run_name") -> None:
    """An output folder name must be one path component (letters, digits, ``_.-``): it may not escape
    ``DATA_DIR``.

    Raises:
        ConfigError: naming the key and the value.
    """
    if not _RUN_NAME.match(name) or name in (".", ".."):
        raise ConfigError(f"{key}: expected one folder name of letters, digits and _.- , got {name!r}")
