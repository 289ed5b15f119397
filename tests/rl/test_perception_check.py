"""``rl.perception_check``'s contact agreement: the lookahead head's pedestrian-contact feature on perceived and on
true people, per action arc (the track and scan errors it also reports: tests/rl/test_perceive.py)."""

import numpy as np
import pytest

from rl.observe import observer_for_env
from rl.perception_check import contact_agreement, contact_head, contact_shares, evaluate_perception
from tests.rl.test_perceive import lobby  # noqa: F401 (fixture)


def test_contact_agreement_compares_the_same_feature_on_perceived_and_true_people(lobby):  # noqa: F811
    observer = observer_for_env(lobby, "no_bev", None, head="lookahead")
    head = contact_head(lobby, observer)
    obs = {k: np.zeros(s.shape, np.float32) for k, s in observer.observation_space.spaces.items()}
    obs["scan"][:] = lobby.cfg.scan_range_m  # no obstacle
    obs["state"][:3] = [5.0, 0.0, 5.0]  # the goal 5 m ahead, at rest
    person = np.array([[1.0, 0.0, 0.0, 0.0, 0.25, 1.0]], np.float32)  # standing 1 m ahead
    obs["peds"][:1] = person
    same = contact_agreement(head, obs, person)
    assert same.shape == (head.n_actions, 3)
    np.testing.assert_allclose(same[:, 0], same[:, 1], atol=1e-6)
    np.testing.assert_allclose(same[:, 2], same[:, 1], atol=1e-6)  # the person is in view (180° by default)
    assert (same[:, 1] > 0).any() and (same[:, 1] == 0).any()  # straight arcs run into them, sharp turns do not
    assert contact_shares(same) == pytest.approx({"contact_arcs_perceived": float((same[:, 1] > 0).mean()),
                                                  "contact_arcs_true": float((same[:, 1] > 0).mean()),
                                                  "contact_false_share": 0.0, "contact_missed_share": 0.0,
                                                  "contact_missed_share_in_view": 0.0})
    unseen = {**obs, "peds": np.zeros_like(obs["peds"])}  # the person is there, the tracks do not have them
    missed = contact_shares(contact_agreement(head, unseen, person))
    assert missed["contact_arcs_perceived"] == 0.0 and missed["contact_missed_share"] == 1.0
    ghost = contact_shares(contact_agreement(head, obs, np.zeros((1, 6), np.float32)))  # a track where nobody is
    assert ghost["contact_arcs_true"] == 0.0 and ghost["contact_false_share"] == 1.0
    beside = np.array([[0.0, 0.6, 0.0, 0.0, 0.25, 1.0]], np.float32)  # at 90°, outside a 60° view: missed, not "in view"
    c = contact_agreement(head, unseen, beside, view_deg=60.0)
    assert (c[:, 1] > 0).any() and not (c[:, 2] > 0).any()
    assert contact_shares(c)["contact_missed_share"] == 1.0 and contact_shares(c)["contact_missed_share_in_view"] == 0.0


def test_a_short_episode_reports_the_contact_shares_and_draws_the_arcs(tmp_path):
    out = evaluate_perception("office_lobby", 0.2, seed=0, steps=30, width_px=64, height_px=48,
                              figure=str(tmp_path / "p.png"), figure_step=20)
    assert out["people"] == "constant velocity" and out["frames"] >= 20
    for k in ("contact_arcs_perceived", "contact_arcs_true", "contact_false_share", "contact_missed_share",
              "contact_missed_share_in_view"):
        assert 0.0 <= out[k] <= 1.0
    assert (tmp_path / "p.png").stat().st_size > 0
