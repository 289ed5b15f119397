"""``icrowdnav export``: turn a finished recording (``DATA_DIR/raw/<run_name>/``) into a LeRobot v3.0 dataset.

::

    icrowdnav export --run-name expert --repo-id icrowdnav/expert        # make record runs it after recording

Input: a recording whose ``manifest.json`` exists (the record stage writes it only when every episode is
finished, so only complete MCAPs are exported). Output: ``DATA_DIR/datasets/<repo_id>/`` — a stock LeRobot
dataset (see :mod:`recorder.export` for its features and side files) plus this stage's ``config.yaml`` and
``manifest.json``. It is written in a staging directory, validated by the dataset doctor, then renamed into
place; a killed export leaves no dataset (or the previous one). Load it with::

    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    ds = LeRobotDataset("icrowdnav/expert", root="data/datasets/icrowdnav/expert", video_backend="pyav")
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.core import layout
from pipeline.core.config import BaseStageConfig, check_run_name
from pipeline.core.errors import ConfigError, CorruptArtifactError, InputMissingError
from pipeline.core.executor import Executor, check_executor
from pipeline.core.manifest import MANIFEST_NAME
from recorder.doctor_dataset import check_dataset
from recorder.export import write_dataset

_REPO_ID = re.compile(r"^[A-Za-z0-9][\w.-]*/[A-Za-z0-9][\w.-]*$")


@dataclass
class ExportConfig(BaseStageConfig):
    """Config of the ``export`` stage."""

    run_name: str = field(default="expert", metadata={"help": "recording to export: DATA_DIR/raw/<run_name>/"})
    repo_id: str = field(default="icrowdnav/expert",
                         metadata={"help": "LeRobot repo id (owner/name); output DATA_DIR/datasets/<repo_id>/"})
    workers: int = field(default=2, metadata={"help": "export shards written in parallel, then merged by lerobot's "
                                                      "aggregate_datasets (1: one process, no merge)"})
    executor: str = field(default="auto", metadata={"help": "where shards run: auto (Ray when RAY_ADDRESS is set) | "
                                                            "local | ray (pipeline.core.executor)"})
    ray_address: str = field(default="", metadata={"help": "Ray cluster address host:port (empty: RAY_ADDRESS, or "
                                                           "a Ray instance started on this machine)"})

    def validate(self) -> None:
        super().validate()
        check_run_name(self.run_name)
        check_executor(self.executor, self.ray_address, "export")
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 1:
            raise ConfigError(f"export: config key 'workers': expected an int >= 1, got {self.workers!r}")
        if not _REPO_ID.match(self.repo_id) or ".." in self.repo_id.split("/"):
            raise ConfigError(f"repo_id: expected 'owner/name' (letters, digits, ._-), got {self.repo_id!r}")


def raw_dir(cfg: ExportConfig) -> Path:
    return layout.raw_dir(cfg.data_dir, cfg.run_name)


def dataset_dir(cfg: ExportConfig) -> Path:
    return layout.dataset_dir(cfg.data_dir, cfg.repo_id)


def inputs(cfg: ExportConfig) -> list[Path]:
    src = raw_dir(cfg)
    if src.is_dir() and not (src / MANIFEST_NAME).is_file():
        raise InputMissingError(f"recording {src} is unfinished (no {MANIFEST_NAME}); finish it with "
                                "`icrowdnav record --resume` first")
    return [src]


def body(cfg: ExportConfig, out: Path) -> dict:
    # exactly the episodes the recording lists (not, e.g., *.recovered.mcap salvage copies lying beside them)
    listing = raw_dir(cfg) / "episodes.jsonl"
    if not listing.is_file():
        raise InputMissingError(f"missing episode list {listing} (made by `icrowdnav record`)")
    names = [json.loads(line)["file"] for line in listing.read_text().splitlines() if line.strip()]
    files = [raw_dir(cfg) / n for n in names]
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        raise InputMissingError(f"recording {raw_dir(cfg)} lists missing episode file(s): {', '.join(missing[:3])}")
    if not files:
        raise InputMissingError(f"no episode in {raw_dir(cfg)}")
    counts = write_dataset(files, out, cfg.repo_id, shards=cfg.workers, executor=Executor.of(cfg))
    problems = check_dataset(out)
    if problems:
        raise CorruptArtifactError(f"exported dataset failed validation, nothing published: {problems[0]}"
                                   + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""))
    return counts
