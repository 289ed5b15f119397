"""``icrowdnav rollout``: the verb over :mod:`sim.rollout` (config, body) — the stage's inputs, output and manifest."""

from __future__ import annotations

from pipeline.core import layout
from pipeline.core.stage import Stage, run_stage
from sim.rollout import RolloutConfig, body

STAGE = Stage(
    name="rollout",
    config_cls=RolloutConfig,
    help="run the privileged expert over scenes x densities x seeds; metrics, figures, videos",
    output_dir=lambda cfg: layout.rollout_dir(cfg.data_dir, cfg.run_name),
    inputs=lambda cfg: [],
    body=body,
    code=("pipeline", "sim"),
)


def run(cfg: RolloutConfig):
    """Run the stage (library entry point); returns its :class:`pipeline.core.manifest.Manifest`."""
    return run_stage(STAGE, cfg)

