"""``python -m rl.cost_refit``: which of the lookahead student's cost terms its teacher's distribution asks to move.

A lookahead student starts from its teacher's linear cost, evaluated on what the student perceives (tracks, intention
forecasts, depth scan) instead of the teacher's ground truth, and by default only its map cost is fitted on top
(``train.dagger.linear_cost: teacher``). This refits, on the student's own DAgger frames and the teacher's soft
targets there, the same convex regression as training (:func:`rl.teacher.fit_lookahead_linear`) with more and more
terms free — the map cost alone (``map``), the pedestrian terms with it (``peds``), every term (``all``) — each time
from the teacher's weights, and reports the cross-entropy each explains and where the weights go. A term whose
weight moves far and explains much when freed is one whose perceived feature does not mean what the teacher's did::

    python -m rl.cost_refit data/checkpoints/policy/full --terms map,peds,all --json refit.json

Numbers in docs/notes/2026-11-pedestrian-terms-refit.md.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.core.errors import ConfigError, InputMissingError, reports_errors
from rl.dagger import load_features
from rl.lookahead import LINEAR_TERMS, PED_CONTACT
from rl.policy import load_policy, read_policy_json
from rl.stage import inherit_linear_cost
from rl.teacher import FIT_TERMS, fit_lookahead_linear, has_lookahead, lookahead_feature_cache


def refit(policy_dir: Path, terms: list[str], soft_tau: float = 1.0, mirror: bool = True, seed: int = 0,
          max_frames: int = 20_000) -> list[dict[str, Any]]:
    """One :func:`fit_lookahead_linear` per entry of ``terms`` on every DAgger frame of the student at
    ``policy_dir``, each from the teacher's linear cost and a zero map cost. Returns :func:`teacher_contacts` on
    those frames (``terms: "perception"``), then the fits' records."""
    policy_dir = Path(policy_dir)
    desc = read_policy_json(policy_dir)
    produced = desc.get("produced_by") or {}
    if desc.get("kind") != "student" or "teacher" not in produced:
        raise ConfigError(f"{policy_dir / 'policy.json'}: produced_by.teacher: expected a DAgger-trained student, "
                          f"got kind {desc.get('kind')!r} with produced_by {produced}")
    for t in terms:
        if t not in FIT_TERMS:
            raise ConfigError(f"--terms: expected a comma-separated subset of {list(FIT_TERMS)}, got {t!r}")
    iters = [policy_dir / "dagger" / f"iter_{k}" for k in range(int(produced.get("dagger_iterations", 0)))]
    if not iters:
        raise InputMissingError(f"{policy_dir}: no DAgger iterations to refit on (produced_by {produced})")
    # the last iteration's policy as cloned (no obstacle shield: the fit reads the cost, not the shielded logits)
    policy, _ = load_policy(iters[-1] / "policy", shield_s=0.0)
    if not has_lookahead(policy):
        raise ConfigError(f"{policy_dir / 'policy.json'}: net.head: expected 'lookahead', got "
                          f"{desc['net'].get('head')!r}")
    data = load_features(iters)
    if "teacher_logits" not in data:
        raise InputMissingError(f"{policy_dir}/dagger: the frames hold no teacher_logits (recorded with soft_tau 0)")
    data["costs"] = -data.pop("teacher_logits")
    n_rot = int(desc["net"]["robot"]["n_rotations"])  # the action grid's yaw rates (mirroring reverses them)
    cache = lookahead_feature_cache(policy, data, mirror, n_rot)
    head = policy.features_extractor.lookahead
    teacher = (policy_dir / produced["teacher"]).resolve()
    out = [{"terms": "perception", **teacher_contacts(cache[0], data["action"])}]
    for t in terms:
        inherit_linear_cost(policy, teacher)
        if head.n_map:
            with torch.no_grad():
                head.map_cost.weight.zero_()
        fit = fit_lookahead_linear(policy, data, soft_tau, max_frames=max_frames, seed=seed, mirror=mirror,
                                   n_rot=n_rot, cache=cache, terms=t)
        out.append({"terms": t, **fit})
    return out


def teacher_contacts(feats: np.ndarray, actions: np.ndarray) -> dict[str, Any]:
    """How the student's perceived pedestrian-contact feature (the first :data:`rl.lookahead.PED_TERMS`) reads the
    teacher's own choices: the share of frames where some arc is predicted to touch a person, where the teacher's
    action is, and where the teacher's action is not the least-contact arc. ``feats``: ``N x A x F`` (unmirrored)."""
    contact = feats[..., PED_CONTACT].astype(np.float32)
    chosen = contact[np.arange(len(actions)), actions]
    return {"frames": int(len(actions)), "any_arc_contact": float((contact > 0).any(1).mean()),
            "teacher_action_contact": float((chosen > 0).mean()),
            "teacher_action_not_least_contact": float((chosen > contact.min(1) + 1e-6).mean())}


def markdown(policy_dir: Path, fits: list[dict[str, Any]]) -> str:
    names = list(LINEAR_TERMS)
    seen, fits = fits[0], fits[1:]
    lines = [f"{policy_dir}: the student's perception of the teacher's choices on {seen['frames']} frames: some arc "
             f"predicted to touch a person {seen['any_arc_contact']:.1%}, the teacher's action "
             f"{seen['teacher_action_contact']:.1%}, the teacher's action not the least-contact arc "
             f"{seen['teacher_action_not_least_contact']:.1%}", "",
             f"Refits on {fits[0]['frames']} frames (with mirrored copies); weights in nats per unit", "",
             "| terms free | CE before | CE after | " + " | ".join(names) + " | map weights |",
             "|---|---|---|" + "---|" * len(names) + "---|"]
    for f in fits:
        lines.append(f"| {f['terms']} | {f['ce_before']:.2f} | {f['ce_after']:.2f} | "
                     + " | ".join(f"{f['linear_weights'][n]:.1f}" for n in names)
                     + f" | {f.get('map_weights', '–')} |")
    return "\n".join(lines) + "\n"


@reports_errors
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m rl.cost_refit", description=__doc__.split("\n\n")[0])
    ap.add_argument("policy", type=Path, help="a DAgger-trained lookahead student (checkpoints/policy/<variant>)")
    ap.add_argument("--terms", default="map,peds,all", help=f"comma-separated, of {list(FIT_TERMS)}")
    ap.add_argument("--soft-tau", type=float, default=1.0, help="the targets' temperature (train.dagger.soft_tau)")
    ap.add_argument("--json", type=Path, default=None, help="also write the fits here")
    args = ap.parse_args(argv)
    if not args.soft_tau > 0:
        raise ConfigError(f"--soft-tau: expected > 0, got {args.soft_tau}")
    fits = refit(args.policy, [t.strip() for t in args.terms.split(",") if t.strip()], args.soft_tau)
    if args.json:
        args.json.write_text(json.dumps(fits, indent=2))
    print(markdown(args.policy, fits), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
