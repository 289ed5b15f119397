"""SARL*-OM's options: validation names the field."""

from dataclasses import replace

import pytest

from pipeline.core.errors import ConfigError
from tests.rl.baselines.sarl_om.helpers import OC


def test_config_validation():
    with pytest.raises(ConfigError, match="sarl_om.max_humans"):
        replace(OC, max_humans=0).validate()
    with pytest.raises(ConfigError, match="epsilon"):
        replace(OC, epsilon_start=0.1, epsilon_end=0.5).validate()
    with pytest.raises(ConfigError, match=r"^sarl_om\.curve_episodes: expected increasing RL episode counts in "
                                          r"\(0, rl_iterations x episodes_per_iter = 24\), got \[24\]"):
        replace(OC, rl_iterations=2, episodes_per_iter=12, curve_episodes=[24]).validate()
    replace(OC, rl_iterations=2, episodes_per_iter=12, curve_episodes=[12]).validate()
