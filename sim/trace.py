"""The record of one navigation episode: what metrics and figures consume.

Frames and units: world frame of the scene, metres, seconds, radians (yaw counter-clockwise from +x). Time index
``t = 0`` is the reset state; step ``t`` (``1 <= t <= T``) is the state reached after the ``t``-th control command
``robot_cmd[t - 1]``. Arrays indexed by state therefore have ``T + 1`` rows and arrays indexed by command ``T``.

The environment fills an :class:`EpisodeTrace` while it runs; :mod:`sim.metrics` and :mod:`sim.viz` only read it.
Traces round-trip losslessly through :meth:`EpisodeTrace.save_npz` / :meth:`EpisodeTrace.load_npz` (a compressed
``.npz`` without pickled objects).
"""

from __future__ import annotations

import math
import os
import zipfile
from dataclasses import dataclass, fields
from pathlib import Path
from typing import ClassVar

import numpy as np

from pipeline.core.artifacts import atomic_write_with

OUTCOMES: tuple[str, ...] = ("success", "collision_pedestrian", "collision_obstacle", "timeout")
"""Every value :attr:`EpisodeTrace.outcome` may take."""

_FORMAT_VERSION = 1


@dataclass
class EpisodeTrace:
    """One episode, from the reset state to the final state.

    ``T`` is the number of control steps and ``N`` the number of pedestrians (constant over the episode; ``N`` may
    be 0, ``T`` may be 0 for an episode that ended at reset).

    Attributes:
        dt_s: control period, s.
        robot_radius_m: radius of the robot's circular footprint, m.
        goal_radius_m: the robot's centre within this distance of ``goal_xy`` counts as reaching the goal, m.
        robot_pose: ``(T+1) x 3`` robot ``[x m, y m, yaw rad]`` per state.
        robot_cmd: ``T x 2`` commanded ``[v m/s, omega rad/s]`` per step.
        goal_xy: ``2`` goal position, m.
        start_xy: ``2`` start position, m.
        ped_xy: ``(T+1) x N x 2`` pedestrian body centres, m.
        ped_vel: ``(T+1) x N x 2`` pedestrian velocities, m/s.
        ped_radius: ``N`` pedestrian body-disc radii, m.
        ped_yaw: ``(T+1) x N`` pedestrian body yaw, rad.
        ped_head_yaw: ``(T+1) x N`` pedestrian head yaw (world frame, not relative to the body), rad.
        static_clearance_m: ``T+1`` distance from the robot centre to the nearest obstacle surface, m (negative
            inside an obstacle, ``inf`` in an empty scene).
        outcome: one of :data:`OUTCOMES`.
        shortest_path_m: geodesic start-to-goal length for SPL, m; ``nan`` when unknown.
        scene: scene name.
        density: crowd density setting (whatever unit the scene config uses, e.g. pedestrians per m^2).
        seed: episode seed.
        method: name of the navigation method that drove the robot.
    """

    dt_s: float
    robot_radius_m: float
    goal_radius_m: float
    robot_pose: np.ndarray
    robot_cmd: np.ndarray
    goal_xy: np.ndarray
    start_xy: np.ndarray
    ped_xy: np.ndarray
    ped_vel: np.ndarray
    ped_radius: np.ndarray
    ped_yaw: np.ndarray
    ped_head_yaw: np.ndarray
    static_clearance_m: np.ndarray
    outcome: str
    shortest_path_m: float = math.nan
    scene: str = ""
    density: float = 0.0
    seed: int = 0
    method: str = ""

    _ARRAYS: ClassVar[tuple[str, ...]] = (
        "robot_pose",
        "robot_cmd",
        "goal_xy",
        "start_xy",
        "ped_xy",
        "ped_vel",
        "ped_radius",
        "ped_yaw",
        "ped_head_yaw",
        "static_clearance_m",
    )
    _FLOATS: ClassVar[tuple[str, ...]] = (
        "dt_s",
        "robot_radius_m",
        "goal_radius_m",
        "shortest_path_m",
        "density",
    )
    _STRS: ClassVar[tuple[str, ...]] = ("outcome", "scene", "method")
    _INTS: ClassVar[tuple[str, ...]] = ("seed",)

    def __post_init__(self) -> None:
        for name in self._ARRAYS:
            setattr(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        # an empty crowd is often built as np.zeros((T+1, 0)); give it the documented shape
        t1 = self.robot_pose.shape[0] if self.robot_pose.ndim == 2 else 0
        if self.ped_xy.size == 0 and self.ped_xy.shape != (t1, 0, 2):
            self.ped_xy = np.zeros((t1, 0, 2))
        if self.ped_vel.size == 0 and self.ped_vel.shape != (t1, 0, 2):
            self.ped_vel = np.zeros((t1, 0, 2))
        for name in ("ped_yaw", "ped_head_yaw"):
            if getattr(self, name).size == 0:
                setattr(self, name, np.zeros((t1, 0)))
        if self.ped_radius.size == 0:
            self.ped_radius = np.zeros(0)
        if self.robot_cmd.size == 0:
            self.robot_cmd = np.zeros((0, 2))

    @property
    def n_steps(self) -> int:
        """``T``, the number of control steps (``len(robot_pose) - 1``)."""
        return int(self.robot_pose.shape[0]) - 1

    @property
    def n_peds(self) -> int:
        """``N``, the number of pedestrians."""
        return int(self.ped_radius.shape[0])

    @property
    def robot_xy(self) -> np.ndarray:
        """``(T+1) x 2`` robot positions, m (a view of ``robot_pose``)."""
        return self.robot_pose[:, :2]

    def validate(self) -> EpisodeTrace:
        """Check shapes, values and mutual consistency.

        Returns:
            ``self``, so that ``trace.validate()`` can be chained.

        Raises:
            ValueError: naming the first inconsistent field and what was expected.
        """
        if self.robot_pose.ndim != 2 or self.robot_pose.shape[1] != 3 or self.robot_pose.shape[0] < 1:
            raise ValueError(f"robot_pose must be (T+1) x 3 with T >= 0, got shape {self.robot_pose.shape}")
        t, n = self.n_steps, self.ped_radius.shape[0] if self.ped_radius.ndim == 1 else -1
        if n < 0:
            raise ValueError(f"ped_radius must be a 1-D array of N radii, got shape {self.ped_radius.shape}")
        expected: dict[str, tuple[int, ...]] = {
            "robot_cmd": (t, 2),
            "goal_xy": (2,),
            "start_xy": (2,),
            "ped_xy": (t + 1, n, 2),
            "ped_vel": (t + 1, n, 2),
            "ped_radius": (n,),
            "ped_yaw": (t + 1, n),
            "ped_head_yaw": (t + 1, n),
            "static_clearance_m": (t + 1,),
        }
        for name, shape in expected.items():
            got = getattr(self, name).shape
            if got != shape:
                raise ValueError(f"{name} must have shape {shape} (T={t}, N={n}), got {got}")
        for name in (a for a in self._ARRAYS if a != "static_clearance_m"):  # clearance may be +inf
            arr = getattr(self, name)
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} contains non-finite values")
        if np.any(np.isnan(self.static_clearance_m)):
            raise ValueError("static_clearance_m contains nan (use +inf for an empty scene)")
        if not (math.isfinite(self.dt_s) and self.dt_s > 0):
            raise ValueError(f"dt_s must be a positive finite period, got {self.dt_s}")
        if not (math.isfinite(self.robot_radius_m) and self.robot_radius_m > 0):
            raise ValueError(f"robot_radius_m must be positive, got {self.robot_radius_m}")
        if not (math.isfinite(self.goal_radius_m) and self.goal_radius_m >= 0):
            raise ValueError(f"goal_radius_m must be >= 0, got {self.goal_radius_m}")
        if np.any(self.ped_radius <= 0):
            raise ValueError(f"ped_radius must be positive, got min {self.ped_radius.min()}")
        if self.outcome not in OUTCOMES:
            raise ValueError(f"outcome must be one of {OUTCOMES}, got {self.outcome!r}")
        if not (math.isnan(self.shortest_path_m) or self.shortest_path_m >= 0):
            raise ValueError(f"shortest_path_m must be >= 0 or nan, got {self.shortest_path_m}")
        return self

    def save_npz(self, path: str | os.PathLike[str]) -> Path:
        """Validate and write the trace as a compressed ``.npz`` (atomically: temp file + rename).

        Args:
            path: destination file; written exactly there (no ``.npz`` suffix is appended). Parent folders are
                created.

        Returns:
            The destination path.
        """
        self.validate()
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        payload: dict[str, np.ndarray] = {"format_version": np.asarray(_FORMAT_VERSION)}
        for name in self._ARRAYS:
            payload[name] = getattr(self, name)
        for name in self._FLOATS:
            payload[name] = np.asarray(float(getattr(self, name)))
        for name in self._INTS:
            payload[name] = np.asarray(int(getattr(self, name)), dtype=np.int64)
        for name in self._STRS:
            payload[name] = np.asarray(str(getattr(self, name)))
        atomic_write_with(path, lambda fh: np.savez_compressed(fh, **payload))
        return path

    @classmethod
    def load_npz(cls, path: str | os.PathLike[str]) -> EpisodeTrace:
        """Read a trace written by :meth:`save_npz` and validate it.

        Args:
            path: the ``.npz`` file.

        Returns:
            The trace.

        Raises:
            ValueError: the file is missing, unreadable, not a trace, or fails :meth:`validate`; the message names
                the file.
        """
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as data:
                raw = {k: data[k] for k in data.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            raise ValueError(f"cannot read episode trace {path}: {exc}") from exc
        names = {f.name for f in fields(cls)}
        missing = sorted(names - raw.keys())
        if missing:
            raise ValueError(f"episode trace {path} lacks fields {missing}")
        version = int(raw.get("format_version", np.asarray(-1)))
        if version != _FORMAT_VERSION:
            raise ValueError(f"episode trace {path} has format_version {version}, expected {_FORMAT_VERSION}")
        kwargs: dict[str, object] = {}
        for name in cls._ARRAYS:
            kwargs[name] = raw[name]
        for name in cls._FLOATS:
            kwargs[name] = float(raw[name])
        for name in cls._INTS:
            kwargs[name] = int(raw[name])
        for name in cls._STRS:
            kwargs[name] = str(raw[name])
        try:
            return cls(**kwargs).validate()  # type: ignore[arg-type]
        except ValueError as exc:
            raise ValueError(f"invalid episode trace {path}: {exc}") from exc
