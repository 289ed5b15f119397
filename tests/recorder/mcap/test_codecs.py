"""Tests of recorder.mcap.codecs: bit-exact JSON arrays, non-finite values, depth quantisation."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from recorder.mcap.codecs import dec_array, enc_array
from recorder.mcap.reader import read_episode
from recorder.mcap.writer import EpisodeWriter
from tests.recorder.mcap.common import DEPTH_TOL_M, assert_frames_equal


def test_float32_json_encoding_is_bit_exact() -> None:
    """9 significant digits identify every finite float32 (normals, subnormals, ±0, extremes) exactly."""
    rng = np.random.default_rng(0)
    bits = np.concatenate([rng.integers(0, 2**32, 200_000, dtype=np.uint64).astype(np.uint32),
                           np.array([0, 1, 0x007FFFFF, 0x00800000, 0x7F7FFFFF, 0x80000000, 0x3DCCCCCD], np.uint32)])
    x = bits.view(np.float32)
    x = x[np.isfinite(x)]
    back = dec_array(json.loads(enc_array(x)))
    assert back.dtype == np.float32 and np.array_equal(back.view(np.uint32), x.view(np.uint32))
    y = np.array([1.5, np.inf, -np.inf, np.nan, 1e-300], np.float64)
    z = dec_array(json.loads(enc_array(y)))
    assert z.dtype == np.float64 and np.array_equal(z, y, equal_nan=True)


def test_nonfinite_values_and_depth_quantisation(episode, tmp_path: Path) -> None:
    meta, occ, frames = episode
    f0, f1 = frames[0], frames[1]
    vel = f1.ped_vel.copy()
    vel[0, 0] = np.nan
    depth = {c: d.copy() for c, d in f1.depth.items()}
    depth["left"][0, :4] = [1.0004999, 1.0005001, 70.0, -1.0]  # round down, round up, saturate, invalid
    f1 = replace(f1, d_o=float("inf"), ped_vel=vel, reward_terms={**f1.reward_terms, "near": float("-inf")},
                 depth=depth)
    with EpisodeWriter(tmp_path / "x.mcap", meta, occ) as w:
        w.add(f0)
        w.add(f1)
    got = list(read_episode(tmp_path / "x.mcap")[2])
    assert got[1].d_o == float("inf") and got[1].reward_terms["near"] == float("-inf")
    assert np.isnan(got[1].ped_vel[0, 0]) and np.array_equal(got[1].ped_vel[1:], vel[1:])
    assert got[1].depth["left"][0, :4].tolist() == pytest.approx([1.0, 1.001, 65.535, 0.0])
    assert_frames_equal(f0, got[0], depth_tol=DEPTH_TOL_M)
