"""``icrowdnav pretrain-intention``: the verb over :mod:`pretrain.intention` — the intention model (where a tracked
pedestrian walks next, from its track and detected pose), the second target of ``make pretrain``."""

from __future__ import annotations

from pipeline.core.stage import Stage, run_stage
from pretrain.intention import IntentionConfig, body, checkpoint_dir, inputs

STAGE = Stage(
    name="pretrain-intention",
    config_cls=IntentionConfig,
    help="pretrain the intention model (track + detected pose -> future positions) on a LeRobot dataset "
         "-> DATA_DIR/checkpoints/intention/",
    output_dir=checkpoint_dir,
    inputs=inputs,
    body=body,
    code=("pipeline", "sim", "pretrain"),
)


def run(cfg: IntentionConfig):
    """Run the stage (library entry point); returns its :class:`pipeline.core.manifest.Manifest`."""
    return run_stage(STAGE, cfg)
