"""DAgger distillation of the privileged teacher into the visual student, through the recorder.

Iteration ``k`` (β_k = ``beta0 · beta_decay^k``; β_0 = 1 means the teacher drives the first iteration):

1. **Roll out** ``episodes_per_iter`` rendered episodes over the training scenes and densities (process pool). At
   every step the teacher labels the observation from privileged state (:func:`sim.wrappers.privileged_observation`)
   and the robot executes the teacher's action with probability β_k, else the current student's.
2. **Record** each episode through the recorder: one MCAP log (``Frame.label`` = the teacher's command) and, after
   the iteration, one LeRobot dataset of the iteration (``action.teacher`` feature) — the data-centric loop: every
   iteration's data is a dataset anyone can load. Beside it, ``features/<episode>.npz`` caches what the student
   saw (its observation dict, ``s_bev`` as float16) with the label index, so cloning does not re-run the encoder.
3. **Clone**: behaviour cloning (cross-entropy on the teacher's action index, or on its action distribution) on the
   aggregate of all iterations, each sample mirrored left-right with probability 1/2 (``dagger.mirror``; ``bev``
   variants cache the mirrored world's ``s_bev`` as ``bev_mirror`` for this).

Everything an iteration writes is in ``dagger/iter_<k>/``; a finished iteration has ``done.json``. An episode is
finished when its ``features/<episode>.npz`` exists (written last, atomically); an unfinished one starts over and
first removes what a killed attempt left (its MCAP or ``.partial``). So a killed run resumes at the first unfinished
episode of the first unfinished iteration, and a rollout retried on another Ray worker rewrites the same files.

The rollouts run where ``train.executor`` says (:mod:`pipeline.core.executor`: the local process pool, or Ray tasks
writing into the shared data directory), with the same seeds and files either way. The students' frozen encoder
runs on a job's ``device`` (``train.device``; the teacher and the student act on the CPU); local workers that encode
on CUDA are spawned, not forked (:func:`pipeline.core.device.start_method`); Ray tasks get no GPU, so rollouts on
Ray encode on the CPU.
"""

from __future__ import annotations

import itertools
import json
import os
import tempfile
import time
import zlib
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.core.artifacts import atomic_write_json
from pipeline.core.device import start_method
from pipeline.core.errors import InputMissingError
from pipeline.core.executor import Bundle, Executor, in_scratch, map_jobs, receive_files
from pipeline.core.timing import PhaseClock
from recorder.export import export_run
from recorder.mcap.layout import partial_path_of
from recorder.mcap.writer import EpisodeWriter
from recorder.schema import episode_meta_from_env, frame_from_env
from rl.driver import (
    cached_policy,
    cached_student_encoder,
    cached_student_forecaster,
    cached_student_heads,
    mlp_shield,
    observer_head,
    shielded_logits,
)
from rl.lookahead import ObstacleShield
from rl.observe import observer_for_env
from rl.policy import act, action_logits, checkpoint_bundle
from sim.env import CrowdNavEnv, SimConfig
from sim.episode import episode_steps
from sim.wrappers import PrivilegedObservation


def episode_name(scene: str, density: float, seed: int) -> str:
    return f"{Path(scene).stem}_d{density:g}_s{seed}"


class _DaggerDriver:
    """Executes the teacher's label of the current frame (set by :func:`dagger_episode` before each act) with
    probability β, else the student's action on the same frame — for an MLP head with an obstacle shield
    (``train.mlp_shield_s``) the argmax of its logits less the shield's penalty, as it acts once trained."""

    def __init__(self, student, beta: float, rng: np.random.Generator, clock: PhaseClock,
                 shield: ObstacleShield | None = None) -> None:
        self.student, self.beta, self.rng, self.clock, self.shield = student, beta, rng, clock, shield
        self.label, self.s_obs, self.student_steps = 0, None, 0

    def reset(self, obs, info) -> None:
        self.student_steps = 0

    def act(self, obs, info):
        if self.student is not None and self.rng.random() >= self.beta:
            self.student_steps += 1
            with self.clock("student"):
                if self.shield is None:
                    return act(self.student, self.s_obs)
                return int(np.argmax(shielded_logits(self.student, self.s_obs, self.shield)))
        return self.label


# an episode's phases, each exclusive of the others (:func:`episode_phases`): the simulator's step (robot, crowd,
# bodies, privileged channels), its two cameras' rendering, the pose detector, the student's action (steps it
# drives), its observation (the frozen encoder with its mirrored stream and map heads; tracks, forecasts, scan), the
# teacher's label, the MCAP frame, the features file, and what is left (the loop itself, the env's construction)
PHASES = ("sim", "render", "detect", "student", "encode", "perceive", "teacher", "record", "save", "other")


def episode_phases(seconds: dict[str, float], total_s: float) -> dict[str, float]:
    """A :class:`PhaseClock`'s sums of one DAgger episode (``env`` holding ``render``, ``detect`` and ``student``)
    → the exclusive seconds of every name in :data:`PHASES` (rounded to ms), ``other`` = ``total_s`` less the rest."""
    get = seconds.get
    out = {"sim": get("env", 0.0) - get("render", 0.0) - get("detect", 0.0) - get("student", 0.0)}
    out.update({k: get(k, 0.0) for k in PHASES[1:-1]})
    out["other"] = total_s - sum(out.values())
    return {k: round(max(out[k], 0.0), 3) for k in PHASES}


def _timed(steps, clock: PhaseClock, name: str):
    """The items of iterator ``steps``, the wall time of producing each added to ``clock``'s phase ``name``."""
    while True:
        with clock(name):
            item = next(steps, None)
        if item is None:
            return
        yield item


def dagger_episode(args: dict[str, Any]) -> dict[str, Any]:
    """One DAgger episode (see the module docstring); writes ``raw/<name>.mcap`` and ``features/<name>.npz``.

    Every frame (the last included) is seen by the student's observer, labelled by the teacher from the privileged
    channels (:class:`sim.wrappers.PrivilegedObservation`) and logged; the episode loop then executes the label or
    the student's action (:class:`_DaggerDriver`)."""
    torch.set_num_threads(1)
    sim_cfg: SimConfig = args["sim"]
    name = episode_name(args["scene"], args["density"], args["seed"])
    raw, feat = Path(args["iter_dir"]) / "raw", Path(args["iter_dir"]) / "features"
    t0 = time.perf_counter()
    for stale in (raw / f"{name}.mcap", partial_path_of(raw / f"{name}.mcap"), feat / f"{name}.tmp.npz"):
        stale.unlink(missing_ok=True)  # a killed attempt's files (the features file, written last, is not there)
    env = CrowdNavEnv(config=replace(sim_cfg, scene=args["scene"], density=args["density"], obs_mode="visual",
                                     info_level="full", action_type="discrete"))
    clock = PhaseClock()  # where the episode's time goes: the row's "phase_s"
    env.render_cameras = clock.wrap("render", env.render_cameras)
    env.detector.detect = clock.wrap("detect", env.detector.detect)
    encoder = cached_student_encoder(args["variant"], args["encoder"], args.get("device", "cpu"),
                                     args.get("encoder_precision", "fp32"))
    teacher = cached_policy(args["teacher"])
    head = args.get("head", "mlp")
    shield = mlp_shield(sim_cfg, float(args.get("mlp_shield_s", 0.0))) if head == "mlp" else None
    driver = _DaggerDriver(cached_policy(args["student"]), args["beta"], np.random.default_rng(args["seed"] + 7919),
                           clock, shield)
    forecaster = cached_student_forecaster(args["variant"], head, args.get("intention"))
    map_cost = bool(args.get("map_cost", False)) and head == "lookahead"  # the MLP head reads no map (nor its shield)
    observer = observer_for_env(env, args["variant"], encoder, observer_head(head, shield is not None),
                                mirror=args.get("mirror", False),
                                forecaster=forecaster, map_cost=map_cost,
                                map_heads=cached_student_heads(args["variant"], head, map_cost, args["encoder"],
                                                               encoder))
    observer.clock = clock
    steps = _timed(episode_steps(PrivilegedObservation(env), driver, args["seed"]), clock, "env")
    first = next(steps)
    meta = episode_meta_from_env(env, args["seed"], f"dagger:{args['variant']}:iter{args['iteration']}:"
                                                    f"beta{args['beta']:g}")
    rows: dict[str, list] = {}
    labels: list[int] = []
    teacher_logits: list[np.ndarray] = []
    info = first.info
    writer = EpisodeWriter(raw / f"{name}.mcap", meta, env.layout.occupancy)
    writer.finish = clock.wrap("record", writer.finish)  # the MCAP's summary and index, written as it closes
    with writer:
        for tr in itertools.chain([first], steps):
            info = tr.info
            s_obs = observer(tr.obs)
            with clock("teacher"):
                logits = action_logits(teacher, tr.obs)
            label = int(np.argmax(logits))
            cmd = (0.0, 0.0) if tr.step == 0 else tuple(env.robot_v)
            with clock("record"):
                writer.add(frame_from_env(env, tr.obs, tr.info, tr.step, command=cmd, reward=tr.reward or 0.0,
                                          done=tr.done, label=env.decode_action(label)))
            for k, v in s_obs.items():
                rows.setdefault(k, []).append(v.astype(np.float16) if k.startswith("bev") else v)
            labels.append(label)
            teacher_logits.append(logits.astype(np.float32))
            driver.label, driver.s_obs = label, s_obs
    env.close()
    outcome = info.get("outcome") or "timeout"
    with clock("save"):
        arrays = {k: np.stack(v) for k, v in rows.items()}
        arrays["action"] = np.asarray(labels, np.int64)
        arrays["teacher_logits"] = np.stack(teacher_logits)
        tmp = feat / f"{name}.tmp.npz"
        np.savez(tmp, **arrays)
        tmp.replace(feat / f"{name}.npz")
    seconds = time.perf_counter() - t0
    return {"episode": name, "scene": Path(args["scene"]).stem, "density": args["density"], "seed": args["seed"],
            "frames": len(labels), "student_steps": driver.student_steps, "outcome": outcome,
            "seconds": round(seconds, 2), "phase_s": episode_phases(clock.seconds, seconds)}


def run_iteration(iter_dir: Path, jobs: list[dict[str, Any]], workers: int, progress: bool = True,
                  executor: Executor | None = None) -> list[dict]:
    """Runs the iteration's episodes that have no ``features/<name>.npz`` yet (``executor``: the local process pool
    when None or local — spawned workers when the jobs encode on CUDA — or Ray tasks); returns all rows."""
    iter_dir = Path(iter_dir)
    for sub in ("raw", "features"):
        (iter_dir / sub).mkdir(parents=True, exist_ok=True)
    rows_path = iter_dir / "episodes.jsonl"
    done_rows = {}
    if rows_path.exists():
        for line in rows_path.read_text().splitlines():
            r = json.loads(line)
            if (iter_dir / "features" / f"{r['episode']}.npz").exists():
                done_rows[r["episode"]] = r
    todo = [j for j in jobs if episode_name(j["scene"], j["density"], j["seed"]) not in done_rows]
    threads = torch.get_num_threads()  # run in this process (workers <= 1), an episode sets one thread
    on_ray = executor is not None and executor.kind == "ray"
    if on_ray:  # Ray tasks are given CPUs only (module docstring)
        todo = [{**j, "device": "cpu"} for j in todo]
    transfer = on_ray and executor.transfers
    with open(rows_path, "a") as f:
        def finished(_: int, result: Any) -> None:
            r = result
            if transfer:  # (row, files): the MCAP, then the features file (last: it marks the episode done)
                r, files = result
                receive_files(iter_dir, files, last="features/")
            done_rows[r["episode"]] = r
            f.write(json.dumps(r) + "\n")
            f.flush()

        desc = f"dagger {iter_dir.name}" + (f" ({len(jobs) - len(todo)} done before)" if len(todo) < len(jobs) else "")
        if transfer and todo:
            map_jobs(dagger_episode_transfer, todo, workers, desc, progress, executor=executor, on_result=finished,
                     keep_results=False, shared=rollout_bundle(todo[0]))
        else:
            start = start_method(todo[0].get("device", "cpu")) if todo else "fork"
            map_jobs(dagger_episode, todo, workers, desc, progress, executor=executor, on_result=finished,
                     start=start)
    torch.set_num_threads(threads)  # the stage's cloning that follows keeps its cores
    return [done_rows[episode_name(j["scene"], j["density"], j["seed"])] for j in jobs]


ROLLOUT_DIRS = ("teacher", "student", "encoder", "intention")  # the checkpoint folders a rollout job reads


def rollout_bundle(job: dict[str, Any]) -> Bundle:
    """What an iteration's rollouts read (every job of an iteration names the same folders), as one bundle for
    Ray nodes without the data directory: the teacher and the student of the previous iteration (policy
    checkpoints) and the encoder and intention model (:func:`rl.policy.checkpoint_bundle`)."""
    policies = [Path(job[k]) for k in ("teacher", "student") if job.get(k)]
    return checkpoint_bundle(policies, [Path(job[k]) for k in ("encoder", "intention") if job.get(k)])


def dagger_episode_transfer(job: dict[str, Any], shared: Bundle) -> tuple[dict[str, Any], list[tuple[str, bytes,
                                                                                                        str]]]:
    """:func:`dagger_episode` on a node without the data directory: the checkpoints from the unpacked bundle
    ``shared``, the episode written into a scratch iteration folder and returned as ``(row, [(path relative to
    the iteration folder, bytes, sha256)])``; the scratch folder is removed. A retried task returns the same
    files again; the driver writes them once, when its result arrives."""
    root = shared.unpack()
    local = {k: str(shared.local(root, job[k])) for k in ROLLOUT_DIRS if job.get(k)}

    def rollout(scratch: Path) -> dict[str, Any]:
        for sub in ("raw", "features"):
            (scratch / sub).mkdir()
        return dagger_episode({**job, **local, "iter_dir": str(scratch)})

    return in_scratch(rollout, "icrowdnav-dagger-")


def feature_files(iter_dirs: list[Path]) -> list[Path]:
    """Every finished episode's ``features/<episode>.npz`` of these iterations, in order."""
    return [f for d in iter_dirs for f in sorted((Path(d) / "features").glob("*.npz"))
            if not f.name.endswith(".tmp.npz")]


def held_out_episode(name: str, fraction: float) -> bool:
    """Whether the episode ``name`` (its features file's stem) is in the cloning's held-out share ``fraction``: a
    hash of the name, so an episode stays on its side of the split as later iterations join the pool, and the share
    spreads over scenes and densities (the rollout index would not: jobs cycle through the scene-density pairs)."""
    return zlib.crc32(name.encode()) % 10_000 < fraction * 10_000


def held_out_frames(iter_dirs: list[Path], fraction: float) -> np.ndarray:
    """Per frame of :func:`load_features` (same order), whether it belongs to a held-out episode
    (:func:`held_out_episode`). At least one episode is held out and at least one is not, when there are two."""
    files = feature_files(iter_dirs)
    lengths = []
    for f in files:
        try:
            with np.load(f) as z:
                lengths.append(len(z["action"]))
        except (OSError, ValueError, KeyError, EOFError) as e:
            raise InputMissingError(f"{f}: unreadable cached features ({type(e).__name__}: {e})") from None
    out = np.array([held_out_episode(f.stem, fraction) for f in files], bool)
    if len(files) > 1 and not out.any():  # the smallest hash: a tiny pool still gets a held-out episode
        out[int(np.argmin([zlib.crc32(f.stem.encode()) for f in files]))] = True
    if len(files) > 1 and out.all():
        out[int(np.argmax([zlib.crc32(f.stem.encode()) for f in files]))] = False
    return np.repeat(out, lengths)


def load_features(iter_dirs: list[Path], keys: tuple[str, ...] | None = None, memory_gb: float | None = None,
                  scratch: Path | None = None) -> dict[str, np.ndarray]:
    """The cached student observations + labels of every episode of these iterations, concatenated
    (:func:`pool_frames`)."""
    files = feature_files(iter_dirs)
    if not files:
        raise InputMissingError(f"no DAgger features in {[str(d) for d in iter_dirs]}")
    return pool_frames(files, keys, memory_gb, scratch)


def pool_frames(files: list[Path], keys: tuple[str, ...] | None = None, memory_gb: float | None = None,
                scratch: Path | None = None) -> dict[str, np.ndarray]:
    """The ``keys`` (default: every key all ``files`` hold) of cached-feature episodes concatenated in order into
    arrays allocated once (no list of parts and second copy, as ``np.concatenate`` would need).

    A pool larger than ``memory_gb`` GiB (None: no limit) is written to memory-mapped files instead of anonymous
    memory: the page cache then holds what fits and the kernel writes the rest back to disk, so a DAgger set of
    100 k+ frames (≈ 190 KB each with the mirrored ``s_bev``) clones on a 24 GiB machine. The files are created in
    ``scratch`` (default: the system's temporary directory) and unlinked at once — the mapping keeps them readable
    and their space is freed when the arrays are, so a killed process leaves nothing behind (POSIX semantics). The
    arrays are the same either way (tested).
    """
    lengths, present = [], None
    for f in files:
        try:
            with np.load(f) as z:
                lengths.append(len(z["action"]))
                names = set(z.files)
        except (OSError, ValueError, KeyError, EOFError) as e:
            raise InputMissingError(f"{f}: unreadable cached features ({type(e).__name__}: {e})") from None
        if keys is not None and set(keys) - names:
            raise InputMissingError(f"{f}: cached features: expected keys {sorted(set(keys) - names)}, found "
                                    f"{sorted(names)}")
        present = names if present is None else present & names
    if not files:
        raise InputMissingError("no cached-feature episodes to pool")
    keys = tuple(keys) if keys is not None else tuple(sorted(present))
    total = int(sum(lengths))
    with np.load(files[0]) as z:  # one episode gives every key's dtype and per-frame shape
        spec = {k: (z[k].dtype, z[k].shape[1:]) for k in keys}
    nbytes = sum(total * dt.itemsize * int(np.prod(shape)) for dt, shape in spec.values())
    spill = memory_gb is not None and nbytes > memory_gb * 2**30
    out: dict[str, np.ndarray] = {}
    for k, (dt, shape) in spec.items():
        if spill:
            fd, path = tempfile.mkstemp(prefix="icrowdnav-pool-", suffix=".npy", dir=scratch)
            os.close(fd)
            out[k] = np.lib.format.open_memmap(path, mode="w+", dtype=dt, shape=(total, *shape))
            os.unlink(path)  # the mapping stays valid; the space goes back when the array does
        else:
            out[k] = np.empty((total, *shape), dt)
    at = 0
    for f, n in zip(files, lengths, strict=True):
        try:
            with np.load(f) as z:
                parts = [(k, z[k]) for k in keys]
        except (OSError, ValueError, KeyError, EOFError) as e:
            raise InputMissingError(f"{f}: unreadable cached features ({type(e).__name__}: {e})") from None
        for k, a in parts:
            if a.shape[1:] != spec[k][1] or len(a) != n:
                raise InputMissingError(f"{f}: cached features: {k}: expected {n} frames of shape {spec[k][1]} "
                                        f"(as in {files[0].name}), got {a.shape}")
            out[k][at:at + n] = a
        at += n
    return out


def bev_stats(data: dict[str, np.ndarray], max_frames: int = 2000) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-channel mean and std of the cached ``s_bev`` (a strided subsample of at most ``max_frames``)."""
    bev = data["bev"]
    sub = bev[:: max(1, len(bev) // max_frames)].astype(np.float32)
    return torch.from_numpy(sub.mean((0, 2, 3))), torch.from_numpy(sub.std((0, 2, 3)))


def export_iteration(iter_dir: Path, repo_id: str, progress: bool = True, shards: int = 1,
                     executor: Executor | None = None, **kwargs: Any) -> dict[str, Any]:
    """The iteration's MCAP logs → ``iter_dir/dataset`` (a validated LeRobot dataset with ``action.teacher``), in
    ``shards`` parallel blocks on ``executor`` merged by lerobot as ``make record``'s export does (fewer for a small
    iteration: :data:`recorder.export.MIN_SHARD_FRAMES`; ``kwargs``: :func:`recorder.export.export_dataset`'s)."""
    return export_run(Path(iter_dir) / "raw", Path(iter_dir) / "dataset", repo_id, overwrite=True,
                      progress=progress, shards=shards, executor=executor, **kwargs)


ITERATION_PARTS = ("rollout", "export", "intention_tune", "pool", "clone")  # rl.stage's parts of an iteration


def iteration_timing(seconds: dict[str, float], rows: list[dict[str, Any]], frames: int,
                     resumed: bool) -> dict[str, Any]:
    """Where a DAgger iteration's time went (its ``done.json`` ``"timing"``): the wall seconds of its parts
    (``seconds``: :data:`ITERATION_PARTS` from the stage's :class:`PhaseClock`), the loop's frames per second over
    them and the rollouts' alone (both left out when ``resumed``: part of the rollouts ran before), and the
    episodes' own phases (:data:`PHASES`) summed over the workers — worker-seconds and milliseconds per frame."""
    total = sum(seconds.values())
    timed = [r for r in rows if "phase_s" in r]  # episodes rolled out by code that timed them
    timed_frames = sum(r["frames"] for r in timed)
    worker = {p: sum(r["phase_s"][p] for r in timed) for p in PHASES}
    out: dict[str, Any] = {"seconds": {p: round(seconds.get(p, 0.0), 1) for p in ITERATION_PARTS},
                           "total_s": round(total, 1), "frames": frames, "resumed": resumed,
                           "worker_s": {p: round(v, 1) for p, v in worker.items()},
                           "worker_ms_per_frame": {p: round(1e3 * v / max(timed_frames, 1), 2)
                                                   for p, v in worker.items()},
                           "timed_frames": timed_frames}
    if not resumed:
        out["loop_frames_per_s"] = round(frames / max(total, 1e-9), 2)
        out["rollout_frames_per_s"] = round(frames / max(seconds.get("rollout", 0.0), 1e-9), 2)
    return out


def throughput_table(iterations: list[dict[str, Any]], final: dict[str, Any] | None = None) -> str:
    """A Markdown account of a student's DAgger loop from its iterations' ``done.json`` (those with ``"timing"``):
    per iteration the frames, each part's wall and the frames per second; then the rollout episodes' phases in
    worker-milliseconds per frame over every timed iteration, with each phase's share. ``final``: the final
    cloning's ``done.json`` (``dagger.final_clone``; ``dagger/final``), its pool loading and cloning after the loop."""
    its = [i for i in iterations if "timing" in i]
    if not its:
        return "no timed DAgger iteration"
    lines = ["| iteration | frames (pool) | " + " | ".join(f"{p} s" for p in ITERATION_PARTS)
             + " | total s | loop frames/s | rollout frames/s |", "|---" * (len(ITERATION_PARTS) + 5) + "|"]
    for i in its:
        t = i["timing"]
        rates = ("— | — (resumed)" if t["resumed"]
                 else f"{t['loop_frames_per_s']:.1f} | {t['rollout_frames_per_s']:.1f}")
        lines.append(f"| {i['iteration']} | {i['frames']:,} ({i['aggregate_frames']:,}) | "
                     + " | ".join(f"{t['seconds'][p]:.0f}" for p in ITERATION_PARTS)
                     + f" | {t['total_s']:.0f} | {rates} |")
    fresh = [i["timing"] for i in its if not i["timing"]["resumed"]]
    if fresh:
        frames, total = sum(t["frames"] for t in fresh), sum(t["total_s"] for t in fresh)
        rollout = sum(t["seconds"]["rollout"] for t in fresh)
        lines.append(f"\n{frames:,} frames in {total / 60:.1f} min: the loop {frames / total:.1f} frames/s, its "
                     f"rollouts {frames / rollout:.1f} frames/s ({rollout / total:.0%} of the loop's wall)")
    timed_frames = sum(i["timing"]["timed_frames"] for i in its)
    if timed_frames:
        worker = {p: sum(i["timing"]["worker_s"][p] for i in its) for p in PHASES}
        whole = sum(worker.values())
        lines += ["", f"Rollout episodes, {timed_frames:,} frames: worker-milliseconds per frame by phase",
                  "", "| " + " | ".join(PHASES) + " | all |", "|---" * (len(PHASES) + 1) + "|",
                  "| " + " | ".join(f"{1e3 * worker[p] / timed_frames:.1f} ({worker[p] / whole:.0%})" for p in PHASES)
                  + f" | {1e3 * whole / timed_frames:.1f} |"]
    if final:  # rl.stage._final_clone's done.json
        sec, samples = final["seconds"], final["clone_samples"]
        lines.append(f"\nFinal cloning (dagger/final): a fresh student on {final['frames']:,} frames, {samples:,} samples "
                     f"in {(sec['pool'] + sec['clone']) / 60:.1f} min (pool {sec['pool']:.0f} s, cloning "
                     f"{sec['clone']:.0f} s: {1e3 * sec['clone'] / samples:.2f} ms per sample)")
    return "\n".join(lines)


def write_done(iter_dir: Path, info: dict[str, Any]) -> None:
    atomic_write_json(Path(iter_dir) / "done.json", info)
