"""Pedestrians: a vectorised Helbing social-force model plus the intention behaviour that bodies announce.

Forces (Helbing & Molnár 1995; anisotropy after Helbing et al. 2000), per pedestrian ``i`` (accelerations,
m/s²)::

    f_goal  = (v0_i · e_i − v_i) / tau
    f_ped   = Σ_j A_p · exp((r_i + r_j − d_ij) / B_p) · n_ij · w(φ_ij),  w = λ + (1 − λ)(1 + cos φ_ij)/2
    f_wall  = A_w · exp((r_i − d_iW) / B_w) · n_iW            (nearest obstacle surface, from the
                                                              scene's clearance grid and its gradient)
    f_robot = A_r · exp((r_i + ρ − d_iR) / B_r) · n_iR · w    (only if pedestrians react to the robot)

with ``n`` the unit vector pointing away from the other agent / surface and ``φ`` the angle between ``v_i``
and ``−n``. Speeds are capped at 1.3·v0. After each integration step a hard constraint pushes anyone who ended
up closer than their radius to an obstacle back out, so nobody walks through walls.

Intention (what the articulated bodies show): a pedestrian decides on its next goal *before* it walks there.
When a new goal is drawn (on approaching the current one, after standing idle, on a random change of mind, or
when stuck), it becomes ``pending`` for a lead time drawn from ``[lead_min_s, lead_max_s]`` (0.3–1.0 s by
default); during the lead the head and torso already turn toward the pending goal while the feet still walk to
the old one; then the pending goal becomes the active one and the walking direction follows through the
relaxation time ``tau``.

Scripted pedestrians (:class:`ScriptedPed`, from a scenario file: :mod:`sim.scenario`) follow the same forces and
show the same cue: each stands at its start until its trigger fires (a time, or the robot coming within a distance
of a point), then announces its first waypoint for ``lead_s`` (head and torso turn, feet still) and walks; ``lead_s``
before it reaches a waypoint it announces the next one, so the walking direction changes at the waypoint while the
head has led by ``lead_s``. After the last waypoint it stands. Every trigger and turn cue is logged in
:attr:`Crowd.events` (the onset of the cue, for the robot's reaction time). ``cue=False`` keeps the walk and its
timing and drops the announcement the reaction is timed from (every turn's; the start's when the walk is one straight
leg): the head and torso look where the feet go (a scenario's no-cue twin). They are appended after the random
pedestrians (indices ``n_random ..``), drawing nothing from the random stream.

:func:`social_force_reference` is the plain per-agent loop the vectorised :meth:`Crowd.social_forces` is
tested and benchmarked against.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.core.errors import ConfigError
from sim.geometry import wrap_angle
from sim.scene import SceneLayout

WALK, IDLE = 0, 1
ARRIVED_M = 0.3  # a scripted pedestrian has reached its last waypoint within this distance


@dataclass(frozen=True)
class ScriptedPed:
    """A pedestrian whose route and start are scripted (world frame, m, m/s, s)."""

    start: tuple[float, float]
    waypoints: tuple[tuple[float, float], ...]  # walked in order; the last is where it stops
    speed_mps: float = 1.0
    lead_s: float = 0.7  # the cue: head and torso turn this long before the walking direction does
    trigger_time_s: float | None = None  # starts at this time ...
    trigger_within_m: float | None = None  # ... or when the robot comes this close to ``trigger_point``
    trigger_point: tuple[float, float] | None = None  # (default: its start)
    cue: bool = True  # False: the head and torso do not lead (the same walk, unannounced: a scenario's no-cue twin)

    def fires(self, time_s: float, robot_xy: np.ndarray | None) -> bool:
        """Whether the trigger fires now (no trigger: at once)."""
        if self.trigger_time_s is not None and time_s + 1e-9 >= self.trigger_time_s:
            return True
        if self.trigger_within_m is not None and robot_xy is not None:
            p = self.trigger_point if self.trigger_point is not None else self.start
            return math.hypot(robot_xy[0] - p[0], robot_xy[1] - p[1]) <= self.trigger_within_m
        return self.trigger_time_s is None and self.trigger_within_m is None


def norm2d(v: np.ndarray) -> np.ndarray:
    """Length of 2-vectors along the last axis (``np.hypot`` is much cheaper than ``linalg.norm`` here)."""
    return np.hypot(v[..., 0], v[..., 1])


@dataclass
class CrowdConfig:
    """Social-force and behaviour parameters (units in the names)."""

    speed_mean_mps: float = 1.0  # preferred walking speed, mean
    speed_std_mps: float = 0.15  # and spread (clipped to [0.5, 1.5])
    tau_s: float = 0.5  # relaxation time of the goal force
    ped_a_mps2: float = 2.5  # pedestrian repulsion strength
    ped_b_m: float = 0.35  # pedestrian repulsion range
    anisotropy: float = 0.35  # λ: weight of interactions behind the walker
    wall_a_mps2: float = 6.0  # obstacle repulsion strength
    wall_b_m: float = 0.15  # obstacle repulsion range
    robot_a_mps2: float = 3.5  # robot repulsion strength
    robot_b_m: float = 0.5  # robot repulsion range
    react_to_robot: bool = True  # whether pedestrians see and avoid the robot
    interaction_range_m: float = 4.0  # pairs farther than this exert no force
    goal_reached_m: float = 1.0  # a new goal is chosen within this distance of the current one
    goal_distance_m: tuple[float, float] = (2.0, 9.0)  # range of distances to newly drawn goals
    lead_min_s: float = 0.3  # head/torso turn this long before the walking direction changes ...
    lead_max_s: float = 1.0  # ... up to this long
    idle_prob: float = 0.25  # chance to stand still on reaching a goal
    idle_s: tuple[float, float] = (1.0, 4.0)  # how long an idle stop lasts
    turn_rate_hz: float = 0.05  # rate of spontaneous changes of mind while walking (per second)
    stuck_s: float = 3.0  # walking slower than 0.15 m/s for this long draws a new goal

    def validate(self) -> None:
        positive = ("speed_mean_mps", "tau_s", "ped_b_m", "wall_b_m", "robot_b_m", "interaction_range_m",
                    "goal_reached_m", "stuck_s")
        for k in positive:
            if not getattr(self, k) > 0:
                raise ConfigError(f"crowd.{k}: expected > 0, got {getattr(self, k)}")
        for k in ("speed_std_mps", "ped_a_mps2", "wall_a_mps2", "robot_a_mps2", "turn_rate_hz"):
            if getattr(self, k) < 0:
                raise ConfigError(f"crowd.{k}: expected >= 0, got {getattr(self, k)}")
        if not 0 <= self.anisotropy <= 1 or not 0 <= self.idle_prob <= 1:
            raise ConfigError(f"crowd.anisotropy / idle_prob: expected values in [0, 1], got "
                              f"{self.anisotropy} / {self.idle_prob}")
        if not 0 <= self.lead_min_s <= self.lead_max_s:
            raise ConfigError(f"crowd lead time: expected 0 <= lead_min_s <= lead_max_s, got "
                              f"[{self.lead_min_s}, {self.lead_max_s}]")
        for k in ("goal_distance_m", "idle_s"):
            lo, hi = getattr(self, k)
            if not 0 <= lo <= hi:
                raise ConfigError(f"crowd.{k}: expected 0 <= min <= max, got [{lo}, {hi}]")


class Crowd:
    """State and dynamics of ``n`` pedestrians in one scene layout (all arrays world frame, SI units).

    Attributes:
        pos, vel: ``N x 2`` positions (m) and velocities (m/s).
        radius: ``N`` body disc radii, m.
        v0: ``N`` preferred speeds, m/s.
        goal: ``N x 2`` active goals; ``pending``: ``N x 2`` next goals; ``lead``: ``N`` seconds until the pending
            goal becomes active (``<= 0``: none pending).
        mode: ``N`` WALK or IDLE; ``idle_left``: seconds of standing left.
    """

    def __init__(self, layout: SceneLayout, cfg: CrowdConfig, rng: np.random.Generator, n: int,
                 radius: np.ndarray, avoid_xy: list[np.ndarray] | None = None, avoid_m: float = 1.0,
                 scripted: tuple[ScriptedPed, ...] = ()):
        self.layout = layout
        self.cfg = cfg
        self.rng = rng
        self.script = tuple(scripted)
        k = len(self.script)
        self.n_random = n
        self.n = n + k
        self.radius = np.asarray(radius, dtype=np.float64)
        if len(self.radius) != self.n:
            raise ValueError(f"Crowd: expected {self.n} radii ({n} random + {k} scripted), got {len(self.radius)}")
        starts = np.array([p.start for p in self.script], float).reshape(k, 2)
        self.v0 = np.clip(rng.normal(cfg.speed_mean_mps, cfg.speed_std_mps, n), 0.5, 1.5)
        self.pos = self._spawn(n, [*(avoid_xy or []), *starts], avoid_m)
        self.goal = self._draw_goals(np.arange(n))
        heading = self.goal - self.pos
        heading /= np.maximum(np.linalg.norm(heading, axis=1, keepdims=True), 1e-9)
        self.vel = heading * self.v0[:, None] * rng.uniform(0.0, 1.0, (n, 1))
        self.v0 = np.concatenate([self.v0, [p.speed_mps for p in self.script]])
        self.pos = np.vstack([self.pos, starts])
        self.goal = np.vstack([self.goal, starts])  # scripted: standing at the start until the trigger
        self.vel = np.vstack([self.vel, np.zeros((k, 2))])
        self.pending = self.goal.copy()
        self.lead = np.zeros(self.n)
        self.mode = np.concatenate([np.full(n, WALK, dtype=np.int8), np.full(k, IDLE, dtype=np.int8)])
        self.idle_left = np.concatenate([np.zeros(n), np.full(k, np.inf)])
        self.slow_for = np.zeros(self.n)
        self.scripted = np.arange(self.n) >= n
        self.cue_shown = np.ones(self.n, bool)  # whether the running lead turns the head and torso (_announce)
        self.script_next = [-1] * k  # per scripted pedestrian: the waypoint it walks (or will walk) to; -1: waiting
        self.time_s = 0.0
        self.events: list[dict[str, float | int | str]] = []  # {"t_s", "ped", "kind": "start" | "turn", "lead_s"}

    def initial_yaw(self) -> np.ndarray:
        """``N`` facing directions at reset: toward the goal (random pedestrians), toward the first waypoint
        (scripted ones)."""
        target = self.goal.copy()
        for j, p in enumerate(self.script):
            target[self.n_random + j] = p.waypoints[0]
        return np.arctan2(target[:, 1] - self.pos[:, 1], target[:, 0] - self.pos[:, 0])

    # ---------------------------------------------------------------------------------------------- sampling
    def _region(self):
        return self.layout.spec.ped_region

    def _spawn(self, n: int, avoid_xy: list[np.ndarray], avoid_m: float) -> np.ndarray:
        pts = np.zeros((0, 2))
        clearance = float(self.radius.max(initial=0.25)) + 0.1
        for _ in range(200):
            if len(pts) >= n:
                break
            cand = self.layout.free_points(self.rng, 4 * n, clearance, self._region())
            for c in cand:
                if len(pts) >= n:
                    break
                if len(pts) and np.min(np.hypot(*(pts - c).T)) < 0.8:
                    continue
                if any(np.hypot(*(c - a)) < avoid_m for a in avoid_xy):
                    continue
                pts = np.vstack([pts, c])
        if len(pts) < n:
            raise RuntimeError(f"could not place {n} pedestrians in scene {self.layout.spec.name!r}")
        return pts

    def _draw_goals(self, idx: np.ndarray, k: int = 24) -> np.ndarray:
        """Random goals in line of sight of each pedestrian in ``idx`` (``len(idx) x 2``), all drawn at once.

        Each pedestrian gets ``k`` free candidates; the first at a distance in ``goal_distance_m`` whose straight
        segment keeps the body clear of obstacles wins (when the scene's ``pedestrians.goal_choice`` is
        ``farthest``: the farthest visible candidate beyond the minimum distance, so people walk corridors end to
        end — random goals within a range crowd the middle of a layout, where corridors meet); failing that, any
        visible candidate; failing that, it stays where it is.
        """
        m = len(idx)
        lo, hi = self.cfg.goal_distance_m
        r = self.radius[idx]
        cand = self.layout.free_points(self.rng, m * k, float(r.max(initial=0.25)) + 0.15,
                                       self._region()).reshape(m, k, 2)
        start = np.repeat(self.pos[idx][:, None, :], k, axis=1)
        d = norm2d(cand - start)
        clear = self.layout.segments_min_clearance(start.reshape(-1, 2), cand.reshape(-1, 2)).reshape(m, k)
        vis = clear >= r[:, None]
        if self.layout.spec.ped_goal_choice == "farthest":  # walk the corridors end to end: no upper bound
            ok = (d >= lo) & (clear >= r[:, None] + 0.05)
            pick = np.argmax(np.where(ok, d, -1.0), 1)
        else:
            ok = (d >= lo) & (d <= hi) & (clear >= r[:, None] + 0.05)
            pick = np.argmax(ok, 1)
        choice = np.where(ok.any(1), pick, np.argmax(vis, 1))
        out = cand[np.arange(m), choice]
        stay = ~ok.any(1) & ~vis.any(1)
        out[stay] = self.pos[idx][stay]
        return out

    # ---------------------------------------------------------------------------------------------- dynamics
    def desired_velocity(self) -> np.ndarray:
        """``N x 2`` preferred velocity: toward the active goal at v0 (slowing within 0.5 m), zero when idle."""
        to_goal = self.goal - self.pos
        dist = norm2d(to_goal)
        speed = self.v0 * np.clip(dist / 0.5, 0.0, 1.0) * (self.mode == WALK)
        return to_goal / np.maximum(dist, 1e-9)[:, None] * speed[:, None]

    def social_forces(self, robot_xy: np.ndarray | None, robot_radius: float) -> np.ndarray:
        """``N x 2`` total social-force acceleration (vectorised over all pairs)."""
        c = self.cfg
        f = (self.desired_velocity() - self.vel) / c.tau_s
        n = self.n
        speed = norm2d(self.vel)
        e_v = self.vel / np.maximum(speed, 1e-9)[:, None]
        if n > 1:
            diff = self.pos[:, None, :] - self.pos[None, :, :]  # i - j
            dist = norm2d(diff)
            np.fill_diagonal(dist, np.inf)
            nij = diff / np.maximum(dist, 1e-9)[..., None]
            cos_phi = -(e_v[:, None, :] * nij).sum(-1)
            w = c.anisotropy + (1 - c.anisotropy) * (1 + cos_phi) / 2
            rsum = self.radius[:, None] + self.radius[None, :]
            mag = c.ped_a_mps2 * np.exp((rsum - dist) / c.ped_b_m) * w
            mag = np.where(dist < c.interaction_range_m, mag, 0.0)
            f += (mag[..., None] * nij).sum(1)
        d_w, grad = self.layout.clearance_fast(self.pos)
        n_w = grad / np.maximum(norm2d(grad), 1e-9)[:, None]
        f += (c.wall_a_mps2 * np.exp((self.radius - d_w) / c.wall_b_m))[:, None] * n_w
        if robot_xy is not None and c.react_to_robot:
            diff = self.pos - robot_xy[None]
            dist = norm2d(diff)
            nr = diff / np.maximum(dist, 1e-9)[:, None]
            cos_phi = -(e_v * nr).sum(-1)
            w = c.anisotropy + (1 - c.anisotropy) * (1 + cos_phi) / 2
            mag = c.robot_a_mps2 * np.exp((self.radius + robot_radius - dist) / c.robot_b_m) * w
            f += np.where(dist < c.interaction_range_m, mag, 0.0)[:, None] * nr
        return f

    def step(self, dt: float, robot_xy: np.ndarray | None = None, robot_radius: float = 0.3) -> None:
        """Advance ``dt`` seconds: behaviour (goals, leads, idling), forces, integration, wall constraint."""
        self._behaviour(dt, robot_xy)
        acc = self.social_forces(robot_xy, robot_radius)
        vel = self.vel + dt * acc
        speed = norm2d(vel)
        cap = 1.3 * self.v0
        vel *= np.minimum(1.0, cap / np.maximum(speed, 1e-9))[:, None]
        pos = self.pos + dt * vel
        # hard constraint: nobody inside an obstacle
        d_w, grad = self.layout.clearance_fast(pos)
        bad = d_w < self.radius
        if bad.any():
            # exact geometry for the few that touch: move them out along the surface normal
            d_x, closest = self.layout.geometry.signed_distance(pos[bad])
            away = pos[bad] - closest
            nrm = norm2d(away)
            sign = np.where(d_x < 0, -1.0, 1.0)
            n_w = away / np.maximum(nrm, 1e-9)[:, None] * sign[:, None]
            pos[bad] = np.where((d_x < self.radius[bad])[:, None], closest + n_w * self.radius[bad][:, None], pos[bad])
            # remove the velocity component into the wall
            vn = (vel[bad] * n_w).sum(1)
            vel[bad] -= np.minimum(vn, 0.0)[:, None] * n_w
        self.pos, self.vel = pos, vel

    def _behaviour(self, dt: float, robot_xy: np.ndarray | None = None) -> None:
        c, rng = self.cfg, self.rng
        free = ~self.scripted  # the random pedestrians' behaviour below; the scripted ones follow their script
        # pending goals whose lead has run out become active
        had = self.lead > 0
        self.lead -= dt
        switch = had & (self.lead <= 0)
        if switch.any():
            self.goal[switch] = self.pending[switch]
            self.mode[switch] = WALK
            self.slow_for[switch] = 0.0
        # idle pedestrians count down, then decide where to go (and announce it)
        idle = self.mode == IDLE
        self.idle_left[idle] -= dt
        wake = idle & (self.idle_left <= 0) & (self.lead <= 0) & free
        # walkers near their goal, stuck, or changing their mind decide on a new goal
        walking = (self.mode == WALK) & (self.lead <= 0) & free
        near = walking & (norm2d(self.goal - self.pos) < c.goal_reached_m)
        speed = norm2d(self.vel)
        self.slow_for = np.where(walking & (speed < 0.15), self.slow_for + dt, 0.0)
        stuck = walking & (self.slow_for > c.stuck_s)
        whim = walking & ~near & (rng.random(self.n) < c.turn_rate_hz * dt)
        # some of the arrivals stop and stand for a while instead of walking on at once
        stop = near & (rng.random(self.n) < c.idle_prob)
        if stop.any():
            self.mode[stop] = IDLE
            self.idle_left[stop] = rng.uniform(*c.idle_s, stop.sum())
            self.goal[stop] = self.pos[stop]
        decide = wake | (near & ~stop) | stuck | whim
        if decide.any():
            idx = np.nonzero(decide)[0]
            self.pending[idx] = self._draw_goals(idx)
            self.lead[idx] = rng.uniform(c.lead_min_s, c.lead_max_s, len(idx))
            self.slow_for[idx] = 0.0
        if self.script:
            self._follow_scripts(robot_xy)
        self.time_s += dt

    def _follow_scripts(self, robot_xy: np.ndarray | None) -> None:
        """Triggers, turn cues and arrivals of the scripted pedestrians (see the module docstring)."""
        for j, p in enumerate(self.script):
            i = self.n_random + j
            k = self.script_next[j]
            if self.lead[i] > 0 or k >= len(p.waypoints):
                continue  # a cue is running, or it has arrived
            if k < 0:
                if p.fires(self.time_s, robot_xy):
                    self._announce(j, 0, "start")
                continue
            remaining = math.hypot(*(np.asarray(p.waypoints[k]) - self.pos[i]))
            if k == len(p.waypoints) - 1:
                if remaining < ARRIVED_M:
                    self.mode[i], self.idle_left[i] = IDLE, np.inf
                    self.goal[i] = self.pending[i] = self.pos[i]
                    self.script_next[j] = len(p.waypoints)
            elif remaining <= p.speed_mps * p.lead_s + ARRIVED_M / 2:
                self._announce(j, k + 1, "turn")

    def _announce(self, j: int, k: int, kind: str) -> None:
        i = self.n_random + j
        p = self.script[j]
        self.pending[i] = p.waypoints[k]
        self.lead[i] = max(p.lead_s, 1e-3)
        # cue=False hides the cue the reaction is timed from: every turn's, or the start's on a single straight leg
        self.cue_shown[i] = p.cue or (kind == "start" and len(p.waypoints) > 1)
        self.script_next[j] = k
        self.events.append({"t_s": round(self.time_s, 9), "ped": i, "kind": kind, "lead_s": p.lead_s})

    def attention_xy(self) -> np.ndarray:
        """``N x 2`` where each pedestrian is heading in mind: the pending goal during a lead, else the goal (a
        scripted pedestrian without its cue looks where it walks until the lead has run out)."""
        return np.where(((self.lead > 0) & self.cue_shown)[:, None], self.pending, self.goal)

    def state_dict(self) -> dict[str, np.ndarray]:
        """Copies of the privileged per-pedestrian state (world frame)."""
        return {"pos": self.pos.copy(), "vel": self.vel.copy(), "radius": self.radius.copy(),
                "goal": self.goal.copy(), "pending": self.pending.copy(), "lead_s": self.lead.copy(),
                "mode": self.mode.copy()}


def social_force_reference(pos, vel, goal, v0, radius, mode, layout: SceneLayout, cfg: CrowdConfig,
                           robot_xy=None, robot_radius: float = 0.3) -> np.ndarray:
    """The same accelerations as :meth:`Crowd.social_forces`, one agent and one pair at a time (reference)."""
    n = len(pos)
    out = np.zeros((n, 2))
    for i in range(n):
        gx, gy = goal[i][0] - pos[i][0], goal[i][1] - pos[i][1]
        gd = math.hypot(gx, gy)
        s = v0[i] * min(max(gd / 0.5, 0.0), 1.0) * (1.0 if mode[i] == WALK else 0.0)
        des = (gx / max(gd, 1e-9) * s, gy / max(gd, 1e-9) * s)
        fx = (des[0] - vel[i][0]) / cfg.tau_s
        fy = (des[1] - vel[i][1]) / cfg.tau_s
        sp = math.hypot(vel[i][0], vel[i][1])
        ev = (vel[i][0] / max(sp, 1e-9), vel[i][1] / max(sp, 1e-9))
        for j in range(n):
            if j == i:
                continue
            dx, dy = pos[i][0] - pos[j][0], pos[i][1] - pos[j][1]
            d = math.hypot(dx, dy)
            if d >= cfg.interaction_range_m:
                continue
            nx, ny = dx / max(d, 1e-9), dy / max(d, 1e-9)
            w = cfg.anisotropy + (1 - cfg.anisotropy) * (1 - (ev[0] * nx + ev[1] * ny)) / 2
            m = cfg.ped_a_mps2 * math.exp((radius[i] + radius[j] - d) / cfg.ped_b_m) * w
            fx += m * nx
            fy += m * ny
        dw, g = layout.clearance_fast(np.asarray(pos[i], dtype=float))
        gn = max(math.hypot(g[0], g[1]), 1e-9)
        m = cfg.wall_a_mps2 * math.exp((radius[i] - float(dw)) / cfg.wall_b_m)
        fx += m * g[0] / gn
        fy += m * g[1] / gn
        if robot_xy is not None and cfg.react_to_robot:
            dx, dy = pos[i][0] - robot_xy[0], pos[i][1] - robot_xy[1]
            d = math.hypot(dx, dy)
            if d < cfg.interaction_range_m:
                nx, ny = dx / max(d, 1e-9), dy / max(d, 1e-9)
                w = cfg.anisotropy + (1 - cfg.anisotropy) * (1 - (ev[0] * nx + ev[1] * ny)) / 2
                m = cfg.robot_a_mps2 * math.exp((radius[i] + robot_radius - d) / cfg.robot_b_m) * w
                fx += m * nx
                fy += m * ny
        out[i] = (fx, fy)
    return out


def heading_of(v: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Yaw of ``N x 2`` vectors, ``fallback`` where they are (near) zero."""
    n = norm2d(v)
    return np.where(n > 1e-6, np.arctan2(v[:, 1], v[:, 0]), fallback)


__all__ = ["Crowd", "CrowdConfig", "ScriptedPed", "social_force_reference", "heading_of", "wrap_angle", "WALK",
           "IDLE"]
