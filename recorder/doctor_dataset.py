"""The dataset doctor: checks that a LeRobot v3.0 dataset directory is complete and self-consistent.

::

    python -m recorder.doctor_dataset data/datasets/run      # one line per problem, exit 1 if any

A LeRobot writer killed mid-way can leave parquet files without footers, an episode index with gaps, totals in
``meta/info.json`` that disagree with the data, and videos that stop early (see ``RELIABILITY.md``). The doctor
checks, naming the file in every problem line:

* ``meta/info.json`` parses, is codebase ``v3.x`` and has the keys the format needs;
* every ``*.parquet`` has a valid footer (pyarrow reads its metadata);
* ``meta/episodes``: episode indices are exactly ``0..E-1`` in order, ``E`` = ``total_episodes``, lengths add
  up to ``total_frames`` and each episode's ``[dataset_from_index, dataset_to_index)`` continues the previous;
* ``data``: every data file ``meta/episodes`` names exists; the global ``index`` is ``0..N-1`` in file order,
  ``N`` = ``total_frames``; every episode has exactly ``length`` rows, in the file its metadata names, with
  ``frame_index`` ``0..length-1`` and ``timestamp`` = ``frame_index / fps``; task indices exist in
  ``meta/tasks.parquet``; every non-video feature of ``info.json`` is a column;
* ``videos``: every video file decodes with PyAV (every frame), has the feature's size, and every timestamp the
  dataset references (``from_timestamp + frame_index / fps`` of every frame of every episode) has a decoded
  frame within ``tolerance_s``; the episode's ``[from, to)`` span covers its frames (without decoding: every video
  file the episodes name exists and is not empty);
* ``meta/stats.json``: min, max and mean of every numeric non-video feature (and ``count``) match values
  recomputed from the data the way lerobot computes them (over every axis but the last);
* our annotations of ``meta/info.json`` (the dataset format, every camera's calibration:
  :func:`recorder.dataset_info.read_dataset_info`); ``meta/icrowdnav.json`` and ``meta/icrowdnav_episodes.jsonl``
  (optional extras written by :mod:`recorder.export`; lerobot's dataset tools drop them), where present, agree with
  the episode count, fps and episode lengths.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.core.errors import CorruptArtifactError, InputMissingError
from recorder.dataset_info import (
    ICROWDNAV_EPISODES,
    ICROWDNAV_META,
    INFO,
    read_dataset_info,
)

STATS = "meta/stats.json"
TASKS = "meta/tasks.parquet"
EPISODES_DIR = "meta/episodes"
DEFAULT_KEYS = ("timestamp", "frame_index", "episode_index", "index", "task_index")
RENUMBERED = ("index", "episode_index")  # lerobot's dataset tools renumber these columns
TOLERANCE_S = 1e-4  # lerobot's default tolerance between a requested and a decoded video timestamp


class _Report:
    """Collects problem lines ``<file>: <message>``; ``missing`` holds those about a file that is not there."""

    def __init__(self, root: Path):
        self.root = root
        self.lines: list[str] = []
        self.missing: list[str] = []

    def add(self, rel: str | Path, msg: str, missing: bool = False) -> None:
        path = rel if Path(rel).is_absolute() else self.root / rel
        self.lines.append(f"{path}: {msg}")
        if missing:
            self.missing.append(self.lines[-1])


def _column_numpy(col: pa.ChunkedArray | pa.Array, shape: tuple[int, ...] = ()) -> np.ndarray:
    """A (possibly nested-list / HF extension) column as an ``(rows, *shape)`` numpy array."""
    arr = col.combine_chunks() if isinstance(col, pa.ChunkedArray) else col
    if isinstance(arr, pa.ExtensionArray):
        arr = arr.storage
    rows = len(arr)
    while pa.types.is_list(arr.type) or pa.types.is_large_list(arr.type) or pa.types.is_fixed_size_list(arr.type):
        arr = arr.flatten()
        if isinstance(arr, pa.ExtensionArray):
            arr = arr.storage
    values = arr.to_numpy(zero_copy_only=False)
    return values.reshape((rows, *shape)) if rows else values.reshape((0, *shape))


def _chunk_file(template: str, **kw: Any) -> str:
    return template.format(**kw)


def _check_info(root: Path, rep: _Report) -> dict | None:
    path = root / INFO
    if not path.is_file():
        rep.add(INFO, "missing: not a LeRobot dataset (or an unfinished export)", missing=True)
        return None
    try:
        info = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        rep.add(INFO, f"unreadable JSON: {e}")
        return None
    need = ("codebase_version", "fps", "total_episodes", "total_frames", "total_tasks", "features", "data_path")
    missing = [k for k in need if k not in info]
    if missing:
        rep.add(INFO, f"missing keys {missing}")
        return None
    if not str(info["codebase_version"]).startswith("v3."):
        rep.add(INFO, f"codebase_version: expected v3.x, got {info['codebase_version']!r}")
        return None
    if not (isinstance(info["fps"], int | float) and info["fps"] > 0):
        rep.add(INFO, f"fps: expected > 0, got {info['fps']!r}")
        return None
    return info


def _check_footers(root: Path, rep: _Report) -> set[Path]:
    """Every parquet file's footer; returns the readable ones."""
    good = set()
    for p in sorted(root.rglob("*.parquet")):
        if any(part.startswith(".") for part in p.relative_to(root).parts):
            continue
        try:
            pq.read_metadata(p)
        except Exception as e:
            rep.add(p.relative_to(root), f"not a readable parquet file (footer missing or damaged): "
                    f"{type(e).__name__}: {e}")
            continue
        good.add(p)
    return good


def _load_episodes(root: Path, good: set[Path], info: dict, rep: _Report) -> list[dict]:
    """Episode rows (non-stats columns) with ``_file`` = the episodes file they came from."""
    files = sorted((root / EPISODES_DIR).glob("chunk-*/file-*.parquet"))
    if not files:
        rep.add(EPISODES_DIR, "no episodes metadata files (chunk-*/file-*.parquet)", missing=True)
        return []
    rows: list[dict] = []
    for p in files:
        if p not in good:
            continue  # already reported
        try:
            schema = pq.read_schema(p)
            cols = [c for c in schema.names if not c.startswith("stats/")]
            table = pq.read_table(p, columns=cols)
        except Exception as e:
            rep.add(p.relative_to(root), f"cannot read the episodes table: {type(e).__name__}: {e}")
            continue
        need = ("episode_index", "length", "dataset_from_index", "dataset_to_index", "data/chunk_index",
                "data/file_index")
        missing = [c for c in need if c not in table.column_names]
        if missing:
            rep.add(p.relative_to(root), f"missing columns {missing}")
            continue
        for r in table.to_pylist():
            r["_file"] = p.relative_to(root).as_posix()
            rows.append(r)
    return rows


def _check_episodes(rows: list[dict], info: dict, rep: _Report) -> None:
    prev_to = 0
    for expected, r in enumerate(rows):
        f = r["_file"]
        if r["episode_index"] != expected:
            rep.add(f, f"episode index gap: expected episode_index {expected} next, got {r['episode_index']} "
                       "(indices must be 0..E-1 in order)")
            break
        if r["dataset_to_index"] - r["dataset_from_index"] != r["length"]:
            rep.add(f, f"episode {expected}: dataset_to_index - dataset_from_index = "
                       f"{r['dataset_to_index'] - r['dataset_from_index']}, expected length {r['length']}")
        if r["dataset_from_index"] != prev_to:
            rep.add(f, f"episode {expected}: dataset_from_index {r['dataset_from_index']}, expected {prev_to} "
                       "(the previous episode's dataset_to_index)")
        prev_to = r["dataset_to_index"]
    if len(rows) != info["total_episodes"]:
        rep.add(INFO, f"total_episodes {info['total_episodes']} but meta/episodes holds {len(rows)} episode(s)")
    total = sum(int(r["length"]) for r in rows)
    if total != info["total_frames"]:
        rep.add(INFO, f"total_frames {info['total_frames']} but the episodes' lengths add up to {total}")


def _data_files(root: Path) -> list[Path]:
    return sorted((root / "data").glob("chunk-*/file-*.parquet"))


def _check_data(root: Path, good: set[Path], info: dict, rows: list[dict], n_tasks: int | None,
                rep: _Report) -> dict[int, np.ndarray]:
    """Index/frame/timestamp invariants; returns ``episode -> frame_index array`` as found in the data."""
    fps = float(info["fps"])
    files = _data_files(root)
    named: dict[str, list[int]] = defaultdict(list)  # data file -> the episodes meta/episodes places in it
    for r in rows:
        named[_chunk_file(info["data_path"], chunk_index=r["data/chunk_index"],
                          file_index=r["data/file_index"])].append(int(r["episode_index"]))
    absent = {rel for rel in named if not (root / rel).is_file()}
    for rel in sorted(absent):
        eps = named[rel]
        rep.add(rel, f"missing: meta/episodes places {_span(eps)} in this data file", missing=True)
    if not files:
        if not absent:
            rep.add("data", "no data files (chunk-*/file-*.parquet)", missing=True)
        return {}
    feats = info["features"]
    want_cols = [k for k, ft in feats.items() if ft.get("dtype") != "video"]
    parts: list[tuple[str, dict[str, np.ndarray]]] = []
    for p in files:
        rel = p.relative_to(root).as_posix()
        if p not in good:
            continue
        try:
            names = pq.read_schema(p).names
            missing = [c for c in want_cols if c not in names]
            if missing:
                rep.add(rel, f"missing feature column(s) {missing} listed in {INFO}")
            table = pq.read_table(p, columns=[c for c in DEFAULT_KEYS if c in names])
        except Exception as e:
            rep.add(rel, f"cannot read: {type(e).__name__}: {e}")
            continue
        cols = {c: _column_numpy(table[c]) for c in table.column_names}
        if any(c not in cols for c in DEFAULT_KEYS):
            continue
        parts.append((rel, cols))
    if not parts:
        return {}
    # global index contiguous in file order
    n_seen = 0
    for rel, cols in parts:
        idx = cols["index"]
        want = np.arange(n_seen, n_seen + len(idx))
        if not np.array_equal(idx, want):
            bad = int(np.flatnonzero(idx != want)[0])
            rep.add(rel, f"index not contiguous: row {bad} has index {int(idx[bad])}, expected {int(want[bad])}")
        n_seen += len(idx)
    if n_seen != info["total_frames"]:
        rep.add(INFO, f"total_frames {info['total_frames']} but the data files hold {n_seen} rows")
    # per episode
    found: dict[int, list[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]] = defaultdict(list)
    for rel, cols in parts:
        ep = cols["episode_index"]
        for e in np.unique(ep):
            m = ep == e
            found[int(e)].append((rel, cols["index"][m], cols["frame_index"][m], cols["timestamp"][m],
                                  cols["task_index"][m]))
        if n_tasks is not None and len(cols["task_index"]) and (
                cols["task_index"].min() < 0 or cols["task_index"].max() >= n_tasks):
            rep.add(rel, f"task_index outside 0..{n_tasks - 1} (the tasks in {TASKS})")
    known = {int(r["episode_index"]) for r in rows}
    for e in sorted(set(found) - known):
        rep.add(found[e][0][0], f"rows of episode {e}, which meta/episodes does not list")
    frame_indices: dict[int, np.ndarray] = {}
    for r in rows:
        e = int(r["episode_index"])
        want_file = _chunk_file(info["data_path"], chunk_index=r["data/chunk_index"], file_index=r["data/file_index"])
        pieces = found.get(e, [])
        files_of_e = sorted({x[0] for x in pieces})
        if not pieces:
            if want_file not in absent:  # a missing file is reported once, above
                rep.add(want_file, f"episode {e}: no rows (meta/episodes says {r['length']} frames here)")
            continue
        if files_of_e != [want_file]:
            rep.add(want_file, f"episode {e}: rows found in {files_of_e}, expected only in this file")
        index = np.concatenate([x[1] for x in pieces])
        fidx = np.concatenate([x[2] for x in pieces])
        ts = np.concatenate([x[3] for x in pieces])
        frame_indices[e] = fidx
        n = len(index)
        if n != r["length"]:
            rep.add(want_file, f"episode {e}: {n} rows, expected length {r['length']} (meta/episodes)")
        if not np.array_equal(index, np.arange(r["dataset_from_index"], r["dataset_from_index"] + n)):
            rep.add(want_file, f"episode {e}: index runs {int(index.min())}..{int(index.max())}, expected "
                               f"{r['dataset_from_index']}..{r['dataset_to_index'] - 1}")
        if not np.array_equal(fidx, np.arange(n)):
            rep.add(want_file, f"episode {e}: frame_index is not 0..{n - 1} in order")
        err = np.abs(ts.astype(np.float64) - fidx / fps)
        tol = np.maximum(TOLERANCE_S, 1e-6 * np.abs(fidx / fps))
        if np.any(err > tol):
            k = int(np.argmax(err > tol))
            rep.add(want_file, f"episode {e}: timestamp {float(ts[k]):.6f} at frame_index {int(fidx[k])}, "
                               f"expected frame_index / fps = {fidx[k] / fps:.6f}")
    return frame_indices


def _decode_video(path: Path) -> tuple[np.ndarray, tuple[int, int] | None, str | None]:
    """Decodes every frame: ``(timestamps_s, (height, width), error)``; timestamps of frames before an error."""
    import av

    times: list[float] = []
    size = None
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                return np.zeros(0), None, "no video stream"
            stream = container.streams.video[0]
            for frame in container.decode(stream):
                if frame.pts is None:
                    continue
                times.append(float(frame.pts * stream.time_base))
                size = (frame.height, frame.width)
    except Exception as e:  # PyAV raises its own error classes (InvalidDataError, EOFError, ...)
        return np.asarray(times), size, f"{type(e).__name__}: {e}"
    return np.asarray(times), size, None


def _check_videos(root: Path, info: dict, rows: list[dict], rep: _Report) -> None:
    fps = float(info["fps"])
    video_keys = [k for k, ft in info["features"].items() if ft.get("dtype") == "video"]
    if not video_keys:
        return
    template = info.get("video_path")
    if not template:
        rep.add(INFO, f"video features {video_keys} but no video_path")
        return
    for key in video_keys:
        shape = info["features"][key].get("shape", [])
        want_hw = (int(shape[0]), int(shape[1])) if len(shape) == 3 else None
        cols = [f"videos/{key}/{c}" for c in ("chunk_index", "file_index", "from_timestamp", "to_timestamp")]
        decoded: dict[str, tuple[np.ndarray, tuple[int, int] | None, str | None]] = {}
        for r in rows:
            e = int(r["episode_index"])
            if any(r.get(c) is None for c in cols):
                rep.add(r["_file"], f"episode {e}: missing video columns for '{key}'")
                continue
            rel = _chunk_file(template, video_key=key, chunk_index=r[cols[0]], file_index=r[cols[1]])
            if rel not in decoded:
                p = root / rel
                if not p.is_file():
                    decoded[rel] = (np.zeros(0), None, "missing")
                    rep.add(rel, f"video file of '{key}' is missing", missing=True)
                else:
                    decoded[rel] = _decode_video(p)
                    times, size, err = decoded[rel]
                    if err:
                        rep.add(rel, f"video does not decode after {len(times)} frame(s): {err}")
                    if size is not None and want_hw is not None and size != want_hw:
                        rep.add(rel, f"video frames are {size[0]}x{size[1]} (height x width), "
                                     f"expected {want_hw[0]}x{want_hw[1]} ({INFO} '{key}')")
            times, _, err = decoded[rel]
            if err == "missing":
                continue
            length = int(r["length"])
            t0, t1 = float(r[cols[2]]), float(r[cols[3]])
            if t1 - t0 < length / fps - TOLERANCE_S:
                rep.add(rel, f"episode {e}: video span {t0:.4f}..{t1:.4f} s is shorter than its {length} "
                             f"frames at {fps:g} fps")
            wanted = t0 + np.arange(length) / fps
            if len(times) == 0:
                rep.add(rel, f"episode {e}: none of its {length} frame timestamps decodable (no frames)")
                continue
            srt = np.sort(times)
            pos = np.clip(np.searchsorted(srt, wanted), 1, len(srt) - 1) if len(srt) > 1 else np.zeros(
                length, int)
            near = np.minimum(np.abs(srt[pos] - wanted), np.abs(srt[np.maximum(pos - 1, 0)] - wanted))
            miss = near > TOLERANCE_S
            if np.any(miss):
                k = int(np.argmax(miss))
                rep.add(rel, f"episode {e}: {int(miss.sum())} of {length} frame timestamps not decodable "
                             f"(first {wanted[k]:.4f} s; the file decodes {len(srt)} frames, "
                             f"{srt[0]:.4f}..{srt[-1]:.4f} s)")


def _check_video_files(root: Path, info: dict, rows: list[dict], rep: _Report) -> None:
    """Without decoding: every video file the episodes name exists and is not empty."""
    template = info.get("video_path")
    for key in [k for k, ft in info["features"].items() if ft.get("dtype") == "video"]:
        if not template:
            rep.add(INFO, f"video features ['{key}', ...] but no video_path")
            return
        cols = (f"videos/{key}/chunk_index", f"videos/{key}/file_index")
        named: dict[str, list[int]] = defaultdict(list)
        for r in rows:
            if any(r.get(c) is None for c in cols):
                rep.add(r["_file"], f"episode {r['episode_index']}: missing video columns for '{key}'")
                continue
            named[_chunk_file(template, video_key=key, chunk_index=r[cols[0]], file_index=r[cols[1]])].append(
                int(r["episode_index"]))
        for rel, eps in sorted(named.items()):
            p = root / rel
            if not p.is_file():
                rep.add(rel, f"video file of '{key}' is missing (meta/episodes places {_span(eps)} in it)", missing=True)
            elif p.stat().st_size == 0:
                rep.add(rel, f"video file of '{key}' is empty (0 bytes), expected the frames of {_span(eps)}")


def _span(eps: list[int]) -> str:
    """``episode 3`` or ``episodes 0..7``: the episodes a file holds (they are consecutive)."""
    return f"episode {eps[0]}" if len(eps) == 1 else f"episodes {min(eps)}..{max(eps)}"


def _check_stats(root: Path, good: set[Path], info: dict, rep: _Report) -> None:
    path = root / STATS
    if not path.is_file():
        rep.add(STATS, "missing")
        return
    try:
        stats = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        rep.add(STATS, f"unreadable JSON: {e}")
        return
    feats = info["features"]
    # not 'index' / 'episode_index': lerobot's delete_episodes renumbers them but keeps their recorded per-episode
    # stats (bookkeeping columns, never normalised)
    numeric = [k for k, ft in feats.items()
               if ft.get("dtype") not in ("video", "image", "string") and k not in RENUMBERED]
    for k in [k for k, ft in feats.items() if ft.get("dtype") == "video"]:
        s = stats.get(k)
        if s is None:
            rep.add(STATS, f"no stats for video feature '{k}'")
            continue
        for q in ("min", "max", "mean"):
            v = np.asarray(s.get(q, []), dtype=np.float64)
            if v.shape != (3, 1, 1) or np.any(v < -1e-6) or np.any(v > 1 + 1e-6):
                rep.add(STATS, f"'{k}' {q}: expected 3x1x1 values in [0, 1], got shape {v.shape}")
    acc: dict[str, dict[str, Any]] = {}
    for p in _data_files(root):
        if p not in good:
            return  # a damaged data file is already reported; stats cannot be recomputed
        try:
            names = pq.read_schema(p).names
        except Exception:
            return
        for k in numeric:
            if k not in names:
                continue
            shape = tuple(int(s) for s in feats[k]["shape"])
            shape = () if shape == (1,) else shape
            try:
                x = _column_numpy(pq.read_table(p, columns=[k])[k], shape)
            except Exception as e:
                rep.add(p.relative_to(root), f"cannot read column '{k}': {type(e).__name__}: {e}")
                continue
            x = x.astype(np.float64).reshape(-1, 1 if x.ndim == 1 else x.shape[-1])
            if len(x) == 0:
                continue
            a = acc.setdefault(k, {"min": None, "max": None, "sum": 0.0, "n": 0, "rows": 0})
            a["min"] = x.min(0) if a["min"] is None else np.minimum(a["min"], x.min(0))
            a["max"] = x.max(0) if a["max"] is None else np.maximum(a["max"], x.max(0))
            a["sum"] = a["sum"] + x.sum(0)
            a["n"] += len(x)
    total = int(info["total_frames"])
    for k in numeric:
        if k not in acc:
            continue
        s = stats.get(k)
        if s is None:
            rep.add(STATS, f"no stats for feature '{k}'")
            continue
        a = acc[k]
        data = {"min": a["min"], "max": a["max"], "mean": a["sum"] / a["n"]}
        for q, rtol, atol in (("min", 1e-6, 1e-6), ("max", 1e-6, 1e-6), ("mean", 1e-4, 1e-4)):
            try:
                stored = np.asarray(s[q], dtype=np.float64).reshape(-1)
            except (KeyError, TypeError, ValueError) as e:
                rep.add(STATS, f"'{k}' {q}: unreadable ({type(e).__name__}: {e})")
                continue
            if stored.shape != data[q].shape:
                rep.add(STATS, f"'{k}' {q}: {stored.size} value(s) stored, expected {data[q].size}")
                continue
            if not np.allclose(stored, data[q], rtol=rtol, atol=atol):
                j = int(np.argmax(~np.isclose(stored, data[q], rtol=rtol, atol=atol)))
                rep.add(STATS, f"'{k}' {q} does not match the data: stored {stored[j]:.6g}, data {data[q][j]:.6g} "
                               f"(element {j})")
        count = np.asarray(s.get("count", [-1])).reshape(-1)
        if count.size != 1 or int(count[0]) != total:
            rep.add(STATS, f"'{k}' count {count.tolist()}, expected [{total}] (total_frames)")


def _check_tasks(root: Path, good: set[Path], info: dict, rep: _Report) -> int | None:
    p = root / TASKS
    if not p.is_file():
        rep.add(TASKS, "missing", missing=True)
        return None
    if p not in good:
        return None
    try:
        n = pq.read_metadata(p).num_rows
    except Exception as e:
        rep.add(TASKS, f"cannot read: {e}")
        return None
    if n != info["total_tasks"]:
        rep.add(INFO, f"total_tasks {info['total_tasks']} but {TASKS} holds {n} task(s)")
    return n


def _check_icrowdnav(root: Path, info: dict, rows: list[dict], rep: _Report) -> None:
    try:
        read_dataset_info(root)
    except CorruptArtifactError as e:
        rep.add(INFO, str(e).split(": ", 1)[-1])
    p = root / ICROWDNAV_META
    if p.is_file():
        try:
            meta = json.loads(p.read_text())
            if meta.get("total_episodes") != info["total_episodes"]:
                rep.add(ICROWDNAV_META, f"total_episodes {meta.get('total_episodes')}, expected "
                                        f"{info['total_episodes']} ({INFO})")
            if meta.get("total_frames") != info["total_frames"]:
                rep.add(ICROWDNAV_META, f"total_frames {meta.get('total_frames')}, expected "
                                        f"{info['total_frames']} ({INFO})")
            if meta.get("fps") is None or not math.isclose(float(meta["fps"]), float(info["fps"])):
                rep.add(ICROWDNAV_META, f"fps {meta.get('fps')}, expected {info['fps']} ({INFO})")
        except (OSError, ValueError, AttributeError) as e:
            rep.add(ICROWDNAV_META, f"unreadable JSON object: {e}")
    p = root / ICROWDNAV_EPISODES
    if not p.is_file():
        return
    try:
        eps = [json.loads(line) for line in p.read_text().splitlines() if line.strip()]
    except (OSError, ValueError) as e:
        rep.add(ICROWDNAV_EPISODES, f"unreadable JSON line: {e}")
        return
    if len(eps) != info["total_episodes"]:
        rep.add(ICROWDNAV_EPISODES, f"{len(eps)} row(s), expected {info['total_episodes']} (total_episodes)")
    lengths = {int(r["episode_index"]): int(r["length"]) for r in rows}
    for i, r in enumerate(eps):
        if not isinstance(r, dict) or r.get("episode_index") != i:
            rep.add(ICROWDNAV_EPISODES, f"row {i}: episode_index {r.get('episode_index') if isinstance(r, dict) else r!r}"
                                        f", expected {i}")
            break
        if i in lengths and r.get("length") != lengths[i]:
            rep.add(ICROWDNAV_EPISODES, f"episode {i}: length {r.get('length')}, expected {lengths[i]} "
                                        "(meta/episodes)")


def check_dataset(root: Path, *, videos: bool = True, stats: bool = True, icrowdnav: bool = True) -> list[str]:
    """Checks a LeRobot v3.0 dataset directory (see the module docstring for the invariants).

    Args:
        root: the dataset directory.
        videos: decode every video file and check every referenced timestamp (False: only check that every video
            file the episodes name exists and is not empty).
        stats: recompute min/max/mean of every numeric non-video feature and compare with ``meta/stats.json``.
        icrowdnav: check our ``info.json`` annotations and, where present, ``meta/icrowdnav*.json*``.

    Returns:
        One line per problem, each starting with the path of the file concerned; empty when the dataset is
        sound.
    """
    return _run(Path(root), videos, stats, icrowdnav).lines


def _run(root: Path, videos: bool, stats: bool, icrowdnav: bool) -> _Report:
    rep = _Report(root)
    if not root.is_dir():
        rep.lines.append(f"{root}: dataset directory does not exist")
        rep.missing.append(rep.lines[-1])
        return rep
    info = _check_info(root, rep)
    if info is None:
        return rep
    good = _check_footers(root, rep)
    rows = _load_episodes(root, good, info, rep)
    _check_episodes(rows, info, rep)
    n_tasks = _check_tasks(root, good, info, rep)
    _check_data(root, good, info, rows, n_tasks, rep)
    if videos:
        _check_videos(root, info, rows, rep)
    else:
        _check_video_files(root, info, rows, rep)
    if stats:
        _check_stats(root, good, info, rep)
    if icrowdnav:
        _check_icrowdnav(root, info, rows, rep)
    return rep


def require_sound_dataset(root: Path) -> None:
    """The doctor's cheap checks, as one error: what the stages that read a dataset (``pretrain``, ``train
    --variant vint``) run before lerobot opens it, whose own errors for a damaged dataset do not name the file (a
    deleted parquet gives ``OfflineModeIsEnabled: Cannot reach https://huggingface.co/...``, a truncated one
    ``DatasetGenerationError``).

    Cheap: :func:`check_dataset` without decoding videos or recomputing stats — ``meta/info.json``, every parquet
    footer, the episode and frame indices (five small columns of each data file), every data and video file the
    episodes name present, the iCrowdNav meta files. Measured: ~25 ms on the 62-frame smoke dataset, once pyarrow
    is warm (its first table read costs ~1.7 s of imports, which lerobot would pay anyway).

    Raises:
        InputMissingError: a file the dataset needs is missing (named; the first such problem).
        CorruptArtifactError: a file is damaged or disagrees with the metadata (named; the first problem).
        recorder.dataset_info.DatasetFormatError: the dataset was written by another version of the export.
        Each message ends with how many more problems ``icrowdnav doctor ROOT`` lists.
    """
    root = Path(root)
    if (root / INFO).is_file():
        read_dataset_info(root)  # a dataset of another format: DatasetFormatError, with the re-export command
    rep = _run(root, videos=False, stats=False, icrowdnav=True)
    if not rep.lines:
        return
    first = rep.missing[0] if rep.missing else rep.lines[0]
    more = len(rep.lines) - 1
    msg = f"damaged dataset {root}: {first}" + (
        f" (and {more} more problem(s); `icrowdnav doctor {root}` lists them)" if more else "")
    raise (InputMissingError if rep.missing else CorruptArtifactError)(msg)


def main(argv: list[str] | None = None) -> int:
    """``python -m recorder.doctor_dataset ROOT``: prints every problem; exit 1 if any, 2 on bad usage."""
    ap = argparse.ArgumentParser(prog="python -m recorder.doctor_dataset",
                                 description="check a LeRobot v3.0 dataset directory")
    ap.add_argument("root", type=Path, help="the dataset directory (holds meta/info.json)")
    ap.add_argument("--no-videos", action="store_true", help="skip decoding the videos")
    ap.add_argument("--no-stats", action="store_true", help="skip recomputing stats")
    ap.add_argument("--generic", action="store_true", help="skip the iCrowdNav checks (info.json annotations, meta/icrowdnav*)")
    args = ap.parse_args(argv)
    problems = check_dataset(args.root, videos=not args.no_videos, stats=not args.no_stats,
                             icrowdnav=not args.generic)
    for line in problems:
        print(f"problem: {line}")
    if problems:
        print(f"{args.root}: {len(problems)} problem(s)", file=sys.stderr)
        return 1
    info = json.loads((args.root / INFO).read_text())
    print(f"ok: {args.root}: {info['total_episodes']} episodes, {info['total_frames']} frames")
    return 0


if __name__ == "__main__":
    sys.exit(main())
