"""The ViNT-style options: validation names the option."""

from __future__ import annotations

import pytest

from pipeline.core.errors import ConfigError
from rl.baselines.vint import Config


def test_config_validate() -> None:
    Config().validate()
    for bad, word in ((dict(encoder="resnet"), "encoder"), (dict(waypoint_index=5), "waypoint_index"),
                      (dict(embed_dim=30, heads=4), "embed_dim"), (dict(image_hw=[4, 40]), "image_hw"),
                      (dict(val_fraction=1.0), "val_fraction")):
        with pytest.raises(ConfigError, match=word):
            Config(**bad).validate()
