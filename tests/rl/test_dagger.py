"""rl.dagger's frame pool (the cached DAgger episodes concatenated once, in memory or memory-mapped), its timing
and the driver of its rollouts."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.core.config import load_config
from pipeline.core.errors import ConfigError, InputMissingError
from pipeline.core.timing import PhaseClock
from rl.dagger import (
    PHASES,
    _DaggerDriver,
    episode_phases,
    feature_files,
    iteration_timing,
    load_features,
    pool_frames,
    throughput_table,
)
from rl.driver import PolicyDriver, cached_policy, mlp_shield
from rl.stage import TrainConfig
from sim.env import CrowdNavEnv
from tests.rl.helpers_mlp import SIM, TARGET, save_mlp_student


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


def test_an_unknown_cloning_schedule_is_named():
    with pytest.raises(ConfigError, match=r"train\.dagger\.bc_schedule: expected one of \['pool', 'new'\], got 'both'"):
        load_config(TrainConfig, "train", "smoke", {"dagger.bc_schedule": "both"})


def test_an_episodes_phases_are_exclusive_and_account_for_its_wall():
    """The clock's ``env`` holds the render, the detector and the student's action (the steps it drove): each is
    counted once, and ``other`` is the wall no phase claims."""
    sums = {"env": 10.0, "render": 4.0, "detect": 1.0, "student": 0.5, "encode": 6.0, "perceive": 2.0,
            "teacher": 1.5, "record": 1.0, "save": 0.25}
    p = episode_phases(sums, total_s=24.0)
    assert tuple(p) == PHASES
    assert p["sim"] == 4.5 and p["render"] == 4.0 and p["student"] == 0.5 and p["encode"] == 6.0
    assert p["other"] == 24.0 - 10.0 - 6.0 - 2.0 - 1.5 - 1.0 - 0.25
    assert sum(p.values()) == pytest.approx(24.0)
    assert episode_phases({}, 1.0) == {**dict.fromkeys(PHASES, 0.0), "other": 1.0}  # no phase ran


def test_an_iterations_timing_and_its_table():
    """``done.json``'s ``timing``: the parts' walls, frames per second over the loop and over its rollouts, the
    episodes' phases summed over workers; a resumed iteration has no rates (part of its rollouts ran before), and
    episodes rolled out by code that did not time them are left out of the per-frame phases."""
    phase = dict.fromkeys(PHASES, 0.0) | {"render": 0.5, "encode": 1.5}
    rows = [{"frames": 100, "phase_s": phase}, {"frames": 100, "phase_s": phase}, {"frames": 50}]
    t = iteration_timing({"rollout": 20.0, "export": 5.0, "pool": 1.0, "clone": 14.0}, rows, 250, resumed=False)
    assert t["total_s"] == 40.0 and t["loop_frames_per_s"] == 6.25 and t["rollout_frames_per_s"] == 12.5
    assert t["seconds"]["intention_tune"] == 0.0 and t["timed_frames"] == 200
    assert t["worker_s"]["encode"] == 3.0 and t["worker_ms_per_frame"]["render"] == 5.0
    resumed = iteration_timing({"rollout": 2.0, "clone": 1.0}, rows, 250, resumed=True)
    assert "loop_frames_per_s" not in resumed and "rollout_frames_per_s" not in resumed
    its = [{"iteration": 0, "frames": 250, "aggregate_frames": 250, "timing": t},
           {"iteration": 1, "frames": 250, "aggregate_frames": 500, "timing": resumed},
           {"iteration": 2, "frames": 10, "aggregate_frames": 510}]  # an iteration of older code: no timing
    table = throughput_table(its)
    header, rule = table.splitlines()[:2]
    assert header.count("|") == rule.count("|") == 11  # 10 columns
    assert "| 0 | 250 (250) | 20 | 5 | 0 | 1 | 14 | 40 | 6.2 | 12.5 |" in table
    assert "| 1 | 250 (500) | 2 | 0 | 0 | 0 | 1 | 3 | — | — (resumed) |" in table
    assert "250 frames in 0.7 min: the loop 6.2 frames/s, its rollouts 12.5 frames/s (50% of the loop's wall)" in table
    # 400 timed frames: render 1.0 s and encode 3.0 s in each iteration -> 5.0 and 15.0 ms per frame, 25 % / 75 %
    assert "Rollout episodes, 400 frames" in table and "| 0.0 (0%) | 5.0 (25%) |" in table
    assert "| 15.0 (75%) |" in table and table.rstrip().endswith("| 20.0 |")
    assert throughput_table([its[2]]) == "no timed DAgger iteration"


def test_the_students_rollout_steps_are_its_shielded_actions(tmp_path):
    """``train.mlp_shield_s``: where a DAgger rollout executes the MLP-head student's action (probability 1 − β),
    that action is the one :class:`rl.driver.PolicyDriver` takes with the saved shield — the argmax of its logits
    less the shield's penalty on the perceived scan — so the rollouts visit the states the trained student will.
    Facing a wall all round at 0.6 m, a student whose argmax drives straight into it turns instead; without the
    shield it drives on; with β = 1 the teacher's label is executed either way."""
    env = CrowdNavEnv(config=SIM)
    obs, info = env.reset(seed=0)
    env.close()
    ckpt = save_mlp_student(tmp_path / "straight", info, straight_bias=100.0)
    deployed = PolicyDriver(ckpt, shield_s=0.6)
    deployed.reset(obs, info)
    deployed.act(obs, info)
    wall = {**deployed.last_obs, "scan": np.full(SIM.scan_rays, 0.6, np.float32)}
    deployed.observer = lambda _obs: dict(wall)
    policy, shield = cached_policy(ckpt), mlp_shield(SIM, 0.6)
    intruding = set(np.flatnonzero(shield(torch.as_tensor(wall["scan"])[None])[0].numpy() > 0).tolist())
    rollout = {}
    for name, beta, sh in (("plain", 0.0, None), ("shielded", 0.0, shield), ("teacher", 1.0, shield)):
        d = _DaggerDriver(policy, beta, np.random.default_rng(0), PhaseClock(), sh)
        d.label, d.s_obs = 3, wall
        rollout[name] = d.act(obs, info)
    assert TARGET in intruding and rollout["plain"] == TARGET
    assert rollout["shielded"] not in intruding and rollout["shielded"] == deployed.act(obs, info)
    assert rollout["teacher"] == 3 and mlp_shield(SIM, 0.0) is None


def test_held_out_episodes_keep_their_side_as_the_pool_grows(tmp_path):
    """The adaptive cloning budget's held-out episodes (``dagger.bc_holdout``) are chosen by a hash of their names:
    per frame in the pool's order, the same episodes whichever iterations are pooled, spread over scenes; a pool of
    two episodes still has one on each side."""
    from rl.dagger import held_out_episode, held_out_frames

    names = [f"{s}_d{x}_s{e}" for e in range(40) for s, x in [("hallway", 0.1), ("corner", 0.2)]]
    for k in range(2):
        for j, name in enumerate(names[k::2]):
            _episode(tmp_path / f"iter_{k}" / "features" / f"{name}.npz", 3 + j % 4, j)
    one = held_out_frames([tmp_path / "iter_0"], 0.25)
    both = held_out_frames([tmp_path / "iter_0", tmp_path / "iter_1"], 0.25)
    assert len(one) == len(load_features([tmp_path / "iter_0"])["action"]) and np.array_equal(both[:len(one)], one)
    chosen = {n for n in names if held_out_episode(n, 0.25)}
    assert 0 < len(chosen) < len(names) and {n.split("_")[0] for n in chosen} == {"hallway", "corner"}
    lengths = [len(np.load(f)["action"]) for f in feature_files([tmp_path / "iter_0", tmp_path / "iter_1"])]
    per_episode = np.add.reduceat(both, np.cumsum([0, *lengths[:-1]]))
    assert [bool(c) for c in per_episode] == [held_out_episode(f.stem, 0.25) for f in
                                               feature_files([tmp_path / "iter_0", tmp_path / "iter_1"])]
    small = tmp_path / "small"
    for j in range(2):
        _episode(small / "features" / f"hallway_d0.1_s{j}.npz", 4, j)
    for fraction in (1e-4, 0.9999):
        mask = held_out_frames([small], fraction)
        assert mask[:4].all() != mask[4:].all() and mask.sum() == 4


@pytest.mark.parametrize("over,field", [({"dagger.bc_max_epochs": "1", "dagger.bc_epochs": "2"}, "bc_max_epochs"),
                                        ({"dagger.bc_max_epochs": "4", "dagger.bc_holdout": "nan"}, "bc_holdout"),
                                        ({"dagger.bc_max_epochs": "4", "dagger.bc_patience": "0"}, "bc_patience"),
                                        ({"dagger.bc_max_epochs": "-1"}, "bc_max_epochs"),
                                        ({"dagger.bc_holdout_scope": "newest"}, "bc_holdout_scope")])
def test_a_wrong_adaptive_budget_is_named(over, field):
    with pytest.raises(ConfigError, match=rf"dagger.*{field}"):
        load_config(TrainConfig, "train", "smoke", over)
