"""``icrowdnav train``: the privileged teacher, then each visual student variant (DAgger + PPO fine-tuning).

::

    icrowdnav train --variant teacher            # expert cloning + DAgger, then PPO (privileged, no rendering)
    icrowdnav train --variant full               # DAgger from the teacher, then PPO fine-tuning (rendered)
    icrowdnav train --variant no_i2 --resume     # continue a killed run
    icrowdnav train --variant drl_vo             # a learned baseline: drl_vo | sarl_om | vint (rl.baselines)
    make train                                   # teacher, full, no_i2, no_bev, the baselines (TRAIN_VARIANTS)
    icrowdnav train --variant full --device cuda # updates and the frozen encoder on the GPU (default auto)

Inputs: the teacher, DRL-VO and SARL*-OM need nothing but the simulator; ViNT-style needs the recorded dataset
(``DATA_DIR/datasets/<vint.repo_id>``); a student needs ``DATA_DIR/checkpoints/policy/teacher`` and,
for ``full`` and ``no_i2``, the pretrained encoder ``DATA_DIR/checkpoints/<encoder>``. Output
``DATA_DIR/checkpoints/policy/<variant>/``::

    policy.safetensors, policy.json   the final policy (weights incl. input statistics; what to build + provenance)
    config.yaml, manifest.json        resolved config; provenance (written last: an unfinished run has none)
    metrics.json                      training summary + the acceptance evaluation (SR per scene, seeded)
    train_log.csv, tb/                per-step / per-iteration logs (TensorBoard)
    curves.png                        training curves
    teacher:  imitation/<k>/{policy.*, data.npz}: k = 0 clones the expert's episodes, k >= 1 is a DAgger iteration
              (the teacher drives, the expert labels every state with its cost of each action); ppo/ (SB3
              checkpoint for --resume); metrics.json also has the acceptance run of the policy before PPO
    student:  dagger/iter_<k>/{raw/*.mcap, dataset/ (LeRobot), features/*.npz, episodes.jsonl, policy/, done.json,
              intention/ (with --intention_tune.epochs N: the intention model fine-tuned on iterations 0..k)}
              ppo/ (SB3 checkpoint of the fine-tuning for --resume)
    baseline: policy.json has kind "baseline"; its own resume state (drl_vo: bc/, ppo/; sarl_om: rl/) — see
              rl.baselines.<name>

Every policy.json states which steps produced it (``produced_by``). Runs write in place (resumable, like
``record``/``pretrain``); ``manifest.json`` comes last.

Device (``--device``, default ``auto``: CUDA when present): the cloning updates (teacher and students), SB3 PPO
(teacher, student fine-tuning, DRL-VO) and the students' frozen encoder in the DAgger rollouts and the fine-tuning
envs run there; the rollout workers' policies act on the CPU. Everything saved is written from CPU tensors (SB3
zips load with ``map_location``), so a policy trained on a GPU loads anywhere; metrics.json and the manifest's
counts record the device.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from pipeline.core import layout
from pipeline.core.artifacts import atomic_save_npz, atomic_write_json, atomic_write_text
from pipeline.core.config import BaseStageConfig, dump_yaml
from pipeline.core.device import device_counts, resolve_device, resolve_precision, start_method
from pipeline.core.errors import ConfigError, CorruptArtifactError, InputMissingError
from pipeline.core.executor import Executor, check_executor, check_ray_files
from pipeline.core.timing import PhaseClock
from pretrain.checkpoint import read_encoder_json
from pretrain.geometry import BEVGrid
from pretrain.intention import (
    FORECASTER_WEIGHTS,
    INTENTION_JSON,
    FitOptions,
    finetune_forecaster,
    load_forecaster,
)
from pretrain.quantize import CALIBRATION_FILE, check_precision, resolve_encoder_precision
from rl.baselines import BASELINES, baseline_module
from rl.baselines.common import curve_points
from rl.baselines.drl_vo.configuration import Config as DRLVOConfig
from rl.baselines.sarl_om.configuration import Config as SARLOMConfig
from rl.baselines.vint.configuration import Config as ViNTConfig
from rl.callbacks import checkpoint_callback, learn_with_critic_warmup, progress_callback, save_ppo
from rl.dagger import (
    bev_stats,
    export_iteration,
    held_out_frames,
    iteration_timing,
    load_features,
    run_iteration,
    write_done,
)
from rl.evaluate import evaluate, success_table
from rl.figures import plot_learning_curve, plot_training
from rl.lookahead import LINEAR_TERMS, PED_TERMS, check_shield_s
from rl.networks import STUDENT_HEADS, VARIANTS, check_i2_dropout
from rl.observe import (
    StudentEnv,
    check_encoder_matches,
    env_cameras,
    load_student_encoder,
    load_student_forecaster,
    load_student_heads,
    observer_for_env,
    uses_forecaster,
)
from rl.policy import (
    build_policy,
    describe,
    detach_critic,
    load_policy,
    policy_class,
    policy_kwargs,
    read_policy_json,
    relative_to,
    save_policy,
    set_sampling_temperature,
)
from rl.teacher import (
    FITTED_PREFIXES,
    MAP_SIGNS,
    CurriculumStage,
    SceneMixEnv,
    attach_lookahead_cache,
    bc_loss,
    behaviour_clone,
    check_curriculum,
    collect_dagger,
    collect_expert,
    curriculum_callback,
    extend_feature_cache,
    fit_lookahead_linear,
    has_lookahead,
    lookahead_feature_cache,
    make_vec_env,
    ppo_kwargs,
    stage_pairs_all,
    teacher_net,
)
from sim.env import CrowdNavEnv, SimConfig
from sim.scene import load_scene

log = logging.getLogger("icrowdnav")
TRAIN_VARIANTS = ("teacher", *VARIANTS, *BASELINES)

# train.dagger.linear_cost -> the terms fit_lookahead_linear fits each iteration, and how the log names that fit
LINEAR_COSTS = {"teacher": ("map", "map"), "fit": ("all", "linear"), "peds": ("peds", "pedestrian + map")}
PED_NAMES = tuple(LINEAR_TERMS[i] for i in PED_TERMS)


@dataclass
class TeacherConfig:
    """The privileged teacher (rl.teacher)."""

    bc_episodes: int = 200  # expert episodes for the warm start (spread over the curriculum's pairs)
    bc_epochs: int = 8  # behaviour-cloning epochs
    bc_batch: int = 512
    bc_lr: float = 1e-3
    soft_tau: float = 0.1  # > 0: clone the expert's softmin over the action grid (its costs) instead of its argmin
    mirror: bool = True  # left-right mirror augmentation while cloning
    dagger_iterations: int = 4  # DAgger on privileged states: the teacher drives, the expert labels (no rendering)
    dagger_episodes: int = 100  # episodes per DAgger iteration
    dagger_beta0: float = 0.5  # probability that the expert drives a step in the first DAgger iteration (0 later)
    dagger_epochs: int = 4  # cloning epochs on the aggregate after each iteration
    ppo_steps: int = 200_000  # PPO env steps after the warm start (0 = the teacher is the cloned expert)
    critic_warmup_steps: int = 0  # first PPO steps train only the value head (the actor is frozen)
    # shared | detached: whether the value loss trains the shared extractor too (as FinetuneConfig.critic_features)
    critic_features: str = "shared"
    n_envs: int = 8  # vectorised envs
    subprocess: bool = True  # rl.vec_env.BatchedSubprocVecEnv (a worker per core) instead of DummyVecEnv
    ppo: dict[str, float] = field(default_factory=lambda: {"n_steps": 512, "batch_size": 512, "n_epochs": 6,
                                                           "learning_rate": 1e-4, "clip_range": 0.1,
                                                           "ent_coef": 0.0})
    net: dict[str, Any] = field(default_factory=lambda: {"pi": [256, 256], "vf": [256, 256], "encoder": "lookahead"})
    curriculum: list[CurriculumStage] = field(default_factory=lambda: [
        CurriculumStage(until=0.3, densities=[0.1]), CurriculumStage(until=1.0, densities=[0.1, 0.2])])


BC_SCHEDULES = ("pool", "new")  # DaggerConfig.bc_schedule
CRITIC_FEATURES = ("shared", "detached")  # TeacherConfig.critic_features, FinetuneConfig.critic_features
# an MLP-head DAgger cloning that leaves the new frames' loss above this fraction of ln(n actions) has learned next to
# nothing: the sixth chain's MLP `w/o I²` stayed at 0.87-0.94 of it (iterations 1-7) and its next rollouts succeeded
# in 0-8 % (`full`'s 0.50-0.58, 50-65 %; docs/results.md#mlp-no-i2-chain6)
NEAR_UNIFORM = 0.85


def near_uniform_warning(loss: float, n_actions: int, what: str) -> str | None:
    """The warning for a cloning whose loss on its frames stays near a uniform choice (:data:`NEAR_UNIFORM` · ln n),
    else ``None``: the next DAgger rollouts are then driven by a student that has learned little."""
    if n_actions < 2 or not loss > NEAR_UNIFORM * math.log(n_actions):
        return None
    uniform = math.log(n_actions)
    return (f"{what}: after cloning, the loss on the iteration's frames is {loss:.2f} nats, near a uniform choice "
            f"({uniform:.2f} = ln {n_actions}): the next rollouts are driven by a student that has learned little, and "
            f"end sooner (more cloning per iteration: train.dagger.bc_max_epochs, the adaptive budget, or "
            f"train.dagger.bc_epochs, or train.dagger.bc_schedule: pool)")


@dataclass
class DaggerConfig:
    """DAgger distillation into the student (rl.dagger)."""

    iterations: int = 4
    episodes_per_iter: int = 20  # rendered episodes per iteration
    beta0: float = 1.0  # probability that the teacher drives, iteration 0
    beta_decay: float = 0.5  # β_k = beta0 · beta_decay^k
    bc_epochs: int = 8  # cloning epochs after each iteration (over what bc_schedule says)
    # the cloning after iteration k, continuing from iteration k-1's student: "pool" = bc_epochs passes over the whole
    # pool (every iteration's frames: its cost grows with k, quadratic over the run); "new" = bc_epochs x the
    # iteration's new frames, drawn from the whole pool (rl.teacher.behaviour_clone's epoch_size: linear over the run,
    # the last student has taken as many steps as one bc_epochs-cloning of the final pool)
    bc_schedule: str = "pool"
    # after the last iteration, clone a fresh student (new weights) on the whole pool for bc_epochs and keep it as the
    # final policy (dagger/final/): for the MLP head's own 8 x 60 run three such clonings drove +0.080 / +0.053 /
    # +0.013 SR better than the warm-started last iteration, only the first significant (docs/results.md, the MLP head)
    final_clone: bool = False
    # an adaptive cloning budget (0 = off: bc_epochs, every frame cloned): a share bc_holdout of the episodes (a hash
    # of their names: the same episodes through every iteration) is never cloned on, and each cloning — every
    # iteration's and the final one — runs at least bc_epochs and on up to bc_max_epochs while its loss on those
    # episodes reaches a new best within bc_patience epochs, keeping its best epoch's weights
    # (rl.teacher.behaviour_clone); an MLP-head cloning whose best held-out loss is still above NEAR_UNIFORM · ln n
    # does not stop (its early plateau), and a fresh final cloning left there is cloned once more from the next seed
    # (leaving the plateau is a draw of the initialisation). Built for the MLP head whose 8-epoch clonings stayed
    # near chance (w/o I², chain 6); measured there: docs/results.md#mlp-adaptive-budget
    bc_max_epochs: int = 0
    bc_patience: int = 2
    bc_holdout: float = 0.1
    # which held-out frames decide an iteration's stop: "pool" = every iteration's held-out episodes; "new" = only the
    # newest iteration's (the states the student visits now; the split is the same, held-out episodes of earlier
    # iterations are still never cloned on). Over the pool, past the first iterations the loss barely moved with one
    # iteration's frames and the stops kept epoch 1-3 weights (chain 6: docs/results.md#mlp-adaptive-budget); an
    # iteration with no held-out episode falls back to the pool. The final cloning always reads the pool's.
    bc_holdout_scope: str = "pool"
    bc_batch: int = 128
    bc_lr: float = 5e-4
    soft_tau: float = 1.0  # > 0: clone the teacher's action distribution softmax(logits / soft_tau); 0: its argmax
    mirror: bool = True  # left-right mirror augmentation while cloning (bev variants record the mirrored s_bev)
    # the lookahead head's linear cost: "teacher" = the lookahead teacher's own (the same layer on the student's
    # perceived tracks and scan; frozen, the MLP scorer learns the rest), "fit" = convex regression to the teacher's
    # distribution on the DAgger frames (measured weaker: docs/notes/2026-11-lookahead-student-variants.md), "peds" =
    # the teacher's, with its pedestrian terms refitted by the same regression together with the map cost (the
    # student's tracks and intention forecasts are not the teacher's ground truth)
    linear_cost: str = "teacher"
    # the cloning set (every iteration's cached frames) in memory up to this size; larger, it is memory-mapped from
    # unlinked files beside the checkpoint (rl.dagger.pool_frames: the same arrays, the page cache holds what fits)
    pool_memory_gb: float = 8.0
    # the cloning's arithmetic: fp32, or bf16 (the forward pass under bfloat16 autocast; weights, loss and optimiser in
    # float32), or auto = bf16 where the device computes bfloat16 natively (pipeline.core.device.resolve_precision)
    bc_precision: str = "fp32"
    scenes: list[str] = field(default_factory=lambda: ["hallway", "corner", "doorway", "cluttered_room", "open_crowd"])
    densities: list[float] = field(default_factory=lambda: [0.1, 0.2])


@dataclass
class FinetuneConfig:
    """PPO fine-tuning of the student with the paper's reward and the frozen encoder."""

    ppo_steps: int = 0  # rendered env steps (0 = no fine-tuning; the paper profile sizes it like the paper)
    # the first env steps train only the value head, the actor frozen (as DRL-VO's): DAgger clones the actor only, so
    # the distilled student's critic has never seen a return (rl.callbacks.learn_with_critic_warmup)
    critic_warmup_steps: int = 4096
    # shared: the value loss trains the shared extractor too (the paper's joint optimisation, from scratch there);
    # detached: the critic reads the extractor's features without sending gradients into them, so only the policy
    # gradient moves what the cloned actor decides from (rl.policy.detach_critic)
    critic_features: str = "shared"
    # PPO samples from softmax(logits / T) (rl.policy.set_sampling_temperature; the argmax, which acceptance and the
    # benchmark take, is unchanged): below 1 its rollouts drive closer to the cloned student's deterministic policy,
    # whose head is far more diffuse than the teacher's targets (docs/notes/2026-12-student-ppo-109k.md)
    sampling_temperature: float = 1.0
    n_envs: int = 2
    # target_kl 0.02 stops an update's epochs once the policy has moved that far (as DRL-VO's, which PPO straight
    # after cloning destroyed: docs/notes/2026-11-drl-vo-ppo-after-cloning.md)
    ppo: dict[str, float] = field(default_factory=lambda: {"n_steps": 256, "batch_size": 128, "n_epochs": 6,
                                                           "learning_rate": 5e-5, "clip_range": 0.1,
                                                           "target_kl": 0.02})
    checkpoint_steps: int = 2048  # ppo/last.zip after the first update past every this many env steps (--resume)


@dataclass
class IntentionTuneConfig:
    """Frozen or fine-tuned intention model (``pretrain.intention.finetune_forecaster``): with ``epochs`` > 0, after
    every DAgger iteration the pretrained model is fine-tuned on that student's rollouts so far (its pretext: the
    tracked people's future positions) and the next iteration, and the final policy, use it."""

    epochs: int = 0  # 0 = frozen (measured: fine-tuning on the default profile's rollouts changes its error < 1 %)
    lr: float = 1e-3  # AdamW peak learning rate (one-cycle)
    batch: int = 256
    pose_dropout: float = 0.3  # as in pretraining (pretrain-intention.pose_dropout)
    head_aux_weight: float = 0.2
    val_fraction: float = 0.2  # rollout episodes held out to measure the fine-tuning


@dataclass
class AcceptanceConfig:
    """The seeded evaluation run at the end of training (the test scenes; `make eval` is the full benchmark)."""

    scenes: list[str] = field(default_factory=lambda: ["office_lobby", "hospital_corridor", "warehouse"])
    densities: list[float] = field(default_factory=lambda: [0.1])
    episodes: int = 50  # per (scene, density); seeds 10_000 + k (disjoint from training seeds)


@dataclass
class TrainConfig(BaseStageConfig):
    """Config of the ``train`` stage (one variant per run)."""
    # how many cores, as device says where: every episode is seeded by itself and comes back in job order (SARL*-OM's
    # RL rollouts too: tests/rl/baselines/sarl_om/test_training.py), the DAgger datasets' shards merge to the same
    # frames (tests/recorder/test_export_shards.py)
    PLACEMENT_FIELDS: ClassVar[tuple[str, ...]] = ("threads", "workers")

    variant: str = "full"  # teacher | full | no_i2 | no_bev | a learned baseline: drl_vo | sarl_om | vint
    encoder: str = "bev"  # pretrained encoder: DATA_DIR/checkpoints/<encoder>/
    # the students' frozen encoder in DAgger, fine-tuning, acceptance and eval: fp32 | bf16 (its convolutions in
    # bfloat16, BatchNorms folded: ~2x on a CPU with AVX512-BF16/AMX, or a GPU) | int8 (its int8 version, calibrated by
    # pretrain: ~2x faster on a CPU; CPU only; docs/results.md, Performance) | auto (bf16 where the device has native
    # bfloat16, else fp32); saved in policy.json as the precision it resolved to
    encoder_precision: str = "fp32"
    # pretrained intention model DATA_DIR/checkpoints/<intention>/ (icrowdnav pretrain-intention): the lookahead head
    # of a variant with poses (full, no_bev) predicts the people it tracks with it; "" = constant velocity (the
    # ablation); the mlp_intention head's I²Former reads its forecasts. The profiles set it; no_i2 and the mlp head
    # never use it.
    intention: str = ""
    intention_tune: IntentionTuneConfig = field(default_factory=IntentionTuneConfig)  # frozen (default) | fine-tuned
    sim: SimConfig = field(default_factory=SimConfig)
    teacher: TeacherConfig = field(default_factory=TeacherConfig)
    dagger: DaggerConfig = field(default_factory=DaggerConfig)
    finetune: FinetuneConfig = field(default_factory=FinetuneConfig)
    acceptance: AcceptanceConfig = field(default_factory=AcceptanceConfig)
    # student network sizes and i2_dropout (the I²Former output zeroed per cloning sample with this probability)
    # (rl.networks.StudentExtractor)
    net: dict[str, Any] = field(default_factory=dict)
    # the student's actor: "lookahead" scores each action by rolling it out against the pedestrians tracked from its
    # detected poses and a depth obstacle scan (rl.perceive, rl.networks.StudentLookaheadExtractor); "mlp" is the
    # paper's MLP head on z alone (why the default differs: docs/notes/2026-11-paper-mlp-head-student.md);
    # "mlp_intention" the same MLP head whose I²Former reads the tracks and the pretrained intention model's forecasts
    # instead of raw poses (rl.networks.ForecastI2Former; needs train.intention for full and no_bev)
    head: str = "lookahead"
    scorer_bound: float = 3.0  # lookahead head: its learned correction is bounded to ± this many nats (0 = unbounded)
    # lookahead head: the obstacle shield's horizon in s (0 = off): an action whose arc is predicted to come within
    # 2 cm of the perceived obstacles by then is chosen only if every action is (rl.lookahead.LookaheadHead; on
    # the N = 75 benchmark it raised full's SR by 0.078 pooled, docs/results.md "Why they fail")
    shield_s: float = 0.6
    # mlp head: the same shield (rl.lookahead.ObstacleShield on its perceived depth scan, subtracted from its logits)
    # over this horizon in s, in its DAgger rollouts, its acceptance and wherever the checkpoint is loaded (saved as
    # net.shield_s; eval --shield_s overrides it); 0 = off, the paper's head with every weight learned. A hand-built
    # rule: with it the head is no longer all learned (docs/results.md, "the obstacle shield on the MLP head")
    mlp_shield_s: float = 0.0
    # lookahead head: also sample an occupancy map along every arc, weighted by a convex-fitted cost (rl.lookahead):
    # the pretrained BEV's predicted occupancy (static, people now / +0.5 s / +1.0 s) for full and no_i2, the depth
    # occupancy (the w/o BEV substitute) for no_bev; the mlp head has no costs and ignores it
    map_cost: bool = False
    # lookahead head with map_cost: read the map only inside the cameras' joint view (|bearing| <= camera yaw + half
    # its field of view); the pretrained BEV marks the unseen as occupied in every channel, which a cost over the
    # whole map reads as a preference among turning arcs. One training: no SR gain on development seeds (-0.04,
    # p = 0.44), so off (docs/notes/2026-11-pedestrian-hits-untracked-people.md)
    map_view: bool = False
    # lookahead head with map_cost: the fitted map weights' signs — free (the convex fit's), or costs (every map term
    # constrained to lower an arc's score: occupancy is never a bonus; rl.teacher.fit_lookahead_linear)
    map_signs: str = "free"
    drl_vo: DRLVOConfig = field(default_factory=DRLVOConfig)  # the learned baselines (rl.baselines.<name>)
    sarl_om: SARLOMConfig = field(default_factory=SARLOMConfig)
    vint: ViNTConfig = field(default_factory=ViNTConfig)
    workers: int = 2  # processes for rollouts and evaluation
    # where the DAgger rollouts and acceptance episodes run: auto (Ray when RAY_ADDRESS is set) | local | ray
    # (pipeline.core.executor; the same seeds give the same files either way); not in the config hash
    executor: str = "auto"
    ray_address: str = ""  # Ray cluster host:port (empty: RAY_ADDRESS, or a Ray instance started on this machine)
    # on Ray, how checkpoints and episode files travel: shared (every node reads and writes the data dir: a shared
    # filesystem) | transfer (Ray's object store; only this process touches the data dir); not in the config hash
    ray_files: str = "shared"
    threads: int = 0  # torch threads for cloning / PPO updates (0 = every core)
    # where cloning, PPO updates and the students' frozen encoder run: auto (CUDA when this machine has it, else the
    # CPU) | cpu | cuda | cuda:N (--device cuda); not in the config hash (a run resumes on another device); the
    # manifest's counts record the one used
    device: str = "auto"
    progress: bool = True

    def validate(self) -> None:
        super().validate()
        if self.variant not in TRAIN_VARIANTS:
            raise ConfigError(f"train.variant: expected one of {list(TRAIN_VARIANTS)}, got {self.variant!r}")
        check_curriculum(self.teacher.curriculum)
        t, d = self.teacher, self.dagger
        if t.dagger_iterations < 0 or t.soft_tau < 0 or not 0.0 <= t.dagger_beta0 <= 1.0:
            raise ConfigError("teacher: expected dagger_iterations >= 0, soft_tau >= 0 and dagger_beta0 in [0, 1], "
                              f"got {t.dagger_iterations}, {t.soft_tau}, {t.dagger_beta0}")
        if t.dagger_iterations and t.dagger_episodes < 1:
            raise ConfigError(f"teacher.dagger_episodes: expected >= 1, got {t.dagger_episodes}")
        for key, v in (("teacher.bc_episodes", t.bc_episodes), ("teacher.bc_epochs", t.bc_epochs),
                       ("teacher.n_envs", t.n_envs), ("dagger.iterations", d.iterations),
                       ("dagger.episodes_per_iter", d.episodes_per_iter), ("dagger.bc_epochs", d.bc_epochs),
                       ("workers", self.workers), ("finetune.n_envs", self.finetune.n_envs),
                       ("finetune.checkpoint_steps", self.finetune.checkpoint_steps),
                       ("acceptance.episodes", self.acceptance.episodes),
                       ("intention_tune.batch", self.intention_tune.batch)):
            if v < 1:
                raise ConfigError(f"train.{key}: expected an integer >= 1, got {v}")
        for key, v in (("teacher.ppo_steps", t.ppo_steps), ("finetune.ppo_steps", self.finetune.ppo_steps),
                       ("teacher.critic_warmup_steps", t.critic_warmup_steps),
                       ("finetune.critic_warmup_steps", self.finetune.critic_warmup_steps)):
            if v < 0:
                raise ConfigError(f"train.{key}: expected an integer >= 0, got {v}")
        for key, v in (("teacher.critic_features", t.critic_features),
                       ("finetune.critic_features", self.finetune.critic_features)):
            if v not in CRITIC_FEATURES:
                raise ConfigError(f"train.{key}: expected one of {list(CRITIC_FEATURES)}, got {v!r}")
        if not (math.isfinite(self.finetune.sampling_temperature) and self.finetune.sampling_temperature > 0):
            raise ConfigError(f"train.finetune.sampling_temperature: expected a finite number > 0, got "
                              f"{self.finetune.sampling_temperature}")
        if d.soft_tau < 0:
            raise ConfigError(f"train.dagger.soft_tau: expected >= 0, got {d.soft_tau}")
        if d.bc_schedule not in BC_SCHEDULES:
            raise ConfigError(f"train.dagger.bc_schedule: expected one of {list(BC_SCHEDULES)}, got {d.bc_schedule!r}")
        if d.bc_max_epochs and not (d.bc_max_epochs >= d.bc_epochs and d.bc_patience >= 1
                                    and 0 < d.bc_holdout < 1):  # NaN fails too
            raise ConfigError(f"train.dagger: the adaptive budget expects bc_max_epochs >= bc_epochs, bc_patience >= 1 "
                              f"and 0 < bc_holdout < 1, got {d.bc_max_epochs} (bc_epochs {d.bc_epochs}), "
                              f"{d.bc_patience}, {d.bc_holdout}")
        if d.bc_holdout_scope not in ("pool", "new"):
            raise ConfigError(f"train.dagger.bc_holdout_scope: expected 'pool' or 'new', got {d.bc_holdout_scope!r}")
        if d.bc_max_epochs < 0:
            raise ConfigError(f"train.dagger.bc_max_epochs: expected an integer >= 0 (0 = off), got {d.bc_max_epochs}")
        if not d.pool_memory_gb > 0:  # NaN fails too
            raise ConfigError(f"train.dagger.pool_memory_gb: expected > 0 (GiB), got {d.pool_memory_gb}")
        it = self.intention_tune
        if it.epochs < 0:
            raise ConfigError(f"train.intention_tune.epochs: expected an integer >= 0 (0 = frozen), got {it.epochs}")
        if not (math.isfinite(it.lr) and it.lr > 0 and 0 <= it.pose_dropout < 1 and it.head_aux_weight >= 0
                and 0 < it.val_fraction < 1):
            raise ConfigError("train.intention_tune: expected lr > 0, 0 <= pose_dropout < 1, head_aux_weight >= 0 and "
                              f"0 < val_fraction < 1, got {it.lr}, {it.pose_dropout}, {it.head_aux_weight}, "
                              f"{it.val_fraction}")

        device = resolve_device(self.device, "train.device")
        check_precision(self.encoder_precision, "train.encoder_precision", device)
        resolve_precision(d.bc_precision, device, "train.dagger.bc_precision")
        if self.head not in STUDENT_HEADS:
            raise ConfigError(f"train.head: expected one of {list(STUDENT_HEADS)}, got {self.head!r}")
        if self.head == "mlp_intention" and uses_forecaster(self.variant, self.head) and not self.intention:
            raise ConfigError(f"train.intention: the mlp_intention head of variant {self.variant!r} reads the "
                              "pretrained intention model's forecasts; expected a checkpoint name (e.g. intention), "
                              "got ''")
        check_i2_dropout(self.net.get("i2_dropout", 0.0))
        if self.scorer_bound < 0:
            raise ConfigError(f"train.scorer_bound: expected >= 0, got {self.scorer_bound}")
        check_shield_s(self.shield_s, "train.shield_s")
        check_shield_s(self.mlp_shield_s, "train.mlp_shield_s")
        if self.mlp_shield_s and self.head != "mlp":
            raise ConfigError(f"train.mlp_shield_s: the MLP head's shield, expected 0 with head {self.head!r} (its "
                              f"own is train.shield_s), got {self.mlp_shield_s}")
        if self.mlp_shield_s and self.finetune.ppo_steps:
            raise ConfigError(f"train.mlp_shield_s: PPO fine-tuning acts through the network alone, without the "
                              f"shield; expected finetune.ppo_steps 0 with it, got {self.finetune.ppo_steps}")
        if self.map_signs not in MAP_SIGNS:
            raise ConfigError(f"train.map_signs: expected one of {list(MAP_SIGNS)}, got {self.map_signs!r}")
        if d.linear_cost not in LINEAR_COSTS:
            raise ConfigError(f"train.dagger.linear_cost: expected one of {list(LINEAR_COSTS)}, got {d.linear_cost!r}")
        if not (0 <= d.beta0 <= 1 and 0 <= d.beta_decay <= 1):
            raise ConfigError(f"train.dagger: beta0 and beta_decay must be in [0, 1], got {d.beta0}, {d.beta_decay}")
        if not d.scenes or not d.densities or not self.acceptance.scenes or not self.acceptance.densities:
            raise ConfigError("train: dagger and acceptance need at least one scene and one density")

        for s in {*d.scenes, *self.acceptance.scenes, *(x for st in t.curriculum for x in st.scenes)}:
            load_scene(s)  # unknown scene -> ConfigError naming it
        resolve_device(self.device, "train.device")  # cuda without CUDA: one error, before anything is written
        check_executor(self.executor, self.ray_address, "train")
        check_ray_files(self.ray_files, "train")


def policy_root(cfg: TrainConfig) -> Path:
    return layout.policy_root(cfg.data_dir)


def output_dir(cfg: TrainConfig) -> Path:
    return policy_root(cfg) / cfg.variant


def encoder_dir(cfg: TrainConfig) -> Path:
    return layout.checkpoint_dir(cfg.data_dir, cfg.encoder)


def intention_dir(cfg: TrainConfig) -> Path | None:
    """The intention checkpoint the student uses (None: constant velocity, or a student that does not use one)."""
    if not cfg.intention or not uses_forecaster(cfg.variant, cfg.head):
        return None
    return layout.checkpoint_dir(cfg.data_dir, cfg.intention)


def inputs(cfg: TrainConfig) -> list[Path]:
    """The teacher, the encoder and the intention model a student needs; checked here, before any output exists."""
    if cfg.variant == "teacher":
        return []
    if cfg.variant in BASELINES:
        return list(baseline_module(cfg.variant).inputs(cfg))

    teacher = policy_root(cfg) / "teacher"
    read_policy_json(teacher)
    if not (teacher / "manifest.json").is_file():
        raise InputMissingError(f"teacher checkpoint {teacher} is unfinished (no manifest.json); run "
                                "`icrowdnav train --variant teacher` first")
    paths = [teacher / "policy.json", teacher / "policy.safetensors"]
    if cfg.head == "lookahead" and cfg.dagger.linear_cost != "fit" and \
            read_policy_json(teacher)["net"].get("encoder") != "lookahead":
        raise ConfigError(f"train.dagger.linear_cost {cfg.dagger.linear_cost!r}: the teacher {teacher} is not a lookahead teacher "
                          "(teacher.net.encoder lookahead), so it has no linear cost to inherit; re-train it or use "
                          "--dagger.linear_cost fit")
    if cfg.variant != "no_bev":
        read_encoder_json(encoder_dir(cfg))  # missing / unfinished / corrupt -> one clear error

        enc = load_student_encoder(cfg.variant, encoder_dir(cfg), precision=cfg.encoder_precision)
        env = CrowdNavEnv(config=replace(cfg.sim, scene=cfg.dagger.scenes[0], obs_mode="state"))
        env.reset(seed=0)
        check_encoder_matches(enc, env_cameras(env), f"train --variant {cfg.variant} (encoder {encoder_dir(cfg)})")
        paths += [encoder_dir(cfg) / "encoder.json", encoder_dir(cfg) / "encoder.safetensors"]
        if cfg.encoder_precision == "int8":
            paths.append(encoder_dir(cfg) / CALIBRATION_FILE)
    if (int_dir := intention_dir(cfg)) is not None:
        load_forecaster(int_dir)  # missing / unfinished / corrupt -> one clear error naming it
        paths += [int_dir / INTENTION_JSON, int_dir / FORECASTER_WEIGHTS]
    return paths


class _Log:
    """Appends rows to ``train_log.csv`` and TensorBoard."""

    def __init__(self, out: Path) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.path = out / "train_log.csv"
        self.tb = SummaryWriter(str(out / "tb"))

    def add(self, phase: str, step: int, **values: float) -> None:
        new = not self.path.exists()
        with open(self.path, "a", newline="") as f:
            w = csv.writer(f)
            if new:
                w.writerow(["phase", "step", "key", "value"])
            for k, v in values.items():
                w.writerow([phase, step, k, f"{float(v):.6g}"])
                self.tb.add_scalar(f"{phase}/{k}", float(v), step)
        self.tb.flush()


def _acceptance(cfg: TrainConfig, policy_dir: Path, method: str) -> dict[str, Any]:
    a = cfg.acceptance
    seeds = [10_000 + k for k in range(a.episodes)]
    rows = evaluate(policy_dir, cfg.sim, [(s, d) for s in a.scenes for d in a.densities], seeds,
                    cfg.workers, method, cfg.progress, Executor.of(cfg))
    return {"seeds": [seeds[0], seeds[-1]], "table": success_table(rows), "episodes": rows}


def acceptance(cfg: TrainConfig, policy_dir: Path, method: str) -> dict[str, Any]:
    """The acceptance episodes of ``cfg.acceptance`` (seeds 10000 on) for the checkpoint in ``policy_dir``, written
    to its ``acceptance_episodes.jsonl`` (what ``python -m evaluation.compare`` pairs by seed); returns the table."""
    acc = _acceptance(cfg, Path(policy_dir), method)
    write_acceptance(Path(policy_dir), acc)
    return {k: v for k, v in acc.items() if k != "episodes"}


def write_acceptance(out: Path, acc: dict[str, Any]) -> None:
    lines = "".join(json.dumps({k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                                for k, v in r.items()}) + "\n" for r in acc["episodes"])
    atomic_write_text(out / "acceptance_episodes.jsonl", lines)


# --------------------------------------------------------------------------------------------------------- teacher
def _train_teacher(cfg: TrainConfig, out: Path) -> dict[str, Any]:
    from stable_baselines3 import PPO

    device = resolve_device(cfg.device, "train.device")
    t = cfg.teacher
    logger = _Log(out)
    pairs = stage_pairs_all(t.curriculum)
    probe = SceneMixEnv(cfg.sim, pairs[:1])
    net = teacher_net(t.net, cfg.sim)
    summary: dict[str, Any] = {}
    gamma = ppo_kwargs(t.ppo)["gamma"]
    clone = {"batch": t.bc_batch, "soft_tau": t.soft_tau, "mirror": t.mirror, "progress": cfg.progress}
    policy, data = None, None
    # the lookahead teacher's rollout features of every frame of `data` (rl.teacher.lookahead_feature_cache): they
    # depend on the observation alone, so each stage computes them for its new frames only and appends them — the
    # same arrays as recomputing the whole aggregate (bit for bit, tested), which took a third of the stage's time
    cache: tuple[np.ndarray, np.ndarray | None] | None = None
    # stage k = 0: clone the expert's own episodes; k >= 1: DAgger iteration k (teacher drives, expert labels).
    # Each stage's policy and data land in imitation/<k>/ so a killed run resumes after the last finished one.
    for k in range(t.dagger_iterations + 1):
        sdir = out / "imitation" / f"{k:02d}"
        if (sdir / "policy.json").exists() and (sdir / "data.npz").exists():
            continue
        if k > 0 and policy is None:  # resuming: the previous stage's policy and aggregate
            policy, _ = load_policy(out / "imitation" / f"{k - 1:02d}")
            policy.to(device)
        if data is None and k > 0:
            data = _load_aggregate(out, k)
            if has_lookahead(policy):
                cache = lookahead_feature_cache(policy, data, t.mirror)  # the aggregate's features, once
        t0 = time.perf_counter()
        if k == 0:
            new = collect_expert(cfg.sim, pairs, t.bc_episodes, cfg.seed, gamma, cfg.workers, cfg.progress)
            new["success_rate"] = new.pop("expert_success_rate")
        else:
            beta = t.dagger_beta0 if k == 1 else 0.0
            new = collect_dagger(policy, net, cfg.sim, pairs, t.dagger_episodes, cfg.seed + 100_000 * k, beta, gamma,
                                 cfg.workers, cfg.progress, desc=f"teacher: DAgger {k}/{t.dagger_iterations}")
        collect_s = time.perf_counter() - t0
        rate = float(new.pop("success_rate"))
        data = new if data is None else {key: np.concatenate([data[key], new[key]]) for key in data}
        if k == 0:
            torch.manual_seed(cfg.seed)
            policy = build_policy("teacher", None, probe.observation_space, net).to(device)
        linear_fit = None
        if has_lookahead(policy):  # convex fit of the linear cost, then the MLP learns the rest
            cache = extend_feature_cache(cache, lookahead_feature_cache(policy, new, t.mirror))  # fit and cloning's
            linear_fit = fit_lookahead_linear(policy, data, t.soft_tau, seed=cfg.seed + k, mirror=t.mirror,
                                              cache=cache)
            log.info("teacher stage %d: linear cost fit on %d frames, cross-entropy %.3f -> %.3f", k,
                     linear_fit["frames"], linear_fit["ce_before"], linear_fit["ce_after"])
        rows = behaviour_clone(policy, data, t.bc_epochs if k == 0 else t.dagger_epochs,
                               lr=t.bc_lr if k == 0 else t.bc_lr / 2, seed=cfg.seed + k,
                               frozen=("features_extractor.lookahead.linear.",) if linear_fit else (), cache=cache, **clone)
        for r in rows:
            logger.add("teacher_bc" if k == 0 else f"teacher_dagger{k}", r["epoch"], bc_loss=r["bc_loss"],
                       accuracy=r["accuracy"], value_loss=r["value_loss"])
        stat = {"stage": k, "episodes": t.bc_episodes if k == 0 else t.dagger_episodes, "new_frames": len(new["action"]),
                "frames": int(len(data["action"])), "driver_success_rate": rate, "collect_s": round(collect_s, 1),
                "final": rows[-1], **({"linear_fit": linear_fit} if linear_fit else {})}
        logger.add("teacher_imitation", k, driver_success_rate=rate, frames=stat["frames"])
        sdir.mkdir(parents=True, exist_ok=True)
        atomic_save_npz(sdir / "data.npz", new)
        save_policy(sdir, policy, describe("teacher", None, probe.observation_space, net, imitation=stat,
                                           produced_by={"expert_frames": stat["frames"], "dagger_iterations": k}))

    cache = None  # the aggregate's features: not needed by what follows
    last = out / "imitation" / f"{t.dagger_iterations:02d}"
    if policy is None:
        policy, _ = load_policy(last)
    stats = [read_policy_json(out / "imitation" / f"{k:02d}")["imitation"] for k in range(t.dagger_iterations + 1)]
    summary["imitation"] = stats
    summary["bc"] = {"episodes": t.bc_episodes, "frames": stats[0]["new_frames"],
                     "expert_success_rate": stats[0]["driver_success_rate"], "final": stats[0]["final"]}
    imitation_frames = stats[-1]["frames"]
    ppo_steps = 0
    if t.ppo_steps > 0:
        torch.set_num_threads(1)  # the envs use the cores; the MLP update is small
        venv = make_vec_env(cfg.sim, pairs, t.n_envs, cfg.seed, t.subprocess)
        last = out / "ppo" / "last.zip"
        if last.exists():
            model = PPO.load(last, env=venv, device=device)
        else:
            model = PPO(policy_class("teacher", net), venv, policy_kwargs=policy_kwargs("teacher", None, net), seed=cfg.seed,
                        device=device, verbose=0, tensorboard_log=str(out / "tb"), **ppo_kwargs(t.ppo))
            model.policy.load_state_dict(policy.state_dict())
        attach_lookahead_cache(model)
        if t.critic_features == "detached":  # a hook, not a weight: set again on a resumed model
            detach_critic(model.policy)
        done = model.num_timesteps
        t0 = time.perf_counter()
        cb = [curriculum_callback(t.curriculum, t.ppo_steps), checkpoint_callback(out / "ppo", model, 20_000),
              progress_callback(t.ppo_steps, "teacher PPO", cfg.progress)]
        learn_with_critic_warmup(model, t.ppo_steps, t.critic_warmup_steps, cb, "ppo")
        summary["ppo_steps_per_s"] = round((model.num_timesteps - done) / max(time.perf_counter() - t0, 1e-9), 1)
        ppo_steps = int(model.num_timesteps)
        save_ppo(model, last)
        venv.close()
        policy = model.policy
    summary["ppo_steps"] = ppo_steps
    desc = describe("teacher", None, probe.observation_space, net, sim_scan_range_m=cfg.sim.scan_range_m,
                    produced_by={"expert_labelled_frames": imitation_frames, "dagger_iterations": t.dagger_iterations,
                                 "ppo_steps": ppo_steps,
                                 **({"ppo_critic_warmup_steps": min(t.critic_warmup_steps, ppo_steps),
                                     "ppo_critic_features": t.critic_features} if ppo_steps else {})})
    save_policy(out, policy, desc)
    return summary


def _load_aggregate(out: Path, k: int) -> dict[str, np.ndarray]:
    """The imitation data of stages 0 .. k-1 (each ``imitation/<j>/data.npz`` holds that stage's new frames)."""

    parts = []
    for j in range(k):
        path = out / "imitation" / f"{j:02d}" / "data.npz"
        try:
            with np.load(path) as z:
                parts.append({key: z[key] for key in z.files})
        except (OSError, ValueError, KeyError) as e:
            raise CorruptArtifactError(f"{path}: unreadable imitation data ({type(e).__name__}: {e}); delete "
                                       f"{path.parent} to redo that stage") from None
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}


# --------------------------------------------------------------------------------------------------------- student
def _train_student(cfg: TrainConfig, out: Path) -> dict[str, Any]:
    d = cfg.dagger
    logger = _Log(out)
    teacher_dir = policy_root(cfg) / "teacher"
    enc_dir = encoder_dir(cfg) if cfg.variant != "no_bev" else None
    encoder = load_student_encoder(cfg.variant, enc_dir, precision=cfg.encoder_precision)
    int_dir = intention_dir(cfg)
    forecaster = load_student_forecaster(cfg.variant, cfg.head, int_dir)
    env = CrowdNavEnv(config=replace(cfg.sim, scene=d.scenes[0], obs_mode="state"))
    env.reset(seed=0)
    observer = observer_for_env(env, cfg.variant, encoder, cfg.head, forecaster=forecaster, map_cost=cfg.map_cost,
                                map_heads=load_student_heads(cfg.variant, cfg.head, cfg.map_cost, enc_dir, encoder))
    space = observer.observation_space
    net = student_net(cfg, observer.grid)
    device = resolve_device(cfg.device, "train.device")
    extra = {"encoder": str(enc_dir) if enc_dir else None, "teacher": str(teacher_dir),
             **({"encoder_precision": resolve_encoder_precision(cfg.encoder_precision, "train.encoder_precision",
                                                                 device)} if enc_dir else {})}
    pairs = [(s, float(x)) for s in d.scenes for x in d.densities]
    n_rot = cfg.sim.robot.n_rotations  # yaw rates of the action grid (mirroring reverses them)
    torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    torch.manual_seed(cfg.seed)
    # the obstacle shield (net["shield_s"]) filters the saved policy's actions — DAgger rollouts, acceptance, eval,
    # PPO — but is not part of the distribution cloned from the teacher: a teacher action the student's perceived
    # scan rules out would be a loss term of up to 1,000 nats per metre that the bounded scorer can only fight
    policy = build_policy("student", cfg.variant, space, cloned_net(net)).to(device)
    inherited = has_lookahead(policy) and d.linear_cost != "fit"
    if inherited:
        inherit_linear_cost(policy, teacher_dir)
    iters: list[dict[str, Any]] = []
    frames_total = 0
    # the lookahead head's rollout features of the pool's frames (rl.teacher.lookahead_feature_cache): they depend
    # on the cached observation alone (the intention model's prediction is stored per frame), so each iteration
    # appends its new frames' to the earlier iterations' — bit for bit the whole pool's (as the teacher's stages do)
    cache: tuple[np.ndarray, np.ndarray | None] | None = None
    tune = cfg.intention_tune.epochs > 0 and int_dir is not None
    for k in range(d.iterations):
        it = out / "dagger" / f"iter_{k}"
        if (it / "done.json").exists():
            info = json.loads((it / "done.json").read_text())
            iters.append(info)
            frames_total = info["aggregate_frames"]
            policy, _ = load_policy(it / "policy", shield_s=0.0 if "shield_s" in net else None)  # as cloned
            policy.to(device)
            if tune and "skipped" not in info.get("intention_tune", {"skipped": ""}):
                int_dir = it / "intention"
                load_forecaster(int_dir)  # missing or corrupt: one error naming it (delete the iteration to redo it)
            continue
        beta = d.beta0 * d.beta_decay ** k
        student_dir = out / "dagger" / f"iter_{k - 1}" / "policy" if k > 0 else None
        jobs = [{"sim": cfg.sim, "scene": pairs[e % len(pairs)][0], "density": pairs[e % len(pairs)][1],
                 "seed": cfg.seed + 1000 * k + e, "variant": cfg.variant, "encoder": str(enc_dir) if enc_dir else None,
                 "teacher": str(teacher_dir), "student": str(student_dir) if student_dir else None, "beta": beta,
                 "iteration": k, "iter_dir": str(it), "mirror": d.mirror, "head": cfg.head, "device": str(device),
                 "map_cost": cfg.map_cost, "encoder_precision": cfg.encoder_precision,
                 "mlp_shield_s": cfg.mlp_shield_s,
                 "intention": str(int_dir) if int_dir else None}
                for e in range(d.episodes_per_iter)]
        ex = Executor.of(cfg)
        clock = PhaseClock()  # the iteration's parts (done.json "timing"; rl.dagger.throughput_table)
        resumed = (it / "episodes.jsonl").exists()  # some rollouts ran in an earlier invocation
        with clock("rollout"):
            rows = run_iteration(it, jobs, cfg.workers, cfg.progress, ex)
        with clock("export"):
            counts = export_iteration(it, f"icrowdnav/dagger_{cfg.variant}_iter{k}", cfg.progress, cfg.workers, ex)
        # the intention model on this student's rollouts so far, from the pretrained weights every time
        with clock("intention_tune"):
            tuned = _tune_intention(cfg, out, k, device) if tune else None
        if tuned and "skipped" not in tuned:
            int_dir = it / "intention"
        with clock("pool"):
            data, soft = _cloning_pool(out, k + 1, d)
            held = held_out_frames(_iter_dirs(out, k + 1), d.bc_holdout) if d.bc_max_epochs else None
            scored = newest_held_out(held, frames_total, d.bc_holdout_scope, f"student {cfg.variant} iteration {k}")
        with clock("clone"):  # the lookahead features, the linear fit, the cloning, and its losses
            # the newest iteration's frames: the pool's tail after the earlier iterations' frames_total (views)
            new = {key: v[frames_total:] for key, v in data.items()}
            if k == 0 and "bev" in space.spaces:
                policy.features_extractor.set_bev_stats(*bev_stats(data))
            before = bc_loss(policy, new)  # the hard-label loss (bc_loss reads costs only with soft_tau)
            if soft:
                soft_before = bc_loss(policy, new, soft_tau=d.soft_tau)
            # samples per epoch: the new frames' count, drawn from the pool ("new"), or the pool's cloned frames
            # ("pool": the default epoch); an adaptive budget's held-out frames are never drawn
            epoch = len(new["action"]) if d.bc_schedule == "new" else int(len(data["action"]) - (
                0 if held is None else held.sum()))
            if has_lookahead(policy):  # a resumed run computes the earlier iterations' features once, then appends
                cache = (lookahead_feature_cache(policy, data, d.mirror, n_rot) if cache is None
                         else extend_feature_cache(cache, lookahead_feature_cache(policy, new, d.mirror, n_rot)))
            hist, linear_fit = distill(policy, data, d, cfg.map_signs, cfg.seed + k, n_rot, inherited, soft,
                                       cfg.progress, f"student {cfg.variant} iteration {k}", epoch_size=epoch,
                                       cache=cache, held_out=held, scored=scored)
            clone_samples = len(hist) * epoch
            after = bc_loss(policy, new)
            n_actions = int(getattr(policy.action_space, "n", 0))  # the students' action grid (Discrete)
            # the MLP head's logits start near 0, so its loss starts at ln n; the lookahead head's scores are scaled
            # (rl.lookahead.SCORE_SCALE): its hard-label loss is not bounded by ln n (24-34 nats on a good student)
            warning = (None if has_lookahead(policy)
                       else near_uniform_warning(after, n_actions, f"student {cfg.variant} iteration {k}"))
            if warning:
                log.warning(warning)
            soft_ce = ({"soft_ce_new_before": soft_before,
                        "soft_ce_new_after": bc_loss(policy, new, soft_tau=d.soft_tau)} if soft else {})
        frames_total = int(len(data["action"]))
        for r in hist:  # (an iteration's epochs fill the steps k·E .. k·E + E-1, E its most epochs)
            logger.add("dagger_bc", k * max(d.bc_epochs, d.bc_max_epochs) + r["epoch"], bc_loss=r["bc_loss"],
                       accuracy=r["accuracy"], **({"held_out_loss": r["held_out_loss"]} if "held_out_loss" in r else {}))
        sr_rollout = float(np.mean([r["outcome"] == "success" for r in rows]))
        logger.add("dagger", k, rollout_success=sr_rollout, bc_loss_new_before=before, bc_loss_new_after=after,
                   aggregate_frames=frames_total, **soft_ce)
        info = {"iteration": k, "beta": beta, "episodes": len(rows), "frames": int(len(new["action"])),
                "aggregate_frames": frames_total, "rollout_success_rate": sr_rollout,
                "student_steps": int(sum(r["student_steps"] for r in rows)),
                "bc_loss_new_before": before, "bc_loss_new_after": after, "final_accuracy": hist[-1]["accuracy"],
                **({"uniform_loss": math.log(n_actions)} if n_actions > 1 else {}),
                "clone_samples": clone_samples, **adaptive_record(hist, held, scored),
                **({"pool_held_out_loss": bc_loss(policy, held_out_set(policy, data, held, soft),
                                                  soft_tau=d.soft_tau if soft else 0.0)}
                   if scored is not None else {}),
                "dataset": str(it / "dataset"), "dataset_frames": counts["frames"], **soft_ce,
                **({"linear_fit": linear_fit} if linear_fit else {}), **({"intention_tune": tuned} if tuned else {}),
                "timing": iteration_timing(clock.seconds, rows, int(len(new["action"])), resumed)}
        save_policy(it / "policy", policy, describe("student", cfg.variant, space, net, **extra,
                                                    intention=str(int_dir) if int_dir else None,
                                                    produced_by={"dagger_iterations": k + 1,
                                                                 "dagger_frames": frames_total}))
        write_done(it, info)
        iters.append(info)
        del data, new
    summary: dict[str, Any] = {"dagger": iters}
    if d.final_clone:
        policy, summary["final_clone"] = _final_clone(cfg, out, space, net, teacher_dir, n_rot, device, frames_total,
                                                      extra, int_dir, cache)
    # provenance paths, like policy.json's checkpoint references, relative to the checkpoint (rl.policy)
    produced = {"teacher": relative_to(teacher_dir, out), "dagger_iterations": d.iterations,
                "dagger_frames": frames_total, "dagger_bc_schedule": d.bc_schedule, "ppo_finetune_steps": 0,
                "bc_precision": resolve_precision(d.bc_precision, device, "train.dagger.bc_precision")}
    if d.bc_max_epochs:
        produced["dagger_bc_adaptive"] = {"min_epochs": d.bc_epochs, "max_epochs": d.bc_max_epochs,
                                          "patience": d.bc_patience, "holdout": d.bc_holdout,
                                          "holdout_scope": d.bc_holdout_scope}
    if d.final_clone:
        produced["dagger_final_clone"] = {k: summary["final_clone"][k] for k in ("frames", "clone_samples", "seed",
                                                                               "kept") if k in summary["final_clone"]}
    produced["intention"] = (None if int_dir is None else "frozen" if int_dir == intention_dir(cfg)
                             else {"tuned": relative_to(int_dir, out), "epochs": cfg.intention_tune.epochs})
    if cfg.finetune.ppo_steps > 0:
        policy, steps, rate = _finetune(cfg, out, policy, net, pairs, enc_dir, device, int_dir)
        produced["ppo_finetune_steps"] = steps
        produced["ppo_critic_warmup_steps"] = min(cfg.finetune.critic_warmup_steps, steps)
        produced["ppo_critic_features"] = cfg.finetune.critic_features
        produced["ppo_sampling_temperature"] = cfg.finetune.sampling_temperature
        summary["finetune"] = {"steps": steps, "steps_per_s": rate}
    save_policy(out, policy, describe("student", cfg.variant, space, net, **extra,
                                      intention=str(int_dir) if int_dir else None, produced_by=produced))
    return summary


def _iter_dirs(out: Path, n_iters: int) -> list[Path]:
    return [out / "dagger" / f"iter_{j}" for j in range(n_iters)]


def newest_held_out(held: np.ndarray | None, start: int, scope: str, label: str) -> np.ndarray | None:
    """With ``dagger.bc_holdout_scope`` "new", the held-out frames that decide an iteration's stop: those of ``held``
    from frame ``start`` on (the newest iteration's episodes). None — the whole of ``held`` decides — for "pool",
    without a budget, or where the newest iteration has no held-out episode (said in the log)."""
    if held is None or scope != "new":
        return None
    scored = held.copy()
    scored[:start] = False
    if not scored.any():
        log.info("%s: no held-out episode among the newest frames; the pool's held-out episodes decide", label)
        return None
    return scored


def adaptive_record(hist: list[dict[str, float]], held: np.ndarray | None,
                    scored: np.ndarray | None = None) -> dict[str, Any]:
    """What an adaptive cloning (``dagger.bc_max_epochs``) records in ``done.json``: the epochs it ran, the epoch
    whose weights it kept, that epoch's held-out loss, the held-out frames that decided (``scored``, the newest
    iteration's, else all of ``held``) and which (``held_out_scope``); nothing without a budget; a pool of one episode
    holds none out and is cloned ``bc_epochs``."""
    if held is None:
        return {}
    if not held.any():  # a pool of one episode: nothing to hold out, the fixed budget
        return {"clone_epochs": len(hist), "held_out_frames": 0}
    best = next(r for r in hist if r["best"])
    return {"clone_epochs": len(hist), "best_epoch": int(best["epoch"]), "held_out_loss": best["held_out_loss"],
            "held_out_frames": int((held if scored is None else scored).sum()),
            "held_out_scope": "pool" if scored is None else "new"}


def _cloning_pool(out: Path, n_iters: int, d: DaggerConfig) -> tuple[dict[str, np.ndarray], bool]:
    """The cached frames of DAgger iterations 0 .. n_iters-1 as one pool (rl.dagger.load_features), and whether the
    cloning is soft: every episode has the teacher's logits (the pool keeps only keys all episodes hold), turned into
    ``costs`` — softmin(-logits / τ) is the teacher's distribution softmax(logits / τ)."""
    data = load_features(_iter_dirs(out, n_iters), memory_gb=d.pool_memory_gb, scratch=out / "dagger")
    soft = d.soft_tau > 0 and "teacher_logits" in data
    if soft:
        data["costs"] = -data.pop("teacher_logits")
    return data, soft


def fresh_student(cfg: TrainConfig, space, net: dict[str, Any], teacher_dir: Path, data: dict[str, np.ndarray],
                  seed: int):
    """A new student of ``cfg``'s variant and head (seeded weights; the lookahead head inherits its teacher's linear
    cost unless ``dagger.linear_cost`` fits it), its BEV normalisation from ``data``. Returns (policy, inherited).
    Used by the final cloning of a DAgger run and by ``rl.data_scale``."""
    torch.manual_seed(seed)
    policy = build_policy("student", cfg.variant, space, cloned_net(net))
    inherited = has_lookahead(policy) and cfg.dagger.linear_cost != "fit"
    if inherited:
        inherit_linear_cost(policy, teacher_dir)
    if "bev" in space.spaces:
        policy.features_extractor.set_bev_stats(*bev_stats(data))
    return policy, inherited


def _final_clone(cfg: TrainConfig, out: Path, space, net: dict[str, Any], teacher_dir: Path, n_rot: int,
                 device: torch.device, frames_total: int, extra: dict[str, Any], int_dir: Path | None,
                 cache: tuple[np.ndarray, np.ndarray | None] | None = None):
    """``dagger.final_clone``: a fresh student cloned ``bc_epochs`` over every iteration's frames, saved in
    ``dagger/final/`` (its ``done.json`` last, so a resumed run loads it instead of cloning again). With the adaptive
    budget (``dagger.bc_max_epochs``) the held-out episodes choose: the fresh student is kept only where its held-out
    loss is below the last iteration's student's, else that student is (``done.json`` ``kept``; a fresh cloning can
    stay on the MLP head's early plateau — the sixth chain's adaptive `full`, 4.08 nats against 3.12 — so one left
    near ln n is first cloned once more from the next seed, ``other_cloning`` recording the one not kept). ``cache``: the
    pool's lookahead features when the iterations' loop computed them (all its frames: the last iteration's pool is
    every iteration's; the fresh student's are the same, they have no weights)."""
    d = cfg.dagger
    fin = out / "dagger" / "final"
    shield = 0.0 if "shield_s" in net else None
    if (fin / "done.json").exists():
        policy, _ = load_policy(fin / "policy", shield_s=shield)
        return policy.to(device), json.loads((fin / "done.json").read_text())
    clock = PhaseClock()
    with clock("pool"):
        data, soft = _cloning_pool(out, d.iterations, d)
        held = held_out_frames(_iter_dirs(out, d.iterations), d.bc_holdout) if d.bc_max_epochs else None
    if len(data["action"]) != frames_total:  # before the cloning, not after it
        raise CorruptArtifactError(f"{out / 'dagger'}: the iterations' features hold {len(data['action'])} frames, "
                                   f"their done.json files {frames_total}; delete {fin} and the damaged iteration to "
                                   "redo them")
    with clock("clone"):
        def clone(seed: int, label: str):  # a fresh student cloned on the pool: (policy, epochs, its record)
            fresh, inherited = fresh_student(cfg, space, net, teacher_dir, data, seed)
            fresh.to(device)
            rows, _ = distill(fresh, data, d, cfg.map_signs, seed, n_rot, inherited, soft, cfg.progress,
                              f"student {cfg.variant} {label}", cache=cache, held_out=held)
            return fresh, rows, adaptive_record(rows, held)

        seed = cfg.seed + d.iterations
        policy, hist, record = clone(seed, "final cloning")
        n_actions = int(getattr(policy.action_space, "n", 0))
        floor = plateau_floor(policy)
        restarted = None
        # with the adaptive budget, an MLP-head cloning whose best held-out loss is still near a uniform choice sat
        # on the head's early plateau — a draw of its initialisation (chain 6's adaptive `full`: seed 8 stayed at
        # 4.08-4.22 nats on two pools, seed 9 left it, 3.21): cloned once more from the next seed, the better kept
        if "held_out_loss" in record and floor is not None and record["held_out_loss"] > floor:
            log.warning("student %s final cloning: held-out loss %.3f is near a uniform choice (%.3f): cloned again "
                        "from seed %d", cfg.variant, record["held_out_loss"], math.log(n_actions), seed + 1)
            first, second = (policy, hist, record, seed), (*clone(seed + 1, "final cloning, again"), seed + 1)
            kept, other = (second, first) if second[2]["held_out_loss"] < record["held_out_loss"] else (first, second)
            policy, hist, record, seed = kept
            restarted = {"seed": other[3], "held_out_loss": other[2]["held_out_loss"], "clone_epochs": len(other[1])}
    cloned = frames_total - (0 if held is None else int(held.sum()))
    info = {"frames": frames_total, "clone_samples": len(hist) * cloned, "seed": seed,
            "final_bc_loss": hist[-1]["bc_loss"], **record, "seconds": clock.seconds,
            **({"other_cloning": restarted} if restarted else {})}
    warning = (None if has_lookahead(policy)
               else near_uniform_warning(hist[-1]["bc_loss"], n_actions, f"student {cfg.variant} final cloning"))
    if warning:
        log.warning(warning)
    kept = "fresh"
    if "held_out_loss" in info:  # the adaptive budget's held-out episodes choose between it and the last iteration's
        last, _ = load_policy(out / "dagger" / f"iter_{d.iterations - 1}" / "policy", shield_s=shield)
        last.to(device)
        info["last_iteration_held_out_loss"] = bc_loss(last, held_out_set(last, data, held, soft),
                                                       soft_tau=d.soft_tau if soft else 0.0)
        if not info["held_out_loss"] < info["last_iteration_held_out_loss"]:
            kept, policy = "last_iteration", last
            log.warning("student %s final cloning: its held-out loss %.3f is not below the last iteration's student's "
                        "%.3f; that student is kept", cfg.variant, info["held_out_loss"],
                        info["last_iteration_held_out_loss"])
    info["kept"] = kept
    save_policy(fin / "policy", policy, describe("student", cfg.variant, space, net, **extra,
                                                 intention=str(int_dir) if int_dir else None,
                                                 produced_by={"dagger_iterations": d.iterations,
                                                              "dagger_frames": frames_total, "final_clone": True,
                                                              "final_clone_kept": kept}))
    write_done(fin, info)
    return policy, info


def plateau_floor(policy) -> float | None:
    """The held-out loss above which an MLP-head cloning still sits on its early plateau near a uniform choice,
    ``NEAR_UNIFORM · ln n`` (n actions): it does not stop there, and a fresh final cloning left there is cloned again.
    None for the lookahead head (its scores are not bounded by ln n) or a grid of fewer than two actions."""
    n_actions = int(getattr(policy.action_space, "n", 0))
    return None if has_lookahead(policy) or n_actions < 2 else NEAR_UNIFORM * math.log(n_actions)


def held_out_set(policy, data: dict[str, np.ndarray], held: np.ndarray, soft: bool) -> dict[str, np.ndarray]:
    """Copies of what :func:`rl.teacher.bc_loss` reads of the held-out frames ``held`` (a per-frame mask of
    ``data``): the policy's observation keys, the action, and the teacher's costs when the cloning is ``soft``."""
    keys = (*policy.observation_space.spaces, "action", *(("costs",) if soft else ()))
    return {k: data[k][held] for k in keys}


def distill(policy, data: dict[str, np.ndarray], d: DaggerConfig, map_signs: str, seed: int, n_rot: int,
            inherited: bool, soft: bool, progress: bool = True, label: str = "student",
            epoch_size: int | None = None, cache: tuple[np.ndarray, np.ndarray | None] | None = None,
            held_out: np.ndarray | None = None,
            scored: np.ndarray | None = None) -> tuple[list[dict[str, float]], dict[str, Any] | None]:
    """One cloning of a student on ``data`` (the aggregate of DAgger frames, ``costs`` = the teacher's negated logits
    when ``soft``): for the lookahead head its rollout features once, the convex fit of the linear cost terms
    ``d.linear_cost`` names (the map cost on top of an ``inherited`` teacher cost by default), then
    :func:`behaviour_clone` of every other weight (``epoch_size`` samples per epoch: all of ``data`` by default).
    ``cache``: :func:`rl.teacher.lookahead_feature_cache` of ``data`` when the caller has it (computed here
    otherwise). ``held_out`` (per frame, with ``d.bc_max_epochs``): the frames of the adaptive budget's held-out
    episodes — neither the linear fit nor the cloning sees them, the cloning stops on its loss over them (over
    ``scored`` instead where given: a subset of them, :func:`newest_held_out`). Returns the
    cloning's per-epoch rows and the linear fit's record (None without one). Used by every DAgger iteration and by
    ``rl.data_scale``."""
    linear_fit = None
    adaptive = {}
    if held_out is not None and held_out.any() and d.bc_max_epochs:
        adaptive = {"indices": np.flatnonzero(~held_out), "max_epochs": d.bc_max_epochs, "patience": d.bc_patience,
                    "held_out": held_out_set(policy, data, held_out if scored is None else scored, soft),
                    # the MLP head's plateau near ln n is not an end (the lookahead head's scores are not bounded so)
                    "floor": plateau_floor(policy)}
    if has_lookahead(policy):  # rollout features once; the linear cost by convex regression, then the rest
        if cache is None:
            cache = lookahead_feature_cache(policy, data, d.mirror, n_rot)
        elif len(cache[0]) != len(data["action"]) or (cache[1] is None) == d.mirror:
            raise ValueError(f"distill: the feature cache holds {len(cache[0])} frames "
                             f"({'with' if cache[1] is not None else 'without'} mirrored ones), the pool "
                             f"{len(data['action'])} (mirror {d.mirror})")
        map_head = policy.features_extractor.lookahead.n_map > 0
        terms, fitted = LINEAR_COSTS[d.linear_cost]
        if soft and (terms != "map" or map_head):  # the map cost is fitted on top of an inherited linear cost
            fit_data, fit_cache = data, cache
            if adaptive:  # copies of the cloned frames (the lookahead pools are small)
                fit_data = {k: v[adaptive["indices"]] for k, v in data.items()}
                fit_cache = (cache[0][adaptive["indices"]],
                             None if cache[1] is None else cache[1][adaptive["indices"]])
            linear_fit = fit_lookahead_linear(policy, fit_data, d.soft_tau, seed=seed, mirror=d.mirror,
                                              n_rot=n_rot, cache=fit_cache, terms=terms, map_signs=map_signs)
            log.info("%s: %s cost fit on %d frames, cross-entropy %.3f -> %.3f%s%s%s",
                     label, fitted, linear_fit["frames"], linear_fit["ce_before"], linear_fit["ce_after"],
                     f", pedestrian weights {[linear_fit['linear_weights'][n] for n in PED_NAMES]}"
                     if terms == "peds" else "",
                     f", map weights {linear_fit['map_weights']}" if map_head else "",
                     f", pinned at 0: {linear_fit['map_pinned']}" if "map_pinned" in linear_fit else "")
    hist = behaviour_clone(policy, data, d.bc_epochs, d.bc_batch, d.bc_lr, seed, progress=progress,
                           soft_tau=d.soft_tau if soft else 0.0, mirror=d.mirror, n_rot=n_rot,
                           frozen=FITTED_PREFIXES if (linear_fit or inherited) else (), cache=cache,
                           precision=resolve_precision(d.bc_precision, policy.device, "train.dagger.bc_precision"),
                           epoch_size=epoch_size, **adaptive)
    return hist, linear_fit


def _tune_intention(cfg: TrainConfig, out: Path, k: int, device: torch.device) -> dict[str, Any]:
    """The pretrained intention model fine-tuned on DAgger iterations 0..k (``iter_k/intention``) with its held-out
    errors; ``{"skipped": why}`` when the rollouts so far hold no training and validation episode with a tracked
    person (the iteration keeps the model it had)."""
    tc = cfg.intention_tune
    roots = [out / "dagger" / f"iter_{j}" / "dataset" for j in range(k + 1)]
    try:
        tuned = finetune_forecaster(intention_dir(cfg), roots, out / "dagger" / f"iter_{k}" / "intention",
                                    FitOptions(tc.epochs, tc.batch, tc.lr, tc.pose_dropout, tc.head_aux_weight,
                                               cfg.seed + k), tc.val_fraction, device)
    except InputMissingError as e:
        log.warning("student %s iteration %d: intention model not fine-tuned: %s", cfg.variant, k, e)
        return {"skipped": str(e)}
    v = tuned["val"]
    log.info("student %s iteration %d: intention model fine-tuned on %d samples, held-out FDE@1 s %.3f -> %.3f m "
             "(turns %s -> %s m)", cfg.variant, k, tuned["train_samples"], v["pretrained"]["fde_1s_m"],
             v["tuned"]["fde_1s_m"], v["pretrained"]["fde_1s_turns_m"], v["tuned"]["fde_1s_turns_m"])
    return tuned


def inherit_linear_cost(policy, teacher_dir: Path) -> None:
    """Copies the lookahead teacher's linear cost into a student's lookahead head (the same rollout features, here of
    the perceived tracks and scan) and zeroes the MLP scorer's output layer, so the student starts as the teacher's
    cost over what it perceives and cloning learns corrections on top."""

    teacher, _ = load_policy(teacher_dir)
    src, dst = getattr(teacher.features_extractor, "lookahead", None), policy.features_extractor.lookahead
    if src is None or src.linear.weight.shape != dst.linear.weight.shape:
        raise ConfigError(f"dagger.linear_cost 'teacher' needs a lookahead teacher ({teacher_dir} has "
                          f"{type(teacher.features_extractor).__name__}); use dagger.linear_cost fit")
    with torch.no_grad():
        dst.linear.load_state_dict(src.linear.state_dict())
        dst.scorer[-1].weight.zero_()
        dst.scorer[-1].bias.zero_()


def student_net(cfg: TrainConfig, grid: BEVGrid) -> dict[str, Any]:
    """The student's network description (saved in policy.json): ``cfg.net``, the head and, for the lookahead head,
    what its rollouts need from the simulator (robot limits and radius, control period, scan range) and, with
    ``map_cost``, the extent of the occupancy map it samples (``grid``: the observer's BEV grid); for the MLP head
    with ``mlp_shield_s`` that shield's horizon (``shield_s``)."""
    from dataclasses import asdict

    net = {**cfg.net, "head": cfg.head}
    if cfg.head == "lookahead":
        net.update({"robot": asdict(cfg.sim.robot), "dt_s": cfg.sim.dt_s, "scan_range_m": cfg.sim.scan_range_m,
                    "scorer_bound": cfg.scorer_bound, "heading": teacher_heading(policy_root(cfg) / "teacher")})
        if cfg.shield_s:
            net["shield_s"] = cfg.shield_s
        if cfg.map_cost:
            net.update({"map_cost": True, "map_bounds": [list(map(float, b[:2])) for b in (grid.x_bound, grid.y_bound)]})
            if cfg.map_view:
                net["map_view_deg"] = abs(float(cfg.sim.camera.yaw_deg)) + float(cfg.sim.camera.hfov_deg) / 2.0
    elif cfg.mlp_shield_s:  # the MLP head's shield acts in rl.driver.PolicyDriver and the DAgger rollouts
        net["shield_s"] = cfg.mlp_shield_s
    return net


def cloned_net(net: dict[str, Any]) -> dict[str, Any]:
    """``net`` without the obstacle shield: the network whose action distribution DAgger clones (the shield has no
    weights; the saved policy.json keeps it, so everything that loads the checkpoint acts shielded)."""
    return {k: v for k, v in net.items() if k != "shield_s"}


def teacher_heading(teacher_dir: Path) -> str:
    """The heading error mode of a lookahead teacher's rollout features (``rl.lookahead.LookaheadHead``; checkpoints
    from before the option have ``"end"``): a student's lookahead head computes its features the same way, so the
    teacher's linear cost it inherits means the same thing."""

    if not (teacher_dir / "policy.json").exists():
        return "end"
    return str(read_policy_json(teacher_dir)["net"].get("heading", "end"))


def _finetune(cfg: TrainConfig, out: Path, policy, net: dict[str, Any], pairs, enc_dir, device: torch.device,
              int_dir: Path | None):
    """PPO on the student (rendered envs, the paper's reward), starting from the distilled policy; the updates and
    each env's frozen encoder on ``device`` (env subprocesses spawned for CUDA); ``int_dir`` the intention model the
    DAgger loop ended with."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecMonitor

    f = cfg.finetune
    sim, variant, head, dev, map_cost = cfg.sim, cfg.variant, cfg.head, str(device), cfg.map_cost
    precision = cfg.encoder_precision

    def make():  # captures plain values only: pickled into spawned subprocesses
        return StudentEnv(SceneMixEnv(sim, pairs, obs_mode="visual"), variant, enc_dir, head=head, device=dev,
                          intention_ckpt=int_dir, map_cost=map_cost, encoder_precision=precision)

    venv = (SubprocVecEnv([make] * f.n_envs, start_method=start_method(device)) if f.n_envs > 1
            else DummyVecEnv([make]))
    venv = VecMonitor(venv)  # episode returns and lengths: tb/finetune_*'s rollout/ep_rew_mean, ep_len_mean
    venv.seed(cfg.seed + 77)
    last = out / "ppo" / "last.zip"
    if last.exists():
        model = PPO.load(last, env=venv, device=device)
    else:
        model = PPO(policy_class("student", net), venv, policy_kwargs=policy_kwargs("student", cfg.variant, net),
                    seed=cfg.seed, device=device, verbose=0, tensorboard_log=str(out / "tb"), **ppo_kwargs(f.ppo))
        model.policy.load_state_dict(policy.state_dict())
    if f.critic_features == "detached":  # a hook, not a weight: set again on a resumed model
        detach_critic(model.policy)
    set_sampling_temperature(model.policy, f.sampling_temperature)  # likewise
    done = model.num_timesteps
    t0 = time.perf_counter()
    learn_with_critic_warmup(model, f.ppo_steps, f.critic_warmup_steps, tb_log_name="finetune",
                             callback=[checkpoint_callback(out / "ppo", model, f.checkpoint_steps),
                                       progress_callback(f.ppo_steps, "student PPO", cfg.progress)])
    rate = round((model.num_timesteps - done) / max(time.perf_counter() - t0, 1e-9), 2)
    save_ppo(model, last)
    venv.close()
    model.policy.set_training_mode(False)
    set_sampling_temperature(model.policy, 1.0)  # the policy returned acts as the one saved (and loaded) does
    return model.policy, int(model.num_timesteps), rate


# -------------------------------------------------------------------------------------------------------- the stage
def learning_curve(cfg: TrainConfig, points: list[tuple[int, str, Path]], final_budget: dict[str, Any],
                   final_acc: dict[str, Any]) -> list[dict[str, Any]]:
    """The acceptance table at every learning-curve point (:func:`rl.baselines.common.curve_points`), then the
    final checkpoint's (already run: ``final_acc``, at ``final_budget[unit]``), each with its pooled SR."""
    def row(budget: int, unit: str, table: dict[str, Any]) -> dict[str, Any]:
        n = sum(r["n"] for r in table.values())
        return {"budget": budget, "unit": unit, "pooled_sr": sum(r["sr"] * r["n"] for r in table.values()) / n,
                "table": table}

    rows = [row(b, unit, _acceptance(cfg, d, f"{cfg.variant}@{b}")["table"]) for b, unit, d in points]
    unit = points[-1][1]
    final = int(final_budget.get(unit, -1))
    if final > points[-1][0]:
        rows.append(row(final, unit, final_acc["table"]))
    return rows


def body(cfg: TrainConfig, out: Path) -> dict[str, Any]:
    dump_yaml(cfg, out / "config.yaml")
    t0 = time.perf_counter()
    if cfg.variant == "teacher":
        summary = _train_teacher(cfg, out)
    elif cfg.variant in BASELINES:
        summary = baseline_module(cfg.variant).train(cfg, out, _Log(out))
    else:
        summary = _train_student(cfg, out)
    train_s = time.perf_counter() - t0
    method = "teacher" if cfg.variant == "teacher" else cfg.variant
    acc = _acceptance(cfg, out, method)
    used = device_counts(resolve_device(cfg.device, "train.device"))
    metrics = {"variant": cfg.variant, "train_seconds": round(train_s, 1), **used, **summary,
               "acceptance": {k: v for k, v in acc.items() if k != "episodes"}}
    if cfg.variant == "teacher" and summary.get("ppo_steps", 0) > 0:
        # the same episodes for the imitation policy before PPO: does PPO help? (reported, never hidden)
        pre = _acceptance(cfg, out / "imitation" / f"{cfg.teacher.dagger_iterations:02d}", "teacher_imitation")
        metrics["acceptance_before_ppo"] = {k: v for k, v in pre.items() if k != "episodes"}
    points = curve_points(out)
    if points:  # a baseline trained with a learning curve: the same acceptance episodes at every saved budget
        metrics["learning_curve"] = learning_curve(cfg, points, summary.get("budget", {}), acc)
        plot_learning_curve(metrics["learning_curve"], out / "learning_curve.png", cfg.variant)
    atomic_write_json(out / "metrics.json", metrics)
    write_acceptance(out, acc)
    plot_training(out / "train_log.csv", out / "curves.png", cfg.variant)
    counts: dict[str, Any] = {"train_seconds": round(train_s, 1), **used}
    for cell, row in acc["table"].items():
        counts[f"sr_{cell}"] = round(row["sr"], 3)
    return counts
