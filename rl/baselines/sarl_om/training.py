"""Training SARL*-OM (package docstring): imitation of the expert's episodes, then deep V-learning on ε-greedy
lookahead episodes collected in a process pool; resumable from ``out/rl/``."""

from __future__ import annotations

import functools
import logging
import math
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from pipeline.core.artifacts import atomic_write_with
from pipeline.core.errors import CorruptArtifactError
from pipeline.core.executor import process_pool
from rl.baselines.common import collect_expert_episodes, save_baseline, save_curve_point, training_pairs
from rl.baselines.sarl_om.configuration import KEYS, NAME, RUNTIME_FIELDS, Config
from rl.baselines.sarl_om.lookahead import Lookahead
from rl.baselines.sarl_om.model import SarlOMValue, build, to_tensors
from rl.baselines.sarl_om.observation import current_state, perceive
from rl.baselines.sarl_om.rewards import reward
from sim.env import CrowdNavEnv, SimConfig
from sim.episode import episode_steps
from sim.wrappers import PrivilegedWorld


def inputs(cfg) -> list[Path]:
    """Nothing but the simulator."""
    return []


def mirror(js: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The joint states reflected about the goal direction (y -> -y): a world that is as likely as the original
    (augmentation, as the teacher's cloning mirrors its data)."""
    flip_self = np.array([1, 1, -1, 1, 1, -1], np.float32)
    flip_human = np.array([1, -1, 1, -1, 1, 1, 1], np.float32)
    return {"self": js["self"] * flip_self, "humans": js["humans"] * flip_human, "mask": js["mask"],
            "om": js["om"][..., ::-1].copy()}


class SarlObserver:
    """The joint state of every step plus ``arrival``: R's shaping terms of arriving in this state (progress since
    the previous step, discomfort, danger zones); for :func:`collect_expert_episodes` (picklable with a config)."""

    def __init__(self, oc: Config) -> None:
        self.oc = oc
        self.d_prev = math.nan

    def reset(self, env: CrowdNavEnv, obs: dict | None = None) -> None:
        self.d_prev = math.nan

    def __call__(self, env: CrowdNavEnv, obs: dict | None = None) -> dict[str, np.ndarray]:
        sc = perceive(env, None, self.oc)
        here = np.zeros((1, 2))
        d = float(np.hypot(*sc.goal))
        r, _ = reward(sc, here, sc.humans[:, :2], d if math.isnan(self.d_prev) else self.d_prev, env.cfg.dt_s,
                      self.oc)
        self.d_prev = d
        return {**{k: v[0] for k, v in current_state(sc, self.oc).items()}, "arrival": r.astype(np.float32)[0]}


_WORKER: dict[str, Any] = {}


def _init_worker(sim_cfg: SimConfig, oc: Config, net: dict[str, Any]) -> None:
    torch.set_num_threads(1)
    _WORKER.update(sim_cfg=sim_cfg, oc=oc, model=build(net).eval(), envs={})


def _env(pair: tuple[str, float]) -> CrowdNavEnv:
    envs = _WORKER["envs"]
    if pair not in envs:
        envs[pair] = CrowdNavEnv(config=replace(_WORKER["sim_cfg"], scene=pair[0], density=pair[1], obs_mode="state",
                                                action_type="discrete", info_level="basic"))
    return envs[pair]


def _run_episodes(state: dict[str, np.ndarray], jobs: list[tuple[str, float, int, float]]) -> list[dict]:
    """Runs ε-greedy lookahead episodes ``(scene, density, seed, ε)`` with weights ``state`` in this process."""
    model: SarlOMValue = _WORKER["model"]
    model.load_state_dict({k: torch.as_tensor(v) for k, v in state.items()})
    oc: Config = _WORKER["oc"]
    return [run_episode(_env((scene, density)), model, oc, seed, eps) for scene, density, seed, eps in jobs]


def _pooled_episodes(pool: ProcessPoolExecutor, workers: int, state: dict[str, np.ndarray],
                     jobs: list[tuple[str, float, int, float]]) -> list[dict]:
    """``_run_episodes(state, jobs)`` on ``workers`` processes, each given every ``workers``-th job, the episodes
    back in job order — so the replay memory fills in the same order whatever the worker count."""
    chunks = [jobs[w::workers] for w in range(min(workers, len(jobs)))]
    out: list[dict] = [{}] * len(jobs)
    for w, part in enumerate(pool.map(_run_episodes, [state] * len(chunks), chunks)):
        out[w::workers] = part
    return out


class _EpsilonGreedy:
    """SARL's one-step lookahead, ε-greedy (training rollouts), on the true world (``info["world"]``)."""

    def __init__(self, model: SarlOMValue, oc: Config, epsilon: float, rng: np.random.Generator) -> None:
        self.model, self.oc, self.epsilon, self.rng = model, oc, epsilon, rng

    def reset(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> None:
        self.look = Lookahead(self.model, self.oc, info["world"])

    def act(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> int:
        return self.look.act(perceive(info["world"], None, self.oc), self.epsilon, self.rng)


def run_episode(env: CrowdNavEnv, model: SarlOMValue, oc: Config, seed: int, epsilon: float) -> dict:
    """One episode: its transitions (``s_*``, ``n_*`` joint states, ``reward``, ``done``), outcome and actions."""
    observer = SarlObserver(oc)
    states, actions, rewards = [], [], []
    outcome, terminated = None, False
    driver = _EpsilonGreedy(model, oc, epsilon, np.random.default_rng(seed))
    for tr in episode_steps(PrivilegedWorld(env), driver, seed):
        world = tr.info["world"]
        if tr.step == 0:
            observer.reset(world)
        states.append(observer(world))
        if tr.step == 0:
            continue
        actions.append(tr.action)
        outcome, terminated = tr.info["outcome"], tr.terminated
        if outcome == "success":
            rewards.append(oc.success_reward)
        elif tr.terminated:
            rewards.append(oc.collision_penalty)
        else:
            rewards.append(float(states[-1]["arrival"]))
    cur = {k: np.stack([s[k] for s in states[:-1]]) for k in KEYS}
    nxt = {k: np.stack([s[k] for s in states[1:]]) for k in KEYS}
    done = np.zeros(len(rewards), bool)
    done[-1] = terminated
    return {**{f"s_{k}": v for k, v in cur.items()}, **{f"n_{k}": v for k, v in nxt.items()},
            "reward": np.asarray(rewards, np.float32), "done": done, "outcome": outcome or "timeout",
            "actions": np.asarray(actions)}


class Replay:
    """Ring buffer of transitions (s, R, s', terminal)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self.data: dict[str, np.ndarray] = {}
        self.size = 0
        self.head = 0

    def push(self, batch: dict[str, np.ndarray]) -> None:
        n = len(batch["reward"])
        if not self.data:
            self.data = {k: np.zeros((self.capacity, *v.shape[1:]), v.dtype) for k, v in batch.items()}
        idx = (self.head + np.arange(n)) % self.capacity
        for k, v in batch.items():
            self.data[k][idx] = v[-self.capacity:] if n > self.capacity else v
        self.head = int((self.head + n) % self.capacity)
        self.size = min(self.capacity, self.size + n)

    def sample(self, rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
        idx = rng.integers(self.size, size=n)
        return {k: v[idx] for k, v in self.data.items()}


TRANSITION_KEYS = tuple(f"{p}_{k}" for p in ("s", "n") for k in KEYS) + ("reward", "done")


def _imitation_data(cfg, oc: Config, n_episodes: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict]:
    """Expert episodes -> (value-regression data {KEYS, target}, transitions for the replay, stats)."""
    data = collect_expert_episodes(cfg.sim, training_pairs(cfg), n_episodes, cfg.seed,
                                   functools.partial(SarlObserver, oc), cfg.workers, obs_mode="state",
                                   action_type="discrete", progress=cfg.progress, desc="sarl_om: expert episodes")
    ep = data["episode"]
    last = data["done"]
    collided = last & (data["reward"] <= 0.5 * cfg.sim.reward.collision)  # the paper's reward's collision term
    succeeded = last & data["success"]
    # R of step t is the arrival reward of step t + 1; the last step's is the outcome's (0 after a timeout)
    r = np.where(last, 0.0, np.roll(data["arrival"], -1)).astype(np.float32)
    r = np.where(succeeded, oc.success_reward, np.where(collided, oc.collision_penalty, r)).astype(np.float32)
    step_gamma = oc.gamma ** (cfg.sim.dt_s * cfg.sim.robot.v_max_mps)
    target = np.zeros_like(r)
    acc = 0.0
    for t in range(len(r) - 1, -1, -1):  # discounted return per episode
        acc = r[t] + (0.0 if last[t] else step_gamma * acc)
        target[t] = acc
    keep_ep = np.unique(ep[succeeded | collided])  # CrowdNav's IL keeps successes and collisions
    keep = np.isin(ep, keep_ep)
    il = {k: data[k][keep] for k in KEYS}
    il["target"] = target[keep]
    nxt = {f"n_{k}": np.where(last[keep].reshape(-1, *[1] * (data[k].ndim - 1)), data[k][keep],
                              np.roll(data[k], -1, 0)[keep]) for k in KEYS}
    trans = {**{f"s_{k}": data[k][keep] for k in KEYS}, **nxt, "reward": r[keep], "done": last[keep]}
    stats = {"expert_episodes": n_episodes, "expert_frames": int(len(r)), "il_episodes_kept": int(len(keep_ep)),
             "expert_success_rate": float(succeeded.sum() / max(1, last.sum()))}
    return il, trans, stats


def regress(model: SarlOMValue, data: dict[str, np.ndarray], epochs: int, batch: int, lr: float, seed: int,
            log=None) -> float:
    """MSE regression of V on ``data['target']`` and on the mirrored states (imitation); returns the last epoch's
    mean loss."""
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    rng = np.random.default_rng(seed)
    both = {k: np.concatenate([data[k], mirror(data)[k]]) for k in KEYS}
    x = to_tensors(both)
    y = torch.as_tensor(np.concatenate([data["target"]] * 2), dtype=torch.float32)
    n = len(y)
    mean = math.nan
    if n == 0:  # no expert episode reached the goal (timeouts are dropped, as CrowdNav does)
        logging.getLogger("icrowdnav").warning("SARL*-OM: no imitation targets (no expert episode succeeded); "
                                               "imitation skipped")
        return mean
    model.train()
    for epoch in range(epochs):
        perm = torch.as_tensor(rng.permutation(n))
        losses = []
        for i in range(0, n, batch):
            idx = perm[i:i + batch]
            loss = nn.functional.mse_loss(model(*(t[idx] for t in x)), y[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(loss.item())
        mean = float(np.mean(losses))
        if log is not None:
            log.add("imitation", epoch, value_mse=mean)
    model.eval()
    return mean


def td_update(model: SarlOMValue, target: SarlOMValue, opt: torch.optim.Optimizer, batch: dict[str, np.ndarray],
              step_gamma: float) -> float:
    """One deep V-learning step: MSE of V(s) to R + γ̄ · V_target(s') (no bootstrap when terminal); the second half
    of the batch is mirrored (:func:`mirror`)."""
    half = len(batch["reward"]) // 2

    def states(prefix: str) -> list[torch.Tensor]:
        js = {k: batch[f"{prefix}_{k}"] for k in KEYS}
        flipped = mirror({k: v[half:] for k, v in js.items()})
        return to_tensors({k: np.concatenate([v[:half], flipped[k]]) for k, v in js.items()})

    s, n = states("s"), states("n")
    with torch.no_grad():
        v_next = target(*n)
    y = torch.as_tensor(batch["reward"]) + step_gamma * v_next * torch.as_tensor(~batch["done"], dtype=torch.float32)
    loss = nn.functional.mse_loss(model(*s), y)
    opt.zero_grad()
    loss.backward()
    opt.step()
    return float(loss.item())


def _save_state(path: Path, model: SarlOMValue, target: SarlOMValue, opt: torch.optim.Optimizer, replay: Replay,
                counters: dict[str, Any], rng: np.random.Generator) -> None:
    """``out/rl/state.pt``: weights, optimiser, counters, the minibatch generator's state and the replay memory in
    one file written atomically, so a resumed run never pairs counters with a replay of another iteration (a kill
    between two files could) and draws the minibatches the uninterrupted run would have drawn."""
    state = {"model": model.state_dict(), "target": target.state_dict(), "opt": opt.state_dict(), "counters": counters,
             "rng": rng.bit_generator.state,
             "replay": {"size": replay.size, "head": replay.head,
                        "data": {k: torch.from_numpy(v) for k, v in replay.data.items()}}}
    atomic_write_with(path / "state.pt", lambda f: torch.save(state, f))
    (path / "replay.npz").unlink(missing_ok=True)  # a state of before the single file: superseded


def _load_state(path: Path, model: SarlOMValue, target: SarlOMValue, opt: torch.optim.Optimizer,
                replay: Replay, rng: np.random.Generator) -> dict[str, Any]:
    try:
        st = torch.load(path / "state.pt", weights_only=False)
        model.load_state_dict(st["model"])
        target.load_state_dict(st["target"])
        opt.load_state_dict(st["opt"])
        if "rng" in st:  # absent in a state written before it was saved: the generator then starts afresh
            rng.bit_generator.state = st["rng"]
        if "replay" in st:
            replay.data = {k: st["replay"]["data"][k].numpy() for k in TRANSITION_KEYS}
            replay.size, replay.head = int(st["replay"]["size"]), int(st["replay"]["head"])
        else:  # written before the replay moved into state.pt
            with np.load(path / "replay.npz") as z:
                replay.data = {k: z[k] for k in TRANSITION_KEYS}
                replay.size, replay.head = int(z["size"]), int(z["head"])
    except (OSError, KeyError, RuntimeError, ValueError) as e:
        raise CorruptArtifactError(f"{path}: cannot resume SARL*-OM ({type(e).__name__}: {e}); rerun with "
                                   "--overwrite") from None
    return st["counters"]


def train(cfg, out: Path, log) -> dict[str, Any]:
    """Imitation of the expert, then deep V-learning (package docstring); writes the checkpoint into ``out``."""
    oc: Config = cfg.sarl_om
    oc.validate()
    t0 = time.time()
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    out = Path(out)
    rl_dir = out / "rl"
    model = SarlOMValue(oc.om_sectors)
    target = SarlOMValue(oc.om_sectors)
    opt = torch.optim.Adam(model.parameters(), lr=oc.rl_lr)
    replay = Replay(oc.capacity)
    step_gamma = oc.gamma ** (cfg.sim.dt_s * cfg.sim.robot.v_max_mps)
    pairs = training_pairs(cfg)
    rng = np.random.default_rng(cfg.seed + 7)  # the replay's minibatches; its state travels in state.pt
    if getattr(cfg, "resume", False) and (rl_dir / "state.pt").is_file():
        c = _load_state(rl_dir, model, target, opt, replay, rng)
    else:
        n_il = oc.il_episodes or cfg.teacher.bc_episodes
        il, trans, stats = _imitation_data(cfg, oc, n_il)
        il_loss = regress(model, il, oc.il_epochs, oc.batch_size, oc.il_lr, cfg.seed, log)
        target.load_state_dict(model.state_dict())
        replay.push(trans)
        c = {"iteration": 0, "episodes": 0, "env_steps": 0, "updates": 0, "since_target": 0,
             "wall_s": time.time() - t0, "il_loss": il_loss, **stats}
        _save_state(rl_dir, model, target, opt, replay, c, rng)
    def curve_point(episodes: int) -> None:
        save_curve_point(out, NAME, model, model.spec, observation_description(oc),
                         {"expert_episodes": c["expert_episodes"], "expert_frames": c["expert_frames"],
                          "il_epochs": oc.il_epochs, "rl_episodes": c["episodes"], "rl_env_steps": c["env_steps"]},
                         episodes, "rl_episodes", config={f.name: getattr(oc, f.name) for f in fields(oc)})

    if oc.curve_episodes and c["episodes"] == 0:
        curve_point(0)  # after imitation: the curve's first point
    t_start = time.time() - c["wall_s"]  # wall time accumulates over resumed runs
    pool = None
    if cfg.workers > 1 and c["iteration"] < oc.rl_iterations:
        pool = process_pool(cfg.workers, "fork", initializer=_init_worker, initargs=(cfg.sim, oc, model.spec))
    else:
        _init_worker(cfg.sim, oc, model.spec)
        torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    try:
        while c["iteration"] < oc.rl_iterations:
            k0 = c["episodes"]
            jobs = []
            for j in range(oc.episodes_per_iter):
                k = k0 + j
                eps = oc.epsilon_start + (oc.epsilon_end - oc.epsilon_start) * min(1.0, k / oc.epsilon_decay_episodes)
                jobs.append((*pairs[k % len(pairs)], cfg.seed + 100_000 + k, eps))
            state = {k: v.detach().numpy().copy() for k, v in model.state_dict().items()}
            t_roll = time.time()
            if pool is None:  # one thread, as a pool worker has: the episodes do not depend on `workers`
                torch.set_num_threads(1)
                eps_out = _run_episodes(state, jobs)
                torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
            else:
                eps_out = _pooled_episodes(pool, cfg.workers, state, jobs)
            for e in eps_out:
                replay.push({k: e[k] for k in TRANSITION_KEYS})
            steps = int(sum(len(e["reward"]) for e in eps_out))
            steps_per_s = steps / max(time.time() - t_roll, 1e-9)
            model.train()
            losses = [td_update(model, target, opt, replay.sample(rng, oc.batch_size), step_gamma)
                      for _ in range(oc.train_batches)]
            model.eval()
            c["episodes"] += len(eps_out)
            c["env_steps"] += steps
            c["updates"] += oc.train_batches
            c["since_target"] += len(eps_out)
            if c["since_target"] >= oc.target_update_episodes:
                target.load_state_dict(model.state_dict())
                c["since_target"] = 0
            c["iteration"] += 1
            for b in oc.curve_episodes:  # the first iteration that reaches b saves the point b
                if c["episodes"] - len(eps_out) < b <= c["episodes"]:
                    curve_point(b)
            outcomes = [e["outcome"] for e in eps_out]
            log.add("rl", c["episodes"], td_loss=float(np.mean(losses)), epsilon=jobs[-1][3],
                    success_rate=outcomes.count("success") / len(outcomes),
                    collision_rate=sum(o.startswith("collision") for o in outcomes) / len(outcomes),
                    episode_steps=steps / len(outcomes), env_steps_per_s=steps_per_s)
            if c["iteration"] % oc.checkpoint_every == 0 or c["iteration"] == oc.rl_iterations:
                c["wall_s"] = time.time() - t_start
                _save_state(rl_dir, model, target, opt, replay, c, rng)
    finally:
        if pool is not None:
            pool.shutdown()
    c["wall_s"] = time.time() - t_start
    budget = {"expert_episodes": c["expert_episodes"], "expert_frames": c["expert_frames"],
              "il_epochs": oc.il_epochs, "rl_episodes": c["episodes"], "rl_env_steps": c["env_steps"],
              "rl_updates": c["updates"], "rendered_frames": 0, "wall_s": round(c["wall_s"], 1)}
    save_baseline(out, NAME, model, model.spec, observation_description(oc), budget,
                  config={f.name: getattr(oc, f.name) for f in fields(oc)})
    return {"budget": budget, "il_loss": c["il_loss"], "il_episodes_kept": c["il_episodes_kept"],
            "expert_success_rate": c["expert_success_rate"]}


def observation_description(oc: Config) -> dict[str, Any]:
    """``policy.json``'s ``observation_space``: the inputs and the run-time options of the lookahead."""
    return {"humans": f"perfect tracks within {oc.sensor_range_m} m, nearest {oc.max_humans}, goal frame "
                      "[px, py, vx, vy, radius, distance, radius sum] + mask",
            "self": "[d_g, v_pref, theta, radius, vx, vy] (goal frame)",
            "om": f"angular map of the static scan: {oc.om_sectors} sectors, closeness 1 - r/{oc.om_range_m} m",
            **{k: v for k, v in asdict(oc).items() if k in RUNTIME_FIELDS}}
