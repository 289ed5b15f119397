"""Tests of sim.viz: the matplotlib plot, the OpenCV top-down raster, H.264 writing and panel composition."""

from __future__ import annotations

import math
import time
from pathlib import Path

import av
import cv2
import numpy as np
import pytest

from sim.geometry import Box, Cylinder
from sim.trace import EpisodeTrace
from sim.viz import (
    _OBSTACLE,
    _PED,
    _ROBOT,
    TopDownRenderer,
    box_corners,
    colorize_depth,
    compose_frame,
    plot_episode_topdown,
    write_video,
)

OBSTACLES = [Box(center=(2.0, 2.0), size=(1.0, 0.4), yaw=0.5), Cylinder(center=(-3.0, 1.0), radius_m=0.5)]


def _trace(t_steps: int = 40, n: int = 3, dt: float = 0.25) -> EpisodeTrace:
    t = np.arange(t_steps + 1) * dt
    robot = np.column_stack([-4.0 + 0.8 * t, -1.0 + 0.3 * np.sin(t), np.full_like(t, 0.2)])
    vel = np.zeros((t_steps + 1, n, 2))
    vel[..., 0] = -0.6
    ped0 = np.column_stack([np.linspace(3.0, 5.0, n), np.linspace(-2.0, 1.0, n)])
    ped = ped0[None] + vel * t[:, None, None]
    return EpisodeTrace(
        dt_s=dt,
        robot_radius_m=0.3,
        goal_radius_m=0.4,
        robot_pose=robot,
        robot_cmd=np.zeros((t_steps, 2)),
        goal_xy=np.array([5.0, -1.0]),
        start_xy=robot[0, :2].copy(),
        ped_xy=ped,
        ped_vel=vel,
        ped_radius=np.full(n, 0.25),
        ped_yaw=np.full((t_steps + 1, n), math.pi),
        ped_head_yaw=np.full((t_steps + 1, n), math.pi - 0.4),
        static_clearance_m=np.full(t_steps + 1, 1.5),
        outcome="timeout",
        shortest_path_m=9.0,
        scene="hall",
        density=0.3,
        seed=3,
        method="demo",
    )


def test_box_corners_rotated() -> None:
    c = box_corners(Box(center=(1.0, 2.0), size=(2.0, 1.0), yaw=math.pi / 2))
    np.testing.assert_allclose(c, [[1.5, 1.0], [1.5, 3.0], [0.5, 3.0], [0.5, 1.0]], atol=1e-12)


def test_plot_episode_topdown_writes_png(tmp_path: Path) -> None:
    out = plot_episode_topdown(OBSTACLES, _trace(), tmp_path / "figs" / "ep.png", title="unit test")
    assert out == tmp_path / "figs" / "ep.png"
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = cv2.imread(str(out))
    assert img is not None and 600 <= img.shape[1] <= 2000 and 500 <= img.shape[0] <= 2000
    assert img.std() > 10  # not blank
    assert [p.name for p in out.parent.iterdir()] == ["ep.png"]  # no temp files left
    # explicit bounds/snapshots, no pedestrians, a single-state episode
    empty = _trace(t_steps=0, n=0)
    out2 = plot_episode_topdown([], empty, tmp_path / "e.png", bounds=(-6, 6, -4, 4), snapshot_steps=[0])
    assert out2.stat().st_size > 1000
    with pytest.raises(ValueError, match="snapshot_steps"):
        plot_episode_topdown([], _trace(), tmp_path / "bad.png", snapshot_steps=[0, 99])


def test_topdown_renderer_pixel_convention_and_speed() -> None:
    r = TopDownRenderer(OBSTACLES, bounds=(-10.0, 10.0, -10.0, 10.0), px_per_m=40)
    assert (r.height, r.width) == (800, 800)
    np.testing.assert_allclose(r.world_to_pixel(np.array([[-10.0, 10.0], [0.0, 0.0]])), [[0, 0], [400, 400]])
    ped = np.array([[3.2, -4.7]])
    # heading / head lines point +x, so probe the disc 0.15 m to the side (+y, i.e. up in the image)
    img = r.draw(
        robot_pose=np.array([-5.5, 6.2, 0.0]),
        ped_xy=ped,
        ped_yaw=np.zeros(1),
        ped_head_yaw=np.zeros(1),
        ped_radius=np.array([0.25]),
        goal_xy=np.array([8.0, 8.0]),
        trail_xy=np.array([[-7.0, 6.2], [-6.5, 6.2], [-5.5, 6.2]]),
    )
    assert img.shape == (800, 800, 3) and img.dtype == np.uint8
    col, row = int((3.2 + 10.0) * 40), int((10.0 - (-4.7 + 0.15)) * 40)
    assert tuple(img[row, col]) == _PED
    assert tuple(img[int((10.0 - 4.7 - 0.15) * 40), col]) == (255, 255, 255)  # mirrored: floor, so +y is up
    robot_col, robot_row = int((-5.5 + 10.0) * 40), int((10.0 - 6.2 - 0.15) * 40)
    assert tuple(img[robot_row, robot_col]) == _ROBOT
    assert tuple(img[int((10.0 - 1.0) * 40), int((-3.0 + 10.0) * 40)]) == _OBSTACLE  # cylinder centre
    assert not r.background.flags.writeable and tuple(r.background[robot_row, robot_col]) == (255, 255, 255)
    # odd-sized map: sizes round up
    assert TopDownRenderer([], bounds=(0.0, 1.01, 0.0, 0.5), px_per_m=10).background.shape == (5, 11, 3)

    rng = np.random.default_rng(0)
    n = 20
    args = dict(
        ped_xy=rng.uniform(-9, 9, (n, 2)),
        ped_yaw=rng.uniform(-3, 3, n),
        ped_head_yaw=rng.uniform(-3, 3, n),
        ped_radius=np.full(n, 0.25),
        goal_xy=np.array([8.0, 8.0]),
        trail_xy=np.cumsum(rng.normal(0.0, 0.08, (400, 2)), axis=0),  # ~0.1 m steps
    )
    r.draw(np.array([0.0, 0.0, 0.3]), **args)
    frames = 100
    t0 = time.perf_counter()
    for k in range(frames):
        r.draw(np.array([0.01 * k, 0.0, 0.3]), **args)
    ms = (time.perf_counter() - t0) / frames * 1e3
    print(f"TopDownRenderer.draw: {ms:.3f} ms/frame (800x800, {n} pedestrians, 400-point trail)")


def test_write_video_round_trip(tmp_path: Path) -> None:
    h, w, n = 63, 81, 12  # odd sizes are padded to even
    frames = [np.full((h, w, 3), (20 * i, 255 - 20 * i, 128), dtype=np.uint8) for i in range(n)]
    out = write_video(iter(frames), tmp_path / "v.mp4", fps=10.0)
    assert [p.name for p in tmp_path.iterdir()] == ["v.mp4"]
    with av.open(str(out)) as c:
        stream = c.streams.video[0]
        assert stream.codec_context.name in ("h264", "libx264")
        decoded = [f.to_ndarray(format="rgb24") for f in c.decode(stream)]
    assert len(decoded) == n and decoded[0].shape == (64, 82, 3)
    assert np.abs(decoded[5][:h, :w].astype(int) - frames[5].astype(int)).mean() < 6


def test_write_video_errors(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no frames"):
        write_video([], tmp_path / "a.mp4", fps=5)
    frames = [np.zeros((32, 32, 3), np.uint8)] * 3 + [np.zeros((32, 30, 3), np.uint8)]
    with pytest.raises(ValueError, match="frame 3"):
        write_video(frames, tmp_path / "b.mp4", fps=5)
    with pytest.raises(ValueError, match="frame 0"):
        write_video([np.zeros((32, 32), np.float32)], tmp_path / "c.mp4", fps=5)
    assert list(tmp_path.iterdir()) == []


def test_compose_frame_with_depth_panel() -> None:
    rgb = np.full((120, 160, 3), 200, dtype=np.uint8)
    depth = np.full((60, 80), 5.0, dtype=np.float32)
    depth[:, :40] = 0.0  # invalid half
    depth[0, 79] = np.nan
    out = compose_frame([rgb, depth], ["rgb", "depth"], height=240)
    assert out.shape == (240, 320 + 320, 3) and out.dtype == np.uint8
    assert (out[200:, 320:470] == 0).all()  # invalid depth is black
    mid = out[200, 600]
    np.testing.assert_array_equal(mid, colorize_depth(np.array([[5.0]]))[0, 0])
    assert mid.sum() > 100  # valid depth is coloured
    assert out[3, 2].sum() < rgb[0, 0].sum()  # label strip darkened
    assert (out[200:, 5:300] == 200).all()  # the rgb panel body is untouched
    gray = compose_frame([np.zeros((10, 30), np.uint8)], [""], height=20)
    assert gray.shape == (20, 60, 3)
    with pytest.raises(ValueError, match="labels"):
        compose_frame([rgb], ["a", "b"])
    with pytest.raises(ValueError, match="panel 0"):
        compose_frame([np.zeros((4, 4, 4), np.uint8)], ["x"])


def test_colorize_depth_fixed_scale() -> None:
    c = colorize_depth(np.array([[0.0, 1.0, 10.0, 50.0, -1.0]]))
    assert (c[0, 0] == 0).all() and (c[0, 4] == 0).all()
    np.testing.assert_array_equal(c[0, 2], c[0, 3])  # clipped at 10 m
    assert not np.array_equal(c[0, 1], c[0, 2])
