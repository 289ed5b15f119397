"""Tests of pretrain.geometry: the measured-depth lift (fast vs reference, hand-computed cells), depth sampling,
the ego-motion warp, grid/camera checks and small helpers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pipeline.core.errors import ConfigError, CorruptArtifactError
from pretrain.geometry import (
    BEVGrid,
    Camera,
    LiftGeometry,
    bev_to_image,
    check_grid_fits_cameras,
    fov_mask,
    lift_pixel_index,
    lift_splat,
    lift_splat_reference,
    relative_pose,
    sample_depth,
    warp_bev,
)
from pretrain.model import EncoderConfig
from sim.cameras import CameraSpec

W, H, STRIDE = 64, 48, 4
MOUNT_X, MOUNT_Y, MOUNT_Z = 0.1, 0.03, 0.8
SPECS = (CameraSpec("left", W, H, 70.0, 35.0, 0.0, (MOUNT_X, MOUNT_Y, MOUNT_Z)),
         CameraSpec("right", W, H, 70.0, -35.0, 0.0, (MOUNT_X, -MOUNT_Y, MOUNT_Z)))


def cameras() -> list[Camera]:
    return [Camera.from_dict(s.to_dict()) for s in SPECS]


def default_grid() -> BEVGrid:
    return EncoderConfig().grid


def hand_point(spec: CameraSpec, u: float, v: float, d: float) -> np.ndarray:
    """Base-frame point of continuous pixel (u, v) at z-depth d, from the camera's mounting alone (pitch 0).

    The camera looks along (cos yaw, sin yaw, 0); its image x (right) is (sin yaw, -cos yaw, 0) and its image y
    (down) is (0, 0, -1); the pinhole has fx = fy = W / (2 tan(hfov / 2)) and its principal point at the centre.
    """
    assert spec.pitch_deg == 0.0
    f = spec.width_px / (2.0 * math.tan(math.radians(spec.hfov_deg) / 2.0))
    xc = (u - spec.width_px / 2.0) / f * d
    yc = (v - spec.height_px / 2.0) / f * d
    yaw = math.radians(spec.yaw_deg)
    fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    return np.array(spec.mount_xyz_m) + d * fwd + xc * right + yc * down


def lift_bev(feats: np.ndarray, depth: np.ndarray, cams: list[Camera], grid: BEVGrid) -> np.ndarray:
    geom = LiftGeometry(cams, STRIDE)
    return lift_splat(torch.as_tensor(feats), torch.as_tensor(depth), geom, grid).numpy()


# ---------------------------------------------------------------- the lift


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lift_splat_matches_reference(seed):
    """The vectorised lift equals the per-point loop on random features and realistic depth (invalid zeros,
    depths beyond max_depth, points under the floor, outside the grid), 2 cameras, batch 2."""
    rng = np.random.default_rng(seed)
    cams, grid = cameras(), default_grid()
    h, w = H // STRIDE, W // STRIDE
    b, n, c = 2, 2, 5
    feats = rng.normal(size=(b, n, c, h, w))
    depth = rng.uniform(0.1, 12.0, size=(b, n, h, w))  # some < min_depth (0.3), some > max_depth (10)
    depth[rng.random(depth.shape) < 0.2] = 0.0  # invalid
    ref = lift_splat_reference(feats, depth, cams, STRIDE, grid)
    fast = lift_bev(feats, depth, cams, grid)
    assert fast.shape == ref.shape == (b, c, *grid.shape)
    np.testing.assert_allclose(fast, ref, rtol=1e-4, atol=1e-8)
    # the data exercise every branch: some points kept, some dropped by each rule
    occupied = (np.abs(ref).sum(1) > 0).sum()
    assert occupied > 20
    assert (depth > 10.0).any() and (depth == 0).any() and (depth[depth > 0] < 0.3).any()
    # among the valid depths, some points are under the floor and some outside the grid (hand geometry)
    under = outside = 0
    for bi, ci, r, c in zip(*np.nonzero((depth >= 0.3) & (depth <= 10.0)), strict=True):
        p = hand_point(SPECS[ci], c * STRIDE + STRIDE // 2 + 0.5, r * STRIDE + STRIDE // 2 + 0.5, depth[bi, ci, r, c])
        under += p[2] < grid.z_bound[0]
        outside += grid.z_bound[0] <= p[2] <= grid.z_bound[1] and grid.cell_of(p[0], p[1]) is None
    assert under > 10 and outside > 10
    # batches are independent: each batch element alone gives its slice
    one = lift_bev(feats[1:], depth[1:], cams, grid)
    np.testing.assert_allclose(one[0], fast[1], rtol=1e-6, atol=1e-10)


def _centre_lift_pixel() -> tuple[int, int]:
    """(row, col) of the lift pixel whose centre is nearest the image centre."""
    rows = np.arange(H // STRIDE) * STRIDE + STRIDE // 2 + 0.5
    cols = np.arange(W // STRIDE) * STRIDE + STRIDE // 2 + 0.5
    return int(np.argmin(np.abs(rows - H / 2))), int(np.argmin(np.abs(cols - W / 2)))


def _single_point_bev(cam_index: int, r: int, c: int, d: float, feat: np.ndarray) -> np.ndarray:
    cams, grid = cameras(), default_grid()
    h, w = H // STRIDE, W // STRIDE
    feats = np.zeros((1, 2, len(feat), h, w))
    feats[0, cam_index, :, r, c] = feat
    feats[0, 1 - cam_index] = 7.0  # features of the other camera, whose depth is all invalid
    depth = np.zeros((1, 2, h, w))
    depth[0, cam_index, r, c] = d
    return lift_bev(feats, depth, cams, grid)[0]


@pytest.mark.parametrize("cam_index", [0, 1])
def test_lift_point_at_known_depth_lands_in_hand_computed_cell(cam_index):
    """The centre lift pixel at 3.3 m ends up in the cell of T_base_cam K^-1 [u, v, 1] d computed by hand from
    the camera's yaw and mount, carrying exactly its feature vector; every other cell is 0."""
    r, c = _centre_lift_pixel()
    assert (r, c) == (5, 7)  # pixel (22, 30): centre (30.5, 22.5), 1.5 px from the image centre (32, 24)
    u, v = c * STRIDE + STRIDE // 2 + 0.5, r * STRIDE + STRIDE // 2 + 0.5
    d = 3.3
    p = hand_point(SPECS[cam_index], u, v, d)
    grid = default_grid()
    # the point is clear of cell boundaries (no float32 rounding ambiguity) and inside the height band
    for val, (lo, _, step) in ((p[0], grid.x_bound), (p[1], grid.y_bound)):
        frac = (val - lo) / step - math.floor((val - lo) / step)
        assert 0.02 < frac < 0.98
    assert grid.z_bound[0] < p[2] < grid.z_bound[1]
    cell = grid.cell_of(p[0], p[1])
    assert cell is not None
    # sanity of the hand geometry: the left camera looks left (y > 0), the right one right
    assert (p[1] > 0) == (cam_index == 0)
    feat = np.array([1.0, -2.0, 3.5])
    bev = _single_point_bev(cam_index, r, c, d, feat)
    np.testing.assert_allclose(bev[:, cell[0], cell[1]], feat, rtol=1e-6)
    rest = bev.copy()
    rest[:, cell[0], cell[1]] = 0.0
    assert not rest.any()


@pytest.mark.parametrize("cam_index", [0, 1])
def test_lift_drops_points_under_the_floor(cam_index):
    """A bottom-row pixel is kept at 1 m (z ≈ 0.31 m) but dropped at 5 m, where its back-projection is under the
    ground threshold z_bound[0] although its (x, y) is inside the grid."""
    grid = default_grid()
    r, c = H // STRIDE - 1, _centre_lift_pixel()[1]
    u, v = c * STRIDE + STRIDE // 2 + 0.5, r * STRIDE + STRIDE // 2 + 0.5
    near, far = hand_point(SPECS[cam_index], u, v, 1.0), hand_point(SPECS[cam_index], u, v, 5.0)
    assert near[2] > grid.z_bound[0] + 0.05 and far[2] < grid.z_bound[0]
    assert grid.cell_of(near[0], near[1]) is not None and grid.cell_of(far[0], far[1]) is not None
    feat = np.array([1.0, 2.0])
    kept = _single_point_bev(cam_index, r, c, 1.0, feat)
    i, j = grid.cell_of(near[0], near[1])
    np.testing.assert_allclose(kept[:, i, j], feat, rtol=1e-6)
    assert not _single_point_bev(cam_index, r, c, 5.0, feat).any()


@pytest.mark.parametrize("cam_index", [0, 1])
def test_lift_drops_points_outside_the_grid(cam_index):
    """The centre pixel at 9 m (a valid depth, < max_depth 10 m) back-projects beyond x_bound[1] = 6 m and is
    dropped; beyond max_depth it is dropped too."""
    grid = default_grid()
    r, c = _centre_lift_pixel()
    u, v = c * STRIDE + STRIDE // 2 + 0.5, r * STRIDE + STRIDE // 2 + 0.5
    p = hand_point(SPECS[cam_index], u, v, 9.0)
    assert p[0] > grid.x_bound[1] and grid.z_bound[0] < p[2] < grid.z_bound[1]
    assert grid.cell_of(p[0], p[1]) is None
    assert not _single_point_bev(cam_index, r, c, 9.0, np.array([1.0, 2.0])).any()
    assert not _single_point_bev(cam_index, r, c, 10.5, np.array([1.0, 2.0])).any()


def test_lift_sums_points_in_one_cell():
    """Two points that fall in the same cell are sum-pooled (vertical sum pooling)."""
    r, c = _centre_lift_pixel()
    cams, grid = cameras(), default_grid()
    h, w = H // STRIDE, W // STRIDE
    feats = np.zeros((1, 2, 2, h, w))
    depth = np.zeros((1, 2, h, w))
    feats[0, 0, :, r, c] = [1.0, 2.0]
    feats[0, 0, :, r - 1, c] = [10.0, 20.0]  # the pixel above: same (x, y) at the same depth, only higher
    depth[0, 0, r, c] = depth[0, 0, r - 1, c] = 3.3
    bev = lift_bev(feats, depth, cams, grid)[0]
    p = hand_point(SPECS[0], c * STRIDE + 2.5, r * STRIDE + 2.5, 3.3)
    i, j = grid.cell_of(p[0], p[1])
    np.testing.assert_allclose(bev[:, i, j], [11.0, 22.0], rtol=1e-6)
    assert np.count_nonzero(bev.sum(0)) == 1


# ---------------------------------------------------------------- depth sampling


@pytest.mark.parametrize("stride,hh,ww", [(4, 48, 64), (3, 10, 14), (5, 12, 11), (1, 3, 4)])
def test_sample_depth_picks_the_lift_pixels(stride, hh, ww):
    """sample_depth returns the pixels (s*r + s//2, s*c + s//2), for any leading dims."""
    depth = torch.arange(2 * 3 * hh * ww, dtype=torch.float32).view(2, 3, hh, ww)
    out = sample_depth(depth, stride)
    assert out.shape == (2, 3, hh // stride, ww // stride)
    for r in range(hh // stride):
        for c in range(ww // stride):
            assert torch.equal(out[..., r, c], depth[..., stride * r + stride // 2, stride * c + stride // 2])


# ---------------------------------------------------------------- ego-motion warp


def _hot_map(grid: BEVGrid, x: float, y: float) -> tuple[torch.Tensor, tuple[int, int]]:
    cell = grid.cell_of(x, y)
    assert cell is not None
    m = torch.zeros(1, 2, *grid.shape, dtype=torch.float64)
    m[0, 0, cell[0], cell[1]] = 1.0
    m[0, 1, cell[0], cell[1]] = -3.0
    return m, cell


def _assert_single_hot(out: torch.Tensor, cell: tuple[int, int]) -> None:
    assert out[0, 0, cell[0], cell[1]].item() == pytest.approx(1.0)
    assert out[0, 1, cell[0], cell[1]].item() == pytest.approx(-3.0)
    rest = out.clone()
    rest[0, :, cell[0], cell[1]] = 0.0
    assert not rest.any()


def _warp(m: torch.Tensor, pose_past, pose_now, grid: BEVGrid) -> torch.Tensor:
    rel = relative_pose(torch.tensor([pose_past], dtype=torch.float64), torch.tensor([pose_now], dtype=torch.float64))
    return warp_bev(m, rel, grid, mode="nearest")


def test_warp_forward_translation():
    """The robot moves 1 m forward: the hot cell at past (3.05, 0.55) appears at current (2.05, 0.55)."""
    grid = default_grid()
    m, _ = _hot_map(grid, 3.05, 0.55)
    out = _warp(m, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0), grid)
    _assert_single_hot(out, grid.cell_of(2.05, 0.55))


def test_warp_forward_translation_from_any_world_pose():
    """Only the relative motion matters: the same 1 m forward step from a rotated world pose gives the same map."""
    grid = default_grid()
    m, _ = _hot_map(grid, 3.05, 0.55)
    yaw = 2.1
    p0 = (4.0, -3.0, yaw)
    p1 = (4.0 + math.cos(yaw), -3.0 + math.sin(yaw), yaw)
    _assert_single_hot(_warp(m, p0, p1, grid), grid.cell_of(2.05, 0.55))


def test_warp_rotation_in_place():
    """The robot turns +90° (to the left) in place: past point (x, y) appears at current (y, -x)."""
    grid = default_grid()
    m, _ = _hot_map(grid, 1.05, 2.45)
    out = _warp(m, (0.0, 0.0, 0.0), (0.0, 0.0, math.pi / 2), grid)
    _assert_single_hot(out, grid.cell_of(2.45, -1.05))


def test_warp_general_motion_matches_world_geometry():
    """For a turn plus a translation, each current cell reads the past map at the same world point.

    The past map holds its own cell-centre coordinates (a linear field, which bilinear sampling reproduces
    exactly): after the warp, every current cell whose point lies well inside the past grid must hold the past
    coordinates of that point, computed here through world coordinates.
    """
    grid = default_grid()
    centres = grid.cell_centres()
    m = torch.as_tensor(centres).permute(2, 0, 1).unsqueeze(0).contiguous()  # 1 x 2 x X x Y: (x, y) past
    p0 = (1.0, 2.0, 0.4)
    # the new pose: 0.5 m forward and 0.3 m left of the past pose, turned by -30°
    c0, s0 = math.cos(p0[2]), math.sin(p0[2])
    p1 = (p0[0] + c0 * 0.5 - s0 * 0.3, p0[1] + s0 * 0.5 + c0 * 0.3, p0[2] - math.pi / 6)
    rel = relative_pose(torch.tensor([p0], dtype=torch.float64), torch.tensor([p1], dtype=torch.float64))
    out = warp_bev(m, rel, grid)[0].numpy()
    # current cell centres -> world -> past frame
    c1, s1 = math.cos(p1[2]), math.sin(p1[2])
    wx = p1[0] + c1 * centres[..., 0] - s1 * centres[..., 1]
    wy = p1[1] + s1 * centres[..., 0] + c1 * centres[..., 1]
    px = c0 * (wx - p0[0]) + s0 * (wy - p0[1])
    py = -s0 * (wx - p0[0]) + c0 * (wy - p0[1])
    inner = ((px > grid.x_bound[0] + 0.1) & (px < grid.x_bound[1] - 0.1)
             & (py > grid.y_bound[0] + 0.1) & (py < grid.y_bound[1] - 0.1))
    assert 0.3 < inner.mean() < 0.95
    np.testing.assert_allclose(out[0][inner], px[inner], atol=1e-9)
    np.testing.assert_allclose(out[1][inner], py[inner], atol=1e-9)
    outside = ((px < grid.x_bound[0] - 0.1) | (px > grid.x_bound[1] + 0.1)
               | (py < grid.y_bound[0] - 0.1) | (py > grid.y_bound[1] + 0.1))
    assert outside.any() and not out[:, outside].any()


def test_warp_cells_leaving_the_grid_disappear():
    """A hot cell that moves behind the robot vanishes; cells whose past position is beyond the grid read 0."""
    grid = default_grid()
    m, _ = _hot_map(grid, 0.55, 0.55)
    assert not _warp(m, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0), grid).any()
    ones = torch.ones(1, 1, *grid.shape, dtype=torch.float64)
    out = _warp(ones, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0), grid)[0, 0]
    i_edge = grid.cell_of(5.05, 0.0)[0]  # current x > 5 m was beyond x = 6 m in the past frame
    assert not out[i_edge:].any()
    assert bool((out[:i_edge] == 1.0).all())


def test_warp_identity_is_exact_with_bilinear():
    """No motion: bilinear warp returns the map unchanged."""
    grid = default_grid()
    m = torch.rand(2, 3, *grid.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    out = warp_bev(m, torch.zeros(2, 3, dtype=torch.float64), grid)
    torch.testing.assert_close(out, m, rtol=0, atol=1e-9)


def test_relative_pose_is_consistent_with_world_coordinates():
    """A point p in frame `to` has the same world coordinates whether mapped by `to`'s pose or by R(dyaw) p + d
    into `from` and then by `from`'s pose (the documented convention); dyaw is wrapped to (-pi, pi]."""
    rng = np.random.default_rng(3)
    pf = rng.uniform([-5, -5, -math.pi], [5, 5, math.pi], size=(20, 3))
    pt = rng.uniform([-5, -5, -math.pi], [5, 5, math.pi], size=(20, 3))
    rel = relative_pose(torch.as_tensor(pf), torch.as_tensor(pt)).numpy()
    p = rng.normal(size=(20, 2))

    def to_world(pose, q):
        c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
        return np.stack([pose[:, 0] + c * q[:, 0] - s * q[:, 1], pose[:, 1] + s * q[:, 0] + c * q[:, 1]], -1)

    in_from = to_world(rel, p)  # R(dyaw) p + (dx, dy)
    np.testing.assert_allclose(to_world(pf, in_from), to_world(pt, p), atol=1e-9)
    assert (np.abs(rel[:, 2]) <= math.pi + 1e-12).all()
    # and the identity
    np.testing.assert_allclose(relative_pose(torch.as_tensor(pf), torch.as_tensor(pf)).numpy(), 0.0, atol=1e-12)


# ---------------------------------------------------------------- grid checks


def test_default_grid_fits_the_cameras():
    """The default grid passes, and a reasonable share of it is in the cameras' field of view."""
    cams, grid = cameras(), default_grid()
    mask = check_grid_fits_cameras(grid, cams)
    assert mask.shape == grid.shape and mask.dtype == bool
    assert 0.5 <= mask.mean() < 1.0
    np.testing.assert_array_equal(mask, fov_mask(grid, cams))
    # cells straight ahead at mid-range are seen; the near corners beside the robot are not
    assert mask[grid.cell_of(3.0, 0.0)]
    assert not mask[grid.cell_of(0.05, 4.75)] and not mask[grid.cell_of(0.05, -4.75)]


def test_fov_mask_single_camera_sees_its_side():
    """The left camera (yaw +35°) sees far-left cells but not far-right ones, and vice versa."""
    cams, grid = cameras(), default_grid()
    left, right = fov_mask(grid, [cams[0]]), fov_mask(grid, [cams[1]])
    a, b = grid.cell_of(3.0, 2.5), grid.cell_of(3.0, -2.5)
    assert left[a] and not left[b]
    assert right[b] and not right[a]


def test_grid_beyond_max_depth_is_rejected():
    """A grid reaching 12 m forward with 10 m cameras raises a ConfigError naming max_depth."""
    grid = BEVGrid((0.0, 12.0, 0.1), (-4.8, 4.8, 0.1), (0.1, 2.0))
    with pytest.raises(ConfigError, match="max_depth"):
        check_grid_fits_cameras(grid, cameras())


def test_grid_behind_the_robot_is_rejected():
    """A grid behind the robot is (almost) out of the field of view: ConfigError."""
    grid = BEVGrid((-6.0, -0.5, 0.1), (-4.8, 4.8, 0.1), (0.1, 2.0))
    with pytest.raises(ConfigError, match="field of view"):
        check_grid_fits_cameras(grid, cameras())


def test_grid_with_no_cameras_is_rejected():
    with pytest.raises(ConfigError):
        check_grid_fits_cameras(default_grid(), [])


@pytest.mark.parametrize("kw", [
    {"x_bound": (0.0, 6.05, 0.1)},  # 60.5 cells
    {"y_bound": (-4.8, 4.8, 0.25)},  # 38.4 cells
    {"x_bound": (6.0, 6.0, 0.1)},  # max == min
    {"x_bound": (6.0, 0.0, 0.1)},  # max < min
    {"y_bound": (-1.0, 1.0, 0.0)},  # zero step
    {"z_bound": (2.0, 0.1)},  # max < min
])
def test_grid_validate_rejects_bad_bounds(kw):
    """BEVGrid.validate rejects a non-integer cell count, max <= min, a non-positive step."""
    args = {"x_bound": (0.0, 6.0, 0.1), "y_bound": (-4.8, 4.8, 0.1), "z_bound": (0.1, 2.0)} | kw
    with pytest.raises(ConfigError):
        BEVGrid(**args).validate()


def test_grid_shape_cell_of_and_centres_agree():
    """shape, cell_centres and cell_of use the same layout: the centre of cell (i, j) is in cell (i, j)."""
    grid = BEVGrid((0.0, 4.0, 0.2), (-3.2, 3.2, 0.2), (0.1, 2.0))
    grid.validate()
    assert grid.shape == (20, 32)
    c = grid.cell_centres()
    assert c.shape == (20, 32, 2)
    assert c[0, 0].tolist() == pytest.approx([0.1, -3.1])
    assert c[19, 31].tolist() == pytest.approx([3.9, 3.1])
    for i, j in [(0, 0), (7, 13), (19, 31)]:
        assert grid.cell_of(*c[i, j]) == (i, j)
    assert grid.cell_of(-0.01, 0.0) is None and grid.cell_of(4.01, 0.0) is None
    assert grid.cell_of(1.0, 3.3) is None and grid.cell_of(1.0, -3.3) is None


# ---------------------------------------------------------------- helpers


def test_bev_to_image_flips_both_axes():
    """bev_to_image reverses X and Y (and leaves trailing channel axes alone)."""
    bev = np.arange(3 * 4 * 2).reshape(3, 4, 2)
    img = bev_to_image(bev)
    assert img.shape == bev.shape
    for i in range(3):
        for j in range(4):
            np.testing.assert_array_equal(img[i, j], bev[2 - i, 3 - j])
    assert img.flags["C_CONTIGUOUS"]
    # the robot heads up: the farthest row is on top, the left-most (largest y) column on the left
    assert img[0, 0, 0] == bev[-1, -1, 0]


def test_camera_round_trip_and_spec_conversion():
    """Camera.from_dict(CameraSpec.to_dict()) keeps K, T and the depth range; to_dict round-trips."""
    cam = cameras()[0]
    np.testing.assert_allclose(cam.K_np, SPECS[0].K)
    np.testing.assert_allclose(cam.T_np, SPECS[0].T_base_cam)
    assert (cam.width, cam.height, cam.min_depth_m, cam.max_depth_m) == (W, H, 0.3, 10.0)
    assert Camera.from_dict(cam.to_dict()) == cam


@pytest.mark.parametrize("mutate", [
    lambda d: d.pop("K"),
    lambda d: d.pop("max_depth_m"),
    lambda d: d.update(K=[[1.0, 0.0], [0.0, 1.0]]),
    lambda d: d.update(T_base_cam=np.eye(3).tolist()),
    lambda d: d.update(K="not a matrix"),
    lambda d: d.update(K=[[1.0, 0.0, 1.0], [0.0, 1.0]]),
    lambda d: d.update(width="wide"),
    lambda d: d.update(width=0),
    lambda d: d.update(height=None),
    lambda d: d.update(max_depth_m=[1, 2]),
])
def test_camera_from_malformed_dict_raises(mutate):
    """A malformed camera mapping raises CorruptArtifactError (not KeyError/ValueError/...)."""
    d = SPECS[0].to_dict()
    mutate(d)
    with pytest.raises(CorruptArtifactError):
        Camera.from_dict(d, where="meta/icrowdnav.json cameras.left")


@pytest.mark.parametrize("bad", [None, [1, 2, 3], "camera"])
def test_camera_from_non_mapping_raises(bad):
    with pytest.raises(CorruptArtifactError):
        Camera.from_dict(bad)


# ---------------------------------------------------------------- depth evidence (hits / floor / free rays)


def evidence_reference(depth: np.ndarray, cams: list[Camera], stride: int, grid: BEVGrid) -> np.ndarray:
    """The obvious per-point loop of :func:`lift_evidence` for one frame: ``N x h x w`` depth → ``3 x X x Y``."""
    from pretrain.geometry import FREE_MARGIN_M, FREE_SAMPLES, free_offsets

    nx, ny = grid.shape
    counts = np.zeros((3, nx, ny))
    rows, cols = lift_pixel_index(cams[0].height, cams[0].width, stride)
    offsets = free_offsets(rows.shape).numpy()[..., 0]

    def add(ch: int, p: np.ndarray) -> None:
        i = math.floor((p[0] - grid.x_bound[0]) / grid.x_bound[2])
        j = math.floor((p[1] - grid.y_bound[0]) / grid.y_bound[2])
        if 0 <= i < nx and 0 <= j < ny:
            counts[ch, i, j] += 1

    for n, cam in enumerate(cams):
        K, T = cam.K_np, cam.T_np
        for r in range(rows.shape[0]):
            for c in range(rows.shape[1]):
                d = float(depth[n, r, c])
                if not (d > 0 and cam.min_depth_m <= d <= cam.max_depth_m):
                    continue
                ray = T[:3, :3] @ np.array([(cols[r, c] + 0.5 - K[0, 2]) / K[0, 0],
                                            (rows[r, c] + 0.5 - K[1, 2]) / K[1, 1], 1.0])
                p = T[:3, 3] + d * ray
                if grid.z_bound[0] <= p[2] <= grid.z_bound[1]:
                    add(0, p)
                elif p[2] < grid.z_bound[0]:
                    add(1, p)
                for s in range(FREE_SAMPLES):
                    q = T[:3, 3] + max(d - FREE_MARGIN_M, 0.0) * (s + offsets[r, c]) / FREE_SAMPLES * ray
                    if q[2] <= grid.z_bound[1]:
                        add(2, q)
    return np.log1p(counts)


@pytest.mark.parametrize("seed", [0, 1])
def test_lift_evidence_matches_reference(seed):
    """The vectorised evidence equals the per-point loop (floor hits included: the depths reach the floor)."""
    from pretrain.geometry import LiftGeometry, lift_evidence

    cams, grid = cameras(), default_grid()
    rng = np.random.default_rng(seed)
    h, w = lift_pixel_index(H, W, STRIDE)[0].shape
    depth = rng.uniform(0.0, 7.0, (1, 2, h, w)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.1] = 0.0  # invalid pixels
    got = lift_evidence(torch.from_numpy(depth), LiftGeometry(cams, STRIDE), grid)[0].numpy()
    want = evidence_reference(depth[0], cams, STRIDE, grid)
    assert got.shape == (3, *grid.shape)
    np.testing.assert_allclose(got, want, atol=1e-5)
    assert want[1].sum() > 0 and want[0].sum() > 0 and want[2].sum() > want[0].sum()


def test_free_rays_mark_the_cells_before_a_wall():
    """A wall 3 m ahead of the left camera: hits at 3 m, free cells between camera and wall, nothing behind it."""
    from pretrain.geometry import LiftGeometry, lift_evidence

    spec = CameraSpec("front", W, H, 70.0, 0.0, 0.0, (0.0, 0.0, 0.8))
    cam = Camera.from_dict(spec.to_dict())
    grid = default_grid()
    h, w = lift_pixel_index(H, W, STRIDE)[0].shape
    depth = torch.full((1, 1, h, w), 3.0)
    ev = lift_evidence(depth, LiftGeometry([cam], STRIDE), grid)[0]
    rows = ev.sum(2)  # 3 x X: evidence per distance ahead, over every lateral cell
    wall = grid.cell_of(3.0, 0.0)[0]
    assert rows[0, wall - 1:wall + 2].sum() > 0 and rows[0, :wall - 1].sum() == 0  # hits only at the wall
    assert (rows[2, 1:wall - 1] > 0).all()  # free rays in front of it, without gaps
    assert rows[:, wall + 2:].sum() == 0  # nothing known behind it
