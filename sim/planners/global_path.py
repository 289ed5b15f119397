"""The global path on the static map and a pure-pursuit sub-goal along it.

What a robot with a map and a global planner knows about the route: the any-angle shortest path from the robot to
the target on the occupancy grid inflated by the robot radius (:meth:`sim.scene._NavGraph.shortest_path`), and the
point ``lookahead_m`` ahead along it. Used by the privileged teacher's observation (``subgoal``), by DRL-VO (its
sub-goal input) and by anything else that follows a global plan.
"""

from __future__ import annotations

import numpy as np


class GlobalPath:
    """The global planner's path on the static map: the shortest path from the robot to the target on the
    occupancy grid inflated by the robot radius, and a pure-pursuit sub-goal ``lookahead_m`` along it. Replanned
    when the robot strays ``replan_m`` from the path (``reset`` for each new episode). Each target keeps its own
    path: a long-horizon run asks for the final goal's (the env's own observation) and the current waypoint's
    (:class:`sim.wrappers.FollowWaypoints`) every step, and one shared path replanned at each switch — a Dijkstra
    over the whole floor, ≈ 20 ms on the office floor — was 72 % of such a step (docs/results.md, Performance)."""

    KEEP = 8  # paths kept for other targets than the current one (a run's waypoints and its goal)

    def __init__(self, lookahead_m: float = 2.0, replan_m: float = 0.75) -> None:
        self.lookahead_m = lookahead_m
        self.replan_m = replan_m
        self.path: np.ndarray | None = None  # the current target's path
        self.target: np.ndarray | None = None
        self._kept: dict[tuple[float, float], tuple[np.ndarray, np.ndarray]] = {}  # other targets': key -> (target, path)

    def reset(self, env) -> None:
        self.nav = env.layout.nav(env.cfg.robot.radius_m + 0.05)
        self.layout = env.layout
        self.path = None
        self.target = None
        self._kept = {}

    def _plan(self, xy: np.ndarray, target: np.ndarray) -> None:
        try:
            path = np.asarray(self.nav.shortest_path(self.layout, xy, target), float).reshape(-1, 2)
        except (ValueError, IndexError):
            path = np.zeros((0, 2))
        if len(path) == 0 or not np.all(np.isfinite(path)):
            path = np.stack([xy, target])
        self.path = path
        self.target = np.asarray(target, float).copy()

    def _switch(self, xy: np.ndarray, target: np.ndarray) -> None:
        """Makes ``target``'s path the current one: kept from before, or planned from ``xy``."""
        if self.path is not None and self.target is not None:
            self._kept[_key(self.target)] = (self.target, self.path)
            while len(self._kept) > self.KEEP:
                self._kept.pop(next(iter(self._kept)))
        kept = self._kept.pop(_key(target), None)
        if kept is None:
            self._plan(xy, target)
        else:
            self.target, self.path = kept

    def subgoal(self, env, target: np.ndarray | None = None) -> np.ndarray:
        """The sub-goal (world frame) toward ``target`` (default: the env's goal)."""
        return self.ahead(env, [self.lookahead_m], target)[0]

    def ahead(self, env, distances, target: np.ndarray | None = None) -> np.ndarray:
        """World-frame points ``len(distances) x 2`` at the given distances (m, increasing) along the path from
        the point of the path closest to the robot (the target itself beyond the path's end)."""
        xy = np.asarray(env.robot[:2], float)
        target = np.asarray(env.goal if target is None else target, float)
        if self.path is None or self.target is None or np.hypot(*(self.target - target)) > 1e-6:
            self._switch(xy, target)
        seg_d = distance_to_polyline(xy, self.path)
        if seg_d[0] > self.replan_m:
            self._plan(xy, target)
            seg_d = distance_to_polyline(xy, self.path)
        # walk along the path from the closest point
        k = int(seg_d[1])
        p = self.path
        pos = seg_d[2]
        walked = 0.0
        out = np.repeat(p[-1:].astype(float), len(distances), 0)
        j = 0
        while k < len(p) - 1 and j < len(distances):
            step = float(np.hypot(*(p[k + 1] - pos)))
            while j < len(distances) and distances[j] - walked <= step:
                out[j] = pos + (p[k + 1] - pos) * ((distances[j] - walked) / max(step, 1e-9))
                j += 1
            walked += step
            pos = p[k + 1]
            k += 1
        return out


def _key(target: np.ndarray) -> tuple[float, float]:
    return (round(float(target[0]), 6), round(float(target[1]), 6))


def route_waypoints(layout, start: np.ndarray, goal: np.ndarray, robot_radius_m: float) -> np.ndarray:
    """The global planner's waypoints from ``start`` to ``goal`` (world frame, ``M x 2``, the last = the goal): the
    corners of the any-angle shortest path on the grid inflated by the robot radius + 5 cm, as :class:`GlobalPath`
    plans it. Raises ValueError when the goal cannot be reached."""
    path = np.asarray(layout.nav(robot_radius_m + 0.05).shortest_path(layout, np.asarray(start, float),
                                                                       np.asarray(goal, float)), float)
    if path.ndim != 2 or len(path) == 0 or not np.all(np.isfinite(path)):
        raise ValueError(f"no path from {np.round(start, 2).tolist()} to {np.round(goal, 2).tolist()}")
    wps = path[1:] if len(path) > 1 else path
    wps[-1] = np.asarray(goal, float)
    return wps


def distance_to_polyline(xy: np.ndarray, path: np.ndarray) -> tuple[float, int, np.ndarray]:
    """(distance, index of the closest segment's start, closest point) of ``xy`` to the polyline ``path``."""
    if len(path) == 1:
        return float(np.hypot(*(xy - path[0]))), 0, path[0].copy()
    a, b = path[:-1], path[1:]
    ab = b - a
    t = np.clip(((xy - a) * ab).sum(-1) / np.maximum((ab ** 2).sum(-1), 1e-12), 0.0, 1.0)
    q = a + t[:, None] * ab
    d = np.hypot(*(q - xy).T)
    k = int(np.argmin(d))
    return float(d[k]), k, q[k]
