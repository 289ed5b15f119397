"""Observation and dataset feature names, one place (LeRobot's convention: ``observation.*``, ``action``,
``next.*``; ours: ``privileged.*`` for what only the simulator knows). Shapes, units and frames of each feature are
in :mod:`recorder.features` (and in every dataset's ``meta/icrowdnav.json``)."""

from __future__ import annotations

OBS_STATE = "observation.state"  # s = [g_x, g_y, d_g, v_x, v_y], robot frame
OBS_ODOM = "observation.odom"  # [x, y, yaw], world frame
OBS_GOAL = "observation.goal"  # [x, y], world frame
OBS_POSES = "observation.poses"  # detected people x COCO-17 joints x xyz, robot frame
OBS_POSE_MASK = "observation.pose_mask"
OBS_POSE_CONF = "observation.pose_conf"
OBS_IMAGES = "observation.images"  # + ".<camera>"
OBS_DEPTH = "observation.depth"  # + ".<camera>"
ACTION = "action"
ACTION_TEACHER = "action.teacher"
NEXT_REWARD = "next.reward"
NEXT_REWARD_TERMS = "next.reward_terms"
NEXT_DONE = "next.done"
PRIV_PED_STATE = "privileged.ped_state"
PRIV_PED_INTENT = "privileged.ped_intent"
PRIV_PED_KEYPOINTS = "privileged.ped_keypoints"
PRIV_POSE_TRACK = "privileged.pose_track"
PRIV_LOCAL_OCCUPANCY = "privileged.local_occupancy"
PRIV_D_O = "privileged.d_o"


def image_key(camera: str) -> str:
    """The RGB video feature of ``camera`` (``observation.images.<camera>``)."""
    return f"{OBS_IMAGES}.{camera}"


def depth_key(camera: str) -> str:
    """The depth feature of ``camera`` (``observation.depth.<camera>``)."""
    return f"{OBS_DEPTH}.{camera}"
