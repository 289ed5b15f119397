"""The LeRobot feature spec of an exported iCrowdNav dataset, and the conversion of a recorded frame into it.

:class:`ExportSpec` fixes every size an exported dataset has (camera images, the number of detected people
``K``, the pedestrian padding ``N_MAX``, the local occupancy crop); :meth:`ExportSpec.features` is the
``features`` dict handed to ``LeRobotDataset.create`` and :func:`frame_to_features` turns one
:class:`recorder.schema.Frame` into the ``add_frame`` dict, checking every field on the way: a wrong shape,
dtype, a missing field or a non-finite value raises :class:`FeatureError` naming the file, the field, what was
expected and what was found.

Features (``T`` frames; shapes per frame; frames: *world* = the scene's, *robot* = x forward, y left, z up):

===============================  ==============  =======  =========================================================
feature                          shape           dtype    meaning
===============================  ==============  =======  =========================================================
observation.images.{left,right}  H x W x 3       video    RGB camera image (AV1 mp4; decoded as 3 x H x W float)
observation.depth.{left,right}   H x W           uint16   z-depth along the optical axis, mm, 0 = invalid
observation.state                5               float32  [g_x, g_y, d_g, v_x, v_y], robot frame
observation.odom                 3               float32  robot pose [x, y, yaw], world frame
observation.goal                 2               float32  goal [x, y], world frame
observation.poses                K * 17 * 3      float32  detected COCO-17 joints [x, y, z], robot frame, m (flat)
observation.pose_mask            K * 17          float32  1 = detected joint, 0 = not (rows/joints of 0 are zeros)
observation.pose_conf            K * 17          float32  detector confidence of each joint (flat)
action                           2               float32  the command [v m/s, ω rad/s] chosen from observation t
                                                          and applied from frame t to frame t + 1
action.teacher                   2               float32  only in labelled (DAgger) datasets: the teacher's
                                                          command for observation t [v m/s, ω rad/s]
next.reward                      1               float32  the paper's reward of the step t → t + 1
next.reward_terms                6               float32  success, collision, near, progress, spin, total
next.done                        1               bool     the step t → t + 1 ended the episode
privileged.ped_state             N_MAX x 8       float32  x, y, vx, vy (world), radius, body yaw, head yaw
                                                          (world, rad), present (1/0); row n = pedestrian n
privileged.ped_keypoints         N_MAX x 17 x 3  float32  true COCO-17 keypoints, world frame, m
privileged.ped_intent            N_MAX x 2       float32  where each pedestrian is heading in mind, world, m
privileged.pose_track            K               int64    true pedestrian row of each detection, -1 = padding
privileged.d_o                   1               float32  robot centre to the nearest pedestrian/obstacle surface
privileged.local_occupancy       R x C           bool     static map around the robot (see :class:`LocalMapSpec`)
===============================  ==============  =======  =========================================================

Rows of the ``privileged.ped_*`` arrays beyond the episode's crowd size are zeros (``present`` = 0).

**Action convention (dataset format 2).** LeRobot's (and ``lerobot-record``'s): frame ``t`` holds observation
``t``, the command chosen from it (``action``), and what that command led to (``next.*``). The MCAP log keeps the
simulator's own timing — its frame ``t`` carries the command that *led to* it and the reward of the step into
it — so the export pairs observation ``t`` with the command/reward/done of MCAP frame ``t + 1``, and an episode's
last (terminal) observation, from which no command was chosen, stays in the MCAP log only: a dataset episode has
one frame fewer than its recording. Format 1 datasets (``action[t]`` = the command that led to frame ``t``) are
refused by every reader with a named error (:mod:`recorder.dataset_info`); re-export them from their recording.

**Types for stock LeRobot policies.** lerobot turns every non-video ``observation.*`` feature into a state input
and normalises it, so those are numbers: ``observation.pose_mask`` is float32 0/1 (a bool mask made lerobot's
normaliser fail: "Subtraction ... with two bool tensors"); depth is uint16 millimetres (half the float32 size,
exact to the MCAP log's millimetres; lerobot's torch formatting returns it as an int64 tensor — divide by 1000 for
metres). ``next.*`` and ``privileged.*`` features are ignored by lerobot's policies (neither ``observation.*`` nor
``action*``), so ``next.done`` and ``privileged.local_occupancy`` stay ``bool``. The three detection features are flat vectors
(C order: person, joint, xyz; ``names`` spell every element, e.g. ``p0.nose.x``; :func:`unflatten_poses`):
lerobot formats every column of every row it reads, and a multi-dimensional ``datasets`` array costs ~10x a flat
vector of the same numbers (306 pose numbers: 61 ms vs 6 ms per 100 rows) — the difference between a 100-step
action chunk loading at ~5x and ~2x a stock-shaped dataset once depth and ``privileged.*`` are removed
(``make bench``). Depth and the privileged arrays keep their shapes: flat, lerobot's per-element statistics would
be ~1.4 MB per episode for each depth map.

**Calibration** lives in ``meta/info.json``, where lerobot's own tools keep it: every feature we write carries an
``info`` dict (``description`` with units and frames; cameras' ``camera`` = intrinsics/extrinsics on the image and
depth features; ``action``'s ``convention`` and ``icrowdnav_format``; the occupancy crop's ``layout``) —
:meth:`ExportSpec.feature_info`. ``meta/icrowdnav*.json*`` are optional extras (episode facts, sources).
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from pipeline.core.errors import CorruptArtifactError
from pipeline.core.keys import (
    ACTION,
    ACTION_TEACHER,
    NEXT_DONE,
    NEXT_REWARD,
    NEXT_REWARD_TERMS,
    OBS_GOAL,
    OBS_ODOM,
    OBS_POSE_CONF,
    OBS_POSE_MASK,
    OBS_POSES,
    OBS_STATE,
    PRIV_D_O,
    PRIV_LOCAL_OCCUPANCY,
    PRIV_PED_INTENT,
    PRIV_PED_KEYPOINTS,
    PRIV_PED_STATE,
    PRIV_POSE_TRACK,
    depth_key,
    image_key,
)
from recorder.schema import CAMERA_NAMES, DEPTH_SCALE_M, EpisodeMeta, Frame, depth_to_mm

TASK = "navigate to the goal through the crowd"
FORMAT_VERSION = 2  # 2: LeRobot's action convention, uint16 mm depth, float32 pose mask, calibration in info.json
FORMAT_KEY = "icrowdnav_format"  # in meta/info.json features["action"]["info"]
ACTION_CONVENTION = ("action[t] is the command [v m/s, omega rad/s] chosen from observation t and applied from "
                     "frame t to frame t + 1 (LeRobot's convention); next.reward / next.done[t] are the reward / end "
                     "of that step; the episode's terminal observation is not a frame (it stays in the MCAP log)")
ROBOT_TYPE = "icrowdnav_diffdrive"
N_MAX_PEDESTRIANS = 64
DEFAULT_MAX_PEOPLE = 6  # sim.detector.DetectorConfig.max_people
N_JOINTS = 17
COCO_KEYPOINTS = (
    "nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder", "right_shoulder", "left_elbow",
    "right_elbow", "left_wrist", "right_wrist", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle",
    "right_ankle",
)
REWARD_TERMS = ("success", "collision", "near", "progress", "spin", "total")
PED_STATE_COLUMNS = ("x", "y", "vx", "vy", "radius", "body_yaw", "head_yaw", "present")


class FeatureError(CorruptArtifactError):
    """A recorded frame or episode does not fit the dataset's feature spec (names file, field, expected, actual)."""


@dataclass(frozen=True)
class LocalMapSpec:
    """A robot-centred crop of the static occupancy grid (``privileged.local_occupancy``).

    The crop covers ``x ∈ [x_min_m, x_max_m)`` forward and ``y ∈ [y_min_m, y_max_m)`` lateral in the robot
    frame (x forward, y left) with square cells of ``resolution_m``. It is laid out like a top-down image with
    the robot heading up:

    * row ``r`` holds forward ``x = x_max_m - (r + 0.5) * resolution_m`` — row 0 is the farthest ahead;
    * column ``c`` holds lateral ``y = y_max_m - (c + 0.5) * resolution_m`` — column 0 is the farthest to the
      robot's left, so columns run left → right as the robot sees them.

    With the defaults (100 x 100 cells, 0.1 m) the robot centre lies at (row 79.5, col 49.5). Each cell takes
    the value of the world-grid cell whose centre is nearest to the cell's centre; ``True`` = static obstacle,
    or outside the world grid (outside the scene bounds).
    """

    resolution_m: float = 0.1
    x_min_m: float = -2.0
    x_max_m: float = 8.0
    y_min_m: float = -5.0
    y_max_m: float = 5.0

    def __post_init__(self) -> None:
        rows = (self.x_max_m - self.x_min_m) / self.resolution_m
        cols = (self.y_max_m - self.y_min_m) / self.resolution_m
        if not (self.resolution_m > 0 and rows >= 1 and cols >= 1):
            raise ValueError(f"LocalMapSpec: expected resolution > 0 and non-empty extents, got {self}")
        if abs(rows - round(rows)) > 1e-6 or abs(cols - round(cols)) > 1e-6:
            raise ValueError(f"LocalMapSpec: extents must be whole multiples of the resolution, got {self}")

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)`` of the crop."""
        return (round((self.x_max_m - self.x_min_m) / self.resolution_m),
                round((self.y_max_m - self.y_min_m) / self.resolution_m))

    def cell_centres(self) -> np.ndarray:
        """``rows x cols x 2`` robot-frame ``(x, y)`` of every cell centre (float64, read-only)."""
        return _cell_centres(self)

    def to_dict(self) -> dict[str, Any]:
        """Plain data for the dataset metadata, with the layout spelled out."""
        return {**asdict(self), "shape": list(self.shape), "dtype": "bool",
                "frame": "robot (x forward, y left), centred on the robot centre",
                "rows": "forward x, row 0 farthest ahead: x = x_max_m - (row + 0.5) * resolution_m",
                "cols": "lateral y, col 0 farthest left: y = y_max_m - (col + 0.5) * resolution_m",
                "values": "True = static obstacle or outside the scene's grid; nearest world cell"}


@functools.cache
def _cell_centres(spec: LocalMapSpec) -> np.ndarray:
    rows, cols = spec.shape
    x = spec.x_max_m - (np.arange(rows) + 0.5) * spec.resolution_m
    y = spec.y_max_m - (np.arange(cols) + 0.5) * spec.resolution_m
    out = np.stack(np.meshgrid(x, y, indexing="ij"), -1)
    out.setflags(write=False)
    return out


def local_occupancy(grid: np.ndarray, origin_xy: tuple[float, float] | list[float], resolution_m: float,
                    pose: np.ndarray, spec: LocalMapSpec) -> np.ndarray:
    """Samples the static world grid around a robot pose (vectorised nearest-cell lookup).

    Args:
        grid: ``H x W`` bool world occupancy; cell ``[i, j]`` has its centre at
            ``(origin_x + j * resolution_m, origin_y + i * resolution_m)`` (see :class:`recorder.drive.Episode`).
        origin_xy: world ``(x, y)`` of the centre of cell ``[0, 0]``.
        resolution_m: world cell size.
        pose: robot pose ``[x, y, yaw]`` in the world frame.
        spec: the crop's geometry.

    Returns:
        ``spec.shape`` bool array laid out as :class:`LocalMapSpec` describes.
    """
    pts = spec.cell_centres()
    x, y, yaw = (float(v) for v in np.asarray(pose, dtype=np.float64)[:3])
    c, s = math.cos(yaw), math.sin(yaw)
    wx = x + c * pts[..., 0] - s * pts[..., 1]
    wy = y + s * pts[..., 0] + c * pts[..., 1]
    j = np.rint((wx - origin_xy[0]) / resolution_m).astype(np.int64)
    i = np.rint((wy - origin_xy[1]) / resolution_m).astype(np.int64)
    h, w = grid.shape
    inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)
    out = np.ones(spec.shape, dtype=bool)
    out[inside] = grid[i[inside], j[inside]]
    return out


@dataclass(frozen=True)
class ExportSpec:
    """Every size of an exported dataset.

    Attributes:
        camera_sizes: per camera name, ``(height, width)`` in pixels.
        max_people: ``K``, detections per frame (``sim.detector.DetectorConfig.max_people``).
        n_max: ``N_MAX``, rows of the padded pedestrian arrays; a bigger crowd is an error.
        local_map: geometry of ``privileged.local_occupancy``.
    """

    camera_sizes: dict[str, tuple[int, int]]
    max_people: int = DEFAULT_MAX_PEOPLE
    n_max: int = N_MAX_PEDESTRIANS
    local_map: LocalMapSpec = field(default_factory=LocalMapSpec)
    labels: bool = False  # frames carry the labeller's command (``Frame.label`` -> ``action.teacher``)

    @staticmethod
    def from_meta(meta: EpisodeMeta, max_people: int = DEFAULT_MAX_PEOPLE, n_max: int = N_MAX_PEDESTRIANS,
                  local_map: LocalMapSpec | None = None, source: str = "episode", labels: bool = False) -> ExportSpec:
        """The spec of a dataset whose cameras are those of ``meta``.

        Raises:
            FeatureError: ``meta.cameras`` lacks a camera of :data:`recorder.schema.CAMERA_NAMES` or its size.
        """
        sizes = {}
        for cam in CAMERA_NAMES:
            c = (meta.cameras or {}).get(cam)
            if not isinstance(c, dict) or "height" not in c or "width" not in c:
                raise FeatureError(f"{source}: episode metadata field 'cameras[{cam}]': expected a camera dict "
                                   f"with 'height' and 'width', got {c!r}")
            sizes[cam] = (int(c["height"]), int(c["width"]))
        return ExportSpec(sizes, max_people, n_max, local_map or LocalMapSpec(), labels)

    def features(self) -> dict[str, dict[str, Any]]:
        """The LeRobot ``features`` dict (without lerobot's own index/timestamp features)."""
        k, n = self.max_people, self.n_max
        feats: dict[str, dict[str, Any]] = {}
        for cam in CAMERA_NAMES:
            h, w = self.camera_sizes[cam]
            feats[image_key(cam)] = {"dtype": "video", "shape": (h, w, 3), "names": ["height", "width", "channels"]}
        for cam in CAMERA_NAMES:
            h, w = self.camera_sizes[cam]
            feats[depth_key(cam)] = {"dtype": "uint16", "shape": (h, w), "names": ["height", "width"]}
        feats.update({
            OBS_STATE: {"dtype": "float32", "shape": (5,), "names": ["g_x", "g_y", "d_g", "v_x", "v_y"]},
            OBS_ODOM: {"dtype": "float32", "shape": (3,), "names": ["x", "y", "yaw"]},
            OBS_GOAL: {"dtype": "float32", "shape": (2,), "names": ["x", "y"]},
            OBS_POSES: {"dtype": "float32", "shape": (k * N_JOINTS * 3,), "names": _joint_names(k, "xyz")},
            OBS_POSE_MASK: {"dtype": "float32", "shape": (k * N_JOINTS,), "names": _joint_names(k)},
            OBS_POSE_CONF: {"dtype": "float32", "shape": (k * N_JOINTS,), "names": _joint_names(k)},
            ACTION: {"dtype": "float32", "shape": (2,), "names": ["v", "omega"]},
            **({ACTION_TEACHER: {"dtype": "float32", "shape": (2,), "names": ["v", "omega"]}} if self.labels else {}),
            NEXT_REWARD: {"dtype": "float32", "shape": (1,), "names": ["reward"]},
            NEXT_REWARD_TERMS: {"dtype": "float32", "shape": (len(REWARD_TERMS),), "names": list(REWARD_TERMS)},
            NEXT_DONE: {"dtype": "bool", "shape": (1,), "names": ["done"]},
            PRIV_PED_STATE: {"dtype": "float32", "shape": (n, len(PED_STATE_COLUMNS)),
                                     "names": ["pedestrian", "state"]},
            PRIV_PED_KEYPOINTS: {"dtype": "float32", "shape": (n, N_JOINTS, 3),
                                         "names": ["pedestrian", "joint", "xyz"]},
            PRIV_PED_INTENT: {"dtype": "float32", "shape": (n, 2), "names": ["pedestrian", "xy"]},
            PRIV_POSE_TRACK: {"dtype": "int64", "shape": (k,), "names": ["person"]},
            PRIV_D_O: {"dtype": "float32", "shape": (1,), "names": ["d_o"]},
            PRIV_LOCAL_OCCUPANCY: {"dtype": "bool", "shape": self.local_map.shape,
                                           "names": ["forward", "lateral"]},
        })
        return feats

    def describe(self) -> dict[str, Any]:
        """What each feature's axes and values mean (for ``meta/icrowdnav.json``)."""
        k, n = self.max_people, self.n_max
        return {
            "camera_sizes": {c: list(hw) for c, hw in self.camera_sizes.items()},
            "max_people": k, "n_max": n, "local_map": self.local_map.to_dict(),
            "coco_keypoints": list(COCO_KEYPOINTS), "reward_terms": list(REWARD_TERMS),
            "ped_state_columns": list(PED_STATE_COLUMNS),
            "frames": {"world": "the scene's frame, z up", "robot": "x forward, y left, z up, origin under the "
                       "robot centre", "camera": "OpenCV: x right, y down, z forward"},
            "features": {
                "observation.images.*": "RGB, video (AV1 mp4 via PyAV/SVT-AV1, yuv420p): lossy",
                "observation.depth.*": "z-depth along the optical axis, mm, 0 = invalid (uint16)",
                OBS_STATE: "[g_x, g_y, d_g, v_x, v_y]: goal in the robot frame (m), its distance (m), "
                                     "robot velocity in the robot frame (m/s)",
                OBS_ODOM: "robot pose [x, y, yaw] in the world frame (m, rad)",
                OBS_GOAL: "goal [x, y] in the world frame (m)",
                OBS_POSES: f"{k} detected people x COCO-17 joints x [x, y, z], robot frame (m), "
                                     "nearest first, zeros where not detected; flat, C order (person, joint, xyz)",
                OBS_POSE_MASK: "1.0 where the joint was detected, 0.0 where not; flat (person, joint)",
                OBS_POSE_CONF: "detector confidence of each joint; flat (person, joint)",
                ACTION: ACTION_CONVENTION,
                **({ACTION_TEACHER: "the DAgger teacher's command [v m/s, omega rad/s] for this frame's "
                                      "observation (the behaviour-cloning label)"} if self.labels else {}),
                NEXT_REWARD: "the paper's reward of the step from this frame to the next",
                NEXT_REWARD_TERMS: "the reward's terms in reward_terms order",
                NEXT_DONE: "True when the step from this frame ended the episode (terminated or truncated): the "
                           "episode's last dataset frame",
                PRIV_PED_STATE: f"{n} rows (row n = pedestrian n, zeros beyond the crowd) of "
                                        "[x, y, vx, vy] world (m, m/s), radius (m), body yaw, head yaw "
                                        "(world, rad), present (1 = a real pedestrian)",
                PRIV_PED_KEYPOINTS: "true COCO-17 keypoints of each pedestrian row, world frame (m)",
                PRIV_PED_INTENT: "each pedestrian row's pending goal [x, y], world frame (m)",
                PRIV_POSE_TRACK: "row of privileged.ped_state each detection belongs to, -1 = padding",
                PRIV_D_O: "robot centre to the nearest pedestrian/obstacle surface (m)",
                PRIV_LOCAL_OCCUPANCY: "see local_map",
            },
        }


def _joint_names(people: int, axes: str = "") -> list[str]:
    """Element names of a flat detection feature: ``p0.nose.x``, ... (or ``p0.nose``, ... without axes)."""
    return [f"p{p}.{j}" + (f".{a}" if a else "") for p in range(people) for j in COCO_KEYPOINTS for a in (axes or [""])]


def unflatten_poses(poses: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """The flat ``observation.poses`` (``... x K*51``) and ``observation.pose_mask`` (``... x K*17``) as
    ``... x K x 17 x 3`` and ``... x K x 17`` (any leading axes, numpy or torch)."""
    p = poses.reshape(*poses.shape[:-1], -1, N_JOINTS, 3)
    return p, None if mask is None else mask.reshape(*mask.shape[:-1], -1, N_JOINTS)


def feature_info(spec: ExportSpec, cameras: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The ``info`` dict of each feature of ``spec`` for ``meta/info.json`` (see the module docstring).

    Args:
        spec: the dataset's sizes.
        cameras: per camera name, its ``CameraSpec.to_dict()`` (intrinsics ``K``, extrinsics ``T_base_cam``, size).
    """
    desc = spec.describe()["features"]
    out: dict[str, dict[str, Any]] = {}
    for name in spec.features():
        text = desc.get(name) or desc.get(name.rsplit(".", 1)[0] + ".*", "")
        out[name] = {"description": text}
    for cam in CAMERA_NAMES:
        out[image_key(cam)]["camera"] = dict(cameras[cam])
        depth_cam = {**cameras[cam], "depth_units": "mm in this feature (uint16), z along the optical axis, 0 = invalid"}
        out[depth_key(cam)].update({"camera": depth_cam, "unit": "mm", "scale_to_m": DEPTH_SCALE_M, "invalid_value": 0})
    out[ACTION].update({"convention": ACTION_CONVENTION, "units": ["m/s", "rad/s"], FORMAT_KEY: FORMAT_VERSION})
    for key, shape in ((OBS_POSES, [spec.max_people, N_JOINTS, 3]), (OBS_POSE_MASK, [spec.max_people, N_JOINTS]),
                       (OBS_POSE_CONF, [spec.max_people, N_JOINTS])):
        out[key].update({"joints": list(COCO_KEYPOINTS), "unflattened_shape": shape, "order": "C"})
    out[PRIV_PED_KEYPOINTS]["joints"] = list(COCO_KEYPOINTS)
    out[PRIV_PED_STATE]["columns"] = list(PED_STATE_COLUMNS)
    out[NEXT_REWARD_TERMS]["terms"] = list(REWARD_TERMS)
    out[PRIV_LOCAL_OCCUPANCY]["layout"] = spec.local_map.to_dict()
    return out


def _describe(a: Any) -> str:
    """``shape (48, 64) float32`` for arrays, the type name otherwise."""
    if isinstance(a, np.ndarray):
        return f"shape {tuple(a.shape)} {a.dtype}"
    if a is None:
        return "nothing (missing)"
    return f"a {type(a).__name__} ({a!r:.60})"


_KIND_TEXT = {"f": "a float dtype", "u1": "uint8", "b": "bool (or 0/1 integers)", "i": "an integer dtype"}


def _dtype_ok(a: np.ndarray, kind: str) -> bool:
    if kind == "f":
        return a.dtype.kind == "f"
    if kind == "u1":
        return a.dtype == np.uint8
    if kind == "b":
        return a.dtype.kind == "b" or (a.dtype.kind in "iu" and bool(np.all((a == 0) | (a == 1))))
    if kind == "i":
        return a.dtype.kind in "iu"
    raise ValueError(kind)


class _FrameChecker:
    """Checks the fields of one recorded frame, raising :class:`FeatureError` with file/field/expected/actual."""

    def __init__(self, source: str, step: Any):
        self.where = f"{source}: frame {step}"

    def fail(self, name: str, expected: str, actual: str, feature: str | None = None) -> None:
        feat = f" (feature '{feature}')" if feature else ""
        raise FeatureError(f"{self.where}: field '{name}'{feat}: expected {expected}, got {actual}")

    def array(self, name: str, value: Any, shape: tuple[int | None, ...], kind: str,
              feature: str | None = None) -> np.ndarray:
        """``value`` as an ndarray of ``shape`` (``None`` = any size) and dtype ``kind``, all finite if float."""
        shown = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        expected = f"shape {shown} {_KIND_TEXT[kind]}"
        if not isinstance(value, np.ndarray):
            if not isinstance(value, list | tuple | np.generic):
                self.fail(name, expected, _describe(value), feature)
            value = np.asarray(value)
            if value.dtype == object:
                self.fail(name, expected, "a ragged sequence", feature)
        if value.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, value.shape, strict=True)):
            self.fail(name, expected, _describe(value), feature)
        if not _dtype_ok(value, kind):
            self.fail(name, expected, _describe(value), feature)
        if kind == "f" and not np.all(np.isfinite(value)):
            bad = int(np.size(value) - np.count_nonzero(np.isfinite(value)))
            self.fail(name, f"finite values ({expected})", f"{bad} NaN/inf value(s)", feature)
        return value

    def scalar(self, name: str, value: Any, feature: str | None = None) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
            self.fail(name, "a finite number", _describe(value), feature)
        if not math.isfinite(float(value)):
            self.fail(name, "a finite number", repr(float(value)), feature)
        return float(value)


_MISSING = object()


def _field(frame: Any, name: str, chk: _FrameChecker) -> Any:
    value = getattr(frame, name, _MISSING)
    if value is _MISSING or value is None:
        chk.fail(name, f"a value (Frame.{name})", "nothing (missing)")
    return value


def frame_to_features(frame: Frame, following: Frame, meta: EpisodeMeta, occupancy: np.ndarray, spec: ExportSpec,
                      source: str, frame_index: int) -> dict[str, np.ndarray]:
    """One dataset frame (the ``add_frame`` dict of :meth:`ExportSpec.features`, without ``task``): observation
    ``frame_index`` from ``frame`` and the step it starts (``action``, ``next.*``) from ``following``, the recorded
    frame that step led to (the MCAP log's frame carries the command that led to it: see the module docstring).

    Args:
        frame: the recorded frame ``t`` (:class:`recorder.schema.Frame` or anything with its attributes).
        following: the recorded frame ``t + 1``.
        meta: their episode's metadata (crowd size, occupancy geometry).
        occupancy: the episode's static world grid (``H x W`` bool).
        spec: the dataset's sizes.
        source: the file (or in-memory episode) it came from, for error messages.
        frame_index: ``t``, the position of ``frame`` in its episode (``frame.step`` must equal it).

    Raises:
        FeatureError: a field is missing, has the wrong shape or dtype, holds NaN/inf, or exceeds a max size.
    """
    out = observation_features(frame, meta, occupancy, spec, source, frame_index)
    out.update(step_features(following, source, frame_index + 1))
    return out


def _check_step(frame: Frame, chk: _FrameChecker, frame_index: int) -> None:
    step = _field(frame, "step", chk)
    if isinstance(step, bool) or not isinstance(step, int | np.integer) or int(step) != frame_index:
        chk.fail("step", f"{frame_index} (frames numbered 0, 1, 2, ... without gaps)", repr(step))


def step_features(frame: Frame, source: str, frame_index: int) -> dict[str, np.ndarray]:
    """``action`` and ``next.*`` of the step that led to recorded frame ``frame_index`` (``frame``): what the
    dataset stores at frame ``frame_index - 1``."""
    chk = _FrameChecker(source, getattr(frame, "step", f"#{frame_index}"))
    _check_step(frame, chk, frame_index)
    out = {ACTION: chk.array(ACTION, _field(frame, ACTION, chk), (2,), "f", ACTION).astype(np.float32, copy=False)}
    out[NEXT_REWARD] = np.array([chk.scalar("reward", _field(frame, "reward", chk), NEXT_REWARD)], np.float32)
    terms = _field(frame, "reward_terms", chk)
    if not isinstance(terms, dict) or set(terms) - set(REWARD_TERMS):
        chk.fail("reward_terms", f"a dict with keys from {list(REWARD_TERMS)}",
                 _describe(terms) if not isinstance(terms, dict) else f"keys {sorted(terms)}", NEXT_REWARD_TERMS)
    out[NEXT_REWARD_TERMS] = np.array(
        [chk.scalar(f"reward_terms[{t}]", terms.get(t, 0.0), NEXT_REWARD_TERMS) for t in REWARD_TERMS], np.float32)
    done = _field(frame, "done", chk)
    if not isinstance(done, bool | np.bool_):
        chk.fail("done", "a bool", _describe(done), NEXT_DONE)
    out[NEXT_DONE] = np.array([bool(done)], dtype=bool)
    return out


def observation_features(frame: Frame, meta: EpisodeMeta, occupancy: np.ndarray, spec: ExportSpec, source: str,
                         frame_index: int) -> dict[str, np.ndarray]:
    """The observation, label and privileged features of recorded frame ``frame_index`` (all but ``action`` and
    ``next.*``; arguments as :func:`frame_to_features`)."""
    chk = _FrameChecker(source, getattr(frame, "step", f"#{frame_index}"))
    _check_step(frame, chk, frame_index)
    out: dict[str, np.ndarray] = {}
    rgb, depth = _field(frame, "rgb", chk), _field(frame, "depth", chk)
    for cam in CAMERA_NAMES:
        h, w = spec.camera_sizes[cam]
        out[image_key(cam)] = chk.array(f"rgb[{cam}]", rgb.get(cam) if isinstance(rgb, dict) else None,
                                        (h, w, 3), "u1", image_key(cam))
        d = chk.array(f"depth[{cam}]", depth.get(cam) if isinstance(depth, dict) else None, (h, w), "f",
                      depth_key(cam))
        if d.size and (float(d.min()) < 0.0 or float(d.max()) > 65535 * DEPTH_SCALE_M):
            chk.fail(f"depth[{cam}]", f"depths in [0, {65535 * DEPTH_SCALE_M:g}] m (uint16 millimetres)",
                     f"range [{float(d.min()):g}, {float(d.max()):g}] m", depth_key(cam))
        out[depth_key(cam)] = depth_to_mm(d)  # exact for depth read from the MCAP log, which keeps millimetres

    def f32(name: str, shape: tuple[int | None, ...], feature: str) -> np.ndarray:
        return chk.array(name, _field(frame, name, chk), shape, "f", feature).astype(np.float32, copy=False)

    out[OBS_STATE] = f32("state", (5,), OBS_STATE)
    odom = f32("odom", (3,), OBS_ODOM)
    out[OBS_ODOM] = odom
    out[OBS_GOAL] = f32("goal_xy", (2,), OBS_GOAL)
    if spec.labels:
        out[ACTION_TEACHER] = f32("label", (2,), ACTION_TEACHER)

    k = spec.max_people
    poses = chk.array("poses", _field(frame, "poses", chk), (None, N_JOINTS, 3), "f", OBS_POSES)
    kf = poses.shape[0]
    if kf > k:
        chk.fail("poses", f"at most {k} detected people (max_people)", f"{kf}", OBS_POSES)
    mask = chk.array("pose_mask", _field(frame, "pose_mask", chk), (kf, N_JOINTS), "b", OBS_POSE_MASK)
    conf = chk.array("pose_conf", _field(frame, "pose_conf", chk), (kf, N_JOINTS), "f", OBS_POSE_CONF)
    track = chk.array("pose_track", _field(frame, "pose_track", chk), (kf,), "i", PRIV_POSE_TRACK)
    out[OBS_POSES] = _pad(poses.astype(np.float32, copy=False), k, 0.0).reshape(-1)
    out[OBS_POSE_MASK] = _pad(mask.astype(np.float32), k, 0.0).reshape(-1)
    out[OBS_POSE_CONF] = _pad(conf.astype(np.float32, copy=False), k, 0.0).reshape(-1)
    out[PRIV_POSE_TRACK] = _pad(track.astype(np.int64, copy=False), k, -1)

    n = int(meta.n_pedestrians)
    if n > spec.n_max:
        chk.fail("ped_pos", f"at most {spec.n_max} pedestrians (n_max; raise it)", f"{n} (meta.n_pedestrians)",
                 PRIV_PED_STATE)
    pos = f32("ped_pos", (n, 2), PRIV_PED_STATE)
    vel = f32("ped_vel", (n, 2), PRIV_PED_STATE)
    radius = f32("ped_radius", (n,), PRIV_PED_STATE)
    yaw = f32("ped_yaw", (n, 3), PRIV_PED_STATE)
    intent = f32("ped_intent_xy", (n, 2), PRIV_PED_INTENT)
    kp = f32("ped_keypoints", (n, N_JOINTS, 3), PRIV_PED_KEYPOINTS)
    state = np.zeros((spec.n_max, len(PED_STATE_COLUMNS)), np.float32)
    state[:n, 0:2], state[:n, 2:4], state[:n, 4] = pos, vel, radius
    state[:n, 5], state[:n, 6], state[:n, 7] = yaw[:, 0], yaw[:, 2], 1.0
    out[PRIV_PED_STATE] = state
    out[PRIV_PED_KEYPOINTS] = _pad(kp, spec.n_max, 0.0)
    out[PRIV_PED_INTENT] = _pad(intent, spec.n_max, 0.0)
    out[PRIV_D_O] = np.array([chk.scalar("d_o", _field(frame, "d_o", chk), PRIV_D_O)], np.float32)
    out[PRIV_LOCAL_OCCUPANCY] = local_occupancy(
        occupancy, meta.occupancy_origin_xy, meta.occupancy_resolution_m, odom, spec.local_map)
    return out


def _pad(a: np.ndarray, rows: int, fill: Any) -> np.ndarray:
    """``a`` padded with ``fill`` rows up to ``rows`` along axis 0 (a contiguous copy-free view when full)."""
    if a.shape[0] == rows:
        return np.ascontiguousarray(a)
    out = np.full((rows, *a.shape[1:]), fill, dtype=a.dtype)
    out[: a.shape[0]] = a
    return out


def check_features(values: dict[str, Any], features: dict[str, dict[str, Any]], source: str,
                   frame_index: int) -> None:
    """Checks an ``add_frame`` dict against a feature spec before it reaches lerobot.

    Args:
        values: feature name → value (``task`` is ignored).
        features: the spec (:meth:`ExportSpec.features`).
        source: file the frame came from, for messages.
        frame_index: the frame's index in its episode, for messages.

    Raises:
        FeatureError: a feature is missing or extra, or has the wrong shape or dtype.
    """
    where = f"{source}: frame {frame_index}"
    for name, ft in features.items():
        if name not in values:
            raise FeatureError(f"{where}: feature '{name}': expected {ft['dtype']} of shape {tuple(ft['shape'])}, "
                               "got nothing (missing)")
        v = values[name]
        dtype = np.dtype("uint8") if ft["dtype"] == "video" else np.dtype(ft["dtype"])
        if not isinstance(v, np.ndarray) or v.shape != tuple(ft["shape"]) or v.dtype != dtype:
            raise FeatureError(f"{where}: feature '{name}': expected shape {tuple(ft['shape'])} {dtype}, "
                               f"got {_describe(v)}")
    extra = sorted(set(values) - set(features) - {"task"})
    if extra:
        raise FeatureError(f"{where}: feature '{extra[0]}': expected only the spec's features "
                           f"({len(features)}), got extra feature(s) {extra}")


def meta_facts(meta: EpisodeMeta) -> dict[str, Any]:
    """The episode metadata as plain JSON data."""
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(meta).items()}


def cameras_of(meta: EpisodeMeta) -> dict[str, dict[str, Any]]:
    """Intrinsics/extrinsics of the episode's cameras (``CameraSpec.to_dict`` of each)."""
    return {c: dict(meta.cameras[c]) for c in CAMERA_NAMES if c in (meta.cameras or {})}
