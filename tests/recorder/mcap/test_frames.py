"""Tests of recorder.mcap.frames: Foxglove and JSON schemas per channel, /tf, 2D keypoints, calibration."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from mcap.reader import make_reader

from recorder.mcap.frames import quat_to_rot
from recorder.mcap.layout import LIBRARY
from recorder.schema import CAMERA_NAMES, METADATA_EPISODE, TOPIC_CALIB, TOPIC_DEPTH, TOPIC_KEYPOINTS_2D


def test_channels_use_foxglove_schemas_and_json_schemas(episode, recorded: Path) -> None:
    meta, _, frames = episode
    with open(recorded, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        header = reader.get_header()
        summ = reader.get_summary()
        schema_of = {ch.topic: summ.schemas[ch.schema_id] for ch in summ.channels.values()}
        enc_of = {ch.topic: ch.message_encoding for ch in summ.channels.values()}
        md = {m.name: m.metadata for m in reader.iter_metadata()}
        msgs = {(ch.topic, m.log_time): m.data for _, ch, m in reader.iter_messages()}
    assert header.library == LIBRARY  # constant: no version or time in the header
    assert md[METADATA_EPISODE] == meta.to_metadata()
    for cam in CAMERA_NAMES:
        assert schema_of[f"/camera/{cam}/image"].name == "foxglove.RawImage"
        assert schema_of[f"/camera/{cam}/depth"].name == "foxglove.RawImage"
        assert schema_of[f"/camera/{cam}/calibration"].name == "foxglove.CameraCalibration"
        assert schema_of[f"/camera/{cam}/keypoints"].name == "foxglove.ImageAnnotations"
    assert schema_of["/tf"].name == "foxglove.FrameTransforms"
    assert schema_of["/robot/pose"].name == schema_of["/robot/goal"].name == "foxglove.PoseInFrame"
    assert schema_of["/pedestrians/scene"].name == "foxglove.SceneUpdate"
    assert schema_of["/map/occupancy"].name == "foxglove.Grid"
    for topic in ("/robot/state", "/pedestrians/state", "/perception/poses", "/episode/reward"):
        assert enc_of[topic] == "json" and schema_of[topic].encoding == "jsonschema"
        js = json.loads(schema_of[topic].data)
        payload = json.loads(msgs[(topic, 0)])
        assert js["type"] == "object" and set(js["required"]) == set(payload)

    # /tf: base_link -> camera_<cam> is T_base_cam (camera in OpenCV axes), world -> base_link is the odometry
    k = 7
    tfs = FrameTransforms()
    tfs.ParseFromString(msgs[("/tf", frames[k].t_ns)])
    by_child = {t.child_frame_id: t for t in tfs.transforms}
    x, y, yaw = frames[k].odom.astype(np.float64)
    wb = by_child["base_link"]
    assert wb.parent_frame_id == "world"
    assert (wb.translation.x, wb.translation.y) == pytest.approx((x, y))
    assert quat_to_rot(wb.rotation)[:2, :2] == pytest.approx(
        np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]), abs=1e-9)
    for cam in CAMERA_NAMES:
        tbc = np.asarray(meta.cameras[cam]["T_base_cam"])
        t = by_child[f"camera_{cam}"]
        assert t.parent_frame_id == "base_link"
        assert quat_to_rot(t.rotation) == pytest.approx(tbc[:3, :3], abs=1e-9)
        assert [t.translation.x, t.translation.y, t.translation.z] == pytest.approx(tbc[:3, 3])

    # 2D keypoints: every drawn point is a detected joint projected with K and T_base_cam, inside the image
    drawn = 0
    for fr in frames:
        for cam in CAMERA_NAMES:
            ann = ImageAnnotations()
            ann.ParseFromString(msgs[(TOPIC_KEYPOINTS_2D.format(cam=cam), fr.t_ns)])
            spec = meta.cameras[cam]
            kmat, tbc = np.asarray(spec["K"]), np.asarray(spec["T_base_cam"])
            pc = (fr.poses[fr.pose_mask].astype(np.float64) - tbc[:3, 3]) @ tbc[:3, :3]
            uv = pc[:, :2] / pc[:, 2:] * np.diag(kmat)[:2] + kmat[:2, 2]
            ok = (pc[:, 2] > 0.05) & (uv[:, 0] >= 0) & (uv[:, 0] < spec["width"]) & (uv[:, 1] >= 0) & \
                 (uv[:, 1] < spec["height"])
            pts = np.array([(p.x, p.y) for pa in ann.points for p in pa.points]).reshape(-1, 2)
            assert len(pts) == ok.sum()
            if len(pts):
                assert np.allclose(np.sort(pts, axis=0), np.sort(uv[ok], axis=0))
            drawn += len(pts)
    assert drawn > 0
    # calibration on every frame, depth channel metadata says millimetres
    assert sum(1 for (t, _) in msgs if t == TOPIC_CALIB.format(cam="left")) == len(frames)
    assert summ.channels[next(c for c, ch in summ.channels.items()
                              if ch.topic == TOPIC_DEPTH.format(cam="left"))].metadata["unit"] == "mm"
