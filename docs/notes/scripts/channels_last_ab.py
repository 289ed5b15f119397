"""Same-run A/B of the image trunk's memory layout (docs/results.md, Performance; docs/notes/2026-12-channels-last-
trunk.md): BEVEncoder.image_features feeds the trunk channels-last in eval mode; pretrain.bench.NCHWTrunkEncoder is
the NCHW reference with the same weights.

1. the students' streaming step (BEVStream.step, one stream, one thread, random frames, default encoder) in fp32
   and under the bf16 autocast (the bf16 encoder as it was when the note was written, restated below:
   pretrain.quantize.BF16BEVEncoder prepares folded channels-last bf16 copies since 99f0a13, and
   docs/notes/scripts/bf16_prepared_stream.py compares the two), 3 alternating rounds of 16 steps (median);
2. the default pretraining step (pretrain.bench.measure_fit_step, every thread, synthetic frames) with the trunk
   NCHW (what training does) or channels-last (the layout training does not take), 3 alternating rounds of 4 steps.

Run from the repository root: .venv/bin/python docs/notes/scripts/channels_last_ab.py"""
import json
import time
import warnings
from dataclasses import replace

import numpy as np
import torch

warnings.filterwarnings("ignore")
import pretrain.model as M  # noqa: E402
from evaluation.stage import EvalConfig  # noqa: E402
from pipeline.core.config import load_config  # noqa: E402
from pretrain.bench import NCHWTrunkEncoder, measure_fit_step  # noqa: E402
from pretrain.quantize import _FrozenCopy  # noqa: E402
from pretrain.stage import PretrainConfig  # noqa: E402
from rl.observe import env_cameras  # noqa: E402
from sim.env import CrowdNavEnv  # noqa: E402

sim = load_config(EvalConfig, "eval", "default", {}).sim
enc_cfg = load_config(PretrainConfig, "pretrain", "default").encoder
env = CrowdNavEnv(config=replace(sim, scene="office_lobby", density=0.2, obs_mode="visual"))
env.reset(seed=0)
cams = env_cameras(env)
env.close()
c0, n = cams[0], len(cams)


class AutocastBF16(_FrozenCopy):
    """The bf16 encoder until 99f0a13 (what this A/B measured): the float modules under bfloat16 autocast."""

    def image_features(self, rgb):
        with torch.autocast(rgb.device.type, dtype=torch.bfloat16):
            return M.BEVEncoder.image_features(self, rgb)

    def fuse_aligned(self, aligned, newest):
        with torch.autocast(aligned.device.type, dtype=torch.bfloat16):
            return M.BEVEncoder.fuse_aligned(self, aligned, newest)


class BF16NCHW(AutocastBF16):
    def image_features(self, rgb):
        with torch.autocast(rgb.device.type, dtype=torch.bfloat16):
            return NCHWTrunkEncoder.image_features(self, rgb)


def stream_ms(enc, steps=16):
    s = M.BEVStream(enc)
    g = torch.Generator().manual_seed(0)
    rgb = torch.randint(0, 256, (1, n, 3, c0.height, c0.width), dtype=torch.uint8, generator=g)
    depth = torch.rand(1, n, c0.height, c0.width, generator=g) * 7.7 + 0.3
    pose = torch.zeros(1, 3, dtype=torch.float64)
    ts = []
    with torch.no_grad():
        for i in range(steps + 2):
            t = time.perf_counter()
            s.step(rgb, depth, pose + 0.01 * i)
            ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts[2:]))


threads = torch.get_num_threads()
torch.set_num_threads(1)
torch.manual_seed(0)
f32 = M.BEVEncoder(enc_cfg, cams).eval().requires_grad_(False)
ref = NCHWTrunkEncoder(enc_cfg, cams).eval().requires_grad_(False)
ref.load_state_dict(f32.state_dict())
encs = {"fp32_channels_last": f32, "fp32_nchw": ref, "bf16_channels_last": AutocastBF16(f32), "bf16_nchw": BF16NCHW(f32)}
stream = {k: [] for k in encs}
for rnd in range(3):
    for k, e in encs.items():
        stream[k].append(stream_ms(e))
    print("stream round", rnd, {k: round(v[-1], 1) for k, v in stream.items()}, flush=True)
torch.set_num_threads(threads)
cl_body = M.BEVEncoder.image_features


def channels_last_in_training(self, rgb):
    x = self.normalize(rgb).contiguous(memory_format=torch.channels_last)
    f = self.neck(self.trunk(x)).float().contiguous()
    if tuple(f.shape[-2:]) != tuple(self.geom.lift_hw):
        f = torch.nn.functional.interpolate(f, size=tuple(self.geom.lift_hw), mode="bilinear", align_corners=False)
    return f


fit = {"channels_last": [], "nchw": []}
for rnd in range(3):
    for k, body in (("nchw", NCHWTrunkEncoder.image_features), ("channels_last", channels_last_in_training)):
        M.BEVEncoder.image_features = body
        fit[k].append(measure_fit_step(cams, enc_cfg, "cpu", steps=4))
    print("fit round", rnd, {k: round(v[-1]) for k, v in fit.items()}, flush=True)
M.BEVEncoder.image_features = cl_body
med = {f"stream_ms_{k}": float(np.median(v)) for k, v in stream.items()}
med |= {f"pretrain_step_ms_{k}": float(np.median(v)) for k, v in fit.items()}
for p in ("fp32", "bf16"):
    med[f"stream_speedup_{p}"] = med[f"stream_ms_{p}_nchw"] / med[f"stream_ms_{p}_channels_last"]
med["pretrain_step_speedup"] = med["pretrain_step_ms_nchw"] / med["pretrain_step_ms_channels_last"]
print(json.dumps({k: round(v, 2) for k, v in med.items()}, indent=1))
