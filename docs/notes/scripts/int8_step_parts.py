"""Wall time per step of a method's benchmark episodes, split by part (no profiler): env.step (sim+render+detect),
observer (encoder, perception), policy. .venv/bin/python docs/notes/scripts/int8_step_parts.py DATA METHOD SCENE DENSITY SEED N"""
import sys
import time
from pathlib import Path

import torch

import pretrain.model as M
import rl.driver as D
import rl.observe as O
import sim.env as E
from evaluation.harness import Job, cached_driver, make_env, reset_options
from evaluation.methods import resolve_methods
from evaluation.stage import EvalConfig
from pipeline.core.config import load_config
from sim.episode import episode_steps

torch.set_num_threads(1)
data, method, scene, dens, seed, n = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4]), int(sys.argv[5]), int(sys.argv[6])
cfg = load_config(EvalConfig, "eval", "default", {"data_dir": data})
spec = resolve_methods([method], Path(data))[0]
T = {}
def timed(cls, name, key):
    f = getattr(cls, name)
    def w(*a, **k):
        t = time.perf_counter(); r = f(*a, **k); T[key] = T.get(key, 0) + time.perf_counter() - t; return r
    setattr(cls, name, w)
timed(E.CrowdNavEnv, "step", "env.step")
timed(E.CrowdNavEnv, "render_cameras", "render")
timed(O.StudentObserver, "__call__", "observer")
timed(M.BEVStream, "step", "encoder")
timed(M.BEVEncoder, "image_features", "trunk")
timed(M.BEVEncoder, "fuse_pooled", "fuse")
timed(D.PolicyDriver, "act", "act")
out = Path("/tmp/exp/prof_out")
steps = 0; t0 = None
for k in range(n + 1):
    if k == 1:
        T.clear(); t0 = time.perf_counter(); steps = 0
    j = Job(spec, cfg.sim, scene, dens, seed + k, out, save_trace=False, scene_seed=seed + k)
    drv = cached_driver(spec); env = make_env(j)
    for tr in episode_steps(env, drv, j.seed, reset_options(j)):
        steps += tr.step > 0
    env.close()
wall = time.perf_counter() - t0
print(f"{method} {scene} {dens}: {n} ep, {steps} steps, {1000*wall/steps:.1f} ms/step")
for k, v in T.items():
    print(f"  {k:10s} {1000*v/steps:6.1f} ms/step")
