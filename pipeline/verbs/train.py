"""``icrowdnav train``: the verb over :mod:`rl.stage` (config, body) — the stage's inputs, output and manifest."""

from __future__ import annotations

from pipeline.core.stage import Stage, run_stage
from rl.stage import TrainConfig, body, inputs, output_dir

STAGE = Stage(
    name="train",
    config_cls=TrainConfig,
    help="train the privileged teacher or a visual student variant (DAgger + PPO) -> DATA_DIR/checkpoints/policy/",
    output_dir=output_dir,
    inputs=inputs,
    body=body,
    resumable=True,
    in_place=True,
    code=("pipeline", "rl", "sim", "pretrain", "recorder"),
)


def run(cfg: TrainConfig):
    """Runs the train stage for ``cfg.variant``; returns its manifest."""
    return run_stage(STAGE, cfg)

