"""Benchmark figures of the BEV encoder (called by ``icrowdnav bench``; single CPU thread, the profile's cameras).

* ``bev_lift_ms`` / ``bev_lift_reference_ms`` / ``bev_lift_speedup_vs_reference`` — :func:`lift_splat` vs the
  per-point loop :func:`lift_splat_reference` on the same rendered RGB-D frame pair (real depth from the sim, so
  the number of lifted points is realistic); the outputs are compared first;
* ``bev_stream_ms_per_step`` — :meth:`BEVStream.step`: encode the newest frame pair, warp the cached history,
  temporal model; ``bev_recompute_ms_per_step`` — :meth:`BEVEncoder.forward` on the whole window of T frames (what
  a policy without the cache would do each step); ``bev_stream_speedup_vs_recompute`` their ratio;
* ``bev_stream_hz`` — streaming steps per second; ``bev_backbone_ms`` — the image backbone alone on one frame pair.

The encoder has the profile's ``pretrain.encoder`` architecture with random weights (speed does not depend on
the weights); the frames come from the bench scene rendered at the profile's camera resolution.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np
import torch

import sim  # noqa: F401
from pipeline.core.timing import time_call
from pretrain.geometry import Camera, lift_splat, lift_splat_reference
from pretrain.model import BEVEncoder, BEVStream


def _ms(fn, seconds: float) -> float:
    """Mean milliseconds per call (the bench's own timer, :func:`pipeline.core.timing.time_call`)."""

    return 1000.0 * time_call(fn, seconds)


def measure_bev(sim_cfg: Any, scene: str, density: float, seed: int, encoder_cfg: Any, seconds: float) -> dict:
    """The figures of this module (see its docstring)."""
    import gymnasium as gym

    env = gym.make("icrowdnav/CrowdNav-v0", config=replace(sim_cfg, scene=scene, density=density, obs_mode="visual",
                                                           info_level="basic"))
    obs, _ = env.reset(seed=seed)
    u = env.unwrapped
    cameras = [Camera.from_dict(spec.to_dict()) for spec in u.cameras]
    frames = []
    for _ in range(encoder_cfg.history_frames + 1):
        frames.append(obs)
        obs, *_ = env.step(np.array([0.6, 0.2], dtype=np.float32))
    env.close()
    names = [c.name for c in cameras]

    def tensors(o):
        rgb = torch.from_numpy(np.stack([o[f"rgb_{n}"] for n in names])).permute(0, 3, 1, 2).unsqueeze(0)
        depth = torch.from_numpy(np.stack([o[f"depth_{n}"] for n in names])).unsqueeze(0)
        return rgb.contiguous(), depth, torch.from_numpy(o["odom"].astype(np.float64)).unsqueeze(0)

    prev = torch.get_num_threads()
    torch.set_num_threads(1)
    out: dict[str, float] = {}
    try:
        torch.manual_seed(seed)
        enc = BEVEncoder(encoder_cfg, cameras).eval()
        rgb, depth, pose = tensors(frames[-1])
        with torch.inference_mode():
            feats = enc.image_features(rgb[0]).unsqueeze(0)
            d = enc.lift_depth(depth)
            fast = lift_splat(feats, d, enc.geom, enc.grid)
            ref = lift_splat_reference(feats.double().numpy(), d.double().numpy(), cameras,
                                       encoder_cfg.lift_stride_px, enc.grid)
            if not np.allclose(fast.numpy(), ref, rtol=1e-4, atol=1e-3):
                raise RuntimeError("fast lift disagrees with the reference lift")
            out["bev_lift_points"] = float((d > 0).sum())
            out["bev_lift_ms"] = _ms(lambda: lift_splat(feats, d, enc.geom, enc.grid), seconds / 4)
            t0 = time.perf_counter()
            lift_splat_reference(feats.double().numpy(), d.double().numpy(), cameras, encoder_cfg.lift_stride_px,
                                 enc.grid)
            out["bev_lift_reference_ms"] = 1000.0 * (time.perf_counter() - t0)
            out["bev_lift_speedup_vs_reference"] = out["bev_lift_reference_ms"] / out["bev_lift_ms"]
            out["bev_backbone_ms"] = _ms(lambda: enc.image_features(rgb[0]), seconds / 4)

            window = [tensors(f) for f in frames[-encoder_cfg.history_frames:]]
            w_rgb = torch.stack([w[0] for w in window], 1)
            w_depth = torch.stack([w[1] for w in window], 1)
            w_pose = torch.stack([w[2] for w in window], 1)
            out["bev_recompute_ms_per_step"] = _ms(lambda: enc(w_rgb, w_depth, w_pose), seconds / 2)
            stream = BEVStream(enc)
            for w in window:
                s = stream.step(*w)
            batch = enc(w_rgb, w_depth, w_pose)
            if not torch.allclose(s, batch, atol=1e-4, rtol=1e-4):
                raise RuntimeError("streaming encoder disagrees with the batch forward")
            out["bev_stream_ms_per_step"] = _ms(lambda: stream.step(*window[-1]), seconds / 2)
        out["bev_stream_speedup_vs_recompute"] = out["bev_recompute_ms_per_step"] / out["bev_stream_ms_per_step"]
        out["bev_stream_hz"] = 1000.0 / out["bev_stream_ms_per_step"]
        out["bev_grid_cells"] = float(np.prod(enc.grid.shape))
        out["bev_channels"] = float(encoder_cfg.bev_channels)
    finally:
        torch.set_num_threads(prev)
    return out
