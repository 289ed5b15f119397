"""Planar geometry of the static world: boxes and cylinders, vectorised distance and ray queries.

Frames: everything here is in the scene's world frame, metres, x/y on the floor plane, yaw in radians
counter-clockwise from +x. Obstacles are extruded prisms (the floor plan is what matters for navigation; the
height only matters for rendering).

The fast paths are numpy-vectorised over points x obstacles; :func:`signed_distance_reference` is the plain loop
they are tested against.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Box:
    """An oriented box obstacle (a wall, a shelf, a table).

    Attributes:
        center: (x, y) of the footprint centre, world frame, m.
        size: (sx, sy) full side lengths along the box's own x and y axes, m.
        yaw: rotation of the box about +z, rad.
        height_m: extrusion height, m (rendering only).
        color: RGB in [0, 1] (rendering only).
    """

    center: tuple[float, float]
    size: tuple[float, float]
    yaw: float = 0.0
    height_m: float = 2.5
    color: tuple[float, float, float] = (0.75, 0.75, 0.72)


@dataclass(frozen=True)
class Cylinder:
    """A round obstacle (a pillar, a bin). ``center`` (x, y) in m, ``radius_m`` in m."""

    center: tuple[float, float]
    radius_m: float
    height_m: float = 2.5
    color: tuple[float, float, float] = (0.6, 0.6, 0.65)


Obstacle = Box | Cylinder


_PAIRS_PER_CHUNK = 1 << 21  # point-obstacle pairs per pass of signed_distance (~16 MB per float64 temporary)


class StaticGeometry:
    """Packed arrays of a scene's obstacles for vectorised queries.

    Args:
        obstacles: boxes and cylinders, world frame.
    """

    def __init__(self, obstacles: list[Obstacle]):
        boxes = [o for o in obstacles if isinstance(o, Box)]
        cyls = [o for o in obstacles if isinstance(o, Cylinder)]
        self.box_center = np.array([b.center for b in boxes], dtype=np.float64).reshape(-1, 2)
        self.box_half = np.array([b.size for b in boxes], dtype=np.float64).reshape(-1, 2) / 2.0
        yaw = np.array([b.yaw for b in boxes], dtype=np.float64)
        self.box_cos = np.cos(yaw)
        self.box_sin = np.sin(yaw)
        self.cyl_center = np.array([c.center for c in cyls], dtype=np.float64).reshape(-1, 2)
        self.cyl_radius = np.array([c.radius_m for c in cyls], dtype=np.float64)

    @property
    def n_obstacles(self) -> int:
        return len(self.box_center) + len(self.cyl_center)

    def signed_distance(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance from points to the nearest obstacle surface, and that surface point.

        Args:
            points: ``... x 2`` world-frame positions, m.

        Returns:
            ``(dist, closest)``: ``...`` signed distances (negative inside an obstacle), m, and ``... x 2`` the
            closest surface point of the nearest obstacle. With no obstacles: ``+inf`` and the points themselves.
        """
        pts = np.asarray(points, dtype=np.float64)
        shape = pts.shape[:-1]
        p = pts.reshape(-1, 2)
        chunk = max(1, _PAIRS_PER_CHUNK // max(self.n_obstacles, 1))
        if len(p) > chunk:  # bounded memory: each temporary is (points in the chunk) x obstacles
            parts = [self._signed_distance(p[i:i + chunk]) for i in range(0, len(p), chunk)]
            best = np.concatenate([d for d, _ in parts])
            closest = np.concatenate([c for _, c in parts])
        else:
            best, closest = self._signed_distance(p)
        return best.reshape(shape), closest.reshape(*shape, 2)

    def _signed_distance(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`signed_distance` of ``P x 2`` points (one chunk)."""
        best = np.full(len(p), np.inf)
        closest = p.copy()
        if len(self.box_center):
            d = p[:, None, :] - self.box_center[None]  # P x B x 2
            c, s = self.box_cos[None], self.box_sin[None]
            lx = c * d[..., 0] + s * d[..., 1]  # box frame
            ly = -s * d[..., 0] + c * d[..., 1]
            hx, hy = self.box_half[None, :, 0], self.box_half[None, :, 1]
            qx, qy = np.abs(lx) - hx, np.abs(ly) - hy
            outside = np.hypot(np.maximum(qx, 0.0), np.maximum(qy, 0.0))
            inside = np.minimum(np.maximum(qx, qy), 0.0)
            sd = outside + inside  # P x B
            # closest surface point in the box frame
            cx = np.clip(lx, -hx, hx)
            cy = np.clip(ly, -hy, hy)
            is_in = (qx < 0) & (qy < 0)
            push_x = qx > qy  # inside: leave through the nearest face
            cx = np.where(is_in & push_x, np.sign(lx + 1e-12) * hx, cx)
            cy = np.where(is_in & ~push_x, np.sign(ly + 1e-12) * hy, cy)
            wx = self.box_center[None, :, 0] + c * cx - s * cy
            wy = self.box_center[None, :, 1] + s * cx + c * cy
            j = np.argmin(sd, axis=1)
            rows = np.arange(len(p))
            best = sd[rows, j]
            closest = np.stack([wx[rows, j], wy[rows, j]], axis=-1)
        if len(self.cyl_center):
            d = p[:, None, :] - self.cyl_center[None]
            r = np.hypot(d[..., 0], d[..., 1])
            sd = r - self.cyl_radius[None]
            j = np.argmin(sd, axis=1)
            rows = np.arange(len(p))
            sdj = sd[rows, j]
            better = sdj < best
            rj = np.maximum(r[rows, j], 1e-9)[:, None]
            cp = self.cyl_center[j] + d[rows, j] / rj * self.cyl_radius[j][:, None]
            best = np.where(better, sdj, best)
            closest = np.where(better[:, None], cp, closest)
        return best, closest

    def raycast(self, origins: np.ndarray, angles: np.ndarray, max_range: float) -> np.ndarray:
        """Distance along rays to the first obstacle surface (a 2D range scan of the static map).

        Args:
            origins: ``R x 2`` ray origins, world frame, m (or ``2`` for one origin shared by all rays).
            angles: ``R`` world-frame ray directions, rad.
            max_range: value returned when nothing is hit, m.

        Returns:
            ``R`` hit distances in ``[0, max_range]``, m. A ray starting inside an obstacle returns 0.
        """
        ang = np.asarray(angles, dtype=np.float64)
        o = np.broadcast_to(np.asarray(origins, dtype=np.float64), (len(ang), 2))
        dx, dy = np.cos(ang), np.sin(ang)
        best = np.full(len(ang), float(max_range))
        if len(self.box_center):
            c, s = self.box_cos[None], self.box_sin[None]
            rel = o[:, None, :] - self.box_center[None]
            ox = c * rel[..., 0] + s * rel[..., 1]
            oy = -s * rel[..., 0] + c * rel[..., 1]
            vx = c * dx[:, None] + s * dy[:, None]
            vy = -s * dx[:, None] + c * dy[:, None]
            hx, hy = self.box_half[None, :, 0], self.box_half[None, :, 1]
            with np.errstate(divide="ignore", invalid="ignore"):
                inv_x = 1.0 / vx
                inv_y = 1.0 / vy
                t1x, t2x = (-hx - ox) * inv_x, (hx - ox) * inv_x
                t1y, t2y = (-hy - oy) * inv_y, (hy - oy) * inv_y
            # rays parallel to a slab: inside the slab -> (-inf, inf), outside -> empty
            par_x = vx == 0
            par_y = vy == 0
            in_x = np.abs(ox) <= hx
            in_y = np.abs(oy) <= hy
            tminx = np.where(par_x, np.where(in_x, -np.inf, np.inf), np.minimum(t1x, t2x))
            tmaxx = np.where(par_x, np.where(in_x, np.inf, -np.inf), np.maximum(t1x, t2x))
            tminy = np.where(par_y, np.where(in_y, -np.inf, np.inf), np.minimum(t1y, t2y))
            tmaxy = np.where(par_y, np.where(in_y, np.inf, -np.inf), np.maximum(t1y, t2y))
            tnear = np.maximum(tminx, tminy)
            tfar = np.minimum(tmaxx, tmaxy)
            hit = (tnear <= tfar) & (tfar >= 0)
            t = np.where(hit, np.maximum(tnear, 0.0), np.inf)
            best = np.minimum(best, t.min(axis=1))
        if len(self.cyl_center):
            rel = o[:, None, :] - self.cyl_center[None]
            b = rel[..., 0] * dx[:, None] + rel[..., 1] * dy[:, None]
            cc = (rel**2).sum(-1) - self.cyl_radius[None] ** 2
            disc = b * b - cc
            sq = np.sqrt(np.maximum(disc, 0.0))
            t0 = -b - sq
            t1 = -b + sq
            t = np.where(cc <= 0, 0.0, np.where((disc >= 0) & (t0 >= 0), t0, np.inf))
            t = np.where((disc >= 0) & (t1 >= 0), t, np.inf)
            best = np.minimum(best, t.min(axis=1))
        return np.minimum(best, max_range)

    def segment_clear(self, a: np.ndarray, b: np.ndarray, margin: float, step: float = 0.1) -> np.ndarray:
        """Whether straight segments keep at least ``margin`` from every obstacle.

        Args:
            a, b: ``K x 2`` segment end points, m.
            margin: required clearance, m.
            step: sampling step along the segments, m.

        Returns:
            ``K`` booleans.
        """
        a = np.asarray(a, dtype=np.float64).reshape(-1, 2)
        b = np.asarray(b, dtype=np.float64).reshape(-1, 2)
        n = max(2, int(math.ceil(np.max(np.hypot(*(b - a).T), initial=0.0) / step)) + 1)
        t = np.linspace(0.0, 1.0, n)[None, :, None]
        pts = a[:, None, :] * (1 - t) + b[:, None, :] * t  # K x n x 2
        d, _ = self.signed_distance(pts)
        return d.min(axis=1) >= margin


def signed_distance_reference(obstacles: list[Obstacle], point: tuple[float, float]) -> float:
    """Slow, obvious signed distance from one point to the nearest obstacle (reference for tests)."""
    best = math.inf
    px, py = point
    for o in obstacles:
        if isinstance(o, Cylinder):
            d = math.hypot(px - o.center[0], py - o.center[1]) - o.radius_m
        else:
            c, s = math.cos(o.yaw), math.sin(o.yaw)
            dx, dy = px - o.center[0], py - o.center[1]
            lx, ly = c * dx + s * dy, -s * dx + c * dy
            qx, qy = abs(lx) - o.size[0] / 2, abs(ly) - o.size[1] / 2
            d = math.hypot(max(qx, 0), max(qy, 0)) + min(max(qx, qy), 0)
        best = min(best, d)
    return best


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles to ``[-pi, pi)``."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def world_to_robot(points: np.ndarray, pose, *, vectors: bool = False) -> np.ndarray:
    """World-frame points (``... x d``, d >= 2) in the frame of a robot at ``pose = (x, y, yaw)``: x forward, y left.

    Only the first two columns change (a z or any other trailing column is kept). ``vectors=True`` rotates without
    translating (velocities, directions).
    """
    p = np.asarray(points, dtype=np.float64)
    x, y, yaw = (float(v) for v in pose)
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = (p[..., 0], p[..., 1]) if vectors else (p[..., 0] - x, p[..., 1] - y)
    out = p.copy()
    out[..., 0], out[..., 1] = c * dx + s * dy, -s * dx + c * dy
    return out


def world_to_robot_each(points: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """World points ``N x 2`` into the frames of poses ``N x 3`` (x forward, y left): point i in the frame of pose i
    (:func:`world_to_robot` takes one pose for every point)."""
    d = points - poses[:, :2]
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], -1)


def robot_to_world(points: np.ndarray, pose, *, vectors: bool = False) -> np.ndarray:
    """The inverse of :func:`world_to_robot`."""
    p = np.asarray(points, dtype=np.float64)
    x, y, yaw = (float(v) for v in pose)
    c, s = math.cos(yaw), math.sin(yaw)
    out = p.copy()
    out[..., 0], out[..., 1] = c * p[..., 0] - s * p[..., 1], s * p[..., 0] + c * p[..., 1]
    if not vectors:
        out[..., 0] += x
        out[..., 1] += y
    return out
