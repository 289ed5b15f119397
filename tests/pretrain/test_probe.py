"""Tests of the intention probe (pretrain.probe): sample geometry on synthetic episodes, turn events and their lead
time, the detected keypoints' frame change, and that the learned probes use a pose cue when the data has one."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.core.errors import InputMissingError
from pipeline.core.keys import (
    OBS_ODOM,
    OBS_POSE_MASK,
    OBS_POSES,
    PRIV_PED_KEYPOINTS,
    PRIV_PED_STATE,
    PRIV_POSE_TRACK,
)
from pretrain import probe
from pretrain.probe import ProbeConfig, Samples, episode_samples, errors

FPS = 10.0


def episode(xy: np.ndarray, head: np.ndarray | None = None, robot=(1.0, -2.0, 0.7)) -> dict[str, np.ndarray]:
    """One pedestrian walking along ``xy`` (T x 2), always detected as detection 0 with every joint at its feet
    (world z = 0.1 * joint index), seen from a robot standing at ``robot`` (x, y, yaw)."""
    t = len(xy)
    vel = np.gradient(xy, 1 / FPS, axis=0)
    state = np.zeros((t, 2, 8), np.float32)
    state[:, 0, :2], state[:, 0, 2:4], state[:, 0, 4] = xy, vel, 0.25
    state[:, 0, 5] = np.arctan2(vel[:, 1], vel[:, 0])
    state[:, 0, 6] = state[:, 0, 5] if head is None else head
    state[:, 0, 7] = 1.0
    z = 0.1 * np.arange(17)
    kp_world = np.concatenate([np.repeat(xy[:, None], 17, 1), np.broadcast_to(z[None, :, None], (t, 17, 1))], -1)
    rx, ry, ryaw = robot
    c, s = math.cos(ryaw), math.sin(ryaw)
    dx, dy = kp_world[..., 0] - rx, kp_world[..., 1] - ry
    kp_robot = np.stack([c * dx + s * dy, -s * dx + c * dy, kp_world[..., 2]], -1)
    track = np.full((t, 3), -1)
    track[:, 0] = 0
    return {OBS_ODOM: np.tile(np.array(robot, np.float32), (t, 1)), OBS_POSES: kp_robot[:, None].repeat(3, 1),
            OBS_POSE_MASK: np.ones((t, 3, 17), bool), PRIV_PED_STATE: state,
            PRIV_PED_KEYPOINTS: np.concatenate([kp_world[:, None], np.zeros_like(kp_world)[:, None]], 1),
            PRIV_POSE_TRACK: track}


def test_straight_walk_constant_velocity_is_exact_and_no_turn():
    xy = np.stack([np.linspace(0, 3.9, 40), 0.5 * np.linspace(0, 3.9, 40)], -1)  # 1.0 x 0.5 m/s
    s = episode_samples(episode(xy), FPS, 0)
    assert len(s) == 40 - 8 - 10  # history 0.8 s, horizon 1.0 s inside the episode
    speed = math.hypot(1.0, 0.5)
    np.testing.assert_allclose(s.speed, speed, rtol=1e-4)
    np.testing.assert_allclose(s.target[:, 0], [[0.5 * speed, 0.0]] * len(s), atol=1e-4)  # along x of its frame
    np.testing.assert_allclose(s.target[:, 1], [[1.0 * speed, 0.0]] * len(s), atol=1e-4)
    err = errors(probe.predict(None, s), s)
    assert err["all"]["fde_m"] < 1e-4 and err["turns"]["n"] == 0
    np.testing.assert_allclose(s.hist[:, -1], [[-0.1 * speed, 0.0]] * len(s), atol=1e-4)
    # the robot stands at (1, -2): the view angle is between the head's direction and the bearing to it
    bearing = np.arctan2(-2.0 - xy[8:-10, 1], 1.0 - xy[8:-10, 0])
    np.testing.assert_allclose(s.view, np.abs((math.atan2(0.5, 1.0) - bearing + np.pi) % (2 * np.pi) - np.pi),
                               atol=1e-4)


def test_detected_keypoints_are_moved_into_the_pedestrian_frame():
    xy = np.stack([np.linspace(0, 3.9, 40), np.full(40, 2.0)], -1)
    s = episode_samples(episode(xy), FPS, 0)
    # every joint sits at the person's position: (0, 0) in its own frame, z kept; detected equals true here
    np.testing.assert_allclose(s.kp_det[..., :2], 0.0, atol=1e-4)
    np.testing.assert_allclose(s.kp_det[0, :, 2], 0.1 * np.arange(17), atol=1e-5)
    np.testing.assert_allclose(s.kp_det, s.kp_true, atol=1e-4)


def test_a_right_angle_turn_is_a_turn_event_with_its_lead_time():
    # walk +x for 2 s, then +y: the direction crosses half the turn at the corner frame
    a = np.stack([np.arange(20) * 0.1, np.zeros(20)], -1)
    b = np.stack([np.full(20, 1.9), 0.1 * np.arange(1, 21)], -1)
    s = episode_samples(episode(np.concatenate([a, b])), FPS, 0)
    assert s.turn.any()
    t_of = np.arange(8, 8 + len(s))  # the prediction frames
    for t, turn, lead in zip(t_of, s.turn, s.lead_s, strict=True):
        if turn:
            assert 10 <= t + round(lead * FPS) <= 20  # the direction has turned by half near the corner
    assert (~s.turn[:2]).all() or s.lead_s[s.turn].max() <= 1.0


def cue_samples(n: int) -> Samples:
    """Synthetic samples whose future lateral step (left, straight, right) is announced only by one joint's
    position (and the head yaw); the past positions are the same straight walk for all three."""
    rng = np.random.default_rng(0)
    side = rng.choice([-1.0, 0.0, 1.0], n).astype(np.float32)
    speed = rng.uniform(0.8, 1.4, n).astype(np.float32)
    hist = -speed[:, None, None] * np.arange(8, 0, -1)[None, :, None] / FPS * np.array([1, 0], np.float32)
    target = np.stack([np.stack([speed * 0.5, side * 0.3], -1), np.stack([speed * 1.0, side * 0.8], -1)], 1)
    kp = rng.normal(0, 0.02, (n, 17, 3)).astype(np.float32)
    kp[:, 0, 1] += 0.3 * side  # the "nose" points where the person will go
    return Samples(hist.astype(np.float32), target.astype(np.float32), kp, np.ones((n, 17), bool), kp, speed,
                   (0.6 * side).astype(np.float32), side != 0,
                   np.where(side != 0, 0.5, np.nan).astype(np.float32), np.repeat(np.arange(30), n // 30),
                   np.zeros(n, np.float32))


@pytest.mark.slow
def test_learned_probes_use_a_pose_cue_when_the_data_has_one():
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small batches: one thread is faster
    try:
        s = cue_samples(900)
        cfg = ProbeConfig(epochs=12, dim=16, batch=32, seed=0)
        fde = {cue: errors(probe.predict(probe.train_probe(cue, s, cfg, 8), s), s)["turns"]["fde_m"]
               for cue in ("position", "pose_detected", "head_true")}
    finally:
        torch.set_num_threads(threads)
    cv = errors(probe.predict(None, s), s)["turns"]["fde_m"]
    assert cv > 0.7 and fde["position"] > 0.5  # nothing in the positions says which side
    assert fde["pose_detected"] < 0.2 * fde["position"] and fde["head_true"] < 0.2 * fde["position"], fde


def test_run_probe_writes_its_report(monkeypatch, tmp_path):
    monkeypatch.setattr(probe, "collect", lambda root: (cue_samples(300), FPS))
    cfg = ProbeConfig(dataset=tmp_path / "ds", out=tmp_path / "out", epochs=1, dim=8, seed=0)
    rep = probe.run_probe(cfg)
    assert set(rep["results"]) == set(probe.MODELS)
    assert rep["samples"]["train"] + rep["samples"]["val"] == 300 and rep["samples"]["val"] > 0
    for r in rep["results"].values():
        assert r["all"]["n"] == rep["samples"]["val"] and math.isfinite(r["all"]["fde_m"])
    assert {p.name for p in cfg.out.iterdir()} == {"probe.json", "probe.md", "probe.png"}
    assert "pose_detected" in (cfg.out / "probe.md").read_text()
    det = rep["detection"]  # detected = true keypoints here: no joint error, no head-yaw error
    assert det["joints_detected"] == 1.0 and det["joint_error_m_median"] == 0.0 and det["head_yaw_error_deg_p90"] == 0.0


def test_a_dataset_without_long_tracks_is_a_named_error(monkeypatch, tmp_path):
    xy = np.stack([np.linspace(0, 1, 12), np.zeros(12)], -1)  # 1.2 s: shorter than history + horizon
    monkeypatch.setattr(probe, "read_episodes", lambda root: [episode(xy)])
    (tmp_path / "meta").mkdir()
    (tmp_path / "meta" / "info.json").write_text('{"fps": 10, "features": {"action": {"info": {"icrowdnav_format": 2}}}}')
    with pytest.raises(InputMissingError, match="no tracked pedestrian"):
        probe.collect(tmp_path)
