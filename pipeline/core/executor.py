"""Where independent jobs (episodes) run: the local process pool (the default) or a Ray cluster.

::

    icrowdnav record --executor ray                      # a Ray instance started for this run on this machine
    RAY_ADDRESS=10.0.0.5:6379 icrowdnav eval ...         # a running cluster (``ray start --head`` there)
    icrowdnav eval --executor ray --ray_address 10.0.0.5:6379

``executor``: ``auto`` (Ray when ``RAY_ADDRESS`` is set, else local), ``local`` or ``ray``. Both give the same
results: a job is a pure function of its arguments (seeded episodes), each writes its own files under deterministic
names (atomically: a temporary name, then a rename), and results come back in job order. On Ray:

* every job is one task (one CPU); a task whose worker process or node dies is rerun (``max_retries``) — it
  rewrites the same files, so nothing is lost or duplicated; an exception raised *by* the job is not retried and
  surfaces as itself (a named error stays a named error);
* files reach the driver's data directory in one of two ways (``files``, a stage's ``--ray_files``):
  ``shared`` (the default): files are written where the job's paths point, so the data directory must be the same
  path on every node (a shared filesystem: NFS, a cluster volume; on one machine nothing is needed);
  :func:`check_data_dir` runs a probe task on every alive node first and names a node that cannot write there (exit
  2, nothing written). ``transfer`` (the ``record`` stage): a task writes into a scratch folder of its own node and
  returns the file's bytes through Ray's object store; the driver checks them against the row's sha256 and writes
  them atomically (:func:`receive_file`) — no node but the driver touches the data directory, which is not probed.
  ``eval`` and ``train`` (DAgger rollouts, acceptance) transfer both ways: the checkpoints the episodes act from go
  to the nodes once per run or iteration as a :class:`Bundle` (one object in the store, unpacked once per node into
  a folder of its own), and each episode's files (figures, traces, videos, logs; DAgger's MCAP and feature cache)
  come back as bytes (docs/scale-out.md);
* the progress bar counts finished tasks; Ctrl-C (or SIGTERM) cancels every pending and running task
  (``ray.cancel(force=True)``), then the stage reports what finished, as with the local pool;
* an address nobody answers is a named error after a 5 s TCP probe (``ray.init`` itself would wait for minutes).

The local pool forks (workers keep what they load, e.g. a method's weights, for the jobs that follow); Ray workers
are long-lived processes too, so per-process caches work the same way there.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import multiprocessing as mp
import os
import shutil
import signal
import socket
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from tqdm import tqdm

from pipeline.core.artifacts import atomic_write_bytes, pid_alive
from pipeline.core.child import die_with_parent
from pipeline.core.errors import ConfigError, CorruptArtifactError, ICrowdNavError

log = logging.getLogger("icrowdnav")

J = TypeVar("J")
R = TypeVar("R")
EXECUTORS = ("auto", "local", "ray")
RAY_FILES = ("shared", "transfer")  # how a Ray task's files reach the driver's data directory (module docstring)
BUNDLE_KEEP_S = 24 * 3600.0  # an unpacked Bundle unused this long is removed from its node (Bundle.unpack)
PROBE_TIMEOUT_S = 5.0
MAX_RETRIES = 3  # reruns of a task whose worker died


def check_executor(executor: str, address: str, where: str) -> None:
    """Config check of the ``executor`` / ``ray_address`` fields of a stage config (``where``: its key prefix)."""
    if executor not in EXECUTORS:
        raise ConfigError(f"{where}.executor: expected one of {list(EXECUTORS)}, got {executor!r}")
    if address and executor == "local":
        raise ConfigError(f"{where}.ray_address: given ({address!r}) but {where}.executor is 'local'")


def check_ray_files(files: str, where: str) -> None:
    """Config check of a stage's ``ray_files`` field."""
    if files not in RAY_FILES:
        raise ConfigError(f"{where}.ray_files: expected one of {list(RAY_FILES)}, got {files!r}")


def receive_file(path: Path, data: bytes, sha256: str) -> Path:
    """Writes a file a Ray task returned through the object store (``files: transfer``) to ``path`` atomically,
    after checking its bytes against the ``sha256`` the task computed; a mismatch is one named error and leaves
    ``path`` as it was."""
    got = hashlib.sha256(data).hexdigest()
    if got != sha256:
        raise CorruptArtifactError(f"{path}: the {len(data)} bytes a Ray task returned have sha256 {got[:12]}..., "
                                   f"the task computed {sha256[:12]}...; nothing written")
    return atomic_write_bytes(Path(path), data)


@dataclass(frozen=True)
class Bundle:
    """Files Ray tasks read, shipped through the object store once per run (``files: transfer``): ``files`` pairs a
    path relative to ``root`` (the deepest folder holding every shipped file, on the driver) with its bytes; ``key``
    is the sha256 over names and bytes. A task calls :meth:`unpack` and :meth:`local` instead of reading ``root``."""

    root: str
    files: tuple[tuple[str, bytes], ...]
    key: str

    @classmethod
    def of(cls, files: dict[Path, bytes]) -> Bundle:
        """A bundle of ``files`` (absolute path → bytes; what a task will find under :meth:`local`)."""
        paths = [os.path.abspath(p) for p in files]
        root = os.path.commonpath([os.path.dirname(p) for p in paths]) if paths else "/"
        items = tuple(sorted((os.path.relpath(os.path.abspath(p), root), bytes(b)) for p, b in files.items()))
        h = hashlib.sha256()
        for name, data in items:
            h.update(name.encode() + b"\0" + hashlib.sha256(data).digest())
        return cls(root, items, h.hexdigest())

    def unpack(self) -> Path:
        """The files on this node: written once per node and bundle into ``<tmp>/icrowdnav-files-<key>`` (a folder
        filled under a temporary name ``.icrowdnav-files-<key>-<pid>-*``, then renamed: concurrent tasks and a
        killed one leave no half-filled folder, and the temporary folders of dead processes are removed here);
        later calls return it and mark it used (its mtime). Unpacking a new bundle removes the bundles of this node
        that no task has used for :data:`BUNDLE_KEEP_S` (a node serving many runs does not fill its disk)."""
        final = Path(tempfile.gettempdir()) / f"icrowdnav-files-{self.key[:20]}"
        if final.is_dir():
            with suppress(OSError):  # removed meanwhile as unused: the caller still gets a folder below
                os.utime(final)
                return final
        for stale in final.parent.glob(f".{final.name}-*-*"):
            pid = stale.name[len(final.name) + 2:].split("-", 1)[0]
            if pid.isdigit() and not pid_alive(int(pid)):
                shutil.rmtree(stale, ignore_errors=True)
        for old in final.parent.glob("icrowdnav-files-*"):
            with suppress(OSError):
                if old != final and time.time() - old.stat().st_mtime > BUNDLE_KEEP_S:
                    shutil.rmtree(old, ignore_errors=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}-{os.getpid()}-", dir=final.parent))
        try:
            for name, data in self.files:
                (tmp / name).parent.mkdir(parents=True, exist_ok=True)
                (tmp / name).write_bytes(data)
            os.rename(tmp, final)
        except OSError:
            if not final.is_dir():  # not another task that won the rename
                raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        return final

    def local(self, unpacked: Path, path: Path | str) -> Path:
        """Where ``path`` (a driver path at or under :attr:`root`) is in the ``unpacked`` folder."""
        return Path(unpacked) / os.path.relpath(os.path.abspath(path), self.root)


def in_scratch(fn: Callable[[Path], R], prefix: str) -> tuple[R, list[tuple[str, bytes, str]]]:
    """``fn(folder)`` run in a fresh scratch folder of this node, then its result and every file it wrote there
    (:func:`returned_files`); the folder is removed. What a ``transfer`` task returns (a retried task returns the
    same files again; the driver writes them once, when its result arrives: :func:`receive_files`)."""
    scratch = Path(tempfile.mkdtemp(prefix=prefix))
    try:
        result = fn(scratch)
        return result, returned_files(scratch)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def receive_files(folder: Path, files: list[tuple[str, bytes, str]], last: str = "") -> None:
    """The files a ``transfer`` task returned (:func:`in_scratch`) written under ``folder`` with
    :func:`receive_file`; those whose path starts with ``last`` after the others (a file that marks its episode
    done)."""
    for name, data, sha in sorted(files, key=lambda f: bool(last) and f[0].startswith(last)):
        receive_file(Path(folder) / name, data, sha)


def returned_files(folder: Path) -> list[tuple[str, bytes, str]]:
    """Every file under ``folder`` as ``(path relative to it, bytes, sha256)``: what a ``transfer`` task returns
    for the driver to write with :func:`receive_file`."""
    out = []
    for p in sorted(Path(folder).rglob("*")):
        if p.is_file():
            data = p.read_bytes()
            out.append((p.relative_to(folder).as_posix(), data, hashlib.sha256(data).hexdigest()))
    return out


def resolve_executor(executor: str, address: str = "") -> str:
    """``local`` or ``ray``: ``auto`` is Ray when an address is given or ``RAY_ADDRESS`` is set."""
    if executor == "auto":
        return "ray" if (address or os.environ.get("RAY_ADDRESS")) else "local"
    return executor


def _probe_address(address: str) -> None:
    """A TCP connection to a ``host:port`` / ``ray://host:port`` address, or one named error."""
    if address in ("", "auto", "local"):
        return
    hostport = address.split("://", 1)[-1]
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit():
        raise ConfigError(f"Ray address: expected host:port (or ray://host:port, auto), got {address!r}")
    try:
        socket.create_connection((host, int(port)), timeout=PROBE_TIMEOUT_S).close()
    except OSError as e:
        raise ConfigError(f"Ray address {address}: nobody answers ({type(e).__name__}: {e}); start a cluster with "
                          "`ray start --head` (then --address / RAY_ADDRESS = what it prints) or unset RAY_ADDRESS "
                          "to run locally") from None


def _write_probe(data_dir: str, token: str) -> tuple[str, str]:
    """On one node: ``(node ip, "")`` if ``data_dir`` exists there and a file can be written in it, else the
    reason."""
    import ray

    ip = ray.util.get_node_ip_address()
    d = Path(data_dir)
    if not d.is_dir():
        return ip, f"{data_dir} does not exist there"
    probe = d / f".ray_probe_{token}_{ray.get_runtime_context().get_node_id()[:12]}"  # nodes may share the folder
    try:
        probe.write_text(token)
        probe.unlink()
    except OSError as e:
        return ip, f"{data_dir} is not writable there ({type(e).__name__}: {e})"
    return ip, ""


def check_data_dir(data_dir: Path) -> None:
    """Every alive node can write into ``data_dir`` (the same path as on the driver), or one named error."""
    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    probe = ray.remote(num_cpus=0, max_retries=0)(_write_probe)
    token = uuid.uuid4().hex
    nodes = [n["NodeID"] for n in ray.nodes() if n.get("Alive")]
    refs = [probe.options(scheduling_strategy=NodeAffinitySchedulingStrategy(n, soft=False)).remote(
        str(Path(data_dir).resolve()), token) for n in nodes]
    bad = [(ip, why) for ip, why in ray.get(refs) if why]
    if bad:
        ip, why = bad[0]
        raise ConfigError(f"data dir {Path(data_dir).resolve()}: the Ray workers cannot reach it — on node {ip}, "
                          f"{why} ({len(bad)} of {len(nodes)} nodes); the data directory must be the same path on "
                          "every node (a shared filesystem), see docs/scale-out.md")


@contextmanager
def ray_session(address: str, data_dir: Path, workers: int, files: str = "shared") -> Iterator[None]:
    """Connects to the cluster at ``address`` (or ``RAY_ADDRESS``), or starts a local Ray instance with ``workers``
    CPUs; checks the data dir from every node (``files: shared``; with ``transfer`` the nodes never touch it);
    shuts down what it started. Reuses a session already connected (tests, notebooks)."""
    import ray

    addr = address or os.environ.get("RAY_ADDRESS", "")
    started = False
    if not ray.is_initialized():
        _probe_address(addr)
        # "local": our own instance even when another runs on this machine (a `ray start`, another run's cluster);
        # a bare ray.init() would join the one recorded in /tmp/ray/ray_current_cluster and refuse num_cpus there
        kw: dict[str, Any] = {"address": addr or "local", "log_to_driver": False, "configure_logging": False}
        if not addr:
            kw.update(num_cpus=max(1, workers), include_dashboard=False)
        try:
            ray.init(**kw)
        except (ConnectionError, RuntimeError, ValueError) as e:
            raise ConfigError(f"Ray address {addr or '(a local instance)'}: could not connect "
                              f"({type(e).__name__}: {str(e)[:200]})") from None
        started = True
    try:
        if files == "shared":
            check_data_dir(data_dir)
        yield
    finally:
        if started:
            ray.shutdown()


def _ray_map(fn: Callable[..., Any], jobs: Sequence[J], desc: str, progress: bool, unit: str,
             on_result: Callable[[int, Any], None] | None, cpus_per_job: int = 1,
             keep_results: bool = True, shared: Any = None) -> list[Any]:
    import ray
    from ray.exceptions import RayTaskError

    task = ray.remote(num_cpus=cpus_per_job, max_retries=MAX_RETRIES, retry_exceptions=False)(fn)
    if shared is None:
        pending = [task.remote(j) for j in jobs]
    else:  # one object in the store; Ray hands each task its value (fetched once per node)
        ref = ray.put(shared)
        pending = [task.remote(j, shared=ref) for j in jobs]
    index = {r: i for i, r in enumerate(pending)}
    out: list[Any] = [None] * len(jobs)
    bar = tqdm(total=len(jobs), desc=desc, unit=unit, disable=not progress, dynamic_ncols=True)
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for r in done:
                i = index.pop(r)  # the last reference to a finished object: released once handled
                try:
                    result = ray.get(r)
                except RayTaskError as e:  # the job's own exception: raise it as itself (named errors stay named)
                    cause = getattr(e, "cause", None)
                    if isinstance(cause, ICrowdNavError | KeyboardInterrupt):
                        raise cause from None
                    raise
                if on_result is not None:
                    on_result(i, result)
                if keep_results:
                    out[i] = result
                bar.update()
    except BaseException:
        for r in pending:
            ray.cancel(r, force=True)
        raise
    finally:
        bar.close()
    return out


@dataclass(frozen=True)
class Executor:
    """Where a stage's jobs run: ``kind`` ``local`` or ``ray`` (resolved), the Ray ``address`` ("" = ``RAY_ADDRESS``
    or a local instance), the ``data_dir`` the jobs write into (checked from every Ray node) and how a Ray task's
    files reach it (``files``: ``shared`` | ``transfer``, module docstring)."""

    kind: str = "local"
    address: str = ""
    data_dir: Path = Path(".")
    files: str = "shared"

    @classmethod
    def of(cls, cfg: Any) -> Executor:
        """From a stage config's ``executor`` / ``ray_address`` / ``data_dir`` (/ ``ray_files``) fields."""
        return cls(resolve_executor(cfg.executor, cfg.ray_address), cfg.ray_address, Path(cfg.data_dir),
                   getattr(cfg, "ray_files", "shared"))

    @property
    def transfers(self) -> bool:
        """Ray tasks that never touch the data directory: their inputs travel in the object store and the driver
        writes the files they return (``files: transfer``)."""
        return self.kind == "ray" and self.files == "transfer"

    @contextmanager
    def session(self, workers: int) -> Iterator[None]:
        """One Ray connection for a whole stage (every :func:`map_jobs` inside reuses it); nothing for ``local``."""
        if self.kind != "ray":
            yield
            return
        with ray_session(self.address, self.data_dir, workers, self.files):
            yield


def _init_pool_worker(parent_pid: int, initializer: Callable[..., None] | None, initargs: tuple) -> None:
    # a worker dies on SIGTERM even when forked from a run that turns it into an exception
    # (pipeline.core.signals.sigterm_raises): otherwise a job would catch it and the worker take the next one
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    die_with_parent(parent_pid)
    if initializer is not None:
        initializer(*initargs)


def process_pool(workers: int, start: str = "fork", initializer: Callable[..., None] | None = None,
                 initargs: tuple = ()) -> ProcessPoolExecutor:
    """The project's local process pool: ``workers`` processes started with ``start`` that get SIGTERM when this
    process dies (:func:`pipeline.core.child.die_with_parent`: a killed run leaves no worker writing on), then run
    ``initializer(*initargs)``. Every local pool is made here (``map_jobs``, the recorder's, the teacher's and the
    baselines' expert pools)."""
    return ProcessPoolExecutor(workers, mp_context=mp.get_context(start), initializer=_init_pool_worker,
                               initargs=(os.getpid(), initializer, initargs))


def stop_pool(pool: ProcessPoolExecutor, grace_s: float = 3.0) -> None:
    """Stops a :func:`process_pool` now, not after its queue (a run stopped by Ctrl-C or SIGTERM): cancels the jobs
    not begun, SIGTERMs the workers (running jobs abort) and kills whatever is still alive after ``grace_s``."""
    procs = list((getattr(pool, "_processes", None) or {}).values())  # CPython's executor keeps its workers here
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        if p.is_alive():
            os.kill(p.pid, signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for p in procs:
        p.join(timeout=max(0.0, deadline - time.monotonic()))
        if p.is_alive():
            p.kill()
            p.join(timeout=1.0)


def map_jobs(fn: Callable[[J], Any], jobs: Sequence[J], workers: int, desc: str, progress: bool = True,
             unit: str = "ep", executor: Executor | None = None,
             on_result: Callable[[int, Any], None] | None = None, start: str = "fork",
             cpus_per_job: int = 1, keep_results: bool = True, shared: Any = None) -> list[Any]:
    """``[fn(j) for j in jobs]`` in job order: in this process (``workers <= 1``), a process pool of ``workers``
    (started with ``start``: ``fork``, or ``spawn`` for workers that use CUDA), or Ray tasks (``executor.kind ==
    "ray"``; inside :meth:`Executor.session` or starting one; each task holds ``cpus_per_job`` CPUs, e.g. a job
    that runs its own process pool). ``on_result(i, result)`` is called as each job finishes (in completion order
    with Ray, in job order otherwise), e.g. to record progress; with ``keep_results=False`` (Ray) a result is only
    handed to ``on_result`` and not kept (e.g. a file's bytes, written as they arrive), and the list holds None.
    ``shared`` (not None): ``fn(j, shared=shared)`` instead — one value every job reads (e.g. a :class:`Bundle`), put in
    Ray's object store once instead of being pickled into every task."""
    if executor is not None and executor.kind == "ray":
        if not jobs:
            return []
        with executor.session(workers):
            return _ray_map(fn, jobs, desc, progress, unit, on_result, cpus_per_job, keep_results, shared)
    if shared is not None:
        fn = functools.partial(fn, shared=shared)
    if workers <= 1:
        out = []
        for i, j in enumerate(tqdm(jobs, desc=desc, unit=unit, disable=not progress, dynamic_ncols=True)):
            out.append(fn(j))
            if on_result is not None:
                on_result(i, out[-1])
        return out
    pool = process_pool(workers, start)
    try:
        out = []
        for i, r in enumerate(tqdm(pool.map(fn, jobs, chunksize=1), total=len(jobs), desc=desc, unit=unit,
                                   disable=not progress, dynamic_ncols=True)):
            out.append(r)
            if on_result is not None:
                on_result(i, r)
    except BaseException:  # a failed job, Ctrl-C or SIGTERM: the queued jobs are not run first
        stop_pool(pool)
        raise
    pool.shutdown(wait=True)
    return out
