"""Tests of recorder.mcap.reader: round trip, named errors for missing and CRC-damaged files."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.errors import CorruptArtifactError, InputMissingError
from recorder.doctor_mcap import check_mcap_dir
from recorder.mcap.reader import EpisodeReader, count_frames, episode_summary, read_episode
from recorder.mcap.recovery import recover
from recorder.mcap.writer import EpisodeWriter
from tests.recorder.mcap.common import CHUNK, DEPTH_TOL_M, assert_frames_equal, chunk_layout


def test_round_trip(episode, recorded: Path) -> None:
    meta, occ, frames = episode
    assert sum(fr.pose_mask.any() for fr in frames) > 0, "the fixture episode should contain detections"
    got_meta, got_occ, it = read_episode(recorded)
    got = list(it)
    assert got_meta == meta
    assert got_occ.dtype == bool and np.array_equal(got_occ, occ)
    assert len(got) == len(frames) == count_frames(recorded)
    for a, b in zip(frames, got, strict=True):
        assert_frames_equal(a, b, depth_tol=DEPTH_TOL_M)
    s = episode_summary(recorded)
    assert s["n_frames"] == len(frames) and s["done"] and s["outcome"] == frames[-1].outcome
    assert s["duration_s"] == pytest.approx(frames[-1].t_ns / 1e9)
    assert s["topics"]["/map/occupancy"] == 1 and s["topics"]["/tf"] == len(frames)


def test_missing_inputs_are_named(tmp_path: Path) -> None:
    p = tmp_path / "nope.mcap"
    for fn in (read_episode, count_frames, episode_summary, recover, EpisodeReader):
        with pytest.raises(InputMissingError, match=re.escape(str(p))):
            fn(p)


def _flip(src: Path, dst: Path, offset: int) -> None:
    data = bytearray(src.read_bytes())
    data[offset] ^= 0x5A
    dst.write_bytes(bytes(data))


def _chunk_data_offset(path: Path, chunk_offset: int) -> tuple[int, int]:
    """(offset, length) of the compressed payload inside the chunk record at ``chunk_offset``."""
    b = path.read_bytes()
    p = chunk_offset + 9 + 8 + 8 + 8 + 4
    (n,) = np.frombuffer(b[p:p + 4], "<u4")
    p += 4 + int(n)
    (length,) = np.frombuffer(b[p:p + 8], "<u8")
    return p + 8, int(length)


@pytest.mark.parametrize("compression", ["zstd", "none"])
def test_crc_flip_named_error(episode, tmp_path: Path, compression: str) -> None:
    meta, occ, frames = episode
    good = tmp_path / "good.mcap"
    with EpisodeWriter(good, meta, occ, chunk_size=CHUNK, compression=compression) as w:
        for fr in frames:
            w.add(fr)
    chunk_off = chunk_layout(good)[2][0]
    start, length = _chunk_data_offset(good, chunk_off)
    d = tmp_path / "damaged"
    d.mkdir()
    bad = d / "bad.mcap"
    _flip(good, bad, start + length // 2)
    with pytest.raises(CorruptArtifactError) as ei:
        read_episode(bad)
    msg = str(ei.value)
    assert str(bad) in msg and f"offset {chunk_off}" in msg and "chunk" in msg
    if compression == "none":
        assert "CRC mismatch" in msg
    with pytest.raises(CorruptArtifactError, match=re.escape(str(bad))):
        episode_summary(bad)
    # damage outside the chunks (in a message index record) is caught by the data-section CRC
    idx_bad = d / "idx.mcap"
    s0, l0, _, _ = chunk_layout(good)[0]
    _flip(good, idx_bad, s0 + l0 + 12)
    with pytest.raises(CorruptArtifactError, match="data section CRC mismatch"):
        read_episode(idx_bad)
    problems = check_mcap_dir(d)
    assert len(problems) == 2
    assert any(line.startswith(str(bad)) for line in problems)
    assert any(line.startswith(str(idx_bad)) for line in problems)
    # salvage keeps the chunks before the damaged one
    part = bad.rename(d / "bad.mcap.partial")
    dt = frames[1].t_ns
    n_expect = sum((t1 - t0) // dt + 1 for s, _, t0, t1 in chunk_layout(good) if s < chunk_off)
    assert count_frames(recover(part)) == n_expect
