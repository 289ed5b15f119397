"""RGB-D camera models: intrinsics, extrinsics, projection and back-projection.

Frames:
* world: the scene's, z up;
* base: the robot's, x forward, y left, z up, origin on the floor under the robot centre;
* camera (OpenCV convention): x right, y down, z forward along the optical axis.

Pixel coordinates ``(u, v)`` are continuous with ``(0, 0)`` at the top-left corner of the top-left pixel, so
pixel ``[row, col]`` has its centre at ``(col + 0.5, row + 0.5)``; depth is the z coordinate in the camera frame
(as RealSense reports it), metres, 0 = invalid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# base-from-camera rotation for a camera looking along base +x: camera x (right) = -y_base, y (down) = -z_base,
# z (forward) = +x_base
_R_BASE_CAM0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class CameraSpec:
    """One RGB-D camera on the robot.

    Attributes:
        name: ``left`` / ``right``.
        width_px, height_px: image size.
        hfov_deg: horizontal field of view.
        yaw_deg: mounting yaw in the base frame (positive = to the left).
        pitch_deg: mounting pitch (positive = looking down).
        mount_xyz_m: optical centre in the base frame.
        near_m, far_m: renderer clip planes.
        min_depth_m, max_depth_m: valid depth range; outside it depth reads 0.
    """

    name: str
    width_px: int
    height_px: int
    hfov_deg: float
    yaw_deg: float
    pitch_deg: float
    mount_xyz_m: tuple[float, float, float]
    near_m: float = 0.05
    far_m: float = 12.0
    min_depth_m: float = 0.3
    max_depth_m: float = 10.0

    @property
    def fx(self) -> float:
        return self.width_px / (2.0 * math.tan(math.radians(self.hfov_deg) / 2.0))

    @property
    def vfov_deg(self) -> float:
        return math.degrees(2.0 * math.atan(self.height_px / (2.0 * self.fx)))

    @property
    def K(self) -> np.ndarray:
        """3 x 3 intrinsic matrix (square pixels, principal point at the image centre)."""
        return np.array([[self.fx, 0.0, self.width_px / 2.0], [0.0, self.fx, self.height_px / 2.0], [0.0, 0.0, 1.0]])

    @property
    def T_base_cam(self) -> np.ndarray:
        """4 x 4 pose of the camera (OpenCV axes) in the base frame."""
        y, p = math.radians(self.yaw_deg), math.radians(self.pitch_deg)
        rz = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
        ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
        t = np.eye(4)
        t[:3, :3] = rz @ ry @ _R_BASE_CAM0
        t[:3, 3] = self.mount_xyz_m
        return t

    def to_dict(self) -> dict:
        """Intrinsics and extrinsics as plain data (for dataset metadata and logs)."""
        return {"name": self.name, "width": self.width_px, "height": self.height_px, "K": self.K.tolist(),
                "T_base_cam": self.T_base_cam.tolist(), "hfov_deg": self.hfov_deg, "yaw_deg": self.yaw_deg,
                "pitch_deg": self.pitch_deg, "min_depth_m": self.min_depth_m, "max_depth_m": self.max_depth_m,
                "depth_units": "m (z along the optical axis), 0 = invalid", "frame": "opencv (x right, y down, z fwd)"}


def pose_matrix(x: float, y: float, yaw: float) -> np.ndarray:
    """4 x 4 world-from-base transform of a planar robot pose."""
    c, s = math.cos(yaw), math.sin(yaw)
    t = np.eye(4)
    t[:2, :2] = [[c, -s], [s, c]]
    t[0, 3], t[1, 3] = x, y
    return t


def world_to_camera(points_w: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """``... x 3`` world points to the camera frame."""
    r, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    return (np.asarray(points_w) - t) @ r


def project(points_c: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points ``... x 3`` to continuous pixels ``... x 2`` and their depth ``...`` (z)."""
    z = points_c[..., 2]
    zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
    u = K[0, 0] * points_c[..., 0] / zs + K[0, 2]
    v = K[1, 1] * points_c[..., 1] / zs + K[1, 2]
    return np.stack([u, v], -1), z


def backproject(uv: np.ndarray, depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Continuous pixels ``... x 2`` with depth ``...`` (m, z) to camera-frame points ``... x 3``."""
    x = (uv[..., 0] - K[0, 2]) / K[0, 0] * depth
    y = (uv[..., 1] - K[1, 2]) / K[1, 1] * depth
    return np.stack([x, y, depth], -1)


def opengl_projection(spec: CameraSpec) -> list[float]:
    """Column-major OpenGL projection matrix matching ``spec.K`` (for pybullet's ``getCameraImage``)."""
    n, f = spec.near_m, spec.far_m
    w, h = spec.width_px, spec.height_px
    fx = spec.fx
    # the off-centre terms shift TinyRenderer's sampling grid onto pixel centres (col + 0.5, row + 0.5); without
    # them rendered images sit half a pixel off the intrinsics used for projection (tested)
    p = np.array([
        [2 * fx / w, 0, 1.0 / w, 0],
        [0, 2 * fx / h, 1.0 / h, 0],
        [0, 0, -(f + n) / (f - n), -2 * f * n / (f - n)],
        [0, 0, -1, 0],
    ])
    return p.T.reshape(-1).tolist()


def opengl_view(T_world_cam: np.ndarray) -> list[float]:
    """Column-major OpenGL view matrix (world → GL eye, where GL eye has y up and looks along −z)."""
    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera axes -> OpenGL eye axes
    view = flip @ np.linalg.inv(T_world_cam)
    return view.T.reshape(-1).tolist()


def depth_from_buffer(buf: np.ndarray, spec: CameraSpec) -> np.ndarray:
    """Metric z-depth (float32, m) from an OpenGL depth buffer in [0, 1]; out-of-range → 0."""
    n, f = spec.near_m, spec.far_m
    z = f * n / (f - (f - n) * np.asarray(buf, dtype=np.float64))
    valid = (z >= spec.min_depth_m) & (z <= spec.max_depth_m) & (buf < 1.0)
    return np.where(valid, z, 0.0).astype(np.float32)
