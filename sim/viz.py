"""Figures and videos of episodes: a matplotlib top-down plot, a fast OpenCV top-down raster, H.264 writing.

Frames: world frame of the scene, metres, yaw in radians counter-clockwise from +x. Raster images are
``H x W x 3`` uint8 **RGB** with world +y pointing up: pixel column ``floor((x - xmin) * px_per_m)``, row
``floor((ymax - y) * px_per_m)`` (see :meth:`TopDownRenderer.world_to_pixel`).

matplotlib is used through :class:`matplotlib.figure.Figure` and the Agg canvas directly, so drawing neither needs a
display nor changes pyplot's global backend; it is imported by :func:`plot_episode_topdown` only (≈ 1 s that every
process importing the simulator's episode tools would otherwise pay).
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Iterable, Sequence
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.artifacts import FILE_MODE
from sim.geometry import Box, Cylinder
from sim.metrics import episode_metrics
from sim.trace import EpisodeTrace

Bounds = tuple[float, float, float, float]
"""``(xmin, xmax, ymin, ymax)`` of a map view, m."""

DEPTH_MAX_M = 10.0
"""Depth panels are colourised on a fixed 0 to this range, m."""


def box_corners(box: Box) -> np.ndarray:
    """Footprint corners of a box, counter-clockwise.

    Args:
        box: the obstacle.

    Returns:
        ``4 x 2`` world-frame corners, m.
    """
    hx, hy = box.size[0] / 2.0, box.size[1] / 2.0
    local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    c, s = math.cos(box.yaw), math.sin(box.yaw)
    rot = np.array([[c, -s], [s, c]])
    return local @ rot.T + np.asarray(box.center, dtype=np.float64)


def _auto_bounds(obstacles: Sequence[Box | Cylinder], trace: EpisodeTrace, margin_m: float = 1.0) -> Bounds:
    """Smallest axis-aligned view holding the obstacles, the robot, the goal and the pedestrians, plus a margin."""
    pts = [trace.robot_pose[:, :2], trace.goal_xy[None], trace.start_xy[None], trace.ped_xy.reshape(-1, 2)]
    for o in obstacles:
        if isinstance(o, Box):
            pts.append(box_corners(o))
        else:
            c = np.asarray(o.center, dtype=np.float64)
            pts.append(np.stack([c - o.radius_m, c + o.radius_m]))
    allp = np.concatenate(pts, axis=0)
    lo, hi = allp.min(axis=0) - margin_m, allp.max(axis=0) + margin_m
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def _atomic_target(path: Path, suffix: str) -> Path:
    """A fresh temp file name next to ``path`` (same filesystem, so that ``os.replace`` is atomic)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    os.chmod(tmp, FILE_MODE)  # mkstemp makes 0600; writers that truncate the file keep this mode
    return Path(tmp)


def save_figure(fig, path: str | os.PathLike[str], dpi: int = 120) -> Path:
    """Saves a matplotlib figure as PNG atomically (temp file beside it, then rename; mode 0644)."""
    path = Path(path)
    tmp = _atomic_target(path, ".png")
    try:
        fig.savefig(tmp, format="png", dpi=dpi)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def plot_episode_topdown(
    obstacles: Sequence[Box | Cylinder],
    trace: EpisodeTrace,
    path: str | os.PathLike[str],
    *,
    bounds: Bounds | None = None,
    camera_yaws_deg: Sequence[float] = (35.0, -35.0),
    camera_hfov_deg: float = 69.0,
    frustum_range_m: float = 3.0,
    snapshot_steps: Sequence[int] | None = None,
    title: str = "",
    dpi: int = 120,
) -> Path:
    """Top-down figure of one episode, saved as PNG.

    Draws the obstacles (black), the robot trajectory coloured by time (viridis, with a "time [s]" colourbar), the
    start (circle) and goal (star and goal-radius circle), pedestrian trails (thin grey), and at each snapshot step
    the pedestrians (discs of their radius, an arrow for body heading, a short dark line for head direction) and
    the robot (disc of its radius with its camera frusta as wedges). Snapshot outlines use the trajectory colour of
    their time. The title holds ``title``, the episode identity, outcome and a metrics summary.

    Args:
        obstacles: static obstacles, world frame.
        trace: the episode.
        path: output ``.png`` file (written atomically: temp file in the same folder, then renamed).
        bounds: ``(xmin, xmax, ymin, ymax)`` view, m; ``None`` fits everything with a 1 m margin.
        camera_yaws_deg: camera yaw offsets relative to the robot heading, deg (counter-clockwise).
        camera_hfov_deg: horizontal field of view of each camera, deg.
        frustum_range_m: drawn length of the frusta, m.
        snapshot_steps: state indices ``0..T`` to draw pedestrians and robot at; default start, middle, end.
        title: first title line.
        dpi: output resolution.

    Returns:
        The written path.

    Raises:
        ValueError: a snapshot step is outside ``0..T`` or the trace is invalid.
    """
    from matplotlib import colormaps  # lazy: matplotlib only when a figure is drawn
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.cm import ScalarMappable
    from matplotlib.collections import LineCollection
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle, Polygon, Wedge

    trace.validate()
    path = Path(path)
    t_steps = trace.n_steps
    dt = trace.dt_s
    steps = sorted(set(snapshot_steps if snapshot_steps is not None else (0, t_steps // 2, t_steps)))
    bad = [s for s in steps if not 0 <= s <= t_steps]
    if bad:
        raise ValueError(f"snapshot_steps {bad} outside 0..{t_steps}")
    xmin, xmax, ymin, ymax = bounds if bounds is not None else _auto_bounds(obstacles, trace)

    aspect = (ymax - ymin) / max(xmax - xmin, 1e-9)
    fig = Figure(figsize=(8.0, float(np.clip(6.2 * aspect + 1.6, 4.0, 12.0))), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.set_facecolor("white")

    for o in obstacles:
        if isinstance(o, Box):
            ax.add_patch(Polygon(box_corners(o), closed=True, facecolor="black", edgecolor="black", zorder=1))
        else:
            ax.add_patch(Circle(o.center, o.radius_m, facecolor="black", edgecolor="black", zorder=1))

    # pedestrian trails
    if trace.n_peds:
        trails = np.transpose(trace.ped_xy, (1, 0, 2))  # N x (T+1) x 2
        ax.add_collection(LineCollection(list(trails), colors="0.6", linewidths=0.7, alpha=0.8, zorder=2))

    # robot trajectory coloured by time
    cmap = colormaps["viridis"]
    t_end = max(t_steps * dt, dt)
    norm = Normalize(vmin=0.0, vmax=t_end)
    xy = trace.robot_pose[:, :2]
    if t_steps:
        segs = np.stack([xy[:-1], xy[1:]], axis=1)  # T x 2 x 2
        lc = LineCollection(list(segs), cmap=cmap, norm=norm, linewidths=2.5, zorder=4)
        lc.set_array((np.arange(t_steps) + 0.5) * dt)
        ax.add_collection(lc)
    fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=ax, label="time [s]", shrink=0.85)

    ax.plot(
        *trace.start_xy,
        marker="o",
        markersize=9,
        markerfacecolor="white",
        markeredgecolor="tab:blue",
        markeredgewidth=2,
        linestyle="none",
        zorder=6,
        label="start",
    )
    ax.add_patch(
        Circle(
            tuple(trace.goal_xy),
            trace.goal_radius_m,
            facecolor="gold",
            alpha=0.25,
            edgecolor="goldenrod",
            zorder=3,
        )
    )
    ax.plot(
        *trace.goal_xy,
        marker="*",
        markersize=16,
        color="gold",
        markeredgecolor="darkgoldenrod",
        linestyle="none",
        zorder=6,
        label="goal",
    )

    arrow_len = 0.5
    for s in steps:
        colour = cmap(norm(s * dt))
        alpha = 0.35 + 0.65 * (s / t_steps if t_steps else 1.0)
        for j in range(trace.n_peds):
            p = trace.ped_xy[s, j]
            r = float(trace.ped_radius[j])
            ax.add_patch(
                Circle(
                    tuple(p),
                    r,
                    facecolor="tab:orange",
                    edgecolor=colour,
                    linewidth=1.5,
                    alpha=alpha,
                    zorder=5,
                )
            )
            yaw = float(trace.ped_yaw[s, j])
            ax.arrow(
                p[0],
                p[1],
                arrow_len * math.cos(yaw),
                arrow_len * math.sin(yaw),
                width=0.02,
                head_width=0.12,
                head_length=0.12,
                length_includes_head=True,
                color="saddlebrown",
                alpha=alpha,
                zorder=6,
            )
            head = float(trace.ped_head_yaw[s, j])
            ax.plot(
                [p[0], p[0] + 0.8 * r * math.cos(head) + 0.15 * math.cos(head)],
                [p[1], p[1] + 0.8 * r * math.sin(head) + 0.15 * math.sin(head)],
                color="darkred",
                linewidth=1.5,
                alpha=alpha,
                zorder=7,
            )
        rx, ry, ryaw = trace.robot_pose[s]
        for cam in camera_yaws_deg:
            centre_deg = math.degrees(ryaw) + cam
            ax.add_patch(
                Wedge(
                    (rx, ry),
                    frustum_range_m,
                    centre_deg - camera_hfov_deg / 2.0,
                    centre_deg + camera_hfov_deg / 2.0,
                    facecolor="tab:cyan",
                    alpha=0.12 * alpha + 0.05,
                    edgecolor="tab:cyan",
                    linewidth=0.6,
                    zorder=2,
                )
            )
        ax.add_patch(
            Circle(
                (rx, ry),
                trace.robot_radius_m,
                facecolor="tab:blue",
                edgecolor=colour,
                linewidth=2.0,
                alpha=alpha,
                zorder=5,
            )
        )
        ax.plot(
            [rx, rx + 1.3 * trace.robot_radius_m * math.cos(ryaw)],
            [ry, ry + 1.3 * trace.robot_radius_m * math.sin(ryaw)],
            color="white",
            linewidth=1.5,
            zorder=6,
        )

    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, linewidth=0.3, alpha=0.5)
    ax.legend(loc="upper right", fontsize=8)

    m = episode_metrics(trace)
    ident = " | ".join(
        x for x in (trace.method, trace.scene, f"density {trace.density:g}", f"seed {trace.seed}") if x
    )
    summary = (
        f"{trace.outcome}: NT {m['nav_time_s']:.2f} s, PL {m['path_length_m']:.2f} m, TPZ {m['tpz_s']:.2f} s, "
        f"min ped clr {m['min_ped_clearance_m']:.2f} m, SPL {m['spl']:.2f}"
    )
    ax.set_title("\n".join(x for x in (title, ident, summary) if x), fontsize=9)
    return save_figure(fig, path, dpi)


# ---------------------------------------------------------------------------------------------------------------
# OpenCV raster
# ---------------------------------------------------------------------------------------------------------------

_SHIFT = 4  # OpenCV fixed-point sub-pixel bits
_SCALE = float(1 << _SHIFT)

_FLOOR = (255, 255, 255)
_GRID = (232, 232, 232)
_OBSTACLE = (0, 0, 0)
_PED = (245, 140, 40)
_PED_HEADING = (120, 60, 10)
_PED_HEAD = (170, 0, 0)
_ROBOT = (30, 100, 220)
_ROBOT_HEADING = (255, 255, 255)
_FRUSTUM = (80, 200, 230)
_TRAIL = (60, 160, 90)
_GOAL = (230, 180, 0)


class TopDownRenderer:
    """Fast top-down raster of a scene for videos (OpenCV, static background rendered once).

    Args:
        obstacles: static obstacles, world frame.
        bounds: ``(xmin, xmax, ymin, ymax)`` of the view, m.
        px_per_m: resolution, pixels per metre.

    Attributes:
        height, width: image size, px (``ceil`` of the bounds extent times ``px_per_m``).
        background: ``H x W x 3`` uint8 RGB static layer (floor, 1 m grid, obstacles in black).
    """

    def __init__(self, obstacles: Sequence[Box | Cylinder], bounds: Bounds, px_per_m: float = 40.0):
        xmin, xmax, ymin, ymax = (float(b) for b in bounds)
        if not (xmax > xmin and ymax > ymin and px_per_m > 0):
            raise ValueError(f"need xmin < xmax, ymin < ymax, px_per_m > 0; got {bounds}, {px_per_m}")
        self.bounds: Bounds = (xmin, xmax, ymin, ymax)
        self.px_per_m = float(px_per_m)
        self.width = int(math.ceil((xmax - xmin) * self.px_per_m - 1e-9))
        self.height = int(math.ceil((ymax - ymin) * self.px_per_m - 1e-9))
        bg = np.full((self.height, self.width, 3), _FLOOR, dtype=np.uint8)
        for gx in np.arange(math.ceil(xmin), math.floor(xmax) + 1):
            u = int((gx - xmin) * self.px_per_m)
            cv2.line(bg, (u, 0), (u, self.height - 1), _GRID, 1)
        for gy in np.arange(math.ceil(ymin), math.floor(ymax) + 1):
            v = int((ymax - gy) * self.px_per_m)
            cv2.line(bg, (0, v), (self.width - 1, v), _GRID, 1)
        for o in obstacles:
            if isinstance(o, Box):
                cv2.fillPoly(bg, [self._fixed(box_corners(o))], _OBSTACLE, cv2.LINE_AA, _SHIFT)
            else:
                c = self._fixed(np.asarray(o.center, dtype=np.float64))
                cv2.circle(
                    bg,
                    (int(c[0]), int(c[1])),
                    int(round(o.radius_m * self.px_per_m * _SCALE)),
                    _OBSTACLE,
                    -1,
                    cv2.LINE_AA,
                    _SHIFT,
                )
        bg.flags.writeable = False
        self.background = bg

    def world_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """Continuous pixel coordinates of world points.

        Args:
            xy: ``... x 2`` world positions, m.

        Returns:
            ``... x 2`` ``(u, v)`` = (column, row) in pixels, continuous: the point lies in pixel
            ``(floor(v), floor(u))`` (row, column) of the image.
        """
        p = np.asarray(xy, dtype=np.float64)
        xmin, _, _, ymax = self.bounds
        return np.stack([(p[..., 0] - xmin) * self.px_per_m, (ymax - p[..., 1]) * self.px_per_m], axis=-1)

    def _fixed(self, xy: np.ndarray) -> np.ndarray:
        """World points to OpenCV fixed-point coordinates (integer coordinate = pixel centre), int32."""
        uv = self.world_to_pixel(xy) - 0.5
        return np.round(uv * _SCALE).astype(np.int32)

    def draw(
        self,
        robot_pose: np.ndarray,
        ped_xy: np.ndarray,
        ped_yaw: np.ndarray,
        ped_head_yaw: np.ndarray,
        ped_radius: np.ndarray,
        goal_xy: np.ndarray,
        trail_xy: np.ndarray | None = None,
        robot_radius: float = 0.3,
        camera_yaws_deg: Sequence[float] = (35.0, -35.0),
        camera_hfov_deg: float = 69.0,
        frustum_range_m: float = 3.0,
        goal_radius: float = 0.3,
    ) -> np.ndarray:
        """Render one frame.

        Args:
            robot_pose: ``3`` robot ``[x m, y m, yaw rad]``.
            ped_xy: ``N x 2`` pedestrian centres, m.
            ped_yaw: ``N`` body yaw, rad.
            ped_head_yaw: ``N`` head yaw (world frame), rad.
            ped_radius: ``N`` body radii, m.
            goal_xy: ``2`` goal position, m.
            trail_xy: ``K x 2`` robot positions so far (drawn as a polyline), m; optional.
            robot_radius: robot footprint radius, m.
            camera_yaws_deg: camera yaw offsets relative to the robot heading, deg.
            camera_hfov_deg: horizontal field of view of each camera, deg.
            frustum_range_m: drawn length of the frusta, m.
            goal_radius: radius of the goal circle, m.

        Returns:
            ``H x W x 3`` uint8 RGB image (a new array).
        """
        img = self.background.copy()
        ppm, sc = self.px_per_m, _SCALE
        rx, ry, ryaw = (float(v) for v in np.asarray(robot_pose, dtype=np.float64)[:3])

        # goal
        g = self._fixed(np.asarray(goal_xy, dtype=np.float64))
        cv2.circle(
            img, (int(g[0]), int(g[1])), max(1, int(goal_radius * ppm * sc)), _GOAL, 2, cv2.LINE_AA, _SHIFT
        )
        cv2.drawMarker(
            img,
            (int(round(g[0] / sc)), int(round(g[1] / sc))),
            _GOAL,
            cv2.MARKER_STAR,
            max(6, int(0.4 * ppm)),
            2,
        )

        # camera frusta, alpha-blended inside their bounding box only
        if camera_yaws_deg and frustum_range_m > 0:
            n_arc = 8
            polys = []
            for cam in camera_yaws_deg:
                a = ryaw + math.radians(cam) + np.linspace(-0.5, 0.5, n_arc) * math.radians(camera_hfov_deg)
                pts = np.concatenate(
                    [
                        [[rx, ry]],
                        np.stack(
                            [rx + frustum_range_m * np.cos(a), ry + frustum_range_m * np.sin(a)], axis=-1
                        ),
                    ]
                )
                polys.append(self.world_to_pixel(pts))
            allp = np.concatenate(polys)
            u0, v0 = (max(0, int(math.floor(c))) for c in allp.min(axis=0))
            u1, v1 = (int(math.ceil(c)) + 1 for c in allp.max(axis=0))
            u1, v1 = min(u1, self.width), min(v1, self.height)
            if u1 > u0 and v1 > v0:
                roi = img[v0:v1, u0:u1]
                overlay = roi.copy()
                fixed = [np.round((p - 0.5 - [u0, v0]) * sc).astype(np.int32) for p in polys]
                for poly in fixed:  # one call each: a multi-contour fill would cut out overlaps (even-odd)
                    cv2.fillPoly(overlay, [poly], _FRUSTUM, cv2.LINE_8, _SHIFT)
                cv2.addWeighted(overlay, 0.35, roi, 0.65, 0.0, dst=roi)

        # robot trail (LINE_8: anti-aliased 2 px polylines cost ~5x more)
        if trail_xy is not None and len(trail_xy) > 1:
            trail = self._fixed(np.asarray(trail_xy, dtype=np.float64)[:, :2])
            cv2.polylines(img, [trail], False, _TRAIL, 2, cv2.LINE_8, _SHIFT)

        # pedestrians
        pxy = np.asarray(ped_xy, dtype=np.float64).reshape(-1, 2)
        if len(pxy):
            yaw = np.asarray(ped_yaw, dtype=np.float64).reshape(-1)
            head = np.asarray(ped_head_yaw, dtype=np.float64).reshape(-1)
            rad = np.asarray(ped_radius, dtype=np.float64).reshape(-1)
            centre = self._fixed(pxy)
            r_fx = np.maximum(np.round(rad * ppm * sc), sc).astype(np.int64)
            body_tip = self._fixed(pxy + (rad * 1.6)[:, None] * np.stack([np.cos(yaw), np.sin(yaw)], -1))
            head_tip = self._fixed(pxy + (rad * 1.1)[:, None] * np.stack([np.cos(head), np.sin(head)], -1))
            for j in range(len(pxy)):
                c = (int(centre[j, 0]), int(centre[j, 1]))
                cv2.circle(img, c, int(r_fx[j]), _PED, -1, cv2.LINE_AA, _SHIFT)
                cv2.arrowedLine(
                    img,
                    c,
                    (int(body_tip[j, 0]), int(body_tip[j, 1])),
                    _PED_HEADING,
                    1,
                    cv2.LINE_AA,
                    _SHIFT,
                    0.35,
                )
                cv2.line(
                    img, c, (int(head_tip[j, 0]), int(head_tip[j, 1])), _PED_HEAD, 2, cv2.LINE_AA, _SHIFT
                )

        # robot
        rc = self._fixed(np.array([rx, ry]))
        tip = self._fixed(np.array([rx + robot_radius * math.cos(ryaw), ry + robot_radius * math.sin(ryaw)]))
        cv2.circle(
            img,
            (int(rc[0]), int(rc[1])),
            max(1, int(round(robot_radius * ppm * sc))),
            _ROBOT,
            -1,
            cv2.LINE_AA,
            _SHIFT,
        )
        cv2.line(
            img, (int(rc[0]), int(rc[1])), (int(tip[0]), int(tip[1])), _ROBOT_HEADING, 2, cv2.LINE_AA, _SHIFT
        )
        return img


# ---------------------------------------------------------------------------------------------------------------
# Video and panel composition
# ---------------------------------------------------------------------------------------------------------------


def write_video(
    frames: Iterable[np.ndarray], path: str | os.PathLike[str], fps: float, crf: int = 23
) -> Path:
    """Encode RGB frames as an H.264 (libx264, yuv420p) MP4, atomically (temp file in the same folder, then rename).

    Odd frame sizes are padded by one black row / column (yuv420p needs even sizes).

    Args:
        frames: ``H x W x 3`` uint8 RGB images, all the same shape; any iterable (consumed once, streamed).
        path: output ``.mp4`` file.
        fps: frame rate, Hz.
        crf: x264 constant rate factor (lower is better quality).

    Returns:
        The written path.

    Raises:
        ValueError: no frames, a frame that is not ``H x W x 3`` uint8, or a frame whose shape differs from the
            first (the message names the frame index); nothing is left at ``path`` or in a temp file.
    """
    import av  # local: PyAV is only needed for videos

    if not (fps > 0 and math.isfinite(fps)):
        raise ValueError(f"fps must be positive, got {fps}")
    path = Path(path)
    it = iter(frames)
    try:
        first = np.asarray(next(it))
    except StopIteration:
        raise ValueError(f"write_video({path}): no frames") from None

    def check(i: int, f: np.ndarray) -> None:
        if f.ndim != 3 or f.shape[2] != 3 or f.dtype != np.uint8:
            raise ValueError(
                f"write_video({path}): frame {i} must be H x W x 3 uint8, got {f.shape} {f.dtype}"
            )
        if f.shape != first.shape:
            raise ValueError(f"write_video({path}): frame {i} has shape {f.shape}, frame 0 has {first.shape}")

    check(0, first)
    h, w = first.shape[:2]
    ph, pw = h + (h % 2), w + (w % 2)
    tmp = _atomic_target(path, ".mp4")
    try:
        with av.open(str(tmp), mode="w", format="mp4") as container:
            stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
            stream.width, stream.height, stream.pix_fmt = pw, ph, "yuv420p"
            stream.options = {"crf": str(int(crf))}
            buf = np.zeros((ph, pw, 3), dtype=np.uint8)
            i, f = 0, first
            while True:
                check(i, f)
                buf[:h, :w] = f
                for packet in stream.encode(av.VideoFrame.from_ndarray(buf, format="rgb24")):
                    container.mux(packet)
                try:
                    f = np.asarray(next(it))
                except StopIteration:
                    break
                i += 1
            for packet in stream.encode(None):
                container.mux(packet)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def colorize_depth(depth_m: np.ndarray, max_m: float = DEPTH_MAX_M) -> np.ndarray:
    """Colourise a metric depth image on a fixed scale (turbo colormap, near = blue, far = red).

    Args:
        depth_m: ``H x W`` depth, m; ``<= 0`` or non-finite means invalid.
        max_m: depth mapped to the top of the colormap, m (larger values are clipped).

    Returns:
        ``H x W x 3`` uint8 RGB; invalid pixels are black.
    """
    d = np.asarray(depth_m, dtype=np.float32)
    valid = np.isfinite(d) & (d > 0)
    q = np.round(np.clip(np.where(valid, d, 0.0) / max_m, 0.0, 1.0) * 255.0).astype(np.uint8)
    bgr = cv2.applyColorMap(q, cv2.COLORMAP_TURBO)
    rgb = bgr[..., ::-1].copy()
    rgb[~valid] = 0
    return rgb


def compose_frame(panels: Sequence[np.ndarray], labels: Sequence[str], height: int = 240) -> np.ndarray:
    """Resize panels to one height, label them, and place them side by side.

    Args:
        panels: each ``H x W x 3`` uint8 RGB, ``H x W`` uint8 grey, or ``H x W`` float depth in m (colourised on a
            fixed 0 to :data:`DEPTH_MAX_M` scale, ``<= 0`` = invalid = black).
        labels: one caption per panel (drawn at the top-left on a dark strip; may be empty).
        height: output height, px.

    Returns:
        ``height x sum(W_i') x 3`` uint8 RGB, each panel scaled to ``height`` keeping its aspect ratio.

    Raises:
        ValueError: no panels, a label count that differs from the panel count, or an unsupported panel.
    """
    if not panels:
        raise ValueError("compose_frame needs at least one panel")
    if len(labels) != len(panels):
        raise ValueError(f"compose_frame got {len(panels)} panels but {len(labels)} labels")
    if height < 1:
        raise ValueError(f"height must be positive, got {height}")
    out = []
    for i, (p, label) in enumerate(zip(panels, labels, strict=True)):
        a = np.asarray(p)
        interp: int | None = None
        if a.ndim == 2 and np.issubdtype(a.dtype, np.floating):
            a = colorize_depth(a)
            interp = cv2.INTER_NEAREST  # do not blend invalid (black) pixels into valid ones
        elif a.ndim == 2 and a.dtype == np.uint8:
            a = np.repeat(a[..., None], 3, axis=2)
        elif not (a.ndim == 3 and a.shape[2] == 3 and a.dtype == np.uint8):
            raise ValueError(
                f"panel {i}: expected H x W x 3 uint8, H x W uint8 or H x W float depth; got {a.shape} {a.dtype}"
            )
        h, w = a.shape[:2]
        if h == 0 or w == 0:
            raise ValueError(f"panel {i} is empty: {a.shape}")
        new_w = max(1, int(round(w * height / h)))
        if (h, w) != (height, new_w):
            if interp is None:
                interp = cv2.INTER_AREA if h > height else cv2.INTER_LINEAR
            a = cv2.resize(np.ascontiguousarray(a), (new_w, height), interpolation=interp)
        else:
            a = a.copy()
        if label:
            scale = max(0.35, height / 480.0)
            (tw, th), base = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
            strip_h = min(height, th + base + 6)
            roi = a[:strip_h, : min(new_w, tw + 8)]
            roi[:] = (roi.astype(np.uint16) * 2 // 5).astype(np.uint8)
            cv2.putText(
                a, label, (4, th + 3), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA
            )
        out.append(a)
    return np.concatenate(out, axis=1)
