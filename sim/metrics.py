"""Per-episode navigation metrics, their aggregation over episodes, and paired method comparisons.

Conventions (all distances in metres, times in seconds, world frame; ``T`` steps, ``N`` pedestrians, states
``t = 0..T`` as in :mod:`sim.trace`):

* The robot is a disc of radius ``r_R``; pedestrian ``j`` a disc of radius ``r_j``; ``d_j(t)`` is the distance
  between the two centres.
* **Private zone** (the paper's TPZ): the robot is in pedestrian ``j``'s private zone at state ``t`` when the
  distance from the pedestrian's centre to the robot's footprint, ``d_j(t) - r_R``, is ``< private_zone_m``
  (0.8 m). ``tpz_s = dt * #{t in 1..T : in some pedestrian's private zone}``.
* **Clearance** to a pedestrian: ``d_j(t) - r_R - r_j`` (negative when the discs overlap). The minimum is taken over
  all states ``t = 0..T`` and all pedestrians; it is ``nan`` when there are no pedestrians (``inf`` would not survive
  JSON).
* **Personal-space compliance**: fraction of states ``t = 1..T`` where ``d_j(t) - r_R >= personal_space_m`` for
  every pedestrian (1.0 without pedestrians).
* **Step-based** quantities use the states reached by the commands (``t = 1..T``); quantities that need the motion
  *from* a state (path irregularity, TTC) use ``t = 0..T-1`` with the robot velocity
  ``(xy[t+1] - xy[t]) / dt``.
* **TTC**: both robot and pedestrian keep their velocity; collision when the centre distance reaches
  ``r_R + r_j``; horizon :data:`TTC_HORIZON_S` (10 s). A (state, pedestrian) pair with no predicted collision
  within the horizon counts as the horizon; overlapping discs count as 0. ``min_ttc_s`` is the minimum over
  ``t = 0..T-1`` and pedestrians (the horizon without pedestrians).
* Metrics undefined for an episode (e.g. ``mean_speed_mps`` with ``T = 0``, ``spl`` with unknown shortest path)
  are ``nan``; :func:`aggregate` skips ``nan`` (and infinite) values.
* NT, PL and TPZ are averaged over successful episodes only (:data:`SUCCESS_ONLY`), as in the paper.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from sim.geometry import wrap_angle
from sim.trace import EpisodeTrace

TTC_HORIZON_S = 10.0
"""Time-to-collision horizon, s; pairs with no collision predicted within it contribute this value."""

BINARY_METRICS: tuple[str, ...] = (
    "success",
    "collision",
    "collision_pedestrian",
    "collision_obstacle",
    "timeout",
)
"""0/1 metrics, aggregated as rates with a Wilson score interval."""

SUCCESS_ONLY: tuple[str, ...] = ("nav_time_s", "path_length_m", "tpz_s")
"""Metrics averaged over successful episodes only (the paper's NT, PL, TPZ)."""

METRIC_KEYS: tuple[str, ...] = (
    *BINARY_METRICS,
    "nav_time_s",
    "path_length_m",
    "tpz_s",
    "min_ped_clearance_m",
    "min_static_clearance_m",
    "personal_space_compliance",
    "spl",
    "path_irregularity_rad",
    "mean_jerk_mps3",
    "min_ttc_s",
    "mean_speed_mps",
    "final_goal_distance_m",
)
"""Keys returned by :func:`episode_metrics`, in order."""


def time_to_collision(
    rel_pos: np.ndarray, rel_vel: np.ndarray, radius: np.ndarray, horizon_s: float = TTC_HORIZON_S
) -> np.ndarray:
    """Constant-velocity time to collision of disc pairs.

    Args:
        rel_pos: ``... x 2`` position of the other disc relative to the first, m.
        rel_vel: ``... x 2`` velocity of the other disc relative to the first, m/s.
        radius: ``...`` (broadcastable) collision distance between the centres, m.
        horizon_s: value for pairs that do not collide within it, s.

    Returns:
        ``...`` times to collision in ``[0, horizon_s]``, s; 0 where the discs already overlap.
    """
    p = np.asarray(rel_pos, dtype=np.float64)
    w = np.asarray(rel_vel, dtype=np.float64)
    a = np.einsum("...i,...i->...", w, w)
    b = np.einsum("...i,...i->...", p, w)  # half of the usual b
    c = np.einsum("...i,...i->...", p, p) - np.asarray(radius, dtype=np.float64) ** 2
    disc = b * b - a * c
    approaching = (a > 0) & (b < 0) & (disc >= 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        tau = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
    tau = np.where(approaching & (tau <= horizon_s), tau, horizon_s)
    return np.where(c <= 0, 0.0, np.maximum(tau, 0.0))


def episode_metrics(
    trace: EpisodeTrace, private_zone_m: float = 0.8, personal_space_m: float = 1.2
) -> dict[str, float]:
    """All per-episode metrics of one trace (see the module docstring for the conventions).

    Args:
        trace: the episode; validated first.
        private_zone_m: private-zone radius around a pedestrian centre, measured to the robot footprint, m.
        personal_space_m: personal-space radius for the compliance metric, measured the same way, m.

    Returns:
        ``{key: value}`` for every key of :data:`METRIC_KEYS`: outcome flags ``success``, ``collision``,
        ``collision_pedestrian``, ``collision_obstacle``, ``timeout`` (0.0/1.0); ``nav_time_s`` (s);
        ``path_length_m`` (m); ``tpz_s`` (s); ``min_ped_clearance_m`` (m, nan without pedestrians);
        ``min_static_clearance_m`` (m, nan in an empty scene); ``personal_space_compliance`` (fraction);
        ``spl`` (in [0, 1], nan when the shortest path is unknown); ``path_irregularity_rad`` (rad);
        ``mean_jerk_mps3`` (m/s^3); ``min_ttc_s`` (s); ``mean_speed_mps`` (m/s); ``final_goal_distance_m``
        (robot centre to goal, m).
    """
    trace.validate()
    dt = float(trace.dt_s)
    t_steps = trace.n_steps
    xy = trace.robot_pose[:, :2]  # (T+1) x 2
    yaw = trace.robot_pose[:, 2]
    r_robot = float(trace.robot_radius_m)
    n_peds = trace.n_peds

    out: dict[str, float] = {}
    outcome = trace.outcome
    out["success"] = float(outcome == "success")
    out["collision"] = float(outcome in ("collision_pedestrian", "collision_obstacle"))
    out["collision_pedestrian"] = float(outcome == "collision_pedestrian")
    out["collision_obstacle"] = float(outcome == "collision_obstacle")
    out["timeout"] = float(outcome == "timeout")

    seg = np.diff(xy, axis=0)  # T x 2
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    path_len = float(seg_len.sum())
    out["nav_time_s"] = t_steps * dt
    out["path_length_m"] = path_len

    # pedestrian distances: (T+1) x N
    rel = trace.ped_xy - xy[:, None, :]
    centre = np.hypot(rel[..., 0], rel[..., 1])
    to_footprint = centre - r_robot  # pedestrian centre to robot footprint
    if n_peds:
        in_zone = (to_footprint[1:] < private_zone_m).any(axis=1)  # T
        compliant = (to_footprint[1:] >= personal_space_m).all(axis=1)
        clearance = to_footprint - trace.ped_radius[None, :]
        out["tpz_s"] = float(in_zone.sum()) * dt
        out["min_ped_clearance_m"] = float(clearance.min())
        out["personal_space_compliance"] = float(compliant.mean()) if t_steps else math.nan
    else:
        out["tpz_s"] = 0.0
        out["min_ped_clearance_m"] = math.nan
        out["personal_space_compliance"] = 1.0 if t_steps else math.nan

    static_min = float(np.min(trace.static_clearance_m))
    out["min_static_clearance_m"] = static_min if math.isfinite(static_min) else math.nan

    shortest = float(trace.shortest_path_m)
    if math.isnan(shortest):
        out["spl"] = math.nan
    else:
        denom = max(path_len, shortest)
        out["spl"] = out["success"] * (shortest / denom if denom > 0 else 1.0)

    if t_steps:
        to_goal = trace.goal_xy[None, :] - xy[:-1]
        bearing = np.arctan2(to_goal[:, 1], to_goal[:, 0])
        out["path_irregularity_rad"] = float(np.mean(np.abs(wrap_angle(yaw[:-1] - bearing))))
        out["mean_speed_mps"] = path_len / (t_steps * dt)
    else:
        out["path_irregularity_rad"] = math.nan
        out["mean_speed_mps"] = math.nan

    if t_steps >= 3:
        jerk = np.diff(xy, n=3, axis=0) / dt**3
        out["mean_jerk_mps3"] = float(np.mean(np.hypot(jerk[:, 0], jerk[:, 1])))
    else:
        out["mean_jerk_mps3"] = 0.0

    if t_steps == 0:
        out["min_ttc_s"] = math.nan
    elif n_peds == 0:
        out["min_ttc_s"] = TTC_HORIZON_S
    else:
        v_robot = seg / dt  # T x 2, motion from state t
        ttc = time_to_collision(
            rel[:-1], trace.ped_vel[:-1] - v_robot[:, None, :], r_robot + trace.ped_radius[None, :]
        )
        out["min_ttc_s"] = float(ttc.min())

    out["final_goal_distance_m"] = float(np.hypot(*(xy[-1] - trace.goal_xy)))
    return {k: out[k] for k in METRIC_KEYS}


_NUMERIC = (int, float, np.integer, np.floating, np.bool_)


def wilson_interval(successes: float, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion.

    Args:
        successes: number of positive outcomes (may be fractional if the inputs were averaged).
        n: number of trials.
        confidence: two-sided confidence level.

    Returns:
        ``(low, high)`` in ``[0, 1]``; ``(nan, nan)`` for ``n = 0``.
    """
    if n <= 0:
        return math.nan, math.nan
    from scipy import stats as sps  # lazy: seconds to import; only intervals and tests use it

    z = float(sps.norm.ppf(0.5 + confidence / 2.0))
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def summarize(values: Sequence[float], binary: bool = False, confidence: float = 0.95) -> dict[str, float]:
    """Mean, sample std and confidence interval of the finite values.

    Args:
        values: samples; ``nan`` and infinite values are skipped.
        binary: 0/1 samples: Wilson score interval; otherwise a Student-t interval on the mean.
        confidence: two-sided confidence level.

    Returns:
        ``{"mean", "std", "ci95_low", "ci95_high", "n"}``. ``std`` uses ``ddof=1`` (0 for one sample); every
        statistic is ``nan`` for ``n = 0``; the t interval is ``nan`` for ``n = 1``.
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    n = int(v.size)
    if n == 0:
        return {"mean": math.nan, "std": math.nan, "ci95_low": math.nan, "ci95_high": math.nan, "n": 0}
    mean = float(v.mean())
    std = float(v.std(ddof=1)) if n > 1 else 0.0
    if binary:
        low, high = wilson_interval(float(v.sum()), n, confidence)
    elif n > 1:
        from scipy import stats as sps  # lazy: as in wilson_interval

        half = float(sps.t.ppf(0.5 + confidence / 2.0, df=n - 1)) * std / math.sqrt(n)
        low, high = mean - half, mean + half
    else:
        low, high = math.nan, math.nan
    return {"mean": mean, "std": std, "ci95_low": low, "ci95_high": high, "n": n}


def aggregate(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Aggregate per-episode metric rows.

    Args:
        rows: one dict per episode, e.g. from :func:`episode_metrics` (extra numeric keys are aggregated too;
            non-numeric values such as strings are ignored).

    Returns:
        ``{"episodes": len(rows), key: summarize(...)}`` for every numeric key seen in the rows (see
        :func:`summarize`). Keys of :data:`BINARY_METRICS` get a Wilson interval; keys of :data:`SUCCESS_ONLY` use
        only rows with ``success == 1``; ``n`` counts the rows actually used.
    """
    keys: list[str] = []
    for row in rows:
        keys.extend(k for k, v in row.items() if k not in keys and isinstance(v, _NUMERIC))
    result: dict[str, Any] = {"episodes": len(rows)}
    for k in keys:
        used = [r for r in rows if k in r]
        if k in SUCCESS_ONLY:
            used = [r for r in used if r.get("success") == 1]
        values = [float(r[k]) for r in used if isinstance(r[k], _NUMERIC)]
        result[k] = summarize(values, binary=k in BINARY_METRICS)
    return result


def paired_test(a: Sequence[float], b: Sequence[float]) -> dict[str, float]:
    """Paired comparison of two methods evaluated on the same seeds.

    Args:
        a: per-seed values of method A.
        b: per-seed values of method B, same order and length; pairs with a non-finite member are dropped.

    Returns:
        ``{"mean_diff": mean(a - b), "p_value": two-sided Wilcoxon signed-rank p, "n": pairs used}``. The p-value
        is ``nan`` for fewer than 5 pairs or when every difference is zero; ``mean_diff`` is ``nan`` without pairs.

    Raises:
        ValueError: ``a`` and ``b`` differ in length.
    """
    x = np.asarray(a, dtype=np.float64).ravel()
    y = np.asarray(b, dtype=np.float64).ravel()
    if x.shape != y.shape:
        raise ValueError(f"paired_test needs equally long inputs, got {x.size} and {y.size}")
    keep = np.isfinite(x) & np.isfinite(y)
    d = x[keep] - y[keep]
    n = int(d.size)
    mean_diff = float(d.mean()) if n else math.nan
    p_value = math.nan
    if n >= 5 and np.any(d != 0):
        from scipy import stats as sps  # lazy: as in wilson_interval

        p_value = float(sps.wilcoxon(d).pvalue)
    return {"mean_diff": mean_diff, "p_value": p_value, "n": n}


def format_mean_std(stats: Mapping[str, Any], digits: int = 2) -> str:
    """``mean±std`` of a :func:`summarize` dict, e.g. ``9.03±0.42``; ``n/a`` when it has no samples.

    Args:
        stats: dict with ``mean`` and ``std``.
        digits: decimals.
    """
    mean, std = float(stats.get("mean", math.nan)), float(stats.get("std", math.nan))
    if math.isnan(mean):
        return "n/a"
    return f"{mean:.{digits}f}±{std:.{digits}f}"


def _format_rate(stats: Mapping[str, Any]) -> str:
    """A rate as ``90.0% [59.6, 98.2]`` (percent, with the CI); ``n/a`` without samples."""
    mean = float(stats.get("mean", math.nan))
    if math.isnan(mean):
        return "n/a"
    low, high = float(stats.get("ci95_low", math.nan)), float(stats.get("ci95_high", math.nan))
    return f"{100 * mean:.1f}% [{100 * low:.1f}, {100 * high:.1f}]"


def metrics_table_markdown(
    rows_by_method: Mapping[str, Mapping[str, Any] | Sequence[Mapping[str, Any]]],
) -> str:
    """A Markdown table of the paper's metrics per method.

    Args:
        rows_by_method: ``{method: aggregate(rows)}``; a list of per-episode rows is aggregated on the fly.

    Returns:
        The table: N episodes, SR, collision and timeout rates (percent with the 95 % Wilson interval), and NT [s],
        PL [m], TPZ [s] as ``mean±std`` over successful episodes (with their count).
    """
    header = "| Method | N | SR | Collision | Timeout | NT [s] | PL [m] | TPZ [s] |"
    lines = [header, "|" + "---|" * 8]
    for method, agg in rows_by_method.items():
        if not isinstance(agg, Mapping):
            agg = aggregate(list(agg))
        empty: dict[str, Any] = {}
        cells = [
            str(method),
            str(int(agg.get("episodes", 0))),
            _format_rate(agg.get("success", empty)),
            _format_rate(agg.get("collision", empty)),
            _format_rate(agg.get("timeout", empty)),
        ]
        for key in SUCCESS_ONLY:
            s = agg.get(key, empty)
            text = format_mean_std(s)
            cells.append(text if text == "n/a" else f"{text} (n={int(s.get('n', 0))})")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
