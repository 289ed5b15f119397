"""The students' frozen encoder under bfloat16 autocast (pretrain.quantize.BF16BEVEncoder) against float32: the
relative error of s_bev on 20 frames of a drive (office lobby 0.2, seed 777), and the streaming step's time on one
thread (three alternating rounds).
.venv/bin/python docs/notes/scripts/bf16_encoder_error.py DATA_DIR   (DATA_DIR/checkpoints/bev: a trained encoder)"""
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

warnings.filterwarnings("ignore")
torch.set_num_threads(1)
from evaluation.stage import EvalConfig
from pipeline.core.config import load_config
from pipeline.core.timing import time_call
from pretrain.model import BEVStream
from pretrain.quantize import BF16BEVEncoder
from rl.bench import _stream_inputs
from rl.observe import env_cameras, load_student_encoder
from sim.env import CrowdNavEnv

sim = load_config(EvalConfig, "eval", "default", {}).sim
env = CrowdNavEnv(config=replace(sim, scene="office_lobby", density=0.2, obs_mode="visual"))
obs, _ = env.reset(seed=777)
names = [c.name for c in env_cameras(env)]
enc = load_student_encoder("full", Path(sys.argv[1]) / "checkpoints" / "bev")
s32, s16 = BEVStream(enc), BEVStream(BF16BEVEncoder(enc))
frames = []
for k in range(20):  # forward, turning left then right
    frames.append(_stream_inputs(obs, names))
    obs = env.step(np.array([0.6, 0.3 if k < 10 else -0.3], np.float32))[0]
with torch.no_grad():
    err = []
    for f in frames:
        a, b = s32.step(*f), s16.step(*f)
        err.append(float((a - b).norm() / a.norm()))
print("relative error of s_bev per frame:", np.round(err, 4).tolist())
f = frames[-1]
for _ in range(3):
    print("fp32 %.1f ms, bf16 %.1f ms per streaming step" % (1000 * time_call(lambda: s32.step(*f), 2.0),
                                                             1000 * time_call(lambda: s16.step(*f), 2.0)))
