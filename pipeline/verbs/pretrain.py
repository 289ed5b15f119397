"""``icrowdnav pretrain``: the verb over :mod:`pretrain.stage` (config, body) — the stage's inputs, output and manifest."""

from __future__ import annotations

from pipeline.core.stage import Stage, run_stage
from pretrain.stage import PretrainConfig, body, checkpoint_dir, inputs

STAGE = Stage(
    name="pretrain",
    config_cls=PretrainConfig,
    help="pretrain the spatio-temporal BEV encoder on a LeRobot dataset -> DATA_DIR/checkpoints/<name>/",
    output_dir=checkpoint_dir,
    inputs=inputs,
    body=body,
    resumable=True,
    in_place=True,
    code=("pipeline", "pretrain"),
)


def run(cfg: PretrainConfig):
    """Run the stage (library entry point); returns its :class:`pipeline.core.manifest.Manifest`."""
    return run_stage(STAGE, cfg)

