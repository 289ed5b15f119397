"""Tests of sim.geometry (boxes, cylinders, signed distance, ray casts) and the grid lookups of SceneLayout."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.geometry import (
    Box,
    Cylinder,
    StaticGeometry,
    robot_to_world,
    signed_distance_reference,
    world_to_robot,
    wrap_angle,
)
from sim.scene import GRID_RES_M, load_scene


def random_obstacles(rng: np.random.Generator, n_boxes: int = 5, n_cyl: int = 4) -> list:
    obs: list = []
    for _ in range(n_boxes):
        obs.append(Box(center=tuple(rng.uniform(-4, 4, 2)), size=tuple(rng.uniform(0.2, 2.5, 2)),
                       yaw=float(rng.uniform(-math.pi, math.pi))))
    for _ in range(n_cyl):
        obs.append(Cylinder(center=tuple(rng.uniform(-4, 4, 2)), radius_m=float(rng.uniform(0.1, 1.0))))
    return obs


def box_corners(o: Box) -> np.ndarray:
    c, s = math.cos(o.yaw), math.sin(o.yaw)
    out = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            lx, ly = sx * o.size[0] / 2, sy * o.size[1] / 2
            out.append((o.center[0] + c * lx - s * ly, o.center[1] + s * lx + c * ly))
    return np.array(out)


# ------------------------------------------------------------------------------------------ signed distance
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_signed_distance_matches_reference(seed):
    rng = np.random.default_rng(seed)
    obs = random_obstacles(rng)
    geo = StaticGeometry(obs)
    pts = rng.uniform(-6, 6, (400, 2))
    d, _ = geo.signed_distance(pts)
    ref = np.array([signed_distance_reference(obs, tuple(p)) for p in pts])
    np.testing.assert_allclose(d, ref, atol=1e-9)
    assert (d < 0).any() and (d > 0).any()  # the sample covers inside and outside points


@pytest.mark.parametrize("kind", ["boxes", "cylinders", "mixed"])
def test_signed_distance_only_boxes_or_cylinders(kind):
    rng = np.random.default_rng(7)
    obs = random_obstacles(rng, n_boxes=0 if kind == "cylinders" else 4, n_cyl=0 if kind == "boxes" else 4)
    geo = StaticGeometry(obs)
    assert geo.n_obstacles == len(obs)
    pts = rng.uniform(-6, 6, (200, 2))
    d, _ = geo.signed_distance(pts)
    ref = np.array([signed_distance_reference(obs, tuple(p)) for p in pts])
    np.testing.assert_allclose(d, ref, atol=1e-9)


@pytest.mark.parametrize("seed", [0, 5])
def test_closest_points_lie_on_the_nearest_surface(seed):
    rng = np.random.default_rng(seed)
    obs = random_obstacles(rng)
    geo = StaticGeometry(obs)
    pts = rng.uniform(-6, 6, (400, 2))
    d, closest = geo.signed_distance(pts)
    d_on, _ = geo.signed_distance(closest)
    # a closest point sits on some surface; it may be inside another, overlapping obstacle, so compare with the
    # distance to the nearest obstacle's own surface
    per_obstacle = np.stack([StaticGeometry([o]).signed_distance(closest)[0] for o in obs], axis=1)
    assert np.all(np.min(np.abs(per_obstacle), axis=1) < 1e-9)
    assert np.all(d_on <= 1e-9)
    # and it is |d| away from the query point
    np.testing.assert_allclose(np.linalg.norm(pts - closest, axis=1), np.abs(d), atol=1e-9)


def test_signed_distance_keeps_leading_shape_and_known_values():
    geo = StaticGeometry([Box((0.0, 0.0), (2.0, 1.0)), Cylinder((5.0, 0.0), 1.0)])
    pts = np.array([[[3.0, 0.0], [0.0, 0.0]], [[5.0, 0.5], [0.0, 2.5]]])
    d, closest = geo.signed_distance(pts)
    assert d.shape == (2, 2) and closest.shape == (2, 2, 2)
    np.testing.assert_allclose(d, [[1.0, -0.5], [-0.5, 2.0]], atol=1e-12)
    np.testing.assert_allclose(closest[0, 0], [4.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(closest[0, 1], [0.0, 0.5], atol=1e-12)  # inside: out through the nearest face
    np.testing.assert_allclose(closest[1, 1], [0.0, 0.5], atol=1e-12)


def test_signed_distance_without_obstacles_is_infinite():
    geo = StaticGeometry([])
    pts = np.array([[1.0, 2.0], [3.0, -1.0]])
    d, closest = geo.signed_distance(pts)
    assert np.all(np.isinf(d)) and np.all(d > 0)
    np.testing.assert_array_equal(closest, pts)


# ------------------------------------------------------------------------------------------------ ray casts
def test_raycast_box_known_distances():
    geo = StaticGeometry([Box((5.0, 0.0), (2.0, 2.0))])
    hits = geo.raycast(np.zeros(2), np.array([0.0, math.pi, math.pi / 2, math.atan2(0.5, 4.0)]), 20.0)
    np.testing.assert_allclose(hits[:3], [4.0, 20.0, 20.0], atol=1e-9)
    np.testing.assert_allclose(hits[3], math.hypot(4.0, 0.5), atol=1e-9)


def test_raycast_rotated_box_hits_the_corner():
    # a 2 x 2 box turned by 45 degrees is a diamond whose left corner lies at x = 5 - sqrt(2)
    geo = StaticGeometry([Box((5.0, 0.0), (2.0, 2.0), yaw=math.pi / 4)])
    hit = geo.raycast(np.zeros(2), np.array([0.0]), 20.0)
    np.testing.assert_allclose(hit, [5.0 - math.sqrt(2.0)], atol=1e-9)
    # a ray along y = 0.5 meets the diamond's lower-left face at x = 5 - sqrt(2) + 0.5
    hit = geo.raycast(np.array([0.0, 0.5]), np.array([0.0]), 20.0)
    np.testing.assert_allclose(hit, [5.0 - math.sqrt(2.0) + 0.5], atol=1e-9)


def test_raycast_cylinder_known_distances():
    geo = StaticGeometry([Cylinder((5.0, 1.0), 2.0)])
    hits = geo.raycast(np.zeros(2), np.array([0.0, math.pi, -math.pi / 2]), 20.0)
    np.testing.assert_allclose(hits, [5.0 - math.sqrt(3.0), 20.0, 20.0], atol=1e-9)


@pytest.mark.parametrize("obstacle", [Box((0.0, 0.0), (2.0, 1.0), yaw=0.3), Cylinder((0.0, 0.0), 1.0)])
def test_raycast_from_inside_returns_zero(obstacle):
    geo = StaticGeometry([obstacle])
    ang = np.linspace(-math.pi, math.pi, 16, endpoint=False)
    np.testing.assert_array_equal(geo.raycast(np.array([0.1, 0.05]), ang, 10.0), np.zeros(16))


def test_raycast_clips_to_max_range():
    geo = StaticGeometry([Box((50.0, 0.0), (2.0, 2.0))])
    np.testing.assert_allclose(geo.raycast(np.zeros(2), np.array([0.0]), 10.0), [10.0])
    np.testing.assert_allclose(StaticGeometry([]).raycast(np.zeros(2), np.array([0.0, 1.0]), 3.0), [3.0, 3.0])


@pytest.mark.parametrize("seed", [0, 1])
def test_raycast_agrees_with_sphere_tracing(seed):
    rng = np.random.default_rng(seed)
    obs = random_obstacles(rng)
    geo = StaticGeometry(obs)
    origins = rng.uniform(-6, 6, (600, 2))
    origins = origins[geo.signed_distance(origins)[0] > 0.05][:300]
    ang = rng.uniform(-math.pi, math.pi, len(origins))
    max_range = 15.0
    hits = geo.raycast(origins, ang, max_range)
    # march along each ray by the distance to the nearest surface (exact for a signed distance field)
    direction = np.stack([np.cos(ang), np.sin(ang)], -1)
    t = np.zeros(len(origins))
    for _ in range(400):
        d, _ = geo.signed_distance(origins + t[:, None] * direction)
        t = np.minimum(t + np.maximum(d, 0.0), max_range)
    np.testing.assert_allclose(hits, t, atol=2e-3)
    assert (hits < max_range).sum() > 50  # many rays actually hit something


def test_segment_clear():
    geo = StaticGeometry([Box((0.0, 0.0), (1.0, 1.0))])
    a = np.array([[-3.0, 0.0], [-3.0, 1.0], [-3.0, 2.0]])
    b = np.array([[3.0, 0.0], [3.0, 1.0], [3.0, 2.0]])
    np.testing.assert_array_equal(geo.segment_clear(a, b, margin=0.6), [False, False, True])
    np.testing.assert_array_equal(geo.segment_clear(a, b, margin=0.4), [False, True, True])


def test_wrap_angle_range():
    a = np.linspace(-20, 20, 1001)
    w = wrap_angle(a)
    assert np.all(w >= -math.pi) and np.all(w < math.pi)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-9)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-9)


# ---------------------------------------------------------------------------------------- clearance grids
def _layout_samples(name: str, seed: int, n: int = 12000):
    spec = load_scene(name)
    layout = spec.layout(np.random.default_rng(seed))
    rng = np.random.default_rng(100 + seed)
    x0, x1, y0, y1 = spec.bounds
    pts = np.stack([rng.uniform(x0, x1, n), rng.uniform(y0, y1, n)], -1)
    corners = np.concatenate([box_corners(o) for o in layout.obstacles if isinstance(o, Box)])
    d_corner = np.min(np.linalg.norm(pts[:, None] - corners[None], axis=-1), axis=1)
    return layout, pts, d_corner


@pytest.mark.parametrize("name,seed", [("office_lobby", 0), ("warehouse", 3), ("hospital_floor", 0)])
def test_clearance_fast_matches_exact_away_from_corners_and_medial_lines(name, seed):
    layout, pts, d_corner = _layout_samples(name, seed)
    # distance to each obstacle on its own: a point is on a medial line where two surfaces are nearly equidistant
    per = np.sort(np.stack([StaticGeometry([o]).signed_distance(pts)[0] for o in layout.obstacles], 1), axis=1)
    keep = (d_corner > 0.1) & (per[:, 0] > 0.0) & (per[:, 1] - per[:, 0] > 3 * GRID_RES_M)
    assert keep.sum() > 3000
    exact = layout.clearance_at(pts[keep])
    fast, grad = layout.clearance_fast(pts[keep])
    assert np.max(np.abs(fast - exact)) < 0.01
    # the gradient is a unit vector pointing away from the nearest surface
    _, closest = layout.geometry.signed_distance(pts[keep])
    away = pts[keep] - closest
    away /= np.linalg.norm(away, axis=1, keepdims=True)
    far = exact > 0.1
    norm = np.linalg.norm(grad[far], axis=1)
    np.testing.assert_allclose(np.median(norm), 1.0, atol=0.01)
    assert np.all((norm > 0.85) & (norm < 1.15))  # curved surfaces (pillars, box corners) bend it a little
    assert np.min((grad[far] * away[far]).sum(1) / norm) > 0.96


@pytest.mark.parametrize("name,seed", [("office_lobby", 0), ("warehouse", 3)])
def test_clearance_fast_error_is_bounded_by_half_a_cell_in_free_space(name, seed):
    layout, pts, _ = _layout_samples(name, seed)
    exact = layout.clearance_at(pts)
    fast, _ = layout.clearance_fast(pts)
    free = exact > 0
    assert np.max(np.abs(fast - exact)[free]) <= GRID_RES_M / 2 + 1e-3


def test_frame_transforms_known_values_and_round_trip():
    pose = (1.0, 2.0, np.pi / 2)  # robot at (1, 2) facing +y
    # a point 1 m along +y from the robot is 1 m ahead; 1 m along −x is 1 m to its left
    np.testing.assert_allclose(world_to_robot(np.array([[1.0, 3.0], [0.0, 2.0]]), pose), [[1, 0], [0, 1]],
                               atol=1e-12)
    # vectors rotate without the translation; a trailing z column is kept
    np.testing.assert_allclose(world_to_robot(np.array([0.0, 1.0, 0.7]), pose, vectors=True), [1, 0, 0.7],
                               atol=1e-12)
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(5, 7, 3))
    for vec in (False, True):
        back = robot_to_world(world_to_robot(pts, (0.3, -1.2, 2.5), vectors=vec), (0.3, -1.2, 2.5), vectors=vec)
        np.testing.assert_allclose(back, pts, atol=1e-12)


def test_world_to_robot_each_equals_one_pose_at_a_time():
    from sim.geometry import world_to_robot_each

    rng = np.random.default_rng(0)
    pts, poses = rng.normal(size=(20, 2)) * 5, np.c_[rng.normal(size=(20, 2)) * 5, rng.uniform(-4, 4, 20)]
    one = np.stack([world_to_robot(p, q) for p, q in zip(pts, poses, strict=True)])
    np.testing.assert_allclose(world_to_robot_each(pts, poses), one, atol=1e-12)
