"""A CLI verb run in a child process as one executor job (:func:`pipeline.core.executor.map_jobs`).

Used by ``icrowdnav train-all`` (one training variant per job). The job runs ``python -m <module> <args>`` with its
output appended to a log file and returns the exit status instead of raising, so one failed job does not stop the
others. The child is ended with its parent (``PR_SET_PDEATHSIG``): a Ray task cancelled or killed mid-job, or a
local worker stopped by Ctrl-C, leaves no process behind; :func:`die_with_parent` does the same for the workers of
every local process pool (:func:`pipeline.core.executor.process_pool`). This module imports nothing heavy, so a Ray worker
that runs the job starts in a fraction of a second instead of importing torch and the simulator first.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

_PR_SET_PDEATHSIG = 1


@dataclass(frozen=True)
class ChildJob:
    """``python -m <module> <*args>`` with its output in ``log_path``; ``name`` labels the result."""

    name: str
    args: tuple[str, ...]
    log_path: str
    module: str = "pipeline"
    drop_env: tuple[str, ...] = ()  # environment variables the child must not see (e.g. RAY_ADDRESS)


def _die_with_parent() -> None:
    """In the child, before exec: SIGTERM when the parent (the pool worker or Ray task) dies. SIGTERM is unblocked
    too: a signal mask is inherited through fork and exec, and a run started by a process or thread that blocks
    SIGTERM would otherwise leave the death signal pending and the child running on."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
    ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


def die_with_parent(parent_pid: int) -> None:
    """A process-pool worker's initializer (``initargs=(os.getpid(),)`` in the parent): SIGTERM to the worker when
    ``parent_pid`` dies (Linux; elsewhere nothing). Without it a killed run's workers outlive it: they finish the
    episodes already queued to them — writing into the output a resumed run is writing too — then wait forever on a
    queue nobody feeds. A parent that died before the worker armed the signal is caught by its parent id changing."""
    if not sys.platform.startswith("linux"):
        return
    _die_with_parent()
    if os.getppid() != parent_pid:  # the parent was gone before the signal was armed
        os.kill(os.getpid(), signal.SIGTERM)


def run_child(job: ChildJob) -> dict:
    """Runs the job; ``{"name", "returncode", "seconds", "log"}``. The log starts each run with ``$ <command>``."""
    cmd = [sys.executable, "-m", job.module, *job.args]
    env = {k: v for k, v in os.environ.items() if k not in job.drop_env} | {"PYTHONUNBUFFERED": "1"}
    Path(job.log_path).parent.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    with open(job.log_path, "ab") as logf:
        logf.write(f"$ {' '.join(cmd)}\n".encode())
        logf.flush()
        proc = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, preexec_fn=_die_with_parent, env=env)
        try:
            rc = proc.wait()
        except BaseException:
            proc.terminate()
            proc.wait()
            raise
    return {"name": job.name, "returncode": rc, "seconds": round(time.monotonic() - t0, 1), "log": job.log_path}


def log_tail(path: str, lines: int = 1) -> str:
    """The last ``lines`` lines of a log, joined with `` | `` ("" when it cannot be read)."""
    try:
        text = Path(path).read_text(errors="replace").strip().splitlines()
    except OSError:
        return ""
    return " | ".join(text[-lines:])
