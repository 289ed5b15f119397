"""The golden episodes and artifacts of ``rehousing.json`` (shared by the generator and the test).

This module is the only place that names the code paths under test, so that a move of the code changes the
imports here and nothing in the golden file.
"""

from __future__ import annotations

import math
from pathlib import Path

from evaluation.harness import Job, run_episode
from evaluation.methods import resolve_methods
from sim.env import CameraConfig, SimConfig


def golden_sim() -> SimConfig:
    return SimConfig(max_episode_s=16.0, camera=CameraConfig(width_px=64, height_px=48))


def _clean(v):
    if isinstance(v, float):
        return None if math.isnan(v) else round(v, 9)
    return v


def golden_rows(scenes, seeds, methods, keys) -> list[dict]:
    out = []
    with __import__("tempfile").TemporaryDirectory() as tmp:
        specs = resolve_methods(list(methods), Path(tmp))
        for scene in scenes:
            for seed in seeds:
                for spec in specs:
                    job = Job(spec, golden_sim(), scene, 0.1, seed, Path(tmp), save_trace=False)
                    row = run_episode(job)
                    out.append({"method": spec.name, "scene": scene, "seed": seed,
                                **{k: _clean(row[k]) for k in keys}})
    return out


def golden_artifacts(tmp: Path) -> tuple[Path, list[Path]]:
    """One tiny MCAP episode and the parquet data files exported from two of them (the test fixtures' world; one
    file per episode)."""
    from recorder.drive import drive_episode
    from recorder.export import export_run
    from recorder.mcap.writer import EpisodeWriter
    from tests.conftest import TINY_SEEDS, tiny_sim_config

    raw = tmp / "raw"
    raw.mkdir()
    for k, seed in enumerate(TINY_SEEDS):
        ep = drive_episode(tiny_sim_config(), seed)
        with EpisodeWriter(raw / f"ep_{k:03d}.mcap", ep.meta, ep.occupancy) as w:
            for fr in ep.frames:
                w.add(fr)
    out = tmp / "dataset"
    export_run(raw, out, "icrowdnav/golden", progress=False)
    parquets = sorted(out.glob("data/*/*.parquet"))
    assert len(parquets) == len(TINY_SEEDS), parquets
    return raw / "ep_000.mcap", parquets
