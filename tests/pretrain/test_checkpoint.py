"""pretrain.checkpoint's weights reader: every load is checked against the manifest's sha256 and for finite values."""

from __future__ import annotations

import dataclasses
import json
import struct
from pathlib import Path

import pytest
import torch

from pipeline.core.errors import CorruptArtifactError, InputMissingError
from pipeline.core.manifest import MANIFEST_NAME, Manifest, hash_file, hash_tree
from pretrain.checkpoint import load_safetensors, read_weights, save_safetensors


def _model(seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(8, 16), torch.nn.BatchNorm1d(16), torch.nn.Linear(16, 4))


def _finish(out: Path) -> None:
    """What run_stage writes last: config.yaml and a manifest.json listing every file."""
    (out / "config.yaml").write_text("seed: 0\n")
    Manifest(stage="toy", params={}, config_hash="0" * 64, seed=0, outputs=hash_tree(out)).write(out / MANIFEST_NAME)


def _payload_start(path: Path) -> int:
    """Offset of the first tensor byte: safetensors = 8-byte header length, JSON header, then the tensor data."""
    (n,) = struct.unpack("<Q", path.read_bytes()[:8])
    return 8 + n


def _tensor_offset(path: Path, name: str) -> int:
    data = path.read_bytes()
    (n,) = struct.unpack("<Q", data[:8])
    return 8 + n + json.loads(data[8:8 + n])[name]["data_offsets"][0]


@pytest.fixture
def ckpt(tmp_path: Path) -> Path:
    """A finished checkpoint directory: weights, config.yaml, manifest.json."""
    out = tmp_path / "ckpt"
    out.mkdir()
    save_safetensors(_model(), out / "w.safetensors", {"kind": "toy"})
    _finish(out)
    return out


def test_intact_checkpoint_loads(ckpt: Path) -> None:
    m = _model(seed=1)
    load_safetensors(m, ckpt / "w.safetensors")
    assert all(torch.equal(a, b) for a, b in zip(m.state_dict().values(), _model().state_dict().values(), strict=True))


def test_damaged_tensor_bytes_under_an_intact_header_are_named(ckpt: Path) -> None:
    """The issue: bytes of a tensor are damaged, the header is intact, so safetensors loads it without complaint;
    the manifest's sha256 refuses it, naming the file, the expected and the found hash."""
    w = ckpt / "w.safetensors"
    expected = hash_file(w)
    data = bytearray(w.read_bytes())
    at = _payload_start(w) + 40
    data[at:at + 4] = struct.pack("<f", 123.0)  # a finite but wrong weight: only the hash can tell
    w.write_bytes(bytes(data))
    from safetensors.torch import load_file

    assert set(load_file(str(w))) == set(_model().state_dict())  # the header still parses
    with pytest.raises(CorruptArtifactError) as e:
        load_safetensors(_model(), w)
    msg = str(e.value)
    assert str(w) in msg and f"expected sha256 {expected[:16]}" in msg and f"found {hash_file(w)[:16]}" in msg
    assert "\n" not in msg


def test_sha_mismatch_of_the_manifest_record_is_named(ckpt: Path) -> None:
    """The file is intact but the manifest records another hash (same size): refused, both hashes named."""
    mpath = ckpt / MANIFEST_NAME
    m = Manifest.read(mpath)
    m.outputs = [dataclasses.replace(r, sha256="ab" * 32) if r.path == "w.safetensors" else r for r in m.outputs]
    m.write(mpath)
    with pytest.raises(CorruptArtifactError, match=r"w\.safetensors: expected sha256 abababababababab.*found "):
        read_weights(ckpt / "w.safetensors")


def test_truncated_checkpoint_is_named_by_size(ckpt: Path) -> None:
    w = ckpt / "w.safetensors"
    w.write_bytes(w.read_bytes()[:-16])
    with pytest.raises(CorruptArtifactError, match=r"w\.safetensors: expected \d+ bytes .* found \d+ bytes"):
        read_weights(w)


def test_non_finite_weights_are_named_with_the_tensor(tmp_path: Path) -> None:
    """NaN weights (a diverged run saved them, so the manifest matches): refused naming the file and the tensor."""
    out = tmp_path / "ckpt"
    out.mkdir()
    m = _model()
    with torch.no_grad():
        m[2].weight[1, 3] = float("nan")
        m[0].bias[0] = float("inf")
    save_safetensors(m, out / "w.safetensors")
    _finish(out)
    with pytest.raises(CorruptArtifactError, match=r"w\.safetensors: tensor '0\.bias' has 1 non-finite"):
        load_safetensors(_model(), out / "w.safetensors")


def test_nan_bytes_in_a_file_no_manifest_lists_are_named(tmp_path: Path) -> None:
    """Without a manifest (user weights, an unfinished output) there is no hash to compare; NaN still is refused."""
    w = tmp_path / "w.safetensors"
    save_safetensors(_model(), w)
    data = bytearray(w.read_bytes())
    at = _tensor_offset(w, "2.weight")
    data[at:at + 4] = b"\x00\x00\xc0\x7f"  # a float32 NaN
    w.write_bytes(bytes(data))
    with pytest.raises(CorruptArtifactError, match=r"tensor '2\.weight' has 1 non-finite"):
        read_weights(w)


def test_torch_files_are_checked_too(tmp_path: Path) -> None:
    p = tmp_path / "backbone.pth"
    torch.save({"model": {"w": torch.tensor([1.0, float("nan")])}}, p)
    with pytest.raises(CorruptArtifactError, match=r"backbone\.pth: tensor 'model\.w'"):
        read_weights(p)
    p.write_bytes(b"not a checkpoint")
    with pytest.raises(CorruptArtifactError, match=r"backbone\.pth: cannot read it .*; try this"):
        read_weights(p, hint="try this")
    with pytest.raises(InputMissingError, match="nope.safetensors"):
        read_weights(tmp_path / "nope.safetensors")


def test_rewriting_a_listed_checkpoint_in_place_drops_the_stale_manifest(ckpt: Path) -> None:
    """A --resume run rewrites weights in a finished directory: the old manifest goes (the directory is unfinished
    until its stage writes a new one), so the new weights are not checked against the old record."""
    save_safetensors(_model(seed=5), ckpt / "w.safetensors")
    assert not (ckpt / MANIFEST_NAME).exists()
    load_safetensors(_model(), ckpt / "w.safetensors")


def test_a_pooled_fusion_encoder_round_trips_through_its_checkpoint(tmp_path: Path) -> None:
    """An encoder with ``fuse_pool: 2`` (its refinement layer included) is rebuilt from ``encoder.json`` and its
    weights, and gives the same s_bev."""
    from pretrain.checkpoint import load_encoder, write_encoder_checkpoint
    from pretrain.model import BEVEncoder, BEVStream, EncoderConfig, PretextHeads
    from tests.pretrain.test_model import cameras, sequence

    torch.manual_seed(0)
    cfg = EncoderConfig(bev_channels=8, x_bound=[0.0, 4.0, 0.2], y_bound=[-3.2, 3.2, 0.2], history_frames=3,
                        fuse_pool=2)
    enc = BEVEncoder(cfg, cameras()).eval()
    out = tmp_path / "bev"
    out.mkdir()
    write_encoder_checkpoint(out, enc, PretextHeads(8), {})
    _finish(out)
    loaded = load_encoder(out)
    assert loaded.cfg.fuse_pool == 2 and hasattr(loaded, "refine")
    rgb, depth, poses = sequence(1, seed=3)
    a, b = BEVStream(enc), BEVStream(loaded)
    for k in range(3):
        torch.testing.assert_close(a.step(rgb[:, k], depth[:, k], poses[:, k]),
                                   b.step(rgb[:, k], depth[:, k], poses[:, k]))
