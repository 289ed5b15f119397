"""Pedestrian tracks from detected poses: the perceived people a student (and the intention model) sees.

Each detected person (:mod:`sim.detector`: COCO-17 joints lifted with measured depth) becomes one point, the mean
(x, y) of its detected joints moved :data:`SURFACE_TO_CENTRE_M` further along the viewing ray (lifted joints lie on
the surface that faces the cameras). :class:`PedestrianTracker` associates those points over frames in the odometry
frame (greedy nearest neighbour within a gate) and runs an alpha–beta filter per track, whose velocity is the
estimate (a new track starts at rest). A track that is not re-detected coasts at its velocity for ``max_missed``
frames. Each track also keeps its last ``history`` filtered positions and which detection (if any) updated it in
the last frame, so a forecaster can read a track's past and the pose seen on it now (:mod:`pretrain.intention`).

Here, below ``pretrain`` and ``rl``, because both read it: the intention model is pretrained on tracks replayed from
a recorded dataset, and the student's perception (:mod:`rl.perceive`) runs the same tracker online — one definition
of what a "track" is for training and for deployment. Nothing here is learned or privileged.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from sim.geometry import world_to_robot

SURFACE_TO_CENTRE_M = 0.1  # detected joints → body centre, along the viewing ray
PED_RADIUS_M = 0.25  # nominal body radius of a perceived person (the simulator's bodies: 0.2-0.3 m)
MIN_JOINTS = 3  # a detection with fewer detected joints is not a person


def person_detections(poses: np.ndarray, mask: np.ndarray, min_joints: int = MIN_JOINTS
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The detected people of one frame: ``M x 2`` robot-frame (x, y) centres (the mean of each person's detected
    joints, moved behind the surface) and the ``M`` indices of those people in ``poses`` (persons with fewer than
    ``min_joints`` joints are dropped)."""
    m = np.asarray(mask, bool)
    n = m.sum(-1)
    idx = np.flatnonzero(n >= min_joints)
    if not len(idx):
        return np.zeros((0, 2)), idx
    p = np.asarray(poses, np.float64)[idx, :, :2]
    c = (p * m[idx][..., None]).sum(1) / n[idx][:, None]
    return c + SURFACE_TO_CENTRE_M * c / np.maximum(np.linalg.norm(c, axis=-1, keepdims=True), 1e-6), idx


def person_centres(poses: np.ndarray, mask: np.ndarray, min_joints: int = MIN_JOINTS) -> np.ndarray:
    """``M x 2`` robot-frame centres of the detected people (:func:`person_detections` without the indices)."""
    return person_detections(poses, mask, min_joints)[0]


class PedestrianTracker:
    """Alpha–beta tracks of detected people in the odometry frame (module docstring).

    State after each :meth:`update` (one row per live track): ``pos``, ``vel`` (odometry frame), ``missed`` (frames
    since the last detection), ``age`` (updates the track has lived through), ``ids`` (a number unique within the
    episode), ``det`` (the index into the last update's detections that updated the track, -1 when it coasted) and
    ``hist`` ``history x 2`` (its filtered positions, oldest first, ending with ``pos``; a young track repeats its
    first position).

    Args:
        dt_s: time between updates (the control period).
        gate_m: a detection further than ``gate_m`` from every predicted track starts a new track.
        alpha, beta: the filter's position and velocity gains.
        max_missed: frames a track coasts without a detection before it is dropped.
        max_unseen: frames a track coasts while :meth:`update` is told it could not have been detected (outside the
            cameras' view, or too near them for its joints to be in the images): a person who walks out of view
            beside the robot is still there, so their absence from the images is no evidence. ``None`` = as
            ``max_missed`` (no difference between the two). Once observable again, a track missed for more than
            ``max_missed`` frames is dropped.
        max_speed_mps: velocity estimates are clipped to this speed (people walk at ≤ 2 m/s).
        history: positions kept per track.
    """

    def __init__(self, dt_s: float, gate_m: float = 0.8, alpha: float = 0.5, beta: float = 0.15,
                 max_missed: int = 5, max_speed_mps: float = 2.0, history: int = 8,
                 max_unseen: int | None = None) -> None:
        self.dt_s, self.gate_m, self.alpha, self.beta = float(dt_s), float(gate_m), float(alpha), float(beta)
        self.max_missed, self.max_speed, self.history = int(max_missed), float(max_speed_mps), int(history)
        self.max_unseen = self.max_missed if max_unseen is None else int(max_unseen)
        self.reset()

    def reset(self) -> None:
        self.pos = np.zeros((0, 2))
        self.vel = np.zeros((0, 2))
        self.missed = np.zeros(0, np.int64)
        self.age = np.zeros(0, np.int64)
        self.ids = np.zeros(0, np.int64)
        self.det = np.zeros(0, np.int64)
        self.hist = np.zeros((0, self.history, 2))
        self._next_id = 0

    def predicted(self) -> np.ndarray:
        """``N x 2`` odometry-frame positions the live tracks are predicted at in the next frame."""
        return self.pos + self.dt_s * self.vel

    def update(self, detections_w: np.ndarray, observable: np.ndarray | None = None) -> None:
        """One frame: ``M x 2`` odometry-frame detections; ``observable``: per live track (the order of ``pos``),
        whether it could have been detected at its :meth:`predicted` position (None = all could)."""
        z = np.asarray(detections_w, np.float64).reshape(-1, 2)
        pred = self.predicted()
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
        if observable is not None:
            alive |= ~np.asarray(observable, bool) & (missed <= self.max_unseen)
        new_idx = np.flatnonzero(~used)
        new = z[new_idx]
        hist = np.concatenate([self.hist[alive, 1:], pos[alive, None]], 1)
        self.pos = np.concatenate([pos[alive], new])
        self.vel = np.concatenate([vel[alive], np.zeros_like(new)])
        self.missed = np.concatenate([missed[alive], np.zeros(len(new), np.int64)])
        self.age = np.concatenate([self.age[alive] + 1, np.ones(len(new), np.int64)])
        self.ids = np.concatenate([self.ids[alive], self._next_id + np.arange(len(new))])
        self._next_id += len(new)
        self.det = np.concatenate([det_of[alive], new_idx])
        self.hist = np.concatenate([hist, np.repeat(new[:, None], self.history, 1)])

    def nearest(self, robot_pose: Sequence[float], k: int) -> np.ndarray:
        """Indices of the (at most ``k``) tracks nearest to the robot, nearest first."""
        rel = world_to_robot(self.pos, robot_pose)
        return np.argsort(np.hypot(rel[:, 0], rel[:, 1]), kind="stable")[:k]

    def observation(self, robot_pose: Sequence[float], k: int, radius_m: float = PED_RADIUS_M,
                    order: np.ndarray | None = None) -> np.ndarray:
        """``k x 6`` [x, y, vx, vy, r, present] of the nearest tracks in the robot frame (the teacher's layout);
        ``order``: those tracks' :meth:`nearest` indices when the caller already has them."""
        out = np.zeros((k, 6), np.float32)
        if not len(self.pos):
            return out
        order = self.nearest(robot_pose, k) if order is None else order
        n = len(order)
        out[:n, :2] = world_to_robot(self.pos[order], robot_pose)
        out[:n, 2:4] = world_to_robot(self.vel[order], robot_pose, vectors=True)
        out[:n, 4], out[:n, 5] = radius_m, 1.0
        return out
