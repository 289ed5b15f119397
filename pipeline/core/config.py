"""Typed stage configs on draccus: dataclasses filled from YAML profiles, an optional config file and CLI overrides.

A stage config is a dataclass deriving from :class:`BaseStageConfig`; it may nest other dataclasses
(``sim: SimConfig``), and any of them may define ``validate(self) -> None`` raising :class:`ConfigError`.
:func:`load_config` layers, lowest precedence first:

1. the dataclass defaults,
2. the ``common`` section of ``pipeline/profiles/<profile>.yaml`` (only keys the stage config has),
3. the ``<stage>`` section of that profile,
4. the ``common`` and ``<stage>`` sections of ``--config FILE``,
5. command-line overrides ``--sim.camera.width_px 320`` (dotted keys),

then calls every ``validate()`` (children first), so that every check fails before any work starts.

What draccus (the config library lerobot uses) does here:

* decoding: every layer is turned into the typed, nested dataclass by ``draccus.decode`` — the recursion over
  nested dataclasses, ``list``/``tuple``/``dict``, ``X | None`` and other unions, enums and ``Any``, and the
  detection of unknown and of missing required keys (reported by draccus as a key path, reworded here);
* encoding: :func:`to_dict` is ``draccus.encode`` (paths → str, tuples → lists; enums would be stored by name);
* help: the help of a field comes from its comment or docstring, read by ``draccus.wrappers.docstring``
  (a ``metadata={"help": ...}`` on the field wins).

What stays ours, each because draccus does not do it (measured with draccus 0.10.0):

* profile layering (defaults → ``common`` → ``<stage>`` → ``--config`` file → command line): ``draccus.parse``
  merges one ``--config_path`` file (decoded as the whole config, no sections) with the command line. Merging is
  type-aware (:func:`_merge`): a nested dataclass is merged key by key, any other value (a ``dict`` field too)
  is replaced, and dotted command-line keys into a ``dict`` field (``--teacher.net.heading best``) change only
  those keys. Each layer is decoded on its own, so an error names the file it came from; a value that no layer
  sets stays the default object as written (:func:`_overlay`: decoding ``{"n_steps": 512}`` in a
  ``dict[str, float]`` default would store ``512.0`` and change the config hashes of the manifests);
* strict leaf types, installed into draccus's decoder registry (``draccus.decode.register``, its extension
  point): draccus decodes ``True`` into an int field as ``1``, ``3`` into a str field as ``'3'``, the string
  ``"12"`` into a ``tuple[float, float]`` as ``(1.0, 2.0)``, and has no decoder for ``Literal`` ("No decoding
  function for type typing.Literal[...]"). The strict int/float/bool/str/Path decoders are installed only while
  we decode (draccus's own CLI needs its lenient ones: it YAML-parses every argv value first, so ``--run_name
  007`` reaches the str decoder as the int ``7``); the ``Literal`` and ``tuple`` decoders stay registered;
* command-line values: draccus YAML-parses every value, which turns ``--run_name 007`` into ``'7'``, and rejects
  ``--scenes a,b`` for a list ("Failed when parsing value='a,b'") and ``--flag 1`` ("Couldn't parse '1' into a
  bool"). Here a value is read for the type of its
  field (:func:`_from_cli`): ``str``/``Path`` verbatim, ``bool`` from ``true/false/1/0/yes/no/on/off``, lists and
  tuples also as ``a,b,c``, ``none``/``null`` for ``X | None``, anything else with ``yaml.safe_load``;
* error wording: a ``draccus.utils.DecodingError`` carries the key path; :func:`_explain` turns it into one line
  naming the key, the file (or "command line"), the expected type and the actual value;
* ``validate()`` children first (draccus has no validation hook; a :class:`FieldValueError` raised there is
  reported with the full dotted key), the config hash of the manifests (:func:`config_hash`) and the profile
  files themselves (``yaml.safe_load``: draccus reads files with ``yaml.FullLoader`` plus ``!include``).

Scene files (:mod:`sim.scene`) are decoded and checked by this same machinery.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import functools
import hashlib
import json
import math
import os
import re
import types
import typing
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal, TypeVar

import draccus
import yaml
from draccus.parsers.decoding import decode_tuple, get_decoding_fn
from draccus.utils import DecodingError, ParsingError
from draccus.wrappers import docstring

from pipeline.core.artifacts import atomic_write_text
from pipeline.core.errors import ConfigError, InputMissingError

T = TypeVar("T")

PROFILES_ENV = "ICROWDNAV_PROFILES_DIR"
COMMON_SECTION = "common"
CLI_SOURCE = "command line"
HASH_EXCLUDED_FIELDS: frozenset[str] = frozenset({"overwrite", "resume", "data_dir", "profile", "device", "executor",
                                                  "ray_address", "ray_files"})

_TRUE_WORDS = frozenset({"true", "1", "yes", "y", "on"})
_FALSE_WORDS = frozenset({"false", "0", "no", "n", "off"})
_NONE_WORDS = frozenset({"none", "null", "~"})


@dataclass
class BaseStageConfig:
    """Fields every stage has. Stage configs subclass this."""

    #: A stage config's own fields that say how parallel it runs, not what it makes (``workers`` where every
    #: episode is seeded by itself; torch ``threads``): left out of its config hash (:func:`hash_excluded_fields`),
    #: so a run resumed or repeated with another worker or thread count keeps its output.
    PLACEMENT_FIELDS: ClassVar[tuple[str, ...]] = ()

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
        metadata={"help": "continue a killed run: a resumable stage continues its partial output, any other "
                          "stage (published atomically) keeps an up-to-date output and rebuilds a missing or "
                          "stale one"},
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


class FieldValueError(ValueError):
    """Raised by a ``validate()``: one of its own fields has a value out of range.

    :func:`validate_tree` turns it into a :class:`ConfigError` naming the full dotted key, which the section
    itself does not know (``obstacles[0].box.color``).

    Args:
        name: The field of the section that raised it.
        expected: What the value should be (``"three numbers in [0, 1]"``).
        actual: The value it has.
    """

    def __init__(self, name: str, expected: str, actual: Any):
        super().__init__(f"{name}: expected {expected}, got {actual!r}")
        self.name, self.expected, self.actual = name, expected, actual


# ----------------------------------------------------------------------------------------------------------
# Types: names for messages, and the decoders draccus lacks or decodes too leniently
# ----------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _CliText:
    """A raw command-line value, read according to the type of the field it lands in (:func:`_from_cli`)."""

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


def _strip(tp: Any) -> Any:
    """``Annotated[X, ...]`` → ``X``; ``X | None`` → ``X`` (one non-None arm only)."""
    if typing.get_origin(tp) is typing.Annotated:
        return _strip(typing.get_args(tp)[0])
    if _is_union(tp):
        arms = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(arms) == 1:
            return _strip(arms[0])
    return tp


def nested_dataclass(tp: Any) -> type | None:
    """Returns the dataclass in ``tp`` if ``tp`` is a dataclass or ``Dataclass | None``, else None.

    Args:
        tp: A type annotation.
    """
    inner = _strip(tp)
    return inner if isinstance(inner, type) and dataclasses.is_dataclass(inner) else None


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


def _show(value: Any) -> str:
    text = repr(value.text if isinstance(value, _CliText) else value)
    if len(text) > 80:
        text = text[:77] + "..."
    return f"{text} ({type(value.text if isinstance(value, _CliText) else value).__name__})"


def _fail(path: Any, tp: Any) -> DecodingError:
    return DecodingError(path, f"expected {type_name(tp)}")  # the message is rebuilt by _explain


def _decode_int(raw: Any, path: Any) -> int:
    if isinstance(raw, int) and not isinstance(raw, bool):
        return raw
    if isinstance(raw, float) and raw.is_integer():
        return int(raw)
    if isinstance(raw, str):  # YAML reads 1e3 (no dot) as a string
        with contextlib.suppress(ValueError):
            return int(raw.strip())
        with contextlib.suppress(ValueError):
            as_float = float(raw)
            if as_float.is_integer():
                return int(as_float)
    raise _fail(path, int)


def _decode_float(raw: Any, path: Any) -> float:
    if isinstance(raw, int | float) and not isinstance(raw, bool):
        return float(raw)
    if isinstance(raw, str):  # YAML reads 1e-3 (no dot) as a string
        with contextlib.suppress(ValueError):
            return float(raw.strip())
    raise _fail(path, float)


def _decode_bool(raw: Any, path: Any) -> bool:
    if isinstance(raw, bool):
        return raw
    raise _fail(path, bool)


def _decode_str(raw: Any, path: Any) -> str:
    if isinstance(raw, str):
        return raw
    raise _fail(path, str)


def _decode_path(raw: Any, path: Any) -> Path:
    if isinstance(raw, str | os.PathLike):
        return Path(raw)
    raise _fail(path, Path)


def _decode_literal(tp: Any, raw: Any, path: Any) -> Any:
    for option in typing.get_args(tp):
        if raw == option and type(raw) is type(option):
            return option
    raise _fail(path, tp)


def _decode_tuple(tp: Any, raw: Any, path: Any) -> tuple[Any, ...]:
    if not isinstance(raw, list | tuple):  # draccus iterates any value: "12" would become (1.0, 2.0)
        raise _fail(path, tp)
    return decode_tuple(*typing.get_args(tp))(raw, path)


draccus.decode.register(Literal, _decode_literal, include_subclasses=True)
draccus.decode.register(tuple, _decode_tuple, include_subclasses=True)
_STRICT = {int: _decode_int, float: _decode_float, bool: _decode_bool, str: _decode_str, Path: _decode_path}


@contextlib.contextmanager
def _strict_scalars() -> Iterator[None]:
    """Installs the strict scalar decoders in draccus's registry for the duration of one decode."""
    before = {t: draccus.decode.registry[t] for t in _STRICT}
    for t, fn in _STRICT.items():
        draccus.decode.register(t, fn)
    get_decoding_fn.cache_clear()
    try:
        yield
    finally:
        for t, reg in before.items():
            draccus.decode.register(t, reg.func, include_subclasses=reg.include_subclasses)
        get_decoding_fn.cache_clear()


# ----------------------------------------------------------------------------------------------------------
# Decoding with our error wording
# ----------------------------------------------------------------------------------------------------------


def _join(prefix: str, key: Any) -> str:
    return f"{prefix}.{key}" if prefix else str(key)


def _step(tp: Any, value: Any, key: str, part: str) -> tuple[Any, Any, str]:
    """One step down a draccus key path: the type, the raw value and the dotted key of the child ``part``."""
    tp = _strip(tp)
    origin = typing.get_origin(tp) or tp
    args = typing.get_args(tp)
    dc = nested_dataclass(tp)
    if dc is not None:
        child = value.get(part) if isinstance(value, Mapping) else None
        return field_types(dc).get(part, Any), child, _join(key, part)
    if origin in (list, tuple) and str(part).isdigit():
        i = int(part)
        child = value[i] if isinstance(value, list | tuple) and i < len(value) else None
        if origin is tuple and args and args[-1] is not Ellipsis:
            item = args[i] if i < len(args) else Any
        else:
            item = args[0] if args else Any
        return item, child, f"{key}[{i}]"
    if origin is dict:
        key_tp, val_tp = args or (Any, Any)
        if str(part).startswith("key="):
            k = str(part)[4:]
            return key_tp, k, f"{key}.<key {k!r}>"
        child = value.get(part) if isinstance(value, Mapping) else None
        return val_tp, child, _join(key, part)
    return Any, None, _join(key, part)


def _explain(cls: type, raw: Mapping[str, Any], path: Any, source: str, prefix: str) -> ConfigError:
    """Turns the key path of a draccus ``DecodingError`` into one line: key, source, expected, actual."""
    tp, value, key = cls, raw, prefix
    for part in path:
        bare = _strip(tp)
        if typing.get_origin(bare) is tuple and Ellipsis not in typing.get_args(bare):
            break  # a fixed-size tuple (a point, a range) is reported whole: 'bounds', not 'bounds[2]'
        tp, value, key = _step(tp, value, key, part)
    arm = _strip(tp)
    if arm is not tp and value is not None and (typing.get_origin(arm) or dataclasses.is_dataclass(arm)):
        # draccus reports an error inside the X of `X | None` at the union: decode X alone to find the key
        try:
            with _strict_scalars():
                draccus.decode(arm, value)
        except DecodingError as e:
            return _explain(arm, value, tuple(e.key_path), source, key)
    dc = nested_dataclass(tp)
    if dc is not None and isinstance(value, Mapping):
        names = [f.name for f in _init_fields(dc)]
        unknown = [k for k in value if k not in names]
        if unknown:
            where = f"in '{key}'" if key else "at the top level"
            return ConfigError(
                f"unknown config key '{_join(key, unknown[0])}' in {source}; "
                f"valid keys {where}: {', '.join(sorted(names))}"
            )
        required = [
            f.name
            for f in _init_fields(dc)
            if f.name not in value and f.default is f.default_factory is dataclasses.MISSING
        ]
        if required:
            return ConfigError(
                f"config key '{_join(key, required[0])}' is required but not set in {source}"
            )
    bare = _strip(tp)
    note = ""
    if dc is not None:
        note = "; give a mapping of its keys"
    elif (
        typing.get_origin(bare) is tuple
        and Ellipsis not in typing.get_args(bare)
        and isinstance(value, list | tuple)
        and len(value) != len(typing.get_args(bare))
    ):
        note = f"; it needs exactly {len(typing.get_args(bare))} items"
    elif bare is str and isinstance(value, int | float):
        note = "; quote it in YAML"
    elif bare is bool and source == CLI_SOURCE:
        note = "; use true/false/1/0/yes/no"
    expected = type_name(tp)
    if typing.get_origin(tp) is Literal:
        expected = "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    return ConfigError(f"config key '{key}' in {source}: expected {expected}, got {_show(value)}{note}")


def _decode(cls: type[T], raw: Mapping[str, Any], source: str, prefix: str = "") -> T:
    """``draccus.decode`` with the strict scalar decoders, errors reworded by :func:`_explain`."""
    try:
        with _strict_scalars():
            return draccus.decode(cls, raw)
    except DecodingError as e:
        raise _explain(cls, raw, tuple(e.key_path), source, prefix) from None
    except ParsingError as e:  # the dataclass's own __init__/__post_init__ refused the values
        raise ConfigError(f"config in {source}: {e.__cause__ or e}") from None


# ----------------------------------------------------------------------------------------------------------
# Layering: command-line text, type-aware merge
# ----------------------------------------------------------------------------------------------------------


def _yaml_scalar(text: str, key: str) -> Any:
    try:
        return yaml.safe_load(text)
    except RecursionError:
        raise ConfigError(f"config key '{key}' in {CLI_SOURCE}: cannot parse a value nested this deeply") from None
    except yaml.YAMLError as e:
        problem = getattr(e, "problem", None) or type(e).__name__
        raise ConfigError(
            f"config key '{key}' in {CLI_SOURCE}: cannot parse {text!r} as a YAML value ({problem})"
        ) from None


def _from_cli(text: str, tp: Any, key: str) -> Any:
    """Reads a command-line string for a field of type ``tp`` into a raw value for draccus to decode."""
    stripped = text.strip()
    if _is_union(tp) and type(None) in typing.get_args(tp) and stripped.lower() in _NONE_WORDS:
        return None
    tp = _strip(tp)
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is Literal:
        for option in args:
            if isinstance(option, bool):
                word = stripped.lower()
                if (option and word in _TRUE_WORDS) or (not option and word in _FALSE_WORDS):
                    return option
            elif stripped == str(option):
                return option
        return text  # the Literal decoder names the allowed values
    if tp is bool:
        word = stripped.lower()
        return True if word in _TRUE_WORDS else False if word in _FALSE_WORDS else text
    if tp is str or (isinstance(tp, type) and issubclass(tp, Path)):
        return text
    if origin in (list, tuple) or tp in (list, tuple):
        if stripped.startswith("["):
            return _yaml_scalar(text, key)
        if not stripped:
            return []
        parts = [p.strip() for p in text.split(",")]
        if origin is tuple and args and args[-1] is not Ellipsis:
            item_types = [args[i] if i < len(args) else Any for i in range(len(parts))]
        else:
            item_types = [args[0] if args else Any] * len(parts)
        return [_from_cli(p, t, f"{key}[{i}]") for i, (p, t) in enumerate(zip(parts, item_types, strict=True))]
    return _yaml_scalar(text, key)


def _cli_leaves(value: Any, tp: Any, key: str) -> Any:
    """Reads every command-line leaf of a nested mapping (dotted keys into a ``dict`` field)."""
    if isinstance(value, _CliText):
        return _from_cli(value.text, tp, key)
    if isinstance(value, Mapping):
        val_tp = (typing.get_args(_strip(tp)) or (Any, Any))[1] if typing.get_origin(_strip(tp)) is dict else Any
        return {k: _cli_leaves(v, val_tp, _join(key, k)) for k, v in value.items()}
    return value


def _has_cli_text(value: Any) -> bool:
    return isinstance(value, _CliText) or (
        isinstance(value, Mapping) and any(_has_cli_text(v) for v in value.values())
    )


def _merge(cls: type, base: Mapping[str, Any], data: Mapping[str, Any], prefix: str) -> dict[str, Any]:
    """``base`` (plain values of ``cls``) with the layer ``data`` applied: nested dataclasses are merged key by key,
    any other value is replaced, and dotted command-line keys into a ``dict`` field change only those keys.
    Unknown keys are kept, for draccus to report."""
    hints = field_types(cls)
    names = {f.name for f in _init_fields(cls)}
    out = dict(base)
    for k, v in data.items():
        key = _join(prefix, k)
        if k not in names:
            out[k] = v
            continue
        tp = hints[k]
        current = base.get(k)
        if isinstance(v, _CliText):
            v = _from_cli(v.text, tp, key)  # the whole field as text: replaces it, as a YAML layer does
        elif isinstance(v, Mapping) and _has_cli_text(v) and typing.get_origin(_strip(tp)) is dict:
            v = {**(current if isinstance(current, Mapping) else {}), **_cli_leaves(v, tp, key)}
        dc = nested_dataclass(tp)
        if dc is not None and isinstance(v, Mapping):
            v = _merge(dc, current if isinstance(current, Mapping) else {}, v, key)
        out[k] = v
    return out


def _defaults(cls: type) -> dict[str, Any]:
    """The plain values of the defaults of ``cls`` (fields without a default are left out)."""
    values = {f.name: _field_default(f) for f in _init_fields(cls)}
    return {k: draccus.encode(v) for k, v in values.items() if v is not dataclasses.MISSING}


def _overlay(decoded: T, base: Any, data: Mapping[str, Any], prefix: str) -> T:
    """``decoded`` where the layer ``data`` set a key, ``base`` (or the field default) everywhere else.

    A value no layer sets stays the default object as written (``{"n_steps": 512}`` in a ``dict[str, float]``
    field keeps its int): draccus would decode it to ``512.0``, which would change the config hashes.
    """
    cls = type(decoded)
    hints = field_types(cls)
    kwargs: dict[str, Any] = {}
    for f in _init_fields(cls):
        key = _join(prefix, f.name)
        old = getattr(base, f.name) if base is not None else _field_default(f)
        if f.name not in data and old is not dataclasses.MISSING:
            kwargs[f.name] = old
            continue
        new, given = getattr(decoded, f.name), data.get(f.name)
        if isinstance(given, _CliText) and nested_dataclass(hints[f.name]) is not None:
            given = _from_cli(given.text, hints[f.name], key)
        if isinstance(given, Mapping) and dataclasses.is_dataclass(new) and type(old) is type(new):
            new = _overlay(new, old, given, key)
        kwargs[f.name] = new
    return cls(**kwargs)


def _field_default(f: dataclasses.Field[Any]) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


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
    if not isinstance(data, Mapping):
        where = f"'{prefix}'" if prefix else "top level"
        raise ConfigError(f"config section {where} in {source}: expected a mapping of keys, got {_show(data)}")
    decoded = _decode(cls, _merge(cls, _defaults(cls), data, prefix), source, prefix)
    return _overlay(decoded, None, data, prefix)


def apply_dict(cfg: T, data: Mapping[str, Any], source: str) -> T:
    """Returns a copy of ``cfg`` with the (possibly partial, nested) keys of ``data`` applied.

    Args:
        cfg: A config dataclass instance; it is not modified.
        data: Keys to set, as for :func:`from_dict`.
        source: Where ``data`` came from, for error messages.

    Raises:
        ConfigError: Unknown key or wrong type.
    """
    if not isinstance(data, Mapping):
        raise ConfigError(f"config section top level in {source}: expected a mapping of keys, got {_show(data)}")
    decoded = _decode(type(cfg), _merge(type(cfg), to_dict(cfg), data, ""), source)
    return _overlay(decoded, cfg, data, "")


def _visit(value: Any, key: str) -> None:
    """One field value of a config, a scene or a scenario file: a float must be finite (NaN passes every range
    comparison — ``not lo <= nan <= hi`` is the only safe spelling — and inf silently switches limits off, so they
    are refused here, once for every field, before any ``validate()`` compares them); lists, tuples and dict values
    are walked; a dataclass is validated (:func:`validate_tree`)."""
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ConfigError(f"config key '{key}': expected a finite number, got {value!r}")
    elif isinstance(value, list | tuple):
        for i, item in enumerate(value):
            _visit(item, f"{key}[{i}]")
    elif isinstance(value, dict):
        for k, item in value.items():
            _visit(item, f"{key}.{k}")
    else:
        validate_tree(value, key)


def validate_tree(cfg: Any, prefix: str = "") -> None:
    """Calls ``validate()`` on every dataclass in ``cfg``, depth-first, children before their parent.

    Every float field (and every float inside a list, tuple or dict field) is checked finite (:func:`_visit`) before
    the section's own ``validate()`` runs, so it only ever compares finite numbers.

    Dataclasses inside lists, tuples and dict values are visited too. A ``ValueError`` raised by a
    ``validate()`` is turned into a :class:`ConfigError` naming the section (a :class:`FieldValueError`: naming
    the dotted key, the expected and the actual value).

    Args:
        cfg: The config dataclass instance.
        prefix: Dotted key of ``cfg``, for error messages.

    Raises:
        ConfigError: Some ``validate()`` rejected the config.
    """
    if not dataclasses.is_dataclass(cfg) or isinstance(cfg, type):
        return
    for f in dataclasses.fields(cfg):
        _visit(getattr(cfg, f.name), _join(prefix, f.name))
    validate = getattr(cfg, "validate", None)
    if callable(validate):
        try:
            validate()
        except FieldValueError as e:
            raise ConfigError(
                f"config key '{_join(prefix, e.name)}': expected {e.expected}, got {e.actual!r}"
            ) from None
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


MAX_YAML_BYTES = 1 << 20  # 1 MiB: the largest shipped data file is ~2 KB; PyYAML reads ~80 KB/s of nested YAML


def read_yaml(path: Path, what: str, max_bytes: int = MAX_YAML_BYTES) -> Any:
    """Reads a YAML file (``yaml.safe_load``; an empty file reads as None).

    Args:
        path: The file.
        what: What it is (``"profile"``, ``"config file"``, ``"scene file"``), for error messages.
        max_bytes: Larger files are refused before they are read (a 10 MB file spends minutes in the parser).

    Raises:
        InputMissingError: The file does not exist.
        ConfigError: The file cannot be read, is larger than ``max_bytes``, or is not valid YAML (naming the
            line and column).
    """
    path = Path(path)
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise InputMissingError(f"missing {what}: {path}") from None
    except OSError as e:
        raise ConfigError(f"cannot read {what} {path}: {e.strerror or e}") from None
    if size > max_bytes:
        raise ConfigError(f"{what} {path}: expected at most {max_bytes} bytes (the limit), got {size} bytes")
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputMissingError(f"missing {what}: {path}") from None
    except (IsADirectoryError, UnicodeDecodeError) as e:
        raise ConfigError(f"cannot read {what} {path}: {e}") from None
    except OSError as e:  # permission denied, a FIFO, ...
        raise ConfigError(f"cannot read {what} {path}: {e.strerror or e}") from None
    try:
        return yaml.safe_load(text)
    except RecursionError:
        raise ConfigError(f"malformed YAML in {what} {path}: nested too deeply to parse") from None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        at = f" at line {mark.line + 1} column {mark.column + 1}" if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise ConfigError(f"malformed YAML in {what} {path}{at}: {problem}") from None


def read_yaml_mapping(path: Path, what: str) -> dict[str, Any]:
    """Reads a YAML file whose top level must be a mapping (an empty file counts as ``{}``).

    Args:
        path: The file.
        what: What it is (``"profile"``, ``"config file"``), for error messages.

    Raises:
        InputMissingError: The file does not exist.
        ConfigError: The file is not valid YAML or its top level is not a mapping.
    """
    data = read_yaml(path, what)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{what} {path}: expected a mapping of sections at the top level, got {_show(data)}")
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
    ``max_episode_s``). The leaf values stay raw strings, to be read for the type of their field.

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
        raise ConfigError(f"unknown profile '{profile}' (no file {profile_path}); available profiles: {known}")
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
# Serialisation and help
# ----------------------------------------------------------------------------------------------------------


def to_dict(cfg: Any) -> dict[str, Any]:
    """Returns a config dataclass as a nested dict of plain JSON/YAML-able values (``draccus.encode``).

    Args:
        cfg: A config dataclass instance.
    """
    if not dataclasses.is_dataclass(cfg) or isinstance(cfg, type):
        raise TypeError(f"to_dict: expected a dataclass instance, got {type(cfg).__name__}")
    return draccus.encode(cfg)


def hash_excluded_fields(cfg: Any) -> frozenset[str]:
    """The top-level fields of ``cfg`` left out of its config hash: :data:`HASH_EXCLUDED_FIELDS` and the fields its
    class names in ``PLACEMENT_FIELDS`` (:class:`BaseStageConfig`)."""
    own = frozenset(getattr(type(cfg), "PLACEMENT_FIELDS", ()))
    names = {f.name for f in dataclasses.fields(cfg)}
    if not own <= names:
        raise TypeError(f"{type(cfg).__name__}.PLACEMENT_FIELDS names fields it does not have: {sorted(own - names)}")
    return HASH_EXCLUDED_FIELDS | own


def config_hash(cfg: Any) -> str:
    """Returns the sha256 hex of the canonical JSON of ``to_dict(cfg)``.

    The top-level fields ``overwrite`` and ``resume`` (how to treat an existing output), ``data_dir`` (where
    it lives: manifests record paths relative to it, so a moved data directory stays up to date), ``profile``
    (a name; the values it set are in the hash), ``device`` (where it is computed, :mod:`pipeline.core.device`:
    a run resumes on another device; the counts of the manifest record the one used) and ``executor`` /
    ``ray_address`` / ``ray_files`` (where its jobs run and how their files travel, :mod:`pipeline.core.executor`:
    the same results either way) are left out, and so are the fields a stage config names in ``PLACEMENT_FIELDS``
    (how many processes or threads compute it: :func:`hash_excluded_fields`).

    Args:
        cfg: A config dataclass instance.
    """
    excluded = hash_excluded_fields(cfg)
    data = {k: v for k, v in to_dict(cfg).items() if k not in excluded}
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


def field_help(cls: type, name: str) -> str:
    """The help of a field: its ``metadata["help"]``, else its comment or docstring (read by draccus).

    Args:
        cls: The dataclass.
        name: The field.
    """
    meta = next((f.metadata.get("help") for f in dataclasses.fields(cls) if f.name == name), None)
    if meta:
        return str(meta)
    try:
        doc = docstring.get_attribute_docstring(cls, name)
    except Exception:  # draccus gives up on classes without source (as its own help does)
        return ""
    return " ".join((docstring.get_preferred_help_text(doc) or "").split())


def describe_fields(cls: type, prefix: str = "", instance: Any = None) -> list[tuple[str, str, str, str]]:
    """Lists every leaf config key of ``cls``, recursing into nested dataclasses.

    Args:
        cls: The config dataclass.
        prefix: Dotted prefix of ``cls``.
        instance: Instance to read defaults from (default: the field defaults).

    Returns:
        ``(dotted key, type name, default, help)`` per key, in declaration order.
    """
    hints = field_types(cls)
    rows: list[tuple[str, str, str, str]] = []
    for f in _init_fields(cls):
        key = _join(prefix, f.name)
        default = getattr(instance, f.name) if instance is not None else _field_default(f)
        tp = hints[f.name]
        if isinstance(tp, type) and dataclasses.is_dataclass(tp):
            rows.extend(describe_fields(tp, key, default if isinstance(default, tp) else None))
            continue
        if default is dataclasses.MISSING:
            shown = "(required)"
        elif isinstance(default, os.PathLike):
            shown = os.fspath(default)
        else:
            shown = repr(default.value if isinstance(default, enum.Enum) else default)
        rows.append((key, type_name(tp), shown, field_help(cls, f.name)))
    return rows


_RUN_NAME = re.compile(r"^[A-Za-z0-9][\w.-]*$")


def check_run_name(name: str, key: str = "run_name") -> None:
    """An output folder name must be one path component (letters, digits, ``_.-``): it may not escape
    ``DATA_DIR``.

    Raises:
        ConfigError: naming the key and the value.
    """
    if not _RUN_NAME.match(name) or name in (".", ".."):
        raise ConfigError(f"{key}: expected one folder name of letters, digits and _.- , got {name!r}")
