"""The ViNT-style labels and context windows on constructed tracks; a damaged recorded dataset is named."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.core.errors import CorruptArtifactError, InputMissingError
from rl.baselines.vint import check_dataset, context_indices, load_dataset, trajectory_labels


def test_trajectory_labels_on_a_known_track() -> None:
    # heading +y at 1 m/s for 5 frames, then turning left on the spot by 0.1 rad per frame; 10 frames at 10 fps
    yaw = np.pi / 2 + np.r_[np.zeros(5), 0.1 * np.arange(1, 6)]
    y = np.r_[0.1 * np.arange(5), np.full(5, 0.4)]
    pose = np.stack([np.zeros(10), y, yaw], -1)
    goal = np.tile([0.0, 5.0], (10, 1))
    wp, dist, g = trajectory_labels(pose, goal, np.array([0, 4, 8]), np.full(3, 10), horizon=3, spacing=2,
                                    metres_per_step=0.2, max_dist=3)
    # frame 0: poses of frames 2, 4, 6 straight ahead (0.2, 0.4 m), then 0.4 m ahead turned by 0.2 rad
    np.testing.assert_allclose(wp[0, :, :2], [[1.0, 0.0], [2.0, 0.0], [2.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(wp[0, :, 2:], [[1, 0], [1, 0], [math.cos(0.2), math.sin(0.2)]], atol=1e-6)
    # frame 4: on the spot, yaw +0.2, +0.4, +0.5 (frame 9 past the end: held at the last pose)
    np.testing.assert_allclose(wp[1, :, :2], 0.0, atol=1e-6)
    np.testing.assert_allclose(np.arctan2(wp[1, :, 3], wp[1, :, 2]), [0.2, 0.4, 0.5], atol=1e-6)
    np.testing.assert_allclose(np.arctan2(wp[2, :, 3], wp[2, :, 2]), [0.1, 0.1, 0.1], atol=1e-6)
    np.testing.assert_allclose(dist, [3.0, 2.5, 0.5])  # (9 - t) / 2, capped at 3
    # goal 5 m ahead at frame 0; at frame 8 (yaw +0.4) it lies to the right
    np.testing.assert_allclose(g[0], [5.0, 0.0], atol=1e-6)
    assert g[2, 1] < 0


def test_context_indices_repeat_the_first_frame() -> None:
    ctx = context_indices(np.array([10, 13, 20]), np.array([10, 10, 10]), context=2, spacing=2)
    np.testing.assert_array_equal(ctx, [[10, 10, 10], [10, 11, 13], [16, 18, 20]])


def test_damaged_dataset_is_named_before_lerobot_opens_it(dataset_copy) -> None:
    """`train --variant vint` reads the recorded dataset: a deleted or truncated parquet is named by the doctor's
    cheap checks (lerobot's own errors name no file)."""
    p = dataset_copy / "data" / "chunk-000" / "file-000.parquet"
    p.write_bytes(p.read_bytes()[:-300])
    with pytest.raises(CorruptArtifactError, match=f"{p}: not a readable parquet file"):
        load_dataset(dataset_copy, [32, 32], progress=False)
    p.unlink()
    with pytest.raises(InputMissingError, match=f"{p}: missing"):
        check_dataset(dataset_copy)
