"""The lookahead teacher: rollout features, the scored policy, the convex fit of its linear cost."""

import copy
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from pipeline.core.errors import ConfigError, CorruptArtifactError
from rl.lookahead import N_LINEAR, SHIELD_NATS_PER_M, ObstacleShield, unicycle_arcs
from rl.networks import LookaheadTeacherExtractor
from rl.policy import (
    POLICY_WEIGHTS,
    ScoredPolicy,
    build_policy,
    describe,
    load_policy,
    save_policy,
    upgrade_state_dict,
)
from rl.teacher import (
    _fit_nonpositive,
    behaviour_clone,
    collect_expert,
    extend_feature_cache,
    fit_lookahead_linear,
    lookahead_feature_cache,
    mirror_batch,
    teacher_net,
)
from sim.env import CrowdNavEnv, SimConfig
from sim.robot import action_grid, unicycle_step
from tests.rl.helpers_lookahead import HEAD_KEYS, pre_head_layout

SIM = SimConfig(max_episode_s=6.0)
N_ROT = 21


@pytest.fixture(scope="module")
def space():
    env = CrowdNavEnv(config=replace(SIM, scene="hallway", obs_mode="privileged", action_type="discrete"))
    return env.observation_space


def _policy(space, seed=0):
    torch.manual_seed(seed)
    return build_policy("teacher", None, space, teacher_net({"encoder": "lookahead"}, SIM))


def _obs(peds=(), scan_m=10.0, goal=(4.0, 0.0), path_dir=(1.0, 0.0)):
    """A robot-frame observation: pedestrians [x, y, vx, vy], a uniform scan, the goal and a straight path."""
    p = torch.zeros(1, 10, 6)
    for k, (x, y, vx, vy) in enumerate(peds):
        p[0, k] = torch.tensor([x, y, vx, vy, 0.25, 1.0])
    d = torch.tensor(path_dir) / torch.linalg.vector_norm(torch.tensor(path_dir))
    path = (0.25 * torch.arange(1, 13.0))[:, None] * d
    g = torch.tensor(goal)
    return {"state": torch.tensor([[g[0], g[1], float(torch.linalg.vector_norm(g)), 0.0, 0.0]]),
            "odom": torch.zeros(1, 3), "peds": p, "scan": torch.full((1, 72), scan_m),
            "subgoal": path[7][None], "path": path[None]}


def test_arcs_match_the_robot_kinematics():
    grid = torch.as_tensor(action_grid(SIM.robot), dtype=torch.float32)
    times = torch.tensor([0.1, 0.7, 2.0])
    xy, th = unicycle_arcs(grid, times)
    for a in (0, 10, 52, 60, 104):
        for s, t in enumerate(times.tolist()):
            x, y, yaw = unicycle_step(0.0, 0.0, 0.0, *grid[a].tolist(), t)
            assert xy[a, s].tolist() == pytest.approx([x, y], abs=1e-5)
            assert math.cos(float(th[a, s]) - yaw) == pytest.approx(1.0, abs=1e-5)


def test_features_see_a_pedestrian_ahead_and_reward_the_route(space):
    ext = _policy(space).features_extractor
    assert isinstance(ext, LookaheadTeacherExtractor)
    s = len(ext.lookahead.times)
    straight_fast, stop, straight_slow = 4 * N_ROT + N_ROT // 2, N_ROT // 2, 1 * N_ROT + N_ROT // 2
    f = ext.action_features(_obs(peds=[(1.5, 0.0, 0.0, 0.0)]))[0]
    # driving straight at 1 m/s into a standing person 1.5 m ahead: negative clearance, a predicted contact
    assert f[straight_fast, :s].min() < 0 and f[straight_fast, -N_LINEAR] > 0
    assert f[stop, :s].min() > 0.5 and f[stop, -N_LINEAR] == 0  # standing still touches nobody
    # without the person, going straight along the route gains ~2 m of cost-to-go, standing still nothing
    g = ext.action_features(_obs())[0]
    gain = g[:, -N_LINEAR + 4]
    assert float(gain[straight_fast]) == pytest.approx(2.0, abs=0.05) and float(gain[stop]) == pytest.approx(0.0, abs=1e-5)
    assert float(gain[straight_slow]) == pytest.approx(0.5, abs=0.05)
    # a wall 0.5 m ahead (every ray ends there): the fast straight arc predicts obstacle contact
    w = ext.action_features(_obs(scan_m=0.6))[0]
    assert w[straight_fast, -N_LINEAR + 2] > 0 and w[stop, -N_LINEAR + 2] == 0


def test_features_are_mirror_symmetric(space):
    """Reflecting the world about the robot's x axis maps action (v, ω) to (v, -ω) and keeps every clearance,
    intrusion and progress feature (the cloning cache relies on it)."""
    ext = _policy(space).features_extractor
    obs = _obs(peds=[(2.0, 0.7, -0.5, 0.2), (1.0, -1.2, 0.3, 0.6)], goal=(3.0, 1.5), path_dir=(1.0, 0.5))
    obs["scan"] = torch.linspace(1.0, 6.0, 72)[None]
    flip = torch.ones(1, dtype=torch.bool)
    mobs, _, _ = mirror_batch(obs, torch.zeros(1, dtype=torch.long), None, flip, N_ROT)
    f = ext.action_features(obs)[0].view(5, N_ROT, -1)
    m = ext.action_features(mobs)[0].view(5, N_ROT, -1).flip(1)
    s = len(ext.lookahead.times)
    sym = list(range(2 * s + 4)) + [f.shape[-1] - N_LINEAR + k for k in range(N_LINEAR)]
    np.testing.assert_allclose(f[..., sym].numpy(), m[..., sym].numpy(), atol=1e-4)


def test_scored_policy_round_trips_through_a_checkpoint(tmp_path, space):
    policy = _policy(space)
    assert isinstance(policy, ScoredPolicy)
    save_policy(tmp_path / "t", policy, describe("teacher", None, space, teacher_net({"encoder": "lookahead"}, SIM)))
    again, desc = load_policy(tmp_path / "t")
    obs = _obs(peds=[(1.5, 0.3, -0.2, 0.0)])
    with torch.no_grad():
        a = policy.get_distribution(obs).distribution.logits
        b = again.get_distribution(obs).distribution.logits
    assert isinstance(again, ScoredPolicy) and desc["net"]["encoder"] == "lookahead"
    assert torch.allclose(a, b)
    # saved in the head-module layout: its learned layers under the extractor's "lookahead." prefix, nothing else
    saved = set(load_file(str(tmp_path / "t" / POLICY_WEIGHTS)))
    assert saved == set(policy.state_dict()) and "features_extractor.lookahead.linear.weight" in saved
    assert upgrade_state_dict(dict.fromkeys(saved)).keys() == saved  # the current layout passes unchanged


def test_checkpoint_from_before_the_head_module_loads_into_the_same_policy(tmp_path, space):
    """A policy.safetensors written with the pre-module key names loads through load_policy (strict, as always) into
    the same logits and values; a checkpoint missing one of the head's weights is still refused."""
    policy = _policy(space, seed=3)
    assert set(policy.features_extractor.lookahead.state_dict()) == HEAD_KEYS
    ckpt = tmp_path / "old"
    save_policy(ckpt, policy, describe("teacher", None, space, teacher_net({"encoder": "lookahead"}, SIM)))
    old = pre_head_layout(policy.state_dict())
    assert upgrade_state_dict(old).keys() == policy.state_dict().keys()
    save_file(old, str(ckpt / POLICY_WEIGHTS))
    again, _ = load_policy(ckpt)
    obs = _obs(peds=[(1.5, 0.3, -0.2, 0.0), (2.5, -1.0, 0.0, 0.4)], scan_m=2.0)
    with torch.no_grad():
        for p in (policy, again):
            p.set_training_mode(False)
        assert torch.equal(again.get_distribution(obs).distribution.logits,
                           policy.get_distribution(obs).distribution.logits)
        assert torch.equal(again.predict_values(obs), policy.predict_values(obs))
    del old["features_extractor.linear.bias"]
    save_file(old, str(ckpt / POLICY_WEIGHTS))
    with pytest.raises(CorruptArtifactError, match="lookahead.linear.bias"):
        load_policy(ckpt)


def test_sign_constrained_fit_is_the_nonnegative_least_squares_solution():
    """``_fit_nonpositive`` (the map cost's ``map_signs: costs``) solves min |A w + c u - b|² with w <= 0 and u free
    exactly: scipy's NNLS on the same problem (v = -w >= 0, u eliminated by projection) gives the same w, and some
    of the unconstrained solution's entries were positive, so the constraint is active."""
    from scipy.optimize import nnls

    gen = torch.Generator().manual_seed(3)
    a = torch.randn(200, 6, generator=gen, dtype=torch.float64)
    c = torch.randn(200, 1, generator=gen, dtype=torch.float64)
    b = a @ torch.tensor([1.5, -2.0, 0.7, -0.3, 2.5, -1.0], dtype=torch.float64) + 0.8 * c[:, 0] \
        + 0.1 * torch.randn(200, generator=gen, dtype=torch.float64)
    free = torch.linalg.lstsq(torch.cat([a, c], 1), b).solution[:6]
    assert (free > 0).sum() >= 2
    w = torch.zeros(1, 6, dtype=torch.float64, requires_grad=True)
    u = torch.zeros(1, dtype=torch.float64, requires_grad=True)
    pinned = _fit_nonpositive([w, u], w, lambda: ((a @ w[0] + c[:, 0] * u - b) ** 2).mean())
    proj = torch.eye(200, dtype=torch.float64) - c @ c.T / (c.T @ c)  # removes the free column
    v, _ = nnls((-proj @ a).numpy(), (proj @ b).numpy())
    assert np.allclose(w.detach()[0].numpy(), -v, atol=1e-5)
    assert (w.detach() <= 0).all() and pinned == [int(i) for i in np.flatnonzero(v == 0)] and pinned
    assert w.grad is None and u.grad is None


def test_linear_fit_and_cloning_lower_the_cross_entropy(space):
    data = collect_expert(replace(SIM, max_episode_s=4.0), [("hallway", 0.1)], 2, 0, 0.99, 1, progress=False)
    policy = _policy(space)
    fit = fit_lookahead_linear(policy, data, 0.1)
    assert fit["frames"] == 2 * len(data["action"]) and fit["ce_after"] < 0.75 * fit["ce_before"]
    frozen = policy.features_extractor.lookahead.linear.weight.detach().clone()
    rows = behaviour_clone(policy, data, 2, 64, 1e-3, 0, progress=False, soft_tau=0.1, mirror=True,
                           frozen=("features_extractor.lookahead.linear.",))
    assert torch.equal(policy.features_extractor.lookahead.linear.weight, frozen)  # the fitted cost stays
    assert rows[-1]["bc_loss"] <= fit["ce_after"] + 0.3


def test_cloning_does_not_depend_on_gradients_left_on_frozen_weights(space):
    """The frozen linear cost gets no gradient while cloning and what an earlier fit or cloning left on it changes
    nothing: a policy whose frozen weights carry a stale gradient clones to the bytes of its fresh copy (the clipped
    norm is the updated weights' own), and keeps its frozen weights trainable afterwards."""
    data = collect_expert(replace(SIM, max_episode_s=4.0), [("hallway", 0.1)], 2, 0, 0.99, 1, progress=False)
    frozen = ("features_extractor.lookahead.linear.",)
    clone = {"progress": False, "soft_tau": 0.1, "mirror": True, "frozen": frozen}
    a = _policy(space)
    b = copy.deepcopy(a)  # no gradients (deepcopy drops them)
    for p in a.features_extractor.lookahead.linear.parameters():
        p.grad = torch.full_like(p, 1e3)
    rows_a = behaviour_clone(a, data, 2, 64, 1e-3, 0, **clone)
    rows_b = behaviour_clone(b, data, 2, 64, 1e-3, 0, **clone)
    assert rows_a == rows_b
    sa, sb = a.state_dict(), b.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert all(p.requires_grad and p.grad is None for p in a.features_extractor.lookahead.linear.parameters())


def test_a_feature_cache_extended_stage_by_stage_is_the_whole_aggregates(space):
    """The teacher's DAgger appends each stage's features to the aggregate's instead of recomputing them all:
    bit for bit what one pass over the aggregate gives, in chunks that fall anywhere (a run resumed mid-way starts
    from the aggregate's cache, then appends)."""
    data = collect_expert(replace(SIM, max_episode_s=4.0), [("hallway", 0.1)], 2, 0, 0.99, 1, progress=False)
    data = {k: v for k, v in data.items() if np.ndim(v)}  # the frames (not the run's success rate)
    policy = _policy(space)
    n = len(data["action"])
    cut = [0, n // 3, n // 3 + 5, n]  # three stages, the middle one short
    part = [{k: v[a:b] for k, v in data.items()} for a, b in zip(cut[:-1], cut[1:], strict=True)]
    whole = lookahead_feature_cache(policy, data, mirror=True, chunk=16)
    staged = None
    for p in part:
        staged = extend_feature_cache(staged, lookahead_feature_cache(policy, p, mirror=True, chunk=16))
    first_two = {k: v[:cut[2]] for k, v in data.items()}
    resumed = extend_feature_cache(lookahead_feature_cache(policy, first_two, mirror=True, chunk=16),
                                   lookahead_feature_cache(policy, part[2], mirror=True, chunk=16))
    for got in (staged, resumed):
        assert all(np.array_equal(a, b) for a, b in zip(got, whole, strict=True))
    with pytest.raises(ValueError, match="mirrored features"):
        extend_feature_cache(whole, lookahead_feature_cache(policy, part[2], mirror=False))


def test_ppo_rollout_feature_cache_changes_nothing_but_speed():
    """PPO's minibatches carry the rollout features computed once per rollout; the policy's evaluation of a batch
    is the same with and without them."""
    from stable_baselines3 import PPO

    from rl.policy import LOOKAHEAD_KEY, policy_class, policy_kwargs
    from rl.teacher import attach_lookahead_cache, make_vec_env

    torch.manual_seed(0)
    venv = make_vec_env(SIM, [("hallway", 0.1)], 2, 0, subprocess=False)
    net = teacher_net({"encoder": "lookahead"}, SIM)
    model = PPO(policy_class("teacher", net), venv, policy_kwargs=policy_kwargs("teacher", None, net), seed=0,
                device="cpu", n_steps=32, batch_size=32, n_epochs=1)
    attach_lookahead_cache(model)
    model.learn(64)
    batch = next(model.rollout_buffer.get(16))
    assert LOOKAHEAD_KEY in batch.observations
    plain = {k: v for k, v in batch.observations.items() if k != LOOKAHEAD_KEY}
    with torch.no_grad():
        cached = model.policy.evaluate_actions(batch.observations, batch.actions)
        fresh = model.policy.evaluate_actions(plain, batch.actions)
    for a, b in zip(cached, fresh, strict=True):
        assert torch.allclose(a, b, atol=1e-5)
    venv.close()


def test_best_heading_prefers_the_turn_towards_the_route(space):
    """Facing a wall with the route 40° to the right: every forward arc predicts contact and every turn on the spot
    stays put. The end-of-arc heading error (``heading: end``) prefers the 2 rad/s turn *away* from the route (4 rad
    to the right ends 171° off, 4 rad to the left 91° off); the best error along the arc (``heading: best``) is 0
    for the right turn, which passes through the route's direction, and the initial 40° for the left one."""
    from pipeline.core.errors import ConfigError

    a = math.radians(-40)
    obs = _obs(scan_m=0.33, goal=(3.0 * math.cos(a), 3.0 * math.sin(a)), path_dir=(math.cos(a), math.sin(a)))
    err = -N_LINEAR + 6  # the heading term of the linear cost
    spin_right, spin_left = 0, N_ROT - 1  # v = 0, ω = -2 / +2
    torch.manual_seed(0)
    best = build_policy("teacher", None, space, teacher_net({"encoder": "lookahead", "heading": "best"}, SIM))
    fb = best.features_extractor.action_features(obs)[0]
    fe = _policy(space).features_extractor.action_features(obs)[0]
    assert float(fb[spin_right, err]) == pytest.approx(0.0, abs=1e-6)
    assert float(fb[spin_left, err]) == pytest.approx(math.radians(40), abs=0.05)
    assert float(fe[spin_right, err]) > float(fe[spin_left, err]) + 1.0  # "end": the wrong way round
    assert float(fb[:N_ROT, err].min()) <= float(fe[:N_ROT, err].min())  # never worse than the end's error
    # "spin": the turns on the spot as "best", every moving arc as "end"
    spin = build_policy("teacher", None, space, teacher_net({"encoder": "lookahead", "heading": "spin"}, SIM))
    fs = spin.features_extractor.action_features(obs)[0]
    torch.testing.assert_close(fs[:N_ROT, err], fb[:N_ROT, err])
    torch.testing.assert_close(fs[N_ROT:, err], fe[N_ROT:, err])
    with pytest.raises(ConfigError, match="heading"):
        build_policy("teacher", None, space, teacher_net({"encoder": "lookahead", "heading": "sideways"}, SIM))


def _plain_and(space, **extra):
    """A lookahead teacher and the same weights built with ``extra`` net keys (the shields have no weights)."""
    torch.manual_seed(0)
    plain = build_policy("teacher", None, space, teacher_net({"encoder": "lookahead"}, SIM))
    other = build_policy("teacher", None, space, {**teacher_net({"encoder": "lookahead"}, SIM), **extra})
    other.load_state_dict(plain.state_dict())
    return plain, other


def test_obstacle_shield_lowers_exactly_the_arcs_predicted_to_hit(space):
    """With ``shield_s`` the head lowers the logit of every action whose arc comes within the margin of the scan's
    obstacles by then (a wall 0.6 m ahead: the fast straight arcs), leaves the others (standing still, turning on
    the spot) as they were, and is off by default; an out-of-range horizon is one ConfigError."""
    plain, shielded = _plain_and(space, shield_s=0.6)
    head = shielded.features_extractor.lookahead
    obs = _obs(scan_m=0.6)
    feats = head.action_features(obs)
    intr = head.shield_intrusion(feats)[0]
    straight_fast = 4 * N_ROT + N_ROT // 2
    assert intr[straight_fast] > 0.1 and intr[:N_ROT].abs().max() == 0  # v = 0: no intrusion
    a = plain.features_extractor(obs)[0, :head.n_actions]
    b = shielded.features_extractor(obs)[0, :head.n_actions]
    torch.testing.assert_close(a - b, SHIELD_NATS_PER_M * intr)
    assert int(b.argmax()) not in torch.nonzero(intr > 0).flatten().tolist()
    free = _obs()  # nothing near: the shield changes nothing
    torch.testing.assert_close(plain.features_extractor(free), shielded.features_extractor(free))
    with pytest.raises(ConfigError, match="shield_s"):
        build_policy("teacher", None, space, {**teacher_net({"encoder": "lookahead"}, SIM), "shield_s": 5.0})


def test_the_mlp_heads_obstacle_shield_is_the_lookahead_heads_rule(space):
    """:class:`rl.lookahead.ObstacleShield` (the shield of a head without rollouts) subtracts exactly what the
    lookahead head's shield subtracts, on a wall, on random scans and on an empty one; 0 or an out-of-range
    horizon is one ConfigError."""
    _, shielded = _plain_and(space, shield_s=0.6)
    head = shielded.features_extractor.lookahead
    shield = ObstacleShield(SIM.robot, SIM.dt_s, SIM.scan_rays, SIM.scan_range_m, 0.6)
    gen = torch.Generator().manual_seed(0)
    scans = [_obs(scan_m=0.6)["scan"], _obs()["scan"], 0.2 + 3.0 * torch.rand(4, 72, generator=gen)]
    for scan in scans:
        obs = {**_obs(), "scan": scan, **{k: v.expand(len(scan), *v.shape[1:]) for k, v in _obs().items()
                                          if k != "scan"}}
        expected = SHIELD_NATS_PER_M * head.shield_intrusion(head.action_features(obs))
        torch.testing.assert_close(shield(scan), expected)
    assert shield(scans[0])[0].max() > 100.0 and shield(scans[1]).abs().max() == 0
    for bad in (0.0, 5.0, float("nan")):
        with pytest.raises(ConfigError, match="obstacle shield shield_s"):
            ObstacleShield(SIM.robot, SIM.dt_s, SIM.scan_rays, SIM.scan_range_m, bad)


def test_shield_can_be_set_on_a_saved_checkpoint_without_touching_its_files(tmp_path, space):
    """``load_policy(ckpt, shield_s)`` (``eval --shield_s``) builds the saved weights with the shield on (or off):
    the same logits wherever no arc intrudes, the intruding arcs lowered, the checkpoint's files unchanged."""
    policy = _policy(space)
    save_policy(tmp_path / "t", policy, describe("teacher", None, space, teacher_net({"encoder": "lookahead"}, SIM)))
    before = {p.name: p.read_bytes() for p in (tmp_path / "t").iterdir() if p.is_file()}
    saved, _ = load_policy(tmp_path / "t")
    shielded, desc = load_policy(tmp_path / "t", shield_s=0.6)
    assert desc["net"]["shield_s"] == 0.6 and saved.features_extractor.lookahead.shield_steps == 0
    wall, free = _obs(scan_m=0.6), _obs()
    with torch.no_grad():
        torch.testing.assert_close(saved.get_distribution(free).distribution.logits,
                                   shielded.get_distribution(free).distribution.logits)
        assert not torch.allclose(saved.get_distribution(wall).distribution.logits,
                                  shielded.get_distribution(wall).distribution.logits)
    off, _ = load_policy(tmp_path / "t", shield_s=0.0)
    assert off.features_extractor.lookahead.shield_steps == 0
    assert {p.name: p.read_bytes() for p in (tmp_path / "t").iterdir() if p.is_file()} == before


def test_people_shield_lowers_exactly_the_arcs_predicted_to_overlap_a_person(space):
    """With ``ped_shield_s`` the head lowers the logit of every action whose arc overlaps a predicted pedestrian by
    then (a person standing 0.8 m ahead: the fast straight arcs), by the predicted overlap, leaves the others
    (standing still, turning on the spot) as they were and changes nothing with nobody near; it stacks with the
    obstacle shield; an out-of-range horizon is one ConfigError."""
    plain, shielded = _plain_and(space, ped_shield_s=0.6)
    head = shielded.features_extractor.lookahead
    obs = _obs(peds=[(0.8, 0.0, 0.0, 0.0)])
    overlap = (-head.pedestrian_clearances(head.action_features(obs), head.ped_shield_steps).amin(-1)[0]).clamp_min(0)
    straight_fast = 4 * N_ROT + N_ROT // 2
    assert overlap[straight_fast] > 0.1 and overlap[:N_ROT].abs().max() == 0  # v = 0: no overlap
    a = plain.features_extractor(obs)[0, :head.n_actions]
    b = shielded.features_extractor(obs)[0, :head.n_actions]
    torch.testing.assert_close(a - b, SHIELD_NATS_PER_M * overlap)
    assert int(b.argmax()) not in torch.nonzero(overlap > 0).flatten().tolist()
    free = _obs()
    torch.testing.assert_close(plain.features_extractor(free), shielded.features_extractor(free))
    both = _plain_and(space, ped_shield_s=0.6, shield_s=0.6)[1]
    wall = _obs(peds=[(0.8, 0.0, 0.0, 0.0)], scan_m=0.6)
    c = both.features_extractor(wall)[0, :head.n_actions]
    intr = both.features_extractor.lookahead.shield_intrusion(head.action_features(wall))[0]
    torch.testing.assert_close(plain.features_extractor(wall)[0, :head.n_actions] - c,
                               SHIELD_NATS_PER_M * (intr + overlap))
    with pytest.raises(ConfigError, match="ped_shield_s"):
        build_policy("teacher", None, space, {**teacher_net({"encoder": "lookahead"}, SIM), "ped_shield_s": -1.0})
