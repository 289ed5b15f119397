"""The chunk-loading benchmark (recorder.bench): figures exist and the written datasets load with stock lerobot.

No timing assertions: the figures are reported by ``make bench``, not checked.
"""

from __future__ import annotations

import json
import math

import pytest

from recorder.bench import datasets_cache, measure_chunk_loading


@pytest.fixture(scope="module")
def chunk_bench(tmp_path_factory, tiny_dataset):
    work = tmp_path_factory.mktemp("chunkbench")
    return work, measure_chunk_loading(tiny_dataset.root, work, chunk=10, items=2, seed=0)


def test_figures_exist_and_are_finite_and_positive(chunk_bench, tiny_dataset):
    _, figures = chunk_bench
    for name in ("chunk_load_ms_ours", "chunk_load_ms_stock_shaped", "chunk_load_ms_policy_features",
                 "chunk_load_ratio", "chunk_load_ratio_policy_features", "row_numbers_ours",
                 "row_numbers_stock_shaped", "row_numbers_policy_features", "chunk_load_steps"):
        assert name in figures, name
        assert math.isfinite(figures[name]) and figures[name] > 0, (name, figures[name])
    assert figures["chunk_load_steps"] == 10
    assert figures["row_numbers_ours"] > figures["row_numbers_policy_features"] > figures["row_numbers_stock_shaped"]


def test_stock_shaped_dataset_loads_with_stock_lerobot_and_has_the_sources_length(chunk_bench, tiny_dataset):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    work, _ = chunk_bench
    src = json.loads((tiny_dataset.root / "meta" / "info.json").read_text())
    with datasets_cache(work / "hf_datasets_cache"):
        ds = LeRobotDataset("bench/stock_shaped", root=work / "stock_shaped", video_backend="pyav")
    assert ds.meta.total_frames == len(ds) == src["total_frames"]
    assert ds.meta.total_episodes == ds.num_episodes == src["total_episodes"]
    assert ds.fps == src["fps"]
    cams = {k: ft["shape"] for k, ft in src["features"].items() if ft["dtype"] == "video"}
    assert cams and {k: list(ft["shape"]) for k, ft in ds.meta.features.items() if ft["dtype"] == "video"} == cams
    item = ds[len(ds) - 1]
    for cam, (h, w, c) in cams.items():
        assert tuple(item[cam].shape) == (c, h, w)
    assert tuple(item["action"].shape) == (2,) and tuple(item["observation.state"].shape) == (5,)


def test_policy_features_variant_has_no_wide_features(chunk_bench, tiny_dataset):
    work, _ = chunk_bench
    src = json.loads((tiny_dataset.root / "meta" / "info.json").read_text())["features"]
    assert any(k.startswith(("observation.depth.", "privileged.")) for k in src)
    info = json.loads((work / "policy_features" / "meta" / "info.json").read_text())
    assert not [k for k in info["features"] if k.startswith(("observation.depth.", "privileged."))]
    assert "action" in info["features"] and any(ft["dtype"] == "video" for ft in info["features"].values())
