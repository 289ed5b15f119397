"""Dataset benchmark: loading a ``chunk``-step action chunk with stock lerobot, ours against a stock-shaped dataset.

::

    from recorder.bench import measure_chunk_loading
    measure_chunk_loading(Path("data/datasets/run"), Path("/tmp/chunkbench"))   # or: make bench

A policy trained with action chunking reads ``LeRobotDataset(..., delta_timestamps={"action": [i / fps for i in
range(chunk)]})[i]``. Stock lerobot 0.4.4 sets ``hf_transform_to_torch`` as the ``hf_dataset`` transform, so
fetching the ``chunk`` rows of the action formats *every* column of those rows into Python lists: the cost grows
with the numbers per parquet row, and our rows are wide (two depth maps, the local occupancy crop, the privileged
pedestrian keypoints ...). The figure (not an assertion) is the median time per item of three datasets with the
same fps, episodes and frames per episode, read with the same seeded indices:

* ``ours`` — the dataset as exported (:mod:`recorder.export`);
* ``stock_shaped`` — what a stock LeRobot dataset of the same length looks like: the same ``observation.images.*``
  video cameras (same names and sizes, AV1 like our export), ``observation.state`` float32 (5,), ``action``
  float32 (2,), ``next.reward`` float32 (1,), ``next.done`` bool (1,); synthetic, seeded content, written with
  ``LeRobotDataset.create`` / ``add_frame`` / ``save_episode`` / ``finalize``;
* ``ours_policy_features`` — ours after stock lerobot's ``dataset_tools.remove_feature`` of the wide features a
  stock policy does not read (every ``observation.depth.*`` and ``privileged.*`` feature of ``meta/info.json``).

Everything is written under ``work_dir`` (sub-directories are recreated on every call), including the HF
``datasets`` arrow cache that ``LeRobotDataset`` fills on load (``datasets.config.HF_DATASETS_CACHE`` is pointed
there while measuring, so repeated benchmarks do not pile up entries in ``~/.cache``). Only ``meta/info.json`` of
the source is relied on (feature names, dtypes, shapes, fps) plus its parquet ``episode_index`` column.

:mod:`pipeline.core.timing` measures mean calls per second over a time budget; this figure is a median over a
fixed, seeded set of items (the same for every variant), so it times the calls itself.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import shutil
import statistics
import time
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.keys import ACTION, NEXT_DONE, NEXT_REWARD, OBS_DEPTH, OBS_STATE
from recorder.export import VCODEC, add_frame, quiet_lerobot, remove_empty_images_dir

log = logging.getLogger("icrowdnav")

VARIANTS = ("ours", "stock_shaped", "ours_policy_features")
WIDE_PREFIXES = (f"{OBS_DEPTH}.", "privileged.")  # features a stock policy does not read
_FIGURE_NAME = {"ours": "ours", "stock_shaped": "stock_shaped", "ours_policy_features": "policy_features"}
_CACHE_DIR = "hf_datasets_cache"
_STOCK_DIR = "stock_shaped"
_POLICY_DIR = "policy_features"


def info_of(root: Path) -> dict[str, Any]:
    """The dataset's ``meta/info.json``."""
    return json.loads((Path(root) / "meta" / "info.json").read_text())


def row_numbers(features: dict[str, dict]) -> int:
    """Numbers per parquet row: the sum of ``prod(shape)`` over the non-video features."""
    return int(sum(math.prod(int(d) for d in ft["shape"]) for ft in features.values()
                   if ft.get("dtype") not in ("video", "image")))


def wide_features(features: dict[str, dict]) -> list[str]:
    """The features a stock policy does not read: every ``observation.depth.*`` and ``privileged.*`` one."""
    return [k for k in features if k.startswith(WIDE_PREFIXES)]


def episode_lengths(root: Path) -> list[int]:
    """Frames per episode, in ``episode_index`` order, from the parquet ``episode_index`` column."""
    import pyarrow.parquet as pq

    paths = sorted((Path(root) / "data").glob("*/*.parquet"))
    if not paths:
        raise FileNotFoundError(f"{root}: no data/*/*.parquet")
    index = np.concatenate([pq.read_table(p, columns=["episode_index"]).column(0).to_numpy() for p in paths])
    counts = np.bincount(index.astype(np.int64))
    return [int(c) for c in counts if c > 0]


@contextlib.contextmanager
def datasets_cache(path: Path) -> Iterator[None]:
    """Points the HF ``datasets`` arrow cache (filled by ``LeRobotDataset`` on load) at ``path`` for a while."""
    import datasets.config

    old = datasets.config.HF_DATASETS_CACHE
    datasets.config.HF_DATASETS_CACHE = Path(path)
    try:
        yield
    finally:
        datasets.config.HF_DATASETS_CACHE = old


def _camera_frames(rng: np.random.Generator, shape: tuple[int, int, int], length: int) -> Iterator[np.ndarray]:
    """Smooth, moving uint8 frames (coarse seeded noise upsampled and panned): video-like, cheap to encode."""
    h, w, c = shape
    cell = 8
    coarse = rng.integers(0, 256, (h // cell + 2, (w + length) // cell + 2, c), dtype=np.uint8)
    wide = np.repeat(np.repeat(coarse, cell, axis=0), cell, axis=1)
    for t in range(length):
        yield np.ascontiguousarray(wide[:h, t:t + w])


def write_stock_shaped(root: Path, out: Path, *, seed: int = 0, repo_id: str = "bench/stock_shaped",
                       vcodec: str = VCODEC) -> Path:
    """Writes a stock-shaped LeRobot dataset at ``out`` (which must not exist) with ``root``'s fps, episode lengths
    and video cameras (names and sizes); synthetic content seeded by ``seed``. Returns ``out``."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    info = info_of(root)
    fps = int(info["fps"])
    cameras = {k: tuple(int(d) for d in ft["shape"]) for k, ft in info["features"].items() if ft["dtype"] == "video"}
    features: dict[str, dict] = {
        k: {"dtype": "video", "shape": shape, "names": ["height", "width", "channels"]} for k, shape in cameras.items()}
    features.update({
        OBS_STATE: {"dtype": "float32", "shape": (5,), "names": [f"s{i}" for i in range(5)]},
        ACTION: {"dtype": "float32", "shape": (2,), "names": ["a0", "a1"]},
        NEXT_REWARD: {"dtype": "float32", "shape": (1,), "names": ["reward"]},
        NEXT_DONE: {"dtype": "bool", "shape": (1,), "names": ["done"]},
    })
    scalar_keys = [k for k, ft in features.items() if tuple(ft["shape"]) == (1,)]
    ds = LeRobotDataset.create(repo_id, fps, features, root=out, robot_type="bench", use_videos=True, vcodec=vcodec,
                               video_backend="pyav")
    try:
        for ep, length in enumerate(episode_lengths(root)):
            rng = np.random.default_rng([seed, ep])
            images = {k: _camera_frames(rng, shape, length) for k, shape in cameras.items()}
            state = rng.standard_normal((length, 5)).astype(np.float32)
            action = rng.uniform(-1.0, 1.0, (length, 2)).astype(np.float32)
            reward = rng.standard_normal((length, 1)).astype(np.float32)
            for i in range(length):
                frame = {k: next(it) for k, it in images.items()}
                frame.update({OBS_STATE: state[i], ACTION: action[i], NEXT_REWARD: reward[i],
                              NEXT_DONE: np.array([i == length - 1]), "task": "bench"})
                add_frame(ds, frame, scalar_keys)
            with quiet_lerobot():
                ds.save_episode(parallel_encoding=False)
        ds.finalize()
    except BaseException:
        with contextlib.suppress(Exception):
            ds.finalize()
        raise
    remove_empty_images_dir(out)
    return Path(out)


def write_policy_features(root: Path, out: Path, *, repo_id: str = "bench/policy_features") -> list[str]:
    """Writes ``root`` without its wide features (:func:`wide_features`) at ``out`` (which must not exist) with
    stock lerobot's ``dataset_tools.remove_feature``. Returns the removed feature names."""
    from lerobot.datasets.dataset_tools import remove_feature
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    removed = wide_features(info_of(root)["features"])
    src = LeRobotDataset("bench/ours", root=root, video_backend="pyav")
    with quiet_lerobot():
        remove_feature(src, removed, output_dir=out, repo_id=repo_id)
    return removed


def chunk_indices(total_frames: int, items: int, seed: int) -> list[int]:
    """``items`` seeded frame indices (distinct where the dataset has enough frames)."""
    rng = np.random.default_rng(seed)
    return [int(i) for i in rng.choice(total_frames, size=items, replace=items > total_frames)]


def time_chunk_loading(root: Path, indices: Iterable[int], chunk: int, *, repo_id: str = "bench/dataset") -> float:
    """Median ms per item of ``LeRobotDataset(root, video_backend="pyav", delta_timestamps={"action": chunk
    steps})[i]`` over ``indices`` (after one warm-up item)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    indices = list(indices)
    fps = int(info_of(root)["fps"])
    ds = LeRobotDataset(repo_id, root=root, video_backend="pyav",
                        delta_timestamps={ACTION: [i / fps for i in range(chunk)]})
    seconds = []
    with warnings.catch_warnings():  # pyav decoding goes through torchvision.io, which warns once per process
        warnings.filterwarnings("ignore", "The video decoding and encoding capabilities of torchvision",
                                UserWarning)
        item = ds[indices[0]]  # warm-up: opens the arrow table and the video containers
        if tuple(item[ACTION].shape[:1]) != (chunk,):
            raise RuntimeError(f"{root}: expected an action chunk of {chunk} steps, "
                               f"got shape {tuple(item[ACTION].shape)}")
        for i in indices:
            t0 = time.perf_counter()
            ds[i]
            seconds.append(time.perf_counter() - t0)
    return 1000.0 * statistics.median(seconds)


def measure_chunk_loading(root: Path, work_dir: Path, *, chunk: int = 100, items: int = 8, seed: int = 0,
                          variants: Iterable[str] = VARIANTS) -> dict[str, float]:
    """The chunk-loading figures of ``root`` (see the module docstring), written datasets under ``work_dir``.

    Returns:
        ``chunk_load_steps``, ``chunk_load_ms_<variant>`` (``ours``, ``stock_shaped``, ``policy_features``),
        ``chunk_load_ratio`` (ours / stock-shaped) and ``chunk_load_ratio_policy_features`` (policy features /
        stock-shaped) when the stock-shaped dataset is measured, and ``row_numbers_<variant>`` (numbers per parquet
        row).
    """
    variants = tuple(variants)
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        raise ValueError(f"variants: unknown {unknown}, expected some of {list(VARIANTS)}")
    if chunk < 1 or items < 1:
        raise ValueError(f"chunk and items: expected >= 1, got {chunk} and {items}")
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    root, work_dir = Path(root), Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    for sub in (_CACHE_DIR, _STOCK_DIR, _POLICY_DIR):
        if (work_dir / sub).exists():
            shutil.rmtree(work_dir / sub)
    roots = {"ours": root}
    out: dict[str, float] = {"chunk_load_steps": float(chunk)}
    with datasets_cache(work_dir / _CACHE_DIR):
        if "stock_shaped" in variants:
            roots["stock_shaped"] = write_stock_shaped(root, work_dir / _STOCK_DIR, seed=seed)
        if "ours_policy_features" in variants:
            write_policy_features(root, work_dir / _POLICY_DIR)
            roots["ours_policy_features"] = work_dir / _POLICY_DIR
        indices = chunk_indices(int(info_of(root)["total_frames"]), items, seed)
        for variant in variants:
            name = _FIGURE_NAME[variant]
            out[f"row_numbers_{name}"] = float(row_numbers(info_of(roots[variant])["features"]))
            out[f"chunk_load_ms_{name}"] = time_chunk_loading(roots[variant], indices, chunk, repo_id=f"bench/{name}")
            log.info("bench: %d-step action chunk, %s: %.1f ms per item", chunk, name, out[f"chunk_load_ms_{name}"])
    if "stock_shaped" in variants:
        for variant, key in (("ours", "chunk_load_ratio"), ("ours_policy_features", "chunk_load_ratio_policy_features")):
            if variant in variants:
                out[key] = out[f"chunk_load_ms_{_FIGURE_NAME[variant]}"] / out["chunk_load_ms_stock_shaped"]
    return out
