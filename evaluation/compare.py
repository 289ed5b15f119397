"""Paired comparison of two runs on the same seeds: two trainings of one method, or one method with and without a
component (e.g. a student with the intention model vs its constant-velocity ablation), each trained into its own
data dir.

::

    python -m evaluation.compare data/checkpoints/policy/no_bev data/cvabl/checkpoints/policy/no_bev \\
        --labels intention,cv

Each argument is a file of per-episode rows — ``acceptance_episodes.jsonl`` (end of ``train``) or an eval run's
``episodes.jsonl`` / ``scenarios/episodes.jsonl``, or such a file gzipped (``docs/runs/``: the rows of the runs
docs/results.md cites, kept in git so that a later run can be paired with them) — or a directory holding one
(``acceptance_episodes.jsonl``, then ``episodes.jsonl``), or an eval run that has not finished (its ``rows/`` so far,
with a warning). Rows are matched by (scene, density, seed); per cell, pooled over the cells of each density and of
each scene (where the runs hold more than one), and pooled over all cells: SR of each, the exact McNemar test, the SR
difference detectable at 80 % power with these pairs, and the Wilcoxon test of the time in private zones (TPZ) over all
pairs and over the pairs both finished (TPZ sums an episode's time near people: a run whose episodes end sooner, in
contacts, has less of it over all pairs); pooled over the pairs, each failure outcome the two runs' rows both carry
(collision, pedestrian and obstacle collision, timeout: the exact McNemar test on who alone failed that way) and the
mean jerk of each. A run of several methods (an
eval run of ``--methods '[a, b]'``) is compared on one of them: ``--methods <first run's>,<second run's>`` (the same
run may then be given twice). Two eval runs whose episodes were timed (:mod:`evaluation.cost`) are also compared on
what their paired episodes cost per env step — e.g. a student with its encoder in fp32 and in int8, both runs started
together. Prints Markdown; ``--json`` writes the numbers.

A comparison replicated over independent trainings (e.g. ``full`` against ``w/o BEV`` in two chains trained with
different seeds, each evaluated on the same benchmark seeds) adds each further pair of runs with ``--also A B``
(``--methods`` applies to every pair): every pair of runs is matched on its own, its cells are reported tagged
with the replicate (``office_lobby [2]@0.1``), and the pooled test counts every replicate's pairs — independent
pairs, so the exact McNemar test on the summed discordant counts::

    python -m evaluation.compare run_s0 run_s0 --methods full,no_bev --also run_s1_full run_s1_no_bev
"""

from __future__ import annotations

import argparse
import gzip
import json
import logging
from pathlib import Path
from typing import Any

from evaluation.cost import episode_costs, paired_cost
from evaluation.report import matched, paired, paired_pooled
from evaluation.stats import mcnemar_exact
from pipeline.core.artifacts import atomic_write_json, json_safe
from pipeline.core.errors import (
    ConfigError,
    CorruptArtifactError,
    InputMissingError,
    reports_errors,
)

log = logging.getLogger("icrowdnav")

ROW_FILES = ("acceptance_episodes.jsonl", "episodes.jsonl")
KEYS = ("scene", "density", "seed", "success", "tpz_s")
OUTCOMES = ("collision", "collision_pedestrian", "collision_obstacle", "timeout")  # 0/1 per episode row
MEANS = ("mean_jerk_mps3",)


def checked_row(r: dict[str, Any], where: str) -> dict[str, Any]:
    """``r`` if it carries every key of :data:`KEYS`; otherwise a named error at ``where``."""
    missing = [key for key in KEYS if key not in r]
    if missing:
        raise CorruptArtifactError(f"{where}: row lacks {missing}")
    return r


def read_rows(path: Path) -> list[dict[str, Any]]:
    """The per-episode rows of a run (module docstring); every row must carry :data:`KEYS`."""
    path = Path(path)
    if path.is_dir():
        found = [path / n for n in ROW_FILES if (path / n).is_file()]
        if not found and (path / "rows").is_dir():
            return unfinished_run_rows(path)
        if not found:
            raise InputMissingError(f"{path}: no per-episode rows ({' or '.join(ROW_FILES)})")
        path = found[0]
    if not path.is_file():
        raise InputMissingError(f"no per-episode rows at {path}")
    rows = []
    for k, line in enumerate(row_text(path).splitlines(), 1):
        if not line.strip():
            continue
        try:
            r = json.loads(line)
        except json.JSONDecodeError as e:
            raise CorruptArtifactError(f"{path}:{k}: not a JSON row ({e})") from None
        rows.append(checked_row(r, f"{path}:{k}"))
    if not rows:
        raise InputMissingError(f"{path}: no rows")
    return rows


def row_text(path: Path) -> str:
    """The text of a rows file; a ``.gz`` one (an archived run's rows: ``docs/runs/``) decompressed, a damaged one a
    named error."""
    if path.suffix != ".gz":
        return path.read_text()
    try:
        return gzip.decompress(path.read_bytes()).decode()
    except (OSError, EOFError, UnicodeDecodeError) as e:  # gzip.BadGzipFile is an OSError
        raise CorruptArtifactError(f"{path}: not a gzip file of JSON rows ({type(e).__name__}: {e})") from None


def unfinished_run_rows(run: Path) -> list[dict[str, Any]]:
    """The benchmark rows an eval run that has not finished (no ``episodes.jsonl`` yet; killed, or still running)
    has written so far: its ``rows/`` cache (one file per finished episode), without the routing, scenario and
    long-horizon rows (a benchmark row carries its ``goal`` and its file no ``route_`` tag:
    :func:`evaluation.stage.benchmark_jobs`). Its cells run in a fixed order, so the finished ones are not chosen by
    their outcome; a cell in progress compares on the pairs it has."""
    rows = []
    for f in sorted((run / "rows").glob("*.json")):
        try:
            r = json.loads(f.read_text())
        except (OSError, ValueError) as e:
            raise CorruptArtifactError(f"{f}: unreadable episode row ({type(e).__name__}: {e})") from None
        if "goal" in checked_row(r, str(f)) and not f.name.startswith("route_"):
            rows.append(r)
    if not rows:
        raise InputMissingError(f"{run}: an unfinished eval run with no finished benchmark episode yet (rows/)")
    log.warning("%s: unfinished eval run (no episodes.jsonl): comparing its %d finished benchmark episodes",
                run, len(rows))
    return rows


def one_method(rows: list[dict[str, Any]], method: str | None, where: Path) -> list[dict[str, Any]]:
    """The rows of ``method`` (``None``: the run's only method) — a run of several methods (an eval run of
    ``--methods '[a, b]'``) must be told which, or its methods' episodes would be paired as one."""
    held = sorted({str(r["method"]) for r in rows if "method" in r})
    if method is None:
        if len(held) > 1:
            raise ConfigError(f"{where}: rows of {len(held)} methods {held}; name the one to compare with "
                              "--methods <method of the first run>,<method of the second>")
        return rows
    if method not in held:
        raise ConfigError(f"--methods: {where} has no rows of method {method!r} (it holds {held or 'unnamed rows'})")
    return [r for r in rows if r.get("method") == method]


def read_protocol(run: Path) -> list[dict[str, Any]]:
    """The benchmark episodes an eval run ran (``seeds.json``: per episode its ``seed``, ``goal``, ``trial`` and
    ``scene_seed``)."""
    path = Path(run) / "seeds.json"
    try:
        eps = json.loads(path.read_text())["benchmark"]["episodes"]
        if not isinstance(eps, list) or not all(isinstance(e, dict) and "seed" in e for e in eps):
            raise TypeError("benchmark.episodes is not a list of episodes with a seed")
        return eps
    except FileNotFoundError:
        raise InputMissingError(f"{path}: missing (an eval run's seeds say which episodes it ran)") from None
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise CorruptArtifactError(f"{path}: unreadable ({type(e).__name__}: {e})") from None


def pair_key(r: dict[str, Any]) -> tuple[str, float, int]:
    """What pairs two runs' episodes: the cell and the episode's seed."""
    return r["scene"], float(r["density"]), int(r["seed"])


def replicate(rows: list[dict[str, Any]], k: int) -> list[dict[str, Any]]:
    """``rows`` with their scene tagged as replicate ``k`` (``--also``): pairs are then matched within a replicate,
    and every replicate's cells count as cells of their own (``replicate_of`` keeps the scene for :data:`GROUPS`)."""
    return [{**r, "scene": f"{r['scene']} [{k}]", "replicate_of": r["scene"]} for r in rows]


def compare(a: list[dict[str, Any]], b: list[dict[str, Any]], labels: tuple[str, str]) -> dict[str, Any]:
    """``a`` (labelled ``labels[0]``, the reference) against ``b`` on their common (scene, density, seed)."""
    if labels[0] == labels[1]:
        raise ConfigError(f"compare: the two labels must differ, got {labels}")
    rows = [{**r, "method": labels[0]} for r in a] + [{**r, "method": labels[1]} for r in b]
    cells = paired(rows, labels[0])
    if not cells:
        raise InputMissingError("compare: the two runs share no (scene, density, seed)")

    common = {pair_key(r) for r in a} & {pair_key(r) for r in b}  # each SR over the pairs (an unfinished run has fewer)
    sr = {lab: {} for lab in labels}
    for lab, rs in zip(labels, (a, b), strict=True):
        for r in rs:
            if pair_key(r) in common:
                sr[lab].setdefault(f"{r['scene']}@{float(r['density']):g}", []).append(float(r["success"]))
    return {"reference": labels[0], "other": labels[1], "cells": cells,
            "pooled": paired_pooled(rows, labels[0]).get(labels[1]),
            "pooled_by": pooled_groups(rows, labels),
            "sr": {lab: {c: sum(v) / len(v) for c, v in cs.items()} for lab, cs in sr.items()},
            **pooled_outcomes(rows, labels[0])}


GROUPS = {"density": lambda r: f"{float(r['density']):g}",
          "scene": lambda r: r.get("replicate_of", r["scene"])}  # a replicate's cells join their scene
"""What the cells are pooled by besides all at once: the density (the paper reports each), the scene."""


def pooled_groups(rows: list[dict[str, Any]], labels: tuple[str, str]) -> dict[str, dict[str, Any]]:
    """Per grouping of :data:`GROUPS` that splits the runs' cells into more than one group and pools more than one
    cell in some group (else it would repeat the per-cell or the overall test): per group, the pooled paired test of
    :func:`evaluation.report.paired_pooled` (``labels[0]`` against ``labels[1]``) over its cells."""
    out: dict[str, dict[str, Any]] = {}
    for name, key in GROUPS.items():
        groups = {}
        for g in sorted({key(r) for r in rows}):
            res = paired_pooled([r for r in rows if key(r) == g], labels[0]).get(labels[1])
            if res is not None:
                groups[g] = res
        if len(groups) > 1 and max(d["n_cells"] for d in groups.values()) > 1:
            out[name] = groups
    return out


def pooled_outcomes(rows: list[dict[str, Any]], ref: str) -> dict[str, Any]:
    """Over the pairs of ``rows`` (:func:`evaluation.report.matched`, ``ref`` against the other label): per failure
    outcome of :data:`OUTCOMES` that every paired row carries, the count of each and the exact McNemar test
    (``a_only``: only ``ref`` failed that way); per key of :data:`MEANS` carried by all, the mean of each. Rows of
    older runs without a key leave it out."""
    pairs = [(x, y) for _, _, a, b in matched(rows, ref) for x, y in zip(a, b, strict=True)]
    outcomes, means = {}, {}
    for k in (*OUTCOMES, *MEANS):
        if not all(k in x and k in y for x, y in pairs):
            continue
        xs, ys = [float(x[k]) for x, _ in pairs], [float(y[k]) for _, y in pairs]
        if k in MEANS:
            means[k] = [sum(xs) / len(xs), sum(ys) / len(ys)]
        else:
            outcomes[k] = {**mcnemar_exact(xs, ys), "count_a": sum(v > 0.5 for v in xs),
                           "count_b": sum(v > 0.5 for v in ys)}
    return {"outcomes": outcomes, "means": means}


def markdown(res: dict[str, Any]) -> str:
    a, b = res["reference"], res["other"]
    lines = [f"| cell | pairs | SR {a} | SR {b} | {a} only / {b} only | McNemar p | detectable ΔSR | TPZ Wilcoxon p, "
             "all pairs | TPZ Wilcoxon p, pairs both finished |",
             "|---|---|---|---|---|---|---|---|---|"]

    def p(x: Any) -> str:
        return "—" if x is None or x != x else f"{x:.3f}"

    for cell, d in res["cells"].items():
        e = d[b]
        s = e["sr"]
        lines.append(f"| {cell} | {e['n_pairs']} | {res['sr'][a][cell]:.2f} | {res['sr'][b][cell]:.2f} | "
                     f"{s['a_only']} / {s['b_only']} | {p(s['p_value'])} | {p(s['detectable_diff'])} | "
                     f"{p(e['tpz_s'].get('p_value'))} | {p(e['tpz_s_success'].get('p_value'))} |")
    lines += ["", "TPZ sums an episode's time near people: over all pairs a run whose episodes end sooner (in "
              "contacts) has less of it without being more comfortable; over the pairs both finished the two drove "
              "the same task to its end (the paper's TPZ is over successes)."]
    pooled = res["pooled"]["sr"]
    lines += ["", f"Pooled over {res['pooled']['n_cells']} cells: {pooled['n']} pairs, ΔSR ({a} − {b}) "
              f"{pooled['sr_diff']:+.3f}, {pooled['a_only']} / {pooled['b_only']} discordant, McNemar p = "
              f"{p(pooled['p_value'])}, detectable ΔSR at 80 % power {p(pooled['detectable_diff'])}."]
    for name, groups in res["pooled_by"].items():
        lines += ["", f"| pooled by {name} | cells | pairs | ΔSR ({a} − {b}) | {a} only / {b} only | McNemar p | "
                  "detectable ΔSR |", "|---|---|---|---|---|---|---|"]
        lines += [f"| {g} | {d['n_cells']} | {d['sr']['n']} | {d['sr']['sr_diff']:+.3f} | {d['sr']['a_only']} / "
                  f"{d['sr']['b_only']} | {p(d['sr']['p_value'])} | {p(d['sr']['detectable_diff'])} |"
                  for g, d in groups.items()]
    if res["outcomes"]:
        lines += ["", f"| pooled failure outcome | {a} | {b} | only {a} / only {b} failed so | McNemar p |", "|---|---|---|---|---|"]
        lines += [f"| {k} | {o['count_a']} | {o['count_b']} | {o['a_only']} / {o['b_only']} | {p(o['p_value'])} |"
                  for k, o in res["outcomes"].items()]
    for k, (ma, mb) in res["means"].items():
        lines += ["", f"Mean of {k} over the pairs: {a} {ma:.2f}, {b} {mb:.2f}."]
    c = res.get("cost")
    if c and c["wall_ratio"] and c["cpu_ratio"] and c["median_episode_ratio"]:
        lines += ["", f"Compute over the {c['pairs']} episodes both runs timed (evaluation.cost; one worker's wall "
                  f"per env step): {a} {c['wall_ms_per_step'][0]:.1f} ms, {b} {c['wall_ms_per_step'][1]:.1f} ms, "
                  f"{a} / {b} = {c['wall_ratio']:.2f} (median per episode {c['median_episode_ratio']:.2f}); CPU "
                  f"{c['cpu_ms_per_step'][0]:.1f} vs {c['cpu_ms_per_step'][1]:.1f} ms per step "
                  f"({c['cpu_ratio']:.2f}). Runs timed on one machine at one time compare; others need not."]
    return "\n".join(lines) + "\n"


@reports_errors
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m evaluation.compare", description=__doc__.split("\n\n")[0])
    ap.add_argument("a", type=Path, help="reference run: rows file or directory")
    ap.add_argument("b", type=Path, help="the other run")
    ap.add_argument("--labels", default="a,b", help="names of the two runs, comma-separated")
    ap.add_argument("--methods", default=None,
                    help="the method of each run to compare, comma-separated (needed where a run holds several)")
    ap.add_argument("--also", nargs=2, type=Path, action="append", default=[], metavar=("A", "B"),
                    help="a further replicate: its reference run and its other run (repeatable)")
    ap.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = ap.parse_args(argv)
    labels = tuple(x.strip() for x in args.labels.split(","))
    if len(labels) != 2 or not all(labels):
        raise ConfigError(f"--labels: expected two comma-separated names, got {args.labels!r}")
    methods: tuple[str | None, ...] = (None, None)
    if args.methods is not None:
        methods = tuple(x.strip() for x in args.methods.split(","))
        if len(methods) != 2 or not all(methods):
            raise ConfigError(f"--methods: expected two comma-separated method names, got {args.methods!r}")
    pairs = [[one_method(read_rows(p), m, p) for p, m in zip(pair, methods, strict=True)]
             for pair in ((args.a, args.b), *args.also)]
    for (ra, rb), pair in zip(pairs[1:], args.also, strict=True):
        if not {pair_key(r) for r in ra} & {pair_key(r) for r in rb}:
            raise InputMissingError(f"--also {pair[0]} {pair[1]}: the two runs share no (scene, density, seed)")
    first = pairs[0]
    if len(pairs) > 1:  # replicates: each pair's cells tagged with its number, so pairs match within it
        pairs = [[replicate(rows, k) for rows in pair] for k, pair in enumerate(pairs, 1)]
    a, b = ([r for pair in pairs for r in pair[i]] for i in (0, 1))
    res = compare(a, b, labels)
    if args.a.is_dir() and args.b.is_dir():  # two timed eval runs: what their episodes cost, pair by pair
        res["cost"] = paired_cost(*(episode_costs(run, rows)
                                    for run, rows in zip((args.a, args.b), first, strict=True)))
    if args.json:
        atomic_write_json(args.json, json_safe(res))
    print(markdown(res), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
