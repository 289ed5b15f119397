"""The ``mlp_intention`` head's student network (rl.networks): which inputs each variant reads, and its I²Former over
tracks and the intention model's forecasts."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from pipeline.core.errors import ConfigError
from pretrain.i2former import I2FormerConfig
from rl.networks import ForecastI2Former, StudentExtractor, variant_keys
from rl.policy import N_ACTIONS, build_policy

K, S = 4, 11


def _space(keys):
    d = {"state": gym.spaces.Box(-1e4, 1e4, (5,), np.float32)}
    shapes = {"bev": (8, 30, 48), "occ": (1, 30, 48), "peds": (K, 6), "peds_future": (K, S, 2),
              "scan": (72,), "poses": (K, 17, 3), "pose_mask": (K, 17)}
    for k in keys:
        if k in shapes:
            d[k] = gym.spaces.Box(-1e4, 1e4, shapes[k], np.float32)
    return gym.spaces.Dict(d)


def _tracks(b=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    peds = torch.randn(b, K, 6, generator=g) * 2.0
    peds[..., 5] = torch.tensor([1.0, 1.0, 0.0, 1.0])
    future = peds[..., None, :2] + torch.randn(b, K, S, 2, generator=g)
    return peds, future, torch.randn(b, 5, generator=g)


def test_the_ablations_remove_exactly_the_named_inputs():
    """``mlp_intention``: full and no_bev read tracks and forecasts in place of raw poses; no_i2 reads neither (the
    same keys as the paper's ``mlp`` head); the BEV / occupancy choice is the paper's."""
    assert variant_keys("full", "mlp_intention") == ("bev", "peds", "peds_future", "state")
    assert variant_keys("no_bev", "mlp_intention") == ("occ", "peds", "peds_future", "state")
    assert variant_keys("no_i2", "mlp_intention") == variant_keys("no_i2", "mlp") == ("bev", "state")
    with pytest.raises(ConfigError, match="net.head"):
        variant_keys("full", "mlp_intent")


@pytest.mark.parametrize("variant", ["full", "no_i2", "no_bev"])
def test_mlp_intention_students_build_and_act(variant):
    space = _space(variant_keys(variant, "mlp_intention"))
    policy = build_policy("student", variant, space, {"bev_width": 8, "head": "mlp_intention"})
    ext = policy.features_extractor
    assert isinstance(ext, StudentExtractor)
    assert isinstance(getattr(ext, "i2former", None), ForecastI2Former) == (variant != "no_i2")
    obs = {k: torch.as_tensor(np.stack([s.sample() for _ in range(2)])) for k, s in space.spaces.items()}
    assert policy.get_distribution(obs).distribution.logits.shape == (2, N_ACTIONS)
    # the paper's head on the same space misses the poses it reads
    if variant != "no_i2":
        with pytest.raises(ConfigError, match="needs observation keys"):
            build_policy("student", variant, space, {"bev_width": 8, "head": "mlp"})


@torch.no_grad()
def test_the_forecast_i2former_reads_present_tracks_in_any_order_and_their_forecasts():
    torch.manual_seed(0)
    m = ForecastI2Former(I2FormerConfig(dim=16), S)
    m.eval()
    peds, future, state = _tracks()
    z = m(peds, future, state)
    assert z.shape == (3, 16) and torch.isfinite(z).all()
    perm = torch.tensor([3, 0, 2, 1])
    assert torch.allclose(m(peds[:, perm], future[:, perm], state), z, atol=1e-5)  # order-free
    # an absent track's numbers are never read
    junk_p, junk_f = peds.clone(), future.clone()
    junk_p[:, 2, :5] = 99.0
    junk_f[:, 2] = -99.0
    assert torch.allclose(m(junk_p, junk_f, state), z, atol=1e-5)
    # a present track's forecast is: a person predicted to turn changes the embedding
    turned = future.clone()
    turned[:, 0, 5:] += torch.tensor([0.0, 1.5])
    assert (m(peds, turned, state) - z).abs().max() > 1e-3
    # nobody tracked: the empty-crowd key gives a finite embedding
    nobody = peds.clone()
    nobody[..., 5] = 0.0
    assert torch.isfinite(m(nobody, future, state)).all()


@torch.no_grad()
def test_i2_dropout_zeroes_the_i2former_output_of_some_training_samples_only():
    """``net.i2_dropout``: in training mode each sample's I²Former output is either kept or zeroed (about the given
    share zeroed); in eval mode (acting, held-out losses) every sample keeps it. A bad value is a named error."""
    space = _space(variant_keys("full", "mlp_intention"))
    policy = build_policy("student", "full", space, {"bev_width": 8, "head": "mlp_intention", "i2_dropout": 0.5})
    ext = policy.features_extractor
    obs = {k: torch.as_tensor(np.stack([s.sample() for _ in range(200)])) for k, s in space.spaces.items()}
    ext.eval()
    kept = ext(obs)
    hook = ext.i2former.register_forward_hook(lambda m, i, out: torch.zeros_like(out))
    without = ext(obs)
    hook.remove()
    assert torch.equal(ext(obs), kept)
    ext.train()
    torch.manual_seed(0)
    z = ext(obs)
    is_kept = torch.isclose(z, kept, atol=1e-5).all(-1)
    is_dropped = torch.isclose(z, without, atol=1e-5).all(-1)
    assert bool((is_kept ^ is_dropped).all())
    assert 60 <= int(is_dropped.sum()) <= 140
    with pytest.raises(ConfigError, match="i2_dropout"):
        build_policy("student", "full", space, {"head": "mlp_intention", "i2_dropout": 1.0})
