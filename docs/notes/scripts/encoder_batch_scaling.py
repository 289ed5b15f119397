"""The students' frozen BEV encoder streaming B episodes at once: ms per step and per stream, fp32 and bf16, one
and two torch threads (random weights of the default architecture; one rendered office-lobby 0.2 frame repeated
over the batch). Run from the repository root, machine otherwise idle:
.venv/bin/python docs/notes/scripts/encoder_batch_scaling.py"""
import statistics
import time
import warnings
from dataclasses import replace

import torch

warnings.filterwarnings("ignore")
from evaluation.stage import EvalConfig  # noqa: E402
from pipeline.core.config import load_config  # noqa: E402
from pretrain.model import BEVEncoder, BEVStream  # noqa: E402
from pretrain.quantize import BF16BEVEncoder  # noqa: E402
from pretrain.stage import PretrainConfig  # noqa: E402
from rl.bench import _stream_inputs  # noqa: E402
from rl.observe import env_cameras  # noqa: E402
from sim.env import CrowdNavEnv  # noqa: E402

enc_cfg = load_config(PretrainConfig, "pretrain", "default").encoder
sim_cfg = load_config(EvalConfig, "eval", "default").sim
env = CrowdNavEnv(config=replace(sim_cfg, scene="office_lobby", density=0.2, obs_mode="visual"))
obs, _ = env.reset(seed=0)
cams = env_cameras(env)
torch.manual_seed(0)
enc = BEVEncoder(enc_cfg, cams).eval().requires_grad_(False)
rgb, depth, pose = _stream_inputs(obs, [c.name for c in cams])
configs = [(pr, th, b) for pr in ("fp32", "bf16") for th in (1, 2) for b in (1, 2, 4, 8)]
encoders = {"fp32": enc, "bf16": BF16BEVEncoder(enc)}
ms: dict[tuple, list[float]] = {c: [] for c in configs}
for _round in range(5):  # the configurations alternate, so a slow spell of the shared VM hits them all alike
    for precision, threads, b in configs:
        torch.set_num_threads(threads)
        s = BEVStream(encoders[precision])
        r, d = rgb.expand(b, *rgb.shape[1:]).contiguous(), depth.expand(b, *depth.shape[1:]).contiguous()
        p = pose.expand(b, 3).contiguous()
        for _ in range(2):
            s.step(r, d, p)
        n, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < 1.5:
            s.step(r, d, p)
            n += 1
        ms[(precision, threads, b)].append(1e3 * (time.perf_counter() - t0) / n)
for (precision, threads, b), v in ms.items():
    m = statistics.median(v)
    print(f"{precision} threads={threads} B={b}: {m:.1f} ms per step, {m / b:.1f} ms per stream "
          f"(median of {len(v)}, {min(v) / b:.1f}-{max(v) / b:.1f})", flush=True)
