"""Stable-Baselines3 callbacks shared by the PPO runs (the teacher's, the students' fine-tuning, DRL-VO's): the
resume checkpoint and the progress bar."""

from __future__ import annotations

from pathlib import Path

from stable_baselines3.common.callbacks import BaseCallback
from tqdm import tqdm

from pipeline.core.artifacts import atomic_write_with


def save_ppo(model, path: Path) -> Path:
    """Saves an SB3 ``model`` to ``path`` atomically (a kill leaves the previous file or none, never half of one)."""
    return atomic_write_with(path, model.save)


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
