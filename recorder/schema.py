"""What one recorded step and one recorded episode contain — the contract between the env, the MCAP log and the
LeRobot export.

A :class:`Frame` is one env step (after the action took effect) as the robot saw it plus the privileged labels
later stages need; :class:`EpisodeMeta` is everything constant over an episode. :func:`frame_from_env` builds a
frame from a visual-mode :class:`sim.env.CrowdNavEnv`; :func:`episode_meta_from_env` the metadata.

Frames (SI units, float32 unless said otherwise):

=================  ======================  ==========================================================
field              shape                   meaning
=================  ======================  ==========================================================
step               int                     0 = the state after reset, k = after the k-th action
t_ns               int                     simulation time, ns (= step · dt); the MCAP log time
rgb[cam]           H x W x 3 uint8         camera image, cam ∈ CAMERA_NAMES
depth[cam]         H x W                   z-depth in m, 0 = invalid
state              5                       s = [g_x, g_y, d_g, v_x, v_y], robot frame
odom               3                       robot pose [x, y, yaw], world frame
action             2                       the command that led to this frame [v m/s, ω rad/s]
                                           (zeros at step 0)
goal_xy            2                       goal, world frame
poses              K x 17 x 3              detected COCO-17 joints, robot frame (K = max_people)
pose_mask          K x 17 bool             detected joints
pose_conf          K x 17                  detector confidence
pose_track         K int64                 true pedestrian index of each detection, −1 = padding
ped_pos, ped_vel   N x 2                   true pedestrian positions (m) / velocities (m/s), world
ped_radius         N                       body disc radii, m
ped_yaw            N x 3                   body, torso, head yaw (world frame), rad
ped_intent_xy      N x 2                   where each pedestrian is heading in mind (pending goal)
ped_keypoints      N x 17 x 3              true COCO-17 keypoints, world frame
reward             float                   the paper's reward for the step (0 at step 0)
reward_terms       dict[str, float]        success / collision / near / progress / spin / total
d_o                float                   robot centre to the nearest pedestrian/obstacle surface, m
done               bool                    terminated or truncated at this step
outcome            str                     "" while running; success / collision_* / timeout at the end
label              2 or None               optional: the command a labeller (the DAgger teacher) gives for
                                           this frame's observation [v m/s, ω rad/s]; exported as
                                           ``action.teacher`` when the episodes carry it
=================  ======================  ==========================================================
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field

import numpy as np

from pipeline.core.config import to_dict

CAMERA_NAMES = ("left", "right")
DEPTH_SCALE_M = 0.001  # metres per depth count: the MCAP log (16UC1) and the dataset (uint16) keep millimetres


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

FRAME_WORLD = "world"
FRAME_BASE = "base_link"

# MCAP topics (Foxglove schemas where one fits; JSON with a JSON schema for structured arrays)
TOPIC_RGB = "/camera/{cam}/image"  # foxglove.RawImage rgb8
TOPIC_DEPTH = "/camera/{cam}/depth"  # foxglove.RawImage 16UC1, millimetres, 0 = invalid
TOPIC_CALIB = "/camera/{cam}/calibration"  # foxglove.CameraCalibration
TOPIC_KEYPOINTS_2D = "/camera/{cam}/keypoints"  # foxglove.ImageAnnotations (detected joints)
TOPIC_TF = "/tf"  # foxglove.FrameTransforms: world -> base_link -> camera_{cam}
TOPIC_ROBOT_POSE = "/robot/pose"  # foxglove.PoseInFrame
TOPIC_GOAL = "/robot/goal"  # foxglove.PoseInFrame
TOPIC_ROBOT = "/robot/state"  # json: step, state, odom, action, goal_xy
TOPIC_PEDS_SCENE = "/pedestrians/scene"  # foxglove.SceneUpdate (bodies + heading arrows, for display)
TOPIC_PEDS = "/pedestrians/state"  # json: pos, vel, radius, yaw, intent_xy, keypoints
TOPIC_DETECTIONS = "/perception/poses"  # json: poses, mask, confidence, track ids (robot frame)
TOPIC_REWARD = "/episode/reward"  # json: reward, terms, d_o, done, outcome
TOPIC_OCCUPANCY = "/map/occupancy"  # foxglove.Grid, once at t = 0 (static map)

METADATA_EPISODE = "episode"  # MCAP metadata record name


@dataclass
class EpisodeMeta:
    """Constant facts of an episode (stored as MCAP metadata; strings only there, JSON-encoded values).

    Attributes:
        scene, density, seed: what was run (``seed`` is the reset seed).
        episode_seed: the env's internal episode seed derived from it.
        driver: who drove (``expert`` or a checkpoint path).
        config_hash: sha256 of the resolved sim config (JSON).
        dt_s: control period.
        cameras: per camera name, :meth:`sim.cameras.CameraSpec.to_dict`.
        start_xy, goal_xy: world positions, m.
        robot_radius_m, goal_radius_m: m.
        occupancy_origin_xy, occupancy_resolution_m, occupancy_shape: the static occupancy grid's geometry.
        renderer: rendering backend.
        n_pedestrians: crowd size.
    """

    scene: str
    density: float
    seed: int
    episode_seed: int
    driver: str
    config_hash: str
    dt_s: float
    cameras: dict[str, dict]
    start_xy: list[float]
    goal_xy: list[float]
    robot_radius_m: float
    goal_radius_m: float
    occupancy_origin_xy: list[float]
    occupancy_resolution_m: float
    occupancy_shape: list[int]
    n_pedestrians: int
    renderer: str = "pybullet-3.2.7 TinyRenderer (CPU)"

    def to_metadata(self) -> dict[str, str]:
        """MCAP metadata (a str → str map): each field JSON-encoded."""
        return {k: json.dumps(v) for k, v in self.__dict__.items()}

    @staticmethod
    def from_metadata(md: dict[str, str]) -> EpisodeMeta:
        return EpisodeMeta(**{k: json.loads(v) for k, v in md.items()})


@dataclass
class Frame:
    """One recorded step (see the module docstring for fields, shapes and frames)."""

    step: int
    t_ns: int
    rgb: dict[str, np.ndarray]
    depth: dict[str, np.ndarray]
    state: np.ndarray
    odom: np.ndarray
    action: np.ndarray
    goal_xy: np.ndarray
    poses: np.ndarray
    pose_mask: np.ndarray
    pose_conf: np.ndarray
    pose_track: np.ndarray
    ped_pos: np.ndarray
    ped_vel: np.ndarray
    ped_radius: np.ndarray
    ped_yaw: np.ndarray
    ped_intent_xy: np.ndarray
    ped_keypoints: np.ndarray
    reward: float = 0.0
    reward_terms: dict[str, float] = field(default_factory=dict)
    d_o: float = float("inf")
    done: bool = False
    outcome: str = ""
    label: np.ndarray | None = None


def sim_config_hash(cfg) -> str:
    """sha256 of a sim config's canonical JSON."""

    return hashlib.sha256(json.dumps(to_dict(cfg), sort_keys=True).encode()).hexdigest()


def episode_meta_from_env(env, seed: int, driver: str) -> EpisodeMeta:
    """Metadata of the episode an unwrapped :class:`sim.env.CrowdNavEnv` has just been reset into."""
    u = env
    return EpisodeMeta(
        scene=u.spec_scene.name, density=float(u.cfg.density), seed=int(seed), episode_seed=int(u.episode_seed),
        driver=driver, config_hash=sim_config_hash(u.cfg), dt_s=float(u.cfg.dt_s),
        cameras={spec.name: spec.to_dict() for spec in u.cameras},
        start_xy=[float(v) for v in u.start], goal_xy=[float(v) for v in u.goal],
        robot_radius_m=float(u.cfg.robot.radius_m), goal_radius_m=float(u.cfg.goal_radius_m),
        occupancy_origin_xy=[float(v) for v in u.layout.grid_origin], occupancy_resolution_m=0.05,
        occupancy_shape=[int(v) for v in u.layout.occupancy.shape], n_pedestrians=int(u.crowd.n),
    )


def frame_from_env(env, obs: dict, info: dict, step: int, command: tuple[float, float] = (0.0, 0.0),
                   reward: float = 0.0, done: bool = False, label: tuple[float, float] | None = None) -> Frame:
    """Build a :class:`Frame` from an unwrapped visual-mode env right after ``reset`` or ``step``.

    Args:
        env: the unwrapped env (``obs_mode="visual"``, ``info_level="full"``).
        obs, info: what ``reset``/``step`` returned.
        step: 0 after reset, k after the k-th step.
        command: the physical (v, ω) that was executed (zeros at step 0).
        reward, done: what ``step`` returned (``done`` = terminated or truncated).
        label: the labeller's command for this frame's observation (DAgger), or None.
    """
    priv = info["privileged"]
    det = env.last_detections
    dt_ns = int(round(env.cfg.dt_s * 1e9))
    return Frame(
        step=step, t_ns=step * dt_ns,
        rgb={c: obs[f"rgb_{c}"] for c in CAMERA_NAMES}, depth={c: obs[f"depth_{c}"] for c in CAMERA_NAMES},
        state=obs["state"].astype(np.float32), odom=obs["odom"].astype(np.float32),
        action=np.asarray(command, dtype=np.float32), goal_xy=priv["goal_xy"].astype(np.float32),
        poses=det.poses.astype(np.float32), pose_mask=det.joint_mask.astype(bool),
        pose_conf=det.confidence.astype(np.float32), pose_track=det.track_id.astype(np.int64),
        ped_pos=priv["ped_pos"].astype(np.float32), ped_vel=priv["ped_vel"].astype(np.float32),
        ped_radius=priv["ped_radius"].astype(np.float32),
        ped_yaw=np.stack([priv["ped_body_yaw"], priv["ped_torso_yaw"], priv["ped_head_yaw"]], -1).astype(np.float32),
        ped_intent_xy=priv["ped_intent_xy"].astype(np.float32),
        ped_keypoints=priv["keypoints_world"].astype(np.float32),
        reward=float(reward), reward_terms={k: float(v) for k, v in info.get("reward_terms", {}).items()},
        d_o=float(info["d_o"]), done=bool(done), outcome=info.get("outcome") or "",
        label=None if label is None else np.asarray(label, dtype=np.float32),
    )
