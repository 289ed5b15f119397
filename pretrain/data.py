"""Training data of the BEV encoder: frames of a LeRobot dataset and their BEV occupancy labels.

A :class:`FrameStore` holds every frame of the chosen episodes in memory, aligned by the dataset's global frame
index (``index``):

* ``rgb``       ``F x N x 3 x H x W`` uint8 — decoded from the dataset's videos;
* ``depth``     ``F x N x h x w`` float32 m — the depth images at the lift pixels only (:func:`sample_depth`);
* ``pose``      ``F x 3`` float64 — ``observation.odom`` (world ``[x, y, yaw]``);
* ``labels``    ``F x 4 x X x Y`` uint8 — the pretext targets (:data:`pretrain.model.TARGETS`) in the BEV grid of
  each frame's robot: static obstacles (``privileged.local_occupancy`` resampled), pedestrians now, in 0.5 s and
  in 1.0 s (discs of each ``privileged.ped_state`` row's radius; future positions expressed in the *current*
  robot frame, as FIERY does; with ``people_label="seen"`` only the people the current frame's depth reaches);
* ``valid``     ``F x 4`` bool — False where a future lies beyond the episode's end.

Reading: the dataset is opened with stock ``LeRobotDataset`` (metadata, episode index, parquet columns through its
``datasets.Dataset``). Videos are decoded with PyAV *sequentially, one pass per video file*, and frames are placed
by the episode timestamps LeRobot records (``videos/<key>/from_timestamp``); LeRobot's per-frame
``decode_video_frames`` seeks for every query and is ~20x slower for a full pass (measured: 3.8 s for all 12,831
frames of one camera of the default dataset vs ~45 s episode by episode).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.core.errors import ConfigError, CorruptArtifactError, InputMissingError
from pipeline.core.keys import OBS_ODOM, PRIV_LOCAL_OCCUPANCY, PRIV_PED_STATE, depth_key, image_key
from pretrain.geometry import BEVGrid, Camera, LiftGeometry, cameras_from_meta, lift_evidence, sample_depth
from recorder.dataset_info import read_dataset_info
from recorder.doctor_dataset import require_sound_dataset
from recorder.schema import depth_from_mm

log = logging.getLogger("icrowdnav")

REQUIRED_FEATURES = (OBS_ODOM, PRIV_PED_STATE, PRIV_LOCAL_OCCUPANCY)


def camera_features(cameras: list[Camera]) -> list[str]:
    return [image_key(c.name) for c in cameras] + [depth_key(c.name) for c in cameras]


@dataclass
class DatasetMeta:
    """What pretraining reads from a dataset's metadata (:class:`recorder.dataset_info.DatasetInfo`: lerobot's
    ``info.json`` with our features' ``info``) and the cameras it uses."""

    info: dict
    cameras: list[Camera]
    local_map: dict
    fps: float
    repo_id: str


def check_dataset(root: Path, cameras: list[Camera] | None = None) -> DatasetMeta:
    """Checks that a dataset has what pretraining reads and returns its metadata.

    Args:
        root: dataset root.
        cameras: the cameras whose images and depth must be there (default: the dataset's own).

    Raises:
        InputMissingError: no dataset at ``root``, or it lacks needed features (all of them are named), or a file
            it needs is missing (named).
        CorruptArtifactError: unreadable metadata, or a damaged file (named): the dataset doctor's cheap checks
            (:func:`recorder.doctor_dataset.require_sound_dataset`, ~25 ms) run before lerobot opens it.
    """
    root = Path(root)
    ds_info = read_dataset_info(root)
    features = ds_info.features
    if cameras is None:
        cameras = cameras_from_meta({"cameras": ds_info.cameras}, f"{root / 'meta' / 'info.json'}")
    need = list(REQUIRED_FEATURES) + camera_features(cameras)
    missing = [k for k in need if k not in features]
    if missing:
        raise InputMissingError(f"dataset {root} lacks the feature(s) pretraining needs: {', '.join(missing)} "
                                f"(it has {len(features)} features; export it with `icrowdnav export`)")
    ps = features[PRIV_PED_STATE].get("shape", [])
    if len(ps) != 2 or ps[1] != 8:
        raise CorruptArtifactError(f"dataset {root}: privileged.ped_state: expected shape [n, 8], got {ps}")
    for c in cameras:
        shape = features[depth_key(c.name)].get("shape")
        if list(shape) != [c.height, c.width]:
            raise CorruptArtifactError(f"dataset {root}: observation.depth.{c.name}: expected shape "
                                       f"[{c.height}, {c.width}] (the camera's), got {shape}")
    if ds_info.local_map is None:
        raise CorruptArtifactError(f"dataset {root}: meta/info.json field 'features.privileged.local_occupancy.info."
                                   "layout': expected the crop's geometry, got nothing")
    require_sound_dataset(root)  # a deleted / truncated parquet or video: named here, not by lerobot's errors
    return DatasetMeta(ds_info.info, cameras, ds_info.local_map, float(ds_info.fps), ds_info.repo_id)


def check_grid_in_local_map(grid: BEVGrid, local_map: dict, where: str) -> None:
    """The static labels come from ``privileged.local_occupancy``: the BEV grid must lie inside that crop."""
    lm = local_map
    if (grid.x_bound[0] < lm["x_min_m"] - 1e-9 or grid.x_bound[1] > lm["x_max_m"] + 1e-9
            or grid.y_bound[0] < lm["y_min_m"] - 1e-9 or grid.y_bound[1] > lm["y_max_m"] + 1e-9):
        raise ConfigError(f"encoder grid x {grid.x_bound[:2]}, y {grid.y_bound[:2]} does not fit the static labels "
                          f"of {where} (privileged.local_occupancy covers x [{lm['x_min_m']}, {lm['x_max_m']}], "
                          f"y [{lm['y_min_m']}, {lm['y_max_m']}] m)")


def static_label_index(grid: BEVGrid, local_map: dict) -> tuple[np.ndarray, np.ndarray]:
    """Row/column of the ``privileged.local_occupancy`` cell under each BEV cell centre (``X x Y`` each)."""
    c = grid.cell_centres()
    res = float(local_map["resolution_m"])
    rows = np.floor((local_map["x_max_m"] - c[..., 0]) / res + 1e-9).astype(np.int64)
    cols = np.floor((local_map["y_max_m"] - c[..., 1]) / res + 1e-9).astype(np.int64)
    r_max, c_max = local_map["shape"]
    return np.clip(rows, 0, r_max - 1), np.clip(cols, 0, c_max - 1)


def rasterise_people(grid: BEVGrid, ped_xy: np.ndarray, radius: np.ndarray, present: np.ndarray) -> np.ndarray:
    """Disc occupancy of people in a BEV grid (each person only visits the cells of its bounding box).

    Args:
        grid: the BEV grid.
        ped_xy: ``L x P x 2`` people positions in each frame's base frame.
        radius: ``L x P`` disc radii (m).
        present: ``L x P`` bool.

    Returns:
        ``L x X x Y`` bool: a cell is occupied when its centre lies within a present person's radius.
    """
    nx, ny = grid.shape
    (x0, _, dx), (y0, _, dy) = grid.x_bound, grid.y_bound
    length = ped_xy.shape[0]
    out = np.zeros(length * nx * ny, dtype=bool)
    keep = present & (radius > 0)
    if not keep.any():
        return out.reshape(length, nx, ny)
    f, p = np.nonzero(keep)
    x, y, r = ped_xy[f, p, 0], ped_xy[f, p, 1], radius[f, p]
    r_max = float(r.max())
    oi = np.arange(-math.ceil(r_max / dx) - 1, math.ceil(r_max / dx) + 2)
    oj = np.arange(-math.ceil(r_max / dy) - 1, math.ceil(r_max / dy) + 2)
    ii = np.floor((x - x0) / dx).astype(np.int64)[:, None, None] + oi[None, :, None]  # Q x Ki x 1
    jj = np.floor((y - y0) / dy).astype(np.int64)[:, None, None] + oj[None, None, :]  # Q x 1 x Kj
    cx = x0 + (ii + 0.5) * dx
    cy = y0 + (jj + 0.5) * dy
    hit = ((cx - x[:, None, None]) ** 2 + (cy - y[:, None, None]) ** 2 <= (r ** 2)[:, None, None])
    hit &= (ii >= 0) & (ii < nx) & (jj >= 0) & (jj < ny)
    q, a, b = np.nonzero(hit)
    out[(f[q] * nx + ii[q, a, 0]) * ny + jj[q, 0, b]] = True
    return out.reshape(length, nx, ny)


def rasterise_people_reference(grid: BEVGrid, ped_xy: np.ndarray, radius: np.ndarray,
                               present: np.ndarray) -> np.ndarray:
    """Dense reference of :func:`rasterise_people`: every cell against every person."""
    c = grid.cell_centres()
    d2 = ((c[None, None] - ped_xy[:, :, None, None, :]) ** 2).sum(-1)  # L P X Y
    return ((d2 <= (radius ** 2)[..., None, None]) & present[..., None, None]).any(1)


def world_to_base(xy: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """World points ``L x P x 2`` into the base frames of poses ``L x 3``."""
    d = xy - pose[:, None, :2]
    c, s = np.cos(pose[:, 2])[:, None], np.sin(pose[:, 2])[:, None]
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)


PEOPLE_LABELS = ("all", "seen")


def seen_people(grid: BEVGrid, hits: np.ndarray, ped_xy: np.ndarray, radius: np.ndarray,
                present: np.ndarray) -> np.ndarray:
    """Which people the depth sees: ``hits`` ``L x X x Y`` bool (a measured point in the height band, from
    :func:`pretrain.geometry.lift_evidence`), people ``L x P x 2`` in each frame's base frame with radii and presence
    ``L x P`` → ``L x P`` bool, True where at least one hit cell's centre lies on the person's disc (the cells its
    label marks)."""
    out = np.zeros(present.shape, dtype=bool)
    centres = grid.cell_centres()  # X x Y x 2
    for t in np.flatnonzero(present.any(1)):
        c = centres[hits[t]]  # H x 2
        if not len(c):
            continue
        p = np.flatnonzero(present[t])
        d2 = ((c[:, None, :] - ped_xy[t, p][None]) ** 2).sum(-1)  # H x P'
        out[t, p] = (d2 <= radius[t, p][None] ** 2).any(0)
    return out


def episode_labels(grid: BEVGrid, local_map: dict, occupancy: np.ndarray, ped_state: np.ndarray,
                   odom: np.ndarray, future_frames: list[int],
                   hits: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The pretext labels of one episode.

    Args:
        grid: the BEV grid.
        local_map: the dataset's ``spec.local_map``.
        occupancy: ``L x R x Cc`` bool ``privileged.local_occupancy``.
        ped_state: ``L x P x 8`` ``privileged.ped_state`` (world x, y, vx, vy, radius, body yaw, head yaw, present).
        odom: ``L x 3`` world poses.
        future_frames: frame offsets of the future pedestrian targets (e.g. ``[5, 10]`` at 10 Hz).
        hits: ``L x X x Y`` bool, the depth's points in the height band per frame, or None. Given, the people targets
            keep only the people the depth sees in the *current* frame (:func:`seen_people`), now and in the future
            — what a camera-only model can know of (``people_label: seen``); None: everyone present.

    Returns:
        ``labels`` ``L x (2 + len(future_frames)) x X x Y`` uint8 and ``valid`` ``L x (2 + ...)`` bool.
    """
    length = odom.shape[0]
    rows, cols = static_label_index(grid, local_map)
    static = occupancy[:, rows, cols]
    pose = np.asarray(odom, dtype=np.float64)
    ps = np.asarray(ped_state, dtype=np.float64)
    out = np.zeros((length, 2 + len(future_frames), *grid.shape), dtype=np.uint8)
    valid = np.ones((length, 2 + len(future_frames)), dtype=bool)
    out[:, 0] = static
    seen = None
    if hits is not None:
        seen = seen_people(grid, hits, world_to_base(ps[..., :2], pose), ps[..., 4], ps[..., 7] > 0.5)
    for k, off in enumerate([0, *future_frames]):
        n = length - off
        if n <= 0:
            valid[:, 1 + k] = False
            continue
        fut = ps[off:]
        xy = world_to_base(fut[..., :2], pose[:n])
        present = fut[..., 7] > 0.5
        if seen is not None:
            present = present & seen[:n]
        out[:n, 1 + k] = rasterise_people(grid, xy, fut[..., 4], present)
        valid[n:, 1 + k] = False
    return out, valid


@dataclass
class FrameStore:
    """Every frame of some episodes, in memory (see the module docstring for the arrays)."""

    rgb: np.ndarray
    depth: np.ndarray
    pose: np.ndarray
    labels: np.ndarray
    valid: np.ndarray
    episode_start: np.ndarray  # F: store index of the first frame of each frame's episode
    episode_end: np.ndarray  # F: store index one past the last frame of each frame's episode
    episodes: list[int]  # dataset episode_index of each stored episode, in store order
    episode_slices: list[tuple[int, int]]  # store [start, end) of each stored episode
    # F x X x Y uint8, only when asked (load_frames(with_seen_now=True)): the "pedestrians now" label of the people
    # the frame's depth sees (:func:`seen_people`) — what a camera-only model can know of, whatever ``labels`` holds
    seen_now: np.ndarray | None = None

    def __len__(self) -> int:
        return self.pose.shape[0]

    @property
    def nbytes(self) -> int:
        arrays = (self.rgb, self.depth, self.pose, self.labels, self.valid, self.seen_now)
        return sum(a.nbytes for a in arrays if a is not None)


def estimate_bytes(n_frames: int, cameras: list[Camera], grid: BEVGrid, stride: int, targets: int) -> int:
    c = cameras[0]
    lift = (c.height // stride) * (c.width // stride)
    return n_frames * (len(cameras) * (3 * c.height * c.width + 4 * lift) + targets * math.prod(grid.shape) + 40)


def decode_video_file(path: Path, expected: dict[int, tuple[float, float, int]], fps: float,
                      sink: np.ndarray, cam: int, key: str) -> int:
    """Decodes one video file front to back and writes each frame into ``sink``.

    ``expected`` maps a dataset episode to ``(from_timestamp, to_timestamp, first store index)`` inside this file.
    Returns the number of frames placed.
    """
    import av

    spans = sorted((v[0], v[1], v[2]) for v in expected.values())
    starts = np.array([s[0] for s in spans])
    placed = 0
    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            for frame in container.decode(stream):
                t = float(frame.pts * stream.time_base)
                k = int(np.searchsorted(starts, t + 0.5 / fps, side="right")) - 1
                if k < 0:
                    continue
                t0, t1, first = spans[k]
                if t >= t1 - 0.5 / fps:
                    continue  # a frame of an episode we do not load
                sink[first + round((t - t0) * fps), cam] = frame.to_ndarray(format="rgb24").transpose(2, 0, 1)
                placed += 1
    except (av.error.FFmpegError, OSError) as e:
        raise CorruptArtifactError(f"video {path} ({key}): cannot decode: {e}") from None
    return placed


def load_frames(root: Path, cameras: list[Camera], grid: BEVGrid, lift_stride_px: int, future_s: list[float],
                episodes: list[int] | None = None, max_gb: float = 16.0, progress: bool = True,
                people_label: str = "all", with_seen_now: bool = False) -> FrameStore:
    """Loads episodes of a LeRobot dataset into a :class:`FrameStore`.

    Args:
        root: dataset root (``DATA_DIR/datasets/<repo_id>``).
        cameras: the encoder's cameras (``observation.images.<name>`` / ``observation.depth.<name>``).
        grid: the BEV grid of the labels.
        lift_stride_px: the encoder's lift stride (only those depth pixels are kept).
        future_s: horizons of the future pedestrian targets (s); must be multiples of the dataset's frame period.
        episodes: dataset episode indices to load (all when None).
        max_gb: refuse to load more than this many GB (the estimate is checked before reading anything).
        progress: show a progress bar.
        people_label: ``all`` (every person present) or ``seen`` (only the people the frame's depth sees, now and in
            the future targets: :func:`episode_labels`).
        with_seen_now: also keep :attr:`FrameStore.seen_now`, the "now" label of the seen people (for scoring a
            model on the people it can see, :mod:`pretrain.evaluate`).

    Raises:
        InputMissingError / CorruptArtifactError: see :func:`check_dataset`; a video frame missing or undecodable.
        ConfigError: the grid does not fit the labels, a horizon is not a whole number of frames, or the data
            would not fit in ``max_gb``.
    """
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from tqdm import tqdm

    root = Path(root)
    if people_label not in PEOPLE_LABELS:
        raise ConfigError(f"people_label: expected one of {list(PEOPLE_LABELS)}, got {people_label!r}")
    meta = check_dataset(root, cameras)
    local_map = meta.local_map
    check_grid_in_local_map(grid, local_map, str(root))
    fps = meta.fps
    future_frames = []
    for s in future_s:
        f = s * fps
        if s <= 0 or abs(f - round(f)) > 1e-6:
            raise ConfigError(f"future_s: {s} s is not a positive whole number of frames at {fps:g} fps")
        future_frames.append(round(f))
    try:
        ds = LeRobotDataset(meta.repo_id, root=root, video_backend="pyav")
    except Exception as e:  # lerobot raises many types for broken datasets
        raise CorruptArtifactError(f"dataset {root}: LeRobotDataset cannot open it ({type(e).__name__}: {e})") from None
    eps = list(range(ds.meta.total_episodes)) if episodes is None else list(episodes)
    meta_eps = ds.meta.episodes
    lengths = [int(meta_eps[e]["length"]) for e in eps]
    n = sum(lengths)
    need = estimate_bytes(n, cameras, grid, lift_stride_px, 2 + len(future_frames) + int(with_seen_now))
    if need > max_gb * 1e9:
        raise ConfigError(f"pretraining would hold {need / 1e9:.1f} GB of frames in memory ({n} frames), more than "
                          f"max_ram_gb={max_gb:g}; use fewer episodes or raise max_ram_gb")
    c0 = cameras[0]
    h, w = c0.height // lift_stride_px, c0.width // lift_stride_px
    store = FrameStore(
        rgb=np.zeros((n, len(cameras), 3, c0.height, c0.width), np.uint8),
        depth=np.zeros((n, len(cameras), h, w), np.float32), pose=np.zeros((n, 3), np.float64),
        labels=np.zeros((n, 2 + len(future_frames), *grid.shape), np.uint8),
        valid=np.zeros((n, 2 + len(future_frames)), bool), episode_start=np.zeros(n, np.int64),
        episode_end=np.zeros(n, np.int64), episodes=eps, episode_slices=[],
        seen_now=np.zeros((n, *grid.shape), np.uint8) if with_seen_now else None)
    cols = [OBS_ODOM, PRIV_PED_STATE, PRIV_LOCAL_OCCUPANCY] + [
        depth_key(c.name) for c in cameras]
    hf = ds.hf_dataset.select_columns(cols).with_format("numpy")
    first_of: dict[int, int] = {}
    pos = 0
    # the depth hits that decide who is seen
    geom = LiftGeometry(cameras, lift_stride_px) if people_label == "seen" or with_seen_now else None
    for e, length in tqdm(list(zip(eps, lengths, strict=True)), desc="pretrain: labels", unit="ep",
                          disable=not progress):
        a, b = int(meta_eps[e]["dataset_from_index"]), int(meta_eps[e]["dataset_to_index"])
        if b - a != length:
            raise CorruptArtifactError(f"dataset {root}: episode {e} spans {b - a} rows but its length is {length}")
        rows = hf[a:b]
        sl = slice(pos, pos + length)
        for ci, c in enumerate(cameras):
            store.depth[sl, ci] = sample_depth(torch.as_tensor(depth_from_mm(rows[depth_key(c.name)])),
                                               lift_stride_px).numpy()
        store.pose[sl] = rows[OBS_ODOM]
        hits = None if geom is None else (lift_evidence(torch.from_numpy(store.depth[sl]), geom, grid)[:, 0] > 0).numpy()
        label_args = (grid, local_map, rows[PRIV_LOCAL_OCCUPANCY].astype(bool), rows[PRIV_PED_STATE],
                      rows[OBS_ODOM].astype(np.float64), future_frames)
        store.labels[sl], store.valid[sl] = episode_labels(*label_args, hits if people_label == "seen" else None)
        if with_seen_now:
            store.seen_now[sl] = (store.labels[sl, 1] if people_label == "seen"
                                  else episode_labels(*label_args[:5], [], hits)[0][:, 1])
        store.episode_start[sl], store.episode_end[sl] = pos, pos + length
        store.episode_slices.append((pos, pos + length))
        first_of[e] = pos
        pos += length
    for ci, c in enumerate(cameras):
        key = image_key(c.name)
        files: dict[Path, dict[int, tuple[float, float, int]]] = {}
        for e in eps:
            path = root / ds.meta.get_video_file_path(e, key)
            files.setdefault(path, {})[e] = (float(meta_eps[e][f"videos/{key}/from_timestamp"]),
                                             float(meta_eps[e][f"videos/{key}/to_timestamp"]), first_of[e])
        placed = 0
        for path, expected in tqdm(files.items(), desc=f"pretrain: decode {c.name}", unit="file",
                                   disable=not progress):
            if not path.is_file():
                raise InputMissingError(f"dataset {root}: video file {path} is missing")
            placed += decode_video_file(path, expected, fps, store.rgb, ci, key)
        if placed != n:
            raise CorruptArtifactError(f"dataset {root}: {key}: decoded {placed} frames of the {n} its episodes list")
    log.info("pretrain: loaded %d episodes, %d frames (%.2f GB) from %s", len(eps), n, store.nbytes / 1e9, root)
    return store


def split_episodes(n_episodes: int, val_fraction: float, seed: int) -> tuple[list[int], list[int]]:
    """Train/validation split by episode (deterministic in ``seed``); at least one episode on each side."""
    if n_episodes < 2:
        raise ConfigError(f"pretraining needs at least 2 episodes (train + validation), the dataset has {n_episodes}")
    order = np.random.default_rng(seed).permutation(n_episodes)
    n_val = min(n_episodes - 1, max(1, round(val_fraction * n_episodes)))
    return sorted(order[n_val:].tolist()), sorted(order[:n_val].tolist())


@dataclass
class Batch:
    """A training batch: clips of consecutive frames and the windows of T frames that end at each target.

    Attributes:
        frames: ``M`` store indices whose images are encoded (clips concatenated; repeats at episode starts).
        windows: ``P x T`` positions in ``frames`` of each target's window, oldest first.
        targets: ``P`` store indices of the target frames.
    """

    frames: np.ndarray
    windows: np.ndarray
    targets: np.ndarray


def make_clips(store: FrameStore, slices: list[tuple[int, int]], clip_targets: int, history: int,
               rng: np.random.Generator | None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Cuts episodes into clips: each clip = ``(frames, targets)`` with T−1 frames of context before its targets.

    Targets tile every episode exactly once (a random phase when ``rng`` is given, else from frame 0); context
    frames before an episode's start repeat its first frame (the encoder's start-of-episode rule).
    """
    clips = []
    for start, end in slices:
        phase = int(rng.integers(0, clip_targets)) if rng is not None else 0
        cuts = [start] + list(range(start + (phase or clip_targets), end, clip_targets)) if end - start > 0 else []
        for k, s in enumerate(cuts):
            e = cuts[k + 1] if k + 1 < len(cuts) else end
            frames = np.maximum(np.arange(s - history + 1, e), start)
            clips.append((frames, np.arange(s, e)))
    return clips


def make_batches(clips: list[tuple[np.ndarray, np.ndarray]], clips_per_batch: int, history: int) -> list[Batch]:
    """Groups clips into batches (in the given order) with their window index arrays."""
    out = []
    for i in range(0, len(clips), clips_per_batch):
        frames, windows, targets, offset = [], [], [], 0
        for f, t in clips[i:i + clips_per_batch]:
            frames.append(f)
            base = offset + np.arange(len(t))
            windows.append(base[:, None] + np.arange(history)[None, :])
            targets.append(t)
            offset += len(f)
        out.append(Batch(np.concatenate(frames), np.concatenate(windows), np.concatenate(targets)))
    return out
