"""The data-dir tree, one place: every stage's output folder as a function of the data dir and the run's name.

::

    DATA_DIR/
    ├── raw/<run_name>/                  record   (one MCAP per episode)
    ├── datasets/<owner>/<name>/         export   (LeRobot v3.0; repo_id = <owner>/<name>)
    ├── rollouts/<run_name>/             rollout  (the expert's acceptance run)
    ├── checkpoints/<name>/              pretrain (the BEV encoder; default name "bev")
    ├── checkpoints/policy/<variant>/    train    (teacher, students, learned baselines)
    ├── eval/<run_name>/                 eval     (the benchmark)
    └── bench/bench.json                 bench

The full tree of each folder is drawn in docs/architecture.md.
"""

from __future__ import annotations

from pathlib import Path


def raw_dir(data_dir: Path | str, run_name: str) -> Path:
    return Path(data_dir) / "raw" / run_name


def dataset_dir(data_dir: Path | str, repo_id: str) -> Path:
    return Path(data_dir) / "datasets" / repo_id


def rollout_dir(data_dir: Path | str, run_name: str) -> Path:
    return Path(data_dir) / "rollouts" / run_name


def checkpoint_dir(data_dir: Path | str, name: str) -> Path:
    return Path(data_dir) / "checkpoints" / name


def policy_root(data_dir: Path | str) -> Path:
    return Path(data_dir) / "checkpoints" / "policy"


def policy_dir(data_dir: Path | str, variant: str) -> Path:
    return policy_root(data_dir) / variant


def eval_dir(data_dir: Path | str, run_name: str) -> Path:
    return Path(data_dir) / "eval" / run_name


def bench_file(data_dir: Path | str) -> Path:
    return Path(data_dir) / "bench" / "bench.json"
