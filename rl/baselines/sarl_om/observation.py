"""What SARL*-OM observes (package docstring): the :class:`Scene` in the robot frame, and the joint states in the
goal frame that the value network reads."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rl.baselines.common import to_robot_frame, tracked_pedestrians
from rl.baselines.sarl_om.configuration import HUMAN_DIM, SELF_DIM, Config
from sim.env import CrowdNavEnv
from sim.geometry import wrap_angle


@dataclass
class Scene:
    """What the robot sees now, in its own frame (x forward, y left): ``goal`` (2,), ``humans`` M x 5 [x, y, vx,
    vy, radius] (M <= max_humans, nearest first), ``hits`` P x 2 static-scan hits, ``speed`` (m/s, last command),
    ``radius`` ρ_robot, ``v_pref`` and ``goal_radius`` (m)."""

    goal: np.ndarray
    humans: np.ndarray
    hits: np.ndarray
    speed: float
    radius: float
    v_pref: float
    goal_radius: float


def perceive(env: CrowdNavEnv, goal_xy: np.ndarray | None, oc: Config) -> Scene:
    """The :class:`Scene` of the env's current state toward ``goal_xy`` (world frame; the env's goal if None)."""
    x, y, yaw = env.robot
    ang = np.arange(oc.om_rays) * (2 * math.pi / oc.om_rays)  # robot frame
    r = np.asarray(env.layout.geometry.raycast(np.array([x, y]), yaw + ang, oc.om_range_m), np.float64)
    hit = r < oc.om_range_m - 1e-6
    hits = np.stack([r[hit] * np.cos(ang[hit]), r[hit] * np.sin(ang[hit])], -1)
    rc = env.cfg.robot
    return Scene(goal=to_robot_frame(env, env.goal if goal_xy is None else goal_xy).astype(np.float64),
                 humans=tracked_pedestrians(env, oc.sensor_range_m)[:oc.max_humans].astype(np.float64),
                 hits=hits, speed=float(env.robot_v[0]), radius=rc.radius_m, v_pref=rc.v_max_mps,
                 goal_radius=env.cfg.goal_radius_m)


def joint_state(sc: Scene, pos: np.ndarray, theta: np.ndarray, vel: np.ndarray, hpos: np.ndarray,
                oc: Config) -> dict[str, np.ndarray]:
    """The joint states (package docstring) of ``B`` robot states in the scene's frame: ``pos`` B x 2, ``theta``
    B, ``vel`` B x 2 (velocity), with the humans at ``hpos`` (M x 2) moving with ``sc.humans`` velocities.

    Returns ``self`` B x 6, ``humans`` B x K x 7, ``mask`` B x K, ``om`` B x S (float32)."""
    b, k, m = len(pos), oc.max_humans, len(hpos)
    d = sc.goal[None, :] - pos
    rot = np.arctan2(d[:, 1], d[:, 0])
    c, s = np.cos(rot)[:, None], np.sin(rot)[:, None]

    def rotate(v: np.ndarray) -> np.ndarray:  # ... x 2 vectors into each goal frame (B leading)
        cc, ss = (c, s) if v.ndim == 2 else (c[..., None], s[..., None])
        return np.stack([v[..., 0] * cc[..., 0] + v[..., 1] * ss[..., 0],
                         v[..., 1] * cc[..., 0] - v[..., 0] * ss[..., 0]], -1)

    out = {"self": np.zeros((b, SELF_DIM)), "humans": np.zeros((b, k, HUMAN_DIM)), "mask": np.zeros((b, k)),
           "om": np.zeros((b, oc.om_sectors))}
    out["self"][:, 0] = np.hypot(d[:, 0], d[:, 1])
    out["self"][:, 1] = sc.v_pref
    out["self"][:, 2] = wrap_angle(theta - rot)
    out["self"][:, 3] = sc.radius
    out["self"][:, 4:6] = rotate(vel)
    if m:
        rel = rotate(hpos[None, :, :] - pos[:, None, :])  # B x M x 2
        hv = rotate(np.broadcast_to(sc.humans[None, :, 2:4], (b, m, 2)))
        hr = sc.humans[:, 4]
        out["humans"][:, :m] = np.concatenate(
            [rel, hv, np.broadcast_to(hr, (b, m))[..., None], np.hypot(rel[..., 0], rel[..., 1])[..., None],
             np.broadcast_to(hr + sc.radius, (b, m))[..., None]], -1)
        out["mask"][:, :m] = 1.0
    if len(sc.hits):
        rel = rotate(sc.hits[None, :, :] - pos[:, None, :])  # B x P x 2
        close = 1.0 - np.clip(np.hypot(rel[..., 0], rel[..., 1]) / oc.om_range_m, 0.0, 1.0)
        sector = np.floor((np.arctan2(rel[..., 1], rel[..., 0]) + math.pi) / (2 * math.pi) * oc.om_sectors)
        sector = np.clip(sector.astype(np.intp), 0, oc.om_sectors - 1)
        np.maximum.at(out["om"], (np.repeat(np.arange(b), sector.shape[1]), sector.ravel()), close.ravel())
    return {key: v.astype(np.float32) for key, v in out.items()}


def current_state(sc: Scene, oc: Config) -> dict[str, np.ndarray]:
    """The joint state of the robot now (one row)."""
    return joint_state(sc, np.zeros((1, 2)), np.zeros(1), np.array([[sc.speed, 0.0]]), sc.humans[:, :2], oc)
