"""DRL-VO (Xie & Dames, "DRL-VO: Learning to Navigate Through Crowded Dynamic Scenes Using Velocity Obstacles",
IEEE T-RO 2023; code: github.com/TempleRAIL/drl_vo_nav), rebuilt for our simulator.

**What it observes** (built from the ``env`` object each step, never from the ``obs`` dict), in the robot frame
(x forward, y left):

* the *pedestrian kinematic map* — ``2 x 80 x 80`` (vx, vy in m/s), 0.125 m cells over x ∈ [0, 10] m,
  y ∈ [−5, 5] m (row = ⌊x / 0.125⌋, column = ⌊(5 − y) / 0.125⌋, the original's extent and resolution): each
  tracked pedestrian writes its robot-frame velocity into the cell of its centre. Tracks are a *perfect tracker*:
  true positions and velocities of every pedestrian within ``tracker_range_m`` (12 m: the whole map and the 7 m
  velocity-obstacle range), without occlusion — as the original's simulation training read pedsim's ground truth.
  The observation carries the tracks inside the map (``peds``: K x 5 [x, y, vx, vy, present]); the network
  scatters them into the map (:func:`kinematic_map`, one implementation for training, driving and the tests).
* the *lidar history map* — the last 10 scans (1 s at 10 Hz, as the original) of a 180° lidar with 720 beams
  (0.25°, the original's Hokuyo slice) and 30 m range that sees obstacles and pedestrian bodies
  (:func:`rl.baselines.common.lidar_scan`, ~0.7 ms a scan); each scan is min- and average-pooled over 9-beam bins
  into two 80-vectors (``scan``: 20 x 80, oldest first), tiled 4 times into an 80 x 80 map by the network.
* the *sub-goal* — the pure-pursuit point 2 m ahead on the global shortest path on the static map
  (:class:`sim.planners.global_path.GlobalPath`), robot frame (m). A waypoint (long-horizon runs) replaces the goal as
  the path's target.

Inputs are scaled as the original's MaxAbsScaler: velocities / 2 m/s, sub-goal / 2 m, ranges to [−1, 1] over 30 m.

**Network** (:class:`DRLVOExtractor`, an SB3 features extractor): the original's early-fusion ResNet — the lidar map
and the kinematic map stacked as 3 channels; stem conv 3x3 + max-pool; 2 bottlenecks (expansion 2); a stride-2
bottleneck and a 1x1-3x3-1x1 block with a stride-2 shortcut from the first stage; a stride-2 bottleneck and a
1x1-3x3-1x1 block with a stride-4 shortcut from the stem; global average pool; the sub-goal concatenated; FC 256 +
ReLU. Heads as the original: policy MLP [256], value MLP [128], a diagonal Gaussian over the normalised (v, ω)
(SB3 PPO). Our sizes (default ``width`` 16): channels 16 → 32 → 64 → 128 over 20 → 10 → 5 cells, 0.19 M
parameters in the extractor.

**Reward** (:func:`reward_terms`, in :class:`DRLVOEnv`, the original's terms and constants):
``r = r_g + r_c + r_w + r_t`` with r_g = +20 at the goal, −20 on a timeout, else 3.2 · (progress toward the goal,
m); r_c = −20 on a collision, else −0.2 · (0.9 − d_scan) when the nearest lidar return d_scan < 3 ρ_robot = 0.9 m;
r_w = −0.1 |ω| when |ω| > 1 rad/s; r_t = 0.6 · (π/6 − |θ_vo|), where θ_vo is the heading closest to the sub-goal
direction whose velocity (the robot's current speed along it) lies outside the velocity obstacle — the cone of
half-angle asin(3 ρ_robot / d) toward each pedestrian within 7 m, relative to its velocity — of every
pedestrian (π/2 if none is free; the sub-goal direction when no pedestrian is within 7 m) (:func:`vo_heading`).

**Training** (:func:`train`, on the training scenes of the teacher's curriculum only): a behaviour-cloning warm start
on the privileged expert's episodes (as many as the teacher's ``bc_episodes`` by default; Gaussian
log-likelihood of the expert's action + value regression on the discounted DRL-VO returns), then SB3 PPO with
continuous actions and the DRL-VO reward on vectorised envs (both cores), the teacher's curriculum of (scene,
density) pools, resumable from ``ppo/last.zip``. Output (``out``)::

    policy.safetensors, policy.json   the final policy (rl.baselines.common.save_baseline)
    bc/data.npz                       the expert episodes as DRL-VO observations (+ actions, returns)
    bc/policy.*                       the warm-started policy (a resumed run skips the cloning)
    ppo/last.zip                      SB3 checkpoint for --resume

**Deviations from the original, and why**

* Warm start by behaviour cloning on the privileged expert, then PPO on the default profile's budget (15 cloning
  epochs, 16,384 PPO env steps: about 10 minutes on a 2-core CPU, :class:`Config`) — the original trains PPO on
  ~2 M Gazebo steps (from a pre-trained model); the warm start makes the budget comparable with our teacher's (the
  same expert episodes). The PPO settings are the original's fine-tuning ones (lr 5e-5, batch 128) with 4 epochs
  instead of 10 (the CNN update dominates the wall time).
* The network is narrower and downsamples earlier: base width 16 instead of 64, and a stride-2 stem conv + stride-2
  max-pool (the standard ResNet stem) instead of stride 1 + stride 1 — the original runs its first stage at
  80 x 80 with 64-256 channels (~2 GMAC a sample, ~0.7 s per sample for a PPO update on our CPU). Every input cell
  is still seen (kernel ≥ stride).
* GroupNorm (8 channels a group) instead of BatchNorm: SB3 PPO evaluates the rollout's log-probabilities in eval mode
  and the update's in train mode, which BatchNorm makes disagree (a biased ratio); GroupNorm has no mode.
* PPO starts with a critic warm-up (``critic_warmup_steps`` = 4096: only the value head learns, the actor is
  frozen) and ``target_kl`` 0.02: without them, PPO straight after cloning destroyed the cloned policy (the cloned
  critic steered the first updates; measured: docs/notes/2026-11-drl-vo-ppo-after-cloning.md).
* The velocity-obstacle heading search uses 60 headings evenly spaced from the sub-goal direction instead of 60
  uniform random samples (same resolution; the reward is deterministic and exact when the sub-goal direction is
  free); angles are compared modulo 2π (the original's unwrapped comparison misses cones across ±π); the cone of a
  pedestrian closer than 3 ρ_robot is the half plane (the original's square root is NaN there, i.e. never
  blocked).
* r_g rewards per-step progress (the paper's equation; the code compares with the distance 10 control steps
  earlier). Collisions are the env's (footprints touch; the original counted lidar returns ≤ ρ_robot with a bumper
  tolerance). The robot's limits are ours (v ≤ 1 m/s instead of the Turtlebot's 0.5, |ω| ≤ 2 rad/s), the episode
  limit is the env's ``max_episode_s``.
* Value targets of the cloned episodes: the DRL-VO return of each expert step, the final step's small shaping terms
  replaced by its terminal reward (±20) since no observation follows it.

**Layout**: :mod:`~rl.baselines.drl_vo.configuration` (options, reward constants, map sizes),
:mod:`~rl.baselines.drl_vo.observation` (the observer and the kinematic map), :mod:`~rl.baselines.drl_vo.rewards`
(the reward and the velocity-obstacle heading), :mod:`~rl.baselines.drl_vo.model` (the network),
:mod:`~rl.baselines.drl_vo.training` (expert data, cloning, PPO), :mod:`~rl.baselines.drl_vo.driver` (the benchmark
driver).
"""

from rl.baselines.drl_vo.configuration import (
    GOAL_SCALE_M,
    HISTORY,
    MAP_CELLS,
    MAP_EXTENT_M,
    MAP_RES_M,
    NAME,
    PED_SLOTS,
    SPEED_SCALE_MPS,
    Config,
    RewardConfig,
)
from rl.baselines.drl_vo.driver import Driver

# DRLVOExtractor stays importable from here: SB3 checkpoints (ppo/last.zip) written before the package split pickle
# the extractor class as rl.baselines.drl_vo.DRLVOExtractor.
from rl.baselines.drl_vo.model import DRLVOExtractor, build_policy, describe_inputs, policy_kwargs
from rl.baselines.drl_vo.observation import Observer, kinematic_map, observation_space, pool_scans
from rl.baselines.drl_vo.rewards import reward_terms, vo_heading
from rl.baselines.drl_vo.training import DRLVOEnv, inputs, train

__all__ = [
    "GOAL_SCALE_M", "HISTORY", "MAP_CELLS", "MAP_EXTENT_M", "MAP_RES_M", "NAME", "PED_SLOTS", "SPEED_SCALE_MPS",
    "Config", "DRLVOEnv", "DRLVOExtractor", "Driver", "Observer", "RewardConfig", "build_policy", "describe_inputs",
    "inputs", "kinematic_map", "observation_space", "policy_kwargs", "pool_scans", "reward_terms", "train",
    "vo_heading",
]
