"""The student's perception for its lookahead head (rl.perceive) and the head itself (StudentLookaheadExtractor)."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from pipeline.core.errors import ConfigError
from pretrain.intention import STANDING_MPS, ForecasterConfig, IntentionForecaster
from rl.lookahead import LINEAR_TERMS, N_LINEAR, PED_TERMS, lookahead_times
from rl.networks import StudentLookaheadExtractor, variant_keys
from rl.observe import observer_for_env, uses_forecaster
from rl.perceive import CameraView, DepthScan, interpolation_matrix, scan_from_points
from rl.policy import POLICY_WEIGHTS, ScoredPolicy, build_policy, describe, load_policy, save_policy
from rl.teacher import fit_lookahead_linear, lookahead_feature_cache, mirror_batch
from sim.env import CrowdNavEnv, SimConfig
from sim.expert import PrivilegedExpert
from sim.tracking import PED_RADIUS_M
from tests.rl.helpers_lookahead import HEAD_KEYS, pre_head_layout

SIM = replace(SimConfig(max_episode_s=8.0), obs_mode="visual", info_level="basic")
SIM.camera.width_px, SIM.camera.height_px = 80, 60


def test_scan_bins_points_like_the_static_scan():
    pts = np.array([[2.0, 0.0], [3.0, 0.0], [0.0, 1.0], [-1.0, -1.0]])
    s = scan_from_points(pts, 8, 10.0)
    assert s.tolist() == pytest.approx([2.0, 10.0, 1.0, 10.0, 10.0, np.sqrt(2), 10.0, 10.0])


@pytest.fixture(scope="module")
def lobby():
    env = CrowdNavEnv(config=replace(SIM, scene="office_lobby", density=0.2))
    yield env
    env.close()


def test_perception_agrees_with_the_simulator_in_view(lobby):
    """Tracks near the true pedestrians (with their velocity); the depth scan ahead shows the static map or people."""
    env = lobby
    obs, _ = env.reset(seed=3)
    observer = observer_for_env(env, "no_bev", None, head="lookahead")
    assert set(variant_keys("no_bev", "lookahead")) <= set(observer.observation_space.spaces)
    observer.reset()
    expert = PrivilegedExpert()
    expert.reset(env)
    pos_err, vel_err, scan_err = [], [], []
    for step in range(60):
        o = observer(obs)
        assert observer.observation_space.contains({k: np.asarray(v, np.float32) for k, v in o.items()})
        true = env.privileged_peds()
        true = true[true[:, 5] > 0]
        for p in o["peds"][o["peds"][:, 5] > 0]:
            d = np.hypot(*(true[:, :2] - p[:2]).T)
            if d.min() < 0.6 and step >= 10:
                pos_err.append(d.min())
                vel_err.append(np.hypot(*(true[d.argmin(), 2:4] - p[2:4])))
        # in view (±35°), every perceived scan bin is the static map or a pedestrian (undetected people stay in it)
        ahead = np.r_[0:8, 65:72]
        rng, static = np.minimum(o["scan"][ahead], 4.0), np.minimum(env.static_scan()[ahead], 4.0)
        ang = ahead * (2 * np.pi / 72)
        hit = np.stack([rng * np.cos(ang), rng * np.sin(ang)], -1)
        x, y, yaw = env.robot
        c, s_ = np.cos(yaw), np.sin(yaw)
        rel = env.crowd.pos - env.robot[:2]
        people = np.stack([c * rel[:, 0] + s_ * rel[:, 1], -s_ * rel[:, 0] + c * rel[:, 1]], -1)
        near_person = np.linalg.norm(hit[:, None] - people[None], axis=-1).min(1) < 0.6
        scan_err.append((np.abs(rng - static) < 0.3) | (near_person & (rng < 4.0)))
        obs, _, term, trunc, _ = env.step(env.encode_command(*expert.command(env)))
        if term or trunc:
            break
    assert len(pos_err) > 20
    assert np.median(pos_err) < 0.2
    assert np.median(vel_err) < 0.5
    # 0.84 measured: the rest are trails of people who walked on within the 5 s memory (outside the seen-through test)
    assert np.mean(np.concatenate(scan_err)) > 0.75


def test_depth_scan_remembers_what_the_cameras_turned_away_from(lobby):
    env = lobby
    env.reset(seed=1)
    cams = [CameraView.of(c) for c in observer_for_env(env, "no_bev", None).cameras]
    scan = DepthScan(cams, 72, 10.0, memory_s=1.5)
    depth = np.zeros((cams[0].height_px, cams[0].width_px), np.float32)
    depth[:, :] = 2.0  # a wall 2 m in front of the left camera (the floor and ceiling fall outside the band)
    first = scan.update([depth, np.zeros_like(depth)], (0.0, 0.0, 0.0), 0.1)
    hit = np.flatnonzero(first < 10.0)
    assert len(hit) > 0
    # the robot turns by 180° and sees nothing: the wall is now behind it, still in the scan
    turned = scan.update([np.zeros_like(depth)] * 2, (0.0, 0.0, np.pi), 0.1)
    assert np.all(turned[(hit + 36) % 72] == pytest.approx(first[hit], abs=0.05))
    for _ in range(15):  # ... until the memory expires
        turned = scan.update([np.zeros_like(depth)] * 2, (0.0, 0.0, np.pi), 0.1)
    assert np.all(turned == 10.0)


def _student_space(lobby, variant="no_bev"):
    return observer_for_env(lobby, variant, None, head="lookahead").observation_space


def _net(lobby):
    from dataclasses import asdict

    c = lobby.cfg
    return {"head": "lookahead", "robot": asdict(c.robot), "dt_s": c.dt_s, "scan_range_m": c.scan_range_m}


def _batch(space, n, seed=0):
    g = torch.Generator().manual_seed(seed)
    out = {k: torch.rand((n, *s.shape), generator=g) for k, s in space.spaces.items()}
    out["scan"] = 1.0 + 9.0 * out["scan"]
    out["peds"][..., :2] = 6.0 * out["peds"][..., :2] - 3.0
    out["peds"][..., 4] = PED_RADIUS_M
    out["peds"][..., 5] = (out["peds"][..., 5] > 0.5).float()
    out["state"][:, :2] = 8.0 * out["state"][:, :2] - 4.0
    out["state"][:, 2] = torch.linalg.vector_norm(out["state"][:, :2], dim=-1)
    return out


def test_student_head_scores_actions_and_round_trips(lobby, tmp_path):
    space = _student_space(lobby)
    torch.manual_seed(0)
    policy = build_policy("student", "no_bev", space, _net(lobby))
    assert isinstance(policy, ScoredPolicy)
    ext = policy.features_extractor
    assert isinstance(ext, StudentLookaheadExtractor)
    obs = _batch(space, 4)
    logits = policy.get_distribution(obs).distribution.logits
    assert logits.shape == (4, 105) and torch.isfinite(logits).all()
    save_policy(tmp_path, policy, describe("student", "no_bev", space, _net(lobby)))
    again, _ = load_policy(tmp_path)
    assert torch.allclose(again.get_distribution(obs).distribution.logits, logits, atol=1e-5)


def test_student_checkpoint_from_before_the_head_module_loads(lobby, tmp_path):
    """A student saved with the pre-module key names (``features_extractor.scorer.0.weight``, ...) loads through
    load_policy (strict) into the same logits and values, its bounded scorer included."""
    space = _student_space(lobby)
    net = {**_net(lobby), "scorer_bound": 3.0}
    torch.manual_seed(1)
    policy = build_policy("student", "no_bev", space, net)
    assert set(policy.features_extractor.lookahead.state_dict()) == HEAD_KEYS
    save_policy(tmp_path, policy, describe("student", "no_bev", space, net))
    save_file(pre_head_layout(policy.state_dict()), str(tmp_path / POLICY_WEIGHTS))
    again, _ = load_policy(tmp_path)
    assert again.features_extractor.lookahead.scorer_bound == 3.0
    obs = _batch(space, 4, seed=5)
    with torch.no_grad():
        policy.set_training_mode(False)
        assert torch.equal(again.get_distribution(obs).distribution.logits,
                           policy.get_distribution(obs).distribution.logits)
        assert torch.equal(again.predict_values(obs), policy.predict_values(obs))


def test_student_head_mirror_symmetry_and_no_i2_without_people(lobby):
    space = _student_space(lobby)
    ext = build_policy("student", "no_bev", space, _net(lobby)).features_extractor
    obs = _batch(space, 3, seed=1)
    flip = torch.ones(3, dtype=torch.bool)
    mobs, _, _ = mirror_batch(obs, torch.zeros(3, dtype=torch.long), None, flip, 21)
    f, mf = ext.action_features(obs), ext.action_features(mobs)
    # the mirrored world's action j of yaw index r is action j of yaw index 20 - r; the linear cost's terms agree
    lin, mlin = f[..., -N_LINEAR:].view(3, 5, 21, -1), mf[..., -N_LINEAR:].view(3, 5, 21, -1)
    assert torch.allclose(lin, torch.flip(mlin, [2]), atol=1e-4)
    # w/o I²: no poses, so no tracks; its rollouts predict nobody
    assert "peds" not in variant_keys("no_i2", "lookahead")
    no_people = {k: v for k, v in obs.items() if k != "peds"}
    g = ext.action_features(no_people)
    assert torch.all(g[..., 0] == g[..., 0].max())  # ped clearance at its cap everywhere


def test_linear_cost_fits_the_teachers_distribution(lobby):
    """The convex fit recovers a linear cost the targets were generated from (the student's distillation step)."""
    space = _student_space(lobby)
    torch.manual_seed(0)
    policy = build_policy("student", "no_bev", space, _net(lobby))
    obs = _batch(space, 256, seed=2)
    data = {k: v.numpy() for k, v in obs.items()}
    ext = policy.features_extractor
    feats = ext.action_features(obs)[..., -N_LINEAR:]
    w_true = torch.tensor([-3.0, -1.0, -2.0, -0.5, 1.0, 0.5, -0.3, 0.2, 0.1, -0.1])
    logits = 10.0 * (feats @ w_true)
    data["costs"], data["action"] = -logits.numpy(), logits.argmax(-1).numpy()
    cache = lookahead_feature_cache(policy, data, mirror=True)
    fit = fit_lookahead_linear(policy, data, soft_tau=1.0, mirror=True, cache=cache)
    assert fit["ce_after"] < 0.5 * fit["ce_before"]


def test_bounded_scorer_cannot_override_the_cost(lobby):
    """With scorer_bound c, logits differ from the linear cost's by at most c nats, however large the MLP's output."""
    space = _student_space(lobby)
    torch.manual_seed(0)
    policy = build_policy("student", "no_bev", space, {**_net(lobby), "scorer_bound": 2.0})
    ext = policy.features_extractor
    with torch.no_grad():
        ext.lookahead.scorer[-1].weight.mul_(1e3)
        ext.lookahead.scorer[-1].bias.fill_(50.0)
    obs = _batch(space, 8, seed=3)
    feats = ext.action_features(obs)
    logits = ext(obs)[:, :ext.lookahead.n_actions]
    linear = 10.0 * ext.lookahead.linear(feats[..., -N_LINEAR:]).squeeze(-1)
    gap = (logits - linear).abs()
    assert gap.max() <= 2.0 + 1e-4 and gap.max() > 1.5


# ------------------------------------------------------------------------ the intention model in the lookahead head
def _cv_forecaster() -> IntentionForecaster:
    """An intention model whose learned residuals are zero: it predicts constant velocity."""
    m = IntentionForecaster(ForecasterConfig())
    for head in (m.base, m.pose_residual):
        torch.nn.init.zeros_(head[-1].weight)
        torch.nn.init.zeros_(head[-1].bias)
    return m.eval().requires_grad_(False)


def test_interpolation_matrix_is_exact_on_lines_and_extrapolates():
    src, dst = np.array([0.2, 0.4, 1.0]), np.array([0.1, 0.2, 0.7, 1.2])
    w = interpolation_matrix(src, dst)
    assert np.allclose(w.sum(1), 1.0)
    vals = 3.0 * np.r_[0.0, src] - 1.0  # a line: interpolation and extrapolation are exact
    assert np.allclose(w @ vals, 3.0 * dst - 1.0)


def test_perception_forecasts_every_reported_track_in_the_robot_frame(lobby):
    """With a zero-residual model the forecast of a moving track is its constant velocity at the lookahead times:
    peds_future equals what the head would extrapolate from ``peds`` (one frame convention for both)."""
    env = lobby
    obs, _ = env.reset(seed=3)
    observer = observer_for_env(env, "no_bev", None, head="lookahead", forecaster=_cv_forecaster())
    assert observer.observation_space["peds_future"].shape == (env.cfg.privileged_peds, len(lookahead_times(0.1)), 2)
    observer.reset()
    expert = PrivilegedExpert()
    expert.reset(env)
    seen = 0
    for _ in range(30):
        o = observer(obs)
        peds, fut = o["peds"], o["peds_future"]
        times = lookahead_times(env.cfg.dt_s).numpy()
        cv = peds[:, None, :2] + times[None, :, None] * peds[:, None, 2:4]
        live = peds[:, 5] > 0.5
        speed = np.hypot(peds[:, 2], peds[:, 3])
        moving = live & (speed > STANDING_MPS)  # a standing track's frame faces the robot: its speed along that ray
        assert np.allclose(fut[moving], cv[moving], atol=1e-4) and not fut[~live].any()
        drift = np.linalg.norm(fut[live & ~moving] - peds[live & ~moving, None, :2], axis=-1)
        assert np.all(drift <= speed[live & ~moving, None] * times[None] + 1e-4)
        seen += int(moving.sum())
        obs, _, term, trunc, _ = env.step(env.encode_command(*expert.command(env)))
        if term or trunc:
            break
    assert seen > 10


def test_the_lookahead_head_uses_the_intention_prediction(lobby):
    """A pedestrian 2 m ahead walking across the robot's path: predicted to turn into the path (peds_future) it
    changes the scores of the straight actions; predicted where constant velocity puts it, nothing changes."""
    space = observer_for_env(lobby, "no_bev", None, head="lookahead", forecaster=_cv_forecaster()).observation_space
    torch.manual_seed(0)
    policy = build_policy("student", "no_bev", space, _net(lobby))
    head = policy.features_extractor.lookahead
    obs = _batch(space, 1)
    obs["peds"][:] = 0.0
    obs["peds"][0, 0] = torch.tensor([2.0, 1.5, 0.0, 1.0, PED_RADIUS_M, 1.0])  # ahead-left, walking further left
    obs["state"][0] = torch.tensor([6.0, 0.0, 6.0, 0.0, 0.0])
    obs["scan"][:] = 10.0
    times = head.times
    cv = obs["peds"][:, :, None, :2] + times[None, None, :, None] * obs["peds"][:, :, None, 2:4]
    without = {k: v for k, v in obs.items() if k != "peds_future"}
    f_cv = head.action_features({**obs, "peds_future": cv})
    assert torch.allclose(f_cv, head.action_features(without), atol=1e-5)
    turn = cv.clone()
    turn[0, 0, :, 1] = 1.5 - 1.5 * (times / times[-1]).clamp(max=1.0)  # it turns right, into the robot's path
    f_turn = head.action_features({**obs, "peds_future": turn})
    assert not torch.allclose(f_turn, f_cv)
    logits = policy.get_distribution({**obs, "peds_future": turn}).distribution.logits
    assert torch.isfinite(logits).all()
    # mirroring reflects the prediction with the world: the linear cost's terms of yaw index r and 20 - r agree
    flip = torch.ones(1, dtype=torch.bool)
    mobs, _, _ = mirror_batch({**obs, "peds_future": turn}, torch.zeros(1, dtype=torch.long), None, flip, 21)
    lin = f_turn[..., -N_LINEAR:].view(1, 5, 21, -1)
    mlin = head.action_features(mobs)[..., -N_LINEAR:].view(1, 5, 21, -1)
    assert torch.allclose(lin, torch.flip(mlin, [2]), atol=1e-4)


def test_a_student_without_poses_or_with_the_mlp_head_uses_no_intention_model():
    assert uses_forecaster("full", "lookahead") and uses_forecaster("no_bev", "lookahead")
    assert not uses_forecaster("no_i2", "lookahead") and not uses_forecaster("full", "mlp")


# ------------------------------------------------------------------------ the occupancy map along the arcs (map_cost)
BOUNDS = [[0.0, 6.0], [-4.8, 4.8]]  # the default BEV grid; maps of 30 x 48 cells of 0.2 m (s_bev pooled 2 x 2)
STRAIGHT_FAST, STOP = 4 * 21 + 10, 10  # action indices: 1 m/s straight on, standing still


def _block(occ, ch, x0, x1, y0, y1):
    """Marks the cells of channel ``ch`` whose centres lie in [x0, x1] x [y0, y1] (m) occupied."""
    xs = BOUNDS[0][0] + (np.arange(occ.shape[-2]) + 0.5) * 0.2
    ys = BOUNDS[1][0] + (np.arange(occ.shape[-1]) + 0.5) * 0.2
    occ[..., ch, :, :] += torch.from_numpy(((xs[:, None] >= x0) & (xs[:, None] <= x1)
                                            & (ys[None] >= y0) & (ys[None] <= y1)).astype(np.float32))
    return occ


def _map_head(lobby, channels, view_deg=None):
    from dataclasses import asdict

    import gymnasium as gym

    from rl.lookahead import LookaheadHead

    space = _student_space(lobby)
    spaces = dict(space.spaces)
    spaces["bev_occ"] = gym.spaces.Box(0.0, 1.0, (channels, 30, 48), np.float32)
    c = lobby.cfg
    return LookaheadHead(gym.spaces.Dict(spaces), asdict(c.robot), c.dt_s, 0.25, 8, 8, 4, subgoal=False,
                         scan_range_m=c.scan_range_m, map_key="bev_occ", map_bounds=BOUNDS, map_view_deg=view_deg)


def _map_obs(lobby, occ):
    obs = _batch(_student_space(lobby), 1)
    obs["peds"][..., 5] = 0.0  # nobody tracked, no scan hits: only the map speaks
    obs["scan"][:] = 10.0
    obs["bev_occ"] = occ
    return obs


def test_map_features_read_static_occupancy_along_each_arc(lobby):
    head = _map_head(lobby, 4)
    occ = _block(torch.zeros(1, 4, 30, 48), 0, 1.2, 1.8, -0.4, 0.4)  # a box 1.2-1.8 m straight ahead
    f = head.action_features(_map_obs(lobby, occ))[0]
    m = f[:, -N_LINEAR - 4:-N_LINEAR]  # static max, static mean, people max, people mean
    assert m[STRAIGHT_FAST, 0] > 0.9 and m[STRAIGHT_FAST, 1] > 0.2  # driving into it
    assert m[STOP, 0] == 0 and m[STOP, 1] == 0  # standing still touches nothing
    assert m[:, 2:].abs().max() == 0  # no people in the map
    empty = head.action_features(_map_obs(lobby, torch.zeros(1, 4, 30, 48)))[0]
    assert empty[:, -N_LINEAR - 4:-N_LINEAR].abs().max() == 0
    # everything but the map features is what the head without a map computes
    plain = build_policy("student", "no_bev", _student_space(lobby), _net(lobby)).features_extractor.lookahead
    g = plain.action_features(_map_obs(lobby, occ))[0]
    assert torch.equal(torch.cat([f[:, :-N_LINEAR - 4], f[:, -N_LINEAR:]], -1), g)


def test_map_people_channels_are_read_at_their_time(lobby):
    """A person predicted 1 m ahead at +1.0 s is met by the 1 m/s straight arc (there at t = 1 s); the same
    person in the "now" channel is not (the arc is at ≤ 0.25 m while "now" is read)."""
    head = _map_head(lobby, 4)
    future = _block(torch.zeros(1, 4, 30, 48), 3, 0.9, 1.1, -0.1, 0.1)
    now = _block(torch.zeros(1, 4, 30, 48), 1, 0.9, 1.1, -0.1, 0.1)
    f = head.action_features(_map_obs(lobby, future))[0, :, -N_LINEAR - 4:-N_LINEAR]
    g = head.action_features(_map_obs(lobby, now))[0, :, -N_LINEAR - 4:-N_LINEAR]
    assert f[STRAIGHT_FAST, 2] > 0.5 and g[STRAIGHT_FAST, 2] < 0.05
    assert f[STOP, 2] == 0 and f[:, :2].abs().max() == 0  # the static channel stays empty


def test_map_features_are_mirror_symmetric_and_the_map_cost_fits_on_top_of_the_inherited_cost(lobby):
    """no_bev with map_cost reads its depth occupancy ``occ``; mirroring flips the map with the world; the convex fit
    of the map cost leaves the inherited linear cost untouched and recovers the sign of the map weight."""
    space = _student_space(lobby)
    assert "occ" in space.spaces and "bev_occ" not in variant_keys("no_bev", "lookahead", map_cost=True)
    assert "bev_occ" in variant_keys("full", "lookahead", map_cost=True)
    net = {**_net(lobby), "map_cost": True, "map_bounds": BOUNDS}
    torch.manual_seed(0)
    policy = build_policy("student", "no_bev", space, net)
    head = policy.features_extractor.lookahead
    assert head.map_key == "occ" and head.n_feat == build_policy(
        "student", "no_bev", space, _net(lobby)).features_extractor.lookahead.n_feat + 4
    obs = _batch(space, 256, seed=4)
    rng = np.random.default_rng(1)
    obs["occ"] = torch.zeros_like(obs["occ"])
    for i in range(256):  # one 0.6 m box per frame, somewhere ahead
        x, y = rng.uniform(0.5, 3.0), rng.uniform(-1.5, 1.5)
        _block(obs["occ"][i:i + 1], 0, x, x + 0.6, y, y + 0.6)
    with torch.no_grad():  # the inherited cost (as in test_linear_cost_fits_the_teachers_distribution)
        head.linear.weight.copy_(torch.tensor([[-3.0, -1.0, -2.0, -0.5, 1.0, 0.5, -0.3, 0.2, 0.1, -0.1]]) / 10.0)
    flip = torch.ones(256, dtype=torch.bool)
    mobs, _, _ = mirror_batch(obs, torch.zeros(256, dtype=torch.long), None, flip, 21)
    mf = head.action_features(mobs)[..., -N_LINEAR - 4:-N_LINEAR].view(256, 5, 21, -1)
    f = head.action_features(obs)[..., -N_LINEAR - 4:-N_LINEAR].view(256, 5, 21, -1)
    assert torch.allclose(f, torch.flip(mf, [2]), atol=1e-4)
    # targets from the inherited linear cost plus a map cost of -40 nats per unit of static maximum
    feats = head.action_features(obs)
    with torch.no_grad():
        logits = 10.0 * head.linear(feats[..., -N_LINEAR:]).squeeze(-1) - 40.0 * feats[..., -N_LINEAR - 4]
    data = {k: v.numpy() for k, v in obs.items()}
    data["costs"], data["action"] = -logits.numpy(), logits.argmax(-1).numpy()
    linear = head.linear.weight.detach().clone()
    fit = fit_lookahead_linear(policy, data, soft_tau=1.0, mirror=True, terms="map",
                               cache=lookahead_feature_cache(policy, data, mirror=True))
    assert torch.equal(head.linear.weight, linear)
    assert fit["ce_after"] < fit["ce_before"]
    assert fit["map_weights"][0] == pytest.approx(-40.0, abs=2.0)  # recovered, in nats per unit
    assert fit["map_weights"][2:] == [0.0, 0.0]  # a depth map has no people channels: their weights stay at zero
    # a map *bonus* in the targets: the free fit follows it, map_signs="costs" holds that term at 0 (no weight > 0)
    with torch.no_grad():
        bonus = 10.0 * head.linear(feats[..., -N_LINEAR:]).squeeze(-1) + 40.0 * feats[..., -N_LINEAR - 4]
    data["costs"], data["action"] = -bonus.numpy(), bonus.argmax(-1).numpy()
    cache = lookahead_feature_cache(policy, data, mirror=True)
    free = fit_lookahead_linear(policy, data, soft_tau=1.0, mirror=True, terms="map", cache=cache)
    costs = fit_lookahead_linear(policy, data, soft_tau=1.0, mirror=True, terms="map", cache=cache, map_signs="costs")
    assert free["map_weights"][0] > 20.0 and "map_pinned" not in free
    assert 0 in costs["map_pinned"] and max(costs["map_weights"]) <= 0.0 and costs["ce_after"] >= free["ce_after"]
    with pytest.raises(ConfigError, match="map_signs"):
        fit_lookahead_linear(policy, data, soft_tau=1.0, terms="map", cache=cache, map_signs="bonus")


def test_pedestrian_refit_moves_only_the_pedestrian_terms_and_the_map(lobby):
    """``terms="peds"`` (``train.dagger.linear_cost: peds``): targets made with a softer pedestrian-contact weight than
    the inherited one, another goal-gain weight and a static-map cost — the fit recovers the pedestrian and map
    weights and leaves every other linear term, the goal gain included, where it was; the map-only fit, whose
    pedestrian weight is held, explains less."""
    space = _student_space(lobby)
    net = {**_net(lobby), "map_cost": True, "map_bounds": BOUNDS}
    torch.manual_seed(0)
    policy = build_policy("student", "no_bev", space, net)
    head = policy.features_extractor.lookahead
    obs = _batch(space, 256, seed=5)
    rng = np.random.default_rng(2)
    obs["occ"] = torch.zeros_like(obs["occ"])
    for i in range(256):
        x, y = rng.uniform(0.5, 3.0), rng.uniform(-1.5, 1.5)
        _block(obs["occ"][i:i + 1], 0, x, x + 0.6, y, y + 0.6)
    inherited = torch.tensor([[-3.0, -1.0, -2.0, -0.5, 1.0, 0.5, -0.3, 0.2, 0.1, -0.1]]) / 10.0
    truth = inherited.clone()
    truth[0, 0] = -0.8 / 10.0  # the targets' pedestrian contact: -0.8 nats per unit where the inherited cost says -3
    truth[0, 5] = 2.0 / 10.0  # and a goal gain the fit must not take up (it is not a pedestrian term)
    feats = head.action_features(obs)
    assert float(feats[..., -N_LINEAR].std()) > 0.1  # the batch has predicted contacts for the weight to explain
    with torch.no_grad():
        logits = (10.0 * (feats[..., -N_LINEAR:] @ truth.T).squeeze(-1) - 40.0 * feats[..., -N_LINEAR - 4])
    data = {k: v.numpy() for k, v in obs.items()}
    data["costs"], data["action"] = -logits.numpy(), logits.argmax(-1).numpy()
    cache = lookahead_feature_cache(policy, data, mirror=True)
    fits = {}
    for terms in ("map", "peds"):
        with torch.no_grad():
            head.linear.weight.copy_(inherited)
            head.map_cost.weight.zero_()
        fits[terms] = fit_lookahead_linear(policy, data, soft_tau=1.0, mirror=True, terms=terms, cache=cache)
    peds = fits["peds"]
    assert peds["linear_weights"]["ped_contact"] == pytest.approx(-0.8, abs=0.15)
    assert -50.0 < peds["map_weights"][0] < -20.0  # the -40 of the targets, less what the held goal gain confounds
    held = [n for i, n in enumerate(LINEAR_TERMS) if i not in PED_TERMS]
    assert all(peds["linear_weights"][n] == pytest.approx(float(inherited[0, LINEAR_TERMS.index(n)]) * 10.0, abs=1e-5)
               for n in held)
    assert fits["map"]["linear_weights"]["ped_contact"] == pytest.approx(-3.0, abs=1e-5)
    assert peds["ce_after"] < fits["map"]["ce_after"]
    with pytest.raises(ConfigError, match="terms"):
        fit_lookahead_linear(policy, data, soft_tau=1.0, terms="goal", cache=cache)


def test_observer_makes_the_bev_occupancy_from_the_pretext_heads(lobby):
    from pipeline.core.errors import ConfigError
    from pretrain.model import BEVEncoder, EncoderConfig, PretextHeads
    from rl.observe import env_cameras

    torch.manual_seed(0)
    enc = BEVEncoder(EncoderConfig(bev_channels=8, resnet_stages=1, lift_stride_px=4), env_cameras(lobby)).eval()
    with pytest.raises(ConfigError, match="pretext heads"):
        observer_for_env(lobby, "full", enc, head="lookahead", map_cost=True)
    ob = observer_for_env(lobby, "full", enc, head="lookahead", map_cost=True, map_heads=PretextHeads(8))
    o, _ = lobby.reset(seed=3)
    out = ob(o)
    nx, ny = enc.grid.shape
    assert out["bev_occ"].shape == (4, nx // 2, ny // 2) == ob.observation_space["bev_occ"].shape
    assert out["bev_occ"].min() >= 0.0 and out["bev_occ"].max() <= 1.0
    assert "bev_occ" not in observer_for_env(lobby, "full", enc, head="lookahead").observation_space.spaces


def test_tracks_of_people_the_cameras_cannot_see_coast_with_unseen_s(lobby):
    """``unseen_s``: a track is observable inside a camera's horizontal view (by the margin) and at least NEAR_M
    from the robot; only then does a missed detection count towards dropping it. Out of range is one ConfigError."""
    from pipeline.core.errors import ConfigError
    from rl.perceive import NEAR_M, Perception

    env = lobby
    env.reset(seed=3)
    observer = observer_for_env(env, "no_bev", None, head="lookahead")
    tracker = observer.perception.tracker  # the default: unseen tracks coast as any missed one
    assert tracker.max_unseen == tracker.max_missed
    views = [CameraView.of(c) for c in observer.cameras]
    p = Perception(views, 0.1, 10, 72, 10.0, unseen_s=2.0)
    assert p.tracker.max_unseen == 20
    # the joint view: the cameras' axes yawed by ±yaw_deg, each seeing half its horizontal field of view beyond
    assert math.degrees(p.view_half) == pytest.approx(env.cfg.camera.yaw_deg + env.cfg.camera.hfov_deg / 2, abs=0.5)
    pts = np.array([[3.0, 0.0], [3.0 * math.cos(1.0), 3.0 * math.sin(1.0)], [0.0, 2.0], [-2.0, 0.0],
                    [0.5 * NEAR_M, 0.0]])
    assert p.observable(pts).tolist() == [True, True, False, False, False]  # ahead, 57° left, beside, behind, near
    with pytest.raises(ConfigError, match="unseen_s"):
        Perception(views, 0.1, 10, 72, 10.0, unseen_s=-1.0)


def test_the_map_is_read_only_inside_the_cameras_view_with_map_view_deg(lobby):
    """With ``map_view_deg`` the cells beside the robot (outside the view, where the pretrained BEV marks the unseen as
    occupied) read as free: a block at bearing ~80° no longer reaches the turning arcs' features, one straight ahead
    reads as without the mask; an out-of-range bearing is one ConfigError."""
    from pipeline.core.errors import ConfigError

    whole, masked = _map_head(lobby, 4), _map_head(lobby, 4, view_deg=70.0)
    side = _block(torch.zeros(1, 4, 30, 48), 0, 0.0, 0.2, 0.8, 4.8)  # beside the robot, left: bearing > 80°
    side = _block(side, 3, 0.0, 0.2, 0.8, 4.8)  # and people predicted there at +1.0 s
    fw, fm = (h.action_features(_map_obs(lobby, side))[0, :, -N_LINEAR - 4:-N_LINEAR] for h in (whole, masked))
    assert fw[:, 0].max() > 0.9 and fw[:, 2].max() > 0.5  # the whole map: turning left runs into it
    assert fm[:, 0].max() < fw[:, 0].max() - 0.5 and fm[:, 2].max() < fw[:, 2].max() - 0.4
    ahead = _block(torch.zeros(1, 4, 30, 48), 0, 1.2, 1.8, -0.4, 0.4)
    torch.testing.assert_close(*(h.action_features(_map_obs(lobby, ahead)) for h in (whole, masked)))
    with pytest.raises(ConfigError, match="map_view_deg"):
        _map_head(lobby, 4, view_deg=270.0)


def test_lookahead_feature_cache_reads_only_the_heads_inputs(lobby):
    """A ``full`` student's rollout features come from the keys the head reads: computed from every key of its
    observation (``bev`` and the mirrored world's ``bev_mirror`` included) or from a pool without the BEV features,
    they are the same arrays."""
    from pretrain.model import BEVEncoder, EncoderConfig
    from rl.observe import env_cameras

    torch.manual_seed(0)
    enc = BEVEncoder(EncoderConfig(bev_channels=8, resnet_stages=1, lift_stride_px=4), env_cameras(lobby)).eval()
    space = observer_for_env(lobby, "full", enc, head="lookahead", mirror=True).observation_space
    policy = build_policy("student", "full", space, _net(lobby))
    keys = policy.features_extractor.lookahead.input_keys
    assert "bev" in space.spaces and "bev" not in keys and {"state", "scan", "peds"} <= set(keys)
    data = {k: v.numpy() for k, v in _batch(space, 40, seed=7).items()}
    data["bev_mirror"] = np.random.default_rng(1).random(data["bev"].shape, np.float32)
    data["action"] = np.zeros(40, np.int64)
    every = lookahead_feature_cache(policy, data, mirror=True, keys=tuple(space.spaces), chunk=16)
    only = lookahead_feature_cache(policy, data, mirror=True, chunk=16)
    no_bev = lookahead_feature_cache(policy, {k: v for k, v in data.items() if not k.startswith("bev")}, mirror=True)
    for got in (only, no_bev):
        assert all(np.array_equal(a, b) for a, b in zip(got, every, strict=True))
