"""SARL*-OM: SARL's attention value network + a local occupancy map of static obstacles + danger-zone reward.

The paper's SARL*-OM baseline combines three works; this package reproduces each part in our simulator:

* **SARL** (Chen, Liu, Kreiss, Alahi, "Crowd-Robot Interaction: Crowd-aware Robot Navigation with Attention-based
  Deep Reinforcement Learning", ICRA 2019): a value network V(joint state) over the robot state and every human's
  state in a goal-aligned frame, with self-attention pooling of human-robot interaction features, trained by
  imitation of a demonstrator and then deep V-learning; actions by one-step lookahead.
* **OM** (Liu, Dugas, Cesari, Siegwart, Dubé, "Robot Navigation in Crowded Environments Using Deep Reinforcement
  Learning", IROS 2020): static obstacles enter the value network as a local *angular map* — the range scan of the
  static map binned into angular sectors, the nearest range per sector — encoded by an MLP and joined to the crowd
  feature before the value MLP (humans stay in the attention branch, walls in the map branch).
* **Danger zones** (Samsani & Muhammad, "Socially Compliant Robot Navigation in Crowded Environment by Human
  Behavior Resemblance Using Deep Reinforcement Learning", RA-L 2021): each human carries a velocity-dependent
  zone — a sector centred on its walking direction whose radius grows and whose opening narrows with its speed —
  and the reward penalises the robot for being inside it.

What it observes (``obs_mode: privileged``; built from the ``env`` object, never from ``obs``):
perfect tracks (:func:`rl.baselines.common.tracked_pedestrians`: true positions, velocities, radii) of the
``max_humans`` nearest pedestrians whose centre is within ``sensor_range_m``; a ray-cast of the *static* map
(``om_rays`` rays over 360°, ``om_range_m``) from the robot centre; the goal (or the waypoint of long-horizon runs);
its own pose and last commanded speed.

Joint state (CrowdNav's ``rotate()``), frame: origin at the robot, x toward the goal::

    self   (6)    d_g, v_pref, θ (heading − goal direction, wrapped), ρ_robot, v_x, v_y
    human  (K x 7) p_x, p_y, v_x, v_y, ρ_h, |p| (distance), ρ_h + ρ_robot     (K = max_humans, padded, + mask)
    om     (S)    closeness 1 − r/om_range_m of the nearest static hit in each of S sectors (0 = free), sector
                  k covering angles [−π + k·2π/S, −π + (k+1)·2π/S) in the goal frame

Network (:class:`SarlOMValue`, SARL's sizes): mlp1 (13 → 150 → 100) per human; mlp2 (100 → 100 → 50) interaction
features; attention MLP ([mlp1 ‖ masked mean of mlp1] 200 → 100 → 100 → 1) → masked softmax weights; crowd
feature = Σ weights · mlp2 (zero for an empty crowd); om encoder (S → 64 → 32); mlp3 ([self ‖ crowd ‖ om] 88 → 150 →
100 → 100 → 1) = V.

Policy: one-step lookahead over the robot's 5 x 21 (v, ω) grid (:func:`sim.robot.action_grid`): every action is
held for ``lookahead_s`` = 0.25 s (CrowdNav's decision period; exact unicycle arcs, events checked at every 0.1 s
control step on the way), the humans move with constant velocity; the value of an action is
R(s, a) + γ^(τ·v_pref) · V(s') (no bootstrap where R ends the episode), all 105 candidates in one batched forward;
argmax (ε-greedy during RL), executed for one control step and re-planned (receding horizon).

Reward R (per control step Δt; CrowdNav's terms with Samsani's zones)::

    +1                              reaching the goal (d_g ≤ goal radius)                       terminal
    −0.25                           collision: gap to a human ≤ 0, or static clearance ≤ ρ_robot terminal
    0.5 · (gap − 0.2) · Δt          discomfort: nearest human gap below 0.2 m (CrowdNav)
    − w_dz · Σ_h depth_h · Δt       danger zones: human h's zone is the sector of radius
                                    R_h = ρ_h + ρ_robot + dz_margin_m + dz_time_s · |v_h| and full opening
                                    Θ_h = 11π/6 · exp(−1.4 |v_h|) + π/6 (a full circle when standing) about
                                    its walking direction; depth_h = (R_h − d)/(R_h − ρ_h − ρ_robot) ∈ [0, 1]
    + w_prog · (d_g(s) − d_g(s'))   progress toward the goal (our addition, see below)

Training (:func:`train`, CrowdNav's procedure):

1. imitation: ``il_episodes`` (default: the teacher's ``bc_episodes``) episodes of the privileged expert on the
   training scenes (``training_pairs(cfg)``), observed by :class:`SarlObserver`; each visited joint state gets the
   discounted return of R along the episode (CrowdNav's IL value targets; timeouts are dropped as in CrowdNav);
   V is regressed on them (MSE, ``il_epochs``), and the transitions seed the replay memory (CrowdNav keeps its IL
   memory for RL);
2. deep V-learning: ``rl_iterations`` iterations of ``episodes_per_iter`` ε-greedy lookahead episodes (ε linear
   from ``epsilon_start`` to ``epsilon_end`` over ``epsilon_decay_episodes``) collected by ``cfg.workers``
   processes with a copy of the current weights; transitions (s, R, s', terminal) in a replay memory of
   ``capacity``; ``train_batches`` minibatches of TD targets R + γ^(Δt·v_pref) · V_target(s') per iteration; the
   target network is copied every ``target_update_episodes`` episodes. ``out/rl/`` holds a checkpoint (weights,
   optimiser, replay, counters) every ``checkpoint_every`` iterations, so ``--resume`` continues from there.

Deviations from the papers (and why):

* Unicycle robot with our 5 x 21 (v, ω) grid and Δt = 0.1 s (CrowdNav: holonomic 80 actions or unicycle with
  ±π/4 rotations, Δt = 0.25 s): the action space of the benchmark. The lookahead keeps CrowdNav's 0.25 s: over a
  single 0.1 s step the candidates' values differ by less than the value network's error.
* Mirror augmentation (y -> -y in the goal frame) of the imitation data and of half of each TD minibatch, as our
  teacher's cloning does: with few demonstrations V's dependence on heading was otherwise lopsided.
* Static obstacles: CrowdNav has none. The angular map follows Liu et al.; the collision test of R uses the nearest
  static-scan hit (the static map is privileged information in our benchmark, as for DRL-VO).
* Progress term w_prog = 0.1 per m: our episodes are 6 m among walls and timeouts at 40 s; with γ = 0.9 per
  second the terminal +1 alone gives a value slope of a few hundredths per metre, too flat for the lookahead
  to find its way around obstacles within a 10-minute budget. Danger-zone constants (dz_time_s, dz_margin_m,
  w_dz) are our choices scaled to Δt; the opening angle is the speed-dependent field of Samsani & Muhammad
  (after Kitazawa & Fujiyama).
* Value targets: TD targets with a frozen target network computed when a minibatch is drawn (CrowdNav computes
  them when the episode is stored), bootstrapped after a timeout (truncation, not a terminal state); transitions
  are collected in parallel batches of episodes rather than one episode per update; Adam instead of SGD.
* Budget: the number of expert episodes matches our teacher's; RL runs a few hundred episodes (CrowdNav: 10k), sized
  to train in about ten minutes on two CPU cores in the default profile.

Layout: :mod:`~rl.baselines.sarl_om.configuration` (options), :mod:`~rl.baselines.sarl_om.model` (the value
network), :mod:`~rl.baselines.sarl_om.observation` (the scene and the joint state), :mod:`~rl.baselines.sarl_om.rewards`
(R with the danger zones), :mod:`~rl.baselines.sarl_om.lookahead` (the policy), :mod:`~rl.baselines.sarl_om.training`
(imitation, rollouts, deep V-learning), :mod:`~rl.baselines.sarl_om.driver` (the benchmark driver).
"""

from rl.baselines.sarl_om.configuration import HUMAN_DIM, KEYS, NAME, RUNTIME_FIELDS, SELF_DIM, Config
from rl.baselines.sarl_om.driver import Driver
from rl.baselines.sarl_om.lookahead import Lookahead
from rl.baselines.sarl_om.model import SarlOMValue, build, to_tensors
from rl.baselines.sarl_om.observation import Scene, current_state, joint_state, perceive
from rl.baselines.sarl_om.rewards import danger_depth, reward
from rl.baselines.sarl_om.training import (
    TRANSITION_KEYS,
    Replay,
    SarlObserver,
    inputs,
    mirror,
    observation_description,
    regress,
    run_episode,
    td_update,
    train,
)

__all__ = [
    "HUMAN_DIM", "KEYS", "NAME", "RUNTIME_FIELDS", "SELF_DIM", "TRANSITION_KEYS", "Config", "Driver", "Lookahead",
    "Replay", "SarlOMValue", "SarlObserver", "Scene", "build", "current_state", "danger_depth", "inputs",
    "joint_state", "mirror", "observation_description", "perceive", "regress", "reward", "run_episode",
    "td_update", "to_tensors", "train",
]
