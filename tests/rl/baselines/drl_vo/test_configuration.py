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
    drl_vo.Config().validate()
