"""Driving with a trained SARL*-OM checkpoint: the benchmark's driver (the contract in :mod:`rl.baselines.common`)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from pipeline.core.errors import CorruptArtifactError
from rl.baselines.common import load_baseline
from rl.baselines.sarl_om.configuration import NAME, RUNTIME_FIELDS, Config
from rl.baselines.sarl_om.lookahead import Lookahead
from rl.baselines.sarl_om.model import build
from rl.baselines.sarl_om.observation import current_state, perceive


class Driver:
    """Drives with the saved value network's lookahead (see :mod:`rl.baselines.common`)."""

    def __init__(self, ckpt: Path) -> None:
        self.model, desc = load_baseline(Path(ckpt), NAME, build)
        try:
            self.oc = replace(Config(), **{k: desc["observation_space"][k] for k in RUNTIME_FIELDS})
        except (KeyError, TypeError) as e:
            raise CorruptArtifactError(f"{Path(ckpt) / 'policy.json'}: observation_space lacks {e}") from None
        self.look: Lookahead | None = None
        self.last_om: np.ndarray | None = None

    def reset(self, obs: dict[str, np.ndarray], info: dict) -> None:
        self.look = Lookahead(self.model, self.oc, info["world"])

    def act(self, obs: dict[str, np.ndarray], info: dict) -> int:
        """The lookahead's action toward ``info["waypoint"]`` (absent: the goal) in the true world
        (``info["world"]``, :class:`sim.wrappers.PrivilegedWorld`)."""
        sc = perceive(info["world"], info.get("waypoint"), self.oc)
        self.last_om = current_state(sc, self.oc)["om"][0]
        return self.look.act(sc)

    def bev_panel(self) -> np.ndarray | None:
        """The angular map as an image (rows: range bins near to far; columns: sectors, goal direction centred;
        1 = a static hit at or before that range)."""
        if self.last_om is None:
            return None
        bins = (np.arange(32) + 0.5) / 32  # closeness 1 - r/R of each range bin: near rows first
        return (self.last_om[None, :] >= 1.0 - bins[:, None]).astype(np.float32)
