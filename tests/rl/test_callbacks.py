"""``rl.callbacks.learn_with_critic_warmup``: PPO whose first steps fit only the value branch, resumable inside or
after the warm-up, every weight trainable again afterwards (even when the warm-up is interrupted)."""

from __future__ import annotations

import gymnasium as gym
import pytest
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback

from rl.callbacks import learn_with_critic_warmup

VALUE = ("value_net.", "mlp_extractor.value_net.")


def _ppo() -> PPO:
    return PPO("MlpPolicy", gym.make("CartPole-v1"), n_steps=32, batch_size=32, n_epochs=2, seed=0, device="cpu",
               policy_kwargs={"net_arch": [8]})


def _moved(model: PPO, ref: dict[str, torch.Tensor]) -> set[bool]:
    """(is a value-branch weight) for every weight that differs from ``ref``."""
    return {k.startswith(VALUE) for k, v in model.policy.state_dict().items() if not torch.equal(v, ref[k])}


def test_the_warmup_moves_the_critic_only_then_ppo_moves_the_actor():
    model = _ppo()
    start = {k: v.clone() for k, v in model.policy.state_dict().items()}
    learn_with_critic_warmup(model, total_steps=64, warmup_steps=64, callback=[], tb_log_name="t")
    assert model.num_timesteps == 64 and _moved(model, start) == {True}
    assert all(p.requires_grad for p in model.policy.parameters())
    # continued past the warm-up (a resumed run): the actor learns
    learn_with_critic_warmup(model, total_steps=128, warmup_steps=64, callback=[], tb_log_name="t")
    assert model.num_timesteps == 128 and _moved(model, start) == {True, False}
    # no warm-up: PPO from the first step
    plain = _ppo()
    learn_with_critic_warmup(plain, total_steps=32, warmup_steps=0, callback=[], tb_log_name="t")
    assert _moved(plain, start) == {True, False}


def test_a_warmup_interrupted_by_a_kill_leaves_every_weight_trainable():
    class Kill(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps > 40:
                raise KeyboardInterrupt
            return True

    model = _ppo()
    with pytest.raises(KeyboardInterrupt):
        learn_with_critic_warmup(model, total_steps=128, warmup_steps=96, callback=[Kill()], tb_log_name="t")
    assert all(p.requires_grad for p in model.policy.parameters())
