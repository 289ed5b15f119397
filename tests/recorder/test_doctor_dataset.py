"""The dataset doctor: silent on a good export, one line naming the file for each kind of damage."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from recorder.dataset_info import DatasetFormatError, read_dataset_info
from recorder.doctor_dataset import check_dataset, main, require_sound_dataset
from recorder.schema import depth_to_mm

DATA = "data/chunk-000/file-000.parquet"  # episode 0 (the export writes one data file per episode)
DATA1 = "data/chunk-000/file-001.parquet"  # episode 1
EPISODES = "meta/episodes/chunk-000/file-000.parquet"
VIDEO = "videos/observation.images.right/chunk-000/file-000.mp4"


def _lines_naming(problems: list[str], root: Path, rel: str) -> list[str]:
    return [p for p in problems if p.startswith(f"{root / rel}: ")]


def test_good_dataset_passes(tiny_dataset, capsys):
    assert check_dataset(tiny_dataset.root) == []
    assert main([str(tiny_dataset.root)]) == 0
    assert "ok:" in capsys.readouterr().out


def test_missing_directory_is_one_problem(tmp_path):
    assert check_dataset(tmp_path / "nope") == [f"{tmp_path / 'nope'}: dataset directory does not exist"]


@pytest.mark.parametrize("rel", [DATA, EPISODES])
def test_truncated_parquet_footer_is_named(dataset_copy, rel, capsys):
    p = dataset_copy / rel
    data = p.read_bytes()
    p.write_bytes(data[: len(data) - 200])  # cut into the footer, as a killed writer leaves it
    problems = check_dataset(dataset_copy)
    named = _lines_naming(problems, dataset_copy, rel)
    assert named and "footer" in named[0], problems
    assert main([str(dataset_copy)]) == 1
    out = capsys.readouterr().out
    assert str(p) in out


def test_episode_index_gap_is_named(dataset_copy):
    p = dataset_copy / EPISODES
    table = pq.read_table(p)
    table = table.set_column(table.column_names.index("episode_index"), "episode_index", pa.array([0, 2]))
    pq.write_table(table, p)
    problems = check_dataset(dataset_copy)
    gap = _lines_naming(problems, dataset_copy, EPISODES)
    assert gap and "episode index gap: expected episode_index 1 next, got 2" in gap[0], problems


def test_removed_episode_metadata_row_is_found(dataset_copy):
    p = dataset_copy / EPISODES
    table = pq.read_table(p)
    pq.write_table(table.slice(0, 1), p)  # the last episode's metadata row is gone
    problems = check_dataset(dataset_copy)
    assert any("total_episodes 2 but meta/episodes holds 1" in line for line in
               _lines_naming(problems, dataset_copy, "meta/info.json")), problems
    assert any("rows of episode 1, which meta/episodes does not list" in line for line in
               _lines_naming(problems, dataset_copy, DATA1)), problems


def test_removed_data_rows_are_found(dataset_copy, tiny_dataset):
    p = dataset_copy / DATA1
    table = pq.read_table(p)
    ep = table["episode_index"].to_numpy()
    pq.write_table(table.filter(pa.array(ep == 0)), p)  # the rows of episode 1 are gone
    problems = check_dataset(dataset_copy)
    named = _lines_naming(problems, dataset_copy, DATA1)
    assert any("episode 1: no rows" in line for line in named), problems
    n0 = len(tiny_dataset.episodes[0].frame_list) - 1  # a dataset episode: its recording but the terminal frame
    assert any(f"data files hold {n0} rows" in line for line in problems), problems


def test_wrong_timestamps_are_found(dataset_copy, tiny_dataset):
    p = dataset_copy / DATA1
    table = pq.read_table(p)
    ts = table["timestamp"].to_numpy().copy()
    ts[4] += 0.05  # episode 1, frame 4
    table = table.set_column(table.column_names.index("timestamp"), "timestamp", pa.array(ts, pa.float32()))
    pq.write_table(table, p)
    problems = check_dataset(dataset_copy, videos=False, stats=False)
    assert any("timestamp" in line and "frame_index 4" in line for line in
               _lines_naming(problems, dataset_copy, DATA1)), problems


def test_truncated_video_is_named(dataset_copy):
    p = dataset_copy / VIDEO
    data = p.read_bytes()
    p.write_bytes(data[: len(data) * 2 // 3])
    problems = check_dataset(dataset_copy, stats=False)
    named = _lines_naming(problems, dataset_copy, VIDEO)
    assert named, problems
    assert any("not decodable" in line or "does not decode" in line for line in named), problems


def test_garbage_and_missing_videos_are_named(dataset_copy):
    p = dataset_copy / VIDEO
    p.write_bytes(b"\x00" * 4096)
    other = dataset_copy / VIDEO.replace("right", "left")
    other.unlink()
    problems = check_dataset(dataset_copy, stats=False)
    assert _lines_naming(problems, dataset_copy, VIDEO), problems
    assert any("is missing" in line for line in _lines_naming(problems, dataset_copy, VIDEO.replace("right", "left")))


def test_stats_that_do_not_match_are_named(dataset_copy):
    p = dataset_copy / "meta/stats.json"
    stats = json.loads(p.read_text())
    stats["observation.state"]["max"][2] += 0.25
    stats["privileged.ped_state"]["mean"][0] *= 1.5
    stats["action"]["count"] = [7]
    p.write_text(json.dumps(stats))
    problems = check_dataset(dataset_copy, videos=False)
    named = _lines_naming(problems, dataset_copy, "meta/stats.json")
    assert any("'observation.state' max does not match the data" in line for line in named), problems
    assert any("'privileged.ped_state' mean does not match the data" in line for line in named), problems
    assert any("'action' count [7]" in line for line in named), problems
    assert len(problems) == 3


def test_recomputed_stats_follow_lerobots_axes(tiny_dataset):
    stats = json.loads((tiny_dataset.root / "meta/stats.json").read_text())
    # the dataset's frames: every recorded observation but each episode's terminal one, depth in uint16 mm
    depth = np.stack([depth_to_mm(f.depth["left"]) for e in tiny_dataset.episodes for f in e.frame_list[:-1]])
    # lerobot reduces every axis but the last: one value per image column
    assert len(stats["observation.depth.left"]["min"]) == depth.shape[-1]
    np.testing.assert_array_equal(stats["observation.depth.left"]["max"], depth.reshape(-1, 64).max(0))


def test_icrowdnav_meta_files_are_checked(dataset_copy):
    p = dataset_copy / "meta/icrowdnav_episodes.jsonl"
    p.write_text(p.read_text().splitlines()[0] + "\n")
    (dataset_copy / "meta/icrowdnav.json").unlink()  # an optional extra: lerobot's dataset tools drop it
    info_path = dataset_copy / "meta/info.json"
    info = json.loads(info_path.read_text())
    del info["features"]["observation.images.right"]["info"]["camera"]  # the calibration is not optional
    info_path.write_text(json.dumps(info, indent=4))
    problems = check_dataset(dataset_copy, videos=False, stats=False)
    assert any("1 row(s), expected 2" in line for line in
               _lines_naming(problems, dataset_copy, "meta/icrowdnav_episodes.jsonl")), problems
    assert not _lines_naming(problems, dataset_copy, "meta/icrowdnav.json"), problems
    assert any("features.observation.images.right.info.camera" in line
               for line in _lines_naming(problems, dataset_copy, "meta/info.json")), problems
    assert len(problems) == 2, problems
    assert check_dataset(dataset_copy, videos=False, stats=False, icrowdnav=False) == []


def test_a_format_1_dataset_is_refused_by_name(dataset_copy):
    info_path = dataset_copy / "meta/info.json"
    info = json.loads(info_path.read_text())
    del info["features"]["action"]["info"]  # as an export before format 2 wrote it
    info_path.write_text(json.dumps(info, indent=4))
    with pytest.raises(DatasetFormatError) as ei:
        read_dataset_info(dataset_copy)
    msg = str(ei.value)
    for words in (str(info_path), "features.action.info.icrowdnav_format", "expected 2", "led to frame t",
                  "--overwrite"):
        assert words in msg, (words, msg)
    with pytest.raises(DatasetFormatError):
        require_sound_dataset(dataset_copy)


def test_info_totals_must_match(dataset_copy, tiny_dataset):
    p = dataset_copy / "meta/info.json"
    info = json.loads(p.read_text())
    info["total_frames"] += 5
    p.write_text(json.dumps(info))
    problems = check_dataset(dataset_copy, videos=False, stats=False)
    want = f"total_frames {tiny_dataset.counts['frames'] + 5}"
    assert any(want in line for line in _lines_naming(problems, dataset_copy, "meta/info.json")), problems


def test_deleted_data_file_is_named_as_missing(dataset_copy):
    (dataset_copy / DATA).unlink()
    problems = check_dataset(dataset_copy, videos=False, stats=False)
    named = _lines_naming(problems, dataset_copy, DATA)
    assert named and "missing: meta/episodes places episode 0 in this data file" in named[0], problems


def test_missing_video_is_named_without_decoding(dataset_copy):
    other = dataset_copy / VIDEO.replace("right", "left")
    other.unlink()
    (dataset_copy / VIDEO).write_bytes(b"")
    problems = check_dataset(dataset_copy, videos=False, stats=False)
    assert any("is missing" in line for line in _lines_naming(problems, dataset_copy, VIDEO.replace("right", "left")))
    assert any("empty (0 bytes)" in line for line in _lines_naming(problems, dataset_copy, VIDEO)), problems


def test_require_sound_dataset_raises_one_named_error(dataset_copy, tiny_dataset):
    """The cheap checks as one error (what pretrain / train run before lerobot opens a dataset)."""
    from pipeline.core.errors import CorruptArtifactError, InputMissingError
    from recorder.doctor_dataset import require_sound_dataset

    require_sound_dataset(tiny_dataset.root)  # a sound dataset passes
    p = dataset_copy / DATA
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(CorruptArtifactError, match=rf"{p}: not a readable parquet file \(footer missing"):
        require_sound_dataset(dataset_copy)
    p.unlink()
    with pytest.raises(InputMissingError, match=rf"damaged dataset {dataset_copy}: {p}: missing"):
        require_sound_dataset(dataset_copy)
