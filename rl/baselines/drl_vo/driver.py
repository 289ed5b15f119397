"""Driving with a trained DRL-VO checkpoint: the benchmark's driver (the contract in :mod:`rl.baselines.common`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from pipeline.core.errors import CorruptArtifactError
from rl.baselines.common import load_baseline
from rl.baselines.drl_vo.configuration import NAME
from rl.baselines.drl_vo.model import build_policy
from rl.baselines.drl_vo.observation import Observer, kinematic_map


class Driver:
    """Drives with a trained DRL-VO checkpoint (deterministic: the Gaussian's mean)."""

    def __init__(self, ckpt: Path) -> None:
        self.policy, desc = load_baseline(Path(ckpt), NAME, build_policy)
        try:
            self.observer = Observer(**desc["observer"])
            self.v_max, self.w_max = float(desc["robot"]["v_max_mps"]), float(desc["robot"]["omega_max_radps"])
        except (KeyError, TypeError) as e:
            raise CorruptArtifactError(f"{Path(ckpt) / 'policy.json'}: not a drl_vo description "
                                       f"({type(e).__name__}: {e})") from None
        self.last: dict[str, np.ndarray] = {}

    def reset(self, obs: dict[str, np.ndarray], info: dict) -> None:
        self.codec = info["action_codec"]
        self.observer.reset(info["world"])
        self.last = {}

    @torch.no_grad()
    def act(self, obs: dict[str, np.ndarray], info: dict):
        """The env action of the policy's (v, ω) toward ``info["waypoint"]`` (absent: the goal); the lidar and the
        tracks come from the true world (``info["world"]``, :class:`sim.wrappers.PrivilegedWorld`)."""
        self.last = self.observer(info["world"], target=info.get("waypoint"))
        a, _ = self.policy.predict(self.last, deterministic=True)
        a = np.clip(np.asarray(a, np.float64).reshape(2), -1.0, 1.0)
        return self.codec.encode((a[0] + 1.0) / 2.0 * self.v_max, a[1] * self.w_max)

    def bev_panel(self) -> np.ndarray | None:
        """Speed (m/s) in each cell of the last kinematic map (80 x 80, row 0 nearest), None before a step."""
        if not self.last:
            return None
        m = kinematic_map(torch.as_tensor(self.last["peds"])[None])[0].numpy()
        return np.hypot(m[0], m[1])
