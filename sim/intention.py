"""Does body pose announce intention? Measure how long head turns precede walking turns in a free crowd.

For every decision a pedestrian makes (a new goal that turns its walking direction by at least ``min_turn_deg``)
we find the first step at which the head yaw has covered half of the turn and the first step at which the
walking direction (velocity heading) has; their difference is the *head lead*. The design target is 0.3–1.0 s
plus the relaxation of the walking direction; a lead ≤ 0 would mean poses carry no intention.

::

    python -m sim.intention --scene office_lobby --density 0.2 --seconds 120 --plot data/intention.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from sim.crowd import Crowd, CrowdConfig, heading_of
from sim.geometry import wrap_angle
from sim.humans import Bodies, BodyConfig
from sim.scene import load_scene


def simulate(scene: str, density: float, seconds: float, seed: int = 0, dt: float = 0.1) -> dict[str, np.ndarray]:
    """Run a crowd without a robot; returns per-step arrays (``T x N``) of head yaw, walking yaw and decisions."""
    rng = np.random.default_rng(seed)
    layout = load_scene(scene).layout(rng)
    n = max(1, layout.ped_count(density))
    bodies = Bodies(BodyConfig(), rng, n, np.zeros(n))
    crowd = Crowd(layout, CrowdConfig(), rng, n, bodies.radius)
    walk_prev = heading_of(crowd.vel, np.zeros(n))
    head, walk, switch, target = [], [], [], []
    for _ in range(int(seconds / dt)):
        lead_before = crowd.lead.copy()
        prev = crowd.pos.copy()
        crowd.step(dt)
        bodies.update(dt, crowd.pos, crowd.vel, crowd.attention_xy(), np.linalg.norm(crowd.pos - prev, axis=1))
        walk_prev = heading_of(crowd.vel, walk_prev)
        head.append(bodies.head_yaw.copy())
        walk.append(walk_prev.copy())
        # a decision: a lead was started this step (pending goal drawn)
        started = (crowd.lead > 0) & ~(lead_before > 0)
        switch.append(started)
        to = crowd.pending - crowd.pos
        target.append(np.arctan2(to[:, 1], to[:, 0]))
    return {"head": np.array(head), "walk": np.array(walk), "decision": np.array(switch),
            "target": np.array(target), "dt": np.array(dt)}


def head_leads(sim: dict[str, np.ndarray], min_turn_deg: float = 45.0, window_s: float = 4.0) -> np.ndarray:
    """Head lead (s) of every decision that turns the walking direction by at least ``min_turn_deg``."""
    dt = float(sim["dt"])
    head, walk, dec, tgt = sim["head"], sim["walk"], sim["decision"], sim["target"]
    w = int(window_s / dt)
    out = []
    for k, i in zip(*np.nonzero(dec), strict=True):
        if k == 0 or k + w >= len(head):
            continue
        start = walk[k - 1, i]
        turn = wrap_angle(tgt[k, i] - start)
        if abs(turn) < np.radians(min_turn_deg):
            continue
        half = np.sign(turn) * wrap_angle(np.stack([head[k:k + w, i], walk[k:k + w, i]]) - start) >= abs(turn) / 2
        if not half[0].any() or not half[1].any():
            continue
        out.append((np.argmax(half[1]) - np.argmax(half[0])) * dt)
    return np.array(out)


def plot_example(sim: dict[str, np.ndarray], path: Path, ped: int = 0, seconds: float = 30.0) -> Path:
    """Head yaw and walking direction of one pedestrian over time, decisions marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dt = float(sim["dt"])
    n = min(len(sim["head"]), int(seconds / dt))
    t = np.arange(n) * dt
    fig, ax = plt.subplots(figsize=(9, 3.2))
    head = np.unwrap(sim["head"][:n, ped])
    walk = head + wrap_angle(sim["walk"][:n, ped] - head)  # same 2π branch as the head
    ax.plot(t, np.degrees(head), label="head yaw")
    ax.plot(t, np.degrees(walk), label="walking direction")
    for k in np.nonzero(sim["decision"][:n, ped])[0]:
        ax.axvline(k * dt, color="grey", lw=0.8, ls=":")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("yaw [deg]")
    ax.set_title("head turns before the walk turns (dotted: decisions)")
    ax.legend(loc="best")
    fig.tight_layout()
    from sim.viz import save_figure  # lazy: matplotlib only for the figure

    save_figure(fig, path, 110)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="office_lobby")
    ap.add_argument("--density", type=float, default=0.2)
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--plot", type=Path, default=None)
    a = ap.parse_args(argv)
    s = simulate(a.scene, a.density, a.seconds, a.seed)
    leads = head_leads(s)
    q = np.percentile(leads, [10, 50, 90]) if len(leads) else [np.nan] * 3
    print(f"decisions turning >= 45 deg: {len(leads)}; head lead p10/median/p90 = "
          f"{q[0]:.2f}/{q[1]:.2f}/{q[2]:.2f} s; share with lead > 0: {np.mean(leads > 0):.2f}")
    if a.plot:
        print(f"wrote {plot_example(s, a.plot)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
