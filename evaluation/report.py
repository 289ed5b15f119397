"""Tables, paired comparisons and figures from per-episode rows (``episodes.jsonl``).

* ``results.json`` / ``results.csv`` — per (scene, density, method): N and every metric's mean, std, 95 % CI;
* ``paired.json`` — the full model against every other method on the same seeds: SR by an exact McNemar test
  (the discordant pairs) with the smallest SR difference it detects at 80 % power given the observed discordance
  (:mod:`evaluation.stats`), TPZ by a Wilcoxon signed-rank test on all episodes, NT and PL by Wilcoxon on the
  episodes both methods finished; per cell and pooled over the cells;
* ``report.md`` — the paper's tables (SR, collision, timeout with Wilson CIs; NT, PL, TPZ mean ± std over successes;
  N), the paired tests, the paper's expected ordering checked against our numbers, the long-horizon table;
* ``figures/sr_by_cell.png`` — SR with 95 % CIs per cell and method.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from evaluation.stats import detectable_difference, max_discordance, mcnemar_exact, pooled_mcnemar
from sim.metrics import aggregate, metrics_table_markdown, paired_test
from sim.viz import save_figure

TABLE_METRICS = ("success", "collision", "timeout", "nav_time_s", "path_length_m", "tpz_s")
ALPHA, POWER = 0.05, 0.8  # the detectable-difference columns: two-sided McNemar at 5 %, 80 % power


def cells_of(rows: Sequence[dict[str, Any]]) -> list[tuple[str, float]]:
    seen: dict[tuple[str, float], None] = {}
    for r in rows:
        seen[(r["scene"], float(r["density"]))] = None
    return list(seen)


def methods_of(rows: Sequence[dict[str, Any]]) -> list[str]:
    seen: dict[str, None] = {}
    for r in rows:
        seen[r["method"]] = None
    return list(seen)


def results(rows: Sequence[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """``{"<scene>@<density>": {method: aggregate(rows)}}``."""
    out: dict[str, dict[str, Any]] = {}
    for scene, d in cells_of(rows):
        cell = [r for r in rows if r["scene"] == scene and float(r["density"]) == d]
        out[f"{scene}@{d:g}"] = {m: aggregate([r for r in cell if r["method"] == m]) for m in methods_of(cell)}
    return out


def results_csv(res: dict[str, dict[str, Any]]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["cell", "method", "metric", "n", "mean", "std", "ci95_low", "ci95_high"])
    for cell, by_m in res.items():
        for m, agg in by_m.items():
            for k, s in agg.items():
                if isinstance(s, dict):
                    w.writerow([cell, m, k, s.get("n"), *(_num(s.get(q)) for q in ("mean", "std", "ci95_low",
                                                                                       "ci95_high"))])
    return buf.getvalue()


def _num(v: Any) -> str:
    return "" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{float(v):.6g}"


def matched(rows: Sequence[dict[str, Any]], ref: str):
    """Per cell with ``ref`` and per other method: ``(cell, other, ref_rows, other_rows)``, the rows of the seeds
    both ran, in seed order."""
    for scene, d in cells_of(rows):
        cell = [r for r in rows if r["scene"] == scene and float(r["density"]) == d]
        by = {m: {r["seed"]: r for r in cell if r["method"] == m} for m in methods_of(cell)}
        if ref not in by:
            continue
        for m, other in by.items():
            if m != ref:
                seeds = sorted(set(by[ref]) & set(other))
                yield f"{scene}@{d:g}", m, [by[ref][s] for s in seeds], [other[s] for s in seeds]


def _sr_test(a: Sequence[dict[str, Any]], b: Sequence[dict[str, Any]]) -> dict[str, float]:
    """Exact McNemar on the successes of matched rows, with the SR difference it detects at POWER."""
    sr = mcnemar_exact([r["success"] for r in a], [r["success"] for r in b])
    sr["detectable_diff"] = detectable_difference(sr["n"], sr["discordant"], ALPHA, POWER)
    return sr


def paired(rows: Sequence[dict[str, Any]], ref: str = "full") -> dict[str, dict[str, Any]]:
    """``{"<cell>": {other: {"sr": mcnemar, "tpz_s": wilcoxon, "tpz_s_success": ..., "nav_time_s": ...,
    "path_length_m": ...}}}``.

    ``tpz_s`` is tested over every pair; ``tpz_s_success``, NT and PL over the pairs both methods finished. TPZ sums
    an episode's time near people, so over every pair a method whose episodes end sooner (in contacts) scores lower
    TPZ without being more comfortable; over the pairs both finished the two drove the same task to its end (the
    paper reports TPZ over successful episodes)."""
    out: dict[str, dict[str, Any]] = {}
    for cell, m, a, b in matched(rows, ref):
        entry = {"n_pairs": len(a), "sr": _sr_test(a, b),
                 "tpz_s": paired_test([r["tpz_s"] for r in a], [r["tpz_s"] for r in b])}
        both = [(x, y) for x, y in zip(a, b, strict=True) if x["success"] == 1 and y["success"] == 1]
        for k, key in (("nav_time_s", "nav_time_s"), ("path_length_m", "path_length_m"), ("tpz_s_success", "tpz_s")):
            entry[k] = paired_test([x[key] for x, _ in both], [y[key] for _, y in both])
        out.setdefault(cell, {})[m] = entry
    return out


def paired_pooled(rows: Sequence[dict[str, Any]], ref: str = "full") -> dict[str, dict[str, Any]]:
    """``ref`` against every other method over all cells' pairs at once: ``{other: {"sr": McNemar with its
    detectable difference, "n_cells", "max_discordance_for_0.10": the largest discordance at which a 10-point
    difference is still detectable with these pairs}}``."""
    by_method: dict[str, list[tuple[list[float], list[float]]]] = {}
    for _, m, a, b in matched(rows, ref):
        by_method.setdefault(m, []).append(([r["success"] for r in a], [r["success"] for r in b]))
    out = {}
    for m, cells in by_method.items():
        sr = pooled_mcnemar(cells)
        sr["detectable_diff"] = detectable_difference(sr["n"], sr["discordant"], ALPHA, POWER)
        out[m] = {"n_cells": len(cells), "sr": sr,
                  "max_discordance_for_0.10": max_discordance(sr["n"], 0.10, ALPHA, POWER)}
    return out


def _fmt_d(x: float) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:+.2f}"


def _fmt_p(p: float) -> str:
    return "n/a" if p is None or not math.isfinite(p) else (f"{p:.3f}" if p >= 0.001 else "<0.001")


def _sr(agg: dict[str, Any]) -> float:
    return float(agg.get("success", {}).get("mean", math.nan))


def _tpz(agg: dict[str, Any]) -> float:
    return float(agg.get("tpz_s", {}).get("mean", math.nan))


def shape_checks(res: dict[str, dict[str, Any]]) -> list[str]:
    """The paper's expected ordering, checked cell by cell; each line states the numbers (never tuned)."""
    lines = []
    for cell, by in res.items():
        if not cell.endswith("@0.2") or "full" not in by:
            continue
        f = _sr(by["full"])
        for ab in ("no_i2", "no_bev"):
            if ab in by:
                ok = f >= _sr(by[ab])
                lines.append(f"- {cell}: SR full {f:.2f} {'≥' if ok else '<'} {ab} {_sr(by[ab]):.2f} — "
                             f"{'as in the paper' if ok else 'differs from the paper'}")
                if "dwa" in by:
                    ok2 = _sr(by[ab]) >= _sr(by["dwa"])
                    lines.append(f"- {cell}: SR {ab} {_sr(by[ab]):.2f} {'≥' if ok2 else '<'} DWA "
                                 f"{_sr(by['dwa']):.2f} — {'as in the paper' if ok2 else 'differs from the paper'}")
    for cell, by in res.items():  # the paper's Tables I-III: full has the highest SR of every learned baseline
        if "full" not in by:
            continue
        f = _sr(by["full"])
        for bl in ("drl_vo", "sarl_om", "vint"):
            if bl in by:
                ok = f >= _sr(by[bl])
                lines.append(f"- {cell}: SR full {f:.2f} {'≥' if ok else '<'} {bl} {_sr(by[bl]):.2f} — "
                             f"{'as in the paper' if ok else 'differs from the paper'}")
    for cell, by in res.items():
        if "full" in by and "no_i2" in by:
            a, b = _tpz(by["full"]), _tpz(by["no_i2"])
            ok = a < b
            lines.append(f"- {cell}: TPZ full {a:.2f} s {'<' if ok else '≥'} w/o I² {b:.2f} s — "
                         f"{'as in the paper' if ok else 'differs from the paper'}")
    return lines


def training_budget(ckpt: Path) -> dict[str, Any]:
    """What produced a checkpoint: ``produced_by`` of its ``policy.json`` and ``train_seconds`` of its
    ``metrics.json`` (when the train stage wrote one)."""
    desc = json.loads((Path(ckpt) / "policy.json").read_text())
    out = {"produced_by": desc.get("produced_by", {})}
    metrics = Path(ckpt) / "metrics.json"
    if metrics.is_file():
        out["train_seconds"] = json.loads(metrics.read_text()).get("train_seconds")
    return out


def _budget_text(produced_by: dict[str, Any], prefix: str = "") -> str:
    parts = []
    for k, v in sorted(produced_by.items()):
        if isinstance(v, dict):
            parts.append(_budget_text(v, f"{prefix}{k}."))
        else:
            parts.append(f"{prefix}{k} {v}")
    return ", ".join(p for p in parts if p) or ("" if prefix else "n/a")


def report_markdown(rows: Sequence[dict[str, Any]], labels: dict[str, str], header: str,
                    lh_rows: Sequence[dict[str, Any]] = (), references: Sequence[str] = (),
                    budgets: dict[str, dict[str, Any]] | None = None,
                    routing_rows: Sequence[dict[str, Any]] = (), ref: str = "full",
                    scenario_rows: Sequence[dict[str, Any]] = (),
                    cue_twin_rows: Sequence[dict[str, Any]] = ()) -> str:
    """The run's ``report.md``: tables per cell, paired comparisons of ``ref`` with every other method (per cell
    and pooled, with the detectable difference), the paper's ordering, routing cells and long horizon."""
    res = results(rows)
    parts = [header, ""]
    if references:
        parts.append("Upper references (privileged information, not competitors): "
                     + ", ".join(labels.get(m, m) for m in references) + ".\n")
    if budgets:
        parts.append("## Training budgets (what produced each checkpoint)\n")
        parts.append("| method | produced by | train wall [s] |")
        parts.append("|---|---|---|")
        for m, b in budgets.items():
            secs = b.get("train_seconds")
            parts.append(f"| {labels.get(m, m)} | {_budget_text(b.get('produced_by', {}))} | "
                         f"{'n/a' if secs is None else f'{float(secs):.0f}'} |")
        parts.append("")
    parts.append("SR, collision and timeout: percent with the 95 % Wilson interval. NT, PL, TPZ: mean ± std over "
                 "successful episodes (their count in parentheses).\n")
    parts.extend(_cell_tables(rows, labels))
    parts.extend(_paired_section(rows, labels, f"## Paired comparisons with {labels.get(ref, ref)} (same seeds)",
                                 ref))
    pooled = paired_pooled(rows, ref)
    if pooled:
        n_cells = max(e["n_cells"] for e in pooled.values())
        parts.append(f"### Pooled over the {n_cells} cells\n")
        parts.append("The same tests on every cell's pairs at once. *Detectable ΔSR*: the smallest SR difference "
                     f"a two-sided McNemar test at {ALPHA:g} detects with {POWER:.0%} power at the observed "
                     "discordance ψ. *ψ max for 10 pts*: the largest discordance at which these pairs still detect a "
                     "10-point difference (the run is sized so that ψ stays below it).\n")
        parts.append(f"| other | pairs | ΔSR | {ref} only / other only | ψ | p (SR) | detectable ΔSR | "
                     "ψ max for 10 pts |")
        parts.append("|---|---|---|---|---|---|---|---|")
        for m, e in pooled.items():
            sr = e["sr"]
            parts.append(f"| {labels.get(m, m)} | {sr['n']} | {sr['sr_diff']:+.3f} | {sr['a_only']} / "
                         f"{sr['b_only']} | {sr['discordant']:.3f} | {_fmt_p(sr['p_value'])} | "
                         f"{_fmt_mdd(sr['detectable_diff'])} | {e['max_discordance_for_0.10']:.2f} |")
        parts.append("")
    checks = shape_checks(res)
    if checks:
        parts.append("## The paper's expected ordering, checked\n")
        parts.extend(checks)
        parts.append("")
    if routing_rows:
        parts.append("## Warehouse routing (not in the paper): every method follows the global planner's "
                     "waypoints\n")
        parts.append("The shelf hall where start and goal may lie in different aisles; each method is handed the "
                     "same waypoints (the corners of the shortest path on the map), as in the long-horizon runs, "
                     "so the cell measures crowd navigation along a given route.\n")
        parts.extend(_cell_tables(routing_rows, labels))
        parts.extend(_paired_section(routing_rows, labels, "### Paired comparisons (routing)", ref))
    if scenario_rows:
        parts.extend(scenario_table(scenario_rows, labels))
    if cue_twin_rows:
        parts.extend(cue_twin_table(cue_twin_rows, labels, ref))
    if lh_rows:
        parts.append("## Long-horizon navigation on the topological map (paper §IV-C)\n")
        by_map: dict[str, dict[str, list]] = {}
        for r in lh_rows:
            by_map.setdefault(r["scene"], {}).setdefault(labels.get(r["method"], r["method"]), []).append(r)
        for scene, by in by_map.items():
            parts.append(f"### {scene}\n\n" + metrics_table_markdown(by))
    return "\n".join(parts) + "\n"


def scenario_table(rows: Sequence[dict[str, Any]], labels: dict[str, str]) -> list[str]:
    """The scenario suite: per scenario and method, SR, collisions with the scripted pedestrians, the minimum
    clearance to them and the reaction time to their cue (:func:`sim.scenario.scenario_metrics`)."""
    parts = ["## Scenario suite (scripted pedestrians)\n",
             "Per scenario and method over its seeded trials: SR; *hit scripted*: episodes ending in a collision with "
             "a scripted pedestrian; *min clearance*: robot footprint to the nearest scripted body, mean ± std [m]; "
             "*reaction*: seconds from the onset of the pedestrian's cue (head/torso lead before a turn, else the "
             "start) to the first command change that increases the predicted clearance — median over the "
             "episodes that reacted, with their count (a negative value: the robot was already changing course "
             "before the cue).\n",
             "| scenario | method | N | SR | hit scripted | min clearance [m] | reaction [s] (reacted) |",
             "|---|---|---|---|---|---|---|"]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for m in methods_of(rows):
            rs = [r for r in rows if r["scene"] == scene and r["method"] == m]
            if not rs:
                continue
            clr = np.array([r["min_clearance_scripted_m"] for r in rs], float)
            react = np.array([r["reaction_time_s"] for r in rs], float)
            react = react[np.isfinite(react)]
            parts.append(f"| {scene} | {labels.get(m, m)} | {len(rs)} | {np.mean([r['success'] for r in rs]):.2f} | "
                         f"{int(sum(r['collision_scripted'] for r in rs))} | {np.nanmean(clr):.2f} ± "
                         f"{np.nanstd(clr):.2f} | {(f'{np.median(react):.1f}' if len(react) else 'n/a')} "
                         f"({len(react)}/{len(rs)}) |")
    parts.append("")
    return parts


def cue_timing_test(a: Sequence[dict[str, Any]], b: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """When two methods respond to the cue, over paired trials (cue-twin rows in the same order) in which both
    changed course: ``{"n", "median_diff": median of a − b [s], "earlier": pairs with a first, "later", "p_value":
    two-sided Wilcoxon signed-rank (:func:`sim.metrics.paired_test`; nan under 5 pairs)}``. The times are multiples
    of the control step, so they are rounded to the microsecond first: equal steps tie exactly."""
    x = np.round(np.array([r["cue_divergence_s"] for r in a], float), 6)
    y = np.round(np.array([r["cue_divergence_s"] for r in b], float), 6)
    d = (x - y)[np.isfinite(x) & np.isfinite(y)]
    return {"n": int(d.size), "median_diff": float(np.median(d)) if d.size else math.nan,
            "earlier": int((d < 0).sum()), "later": int((d > 0).sum()), "p_value": paired_test(x, y)["p_value"]}


def cue_twin_table(rows: Sequence[dict[str, Any]], labels: dict[str, str], ref: str = "full") -> list[str]:
    """What the pedestrians' cue alone changed, per scenario and method (:func:`sim.scenario.cue_twin_metrics`), and
    ``ref`` against each other method on the trials the cue made change course before the walk turned."""
    parts = ["## The cue alone: each scenario trial with and without the head/torso lead\n",
             "Each trial also ran as its no-cue twin: the same seed and walk, the scripted pedestrians' head and torso "
             "not turning before their walking direction does. *Changed*: trials in which the robot's commands differ "
             "between the two runs after the cue's onset (only the cue differs, so that difference is a response to "
             "it); *before the turn*: changed within the cue's lead, before the walking direction changed; *at [s]*: "
             "median seconds from the onset to the first differing command; *safer*: of the changed trials, those "
             "whose first differing command predicts more clearance to the scripted pedestrians over 2 s; clearance "
             "and hits with / without the cue; *twins*: trials whose two runs agree on every command before the "
             "onset (all, or the runs are not twins).\n",
             "| scenario | method | N | changed | before the turn | at [s] | safer | min clearance with / without cue "
             "[m] | hit scripted with / without | twins |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    for scene in scenes:
        for m in methods_of(rows):
            rs = [r for r in rows if r["scene"] == scene and r["method"] == m]
            if not rs:
                continue
            div = np.array([r["cue_divergence_s"] for r in rs], float)
            changed = np.isfinite(div)
            safer = [r["cue_divergence_safer"] for r in rs if math.isfinite(r["cue_divergence_safer"])]
            parts.append(
                f"| {scene} | {labels.get(m, m)} | {len(rs)} | {int(changed.sum())} | "
                f"{int(sum(r['cue_anticipated'] for r in rs))} | "
                f"{(f'{np.median(div[changed]):.1f}' if changed.any() else 'n/a')} | {int(sum(safer))} / {len(safer)} | "
                f"{np.nanmean([r['min_clearance_scripted_m'] for r in rs]):.2f} / "
                f"{np.nanmean([r['twin_min_clearance_scripted_m'] for r in rs]):.2f} | "
                f"{int(sum(r['collision_scripted'] for r in rs))} / {int(sum(r['twin_collision_scripted'] for r in rs))}"
                f" | {int(sum(r['twin_identical_before_cue'] for r in rs))} / {len(rs)} |")
    tests = []
    for scene in scenes:
        own = {r["seed"]: r for r in rows if r["scene"] == scene and r["method"] == ref}
        for m in methods_of(rows):
            other = {r["seed"]: r for r in rows if r["scene"] == scene and r["method"] == m}
            seeds = sorted(set(own) & set(other))
            if m == ref or not seeds:
                continue
            t = mcnemar_exact([own[k]["cue_anticipated"] for k in seeds], [other[k]["cue_anticipated"] for k in seeds])
            w = cue_timing_test([own[k] for k in seeds], [other[k] for k in seeds])
            tests.append(f"| {scene} | {labels.get(m, m)} | {len(seeds)} | {t['a_only']} / {t['b_only']} | "
                         f"{_fmt_p(t['p_value'])} | {w['n']} | {_fmt_d(w['median_diff'])} | "
                         f"{w['earlier']} / {w['later']} | {_fmt_p(w['p_value'])} |")
    if tests:
        r = labels.get(ref, ref)
        parts += ["", f"{r} against each method on the same trials: *changed course before the turn* (exact McNemar); "
                      f"*when*: over the trials in which both changed course, the first differing command's time, "
                      f"{r} − other (median [s], trials in which {r} came earlier / later, two-sided Wilcoxon "
                      "signed-rank).\n",
                  f"| scenario | other | trials | before the turn: only {r} / only other | p | both changed | "
                  f"when: median {r} − other [s] | {r} earlier / later | p |",
                  "|---|---|---|---|---|---|---|---|---|", *tests]
    parts.append("")
    return parts


def _cell_tables(rows: Sequence[dict[str, Any]], labels: dict[str, str]) -> list[str]:
    parts = []
    for scene, d in cells_of(rows):
        by = {labels.get(m, m): [r for r in rows if r["scene"] == scene and float(r["density"]) == d
                                 and r["method"] == m] for m in methods_of(rows)}
        by = {k: v for k, v in by.items() if v}
        parts.append(f"### {scene} @ {d:g} ped/m²\n\n" + metrics_table_markdown(by))
    return parts


def _paired_section(rows: Sequence[dict[str, Any]], labels: dict[str, str], title: str, ref: str) -> list[str]:
    pr = paired(rows, ref)
    if not pr:
        return []
    parts = [title + "\n",
             f"SR: exact McNemar test (episodes only {ref} / only the other method finished); ψ = the "
             f"discordant fraction; *detectable* = the smallest |ΔSR| detected with {POWER:.0%} power at "
             f"{ALPHA:g} given ψ and the pairs. TPZ: Wilcoxon signed-rank over all pairs (a method whose episodes "
             f"end sooner, in contacts, sums less time near people) and over the pairs both finished (*TPZ ok*, "
             f"the paper's episodes); NT: over pairs both finished. Δ = {ref} − other.\n",
             f"| cell | other | pairs | ΔSR | {ref} only / other only | p (SR) | detectable ΔSR | ΔTPZ [s] | "
             "p (TPZ) | ΔTPZ ok [s] | p (TPZ ok) | ΔNT [s] | p (NT) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for cell, by in pr.items():
        for m, e in by.items():
            sr, tpz, tok, nt = e["sr"], e["tpz_s"], e["tpz_s_success"], e["nav_time_s"]
            parts.append(f"| {cell} | {labels.get(m, m)} | {e['n_pairs']} | {sr['sr_diff']:+.2f} | "
                         f"{sr['a_only']} / {sr['b_only']} | {_fmt_p(sr['p_value'])} | "
                         f"{_fmt_mdd(sr['detectable_diff'])} | {_fmt_d(tpz['mean_diff'])} | "
                         f"{_fmt_p(tpz['p_value'])} | {_fmt_d(tok['mean_diff'])} | {_fmt_p(tok['p_value'])} | "
                         f"{_fmt_d(nt['mean_diff'])} | {_fmt_p(nt['p_value'])} |")
    parts.append("")
    return parts


def _fmt_mdd(x: float) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a (ψ = 0)"
    return "none ≤ ψ" if math.isinf(x) else f"{x:.2f}"


def plot_sr(res: dict[str, dict[str, Any]], labels: dict[str, str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = list(res)
    methods = list(dict.fromkeys(m for c in cells for m in res[c]))
    fig, ax = plt.subplots(figsize=(max(6.0, 1.6 * len(cells)), 3.8))
    w = 0.8 / max(len(methods), 1)
    cmap = plt.get_cmap("viridis", max(len(methods), 2))
    for k, m in enumerate(methods):
        xs, ys, lo, hi = [], [], [], []
        for i, c in enumerate(cells):
            s = res[c].get(m, {}).get("success")
            if not s:
                continue
            xs.append(i + (k - (len(methods) - 1) / 2) * w)
            ys.append(s["mean"])
            lo.append(max(0.0, s["mean"] - s["ci95_low"]))  # the Wilson bounds can miss 0 or 1 by rounding
            hi.append(max(0.0, s["ci95_high"] - s["mean"]))
        ax.bar(xs, ys, w, yerr=[lo, hi], capsize=2, label=labels.get(m, m), color=cmap(k))
    ax.set_xticks(range(len(cells)), cells, rotation=15)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("success rate (95 % CI)")
    ax.legend(fontsize=7, ncol=min(len(methods), 4), loc="lower center", bbox_to_anchor=(0.5, 1.0), frameon=False)
    fig.tight_layout()

    save_figure(fig, path, 120)
    plt.close(fig)


def plot_cue_twins(pairs: dict[str, tuple[Any, Any, dict[str, Any]]], labels: dict[str, str], title: str,
                   path: Path) -> None:
    """One scenario trial per method with and without the cue: the robot's speed and turn-rate commands and its
    distance to the scripted pedestrians over time, the cue's onset, the walking direction's change (onset + lead)
    and the first differing command marked. ``pairs``: method -> (cued trace, twin trace, its cue-twin row)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(pairs), 3, figsize=(11, 1.9 * len(pairs) + 0.6), squeeze=False, sharex=True)
    for row, (m, (cued, twin, r)) in zip(axes, pairs.items(), strict=True):
        onset, lead = float(r["cue_onset_s"]), float(r["cue_lead_s"])
        peds = np.asarray(r["scripted_peds"], int)
        for tr, style, name in ((cued, "-", "with cue"), (twin, "--", "without cue")):
            t = np.arange(len(tr.robot_cmd)) * tr.dt_s
            dist = np.min(np.hypot(*(tr.ped_xy[:, peds] - tr.robot_pose[:, None, :2]).transpose(2, 0, 1)), axis=1)
            for ax, y in zip(row, (tr.robot_cmd[:, 0], tr.robot_cmd[:, 1], dist[:len(t)]), strict=True):
                ax.plot(t, y, style, lw=1.2, label=name)
        for ax in row:
            ax.axvline(onset, color="0.5", lw=0.8)
            ax.axvline(onset + lead, color="k", ls=":", lw=0.8)
            if math.isfinite(r["cue_divergence_s"]):
                ax.axvline(onset + r["cue_divergence_s"], color="tab:red", lw=0.8)
            ax.set_xlim(max(0.0, onset - 2.0), onset + 4.0)
        row[0].set_ylabel(f"{labels.get(m, m)}\nv [m/s]", fontsize=8)
        row[1].set_ylabel("ω [rad/s]", fontsize=8)
        row[2].set_ylabel("to walker [m]", fontsize=8)
    axes[0, 0].legend(fontsize=7, frameon=False)
    for ax in axes[-1]:
        ax.set_xlabel("t [s]", fontsize=8)
    fig.suptitle(f"{title}\ngrey: the cue's onset; dotted: the walking direction changes; red: the first command "
                 "that differs between the two runs", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, 110)
    plt.close(fig)


def plot_cue_timing(rows: Sequence[dict[str, Any]], labels: dict[str, str], path: Path) -> None:
    """When each method answered the cue, per scenario (a panel each) and trial: the first cue-driven command's
    time after the onset (``cue_divergence_s``) per method, the same trial joined across methods, the walking
    direction's change (the cue's lead) dotted, trials whose commands the cue never changed at the top."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    methods = methods_of(rows)
    fig, axes = plt.subplots(1, len(scenes), figsize=(1.2 + 1.3 * len(methods) * len(scenes), 3.6), squeeze=False)
    for ax, scene in zip(axes[0], scenes, strict=True):
        rs = [r for r in rows if r["scene"] == scene]
        div = [r["cue_divergence_s"] for r in rs if math.isfinite(r["cue_divergence_s"])]
        leads = [r["cue_lead_s"] for r in rs if math.isfinite(r["cue_lead_s"])]
        top = max([*div, *leads, 0.5]) + 0.3  # where "never" goes
        by_seed: dict[int, dict[str, float]] = {}
        for r in rs:
            by_seed.setdefault(r["seed"], {})[r["method"]] = r["cue_divergence_s"]
        rng = np.random.default_rng(0)  # a fixed jitter, so that equal times (multiples of the step) stay visible
        for times in by_seed.values():
            xs = [i + rng.uniform(-0.12, 0.12) for i, m in enumerate(methods) if m in times]
            ys = [times[m] if math.isfinite(times[m]) else top for m in methods if m in times]
            ax.plot(xs, ys, "-", color="0.75", lw=0.6, zorder=1)
            ax.scatter(xs, ys, s=12, color="tab:blue", zorder=2)
        if leads:
            ax.axhline(float(np.median(leads)), color="k", ls=":", lw=0.8)
        ax.axhline(top, color="0.85", lw=6, zorder=0)
        ax.text(len(methods) - 0.5, top, "never", fontsize=7, va="center", ha="right", color="0.4")
        ax.set_xticks(range(len(methods)), [labels.get(m, m) for m in methods], rotation=20, fontsize=7)
        ax.set_ylim(-0.05, top + 0.2)
        ax.set_title(f"{scene} ({len(by_seed)} trials)", fontsize=9)
    axes[0, 0].set_ylabel("first cue-driven command [s after onset]", fontsize=8)
    fig.suptitle("When each method answered the head/torso cue (one dot per trial, the same trial joined)\n"
                 "dotted: the walking direction changes; grey band: never", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, 110)
    plt.close(fig)
