"""Articulated kinematic human bodies: gait, intention-revealing head/torso turns, COCO-17 keypoints, primitives.

Every pedestrian has a skeleton driven by its social-force state:

* the pelvis (and legs) face the walking direction, smoothed (``body_yaw``);
* the head looks at where the pedestrian is heading in mind (:meth:`sim.crowd.Crowd.attention_xy`: the pending
  goal during a lead, so it turns 0.3–1.0 s before the feet do), rate-limited and at most ±75° from the torso;
* the torso turns half way between pelvis and head (at most ±40° from the pelvis);
* a walking gait whose phase advances with the distance walked (legs swing, knees flex, arms counter-swing,
  the pelvis bobs); its amplitude follows the speed, so a standing pedestrian takes a neutral standing pose.

Body frame: x forward, y left, z up; world frame: the scene's, z up from the floor, metres.

Keypoints follow the COCO-17 order of :data:`COCO_KEYPOINTS`. Each body is drawn from :data:`N_PRIMITIVES`
oriented boxes (boxes are the cheapest TinyRenderer primitive): torso, head, hair (at the back of the head, so
the facing direction shows in RGB), upper arms, forearms, thighs and shins.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.errors import ConfigError
from sim.geometry import wrap_angle

COCO_KEYPOINTS = (
    "nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder", "right_shoulder", "left_elbow",
    "right_elbow", "left_wrist", "right_wrist", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle",
    "right_ankle",
)
N_KEYPOINTS = 17
PRIMITIVES = ("torso", "head", "hair", "l_upper_arm", "r_upper_arm", "l_forearm", "r_forearm", "l_thigh",
              "r_thigh", "l_shin", "r_shin")
N_PRIMITIVES = len(PRIMITIVES)


@dataclass
class BodyConfig:
    """Body randomisation and animation limits."""

    height_m: tuple[float, float] = (1.55, 1.92)  # standing height range
    width_scale: tuple[float, float] = (0.9, 1.15)  # shoulder/hip width multiplier range
    head_rate_radps: float = 5.0  # max head yaw rate
    torso_rate_radps: float = 3.0  # max torso yaw rate
    body_rate_radps: float = 4.0  # max pelvis yaw rate
    head_limit_deg: float = 75.0  # head yaw relative to the torso
    torso_limit_deg: float = 40.0  # torso yaw relative to the pelvis

    def validate(self) -> None:
        for k in ("height_m", "width_scale"):
            lo, hi = getattr(self, k)
            if not 0 < lo <= hi:
                raise ConfigError(f"body.{k}: expected 0 < min <= max, got [{lo}, {hi}]")
        for k in ("head_rate_radps", "torso_rate_radps", "body_rate_radps", "head_limit_deg", "torso_limit_deg"):
            if not getattr(self, k) > 0:
                raise ConfigError(f"body.{k}: expected > 0, got {getattr(self, k)}")


SKIN = np.array([[0.96, 0.8, 0.69], [0.87, 0.67, 0.5], [0.66, 0.46, 0.33], [0.45, 0.3, 0.2], [0.95, 0.76, 0.6]])
HAIR = np.array([[0.1, 0.07, 0.05], [0.35, 0.22, 0.1], [0.75, 0.6, 0.3], [0.5, 0.5, 0.5], [0.2, 0.12, 0.08]])


class Bodies:
    """Shapes, colours and animation state of ``N`` human bodies (vectorised).

    Attributes:
        height, width: ``N`` standing height (m) and width multiplier.
        radius: ``N`` collision disc radius used by the crowd and metrics, m.
        colors: ``N x 11 x 3`` RGB per primitive.
        body_yaw, torso_yaw, head_yaw: ``N`` world-frame yaws, rad.
        phase: ``N`` gait phase, rad; ``amp``: ``N`` gait amplitude in [0, 1].
    """

    def __init__(self, cfg: BodyConfig, rng: np.random.Generator, n: int, yaw0: np.ndarray):
        self.cfg = cfg
        self.n = n
        self.height = rng.uniform(*cfg.height_m, n)
        self.width = rng.uniform(*cfg.width_scale, n)
        self.radius = np.maximum(0.2, 0.13 * self.height * self.width) + 0.02
        shirt = rng.uniform(0.05, 0.95, (n, 3))
        pants = rng.uniform(0.05, 0.6, (n, 3))
        skin = SKIN[rng.integers(len(SKIN), size=n)]
        hair = HAIR[rng.integers(len(HAIR), size=n)]
        cols = np.empty((n, N_PRIMITIVES, 3))
        cols[:, 0] = shirt
        cols[:, 1] = skin
        cols[:, 2] = hair
        cols[:, 3:5] = shirt[:, None]
        cols[:, 5:7] = skin[:, None]
        cols[:, 7:11] = pants[:, None]
        self.colors = cols
        self.body_yaw = np.asarray(yaw0, dtype=np.float64).copy()
        self.torso_yaw = self.body_yaw.copy()
        self.head_yaw = self.body_yaw.copy()
        self.phase = rng.uniform(0, 2 * np.pi, n)
        self.amp = np.zeros(n)

    # --------------------------------------------------------------------------------------------- animation
    def update(self, dt: float, pos: np.ndarray, vel: np.ndarray, attention_xy: np.ndarray,
               walked_m: np.ndarray) -> None:
        """Advance the animation by ``dt`` s.

        Args:
            pos, vel: ``N x 2`` positions (m) and velocities (m/s) after the step.
            attention_xy: ``N x 2`` where each pedestrian intends to go (pending goal during a lead).
            walked_m: ``N`` distance walked during the step, m (drives the gait phase).
        """
        c = self.cfg
        speed = np.hypot(vel[:, 0], vel[:, 1])
        moving = speed > 0.1
        vel_yaw = np.arctan2(vel[:, 1], vel[:, 0])
        self.body_yaw = _approach(self.body_yaw, np.where(moving, vel_yaw, self.body_yaw), c.body_rate_radps * dt)
        to = attention_xy - pos
        far = np.hypot(to[:, 0], to[:, 1]) > 0.3
        att_yaw = np.where(far, np.arctan2(to[:, 1], to[:, 0]), self.head_yaw)
        torso_target = self.body_yaw + np.clip(wrap_angle(att_yaw - self.body_yaw) * 0.5,
                                               -np.radians(c.torso_limit_deg), np.radians(c.torso_limit_deg))
        self.torso_yaw = _approach(self.torso_yaw, torso_target, c.torso_rate_radps * dt)
        lim = np.radians(c.head_limit_deg)
        head_target = self.torso_yaw + np.clip(wrap_angle(att_yaw - self.torso_yaw), -lim, lim)
        self.head_yaw = _approach(self.head_yaw, head_target, c.head_rate_radps * dt)
        # keep the head within its limit of the (possibly still turning) torso
        rel = np.clip(wrap_angle(self.head_yaw - self.torso_yaw), -lim, lim)
        self.head_yaw = wrap_angle(self.torso_yaw + rel)
        stride = 0.8 * self.height  # one gait cycle (two steps), m
        self.phase = (self.phase + 2 * np.pi * walked_m / stride) % (2 * np.pi)
        target_amp = np.clip(speed / 1.2, 0.0, 1.0)
        self.amp += np.clip(target_amp - self.amp, -3.0 * dt, 3.0 * dt)

    # --------------------------------------------------------------------------------------------- kinematics
    def skeleton(self, pos: np.ndarray) -> dict[str, np.ndarray]:
        """Joint positions in the world frame, each ``N x 3``; also the per-segment frames' forward axes."""
        n = self.n
        h = self.height[:, None]
        w = self.width[:, None]
        a = self.amp[:, None]
        ph = self.phase[:, None]
        up = np.array([0.0, 0.0, 1.0])
        fb, lb = _axes(self.body_yaw)
        ft, lt = _axes(self.torso_yaw)
        fh, lh = _axes(self.head_yaw)
        base = np.concatenate([pos, np.zeros((n, 1))], axis=1)
        bob = 0.012 * h * a * (1 - np.cos(2 * ph)) / 2
        pelvis = base + up * (0.53 * h - bob)
        hip_half = 0.095 * h * w
        thigh, shin = 0.245 * h, 0.246 * h
        j: dict[str, np.ndarray] = {}
        for side, sgn, off in (("left", 1.0, 0.0), ("right", -1.0, np.pi)):
            swing = np.sin(ph + off)
            th = 0.42 * a * swing  # hip flexion, forward positive
            kn = a * (0.12 + 0.55 * np.clip(np.sin(ph + off + 1.2), 0.0, None))  # knee flexion
            hip = pelvis + lb * (sgn * hip_half)
            knee = hip + thigh * (np.sin(th) * fb - np.cos(th) * up)
            ankle = knee + shin * (np.sin(th - kn) * fb - np.cos(th - kn) * up)
            j[f"{side}_hip"], j[f"{side}_knee"], j[f"{side}_ankle"] = hip, knee, ankle
        sh_c = base + up * (0.818 * h - bob)
        sh_half = 0.129 * h * w
        ua, fa = 0.186 * h, 0.146 * h
        for side, sgn, off in (("left", 1.0, np.pi), ("right", -1.0, 0.0)):
            swing = np.sin(ph + off)  # arms counter-swing the same-side leg
            sf = 0.35 * a * swing
            el = 0.25 + 0.25 * a
            sh = sh_c + lt * (sgn * sh_half)
            out = lt * (sgn * 0.06)
            elbow = sh + ua * (np.sin(sf) * ft - np.cos(sf) * up) + out * ua
            wrist = elbow + fa * (np.sin(sf + el) * ft - np.cos(sf + el) * up) + out * fa * 0.5
            j[f"{side}_shoulder"], j[f"{side}_elbow"], j[f"{side}_wrist"] = sh, elbow, wrist
        rh = 0.062 * h
        head_c = base + up * (h - 1.15 * rh - bob)
        j["head_center"] = head_c
        j["neck"] = base + up * (0.86 * h - bob)
        j["nose"] = head_c + fh * rh - up * (0.25 * rh)
        j["left_eye"] = head_c + fh * (0.85 * rh) + lh * (0.35 * rh) + up * (0.1 * rh)
        j["right_eye"] = head_c + fh * (0.85 * rh) - lh * (0.35 * rh) + up * (0.1 * rh)
        j["left_ear"] = head_c + lh * (0.95 * rh)
        j["right_ear"] = head_c - lh * (0.95 * rh)
        j["pelvis"] = pelvis
        j["_fb"], j["_lb"], j["_ft"], j["_lt"], j["_fh"], j["_lh"] = fb, lb, ft, lt, fh, lh
        j["_rh"] = rh
        return j

    def keypoints(self, pos: np.ndarray, skel: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """``N x 17 x 3`` COCO keypoints in the world frame, m."""
        s = skel if skel is not None else self.skeleton(pos)
        return np.stack([s[k] for k in COCO_KEYPOINTS], axis=1)

    def primitives(self, pos: np.ndarray, skel: dict[str, np.ndarray] | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Oriented boxes that draw the bodies.

        Returns:
            ``(center, quat, half_extents)``: ``N x 11 x 3`` world centres (m), ``N x 11 x 4`` quaternions
            (x, y, z, w) and ``N x 11 x 3`` half extents (m), in the order of :data:`PRIMITIVES`.
        """
        s = skel if skel is not None else self.skeleton(pos)
        n = self.n
        h = self.height
        w = self.width
        up = np.broadcast_to(np.array([0.0, 0.0, 1.0]), (n, 3))
        centers = np.empty((n, N_PRIMITIVES, 3))
        rots = np.empty((n, N_PRIMITIVES, 3, 3))
        half = np.empty((n, N_PRIMITIVES, 3))
        hip_c = (s["left_hip"] + s["right_hip"]) / 2
        sh_c = (s["left_shoulder"] + s["right_shoulder"]) / 2
        # torso: from slightly below the hips to the shoulders, facing the torso yaw
        bottom = hip_c - up * (0.04 * h)[:, None]
        centers[:, 0] = (bottom + sh_c) / 2
        rots[:, 0] = _frame(s["_ft"], sh_c - bottom)
        half[:, 0] = np.stack([0.065 * h * w, 0.14 * h * w, np.linalg.norm(sh_c - bottom, axis=1) / 2], -1)
        rh = s["_rh"][:, 0]
        centers[:, 1] = s["head_center"]
        rots[:, 1] = _frame(s["_fh"], up)
        half[:, 1] = np.stack([rh * 0.95, rh * 0.8, rh * 1.1], -1)
        # hair: a slab on the back and top of the head
        centers[:, 2] = s["head_center"] - s["_fh"] * (0.55 * rh)[:, None] + up * (0.35 * rh)[:, None]
        rots[:, 2] = rots[:, 1]
        half[:, 2] = np.stack([rh * 0.55, rh * 0.88, rh * 0.85], -1)
        limbs = (("left_shoulder", "left_elbow", 0.032, "_ft"), ("right_shoulder", "right_elbow", 0.032, "_ft"),
                 ("left_elbow", "left_wrist", 0.027, "_ft"), ("right_elbow", "right_wrist", 0.027, "_ft"),
                 ("left_hip", "left_knee", 0.045, "_fb"), ("right_hip", "right_knee", 0.045, "_fb"),
                 ("left_knee", "left_ankle", 0.035, "_fb"), ("right_knee", "right_ankle", 0.035, "_fb"))
        for k, (a_, b_, thick, fwd) in enumerate(limbs, start=3):
            a, b = s[a_], s[b_]
            centers[:, k] = (a + b) / 2
            rots[:, k] = _frame(s[fwd], b - a)
            t = thick * h * w
            half[:, k] = np.stack([t, t, np.linalg.norm(b - a, axis=1) / 2 + 0.5 * t], -1)
        return centers, _quat_from_matrix(rots), half


def _approach(cur: np.ndarray, target: np.ndarray, max_step: np.ndarray | float) -> np.ndarray:
    """Move angles toward targets by at most ``max_step`` rad (shortest way round)."""
    d = wrap_angle(target - cur)
    return wrap_angle(cur + np.clip(d, -max_step, max_step))


def _axes(yaw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Forward and left unit vectors (``N x 3``) of yaw angles."""
    c, s = np.cos(yaw), np.sin(yaw)
    z = np.zeros_like(yaw)
    return np.stack([c, s, z], -1), np.stack([-s, c, z], -1)


def _frame(forward: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """``N x 3 x 3`` rotation whose z column is ``axis`` and x column the part of ``forward`` orthogonal to it."""
    z = axis / np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-9)
    x = forward - (forward * z).sum(-1, keepdims=True) * z
    x /= np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-9)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def _quat_from_matrix(r: np.ndarray) -> np.ndarray:
    """``... x 3 x 3`` rotation matrices to ``... x 4`` quaternions (x, y, z, w), numerically safe branches."""
    m = r
    t = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    q = np.empty(m.shape[:-2] + (4,))
    c0 = t > 0
    s = np.sqrt(np.maximum(t + 1.0, 1e-12)) * 2
    q0 = np.stack([(m[..., 2, 1] - m[..., 1, 2]) / s, (m[..., 0, 2] - m[..., 2, 0]) / s,
                   (m[..., 1, 0] - m[..., 0, 1]) / s, 0.25 * s], -1)
    c1 = (m[..., 0, 0] > m[..., 1, 1]) & (m[..., 0, 0] > m[..., 2, 2])
    s1 = np.sqrt(np.maximum(1.0 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], 1e-12)) * 2
    q1 = np.stack([0.25 * s1, (m[..., 0, 1] + m[..., 1, 0]) / s1, (m[..., 0, 2] + m[..., 2, 0]) / s1,
                   (m[..., 2, 1] - m[..., 1, 2]) / s1], -1)
    c2 = m[..., 1, 1] > m[..., 2, 2]
    s2 = np.sqrt(np.maximum(1.0 + m[..., 1, 1] - m[..., 0, 0] - m[..., 2, 2], 1e-12)) * 2
    q2 = np.stack([(m[..., 0, 1] + m[..., 1, 0]) / s2, 0.25 * s2, (m[..., 1, 2] + m[..., 2, 1]) / s2,
                   (m[..., 0, 2] - m[..., 2, 0]) / s2], -1)
    s3 = np.sqrt(np.maximum(1.0 + m[..., 2, 2] - m[..., 0, 0] - m[..., 1, 1], 1e-12)) * 2
    q3 = np.stack([(m[..., 0, 2] + m[..., 2, 0]) / s3, (m[..., 1, 2] + m[..., 2, 1]) / s3, 0.25 * s3,
                   (m[..., 1, 0] - m[..., 0, 1]) / s3], -1)
    q = np.where(c0[..., None], q0, np.where(c1[..., None], q1, np.where(c2[..., None], q2, q3)))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)
