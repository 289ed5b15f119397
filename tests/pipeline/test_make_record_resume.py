"""The README's recovery command, end to end through the Makefile: ``make record`` SIGKILLed at seeded random
points (while recording, then while exporting), then ``make record ARGS=--resume``, gives the same bytes as an
uninterrupted ``make record`` — every MCAP and every dataset file (the files that name the data directory are
compared with that path replaced; ``config.yaml`` and ``manifest.json`` hold it and the run's time)."""

from __future__ import annotations

import hashlib
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
TINY = ("--scenes hallway --densities 0.05 --episodes 4 --sim.max-episode-s 3.0 --sim.camera.width-px 64 "
        "--sim.camera.height-px 48 --workers 1")
REPO_ID = "test/tiny"
PROVENANCE = {"config.yaml", "manifest.json"}
TIMINGS = {"seconds", "mcap_seconds"}

pytestmark = [pytest.mark.slow, pytest.mark.skipif(shutil.which("make") is None, reason="needs make")]


def make_record(data: Path, log: Path, *extra: str) -> subprocess.Popen:
    """``make record`` on tiny sizes into ``data`` in its own process group (a kill spares pytest)."""
    argv = ["make", "-s", "--no-print-directory", "record", f"DATA_DIR={data}", f"RECORD_ARGS={TINY}",
            f"EXPORT_ARGS=--repo-id {REPO_ID}", f"VENV={Path(sys.executable).parents[1]}", *extra]
    with open(log, "a") as f:
        return subprocess.Popen(argv, cwd=REPO, stdout=f, stderr=subprocess.STDOUT, start_new_session=True)


def kill_when(p: subprocess.Popen, ready, delay_s: float, timeout_s: float = 180.0) -> bool:
    """SIGKILLs ``p``'s process group ``delay_s`` after ``ready()`` holds; False if it finished first."""
    deadline = time.monotonic() + timeout_s
    while not ready():
        if p.poll() is not None:
            return False
        assert time.monotonic() < deadline, "the run never reached the kill point"
        time.sleep(0.01)
    time.sleep(delay_s)
    if p.poll() is not None:
        return False
    os.killpg(p.pid, signal.SIGKILL)
    p.wait()
    return True


def digests(data: Path) -> dict[str, str]:
    """sha256 of every file under raw/ and datasets/ except provenance, with ``data``'s path made neutral."""
    out = {}
    for p in sorted(data.rglob("*")):
        if not p.is_file() or p.name in PROVENANCE:
            continue
        blob = p.read_bytes().replace(str(data).encode(), b"<DATA>")
        if p.name == "episodes.jsonl":  # one row per finished episode; its timings differ between runs
            rows = [json.loads(line) for line in blob.decode().splitlines()]
            blob = json.dumps([{k: v for k, v in r.items() if k not in TIMINGS} for r in rows]).encode()
        out[p.relative_to(data).as_posix()] = hashlib.sha256(blob).hexdigest()
    return out


def test_make_record_killed_at_random_points_then_resume_gives_the_uninterrupted_bytes(tmp_path):
    rng = random.Random(24)
    ref_data, data, log = tmp_path / "ref", tmp_path / "data", tmp_path / "make.log"
    assert make_record(ref_data, log).wait() == 0, log.read_text()
    reference = digests(ref_data)
    assert sum(k.endswith(".mcap") for k in reference) == 4 and any(k.endswith(".parquet") for k in reference)

    raw = data / "raw" / "expert"
    p = make_record(data, log)  # 1. killed while recording: after the first episode, within the next ones
    killed_recording = kill_when(p, lambda: any(raw.glob("*.mcap")), rng.uniform(0.0, 0.3))
    assert killed_recording, "the run finished before the kill"
    assert not (raw / "manifest.json").exists() and not (data / "datasets").exists()

    owner = data / "datasets" / REPO_ID.split("/")[0]  # 2. the resume, killed while exporting
    p = make_record(data, log, "ARGS=--resume")
    killed_export = kill_when(p, lambda: owner.is_dir() and any(owner.iterdir()), rng.uniform(0.0, 3.0))
    assert (raw / "manifest.json").is_file()  # the recording itself was finished by the resume

    p = make_record(data, log, "ARGS=--resume")  # 3. the README's command, to the end
    assert p.wait() == 0, log.read_text()
    assert digests(data) == reference
    assert sorted(os.listdir(owner)) == [REPO_ID.split("/")[1]]  # no staging dir of the killed export left
    # what the test exercised (a run whose export finished before its kill still checks the resume path)
    print(f"killed while exporting: {killed_export}")
