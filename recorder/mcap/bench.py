"""The measurement behind the writer's defaults: :func:`benchmark_writer` times MCAP writing per compression and
chunk size (``python -m recorder.mcap.cli bench``).

Chunking and compression were chosen by measuring (``python -m recorder.mcap.cli bench --density D``): a realistic
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

import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from recorder.mcap.writer import EpisodeWriter
from recorder.schema import CAMERA_NAMES, EpisodeMeta, Frame


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
