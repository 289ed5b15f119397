"""Tests of sim.humans: intention (head turns before the feet), gait, COCO-17 keypoints, body primitives."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sim.crowd import Crowd, CrowdConfig
from sim.humans import (
    COCO_KEYPOINTS,
    N_KEYPOINTS,
    N_PRIMITIVES,
    PRIMITIVES,
    Bodies,
    BodyConfig,
    _quat_from_matrix,
)
from sim.scene import load_scene

DT = 0.1
KP = {name: i for i, name in enumerate(COCO_KEYPOINTS)}


def step(crowd: Crowd, bodies: Bodies, dt: float = DT) -> None:
    """One env step: crowd first, then the bodies (as CrowdNavEnv.step does)."""
    prev = crowd.pos.copy()
    crowd.step(dt)
    bodies.update(dt, crowd.pos, crowd.vel, crowd.attention_xy(), np.linalg.norm(crowd.pos - prev, axis=1))


def walker_east(seed: int = 0) -> tuple[Crowd, Bodies]:
    """One pedestrian in open_crowd walking east at 1 m/s, no spontaneous decisions."""
    layout = load_scene("open_crowd").layout()
    rng = np.random.default_rng(seed)
    bodies = Bodies(BodyConfig(), rng, 1, np.zeros(1))
    crowd = Crowd(layout, CrowdConfig(turn_rate_hz=0.0, idle_prob=0.0), rng, 1, bodies.radius)
    crowd.pos[:] = [[2.0, 6.0]]
    crowd.v0[:] = 1.0
    crowd.vel[:] = [[1.0, 0.0]]
    crowd.goal[:] = [[10.5, 6.0]]
    crowd.pending[:] = crowd.goal
    crowd.lead[:] = 0.0
    for _ in range(5):  # settle into a steady walk
        step(crowd, bodies)
    return crowd, bodies


def turn_timing(lead_s: float) -> tuple[float, float]:
    """Times (s after the decision) at which head yaw and walking direction first pass 45 degrees (north-east)."""
    crowd, bodies = walker_east()
    assert abs(bodies.head_yaw[0]) < 0.05 and abs(math.atan2(crowd.vel[0, 1], crowd.vel[0, 0])) < 0.05
    target = crowd.pos[0] + [0.0, 4.0]  # 90 degrees to the left
    if lead_s > 0:  # what Crowd._behaviour does on a decision
        crowd.pending[0] = target
        crowd.lead[0] = lead_s
    else:  # no intention: the goal switches at once
        crowd.goal[0] = target
    t_head = t_vel = None
    for k in range(1, 40):
        step(crowd, bodies)
        t = k * DT
        if t_head is None and bodies.head_yaw[0] >= math.radians(45):
            t_head = t
        if t_vel is None and math.atan2(crowd.vel[0, 1], crowd.vel[0, 0]) >= math.radians(45):
            t_vel = t
    assert t_head is not None and t_vel is not None
    return t_head, t_vel


def test_head_yaw_leads_the_walking_direction():
    t_head, t_vel = turn_timing(0.6)
    assert 0.3 <= t_vel - t_head <= 1.5
    # the walking direction does not change before the lead has run out
    assert t_vel > 0.6


def test_the_lead_comes_from_the_announced_intention():
    with_intent = turn_timing(0.6)
    without = turn_timing(0.0)
    lead_with = with_intent[1] - with_intent[0]
    lead_without = without[1] - without[0]
    assert lead_with - lead_without == pytest.approx(0.6, abs=0.21)


def test_torso_turns_between_pelvis_and_head():
    crowd, bodies = walker_east()
    crowd.pending[0] = crowd.pos[0] + [0.0, 4.0]
    crowd.lead[0] = 1.0
    for _ in range(6):
        step(crowd, bodies)
    body, torso, head = bodies.body_yaw[0], bodies.torso_yaw[0], bodies.head_yaw[0]
    assert abs(body) < 0.1  # feet still walk east
    assert body < torso < head
    assert torso - body <= math.radians(40) + 1e-9
    assert head - torso <= math.radians(75) + 1e-9


def test_standing_pedestrian_takes_a_neutral_symmetric_pose():
    crowd, bodies = walker_east()
    assert bodies.amp[0] > 0.5  # walking
    crowd.mode[0] = 1  # IDLE
    crowd.idle_left[0] = 100.0
    crowd.goal[0] = crowd.pos[0]
    for _ in range(30):
        step(crowd, bodies)
    assert np.linalg.norm(crowd.vel[0]) < 0.05
    assert bodies.amp[0] < 0.05
    h = bodies.height[0]
    kp = bodies.keypoints(crowd.pos)[0]
    la, ra = kp[KP["left_ankle"]], kp[KP["right_ankle"]]
    assert la[2] == pytest.approx(ra[2], abs=0.01 * h)
    assert la[2] == pytest.approx(0.04 * h, abs=0.015 * h)
    assert kp[KP["left_knee"], 2] == pytest.approx(kp[KP["right_knee"], 2], abs=0.01 * h)
    assert kp[KP["left_wrist"], 2] == pytest.approx(kp[KP["right_wrist"], 2], abs=0.01 * h)
    # legs straight under the hips
    for side in ("left", "right"):
        hip, ankle = kp[KP[f"{side}_hip"]], kp[KP[f"{side}_ankle"]]
        assert np.linalg.norm((ankle - hip)[:2]) < 0.05 * h


def test_keypoint_count_and_heights():
    rng = np.random.default_rng(1)
    n = 12
    bodies = Bodies(BodyConfig(), rng, n, rng.uniform(-np.pi, np.pi, n))
    pos = rng.uniform(0, 10, (n, 2))
    kp = bodies.keypoints(pos)
    assert len(COCO_KEYPOINTS) == N_KEYPOINTS == 17
    assert kp.shape == (n, 17, 3)
    h = bodies.height[:, None]
    cfg = BodyConfig()
    assert np.all((bodies.height >= cfg.height_m[0]) & (bodies.height <= cfg.height_m[1]))
    z = kp[..., 2] / h  # amp = 0 at creation: standing pose
    assert np.all(np.abs(z[:, KP["nose"]] - 0.93) < 0.03)
    assert np.all(np.abs(z[:, KP["left_eye"]] - 0.935) < 0.03)
    assert np.all(np.abs(z[:, KP["left_shoulder"]] - 0.818) < 0.03)
    assert np.all(np.abs(z[:, KP["left_hip"]] - 0.53) < 0.03)
    assert np.all(np.abs(z[:, KP["left_knee"]] - 0.285) < 0.03)
    assert np.all(np.abs(z[:, KP["left_ankle"]] - 0.04) < 0.015)
    # head above shoulders above hips above knees above ankles
    order = [KP["nose"], KP["left_shoulder"], KP["left_hip"], KP["left_knee"], KP["left_ankle"]]
    assert np.all(np.diff(z[:, order], axis=1) < 0)
    # all keypoints near the body's vertical axis
    assert np.all(np.linalg.norm(kp[..., :2] - pos[:, None], axis=-1) < 0.45 * h)


def test_left_is_left_and_the_face_looks_forward():
    bodies = Bodies(BodyConfig(), np.random.default_rng(2), 1, np.zeros(1))  # facing +x: left is +y
    kp = bodies.keypoints(np.array([[0.0, 0.0]]))[0]
    for part in ("eye", "ear", "shoulder", "elbow", "wrist", "hip", "knee", "ankle"):
        assert kp[KP[f"left_{part}"], 1] > kp[KP[f"right_{part}"], 1], part
    ears = (kp[KP["left_ear"]] + kp[KP["right_ear"]]) / 2
    assert kp[KP["nose"], 0] > ears[0] + 0.05
    # turn the head alone to face +y: the nose follows, the shoulders do not
    bodies.head_yaw[:] = np.pi / 2
    kp2 = bodies.keypoints(np.array([[0.0, 0.0]]))[0]
    ears2 = (kp2[KP["left_ear"]] + kp2[KP["right_ear"]]) / 2
    assert kp2[KP["nose"], 1] > ears2[1] + 0.05
    np.testing.assert_allclose(kp2[KP["left_shoulder"]], kp[KP["left_shoulder"]])


def walk(n_steps: int = 40, seed: int = 3):
    crowd, bodies = walker_east(seed)
    out = []
    for _ in range(n_steps):
        prev = crowd.pos.copy()
        ph = bodies.phase.copy()
        step(crowd, bodies)
        out.append((np.linalg.norm(crowd.pos - prev, axis=1)[0], ph[0], bodies.phase[0],
                    bodies.keypoints(crowd.pos)[0], crowd.pos[0].copy(), bodies.amp[0]))
    return bodies, out


def test_gait_phase_advances_with_distance_walked():
    bodies, out = walk()
    stride = 0.8 * bodies.height[0]
    for walked, before, after, *_ in out:
        expected = (before + 2 * np.pi * walked / stride) % (2 * np.pi)
        assert after == pytest.approx(expected, abs=1e-9)
    assert sum(o[0] for o in out) > 2.5
    assert out[-1][5] > 0.7  # amplitude follows the ~1 m/s speed


def test_gait_phase_does_not_advance_without_walking():
    bodies = Bodies(BodyConfig(), np.random.default_rng(0), 2, np.zeros(2))
    ph = bodies.phase.copy()
    pos = np.zeros((2, 2))
    bodies.update(DT, pos, np.zeros((2, 2)), pos + 5.0, np.zeros(2))
    np.testing.assert_array_equal(bodies.phase, ph)


def test_limb_lengths_are_constant_over_a_walk():
    bodies, out = walk(60)
    h = bodies.height[0]
    kps = np.array([o[3] for o in out])
    limbs = {("hip", "knee"): 0.245, ("knee", "ankle"): 0.246, ("shoulder", "elbow"): None,
             ("elbow", "wrist"): None}
    for (a, b), frac in limbs.items():
        for side in ("left", "right"):
            length = np.linalg.norm(kps[:, KP[f"{side}_{a}"]] - kps[:, KP[f"{side}_{b}"]], axis=-1)
            assert np.ptp(length) < 1e-9, (side, a, b)
            if frac is not None:
                assert length[0] == pytest.approx(frac * h, rel=1e-9)
        left = np.linalg.norm(kps[:, KP[f"left_{a}"]] - kps[:, KP[f"left_{b}"]], axis=-1)
        right = np.linalg.norm(kps[:, KP[f"right_{a}"]] - kps[:, KP[f"right_{b}"]], axis=-1)
        np.testing.assert_allclose(left, right, rtol=1e-9)
    # and the legs really swing: the ankle moves relative to the pelvis
    rel = kps[:, KP["left_ankle"]] - (kps[:, KP["left_hip"]] + kps[:, KP["right_hip"]]) / 2
    assert np.ptp(rel[:, 0]) > 0.2 * h


def test_arms_counter_swing_the_legs():
    bodies, out = walk(60)
    kps = np.array([o[3] for o in out])
    fwd = np.array([1.0, 0.0])  # walking east
    leg = (kps[:, KP["left_ankle"], :2] - kps[:, KP["left_hip"], :2]) @ fwd
    arm = (kps[:, KP["left_wrist"], :2] - kps[:, KP["left_shoulder"], :2]) @ fwd
    assert np.corrcoef(leg, arm)[0, 1] < -0.5


def test_primitives_follow_the_skeleton():
    rng = np.random.default_rng(4)
    n = 5
    bodies = Bodies(BodyConfig(), rng, n, rng.uniform(-np.pi, np.pi, n))
    bodies.amp[:] = 1.0
    bodies.head_yaw += 0.5
    pos = rng.uniform(0, 5, (n, 2))
    skel = bodies.skeleton(pos)
    centers, quats, half = bodies.primitives(pos, skel)
    assert centers.shape == (n, N_PRIMITIVES, 3) and quats.shape == (n, N_PRIMITIVES, 4)
    assert half.shape == (n, N_PRIMITIVES, 3) and len(PRIMITIVES) == N_PRIMITIVES == 11
    np.testing.assert_allclose(np.linalg.norm(quats, axis=-1), 1.0, atol=1e-9)
    assert np.all(half > 0)
    rot = Rotation.from_quat(quats.reshape(-1, 4)).as_matrix().reshape(n, N_PRIMITIVES, 3, 3)
    limbs = {"l_upper_arm": ("left_shoulder", "left_elbow"), "r_forearm": ("right_elbow", "right_wrist"),
             "l_thigh": ("left_hip", "left_knee"), "r_shin": ("right_knee", "right_ankle")}
    for prim, (a, b) in limbs.items():
        k = PRIMITIVES.index(prim)
        seg = skel[b] - skel[a]
        np.testing.assert_allclose(centers[:, k], (skel[a] + skel[b]) / 2, atol=1e-9)
        axis = rot[:, k, :, 2]  # the box's local z axis runs along the limb
        np.testing.assert_allclose(np.abs((axis * seg).sum(-1)), np.linalg.norm(seg, axis=-1), rtol=1e-6)
    # the head box faces the head yaw, the hair sits behind it
    k_head, k_hair = PRIMITIVES.index("head"), PRIMITIVES.index("hair")
    fwd = rot[:, k_head, :, 0]
    np.testing.assert_allclose(fwd[:, :2], np.stack([np.cos(bodies.head_yaw), np.sin(bodies.head_yaw)], -1),
                               atol=1e-6)
    assert np.all(((centers[:, k_hair] - centers[:, k_head]) * fwd).sum(-1) < 0)
    # the torso box spans hips to shoulders and faces the torso yaw
    k_torso = PRIMITIVES.index("torso")
    np.testing.assert_allclose(rot[:, k_torso, :2, 0], np.stack([np.cos(bodies.torso_yaw),
                                                                 np.sin(bodies.torso_yaw)], -1), atol=1e-6)
    hip_c = (skel["left_hip"] + skel["right_hip"]) / 2
    sh_c = (skel["left_shoulder"] + skel["right_shoulder"]) / 2
    assert np.all((centers[:, k_torso, 2] > hip_c[:, 2]) & (centers[:, k_torso, 2] < sh_c[:, 2]))


def test_quat_from_matrix_matches_scipy():
    mats = Rotation.random(200, random_state=7).as_matrix()
    # include the awkward branches: 180-degree turns about each axis
    mats = np.concatenate([mats, np.diag([1.0, -1.0, -1.0])[None], np.diag([-1.0, 1.0, -1.0])[None],
                           np.diag([-1.0, -1.0, 1.0])[None], np.eye(3)[None]])
    q = _quat_from_matrix(mats)
    ref = Rotation.from_matrix(mats).as_quat()
    dots = np.abs((q * ref).sum(-1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-9)


def test_body_randomisation_is_seeded_and_in_range():
    a = Bodies(BodyConfig(), np.random.default_rng(8), 20, np.zeros(20))
    b = Bodies(BodyConfig(), np.random.default_rng(8), 20, np.zeros(20))
    np.testing.assert_array_equal(a.height, b.height)
    np.testing.assert_array_equal(a.colors, b.colors)
    assert np.all((a.colors >= 0) & (a.colors <= 1))
    assert np.all((a.radius >= 0.22) & (a.radius < 0.35))
    assert np.ptp(a.height) > 0.1
