"""The benchmark's methods behind one driver interface.

A method is a :class:`MethodSpec` (name, label, what it observes, whether it is an upper reference, its checkpoint)
and makes a :class:`sim.episode.Driver` per episode process (``reset(obs, info)``, ``act(obs, info)``; optionally
``bev_panel()`` for videos)::

    driver = spec.driver()            # loads weights / builds the controller (once per process, cached)
    env = spec.wrap(env)              # what the method may know beyond its sensors (privileged world / observation)
    trace = run_episode(env, driver, seed, spec.name)

Built-in methods:

=========  ====================================================================  ============  ==========
name       what                                                                  observes      reference
=========  ====================================================================  ============  ==========
expert     the privileged sampling expert (:mod:`sim.expert`; true crowd + map)  privileged    yes
teacher    the privileged teacher policy (``checkpoints/policy/teacher``)        privileged    yes
full       iCrowdNav: BEV + I²Former student (``checkpoints/policy/full``)       RGB-D + poses no
no_i2      ablation w/o I²                                                       RGB-D         no
no_bev     ablation w/o BEV (occupancy CNN from depth)                           depth + poses no
dwa        Dynamic Window Approach on a depth costmap (:mod:`sim.planners.dwa`)  depth + odom  no
=========  ====================================================================  ============  ==========

Learned baselines (:mod:`rl.baselines`: ``drl_vo``, ``sarl_om``, ``vint``) are methods of kind ``baseline``
(checkpoints in ``checkpoints/policy/<name>``, drivers from their packages); other methods can be added with
:func:`register_method`. Waypoints (long-horizon runs, :class:`sim.wrappers.FollowWaypoints`): a learned policy
sees the waypoint instead of the goal in its robot state s; DWA heads for ``info["waypoint"]``; the expert plans on
the full map to the final goal and ignores it (it is a reference, not a competitor).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import gymnasium as gym
import torch

from pipeline.core import layout
from pipeline.core.errors import ConfigError, InputMissingError
from rl.baselines import BASELINES, baseline_module
from rl.driver import PolicyDriver
from rl.evaluate import checkpoint_env
from rl.policy import read_policy_json
from sim.episode import Driver
from sim.expert import ExpertDriver
from sim.planners.dwa import DWADriver
from sim.wrappers import with_privileges


@dataclass(frozen=True)
class MethodSpec:
    """One benchmark method."""

    name: str
    label: str
    kind: str  # expert | dwa | policy | baseline
    obs_mode: str  # the env's obs mode the driver needs: privileged | visual
    reference: bool = False  # an upper reference (privileged information), not a competitor
    checkpoint: Path | None = None  # policy checkpoint directory (kind == policy)
    action_type: str = "continuous"
    shield_s: float | None = None  # kind == policy: the obstacle shield instead of the saved one (rl.driver.PolicyDriver)
    sample_tau: float | None = None  # kind == policy: sample softmax(logits / τ) per step instead of the argmax
    encoder_precision: str | None = None  # kind == policy (students): the frozen encoder's precision, not the saved
    poses: bool = True  # visual: whether the driver reads the detected poses (False: the env skips its detector)

    def env_overrides(self) -> dict[str, Any]:
        return {"obs_mode": self.obs_mode, "action_type": self.action_type, "detect_poses": self.poses}

    def driver(self) -> Driver:
        return _DRIVER_FACTORIES[self.kind](self)

    def wrap(self, env: gym.Env) -> gym.Env:
        """``env`` with what this method may know beyond its sensors (:func:`sim.wrappers.with_privileges`; a
        privileged method keeps its privileged channels when the episode is rendered for a video or a log)."""
        return with_privileges(env, self.obs_mode)


class _Builtin(NamedTuple):
    label: str
    kind: str  # expert | policy | dwa
    obs_mode: str  # privileged | visual
    reference: bool  # an upper reference (privileged information), not a competitor
    poses: bool = True  # whether its driver reads detected poses (DWA: the depth images only)


_BUILTIN: dict[str, _Builtin] = {
    "expert": _Builtin("Privileged expert (reference)", "expert", "privileged", True),
    "teacher": _Builtin("Privileged teacher (reference)", "policy", "privileged", True),
    "full": _Builtin("iCrowdNav (full)", "policy", "visual", False),
    "no_i2": _Builtin("w/o I²", "policy", "visual", False),
    "no_bev": _Builtin("w/o BEV", "policy", "visual", False),
    "dwa": _Builtin("DWA", "dwa", "visual", False, poses=False),
}
_REGISTERED: dict[str, Callable[[Path], MethodSpec]] = {}
METHOD_NAMES = tuple(_BUILTIN)


def method_label(name: str) -> tuple[str, bool]:
    """The label of a method name and whether it is an upper reference, without its checkpoint (a built-in, a learned
    baseline; any other name is its own label, a competitor)."""
    if name in _BUILTIN:
        return _BUILTIN[name].label, _BUILTIN[name].reference
    if name in BASELINES:
        return BASELINES[name].label, False
    return name, False


def register_method(name: str, make_spec: Callable[[Path], MethodSpec], make_driver=None, kind: str | None = None):
    """Adds a method: ``make_spec(data_dir)`` returns its spec; ``make_driver(spec)`` (for a new ``kind``) its
    driver."""
    _REGISTERED[name] = make_spec
    if make_driver is not None and kind is not None:
        _DRIVER_FACTORIES[kind] = make_driver


def available_methods() -> list[str]:
    return [*METHOD_NAMES, *BASELINES, *_REGISTERED]


def _checkpoint(data_dir: Path, name: str) -> Path:
    ckpt = layout.policy_dir(data_dir, name)
    if not (ckpt / "policy.json").is_file() or not (ckpt / "manifest.json").is_file():
        raise InputMissingError(f"method {name!r}: no finished policy checkpoint in {ckpt} (run "
                                f"`icrowdnav train --variant {name}` or `make train`)")
    return ckpt


def spec_from_checkpoint(ckpt: Path, name: str | None = None) -> MethodSpec:
    """The spec of the policy or baseline saved in ``ckpt``, named ``name`` (default: the folder's name)."""
    desc = read_policy_json(Path(ckpt))
    name = name or Path(ckpt).name
    env = checkpoint_env(Path(ckpt))
    if desc["kind"] == "baseline":
        info = BASELINES[desc["variant"]]
        return MethodSpec(name, info.label, "baseline", env["obs_mode"], False, Path(ckpt), env["action_type"],
                          poses=info.poses)
    return MethodSpec(name, name, "policy", env["obs_mode"], checkpoint=Path(ckpt), action_type=env["action_type"])


def resolve_methods(names: list[str], data_dir: Path, shield_s: float | None = None,
                    sample_tau: float | None = None, encoder_precision: str | None = None) -> list[MethodSpec]:
    """Specs of ``names``; an unknown name is a ConfigError, a missing or unfinished checkpoint InputMissingError.
    ``shield_s``: every saved policy's (teacher, students) obstacle shield horizon instead of its own (None = as
    saved; :func:`rl.policy.load_policy`); ``sample_tau``: every saved policy samples softmax(logits / τ) instead of
    taking the argmax (None = argmax; :class:`rl.driver.PolicyDriver`); ``encoder_precision``: every student's
    frozen encoder at this precision (``fp32`` | ``int8``) instead of the one it was trained with (None = as saved)."""
    if not names:
        raise ConfigError("eval.methods: expected at least one method")
    out = []
    for name in names:
        if name in _REGISTERED:
            out.append(_REGISTERED[name](Path(data_dir)))
            continue
        if name in BASELINES:
            info = BASELINES[name]
            out.append(MethodSpec(name, info.label, "baseline", info.obs_mode, False, _checkpoint(data_dir, name),
                                  info.action_type, poses=info.poses))
            continue
        if name not in _BUILTIN:
            raise ConfigError(f"eval.methods: unknown method {name!r}; known: {available_methods()}")
        b = _BUILTIN[name]
        policy = b.kind == "policy"
        out.append(MethodSpec(name, b.label, b.kind, b.obs_mode, b.reference,
                              _checkpoint(data_dir, name) if policy else None, "discrete" if policy else "continuous",
                              shield_s if policy else None, sample_tau if policy else None,
                              encoder_precision if policy else None, b.poses))
    if len({m.name for m in out}) != len(out):
        raise ConfigError(f"eval.methods: duplicate names in {names}")
    return out


def baseline_driver(spec: MethodSpec) -> Driver:
    """The driver of a learned baseline (its package's ``Driver`` on the checkpoint)."""
    torch.set_num_threads(1)
    return baseline_module(read_policy_json(spec.checkpoint)["variant"]).Driver(spec.checkpoint)


_DRIVER_FACTORIES: dict[str, Callable[[MethodSpec], Driver]] = {
    "expert": lambda spec: ExpertDriver(),
    "dwa": lambda spec: DWADriver(),
    "policy": lambda spec: PolicyDriver(spec.checkpoint, spec.shield_s, spec.sample_tau, spec.encoder_precision),
    "baseline": baseline_driver,
}
