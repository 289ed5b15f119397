"""Seeded benchmark episodes in a process pool: one job = (method, scene, density, seed[, scene seed, waypoints]).

Every method of a run faces the same list of seeds, so the same start, goal, obstacles and crowd
(:func:`initial_state` of two methods' envs is equal — tested). A job's ``scene_seed`` draws the clutter, start
and goal (the benchmark's goal) and its ``seed`` the crowd (the trial); ``route`` makes the method follow the
global planner's waypoints to the goal (the routing cells). A job returns its metrics row (every metric of
:mod:`sim.metrics`, plus method / scene / density / seed / outcome) and, when asked, writes the episode's trace,
a top-down trajectory figure, an mp4 (both cameras, the method's BEV input, top-down) and an MCAP log for Foxglove;
it always writes what it cost (:mod:`evaluation.cost`).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import gymnasium as gym
import numpy as np

from evaluation.cost import Clock, episode_name, write_cost
from evaluation.methods import MethodSpec
from pipeline.core.artifacts import atomic_write_text
from pipeline.core.errors import CorruptArtifactError
from pipeline.core.executor import Bundle, Executor, in_scratch, map_jobs, receive_files
from recorder.mcap.writer import EpisodeWriter
from recorder.schema import episode_meta_from_env, frame_from_env
from rl.policy import checkpoint_bundle
from sim.env import CrowdNavEnv, SimConfig
from sim.episode import episode_steps
from sim.metrics import episode_metrics
from sim.scenario import scenario_metrics
from sim.viz import colorize_depth, compose_frame, plot_episode_topdown, write_video
from sim.wrappers import FollowWaypoints

log = logging.getLogger("icrowdnav")


@dataclass
class Job:
    """One evaluation episode."""

    method: MethodSpec
    sim: SimConfig
    scene: str
    density: float
    seed: int
    out: Path
    figure: bool = False
    video: bool = False
    mcap: bool = False
    waypoints: np.ndarray | None = None  # long horizon: the topological plan (world frame), last = the goal
    goal: np.ndarray | None = None  # long horizon: start/goal chosen on the map (overrides the sampled pair)
    start: np.ndarray | None = None
    scene_seed: int | None = None  # the benchmark's goal: clutter, start and goal from this seed (env reset option)
    route: bool = False  # follow the global planner's waypoints from start to goal (the routing cells)
    scenario: str = ""  # a scenario (sim.scenario): its scene, start, goal and scripted pedestrians; ``scene`` names it
    tag: str = ""  # a prefix for file names (e.g. "lh")
    save_trace: bool = True  # traces/<name>.npz
    row_cache: Path | None = None  # write the finished row to <row_cache>/<name>.json (last: eval --resume skips it)
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return episode_name(self.tag, self.scene, self.density, self.seed, self.method.name)


_DRIVERS: dict[str, Any] = {}


def cached_driver(spec: MethodSpec):
    """The driver of ``spec``, made once per process (its weights loaded once)."""
    key = f"{spec.name}:{spec.checkpoint}:{spec.shield_s}:{spec.sample_tau}:{spec.encoder_precision}"
    if key not in _DRIVERS:  # one driver per method and checkpoint per process (weights loaded once)
        _DRIVERS[key] = spec.driver()
    return _DRIVERS[key]


def make_env(job: Job) -> gym.Env:
    """The env of ``job``: its method's obs mode (rendered when a video or a log is asked), the long-horizon
    waypoints (:class:`sim.wrappers.FollowWaypoints`), and what the method may know (:meth:`MethodSpec.wrap`)."""
    rendered = job.video or job.mcap
    over = job.method.env_overrides()
    if rendered:
        over["obs_mode"] = "visual"
    if job.mcap:
        over["detect_poses"] = True  # the episode's log holds the detections (recorder.schema)
    where = {"scenario": job.scenario} if job.scenario else {"scene": job.scene, "scenario": ""}
    cfg = replace(job.sim, **where, density=job.density, info_level="full" if job.mcap else "basic", **over)
    env: gym.Env = CrowdNavEnv(config=cfg, render_mode="rgb_array" if job.video else None)
    if job.waypoints is not None or job.route:
        env = FollowWaypoints(env, job.waypoints)
    return job.method.wrap(env)


def initial_state(env: gym.Env) -> dict[str, np.ndarray]:
    """What defines an episode's start: robot pose, goal, pedestrian positions/velocities/goals."""
    u = env.unwrapped
    return {"robot": np.asarray(u.robot, float).copy(), "goal": np.asarray(u.goal, float).copy(),
            "peds": np.asarray(u.crowd.pos, float).copy(), "ped_vel": np.asarray(u.crowd.vel, float).copy()}


def reset_options(job: Job) -> dict | None:
    """The reset options of ``job``: a given start and goal (long-horizon runs on a map) and / or the goal's
    scene seed; None when it has neither."""
    out: dict[str, Any] = {}
    if job.start is not None:
        out.update(start=[float(v) for v in job.start], goal=[float(v) for v in job.goal])
    if job.scene_seed is not None:
        out["scene_seed"] = int(job.scene_seed)
    return out or None


def run_episode(job: Job) -> dict[str, Any]:
    """Runs ``job`` through the episode loop (:func:`sim.episode.episode_steps`); returns its metrics row (and
    writes what it was asked to)."""
    loading = Clock()
    driver = cached_driver(job.method)
    load_s = loading.read()[0]
    clock = Clock()  # the episode's own cost (evaluation.cost): its world, every step's sensors and decision
    env = make_env(job)
    u = env.unwrapped
    frames: list[np.ndarray] = []
    writer = None
    try:
        for tr in episode_steps(env, driver, job.seed, reset_options(job)):
            if tr.step == 0 and job.mcap:
                (job.out / "mcap").mkdir(parents=True, exist_ok=True)
                path = job.out / "mcap" / f"{job.name}.mcap"
                if path.exists():
                    path.unlink()
                writer = EpisodeWriter(path, episode_meta_from_env(u, job.seed, f"eval:{job.method.name}"),
                                       u.layout.occupancy)
                writer.start()
            if writer is not None:  # the log keeps the goal-directed state s (a waypoint re-targets the policy's)
                obs = {**tr.obs, "state": u.robot_state()}
                step_kw = {} if tr.step == 0 else {"command": tuple(u.robot_v), "reward": tr.reward, "done": tr.done}
                writer.add(frame_from_env(u, obs, tr.info, tr.step, **step_kw))
            if job.video and tr.step > 0:
                frames.append(_video_frame(u, tr.obs, tr.info, driver))
        if writer is not None:
            writer.finish()
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    wall_s, cpu_s = clock.read()
    trace = u.trace(method=job.method.name)
    layout = u.layout
    time_limit_s = float(u.time_limit_s)
    scripted, events = u.crowd.scripted.copy(), list(u.crowd.events)
    env.close()
    row = {"method": job.method.name, "scene": Path(job.scene).stem, "density": job.density, "seed": job.seed,
           "outcome": trace.outcome, "steps": trace.n_steps, **episode_metrics(trace),
           "time_limit_s": time_limit_s, **job.extra}
    if job.scenario:
        row.update(scenario_metrics(trace, scripted, events), scripted_peds=np.nonzero(scripted)[0].tolist())
    if job.save_trace:
        (job.out / "traces").mkdir(parents=True, exist_ok=True)
        trace.save_npz(job.out / "traces" / f"{job.name}.npz")
    if job.figure:
        (job.out / "figures").mkdir(parents=True, exist_ok=True)
        plot_episode_topdown(layout.obstacles, trace, job.out / "figures" / f"{job.name}.png",
                             bounds=layout.spec.bounds,
                             camera_yaws_deg=(job.sim.camera.yaw_deg, -job.sim.camera.yaw_deg),
                             camera_hfov_deg=job.sim.camera.hfov_deg,
                             title=f"{job.method.label} — {job.name}: {trace.outcome}, "
                                   f"PL {row['path_length_m']:.1f} m, TPZ {row['tpz_s']:.1f} s")
    if job.video and frames:
        (job.out / "videos").mkdir(parents=True, exist_ok=True)
        write_video(frames, job.out / "videos" / f"{job.name}.mp4", fps=1.0 / job.sim.dt_s)
    write_cost(job.out, job.name, method=job.method.name, steps=trace.n_steps, wall_s=wall_s, cpu_s=cpu_s,
               load_s=load_s, rendered=job.video or job.mcap)
    write_row(job, row)
    return row


def write_row(job: Job, row: dict[str, Any]) -> None:
    """``row`` into ``job``'s row cache, if it has one — last: a row on disk means every file of the episode is
    complete."""
    if job.row_cache is not None:
        job.row_cache.mkdir(parents=True, exist_ok=True)
        atomic_write_text(job.row_cache / f"{job.name}.json", json.dumps(row) + "\n")


def _video_frame(env: CrowdNavEnv, obs: dict[str, np.ndarray], info: dict, driver) -> np.ndarray:
    panels = [obs["rgb_left"], obs["rgb_right"], colorize_depth(obs["depth_left"]),
              colorize_depth(obs["depth_right"])]
    labels = ["left RGB", "right RGB", "left depth", "right depth"]
    bev = driver.bev_panel() if hasattr(driver, "bev_panel") else None  # optional in the Driver protocol
    if bev is not None:
        panels.append(_heat(bev))
        labels.append("BEV input")
    panels.append(env.render())
    labels.append(f"top-down t={info['time_s']:.1f}s")
    return compose_frame(panels, labels)


def _heat(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, np.float32)
    a = (a - a.min()) / max(float(a.max() - a.min()), 1e-6)
    img = cv2.applyColorMap((a * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[..., ::-1]
    return np.ascontiguousarray(np.flipud(img))  # row 0 = far / top


def pending(jobs: list[Job], cache: Path) -> list[Job]:
    """The ``jobs`` without a finished row in ``cache`` (what :func:`run_jobs_cached` will run)."""
    return [j for j in jobs if not (cache / f"{j.name}.json").is_file()]


def run_jobs_cached(jobs: list[Job], cache: Path, workers: int, desc: str, progress: bool = True,
                    executor: Executor | None = None) -> list[dict[str, Any]]:
    """:func:`run_jobs` that keeps each finished row in ``cache`` and runs only the jobs without one (a killed run
    continues where it stopped); rows in job order."""
    jobs = [replace(j, row_cache=cache) for j in jobs]
    todo = pending(jobs, cache)
    if len(todo) < len(jobs):
        log.info("%s: %d of %d episodes already done (%s)", desc, len(jobs) - len(todo), len(jobs), cache)
    run_jobs(todo, workers, desc, progress, executor)
    rows = []
    for j in jobs:
        path = cache / f"{j.name}.json"
        try:
            rows.append(json.loads(path.read_text()))
        except (OSError, ValueError) as e:
            raise CorruptArtifactError(f"{path}: unreadable episode row ({type(e).__name__}: {e}); delete it and "
                                       "rerun with --resume") from None
    return rows


def run_jobs(jobs: list[Job], workers: int, desc: str, progress: bool = True,
             executor: Executor | None = None) -> list[dict[str, Any]]:
    """All ``jobs`` in a process pool (fork; each worker loads a method's weights once) or on Ray
    (:mod:`pipeline.core.executor`), rows in job order. On Ray with ``files: transfer`` no task touches the data
    directory: the methods' checkpoints travel as one :class:`~pipeline.core.executor.Bundle`
    (:func:`rl.policy.checkpoint_bundle`), each episode runs in a scratch folder of its node (:func:`run_episode_transfer`),
    and this process writes the files it returns, then its row."""
    if executor is None or not executor.transfers:
        return map_jobs(run_episode, jobs, workers, desc, progress, executor=executor)
    rows: list[dict[str, Any]] = [{} for _ in jobs]

    def arrived(i: int, result: tuple[dict[str, Any], list[tuple[str, bytes, str]]]) -> None:
        row, files = result
        receive_files(jobs[i].out, files)
        write_row(jobs[i], row)
        rows[i] = row

    bundle = checkpoint_bundle([j.method.checkpoint for j in jobs if j.method.checkpoint is not None])
    map_jobs(run_episode_transfer, jobs, workers, desc, progress, executor=executor, on_result=arrived,
             keep_results=False, shared=bundle)
    return rows


def run_episode_transfer(job: Job, shared: Bundle) -> tuple[dict[str, Any], list[tuple[str, bytes, str]]]:
    """:func:`run_episode` on a node without the data directory: the method's checkpoint from the unpacked bundle
    ``shared``, the episode's files written into a scratch folder and returned as ``(row, [(path relative to the
    job's out, bytes, sha256)])``; the scratch folder is removed. A retried task (its worker died) returns the same
    files again; the driver writes an episode's files once, when its result arrives."""
    method = job.method
    if method.checkpoint is not None:
        method = replace(method, checkpoint=shared.local(shared.unpack(), method.checkpoint))
    return in_scratch(lambda scratch: run_episode(replace(job, method=method, out=scratch, row_cache=None)),
                      "icrowdnav-eval-")
