"""The privileged teacher: behaviour cloning of the privileged expert, then PPO with the paper's reward.

The teacher sees what the student cannot (robot state, the nearest pedestrians' true relative positions and
velocities, a range scan of the static map) and needs no rendering, so thousands of env steps per second run on two
cores. Training, on the *training* scenes only:

1. **Warm start** (``bc_episodes``): the privileged expert (:mod:`sim.expert`) drives episodes over every
   (scene, density) of the curriculum and scores every action of the 5 x 21 grid; the policy is trained by
   cross-entropy to the softmin of those costs and the value head by regression on the discounted returns of the
   paper's reward. The default teacher network (``encoder="lookahead"``, :class:`rl.networks.LookaheadTeacherExtractor`)
   scores each action from kinematic rollout features; its linear cost is first fitted by convex regression
   (:func:`fit_lookahead_linear`), then the rest is cloned. Then ``dagger_iterations`` of DAgger: the teacher
   drives, the expert labels every visited state (no rendering).
2. **PPO** (stable-baselines3 on :class:`rl.vec_env.BatchedSubprocVecEnv`: one process per core, each stepping
   several envs; the paper's reward) continues from the warm start.
   A curriculum widens the (scene, density) pool with training progress (:class:`SceneMixEnv`). ``ppo_steps = 0``
   skips PPO (the teacher is then the cloned expert; the report says so).

Without the warm start, PPO alone learns an empty scene in a few thousand steps (tested) but needs millions of
steps for crowds — the paper's GPU budget, kept in the ``paper`` profile.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from pipeline.core.device import autocast
from pipeline.core.errors import ConfigError, InputMissingError
from pipeline.core.executor import process_pool
from rl.lookahead import LINEAR_TERMS, PED_TERMS, SCORE_SCALE
from rl.policy import LOOKAHEAD_KEY, act, build_policy
from rl.vec_env import BatchedSubprocVecEnv
from sim.env import CrowdNavEnv, SimConfig
from sim.episode import episode_steps
from sim.expert import PrivilegedExpert
from sim.robot import action_grid
from sim.wrappers import PrivilegedWorld


@dataclass
class CurriculumStage:
    """Until ``until`` (fraction of the PPO steps) episodes are drawn from these scenes and densities."""

    until: float = 1.0
    scenes: list[str] = field(default_factory=lambda: ["hallway", "corner", "doorway", "cluttered_room", "open_crowd"])
    densities: list[float] = field(default_factory=lambda: [0.1, 0.2])


def curriculum_pairs(stage: CurriculumStage) -> list[tuple[str, float]]:
    return [(s, float(d)) for s in stage.scenes for d in stage.densities]


def check_curriculum(stages: list[CurriculumStage]) -> None:
    if not stages:
        raise ConfigError("teacher.curriculum: expected at least one stage")
    last = 0.0
    for k, st in enumerate(stages):
        if not st.scenes or not st.densities:
            raise ConfigError(f"teacher.curriculum[{k}]: expected non-empty scenes and densities")
        if not last < st.until <= 1.0:
            raise ConfigError(f"teacher.curriculum[{k}].until: expected increasing fractions in (0, 1], got "
                              f"{st.until}")
        last = st.until
    if abs(last - 1.0) > 1e-9:
        raise ConfigError(f"teacher.curriculum: the last stage must run until 1.0, got {last}")


class SceneMixEnv(gym.Env):
    """Crowd env (privileged, discrete actions by default) drawing (scene, density) from a pool at every reset.

    One :class:`sim.env.CrowdNavEnv` per pair is built lazily; :meth:`set_pool` changes the pool (curriculum).
    """

    metadata = {"render_modes": []}

    def __init__(self, sim_cfg: SimConfig, pairs: list[tuple[str, float]], obs_mode: str = "privileged",
                 action_type: str = "discrete") -> None:
        super().__init__()
        self.sim_cfg = replace(sim_cfg, obs_mode=obs_mode, action_type=action_type, info_level="basic")
        self._envs: dict[tuple[str, float], CrowdNavEnv] = {}
        self.pairs = list(pairs)
        probe = self._env(self.pairs[0])
        self.observation_space = probe.observation_space
        self.action_space = probe.action_space
        self.current: CrowdNavEnv = probe
        self._rng = np.random.default_rng(0)

    def _env(self, pair: tuple[str, float]) -> CrowdNavEnv:
        if pair not in self._envs:
            self._envs[pair] = CrowdNavEnv(config=replace(self.sim_cfg, scene=pair[0], density=pair[1]))
        return self._envs[pair]

    def set_pool(self, pairs: list[tuple[str, float]]) -> None:
        self.pairs = [(s, float(d)) for s, d in pairs]

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        pair = self.pairs[int(self._rng.integers(len(self.pairs)))]
        self.current = self._env(pair)
        return self.current.reset(seed=int(self._rng.integers(2**31 - 1)))

    @property
    def cfg(self) -> SimConfig:
        return self.current.cfg

    @property
    def cameras(self):
        return self.current.cameras

    def close(self) -> None:
        for e in self._envs.values():
            e.close()

    def step(self, action):
        return self.current.step(action)


# ------------------------------------------------------------------------------------------------ expert warm start
def expert_episode(args: tuple[SimConfig, str, float, int, float]) -> dict[str, np.ndarray]:
    """One privileged expert episode: observations, the expert's action indices and its cost of every action,
    rewards, discounted returns (a DAgger episode in which the expert always drives)."""
    sim_cfg, scene, density, seed, gamma = args
    return expert_dagger_episode((sim_cfg, scene, density, seed, 1.0, gamma))


def expert_grid_costs(expert, env: CrowdNavEnv) -> np.ndarray:
    """The privileged expert's cost of each of the policy's discrete actions (the env's 5 x 21 grid)."""
    return expert.costs(env, action_grid(env.cfg.robot))


def discounted(rewards: list[float], gamma: float) -> np.ndarray:
    """Discounted Monte-Carlo returns of one episode (nothing is bootstrapped after a timeout)."""
    ret = np.zeros(len(rewards), np.float32)
    acc = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        acc = rewards[t] + gamma * acc
        ret[t] = acc
    return ret


def _concat(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    keys = [k for k in parts[0] if k not in ("success", "outcome")]
    data = {k: np.concatenate([p[k] for p in parts]) for k in keys}
    data["success_rate"] = np.array(np.mean([p["success"][0] for p in parts]))
    return data


def collect_expert(sim_cfg: SimConfig, pairs: list[tuple[str, float]], episodes: int, seed: int, gamma: float,
                   workers: int, progress: bool = True) -> dict[str, np.ndarray]:
    """``episodes`` expert episodes spread evenly over ``pairs`` (process pool), concatenated."""
    from tqdm import tqdm

    jobs = [(sim_cfg, *pairs[k % len(pairs)], seed + k, gamma) for k in range(episodes)]
    parts = []
    with process_pool(max(1, workers)) as pool:
        for part in tqdm(pool.map(expert_episode, jobs), total=len(jobs), desc="teacher: expert episodes",
                         unit="ep", disable=not progress, dynamic_ncols=True):
            parts.append(part)
    data = _concat(parts)
    data["expert_success_rate"] = data.pop("success_rate")
    return data


# ------------------------------------------------------------------------------------ DAgger on the expert
_WORKER_POLICY: dict[str, Any] = {}


def _init_dagger_worker(kind: str, obs_space, net: dict[str, Any], state: dict[str, torch.Tensor]) -> None:
    torch.set_num_threads(1)
    policy = build_policy(kind, None, obs_space, net)
    policy.load_state_dict(state)
    policy.set_training_mode(False)
    _WORKER_POLICY["policy"] = policy


class _ExpertDaggerDriver:
    """The privileged expert labels every visited state (its cost of each action of the grid, from
    ``info["world"]``); the worker's policy acts, the expert's label with probability ``beta`` (always without a
    policy). Records the observations, labels and costs of the states it acted in."""

    def __init__(self, policy, beta: float, rng: np.random.Generator) -> None:
        self.policy, self.beta, self.rng = policy, beta, rng
        self.expert = PrivilegedExpert()

    def reset(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> None:
        self.codec = info["action_codec"]
        self.expert.reset(info["world"])
        self.rows: dict[str, list] = {k: [] for k in obs}
        self.labels: list[int] = []
        self.costs: list[np.ndarray] = []

    def act(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> int:
        cost = expert_grid_costs(self.expert, info["world"])
        label = int(np.argmin(cost))
        a = label if self.policy is None or self.rng.random() < self.beta else act(self.policy, obs)
        self.expert.executed(self.codec.decode(a)[1])  # smoothness relative to what was executed
        for k, v in obs.items():
            self.rows[k].append(v)
        self.labels.append(label)
        self.costs.append(cost)
        return a


def expert_dagger_episode(args: tuple[SimConfig, str, float, int, float, float]) -> dict[str, np.ndarray]:
    """One DAgger episode on privileged observations: the policy of this worker drives (the expert with probability
    ``beta`` per step), the privileged expert labels every visited state with the action it would take."""
    sim_cfg, scene, density, seed, beta, gamma = args
    policy = _WORKER_POLICY["policy"] if beta < 1.0 else None
    env = PrivilegedWorld(CrowdNavEnv(config=replace(sim_cfg, scene=scene, density=density, obs_mode="privileged",
                                                     action_type="discrete", info_level="basic")))
    driver = _ExpertDaggerDriver(policy, beta, np.random.default_rng(seed + 7_919))
    rewards, outcome = [], "timeout"
    for tr in episode_steps(env, driver, seed):
        if tr.step > 0:
            rewards.append(tr.reward)
        if tr.done:
            outcome = tr.info["outcome"] or "timeout"
    out = {k: np.stack(v).astype(np.float32) for k, v in driver.rows.items()}
    out["action"] = np.asarray(driver.labels, np.int64)
    out["costs"] = np.stack(driver.costs).astype(np.float32)
    out["return"] = discounted(rewards, gamma)
    out["success"] = np.array([outcome == "success"])
    out["outcome"] = np.array([outcome])
    env.close()
    return out


def collect_dagger(policy, net: dict[str, Any], sim_cfg: SimConfig, pairs: list[tuple[str, float]], episodes: int,
                   seed: int, beta: float, gamma: float, workers: int, progress: bool = True,
                   desc: str = "teacher: DAgger") -> dict[str, np.ndarray]:
    """``episodes`` DAgger episodes of ``policy`` (a privileged teacher built with ``net``) over ``pairs``, every
    visited state labelled by the expert; concatenated like :func:`collect_expert` plus ``success_rate``."""
    from tqdm import tqdm

    state = {k: v.detach().to("cpu", copy=True) for k, v in policy.state_dict().items()}  # the workers act on CPU
    jobs = [(sim_cfg, *pairs[k % len(pairs)], seed + k, beta, gamma) for k in range(episodes)]
    init = ("teacher", policy.observation_space, net, state)
    parts = []
    with process_pool(max(1, workers), initializer=_init_dagger_worker, initargs=init) as pool:
        for part in tqdm(pool.map(expert_dagger_episode, jobs), total=len(jobs), desc=desc, unit="ep",
                         disable=not progress, dynamic_ncols=True):
            parts.append(part)
    return _concat(parts)


def behaviour_clone(policy, data: dict[str, np.ndarray], epochs: int, batch: int, lr: float, seed: int,
                    value_coef: float = 0.5, keys: tuple[str, ...] | None = None,
                    progress: bool = True, soft_tau: float = 0.0, mirror: bool = False,
                    n_rot: int = 21, frozen: tuple[str, ...] = (),
                    cache: tuple[np.ndarray, np.ndarray | None] | None = None,
                    precision: str = "fp32", epoch_size: int | None = None, indices: np.ndarray | None = None,
                    held_out: dict[str, np.ndarray] | None = None, max_epochs: int | None = None,
                    patience: int = 2, floor: float | None = None) -> list[dict[str, float]]:
    """Cross-entropy on ``data["action"]`` (+ value regression on ``data["return"]`` when present).

    With ``soft_tau > 0`` and ``data["costs"]`` (the expert's cost of every action), the target is the softmin
    ``softmax(-cost / soft_tau)`` over the whole action grid instead of the one-hot argmin: every state then says
    how much worse each other action is (dense supervision; near-ties stop being label noise). With ``mirror``
    every sample is reflected about the robot's x axis with probability 1/2 (:func:`mirror_batch`; the world is
    left-right symmetric, so this doubles the data for free). ``n_rot`` is the number of yaw rates of the grid.
    Parameters whose names start with one of ``frozen`` are not updated (the lookahead teacher's linear path, fitted
    by :func:`fit_lookahead_linear`). ``cache``: the lookahead teacher's :func:`lookahead_feature_cache` of ``data``
    when the caller has it already (computed here otherwise). The updates run on the policy's device (``policy.to``
    first); ``data`` stays in host memory and each batch is copied over. ``precision`` (resolved:
    :func:`pipeline.core.device.resolve_precision`): ``bf16`` runs the forward pass under bfloat16 autocast (the loss,
    the weights and the optimiser stay float32). The convolutions over the cached maps (``bev``, ``occ``) run
    channels-last (the policy is converted for the cloning and back afterwards: what is saved is unchanged).
    ``epoch_size``: samples per epoch (default: all of ``data``), drawn from one stream of shuffled passes over all of
    ``data`` — every frame once per pass, a pass running on across epochs — so ``epochs`` x ``epoch_size`` samples in
    all, whatever the size of ``data`` (DAgger's ``bc_schedule: new``: passes over each iteration's new frames, drawn
    from the whole pool). With ``epoch_size`` = ``len(data)`` it is the default, to the bit. ``indices``: the rows of
    ``data`` the cloning may draw (default: all; the passes are over these).

    An adaptive budget (``held_out``: frames never cloned on, and ``max_epochs`` > ``epochs``): after every epoch the
    cloning objective on ``held_out`` (:func:`bc_loss`, evaluation mode, unmirrored); past ``epochs`` the cloning goes
    on while that loss keeps reaching a new best within ``patience`` epochs, up to ``max_epochs``, and ends with the
    weights of its best epoch (early stopping: a student still learning gets more steps, one that has stopped does
    not; either way at least ``epochs`` epochs run, and the weights kept are those of the best held-out epoch). It
    does not stop while its best held-out loss is above ``floor`` (a cloning still near a uniform choice sits on the
    MLP head's early plateau, not at its end: it runs on to ``max_epochs``).

    Returns one row per epoch run: ``{"epoch", "bc_loss", "accuracy", "value_loss"}`` (means over the epoch), with
    ``held_out_loss`` and ``best`` (True on the epoch whose weights are kept) when ``held_out`` is given.
    """
    from tqdm import tqdm

    keys = keys or tuple(policy.observation_space.spaces)
    dev = policy.device
    n = len(data["action"]) if indices is None else len(indices)
    per_epoch = n if epoch_size is None else int(epoch_size)
    if per_epoch < 1:
        raise ConfigError(f"behaviour_clone epoch_size: expected an integer >= 1, got {epoch_size}")
    if n < 1:
        raise InputMissingError("behaviour_clone: no frames to clone (every frame held out, or an empty set)")
    last_epoch = epochs if held_out is None or max_epochs is None else max(epochs, int(max_epochs))
    g = torch.Generator().manual_seed(seed)
    stream = np.empty(0, np.int64)  # the unused rest of the current shuffled pass over the data

    def draw(m: int) -> np.ndarray:  # the next m sample indices of the stream of passes
        nonlocal stream
        while len(stream) < m:
            perm = torch.randperm(n, generator=g).numpy()
            stream = np.concatenate([stream, perm if indices is None else np.asarray(indices)[perm]])
        out, stream = stream[:m], stream[m:]
        return out

    trained = [p for name, p in policy.named_parameters() if not name.startswith(frozen)]
    # the frozen weights get no gradient while cloning: the optimiser does not zero theirs, so it would sum over the
    # batches — and earlier clonings of the same policy object — inside the norm clipped below, and a resumed DAgger
    # run (its policy loaded without gradients) would end with other bytes than an uninterrupted one
    held = [p for name, p in policy.named_parameters() if name.startswith(frozen) and p.requires_grad]
    opt = torch.optim.Adam(trained, lr=lr)
    policy.set_training_mode(True)

    if mirror and "bev" in keys:
        if "bev_mirror" not in data:
            raise InputMissingError("mirror augmentation of s_bev needs the mirrored world's s_bev ('bev_mirror') in "
                                    "the cached features (recorded with dagger.mirror true); clone without mirror")
        keys = (*keys, "bev_mirror")

    def take(idx: np.ndarray) -> dict[str, torch.Tensor]:  # per batch: the cache stays float16 numpy
        out = {k: torch.as_tensor(data[k][idx], dtype=torch.float32).to(dev, non_blocking=True) for k in keys}
        return {k: v.contiguous(memory_format=torch.channels_last) if v.dim() == 4 else v for k, v in out.items()}

    mirror_rng = np.random.default_rng(seed + 1)
    # the lookahead teacher's rollout features depend on the observation alone: computed once, not every epoch
    if cache is None and has_lookahead(policy):
        cache = lookahead_feature_cache(policy, data, mirror, n_rot)

    rows = []
    convs = [m for m in policy.modules() if isinstance(m, torch.nn.Conv2d)]  # the map CNNs'
    for m in convs:  # channels-last while cloning (faster on the CPU, most so in bf16); contiguous again below
        m.to(memory_format=torch.channels_last)
    policy.zero_grad(set_to_none=True)  # nothing left over from an earlier fit or cloning
    for p in held:
        p.requires_grad_(False)
    best: tuple[float, int, dict[str, torch.Tensor]] | None = None  # held-out loss, epoch, weights
    try:
        for epoch in tqdm(range(last_epoch), desc=f"behaviour cloning ({precision})", unit="epoch",
                          disable=not progress, dynamic_ncols=True):
            perm = draw(per_epoch)
            tot = {"bc_loss": 0.0, "accuracy": 0.0, "value_loss": 0.0}
            for s in range(0, per_epoch, batch):
                idx = np.sort(perm[s:s + batch])
                obs = take(idx)
                act_t = torch.as_tensor(data["action"][idx], dtype=torch.long).to(dev)
                cost = torch.as_tensor(data["costs"][idx], dtype=torch.float32).to(dev) if "costs" in data else None
                afeat = None if cache is None else torch.as_tensor(cache[0][idx], dtype=torch.float32).to(dev)
                if mirror:
                    flip = torch.as_tensor(mirror_rng.random(len(idx)) < 0.5).to(dev)
                    obs, act_t, cost = mirror_batch(obs, act_t, cost, flip, n_rot)
                    if cache is not None:
                        afeat = torch.where(flip.view(-1, 1, 1),
                                            torch.as_tensor(cache[1][idx], dtype=torch.float32).to(dev), afeat)
                with autocast(dev, precision):
                    logits, values = policy_logits_values(policy, obs, afeat)
                logits, values = logits.float(), values.float()
                logp_all = torch.log_softmax(logits, -1)
                if soft_tau > 0 and cost is not None:  # cross-entropy to the expert's softmin over the whole grid
                    target = torch.softmax(-(cost - cost.min(1, keepdim=True).values) / soft_tau, -1)
                    loss_bc = -(target * logp_all).sum(-1).mean()
                else:
                    loss_bc = -logp_all.gather(1, act_t.unsqueeze(1)).mean()
                loss = loss_bc
                if "return" in data:
                    ret = torch.as_tensor(data["return"][idx], dtype=torch.float32).to(dev)
                    loss_v = torch.nn.functional.mse_loss(values.flatten(), ret)
                    loss = loss + value_coef * loss_v
                    tot["value_loss"] += loss_v.item() * len(idx)
                opt.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(trained, 1.0)  # this batch's gradient of the weights it updates
                opt.step()
                pred = logits.detach().argmax(-1)
                tot["bc_loss"] += loss_bc.item() * len(idx)
                tot["accuracy"] += float((pred == act_t).float().sum())
            rows.append({"epoch": epoch, **{k: v / per_epoch for k, v in tot.items()}})
            if held_out is None:
                continue
            policy.set_training_mode(False)
            rows[-1]["held_out_loss"] = loss = bc_loss(policy, held_out, soft_tau=soft_tau)
            policy.set_training_mode(True)
            if best is None or loss < best[0]:
                best = (loss, epoch, {k: v.detach().clone() for k, v in policy.state_dict().items()})
            if epoch + 1 >= epochs and epoch - best[1] >= patience and (floor is None or best[0] <= floor):
                break  # no new best for `patience` epochs past the minimum, and off the plateau
        if best is not None:
            policy.load_state_dict(best[2])
            for r in rows:
                r["best"] = r["epoch"] == best[1]
    finally:
        for m in convs:
            m.to(memory_format=torch.contiguous_format)
        for p in held:
            p.requires_grad_(True)
        policy.set_training_mode(False)
    return rows


def fit_lookahead_linear(policy, data: dict[str, np.ndarray], soft_tau: float, max_frames: int = 20_000,
                         seed: int = 0, mirror: bool = True, n_rot: int = 21,
                         cache: tuple[np.ndarray, np.ndarray | None] | None = None,
                         terms: str = "all", map_signs: str = "free") -> dict[str, Any]:
    """Fits the linear path of a lookahead teacher (:class:`rl.networks.LookaheadTeacherExtractor`) to the expert's
    softmin targets by convex multinomial regression (L-BFGS), and zeroes the MLP scorer's output layer, so cloning
    starts from the best linear cost over the rollout features instead of from random logits (Adam would need
    thousands of steps to grow weights to the tens of nats the expert's costs span). With ``mirror`` the fit also
    sees every frame reflected. ``cache``: :func:`lookahead_feature_cache` of all of ``data`` (with the same
    ``mirror``) when the caller has it; otherwise only the subsample's features are computed. ``terms``: ``"all"``
    fits the linear cost and, when the head reads an occupancy map, its map cost; ``"map"`` only the map cost, on
    top of the linear cost a student inherited from its teacher; ``"peds"`` the inherited cost's pedestrian terms
    (:data:`rl.lookahead.PED_TERMS`) together with the map cost, every other term held at the teacher's weight. ``map_signs``: ``"free"`` fits the map weights
    unconstrained; ``"costs"`` constrains every one to be a cost (occupancy along an arc never raises its score:
    weight <= 0), solved exactly by an active-set loop (:func:`_fit_nonpositive`). Returns the cross-entropy to the
    targets before and after (and the fitted map weights). Runs on the policy's device."""
    head = policy.features_extractor.lookahead  # rl.lookahead.LookaheadHead
    if terms not in FIT_TERMS or (terms == "map" and not head.n_map):
        raise ConfigError(f"fit_lookahead_linear terms: expected 'all', 'peds', or 'map' for a head with a map, "
                          f"got {terms!r}")
    if map_signs not in MAP_SIGNS:
        raise ConfigError(f"fit_lookahead_linear map_signs: expected one of {list(MAP_SIGNS)}, got {map_signs!r}")
    dev = policy.device
    rng = np.random.default_rng(seed)
    n = len(data["action"])
    idx = np.sort(rng.choice(n, min(n, max_frames), replace=False))
    if cache is None:
        sub = {k: data[k][idx] for k in (*head.input_keys, "action") if k in data}
        cache = lookahead_feature_cache(policy, sub, mirror, n_rot)
    else:
        cache = (cache[0][idx], None if cache[1] is None else cache[1][idx])
    cost = torch.as_tensor(data["costs"][idx], dtype=torch.float32).to(dev)
    feats = torch.as_tensor(cache[0], dtype=torch.float32).to(dev)
    if mirror:
        flip = torch.ones(len(cost), dtype=torch.bool, device=dev)
        _, _, mcost = mirror_batch({}, torch.zeros(len(cost), dtype=torch.long, device=dev), cost, flip, n_rot)
        cost = torch.cat([cost, mcost])
        feats = torch.cat([feats, torch.as_tensor(cache[1], dtype=torch.float32).to(dev)])
    tau = soft_tau if soft_tau > 0 else 0.1
    target = torch.softmax(-(cost - cost.min(1, keepdim=True).values) / tau, -1)

    def ce() -> torch.Tensor:
        logits = SCORE_SCALE * head.fitted_cost(feats).squeeze(-1)
        return -(target * torch.log_softmax(logits, -1)).sum(-1).mean()

    with torch.no_grad():
        head.scorer[-1].weight.zero_()
        head.scorer[-1].bias.zero_()
        before = float(ce())
    params = [*(head.linear.parameters() if terms == "all" else (head.linear.weight,) if terms == "peds" else ()),
              *(head.map_cost.parameters() if head.n_map else ())]
    keep = torch.zeros_like(head.linear.weight, dtype=torch.bool)
    if terms == "peds":  # every other term keeps its weight: its gradient is masked, so L-BFGS never moves it
        keep[:] = True
        keep[0, list(PED_TERMS)] = False
    with masked_gradient(head.linear.weight, keep):
        pinned = _fit_nonpositive(params, head.map_cost.weight, ce) if head.n_map and map_signs == "costs" else None
        if pinned is None:
            _lbfgs(params, ce)
    out: dict[str, Any] = {"frames": int(len(cost)), "ce_before": before, "ce_after": float(ce().detach()),
                           # nats per unit of each term, like the map weights below
                           "linear_weights": {name: round(float(w) * SCORE_SCALE, 3) for name, w in
                                              zip(LINEAR_TERMS, head.linear.weight.detach().view(-1), strict=True)}}
    if pinned is not None:  # the map terms the sign constraint holds at 0
        out["map_pinned"] = pinned
    if head.n_map:  # nats per unit of each map feature (static max, static mean, people max, people mean)
        out["map_weights"] = [round(float(w) * SCORE_SCALE, 3) for w in head.map_cost.weight.detach().view(-1)]
    return out


MAP_SIGNS = ("free", "costs")  # fit_lookahead_linear(map_signs=...)
FIT_TERMS = ("all", "map", "peds")  # fit_lookahead_linear(terms=...)


def _lbfgs(params: list[torch.Tensor], loss_fn) -> None:
    """Minimises the convex ``loss_fn()`` over ``params`` by L-BFGS (strong Wolfe line search)."""
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=200, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        return loss

    opt.step(closure)


def _fit_nonpositive(params: list[torch.Tensor], w: torch.Tensor, loss_fn, rounds: int = 8) -> list[int]:
    """Minimises the convex ``loss_fn()`` over ``params`` subject to every entry of ``w`` (one of ``params``) being
    <= 0, by an active-set loop: entries held at 0 get no gradient (so L-BFGS's steps leave them there); after each
    fit, free entries that came out positive are pinned at 0, and pinned entries whose gradient at 0 is positive
    (lowering them would lower the loss) are freed. Stops when neither happens — the KKT conditions of the
    constrained problem — or after ``rounds`` fits. Returns the pinned indices (of ``w.view(-1)``)."""
    pinned = torch.zeros(w.numel(), dtype=torch.bool, device=w.device)
    try:
        for _ in range(rounds):
            with torch.no_grad():
                w.view(-1)[pinned] = 0.0
            with masked_gradient(w, pinned):
                _lbfgs(params, loss_fn)
            violating = ~pinned & (w.detach().view(-1) > 0)
            if violating.any():
                pinned |= violating
                continue
            (grad,) = torch.autograd.grad(loss_fn(), w)  # the unmasked gradient: would a pinned entry move down?
            release = pinned & (grad.view(-1) > 0)
            if not release.any():
                break
            pinned &= ~release
        with torch.no_grad():
            w.view(-1)[pinned] = 0.0
    finally:
        for p in params:
            p.grad = None
    return [int(i) for i in torch.nonzero(pinned).view(-1)]


@contextmanager
def masked_gradient(t: torch.Tensor, mask: torch.Tensor) -> Iterator[None]:
    """Inside the block the entries of ``t`` where ``mask`` (same number of entries, read at every backward pass) is
    True get a zero gradient, so L-BFGS's steps leave them where they are: how a fit holds some weights fixed."""
    hook = t.register_hook(lambda g: g.masked_fill(mask.view_as(g), 0.0))
    try:
        yield
    finally:
        hook.remove()


FITTED_PREFIXES = ("features_extractor.lookahead.linear.", "features_extractor.lookahead.map_cost.")


def has_lookahead(policy) -> bool:
    return hasattr(policy.features_extractor, "action_features")


@torch.no_grad()
def lookahead_feature_cache(policy, data: dict[str, np.ndarray], mirror: bool, n_rot: int = 21,
                            keys: tuple[str, ...] | None = None, chunk: int = 2048) -> tuple[np.ndarray, np.ndarray | None]:
    """The lookahead head's rollout features of every frame of ``data`` (``N x A x F``, float16) and, with
    ``mirror``, of every frame reflected (what :func:`mirror_batch` makes of it). Computed on the policy's device
    from the observation keys the head reads (``keys``: default those of the policy's observation space in
    :attr:`rl.lookahead.LookaheadHead.input_keys` — not a student's ``bev`` features, ≈ 190 KB a frame with their
    mirror, which the features do not depend on), kept in host memory."""
    ext = policy.features_extractor
    dev = policy.device
    keys = keys or tuple(k for k in policy.observation_space.spaces if k in ext.lookahead.input_keys)
    if mirror and "bev" in keys and "bev_mirror" not in keys:  # mirror_batch swaps in the mirrored world's s_bev
        keys = (*keys, "bev_mirror")
    n = len(data["action"])
    out = [np.empty((n, ext.lookahead.n_actions, ext.lookahead.n_feat), np.float16) for _ in range(1 + mirror)]
    for s in range(0, n, chunk):
        obs = {k: torch.as_tensor(data[k][s:s + chunk], dtype=torch.float32).to(dev) for k in keys}
        out[0][s:s + chunk] = ext.action_features(obs).cpu().numpy()
        if mirror:
            flip = torch.ones(len(obs[keys[0]]), dtype=torch.bool, device=dev)
            mobs, _, _ = mirror_batch(obs, torch.zeros(len(flip), dtype=torch.long, device=dev), None, flip, n_rot)
            out[1][s:s + chunk] = ext.action_features(mobs).cpu().numpy()
    return out[0], (out[1] if mirror else None)


def extend_feature_cache(cache: tuple[np.ndarray, np.ndarray | None] | None,
                         more: tuple[np.ndarray, np.ndarray | None]) -> tuple[np.ndarray, np.ndarray | None]:
    """``cache`` (:func:`lookahead_feature_cache` of some frames; None: no frames yet) followed by ``more`` (the same
    of the frames appended after them): what :func:`lookahead_feature_cache` gives for all of them, whose features
    are computed per frame."""
    if cache is None:
        return more
    if (cache[1] is None) != (more[1] is None):
        raise ValueError("extend_feature_cache: both caches need the mirrored features, or neither")
    return (np.concatenate([cache[0], more[0]]),
            None if cache[1] is None else np.concatenate([cache[1], more[1]]))


def policy_logits_values(policy, obs: dict[str, torch.Tensor],
                         action_features: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Action logits and values of an SB3 ``ActorCriticPolicy`` (discrete actions) in one forward pass
    (``action_features``: the lookahead teacher's precomputed rollout features of this batch)."""
    features = (policy.extract_features(obs) if action_features is None
                else policy.features_extractor(obs, action_features))
    latent_pi, latent_vf = policy.mlp_extractor(features)
    return policy.action_net(latent_pi), policy.value_net(latent_vf)


# COCO-17 joint order (nose, eyes, ears, shoulders, elbows, wrists, hips, knees, ankles; left before right) mirrored
COCO_MIRROR = (0, 2, 1, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11, 14, 13, 16, 15)


def mirror_batch(obs: dict[str, torch.Tensor], action: torch.Tensor, cost: torch.Tensor | None, flip: torch.Tensor,
                 n_rot: int) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor | None]:
    """Reflects the samples where ``flip`` about the robot's x axis: y, v_y of the goal state, of the sub-goal, of the
    path points and of every pedestrian change sign, scan ray k becomes ray −k, and yaw-rate index j of the action grid
    becomes n_rot−1−j. Student keys: the occupancy map's y axis is reversed, detected joints change y and swap left
    and right (COCO-17), and ``bev`` is replaced by ``bev_mirror`` (the mirrored world's own ``s_bev``, recorded by
    :class:`rl.observe.StudentObserver` with ``mirror=True``)."""
    out = dict(obs)
    f = flip.view(-1, 1)
    if "state" in obs:  # [g_x, g_y, d_g, v_x, v_y]
        sign = obs["state"].new_tensor([1.0, -1.0, 1.0, 1.0, -1.0])
        out["state"] = torch.where(f, obs["state"] * sign, obs["state"])
    if "peds" in obs:  # [x, y, vx, vy, r, present]
        sign = obs["peds"].new_tensor([1.0, -1.0, 1.0, -1.0, 1.0, 1.0])
        out["peds"] = torch.where(f.unsqueeze(-1), obs["peds"] * sign, obs["peds"])
    if "peds_future" in obs:  # K x S x [x, y]: the intention model's prediction (reflected with the world)
        sign = obs["peds_future"].new_tensor([1.0, -1.0])
        out["peds_future"] = torch.where(f.view(-1, 1, 1, 1), obs["peds_future"] * sign, obs["peds_future"])
    if "subgoal" in obs:  # [x, y]
        out["subgoal"] = torch.where(f, obs["subgoal"] * obs["subgoal"].new_tensor([1.0, -1.0]), obs["subgoal"])
    if "path" in obs:  # P x [x, y]
        out["path"] = torch.where(f.unsqueeze(-1), obs["path"] * obs["path"].new_tensor([1.0, -1.0]), obs["path"])
    for key in ("occ", "bev_occ"):  # C x X x Y maps on a grid symmetric in y: reverse the y axis (bev_occ: the
        if key in obs:  # predicted occupancy reflected, a stand-in for what the encoder would predict of the mirror)
            out[key] = torch.where(f.view(-1, 1, 1, 1), torch.flip(obs[key], [-1]), obs[key])
    if "bev" in obs:  # the encoder's latent is not mirror-equivariant: the mirrored world's own s_bev is needed
        if "bev_mirror" not in obs:
            raise ValueError("mirror_batch: 'bev' needs 'bev_mirror' (StudentObserver(mirror=True))")
        out["bev"] = torch.where(f.view(-1, 1, 1, 1), obs["bev_mirror"], obs["bev"])
    out.pop("bev_mirror", None)
    if "poses" in obs:  # K x 17 x [x, y, z], robot frame: y changes sign, left and right joints swap
        perm = torch.as_tensor(COCO_MIRROR, device=obs["poses"].device)
        sign = obs["poses"].new_tensor([1.0, -1.0, 1.0])
        out["poses"] = torch.where(f.view(-1, 1, 1, 1), obs["poses"][:, :, perm] * sign, obs["poses"])
        out["pose_mask"] = torch.where(f.view(-1, 1, 1), obs["pose_mask"][:, :, perm], obs["pose_mask"])
    if "scan" in obs:  # rays at heading + k·2π/n → heading − k·2π/n
        rev = torch.roll(torch.flip(obs["scan"], [-1]), 1, -1)
        out["scan"] = torch.where(f, rev, obs["scan"])
    i, j = action // n_rot, action % n_rot
    action = torch.where(flip, i * n_rot + (n_rot - 1 - j), action)
    if cost is not None:
        c = cost.view(len(cost), -1, n_rot)
        cost = torch.where(f, torch.flip(c, [-1]).reshape(len(cost), -1), cost)
    return out, action, cost


@torch.no_grad()
def bc_loss(policy, data: dict[str, np.ndarray], batch: int = 1024, soft_tau: float = 0.0) -> float:
    """Mean negative log-likelihood of ``data["action"]`` under ``policy`` (no gradient); with ``soft_tau > 0`` and
    ``data["costs"]``, the cross-entropy to the softmin of the costs instead (the cloning objective). On the policy's
    device."""
    keys = tuple(policy.observation_space.spaces)
    dev = policy.device
    n = len(data["action"])
    tot = 0.0
    for s in range(0, n, batch):
        obs = {k: torch.as_tensor(data[k][s:s + batch], dtype=torch.float32).to(dev) for k in keys}
        if soft_tau > 0 and "costs" in data:
            logits, _ = policy_logits_values(policy, obs)
            cost = torch.as_tensor(data["costs"][s:s + batch], dtype=torch.float32).to(dev)
            target = torch.softmax(-(cost - cost.min(1, keepdim=True).values) / soft_tau, -1)
            tot += float(-(target * torch.log_softmax(logits, -1)).sum())
        else:
            _, logp, _ = policy.evaluate_actions(obs, torch.as_tensor(data["action"][s:s + batch]).to(dev))
            tot += float(-logp.sum())
    return tot / max(n, 1)


def make_vec_env(sim_cfg: SimConfig, pairs: list[tuple[str, float]], n_envs: int, seed: int, subprocess: bool,
                 vec_env_cls: type | None = None):
    """``n_envs`` privileged :class:`SceneMixEnv` s, env ``i`` seeded with ``seed + i`` at the first reset.

    ``subprocess`` and more than one env: :class:`rl.vec_env.BatchedSubprocVecEnv` (one worker process per usable
    core, each stepping its block of envs together); else SB3's ``DummyVecEnv`` in this process. Both give the same
    episodes. ``vec_env_cls`` (e.g. SB3's ``SubprocVecEnv``, for the benchmark's comparison) replaces the subprocess
    class; it is called as ``cls(env_fns, start_method="fork")``.
    """
    from stable_baselines3.common.vec_env import DummyVecEnv

    fns = [lambda: SceneMixEnv(sim_cfg, pairs) for _ in range(n_envs)]
    if subprocess and n_envs > 1:
        venv = (vec_env_cls or BatchedSubprocVecEnv)(fns, start_method="fork")
    else:
        venv = DummyVecEnv(fns)
    venv.seed(seed)
    return venv


def _lookahead_buffer_class():
    from stable_baselines3.common.buffers import DictRolloutBuffer

    class _Buffer(DictRolloutBuffer):
        """A rollout buffer that computes the lookahead teacher's rollout features of every stored observation once
        per rollout (they depend on the observation alone) and hands them to the policy with each minibatch, so
        PPO's epochs do not recompute them (:class:`rl.policy.ScoredPolicy` reads ``LOOKAHEAD_KEY``)."""

        features_fn = None
        features_s = 0.0  # wall time spent computing the cached features so far (rl.bench reports it)

        def reset(self) -> None:
            super().reset()
            self._lookahead: torch.Tensor | None = None

        @torch.no_grad()
        def _features(self) -> torch.Tensor:
            n = len(next(iter(self.observations.values())))
            parts = []
            for s in range(0, n, 2048):  # on the model's device (the buffer's)
                obs = {k: torch.as_tensor(v[s:s + 2048], dtype=torch.float32).to(self.device)
                       for k, v in self.observations.items()}
                parts.append(self.features_fn(obs))
            return torch.cat(parts)

        def _get_samples(self, batch_inds, env=None):
            samples = super()._get_samples(batch_inds, env)
            if self.features_fn is not None:  # called after get() flattened the observations
                if self._lookahead is None:
                    t0 = time.perf_counter()
                    self._lookahead = self._features()
                    self.features_s += time.perf_counter() - t0
                samples.observations[LOOKAHEAD_KEY] = self._lookahead[torch.as_tensor(batch_inds,
                                                                                      device=self._lookahead.device)]
            return samples

    return _Buffer


def attach_lookahead_cache(model) -> None:
    """Gives a PPO model of the lookahead teacher a rollout buffer that caches the rollout features (no-op for other
    policies). Call after building or loading the model."""
    if not has_lookahead(model.policy):
        return
    rb = model.rollout_buffer
    buf = _lookahead_buffer_class()(rb.buffer_size, rb.observation_space, rb.action_space, device=rb.device,
                                    gae_lambda=rb.gae_lambda, gamma=rb.gamma, n_envs=rb.n_envs)
    buf.features_fn = model.policy.features_extractor.action_features
    model.rollout_buffer = buf


def curriculum_callback(stages: list[CurriculumStage], total_steps: int, start_steps: int = 0):
    """An SB3 callback that sets each env's (scene, density) pool from the training progress."""
    from stable_baselines3.common.callbacks import BaseCallback

    class Curriculum(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.stage = -1

        def _on_step(self) -> bool:
            frac = (self.num_timesteps - start_steps) / max(total_steps, 1)
            k = next((i for i, st in enumerate(stages) if frac < st.until), len(stages) - 1)
            if k != self.stage:
                self.stage = k
                self.training_env.env_method("set_pool", curriculum_pairs(stages[k]))
                self.logger.record("curriculum/stage", k)
            return True

    return Curriculum()


def stage_pairs_all(stages: list[CurriculumStage]) -> list[tuple[str, float]]:
    seen: dict[tuple[str, float], None] = {}
    for st in stages:
        for p in curriculum_pairs(st):
            seen[p] = None
    return list(seen)


def teacher_net(net: dict[str, Any], sim_cfg: SimConfig) -> dict[str, Any]:
    """The teacher's network description with what its extractor needs from the simulator (saved with the policy,
    so a checkpoint rebuilds without the training config): the scan range, and for the lookahead encoder the
    robot's limits, radius and action grid and the control period."""
    from dataclasses import asdict

    out = {**net, "scan_range_m": sim_cfg.scan_range_m}
    if net.get("encoder") == "lookahead":
        out.update({"robot": asdict(sim_cfg.robot), "dt_s": sim_cfg.dt_s, "path_spacing_m": sim_cfg.path_spacing_m})
    return out


def ppo_kwargs(ppo: dict[str, Any]) -> dict[str, Any]:
    """SB3 PPO keyword arguments from a config section (the paper's values as defaults)."""
    keys = ("n_steps", "batch_size", "n_epochs", "learning_rate", "gamma", "gae_lambda", "clip_range",
            "ent_coef", "vf_coef", "max_grad_norm", "target_kl")
    out = {"n_steps": 1024, "batch_size": 128, "n_epochs": 6, "learning_rate": 5e-4, "gamma": 0.99,
           "gae_lambda": 0.95, "clip_range": 0.2, "ent_coef": 0.0, "vf_coef": 0.5, "max_grad_norm": 0.5}
    unknown = sorted(set(ppo) - set(keys))
    if unknown:
        raise ConfigError(f"ppo: unknown option(s) {unknown}; options: {list(keys)}")
    out.update({k: ppo[k] for k in keys if k in ppo and ppo[k] is not None})
    for k in ("n_steps", "batch_size", "n_epochs"):
        out[k] = int(out[k])
    return out

