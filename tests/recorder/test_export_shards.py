"""The export in parallel shards merged by lerobot's ``aggregate_datasets``: the same dataset as the serial export,
frame for frame (data and decoded video), with the same metadata, stats up to float rounding and the same named
errors; blocks are contiguous and balanced."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from recorder.doctor_dataset import check_dataset
from recorder.export import ICROWDNAV_EPISODES, ICROWDNAV_META, export_dataset, shard_blocks, write_dataset
from recorder.features import FeatureError


@pytest.fixture(scope="module")
def five_mcaps(tmp_path_factory, tiny_mcap_dir) -> list[Path]:
    """Five complete MCAP episodes: the two tiny recordings, repeated under new names (order ep_000 .. ep_004)."""
    raw = tmp_path_factory.mktemp("raw5")
    src = sorted(tiny_mcap_dir.glob("*.mcap"))
    for k in range(5):
        shutil.copy(src[k % 2], raw / f"ep_{k:03d}.mcap")
    return sorted(raw.glob("*.mcap"))


@pytest.fixture(scope="module")
def serial_and_sharded(tmp_path_factory, five_mcaps) -> tuple[Path, Path, dict]:
    out = tmp_path_factory.mktemp("shards")
    write_dataset(five_mcaps, out / "serial", "icrowdnav/shards", progress=False)
    counts = write_dataset(five_mcaps, out / "sharded", "icrowdnav/shards", progress=False, shards=3,
                           min_shard_frames=0)
    return out / "serial", out / "sharded", counts


def test_shard_blocks_are_contiguous_balanced_and_never_empty():
    assert shard_blocks([1] * 6, 3) == [(0, 2), (2, 4), (4, 6)]
    assert shard_blocks([1] * 5, 2) == [(0, 3), (3, 5)]
    assert shard_blocks([10, 1, 1, 1, 1], 2) == [(0, 1), (1, 5)]  # by size, not count
    assert shard_blocks([1, 1], 8) == [(0, 1), (1, 2)]  # never more blocks than episodes
    assert shard_blocks([1] * 4, 1) == [(0, 4)]
    for sizes in ([3, 1, 4, 1, 5, 9, 2, 6], [1] * 11, [0, 0, 0]):
        for k in range(1, 6):
            blocks = shard_blocks(sizes, k)
            assert blocks[0][0] == 0 and blocks[-1][1] == len(sizes) and len(blocks) <= k
            assert all(a < b for a, b in blocks) and all(b == c for (_, b), (c, _) in zip(blocks, blocks[1:], strict=False))


def test_small_recordings_are_exported_in_fewer_shards(tmp_path, five_mcaps):
    """A shard's fixed cost outweighs its gain below min_shard_frames frames per shard: fewer shards, down to one."""
    from recorder.mcap.reader import count_frames

    total = sum(count_frames(p) for p in five_mcaps)
    one = write_dataset(five_mcaps, tmp_path / "one", "icrowdnav/x", progress=False, shards=3,
                        min_shard_frames=total + 1)
    assert "shards" not in one  # the one-process export
    two = write_dataset(five_mcaps, tmp_path / "two", "icrowdnav/x", progress=False, shards=3,
                        min_shard_frames=total // 2)
    assert two["shards"] == 2


def test_sharded_export_passes_the_doctor_and_counts(serial_and_sharded):
    serial, sharded, counts = serial_and_sharded
    assert counts["shards"] == 3 and counts["episodes"] == 5
    assert check_dataset(sharded) == []
    assert not (sharded / ".shards").exists()  # the shards were merged and removed
    assert sorted(p.name for p in sharded.iterdir()) == sorted(p.name for p in serial.iterdir())


def test_sharded_export_equals_the_serial_export_frame_for_frame(serial_and_sharded):
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    serial, sharded, _ = serial_and_sharded
    a = LeRobotDataset("icrowdnav/shards", root=serial, video_backend="pyav")
    b = LeRobotDataset("icrowdnav/shards", root=sharded, video_backend="pyav")
    assert (a.num_episodes, len(a)) == (b.num_episodes, len(b)) == (5, len(a))
    for i in range(len(a)):
        x, y = a[i], b[i]
        assert x.keys() == y.keys()
        for key, value in x.items():
            if isinstance(value, torch.Tensor):  # decoded video frames included: the mp4s are not re-encoded
                assert torch.equal(value, y[key]), (i, key)
            else:
                assert value == y[key], (i, key)


def test_sharded_export_keeps_the_metadata(serial_and_sharded):
    import pandas as pd
    import pyarrow.parquet as pq

    serial, sharded, _ = serial_and_sharded
    info_a, info_b = (json.loads((r / "meta" / "info.json").read_text()) for r in (serial, sharded))
    assert info_a == info_b  # features with our ``info``, totals, splits, paths
    for name in (ICROWDNAV_META, ICROWDNAV_EPISODES):
        assert (serial / name).read_text() == (sharded / name).read_text()
    ep_a, ep_b = (pd.read_parquet(r / "meta" / "episodes") for r in (serial, sharded))
    for col in ("episode_index", "length", "dataset_from_index", "dataset_to_index", "data/file_index",
                "tasks"):
        assert ep_a[col].astype(str).tolist() == ep_b[col].astype(str).tolist(), col
    assert list(ep_a.columns) == list(ep_b.columns)
    for col in [c for c in ep_a.columns if c.endswith("from_timestamp") or c.endswith("to_timestamp")]:
        np.testing.assert_allclose(ep_a[col], ep_b[col], atol=1e-6, err_msg=col)
    tab_a, tab_b = (pq.read_table(r / "meta" / "episodes") for r in (serial, sharded))
    for col in [c for c in ep_a.columns if c.startswith("stats/")]:  # per-episode stats, index columns included
        np.testing.assert_allclose(np.asarray(tab_a.column(col).to_pylist(), float),
                                   np.asarray(tab_b.column(col).to_pylist(), float), rtol=1e-6, atol=1e-9,
                                   err_msg=col)
    stats_a, stats_b = (json.loads((r / "meta" / "stats.json").read_text()) for r in (serial, sharded))
    assert stats_a.keys() == stats_b.keys()
    for feature, by_stat in stats_a.items():
        assert by_stat.keys() == stats_b[feature].keys(), feature
        for stat, value in by_stat.items():  # lerobot's weighted combination, over episodes vs over shards
            np.testing.assert_allclose(np.asarray(value, float), np.asarray(stats_b[feature][stat], float),
                                       rtol=1e-5, atol=1e-6, err_msg=f"{feature}.{stat}")


def test_a_bad_episode_in_a_later_shard_is_the_serial_exports_error(tmp_path, five_mcaps, tiny_episodes):
    """Shards check every episode against the dataset's first one, as the serial export does: one named error,
    nothing published."""
    from dataclasses import replace

    from recorder.mcap.writer import EpisodeWriter

    ep = tiny_episodes[0]
    cams = {c: dict(v) for c, v in ep.meta.cameras.items()}
    cams["left"]["hfov_deg"] = 90.0  # another camera model
    bad = tmp_path / "raw" / "ep_003.mcap"
    bad.parent.mkdir()
    with EpisodeWriter(bad, replace(ep.meta, cameras=cams), ep.occupancy) as w:
        for fr in ep.frame_list:
            w.add(fr)
    files = [*five_mcaps[:3], bad, five_mcaps[4]]
    errors = []
    for shards in (1, 3):
        with pytest.raises(FeatureError, match=r"ep_003\.mcap.*cameras\[left\]\[hfov_deg\]") as e:
            export_dataset(files, tmp_path / f"out{shards}", "icrowdnav/x", progress=False, shards=shards,
                           min_shard_frames=0)
        errors.append(str(e.value))
        assert not (tmp_path / f"out{shards}").exists()
    assert errors[0] == errors[1]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging or shard dir left


@pytest.mark.slow
def test_export_shards_on_ray_equal_the_local_pool(tmp_path, five_mcaps, serial_and_sharded):
    """The shards as Ray tasks (a Ray instance on this machine): the same data files, video files, metadata and
    stats as the local pool's sharded export."""
    pytest.importorskip("ray")
    import pyarrow.parquet as pq

    from pipeline.core.executor import Executor

    _, local, _ = serial_and_sharded
    out = tmp_path / "ray"
    counts = write_dataset(five_mcaps, out, "icrowdnav/shards", progress=False, shards=3,
                           executor=Executor("ray", "", tmp_path), min_shard_frames=0)
    assert counts["shards"] == 3 and check_dataset(out) == []
    files = sorted(p.relative_to(local) for p in local.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file())
    for rel in files:
        if rel.suffix == ".parquet":
            assert pq.read_table(out / rel).equals(pq.read_table(local / rel)), rel
        else:  # mp4 (concatenated, not re-encoded), json, jsonl
            assert (out / rel).read_bytes() == (local / rel).read_bytes(), rel
