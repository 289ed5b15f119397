"""Pretraining step time, fp32 vs bf16 autocast, on 3 episodes of a default recording's dataset (the default encoder,
random init, 6 timed steps after one warm-up; losses printed to show the same descent).
Run from the repository root: .venv/bin/python docs/notes/scripts/bf16_pretrain_step.py THREADS [DATASET]
(docs/notes/2026-12-bf16-training.md)"""
import sys
import time

import numpy as np
import torch

from pretrain.data import check_dataset, load_frames, make_batches, make_clips
from pretrain.geometry import check_grid_fits_cameras
from pretrain.model import BEVEncoder, EncoderConfig, PretextHeads
from pretrain.train import forward_batch, loss_mask, masked_bce, positive_weights

torch.set_num_threads(int(sys.argv[1]))
root = sys.argv[2] if len(sys.argv) > 2 else 'data/datasets/icrowdnav/expert'
from pathlib import Path

meta = check_dataset(Path(root))
ec = EncoderConfig(fuse_pool=2)
fov = check_grid_fits_cameras(ec.grid, meta.cameras, "x")
store = load_frames(Path(root), meta.cameras, ec.grid, ec.lift_stride_px, [0.5, 1.0], episodes=[0, 1, 2], progress=False)
sl = store.episode_slices
mask = torch.from_numpy(loss_mask(fov, "fov"))
pw = positive_weights(store, sl, loss_mask(fov, "fov"), 3.0)
torch.manual_seed(0)
enc0 = BEVEncoder(ec, meta.cameras)
heads0 = PretextHeads(ec.bev_channels)
clips = make_clips(store, sl, 8, enc0.frames, np.random.default_rng(0))
batches = make_batches(clips, 4, enc0.frames)
import copy


def run(bf16, cl, n=6):
    torch.manual_seed(0)
    enc, heads = copy.deepcopy(enc0), copy.deepcopy(heads0)
    if cl:
        enc = enc.to(memory_format=torch.channels_last); heads = heads.to(memory_format=torch.channels_last)
    params = list(enc.parameters()) + list(heads.parameters())
    opt = torch.optim.AdamW(params, lr=2e-3)
    ts, ls = [], []
    for i in range(n + 1):
        t = time.perf_counter()
        with torch.autocast('cpu', dtype=torch.bfloat16, enabled=bf16):
            logits, labels, valid = forward_batch(enc, heads, store, batches[i % len(batches)])
        losses = masked_bce(logits.float(), labels, valid, mask, pw)
        loss = losses.mean()
        opt.zero_grad(); loss.backward(); torch.nn.utils.clip_grad_norm_(params, 5.0); opt.step()
        ls.append(loss.item())
        if i: ts.append(time.perf_counter() - t)
    print(f"bf16={bf16} channels_last={cl}: {np.mean(ts):.2f} s/step (median {np.median(ts):.2f}); losses {np.round(ls, 4)}", flush=True)
for bf16, cl in [(False, False), (True, False)]:  # channels-last: the encoder has 5-D weights
    run(bf16, cl)
