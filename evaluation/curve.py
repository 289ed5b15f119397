"""A learning curve across separate trainings: acceptance SR against a budget that each training fixed once — the
recorded episodes a ViNT-style checkpoint was trained on, the DAgger frames of a student — where a single training
cannot save points along the way (a baseline's PPO steps or RL episodes can: ``curve_steps`` / ``curve_episodes``,
whose curve ``train`` itself writes).

::

    python -m evaluation.curve data/checkpoints/policy/vint data300/checkpoints/policy/vint \\
        data600/checkpoints/policy/vint --budget budget.episodes --unit "recorded episodes" \\
        --out vint_data_curve.png --json vint_data_curve.json

Each argument is a training's checkpoint directory: its ``metrics.json`` gives the budget (``--budget``: a dotted
key, e.g. ``budget.frames``) and its ``acceptance_episodes.jsonl`` the per-episode rows, which must cover the same
(scene, density, seed) in every checkpoint (the acceptance seeds: a paired curve). Per point, sorted by budget: SR
per cell, pooled SR with its 95 % Wilson interval, and the exact McNemar test of the pooled pairs against the
previous point and against the first. Prints Markdown; ``--out`` draws the curve (the picture ``train`` draws for a
baseline's curve), ``--json`` writes the numbers.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from evaluation.compare import pair_key, read_rows
from evaluation.stats import mcnemar_exact
from pipeline.core.artifacts import atomic_write_json, json_safe
from pipeline.core.errors import ConfigError, CorruptArtifactError, InputMissingError, reports_errors
from rl.figures import plot_learning_curve
from sim.metrics import wilson_interval


def budget_of(ckpt: Path, key: str) -> float:
    """The number at the dotted ``key`` of ``ckpt/metrics.json``; a named error where it is missing or no number."""
    path = Path(ckpt) / "metrics.json"
    try:
        node: Any = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputMissingError(f"{path}: missing (a finished training's metrics give its budget)") from None
    except (OSError, json.JSONDecodeError) as e:
        raise CorruptArtifactError(f"{path}: unreadable ({type(e).__name__}: {e})") from None
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            raise ConfigError(f"{path}: --budget {key}: expected a number at that key, got no key {part!r}")
        node = node[part]
    if isinstance(node, bool) or not isinstance(node, int | float) or not math.isfinite(node):
        raise ConfigError(f"{path}: --budget {key}: expected a finite number, got {node!r}")
    return node


def curve(points: list[tuple[float, list[dict[str, Any]], str]], unit: str) -> list[dict[str, Any]]:
    """``points``: ``(budget, acceptance rows, name)``. The rows of :func:`rl.stage.learning_curve` (``budget``,
    ``unit``, ``pooled_sr``, ``table``: per cell ``sr`` and ``n``), sorted by budget, each with its pooled Wilson
    interval and the paired tests against the previous and the first point (``vs_previous``, ``vs_first``)."""
    if len(points) < 2:
        raise ConfigError(f"evaluation.curve: expected at least 2 checkpoints, got {len(points)}")
    keys = [{pair_key(r) for r in rows} for _, rows, _ in points]
    for (_, rows, name), k in zip(points, keys, strict=True):
        if len(k) != len(rows):
            raise CorruptArtifactError(f"{name}: acceptance rows repeat a (scene, density, seed)")
        if k != keys[0]:
            raise ConfigError(f"{name}: acceptance episodes: expected the same (scene, density, seed) as "
                              f"{points[0][2]} ({len(keys[0])} episodes), got {len(k)} of which "
                              f"{len(k - keys[0])} are not in it — not a paired curve")
    ks = sorted(keys[0])
    cells = [f"{scene}@{density:g}" for scene, density, _ in ks]
    out, earlier = [], []  # earlier: the success vectors of the points before, aligned on ks
    for budget, rows, name in sorted(points, key=lambda p: p[0]):
        by_key = {pair_key(r): float(r["success"]) for r in rows}
        wins = [by_key[k] for k in ks]  # aligned on ks in every point: the pairs of the tests below
        table: dict[str, dict[str, Any]] = {}
        for cell, w in zip(cells, wins, strict=True):
            t = table.setdefault(cell, {"n": 0, "wins": 0.0})
            t["n"], t["wins"] = t["n"] + 1, t["wins"] + w
        lo, hi = wilson_interval(sum(wins), len(ks))
        row = {"budget": budget, "unit": unit, "checkpoint": name, "pooled_sr": sum(wins) / len(ks),
               "pooled_wilson95": [lo, hi], "table": {c: {"n": t["n"], "sr": t["wins"] / t["n"]} for c, t in table.items()}}
        if earlier:
            row["vs_previous"] = mcnemar_exact(wins, earlier[-1])
            row["vs_first"] = mcnemar_exact(wins, earlier[0])
        out.append(row)
        earlier.append(wins)
    return out


def markdown(rows: list[dict[str, Any]]) -> str:
    cells = list(rows[0]["table"])
    lines = [f"| {rows[0]['unit']} | " + " | ".join(cells) + " | pooled [95 % Wilson] | vs previous: "
             "gained / lost, McNemar p | vs first: gained / lost, McNemar p |",
             "|---" * (len(cells) + 4) + "|"]

    def test(s: dict[str, Any] | None) -> str:
        if s is None:
            return "—"
        return f"{s['a_only']} / {s['b_only']}, p = " + ("n/a" if math.isnan(s["p_value"]) else f"{s['p_value']:.3g}")

    for r in rows:
        lo, hi = r["pooled_wilson95"]
        lines.append(f"| {r['budget']:g} | " + " | ".join(f"{r['table'][c]['sr']:.2f}" for c in cells)
                     + f" | {r['pooled_sr']:.2f} [{lo:.2f}, {hi:.2f}] | {test(r.get('vs_previous'))} | "
                     f"{test(r.get('vs_first'))} |")
    n = sum(c["n"] for c in rows[0]["table"].values())
    return "\n".join(lines) + f"\n\nN = {n} acceptance episodes per point, the same (scene, density, seed) at each.\n"


@reports_errors
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m evaluation.curve", description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoints", nargs="+", type=Path, help="training checkpoint directories (metrics.json, "
                    "acceptance_episodes.jsonl)")
    ap.add_argument("--budget", required=True, help="dotted key of metrics.json holding each one's budget")
    ap.add_argument("--unit", default=None, help="the budget's name on the axis (default: the key)")
    ap.add_argument("--title", default="", help="the figure's title (default: the first checkpoint's name)")
    ap.add_argument("--out", type=Path, default=None, help="draw the curve here (.png)")
    ap.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    a = ap.parse_args(argv)
    points = [(budget_of(c, a.budget), read_rows(c / "acceptance_episodes.jsonl"), str(c)) for c in a.checkpoints]
    rows = curve(points, a.unit or a.budget)
    print(markdown(rows), end="")
    if a.out is not None:
        plot_learning_curve(rows, a.out, a.title or a.checkpoints[0].name)
    if a.json is not None:
        atomic_write_json(a.json, json_safe({"budget_key": a.budget, "rows": rows}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
