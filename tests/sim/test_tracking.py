"""Pedestrian tracks from detected poses (sim.tracking): centres, association, alpha-beta filter, history."""

import numpy as np
import pytest

from sim.tracking import PED_RADIUS_M, PedestrianTracker, person_centres, person_detections


def test_person_centre_is_behind_the_lifted_joints():
    poses = np.zeros((2, 17, 3), np.float32)
    poses[0, :, 0], poses[0, :, 1] = 3.0, np.linspace(-0.2, 0.2, 17)
    mask = np.zeros((2, 17), np.uint8)
    mask[0] = 1
    mask[1, :2] = 1  # too few joints: not a person
    c = person_centres(poses, mask)
    assert c.shape == (1, 2)
    assert c[0] == pytest.approx([3.1, 0.0], abs=1e-6)


def test_tracker_estimates_a_constant_velocity_and_coasts():
    tr = PedestrianTracker(dt_s=0.1)
    rng = np.random.default_rng(0)
    v = np.array([0.8, -0.4])
    est = []
    for t in range(60):
        p = np.array([[1.0, 2.0]]) + v * 0.1 * t + rng.normal(0, 0.03, 2)
        far = np.array([[-5.0, 5.0]])  # a standing person
        tr.update(np.concatenate([p, far]) if t % 2 else np.concatenate([far, p]))  # order must not matter
        obs = tr.observation((0.0, 0.0, np.pi / 2), k=4)  # robot at the origin facing +y
        assert obs[:2, 5].tolist() == [1.0, 1.0] and obs[2:, 5].tolist() == [0.0, 0.0]
        walker = obs[np.argmin(np.hypot(obs[:2, 0] - (p[0, 1]), obs[:2, 1] + p[0, 0]))]
        if t >= 20:
            est.append(walker[2:4])
    # world velocity (0.8, -0.4) seen from a robot facing +y: x_r = world y, y_r = -world x
    assert np.mean(est, 0) == pytest.approx([-0.4, -0.8], abs=0.06)
    assert np.std(est, 0).max() < 0.25  # per-frame noise of the estimate (0.03 m position noise)
    assert walker[4] == PED_RADIUS_M
    n = len(tr.pos)
    for _ in range(tr.max_missed):  # nobody detected: the tracks coast
        tr.update(np.zeros((0, 2)))
    assert len(tr.pos) == n
    tr.update(np.zeros((0, 2)))
    assert len(tr.pos) == 0


def test_tracks_keep_their_history_ids_and_detection():
    tr = PedestrianTracker(dt_s=0.1, history=4)
    tr.update(np.array([[1.0, 0.0]]))
    assert tr.hist.shape == (1, 4, 2) and np.allclose(tr.hist[0], [1.0, 0.0])  # young: its first position repeated
    assert tr.age.tolist() == [1] and tr.det.tolist() == [0] and tr.ids.tolist() == [0]
    for t in range(1, 6):
        tr.update(np.array([[9.0, 9.0], [1.0 + 0.1 * t, 0.0]]))  # a second person appears; the walker is index 1
    walker = int(np.flatnonzero(tr.ids == 0)[0])
    assert tr.det[walker] == 1 and tr.age[walker] == 6
    assert np.allclose(tr.hist[walker, -1], tr.pos[walker])  # the history ends with the current position
    assert np.all(np.diff(tr.hist[walker, :, 0]) > 0)  # oldest first, walking +x
    other = int(np.flatnonzero(tr.ids == 1)[0])
    assert tr.det[other] == 0 and tr.age[other] == 5
    tr.update(np.zeros((0, 2)))  # nobody detected: both coast, no detection
    assert tr.det.tolist() == [-1, -1] and tr.missed.tolist() == [1, 1]


def test_person_detections_name_the_kept_people():
    poses = np.zeros((3, 17, 3), np.float32)
    poses[:, :, 0] = 2.0
    mask = np.zeros((3, 17), bool)
    mask[0, :2] = True  # too few joints
    mask[1:, :5] = True
    c, idx = person_detections(poses, mask)
    assert idx.tolist() == [1, 2] and c.shape == (2, 2)


def test_a_track_that_cannot_be_seen_coasts_until_max_unseen():
    """A person who walks out of the cameras' view is kept coasting up to ``max_unseen`` frames while the caller
    says he could not have been detected; a track that could have been and was not is dropped after ``max_missed``
    as before — also once it is observable again after coasting unseen."""
    def walker(max_unseen):
        tr = PedestrianTracker(dt_s=0.1, max_missed=5, max_unseen=max_unseen)
        for t in range(10):
            tr.update(np.array([[0.1 * t, 1.0]]))
        return tr

    tr = walker(20)
    for _ in range(20):  # out of view: coasting at its velocity
        tr.update(np.zeros((0, 2)), observable=np.zeros(len(tr.pos), bool))
    assert len(tr.pos) == 1 and tr.pos[0] == pytest.approx([0.9 + 0.1 * 20, 1.0], abs=0.05)
    tr.update(np.zeros((0, 2)), observable=np.zeros(1, bool))  # past max_unseen: gone
    assert len(tr.pos) == 0
    tr = walker(20)
    for _ in range(8):
        tr.update(np.zeros((0, 2)), observable=np.zeros(1, bool))
    tr.update(np.zeros((0, 2)), observable=np.ones(1, bool))  # back in view, not detected, missed 9 > 5: dropped
    assert len(tr.pos) == 0
    tr = walker(None)  # the default: no difference between unseen and missed
    for _ in range(6):
        tr.update(np.zeros((0, 2)), observable=np.zeros(len(tr.pos), bool))
    assert len(tr.pos) == 0
