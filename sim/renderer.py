"""pybullet scene for RGB-D rendering (DIRECT mode, TinyRenderer on the CPU).

Only visual shapes are created: the world's physics is ours (:mod:`sim.crowd`, :mod:`sim.robot`), pybullet is
the rasteriser. One client per env; :meth:`WorldRenderer.build` rebuilds everything per episode
(``resetSimulation``), which keeps episodes independent and deterministic.
"""

from __future__ import annotations

import numpy as np
import pybullet as pb

from sim.cameras import CameraSpec, depth_from_buffer, opengl_projection, opengl_view
from sim.geometry import Box, Cylinder, Obstacle
from sim.humans import N_PRIMITIVES


class WorldRenderer:
    """Static scene + human primitives in a private pybullet client."""

    def __init__(self) -> None:
        self.client = pb.connect(pb.DIRECT)
        self.human_ids: np.ndarray = np.zeros((0, N_PRIMITIVES), dtype=int)
        self._proj: dict[CameraSpec, list[float]] = {}

    def close(self) -> None:
        client = getattr(self, "client", None)  # None if __init__ was interrupted before connecting
        if client is not None and client >= 0:
            try:
                pb.disconnect(client)
            except pb.error:
                pass
            self.client = -1

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:  # noqa: BLE001 - at interpreter exit pybullet's module may be torn down (pb.error None)
            pass

    def build(self, obstacles: list[Obstacle], bounds: tuple[float, float, float, float],
              floor_color: tuple[float, float, float], half_extents: np.ndarray, colors: np.ndarray) -> None:
        """Create the floor, the obstacles and ``N x 11`` human boxes.

        Args:
            obstacles: static boxes and cylinders (world frame).
            bounds: ``(x_min, x_max, y_min, y_max)`` of the floor, m.
            floor_color: RGB in [0, 1].
            half_extents: ``N x 11 x 3`` box half extents of the human primitives, m.
            colors: ``N x 11 x 3`` RGB of the human primitives.
        """
        c = self.client
        pb.resetSimulation(physicsClientId=c)
        x0, x1, y0, y1 = bounds
        self._box((x0 + x1) / 2, (y0 + y1) / 2, -0.01, 0.0, ((x1 - x0) / 2 + 0.5, (y1 - y0) / 2 + 0.5, 0.01),
                  floor_color)
        for o in obstacles:
            if isinstance(o, Box):
                self._box(o.center[0], o.center[1], o.height_m / 2, o.yaw, (o.size[0] / 2, o.size[1] / 2,
                                                                          o.height_m / 2), o.color)
            elif isinstance(o, Cylinder):
                vs = pb.createVisualShape(pb.GEOM_CYLINDER, radius=o.radius_m, length=o.height_m,
                                          rgbaColor=[*o.color, 1.0], physicsClientId=c)
                pb.createMultiBody(0, -1, vs, [o.center[0], o.center[1], o.height_m / 2], physicsClientId=c)
        n = len(half_extents)
        ids = np.zeros((n, N_PRIMITIVES), dtype=int)
        for i in range(n):
            for k in range(N_PRIMITIVES):
                vs = pb.createVisualShape(pb.GEOM_BOX, halfExtents=half_extents[i, k].tolist(),
                                          rgbaColor=[*colors[i, k].tolist(), 1.0], physicsClientId=c)
                ids[i, k] = pb.createMultiBody(0, -1, vs, [0, 0, -10], physicsClientId=c)
        self.human_ids = ids

    def _box(self, x, y, z, yaw, half, color) -> int:
        vs = pb.createVisualShape(pb.GEOM_BOX, halfExtents=list(half), rgbaColor=[*color, 1.0],
                                  physicsClientId=self.client)
        q = pb.getQuaternionFromEuler([0, 0, yaw])
        return pb.createMultiBody(0, -1, vs, [x, y, z], q, physicsClientId=self.client)

    def set_humans(self, centers: np.ndarray, quats: np.ndarray) -> None:
        """Place the human boxes: ``N x 11 x 3`` centres (m) and ``N x 11 x 4`` quaternions (x, y, z, w)."""
        c = self.client
        reset = pb.resetBasePositionAndOrientation
        ids = self.human_ids.reshape(-1).tolist()
        cs = centers.reshape(-1, 3).tolist()
        qs = quats.reshape(-1, 4).tolist()
        for b, p, q in zip(ids, cs, qs, strict=True):
            reset(b, p, q, physicsClientId=c)

    def render(self, spec: CameraSpec, T_world_cam: np.ndarray, segmentation: bool = False
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Render one camera.

        Returns:
            ``(rgb, depth, seg)``: ``H x W x 3`` uint8, ``H x W`` float32 z-depth in m (0 = invalid), and the
            ``H x W`` int32 body-id mask if ``segmentation`` else None. Row 0 is the top of the image.
        """
        proj = self._proj.get(spec)
        if proj is None:
            proj = self._proj[spec] = opengl_projection(spec)
        flags = 0 if segmentation else pb.ER_NO_SEGMENTATION_MASK
        _, _, rgba, buf, seg = pb.getCameraImage(
            spec.width_px, spec.height_px, opengl_view(T_world_cam), proj, renderer=pb.ER_TINY_RENDERER,
            flags=flags, shadow=0, lightDirection=[0.4, 0.3, 1.0], physicsClientId=self.client,
        )
        rgba = np.asarray(rgba, dtype=np.uint8).reshape(spec.height_px, spec.width_px, 4)
        depth = depth_from_buffer(np.asarray(buf).reshape(spec.height_px, spec.width_px), spec)
        segm = np.asarray(seg, dtype=np.int32).reshape(spec.height_px, spec.width_px) if segmentation else None
        return np.ascontiguousarray(rgba[..., :3]), depth, segm
