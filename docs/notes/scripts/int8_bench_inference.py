"""make bench's inference figures alone (rl.bench.measure_inference: fp32 vs int8 student, default profile, office lobby 0.2).
Run from the repository root: .venv/bin/python docs/notes/scripts/int8_bench_inference.py"""
import json
import warnings

warnings.filterwarnings("ignore")
from evaluation.stage import EvalConfig
from pipeline.core.config import load_config
from pretrain.stage import PretrainConfig
from rl.bench import measure_inference

sim = load_config(EvalConfig, "eval", "default", {}).sim
enc = load_config(PretrainConfig, "pretrain", "default").encoder
out = measure_inference(sim, "office_lobby", 0.2, 0, enc, 5.0)
print(json.dumps({k: round(v, 2) for k, v in out.items()}, indent=1))
