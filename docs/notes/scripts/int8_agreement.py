"""Action agreement of a student with its frozen encoder in int8 vs fp32 on the same observation stream.

The fp32 student drives; at every step the int8 copy and a control copy (the same fp32 encoder object, its own
observer: must agree always) — each with its own observer, fed the same observations — also choose.
.venv/bin/python docs/notes/scripts/int8_agreement.py DATA_DIR METHOD|CHECKPOINT_DIR SEED_BASE EPISODES_PER_CELL DENSITY
"""
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

warnings.filterwarnings("ignore")
from evaluation.harness import Job, make_env, reset_options
from evaluation.methods import MethodSpec, resolve_methods
from evaluation.stage import EvalConfig
from pipeline.core.config import load_config
from rl.driver import PolicyDriver
from rl.policy import action_logits

torch.set_num_threads(1)
data, method, seed_base, n, dens = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5])
cfg = load_config(EvalConfig, "eval", "default", {"data_dir": data})
if Path(method).is_dir():  # a policy checkpoint directory (e.g. a DAgger iteration's policy/)
    spec = MethodSpec("student", "student", "policy", "visual", checkpoint=Path(method), action_type="discrete")
else:
    spec = resolve_methods([method], Path(data))[0]
f, q, c = (PolicyDriver(spec.checkpoint), PolicyDriver(spec.checkpoint, encoder_precision="int8"),
           PolicyDriver(spec.checkpoint))
rows = []
t0 = time.perf_counter()
for scene in ("office_lobby", "hospital_corridor", "warehouse"):
    for k in range(n):
        seed = seed_base + k
        job = Job(spec, cfg.sim, scene, dens, seed, Path("/tmp/exp/agree"), save_trace=False, scene_seed=seed)
        env = make_env(job)
        obs, info = env.reset(seed=job.seed, options=reset_options(job))
        for d in (f, q, c):
            d.reset(obs, info)
        same = same_c = steps = 0; gaps = []; dbev = []; docc = []; tf = tq = 0.0
        while True:
            t = time.perf_counter(); of = f.observer(obs); tf += time.perf_counter() - t
            t = time.perf_counter(); oq = q.observer(obs); tq += time.perf_counter() - t
            oc = c.observer(obs)
            of["state"] = oq["state"] = oc["state"] = obs["state"]
            lf, lq, lc = action_logits(f.policy, of), action_logits(q.policy, oq), action_logits(c.policy, oc)
            af, aq, ac = int(np.argmax(lf)), int(np.argmax(lq)), int(np.argmax(lc))
            same += af == aq; same_c += af == ac; steps += 1
            gaps.append(float(lf[af] - lf[aq]))
            dbev.append(float(np.abs(oq["bev"] - of["bev"]).mean() / (np.abs(of["bev"]).mean() + 1e-12)))
            if "bev_occ" in of:
                docc.append(float(np.abs(oq["bev_occ"] - of["bev_occ"]).mean()))
            obs, _, term, trunc, info = env.step(af)
            if term or trunc:
                break
        outcome = env.unwrapped.trace(method="student").outcome
        env.close()
        rows.append({"scene": scene, "seed": seed, "steps": steps, "agree": same / steps, "agree_control": same_c / steps,
                     "outcome": outcome, "bev_rel_err": float(np.mean(dbev)),
                     "bev_occ_abs_err": float(np.mean(docc)) if docc else None,
                     "gap_median_when_different": float(np.median([g for g in gaps if g > 0])) if any(g > 0 for g in gaps) else 0.0,
                     "gap_p90": float(np.percentile(gaps, 90)),
                     "observer_ms_fp32": 1000 * tf / steps, "observer_ms_int8": 1000 * tq / steps})
        print(json.dumps(rows[-1]), flush=True)
steps = sum(r["steps"] for r in rows)
agree = sum(r["agree"] * r["steps"] for r in rows) / steps
agree_c = sum(r["agree_control"] * r["steps"] for r in rows) / steps
print(f"{method} d={dens}: {len(rows)} episodes, {steps} steps, argmax agreement int8 {agree:.4f} (control "
      f"{agree_c:.4f}); observer {np.mean([r['observer_ms_fp32'] for r in rows]):.1f} vs "
      f"{np.mean([r['observer_ms_int8'] for r in rows]):.1f} ms; {time.perf_counter() - t0:.0f} s")
