"""Batched subprocess vectorised env for stable-baselines3: several envs per worker process, stepped together.

SB3's ``SubprocVecEnv`` runs one env per process and talks to each over its own pipe every step; with 8 envs on 2
cores that is 8 processes competing for the cores and 8 pipe round-trips per step. :class:`BatchedSubprocVecEnv`
runs ``n_workers`` processes (default: the usable cores), each holding a contiguous block of the envs; a step is one
pipe round-trip per worker (its block's actions in, its block's stacked observations, rewards, dones and infos out).
Inside a worker each env auto-resets on its own when its episode ends, with SB3's conventions (``terminal_observation``
and ``TimeLimit.truncated`` in the info, the reset info in ``reset_infos``).

It follows ``SubprocVecEnv``'s protocol (commands over a ``multiprocessing`` pipe, env factories sent through
``CloudpickleWrapper``) and gives, for the same seeds, the same observations, rewards, dones and infos as
``DummyVecEnv`` whatever the number of workers (env ``i`` is reset with ``seed + i``; tests/rl/test_vec_env.py).
Written here because SB3 has no vec env with several envs per process (its ``SubprocVecEnv`` / ``DummyVecEnv`` are
one per process / all in one). An exception in a worker is raised again in the caller, the worker keeps serving.

Example::

    venv = BatchedSubprocVecEnv([lambda: gym.make("CartPole-v1")] * 8, n_workers=2, start_method="fork")
    venv.seed(0)
    obs = venv.reset()          # n_envs x ...
    obs, rew, done, info = venv.step(actions)
    venv.close()
"""

from __future__ import annotations

import multiprocessing as mp
import os
import traceback
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.env_util import is_wrapped
from stable_baselines3.common.vec_env.base_vec_env import (
    CloudpickleWrapper,
    VecEnv,
    VecEnvIndices,
    VecEnvObs,
    VecEnvStepReturn,
)
from stable_baselines3.common.vec_env.util import dict_to_obs, obs_space_info


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask; ``os.cpu_count()`` where there is none)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def split_evenly(n_envs: int, n_workers: int) -> list[range]:
    """Contiguous blocks of env indices, one per worker, sizes differing by at most one (larger blocks first)."""
    base, extra = divmod(n_envs, n_workers)
    out, start = [], 0
    for w in range(n_workers):
        size = base + (w < extra)
        out.append(range(start, start + size))
        start += size
    return out


def _pick(obs: Any, key: Any) -> Any:
    """The part of one observation stored under ``key`` (``obs_space_info``'s keys: a Dict key, a Tuple index, or
    ``None`` for an unstructured space)."""
    return obs if key is None else obs[key]


def _stack(obs_list: Sequence[Any], keys: list[Any]) -> dict[Any, np.ndarray]:
    """Per key, the observations of a block of envs stacked on a new first axis (block x ...)."""
    return {k: np.stack([_pick(o, k) for o in obs_list]) for k in keys}


def _worker(remote, parent_remote, env_fns_wrapper: CloudpickleWrapper) -> None:
    """Serves one block of envs: ``(command, data)`` in, ``(ok, payload)`` out (``ok`` False: payload is the
    exception, or its traceback text when it does not pickle)."""
    parent_remote.close()
    envs: list[gym.Env] = []
    try:
        envs = [fn() for fn in env_fns_wrapper.var]
        keys, _, _ = obs_space_info(envs[0].observation_space)
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises it
        _reply_error(remote, exc)
        remote.close()
        return
    remote.send((True, None))
    while True:
        try:
            cmd, data = remote.recv()
        except (EOFError, KeyboardInterrupt):
            break
        if cmd == "close":
            for env in envs:
                env.close()
            remote.close()
            break
        try:
            remote.send((True, _serve(envs, keys, cmd, data)))
        except KeyboardInterrupt:
            break
        except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises it
            _reply_error(remote, exc)


def _reply_error(remote, exc: BaseException) -> None:
    text = "".join(traceback.format_exception(exc))
    try:
        remote.send((False, (exc, text)))
    except Exception:  # noqa: BLE001 - the exception itself does not pickle: send its text
        remote.send((False, (None, text)))


def _serve(envs: list[gym.Env], keys: list[Any], cmd: str, data: Any) -> Any:
    """One command on the worker's envs (``data`` indexes them locally: 0 .. block size - 1)."""
    if cmd == "step":
        obs_out, rews, dones, infos, reset_infos = [], [], [], [], []
        for env, action in zip(envs, data, strict=True):
            obs, rew, terminated, truncated, info = env.step(action)
            done = terminated or truncated
            info["TimeLimit.truncated"] = truncated and not terminated
            reset_info = None  # the env's reset info changes only when it resets
            if done:  # keep the final observation, then start this env's next episode (the others go on)
                info["terminal_observation"] = obs
                obs, reset_info = env.reset()
            obs_out.append(obs)
            rews.append(rew)
            dones.append(done)
            infos.append(info)
            reset_infos.append(reset_info)
        return _stack(obs_out, keys), rews, dones, infos, reset_infos
    if cmd == "reset":
        results = []
        for env, (seed, options) in zip(envs, data, strict=True):
            results.append(env.reset(seed=seed, **({"options": options} if options else {})))
        return _stack([o for o, _ in results], keys), [i for _, i in results]
    if cmd == "get_spaces":
        return envs[0].observation_space, envs[0].action_space
    if cmd == "env_method":
        idx, name, args, kwargs = data
        return [envs[i].get_wrapper_attr(name)(*args, **kwargs) for i in idx]
    if cmd == "get_attr":
        idx, name = data
        return [envs[i].get_wrapper_attr(name) for i in idx]
    if cmd == "has_attr":
        found = []
        for env in envs:
            try:
                env.get_wrapper_attr(data)
                found.append(True)
            except AttributeError:
                found.append(False)
        return all(found)
    if cmd == "set_attr":
        idx, name, value = data
        for i in idx:
            setattr(envs[i], name, value)
        return None
    if cmd == "is_wrapped":
        idx, wrapper_class = data
        return [is_wrapped(envs[i], wrapper_class) for i in idx]
    if cmd == "render":
        return [env.render() for env in envs]
    raise RuntimeError(f"BatchedSubprocVecEnv worker: unknown command {cmd!r} (a caller bug; the protocol is close, "
                       "step, reset, get_spaces, env_method, get_attr, has_attr, set_attr, is_wrapped, render)")


class BatchedSubprocVecEnv(VecEnv):
    """``n_envs`` envs in ``n_workers`` processes, each process stepping its block of envs together.

    Args:
        env_fns: one factory per env, returning a ``gymnasium.Env`` (called inside the worker that holds the env).
        n_workers: worker processes; ``None``: the usable cores (``os.sched_getaffinity``), at most ``n_envs``.
            Envs are split into contiguous blocks of sizes differing by at most one.
        start_method: ``multiprocessing`` start method; ``None``: SB3's default (forkserver where available, else
            spawn). ``"fork"`` starts fastest and needs no ``if __name__ == "__main__"`` guard, but must not be
            used after CUDA was initialised in the parent.
    """

    def __init__(self, env_fns: list[Callable[[], gym.Env]], n_workers: int | None = None,
                 start_method: str | None = None) -> None:
        n_envs = len(env_fns)
        if n_envs < 1:
            raise ValueError("BatchedSubprocVecEnv: expected at least one env factory")
        n_workers = min(n_envs, usable_cores()) if n_workers is None else n_workers
        if not 1 <= n_workers <= n_envs:
            raise ValueError(f"BatchedSubprocVecEnv: n_workers must be in [1, n_envs = {n_envs}], got {n_workers}")
        if start_method is None:
            start_method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
        ctx = mp.get_context(start_method)
        self.waiting = False
        self.closed = False
        self.blocks = split_evenly(n_envs, n_workers)
        # env index -> (worker, index in the worker's block)
        self._where = [(w, i) for w, block in enumerate(self.blocks) for i in range(len(block))]
        self.remotes, self.processes = [], []
        for block in self.blocks:
            remote, work_remote = ctx.Pipe()
            fns = CloudpickleWrapper([env_fns[i] for i in block])
            # daemon: a crashed parent does not leave workers behind
            process = ctx.Process(target=_worker, args=(work_remote, remote, fns), daemon=True)
            process.start()
            work_remote.close()
            self.remotes.append(remote)
            self.processes.append(process)
        try:
            for w in range(n_workers):  # every worker has built its envs (or says why not)
                self._recv(w)
            self.remotes[0].send(("get_spaces", None))
            observation_space, action_space = self._recv(0)
            super().__init__(n_envs, observation_space, action_space)  # reads the envs' render_mode (get_attr)
        except BaseException:
            self._terminate()
            raise
        self._keys, shapes, dtypes = obs_space_info(observation_space)
        # observations are cast to the space's dtypes, as DummyVecEnv does
        self._buf_obs = {k: np.zeros((n_envs, *shapes[k]), dtype=dtypes[k]) for k in self._keys}

    # ------------------------------------------------------------------------------------------- pipe helpers
    def _recv(self, w: int) -> Any:
        try:
            ok, payload = self.remotes[w].recv()
        except EOFError as exc:
            raise RuntimeError(f"BatchedSubprocVecEnv: worker {w} (envs {list(self.blocks[w])}) died "
                               f"(exit code {self.processes[w].exitcode})") from exc
        if ok:
            return payload
        exc, text = payload
        note = f"in BatchedSubprocVecEnv worker {w} (envs {list(self.blocks[w])}):\n{text}"
        if isinstance(exc, BaseException):
            exc.add_note(note)
            raise exc
        raise RuntimeError(note)

    def _recv_all(self, workers: Sequence[int]) -> list[Any]:
        """Replies of ``workers``, all read before the first error is raised (the pipes stay in step)."""
        out, error = [], None
        for w in workers:
            try:
                out.append(self._recv(w))
            except Exception as exc:  # noqa: BLE001 - raised below, once every reply is read
                error = error or exc
                out.append(None)
        if error is not None:
            raise error
        return out

    def _by_worker(self, indices: VecEnvIndices) -> dict[int, list[int]]:
        """The target envs grouped by worker: worker -> local indices, in the order of ``indices``."""
        out: dict[int, list[int]] = {}
        for i in self._get_indices(indices):
            w, local = self._where[i]
            out.setdefault(w, []).append(local)
        return out

    def _order(self, indices: VecEnvIndices, replies: dict[int, list[Any]]) -> list[Any]:
        """Per-env replies of grouped calls put back in the order of ``indices``."""
        taken = {w: iter(r) for w, r in replies.items()}
        return [next(taken[self._where[i][0]]) for i in self._get_indices(indices)]

    def _call(self, cmd: str, indices: VecEnvIndices, *args: Any) -> list[Any]:
        groups = self._by_worker(indices)
        for w, local in groups.items():
            self.remotes[w].send((cmd, (local, *args)))
        replies = dict(zip(groups, self._recv_all(list(groups)), strict=True))
        return self._order(indices, replies)

    def _write_obs(self, w: int, stacked: dict[Any, np.ndarray]) -> None:
        block = self.blocks[w]
        for k in self._keys:
            self._buf_obs[k][block.start:block.stop] = stacked[k]

    def _obs(self) -> VecEnvObs:
        return dict_to_obs(self.observation_space, {k: v.copy() for k, v in self._buf_obs.items()})

    # ----------------------------------------------------------------------------------------------- VecEnv API
    def step_async(self, actions: np.ndarray) -> None:
        for remote, block in zip(self.remotes, self.blocks, strict=True):
            remote.send(("step", actions[block.start:block.stop]))
        self.waiting = True

    def step_wait(self) -> VecEnvStepReturn:
        try:
            results = self._recv_all(range(len(self.remotes)))
        finally:
            self.waiting = False
        rews = np.zeros(self.num_envs, dtype=np.float32)
        dones = np.zeros(self.num_envs, dtype=bool)
        infos: list[dict[str, Any]] = []
        for w, (stacked, r, d, info, reset_info) in enumerate(results):
            block = self.blocks[w]
            self._write_obs(w, stacked)
            rews[block.start:block.stop] = r
            dones[block.start:block.stop] = d
            infos.extend(info)
            for i, ri in zip(block, reset_info, strict=True):
                if ri is not None:
                    self.reset_infos[i] = ri
        return self._obs(), rews, dones, infos

    def reset(self) -> VecEnvObs:
        for remote, block in zip(self.remotes, self.blocks, strict=True):
            remote.send(("reset", [(self._seeds[i], self._options[i]) for i in block]))
        results = self._recv_all(range(len(self.remotes)))
        self.reset_infos = []
        for w, (stacked, reset_info) in enumerate(results):
            self._write_obs(w, stacked)
            self.reset_infos.extend(reset_info)
        # seeds and options are used once
        self._reset_seeds()
        self._reset_options()
        return self._obs()

    def close(self) -> None:
        if self.closed:
            return
        if self.waiting:
            for remote in self.remotes:
                try:
                    remote.recv()
                except EOFError:
                    pass
        for remote in self.remotes:
            try:
                remote.send(("close", None))
            except (BrokenPipeError, OSError):
                pass
        for process in self.processes:
            process.join(timeout=30)
        self._terminate()
        self.closed = True

    def _terminate(self) -> None:
        """Kills workers that have not exited (after ``close``'s join, or a failed start) and closes the pipes."""
        for process in self.processes:
            if process.is_alive():
                process.terminate()
                process.join()
        for remote in self.remotes:
            remote.close()

    def get_images(self) -> Sequence[np.ndarray | None]:
        if self.render_mode != "rgb_array":
            warnings.warn(f"The render mode is {self.render_mode}, but this method assumes it is `rgb_array` to "
                          "obtain images.", stacklevel=2)
            return [None] * self.num_envs
        for remote in self.remotes:
            remote.send(("render", None))
        return [img for imgs in self._recv_all(range(len(self.remotes))) for img in imgs]

    def has_attr(self, attr_name: str) -> bool:
        for remote in self.remotes:
            remote.send(("has_attr", attr_name))
        return all(self._recv_all(range(len(self.remotes))))

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return self._call("get_attr", indices, attr_name)

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        groups = self._by_worker(indices)
        for w, local in groups.items():
            self.remotes[w].send(("set_attr", (local, attr_name, value)))
        self._recv_all(list(groups))

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs) -> list[Any]:
        return self._call("env_method", indices, method_name, method_args, method_kwargs)

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return self._call("is_wrapped", indices, wrapper_class)
