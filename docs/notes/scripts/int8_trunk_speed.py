"""The float rewrites and int8 of the ResNet trunk (2 x 160 x 120, one thread, random weights): speed and output change.
Run from the repository root: .venv/bin/python docs/notes/scripts/int8_trunk_speed.py (docs/notes/2026-12-int8-encoder.md)"""
import copy
import time

import torch
import torch.nn as nn

from pretrain.model import _resnet18_trunk

torch.set_num_threads(1)
torch.manual_seed(0)
m = _resnet18_trunk(2).eval()
# randomise BN stats so folding is not trivial
for mod in m.modules():
    if isinstance(mod, nn.BatchNorm2d):
        mod.running_mean.uniform_(-0.5, 0.5); mod.running_var.uniform_(0.5, 2.0); mod.weight.data.uniform_(0.5, 1.5); mod.bias.data.uniform_(-0.2, 0.2)
x = torch.randn(2, 3, 120, 160)
def bench(f, x, n=60):
    with torch.no_grad():
        for _ in range(5): f(x)
        t = time.perf_counter()
        for _ in range(n): y = f(x)
    return 1000 * (time.perf_counter() - t) / n, y
t0, y0 = bench(m, x)
print(f"eager fp32: {t0:.2f} ms")
with torch.no_grad():
    fr = torch.jit.optimize_for_inference(torch.jit.freeze(torch.jit.script(copy.deepcopy(m))))
t1, y1 = bench(fr, x)
print(f"jit freeze+optimize_for_inference: {t1:.2f} ms  x{t0/t1:.2f}  max|d|={ (y1-y0).abs().max():.2e} rel={(y1-y0).abs().max()/y0.abs().max():.2e}")
mc = copy.deepcopy(m).to(memory_format=torch.channels_last)
xc = x.contiguous(memory_format=torch.channels_last)
t2, y2 = bench(mc, xc)
print(f"channels_last eager: {t2:.2f} ms x{t0/t2:.2f} max|d|={(y2-y0).abs().max():.2e}")
from torch.fx.experimental.optimization import fuse

mf = fuse(copy.deepcopy(m))
t3, y3 = bench(mf, x)
print(f"fx fuse conv-bn: {t3:.2f} ms x{t0/t3:.2f} max|d|={(y3-y0).abs().max():.2e}")
mfc = mf.to(memory_format=torch.channels_last)
t4, y4 = bench(mfc, xc)
print(f"fx fuse + channels_last: {t4:.2f} ms x{t0/t4:.2f} max|d|={(y4-y0).abs().max():.2e}")
try:
    from torch.ao.quantization import get_default_qconfig_mapping
    from torch.ao.quantization.quantize_fx import convert_fx, prepare_fx
    qm = prepare_fx(copy.deepcopy(m), get_default_qconfig_mapping("x86"), (x,))
    with torch.no_grad():
        for _ in range(8): qm(torch.randn(2, 3, 120, 160))
    qm = convert_fx(qm)
    t5, y5 = bench(qm, x)
    print(f"int8 fx x86: {t5:.2f} ms x{t0/t5:.2f} rel={(y5-y0).abs().max()/y0.abs().max():.2e} mean|d|/mean|y|={(y5-y0).abs().mean()/y0.abs().mean():.2e}")
except Exception as e:
    print("int8 failed", e)
