"""Deploying the ViNT-style baseline: ViNT's controller, the context buffer and the benchmark's driver (the
contract in :mod:`rl.baselines.common`)."""

from __future__ import annotations

import math
from collections import deque
from pathlib import Path

import numpy as np
import torch

from pipeline.core.errors import ConfigError, CorruptArtifactError
from rl.baselines.common import load_baseline
from rl.baselines.vint.configuration import NAME
from rl.baselines.vint.data import goal_features, side_by_side
from rl.baselines.vint.model import ViNTStyle, build_model
from sim.geometry import world_to_robot


def vint_controller(waypoint: np.ndarray, dt_s: float, v_max: float, w_max: float, eps: float = 1e-8
                    ) -> tuple[float, float]:
    """ViNT's ``pd_controller``: one waypoint [dx, dy, cos, sin] (metres, robot frame) -> clipped (v, ω);
    ``dt_s`` = the time of one waypoint step."""
    dx, dy, hx, hy = (float(v) for v in waypoint)
    if abs(dx) < eps and abs(dy) < eps:
        v, w = 0.0, math.atan2(hy, hx) / dt_s
    elif abs(dx) < eps:
        v, w = 0.0, math.copysign(math.pi / (2 * dt_s), dy)
    else:
        v, w = dx / dt_s, math.atan(dy / dx) / dt_s
    return float(np.clip(v, 0.0, v_max)), float(np.clip(w, -w_max, w_max))


class ContextBuffer:
    """The last ``context * spacing + 1`` frames of an episode; :meth:`window` = every ``spacing``-th one, oldest
    first, the newest last. The first frame of an episode fills it (ViNT repeats it likewise)."""

    def __init__(self, context: int, spacing: int) -> None:
        self.context, self.spacing = context, spacing
        self.frames: deque[np.ndarray] = deque(maxlen=context * spacing + 1)

    def reset(self) -> None:
        self.frames.clear()

    def push(self, frame: np.ndarray) -> None:
        if not self.frames:
            self.frames.extend([frame] * self.frames.maxlen)
        else:
            self.frames.append(frame)

    def window(self) -> np.ndarray:
        """``(P+1) x ...`` the context frames and the current one."""
        return np.stack(list(self.frames)[:: self.spacing])


class Driver:
    """The ViNT-style policy in the benchmark harness (:class:`sim.episode.Driver`): the two camera images
    of ``obs`` into the context buffer, the goal (or ``info["waypoint"]``) in the robot frame from odometry, ViNT's controller on the
    predicted waypoint."""

    def __init__(self, ckpt: Path) -> None:
        model, desc = load_baseline(Path(ckpt), NAME, build_model)
        self.model: ViNTStyle = model  # type: ignore[assignment]
        try:
            d = desc["deploy"]
            self.spacing_s = float(d["spacing"]) / float(d["fps"])
            self.metres_per_step = float(d["metres_per_step"])
            self.waypoint_index = int(d["waypoint_index"])
            self.goal_scale_m = float(d["goal_scale_m"])
        except (KeyError, TypeError, ValueError) as e:
            raise CorruptArtifactError(f"{Path(ckpt) / 'policy.json'}: bad deploy block ({e!r})") from None
        self.buffer = ContextBuffer(self.model.context, 1)
        self.last_waypoints: np.ndarray | None = None

    def reset(self, obs: dict[str, np.ndarray], info: dict) -> None:
        self.sim, self.codec, self.goal_xy = info["config"], info["action_codec"], info["goal_xy"]
        dt_s = self.sim.dt_s
        steps = round(self.spacing_s / dt_s)
        if steps < 1 or abs(steps * dt_s - self.spacing_s) > 1e-6:
            raise ConfigError(f"vint: the context spacing {self.spacing_s:g} s is not a whole number of env steps "
                              f"(dt_s = {dt_s:g})")
        self.buffer = ContextBuffer(self.model.context, steps)
        self.last_waypoints = None

    def act(self, obs: dict[str, np.ndarray], info: dict):
        self.buffer.push(side_by_side(obs["rgb_left"], obs["rgb_right"], self.model.image_hw))
        target = info.get("waypoint")
        target = self.goal_xy if target is None else target
        goal_rf = world_to_robot(np.asarray(target, np.float64)[:2], info["odom"]).astype(np.float32)
        goal = goal_features(goal_rf, self.goal_scale_m)
        with torch.no_grad():
            _, wp = self.model(torch.from_numpy(self.buffer.window())[None], torch.from_numpy(goal)[None])
        wp = wp[0].numpy().astype(np.float64)
        wp[:, :2] *= self.metres_per_step
        self.last_waypoints = wp
        r = self.sim.robot
        v, w = vint_controller(wp[self.waypoint_index], self.spacing_s, r.v_max_mps, r.omega_max_radps)
        return self.codec.encode(v, w)

    def bev_panel(self) -> np.ndarray | None:
        return None
