"""``icrowdnav/CrowdNav-v0``: the crowd-navigation gymnasium environment.

::

    import gymnasium, sim
    env = gymnasium.make("icrowdnav/CrowdNav-v0", scene="office_lobby", density=0.1)
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())

``reset`` options: ``start`` and ``goal`` (world xy, m) fix the pair instead of drawing it; ``scene_seed`` (int)
draws the layout's clutter, start and goal from that seed and only the crowd and sensing noise from ``seed`` (the
benchmark's goals × trials: every trial of a goal has the same start, goal and clutter, another crowd).

Observations (``obs_mode``):

* ``visual`` (the paper's policy input): ``rgb_left``/``rgb_right`` (H x W x 3 uint8), ``depth_left``/
  ``depth_right`` (H x W float32, z-depth in m, 0 = invalid), ``poses`` (6 x 17 x 3 float32, detected COCO-17
  joints in the robot frame, m), ``pose_mask`` (6 x 17 uint8) — both only with ``detect_poses`` (the default) —,
  ``state`` and ``odom``;
* ``state``: ``state`` and ``odom`` only (no rendering; the fastest mode);
* ``privileged`` (for the teacher): ``state``, ``odom``, ``peds`` (K x 6: x, y, vx, vy in the robot frame,
  radius, present — nearest first), ``scan`` (a range scan of the static map, m) and ``subgoal`` (the point
  ``subgoal_lookahead_m`` ahead on the global shortest path to the goal, robot frame, m: what a global planner on
  the map knows about the route) and ``path`` (``path_points`` points every ``path_spacing_m`` along that path,
  robot frame, m: the local shape of the route).

``state`` is the paper's s = [g_x, g_y, d_g, v_x, v_y]: the goal in the robot frame (m), its distance (m) and
the robot's velocity in the robot frame (m/s). ``odom`` is the robot pose [x, y, yaw] in the world frame.

Actions (``action_type``): ``continuous`` — Box([-1, 1]²) mapped to v = (a₀ + 1)/2 · v_max and ω = a₁ · ω_max;
``discrete`` — an index into the 5 × 21 grid of :func:`sim.robot.action_grid`. :meth:`CrowdNavEnv.encode_command`
turns a physical (v, ω) into either.

``info`` carries each reward term, ``d_o`` (distance from the robot centre to the nearest pedestrian or
obstacle surface), ``d_goal``, ``outcome``, ``command`` (the executed [v, ω]), ``odom`` (the robot pose
[x, y, yaw], world frame, float64; ``obs["odom"]`` is its float32 copy) and ``privileged`` (the true pedestrian
states, yaws and, at ``info_level="full"``, 3D keypoints and a range scan of the static map; for recording — a
driver must not read it). ``reset`` adds what stays fixed for the episode: ``occupancy`` (the static grid),
``cameras`` (the camera specs: intrinsics, extrinsics), ``action_codec`` (:class:`sim.robot.ActionCodec`),
``goal_xy`` (world frame) and ``config`` (this env's :class:`SimConfig`: control period, sensor layout). Drivers (:mod:`sim.episode`) act on ``obs`` and ``info`` only; the privileged world and
waypoints come from wrappers (:mod:`sim.wrappers`). The episode ends on
reaching the goal, on a collision (terminated) or at the time limit (truncated): :attr:`CrowdNavEnv.time_limit_s`
= max(``max_episode_s``, ``timeout_s_per_m`` × the shortest start-goal path), so a longer route gets more time. ``render()`` returns a
top-down RGB image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from pipeline.core.errors import ConfigError
from sim.cameras import CameraSpec, pose_matrix
from sim.crowd import Crowd, CrowdConfig, norm2d
from sim.detector import CameraFrame, DetectorConfig, OracleDetector, PoseDetector
from sim.geometry import world_to_robot
from sim.humans import Bodies, BodyConfig
from sim.planners.global_path import GlobalPath
from sim.reward import RewardConfig, reward_terms
from sim.robot import ActionCodec, RobotConfig, unicycle_step
from sim.scenario import ScenarioSpec, load_scenario
from sim.scene import SceneLayout, SceneSpec, load_scene
from sim.trace import EpisodeTrace

CAMERA_NAMES = ("left", "right")


@dataclass
class CameraConfig:
    """The two RGB-D cameras (RealSense D435-like), mounted symmetrically and yawed ±``yaw_deg``."""

    width_px: int = 160  # image width (640 in the paper profile)
    height_px: int = 120  # image height (480 in the paper profile)
    hfov_deg: float = 70.0  # horizontal field of view of each camera (D435 colour: 69°; 70° closes the seam)
    yaw_deg: float = 35.0  # left camera at +yaw, right at −yaw (≈ 140° combined)
    pitch_deg: float = 0.0  # positive looks down
    mount_height_m: float = 0.8  # optical centres above the floor
    mount_forward_m: float = 0.1  # ahead of the robot centre
    mount_lateral_m: float = 0.03  # left camera at +y, right at −y
    min_depth_m: float = 0.3  # valid depth range (0 outside)
    max_depth_m: float = 10.0

    def validate(self) -> None:
        if not (16 <= self.width_px <= 4096 and 16 <= self.height_px <= 4096):
            raise ConfigError(f"camera resolution: expected width and height in [16, 4096] px, got "
                              f"{self.width_px}x{self.height_px}")
        if not 10.0 <= self.hfov_deg <= 170.0:
            raise ConfigError(f"camera.hfov_deg: expected 10..170, got {self.hfov_deg}")
        if not 0 < self.min_depth_m < self.max_depth_m:
            raise ConfigError(f"camera depth range: expected 0 < min < max, got [{self.min_depth_m}, "
                              f"{self.max_depth_m}] m")

    def specs(self) -> tuple[CameraSpec, CameraSpec]:
        """The left and right :class:`CameraSpec`."""
        return tuple(  # type: ignore[return-value]
            CameraSpec(name, self.width_px, self.height_px, self.hfov_deg, sgn * self.yaw_deg, self.pitch_deg,
                       (self.mount_forward_m, sgn * self.mount_lateral_m, self.mount_height_m),
                       min_depth_m=self.min_depth_m, max_depth_m=self.max_depth_m, far_m=self.max_depth_m + 2.0)
            for name, sgn in (("left", 1.0), ("right", -1.0))
        )


@dataclass
class SimConfig:
    """Everything that defines an episode of the crowd world (units in the names)."""

    scene: str = "office_lobby"  # shipped scene name or path to a scene YAML file
    scenario: str = ""  # a scenario name or file (sim.scenario): its scene, start, goal and scripted pedestrians
    #                     replace `scene` and the drawn pair; `density` still adds a random crowd
    scenario_cues: bool = True  # False: the scripted pedestrians walk the same, but their head and torso do not lead
    #                             (the scenario's no-cue twin: what the cue alone changes, evaluation.stage)
    density: float = 0.1  # pedestrians per m² of free area (the paper: 0.1 low, 0.2 high)
    dt_s: float = 0.1  # control period
    substeps: int = 1  # social-force integration steps per control step
    max_episode_s: float = 40.0  # timeout: the episode's time limit is max(this, timeout_s_per_m x path length)
    timeout_s_per_m: float = 0.0  # ... the shortest start-goal path (m) times this: a route twice as long gets
    #                               twice the time (0: the limit is max_episode_s alone; the benchmark uses 5)
    goal_radius_m: float = 0.3  # success when the robot centre is this close to the goal (paper: ρ_robot)
    obs_mode: Literal["visual", "state", "privileged"] = "visual"  # what observations hold (module doc)
    detect_poses: bool = True  # visual: run the pose detector (poses, pose_mask); False: neither key and no detector
    #                            (for drivers that read only the images: DWA, ViNT-style; ≈ 0.8 ms of a step saved)
    action_type: Literal["continuous", "discrete"] = "continuous"  # Box([-1, 1]²) or the 5 × 21 grid
    privileged_peds: int = 10  # pedestrians in the privileged observation
    scan_rays: int = 72  # rays of the static-map range scan (360°)
    subgoal_lookahead_m: float = 2.0  # privileged sub-goal: this far along the global path (sim.planners.global_path)
    path_points: int = 12  # privileged path: this many points along the global path ...
    path_spacing_m: float = 0.25  # ... this far apart (the first one this far from the robot's closest path point)
    scan_range_m: float = 10.0  # range of the scan
    spawn_clearance_m: float = 1.0  # no pedestrian spawns closer than this to the robot's start or goal
    info_level: Literal["full", "basic"] = "full"  # basic: info without keypoints and scan (fast RL)
    robot: RobotConfig = field(default_factory=RobotConfig)
    crowd: CrowdConfig = field(default_factory=CrowdConfig)
    body: BodyConfig = field(default_factory=BodyConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)

    def validate(self) -> None:
        if self.scenario:
            load_scenario(self.scenario)  # unknown scenario / malformed file -> ConfigError naming it
        else:
            load_scene(self.scene)  # unknown scene / malformed file -> ConfigError naming it
        if not isinstance(self.density, int | float) or not math.isfinite(self.density) or self.density < 0:
            raise ConfigError(f"density: expected a number >= 0 (pedestrians per m²), got {self.density!r}")
        if self.density > 2.0:
            raise ConfigError(f"density: expected <= 2.0 ped/m² (denser crowds cannot be placed), got {self.density}")
        if not math.isfinite(self.timeout_s_per_m) or not 0 <= self.timeout_s_per_m <= 1000:
            raise ConfigError(f"timeout_s_per_m: expected a number in [0, 1000] s/m, got {self.timeout_s_per_m!r}")
        for k, hi in (("dt_s", 10.0), ("max_episode_s", 86_400.0)):  # NaN passes every comparison: check first
            v = getattr(self, k)
            if not isinstance(v, int | float) or not math.isfinite(v) or not 0 < v <= hi:
                raise ConfigError(f"{k}: expected a finite number in (0, {hi:g}] s, got {v!r}")
        if self.dt_s <= 0 or self.substeps < 1 or self.max_episode_s <= self.dt_s:
            raise ConfigError(f"timing: expected dt_s > 0, substeps >= 1 and max_episode_s > dt_s, got "
                              f"{self.dt_s}, {self.substeps}, {self.max_episode_s}")
        if self.info_level not in ("full", "basic"):
            raise ConfigError(f"info_level: expected full or basic, got {self.info_level!r}")
        if self.obs_mode not in ("visual", "state", "privileged"):
            raise ConfigError(f"obs_mode: expected visual, state or privileged, got {self.obs_mode!r}")
        if self.action_type not in ("continuous", "discrete"):
            raise ConfigError(f"action_type: expected continuous or discrete, got {self.action_type!r}")
        if (self.goal_radius_m <= 0 or self.scan_rays < 4 or self.privileged_peds < 1 or self.subgoal_lookahead_m <= 0
                or self.path_points < 1 or self.path_spacing_m <= 0):
            raise ConfigError("goal_radius_m must be > 0, scan_rays >= 4, privileged_peds >= 1, "
                              "subgoal_lookahead_m > 0, path_points >= 1 and path_spacing_m > 0")
        for sub in (self.robot, self.camera, self.detector, self.crowd, self.body):
            sub.validate()


class CrowdNavEnv(gym.Env):
    """The crowd world as a gymnasium env (see the module docstring for spaces and semantics).

    Args:
        scene: scene name or YAML path (overrides ``config.scene``).
        density: pedestrians per m² (overrides ``config.density``).
        config: the full :class:`SimConfig`; other keyword arguments override its top-level fields.
        render_mode: ``"rgb_array"`` for top-down images from :meth:`render`.
        detector: a :class:`sim.detector.PoseDetector`; the oracle by default.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, scene: str | None = None, density: float | None = None, config: SimConfig | None = None,
                 render_mode: str | None = None, detector: PoseDetector | None = None, **overrides: Any):
        super().__init__()
        cfg = config or SimConfig()
        if scene is not None:
            overrides["scene"] = scene
        if density is not None:
            overrides["density"] = density
        bad = set(overrides) - set(SimConfig.__dataclass_fields__)
        if bad:
            raise ConfigError(f"CrowdNavEnv: unknown option {sorted(bad)[0]!r}; options: "
                              f"{sorted(SimConfig.__dataclass_fields__)}")
        cfg = replace(cfg, **overrides)
        cfg.validate()
        if render_mode not in (None, "rgb_array"):
            raise ConfigError(f"render_mode: expected None or 'rgb_array', got {render_mode!r}")
        self.cfg = cfg
        self.render_mode = render_mode
        self.scenario: ScenarioSpec | None = load_scenario(cfg.scenario) if cfg.scenario else None
        self.spec_scene: SceneSpec = self.scenario.scene if self.scenario else load_scene(cfg.scene)
        self.cameras = cfg.camera.specs()
        self.detector: PoseDetector = detector or OracleDetector(cfg.detector)
        self.codec = ActionCodec(cfg.action_type, cfg.robot)
        self._grid = self.codec.grid
        self._renderer = None
        self._topdown = None
        self.observation_space = self._make_obs_space()
        if cfg.action_type == "discrete":
            self.action_space = spaces.Discrete(len(self._grid))
        else:
            self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.layout: SceneLayout | None = None
        self.last_detections = None  # the pose detector's latest output (visual obs with detect_poses; recorder)

    # ------------------------------------------------------------------------------------------------ spaces
    def _make_obs_space(self) -> spaces.Dict:
        c = self.cfg
        big = np.float32(1e4)
        d: dict[str, spaces.Space] = {
            "state": spaces.Box(-big, big, (5,), np.float32),
            "odom": spaces.Box(-big, big, (3,), np.float32),
        }
        if c.obs_mode == "visual":
            h, w = c.camera.height_px, c.camera.width_px
            k = c.detector.max_people
            for name in CAMERA_NAMES:
                d[f"rgb_{name}"] = spaces.Box(0, 255, (h, w, 3), np.uint8)
                d[f"depth_{name}"] = spaces.Box(0.0, np.float32(c.camera.max_depth_m), (h, w), np.float32)
            if c.detect_poses:
                d["poses"] = spaces.Box(-big, big, (k, 17, 3), np.float32)
                d["pose_mask"] = spaces.Box(0, 1, (k, 17), np.uint8)
        elif c.obs_mode == "privileged":
            d["peds"] = spaces.Box(-big, big, (c.privileged_peds, 6), np.float32)
            d["scan"] = spaces.Box(0.0, np.float32(c.scan_range_m), (c.scan_rays,), np.float32)
            d["subgoal"] = spaces.Box(-big, big, (2,), np.float32)
            d["path"] = spaces.Box(-big, big, (c.path_points, 2), np.float32)
        return spaces.Dict(d)

    # ------------------------------------------------------------------------------------------------- reset
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        c = self.cfg
        ep_seed = int(self.np_random.integers(2**63 - 1))
        ss = np.random.SeedSequence(ep_seed)
        r_layout, r_sg, r_crowd, r_body, r_det = (np.random.default_rng(s) for s in ss.spawn(5))
        self.episode_seed = ep_seed
        self.reset_seed = seed
        if options and options.get("scene_seed") is not None:  # the benchmark's goal: layout, start and goal from
            # the goal's seed, the crowd (and sensing) from the episode's, so trials of one goal differ only in people
            r_layout, r_sg = (np.random.default_rng(s) for s in
                              np.random.SeedSequence(int(options["scene_seed"])).spawn(2))
        self.layout = self.spec_scene.layout(r_layout)
        sc = self.scenario
        if sc is not None:  # a staged situation: its pair and heading
            start, goal, geo = np.array(sc.start, float), np.array(sc.goal, float), math.nan
        elif options and "start" in options and "goal" in options:  # a given pair (long-horizon runs on a map)
            start = np.asarray(options["start"], float).reshape(2)
            goal = np.asarray(options["goal"], float).reshape(2)
            geo = math.nan
        else:
            start, goal, geo = self.layout.sample_start_goal(r_sg, c.robot.radius_m, exact_length=False)
        self.start, self.goal = start, goal
        self._shortest = geo if math.isfinite(geo) else None  # exact length, computed on first use if not known
        to_goal = math.atan2(goal[1] - start[1], goal[0] - start[0])
        if sc is not None:  # trials of a scenario differ in the robot's heading and the scripted walkers' speeds
            yaw = sc.start_yaw + (r_sg.uniform(-sc.yaw_jitter, sc.yaw_jitter) if sc.yaw_jitter else 0.0)
        else:
            yaw = to_goal + r_sg.uniform(-0.5, 0.5)
        self.robot = np.array([start[0], start[1], yaw])
        self.robot_v = np.zeros(2)  # [v, omega] last command
        n = self.layout.ped_count(c.density)
        scripted = () if sc is None else tuple(
            replace(p, speed_mps=p.speed_mps * (1 + r_sg.uniform(-sc.speed_jitter, sc.speed_jitter)),
                    cue=p.cue and c.scenario_cues)
            for p in sc.pedestrians)
        self.bodies = Bodies(c.body, r_body, n + len(scripted), np.zeros(n + len(scripted)))
        self.crowd = Crowd(self.layout, c.crowd, r_crowd, n, self.bodies.radius, avoid_xy=[start, goal],
                           avoid_m=c.spawn_clearance_m + c.robot.radius_m, scripted=scripted)
        self.bodies.body_yaw[:] = self.crowd.initial_yaw()
        self.bodies.torso_yaw[:] = self.bodies.body_yaw
        self.bodies.head_yaw[:] = self.bodies.body_yaw
        self.det_rng = r_det
        self.t = 0
        self._global_path = None  # built on the first privileged_subgoal() of the episode
        self.d_goal = float(np.hypot(*(goal - start)))
        self._skel = None
        if c.obs_mode == "visual":
            self._build_renderer()
        self._trace_init()
        self.d_o, self.d_static = self._clearance()
        obs = self._obs()
        info = self._info(None, None)
        info["occupancy"] = {"grid": self.layout.occupancy.copy(), "origin_xy": self.layout.grid_origin,
                             "resolution_m": 0.05}
        info["episode_seed"] = ep_seed
        info["cameras"] = self.cameras
        info["action_codec"] = self.codec
        info["goal_xy"] = self.goal.copy()
        info["config"] = self.cfg
        return obs, info

    @property
    def shortest_path_m(self) -> float:
        """Length of the any-angle shortest path from start to goal (m), computed on first use."""
        if self._shortest is None:
            self._shortest = self.layout.path_length(self.start, self.goal, self.cfg.robot.radius_m)
        return self._shortest

    @property
    def time_limit_s(self) -> float:
        """This episode's time limit (s): max(``max_episode_s``, ``timeout_s_per_m`` × :attr:`shortest_path_m`)."""
        c = self.cfg
        if c.timeout_s_per_m <= 0:
            return c.max_episode_s
        length = self.shortest_path_m
        return max(c.max_episode_s, c.timeout_s_per_m * length) if math.isfinite(length) else c.max_episode_s

    def _build_renderer(self) -> None:
        from sim.renderer import WorldRenderer  # lazy: pybullet (and its stderr banner) only when rendering

        if self._renderer is None:
            self._renderer = WorldRenderer()
        _, _, half = self.bodies.primitives(self.crowd.pos)
        self._renderer.build(self.layout.obstacles, self.spec_scene.bounds, self.spec_scene.floor_color, half,
                             self.bodies.colors)

    # -------------------------------------------------------------------------------------------------- step
    def decode_action(self, action) -> tuple[float, float]:
        """Physical (v m/s, ω rad/s) of an action of this env's action space (clipped to the limits)."""
        return self.codec.decode(action)

    def encode_command(self, v: float, omega: float):
        """The action of this env's action space closest to the physical command (v, ω)."""
        return self.codec.encode(v, omega)

    def step(self, action):
        if self.layout is None:
            raise RuntimeError("call reset() before step()")
        c = self.cfg
        v, w = self.decode_action(action)
        x, y, yaw = unicycle_step(*self.robot, v, w, c.dt_s)
        self.robot = np.array([x, y, yaw])
        self.robot_v = np.array([v, w])
        sub = c.dt_s / c.substeps
        prev = self.crowd.pos.copy()
        for _ in range(c.substeps):
            self.crowd.step(sub, self.robot[:2], c.robot.radius_m)
        walked = norm2d(self.crowd.pos - prev)
        self.bodies.update(c.dt_s, self.crowd.pos, self.crowd.vel, self.crowd.attention_xy(), walked)
        self._skel = None
        self.t += 1
        d_prev = self.d_goal
        self.d_goal = float(np.hypot(self.goal[0] - x, self.goal[1] - y))
        self.d_o, self.d_static = self._clearance()
        terms = reward_terms(c.reward, self.d_goal, d_prev, self.d_o, w, c.robot.radius_m, c.goal_radius_m)
        outcome = None
        if terms["success"] > 0:
            outcome = "success"
        elif terms["collision"] < 0:
            outcome = "collision_obstacle" if self.d_static <= c.robot.radius_m else "collision_pedestrian"
        terminated = outcome is not None
        elapsed = self.t * c.dt_s  # the path length is measured only once the floor max_episode_s is reached
        truncated = (not terminated and elapsed >= c.max_episode_s - 1e-9 and elapsed >= self.time_limit_s - 1e-9)
        if truncated:
            outcome = "timeout"
        self._outcome = outcome
        self._trace_append(v, w)
        obs = self._obs()
        info = self._info(terms, outcome)
        return obs, float(terms["total"]), terminated, truncated, info

    def _clearance(self) -> tuple[float, float]:
        """(d_o, d_static): robot centre to the nearest pedestrian-or-obstacle surface, and to obstacles only."""
        p = self.robot[:2]
        d_static = float(self.layout.clearance_fast(p)[0])
        if d_static < 1.0:  # near obstacles: exact geometry (the grid is only used as a far-field shortcut)
            d_static = float(self.layout.geometry.signed_distance(p)[0])
        if self.crowd.n:
            d_ped = float(np.min(np.hypot(*(self.crowd.pos - p).T) - self.crowd.radius))
        else:
            d_ped = math.inf
        return min(d_static, d_ped), d_static

    # --------------------------------------------------------------------------------------------- observing
    def skeleton(self) -> dict[str, np.ndarray]:
        if self._skel is None:
            self._skel = self.bodies.skeleton(self.crowd.pos)
        return self._skel

    def keypoints_world(self) -> np.ndarray:
        """``N x 17 x 3`` true COCO keypoints of every pedestrian, world frame, m."""
        return self.bodies.keypoints(self.crowd.pos, self.skeleton())

    def robot_state(self, target: np.ndarray | None = None) -> np.ndarray:
        """The paper's s = [g_x, g_y, d_g, v_x, v_y] (goal and velocity in the robot frame); with ``target`` (a
        world-frame point, e.g. a waypoint) in place of the goal."""
        tx, ty = (self.goal if target is None else np.asarray(target, np.float64).reshape(2))
        dx, dy = float(tx) - self.robot[0], float(ty) - self.robot[1]
        g = world_to_robot(np.array([tx, ty], np.float64), self.robot)
        return np.array([g[0], g[1], math.hypot(dx, dy), self.robot_v[0], 0.0], dtype=np.float32)

    def camera_poses(self) -> list[np.ndarray]:
        """World-from-camera 4 x 4 transforms of the left and right cameras."""
        T = pose_matrix(*self.robot)
        return [T @ spec.T_base_cam for spec in self.cameras]

    def render_cameras(self, segmentation: bool = False) -> list[tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
        """(rgb, depth, seg) of the left and right cameras for the current state."""
        if self._renderer is None:
            self._build_renderer()
        centers, quats, _ = self.bodies.primitives(self.crowd.pos, self.skeleton())
        self._renderer.set_humans(centers, quats)
        return [self._renderer.render(spec, T, segmentation) for spec, T in zip(self.cameras, self.camera_poses(),
                                                                                strict=True)]

    def _obs(self) -> dict[str, np.ndarray]:
        c = self.cfg
        obs = {"state": self.robot_state(), "odom": self.robot.astype(np.float32)}
        if c.obs_mode == "visual":
            frames = []
            for spec, T, (rgb, depth, _) in zip(self.cameras, self.camera_poses(), self.render_cameras(), strict=True):
                obs[f"rgb_{spec.name}"] = rgb
                obs[f"depth_{spec.name}"] = depth
                frames.append(CameraFrame(spec, T, spec.T_base_cam, rgb, depth))
            if c.detect_poses:
                det = self.detector.detect(frames, {"keypoints_world": self.keypoints_world()}, self.det_rng)
                self.last_detections = det
                obs["poses"] = det.poses.astype(np.float32)
                obs["pose_mask"] = det.joint_mask.astype(np.uint8)
        elif c.obs_mode == "privileged":
            obs["peds"] = self.privileged_peds()
            obs["scan"] = self.static_scan().astype(np.float32)
            obs["subgoal"] = self.privileged_subgoal()
            obs["path"] = self.privileged_path()
        return obs

    def privileged_peds(self) -> np.ndarray:
        """``K x 6`` nearest pedestrians [x, y, vx, vy, radius, present] in the robot frame (zero-padded)."""
        k = self.cfg.privileged_peds
        out = np.zeros((k, 6), np.float32)
        if self.crowd.n == 0:
            return out
        x, y, yaw = self.robot
        c, s = math.cos(yaw), math.sin(yaw)
        rel = self.crowd.pos - self.robot[:2]
        order = np.argsort(np.hypot(*rel.T), kind="stable")[:k]
        r = rel[order]
        v = self.crowd.vel[order]
        m = len(order)
        out[:m, 0] = c * r[:, 0] + s * r[:, 1]
        out[:m, 1] = -s * r[:, 0] + c * r[:, 1]
        out[:m, 2] = c * v[:, 0] + s * v[:, 1]
        out[:m, 3] = -s * v[:, 0] + c * v[:, 1]
        out[:m, 4] = self.crowd.radius[order]
        out[:m, 5] = 1.0
        return out

    def privileged_subgoal(self, target: np.ndarray | None = None) -> np.ndarray:
        """The point ``subgoal_lookahead_m`` ahead on the global shortest path to ``target`` (default: the goal) on
        the static map, in the robot frame (m)."""
        if self._global_path is None:
            self._global_path = GlobalPath(self.cfg.subgoal_lookahead_m)
            self._global_path.reset(self)
        p = self._global_path.subgoal(self, target)
        return world_to_robot(np.asarray(p[:2]), self.robot).astype(np.float32)

    def privileged_path(self, target: np.ndarray | None = None) -> np.ndarray:
        """``path_points x 2``: points every ``path_spacing_m`` along the global shortest path to ``target``
        (default: the goal), robot frame (m) — the local shape of the route (what the expert's cost-to-go field
        encodes)."""
        self.privileged_subgoal(target)  # plans the path if needed
        d = self.cfg.path_spacing_m * np.arange(1, self.cfg.path_points + 1)
        p = self._global_path.ahead(self, d, target)
        return world_to_robot(p, self.robot).astype(np.float32)

    def static_scan(self) -> np.ndarray:
        """Range scan of the static map from the robot centre, rays evenly over 360° from the robot heading."""
        n = self.cfg.scan_rays
        ang = self.robot[2] + np.arange(n) * (2 * np.pi / n)
        return self.layout.geometry.raycast(self.robot[:2], ang, self.cfg.scan_range_m)

    def _info(self, terms: dict | None, outcome: str | None) -> dict[str, Any]:
        info: dict[str, Any] = {
            "d_o": self.d_o, "d_goal": self.d_goal, "time_s": self.t * self.cfg.dt_s, "outcome": outcome,
            "reward_terms": terms or {},
            "command": self.robot_v.copy(), "odom": self.robot.copy(),
        }
        info["privileged"] = {
            "robot_pose": self.robot.copy(), "goal_xy": self.goal.copy(),
            "ped_pos": self.crowd.pos.copy(), "ped_vel": self.crowd.vel.copy(), "ped_radius": self.crowd.radius.copy(),
            "ped_body_yaw": self.bodies.body_yaw.copy(), "ped_torso_yaw": self.bodies.torso_yaw.copy(),
            "ped_head_yaw": self.bodies.head_yaw.copy(), "ped_goal": self.crowd.goal.copy(),
            "ped_intent_xy": self.crowd.attention_xy(), "ped_lead_s": np.maximum(self.crowd.lead, 0.0),
        }
        if self.cfg.info_level == "full":
            info["privileged"]["keypoints_world"] = self.keypoints_world()
            info["privileged"]["static_scan"] = self.static_scan()
        return info

    # -------------------------------------------------------------------------------------------------- trace
    def _trace_init(self) -> None:
        self._tr = {"pose": [self.robot.copy()], "cmd": [], "ped_xy": [self.crowd.pos.copy()],
                    "ped_vel": [self.crowd.vel.copy()], "ped_yaw": [self.bodies.body_yaw.copy()],
                    "ped_head": [self.bodies.head_yaw.copy()],
                    "static": [float(self.layout.geometry.signed_distance(self.robot[:2])[0])]}
        self._outcome = None

    def _trace_append(self, v: float, w: float) -> None:
        tr = self._tr
        tr["pose"].append(self.robot.copy())
        tr["cmd"].append((v, w))
        tr["ped_xy"].append(self.crowd.pos.copy())
        tr["ped_vel"].append(self.crowd.vel.copy())
        tr["ped_yaw"].append(self.bodies.body_yaw.copy())
        tr["ped_head"].append(self.bodies.head_yaw.copy())
        tr["static"].append(self.d_static)

    def trace(self, method: str = "") -> EpisodeTrace:
        """The episode so far as an :class:`sim.trace.EpisodeTrace` (for metrics and figures)."""
        tr = self._tr
        n = self.crowd.n
        t1 = len(tr["pose"])
        return EpisodeTrace(
            dt_s=self.cfg.dt_s, robot_radius_m=self.cfg.robot.radius_m, goal_radius_m=self.cfg.goal_radius_m,
            robot_pose=np.array(tr["pose"]), robot_cmd=np.array(tr["cmd"]).reshape(-1, 2),
            goal_xy=self.goal.copy(), start_xy=self.start.copy(),
            ped_xy=np.array(tr["ped_xy"]).reshape(t1, n, 2), ped_vel=np.array(tr["ped_vel"]).reshape(t1, n, 2),
            ped_radius=self.crowd.radius.copy(), ped_yaw=np.array(tr["ped_yaw"]).reshape(t1, n),
            ped_head_yaw=np.array(tr["ped_head"]).reshape(t1, n), static_clearance_m=np.array(tr["static"]),
            outcome=self._outcome or "timeout", shortest_path_m=self.shortest_path_m, scene=self.spec_scene.name,
            density=float(self.cfg.density), seed=int(self.reset_seed if self.reset_seed is not None else self.episode_seed),
            method=method,
        )

    # ------------------------------------------------------------------------------------------------ render
    def render(self):
        if self.render_mode != "rgb_array" or self.layout is None:
            return None
        from sim.viz import TopDownRenderer  # lazy: matplotlib (~1 s) only for render()'s top-down image

        if self._topdown is None or self._topdown_layout is not self.layout:
            self._topdown = TopDownRenderer(self.layout.obstacles, self.spec_scene.bounds, px_per_m=40)
            self._topdown_layout = self.layout
        trail = np.array(self._tr["pose"])[:, :2]
        return self._topdown.draw(self.robot, self.crowd.pos, self.bodies.body_yaw, self.bodies.head_yaw,
                                  self.crowd.radius, self.goal, trail_xy=trail, robot_radius=self.cfg.robot.radius_m,
                                  camera_yaws_deg=(self.cfg.camera.yaw_deg, -self.cfg.camera.yaw_deg),
                                  camera_hfov_deg=self.cfg.camera.hfov_deg)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
