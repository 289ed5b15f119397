"""Training curves of a ``train`` run (from its ``train_log.csv``) as one PNG, and the DAgger runs — or the PPO
fine-tunings — of several students side by side::

    python -m rl.figures data/checkpoints/policy/no_bev other/checkpoints/policy/no_bev:more_frames --out dagger.png
    python -m rl.figures --ppo run_a/checkpoints/policy/no_bev:lr5e-5 run_b/checkpoints/policy/no_bev:lr1e-5 --out ppo.png

Each argument is a student checkpoint (``CKPT[:LABEL]``, the label defaulting to the folder's parent and name) whose
``metrics.json`` holds the ``dagger`` iterations its ``train`` wrote. The figure plots, against the frames pooled so
far, each iteration's held-out cross-entropy (the student of the iteration before, on the new iteration's frames,
before cloning on them), the same loss after the cloning, and the rollout success rate of the mixed policy.

With ``--ppo`` it plots, against env steps, what stable-baselines3 logged of each checkpoint's PPO — a student's
fine-tuning (``tb/finetune_*``, when ``finetune.ppo_steps`` > 0) or a teacher's PPO after DAgger (``tb/ppo_*``): the
mean episode return and length of the stochastic rollouts, the policy's entropy, the critic's explained variance, the
approximate KL and clip fraction of each update — with the end of the critic warm-up (the actor frozen before it)
marked.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from collections import defaultdict
from pathlib import Path
from typing import Any

from pipeline.core.artifacts import require_input
from pipeline.core.errors import CorruptArtifactError, InputMissingError, reports_errors
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


def uniform_loss(ckpt: Path) -> float | None:
    """The cross-entropy of a uniform choice among the checkpoint's actions, ln n (``policy.json``'s ``actions.n``):
    a cloning left near it has learned next to nothing. ``None`` where ``policy.json`` does not say."""
    try:
        n = json.loads((Path(ckpt) / "policy.json").read_text())["actions"]["n"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return math.log(n) if isinstance(n, int) and n > 1 else None


def plot_dagger(runs: list[tuple[str, list[dict[str, Any]]]], out: Path, chance: float | None = None) -> None:
    """Three panels, one line per ``(label, dagger_iterations(...))``: the held-out and after-cloning cross-entropy
    of each iteration's frames and the rollout success rate, against the frames pooled before the iteration;
    ``chance`` (:func:`uniform_loss`) is drawn on the two loss panels."""
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
    if chance is not None:
        for ax in axes[:2]:
            ax.axhline(chance, color="0.4", linestyle="--", linewidth=0.9, label="uniform over the actions (ln n)")
    axes[0].set_ylabel("cross-entropy to the teacher's action [nats]", fontsize=8)
    axes[1].set_ylabel("cross-entropy [nats]", fontsize=8)
    axes[2].set_ylabel("SR of the iteration's rollouts", fontsize=8)
    axes[2].set_ylim(-0.02, 1.02)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out, 110)
    plt.close(fig)


# SB3's PPO scalars the fine-tuning figure plots: (tag, panel title, sign): entropy_loss is minus the entropy
PPO_TAGS = (("rollout/ep_rew_mean", "mean episode return (stochastic rollouts)", 1.0),
            ("rollout/ep_len_mean", "mean episode length [steps]", 1.0),
            ("train/entropy_loss", "policy entropy [nats]", -1.0),
            ("train/explained_variance", "critic: explained variance", 1.0),
            ("train/approx_kl", "approximate KL per update", 1.0),
            ("train/clip_fraction", "clip fraction per update", 1.0))


def ppo_log(ckpt: Path) -> tuple[dict[str, list[tuple[int, float]]], int]:
    """What SB3 logged of ``ckpt``'s PPO — a student's fine-tuning (``tb/finetune_*``) or a teacher's PPO after DAgger
    (``tb/ppo_*``), resumed parts in step order: ``{tag: [(env step, value)]}`` for the :data:`PPO_TAGS`, and the
    critic warm-up's steps (``policy.json``).

    Raises:
        InputMissingError: no such event files (trained with ``finetune.ppo_steps`` / ``teacher.ppo_steps`` 0).
        CorruptArtifactError: the logs hold none of the tags, or ``policy.json`` is unreadable.
    """
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    ckpt = Path(ckpt)
    tb = ckpt / "tb"
    runs: list[Path] = []
    for pattern in ("finetune_*", "ppo_*"):  # a student's fine-tuning, else a teacher's PPO
        runs = sorted(p for p in tb.glob(pattern) if p.is_dir())
        if runs:
            break
    if not runs:
        raise InputMissingError(f"{tb}: no PPO logs (finetune_* or ppo_*): expected a student trained with "
                                "finetune.ppo_steps > 0 or a teacher with teacher.ppo_steps > 0")
    series: dict[str, dict[int, float]] = defaultdict(dict)
    for run in runs:
        acc = EventAccumulator(str(run), size_guidance={"scalars": 0})
        acc.Reload()
        have = set(acc.Tags().get("scalars", []))
        for tag, _, sign in PPO_TAGS:
            for e in acc.Scalars(tag) if tag in have else []:
                series[tag][int(e.step)] = sign * float(e.value)  # a resumed part rewrites its steps: the last wins
    if not series:
        raise CorruptArtifactError(f"{tb}: the PPO logs hold none of {[t for t, _, _ in PPO_TAGS]}")
    path = require_input(ckpt / "policy.json", "policy description", "written by `icrowdnav train`")
    try:
        warmup = int(json.loads(path.read_text()).get("produced_by", {}).get("ppo_critic_warmup_steps", 0))
    except (ValueError, UnicodeDecodeError, AttributeError, TypeError) as e:
        raise CorruptArtifactError(f"{path}: field 'produced_by.ppo_critic_warmup_steps': expected an integer "
                                   f"({e})") from e
    return {tag: sorted(v.items()) for tag, v in series.items()}, warmup


def plot_ppo(runs: list[tuple[str, dict[str, list[tuple[int, float]]], int]], out: Path) -> None:
    """One panel per :data:`PPO_TAGS` entry, one line per ``(label, log, warmup)`` (:func:`ppo_log`),
    the end of each run's critic warm-up dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(13.0, 6.4))
    for k, (label, log, warmup) in enumerate(runs):
        color = f"C{k}"
        for ax, (tag, _, _) in zip(axes.flat, PPO_TAGS, strict=True):
            if log.get(tag):
                xs, ys = zip(*log[tag], strict=True)
                ax.plot(xs, ys, marker="." if len(xs) < 40 else None, color=color,
                        label=f"{label} (warm-up {warmup:,})")
            if warmup:
                ax.axvline(warmup, color=color, ls="--", lw=0.8, alpha=0.6)
    for ax, (tag, title, _) in zip(axes.flat, PPO_TAGS, strict=True):
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("env steps of PPO (dashed: the actor starts to learn)", fontsize=8)
        ax.grid(alpha=0.3)
        if not any(log.get(tag) for _, log, _ in runs):  # e.g. a teacher's unmonitored envs log no episode returns
            ax.text(0.5, 0.5, f"not logged ({tag})", ha="center", va="center", fontsize=8, transform=ax.transAxes)
    next(ax for ax in axes.flat if ax.get_legend_handles_labels()[0]).legend(fontsize=7)
    fig.suptitle("PPO from distilled policies (the paper's reward)", fontsize=10)
    fig.tight_layout()
    save_figure(fig, out, 110)
    plt.close(fig)


def parse_ckpt(arg: str) -> tuple[Path, str]:
    """``CKPT[:LABEL]``: a checkpoint folder and its label (default: the folder's parent and name).

    A label cannot contain "/": paths may hold ":" (``C:/…``, ``run:2/ckpt``), so a suffix with a "/" is part of the path.
    """
    path, sep, label = arg.rpartition(":")
    if sep and path and label and "/" not in label:
        return Path(path), label
    p = Path(arg)
    return p, f"{p.parent.name}/{p.name}" if p.parent.name else p.name


@reports_errors
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m rl.figures", description=__doc__.split("\n\n")[0])
    ap.add_argument("ckpts", nargs="+", help="student checkpoints: CKPT or CKPT:LABEL (a label holds no '/': after a '/' the whole argument is read as a path)")
    ap.add_argument("--out", type=Path, required=True, help="the PNG to write")
    ap.add_argument("--ppo", action="store_true", help="their PPO (tb/finetune_*, a teacher's tb/ppo_*), not DAgger")
    args = ap.parse_args(argv)
    if args.ppo:
        logs = [(label, *ppo_log(path)) for path, label in map(parse_ckpt, args.ckpts)]
        plot_ppo(logs, args.out)
        print(f"{len(logs)} PPO runs -> {args.out}")
        return 0
    ckpts = list(map(parse_ckpt, args.ckpts))
    runs = [(label, dagger_iterations(path)) for path, label in ckpts]
    chances = {uniform_loss(path) for path, _ in ckpts}  # one line only where every run has the same action set
    plot_dagger(runs, args.out, chances.pop() if len(chances) == 1 else None)
    print(f"{len(runs)} DAgger runs -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
