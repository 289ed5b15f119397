"""``icrowdnav bench``: performance figures, each fast path measured against a simple reference in the same run.

::

    icrowdnav bench --profile default --data-dir data        # or: make bench

Writes ``DATA_DIR/bench/bench.json`` (a flat dict of named figures; figures written by other stages' benchmarks
are kept, ours are replaced) and prints every figure. Figures (single process, this machine):

* ``env_steps_per_s_norender`` — ``gymnasium.make`` env, office lobby at 0.2 ped/m², ``obs_mode=state``,
  ``info_level=basic``, random actions (the RL fast path); ``..._full_info`` the same with keypoints and the
  static scan in ``info``; ``env_steps_per_s_privileged`` the teacher's observation mode;
* ``env_steps_per_s_render`` — the same with both RGB-D cameras rendered at the profile's resolution plus
  the oracle pose detector (``obs_mode=visual``); ``render_ms_per_camera`` the TinyRenderer share;
* ``sfm_vectorized_speedup`` — :meth:`sim.crowd.Crowd.social_forces` vs the per-agent loop
  :func:`sim.crowd.social_force_reference` on the same state (and ``..._n40`` for a 40-person crowd);
* ``static_distance_speedup`` — vectorised obstacle distances vs the plain loop, 1,000 points;
* ``expert_ms_per_step`` — one decision of the privileged expert;
* ``intention_head_lead_*`` — how long head turns precede walking turns in a free crowd
  (:mod:`sim.intention`; median, 10th and 90th percentile, share of decisions where the head turns first);
* ``record_frames_per_s_1worker`` / ``_2workers`` — the record stage (expert driving, both cameras rendered,
  MCAP written) on ``record_episodes`` episodes of the bench scene, and ``record_mcap_share``, the share of
  recording time spent writing MCAP; ``record_frames_per_s_ray_1node`` / ``_2nodes`` — the same episodes as
  Ray tasks (:mod:`pipeline.core.executor`) on a Ray instance the stage starts (1 node, 2 CPUs; its start-up is in
  the wall time) and on a running two-node local cluster (1 CPU each), and ``record_ray_*_vs_local_pool`` their
  ratios to the 2-worker local pool (``--ray false`` skips them); ``export_frames_per_s`` — the LeRobot export of that recording
  (reading MCAP, lerobot's writer incl. AV1 video and stats; the dataset doctor excluded), one process;
  ``export_frames_per_s_2shards`` the same export in 2 parallel shards merged by lerobot's ``aggregate_datasets``
  (``export_merge_seconds_2shards`` of it the merge) and ``export_speedup_2shards`` the ratio;
* ``chunk_load_ms_ours`` — stock lerobot reading one item with a 100-step action chunk (``chunk_load_steps``)
  (``LeRobotDataset(..., video_backend="pyav", delta_timestamps={"action": 100 steps})[i]``) of that export,
  median of 8 seeded items; ``chunk_load_ms_stock_shaped`` the same on a stock-shaped dataset of the same length
  (same cameras, only ``observation.state``/``action``/``next.reward``/``next.done``) and ``chunk_load_ratio``
  ours / stock-shaped; ``chunk_load_ms_policy_features`` and ``chunk_load_ratio_policy_features`` ours after
  lerobot's ``remove_feature`` of every ``observation.depth.*``/``privileged.*`` feature; ``row_numbers_*`` the
  numbers per parquet row of each, which the load time follows (see :mod:`recorder.bench`);
* ``bev_*`` — the BEV encoder with the profile's ``pretrain.encoder`` architecture, one thread: lift vs its
  reference, streaming step vs recomputing the window (see :mod:`pretrain.bench`);
* ``startup_s_<module>`` — a fresh interpreter's wall time to import the module a stage's worker process starts from
  (``rl.dagger``: DAgger rollouts on Ray, ``evaluation.harness``: evaluation episodes on Ray; a child of
  ``train-all`` or the CLI pays the same), median of ``startup_runs`` runs alternated with the reference
  ``startup_s_torch`` (``import torch`` alone, the floor every such process pays); ``startup_over_torch_<module>``
  the ratio (:func:`measure_startup`);
* ``teacher_env_steps_per_s`` (vs one in-process env), ``policy_inference_hz`` (streaming vs recomputing the
  window) and ``dagger_ms_per_frame`` (a DAgger rollout frame by phase; its encoder in fp32 vs bf16) — see
  :mod:`rl.bench`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

import sim  # noqa: F401
from pipeline.core import layout
from pipeline.core.artifacts import atomic_write_json
from pipeline.core.config import BaseStageConfig, load_config
from pipeline.core.errors import ConfigError
from pipeline.core.timing import throughput, time_call
from pretrain.bench import measure_bev
from pretrain.stage import PretrainConfig
from recorder.bench import measure_chunk_loading
from recorder.export import write_dataset
from recorder.record import RecordConfig
from recorder.record import body as record_body
from rl.bench import (
    measure_dagger_rollout,
    measure_frame_pool,
    measure_inference,
    measure_student_ppo,
    measure_teacher,
)
from rl.stage import TrainConfig
from sim.crowd import Crowd, social_force_reference
from sim.env import SimConfig
from sim.expert import PrivilegedExpert
from sim.geometry import signed_distance_reference
from sim.humans import Bodies
from sim.intention import head_leads, simulate


@dataclass
class BenchConfig(BaseStageConfig):
    """Config of the benchmark."""

    seconds_per_figure: float = field(default=5.0, metadata={"help": "measuring time per throughput figure, s"})
    record_episodes: int = field(default=4, metadata={"help": "episodes recorded for the recorder figures (0: skip)"})
    scene: str = field(default="office_lobby", metadata={"help": "scene of the env figures"})
    density: float = field(default=0.2, metadata={"help": "crowd density of the env figures, ped/m²"})
    sim: SimConfig = field(default_factory=SimConfig, metadata={"help": "the crowd world (camera resolution)"})
    bev: bool = field(default=True, metadata={"help": "measure the BEV encoder figures (pretrain.bench)"})
    rl: bool = field(default=True, metadata={"help": "measure the teacher's and the rendered students' PPO and policy "
                                                      "inference figures (rl.bench)"})
    ray: bool = field(default=True, metadata={"help": "also record the recorder figures' episodes on Ray (1 and 2 "
                                                       "local nodes)"})
    startup_runs: int = field(default=3, metadata={"help": "fresh interpreters per start-up figure (0: skip them)"})

    def validate(self) -> None:
        super().validate()
        if self.seconds_per_figure <= 0:
            raise ConfigError(f"seconds_per_figure: expected > 0, got {self.seconds_per_figure}")
        if self.startup_runs < 0:
            raise ConfigError(f"startup_runs: expected >= 0, got {self.startup_runs}")


def _env_rate(cfg: BenchConfig, seconds: float, **overrides) -> tuple[float, object]:
    import gymnasium as gym

    env = gym.make("icrowdnav/CrowdNav-v0", config=replace(cfg.sim, scene=cfg.scene, density=cfg.density,
                                                           **overrides))
    env.reset(seed=cfg.seed)
    env.action_space.seed(cfg.seed)

    def step():
        _, _, term, trunc, _ = env.step(env.action_space.sample())
        if term or trunc:
            env.reset()

    return throughput(step, seconds), env


def measure(cfg: BenchConfig) -> dict[str, float]:
    """All figures of this module (see the module docstring)."""

    s = cfg.seconds_per_figure
    out: dict[str, float] = {}
    out["env_steps_per_s_norender"], _ = _env_rate(cfg, s, obs_mode="state", info_level="basic")
    out["env_steps_per_s_norender_full_info"], _ = _env_rate(cfg, s, obs_mode="state", info_level="full")
    out["env_steps_per_s_privileged"], _ = _env_rate(cfg, s, obs_mode="privileged", info_level="basic")
    out["env_steps_per_s_render"], env = _env_rate(cfg, s, obs_mode="visual", info_level="full")
    u = env.unwrapped
    out["render_ms_per_camera"] = 1000 * time_call(u.render_cameras, s / 2) / 2
    out["render_resolution_px"] = float(cfg.sim.camera.width_px * cfg.sim.camera.height_px)
    out["bench_peds"] = float(u.crowd.n)

    def sfm_pair(crowd: Crowd, prefix: str) -> None:
        robot = np.array(u.robot[:2])
        args = (crowd.pos, crowd.vel, crowd.goal, crowd.v0, crowd.radius, crowd.mode, crowd.layout, crowd.cfg,
                robot, 0.3)
        fast = crowd.social_forces(robot, 0.3)
        ref = social_force_reference(*args)
        if not np.allclose(fast, ref, atol=1e-9):
            raise RuntimeError("vectorised social force disagrees with the reference")
        t_fast = time_call(lambda: crowd.social_forces(robot, 0.3), s / 4)
        t_ref = time_call(lambda: social_force_reference(*args), s / 4)
        out[f"{prefix}_us"] = 1e6 * t_fast
        out[f"{prefix}_reference_us"] = 1e6 * t_ref
        out[f"{prefix}_speedup"] = t_ref / t_fast

    sfm_pair(u.crowd, "sfm_vectorized")

    rng = np.random.default_rng(cfg.seed)
    big = Crowd(u.layout, u.crowd.cfg, rng, 40, Bodies(u.cfg.body, rng, 40, np.zeros(40)).radius) \
        if u.layout.ped_count(0.6) >= 40 else None
    if big is not None:
        sfm_pair(big, "sfm_vectorized_n40")
    pts = rng.uniform([u.layout.spec.bounds[0], u.layout.spec.bounds[2]],
                      [u.layout.spec.bounds[1], u.layout.spec.bounds[3]], (1000, 2))
    t_fast = time_call(lambda: u.layout.geometry.signed_distance(pts), s / 4)
    t_ref = time_call(lambda: [signed_distance_reference(u.layout.obstacles, p) for p in pts], s / 4)
    out["static_distance_speedup"] = t_ref / t_fast
    env.close()
    # the expert's decision time
    import gymnasium as gym

    env = gym.make("icrowdnav/CrowdNav-v0", config=replace(cfg.sim, scene=cfg.scene, density=cfg.density,
                                                           obs_mode="state", info_level="basic"))
    env.reset(seed=cfg.seed)
    expert = PrivilegedExpert()
    expert.reset(env.unwrapped)
    out["expert_ms_per_step"] = 1000 * time_call(lambda: expert.command(env.unwrapped), s / 2)
    env.close()
    # the premise: heads turn before the walking direction does (free crowd, 120 s simulated)

    leads = head_leads(simulate(cfg.scene, cfg.density, 120.0, cfg.seed))
    out["intention_decisions"] = len(leads)
    out["intention_head_lead_median_s"] = float(np.median(leads))
    out["intention_head_lead_p10_s"] = float(np.percentile(leads, 10))
    out["intention_head_lead_p90_s"] = float(np.percentile(leads, 90))
    out["intention_head_first_share"] = float(np.mean(leads > 0))
    if cfg.bev:
        enc_cfg = load_config(PretrainConfig, "pretrain", cfg.profile).encoder
        out.update(measure_bev(cfg.sim, cfg.scene, cfg.density, cfg.seed, enc_cfg, s))
    if cfg.rl:
        train_cfg = load_config(TrainConfig, "train", cfg.profile)
        out.update(measure_teacher(cfg.sim, cfg.scene, cfg.density, cfg.seed, train_cfg, 2 * s))
        enc_cfg = load_config(PretrainConfig, "pretrain", cfg.profile).encoder
        out.update(measure_inference(cfg.sim, cfg.scene, cfg.density, cfg.seed, enc_cfg, s))
        out.update(measure_student_ppo(cfg.sim, cfg.scene, cfg.density, cfg.seed, train_cfg, enc_cfg, 2 * s))
        out.update(measure_dagger_rollout(train_cfg, enc_cfg, cfg.seed))
        out.update(measure_frame_pool())
    if cfg.record_episodes > 0:
        out.update(measure_recorder(cfg))
    if cfg.startup_runs > 0:
        out.update(measure_startup(STARTUP_MODULES, cfg.startup_runs))
    return {k: round(float(v), 3) for k, v in out.items()}


# the modules a stage's fresh worker process imports first (module docstring, ``startup_s_*``)
STARTUP_MODULES = ("rl.dagger", "evaluation.harness")


def measure_startup(modules: Sequence[str], runs: int) -> dict[str, float]:
    """Wall seconds of a fresh interpreter (this one's executable, the repository on its path) importing each of
    ``modules``, against importing torch alone, ``runs`` rounds alternating the commands; medians and ratios."""
    root = Path(__file__).resolve().parents[2]
    names = ("torch", *modules)
    walls: dict[str, list[float]] = {n: [] for n in names}
    for _ in range(runs):
        for n in names:
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-c", f"import {n}"], cwd=root, check=True, capture_output=True)
            walls[n].append(time.perf_counter() - t0)
    med = {n: float(np.median(w)) for n, w in walls.items()}
    out = {f"startup_s_{n.replace('.', '_')}": med[n] for n in names}
    out.update({f"startup_over_torch_{n.replace('.', '_')}": med[n] / med["torch"] for n in modules})
    return out


def measure_recorder(cfg: BenchConfig) -> dict[str, float]:
    """Record the same seeded episodes with 1 and 2 workers (fresh temp dirs), then export one recording."""
    import os
    import tempfile

    os.environ.setdefault("HF_HUB_OFFLINE", "1")

    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="icrowdnav-bench-") as tmp:
        for workers in (1, 2):
            rc = RecordConfig(data_dir=Path(tmp), scenes=[cfg.scene], densities=[cfg.density],
                              episodes=cfg.record_episodes, workers=workers, sim=cfg.sim, seed=cfg.seed)
            counts = record_body(rc, Path(tmp) / f"raw{workers}")
            out[f"record_frames_per_s_{workers}worker{'s' if workers > 1 else ''}"] = counts["frames_per_s"]
            if workers == 1:
                out["record_mcap_share"] = counts["mcap_share"]
                out["record_frames"] = counts["frames"]
        if cfg.ray:
            out.update(_record_on_ray(cfg, Path(tmp)))
            for k in ("1node", "2nodes"):
                out[f"record_ray_{k}_vs_local_pool"] = (out[f"record_frames_per_s_ray_{k}"]
                                                        / out["record_frames_per_s_2workers"])
        import lerobot.datasets.lerobot_dataset  # noqa: F401  (import cost is not export cost)

        files = sorted((Path(tmp) / "raw1").glob("*.mcap"))
        counts = write_dataset(files, Path(tmp) / "dataset", "bench/export", progress=False)
        out["export_frames_per_s"] = counts["frames_per_s"]
        # 2 shards even on this small set (the export itself would not shard under 1,000 frames per shard)
        sharded = write_dataset(files, Path(tmp) / "dataset_sharded", "bench/export", progress=False, shards=2,
                                min_shard_frames=0)
        out["export_frames_per_s_2shards"] = sharded["frames_per_s"]
        out["export_merge_seconds_2shards"] = sharded["merge_seconds"]
        out["export_speedup_2shards"] = sharded["frames_per_s"] / counts["frames_per_s"]
        out.update(measure_chunk_loading(Path(tmp) / "dataset", Path(tmp) / "chunk", seed=cfg.seed))
    return out


def _record_on_ray(cfg: BenchConfig, tmp: Path) -> dict[str, float]:
    """The recorder figure's episodes as Ray tasks: on a Ray instance the stage starts on this machine (1 node, 2
    CPUs; starting it is part of the wall time, as for a user) and on a running two-node local cluster (1 CPU each;
    only connecting is timed). Same machine as the local pool: the ratios are the executor's overhead."""
    import os

    from ray.cluster_utils import Cluster

    out: dict[str, float] = {}
    rc = RecordConfig(data_dir=tmp, scenes=[cfg.scene], densities=[cfg.density], episodes=cfg.record_episodes,
                      workers=2, sim=cfg.sim, seed=cfg.seed, executor="ray")
    old = os.environ.pop("RAY_ADDRESS", None)
    try:
        out["record_frames_per_s_ray_1node"] = record_body(rc, tmp / "ray1")["frames_per_s"]
        cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
        try:
            cluster.add_node(num_cpus=1)
            cluster.wait_for_nodes()
            out["record_frames_per_s_ray_2nodes"] = record_body(
                replace(rc, ray_address=cluster.address), tmp / "ray2")["frames_per_s"]
        finally:
            cluster.shutdown()
    finally:
        if old is not None:
            os.environ["RAY_ADDRESS"] = old
    return out


def main(argv: list[str]) -> int:
    """performance figures, each fast path against a simple reference in the same run -> DATA_DIR/bench/bench.json

    ``icrowdnav bench [--profile P] [--data-dir D] [--seconds-per-figure S]``."""
    ap = argparse.ArgumentParser(prog="icrowdnav bench", description=__doc__.split("\n")[0])
    ap.add_argument("--profile", default="default")
    ap.add_argument("--data-dir", default="data")
    ap.add_argument("--seconds-per-figure", default=None)
    a = ap.parse_args(argv)
    overrides = {"data_dir": a.data_dir}
    if a.seconds_per_figure is not None:
        overrides["seconds_per_figure"] = a.seconds_per_figure
    cfg = load_config(BenchConfig, "bench", a.profile, overrides)
    figures = measure(cfg)
    path = layout.bench_file(cfg.data_dir)
    path.parent.mkdir(parents=True, exist_ok=True)
    current = {}
    if path.exists():
        try:
            current = json.loads(path.read_text())
        except json.JSONDecodeError:
            current = {}
    current.update(figures)
    current["machine"] = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, " \
                         f"python {platform.python_version()}"
    current["profile"] = cfg.profile
    atomic_write_json(path, current)
    width = max(len(k) for k in figures)
    for k, v in figures.items():
        print(f"{k:<{width}}  {v}")
    print(f"bench: wrote {path}")
    return 0
