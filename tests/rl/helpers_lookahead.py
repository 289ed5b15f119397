"""Checkpoint layouts of the lookahead head, shared by its tests (test_lookahead, test_perceive)."""

import torch

# the learned layers of the lookahead head, as keys under its prefix (its rollout geometry is non-persistent)
HEAD_KEYS = {"context.0.weight", "context.0.bias", "scorer.0.weight", "scorer.0.bias", "scorer.2.weight",
             "scorer.2.bias", "scorer.4.weight", "scorer.4.bias", "linear.weight", "linear.bias"}
# SB3 registers the shared features extractor under all three names
EXTRACTORS = ("features_extractor.", "pi_features_extractor.", "vf_features_extractor.")


def pre_head_layout(sd: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A current policy state dict as checkpoints from before the head was a module stored it (the inverse of
    :func:`rl.policy.upgrade_state_dict`): the head's layers directly on the extractor, e.g.
    ``features_extractor.linear.weight`` for ``features_extractor.lookahead.linear.weight``. Checks that the head
    contributes exactly :data:`HEAD_KEYS` under each extractor name (no persistent buffer)."""
    old = {}
    for k, v in sd.items():
        for pre in EXTRACTORS:
            if k.startswith(pre + "lookahead."):
                k = pre + k[len(pre + "lookahead."):]
        old[k] = v.detach().clone()
    assert {k for k in old if k not in sd} == {pre + h for pre in EXTRACTORS for h in HEAD_KEYS}
    return old
