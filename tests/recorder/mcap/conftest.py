"""Fixtures of the recorder.mcap tests: the tiny episode of seed 1, in memory and recorded (once per module)."""

from __future__ import annotations

from pathlib import Path

import pytest

from recorder.drive import drive_episode
from recorder.mcap.writer import EpisodeWriter
from tests.recorder.helpers_mcap import tiny_config
from tests.recorder.mcap.common import CHUNK


@pytest.fixture(scope="module")
def episode():
    """The tiny episode of seed 1 in memory: (meta, occupancy, frames)."""
    ep = drive_episode(tiny_config(), 1)
    return ep.meta, ep.occupancy, list(ep.frames)


@pytest.fixture(scope="module")
def recorded(episode, tmp_path_factory) -> Path:
    meta, occ, frames = episode
    path = tmp_path_factory.mktemp("rec") / "ep.mcap"
    with EpisodeWriter(path, meta, occ, chunk_size=CHUNK) as w:
        for fr in frames:
            w.add(fr)
    return path
