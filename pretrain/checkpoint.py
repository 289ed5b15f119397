"""The BEV encoder checkpoint: what ``icrowdnav pretrain`` publishes and what ``train`` loads.

Tree (``DATA_DIR/checkpoints/<name>/``, default name ``bev``)::

    encoder.safetensors     frozen encoder weights: ResNet-18 trunk, neck, temporal model (BatchNorm buffers too)
    heads.safetensors       pretext heads (occupancy logits; not needed to use the encoder)
    encoder.json            everything a consumer needs: encoder config (grid bounds, channels, T, lift stride),
                            cameras (K, T_base_cam, size, depth range), s_bev shape, targets, dataset, step
    metrics.json            validation IoU per target in the cameras' field of view (final + per epoch), counts
    train_log.csv           step, epoch, lr, losses (one row per logged step)
    tb/                     TensorBoard events
    figures/                sample_<k>.png (inputs, true and predicted BEV maps), curves.png, fov.png
    state/last.pt           training state for --resume (weights, optimizer, scheduler, RNG, step)
    config.yaml, manifest.json   resolved stage config and provenance (written last: a checkpoint without
                            manifest.json is unfinished and is refused by :func:`load_encoder`)
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file
from safetensors.torch import save as save_safetensors_bytes

from pipeline.core.artifacts import atomic_write_bytes, atomic_write_text
from pipeline.core.errors import CorruptArtifactError, InputMissingError
from pipeline.core.manifest import MANIFEST_NAME, release_output, verify_output
from pretrain.geometry import Camera
from pretrain.model import LEGACY_ENCODER, BEVEncoder, EncoderConfig, PretextHeads

ENCODER_WEIGHTS = "encoder.safetensors"
HEADS_WEIGHTS = "heads.safetensors"
ENCODER_JSON = "encoder.json"
METRICS_JSON = "metrics.json"
STATE_FILE = "state/last.pt"
FORMAT_VERSION = 1


def save_safetensors(module: torch.nn.Module, path: Path, metadata: dict[str, str] | None = None) -> None:
    """Saves a module's state dict atomically (temporary name, then rename).

    The tensors are written from CPU copies (a module trained on a GPU loads on any machine). The same weights and
    metadata give the same bytes: safetensors writes its metadata from a Rust hash map
    (random order per call), so the metadata travels as one key, ``icrowdnav``, holding sorted JSON. Rewriting a
    file that a finished output's manifest lists (a ``--resume`` run writing in place) first drops that manifest
    (:func:`pipeline.core.manifest.release_output`): the directory is unfinished until its stage writes a new one.
    """
    save_tensors(module.state_dict(), path, metadata)


def save_tensors(tensors: Mapping[str, torch.Tensor], path: Path, metadata: dict[str, str] | None = None) -> None:
    """:func:`save_safetensors` of a mapping of names to tensors (not a module's state dict)."""
    path = Path(path)
    state = {k: v.detach().cpu().contiguous().clone() for k, v in tensors.items()}  # from any device
    meta = {"icrowdnav": json.dumps(metadata, sort_keys=True)} if metadata else None
    blob = save_safetensors_bytes(state, metadata=meta)
    release_output(path)
    atomic_write_bytes(path, blob)


def check_finite(tensors: Mapping[str, Any], path: Path, prefix: str = "") -> None:
    """Refuses NaN or infinite values in any floating-point tensor of a (nested) mapping read from ``path``.

    Raises:
        CorruptArtifactError: names the file, the first such tensor and how many of its values are not finite.
    """
    for name, value in tensors.items():
        key = f"{prefix}{name}"
        if isinstance(value, Mapping):
            check_finite(value, path, f"{key}.")
        elif isinstance(value, torch.Tensor) and (value.is_floating_point() or value.is_complex()):
            # numpy: one thread, ~1 ms for a 7 MB policy; torch's OpenMP pool spun ~1 s on a busy 2-core machine
            t = value.detach().cpu()
            try:
                finite = np.isfinite(t.numpy())
            except TypeError:  # bfloat16, float8: no numpy dtype
                finite = torch.isfinite(t).numpy()
            if not finite.all():
                bad = finite.size - int(finite.sum())
                raise CorruptArtifactError(f"corrupt weights file {path}: tensor '{key}' has {bad} non-finite (NaN or "
                                           f"infinite) value(s) of {finite.size}, expected finite weights")


def read_weights(path: Path, hint: str = "") -> dict[str, Any]:
    """Reads a weights file, checked: the one way weights are read (policies, baselines, the BEV encoder and its
    heads, user-given pretrained weights).

    1. the file exists;
    2. it matches the sha256 and size its stage's manifest records for it, when a manifest lists it
       (:func:`pipeline.core.manifest.verify_output`: hashed once per process; unlisted files are not verified);
    3. it parses: ``.safetensors`` with safetensors, any other suffix with ``torch.load(weights_only=True)``;
    4. every floating-point tensor is finite (:func:`check_finite`).

    Args:
        path: The weights file.
        hint: Advice appended to the message when the file does not parse.

    Returns:
        The stored mapping (name -> tensor; a torch file may nest it, e.g. under ``model``).

    Raises:
        InputMissingError: the file is missing. CorruptArtifactError: a failed check, naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputMissingError(f"missing weights file {path}")
    verify_output(path)
    try:
        if path.suffix == ".safetensors":
            state: Any = load_file(str(path))
        else:
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # safetensors and torch raise many types (SafetensorError, UnpicklingError, EOFError, ...)
        raise CorruptArtifactError(f"corrupt weights file {path}: cannot read it ({type(e).__name__}: "
                                   f"{str(e)[:200]}){'; ' + hint if hint else ''}") from None
    if not isinstance(state, Mapping):
        raise CorruptArtifactError(f"weights file {path}: expected a mapping of names to tensors, got "
                                   f"{type(state).__name__}")
    check_finite(state, path)
    return dict(state)


def load_safetensors(module: torch.nn.Module, path: Path,
                     upgrade: Callable[[dict[str, torch.Tensor]], dict[str, torch.Tensor]] | None = None) -> None:
    """Loads a state dict into ``module`` (strict) from a file read by :func:`read_weights` (verified against its
    manifest, finite); any problem names the file. ``upgrade``: maps the stored state dict to the module's current
    key names first (checkpoints of an older layout)."""
    path = Path(path)
    state = read_weights(path)
    if upgrade is not None:
        state = upgrade(state)
    try:
        module.load_state_dict(state, strict=True)
    except RuntimeError as e:
        first = str(e).strip().splitlines()
        raise CorruptArtifactError(f"weights file {path} does not match the architecture its JSON describes: "
                                   f"{' '.join(first[:3])[:400]}") from None


def write_encoder_checkpoint(out: Path, encoder: BEVEncoder, heads: PretextHeads, extra: dict[str, Any]) -> None:
    """Writes ``encoder.safetensors``, ``heads.safetensors`` and ``encoder.json`` into ``out``."""
    meta = {"format_version": str(FORMAT_VERSION)}
    save_safetensors(encoder, out / ENCODER_WEIGHTS, meta)
    save_safetensors(heads, out / HEADS_WEIGHTS, meta)
    desc = {"format_version": FORMAT_VERSION, **encoder.describe(), **extra}
    atomic_write_text(out / ENCODER_JSON, json.dumps(desc, indent=2, sort_keys=True) + "\n")


def read_encoder_json(ckpt: Path) -> dict[str, Any]:
    """The ``encoder.json`` of a finished checkpoint directory (errors name the path)."""
    ckpt = Path(ckpt)
    if not ckpt.is_dir():
        raise InputMissingError(f"no BEV encoder checkpoint at {ckpt}; make one with `make pretrain`")
    if not (ckpt / MANIFEST_NAME).is_file():
        raise InputMissingError(f"BEV encoder checkpoint {ckpt} is unfinished (no {MANIFEST_NAME}); finish it with "
                                "`icrowdnav pretrain --resume` or redo it with --overwrite")
    path = ckpt / ENCODER_JSON
    if not path.is_file():
        raise InputMissingError(f"BEV encoder checkpoint {ckpt} has no {ENCODER_JSON}")
    try:
        desc = json.loads(path.read_text())
        enc = desc["encoder"]
        cams = desc["cameras"]
    except (json.JSONDecodeError, KeyError, TypeError, UnicodeDecodeError) as e:
        raise CorruptArtifactError(f"corrupt {path}: {type(e).__name__}: {e}") from None
    if desc.get("format_version") != FORMAT_VERSION:
        raise CorruptArtifactError(f"{path}: format_version {desc.get('format_version')!r}, expected {FORMAT_VERSION}")
    if not isinstance(enc, dict) or not isinstance(cams, list) or not cams:
        raise CorruptArtifactError(f"{path}: 'encoder' must be a mapping and 'cameras' a non-empty list")
    return desc


def encoder_from_json(desc: dict[str, Any], where: str = "encoder.json") -> BEVEncoder:
    """An (untrained) encoder built from an ``encoder.json`` description."""
    fields = EncoderConfig.__dataclass_fields__
    unknown = sorted(set(desc["encoder"]) - set(fields))
    if unknown:
        raise CorruptArtifactError(f"{where}: unknown encoder keys {unknown}")
    cfg = EncoderConfig(**{**LEGACY_ENCODER, **desc["encoder"]})  # keys newer than the file: what it was trained as
    cameras = [Camera.from_dict(c, f"{where} cameras[{k}]") for k, c in enumerate(desc["cameras"])]
    return BEVEncoder(cfg, cameras)


def load_encoder(ckpt: Path, frozen: bool = True) -> BEVEncoder:
    """Loads the pretrained encoder of a checkpoint directory, ready for ``train`` (its int8 version:
    :func:`pretrain.quantize.load_frozen_encoder`).

    Args:
        ckpt: ``DATA_DIR/checkpoints/bev`` (or another pretrain output).
        frozen: eval mode and ``requires_grad=False`` on every parameter (the paper freezes it during RL).

    Raises:
        InputMissingError: no or unfinished checkpoint. CorruptArtifactError: unreadable or mismatching files.
    """
    ckpt = Path(ckpt)
    desc = read_encoder_json(ckpt)
    encoder = encoder_from_json(desc, str(ckpt / ENCODER_JSON))
    load_safetensors(encoder, ckpt / ENCODER_WEIGHTS)
    if frozen:
        encoder.eval()
        encoder.requires_grad_(False)
    return encoder


def load_heads(ckpt: Path, encoder: BEVEncoder) -> PretextHeads:
    """The pretext heads of a checkpoint (for figures and evaluation of the pretext task)."""
    heads = PretextHeads(encoder.cfg.bev_channels)
    load_safetensors(heads, Path(ckpt) / HEADS_WEIGHTS)
    return heads.eval()
