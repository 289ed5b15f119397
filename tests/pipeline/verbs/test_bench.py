"""``icrowdnav bench``'s start-up figures: fresh interpreters timed against ``import torch``."""

from __future__ import annotations

import pytest

from pipeline.core.errors import ConfigError
from pipeline.verbs.bench import STARTUP_MODULES, BenchConfig, measure_startup


def test_startup_figures_time_fresh_imports_against_torch():
    out = measure_startup(["json"], runs=1)
    assert set(out) == {"startup_s_torch", "startup_s_json", "startup_over_torch_json"}
    assert out["startup_s_torch"] > 0 and out["startup_s_json"] > 0
    assert out["startup_over_torch_json"] == pytest.approx(out["startup_s_json"] / out["startup_s_torch"])


def test_startup_modules_exist_and_bad_run_counts_are_named():
    import importlib.util

    assert all(importlib.util.find_spec(m) is not None for m in STARTUP_MODULES)
    with pytest.raises(ConfigError, match="startup_runs"):
        BenchConfig(startup_runs=-1).validate()
