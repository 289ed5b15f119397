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
    free_space:                        # optional: the free interior as a union of rectangles; the rest of
      - [x_min, x_max, y_min, y_max]   # the bounds becomes solid (an L- or T-junction without carving)
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
      max_detour: 1.25                 # optional: shortest path <= this x the straight line
      fixed_line_of_sight: true        # optional (false): the straight start-goal segment crosses none of the
                                       # fixed obstacles (random clutter may block it): with max_detour, no
                                       # routing round a shelf row -- the test measures crowd navigation
    pedestrians:                       # optional
      region: [x_min, x_max, y_min, y_max]   # optional spawn/goal region
      max_count: 40                    # optional cap
      goal_choice: first               # optional: first | farthest visible goal in range (corridor layouts)

A file is decoded and checked by the same machinery as the stage configs (:mod:`pipeline.core.config`: draccus
decodes it into :class:`SceneFile`, then every ``validate()`` runs), so its errors name the file, the key, the
expected and the actual value in the same words. ``from`` is a Python keyword, so a wall's ``from`` is read into
the field ``from_`` (and named so in error messages).

Density (ped/m²) is a run parameter, not part of the file: the pedestrian count is
``round(density * free_area_m2)`` with the free area measured on the occupancy grid.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from pipeline.core.config import FieldValueError, from_dict, read_yaml, validate_tree
from pipeline.core.errors import ConfigError, InputMissingError
from sim.geometry import Box, Cylinder, Obstacle, StaticGeometry

SCENES_DIR = Path(__file__).resolve().parent / "scenes"
SPLITS = ("train", "test", "long_horizon")
GRID_RES_M = 0.05  # occupancy grid resolution
NAV_RES_M = 0.1  # shortest-path grid resolution
# Size limits, checked when a file is read, before any grid is allocated (the largest shipped scene, office_floor,
# has 600 m², 32 obstacles and ~8e6 cell-obstacle pairs): the clearance grid costs GRID_RES_M⁻² cells per m² and
# its signed-distance pass time ∝ cells × obstacles.
MAX_AREA_M2 = 5_000.0
MAX_OBSTACLES = 1_000  # listed + the random clutter's maximum + the boxes filling outside free_space
MAX_CELL_OBSTACLE_PAIRS = 200_000_000  # ≈ 15 s of the signed-distance pass on one core (measured: 2.5e8 in 18.6 s)


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
    max_detour: float | None = None  # shortest path / straight line, at most
    fixed_line_of_sight: bool = False  # the straight segment keeps clear of the fixed obstacles (not the clutter)


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
    ped_goal_choice: str = "first"  # first | farthest (see PedestriansFile)
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
        fixed = _static_layout(self.spec) if sg.fixed_line_of_sight else None  # the fixed obstacles alone
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
            if sg.max_detour is not None:  # grid lengths run up to ~3 % long: pre-select with that slack
                ok &= geo <= sg.max_detour * 1.04 * eu + NAV_RES_M
            if fixed is not None and ok.any():  # on the fixed layout's grid, a few mm generous (exact below)
                idx = np.nonzero(ok)[0]
                ok[idx] = fixed.segments_min_clearance(start, cand[idx]) > -0.05
            if not ok.any():
                continue
            k = rng.choice(np.nonzero(ok)[0])
            goal = cand[k] + rng.uniform(-GRID_RES_M / 2, GRID_RES_M / 2, 2)
            if fixed is not None and not fixed.geometry.segment_clear(start, goal, 0.0, step=0.01)[0]:
                continue  # the segment grazes a fixed obstacle's corner (the grid's slack, the goal's jitter)
            if sg.metric == "euclidean" and sg.max_detour is None and not exact_length:
                return start, goal, math.nan
            length = self.path_length(start, goal, robot_radius_m)
            if not math.isfinite(length) or (sg.metric == "geodesic" and not lo <= length <= hi):
                continue
            if sg.max_detour is not None and length > sg.max_detour * float(np.hypot(*(goal - start))):
                continue
            return start, goal, length
        raise ConfigError(
            f"scene {self.spec.name!r}: found no connected start/goal pair with {sg.metric} distance in "
            f"[{lo}, {hi}] m" + ("" if sg.max_detour is None else f" and a path <= {sg.max_detour} x the "
                                   "straight line") + (" whose straight line crosses no fixed obstacle"
                                                       if sg.fixed_line_of_sight else "") + f" after {max_tries} tries"
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
# The file schema as config dataclasses: a scene file is decoded and checked by the same machinery as the stage
# configs (pipeline.core.config: draccus decoding, then every validate(), children first).
Vec2 = tuple[float, float]
Range = tuple[float, float]  # [min, max]
Rect = tuple[float, float, float, float]  # [x_min, x_max, y_min, y_max]
Color = tuple[float, float, float]  # r, g, b in [0, 1]


def _check_num(name: str, v: float, lo: float, hi: float) -> None:
    if not lo <= v <= hi:
        raise FieldValueError(name, f"a number in [{lo}, {hi}]", v)


def _check_range(name: str, r: Range) -> None:
    if not all(math.isfinite(v) for v in r) or r[0] > r[1]:
        raise FieldValueError(name, "[min, max], finite, with min <= max", list(r))


def _check_rect(name: str, r: Rect | None) -> None:
    if r is not None and (not all(math.isfinite(v) for v in r) or r[0] >= r[1] or r[2] >= r[3]):
        raise FieldValueError(name, "[x_min, x_max, y_min, y_max], finite, with min < max", list(r))


def _check_color(name: str, c: Color | None) -> None:
    if c is not None and any(x < 0 or x > 1 for x in c):
        raise FieldValueError(name, "three numbers in [0, 1]", list(c))


@dataclass
class BoxFile:
    """``box:`` an upright box."""

    center: Vec2  # m, world frame
    size: Vec2  # m, along its own x and y
    yaw_deg: float = 0.0
    height_m: float = 1.0
    color: Color = (0.55, 0.4, 0.25)

    def validate(self) -> None:
        if any(x <= 0 for x in self.size):
            raise FieldValueError("size", "positive numbers", list(self.size))
        _check_num("height_m", self.height_m, 0.01, 20)
        _check_color("color", self.color)


@dataclass
class WallFile:
    """``wall:`` a straight wall segment (``from`` is a Python keyword: the file key is renamed ``from_``)."""

    from_: Vec2  # m, one end
    to: Vec2  # m, the other end
    thickness_m: float = 0.2
    height_m: float | None = None  # default: the scene's wall_height_m
    color: Color | None = None  # default: the scene's wall_color

    def validate(self) -> None:
        if self.from_ == self.to:
            raise ValueError(f"expected 'from' and 'to' to differ, got both {list(self.to)}")
        _check_num("thickness_m", self.thickness_m, 0.01, 5)
        if self.height_m is not None:
            _check_num("height_m", self.height_m, 0.01, 20)
        _check_color("color", self.color)


@dataclass
class CylinderFile:
    """``cylinder:`` an upright cylinder."""

    center: Vec2  # m, world frame
    radius_m: float
    height_m: float = 1.0
    color: Color = (0.6, 0.6, 0.65)

    def validate(self) -> None:
        _check_num("radius_m", self.radius_m, 0.01, 20)
        _check_num("height_m", self.height_m, 0.01, 20)
        _check_color("color", self.color)


@dataclass
class ObstacleFile:
    """One item of ``obstacles``: exactly one of its keys."""

    box: BoxFile | None = None
    wall: WallFile | None = None
    cylinder: CylinderFile | None = None

    def validate(self) -> None:
        kinds = [k for k in ("box", "wall", "cylinder") if getattr(self, k) is not None]
        if len(kinds) != 1:
            raise ValueError(f"expected exactly one of box / wall / cylinder, got {kinds or 'none'}")

    def extent(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """Axis-aligned (min x, min y), (max x, max y) that contain the obstacle (a box's circumscribed circle)."""
        if self.box is not None:
            (cx, cy), r = self.box.center, math.hypot(*self.box.size) / 2
        elif self.wall is not None:
            (ax, ay), (bx, by), t = self.wall.from_, self.wall.to, self.wall.thickness_m / 2
            return (min(ax, bx) - t, min(ay, by) - t), (max(ax, bx) + t, max(ay, by) + t)
        else:
            assert self.cylinder is not None
            (cx, cy), r = self.cylinder.center, self.cylinder.radius_m
        return (cx - r, cy - r), (cx + r, cy + r)

    def build(self, wall_height_m: float, wall_color: Color) -> Obstacle:
        if self.box is not None:
            b = self.box
            return Box(b.center, b.size, math.radians(b.yaw_deg), b.height_m, b.color)
        if self.wall is not None:
            w = self.wall
            a, b = np.array(w.from_), np.array(w.to)
            height = w.height_m if w.height_m is not None else wall_height_m
            color = w.color if w.color is not None else wall_color
            return Box(tuple((a + b) / 2), (float(np.hypot(*(b - a))), w.thickness_m),
                       math.atan2(b[1] - a[1], b[0] - a[0]), height, color)
        c = self.cylinder
        assert c is not None
        return Cylinder(c.center, c.radius_m, c.height_m, c.color)


@dataclass
class RandomObstaclesFile:
    """``random_obstacles:`` see :class:`RandomObstacles`."""

    count: tuple[int, int]
    size_m: Range
    region: Rect
    height_m: Range = (0.5, 1.2)
    clearance_m: float = 0.6

    def validate(self) -> None:
        if self.count[0] < 0 or self.count[0] > self.count[1]:
            raise FieldValueError("count", "two non-negative integers [min, max] with min <= max", list(self.count))
        _check_range("size_m", self.size_m)
        _check_range("height_m", self.height_m)
        _check_rect("region", self.region)
        _check_num("clearance_m", self.clearance_m, 0, 5)


@dataclass
class StartGoalFile:
    """``start_goal:`` see :class:`StartGoalSpec`."""

    distance_m: Range = (5.5, 6.5)
    metric: Literal["euclidean", "geodesic"] = "euclidean"
    clearance_m: float = 0.5
    region: Rect | None = None
    max_detour: float | None = None
    fixed_line_of_sight: bool = False

    def validate(self) -> None:
        _check_range("distance_m", self.distance_m)
        if self.distance_m[0] <= 0:
            raise FieldValueError("distance_m", "positive distances", list(self.distance_m))
        _check_num("clearance_m", self.clearance_m, 0.0, 5.0)
        _check_rect("region", self.region)
        if self.max_detour is not None:
            _check_num("max_detour", self.max_detour, 1.0, 100.0)


@dataclass
class PedestriansFile:
    """``pedestrians:`` optional spawn/goal region and a cap on the count."""

    region: Rect | None = None
    max_count: int = 60
    goal_choice: Literal["first", "farthest"] = "first"  # of the visible candidate goals in range: the first
    #   drawn (open rooms), or the farthest (corridor layouts: people walk the corridors instead of gathering
    #   where they meet, which is visible from every corridor)

    def validate(self) -> None:
        _check_rect("region", self.region)
        _check_num("max_count", self.max_count, 0, 500)


@dataclass
class SceneFile:
    """A scene file as written (the schema in the module docstring)."""

    name: str  # must equal the file stem
    split: Literal["train", "test", "long_horizon"]
    bounds: Rect  # m, the free interior
    description: str = ""
    wall_height_m: float = 2.5
    wall_thickness_m: float = 0.2
    wall_color: Color = (0.82, 0.8, 0.76)
    floor_color: Color = (0.55, 0.55, 0.52)
    free_space: list[Rect] | None = None  # the free interior as a union of rectangles (the rest is solid)
    obstacles: list[ObstacleFile] = field(default_factory=list)
    random_obstacles: RandomObstaclesFile | None = None
    start_goal: StartGoalFile | None = None
    pedestrians: PedestriansFile | None = None

    def validate(self) -> None:
        if not self.name:
            raise FieldValueError("name", "a non-empty string", self.name)
        _check_rect("bounds", self.bounds)
        if self.free_space is not None:
            if not self.free_space:
                raise FieldValueError("free_space", "at least one rectangle", [])
            x0, x1, y0, y1 = self.bounds
            for k, r in enumerate(self.free_space):
                _check_rect(f"free_space[{k}]", r)
                if r[0] < x0 - 1e-9 or r[1] > x1 + 1e-9 or r[2] < y0 - 1e-9 or r[3] > y1 + 1e-9:
                    raise FieldValueError(f"free_space[{k}]", f"a rectangle inside the bounds {list(self.bounds)}",
                                          list(r))
        _check_num("wall_height_m", self.wall_height_m, 0.1, 20)
        _check_num("wall_thickness_m", self.wall_thickness_m, 0.01, 5)
        _check_color("wall_color", self.wall_color)
        _check_color("floor_color", self.floor_color)
        self._check_size()
        for k, o in enumerate(self.obstacles):
            lo, hi = o.extent()
            x0, x1, y0, y1 = self.bounds
            if hi[0] < x0 or lo[0] > x1 or hi[1] < y0 or lo[1] > y1:
                raise FieldValueError(f"obstacles[{k}]", f"an obstacle that overlaps the bounds {list(self.bounds)}",
                                      f"one spanning x {lo[0]:g}..{hi[0]:g}, y {lo[1]:g}..{hi[1]:g}")

    def _check_size(self) -> None:
        """The limits of the module (area, obstacle count, grid cells × obstacles), before anything is built."""
        x0, x1, y0, y1 = self.bounds
        area = (x1 - x0) * (y1 - y0)
        if area > MAX_AREA_M2:
            raise FieldValueError("bounds", f"an area of at most {MAX_AREA_M2:g} m² (the limit)",
                                  f"{list(self.bounds)} ({area:g} m²)")
        n_free = len(self.free_space or [])
        n_obst = (len(self.obstacles) + 4 + (self.random_obstacles.count[1] if self.random_obstacles else 0)
                  + (2 * n_free + 1) ** 2 * (n_free > 0))
        if n_obst > MAX_OBSTACLES:
            raise FieldValueError("obstacles", f"at most {MAX_OBSTACLES} obstacles in all (the limit; listed, "
                                  "random clutter's maximum, outer walls and boxes outside free_space)", n_obst)
        m = self.wall_thickness_m
        cells = math.ceil((x1 - x0 + 2 * m) / GRID_RES_M) * math.ceil((y1 - y0 + 2 * m) / GRID_RES_M)
        if cells * n_obst > MAX_CELL_OBSTACLE_PAIRS:
            raise FieldValueError("obstacles", f"at most {MAX_CELL_OBSTACLE_PAIRS:.0e} grid cells × obstacles "
                                  f"(the limit; {cells} cells of {GRID_RES_M} m)", f"{n_obst} obstacles "
                                  f"({cells * n_obst:.2e} pairs)")

    def spec(self, path: str) -> SceneSpec:
        """The runtime :class:`SceneSpec` of this (validated) file."""
        ro, sg, peds = self.random_obstacles, self.start_goal or StartGoalFile(), self.pedestrians or PedestriansFile()
        return SceneSpec(
            name=self.name, split=self.split, bounds=self.bounds, description=self.description,
            obstacles=tuple([*solid_outside(self.bounds, self.free_space, self.wall_height_m, self.wall_color),
                             *(o.build(self.wall_height_m, self.wall_color) for o in self.obstacles)]),
            wall_height_m=self.wall_height_m, wall_thickness_m=self.wall_thickness_m, wall_color=self.wall_color,
            floor_color=self.floor_color,
            random_obstacles=None if ro is None else RandomObstacles(ro.count, ro.size_m, ro.height_m, ro.region,
                                                                     ro.clearance_m),
            start_goal=StartGoalSpec(sg.distance_m, sg.metric, sg.clearance_m, sg.region, sg.max_detour,
                                     sg.fixed_line_of_sight),
            ped_region=peds.region, ped_max_count=peds.max_count, ped_goal_choice=peds.goal_choice, path=path,
        )


def solid_outside(bounds: Rect, free: list[Rect] | None, height_m: float, color: Color) -> list[Box]:
    """Boxes filling the part of ``bounds`` outside the union of the ``free`` rectangles (none without them):
    the rectangles' edges cut the bounds into cells; the solid cells of each column merge into one box per run."""
    if not free:
        return []
    xs = sorted({bounds[0], bounds[1], *(v for r in free for v in r[:2] if bounds[0] < v < bounds[1])})
    ys = sorted({bounds[2], bounds[3], *(v for r in free for v in r[2:] if bounds[2] < v < bounds[3])})
    boxes = []
    for xa, xb in zip(xs[:-1], xs[1:], strict=True):
        cx = (xa + xb) / 2
        run: list[float] | None = None
        for ya, yb in [*zip(ys[:-1], ys[1:], strict=True), (None, None)]:
            solid = ya is not None and not any(r[0] <= cx <= r[1] and r[2] <= (ya + yb) / 2 <= r[3] for r in free)
            if solid and run is None:
                run = [ya, yb]
            elif solid:
                run[1] = yb
            elif run is not None:
                boxes.append(Box(((xa + xb) / 2, (run[0] + run[1]) / 2), (xb - xa, run[1] - run[0]), 0.0,
                                 height_m, color))
                run = None
    return boxes


def parse_scene(data: Any, src: str, stem: str | None = None) -> SceneSpec:
    """Validate a scene mapping (as loaded from YAML) and build its :class:`SceneSpec`.

    Raises:
        ConfigError: naming the file, the field, what was expected and what was found.
    """
    source = f"scene file {src}"
    if isinstance(data, dict) and isinstance(data.get("obstacles"), list):  # `from` cannot be a dataclass field
        data = {**data, "obstacles": [
            {**item, "wall": {("from_" if k == "from" else k): v for k, v in item["wall"].items()}}
            if isinstance(item, dict) and isinstance(item.get("wall"), dict) else item
            for item in data["obstacles"]
        ]}
    return decode_file(SceneFile, data, source, stem).spec(src)


def decode_file(cls: type, data: Any, source: str, stem: str | None) -> Any:
    """A data file (scene, scenario) decoded into ``cls`` and validated; its ``name`` must equal the file ``stem``
    when one is given. Errors name ``source``, the key, the expected and the actual value."""
    obj = from_dict(cls, data, source)
    try:
        validate_tree(obj)
    except ConfigError as e:
        raise ConfigError(f"{source}: {e}") from None
    if stem is not None and obj.name != stem:
        raise ConfigError(f"{source}: config key 'name': expected the file stem {stem!r}, got {obj.name!r}")
    return obj


def load_scene(name_or_path: str) -> SceneSpec:
    """Load and validate a scene by shipped name (``office_lobby``) or by path to a YAML file.

    Raises:
        ConfigError: unknown scene name (listing the known ones) or an invalid file.
        InputMissingError: a path that does not exist.
    """
    p = named_file(name_or_path, SCENES_DIR, "scene")
    return _load_scene_file(str(p.resolve()), p.stat().st_mtime_ns)


def named_file(name_or_path: str, folder: Path, what: str) -> Path:
    """The YAML file a name or path stands for: ``<folder>/<name>.yaml`` for a shipped name, else the path.

    Raises:
        ConfigError: an unknown name (listing the shipped ones).
        InputMissingError: a path that does not exist.
    """
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or "/" in name_or_path:
        if not p.exists():
            raise InputMissingError(f"{what} file not found: {p}")
        return p
    p = folder / f"{name_or_path}.yaml"
    if not p.exists():
        known = ", ".join(sorted(q.stem for q in folder.glob("*.yaml")))
        raise ConfigError(f"unknown {what} {name_or_path!r}; known {what}s: {known} (or pass a path to a {what} "
                          "YAML file)")
    return p


@functools.lru_cache(maxsize=64)
def _load_scene_file(path: str, mtime_ns: int) -> SceneSpec:
    """Parse one scene file (cached per path and modification time, so edits are picked up)."""
    p = Path(path)
    return parse_scene(read_yaml(p, "scene file"), str(p), stem=p.stem)
