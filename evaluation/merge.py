"""One benchmark report from several eval runs of the same protocol: the paper's protocol is run one method at a time
on 2 cores (a student's 450 episodes take most of an hour), so its table is assembled from runs that share seeds.

::

    python -m evaluation.merge data/eval/p75_full data/eval/p75_no_i2 data/eval/p75_no_bev --out data/eval/p75_all
    python -m evaluation.merge data/eval/p75_full other/eval/p75_full:full_seen6 --out cmp   # rename a method

    python -m evaluation.merge data/eval/p75_lobby_corridor data/eval/p75_warehouse \
        data/eval/light@office_lobby,hospital_corridor,sarl_om --out data/eval/six_cells   # cells from several runs

Each argument is an eval run directory (its ``episodes.jsonl``, and ``scenarios/episodes.jsonl`` when present);
``RUN:NAME`` renames the run's method (a run of one method only) so that two trainings of one method can stand side by
side; ``RUN@a,b,...`` (before any ``:NAME``) takes only the run's rows of the named scenes and scenarios (all when
none is named) and of the named methods (likewise) — e.g. the baselines of a run whose other cells were measured on an
earlier version of a scene. Runs must share their protocol: the same seeds and scene
seeds (``seeds.json``), else the merge stops with an error naming the run that differs. They may cover different
cells (a six-cell table assembled from a warehouse run and a lobby / corridor run), but each method's cell (and
scenario) must come from one run only. A method may have run a subset of the episodes (``eval --method_episodes``, a
killed run): paired tests use the episodes both methods ran, and pooled tests the cells both ran.

Writes into ``--out``: ``seeds.json`` (the shared protocol, so that the folder is itself a run to merge or compare),
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

# a run directory, its method's new name, the scenes / scenarios / methods taken from it (None: all)
Run = tuple[Path, str | None, tuple[str, ...] | None]


def parse_run(arg: str) -> Run:
    """``RUN[@NAME,...][:NEW]``: a run directory, the scenes, scenarios and methods to take from it (None: all),
    the method's new name (None: kept)."""
    name = None
    path, sep, tail = arg.rpartition(":")
    if sep and tail and "/" not in tail and path:
        arg, name = path, tail
    only = None
    path, sep, tail = arg.rpartition("@")
    if sep and path and "/" not in tail:
        only = tuple(s for s in tail.split(",") if s)
        if not only:
            raise ConfigError(f"{arg}: expected scene, scenario or method names after '@', got none")
        arg = path
    return Path(arg), name, only


def _protocol(run: Path) -> list[tuple[Any, ...]]:
    return sorted((int(e["seed"]), e.get("scene_seed")) for e in read_protocol(run))


def _renamed(rows: list[dict[str, Any]], run: Path, name: str | None) -> list[dict[str, Any]]:
    if name is None:
        return rows
    methods = sorted({r["method"] for r in rows})
    if len(methods) != 1:
        raise ConfigError(f"{run}:{name}: renaming needs a run of one method, it holds {methods}")
    return [{**r, "method": name} for r in rows]


def _taken(rows: list[dict[str, Any]], scenes: set[str], methods: set[str]) -> list[dict[str, Any]]:
    """The rows of the named scenes (all when none is named) and methods (likewise)."""
    return [r for r in rows if (not scenes or r["scene"] in scenes) and (not methods or r["method"] in methods)]


def _claim(owner: dict[tuple, Path], rows: list[dict[str, Any]], run: Path, key) -> None:
    """Each (method, cell or scenario) comes from one run: a second one is an error naming both."""
    for k in sorted({key(r) for r in rows}, key=str):
        if k in owner:
            raise ConfigError(f"{run}: method {k[0]!r} in {' @ '.join(map(str, k[1:]))} is already in {owner[k]}; "
                              "rename one (RUN:NEW) or take other rows (RUN@scene,method,...)")
        owner[k] = run


def merge(runs: list[Run]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The benchmark and scenario rows of ``runs`` (renamed and restricted where asked), checked to share one
    protocol and to hold each method's cell once."""
    if len(runs) < 2:
        raise ConfigError(f"merge: expected at least two runs, got {len(runs)}")
    rows: list[dict[str, Any]] = []
    scen: list[dict[str, Any]] = []
    first_run, first = None, None
    owner: dict[tuple, Path] = {}
    for run, name, only in runs:
        protocol = _protocol(run)
        bench = _renamed(read_rows(run / "episodes.jsonl"), run, name)
        sc_path = run / "scenarios" / "episodes.jsonl"
        sc = _renamed(read_rows(sc_path), run, name) if sc_path.is_file() else []
        if only is not None:
            every = bench + sc
            held_scenes, held_methods = {r["scene"] for r in every}, {r["method"] for r in every}
            unknown = set(only) - held_scenes - held_methods
            if unknown:
                raise ConfigError(f"{run}@{','.join(only)}: expected scenes, scenarios or methods the run holds "
                                  f"({', '.join(sorted(held_scenes | held_methods))}), got {sorted(unknown)}")
            scenes, methods = set(only) & held_scenes, set(only) & held_methods
            bench, sc = _taken(bench, scenes, methods), _taken(sc, scenes, methods)
        if first is None:
            first_run, first = run, protocol
        outside = {int(r["seed"]) for r in bench} - {seed for seed, _ in protocol}
        if protocol != first or outside:
            raise ConfigError(f"{run}: not the protocol of {first_run} (other seeds or scene seeds); only runs of "
                              "the same protocol can be merged")
        _claim(owner, bench, run, lambda r: (r["method"], r["scene"], float(r["density"])))
        _claim(owner, sc, run, lambda r: (r["method"], "scenario", r["scene"]))
        rows += bench
        scen += sc
    return rows, scen


def write(rows: list[dict[str, Any]], scen: list[dict[str, Any]], runs: list[Run], out: Path,
          ref: str) -> None:
    methods = list(dict.fromkeys(r["method"] for r in rows))
    if ref not in methods:
        raise ConfigError(f"--ref: {ref!r} is not among the merged methods {methods}")
    labels = {m: method_label(m)[0] for m in methods}
    refs = [m for m in methods if method_label(m)[1]]
    out.mkdir(parents=True, exist_ok=True)
    res = results(rows)
    # the protocol the runs share (merge checked it), so that the merged folder is itself a run to compare or merge
    atomic_write_text(out / "seeds.json", (runs[0][0] / "seeds.json").read_text())
    atomic_write_text(out / "episodes.jsonl", "".join(json.dumps(r) + "\n" for r in json_safe(rows)))
    atomic_write_json(out / "results.json", json_safe(res))
    atomic_write_text(out / "results.csv", results_csv(res))
    atomic_write_json(out / "paired.json", json_safe({"reference": ref, "cells": paired(rows, ref),
                                                      "pooled": paired_pooled(rows, ref)}))
    plot_sr(res, labels, out / "figures" / "sr_by_cell.png")
    n = {m: sum(r["method"] == m for r in rows) // max(sum(m in by for by in res.values()), 1) for m in methods}
    per = (f"{n[methods[0]]} episodes per cell and method" if len(set(n.values())) == 1 else
           "episodes per cell " + ", ".join(f"`{m}` {k}" for m, k in n.items()) + " (paired tests use the episodes "
           "both methods ran)")
    header = (f"# Benchmark merged from {len(runs)} runs\n\n" + ", ".join(
        f"`{run}`" + (f" ({', '.join(only)} only)" if only else "") + (f" (as `{name}`)" if name else "")
        for run, name, only in runs)
        + f" — {per}, the same seeds for every method; methods: " + ", ".join(f"`{m}`" for m in methods) + ".")
    atomic_write_text(out / "report.md", report_markdown(rows, labels, header, references=refs, ref=ref,
                                                         scenario_rows=scen))


@reports_errors
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m evaluation.merge", description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="eval run directories: RUN, RUN:NEW, RUN@scene,method,...[:NEW]")
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
