"""Frames <-> messages: :class:`FrameEncoder` turns a :class:`recorder.schema.Frame` into the serialized payloads
of its topics (Foxglove protobuf and JSON), :func:`decode_frame` turns them back into a Frame.
"""

from __future__ import annotations

import json
import math

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Grid_pb2 import Grid
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.Vector2_pb2 import Vector2
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp

from recorder.mcap.codecs import dec_array, dec_float, dumps, enc_array, enc_float
from recorder.mcap.layout import camera_frame_id
from recorder.schema import (
    CAMERA_NAMES,
    FRAME_BASE,
    FRAME_WORLD,
    TOPIC_CALIB,
    TOPIC_DEPTH,
    TOPIC_DETECTIONS,
    TOPIC_GOAL,
    TOPIC_KEYPOINTS_2D,
    TOPIC_PEDS,
    TOPIC_PEDS_SCENE,
    TOPIC_REWARD,
    TOPIC_RGB,
    TOPIC_ROBOT,
    TOPIC_ROBOT_POSE,
    TOPIC_TF,
    EpisodeMeta,
    Frame,
    depth_from_mm,
    depth_to_mm,
)


def _stamp(t_ns: int) -> Timestamp:
    return Timestamp(seconds=t_ns // 1_000_000_000, nanos=t_ns % 1_000_000_000)


def _yaw_quat(yaw: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0))


def _rot_to_quat(r: np.ndarray) -> Quaternion:
    """3 x 3 rotation matrix → unit quaternion (Shepperd's method, w >= 0)."""
    m = np.asarray(r, dtype=np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        w, x, y, z = 0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        w, x, y, z = (m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        w, x, y, z = (m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        w, x, y, z = (m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s
    if w < 0:
        w, x, y, z = -w, -x, -y, -z
    return Quaternion(x=x, y=y, z=z, w=w)


def quat_to_rot(q: Quaternion) -> np.ndarray:
    """Unit quaternion → 3 x 3 rotation matrix (the inverse of what the writer logs on /tf)."""
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


# --------------------------------------------------------------------------------------------------------------
# frame → messages


def _raw_image(t_ns: int, frame_id: str, img: np.ndarray, encoding: str, bytes_per_px: int) -> RawImage:
    h, w = img.shape[:2]
    return RawImage(timestamp=_stamp(t_ns), frame_id=frame_id, width=w, height=h, encoding=encoding,
                    step=w * bytes_per_px, data=np.ascontiguousarray(img).tobytes())


def _tf(parent: str, child: str, t_ns: int, xyz: np.ndarray, q: Quaternion) -> FrameTransform:
    return FrameTransform(timestamp=_stamp(t_ns), parent_frame_id=parent, child_frame_id=child,
                          translation=Vector3(x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])), rotation=q)


_TRACK_COLORS = [Color(r=r, g=g, b=b, a=1.0) for r, g, b in (
    (0.90, 0.10, 0.29), (0.24, 0.71, 0.29), (1.0, 0.88, 0.10), (0.26, 0.39, 0.85), (0.96, 0.51, 0.19),
    (0.57, 0.12, 0.71), (0.27, 0.94, 0.94), (0.94, 0.20, 0.90))]
_WHITE = Color(r=1.0, g=1.0, b=1.0, a=1.0)
_BODY_COLOR = Color(r=0.2, g=0.5, b=0.9, a=0.6)
_HEAD_COLOR = Color(r=1.0, g=0.4, b=0.1, a=1.0)


class FrameEncoder:
    """Turns frames into serialized messages for the episode's channels (constant per-episode parts cached)."""

    def __init__(self, meta: EpisodeMeta) -> None:
        self.meta = meta
        self.cams: dict[str, dict] = {}
        for cam in CAMERA_NAMES:
            spec = meta.cameras[cam]
            k = np.asarray(spec["K"], dtype=np.float64)
            t_base_cam = np.asarray(spec["T_base_cam"], dtype=np.float64)
            self.cams[cam] = {"K": k, "T": t_base_cam, "w": int(spec["width"]), "h": int(spec["height"]),
                              "q": _rot_to_quat(t_base_cam[:3, :3]), "p": k.ravel().tolist(),
                              "P": np.hstack([k, np.zeros((3, 1))]).ravel().tolist()}

    def frame_messages(self, fr: Frame) -> list[tuple[str, bytes]]:
        """(topic, payload) of every message of one frame, in :func:`frame_topics` order (minus the grid)."""
        t = fr.t_ns
        out: list[tuple[str, bytes]] = []
        for cam in CAMERA_NAMES:
            c = self.cams[cam]
            fid = camera_frame_id(cam)
            out.append((TOPIC_RGB.format(cam=cam), _raw_image(t, fid, fr.rgb[cam], "rgb8", 3).SerializeToString()))
            mm = depth_to_mm(fr.depth[cam])
            out.append((TOPIC_DEPTH.format(cam=cam), _raw_image(t, fid, mm, "16UC1", 2).SerializeToString()))
            calib = CameraCalibration(timestamp=_stamp(t), frame_id=fid, width=c["w"], height=c["h"],
                                      distortion_model="plumb_bob", D=[0.0] * 5, K=c["p"],
                                      R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], P=c["P"])
            out.append((TOPIC_CALIB.format(cam=cam), calib.SerializeToString()))
            out.append((TOPIC_KEYPOINTS_2D.format(cam=cam), self._keypoints(fr, cam, t).SerializeToString()))
        x, y, yaw = (float(v) for v in fr.odom[:3])
        tfs = [_tf(FRAME_WORLD, FRAME_BASE, t, np.array([x, y, 0.0]), _yaw_quat(yaw))]
        for cam in CAMERA_NAMES:
            c = self.cams[cam]
            tfs.append(_tf(FRAME_BASE, camera_frame_id(cam), t, c["T"][:3, 3], c["q"]))
        out.append((TOPIC_TF, FrameTransforms(transforms=tfs).SerializeToString()))
        pose = PoseInFrame(timestamp=_stamp(t), frame_id=FRAME_WORLD,
                           pose=Pose(position=Vector3(x=x, y=y, z=0.0), orientation=_yaw_quat(yaw)))
        out.append((TOPIC_ROBOT_POSE, pose.SerializeToString()))
        gx, gy = (float(v) for v in fr.goal_xy[:2])
        goal = PoseInFrame(timestamp=_stamp(t), frame_id=FRAME_WORLD,
                           pose=Pose(position=Vector3(x=gx, y=gy, z=0.0), orientation=Quaternion(w=1.0)))
        out.append((TOPIC_GOAL, goal.SerializeToString()))
        out.append((TOPIC_PEDS_SCENE, self._scene(fr, t).SerializeToString()))
        robot = {"step": int(fr.step), "state": enc_array(fr.state), "odom": enc_array(fr.odom),
                 "action": enc_array(fr.action), "goal_xy": enc_array(fr.goal_xy)}
        if getattr(fr, "label", None) is not None:
            robot["label"] = enc_array(np.asarray(fr.label, dtype=np.float32))
        peds = {"pos": enc_array(fr.ped_pos), "vel": enc_array(fr.ped_vel), "radius": enc_array(fr.ped_radius),
                "yaw": enc_array(fr.ped_yaw), "intent_xy": enc_array(fr.ped_intent_xy),
                "keypoints": enc_array(fr.ped_keypoints)}
        det = {"poses": enc_array(fr.poses), "mask": enc_array(fr.pose_mask),
               "confidence": enc_array(fr.pose_conf), "track": enc_array(fr.pose_track)}
        rew = {"reward": enc_float(fr.reward), "terms": {str(k): enc_float(v) for k, v in fr.reward_terms.items()},
               "d_o": enc_float(fr.d_o), "done": bool(fr.done), "outcome": str(fr.outcome)}
        for topic, obj in ((TOPIC_ROBOT, robot), (TOPIC_PEDS, peds), (TOPIC_DETECTIONS, det), (TOPIC_REWARD, rew)):
            out.append((topic, dumps(obj)))
        return out

    def _keypoints(self, fr: Frame, cam: str, t: int) -> ImageAnnotations:
        """Detected joints (robot frame) projected into camera ``cam``: one POINTS annotation per detection."""
        c = self.cams[cam]
        poses = np.asarray(fr.poses, dtype=np.float64)
        ann = ImageAnnotations()
        if poses.size == 0:
            return ann
        r, tr = c["T"][:3, :3], c["T"][:3, 3]
        p_cam = (poses - tr) @ r  # K x 17 x 3: p_cam = R^T (p_base - t), T maps camera (OpenCV) → base
        z = p_cam[..., 2]
        zs = np.where(z > 1e-6, z, 1.0)
        u = c["K"][0, 0] * p_cam[..., 0] / zs + c["K"][0, 2]
        v = c["K"][1, 1] * p_cam[..., 1] / zs + c["K"][1, 2]
        ok = np.asarray(fr.pose_mask, bool) & (z > 0.05) & (u >= 0) & (u < c["w"]) & (v >= 0) & (v < c["h"])
        stamp = _stamp(t)
        for k in np.flatnonzero(ok.any(axis=1)).tolist():
            track = int(fr.pose_track[k])
            pa = ann.points.add()
            pa.timestamp.CopyFrom(stamp)
            pa.type = PointsAnnotation.POINTS
            pa.thickness = 3.0
            pa.outline_color.CopyFrom(_TRACK_COLORS[track % len(_TRACK_COLORS)] if track >= 0 else _WHITE)
            for x, y in zip(u[k][ok[k]].tolist(), v[k][ok[k]].tolist(), strict=True):
                pt = pa.points.add()
                pt.x, pt.y = x, y
        return ann

    def _scene(self, fr: Frame, t: int) -> SceneUpdate:
        """One entity per pedestrian: a body cylinder of its radius and an arrow along its head yaw."""
        upd = SceneUpdate()
        kp = np.asarray(fr.ped_keypoints, dtype=np.float64)
        heights = kp[:, :, 2].max(axis=1) if kp.ndim == 3 and kp.shape[1] else np.full(len(fr.ped_pos), 1.7)
        heights = np.where(np.isfinite(heights) & (heights > 0.3), heights, 1.7)
        stamp = _stamp(t)
        for i, (x, y, r, head_yaw, h) in enumerate(zip(
                fr.ped_pos[:, 0].tolist(), fr.ped_pos[:, 1].tolist(), fr.ped_radius.tolist(),
                fr.ped_yaw[:, 2].tolist(), heights.tolist(), strict=True)):
            e = upd.entities.add()
            e.timestamp.CopyFrom(stamp)
            e.frame_id = FRAME_WORLD
            e.id = f"ped{i}"
            c = e.cylinders.add()
            c.pose.position.x, c.pose.position.y, c.pose.position.z = x, y, h / 2
            c.pose.orientation.w = 1.0
            c.size.x, c.size.y, c.size.z = 2 * r, 2 * r, h
            c.bottom_scale = c.top_scale = 1.0
            c.color.CopyFrom(_BODY_COLOR)
            a = e.arrows.add()
            a.pose.position.x, a.pose.position.y, a.pose.position.z = x, y, h
            a.pose.orientation.z, a.pose.orientation.w = math.sin(head_yaw / 2), math.cos(head_yaw / 2)
            a.shaft_length, a.shaft_diameter, a.head_length, a.head_diameter = 0.4, 0.04, 0.12, 0.1
            a.color.CopyFrom(_HEAD_COLOR)
        return upd

    def grid(self, occupancy: np.ndarray) -> bytes:
        """The static occupancy as a foxglove.Grid (uint8 0 = free, 100 = obstacle; pose at the grid corner)."""
        m = self.meta
        occ = np.asarray(occupancy, dtype=bool)
        h, w = occ.shape
        res = float(m.occupancy_resolution_m)
        ox, oy = (float(v) - res / 2 for v in m.occupancy_origin_xy)  # meta has the centre of cell [0, 0]
        g = Grid(timestamp=_stamp(0), frame_id=FRAME_WORLD,
                 pose=Pose(position=Vector3(x=ox, y=oy, z=0.0), orientation=Quaternion(w=1.0)),
                 column_count=w, cell_size=Vector2(x=res, y=res), row_stride=w, cell_stride=1,
                 fields=[PackedElementField(name="occupancy", offset=0, type=PackedElementField.UINT8)],
                 data=(occ.astype(np.uint8) * 100).tobytes())
        return g.SerializeToString()


# --------------------------------------------------------------------------------------------------------------
# messages → frame


def _decode_image(data: bytes, encoding: str, dtype: type, channels: int) -> np.ndarray:
    img = RawImage()
    img.ParseFromString(data)
    if img.encoding != encoding:
        raise ValueError(f"image encoding {img.encoding!r}, expected {encoding!r}")
    itemsize = np.dtype(dtype).itemsize
    if img.step != img.width * channels * itemsize or len(img.data) != img.step * img.height:
        raise ValueError(f"image {img.width}x{img.height} step {img.step} does not match {len(img.data)} bytes")
    shape = (img.height, img.width, channels) if channels > 1 else (img.height, img.width)
    return np.frombuffer(img.data, dtype=np.dtype(dtype).newbyteorder("<")).reshape(shape).astype(dtype)


def decode_grid(data: bytes, shape: list[int]) -> np.ndarray:
    """The foxglove.Grid of :meth:`FrameEncoder.grid` → ``H x W`` bool occupancy (ValueError if not ``shape``)."""
    g = Grid()
    g.ParseFromString(data)
    h, w = shape
    if g.column_count != w or g.cell_stride != 1 or g.row_stride != w or len(g.data) != h * w:
        raise ValueError(f"occupancy grid {g.column_count} columns, {len(g.data)} bytes does not match "
                         f"meta.occupancy_shape {shape}")
    return np.frombuffer(g.data, dtype=np.uint8).reshape(h, w) > 0


def decode_frame(msgs: dict[str, bytes], t_ns: int) -> Frame:
    """Builds a :class:`Frame` from the payloads of one complete frame (topic → bytes).

    Raises:
        KeyError, ValueError, DecodeError: a payload is missing or malformed (callers wrap these).
    """
    rgb: dict[str, np.ndarray] = {}
    depth: dict[str, np.ndarray] = {}
    for cam in CAMERA_NAMES:
        rgb[cam] = _decode_image(msgs[TOPIC_RGB.format(cam=cam)], "rgb8", np.uint8, 3)
        depth[cam] = depth_from_mm(_decode_image(msgs[TOPIC_DEPTH.format(cam=cam)], "16UC1", np.uint16, 1))
    robot = json.loads(msgs[TOPIC_ROBOT])
    peds = json.loads(msgs[TOPIC_PEDS])
    det = json.loads(msgs[TOPIC_DETECTIONS])
    rew = json.loads(msgs[TOPIC_REWARD])
    if not isinstance(robot["step"], int) or not isinstance(rew["done"], bool) or not isinstance(rew["outcome"], str):
        raise ValueError("step/done/outcome have the wrong JSON types")
    return Frame(
        step=robot["step"], t_ns=int(t_ns), rgb=rgb, depth=depth,
        state=dec_array(robot["state"]), odom=dec_array(robot["odom"]), action=dec_array(robot["action"]),
        goal_xy=dec_array(robot["goal_xy"]),
        poses=dec_array(det["poses"]), pose_mask=dec_array(det["mask"]), pose_conf=dec_array(det["confidence"]),
        pose_track=dec_array(det["track"]),
        ped_pos=dec_array(peds["pos"]), ped_vel=dec_array(peds["vel"]), ped_radius=dec_array(peds["radius"]),
        ped_yaw=dec_array(peds["yaw"]), ped_intent_xy=dec_array(peds["intent_xy"]),
        ped_keypoints=dec_array(peds["keypoints"]),
        reward=dec_float(rew["reward"]), reward_terms={str(k): dec_float(v) for k, v in rew["terms"].items()},
        d_o=dec_float(rew["d_o"]), done=rew["done"], outcome=rew["outcome"],
        label=dec_array(robot["label"]) if "label" in robot else None,
    )
