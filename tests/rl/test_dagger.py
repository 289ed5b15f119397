"""rl.dagger's frame pool: the cached DAgger episodes concatenated once, in memory or memory-mapped."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.config import load_config
from pipeline.core.errors import ConfigError, InputMissingError
from rl.dagger import feature_files, load_features, pool_frames
from rl.stage import TrainConfig


def _episode(path: Path, n: int, seed: int, **extra: np.ndarray) -> dict[str, np.ndarray]:
    """One cached-features episode of ``n`` frames shaped like the students' (float16 ``s_bev``, int action)."""
    g = np.random.default_rng(seed)
    arrays = {"action": g.integers(0, 105, n), "bev": g.standard_normal((n, 4, 6, 5)).astype(np.float16),
              "state": g.standard_normal((n, 7)).astype(np.float32),
              "teacher_logits": g.standard_normal((n, 105)).astype(np.float32), **extra}
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **arrays)
    return arrays


def test_pool_in_memory_and_memory_mapped_equals_the_concatenation(tmp_path):
    """Both pools hold exactly np.concatenate of the episodes in file order; the memory-mapped one leaves no file
    behind in its scratch directory (unlinked at once) and is a memmap."""
    eps = [_episode(tmp_path / "iter_0" / "features" / f"e{i}.npz", n, i) for i, n in enumerate((5, 9, 3))]
    (tmp_path / "iter_0" / "features" / "half.tmp.npz").write_bytes(b"a killed writer's leftover")  # skipped
    files = feature_files([tmp_path / "iter_0"])
    assert [f.name for f in files] == ["e0.npz", "e1.npz", "e2.npz"]
    want = {k: np.concatenate([e[k] for e in eps]) for k in eps[0]}
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    for pool in (pool_frames(files), pool_frames(files, memory_gb=1e-9, scratch=scratch),
                 load_features([tmp_path / "iter_0"], memory_gb=1e-9, scratch=scratch)):
        assert set(pool) == set(want)
        for k, v in want.items():
            assert pool[k].dtype == v.dtype and np.array_equal(pool[k], v)
    mapped = pool_frames(files, ("bev", "action"), memory_gb=1e-9, scratch=scratch)
    assert set(mapped) == {"bev", "action"} and isinstance(mapped["bev"], np.memmap)
    assert not isinstance(pool_frames(files, ("bev",), memory_gb=1.0)["bev"], np.memmap)  # under the limit
    assert os.listdir(scratch) == []


def test_pool_keeps_the_keys_every_episode_has(tmp_path):
    """An episode without ``teacher_logits`` (recorded with soft_tau 0) drops that key from the default pool — the
    student then clones the argmax labels — and asking for it by name is one error naming the file."""
    a = tmp_path / "features" / "a.npz"
    b = tmp_path / "features" / "b.npz"
    _episode(a, 4, 0)
    ep = _episode(b, 2, 1)
    np.savez(b, **{k: v for k, v in ep.items() if k != "teacher_logits"})
    pool = pool_frames([a, b])
    assert "teacher_logits" not in pool and len(pool["action"]) == 6
    with pytest.raises(InputMissingError, match=r"b\.npz.*teacher_logits"):
        pool_frames([a, b], ("action", "teacher_logits"))


def test_damaged_or_mismatched_episode_is_one_named_error(tmp_path):
    a = tmp_path / "features" / "a.npz"
    _episode(a, 4, 0)
    bad = tmp_path / "features" / "bad.npz"
    bad.write_bytes(b"not a zip archive")
    with pytest.raises(InputMissingError, match=r"bad\.npz: unreadable cached features"):
        pool_frames([a, bad])
    other = tmp_path / "features" / "other.npz"
    _episode(other, 3, 1, bev=np.zeros((3, 4, 6, 6), np.float16))  # another grid
    with pytest.raises(InputMissingError, match=r"other\.npz: cached features: bev: expected 3 frames of shape"):
        pool_frames([a, other])
    with pytest.raises(InputMissingError, match="no DAgger features"):
        load_features([tmp_path / "empty"])


@pytest.mark.parametrize("value", [0.0, -1.0, math.nan])
def test_pool_memory_limit_must_be_positive(value):
    with pytest.raises(ConfigError, match="pool_memory_gb"):
        load_config(TrainConfig, "train", "smoke", {"dagger.pool_memory_gb": str(value)})
