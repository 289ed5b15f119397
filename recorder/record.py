"""``icrowdnav record``: drive episodes in the crowd world and log each one to its own MCAP file.

::

    icrowdnav record --profile default --workers 2              # or: make record
    icrowdnav record --scenes hallway,corner --densities 0.1 --episodes 5 --resume

Output tree (``DATA_DIR/raw/<run_name>/``)::

    config.yaml, manifest.json        written when every episode is finished
    seeds.json                        the (scene, density, seed) of every episode
    episodes.jsonl                    one row per finished episode: file, frames, outcome, sha256
    <scene>_d<density>_s<seed>.mcap   one MCAP per episode (recorder.mcap.writer); ``*.mcap.partial`` while open

Recording writes in place, never in a staging copy: a killed run keeps every finished episode (and leaves the
open one as ``*.mcap.partial``, which ``icrowdnav recover`` salvages). ``--resume`` continues such a run:
finished episodes are kept, partial ones are re-recorded from their seed (episodes are deterministic).
SIGTERM/SIGINT stop the run cleanly: workers finish or abandon their current episode, a log line says what is
complete, and the exit status is non-zero.
"""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import shutil
import signal
import tempfile
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import ClassVar

from tqdm import tqdm

from pipeline.core import layout
from pipeline.core.artifacts import atomic_write_json, atomic_write_text
from pipeline.core.config import BaseStageConfig, check_run_name
from pipeline.core.errors import ConfigError, StoppedError
from pipeline.core.executor import (
    Executor,
    check_executor,
    check_ray_files,
    map_jobs,
    process_pool,
    receive_file,
    stop_pool,
)
from pipeline.core.manifest import hash_file
from recorder.drive import DRIVERS, drive_episode
from recorder.mcap.reader import episode_summary
from recorder.mcap.signals import Interrupted as Signalled
from recorder.mcap.signals import graceful_signals
from recorder.mcap.writer import EpisodeWriter
from sim.env import SimConfig
from sim.scene import check_episode_grid, scenes_of_split

log = logging.getLogger("icrowdnav")


class Interrupted(StoppedError):
    """The run was stopped by SIGTERM/SIGINT; finished episodes are kept (exit status 128 + the signal)."""


@dataclass
class RecordConfig(BaseStageConfig):
    """Config of the ``record`` stage."""
    PLACEMENT_FIELDS: ClassVar[tuple[str, ...]] = ("workers",)  # every episode seeded by itself: the same MCAP bytes

    run_name: str = field(default="expert", metadata={"help": "output folder name under DATA_DIR/raw/"})
    scenes: list[str] = field(default_factory=lambda: scenes_of_split("train"),
                              metadata={"help": "scene names or YAML paths (default: the training scenes)"})
    densities: list[float] = field(default_factory=lambda: [0.1, 0.2], metadata={"help": "pedestrians per m²"})
    episodes: int = field(default=4, metadata={"help": "episodes per (scene, density); seeds seed..seed+N-1"})
    driver: str = field(default="expert", metadata={"help": f"who drives: one of {list(DRIVERS)}"})
    workers: int = field(default=2, metadata={"help": "parallel episode processes"})
    executor: str = field(default="auto", metadata={"help": "where episodes run: auto (Ray when RAY_ADDRESS is set) "
                                                            "| local | ray (pipeline.core.executor)"})
    ray_address: str = field(default="", metadata={"help": "Ray cluster address host:port (empty: RAY_ADDRESS, or "
                                                           "a Ray instance started on this machine)"})
    ray_files: str = field(default="shared", metadata={
        "help": "on Ray, how episode files reach the data dir: shared (every node writes into it: a shared "
                "filesystem) | transfer (through Ray's object store; only the driver writes)"})
    sim: SimConfig = field(default_factory=SimConfig, metadata={"help": "the crowd world"})

    def validate(self) -> None:
        super().validate()
        check_executor(self.executor, self.ray_address, "record")
        check_ray_files(self.ray_files, "record")
        check_episode_grid(self.scenes, self.densities, self.episodes, self.workers)
        check_run_name(self.run_name)
        if self.driver not in DRIVERS:
            raise ConfigError(f"driver: expected one of {list(DRIVERS)}, got {self.driver!r}")


@dataclass(frozen=True)
class Job:
    """One episode to record."""

    scene: str
    density: float
    seed: int

    @property
    def name(self) -> str:
        return f"{Path(self.scene).stem}_d{self.density:g}_s{self.seed}"


def jobs_of(cfg: RecordConfig) -> list[Job]:
    return [Job(s, d, cfg.seed + k) for s in cfg.scenes for d in cfg.densities for k in range(cfg.episodes)]


def record_one(sim_cfg: SimConfig, job: Job, out: Path, driver: str) -> dict:
    """Record one episode to ``out/<job.name>.mcap``; returns its row for ``episodes.jsonl``."""

    t0 = time.perf_counter()
    ep = drive_episode(replace(sim_cfg, scene=job.scene, density=job.density), job.seed, driver)
    path = out / f"{job.name}.mcap"
    n = 0
    outcome = ""
    with EpisodeWriter(path, ep.meta, ep.occupancy) as w:
        for fr in ep.frames:
            w.add(fr)
            n += 1
            outcome = fr.outcome
        mcap_s = w.write_seconds
    return {"file": path.name, "scene": Path(job.scene).stem, "density": job.density, "seed": job.seed,
            "frames": n, "outcome": outcome, "bytes": path.stat().st_size, "sha256": hash_file(path),
            "seconds": round(time.perf_counter() - t0, 3), "mcap_seconds": round(mcap_s, 3)}


_STOP: mp.synchronize.Event | None = None  # set in pool workers by _init_worker: the run is stopping


def _worker(args: tuple) -> dict | None:
    """One episode in a pool worker; None without starting it once the run is stopping (a worker that was
    stopped itself, or a sibling, sets the shared event: episodes already queued to the pool are not begun)."""
    if _STOP is not None and _STOP.is_set():
        return None
    try:
        with graceful_signals():
            return record_one(*args)
    except Signalled:
        if _STOP is not None:
            _STOP.set()
        raise


def body(cfg: RecordConfig, out: Path) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    jobs = jobs_of(cfg)
    done_rows = _finished_rows(out, jobs)
    for p in out.glob("*.mcap.partial"):  # resumed run: the open episodes of the killed one are re-recorded
        log.info("record: re-recording unfinished episode %s", p.name)
        p.unlink()
    todo = [j for j in jobs if f"{j.name}.mcap" not in done_rows]
    if len(todo) < len(jobs):
        log.info("record: resuming, %d of %d episodes already finished", len(jobs) - len(todo), len(jobs))
    atomic_write_json(out / "seeds.json", {"episodes": [j.__dict__ for j in jobs]})
    rows = dict(done_rows)
    t0 = time.perf_counter()
    try:
        _run_jobs(cfg, todo, out, rows, jobs)
    finally:
        _write_rows(out, rows, jobs)
    wall = time.perf_counter() - t0
    new = [rows[f"{j.name}.mcap"] for j in todo]
    frames = sum(r["frames"] for r in rows.values())
    new_frames = sum(r["frames"] for r in new)
    mcap_share = sum(r["mcap_seconds"] for r in new) / max(sum(r["seconds"] for r in new), 1e-9)
    return {"episodes": len(rows), "frames": frames, "recorded_now": len(new),
            "frames_per_s": round(new_frames / wall, 2) if new else 0.0, "mcap_share": round(mcap_share, 4),
            "success_rate": round(sum(r["outcome"] == "success" for r in rows.values()) / len(rows), 4)}


def _init_worker(stop: mp.synchronize.Event) -> None:
    """Pool workers (:func:`pipeline.core.executor.process_pool`: SIGTERM when the main process dies): ignore Ctrl-C
    while idle (the main process coordinates the stop) and die on SIGTERM.

    While a worker records, :func:`_worker` installs :func:`recorder.mcap.signals.graceful_signals`, so SIGTERM or
    SIGINT then abort the open episode cleanly (a valid ``*.mcap.partial``).
    """
    global _STOP
    _STOP = stop
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _stop_pool(pool: ProcessPoolExecutor, stop: mp.synchronize.Event, grace_s: float = 3.0) -> None:
    """Stop starting episodes (the shared event; the executor pre-queues a few jobs that cancelling does not
    reach), cancel queued ones, ask running workers to abort theirs (SIGTERM: a valid ``*.mcap.partial``), and
    kill whatever is still alive after ``grace_s`` (its open episode stays ``.partial``; ``--resume`` redoes it)."""
    stop.set()
    stop_pool(pool, grace_s)


def _record_task(args: tuple) -> dict:
    """One episode as a Ray task (:mod:`pipeline.core.executor`): a killed worker leaves ``*.mcap.partial``; the
    retried task deletes that leftover of its own episode (the driver gives each episode to one task, and Ray reruns
    it only once the worker is known dead) and records the episode again under the same name."""
    _, job, out, _ = args
    (Path(out) / f"{job.name}.mcap.partial").unlink(missing_ok=True)
    return record_one(*args)


def _record_transfer_task(args: tuple) -> tuple[dict, bytes]:
    """One episode as a Ray task that does not touch the data directory (``ray_files: transfer``): recorded into a
    scratch folder of the worker's node, returned as ``(row, the MCAP's bytes)`` through the object store, the
    scratch folder removed. A retried task (its worker died) records the same bytes again in a new folder; the driver
    writes each episode once, when its task's result arrives (:func:`pipeline.core.executor.receive_file`)."""
    sim_cfg, job, driver = args
    scratch = Path(tempfile.mkdtemp(prefix="icrowdnav-record-"))
    try:
        row = record_one(sim_cfg, job, scratch, driver)
        return row, (scratch / row["file"]).read_bytes()
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def _run_jobs(cfg: RecordConfig, todo: list[Job], out: Path, rows: dict, jobs: list[Job]) -> None:
    bar = tqdm(total=len(todo), desc=f"record {cfg.driver}", unit="ep")
    ex = Executor.of(cfg)
    try:
        with graceful_signals():
            if ex.kind == "ray":
                transfer = ex.transfers

                def finished(_: int, result) -> None:
                    r = result[0] if transfer else result
                    if transfer:  # (row, bytes): only the driver writes into the data dir
                        receive_file(out / r["file"], result[1], r["sha256"])
                    rows[r["file"]] = r
                    _write_rows(out, rows, jobs)
                    bar.update()

                task, args = ((_record_transfer_task, [(cfg.sim, j, cfg.driver) for j in todo]) if transfer else
                              (_record_task, [(cfg.sim, j, out, cfg.driver) for j in todo]))
                map_jobs(task, args, cfg.workers, "record", progress=False, executor=ex, on_result=finished,
                         keep_results=not transfer)
                return
            if cfg.workers == 1:
                for j in todo:
                    r = record_one(cfg.sim, j, out, cfg.driver)
                    rows[r["file"]] = r
                    _write_rows(out, rows, jobs)
                    bar.update()
                return
        # the pool is created outside graceful_signals: forked workers must not inherit its handlers
        ctx = mp.get_context("fork")
        stop = ctx.Event()
        pool = process_pool(cfg.workers, "fork", initializer=_init_worker, initargs=(stop,))
        try:
            with graceful_signals():
                pending = {pool.submit(_worker, (cfg.sim, j, out, cfg.driver)) for j in todo}
                while pending:
                    finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for f in finished:
                        r = f.result()
                        if r is None:  # not begun: the run is stopping (a worker was signalled)
                            raise KeyboardInterrupt
                        rows[r["file"]] = r
                        _write_rows(out, rows, jobs)
                        bar.update()
        except BaseException:
            _stop_pool(pool, stop)
            raise
        pool.shutdown(wait=True)
    except (KeyboardInterrupt, BrokenProcessPool) as e:
        rows.clear()
        rows.update(_finished_rows(out, jobs))  # what is on disk, including episodes workers finished meanwhile
        partial = sorted(p.name for p in out.glob("*.mcap.partial"))
        names = f" ({', '.join(partial[:3])})" if partial else ""
        code = e.exit_code if isinstance(e, Signalled) else 130 if isinstance(e, KeyboardInterrupt) else 2
        raise Interrupted(f"record interrupted: {len(rows)} episodes finished (of {len(jobs)}) in {out}, "
                          f"{len(partial)} left unfinished{names}; rerun with --resume to continue",
                          exit_code=code) from e
    finally:
        bar.close()


def _finished_rows(out: Path, jobs: list[Job]) -> dict[str, dict]:
    """Rows of the episodes already finished in ``out``: every ``<name>.mcap`` of a job (a final name only exists
    once its writer finished). Rows come from ``episodes.jsonl`` when it has them, else from the file itself."""

    known: dict[str, dict] = {}
    p = out / "episodes.jsonl"
    if p.exists():
        for line in p.read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                known[r["file"]] = r
    rows: dict[str, dict] = {}
    for j in jobs:
        name = f"{j.name}.mcap"
        f = out / name
        if not f.is_file():
            continue
        if name in known and known[name].get("bytes") == f.stat().st_size:
            rows[name] = known[name]
            continue
        summ = episode_summary(f)  # raises a named error if the file is damaged
        rows[name] = {"file": name, "scene": Path(j.scene).stem, "density": j.density, "seed": j.seed,
                      "frames": summ["n_frames"], "outcome": summ["outcome"], "bytes": f.stat().st_size,
                      "sha256": hash_file(f), "seconds": 0.0, "mcap_seconds": 0.0}
    return rows


def _write_rows(out: Path, rows: dict[str, dict], jobs: list[Job]) -> None:
    order = {f"{j.name}.mcap": i for i, j in enumerate(jobs)}
    lines = [json.dumps(rows[k]) for k in sorted(rows, key=lambda k: order.get(k, 1 << 30))]
    atomic_write_text(out / "episodes.jsonl", "".join(line + "\n" for line in lines))


def raw_dir(cfg) -> Path:
    return layout.raw_dir(cfg.data_dir, cfg.run_name)
