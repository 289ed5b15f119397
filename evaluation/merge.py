"""One benchmark report from several eval runs of the same protocol: the paper's protocol is run one method at a time
on 2 cores (a student's 450 episodes take most of an hour), so its table is assembled from runs that share seeds.

::

    python -m evaluation.merge data/eval/p75_full data/eval/p75_no_i2 data/eval/p75_no_bev --out data/eval/p75_all
    python -m evaluation.merge data/eval/p75_full other/eval/p75_full:full_seen6 --out cmp   # rename a method

Each argument is an eval run directory (its ``episodes.jsonl``, and ``scenarios/episodes.jsonl`` when present);
``RUN:NAME`` renames the run's method (a run of one method only) so that two trainings of one method can stand side by
side. Runs must share their protocol: the same cells and the same seeds and scene seeds (``seeds.json``), else the
merge stops with an error naming the run that differs; a method may have run a subset of the episodes (``eval
--method_episodes``, a killed run): paired tests use the episodes both methods ran. Writes into ``--out``:
``episodes.jsonl``, ``results.json`` / ``results.csv``, ``paired.json`` (``--ref`` against every other method, per
cell and pooled), ``report.md`` and ``figures/sr_by_cell.png`` — the files of an ``icrowdnav eval`` run
(:mod:`evaluation.report`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from evaluation.compare import read_protocol, read_rows
from evaluation.methods import method_label
from evaluation.report import paired, paired_pooled, plot_sr, report_markdown, results, results_csv
from pipeline.core.artifacts import atomic_write_json, atomic_write_text, json_safe
from pipeline.core.errors import ConfigError, reports_errors


def parse_run(arg: str) -> tuple[Path, str | None]:
    """``RUN`` or ``RUN:NAME`` (a run directory, the method's new name)."""
    path, sep, name = arg.rpartition(":")
    if sep and name and "/" not in name and path:
        return Path(path), name
    return Path(arg), None


def _protocol(run: Path) -> list[tuple[Any, ...]]:
    return sorted((int(e["seed"]), e.get("scene_seed")) for e in read_protocol(run))


def _renamed(rows: list[dict[str, Any]], run: Path, name: str | None) -> list[dict[str, Any]]:
    if name is None:
        return rows
    methods = sorted({r["method"] for r in rows})
    if len(methods) != 1:
        raise ConfigError(f"{run}:{name}: renaming needs a run of one method, it holds {methods}")
    return [{**r, "method": name} for r in rows]


def merge(runs: list[tuple[Path, str | None]]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The benchmark and scenario rows of ``runs`` (renamed where asked), checked to share one protocol."""
    if len(runs) < 2:
        raise ConfigError(f"merge: expected at least two runs, got {len(runs)}")
    rows: list[dict[str, Any]] = []
    scen: list[dict[str, Any]] = []
    first_run, first, episodes = None, None, None
    owner: dict[str, Path] = {}
    for run, name in runs:
        protocol = _protocol(run)
        bench = _renamed(read_rows(run / "episodes.jsonl"), run, name)
        cells = sorted({(r["scene"], float(r["density"])) for r in bench})
        if first is None:
            first_run, first, episodes = run, protocol, cells
        outside = {int(r["seed"]) for r in bench} - {seed for seed, _ in protocol}
        if protocol != first or cells != episodes or outside:
            raise ConfigError(f"{run}: not the protocol of {first_run} (other seeds, scene seeds or cells); only "
                              "runs of the same protocol can be merged")
        for m in sorted({r["method"] for r in bench}):
            if m in owner:
                raise ConfigError(f"{run}: method {m!r} is already in {owner[m]}; rename one (RUN:NAME)")
            owner[m] = run
        rows += bench
        if (run / "scenarios" / "episodes.jsonl").is_file():
            scen += _renamed(read_rows(run / "scenarios" / "episodes.jsonl"), run, name)
    return rows, scen


def write(rows: list[dict[str, Any]], scen: list[dict[str, Any]], runs: list[tuple[Path, str | None]], out: Path,
          ref: str) -> None:
    methods = list(dict.fromkeys(r["method"] for r in rows))
    if ref not in methods:
        raise ConfigError(f"--ref: {ref!r} is not among the merged methods {methods}")
    labels = {m: method_label(m)[0] for m in methods}
    refs = [m for m in methods if method_label(m)[1]]
    out.mkdir(parents=True, exist_ok=True)
    res = results(rows)
    atomic_write_text(out / "episodes.jsonl", "".join(json.dumps(r) + "\n" for r in json_safe(rows)))
    atomic_write_json(out / "results.json", json_safe(res))
    atomic_write_text(out / "results.csv", results_csv(res))
    atomic_write_json(out / "paired.json", json_safe({"reference": ref, "cells": paired(rows, ref),
                                                      "pooled": paired_pooled(rows, ref)}))
    plot_sr(res, labels, out / "figures" / "sr_by_cell.png")
    n = {m: sum(r["method"] == m for r in rows) // max(len(res), 1) for m in methods}
    per = (f"{n[methods[0]]} episodes per cell and method" if len(set(n.values())) == 1 else
           "episodes per cell " + ", ".join(f"`{m}` {k}" for m, k in n.items()) + " (paired tests use the episodes "
           "both methods ran)")
    header = (f"# Benchmark merged from {len(runs)} runs\n\n" + ", ".join(
        f"`{run}`" + (f" (as `{name}`)" if name else "") for run, name in runs)
        + f" — {per}, the same seeds for every method; methods: " + ", ".join(f"`{m}`" for m in methods) + ".")
    atomic_write_text(out / "report.md", report_markdown(rows, labels, header, references=refs, ref=ref,
                                                         scenario_rows=scen))


@reports_errors
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m evaluation.merge", description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="eval run directories, RUN or RUN:NAME")
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument("--ref", default="full", help="the method compared with every other (default full)")
    args = ap.parse_args(argv)
    runs = [parse_run(a) for a in args.runs]
    rows, scen = merge(runs)
    write(rows, scen, runs, args.out, args.ref)
    print(f"merged {len(rows)} episodes of {len({r['method'] for r in rows})} methods -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
