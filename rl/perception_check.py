"""``python -m rl.perception_check``: the students' lookahead perception (:mod:`rl.perceive`) measured against
the simulator's truth on episodes driven by the privileged expert (numbers in docs/results.md)::

    python -m rl.perception_check --scene office_lobby --density 0.2 --seeds 0,1,2 --figure docs/img/perception_lobby.png

Besides the tracks' and the scan's errors, it compares what decides the lookahead head: per action arc of the grid,
whether the perceived people (tracks, and with ``--intention CKPT`` the intention model's forecasts) put someone in
the robot's contact zone along it — against the same feature on the true positions and velocities, which is what
the privileged teacher's cost reads.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from pretrain.intention import load_forecaster  # noqa: E402
from rl.lookahead import PED_CONTACT  # noqa: E402
from rl.observe import observer_for_env  # noqa: E402
from rl.policy import build_policy, obs_to_tensor  # noqa: E402
from sim.env import CrowdNavEnv, SimConfig  # noqa: E402
from sim.episode import episode_steps  # noqa: E402
from sim.expert import ExpertDriver  # noqa: E402
from sim.geometry import world_to_robot  # noqa: E402
from sim.viz import save_figure  # noqa: E402
from sim.wrappers import PrivilegedWorld  # noqa: E402


def evaluate_perception(scene: str = "office_lobby", density: float = 0.2, seed: int = 0, steps: int = 150,
                        width_px: int = 160, height_px: int = 120, figure: str | None = None,
                        figure_step: int = 60, forecaster=None) -> dict[str, float]:
    """Drives the privileged expert through one rendered episode and compares what the lookahead head perceives with
    the simulator's truth: the error of each track against the nearest true pedestrian within 0.6 m (position, and
    velocity once the track is 1 s old), the share of true pedestrians within 4 m in the cameras' view that have a
    track within 0.6 m, and the share of in-view scan bins (±35°) that match the static map within 0.3 m or end on a
    pedestrian; and, over every action arc of every step, the perceived pedestrian-contact feature against the one on
    the true pedestrians (:func:`contact_agreement`; ``forecaster``: the intention model whose forecasts the
    perceived people are rolled out with, else constant velocity). With ``figure`` also a top-down figure of the robot
    frame at ``figure_step``."""
    cfg = SimConfig()
    cfg = replace(cfg, scene=scene, density=density, obs_mode="visual", info_level="basic",
                  camera=replace(cfg.camera, width_px=width_px, height_px=height_px))
    env = PrivilegedWorld(CrowdNavEnv(config=cfg))
    u = env.unwrapped
    rollout = "intention model" if forecaster is not None else "constant velocity"  # how the tracks are rolled out
    observer = observer_for_env(u, "no_bev", None, head="lookahead", forecaster=forecaster)
    observer.reset()
    head = contact_head(u, observer)
    view_deg = abs(float(cfg.camera.yaw_deg)) + float(cfg.camera.hfov_deg) / 2.0  # the cameras' joint half-view
    pos_err, vel_err, recall, scan_ok, contact = [], [], [], [], []
    ahead = np.r_[0:8, 65:72]
    snap = None
    step = 0
    for tr in episode_steps(env, ExpertDriver(), seed):
        step = tr.step
        if tr.done or step >= steps:
            break
        o = observer(tr.obs)
        world = tr.info["world"]
        people = world_to_robot(world.crowd.pos, world.robot)
        pvel = world_to_robot(world.crowd.vel, world.robot, vectors=True)
        tracks = o["peds"][o["peds"][:, 5] > 0]
        if len(people) and len(tracks):
            d = np.linalg.norm(tracks[:, None, :2] - people[None], axis=-1)
            for i, j in enumerate(d.argmin(1)):
                if d[i, j] < 0.6:
                    pos_err.append(d[i, j])
                    if step >= 10:
                        vel_err.append(float(np.linalg.norm(tracks[i, 2:4] - pvel[j])))
        bearing = np.degrees(np.arctan2(people[:, 1], people[:, 0]))
        seen = (np.abs(bearing) < 65) & (np.hypot(people[:, 0], people[:, 1]) < 4.0)
        for p in people[seen]:
            recall.append(bool(len(tracks)) and float(np.linalg.norm(tracks[:, :2] - p, axis=-1).min()) < 0.6)
        static_scan = u.static_scan()  # the truth this check compares with
        rng = np.minimum(o["scan"][ahead], 4.0)
        static = np.minimum(static_scan[ahead], 4.0)
        ang = ahead * (2 * np.pi / len(o["scan"]))
        hit = np.stack([rng * np.cos(ang), rng * np.sin(ang)], -1)
        on_person = (np.linalg.norm(hit[:, None] - people[None], axis=-1).min(1) < 0.6) if len(people) else False
        scan_ok.append((np.abs(rng - static) < 0.3) | (on_person & (rng < 4.0)))
        contact.append(contact_agreement(head, o, u.privileged_peds(), view_deg))
        if step == figure_step:
            snap = (o, people, pvel, static_scan, contact[-1], head.arcs.numpy())
    env.close()
    out = {"frames": step, "track_pos_err_median_m": float(np.median(pos_err)),
           "track_pos_err_p90_m": float(np.percentile(pos_err, 90)),
           "track_vel_err_median_mps": float(np.median(vel_err)), "track_vel_err_p90_mps": float(np.percentile(vel_err, 90)),
           "track_recall_in_view_4m": float(np.mean(recall)), "scan_bins_explained_in_view": float(np.mean(np.concatenate(scan_ok))),
           **contact_shares(np.concatenate(contact)), "people": rollout}
    if figure and snap is not None:
        _plot_snapshot(snap, figure, f"{scene} @ {density:g} ped/m², seed {seed}, step {figure_step}")
    return out


def contact_head(env, observer):
    """The lookahead head a student of ``env``'s robot builds over ``observer``'s observations (its arcs and
    features need no trained weights)."""
    from dataclasses import asdict

    c = env.cfg
    net = {"head": "lookahead", "robot": asdict(c.robot), "dt_s": c.dt_s, "scan_range_m": c.scan_range_m}
    return build_policy("student", "no_bev", observer.observation_space, net).features_extractor.lookahead


@torch.no_grad()
def contact_agreement(head, obs: dict[str, np.ndarray], true_peds: np.ndarray, view_deg: float = 180.0
                      ) -> np.ndarray:
    """``A x 3``: per action arc the head's pedestrian-contact feature (discounted intrusion into the contact zone)
    on the perceived people of ``obs`` (their forecasts when it has ``peds_future``), on ``true_peds`` (``K x 6``
    [x, y, vx, vy, r, present], robot frame, rolled out at constant velocity as the teacher's cost does), and on
    those of them now within ``view_deg`` of the heading (the cameras' joint half-view: people a student could see)."""
    truth = {k: v for k, v in obs.items() if k != "peds_future"}
    seen = true_peds.copy()
    seen[np.abs(np.degrees(np.arctan2(seen[:, 1], seen[:, 0]))) > view_deg, 5] = 0.0
    out = [head.action_features(obs_to_tensor(o))[0, :, PED_CONTACT]
           for o in (obs, truth | {"peds": true_peds}, truth | {"peds": seen})]
    return torch.stack(out, -1).numpy()


def contact_shares(c: np.ndarray) -> dict[str, float]:
    """From :func:`contact_agreement` rows: the share of arcs predicted to touch someone on the perceived and on the
    true people, of the perceived contacts the share with none in truth (false), of the true contacts the share the
    perception misses, and of the true contacts with people in view the share it misses."""
    p, t, v = c[:, 0] > 0, c[:, 1] > 0, c[:, 2] > 0
    return {"contact_arcs_perceived": float(p.mean()), "contact_arcs_true": float(t.mean()),
            "contact_false_share": float((p & ~t).sum() / max(p.sum(), 1)),
            "contact_missed_share": float((t & ~p).sum() / max(t.sum(), 1)),
            "contact_missed_share_in_view": float((v & ~p).sum() / max(v.sum(), 1))}


def _plot_snapshot(snap, path: str, title: str) -> None:
    o, people, pvel, static, contact, arcs = snap
    rays = len(o["scan"])
    ang = np.arange(rays) * (2 * np.pi / rays)
    fig, ax = plt.subplots(figsize=(6.4, 5.6))
    # the action arcs (robot frame, over the lookahead horizon), by whether perception and truth predict a contact
    perceived, true = contact[:, 0] > 0, contact[:, 1] > 0
    for mask, colour, label in ((~perceived & ~true, "0.8", "arc: no contact (both)"),
                                (perceived & true, "tab:purple", "arc: contact (both)"),
                                (perceived & ~true, "tab:orange", "arc: false contact (perceived only)"),
                                (~perceived & true, "tab:cyan", "arc: missed contact (truth only)")):
        for k, i in enumerate(np.flatnonzero(mask)):
            ax.plot(arcs[i, :, 0], arcs[i, :, 1], c=colour, lw=0.8, zorder=0, label=label if k == 0 else None)
    for r, style, label in ((static, dict(c="0.6", s=14, marker="s"), "static map (truth)"),
                            (o["scan"], dict(c="k", s=22, marker="x"), "depth scan (perceived)")):
        m = r < 9.99
        ax.scatter(r[m] * np.cos(ang[m]), r[m] * np.sin(ang[m]), label=label, **style)
    ax.scatter(people[:, 0], people[:, 1], s=120, facecolors="none", edgecolors="tab:blue", label="pedestrians (truth)")
    ax.quiver(people[:, 0], people[:, 1], pvel[:, 0], pvel[:, 1], color="tab:blue", angles="xy", scale_units="xy",
              scale=1.0, width=0.004)
    tr = o["peds"][o["peds"][:, 5] > 0]
    ax.scatter(tr[:, 0], tr[:, 1], s=40, c="tab:red", label="tracks from detected poses")
    ax.quiver(tr[:, 0], tr[:, 1], tr[:, 2], tr[:, 3], color="tab:red", angles="xy", scale_units="xy", scale=1.0,
              width=0.004)
    for a in (np.radians(70), -np.radians(70)):
        ax.plot([0, 6 * np.cos(a)], [0, 6 * np.sin(a)], ls=":", c="0.4", lw=0.8)
    ax.add_patch(plt.Circle((0, 0), 0.3, color="tab:green", alpha=0.6))
    ax.set_xlim(-3, 6)
    ax.set_ylim(-4.5, 4.5)
    ax.set_aspect("equal")
    ax.set_xlabel("x forward [m] (robot frame; arrows: velocity over 1 s)")
    ax.set_ylabel("y left [m]")
    ax.set_title(title, fontsize=10)
    ax.legend(loc="lower left", fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, 110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="measure the lookahead head's perception against the simulator's truth")
    ap.add_argument("--scene", default="office_lobby")
    ap.add_argument("--density", type=float, default=0.2)
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--figure", default=None)
    ap.add_argument("--intention", default=None, help="an intention checkpoint: roll the tracks out with its forecasts")
    a = ap.parse_args(argv)
    forecaster = None
    if a.intention:
        forecaster = load_forecaster(a.intention)[0]
    rows = [evaluate_perception(a.scene, a.density, int(s), figure=a.figure if i == 0 else None,
                                forecaster=forecaster) for i, s in enumerate(a.seeds.split(","))]
    print(json.dumps({k: round(float(np.mean([r[k] for r in rows])), 3) for k in rows[0] if k != "people"}
                     | {"people": rows[0]["people"], "episodes": len(rows)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
