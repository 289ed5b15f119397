"""Tests of recorder.mcap.writer: determinism, the start/add/finish lifecycle, frame checks, abort."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import pytest

from pipeline.core.errors import OutputExistsError
from recorder.mcap.reader import EpisodeReader, count_frames, read_episode
from recorder.mcap.recovery import recover
from recorder.mcap.writer import EpisodeWriter
from tests.recorder.helpers_mcap import record_episode
from tests.recorder.mcap.common import CHUNK, DEPTH_TOL_M, assert_frames_equal, sha256


def test_same_seed_identical_different_seed_differs(tmp_path: Path, recorded: Path) -> None:
    a = record_episode(tmp_path / "a.mcap", 1, CHUNK).final_path
    b = record_episode(tmp_path / "b.mcap", 1, CHUNK).final_path
    c = record_episode(tmp_path / "c.mcap", 2, CHUNK).final_path
    assert sha256(a) == sha256(b) == sha256(recorded)
    assert sha256(c) != sha256(a)


def test_lifecycle_partial_name_and_no_overwrite(episode, tmp_path: Path) -> None:
    meta, occ, frames = episode
    final = tmp_path / "e.mcap"
    w = EpisodeWriter(final, meta, occ)
    assert not w.partial_path.exists()
    w.start()
    assert w.partial_path == tmp_path / "e.mcap.partial" and w.partial_path.exists() and not final.exists()
    for fr in frames:
        w.add(fr)
    with pytest.raises(ValueError, match="done=True"):
        w.add(replace(frames[-1], step=len(frames), t_ns=frames[-1].t_ns + 100_000_000))
    assert w.finish() == final and w.finish() == final  # idempotent
    assert final.exists() and not w.partial_path.exists() and w.frames_durable == len(frames)
    with pytest.raises(RuntimeError, match="finished"):
        w.add(frames[0])
    digest = sha256(final)
    with pytest.raises(OutputExistsError, match=re.escape(str(final))):
        EpisodeWriter(final, meta, occ).start()
    assert sha256(final) == digest
    stale = tmp_path / "s.mcap.partial"
    stale.write_bytes(b"left by a killed run")
    with pytest.raises(OutputExistsError, match="recover"):
        EpisodeWriter(tmp_path / "s.mcap", meta, occ).start()
    assert stale.read_bytes() == b"left by a killed run"


def test_add_checks_the_frame(episode, tmp_path: Path) -> None:
    meta, occ, frames = episode
    with pytest.raises(ValueError, match="step expected 0, got 1"), EpisodeWriter(tmp_path / "f.mcap", meta, occ) as w:
        w.add(frames[1])
    bad = replace(frames[0], rgb={**frames[0].rgb, "left": frames[0].rgb["left"][:, :10]})
    with pytest.raises(ValueError, match=r"rgb\[left\] expected"), EpisodeWriter(tmp_path / "g.mcap", meta, occ) as w:
        w.add(bad)
    assert not (tmp_path / "g.mcap").exists() and (tmp_path / "g.mcap.partial").exists()


def test_exception_leaves_valid_partial(episode, tmp_path: Path) -> None:
    meta, occ, frames = episode
    final = tmp_path / "h.mcap"
    with pytest.raises(KeyError), EpisodeWriter(final, meta, occ, chunk_size=CHUNK) as w:
        for fr in frames[:5]:
            w.add(fr)
        raise KeyError("boom")
    assert not final.exists()
    partial = tmp_path / "h.mcap.partial"
    r = EpisodeReader(partial)  # closed cleanly: a valid MCAP with an 'aborted' record, not renamed
    assert r.n_frames == 5 and r.metadata["aborted"]["reason"] == "KeyError"
    out = recover(partial)
    assert out == tmp_path / "h.recovered.mcap" and count_frames(out) == 5 and partial.exists()
    for a, b in zip(frames[:5], read_episode(out)[2], strict=True):
        assert_frames_equal(a, b, depth_tol=DEPTH_TOL_M)
    with pytest.raises(OutputExistsError, match="h.recovered.mcap"):
        recover(partial)
