"""Scenario files: a staged situation — a scene, a fixed start and goal, a crowd, scripted pedestrians.

A scenario is a YAML file in ``sim/scenarios/`` (or any path). Schema (units in the names)::

    name: blind_corner                 # must equal the file stem
    description: "..."                 # optional
    scene: corner                      # a shipped scene name or a scene file path ...
    layout: {bounds: [...], free_space: [[...], ...], obstacles: [...]}   # ... or a scene written inline
                                       # (the scene schema of sim/scene.py without name/split); one of the two
    start: [x, y]                      # the robot's start (m, world frame)
    goal: [x, y]                       # its goal
    start_yaw_deg: 0                   # optional: the robot's heading at start (default: facing the goal)
    density: 0.0                       # optional: random pedestrians per m² of free area, beside the scripted
    yaw_jitter_rad: 0.2                # optional: trials draw the robot's heading within ± this of start_yaw
    speed_jitter: 0.1                  # optional: ... and each scripted walker's speed within ± this fraction
    pedestrians:                       # scripted pedestrians (at least one)
      - start: [x, y]                  # where it stands until its trigger fires
        waypoints: [[x, y], ...]       # walked in order, straight from one to the next; it stops at the last
        speed_mps: 1.0                 # optional (1.0)
        lead_s: 0.7                    # optional: head and torso turn this long before each change of walking
                                       # direction (the crowd's intention cue; the crowd draws 0.3–1.0 s)
        trigger:                       # optional (default: it walks from t = 0); one of
          time_s: 2.0                  #   at this time
          robot_within_m: 2.0          #   or when the robot is this close to ...
          point: [x, y]                #   ... this point (default: the pedestrian's start)

Checked when loaded, against the scene's static layout (a scenario's scene may not draw random clutter): every
number finite and in range; start and goal free for the robot and connected; every scripted start and waypoint
free for a pedestrian and each leg walkable in a straight line; a distance trigger's point within its distance of
the robot's shortest route (else it can never fire on the way), a time trigger before the time limit. Errors name
the file, the field, the expected and the actual value (:class:`pipeline.core.errors.ConfigError`).

Per episode, :func:`scenario_metrics` measures what the scenario is for: a collision with a scripted pedestrian,
the minimum clearance to them, and the robot's **reaction time** — from the onset of the cue (the first turn cue of
a scripted pedestrian, else the first start) to the first change of command that increases the robot's predicted
clearance to where that pedestrian actually walks over the next 2 s (robot: the command held; pedestrian: its
recorded future). A method that reads intention from pose can react before the walking direction changes.

That reaction time counts any clearance-raising change of command, and a policy's commands change every few
steps near a person, so it sits at its floor (0.1–0.2 s) for every method. The direct test of "intention from
pose" is a **no-cue twin**: the same trial run again with the scripted pedestrians' head and torso lead switched
off (``SimConfig.scenario_cues``; the walk and its timing unchanged), and :func:`cue_twin_metrics` — the first step
at which the robot's commands differ between the two runs is a response to the cue and to nothing else.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.config import FieldValueError, read_yaml
from pipeline.core.errors import ConfigError, InputMissingError
from sim.crowd import ScriptedPed
from sim.planners.global_path import distance_to_polyline
from sim.scene import SceneLayout, SceneSpec, decode_file, load_scene, named_file, parse_scene
from sim.trace import EpisodeTrace

SCENARIOS_DIR = Path(__file__).resolve().parent / "scenarios"
PED_CLEARANCE_M = 0.25  # a scripted start / waypoint keeps this from obstacles (a body radius)
ROBOT_RADIUS_M = 0.3  # start and goal are checked for the default robot (sim.robot.RobotConfig)
REACTION_HORIZON_S = 2.0
MAX_SCRIPTED = 20

Vec2 = tuple[float, float]


def _finite(name: str, *values: float) -> None:
    if not all(isinstance(v, int | float) and math.isfinite(v) for v in values):
        raise FieldValueError(name, "finite numbers", list(values) if len(values) > 1 else values[0])


@dataclass
class TriggerFile:
    """``trigger:`` when a scripted pedestrian starts: at ``time_s``, or when the robot is ``robot_within_m`` of
    ``point``."""

    time_s: float | None = None
    robot_within_m: float | None = None
    point: Vec2 | None = None

    def validate(self) -> None:
        if (self.time_s is None) == (self.robot_within_m is None):
            raise ValueError("expected exactly one of time_s / robot_within_m")
        if self.time_s is not None:
            _finite("time_s", self.time_s)
            if not 0 <= self.time_s <= 600:
                raise FieldValueError("time_s", "a time in [0, 600] s", self.time_s)
        if self.robot_within_m is not None:
            _finite("robot_within_m", self.robot_within_m)
            if not 0 < self.robot_within_m <= 50:
                raise FieldValueError("robot_within_m", "a distance in (0, 50] m", self.robot_within_m)
        if self.point is not None:
            _finite("point", *self.point)


@dataclass
class ScriptedPedFile:
    """One item of ``pedestrians:``."""

    start: Vec2
    waypoints: list[Vec2]
    speed_mps: float = 1.0
    lead_s: float = 0.7
    trigger: TriggerFile | None = None

    def validate(self) -> None:
        _finite("start", *self.start)
        if not self.waypoints:
            raise FieldValueError("waypoints", "at least one waypoint", [])
        for k, w in enumerate(self.waypoints):
            _finite(f"waypoints[{k}]", *w)
        _finite("speed_mps", self.speed_mps)
        if not 0.1 <= self.speed_mps <= 2.5:
            raise FieldValueError("speed_mps", "a walking speed in [0.1, 2.5] m/s", self.speed_mps)
        _finite("lead_s", self.lead_s)
        if not 0 <= self.lead_s <= 3:
            raise FieldValueError("lead_s", "a lead in [0, 3] s", self.lead_s)


@dataclass
class ScenarioFile:
    """A scenario file as written (the schema in the module docstring; ``layout`` is read apart)."""

    name: str
    start: Vec2
    goal: Vec2
    description: str = ""
    scene: str | None = None
    start_yaw_deg: float | None = None
    density: float = 0.0
    yaw_jitter_rad: float = 0.2
    speed_jitter: float = 0.1
    pedestrians: list[ScriptedPedFile] = field(default_factory=list)

    def validate(self) -> None:
        _finite("yaw_jitter_rad", self.yaw_jitter_rad)
        if not 0 <= self.yaw_jitter_rad <= math.pi:
            raise FieldValueError("yaw_jitter_rad", "an angle in [0, pi] rad", self.yaw_jitter_rad)
        _finite("speed_jitter", self.speed_jitter)
        if not 0 <= self.speed_jitter <= 0.5:
            raise FieldValueError("speed_jitter", "a fraction in [0, 0.5]", self.speed_jitter)
        if not self.name:
            raise FieldValueError("name", "a non-empty string", self.name)
        _finite("start", *self.start)
        _finite("goal", *self.goal)
        if self.start_yaw_deg is not None:
            _finite("start_yaw_deg", self.start_yaw_deg)
        _finite("density", self.density)
        if not 0 <= self.density <= 2:
            raise FieldValueError("density", "a density in [0, 2] ped/m²", self.density)
        if not 1 <= len(self.pedestrians) <= MAX_SCRIPTED:
            raise FieldValueError("pedestrians", f"1 to {MAX_SCRIPTED} scripted pedestrians", len(self.pedestrians))


@dataclass(frozen=True)
class ScenarioSpec:
    """A validated scenario: its scene, start, goal, robot heading, crowd density and scripted pedestrians."""

    name: str
    scene: SceneSpec
    start: Vec2
    goal: Vec2
    start_yaw: float  # rad
    density: float
    pedestrians: tuple[ScriptedPed, ...]
    description: str = ""
    path: str = ""
    yaw_jitter: float = 0.2  # rad: per trial, the robot's heading within ± this
    speed_jitter: float = 0.1  # per trial, each scripted walker's speed within ± this fraction


def available_scenarios() -> list[str]:
    return sorted(p.stem for p in SCENARIOS_DIR.glob("*.yaml"))


def load_scenario(name_or_path: str) -> ScenarioSpec:
    """Load and check a scenario by shipped name (``blind_corner``) or path.

    Raises:
        ConfigError: an unknown name (listing the known ones) or an invalid file (file, field, expected, actual).
        InputMissingError: a path that does not exist.
    """
    p = named_file(name_or_path, SCENARIOS_DIR, "scenario")
    return _load_scenario_file(str(p.resolve()), p.stat().st_mtime_ns)


@functools.lru_cache(maxsize=32)
def _load_scenario_file(path: str, mtime_ns: int) -> ScenarioSpec:
    p = Path(path)
    return parse_scenario(read_yaml(p, "scenario file"), str(p), stem=p.stem)


def parse_scenario(data: Any, src: str, stem: str | None = None) -> ScenarioSpec:
    """Validate a scenario mapping (as loaded from YAML) against its scene; see the module docstring."""
    source = f"scenario file {src}"
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping at the top level, got {type(data).__name__}")
    data = dict(data)
    layout = data.pop("layout", None)
    sc = decode_file(ScenarioFile, data, source, stem)
    if (sc.scene is None) == (layout is None):
        raise ConfigError(f"{source}: expected exactly one of 'scene' (a scene name or file) and 'layout' (a scene "
                          f"written inline), got {'both' if layout is not None else 'neither'}")
    if layout is not None:
        if not isinstance(layout, dict):
            raise ConfigError(f"{source}: config key 'layout': expected a mapping, got {type(layout).__name__}")
        scene = parse_scene({"name": sc.name, "split": "test", **layout}, f"{src} (layout)")
    else:
        try:
            scene = load_scene(sc.scene)
        except (ConfigError, InputMissingError) as e:
            raise ConfigError(f"{source}: config key 'scene': {e}") from None
    if scene.random_obstacles is not None:
        raise ConfigError(f"{source}: config key 'scene': expected a scene without random_obstacles (a scenario "
                          f"is staged on a fixed layout), got {scene.name!r} with random clutter")
    peds = tuple(_scripted(p) for p in sc.pedestrians)
    start, goal = tuple(map(float, sc.start)), tuple(map(float, sc.goal))
    yaw = (math.radians(sc.start_yaw_deg) if sc.start_yaw_deg is not None
           else math.atan2(goal[1] - start[1], goal[0] - start[0]))
    spec = ScenarioSpec(sc.name, scene, start, goal, yaw, float(sc.density), peds, sc.description, src,
                        float(sc.yaw_jitter_rad), float(sc.speed_jitter))
    _check_against_layout(spec, source)
    return spec


def _scripted(p: ScriptedPedFile) -> ScriptedPed:
    t = p.trigger
    return ScriptedPed(
        start=tuple(map(float, p.start)), waypoints=tuple(tuple(map(float, w)) for w in p.waypoints),
        speed_mps=float(p.speed_mps), lead_s=float(p.lead_s),
        trigger_time_s=None if t is None else t.time_s,
        trigger_within_m=None if t is None else t.robot_within_m,
        trigger_point=None if t is None or t.point is None else tuple(map(float, t.point)))


def _check_against_layout(spec: ScenarioSpec, source: str) -> None:
    layout: SceneLayout = spec.scene.layout()
    x0, x1, y0, y1 = spec.scene.bounds

    def clearance(name: str, xy: Vec2, need: float, what: str) -> None:
        if not (x0 <= xy[0] <= x1 and y0 <= xy[1] <= y1):
            raise ConfigError(f"{source}: config key '{name}': expected a point inside the bounds "
                              f"{list(spec.scene.bounds)}, got {list(xy)}")
        got = float(layout.clearance_at(np.asarray(xy, float)))
        if got < need:
            raise ConfigError(f"{source}: config key '{name}': expected {what} (>= {need:.2f} m from every "
                              f"obstacle), got {list(xy)} at {got:.2f} m")

    clearance("start", spec.start, ROBOT_RADIUS_M + 0.05, "a free start for the robot")
    clearance("goal", spec.goal, ROBOT_RADIUS_M + 0.05, "a free goal for the robot")
    route = np.asarray(layout.nav(ROBOT_RADIUS_M + 0.05).shortest_path(layout, np.asarray(spec.start),
                                                                       np.asarray(spec.goal)), float)
    if route.ndim != 2 or len(route) < 2 or not np.all(np.isfinite(route)):
        raise ConfigError(f"{source}: config keys 'start', 'goal': expected a goal the robot can reach from the "
                          f"start, got no path from {list(spec.start)} to {list(spec.goal)}")
    for i, p in enumerate(spec.pedestrians):
        key = f"pedestrians[{i}]"
        clearance(f"{key}.start", p.start, PED_CLEARANCE_M, "a free place for a pedestrian")
        pts = [p.start, *p.waypoints]
        for k, w in enumerate(p.waypoints):
            clearance(f"{key}.waypoints[{k}]", w, PED_CLEARANCE_M, "a waypoint outside every obstacle")
            a, b = np.asarray(pts[k], float)[None], np.asarray(w, float)[None]
            if float(layout.segments_min_clearance(a, b)[0]) < PED_CLEARANCE_M - 0.05:
                raise ConfigError(f"{source}: config key '{key}.waypoints[{k}]': expected a straight walk from "
                                  f"{list(pts[k])} clear of obstacles, got one that crosses an obstacle")
        if p.trigger_within_m is not None:
            point = p.trigger_point if p.trigger_point is not None else p.start
            d = float(distance_to_polyline(np.asarray(point, float), route)[0])
            if d > p.trigger_within_m:
                raise ConfigError(f"{source}: config key '{key}.trigger': expected a point within robot_within_m = "
                                  f"{p.trigger_within_m} m of the robot's route, got {list(point)} at {d:.2f} m "
                                  "(the trigger could never fire on the way)")


# ------------------------------------------------------------------------------------------------- metrics
def _cue_event(events: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The event the reaction is timed from: the first turn cue, else the first start (None: no cue yet)."""
    turns = [e for e in events if e["kind"] == "turn"]
    return min(turns or [e for e in events if e["kind"] == "start"], key=lambda e: e["t_s"], default=None)


def cue_onset_s(events: list[dict[str, Any]]) -> float:
    """The onset of the cue the reaction time is measured from: the first turn cue, else the first start."""
    e = _cue_event(events)
    return math.nan if e is None else float(e["t_s"])


def _rollout(pose: np.ndarray, cmd: np.ndarray, dt: float, steps: int) -> np.ndarray:
    x, y, yaw = (float(v) for v in pose)
    v, w = (float(c) for c in cmd)
    out = np.empty((steps, 2))
    for k in range(steps):
        yaw += w * dt
        x += v * math.cos(yaw) * dt
        y += v * math.sin(yaw) * dt
        out[k] = (x, y)
    return out


def reaction_time_s(trace: EpisodeTrace, peds: np.ndarray, onset_s: float, horizon_s: float = REACTION_HORIZON_S,
                    dv: float = 0.05, dw: float = 0.1) -> float:
    """Seconds from ``onset_s`` to the first command (issued at or after it) that differs from the previous one
    by > ``dv`` m/s or > ``dw`` rad/s and gives a larger predicted clearance to pedestrians ``peds`` over
    ``horizon_s`` than holding the previous command (robot: the command held; pedestrians: their recorded
    future); nan when no such command comes."""
    if not math.isfinite(onset_s) or len(peds) == 0:
        return math.nan
    cmd, pose, dt = trace.robot_cmd, trace.robot_pose, trace.dt_s
    steps = max(1, int(round(horizon_s / dt)))
    for k in range(max(1, math.ceil(onset_s / dt - 1e-9)), len(cmd)):
        if abs(cmd[k, 0] - cmd[k - 1, 0]) <= dv and abs(cmd[k, 1] - cmd[k - 1, 1]) <= dw:
            continue
        fut = trace.ped_xy[k + 1:k + 1 + steps][:, peds]  # T' x P x 2
        if len(fut) == 0:
            break
        if _clearance(pose[k], cmd[k], fut, dt) > _clearance(pose[k], cmd[k - 1], fut, dt) + 1e-3:
            return k * dt - onset_s
    return math.nan


def cue_lead_s(events: list[dict[str, Any]]) -> float:
    """How long the cue of :func:`cue_onset_s` leads the change of walking direction (s; nan without a cue)."""
    e = _cue_event(events)
    return math.nan if e is None else float(e.get("lead_s", math.nan))


def cue_twin_metrics(cued: EpisodeTrace, twin: EpisodeTrace, peds: np.ndarray, onset_s: float, lead_s: float,
                     horizon_s: float = REACTION_HORIZON_S) -> dict[str, float]:
    """What the cue alone changed: ``cued`` and ``twin`` are one scenario trial run twice, the twin with the scripted
    pedestrians' head and torso lead switched off (``SimConfig.scenario_cues``) — the same seed, the same walk.

    ``cue_divergence_s``: seconds from the cue's onset to the first step at which the robot's commands differ
    between the two runs (nan: never within their common steps) — a reaction caused by the cue and nothing else, so
    it has no floor of command jitter; ``cue_anticipated`` 1 if that came before the walking direction changed
    (``< lead_s`` after the onset); ``cue_divergence_safer`` 1 if, at that step (the same pose in both runs), the cued
    command's predicted clearance to the scripted pedestrians over ``horizon_s`` (their recorded future in the cued
    run) is larger than the twin's command's, 0 if not, nan without divergence; ``twin_identical_before_cue`` 1 if
    the runs' commands agree on every step before the onset (0 would mean the runs are not twins)."""
    n = min(len(cued.robot_cmd), len(twin.robot_cmd))
    diff = np.any(np.abs(cued.robot_cmd[:n] - twin.robot_cmd[:n]) > 1e-9, axis=1)
    dt = cued.dt_s
    first = max(0, math.ceil(onset_s / dt - 1e-9)) if math.isfinite(onset_s) else n
    out = {"cue_divergence_s": math.nan, "cue_anticipated": 0.0, "cue_divergence_safer": math.nan,
           "twin_identical_before_cue": float(not diff[:min(first, n)].any())}
    after = np.nonzero(diff[first:])[0]
    if not len(after) or len(peds) == 0:
        return out
    k = first + int(after[0])
    div = k * dt - onset_s
    out["cue_divergence_s"] = float(div)
    out["cue_anticipated"] = float(div < lead_s - 1e-9)
    fut = cued.ped_xy[k + 1:k + 1 + max(1, int(round(horizon_s / dt)))][:, peds]
    if len(fut):
        out["cue_divergence_safer"] = float(_clearance(cued.robot_pose[k], cued.robot_cmd[k], fut, dt)
                                            > _clearance(cued.robot_pose[k], twin.robot_cmd[k], fut, dt) + 1e-3)
    return out


def _clearance(pose: np.ndarray, cmd: np.ndarray, fut: np.ndarray, dt: float) -> float:
    """Smallest centre distance between the robot holding ``cmd`` from ``pose`` and pedestrians ``fut`` (T x P x 2)."""
    path = _rollout(pose, cmd, dt, len(fut))
    return float(np.min(np.hypot(*(fut - path[:, None, :]).transpose(2, 0, 1))))


def scenario_metrics(trace: EpisodeTrace, scripted: np.ndarray, events: list[dict[str, Any]]) -> dict[str, float]:
    """``collision_scripted`` (1 if the episode ended in a collision with a scripted pedestrian),
    ``min_clearance_scripted_m`` (robot footprint to the nearest scripted body, m), ``cue_onset_s``, ``cue_lead_s``
    (how long that cue leads the turn) and ``reaction_time_s`` (nan: no reaction)."""
    peds = np.nonzero(np.asarray(scripted, bool))[0]
    if len(peds) == 0:
        return {"collision_scripted": 0.0, "min_clearance_scripted_m": math.nan, "cue_onset_s": math.nan,
                "cue_lead_s": math.nan, "reaction_time_s": math.nan}
    d = np.hypot(*(trace.ped_xy[:, peds] - trace.robot_pose[:, None, :2]).transpose(2, 0, 1))
    clr = d - trace.ped_radius[peds][None] - trace.robot_radius_m
    collided = 0.0
    if trace.outcome == "collision_pedestrian" and trace.ped_xy.shape[1]:
        final = np.hypot(*(trace.ped_xy[-1] - trace.robot_pose[-1, :2]).T) - trace.ped_radius
        collided = float(int(np.argmin(final)) in set(peds.tolist()))
    onset = cue_onset_s(events)
    return {"collision_scripted": collided, "min_clearance_scripted_m": float(np.min(clr)),
            "cue_onset_s": onset, "cue_lead_s": cue_lead_s(events), "reaction_time_s": reaction_time_s(trace, peds, onset)}
