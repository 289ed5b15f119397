"""The one-cycle schedule for fits of any length (pretrain.schedule)."""

import pytest
import torch

from pretrain.schedule import one_cycle


def _optim() -> torch.optim.Optimizer:
    return torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0)


def _lrs(opt: torch.optim.Optimizer, sched, steps: int) -> list[float]:
    out = []
    for _ in range(steps):
        out.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    return out


@pytest.mark.parametrize("total,pct", [(10, 0.1), (5, 0.2), (4, 0.25), (20, 0.05)])
def test_a_one_step_warm_up_gets_a_schedule_instead_of_a_zero_division(total, pct):
    """torch's OneCycleLR divides by zero when pct_start * total_steps == 1 (a pretraining of 10 steps at 0.1)."""
    with pytest.raises(ZeroDivisionError):
        torch.optim.lr_scheduler.OneCycleLR(_optim(), max_lr=1.0, total_steps=total, pct_start=pct)
    opt = _optim()
    lrs = _lrs(opt, one_cycle(opt, 1.0, total, pct_start=pct), total)
    assert len(lrs) == total and all(0 < v <= 1.0 for v in lrs)
    peak = max(range(total), key=lrs.__getitem__)
    assert peak >= 1 and lrs[0] < lrs[peak] and lrs[-1] < lrs[peak]


@pytest.mark.parametrize("total,pct", [(40, 0.1), (3, 0.1), (1, 0.3), (7, 0.0), (755, 0.1)])
def test_torchs_schedule_is_unchanged_where_torch_accepts_it(total, pct):
    ref_opt, opt = _optim(), _optim()
    ref = torch.optim.lr_scheduler.OneCycleLR(ref_opt, max_lr=1.0, total_steps=total, pct_start=pct,
                                              anneal_strategy="cos")
    assert _lrs(opt, one_cycle(opt, 1.0, total, pct_start=pct), total) == _lrs(ref_opt, ref, total)
