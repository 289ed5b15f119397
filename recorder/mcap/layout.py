"""The layout of an episode MCAP: what a frame is, the metadata records, the file names.

One episode is one MCAP file. File layout (log time = publish time = ``frame.t_ns``, simulation time; no wall
clock anywhere, so the same seed and config give byte-identical files)::

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
"""

from __future__ import annotations

from pathlib import Path

from recorder import schema
from recorder.schema import CAMERA_NAMES, EpisodeMeta

# MCAP header library string: constant, so files are reproducible. It keeps the name of the module this package
# was split from, because changing it would change the bytes of every file (tests/test_golden.py pins them).
LIBRARY = "icrowdnav recorder.mcap_io/1"
METADATA_ABORTED = "aborted"  # metadata record of a *.partial closed after an exception
METADATA_RECOVERY = "recovery"  # metadata record of a file written by recover()
PARTIAL_SUFFIX = ".partial"

MAGIC = b"\x89MCAP0\r\n"


def frame_topics(first: bool = False) -> tuple[str, ...]:
    """The topics a complete frame has (in the writer's order, except that it logs ``/map/occupancy`` first).

    Args:
        first: Whether this is the frame at t = 0 (which also carries ``/map/occupancy``).
    """
    per_cam = tuple(t.format(cam=c) for c in CAMERA_NAMES for t in (schema.TOPIC_RGB, schema.TOPIC_DEPTH, schema.TOPIC_CALIB,
                                                                    schema.TOPIC_KEYPOINTS_2D))
    rest = (schema.TOPIC_TF, schema.TOPIC_ROBOT_POSE, schema.TOPIC_GOAL, schema.TOPIC_PEDS_SCENE, schema.TOPIC_ROBOT, schema.TOPIC_PEDS, schema.TOPIC_DETECTIONS,
            schema.TOPIC_REWARD)
    return per_cam + rest + ((schema.TOPIC_OCCUPANCY,) if first else ())


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


def all_topics() -> tuple[str, ...]:
    """Every topic of an episode (those of the frame at t = 0)."""
    return frame_topics(first=True)
