"""Scenes as data files: schema, validation, per-episode layouts, occupancy grids and shortest paths.

A scene is a YAML file in ``sim/scenes/`` (or any path given by the user). Schema (units in the names; every key
not marked optional is required)::

    name: office_lobby                 # must equal the file stem
    split: test                        # train | test | long_horizon
    description: "..."                 # optional, free text
    bounds: [x_min, x_max, y_min, y_max]   # m, the free interior; the four outer walls are added just outside
    wall_height_m: 2.5                 # optional (2.5)
    wall_thickness_m: 0.2              # optional (0.2)
    wall_color: [r, g, b]              # optional, 0..1
    floor_color: [r, g, b]             # optional, 0..1
    obstacles:                         # optional; each item has exactly one of these keys
      - box: {center: [x, y], size: [sx, sy], yaw_deg: 0, height_m: 1.0, color: [r, g, b]}
      - wall: {from: [x, y], to: [x, y], thickness_m: 0.2, height_m: 2.5, color: [r, g, b]}
      - cylinder: {center: [x, y], radius_m: 0.3, height_m: 1.0, color: [r, g, b]}
    random_obstacles:                  # optional: clutter drawn anew every episode (seeded)
      count: [min, max]
      size_m: [min, max]               # side length of square-ish boxes
      height_m: [min, max]
      region: [x_min, x_max, y_min, y_max]
      clearance_m: 0.6                 # optional: kept free around start and goal
    start_goal:                        # optional
      distance_m: [min, max]           # straight-line (euclidean) or path (geodesic) distance
      metric: euclidean                # euclidean | geodesic
      clearance_m: 0.5                 # free space around start and goal
      region: [x_min, x_max, y_min, y_max]   # optional, where start and goal may lie
    pedestrians:                       # optional
      region: [x_min, x_max, y_min, y_max]   # optional spawn/goal region
      max_count: 40                    # optional cap

Density (ped/m²) is a run parameter, not part of the file: the pedestrian count is
``round(density * free_area_m2)`` with the free area measured on the occupancy grid.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from pipeline.core.errors import ConfigError, InputMissingError
from sim.geometry import Box, Cylinder, Obstacle, StaticGeometry

SCENES_DIR = Path(__file__).resolve().parent / "scenes"
SPLITS = ("train", "test", "long_horizon")
GRID_RES_M = 0.05  # occupancy grid resolution
NAV_RES_M = 0.1  # shortest-path grid resolution

_TOP_KEYS = {
    "name", "split", "description", "bounds", "wall_height_m", "wall_thickness_m", "wall_color", "floor_color",
    "obstacles", "random_obstacles", "start_goal", "pedestrians",
}


def check_episode_grid(scenes: list[str], densities: list[float], episodes: int, workers: int) -> None:
    """Validate the (scenes × densities × episodes) grid of a stage that runs episodes, and its worker count.

    Raises:
        ConfigError: naming the field, the expected and the actual value.
    """
    if not scenes:
        raise ConfigError("scenes: expected at least one scene, got an empty list")
    for s in scenes:
        load_scene(s)
    if not densities:
        raise ConfigError("densities: expected at least one density, got an empty list")
    for d in densities:
        if not math.isfinite(d) or d < 0 or d > 2.0:
            raise ConfigError(f"densities: expected values in [0, 2] ped/m², got {d}")
    if episodes < 1:
        raise ConfigError(f"episodes: expected >= 1, got {episodes}")
    if workers < 1:
        raise ConfigError(f"workers: expected >= 1, got {workers}")


def available_scenes() -> list[str]:
    """Names of the scenes shipped in ``sim/scenes/``."""
    return sorted(p.stem for p in SCENES_DIR.glob("*.yaml"))


def scenes_of_split(split: str) -> list[str]:
    """Shipped scene names of one split (``train``, ``test`` or ``long_horizon``)."""
    return [n for n in available_scenes() if load_scene(n).split == split]


@dataclass(frozen=True)
class RandomObstacles:
    """Per-episode clutter. Ranges are inclusive ``(min, max)``; ``region`` is ``(x_min, x_max, y_min, y_max)``."""

    count: tuple[int, int]
    size_m: tuple[float, float]
    height_m: tuple[float, float]
    region: tuple[float, float, float, float]
    clearance_m: float = 0.6


@dataclass(frozen=True)
class StartGoalSpec:
    """How start and goal are drawn: distance range (m) under a metric, clearance (m), optional region."""

    distance_m: tuple[float, float] = (5.5, 6.5)
    metric: str = "euclidean"
    clearance_m: float = 0.5
    region: tuple[float, float, float, float] | None = None


@dataclass(frozen=True)
class SceneSpec:
    """A validated scene file. See the module docstring for the schema."""

    name: str
    split: str
    bounds: tuple[float, float, float, float]
    obstacles: tuple[Obstacle, ...]
    description: str = ""
    wall_height_m: float = 2.5
    wall_thickness_m: float = 0.2
    wall_color: tuple[float, float, float] = (0.82, 0.8, 0.76)
    floor_color: tuple[float, float, float] = (0.55, 0.55, 0.52)
    random_obstacles: RandomObstacles | None = None
    start_goal: StartGoalSpec = field(default_factory=StartGoalSpec)
    ped_region: tuple[float, float, float, float] | None = None
    ped_max_count: int = 60
    path: str = ""

    def outer_walls(self) -> list[Box]:
        """The four boundary walls, just outside the bounds (the bounds are the free interior, wall to wall)."""
        x0, x1, y0, y1 = self.bounds
        t, h, c = self.wall_thickness_m, self.wall_height_m, self.wall_color
        w, d = x1 - x0, y1 - y0
        return [
            Box(((x0 + x1) / 2, y0 - t / 2), (w + 2 * t, t), 0.0, h, c),
            Box(((x0 + x1) / 2, y1 + t / 2), (w + 2 * t, t), 0.0, h, c),
            Box((x0 - t / 2, (y0 + y1) / 2), (t, d + 2 * t), 0.0, h, c),
            Box((x1 + t / 2, (y0 + y1) / 2), (t, d + 2 * t), 0.0, h, c),
        ]

    def layout(self, rng: np.random.Generator | None = None) -> SceneLayout:
        """The static world of one episode: fixed obstacles plus, if the scene has them, random clutter.

        Scenes without random obstacles return one cached layout (occupancy and graphs are computed once).
        """
        if self.random_obstacles is None:
            return _static_layout(self)
        if rng is None:
            raise ValueError(f"scene {self.name!r} has random obstacles: layout() needs an rng")
        return SceneLayout(self, list(self.obstacles) + self.outer_walls() + self._draw_clutter(rng))

    def _draw_clutter(self, rng: np.random.Generator) -> list[Obstacle]:
        ro = self.random_obstacles
        assert ro is not None
        n = int(rng.integers(ro.count[0], ro.count[1] + 1))
        out: list[Obstacle] = []
        colors = [(0.55, 0.38, 0.22), (0.3, 0.45, 0.6), (0.6, 0.55, 0.3), (0.45, 0.45, 0.45)]
        for _ in range(n):
            sx, sy = rng.uniform(*ro.size_m, size=2)
            cx = rng.uniform(ro.region[0] + sx / 2, ro.region[1] - sx / 2)
            cy = rng.uniform(ro.region[2] + sy / 2, ro.region[3] - sy / 2)
            yaw = float(rng.uniform(-math.pi, math.pi))
            h = float(rng.uniform(*ro.height_m))
            out.append(Box((float(cx), float(cy)), (float(sx), float(sy)), yaw, h, colors[int(rng.integers(len(colors)))]))
        return out


@functools.lru_cache(maxsize=32)
def _static_layout(spec: SceneSpec) -> SceneLayout:
    return SceneLayout(spec, list(spec.obstacles) + spec.outer_walls())


class SceneLayout:
    """The static world of one episode and the grids derived from it.

    Attributes:
        spec: the scene file it came from.
        obstacles: every obstacle including the outer walls, world frame.
        geometry: packed arrays for distance and ray queries.
        grid_origin: world (x, y) of the centre of cell ``[0, 0]``; cell ``[i, j]`` is row ``i`` along +y and
            column ``j`` along +x, both at ``GRID_RES_M``.
        clearance: ``H x W`` signed distance of each cell centre to the nearest obstacle surface, m.
        occupancy: ``H x W`` bool, True where the cell centre is inside an obstacle (the grid spans the bounds
            plus the outer walls).
        free_area_m2: area of free cells (all of them lie inside the bounds).
    """

    def __init__(self, spec: SceneSpec, obstacles: list[Obstacle]):
        self.spec = spec
        self.obstacles = obstacles
        self.geometry = StaticGeometry(obstacles)
        # the grid covers the bounds plus the outer walls, so lookups near the walls need no clipping
        m = spec.wall_thickness_m
        x0, x1, y0, y1 = spec.bounds
        xs = np.arange(x0 - m + GRID_RES_M / 2, x1 + m, GRID_RES_M)
        ys = np.arange(y0 - m + GRID_RES_M / 2, y1 + m, GRID_RES_M)
        self.grid_origin = (float(xs[0]), float(ys[0]))
        gx, gy = np.meshgrid(xs, ys)
        clear, _ = self.geometry.signed_distance(np.stack([gx, gy], -1))
        self.clearance = clear.astype(np.float32)
        self.occupancy = self.clearance <= 0.0
        self.free_area_m2 = float((~self.occupancy).sum()) * GRID_RES_M**2
        self._nav: dict[tuple[float, bool], _NavGraph] = {}
        self._free_cells: dict[tuple, np.ndarray] = {}
        self._clear_flat = self.clearance.astype(np.float64).ravel()

    def clearance_fast(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bilinear lookup of the clearance grid: signed distance (m) and its gradient at ``... x 2`` points.

        The gradient (of the bilinear interpolant) points away from the nearest obstacle, length ≈ 1 away from
        medial lines and corners. Error
        against :meth:`clearance_at` is below a few mm except within one cell of an obstacle corner (tested).
        Points outside the grid take the value of the nearest border cell.
        """
        p = np.asarray(xy, dtype=np.float64)
        h, w = self.clearance.shape
        fx = np.clip((p[..., 0] - self.grid_origin[0]) / GRID_RES_M, 0.0, w - 1.000001)
        fy = np.clip((p[..., 1] - self.grid_origin[1]) / GRID_RES_M, 0.0, h - 1.000001)
        j = fx.astype(np.intp)
        i = fy.astype(np.intp)
        tx = fx - j
        ty = fy - i
        flat = self._clear_flat
        k = i * w + j
        c00, c01, c10, c11 = flat[k], flat[k + 1], flat[k + w], flat[k + w + 1]
        bottom = c00 + (c01 - c00) * tx
        top = c10 + (c11 - c10) * tx
        d = bottom + (top - bottom) * ty
        gx = ((c01 - c00) * (1 - ty) + (c11 - c10) * ty) / GRID_RES_M
        gy = (top - bottom) / GRID_RES_M
        return d, np.stack([gx, gy], -1)

    def segments_min_clearance(self, a: np.ndarray, b: np.ndarray, step: float = 0.1) -> np.ndarray:
        """Smallest obstacle clearance (m) along straight segments ``K x 2 -> K x 2``, sampled every ``step`` m
        on the clearance grid."""
        a = np.asarray(a, dtype=np.float64).reshape(-1, 2)
        b = np.asarray(b, dtype=np.float64).reshape(-1, 2)
        n = max(2, int(math.ceil(np.max(np.hypot(*(b - a).T), initial=0.0) / step)) + 1)
        t = np.linspace(0.0, 1.0, n)[None, :, None]
        d, _ = self.clearance_fast(a[:, None, :] * (1 - t) + b[:, None, :] * t)
        return d.min(axis=1)

    def segments_clear(self, a: np.ndarray, b: np.ndarray, margin: float | np.ndarray,
                       step: float = 0.1) -> np.ndarray:
        """Whether straight segments keep ``margin`` (m, scalar or ``K``) from every obstacle (grid lookup)."""
        return self.segments_min_clearance(a, b, step) >= margin

    # ----------------------------------------------------------------------------------------------- queries
    def clearance_at(self, xy: np.ndarray) -> np.ndarray:
        """Exact signed distance (m) of ``... x 2`` world points to the nearest obstacle."""
        return self.geometry.signed_distance(xy)[0]

    def ped_count(self, density: float) -> int:
        """Pedestrians for a density in ped/m² of free area, capped by the scene's ``max_count``."""
        return int(min(round(density * self.free_area_m2), self.spec.ped_max_count))

    def free_points(self, rng: np.random.Generator, n: int, clearance_m: float,
                    region: tuple[float, float, float, float] | None = None) -> np.ndarray:
        """``n x 2`` random world points with at least ``clearance_m`` to every obstacle (cell-centre jitter)."""
        cells = self._cells_with_clearance(clearance_m + GRID_RES_M, region)
        if len(cells) == 0:
            raise ConfigError(
                f"scene {self.spec.name!r}: no free space with clearance {clearance_m:.2f} m"
                + (f" in region {region}" if region else "")
            )
        idx = rng.integers(len(cells), size=n)
        jitter = rng.uniform(-GRID_RES_M / 2, GRID_RES_M / 2, size=(n, 2))
        return cells[idx] + jitter

    def _cells_with_clearance(self, clearance_m: float, region) -> np.ndarray:
        # quantise up to 1 cm *before* computing, so the cached result never depends on which nearby value came
        # first (determinism) and the cache stays small
        clearance_m = math.ceil(round(clearance_m * 100.0, 6)) / 100.0
        key = (clearance_m, region)
        if key in self._free_cells:
            return self._free_cells[key]
        mask = self.clearance >= clearance_m
        ii, jj = np.nonzero(mask)
        pts = np.stack([self.grid_origin[0] + jj * GRID_RES_M, self.grid_origin[1] + ii * GRID_RES_M], -1)
        if region is not None:
            r = region
            keep = (pts[:, 0] >= r[0]) & (pts[:, 0] <= r[1]) & (pts[:, 1] >= r[2]) & (pts[:, 1] <= r[3])
            pts = pts[keep]
        self._free_cells[key] = pts
        return pts

    def path_length(self, a: np.ndarray, b: np.ndarray, robot_radius_m: float) -> float:
        """Any-angle shortest path length (m) from ``a`` to ``b`` keeping the robot radius + 5 cm; inf if none."""
        return _polyline_length(self.nav(robot_radius_m + 0.05).shortest_path(self, a, b))

    def nav(self, inflation_m: float, wall_penalty: bool = False) -> _NavGraph:
        """The shortest-path graph for a disc robot of radius ``inflation_m`` (cached per radius).

        With ``wall_penalty`` edge weights grow near obstacles (for planning); without, they are metric lengths
        (for geodesic distances).
        """
        key = (round(inflation_m, 3), wall_penalty)
        if key not in self._nav:
            self._nav[key] = _NavGraph(self, key[0], wall_penalty)
        return self._nav[key]

    def sample_start_goal(self, rng: np.random.Generator, robot_radius_m: float, max_tries: int = 200,
                          exact_length: bool = True) -> tuple[np.ndarray, np.ndarray, float]:
        """Draw a connected start and goal per the scene's ``start_goal`` spec.

        Returns:
            ``(start_xy, goal_xy, geodesic_m)``: world positions (m) and the length of the any-angle shortest path
            between them that keeps the robot radius + 5 cm from obstacles (:meth:`_NavGraph.shortest_path`);
            nan when ``exact_length`` is False and the scene's metric is euclidean (it is then not needed to
            accept the pair; :meth:`path_length` computes it later).
        """
        sg = self.spec.start_goal
        nav = self.nav(robot_radius_m + 0.05)
        lo, hi = sg.distance_m
        for _ in range(max_tries):
            start = self.free_points(rng, 1, max(sg.clearance_m, robot_radius_m + 0.1), sg.region)[0]
            dist_field = nav.distances_from(start)
            cand = self._cells_with_clearance(max(sg.clearance_m, robot_radius_m + 0.1) + GRID_RES_M, sg.region)
            geo = nav.lookup(dist_field, cand)
            eu = np.hypot(*(cand - start).T)
            # grid lengths exceed any-angle lengths by up to ~3 %: pre-select generously, then measure exactly
            metric = geo if sg.metric == "geodesic" else eu
            upper = hi * 1.04 if sg.metric == "geodesic" else hi
            ok = np.isfinite(geo) & (metric >= lo) & (metric <= upper)
            if not ok.any():
                continue
            k = rng.choice(np.nonzero(ok)[0])
            goal = cand[k] + rng.uniform(-GRID_RES_M / 2, GRID_RES_M / 2, 2)
            if sg.metric == "euclidean" and not exact_length:
                return start, goal, math.nan
            length = self.path_length(start, goal, robot_radius_m)
            if not math.isfinite(length) or (sg.metric == "geodesic" and not lo <= length <= hi):
                continue
            return start, goal, length
        raise ConfigError(
            f"scene {self.spec.name!r}: found no connected start/goal pair with {sg.metric} distance in "
            f"[{lo}, {hi}] m after {max_tries} tries"
        )


def _polyline_length(path: np.ndarray) -> float:
    return float(np.sum(np.hypot(*np.diff(path, axis=0).T))) if len(path) else math.inf


class _NavGraph:
    """16-connected grid graph over cells with clearance >= ``inflation_m`` (``NAV_RES_M`` cells).

    Edge weights are metric lengths; with ``wall_penalty`` they are multiplied by ``1 + 2·(0.5 − e)/0.5`` where
    ``e = clip(clearance − inflation, 0, 0.5)`` m, so planned paths keep a margin from walls where there is room.
    """

    def __init__(self, layout: SceneLayout, inflation_m: float, wall_penalty: bool = False):
        self.inflation_m = inflation_m
        x0, x1, y0, y1 = layout.spec.bounds
        xs = np.arange(x0 + NAV_RES_M / 2, x1, NAV_RES_M)
        ys = np.arange(y0 + NAV_RES_M / 2, y1, NAV_RES_M)
        self.origin = np.array([xs[0], ys[0]])
        self.shape = (len(ys), len(xs))
        gx, gy = np.meshgrid(xs, ys)
        clear = layout.clearance_at(np.stack([gx, gy], -1))
        self.clearance = clear
        free = clear >= inflation_m
        self.free = free
        h, w = self.shape
        idx = np.arange(h * w).reshape(h, w)
        extra = np.clip(clear - inflation_m, 0.0, 0.5)
        penalty = 1.0 + 2.0 * (0.5 - extra) / 0.5 if wall_penalty else np.ones_like(extra)
        rows, cols, wts = [], [], []
        def shifted(a: np.ndarray, di: int, dj: int) -> np.ndarray:
            """``a[i + di, j + dj]`` for every cell (False beyond the border)."""
            out = np.zeros_like(a)
            out[max(0, -di):h - max(0, di), max(0, -dj):w - max(0, dj)] = \
                a[max(0, di):h - max(0, -di), max(0, dj):w - max(0, -dj)]
            return out

        # 16-connected: straight, diagonal and knight moves (path lengths within ~3 % of any-angle paths); a move
        # needs every cell it sweeps to be free
        for di, dj, via in ((0, 1, ()), (1, 0, ()), (1, 1, ((0, 1), (1, 0))), (1, -1, ((0, -1), (1, 0))),
                            (1, 2, ((0, 1), (1, 1))), (2, 1, ((1, 0), (1, 1))),
                            (1, -2, ((0, -1), (1, -1))), (2, -1, ((1, 0), (1, -1)))):
            ra, rb = slice(0, h - di), slice(di, h)
            ca, cb = (slice(0, w - dj), slice(dj, w)) if dj >= 0 else (slice(-dj, w), slice(0, w + dj))
            ok = free[ra, ca] & free[rb, cb]
            for vi, vj in via:
                ok &= shifted(free, vi, vj)[ra, ca]
            length = NAV_RES_M * math.hypot(di, dj)
            rows.append(idx[ra, ca][ok])
            cols.append(idx[rb, cb][ok])
            wts.append(length * 0.5 * (penalty[ra, ca][ok] + penalty[rb, cb][ok]))
        r = np.concatenate(rows)
        c = np.concatenate(cols)
        wv = np.concatenate(wts)
        n = h * w
        self.graph = coo_matrix((np.concatenate([wv, wv]), (np.concatenate([r, c]), np.concatenate([c, r]))),
                                shape=(n, n)).tocsr()

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        """``... x 2`` (row, col) indices of world points, clipped to the grid."""
        ij = np.floor((np.asarray(xy)[..., ::-1] - self.origin[::-1]) / NAV_RES_M + 0.5).astype(int)
        ij[..., 0] = np.clip(ij[..., 0], 0, self.shape[0] - 1)
        ij[..., 1] = np.clip(ij[..., 1], 0, self.shape[1] - 1)
        return ij

    def _nearest_free(self, xy: np.ndarray) -> int:
        i, j = self.cell_of(xy)
        if self.free[i, j]:
            return int(i * self.shape[1] + j)
        fi, fj = np.nonzero(self.free)
        k = np.argmin((fi - i) ** 2 + (fj - j) ** 2)
        return int(fi[k] * self.shape[1] + fj[k])

    def distances_from(self, xy: np.ndarray) -> np.ndarray:
        """``H x W`` weighted path length (m) from every cell to the free cell nearest ``xy``; inf if unreachable."""
        src = self._nearest_free(np.asarray(xy, dtype=np.float64))
        d = dijkstra(self.graph, directed=False, indices=src)
        d = d.reshape(self.shape)
        d[~self.free] = np.inf
        return d

    def shortest_path(self, layout: SceneLayout, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Any-angle shortest path from ``a`` to ``b`` (``K x 2`` world points, m), or an empty array if unreachable.

        The grid path from Dijkstra is shortened by line-of-sight string pulling: from each kept vertex, jump to
        the farthest later vertex whose straight segment keeps the graph's clearance.
        """
        src = self._nearest_free(np.asarray(a, dtype=np.float64))
        dst = self._nearest_free(np.asarray(b, dtype=np.float64))
        _, pred = dijkstra(self.graph, directed=False, indices=src, return_predecessors=True)
        if src != dst and pred[dst] < 0:
            return np.zeros((0, 2))
        cells = [dst]
        while cells[-1] != src:
            cells.append(int(pred[cells[-1]]))
        cells.reverse()
        ij = np.array([divmod(c, self.shape[1]) for c in cells])
        pts = np.concatenate([np.asarray(a, dtype=np.float64)[None], self.origin + ij[:, ::-1] * NAV_RES_M,
                              np.asarray(b, dtype=np.float64)[None]])
        margin = self.inflation_m - 0.5 * NAV_RES_M  # the grid's own tolerance
        out = [pts[0]]
        i = 0
        while i < len(pts) - 1:
            later = pts[i + 1:]
            ok = layout.segments_clear(np.repeat(pts[i][None], len(later), 0), later, margin, step=0.05)
            ok[0] = True  # neighbours on the grid path are always connected
            j = i + 1 + int(np.nonzero(ok)[0].max())
            out.append(pts[j])
            i = j
        return np.array(out)

    def lookup(self, field_: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """Values of a grid field at the cells of ``... x 2`` world points."""
        ij = self.cell_of(xy)
        return field_[ij[..., 0], ij[..., 1]]


# ---------------------------------------------------------------------------------------------------- loading
def _err(src: str, key: str, expected: str, actual: Any) -> ConfigError:
    return ConfigError(f"scene file {src}: field '{key}': expected {expected}, got {actual!r}")


def _num_list(src: str, key: str, v: Any, n: int, positive: bool = False) -> tuple[float, ...]:
    if not isinstance(v, list | tuple) or len(v) != n or not all(
        isinstance(x, int | float) and not isinstance(x, bool) for x in v
    ):
        raise _err(src, key, f"a list of {n} numbers", v)
    if positive and any(x <= 0 for x in v):
        raise _err(src, key, "positive numbers", v)
    return tuple(float(x) for x in v)


def _num(src: str, key: str, v: Any, lo: float = -math.inf, hi: float = math.inf) -> float:
    if not isinstance(v, int | float) or isinstance(v, bool) or not (lo <= v <= hi):
        raise _err(src, key, f"a number in [{lo}, {hi}]", v)
    return float(v)


def _range(src: str, key: str, v: Any) -> tuple[float, float]:
    a, b = _num_list(src, key, v, 2)
    if a > b:
        raise _err(src, key, "[min, max] with min <= max", v)
    return a, b


def _rect(src: str, key: str, v: Any) -> tuple[float, float, float, float]:
    r = _num_list(src, key, v, 4)
    if r[0] >= r[1] or r[2] >= r[3]:
        raise _err(src, key, "[x_min, x_max, y_min, y_max] with min < max", v)
    return r  # type: ignore[return-value]


def _color(src: str, key: str, v: Any) -> tuple[float, float, float]:
    c = _num_list(src, key, v, 3)
    if any(x < 0 or x > 1 for x in c):
        raise _err(src, key, "three numbers in [0, 1]", v)
    return c  # type: ignore[return-value]


def _check_keys(src: str, key: str, d: Any, allowed: set[str], required: set[str]) -> None:
    if not isinstance(d, dict):
        raise _err(src, key, "a mapping", d)
    unknown = set(d) - allowed
    if unknown:
        raise ConfigError(f"scene file {src}: unknown field '{key}.{sorted(unknown)[0]}'; allowed: {sorted(allowed)}")
    missing = required - set(d)
    if missing:
        raise ConfigError(f"scene file {src}: missing field '{key}.{sorted(missing)[0]}'")


def _parse_obstacle(src: str, i: int, item: Any, wall_h: float, wall_c: tuple) -> Obstacle:
    key = f"obstacles[{i}]"
    if not isinstance(item, dict) or len(item) != 1:
        raise _err(src, key, "a mapping with exactly one of box / wall / cylinder", item)
    kind, d = next(iter(item.items()))
    k = f"{key}.{kind}"
    if kind == "box":
        _check_keys(src, k, d, {"center", "size", "yaw_deg", "height_m", "color"}, {"center", "size"})
        return Box(_num_list(src, k + ".center", d["center"], 2), _num_list(src, k + ".size", d["size"], 2, True),
                   math.radians(_num(src, k + ".yaw_deg", d.get("yaw_deg", 0.0))),
                   _num(src, k + ".height_m", d.get("height_m", 1.0), 0.01, 20),
                   _color(src, k + ".color", d.get("color", [0.55, 0.4, 0.25])))
    if kind == "wall":
        _check_keys(src, k, d, {"from", "to", "thickness_m", "height_m", "color"}, {"from", "to"})
        a = np.array(_num_list(src, k + ".from", d["from"], 2))
        b = np.array(_num_list(src, k + ".to", d["to"], 2))
        length = float(np.hypot(*(b - a)))
        if length <= 0:
            raise _err(src, k, "'from' and 'to' to differ", d)
        t = _num(src, k + ".thickness_m", d.get("thickness_m", 0.2), 0.01, 5)
        yaw = math.atan2(b[1] - a[1], b[0] - a[0])
        return Box(tuple((a + b) / 2), (length, t), yaw, _num(src, k + ".height_m", d.get("height_m", wall_h), 0.01, 20),
                   _color(src, k + ".color", d.get("color", list(wall_c))))
    if kind == "cylinder":
        _check_keys(src, k, d, {"center", "radius_m", "height_m", "color"}, {"center", "radius_m"})
        return Cylinder(_num_list(src, k + ".center", d["center"], 2), _num(src, k + ".radius_m", d["radius_m"], 0.01, 20),
                        _num(src, k + ".height_m", d.get("height_m", 1.0), 0.01, 20),
                        _color(src, k + ".color", d.get("color", [0.6, 0.6, 0.65])))
    raise _err(src, key, "one of box / wall / cylinder", kind)


def parse_scene(data: Any, src: str, stem: str | None = None) -> SceneSpec:
    """Validate a scene mapping (as loaded from YAML) and build its :class:`SceneSpec`.

    Raises:
        ConfigError: naming the file, the field, what was expected and what was found.
    """
    _check_keys(src, "<top>", data, _TOP_KEYS, {"name", "split", "bounds"})
    name = data["name"]
    if not isinstance(name, str) or not name:
        raise _err(src, "name", "a non-empty string", name)
    if stem is not None and name != stem:
        raise _err(src, "name", f"the file stem {stem!r}", name)
    if data["split"] not in SPLITS:
        raise _err(src, "split", f"one of {list(SPLITS)}", data["split"])
    bounds = _rect(src, "bounds", data["bounds"])
    wall_h = _num(src, "wall_height_m", data.get("wall_height_m", 2.5), 0.1, 20)
    wall_c = _color(src, "wall_color", data.get("wall_color", [0.82, 0.8, 0.76]))
    obstacles_raw = data.get("obstacles") or []
    if not isinstance(obstacles_raw, list):
        raise _err(src, "obstacles", "a list", obstacles_raw)
    obstacles = tuple(_parse_obstacle(src, i, it, wall_h, wall_c) for i, it in enumerate(obstacles_raw))
    ro = None
    if data.get("random_obstacles") is not None:
        d = data["random_obstacles"]
        _check_keys(src, "random_obstacles", d, {"count", "size_m", "height_m", "region", "clearance_m"},
                    {"count", "size_m", "region"})
        cnt = _range(src, "random_obstacles.count", d["count"])
        if cnt[0] < 0 or cnt != tuple(int(x) for x in cnt):
            raise _err(src, "random_obstacles.count", "two non-negative integers", d["count"])
        ro = RandomObstacles((int(cnt[0]), int(cnt[1])), _range(src, "random_obstacles.size_m", d["size_m"]),
                             _range(src, "random_obstacles.height_m", d.get("height_m", [0.5, 1.2])),
                             _rect(src, "random_obstacles.region", d["region"]),
                             _num(src, "random_obstacles.clearance_m", d.get("clearance_m", 0.6), 0, 5))
    sg = StartGoalSpec()
    if data.get("start_goal") is not None:
        d = data["start_goal"]
        _check_keys(src, "start_goal", d, {"distance_m", "metric", "clearance_m", "region"}, set())
        metric = d.get("metric", "euclidean")
        if metric not in ("euclidean", "geodesic"):
            raise _err(src, "start_goal.metric", "euclidean or geodesic", metric)
        dist = _range(src, "start_goal.distance_m", d.get("distance_m", [5.5, 6.5]))
        if dist[0] <= 0:
            raise _err(src, "start_goal.distance_m", "positive distances", d.get("distance_m"))
        sg = StartGoalSpec(dist, metric, _num(src, "start_goal.clearance_m", d.get("clearance_m", 0.5), 0.0, 5.0),
                           _rect(src, "start_goal.region", d["region"]) if d.get("region") is not None else None)
    ped_region, ped_max = None, 60
    if data.get("pedestrians") is not None:
        d = data["pedestrians"]
        _check_keys(src, "pedestrians", d, {"region", "max_count"}, set())
        if d.get("region") is not None:
            ped_region = _rect(src, "pedestrians.region", d["region"])
        ped_max = int(_num(src, "pedestrians.max_count", d.get("max_count", 60), 0, 500))
    desc = data.get("description", "")
    if not isinstance(desc, str):
        raise _err(src, "description", "a string", desc)
    return SceneSpec(
        name=name, split=data["split"], bounds=bounds, obstacles=obstacles, description=desc,
        wall_height_m=wall_h, wall_thickness_m=_num(src, "wall_thickness_m", data.get("wall_thickness_m", 0.2), 0.01, 5),
        wall_color=wall_c, floor_color=_color(src, "floor_color", data.get("floor_color", [0.55, 0.55, 0.52])),
        random_obstacles=ro, start_goal=sg, ped_region=ped_region, ped_max_count=ped_max, path=src,
    )


def load_scene(name_or_path: str) -> SceneSpec:
    """Load and validate a scene by shipped name (``office_lobby``) or by path to a YAML file.

    Raises:
        ConfigError: unknown scene name (listing the known ones) or an invalid file.
        InputMissingError: a path that does not exist.
    """
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or "/" in name_or_path:
        if not p.exists():
            raise InputMissingError(f"scene file not found: {p}")
    else:
        p = SCENES_DIR / f"{name_or_path}.yaml"
        if not p.exists():
            raise ConfigError(f"unknown scene {name_or_path!r}; known scenes: {', '.join(available_scenes())} "
                              "(or pass a path to a scene YAML file)")
    return _load_scene_file(str(p.resolve()), p.stat().st_mtime_ns)


@functools.lru_cache(maxsize=64)
def _load_scene_file(path: str, mtime_ns: int) -> SceneSpec:
    """Parse one scene file (cached per path and modification time, so edits are picked up)."""
    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text())
    except yaml.YAMLError as e:
        raise ConfigError(f"scene file {p}: not valid YAML ({str(e).splitlines()[0]})") from None
    return parse_scene(data, str(p), stem=p.stem)
