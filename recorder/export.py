"""Export recorded episodes (complete MCAP logs) into a LeRobot v3.0 dataset, crash-safely.

::

    from recorder.export import export_run
    export_run(Path("data/raw/run"), Path("data/datasets/run"), repo_id="icrowdnav/run")

    python -m recorder.export data/raw/run data/datasets/run --repo-id icrowdnav/run [--overwrite]

The per-episode MCAP files are the durable log; the LeRobot dataset is derived from complete ones only
(``*.partial`` recordings are refused, or skipped with a warning by :func:`export_run`). LeRobot 0.4.4 keeps
parquet writers open across episodes and rewrites ``meta/info.json`` per episode, so a killed export could
leave a dataset with footer-less parquet files or an episode-index gap. Hence the export:

1. writes into a staging directory ``.<name>.staging-<pid>`` next to ``out_dir``
   (:class:`pipeline.core.artifacts.OutputDir`; staging dirs of dead processes are removed by the next export);
2. ``LeRobotDataset.create`` → ``add_frame`` per frame (task :data:`recorder.features.TASK`; observation ``t``
   with the step from it, LeRobot's action convention: :mod:`recorder.features`) → ``save_episode`` per episode
   (one parquet data file each) → ``finalize()``;
3. adds our ``info`` to every feature of lerobot's ``meta/info.json`` (descriptions, the cameras' intrinsics /
   extrinsics, the dataset format, the local-map layout: :func:`recorder.features.feature_info`) and writes the
   optional extras ``meta/icrowdnav.json`` (feature docs, sources) and ``meta/icrowdnav_episodes.jsonl`` (one row
   per episode: the episode's metadata, source file name, outcome, length, return);
4. runs the dataset doctor (:func:`recorder.doctor_dataset.check_dataset`) on the staging directory — any
   problem is an error and the staging directory is removed;
5. renames the staging directory into place (with ``overwrite``, the old dataset stays until the new one is
   complete).

With ``shards > 1`` (``icrowdnav export --workers N``), step 2 runs on contiguous blocks of episodes in parallel,
each into its own LeRobot dataset inside the staging directory, and lerobot's ``aggregate_datasets`` merges them
(:func:`_write_sharded`): the same dataset frame for frame, stats equal up to float rounding (docs/scale-out.md).

Why the per-episode facts are in a side file: lerobot 0.4.4's ``meta/episodes`` parquet is written from an internal
dict (``LeRobotDataset.save_episode`` takes no extra per-episode columns), so they live in
``meta/icrowdnav_episodes.jsonl``, which stock lerobot ignores and its dataset tools drop; what our readers need
(format, calibration) is in ``meta/info.json``, which they keep.

Reading the dataset back with stock lerobot: ``video_backend="pyav"`` (lerobot's default torchcodec needs system
FFmpeg libraries; our lock leaves torchcodec out, so lerobot falls back to pyav by itself)::

    LeRobotDataset("icrowdnav/run", root="data/datasets/run", video_backend="pyav")
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import logging
import math
import os
import sys
import time
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pipeline.core.artifacts import OutputDir, atomic_write_json, atomic_write_text
from pipeline.core.errors import (
    ConfigError,
    CorruptArtifactError,
    ICrowdNavError,
    InputMissingError,
    reports_errors,
)
from pipeline.core.executor import Executor, map_jobs
from pipeline.core.keys import NEXT_DONE, NEXT_REWARD
from recorder.dataset_info import ICROWDNAV_EPISODES, ICROWDNAV_META
from recorder.doctor_dataset import check_dataset
from recorder.features import (
    ACTION_CONVENTION,
    DEFAULT_MAX_PEOPLE,
    FORMAT_KEY,
    FORMAT_VERSION,
    N_MAX_PEDESTRIANS,
    ROBOT_TYPE,
    TASK,
    ExportSpec,
    FeatureError,
    LocalMapSpec,
    cameras_of,
    check_features,
    feature_info,
    meta_facts,
    observation_features,
    step_features,
)
from recorder.mcap.reader import count_frames, read_episode
from recorder.schema import CAMERA_NAMES, EpisodeMeta, Frame

log = logging.getLogger("icrowdnav")

PARTIAL_SUFFIX = ".partial"
# Below this many frames per shard a shard costs more than it saves on the 2-core VM: 4 episodes (486 frames) in 2
# shards ran at 0.88x the one-process export, 6 episodes (629) at 1.1x, 100 episodes (12,646) at 1.52x.
MIN_SHARD_FRAMES = 1000
# One parquet data file per episode (lerobot starts a new file once the current one reaches this size). lerobot
# 0.4.4's ``delete_episodes`` must filter rows out of a data file that holds a deleted and a kept episode, and that
# fails on multi-dimensional features (``datasets``' PandasArrayExtensionDtype compares a string ``_metadata`` letter
# by letter: "AttributeError: ... has no attribute 'v'"); with one episode per file it copies or skips whole files.
DATA_FILE_MB = 1e-6
VCODEC = "libsvtav1"  # AV1 through PyAV / SVT-AV1, lerobot's default


@dataclass
class _Source:
    """One episode to export: where it came from and how to open it (lazily)."""

    name: str
    open: Callable[[], tuple[EpisodeMeta, np.ndarray, Iterator[Frame]]]
    path: Path | None = None

    @property
    def label(self) -> str:
        """What the dataset records as the episode's source: the MCAP file's name (no local directory), or the
        in-memory episode's name."""
        return self.path.name if self.path is not None else self.name


def is_partial(path: Path) -> bool:
    """Whether ``path`` is an unfinished recording (``*.partial``, e.g. ``ep_0001.mcap.partial``)."""
    return Path(path).name.endswith(PARTIAL_SUFFIX)


def _unpack(obj: Any, name: str) -> tuple[EpisodeMeta, np.ndarray, Iterator[Frame]]:
    """``(meta, occupancy, frames)`` from a ``read_episode`` result or an Episode-like object."""
    if isinstance(obj, tuple) and len(obj) == 3:
        meta, occ, frames = obj
    elif hasattr(obj, "meta") and hasattr(obj, "occupancy") and hasattr(obj, "frames"):
        meta, occ, frames = obj.meta, obj.occupancy, obj.frames
    else:
        raise TypeError(f"{name}: expected (meta, occupancy, frames) or an object with .meta, .occupancy and "
                        f".frames, got {type(obj).__name__}")
    if callable(frames):
        frames = frames()
    if not isinstance(meta, EpisodeMeta):
        raise FeatureError(f"{name}: episode metadata: expected an EpisodeMeta, got {type(meta).__name__}")
    occ = np.asarray(occ)
    if occ.ndim != 2 or occ.dtype != bool:
        raise FeatureError(f"{name}: field 'occupancy': expected a 2-D bool grid of shape "
                           f"{tuple(meta.occupancy_shape)}, got shape {occ.shape} {occ.dtype}")
    if list(occ.shape) != [int(v) for v in meta.occupancy_shape]:
        raise FeatureError(f"{name}: field 'occupancy': expected shape {tuple(meta.occupancy_shape)} "
                           f"(meta.occupancy_shape), got {occ.shape}")
    return meta, occ, iter(frames)


def _read_mcap(path: Path) -> tuple[EpisodeMeta, np.ndarray, Iterator[Frame]]:
    """Opens one complete MCAP episode with :func:`recorder.mcap.reader.read_episode`."""

    try:
        result = read_episode(path)
    except ICrowdNavError:
        raise
    except Exception as e:  # a damaged file must be named, never a bare struct.error
        raise CorruptArtifactError(f"{path}: cannot read the episode: {type(e).__name__}: {e}") from e
    return _unpack(result, str(path))


def _sources(inputs: Iterable[Any]) -> Iterator[_Source]:
    """Normalises paths and Episode-like objects into :class:`_Source` items (lazily)."""
    for k, item in enumerate(inputs):
        if isinstance(item, str | os.PathLike):
            path = check_inputs([Path(item)])[0]
            yield _Source(str(path), lambda p=path: _read_mcap(p), path)
        else:
            name = str(getattr(item, "source", None) or getattr(item, "path", None) or f"<episode {k} (in memory)>")
            yield _Source(name, lambda it=item, n=name: _unpack(it, n))


def check_inputs(paths: Iterable[Path]) -> list[Path]:
    """Checks that every MCAP input exists and is complete (before anything is written).

    Raises:
        InputMissingError: a file does not exist.
        CorruptArtifactError: a file is an unfinished ``*.partial`` recording.
    """
    out = []
    for p in paths:
        p = Path(p)
        if is_partial(p):
            raise CorruptArtifactError(
                f"{p}: unfinished recording (*{PARTIAL_SUFFIX}); the export reads complete MCAP episodes only — "
                "recover it first (recorder.mcap.recovery.recover) or leave it out")
        if not p.is_file():
            raise InputMissingError(f"missing MCAP episode: {p}")
        out.append(p)
    return out


def _guarded(frames: Iterator[Frame], source: _Source) -> Iterator[Frame]:
    """Iterates a reader's frames, naming the file when reading fails mid-episode."""
    while True:
        try:
            fr = next(frames)
        except StopIteration:
            return
        except ICrowdNavError:
            raise
        except Exception as e:
            if source.path is None:
                raise
            raise CorruptArtifactError(f"{source.name}: cannot read a frame: {type(e).__name__}: {e}") from e
        yield fr


def _peek_first(frames: Iterator[Frame], source: _Source) -> tuple[Iterator[Frame], int, bool]:
    """``K`` = the number of detection rows of the first frame, and whether it carries a label (frames are
    given back unconsumed)."""
    frames = _guarded(frames, source)
    first = next(frames, None)
    if first is None:
        return iter(()), DEFAULT_MAX_PEOPLE, False
    poses = getattr(first, "poses", None)
    k = poses.shape[0] if isinstance(poses, np.ndarray) and poses.ndim == 3 else DEFAULT_MAX_PEOPLE
    return itertools.chain([first], frames), int(k), getattr(first, "label", None) is not None


def _resolve_fps(fps: int | None, meta: EpisodeMeta, source: str) -> int:
    """The dataset fps: ``fps`` if it equals ``1 / meta.dt_s``, else an error; ``1 / dt_s`` when None."""
    dt = float(meta.dt_s)
    if not (dt > 0 and math.isfinite(dt)):
        raise FeatureError(f"{source}: episode metadata field 'dt_s': expected a positive period, got {dt}")
    want = 1.0 / dt
    if fps is None:
        if abs(want - round(want)) > 1e-6:
            raise ConfigError(f"fps: LeRobot needs an integer fps, but {source} has dt_s = {dt} s "
                              f"(1/dt_s = {want:g})")
        return int(round(want))
    if isinstance(fps, bool) or not isinstance(fps, int) or fps <= 0:
        raise ConfigError(f"fps: expected a positive int, got {fps!r}")
    if abs(fps * dt - 1.0) > 1e-6:
        raise ConfigError(f"fps: expected {want:g} (1 / dt_s of {source}, dt_s = {dt} s), got {fps}; "
                          "timestamps are frame_index / fps and must equal the recorded times")
    return fps


def _check_same_spec(meta: EpisodeMeta, first: EpisodeMeta, spec: ExportSpec, fps: int, source: str) -> None:
    """Every episode of a dataset must have the first one's cameras (sizes, intrinsics, extrinsics) and period."""
    other = ExportSpec.from_meta(meta, spec.max_people, spec.n_max, spec.local_map, source, spec.labels)
    for cam in CAMERA_NAMES:
        if other.camera_sizes[cam] != spec.camera_sizes[cam]:
            raise FeatureError(f"{source}: episode metadata field 'cameras[{cam}]' (height, width): expected "
                               f"{spec.camera_sizes[cam]} like the dataset's first episode, "
                               f"got {other.camera_sizes[cam]}")
        mine, theirs = cameras_of(meta).get(cam, {}), cameras_of(first).get(cam, {})
        for key in sorted(set(mine) | set(theirs)):
            if mine.get(key) != theirs.get(key):
                raise FeatureError(f"{source}: episode metadata field 'cameras[{cam}][{key}]': expected "
                                   f"{theirs.get(key)!r} like the dataset's first episode (one camera model per "
                                   f"dataset), got {mine.get(key)!r}")
    if abs(fps * float(meta.dt_s) - 1.0) > 1e-6:
        raise FeatureError(f"{source}: episode metadata field 'dt_s': expected {1.0 / fps:g} s "
                           f"(the dataset's {fps} fps), got {meta.dt_s}")


@contextlib.contextmanager
def quiet_lerobot() -> Iterator[None]:
    """Around lerobot's ``save_episode``: hides the HF ``datasets`` "Map" bars it triggers per episode (our own bar
    counts frames) and the (harmless) uint8-conversion warning of its stats histogram of bool features."""
    import datasets

    was = datasets.is_progress_bar_enabled()
    datasets.disable_progress_bars()
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", "Converting input from bool", RuntimeWarning)
            yield
    finally:
        if was:
            datasets.enable_progress_bars()


def add_frame(ds: Any, values: dict[str, Any], scalar_keys: list[str]) -> None:
    """``ds.add_frame(values)``, then the ``(1,)``-shaped ``scalar_keys`` of the buffered frame made 0-d: with
    lerobot 0.4.4 and numpy >= 2.3, ``float()`` of a (1,) array raises later in ``save_episode``."""
    ds.add_frame(values)
    for key in scalar_keys:
        ds.episode_buffer[key][-1] = ds.episode_buffer[key][-1].reshape(())


def remove_empty_images_dir(root: Path) -> None:
    """Removes lerobot's temporary frame directory ``root/images`` once encoding left it without files."""
    images = Path(root) / "images"
    if images.is_dir() and not any(p.is_file() for p in images.rglob("*")):
        import shutil

        shutil.rmtree(images)


@contextlib.contextmanager
def _no_image_embedding(features: dict[str, dict]) -> Iterator[None]:
    """Skip lerobot's per-row ``embed_images`` pass when the dataset has no ``image`` features.

    lerobot 0.4.4 runs ``datasets.Dataset.map(embed_table_storage)`` row by row on every saved episode to embed
    image bytes into parquet; our images are videos (separate mp4 files), so the pass is the identity — but it
    costs ~13 ms per frame because it round-trips every row's array extension types (a third of the export
    time, measured with cProfile). The patch is active only inside ``save_episode`` and only without image
    features; the dataset doctor and the stock-loader round-trip tests check the result.
    """
    import lerobot.datasets.lerobot_dataset as lds

    if any(ft.get("dtype") == "image" for ft in features.values()):
        yield
        return
    original = lds.embed_images
    lds.embed_images = lambda dataset: dataset
    try:
        yield
    finally:
        lds.embed_images = original


@dataclass
class _Written:
    """What :func:`_write_episodes` wrote: the per-episode rows of ``meta/icrowdnav_episodes.jsonl`` and the spec the
    dataset was built with (all picklable: a shard's result comes back from a worker process)."""

    rows: list[dict[str, Any]]
    spec: ExportSpec
    first_meta: EpisodeMeta
    fps: int
    frames: int


def _spec_of_first(src: _Source, meta: EpisodeMeta, frames: Iterator[Frame], fps: int | None,
                   max_people: int | None, n_max: int, local_map: LocalMapSpec | None
                   ) -> tuple[ExportSpec, int, Iterator[Frame]]:
    """The dataset's spec and fps from its first episode (``K`` from the first frame unless ``max_people`` says);
    the episode's frames are given back unconsumed."""
    fps = _resolve_fps(fps, meta, src.name)
    frames, k_first, labels = _peek_first(frames, src)
    max_people = k_first if max_people is None else max_people
    return ExportSpec.from_meta(meta, max_people, n_max, local_map, src.name, labels), fps, frames


def _first_episode_spec(inputs: list[Any], fps: int | None, max_people: int | None, n_max: int,
                        local_map: LocalMapSpec | None) -> tuple[ExportSpec, EpisodeMeta, int]:
    """The dataset's spec, first episode's metadata and fps, from the first input (read up to its first frame)."""
    src = next(_sources(inputs[:1]), None)
    if src is None:
        raise InputMissingError("no episodes to export: the input list is empty")
    meta, _occ, frames = src.open()
    spec, fps, _frames = _spec_of_first(src, meta, frames, fps, max_people, n_max, local_map)
    return spec, meta, fps


def _write_episodes(inputs: Iterable[Any], root: Path, repo_id: str, fps: int | None, *,
                    max_people: int | None, n_max: int, local_map: LocalMapSpec | None, progress: bool,
                    vcodec: str, fixed: tuple[ExportSpec, EpisodeMeta] | None = None,
                    first_index: int = 0, bar_position: int | None = None) -> _Written:
    """The LeRobot part of an export: ``create`` → ``add_frame``/``save_episode`` per episode → ``finalize`` at
    ``root`` (which must not exist). ``fixed``: the dataset's spec and first episode's metadata, decided by the
    caller (an export shard checks every one of its episodes against them, as the serial export checks episodes
    after the first); otherwise both come from the first input. ``first_index``: the dataset-wide index of the
    first input (its rows' ``episode_index``)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = None
    spec, first_meta = fixed if fixed is not None else (None, None)
    features: dict[str, dict] = {}
    scalar_keys: list[str] = []
    rows: list[dict[str, Any]] = []
    n_frames = 0
    bar = tqdm(desc=f"export {Path(root).name}", unit="frame", disable=not progress, dynamic_ncols=True,
               position=bar_position, leave=bar_position is None)
    try:
        for k, src in enumerate(_sources(inputs)):
            ep_index = first_index + k
            meta, occ, frames = src.open()
            if ds is None:
                if spec is None:
                    spec, fps, frames = _spec_of_first(src, meta, frames, fps, max_people, n_max, local_map)
                    first_meta = meta
                else:
                    assert fps is not None and first_meta is not None
                    _check_same_spec(meta, first_meta, spec, fps, src.name)
                features = spec.features()
                scalar_keys = [key for key, ft in features.items() if tuple(ft["shape"]) == (1,)]
                ds = LeRobotDataset.create(repo_id, fps, features, root=root, robot_type=ROBOT_TYPE,
                                           use_videos=True, vcodec=vcodec, video_backend="pyav")
                ds.meta.update_chunk_settings(data_files_size_in_mb=DATA_FILE_MB)
            else:
                _check_same_spec(meta, first_meta, spec, fps, src.name)
            length, ret, outcome, done = 0, 0.0, "", False
            observed: dict[str, np.ndarray] | None = None  # observation t, waiting for the step it starts
            for i, fr in enumerate(_guarded(frames, src)):
                if observed is not None:  # LeRobot's convention: frame t = observation t + the step t -> t + 1
                    values = {**observed, **step_features(fr, src.name, i)}
                    check_features(values, features, src.name, i - 1)
                    values["task"] = TASK
                    add_frame(ds, values, scalar_keys)
                    length += 1
                    ret += float(values[NEXT_REWARD][0])
                    done = bool(values[NEXT_DONE][0])
                    bar.update(1)
                observed = observation_features(fr, meta, occ, spec, src.name, i)
                outcome = str(getattr(fr, "outcome", "") or outcome)
            if length == 0:
                raise FeatureError(f"{src.name}: frames: expected at least two recorded frames (an observation and "
                                   f"the step from it), got {0 if observed is None else 1}")
            with quiet_lerobot(), _no_image_embedding(features):
                ds.save_episode(parallel_encoding=False)
            n_frames += length
            bar.set_postfix(episodes=k + 1)
            rows.append({"episode_index": ep_index, "source": src.label, "recorded_frames": length + 1,
                         "source_bytes": src.path.stat().st_size if src.path is not None else None,
                         "length": length, "duration_s": round(length / fps, 6), "outcome": outcome,
                         "done": done, "return": ret, "scene": meta.scene, "density": meta.density,
                         "seed": meta.seed, "episode_seed": meta.episode_seed, "driver": meta.driver,
                         "meta": meta_facts(meta)})
        if ds is None:
            raise InputMissingError("no episodes to export: the input list is empty")
        ds.finalize()
    except BaseException:
        if ds is not None:
            with contextlib.suppress(Exception):
                ds.finalize()  # close lerobot's parquet writers; the caller discards the failed root
        raise
    finally:
        bar.close()
    assert spec is not None and first_meta is not None and fps is not None
    return _Written(rows, spec, first_meta, fps, n_frames)


def _finish(root: Path, repo_id: str, w: _Written, seconds: float) -> dict[str, Any]:
    """What every export adds to lerobot's files: sorted stats, our feature ``info``, the side files; its counts."""
    _sort_stats(root)
    _annotate_info(root, feature_info(w.spec, cameras_of(w.first_meta)))
    remove_empty_images_dir(root)
    info = {
        "repo_id": repo_id, "fps": w.fps, "dt_s": 1.0 / w.fps, "task": TASK,
        "robot_type": ROBOT_TYPE, "total_episodes": len(w.rows), "total_frames": w.frames,
        FORMAT_KEY: FORMAT_VERSION, "action_convention": ACTION_CONVENTION,
        "cameras": cameras_of(w.first_meta), "spec": w.spec.describe(),
        "sources": [r["source"] for r in w.rows],
        "episode_facts": f"{ICROWDNAV_EPISODES}: one JSON row per episode_index",
        "lerobot_load": "LeRobotDataset(repo_id, root=..., video_backend='pyav')",
    }
    atomic_write_json(root / ICROWDNAV_META, info)
    atomic_write_text(root / ICROWDNAV_EPISODES, "".join(json.dumps(_json_safe(r)) + "\n" for r in w.rows))
    return {"episodes": len(w.rows), "frames": w.frames, "seconds": round(seconds, 3),
            "frames_per_s": round(w.frames / seconds, 2) if seconds > 0 else 0.0}


def write_dataset(inputs: Iterable[Any], root: Path, repo_id: str, fps: int | None = None, *,
                  max_people: int | None = None, n_max: int = N_MAX_PEDESTRIANS,
                  local_map: LocalMapSpec | None = None, progress: bool = True,
                  vcodec: str = VCODEC, shards: int = 1, executor: Executor | None = None,
                  min_shard_frames: int = MIN_SHARD_FRAMES) -> dict[str, Any]:
    """Writes episodes into a new LeRobot dataset at ``root`` (no staging, no validation: the caller's job).

    Use :func:`export_dataset` unless the caller already provides a crash-safe directory (e.g. a stage body
    writing into its :class:`pipeline.core.artifacts.OutputDir`).

    Args:
        inputs: MCAP paths and/or Episode-like objects (``.meta``, ``.occupancy``, ``.frames``), in order.
        root: the dataset directory; must not exist or be an empty directory.
        repo_id: the LeRobot repo id (``owner/name``) stored in the metadata.
        fps: frames per second; must equal ``1 / dt_s`` of the episodes (default: taken from the first).
        max_people: ``K``, detections per frame (default: the first frame's, i.e. the detector's setting).
        n_max, local_map: sizes of the padded arrays (:class:`recorder.features.ExportSpec`).
        progress: show a tqdm bar (frames; shards when ``shards > 1``).
        vcodec: the video codec lerobot encodes with.
        shards: split the episodes into this many contiguous blocks, export each as its own LeRobot dataset in
            parallel (``executor``: a local process pool or Ray tasks) and merge them with lerobot's
            ``aggregate_datasets`` (:func:`_write_sharded`); 1, one episode or in-memory episodes (which cannot
            be handed to workers) export in this process.
        executor: where shards run (:mod:`pipeline.core.executor`; default the local pool).
        min_shard_frames: fewer shards when the episodes hold fewer than this many frames per shard (a shard's
            fixed cost — a worker, a dataset, its share of the merge — outweighs its gain on small recordings).

    Returns:
        ``{"episodes", "frames", "seconds", "frames_per_s"}`` (+ ``"shards"``, ``"merge_seconds"`` when sharded).

    Raises:
        FeatureError: a frame or episode does not fit the spec (names file, field, expected, actual).
        CorruptArtifactError: an input cannot be read.
        InputMissingError: there is no episode at all.
    """
    root = Path(root)
    if root.is_dir() and not any(root.iterdir()):
        root.rmdir()  # lerobot creates the root itself and refuses an existing one
    # SVT-AV1 prints its ~20-line config banner to stderr for every encoded episode unless its log level says
    # errors only (it reads SVT_LOG when an encoder starts; forked shard workers inherit it); a user's value wins
    os.environ.setdefault("SVT_LOG", "1")
    t0 = time.monotonic()
    items = list(inputs) if shards > 1 else inputs
    frames: list[int] = []
    if shards > 1 and len(items) > 1 and all(isinstance(it, str | os.PathLike) for it in items):
        # frames per episode from each file's summary (no decompression): the shards' sizes
        frames = [count_frames(p) for p in check_inputs(items)]
        if min_shard_frames > 0:
            shards = min(shards, max(1, sum(frames) // min_shard_frames))
    if shards > 1 and frames:
        w, extra = _write_sharded(items, frames, root, repo_id, fps, shards, max_people=max_people, n_max=n_max,
                                  local_map=local_map, progress=progress, vcodec=vcodec, executor=executor)
    else:
        w = _write_episodes(items, root, repo_id, fps, max_people=max_people, n_max=n_max, local_map=local_map,
                            progress=progress, vcodec=vcodec)
        extra = {}
    return {**_finish(root, repo_id, w, time.monotonic() - t0), **extra}


def shard_blocks(sizes: list[int], shards: int) -> list[tuple[int, int]]:
    """Contiguous ``[start, stop)`` blocks of the episodes with about equal total size (e.g. frames) each (episode
    order is the dataset's order, so blocks are never interleaved); at most ``shards`` blocks, none empty."""
    n = len(sizes)
    shards = max(1, min(shards, n))
    weights = sizes if sum(sizes) > 0 else [1] * n  # all empty: balance by count
    total = float(sum(weights))
    blocks, start, acc = [], 0, 0.0
    for i, s in enumerate(weights):
        acc += s
        left_blocks = shards - len(blocks) - 1
        if left_blocks == 0:
            break
        # close the block once it holds its share, leaving at least one episode per remaining block
        if acc >= total * (len(blocks) + 1) / shards and n - (i + 1) >= left_blocks:
            blocks.append((start, i + 1))
            start = i + 1
    blocks.append((start, n))
    return blocks


def _export_shard(job: tuple) -> _Written:
    """One shard (a worker's job): its episodes as a LeRobot dataset at its own root."""
    items, root, repo_id, fps, spec, first_meta, first_index, vcodec, progress, position = job
    return _write_episodes(items, root, repo_id, fps, max_people=spec.max_people, n_max=spec.n_max,
                           local_map=spec.local_map, progress=progress, vcodec=vcodec, fixed=(spec, first_meta),
                           first_index=first_index, bar_position=position)


def _aggregate_data_arrow(src_meta: Any, dst_meta: Any, data_idx: dict, data_files_size_in_mb: float,
                          chunk_size: int) -> dict:
    """lerobot 0.4.4's ``aggregate.aggregate_data`` done in pyarrow: the same contract (copy every data file of
    ``src_meta`` into the destination with ``episode_index`` / ``index`` shifted by what the destination already
    holds and ``task_index`` mapped by task name, rotate to a new file when the size limit is reached, return
    ``data_idx`` with the ``src_to_dst`` file mapping), but without its pandas round trip — ``pd.read_parquet``
    turns our multi-dimensional features (``datasets`` ``Array2D``/``Array3D`` columns, e.g. the depth images) into
    an extension dtype that ``DataFrame.to_parquet`` cannot write back ("ArrowTypeError: Did not pass numpy.dtype
    object"). Columns and the schema's ``huggingface`` features metadata are kept as they are."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    from lerobot.datasets.utils import DEFAULT_DATA_PATH, update_chunk_file_indices

    pairs = sorted(set(zip(src_meta.episodes["data/chunk_index"], src_meta.episodes["data/file_index"],
                           strict=True)))
    task_map = np.array([int(dst_meta.tasks.loc[name, "task_index"]) for name in src_meta.tasks.index],
                        dtype=np.int64)
    src_to_dst: dict[tuple[int, int], tuple[int, int]] = {}
    for c, f in pairs:
        src = src_meta.root / DEFAULT_DATA_PATH.format(chunk_index=c, file_index=f)
        table = pq.read_table(src)
        shifts = {"episode_index": dst_meta.info["total_episodes"], "index": dst_meta.info["total_frames"]}
        for name, shift in shifts.items():
            col = table.column(name)
            table = table.set_column(table.schema.get_field_index(name), table.schema.field(name),
                                     pa.array(col.to_numpy() + shift, type=col.type))
        col = table.column("task_index")
        table = table.set_column(table.schema.get_field_index("task_index"), table.schema.field("task_index"),
                                 pa.array(task_map[col.to_numpy()], type=col.type))
        dst = dst_meta.root / DEFAULT_DATA_PATH.format(chunk_index=data_idx["chunk"], file_index=data_idx["file"])
        if dst.exists():
            if src.stat().st_size + dst.stat().st_size < data_files_size_in_mb * 1024 * 1024:
                raise CorruptArtifactError(f"{dst}: the export merges shards one data file per episode "
                                           f"(data_files_size_in_mb={data_files_size_in_mb}); appending is not "
                                           "implemented")
            data_idx["chunk"], data_idx["file"] = update_chunk_file_indices(data_idx["chunk"], data_idx["file"],
                                                                            chunk_size)
            dst = dst_meta.root / DEFAULT_DATA_PATH.format(chunk_index=data_idx["chunk"],
                                                           file_index=data_idx["file"])
        dst.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table, dst)
        src_to_dst[(c, f)] = (data_idx["chunk"], data_idx["file"])
    data_idx["src_to_dst"] = src_to_dst
    return data_idx


def _shift_index_stats(root: Path, episodes: int, frames: int) -> None:
    """Makes a shard's statistics of ``episode_index`` and ``index`` those of its place in the merged dataset (its
    first episode is the dataset's ``episodes``-th, its first frame the ``frames``-th): lerobot 0.4.4's aggregation
    shifts the data columns but copies these per-episode stats (``meta/episodes``) and the shard's
    ``meta/stats.json`` unchanged, so a merge of shards would say episode indices end at the last shard's local
    maximum. Location statistics move with the shift; ``std`` and ``count`` do not."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    def moves(stat: str) -> bool:
        return stat in ("min", "max", "mean") or (stat.startswith("q") and stat[1:].isdigit())

    shift = {"episode_index": episodes, "index": frames}
    for path in sorted((root / "meta" / "episodes").rglob("*.parquet")):
        table = pq.read_table(path)
        for i, name in enumerate(table.column_names):
            parts = name.split("/")
            if len(parts) == 3 and parts[0] == "stats" and parts[1] in shift and moves(parts[2]):
                col = table.column(i)
                values = [[v + shift[parts[1]] for v in row] for row in col.to_pylist()]
                table = table.set_column(i, table.schema.field(i), pa.array(values, type=col.type))
        pq.write_table(table, path)
    path = root / "meta" / "stats.json"
    stats = json.loads(path.read_text())
    for feature, k in shift.items():
        for stat, value in stats.get(feature, {}).items():
            if moves(stat):
                stats[feature][stat] = (np.asarray(value) + k).tolist()
    atomic_write_text(path, json.dumps(stats, indent=4))


@contextlib.contextmanager
def _arrow_data_aggregation() -> Iterator[None]:
    """Inside lerobot's ``aggregate_datasets``: its data step replaced by :func:`_aggregate_data_arrow` (the video,
    episode-metadata, task and stats steps stay lerobot's own)."""
    import lerobot.datasets.aggregate as agg

    original = agg.aggregate_data
    agg.aggregate_data = _aggregate_data_arrow
    try:
        yield
    finally:
        agg.aggregate_data = original


def _write_sharded(items: list[Any], frames: list[int], root: Path, repo_id: str, fps: int | None, shards: int, *,
                   max_people: int | None, n_max: int, local_map: LocalMapSpec | None, progress: bool,
                   vcodec: str, executor: Executor | None) -> tuple[_Written, dict[str, Any]]:
    """Exports contiguous blocks of episodes as separate LeRobot datasets in parallel, then merges them with lerobot's
    own ``aggregate_datasets`` into ``root``.

    The spec (cameras, ``K``, sizes) and fps are decided once from the first episode and handed to every shard, so
    a shard checks each of its episodes against the dataset's first one exactly as the serial export does (the same
    named errors). Shards live in ``root/.shards/`` while they are written and are merged into
    ``root/.shards/merged`` (lerobot creates its output root itself), whose files are then moved up into ``root``:
    everything stays inside the caller's staging directory, so a killed export leaves nothing outside it. The merge
    copies each shard's parquet files as they are (``data_files_size_in_mb`` keeps one file per episode) and
    concatenates the shards' mp4 files per camera without re-encoding; ``meta/stats.json`` is lerobot's
    ``aggregate_stats`` over the shards — the same weighted combination the serial export applies episode by
    episode, so equal up to float rounding (tests/recorder/test_export_shards.py compares both frame for frame)."""
    import shutil

    from lerobot.datasets.aggregate import aggregate_datasets

    spec, first_meta, fps = _first_episode_spec(items, fps, max_people, n_max, local_map)
    # balanced by frames (the export's cost is per frame; bytes per frame vary with the crowd)
    blocks = shard_blocks(frames, shards)
    work = root / ".shards"
    work.mkdir(parents=True)
    roots = [work / f"shard_{i:03d}" for i in range(len(blocks))]
    jobs = [(items[a:b], r, repo_id, fps, spec, first_meta, a, vcodec, progress, i)
            for i, ((a, b), r) in enumerate(zip(blocks, roots, strict=True))]
    # progress: one frame bar per shard (tqdm positions), none for the shards themselves
    parts: list[_Written] = map_jobs(_export_shard, jobs, len(jobs), "export shards", progress=False,
                                     unit="shard", executor=executor)
    t0 = time.monotonic()
    first_frame = 0
    for r, part, (a, _b) in zip(roots, parts, blocks, strict=True):
        _shift_index_stats(r, a, first_frame)
        first_frame += part.frames
    merged = work / "merged"
    with quiet_lerobot(), _arrow_data_aggregation():
        aggregate_datasets([repo_id] * len(roots), repo_id, roots=roots, aggr_root=merged,
                           data_files_size_in_mb=DATA_FILE_MB)
    for child in merged.iterdir():
        os.rename(child, root / child.name)
    shutil.rmtree(work)
    rows = [r for p in parts for r in p.rows]
    w = _Written(rows, spec, first_meta, fps, sum(p.frames for p in parts))
    return w, {"shards": len(blocks), "merge_seconds": round(time.monotonic() - t0, 3)}


def _annotate_info(root: Path, infos: dict[str, dict[str, Any]]) -> None:
    """Adds our ``info`` dict to each feature of lerobot's ``meta/info.json`` (merged into lerobot's own, e.g. the
    videos' ``video.*`` keys), where lerobot's dataset tools keep it; same layout (indent 4)."""
    path = root / "meta" / "info.json"
    info = json.loads(path.read_text())
    for name, extra in infos.items():
        ft = info["features"][name]
        ft["info"] = {**(ft.get("info") or {}), **extra}
    atomic_write_text(path, json.dumps(info, indent=4, ensure_ascii=False))


def _sort_stats(root: Path) -> None:
    """Rewrites ``meta/stats.json`` with sorted keys (lerobot's aggregation collects the feature names in a set,
    so its key order follows PYTHONHASHSEED); same values, same layout (lerobot's indent of 4)."""
    path = root / "meta" / "stats.json"
    if path.is_file():
        stats = json.loads(path.read_text())
        atomic_write_text(path, json.dumps(stats, indent=4, ensure_ascii=False, sort_keys=True))


def _json_safe(obj: Any) -> Any:
    """A JSON-safe copy: NaN/inf become None, numpy values plain Python."""
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_json_safe(v) for v in obj]
    if hasattr(obj, "item") and not isinstance(obj, str):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def export_dataset(inputs: Iterable[Any], out_dir: Path, repo_id: str, fps: int | None = None,
                   overwrite: bool = False, *, max_people: int | None = None,
                   n_max: int = N_MAX_PEDESTRIANS, local_map: LocalMapSpec | None = None,
                   progress: bool = True, vcodec: str = VCODEC, shards: int = 1,
                   executor: Executor | None = None, min_shard_frames: int = MIN_SHARD_FRAMES) -> dict[str, Any]:
    """Exports episodes into a validated LeRobot dataset at ``out_dir``, atomically.

    Args:
        inputs: complete MCAP episode paths (``*.partial`` refused) and/or Episode-like objects, in order;
            a list of paths is checked before anything is written.
        out_dir: the dataset directory to publish.
        repo_id: LeRobot repo id (``owner/name``).
        fps: frames per second; must equal ``1 / dt_s`` (default: from the first episode).
        overwrite: replace an existing ``out_dir`` (kept until the new dataset is complete and valid).
        max_people, n_max, local_map, progress, vcodec, shards, executor, min_shard_frames: see
            :func:`write_dataset`.

    Returns:
        ``{"episodes", "frames", "seconds", "frames_per_s", "doctor_seconds"}``.

    Raises:
        OutputExistsError: ``out_dir`` exists (and is not an empty directory) and ``overwrite`` is false.
        InputMissingError / CorruptArtifactError / FeatureError: see :func:`write_dataset`; also when the
            doctor finds a problem in the written dataset. Nothing is published then.
    """

    if isinstance(inputs, list | tuple):
        check_inputs([p for p in inputs if isinstance(p, str | os.PathLike)])
    out_dir = Path(out_dir)
    with OutputDir(out_dir, "overwrite" if overwrite else "new") as od:
        counts = write_dataset(inputs, od.path, repo_id, fps, max_people=max_people, n_max=n_max,
                               local_map=local_map, progress=progress, vcodec=vcodec, shards=shards,
                               executor=executor, min_shard_frames=min_shard_frames)
        t0 = time.monotonic()
        problems = check_dataset(od.path)
        counts["doctor_seconds"] = round(time.monotonic() - t0, 3)
        if problems:
            more = f" (and {len(problems) - 1} more problem(s))" if len(problems) > 1 else ""
            raise CorruptArtifactError(f"exported dataset failed validation, nothing published to {out_dir}: "
                                       f"{problems[0]}{more}")
    log.info("exported %d episodes, %d frames (%.1f frames/s) -> %s", counts["episodes"], counts["frames"],
             counts["frames_per_s"], out_dir)
    return counts


def export_run(raw_dir: Path, out_dir: Path, repo_id: str, fps: int | None = None, overwrite: bool = False,
               **kwargs: Any) -> dict[str, Any]:
    """Exports every complete ``*.mcap`` of a recording directory, in sorted order.

    ``*.partial`` files (unfinished recordings) are skipped with one warning line naming them.

    Args:
        raw_dir: the directory of per-episode MCAP files.
        out_dir, repo_id, fps, overwrite, kwargs: see :func:`export_dataset`.

    Returns:
        :func:`export_dataset`'s counts plus ``skipped_partial``.

    Raises:
        InputMissingError: ``raw_dir`` does not exist or holds no complete ``*.mcap``.
    """
    raw_dir = Path(raw_dir)
    if not raw_dir.is_dir():
        raise InputMissingError(f"missing recording directory: {raw_dir}")
    files = sorted(p for p in raw_dir.glob("*.mcap") if p.is_file())
    partial = sorted(p for p in raw_dir.glob(f"*{PARTIAL_SUFFIX}") if p.is_file())
    if partial:
        log.warning("export: skipping %d unfinished recording(s) (*%s): %s", len(partial), PARTIAL_SUFFIX,
                    ", ".join(p.name for p in partial))
    if not files:
        raise InputMissingError(f"no complete *.mcap episode in {raw_dir}"
                                + (f" ({len(partial)} *{PARTIAL_SUFFIX} skipped)" if partial else ""))
    counts = export_dataset(files, out_dir, repo_id, fps, overwrite, **kwargs)
    counts["skipped_partial"] = len(partial)
    return counts


@reports_errors
def main(argv: list[str] | None = None) -> int:
    """``python -m recorder.export RAW_DIR OUT_DIR --repo-id ID [--fps N] [--overwrite]``."""
    ap = argparse.ArgumentParser(prog="python -m recorder.export", description=__doc__.split("\n")[0])
    ap.add_argument("raw_dir", type=Path, help="directory of per-episode *.mcap files")
    ap.add_argument("out_dir", type=Path, help="the LeRobot dataset directory to create")
    ap.add_argument("--repo-id", required=True, help="LeRobot repo id, owner/name")
    ap.add_argument("--fps", type=int, default=None, help="frames per second (default: 1 / dt_s)")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing dataset")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    counts = export_run(args.raw_dir, args.out_dir, args.repo_id, args.fps, args.overwrite,
                        progress=not args.no_progress)
    print(json.dumps(counts))
    return 0


if __name__ == "__main__":
    sys.exit(main())
