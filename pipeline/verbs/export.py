"""``icrowdnav export``: the verb over :mod:`recorder.export_stage` (config, body) — the stage's inputs, output and manifest."""

from __future__ import annotations

from pipeline.core.stage import Stage, run_stage
from recorder.export_stage import ExportConfig, body, dataset_dir, inputs

STAGE = Stage(
    name="export",
    config_cls=ExportConfig,
    help="export a finished recording (MCAP) to a LeRobot v3.0 dataset under DATA_DIR/datasets/<repo_id>/",
    output_dir=dataset_dir,
    inputs=inputs,
    body=body,
    code=("pipeline", "sim", "recorder"),
)


def run(cfg: ExportConfig):
    """Run the stage (library entry point); returns its :class:`pipeline.core.manifest.Manifest`."""
    return run_stage(STAGE, cfg)

