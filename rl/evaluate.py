"""Seeded evaluation episodes of a saved policy (teacher: privileged, no rendering; student: rendered), with the
metrics of :mod:`sim.metrics`, through the benchmark's episode runner (:mod:`evaluation.harness`). ``train`` uses it
for its acceptance figures.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sim.env import SimConfig


def evaluate(policy_dir: Path, sim_cfg: SimConfig, cells: list[tuple[str, float]], seeds: list[int],
             workers: int = 2, method: str | None = None, progress: bool = True) -> list[dict[str, Any]]:
    """Every (scene, density) of ``cells`` x ``seeds`` (the same seeds for every method), run by the benchmark
    harness (:mod:`evaluation.harness`) in a process pool; one metrics row per episode."""
    from evaluation.harness import Job, run_jobs
    from evaluation.methods import spec_from_checkpoint

    spec = spec_from_checkpoint(Path(policy_dir), method)
    name = spec.name
    jobs = [Job(spec, sim_cfg, s, d, k, Path(policy_dir), save_trace=False) for s, d in cells for k in seeds]
    return run_jobs(jobs, workers, f"evaluate {name}", progress)


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
