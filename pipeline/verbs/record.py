"""``icrowdnav record``: the verb over :mod:`recorder.record` (config, body) — the stage's inputs, output and manifest."""

from __future__ import annotations

from pipeline.core.stage import Stage, run_stage
from recorder.record import RecordConfig, body, raw_dir

STAGE = Stage(
    name="record",
    config_cls=RecordConfig,
    help="drive episodes (expert) and log each to an MCAP file under DATA_DIR/raw/<run_name>/",
    output_dir=raw_dir,
    inputs=lambda cfg: [],
    body=body,
    resumable=True,
    in_place=True,
    scaffold=("seeds.json", "episodes.jsonl"),
    code=("pipeline", "sim", "recorder"),
)


def run(cfg: RecordConfig):
    """Run the stage (library entry point); returns its :class:`pipeline.core.manifest.Manifest`."""
    return run_stage(STAGE, cfg)

