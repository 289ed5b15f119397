"""What the fitted map terms contribute per action (rl.map_check), on constructed maps."""

import pytest
import torch

from pipeline.core.errors import ConfigError
from rl.lookahead import N_LINEAR, N_MAP, SCORE_SCALE
from rl.map_check import PEOPLE, map_terms, step_stats
from tests.rl.test_perceive import STRAIGHT_FAST, _block, _map_head, _map_obs, lobby  # noqa: F401 (fixture)


def test_map_terms_are_the_fitted_weights_times_the_map_features(lobby):  # noqa: F811
    head = _map_head(lobby, 4)
    with torch.no_grad():
        head.map_cost.weight[:] = torch.tensor([[0.5, -1.0, -0.2, 2.0]])
    occ = _block(_block(torch.zeros(1, 4, 30, 48), 0, 1.2, 1.8, -0.4, 0.4), 3, 0.6, 1.4, -0.4, 0.4)
    feats = head.action_features(_map_obs(lobby, occ))
    terms = map_terms(head, feats)[0]
    x = feats[0, :, -N_LINEAR - N_MAP:-N_LINEAR]
    torch.testing.assert_close(terms, SCORE_SCALE * x * head.map_cost.weight[0])
    assert terms[STRAIGHT_FAST, 3] > 0  # the people-mean bonus on the arc through the predicted person
    # an action chosen by the people terms alone changes when they are dropped; one chosen by the rest does not
    logits = terms[:, PEOPLE].sum(-1).clone()
    assert step_stats(logits, terms, x[:, 3])["changed"]
    rest = torch.zeros(len(logits))
    rest[0] = 100.0
    assert not step_stats(rest + logits, terms, x[:, 3])["changed"]
    spread = step_stats(logits, terms, x[:, 3])["spread"]
    assert spread == pytest.approx((terms.amax(0) - terms.amin(0)).tolist())


def test_a_head_without_a_map_is_refused():
    class NoMap:
        n_map = 0

    with pytest.raises(ConfigError, match="no occupancy map"):
        map_terms(NoMap(), torch.zeros(1, 3, 40))
