"""What a student's lookahead head perceives: pedestrian tracks from its detected poses and an obstacle scan from its
depth images — the student-side counterparts of the teacher's privileged ``peds`` and ``scan``.

The privileged teacher scores every action of the grid by rolling it forward against *true* pedestrian positions and
velocities and a range scan of the *static map* (:class:`rl.networks.LookaheadTeacherExtractor`). A student with
``net.head = "lookahead"`` gets the same kind of scorer, fed only with what a real robot measures:

* ``peds`` (``K x 6``, [x, y, vx, vy, r, present], robot frame, nearest first): the tracks of
  :class:`sim.tracking.PedestrianTracker` over the detected people (each the centre of its detected joints; greedy
  nearest-neighbour association in the odometry frame, an alpha–beta filter whose velocity is the estimate, a
  coasting track kept for ``max_missed`` frames; with ``unseen_s`` a track that could not have been detected — its
  predicted centre outside the cameras' horizontal view, :data:`VIEW_MARGIN_DEG` inside its edge, or nearer than
  :data:`NEAR_M` to the robot, where a body's joints leave the images — coasts up to ``unseen_s``). ``r`` is a
  nominal body radius.
* ``scan`` (``R`` ranges over 360° from the robot heading, ``range_m`` = no hit): :class:`DepthScan` back-projects
  the depth images (the DWA baseline's :func:`sim.planners.dwa.depth_to_points`, floor and ceiling dropped), drops the
  points within ``person_clear_m`` of a detected person (people are in ``peds``, with a velocity), keeps the rest in an
  odometry-frame :class:`sim.planners.dwa.ObstacleMemory` for ``memory_s`` = 5 s (what the cameras turned away from,
  and what is now closer than their minimum depth), and
  takes the nearest point per bearing bin — the same ray layout as the env's static scan, so one lookahead layer
  serves both. Undetected people stay in the scan as obstacles without velocity.

* ``peds_future`` (``K x S x 2``, only with a pretrained intention model, :mod:`pretrain.intention`): where each
  reported track will be at the lookahead head's times, predicted from the track's history and the pose detected on
  it now — the model is trained on tracks of this very tracker replayed over a recorded dataset.

The MLP head with the intention model (``net.head = "mlp_intention"``, :class:`rl.networks.ForecastI2Former`) reads
``peds`` and ``peds_future`` alone (no ``scan``).

Apart from that frozen model, nothing here is learned or privileged; the numbers are checked against the simulator's truth in
``tests/rl/test_perceive.py`` and measured in docs/results.md ("The students' perception").
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.core.errors import ConfigError
from pretrain.intention import IntentionForecaster, from_track_frame, track_inputs
from rl.lookahead import lookahead_times
from sim.depth import ObstacleMemory, depth_to_points
from sim.geometry import robot_to_world, world_to_robot
from sim.tracking import PedestrianTracker, person_detections

VIEW_MARGIN_DEG = 5.0  # a track's centre this far inside the cameras' joint view edge counts as observable ...
NEAR_M = 1.0  # ... when it is at least this far from the robot's centre (nearer, the joints leave the images)


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


def camera_half_view(cam) -> float:
    """How far (rad) from the robot's heading a camera sees horizontally: |the yaw of its optical axis (OpenCV axes,
    z forward)| + half its horizontal field of view."""
    T = np.asarray(cam.T_base_cam, np.float64)
    fx = float(np.asarray(cam.K, np.float64)[0, 0])
    return abs(math.atan2(T[1, 2], T[0, 2])) + math.atan(0.5 * float(cam.width_px) / fx)


def scan_from_points(xy: np.ndarray, rays: int, range_m: float) -> np.ndarray:
    """The nearest of ``N x 2`` robot-frame points per bearing bin (``rays`` bins, bin k centred on k·2π/rays);
    ``range_m`` where a bin has none (float32)."""
    out = np.full(rays, range_m, np.float64)
    if len(xy):
        rng = np.hypot(xy[:, 0], xy[:, 1])
        k = np.rint(np.arctan2(xy[:, 1], xy[:, 0]) / (2 * np.pi / rays)).astype(np.int64) % rays
        np.minimum.at(out, k, np.minimum(rng, range_m))
    return out.astype(np.float32)


def interpolation_matrix(src_s: np.ndarray, dst_s: np.ndarray) -> np.ndarray:
    """``len(dst) x (len(src) + 1)`` weights that map values at times ``[0, *src_s]`` to times ``dst_s``: linear
    between neighbours, extrapolated along the last segment beyond the last time."""
    src = np.concatenate([[0.0], np.asarray(src_s, np.float64)])
    w = np.zeros((len(dst_s), len(src)))
    for i, t in enumerate(np.asarray(dst_s, np.float64)):
        j = int(np.clip(np.searchsorted(src, t) - 1, 0, len(src) - 2))
        a = (t - src[j]) / (src[j + 1] - src[j])
        w[i, j], w[i, j + 1] = 1.0 - a, a
    return w


class Perception:
    """``peds`` and ``scan`` of a student's lookahead head from one visual observation per control step, and with a
    ``forecaster`` also ``peds_future``.

    Args:
        cameras: the robot's cameras, left then right (:class:`CameraView`).
        dt_s: the control period.
        k: tracks reported (the teacher's ``privileged_peds``).
        rays, range_m: the scan layout (the env's ``scan_rays`` / ``scan_range_m``).
        people: track detected people (False for a variant without poses: the people are then only depth obstacles).
        unseen_s: how long a track that could not have been detected coasts (module docstring; 0 = as any missed
            track, ``max_missed`` frames).
        scan: measure the depth ``scan`` (False: tracks and forecasts only, for the ``mlp_intention`` head).
        forecaster: the pretrained intention model (:func:`pretrain.intention.load_forecaster`); each reported track
            is then predicted by it from its history and the pose detected on it now, and ``peds_future``
            (``k x S x 2``, robot frame, m) holds where it will be at the lookahead head's times
            (:func:`rl.lookahead.lookahead_times`; linear between the model's horizons). Without it the head
            extrapolates the tracks' velocities.
    """

    def __init__(self, cameras: Sequence, dt_s: float, k: int, rays: int, range_m: float, people: bool = True,
                 forecaster: IntentionForecaster | None = None, unseen_s: float = 0.0, scan: bool = True) -> None:
        self.forecaster = forecaster if people else None
        history = forecaster.cfg.history if self.forecaster is not None else 8
        if not (isinstance(unseen_s, int | float) and 0.0 <= unseen_s <= 10.0):
            raise ConfigError(f"perception unseen_s: expected 0 .. 10 s, got {unseen_s!r}")
        self.unseen = float(unseen_s) > 0.0
        self.tracker = PedestrianTracker(dt_s, history=history,
                                         max_unseen=int(round(unseen_s / dt_s)) if self.unseen else None)
        self.view_half = max(map(camera_half_view, cameras))
        self.scan = DepthScan(cameras, rays, range_m) if scan else None
        self.names = [c.name for c in cameras]
        self.dt_s, self.k, self.people = float(dt_s), int(k), bool(people)
        self.times = lookahead_times(dt_s).numpy()
        if self.forecaster is not None:
            self.interp = interpolation_matrix(np.asarray(self.forecaster.cfg.horizons_s), self.times)

    def reset(self) -> None:
        self.tracker.reset()
        if self.scan is not None:
            self.scan.reset()

    def __call__(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        pose = np.asarray(obs["odom"], np.float64)
        depths = [np.asarray(obs[f"depth_{n}"]) for n in self.names]
        out: dict[str, np.ndarray] = {}
        centres = None
        if self.people:
            centres, det_index = person_detections(obs["poses"], obs["pose_mask"])
            seen = self.observable(world_to_robot(self.tracker.predicted(), pose)) if self.unseen else None
            self.tracker.update(robot_to_world(centres, pose), seen)
            rows = self.tracker.nearest(pose, self.k)  # the reported tracks, nearest first (peds and peds_future)
            out["peds"] = self.tracker.observation(pose, self.k, order=rows)
            if self.forecaster is not None:
                out["peds_future"] = self.forecast(pose, obs["poses"], obs["pose_mask"], det_index, rows)
        if self.scan is not None:
            out["scan"] = self.scan.update(depths, pose, self.dt_s, centres)
        return out

    def observable(self, xy: np.ndarray) -> np.ndarray:
        """Whether a person centred at each of ``N x 2`` robot-frame points could be detected: its bearing at least
        :data:`VIEW_MARGIN_DEG` inside the cameras' joint horizontal view (their cones side by side, as the rig
        mounts them: the outer edge is the largest |axis yaw| + half field of view) and at least :data:`NEAR_M` from
        the robot."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        bearing = np.abs(np.arctan2(xy[:, 1], xy[:, 0]))
        return (bearing <= self.view_half - math.radians(VIEW_MARGIN_DEG)) & (np.hypot(xy[:, 0], xy[:, 1]) >= NEAR_M)

    @torch.no_grad()
    def forecast(self, pose: np.ndarray, poses: np.ndarray, mask: np.ndarray, det_index: np.ndarray,
                 rows: np.ndarray) -> np.ndarray:
        """``k x S x 2`` robot-frame positions of the reported tracks ``rows`` (the order of ``peds``) at the
        lookahead times, from the intention model; zero rows where there is no track."""
        out = np.zeros((self.k, len(self.times), 2), np.float32)
        if not len(rows):
            return out
        x, origin, heading = track_inputs(self.tracker, rows, pose, poses, mask, det_index)
        disp = self.forecaster({n: torch.from_numpy(v) for n, v in x.items()}).numpy().astype(np.float64)
        at = np.einsum("sj,njc->nsc", self.interp, np.concatenate([np.zeros((len(rows), 1, 2)), disp], 1))
        out[:len(rows)] = world_to_robot(from_track_frame(at, origin, heading), pose)
        return out
