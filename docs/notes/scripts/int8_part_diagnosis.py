"""Which part of the int8 encoder loses the static map: the image branch (trunk + neck) or the dense fusion
(temporal model + decoder + refinement)? Rebuilds `make pretrain`'s int8 version of a data dir's BEV checkpoint
exactly as the stage does (the same seeded calibration clips), then scores on the validation episodes the float
encoder, the full int8 version, and the two hybrids (one part int8, the other float); then, with the image branch
float, the dense fusion in int8 but for one of its modules kept float (each calibrated on the same clips).
.venv/bin/python docs/notes/scripts/int8_part_diagnosis.py DATA_DIR [MAX_VAL_EPISODES]"""
import json
import sys
import types
import warnings
from pathlib import Path

import torch

warnings.filterwarnings("ignore")
from pipeline.core.config import load_config
from pretrain.checkpoint import load_encoder, load_heads
from pretrain.data import check_dataset, load_frames, make_batches, split_episodes
from pretrain.geometry import check_grid_fits_cameras
from pretrain.model import BEVEncoder
from pretrain.quantize import QuantizedBEVEncoder
from pretrain.stage import PretrainConfig, calibration_clips, dataset_dir
from pretrain.train import evaluate, forward_batch

torch.set_num_threads(2)
data = Path(sys.argv[1]); max_val = int(sys.argv[2]) if len(sys.argv) > 2 else 0
cfg = load_config(PretrainConfig, "pretrain", "default", {"data_dir": str(data)})
ck = data / "checkpoints" / "bev"
metrics = json.loads((ck / "metrics.json").read_text())
root = dataset_dir(cfg); meta = check_dataset(root)
fov = check_grid_fits_cameras(cfg.encoder.grid, meta.cameras, "pretrain.encoder")
n_eps = int(meta.info["total_episodes"])
train_eps, val_eps = split_episodes(n_eps, cfg.val_fraction, cfg.seed)
val_eps = val_eps[:max_val] if max_val else val_eps
eps = sorted(set(train_eps) | set(val_eps))
store = load_frames(root, meta.cameras, cfg.encoder.grid, cfg.encoder.lift_stride_px, cfg.future_s, episodes=eps,
                    max_gb=cfg.max_ram_gb, progress=False, people_label=cfg.people_label)
sl = store.episode_slices
pos = {e: i for i, e in enumerate(eps)}  # the store's slices follow `eps`
train_slices, val_slices = [sl[pos[e]] for e in train_eps], [sl[pos[e]] for e in val_eps]
enc = load_encoder(ck, frozen=True); heads = load_heads(ck, enc).eval()
pw = torch.as_tensor(metrics["pos_weight"])
# the stage's calibration (pretrain.stage.int8_version)
picked, n = calibration_clips(store, train_slices, enc.frames, cfg)
def calibrated():
    v = QuantizedBEVEncoder(enc)
    with torch.no_grad():
        for batch in make_batches(picked, cfg.clips_per_batch, enc.frames):
            forward_batch(v, heads, store, batch)
    return v.freeze()
q = calibrated()
img_only = QuantizedBEVEncoder(enc); img_only._image_q, img_only._dense_q, img_only.frozen = q._image_q, q._dense_q, True
img_only.fuse_aligned = types.MethodType(BEVEncoder.fuse_aligned, img_only)
dense_only = QuantizedBEVEncoder(enc); dense_only._image_q, dense_only._dense_q, dense_only.frozen = q._image_q, q._dense_q, True
dense_only.image_features = types.MethodType(BEVEncoder.image_features, dense_only)
out = {"data_dir": str(data), "val_episodes": len(val_eps), "calibration_frames": n}
for name, e in (("fp32", enc), ("int8", q), ("int8 image only", img_only), ("int8 dense only", dense_only)):
    m = evaluate(e, heads, store, val_slices, fov, pw, cfg.clip_frames, cfg.clips_per_batch)
    out[name] = {k: round(float(v), 4) for k, v in m.items() if k.startswith("iou_")}
    print(name, out[name], flush=True)
from torch.ao.quantization import get_default_qconfig_mapping

import pretrain.quantize as quantize

stage_prepare = quantize._prepare


def prepare_keeping(names):
    """The stage's preparation with the modules ``names`` left float."""
    mapping = get_default_qconfig_mapping(quantize.BACKEND)
    for nm in names:
        mapping = mapping.set_module_name(nm, None)
    return lambda module, example: stage_prepare(module, example, mapping)
dense_parts = {"temporal blocks": ["blocks"], "skip + norm": ["skip", "norm"], "decoder": ["decoder"],
               "refinement": ["refine"]}
for label, names in dense_parts.items():
    quantize._prepare = prepare_keeping(names)
    v = calibrated()
    v.image_features = types.MethodType(BEVEncoder.image_features, v)
    m = evaluate(v, heads, store, val_slices, fov, pw, cfg.clip_frames, cfg.clips_per_batch)
    out[f"int8 dense, {label} float"] = {k: round(float(x), 4) for k, x in m.items() if k.startswith("iou_")}
    print(f"int8 dense, {label} float", out[f"int8 dense, {label} float"], flush=True)
print(json.dumps(out))
