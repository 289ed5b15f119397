"""Tests of recorder.mcap.signals: SIGTERM/SIGINT as Interrupted, and kill -9 / signals to a recording subprocess."""

from __future__ import annotations

import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from pipeline.core.errors import CorruptArtifactError
from recorder.doctor_mcap import check_mcap_dir
from recorder.mcap.reader import EpisodeReader, count_frames, read_episode
from recorder.mcap.recovery import recover
from recorder.mcap.signals import Interrupted, critical, graceful_signals
from tests.recorder.helpers_mcap import record_episode
from tests.recorder.mcap.common import CHUNK, MSGS_PER_FRAME, REPO, assert_frames_equal, sha256
from tests.terminal import sigint_as_in_a_terminal


def test_graceful_signals_raise_interrupted_and_restore_handlers() -> None:
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Interrupted) as ei, graceful_signals():
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(1.0)  # the handler raises here
    assert ei.value.signum == signal.SIGTERM and ei.value.exit_code == 128 + signal.SIGTERM
    assert isinstance(ei.value, KeyboardInterrupt)
    assert signal.getsignal(signal.SIGTERM) is before
    # inside a critical section (what the writer uses around mcap calls) the signal waits for the section's end;
    # SIGINT as a terminal's run has it, whatever started pytest (tests/terminal.py)
    steps = []
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(Interrupted), graceful_signals():
            with critical():
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)
                steps.append("finished the write")
            steps.append("not reached")
    finally:
        signal.signal(signal.SIGINT, previous)
    assert steps == ["finished the write"]


def test_a_signal_ignored_when_the_block_starts_stays_ignored() -> None:
    """A job started with SIGINT ignored (``nohup``, ``&`` from a script) is not stopped by one, as Python and the
    other stages leave it; SIGTERM still stops it, and the ignoring is in place again after the block."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with pytest.raises(Interrupted) as ei, graceful_signals():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)  # ignored: nothing raised here
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1.0)
        assert ei.value.signum == signal.SIGTERM
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


class _Proc:
    """The helper recorder in a subprocess, with its stdout lines read by a thread."""

    def __init__(self, out: Path, episodes: int = 3) -> None:
        self.p = subprocess.Popen(
            [sys.executable, "-m", "tests.recorder.helpers_mcap", str(out), "--episodes", str(episodes),
             "--frame-sleep", "0.03", "--chunk-size", str(CHUNK)],
            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, preexec_fn=sigint_as_in_a_terminal)
        self.lines: list[str] = []
        self.q: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        assert self.p.stdout is not None
        for line in self.p.stdout:
            self.q.put(line.rstrip("\n"))
        self.q.put(None)

    def wait_for(self, pattern: str, timeout: float = 30.0) -> re.Match:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.q.get(timeout=max(0.01, deadline - time.monotonic()))
            except queue.Empty:
                break
            if line is None:
                break
            self.lines.append(line)
            if m := re.search(pattern, line):
                return m
        self.p.kill()
        raise AssertionError(f"helper never printed {pattern!r}; output:\n" + "\n".join(self.lines))

    def rest(self) -> list[str]:
        while (line := self.q.get(timeout=10)) is not None:
            self.lines.append(line)
        return self.lines


def _finished_counts(lines: list[str]) -> dict[str, int]:
    return {f"ep{m[1]}.mcap": int(m[2]) for line in lines if (m := re.match(r"finished ep=(\d+) frames=(\d+)", line))}


def test_kill9_mid_episode(tmp_path: Path) -> None:
    out = tmp_path / "run"
    proc = _Proc(out)
    m = proc.wait_for(r"frame ep=2 step=12 durable=(\d+)")
    durable = int(m[1])
    proc.p.send_signal(signal.SIGKILL)
    assert proc.p.wait(timeout=10) == -signal.SIGKILL
    counts = _finished_counts(proc.rest())
    assert sorted(counts) == ["ep0.mcap", "ep1.mcap"]
    assert sorted(p.name for p in out.iterdir()) == ["ep0.mcap", "ep1.mcap", "ep2.mcap.partial"]
    for name, n in counts.items():  # finished episodes: CRC-checked, expected message count, same as a clean run
        r = EpisodeReader(out / name)
        assert r.n_frames == n and sum(r.message_counts.values()) == n * MSGS_PER_FRAME + 1
        assert sum(1 for _ in r.frames()) == n
        clean = record_episode(tmp_path / f"clean_{name}", int(name[2]), CHUNK).final_path
        assert sha256(out / name) == sha256(clean)
    partial = out / "ep2.mcap.partial"
    with pytest.raises(CorruptArtifactError, match=re.escape(str(partial))):
        read_episode(partial)
    problems = check_mcap_dir(out)
    assert len(problems) == 1 and problems[0].startswith(str(partial)) and "unfinished" in problems[0]
    rec = recover(partial)
    n = count_frames(rec)
    assert durable <= n <= 21 and durable >= 10
    clean = list(read_episode(record_episode(tmp_path / "clean_ep2.mcap", 2, CHUNK).final_path)[2])
    for a, b in zip(clean[:n], read_episode(rec)[2], strict=True):
        assert_frames_equal(a, b)
    assert "already recovered" in check_mcap_dir(out)[0]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_sigterm_graceful(tmp_path: Path, sig: signal.Signals) -> None:
    out = tmp_path / "run"
    proc = _Proc(out)
    proc.wait_for(r"frame ep=1 step=6 ")
    t0 = time.monotonic()
    proc.p.send_signal(sig)
    rc = proc.p.wait(timeout=10)
    assert time.monotonic() - t0 < 5.0
    assert rc == 128 + sig
    lines = proc.rest()
    assert any(line.startswith(f"interrupted by {sig.name}") and "ep1.mcap.partial" in line for line in lines), lines
    assert sorted(p.name for p in out.iterdir()) == ["ep0.mcap", "ep1.mcap.partial"]
    assert EpisodeReader(out / "ep0.mcap").n_frames == _finished_counts(lines)["ep0.mcap"]
    # the interrupted episode was closed cleanly: a valid MCAP holding every frame added before the signal
    partial = EpisodeReader(out / "ep1.mcap.partial")
    last = max(int(m[1]) for line in lines if (m := re.match(r"frame ep=1 step=(\d+)", line)))
    assert partial.n_frames == last + 1 and partial.metadata["aborted"]["reason"] == "Interrupted"
    assert count_frames(recover(out / "ep1.mcap.partial")) == last + 1
