"""Why a method's benchmark episodes fail: each failed episode of an eval run put in a cause, counted per cell, and
the first few of each cause drawn at the moment it ended.

::

    python -m evaluation.failures data/eval/<run>                        # every method of the run
    python -m evaluation.failures data/eval/<run> --method full --figures 3 --out failures/

Reads the run's ``episodes.jsonl``, its per-episode ``traces/*.npz`` and ``seeds.json`` (``icrowdnav eval`` writes
them). Causes, from the trace's last state:

* ``collision_pedestrian``, ``timeout`` — the outcome;
* ``collision_obstacle_near_person`` — the robot hit a wall or an obstacle with a pedestrian's body within
  ``near_m`` of its own (surface to surface): it was evading someone, or squeezed between people and clutter;
* ``collision_obstacle_clear`` — it hit a wall or an obstacle with nobody that close.

Each failure also records the robot's mean speed and yaw rate over its last ``tail_s`` and, for a timeout, how far
the goal still was and whether the robot was *frozen* (its last :data:`FROZEN_S` within :data:`FROZEN_M` of one
spot — a deterministic policy in a near-static scene that chose to stand still keeps choosing it) with a person
within ``near_m`` for most of that time or not (counted as ``timeouts_frozen``); an obstacle hit records where the
obstacle was — the bearing of its nearest surface point from the robot's heading, and whether that lies in the cameras' field of view (|bearing| ≤ camera yaw + half its
horizontal FOV): a student only sees what its two forward cameras see, so a hit out of view is a side or rear one. A
pedestrian hit records, from the trace alone and so for any method, where the person hit (the body nearest the
robot's at the end) was: his bearing at contact and whether it lay in that field of view, how long before contact he
was last inside it (0 when in view at contact; none when never during the episode — the view here is the cameras'
angle only: no range limit, no occlusion), and the closing speed over the last ``tail_s`` split into the robot's
part (its velocity towards him) and his (towards the robot): who walked into whom. Per cell, the episodes whose straight start–goal segment crosses an obstacle of the layout (``line_blocked``,
a detour is needed: the warehouse allows a path up to 1.25 × the straight line, and a pallet on it) are counted with their
successes, and the table gives the SR of those and of the rest. Writes ``failures.json`` (the counts per method and
cell, and one record per failure) and
``failures.md`` into ``--out`` (default ``<run>/failures``), and ``figures/<cause>_<k>.png``: the top-down view
(:func:`sim.viz.plot_episode_topdown`) 3 m around the end (a timeout's view grown to hold its start and goal),
the robot and the people 1 s before and at the end. The
layout is rebuilt from the run's scene, scene seed and crowd seed; a trace whose start and goal do not match it
(scene files changed since the run) is a named error.

``--replay K`` reruns the first K obstacle hits of a lookahead-head policy (its checkpoint in the run's data dir,
the run's ``shield_s``) and asks whether the policy *saw* the hit coming: at each of the last steps, the obstacle
clearance its head predicted for the arc it chose (over the next :data:`REPLAY_WINDOW_S`, from its perceived scan;
for a student with the paper's MLP head, which predicts none, the clearance of that arc to the depth scan its
driver perceives beside its own inputs — what its obstacle shield reads, whether it acts with one or not),
the best clearance any action of the grid offered, and the true clearance after the step. A hit whose chosen arcs
were predicted to touch while a free arc existed is the cost's choice (``chose_predicted_contact``), not a
perception miss. Episodes are deterministic given their seeds; a replay that does not end as the run's row did is
reported as not reproduced. Hits are replayed ``--workers`` at a time (a process pool), reported in hit order.

``--teacher`` adds to each replayed step what the privileged teacher (``checkpoints/policy/teacher`` of the data
dir: the policy the students are distilled from) would have done in the same state, from its privileged observation
(:func:`sim.wrappers.privileged_observation`): its own action and that arc's predicted clearance, its probability of
the action the policy chose, the share of its action distribution on arcs predicted to touch (what the students'
soft cloning targets, ``softmax(teacher logits)``, put there), and the policy's own probability of its choice. A hit
where the policy chose a predicted contact that the teacher would not have chosen is an imitation error; one where
the teacher's target puts much of its mass on contact arcs is a target that does not teach avoiding them.
``--other METHOD`` (with ``--teacher``) also asks another student of the data dir, one whose inputs are a subset of
the replayed policy's (e.g. ``no_i2`` for a ``full`` of the same encoder), which arc it would choose in the same
states: whether the replayed policy's contact choices are states its ablation also gets wrong.

``--replay-peds K`` does the same for the first K pedestrian hits and asks whether the policy *perceived* the person
it hit: at each of the last steps, where that person truly was (range, bearing, inside the cameras' view or not),
whether one of the policy's reported tracks (``peds``, present) lay within :data:`PED_MATCH_M` of him, the
pedestrian clearance the head predicted for the chosen arc (over :data:`REPLAY_WINDOW_S`, from its tracks and
their predicted motion), the best clearance to people *and* obstacles any arc offered, and the true clearance to
him after the step. Each hit is put in one class (:data:`PED_HIT_CLASSES`, :func:`ped_hit_class`): the person was
not tracked at the last step before contact (``untracked``); tracked, and the chosen arcs were predicted to touch
someone while a free arc existed (``chose_predicted_contact``); tracked, and no arc was free (``no_free_arc``);
tracked, and the chosen arcs were predicted clear of everyone (``predicted_clear``: the track or its predicted
motion was wrong, or the person walked into the robot).

``--scene NAME`` keeps only one scene's episodes (e.g. a run whose other scenes changed since).

``--against BASE[:METHOD]`` pairs the run's episodes of ``--method`` with those of another run on the same seeds
(``BASE``'s episodes of ``METHOD``, default ``--method``; e.g. a student before and after fine-tuning, or two
variants) separately where the straight line is blocked and where it is clear: each side's SR and the exact
McNemar test on who alone succeeded (:func:`paired_by_line`) — whether a gain is in the detours or in the open.
Both runs' layouts decide the split; episodes that do not pair, or a line blocked in one run and clear in the
other (different scene files), are a named error.
"""

from __future__ import annotations

import argparse
import math
import os
from collections import Counter
from dataclasses import dataclass, replace
from functools import cached_property, lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import torch

from evaluation.compare import pair_key, read_protocol, read_rows
from evaluation.harness import Job, cached_driver, make_env, reset_options
from evaluation.methods import MethodSpec, resolve_methods
from evaluation.stats import mcnemar_exact
from pipeline.core.artifacts import atomic_write_json, atomic_write_text, json_safe
from pipeline.core.config import from_dict, read_yaml_mapping
from pipeline.core.errors import (
    ConfigError,
    CorruptArtifactError,
    InputMissingError,
    reports_errors,
)
from pipeline.core.executor import map_jobs
from pipeline.core.layout import policy_dir
from rl.driver import cached_policy
from rl.lookahead import ObstacleShield
from rl.networks import MLP_HEADS
from rl.policy import action_logits, obs_to_tensor
from sim.env import CrowdNavEnv, SimConfig
from sim.episode import episode_steps
from sim.geometry import world_to_robot, world_to_robot_each
from sim.trace import EpisodeTrace
from sim.viz import plot_episode_topdown
from sim.wrappers import privileged_observation

REPLAY_WINDOW_S = 0.6  # --replay: the predicted clearance of an arc is its minimum over the lookahead times up to this
REPLAY_STEPS = 10  # --replay: the last steps kept per replayed hit
PED_MATCH_M = 0.5  # --replay-peds: a reported track within this of the hit person's true centre is his
PED_HIT_CLASSES = ("untracked", "chose_predicted_contact", "no_free_arc", "predicted_clear")
CAUSES = ("collision_pedestrian", "collision_obstacle_near_person", "collision_obstacle_clear", "timeout")
OUT_OF_VIEW = "obstacle_hits_out_of_view"  # obstacle hits whose obstacle lay outside the cameras' field of view
PED_OUT_OF_VIEW = "ped_hits_out_of_view"  # pedestrian hits whose person was outside the cameras' field of view
FROZEN = "timeouts_frozen"  # timeouts that ended standing still (the last FROZEN_S within FROZEN_M of one spot)
FROZEN_S, FROZEN_M = 10.0, 0.1
BLOCKED = "line_blocked"  # episodes whose straight start-goal segment crosses an obstacle (a detour is needed)
BLOCKED_OK = "line_blocked_successes"


def trace_path(run: Path, row: dict[str, Any]) -> Path:
    """The trace of a benchmark row (the harness names it ``<scene>_d<density>_s<seed>_<method>.npz``)."""
    return Path(run) / "traces" / f"{row['scene']}_d{float(row['density']):g}_s{row['seed']}_{row['method']}.npz"


def classify(trace: EpisodeTrace, near_m: float = 1.0, tail_s: float = 0.5) -> dict[str, Any]:
    """The cause of a failed episode (module docstring) and the robot's last moments."""
    pose = trace.robot_pose[-1]
    px = trace.ped_xy[-1]
    here = np.isfinite(px).all(-1) if len(px) else np.zeros(0, bool)
    gaps = np.linalg.norm(px[here] - pose[:2], axis=-1) - trace.ped_radius[here] - trace.robot_radius_m
    nearest = float(gaps.min()) if len(gaps) else float("inf")
    cause = trace.outcome
    if cause == "collision_obstacle":
        cause = "collision_obstacle_near_person" if nearest <= near_m else "collision_obstacle_clear"
    if cause not in CAUSES:
        raise ConfigError(f"failure cause of a {trace.outcome!r} episode: not a failure")
    n = max(1, round(tail_s / trace.dt_s))
    cmd = trace.robot_cmd[-n:] if len(trace.robot_cmd) else np.zeros((1, 2))
    out = {"cause": cause, "nearest_person_m": nearest, "tail_speed_mps": float(np.abs(cmd[:, 0]).mean()),
           "tail_yaw_rate_radps": float(np.abs(cmd[:, 1]).mean()),
           "goal_distance_m": float(np.linalg.norm(trace.goal_xy - pose[:2])), "steps": int(len(trace.robot_cmd))}
    nf = round(FROZEN_S / trace.dt_s)
    if cause == "timeout" and len(trace.robot_pose) > nf:
        xy = trace.robot_pose[-nf:, :2]
        out["frozen"] = bool(np.linalg.norm(xy - xy.mean(0), axis=-1).max() < FROZEN_M)
        px = trace.ped_xy[-nf:]
        gap = np.linalg.norm(px - xy[:, None], axis=-1) - trace.ped_radius[None] - trace.robot_radius_m
        near = np.where(np.isfinite(gap), gap, np.inf).min(-1) <= near_m if px.shape[1] else np.zeros(nf, bool)
        out["frozen_people_near"] = out["frozen"] and bool(near.mean() > 0.5)
    return out


def _load_trace(path: Path) -> EpisodeTrace:
    if not path.is_file():
        raise InputMissingError(f"{path}: no trace of this episode (run `icrowdnav eval` again; it saves one per "
                                "benchmark episode)")
    try:
        return EpisodeTrace.load_npz(path)
    except (OSError, ValueError, KeyError) as e:
        raise CorruptArtifactError(f"{path}: unreadable trace ({type(e).__name__}: {e})") from None


def hit_bearing(layout: Any, pose: np.ndarray) -> float:
    """Bearing (deg, counter-clockwise from the heading) of the nearest obstacle surface point from robot ``pose``."""
    _, closest = layout.geometry.signed_distance(np.asarray(pose[:2], float))
    d = np.asarray(closest, float) - pose[:2]
    return float(np.degrees(np.angle(np.exp(1j * (math.atan2(d[1], d[0]) - pose[2])))))


def hit_person(trace: EpisodeTrace) -> int:
    """Index of the person a pedestrian collision hit: the body nearest the robot's (surface to surface) at the end."""
    gaps = (np.linalg.norm(trace.ped_xy[-1] - trace.robot_pose[-1, :2], axis=-1) - trace.ped_radius
            - trace.robot_radius_m)
    return int(np.argmin(np.where(np.isfinite(gaps), gaps, np.inf)))


def ped_hit_geometry(trace: EpisodeTrace, view_deg: float, tail_s: float) -> dict[str, Any]:
    """Where the person a pedestrian collision hit was (module docstring), from the trace alone: his bearing at
    contact (deg, counter-clockwise from the heading), inside the cameras' field of view (|bearing| <= ``view_deg``)
    or not, the seconds from the last step he was inside it to contact (None if never), and the closing speed over
    the last ``tail_s`` split into the robot's part and his (m/s, positive = towards the other)."""
    j = hit_person(trace)
    d = trace.ped_xy[:, j] - trace.robot_pose[:, :2]  # T x 2, NaN before a scripted person enters
    p = world_to_robot_each(trace.ped_xy[:, j], trace.robot_pose)  # in the robot's frame at each step
    bearing = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
    seen = np.flatnonzero(np.abs(bearing) <= view_deg)  # NaN compares False
    out = {"ped_hit_bearing_deg": float(bearing[-1]), "ped_hit_in_view": bool(abs(bearing[-1]) <= view_deg),
           "ped_last_in_view_s_before": float((len(d) - 1 - seen[-1]) * trace.dt_s) if len(seen) else None,
           "closing_robot_mps": 0.0, "closing_ped_mps": 0.0}
    n = min(len(d) - 1, max(1, round(tail_s / trace.dt_s)))
    if n:
        u = d[-1] / max(float(np.linalg.norm(d[-1])), 1e-9)  # robot -> person at contact
        v_robot = (trace.robot_pose[-1, :2] - trace.robot_pose[-1 - n, :2]) / (n * trace.dt_s)
        v_ped = (trace.ped_xy[-1, j] - trace.ped_xy[-1 - n, j]) / (n * trace.dt_s)
        out["closing_robot_mps"] = float(v_robot @ u)
        out["closing_ped_mps"] = float(-(v_ped @ u)) if np.isfinite(v_ped).all() else 0.0
    return out


def analyse(run: Path, method: str | None = None, near_m: float = 1.0, tail_s: float = 0.5,
            scene: str | None = None) -> dict[str, Any]:
    """Counts of failure causes per method and cell, and one record per failed benchmark episode of ``run`` (only
    ``method``'s and ``scene``'s when given)."""
    if not (near_m >= 0 and tail_s > 0):
        raise ConfigError(f"failures: expected near_m >= 0 and tail_s > 0, got {near_m}, {tail_s}")
    run = Path(run)
    rows = read_rows(run / "episodes.jsonl")
    for key, want in (("method", method), ("scene", scene)):
        if want is not None:
            held = sorted({str(r.get(key)) for r in rows})
            rows = [r for r in rows if r.get(key) == want]
            if not rows:
                raise InputMissingError(f"{run}: no episode of {key} {want!r} (it holds {held})")
    records, counts, blocked, episodes = [], {}, {}, []
    with Layouts(run) as layouts:
        for r in rows:
            cell = f"{r['scene']}@{float(r['density']):g}"
            c = counts.setdefault(r["method"], {}).setdefault(cell, Counter())
            ok, line = r["success"] > 0.5, line_blocked(run, r, layouts, blocked)
            c.update(episodes=1, successes=int(ok), **{BLOCKED: int(line), BLOCKED_OK: int(line and ok)})
            episodes.append({"method": r["method"], "scene": r["scene"], "density": float(r["density"]),
                             "seed": int(r["seed"]), "success": int(ok), BLOCKED: bool(line)})
            if ok:
                continue
            trace = _load_trace(trace_path(run, r))
            info = classify(trace, near_m, tail_s)
            c[info["cause"]] += 1
            if trace.outcome == "collision_obstacle":
                info["hit_bearing_deg"] = hit_bearing(layouts.layout(r, trace), trace.robot_pose[-1])
                info["hit_in_view"] = abs(info["hit_bearing_deg"]) <= layouts.view_deg
                c[OUT_OF_VIEW] += int(not info["hit_in_view"])
            elif trace.outcome == "collision_pedestrian":
                info.update(ped_hit_geometry(trace, layouts.view_deg, tail_s))
                c[PED_OUT_OF_VIEW] += int(not info["ped_hit_in_view"])
            if info.get("frozen"):
                c[FROZEN] += 1
            records.append({"method": r["method"], "scene": r["scene"], "density": r["density"], "seed": r["seed"],
                            **info})
    return {"run": str(run), "near_m": near_m, "tail_s": tail_s,
            "counts": {m: {cell: dict(c) for cell, c in cs.items()} for m, cs in counts.items()},
            "failures": records, "episodes": episodes}


def paired_by_line(res: dict[str, Any], base: dict[str, Any]) -> dict[str, Any]:
    """Two :func:`analyse` results of one method each (``res`` the run, ``base`` the one it is held against),
    paired on (scene, density, seed): for the episodes whose straight line is blocked, those where it is clear, and
    all, each side's SR and the exact McNemar test (``a_only``: only ``base`` succeeded)."""
    def one(r: dict[str, Any]) -> dict[tuple, dict[str, Any]]:
        methods = sorted({e["method"] for e in r["episodes"]})
        if len(methods) != 1:
            raise ConfigError(f"{r['run']}: pairing by line needs one method, the run holds {methods} (--method)")
        return {pair_key(e): e for e in r["episodes"]}

    mine, theirs = one(res), one(base)
    alone = sorted(set(mine) ^ set(theirs))
    if alone:
        raise InputMissingError(f"{res['run']} against {base['run']}: {len(alone)} episodes have no pair on the other "
                                f"side, e.g. {alone[0]} (the same protocol, cells and seeds are needed)")
    keys = sorted(mine)
    differ = [k for k in keys if mine[k][BLOCKED] != theirs[k][BLOCKED]]
    if differ:
        raise CorruptArtifactError(f"{res['run']} against {base['run']}: the straight line of {len(differ)} paired "
                                   f"episodes is blocked in one run's layout and clear in the other's, e.g. "
                                   f"{differ[0]} (scene files changed between the runs)")
    out = {"run": res["run"], "base": base["run"], "groups": {}, "ped_hits": {}}
    for name, sel in (("line blocked", True), ("line clear", False), ("all", None)):
        ks = [k for k in keys if sel is None or mine[k][BLOCKED] == sel]
        a, b = [theirs[k]["success"] for k in ks], [mine[k]["success"] for k in ks]
        out["groups"][name] = {**mcnemar_exact(a, b), "sr_base": float(np.mean(a)) if ks else math.nan,
                               "sr_run": float(np.mean(b)) if ks else math.nan}
    for name, in_view in (("person in view", True), ("person out of view", False)):
        hit = [{pair_key(f) for f in r["failures"] if f["cause"] == "collision_pedestrian"
                and f["ped_hit_in_view"] == in_view} for r in (base, res)]
        out["ped_hits"][name] = mcnemar_exact([k in hit[0] for k in keys], [k in hit[1] for k in keys])
    return out


def _p(test: dict[str, Any]) -> str:
    """An exact McNemar test's p-value for a table cell ("—" where no pair is discordant)."""
    return "—" if math.isnan(test["p_value"]) else f"{test['p_value']:.3g}"


def paired_markdown(paired: dict[str, Any]) -> str:
    lines = ["", f"Paired with {paired['base']} on the same seeds (exact McNemar on who alone succeeded)", "",
             "| episodes | pairs | SR base | SR this run | only base / only this run | p |", "|---|---|---|---|---|---|"]
    for name, g in paired["groups"].items():
        lines.append(f"| {name} | {g['n']} | {g['sr_base']:.3f} | {g['sr_run']:.3f} | {g['a_only']} / {g['b_only']} "
                     f"| {_p(g)} |")
    lines += ["", "Pedestrian hits on the same seeds, by where the person hit was (exact McNemar on who alone had one)", "",
              "| pedestrian hit | only base / only this run | p |", "|---|---|---|"]
    lines += [f"| {name} | {g['a_only']} / {g['b_only']} | {_p(g)} |" for name, g in paired.get("ped_hits", {}).items()]
    return "\n".join(lines) + "\n"


def line_blocked(run: Path, row: dict[str, Any], layouts: Layouts, cache: dict[tuple, bool]) -> bool:
    """Whether the straight segment from ``row``'s start to its goal crosses an obstacle of its layout (once per
    cell and scene seed: the start, the goal and the layout are the scene seed's)."""
    scene_seed = layouts.scene_seeds.get(int(row["seed"]))
    key = (row["scene"], float(row["density"]), ("crowd", int(row["seed"])) if scene_seed is None else scene_seed)
    if key not in cache:
        trace = _load_trace(trace_path(run, row))
        geometry = layouts.layout(row, trace).geometry
        cache[key] = not bool(geometry.segment_clear(trace.start_xy, trace.goal_xy, 0.0)[0])
    return cache[key]


def _sr_split(c: dict[str, int]) -> str:
    """``SR blocked (n) / SR clear (n)`` of one count table (:data:`BLOCKED`)."""
    nb, sb = c.get(BLOCKED, 0), c.get(BLOCKED_OK, 0)
    nc, sc = c["episodes"] - nb, c.get("successes", 0) - sb
    return " / ".join(f"{k / n:.2f} ({n})" if n else f"— ({n})" for k, n in ((sb, nb), (sc, nc)))


def ped_hit_markdown(res: dict[str, Any]) -> str:
    """Per method, where the people its pedestrian hits hit were (:func:`ped_hit_geometry`): in the cameras' view at
    contact, within the last second, never; who did more of the closing; the median closing speeds and the median of
    the robot's mean speed over the last ``tail_s``."""
    lines = ["", "Pedestrian hits: where the person hit was (the cameras' angle only) and who closed the gap", "",
             "| method | hits | in view at contact | in view within 1 s before | never in view | robot closed more | "
             "median closing robot / person (m/s) | median robot speed over the last tail_s (m/s) |", "|---|---|---|---|---|---|---|---|"]
    for m in res["counts"]:
        h = [f for f in res["failures"] if f["method"] == m and f["cause"] == "collision_pedestrian"]
        if not h:
            continue
        last = [f["ped_last_in_view_s_before"] for f in h]
        cr, cp = (np.array([f[k] for f in h]) for k in ("closing_robot_mps", "closing_ped_mps"))
        lines.append(f"| {m} | {len(h)} | {sum(f['ped_hit_in_view'] for f in h)} | "
                     f"{sum(x is not None and x <= 1.0 for x in last)} | {sum(x is None for x in last)} | "
                     f"{int((cr > cp).sum())} | {np.median(cr):.2f} / {np.median(cp):.2f} | "
                     f"{np.median([f['tail_speed_mps'] for f in h]):.2f} |")
    return "\n".join(lines) + "\n"


def markdown(res: dict[str, Any]) -> str:
    lines = [f"Failure causes in {res['run']} (obstacle hits split at a person within {res['near_m']:g} m)", "",
             "| method | cell | episodes | " + " | ".join(CAUSES) + f" | {OUT_OF_VIEW} | {PED_OUT_OF_VIEW} | "
             f"{FROZEN} | SR straight line blocked (n) / clear (n) |",
             "|---|---|---|" + "---|" * (len(CAUSES) + 4)]
    cols = (*CAUSES, OUT_OF_VIEW, PED_OUT_OF_VIEW, FROZEN)
    for m, cells in res["counts"].items():
        total = sum((Counter(c) for c in cells.values()), Counter())
        for cell, c in [*cells.items(), ("all", total)]:
            lines.append(f"| {m} | {cell} | {c['episodes']} | " + " | ".join(str(c.get(k, 0)) for k in cols)
                         + f" | {_sr_split(c)} |")
    return "\n".join(lines) + "\n"


class Layouts:
    """The episodes of an eval run rebuilt from its sim config, scene seeds and crowd seeds (state mode: no
    rendering; one env per cell, reset per episode), checked against their traces' start and goal. The run's config
    and seeds are read on first use; a context manager (the envs are closed on exit)."""

    def __init__(self, run: Path) -> None:
        self.run = Path(run)
        self._envs: dict[tuple[str, float], CrowdNavEnv] = {}

    @cached_property
    def config(self) -> dict[str, Any]:
        """The run's eval config (``config.yaml``) as a mapping."""
        return read_yaml_mapping(self.run / "config.yaml", "eval config")

    @cached_property
    def sim(self) -> SimConfig:
        return from_dict(SimConfig, self.config.get("sim", {}), str(self.run / "config.yaml"))

    @cached_property
    def view_deg(self) -> float:
        """The two mirrored cameras' joint field of view: |bearing| up to this is seen."""
        return abs(self.sim.camera.yaw_deg) + self.sim.camera.hfov_deg / 2.0

    @cached_property
    def scene_seeds(self) -> dict[int, int | None]:
        return {int(e["seed"]): e.get("scene_seed") for e in read_protocol(self.run)}

    def __enter__(self) -> Layouts:
        return self

    def __exit__(self, *exc: object) -> None:
        for env in self._envs.values():
            env.close()
        self._envs.clear()

    def env(self, row: dict[str, Any], trace: EpisodeTrace) -> Any:
        """The env (unwrapped) reset to ``row``'s episode; its start and goal must be the trace's."""
        key = (row["scene"], float(row["density"]))
        if key not in self._envs:
            self._envs[key] = CrowdNavEnv(config=replace(self.sim, scene=key[0], scenario="", density=key[1],
                                                         obs_mode="state"))
        seed = self.scene_seeds.get(int(row["seed"]))
        self._envs[key].reset(seed=int(row["seed"]), options=None if seed is None else {"scene_seed": int(seed)})
        u = self._envs[key].unwrapped
        if not (np.allclose(u.goal, trace.goal_xy, atol=1e-6) and np.allclose(u.robot[:2], trace.start_xy,
                                                                             atol=1e-6)):
            raise CorruptArtifactError(f"{trace_path(self.run, row)}: its start and goal are not those of scene "
                                       f"{row['scene']!r} with seed {row['seed']} today (scene files changed since "
                                       "the run?)")
        return u

    def layout(self, row: dict[str, Any], trace: EpisodeTrace) -> Any:
        """The static world of ``row``'s episode (:meth:`env`)."""
        return self.env(row, trace).layout


def view_bounds(trace: EpisodeTrace, whole_span: bool, half_m: float = 3.0, margin_m: float = 1.0
                ) -> tuple[float, float, float, float]:
    """The figure's view: ``half_m`` around the robot's end, and with ``whole_span`` (a timeout: where it stopped
    matters relative to the goal, e.g. a freeze behind a shelf) grown to hold the start and the goal with
    ``margin_m``."""
    end = np.asarray(trace.robot_pose[-1][:2], dtype=float)
    lo, hi = end - half_m, end + half_m
    if whole_span:
        pts = np.stack([np.asarray(trace.start_xy, dtype=float), np.asarray(trace.goal_xy, dtype=float)])
        lo, hi = np.minimum(lo, pts.min(0) - margin_m), np.maximum(hi, pts.max(0) + margin_m)
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def draw(run: Path, res: dict[str, Any], out: Path, per_cause: int) -> list[Path]:
    """The first ``per_cause`` failures of each cause (in run order), drawn at their end (module docstring)."""
    written, seen = [], Counter()
    with Layouts(run) as layouts:
        cam = layouts.sim.camera
        for f in res["failures"]:
            k = seen[f["cause"]]
            if k >= per_cause:
                continue
            seen[f["cause"]] += 1
            trace = _load_trace(trace_path(run, f))
            obstacles = layouts.layout(f, trace).obstacles
            t_end = len(trace.robot_pose) - 1
            path = plot_episode_topdown(
                obstacles, trace, out / "figures" / f"{f['cause']}_{k}.png",
                bounds=view_bounds(trace, whole_span=f["cause"] == "timeout"),
                camera_yaws_deg=(cam.yaw_deg, -cam.yaw_deg), camera_hfov_deg=cam.hfov_deg,
                snapshot_steps=[max(0, t_end - round(1.0 / trace.dt_s)), t_end],
                title=f"{f['method']}: {f['cause']} (nearest person {f['nearest_person_m']:.2f} m"
                      + (f", obstacle at {f['hit_bearing_deg']:+.0f}°)" if "hit_bearing_deg" in f else ")"))
            written.append(path)
    return written


@dataclass(frozen=True)
class ReplayJob:
    """One obstacle hit of an eval run to rerun (a picklable job for :func:`pipeline.core.executor.map_jobs`)."""

    run: Path
    spec: MethodSpec
    failure: dict[str, Any]
    teacher: Path | None = None  # --teacher: the teacher checkpoint that labels each replayed step
    other: MethodSpec | None = None  # --other: another student asked in the same states


@lru_cache(maxsize=4)
def run_layouts(run: Path) -> Layouts:
    """The run's :class:`Layouts` read once per process (its config and seeds; no env is opened through it here)."""
    return Layouts(run)


def replay_head(spec: MethodSpec, sim: SimConfig, pedestrian: bool = False) -> Any:
    """What predicts the clearances of ``spec``'s actions (its driver made once per process): the lookahead head
    of its policy, or for a student with the paper's MLP head (obstacle hits only) the arcs of the action grid
    against the depth scan its driver then perceives (:class:`rl.lookahead.ObstacleShield` over
    :data:`REPLAY_WINDOW_S` on the run's robot and scan: the clearances its shield reads, whether or not it acts
    with one). Any other method is a named error."""
    driver = cached_driver(spec)
    head = getattr(getattr(getattr(driver, "policy", None), "features_extractor", None), "lookahead", None)
    if head is not None:
        return head
    if getattr(driver, "student", False) and getattr(driver, "head", None) in MLP_HEADS and not pedestrian:
        driver.perceive_scan = True
        return ObstacleShield(sim.robot, sim.dt_s, sim.scan_rays, sim.scan_range_m, REPLAY_WINDOW_S)
    what = "predicted pedestrian clearances (a lookahead head)" if pedestrian else (
        "predicted clearances (a lookahead head, or a student's MLP head and its depth scan)")
    raise ConfigError(f"--replay{'-peds' if pedestrian else ''}: method {spec.name!r} has no {what} to read")


def replay_hit(job: ReplayJob) -> dict[str, Any]:
    """``job``'s episode rerun with its method's policy, recording per step what the head predicted for the chosen
    arc and the true clearance after the step: for an obstacle hit the obstacle clearances (module docstring,
    ``--replay``), for a pedestrian hit also the tracks and the pedestrian clearances (``--replay-peds``)."""
    torch.set_num_threads(1)  # one episode per worker process
    f, spec, layouts = job.failure, job.spec, run_layouts(job.run)
    ped_hit = f["cause"] == "collision_pedestrian"
    driver, head = cached_driver(spec), replay_head(spec, layouts.sim, ped_hit)
    w = head.steps_within(REPLAY_WINDOW_S)
    ep = Job(spec, layouts.sim, f["scene"], float(f["density"]), int(f["seed"]), job.run, save_trace=False,
             scene_seed=layouts.scene_seeds.get(int(f["seed"])))
    env = make_env(ep)
    u = env.unwrapped
    teacher = cached_policy(job.teacher)
    other = cached_driver(job.other).policy if job.other is not None else None
    steps, tracks = [], []
    priv = None  # --teacher: the privileged observation of the state the policy acts on next
    try:
        for tr in episode_steps(env, driver, ep.seed, reset_options(ep)):
            o, seen = driver.last_obs, priv  # what the policy (and the teacher) saw when it chose tr.action
            if teacher is not None:
                priv = privileged_observation(env, tr.info.get("waypoint"))
            if tr.step == 0 or o is None:
                continue
            keys = [*driver.policy.observation_space.spaces, *(("scan",) if "scan" in o else ())]
            obs = obs_to_tensor({key: o[key] for key in dict.fromkeys(keys)})
            with torch.no_grad():
                feats = head.action_features(obs)
            clear = head.obstacle_clearances(feats, w)[0]  # A x w, m
            true = float(u.layout.geometry.signed_distance(np.asarray(u.robot[:2], float))[0])
            rec = {"step": tr.step - 1, "action": int(tr.action),
                   "predicted_m": float(clear[tr.action].min()),
                   "predicted_next_m": float(clear[tr.action, 0]),
                   "best_available_m": float(clear.min(-1).values.max()),
                   "true_next_m": true - float(head.radius_m)}
            if ped_hit:
                pc = head.pedestrian_clearances(feats, w)[0]  # A x w, m
                rec.update(ped_predicted_m=float(pc[tr.action].min()),
                           best_free_m=float(torch.minimum(pc, clear).min(-1).values.max()))
                peds = np.asarray(o.get("peds", np.zeros((0, 6))), float)
                tracks.append(peds[peds[:, 5] > 0.5, :2] if len(peds) else np.zeros((0, 2)))
            if teacher is not None:
                rec.update(teacher_step(teacher, seen, driver.policy, o, clear.min(-1).values, int(tr.action), other))
            steps.append(rec)
        trace = u.trace(method=spec.name)
    finally:
        env.close()
    if ped_hit:
        _hit_person(trace, steps, tracks, layouts.view_deg)
    tail = steps[-REPLAY_STEPS:]
    err = [abs(r["predicted_next_m"] - r["true_next_m"]) for r in steps if r["true_next_m"] < 1.0]
    outcome = "collision_pedestrian" if ped_hit else "collision_obstacle"
    out = {"method": f["method"], "scene": f["scene"], "density": f["density"], "seed": f["seed"],
           "cause": f["cause"], "reproduced": trace.outcome == outcome and trace.n_steps == f["steps"],
           "clearance_error_m": float(np.median(err)) if err else None, "steps": tail}
    if not ped_hit:
        out["chose_predicted_contact"] = any(r["predicted_m"] < 0.0 < r["best_available_m"] for r in tail)
        if teacher is not None:
            out.update(teacher_verdict(tail))
    else:
        out["class"] = ped_hit_class(tail)
        out["chose_predicted_contact"] = out["class"] == "chose_predicted_contact"
        out["in_view_at_contact"] = bool(tail[-1]["in_view"]) if tail else None
        out["speed_at_contact_mps"] = float(abs(trace.robot_cmd[-1, 0])) if len(trace.robot_cmd) else 0.0
        seen = [r for r in steps if r["tracked"]]
        last = seen[-1] if seen else None  # when and where the hit person was last tracked
        out["last_tracked_s_before"] = (trace.n_steps - 1 - last["step"]) * trace.dt_s if last else None
        out["last_tracked_bearing_deg"] = last["bearing_deg"] if last else None
        out["last_tracked_range_m"] = last["range_m"] if last else None
    return out


def teacher_step(teacher: Any, priv: dict[str, np.ndarray], policy: Any, seen: dict[str, np.ndarray],
                 clear_m: torch.Tensor, action: int, other: Any = None) -> dict[str, Any]:
    """One replayed step seen by the teacher (``--teacher``): its action on the privileged observation ``priv`` of
    the state where the policy chose ``action`` and that arc's predicted clearance (``clear_m``: each action's
    minimum over the window), its probability of ``action``, the share of its distribution on arcs predicted to
    touch (< 0 m), the policy's own probability of ``action`` (``seen``: what the policy read), and for a policy that
    reads people (poses or tracks) the predicted clearance of the action it would choose perceiving nobody (None
    for one that reads none); with ``other`` (a policy reading a subset of ``seen``), the predicted clearance of
    its choice."""
    def probs(pi: Any, o: dict[str, np.ndarray]) -> torch.Tensor:
        return torch.softmax(torch.as_tensor(action_logits(pi, o), dtype=torch.float64), -1)

    def choice_m(pi: Any, o: dict[str, np.ndarray]) -> float:
        return float(clear_m[int(np.argmax(action_logits(pi, o)))])

    t, s = probs(teacher, priv), probs(policy, seen)
    a_t = int(t.argmax())
    empty = {**seen}  # the same state with nobody perceived: no detected pose, no present track
    if "pose_mask" in empty:
        empty["pose_mask"] = np.zeros_like(seen["pose_mask"])
    if "peds" in empty:
        empty["peds"] = np.array(seen["peds"], copy=True)
        empty["peds"][..., 5] = 0.0
    reads_people = any(k in policy.observation_space.spaces for k in ("pose_mask", "peds"))
    return {"teacher_action": a_t, "teacher_predicted_m": float(clear_m[a_t]), "teacher_p_chosen": float(t[action]),
            "teacher_p_contact": float(t[clear_m < 0.0].sum()), "policy_p_chosen": float(s[action]),
            "empty_crowd_predicted_m": choice_m(policy, empty) if reads_people else None,
            "other_predicted_m": None if other is None else choice_m(other, seen)}


def teacher_verdict(tail: list[dict[str, Any]]) -> dict[str, Any]:
    """What the teacher says of a replayed obstacle hit's last steps (``--teacher``): the steps where the policy
    chose an arc predicted to touch while a free one existed (its contact choices), how many of them the teacher
    would have taken an arc predicted free instead (an imitation error when all), and, over them, the teacher's mean
    probability of the policy's choice and the mean share of its distribution on contact arcs."""
    bad = [r for r in tail if r["predicted_m"] < 0.0 < r["best_available_m"]]
    return {"contact_choices": len(bad),
            "teacher_free_at_contact_choices": sum(r["teacher_predicted_m"] >= 0.0 for r in bad),
            "teacher_p_chosen_at_contact_choices": float(np.mean([r["teacher_p_chosen"] for r in bad])) if bad else None,
            "teacher_p_contact_at_contact_choices": float(np.mean([r["teacher_p_contact"] for r in bad])) if bad
            else None}


def _hit_person(trace: EpisodeTrace, steps: list[dict[str, Any]], tracks: list[np.ndarray], view_deg: float) -> None:
    """Adds to each step record of a pedestrian hit where the person the robot hit (the nearest body at the end)
    truly was in the robot frame when the action was chosen (``range_m``, ``bearing_deg``, ``in_view``), whether a
    reported track lay within :data:`PED_MATCH_M` of him (``tracked``, ``track_error_m``) and his true clearance
    after the step (``true_ped_next_m``)."""
    j = hit_person(trace)
    for rec, tr in zip(steps, tracks, strict=True):
        k = rec["step"]
        if not np.isfinite(trace.ped_xy[k:k + 2, j]).all():  # not yet in the scene (a scripted person)
            rec.update(range_m=float("nan"), bearing_deg=float("nan"), in_view=False, tracked=False,
                       track_error_m=None, true_ped_next_m=float("nan"))
            continue
        p = world_to_robot(trace.ped_xy[k, j][None], trace.robot_pose[k])[0]
        err = np.linalg.norm(tr - p, axis=-1).min() if len(tr) else np.inf
        nxt = np.linalg.norm(trace.ped_xy[k + 1, j] - trace.robot_pose[k + 1, :2])
        bearing = float(np.degrees(np.arctan2(p[1], p[0])))
        rec.update(range_m=float(np.hypot(*p)), bearing_deg=bearing, in_view=abs(bearing) <= view_deg,
                   tracked=bool(err <= PED_MATCH_M), track_error_m=float(err) if np.isfinite(err) else None,
                   true_ped_next_m=float(nxt - trace.ped_radius[j] - trace.robot_radius_m))


def ped_hit_class(steps: list[dict[str, Any]]) -> str:
    """The class of a replayed pedestrian hit (:data:`PED_HIT_CLASSES`) from its last step records: ``untracked``
    when the person was not tracked at the last step before contact; else ``chose_predicted_contact`` when a chosen
    arc was predicted to touch someone while an arc free of people and obstacles existed, ``no_free_arc`` when a
    chosen arc was predicted to touch and none was free, ``predicted_clear`` when every chosen arc was predicted
    clear of everyone."""
    if not steps or not steps[-1]["tracked"]:
        return "untracked"
    if any(r["ped_predicted_m"] < 0.0 < r["best_free_m"] for r in steps):
        return "chose_predicted_contact"
    if any(r["ped_predicted_m"] < 0.0 for r in steps):
        return "no_free_arc"
    return "predicted_clear"


def replay_hits(run: Path, res: dict[str, Any], k: int, data_dir: Path | None = None, workers: int = 1,
                progress: bool = False, pedestrian: bool = False, teacher: bool = False,
                other: str | None = None) -> list[dict[str, Any]]:
    """The first ``k`` obstacle hits of ``res`` (pedestrian hits with ``pedestrian``) rerun with their method's
    policy (module docstring, ``--replay`` / ``--replay-peds``), ``workers`` episodes at a time (a process pool; each
    worker loads a method's weights once), in hit order; with ``teacher``, each step also seen by the data dir's
    teacher (``--teacher``) and by the data dir's student ``other`` (``--other``)."""
    run = Path(run)
    data_dir = Path(data_dir) if data_dir is not None else run.parent.parent
    hits = [f for f in res["failures"]
            if (f["cause"] == "collision_pedestrian") == pedestrian and f["cause"] != "timeout"][:k]
    methods = list(dict.fromkeys(f["method"] for f in hits))
    specs = dict(zip(methods, resolve_methods(methods, data_dir, run_layouts(run).config.get("shield_s")), strict=True))
    for spec in specs.values():  # a method with nothing to read is refused before any episode runs
        replay_head(spec, run_layouts(run).sim, pedestrian)
    teacher_ck = policy_dir(data_dir, "teacher") if teacher else None
    cached_policy(teacher_ck)  # so is a missing or unreadable teacher (one named error)
    other_spec = None
    if other is not None:
        if not teacher:
            raise ConfigError("--other: expected with --teacher (it is read at the teacher's steps)")
        (other_spec,) = resolve_methods([other], data_dir, None)
        want = set(cached_driver(other_spec).policy.observation_space.spaces)
        for spec in specs.values():
            have = set(cached_driver(spec).policy.observation_space.spaces)
            if not want <= have:
                raise ConfigError(f"--other: {other!r} reads {sorted(want - have)}, which {spec.name!r} does not "
                                  f"(expected a subset of {sorted(have)})")
    return map_jobs(replay_hit, [ReplayJob(run, specs[f["method"]], f, teacher_ck, other_spec) for f in hits],
                    workers, "replay", progress)


def replay_markdown(replays: list[dict[str, Any]]) -> str:
    chose = sum(r["chose_predicted_contact"] for r in replays)
    errs = [r["clearance_error_m"] for r in replays if r["clearance_error_m"] is not None]
    return (f"\nReplayed obstacle hits: {len(replays)} ({sum(r['reproduced'] for r in replays)} reproduced); in "
            f"{chose} the policy chose, within its last {REPLAY_STEPS} steps, an arc it predicted to touch an "
            f"obstacle within {REPLAY_WINDOW_S:g} s while a free arc existed; median |predicted − true| clearance "
            f"one step ahead within 1 m of obstacles: "
            + (f"{float(np.median(errs)):.3f} m" if errs else "n/a") + "\n"
            + (teacher_markdown(replays) if replays and "contact_choices" in replays[0] else ""))


def teacher_markdown(replays: list[dict[str, Any]]) -> str:
    """Per method, what the teacher would have done at the replayed obstacle hits' contact choices (``--teacher``)."""
    lines = ["", "The teacher in the same states (its privileged observation), at the steps where the policy chose an "
             "arc predicted to touch while a free one existed:", "",
             "| method | hits with such a choice | choices | teacher's own arc predicted free | teacher's p of the "
             "policy's choice (mean) | teacher's mass on contact arcs (mean) | policy's p of its choice (mean) | "
             "policy's arc predicted free when it perceives nobody | the other student's arc predicted free |",
             "|---|---|---|---|---|---|---|---|---|"]
    for m in dict.fromkeys(r["method"] for r in replays):
        steps = [s for r in replays if r["method"] == m for s in r["steps"]
                 if s["predicted_m"] < 0.0 < s["best_available_m"]]
        hits = sum(r["contact_choices"] > 0 for r in replays if r["method"] == m)
        means = [f"{float(np.mean([s[k] for s in steps])):.3f}" if steps else "—"
                 for k in ("teacher_p_chosen", "teacher_p_contact", "policy_p_chosen")]
        free = [[s[k] >= 0.0 for s in steps if s[k] is not None]
                for k in ("empty_crowd_predicted_m", "other_predicted_m")]
        lines.append(f"| {m} | {hits} | {len(steps)} | {sum(s['teacher_predicted_m'] >= 0.0 for s in steps)} | "
                     + " | ".join(means) + " | " + " | ".join(str(sum(f)) if f else "—" for f in free) + " |")
    return "\n".join(lines) + "\n"


def ped_replay_markdown(replays: list[dict[str, Any]]) -> str:
    """The replayed pedestrian hits per method and class, and per hit its cell, class and last moments."""
    lines = [f"\nReplayed pedestrian hits: {len(replays)} ({sum(r['reproduced'] for r in replays)} reproduced), "
             f"classed from their last {REPLAY_STEPS} steps (a track within {PED_MATCH_M:g} m of the hit person = "
             f"tracked; predicted clearances over {REPLAY_WINDOW_S:g} s)", "",
             "| method | hits | " + " | ".join(PED_HIT_CLASSES) + " | hit person in view at contact | robot "
             "stopped at contact (< 0.05 m/s) |", "|---|---|" + "---|" * (len(PED_HIT_CLASSES) + 2)]
    for m in dict.fromkeys(r["method"] for r in replays):
        rs = [r for r in replays if r["method"] == m]
        c = Counter(r["class"] for r in rs)
        lines.append(f"| {m} | {len(rs)} | " + " | ".join(str(c.get(k, 0)) for k in PED_HIT_CLASSES)
                     + f" | {sum(bool(r['in_view_at_contact']) for r in rs)} | "
                     f"{sum(r['speed_at_contact_mps'] < 0.05 for r in rs)} |")
    lines += ["", "| method | cell | seed | class | tracked in last steps | last tracked: s before contact, range / "
              "bearing | range / bearing 1 s before | predicted ped. clearance (chosen, min) | true clearance 1 s "
              "before |", "|---|---|---|---|---|---|---|---|---|"]
    for r in replays:
        st = r["steps"]
        first = st[0] if st else {}
        lines.append(f"| {r['method']} | {r['scene']}@{float(r['density']):g} | {r['seed']} | {r['class']} | "
                     f"{sum(x['tracked'] for x in st)} / {len(st)} | "
                     + (f"{r['last_tracked_s_before']:.1f} s, {r['last_tracked_range_m']:.2f} m / "
                        f"{r['last_tracked_bearing_deg']:+.0f}° | " if r["last_tracked_s_before"] is not None
                        else "never | ")
                     + (f"{first['range_m']:.2f} m / {first['bearing_deg']:+.0f}° | " if st else "— | ")
                     + (f"{min(x['ped_predicted_m'] for x in st):.2f} m | {first['true_ped_next_m']:.2f} m |"
                        if st else "— | — |"))
    return "\n".join(lines) + "\n"


@reports_errors
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m evaluation.failures", description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="an eval run directory (data/eval/<run>)")
    ap.add_argument("--method", default=None, help="only this method's episodes")
    ap.add_argument("--near-m", type=float, default=1.0, help="an obstacle hit is 'near a person' within this")
    ap.add_argument("--tail-s", type=float, default=0.5, help="the last seconds the speed and yaw rate average")
    ap.add_argument("--figures", type=int, default=2, help="failures drawn per cause")
    ap.add_argument("--out", type=Path, default=None, help="output folder (default <run>/failures)")
    ap.add_argument("--replay", type=int, default=0, help="rerun the first K obstacle hits (lookahead-head policies)")
    ap.add_argument("--replay-peds", type=int, default=0, help="rerun the first K pedestrian hits (lookahead-head "
                                                               "policies)")
    ap.add_argument("--teacher", action="store_true", help="--replay: each step also labelled by the data dir's "
                                                           "teacher in the same state")
    ap.add_argument("--other", default=None, metavar="METHOD", help="--teacher: also ask this student of the data "
                                                                     "dir (inputs a subset of the policy's)")
    ap.add_argument("--scene", default=None, help="only this scene's episodes")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="--replay's episodes run at a time "
                                                                           "(default: the machine's CPUs)")
    ap.add_argument("--data-dir", type=Path, default=None, help="where --replay finds the checkpoints (default: the "
                                                                    "run's data dir, <run>/../..)")
    ap.add_argument("--against", default=None, metavar="BASE[:METHOD]",
                    help="pair --method's episodes with this run's (of METHOD, default --method) on the same seeds, "
                         "where the straight line is blocked and where it is clear")
    args = ap.parse_args(argv)
    out = args.out or args.run / "failures"
    for name, low in (("figures", 0), ("replay", 0), ("replay_peds", 0), ("workers", 1)):
        if getattr(args, name) < low:
            raise ConfigError(f"--{name.replace('_', '-')}: expected an integer >= {low}, got {getattr(args, name)}")
    res = analyse(args.run, args.method, args.near_m, args.tail_s, args.scene)
    text = markdown(res) + ped_hit_markdown(res)
    if args.against:
        base_run, _, base_method = args.against.partition(":")
        base = analyse(Path(base_run), base_method or args.method, args.near_m, args.tail_s, args.scene)
        res["against"] = paired_by_line(res, base)
        text += paired_markdown(res["against"])
    if args.replay:
        res["replays"] = replay_hits(args.run, res, args.replay, args.data_dir, args.workers, progress=True,
                                     teacher=args.teacher, other=args.other)
        text += replay_markdown(res["replays"])
    if args.replay_peds:
        res["ped_replays"] = replay_hits(args.run, res, args.replay_peds, args.data_dir, args.workers, progress=True,
                                         pedestrian=True)
        text += ped_replay_markdown(res["ped_replays"])
    out.mkdir(parents=True, exist_ok=True)
    draw(args.run, res, out, args.figures)
    atomic_write_json(out / "failures.json", json_safe(res))
    atomic_write_text(out / "failures.md", text)
    print(text, end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
