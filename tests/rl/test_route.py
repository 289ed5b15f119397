"""rl.route: the sub-goal on the student's own occupancy map (robot frame; rows along x, columns along y)."""

import numpy as np
import pytest

from pipeline.core.errors import ConfigError
from rl.route import map_subgoal

BOUNDS = ((0.0, 6.0), (-4.8, 4.8))  # the default BEV grid, pooled to 0.2 m cells: 30 x 48
FREE = np.zeros((30, 48))


def _cells(x0, x1, y0, y1):
    """A copy of the free map with the cells covering x0..x1, y0..y1 (m) occupied."""
    occ = FREE.copy()
    occ[int(x0 / 0.2):int(x1 / 0.2), int((y0 + 4.8) / 0.2):int((y1 + 4.8) / 0.2)] = 1.0
    return occ


def _bearing(p):
    return np.degrees(np.arctan2(p[1], p[0]))


def test_an_open_line_to_the_goal_is_steered_along_unchanged():
    for goal in ([3.5, 0.3], [20.0, -5.0], [1.0, 0.5]):
        sub = map_subgoal(FREE, goal, BOUNDS)
        assert _bearing(sub) == pytest.approx(_bearing(goal), abs=1e-3)
        assert np.hypot(*sub) == pytest.approx(min(2.0, np.hypot(*goal)), abs=1e-4)
    assert map_subgoal(FREE, [-2.0, 1.0], BOUNDS).tolist() == [-2.0, 1.0]  # behind the map: the goal itself
    # an obstacle beside the line does not bend it
    assert _bearing(map_subgoal(_cells(1.0, 1.4, 1.0, 2.0), [3.5, 0.0], BOUNDS)) == pytest.approx(0.0, abs=1e-3)


def test_a_wall_in_the_way_is_passed_on_its_open_side_and_never_through():
    wall = _cells(1.0, 1.4, -1.0, 1.2)  # across the line to the goal, its left end farther out
    left = map_subgoal(wall, [3.5, 0.3], BOUNDS)
    assert left[1] > 1.2 + 0.2 and 0.0 < left[0] <= 1.2  # round the left end, towards the wall's near side
    closed = wall.copy()
    closed[:, 31:33] = 1.0  # a second wall along x at y = 1.4 closes the left way round
    right = map_subgoal(closed, [3.5, 0.3], BOUNDS)
    assert right[1] < -1.0 - 0.2
    # a robot already closer to an obstacle than its radius leaves sideways, not through it
    near = map_subgoal(_cells(0.4, 1.0, -0.8, 1.2), [3.5, 0.3], BOUNDS)
    assert near[1] < -0.8 and near[0] < 1.4
    assert all(np.hypot(*p) <= 2.0 + 1e-5 for p in (left, right, near))


def test_the_observer_refuses_a_route_without_a_map():
    from rl.observe import StudentObserver

    for variant, head in (("full", "lookahead"), ("no_bev", "mlp")):  # no map_cost; a head that ignores it
        with pytest.raises(ConfigError, match=f"route: the {head} head of variant '{variant}' has no occupancy map"):
            StudentObserver(variant, [], None, 10, head=head, route=True)
