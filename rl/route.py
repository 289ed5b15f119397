"""A route on the student's own occupancy map: the sub-goal its lookahead head steers by (``net.route: map``).

The privileged teacher is handed a point 2 m along the global planner's path (``obs["subgoal"]`` / ``obs["path"]``:
the map of the whole scene); a student has only the goal. Facing an obstacle with the goal behind it, every
forward arc of the student's lookahead head is blocked or costly, turning away raises the heading cost, and the
argmax is to stand still — a deadlock no later frame changes (measured: 10 of `full`'s 27 timeouts on the N = 75
benchmark, docs/results.md). :func:`map_subgoal` routes round what the student perceives instead. When the
straight line to the goal is open on the map, the sub-goal lies on it (what the head steers by without a route);
else it follows the cheapest
8-connected path on its occupancy map (the pretrained BEV's predicted static occupancy for ``full`` / ``no_i2``, the
depth occupancy for ``no_bev``; a cell within the robot's radius of an occupied one costs more the closer it is,
up to :data:`BLOCKED_COST` times a free cell, so a robot already inside that margin leaves it by the shortest way)
from the robot towards the goal, and the
point ``lookahead_m`` along it is the sub-goal. The map covers only what is ahead (the camera frustum's grid), so
a path to a goal beyond it ends at the far or side edge cell that minimises path cost + straight-line distance on
to the goal; a goal behind the map's near edge is its own sub-goal.

Written here rather than taken from a planning library: the grid is tiny (30 x 48 cells) and the one thing needed
is a Dijkstra over it, which :func:`scipy.sparse.csgraph.dijkstra` does; the rest is the map geometry.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

BLOCKED_COST = 50.0  # an occupied cell costs 1 + this many free cells (less, linearly, out to the robot's radius)
OCCUPIED_P = 0.5  # occupancy probability at which a cell is an obstacle
_STEPS = [(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if (di, dj) != (0, 0)]


def map_subgoal(occ: np.ndarray, goal: np.ndarray, bounds: Any, radius_m: float = 0.3,
                lookahead_m: float = 2.0) -> np.ndarray:
    """The point ``lookahead_m`` along the cheapest path on the map ``occ`` from the robot towards ``goal``.

    Args:
        occ: ``X x Y`` occupancy probabilities (or 0/1) in the robot frame: rows along x (forward), columns along y
            (left), covering ``bounds``.
        goal: the goal in the robot frame, m (``obs["state"][:2]``).
        bounds: ``((x_min, x_max), (y_min, y_max))`` of the map, m.
        radius_m: the robot's radius (the margin round occupied cells).
        lookahead_m: how far along the path the sub-goal lies.

    Returns:
        ``[x, y]`` (float32, robot frame, m): the sub-goal — the goal itself when it lies behind the map or is
        reached within ``lookahead_m`` along the path.
    """
    goal = np.asarray(goal, np.float64)
    (x0, x1), (y0, y1) = ((float(a), float(b)) for a, b in bounds)
    nx, ny = occ.shape
    dx, dy = (x1 - x0) / nx, (y1 - y0) / ny
    i0, j0 = int(math.floor(-x0 / dx)), int(math.floor(-y0 / dy))  # the robot's cell
    if goal[0] < x0 or not (0 <= i0 < nx and 0 <= j0 < ny):
        return goal.astype(np.float32)
    occupied = np.asarray(occ) >= OCCUPIED_P
    if not occupied.any():
        return (goal * min(1.0, lookahead_m / max(float(np.hypot(*goal)), 1e-9))).astype(np.float32)
    clear = distance_transform_edt(~occupied, sampling=(dx, dy))  # m from each cell's centre to the nearest obstacle
    # a cell closer to an obstacle than the robot's radius costs more the deeper it lies (1 + BLOCKED_COST at an
    # obstacle), so a path leaves a margin the robot is already inside by the shortest way out, never through it
    cost = 1.0 + BLOCKED_COST * np.clip((radius_m - clear) / radius_m, 0.0, 1.0)
    # in view: no closer to an obstacle than the radius, or than the robot is now
    free = clear >= min(radius_m, float(clear[i0, j0])) - 1e-6
    dist_goal = float(np.hypot(*goal))
    ahead = goal * min(1.0, lookahead_m / max(dist_goal, 1e-9))
    if _in_view(_clipped(goal, x0, x1, y0, y1), free, x0, y0, dx, dy, min(dx, dy) / 2):
        return ahead.astype(np.float32)  # the goal's direction is open: steer at it, as without a route
    idx = np.arange(nx * ny).reshape(nx, ny)
    rows, cols, w = [], [], []
    for di, dj in _STEPS:  # an edge costs its length times the mean cost of its two cells
        a = idx[max(0, -di):nx - max(0, di), max(0, -dj):ny - max(0, dj)]
        b = idx[max(0, di):nx - max(0, -di) or None, max(0, dj):ny - max(0, -dj) or None]
        ca, cb = cost.ravel()[a.ravel()], cost.ravel()[b.ravel()]
        rows.append(a.ravel())
        cols.append(b.ravel())
        w.append(math.hypot(di * dx, dj * dy) * 0.5 * (ca + cb))
    graph = csr_matrix((np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))), shape=(nx * ny, nx * ny))
    dist, pred = dijkstra(graph, indices=idx[i0, j0], return_predecessors=True)
    cx = x0 + (np.arange(nx) + 0.5) * dx
    cy = y0 + (np.arange(ny) + 0.5) * dy
    centres = np.stack(np.meshgrid(cx, cy, indexing="ij"), -1).reshape(-1, 2)
    gi, gj = int(math.floor((goal[0] - x0) / dx)), int(math.floor((goal[1] - y0) / dy))
    if 0 <= gi < nx and 0 <= gj < ny:
        target = int(idx[gi, gj])
    else:  # beyond the map: the exit (far or side edge) with the least path cost + straight line on to the goal
        edge = np.zeros((nx, ny), bool)
        edge[-1, :] = edge[:, 0] = edge[:, -1] = True
        total = dist + np.hypot(*(centres - goal).T)
        target = int(np.argmin(np.where(edge.ravel() & np.isfinite(dist), total, np.inf)))
    path = [target]
    while path[-1] != idx[i0, j0] and pred[path[-1]] >= 0:
        path.append(int(pred[path[-1]]))
    pts = np.vstack([[0.0, 0.0], centres[path[::-1][1:]]])
    if divmod(target, ny) == (gi, gj):
        pts[-1] = goal  # the path ends at the goal itself, not its cell's centre
    # the grid path bends in 45° steps: steer at its farthest point in straight view of the robot instead
    k = len(pts) - 1
    while k > 1 and not _in_view(pts[k], free, x0, y0, dx, dy, min(dx, dy) / 2):
        k -= 1
    far = pts[k]
    d = float(np.hypot(*far))
    if d >= lookahead_m:
        return (far * (lookahead_m / d)).astype(np.float32)
    if k == len(pts) - 1 or d >= 1.0:
        return far.astype(np.float32)
    seg = np.hypot(*np.diff(pts, axis=0).T)  # a corner close by: the point lookahead_m along the path itself
    run = np.concatenate([[0.0], np.cumsum(seg)])
    if run[-1] <= lookahead_m:
        return pts[-1].astype(np.float32)
    k = int(np.searchsorted(run, lookahead_m))  # run[k-1] < lookahead <= run[k]
    t = (lookahead_m - run[k - 1]) / max(seg[k - 1], 1e-9)
    return (pts[k - 1] + t * (pts[k] - pts[k - 1])).astype(np.float32)


def _clipped(p: np.ndarray, x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    """``p`` moved along the ray from the robot onto the map's bounds when it lies beyond them."""
    t = 1.0
    for v, lo, hi in ((p[0], x0, x1), (p[1], y0, y1)):
        if v > hi:
            t = min(t, hi / v)
        elif v < lo:
            t = min(t, lo / v)
    return p * (t * 0.999)


def _in_view(p: np.ndarray, free: np.ndarray, x0: float, y0: float, dx: float, dy: float, step: float) -> bool:
    """Whether the straight segment from the robot (0, 0) to ``p`` crosses only ``free`` cells of the map."""
    n = max(2, int(math.ceil(float(np.hypot(*p)) / step)) + 1)
    t = np.linspace(0.0, 1.0, n)[:, None]
    q = t * p[None]
    i = np.clip(np.floor((q[:, 0] - x0) / dx).astype(int), 0, free.shape[0] - 1)
    j = np.clip(np.floor((q[:, 1] - y0) / dy).astype(int), 0, free.shape[1] - 1)
    return bool(free[i, j].all())
