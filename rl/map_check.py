"""``python -m rl.map_check``: what the lookahead head's map cost does with the BEV along a student's own episodes.

The map cost (``train.map_cost``, :meth:`rl.lookahead.LookaheadHead.map_features`) adds four fitted terms to every
action's logit: the static channel's max and discounted mean along the arc, the people channels' max and discounted
mean. This drives a saved student through rendered episodes (its own actions, as in eval) and reports per term how
much it separates the actions (the spread of its contribution over the action grid, in nats), the people channel's
level along the arcs, and how often dropping the two people terms would change the chosen action — in an empty scene
(density 0: whatever the people channels hold is not people) and in a crowd::

    python -m rl.map_check data/checkpoints/policy/full --sim-from data/eval/<run> --densities 0,0.2 --seeds 31000,31001

``--sim-from``: an eval run whose simulator config (its ``config.yaml``) the episodes use — the cameras must be
the ones the student's encoder was trained for; without it, :class:`sim.env.SimConfig`'s defaults.

Numbers in docs/notes/2026-11-pedestrian-hits-untracked-people.md.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.core.config import from_dict, read_yaml_mapping
from pipeline.core.errors import ConfigError, reports_errors
from rl.driver import PolicyDriver
from rl.lookahead import N_LINEAR, N_MAP, SCORE_SCALE
from rl.policy import obs_to_tensor
from sim.env import CrowdNavEnv, SimConfig
from sim.episode import episode_steps
from sim.viz import save_figure

MAP_TERMS = ("static_max", "static_mean", "people_max", "people_mean")  # LookaheadHead.map_features, in order
PEOPLE = slice(2, 4)  # the people terms of MAP_TERMS


def map_terms(head: Any, feats: torch.Tensor) -> torch.Tensor:
    """``B x A x`` :data:`N_MAP` contributions (nats) of the fitted map cost's terms to each action's logit, from the
    head's :meth:`~rl.lookahead.LookaheadHead.action_features` ``feats``; a head without a map is a ConfigError."""
    if not getattr(head, "n_map", 0):
        raise ConfigError("map_check: the policy's lookahead head reads no occupancy map (train.map_cost off)")
    x = feats[..., -N_LINEAR - N_MAP:-N_LINEAR]
    return SCORE_SCALE * x * head.map_cost.weight[0]


def step_stats(logits: torch.Tensor, terms: torch.Tensor, feats_people_mean: torch.Tensor) -> dict[str, Any]:
    """One step's numbers: per term the spread of its contribution over the actions (nats), the people-mean feature
    (mean over actions) and whether the chosen action (argmax of ``logits``, ``A``) changes without the people terms."""
    spread = (terms.amax(0) - terms.amin(0)).tolist()
    without = logits - terms[:, PEOPLE].sum(-1)
    return {"spread": spread, "people_level": float(feats_people_mean.mean()),
            "changed": int(without.argmax()) != int(logits.argmax())}


def run_check(policy: Path, scene: str, density: float, seeds: list[int], steps: int,
              sim: SimConfig | None = None, snapshot_step: int = 20) -> dict[str, Any]:
    """Drives ``policy`` (a saved lookahead student with a map) through ``seeds`` in ``scene`` at ``density`` (at most
    ``steps`` control steps each) and summarises :func:`step_stats` over all steps; ``snapshot``: the map the head
    read at step ``snapshot_step`` of the first seed (``C x X x Y``, for :func:`draw`)."""
    torch.set_num_threads(1)
    driver = PolicyDriver(Path(policy))
    head = getattr(driver.policy.features_extractor, "lookahead", None)
    if head is None:
        raise ConfigError(f"map_check: {policy} has no lookahead head")
    cfg = replace(sim or SimConfig(), scene=scene, density=float(density), scenario="", obs_mode="visual",
                  action_type="discrete")
    env = CrowdNavEnv(config=cfg)
    rows, snapshot = [], None
    try:
        for seed in seeds:
            for tr in episode_steps(env, driver, int(seed)):
                o = driver.last_obs
                if tr.step == 0 or o is None:
                    continue
                if tr.step > steps:
                    break
                obs = obs_to_tensor({k: o[k] for k in driver.policy.observation_space.spaces})
                with torch.no_grad():
                    feats = head.action_features(obs)
                    logits = driver.policy.features_extractor(obs)[0, :head.n_actions]
                rows.append(step_stats(logits, map_terms(head, feats)[0], feats[0, :, -N_LINEAR - 1]))
                if snapshot is None and (tr.step == snapshot_step or tr.terminated or tr.truncated):
                    snapshot = np.asarray(o[head.map_key], np.float32)
    finally:
        env.close()
    if not rows:
        raise ConfigError(f"map_check: no step was driven (seeds {seeds}, steps {steps})")
    spread = np.array([r["spread"] for r in rows])
    return {"policy": str(policy), "scene": scene, "density": float(density), "seeds": list(seeds), "steps": len(rows),
            "weights_nats": (SCORE_SCALE * head.map_cost.weight[0]).tolist(),
            "spread_nats": dict(zip(MAP_TERMS, spread.mean(0).round(3).tolist(), strict=True)),
            "people_mean_level": float(np.mean([r["people_level"] for r in rows])),
            "changed_without_people_terms": float(np.mean([r["changed"] for r in rows])), "snapshot": snapshot,
            "map_bounds": driver.desc["net"]["map_bounds"]}


def draw(results: list[dict[str, Any]], path: Path) -> Path:
    """One row per result: each channel of its snapshot map (robot frame, x forward up, y left to the left)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (x0, x1), (y0, y1) = results[0]["map_bounds"]
    names = ["static", "people now", "people +0.5 s", "people +1.0 s"]
    n = max(len(r["snapshot"]) for r in results)
    fig, axes = plt.subplots(len(results), n, figsize=(2.4 * n, 2.6 * len(results)), squeeze=False)
    for row, r in zip(axes, results, strict=True):
        for c, ax in enumerate(row):
            if c < len(r["snapshot"]):
                im = ax.imshow(r["snapshot"][c], origin="lower", extent=(y1, y0, x0, x1), vmin=0, vmax=1,
                               cmap="magma")
                ax.plot(0, 0, "c^", ms=6)
            ax.set_title(f"{r['scene']} @ {r['density']:g}: {names[c] if c < len(names) else c}", fontsize=7)
            ax.tick_params(labelsize=6)
    fig.colorbar(im, ax=axes, shrink=0.6, label="predicted occupancy")
    out = save_figure(fig, path)
    plt.close(fig)
    return out


def markdown(results: list[dict[str, Any]]) -> str:
    lines = ["| scene @ density | steps | " + " | ".join(f"{t} spread (nats)" for t in MAP_TERMS)
             + " | people-mean feature | argmax changed without the people terms |", "|---|---|" + "---|" * 6]
    for r in results:
        lines.append(f"| {r['scene']} @ {r['density']:g} | {r['steps']} | "
                     + " | ".join(f"{r['spread_nats'][t]:.1f}" for t in MAP_TERMS)
                     + f" | {r['people_mean_level']:.3f} | {r['changed_without_people_terms']:.2f} |")
    return "\n".join(lines) + "\n"


@reports_errors
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m rl.map_check", description=__doc__.split("\n\n")[0])
    ap.add_argument("policy", type=Path, help="a saved lookahead student with a map (checkpoints/policy/<variant>)")
    ap.add_argument("--scene", default="office_lobby")
    ap.add_argument("--densities", default="0,0.2", help="comma-separated ped/m² (0 = an empty scene)")
    ap.add_argument("--seeds", default="31000,31001", help="comma-separated episode seeds")
    ap.add_argument("--steps", type=int, default=100, help="control steps per episode at most")
    ap.add_argument("--sim-from", type=Path, default=None, help="an eval run whose sim config to use")
    ap.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    ap.add_argument("--figure", type=Path, default=None, help="draw each density's map at step 20 of the first seed")
    args = ap.parse_args(argv)
    try:
        densities = [float(d) for d in args.densities.split(",")]
        seeds = [int(s) for s in args.seeds.split(",")]
    except ValueError:
        raise ConfigError(f"--densities / --seeds: expected comma-separated numbers, got {args.densities!r}, "
                          f"{args.seeds!r}") from None
    if args.steps < 1:
        raise ConfigError(f"--steps: expected an integer >= 1, got {args.steps}")
    sim = None
    if args.sim_from is not None:
        where = args.sim_from / "config.yaml"
        sim = from_dict(SimConfig, read_yaml_mapping(where, "eval config").get("sim", {}), str(where))
    results = [run_check(args.policy, args.scene, d, seeds, args.steps, sim) for d in densities]
    if args.figure:
        draw(results, args.figure)
    if args.json:
        args.json.write_text(json.dumps([{k: v for k, v in r.items() if k != "snapshot"} for r in results], indent=2))
    print(markdown(results), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
