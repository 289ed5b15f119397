"""One cloning step (forward + backward + Adam) of the students' map CNN (rl.networks.BEVNet, 32 channels of 30 x 48,
batch 128) in fp32 / bf16 autocast, contiguous / channels-last.
Run from the repository root: .venv/bin/python docs/notes/scripts/bf16_bevnet_step.py THREADS
(docs/notes/2026-12-bf16-training.md)"""
import sys
import time

import torch

from rl.networks import BEVNet

torch.set_num_threads(int(sys.argv[1]) if len(sys.argv) > 1 else 1)
torch.manual_seed(0)
net = BEVNet(32, 32, 256)
opt = torch.optim.Adam(net.parameters(), 1e-3)
x = torch.randn(128, 32, 30, 48)
def step(bf16, cl):
    xx = x.contiguous(memory_format=torch.channels_last) if cl else x
    with torch.autocast('cpu', dtype=torch.bfloat16, enabled=bf16):
        y = net(xx)
    loss = y.float().square().mean()
    opt.zero_grad(); loss.backward(); opt.step()
for bf16, cl in [(False, False), (True, False), (False, True), (True, True)]:
    if cl: net = net.to(memory_format=torch.channels_last)
    step(bf16, cl)
    t = time.perf_counter(); n = 5
    for _ in range(n): step(bf16, cl)
    print(f"bf16={bf16} channels_last={cl}: {(time.perf_counter()-t)/n*1000:.0f} ms/batch")
