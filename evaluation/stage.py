"""``icrowdnav eval``: the paper's benchmark — scenes × densities × methods × seeded episodes, plus long-horizon
runs on a topological map — with tables, paired tests, figures, videos and MCAP logs. ::

    icrowdnav eval                                   # the profile's methods, scenes, densities, goals x trials
    icrowdnav eval --methods '[full, dwa]' --goals 5 --trials 1 --run_name quick
    icrowdnav eval --resume                          # a killed run: only the episodes without a row run again
    icrowdnav eval --method_episodes '{full: 10}'    # full on a paired subset (10 per cell), the others on all
    make eval                                        # the same on the default profile

The protocol (the paper's): per method and cell ``goals`` start-goal pairs × ``trials`` crowds (25 × 3 = 75), the
same seeded episodes for every method; paired tests by episode (McNemar for SR, Wilcoxon for NT / PL / TPZ) with
the smallest SR difference each comparison can detect at 80 % power (:mod:`evaluation.stats`), per cell and
pooled over the cells; Wilson intervals. ``method_episodes`` runs a method on fewer episodes per cell — the first in
trial-major order, a paired subset of the others' on distinct goals — where its cost would not fit (the default
profile: the rendered methods and the references at 10, the camera-free baselines at 75). Time limits follow the route: max(``sim.max_episode_s``,
``sim.timeout_s_per_m`` × the shortest start-goal path). ``routing_scenes`` (the shelf hall) are extra cells in
which every method follows the global planner's waypoints, reported apart from the paper's cells.

Inputs: ``DATA_DIR/checkpoints/policy/<name>/`` of every learned method (``make train``); the expert and DWA need
nothing. Output ``DATA_DIR/eval/<run_name>/``::

    config.yaml, manifest.json   resolved config, provenance (inputs with hashes, code, versions)
    seeds.json                   the seed list every method faced (per cell and for the long-horizon runs)
    episodes.jsonl               one row per episode: method, scene, density, seed, goal, trial, outcome, every metric
    routing/episodes.jsonl       the routing cells' rows (global-planner waypoints), apart from the paper's cells
    scenarios/episodes.jsonl     the scenario suite's rows (+ collision with / clearance to the scripted pedestrians,
                                 reaction time); scenarios/figures, videos, mcap: the first trials
    scenarios/cue_twins.jsonl    per trial of the ``cue_twins`` scenarios: what the cue alone changed (the trial's
                                 no-cue twin under scenarios/nocue/: the same walk without the head/torso lead);
                                 scenarios/figures/cue_twin_<scenario>.png: the first trial's commands, both runs
    results.json, results.csv    per cell and method: N, mean, std, 95 % CI of every metric
    paired.json                  the full model against each method on the same seeds (McNemar / Wilcoxon, the
                                 detectable SR difference), per cell and pooled over the cells
    report.md                    the paper's tables, paired tests, the expected ordering checked, long horizon,
                                 what the episodes cost (Compute)
    cost.json                    per part (benchmark, routing, scenarios, no-cue twins, long horizon): its wall time
                                 in this invocation and, per method, worker-seconds per episode and per env step
                                 (evaluation.cost; cost/<episode>.json in each part's folder: one episode's timing)
    figures/sr_by_cell.png       SR with CIs; figures/<episode>.png trajectories (robot coloured by time)
    videos/<episode>.mp4         both cameras, depth, the method's BEV input, top-down
    mcap/<episode>.mcap          the same episodes as MCAP logs (open in Foxglove)
    traces/<episode>.npz         every episode's trace (sim.trace.EpisodeTrace)
    rows/<episode>.json          each finished episode's row, written last (``--resume`` skips those episodes; it
                                 assumes the same config and checkpoints, as ``train --resume`` does)
    long_horizon/episodes.jsonl, long_horizon/<map>_gvg.png (the map, its GVG and every method's paths)

``<episode>`` is ``[lh_|route_|sc_|scnc_]<scene or scenario>_d<density>_s<seed>_<method>``.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from evaluation.cost import Clock, cost_markdown, episode_name, part_cost
from evaluation.harness import Job, pending, run_jobs_cached
from evaluation.methods import MethodSpec, available_methods, resolve_methods
from evaluation.report import (
    paired,
    paired_pooled,
    plot_cue_timing,
    plot_cue_twins,
    plot_sr,
    report_markdown,
    results,
    results_csv,
    training_budget,
)
from pipeline.core import layout
from pipeline.core.artifacts import atomic_write_json, atomic_write_text, json_safe
from pipeline.core.config import BaseStageConfig, check_run_name
from pipeline.core.errors import ConfigError
from pipeline.core.executor import Executor, check_executor, check_ray_files
from pretrain.quantize import check_precision, resolve_encoder_precision
from rl.lookahead import check_shield_s
from rl.policy import check_checkpoint_weights
from sim.env import CrowdNavEnv, SimConfig
from sim.planners.topomap import build_gvg, plot_topomap
from sim.scenario import cue_twin_metrics, load_scenario
from sim.scene import check_episode_grid
from sim.trace import EpisodeTrace

log = logging.getLogger("icrowdnav")


@dataclass
class LongHorizonConfig:
    """Long-horizon runs (paper §IV-C): GVG topological map, start and goal on it, waypoints for the local policy."""

    maps: list[str] = field(default_factory=lambda: ["office_floor", "hospital_floor"])
    runs: int = 25  # per map and method (the paper: 25)
    density: float = 0.1
    min_path_m: float = 20.0  # goals at least this far from the start along the graph
    max_episode_s: float = 150.0


@dataclass
class EvalConfig(BaseStageConfig):
    """Config of the ``eval`` stage."""
    PLACEMENT_FIELDS: ClassVar[tuple[str, ...]] = ("workers",)  # every episode seeded by itself: the same rows

    run_name: str = field(default="benchmark", metadata={"help": "output folder under DATA_DIR/eval/"})
    methods: list[str] = field(default_factory=lambda: ["expert", "teacher", "full", "no_i2", "no_bev", "dwa",
                                                        "drl_vo", "sarl_om", "vint"],
                               metadata={"help": "methods (evaluation.methods)"})
    scenes: list[str] = field(default_factory=lambda: ["office_lobby", "hospital_corridor", "warehouse"])
    densities: list[float] = field(default_factory=lambda: [0.1, 0.2])
    goals: int = field(default=25, metadata={"help": "start-goal pairs per cell (the paper: 25)"})
    trials: int = field(default=3, metadata={"help": "crowds per goal (the paper: 3); N = goals x trials per cell"})
    method_episodes: dict[str, int] = field(default_factory=dict, metadata={
        "help": "per method, at most n episodes per cell instead of goals x trials, e.g. {full: 10}: the cell's first n in "
                "trial-major order (trial 0 of every goal, then trial 1, ...), so a capped method runs a paired subset "
                "of the others' episodes on distinct goals (benchmark and routing cells)"})
    routing_method_episodes: dict[str, int] = field(default_factory=dict, metadata={
        "help": "per method capped by method_episodes, its cap in the routing cells instead (same order), e.g. "
                "{full: 10}; a method without a method_episodes cap runs every routing episode"})
    routing_scenes: list[str] = field(default_factory=lambda: ["warehouse_routing"],
                                      metadata={"help": "extra cells where every method follows the global "
                                                        "planner's waypoints (reported separately)"})
    scenarios: list[str] = field(default_factory=lambda: ["blind_corner", "crossing_turn", "head_on", "overtaking",
                                                          "doorway"],
                                 metadata={"help": "scenario files (sim/scenarios/ or paths) every method runs"})
    scenario_trials: int = field(default=3, metadata={"help": "seeded episodes per scenario and method"})
    cue_twins: list[str] = field(default_factory=list, metadata={
        "help": "scenarios whose trials (when in `scenarios`) also run as their no-cue twin — the same seed and walk, the "
                "scripted pedestrians' head and torso lead switched off — to measure what the cue alone changes in "
                "each method's commands (sim.scenario.cue_twin_metrics)"})
    paired_with: str = field(default="full", metadata={"help": "the method every other is paired against"})
    shield_s: float | None = field(default=None, metadata={
        "help": "the saved policies' obstacle shield horizon in s instead of their own (rl.lookahead; 0 = off, "
                "none = as saved): ablate or add the shield without retraining — inside a lookahead head, or on an "
                "MLP-head student's logits (rl.lookahead.ObstacleShield on its perceived depth scan)"})
    sample_tau: float | None = field(default=None, metadata={
        "help": "the saved policies (teacher, students) pick each action by sampling softmax(logits / tau), seeded "
                "per episode, instead of the argmax (none = argmax, as trained policies are normally evaluated)"})
    encoder_precision: str | None = field(default=None, metadata={
        "help": "the students' frozen encoder at this precision instead of the one each was trained with: fp32 | "
                "bf16 (its convolutions in bfloat16) | int8 (its int8 version) | auto (bf16 where this machine's CPU has native "
                "bfloat16, else fp32), pretrain.quantize; none = as trained"})
    seed_base: int = field(default=20_000, metadata={"help": "episode seeds are seed_base + seed + k"})
    workers: int = 2
    executor: str = field(default="auto", metadata={"help": "where episodes run: auto (Ray when RAY_ADDRESS is set) "
                                                            "| local | ray (pipeline.core.executor)"})
    ray_address: str = field(default="", metadata={"help": "Ray cluster address host:port (empty: RAY_ADDRESS, or "
                                                           "a Ray instance started on this machine)"})
    ray_files: str = field(default="shared", metadata={
        "help": "on Ray, how checkpoints and episode files travel: shared (every node reads and writes the data dir: "
                "a shared filesystem) | transfer (through Ray's object store; only the driver touches the data dir)"})
    figures: int = field(default=1, metadata={"help": "trajectory PNGs per cell and method (first episodes)"})
    videos: int = field(default=1, metadata={"help": "mp4 + MCAP per cell and method (first episodes, rendered)"})
    long_horizon: LongHorizonConfig = field(default_factory=LongHorizonConfig)
    sim: SimConfig = field(default_factory=lambda: SimConfig(timeout_s_per_m=5.0))
    progress: bool = True

    @property
    def episodes(self) -> int:
        """Episodes per cell and method: ``goals`` × ``trials``."""
        return self.goals * self.trials

    def episodes_of(self, method: str, routing: bool = False) -> int:
        """Episodes per cell that ``method`` runs: ``goals`` × ``trials``, at most its ``method_episodes`` cap (in a
        routing cell its ``routing_method_episodes`` cap instead, when it has both: uncapping a method with
        ``--method_episodes '{}'`` uncaps it everywhere)."""
        cap = self.method_episodes.get(method, self.episodes)
        if routing and method in self.method_episodes:
            cap = self.routing_method_episodes.get(method, cap)
        return min(cap, self.episodes)

    def validate(self) -> None:
        super().validate()
        check_run_name(self.run_name)
        if not self.scenes:
            raise ConfigError("eval.scenes: expected at least one scene")
        check_shield_s(self.shield_s, "eval.shield_s", optional=True)
        if self.encoder_precision is not None:
            check_precision(self.encoder_precision, "eval.encoder_precision", "cpu")  # the workers run on the CPU
        if self.sample_tau is not None and not (math.isfinite(self.sample_tau) and 0.01 <= self.sample_tau <= 100.0):
            raise ConfigError(f"eval.sample_tau: expected none (argmax) or a temperature in [0.01, 100], got "
                              f"{self.sample_tau!r}")
        for k in ("goals", "trials"):
            if not isinstance(getattr(self, k), int) or not 1 <= getattr(self, k) <= 10_000:
                raise ConfigError(f"eval.{k}: expected an integer in [1, 10000], got {getattr(self, k)!r}")
        check_episode_grid(self.scenes, self.densities, self.episodes, self.workers)
        if self.routing_scenes:
            check_episode_grid(self.routing_scenes, self.densities, self.episodes, self.workers)
        for name in self.scenarios:
            load_scenario(name)  # unknown / invalid -> one ConfigError naming file, field, expected, actual
        if len(set(self.scenarios)) != len(self.scenarios):
            raise ConfigError(f"eval.scenarios: expected distinct scenarios, got {self.scenarios}")
        for name in self.cue_twins:  # twinned only when also in `scenarios` (a profile's twins survive --scenarios)
            load_scenario(name)
        if not isinstance(self.scenario_trials, int) or not 1 <= self.scenario_trials <= 1000:
            raise ConfigError(f"eval.scenario_trials: expected an integer in [1, 1000], got {self.scenario_trials!r}")
        if not self.methods:
            raise ConfigError("eval.methods: expected at least one method")
        for key in ("method_episodes", "routing_method_episodes"):
            for name, n in getattr(self, key).items():
                if name not in available_methods():
                    raise ConfigError(f"eval.{key}: expected method names of {available_methods()}, got {name!r}")
                if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= 10_000:
                    raise ConfigError(f"eval.{key}.{name}: expected an integer in [1, 10000], got {n!r}")
        check_executor(self.executor, self.ray_address, "eval")
        check_ray_files(self.ray_files, "eval")
        if self.figures < 0 or self.videos < 0:
            raise ConfigError(f"eval.figures/videos: expected >= 0, got {self.figures}/{self.videos}")
        lh = self.long_horizon
        if not all(math.isfinite(v) for v in (lh.min_path_m, lh.max_episode_s, lh.density)) or lh.density < 0:
            raise ConfigError(f"eval.long_horizon: expected finite min_path_m, max_episode_s and density >= 0, got "
                              f"{lh.min_path_m}, {lh.max_episode_s}, {lh.density}")
        if lh.runs < 0 or lh.min_path_m <= 0 or lh.max_episode_s <= self.sim.dt_s:
            raise ConfigError("eval.long_horizon: expected runs >= 0, min_path_m > 0, max_episode_s > dt_s")
        if lh.runs:
            check_episode_grid(lh.maps, [lh.density], lh.runs, self.workers)


def output_dir(cfg: EvalConfig) -> Path:
    return layout.eval_dir(cfg.data_dir, cfg.run_name)


def inputs(cfg: EvalConfig) -> list[Path]:
    specs = resolve_methods(cfg.methods, Path(cfg.data_dir), cfg.shield_s, cfg.sample_tau,
                            cfg.encoder_precision)  # unknown / missing -> one error
    for m in specs:  # a damaged or non-finite checkpoint: one error naming the file, before any episode (or MCAP)
        if m.checkpoint is not None:
            check_checkpoint_weights(m.checkpoint)
    return [p for m in specs if m.checkpoint is not None
            for p in (m.checkpoint / "policy.json", m.checkpoint / "policy.safetensors")]


GOAL_SEED_OFFSET = 100_000  # goal g's scene seed is seed_base + seed + GOAL_SEED_OFFSET + g


def seeds_of(cfg: EvalConfig) -> list[int]:
    """The episode seeds of a cell: ``goals`` × ``trials`` consecutive seeds, goal-major."""
    return [cfg.seed_base + cfg.seed + k for k in range(cfg.episodes)]


def protocol_of(cfg: EvalConfig) -> list[dict[str, int]]:
    """Per episode of a cell: its ``seed`` (the crowd), ``goal`` index, ``trial`` index, ``scene_seed`` (the
    goal's clutter, start and goal — the same for every trial of the goal and every method) and ``rank``, its place
    in trial-major order: a method capped at n episodes (``method_episodes``) runs those with ``rank < n``."""
    return [{"seed": seed, "goal": k // cfg.trials, "trial": k % cfg.trials,
             "scene_seed": cfg.seed_base + cfg.seed + GOAL_SEED_OFFSET + k // cfg.trials,
             "rank": (k % cfg.trials) * cfg.goals + k // cfg.trials}
            for k, seed in enumerate(seeds_of(cfg))]


def benchmark_jobs(cfg: EvalConfig, specs: list[MethodSpec], out: Path, scenes: list[str] | None = None,
                   route: bool = False) -> list:
    """Every (scene, density, episode, method) job; ``route``: the methods follow the global planner's waypoints."""
    jobs = []
    protocol = protocol_of(cfg)
    caps = {m.name: cfg.episodes_of(m.name, routing=route) for m in specs}
    for s in cfg.scenes if scenes is None else scenes:
        for d in cfg.densities:
            for k, ep in enumerate(protocol):
                for m in specs:  # methods interleaved: a killed or slow run has every method on the same seeds
                    if ep["rank"] >= caps[m.name]:
                        continue
                    jobs.append(Job(m, cfg.sim, s, float(d), ep["seed"], out, figure=k < cfg.figures,
                                    video=k < cfg.videos, mcap=k < cfg.videos, scene_seed=ep["scene_seed"],
                                    route=route, tag="route_" if route else "",
                                    extra={"goal": ep["goal"], "trial": ep["trial"]}))
    return jobs


def scenario_jobs(cfg: EvalConfig, specs: list[MethodSpec], out: Path) -> list:
    """Every (scenario, trial, method) job: the scenario's density, seeds ``seed_base + seed + 200_000 + trial``;
    the first trials get a figure and a video + MCAP log as for the benchmark cells."""
    jobs = []
    for name in cfg.scenarios:
        sc = load_scenario(name)
        for t in range(cfg.scenario_trials):
            for m in specs:
                jobs.append(Job(m, cfg.sim, sc.name, sc.density, cfg.seed_base + cfg.seed + 200_000 + t, out,
                                figure=t < max(cfg.figures, 1), video=t < cfg.videos, mcap=t < cfg.videos,
                                scenario=name, tag="sc_", extra={"trial": t}))
    return jobs


def cue_twin_jobs(cfg: EvalConfig, specs: list[MethodSpec], out: Path) -> list:
    """The no-cue twin of every job of the ``cue_twins`` scenarios: the same seed with the scripted pedestrians'
    head and torso lead switched off (``SimConfig.scenario_cues``), files under ``out`` prefixed ``scnc_``."""
    sim = replace(cfg.sim, scenario_cues=False)
    return [replace(j, sim=sim, out=out, tag="scnc_") for j in scenario_jobs(cfg, specs, out)
            if j.scenario in cfg.cue_twins]


def cue_twin_rows(cued_rows: list[dict[str, Any]], twin_rows: list[dict[str, Any]], cued_dir: Path,
                  twin_dir: Path) -> list[dict[str, Any]]:
    """Per trial and method with both runs: :func:`sim.scenario.cue_twin_metrics` on the two traces, with the
    scripted pedestrians' clearance, collision and success in each run (``twin_*``: without the cue)."""
    cued_by = {(r["scene"], r["seed"], r["method"]): r for r in cued_rows}
    out = []
    for t in twin_rows:
        c = cued_by.get((t["scene"], t["seed"], t["method"]))
        if c is None:
            continue
        peds = c.get("scripted_peds")
        if peds is None and float(c["density"]):  # a row of a run older than the twins, with a crowd
            raise ConfigError(f"{cued_dir / 'episodes.jsonl'}: expected scenario rows with 'scripted_peds' "
                              f"(rerun the scenarios without --resume), got a row of "
                              f"{episode_name('sc_', c['scene'], c['density'], c['seed'], c['method'])} without it")
        cued, twin = _twin_traces(c, cued_dir, twin_dir)
        if peds is None:  # ... without a crowd: every pedestrian is scripted
            peds = list(range(cued.ped_xy.shape[1]))
        # a row read back from rows/ (--resume) holds null where a cue never came (NaN when written)
        onset, lead = (math.nan if c.get(k) is None else float(c[k]) for k in ("cue_onset_s", "cue_lead_s"))
        m = cue_twin_metrics(cued, twin, np.asarray(peds, int), onset, lead)
        out.append({"method": t["method"], "scene": t["scene"], "density": t["density"], "seed": t["seed"],
                    "trial": t.get("trial"), "cue_onset_s": onset, "cue_lead_s": lead,
                    "scripted_peds": [int(i) for i in peds], **m,
                    **{k: c[k] for k in ("success", "collision_scripted", "min_clearance_scripted_m")},
                    **{f"twin_{k}": t[k] for k in ("success", "collision_scripted", "min_clearance_scripted_m")}})
    return out


def _twin_traces(r: dict[str, Any], cued_dir: Path, twin_dir: Path) -> tuple[EpisodeTrace, EpisodeTrace]:
    """The traces of scenario row ``r``'s trial with its cue (``cued_dir``) and without (``twin_dir``)."""
    key = (r["scene"], r["density"], r["seed"], r["method"])
    return (EpisodeTrace.load_npz(cued_dir / "traces" / f"{episode_name('sc_', *key)}.npz"),
            EpisodeTrace.load_npz(twin_dir / "traces" / f"{episode_name('scnc_', *key)}.npz"))


def _plot_cue_twins(rows: list[dict[str, Any]], labels: dict[str, str], sc_dir: Path) -> None:
    """Per scenario, its first trial with and without the cue for every method (figures/cue_twin_<scenario>.png), and
    when every method answered the cue in every trial (figures/cue_timing.png)."""
    if not rows:
        return
    figs = sc_dir / "figures"
    figs.mkdir(parents=True, exist_ok=True)
    for scene in dict.fromkeys(r["scene"] for r in rows):
        first = min(r["seed"] for r in rows if r["scene"] == scene)
        pairs = {r["method"]: (*_twin_traces(r, sc_dir, sc_dir / "nocue"), r) for r in rows
                 if r["scene"] == scene and r["seed"] == first and math.isfinite(r["cue_onset_s"])}
        if pairs:
            plot_cue_twins(pairs, labels, f"{scene}, seed {first}: with and without the walker's head/torso lead",
                           figs / f"cue_twin_{scene}.png")
    plot_cue_timing(rows, labels, figs / "cue_timing.png")


def long_horizon_plans(cfg: EvalConfig) -> list[dict[str, Any]]:
    """Per map and run: the seed, a start node, a goal among the candidate goals, the GVG waypoints."""

    lh = cfg.long_horizon
    plans = []
    for name in lh.maps:
        env = CrowdNavEnv(config=replace(cfg.sim, scene=name, density=0.0, obs_mode="state", info_level="basic"))
        env.reset(seed=cfg.seed_base + cfg.seed)
        topo = build_gvg(env.layout, env.cfg.robot.radius_m)
        for k in range(lh.runs):
            seed = cfg.seed_base + 50_000 + cfg.seed + k
            rng = np.random.default_rng(seed)
            start = topo.nodes_xy[rng.integers(len(topo.nodes_xy))]
            for _ in range(50):  # a start with goals far enough along the graph
                d = topo.graph_distances(start)
                if np.sum(np.isfinite(d) & (d >= lh.min_path_m)):
                    break
                start = topo.nodes_xy[rng.integers(len(topo.nodes_xy))]
            goal = topo.candidate_goals(rng, 1, lh.min_path_m, start)[0]
            wps = topo.plan(start, goal)
            plans.append({"map": name, "seed": seed, "start": start, "goal": goal, "waypoints": wps, "topo": topo,
                          "layout": env.layout})
        env.close()
    return plans


def body(cfg: EvalConfig, out: Path) -> dict[str, Any]:
    ex = Executor.of(cfg)
    with ex.session(cfg.workers):  # one Ray connection for every part (nothing for the local pool)
        return _body(cfg, out, ex)


def encoder_precision_of(cfg: EvalConfig) -> str | None:
    """The students' encoder precision this run forces (None: each as trained), ``auto`` resolved once here, on the
    machine the stage runs on (every episode of the run then uses the same one, wherever it runs)."""
    if cfg.encoder_precision is None:
        return None
    return resolve_encoder_precision(cfg.encoder_precision, "eval.encoder_precision", "cpu")


def _body(cfg: EvalConfig, out: Path, ex: Executor) -> dict[str, Any]:
    precision = encoder_precision_of(cfg)
    specs = resolve_methods(cfg.methods, Path(cfg.data_dir), cfg.shield_s, cfg.sample_tau, precision)
    labels = {m.name: m.label for m in specs}
    seeds = seeds_of(cfg)
    costs: dict[str, dict[str, Any]] = {}

    def part(name: str, jobs: list, desc: str) -> list[dict[str, Any]]:  # one part's rows, and what it cost
        ran = len(pending(jobs, out / "rows"))
        clock = Clock()
        got = run_jobs_cached(jobs, out / "rows", cfg.workers, desc, cfg.progress, ex)
        costs[name] = part_cost(jobs, clock.read()[0], ran)
        return got

    rows = part("benchmark", benchmark_jobs(cfg, specs, out), "eval: benchmark")
    routing_rows: list[dict[str, Any]] = []
    if cfg.routing_scenes:
        routing_rows = part("routing", benchmark_jobs(cfg, specs, out / "routing", cfg.routing_scenes, route=True),
                            "eval: routing")
        atomic_write_text(out / "routing" / "episodes.jsonl",
                          "".join(json.dumps(r) + "\n" for r in json_safe(routing_rows)))
    sc_rows: list[dict[str, Any]] = []
    if cfg.scenarios:
        sc_rows = part("scenarios", scenario_jobs(cfg, specs, out / "scenarios"), "eval: scenarios")
        atomic_write_text(out / "scenarios" / "episodes.jsonl",
                          "".join(json.dumps(r) + "\n" for r in json_safe(sc_rows)))
    tw_rows: list[dict[str, Any]] = []
    if cfg.cue_twins:
        twins = part("no-cue twins", cue_twin_jobs(cfg, specs, out / "scenarios" / "nocue"), "eval: no-cue twins")
        tw_rows = cue_twin_rows(sc_rows, twins, out / "scenarios", out / "scenarios" / "nocue")
        _plot_cue_twins(tw_rows, labels, out / "scenarios")
        atomic_write_text(out / "scenarios" / "cue_twins.jsonl",
                          "".join(json.dumps(r) + "\n" for r in json_safe(tw_rows)))
    lh_rows: list[dict[str, Any]] = []
    lh_seeds: dict[str, list[int]] = {}
    if cfg.long_horizon.runs:
        lh = cfg.long_horizon
        plans = long_horizon_plans(cfg)
        sim_lh = replace(cfg.sim, max_episode_s=lh.max_episode_s)
        jobs = [Job(m, sim_lh, p["map"], lh.density, p["seed"], out / "long_horizon", figure=False, tag="lh_",
                    waypoints=p["waypoints"], start=p["start"], goal=p["goal"],
                    extra={"graph_path_m": float(np.sum(np.hypot(*np.diff(
                        np.vstack([p["start"], p["waypoints"]]), axis=0).T)))})
                for p in plans for m in specs]
        lh_rows = part("long horizon", jobs, "eval: long horizon")
        _plot_long_horizon(plans, lh_rows, out / "long_horizon", labels)
        for p in plans:
            lh_seeds.setdefault(p["map"], []).append(p["seed"])
        atomic_write_text(out / "long_horizon" / "episodes.jsonl",
                          "".join(json.dumps(r) + "\n" for r in json_safe(lh_rows)))
    atomic_write_json(out / "seeds.json", {"benchmark": {"seeds": seeds, "scenes": cfg.scenes,
                                                         "routing_scenes": cfg.routing_scenes,
                                                         "scenarios": cfg.scenarios,
                                                         "scenario_trials": cfg.scenario_trials,
                                                         "cue_twins": cfg.cue_twins,
                                                         "densities": cfg.densities, "episodes": protocol_of(cfg),
                                                         "episodes_per_method": {m.name: cfg.episodes_of(m.name)
                                                                                 for m in specs},
                                                         "routing_episodes_per_method": {
                                                             m.name: cfg.episodes_of(m.name, routing=True)
                                                             for m in specs}},
                                           "long_horizon": lh_seeds})
    atomic_write_text(out / "episodes.jsonl", "".join(json.dumps(r) + "\n" for r in json_safe(rows)))
    res = results(rows)
    atomic_write_json(out / "results.json", json_safe(res))
    atomic_write_text(out / "results.csv", results_csv(res))
    atomic_write_json(out / "paired.json", json_safe({"reference": cfg.paired_with,
                                                      "cells": paired(rows, cfg.paired_with),
                                                      "pooled": paired_pooled(rows, cfg.paired_with),
                                                      "routing": paired(routing_rows, cfg.paired_with)}))
    plot_sr(res, labels, out / "figures" / "sr_by_cell.png")
    header = (f"# Benchmark `{cfg.run_name}`\n\n{cfg.episodes} episodes per cell = {cfg.goals} goals × {cfg.trials} "
              f"trials (seeds {seeds[0]}..{seeds[-1]}, the same for every method; the paper: 25 × 3 = 75), "
              f"time limit max({cfg.sim.max_episode_s:g} s, {cfg.sim.timeout_s_per_m:g} s/m × shortest path), "
              f"{len(specs)} methods: " + ", ".join(f"`{m.name}` = {m.label}" for m in specs) + "."
              + _capped_text(cfg, specs)
              + (f" The saved policies sample their actions (softmax of the logits / {cfg.sample_tau:g}, seeded per "
                 "episode) instead of taking the argmax." if cfg.sample_tau is not None else "")
              + (f" The students' frozen encoder runs in {precision}"
                 + (" (`auto` on this machine)" if cfg.encoder_precision == "auto" else "")
                 + " whatever they were trained with." if precision is not None else ""))
    refs = [m.name for m in specs if m.reference]
    budgets = {m.name: training_budget(m.checkpoint) for m in specs if m.checkpoint is not None}
    atomic_write_json(out / "cost.json", json_safe({"workers": cfg.workers, "parts": costs}))
    atomic_write_text(out / "report.md", report_markdown(rows, labels, header, lh_rows, refs, budgets,
                                                         routing_rows, cfg.paired_with, sc_rows, tw_rows)
                      + "\n".join(["", *cost_markdown(costs, labels, cfg.workers)]))
    counts: dict[str, Any] = {"episodes": len(rows), "routing_episodes": len(routing_rows),
                              "scenario_episodes": len(sc_rows), "cue_twin_episodes": len(tw_rows),
                              "long_horizon_episodes": len(lh_rows)}
    for cell, by in {**res, **results(routing_rows)}.items():
        for m, agg in by.items():
            counts[f"sr_{m}_{cell}"] = round(float(agg["success"]["mean"]), 3)
    return counts


def _capped_text(cfg: EvalConfig, specs: list[MethodSpec]) -> str:
    """The header's sentence on methods run on fewer episodes per cell (``method_episodes``), or nothing."""
    def n(m: str) -> str:
        cell, route = cfg.episodes_of(m), cfg.episodes_of(m, routing=True)
        return f"`{m}` N = {cell}" + (f" ({route} in the routing cells)" if cfg.routing_scenes and route != cell else "")

    capped = [m.name for m in specs if min(cfg.episodes_of(m.name), cfg.episodes_of(m.name, routing=True))
              < cfg.episodes]
    if not capped:
        return ""
    return (" Fewer episodes per cell (the first in trial-major order, a subset of the others' on distinct goals; "
            "paired tests use the episodes both methods ran): " + ", ".join(n(m) for m in capped) + ".")


def _plot_long_horizon(plans: list[dict[str, Any]], rows: list[dict[str, Any]], out: Path,
                       labels: dict[str, str]) -> None:

    by_map: dict[str, list[dict[str, Any]]] = {}
    for p in plans:
        by_map.setdefault(p["map"], []).append(p)
    for name, ps in by_map.items():
        first = ps[0]
        paths = {}
        for r in rows:
            if r["scene"] == name and r["seed"] == first["seed"]:
                tr = EpisodeTrace.load_npz(out / "traces" / f"lh_{name}_d{r['density']:g}_s{r['seed']}_{r['method']}.npz")
                paths[f"{labels.get(r['method'], r['method'])} ({r['outcome']})"] = tr.robot_xy
        plot_topomap(first["layout"], first["topo"], out / f"{name}_gvg.png", paths=paths, start_xy=first["start"],
                     goals_xy=np.array([p["goal"] for p in ps]), waypoints=first["waypoints"],
                     title=f"{name}: paths of run seed {first['seed']}, every run's goal")
