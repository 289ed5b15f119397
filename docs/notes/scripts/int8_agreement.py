"""Action agreement of a student with its frozen encoder in int8 vs fp32 on the same observation stream.

The fp32 student drives; at every step the int8 copy (its own observer, fed the same observations) also chooses.
.venv/bin/python docs/notes/scripts/int8_agreement.py DATA_DIR METHOD SEED_BASE EPISODES_PER_CELL DENSITY
"""
import sys, time, json, warnings
from pathlib import Path
import numpy as np, torch
warnings.filterwarnings("ignore")
from pipeline.core.config import load_config
from evaluation.methods import resolve_methods
from evaluation.harness import Job, make_env, reset_options
from evaluation.stage import EvalConfig
from rl.driver import PolicyDriver
from rl.policy import action_logits
from sim.episode import episode_steps
torch.set_num_threads(1)
data, method, seed_base, n, dens = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5])
cfg = load_config(EvalConfig, "eval", "default", {"data_dir": data})
spec = resolve_methods([method], Path(data))[0]
f, q = PolicyDriver(spec.checkpoint), PolicyDriver(spec.checkpoint, encoder_precision="int8")
rows = []
t0 = time.perf_counter()
for scene in ("office_lobby", "hospital_corridor", "warehouse"):
    for k in range(n):
        seed = seed_base + k
        job = Job(spec, cfg.sim, scene, dens, seed, Path("/tmp/exp/agree"), save_trace=False, scene_seed=seed)
        env = make_env(job)
        same = steps = 0; gaps = []; tf = tq = 0.0
        for tr in episode_steps(env, f, job.seed, reset_options(job)):
            if tr.step == 0:
                q.reset(tr.obs, tr.info)
                continue
            if tr.done:
                break
            t = time.perf_counter(); of = f.observer(tr.obs); tf += time.perf_counter() - t
            t = time.perf_counter(); oq = q.observer(tr.obs); tq += time.perf_counter() - t
            of["state"] = oq["state"] = tr.obs["state"]
            lf, lq = action_logits(f.policy, of), action_logits(q.policy, oq)
            af, aq = int(np.argmax(lf)), int(np.argmax(lq))
            same += af == aq; steps += 1
            gaps.append(float(lf[af] - lf[aq]))
        outcome = env.unwrapped.trace(method=method).outcome
        env.close()
        rows.append({"scene": scene, "seed": seed, "steps": steps, "agree": same / max(steps, 1), "outcome": outcome,
                     "gap_median": float(np.median(gaps)) if gaps else 0.0,
                     "gap_p90": float(np.percentile(gaps, 90)) if gaps else 0.0,
                     "observer_ms_fp32": 1000 * tf / max(steps, 1), "observer_ms_int8": 1000 * tq / max(steps, 1)})
        print(json.dumps(rows[-1]), flush=True)
steps = sum(r["steps"] for r in rows)
agree = sum(r["agree"] * r["steps"] for r in rows) / steps
print(f"{method} d={dens}: {len(rows)} episodes, {steps} steps, argmax agreement {agree:.4f}; "
      f"observer {np.mean([r['observer_ms_fp32'] for r in rows]):.1f} vs {np.mean([r['observer_ms_int8'] for r in rows]):.1f} ms; "
      f"{time.perf_counter() - t0:.0f} s")
