"""Float vs int8 validation IoU of a BEV training state (mid-training weights), with two activation qconfigs.
.venv/bin/python docs/notes/scripts/int8_map_fidelity.py DATA_DIR STATE_PT VAL_EPISODES"""
import json
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

warnings.filterwarnings("ignore")
import pretrain.quantize as Q
from pipeline.core.config import load_config
from pretrain.data import check_dataset, load_frames, make_batches, make_clips, split_episodes
from pretrain.geometry import check_grid_fits_cameras
from pretrain.model import BEVEncoder, PretextHeads
from pretrain.stage import PretrainConfig, dataset_dir
from pretrain.train import evaluate, forward_batch, load_state

torch.set_num_threads(1)
cfg = load_config(PretrainConfig, "pretrain", "default", {"data_dir": sys.argv[1], "progress": "false"})
root = dataset_dir(cfg); meta = check_dataset(root)
fov = check_grid_fits_cameras(cfg.encoder.grid, meta.cameras, "pretrain.encoder")
n_eps = int(meta.info["total_episodes"])
train_eps, val_eps = split_episodes(n_eps, cfg.val_fraction, cfg.seed)
val_eps = val_eps[: int(sys.argv[3])]
cal_eps = train_eps[:12]
need = sorted(set(val_eps) | set(cal_eps))
store = load_frames(root, meta.cameras, cfg.encoder.grid, cfg.encoder.lift_stride_px, cfg.future_s,
                    episodes=need, max_gb=cfg.max_ram_gb, progress=False, people_label=cfg.people_label)
sl = store.episode_slices
idx = {e: i for i, e in enumerate(need)}
st = load_state(Path(sys.argv[2]))
enc = BEVEncoder(cfg.encoder, meta.cameras); enc.load_state_dict(st["encoder"]); enc.eval()
heads = PretextHeads(cfg.encoder.bev_channels); heads.load_state_dict(st["heads"]); heads.eval()
pw = torch.ones(4)
val_sl = [sl[idx[e]] for e in val_eps]; cal_sl = [sl[idx[e]] for e in cal_eps]
res = {"step": st["step"], "fp32": evaluate(enc, heads, store, val_sl, fov, pw, cfg.clip_frames, cfg.clips_per_batch)}
print(json.dumps(res), flush=True)
clips = make_clips(store, cal_sl, cfg.clip_frames, enc.frames, np.random.default_rng([cfg.seed, 8]))
order = np.random.default_rng([cfg.seed, 9]).permutation(len(clips))
picked, n = [], 0
for i in order:
    if n >= 400: break
    picked.append(clips[int(i)]); n += len(clips[int(i)][1])
orig = Q._prepare
from torch.ao.quantization import get_default_qconfig_mapping
from torch.ao.quantization.quantize_fx import prepare_fx

for name in ("x86", "onednn"):
    def prep(module, example, name=name):
        torch.backends.quantized.engine = "x86"
        return prepare_fx(module.eval(), get_default_qconfig_mapping(name), example)
    Q._prepare = prep
    q = Q.QuantizedBEVEncoder(enc)
    with torch.no_grad():
        for b in make_batches(picked, cfg.clips_per_batch, enc.frames):
            forward_batch(q, heads, store, b)
    q.freeze()
    res[name] = evaluate(q, heads, store, val_sl, fov, pw, cfg.clip_frames, cfg.clips_per_batch)
    print(name, json.dumps(res[name]), flush=True)
