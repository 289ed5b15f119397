"""``icrowdnav rollout``: drive the privileged expert through scenes × densities × seeded episodes.

This is the world's acceptance run — it measures the expert on the same metrics the benchmark uses, and writes
the pictures people look at first (a top-down figure per episode, an mp4 with both camera views). ::

    icrowdnav rollout --scenes office_lobby --densities 0.1 --episodes 50 --workers 2

Output tree (``DATA_DIR/rollouts/<run_name>/``)::

    config.yaml              resolved config
    manifest.json            provenance: params, seed, git commit, versions, outputs with hashes
    seeds.json               the seed list every (scene, density) cell used
    episodes.jsonl           one row per episode: scene, density, seed, outcome, every metric of sim.metrics
    summary.json             aggregate per cell: mean, std, 95 % CI, N of every metric
    summary.md               the paper's table (SR, NT, PL, TPZ, collisions, timeouts, N) per cell
    traces/<cell>_s<seed>.npz         EpisodeTrace of every episode
    figures/<cell>_s<seed>.png        top-down figures of the first ``figures`` episodes per cell
    videos/<cell>_s<seed>.mp4         both cameras + depth + top-down of the first ``videos`` episodes per cell

``<cell>`` is ``<scene>_d<density>``. Episodes are independent jobs run in a local process pool.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import ClassVar, Literal

from tqdm import tqdm

import sim  # noqa: F401  (registers the env)
from pipeline.core.artifacts import atomic_write_json, atomic_write_text, json_safe
from pipeline.core.config import BaseStageConfig, check_run_name
from pipeline.core.errors import ConfigError
from pipeline.core.executor import process_pool
from sim.env import SimConfig
from sim.expert import run_expert_episode
from sim.metrics import aggregate, episode_metrics, metrics_table_markdown
from sim.scene import check_episode_grid
from sim.viz import compose_frame, plot_episode_topdown, write_video

log = logging.getLogger("icrowdnav")


@dataclass
class RolloutConfig(BaseStageConfig):
    """Config of the ``rollout`` stage."""
    PLACEMENT_FIELDS: ClassVar[tuple[str, ...]] = ("workers",)  # every episode seeded by itself

    run_name: str = field(default="expert", metadata={"help": "output folder name under DATA_DIR/rollouts/"})
    scenes: list[str] = field(default_factory=lambda: ["office_lobby"],
                              metadata={"help": "scene names or YAML paths"})
    densities: list[float] = field(default_factory=lambda: [0.1], metadata={"help": "pedestrians per m²"})
    episodes: int = field(default=10, metadata={"help": "episodes per (scene, density); seeds seed..seed+N-1"})
    driver: Literal["expert"] = field(default="expert", metadata={"help": "who drives (policies come with train)"})
    workers: int = field(default=1, metadata={"help": "parallel episode processes"})
    figures: int = field(default=2, metadata={"help": "top-down PNGs per cell (first episodes)"})
    videos: int = field(default=1, metadata={"help": "mp4 videos per cell (first episodes, rendered)"})
    sim: SimConfig = field(default_factory=SimConfig, metadata={"help": "the crowd world"})

    def validate(self) -> None:
        super().validate()
        check_episode_grid(self.scenes, self.densities, self.episodes, self.workers)
        check_run_name(self.run_name)
        if self.figures < 0 or self.videos < 0:
            raise ConfigError(f"figures/videos: expected >= 0, got {self.figures}/{self.videos}")


def cell_name(scene: str, density: float) -> str:
    return f"{Path(scene).stem}_d{density:g}"


def _episode_job(args: tuple) -> dict:
    """Run one expert episode (and its figure/video if asked); returns its metrics row."""
    sim_cfg, scene, density, seed, out, want_fig, want_video = args
    import gymnasium as gym

    cfg = replace(sim_cfg, scene=scene, density=density, obs_mode="state", info_level="basic")
    env = gym.make("icrowdnav/CrowdNav-v0", config=cfg)
    trace = run_expert_episode(env, seed)
    layout = env.unwrapped.layout
    env.close()
    name = f"{cell_name(scene, density)}_s{seed}"
    trace.save_npz(out / "traces" / f"{name}.npz")
    row = {"scene": Path(scene).stem, "density": density, "seed": seed, "method": "expert",
           "outcome": trace.outcome, "steps": trace.n_steps, **episode_metrics(trace)}
    if want_fig:
        m = row
        plot_episode_topdown(layout.obstacles, trace, out / "figures" / f"{name}.png", bounds=layout.spec.bounds,
                             camera_yaws_deg=(sim_cfg.camera.yaw_deg, -sim_cfg.camera.yaw_deg),
                             camera_hfov_deg=sim_cfg.camera.hfov_deg,
                             title=f"{name} expert: {trace.outcome}, NT {m['nav_time_s']:.1f} s, "
                                   f"PL {m['path_length_m']:.1f} m, TPZ {m['tpz_s']:.1f} s")
    if want_video:
        _video(sim_cfg, scene, density, seed, out / "videos" / f"{name}.mp4", trace)
    return row


def _video(sim_cfg: SimConfig, scene: str, density: float, seed: int, path: Path, ref_trace) -> None:
    """Re-run the seeded episode with rendering on and write both cameras, depth and a top-down view."""
    import gymnasium as gym
    import numpy as np

    cfg = replace(sim_cfg, scene=scene, density=density, obs_mode="visual")
    env = gym.make("icrowdnav/CrowdNav-v0", config=cfg, render_mode="rgb_array")
    frames: list[np.ndarray] = []

    def grab(tr):
        if tr.step == 0:  # frames of the steps, not of the reset
            return
        obs, info = tr.obs, tr.info
        frames.append(compose_frame(
            [obs["rgb_left"], obs["rgb_right"], obs["depth_left"], obs["depth_right"], env.render()],
            ["left RGB", "right RGB", "left depth", "right depth", f"top-down t={info['time_s']:.1f}s"]))

    trace = run_expert_episode(env, seed, on_step=grab)
    env.close()
    if not np.allclose(trace.robot_pose, ref_trace.robot_pose):
        raise RuntimeError(f"rendered re-run of {path.stem} diverged from the state-only run (non-determinism)")
    write_video(frames, path, fps=1.0 / sim_cfg.dt_s)


def body(cfg: RolloutConfig, out: Path) -> dict:
    for sub in ("traces", "figures", "videos"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    seeds = [cfg.seed + k for k in range(cfg.episodes)]
    jobs = [(cfg.sim, s, d, seed, out, k < cfg.figures, k < cfg.videos)
            for s in cfg.scenes for d in cfg.densities for k, seed in enumerate(seeds)]
    rows: list[dict] = []
    desc = f"rollout {cfg.driver}"
    if cfg.workers == 1:
        for j in tqdm(jobs, desc=desc, unit="ep"):
            rows.append(_episode_job(j))
    else:
        with process_pool(cfg.workers, "fork") as pool:
            for r in tqdm(pool.map(_episode_job, jobs), total=len(jobs), desc=desc, unit="ep"):
                rows.append(r)
    atomic_write_json(out / "seeds.json", {"seeds": seeds, "scenes": cfg.scenes, "densities": cfg.densities})
    atomic_write_text(out / "episodes.jsonl", "".join(json.dumps(json_safe(r)) + "\n" for r in rows))
    summary, by_cell = {}, {}
    for s in cfg.scenes:
        for d in cfg.densities:
            cell = [r for r in rows if r["scene"] == Path(s).stem and r["density"] == d]
            summary[cell_name(s, d)] = json_safe(aggregate(cell))
            by_cell[f"{Path(s).stem} @ {d:g} ped/m²"] = cell
    atomic_write_json(out / "summary.json", summary)
    atomic_write_text(out / "summary.md", f"# Expert rollouts ({cfg.run_name})\n\nEpisodes per cell: {cfg.episodes}; "
                      f"seeds {seeds[0]}..{seeds[-1]}.\n\n" + metrics_table_markdown(by_cell) + "\n")
    n_succ = sum(r["success"] for r in rows)
    return {"episodes": len(rows), "success_rate": round(n_succ / len(rows), 4),
            "cells": len(cfg.scenes) * len(cfg.densities)}
