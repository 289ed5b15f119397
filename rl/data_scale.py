"""``python -m rl.data_scale``: how a student's imitation of its teacher grows with the DAgger data it is cloned on.

A DAgger iteration caches every frame's student inputs (frozen BEV features and their mirrored twin, poses, tracks,
scan, state) with the teacher's logits (``dagger/iter_k/features/*.npz``), so a student can be cloned again offline on
any set of such frames — several trainings' frames pooled, as long as they share the encoder, the intention model and
the teacher (checked: their ``policy.json`` references must agree). This clones a fresh student of the asked head on
nested subsets of the pooled frames (whole episodes, one seeded order, each subset a prefix of the next) with the
training's own cloning (:func:`rl.stage.distill`, the profile's ``train.dagger`` settings) and scores each on held-out
frames of other episodes (other rollouts: give a different training's iterations): the cross-entropy to the teacher's
distribution, the teacher's own entropy there (its floor) and how often the student's most likely action is the
teacher's. That is the learning curve behind "how many frames does the paper's MLP head need"::

    python -m rl.data_scale --data-dir data --head mlp --train data/checkpoints/policy/full \\
        --holdout data/other/checkpoints/policy/full/dagger/iter_3 --sizes 3000,12000,48000 --json curve.json

``--train`` / ``--holdout`` take policy checkpoints (every DAgger iteration of each) or iteration directories;
duplicate episodes (the same frames reached through copies, or iteration 0 of two trainings with the same seed) count
once, and held-out episodes never enter training. ``--save DIR`` writes the student of the largest size as a
checkpoint that ``icrowdnav eval`` runs (its ``produced_by`` names the frames it was cloned on; its ``manifest.json``,
written last as a stage writes it, hashes the teacher, encoder and features files it came from); ``--acceptance``
then runs the profile's acceptance episodes on it, which ``python -m evaluation.compare`` pairs with a trained
student's.
Numbers in docs/results.md ("The paper's MLP head and the amount of data").
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import logging
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.core import layout
from pipeline.core.artifacts import atomic_write_json
from pipeline.core.config import load_config
from pipeline.core.errors import ConfigError, InputMissingError, reports_errors
from pipeline.core.stage import code_state, finish_output, hash_inputs
from rl.dagger import pool_frames
from rl.networks import STUDENT_HEADS
from rl.observe import load_student_encoder, load_student_heads, observer_for_env
from rl.policy import (
    describe,
    load_policy,
    read_policy_json,
    relative_to,
    resolved_from,
    save_policy,
)
from rl.stage import (
    TrainConfig,
    acceptance,
    distill,
    encoder_dir,
    fresh_student,
    inputs,
    policy_root,
    student_net,
)
from rl.teacher import bc_loss, policy_logits_values
from sim.env import CrowdNavEnv

log = logging.getLogger(__name__)


def iteration_dirs(paths: list[Path]) -> list[Path]:
    """The DAgger iteration directories named by ``paths`` (a policy checkpoint: all of its iterations)."""
    out: list[Path] = []
    for p in map(Path, paths):
        if (p / "features").is_dir():
            out.append(p)
        elif (p / "dagger").is_dir():
            its = sorted((q for q in (p / "dagger").glob("iter_*") if (q / "features").is_dir()),
                         key=lambda q: int(q.name.split("_")[1]))
            if not its:
                raise InputMissingError(f"{p / 'dagger'}: no iteration with cached features (iter_k/features)")
            out.extend(its)
        else:
            raise InputMissingError(f"{p}: expected a student checkpoint with dagger/ or a dagger/iter_k directory "
                                    "with features/, found neither")
    return out


def _sources(policy_dir: Path, keys: tuple[str, ...]) -> dict[str, str | None]:
    """Digests of the ``keys`` weights (encoder / teacher / intention) a student checkpoint names in its policy.json."""
    desc = read_policy_json(policy_dir)
    return {k: _digest_dir(resolved_from(desc[k], policy_dir)) if desc.get(k) else None for k in keys}


@functools.cache
def _digest_dir(d: str) -> str:
    """The weights' digest of a checkpoint directory, read once per process (every pooled iteration names the same
    encoder and teacher)."""
    h = hashlib.sha256()
    for f in sorted(Path(d).glob("*.safetensors")):
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def check_same_sources(policy_dirs: list[Path], keys: tuple[str, ...] = ("encoder", "teacher")) -> None:
    """One named error unless every checkpoint in ``policy_dirs`` names the same ``keys`` weights (by digest)."""
    first = _sources(policy_dirs[0], keys)
    for p in policy_dirs[1:]:
        src = _sources(p, keys)
        for k in keys:
            if src[k] != first[k]:
                raise ConfigError(f"{p}/policy.json: {k}: expected the same weights as {policy_dirs[0]}'s "
                                  f"(digest {first[k]}), got {src[k]}: pool only trainings on one {k}")


def reference_scores(ckpts: list[Path], holdout: list[Path], soft_tau: float,
                     memory_gb: float | None = None) -> dict[str, dict[str, float]]:
    """:func:`holdout_scores` of trained students (``load_policy``, unshielded: the distribution as cloned) on the
    held-out iterations' frames; each must have been trained on the held-out frames' teacher."""
    ho_its = iteration_dirs(holdout)
    files = episode_files(ho_its)
    policies = {}
    for ckpt in map(Path, ckpts):
        check_same_sources([ho_its[0] / "policy", ckpt], ("teacher",))
        policies[str(ckpt)] = load_policy(ckpt, shield_s=0.0)[0]
    keys = {k for pol in policies.values() for k in pol.observation_space.spaces} | {"action", "teacher_logits"}
    ho = pool_frames([f for f, _, _ in files], tuple(sorted(keys)), memory_gb)  # read once
    out = {}
    for ckpt, policy in policies.items():
        out[ckpt] = holdout_scores(policy, ho, soft_tau)
        log.info("reference %s: held-out CE %.3f, top-1 agreement %.3f", ckpt, out[ckpt]["ce"],
                 out[ckpt]["top1_agreement"])
    return out


def episode_files(iters: list[Path]) -> list[tuple[Path, str, int]]:
    """``(file, content key, frames)`` of every cached episode in ``iters``; the key (a digest of the teacher's
    logits and the robot's states) identifies the same episode reached through two paths."""
    out = []
    for it in iters:
        for f in sorted((it / "features").glob("*.npz")):
            if f.name.endswith(".tmp.npz"):
                continue
            try:
                with np.load(f) as z:
                    if "teacher_logits" not in z.files:
                        raise InputMissingError(f"{f}: no teacher_logits (the iteration was recorded with soft_tau 0)")
                    key = hashlib.sha256(z["teacher_logits"].tobytes() + z["state"].tobytes()).hexdigest()[:20]
                    out.append((f, key, int(len(z["action"]))))
            except (OSError, ValueError, KeyError) as e:
                raise InputMissingError(f"{f}: unreadable cached features ({type(e).__name__}: {e})") from None
    return out


@torch.no_grad()
def holdout_scores(policy, data: dict[str, np.ndarray], soft_tau: float, batch: int = 512) -> dict[str, float]:
    """Cross-entropy to the teacher's distribution ``softmax(logits / soft_tau)`` (the cloning objective), the
    teacher's entropy there, and the share of frames whose most likely student action is the teacher's."""
    keys = tuple(policy.observation_space.spaces)
    dev = policy.device
    ce = ent = agree = 0.0
    n = len(data["action"])
    for s in range(0, n, batch):
        obs = {k: torch.as_tensor(data[k][s:s + batch], dtype=torch.float32).to(dev) for k in keys}
        logits, _ = policy_logits_values(policy, obs)
        t = torch.as_tensor(data["teacher_logits"][s:s + batch], dtype=torch.float32).to(dev) / soft_tau
        target = torch.softmax(t, -1)
        ce += float(-(target * torch.log_softmax(logits, -1)).sum())
        ent += float(-(target * torch.log_softmax(t, -1)).sum())
        agree += float((logits.argmax(-1) == t.argmax(-1)).sum())
    return {"ce": ce / n, "teacher_entropy": ent / n, "top1_agreement": agree / n, "frames": n}


def learning_curve(cfg: TrainConfig, train: list[Path], holdout: list[Path], sizes: list[int], seed: int = 0,
                   save: Path | None = None) -> dict[str, Any]:
    """Clones a fresh student (``cfg.head``, ``cfg.variant``) on the first ``size`` frames (whole episodes) of the
    pooled ``train`` iterations for every size, and scores it on the ``holdout`` iterations (module docstring)."""
    d = cfg.dagger
    if d.soft_tau <= 0:
        raise ConfigError(f"train.dagger.soft_tau: expected > 0 (the curve scores the teacher's distribution), got "
                          f"{d.soft_tau}")
    if not sizes or any(s <= 0 for s in sizes) or sorted(sizes) != sizes:
        raise ConfigError(f"--sizes: expected increasing positive frame counts, got {sizes}")
    tr_its, ho_its = iteration_dirs(train), iteration_dirs(holdout)
    check_same_sources([it / "policy" for it in tr_its + ho_its])
    ho_files = episode_files(ho_its)
    ho_keys = {k for _, k, _ in ho_files}
    seen: set[str] = set()
    tr_files = []
    for f, k, n in episode_files(tr_its):
        if k in seen or k in ho_keys:
            continue
        seen.add(k)
        tr_files.append((f, n))
    order = np.random.default_rng(seed).permutation(len(tr_files))
    tr_files = [tr_files[i] for i in order]
    pool = int(sum(n for _, n in tr_files))
    if sizes[-1] > pool:
        raise ConfigError(f"--sizes: expected at most the {pool} distinct training frames of {len(tr_files)} "
                          f"episodes, got {sizes[-1]}")

    enc_dir = encoder_dir(cfg) if cfg.variant != "no_bev" else None
    encoder = load_student_encoder(cfg.variant, enc_dir)
    env = CrowdNavEnv(config=replace(cfg.sim, scene=d.scenes[0], obs_mode="state"))
    env.reset(seed=0)
    observer = observer_for_env(env, cfg.variant, encoder, cfg.head, map_cost=cfg.map_cost,
                                map_heads=load_student_heads(cfg.variant, cfg.head, cfg.map_cost, enc_dir, encoder))
    env.close()
    space = observer.observation_space
    net = student_net(cfg, observer.grid)
    keys = (*space.spaces, "action", "teacher_logits", *(("bev_mirror",) if d.mirror and "bev" in space.spaces else ()))
    ends = np.cumsum([n for _, n in tr_files])
    n_files = [int(np.searchsorted(ends, s) + 1) for s in sizes]  # whole episodes up to at least `size` frames
    log.info("data scale: %d distinct training episodes (%d frames), %d held-out episodes", len(tr_files), pool,
             len(ho_files))
    # the pool in memory up to the profile's dagger.pool_memory_gb, memory-mapped beyond (rl.dagger.pool_frames)
    data = pool_frames([f for f, _ in tr_files[:n_files[-1]]], keys, d.pool_memory_gb)
    data["costs"] = -data.pop("teacher_logits")  # the cloning objective's form (rl.stage: softmin of the costs)
    ho = pool_frames([f for f, _, _ in ho_files], keys, d.pool_memory_gb)
    teacher_dir = policy_root(cfg) / "teacher"
    n_rot = cfg.sim.robot.n_rotations
    torch.set_num_threads(cfg.threads or torch.get_num_threads())
    rows = []
    policy = None
    for size, nf in zip(sizes, n_files, strict=True):
        n = int(ends[nf - 1])
        sub = {k: v[:n] for k, v in data.items()}  # views: each subset is a prefix of the next
        policy, inherited = fresh_student(cfg, space, net, teacher_dir, sub, seed)
        hist, linear_fit = distill(policy, sub, d, cfg.map_signs, seed, n_rot, inherited, True, cfg.progress,
                                   f"data scale {n} frames")
        row = {"size": size, "frames": n, "episodes": nf, "train_ce_last_epoch": hist[-1]["bc_loss"],
               "train_ce": bc_loss(policy, {k: v[:min(n, 4096)] for k, v in sub.items()}, soft_tau=d.soft_tau),
               "holdout": holdout_scores(policy, ho, d.soft_tau),
               **({"linear_fit": {k: linear_fit[k] for k in ("ce_before", "ce_after")}} if linear_fit else {})}
        log.info("data scale %d frames: held-out CE %.3f (teacher entropy %.3f), top-1 agreement %.3f", n,
                 row["holdout"]["ce"], row["holdout"]["teacher_entropy"], row["holdout"]["top1_agreement"])
        rows.append(row)
    result = {"head": cfg.head, "variant": cfg.variant, "seed": seed, "train": [str(p) for p in tr_its],
              "holdout": [str(p) for p in ho_its], "distinct_train_episodes": len(tr_files), "pool_frames": pool,
              "dagger": {"bc_epochs": d.bc_epochs, "bc_batch": d.bc_batch, "bc_lr": d.bc_lr, "soft_tau": d.soft_tau,
                         "mirror": d.mirror}, "rows": rows}
    if save is not None and policy is not None:
        save = Path(save)
        produced = {"teacher": relative_to(teacher_dir, save), "dagger_iterations": 0, "dagger_frames": rows[-1]["frames"],
                    "ppo_finetune_steps": 0, "intention": None,
                    "offline_distillation": {"episodes": rows[-1]["episodes"], "seed": seed,
                                             "from": [str(p) for p in tr_its], "by": "rl.data_scale"}}
        save_policy(save, policy, describe("student", cfg.variant, space, net,
                                           encoder=str(enc_dir) if enc_dir else None, teacher=str(teacher_dir),
                                           intention=None, produced_by=produced))
        result["saved"] = str(save)
        result["saved_from"] = [str(f) for f, _ in tr_files[:n_files[-1]]]  # the features files it was cloned on
    return result


def write_manifest(save: Path, cfg: TrainConfig, result: dict[str, Any], t0: float, code: tuple[str, bool, str],
                   argv: list[str] | None) -> None:
    """The saved student's ``config.yaml`` and ``manifest.json`` (:func:`pipeline.core.stage.finish_output`):
    its inputs the teacher, encoder (and intention model) ``train`` would read and the features files it was cloned
    on; its counts the frames, held-out scores and acceptance SR per cell."""
    row = result["rows"][-1]
    counts: dict[str, Any] = {"frames": row["frames"], "episodes": row["episodes"],
                              "holdout_ce": round(row["holdout"]["ce"], 4),
                              "holdout_top1_agreement": round(row["holdout"]["top1_agreement"], 4)}
    for cell, r in result.get("acceptance", {}).get("table", {}).items():
        counts[f"sr_{cell}"] = round(r["sr"], 3)
    paths = [*inputs(cfg), *map(Path, result["saved_from"])]
    command = [sys.argv[0], *(sys.argv[1:] if argv is None else argv)]
    finish_output(save, "data_scale", cfg, counts, hash_inputs(paths, cfg.data_dir), command, t0, code)


def plot(result: dict[str, Any], path: Path) -> None:
    """Held-out and training cross-entropy, and held-out top-1 agreement, against the frames cloned on (log axis);
    ``--reference`` students as horizontal lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: matplotlib only when a figure is asked for
    from matplotlib.ticker import NullFormatter

    rows = result["rows"]
    x = [r["frames"] for r in rows]
    fig, ax = plt.subplots(1, 2, figsize=(9.5, 3.6))
    ax[0].plot(x, [r["holdout"]["ce"] for r in rows], "o-", label="held-out")
    ax[0].plot(x, [r["train_ce"] for r in rows], "s--", label="training frames")
    ax[0].axhline(rows[0]["holdout"]["teacher_entropy"], color="grey", ls=":", label="teacher's entropy (floor)")
    ax[0].set(ylabel="cross-entropy to the teacher [nats]")
    ax[1].plot(x, [r["holdout"]["top1_agreement"] for r in rows], "o-", label=f"{result['head']} head")
    for i, (ckpt, h) in enumerate(result.get("reference", {}).items()):
        ax[1].axhline(h["top1_agreement"], color=f"C{i + 2}", ls="--", lw=1,
                      label=f"{Path(ckpt).parent.parent.parent.name}/{Path(ckpt).name} (trained)")
    ax[1].set(ylabel="held-out top-1 agreement", ylim=(0, 1))
    for a in ax:
        a.set_xscale("log")
        a.set_xticks(x, [f"{v / 1000:.0f}k" if v >= 1000 else str(v) for v in x])
        a.xaxis.set_minor_formatter(NullFormatter())
        a.set_xlabel("DAgger frames cloned on")
        a.legend(fontsize=7)
    fig.suptitle(f"{result['variant']}, {result['head']} head: imitation of the teacher vs data (held-out "
                 f"{rows[0]['holdout']['frames']} frames of other rollouts)", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


@reports_errors
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m rl.data_scale", description=__doc__.split("\n\n")[0])
    ap.add_argument("--data-dir", type=Path, default=Path("data"), help="the encoder and teacher the frames came from")
    ap.add_argument("--profile", default="default")
    ap.add_argument("--variant", default="full")
    ap.add_argument("--head", default="mlp", help=f"one of {list(STUDENT_HEADS)}")
    ap.add_argument("--train", type=Path, nargs="+", default=[])
    ap.add_argument("--holdout", type=Path, nargs="+", required=True)
    ap.add_argument("--sizes", default="", help="comma-separated frame counts, increasing (none: only --reference)")
    ap.add_argument("--reference", type=Path, nargs="*", default=[],
                    help="trained students (same teacher) scored on the same held-out frames")
    ap.add_argument("--epochs", type=int, default=None, help="cloning epochs (default: the profile's dagger.bc_epochs)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--pool-memory-gb", type=float, default=None,
                    help="frames in memory up to this many GiB, memory-mapped beyond (default: the profile's "
                         "dagger.pool_memory_gb)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--figure", type=Path, default=None)
    ap.add_argument("--save", type=Path, default=None, help="write the largest size's student as a checkpoint")
    ap.add_argument("--acceptance", action="store_true",
                    help="then run the profile's acceptance episodes on it (needs --save; acceptance_episodes.jsonl)")
    ap.add_argument("--acceptance-episodes", type=int, default=None,
                    help="episodes per acceptance cell (default: the profile's acceptance.episodes)")
    a = ap.parse_args(argv)
    t0, code = time.monotonic(), code_state()
    if a.head not in STUDENT_HEADS:
        raise ConfigError(f"--head: expected one of {list(STUDENT_HEADS)}, got {a.head!r}")
    try:
        sizes = [int(s) for s in a.sizes.split(",") if s.strip()]
    except ValueError:
        raise ConfigError(f"--sizes: expected comma-separated integers, got {a.sizes!r}") from None
    over = {"data_dir": str(a.data_dir), "variant": a.variant, "head": a.head, "seed": str(a.seed)}
    if a.epochs is not None:
        over["dagger.bc_epochs"] = str(a.epochs)
    if a.pool_memory_gb is not None:
        over["dagger.pool_memory_gb"] = str(a.pool_memory_gb)
    if a.acceptance_episodes is not None:
        over["acceptance.episodes"] = str(a.acceptance_episodes)
    cfg = load_config(TrainConfig, "train", a.profile, over)
    if sizes and not layout.checkpoint_dir(cfg.data_dir, cfg.encoder).exists() and cfg.variant != "no_bev":
        raise InputMissingError(f"{layout.checkpoint_dir(cfg.data_dir, cfg.encoder)}: the encoder checkpoint the "
                                "frames were cached with is missing")
    if a.acceptance and a.save is None:
        raise ConfigError("--acceptance: expected --save DIR (the checkpoint the episodes run), got none")
    if not sizes and not a.reference:
        raise ConfigError("--sizes / --reference: expected frame counts to clone on or checkpoints to score, got neither")
    if sizes and not a.train:
        raise ConfigError("--train: expected the DAgger frames to clone on (checkpoints or iterations), got none")
    result = learning_curve(cfg, a.train, a.holdout, sizes, a.seed, a.save) if sizes else {"rows": []}
    if a.reference:
        result["reference"] = reference_scores(a.reference, a.holdout, cfg.dagger.soft_tau, cfg.dagger.pool_memory_gb)
    if a.acceptance:
        result["acceptance"] = acceptance(cfg, a.save, f"{cfg.variant}_{cfg.head}_{result['rows'][-1]['frames']}")
    if a.save is not None and result.get("saved"):  # last: a checkpoint without it is unfinished (eval refuses it)
        write_manifest(Path(a.save), cfg, result, t0, code, argv)
    if a.json:
        atomic_write_json(a.json, result)
    if a.figure and result["rows"]:
        plot(result, a.figure)
    for r in result["rows"]:
        h = r["holdout"]
        print(f"{r['frames']:>7} frames ({r['episodes']} episodes): held-out CE {h['ce']:.3f} (teacher entropy "
              f"{h['teacher_entropy']:.3f}), top-1 agreement {h['top1_agreement']:.3f}; training CE {r['train_ce']:.3f}")
    for ckpt, h in result.get("reference", {}).items():
        print(f"{ckpt}: held-out CE {h['ce']:.3f} (teacher entropy {h['teacher_entropy']:.3f}), top-1 agreement "
              f"{h['top1_agreement']:.3f}")
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    raise SystemExit(main())
