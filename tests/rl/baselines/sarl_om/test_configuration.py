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
