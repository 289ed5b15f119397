"""3D human pose detection from the robot's RGB-D cameras.

The paper runs YOLO-pose on each RGB image and lifts the 2D keypoints to 3D with the aligned depth image. Our
default :class:`OracleDetector` replaces only the 2D network: it projects the true COCO-17 keypoints into each
camera, keeps those inside the image and not hidden (a depth-buffer test: the rendered surface at that pixel
must not lie more than ``occlusion_tol_m`` in front of the joint — ``face_occlusion_tol_m`` for the nose and eyes,
so a face turned away is hidden by its own head), adds pixel noise, a confidence and random
misses, and then lifts the surviving 2D detections with the *measured* depth exactly like the paper's pipeline
(median of the valid depths in a 3 × 3 window, back-projected with the intrinsics, moved to the robot frame
with the extrinsics). The result is what the I²Former consumes: at most ``max_people`` people, nearest first,
zero-padded, with a joint mask.

A learned detector plugs in by implementing :class:`PoseDetector` (it may ignore ``privileged``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from pipeline.core.errors import ConfigError
from sim.cameras import CameraSpec, backproject, project, world_to_camera
from sim.humans import N_KEYPOINTS

FACE_JOINTS = (0, 1, 2)  # COCO-17 nose, left eye, right eye: on the head's front surface


@dataclass
class DetectorConfig:
    """Oracle detector parameters."""

    max_people: int = 6  # people kept, nearest first
    pixel_noise_px_at_640: float = 2.0  # keypoint pixel noise (std) at 640 px width, scaled with the width
    occlusion_tol_m: float = 0.25  # a joint is hidden if the depth image is this much nearer than the joint
    face_occlusion_tol_m: float = 0.1  # the same for the front-face joints (nose, eyes), which lie on the head's
    #   front surface: less than half a head's depth (2 × 0.062 × height ≈ 0.22 m), so a face turned away from the
    #   camera is hidden by the back of its own head (with 0.25 m, 67 % of such noses passed; measured in
    #   docs/notes/2026-11-intention-probe.md)
    min_joints: int = 4  # a person is detected when at least this many joints are
    conf_threshold: float = 0.3  # joints with a lower confidence are dropped
    miss_prob: float = 0.03  # probability that a visible joint is missed anyway

    def validate(self) -> None:
        if not 1 <= self.max_people <= 32:
            raise ConfigError(f"detector.max_people: expected 1..32, got {self.max_people}")
        if not 1 <= self.min_joints <= N_KEYPOINTS:
            raise ConfigError(f"detector.min_joints: expected 1..17, got {self.min_joints}")
        if self.pixel_noise_px_at_640 < 0 or self.occlusion_tol_m <= 0 or self.face_occlusion_tol_m <= 0:
            raise ConfigError("detector: pixel noise must be >= 0 and occlusion tolerances > 0, got "
                              f"{self.pixel_noise_px_at_640}, {self.occlusion_tol_m}, {self.face_occlusion_tol_m}")


@dataclass
class CameraFrame:
    """One camera's data for a step: spec, pose of the camera in the world and the base, images."""

    spec: CameraSpec
    T_world_cam: np.ndarray
    T_base_cam: np.ndarray
    rgb: np.ndarray
    depth: np.ndarray


@dataclass
class Detections:
    """Detected people in the robot (base) frame.

    Attributes:
        poses: ``K x 17 x 3`` float32 joint positions, m, zero where not detected.
        joint_mask: ``K x 17`` bool.
        confidence: ``K x 17`` float32 in [0, 1], zero where not detected.
        person_mask: ``K`` bool.
        track_id: ``K`` int, the true pedestrian index (oracle only; −1 for padding or unknown).
    """

    poses: np.ndarray
    joint_mask: np.ndarray
    confidence: np.ndarray
    person_mask: np.ndarray
    track_id: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @staticmethod
    def empty(k: int) -> Detections:
        return Detections(np.zeros((k, N_KEYPOINTS, 3), np.float32), np.zeros((k, N_KEYPOINTS), bool),
                          np.zeros((k, N_KEYPOINTS), np.float32), np.zeros(k, bool), np.full(k, -1, np.int64))


class PoseDetector(Protocol):
    """What the env needs from a pose detector."""

    def detect(self, frames: list[CameraFrame], privileged: dict[str, np.ndarray],
               rng: np.random.Generator) -> Detections: ...


class OracleDetector:
    """True keypoints, projected, occlusion-tested, noised, then lifted with measured depth (see module doc)."""

    def __init__(self, cfg: DetectorConfig):
        self.cfg = cfg

    def visible_2d(self, frame: CameraFrame, kp_world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Project ``N x 17 x 3`` world keypoints into one camera.

        Returns:
            ``(uv, z, visible)``: ``N x 17 x 2`` continuous pixels, ``N x 17`` camera depth (m) and ``N x 17``
            bool (inside the image, in the depth range, and not occluded according to the depth image).
        """
        spec = frame.spec
        pc = world_to_camera(kp_world, frame.T_world_cam)
        uv, z = project(pc, spec.K)
        inside = (z > spec.min_depth_m) & (z < spec.max_depth_m) & (uv[..., 0] >= 0) & (uv[..., 0] < spec.width_px) \
            & (uv[..., 1] >= 0) & (uv[..., 1] < spec.height_px)
        col = np.clip(uv[..., 0].astype(int), 0, spec.width_px - 1)
        row = np.clip(uv[..., 1].astype(int), 0, spec.height_px - 1)
        d = frame.depth[row, col]
        tol = np.full(N_KEYPOINTS, self.cfg.occlusion_tol_m)
        tol[list(FACE_JOINTS)] = self.cfg.face_occlusion_tol_m
        visible = inside & (d > 0) & (z - d < tol)
        return uv, z, visible

    def detect(self, frames: list[CameraFrame], privileged: dict[str, np.ndarray],
               rng: np.random.Generator) -> Detections:
        cfg = self.cfg
        kp = privileged["keypoints_world"]
        n = len(kp)
        k = cfg.max_people
        if n == 0:
            return Detections.empty(k)
        best_pts = np.zeros((n, N_KEYPOINTS, 3))
        best_ok = np.zeros((n, N_KEYPOINTS), bool)
        best_conf = np.zeros((n, N_KEYPOINTS))
        best_count = np.zeros(n, int)
        per_cam = []
        for fr in frames:
            spec = fr.spec
            uv, z, vis = self.visible_2d(fr, kp)
            sigma = cfg.pixel_noise_px_at_640 * spec.width_px / 640.0
            uvn = uv + rng.normal(0.0, sigma, uv.shape)
            conf = np.clip(1.0 - 0.045 * z + rng.normal(0.0, 0.05, z.shape), 0.0, 1.0)
            ok = vis & (conf >= cfg.conf_threshold) & (rng.random(z.shape) >= cfg.miss_prob)
            depth = _median_depth(fr.depth, uvn)
            ok &= depth > 0
            pts_c = backproject(uvn, depth, spec.K)
            pts_b = pts_c @ fr.T_base_cam[:3, :3].T + fr.T_base_cam[:3, 3]
            count = ok.sum(1)
            per_cam.append((pts_b, ok, conf, count))
        # the camera that sees a person best provides its joints; the other fills the gaps
        for pts_b, ok, conf, count in per_cam:
            better = count > best_count
            fill = ~best_ok & ok
            take = (better[:, None] & ok) | fill
            best_pts = np.where(take[..., None], pts_b, best_pts)
            best_conf = np.where(take, conf, best_conf)
            best_ok = best_ok | ok
            best_count = np.maximum(best_count, count)
        detected = best_ok.sum(1) >= cfg.min_joints
        idx = np.nonzero(detected)[0]
        if len(idx) == 0:
            return Detections.empty(k)
        dist = np.array([np.linalg.norm(best_pts[i][best_ok[i], :2].mean(0)) for i in idx])
        idx = idx[np.argsort(dist, kind="stable")][:k]
        out = Detections.empty(k)
        m = len(idx)
        out.poses[:m] = np.where(best_ok[idx][..., None], best_pts[idx], 0.0)
        out.joint_mask[:m] = best_ok[idx]
        out.confidence[:m] = np.where(best_ok[idx], best_conf[idx], 0.0)
        out.person_mask[:m] = True
        out.track_id[:m] = idx
        return out


def _median_depth(depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Median of the valid depths in the 3 × 3 window around each pixel of ``... x 2`` (0 if none valid)."""
    h, w = depth.shape
    col = np.floor(uv[..., 0]).astype(int)
    row = np.floor(uv[..., 1]).astype(int)
    offs = np.array([-1, 0, 1])
    rr = np.clip(row[..., None, None] + offs[:, None], 0, h - 1)
    cc = np.clip(col[..., None, None] + offs[None, :], 0, w - 1)
    win = depth[rr, cc].reshape(*row.shape, 9).astype(np.float64)
    win = np.where(win > 0, win, np.nan)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(win, axis=-1)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    return np.where(inside & np.isfinite(med), med, 0.0)
