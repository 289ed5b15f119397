"""``icrowdnav timings [DATA_DIR]``: the wall time of every finished stage in a data dir, read from the stages'
manifests — how long ``make all`` (or any set of stages) took, stage by stage, with the code each ran. ::

    icrowdnav timings                 # data/
    icrowdnav timings /tmp/run --json

A Markdown table in the order the stages finished: stage, output (relative to DATA_DIR), commit (``+`` = uncommitted
changes), finish time (UTC), wall, and the invocations that built the output (more than 1 when continued with
``--resume``: the wall then sums them, a killed one counted until its last write to the output, so it is a lower
bound); then the sum of the walls and the span from the first stage's start to the last one's end (the start: the
finish less the total wall). Then, for every student whose DAgger iterations were timed (finished or not), where its
DAgger loop's time went (:func:`rl.dagger.throughput_table`: each iteration's rollouts, export, pool and cloning,
frames per second, the rollout episodes' phases per frame, and the final cloning's pool and cloning when
``dagger.final_clone`` ran). Exit 0; 1 when a manifest or a ``done.json`` is
damaged (one line each naming the file, the others still listed); 2 when DATA_DIR is not a directory.
"""

from __future__ import annotations

import json
import sys
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from pipeline.core.errors import CorruptArtifactError
from pipeline.core.layout import policy_dir, policy_root
from pipeline.core.manifest import Manifest


def stage_timings(data_dir: Path) -> tuple[list[dict[str, Any]], list[str]]:
    """``(rows, errors)``: one row per ``manifest.json`` under ``data_dir`` (stage, output, commit, dirty, start and
    finish as datetimes, wall_s: every invocation's, last_wall_s: the finishing one's, invocations), sorted by finish
    time; ``errors``: one line per damaged manifest."""
    rows, errors = [], []
    for path in sorted(data_dir.rglob("manifest.json")):
        try:
            m = Manifest.read(path)
            end = datetime.fromisoformat(m.created_utc.replace("Z", "+00:00"))
        except (CorruptArtifactError, ValueError) as e:
            errors.append(f"{path}: {e}")
            continue
        rows.append({"stage": m.stage, "output": str(path.parent.relative_to(data_dir)), "commit": m.git_commit[:7],
                     "dirty": m.git_dirty, "start": end - timedelta(seconds=m.wall_total_s), "end": end,
                     "wall_s": m.wall_total_s, "last_wall_s": m.duration_s, "invocations": m.invocations})
    return sorted(rows, key=lambda r: r["end"]), errors


def dagger_timings(data_dir: Path) -> tuple[dict[str, tuple[list[dict[str, Any]], dict[str, Any] | None]],
                                            list[str]]:
    """``({variant: ([done.json of each finished DAgger iteration, in order], the final cloning's done.json or
    None)}, errors)`` for every student under ``data_dir``'s policy checkpoints; ``errors``: one line per unreadable
    ``done.json``."""
    out: dict[str, tuple[list[dict[str, Any]], dict[str, Any] | None]] = {}
    errors: list[str] = []

    def read(path: Path) -> dict[str, Any] | None:
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError) as e:
            errors.append(f"{path}: unreadable ({type(e).__name__}: {e})")
            return None

    for variant_dir in sorted(policy_root(data_dir).glob("*/")):
        done = [p for p in (variant_dir / "dagger").glob("iter_*/done.json")
                if p.parent.name.removeprefix("iter_").isdigit()]  # iter_<k> only (rl.stage)
        iters = [i for p in sorted(done, key=lambda p: int(p.parent.name.removeprefix("iter_")))
                 if (i := read(p)) is not None]
        final_done = variant_dir / "dagger" / "final" / "done.json"  # dagger.final_clone
        if iters:
            out[variant_dir.name] = (iters, read(final_done) if final_done.exists() else None)
    return out, errors


def _wall(seconds: float) -> str:
    return f"{seconds / 60:.1f} min" if seconds >= 60 else f"{seconds:.0f} s"


def _invocations(row: dict[str, Any]) -> str:
    n = row["invocations"]
    return "1" if n == 1 else f"{n} (the last {_wall(row['last_wall_s'])})"


def markdown(rows: list[dict[str, Any]]) -> str:
    lines = ["| stage | output | commit | finished (UTC) | wall | invocations |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['stage']} | {r['output']} | {r['commit']}{'+' if r['dirty'] else ''} | "
                     f"{r['end']:%Y-%m-%d %H:%M:%S} | {_wall(r['wall_s'])} | {_invocations(r)} |")
    if rows:
        total = sum(r["wall_s"] for r in rows)
        span = (max(r["end"] for r in rows) - min(r["start"] for r in rows)).total_seconds()
        lines.append(f"\n{len(rows)} stages: sum of walls {_wall(total)} ({total / 3600:.2f} h); from the first start "
                     f"to the last finish {_wall(span)} ({span / 3600:.2f} h)")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    """the wall time of every finished stage in a data dir (its manifests), and where each DAgger loop's time went"""
    if argv and argv[0] in ("-h", "--help"):
        print(__doc__)
        return 0
    as_json = "--json" in argv
    args = [a for a in argv if a != "--json"]
    if len(args) > 1 or any(a.startswith("-") for a in args):
        print(f"error: timings: expected [DATA_DIR] [--json], got {' '.join(argv)}", file=sys.stderr)
        return 2
    data_dir = Path(args[0] if args else "data")
    if not data_dir.is_dir():
        print(f"error: timings: {data_dir} is not a directory (expected a data dir)", file=sys.stderr)
        return 2
    rows, errors = stage_timings(data_dir)
    if as_json:
        print(json.dumps([{**r, "start": r["start"].astimezone(UTC).isoformat(),
                           "end": r["end"].astimezone(UTC).isoformat()} for r in rows], indent=2))
    else:
        print(markdown(rows) if rows else f"no finished stage (manifest.json) under {data_dir}")
        loops, bad = dagger_timings(data_dir)
        errors += bad
        if any("timing" in i for iters, _ in loops.values() for i in iters):
            from rl.dagger import throughput_table  # lazy: torch only with a DAgger loop to show

            for variant, (iters, final) in loops.items():
                where = policy_dir(data_dir, variant).relative_to(data_dir) / "dagger"
                print(f"\nDAgger loop of `{variant}` ({where})\n")
                print(throughput_table(iters, final))
    for e in errors:
        print(f"error: {e}", file=sys.stderr)
    return 1 if errors else 0
