"""The lookahead head: a learned cost over the kinematic rollouts of every action of the grid.

:class:`LookaheadHead` is the actor of the lookahead teacher (:class:`rl.networks.LookaheadTeacherExtractor`) and of
the student's lookahead head (:class:`rl.networks.StudentLookaheadExtractor`); the extractor owns it as its
``lookahead`` submodule and hands it its embedding. For each of the A = 5 x 21 (v, ω) commands
(:func:`sim.robot.action_grid`) the head rolls the robot forward along its unicycle arc (fixed buffers) for
:data:`LOOKAHEAD_HORIZON_S`, predicts every observed pedestrian (with constant velocity, or where the pretrained
intention model says it will be: the observation's ``peds_future``), and measures per action
``F`` parameter-free features (:meth:`LookaheadHead.action_features`; all positions in the robot frame at the
current step, x forward, y left, metres; times in seconds; angles in radians). A linear cost over the last
:data:`N_LINEAR` of them plus an MLP over all of them and a context vector from the embedding give each action's
logit (:meth:`LookaheadHead.forward`).

With an occupancy map in the observation (``map_key``: a student's ``bev_occ``, the pretrained BEV's predicted
occupancy of static obstacles and of people now, at +0.5 s and at +1.0 s; or the ``w/o BEV`` ablation's ``occ``,
the occupied cells of the current depth images) the head also samples the map along every arc, each lookahead time
reading the people channel nearest to it, and adds :data:`N_MAP` features (:meth:`LookaheadHead.map_features`): a
second linear cost over them (``map_cost``, fitted by convex regression on top of the inherited cost,
:func:`rl.teacher.fit_map_cost`) and the scorer's input. Removing the BEV then removes what the decision reads.

State-dict keys: the learned layers sit under the head's prefix (``<extractor>.lookahead.context.*``,
``.scorer.*``, ``.linear.*``); the rollout geometry is non-persistent (rebuilt from the policy's JSON), so it is in
no checkpoint. Checkpoints from before the head was a module are mapped by :func:`rl.policy.upgrade_state_dict`.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import torch
import torch.nn.functional as F
from torch import nn

from pipeline.core.errors import ConfigError
from pretrain.i2former import mlp
from sim.robot import RobotConfig, action_grid

LOOKAHEAD_HORIZON_S = 2.0  # rollout horizon of the lookahead layer
LOOKAHEAD_STEP_S = 0.2  # its resolution (plus the next control step itself)
LOOKAHEAD_DISCOUNT_S = 1.5  # time constant of the discount on predicted intrusions
CLEAR_CAP_M = 3.0  # clearances are clipped to [-0.5, this]
SCORE_SCALE = 10.0  # logits = this x the linear path's output + the MLP's: the expert's costs differ by tens of
# nats at τ = 0.1, which the linear path reaches with weights of order one
HEADING_MODES = ("end", "best", "spin")  # the lookahead heading error (LookaheadHead)
SCAN_POINTS = 24  # nearest scan hits the lookahead measures obstacle clearance against
N_LINEAR = 10  # rollout features of the linear cost (the last ones of action_features)
LINEAR_TERMS = ("ped_contact", "ped_comfort", "obs_contact", "obs_near", "subgoal_gain", "goal_gain", "heading_error",
                "goal_approach", "speed", "turn")  # their names, in order (LookaheadHead.action_features)
PED_TERMS = (0, 1)  # the pedestrian terms among them: predicted intrusions into people's contact and comfort zones
PED_CONTACT = LINEAR_TERMS.index("ped_contact") - N_LINEAR  # its index into action_features' last axis (negative)
NEAR_GOAL_M = 0.5  # closer than this to the goal, the cost rewards reaching it instead of the route's heading
N_MAP = 4  # occupancy-map features per action (LookaheadHead.map_features)
MAP_KEYS = ("bev_occ", "occ")  # the maps the head can read: the BEV's predicted occupancy, the depth occupancy
MAP_PED_TIMES_S = (0.0, 0.5, 1.0)  # the times of the people channels 1.. of a ``bev_occ`` map (pretrain.model.TARGETS)
SHIELD_MARGIN_M = 0.02  # the obstacle shield: an arc closer than this to the scan within ``shield_s`` is inadmissible
SHIELD_NATS_PER_M = 1000.0  # ... and its logit is lowered by this many nats per metre of predicted intrusion
PED_SHIELD_MARGIN_M = 0.0  # the people shield: an arc predicted to overlap a predicted person within ``ped_shield_s``


def check_shield_s(value: Any, key: str, optional: bool = False) -> None:
    """The obstacle shield's horizon must be 0 (off) .. :data:`LOOKAHEAD_HORIZON_S` s (or None when ``optional``);
    else one ConfigError naming ``key``."""
    if optional and value is None:
        return
    if not (isinstance(value, (int, float)) and 0.0 <= value <= LOOKAHEAD_HORIZON_S):
        raise ConfigError(f"{key}: expected {'none or ' if optional else ''}0 (off) .. {LOOKAHEAD_HORIZON_S} s, "
                          f"got {value!r}")


def intrusion(clearances: torch.Tensor, margin_m: float) -> torch.Tensor:
    """``... x A`` (m): how far each action's clearances ``... x A x steps`` come inside ``margin_m`` at their
    closest (0 = admissible) — the rule of both shields."""
    return (margin_m - clearances.amin(-1)).clamp_min(0.0)


def ray_directions(rays: int) -> torch.Tensor:
    """``R x 2`` unit directions of a 360° scan's rays in the robot frame (ray k at k·2π/R, as the env's
    ``static_scan`` and :class:`rl.perceive.DepthScan`)."""
    ang = torch.arange(int(rays)) * (2 * torch.pi / int(rays))
    return torch.stack([torch.cos(ang), torch.sin(ang)], -1)


def scan_clearances(arcs: torch.Tensor, scan: torch.Tensor, ray_dir: torch.Tensor, scan_range_m: float,
                    radius_m: float) -> torch.Tensor:
    """``B x A x S`` (m): the robot body's clearance to the obstacles of the range scan ``scan`` ``B x R`` (ray k
    along ``ray_dir[k]``, robot frame; a ray at ``scan_range_m`` hit nothing) at every point of the arcs ``A x S x 2``
    — measured against the end points of the :data:`SCAN_POINTS` nearest hits (farther ones cannot be the nearest
    obstacle of an arc that stays within the horizon); :data:`CLEAR_CAP_M` + 1 - ``radius_m`` where nothing was hit."""
    a, s = arcs.shape[:2]
    b = scan.shape[0]
    rng, idx = scan.topk(min(SCAN_POINTS, scan.shape[-1]), dim=-1, largest=False)
    hit = rng < scan_range_m - 1e-3
    pts = rng[..., None] * ray_dir[idx]  # B R 2
    dq = torch.cdist(arcs.reshape(1, a * s, 2).expand(b, -1, -1), pts)  # B AS R
    return dq.masked_fill(~hit[:, None, :], CLEAR_CAP_M + 1.0).amin(-1).view(b, a, s) - radius_m


def lookahead_times(dt_s: float) -> torch.Tensor:
    """The ``S`` lookahead times (s): the control period, then every :data:`LOOKAHEAD_STEP_S` up to
    :data:`LOOKAHEAD_HORIZON_S` — where the head places the robot and every pedestrian."""
    return torch.cat([torch.tensor([float(dt_s)]),
                      torch.arange(1, int(round(LOOKAHEAD_HORIZON_S / LOOKAHEAD_STEP_S)) + 1) * LOOKAHEAD_STEP_S])


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


class LookaheadHead(nn.Module):
    """Scores every action of the grid by a learned cost over its kinematic rollout (module docstring).

    Fixed geometry (non-persistent buffers, rebuilt from the arguments): ``grid_norm`` ``A x 2`` (v, ω) over the
    robot's limits; ``times`` ``S`` lookahead times (s: the control period ``dt_s``, then every
    :data:`LOOKAHEAD_STEP_S` up to :data:`LOOKAHEAD_HORIZON_S`); ``arcs`` ``A x S x 2`` robot-frame positions (m)
    along each command's arc; ``end_heading`` ``A`` heading at the end of the arc (rad); ``spin`` ``A`` the turns on
    the spot (v = 0); ``disc`` ``S`` the discount on intrusions; ``ray_dir`` ``R x 2`` the scan's unit ray
    directions (robot frame, ray k at k·2π/R); with a ``path`` observation, ``path_s`` ``P`` the arc length (m) of
    each path point. Sizes: ``n_actions`` = A, ``n_feat`` = F = 2·S + 20 (+ :data:`N_MAP` with a map).

    Learned: ``context`` (``base_dim`` embedding → ``context_dim``), ``scorer`` (MLP of ``F + context_dim`` →
    ``score_dim`` → ``score_dim`` → 1) and ``linear`` (the linear cost over the last :data:`N_LINEAR` features).

    Args:
        observation_space: the policy's observations; reads the shapes of ``scan`` (``R``) and ``path`` (``P x 2``,
            optional).
        robot: :class:`sim.robot.RobotConfig` fields (limits, radius, grid); ``None`` = defaults.
        dt_s: the control period (s), the first lookahead time.
        path_spacing_m: the env's spacing of the ``path`` points (m).
        base_dim: the width of the extractor's embedding the context is computed from.
        score_dim, context_dim: widths of the scorer MLP and of the context vector.
        subgoal: read ``obs["subgoal"]`` (robot frame, m) as the progress target when there is no path, else the goal.
        scan_range_m: the scan's maximum range (m); rays at it hit nothing.
        heading: the heading error of the linear cost. ``"end"`` at the end of the 2 s arc (the first checkpoints; a
            turn on the spot at 2 rad/s ends 4 rad away, past the target, so a robot facing a wall may prefer the
            turn away from its route and dither between the two), ``"best"`` the smallest error reached along the
            arc (a turn that passes through the target heading could stop there), ``"spin"`` the smallest error for
            the turns on the spot only (v = 0), the end error for every moving arc. Measured: both remove most
            warehouse stops and triple the shelf collisions, so ``"end"`` stays the default
            (docs/notes/2026-11-lookahead-heading-modes.md).
        scorer_bound: with c, the MLP scorer's output is squashed to ``c · tanh(x / c)`` nats (a student's learned
            correction may re-rank actions, not override a predicted contact); ``None`` = unbounded.
        map_key: the observation's occupancy map the head samples along the arcs (one of :data:`MAP_KEYS`, shape
            ``C x X x Y`` over ``map_bounds``; channel 0 static, channels 1.. people at :data:`MAP_PED_TIMES_S`);
            ``None`` = no map features (the teacher; students trained before the option).
        map_bounds: ``((x_min, x_max), (y_min, y_max))`` of the map (m, robot frame; the BEV grid).
        map_view_deg: read the map only inside this bearing from the heading (deg; the cameras' joint view): cells
            outside it read as 0, like cells outside the map. The pretrained BEV marks what its cameras do not see as
            occupied in the static *and* the people channels, so a cost over the whole map scores turning arcs by
            that artefact (docs/notes/2026-11-pedestrian-hits-untracked-people.md). ``None`` = the whole map.
        shield_s: the obstacle shield's horizon (s; 0 = off). An action whose arc comes closer than
            :data:`SHIELD_MARGIN_M` to the scan's obstacles at a lookahead time up to ``shield_s`` is inadmissible, as
            in DWA's admissible velocities: its logit is lowered by :data:`SHIELD_NATS_PER_M` nats per metre of
            predicted intrusion, so it is chosen only when every action intrudes (then the least intruding). The
            robot can always stop or turn on the spot, so a predicted obstacle contact is the cost's choice, not
            forced: docs/results.md ("Why they fail") found the students choosing arcs they predicted to hit.
        ped_shield_s: the people shield's horizon (s; 0 = off): the same rule against the head's predicted
            pedestrians (an arc whose body comes within :data:`PED_SHIELD_MARGIN_M` of a predicted person's — i.e.
            overlaps it — at a lookahead time up to ``ped_shield_s`` loses :data:`SHIELD_NATS_PER_M` nats per metre),
            so a predicted contact with a person is chosen only when every action has one.
    """

    def __init__(self, observation_space: gym.spaces.Dict, robot: dict[str, Any] | None, dt_s: float,
                 path_spacing_m: float, base_dim: int, score_dim: int, context_dim: int, *, subgoal: bool,
                 scan_range_m: float, heading: str = "end", scorer_bound: float | None = None,
                 map_key: str | None = None, map_bounds: Any = None, shield_s: float = 0.0,
                 ped_shield_s: float = 0.0, map_view_deg: float | None = None) -> None:
        super().__init__()
        check_shield_s(shield_s, "lookahead shield_s")
        check_shield_s(ped_shield_s, "lookahead ped_shield_s")
        if heading not in HEADING_MODES:
            raise ConfigError(f"lookahead heading: expected one of {list(HEADING_MODES)}, got {heading!r}")
        if map_key is not None and map_key not in MAP_KEYS:
            raise ConfigError(f"lookahead map_key: expected one of {list(MAP_KEYS)} or none, got {map_key!r}")
        if map_key is not None and map_key not in observation_space.spaces:
            raise ConfigError(f"lookahead map_key {map_key!r}: the observation has no such key "
                              f"({sorted(observation_space.spaces)})")
        self.heading = heading
        self.subgoal = bool(subgoal)
        self.scan_range_m = float(scan_range_m)

        rc = RobotConfig(**(robot or {}))
        self.radius_m = float(rc.radius_m)
        grid = torch.as_tensor(action_grid(rc), dtype=torch.float32)
        self.n_actions = len(grid)
        times = lookahead_times(dt_s)
        arcs, end = unicycle_arcs(grid, times)
        self.register_buffer("grid_norm", grid / grid.new_tensor([rc.v_max_mps, rc.omega_max_radps]), persistent=False)
        self.register_buffer("times", times, persistent=False)
        self.shield_steps = self.steps_within(shield_s) if shield_s else 0
        self.ped_shield_steps = self.steps_within(ped_shield_s) if ped_shield_s else 0
        self.register_buffer("arcs", arcs, persistent=False)  # A x S x 2
        self.register_buffer("end_heading", end[:, -1], persistent=False)  # A
        self.register_buffer("spin", grid[:, 0].abs() < 1e-6, persistent=False)  # A: the turns on the spot
        self.register_buffer("disc", torch.exp(-times / LOOKAHEAD_DISCOUNT_S), persistent=False)
        self.path = "path" in observation_space.spaces
        if self.path:  # arc length of each path point (the env's path_spacing_m, stored in the policy's net)
            spacing = float(path_spacing_m)
            n_path = observation_space["path"].shape[0]
            self.register_buffer("path_s", spacing * torch.arange(1, n_path + 1, dtype=torch.float32),
                                 persistent=False)
            self.path_lead = max(1, int(round(1.0 / spacing)))  # heading target: 1 m further along the path
        self.register_buffer("ray_dir", ray_directions(observation_space["scan"].shape[0]), persistent=False)
        self.map_key = map_key
        self.n_map = N_MAP if map_key else 0
        if map_key:
            self._init_map(observation_space[map_key].shape, map_bounds, arcs, times, rc.radius_m, map_view_deg)
        self.n_feat = 2 * len(times) + 4 + 4 + 2 + self.n_map + N_LINEAR

        # the learned part: a context vector from the embedding, the MLP scorer, the linear cost
        self.context = nn.Sequential(nn.Linear(base_dim, context_dim), nn.ReLU())
        self.scorer = mlp([self.n_feat + context_dim, score_dim, score_dim, 1], last_act=False)
        self.linear = nn.Linear(N_LINEAR, 1)  # the linear cost over the last N_LINEAR rollout features
        if map_key:  # the linear cost over the map features (zero until fitted: the inherited cost unchanged)
            self.map_cost = nn.Linear(N_MAP, 1, bias=False)
            nn.init.zeros_(self.map_cost.weight)
        self.scorer_bound = float(scorer_bound) if scorer_bound else None

    def _init_map(self, shape: tuple[int, ...], bounds: Any, arcs: torch.Tensor, times: torch.Tensor,
                  radius_m: float, view_deg: float | None = None) -> None:
        """Buffers of the map sampling: ``map_uv`` ``1 x A x S x 2`` the arcs' points in ``grid_sample``
        coordinates (the map's last axis is y, the one before it x; outside the map = unknown, read as free),
        ``map_ped_ch`` ``S`` the people channel nearest in time to each lookahead time (none for a 1-channel map),
        the robot footprint's max-pool kernel in cells and, with ``view_deg``, ``map_view`` ``1 x 1 x X x Y`` (1 for
        the cells whose centre lies within ``view_deg`` of the heading, else 0)."""
        try:
            (x0, x1), (y0, y1) = ((float(a), float(b)) for a, b in bounds)
        except (TypeError, ValueError):
            raise ConfigError(f"lookahead map_bounds: expected ((x_min, x_max), (y_min, y_max)) in m, got {bounds!r}"
                              ) from None
        if not (x1 > x0 and y1 > y0):
            raise ConfigError(f"lookahead map_bounds: expected max > min on both axes, got {bounds!r}")
        c, nx, ny = shape
        if not 1 <= c <= 1 + len(MAP_PED_TIMES_S):
            raise ConfigError(f"lookahead map: expected 1 to {1 + len(MAP_PED_TIMES_S)} channels (static, then people "
                              f"at {list(MAP_PED_TIMES_S)} s), got {c}")
        u = 2.0 * (arcs[..., 1] - y0) / (y1 - y0) - 1.0
        v = 2.0 * (arcs[..., 0] - x0) / (x1 - x0) - 1.0
        self.register_buffer("map_uv", torch.stack([u, v], -1)[None], persistent=False)
        cell = min((x1 - x0) / nx, (y1 - y0) / ny)
        self.map_kernel = 2 * max(1, int(math.ceil(radius_m / cell - 0.5))) + 1  # cells within the robot's radius
        if c > 1:
            ped_t = torch.tensor(MAP_PED_TIMES_S[: c - 1])
            ch = 1 + (times[:, None] - ped_t[None]).abs().argmin(-1)
        else:
            ch = torch.zeros(len(times), dtype=torch.long)
        self.register_buffer("map_ped_ch", ch, persistent=False)
        self.map_people = c > 1
        self.map_view_deg = None if view_deg is None else float(view_deg)
        if view_deg is not None:
            if not (isinstance(view_deg, int | float) and 0.0 < view_deg <= 180.0):
                raise ConfigError(f"lookahead map_view_deg: expected none or a bearing in (0, 180] deg, got {view_deg!r}")
            xc = x0 + (torch.arange(nx) + 0.5) * (x1 - x0) / nx
            yc = y0 + (torch.arange(ny) + 0.5) * (y1 - y0) / ny
            bearing = torch.atan2(yc[None, :], xc[:, None]).abs()
            self.register_buffer("map_view", (bearing <= math.radians(view_deg)).float()[None, None],
                                 persistent=False)

    def forward(self, base: torch.Tensor, obs: dict[str, torch.Tensor],
                action_features: torch.Tensor | None = None) -> torch.Tensor:
        """``B x A`` logits (nats): :data:`SCORE_SCALE` x the linear cost + the (bounded) MLP scorer over each
        action's rollout features and the context of ``base`` (``B x base_dim``). ``action_features``: the
        precomputed ``B x A x F`` :meth:`action_features` of ``obs`` (as cloning and PPO cache them)."""
        feats = self.action_features(obs) if action_features is None else action_features
        ctx = self.context(base)[:, None].expand(-1, feats.shape[1], -1)
        learned = self.scorer(torch.cat([feats, ctx], -1))
        if self.scorer_bound:  # c · tanh(x / c): the learned part may re-rank actions, not override predicted contacts
            learned = self.scorer_bound * torch.tanh(learned / self.scorer_bound)
        logits = (SCORE_SCALE * self.fitted_cost(feats) + learned).squeeze(-1)
        if self.shield_steps:
            logits = logits - SHIELD_NATS_PER_M * self.shield_intrusion(feats)
        if self.ped_shield_steps:
            logits = logits - SHIELD_NATS_PER_M * intrusion(
                self.pedestrian_clearances(feats, self.ped_shield_steps), PED_SHIELD_MARGIN_M)
        return logits

    def steps_within(self, seconds: float) -> int:
        """How many lookahead times are at most ``seconds`` from now."""
        return int((self.times <= float(seconds) + 1e-6).sum())

    def obstacle_clearances(self, feats: torch.Tensor, steps: int) -> torch.Tensor:
        """``B x A x steps`` (m): each action's predicted clearance to the scan's obstacles at its first ``steps``
        lookahead times, read from its :meth:`action_features` ``feats``."""
        s = len(self.times)
        return feats[..., s:s + steps]

    def pedestrian_clearances(self, feats: torch.Tensor, steps: int) -> torch.Tensor:
        """``B x A x steps`` (m): each action's predicted clearance to the nearest predicted pedestrian at its first
        ``steps`` lookahead times (body to body, clipped to [-0.5, :data:`CLEAR_CAP_M`]), from ``feats``."""
        return feats[..., :steps]

    def shield_intrusion(self, feats: torch.Tensor) -> torch.Tensor:
        """``B x A`` (m): how far each action's arc comes inside :data:`SHIELD_MARGIN_M` of the scan's obstacles at
        the lookahead times up to ``shield_s`` (0 = admissible), from the obstacle clearances of ``feats``."""
        return intrusion(self.obstacle_clearances(feats, self.shield_steps), SHIELD_MARGIN_M)

    def fitted_cost(self, feats: torch.Tensor) -> torch.Tensor:
        """``B x A x 1``: the linear cost over the last :data:`N_LINEAR` features, plus the map cost over the
        :data:`N_MAP` before them when the head reads a map (in units of :data:`SCORE_SCALE` nats)."""
        out = self.linear(feats[..., -N_LINEAR:])
        if self.n_map:
            out = out + self.map_cost(feats[..., -N_LINEAR - N_MAP:-N_LINEAR])
        return out

    @torch.no_grad()
    def map_features(self, occ: torch.Tensor) -> torch.Tensor:
        """``B x A x`` :data:`N_MAP` features of the occupancy map ``occ`` ``B x C x X x Y`` (probabilities or 0/1)
        along every arc: the static channel's maximum and discounted mean over the lookahead times, the people
        channels' (each time reading the nearest channel in time) maximum and discounted mean (zero for a
        1-channel map). The map is masked to ``map_view_deg`` (when set) and max-pooled over the robot's footprint
        first."""
        m = occ.float() * self.map_view if self.map_view_deg is not None else occ.float()
        m = F.max_pool2d(m, self.map_kernel, stride=1, padding=self.map_kernel // 2)
        b = m.shape[0]
        a, s = self.map_uv.shape[1:3]
        v = F.grid_sample(m, self.map_uv.expand(b, -1, -1, -1), mode="bilinear", padding_mode="zeros",
                          align_corners=False)  # B C A S
        w = self.disc / self.disc.sum()
        static = v[:, 0]
        if self.map_people:
            people = torch.gather(v, 1, self.map_ped_ch.view(1, 1, 1, s).expand(b, 1, a, s))[:, 0]
        else:
            people = torch.zeros_like(static)
        return torch.stack([static.amax(-1), (static * w).sum(-1), people.amax(-1), (people * w).sum(-1)], -1)

    @property
    def input_keys(self) -> tuple[str, ...]:
        """The observation keys :meth:`action_features` may read (those an observation lacks it does without); the
        rest of an observation — a student's ``bev`` features, its joints — does not change the features, so
        :func:`rl.teacher.lookahead_feature_cache` converts only these."""
        return ("state", "scan", "peds", "peds_future", *(("path",) if self.path else ()),
                *(("subgoal",) if self.subgoal else ()), *((self.map_key,) if self.map_key else ()))

    @torch.no_grad()
    def action_features(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """``B x A x F`` parameter-free rollout features of every action (see
        :class:`rl.networks.LookaheadTeacherExtractor`). Reads ``obs["state"]`` ``B x 5`` (goal x, y, distance in m;
        velocity), ``obs["scan"]`` ``B x R`` (m), ``obs["peds"]`` ``B x K x 6`` (x, y in m, vx, vy in m/s, radius in
        m, present; without it nobody is predicted), optionally ``obs["peds_future"]`` ``B x K x S x 2`` (m: where
        each of them will be at the lookahead :attr:`times`, from the pretrained intention model,
        :class:`rl.perceive.Perception`; without it they are predicted at constant velocity), ``obs["path"]``
        ``B x P x 2`` or ``obs["subgoal"]`` ``B x 2`` (m) when the head was built with them; all in the robot
        frame."""
        arcs, disc = self.arcs, self.disc  # A S 2, S
        b = obs["state"].shape[0]
        a, s = arcs.shape[:2]
        # pedestrians: B K S 2, the intention model's prediction or constant velocity (a student without pose input
        # has none)
        peds = obs["peds"] if "peds" in obs else obs["state"].new_zeros(b, 1, 6)
        present = peds[..., 5] > 0.5
        if "peds_future" in obs:
            pp = obs["peds_future"]
            if pp.shape[-2] != s:
                raise ConfigError(f"peds_future: expected {s} lookahead times per pedestrian, got {pp.shape[-2]}")
        else:
            pp = peds[:, :, None, :2] + self.times[None, None, :, None] * peds[:, :, None, 2:4]
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
        dq = scan_clearances(arcs, obs["scan"], self.ray_dir, self.scan_range_m, self.radius_m)  # B A S
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
            ahead = torch.gather(pts, 1,
                                 (best + self.path_lead).clamp_max(pts.shape[1] - 1)[..., None].expand(-1, -1, 2))
            to_sub = ahead - end
        else:
            sub_gain = (torch.linalg.vector_norm(sub, dim=-1, keepdim=True)
                        - torch.linalg.vector_norm(sub[:, None] - end, dim=-1))
            to_sub = sub[:, None] - end
        goal_gain = obs["state"][:, 2:3] - torch.linalg.vector_norm(goal[:, None] - end, dim=-1)
        err = torch.atan2(to_sub[..., 1], to_sub[..., 0]) - self.end_heading
        goal_near = torch.linalg.vector_norm(goal[:, None, None] - arcs[None], dim=-1).amin(-1)  # B A
        near = (obs["state"][:, 2:3] < NEAR_GOAL_M).float().expand(-1, a)
        abs_err = torch.atan2(torch.sin(err), torch.cos(err)).abs()
        if self.heading != "end":  # the smallest error along the arc (class docstring, ``heading``)
            # the heading sweeps 0 → rot = ω·T; it passes the target direction phi (from the arc's end point) if
            # phi, measured in the direction of the turn, is within the sweep; else the nearer of the start and end
            phi = torch.atan2(to_sub[..., 1], to_sub[..., 0])
            rot = self.end_heading.expand_as(phi)
            ahead = torch.where(rot >= 0, torch.remainder(phi, 2 * torch.pi), torch.remainder(-phi, 2 * torch.pi))
            start_err = phi.abs()
            best = torch.where(ahead <= rot.abs(), torch.zeros_like(phi), torch.minimum(start_err, abs_err))
            abs_err = best if self.heading == "best" else torch.where(self.spin, best, abs_err)
        grid = self.grid_norm[None].expand(b, -1, -1)
        feats = [ped_min, obs_min,
                 torch.log1p(torch.stack([ped_contact, ped_comfort, obs_contact, obs_near], -1)),
                 torch.stack([torch.cos(err), torch.sin(err), goal_near.clamp_max(CLEAR_CAP_M), near], -1),
                 grid,
                 *([self.map_features(obs[self.map_key])] if self.n_map else []),
                 # the terms of the linear cost (the last N_LINEAR features): predicted intrusions, progress along
                 # the route, heading error away from the goal, approach when near it, speed and turning
                 torch.stack([ped_contact.clamp_max(10.0), ped_comfort.clamp_max(10.0), obs_contact.clamp_max(10.0),
                              obs_near.clamp_max(10.0), sub_gain, goal_gain, (1.0 - near) * abs_err,
                              near * (obs["state"][:, 2:3] - goal_near), grid[..., 0], grid[..., 1].abs()], -1)]
        return torch.cat(feats, -1)


class ObstacleShield(nn.Module):
    """The lookahead head's obstacle shield for an actor that has no rollouts of its own (the paper's MLP head,
    ``net.head = "mlp"``): the same arcs of the action grid, the same clearances to the perceived scan
    (:func:`scan_clearances`) and the same rule (:meth:`LookaheadHead.shield_intrusion`: an action whose arc comes
    closer than :data:`SHIELD_MARGIN_M` to the scan within ``shield_s`` loses :data:`SHIELD_NATS_PER_M` nats per
    metre of intrusion), as a penalty to subtract from the actor's logits. No weights: a parameter-free rule on top of
    a learned head (DWA's admissible velocities), so a student with it is no longer "every weight decides".

    Args:
        robot: the robot (:class:`sim.robot.RobotConfig` or its fields; its grid is the policy's action grid).
        dt_s: the control period (the first lookahead time).
        rays, scan_range_m: the scan's layout (the env's ``scan_rays`` / ``scan_range_m``).
        shield_s: the horizon (s, > 0 .. :data:`LOOKAHEAD_HORIZON_S`).
    """

    def __init__(self, robot: RobotConfig | dict[str, Any] | None, dt_s: float, rays: int, scan_range_m: float,
                 shield_s: float) -> None:
        super().__init__()
        check_shield_s(shield_s, "obstacle shield shield_s")
        if not shield_s > 0.0:
            raise ConfigError(f"obstacle shield shield_s: expected > 0 s (0 is no shield: build none), got {shield_s!r}")
        rc = robot if isinstance(robot, RobotConfig) else RobotConfig(**(robot or {}))
        times = lookahead_times(dt_s)
        times = times[times <= float(shield_s) + 1e-6]
        arcs, _ = unicycle_arcs(torch.as_tensor(action_grid(rc), dtype=torch.float32), times)
        self.register_buffer("times", times, persistent=False)  # S: the lookahead times up to shield_s
        self.register_buffer("arcs", arcs, persistent=False)  # A x S x 2
        self.register_buffer("ray_dir", ray_directions(rays), persistent=False)
        self.scan_range_m, self.radius_m = float(scan_range_m), float(rc.radius_m)

    @torch.no_grad()
    def forward(self, scan: torch.Tensor) -> torch.Tensor:
        """``B x A`` (nats, ≥ 0): what to subtract from the logits of the scans ``scan`` ``B x R`` (m)."""
        clear = self.action_features({"scan": scan})
        return SHIELD_NATS_PER_M * intrusion(clear.clamp(-0.5, CLEAR_CAP_M), SHIELD_MARGIN_M)

    # the lookahead head's interface for reading predicted obstacle clearances (evaluation.failures --replay)
    def steps_within(self, seconds: float) -> int:
        """How many of the shield's lookahead times are at most ``seconds`` from now."""
        return int((self.times <= float(seconds) + 1e-6).sum())

    @torch.no_grad()
    def action_features(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """``B x A x S`` (m): each action's clearance to the obstacles of ``obs["scan"]`` at the shield's lookahead
        times (what :meth:`forward` penalises)."""
        return scan_clearances(self.arcs, obs["scan"], self.ray_dir, self.scan_range_m, self.radius_m)

    def obstacle_clearances(self, feats: torch.Tensor, steps: int) -> torch.Tensor:
        """``B x A x steps`` (m): the first ``steps`` lookahead times of :meth:`action_features`."""
        return feats[..., :steps]
