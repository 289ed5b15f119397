"""rl.vec_env.BatchedSubprocVecEnv against SB3's DummyVecEnv: the same seeds give the same episodes whatever the
number of workers; SB3's VecEnv conventions (auto-reset, terminal_observation, TimeLimit.truncated, env_method,
get_attr / set_attr, env_is_wrapped); close() leaves no child process; a worker's exception reaches the caller.

Privileged hallway envs (no rendering) with 1 s episodes: a reset every ~10 steps, by timeout or collision."""

import multiprocessing as mp

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.vec_env import DummyVecEnv

from rl.teacher import SceneMixEnv, make_vec_env
from rl.vec_env import BatchedSubprocVecEnv, split_evenly, usable_cores
from sim.env import SimConfig

SIM = SimConfig(max_episode_s=1.0)
PAIRS = [("hallway", 0.1), ("corner", 0.1)]
N_ENVS = 4


def _fns(n: int = N_ENVS):
    return [lambda: SceneMixEnv(SIM, PAIRS) for _ in range(n)]


def _rollout(venv, steps: int, seed: int = 3) -> list[tuple]:
    """(obs, rewards, dones, infos) of every step under seeded random actions (the reset's obs first)."""
    venv.seed(seed)
    out = [(venv.reset(), None, None, None)]
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        out.append(venv.step(rng.integers(0, venv.action_space.n, size=venv.num_envs)))
    return out


@pytest.fixture(scope="module")
def reference():
    venv = DummyVecEnv(_fns())
    try:
        return _rollout(venv, 300)
    finally:
        venv.close()


def test_split_evenly():
    assert split_evenly(8, 2) == [range(0, 4), range(4, 8)]
    assert split_evenly(5, 3) == [range(0, 2), range(2, 4), range(4, 5)]


@pytest.mark.parametrize("n_workers", [2, 3])
def test_same_episodes_as_dummy_vec_env(reference, n_workers):
    venv = BatchedSubprocVecEnv(_fns(), n_workers=n_workers, start_method="fork")
    try:
        got = _rollout(venv, 300)
    finally:
        venv.close()
    resets = truncations = 0
    for t, ((obs, rew, done, info), (obs_r, rew_r, done_r, info_r)) in enumerate(zip(got, reference, strict=True)):
        assert obs.keys() == obs_r.keys()
        for k in obs:
            assert obs[k].dtype == obs_r[k].dtype and np.array_equal(obs[k], obs_r[k]), (t, k)
        if t == 0:
            continue
        assert rew.dtype == rew_r.dtype and np.array_equal(rew, rew_r), t
        assert np.array_equal(done, done_r), t
        for i, (a, b) in enumerate(zip(info, info_r, strict=True)):
            assert a["TimeLimit.truncated"] == b["TimeLimit.truncated"]
            assert a["outcome"] == b["outcome"] and a["time_s"] == b["time_s"]
            assert ("terminal_observation" in a) == bool(done[i]) == ("terminal_observation" in b)
            if done[i]:
                resets += 1
                truncations += a["TimeLimit.truncated"]
                for k, v in a["terminal_observation"].items():
                    assert np.array_equal(v, b["terminal_observation"][k]), (t, i, k)
    assert resets > 20 and 0 < truncations < resets  # both timeouts and terminations were exercised


def test_env_method_get_set_attr_and_wrappers():
    venv = BatchedSubprocVecEnv(_fns(), start_method="fork")
    try:
        assert len(venv.remotes) == min(N_ENVS, usable_cores())  # the default: one worker per usable core
        venv.env_method("set_pool", [("corner", 0.2)], indices=[1, 3])
        assert venv.get_attr("pairs", indices=[3, 0, 1]) == [[("corner", 0.2)], PAIRS, [("corner", 0.2)]]
        venv.set_attr("pairs", [("doorway", 0.1)], indices=2)
        assert venv.get_attr("pairs") == [PAIRS, [("corner", 0.2)], [("doorway", 0.1)], [("corner", 0.2)]]
        assert venv.has_attr("set_pool") and not venv.has_attr("no_such_attribute")
        assert venv.env_is_wrapped(gym.Wrapper) == [False] * N_ENVS
        with pytest.raises(AttributeError, match="no_such_method"):
            venv.env_method("no_such_method", indices=[0, 3])
        venv.seed(0)
        assert venv.reset()["state"].shape == (N_ENVS, 5)  # the workers still serve after the error
    finally:
        venv.close()


def test_close_leaves_no_child_process():
    before = set(mp.active_children())
    venv = BatchedSubprocVecEnv(_fns(3), n_workers=3, start_method="fork")
    procs = list(venv.processes)
    venv.seed(0)
    venv.reset()
    venv.step_async(np.zeros(3, dtype=np.int64))  # closed while waiting for a step
    venv.close()
    venv.close()  # idempotent
    assert all(not p.is_alive() and p.exitcode == 0 for p in procs)
    assert set(mp.active_children()) <= before


def test_a_worker_that_cannot_build_its_env_is_reported():
    def broken():
        raise ValueError("no such scene: atlantis")

    with pytest.raises(ValueError, match="atlantis"):
        BatchedSubprocVecEnv([broken, broken], n_workers=2, start_method="fork")


def test_make_vec_env_uses_it_for_several_envs():
    venv = make_vec_env(SIM, PAIRS, 2, 0, subprocess=True)
    try:
        assert isinstance(venv, BatchedSubprocVecEnv)
    finally:
        venv.close()
    single = make_vec_env(SIM, PAIRS, 1, 0, subprocess=True)
    assert isinstance(single, DummyVecEnv)
    single.close()
