"""The students' lookahead feature cache in a DAgger run, before and after 2026-12-06's change: (a) every key of the
observation converted (a full student's `bev` and `bev_mirror` included) and the whole growing pool recomputed each
iteration; (b) only the keys the head reads (rl.lookahead.LookaheadHead.input_keys), each iteration's new frames
appended. On a finished `make all` chain's DAgger pools; checks the arrays are equal; 2 threads; one timed pass of
each per student (the iterations' pools are prefixes of the last one, so their passes are timed on prefixes).
Run from the repository root: .venv/bin/python docs/notes/scripts/student_feature_cache.py DATA_DIR
(docs/results.md, Performance)"""
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from rl.dagger import feature_files, pool_frames
from rl.policy import load_policy
from rl.teacher import extend_feature_cache, lookahead_feature_cache

torch.set_num_threads(2)
root = Path(sys.argv[1]) / "checkpoints/policy"
for variant in ("full", "no_i2", "no_bev"):
    dag = root / variant / "dagger"
    n_iter = len(list(dag.glob("iter_*/done.json")))
    totals = [json.loads((dag / f"iter_{k}" / "done.json").read_text())["aggregate_frames"] for k in range(n_iter)]
    data = pool_frames(feature_files([dag / f"iter_{k}" for k in range(n_iter)]))
    policy, _ = load_policy(dag / f"iter_{n_iter - 1}" / "policy", shield_s=0.0)
    every = tuple(policy.observation_space.spaces)
    t = time.perf_counter()
    old = None
    for n in totals:  # before: each iteration recomputed its whole pool from every key
        old = lookahead_feature_cache(policy, {k: v[:n] for k, v in data.items()}, True, 21, keys=every)
    old_s = time.perf_counter() - t
    t = time.perf_counter()
    new, at = None, 0
    for n in totals:  # after: the new frames' features from the head's keys, appended
        new = extend_feature_cache(new, lookahead_feature_cache(policy, {k: v[at:n] for k, v in data.items()},
                                                                True, 21))
        at = n
    new_s = time.perf_counter() - t
    same = all(np.array_equal(a, b) for a, b in zip(old, new, strict=True))
    print(f"{variant}: pools {totals} frames; before {old_s:.1f} s ({sum(totals)} frame-features, "
          f"{1e3 * old_s / sum(totals):.2f} ms each), after {new_s:.1f} s ({totals[-1]}, "
          f"{1e3 * new_s / totals[-1]:.2f} ms each): {old_s / new_s:.1f}x less; arrays equal: {same}", flush=True)
