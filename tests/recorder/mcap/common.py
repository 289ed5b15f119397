"""Shared by the tests of recorder.mcap: constants, frame comparison, chunk layout of a file."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from recorder.mcap.layout import frame_topics
from recorder.schema import Frame

REPO = Path(__file__).resolve().parents[3]
CHUNK = 60_000  # ~2 tiny frames per chunk: several chunks per episode
MSGS_PER_FRAME = len(frame_topics())  # 16; frame 0 has the occupancy grid too
DEPTH_TOL_M = 0.5e-3 + 1e-6  # mm quantisation (+ float32 rounding)


def sha256(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def assert_frames_equal(a: Frame, b: Frame, depth_tol: float = 0.0) -> None:
    """Field by field: arrays exact (dtype and shape too), depth within ``depth_tol`` m."""
    for name, va in a.__dict__.items():
        vb = getattr(b, name)
        if name in ("rgb", "depth"):
            assert set(va) == set(vb), name
            for cam in va:
                x, y = np.asarray(va[cam]), np.asarray(vb[cam])
                assert x.shape == y.shape, (name, cam)
                if name == "rgb":
                    assert y.dtype == np.uint8 and np.array_equal(x, y), (name, cam)
                else:
                    assert y.dtype == np.float32
                    assert np.max(np.abs(x.astype(np.float64) - y)) <= depth_tol, (name, cam)
                    assert np.array_equal(x == 0, y == 0), "invalid depth must stay 0 and valid depth non-zero"
        elif isinstance(va, np.ndarray):
            assert isinstance(vb, np.ndarray) and va.dtype == vb.dtype and va.shape == vb.shape, name
            assert np.array_equal(va, vb, equal_nan=va.dtype.kind == "f"), name
        elif isinstance(va, float) and np.isnan(va):
            assert np.isnan(vb), name
        else:
            assert va == vb, (name, va, vb)


def chunk_layout(path: Path) -> list[tuple[int, int, int, int]]:
    """(start offset, record length, first log time, last log time) of each chunk, from the summary."""
    with open(path, "rb") as f:
        summ = make_reader(f).get_summary()
    return sorted((c.chunk_start_offset, c.chunk_length, c.message_start_time, c.message_end_time)
                  for c in summ.chunk_indexes)
