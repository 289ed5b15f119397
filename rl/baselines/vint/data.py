"""The ViNT-style baseline's data (package docstring): images at the training resolution, goal features, the
trajectory labels, and the recorded LeRobot dataset loaded into memory."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from pipeline.core import layout
from pipeline.core.errors import CorruptArtifactError, InputMissingError
from pipeline.core.keys import ACTION, OBS_GOAL, OBS_ODOM, image_key
from pretrain.data import decode_video_file
from recorder.dataset_info import read_dataset_info
from recorder.doctor_dataset import require_sound_dataset
from rl.baselines.vint.configuration import CAMERAS
from sim.geometry import world_to_robot_each


def resize_images(rgb: np.ndarray, hw: list[int]) -> np.ndarray:
    """``N x 3 x H x W`` uint8 -> ``N x 3 x h x w`` uint8 by area averaging (the same at training and deployment)."""
    x = torch.from_numpy(np.ascontiguousarray(rgb)).float()
    return F.interpolate(x, size=tuple(hw), mode="area").round_().to(torch.uint8).numpy()


def side_by_side(left: np.ndarray, right: np.ndarray, hw: list[int]) -> np.ndarray:
    """Two ``H x W x 3`` camera images -> one ``3 x h x 2w`` uint8 image (left | right)."""
    both = resize_images(np.stack([left, right]).transpose(0, 3, 1, 2), hw)
    return np.concatenate([both[0], both[1]], -1)


def goal_features(rel_xy: np.ndarray, scale_m: float) -> np.ndarray:
    """Goal points ``... x 2`` in the robot frame -> ``... x 3`` [cos θ, sin θ, tanh(d / scale_m)] float32."""
    rel = np.asarray(rel_xy, np.float64)
    ang, d = np.arctan2(rel[..., 1], rel[..., 0]), np.hypot(rel[..., 0], rel[..., 1])
    return np.stack([np.cos(ang), np.sin(ang), np.tanh(d / scale_m)], -1).astype(np.float32)


def context_indices(targets: np.ndarray, start: np.ndarray, context: int, spacing: int) -> np.ndarray:
    """``T x (P+1)`` frame indices of each target's context, oldest first, the target last; before the episode's
    first frame ``start`` that frame is repeated."""
    offsets = np.arange(context, -1, -1) * spacing
    return np.maximum(targets[:, None] - offsets[None, :], start[:, None])


def trajectory_labels(pose: np.ndarray, goal: np.ndarray, targets: np.ndarray, end: np.ndarray, horizon: int,
                      spacing: int, metres_per_step: float, max_dist: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ViNT's labels of some frames.

    Args:
        pose: ``F x 3`` world poses [x, y, yaw] of every frame. goal: ``F x 2`` world goal of every frame.
        targets: ``T`` frame indices. end: ``T`` one past the last frame of each target's episode.
        horizon, spacing: H waypoints, ``spacing`` frames apart. metres_per_step: the normalisation.
        max_dist: the distance label cap (steps).

    Returns:
        waypoints ``T x H x 4`` float32 [Δx, Δy (normalised, the target's robot frame), cos, sin of the relative
        yaw] of the poses ``t + k * spacing`` (k = 1..H; the last pose of the episode past its end); distance
        ``T`` float32: steps of ``spacing`` frames to the episode's last frame, capped at ``max_dist``; goal
        ``T x 2`` float32: the goal in the target's robot frame (m).
    """
    k = np.arange(1, horizon + 1) * spacing
    fut = np.minimum(targets[:, None] + k[None, :], end[:, None] - 1)  # T x H
    p0 = pose[targets]
    rel = world_to_robot_each(pose[fut].reshape(-1, 3)[:, :2], np.repeat(p0, horizon, 0)).reshape(-1, horizon, 2)
    dyaw = pose[fut][..., 2] - p0[:, None, 2]
    wp = np.concatenate([rel / metres_per_step, np.stack([np.cos(dyaw), np.sin(dyaw)], -1)], -1)
    dist = np.minimum((end - 1 - targets) / spacing, max_dist)
    return wp.astype(np.float32), dist.astype(np.float32), world_to_robot_each(goal[targets], p0).astype(np.float32)


@dataclass
class Frames:
    """Every frame of some episodes in memory, concatenated in episode order.

    Attributes:
        images: ``F x 3 x h x 2w`` uint8, left | right side by side, at the training resolution.
        pose: ``F x 3`` float64 world [x, y, yaw] (``observation.odom``).
        goal: ``F x 2`` float64 world goal (``observation.goal``).
        slices: ``[start, end)`` of each episode.
        action: ``F x 2`` float64 the expert's command [v, ω] (``action``; None where the frames are not from a
            dataset). Not a training label (ViNT learns waypoints): :mod:`rl.baselines.vint.diagnose` reads it.
    """

    images: np.ndarray
    pose: np.ndarray
    goal: np.ndarray
    slices: list[tuple[int, int]]
    action: np.ndarray | None = None

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``F`` start and end of each frame's episode."""
        start, end = np.zeros(len(self.pose), np.int64), np.zeros(len(self.pose), np.int64)
        for s, e in self.slices:
            start[s:e], end[s:e] = s, e
        return start, end


class _ResizeSink:
    """A write target for :func:`pretrain.data.decode_video_file`: ``sink[i, cam] = 3 x H x W`` frame, resized
    into camera ``cam``'s half of ``images[i]`` (in chunks of ``chunk`` frames: one resize call each; call
    :meth:`flush` after the last frame)."""

    def __init__(self, images: np.ndarray, hw: list[int], chunk: int = 512) -> None:
        self.images, self.hw, self.chunk = images, hw, chunk
        self.keys: list[tuple[int, int]] = []
        self.pending: list[np.ndarray] = []

    def __setitem__(self, key: tuple[int, int], chw: np.ndarray) -> None:
        self.keys.append(key)
        self.pending.append(chw)
        if len(self.pending) >= self.chunk:
            self.flush()

    def flush(self) -> None:
        if not self.pending:
            return
        small = resize_images(np.stack(self.pending), self.hw)
        w = self.hw[1]
        rows, cams = np.array(self.keys).T
        for cam in np.unique(cams):
            sel = cams == cam
            self.images[rows[sel], :, :, cam * w:(cam + 1) * w] = small[sel]
        self.keys, self.pending = [], []


def dataset_root(cfg) -> Path:
    """``DATA_DIR/datasets/<repo_id>`` of the train config ``cfg``."""
    return layout.dataset_dir(cfg.data_dir, cfg.vint.repo_id)


def check_dataset(root: Path) -> dict:
    """The dataset's features, after checking its format (:func:`recorder.dataset_info.read_dataset_info`), the
    features the baseline reads, and the doctor's cheap checks."""
    features = read_dataset_info(root).features
    need = [image_key(c) for c in CAMERAS] + [OBS_ODOM, OBS_GOAL, ACTION]
    missing = [k for k in need if k not in features]
    if missing:
        raise InputMissingError(f"vint: dataset {root} lacks {', '.join(missing)}; record it with `make record`")
    require_sound_dataset(root)  # a deleted / truncated parquet or video: named here, not by lerobot's errors
    return features


def load_dataset(root: Path, hw: list[int], episodes: int = 0, progress: bool = True) -> tuple[Frames, float]:
    """The first ``episodes`` episodes (0 = all) of a recorded LeRobot dataset at ``hw`` per camera, and its fps.

    Metadata and parquet columns through stock ``LeRobotDataset``; videos decoded sequentially per file by
    :func:`pretrain.data.decode_video_file`, each frame resized as it arrives.
    """
    # lazily: lerobot takes seconds to import, and only loading the dataset needs it
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = Path(root)
    check_dataset(root)
    try:
        ds = LeRobotDataset(f"{root.parent.name}/{root.name}", root=root, video_backend="pyav")
    except Exception as e:  # lerobot raises many types for broken datasets
        raise CorruptArtifactError(f"dataset {root}: cannot open it ({type(e).__name__}: {e})") from None
    fps = float(ds.meta.fps)
    n_eps = ds.meta.total_episodes if episodes <= 0 else min(episodes, ds.meta.total_episodes)
    meta = ds.meta.episodes
    rows = [(int(meta[e]["dataset_from_index"]), int(meta[e]["dataset_to_index"])) for e in range(n_eps)]
    n = sum(b - a for a, b in rows)
    idx = np.concatenate([np.arange(a, b) for a, b in rows])
    cols = ds.hf_dataset.select_columns([OBS_ODOM, OBS_GOAL, ACTION]).with_format("numpy")
    pose = np.asarray(cols[OBS_ODOM], np.float64)[idx]
    goal = np.asarray(cols[OBS_GOAL], np.float64)[idx]
    action = np.asarray(cols[ACTION], np.float64)[idx]
    starts = np.cumsum([0] + [b - a for a, b in rows])
    frames = Frames(np.zeros((n, 3, hw[0], 2 * hw[1]), np.uint8), pose, goal,
                    [(int(s), int(e)) for s, e in zip(starts[:-1], starts[1:], strict=True)], action)
    sink = _ResizeSink(frames.images, hw)
    for ci, cam in enumerate(CAMERAS):
        key = f"observation.images.{cam}"
        files: dict[Path, dict[int, tuple[float, float, int]]] = {}
        for e in range(n_eps):
            files.setdefault(root / ds.meta.get_video_file_path(e, key), {})[e] = (
                float(meta[e][f"videos/{key}/from_timestamp"]), float(meta[e][f"videos/{key}/to_timestamp"]),
                int(starts[e]))
        placed = 0
        for path, expected in tqdm(files.items(), desc=f"vint: decode {cam}", unit="file", disable=not progress):
            if not path.is_file():
                raise InputMissingError(f"dataset {root}: video file {path} is missing; re-record with `make record`")
            placed += decode_video_file(path, expected, fps, sink, ci, key)
            sink.flush()
        if placed != n:
            raise CorruptArtifactError(f"dataset {root}: {key}: decoded {placed} frames of the {n} its episodes list")
    return frames, fps
