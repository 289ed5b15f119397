"""Pool workers die with the run that started them (``pipeline.core.child.die_with_parent``): a killed run leaves
no worker finishing its queued episodes into the output a resumed run writes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.core.artifacts import pid_alive

ROOT = Path(__file__).resolve().parents[3]

# a run of busy 3-s jobs on two pool workers; each job notes its worker's pid when it starts and when it ends
_RUN = """
import os, sys, time
from pathlib import Path
from pipeline.core.executor import map_jobs
OUT = Path(sys.argv[1])
def job(i):
    (OUT / f"start_{i}").write_text(str(os.getpid()))
    t = time.monotonic()
    while time.monotonic() - t < 3.0:
        pass
    (OUT / f"end_{i}").write_text(str(os.getpid()))
    return i
if __name__ == "__main__":
    if sys.argv[2:] == ["sigterm-blocked"]:  # as if started by a process or thread that blocks SIGTERM
        import signal
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    map_jobs(job, list(range(12)), 2, "jobs", progress=False)
"""


def _pids(out: Path) -> set[int]:
    return {int(text) for p in out.glob("start_*") if (text := p.read_text())}


def _workers(out: Path, timeout_s: float = 60.0) -> set[int]:
    """The pids of the two workers, once both have started a job."""
    t = time.monotonic()
    while time.monotonic() - t < timeout_s:
        if len(pids := _pids(out)) == 2:
            return pids
        time.sleep(0.05)
    raise AssertionError(f"two workers did not start within {timeout_s} s: {sorted(out.iterdir())}")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_killing_the_run_ends_its_pool_workers_at_once(tmp_path, sig):
    _kill_the_run(tmp_path, sig)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_the_workers_die_with_a_run_started_with_sigterm_blocked(tmp_path):
    """The mask is inherited through fork: a worker that kept SIGTERM blocked would finish its jobs first."""
    _kill_the_run(tmp_path, signal.SIGKILL, "sigterm-blocked")


def _kill_the_run(tmp_path: Path, sig: signal.Signals, *args: str) -> None:
    main = subprocess.Popen([sys.executable, "-c", _RUN, str(tmp_path), *args], cwd=ROOT)
    try:
        workers = _workers(tmp_path)
        os.kill(main.pid, sig)
        main.wait(timeout=30)
        t = time.monotonic()
        while any(map(pid_alive, workers)) and time.monotonic() - t < 10.0:
            time.sleep(0.05)
        alive = [p for p in workers if pid_alive(p)]
        # without the signal they finish the jobs queued to them (3 s each), then wait on the queue for ever
        assert not alive, f"pool workers {alive} outlived the run killed with {sig.name}"
        assert not list(tmp_path.glob("end_*")), "a worker finished a job after the run was killed"
    finally:
        main.kill()
        for p in _pids(tmp_path):  # never leave a worker behind, whatever failed
            if pid_alive(p):
                os.kill(p, signal.SIGKILL)


@pytest.mark.parametrize("blocked", [False, True], ids=["", "sigterm-blocked"])
def test_a_worker_whose_parent_is_already_gone_ends_itself(blocked):
    code = "from pipeline.core.child import die_with_parent\ndie_with_parent(-1)\nprint('survived')"
    if blocked:
        code = "import signal\nsignal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})\n" + code
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert res.returncode == -signal.SIGTERM and "survived" not in res.stdout
