"""The dense fusion (temporal model + decoder + refinement, default sizes, one thread): eager vs per-pair 2-D convolutions vs int8.
Run from the repository root: .venv/bin/python docs/notes/scripts/int8_fusion_speed.py (docs/notes/2026-12-int8-encoder.md)"""
import copy
import time
import warnings

import torch
import torch.nn as nn
import torch.nn.functional as F

warnings.filterwarnings("ignore")
from torch.ao.quantization import get_default_qconfig_mapping
from torch.ao.quantization.quantize_fx import convert_fx, prepare_fx

from pretrain.model import BEVDecoder, TemporalModel, _conv_bn

torch.set_num_threads(1); torch.manual_seed(0)
C, T = 32, 5
class Temporal2d(nn.Module):
    """TemporalModel with each TimeConv as a Conv2d over channel-stacked pairs (same maths)."""
    def __init__(self, tm: TemporalModel):
        super().__init__()
        self.blocks = nn.ModuleList()
        for blk in tm.blocks:
            tc, bn3 = blk[0], blk[1]
            w = tc.weight.detach()
            conv = nn.Conv2d(w.shape[1] * 2, w.shape[0], 3, padding=1, bias=False)
            conv.weight.data = torch.cat([w[:, :, 0], w[:, :, 1]], 1)
            bn = nn.BatchNorm2d(bn3.num_features); bn.load_state_dict(bn3.state_dict())
            self.blocks.append(nn.Sequential(conv, bn, nn.ReLU()))
        self.skip = tm.skip; self.norm = tm.norm
    def forward(self, x):  # B T C X Y
        frames = [x[:, i] for i in range(len(self.blocks) + 1)]
        newest = frames[-1]
        for blk in self.blocks:
            frames = [blk(torch.cat([frames[i], frames[i + 1]], 1)) for i in range(len(frames) - 1)]
        out = self.skip(newest) + frames[-1]
        return F.relu(self.norm(out))
def rand_bn(m):
    for mod in m.modules():
        if isinstance(mod, (nn.BatchNorm2d, nn.BatchNorm3d)):
            mod.running_mean.uniform_(-0.2, 0.2); mod.running_var.uniform_(0.5, 2.0)
    return m
tm = rand_bn(TemporalModel(C, T)).eval(); dec = rand_bn(BEVDecoder(C)).eval(); ref = rand_bn(_conv_bn(2 * C, C)).eval()
t2 = Temporal2d(tm).eval()
class Fuse(nn.Module):
    def __init__(s, t, d, r): super().__init__(); s.t, s.d, s.r = t, d, r
    def forward(s, aligned, newest):
        y = s.d(s.t(aligned))
        up = F.interpolate(y, size=newest.shape[-2:], mode="bilinear", align_corners=False)
        return s.r(torch.cat([up, newest], 1))
x = torch.relu(torch.randn(1, T, C, 30, 48)); nw = torch.relu(torch.randn(1, C, 60, 96))
f_ref = Fuse(tm, dec, ref).eval(); f2 = Fuse(t2, dec, ref).eval()
def bench(f, *a, n=50):
    with torch.no_grad():
        for _ in range(5): f(*a)
        t = time.perf_counter()
        for _ in range(n): y = f(*a)
    return 1000 * (time.perf_counter() - t) / n, y
a, ya = bench(f_ref, x, nw); b, yb = bench(f2, x, nw)
print(f"fuse eager {a:.2f} ms; pairs-as-conv2d {b:.2f} ms, max|d| {(ya-yb).abs().max():.2e}")
qm = prepare_fx(copy.deepcopy(f2), get_default_qconfig_mapping("x86"), (x, nw))
with torch.no_grad():
    for _ in range(8): qm(torch.relu(torch.randn(1, T, C, 30, 48)), torch.relu(torch.randn(1, C, 60, 96)))
qm = convert_fx(qm)
c, yc = bench(qm, x, nw)
print(f"fuse int8 {c:.2f} ms x{a/c:.2f}; mean|d|/mean|y| {(yc-ya).abs().mean()/ya.abs().mean():.3f}")
