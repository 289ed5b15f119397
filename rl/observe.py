"""What the policies see: the student's observation from the rendered RGB-D frames, and the teacher's from privileged
state.

:class:`StudentObserver` turns a visual-mode observation of :class:`sim.env.CrowdNavEnv` into the student's
observation dict (keys per variant, :func:`rl.networks.variant_keys`):

=========  ===================  ====================================================================================
key        shape                meaning
=========  ===================  ====================================================================================
bev        C x X/2 x Y/2        ``s_bev`` of the frozen pretrained encoder (streaming: only the newest frame is
                                encoded, the cached history is warped), 2 x 2 average-pooled (the fixed first layer of
                                φ_bev, applied here so DAgger caches 4x less)
occ        1 x X/2 x Y/2        local occupancy from depth (the "w/o BEV" ablation): 1 where a measured depth point
                                above the floor (the encoder grid's z band) falls in the cell, on the same grid
poses      K x 17 x 3           detected 3D joints, robot frame (the env's detector)
pose_mask  K x 17               1 = detected joint
state      5                    s = [g_x, g_y, d_g, v_x, v_y]
peds       P x 6                ``head="lookahead"``, variants with poses: pedestrian tracks from the detected poses
                                ([x, y, vx, vy, r, present], robot frame; :mod:`rl.perceive`)
scan       R                    ``head="lookahead"``: nearest depth obstacle per bearing bin over 360° (with memory)
bev_occ    4 x X/2 x Y/2        ``head="lookahead"`` with ``map_cost``, variants with ``bev``: the pretrained pretext
                                heads' occupancy probabilities (static, people now, +0.5 s, +1.0 s; 2 x 2 max-pooled),
                                sampled along the lookahead arcs (``no_bev`` reads its ``occ`` there instead)
=========  ===================  ====================================================================================

With ``mirror=True`` a ``bev`` variant's observer also returns ``bev_mirror``: ``s_bev`` of the *mirrored* world
(reflected about the robot's x axis), from a second stream that encodes the left-right flipped images with the
cameras swapped and the reflected odometry. The rig is symmetric (cameras at ±y, yawed ±35°, principal point at the
image centre), so this is the map the robot would see in the mirrored world — the exact input for mirror
augmentation while cloning (:func:`rl.teacher.mirror_batch`). The encoder's latent is not mirror-equivariant, so
flipping ``s_bev`` itself would not be. Costs one more encoder pass per step (batched with the first).

The frozen encoder runs on the device it is on (:func:`load_student_encoder` ``device``, ``train.device`` in DAgger
rollouts and PPO fine-tuning); the frames go there each step and the observation comes back as numpy arrays.

The privileged teacher's observation of a visual-mode env (its DAgger labels) comes from the env side:
:class:`sim.wrappers.PrivilegedObservation`.
"""

from __future__ import annotations

from contextlib import nullcontext
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
import torch.nn.functional as F

from pipeline.core.errors import ConfigError
from pipeline.core.timing import PhaseClock
from pretrain.checkpoint import load_heads
from pretrain.geometry import Camera, LiftGeometry, lift_splat, sample_depth
from pretrain.intention import IntentionForecaster, load_forecaster
from pretrain.model import TARGETS, BEVEncoder, BEVStream, EncoderConfig, PretextHeads
from pretrain.quantize import load_frozen_encoder
from rl.networks import variant_keys
from rl.perceive import CameraView, Perception

BEV_POOL = 2  # s_bev is average-pooled by this before caching / φ_bev
OCC_STRIDE_PX = 2  # depth pixels lifted for the occupancy map (every 2nd row and column)


def env_cameras(env) -> list[Camera]:
    """The encoder-side :class:`pretrain.geometry.Camera` list of an (unwrapped) env, left then right."""
    return cameras_of(env.cameras)


def cameras_of(specs) -> list[Camera]:
    """The encoder-side :class:`pretrain.geometry.Camera` list of camera specs (``info["cameras"]`` at reset)."""
    return [Camera.from_dict(spec.to_dict(), f"env camera {spec.name}") for spec in specs]


def check_encoder_matches(encoder: BEVEncoder, cameras: list[Camera], where: str) -> None:
    """The encoder must have been trained for exactly these cameras (sizes, intrinsics, mounting)."""
    mine = [c.to_dict() for c in encoder.cameras]
    theirs = [c.to_dict() for c in cameras]
    if len(mine) != len(theirs):
        raise ConfigError(f"{where}: encoder expects {len(mine)} cameras, the env has {len(theirs)}")
    for a, b in zip(mine, theirs, strict=True):
        for key in ("name", "width", "height"):
            if a[key] != b[key]:
                raise ConfigError(f"{where}: encoder/camera mismatch: the encoder was trained for camera "
                                  f"{a['name']} {key}={a[key]!r}, the env has {b[key]!r} (train with the "
                                  "recording's camera settings, or re-run pretrain)")
        for key in ("K", "T_base_cam"):
            if not np.allclose(np.asarray(a[key]), np.asarray(b[key]), atol=1e-6):
                raise ConfigError(f"{where}: encoder/camera mismatch: camera {a['name']} {key} differs from the "
                                  "encoder's (train with the recording's camera settings, or re-run pretrain)")


class StudentObserver:
    """Visual observations → the student's observation dict (module docstring). One stream (one env).

    Args:
        variant: the student variant (decides the keys).
        cameras: the env's cameras (:func:`env_cameras`).
        encoder: the frozen pretrained encoder (required unless the variant is ``no_bev``).
        max_people: ``K`` of the detector.
        mirror: also return ``bev_mirror`` (module docstring); only for variants with ``bev``.
        head: the policy's actor head (``lookahead`` adds ``peds`` and ``scan``; ``mlp_intention`` replaces the
            poses by ``peds`` and ``peds_future``).
        perception: ``{"dt_s", "k", "rays", "range_m"}`` of the lookahead head's :class:`rl.perceive.Perception`
            (:func:`perception_params` of the env), optionally ``"unseen_s"`` (the policy's ``net.track_unseen_s``).
        forecaster: the pretrained intention model; with the lookahead head and a variant with poses it predicts
            the tracks (``peds_future``) instead of constant velocity; the ``mlp_intention`` head needs it.
        map_cost: the lookahead head reads an occupancy map along its arcs (``bev_occ`` for variants with ``bev``).
        map_heads: the encoder checkpoint's pretext heads (:func:`load_student_heads`), which make ``bev_occ``.
    """

    def __init__(self, variant: str, cameras: list[Camera], encoder: BEVEncoder | None, max_people: int,
                 mirror: bool = False, head: str = "mlp", perception: dict[str, Any] | None = None,
                 forecaster: IntentionForecaster | None = None, map_cost: bool = False,
                 map_heads: PretextHeads | None = None) -> None:
        self.variant = variant
        self.keys = variant_keys(variant, head, map_cost)
        self.cameras = cameras
        self.perception = None
        if "scan" in self.keys or "peds" in self.keys:  # the lookahead head; the mlp_intention head's tracks
            if perception is None:
                raise ConfigError(f"the {head} head's observer needs the perception parameters of the env")
            if "peds_future" in self.keys and forecaster is None:
                raise ConfigError(f"the {head} head of variant {variant!r} needs the pretrained intention model "
                                  "(train.intention: its forecasts are the I²Former's input)")
            self.perception = Perception([CameraView.of(c) for c in cameras], perception["dt_s"], perception["k"],
                                         perception["rays"], perception["range_m"], people="peds" in self.keys,
                                         forecaster=forecaster, unseen_s=perception.get("unseen_s", 0.0),
                                         scan="scan" in self.keys)
        # where the frames are encoded (and the occupancy map lifted): the encoder's device
        self.device = next(encoder.parameters()).device if encoder is not None else torch.device("cpu")
        if "bev" in self.keys:
            if encoder is None:
                raise ConfigError(f"variant {variant!r} needs the pretrained encoder")
            check_encoder_matches(encoder, cameras, "student observer")
            self.encoder = encoder
            self.stream = BEVStream(encoder)
            self.grid = encoder.grid
        else:
            self.encoder = None
            self.stream = None
            self.grid = (encoder.grid if encoder is not None else EncoderConfig().grid)
        if "occ" in self.keys:
            self.occ_geom = LiftGeometry(cameras, OCC_STRIDE_PX)
        self.map_heads = None
        if "bev_occ" in self.keys:
            if map_heads is None:
                raise ConfigError(f"variant {variant!r} with map_cost needs the encoder checkpoint's pretext heads")
            self.map_heads = map_heads.to(self.device).eval()
        self.max_people = max_people
        self.mirror = bool(mirror) and "bev" in self.keys
        if self.mirror:
            check_mirror_symmetric(cameras)
        self._first = True
        self.observation_space = self._space()
        # where the observation's time goes, when someone asks (rl.dagger's rollouts): "encode" (the frozen encoder
        # or the depth occupancy, with the map heads) and "perceive" (tracks, forecasts, depth scan)
        self.clock: PhaseClock | None = None

    def _phase(self, name: str):
        return self.clock(name) if self.clock is not None else nullcontext()

    def _pooled_shape(self) -> tuple[int, int]:
        nx, ny = self.grid.shape
        return nx // BEV_POOL, ny // BEV_POOL

    def _space(self) -> gym.spaces.Dict:
        big = np.float32(1e4)
        px, py = self._pooled_shape()
        d: dict[str, gym.spaces.Space] = {"state": gym.spaces.Box(-big, big, (5,), np.float32)}
        if "bev" in self.keys:
            d["bev"] = gym.spaces.Box(-big, big, (self.encoder.cfg.bev_channels, px, py), np.float32)
        if "occ" in self.keys:
            d["occ"] = gym.spaces.Box(0.0, 1.0, (1, px, py), np.float32)
        if "bev_occ" in self.keys:
            d["bev_occ"] = gym.spaces.Box(0.0, 1.0, (len(TARGETS), px, py), np.float32)
        if "poses" in self.keys:
            d["poses"] = gym.spaces.Box(-big, big, (self.max_people, 17, 3), np.float32)
            d["pose_mask"] = gym.spaces.Box(0.0, 1.0, (self.max_people, 17), np.float32)
        if self.perception is not None:
            if self.perception.scan is not None:
                d["scan"] = gym.spaces.Box(0.0, big, (self.perception.scan.rays,), np.float32)
            if self.perception.people:
                d["peds"] = gym.spaces.Box(-big, big, (self.perception.k, 6), np.float32)
            if self.perception.forecaster is not None:
                d["peds_future"] = gym.spaces.Box(-big, big, (self.perception.k, len(self.perception.times), 2),
                                                  np.float32)
        return gym.spaces.Dict(d)

    def reset(self) -> None:
        """The next observation starts a new episode (its history is that frame repeated)."""
        self._first = True
        if self.perception is not None:
            self.perception.reset()

    @torch.no_grad()
    def __call__(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {"state": np.asarray(obs["state"], np.float32)}
        if "bev" in self.keys or "occ" in self.keys:
            with self._phase("encode"):
                self._encode(obs, out)
        if "poses" in self.keys:
            out["poses"] = np.asarray(obs["poses"], np.float32)
            out["pose_mask"] = np.asarray(obs["pose_mask"], np.float32)
        if self.perception is not None:
            with self._phase("perceive"):
                out.update(self.perception(obs))
        self._first = False
        return out

    def _encode(self, obs: dict[str, np.ndarray], out: dict[str, np.ndarray]) -> None:
        """The frozen encoder's ``bev`` (+ ``bev_mirror``, ``bev_occ``) or the depth occupancy ``occ``, into ``out``."""
        names = [c.name for c in self.cameras]
        dev = self.device
        depth = torch.from_numpy(np.stack([obs[f"depth_{n}"] for n in names])).unsqueeze(0).to(dev)  # 1 N H W
        if "bev" in self.keys:
            rgb = torch.from_numpy(np.stack([obs[f"rgb_{n}"] for n in names])).permute(0, 3, 1, 2).unsqueeze(0).to(dev)
            pose = torch.as_tensor(np.asarray(obs["odom"], np.float64)).unsqueeze(0).to(dev)
            first = None if not self._first else torch.ones(1, dtype=torch.bool, device=dev)
            if self._first:
                self.stream.reset()
            if self.mirror:  # stream 1: the mirrored world (flipped images, cameras swapped, reflected odometry)
                rgb = torch.cat([rgb, torch.flip(rgb, [1, 4])])
                depth_in = torch.cat([depth, torch.flip(depth, [1, 3])])
                pose = torch.cat([pose, pose * pose.new_tensor([1.0, -1.0, -1.0])])
                first = None if first is None else first.expand(2)
            else:
                depth_in = depth
            full = self.stream.step(rgb, depth_in, pose, first)
            s_bev = F.avg_pool2d(full, BEV_POOL).cpu().numpy()
            out["bev"] = s_bev[0]
            if self.mirror:
                out["bev_mirror"] = s_bev[1]
            if self.map_heads is not None:  # occupancy probabilities of the real world (mirroring flips them in y)
                occ = torch.sigmoid(self.map_heads(full[:1]))
                out["bev_occ"] = F.max_pool2d(occ, BEV_POOL)[0].cpu().numpy()
        if "occ" in self.keys:
            out["occ"] = self.occupancy(depth)[0].cpu().numpy()

    def occupancy(self, depth: torch.Tensor) -> torch.Tensor:
        """``B x N x H x W`` depth → ``B x 1 x X/2 x Y/2`` occupancy (1 = a depth point above the floor)."""
        d = sample_depth(depth.float(), OCC_STRIDE_PX)
        ones = d.new_ones(d.shape[0], d.shape[1], 1, *d.shape[2:])
        count = lift_splat(ones, d, self.occ_geom, self.grid)
        return F.max_pool2d((count > 0).float(), BEV_POOL)


def perception_params(sim_cfg) -> dict[str, Any]:
    """The lookahead head's perception layout for a :class:`sim.env.SimConfig`: control period, tracks and scan as
    the teacher's privileged observation has them."""
    c = sim_cfg
    return {"dt_s": float(c.dt_s), "k": int(c.privileged_peds), "rays": int(c.scan_rays),
            "range_m": float(c.scan_range_m)}


def observer_for(camera_specs, sim_cfg, variant: str, encoder: BEVEncoder | None, head: str = "mlp",
                 mirror: bool = False, forecaster: IntentionForecaster | None = None, map_cost: bool = False,
                 map_heads: PretextHeads | None = None, track_unseen_s: float = 0.0) -> StudentObserver:
    """The :class:`StudentObserver` of a student variant for the cameras and config an env reports at reset
    (``info["cameras"]``, ``info["config"]``); ``track_unseen_s``: how long its tracks of people it could not have
    detected coast (:class:`rl.perceive.Perception`'s ``unseen_s``)."""
    return StudentObserver(variant, cameras_of(camera_specs), encoder, sim_cfg.detector.max_people, mirror=mirror,
                           head=head, perception={**perception_params(sim_cfg), "unseen_s": float(track_unseen_s)},
                           forecaster=forecaster,
                           map_cost=map_cost, map_heads=map_heads)


def observer_for_env(env, variant: str, encoder: BEVEncoder | None, head: str = "mlp",
                     mirror: bool = False, forecaster: IntentionForecaster | None = None, map_cost: bool = False,
                     map_heads: PretextHeads | None = None) -> StudentObserver:
    """The :class:`StudentObserver` of a student variant on an (unwrapped) env."""
    return observer_for(env.cameras, env.cfg, variant, encoder, head, mirror, forecaster, map_cost, map_heads)


def uses_forecaster(variant: str, head: str) -> bool:
    """Whether a student predicts people with the intention model when one is given: the lookahead or
    ``mlp_intention`` head of a variant that sees poses (``no_i2`` sees none: people are depth obstacles to it).
    The ``mlp_intention`` head needs it (:class:`StudentObserver` says so); the lookahead head falls back to
    constant velocity."""
    return head in ("lookahead", "mlp_intention") and "poses" in variant_keys(variant)


def load_student_forecaster(variant: str, head: str, intention_ckpt: Path | str | None
                            ) -> IntentionForecaster | None:
    """The frozen intention model a student uses (None without a checkpoint, or when the student does not use one,
    :func:`uses_forecaster`); errors name the checkpoint."""
    if not intention_ckpt or not uses_forecaster(variant, head):
        return None
    return load_forecaster(Path(intention_ckpt))[0]


def check_mirror_symmetric(cameras: list[Camera]) -> None:
    """Mirror augmentation of ``s_bev`` needs two cameras that are each other's reflection about the base x axis."""
    if len(cameras) != 2:
        raise ConfigError(f"mirror augmentation needs a symmetric pair of cameras, got {len(cameras)}")
    reflect = np.diag([1.0, -1.0, 1.0, 1.0])
    flip_u = np.diag([-1.0, 1.0, 1.0, 1.0])  # the image flipped left-right: camera x axis reversed
    a, b = (np.asarray(c.to_dict()["T_base_cam"]) for c in cameras)
    ka, kb = (np.asarray(c.to_dict()["K"]) for c in cameras)
    if not (np.allclose(reflect @ a @ flip_u, b, atol=1e-6) and np.allclose(ka, kb)
            and abs(ka[0, 2] - cameras[0].width / 2.0) < 1e-6):
        raise ConfigError("mirror augmentation: the cameras are not a mirror-symmetric pair (mount, yaw, intrinsics); "
                          "set dagger.mirror false")


class StudentEnv(gym.Wrapper):
    """A visual-mode env whose observations are the student's (for PPO fine-tuning and evaluation).

    The encoder is loaded in the process that builds the env (each subprocess of a vectorised env has its own,
    running on one thread, on ``device``: a CUDA one needs subprocesses that were not forked from a process that
    used CUDA, :func:`pipeline.core.device.start_method`).
    """

    def __init__(self, env: gym.Env, variant: str, encoder_ckpt: Path | None, threads: int = 1,
                 head: str = "mlp", device: torch.device | str = "cpu", intention_ckpt: Path | None = None,
                 map_cost: bool = False, encoder_precision: str = "fp32") -> None:
        super().__init__(env)
        torch.set_num_threads(threads)
        u = env.unwrapped
        if u.cfg.obs_mode != "visual":
            raise ConfigError(f"StudentEnv needs obs_mode='visual', got {u.cfg.obs_mode!r}")
        encoder = load_student_encoder(variant, encoder_ckpt, device, encoder_precision)
        self.observer = observer_for_env(u, variant, encoder, head,
                                         forecaster=load_student_forecaster(variant, head, intention_ckpt),
                                         map_cost=map_cost,
                                         map_heads=load_student_heads(variant, head, map_cost, encoder_ckpt, encoder))
        self.observation_space = self.observer.observation_space

    def reset(self, **kwargs: Any):
        obs, info = self.env.reset(**kwargs)
        self.observer.reset()
        return self.observer(obs), info

    def step(self, action):
        obs, r, term, trunc, info = self.env.step(action)
        return self.observer(obs), r, term, trunc, info


def load_student_encoder(variant: str, encoder_ckpt: Path | None, device: torch.device | str = "cpu",
                         precision: str = "fp32") -> BEVEncoder | None:
    """The frozen encoder a variant needs on ``device`` (None for ``no_bev``, whose occupancy map needs no
    network); ``precision`` ``bf16`` | ``int8``: its bfloat16 or int8 version (:mod:`pretrain.quantize`;
    int8 on a CPU only, bf16 where bfloat16 is native)."""
    if "bev" not in variant_keys(variant):
        return None
    if encoder_ckpt is None:
        raise ConfigError(f"variant {variant!r} needs a pretrained encoder checkpoint (encoder_ckpt)")
    return load_frozen_encoder(Path(encoder_ckpt), precision, device)


def load_student_heads(variant: str, head: str, map_cost: bool, encoder_ckpt: Path | str | None,
                       encoder: BEVEncoder | None) -> PretextHeads | None:
    """The frozen pretext heads of the encoder checkpoint, on the encoder's device, when the student's lookahead head
    reads the BEV's predicted occupancy (``bev_occ``, :func:`rl.networks.variant_keys`); None otherwise."""
    if "bev_occ" not in variant_keys(variant, head, map_cost):
        return None
    if encoder is None or encoder_ckpt is None:
        raise ConfigError(f"variant {variant!r} with map_cost needs a pretrained encoder checkpoint (encoder_ckpt)")
    heads = load_heads(Path(encoder_ckpt), encoder)
    for p in heads.parameters():
        p.requires_grad_(False)
    return heads.to(next(encoder.parameters()).device)
