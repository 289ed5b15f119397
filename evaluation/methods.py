"""The benchmark's methods behind one driver interface.

A method is a :class:`MethodSpec` (name, label, what it observes, whether it is an upper reference, its checkpoint)
and makes a :class:`Driver` per episode process::

    driver = spec.driver()            # loads weights / builds the controller (once per process, cached)
    obs, _ = env.reset(seed=seed)     # env built with spec.env_overrides()
    driver.reset(env, obs)
    action = driver.act(env, obs, waypoint)   # waypoint: None (head for env.goal) or a world-frame point

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
(checkpoints in ``checkpoints/policy/<name>``, drivers from their modules); other methods can be added with
:func:`register_method`. Waypoints (long-horizon runs): a
learned policy sees the waypoint instead of the goal in its robot state s; DWA heads for it; the expert plans on the
full map to the final goal and ignores it (it is a reference, not a competitor).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from pipeline.core.errors import ConfigError, InputMissingError


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

    def env_overrides(self) -> dict[str, Any]:
        return {"obs_mode": self.obs_mode, "action_type": self.action_type}

    def driver(self) -> Driver:
        return _DRIVER_FACTORIES[self.kind](self)


_BUILTIN: dict[str, tuple[str, str, str, bool]] = {
    # name: (label, kind, obs_mode, reference)
    "expert": ("Privileged expert (reference)", "expert", "privileged", True),
    "teacher": ("Privileged teacher (reference)", "policy", "privileged", True),
    "full": ("iCrowdNav (full)", "policy", "visual", False),
    "no_i2": ("w/o I²", "policy", "visual", False),
    "no_bev": ("w/o BEV", "policy", "visual", False),
    "dwa": ("DWA", "dwa", "visual", False),
}
_REGISTERED: dict[str, Callable[[Path], MethodSpec]] = {}
METHOD_NAMES = tuple(_BUILTIN)


def register_method(name: str, make_spec: Callable[[Path], MethodSpec], make_driver=None, kind: str | None = None):
    """Adds a method: ``make_spec(data_dir)`` returns its spec; ``make_driver(spec)`` (for a new ``kind``) its
    driver."""
    _REGISTERED[name] = make_spec
    if make_driver is not None and kind is not None:
        _DRIVER_FACTORIES[kind] = make_driver


def available_methods() -> list[str]:
    from rl.baselines import BASELINES

    return [*METHOD_NAMES, *BASELINES, *_REGISTERED]


def _checkpoint(data_dir: Path, name: str) -> Path:
    ckpt = Path(data_dir) / "checkpoints" / "policy" / name
    if not (ckpt / "policy.json").is_file() or not (ckpt / "manifest.json").is_file():
        raise InputMissingError(f"method {name!r}: no finished policy checkpoint in {ckpt} (run "
                                f"`icrowdnav train --variant {name}` or `make train`)")
    return ckpt


def spec_from_checkpoint(ckpt: Path, name: str | None = None) -> MethodSpec:
    """The spec of the policy or baseline saved in ``ckpt`` (for ``train``'s acceptance run), named ``name``."""
    from rl.baselines import BASELINES
    from rl.policy import read_policy_json

    desc = read_policy_json(Path(ckpt))
    name = name or Path(ckpt).name
    if desc["kind"] == "baseline":
        info = BASELINES[desc["variant"]]
        return MethodSpec(name, info.label, "baseline", info.obs_mode, False, Path(ckpt), info.action_type)
    return MethodSpec(name, name, "policy", "visual" if desc["kind"] == "student" else "privileged",
                      checkpoint=Path(ckpt), action_type="discrete")


def resolve_methods(names: list[str], data_dir: Path) -> list[MethodSpec]:
    """Specs of ``names``; an unknown name is a ConfigError, a missing or unfinished checkpoint InputMissingError."""
    if not names:
        raise ConfigError("eval.methods: expected at least one method")
    from rl.baselines import BASELINES

    out = []
    for name in names:
        if name in _REGISTERED:
            out.append(_REGISTERED[name](Path(data_dir)))
            continue
        if name in BASELINES:
            info = BASELINES[name]
            out.append(MethodSpec(name, info.label, "baseline", info.obs_mode, False, _checkpoint(data_dir, name),
                                  info.action_type))
            continue
        if name not in _BUILTIN:
            raise ConfigError(f"eval.methods: unknown method {name!r}; known: {available_methods()}")
        label, kind, obs_mode, ref = _BUILTIN[name]
        ckpt = None
        if kind == "policy":
            ckpt = _checkpoint(data_dir, name)
        out.append(MethodSpec(name, label, kind, obs_mode, ref, ckpt,
                              "discrete" if kind == "policy" else "continuous"))
    if len({m.name for m in out}) != len(out):
        raise ConfigError(f"eval.methods: duplicate names in {names}")
    return out


def state_toward(env, target_xy: np.ndarray | None) -> np.ndarray:
    """The robot state s = [g_x, g_y, d_g, v_x, v_y] with ``target_xy`` in place of the goal (``env.goal`` if None)."""
    if target_xy is None:
        return env.robot_state()
    x, y, yaw = env.robot
    dx, dy = float(target_xy[0]) - x, float(target_xy[1]) - y
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([c * dx + s * dy, -s * dx + c * dy, math.hypot(dx, dy), env.robot_v[0], 0.0], np.float32)


class Driver(Protocol):
    """Drives one episode at a time (see the module docstring)."""

    def reset(self, env, obs: dict[str, np.ndarray]) -> None: ...

    def act(self, env, obs: dict[str, np.ndarray], waypoint: np.ndarray | None = None): ...

    def bev_panel(self) -> np.ndarray | None:
        """An ``H x W`` map of what the method's BEV input held at the last step (videos), or None."""


@dataclass
class ExpertDriver:
    expert: Any = field(default=None)

    def reset(self, env, obs):
        from sim.expert import PrivilegedExpert

        self.expert = PrivilegedExpert()
        self.expert.reset(env)

    def act(self, env, obs, waypoint=None):
        return env.encode_command(*self.expert.command(env))

    def bev_panel(self):
        return None


@dataclass
class DWADriver:
    dwa: Any = field(default=None)

    def reset(self, env, obs):
        from sim.planners.dwa import DWAController

        self.dwa = DWAController()
        self.dwa.reset(env)

    def act(self, env, obs, waypoint=None):
        depths = [obs[f"depth_{c.name}"] for c in env.cameras]
        return env.encode_command(*self.dwa.command(env, waypoint_xy=waypoint, depths=depths))

    def bev_panel(self):
        cm = self.dwa.last_costmap
        return None if cm is None else np.asarray(cm.occupied, np.float32)


class PolicyDriver:
    """A saved teacher (privileged observation) or student (rendered observation through the frozen encoder)."""

    def __init__(self, spec: MethodSpec) -> None:
        import torch

        from rl.dagger import _cached, _policy
        from rl.observe import load_student_encoder
        from rl.policy import read_policy_json

        torch.set_num_threads(1)
        self.policy = _policy(spec.checkpoint)
        self.desc = read_policy_json(spec.checkpoint)
        self.student = self.desc["kind"] == "student"
        self.encoder = None
        if self.student:
            d = self.desc
            self.encoder = _cached(f"enc:{d['variant']}:{d.get('encoder')}",
                                   lambda: load_student_encoder(d["variant"], d.get("encoder")))
        self.observer = None
        self.last_obs: dict[str, np.ndarray] | None = None

    def reset(self, env, obs):
        from rl.observe import observer_for_env

        if self.student:
            if self.observer is None:
                self.observer = observer_for_env(env, self.desc["variant"], self.encoder,
                                                 self.desc["net"].get("head", "mlp"))
            self.observer.reset()

    def act(self, env, obs, waypoint=None):
        from rl.observe import teacher_observation
        from rl.policy import act

        o = self.observer(obs) if self.student else teacher_observation(env, waypoint)
        o["state"] = state_toward(env, waypoint)
        self.last_obs = o
        return act(self.policy, o)

    def bev_panel(self):
        o = self.last_obs or {}
        if "bev" in o:
            return np.linalg.norm(o["bev"], axis=0)
        if "occ" in o:
            return o["occ"][0]
        return None


def baseline_driver(spec: MethodSpec) -> Driver:
    """The driver of a learned baseline (its module's ``Driver`` on the checkpoint)."""
    import torch

    from rl.baselines import baseline_module
    from rl.policy import read_policy_json

    torch.set_num_threads(1)
    return baseline_module(read_policy_json(spec.checkpoint)["variant"]).Driver(spec.checkpoint)


_DRIVER_FACTORIES: dict[str, Callable[[MethodSpec], Driver]] = {
    "expert": lambda spec: ExpertDriver(),
    "dwa": lambda spec: DWADriver(),
    "policy": PolicyDriver,
    "baseline": baseline_driver,
}
