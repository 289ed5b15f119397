"""Policy networks as stable-baselines3 features extractors (the actor/critic heads are SB3's).

Student (the paper's policy, §III-B/C), variants :data:`VARIANTS`::

    full    z = φ_f([φ_bev(s_bev), I²Former(poses, mask, s), φ_s(s)])
    no_i2   z = φ_f([φ_bev(s_bev),                           φ_s(s)])          ablation "w/o I²"
    no_bev  z = φ_f([φ_occ(occ),   I²Former(poses, mask, s), φ_s(s)])          ablation "w/o BEV"

With ``net.head = "mlp_intention"`` (the same MLP head) the I²Former's people come from the *pretrained* intention
model instead of being learned from raw poses by cloning: the variants with poses read the tracks of the people they
detect and each track's forecast by the frozen intention model (``peds``, ``peds_future``: :mod:`rl.perceive`; its
pose encoder and IntentFormer were trained on the recorded dataset by ``make pretrain``), and
:class:`ForecastI2Former` lets the robot query them (the InteractFormer, learned by cloning). ``no_i2`` is unchanged:
no I²Former output, no tracks, no forecasts.

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
(measured: docs/notes/2026-11-teacher-flat-mlp-vs-set-encoder.md). ``encoder="flat"`` keeps the plain
concatenation.
``encoder="lookahead"`` adds the lookahead head (:mod:`rl.lookahead`), which scores every action of the grid by a
learned cost over its kinematic rollout; the student's ``net.head = "lookahead"`` owns the same head.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import torch
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from pipeline.core.errors import ConfigError
from pretrain.i2former import (
    POSE_SCALE_M,
    STATE_DIM,
    AttnPool,
    I2Former,
    I2FormerConfig,
    InteractFormer,
    mlp,
    normalise_state,
)
from rl.lookahead import LookaheadHead

VARIANTS = ("full", "no_i2", "no_bev")
VARIANT_LABELS = {"full": "iCrowdNav (full)", "no_i2": "w/o I²", "no_bev": "w/o BEV"}
# the student's actor: SB3's MLP on z (the paper's), the same with the pretrained intention model's tracks and
# forecasts as the I²Former's people (module docstring), or the lookahead scorer
STUDENT_HEADS = ("mlp", "mlp_intention", "lookahead")
MLP_HEADS = ("mlp", "mlp_intention")  # the heads whose actor is SB3's MLP on z


TEACHER_ENCODERS = ("set", "flat", "lookahead")
SUBGOAL_SCALE_M = 2.0  # the privileged sub-goal's scale (its lookahead along the global path)


def teacher_extractor_class(encoder: str) -> type[BaseFeaturesExtractor]:
    """The teacher's features extractor for ``net["encoder"]`` (checkpoints without the key are "flat")."""
    if encoder not in TEACHER_ENCODERS:
        raise ConfigError(f"teacher.net.encoder: expected one of {list(TEACHER_ENCODERS)}, got {encoder!r}")
    return {"set": SetTeacherExtractor, "flat": TeacherExtractor, "lookahead": LookaheadTeacherExtractor}[encoder]


def variant_keys(variant: str, head: str = "mlp", map_cost: bool = False) -> tuple[str, ...]:
    """The observation keys a student variant consumes (with the ``lookahead`` head also its perceived ``scan`` and,
    for variants with poses, the pedestrian tracks ``peds``: :mod:`rl.perceive`; with ``map_cost`` a variant with
    ``bev`` also reads the BEV's predicted occupancy ``bev_occ``, ``no_bev`` its depth occupancy ``occ``; with the
    ``mlp_intention`` head a variant with poses reads the tracks ``peds`` and the intention model's forecasts
    ``peds_future`` in place of the raw poses)."""

    if variant not in VARIANTS:
        raise ConfigError(f"variant: expected one of {list(VARIANTS)}, got {variant!r}")
    if head not in STUDENT_HEADS:
        raise ConfigError(f"net.head: expected one of {list(STUDENT_HEADS)}, got {head!r}")
    keys = {"full": ("bev", "poses", "pose_mask", "state"), "no_i2": ("bev", "state"),
            "no_bev": ("occ", "poses", "pose_mask", "state")}[variant]
    if head == "mlp_intention" and "poses" in keys:
        keys = tuple(k for k in keys if k not in ("poses", "pose_mask", "state")) + ("peds", "peds_future", "state")
    if head == "lookahead":
        keys += ("scan",) + (("peds",) if "poses" in keys else ()) + (("bev_occ",) if map_cost and "bev" in keys
                                                                    else ())
    return keys


def check_i2_dropout(value: Any) -> None:
    """``train.net.i2_dropout`` must be a probability in [0, 1) (:class:`StudentExtractor`)."""
    if not (isinstance(value, int | float) and not isinstance(value, bool) and 0.0 <= value < 1.0):
        raise ConfigError(f"train.net.i2_dropout: expected a probability in [0, 1), got {value!r}")


def map_key(variant: str, map_cost: bool) -> str | None:
    """The occupancy map a student's lookahead head samples along its arcs with ``map_cost``: the pretrained BEV's
    prediction (``bev_occ``) for variants with it, the depth occupancy (``occ``, the ``w/o BEV`` substitute) else."""
    if not map_cost:
        return None
    return "bev_occ" if "bev" in variant_keys(variant) else "occ"


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


class ForecastI2Former(nn.Module):
    """The I²Former of the ``mlp_intention`` head (module docstring): ``peds`` ``B x K x 6`` ([x, y, vx, vy, r,
    present], robot frame) + ``peds_future`` ``B x K x S x 2`` (the frozen intention model's forecast positions) +
    ``s`` → ``z_interact`` ``B x dim``.

    Each present track is one person token, φ_t([x, y, v_x, v_y, forecast displacements from now]) (lengths divided
    by :data:`pretrain.i2former.POSE_SCALE_M`); the robot's φ_sp(s) queries the tokens through the InteractFormer
    (:class:`pretrain.i2former.InteractFormer`: its empty-crowd key, absent tracks masked). The pose encoder and
    IntentFormer of the paper's I²Former are the intention model's, pretrained and frozen (their output reaches the
    policy as the forecast); φ_t, φ_sp and the InteractFormer are learned with the policy. Invariant to the order of
    the tracks."""

    def __init__(self, cfg: I2FormerConfig, horizons: int) -> None:
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        d = cfg.dim
        self.token = mlp([4 + 2 * horizons, d, d])  # φ_t
        self.state_encoder = mlp([STATE_DIM, d, d])  # φ_sp
        self.interact = InteractFormer(d, cfg.heads, cfg.ffn_mult)

    @property
    def out_dim(self) -> int:
        return self.cfg.dim

    def forward(self, peds: torch.Tensor, future: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        peds, future = peds.float(), future.float()
        now = peds[..., :2]
        ahead = (future - now.unsqueeze(-2)) / POSE_SCALE_M
        x = torch.cat([now / POSE_SCALE_M, peds[..., 2:4], ahead.flatten(-2)], -1)
        e = self.state_encoder(normalise_state(state.float()))
        return self.interact(e, self.token(x), peds[..., 5] > 0.5)


class StudentExtractor(BaseFeaturesExtractor):
    """The visual policy's state embedding ``z`` for one variant (see the module docstring); ``people``: what its
    I²Former reads — ``poses`` (the paper's) or ``forecasts`` (the ``mlp_intention`` head's tracks and forecasts,
    :class:`ForecastI2Former`). ``i2_dropout`` (``train.net.i2_dropout``): in training mode (cloning, PPO updates)
    each sample's I²Former output is zeroed with this probability — modality dropout, so that the fused layers also
    learn to decide from the map and the state alone; acting and the held-out losses use every input."""

    def __init__(self, observation_space: gym.spaces.Dict, variant: str = "full", bev_dim: int = 256,
                 bev_width: int = 32, state_dim: int = 64, fused_dim: int = 256,
                 i2former: dict[str, Any] | None = None, people: str = "poses", i2_dropout: float = 0.0) -> None:
        if people not in ("poses", "forecasts"):
            raise ConfigError(f"student extractor people: expected 'poses' or 'forecasts', got {people!r}")
        check_i2_dropout(i2_dropout)
        keys = variant_keys(variant, "mlp_intention" if people == "forecasts" else "mlp")
        missing = [k for k in keys if k not in observation_space.spaces]
        if missing:
            raise ConfigError(f"variant {variant!r} needs observation keys {missing}, the env gives "
                              f"{sorted(observation_space.spaces)}")
        super().__init__(observation_space, fused_dim)
        self.variant = variant
        self.i2_dropout = float(i2_dropout)
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
        elif "peds_future" in keys:
            self.i2former = ForecastI2Former(I2FormerConfig(**(i2former or {})),
                                             observation_space["peds_future"].shape[1])
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
            if isinstance(self.i2former, ForecastI2Former):
                z_i2 = self.i2former(obs["peds"], obs["peds_future"], obs["state"])
            else:
                z_i2 = self.i2former(obs["poses"], obs["pose_mask"] > 0.5, obs["state"])
            if self.training and self.i2_dropout > 0.0:  # modality dropout (class docstring)
                z_i2 = z_i2 * (torch.rand(len(z_i2), 1, device=z_i2.device) >= self.i2_dropout).to(z_i2.dtype)
            parts.append(z_i2)
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
    cloned from the privileged teacher learned to, and collided more: docs/notes/2026-11-lookahead-student-variants.md).
    The first ``A`` features are the logits (:class:`rl.policy.ScoredPolicy`), the rest is ``z``. The head is the
    submodule ``lookahead`` (:class:`rl.lookahead.LookaheadHead`)."""

    def __init__(self, observation_space: gym.spaces.Dict, variant: str = "full", robot: dict[str, Any] | None = None,
                 dt_s: float = 0.1, scan_range_m: float = 10.0, score_dim: int = 64, context_dim: int = 32,
                 scorer_bound: float | None = None, heading: str = "end", map_cost: bool = False,
                 map_bounds: Any = None, shield_s: float = 0.0, ped_shield_s: float = 0.0,
                 map_view_deg: float | None = None, **kwargs: Any) -> None:
        super().__init__(observation_space, variant, **kwargs)
        missing = [k for k in variant_keys(variant, "lookahead", map_cost) if k not in observation_space.spaces]
        if missing:
            raise ConfigError(f"the lookahead head of variant {variant!r} needs observation keys {missing}")
        base_dim = self._features_dim
        self.lookahead = LookaheadHead(observation_space, robot, dt_s, 0.25, base_dim, score_dim, context_dim,
                                       subgoal=False, scan_range_m=scan_range_m, heading=heading,
                                       scorer_bound=scorer_bound, map_key=map_key(variant, map_cost),
                                       map_bounds=map_bounds, shield_s=shield_s, ped_shield_s=ped_shield_s,
                                       map_view_deg=map_view_deg)
        self._features_dim = self.lookahead.n_actions + base_dim

    def action_features(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """``B x A x F`` rollout features of every action from the perceived ``peds`` / ``scan`` and the goal
        (:meth:`rl.lookahead.LookaheadHead.action_features`)."""
        return self.lookahead.action_features(obs)

    def forward(self, obs: dict[str, torch.Tensor], action_features: torch.Tensor | None = None) -> torch.Tensor:
        """``B x (A + z)``: the action logits, then ``z`` (``action_features``: precomputed, as cloning caches them)."""
        base = super().forward(obs)
        return torch.cat([self.lookahead(base, obs, action_features), base], -1)


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
class LookaheadTeacherExtractor(SetTeacherExtractor):
    """The set encoder's context plus a kinematic *lookahead layer* that scores every action of the grid (its
    submodule ``lookahead``, :class:`rl.lookahead.LookaheadHead`, which holds the rollout geometry and the scorer).

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
                 context_dim: int = 32, heading: str = "end", shield_s: float = 0.0,
                 ped_shield_s: float = 0.0) -> None:
        super().__init__(observation_space, scan_range_m, ped_scale_m)
        base_dim = self._features_dim
        self.lookahead = LookaheadHead(observation_space, robot, dt_s, path_spacing_m, base_dim, score_dim,
                                       context_dim, subgoal=self.subgoal, scan_range_m=scan_range_m, heading=heading,
                                       shield_s=shield_s, ped_shield_s=ped_shield_s)
        self._features_dim = self.lookahead.n_actions + base_dim

    def action_features(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """``B x A x F`` parameter-free rollout features of every action (class docstring;
        :meth:`rl.lookahead.LookaheadHead.action_features`)."""
        return self.lookahead.action_features(obs)

    def forward(self, obs: dict[str, torch.Tensor], action_features: torch.Tensor | None = None) -> torch.Tensor:
        """``B x (A + base)``: the action logits, then the set encoder's embedding (``action_features``: the
        precomputed :meth:`action_features` of ``obs``, as cloning caches them)."""
        base = super().forward(obs)
        return torch.cat([self.lookahead(base, obs, action_features), base], -1)


class TakeScores(nn.Module):
    """The action logits of a :class:`LookaheadTeacherExtractor`: the first ``n`` features (no parameters)."""

    def __init__(self, n: int) -> None:
        super().__init__()
        self.n = n

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        return latent[..., :self.n]
