"""Depth perception shared by the model-based baseline (:mod:`sim.planners.dwa`) and the students' lookahead
perception (:mod:`rl.perceive`): back-projection of depth images into the robot's base frame and an obstacle
memory in the odometry frame.

Frames: base = x forward, y left, z up, origin on the floor under the robot centre; odometry = the world frame.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from sim.cameras import CameraSpec
from sim.geometry import world_to_robot


def depth_to_points(depth: np.ndarray, spec: CameraSpec, stride: int = 1) -> np.ndarray:
    """Back-project the valid pixels of one depth image into the robot's base frame.

    Args:
        depth: ``H x W`` z-depth, m (0 = invalid), as rendered by :class:`sim.renderer.WorldRenderer`.
        spec: the camera (intrinsics ``K`` and base-from-camera ``T_base_cam``).
        stride: use pixels ``[::stride, ::stride]``.

    Returns:
        ``N x 3`` points, base frame (x forward, y left, z up from the floor), m.
    """
    d = np.asarray(depth, dtype=np.float64)
    if d.shape != (spec.height_px, spec.width_px):
        raise ValueError(f"depth image of camera {spec.name!r}: expected shape "
                         f"{(spec.height_px, spec.width_px)}, got {d.shape}")
    rows = np.arange(0, spec.height_px, stride)
    cols = np.arange(0, spec.width_px, stride)
    z = d[np.ix_(rows, cols)]
    valid = z > 0
    vv, uu = np.meshgrid(rows + 0.5, cols + 0.5, indexing="ij")  # pixel centres (u = col, v = row)
    k = spec.K
    z = z[valid]
    pc = np.stack([(uu[valid] - k[0, 2]) / k[0, 0] * z, (vv[valid] - k[1, 2]) / k[1, 1] * z, z], -1)
    t = spec.T_base_cam
    return pc @ t[:3, :3].T + t[:3, 3]


class ObstacleMemory:
    """Obstacle points in the odometry frame, one per voxel, each with the time it was last observed.

    Args:
        memory_s: points older than this are dropped, s.
        voxel_m: voxel size, m.
    """

    def __init__(self, memory_s: float, voxel_m: float):
        self.memory_s = memory_s
        self.voxel_m = voxel_m
        self.xyz = np.zeros((0, 3))
        self.stamp = np.zeros(0)

    def __len__(self) -> int:
        return len(self.xyz)

    def update(self, new_xyz: np.ndarray, t_s: float, keep: np.ndarray | None = None) -> None:
        """Add points observed at ``t_s``, drop expired ones and (optionally) those where ``keep`` is False.

        Args:
            new_xyz: ``N x 3`` odometry-frame points, m.
            t_s: observation time, s.
            keep: ``M`` bool over the current points (e.g. False where a camera sees through them).
        """
        old_xyz, old_t = self.xyz, self.stamp
        if keep is not None:
            old_xyz, old_t = old_xyz[keep], old_t[keep]
        live = t_s - old_t < self.memory_s - 1e-9
        xyz = np.concatenate([np.asarray(new_xyz, dtype=np.float64).reshape(-1, 3), old_xyz[live]])
        stamp = np.concatenate([np.full(len(new_xyz), float(t_s)), old_t[live]])
        if len(xyz) == 0:
            self.xyz, self.stamp = xyz, stamp
            return
        ijk = np.floor(xyz / self.voxel_m).astype(np.int64) + (1 << 20)  # 21 bits per axis: ±100 km at 0.1 m
        key = (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]
        # the first occurrence of each voxel wins: new points come first, so a re-observed voxel is refreshed
        _, first = np.unique(key, return_index=True)
        self.xyz, self.stamp = xyz[first], stamp[first]

    def seen_through(self, depths: Sequence[np.ndarray], cameras: Sequence[CameraSpec], pose: Sequence[float],
                     tol_m: float) -> np.ndarray:
        """``M`` bool: remembered points some camera now sees through (valid depth > point depth + tol)."""
        out = np.zeros(len(self.xyz), dtype=bool)
        if not len(self.xyz):
            return out
        base = world_to_robot(self.xyz, pose)
        for depth, spec in zip(depths, cameras, strict=True):
            t = spec.T_base_cam
            pc = (base - t[:3, 3]) @ t[:3, :3]  # camera frame
            z = pc[:, 2]
            front = z > spec.min_depth_m
            zs = np.where(front, z, 1.0)
            u = spec.K[0, 0] * pc[:, 0] / zs + spec.K[0, 2]
            v = spec.K[1, 1] * pc[:, 1] / zs + spec.K[1, 2]
            inside = front & (u >= 0) & (u < spec.width_px) & (v >= 0) & (v < spec.height_px)
            col = np.clip(u.astype(np.int64), 0, spec.width_px - 1)
            row = np.clip(v.astype(np.int64), 0, spec.height_px - 1)
            measured = np.asarray(depth)[row, col]
            out |= inside & (measured > 0) & (measured > z + tol_m)
        return out
