"""Per-episode MCAP logs: writing, reading, scanning and salvaging.

One episode is one MCAP file. :class:`EpisodeWriter` writes it, :class:`EpisodeReader` / :func:`read_episode`
read it back into :class:`recorder.schema.Frame` objects, :func:`scan_episode` / :func:`episode_summary` /
:func:`count_frames` inspect it cheaply, and :func:`recover` salvages the complete frames of a recording that was
killed. :func:`graceful_signals` turns SIGTERM/SIGINT into an :class:`Interrupted` exception so that writers
are closed cleanly (the writer itself installs no signal handler).

::

    python -m recorder.mcap_io recover data/raw/expert/hallway_d0.1_s3.mcap.partial
    python -m recorder.mcap_io summary data/raw/expert/hallway_d0.1_s3.mcap
    python -m recorder.mcap_io bench                       # the chunking/compression measurement below

File layout (log time = publish time = ``frame.t_ns``, simulation time; no wall clock anywhere, so the same
seed and config give byte-identical files)::

    magic, Header(profile="", library=LIBRARY)
    Metadata "episode"       EpisodeMeta.to_metadata(), written right after the header (survives a kill)
    Chunk 0                  Schema + Channel records of every topic, the grid, then the messages of frames 0..k
    MessageIndex ...
    Chunk 1 ...              whole frames only: chunks are cut at frame boundaries, never inside a frame
    [Metadata "aborted"]     only in a ``*.partial`` closed after an exception (see EpisodeWriter)
    DataEnd(data CRC), summary (schemas, channels, statistics, chunk/metadata indexes), Footer, magic

Topics of every frame (``recorder.schema`` names them; ``cam`` in ``CAMERA_NAMES``):

===========================  ==========================  ====================================================
topic                        schema                      content
===========================  ==========================  ====================================================
/camera/{cam}/image          foxglove.RawImage           ``rgb8``, H x W x 3, frame_id ``camera_{cam}``
/camera/{cam}/depth          foxglove.RawImage           ``16UC1`` little-endian z-depth in mm, 0 = invalid
/camera/{cam}/calibration    foxglove.CameraCalibration  K, P = [K | 0], R = I, no distortion; every frame
/camera/{cam}/keypoints      foxglove.ImageAnnotations   detected joints (``frame.poses``) projected, display
/tf                          foxglove.FrameTransforms    world→base_link (odom), base_link→camera_{cam}
/robot/pose, /robot/goal     foxglove.PoseInFrame        world frame (goal: identity orientation)
/pedestrians/scene           foxglove.SceneUpdate        per pedestrian a cylinder (radius) + head arrow
/robot/state                 json (jsonschema)           step, state, odom, action, goal_xy[, label]
/pedestrians/state           json (jsonschema)           pos, vel, radius, yaw, intent_xy, keypoints
/perception/poses            json (jsonschema)           poses, mask, confidence, track
/episode/reward              json (jsonschema)           reward, terms, d_o, done, outcome
/map/occupancy               foxglove.Grid               static occupancy (uint8 0/100), only at t = 0
===========================  ==========================  ====================================================

Calibration is repeated every frame (about 0.3 kB) so that every frame carries the same topic set and a viewer
can start anywhere; the occupancy grid (tens of kB) is logged once. A *frame* is the set of messages with one
log time; it is complete when it has all topics above (plus ``/map/occupancy`` at t = 0).

Arrays in the JSON topics are ``{"dtype": "float32", "shape": [N, 2], "data": [...]}`` (row-major); float32
values are written with 9 significant digits, which round-trips bit-exactly through a float64 parse (see
``_enc_array``), float64 values with their repr; non-finite floats are the strings ``"inf"``, ``"-inf"``,
``"nan"`` (the JSON stays strict). Depth is the one lossy field: metres are
rounded to whole millimetres (error ≤ 0.5 mm), values ≤ 0 or non-finite become 0 (invalid), values above
65.535 m saturate at 65535 mm (the cameras' range ends at 10 m).

Chunking and compression were chosen by measuring (``python -m recorder.mcap_io bench --density D``): a realistic
160 x 120 episode of office_lobby, frames rendered first and then written from memory, so only MCAP work is
timed; the fastest of 7 interleaved runs per setting on the development machine (2 cores shared with other jobs,
so ±20 % noise). A frame is ~192 kB of raw images (+ ~17 kB JSON/protobuf); the budget is MCAP ≤ 15 % of a
recording step, of which rendering alone is ~20 ms::

                      0.1 ped/m² (9 peds, 92 frames)     0.2 ped/m² (18 peds, 101 frames)
    compression chunk ms/frame kB/frame % of 20 ms       ms/frame kB/frame % of 20 ms
    zstd        1 MiB   1.70     15.0      8.5             2.62     22.4     13.1
    zstd        4 MiB   1.39     14.9      6.9             2.15     22.3     10.7
    lz4         1 MiB   1.28     24.8      6.4             2.16     36.8     10.8
    lz4         4 MiB   1.28     24.8      6.4             1.99     36.7      9.9
    none        1 MiB   1.65    209.1      8.2             2.38    218.5     11.9
    none        4 MiB   1.64    209.0      8.2             2.38    218.4     11.9

Sim + rendering took 22.2 and 25.4 ms per step in the same runs, so zstd/1 MiB is 7 % and 9 % of a whole
recording step. Most of the MCAP time (~1.1-1.6 ms) is encoding (protobuf, JSON, depth to mm, 2D keypoints) and
is the same for every setting; "none" is not faster because it writes 9-14x more bytes.

Chosen: zstd (level 3, the mcap default) with 1 MiB chunks. It stays within the budget, and its files are
1.6x smaller than lz4's and 9-14x smaller than uncompressed ones. 4 MiB chunks compress no better (< 1 %) and
their small speed edge is within the noise, but a SIGKILL loses the whole open chunk: ≤ 6 frames (0.6 s) at
1 MiB against ≤ 21 frames at 4 MiB.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import logging
import math
import os
import signal
import struct
import sys
import threading
import time
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType, TracebackType
from typing import Any, Literal

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
from google.protobuf.message import DecodeError
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import register_schema

from pipeline.core.artifacts import fsync_dir
from pipeline.core.errors import CorruptArtifactError, InputMissingError, OutputExistsError
from recorder.schema import (
    CAMERA_NAMES,
    FRAME_BASE,
    FRAME_WORLD,
    METADATA_EPISODE,
    TOPIC_CALIB,
    TOPIC_DEPTH,
    TOPIC_DETECTIONS,
    TOPIC_GOAL,
    TOPIC_KEYPOINTS_2D,
    TOPIC_OCCUPANCY,
    TOPIC_PEDS,
    TOPIC_PEDS_SCENE,
    TOPIC_REWARD,
    TOPIC_RGB,
    TOPIC_ROBOT,
    TOPIC_ROBOT_POSE,
    TOPIC_TF,
    EpisodeMeta,
    Frame,
)

log = logging.getLogger("icrowdnav")

LIBRARY = "icrowdnav recorder.mcap_io/1"  # MCAP header library string: constant, so files are reproducible
DEFAULT_CHUNK_SIZE = 1 << 20  # uncompressed bytes per chunk (cut at the next frame boundary); see module doc
DEFAULT_COMPRESSION = "zstd"
COMPRESSIONS: dict[str, CompressionType] = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                                            "none": CompressionType.NONE}
METADATA_ABORTED = "aborted"  # metadata record of a *.partial closed after an exception
METADATA_RECOVERY = "recovery"  # metadata record of a file written by recover()
PARTIAL_SUFFIX = ".partial"
DEPTH_SCALE_M = 0.001  # metres per depth count (16UC1)

MAGIC = b"\x89MCAP0\r\n"
_FOOTER_RECORD_SIZE = 1 + 8 + 8 + 8 + 4  # opcode, length, summary_start, summary_offset_start, summary_crc
_DATA_END_RECORD_SIZE = 1 + 8 + 4
_ARRAY_DTYPES = ("float32", "float64", "int64", "int32", "uint8", "bool")
_NONFINITE = {"inf": math.inf, "-inf": -math.inf, "nan": math.nan}

# Everything a damaged file can make the mcap/protobuf/json/zstd/lz4 decoders raise. Caught only around decoding
# and re-raised as CorruptMcapError naming the file; any other exception is a bug and propagates.
_DECODE_ERRORS: tuple[type[BaseException], ...] = (McapError, struct.error, ValueError, KeyError, IndexError,
                                                   EOFError, DecodeError, OverflowError, MemoryError,
                                                   UnicodeDecodeError, RuntimeError, TypeError)
try:  # zstandard.ZstdError derives from Exception only
    import zstandard

    _DECODE_ERRORS = (*_DECODE_ERRORS, zstandard.ZstdError)
except ImportError:  # pragma: no cover - zstandard is a dependency of mcap here
    pass


class CorruptMcapError(CorruptArtifactError):
    """An episode MCAP exists but is truncated, fails a CRC check or does not hold a well-formed episode.

    Attributes:
        path: The file.
        offset: Byte offset of the damaged record where known, else None.
    """

    def __init__(self, path: Path | str, what: str, offset: int | None = None) -> None:
        self.path = Path(path)
        self.offset = offset
        where = f" at byte offset {offset}" if offset is not None else ""
        super().__init__(f"{self.path}: {what}{where}")


# --------------------------------------------------------------------------------------------------------------
# signals


class Interrupted(KeyboardInterrupt):  # noqa: N818 - named like KeyboardInterrupt, which it extends
    """SIGTERM or SIGINT arrived inside :func:`graceful_signals`.

    Derives from :class:`KeyboardInterrupt` so that ``except Exception`` does not swallow it and code that already
    handles Ctrl-C handles SIGTERM the same way.

    Attributes:
        signum: The signal number.
        exit_code: ``128 + signum``, the conventional exit status after that signal.
    """

    def __init__(self, signum: int) -> None:
        self.signum = int(signum)
        self.exit_code = 128 + self.signum
        super().__init__(f"interrupted by {signal.Signals(signum).name}")


_tls = threading.local()  # per thread: depth of _critical() blocks and a deferred signal


@contextlib.contextmanager
def _critical() -> Iterator[None]:
    """A block that :func:`graceful_signals` does not interrupt: a signal arriving inside it is raised on exit.

    The writer marks its calls into the mcap library with this, so that SIGTERM/SIGINT never tear a chunk or the
    summary in half: the frame being added (or the finish in progress) completes first.
    """
    _tls.depth = getattr(_tls, "depth", 0) + 1
    try:
        yield
    except BaseException as e:
        _tls.depth -= 1
        pending = getattr(_tls, "pending", None)
        if _tls.depth == 0 and pending is not None:
            _tls.pending = None
            raise Interrupted(pending) from e
        raise
    _tls.depth -= 1
    pending = getattr(_tls, "pending", None)
    if _tls.depth == 0 and pending is not None:
        _tls.pending = None
        raise Interrupted(pending)


@contextlib.contextmanager
def graceful_signals(signums: tuple[int, ...] = (signal.SIGTERM, signal.SIGINT)) -> Iterator[None]:
    """Converts SIGTERM/SIGINT into an :class:`Interrupted` exception raised in the main thread.

    The exception unwinds the ``with`` blocks in flight, so an :class:`EpisodeWriter` closes its file as a valid
    ``*.partial`` (finished episodes are already final) and the caller can log what is complete and exit with
    ``exc.exit_code``. A signal that arrives while the writer is inside the mcap library (adding a frame,
    finishing) is deferred until that call returns, so no chunk is torn. The first signal raises; further signals
    while unwinding are logged and ignored, so cleanup is not cut short (SIGKILL still works). Previous handlers
    are restored on exit. Outside the main thread (where Python cannot install handlers) this is a no-op.

    The writer installs no handler itself: recording code wraps its loop in this context manager, e.g.::

        try:
            with graceful_signals():
                record_all()
        except Interrupted as e:
            log.warning("stopped by %s; finished episodes are complete", signal.Signals(e.signum).name)
            return e.exit_code

    Args:
        signums: The signals to convert.

    Yields:
        Nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    fired: list[int] = []

    def handler(signum: int, frame: FrameType | None) -> None:
        name = signal.Signals(signum).name
        if fired:
            log.warning("%s received while already stopping; finishing cleanup first", name)
            return
        fired.append(signum)
        if getattr(_tls, "depth", 0) > 0:  # the handler runs in the main thread: this is its state
            log.warning("received %s: stopping once the current MCAP write completes", name)
            _tls.pending = signum
            return
        log.warning("received %s: stopping (open episode files are closed as *.partial)", name)
        raise Interrupted(signum)

    previous = {s: signal.signal(s, handler) for s in signums}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


# --------------------------------------------------------------------------------------------------------------
# small helpers


def frame_topics(first: bool = False) -> tuple[str, ...]:
    """The topics a complete frame has (in the writer's order, except that it logs ``/map/occupancy`` first).

    Args:
        first: Whether this is the frame at t = 0 (which also carries ``/map/occupancy``).
    """
    per_cam = tuple(t.format(cam=c) for c in CAMERA_NAMES for t in (TOPIC_RGB, TOPIC_DEPTH, TOPIC_CALIB,
                                                                    TOPIC_KEYPOINTS_2D))
    rest = (TOPIC_TF, TOPIC_ROBOT_POSE, TOPIC_GOAL, TOPIC_PEDS_SCENE, TOPIC_ROBOT, TOPIC_PEDS, TOPIC_DETECTIONS,
            TOPIC_REWARD)
    return per_cam + rest + ((TOPIC_OCCUPANCY,) if first else ())


def camera_frame_id(cam: str) -> str:
    """The TF frame of camera ``cam`` (OpenCV axes: x right, y down, z forward)."""
    return f"camera_{cam}"


def dt_ns_of(meta: EpisodeMeta) -> int:
    """The control period of an episode in integer nanoseconds (= the log-time step between frames)."""
    return int(round(meta.dt_s * 1e9))


def partial_path_of(final_path: Path) -> Path:
    """``<name>.mcap`` → ``<name>.mcap.partial`` (where an episode lives while it is written)."""
    return Path(final_path).with_suffix(".mcap" + PARTIAL_SUFFIX)


def recovered_path_of(partial_path: Path) -> Path:
    """``<name>.mcap.partial`` (or ``<name>.mcap``) → ``<name>.recovered.mcap``."""
    p = Path(partial_path)
    name = p.name
    for suffix in (PARTIAL_SUFFIX, ".mcap"):
        if name.endswith(suffix):
            name = name[: -len(suffix)]
    return p.with_name(name + ".recovered.mcap")


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


def _enc_float(v: float) -> float | str:
    v = float(v)
    if math.isfinite(v):
        return v
    return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")


def _dec_float(v: Any) -> float:
    if isinstance(v, str):
        return _NONFINITE[v]
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ValueError(f"expected a number, got {v!r}")
    return float(v)


class _RawJSON(str):
    """Pre-formatted JSON text, inserted verbatim by :func:`_dumps`."""


_F32 = "%.9g".__mod__  # 9 significant digits identify a float32 exactly (see _enc_array)


def _fmt_float(v: float, fmt: Any) -> str:
    """One float as JSON, keeping the sign of zero ('%.9g' writes -0.0 as -0, which parses as the int 0)."""
    if v == 0.0:
        return "-0.0" if math.copysign(1.0, v) < 0 else "0"
    return fmt(v) if math.isfinite(v) else f'"{_enc_float(v)}"'


def _enc_array(a: np.ndarray) -> _RawJSON:
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


def _dumps(obj: dict[str, Any]) -> bytes:
    """A flat dict as compact strict JSON, with :class:`_RawJSON` values inserted verbatim."""
    parts = [json.dumps(k) + ":" + (v if isinstance(v, _RawJSON) else
                                    json.dumps(v, allow_nan=False, separators=(",", ":")))
             for k, v in obj.items()]
    return ("{" + ",".join(parts) + "}").encode()


def _dec_array(d: dict) -> np.ndarray:
    dtype, shape, data = d["dtype"], d["shape"], d["data"]
    if dtype not in _ARRAY_DTYPES:
        raise ValueError(f"array dtype {dtype!r} not one of {_ARRAY_DTYPES}")
    if not isinstance(shape, list) or not all(isinstance(s, int) and s >= 0 for s in shape):
        raise ValueError(f"array shape {shape!r} is not a list of sizes")
    if dtype in ("float32", "float64"):
        data = [_dec_float(v) for v in data] if any(isinstance(v, str) for v in data) else data
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
    TOPIC_ROBOT: ("icrowdnav.RobotState", _json_schema("icrowdnav.RobotState", {
        "step": {"type": "integer", "minimum": 0, "description": "0 = after reset, k = after the k-th action"},
        "state": _array_prop("float32", "5", "[g_x, g_y, d_g, v_x, v_y], robot frame, m and m/s"),
        "odom": _array_prop("float32", "3", "[x m, y m, yaw rad], world frame"),
        "action": _array_prop("float32", "2", "[v m/s, omega rad/s] that led to this frame"),
        "goal_xy": _array_prop("float32", "2", "goal, world frame, m"),
        "label": _array_prop("float32", "2", "optional: the labeller's (DAgger teacher's) [v m/s, omega rad/s] "
                             "for this frame's observation"),
    }, optional=("label",))),
    TOPIC_PEDS: ("icrowdnav.PedestrianState", _json_schema("icrowdnav.PedestrianState", {
        "pos": _array_prop("float32", "N x 2", "positions, world frame, m"),
        "vel": _array_prop("float32", "N x 2", "velocities, world frame, m/s"),
        "radius": _array_prop("float32", "N", "body disc radii, m"),
        "yaw": _array_prop("float32", "N x 3", "body, torso, head yaw, world frame, rad"),
        "intent_xy": _array_prop("float32", "N x 2", "pending goals, world frame, m"),
        "keypoints": _array_prop("float32", "N x 17 x 3", "true COCO-17 keypoints, world frame, m"),
    })),
    TOPIC_DETECTIONS: ("icrowdnav.PoseDetections", _json_schema("icrowdnav.PoseDetections", {
        "poses": _array_prop("float32", "K x 17 x 3", "detected COCO-17 joints, robot frame, m"),
        "mask": _array_prop("bool", "K x 17", "joint detected"),
        "confidence": _array_prop("float32", "K x 17", "detector confidence in [0, 1]"),
        "track": _array_prop("int64", "K", "true pedestrian index, -1 = padding"),
    })),
    TOPIC_REWARD: ("icrowdnav.Reward", _json_schema("icrowdnav.Reward", {
        "reward": _NUM,
        "terms": {"type": "object", "additionalProperties": _NUM, "description": "reward terms by name"},
        "d_o": {**_NUM, "description": "robot centre to nearest pedestrian/obstacle surface, m"},
        "done": {"type": "boolean"},
        "outcome": {"type": "string", "description": "empty while running; success / collision_* / timeout"},
    })),
}

_PROTO_TYPES: dict[str, type] = {TOPIC_TF: FrameTransforms, TOPIC_ROBOT_POSE: PoseInFrame, TOPIC_GOAL: PoseInFrame,
                                 TOPIC_PEDS_SCENE: SceneUpdate, TOPIC_OCCUPANCY: Grid}
for _c in CAMERA_NAMES:
    _PROTO_TYPES |= {TOPIC_RGB.format(cam=_c): RawImage, TOPIC_DEPTH.format(cam=_c): RawImage,
                     TOPIC_CALIB.format(cam=_c): CameraCalibration, TOPIC_KEYPOINTS_2D.format(cam=_c): ImageAnnotations}


def expected_schema_name(topic: str) -> str:
    """The schema name the writer uses for ``topic`` (``foxglove.RawImage``, ``icrowdnav.RobotState``, ...)."""
    if topic in JSON_SCHEMAS:
        return JSON_SCHEMAS[topic][0]
    return _PROTO_TYPES[topic].DESCRIPTOR.full_name


def _all_topics() -> tuple[str, ...]:
    return frame_topics(first=True)


# --------------------------------------------------------------------------------------------------------------
# frame → messages


def depth_to_mm(depth_m: np.ndarray) -> np.ndarray:
    """z-depth in metres → uint16 millimetres (round to nearest, ≤ 0 / non-finite → 0, saturates at 65535).

    Args:
        depth_m: ``H x W`` float, m, 0 = invalid.

    Returns:
        ``H x W`` uint16, mm, 0 = invalid.
    """
    d = np.asarray(depth_m, dtype=np.float64)
    mm = np.rint(np.where(np.isfinite(d) & (d > 0), d, 0.0) / DEPTH_SCALE_M)
    return np.clip(mm, 0, 65535).astype(np.uint16)


def depth_from_mm(mm: np.ndarray) -> np.ndarray:
    """uint16 millimetres → float32 metres (0 stays 0 = invalid)."""
    return (np.asarray(mm, dtype=np.float32) * np.float32(DEPTH_SCALE_M)).astype(np.float32)


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


class _Encoder:
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
        robot = {"step": int(fr.step), "state": _enc_array(fr.state), "odom": _enc_array(fr.odom),
                 "action": _enc_array(fr.action), "goal_xy": _enc_array(fr.goal_xy)}
        if getattr(fr, "label", None) is not None:
            robot["label"] = _enc_array(np.asarray(fr.label, dtype=np.float32))
        peds = {"pos": _enc_array(fr.ped_pos), "vel": _enc_array(fr.ped_vel), "radius": _enc_array(fr.ped_radius),
                "yaw": _enc_array(fr.ped_yaw), "intent_xy": _enc_array(fr.ped_intent_xy),
                "keypoints": _enc_array(fr.ped_keypoints)}
        det = {"poses": _enc_array(fr.poses), "mask": _enc_array(fr.pose_mask),
               "confidence": _enc_array(fr.pose_conf), "track": _enc_array(fr.pose_track)}
        rew = {"reward": _enc_float(fr.reward), "terms": {str(k): _enc_float(v) for k, v in fr.reward_terms.items()},
               "d_o": _enc_float(fr.d_o), "done": bool(fr.done), "outcome": str(fr.outcome)}
        for topic, obj in ((TOPIC_ROBOT, robot), (TOPIC_PEDS, peds), (TOPIC_DETECTIONS, det), (TOPIC_REWARD, rew)):
            out.append((topic, _dumps(obj)))
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
# writer


class _FdStream:
    """Unbuffered append-only file stream for the mcap Writer.

    Each ``write`` goes straight to the OS, so every finished chunk is in the file (page cache) as soon as it is
    written and survives a SIGKILL of the process; there is no Python-side buffer to lose.
    """

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.pos = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data)
        while view:
            n = os.write(self.fd, view)
            view = view[n:]
            self.pos += n
        return len(data)

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        pass


def _publish_no_clobber(src: Path, dst: Path) -> None:
    """Atomically gives ``src`` the name ``dst``, failing (OutputExistsError) rather than replacing ``dst``.

    Hard-links ``dst`` to ``src`` (which fails if ``dst`` exists), then unlinks ``src``: a crash in between leaves
    both names on one complete file, which :mod:`recorder.doctor_mcap` reports.
    """
    try:
        os.link(src, dst)
    except FileExistsError:
        raise OutputExistsError(f"{dst} already exists; refusing to overwrite it (the new file is left as {src})") \
            from None
    except OSError as e:  # file systems without hard links: check, then rename (not atomic against a racer)
        if e.errno not in (errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EXDEV, errno.EMLINK):
            raise
        if dst.exists():
            raise OutputExistsError(f"{dst} already exists; refusing to overwrite it") from None
        os.rename(src, dst)
    else:
        os.unlink(src)
    fsync_dir(dst.parent)


WriterState = Literal["new", "open", "finished", "aborted"]


class EpisodeWriter:
    """Writes one episode to ``<name>.mcap`` with an explicit lifecycle: ``start → add* → finish``.

    While open the file is ``<name>.mcap.partial``. :meth:`finish` writes the summary, fsyncs, renames it to the
    final name (never replacing an existing file) and fsyncs the directory. As a context manager the writer starts
    on entry and finishes on a clean exit; on an exception it calls :meth:`abort`, which leaves a valid MCAP under
    the ``.partial`` name (never renamed). Chunks are cut at frame boundaries, and each finished chunk is written
    to the OS at once, so a SIGKILL loses at most the frames of the open chunk (see :func:`recover`).

    Attributes:
        final_path: ``<name>.mcap``.
        partial_path: ``<name>.mcap.partial``.
        n_frames: Frames added so far.
        frames_durable: Frames whose chunk has been written to the file (they survive a kill of the process).
        write_seconds: Wall time spent inside :meth:`start`, :meth:`add` and :meth:`finish` (for the budget).
        state: ``new``, ``open``, ``finished`` or ``aborted``.
    """

    def __init__(self, final_path: Path, meta: EpisodeMeta, occupancy: np.ndarray,
                 chunk_size: int = DEFAULT_CHUNK_SIZE, compression: str = DEFAULT_COMPRESSION) -> None:
        """Checks the arguments; nothing touches the disk before :meth:`start`.

        Args:
            final_path: Destination ``<name>.mcap``.
            meta: The episode's constant facts (written as the ``episode`` metadata record).
            occupancy: ``H x W`` bool static occupancy (``meta.occupancy_shape``), logged once at t = 0.
            chunk_size: Uncompressed bytes after which the chunk is closed at the next frame boundary.
            compression: ``zstd``, ``lz4`` or ``none``.

        Raises:
            ValueError: a bad path suffix, chunk size, compression or occupancy shape.
        """
        self.final_path = Path(final_path)
        if self.final_path.suffix != ".mcap":
            raise ValueError(f"EpisodeWriter: expected a path ending in .mcap, got {self.final_path}")
        if compression not in COMPRESSIONS:
            raise ValueError(f"EpisodeWriter compression: expected one of {list(COMPRESSIONS)}, got {compression!r}")
        if chunk_size < 1:
            raise ValueError(f"EpisodeWriter chunk_size: expected >= 1 byte, got {chunk_size}")
        occ = np.asarray(occupancy)
        if list(occ.shape) != list(meta.occupancy_shape):
            raise ValueError(f"{self.final_path}: occupancy shape {list(occ.shape)} != meta.occupancy_shape "
                             f"{list(meta.occupancy_shape)}")
        for cam in CAMERA_NAMES:
            if cam not in meta.cameras:
                raise ValueError(f"{self.final_path}: meta.cameras lacks camera {cam!r}")
        self.partial_path = partial_path_of(self.final_path)
        self.meta = meta
        self.occupancy = occ.astype(bool)
        self.chunk_size = int(chunk_size)
        self.compression = compression
        self.n_frames = 0
        self.frames_durable = 0
        self.write_seconds = 0.0
        self.state: WriterState = "new"
        self._dt_ns = dt_ns_of(meta)
        self._enc = _Encoder(meta)
        self._fd: int | None = None
        self._mcap: McapWriter | None = None
        self._channels: dict[str, int] = {}
        self._pending = 0  # uncompressed payload bytes in the open chunk
        self._broken = False  # an exception escaped from inside the mcap writer: the file tail is undefined
        self._last_done = False

    # lifecycle -------------------------------------------------------------------------------------------------

    def start(self) -> EpisodeWriter:
        """Creates ``<name>.mcap.partial`` and writes the header, the ``episode`` metadata and the schemas.

        Returns:
            ``self``.

        Raises:
            OutputExistsError: ``<name>.mcap`` exists, or a ``.partial`` of the same name does (a killed or
                concurrent recording; recover or delete it first).
            RuntimeError: already started.
        """
        if self.state != "new":
            raise RuntimeError(f"EpisodeWriter({self.final_path}).start(): already {self.state}")
        t0 = time.perf_counter()
        if self.final_path.exists():
            raise OutputExistsError(f"{self.final_path} already exists; refusing to overwrite a recorded episode")
        self.final_path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._fd = os.open(self.partial_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            raise OutputExistsError(
                f"{self.partial_path} already exists (an unfinished recording of this episode); recover it with "
                f"`python -m recorder.mcap_io recover {self.partial_path}` or delete it") from None
        self.state = "open"
        try:
            self._inside_mcap(self._start_mcap)
        except BaseException as e:
            if self._mcap is not None and not self._broken:
                self.abort(type(e).__name__)  # a signal deferred past the header: leave a valid aborted file
            else:
                self._close_fd()
                self.state = "aborted"
            raise
        self.write_seconds += time.perf_counter() - t0
        return self

    def _start_mcap(self) -> None:
        assert self._fd is not None
        w = McapWriter(_FdStream(self._fd), chunk_size=1 << 62, compression=COMPRESSIONS[self.compression],
                       enable_crcs=True, enable_data_crcs=True)  # chunks are cut by us, at frame boundaries
        self._mcap = w
        w.start(profile="", library=LIBRARY)
        w.add_metadata(METADATA_EPISODE, self.meta.to_metadata())  # directly after the header: survives a kill
        schema_ids: dict[str, int] = {}
        for topic in _all_topics():
            if topic in JSON_SCHEMAS:
                name, data = JSON_SCHEMAS[topic]
                if name not in schema_ids:
                    schema_ids[name] = w.register_schema(name=name, encoding="jsonschema", data=data)
                self._channels[topic] = w.register_channel(topic=topic, message_encoding="json",
                                                           schema_id=schema_ids[name])
            else:
                cls = _PROTO_TYPES[topic]
                name = cls.DESCRIPTOR.full_name
                if name not in schema_ids:
                    schema_ids[name] = register_schema(w, cls)
                md = ({"encoding": "16UC1", "unit": "mm", "scale_m": repr(DEPTH_SCALE_M), "invalid": "0"}
                      if topic.endswith("/depth") else {})
                self._channels[topic] = w.register_channel(topic=topic, message_encoding="protobuf",
                                                           schema_id=schema_ids[name], metadata=md)

    def add(self, frame: Frame) -> None:
        """Logs one frame (all its topics at log time ``frame.t_ns``).

        Args:
            frame: The next frame: ``step`` must be ``n_frames`` and ``t_ns`` = ``step · dt``, images of the
                cameras' size; no frame may follow one with ``done=True``.

        Raises:
            RuntimeError: the writer is not open.
            ValueError: the frame does not continue the episode or has the wrong image size/dtype (the message
                names the field, expected and actual value).
        """
        if self.state != "open":
            raise RuntimeError(f"EpisodeWriter({self.final_path}).add(): writer is {self.state}, not open")
        t0 = time.perf_counter()
        self._check_frame(frame)
        msgs = self._enc.frame_messages(frame)
        if frame.step == 0:  # first, so that it is in the first chunk
            msgs.insert(0, (TOPIC_OCCUPANCY, self._enc.grid(self.occupancy)))

        def write() -> None:
            assert self._mcap is not None
            for topic, data in msgs:
                self._mcap.add_message(self._channels[topic], log_time=frame.t_ns, data=data,
                                       publish_time=frame.t_ns, sequence=frame.step)
                self._pending += len(data)
            self.n_frames += 1
            if self._pending >= self.chunk_size:
                self._mcap.flush()  # closes the chunk at this frame boundary and writes it to the file
                self._pending = 0
                self.frames_durable = self.n_frames

        self._inside_mcap(write)
        self._last_done = bool(frame.done)
        self.write_seconds += time.perf_counter() - t0

    def _check_frame(self, fr: Frame) -> None:
        where = f"{self.partial_path}: frame {self.n_frames}"
        if fr.step != self.n_frames:
            raise ValueError(f"{where}: step expected {self.n_frames}, got {fr.step}")
        if fr.t_ns != fr.step * self._dt_ns:
            raise ValueError(f"{where}: t_ns expected step * dt = {fr.step * self._dt_ns}, got {fr.t_ns}")
        if self._last_done:
            raise ValueError(f"{where}: the previous frame had done=True; an episode ends there")
        for cam in CAMERA_NAMES:
            c = self._enc.cams[cam]
            rgb, depth = np.asarray(fr.rgb[cam]), np.asarray(fr.depth[cam])
            if rgb.shape != (c["h"], c["w"], 3) or rgb.dtype != np.uint8:
                raise ValueError(f"{where}: rgb[{cam}] expected uint8 {(c['h'], c['w'], 3)}, got {rgb.dtype} "
                                 f"{rgb.shape}")
            if depth.shape != (c["h"], c["w"]):
                raise ValueError(f"{where}: depth[{cam}] expected shape {(c['h'], c['w'])}, got {depth.shape}")

    def _inside_mcap(self, fn: Any) -> None:
        """Runs ``fn`` (which calls into the mcap writer) as a critical section (signals wait until it returns);
        an exception escaping from it marks the file tail undefined."""
        with _critical():
            try:
                fn()
            except BaseException:
                self._broken = True
                raise

    def finish(self) -> Path:
        """Writes the summary and footer, fsyncs, renames to the final name and fsyncs the directory.

        Idempotent: a second call returns the final path again.

        Returns:
            ``final_path``.

        Raises:
            RuntimeError: the writer was never started, or was aborted.
            OutputExistsError: the final file appeared meanwhile (the episode stays as ``.partial``).
        """
        if self.state == "finished":
            return self.final_path
        if self.state != "open":
            raise RuntimeError(f"EpisodeWriter({self.final_path}).finish(): writer is {self.state}")
        if self._broken:
            raise RuntimeError(f"EpisodeWriter({self.final_path}).finish(): an earlier write failed; the file "
                               f"stays {self.partial_path}")
        t0 = time.perf_counter()
        with _critical():  # a signal arriving now is raised once the episode is final
            try:
                self._finish_mcap()
                self._close_fd()
            except BaseException:
                self._broken = True
                self.abort()
                raise
            self.frames_durable = self.n_frames
            try:
                _publish_no_clobber(self.partial_path, self.final_path)
            except BaseException:
                self.state = "aborted"  # complete and valid, but stays under the .partial name
                raise
            self.state = "finished"
            self.write_seconds += time.perf_counter() - t0
        return self.final_path

    def _finish_mcap(self) -> None:
        assert self._mcap is not None and self._fd is not None
        self._mcap.finish()
        os.fsync(self._fd)

    def abort(self, reason: str = "") -> Path | None:
        """Closes the file without publishing it: it stays ``<name>.mcap.partial``.

        If the mcap writer is in a consistent state the file gets an ``aborted`` metadata record, its summary and
        footer, so it is a valid MCAP (readable, and :func:`recover` salvages every frame in it); otherwise it
        is just closed (``recover`` salvages the complete chunks). Idempotent; a no-op after :meth:`finish`.

        Args:
            reason: Stored in the ``aborted`` metadata record (e.g. the exception type).

        Returns:
            The ``.partial`` path, or None when the writer was finished or never started.
        """
        if self.state in ("finished", "new"):
            return None
        if self.state == "aborted":
            return self.partial_path
        self.state = "aborted"
        try:
            with _critical():
                if not self._broken and self._mcap is not None and self._fd is not None:
                    self._mcap.add_metadata(METADATA_ABORTED, {"reason": reason, "frames": str(self.n_frames)})
                    self._mcap.finish()
                    self.frames_durable = self.n_frames
        except Exception as e:  # the original exception matters more; the file is recoverable anyway
            log.warning("%s: could not close the MCAP cleanly (%s); recover() salvages its complete chunks",
                        self.partial_path, e)
        finally:
            self._close_fd()
        return self.partial_path

    def _close_fd(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            os.close(fd)

    def __enter__(self) -> EpisodeWriter:
        if self.state == "new":
            self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> bool:
        if exc_type is None:
            self.finish()
        else:
            self.abort(reason=exc_type.__name__)
            log.warning("%s: episode not finished (%s); left as %s with %d frames", self.final_path.name,
                        exc_type.__name__, self.partial_path.name, self.frames_durable)
        return False

    def __del__(self) -> None:  # never leak the descriptor of a writer that was dropped mid-episode
        with contextlib.suppress(Exception):
            self._close_fd()


# --------------------------------------------------------------------------------------------------------------
# reading complete files


@dataclass
class _Index:
    """What the seeking reader learned from a complete file's summary."""

    header: Header
    metadata: dict[str, dict[str, str]]
    channels: dict[int, Channel]
    schemas: dict[int, Schema]
    topic_of: dict[int, str]
    chunks: list[tuple[int, int]]  # (chunk_start_offset, chunk_length), in file order
    message_counts: dict[str, int]
    message_start_time: int
    message_end_time: int
    size: int


def _require_file(path: Path) -> Path:
    path = Path(path)
    if not path.exists():
        raise InputMissingError(f"missing episode MCAP: {path}")
    if not path.is_file():
        raise InputMissingError(f"episode MCAP {path} is not a regular file")
    return path


def _read_exact(f: io.BufferedReader, offset: int, n: int, path: Path, what: str) -> bytes:
    f.seek(offset)
    data = f.read(n)
    if len(data) != n:
        raise CorruptMcapError(path, f"truncated: {what} needs {n} bytes, file ends after {len(data)}", offset)
    return data


def _open_index(f: io.BufferedReader, path: Path) -> _Index:
    """Validates magic, footer, summary CRC and data-section CRC of a complete file and reads its summary."""
    size = os.fstat(f.fileno()).st_size
    min_size = 2 * len(MAGIC) + _FOOTER_RECORD_SIZE
    if size < min_size:
        raise CorruptMcapError(path, f"not a complete MCAP file: {size} bytes (< {min_size})")
    if _read_exact(f, 0, len(MAGIC), path, "leading magic") != MAGIC:
        raise CorruptMcapError(path, "not an MCAP file (bad leading magic)", 0)
    tail_off = size - len(MAGIC)
    if _read_exact(f, tail_off, len(MAGIC), path, "trailing magic") != MAGIC:
        raise CorruptMcapError(path, "truncated or unfinished MCAP (no trailing magic; a killed recording? "
                               "rename it to *.mcap.partial and run recover)", tail_off)
    foot_off = tail_off - _FOOTER_RECORD_SIZE
    raw_footer = _read_exact(f, foot_off, _FOOTER_RECORD_SIZE, path, "footer")
    opcode, length = struct.unpack_from("<BQ", raw_footer)
    if opcode != Opcode.FOOTER or length != 20:
        raise CorruptMcapError(path, "truncated or damaged MCAP (no footer record before the trailing magic)",
                               foot_off)
    footer = Footer.read(ReadDataStream(io.BytesIO(raw_footer[9:])))
    if footer.summary_start == 0 or not len(MAGIC) < footer.summary_start <= foot_off:
        raise CorruptMcapError(path, f"footer has no usable summary (summary_start={footer.summary_start})", foot_off)
    summary_bytes = _read_exact(f, footer.summary_start, foot_off - footer.summary_start, path, "summary")
    if footer.summary_crc != 0:
        crc = zlib.crc32(raw_footer[:-4], zlib.crc32(summary_bytes))
        if crc != footer.summary_crc:
            raise CorruptMcapError(path, f"summary CRC mismatch (expected {footer.summary_crc:#010x}, got "
                                   f"{crc:#010x})", footer.summary_start)
    f.seek(0)
    reader = SeekingReader(f, validate_crcs=True, record_size_limit=size)
    summary = reader.get_summary()
    if summary is None or summary.statistics is None:
        raise CorruptMcapError(path, "MCAP summary lacks statistics", footer.summary_start)
    # data-section CRC (the DataEnd record sits right before the summary): catches damage anywhere in the data,
    # including metadata and message indexes that reading chunks alone would not touch
    de_off = footer.summary_start - _DATA_END_RECORD_SIZE
    raw_de = _read_exact(f, de_off, _DATA_END_RECORD_SIZE, path, "DataEnd record")
    if raw_de[0] != Opcode.DATA_END:
        raise CorruptMcapError(path, "no DataEnd record before the summary", de_off)
    data_end = DataEnd.read(ReadDataStream(io.BytesIO(raw_de[9:])))
    header = reader.get_header()
    metadata: dict[str, dict[str, str]] = {}
    for mi in summary.metadata_indexes:
        rec = _record_at(f, mi.offset, path, size)
        if not isinstance(rec, Metadata):
            raise CorruptMcapError(path, f"metadata index points at a {type(rec).__name__}", mi.offset)
        metadata[rec.name] = dict(rec.metadata)
    chunks = sorted((ci.chunk_start_offset, ci.chunk_length) for ci in summary.chunk_indexes)
    topic_of = {cid: ch.topic for cid, ch in summary.channels.items()}
    counts = {topic_of.get(cid, f"<channel {cid}>"): n
              for cid, n in summary.statistics.channel_message_counts.items()}
    idx = _Index(header=header, metadata=metadata, channels=dict(summary.channels), schemas=dict(summary.schemas),
                 topic_of=topic_of, chunks=chunks, message_counts=counts,
                 message_start_time=summary.statistics.message_start_time,
                 message_end_time=summary.statistics.message_end_time, size=size)
    if data_end.data_section_crc != 0:
        f.seek(0)
        crc, remaining = 0, de_off
        while remaining > 0:
            block = f.read(min(remaining, 1 << 22))
            if not block:
                break
            crc = zlib.crc32(block, crc)
            remaining -= len(block)
        if crc != data_end.data_section_crc:
            for off, _ in idx.chunks:  # name the damaged chunk when the damage is inside one
                list(_chunk_messages(f, path, off, size))
            raise CorruptMcapError(path, f"data section CRC mismatch (expected {data_end.data_section_crc:#010x}, "
                                   f"got {crc:#010x}); the damage is outside the chunk payloads, in bytes "
                                   f"[0, {de_off})")
    return idx


def _record_at(f: io.BufferedReader, offset: int, path: Path, size: int) -> Any:
    """Parses the single record at ``offset`` (Header, Metadata or Chunk)."""
    head = _read_exact(f, offset, 9, path, "record header")
    opcode, length = struct.unpack("<BQ", head)
    if offset + 9 + length > size:
        raise CorruptMcapError(path, f"record length {length} runs past the end of the file ({size} bytes)", offset)
    body = _read_exact(f, offset + 9, length, path, "record")
    stream = ReadDataStream(io.BytesIO(body))
    if opcode == Opcode.METADATA:
        return Metadata.read(stream)
    if opcode == Opcode.CHUNK:
        return Chunk.read(stream)
    if opcode == Opcode.HEADER:
        return Header.read(stream)
    raise CorruptMcapError(path, f"unexpected record opcode {opcode:#04x}", offset)


def _chunk_messages(f: io.BufferedReader, path: Path, offset: int, size: int) -> list[Message]:
    """The messages of the chunk at ``offset``, after decompression and CRC validation."""
    try:
        chunk = _record_at(f, offset, path, size)
        if not isinstance(chunk, Chunk):
            raise CorruptMcapError(path, f"chunk index points at a {type(chunk).__name__}", offset)
        records = breakup_chunk(chunk, validate_crc=True)
    except CorruptMcapError:
        raise
    except _DECODE_ERRORS as e:
        kind = "CRC mismatch" if "crc" in str(e).lower() else "cannot be decoded"
        raise CorruptMcapError(path, f"damaged chunk ({kind}: {type(e).__name__}: {e})", offset) from e
    return [r for r in records if isinstance(r, Message)]


def _guard(path: Path, what: str) -> contextlib.AbstractContextManager[None]:
    """Re-raises decoder exceptions as CorruptMcapError naming ``path``."""

    @contextlib.contextmanager
    def cm() -> Iterator[None]:
        try:
            yield
        except (CorruptArtifactError, InputMissingError):
            raise
        except _DECODE_ERRORS as e:
            raise CorruptMcapError(path, f"{what}: {type(e).__name__}: {e}") from e

    return cm()


def _check_episode_channels(idx: _Index, path: Path) -> dict[str, int]:
    """topic → channel id, checking every topic exists with the expected schema."""
    by_topic = {ch.topic: cid for cid, ch in idx.channels.items()}
    for topic in _all_topics():
        if topic not in by_topic:
            raise CorruptMcapError(path, f"not an episode log: no channel {topic}")
        ch = idx.channels[by_topic[topic]]
        schema = idx.schemas.get(ch.schema_id)
        want = expected_schema_name(topic)
        if schema is None or schema.name != want:
            raise CorruptMcapError(path, f"channel {topic}: expected schema {want}, got "
                                   f"{schema.name if schema else 'none'}")
    return by_topic


def _iter_frame_messages(path: Path, idx: _Index, f: io.BufferedReader) -> Iterator[tuple[int, dict[str, bytes]]]:
    """(log_time, topic → payload) per frame, reading chunks in file order with CRC validation.

    Raises:
        CorruptMcapError: a damaged chunk, a message on an unknown channel, log times going backwards or a topic
            logged twice in one frame.
    """
    cur_t: int | None = None
    cur: dict[str, bytes] = {}
    for off, _ in idx.chunks:
        for m in _chunk_messages(f, path, off, idx.size):
            topic = idx.topic_of.get(m.channel_id)
            if topic is None:
                raise CorruptMcapError(path, f"message on unknown channel {m.channel_id}", off)
            if cur_t is None or m.log_time != cur_t:
                if cur_t is not None:
                    if m.log_time < cur_t:
                        raise CorruptMcapError(path, f"log time goes backwards ({m.log_time} ns after {cur_t} ns)",
                                               off)
                    yield cur_t, cur
                cur_t, cur = m.log_time, {}
            if topic in cur:
                raise CorruptMcapError(path, f"topic {topic} logged twice at t={m.log_time} ns", off)
            cur[topic] = m.data
    if cur_t is not None:
        yield cur_t, cur


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


def _decode_grid(data: bytes, shape: list[int]) -> np.ndarray:
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
        state=_dec_array(robot["state"]), odom=_dec_array(robot["odom"]), action=_dec_array(robot["action"]),
        goal_xy=_dec_array(robot["goal_xy"]),
        poses=_dec_array(det["poses"]), pose_mask=_dec_array(det["mask"]), pose_conf=_dec_array(det["confidence"]),
        pose_track=_dec_array(det["track"]),
        ped_pos=_dec_array(peds["pos"]), ped_vel=_dec_array(peds["vel"]), ped_radius=_dec_array(peds["radius"]),
        ped_yaw=_dec_array(peds["yaw"]), ped_intent_xy=_dec_array(peds["intent_xy"]),
        ped_keypoints=_dec_array(peds["keypoints"]),
        reward=_dec_float(rew["reward"]), reward_terms={str(k): _dec_float(v) for k, v in rew["terms"].items()},
        d_o=_dec_float(rew["d_o"]), done=rew["done"], outcome=rew["outcome"],
        label=_dec_array(robot["label"]) if "label" in robot else None,
    )


class EpisodeReader:
    """Reads a complete episode MCAP back into frames (a seeking reader with CRC validation).

    Opening validates the magic, footer, summary CRC and data-section CRC and reads the metadata and the occupancy
    grid; :meth:`frames` then validates every chunk's CRC as it reads it. No file handle is held between calls.

    Attributes:
        path: The file.
        meta: The :class:`EpisodeMeta` from the ``episode`` metadata record.
        occupancy: ``H x W`` bool static occupancy (True = obstacle), as :class:`recorder.drive.Episode` has it.
        n_frames: Frames in the file (from the summary statistics).
        metadata: Every metadata record, name → str map (``episode``, and ``aborted``/``recovery`` if present).
        library: The MCAP header's library string.
        message_counts: topic → message count (summary statistics).

    Raises (on construction):
        InputMissingError: the file does not exist.
        CorruptMcapError: the file is truncated, fails a CRC check or is not an episode log.
    """

    def __init__(self, path: Path) -> None:
        self.path = _require_file(Path(path))
        with open(self.path, "rb") as f, _guard(self.path, "cannot read the MCAP summary"):
            self._idx = _open_index(f, self.path)
            self._by_topic = _check_episode_channels(self._idx, self.path)
            if METADATA_EPISODE not in self._idx.metadata:
                raise CorruptMcapError(self.path, f"no '{METADATA_EPISODE}' metadata record")
            try:
                self.meta = EpisodeMeta.from_metadata(self._idx.metadata[METADATA_EPISODE])
            except (TypeError, ValueError) as e:
                raise CorruptMcapError(self.path, f"'{METADATA_EPISODE}' metadata is malformed: {e}") from e
            self.occupancy = self._read_occupancy(f)
        self.metadata = self._idx.metadata
        self.library = self._idx.header.library
        self.message_counts = dict(self._idx.message_counts)
        self.n_frames = int(self.message_counts.get(TOPIC_ROBOT, 0))

    def _read_occupancy(self, f: io.BufferedReader) -> np.ndarray:
        """The grid logged at t = 0 (the first message of this writer's first chunk; other writers may put it
        later in frame 0, so chunks are read until the frame at t = 0 is over)."""
        if not self._idx.chunks:
            raise CorruptMcapError(self.path, "no chunks: the episode has no frames")
        cid = self._by_topic[TOPIC_OCCUPANCY]
        for off, _ in self._idx.chunks:
            for m in _chunk_messages(f, self.path, off, self._idx.size):
                if m.channel_id == cid and m.log_time == 0:
                    try:
                        return _decode_grid(m.data, list(self.meta.occupancy_shape))
                    except _DECODE_ERRORS as e:
                        raise CorruptMcapError(self.path, f"{TOPIC_OCCUPANCY}: {e}", off) from e
                if m.log_time > 0:
                    raise CorruptMcapError(self.path, f"no {TOPIC_OCCUPANCY} message at t = 0", off)
        raise CorruptMcapError(self.path, f"no {TOPIC_OCCUPANCY} message at t = 0")

    def frames(self) -> Iterator[Frame]:
        """Yields the frames in log-time order, equal to what was written (depth within 0.5 mm).

        Raises:
            CorruptMcapError: a chunk fails its CRC, a frame misses topics or a payload does not decode.
        """
        dt = dt_ns_of(self.meta)
        with open(self.path, "rb") as f:
            k = 0
            for t, msgs in _iter_frame_messages(self.path, self._idx, f):
                missing = [tp for tp in frame_topics(first=t == 0) if tp not in msgs]
                if missing:
                    raise CorruptMcapError(self.path, f"frame at t={t} ns misses topics {missing}")
                if t != k * dt:
                    raise CorruptMcapError(self.path, f"frame {k} has log time {t} ns, expected {k * dt} ns")
                try:
                    fr = decode_frame(msgs, t)
                except _DECODE_ERRORS as e:
                    raise CorruptMcapError(self.path, f"frame at t={t} ns does not decode: "
                                           f"{type(e).__name__}: {e}") from e
                yield fr
                k += 1

    def __len__(self) -> int:
        return self.n_frames


def read_episode(path: Path) -> tuple[EpisodeMeta, np.ndarray, Iterator[Frame]]:
    """Opens a complete episode MCAP.

    Args:
        path: ``<name>.mcap``.

    Returns:
        ``(meta, occupancy H x W bool, frames)`` where ``frames`` lazily yields the :class:`Frame` objects.

    Raises:
        InputMissingError: the file does not exist.
        CorruptMcapError: the file is truncated, fails a CRC check or is not an episode log (also while
            iterating the frames).
    """
    r = EpisodeReader(path)
    return r.meta, r.occupancy, r.frames()


def count_frames(path: Path) -> int:
    """Frames in a complete episode MCAP, from its (CRC-checked) summary without decompressing chunks."""
    return EpisodeReader(path).n_frames


# --------------------------------------------------------------------------------------------------------------
# scanning (doctor, summaries)


@dataclass
class EpisodeScan:
    """What a full CRC-validated pass over an episode file found (images are not decoded).

    Attributes:
        path: The file.
        meta: The episode metadata, or None when the record is missing or malformed.
        metadata_names: Names of all metadata records.
        library: The MCAP header's library string.
        log_times: Log time of each frame, ns, in file order.
        steps: ``step`` of each frame from /robot/state (−1 where missing).
        missing: ``(log_time, [topics])`` for each frame that misses topics.
        done: ``done`` of each frame from /episode/reward (False where missing).
        outcome: The last frame's outcome.
        topic_counts: topic → message count (counted, not taken from the summary).
        size_bytes: File size.
    """

    path: Path
    meta: EpisodeMeta | None
    metadata_names: list[str]
    library: str
    log_times: list[int] = field(default_factory=list)
    steps: list[int] = field(default_factory=list)
    missing: list[tuple[int, list[str]]] = field(default_factory=list)
    done: list[bool] = field(default_factory=list)
    outcome: str = ""
    topic_counts: dict[str, int] = field(default_factory=dict)
    size_bytes: int = 0

    @property
    def n_frames(self) -> int:
        return len(self.log_times)


def scan_episode(path: Path) -> EpisodeScan:
    """Reads every chunk of a complete episode MCAP with CRC validation, decoding only the small JSON topics.

    Unlike :class:`EpisodeReader` it does not stop at the first missing topic or bad time step: it records them
    (``missing``, ``log_times``, ``steps``) for :mod:`recorder.doctor_mcap`.

    Raises:
        InputMissingError: the file does not exist.
        CorruptMcapError: the file cannot be opened or a chunk fails its CRC / does not decode.
    """
    path = _require_file(Path(path))
    with open(path, "rb") as f, _guard(path, "cannot scan"):
        idx = _open_index(f, path)
        meta: EpisodeMeta | None = None
        if METADATA_EPISODE in idx.metadata:
            with contextlib.suppress(TypeError, ValueError):
                meta = EpisodeMeta.from_metadata(idx.metadata[METADATA_EPISODE])
        scan = EpisodeScan(path=path, meta=meta, metadata_names=sorted(idx.metadata), library=idx.header.library,
                           size_bytes=idx.size)
        for t, msgs in _iter_frame_messages(path, idx, f):
            scan.log_times.append(t)
            for topic in msgs:
                scan.topic_counts[topic] = scan.topic_counts.get(topic, 0) + 1
            miss = [tp for tp in frame_topics(first=t == 0) if tp not in msgs]
            if miss:
                scan.missing.append((t, miss))
            try:
                step = json.loads(msgs[TOPIC_ROBOT])["step"] if TOPIC_ROBOT in msgs else -1
                rew = json.loads(msgs[TOPIC_REWARD]) if TOPIC_REWARD in msgs else {}
            except _DECODE_ERRORS as e:
                raise CorruptMcapError(path, f"frame at t={t} ns: JSON does not decode: {e}") from e
            scan.steps.append(int(step))
            scan.done.append(bool(rew.get("done", False)))
            scan.outcome = str(rew.get("outcome", ""))
    return scan


def episode_summary(path: Path) -> dict[str, Any]:
    """A CRC-validated summary of a complete episode MCAP.

    Returns:
        ``{"path", "n_frames", "outcome", "done", "duration_s", "topics": {topic: count}, "bytes", "scene",
        "seed", "aborted", "recovered"}``; ``duration_s`` is the last log time in seconds.

    Raises:
        InputMissingError, CorruptMcapError: as :func:`scan_episode`.
    """
    s = scan_episode(path)
    return {"path": str(s.path), "n_frames": s.n_frames, "outcome": s.outcome, "done": bool(s.done and s.done[-1]),
            "duration_s": (s.log_times[-1] / 1e9) if s.log_times else 0.0, "topics": dict(sorted(s.topic_counts.items())),
            "bytes": s.size_bytes, "scene": s.meta.scene if s.meta else None, "seed": s.meta.seed if s.meta else None,
            "aborted": METADATA_ABORTED in s.metadata_names, "recovered": METADATA_RECOVERY in s.metadata_names}


# --------------------------------------------------------------------------------------------------------------
# salvage


@dataclass
class _Salvage:
    """What a linear pass over a possibly truncated file recovered."""

    metadata: list[Metadata] = field(default_factory=list)
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: list[Message] = field(default_factory=list)
    chunks_ok: int = 0
    stop_offset: int = 0
    stop_reason: str = "end of file"
    complete: bool = False


def _linear_salvage(path: Path) -> _Salvage:
    """Reads records front to back without seeking, keeping every complete, CRC-valid chunk before the damage.

    Stops at the first incomplete record (the file ends inside it), the first chunk that fails its CRC or does
    not decompress, or the footer. Chunks after damage are not used, so an episode never gets a hole.
    """
    out = _Salvage()
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if f.read(len(MAGIC)) != MAGIC:
            raise CorruptMcapError(path, "not an MCAP file (bad leading magic); nothing to salvage", 0)
        off = len(MAGIC)
        while True:
            out.stop_offset = off
            head = f.read(9)
            if len(head) < 9:
                out.stop_reason = "file ends" + (" inside a record header" if head else "")
                return out
            opcode, length = struct.unpack("<BQ", head)
            if length > size - off - 9:
                out.stop_reason = f"file ends inside a {_opname(opcode)} record ({length} bytes)"
                return out
            body = f.read(length)
            stream = ReadDataStream(io.BytesIO(body))
            try:
                if opcode == Opcode.CHUNK:
                    records = breakup_chunk(Chunk.read(stream), validate_crc=True)
                    for r in records:
                        if isinstance(r, Schema):
                            out.schemas[r.id] = r
                        elif isinstance(r, Channel):
                            out.channels[r.id] = r
                        elif isinstance(r, Message):
                            out.messages.append(r)
                    out.chunks_ok += 1
                elif opcode == Opcode.METADATA:
                    out.metadata.append(Metadata.read(stream))
                elif opcode == Opcode.FOOTER:
                    out.complete = True
                    out.stop_reason = "footer (the file is complete)"
                    return out
                elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):  # unchunked schema/channel records
                    r = Schema.read(stream) if opcode == Opcode.SCHEMA else Channel.read(stream)
                    (out.schemas if isinstance(r, Schema) else out.channels)[r.id] = r  # type: ignore[index]
                elif opcode == Opcode.DATA_END:
                    out.stop_reason = "end of the data section"
                    return out  # the summary holds nothing that is not already salvaged
            except _DECODE_ERRORS as e:
                out.stop_reason = f"damaged {_opname(opcode)} record ({type(e).__name__}: {e})"
                return out
            off += 9 + length


def _opname(opcode: int) -> str:
    try:
        return Opcode(opcode).name.lower()
    except ValueError:
        return f"unknown (opcode {opcode:#04x})"


def recover(partial_path: Path, *, chunk_size: int = DEFAULT_CHUNK_SIZE,
            compression: str = DEFAULT_COMPRESSION) -> Path:
    """Salvages the complete frames of an unfinished episode into a new, valid ``<name>.recovered.mcap``.

    A linear (non-seeking) pass keeps every complete, CRC-valid chunk up to the first damage (see
    :func:`_linear_salvage`); frames are the log times whose full topic set is present, and only the leading run of
    complete frames (t = 0, dt, 2 dt, ...) is kept, so a trailing incomplete frame is dropped. Payloads are copied
    byte for byte; the ``episode`` metadata is kept and a ``recovery`` record says what was salvaged. The result
    is written to a temporary name, re-opened with CRC validation and read through, and then published without
    ever replacing an existing file. The ``.partial`` is left untouched.

    Args:
        partial_path: ``<name>.mcap.partial`` (any MCAP path works, e.g. a truncated copy).
        chunk_size, compression: As for :class:`EpisodeWriter`.

    Returns:
        The recovered file ``<name>.recovered.mcap``.

    Raises:
        InputMissingError: ``partial_path`` does not exist.
        OutputExistsError: ``<name>.recovered.mcap`` exists already.
        CorruptMcapError: not an MCAP, no ``episode`` metadata, or not a single complete frame to salvage.
    """
    src = _require_file(Path(partial_path))
    dst = recovered_path_of(src)
    if dst.exists():
        raise OutputExistsError(f"{dst} already exists; refusing to overwrite it (delete it to recover {src} again)")
    sal = _linear_salvage(src)
    meta_rec = next((m for m in sal.metadata if m.name == METADATA_EPISODE), None)
    if meta_rec is None:
        raise CorruptMcapError(src, f"no '{METADATA_EPISODE}' metadata record before the damage "
                               f"({sal.stop_reason}); nothing to salvage", sal.stop_offset)
    try:
        meta = EpisodeMeta.from_metadata(dict(meta_rec.metadata))
    except (TypeError, ValueError) as e:
        raise CorruptMcapError(src, f"'{METADATA_EPISODE}' metadata is malformed: {e}") from e
    dt = dt_ns_of(meta)
    topic_of = {cid: ch.topic for cid, ch in sal.channels.items()}
    by_time: dict[int, dict[str, Message]] = {}
    for m in sal.messages:
        topic = topic_of.get(m.channel_id)
        if topic is not None:
            by_time.setdefault(m.log_time, {}).setdefault(topic, m)
    n = 0
    while n * dt in by_time and all(tp in by_time[n * dt] for tp in frame_topics(first=n == 0)):
        n += 1
    if n == 0:
        raise CorruptMcapError(src, f"no complete frame before the damage ({sal.chunks_ok} complete chunks, "
                               f"stopped at: {sal.stop_reason}); nothing to salvage", sal.stop_offset)
    dropped = len([t for t in by_time if t >= n * dt])

    tmp = dst.with_name(f".{dst.name}.tmp-{os.getpid()}")
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        w = McapWriter(_FdStream(fd), chunk_size=1 << 62, compression=COMPRESSIONS[compression],
                       enable_crcs=True, enable_data_crcs=True)
        w.start(profile="", library=LIBRARY)
        w.add_metadata(METADATA_EPISODE, dict(meta_rec.metadata))
        w.add_metadata(METADATA_RECOVERY, {"source": src.name, "frames_salvaged": str(n),
                                           "complete_chunks": str(sal.chunks_ok), "stopped_at": sal.stop_reason,
                                           "stop_offset": str(sal.stop_offset),
                                           "incomplete_frames_dropped": str(dropped)})
        new_schema: dict[int, int] = {}
        for sid in sorted(sal.schemas):
            s = sal.schemas[sid]
            new_schema[sid] = w.register_schema(name=s.name, encoding=s.encoding, data=s.data)
        new_channel: dict[str, int] = {}
        for cid in sorted(sal.channels):
            ch = sal.channels[cid]
            if ch.topic in new_channel:
                continue
            new_channel[ch.topic] = w.register_channel(topic=ch.topic, message_encoding=ch.message_encoding,
                                                       schema_id=new_schema.get(ch.schema_id, 0),
                                                       metadata=dict(ch.metadata))
        pending = 0
        for k in range(n):
            wanted = set(frame_topics(first=k == 0))
            for topic, m in by_time[k * dt].items():  # in the source's order
                if topic not in wanted:
                    continue
                w.add_message(new_channel[topic], log_time=m.log_time, data=m.data, publish_time=m.publish_time,
                              sequence=m.sequence)
                pending += len(m.data)
            if pending >= chunk_size:
                w.flush()
                pending = 0
        w.finish()
        os.fsync(fd)
    except BaseException:
        os.close(fd)
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    os.close(fd)
    try:  # verify before publishing: CRCs, summary and every frame decode
        r = EpisodeReader(tmp)
        got = sum(1 for _ in r.frames())
        if got != n:
            raise CorruptMcapError(tmp, f"recovered file holds {got} frames, expected {n}")
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    _publish_no_clobber(tmp, dst)
    log.info("recovered %d frames (t = 0 .. %.2f s) of %s into %s; %d complete chunks, stopped at: %s",
             n, (n - 1) * dt / 1e9, src.name, dst.name, sal.chunks_ok, sal.stop_reason)
    return dst


# --------------------------------------------------------------------------------------------------------------
# measurement and CLI


def benchmark_writer(frames: list[Frame], meta: EpisodeMeta, occupancy: np.ndarray, out_dir: Path,
                     configs: list[tuple[str, int]], repeats: int = 3) -> list[dict[str, Any]]:
    """Times :class:`EpisodeWriter` on in-memory frames for each (compression, chunk size).

    Args:
        frames: The episode's frames (already rendered, so only MCAP work is timed).
        meta, occupancy: Its metadata and grid.
        out_dir: Where the files go (removed after each run).
        configs: ``(compression, chunk_size_bytes)`` pairs.
        repeats: Runs per config (interleaved across configs); the fastest is reported.

    Returns:
        One row per config: ``compression, chunk_size, ms_per_frame, kb_per_frame, raw_kb_per_frame, n_frames``.
    """
    raw = sum(sum(fr.rgb[c].nbytes + fr.depth[c].nbytes // 2 for c in CAMERA_NAMES) for fr in frames)
    best = {cfg: math.inf for cfg in configs}
    size = {cfg: 0 for cfg in configs}
    for r in range(repeats):  # configs interleaved, so that load changes on the machine hit all of them alike
        for comp, cs in configs:
            path = Path(out_dir) / f"bench_{comp}_{cs}_{r}.mcap"
            t0 = time.perf_counter()
            with EpisodeWriter(path, meta, occupancy, chunk_size=cs, compression=comp) as w:
                for fr in frames:
                    w.add(fr)
            best[(comp, cs)] = min(best[(comp, cs)], time.perf_counter() - t0)
            size[(comp, cs)] = path.stat().st_size
            path.unlink()
    return [{"compression": comp, "chunk_size": cs, "ms_per_frame": round(1e3 * best[(comp, cs)] / len(frames), 3),
             "kb_per_frame": round(size[(comp, cs)] / len(frames) / 1e3, 1),
             "raw_kb_per_frame": round(raw / len(frames) / 1e3, 1), "n_frames": len(frames)}
            for comp, cs in configs]


def main(argv: list[str] | None = None) -> int:
    """``python -m recorder.mcap_io {recover FILE | summary FILE | bench [--scene S --seconds T]}``."""
    import argparse
    import tempfile

    from pipeline.core.errors import ICrowdNavError

    ap = argparse.ArgumentParser(prog="python -m recorder.mcap_io", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("recover", help="salvage the complete frames of a *.mcap.partial").add_argument("file", type=Path)
    sub.add_parser("summary", help="print a CRC-checked summary of an episode").add_argument("file", type=Path)
    b = sub.add_parser("bench", help="measure MCAP writing per compression and chunk size")
    b.add_argument("--scene", default="office_lobby")
    b.add_argument("--density", type=float, default=0.1)
    b.add_argument("--seconds", type=float, default=10.0)
    b.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        if args.cmd == "recover":
            out = recover(args.file)
            print(f"recovered {count_frames(out)} frames into {out}")
        elif args.cmd == "summary":
            print(json.dumps(episode_summary(args.file), indent=2))
        else:
            from recorder.drive import drive_episode
            from sim.env import SimConfig

            t0 = time.perf_counter()
            ep = drive_episode(SimConfig(scene=args.scene, density=args.density, max_episode_s=args.seconds), 0)
            frames = list(ep.frames)
            sim_ms = 1e3 * (time.perf_counter() - t0) / len(frames)
            with tempfile.TemporaryDirectory() as d:
                rows = benchmark_writer(frames, ep.meta, ep.occupancy, Path(d),
                                        [(c, s) for c in ("zstd", "lz4", "none") for s in (1 << 20, 4 << 20)],
                                        repeats=args.repeats)
            print(f"sim+render: {sim_ms:.1f} ms/frame over {len(frames)} frames")
            for r in rows:
                print(f"{r['compression']:5s} {r['chunk_size'] >> 20} MiB  {r['ms_per_frame']:6.2f} ms/frame  "
                      f"{r['kb_per_frame']:7.1f} kB/frame (raw {r['raw_kb_per_frame']} kB)  "
                      f"{100 * r['ms_per_frame'] / sim_ms:4.1f} % of sim+render, "
                      f"{100 * r['ms_per_frame'] / 20.0:4.1f} % of 20 ms")
    except ICrowdNavError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
