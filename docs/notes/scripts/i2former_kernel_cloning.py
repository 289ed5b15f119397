"""A default student's bf16 cloning epoch with the I²Former's attention on torch's math kernel (pretrain.i2former.
attention_kernel, since edf9c3d) against torch's own choice (the flash kernel on this CPU): the same start (the
DAgger iteration-1 student), data (iterations 0-1's frames) and seed, 2 epochs each, two alternating rounds.
Run from the repository root: .venv/bin/python docs/notes/scripts/i2former_kernel_cloning.py [DATA_DIR]
(docs/results.md, Performance)"""
import contextlib
import sys
import time
from pathlib import Path

import torch

import pretrain.i2former as i2
from rl.dagger import feature_files, pool_frames
from rl.policy import load_policy
from rl.teacher import FITTED_PREFIXES, behaviour_clone, lookahead_feature_cache

torch.set_num_threads(2)
root = Path(sys.argv[1] if len(sys.argv) > 1 else "data") / "checkpoints/policy/full/dagger"
data = pool_frames(feature_files([root / f"iter_{k}" for k in range(2)]))
data["costs"] = -data.pop("teacher_logits")
math_kernel = i2.attention_kernel
for _ in range(2):
    for name, kernel in (("math", math_kernel), ("default", lambda x: contextlib.nullcontext())):
        i2.attention_kernel = kernel
        policy, _ = load_policy(root / "iter_1" / "policy", shield_s=0.0)
        cache = lookahead_feature_cache(policy, data, True, 21)
        t = time.perf_counter()
        rows = behaviour_clone(policy, data, 2, 128, 5e-4, 3, progress=False, soft_tau=1.0, mirror=True, n_rot=21,
                               frozen=FITTED_PREFIXES, cache=cache, precision="bf16")
        print(f"{name}: {(time.perf_counter() - t) / 2:.2f} s per epoch ({len(data['action'])} frames); epoch losses "
              f"{[round(r['bc_loss'], 4) for r in rows]}", flush=True)
