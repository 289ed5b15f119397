"""Where tensors live: the ``device`` config key (``auto`` | ``cpu`` | ``cuda`` | ``cuda:N``) of the stages that train.

``auto`` is CUDA when this machine has it, else the CPU; ``cuda`` without CUDA is a :class:`ConfigError` naming the
key (``pretrain.device``), raised from the config's ``validate()`` so that it comes before any output is written.
The key is left out of the config hash (:data:`pipeline.core.config.HASH_EXCLUDED_FIELDS`): it says where a result
is computed, not what it is, so a run started on a GPU resumes on a CPU-only machine and an output stays up to date
when only the device changes. Which device produced a result is recorded in the stage's counts
(:func:`device_counts`, in ``manifest.json``).

What is saved stays device-independent: :func:`cpu_state` copies tensors to the host before ``torch.save``, and
every loader maps to the CPU (``map_location="cpu"``, safetensors); the caller moves the module afterwards.

Worker processes that run a model on CUDA (DAgger rollouts with the students' frozen encoder, the fine-tuning
envs) must not be forked from a process that has touched CUDA (PyTorch: "Cannot re-initialize CUDA in forked
subprocess"): :func:`start_method` gives ``spawn`` for a CUDA device, ``fork`` otherwise.

Training precision (the ``precision`` keys of the stages that train: :data:`TRAIN_PRECISIONS`): ``fp32``, or
``bf16`` mixed precision — the forward pass under ``torch.autocast`` (:func:`autocast`: convolutions and matrix
products in bfloat16, reductions, losses and the weights themselves in float32) — or ``auto``, which is ``bf16``
where the device computes bfloat16 natively (a CPU with AVX512-BF16 or AMX, a CUDA GPU that supports it) and
``fp32`` elsewhere (:func:`resolve_precision`). Without native support bfloat16 is emulated and slower than float32,
so asking for ``bf16`` there is a :class:`ConfigError`. Like the device, the precision says how a result was
computed: the resolved one is recorded in the stage's counts (``precision``).
"""

from __future__ import annotations

import contextlib
import re
from typing import Any

import torch

from pipeline.core.errors import ConfigError

DEVICE_CHOICES = ("auto", "cpu", "cuda", "cuda:N")
TRAIN_PRECISIONS = ("auto", "fp32", "bf16")
_CUDA_N = re.compile(r"cuda:(\d+)")


def cuda_build() -> str:
    """``torch X, built with CUDA Y`` (or ``with no CUDA``): what a message about missing CUDA should say."""
    built = torch.version.cuda
    return f"torch {torch.__version__}, built with {'CUDA ' + built if built else 'no CUDA'}"


def resolve_device(name: str, key: str) -> torch.device:
    """The device a ``device`` config value names.

    Args:
        name: ``auto`` (CUDA when available, else the CPU), ``cpu``, ``cuda`` (the current CUDA device) or
            ``cuda:N``.
        key: The config key, for the message (``pretrain.device``).

    Returns:
        ``cpu`` or ``cuda:N`` (always with an index, so that the recorded name says which GPU).

    Raises:
        ConfigError: an unknown value, CUDA asked for on a machine without it, or a CUDA index that does not exist.
    """
    text = str(name).strip().lower()
    if text == "cpu":
        return torch.device("cpu")
    if text == "auto":
        return torch.device("cuda", torch.cuda.current_device()) if torch.cuda.is_available() else torch.device("cpu")
    m = _CUDA_N.fullmatch(text)
    if text != "cuda" and m is None:
        raise ConfigError(f"{key}: expected one of {', '.join(DEVICE_CHOICES)}, got {name!r}")
    if not torch.cuda.is_available():
        raise ConfigError(f"{key}: expected a device this machine has (auto or cpu here), got {name!r}: CUDA is not "
                          f"available on this machine ({cuda_build()})")
    if m is None:
        return torch.device("cuda", torch.cuda.current_device())
    index, count = int(m.group(1)), torch.cuda.device_count()
    if index >= count:
        raise ConfigError(f"{key}: expected cuda:0 to cuda:{count - 1} ({count} CUDA device(s) on this machine), "
                          f"got {name!r}")
    return torch.device("cuda", index)


def device_counts(device: torch.device) -> dict[str, str]:
    """The stage counts (``manifest.json``) that say which hardware produced a result: ``{"device": "cuda:0",
    "device_name": "NVIDIA H100 80GB HBM3"}``, or ``{"device": "cpu"}``."""
    device = torch.device(device)
    if device.type == "cuda":
        return {"device": str(device), "device_name": torch.cuda.get_device_name(device)}
    return {"device": str(device)}


def cpu_state(obj: Any) -> Any:
    """A copy of a (nested) state with every tensor on the CPU, for ``torch.save``: a file written on a GPU loads on a
    machine without one. Tensors already on the CPU are returned as they are (no copy, the same bytes saved)."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu() if obj.device.type != "cpu" else obj
    if isinstance(obj, dict):
        return type(obj)((k, cpu_state(v)) for k, v in obj.items())
    if isinstance(obj, list | tuple):
        return type(obj)(cpu_state(v) for v in obj)
    return obj


def start_method(device: torch.device | str) -> str:
    """The multiprocessing start method of worker processes that run a model on ``device``: ``spawn`` for CUDA (a
    forked child of a process that touched CUDA cannot use it), ``fork`` otherwise (fast, shares loaded modules)."""
    return "spawn" if torch.device(device).type == "cuda" else "fork"


def machine_facts() -> dict[str, Any]:
    """What a benchmark figure was measured on: torch's CPU threads, the processor, the GPU (when present), torch."""
    import platform

    return {"cpu_threads": torch.get_num_threads(), "machine": platform.processor() or platform.machine(),
            **({"gpu": torch.cuda.get_device_name()} if torch.cuda.is_available() else {}),
            "torch": torch.__version__}


def native_bf16(device: torch.device | str) -> bool:
    """Whether ``device`` computes bfloat16 natively: a CPU with AVX512-BF16 or AMX tiles, a CUDA GPU whose
    compute capability supports it (Ampere on)."""
    device = torch.device(device)
    if device.type == "cuda":
        return bool(torch.cuda.is_bf16_supported())
    cpu = torch._C._cpu
    return bool(cpu._is_avx512_bf16_supported() or cpu._is_amx_tile_supported())


def resolve_precision(name: str, device: torch.device | str, key: str) -> str:
    """The training precision (``fp32`` | ``bf16``) a ``precision`` config value names on ``device``.

    Raises:
        ConfigError: an unknown value, or ``bf16`` on a device without native bfloat16 (emulated: slower than
            float32).
    """
    text = str(name).strip().lower()
    if text not in TRAIN_PRECISIONS:
        raise ConfigError(f"{key}: expected one of {', '.join(TRAIN_PRECISIONS)}, got {name!r}")
    native = native_bf16(device)
    if text == "auto":
        return "bf16" if native else "fp32"
    if text == "bf16" and not native:
        raise ConfigError(f"{key}: expected fp32 or auto on {torch.device(device)}, got 'bf16': this device has no "
                          "native bfloat16 (a CPU without AVX512-BF16 or AMX, or an older GPU), where it is emulated "
                          "and slower than float32")
    return text


def autocast(device: torch.device | str, precision: str) -> contextlib.AbstractContextManager:
    """The context of a training forward pass at ``precision`` (a resolved one: ``fp32`` | ``bf16``): bfloat16
    autocast on ``device``'s type for ``bf16``, nothing for ``fp32``. Compute the loss outside it, in float32."""
    if precision == "bf16":
        return torch.autocast(torch.device(device).type, dtype=torch.bfloat16)
    if precision != "fp32":
        raise ValueError(f"autocast: expected a resolved precision fp32 | bf16, got {precision!r}")
    return contextlib.nullcontext()
