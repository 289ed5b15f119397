"""Tests of sim.scene: shipped scenes, the YAML schema and its errors, layouts, densities, start/goal sampling."""

from __future__ import annotations

import copy
import dataclasses
import math

import numpy as np
import pytest
import yaml
from scipy.sparse.csgraph import dijkstra

from pipeline.core.errors import ConfigError, InputMissingError
from sim.env import CrowdNavEnv
from sim.geometry import Box, Cylinder, StaticGeometry
from sim.scene import (
    NAV_RES_M,
    SPLITS,
    SceneLayout,
    available_scenes,
    load_scene,
    parse_scene,
    scenes_of_split,
)

SHIPPED = ["cluttered_room", "corner", "doorway", "hallway", "hospital_corridor", "hospital_floor", "office_floor",
           "office_lobby", "open_crowd", "warehouse", "warehouse_routing"]
ROBOT_RADIUS = 0.3


# ----------------------------------------------------------------------------------------------- shipped scenes
def test_available_scenes_lists_the_shipped_files():
    names = available_scenes()
    assert names == sorted(names)
    assert set(SHIPPED) <= set(names)


@pytest.mark.parametrize("name", available_scenes())
def test_every_shipped_scene_loads_and_builds_a_layout(name):
    spec = load_scene(name)
    assert spec.name == name and spec.split in SPLITS
    assert spec.path.endswith(f"{name}.yaml")
    layout = spec.layout(np.random.default_rng(0))
    x0, x1, y0, y1 = spec.bounds
    assert 0 < layout.free_area_m2 < (x1 - x0) * (y1 - y0)
    assert layout.occupancy.shape == layout.clearance.shape
    # the outer walls enclose the scene: a ray from any free point hits something within the bounds' diagonal
    pts = layout.free_points(np.random.default_rng(1), 20, 0.3)
    ang = np.linspace(0, 2 * np.pi, 20, endpoint=False)
    diag = math.hypot(x1 - x0, y1 - y0)
    assert np.all(layout.geometry.raycast(pts, ang, 10 * diag) < diag)


def test_splits():
    assert scenes_of_split("test") == ["hospital_corridor", "office_lobby", "warehouse", "warehouse_routing"]
    assert scenes_of_split("long_horizon") == ["hospital_floor", "office_floor"]
    assert set(scenes_of_split("train")) == {"cluttered_room", "corner", "doorway", "hallway", "open_crowd"}


def _free_width(name: str, x: float) -> float:
    spec = load_scene(name)
    layout = spec.layout()
    y = (spec.bounds[2] + spec.bounds[3]) / 2
    hits = layout.geometry.raycast(np.array([x, y]), np.array([np.pi / 2, -np.pi / 2]), 100.0)
    return float(hits.sum())


@pytest.mark.parametrize("name,x,width", [("office_lobby", 7.5, 7.0), ("hospital_corridor", 10.5, 4.0),
                                          ("hallway", 7.0, 3.0)])
def test_paper_scene_free_widths_wall_to_wall(name, x, width):
    assert _free_width(name, x) == pytest.approx(width, abs=0.02)


@pytest.mark.parametrize("name,x,width", [("office_lobby", 7.5, 7.0), ("hospital_corridor", 10.5, 4.0),
                                          ("hallway", 7.0, 3.0)])
def test_paper_scene_widths_within_a_wall_thickness(name, x, width):
    spec = load_scene(name)
    assert spec.bounds[3] - spec.bounds[2] <= width + 0.2 + 1e-9
    assert width - spec.wall_thickness_m - 1e-6 <= _free_width(name, x) <= width + 1e-6


def test_warehouse_aisles_are_2_5_m_between_shelf_rows():
    spec = load_scene("warehouse")
    shelves = [o for o in spec.obstacles if isinstance(o, Box)]
    assert len(shelves) == 2
    geo = StaticGeometry([*shelves, *spec.outer_walls()])  # fixed shelves only (the clutter could stand in an aisle)
    for x in (3.0, 7.0, 11.0):  # each of the three aisles is 2.5 m from shelf to shelf or wall
        for y in (1.25, 4.75, 8.25):
            hits = geo.raycast(np.array([x, y]), np.array([np.pi / 2, -np.pi / 2]), 50.0)
            assert hits.sum() == pytest.approx(2.5, abs=1e-9)
    for x in (1.25, 12.75):  # the cross aisles at both ends are 2.5 m wide too
        hits = geo.raycast(np.array([x, 3.0]), np.array([0.0, np.pi]), 50.0)  # beside a shelf row's end
        assert hits.sum() == pytest.approx(2.5, abs=1e-9)


def test_warehouse_pairs_need_no_route_round_a_shelf():
    """Start and goal ~6 m apart along a path at most 1.25 x the straight line (the paper's aisle test); the shelf
    hall (warehouse_routing) keeps pairs whose route goes round a shelf."""
    spec = load_scene("warehouse")
    assert spec.start_goal.max_detour == 1.25
    ratios = []
    for seed in range(12):
        layout = spec.layout(np.random.default_rng(seed))
        start, goal, length = layout.sample_start_goal(np.random.default_rng(100 + seed), 0.3)
        straight = float(np.hypot(*(goal - start)))
        assert 5.45 <= straight <= 6.55  # the goal is jittered within its grid cell
        ratios.append(length / straight)
    assert max(ratios) <= 1.25
    hall = load_scene("warehouse_routing")
    assert not hall.start_goal.fixed_line_of_sight
    assert hall.start_goal.max_detour is None
    long_routes = 0
    for seed in range(12):
        layout = hall.layout(np.random.default_rng(seed))
        start, goal, length = layout.sample_start_goal(np.random.default_rng(100 + seed), 0.3)
        long_routes += length > 1.25 * float(np.hypot(*(goal - start)))
    assert long_routes >= 1


def test_warehouse_pairs_see_each_other_past_the_shelf_rows():
    """``fixed_line_of_sight``: no straight start-goal line crosses a shelf row (1.25 x alone let a pair lie in
    neighbouring aisles, round a row's end), while a pallet of the episode's clutter may still block it; without the
    key, the same draws cross the rows."""
    spec = load_scene("warehouse")
    assert spec.start_goal.fixed_line_of_sight
    shelves = StaticGeometry([o for o in spec.obstacles if isinstance(o, Box)])
    free_spec = dataclasses.replace(spec, start_goal=dataclasses.replace(spec.start_goal, fixed_line_of_sight=False))
    by_pallet = crossing_without = 0
    for seed in range(30):
        layout = spec.layout(np.random.default_rng(seed))
        start, goal, _ = layout.sample_start_goal(np.random.default_rng(200 + seed), 0.3, exact_length=False)
        assert shelves.segment_clear(start, goal, 0.0, step=0.01)[0], (seed, start, goal)
        by_pallet += not layout.geometry.segment_clear(start, goal, 0.0)[0]
        free = free_spec.layout(np.random.default_rng(seed))
        start, goal, _ = free.sample_start_goal(np.random.default_rng(200 + seed), 0.3, exact_length=False)
        crossing_without += not shelves.segment_clear(start, goal, 0.0, step=0.01)[0]
    assert by_pallet >= 1
    assert crossing_without >= 5


def test_line_of_sight_with_an_impossible_layout_is_a_named_error():
    """A wall across most of an 8 m room: every pair 9-10 m apart lies on its two sides and the line crosses it;
    the sampler says which rule it could not meet (without the rule it finds a pair round the wall's end)."""
    data = {"name": "x", "split": "test", "bounds": [0, 8, 0, 8],
            "obstacles": [{"wall": {"from": [0, 4], "to": [6.5, 4]}}],
            "start_goal": {"distance_m": [9.0, 10.0], "fixed_line_of_sight": True}}
    spec = parse_scene(data, "x.yaml", "x")
    with pytest.raises(ConfigError, match="crosses no fixed obstacle"):
        spec.layout().sample_start_goal(np.random.default_rng(0), 0.3, max_tries=20)
    data["start_goal"]["fixed_line_of_sight"] = False
    parse_scene(data, "x.yaml", "x").layout().sample_start_goal(np.random.default_rng(0), 0.3, max_tries=20)


def test_line_of_sight_must_be_a_boolean():
    data = {"name": "x", "split": "test", "bounds": [0, 8, 0, 8],
            "start_goal": {"distance_m": [3, 4], "fixed_line_of_sight": "maybe"}}
    with pytest.raises(ConfigError, match="fixed_line_of_sight"):
        parse_scene(data, "x.yaml", "x")


@pytest.mark.parametrize("value", [0.9, float("nan"), float("inf")])
def test_max_detour_out_of_range_is_a_named_error(value):
    data = {"name": "x", "split": "test", "bounds": [0, 8, 0, 8],
            "start_goal": {"distance_m": [3, 4], "max_detour": value}}
    with pytest.raises(ConfigError, match="max_detour"):
        parse_scene(data, "x.yaml", "x")


# ----------------------------------------------------------------------------------------- start/goal sampling
def _grid_path(layout, start, goal, inflation):
    nav = layout.nav(inflation)
    src, dst = nav._nearest_free(start), nav._nearest_free(goal)
    _, pred = dijkstra(nav.graph, directed=False, indices=src, return_predecessors=True)
    path = [dst]
    while path[-1] != src:
        path.append(pred[path[-1]])
        assert path[-1] >= 0, "no path"
    ij = np.array([divmod(int(k), nav.shape[1]) for k in path[::-1]])
    return np.vstack([start, nav.origin + ij[:, ::-1] * NAV_RES_M, goal])


def _any_angle_length(layout, start, goal, inflation):
    """Length of the grid path after string pulling: a valid path, so an upper bound of the true geodesic."""
    xy = _grid_path(layout, start, goal, inflation)
    out, i = [xy[0]], 0
    while i < len(xy) - 1:
        j = len(xy) - 1
        while j > i + 1 and not layout.geometry.segment_clear(xy[i][None], xy[j][None], inflation, 0.02)[0]:
            j -= 1
        out.append(xy[j])
        i = j
    return float(np.sum(np.linalg.norm(np.diff(np.array(out), axis=0), axis=1)))


@pytest.mark.parametrize("name", ["office_lobby", "hallway", "warehouse", "doorway", "corner", "hospital_corridor"])
def test_sample_start_goal_distance_clearance_connectivity(name):
    spec = load_scene(name)
    sg = spec.start_goal
    for seed in range(4):
        rng = np.random.default_rng(seed)
        layout = spec.layout(rng)
        start, goal, geo = layout.sample_start_goal(rng, ROBOT_RADIUS)
        lo, hi = sg.distance_m
        dist = float(np.hypot(*(goal - start)))
        if sg.metric == "euclidean":
            assert lo - 0.04 <= dist <= hi + 0.04
            assert 5.4 <= dist <= 6.6  # the paper's ~6 m start-goal distance
        else:
            assert lo <= geo <= hi
        assert np.all(layout.clearance_at(np.stack([start, goal])) >= sg.clearance_m)
        assert math.isfinite(geo) and geo >= dist - 2 * NAV_RES_M
        # connected in both directions on the robot's graph
        nav = layout.nav(ROBOT_RADIUS + 0.05)
        assert np.isfinite(nav.lookup(nav.distances_from(goal), start))
        if sg.region is not None:
            r = sg.region
            assert r[0] <= start[0] <= r[1] and r[2] <= start[1] <= r[3]


def test_sample_start_goal_is_seeded():
    layout = load_scene("office_lobby").layout()
    a = layout.sample_start_goal(np.random.default_rng(3), ROBOT_RADIUS)
    b = layout.sample_start_goal(np.random.default_rng(3), ROBOT_RADIUS)
    c = layout.sample_start_goal(np.random.default_rng(4), ROBOT_RADIUS)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert not np.allclose(a[0], c[0])


@pytest.mark.parametrize("name", ["office_floor", "hospital_floor"])
def test_long_horizon_maps_give_long_grid_geodesics(name):
    spec = load_scene(name)
    assert spec.split == "long_horizon" and spec.start_goal.metric == "geodesic"
    layout = spec.layout()
    for seed in range(3):
        start, goal, geo = layout.sample_start_goal(np.random.default_rng(seed), ROBOT_RADIUS)
        assert 20.0 <= geo <= 35.0
        # a valid collision-free path is never much shorter than the reported geodesic
        assert _any_angle_length(layout, start, goal, ROBOT_RADIUS + 0.05) >= 0.9 * geo


def test_long_horizon_true_shortest_path_is_at_least_20m():
    layout = load_scene("office_floor").layout()
    for seed in range(3):
        start, goal, geo = layout.sample_start_goal(np.random.default_rng(seed), ROBOT_RADIUS)
        assert _any_angle_length(layout, start, goal, ROBOT_RADIUS + 0.05) >= 20.0


def test_reported_geodesic_is_within_2_percent_of_the_shortest_path():
    layout = load_scene("hospital_floor").layout()
    for seed in range(3):
        start, goal, geo = layout.sample_start_goal(np.random.default_rng(seed), ROBOT_RADIUS)
        assert geo <= 1.02 * _any_angle_length(layout, start, goal, ROBOT_RADIUS + 0.05)


# ----------------------------------------------------------------------------------------------- densities
def test_ped_count_follows_density_times_free_area():
    layout = load_scene("office_lobby").layout()
    # analytic free area: the interior (the bounds, wall to wall) minus the furniture inside it
    interior = 14.0 * 7.0
    furniture = 2.4 * 0.8 + 2.0 * 0.8 + 2.0 * 0.8 + 2 * math.pi * 0.3**2 + 2 * math.pi * 0.25**2
    assert layout.free_area_m2 == pytest.approx(interior - furniture, rel=0.015)
    for density in (0.0, 0.05, 0.1, 0.2, 0.3):
        assert layout.ped_count(density) == round(density * layout.free_area_m2)
    assert layout.ped_count(0.1) == 9 and layout.ped_count(0.2) == 18


def test_ped_count_is_capped_by_max_count():
    layout = load_scene("office_floor").layout()
    assert layout.spec.ped_max_count == 60
    assert round(0.2 * layout.free_area_m2) > 60
    assert layout.ped_count(0.2) == 60


def test_env_uses_ped_count():
    env = CrowdNavEnv(scene="hallway", density=0.2, obs_mode="state", info_level="basic")
    env.reset(seed=0)
    assert env.crowd.n == env.layout.ped_count(0.2) == round(0.2 * env.layout.free_area_m2)


# ---------------------------------------------------------------------------------------------- random clutter
def test_random_obstacles_are_seeded_per_episode():
    spec = load_scene("warehouse")
    n_fixed = len(spec.obstacles) + 4
    a = spec.layout(np.random.default_rng(1))
    b = spec.layout(np.random.default_rng(1))
    c = spec.layout(np.random.default_rng(2))
    assert 3 <= len(a.obstacles) - n_fixed <= 6
    assert a.obstacles == b.obstacles
    assert a.obstacles != c.obstacles
    ro = spec.random_obstacles
    for o in a.obstacles[n_fixed:]:
        assert ro.size_m[0] <= o.size[0] <= ro.size_m[1] and ro.size_m[0] <= o.size[1] <= ro.size_m[1]
        assert ro.region[0] <= o.center[0] <= ro.region[1] and ro.region[2] <= o.center[1] <= ro.region[3]
    with pytest.raises(ValueError, match="rng"):
        spec.layout()


def test_static_layout_is_cached():
    spec = load_scene("office_lobby")
    assert spec.layout() is spec.layout()


def test_free_points_have_the_requested_clearance():
    layout = load_scene("doorway").layout()
    pts = layout.free_points(np.random.default_rng(0), 500, 0.6)
    assert np.all(layout.clearance_at(pts) >= 0.6)
    region = (1.0, 5.0, 1.0, 5.0)
    pts = layout.free_points(np.random.default_rng(0), 200, 0.3, region)
    assert np.all((pts[:, 0] >= 1.0 - 0.03) & (pts[:, 0] <= 5.03) & (pts[:, 1] >= 0.97) & (pts[:, 1] <= 5.03))
    with pytest.raises(ConfigError, match="doorway"):
        layout.free_points(np.random.default_rng(0), 1, 10.0)


# ------------------------------------------------------------------------------------------------ validation
VALID = {
    "name": "x",
    "split": "train",
    "bounds": [0.0, 8.0, 0.0, 6.0],
    "obstacles": [
        {"box": {"center": [2.0, 2.0], "size": [1.0, 0.5], "yaw_deg": 30, "color": [0.2, 0.3, 0.4]}},
        {"wall": {"from": [5.0, 0.0], "to": [5.0, 2.0]}},
        {"cylinder": {"center": [6.5, 4.0], "radius_m": 0.3}},
    ],
    "start_goal": {"distance_m": [3.0, 4.0], "metric": "euclidean", "clearance_m": 0.5},
}


def _mutate(path: str, value):
    data = copy.deepcopy(VALID)
    node = data
    keys = path.split("/")
    for k in keys[:-1]:
        node = node[int(k)] if isinstance(node, list) else node[k]
    last = keys[-1]
    if value is _DELETE:
        del node[last]
    elif isinstance(node, list):
        node[int(last)] = value
    else:
        node[last] = value
    return data


class _Deleted:
    """The value that removes a field; its repr is stable, so the test ids are the same in every process."""

    def __repr__(self) -> str:
        return "<deleted>"


_DELETE = _Deleted()

BAD = [
    ("colour", [0.1, 0.2, 0.3], "'colour'"),
    ("bounds", "wide", "'bounds'"),
    ("bounds", [0.0, 8.0, 6.0], "'bounds'"),
    ("bounds", [0.0, 8.0, 3.0, 3.0], "'bounds'"),
    ("bounds", [9.0, 8.0, 0.0, 6.0], "'bounds'"),
    ("bounds", _DELETE, "bounds"),
    ("split", "validation", "'split'"),
    ("name", 7, "'name'"),
    ("obstacles/0", {"sphere": {"center": [1.0, 1.0]}}, "'obstacles[0]'"),
    ("obstacles/0", {"box": {"center": [1, 1], "size": [1, 1]}, "cylinder": {"center": [1, 1], "radius_m": 0.3}},
     "'obstacles[0]'"),
    ("obstacles/0/box/color", [0.1, 0.2], "'obstacles[0].box.color'"),
    ("obstacles/0/box/color", [0.1, 0.2, 1.5], "'obstacles[0].box.color'"),
    ("obstacles/0/box/size", [1.0, -0.5], "'obstacles[0].box.size'"),
    ("obstacles/0/box/rotation", 3, "obstacles[0].box.rotation"),
    ("obstacles/1/wall/to", [5.0, 0.0], "'obstacles[1].wall'"),
    ("obstacles/2/cylinder/radius_m", "big", "'obstacles[2].cylinder.radius_m'"),
    ("obstacles", {"box": {}}, "'obstacles'"),
    ("wall_color", [1.2, 0.0, 0.0], "'wall_color'"),
    ("floor_color", "grey", "'floor_color'"),
    ("wall_height_m", True, "'wall_height_m'"),
    ("start_goal/metric", "manhattan", "'start_goal.metric'"),
    ("start_goal/distance_m", [4.0, 3.0], "'start_goal.distance_m'"),
    ("start_goal/distance_m", [0.0, 3.0], "'start_goal.distance_m'"),
    ("random_obstacles", {"count": [2.5, 4], "size_m": [0.4, 0.8], "region": [1, 7, 1, 5]},
     "'random_obstacles.count'"),
    ("pedestrians", {"max_count": -1}, "'pedestrians.max_count'"),
    ("description", ["a"], "'description'"),
    ("bounds", [0.0, float("nan"), 0.0, 6.0], "'bounds[1]'"),
    ("bounds", [0.0, float("inf"), 0.0, 6.0], "'bounds[1]'"),
    ("bounds", [0.0, 200.0, 0.0, 100.0], "'bounds'"),  # 20,000 m² > MAX_AREA_M2
    ("obstacles/0/box/center", [float("nan"), 1.0], "'obstacles[0].box.center[0]'"),
    ("obstacles/0/box/center", [50.0, 50.0], "'obstacles[0]'"),  # far outside the bounds
    ("obstacles/2/cylinder/radius_m", float("inf"), "'obstacles[2].cylinder.radius_m'"),
    ("obstacles/1/wall", {"from": [-40.0, -40.0], "to": [-30.0, -40.0]}, "'obstacles[1]'"),  # all outside
    ("start_goal/clearance_m", float("nan"), "'start_goal.clearance_m'"),
    ("wall_height_m", float("nan"), "'wall_height_m'"),
]


def test_valid_scene_parses():
    spec = parse_scene(copy.deepcopy(VALID), "x.yaml")
    assert spec.name == "x" and spec.bounds == (0.0, 8.0, 0.0, 6.0)
    box, wall, cyl = spec.obstacles
    assert isinstance(box, Box) and box.yaw == pytest.approx(math.radians(30)) and box.color == (0.2, 0.3, 0.4)
    assert isinstance(wall, Box) and wall.center == (5.0, 1.0) and wall.size == (2.0, 0.2)
    assert wall.yaw == pytest.approx(math.pi / 2)
    assert isinstance(cyl, Cylinder) and cyl.radius_m == 0.3
    assert spec.start_goal.distance_m == (3.0, 4.0)


@pytest.mark.parametrize("path,value,field", BAD, ids=[f"{p}={v!r}"[:40] for p, v, _ in BAD])
def test_parse_scene_errors_name_file_and_field(path, value, field):
    data = _mutate(path, value)
    with pytest.raises(ConfigError) as ei:
        parse_scene(data, "x.yaml")
    msg = str(ei.value)
    assert "x.yaml" in msg and field in msg
    assert "\n" not in msg


def test_parse_scene_rejects_a_non_mapping():
    with pytest.raises(ConfigError, match=r"x\.yaml.*expected a mapping"):
        parse_scene(["name", "x"], "x.yaml")


def _write(tmp_path, stem: str, text: str):
    p = tmp_path / f"{stem}.yaml"
    p.write_text(text)
    return p


def test_load_scene_from_a_user_path(tmp_path):
    p = _write(tmp_path, "my_room", yaml.safe_dump({**VALID, "name": "my_room"}))
    spec = load_scene(str(p))
    assert spec.name == "my_room" and spec.path == str(p)


def test_load_scene_name_must_equal_file_stem(tmp_path):
    p = _write(tmp_path, "other_name", yaml.safe_dump(VALID))
    with pytest.raises(ConfigError) as ei:
        load_scene(str(p))
    assert str(p) in str(ei.value) and "'name'" in str(ei.value) and "other_name" in str(ei.value)


def test_load_scene_malformed_yaml(tmp_path):
    p = _write(tmp_path, "broken", "name: broken\nbounds: [0, 1, 0\nsplit: train\n")
    with pytest.raises(ConfigError) as ei:
        load_scene(str(p))
    assert str(p) in str(ei.value) and "YAML" in str(ei.value)


def test_load_scene_empty_file(tmp_path):
    p = _write(tmp_path, "empty", "")
    with pytest.raises(ConfigError, match="empty.yaml"):
        load_scene(str(p))


def test_load_scene_missing_file(tmp_path):
    p = tmp_path / "nope" / "missing.yaml"
    with pytest.raises(InputMissingError) as ei:
        load_scene(str(p))
    assert str(p) in str(ei.value)
    assert not isinstance(ei.value, ConfigError)


def test_unknown_scene_name_lists_known_scenes():
    with pytest.raises(ConfigError) as ei:
        load_scene("nowhere")
    msg = str(ei.value)
    assert "'nowhere'" in msg
    for name in SHIPPED:
        assert name in msg


def test_user_scene_file_works_in_the_env(tmp_path):
    text = """
name: my_lab
split: train
description: "an 8 x 6 m lab with a pillar and a table"
bounds: [0.0, 8.0, 0.0, 6.0]
obstacles:
  - cylinder: {center: [4.0, 3.0], radius_m: 0.4, height_m: 2.5}
  - box: {center: [1.5, 5.0], size: [1.2, 0.6], height_m: 0.75}
start_goal: {distance_m: [4.0, 5.0], clearance_m: 0.5}
pedestrians: {max_count: 3}
"""
    p = _write(tmp_path, "my_lab", text)
    env = CrowdNavEnv(scene=str(p), density=0.2, obs_mode="privileged", info_level="basic")
    obs, info = env.reset(seed=0)
    assert env.spec_scene.name == "my_lab"
    assert env.crowd.n == 3  # 0.2 ped/m2 x ~43 m2 capped by max_count
    assert 4.0 - 0.04 <= np.hypot(*(env.goal - env.start)) <= 5.0 + 0.04
    for _ in range(5):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert obs["scan"].shape == (72,) and np.all(obs["scan"] <= 8.0 * 1.5)
    env.close()


def test_free_points_do_not_depend_on_earlier_queries():
    """The free-cell cache must not hand a query the cells of a nearby, earlier clearance (determinism)."""
    spec = load_scene("warehouse")
    obstacles = spec.layout(np.random.default_rng(0)).obstacles
    fresh = SceneLayout(spec, obstacles)
    used = SceneLayout(spec, obstacles)
    for c in (0.3401, 0.3408, 0.3419):  # earlier queries with nearby clearances
        used.free_points(np.random.default_rng(1), 5, c)
    for c in (0.3404, 0.3412, 0.3499):
        np.testing.assert_array_equal(fresh.free_points(np.random.default_rng(7), 200, c),
                                      used.free_points(np.random.default_rng(7), 200, c))


def test_free_space_rectangles_make_the_rest_of_the_bounds_solid():
    """A T-junction written as two rectangles: their union is free, everything else inside the bounds is solid."""
    data = {"name": "t_junction", "split": "test", "bounds": [0, 10, 0, 8],
            "free_space": [[0, 10, 5, 8], [3.5, 6.5, 0, 5]]}
    spec = parse_scene(data, "t_junction.yaml", "t_junction")
    layout = spec.layout()
    free = np.array([[1.0, 6.5], [9.0, 6.5], [5.0, 1.0], [5.0, 5.5]])
    solid = np.array([[1.0, 2.0], [9.0, 2.0], [3.0, 4.0], [7.0, 4.9]])
    assert np.all(layout.clearance_at(free) > 0.4)
    assert np.all(layout.geometry.signed_distance(solid)[0] < 0)
    start, goal, length = layout.sample_start_goal(np.random.default_rng(0), 0.3)
    assert math.isfinite(length)


@pytest.mark.parametrize("rect", [[-1, 5, 0, 4], [0, 5, 4, 3], [0, float("nan"), 0, 4]])
def test_free_space_outside_the_bounds_or_degenerate_is_a_named_error(rect):
    data = {"name": "x", "split": "test", "bounds": [0, 10, 0, 8], "free_space": [rect]}
    with pytest.raises(ConfigError, match=r"free_space\[0\]"):
        parse_scene(data, "x.yaml", "x")


def test_obstacle_partly_inside_the_bounds_is_accepted():
    data = _mutate("obstacles/0/box/center", [8.3, 3.0])  # straddles the right edge
    parse_scene(data, "x.yaml")


@pytest.mark.parametrize("n,field", [(2_000, "obstacles"), (400, "obstacles")])
def test_scene_size_limits_are_checked_before_any_grid(monkeypatch, n, field):
    """Too many obstacles, or too many grid cells × obstacles, is refused by the validator with the limit in the
    message (the 400-obstacle case: 4,500 m² → ~1.8e6 cells × 404 > 2e8 pairs); nothing is built."""
    import sim.scene as scene_mod

    def no_layout(*a, **k):
        raise AssertionError("a layout was built")

    monkeypatch.setattr(scene_mod.SceneLayout, "__init__", no_layout)
    data = {"name": "x", "split": "test", "bounds": [0, 90, 0, 50],
            "obstacles": [{"cylinder": {"center": [1 + (k % 80), 1 + k // 80], "radius_m": 0.1}} for k in range(n)]}
    with pytest.raises(ConfigError, match=rf"'{field}'.*limit") as ei:
        parse_scene(data, "x.yaml", "x")
    assert "x.yaml" in str(ei.value)


def test_scene_file_size_limit(tmp_path):
    from pipeline.core.config import MAX_YAML_BYTES

    p = _write(tmp_path, "huge", "name: huge\n# " + "x" * MAX_YAML_BYTES + "\n")
    with pytest.raises(ConfigError, match=r"huge\.yaml.*at most .* bytes"):
        load_scene(str(p))


def test_deeply_nested_yaml_is_a_named_error(tmp_path):
    p = _write(tmp_path, "deep", "name: deep\nbounds: " + "[" * 100_000 + "]" * 100_000 + "\n")
    with pytest.raises(ConfigError, match=r"deep\.yaml"):
        load_scene(str(p))
