"""Shared fixtures: tiny driven episodes, their MCAP logs and their exported LeRobot dataset (recorder, pretrain).

Everything is session-scoped and small (64 x 48 cameras, 2 s episodes at 10 Hz = 21 frames) so that the whole
export/doctor suite stays well under a minute and a half on two cores.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("HF_HUB_OFFLINE", "1")

from recorder.drive import drive_episode  # noqa: E402
from recorder.schema import EpisodeMeta, Frame  # noqa: E402
from sim.env import CameraConfig, SimConfig  # noqa: E402

TINY_W, TINY_H = 64, 48
TINY_SEEDS = (0, 1)
REPO_ID = "icrowdnav/tiny"


@pytest.fixture(scope="session", autouse=True)
def _sb3_logs_in_the_session_tmp(tmp_path_factory) -> None:
    """Tests that build an SB3 model without a logger of their own: SB3 makes a folder for its default logger in the
    temp dir at every ``learn`` (``SB3_LOGDIR`` names one instead); keep them inside the session's tmp dir."""
    os.environ["SB3_LOGDIR"] = str(tmp_path_factory.mktemp("sb3_logs"))


@dataclass
class MemEpisode:
    """An in-memory Episode-like object (``.meta``, ``.occupancy``, ``.frames()``) with a source name."""

    meta: EpisodeMeta
    occupancy: np.ndarray
    frame_list: list[Frame]
    source: str = ""

    def frames(self) -> Iterator[Frame]:
        return iter(self.frame_list)

    def with_frames(self, frames: list[Frame], source: str | None = None) -> MemEpisode:
        """A copy with other frames (and optionally another source name)."""
        return MemEpisode(self.meta, self.occupancy, frames, self.source if source is None else source)


def tiny_sim_config() -> SimConfig:
    """The tiny world of these tests: a hallway at 0.2 ped/m² (detections in most frames), 64 x 48 cameras, 2 s
    episodes at dt = 0.1 s (21 frames)."""
    return SimConfig(scene="hallway", density=0.2, max_episode_s=2.0, dt_s=0.1,
                     camera=CameraConfig(width_px=TINY_W, height_px=TINY_H))


@pytest.fixture(scope="session")
def tiny_episodes() -> list[MemEpisode]:
    """Two driven episodes (seeds 0 and 1), frames materialised."""
    out = []
    for seed in TINY_SEEDS:
        ep = drive_episode(tiny_sim_config(), seed)
        out.append(MemEpisode(ep.meta, ep.occupancy, list(ep.frames), f"<seed {seed}>"))
    assert sum(f.pose_mask.any() for e in out for f in e.frame_list) > 10, "the fixture should see people"
    return out


@pytest.fixture(scope="session")
def tiny_mcap_dir(tmp_path_factory: pytest.TempPathFactory, tiny_episodes: list[MemEpisode]) -> Path:
    """The two episodes logged as complete MCAP files (``recorder.mcap.writer.EpisodeWriter``)."""
    from recorder.mcap.writer import EpisodeWriter

    raw = tmp_path_factory.mktemp("raw")
    for k, ep in enumerate(tiny_episodes):
        with EpisodeWriter(raw / f"ep_{k:03d}.mcap", ep.meta, ep.occupancy) as w:
            for fr in ep.frame_list:
                w.add(fr)
    return raw


@dataclass
class TinyDataset:
    """The exported tiny dataset: where it is, what the export returned, and the episodes it came from."""

    root: Path
    counts: dict
    episodes: list[MemEpisode]
    repo_id: str = REPO_ID


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory: pytest.TempPathFactory, tiny_mcap_dir: Path,
                 tiny_episodes: list[MemEpisode]) -> TinyDataset:
    """``export_run`` of the MCAP directory: the real path from logs to a validated LeRobot dataset.

    Tests must not modify it: copy it first (see ``dataset_copy``).
    """
    from recorder.export import export_run

    out = tmp_path_factory.mktemp("datasets") / "tiny"
    counts = export_run(tiny_mcap_dir, out, REPO_ID, progress=False)
    return TinyDataset(out, counts, tiny_episodes)


@pytest.fixture
def dataset_copy(tmp_path: Path, tiny_dataset: TinyDataset) -> Path:
    """A private copy of the tiny dataset, free to damage."""
    import shutil

    dst = tmp_path / "copy"
    shutil.copytree(tiny_dataset.root, dst)
    return dst


def _frame_with(frame: Frame, **changes) -> Frame:
    """A copy of ``frame`` with some fields replaced (dicts copied, so the original stays intact)."""
    base = {"rgb": dict(frame.rgb), "depth": dict(frame.depth)}
    base.update(changes)
    return replace(frame, **base)


@pytest.fixture(scope="session")
def frame_with():
    """``frame_with(frame, **changes)``: a modified copy of a frame (the original stays intact)."""
    return _frame_with
