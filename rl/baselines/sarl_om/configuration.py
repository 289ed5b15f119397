"""SARL*-OM's options (``TrainConfig.sarl_om``): what it observes, its reward, the training budget; and the sizes
of its joint state."""

from __future__ import annotations

from dataclasses import dataclass, field

from pipeline.core.errors import ConfigError
from rl.baselines import check_curve_budgets

NAME = "sarl_om"
SELF_DIM = 6
HUMAN_DIM = 7
KEYS = ("self", "humans", "mask", "om")  # the joint state's arrays (package docstring)


@dataclass
class Config:
    """SARL*-OM options: what it observes, its reward, and the training budget (the ``default`` profile)."""

    # observation
    sensor_range_m: float = 4.0  # pedestrians (perfect tracks) whose centre is within this range are seen
    max_humans: int = 10  # K: the nearest this many are kept (padded + masked below)
    om_rays: int = 180  # rays of the static-map scan (360°)
    om_range_m: float = 4.0  # range of that scan and of the angular map
    om_sectors: int = 36  # S: angular-map sectors over 360° (10° each)
    # reward (package docstring)
    gamma: float = 0.9  # discount per second at v_pref: γ^(Δt·v_pref) per step (CrowdNav)
    lookahead_s: float = 0.25  # how long the lookahead holds each action (CrowdNav's time step)
    success_reward: float = 1.0
    collision_penalty: float = -0.25
    discomfort_m: float = 0.2  # CrowdNav discomfort distance (gap to a human body)
    discomfort_factor: float = 0.5  # per m of intrusion per second
    dz_weight: float = 0.25  # danger-zone penalty per second at full depth
    dz_margin_m: float = 0.2  # zone radius of a standing human beyond body contact
    dz_time_s: float = 1.0  # zone radius grows by this many seconds of the human's walk
    progress_weight: float = 0.1  # per m of progress toward the goal
    # imitation
    il_episodes: int = 0  # expert episodes; 0 = the teacher's teacher.bc_episodes
    il_epochs: int = 30
    il_lr: float = 1e-3
    batch_size: int = 128
    # deep V-learning
    rl_iterations: int = 40
    episodes_per_iter: int = 12  # spread over cfg.workers processes
    train_batches: int = 100  # minibatches per iteration (CrowdNav: 100 of 100 per episode)
    rl_lr: float = 2e-4
    target_update_episodes: int = 48  # copy the value network into the target network this often
    epsilon_start: float = 0.5
    epsilon_end: float = 0.1
    epsilon_decay_episodes: int = 300
    capacity: int = 100_000  # replay memory (transitions)
    checkpoint_every: int = 5  # iterations between checkpoints in out/rl/ (resume)
    # the learning curve: the value network is also saved after imitation and once these many RL episodes are done
    # (curve/), and ``train`` runs the acceptance episodes on each (metrics.json "learning_curve")
    curve_episodes: list[int] = field(default_factory=list)

    def validate(self) -> None:
        """Raises ConfigError naming the first bad field."""
        positive = ("sensor_range_m", "om_range_m", "il_lr", "rl_lr", "discomfort_m", "dz_margin_m", "lookahead_s")
        for k in positive:
            if not getattr(self, k) > 0:
                raise ConfigError(f"sarl_om.{k}: expected > 0, got {getattr(self, k)}")
        counts = ("max_humans", "om_rays", "om_sectors", "il_epochs", "batch_size", "episodes_per_iter",
                  "train_batches", "target_update_episodes", "epsilon_decay_episodes", "capacity",
                  "checkpoint_every")
        for k in counts:
            v = getattr(self, k)
            if not isinstance(v, int) or v < 1:
                raise ConfigError(f"sarl_om.{k}: expected an integer >= 1, got {v!r}")
        if self.il_episodes < 0 or self.rl_iterations < 0:
            raise ConfigError(f"sarl_om: il_episodes and rl_iterations must be >= 0, got {self.il_episodes}, "
                              f"{self.rl_iterations}")
        check_curve_budgets(self.curve_episodes, self.rl_iterations * self.episodes_per_iter, "sarl_om.curve_episodes",
                            "RL episode counts", "rl_iterations x episodes_per_iter")
        if self.om_rays < self.om_sectors:
            raise ConfigError(f"sarl_om.om_rays: expected >= om_sectors ({self.om_sectors}), got {self.om_rays}")
        if not 0.0 < self.gamma <= 1.0:
            raise ConfigError(f"sarl_om.gamma: expected in (0, 1], got {self.gamma}")
        if not 0.0 <= self.epsilon_end <= self.epsilon_start <= 1.0:
            raise ConfigError(f"sarl_om: expected 0 <= epsilon_end <= epsilon_start <= 1, got "
                              f"{self.epsilon_end}, {self.epsilon_start}")
        if min(self.dz_weight, self.dz_time_s, self.discomfort_factor, self.progress_weight) < 0:
            raise ConfigError("sarl_om: dz_weight, dz_time_s, discomfort_factor and progress_weight must be >= 0")
        if self.success_reward <= 0 or self.collision_penalty >= 0:
            raise ConfigError(f"sarl_om: expected success_reward > 0 and collision_penalty < 0, got "
                              f"{self.success_reward}, {self.collision_penalty}")


# Fields the driver needs at run time (stored in policy.json's observation_space).
RUNTIME_FIELDS = ("sensor_range_m", "max_humans", "om_rays", "om_range_m", "om_sectors", "gamma", "lookahead_s",
                  "success_reward",
                  "collision_penalty", "discomfort_m", "discomfort_factor", "dz_weight", "dz_margin_m", "dz_time_s",
                  "progress_weight")
