"""DRL-VO's network: the critic warm-up freezes the actor; the extractor's import path of old SB3 checkpoints."""

import pickle
from dataclasses import replace

from rl.baselines import drl_vo
from rl.baselines.drl_vo.model import DRLVOExtractor
from rl.policy import freeze_actor


def test_freeze_actor_leaves_only_the_value_branch_trainable():
    c = replace(drl_vo.Config(), width=8, features_dim=32, pi=[16], vf=[16])
    policy = drl_vo.build_policy(c.net())
    frozen = freeze_actor(policy)
    trainable = {n for n, p in policy.named_parameters() if p.requires_grad}
    assert trainable and all(n.startswith(("mlp_extractor.value_net.", "value_net.")) for n in trainable)
    assert {n for n, p in policy.named_parameters() if not p.requires_grad} >= {"log_std", "action_net.weight"}
    assert any(n.startswith("features_extractor.") for n, p in policy.named_parameters() if not p.requires_grad)
    assert len(frozen) + len(trainable) == len(list(policy.parameters()))


def test_extractor_keeps_the_import_path_of_old_sb3_checkpoints():
    """SB3 pickles ``policy_kwargs`` (the extractor class, by reference) into ``ppo/last.zip``; runs from before the
    package split name it ``rl.baselines.drl_vo.DRLVOExtractor``, which must still resolve (``--resume``)."""
    assert pickle.loads(b"crl.baselines.drl_vo\nDRLVOExtractor\n.") is DRLVOExtractor
    assert drl_vo.policy_kwargs(drl_vo.Config().net())["features_extractor_class"] is DRLVOExtractor
