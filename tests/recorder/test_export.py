"""The LeRobot export: round trip through stock lerobot, crash consistency, named feature errors, no overwrite."""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import signal
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.errors import ConfigError, CorruptArtifactError, InputMissingError, OutputExistsError
from recorder.doctor_dataset import check_dataset
from recorder.export import ICROWDNAV_EPISODES, ICROWDNAV_META, export_dataset, export_run
from recorder.features import (
    PED_STATE_COLUMNS,
    ExportSpec,
    FeatureError,
    LocalMapSpec,
    frame_to_features,
    local_occupancy,
    unflatten_poses,
)
from recorder.schema import depth_from_mm, depth_to_mm


def _tree_digest(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _leftovers(out: Path) -> list[str]:
    return sorted(p.name for p in out.parent.glob(f".{out.name}.*"))


# ---------------------------------------------------------------------------------------------- local occupancy
def test_local_occupancy_layout_rows_forward_cols_left_to_right():
    res, origin = 0.05, (-10.0, -10.0)
    grid = np.zeros((600, 600), bool)  # world -10..20 m both ways; cell [i, j] centre = origin + (j, i) * res

    def cell(v: float, o: float) -> int:
        return round((v - o) / res)

    # a 0.2 m block centred near world (4.0, 7.0)
    grid[cell(6.9, origin[1]):cell(7.1, origin[1]), cell(3.9, origin[0]):cell(4.1, origin[0])] = True
    spec = LocalMapSpec()
    assert spec.shape == (100, 100)
    # robot at (5, 5) facing +y: the block is 2 m ahead and 1 m to the robot's left
    out = local_occupancy(grid, origin, res, np.array([5.0, 5.0, math.pi / 2]), spec)
    rows, cols = np.nonzero(out)
    # forward x = 8 - (row + 0.5) * 0.1 = 2 -> row 59.5; lateral y = 5 - (col + 0.5) * 0.1 = 1 -> col 39.5
    assert 58 <= rows.min() and rows.max() <= 61, (rows.min(), rows.max())
    assert 38 <= cols.min() and cols.max() <= 41, (cols.min(), cols.max())
    assert out[59:61, 39:41].all()
    # robot at (4, 8) facing -y: the block is 1 m ahead, straight on -> row 69.5, col 49.5
    out2 = local_occupancy(grid, origin, res, np.array([4.0, 8.0, -math.pi / 2]), spec)
    r2, c2 = np.nonzero(out2)
    assert 68 <= r2.min() and r2.max() <= 71 and 48 <= c2.min() and c2.max() <= 51, (r2, c2)
    # robot at (6, 7) facing +x: the block is 2 m behind -> x = -2 is row 99.5; lateral 0 -> col 49.5
    out3 = local_occupancy(grid, origin, res, np.array([6.0, 7.0, 0.0]), spec)
    r3, c3 = np.nonzero(out3)
    assert r3.min() >= 97 and 48 <= c3.min() and c3.max() <= 51, (r3, c3)
    # outside the world grid counts as occupied
    out4 = local_occupancy(grid, origin, res, np.array([-9.0, 5.0, 0.0]), spec)
    assert not out4[79, 49]  # the robot's own (free) cell
    assert out4[99].all()  # 1.95 m behind the robot at x = -9 is x < -10: outside the grid
    assert not out4[:85].any()


# ---------------------------------------------------------------------------------------------- round trip
def _expected_privileged(fr, n_max: int):
    n = len(fr.ped_pos)
    state = np.zeros((n_max, len(PED_STATE_COLUMNS)), np.float32)
    state[:n, 0:2], state[:n, 2:4], state[:n, 4] = fr.ped_pos, fr.ped_vel, fr.ped_radius
    state[:n, 5], state[:n, 6], state[:n, 7] = fr.ped_yaw[:, 0], fr.ped_yaw[:, 2], 1.0
    kp = np.zeros((n_max, 17, 3), np.float32)
    kp[:n] = fr.ped_keypoints
    intent = np.zeros((n_max, 2), np.float32)
    intent[:n] = fr.ped_intent_xy
    return state, kp, intent


def test_stock_lerobot_loads_export_and_frames_match_the_recording(tiny_dataset):
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(tiny_dataset.repo_id, root=tiny_dataset.root, video_backend="pyav")
    episodes = tiny_dataset.episodes
    assert ds.num_episodes == len(episodes) == tiny_dataset.counts["episodes"]
    # LeRobot's convention: a dataset episode is its recording but the terminal observation
    assert len(ds) == sum(len(e.frame_list) - 1 for e in episodes) == tiny_dataset.counts["frames"]
    assert ds.fps == 10
    spec = ExportSpec.from_meta(episodes[0].meta)
    i = 0
    for e, ep in enumerate(episodes):
        for f, (fr, nxt) in enumerate(zip(ep.frame_list[:-1], ep.frame_list[1:], strict=True)):
            item = ds[i]
            i += 1
            assert int(item["episode_index"]) == e and int(item["frame_index"]) == f
            assert float(item["timestamp"]) == pytest.approx(f / 10, abs=1e-6)
            assert item["task"] == "navigate to the goal through the crowd"
            exact = {"observation.state": fr.state, "observation.odom": fr.odom, "observation.goal": fr.goal_xy,
                     "action": nxt.action, "observation.poses": fr.poses.reshape(-1),
                     "observation.pose_mask": fr.pose_mask.astype(np.float32).reshape(-1),
                     "observation.pose_conf": fr.pose_conf.reshape(-1), "privileged.pose_track": fr.pose_track}
            for key, want in exact.items():
                got = item[key].numpy()
                assert got.dtype == np.asarray(want).dtype, key
                np.testing.assert_array_equal(got, want, err_msg=key)
            state, kp, intent = _expected_privileged(fr, spec.n_max)
            np.testing.assert_array_equal(item["privileged.ped_state"].numpy(), state)
            np.testing.assert_array_equal(item["privileged.ped_keypoints"].numpy(), kp)
            np.testing.assert_array_equal(item["privileged.ped_intent"].numpy(), intent)
            assert float(item["next.reward"]) == np.float32(nxt.reward)
            assert bool(item["next.done"]) == nxt.done
            assert float(item["privileged.d_o"]) == np.float32(fr.d_o)
            occ = local_occupancy(ep.occupancy, ep.meta.occupancy_origin_xy, ep.meta.occupancy_resolution_m,
                                  fr.odom, spec.local_map)
            np.testing.assert_array_equal(item["privileged.local_occupancy"].numpy(), occ)
            for cam in ("left", "right"):
                depth = item[f"observation.depth.{cam}"].numpy()  # uint16 mm; lerobot's torch format: int64
                assert depth.shape == (48, 64) and depth.dtype.kind in "iu"
                # the MCAP log stores whole millimetres: the depth is exact up to that quantisation
                np.testing.assert_array_equal(depth, depth_to_mm(fr.depth[cam]))
                np.testing.assert_allclose(depth_from_mm(depth), fr.depth[cam], rtol=0, atol=0.5e-3 + 1e-6)
                img = item[f"observation.images.{cam}"]
                assert img.shape == (3, 48, 64) and img.dtype == torch.float32
                rgb = img.numpy().transpose(1, 2, 0) * 255.0
                mad = np.abs(rgb - fr.rgb[cam].astype(np.float32)).mean()
                assert mad < 8.0, f"{cam} frame {e}/{f}: mean abs diff {mad:.2f} of 255"
        assert bool(item["next.done"])  # the last frame of each episode ends it


LEROBOT_INDEX_FEATURES = ("timestamp", "frame_index", "episode_index", "index", "task_index")


def _documented_reward_terms() -> list[str]:
    """The column order of ``next.reward_terms`` as the feature table in ``recorder.features``' docstring states it."""
    import recorder.features

    rows = [line for line in recorder.features.__doc__.splitlines() if line.startswith("next.reward_terms ")]
    assert len(rows) == 1, rows
    return [t.strip() for t in rows[0].split("float32", 1)[1].split(",")]


def test_every_exported_feature_reads_back_as_in_the_source_mcap(tmp_path, tiny_mcap_dir, frame_with):
    """Exports a re-logged tiny episode and compares every feature of ``meta/info.json``, read back through stock
    lerobot, with the frames of the source MCAP: nothing exported may go unchecked (the key sets must match)."""
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from recorder.mcap.reader import read_episode
    from recorder.mcap.writer import EpisodeWriter

    terms_order = _documented_reward_terms()
    assert terms_order == ["success", "collision", "near", "progress", "spin", "total"]
    # the recorded episode 0 with a labeller's command on every frame (-> action.teacher) and every reward term
    # distinct and non-zero: a real 2 s episode has success = collision = spin = 0 throughout, so a swap of two of
    # those columns would go unseen. Frame 0 keeps only one term: the missing ones are exported as 0.
    meta, occ, frames = read_episode(tiny_mcap_dir / "ep_000.mcap")
    raw = tmp_path / "raw"
    raw.mkdir()
    with EpisodeWriter(raw / "ep_000.mcap", meta, occ) as w:
        for f, fr in enumerate(frames):
            terms = {t: (j + 1) * (-1) ** j + f / 64 for j, t in enumerate(terms_order)} if f else {"near": -0.25}
            w.add(frame_with(fr, reward_terms=terms, label=np.array([0.01 * f, -0.02 * f - 0.5], np.float32)))
    out = tmp_path / "ds"
    export_run(raw, out, "icrowdnav/every", progress=False)

    info = json.loads((out / "meta/info.json").read_text())
    features = info["features"]
    assert features["next.reward_terms"]["names"] == terms_order
    assert json.loads((out / ICROWDNAV_META).read_text())["spec"]["reward_terms"] == terms_order
    meta, occ, frames = read_episode(raw / "ep_000.mcap")  # the source, as the export read it
    frames = list(frames)
    assert {tuple(fr.reward_terms) for fr in frames[1:]} == {tuple(terms_order)} and frames[0].reward_terms
    spec = ExportSpec.from_meta(meta)
    ds = LeRobotDataset("icrowdnav/every", root=out, video_backend="pyav")
    assert len(ds) == len(frames) - 1 == 20  # the terminal observation is not a frame
    checked: set[str] = set()
    for f, (fr, nxt) in enumerate(zip(frames[:-1], frames[1:], strict=True)):
        item = ds[f]
        state, kp, intent = _expected_privileged(fr, spec.n_max)
        want = {
            "observation.state": fr.state, "observation.odom": fr.odom, "observation.goal": fr.goal_xy,
            "observation.poses": fr.poses.reshape(-1), "observation.pose_mask": fr.pose_mask.astype(np.float32).ravel(),
            "observation.pose_conf": fr.pose_conf.reshape(-1), "privileged.pose_track": fr.pose_track,
            "action": nxt.action, "action.teacher": fr.label,  # the command chosen from observation f
            "next.reward": np.float32(nxt.reward),
            "next.reward_terms": np.array([nxt.reward_terms.get(t, 0.0) for t in features["next.reward_terms"]["names"]],
                                          np.float32),
            "next.done": np.bool_(nxt.done), "privileged.d_o": np.float32(fr.d_o),
            "privileged.ped_state": state, "privileged.ped_keypoints": kp, "privileged.ped_intent": intent,
            "privileged.local_occupancy": local_occupancy(occ, meta.occupancy_origin_xy, meta.occupancy_resolution_m,
                                                          fr.odom, spec.local_map),
            "timestamp": np.float32(f / 10), "frame_index": np.int64(f), "episode_index": np.int64(0),
            "index": np.int64(f), "task_index": np.int64(0),
        }
        for key, value in want.items():
            got = item[key].numpy()
            value = np.asarray(value)
            assert got.dtype == value.dtype, (key, got.dtype, value.dtype)
            np.testing.assert_array_equal(got.reshape(value.shape), value, err_msg=f"{key} at frame {f}")
        for cam in ("left", "right"):
            depth = item[f"observation.depth.{cam}"].numpy()  # uint16 mm, as lerobot's int64 tensor
            assert depth.dtype == np.int64 and depth.shape == (48, 64)
            np.testing.assert_array_equal(depth, depth_to_mm(fr.depth[cam]))  # exact: the log keeps whole mm
            img = item[f"observation.images.{cam}"]
            assert img.shape == (3, 48, 64) and img.dtype == torch.float32
            mad = np.abs(img.numpy().transpose(1, 2, 0) * 255.0 - fr.rgb[cam].astype(np.float32)).mean()
            assert mad < 8.0, f"{cam} frame {f}: mean abs diff {mad:.2f} of 255"  # lossy AV1
        checked |= set(want) | {f"observation.{kind}.{cam}" for kind in ("depth", "images") for cam in ("left", "right")}
    assert set(features) == checked, f"exported but never read back: {sorted(set(features) - checked)}"


def test_dataloader_iterates_batches_of_four(tiny_dataset):
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(tiny_dataset.repo_id, root=tiny_dataset.root, video_backend="pyav")
    loader = torch.utils.data.DataLoader(ds, batch_size=4, shuffle=False, num_workers=0)
    n = 0
    for batch in loader:
        b = len(batch["index"])
        assert batch["observation.images.left"].shape == (b, 3, 48, 64)
        assert batch["observation.depth.right"].shape == (b, 48, 64)
        assert batch["observation.depth.right"].dtype == torch.int64  # uint16 mm through lerobot's formatting
        assert batch["observation.poses"].shape == (b, 6 * 17 * 3)  # flat: unflatten_poses
        assert unflatten_poses(batch["observation.poses"])[0].shape == (b, 6, 17, 3)
        assert batch["observation.pose_mask"].dtype == torch.float32
        assert batch["privileged.ped_state"].shape == (b, 64, 8)
        assert batch["privileged.local_occupancy"].shape == (b, 100, 100)
        assert batch["privileged.local_occupancy"].dtype == torch.bool
        assert batch["next.reward"].shape == (b,) and batch["next.done"].dtype == torch.bool
        n += b
    assert n == len(ds)


def test_metadata_files_hold_cameras_and_episode_facts(tiny_dataset):
    root = tiny_dataset.root
    info = json.loads((root / "meta/info.json").read_text())
    meta = json.loads((root / ICROWDNAV_META).read_text())
    rows = [json.loads(line) for line in (root / ICROWDNAV_EPISODES).read_text().splitlines()]
    assert meta["total_episodes"] == info["total_episodes"] == len(rows) == 2
    assert meta["fps"] == info["fps"] == 10
    ep0 = tiny_dataset.episodes[0]
    assert meta["cameras"]["left"]["K"] == ep0.meta.cameras["left"]["K"]
    assert meta["cameras"]["right"]["T_base_cam"] == ep0.meta.cameras["right"]["T_base_cam"]
    assert meta["spec"]["local_map"]["shape"] == [100, 100]
    # the calibration where lerobot's tools keep it: the features' info in meta/info.json
    feats = info["features"]
    for cam in ("left", "right"):
        want = json.loads(json.dumps(ep0.meta.cameras[cam]))
        assert feats[f"observation.images.{cam}"]["info"]["camera"] == want
        depth_cam = feats[f"observation.depth.{cam}"]["info"]["camera"]
        assert {**depth_cam, "depth_units": want["depth_units"]} == want and depth_cam["depth_units"].startswith("mm")
    assert feats["observation.images.left"]["info"]["video.codec"]  # lerobot's own video info kept beside ours
    assert feats["observation.depth.left"]["info"]["unit"] == "mm"
    # the detections are flat vectors whose names spell the C-order layout (person, joint, xyz)
    assert feats["observation.poses"]["shape"] == [306] and len(feats["observation.poses"]["names"]) == 306
    assert feats["observation.poses"]["names"][:4] == ["p0.nose.x", "p0.nose.y", "p0.nose.z", "p0.left_eye.x"]
    assert feats["observation.pose_mask"]["names"][17] == "p1.nose"
    assert feats["observation.poses"]["info"]["unflattened_shape"] == [6, 17, 3]
    assert feats["action"]["info"]["icrowdnav_format"] == 2 and "observation t" in feats["action"]["info"]["convention"]
    assert feats["privileged.local_occupancy"]["info"]["layout"]["shape"] == [100, 100]
    assert all(ft.get("info", {}).get("description") for k, ft in feats.items() if k not in LEROBOT_INDEX_FEATURES)
    for k, (row, ep) in enumerate(zip(rows, tiny_dataset.episodes, strict=True)):
        assert row["episode_index"] == k and row["length"] == len(ep.frame_list) - 1
        assert row["recorded_frames"] == len(ep.frame_list)
        assert (row["scene"], row["seed"], row["density"]) == (ep.meta.scene, ep.meta.seed, ep.meta.density)
        assert row["outcome"] == ep.frame_list[-1].outcome != ""
        assert row["source"] == f"ep_{k:03d}.mcap"  # the file's name: no local directory in a shared dataset
        assert row["meta"]["config_hash"] == ep.meta.config_hash
        assert row["return"] == pytest.approx(sum(np.float32(f.reward) for f in ep.frame_list[1:]), rel=1e-5)
    assert meta["sources"] == [r["source"] for r in rows]
    # every feature names its axes / elements
    for key, ft in info["features"].items():
        if key not in ("timestamp", "frame_index", "episode_index", "index", "task_index"):
            assert ft["names"], key
    assert tiny_dataset.counts["frames_per_s"] > 0 and tiny_dataset.counts["skipped_partial"] == 0
    assert _leftovers(root) == []


# ---------------------------------------------------------------------------------------------- feature errors
@pytest.mark.parametrize("case", ["depth_shape", "depth_dtype", "missing_camera", "missing_field", "rgb_dtype",
                                  "too_many_people", "step_gap", "nan_state"])
def test_feature_errors_name_file_field_expected_actual(case, tiny_episodes, frame_with):
    ep = tiny_episodes[0]
    fr = ep.frame_list[3]
    spec = ExportSpec.from_meta(ep.meta)
    if case == "depth_shape":
        bad, words = frame_with(fr, depth={**fr.depth, "left": np.zeros((48, 63), np.float32)}), \
            ["depth[left]", "observation.depth.left", "(48, 64)", "(48, 63)"]
    elif case == "depth_dtype":
        bad, words = frame_with(fr, depth={**fr.depth, "right": (fr.depth["right"] * 1000).astype(np.uint16)}), \
            ["depth[right]", "float", "uint16"]
    elif case == "missing_camera":
        bad, words = frame_with(fr, depth={"left": fr.depth["left"]}), ["depth[right]", "(48, 64)", "missing"]
    elif case == "missing_field":
        bad, words = frame_with(fr, state=None), ["'state'", "missing"]
    elif case == "rgb_dtype":
        bad, words = frame_with(fr, rgb={**fr.rgb, "left": fr.rgb["left"].astype(np.float32)}), \
            ["rgb[left]", "uint8", "float32", "(48, 64, 3)"]
    elif case == "too_many_people":
        spec = ExportSpec(spec.camera_sizes, max_people=3)
        bad, words = fr, ["'poses'", "at most 3", "6"]
    elif case == "step_gap":
        bad, words = frame_with(fr, step=5), ["'step'", "3", "5"]
    else:
        state = fr.state.copy()
        state[2] = np.nan
        bad, words = frame_with(fr, state=state), ["'state'", "finite", "NaN"]
    with pytest.raises(FeatureError) as ei:
        frame_to_features(bad, ep.frame_list[4], ep.meta, ep.occupancy, spec, "runs/ep_007.mcap", 3)
    msg = str(ei.value)
    assert msg.startswith("runs/ep_007.mcap: frame "), msg
    for w in words:
        assert w in msg, (w, msg)
    assert "\n" not in msg


def test_too_many_pedestrians_is_an_error_naming_n_max(tiny_episodes):
    ep = tiny_episodes[0]
    spec = ExportSpec(ExportSpec.from_meta(ep.meta).camera_sizes, n_max=2)
    with pytest.raises(FeatureError, match=r"ped_pos.*at most 2 pedestrians \(n_max"):
        frame_to_features(ep.frame_list[0], ep.frame_list[1], ep.meta, ep.occupancy, spec, "x.mcap", 0)


def test_bad_frame_mid_export_publishes_nothing(tmp_path, tiny_episodes, frame_with):
    ep0, ep1 = tiny_episodes
    frames = list(ep1.frame_list)
    frames[4] = frame_with(frames[4], depth={**frames[4].depth, "left": np.zeros((48, 63), np.float32)})
    bad = ep1.with_frames(frames, source="raw/ep_001.mcap")
    out = tmp_path / "ds"
    with pytest.raises(FeatureError) as ei:
        export_dataset([ep0, bad], out, "icrowdnav/bad", progress=False)
    msg = str(ei.value)
    assert "raw/ep_001.mcap: frame 4" in msg and "depth[left]" in msg and "(48, 63)" in msg
    assert not out.exists() and _leftovers(out) == []


def test_episodes_must_share_the_camera_model(tmp_path, tiny_episodes):
    ep0, ep1 = tiny_episodes
    cams = {c: dict(v) for c, v in ep1.meta.cameras.items()}
    cams["left"]["hfov_deg"] = 90.0
    other = _with_meta(ep1, replace(ep1.meta, cameras=cams), "raw/ep_001.mcap")
    out = tmp_path / "ds"
    with pytest.raises(FeatureError, match=r"raw/ep_001\.mcap: episode metadata field 'cameras\[left\]\[hfov_deg\]': "
                                           r"expected 70\.0 .*got 90\.0"):
        export_dataset([ep0, other], out, "icrowdnav/x", progress=False)
    assert not out.exists() and _leftovers(out) == []


def _with_meta(ep, meta, source):
    """A copy of a fixture episode with other metadata."""
    copy = ep.with_frames(ep.frame_list, source=source)
    copy.meta = meta
    return copy


# ---------------------------------------------------------------------------------------------- inputs
def test_cli_bad_input_is_one_error_line(tmp_path, capsys):
    from recorder.export import main as export_main

    assert export_main([str(tmp_path / "absent"), str(tmp_path / "ds"), "--repo-id", "icrowdnav/x"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: missing recording directory: {tmp_path / 'absent'}"]
    assert not (tmp_path / "ds").exists()


def test_partial_missing_and_corrupt_inputs_are_refused(tmp_path, tiny_mcap_dir, caplog):
    out = tmp_path / "ds"
    partial = tmp_path / "ep_009.mcap.partial"
    partial.write_bytes((tiny_mcap_dir / "ep_000.mcap").read_bytes())
    with pytest.raises(CorruptArtifactError, match=r"ep_009\.mcap\.partial: unfinished recording"):
        export_dataset([tiny_mcap_dir / "ep_000.mcap", partial], out, "icrowdnav/x", progress=False)
    with pytest.raises(InputMissingError, match="nope.mcap"):
        export_dataset([tmp_path / "nope.mcap"], out, "icrowdnav/x", progress=False)
    truncated = tmp_path / "ep_trunc.mcap"
    data = (tiny_mcap_dir / "ep_001.mcap").read_bytes()
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(CorruptArtifactError, match=r"ep_trunc\.mcap"):
        export_dataset([tiny_mcap_dir / "ep_000.mcap", truncated], out, "icrowdnav/x", progress=False)
    assert not out.exists() and _leftovers(out) == []

    only_partial = tmp_path / "only_partial"
    only_partial.mkdir()
    (only_partial / "a.mcap.partial").write_bytes(b"")
    with pytest.raises(InputMissingError, match=r"no complete \*\.mcap episode .*1 \*\.partial skipped"):
        export_run(only_partial, out, "icrowdnav/x", progress=False)
    with pytest.raises(InputMissingError, match="missing recording directory"):
        export_run(tmp_path / "absent", out, "icrowdnav/x", progress=False)

    mixed = tmp_path / "mixed"
    mixed.mkdir()
    (mixed / "ep_000.mcap").write_bytes((tiny_mcap_dir / "ep_000.mcap").read_bytes())
    (mixed / "ep_001.mcap.partial").write_bytes(b"half")
    with caplog.at_level(logging.WARNING, logger="icrowdnav"):
        counts = export_run(mixed, out, "icrowdnav/x", progress=False)
    assert counts["episodes"] == 1 and counts["skipped_partial"] == 1
    assert any("ep_001.mcap.partial" in r.getMessage() for r in caplog.records)
    assert check_dataset(out) == []


def test_fps_must_match_the_control_period(tmp_path, tiny_episodes):
    out = tmp_path / "ds"
    with pytest.raises(ConfigError, match=r"fps: expected 10 .*got 15"):
        export_dataset(tiny_episodes[:1], out, "icrowdnav/x", fps=15, progress=False)
    assert not out.exists() and _leftovers(out) == []


# ---------------------------------------------------------------------------------------------- no overwrite
def test_no_silent_overwrite_and_overwrite_replaces(tmp_path, tiny_episodes):
    out = tmp_path / "ds"
    counts = export_dataset(tiny_episodes[:1], out, "icrowdnav/ow", progress=False)
    assert counts["episodes"] == 1
    before = _tree_digest(out)
    with pytest.raises(OutputExistsError, match=str(out)):
        export_dataset(tiny_episodes, out, "icrowdnav/ow", progress=False)
    assert _tree_digest(out) == before and _leftovers(out) == []
    counts = export_dataset(tiny_episodes, out, "icrowdnav/ow", overwrite=True, progress=False)
    assert counts["episodes"] == 2
    assert json.loads((out / "meta/info.json").read_text())["total_episodes"] == 2
    assert check_dataset(out) == [] and _leftovers(out) == []


# ---------------------------------------------------------------------------------------------- crash
def _child_export(out: Path, conn) -> None:
    """The export that gets killed: three driven episodes, reporting progress through ``conn``."""
    from recorder.drive import drive_episode
    from sim.env import CameraConfig, SimConfig

    cfg = SimConfig(scene="hallway", density=0.2, max_episode_s=2.0, dt_s=0.1,
                    camera=CameraConfig(width_px=64, height_px=48))

    def episodes():
        for k, seed in enumerate((0, 1, 2)):
            conn.send(f"EPISODE {k}")  # asked for episode k: episodes 0..k-1 are saved
            if k > 0:
                time.sleep(1.0)  # hold here (longer than any kill delay) so a kill lands before publishing
            yield drive_episode(cfg, seed)
        conn.send("ALL SAVED")  # finalize, meta files, doctor and rename follow

    export_dataset(episodes(), out, "icrowdnav/crash", progress=False)
    conn.send("DONE")


def _run_and_kill(out: Path, marker: str, delay_s: float) -> list[str]:
    """Runs the export in a forked process and SIGKILLs it ``delay_s`` after it reports ``marker``.

    Forking (rather than starting a fresh interpreter) spares the ~15 s import of torch/lerobot per run; the
    child is a separate process all the same and dies by SIGKILL without any cleanup.
    """
    import multiprocessing as mp

    import lerobot.datasets.lerobot_dataset  # noqa: F401  (imported once here, shared by the forked child)

    ctx = mp.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child_export, args=(out, send), daemon=True)
    proc.start()
    send.close()
    seen: list[str] = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and recv.poll(deadline - time.monotonic()):
            try:
                seen.append(recv.recv())
            except EOFError:
                break
            if seen[-1] == marker:
                time.sleep(delay_s)
                break
    finally:
        if proc.is_alive():
            os.kill(proc.pid, signal.SIGKILL)
        proc.join(30)
        recv.close()
    assert marker in seen, f"the export never reported {marker!r}: {seen} (exit code {proc.exitcode})"
    return seen


@pytest.mark.slow
def test_killed_export_leaves_no_dataset_or_a_valid_one(tmp_path, tiny_episodes):
    kills = [("EPISODE 1", 0.05), ("EPISODE 2", 0.3), ("ALL SAVED", 0.0), ("ALL SAVED", 0.15), ("ALL SAVED", 0.4)]
    for k, (marker, delay_s) in enumerate(kills):
        out = tmp_path / f"crash{k}"
        _run_and_kill(out, marker, delay_s)
        if marker != "ALL SAVED":  # killed while writing episodes: nothing may be published yet
            assert not out.exists(), (marker, delay_s)
            assert any(".staging-" in n for n in _leftovers(out)), "the kill should have hit a staging directory"
        if out.exists():
            assert check_dataset(out) == [], (marker, delay_s)
        # a later export cleans the dead process's staging directory and succeeds
        counts = export_dataset(tiny_episodes[:1], out, "icrowdnav/crash", overwrite=out.exists(), progress=False)
        assert counts["episodes"] == 1
        assert check_dataset(out) == [] and _leftovers(out) == []
