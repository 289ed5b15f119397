"""SARL*-OM's value network: finite without humans, invariant to their order and to padding."""

import math

import numpy as np
import pytest
import torch

from rl.baselines import sarl_om as S
from tests.rl.baselines.sarl_om.helpers import OC, make_scene


def test_value_is_finite_without_humans_and_permutation_invariant():
    torch.manual_seed(0)
    model = S.SarlOMValue(OC.om_sectors).eval()
    rng = np.random.default_rng(0)
    humans = np.c_[rng.uniform(-3, 3, (5, 2)), rng.uniform(-1, 1, (5, 2)), np.full(5, 0.25)]
    hits = rng.uniform(-3, 3, (40, 2))
    a = S.current_state(make_scene(humans=humans, hits=hits, speed=0.5), OC)
    b = S.current_state(make_scene(humans=humans[::-1], hits=hits, speed=0.5), OC)
    empty = S.current_state(make_scene(hits=hits), OC)
    with torch.no_grad():
        va, vb, ve = (model(*S.to_tensors(x)).item() for x in (a, b, empty))
    assert va == pytest.approx(vb, abs=1e-5)
    assert math.isfinite(ve)
    # padding: the network on the present humans only (the lookahead's shortcut) gives the same value
    short = {**a, "humans": a["humans"][:, :5], "mask": a["mask"][:, :5]}
    with torch.no_grad():
        assert model(*S.to_tensors(short)).item() == pytest.approx(va, abs=1e-5)
