"""What a benchmark's episodes cost to run: per part and method, one worker's wall and CPU seconds per episode and
per env step, and each part's wall time.

Every episode writes ``cost/<name>.json`` beside its part's other files (its trace, figure, video) — not into its
metrics row, because rows are deterministic (compared byte for byte between the local pool and Ray, and across a
resume) and timings are not. The clock covers the episode itself (building the env, every step's sensors and
decision); loading the method's weights, once per worker process, is counted apart, and writing the trace, figure
and video is left out. Episodes that render a video or write an MCAP log (a few per cell) are timed but left out of
the per-step figures, whose work they inflate.

The stage sums the files of the episodes it ran or found (an episode resumed from an older run may have none) into
``cost.json`` and the report's *Compute* section: what lets a user size a run (episodes × worker-seconds per
episode / workers) before starting it, and what ``docs/results.md`` quotes as each method's cost.
"""

from __future__ import annotations

import json
import statistics
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from pipeline.core.artifacts import atomic_write_text

COST_DIR = "cost"


class Clock:
    """Wall (``time.perf_counter``) and this process's CPU time (``time.process_time``: every thread of it) since
    construction."""

    def __init__(self) -> None:
        self.wall0, self.cpu0 = time.perf_counter(), time.process_time()

    def read(self) -> tuple[float, float]:
        return time.perf_counter() - self.wall0, time.process_time() - self.cpu0


def episode_name(tag: str, scene: str, density: float, seed: int, method: str) -> str:
    """An episode's file stem (row, trace, figure, video, cost): ``<tag><scene>_d<density>_s<seed>_<method>``."""
    return f"{tag}{Path(scene).stem}_d{float(density):g}_s{seed}_{method}"


def cost_path(out: Path, name: str) -> Path:
    return Path(out) / COST_DIR / f"{name}.json"


def write_cost(out: Path, name: str, *, method: str, steps: int, wall_s: float, cpu_s: float, load_s: float,
               rendered: bool) -> None:
    """The cost of episode ``name`` (its part's folder ``out``): env steps, wall and CPU seconds of the episode,
    seconds spent loading the method's driver for it (0 when the worker had it), and whether it rendered a video or
    a log."""
    rec = {"method": method, "steps": int(steps), "wall_s": round(float(wall_s), 4), "cpu_s": round(float(cpu_s), 4),
           "load_s": round(float(load_s), 4), "rendered": bool(rendered)}
    atomic_write_text(cost_path(out, name), json.dumps(rec) + "\n")


def read_costs(files: Iterable[Path]) -> list[dict[str, Any]]:
    """The records of the cost files among ``files`` that exist and parse (a missing or damaged one is skipped:
    timings are a report, not a result)."""
    out = []
    for f in files:
        try:
            rec = json.loads(Path(f).read_text())
        except (OSError, ValueError):
            continue
        if isinstance(rec, dict) and {"method", "steps", "wall_s", "cpu_s"} <= rec.keys():
            out.append(rec)
    return out


def summarize(records: Sequence[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per method: episodes timed, those in the per-step figures (not rendered), their env steps, wall and CPU
    seconds per episode and milliseconds per step, and the driver loading seconds."""
    by: dict[str, list[dict[str, Any]]] = {}
    for r in records:
        by.setdefault(str(r["method"]), []).append(r)
    out = {}
    for m, rs in by.items():
        plain = [r for r in rs if not r.get("rendered")]
        steps = sum(int(r["steps"]) for r in plain)
        wall = sum(float(r["wall_s"]) for r in plain)
        cpu = sum(float(r["cpu_s"]) for r in plain)
        n = len(plain)
        out[m] = {"episodes": len(rs), "timed": n, "steps": steps,
                  "wall_s_per_episode": wall / n if n else None, "cpu_s_per_episode": cpu / n if n else None,
                  "wall_ms_per_step": 1e3 * wall / steps if steps else None,
                  "cpu_ms_per_step": 1e3 * cpu / steps if steps else None,
                  "load_s": sum(float(r.get("load_s", 0.0)) for r in rs)}
    return out


def _f(x: float | None, fmt: str) -> str:
    return "n/a" if x is None else format(x, fmt)


def cost_markdown(parts: dict[str, dict[str, Any]], labels: dict[str, str], workers: int) -> list[str]:
    """The report's *Compute* section from :func:`part_cost` records keyed by part name."""
    if not any(p["methods"] for p in parts.values()):
        return []
    lines = ["## Compute (this machine)\n",
             f"What the episodes cost, one worker each ({workers} in parallel): *worker-s / episode* is one "
             "worker's wall time for an episode (building its world, every step's sensors and decision), *ms / step* the same per "
             "env step, *CPU* its process's CPU time over that wall; loading weights (once per worker) and writing "
             "traces, figures and videos are not in them, and episodes with a video or a log are left out. A run of "
             "E episodes of a method takes ≈ E × worker-s / episode ÷ workers. *Part wall*: this invocation's wall "
             "time for the part (episodes found from an earlier run cost nothing).\n",
             "| part | part wall [min] (episodes run) | method | episodes timed | worker-s / episode | ms / step | "
             "CPU / wall |",
             "|---|---|---|---|---|---|---|"]
    for part, p in parts.items():
        first = True
        for m, c in p["methods"].items():
            head = (f"| {part} | {p['wall_s'] / 60:.1f} ({p['ran']}) |" if first else "| | |")
            first = False
            share = (None if not c["wall_s_per_episode"] else c["cpu_s_per_episode"] / c["wall_s_per_episode"])
            lines.append(f"{head} {labels.get(m, m)} | {c['timed']} | {_f(c['wall_s_per_episode'], '.2f')} | "
                         f"{_f(c['wall_ms_per_step'], '.1f')} | {_f(share, '.2f')} |")
    lines.append("")
    return lines


def part_cost(jobs: Sequence[Any], wall_s: float, ran: int) -> dict[str, Any]:
    """One part's record: its wall time in this invocation, the episodes it ran (not found cached), and
    :func:`summarize` of its jobs' cost files (``jobs``: :class:`evaluation.harness.Job`)."""
    return {"wall_s": round(float(wall_s), 2), "ran": int(ran),
            "methods": summarize(read_costs(cost_path(j.out, j.name) for j in jobs))}


def episode_costs(run: Path, rows: Sequence[dict[str, Any]]) -> dict[tuple[str, float, int], dict[str, Any]]:
    """The cost records of an eval run's benchmark ``rows`` (keyed by scene, density, seed), read from
    ``<run>/cost/``; rendered episodes and rows without a file left out (empty for a run that holds none)."""
    folder = Path(run) / COST_DIR
    if not folder.is_dir():
        return {}
    out = {}
    for r in rows:
        rec = read_costs([folder / f"{episode_name('', r['scene'], r['density'], r['seed'], r['method'])}.json"])
        if rec and not rec[0].get("rendered") and rec[0]["steps"] > 0:
            out[(r["scene"], float(r["density"]), int(r["seed"]))] = rec[0]
    return out


def paired_cost(a: dict[tuple, dict[str, Any]], b: dict[tuple, dict[str, Any]]) -> dict[str, Any] | None:
    """Two runs' costs (:func:`episode_costs`) over the episodes both timed: ms per env step of each (wall and CPU,
    summed over the pairs), their ratio ``a / b``, and the median of the per-episode ratios of wall ms per step (an
    episode's own length divides out). None when no episode was timed in both."""
    common = sorted(a.keys() & b.keys())
    if not common:
        return None

    def per_step(recs: list[dict[str, Any]], key: str) -> float:
        return 1e3 * sum(float(r[key]) for r in recs) / sum(int(r["steps"]) for r in recs)

    ra, rb = [a[k] for k in common], [b[k] for k in common]
    ratios = [(float(x["wall_s"]) / x["steps"]) / (float(y["wall_s"]) / y["steps"])
              for x, y in zip(ra, rb, strict=True) if float(y["wall_s"]) > 0]
    out = {"pairs": len(common), "median_episode_ratio": statistics.median(ratios) if ratios else None}
    for key in ("wall_s", "cpu_s"):
        ma, mb = per_step(ra, key), per_step(rb, key)
        out[key.replace("_s", "_ms_per_step")] = [ma, mb]
        out[key.replace("_s", "_ratio")] = ma / mb if mb > 0 else None
    return out
