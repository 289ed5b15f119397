"""Seeded evaluation episodes of a saved policy or learned baseline (teacher: privileged, no rendering; student:
rendered), with the metrics of :mod:`sim.metrics`, through the one episode loop (:func:`sim.episode.run_episode`).
``train`` uses it for its acceptance figures; the benchmark (:mod:`evaluation`) runs the same drivers and loop.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from pipeline.core.executor import Bundle, Executor, map_jobs
from rl.baselines import BASELINES, baseline_module
from rl.driver import PolicyDriver, process_cached
from rl.policy import checkpoint_bundle, read_policy_json
from sim.env import CrowdNavEnv, SimConfig
from sim.episode import Driver, run_episode
from sim.metrics import episode_metrics
from sim.wrappers import with_privileges


def checkpoint_env(ckpt: Path) -> dict[str, str]:
    """The env options the driver of the checkpoint in ``ckpt`` needs: ``obs_mode`` and ``action_type``."""
    desc = read_policy_json(Path(ckpt))
    if desc["kind"] == "baseline":
        info = BASELINES[desc["variant"]]
        return {"obs_mode": info.obs_mode, "action_type": info.action_type}
    return {"obs_mode": "visual" if desc["kind"] == "student" else "privileged", "action_type": "discrete"}


def checkpoint_driver(ckpt: Path) -> Driver:
    """The driver of the policy or baseline saved in ``ckpt`` (built once per process)."""
    def make() -> Driver:
        torch.set_num_threads(1)  # one thread per episode worker (a forked OpenMP pool can hang the child)
        desc = read_policy_json(Path(ckpt))
        if desc["kind"] == "baseline":
            return baseline_module(desc["variant"]).Driver(Path(ckpt))
        return PolicyDriver(Path(ckpt))

    return process_cached(f"driver:{ckpt}", make)


def _episode(job: tuple[Path, str, SimConfig, str, float, int]) -> dict[str, Any]:
    ckpt, method, sim_cfg, scene, density, seed = job
    driver = checkpoint_driver(ckpt)
    over = checkpoint_env(ckpt)
    env = with_privileges(CrowdNavEnv(config=replace(sim_cfg, scene=scene, density=density, info_level="basic",
                                                     **over)), over["obs_mode"])
    trace = run_episode(env, driver, seed, method)
    env.close()
    return {"method": method, "scene": Path(scene).stem, "density": density, "seed": seed, "outcome": trace.outcome,
            "steps": trace.n_steps, **episode_metrics(trace)}


def evaluate(policy_dir: Path, sim_cfg: SimConfig, cells: list[tuple[str, float]], seeds: list[int],
             workers: int = 2, method: str | None = None, progress: bool = True,
             executor: Executor | None = None) -> list[dict[str, Any]]:
    """Every (scene, density) of ``cells`` x ``seeds`` (the same seeds for every method) in a process pool or on
    Ray (``executor``; with ``files: transfer`` the checkpoint travels as one bundle,
    :func:`rl.policy.checkpoint_bundle`); one metrics row per episode, named ``method`` (default: the checkpoint
    folder's name)."""
    name = method or Path(policy_dir).name
    jobs = [(Path(policy_dir), name, sim_cfg, s, d, k) for s, d in cells for k in seeds]
    if executor is not None and executor.transfers:
        return map_jobs(_episode_on_bundle, jobs, workers, f"evaluate {name}", progress, executor=executor,
                        shared=checkpoint_bundle([Path(policy_dir)]))
    return map_jobs(_episode, jobs, workers, f"evaluate {name}", progress, executor=executor)


def _episode_on_bundle(job: tuple[Path, str, SimConfig, str, float, int], shared: Bundle) -> dict[str, Any]:
    """:func:`_episode` on a node without the data directory: the checkpoint from the unpacked bundle ``shared``."""
    return _episode((shared.local(shared.unpack(), job[0]), *job[1:]))


def success_table(rows: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Per ``scene@density``: N, SR, collision and timeout rates, mean navigation time of successes."""
    out: dict[str, dict[str, float]] = {}
    for key in sorted({(r["scene"], r["density"]) for r in rows}):
        rs = [r for r in rows if (r["scene"], r["density"]) == key]
        ok = [r for r in rs if r["success"] == 1]
        out[f"{key[0]}@{key[1]:g}"] = {
            "n": len(rs), "sr": sum(r["success"] for r in rs) / len(rs),
            "collision": sum(r["collision"] for r in rs) / len(rs), "timeout": sum(r["timeout"] for r in rs) / len(rs),
            "nav_time_s": (sum(r["nav_time_s"] for r in ok) / len(ok)) if ok else float("nan"),
            "tpz_s": sum(r["tpz_s"] for r in rs) / len(rs)}
    return out
