"""bf16 vs fp32 cloning on the same data from the same start: /tmp/dc2's `full` DAgger frames (iterations 0-3, fp32
encoder), every 2nd episode of iteration 3 held out (unseen by the start); each clones 8 epochs from the iteration-2 policy (the
fitted linear and map cost frozen, as rl.stage.distill does) and are scored on the held-out frames.
Run from the repository root: .venv/bin/python docs/notes/scripts/bf16_cloning_ab.py DATA_DIR
(docs/notes/2026-12-bf16-training.md)"""
import sys
import time
from pathlib import Path

import numpy as np
import torch

from rl.dagger import feature_files, pool_frames
from rl.policy import load_policy
from rl.teacher import (
    FITTED_PREFIXES,
    bc_loss,
    behaviour_clone,
    lookahead_feature_cache,
    policy_logits_values,
)

torch.set_num_threads(2)
root = Path(sys.argv[1] if len(sys.argv) > 1 else "data") / "checkpoints/policy/full/dagger"
files = feature_files([root / f"iter_{k}" for k in range(4)])
held = feature_files([root / 'iter_3'])[::2]; train = [f for f in files if f not in held]  # unseen by the iteration-2 start
tr = pool_frames(train); te = pool_frames(held)
for d in (tr, te):
    d["costs"] = -d.pop("teacher_logits")
print(f"{len(train)} train episodes ({len(tr['action'])} frames), {len(held)} held out ({len(te['action'])} frames)", flush=True)
res = {}
for name, precision, seed in (("fp32", "fp32", 3), ("bf16", "bf16", 3), ("fp32_seed4", "fp32", 4)):
    policy, _ = load_policy(root / "iter_2" / "policy", shield_s=0.0)
    cache = lookahead_feature_cache(policy, tr, True, 21)
    t = time.perf_counter()
    rows = behaviour_clone(policy, tr, 8, 128, 5e-4, seed, progress=False, soft_tau=1.0, mirror=True, n_rot=21,
                           frozen=FITTED_PREFIXES, cache=cache, precision=precision)
    wall = time.perf_counter() - t
    with torch.no_grad():
        keys = tuple(policy.observation_space.spaces)
        arg = []
        for s in range(0, len(te["action"]), 512):
            obs = {k: torch.as_tensor(te[k][s:s + 512], dtype=torch.float32) for k in keys}
            arg.append(policy_logits_values(policy, obs)[0].argmax(-1).numpy())
    res[name] = {"wall_s": round(wall, 1), "s_per_epoch": round(wall / 8, 1),
                      "train_bc_loss_last_epoch": round(rows[-1]["bc_loss"], 4),
                      "heldout_soft_ce": round(bc_loss(policy, te, soft_tau=1.0), 4),
                      "heldout_nll_teacher_argmax": round(bc_loss(policy, te), 4),
                      "heldout_teacher_argmax_acc": round(float((np.concatenate(arg) == te["action"]).mean()), 4)}
    res[name]["_argmax"] = np.concatenate(arg)
    print(name, {k: v for k, v in res[name].items() if k != "_argmax"}, flush=True)
def agree(a, b):
    return float((res[a]["_argmax"] == res[b]["_argmax"]).mean())
print(f"held-out argmax agreement: fp32 vs bf16 (same seed) {agree('fp32', 'bf16'):.4f}; fp32 seed 3 vs seed 4 "
      f"(the cloning's own spread) {agree('fp32', 'fp32_seed4'):.4f}; bf16 speed-up x{res['fp32']['wall_s'] / res['bf16']['wall_s']:.2f}")
