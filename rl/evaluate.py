"""Seeded evaluation episodes of a saved policy (teacher: privileged, no rendering; student: rendered), with the
metrics of :mod:`sim.metrics`. ``train`` uses it for its acceptance figures; the benchmark harness (``eval``) builds
on the same episode runner.
"""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from sim.env import CrowdNavEnv, SimConfig


def policy_episode(args: dict[str, Any]) -> dict[str, Any]:
    """One episode of the policy in ``args["policy"]`` on (scene, density, seed); returns its metrics row."""
    from rl.dagger import _cached, _policy
    from rl.observe import StudentObserver, env_cameras, load_student_encoder, teacher_observation
    from rl.policy import act
    from sim.metrics import episode_metrics

    torch.set_num_threads(1)
    policy = _policy(Path(args["policy"]))
    from rl.policy import read_policy_json

    desc = _cached(f"desc:{args['policy']}", lambda: read_policy_json(Path(args["policy"])))
    student = desc["kind"] == "student"
    sim_cfg: SimConfig = args["sim"]
    env = CrowdNavEnv(config=replace(sim_cfg, scene=args["scene"], density=args["density"],
                                     obs_mode="visual" if student else "privileged", info_level="basic",
                                     action_type="discrete"))
    obs, _ = env.reset(seed=args["seed"])
    observer = None
    if student:
        encoder = _cached(f"enc:{desc['variant']}:{desc.get('encoder')}",
                          lambda: load_student_encoder(desc["variant"], desc.get("encoder")))
        observer = StudentObserver(desc["variant"], env_cameras(env), encoder, env.cfg.detector.max_people)
    while True:
        a = act(policy, observer(obs) if student else teacher_observation(env))
        obs, _, term, trunc, _ = env.step(a)
        if term or trunc:
            break
    trace = env.trace(method=args.get("method", desc["kind"]))
    env.close()
    return {"scene": Path(args["scene"]).stem, "density": args["density"], "seed": args["seed"],
            "method": args.get("method", desc["kind"]), "outcome": trace.outcome, "steps": trace.n_steps,
            **episode_metrics(trace)}


def evaluate(policy_dir: Path, sim_cfg: SimConfig, cells: list[tuple[str, float]], seeds: list[int],
             workers: int = 2, method: str | None = None, progress: bool = True) -> list[dict[str, Any]]:
    """Every (scene, density) of ``cells`` x ``seeds`` (the same seeds for every method) in a process pool."""
    from tqdm import tqdm

    jobs = [{"policy": str(policy_dir), "sim": sim_cfg, "scene": s, "density": d, "seed": k,
             **({"method": method} if method else {})} for s, d in cells for k in seeds]
    desc = f"evaluate {method or Path(policy_dir).name}"
    if workers <= 1:
        return [policy_episode(j) for j in tqdm(jobs, desc=desc, unit="ep", disable=not progress)]
    with ProcessPoolExecutor(workers) as pool:
        return list(tqdm(pool.map(policy_episode, jobs), total=len(jobs), desc=desc, unit="ep",
                         disable=not progress, dynamic_ncols=True))


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
