"""Stable-Baselines3 callbacks shared by the PPO runs (the teacher's, the students' fine-tuning, DRL-VO's): the
resume checkpoint and the progress bar; and their common schedule, PPO after a critic warm-up
(:func:`learn_with_critic_warmup`)."""

from __future__ import annotations

from pathlib import Path

from stable_baselines3.common.callbacks import BaseCallback
from tqdm import tqdm

from pipeline.core.artifacts import atomic_write_with
from rl.policy import freeze_actor


def save_ppo(model, path: Path) -> Path:
    """Saves an SB3 ``model`` to ``path`` atomically (a kill leaves the previous file or none, never half of one)."""
    return atomic_write_with(path, model.save)


def learn_with_critic_warmup(model, total_steps: int, warmup_steps: int, callback: list[BaseCallback],
                             tb_log_name: str) -> None:
    """PPO ``model.learn`` until ``model.num_timesteps`` reaches ``total_steps``, the first ``warmup_steps`` of them
    (at most ``total_steps``) training only the value branch (:func:`rl.policy.freeze_actor`): a policy cloned by
    imitation starts with a critic that has never seen a return, and its advantages would move the actor at random
    before the critic has fitted on-policy. A resumed model continues where it stopped, inside the warm-up or after
    it (SB3 collects whole rollouts, so each part ends at the first multiple of ``n_steps · n_envs`` past it)."""
    warm = min(warmup_steps, total_steps)
    if model.num_timesteps < warm:
        frozen = freeze_actor(model.policy)
        try:
            model.learn(warm - model.num_timesteps, callback=callback, reset_num_timesteps=False,
                        tb_log_name=tb_log_name)
        finally:
            for p in frozen:
                p.requires_grad_(True)
    model.learn(max(0, total_steps - model.num_timesteps), callback=callback, reset_num_timesteps=False,
                tb_log_name=tb_log_name)


def checkpoint_callback(path: Path, model, every: int) -> BaseCallback:
    """Saves the model to ``path / "last.zip"`` (:func:`save_ppo`) once at least ``every``
    env steps, counted from ``model``'s current step, have passed since the last save (what ``--resume`` continues
    from). It saves when a rollout starts, i.e. after the update of every step it counts: a save in the middle of
    a rollout would count steps whose update a resumed run never makes."""

    class Save(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.next = model.num_timesteps + every

        def _on_rollout_start(self) -> None:
            if self.num_timesteps >= self.next:
                save_ppo(self.model, path / "last.zip")
                while self.next <= self.num_timesteps:
                    self.next += every

        def _on_step(self) -> bool:
            return True

    return Save()


def progress_callback(total: int, desc: str, enabled: bool) -> BaseCallback:
    """A tqdm bar of ``total`` env steps labelled ``desc`` (starting at the model's step count; off unless
    ``enabled``)."""

    class Bar(BaseCallback):
        def _on_training_start(self) -> None:
            self.bar = tqdm(total=total, initial=min(self.num_timesteps, total), desc=desc, unit="step",
                            disable=not enabled, dynamic_ncols=True)

        def _on_step(self) -> bool:
            self.bar.update(self.training_env.num_envs)
            return True

        def _on_training_end(self) -> None:
            self.bar.close()

    return Bar()
