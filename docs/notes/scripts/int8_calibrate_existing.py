"""The pretrain stage's int8 calibration (pretrain.stage.int8_version) for an existing BEV checkpoint of older code.
.venv/bin/python docs/notes/scripts/int8_calibrate_existing.py DATA_DIR (writes DATA_DIR/checkpoints/bev/int8_calibration.safetensors,
which that older manifest does not list: for experiments; `make pretrain` writes and lists it)"""
import json
import sys
import warnings

import torch

warnings.filterwarnings("ignore")
from pipeline.core.config import load_config
from pretrain.checkpoint import load_encoder, load_heads
from pretrain.data import check_dataset, load_frames, split_episodes
from pretrain.geometry import check_grid_fits_cameras
from pretrain.stage import PretrainConfig, checkpoint_dir, dataset_dir, int8_version

torch.set_num_threads(2)
cfg = load_config(PretrainConfig, "pretrain", "default", {"data_dir": sys.argv[1], "progress": "false"})
root = dataset_dir(cfg); meta = check_dataset(root); out = checkpoint_dir(cfg)
fov = check_grid_fits_cameras(cfg.encoder.grid, meta.cameras, "pretrain.encoder")
n_eps = int(meta.info["total_episodes"])
train_eps, val_eps = split_episodes(n_eps, cfg.val_fraction, cfg.seed)
store = load_frames(root, meta.cameras, cfg.encoder.grid, cfg.encoder.lift_stride_px, cfg.future_s,
                    episodes=list(range(n_eps)), max_gb=cfg.max_ram_gb, progress=False, people_label=cfg.people_label)
sl = store.episode_slices
enc = load_encoder(out); heads = load_heads(out, enc)
metrics = json.loads((out / "metrics.json").read_text())
res = int8_version(enc, heads, store, [sl[e] for e in train_eps], [sl[e] for e in val_eps], fov, metrics["pos_weight"], cfg, out)
print(json.dumps({"int8": res, "fp32": metrics["final"]}, indent=1))
