"""Training curves of a ``train`` run (from its ``train_log.csv``) as one PNG, and the DAgger runs of several
students side by side::

    python -m rl.figures data/checkpoints/policy/no_bev other/checkpoints/policy/no_bev:more_frames --out dagger.png

Each argument is a student checkpoint (``CKPT[:LABEL]``, the label defaulting to the folder's parent and name) whose
``metrics.json`` holds the ``dagger`` iterations its ``train`` wrote. The figure plots, against the frames pooled so
far, each iteration's held-out cross-entropy (the student of the iteration before, on the new iteration's frames,
before cloning on them), the same loss after the cloning, and the rollout success rate of the mixed policy.
"""

from __future__ import annotations

import argparse
import csv
import json
from collections import defaultdict
from pathlib import Path
from typing import Any

from pipeline.core.artifacts import require_input
from pipeline.core.errors import CorruptArtifactError, reports_errors
from sim.viz import save_figure

# the keys of a metrics.json "dagger" iteration that the comparison plots (rl.stage._train_student writes them)
DAGGER_KEYS = ("iteration", "beta", "frames", "aggregate_frames", "bc_loss_new_before", "bc_loss_new_after",
               "rollout_success_rate")


def plot_training(log_csv: Path, out: Path, title: str) -> None:
    """One panel per (phase, key) logged in ``log_csv`` (rows: phase, step, key, value); nothing if it is empty."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series: dict[tuple[str, str], list[tuple[int, float]]] = defaultdict(list)
    if Path(log_csv).exists():
        with open(log_csv) as f:
            for row in csv.DictReader(f):
                series[(row["phase"], row["key"])].append((int(row["step"]), float(row["value"])))
    if not series:
        return
    keys = sorted(series)
    cols = min(3, len(keys))
    rows = (len(keys) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 2.8 * rows), squeeze=False)
    for ax, key in zip(axes.flat, keys, strict=False):
        xs, ys = zip(*sorted(series[key]), strict=True)
        ax.plot(xs, ys, marker="." if len(xs) < 30 else None)
        ax.set_title(f"{key[0]}: {key[1]}", fontsize=9)
        ax.set_xlabel("epoch" if key[0].endswith("bc") else "iteration" if key[0] == "dagger" else "step",
                      fontsize=8)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(keys):]:
        ax.axis("off")
    fig.suptitle(f"train {title}")
    fig.tight_layout()

    save_figure(fig, out, 110)
    plt.close(fig)


def plot_learning_curve(rows: list[dict], out: Path, title: str) -> None:
    """Acceptance SR per cell and pooled against the training budget (``rows``: :func:`rl.stage.learning_curve`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not rows:
        return
    xs = [max(r["budget"], 1) for r in rows]
    fig, ax = plt.subplots(figsize=(6.0, 3.6))
    for cell in rows[-1]["table"]:
        ax.plot(xs, [r["table"].get(cell, {}).get("sr", float("nan")) for r in rows], marker=".", alpha=0.7,
                label=cell)
    ax.plot(xs, [r["pooled_sr"] for r in rows], marker="o", color="k", lw=2, label="pooled")
    if len(set(xs)) > 1 and max(xs) / min(xs) > 20:
        ax.set_xscale("log")
    ax.set_xlabel(f"{rows[-1]['unit']} (the first point: {rows[0]['budget']})")
    ax.set_ylabel("acceptance SR")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    n = sum(c["n"] for c in rows[-1]["table"].values())
    ax.set_title(f"{title}: learning curve (N = {n} per point, the same seeds)", fontsize=10)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out, 110)
    plt.close(fig)


def dagger_iterations(ckpt: Path) -> list[dict[str, Any]]:
    """The DAgger iterations recorded in ``ckpt/metrics.json`` (the :data:`DAGGER_KEYS` of each, in order).

    Raises:
        InputMissingError: ``ckpt`` has no ``metrics.json``.
        CorruptArtifactError: it is not JSON, has no ``dagger`` list (a teacher, a baseline) or an iteration lacks
            a key; the message names the file and the field.
    """
    path = require_input(Path(ckpt) / "metrics.json", "training metrics", "written by `icrowdnav train` of a student")
    try:
        metrics = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as e:
        raise CorruptArtifactError(f"{path}: expected JSON, got unreadable text ({e})") from e
    iters = metrics.get("dagger") if isinstance(metrics, dict) else None
    if not isinstance(iters, list) or not iters:
        raise CorruptArtifactError(f"{path}: field 'dagger': expected a non-empty list of DAgger iterations, got "
                                   f"{type(iters).__name__ if iters is not None else 'none'} (not a student's run?)")
    out = []
    for i, it in enumerate(iters):
        missing = [k for k in DAGGER_KEYS if not isinstance(it, dict) or k not in it]
        if missing:
            raise CorruptArtifactError(f"{path}: field 'dagger[{i}]': expected keys {list(DAGGER_KEYS)}, "
                                       f"missing {missing}")
        out.append({k: it[k] for k in DAGGER_KEYS})
    return out


def plot_dagger(runs: list[tuple[str, list[dict[str, Any]]]], out: Path) -> None:
    """Three panels, one line per ``(label, dagger_iterations(...))``: the held-out and after-cloning cross-entropy
    of each iteration's frames and the rollout success rate, against the frames pooled before the iteration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13.0, 3.6))
    for label, iters in runs:
        pooled = [it["aggregate_frames"] - it["frames"] for it in iters]  # what the student had been cloned on
        line, = axes[0].plot(pooled, [it["bc_loss_new_before"] for it in iters], marker="o", label=label)
        axes[1].plot([it["aggregate_frames"] for it in iters], [it["bc_loss_new_after"] for it in iters],
                     marker="o", color=line.get_color(), label=label)
        axes[2].plot(pooled, [it["rollout_success_rate"] for it in iters], marker="o", color=line.get_color(),
                     label=label)
    titles = ("held-out: the new iteration's frames, before cloning on them",
              "the new iteration's frames, after cloning", "rollout success (student mixed with the teacher, β)")
    xlabels = ("frames the student was cloned on", "frames pooled", "frames the rollout student was cloned on")
    for ax, title, xl in zip(axes, titles, xlabels, strict=True):
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(xl, fontsize=8)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("cross-entropy to the teacher's action [nats]", fontsize=8)
    axes[1].set_ylabel("cross-entropy [nats]", fontsize=8)
    axes[2].set_ylabel("SR of the iteration's rollouts", fontsize=8)
    axes[2].set_ylim(-0.02, 1.02)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out, 110)
    plt.close(fig)


def parse_ckpt(arg: str) -> tuple[Path, str]:
    """``CKPT[:LABEL]``: a checkpoint folder and its label (default: the folder's parent and name)."""
    path, sep, label = arg.rpartition(":")
    if sep and path and label and "/" not in label:
        return Path(path), label
    p = Path(arg)
    return p, f"{p.parent.name}/{p.name}" if p.parent.name else p.name


@reports_errors
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m rl.figures", description=__doc__.split("\n\n")[0])
    ap.add_argument("ckpts", nargs="+", help="student checkpoints: CKPT or CKPT:LABEL")
    ap.add_argument("--out", type=Path, required=True, help="the PNG to write")
    args = ap.parse_args(argv)
    runs = [(label, dagger_iterations(path)) for path, label in map(parse_ckpt, args.ckpts)]
    plot_dagger(runs, args.out)
    print(f"{len(runs)} DAgger runs -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
