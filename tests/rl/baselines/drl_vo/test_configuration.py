"""DRL-VO's options: validation names the field."""

import pytest

from pipeline.core.errors import ConfigError
from rl.baselines import drl_vo


def test_config_validate_names_the_field():
    with pytest.raises(ConfigError, match="lidar_rays"):
        drl_vo.Config(lidar_rays=100).validate()
    with pytest.raises(ConfigError, match="width"):
        drl_vo.Config(width=12).validate()
    with pytest.raises(ConfigError, match="unknown"):
        drl_vo.Config(ppo={"n_stepz": 3}).validate()
    for bad in ([0], [20_000], [4096, 1024], [1024, 1024]):  # 0, past ppo_steps (16,384), not increasing
        with pytest.raises(ConfigError, match=r"^drl_vo\.curve_steps: expected increasing PPO step counts in "
                                              r"\(0, ppo_steps = 16384\), got "):
            drl_vo.Config(curve_steps=bad).validate()
    drl_vo.Config(curve_steps=[1024, 4096]).validate()
    drl_vo.Config().validate()
