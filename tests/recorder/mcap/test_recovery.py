"""Tests of recorder.mcap.recovery: exact salvage of truncated files, incomplete frames, byte-for-byte payloads."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from mcap.reader import make_reader

from pipeline.core.errors import CorruptArtifactError
from recorder.mcap.reader import EpisodeReader, count_frames, episode_summary, read_episode
from recorder.mcap.recovery import recover
from tests.recorder.helpers_mcap import rewrite
from tests.recorder.mcap.common import DEPTH_TOL_M, assert_frames_equal, chunk_layout


def test_truncated_mcap_named_error_and_exact_salvage(episode, recorded: Path, tmp_path: Path) -> None:
    _, _, frames = episode
    size = recorded.stat().st_size
    chunks = chunk_layout(recorded)
    assert len(chunks) >= 4
    dt = frames[1].t_ns
    data = recorded.read_bytes()
    (s1, l1, _, _), (s2, l2, _, _) = chunks[1], chunks[2]
    cuts = [size - 1, size - 30, chunks[-1][0] + chunks[-1][1] + 5,  # footer / summary / message index gone
            s2 + l2 // 2, s2 + l2, s2 + 3, s1 + l1 // 3, chunks[0][0] + 10, 100]
    for cut in cuts:
        bad = tmp_path / f"cut{cut}.mcap"
        bad.write_bytes(data[:cut])
        for fn in (read_episode, count_frames, episode_summary, EpisodeReader):
            with pytest.raises(CorruptArtifactError) as ei:
                fn(bad)
            assert str(bad) in str(ei.value), (cut, str(ei.value))
        # salvage: exactly the frames of the chunks that lie completely before the cut
        n_expect = sum((t1 - t0) // dt + 1 for s, ln, t0, t1 in chunks if s + ln <= cut)
        partial = bad.rename(tmp_path / f"cut{cut}.mcap.partial")
        if n_expect == 0:
            with pytest.raises(CorruptArtifactError, match="nothing to salvage"):
                recover(partial)
            continue
        out = recover(partial)
        got = list(read_episode(out)[2])
        assert len(got) == n_expect, cut
        for a, b in zip(frames, got, strict=False):
            assert_frames_equal(a, b, depth_tol=DEPTH_TOL_M)
    # the raw library on the same kind of file fails with a bare, unnamed error: that is what we wrap
    with open(tmp_path / f"cut{s2 + 3}.mcap.partial", "rb") as f, pytest.raises(Exception) as raw:
        list(make_reader(f, validate_crcs=True).iter_messages())
    assert not isinstance(raw.value, CorruptArtifactError)


def test_recover_drops_a_trailing_incomplete_frame(episode, recorded: Path, tmp_path: Path) -> None:
    """A writer that cuts chunks inside frames (the plain mcap Writer): the frame split by the cut is dropped."""
    _, _, frames = episode
    dt = frames[1].t_ns
    split = tmp_path / "split.mcap"
    rewrite(recorded, split, chunk_size=45_000)
    chunks = chunk_layout(split)
    # a chunk whose last frame continues in the next chunk
    k = next(i for i in range(1, len(chunks) - 1) if chunks[i][3] == chunks[i + 1][2])
    start, length, _, t_end = chunks[k]
    part = tmp_path / "split.mcap.partial"
    part.write_bytes(split.read_bytes()[: start + length])
    out = recover(part)
    got = list(read_episode(out)[2])
    assert len(got) == t_end // dt  # frames 0 .. t_end/dt - 1; the frame at t_end is incomplete
    for a, b in zip(frames, got, strict=False):
        assert_frames_equal(a, b, depth_tol=DEPTH_TOL_M)
    assert EpisodeReader(out).metadata["recovery"]["incomplete_frames_dropped"] == "1"


def test_recover_copies_payloads_byte_for_byte(recorded: Path, tmp_path: Path) -> None:
    part = tmp_path / "r.mcap.partial"
    shutil.copy(recorded, part)
    out = recover(part)
    with open(recorded, "rb") as f1, open(out, "rb") as f2:
        a = [(ch.topic, m.log_time, m.data) for _, ch, m in make_reader(f1).iter_messages()]
        b = [(ch.topic, m.log_time, m.data) for _, ch, m in make_reader(f2).iter_messages()]
    assert a == b
    assert EpisodeReader(out).metadata["recovery"]["frames_salvaged"] == str(count_frames(recorded))
