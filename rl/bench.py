"""Benchmark figures of training and inference (called by ``icrowdnav bench``).

* ``teacher_env_steps_per_s`` — the teacher's PPO (stable-baselines3, privileged envs; ``n_envs`` envs in
  :class:`rl.vec_env.BatchedSubprocVecEnv`, one worker process per usable core, as ``train`` runs it) collecting and
  updating, env steps per second of wall time; references in the same run, the same PPO:
  ``teacher_env_steps_per_s_sb3_subproc`` — SB3's ``SubprocVecEnv`` (one process per env, in lockstep; what the
  teacher used before), its chunks alternating with the batched one's so load on a shared machine reaches both, and
  ``teacher_env_steps_per_s_1env`` — one in-process env (DummyVecEnv); the ratios are reported. Where the time goes,
  from the batched run: ``teacher_collect_s_share`` (collecting vs updating), ``teacher_collect_ms_per_step`` (wall
  time of collecting per env step), and the CPU cost per env step of each part measured alone —
  ``teacher_env_step_ms`` (one env, in process), ``teacher_policy_ms_per_step`` (the rollout forward pass per env,
  batched over ``n_envs``), ``teacher_update_ms_per_step`` (PPO's update per collected step: ``n_epochs`` passes,
  one thread; ``teacher_update_cache_ms_per_step`` of it fills the lookahead teacher's feature cache, once per
  rollout). Two ceilings from these parts: ``teacher_cpu_bound_steps_per_s`` — every core busy with no waiting at
  all, ``cores / (sum of the three)``, what any scheduling of this PPO reaches on this machine — and
  ``teacher_loop_bound_steps_per_s`` — SB3's PPO loop as it runs: only the env steps are spread over the cores, the
  forward pass and the update run on one thread while the env workers wait, ``1 / (env / cores + policy +
  update)``; ``teacher_cores`` is the usable core count (``os.sched_getaffinity``);
* ``dagger_ms_per_frame`` / ``dagger_ms_per_frame_<phase>`` — one DAgger rollout frame of the default student,
  phase by phase (simulator, rendering, detector, encoder with its mirrored world and map heads, perception,
  teacher, MCAP, features file), against the same episodes with the encoder in bf16 where native
  (:func:`measure_dagger_rollout`);
* ``dagger_pool_*`` — the students' DAgger frame pool in memory and memory-mapped against the list + concatenate
  it replaced: peak allocated memory and seconds per mode (:func:`measure_frame_pool`);
* ``student_ppo_env_steps_per_s_<no_bev|full>`` / ``student_ppo_update_share_<variant>`` — the rendered student's
  PPO fine-tuning throughput as ``train`` runs it (:func:`measure_student_ppo`);
* ``policy_inference_ms`` / ``policy_inference_hz`` — the full visual policy (variant ``full``) from the two RGB-D
  frames + detected poses to an action index, one CPU thread: streaming encoder step (newest frame only) + pooling +
  φ_bev + I²Former + fusion + actor head; ``policy_inference_recompute_ms`` — the same with the encoder recomputing
  the whole T-frame window (what a policy without the streaming cache does), and the ratio;
* ``student_clone_ms_per_kframe_<device>`` — the default student's DAgger update (``full``, the lookahead head, the
  profile's ``dagger`` batch, learning rate, soft targets and mirroring; :func:`rl.teacher.behaviour_clone`) per
  1,000 frames and epoch, the lookahead feature cache included, on synthetic frames of the observation's shapes;
  ``student_encoder_ms_<device>_b<B>`` — the frozen BEV encoder's streaming step on B streams at once (2 = one env
  with its mirrored world, as DAgger records; 16 = eight such envs); the CUDA / CPU ratios when both are measured
  (:func:`measure_student_devices`; ``python -m rl.bench --dataset ROOT --devices cpu,cuda`` on a GPU machine, no
  simulator needed: the cameras come from ``ROOT/meta/info.json``); with ``--fuse-pool P`` also the encoder with
  ``encoder.fuse_pool: P`` (keys ``..._fuse_pool<P>``).

Weights are random (speed does not depend on them); the encoder has the profile's ``pretrain.encoder`` architecture,
the frames are rendered from the bench scene at the profile's resolution.
"""

from __future__ import annotations

import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.core.config import load_config
from pipeline.core.device import machine_facts, native_bf16, resolve_device
from pipeline.core.errors import reports_errors
from pipeline.core.timing import PhaseClock, time_call
from pretrain.checkpoint import write_encoder_checkpoint
from pretrain.geometry import cameras_from_dataset
from pretrain.intention import ForecasterConfig, IntentionForecaster
from pretrain.model import BEVEncoder, BEVStream, EncoderConfig, PretextHeads
from pretrain.quantize import BF16BEVEncoder, QuantizedBEVEncoder
from pretrain.stage import PretrainConfig
from rl.dagger import PHASES, dagger_episode, pool_frames
from rl.observe import BEV_POOL, StudentEnv, StudentObserver, env_cameras, observer_for_env, perception_params
from rl.policy import act, build_policy, describe, policy_class, policy_kwargs, save_policy
from rl.stage import TrainConfig, student_net
from rl.teacher import (
    SceneMixEnv,
    attach_lookahead_cache,
    behaviour_clone,
    collect_expert,
    fit_lookahead_linear,
    make_vec_env,
    ppo_kwargs,
    teacher_net,
)
from rl.vec_env import usable_cores
from sim.env import CrowdNavEnv


def measure_teacher(sim_cfg: Any, scene: str, density: float, seed: int, train_cfg: Any, seconds: float) -> dict:
    """The teacher's PPO throughput with the configured vec env, SB3's ``SubprocVecEnv`` and one env, and the cost
    breakdown that bounds it (module docstring). The vectorised runs alternate rollout + update chunks, so load on
    a shared machine reaches both alike; each runs for at least ``seconds``."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.logger import Logger
    from stable_baselines3.common.vec_env import SubprocVecEnv

    t = train_cfg.teacher
    cores = usable_cores()
    net = teacher_net(dict(t.net), sim_cfg)
    out: dict[str, float] = {}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)

    def build(n_envs: int, subprocess: bool, cls: type | None = None):
        venv = make_vec_env(sim_cfg, [(scene, density)], n_envs, seed, subprocess, vec_env_cls=cls)
        model = PPO(policy_class("teacher", net), venv, policy_kwargs=policy_kwargs("teacher", None, net),
                    seed=seed, device="cpu", **ppo_kwargs(t.ppo))
        model.set_logger(Logger(None, []))  # nothing to keep (SB3's default makes an empty folder in the temp dir)
        attach_lookahead_cache(model)
        model.learn(model.n_steps * n_envs)  # warm-up: one rollout + update
        return model

    batched = t.subprocess and t.n_envs > 1
    runs = {"teacher_env_steps_per_s": (t.n_envs, t.subprocess, None)}
    if batched:  # today's reference: SB3's one env per process, the same PPO
        runs["teacher_env_steps_per_s_sb3_subproc"] = (t.n_envs, True, SubprocVecEnv)
    models = {}
    try:
        for key, spec in runs.items():
            models[key] = build(*spec)
        main = models["teacher_env_steps_per_s"]
        spent = _time_phases(main)
        cache_s0 = getattr(main.rollout_buffer, "features_s", 0.0)  # the lookahead teacher's feature cache
        wall = dict.fromkeys(models, 0.0)
        done = dict.fromkeys(models, 0)
        while min(wall.values()) < seconds:
            for key, model in models.items():
                chunk = model.n_steps * model.n_envs
                t0 = time.perf_counter()
                model.learn(chunk, reset_num_timesteps=False)
                wall[key] += time.perf_counter() - t0
                done[key] += chunk
        out.update({key: done[key] / wall[key] for key in models})
        n = done["teacher_env_steps_per_s"]
        out["teacher_collect_s_share"] = spent["collect"] / (spent["collect"] + spent["train"])
        out["teacher_collect_ms_per_step"] = 1e3 * spent["collect"] / n
        out["teacher_update_ms_per_step"] = 1e3 * spent["train"] / n
        out["teacher_update_cache_ms_per_step"] = 1e3 * (getattr(main.rollout_buffer, "features_s", 0.0)
                                                         - cache_s0) / n
        out["teacher_policy_ms_per_step"] = _policy_ms_per_step(main, main.get_env(), t.n_envs)
        for model in models.values():
            model.get_env().close()
        models.clear()
        models["1env"] = one = build(1, False)
        t0, n1 = time.perf_counter(), 0
        while time.perf_counter() - t0 < seconds or n1 == 0:
            one.learn(one.n_steps, reset_num_timesteps=False)
            n1 += one.n_steps
        out["teacher_env_steps_per_s_1env"] = n1 / (time.perf_counter() - t0)
        out["teacher_env_step_ms"] = _env_step_ms(sim_cfg, scene, density, seed, seconds / 4)
    finally:
        for model in models.values():
            model.get_env().close()
        torch.set_num_threads(threads)
    out["teacher_env_steps_speedup_vs_1env"] = out["teacher_env_steps_per_s"] / out["teacher_env_steps_per_s_1env"]
    if batched:
        out["teacher_env_steps_speedup_vs_sb3_subproc"] = (out["teacher_env_steps_per_s"]
                                                           / out["teacher_env_steps_per_s_sb3_subproc"])
    env_ms, policy_ms, update_ms = (out["teacher_env_step_ms"], out["teacher_policy_ms_per_step"],
                                    out["teacher_update_ms_per_step"])
    out["teacher_cores"] = float(cores)
    out["teacher_cpu_bound_steps_per_s"] = 1e3 * cores / (env_ms + policy_ms + update_ms)
    out["teacher_loop_bound_steps_per_s"] = 1e3 / (env_ms / cores + policy_ms + update_ms)
    return out


def _pool_by(mode: str, files: list[Path]) -> dict[str, np.ndarray]:
    """The episodes ``files`` pooled by ``mode``: ``concat`` — the reference, a list of every episode's arrays and
    then ``np.concatenate`` (how the DAgger loop pooled before :func:`rl.dagger.pool_frames`) —, ``memory`` or
    ``mapped`` (``pool_frames`` under / over its memory limit)."""
    if mode == "concat":
        parts: dict[str, list[np.ndarray]] = {}
        for f in files:
            with np.load(f) as z:
                for k in z.files:
                    parts.setdefault(k, []).append(z[k])
        return {k: np.concatenate(v) for k, v in parts.items()}
    return pool_frames(files, memory_gb=None if mode == "memory" else 1e-9, scratch=files[0].parent)


def measure_frame_pool(frames: int = 5000, bev_shape: tuple[int, int, int] = (32, 30, 48), n_actions: int = 105,
                       episode_frames: int = 125) -> dict[str, float]:
    """The DAgger frame pool (:func:`rl.dagger.pool_frames`) against the reference it replaced (a list of parts, then
    ``np.concatenate``): ``frames`` synthetic frames of the students' cached features (``bev`` and ``bev_mirror``
    float16 of ``bev_shape`` — the default profile's pooled s_bev —, state, action, teacher logits) in episodes of
    ``episode_frames``. Keys ``dagger_pool_<concat|memory|mapped>_peak_gib`` — the peak of the memory allocated while
    pooling, the pool included (``tracemalloc``, which numpy reports its arrays to; a memory-mapped pool lives in
    the page cache, which the kernel can drop, not in allocated memory) — and ``..._s`` (untraced, the faster of two
    rounds, modes alternating), ``dagger_pool_gib`` and the reference's peak over the pool's,
    ``dagger_pool_peak_ratio_concat_vs_memory``."""
    import tempfile
    import tracemalloc

    g = np.random.default_rng(0)
    modes = ("concat", "memory", "mapped")
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="icrowdnav-bench-pool-") as root:
        for e in range(0, frames, episode_frames):
            n = min(episode_frames, frames - e)
            np.savez(Path(root) / f"e{e:07d}.npz", action=g.integers(0, n_actions, n),
                     bev=g.standard_normal((n, *bev_shape)).astype(np.float16),
                     bev_mirror=g.standard_normal((n, *bev_shape)).astype(np.float16),
                     state=g.standard_normal((n, 7)).astype(np.float32),
                     teacher_logits=g.standard_normal((n, n_actions)).astype(np.float32))
        files = sorted(Path(root).glob("*.npz"))
        for _ in range(2):
            for mode in modes:
                t = time.perf_counter()
                pool = _pool_by(mode, files)
                out[f"dagger_pool_{mode}_s"] = min(time.perf_counter() - t, out.get(f"dagger_pool_{mode}_s", np.inf))
                out["dagger_pool_gib"] = sum(a.nbytes for a in pool.values()) / 2**30
                del pool
        for mode in modes:
            tracemalloc.start()
            try:
                pool = _pool_by(mode, files)
                out[f"dagger_pool_{mode}_peak_gib"] = tracemalloc.get_traced_memory()[1] / 2**30
                del pool
            finally:
                tracemalloc.stop()
    out["dagger_pool_frames"] = float(frames)
    out["dagger_pool_peak_ratio_concat_vs_memory"] = out["dagger_pool_concat_peak_gib"] / out["dagger_pool_memory_peak_gib"]
    return out


def measure_student_ppo(sim_cfg: Any, scene: str, density: float, seed: int, train_cfg: Any, encoder_cfg: Any,
                        seconds: float, variants: tuple[str, ...] = ("no_bev", "full")) -> dict[str, float]:
    """The rendered student's PPO fine-tuning throughput (``student_ppo_env_steps_per_s_<variant>``): SB3 PPO with the
    profile's ``finetune`` settings on ``finetune.n_envs`` rendered :class:`rl.observe.StudentEnv` processes, as
    ``train`` runs it (``rl.stage._finetune``: the lookahead head, the profile's ``map_cost``, the frozen encoder
    on one thread per env; constant-velocity prediction, since no intention model is loaded), after one warm-up
    rollout + update, for at least ``seconds`` each; ``student_ppo_update_share_<variant>`` is the update's share of
    that time. ``full`` uses a random-weight encoder of the profile's ``pretrain.encoder`` (written to a temporary
    checkpoint), ``no_bev`` needs none."""
    import tempfile

    from stable_baselines3 import PPO
    from stable_baselines3.common.logger import Logger
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    f = train_cfg.finetune
    out: dict[str, float] = {}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            cfg = replace(train_cfg, data_dir=tmp, head="lookahead")
            probe = CrowdNavEnv(config=replace(sim_cfg, scene=scene, density=density, obs_mode="visual"))
            probe.reset(seed=seed)
            cams = env_cameras(probe)
            probe.close()
            ckpt = _random_encoder(Path(tmp) / "bev", encoder_cfg, cams, seed)
            for variant in variants:
                enc_dir = ckpt if variant != "no_bev" else None

                def make(variant=variant, enc_dir=enc_dir):
                    return StudentEnv(SceneMixEnv(sim_cfg, [(scene, density)], obs_mode="visual"), variant, enc_dir,
                                      head="lookahead", map_cost=cfg.map_cost)

                one = make()
                net = student_net(replace(cfg, variant=variant), one.observer.grid)
                one.close()
                venv = SubprocVecEnv([make] * f.n_envs, start_method="fork") if f.n_envs > 1 else DummyVecEnv([make])
                venv.seed(seed)
                try:
                    model = PPO(policy_class("student", net), venv, policy_kwargs=policy_kwargs("student", variant, net),
                                seed=seed, device="cpu", verbose=0, **ppo_kwargs(f.ppo))
                    model.set_logger(Logger(None, []))
                    model.learn(model.n_steps * f.n_envs)  # warm-up
                    spent = _time_phases(model)
                    t0, done = time.perf_counter(), 0
                    while time.perf_counter() - t0 < seconds:
                        model.learn(model.n_steps * f.n_envs, reset_num_timesteps=False)
                        done += model.n_steps * f.n_envs
                    wall = time.perf_counter() - t0
                finally:
                    venv.close()
                out[f"student_ppo_env_steps_per_s_{variant}"] = done / wall
                out[f"student_ppo_update_share_{variant}"] = spent["train"] / max(wall, 1e-9)
    finally:
        torch.set_num_threads(threads)
    return out


def _random_encoder(ckpt: Path, encoder_cfg: Any, cams, seed: int) -> Path:
    """A random-weight encoder checkpoint of ``encoder_cfg`` for ``cams`` (with its pretext heads), as
    ``make pretrain`` writes one."""
    ckpt.mkdir()
    torch.manual_seed(seed)
    enc = BEVEncoder(encoder_cfg, cams).eval()
    write_encoder_checkpoint(ckpt, enc, PretextHeads(encoder_cfg.bev_channels), {})
    (ckpt / "manifest.json").write_text("{}")
    return ckpt


def measure_dagger_rollout(train_cfg: Any, encoder_cfg: Any, seed: int, episodes: int = 2,
                           episode_s: float = 12.0) -> dict[str, float]:
    """Where a DAgger frame's time goes (``dagger_ms_per_frame`` and ``dagger_ms_per_frame_<phase>``, the phases of
    :data:`rl.dagger.PHASES`): :func:`rl.dagger.dagger_episode` as ``train`` runs it for the default student
    (``full``, the lookahead head, the mirrored world, the profile's ``map_cost``; constant-velocity prediction, no
    intention model being at hand), one thread, ``episodes`` episodes of at most ``episode_s`` on the first DAgger
    scene at its highest density, driven by a lookahead teacher fitted to one expert episode. The reference is the
    encoder in float32 (``train.encoder_precision`` fp32); where bfloat16 is native, the same episodes with the
    encoder in bf16 (``dagger_bf16_ms_per_frame``, ``dagger_bf16_encode_ms_per_frame`` and their speed-ups)."""
    import tempfile

    d = train_cfg.dagger
    sim = replace(train_cfg.sim, max_episode_s=episode_s)
    scene, density = d.scenes[0], max(d.densities)
    threads = torch.get_num_threads()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            probe = CrowdNavEnv(config=replace(sim, scene=scene, density=density, obs_mode="visual"))
            probe.reset(seed=seed)
            ckpt = _random_encoder(Path(tmp) / "bev", encoder_cfg, env_cameras(probe), seed)
            probe.close()
            teacher = Path(tmp) / "teacher"
            data = collect_expert(sim, [(scene, density)], 1, seed, 0.99, 1, progress=False)
            space = SceneMixEnv(sim, [(scene, density)]).observation_space
            net = teacher_net(train_cfg.teacher.net, sim)
            policy = build_policy("teacher", None, space, net)
            fit_lookahead_linear(policy, data, train_cfg.teacher.soft_tau)
            save_policy(teacher, policy, describe("teacher", None, space, net))
            (teacher / "manifest.json").write_text("{}")
            out: dict[str, float] = {}
            for precision in ("fp32", "bf16") if native_bf16("cpu") else ("fp32",):
                it = Path(tmp) / precision
                for sub in ("raw", "features"):
                    (it / sub).mkdir(parents=True)
                rows = [dagger_episode({"sim": sim, "scene": scene, "density": density, "seed": seed + e,
                                        "variant": "full", "encoder": str(ckpt), "teacher": str(teacher),
                                        "student": None, "beta": 1.0, "iteration": 0, "iter_dir": str(it),
                                        "mirror": d.mirror, "head": "lookahead", "device": "cpu",
                                        "map_cost": train_cfg.map_cost, "encoder_precision": precision})
                        for e in range(episodes)]
                frames = sum(r["frames"] for r in rows)
                ms = {p: 1e3 * sum(r["phase_s"][p] for r in rows) / frames for p in PHASES}
                key = "dagger" if precision == "fp32" else f"dagger_{precision}"
                out[f"{key}_ms_per_frame"] = sum(ms.values())
                out[f"{key}_encode_ms_per_frame"] = ms["encode"]
                if precision == "fp32":
                    out.update({f"dagger_ms_per_frame_{p}": v for p, v in ms.items()})
                    out["dagger_frames"] = frames
            if "dagger_bf16_ms_per_frame" in out:
                out["dagger_bf16_speedup"] = out["dagger_ms_per_frame"] / out["dagger_bf16_ms_per_frame"]
                out["dagger_bf16_encode_speedup"] = (out["dagger_encode_ms_per_frame"]
                                                     / out["dagger_bf16_encode_ms_per_frame"])
    finally:
        torch.set_num_threads(threads)
    return out


def _time_phases(model) -> dict[str, float]:
    """Wraps ``model.collect_rollouts`` / ``model.train`` to add their wall time to the returned dict (the
    :class:`pipeline.core.timing.PhaseClock`'s sums, filled as they run)."""
    clock = PhaseClock()
    clock.seconds.update(collect=0.0, train=0.0)  # both read even if a budget ends before either ran
    model.collect_rollouts = clock.wrap("collect", model.collect_rollouts)
    model.train = clock.wrap("train", model.train)
    return clock.seconds


def _policy_ms_per_step(model, venv, n_envs: int, calls: int = 50) -> float:
    obs = {k: torch.as_tensor(v) for k, v in venv.reset().items()}
    with torch.no_grad():
        model.policy(obs)
        t = time.perf_counter()
        for _ in range(calls):
            model.policy(obs)
    return 1e3 * (time.perf_counter() - t) / (calls * n_envs)


def _env_step_ms(sim_cfg: Any, scene: str, density: float, seed: int, seconds: float) -> float:
    """One privileged env in process, random discrete actions (resets included, as in PPO's rollouts)."""

    venv = make_vec_env(sim_cfg, [(scene, density)], 1, seed, False)
    rng = np.random.default_rng(seed)
    venv.reset()
    t, n = time.perf_counter(), 0
    while time.perf_counter() - t < seconds or n < 100:
        venv.step(rng.integers(0, venv.action_space.n, size=1))
        n += 1
    ms = 1e3 * (time.perf_counter() - t) / n
    venv.close()
    return ms


def synthetic_student_frames(space, n: int, n_actions: int, seed: int) -> dict[str, np.ndarray]:
    """``n`` frames shaped like a student's DAgger features (speed does not depend on their content): positions
    and tracks ~N(0, 2 m), scans 0.3–10 m, pose masks 0/1, a mirrored ``s_bev``, expert actions and costs."""
    rng = np.random.default_rng(seed)
    data: dict[str, np.ndarray] = {}
    for k, box in space.spaces.items():
        shape = (n, *box.shape)
        if k == "scan":
            data[k] = rng.uniform(0.3, 10.0, shape).astype(np.float32)
        elif k.endswith("_mask"):
            data[k] = (rng.random(shape) < 0.7).astype(np.float32)
        else:
            data[k] = rng.normal(0.0, 2.0, shape).astype(np.float32)
    if "bev" in data:
        data["bev_mirror"] = data["bev"][..., ::-1].copy()  # the lateral axis reflected
    data["action"] = rng.integers(0, n_actions, n)
    data["costs"] = rng.uniform(0.0, 5.0, (n, n_actions)).astype(np.float32)
    return data


def measure_student_update(cameras, train_cfg: Any, device: str, frames: int = 2048, epochs: int = 2,
                           seed: int = 0, encoder_cfg: EncoderConfig | None = None) -> float:
    """Milliseconds per 1,000 frames and epoch of the default student's DAgger update on ``device`` (see the module
    docstring): :func:`rl.teacher.behaviour_clone` with the profile's ``dagger`` settings, timed over ``epochs``
    epochs after one warm-up epoch (each call fills the lookahead feature cache once, as every iteration does)."""
    cfg, d = train_cfg, train_cfg.dagger
    dev = resolve_device(device, "device")
    torch.manual_seed(seed)
    enc = BEVEncoder(encoder_cfg or EncoderConfig(), cameras).eval().requires_grad_(False)
    observer = StudentObserver("full", cameras, enc, cfg.sim.detector.max_people, mirror=d.mirror, head="lookahead",
                               perception=perception_params(cfg.sim),
                               forecaster=IntentionForecaster(ForecasterConfig()).eval())
    net = {**cfg.net, "head": "lookahead", "robot": asdict(cfg.sim.robot), "dt_s": cfg.sim.dt_s,
           "scan_range_m": cfg.sim.scan_range_m, "scorer_bound": cfg.scorer_bound}
    policy = build_policy("student", "full", observer.observation_space, net).to(dev)
    n_rot = cfg.sim.robot.n_rotations
    data = synthetic_student_frames(observer.observation_space, frames, policy.action_space.n, seed)

    def clone(n_epochs: int) -> None:
        behaviour_clone(policy, data, n_epochs, d.bc_batch, d.bc_lr, seed, progress=False, soft_tau=d.soft_tau,
                        mirror=d.mirror, n_rot=n_rot)
        if dev.type == "cuda":
            torch.cuda.synchronize()

    clone(1)
    t = time.perf_counter()
    clone(epochs)
    return 1e6 * (time.perf_counter() - t) / (frames * epochs)


def measure_student_encoder(cameras, device: str, streams: int, steps: int = 20, seed: int = 0,
                            encoder_cfg: EncoderConfig | None = None) -> float:
    """Milliseconds per :meth:`pretrain.model.BEVStream.step` of the encoder (default: the default architecture) on
    ``streams`` streams at once (random frames of the cameras' size; median after two warm-up steps)."""
    dev = resolve_device(device, "device")
    torch.manual_seed(seed)
    enc = BEVEncoder(encoder_cfg or EncoderConfig(), cameras).eval().requires_grad_(False).to(dev)
    stream = BEVStream(enc)
    c0, n = cameras[0], len(cameras)
    g = torch.Generator().manual_seed(seed)
    rgb = torch.randint(0, 256, (streams, n, 3, c0.height, c0.width), dtype=torch.uint8, generator=g)
    depth = torch.rand(streams, n, c0.height, c0.width, generator=g) * 7.7 + 0.3
    pose = torch.zeros(streams, 3, dtype=torch.float64)
    times = []
    for i in range(steps + 2):
        t = time.perf_counter()
        # the frames come from the simulator in host memory: their copy to the device is part of the step
        stream.step(rgb.to(dev), depth.to(dev), (pose + 0.01 * i).to(dev))
        if dev.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t)
    return 1e3 * float(np.median(times[2:]))


def measure_student_devices(cameras, train_cfg: Any, devices: list[str], frames: int = 2048,
                            fuse_pool: int = 0, encoder_cfg: EncoderConfig | None = None,
                            encoder_steps: int = 20) -> dict[str, float]:
    """The student's update and encoder figures for each device, with the CUDA / CPU ratios (module docstring), with
    ``encoder_cfg`` (default: the built-in :class:`EncoderConfig`); ``fuse_pool`` > 0 adds the encoder with that
    ``encoder.fuse_pool``; each encoder figure is the median of ``encoder_steps`` steps."""
    encoder_cfg = encoder_cfg or EncoderConfig()
    pooled = replace(encoder_cfg, fuse_pool=fuse_pool) if fuse_pool else None
    if pooled is not None:
        pooled.validate()
    out: dict[str, float] = {}
    for d in devices:
        key = d.split(":")[0]
        out[f"student_clone_ms_per_kframe_{key}"] = round(measure_student_update(cameras, train_cfg, d, frames,
                                                                                 encoder_cfg=encoder_cfg), 1)
        for b in (2, 16):
            out[f"student_encoder_ms_{key}_b{b}"] = round(measure_student_encoder(
                cameras, d, b, encoder_steps, encoder_cfg=encoder_cfg), 2)
            if pooled is not None:
                out[f"student_encoder_ms_{key}_b{b}_fuse_pool{fuse_pool}"] = round(
                    measure_student_encoder(cameras, d, b, encoder_steps, encoder_cfg=pooled), 2)
    if "student_clone_ms_per_kframe_cpu" in out and "student_clone_ms_per_kframe_cuda" in out:
        out["student_clone_speedup_cuda_vs_cpu"] = round(out["student_clone_ms_per_kframe_cpu"]
                                                         / out["student_clone_ms_per_kframe_cuda"], 2)
        for b in (2, 16):
            out[f"student_encoder_b{b}_speedup_cuda_vs_cpu"] = round(out[f"student_encoder_ms_cpu_b{b}"]
                                                                     / out[f"student_encoder_ms_cuda_b{b}"], 2)
    return out


@reports_errors
def main(argv: list[str] | None = None) -> int:
    """``python -m rl.bench --dataset ROOT [--devices cpu,cuda] [--profile default]``: the student's update and
    frozen-encoder figures per device as JSON, with the profile's ``train`` settings and its ``pretrain.encoder``
    (reads only ``ROOT/meta/info.json``: the cameras)."""
    import argparse
    import json
    import os

    ap = argparse.ArgumentParser(prog="python -m rl.bench", description=main.__doc__)
    ap.add_argument("--dataset", type=Path, required=True, help="a dataset root (only meta/info.json is read)")
    ap.add_argument("--devices", default="cpu,cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--profile", default="default")
    ap.add_argument("--frames", type=int, default=2048)
    ap.add_argument("--fuse-pool", type=int, default=0, help="also time the encoder with this encoder.fuse_pool")
    args = ap.parse_args(argv)
    torch.set_num_threads(os.cpu_count() or 1)
    encoder = load_config(PretrainConfig, "pretrain", args.profile).encoder
    out = measure_student_devices(cameras_from_dataset(args.dataset), load_config(TrainConfig, "train", args.profile),
                                  args.devices.split(","), args.frames, args.fuse_pool, encoder)
    out = {"profile": args.profile, "bev_grid_cells": int(np.prod(encoder.grid.shape)), **out}
    print(json.dumps(out | machine_facts()))
    return 0


def measure_inference(sim_cfg: Any, scene: str, density: float, seed: int, encoder_cfg: Any, seconds: float) -> dict:

    import torch.nn.functional as F

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        env = CrowdNavEnv(config=replace(sim_cfg, scene=scene, density=density, obs_mode="visual"))
        obs, _ = env.reset(seed=seed)
        cams = env_cameras(env)
        torch.manual_seed(seed)
        enc = BEVEncoder(encoder_cfg, cams).eval().requires_grad_(False)
        observer = StudentObserver("full", cams, enc, env.cfg.detector.max_people)
        policy = build_policy("student", "full", observer.observation_space, {})
        policy.set_training_mode(False)
        observer(obs)

        def stream() -> None:
            act(policy, observer(obs))

        names = [c.name for c in cams]
        win = enc.frames
        rgb, depth, poses = (x.unsqueeze(1).expand(x.shape[0], win, *x.shape[1:]).contiguous()
                             for x in _stream_inputs(obs, names))  # the newest frame repeated over the window

        @torch.no_grad()
        def recompute() -> None:
            o = {"bev": F.avg_pool2d(enc(rgb, depth, poses), BEV_POOL)[0].numpy(), "state": obs["state"],
                 "poses": obs["poses"], "pose_mask": obs["pose_mask"].astype(np.float32)}
            act(policy, o)

        # the default student: the same, plus perception (tracks, depth scan) and the lookahead head
        look_obs = observer_for_env(env, "full", enc, head="lookahead")
        look = build_policy("student", "full", look_obs.observation_space,
                            {"head": "lookahead", "robot": asdict(env.cfg.robot), "dt_s": env.cfg.dt_s,
                             "scan_range_m": env.cfg.scan_range_m})
        look.set_training_mode(False)
        look_obs(obs)

        def stream_lookahead() -> None:
            act(look, look_obs(obs))

        # the same default student with the encoder's int8 version (pretrain.quantize), calibrated on this scene's
        # frames of a short drive; the reference is the float student above, in the same run
        q = QuantizedBEVEncoder(enc)
        cal = BEVStream(q)
        drive = CrowdNavEnv(config=replace(sim_cfg, scene=scene, density=density, obs_mode="visual"))
        o, _ = drive.reset(seed=seed)
        with torch.no_grad():
            for k in range(12):  # forward, turning left then right
                cal.step(*_stream_inputs(o, names))
                o = drive.step(np.array([0.6, 0.4 if k < 6 else -0.4], np.float32))[0]
        drive.close()
        q.freeze()
        look_q = observer_for_env(env, "full", q, head="lookahead")
        look_q(obs)

        def stream_lookahead_int8() -> None:
            act(look, look_q(obs))

        # and with the encoder's bfloat16 version (pretrain.quantize.BF16BEVEncoder), where bf16 is native
        look_b = observer_for_env(env, "full", BF16BEVEncoder(enc), head="lookahead") if native_bf16("cpu") else None
        if look_b is not None:
            look_b(obs)

        ms = 1000.0 * time_call(stream, seconds)
        ref = 1000.0 * time_call(recompute, seconds)
        ms_look = 1000.0 * time_call(stream_lookahead, seconds)
        ms_look_q = 1000.0 * time_call(stream_lookahead_int8, seconds)
        enc_ms = 1000.0 * time_call(lambda: look_obs.stream.step(*_stream_inputs(obs, names)), seconds / 2)
        enc_q_ms = 1000.0 * time_call(lambda: look_q.stream.step(*_stream_inputs(obs, names)), seconds / 2)
        bf16 = {}
        if look_b is not None:
            ms_look_b = 1000.0 * time_call(lambda: act(look, look_b(obs)), seconds)
            enc_b_ms = 1000.0 * time_call(lambda: look_b.stream.step(*_stream_inputs(obs, names)), seconds / 2)
            bf16 = {"policy_inference_lookahead_bf16_ms": ms_look_b,
                    "policy_inference_lookahead_bf16_speedup": ms_look / ms_look_b, "bev_stream_step_bf16_ms": enc_b_ms,
                    "bev_stream_step_bf16_speedup": enc_ms / enc_b_ms}
    finally:
        torch.set_num_threads(threads)
    return {**bf16, "policy_inference_ms": ms, "policy_inference_hz": 1000.0 / ms, "policy_inference_recompute_ms": ref,
            "policy_inference_speedup_vs_recompute": ref / ms, "policy_inference_lookahead_ms": ms_look,
            "policy_inference_lookahead_hz": 1000.0 / ms_look, "policy_inference_lookahead_int8_ms": ms_look_q,
            "policy_inference_lookahead_int8_speedup": ms_look / ms_look_q, "bev_stream_step_ms": enc_ms,
            "bev_stream_step_int8_ms": enc_q_ms, "bev_stream_step_int8_speedup": enc_ms / enc_q_ms}


def _stream_inputs(obs: dict[str, np.ndarray], names: list[str]) -> tuple[torch.Tensor, ...]:
    """One rendered observation as :meth:`pretrain.model.BEVStream.step` inputs (one stream)."""
    rgb = torch.from_numpy(np.stack([obs[f"rgb_{n}"] for n in names])).permute(0, 3, 1, 2).unsqueeze(0)
    depth = torch.from_numpy(np.stack([obs[f"depth_{n}"] for n in names])).unsqueeze(0)
    return rgb, depth, torch.as_tensor(np.asarray(obs["odom"], np.float64)).view(1, 3)


if __name__ == "__main__":
    raise SystemExit(main())
