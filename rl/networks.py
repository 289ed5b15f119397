"""Policy networks as stable-baselines3 features extractors (the actor/critic heads are SB3's).

Student (the paper's policy, §III-B/C), variants :data:`VARIANTS`::

    full    z = φ_f([φ_bev(s_bev), I²Former(poses, mask, s), φ_s(s)])
    no_i2   z = φ_f([φ_bev(s_bev),                           φ_s(s)])          ablation "w/o I²"
    no_bev  z = φ_f([φ_occ(occ),   I²Former(poses, mask, s), φ_s(s)])          ablation "w/o BEV"

``s_bev`` is the frozen spatio-temporal encoder's output after a fixed 2 x 2 average pool (done by the observer,
:mod:`rl.observe`, so it is what DAgger caches); ``occ`` is a local occupancy map built from the depth images on
the same grid (no learned perception). φ_bev and φ_occ are the same architecture: 2D convolutions with residual
connections and max pooling, then an adaptive average pool to a small spatial grid and a linear layer. The
per-channel mean and standard deviation of ``s_bev`` (measured on the first DAgger data) are buffers of the
extractor, so they travel inside every checkpoint.

Teacher (privileged, no rendering), ``encoder="set"`` (default): the nearest pedestrians (x, y, vx, vy, r, present
in the robot frame) each go through one shared MLP together with s and their distance (the pairwise "robot-human"
features of SARL), then masked attention pooling and masked max pooling (order-free, any count, an empty crowd is a
learned vector); the 360° static range scan goes through circular 1D convolutions; s through an MLP. A set encoder
generalises from tens of thousands of expert frames where a flat MLP over distance-sorted pedestrian slots overfits
(measured: see README, "Training results"). ``encoder="flat"`` keeps the plain concatenation.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import torch
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from rl.i2former import AttnPool, I2Former, I2FormerConfig, mlp, normalise_state

VARIANTS = ("full", "no_i2", "no_bev")
VARIANT_LABELS = {"full": "iCrowdNav (full)", "no_i2": "w/o I²", "no_bev": "w/o BEV"}
STUDENT_HEADS = ("mlp", "lookahead")  # the student's actor: SB3's MLP on z (the paper's) or the lookahead scorer


TEACHER_ENCODERS = ("set", "flat", "lookahead")
SUBGOAL_SCALE_M = 2.0  # the privileged sub-goal's scale (its lookahead along the global path)


def teacher_extractor_class(encoder: str) -> type[BaseFeaturesExtractor]:
    """The teacher's features extractor for ``net["encoder"]`` (checkpoints without the key are "flat")."""
    if encoder not in TEACHER_ENCODERS:
        from pipeline.core.errors import ConfigError

        raise ConfigError(f"teacher.net.encoder: expected one of {list(TEACHER_ENCODERS)}, got {encoder!r}")
    return {"set": SetTeacherExtractor, "flat": TeacherExtractor, "lookahead": LookaheadTeacherExtractor}[encoder]


def variant_keys(variant: str, head: str = "mlp") -> tuple[str, ...]:
    """The observation keys a student variant consumes (with the ``lookahead`` head also its perceived ``scan`` and,
    for variants with poses, the pedestrian tracks ``peds``: :mod:`rl.perceive`)."""
    from pipeline.core.errors import ConfigError

    if variant not in VARIANTS:
        raise ConfigError(f"variant: expected one of {list(VARIANTS)}, got {variant!r}")
    if head not in STUDENT_HEADS:
        raise ConfigError(f"net.head: expected one of {list(STUDENT_HEADS)}, got {head!r}")
    keys = {"full": ("bev", "poses", "pose_mask", "state"), "no_i2": ("bev", "state"),
            "no_bev": ("occ", "poses", "pose_mask", "state")}[variant]
    if head == "lookahead":
        keys += ("scan",) + (("peds",) if "poses" in keys else ())
    return keys


class ResBlock(nn.Module):
    """Two 3 x 3 convolutions with a residual connection (1 x 1 projection when the width changes)."""

    def __init__(self, c_in: int, c_out: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, padding=1)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, padding=1)
        self.skip = nn.Identity() if c_in == c_out else nn.Conv2d(c_in, c_out, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(self.skip(x) + self.conv2(torch.relu(self.conv1(x))))


class BEVNet(nn.Module):
    """φ_bev / φ_occ: ``B x C x X x Y`` map → ``B x out`` (residual conv blocks, max pooling, a linear layer)."""

    def __init__(self, c_in: int, width: int = 32, out: int = 256, pooled: tuple[int, int] = (3, 4)) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(c_in, width, 3, padding=1), nn.ReLU(),
            ResBlock(width, width), nn.MaxPool2d(2),
            ResBlock(width, 2 * width), nn.MaxPool2d(2),
            ResBlock(2 * width, 2 * width), nn.AdaptiveAvgPool2d(pooled), nn.Flatten(),
            nn.Linear(2 * width * pooled[0] * pooled[1], out), nn.ReLU(),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class StudentExtractor(BaseFeaturesExtractor):
    """The visual policy's state embedding ``z`` for one variant (see the module docstring)."""

    def __init__(self, observation_space: gym.spaces.Dict, variant: str = "full", bev_dim: int = 256,
                 bev_width: int = 32, state_dim: int = 64, fused_dim: int = 256,
                 i2former: dict[str, Any] | None = None) -> None:
        keys = variant_keys(variant)
        missing = [k for k in keys if k not in observation_space.spaces]
        if missing:
            from pipeline.core.errors import ConfigError

            raise ConfigError(f"variant {variant!r} needs observation keys {missing}, the env gives "
                              f"{sorted(observation_space.spaces)}")
        super().__init__(observation_space, fused_dim)
        self.variant = variant
        width = 0
        if "bev" in keys:
            c = observation_space["bev"].shape[0]
            self.bev = BEVNet(c, bev_width, bev_dim)
            self.register_buffer("bev_mean", torch.zeros(1, c, 1, 1))
            self.register_buffer("bev_std", torch.ones(1, c, 1, 1))
            width += bev_dim
        if "occ" in keys:
            self.occ = BEVNet(observation_space["occ"].shape[0], bev_width, bev_dim)
            width += bev_dim
        if "poses" in keys:
            self.i2former = I2Former(I2FormerConfig(**(i2former or {})))
            width += self.i2former.out_dim
        self.state_net = mlp([5, state_dim, state_dim])  # φ_s
        width += state_dim
        self.fusion = mlp([width, fused_dim, fused_dim])  # φ_f

    def set_bev_stats(self, mean: torch.Tensor, std: torch.Tensor) -> None:
        """Per-channel statistics of ``s_bev`` (``C``) used to standardise it."""
        self.bev_mean.copy_(mean.view_as(self.bev_mean))
        self.bev_std.copy_(std.clamp_min(1e-3).view_as(self.bev_std))

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        parts = []
        if hasattr(self, "bev"):
            parts.append(self.bev((obs["bev"] - self.bev_mean) / self.bev_std))
        if hasattr(self, "occ"):
            parts.append(self.occ(obs["occ"]))
        if hasattr(self, "i2former"):
            parts.append(self.i2former(obs["poses"], obs["pose_mask"] > 0.5, obs["state"]))
        parts.append(self.state_net(normalise_state(obs["state"])))
        return self.fusion(torch.cat(parts, -1))


class StudentLookaheadExtractor(StudentExtractor):
    """A student variant's embedding ``z`` (:class:`StudentExtractor`, the paper's) with the *lookahead head*
    (``net.head = "lookahead"``): every action of the grid is scored by the teacher's lookahead layer
    (:class:`LookaheadTeacherExtractor`: a linear cost + an MLP over the action's kinematic rollout features, with a
    context vector from ``z``) — fed with what the student perceives instead of privileged state: pedestrian tracks
    from its detected poses and an obstacle scan from its depth images (:mod:`rl.perceive`), and the goal in place of
    the global path. ``no_i2`` has no poses, so its rollouts predict no pedestrians (people are depth obstacles
    in its scan). With ``scorer_bound`` c the MLP scorer's output is squashed to ``c · tanh(x / c)`` nats: the
    learned part can re-rank actions the cost finds close, not override a predicted contact (an unbounded scorer
    cloned from the privileged teacher learned to, and collided more: README, Training). The first ``A`` features
    are the logits (:class:`rl.policy.ScoredPolicy`), the rest is ``z``."""

    def __init__(self, observation_space: gym.spaces.Dict, variant: str = "full", robot: dict[str, Any] | None = None,
                 dt_s: float = 0.1, scan_range_m: float = 10.0, score_dim: int = 64, context_dim: int = 32,
                 scorer_bound: float | None = None, heading: str = "end", **kwargs: Any) -> None:
        super().__init__(observation_space, variant, **kwargs)
        missing = [k for k in variant_keys(variant, "lookahead") if k not in observation_space.spaces]
        if missing:
            from pipeline.core.errors import ConfigError

            raise ConfigError(f"the lookahead head of variant {variant!r} needs observation keys {missing}")
        self.subgoal = False
        self.scan_range_m = float(scan_range_m)
        base_dim = self._features_dim
        init_lookahead(self, observation_space, robot, dt_s, 0.25, heading)
        init_scorer(self, base_dim, score_dim, context_dim)
        self.scorer_bound = float(scorer_bound) if scorer_bound else None

    def action_features(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """``B x A x F`` rollout features of every action from the perceived ``peds`` / ``scan`` and the goal."""
        return lookahead_action_features(self, obs)

    def forward(self, obs: dict[str, torch.Tensor], action_features: torch.Tensor | None = None) -> torch.Tensor:
        return score_actions(self, super().forward(obs), obs, action_features)


class TeacherExtractor(BaseFeaturesExtractor):
    """The privileged teacher's input: scaled and concatenated state, pedestrians and static scan."""

    def __init__(self, observation_space: gym.spaces.Dict, scan_range_m: float = 10.0, ped_scale_m: float = 5.0):
        k = observation_space["peds"].shape
        rays = observation_space["scan"].shape[0]
        super().__init__(observation_space, 5 + k[0] * k[1] + rays)
        self.scan_range_m = float(scan_range_m)
        self.register_buffer("ped_scale", torch.tensor([ped_scale_m, ped_scale_m, 1.0, 1.0, 1.0, 1.0]))

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        peds = (obs["peds"] / self.ped_scale).flatten(1)
        return torch.cat([normalise_state(obs["state"]), peds, obs["scan"] / self.scan_range_m], -1)


class SetTeacherExtractor(BaseFeaturesExtractor):
    """Pairwise pedestrian MLP + attention/max pooling, circular conv over the scan, MLP over s (module doc)."""

    def __init__(self, observation_space: gym.spaces.Dict, scan_range_m: float = 10.0, ped_scale_m: float = 5.0,
                 ped_dim: int = 96, scan_channels: int = 16, state_dim: int = 64) -> None:
        rays = observation_space["scan"].shape[0]
        scan_out = scan_channels * 2 * (rays // 4)
        super().__init__(observation_space, state_dim + 2 * ped_dim + 128)
        self.scan_range_m = float(scan_range_m)
        self.register_buffer("ped_scale", torch.tensor([ped_scale_m, ped_scale_m, 1.0, 1.0, 1.0]))
        self.ped_scale_m = float(ped_scale_m)
        # the privileged sub-goal on the global path (teachers trained before it existed have no "subgoal" input)
        self.subgoal = "subgoal" in observation_space.spaces
        self.phi_s = mlp([5 + 2 * self.subgoal, state_dim, state_dim])
        self.phi_ped = mlp([5 + 1 + 5, ped_dim, ped_dim])
        self.pool = AttnPool(ped_dim)
        self.empty = nn.Parameter(torch.zeros(ped_dim))
        self.scan = nn.Sequential(
            nn.Conv1d(1, scan_channels, 5, padding=2, padding_mode="circular"), nn.ReLU(),
            nn.Conv1d(scan_channels, scan_channels, 5, stride=2, padding=2, padding_mode="circular"), nn.ReLU(),
            nn.Conv1d(scan_channels, 2 * scan_channels, 5, stride=2, padding=2, padding_mode="circular"), nn.ReLU(),
            nn.Flatten(), nn.Linear(scan_out, 128), nn.ReLU())

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        s = normalise_state(obs["state"])
        peds = obs["peds"]
        present = peds[..., 5] > 0.5
        s_in = torch.cat([s, obs["subgoal"] / SUBGOAL_SCALE_M], -1) if self.subgoal else s
        rel = peds[..., :5] / self.ped_scale
        dist = torch.linalg.vector_norm(peds[..., :2], dim=-1, keepdim=True) / self.ped_scale_m
        x = self.phi_ped(torch.cat([rel, dist, s.unsqueeze(1).expand(-1, peds.shape[1], -1)], -1))
        anyone = present.any(-1, keepdim=True)
        valid = present | ~anyone  # an empty crowd: pool over padding, then replace by the learned vector
        attn = torch.where(anyone, self.pool(x, valid), self.empty)
        mx = torch.where(anyone, x.masked_fill(~present.unsqueeze(-1), float("-inf")).amax(1).nan_to_num(0.0),
                         self.empty)
        scan = self.scan((obs["scan"] / self.scan_range_m).unsqueeze(1))
        return torch.cat([self.phi_s(s_in), attn, mx, scan], -1)


# ---------------------------------------------------------------------------------------- lookahead teacher
LOOKAHEAD_HORIZON_S = 2.0  # rollout horizon of the lookahead layer
LOOKAHEAD_STEP_S = 0.2  # its resolution (plus the next control step itself)
LOOKAHEAD_DISCOUNT_S = 1.5  # time constant of the discount on predicted intrusions
CLEAR_CAP_M = 3.0  # clearances are clipped to [-0.5, this]
SCORE_SCALE = 10.0  # logits = this x the linear path's output + the MLP's: the expert's costs differ by tens of
# nats at τ = 0.1, which the linear path reaches with weights of order one
HEADING_MODES = ("end", "best", "spin")  # the lookahead heading error (init_lookahead)
SCAN_POINTS = 24  # nearest scan hits the lookahead measures obstacle clearance against
N_LINEAR = 10  # rollout features of the linear cost (the last ones of action_features)
NEAR_GOAL_M = 0.5  # closer than this to the goal, the cost rewards reaching it instead of the route's heading


def unicycle_arcs(grid: torch.Tensor, times: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Robot-frame positions ``A x S x 2`` and headings ``A x S`` of constant (v, ω) commands ``A x 2`` after
    ``times`` (``S``) from the origin facing +x (exact arcs; straight lines where ω = 0)."""
    v, w = grid[:, :1], grid[:, 1:]
    t = times[None, :]
    straight = w.abs() < 1e-6
    ws = torch.where(straight, torch.ones_like(w), w)
    th = w * t
    x = torch.where(straight, v * t, v / ws * torch.sin(th))
    y = torch.where(straight, torch.zeros_like(th), v / ws * (1.0 - torch.cos(th)))
    return torch.stack([x, y], -1), th


class LookaheadTeacherExtractor(SetTeacherExtractor):
    """The set encoder's context plus a kinematic *lookahead layer* that scores every action of the grid.

    For each of the A = 5 x 21 commands the layer rolls the robot forward along its unicycle arc (a fixed buffer) for
    2 s, predicts every observed pedestrian with constant velocity (their true robot-frame velocity, privileged),
    and measures per action: the clearance to the nearest pedestrian and to the nearest static-scan point at each
    of the S lookahead times, discounted intrusion sums over time (below a 0.15 m gap and within the 0.8 m private
    zone for pedestrians, below 0.05 m and 0.25 m for obstacles), the progress along the privileged global path
    (cost-to-go through its best point) and towards the goal, the heading error to the path 1 m further at the end
    of the arc (or the approach to the goal when it is near), and the command itself. These parameter-free features (computed from the
    observation alone) plus a learned context vector go through one shared MLP that outputs each action's logit —
    the policy network is a learned cost over rollouts, like the expert it imitates, but its weights are fitted by
    cloning and PPO. The first ``A`` outputs of :meth:`forward` are the logits (:class:`ScoredPolicy` reads them);
    the rest is the set encoder's embedding, which the critic uses.
    """

    def __init__(self, observation_space: gym.spaces.Dict, scan_range_m: float = 10.0, ped_scale_m: float = 5.0,
                 robot: dict[str, Any] | None = None, dt_s: float = 0.1, path_spacing_m: float = 0.25, score_dim: int = 64,
                 context_dim: int = 32, heading: str = "end") -> None:
        super().__init__(observation_space, scan_range_m, ped_scale_m)
        base_dim = self._features_dim
        init_lookahead(self, observation_space, robot, dt_s, path_spacing_m, heading)
        init_scorer(self, base_dim, score_dim, context_dim)

    def action_features(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """``B x A x F`` parameter-free rollout features of every action (class docstring)."""
        return lookahead_action_features(self, obs)

    def forward(self, obs: dict[str, torch.Tensor], action_features: torch.Tensor | None = None) -> torch.Tensor:
        """``B x (A + base)``: the action logits, then the set encoder's embedding (``action_features``: the
        precomputed :meth:`action_features` of ``obs``, as cloning caches them)."""
        return score_actions(self, super().forward(obs), obs, action_features)


def init_lookahead(m: nn.Module, observation_space: gym.spaces.Dict, robot: dict[str, Any] | None, dt_s: float,
                   path_spacing_m: float, heading: str = "end") -> None:
    """Registers the lookahead layer's fixed buffers on ``m`` (the arcs of every command of the grid, the lookahead
    times, the discount, the scan's ray directions, the path's arc lengths) and its sizes (``n_actions``,
    ``n_feat``). ``m`` must already have ``subgoal`` and ``scan_range_m``.

    ``heading`` picks the heading error of the linear cost: ``"end"`` at the end of the 2 s arc (the first
    checkpoints; a turn on the spot at 2 rad/s ends 4 rad away, past the target, so a robot facing a wall may
    prefer the turn away from its route and dither between the two), ``"best"`` the smallest error reached along
    the arc (a turn that passes through the target heading could stop there), ``"spin"`` the smallest error for
    the turns on the spot only (v = 0), the end error for every moving arc. Measured (README, Training): both
    remove most warehouse stops and triple the shelf collisions, so ``"end"`` stays the default."""
    from pipeline.core.errors import ConfigError
    from sim.robot import RobotConfig, action_grid

    if heading not in HEADING_MODES:
        raise ConfigError(f"lookahead heading: expected one of {list(HEADING_MODES)}, got {heading!r}")
    m.heading = heading

    rc = RobotConfig(**(robot or {}))
    m.radius_m = float(rc.radius_m)
    grid = torch.as_tensor(action_grid(rc), dtype=torch.float32)
    m.n_actions = len(grid)
    times = torch.cat([torch.tensor([float(dt_s)]),
                       torch.arange(1, int(round(LOOKAHEAD_HORIZON_S / LOOKAHEAD_STEP_S)) + 1) * LOOKAHEAD_STEP_S])
    arcs, heading = unicycle_arcs(grid, times)
    m.register_buffer("grid_norm", grid / grid.new_tensor([rc.v_max_mps, rc.omega_max_radps]), persistent=False)
    m.register_buffer("times", times, persistent=False)
    m.register_buffer("arcs", arcs, persistent=False)  # A x S x 2
    m.register_buffer("end_heading", heading[:, -1], persistent=False)  # A
    m.register_buffer("spin", grid[:, 0].abs() < 1e-6, persistent=False)  # A: the turns on the spot
    m.register_buffer("disc", torch.exp(-times / LOOKAHEAD_DISCOUNT_S), persistent=False)
    m.path = "path" in observation_space.spaces
    if m.path:  # arc length of each path point (the env's path_spacing_m, stored in the policy's net)
        spacing = float(path_spacing_m)
        n_path = observation_space["path"].shape[0]
        m.register_buffer("path_s", spacing * torch.arange(1, n_path + 1, dtype=torch.float32), persistent=False)
        m.path_lead = max(1, int(round(1.0 / spacing)))  # heading target: 1 m further along the path
    rays = observation_space["scan"].shape[0]
    ang = torch.arange(rays) * (2 * torch.pi / rays)
    m.register_buffer("ray_dir", torch.stack([torch.cos(ang), torch.sin(ang)], -1), persistent=False)
    m.n_feat = 2 * len(times) + 4 + 4 + 2 + N_LINEAR


def init_scorer(m: nn.Module, base_dim: int, score_dim: int, context_dim: int) -> None:
    """The learned part of a lookahead head on ``m``: a context vector from the ``base_dim`` embedding, the MLP scorer,
    the linear cost; ``m``'s features become the ``n_actions`` logits followed by the embedding."""
    m.context = nn.Sequential(nn.Linear(base_dim, context_dim), nn.ReLU())
    m.scorer = mlp([m.n_feat + context_dim, score_dim, score_dim, 1], last_act=False)
    m.linear = nn.Linear(N_LINEAR, 1)  # the linear cost over the last N_LINEAR rollout features
    m._features_dim = m.n_actions + base_dim
    m.scorer_bound = None  # a student's learned correction is bounded (StudentLookaheadExtractor)


def score_actions(m: nn.Module, base: torch.Tensor, obs: dict[str, torch.Tensor],
                  action_features: torch.Tensor | None) -> torch.Tensor:
    """``B x (A + base)``: each action's logit (the linear cost + the MLP scorer over its rollout features and the
    context of ``base``), then ``base``."""
    feats = m.action_features(obs) if action_features is None else action_features
    ctx = m.context(base)[:, None].expand(-1, feats.shape[1], -1)
    learned = m.scorer(torch.cat([feats, ctx], -1))
    if m.scorer_bound:  # c · tanh(x / c): the learned part may re-rank actions, not override predicted contacts
        learned = m.scorer_bound * torch.tanh(learned / m.scorer_bound)
    scores = SCORE_SCALE * m.linear(feats[..., -N_LINEAR:]) + learned
    return torch.cat([scores.squeeze(-1), base], -1)


@torch.no_grad()
def lookahead_action_features(self: nn.Module, obs: dict[str, torch.Tensor]) -> torch.Tensor:
    """``B x A x F`` parameter-free rollout features of every action of ``self`` (a module set up by
    :func:`init_lookahead`; see :class:`LookaheadTeacherExtractor`). Without ``obs["peds"]`` nobody is predicted."""
    arcs, disc = self.arcs, self.disc  # A S 2, S
    b = obs["state"].shape[0]
    a, s = arcs.shape[:2]
    # pedestrians, constant velocity: B K S 2 (a student without pose input has none)
    peds = obs["peds"] if "peds" in obs else obs["state"].new_zeros(b, 1, 6)
    present = peds[..., 5] > 0.5
    pp = peds[:, :, None, :2] + self.times[None, None, :, None] * peds[:, :, None, 2:4]  # B K S 2
    # |a - p|² = |a|² - 2 a·p + |p|² (one contraction instead of a B A K S 2 difference tensor)
    d2 = arcs[None, :, None, :, 0] * pp[:, None, :, :, 0]
    d2.addcmul_(arcs[None, :, None, :, 1].expand_as(d2), pp[:, None, :, :, 1].expand_as(d2)).mul_(-2.0)
    d2 += (arcs ** 2).sum(-1)[None, :, None, :]
    d2 += (pp ** 2).sum(-1)[:, None]
    d = d2.clamp_min_(0.0).sqrt_()
    d -= (peds[..., 4] + self.radius_m)[:, None, :, None]
    d.masked_fill_(~present[:, None, :, None], CLEAR_CAP_M + 1.0)
    # the nearest pedestrian at each lookahead time (B A S): clearance and its discounted intrusions
    d = d.amin(2)
    ped_min = d.clamp(-0.5, CLEAR_CAP_M)
    ped_contact = ((0.15 - d).clamp_min(0.0) * disc).sum(-1)
    ped_comfort = ((0.8 - d).clamp_min(0.0) ** 2 * disc).sum(-1) * LOOKAHEAD_STEP_S
    # static obstacles: the end points of the nearest scan hits (farther ones cannot be the nearest obstacle of
    # an arc that stays within the horizon), B R 2
    rng, idx = obs["scan"].topk(min(SCAN_POINTS, obs["scan"].shape[-1]), dim=-1, largest=False)
    hit = rng < self.scan_range_m - 1e-3
    pts = rng[..., None] * self.ray_dir[idx]
    dq = torch.cdist(arcs.reshape(1, a * s, 2).expand(b, -1, -1), pts)  # B AS R
    dq = dq.masked_fill(~hit[:, None, :], CLEAR_CAP_M + 1.0).amin(-1).view(b, a, s) - self.radius_m
    obs_min = dq.clamp(-0.5, CLEAR_CAP_M)
    obs_contact = ((0.05 - dq).clamp_min(0.0) * disc).sum(-1)
    obs_near = ((0.25 - dq).clamp_min(0.0) ** 2 * disc).sum(-1)
    # progress: along the global path when the observation has it (the cost-to-go through the best path point,
    # ctg(p) ≈ min_k |p - P_k| + (L - s_k)), else towards the sub-goal (or the goal); and towards the goal
    goal = obs["state"][:, :2]
    sub = obs["subgoal"] if self.subgoal else goal
    end = arcs[None, :, -1]  # 1 A 2
    if self.path:
        pts = obs["path"]  # B P 2
        s_k = self.path_s[: pts.shape[1]]
        reach_end = s_k - torch.linalg.vector_norm(end[:, :, None] - pts[:, None], dim=-1)  # B A P
        reach_now = (s_k - torch.linalg.vector_norm(pts, dim=-1)).amax(-1, keepdim=True)  # B 1
        best = reach_end.argmax(-1)  # B A
        sub_gain = reach_end.amax(-1) - reach_now
        ahead = torch.gather(pts, 1, (best + self.path_lead).clamp_max(pts.shape[1] - 1)[..., None].expand(-1, -1, 2))
        to_sub = ahead - end
    else:
        sub_gain = torch.linalg.vector_norm(sub, dim=-1, keepdim=True) - torch.linalg.vector_norm(sub[:, None] - end, dim=-1)
        to_sub = sub[:, None] - end
    goal_gain = obs["state"][:, 2:3] - torch.linalg.vector_norm(goal[:, None] - end, dim=-1)
    err = torch.atan2(to_sub[..., 1], to_sub[..., 0]) - self.end_heading
    goal_near = torch.linalg.vector_norm(goal[:, None, None] - arcs[None], dim=-1).amin(-1)  # B A
    near = (obs["state"][:, 2:3] < NEAR_GOAL_M).float().expand(-1, a)
    abs_err = torch.atan2(torch.sin(err), torch.cos(err)).abs()
    mode = getattr(self, "heading", "end")
    if mode != "end":  # the smallest error along the arc (init_lookahead)
        # the heading sweeps 0 → rot = ω·T; it passes the target direction phi (from the arc's end point) if phi,
        # measured in the direction of the turn, is within the sweep; else the nearer of the start and the end
        phi = torch.atan2(to_sub[..., 1], to_sub[..., 0])
        rot = self.end_heading.expand_as(phi)
        ahead = torch.where(rot >= 0, torch.remainder(phi, 2 * torch.pi), torch.remainder(-phi, 2 * torch.pi))
        start_err = phi.abs()
        best = torch.where(ahead <= rot.abs(), torch.zeros_like(phi), torch.minimum(start_err, abs_err))
        abs_err = best if mode == "best" else torch.where(self.spin, best, abs_err)
    grid = self.grid_norm[None].expand(b, -1, -1)
    feats = [ped_min, obs_min,
             torch.log1p(torch.stack([ped_contact, ped_comfort, obs_contact, obs_near], -1)),
             torch.stack([torch.cos(err), torch.sin(err), goal_near.clamp_max(CLEAR_CAP_M), near], -1),
             grid,
             # the terms of the linear cost (the last N_LINEAR features): predicted intrusions, progress along
             # the route, heading error away from the goal, approach when near it, speed and turning
             torch.stack([ped_contact.clamp_max(10.0), ped_comfort.clamp_max(10.0), obs_contact.clamp_max(10.0),
                          obs_near.clamp_max(10.0), sub_gain, goal_gain, (1.0 - near) * abs_err,
                          near * (obs["state"][:, 2:3] - goal_near), grid[..., 0], grid[..., 1].abs()], -1)]
    return torch.cat(feats, -1)


class TakeScores(nn.Module):
    """The action logits of a :class:`LookaheadTeacherExtractor`: the first ``n`` features (no parameters)."""

    def __init__(self, n: int) -> None:
        super().__init__()
        self.n = n

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        return latent[..., :self.n]
