"""Learned baselines, trained and benchmarked like our policies: DRL-VO, SARL*-OM and a ViNT-style policy.

``icrowdnav train --variant <name>`` trains one (``make train`` trains every name of ``TRAIN_VARIANTS``);
``icrowdnav eval --methods '[..., <name>]'`` benchmarks it through the same harness, seeds and metrics as the
paper's methods. Each lives in its own package ``rl.baselines.<name>`` (configuration, model, training, driver, ...;
the contract is in :mod:`rl.baselines.common`); this table is what the pipeline needs without importing them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from pipeline.core.errors import ConfigError


@dataclass(frozen=True)
class BaselineInfo:
    label: str  # the label of tables and figures
    obs_mode: str  # the env obs mode its driver needs at evaluation: privileged (no rendering) | visual
    action_type: str  # the env action space its driver returns actions in: continuous | discrete
    cite: str  # the original paper
    poses: bool = True  # visual: whether its driver reads the detected poses (False: evaluation skips the detector)


BASELINES: dict[str, BaselineInfo] = {
    "drl_vo": BaselineInfo("DRL-VO", "privileged", "continuous", "Xie & Dames, T-RO 2023"),
    "sarl_om": BaselineInfo("SARL*-OM", "privileged", "discrete",
                            "Chen et al. ICRA 2019 + Liu et al. IROS 2020 + Samsani & Muhammad RA-L 2021"),
    "vint": BaselineInfo("ViNT-style (trained on our data)", "visual", "continuous", "Shah et al. CoRL 2023",
                         poses=False),  # the two RGB images only
}


def baseline_module(name: str):
    """The package of baseline ``name`` (imported on first use): ``Config``, ``inputs``, ``train``, ``Driver``, ..."""
    import importlib

    return importlib.import_module(f"rl.baselines.{name}")


def check_curve_budgets(budgets: Sequence[int], total: int, key: str, what: str, bound: str) -> None:
    """Config check of a learning-curve option (``key``, e.g. ``drl_vo.curve_steps``): strictly increasing integer
    budgets (``what``, e.g. "PPO step counts") in (0, ``total``), ``bound`` naming where ``total`` comes from."""
    if any(not isinstance(n, int) or isinstance(n, bool) or not 0 < n < total for n in budgets) \
            or sorted(set(budgets)) != list(budgets):
        raise ConfigError(f"{key}: expected increasing {what} in (0, {bound} = {total}), got {budgets}")
