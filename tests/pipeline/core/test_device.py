"""pipeline.core.device: the ``device`` config key (auto | cpu | cuda | cuda:N), its errors, device-free saving, and the
training ``precision`` keys (auto | fp32 | bf16)."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import torch

from pipeline.core import device as device_mod
from pipeline.core.config import BaseStageConfig, config_hash
from pipeline.core.device import (
    autocast,
    cpu_state,
    cuda_build,
    device_counts,
    native_bf16,
    resolve_device,
    resolve_precision,
    start_method,
)
from pipeline.core.errors import ConfigError


@pytest.fixture
def no_cuda(monkeypatch) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


@pytest.fixture
def two_gpus(monkeypatch) -> None:
    """A pretend machine with CUDA devices 0 and 1 (nothing touches a real GPU)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)


def test_cpu_is_always_there(no_cuda) -> None:
    assert resolve_device("cpu", "pretrain.device") == torch.device("cpu")
    assert resolve_device(" CPU ", "pretrain.device") == torch.device("cpu")


def test_auto_is_cuda_when_present_else_cpu(no_cuda, monkeypatch) -> None:
    assert resolve_device("auto", "pretrain.device") == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    assert resolve_device("auto", "pretrain.device") == torch.device("cuda", 0)


def test_cuda_without_cuda_is_one_named_error(no_cuda) -> None:
    with pytest.raises(ConfigError) as e:
        resolve_device("cuda", "pretrain.device")
    msg = str(e.value)
    assert msg.startswith("pretrain.device: expected a device this machine has (auto or cpu here), got 'cuda'")
    assert "CUDA is not available on this machine" in msg and f"torch {torch.__version__}" in msg
    assert "\n" not in msg
    with pytest.raises(ConfigError, match=r"train\.device: .*CUDA is not available"):
        resolve_device("cuda:0", "train.device")


def test_cuda_build_names_the_torch_build(monkeypatch) -> None:
    monkeypatch.setattr(torch.version, "cuda", None)
    assert cuda_build() == f"torch {torch.__version__}, built with no CUDA"
    monkeypatch.setattr(torch.version, "cuda", "12.8")
    assert cuda_build().endswith("built with CUDA 12.8")


def test_cuda_index(two_gpus) -> None:
    assert resolve_device("cuda", "k") == torch.device("cuda", 0)
    assert resolve_device("cuda:1", "k") == torch.device("cuda", 1)
    with pytest.raises(ConfigError, match=r"k: expected cuda:0 to cuda:1 \(2 CUDA device\(s\) .*got 'cuda:2'"):
        resolve_device("cuda:2", "k")


@pytest.mark.parametrize("bad", ["gpu", "tpu", "cuda:", "cuda:x", "cuda0", "", "mps"])
def test_unknown_values_are_refused(bad, no_cuda) -> None:
    with pytest.raises(ConfigError, match=r"pretrain.device: expected one of auto, cpu, cuda, cuda:N, got"):
        resolve_device(bad, "pretrain.device")


def test_device_counts() -> None:
    assert device_counts(torch.device("cpu")) == {"device": "cpu"}


def test_cpu_state_keeps_cpu_tensors_and_structure() -> None:
    w = torch.ones(2)
    state = {"encoder": {"w": w}, "optimizer": {"state": {0: {"step": torch.tensor(3.0)}}, "param_groups": [{"lr": 1}]},
             "history": [1, 2], "pair": (w, "x"), "step": 7}
    out = cpu_state(state)
    assert out["encoder"]["w"] is w  # already on the CPU: not copied, the same bytes saved
    assert out["optimizer"]["param_groups"] == [{"lr": 1}] and out["history"] == [1, 2] and out["step"] == 7
    assert out["pair"][0] is w and out["pair"][1] == "x"


def test_start_method() -> None:
    assert start_method("cpu") == "fork"
    assert start_method(torch.device("cuda", 0)) == "spawn"


def test_device_is_not_in_the_config_hash() -> None:
    @dataclass
    class Cfg(BaseStageConfig):
        device: str = "auto"
        epochs: int = 1

    assert config_hash(Cfg(device="cuda")) == config_hash(Cfg(device="cpu")) == config_hash(Cfg())
    assert config_hash(Cfg(epochs=2)) != config_hash(Cfg())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cpu_state_moves_cuda_tensors_to_the_host() -> None:
    state = {"w": torch.ones(3, device="cuda"), "nested": [torch.zeros(1, device="cuda")]}
    out = cpu_state(state)
    assert out["w"].device.type == "cpu" and out["nested"][0].device.type == "cpu"
    assert state["w"].device.type == "cuda"  # the live state is untouched
    assert resolve_device("cuda", "k").type == "cuda" and device_counts(resolve_device("auto", "k"))["device"] == "cuda:0"


def test_precision_auto_is_bf16_exactly_where_the_device_has_native_bf16(monkeypatch) -> None:
    assert resolve_precision("auto", "cpu", "pretrain.precision") == ("bf16" if native_bf16("cpu") else "fp32")
    assert resolve_precision(" FP32 ", "cpu", "pretrain.precision") == "fp32"
    monkeypatch.setattr(device_mod, "native_bf16", lambda device: True)
    assert resolve_precision("auto", "cpu", "k") == "bf16" and resolve_precision("bf16", "cpu", "k") == "bf16"
    monkeypatch.setattr(device_mod, "native_bf16", lambda device: False)
    assert resolve_precision("auto", "cpu", "k") == "fp32"
    with pytest.raises(ConfigError, match=r"train\.dagger\.bc_precision: expected fp32 or auto on cpu, got 'bf16'"):
        resolve_precision("bf16", "cpu", "train.dagger.bc_precision")


@pytest.mark.parametrize("bad", ["fp16", "int8", "", "bfloat16"])
def test_unknown_precisions_are_refused(bad) -> None:
    with pytest.raises(ConfigError, match=rf"pretrain\.precision: expected one of auto, fp32, bf16, got '{bad}'"):
        resolve_precision(bad, "cpu", "pretrain.precision")


def test_autocast_computes_convolutions_in_bf16_and_nothing_at_fp32() -> None:
    conv = torch.nn.Conv2d(2, 3, 3)
    x = torch.randn(1, 2, 6, 6)
    with autocast("cpu", "fp32"):
        assert conv(x).dtype == torch.float32
    with autocast("cpu", "bf16"):
        y = conv(x)
    assert y.dtype == torch.bfloat16 and conv.weight.dtype == torch.float32  # the weights stay float32
    torch.testing.assert_close(y.float(), conv(x), rtol=0.05, atol=0.05)
    with pytest.raises(ValueError, match="resolved precision"):
        autocast("cpu", "auto")
