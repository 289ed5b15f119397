"""Tests of pretrain.data: people rasterisation, the BEV pretext labels of a hand-built episode, clip/batch cutting,
the episode split and the grid-vs-local-map check (without a dataset); a damaged dataset named before lerobot opens
it (on a copy of the tests' tiny dataset)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.core.errors import ConfigError, CorruptArtifactError, InputMissingError
from pretrain.data import (
    FrameStore,
    check_dataset,
    check_grid_in_local_map,
    episode_labels,
    load_frames,
    make_batches,
    make_clips,
    rasterise_people,
    rasterise_people_reference,
    seen_people,
    split_episodes,
)
from pretrain.geometry import BEVGrid
from pretrain.model import EncoderConfig

LOCAL_MAP = {"resolution_m": 0.1, "x_min_m": -2.0, "x_max_m": 8.0, "y_min_m": -5.0, "y_max_m": 5.0,
             "shape": [100, 100]}


def default_grid() -> BEVGrid:
    return EncoderConfig().grid  # x [0, 6), y [-4.8, 4.8), 0.1 m


def base_to_world(pose, bx: float, by: float) -> tuple[float, float]:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return pose[0] + c * bx - s * by, pose[1] + s * bx + c * by


def world_to_base_hand(pose, wx: float, wy: float) -> tuple[float, float]:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    dx, dy = wx - pose[0], wy - pose[1]
    return c * dx + s * dy, -s * dx + c * dy


def disc_cells(grid: BEVGrid, bx: float, by: float, r: float) -> np.ndarray:
    """Cells whose centre (x0 + (i + 0.5) dx, y0 + (j + 0.5) dy) is within r of (bx, by), by brute force."""
    nx, ny = grid.shape
    out = np.zeros((nx, ny), dtype=bool)
    for i in range(nx):
        cx = grid.x_bound[0] + (i + 0.5) * grid.x_bound[2]
        for j in range(ny):
            cy = grid.y_bound[0] + (j + 0.5) * grid.y_bound[2]
            out[i, j] = (cx - bx) ** 2 + (cy - by) ** 2 <= r * r
    return out


def plus_cells(grid: BEVGrid, i: int, j: int) -> np.ndarray:
    """Cell (i, j) and its 4 neighbours: the cells of a 0.12 m disc centred on a 0.1 m cell's centre."""
    out = np.zeros(grid.shape, dtype=bool)
    for a, b in ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)):
        out[i + a, j + b] = True
    return out


# ---------------------------------------------------------------- rasterise_people


@pytest.mark.parametrize("seed", range(5))
def test_rasterise_people_matches_reference(seed):
    """The bounding-box rasteriser equals the dense reference on random people (some absent, some with zero
    radius, some outside or straddling the grid edge)."""
    rng = np.random.default_rng(seed)
    grid = BEVGrid((0.0, 4.0, 0.2), (-3.2, 3.2, 0.2), (0.1, 2.0)) if seed % 2 else default_grid()
    n_frames, n_people = 6, 8
    xy = np.stack([rng.uniform(-1.0, grid.x_bound[1] + 1.0, (n_frames, n_people)),
                   rng.uniform(grid.y_bound[0] - 1.0, grid.y_bound[1] + 1.0, (n_frames, n_people))], -1)
    radius = rng.uniform(0.0, 0.8, (n_frames, n_people))
    radius[rng.random(radius.shape) < 0.2] = 0.0
    present = rng.random((n_frames, n_people)) < 0.7
    fast = rasterise_people(grid, xy, radius, present)
    ref = rasterise_people_reference(grid, xy, radius, present)
    assert fast.shape == ref.shape == (n_frames, *grid.shape) and fast.dtype == bool
    np.testing.assert_array_equal(fast, ref)
    assert ref.sum() > 20
    # absent people leave no trace: presence matters
    gone = rasterise_people(grid, xy, radius, np.zeros_like(present))
    assert not gone.any()


def test_rasterise_people_single_person_matches_reference():
    """One person at a time (so that its radius sets the bounding box): the disc's extreme cells, on every side,
    are found for many radii and sub-cell positions."""
    rng = np.random.default_rng(11)
    grid = default_grid()
    for _ in range(300):
        xy = np.array([[[rng.uniform(1.0, 5.0), rng.uniform(-3.0, 3.0)]]])
        radius = np.array([[rng.uniform(0.03, 0.7)]])
        present = np.array([[True]])
        np.testing.assert_array_equal(rasterise_people(grid, xy, radius, present),
                                      rasterise_people_reference(grid, xy, radius, present),
                                      err_msg=f"{xy.ravel()} r={radius.item()}")


def test_rasterise_people_hand_cases():
    """A 0.12 m person on a cell centre covers that cell and its 4 neighbours; a 0.05 m one only its cell; an
    absent or zero-radius one nothing."""
    grid = default_grid()
    xy = np.array([[[2.05, 0.35], [1.05, -1.05], [3.05, 2.05], [4.05, 1.05]]])
    radius = np.array([[0.12, 0.05, 0.5, 0.0]])
    present = np.array([[True, True, False, True]])
    out = rasterise_people(grid, xy, radius, present)[0]
    expected = plus_cells(grid, 20, 51)
    expected[10, 37] = True
    np.testing.assert_array_equal(out, expected)


# ---------------------------------------------------------------- episode_labels


def hand_episode():
    """A 5-frame episode with a rotated, moving robot and 3 people (one always absent, one with radius 0)."""
    odom = np.array([[1.0, 2.0, 0.7], [1.2, 2.1, 0.9], [1.5, 2.3, 1.2], [1.7, 2.6, 1.4], [1.9, 2.8, 1.6]])
    n = len(odom)
    occupancy = np.zeros((n, 100, 100), dtype=bool)
    occupancy[1, 50, 40] = True  # x = 8 - 50.5 * 0.1 = 2.95, y = 5 - 40.5 * 0.1 = 0.95 in frame 1's robot frame
    ped = np.zeros((n, 3, 8))
    # person 0: at frame 0 in robot frame 0 at (2.35, -0.65); its future positions at frames 1 and 2 are placed
    # at known points of robot frame 0 (the future labels of frame 0); later frames walk on
    targets0 = [(2.35, -0.65), (3.05, -0.25), (3.55, 0.15)]
    for k, (bx, by) in enumerate(targets0):
        ped[k, 0, :2] = base_to_world(odom[0], bx, by)
    ped[3, 0, :2] = ped[2, 0, :2] + [0.3, 0.1]
    ped[4, 0, :2] = ped[3, 0, :2] + [0.3, 0.1]
    ped[:, 0, 4] = 0.12
    ped[:, 0, 7] = 1.0
    # person 1: absent but in view
    for k in range(n):
        ped[k, 1, :2] = base_to_world(odom[k], 2.0, 0.0)
    ped[:, 1, 4] = 0.5
    ped[:, 1, 7] = 0.0
    # person 2: present with radius 0 (a padded row)
    for k in range(n):
        ped[k, 2, :2] = base_to_world(odom[k], 1.0, 0.0)
    ped[:, 2, 7] = 1.0
    return odom, occupancy, ped, targets0


def test_episode_labels_static_channel():
    """One occupied local_occupancy cell (row 50, col 40: x 2.95, y 0.95) lands in BEV cell (29, 57) of the
    static channel of its frame only."""
    grid = default_grid()
    odom, occ, ped, _ = hand_episode()
    labels, valid = episode_labels(grid, LOCAL_MAP, occ, ped, odom, [1, 2])
    assert labels.shape == (5, 4, *grid.shape) and labels.dtype == np.uint8
    assert grid.cell_of(2.95, 0.95) == (29, 57)
    expected = np.zeros(grid.shape, dtype=np.uint8)
    expected[29, 57] = 1
    np.testing.assert_array_equal(labels[1, 0], expected)
    assert not labels[[0, 2, 3, 4], 0].any()
    assert valid[:, 0].all()


def test_episode_labels_static_channel_covers_the_grid():
    """Every BEV cell reads the local-map cell under its centre (row = floor((8 - x) / 0.1),
    col = floor((5 - y) / 0.1)): a full pattern of the local map is resampled exactly."""
    grid = default_grid()
    rng = np.random.default_rng(0)
    occ = rng.random((1, 100, 100)) < 0.3
    labels, _ = episode_labels(grid, LOCAL_MAP, occ, np.zeros((1, 0, 8)), np.zeros((1, 3)), [])
    nx, ny = grid.shape
    for i in range(0, nx, 7):
        for j in range(0, ny, 5):
            x, y = 0.05 + 0.1 * i, -4.75 + 0.1 * j
            r, c = round((8.0 - x) / 0.1 - 0.5), round((5.0 - y) / 0.1 - 0.5)
            assert labels[0, 0, i, j] == occ[0, r, c], (i, j, r, c)


def test_episode_labels_pedestrian_now():
    """A person at a known world position seen from a rotated robot occupies the right cells of ped_t: in frame
    0 the 5 cells around (23, 41) (base point (2.35, -0.65)), in other frames where its world position is seen
    from that frame's pose; absent and zero-radius people leave no trace."""
    grid = default_grid()
    odom, occ, ped, _ = hand_episode()
    labels, valid = episode_labels(grid, LOCAL_MAP, occ, ped, odom, [1, 2])
    assert grid.cell_of(2.35, -0.65) == (23, 41)
    np.testing.assert_array_equal(labels[0, 1].astype(bool), plus_cells(grid, 23, 41))
    for t in range(5):
        bx, by = world_to_base_hand(odom[t], *ped[t, 0, :2])
        np.testing.assert_array_equal(labels[t, 1].astype(bool), disc_cells(grid, bx, by, 0.12), err_msg=str(t))
        assert labels[t, 1].sum() >= 1
    assert valid[:, 1].all()


def test_episode_labels_future_channels_use_the_current_robot_frame():
    """The future channel at offset k holds the person's position at frame t + k expressed in frame t's robot
    frame (not frame t + k's); frames whose future is past the episode's end are invalid and empty."""
    grid = default_grid()
    odom, occ, ped, targets0 = hand_episode()
    labels, valid = episode_labels(grid, LOCAL_MAP, occ, ped, odom, [1, 2])
    # frame 0: hand-placed future targets
    for ch, (bx, by) in zip((2, 3), targets0[1:], strict=True):
        i, j = grid.cell_of(bx, by)
        np.testing.assert_array_equal(labels[0, ch].astype(bool), plus_cells(grid, i, j))
    # every frame and offset, by brute force through world coordinates
    n = len(odom)
    for ch, off in ((2, 1), (3, 2)):
        for t in range(n):
            if t + off >= n:
                assert not valid[t, ch]
                assert not labels[t, ch].any()
                continue
            assert valid[t, ch]
            bx, by = world_to_base_hand(odom[t], *ped[t + off, 0, :2])
            np.testing.assert_array_equal(labels[t, ch].astype(bool), disc_cells(grid, bx, by, 0.12),
                                          err_msg=f"t={t} offset={off}")
            # and not the position seen from frame t + off
            wx, wy = world_to_base_hand(odom[t + off], *ped[t + off, 0, :2])
            assert not np.array_equal(labels[t, ch].astype(bool), disc_cells(grid, wx, wy, 0.12))
    np.testing.assert_array_equal(valid[:, 2], [True, True, True, True, False])
    np.testing.assert_array_equal(valid[:, 3], [True, True, True, False, False])


def test_episode_labels_future_beyond_a_short_episode():
    """An offset at least as long as the episode makes that channel invalid for every frame."""
    grid = default_grid()
    odom, occ, ped, _ = hand_episode()
    labels, valid = episode_labels(grid, LOCAL_MAP, occ[:3], ped[:3], odom[:3], [1, 5])
    assert labels.shape == (3, 4, *grid.shape)
    np.testing.assert_array_equal(valid[:, 2], [True, True, False])
    assert not valid[:, 3].any() and not labels[:, 3].any()


def two_people_episode():
    """4 frames, a still robot at the origin, person A at base (2.0, 1.0) and person B at (4.0, -1.0), both walking
    +x at 0.1 m per frame, radius 0.25 m."""
    odom = np.zeros((4, 3))
    ped = np.zeros((4, 2, 8))
    for t in range(4):
        ped[t, 0, :2] = (2.0 + 0.1 * t, 1.0)
        ped[t, 1, :2] = (4.0 + 0.1 * t, -1.0)
    ped[..., 4] = 0.25
    ped[..., 7] = 1.0
    return odom, np.zeros((4, 100, 100), dtype=bool), ped


def test_seen_label_keeps_only_the_people_the_depth_reaches_now_and_in_the_future():
    """With depth hits on person A only (frames 0-1) and on nobody later, the seen label marks A now and in A's
    future targets of frames 0-1, never B, and nobody in frames 2-3; the all-people label marks both."""
    grid = default_grid()
    odom, occ, ped = two_people_episode()
    hits = np.zeros((4, *grid.shape), dtype=bool)
    for t in (0, 1):
        hits[t][grid.cell_of(ped[t, 0, 0] - 0.1, ped[t, 0, 1])] = True  # on A's near side
    hits[2][grid.cell_of(3.0, 3.0)] = True  # a wall, on nobody
    seen = seen_people(grid, hits, ped[..., :2], ped[..., 4], ped[..., 7] > 0.5)
    np.testing.assert_array_equal(seen, [[True, False], [True, False], [False, False], [False, False]])
    every, valid = episode_labels(grid, LOCAL_MAP, occ, ped, odom, [1, 2])
    only, valid_seen = episode_labels(grid, LOCAL_MAP, occ, ped, odom, [1, 2], hits)
    np.testing.assert_array_equal(valid, valid_seen)
    for t in (0, 1):
        for ch, off in ((1, 0), (2, 1), (3, 2)):
            if not valid[t, ch]:
                continue
            a = disc_cells(grid, *ped[t + off, 0, :2], 0.25)
            b = disc_cells(grid, *ped[t + off, 1, :2], 0.25)
            np.testing.assert_array_equal(only[t, ch].astype(bool), a, err_msg=f"t={t} ch={ch}")
            np.testing.assert_array_equal(every[t, ch].astype(bool), a | b, err_msg=f"t={t} ch={ch}")
    assert not only[2:, 1:].any() and every[2:, 1].any()
    np.testing.assert_array_equal(only[:, 0], every[:, 0])  # the static channel is untouched


def test_seen_label_needs_a_hit_on_the_disc():
    """A hit cell whose centre lies just outside a person's radius does not make it seen."""
    grid = default_grid()
    xy = np.array([[[2.05, 0.05]]])
    hits = np.zeros((1, *grid.shape), dtype=bool)
    hits[0][grid.cell_of(2.05 + 0.35, 0.05)] = True  # 0.35 m away, radius 0.25
    assert not seen_people(grid, hits, xy, np.array([[0.25]]), np.array([[True]])).any()
    hits[0][grid.cell_of(2.05 + 0.15, 0.05)] = True
    assert seen_people(grid, hits, xy, np.array([[0.25]]), np.array([[True]])).all()


# ---------------------------------------------------------------- clips and batches


def tiny_store(lengths: list[int]) -> FrameStore:
    n = sum(lengths)
    start, end, slices, pos = np.zeros(n, np.int64), np.zeros(n, np.int64), [], 0
    for length in lengths:
        start[pos:pos + length], end[pos:pos + length] = pos, pos + length
        slices.append((pos, pos + length))
        pos += length
    return FrameStore(rgb=np.zeros((n, 2, 3, 4, 4), np.uint8), depth=np.zeros((n, 2, 1, 1), np.float32),
                      pose=np.zeros((n, 3)), labels=np.zeros((n, 4, 2, 2), np.uint8), valid=np.ones((n, 4), bool),
                      episode_start=start, episode_end=end, episodes=list(range(len(lengths))),
                      episode_slices=slices)


@pytest.mark.parametrize("seed", [None, 0, 1, 2, 3, 4, 5])
@pytest.mark.parametrize("clips_per_batch", [1, 3])
def test_clips_and_batches_tile_every_episode(seed, clips_per_batch):
    """Episodes of 13 and 5 frames, 4 targets per clip, T = 3: every frame is a target exactly once, and each
    window is [t-2, t-1, t] clamped to its episode's start (never crossing into the previous episode)."""
    store = tiny_store([13, 5])
    history = 3
    rng = None if seed is None else np.random.default_rng(seed)
    clips = make_clips(store, store.episode_slices, 4, history, rng)
    for frames, targets in clips:
        assert 1 <= len(targets) <= 4
        assert len(frames) == len(targets) + history - 1
        assert (store.episode_start[frames] == store.episode_start[targets[0]]).all()
    batches = make_batches(clips, clips_per_batch, history)
    assert len(batches) == math.ceil(len(clips) / clips_per_batch)
    all_targets = np.concatenate([b.targets for b in batches])
    assert sorted(all_targets.tolist()) == list(range(len(store)))
    for b in batches:
        assert b.windows.shape == (len(b.targets), history)
        assert b.windows.max() < len(b.frames)
        for p, t in enumerate(b.targets):
            expect = [max(t - 2, store.episode_start[t]), max(t - 1, store.episode_start[t]), t]
            assert b.frames[b.windows[p]].tolist() == expect, (t, b.frames[b.windows[p]])


def test_clips_without_rng_start_at_frame_zero():
    """Without an rng, the clips cut at 0, 4, 8, 12 of each episode."""
    store = tiny_store([13, 5])
    clips = make_clips(store, store.episode_slices, 4, 3, None)
    assert [t.tolist() for _, t in clips] == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11], [12],
                                             [13, 14, 15, 16], [17]]
    assert clips[0][0].tolist() == [0, 0, 0, 1, 2, 3]
    assert clips[4][0].tolist() == [13, 13, 13, 14, 15, 16]
    assert clips[1][0].tolist() == [2, 3, 4, 5, 6, 7]


def test_clips_with_rng_vary_the_phase():
    """With an rng, the cut positions vary between draws (a random phase), still tiling every frame."""
    store = tiny_store([13, 5])
    cuts = set()
    for seed in range(20):
        clips = make_clips(store, store.episode_slices, 4, 3, np.random.default_rng(seed))
        cuts.add(tuple(int(t[0]) for _, t in clips))
    assert len(cuts) > 1


# ---------------------------------------------------------------- split and checks


@pytest.mark.parametrize("n,frac", [(2, 0.1), (3, 0.5), (10, 0.1), (10, 0.99), (37, 0.2), (5, 0.0)])
def test_split_episodes(n, frac):
    """The split is disjoint, covers all episodes, is deterministic in the seed and has >= 1 episode on each
    side."""
    train, val = split_episodes(n, frac, seed=7)
    assert not set(train) & set(val)
    assert sorted(train + val) == list(range(n))
    assert len(val) >= 1 and len(train) >= 1
    assert split_episodes(n, frac, seed=7) == (train, val)
    assert train == sorted(train) and val == sorted(val)
    if 0 < frac < 0.9:
        assert len(val) == max(1, round(frac * n))


def test_split_episodes_depends_on_the_seed():
    splits = {tuple(split_episodes(30, 0.2, seed=s)[1]) for s in range(5)}
    assert len(splits) > 1


@pytest.mark.parametrize("n", [0, 1])
def test_split_episodes_needs_two(n):
    with pytest.raises(ConfigError):
        split_episodes(n, 0.1, seed=0)


@pytest.mark.parametrize("x_bound,y_bound", [((0.0, 9.0, 0.1), (-4.8, 4.8, 0.1)),
                                             ((-2.5, 6.0, 0.1), (-4.8, 4.8, 0.1)),
                                             ((0.0, 6.0, 0.1), (-6.0, 6.0, 0.1)),
                                             ((0.0, 6.0, 0.1), (-4.8, 5.2, 0.1))])
def test_check_grid_in_local_map_rejects_a_grid_beyond_the_map(x_bound, y_bound):
    """A grid reaching outside privileged.local_occupancy's crop raises ConfigError."""
    grid = BEVGrid(x_bound, y_bound, (0.1, 2.0))
    with pytest.raises(ConfigError, match="local_occupancy"):
        check_grid_in_local_map(grid, LOCAL_MAP, "test dataset")


def test_check_grid_in_local_map_accepts_fitting_grids():
    check_grid_in_local_map(default_grid(), LOCAL_MAP, "test dataset")
    check_grid_in_local_map(BEVGrid((-2.0, 8.0, 0.1), (-5.0, 5.0, 0.1), (0.1, 2.0)), LOCAL_MAP, "test dataset")


@pytest.mark.parametrize("damage", ["deleted", "truncated"])
def test_damaged_parquet_is_named_before_lerobot_opens_the_dataset(dataset_copy, tiny_dataset, damage) -> None:
    """lerobot says 'OfflineModeIsEnabled: Cannot reach https://huggingface.co/...' for a deleted data file and
    'DatasetGenerationError' for a truncated one; the doctor's cheap checks name the file first (check_dataset is
    what `pretrain`'s inputs and load_frames call)."""
    p = dataset_copy / "data" / "chunk-000" / "file-000.parquet"
    if damage == "deleted":
        p.unlink()
    else:
        p.write_bytes(p.read_bytes()[:-300])
    error, what = (InputMissingError, "missing") if damage == "deleted" else (CorruptArtifactError, "not a readable")
    pattern = f"damaged dataset {dataset_copy}: {p}: {what}"
    with pytest.raises(error, match=pattern):
        check_dataset(dataset_copy)
    cams = check_dataset(tiny_dataset.root).cameras
    with pytest.raises(error, match=pattern):
        load_frames(dataset_copy, cams, default_grid(), 4, [0.5, 1.0], progress=False)
