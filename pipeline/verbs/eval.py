"""``icrowdnav eval``: the verb over :mod:`evaluation.stage` (config, body) — the stage's inputs, output and manifest."""

from __future__ import annotations

from evaluation.stage import EvalConfig, body, inputs, output_dir
from pipeline.core.stage import Stage, run_stage

STAGE = Stage(
    name="eval",
    config_cls=EvalConfig,
    help="the benchmark: scenes x densities x methods x seeded episodes + long-horizon runs -> DATA_DIR/eval/",
    output_dir=output_dir,
    inputs=inputs,
    body=body,
    resumable=True,
    in_place=True,
    code=("pipeline", "sim", "rl", "evaluation", "pretrain", "recorder"),
)


def run(cfg: EvalConfig):
    """Run the stage (library entry point); returns its :class:`pipeline.core.manifest.Manifest`."""
    return run_stage(STAGE, cfg)

