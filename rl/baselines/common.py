"""What every learned baseline shares: the package contract, checkpoints, expert data, sensors and the sub-goal.

A baseline is a package ``rl.baselines.<name>`` (listed in :data:`rl.baselines.BASELINES`; one module per concern:
``configuration``, ``model``, ``training``, ``driver``, ...) whose ``__init__`` exposes::

    Config                            dataclass of its training options (``TrainConfig.<name>``; profiles set it)
    inputs(cfg) -> list[Path]         files it reads besides the simulator, checked before any output exists
                                      (missing -> InputMissingError naming the file and the command that makes it)
    train(cfg, out, log) -> dict      trains into ``out`` (resumable where it is long), writes the final weights with
                                      :func:`save_baseline` and returns a summary with a ``"budget"`` dict (expert
                                      episodes / frames, env steps, rendered frames, epochs: what it consumed)
    Driver(ckpt)                      ``reset(env, obs)``, ``act(env, obs, waypoint) -> env action``,
                                      ``bev_panel() -> H x W array | None`` (what its map input held, for videos)

``cfg`` is the ``train`` stage's :class:`rl.stage.TrainConfig` (``cfg.sim``, ``cfg.seed``, ``cfg.workers``,
``cfg.teacher.curriculum`` for the training scenes, ``cfg.<name>`` for its own options); ``log.add(phase, step,
**values)`` appends to ``train_log.csv`` and TensorBoard (``curves.png`` is drawn from it).

A driver builds its observation from the ``env`` object (the true state it is allowed to see, e.g. tracks within
sensor range), not from the ``obs`` dict: the harness renders cameras for videos and MCAP logs, which changes
``obs`` but must not change what a privileged baseline sees. A waypoint (long-horizon runs) replaces the goal; the
sub-goal on the static map's shortest path is :class:`sim.planners.global_path.GlobalPath`.

Checkpoint (in ``DATA_DIR/checkpoints/policy/<name>/``): ``policy.safetensors`` (every parameter and buffer) and
``policy.json`` (``kind: baseline``, ``variant: <name>``, ``net``: what to build, ``observation_space``: a
description of the inputs, ``produced_by``: the budget). :func:`load_baseline` rebuilds and loads it; a missing
file or one that does not fit gives one error naming the file.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from pipeline.core.artifacts import atomic_write_text
from pipeline.core.errors import CorruptArtifactError
from pipeline.core.executor import process_pool
from pretrain.checkpoint import load_safetensors, save_safetensors
from rl.policy import read_policy_json
from rl.teacher import discounted, stage_pairs_all
from sim.env import CrowdNavEnv, SimConfig
from sim.episode import episode_steps
from sim.expert import ExpertDriver
from sim.geometry import world_to_robot
from sim.wrappers import PrivilegedWorld

POLICY_JSON = "policy.json"
POLICY_WEIGHTS = "policy.safetensors"


# ------------------------------------------------------------------------------------------------- checkpoints
def save_baseline(out: Path, name: str, model: torch.nn.Module, net: dict[str, Any], inputs: dict[str, Any],
                  produced_by: dict[str, Any], **extra: Any) -> None:
    """Writes ``policy.safetensors`` and ``policy.json`` (each atomically) for baseline ``name``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    save_safetensors(model, out / POLICY_WEIGHTS, {"kind": "baseline", "variant": name})
    desc = {"kind": "baseline", "variant": name, "net": net, "observation_space": inputs,
            "produced_by": produced_by, **extra}
    atomic_write_text(out / POLICY_JSON, json.dumps(desc, indent=2, sort_keys=True, default=_json) + "\n")


CURVE_DIR = "curve"  # <checkpoint>/curve/<point>/: the learning curve's intermediate checkpoints


def save_curve_point(out: Path, name: str, model: torch.nn.Module, net: dict[str, Any], inputs: dict[str, Any],
                     produced_by: dict[str, Any], budget: int, unit: str, **extra: Any) -> Path:
    """Saves an intermediate checkpoint of a baseline's training at ``budget`` ``unit`` (e.g. 65,536
    ``ppo_env_steps``) into ``out/curve/<unit>_<budget>`` (once: an existing point is kept, so a resumed run does
    not overwrite it); ``train`` evaluates every point (:func:`curve_points`). Returns its directory."""
    d = Path(out) / CURVE_DIR / f"{unit}_{budget:09d}"
    if not (d / POLICY_JSON).is_file():
        save_baseline(d, name, model, net, inputs, {**produced_by, "curve_budget": int(budget), "curve_unit": unit},
                      **extra)
    return d


def curve_points(out: Path) -> list[tuple[int, str, Path]]:
    """The learning-curve checkpoints under ``out/curve``: ``(budget, unit, directory)`` sorted by budget."""
    points = []
    for f in sorted((Path(out) / CURVE_DIR).glob(f"*/{POLICY_JSON}")):
        produced = json.loads(f.read_text()).get("produced_by", {})
        if "curve_budget" in produced:
            points.append((int(produced["curve_budget"]), str(produced["curve_unit"]), f.parent))
    return sorted(points)


def _json(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o).__name__)


def load_baseline(ckpt: Path, name: str, build: Callable[[dict[str, Any]], torch.nn.Module]
                  ) -> tuple[torch.nn.Module, dict[str, Any]]:
    """The model of baseline ``name`` saved in ``ckpt`` (eval mode) and its description; ``build(net)`` makes the
    network from ``policy.json``'s ``net``."""
    ckpt = Path(ckpt)
    desc = read_policy_json(ckpt)
    if desc.get("kind") != "baseline" or desc.get("variant") != name:
        raise CorruptArtifactError(f"{ckpt / POLICY_JSON}: expected a {name!r} baseline checkpoint, found kind "
                                   f"{desc.get('kind')!r} variant {desc.get('variant')!r}")
    try:
        model = build(desc["net"])
    except (KeyError, TypeError, ValueError) as e:
        raise CorruptArtifactError(f"{ckpt / POLICY_JSON}: cannot build {name} ({type(e).__name__}: {e})") from None
    load_safetensors(model, ckpt / POLICY_WEIGHTS)
    model.eval()
    return model, desc


# ------------------------------------------------------------------------------------------------- training data
def training_pairs(cfg) -> list[tuple[str, float]]:
    """The (scene, density) pairs of the training scenes (the teacher's curriculum, every stage)."""
    return stage_pairs_all(cfg.teacher.curriculum)


def _expert_episode(args: tuple) -> dict[str, np.ndarray]:
    """One episode driven by the privileged expert; the baseline's observer (which reads the true world,
    ``info["world"]``) observes every state the expert acted in."""
    sim_cfg, scene, density, seed, gamma, make_observer, obs_mode, action_type = args
    env = PrivilegedWorld(CrowdNavEnv(config=replace(sim_cfg, scene=scene, density=density, obs_mode=obs_mode,
                                                     action_type=action_type, info_level="basic")))
    observer = make_observer()
    driver = ExpertDriver()
    rows: dict[str, list] = {}
    cmds, actions, rewards = [], [], []
    outcome = "timeout"
    for tr in episode_steps(env, driver, seed):
        if tr.step == 0:
            observer.reset(tr.info["world"], tr.obs)
        else:
            cmds.append(driver.last_command)
            actions.append(tr.action)
            rewards.append(tr.reward)
        if tr.done:
            outcome = tr.info["outcome"] or "timeout"
            break
        for k, v in observer(tr.info["world"], tr.obs).items():
            rows.setdefault(k, []).append(np.asarray(v))
    env.close()
    out = {k: np.stack(v) for k, v in rows.items()}
    out["command"] = np.asarray(cmds, np.float32)
    out["action"] = np.asarray(actions)
    out["reward"] = np.asarray(rewards, np.float32)
    out["return"] = discounted(rewards, gamma)
    done = np.zeros(len(rewards), bool)
    done[-1] = True
    out["done"] = done
    out["success"] = np.full(len(rewards), outcome == "success")
    return out


def collect_expert_episodes(sim_cfg: SimConfig, pairs: list[tuple[str, float]], episodes: int, seed: int,
                            make_observer: Callable[[], Any], workers: int, gamma: float = 0.99,
                            obs_mode: str = "privileged", action_type: str = "continuous", progress: bool = True,
                            desc: str = "expert episodes") -> dict[str, np.ndarray]:
    """``episodes`` episodes of the privileged expert spread evenly over ``pairs`` (seeds ``seed + k``), each
    step observed by ``make_observer()`` (a picklable factory; the observer has ``reset(env, obs)`` and
    ``__call__(env, obs) -> dict of arrays``) — concatenated over episodes, plus ``command`` (the expert's
    (v, ω)), ``action`` (that command in the env's action space), ``reward`` (the paper's), ``return``
    (discounted with ``gamma``), ``done`` (last step of an episode), ``success`` (the episode's outcome, per
    step) and ``episode`` (its index)."""
    jobs = [(sim_cfg, *pairs[k % len(pairs)], seed + k, gamma, make_observer, obs_mode, action_type)
            for k in range(episodes)]
    parts = []
    if workers <= 1:
        it = map(_expert_episode, jobs)
        parts = list(tqdm(it, total=len(jobs), desc=desc, unit="ep", disable=not progress, dynamic_ncols=True))
    else:
        with process_pool(workers, "fork") as pool:
            parts = list(tqdm(pool.map(_expert_episode, jobs), total=len(jobs), desc=desc, unit="ep",
                              disable=not progress, dynamic_ncols=True))
    data = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    data["episode"] = np.concatenate([np.full(len(p["reward"]), i) for i, p in enumerate(parts)])
    return data


# ------------------------------------------------------------------------------------------------------ sensors
def lidar_scan(env: CrowdNavEnv, n_rays: int, fov_rad: float, max_range_m: float) -> np.ndarray:
    """A 2D lidar at the robot centre that sees obstacles *and* pedestrians (their body discs): ``n_rays`` ranges
    (m, capped at ``max_range_m``) evenly over ``fov_rad`` centred on the heading, right to left."""
    x, y, yaw = env.robot
    if fov_rad >= 2 * math.pi - 1e-9:
        ang = yaw - math.pi + (np.arange(n_rays) + 0.5) * (2 * math.pi / n_rays)
    else:
        ang = yaw + np.linspace(-fov_rad / 2, fov_rad / 2, n_rays)
    r = np.asarray(env.layout.geometry.raycast(np.array([x, y]), ang, max_range_m), np.float64)
    crowd = env.crowd
    if crowd.n:
        d = np.stack([np.cos(ang), np.sin(ang)], -1)  # R x 2
        rel = crowd.pos - np.array([x, y])  # N x 2
        b = d @ rel.T  # R x N: projection of each centre on each ray
        c = (rel ** 2).sum(-1)[None, :] - crowd.radius[None, :] ** 2
        disc = b ** 2 - c
        hit = np.sqrt(np.clip(disc, 0.0, None))
        t = np.where(c < 0, 0.0, b - hit)  # inside a disc: range 0
        t = np.where((disc >= 0) & ((b > 0) | (c < 0)) & (t >= 0), t, np.inf)
        r = np.minimum(r, t.min(1))
    return np.minimum(r, max_range_m).astype(np.float32)


def tracked_pedestrians(env: CrowdNavEnv, range_m: float) -> np.ndarray:
    """Pedestrian tracks a robot's tracker would report: ``M x 5`` [x, y, vx, vy, radius] in the robot frame of
    every pedestrian whose centre is within ``range_m`` (true positions and velocities: a perfect tracker), nearest
    first."""
    crowd = env.crowd
    if not crowd.n:
        return np.zeros((0, 5), np.float32)
    dist = np.hypot(*(crowd.pos - np.asarray(env.robot[:2])).T)
    idx = np.argsort(dist, kind="stable")
    idx = idx[dist[idx] <= range_m]
    out = np.concatenate([world_to_robot(crowd.pos[idx], env.robot),
                          world_to_robot(crowd.vel[idx], env.robot, vectors=True), crowd.radius[idx, None]], -1)
    return out.astype(np.float32)


def to_robot_frame(env: CrowdNavEnv, xy: np.ndarray) -> np.ndarray:
    """A world-frame point in the robot frame (x forward, y left)."""
    return world_to_robot(np.asarray(xy, dtype=np.float64)[:2], env.robot).astype(np.float32)
