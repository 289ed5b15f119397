"""A generalized-Voronoi-graph (GVG) topological map of a scene, planning on it, and following its waypoints.

What: the paper's long-horizon setting (§IV-C, Fig. "long-distance navigation") builds a topological map of
each large map with a generalized Voronoi graph, picks a start point, waypoints and candidate goals on it,
plans on it, and lets the local policy follow the waypoints. This module does the same on the occupancy grid
of a :class:`sim.scene.SceneLayout`:

* :func:`build_gvg` -> :class:`TopoMap`: nodes (junctions of degree >= 3 and endpoints of degree 1), edges
  (the skeleton branches between them, with their polylines and lengths) and the adjacency;
* :meth:`TopoMap.plan`: start and goal are attached to every graph point they can see, Dijkstra runs on the
  graph, and the path comes back as waypoints spaced at most ``spacing_m`` apart along the edge polylines;
* :meth:`TopoMap.candidate_goals`: goals drawn among the graph nodes far (along the graph) from a start;
* :class:`WaypointFollower`: hands any local controller (DWA, the expert, a learned policy that takes the goal
  in its robot state) the waypoint to head for;
* :func:`plot_topomap`: a figure of the map, the graph and planned paths.

How (grid frame and units of :class:`sim.scene.SceneLayout`: cell ``[i, j]`` has its centre at
``grid_origin + (j, i) * GRID_RES_M``, 0.05 m cells):

1. *Medial axis* of the free space with the integer medial axis (IMA) of Hesselink & Roerdink (2008): the
   Euclidean feature transform (``scipy.ndimage.distance_transform_edt(..., return_indices=True)``) gives
   every free cell its nearest obstacle cell; a pair of 4-neighbouring free cells whose nearest obstacle cells
   lie more than ``feature_sep_m`` apart straddles the bisector of two different obstacle stretches, and the
   cell closer to that bisector is kept. This is the GVG in the sense of Choset & Burdick (points with two or
   more nearest obstacle points), with every stretch of wall counted as its own "obstacle" — walls of a
   building are all one connected solid, so labelling obstacles by connected component (the textbook GVG)
   would lose every corridor.
2. *Thinning* to a one-cell-wide, 8-connected curve with the parallel, topology-preserving algorithm of Lam,
   Lee & Suen (1992) (two sub-iterations with 256-entry lookup tables, the algorithm behind
   ``skimage.morphology.thin``; written here because scikit-image is not a dependency of this project).
3. *Clearance*: cells whose exact clearance (``layout.clearance``) is below ``min_clearance_m`` are dropped,
   so every graph point keeps the robot radius plus a margin; passages too narrow for the robot disconnect.
4. *Graph*: skeleton cells with >= 3 neighbours form junction clusters (one node each, at the cluster cell of
   largest clearance), cells with one neighbour are endpoints; the remaining cells split into branches, each
   walked into an ordered polyline between its two nodes. Degree-2 nodes are merged away.
5. *Spur pruning*: a terminal edge (endpoint to junction) whose length is below
   ``spur_ratio * clearance(junction) + min_spur_m`` ends inside (about) the free disc around its junction —
   the medial-axis branches into room corners and into the two corners of every dead end — and is removed;
   then degree-2 nodes are merged again (repeated until nothing changes).

Deviations from the paper: the paper does not say how its GVG is computed or pruned (Isaac Sim maps); the
pruning rule above and the attach-to-every-visible-graph-point planning are ours. Waypoints lie on the GVG
(maximal clearance), not on the shortest path; the local controller cuts corners between them.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from pipeline.core.errors import ConfigError
from sim.geometry import Box
from sim.scene import GRID_RES_M, SceneLayout

_EIGHT = np.ones((3, 3), dtype=bool)


# --------------------------------------------------------------------------------------------------- thinning
def _thin_luts() -> tuple[np.ndarray, np.ndarray]:
    """Deletion tables of the Lam-Lee-Suen (1992) thinning, indexed by the 8-bit neighbourhood code.

    Bit ``k`` of the code is neighbour ``x_{k+1}``, counter-clockwise from east (see ``_NEIGHBOUR_CODE``).
    """

    def bits(n: int) -> list[bool]:
        return [bool(n >> i & 1) for i in range(8)]

    def g1(b: list[bool]) -> bool:  # exactly one 8-connected run of neighbours (crossing number X_H == 1)
        return sum(1 for i in (0, 2, 4, 6) if not b[i] and (b[i + 1] or b[(i + 2) % 8])) == 1

    def g2(b: list[bool]) -> bool:  # 2 <= min(n1, n2) <= 3: not an endpoint, not interior
        n1 = sum(1 for k in (1, 3, 5, 7) if b[k] or b[k - 1])
        n2 = sum(1 for k in (1, 3, 5, 7) if b[k] or b[(k + 1) % 8])
        return min(n1, n2) in (2, 3)

    def g3(b: list[bool]) -> bool:  # first sub-iteration: (x2 | x3 | ~x8) & x1 == 0
        return not ((b[1] or b[2] or not b[7]) and b[0])

    def g3p(b: list[bool]) -> bool:  # second sub-iteration: (x6 | x7 | ~x4) & x5 == 0
        return not ((b[5] or b[6] or not b[3]) and b[4])

    codes = [bits(n) for n in range(256)]
    g12 = np.array([g1(b) and g2(b) for b in codes])
    return g12 & np.array([g3(b) for b in codes]), g12 & np.array([g3p(b) for b in codes])


_LUT_A, _LUT_B = _thin_luts()
# row 0 is "up" in the algorithm's picture; orientation does not matter for topology
_NEIGHBOUR_CODE = np.array([[8, 4, 2], [16, 0, 1], [32, 64, 128]], dtype=np.int32)


def thin(mask: np.ndarray, max_iter: int = 10_000) -> np.ndarray:
    """Thin a binary image to one-cell-wide 8-connected curves, keeping its topology (Lam, Lee & Suen 1992).

    Args:
        mask: ``H x W`` bool foreground.
        max_iter: safety bound on the number of passes.

    Returns:
        ``H x W`` bool skeleton (a subset of ``mask`` with the same 8-connected components and holes).
    """
    sk = np.asarray(mask, dtype=bool).copy()
    for _ in range(max_iter):
        before = int(sk.sum())
        for lut in (_LUT_A, _LUT_B):
            code = ndimage.correlate(sk.astype(np.int32), _NEIGHBOUR_CODE, mode="constant")
            sk &= ~lut[code]
        if int(sk.sum()) == before:
            break
    return sk


def medial_axis_ima(free: np.ndarray, feature_sep_cells: float) -> np.ndarray:
    """Integer medial axis (Hesselink & Roerdink 2008) of a binary free-space mask.

    Args:
        free: ``H x W`` bool, True where free.
        feature_sep_cells: a 4-neighbour pair counts only if its nearest obstacle cells are more than this
            apart (cells); larger values drop ridges caused by small boundary wiggles.

    Returns:
        ``H x W`` bool ridge cells (up to two cells thick; thin with :func:`thin`).
    """
    if free.all() or not free.any():
        return np.zeros_like(free)
    _, (fi, fj) = ndimage.distance_transform_edt(free, return_indices=True)
    h, w = free.shape
    ii, jj = np.mgrid[0:h, 0:w]
    out = np.zeros_like(free)
    for di, dj in ((1, 0), (0, 1)):
        p = (slice(0, h - di), slice(0, w - dj))
        q = (slice(di, h), slice(dj, w))
        both = free[p] & free[q]
        dfi = fi[p] - fi[q]
        dfj = fj[p] - fj[q]
        far = both & (dfi.astype(np.int64) ** 2 + dfj.astype(np.int64) ** 2 > feature_sep_cells**2)
        # crit >= 0: p is at least as close to the bisector of the two feature cells as q is
        crit = dfi * (fi[p] + fi[q] - ii[p] - ii[q]) + dfj * (fj[p] + fj[q] - jj[p] - jj[q])
        out[p] |= far & (crit >= 0)
        out[q] |= far & (crit <= 0)
    return out


# ------------------------------------------------------------------------------------------------------ graph
@dataclass
class TopoEdge:
    """One skeleton branch between two nodes.

    Attributes:
        u, v: node indices (``u == v`` for a loop).
        polyline: ``K x 2`` world points (m) from node ``u`` to node ``v``, both included.
        length_m: arc length of the polyline, m.
    """

    u: int
    v: int
    polyline: np.ndarray
    length_m: float


@dataclass
class TopoMap:
    """A GVG topological map (see the module docstring). Build it with :func:`build_gvg`.

    Attributes:
        layout: the scene's static world the map was built from (visibility checks use its clearance grid).
        nodes_xy: ``N x 2`` node positions, world frame, m.
        degree: ``N`` number of edge ends at each node (1 = endpoint, >= 3 = junction; a loop counts twice).
        clearance_m: ``N`` obstacle clearance of each node, m.
        edges: the branches.
        adjacency: per node, ``(neighbour node, edge index)`` pairs.
        skeleton: ``H x W`` bool skeleton cells on the layout's grid, after the clearance cut (for figures).
        robot_radius_m: radius of the robot the map was built for, m.
        min_clearance_m: clearance every graph point keeps, m.
        build_s: wall time of :func:`build_gvg`, s.
        graph_step_m: spacing of the planning points along the edges, m.
        attach_radius_m: start and goal attach to the graph points they see within this distance (all they see
            if none is that close), m.
        attach_clearance_m: clearance an attaching segment keeps (less only where its ends have less), m.
    """

    layout: SceneLayout
    nodes_xy: np.ndarray
    degree: np.ndarray
    clearance_m: np.ndarray
    edges: list[TopoEdge]
    adjacency: list[list[tuple[int, int]]]
    skeleton: np.ndarray
    robot_radius_m: float
    min_clearance_m: float
    build_s: float = 0.0
    graph_step_m: float = 0.25
    attach_radius_m: float = 5.0
    attach_clearance_m: float = 0.6
    _pts: np.ndarray = field(init=False, repr=False)  # planning points: the nodes, then points along edges
    _is_node: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._build_dense()

    # --------------------------------------------------------------------------------------------- queries
    @property
    def junctions(self) -> np.ndarray:
        """Indices of nodes of degree >= 3."""
        return np.nonzero(self.degree >= 3)[0]

    @property
    def endpoints(self) -> np.ndarray:
        """Indices of nodes of degree 1."""
        return np.nonzero(self.degree == 1)[0]

    @property
    def total_length_m(self) -> float:
        return float(sum(e.length_m for e in self.edges))

    def _build_dense(self) -> None:
        """The planning graph: nodes plus points every <= ``graph_step_m`` along each edge polyline."""
        pts = [self.nodes_xy.reshape(-1, 2)]
        rows: list[np.ndarray] = []
        cols: list[np.ndarray] = []
        n = len(self.nodes_xy)
        for e in self.edges:
            s = _arclength(e.polyline)
            k = max(1, int(math.ceil(s[-1] / self.graph_step_m)))
            inner = _resample(e.polyline, s, np.linspace(0.0, s[-1], k + 1)[1:-1])
            ids = np.concatenate([[e.u], n + np.arange(len(inner)), [e.v]])
            n += len(inner)
            pts.append(inner)
            rows.append(ids[:-1])
            cols.append(ids[1:])
        self._pts = np.concatenate(pts, axis=0) if pts else np.zeros((0, 2))
        self._is_node = np.zeros(len(self._pts), dtype=bool)
        self._is_node[: len(self.nodes_xy)] = True
        r = np.concatenate(rows) if rows else np.zeros(0, dtype=int)
        c = np.concatenate(cols) if cols else np.zeros(0, dtype=int)
        self._edges_rc = (r, c, np.hypot(*(self._pts[r] - self._pts[c]).T))
        self._pts_clear = self.layout.clearance_fast(self._pts)[0] if len(self._pts) else np.zeros(0)

    def _visible(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Planning-graph points that ``xy`` attaches to, and their distances (m).

        A point is seen if the straight segment to it keeps ``attach_clearance_m`` from obstacles, or less
        where ``xy`` itself or the graph point has less clearance (so that points near a wall still attach,
        and doorway points are reached straight through the door); the seen points within ``attach_radius_m``
        are used, or all seen points if none is that close. The margin above the graph's own
        ``min_clearance_m`` keeps attachments from grazing door jambs: paths through doorways follow the graph
        through their middle.
        """
        d = np.hypot(*(self._pts - xy).T)
        own = float(self.layout.clearance_fast(xy)[0])
        margin = np.minimum(min(self.attach_clearance_m, own), self._pts_clear) - 1e-3
        ok = self.layout.segments_clear(np.repeat(xy[None], len(self._pts), 0), self._pts, margin, step=0.05)
        near = ok & (d <= self.attach_radius_m)
        if near.any():
            ok = near
        return np.nonzero(ok)[0], d[ok]

    def _dijkstra_from(self, start_xy: np.ndarray, goal_xy: np.ndarray | None = None):
        """Dijkstra from a virtual start vertex (index M) attached to every visible point; with a goal, a
        virtual goal vertex (index M + 1) attached likewise, plus a direct start-goal edge if it is clear."""
        m = len(self._pts)
        r, c, w = self._edges_rc
        rr, cc, ww = [r], [c], [w]
        vs, ds = self._visible(start_xy)
        rr.append(np.full(len(vs), m))
        cc.append(vs)
        ww.append(ds)
        if goal_xy is not None:
            vg, dg = self._visible(goal_xy)
            rr.append(vg)
            cc.append(np.full(len(vg), m + 1))
            ww.append(dg)
            own = float(self.layout.clearance_fast(np.stack([start_xy, goal_xy]))[0].min())
            margin = min(self.attach_clearance_m, own) - 1e-3
            if self.layout.segments_clear(start_xy, goal_xy, margin, step=0.05)[0]:
                rr.append(np.array([m]))
                cc.append(np.array([m + 1]))
                ww.append(np.array([float(np.hypot(*(goal_xy - start_xy)))]))
        rcat, ccat = np.concatenate(rr), np.concatenate(cc)
        # zero-length edges vanish in a sparse matrix: keep them as tiny weights
        wcat = np.maximum(np.concatenate(ww), 1e-9)
        g = coo_matrix((wcat, (rcat, ccat)), shape=(m + 2, m + 2)).tocsr()
        return dijkstra(g, directed=False, indices=m, return_predecessors=True)

    def plan(self, start_xy: Sequence[float], goal_xy: Sequence[float], spacing_m: float = 1.0) -> np.ndarray:
        """Waypoints from ``start_xy`` to ``goal_xy`` along the graph.

        Start and goal are attached to the graph points they see (straight segments keeping
        ``attach_clearance_m``, see :meth:`_visible`); Dijkstra finds the shortest route through the graph (or
        the direct segment if it is that clear and shorter).

        Args:
            start_xy, goal_xy: world positions, m.
            spacing_m: largest arc length along the path between consecutive waypoints, m (graph nodes the
                path passes are always kept).

        Returns:
            ``K x 2`` waypoints, world frame, m, excluding the start and ending with the goal; ``0 x 2`` if
            the goal cannot be reached on the graph.
        """
        if spacing_m <= 0:
            raise ValueError(f"spacing_m: expected > 0, got {spacing_m}")
        a = np.asarray(start_xy, dtype=np.float64).reshape(2)
        b = np.asarray(goal_xy, dtype=np.float64).reshape(2)
        m = len(self._pts)
        dist, pred = self._dijkstra_from(a, b)
        if not np.isfinite(dist[m + 1]):
            return np.zeros((0, 2))
        ids = [m + 1]
        while ids[-1] != m:
            ids.append(int(pred[ids[-1]]))
        ids.reverse()
        inner = ids[1:-1]
        route = np.concatenate([a[None], self._pts[inner].reshape(-1, 2), b[None]])
        keep_node = np.concatenate([[True], self._is_node[inner], [True]])
        return _space_waypoints(route, keep_node, spacing_m)[1:]

    def graph_distances(self, start_xy: Sequence[float]) -> np.ndarray:
        """``N`` path length (m) from ``start_xy`` to every node along the graph (inf if unreachable)."""
        a = np.asarray(start_xy, dtype=np.float64).reshape(2)
        dist, _ = self._dijkstra_from(a)
        return dist[: len(self.nodes_xy)]

    def candidate_goals(self, rng: np.random.Generator, n: int, min_dist_m: float,
                        start_xy: Sequence[float]) -> np.ndarray:
        """``n`` distinct graph nodes at least ``min_dist_m`` from ``start_xy`` along the graph.

        The paper's long-horizon runs pick a start point and candidate goals on the topological map; each run
        then draws one of the candidates.

        Raises:
            ConfigError: fewer than ``n`` nodes qualify (the message says how many do).
        """
        d = self.graph_distances(start_xy)
        ok = np.nonzero(np.isfinite(d) & (d >= min_dist_m))[0]
        if len(ok) < n:
            x, y = (float(v) for v in np.asarray(start_xy, dtype=np.float64).reshape(2))
            raise ConfigError(f"candidate_goals: asked for {n} goals at >= {min_dist_m} m along the graph "
                              f"from ({x:.2f}, {y:.2f}), but only {len(ok)} nodes qualify")
        return self.nodes_xy[rng.choice(ok, size=n, replace=False)].copy()


def _arclength(poly: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poly, axis=0).T))])


def _resample(poly: np.ndarray, s: np.ndarray, at: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(at, s, poly[:, 0]), np.interp(at, s, poly[:, 1])], -1).reshape(-1, 2)


def _space_waypoints(route: np.ndarray, keep: np.ndarray, spacing_m: float) -> np.ndarray:
    """Route vertices kept so that consecutive kept vertices are at most ``spacing_m`` apart along the route
    (always keeping the ``keep`` ones and the last); segments longer than ``spacing_m`` are subdivided."""
    out = [route[0]]
    s_last = 0.0
    s = _arclength(route)
    for k in range(1, len(route)):
        seg = s[k] - s[k - 1]
        if seg > spacing_m:  # a long straight piece (the start/goal attachment): subdivide it
            n = int(math.ceil(seg / spacing_m))
            for t in np.linspace(0.0, 1.0, n + 1)[1:-1]:
                out.append(route[k - 1] * (1 - t) + route[k] * t)
            s_last = s[k - 1] + seg * (n - 1) / n
        last = k == len(route) - 1
        too_far = k + 1 < len(route) and s[k + 1] - s_last > spacing_m
        if keep[k] or last or too_far:
            out.append(route[k])
            s_last = s[k]
    return np.array(out)


# ------------------------------------------------------------------------------------------------- extraction
def _cell_xy(layout: SceneLayout, ij: np.ndarray) -> np.ndarray:
    ij = np.asarray(ij).reshape(-1, 2)
    x0, y0 = layout.grid_origin
    return np.stack([x0 + ij[:, 1] * GRID_RES_M, y0 + ij[:, 0] * GRID_RES_M], -1)


_OFFS = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]


def _raw_graph(sk: np.ndarray, clearance: np.ndarray):
    """Nodes (as grid cells) and edges (as ordered cell lists) of a thin skeleton.

    Returns:
        ``(node_cells, edges)``: ``N x 2`` (row, col) node cells and a list of ``(u, v, cells)`` where
        ``cells`` is the ``K x 2`` ordered branch from ``u``'s side to ``v``'s side (node cells not included).
    """
    h, w = sk.shape
    nbr = ndimage.correlate(sk.astype(np.int32), _EIGHT.astype(np.int32), mode="constant") - sk
    junction = sk & (nbr >= 3)
    endpoint = sk & (nbr == 1)
    jlab, nj = ndimage.label(junction, structure=_EIGHT)
    node_cells: list[tuple[int, int]] = []
    # one node per junction cluster: its cell of largest clearance
    if nj:
        ji, jj = np.nonzero(junction)
        lab = jlab[ji, jj]
        order = np.lexsort((-clearance[ji, jj], lab))
        first = np.ones(len(order), dtype=bool)
        first[1:] = lab[order][1:] != lab[order][:-1]
        best = order[first]
        node_cells.extend(zip(ji[best].tolist(), jj[best].tolist(), strict=True))
    cluster_node = np.arange(nj)  # junction label k + 1 -> node k
    ep_node = -np.ones((h, w), dtype=np.int64)
    ei, ej = np.nonzero(endpoint)
    for a, b in zip(ei.tolist(), ej.tolist(), strict=True):
        ep_node[a, b] = len(node_cells)
        node_cells.append((a, b))
    branch = sk & ~junction
    blab, nb = ndimage.label(branch, structure=_EIGHT)
    edges: list[tuple[int, int, np.ndarray]] = []
    if nb == 0:
        return np.array(node_cells, dtype=np.int64).reshape(-1, 2), edges
    bi, bj = np.nonzero(branch)
    bl = blab[bi, bj]
    order = np.argsort(bl, kind="stable")
    bi, bj, bl = bi[order], bj[order], bl[order]
    starts = np.searchsorted(bl, np.arange(1, nb + 1))
    stops = np.append(starts[1:], len(bl))
    bnbr = ndimage.correlate(branch.astype(np.int32), _EIGHT.astype(np.int32), mode="constant") - branch

    def touching_clusters(a: int, b: int) -> list[int]:
        out = []
        for da, db in _OFFS:
            x, y = a + da, b + db
            if 0 <= x < h and 0 <= y < w and jlab[x, y] and jlab[x, y] - 1 not in out:
                out.append(int(jlab[x, y]) - 1)
        return out

    for k in range(nb):
        ci, cj = bi[starts[k]:stops[k]], bj[starts[k]:stops[k]]
        label = k + 1
        ends = [(a, b) for a, b in zip(ci.tolist(), cj.tolist(), strict=True) if bnbr[a, b] <= 1]
        if not ends:  # a closed loop with no junction: cut it open at its cell of largest clearance
            s = int(np.argmax(clearance[ci, cj]))
            cells = _walk(blab, label, (int(ci[s]), int(cj[s])))
            u = len(node_cells)
            node_cells.append(cells[0])
            edges.append((u, u, np.array(cells[1:], dtype=np.int64).reshape(-1, 2)))
            continue
        cells = _walk(blab, label, ends[0])
        first, last = cells[0], cells[-1]
        if len(cells) == 1:  # one cell: an endpoint hanging on a cluster, or a bridge between two clusters
            cl = touching_clusters(*first)
            if ep_node[first] >= 0 and cl:
                u, v, inner = int(ep_node[first]), int(cluster_node[cl[0]]), []
            elif len(cl) >= 2:
                u, v, inner = int(cluster_node[cl[0]]), int(cluster_node[cl[1]]), cells
            else:
                continue  # a one-cell notch on a single cluster: no edge
        else:
            ends_nodes = []
            for cell in (first, last):
                if ep_node[cell] >= 0:
                    ends_nodes.append(int(ep_node[cell]))
                else:
                    cl = touching_clusters(*cell)
                    ends_nodes.append(int(cluster_node[cl[0]]) if cl else -1)
            u, v = ends_nodes
            if u < 0 or v < 0:  # cannot happen on a thin skeleton; skip defensively
                continue
            inner = [c for c in cells if ep_node[c] < 0]
        edges.append((u, v, np.array(inner, dtype=np.int64).reshape(-1, 2)))
    return np.array(node_cells, dtype=np.int64).reshape(-1, 2), edges


def _walk(blab: np.ndarray, label: int, start: tuple[int, int]) -> list[tuple[int, int]]:
    """Ordered cells of one branch (a simple 8-connected path or cycle) starting at ``start``."""
    h, w = blab.shape
    out = [start]
    seen = {start}
    cur = start
    while True:
        nxt = None
        for da, db in _OFFS:
            c = (cur[0] + da, cur[1] + db)
            if 0 <= c[0] < h and 0 <= c[1] < w and blab[c] == label and c not in seen:
                # prefer 4-neighbours so a diagonal shortcut never skips a cell of the path
                if nxt is None or (da == 0 or db == 0):
                    nxt = c
        if nxt is None:
            return out
        out.append(nxt)
        seen.add(nxt)
        cur = nxt


class _Graph:
    """Mutable multigraph used while merging degree-2 nodes and pruning spurs."""

    def __init__(self, xy: np.ndarray, edges: list[list]):
        self.xy = xy
        self.edges: dict[int, list] = {k: e for k, e in enumerate(edges)}  # id -> [u, v, polyline]
        self._next = len(edges)

    def incident(self) -> dict[int, list[int]]:
        inc: dict[int, list[int]] = {k: [] for k in range(len(self.xy))}
        for k, (u, v, _) in self.edges.items():
            inc[u].append(k)
            inc[v].append(k)  # a loop appears twice
        return inc

    def merge_degree_two(self) -> None:
        changed = True
        while changed:
            changed = False
            inc = self.incident()
            for n, ks in inc.items():
                if len(ks) != 2 or ks[0] == ks[1]:
                    continue
                e1, e2 = self.edges[ks[0]], self.edges[ks[1]]
                p1 = e1[2] if e1[1] == n else e1[2][::-1]  # ... -> n
                a = e1[0] if e1[1] == n else e1[1]
                p2 = e2[2] if e2[0] == n else e2[2][::-1]  # n -> ...
                b = e2[1] if e2[0] == n else e2[0]
                del self.edges[ks[0]], self.edges[ks[1]]
                self.edges[self._next] = [a, b, np.concatenate([p1, p2[1:]])]
                self._next += 1
                changed = True
                break

    def prune_spurs(self, clearance: np.ndarray, spur_ratio: float, min_spur_m: float) -> bool:
        inc = self.incident()
        deg = {n: len(ks) for n, ks in inc.items()}
        cut: dict[int, list[tuple[float, int]]] = {}
        for k, (u, v, poly) in self.edges.items():
            if u == v:
                continue
            for tip, hub in ((u, v), (v, u)):
                if deg[tip] == 1 and deg[hub] >= 3:
                    length = float(_arclength(poly)[-1])
                    if length < spur_ratio * clearance[hub] + min_spur_m:
                        cut.setdefault(hub, []).append((length, k))
        removed = False
        for hub, spurs in cut.items():
            spurs.sort()
            if len(spurs) >= deg[hub]:  # never strip a junction bare: keep its longest branch
                spurs = spurs[:-1]
            for _, k in spurs:
                if k in self.edges:
                    del self.edges[k]
                    removed = True
        return removed

    def compact(self) -> tuple[np.ndarray, list[TopoEdge], np.ndarray]:
        """Drop nodes without edges and renumber; returns positions, edges and the kept node ids."""
        used = sorted({n for u, v, _ in self.edges.values() for n in (u, v)})
        new = {n: i for i, n in enumerate(used)}
        edges = [TopoEdge(new[u], new[v], poly, float(_arclength(poly)[-1]))
                 for u, v, poly in self.edges.values()]
        return self.xy[used].reshape(-1, 2), edges, np.array(used, dtype=np.int64)


def build_gvg(layout: SceneLayout, robot_radius_m: float, min_clearance_m: float | None = None, *,
              spur_ratio: float = 1.5, min_spur_m: float = 0.3, feature_sep_m: float | None = None,
              graph_step_m: float = 0.25, attach_radius_m: float = 5.0,
              attach_clearance_m: float | None = None) -> TopoMap:
    """The GVG topological map of a layout (method in the module docstring).

    Args:
        layout: the scene's static world (its 0.05 m occupancy and clearance grids are used).
        robot_radius_m: robot footprint radius, m (the default clearances below build on it).
        min_clearance_m: clearance every graph point keeps, m; default robot radius + 0.2 m (a 1.2 m doorway
            still passes; local controllers inflate obstacles by less than that, so the plan stays feasible
            for them).
        spur_ratio, min_spur_m: a terminal edge shorter than ``spur_ratio * clearance(junction) + min_spur_m``
            is pruned (m).
        feature_sep_m: nearest-obstacle separation below which a ridge is ignored (m); default
            ``min_clearance_m`` (a corridor the robot fits through has separation >= 2 * min_clearance).
        graph_step_m: spacing of the planning points along the edges, m.
        attach_radius_m, attach_clearance_m: how :meth:`TopoMap.plan` attaches start and goal (see
            :class:`TopoMap`); the clearance defaults to ``min_clearance_m`` + 0.1 m.

    Returns:
        The :class:`TopoMap`.

    Raises:
        ConfigError: a non-positive radius, clearance below the radius, or negative pruning parameters.
    """
    t0 = time.perf_counter()
    if not robot_radius_m > 0:
        raise ConfigError(f"build_gvg: robot_radius_m: expected > 0, got {robot_radius_m}")
    min_clear = robot_radius_m + 0.2 if min_clearance_m is None else float(min_clearance_m)
    if min_clear < robot_radius_m:
        raise ConfigError(f"build_gvg: min_clearance_m: expected >= robot_radius_m ({robot_radius_m}), got "
                          f"{min_clear}")
    if spur_ratio < 0 or min_spur_m < 0 or graph_step_m <= 0 or attach_radius_m <= 0:
        raise ConfigError(f"build_gvg: expected spur_ratio >= 0, min_spur_m >= 0, graph_step_m > 0, "
                          f"attach_radius_m > 0, got {spur_ratio}, {min_spur_m}, {graph_step_m}, "
                          f"{attach_radius_m}")
    sep = min_clear if feature_sep_m is None else float(feature_sep_m)
    clearance = layout.clearance
    ridge = medial_axis_ima(~layout.occupancy, sep / GRID_RES_M)
    sk = thin(ridge) & (clearance >= min_clear)
    node_cells, raw = _raw_graph(sk, clearance)
    xy = _cell_xy(layout, node_cells)
    g = _Graph(xy, [[u, v, np.concatenate([xy[u:u + 1], _cell_xy(layout, cells), xy[v:v + 1]])]
                    for u, v, cells in raw])
    node_clear = clearance[node_cells[:, 0], node_cells[:, 1]].astype(np.float64)
    g.merge_degree_two()
    for _ in range(20):
        if not g.prune_spurs(node_clear, spur_ratio, min_spur_m):
            break
        g.merge_degree_two()
    nodes_xy, edges, kept = g.compact()
    degree = np.zeros(len(nodes_xy), dtype=np.int64)
    adjacency: list[list[tuple[int, int]]] = [[] for _ in range(len(nodes_xy))]
    for k, e in enumerate(edges):
        degree[e.u] += 1
        degree[e.v] += 1
        adjacency[e.u].append((e.v, k))
        if e.u != e.v:
            adjacency[e.v].append((e.u, k))
    return TopoMap(layout=layout, nodes_xy=nodes_xy, degree=degree, clearance_m=node_clear[kept], edges=edges,
                   adjacency=adjacency, skeleton=sk, robot_radius_m=float(robot_radius_m),
                   min_clearance_m=min_clear, build_s=time.perf_counter() - t0, graph_step_m=graph_step_m,
                   attach_radius_m=attach_radius_m,
                   attach_clearance_m=min_clear + 0.1 if attach_clearance_m is None else attach_clearance_m)


# -------------------------------------------------------------------------------------------------- following
class WaypointFollower:
    """Which waypoint a local controller should head for, given the robot position.

    The current waypoint advances (never back) when the robot is within ``reach_radius_m`` of it, or when the
    next waypoint is closer than the current one (and, with a ``layout``, seen); with a ``layout`` it also
    jumps ahead to the farthest of the next waypoints within ``lookahead_m`` that the robot sees (a straight
    segment keeping ``robot_radius_m + margin_m`` from obstacles, and every waypoint in between seen too), so
    the controller cuts corners where that is safe.

    Usage::

        wps = topomap.plan(start, goal)
        follower = WaypointFollower(wps, layout=layout)
        v, w = dwa.command(env, waypoint_xy=follower.current(env.robot[:2]))
    """

    def __init__(self, waypoints: np.ndarray, reach_radius_m: float = 0.5, layout: SceneLayout | None = None,
                 robot_radius_m: float = 0.3, lookahead_m: float = 3.0, margin_m: float = 0.3):
        wp = np.asarray(waypoints, dtype=np.float64).reshape(-1, 2)
        if len(wp) == 0:
            raise ValueError("WaypointFollower: expected at least one waypoint (the goal), got none")
        if reach_radius_m <= 0 or lookahead_m < 0 or margin_m < 0:
            raise ValueError(f"WaypointFollower: expected reach_radius_m > 0, lookahead_m >= 0 and margin_m "
                             f">= 0, got {reach_radius_m}, {lookahead_m}, {margin_m}")
        self.waypoints = wp
        self.reach_radius_m = reach_radius_m
        self.layout = layout
        self.robot_radius_m = robot_radius_m
        self.lookahead_m = lookahead_m
        self.margin_m = margin_m
        self.index = 0

    @property
    def goal(self) -> np.ndarray:
        return self.waypoints[-1]

    @property
    def is_last(self) -> bool:
        """Whether the current waypoint is the final goal."""
        return self.index == len(self.waypoints) - 1

    def current(self, robot_xy: Sequence[float]) -> np.ndarray:
        """The waypoint to head for now (``2``, world frame, m); updates :attr:`index`."""
        p = np.asarray(robot_xy, dtype=np.float64).reshape(2)
        wp = self.waypoints
        last = len(wp) - 1
        while self.index < last:
            d_cur = float(np.hypot(*(wp[self.index] - p)))
            d_next = float(np.hypot(*(wp[self.index + 1] - p)))
            closer = d_next < d_cur and self._seen(p, wp[self.index + 1][None])[0]
            if d_cur <= self.reach_radius_m or closer:
                self.index += 1
            else:
                break
        if self.layout is not None and self.index < last:
            ahead = np.arange(self.index + 1, last + 1)
            ahead = ahead[np.hypot(*(wp[ahead] - p).T) <= self.lookahead_m]
            if len(ahead):
                # the waypoints in between must be seen too (no jumping around a corner and back)
                run = np.cumprod(self._seen(p, wp[ahead])).astype(bool)
                if run.any():
                    self.index = int(ahead[run][-1])
        return wp[self.index].copy()

    def _seen(self, p: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """Whether straight segments from ``p`` to ``targets`` keep ``robot_radius_m + margin_m`` (all True
        without a layout)."""
        if self.layout is None:
            return np.ones(len(targets), dtype=bool)
        own = float(self.layout.clearance_fast(p)[0])
        margin = min(self.robot_radius_m + self.margin_m, own - 1e-3)
        return self.layout.segments_clear(np.repeat(p[None], len(targets), 0), targets, margin, step=0.05)


# ----------------------------------------------------------------------------------------------------- figure
def plot_topomap(layout: SceneLayout, topomap: TopoMap, out_png: str | os.PathLike[str], *,
                 paths: Mapping[str, np.ndarray] | None = None, start_xy: Sequence[float] | None = None,
                 goals_xy: np.ndarray | None = None, waypoints: np.ndarray | None = None, title: str = "",
                 dpi: int = 120) -> Path:
    """Figure of a topological map, saved as PNG (written atomically).

    Draws obstacles in black, the GVG edges in light blue, junctions (dark blue squares) and endpoints (grey
    dots), and optionally paths coloured by method (legend), the start (red dot), candidate goals (green dots)
    and waypoints (blue dots) — the paper's colour code.

    Args:
        layout: the scene's static world.
        topomap: its :func:`build_gvg` map.
        out_png: output file.
        paths: method name -> ``K x 2`` world path (planned waypoints with the start, or a driven trajectory).
        start_xy: start point, m.
        goals_xy: ``G x 2`` candidate goals, m.
        waypoints: ``K x 2`` waypoints to mark, m.
        title: figure title (the scene name and graph size are appended).
        dpi: output resolution.

    Returns:
        The written path.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle, Polygon

    from sim.viz import box_corners, save_figure  # lazy: matplotlib only for plot_topomap

    path = Path(out_png)
    x0, x1, y0, y1 = layout.spec.bounds
    m = layout.spec.wall_thickness_m
    aspect = (y1 - y0 + 2 * m) / (x1 - x0 + 2 * m)
    fig = Figure(figsize=(10.0, float(np.clip(10.0 * aspect + 1.2, 3.0, 14.0))), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for o in layout.obstacles:
        if isinstance(o, Box):
            ax.add_patch(Polygon(box_corners(o), closed=True, facecolor="black", edgecolor="black", zorder=1))
        else:
            ax.add_patch(Circle(o.center, o.radius_m, facecolor="black", edgecolor="black", zorder=1))
    ax.add_collection(LineCollection([e.polyline for e in topomap.edges], colors="#8ec5ff", linewidths=1.5,
                                     zorder=2))
    j, e = topomap.junctions, topomap.endpoints
    ax.scatter(*topomap.nodes_xy[j].T, marker="s", s=22, c="#1f3f8f", zorder=3, label=f"junctions ({len(j)})")
    ax.scatter(*topomap.nodes_xy[e].T, marker="o", s=14, c="#777777", zorder=3, label=f"endpoints ({len(e)})")
    # one distinct colour per method for the nine of a benchmark, none of the map's own (GVG light blue, waypoints
    # blue, goals green, start red, obstacles black)
    colors = ["tab:orange", "tab:purple", "tab:cyan", "tab:brown", "tab:pink", "tab:olive", "gold", "indigo",
              "tab:gray", "darkgoldenrod"]
    for k, (name, p) in enumerate((paths or {}).items()):
        p = np.asarray(p, dtype=np.float64).reshape(-1, 2)
        ax.plot(p[:, 0], p[:, 1], "-", color=colors[k % len(colors)], lw=2.0, zorder=4, label=name)
    if waypoints is not None and len(waypoints):
        ax.scatter(*np.asarray(waypoints).reshape(-1, 2).T, s=12, c="tab:blue", zorder=5, label="waypoints")
    if goals_xy is not None and len(goals_xy):
        ax.scatter(*np.asarray(goals_xy).reshape(-1, 2).T, s=40, c="tab:green", zorder=6,
                   label="candidate goals")
    if start_xy is not None:
        ax.scatter([start_xy[0]], [start_xy[1]], s=60, c="tab:red", zorder=7, label="start")
    ax.set_xlim(x0 - m, x1 + m)
    ax.set_ylim(y0 - m, y1 + m)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    head = f"{title} — " if title else ""
    ax.set_title(f"{head}{layout.spec.name}: GVG with {len(topomap.nodes_xy)} nodes, "
                 f"{len(topomap.edges)} edges, {topomap.total_length_m:.0f} m", fontsize=9)
    return save_figure(fig, path, dpi)
