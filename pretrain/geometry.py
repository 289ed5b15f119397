"""BEV grid, camera models, the measured-depth lift (fast and reference) and the ego-motion warp.

Frames (as in :mod:`sim.cameras`):

* **base** (robot): x forward, y left, z up, origin on the floor under the robot centre;
* **camera**: OpenCV axes (x right, y down, z forward); pixel ``[row, col]`` has its centre at
  ``(col + 0.5, row + 0.5)``; depth is the z coordinate in the camera frame (m, 0 = invalid).

BEV layout (lift-splat-shoot / FIERY convention): a BEV tensor is ``B x C x X x Y`` where cell ``[i, j]`` covers
the base-frame point ``x = x_min + (i + 0.5) * dx`` (forward) and ``y = y_min + (j + 0.5) * dy`` (left). So row 0
is the nearest row and column 0 the rightmost column; :func:`bev_to_image` flips it into a top-down picture with
the robot heading up.

The lift: every ``lift_stride_px``-th pixel of each depth image (the pixel at ``(s*r + s//2, s*c + s//2)``) is
back-projected with its measured depth, moved into the base frame, dropped if its depth is invalid, if it lies
below the ground threshold ``z_min`` or above ``z_max``, or outside the grid; the feature vector sampled at that
pixel is then *sum-pooled* into its BEV cell (vertical sum pooling, as in the paper). :func:`lift_splat` does it
for a whole batch with one ``index_add_``; :func:`lift_splat_reference` is the obvious per-point loop.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from pipeline.core.errors import ConfigError, CorruptArtifactError
from recorder.dataset_info import read_dataset_info


@dataclass(frozen=True)
class Camera:
    """One RGB-D camera as the encoder sees it.

    Attributes:
        name: camera name (``left`` / ``right``), also the dataset key suffix.
        width, height: image size in pixels.
        K: 3 x 3 intrinsics (pixels).
        T_base_cam: 4 x 4 pose of the camera (OpenCV axes) in the base frame.
        min_depth_m, max_depth_m: valid depth range of the sensor.
    """

    name: str
    width: int
    height: int
    K: tuple[tuple[float, ...], ...]
    T_base_cam: tuple[tuple[float, ...], ...]
    min_depth_m: float
    max_depth_m: float

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "camera") -> Camera:
        """Builds a camera from a ``CameraSpec.to_dict()``-style mapping (dataset ``meta/icrowdnav.json``)."""
        try:
            K = np.asarray(d["K"], dtype=np.float64)
            T = np.asarray(d["T_base_cam"], dtype=np.float64)
            cam = cls(name=str(d["name"]), width=int(d["width"]), height=int(d["height"]),
                      K=tuple(map(tuple, K.tolist())), T_base_cam=tuple(map(tuple, T.tolist())),
                      min_depth_m=float(d.get("min_depth_m", 0.0)), max_depth_m=float(d["max_depth_m"]))
        except (KeyError, TypeError, ValueError) as e:
            raise CorruptArtifactError(f"{where}: expected a camera with name/width/height/K/T_base_cam/"
                                       f"max_depth_m, got {type(e).__name__}: {e}") from None
        if K.shape != (3, 3) or T.shape != (4, 4) or cam.width < 1 or cam.height < 1:
            raise CorruptArtifactError(f"{where}: expected K 3x3, T_base_cam 4x4 and a positive size, got "
                                       f"K {K.shape}, T {T.shape}, {cam.width}x{cam.height}")
        return cam

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "width": self.width, "height": self.height, "K": [list(r) for r in self.K],
                "T_base_cam": [list(r) for r in self.T_base_cam], "min_depth_m": self.min_depth_m,
                "max_depth_m": self.max_depth_m}

    @property
    def K_np(self) -> np.ndarray:
        return np.asarray(self.K, dtype=np.float64)

    @property
    def T_np(self) -> np.ndarray:
        return np.asarray(self.T_base_cam, dtype=np.float64)


def cameras_from_meta(meta: dict[str, Any], where: str) -> list[Camera]:
    """The cameras of a parsed ``meta/icrowdnav.json`` (``where`` names the file in errors), in its order."""
    cams = meta.get("cameras") if isinstance(meta, dict) else None
    if not isinstance(cams, dict) or not cams:
        raise CorruptArtifactError(f"{where}: 'cameras' must be a non-empty mapping, got {cams!r:.80}")
    return [Camera.from_dict(c, f"{where} cameras.{k}") for k, c in cams.items()]


def cameras_from_dataset(root: Path) -> list[Camera]:
    """The cameras of an exported dataset (its features' ``info.camera`` in ``meta/info.json``: see
    :mod:`recorder.dataset_info`), in the file's order (left, right)."""
    return cameras_from_meta({"cameras": read_dataset_info(root).cameras}, str(Path(root) / "meta" / "info.json"))


@dataclass(frozen=True)
class BEVGrid:
    """A robot-centred BEV grid (LSS-style bounds: ``(min, max, step)`` per axis, metres, base frame).

    Attributes:
        x_bound: forward extent and cell size, e.g. ``(0.0, 6.0, 0.1)``.
        y_bound: lateral extent (left positive) and cell size, e.g. ``(-4.8, 4.8, 0.1)``.
        z_bound: height band kept by the lift: points below ``z_bound[0]`` (the ground threshold) or above
            ``z_bound[1]`` are dropped; there is one vertical bin (sum pooling over height).
    """

    x_bound: tuple[float, float, float]
    y_bound: tuple[float, float, float]
    z_bound: tuple[float, float]

    def validate(self, key: str = "grid") -> None:
        for name, b in (("x_bound", self.x_bound), ("y_bound", self.y_bound)):
            if len(b) != 3 or not (b[1] > b[0] and b[2] > 0):
                raise ConfigError(f"{key}.{name}: expected (min, max, step) with max > min and step > 0, got {b}")
            n = (b[1] - b[0]) / b[2]
            if abs(n - round(n)) > 1e-6:
                raise ConfigError(f"{key}.{name}: the extent {b[1] - b[0]:g} m must be a whole number of "
                                  f"{b[2]:g} m cells, got {n:.3f} cells")
        if len(self.z_bound) != 2 or not self.z_bound[1] > self.z_bound[0]:
            raise ConfigError(f"{key}.z_bound: expected (ground threshold, max height) with max > min, "
                              f"got {self.z_bound}")

    @property
    def shape(self) -> tuple[int, int]:
        """``(X, Y)``: cells forward, cells lateral."""
        return (round((self.x_bound[1] - self.x_bound[0]) / self.x_bound[2]),
                round((self.y_bound[1] - self.y_bound[0]) / self.y_bound[2]))

    def cell_centres(self) -> np.ndarray:
        """``X x Y x 2`` base-frame ``(x, y)`` of every cell centre (float64)."""
        nx, ny = self.shape
        xs = self.x_bound[0] + (np.arange(nx) + 0.5) * self.x_bound[2]
        ys = self.y_bound[0] + (np.arange(ny) + 0.5) * self.y_bound[2]
        return np.stack(np.meshgrid(xs, ys, indexing="ij"), -1)

    def cell_of(self, x: float, y: float) -> tuple[int, int] | None:
        """The ``(i, j)`` cell holding base-frame point ``(x, y)``, or None outside the grid."""
        i = math.floor((x - self.x_bound[0]) / self.x_bound[2])
        j = math.floor((y - self.y_bound[0]) / self.y_bound[2])
        nx, ny = self.shape
        return (i, j) if 0 <= i < nx and 0 <= j < ny else None

    def to_dict(self) -> dict[str, Any]:
        return {"x_bound": list(self.x_bound), "y_bound": list(self.y_bound), "z_bound": list(self.z_bound)}


def fov_mask(grid: BEVGrid, cameras: list[Camera], heights_m: tuple[float, ...] = (0.3, 1.0)) -> np.ndarray:
    """Cells inside at least one camera's field of view (bool ``X x Y``).

    A cell counts when its centre, at any of ``heights_m``, projects inside the image with a depth inside the
    sensor's range. Occlusion is ignored: this is the field of view, not visibility.
    """
    c = grid.cell_centres()
    out = np.zeros(grid.shape, dtype=bool)
    for cam in cameras:
        T, K = cam.T_np, cam.K_np
        for h in heights_m:
            pts = np.concatenate([c, np.full(c.shape[:-1] + (1,), h)], -1)
            pc = (pts - T[:3, 3]) @ T[:3, :3]
            z = pc[..., 2]
            zs = np.where(z > 1e-6, z, 1.0)
            u = K[0, 0] * pc[..., 0] / zs + K[0, 2]
            v = K[1, 1] * pc[..., 1] / zs + K[1, 2]
            out |= ((z >= cam.min_depth_m) & (z <= cam.max_depth_m) & (u >= 0) & (u < cam.width)
                    & (v >= 0) & (v < cam.height))
    return out


def check_grid_fits_cameras(grid: BEVGrid, cameras: list[Camera], key: str = "grid") -> np.ndarray:
    """Fails unless the grid lies within the cameras' range; returns the field-of-view mask.

    Raises:
        ConfigError: the grid reaches farther forward than every camera's ``max_depth_m`` (its far corners may
            lie beyond the range: the field of view is a wedge, and those cells are masked out of the loss and
            the IoU), or less than 20 % of the grid's cells are in any camera's field of view (a grid behind or
            beside the cameras).
    """
    grid.validate(key)
    if not cameras:
        raise ConfigError(f"{key}: no cameras to lift from")
    max_range = max(c.max_depth_m for c in cameras)
    reach = max(abs(grid.x_bound[0]), abs(grid.x_bound[1]))
    if reach > max_range:
        raise ConfigError(f"{key}: x_bound reaches {reach:.2f} m forward but the cameras see at most "
                          f"{max_range:.2f} m (max_depth_m); expected x_bound[1] <= {max_range:g}")
    mask = fov_mask(grid, cameras)
    frac = float(mask.mean())
    if frac < 0.2:
        raise ConfigError(f"{key}: only {100 * frac:.1f} % of the BEV cells (x {grid.x_bound}, y {grid.y_bound}) "
                          "are in the cameras' field of view; expected "
                          ">= 20 % — the grid does not fit the cameras")
    return mask


def lift_pixel_index(height: int, width: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns (``h x w`` int arrays) of the pixels the lift samples: ``s*r + s//2``, ``s*c + s//2``."""
    rows = np.arange(height // stride) * stride + stride // 2
    cols = np.arange(width // stride) * stride + stride // 2
    return np.meshgrid(rows, cols, indexing="ij")


def sample_depth(depth: torch.Tensor, stride: int) -> torch.Tensor:
    """Picks the lift pixels of full-resolution depth images: ``... x H x W`` → ``... x H//s x W//s``.

    Nearest sampling (no averaging), so a lifted point always carries a depth that was measured, never a blend
    of a foreground and a background surface.
    """
    h, w = depth.shape[-2:]
    o = stride // 2
    return depth[..., o:(h // stride) * stride:stride, o:(w // stride) * stride:stride]


class LiftGeometry:
    """Precomputed rays of every lift pixel of every camera, in the base frame (the fast lift's constants).

    Attributes:
        rays: ``N x h x w x 3`` base-frame direction of each lift pixel scaled so that ``point = origin + d * ray``
            for z-depth ``d``.
        origins: ``N x 3`` camera centres in the base frame.
    """

    def __init__(self, cameras: list[Camera], stride: int) -> None:
        if len({(c.width, c.height) for c in cameras}) != 1:
            raise ConfigError(f"cameras: expected one image size for all cameras, got "
                              f"{[(c.name, c.width, c.height) for c in cameras]}")
        self.stride = stride
        h, w = cameras[0].height, cameras[0].width
        rows, cols = lift_pixel_index(h, w, stride)
        self.lift_hw = rows.shape
        if min(self.lift_hw) < 1:
            raise ConfigError(f"lift_stride_px {stride} is larger than the {w}x{h} images")
        rays, origins = [], []
        for cam in cameras:
            K, T = cam.K_np, cam.T_np
            u, v = cols + 0.5, rows + 0.5
            ray_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, dtype=float)], -1)
            rays.append(ray_c @ T[:3, :3].T)
            origins.append(T[:3, 3])
        self.rays = torch.as_tensor(np.stack(rays), dtype=torch.float32)
        self.origins = torch.as_tensor(np.stack(origins), dtype=torch.float32)
        self.min_depth = torch.tensor([c.min_depth_m for c in cameras], dtype=torch.float32)
        self.max_depth = torch.tensor([c.max_depth_m for c in cameras], dtype=torch.float32)
        self._on: dict[torch.device, tuple[torch.Tensor, ...]] = {}

    def on(self, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(origins, rays, min_depth, max_depth)`` on ``device`` (copied there once, then cached; the CPU
        tensors themselves on the CPU)."""
        device = torch.device(device)
        if device.type == "cpu":
            return self.origins, self.rays, self.min_depth, self.max_depth
        if device not in self._on:
            self._on[device] = tuple(t.to(device) for t in (self.origins, self.rays, self.min_depth, self.max_depth))
        return self._on[device]


def lift_splat(features: torch.Tensor, depth: torch.Tensor, geom: LiftGeometry, grid: BEVGrid) -> torch.Tensor:
    """Fast measured-depth lift + vertical sum pooling.

    Args:
        features: ``B x N x C x h x w`` image features at the lift pixels (N cameras).
        depth: ``B x N x h x w`` z-depth at the lift pixels (m, 0 = invalid), see :func:`sample_depth`.
        geom: the cameras' lift constants.
        grid: the BEV grid.

    Returns:
        ``B x C x X x Y`` BEV features in the base frame (sum of the features of the points in each cell).
    """
    b, n, c, h, w = features.shape
    nx, ny = grid.shape
    origins, rays, min_depth, max_depth = geom.on(depth.device)
    d = depth.unsqueeze(-1)  # B N h w 1
    pts = origins.view(1, n, 1, 1, 3) + d * rays.unsqueeze(0)  # B N h w 3
    ix = torch.floor((pts[..., 0] - grid.x_bound[0]) / grid.x_bound[2]).long()
    iy = torch.floor((pts[..., 1] - grid.y_bound[0]) / grid.y_bound[2]).long()
    keep = ((depth > 0) & (depth >= min_depth.view(1, n, 1, 1)) & (depth <= max_depth.view(1, n, 1, 1))
            & (pts[..., 2] >= grid.z_bound[0]) & (pts[..., 2] <= grid.z_bound[1])
            & (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny))
    batch = torch.arange(b, device=ix.device).view(b, 1, 1, 1).expand_as(ix)
    flat = (batch * nx + ix) * ny + iy
    feats = features.permute(0, 1, 3, 4, 2)[keep]  # P x C
    out = features.new_zeros(b * nx * ny, c)
    out.index_add_(0, flat[keep], feats)
    return out.view(b, nx, ny, c).permute(0, 3, 1, 2).contiguous()


EVIDENCE_CHANNELS = ("hits", "floor", "free")  # the channels of :func:`lift_evidence`, in order
FREE_SAMPLES = 16  # points sampled along each ray's free stretch (stratified: free_offsets)
FREE_MARGIN_M = 0.15  # the free stretch ends this far before the measured point


def _count_cells(pts: torch.Tensor, keep: torch.Tensor, grid: BEVGrid) -> torch.Tensor:
    """``B x ...`` points (``... x 3``, base frame) and a keep mask → ``B x X x Y`` counts of kept points inside the
    grid."""
    b, nx, ny = pts.shape[0], *grid.shape
    ix = torch.floor((pts[..., 0] - grid.x_bound[0]) / grid.x_bound[2]).long()
    iy = torch.floor((pts[..., 1] - grid.y_bound[0]) / grid.y_bound[2]).long()
    keep = keep & (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    batch = torch.arange(b, device=ix.device).view(b, *([1] * (ix.dim() - 1))).expand_as(ix)
    flat = ((batch * nx + ix) * ny + iy)[keep]
    out = pts.new_zeros(b * nx * ny)
    out.index_add_(0, flat, torch.ones_like(flat, dtype=pts.dtype))
    return out.view(b, nx, ny)


def free_offsets(hw: tuple[int, int], device: torch.device | str = "cpu") -> torch.Tensor:
    """``h x w x 1`` fixed offsets in [0, 1) of the free-ray samples of each lift pixel (golden-ratio sequence over
    the pixel index): rays of equal depth sample different distances, so a flat wall's free stretch is covered
    without gaps between the sample rows (with one offset for all, cells at every 1/S of the depth stay empty)."""
    h, w = hw
    return torch.remainder(torch.arange(h * w, dtype=torch.float64) * 0.6180339887498949, 1.0).view(h, w, 1).to(
        device, torch.float32)


def lift_evidence(depth: torch.Tensor, geom: LiftGeometry, grid: BEVGrid) -> torch.Tensor:
    """Geometric evidence of every BEV cell from the depth alone: ``B x N x h x w`` depth at the lift pixels →
    ``B x 3 x X x Y`` = ``log(1 + count)`` of (:data:`EVIDENCE_CHANNELS`)

    * ``hits``: measured points inside the height band (something is there — what :func:`lift_splat` pools);
    * ``floor``: measured points below the ground threshold (the floor is seen there: free);
    * ``free``: points sampled along each valid ray up to :data:`FREE_MARGIN_M` before its measured point (the ray
      crossed that cell: free), :data:`FREE_SAMPLES` per ray, stratified by :func:`free_offsets`.

    Without ``floor`` and ``free`` a cell with no lifted point is ambiguous — free floor and the space hidden behind
    a wall look the same — which is what held the static IoU down (docs/notes/2026-11-bev-pretrain-epochs-and-
    thresholds.md).
    """
    b, n = depth.shape[:2]
    origins, rays, min_depth, max_depth = geom.on(depth.device)
    d = depth.float()
    ok = (d > 0) & (d >= min_depth.view(1, n, 1, 1)) & (d <= max_depth.view(1, n, 1, 1))
    pts = origins.view(1, n, 1, 1, 3) + d.unsqueeze(-1) * rays.unsqueeze(0)  # B N h w 3
    z = pts[..., 2]
    hits = _count_cells(pts, ok & (z >= grid.z_bound[0]) & (z <= grid.z_bound[1]), grid)
    floor = _count_cells(pts, ok & (z < grid.z_bound[0]), grid)
    frac = (torch.arange(FREE_SAMPLES, device=d.device, dtype=d.dtype) + free_offsets(d.shape[-2:], d.device)
            ) / FREE_SAMPLES  # h x w x S
    reach = (d - FREE_MARGIN_M).clamp_min(0.0).unsqueeze(-1) * frac  # B N h w S: z-depth of each sample
    samples = origins.view(1, n, 1, 1, 1, 3) + reach.unsqueeze(-1) * rays.view(1, n, *rays.shape[1:3], 1, 3)
    # samples above the band's top say nothing about what stands below them in the band
    free = _count_cells(samples, ok.unsqueeze(-1).expand_as(reach) & (samples[..., 2] <= grid.z_bound[1]), grid)
    return torch.log1p(torch.stack([hits, floor, free], 1))


def lift_splat_reference(features: np.ndarray, depth: np.ndarray, cameras: list[Camera], stride: int,
                         grid: BEVGrid) -> np.ndarray:
    """The obvious per-point loop, for testing :func:`lift_splat` (same arguments, numpy, float64).

    Each lift pixel is back-projected with ``K^-1``, moved by ``T_base_cam`` and added to its cell.
    """
    b, n, c, h, w = features.shape
    nx, ny = grid.shape
    out = np.zeros((b, c, nx, ny))
    for bi in range(b):
        for ci, cam in enumerate(cameras):
            K, T = cam.K_np, cam.T_np
            for r in range(h):
                for col in range(w):
                    d = float(depth[bi, ci, r, col])
                    if d <= 0 or d < cam.min_depth_m or d > cam.max_depth_m:
                        continue
                    u, v = col * stride + stride // 2 + 0.5, r * stride + stride // 2 + 0.5
                    p_cam = np.array([(u - K[0, 2]) / K[0, 0] * d, (v - K[1, 2]) / K[1, 1] * d, d, 1.0])
                    x, y, z = (T @ p_cam)[:3]
                    if not grid.z_bound[0] <= z <= grid.z_bound[1]:
                        continue
                    cell = grid.cell_of(x, y)
                    if cell is not None:
                        out[bi, :, cell[0], cell[1]] += features[bi, ci, :, r, col]
    return out


def relative_pose(pose_from: torch.Tensor, pose_to: torch.Tensor) -> torch.Tensor:
    """Pose of frame ``to`` expressed in frame ``from``: ``[dx, dy, dyaw]`` (``... x 3``, planar world poses).

    A point ``p`` in frame ``to`` is at ``R(dyaw) p + (dx, dy)`` in frame ``from``.
    """
    dx = pose_to[..., 0] - pose_from[..., 0]
    dy = pose_to[..., 1] - pose_from[..., 1]
    c, s = torch.cos(pose_from[..., 2]), torch.sin(pose_from[..., 2])
    dyaw = torch.atan2(torch.sin(pose_to[..., 2] - pose_from[..., 2]), torch.cos(pose_to[..., 2] - pose_from[..., 2]))
    return torch.stack([c * dx + s * dy, -s * dx + c * dy, dyaw], -1)


@functools.lru_cache(maxsize=8)
def _centres(grid: BEVGrid, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """Cached ``X x Y x 2`` cell centres on ``device`` (read-only use)."""
    return torch.as_tensor(grid.cell_centres(), dtype=dtype, device=device)


def warp_bev(maps: torch.Tensor, current_in_past: torch.Tensor, grid: BEVGrid, mode: str = "bilinear") -> torch.Tensor:
    """Warps BEV maps from a past robot frame into the current one (ego-motion compensation).

    Args:
        maps: ``B x C x X x Y`` maps in the past frame.
        current_in_past: ``B x 3`` ``[dx, dy, dyaw]`` = :func:`relative_pose` ``(pose_past, pose_current)``:
            the current frame's pose expressed in the past frame.
        grid: the grid of both maps.
        mode: ``grid_sample`` interpolation.

    Returns:
        ``B x C x X x Y`` maps in the current frame; cells that were outside the past map are 0.
    """
    b = maps.shape[0]
    centres = _centres(grid, maps.dtype, maps.device)  # X Y 2
    tx, ty, yaw = (current_in_past[:, k].to(maps.dtype).view(b, 1, 1) for k in range(3))
    c, s = torch.cos(yaw), torch.sin(yaw)
    px = tx + c * centres[..., 0] - s * centres[..., 1]  # B X Y: the cell centres in the past frame
    py = ty + s * centres[..., 0] + c * centres[..., 1]
    # grid_sample: input W axis = Y (last dim), H axis = X; normalised coords with align_corners=False
    gx = 2.0 * (py - grid.y_bound[0]) / (grid.y_bound[1] - grid.y_bound[0]) - 1.0
    gy = 2.0 * (px - grid.x_bound[0]) / (grid.x_bound[1] - grid.x_bound[0]) - 1.0
    return F.grid_sample(maps, torch.stack([gx, gy], -1), mode=mode, padding_mode="zeros", align_corners=False)


def bev_to_image(bev: np.ndarray) -> np.ndarray:
    """``X x Y [...]`` BEV array → top-down picture: robot heading up, its left on the left (flip both axes)."""
    return np.ascontiguousarray(np.asarray(bev)[::-1, ::-1])
