"""A lookahead student's DAgger cloning before and after 2026-12-06's fix of the frozen weights' gradients
(rl.teacher.behaviour_clone: the frozen linear cost kept requires_grad, its gradient was never zeroed and summed over
every batch inside the clipped norm). One arm per process, the same start (the `make all` chain's `full` after DAgger
iteration 2, loaded from disk: no gradients), data (iterations 0-3's pool, soft targets, mirroring, the lookahead
features) and seed, 8 epochs as iteration 3 ran them; 2 threads.
Before: PYTHONPATH=<a worktree of the commit before the fix> .venv/bin/python <this> DATA_DIR OUT.pt
After:  .venv/bin/python <this> DATA_DIR OUT.pt; then: .venv/bin/python <this> --compare BEFORE.pt AFTER.pt DATA_DIR
(docs/results.md, Performance / the notes it links)"""
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


def pool(data_dir: str) -> tuple[Path, dict[str, np.ndarray]]:
    dag = Path(data_dir) / "checkpoints/policy/full/dagger"
    data = pool_frames(feature_files([dag / f"iter_{k}" for k in range(4)]))
    data["costs"] = -data.pop("teacher_logits")
    return dag, data


if sys.argv[1] == "--compare":
    before, after = torch.load(sys.argv[2]), torch.load(sys.argv[3])
    dag, data = pool(sys.argv[4])
    new = {k: v[-4115:] for k, v in data.items()}  # iteration 3's frames (the pool's tail)
    pols, acts = [], []
    for run in (before, after):
        p, _ = load_policy(dag / "iter_2" / "policy", shield_s=0.0)
        p.load_state_dict(run["state"])
        pols.append(p)
        obs = {k: torch.as_tensor(new[k], dtype=torch.float32) for k in p.observation_space.spaces}
        feats = torch.as_tensor(lookahead_feature_cache(p, new, False, 21)[0], dtype=torch.float32)
        with torch.no_grad():
            acts.append(policy_logits_values(p, obs, feats)[0].argmax(-1))
    for name, run, p in zip(("before", "after"), (before, after), pols, strict=True):
        print(f"{name}: epochs' soft CE {[round(r['bc_loss'], 4) for r in run['rows']]}, {run['seconds']:.0f} s; "
              f"iteration 3's frames: hard CE {bc_loss(p, new):.4f}, soft CE {bc_loss(p, new, soft_tau=1.0):.4f}; "
              f"frozen weights' summed gradient norm at the end {run['frozen_grad_norm']}")
    print(f"argmax actions agree on {float((acts[0] == acts[1]).float().mean()):.3f} of iteration 3's frames")
    sys.exit(0)

dag, data = pool(sys.argv[1])
policy, _ = load_policy(dag / "iter_2" / "policy", shield_s=0.0)
cache = lookahead_feature_cache(policy, data, True, 21)
t = time.perf_counter()
rows = behaviour_clone(policy, data, 8, 128, 5e-4, 3, progress=False, soft_tau=1.0, mirror=True, n_rot=21,
                       frozen=FITTED_PREFIXES, cache=cache, precision="bf16")
grads = [p.grad for n, p in policy.named_parameters() if n.startswith(FITTED_PREFIXES) and p.grad is not None]
torch.save({"state": policy.state_dict(), "rows": rows, "seconds": time.perf_counter() - t,
            "frozen_grad_norm": round(float(torch.linalg.vector_norm(torch.stack([g.norm() for g in grads]))), 1)
            if grads else None}, sys.argv[2])
print(rows[-1], flush=True)
