"""The students' frozen encoder's streaming step: float32, the bf16 encoder as it was until 99f0a13 (its dense parts
under bfloat16 autocast, restated here) and as it is (BatchNorms folded, bfloat16 channels-last weights:
pretrain.quantize.BF16BEVEncoder); B = 1 (an evaluation episode) and B = 2 (a DAgger rollout's episode and its mirror),
one thread, 12 random frames, five alternating rounds (median), and each one's error against float32.
Run from the repository root: .venv/bin/python docs/notes/scripts/bf16_prepared_stream.py [ENCODER_DIR]
(docs/notes/2026-12-bf16-training.md)"""
import sys
import time
from pathlib import Path

import torch

from pretrain.checkpoint import load_encoder
from pretrain.model import BEVStream
from pretrain.quantize import BF16BEVEncoder, _FrozenCopy

torch.set_num_threads(1)


class AutocastBF16(_FrozenCopy):
    """The bf16 encoder until 99f0a13: the float modules under bfloat16 autocast."""

    def image_features(self, rgb):
        with torch.autocast(rgb.device.type, dtype=torch.bfloat16):
            return super().image_features(rgb)

    def fuse_aligned(self, aligned, newest):
        with torch.autocast(aligned.device.type, dtype=torch.bfloat16):
            return super().fuse_aligned(aligned, newest)


enc = load_encoder(Path(sys.argv[1] if len(sys.argv) > 1 else "data/checkpoints/bev"), frozen=True)
encoders = {"fp32": enc, "autocast": AutocastBF16(enc), "prepared": BF16BEVEncoder(enc)}
g = torch.Generator().manual_seed(0)
for b in (1, 2):
    frames = [(torch.randint(0, 255, (b, 2, 3, 120, 160), dtype=torch.uint8, generator=g),
               torch.rand(b, 2, 120, 160, generator=g) * 5 + 0.3,
               torch.tensor([[0.05 * i, 0.01 * i, 0.02 * i]] * b)) for i in range(12)]
    outs = {}
    for name, e in encoders.items():
        stream = BEVStream(e)
        outs[name] = torch.stack([stream.step(*f) for f in frames])
    ref = outs["fp32"]
    err = {k: round(float((v - ref).norm() / ref.norm()), 5) for k, v in outs.items() if k != "fp32"}
    ms = {k: [] for k in encoders}
    for _ in range(5):
        for name, e in encoders.items():
            stream = BEVStream(e)
            t = time.perf_counter()
            for f in frames:
                stream.step(*f)
            ms[name].append(1000 * (time.perf_counter() - t) / len(frames))
    med = {k: round(sorted(v)[2], 1) for k, v in ms.items()}
    print(f"B = {b}: ms per step {med}; autocast / prepared {med['autocast'] / med['prepared']:.2f}x; "
          f"relative error against fp32 {err}", flush=True)
