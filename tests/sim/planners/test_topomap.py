"""Tests of sim.planners.topomap: thinning, the GVG of simple and real maps, planning, goals, following."""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy import ndimage

from pipeline.core.errors import ConfigError
from sim.env import CameraConfig, CrowdNavEnv
from sim.planners.dwa import DWAController
from sim.planners.topomap import (
    WaypointFollower,
    build_gvg,
    medial_axis_ima,
    plot_topomap,
    thin,
)
from sim.scene import GRID_RES_M, SceneLayout, load_scene, parse_scene

ROBOT_R = 0.3
EIGHT = np.ones((3, 3), dtype=bool)


def boxes_layout(bounds: list[float], boxes: list[tuple[float, float, float, float]]) -> SceneLayout:
    """A scene from axis-aligned boxes given as (x0, x1, y0, y1)."""
    data = {"name": "t", "split": "train", "bounds": bounds,
            "obstacles": [{"box": {"center": [(a + b) / 2, (c + d) / 2], "size": [b - a, d - c]}}
                          for a, b, c, d in boxes]}
    return parse_scene(data, "t.yaml").layout()


@pytest.fixture(scope="module")
def cross() -> SceneLayout:
    """A plus-shaped crossing of two 2 m corridors, arms 4 m long, centre (5, 5)."""
    return boxes_layout([0, 10, 0, 10], [(0, 4, 0, 4), (6, 10, 0, 4), (0, 4, 6, 10), (6, 10, 6, 10)])


@pytest.fixture(scope="module")
def big_maps() -> dict[str, SceneLayout]:
    return {name: load_scene(name).layout() for name in ("office_floor", "hospital_floor")}


# ------------------------------------------------------------------------------------------------- skeleton
def test_thin_preserves_topology_and_leaves_one_cell_wide_curves():
    rng = np.random.default_rng(0)
    img = ndimage.binary_dilation(rng.random((80, 90)) < 0.03, EIGHT, iterations=3)
    img[30:50, 30:60] = True
    img[38:42, 40:45] = False  # a hole
    sk = thin(img)
    assert not (sk & ~img).any()
    _, n_img = ndimage.label(img, EIGHT)
    _, n_sk = ndimage.label(sk, EIGHT)
    assert n_sk == n_img
    # holes (background components not touching the border, 4-connected) survive
    def holes(m):
        lab, n = ndimage.label(~np.pad(m, 1))
        return n - 1
    assert holes(sk) == holes(img)
    # thin: no 2 x 2 block of skeleton cells
    blocks = sk[:-1, :-1] & sk[1:, :-1] & sk[:-1, 1:] & sk[1:, 1:]
    assert not blocks.any()
    # a filled rectangle thins to its centre line
    rect = np.zeros((20, 60), dtype=bool)
    rect[5:14, 5:55] = True
    rows = np.nonzero(thin(rect))[0]
    assert set(rows.tolist()) <= {8, 9, 10} and np.mean(rows == 9) > 0.8


def test_medial_axis_of_a_corridor_is_its_centre_line():
    free = np.zeros((30, 100), dtype=bool)
    free[5:25, :] = True  # 20 cells wide, open at both ends (treated as free to the border)
    ridge = medial_axis_ima(free, feature_sep_cells=4)
    rows = np.nonzero(ridge)[0]
    assert len(rows) >= 90 and set(rows.tolist()) <= {14, 15}


# ---------------------------------------------------------------------------------------------- simple maps
def test_cross_has_one_central_junction_and_four_arm_endpoints(cross):
    tm = build_gvg(cross, ROBOT_R)
    j, e = tm.junctions, tm.endpoints
    centre = np.array([5.0, 5.0])
    if len(j) == 1:
        assert tm.degree[j[0]] == 4
    else:  # two degree-3 junctions close together are the same crossing
        assert len(j) == 2 and sorted(tm.degree[j].tolist()) == [3, 3]
        assert np.hypot(*(tm.nodes_xy[j[0]] - tm.nodes_xy[j[1]])) < 0.5
    assert np.all(np.hypot(*(tm.nodes_xy[j] - centre).T) < 0.3)
    assert len(e) == 4
    rel = tm.nodes_xy[e] - centre
    arm_dirs = np.round(rel / np.abs(rel).max(axis=1, keepdims=True))
    assert sorted(map(tuple, arm_dirs.tolist())) == [(-1, 0), (0, -1), (0, 1), (1, 0)]
    # each endpoint sits in the middle of its arm, near its dead end
    assert np.all(np.abs(tm.nodes_xy[e] - centre).max(axis=1) > 3.0)
    assert np.all(np.abs(tm.nodes_xy[e] - centre).min(axis=1) < 0.1)
    assert sum(e_.length_m for e_ in tm.edges) == pytest.approx(4 * 4.0, abs=0.5)
    for edge in tm.edges:  # polylines run from node u to node v and keep the clearance
        np.testing.assert_allclose(edge.polyline[0], tm.nodes_xy[edge.u])
        np.testing.assert_allclose(edge.polyline[-1], tm.nodes_xy[edge.v])
        assert cross.clearance_fast(edge.polyline)[0].min() >= tm.min_clearance_m - GRID_RES_M
    assert sorted(len(a) for a in tm.adjacency) == [1, 1, 1, 1, 4] or len(j) == 2


def test_t_junction_has_one_degree_three_node():
    # a 2 m bar along the top (y 3.5..5.5) and a 2 m stem down the middle (x 4..6)
    tee = boxes_layout([0, 10, 0, 5.5], [(0, 4, 0, 3.5), (6, 10, 0, 3.5)])
    tm = build_gvg(tee, ROBOT_R)
    assert tm.degree[tm.junctions].tolist() == [3]
    # the medial-axis junction of a T: equidistant from the top wall and the two inner corners (y = 4.25)
    np.testing.assert_allclose(tm.nodes_xy[tm.junctions[0]], [5.0, 4.25], atol=0.1)
    assert len(tm.endpoints) == 3


def test_plain_corridor_has_no_junction():
    tm = build_gvg(boxes_layout([0, 10, 0, 2], []), ROBOT_R)
    assert len(tm.junctions) == 0
    assert len(tm.endpoints) == 2 and len(tm.edges) == 1
    assert np.all(np.abs(tm.edges[0].polyline[:, 1] - 1.0) < 0.05)


def test_too_narrow_passages_disconnect_the_graph():
    # two rooms joined by a 0.6 m gap: too narrow for a 0.3 m robot with margin
    lay = boxes_layout([0, 10, 0, 4], [(4.9, 5.1, 0, 1.7), (4.9, 5.1, 2.3, 4)])
    tm = build_gvg(lay, ROBOT_R)
    assert np.all(lay.clearance_fast(np.concatenate([e.polyline for e in tm.edges]))[0] >= 0.5 - GRID_RES_M)
    assert len(tm.plan((2.0, 2.0), (8.0, 2.0))) == 0  # unreachable: empty
    wp = tm.plan((1.0, 1.0), (3.0, 3.0))
    assert len(wp) >= 1 and np.allclose(wp[-1], (3.0, 3.0))


def test_build_gvg_rejects_bad_parameters(cross):
    with pytest.raises(ConfigError, match="robot_radius_m"):
        build_gvg(cross, 0.0)
    with pytest.raises(ConfigError, match="min_clearance_m"):
        build_gvg(cross, 0.3, min_clearance_m=0.2)
    with pytest.raises(ConfigError, match="spur_ratio"):
        build_gvg(cross, 0.3, spur_ratio=-1.0)


# ------------------------------------------------------------------------------------------------ real maps
def _path_checks(layout: SceneLayout, tm, start, goal, spacing=1.0):
    wp = tm.plan(start, goal, spacing_m=spacing)
    assert len(wp) >= 2
    pts = np.concatenate([np.asarray(start)[None], wp])
    np.testing.assert_allclose(pts[-1], goal)
    seg = np.hypot(*np.diff(pts, axis=0).T)
    assert seg.max() <= spacing + 1e-6
    clear = layout.segments_min_clearance(pts[:-1], pts[1:], step=0.02)
    assert clear.min() >= ROBOT_R, clear.min()
    shortest = layout.path_length(np.asarray(start), np.asarray(goal), ROBOT_R)
    length = float(seg.sum())
    assert shortest <= length <= 1.5 * shortest, (length, shortest)
    return length / shortest


@pytest.mark.parametrize("name", ["office_floor", "hospital_floor"])
def test_plan_on_the_long_horizon_maps(big_maps, name, capsys):
    layout = big_maps[name]
    t0 = time.perf_counter()
    tm = build_gvg(layout, ROBOT_R)
    build_s = time.perf_counter() - t0
    assert build_s < 10.0  # about 0.1 s on one core; generous for a loaded machine
    assert len(tm.junctions) >= 8 and tm.total_length_m > 80
    # opposite ends of the floor, and three sampled long-horizon pairs
    corners = {"office_floor": ((1.0, 1.0), (29.0, 19.0)), "hospital_floor": ((1.0, 3.5), (39.0, 11.0))}
    pairs = [corners[name]]
    assert layout.clearance_at(np.array(corners[name])).min() > 0.8
    for seed in range(3):
        s, g, _ = layout.sample_start_goal(np.random.default_rng(seed), ROBOT_R)
        pairs.append((tuple(s), tuple(g)))
    t0 = time.perf_counter()
    ratios = [_path_checks(layout, tm, s, g) for s, g in pairs]
    plan_ms = (time.perf_counter() - t0) / len(pairs) * 1e3
    with capsys.disabled():
        print(f"\n{name}: build_gvg {build_s * 1e3:.0f} ms, {len(tm.nodes_xy)} nodes, {len(tm.edges)} edges, "
              f"{tm.total_length_m:.0f} m; plan {plan_ms:.0f} ms; length / shortest {np.round(ratios, 2)}")


def test_candidate_goals_are_far_along_the_graph(big_maps):
    layout = big_maps["office_floor"]
    tm = build_gvg(layout, ROBOT_R)
    start = np.array([3.0, 5.0])
    d = tm.graph_distances(start)
    assert np.isfinite(d).all()
    goals = tm.candidate_goals(np.random.default_rng(0), 4, 15.0, start)
    assert goals.shape == (4, 2) and len({tuple(g) for g in goals.tolist()}) == 4
    for g in goals:
        k = int(np.argmin(np.hypot(*(tm.nodes_xy - g).T)))
        assert d[k] >= 15.0
        assert len(tm.plan(start, g)) > 0
    with pytest.raises(ConfigError, match="qualify"):
        tm.candidate_goals(np.random.default_rng(0), 4, 1e3, start)


def test_plot_topomap_writes_a_png(cross, tmp_path):
    tm = build_gvg(cross, ROBOT_R)
    start, goal = np.array([5.0, 0.8]), np.array([9.2, 5.0])
    wp = tm.plan(start, goal)
    out = plot_topomap(cross, tm, tmp_path / "figs" / "cross.png",
                       paths={"gvg": np.concatenate([start[None], wp])}, start_xy=start, goals_xy=goal[None],
                       waypoints=wp, title="test")
    assert out.exists() and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in out.parent.iterdir()] == ["cross.png"]  # no temporary file left behind


# ------------------------------------------------------------------------------------------------- following
def test_waypoint_follower_advances_and_never_goes_back():
    wps = np.array([[1.0, 0.0], [2.0, 0.0], [3.0, 0.0], [3.0, 1.0]])
    f = WaypointFollower(wps, reach_radius_m=0.3)
    np.testing.assert_allclose(f.current((0.0, 0.0)), [1.0, 0.0])
    np.testing.assert_allclose(f.current((0.8, 0.0)), [2.0, 0.0])  # within the radius of the first
    np.testing.assert_allclose(f.current((2.6, 0.3)), [3.0, 0.0])  # the next one is closer
    np.testing.assert_allclose(f.current((0.0, 0.0)), [3.0, 0.0])  # never back
    np.testing.assert_allclose(f.current((3.0, 0.9)), [3.0, 1.0])
    assert f.is_last
    np.testing.assert_allclose(f.current((10.0, 10.0)), [3.0, 1.0])  # the goal stays the goal
    with pytest.raises(ValueError, match="waypoint"):
        WaypointFollower(np.zeros((0, 2)))


def test_waypoint_follower_skips_ahead_only_to_what_it_sees():
    # a wall from (4, 0) up to (4, 3.5), open above
    lay = boxes_layout([0, 8, 0, 6], [(3.9, 4.1, 0, 3.5)])
    wps = np.array([[2.0, 4.5], [6.5, 2.0]])
    f = WaypointFollower(wps, layout=lay, lookahead_m=10.0)
    np.testing.assert_allclose(f.current((3.5, 1.0)), [2.0, 4.5])  # the goal is closer, but behind the wall
    blind = WaypointFollower(wps, lookahead_m=10.0)
    np.testing.assert_allclose(blind.current((3.5, 1.0)), [6.5, 2.0])  # without a map the closer one wins
    np.testing.assert_allclose(f.current((4.0, 4.6)), [6.5, 2.0])  # over the wall it sees the goal
    # in the open it jumps to the farthest waypoint within the look-ahead
    row = np.array([[1.0, 5.0], [2.0, 5.0], [3.0, 5.0], [4.5, 5.0], [6.0, 5.0]])
    g = WaypointFollower(row, layout=lay, lookahead_m=2.6)
    np.testing.assert_allclose(g.current((0.5, 5.0)), [3.0, 5.0])


def test_dwa_follows_gvg_waypoints_across_the_hospital(big_maps):
    """End to end: the GVG plan of a long-horizon episode, followed by the depth-only DWA, gets there."""
    env = CrowdNavEnv(scene="hospital_floor", density=0.0, obs_mode="state", info_level="basic",
                      max_episode_s=60.0, camera=CameraConfig(width_px=64, height_px=48))
    env.reset(seed=2)
    tm = build_gvg(env.layout, env.cfg.robot.radius_m)
    wps = tm.plan(env.start, env.goal)
    follower = WaypointFollower(wps, layout=env.layout, robot_radius_m=env.cfg.robot.radius_m)
    dwa = DWAController()
    dwa.reset(env)
    while True:
        wp = follower.current(env.robot[:2])
        v, w = dwa.command(env, waypoint_xy=None if follower.is_last else wp)
        _, _, terminated, truncated, info = env.step(env.encode_command(v, w))
        if terminated or truncated:
            break
    assert info["outcome"] == "success", (info["outcome"], env.robot, follower.index, len(wps))
    assert env.shortest_path_m > 20.0
