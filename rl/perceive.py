"""What a student's lookahead head perceives: pedestrian tracks from its detected poses and an obstacle scan from its
depth images — the student-side counterparts of the teacher's privileged ``peds`` and ``scan``.

The privileged teacher scores every action of the grid by rolling it forward against *true* pedestrian positions and
velocities and a range scan of the *static map* (:class:`rl.networks.LookaheadTeacherExtractor`). A student with
``net.head = "lookahead"`` gets the same kind of scorer, fed only with what a real robot measures:

* ``peds`` (``K x 6``, [x, y, vx, vy, r, present], robot frame, nearest first): each detected person
  (:mod:`sim.detector`: COCO-17 joints lifted with measured depth) becomes one point, the mean (x, y) of its detected
  joints moved 0.1 m further along the viewing ray (lifted joints lie on the surface that faces the cameras); :class:`PedestrianTracker` associates those points over frames in the odometry frame (greedy
  nearest neighbour within a gate) and runs an alpha–beta filter per track, whose velocity is the estimate (a new
  track starts at rest). A track that is not re-detected coasts at its velocity for ``max_missed`` frames (a person
  leaving the 140° view beside the robot is not forgotten at once). ``r`` is a nominal body radius.
* ``scan`` (``R`` ranges over 360° from the robot heading, ``range_m`` = no hit): :class:`DepthScan` back-projects
  the depth images (the DWA baseline's :func:`sim.planners.dwa.depth_to_points`, floor and ceiling dropped), drops the
  points within ``person_clear_m`` of a detected person (people are in ``peds``, with a velocity), keeps the rest in an
  odometry-frame :class:`sim.planners.dwa.ObstacleMemory` for ``memory_s`` = 5 s (what the cameras turned away from,
  and what is now closer than their minimum depth), and
  takes the nearest point per bearing bin — the same ray layout as the env's static scan, so one lookahead layer
  serves both. Undetected people stay in the scan as obstacles without velocity.

Nothing here is learned or privileged; the numbers are checked against the simulator's truth in
``tests/rl/test_perceive.py`` and measured in docs/results.md ("The students' perception").
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sim.depth import ObstacleMemory, depth_to_points
from sim.geometry import robot_to_world, world_to_robot

SURFACE_TO_CENTRE_M = 0.1  # detected joints → body centre, along the viewing ray
PED_RADIUS_M = 0.25  # nominal body radius of a perceived person (the simulator's bodies: 0.2-0.3 m)


@dataclass
class CameraView:
    """The attributes of a camera that depth back-projection reads (:class:`sim.cameras.CameraSpec`'s names)."""

    name: str
    width_px: int
    height_px: int
    K: np.ndarray
    T_base_cam: np.ndarray
    min_depth_m: float

    @classmethod
    def of(cls, cam) -> CameraView:
        """From a :class:`pretrain.geometry.Camera` (the encoder's camera description)."""
        return cls(cam.name, int(cam.width), int(cam.height), np.asarray(cam.K, np.float64),
                   np.asarray(cam.T_base_cam, np.float64), float(cam.min_depth_m))


def person_centres(poses: np.ndarray, mask: np.ndarray, min_joints: int = 3) -> np.ndarray:
    """``M x 2`` robot-frame (x, y) of the detected people: the mean of each person's detected joints (persons with
    fewer than ``min_joints`` joints are dropped)."""
    m = np.asarray(mask, bool)
    n = m.sum(-1)
    keep = n >= min_joints
    if not keep.any():
        return np.zeros((0, 2))
    p = np.asarray(poses, np.float64)[keep, :, :2]
    w = m[keep][..., None]
    c = (p * w).sum(1) / n[keep][:, None]
    # lifted joints lie on the body's surface facing the cameras: the centre is about half a body depth behind them
    return c + SURFACE_TO_CENTRE_M * c / np.maximum(np.linalg.norm(c, axis=-1, keepdims=True), 1e-6)


class PedestrianTracker:
    """Alpha–beta tracks of detected people in the odometry frame (module docstring).

    Args:
        dt_s: time between updates (the control period).
        gate_m: a detection further than ``gate_m`` from every predicted track starts a new track.
        alpha, beta: the filter's position and velocity gains.
        max_missed: frames a track coasts without a detection before it is dropped.
        max_speed_mps: velocity estimates are clipped to this speed (people walk at ≤ 2 m/s).
    """

    def __init__(self, dt_s: float, gate_m: float = 0.8, alpha: float = 0.5, beta: float = 0.15,
                 max_missed: int = 5, max_speed_mps: float = 2.0) -> None:
        self.dt_s, self.gate_m, self.alpha, self.beta = float(dt_s), float(gate_m), float(alpha), float(beta)
        self.max_missed, self.max_speed = int(max_missed), float(max_speed_mps)
        self.reset()

    def reset(self) -> None:
        self.pos = np.zeros((0, 2))
        self.vel = np.zeros((0, 2))
        self.missed = np.zeros(0, np.int64)

    def update(self, detections_w: np.ndarray) -> None:
        """One frame: ``M x 2`` odometry-frame detections."""
        z = np.asarray(detections_w, np.float64).reshape(-1, 2)
        pred = self.pos + self.dt_s * self.vel
        n, m = len(pred), len(z)
        det_of = np.full(n, -1)
        used = np.zeros(m, bool)
        if n and m:
            d = np.linalg.norm(pred[:, None] - z[None], axis=-1)
            for flat in np.argsort(d, axis=None):  # greedy: the closest pairs first
                i, j = divmod(int(flat), m)
                if d[i, j] > self.gate_m:
                    break
                if det_of[i] < 0 and not used[j]:
                    det_of[i], used[j] = j, True
        hit = det_of >= 0
        r = np.zeros_like(pred)
        r[hit] = z[det_of[hit]] - pred[hit]
        pos = pred + self.alpha * r
        vel = self.vel + (self.beta / self.dt_s) * r
        speed = np.linalg.norm(vel, axis=-1, keepdims=True)
        vel *= np.minimum(1.0, self.max_speed / np.maximum(speed, 1e-9))
        missed = np.where(hit, 0, self.missed + 1)
        alive = missed <= self.max_missed
        new = z[~used]
        self.pos = np.concatenate([pos[alive], new])
        self.vel = np.concatenate([vel[alive], np.zeros_like(new)])
        self.missed = np.concatenate([missed[alive], np.zeros(len(new), np.int64)])

    def observation(self, robot_pose: Sequence[float], k: int, radius_m: float = PED_RADIUS_M) -> np.ndarray:
        """``k x 6`` [x, y, vx, vy, r, present] of the nearest tracks in the robot frame (the teacher's layout)."""
        out = np.zeros((k, 6), np.float32)
        if not len(self.pos):
            return out
        rel = world_to_robot(self.pos, robot_pose)
        vel = world_to_robot(self.vel, robot_pose, vectors=True)
        order = np.argsort(np.hypot(rel[:, 0], rel[:, 1]), kind="stable")[:k]
        n = len(order)
        out[:n, :2], out[:n, 2:4] = rel[order], vel[order]
        out[:n, 4], out[:n, 5] = radius_m, 1.0
        return out


class DepthScan:
    """A 360° range scan of the obstacles the depth images show, with an odometry-frame memory (module docstring).

    Args:
        cameras: the robot's cameras (:class:`CameraView` or :class:`sim.cameras.CameraSpec`).
        rays: bearing bins over 360° (ray k at heading + k·2π/rays, as the env's ``static_scan``).
        range_m: the reading of a bin without any point.
        min_height_m, max_height_m: the height band of obstacle points (floor and ceiling dropped).
        pixel_stride: every n-th depth pixel in both directions.
        memory_s, voxel_m: the obstacle memory (points older than ``memory_s`` are dropped; one per voxel).
            (5 s also covers an obstacle the robot stopped in front of, closer than the cameras' minimum depth; a
            rule that kept near points from expiring was measured worse: docs/notes/2026-11-depth-scan-keep-near.md.)
        person_clear_m: points this close (x, y) to a detected person's centre are not obstacles.
    """

    def __init__(self, cameras: Sequence, rays: int, range_m: float, min_height_m: float = 0.05,
                 max_height_m: float = 1.8, pixel_stride: int = 2, memory_s: float = 5.0, voxel_m: float = 0.1,
                 person_clear_m: float = 0.45, see_through_tol_m: float = 0.3) -> None:
        self.cameras = list(cameras)
        self.rays, self.range_m = int(rays), float(range_m)
        self.band = (float(min_height_m), float(max_height_m))
        self.stride = int(pixel_stride)
        self.memory = ObstacleMemory(memory_s, voxel_m)
        self.person_clear_m, self.tol_m = float(person_clear_m), float(see_through_tol_m)
        self.t_s = 0.0

    def reset(self) -> None:
        self.memory = ObstacleMemory(self.memory.memory_s, self.memory.voxel_m)
        self.t_s = 0.0

    def update(self, depths: Sequence[np.ndarray], robot_pose: Sequence[float], dt_s: float,
               people_xy: np.ndarray | None = None) -> np.ndarray:
        """One frame → ``rays`` ranges (m). ``people_xy``: ``M x 2`` robot-frame centres of detected people."""
        pts = np.concatenate([depth_to_points(d, c, self.stride) for d, c in zip(depths, self.cameras, strict=True)])
        pts = pts[(pts[:, 2] >= self.band[0]) & (pts[:, 2] <= self.band[1])]
        if people_xy is not None and len(people_xy) and len(pts):
            d = np.linalg.norm(pts[None, :, :2] - np.asarray(people_xy, np.float64)[:, None], axis=-1)
            pts = pts[d.min(0) > self.person_clear_m]
        keep = ~self.memory.seen_through(depths, self.cameras, robot_pose, self.tol_m)
        self.t_s += float(dt_s)
        self.memory.update(robot_to_world(pts, robot_pose), self.t_s, keep)
        base = world_to_robot(self.memory.xyz, robot_pose) if len(self.memory) else np.zeros((0, 3))
        return scan_from_points(base[:, :2], self.rays, self.range_m)


def scan_from_points(xy: np.ndarray, rays: int, range_m: float) -> np.ndarray:
    """The nearest of ``N x 2`` robot-frame points per bearing bin (``rays`` bins, bin k centred on k·2π/rays);
    ``range_m`` where a bin has none (float32)."""
    out = np.full(rays, range_m, np.float64)
    if len(xy):
        rng = np.hypot(xy[:, 0], xy[:, 1])
        k = np.rint(np.arctan2(xy[:, 1], xy[:, 0]) / (2 * np.pi / rays)).astype(np.int64) % rays
        np.minimum.at(out, k, np.minimum(rng, range_m))
    return out.astype(np.float32)


class Perception:
    """``peds`` and ``scan`` of a student's lookahead head from one visual observation per control step.

    Args:
        cameras: the robot's cameras, left then right (:class:`CameraView`).
        dt_s: the control period.
        k: tracks reported (the teacher's ``privileged_peds``).
        rays, range_m: the scan layout (the env's ``scan_rays`` / ``scan_range_m``).
        people: track detected people (False for a variant without poses: the people are then only depth obstacles).
    """

    def __init__(self, cameras: Sequence, dt_s: float, k: int, rays: int, range_m: float, people: bool = True) -> None:
        self.tracker = PedestrianTracker(dt_s)
        self.scan = DepthScan(cameras, rays, range_m)
        self.names = [c.name for c in cameras]
        self.dt_s, self.k, self.people = float(dt_s), int(k), bool(people)

    def reset(self) -> None:
        self.tracker.reset()
        self.scan.reset()

    def __call__(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        pose = np.asarray(obs["odom"], np.float64)
        depths = [np.asarray(obs[f"depth_{n}"]) for n in self.names]
        out: dict[str, np.ndarray] = {}
        centres = None
        if self.people:
            centres = person_centres(obs["poses"], obs["pose_mask"])
            self.tracker.update(robot_to_world(centres, pose))
            out["peds"] = self.tracker.observation(pose, self.k)
        out["scan"] = self.scan.update(depths, pose, self.dt_s, centres)
        return out
