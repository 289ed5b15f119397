"""``icrowdnav train-all``: the training variants of ``make train`` as independent jobs — one after another on this
machine (the default, as ``make train``'s loop does), several at once (``--jobs N``), or as Ray tasks
spread over a cluster (``--executor ray``, or ``RAY_ADDRESS`` set).

::

    icrowdnav train-all --variants '[teacher, full, no_i2, no_bev, drl_vo, sarl_om, vint]' --profile default
    icrowdnav train-all --executor ray --cpus_per_variant 4 --workers 4 --data-dir /shared/data

Every argument this verb does not own is passed to each variant's ``icrowdnav train`` unchanged (``--profile``,
``--data-dir``, ``--workers``, ``--overwrite``, any ``--KEY VALUE``), and every variant's config is loaded and
validated before anything runs: a bad value is one named error, exit 2, nothing trained.

Order: the teacher (when listed) trains first and alone, because the students distil from it; a failed teacher
skips them. Then every other variant is one job: a fresh ``python -m pipeline train --variant V …`` process (its own
torch threads and its own rollout pool; on Ray that also avoids forking a Ray worker), on the local process pool
(``--jobs`` at a time) or as a Ray task that holds ``--cpus_per_variant`` CPUs of whichever node runs it (its
rollouts use that node's cores; the data dir must be the same path on every node, checked first, as for the other
stages). Each job's output is ``DATA_DIR/logs/train-<variant>.log``. A job adds ``--resume`` unless ``--overwrite``
is given, so a Ray task rerun after its worker or node died continues the variant where it stopped instead of
failing on its half-written directory (``train`` resumes exactly: tests/rl/test_train.py). A failed variant does not
stop the others; the verb then exits 2 naming each failed variant and its log. The child process is ended with its
parent (``PR_SET_PDEATHSIG``), so Ctrl-C or a cancelled Ray task leaves no training behind.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from pipeline.cli import parse_stage_args
from pipeline.core.child import ChildJob, log_tail, run_child
from pipeline.core.config import load_config
from pipeline.core.errors import ConfigError, ICrowdNavError
from pipeline.core.executor import Executor, check_executor, map_jobs, resolve_executor
from pipeline.verbs.train import STAGE
from rl.stage import TRAIN_VARIANTS

log = logging.getLogger("icrowdnav")

OWN_KEYS = ("variants", "jobs", "executor", "ray_address", "cpus_per_variant")
DEFAULT_VARIANTS = ("teacher", "full", "no_i2", "no_bev", "drl_vo", "sarl_om", "vint")


@dataclass
class Plan:
    """What ``train-all`` runs: the waves of variants (the teacher alone first), the passthrough arguments, how."""

    waves: list[list[str]]
    passthrough: list[str]
    data_dir: Path
    jobs: int = 1
    executor: str = "local"
    ray_address: str = ""
    cpus_per_variant: int = 2

    @property
    def logs(self) -> Path:
        """Where each variant's ``train-<variant>.log`` goes."""
        return self.data_dir / "logs"


def _parse_list(text: str) -> list[str]:
    items = [s.strip().strip("'\"") for s in text.strip().strip("[]").split(",")]
    return [s for s in items if s]


def _positive(key: str, text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v < 1:
        raise ConfigError(f"train-all.{key}: expected an integer >= 1, got {text!r}")
    return v


def split_args(argv: list[str]) -> tuple[dict[str, str], list[str]]:
    """This verb's own ``--KEY VALUE`` / ``--KEY=VALUE`` options (:data:`OWN_KEYS`) and the rest, in order."""
    own: dict[str, str] = {}
    rest: list[str] = []
    i = 0
    while i < len(argv):
        arg = argv[i]
        name, has_eq, value = arg[2:].partition("=") if arg.startswith("--") else ("", False, "")
        key = name.replace("-", "_")
        if key in OWN_KEYS:
            if not has_eq:
                if i + 1 >= len(argv) or argv[i + 1].startswith("--"):
                    raise ConfigError(f"option --{name} needs a value: expected --{name} VALUE or --{name}=VALUE")
                value, i = argv[i + 1], i + 1
            own[key] = value
        else:
            rest.append(arg)
        i += 1
    return own, rest


def make_plan(argv: list[str]) -> Plan:
    """Parses and checks everything up front (each variant's ``train`` config included); nothing runs."""
    own, rest = split_args(argv)
    variants = _parse_list(own.get("variants", ",".join(DEFAULT_VARIANTS)))
    if not variants:
        raise ConfigError("train-all.variants: expected at least one variant, got none")
    bad = [v for v in variants if v not in TRAIN_VARIANTS]
    if bad or len(set(variants)) != len(variants):
        raise ConfigError(f"train-all.variants: expected distinct names from {list(TRAIN_VARIANTS)}, got {variants}")
    executor = own.get("executor", "auto")
    address = own.get("ray_address", "")
    check_executor(executor, address, "train-all")
    parsed = parse_stage_args(STAGE, rest)
    for key in ("variant", "executor", "ray_address"):
        if key in parsed.overrides:
            raise ConfigError(f"train-all: --{key} is set per job by train-all (variants: --variants '[teacher, "
                              "full, ...]'; where they run: train-all's --executor / --ray_address)")
    cfgs = [load_config(STAGE.config_cls, STAGE.name, parsed.profile, {**parsed.overrides, "variant": v},
                        parsed.config_file) for v in variants]
    workers = cfgs[0].workers
    waves = [["teacher"]] if "teacher" in variants else []
    rest_wave = [v for v in variants if v != "teacher"]
    if rest_wave:
        waves.append(rest_wave)
    data_dir = Path(cfgs[0].data_dir)
    return Plan(waves=waves, passthrough=rest, data_dir=data_dir,
                jobs=_positive("jobs", own.get("jobs", "1")),
                executor=resolve_executor(executor, address), ray_address=address,
                cpus_per_variant=_positive("cpus_per_variant", own.get("cpus_per_variant", str(workers))))


def variant_job(variant: str, plan: Plan, module: str = "pipeline") -> ChildJob:
    """One variant's ``train`` as a child job: the passthrough arguments, ``--resume`` unless ``--overwrite`` (a rerun
    continues what is there), ``--executor local`` (the variant is what is distributed: its rollouts use the cores
    of the node that runs it), without ``RAY_ADDRESS``."""
    argv = list(plan.passthrough)
    if "--overwrite" not in argv and "--resume" not in argv:
        argv.append("--resume")
    return ChildJob(variant, ("train", "--variant", variant, *argv, "--executor", "local"),
                    str(plan.logs / f"train-{variant}.log"), module, drop_env=("RAY_ADDRESS",))


def run_plan(plan: Plan, module: str = "pipeline") -> list[dict]:
    """Runs the waves in order; returns every job's result (skipped students: ``returncode`` None)."""
    results: list[dict] = []
    executor = Executor(plan.executor, plan.ray_address, plan.data_dir)
    with executor.session(plan.cpus_per_variant):
        for wave in plan.waves:
            if any(r["name"] == "teacher" and r["returncode"] != 0 for r in results):
                results += [{"name": v, "returncode": None, "seconds": 0.0, "log": ""} for v in wave]
                continue
            jobs = [variant_job(v, plan, module) for v in wave]
            log.info("train-all: %s (%s, %s)", ", ".join(wave), plan.executor,
                     f"{plan.cpus_per_variant} CPUs per variant" if plan.executor == "ray" else f"{plan.jobs} at a time")
            results += map_jobs(run_child, jobs, min(plan.jobs, len(jobs)), "train-all", unit="variant",
                                executor=executor, cpus_per_job=plan.cpus_per_variant,
                                on_result=lambda _, r: log.info("train-all: %s exit %s after %.0f s (%s)",
                                                                r["name"], r["returncode"], r["seconds"], r["log"]))
    return results


def main(argv: list[str]) -> int:
    """train several variants (the teacher first), in turn, side by side or as Ray tasks -> checkpoints/policy/

    The module docstring is the verb's ``--help``."""
    if any(a in ("-h", "--help") for a in argv):
        print(__doc__)
        return 0
    plan = make_plan(argv)
    results = run_plan(plan)
    def state(r: dict) -> str:
        return "skipped (the teacher failed)" if r["returncode"] is None else f"exit {r['returncode']}"

    failed = [r for r in results if r["returncode"] != 0]
    for r in results:
        print(f"train-all: {r['name']}: {state(r)}, {r['seconds']:.0f} s" + (f" ({r['log']})" if r["log"] else ""))
    if failed:
        named = "; ".join(f"{r['name']} ({state(r)}" + (f", log {r['log']}: {log_tail(r['log'])}" if r["log"] else "")
                          + ")" for r in failed)
        raise ICrowdNavError(f"train-all: {len(failed)} of {len(results)} variants did not finish: {named}")
    return 0

