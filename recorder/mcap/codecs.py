"""Codecs of the message payloads: JSON arrays and floats, the JSON schemas, the protobuf type of each topic,
depth in millimetres.

Arrays in the JSON topics are ``{"dtype": "float32", "shape": [N, 2], "data": [...]}`` (row-major); float32
values are written with 9 significant digits, which round-trips bit-exactly through a float64 parse (see
``enc_array``), float64 values with their repr; non-finite floats are the strings ``"inf"``, ``"-inf"``,
``"nan"`` (the JSON stays strict). Depth is the one lossy field: metres are
rounded to whole millimetres (error ≤ 0.5 mm), values ≤ 0 or non-finite become 0 (invalid), values above
65.535 m saturate at 65535 mm (the cameras' range ends at 10 m).
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Grid_pb2 import Grid
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

from recorder import schema
from recorder.schema import CAMERA_NAMES

_ARRAY_DTYPES = ("float32", "float64", "int64", "int32", "uint8", "bool")
_NONFINITE = {"inf": math.inf, "-inf": -math.inf, "nan": math.nan}


def enc_float(v: float) -> float | str:
    """A float for JSON: itself if finite, else ``"inf"``, ``"-inf"`` or ``"nan"``."""
    v = float(v)
    if math.isfinite(v):
        return v
    return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")


def dec_float(v: Any) -> float:
    """The inverse of :func:`enc_float` (raises ValueError on anything but a number or those strings)."""
    if isinstance(v, str):
        return _NONFINITE[v]
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ValueError(f"expected a number, got {v!r}")
    return float(v)


class _RawJSON(str):
    """Pre-formatted JSON text, inserted verbatim by :func:`dumps`."""


_F32 = "%.9g".__mod__  # 9 significant digits identify a float32 exactly (see enc_array)


def _fmt_float(v: float, fmt: Any) -> str:
    """One float as JSON, keeping the sign of zero ('%.9g' writes -0.0 as -0, which parses as the int 0)."""
    if v == 0.0:
        return "-0.0" if math.copysign(1.0, v) < 0 else "0"
    return fmt(v) if math.isfinite(v) else f'"{enc_float(v)}"'


def enc_array(a: np.ndarray) -> _RawJSON:
    """An array as JSON ``{"dtype", "shape", "data"}`` (row-major), exact for every dtype.

    float32 values are written with 9 significant digits: the decimal lies within 5e-9 (relative) of the float32,
    far inside its rounding interval (≥ 2^-25 relative), so parsing it as a float64 and casting to float32 gives
    back the identical float32 (no double rounding). That is 2.3x faster to format than the float64 repr and
    shorter. float64 values use ``repr`` (shortest exact); non-finite floats are ``"inf"``/``"-inf"``/``"nan"``.
    """
    a = np.asarray(a)
    name = a.dtype.name
    if name not in _ARRAY_DTYPES:
        raise ValueError(f"cannot log arrays of dtype {a.dtype} (supported: {', '.join(_ARRAY_DTYPES)})")
    vals = a.ravel().tolist()
    if a.dtype.kind == "f":
        fmt = _F32 if name == "float32" else repr
        if np.isfinite(a).all() and not (np.signbit(a) & (a == 0)).any():
            data = ",".join(map(fmt, vals))
        else:
            data = ",".join(_fmt_float(v, fmt) for v in vals)
    else:
        data = json.dumps(vals, separators=(",", ":"))[1:-1]
    return _RawJSON(f'{{"dtype":"{name}","shape":{json.dumps(list(a.shape))},"data":[{data}]}}')


def dumps(obj: dict[str, Any]) -> bytes:
    """A flat dict as compact strict JSON, with :class:`_RawJSON` values inserted verbatim."""
    parts = [json.dumps(k) + ":" + (v if isinstance(v, _RawJSON) else
                                    json.dumps(v, allow_nan=False, separators=(",", ":")))
             for k, v in obj.items()]
    return ("{" + ",".join(parts) + "}").encode()


def dec_array(d: dict) -> np.ndarray:
    """The inverse of :func:`enc_array` (from the parsed JSON dict); ValueError on a malformed array."""
    dtype, shape, data = d["dtype"], d["shape"], d["data"]
    if dtype not in _ARRAY_DTYPES:
        raise ValueError(f"array dtype {dtype!r} not one of {_ARRAY_DTYPES}")
    if not isinstance(shape, list) or not all(isinstance(s, int) and s >= 0 for s in shape):
        raise ValueError(f"array shape {shape!r} is not a list of sizes")
    if dtype in ("float32", "float64"):
        data = [dec_float(v) for v in data] if any(isinstance(v, str) for v in data) else data
        arr = np.array(data, dtype=np.float64).astype(dtype)
    else:
        arr = np.array(data, dtype=dtype)
    if arr.size != math.prod(shape):
        raise ValueError(f"array of shape {shape} has {arr.size} values")
    return arr.reshape(shape)


def _json_schema(title: str, properties: dict[str, dict], optional: tuple[str, ...] = ()) -> bytes:
    return json.dumps({"$schema": "https://json-schema.org/draft/2020-12/schema", "title": title,
                       "type": "object", "properties": properties,
                       "required": [k for k in properties if k not in optional],
                       "additionalProperties": False}, indent=None, sort_keys=False).encode()


def _array_prop(dtype: str, shape: str, unit: str) -> dict:
    return {"type": "object", "description": f"{dtype} array {shape}, {unit}; row-major values in data",
            "properties": {"dtype": {"type": "string", "enum": list(_ARRAY_DTYPES)},
                           "shape": {"type": "array", "items": {"type": "integer", "minimum": 0}},
                           "data": {"type": "array",
                                    "items": {"type": ["number", "integer", "boolean", "string"]}}},
            "required": ["dtype", "shape", "data"], "additionalProperties": False}


_NUM = {"type": ["number", "string"], "description": "float; non-finite values as \"inf\", \"-inf\", \"nan\""}
JSON_SCHEMAS: dict[str, tuple[str, bytes]] = {
    schema.TOPIC_ROBOT: ("icrowdnav.RobotState", _json_schema("icrowdnav.RobotState", {
        "step": {"type": "integer", "minimum": 0, "description": "0 = after reset, k = after the k-th action"},
        "state": _array_prop("float32", "5", "[g_x, g_y, d_g, v_x, v_y], robot frame, m and m/s"),
        "odom": _array_prop("float32", "3", "[x m, y m, yaw rad], world frame"),
        "action": _array_prop("float32", "2", "[v m/s, omega rad/s] that led to this frame"),
        "goal_xy": _array_prop("float32", "2", "goal, world frame, m"),
        "label": _array_prop("float32", "2", "optional: the labeller's (DAgger teacher's) [v m/s, omega rad/s] "
                             "for this frame's observation"),
    }, optional=("label",))),
    schema.TOPIC_PEDS: ("icrowdnav.PedestrianState", _json_schema("icrowdnav.PedestrianState", {
        "pos": _array_prop("float32", "N x 2", "positions, world frame, m"),
        "vel": _array_prop("float32", "N x 2", "velocities, world frame, m/s"),
        "radius": _array_prop("float32", "N", "body disc radii, m"),
        "yaw": _array_prop("float32", "N x 3", "body, torso, head yaw, world frame, rad"),
        "intent_xy": _array_prop("float32", "N x 2", "pending goals, world frame, m"),
        "keypoints": _array_prop("float32", "N x 17 x 3", "true COCO-17 keypoints, world frame, m"),
    })),
    schema.TOPIC_DETECTIONS: ("icrowdnav.PoseDetections", _json_schema("icrowdnav.PoseDetections", {
        "poses": _array_prop("float32", "K x 17 x 3", "detected COCO-17 joints, robot frame, m"),
        "mask": _array_prop("bool", "K x 17", "joint detected"),
        "confidence": _array_prop("float32", "K x 17", "detector confidence in [0, 1]"),
        "track": _array_prop("int64", "K", "true pedestrian index, -1 = padding"),
    })),
    schema.TOPIC_REWARD: ("icrowdnav.Reward", _json_schema("icrowdnav.Reward", {
        "reward": _NUM,
        "terms": {"type": "object", "additionalProperties": _NUM, "description": "reward terms by name"},
        "d_o": {**_NUM, "description": "robot centre to nearest pedestrian/obstacle surface, m"},
        "done": {"type": "boolean"},
        "outcome": {"type": "string", "description": "empty while running; success / collision_* / timeout"},
    })),
}

PROTO_TYPES: dict[str, type] = {schema.TOPIC_TF: FrameTransforms, schema.TOPIC_ROBOT_POSE: PoseInFrame, schema.TOPIC_GOAL: PoseInFrame,
                                schema.TOPIC_PEDS_SCENE: SceneUpdate, schema.TOPIC_OCCUPANCY: Grid}
for _c in CAMERA_NAMES:
    PROTO_TYPES |= {schema.TOPIC_RGB.format(cam=_c): RawImage, schema.TOPIC_DEPTH.format(cam=_c): RawImage,
                    schema.TOPIC_CALIB.format(cam=_c): CameraCalibration, schema.TOPIC_KEYPOINTS_2D.format(cam=_c): ImageAnnotations}


def expected_schema_name(topic: str) -> str:
    """The schema name the writer uses for ``topic`` (``foxglove.RawImage``, ``icrowdnav.RobotState``, ...)."""
    if topic in JSON_SCHEMAS:
        return JSON_SCHEMAS[topic][0]
    return PROTO_TYPES[topic].DESCRIPTOR.full_name


