"""Env wrappers that decide what a driver may know beyond the robot's own sensors.

* :class:`PrivilegedWorld` adds ``info["world"]``, a :class:`WorldView` of the true state (robot pose and
  velocity, goal, pedestrians, the static map): for the privileged expert and the teacher's labels.
* :class:`PrivilegedObservation` adds the privileged teacher's observation channels (:func:`privileged_observation`)
  to an env of any obs mode (a teacher driven in a rendered episode, DAgger labels).
* :class:`FollowWaypoints` tracks a topological plan (long-horizon runs) and re-targets the observation: it adds
  ``info["waypoint"]`` (world frame, m) and writes the robot state s (and, in the privileged obs mode, the
  sub-goal, the path and the privileged channels) toward the current waypoint instead of the final goal.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from sim.planners.global_path import route_waypoints
from sim.planners.topomap import WaypointFollower
from sim.scene import SceneLayout


@dataclass(frozen=True)
class CrowdState:
    """The pedestrians' true state: ``pos``/``vel`` ``N x 2`` (world frame, m, m/s), ``radius`` ``N`` (m)."""

    pos: np.ndarray
    vel: np.ndarray
    radius: np.ndarray

    @property
    def n(self) -> int:
        return len(self.pos)


@dataclass(frozen=True)
class WorldView:
    """The true world at one step, as a privileged driver sees it (copies; the layout is the episode's static map).

    ``robot`` [x, y, yaw] (world frame, m, rad), ``robot_v`` [v, ω] (m/s, rad/s), ``goal`` [x, y], ``d_goal``
    (robot centre to goal, m), ``crowd`` (:class:`CrowdState`), ``layout`` (:class:`sim.scene.SceneLayout`), ``cfg``
    (the env's :class:`sim.env.SimConfig`).
    """

    robot: np.ndarray
    robot_v: np.ndarray
    goal: np.ndarray
    d_goal: float
    crowd: CrowdState
    layout: SceneLayout
    cfg: Any

    @classmethod
    def of(cls, env: gym.Env) -> WorldView:
        u = env.unwrapped
        return cls(u.robot.copy(), u.robot_v.copy(), u.goal.copy(), float(u.d_goal),
                   CrowdState(u.crowd.pos.copy(), u.crowd.vel.copy(), u.crowd.radius.copy()), u.layout, u.cfg)


class PrivilegedWorld(gym.Wrapper):
    """Adds ``info["world"]`` (:class:`WorldView`) after ``reset`` and every ``step``."""

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        info["world"] = WorldView.of(self.env)
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        info["world"] = WorldView.of(self.env)
        return obs, reward, terminated, truncated, info


def privileged_observation(env: gym.Env, target: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """What ``obs_mode="privileged"`` observes, for an env in any obs mode; with ``target`` (a world-frame waypoint)
    the robot state, the sub-goal and the path lead there instead of to the goal."""
    u = env.unwrapped
    return {"state": u.robot_state(target), "odom": u.robot.astype(np.float32), "peds": u.privileged_peds(),
            "scan": u.static_scan().astype(np.float32), "subgoal": u.privileged_subgoal(target),
            "path": u.privileged_path(target)}


class PrivilegedObservation(gym.Wrapper):
    """Adds the privileged channels (:func:`privileged_observation`, toward ``info["waypoint"]`` when an inner
    :class:`FollowWaypoints` set one) to every observation; a no-op under ``obs_mode="privileged"``."""

    def _add(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> dict[str, np.ndarray]:
        if self.env.unwrapped.cfg.obs_mode == "privileged":
            return obs
        return {**obs, **privileged_observation(self.env, info.get("waypoint"))}

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        return self._add(obs, info), info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._add(obs, info), reward, terminated, truncated, info


class FollowWaypoints(gym.Wrapper):
    """Heads the observation for the current waypoint of ``waypoints`` (``M x 2``, world frame, the last = the
    goal), tracked by a :class:`sim.planners.topomap.WaypointFollower` on the episode's layout. Without
    ``waypoints``, each episode follows the global planner's route from its start to its goal
    (:func:`sim.planners.global_path.route_waypoints`)."""

    def __init__(self, env: gym.Env, waypoints: np.ndarray | None = None) -> None:
        super().__init__(env)
        self.fixed = None if waypoints is None else np.asarray(waypoints, np.float64)
        self.waypoints = self.fixed
        self.follower: WaypointFollower | None = None

    def _retarget(self, obs: dict[str, np.ndarray], info: dict[str, Any]):
        u = self.env.unwrapped
        wp = self.follower.current(u.robot[:2])
        info["waypoint"] = wp
        obs = dict(obs)
        if u.cfg.obs_mode == "privileged":
            obs.update(privileged_observation(self.env, wp))
        obs["state"] = u.robot_state(wp)
        return obs, info

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        u = self.env.unwrapped
        if self.fixed is None:
            self.waypoints = route_waypoints(u.layout, u.start, u.goal, u.cfg.robot.radius_m)
        self.follower = WaypointFollower(self.waypoints, layout=u.layout)
        return self._retarget(obs, info)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        obs, info = self._retarget(obs, info)
        return obs, reward, terminated, truncated, info


def with_privileges(env: gym.Env, obs_mode: str) -> gym.Env:
    """``env`` as a method that observes ``obs_mode`` gets it: a privileged method (the expert, the teacher, the
    privileged baselines) sees the privileged observation channels and the true world; any other, nothing more."""
    if obs_mode == "privileged":
        return PrivilegedWorld(PrivilegedObservation(env))
    return env
