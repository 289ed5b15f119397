"""Building, saving and loading the actor-critic policies (SB3 ``ActorCriticPolicy`` with our extractors).

A saved policy is two files in a directory: ``policy.safetensors`` (every parameter and buffer, including the
input statistics the extractor standardises with) and ``policy.json`` (what to build: kind, variant, observation
shapes, network sizes, the action grid, and the provenance of the weights). :func:`load_policy` rebuilds the
network from the JSON and loads the weights; a missing file, unreadable JSON or a weight that does not fit gives
one error naming the file.

The checkpoints a student uses (``encoder``: the BEV encoder, ``intention``: the intention model, ``teacher``: the
policy it was distilled from) are stored **relative to the policy's own directory** (``../../bev``), so a data dir
moved, copied or shipped whole to another machine keeps working, and so does a policy written into a staging
directory that is then renamed into place. :func:`read_policy_json` gives them back as absolute paths; a checkpoint
written before this (absolute paths) reads unchanged.
"""

from __future__ import annotations

import functools
import json
import math
import os
import re
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3.common.policies import ActorCriticPolicy

from pipeline.core.artifacts import atomic_write_text
from pipeline.core.errors import CorruptArtifactError, InputMissingError
from pipeline.core.executor import Bundle
from pretrain.checkpoint import ENCODER_WEIGHTS, load_safetensors, read_weights, save_safetensors
from rl.networks import StudentExtractor, StudentLookaheadExtractor, TakeScores, teacher_extractor_class

POLICY_JSON = "policy.json"
POLICY_WEIGHTS = "policy.safetensors"
N_ACTIONS = 105  # the 5 x 21 (v, ω) grid of sim.robot.action_grid (the paper's)
CHECKPOINT_REFS = ("encoder", "intention", "teacher")  # policy.json keys naming another checkpoint directory
RUNTIME_REFS = ("encoder", "intention")  # ... of those, the ones the policy acts with (the teacher is provenance)


def space_to_json(space: gym.spaces.Dict) -> dict[str, Any]:
    return {k: {"shape": list(s.shape), "low": float(np.min(s.low)), "high": float(np.max(s.high))}
            for k, s in space.spaces.items()}


def space_from_json(d: dict[str, Any]) -> gym.spaces.Dict:
    return gym.spaces.Dict({k: gym.spaces.Box(np.float32(v["low"]), np.float32(v["high"]), tuple(v["shape"]),
                                              np.float32) for k, v in d.items()})


LOOKAHEAD_KEY = "_lookahead_features"  # a batch's precomputed rollout features (rl.teacher.attach_lookahead_cache)


class ScoredPolicy(ActorCriticPolicy):
    """An actor-critic whose action logits are scored by the features extractor itself (the lookahead teacher,
    :class:`rl.networks.LookaheadTeacherExtractor`): the actor head takes the first ``n`` features as logits, the
    critic is SB3's MLP on all of them. Use with ``net_arch["pi"] = []``. An observation batch may carry its
    precomputed rollout features under :data:`LOOKAHEAD_KEY` (PPO's cached rollout buffer)."""

    def _build(self, lr_schedule) -> None:
        super()._build(lr_schedule)
        self.action_net = TakeScores(int(self.action_space.n))
        self.optimizer = self.optimizer_class(self.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs)

    def extract_features(self, obs, features_extractor=None):
        if isinstance(obs, dict) and LOOKAHEAD_KEY in obs:
            from stable_baselines3.common.preprocessing import preprocess_obs

            obs = dict(obs)
            cached = obs.pop(LOOKAHEAD_KEY)
            pre = preprocess_obs(obs, self.observation_space, normalize_images=self.normalize_images)
            return (features_extractor or self.features_extractor)(pre, cached)
        return super().extract_features(obs, features_extractor)


def policy_class(kind: str, net: dict[str, Any]) -> type[ActorCriticPolicy]:
    """The SB3 policy class of a teacher or student (for ``PPO(policy_class, ...)``)."""
    scored = (net.get("encoder") == "lookahead") if kind == "teacher" else (net.get("head") == "lookahead")
    return ScoredPolicy if scored else ActorCriticPolicy


def policy_kwargs(kind: str, variant: str | None, net: dict[str, Any]) -> dict[str, Any]:
    """SB3 ``policy_kwargs`` of a teacher or a student variant."""
    if kind == "teacher":
        encoder = net.get("encoder", "flat")
        ext: dict[str, Any] = {"scan_range_m": net.get("scan_range_m", 10.0)}
        pi = list(net.get("pi", [256, 256]))
        if encoder == "lookahead":  # the extractor scores the actions; the actor head only reads the scores
            ext.update({k: net[k] for k in ("robot", "dt_s", "path_spacing_m", "score_dim", "context_dim", "heading",
                                        "shield_s", "ped_shield_s")
                        if k in net})
            pi = []
        return {"features_extractor_class": teacher_extractor_class(encoder),
                "features_extractor_kwargs": ext,
                "net_arch": {"pi": pi, "vf": list(net.get("vf", [256, 256]))},
                "share_features_extractor": True}
    ext = {k: net[k] for k in ("bev_dim", "bev_width", "state_dim", "fused_dim", "i2former", "i2_dropout") if k in net}
    pi = list(net.get("pi", [256]))
    cls: type = StudentExtractor
    if net.get("head", "mlp") == "mlp_intention":  # the I²Former reads the intention model's tracks and forecasts
        ext["people"] = "forecasts"
    if net.get("head", "mlp") == "lookahead":  # the extractor scores the actions (rl.networks.StudentLookaheadExtractor)
        ext.update({k: net[k] for k in ("robot", "dt_s", "scan_range_m", "score_dim", "context_dim", "scorer_bound",
                                        "heading", "map_cost", "map_bounds", "shield_s", "ped_shield_s",
                                        "map_view_deg")
                    if k in net})
        cls, pi = StudentLookaheadExtractor, []
    return {"features_extractor_class": cls,
            "features_extractor_kwargs": {"variant": variant, **ext},
            "net_arch": {"pi": pi, "vf": list(net.get("vf", [128]))},
            "share_features_extractor": True}


def build_policy(kind: str, variant: str | None, obs_space: gym.spaces.Dict, net: dict[str, Any],
                 lr: float = 3e-4) -> ActorCriticPolicy:
    """A fresh policy (random weights) for ``obs_space`` and the discrete action grid. A lookahead head's map cost
    starts at zero (SB3's orthogonal initialisation would give it random weights): until it is fitted, the map does
    not change the inherited cost."""
    policy = policy_class(kind, net)(obs_space, gym.spaces.Discrete(N_ACTIONS), lambda _: lr,
                                     **policy_kwargs(kind, variant, net))
    head = getattr(policy.features_extractor, "lookahead", None)
    if head is not None and head.n_map:
        with torch.no_grad():
            head.map_cost.weight.zero_()
    return policy


def describe(kind: str, variant: str | None, obs_space: gym.spaces.Dict, net: dict[str, Any],
             **extra: Any) -> dict[str, Any]:
    return {"kind": kind, "variant": variant, "observation_space": space_to_json(obs_space), "net": net,
            "actions": {"type": "discrete", "n": N_ACTIONS, "grid": "sim.robot.action_grid: 5 speeds x 21 yaw rates"},
            **extra}


def save_policy(out: Path, policy: ActorCriticPolicy, desc: dict[str, Any]) -> None:
    """Writes ``policy.safetensors`` and ``policy.json`` into ``out`` (each atomically)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    save_safetensors(policy, out / POLICY_WEIGHTS, {"kind": str(desc["kind"]), "variant": str(desc["variant"])})
    desc = {**desc, **{k: relative_to(desc[k], out) for k in CHECKPOINT_REFS if desc.get(k)}}
    atomic_write_text(out / POLICY_JSON, json.dumps(desc, indent=2, sort_keys=True) + "\n")


def relative_to(path: Path | str, ckpt: Path | str) -> str:
    """``path`` written relative to the checkpoint directory ``ckpt`` (lexically: ``../../bev``), as policy.json
    stores the checkpoints it refers to."""
    return os.path.relpath(os.path.abspath(path), os.path.abspath(ckpt))


def resolved_from(ref: str, ckpt: Path | str) -> str:
    """A reference stored in ``ckpt``'s policy.json as an absolute path (an absolute one passes through)."""
    return os.path.normpath(os.path.join(os.path.abspath(ckpt), ref))


def read_policy_json(ckpt: Path) -> dict[str, Any]:
    """``ckpt``'s policy.json, its checkpoint references (:data:`CHECKPOINT_REFS`) as absolute paths.

    Raises:
        InputMissingError: no policy.json. CorruptArtifactError: not a policy description.
    """
    path = Path(ckpt) / POLICY_JSON
    if not path.is_file():
        raise InputMissingError(f"missing policy checkpoint: {path} does not exist (run `make train`)")
    try:
        desc = json.loads(path.read_text())
        desc["kind"], desc["observation_space"], desc["net"]  # noqa: B018 - presence check
        refs = {k: resolved_from(desc[k], ckpt) for k in CHECKPOINT_REFS if desc.get(k)}
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as e:
        raise CorruptArtifactError(f"{path}: not a policy description ({type(e).__name__}: {e})") from None
    return {**desc, **refs}


# a key of the lookahead head's learned layers as saved before the head was a module (upgrade_state_dict)
_PRE_HEAD_KEY = re.compile(r"^((?:pi_|vf_)?features_extractor\.)(context|scorer|linear)\.")


def upgrade_state_dict(sd: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A policy's stored state dict with the keys of older layouts renamed to the current ones (the same tensors;
    current checkpoints and every other key pass through unchanged). Applied once, by :func:`load_policy`.

    The lookahead head (teacher ``encoder: lookahead``, student ``head: lookahead``) was attributes set on the
    features extractor by free functions; it is now the extractor's submodule ``lookahead``
    (:class:`rl.lookahead.LookaheadHead`). For each extractor prefix ``P`` of SB3's shared extractor
    (``features_extractor.``, ``pi_features_extractor.``, ``vf_features_extractor.``), old → new::

        P context.0.weight, P context.0.bias                 →  P lookahead.context.0.weight, ...bias
        P scorer.{0,2,4}.weight, P scorer.{0,2,4}.bias       →  P lookahead.scorer.{0,2,4}.weight, ...bias
        P linear.weight, P linear.bias                       →  P lookahead.linear.weight, ...bias

    The head's rollout geometry (``grid_norm``, ``times``, ``arcs``, ``end_heading``, ``spin``, ``disc``,
    ``path_s``, ``ray_dir``) is non-persistent in both layouts: in no checkpoint, so nothing is added."""
    return {_PRE_HEAD_KEY.sub(r"\1lookahead.\2.", k): v for k, v in sd.items()}


def load_policy(ckpt: Path, shield_s: float | None = None) -> tuple[ActorCriticPolicy, dict[str, Any]]:
    """The policy saved in ``ckpt`` (eval mode) and its description. ``shield_s``: the lookahead head's obstacle
    shield horizon instead of the saved one (:class:`rl.lookahead.LookaheadHead`; it has no weights, so any
    lookahead checkpoint can be evaluated with or without it; other heads ignore it here — the MLP head's shield
    sits in :class:`rl.driver.PolicyDriver`); None = as saved.

    Raises:
        InputMissingError: the directory or a file is missing. CorruptArtifactError: unreadable or mismatching.
    """
    ckpt = Path(ckpt)
    desc = read_policy_json(ckpt)
    if shield_s is not None:
        desc = {**desc, "net": {**desc["net"], "shield_s": float(shield_s)}}
    try:
        space = space_from_json(desc["observation_space"])
        policy = build_policy(desc["kind"], desc.get("variant"), space, desc["net"])
    except (KeyError, TypeError, ValueError) as e:
        raise CorruptArtifactError(f"{ckpt / POLICY_JSON}: cannot build the policy ({type(e).__name__}: {e})") from None
    load_safetensors(policy, ckpt / POLICY_WEIGHTS, upgrade=upgrade_state_dict)
    policy.set_training_mode(False)
    return policy, desc


def checkpoint_bundle(ckpts: list[Path], dirs: list[Path] = ()) -> Bundle:
    """The files the drivers of the policy checkpoints ``ckpts`` read, for Ray nodes without the data directory
    (``ray_files: transfer``): each checkpoint directory's own files (not its subfolders: DAgger data, curves), those
    of the checkpoints its ``policy.json`` acts with (:data:`RUNTIME_REFS`: encoder, intention model) and those of
    ``dirs`` (other checkpoint directories a task reads). The bundled ``policy.json`` names its references relative
    to itself, whatever the file says, so they are found where the bundle is unpacked."""
    ckpts = list(dict.fromkeys(Path(os.path.abspath(c)) for c in ckpts))
    descs = {c: read_policy_json(c) for c in ckpts}
    folders = [*ckpts, *(Path(d[k]) for d in descs.values() for k in RUNTIME_REFS if d.get(k)), *map(Path, dirs)]
    folders = list(dict.fromkeys(Path(os.path.abspath(d)) for d in folders))  # one entry per folder
    files = {f: f.read_bytes() for d in folders for f in sorted(d.iterdir()) if f.is_file()}
    for c, desc in descs.items():
        raw = json.loads(files[c / POLICY_JSON])
        raw.update({k: relative_to(desc[k], c) for k in RUNTIME_REFS if desc.get(k)})
        files[c / POLICY_JSON] = (json.dumps(raw, indent=2, sort_keys=True) + "\n").encode()
    return Bundle.of(files)


def check_checkpoint_weights(ckpt: Path) -> None:
    """Reads the weights a policy or baseline checkpoint directory uses — ``policy.safetensors`` and, for a student,
    its encoder's ``encoder.safetensors`` and intention model's ``forecaster.safetensors`` — through :func:`pretrain.checkpoint.read_weights` (sha256 against the
    manifest, finite values), so that a damaged checkpoint is refused before any episode starts. Forked episode
    workers inherit the hash check (each file is hashed once).

    Raises:
        InputMissingError / CorruptArtifactError: naming the file.
    """
    ckpt = Path(ckpt)
    desc = read_policy_json(ckpt)
    read_weights(ckpt / POLICY_WEIGHTS)
    if desc.get("kind") == "student" and desc.get("encoder"):
        read_weights(Path(desc["encoder"]) / ENCODER_WEIGHTS)
    if desc.get("kind") == "student" and desc.get("intention"):  # the intention model it predicts people with
        read_weights(Path(desc["intention"]) / "forecaster.safetensors")


def freeze_actor(policy: ActorCriticPolicy) -> list[torch.nn.Parameter]:
    """Stops gradients into everything but the value branch (``mlp_extractor.value_net``, ``value_net``): the
    shared extractor, the policy MLP, the action head (and a log-std). Returns the parameters it froze (PPO's
    critic warm-up: the cloned critic is poor, so it is fitted on-policy before the actor moves)."""
    critic = {id(p) for m in (policy.mlp_extractor.value_net, policy.value_net) for p in m.parameters()}
    frozen = [p for p in policy.parameters() if id(p) not in critic and p.requires_grad]
    for p in frozen:
        p.requires_grad_(False)
    return frozen


def _detached_inputs(module: torch.nn.Module, args: tuple) -> tuple:
    return tuple(a.detach() for a in args)


def detach_critic(policy: ActorCriticPolicy) -> None:
    """The value branch reads the shared extractor's features detached (a forward pre-hook on
    ``mlp_extractor.value_net``; no weight changes, so checkpoints stay interchangeable): the value loss trains the
    critic's own layers and nothing the actor decides from. For PPO from a cloned student, whose extractor the value
    loss would otherwise rewrite (``train.finetune.critic_features``). Idempotent."""
    net = policy.mlp_extractor.value_net
    if not getattr(net, "_icrowdnav_detached", False):
        net.register_forward_pre_hook(_detached_inputs)
        net._icrowdnav_detached = True


def _scaled_output(factor: float, module: torch.nn.Module, args: tuple, output: torch.Tensor) -> torch.Tensor:
    return output * factor


def set_sampling_temperature(policy: ActorCriticPolicy, temperature: float) -> None:
    """The policy's action distribution becomes ``softmax(logits / temperature)`` (a forward hook on the action head
    ``action_net``; no weight changes, so checkpoints stay interchangeable and the most likely action — what
    acceptance, evaluation and the driver take — is the same). PPO then samples its rollouts from, and scores its
    updates on, that distribution: below 1 it explores closer to the deterministic policy (a cloned student's head
    is far more diffuse than its teacher's targets; ``train.finetune.sampling_temperature``). Not saved with the
    weights: set again on a resumed model. Setting it again replaces the hook; 1 removes it."""
    if not (math.isfinite(temperature) and temperature > 0):
        raise ValueError(f"sampling temperature: expected a finite number > 0, got {temperature}")
    net = policy.action_net
    handle = getattr(net, "_icrowdnav_temperature", None)
    if handle is not None:
        handle.remove()
        net._icrowdnav_temperature = None
    if temperature != 1.0:
        net._icrowdnav_temperature = net.register_forward_hook(functools.partial(_scaled_output, 1.0 / temperature))


def obs_to_tensor(obs: dict[str, np.ndarray], batch: bool = False) -> dict[str, torch.Tensor]:
    """A (batched) observation dict as float tensors."""
    return {k: torch.as_tensor(np.asarray(v, np.float32)) if batch else
            torch.as_tensor(np.asarray(v, np.float32)).unsqueeze(0) for k, v in obs.items()}


@torch.no_grad()
def action_logits(policy: ActorCriticPolicy, obs: dict[str, np.ndarray]) -> np.ndarray:
    """The logits over the action grid of one observation (``N_ACTIONS``; the deterministic action is their argmax).
    Inference only, like :func:`act`: no autograd graph, and torch's own attention kernel (``attention_kernel``)."""
    dist = policy.get_distribution(obs_to_tensor({k: obs[k] for k in policy.observation_space.spaces}))
    return dist.distribution.logits[0].numpy()


@torch.no_grad()
def act(policy: ActorCriticPolicy, obs: dict[str, np.ndarray], deterministic: bool = True) -> int:
    """The action index of one observation."""
    dist = policy.get_distribution(obs_to_tensor({k: obs[k] for k in policy.observation_space.spaces}))
    return int(dist.get_actions(deterministic=deterministic)[0])
