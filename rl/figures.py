"""Training curves of a ``train`` run (from its ``train_log.csv``) as one PNG."""

from __future__ import annotations

import csv
from collections import defaultdict
from pathlib import Path

from sim.viz import save_figure


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
