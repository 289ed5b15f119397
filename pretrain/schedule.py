"""The one-cycle learning-rate schedule every pretraining fit uses, valid for any number of steps.

torch's ``OneCycleLR`` divides by the length of its warm-up phase, ``pct_start * total_steps - 1`` steps, so a fit
whose warm-up is exactly one step (``pct_start * total_steps == 1``: 10 steps at the BEV pretraining's 0.1, a tiny
dataset's single epoch) fails inside the constructor with a ``ZeroDivisionError``. :func:`one_cycle` keeps torch's
schedule wherever torch accepts it and in that one case lengthens the warm-up by half a step.
"""

from __future__ import annotations

import torch


def one_cycle(optim: torch.optim.Optimizer, max_lr: float, total_steps: int, pct_start: float = 0.3,
              anneal_strategy: str = "cos") -> torch.optim.lr_scheduler.OneCycleLR:
    """torch's ``OneCycleLR`` over ``total_steps`` (≥ 1) steps; ``pct_start`` (the warm-up's fraction, in [0, 1))
    is raised by half a step where torch's warm-up would end at step 0 and divide by zero."""
    total = max(1, int(total_steps))
    pct = float(pct_start)
    if float(pct * total) - 1 == 0:
        pct = (1.0 + 0.5) / total if total > 2 else 0.75
    return torch.optim.lr_scheduler.OneCycleLR(optim, max_lr=max_lr, total_steps=total, pct_start=pct,
                                               anneal_strategy=anneal_strategy)
