"""The Dynamic Window Approach (Fox, Burgard & Thrun 1997) on the robot's own RGB-D depth and odometry.

What: the paper's model-based baseline (Table 1, "DWA"). It uses only what a real robot has: the depth images
of its two RGB-D cameras (intrinsics/extrinsics from :class:`sim.cameras.CameraSpec`), its odometry (pose and
velocity) and the goal or a waypoint. No pedestrian states, no map.

How, each control step (:meth:`DWAController.command`):

1. *Perception* (:func:`depth_to_points`): every ``pixel_stride``-th valid depth pixel (0 = invalid) is
   back-projected with the camera intrinsics into the camera frame and moved into the robot's base frame (x
   forward, y left, z up, origin on the floor under the robot centre) with ``T_base_cam``; points whose height
   is outside ``[min_height_m, max_height_m]`` (the floor, the ceiling) are dropped.
2. *Memory* (:class:`ObstacleMemory`): obstacle points are kept in the odometry (world) frame for ``memory_s``
   seconds on a voxel grid, so obstacles leaving the cameras' 140° view (beside the robot while it turns, or
   closer than the 0.3 m minimum depth) are not forgotten at once. A remembered point that a camera now sees
   *through* (valid depth clearly behind it at its pixel) is deleted at once, so pedestrians that walked away
   leave no ghost in view.
3. *Costmap* (:func:`build_costmap`, :func:`rasterise_costmap`): the points are rasterised into a
   robot-centred, robot-aligned grid (``costmap_size_m`` square, ``costmap_res_m`` cells); a Euclidean
   distance transform (``scipy.ndimage.distance_transform_edt``) gives each cell its distance to the nearest
   occupied cell, and the cells closer than the robot radius + ``safety_margin_m`` form the inflated obstacle
   region.
4. *Dynamic window*: ``n_v x n_omega`` velocities (v, ω) reachable within one control period from the current
   odometry velocity under ``acc_v_mps2`` / ``acc_omega_radps2``, clipped to the robot's limits
   (v ∈ [0, v_max], ω ∈ [−ω_max, ω_max]).
5. *Curvatures*: as in Fox et al., each (v, ω) is judged along its circle of curvature ω/v, sampled by arc
   length up to ``arc_length_m`` (not by time, so a slow arc still sees the obstacle it is heading for); the
   distance field is looked up bilinearly along all arcs at once. ``dist`` is the free arc length before the
   robot centre enters the inflated region.
6. *Admissibility*: the robot must be able to stop before that point: ``v·dt + v²/(2·acc_v_mps2) +
   obstacle_speed_mps·(dt + v/acc_v_mps2) <= dist`` (Fox et al.'s ``v <= sqrt(2·dist·v̇_b)`` plus one control
   period of reaction, plus the ground an obstacle walking towards the robot covers meanwhile). If nothing is
   admissible the robot brakes as hard as the window allows, steering to the arc with the longest free length.
7. *Objective* (Fox et al.'s three terms, each in [0, 1]): ``w_heading·heading + w_dist·dist +
   w_velocity·velocity`` with heading = 1 − |angle between the robot's heading and the bearing of the
   waypoint|/π, both taken at the pose reached by holding (v, ω) for ``heading_horizon_s``; dist = free arc
   length / ``min(dist_cap_m, distance to the waypoint)`` capped at 1 (the clearance along the arc; obstacles
   beyond the waypoint do not count); velocity = v / v_max.

Deviations from Fox et al. (1997), each found necessary on our scenes (office/hospital doorways, pillars,
crowds):

* heading is judged after ``heading_horizon_s`` of constant (v, ω), not after one period plus braking: the
  short look-ahead hardly separates the candidates, and the robot overshot every turn into a doorway;
* a turn on the spot (v = 0) has no curvature; its ``dist`` is that of the straight ray it would face after
  turning for ``spin_ray_s`` (Fox et al. give it "a large constant", which made stopping in front of a pillar
  the best choice forever; a short turn only looks at the same pillar, so the robot stayed stuck at its edge);
* ``obstacle_speed_mps`` (0 gives the original rule) makes admissibility hold against obstacles that approach
  — the world has walking people and the costmap has no velocities;
* scores are normalised by fixed ranges, not per step, and not smoothed over neighbouring velocities; near the
  final goal (not at intermediate waypoints) velocity rewards closeness to the speed from which the robot can
  still stop at the goal, ``min(v_max, sqrt(2·acc_v·d_goal))``, instead of plain speed.

Unseen space counts as free: the cameras look forward (±70°), and a disc robot that never reverses only needs
what lies ahead; the memory covers what it turns away from. There is no recovery behaviour: in a local minimum
(a wall between the robot and its waypoint) the robot stops or turns on the spot, as the classic method does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np
from scipy import ndimage

from pipeline.core.errors import ConfigError
from sim.cameras import CameraSpec
from sim.depth import ObstacleMemory, depth_to_points
from sim.geometry import robot_to_world, world_to_robot, wrap_angle


@dataclass
class DWAConfig:
    """Perception, dynamic window and objective of :class:`DWAController` (units in the names)."""

    # perception
    min_height_m: float = 0.05  # obstacle points lie above this height (the floor is excluded) ...
    max_height_m: float = 1.8  # ... and below this one (the robot passes under nothing higher anyway)
    pixel_stride: int = 2  # use every n-th depth pixel in both directions
    costmap_size_m: float = 8.0  # side of the robot-centred square costmap
    costmap_res_m: float = 0.1  # costmap cell size
    memory_s: float = 3.0  # obstacle points are remembered this long (odometry frame); 0 = current frame only
    memory_voxel_m: float = 0.1  # remembered points are thinned to one per voxel of this size
    see_through_tol_m: float = 0.25  # a remembered point is deleted if a camera sees this far behind it
    safety_margin_m: float = 0.15  # added to the robot radius when inflating (also absorbs the cell size)
    # dynamic window
    acc_v_mps2: float = 1.0  # linear acceleration and braking limit
    acc_omega_radps2: float = 4.0  # angular acceleration limit
    obstacle_speed_mps: float = 0.3  # admissibility holds against obstacles approaching this fast (0: Fox)
    n_v: int = 9  # sampled linear velocities in the window
    n_omega: int = 21  # sampled angular velocities in the window
    arc_length_m: float = 2.5  # each arc (constant curvature ω/v) is checked this far ahead
    arc_step_m: float = 0.05  # arc sampling step
    # objective (each term is normalised to [0, 1])
    w_heading: float = 1.0  # alignment with the waypoint at the pose reached after heading_horizon_s
    heading_horizon_s: float = 1.0  # how far ahead (holding v, ω) the heading to the waypoint is judged
    spin_ray_s: float = 4.0  # a turn on the spot (v = 0) is judged by the ray it faces after this long
    w_dist: float = 1.0  # free arc length before the inflated obstacles (Fox et al.'s dist), up to dist_cap_m
    dist_cap_m: float = 1.5  # free arc lengths above this score the same
    w_velocity: float = 0.5  # forward speed (near the final goal: closeness to the speed that stops there)

    def validate(self) -> None:
        """Check every field before any work.

        Raises:
            ConfigError: naming the field, the expected and the actual value.
        """
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ConfigError(f"dwa.{f.name}: expected a finite number, got {v!r}")
        positive = ("max_height_m", "costmap_size_m", "costmap_res_m", "memory_voxel_m", "see_through_tol_m",
                    "acc_v_mps2", "acc_omega_radps2", "heading_horizon_s", "spin_ray_s", "arc_length_m",
                    "arc_step_m", "dist_cap_m")
        for k in positive:
            if getattr(self, k) <= 0:
                raise ConfigError(f"dwa.{k}: expected > 0, got {getattr(self, k)}")
        for k in ("memory_s", "safety_margin_m", "obstacle_speed_mps", "w_heading", "w_dist", "w_velocity"):
            if getattr(self, k) < 0:
                raise ConfigError(f"dwa.{k}: expected >= 0, got {getattr(self, k)}")
        if not self.min_height_m < self.max_height_m:
            raise ConfigError(f"dwa.min_height_m: expected < max_height_m ({self.max_height_m}), got "
                              f"{self.min_height_m}")
        for k, lo in (("pixel_stride", 1), ("n_v", 2), ("n_omega", 3)):
            v = getattr(self, k)
            if not isinstance(v, int) or v < lo:
                raise ConfigError(f"dwa.{k}: expected an integer >= {lo}, got {v!r}")
        if self.costmap_size_m < 4 * self.costmap_res_m:
            raise ConfigError(f"dwa.costmap_size_m: expected >= 4 cells of costmap_res_m "
                              f"({self.costmap_res_m}), got {self.costmap_size_m}")
        if self.arc_step_m > self.arc_length_m:
            raise ConfigError(f"dwa.arc_step_m: expected <= arc_length_m ({self.arc_length_m}), got "
                              f"{self.arc_step_m}")
        if self.w_heading + self.w_dist + self.w_velocity <= 0:
            raise ConfigError("dwa.w_heading: expected the three weights to sum to > 0, got all zero")


# ---------------------------------------------------------------------------------------------------- costmap
@dataclass
class LocalCostmap:
    """A robot-centred, robot-aligned obstacle grid and its distance field.

    Cell ``[i, j]`` has its centre at base-frame ``(x, y) = origin + (j, i) * res_m`` (column along robot +x =
    forward, row along robot +y = left); the robot centre is the grid centre.

    Attributes:
        occupied: ``H x W`` bool, an obstacle point fell in the cell.
        distance_m: ``H x W`` distance from each cell centre to the nearest occupied cell centre, m (a large
            value where there is none).
        inflated: ``H x W`` bool, ``distance_m < inflation_m`` (the robot centre may not enter).
        origin: base-frame (x, y) of the centre of cell ``[0, 0]``, m.
        res_m: cell size, m.
        inflation_m: robot radius + safety margin, m.
        n_points: obstacle points rasterised (current frame plus memory).
    """

    occupied: np.ndarray
    distance_m: np.ndarray
    inflated: np.ndarray
    origin: tuple[float, float]
    res_m: float
    inflation_m: float
    n_points: int

    def lookup(self, xy: np.ndarray) -> np.ndarray:
        """Bilinear distance (m) at ``... x 2`` base-frame points; points outside the grid read ``size_m``."""
        p = np.asarray(xy, dtype=np.float64)
        h, w = self.distance_m.shape
        fx = (p[..., 0] - self.origin[0]) / self.res_m
        fy = (p[..., 1] - self.origin[1]) / self.res_m
        inside = (fx >= 0) & (fx <= w - 1) & (fy >= 0) & (fy <= h - 1)
        fx = np.clip(fx, 0.0, w - 1.000001)
        fy = np.clip(fy, 0.0, h - 1.000001)
        j, i = fx.astype(np.intp), fy.astype(np.intp)
        tx, ty = fx - j, fy - i
        d = self.distance_m
        val = (d[i, j] * (1 - tx) * (1 - ty) + d[i, j + 1] * tx * (1 - ty) + d[i + 1, j] * (1 - tx) * ty
               + d[i + 1, j + 1] * tx * ty)
        return np.where(inside, val, max(h, w) * self.res_m)


def rasterise_costmap(points_xy: np.ndarray, size_m: float, res_m: float, inflation_m: float) -> LocalCostmap:
    """Costmap of base-frame obstacle points (see :class:`LocalCostmap`).

    Args:
        points_xy: ``N x 2`` obstacle points, base frame, m (points outside the square are ignored).
        size_m: side of the square, m.
        res_m: cell size, m.
        inflation_m: robot radius + safety margin, m.
    """
    n = int(round(size_m / res_m))
    origin = (-(n - 1) / 2.0 * res_m, -(n - 1) / 2.0 * res_m)
    occ = np.zeros((n, n), dtype=bool)
    p = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    j = np.floor((p[:, 0] - origin[0]) / res_m + 0.5).astype(np.int64)
    i = np.floor((p[:, 1] - origin[1]) / res_m + 0.5).astype(np.int64)
    ok = (i >= 0) & (i < n) & (j >= 0) & (j < n)
    occ[i[ok], j[ok]] = True
    if occ.any():
        dist = ndimage.distance_transform_edt(~occ) * res_m
    else:
        dist = np.full((n, n), 2.0 * size_m)
    return LocalCostmap(occ, dist, dist < inflation_m, origin, res_m, inflation_m, int(ok.sum()))


def build_costmap(depths: Sequence[np.ndarray], cameras: Sequence[CameraSpec], robot_pose: Sequence[float],
                  cfg: DWAConfig, robot_radius_m: float,
                  memory_xyz: np.ndarray | None = None) -> LocalCostmap:
    """The local costmap from depth images, camera specs and the robot pose (a pure function).

    Args:
        depths: one ``H x W`` z-depth image (m, 0 = invalid) per camera.
        cameras: the matching :class:`CameraSpec` (intrinsics, base-from-camera extrinsics).
        robot_pose: ``[x, y, yaw]`` odometry pose (m, rad), used to bring ``memory_xyz`` into the base frame.
        cfg: height band, stride and grid of the costmap.
        robot_radius_m: inflation is this plus ``cfg.safety_margin_m``.
        memory_xyz: optional ``M x 3`` remembered obstacle points, odometry (world) frame, m.

    Returns:
        The :class:`LocalCostmap` (robot-centred, robot-aligned).
    """
    pts = [_band(depth_to_points(d, s, cfg.pixel_stride), cfg) for d, s in zip(depths, cameras, strict=True)]
    if memory_xyz is not None and len(memory_xyz):
        pts.append(world_to_robot(np.asarray(memory_xyz, dtype=np.float64), robot_pose))
    xy = np.concatenate([p[:, :2] for p in pts], axis=0) if pts else np.zeros((0, 2))
    return rasterise_costmap(xy, cfg.costmap_size_m, cfg.costmap_res_m, robot_radius_m + cfg.safety_margin_m)


def _band(points: np.ndarray, cfg: DWAConfig) -> np.ndarray:
    z = points[:, 2]
    return points[(z >= cfg.min_height_m) & (z <= cfg.max_height_m)]


# ------------------------------------------------------------------------------------------------- controller
class DWAController:
    """The Dynamic Window Approach on depth + odometry (see the module docstring).

    Usage (the same shape as :class:`sim.expert.PrivilegedExpert`)::

        dwa = DWAController()
        obs, info = env.reset(seed=0)
        dwa.reset(env.unwrapped)
        action = env.unwrapped.encode_command(*dwa.command(env.unwrapped))
        # with a visual observation pass its depth (no second rendering); with a topological map, a waypoint:
        v, w = dwa.command(env.unwrapped, waypoint_xy=follower.current(env.unwrapped.robot[:2]),
                           depths=(obs["depth_left"], obs["depth_right"]))

    What it reads from the env each step: ``env.robot`` (odometry pose [x, y, yaw]), ``env.robot_v`` (odometry
    velocity [v, ω]), and the depth images — ``depths`` if given, else ``env.render_cameras()``; at ``reset``:
    ``env.cameras`` (camera specs), ``env.cfg.robot`` (radius, limits), ``env.cfg.dt_s`` and ``env.goal``.

    Attributes:
        last_costmap: the costmap of the latest step (for figures and tests).
        last_debug: arrays of the latest step: candidate velocities, scores, admissibility, free arc lengths.
    """

    def __init__(self, cfg: DWAConfig | None = None):
        self.cfg = cfg or DWAConfig()
        self.cfg.validate()
        self.last_costmap: LocalCostmap | None = None
        self.last_debug: dict[str, np.ndarray] = {}
        self._ready = False

    def reset(self, env, goal_xy: Sequence[float] | None = None) -> None:
        """Start an episode (call after ``env.reset``): read the robot, cameras and goal; clear the memory.

        Args:
            env: the unwrapped :class:`sim.env.CrowdNavEnv`.
            goal_xy: the final goal, world frame, m; ``env.goal`` by default.
        """
        self.start(env.cameras, env.cfg.robot, env.cfg.dt_s, env.goal if goal_xy is None else goal_xy)

    def start(self, cameras: Sequence[CameraSpec], robot, dt_s: float, goal_xy: Sequence[float]) -> None:
        """Start an episode from what the env reports at reset (what :meth:`reset` reads from an env).

        Args:
            cameras: the camera specs (``info["cameras"]``).
            robot: the :class:`sim.robot.RobotConfig` (radius, limits).
            dt_s: the control period, s.
            goal_xy: the final goal, world frame, m.
        """
        self.radius_m = float(robot.radius_m)
        self.v_max = float(robot.v_max_mps)
        self.w_max = float(robot.omega_max_radps)
        self.dt = float(dt_s)
        self.cameras = tuple(cameras)
        self.goal = np.asarray(goal_xy, dtype=np.float64).reshape(2).copy()
        self.memory = ObstacleMemory(self.cfg.memory_s, self.cfg.memory_voxel_m)
        self.t_s = 0.0
        c = self.cfg
        k = max(1, int(math.ceil(c.arc_length_m / c.arc_step_m - 1e-9)))
        self.arc_s = np.linspace(0.0, c.arc_length_m, k + 1)[1:]  # S arc lengths
        self.last_costmap = None
        self._ready = True

    def command(self, env, waypoint_xy: Sequence[float] | None = None,
                depths: Sequence[np.ndarray] | None = None) -> tuple[float, float]:
        """The (v m/s, ω rad/s) to execute now.

        Args:
            env: the unwrapped env (odometry and, without ``depths``, rendering).
            waypoint_xy: the point to head for (world frame, m); the goal by default.
            depths: the current depth images, one per camera in ``env.cameras`` order (e.g.
                ``obs["depth_left"], obs["depth_right"]``); rendered with ``env.render_cameras()`` if omitted.
        """
        if not self._ready:
            raise RuntimeError("DWAController: call reset(env) after env.reset() and before command()")
        if depths is None:
            depths = [d for _, d, _ in env.render_cameras()]
        pose = np.asarray(env.robot, dtype=np.float64).reshape(3)
        v0, w0 = (float(x) for x in np.asarray(env.robot_v, dtype=np.float64).reshape(2))
        return self.command_from(depths, pose, v0, w0, waypoint_xy)

    def command_from(self, depths: Sequence[np.ndarray], pose: np.ndarray, v0: float, w0: float,
                     waypoint_xy: Sequence[float] | None = None) -> tuple[float, float]:
        """One DWA step from raw inputs (what :meth:`command` calls; needs no env after :meth:`reset`).

        Args:
            depths: one ``H x W`` z-depth image (m, 0 = invalid) per camera of :meth:`reset`'s env.
            pose: odometry pose ``[x, y, yaw]`` (m, rad).
            v0, w0: odometry velocity (m/s, rad/s), the centre of the dynamic window.
            waypoint_xy: the point to head for (world frame, m); the goal by default.

        Returns:
            ``(v, ω)`` in m/s and rad/s.
        """
        c = self.cfg
        # --- perception: current points (world frame), memory update, costmap
        now = np.concatenate([_band(depth_to_points(d, s, c.pixel_stride), c) for d, s in
                              zip(depths, self.cameras, strict=True)], axis=0)
        keep = ~self.memory.seen_through(depths, self.cameras, pose, c.see_through_tol_m)
        if c.memory_s > 0:
            self.memory.update(robot_to_world(now, pose), self.t_s, keep)
            mem = self.memory.xyz
            # only what can fall in the costmap
            near = np.hypot(mem[:, 0] - pose[0], mem[:, 1] - pose[1]) <= c.costmap_size_m * 0.75
            self.memory.xyz, self.memory.stamp = mem[near], self.memory.stamp[near]
            pts_xy = world_to_robot(self.memory.xyz, pose)[:, :2]
        else:
            pts_xy = now[:, :2]
        cm = rasterise_costmap(pts_xy, c.costmap_size_m, c.costmap_res_m, self.radius_m + c.safety_margin_m)
        self.last_costmap = cm
        self.t_s += self.dt

        # --- dynamic window
        v_lo, v_hi = max(0.0, v0 - c.acc_v_mps2 * self.dt), min(self.v_max, v0 + c.acc_v_mps2 * self.dt)
        if v_lo > v_hi:  # odometry beyond the limits: clamp the window
            v_lo = v_hi = min(max(v0, 0.0), self.v_max)
        w_lo = max(-self.w_max, w0 - c.acc_omega_radps2 * self.dt)
        w_hi = min(self.w_max, w0 + c.acc_omega_radps2 * self.dt)
        if w_lo > w_hi:
            w_lo = w_hi = float(np.clip(w0, -self.w_max, self.w_max))
        vs = np.linspace(v_lo, v_hi, c.n_v)
        ws = np.linspace(w_lo, w_hi, c.n_omega)
        if w_lo < 0.0 < w_hi:
            ws[np.argmin(np.abs(ws))] = 0.0  # keep driving straight possible
        vv, ww = np.meshgrid(vs, ws, indexing="ij")
        v = vv.ravel()[:, None]  # C x 1
        w = ww.ravel()[:, None]

        # --- arcs of constant curvature ω/v in the base frame, sampled by arc length (C x S). A turn on the
        # spot (v = 0) has no arc: it is scored by the straight ray in the direction it faces after spin_ray_s
        # (where it will drive next), so stopping in front of an obstacle does not look free
        s_arc = self.arc_s[None, :]
        moving = v > 1e-9
        kappa = np.where(moving, w / np.where(moving, v, 1.0), 0.0)
        straight = np.abs(kappa) < 1e-6
        ks = np.where(straight, 1.0, kappa)
        face = w * c.spin_ray_s
        arc_x = np.where(straight, s_arc, np.sin(kappa * s_arc) / ks)
        arc_y = np.where(straight, 0.0, (1.0 - np.cos(kappa * s_arc)) / ks)
        px = np.where(moving, arc_x, s_arc * np.cos(face))
        py = np.where(moving, arc_y, s_arc * np.sin(face))
        clear = cm.lookup(np.stack([px, py], -1)) - cm.inflation_m  # C x S, < 0 inside the inflated region
        c0 = float(cm.lookup(np.zeros(2))) - cm.inflation_m
        # already inside the inflated region (a pedestrian stepped close): arcs not going deeper are allowed
        hit = clear < min(0.0, c0) - 1e-6
        any_hit = hit.any(1)
        first = np.where(any_hit, hit.argmax(1), hit.shape[1])
        free_len = np.where(any_hit, np.concatenate([[0.0], self.arc_s])[first], np.inf)  # last free sample
        # stopping distance, plus the distance an obstacle moving towards the robot covers meanwhile
        vc = v[:, 0]
        t_stop = self.dt + vc / c.acc_v_mps2
        need = vc * self.dt + vc**2 / (2.0 * c.acc_v_mps2) + c.obstacle_speed_mps * t_stop * (vc > 0)
        admissible = need <= free_len + 1e-9

        # --- objective
        target = self.goal if waypoint_xy is None else np.asarray(waypoint_xy, dtype=np.float64).reshape(2)
        is_final = waypoint_xy is None or float(np.hypot(*(target - self.goal))) < 1e-6
        cy, sy = math.cos(pose[2]), math.sin(pose[2])
        d = target - pose[:2]
        tx, ty = cy * d[0] + sy * d[1], -sy * d[0] + cy * d[1]  # waypoint, base frame
        # pose after holding (v, ω) for heading_horizon_s
        t_h = c.heading_horizon_s
        th = w[:, 0] * t_h
        turning = np.abs(w[:, 0]) > 1e-6
        wsh = np.where(turning, w[:, 0], 1.0)
        hx = np.where(turning, v[:, 0] / wsh * np.sin(th), v[:, 0] * t_h)
        hy = np.where(turning, v[:, 0] / wsh * (1.0 - np.cos(th)), 0.0)
        err = np.abs(wrap_angle(np.arctan2(ty - hy, tx - hx) - th))
        heading = 1.0 - err / math.pi
        # obstacles beyond the waypoint do not matter: free up to it (or dist_cap_m) scores full
        cap = max(min(c.dist_cap_m, math.hypot(tx, ty)), c.arc_step_m)
        dist = np.minimum(free_len, cap) / cap
        if is_final:
            d_goal = math.hypot(tx, ty)
            v_ref = min(self.v_max, math.sqrt(2.0 * c.acc_v_mps2 * d_goal))
            velocity = 1.0 - np.abs(v[:, 0] - v_ref) / self.v_max
        else:
            velocity = v[:, 0] / self.v_max
        score = c.w_heading * heading + c.w_dist * dist + c.w_velocity * velocity

        if admissible.any():
            k = int(np.argmax(np.where(admissible, score, -np.inf)))
        else:  # brake as hard as the window allows, towards the longest free arc
            slow = v[:, 0] <= v_lo + 1e-9
            fl = np.where(np.isfinite(free_len), free_len, 1e9)
            k = int(np.argmax(np.where(slow, fl + 1e-3 * score, -np.inf)))
        self.last_debug = {"v": v[:, 0], "w": w[:, 0], "score": score, "admissible": admissible,
                           "free_len_m": free_len, "heading": heading, "dist": dist}
        return float(v[k, 0]), float(w[k, 0])


class DWADriver:
    """DWA as a :class:`sim.episode.Driver`: depth from ``obs``, odometry from ``info`` (``odom``, ``command``),
    the cameras, limits and goal from the reset ``info``, a long-horizon waypoint from ``info["waypoint"]``."""

    def __init__(self, cfg: DWAConfig | None = None) -> None:
        self.dwa = DWAController(cfg)
        self.codec = None

    def reset(self, obs: dict[str, np.ndarray], info: dict) -> None:
        self.codec = info["action_codec"]
        self.dwa.start(info["cameras"], self.codec.robot, info["config"].dt_s, info["goal_xy"])

    def act(self, obs: dict[str, np.ndarray], info: dict):
        depths = [obs[f"depth_{c.name}"] for c in self.dwa.cameras]
        v0, w0 = (float(x) for x in np.asarray(info["command"], dtype=np.float64).reshape(2))
        pose = np.asarray(info["odom"], dtype=np.float64).reshape(3)
        return self.codec.encode(*self.dwa.command_from(depths, pose, v0, w0, info.get("waypoint")))

    def bev_panel(self) -> np.ndarray | None:
        """The occupied cells of the latest costmap (videos), or None."""
        cm = self.dwa.last_costmap
        return None if cm is None else np.asarray(cm.occupied, np.float32)
