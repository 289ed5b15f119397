"""Tests of sim.trace (EpisodeTrace) and sim.metrics on hand-built traces with known answers."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy import stats as sps

from sim.metrics import (
    METRIC_KEYS,
    SUCCESS_ONLY,
    TTC_HORIZON_S,
    aggregate,
    episode_metrics,
    format_mean_std,
    metrics_table_markdown,
    paired_test,
    summarize,
    time_to_collision,
    wilson_interval,
)
from sim.trace import EpisodeTrace


def make_trace(
    robot_xy: np.ndarray,
    dt: float = 0.5,
    yaw: np.ndarray | None = None,
    ped_xy: np.ndarray | None = None,
    ped_vel: np.ndarray | None = None,
    ped_radius: np.ndarray | None = None,
    goal_xy: tuple[float, float] | None = None,
    outcome: str = "success",
    robot_radius: float = 0.3,
    shortest_path_m: float = math.nan,
) -> EpisodeTrace:
    """A trace from robot positions ``(T+1) x 2`` and optional pedestrians ``(T+1) x N x 2``."""
    robot_xy = np.asarray(robot_xy, dtype=np.float64)
    t1 = len(robot_xy)
    if yaw is None:
        d = np.diff(robot_xy, axis=0)
        yaw = np.arctan2(d[:, 1], d[:, 0]) if len(d) else np.zeros(0)
        yaw = np.concatenate([yaw[:1] if len(yaw) else [0.0], yaw])
    if ped_xy is None:
        ped_xy = np.zeros((t1, 0, 2))
    ped_xy = np.asarray(ped_xy, dtype=np.float64)
    n = ped_xy.shape[1]
    if ped_vel is None:
        ped_vel = np.zeros_like(ped_xy)
    if ped_radius is None:
        ped_radius = np.full(n, 0.25)
    return EpisodeTrace(
        dt_s=dt,
        robot_radius_m=robot_radius,
        goal_radius_m=0.3,
        robot_pose=np.column_stack([robot_xy, yaw]),
        robot_cmd=np.zeros((t1 - 1, 2)),
        goal_xy=np.asarray(goal_xy if goal_xy is not None else robot_xy[-1], dtype=np.float64),
        start_xy=robot_xy[0].copy(),
        ped_xy=ped_xy,
        ped_vel=ped_vel,
        ped_radius=ped_radius,
        ped_yaw=np.zeros((t1, n)),
        ped_head_yaw=np.zeros((t1, n)),
        static_clearance_m=np.full(t1, 2.0),
        outcome=outcome,
        shortest_path_m=shortest_path_m,
        scene="corridor",
        density=0.2,
        seed=7,
        method="test",
    )


def straight(length_m: float = 5.0, speed: float = 1.0, dt: float = 0.5) -> np.ndarray:
    """Robot positions along +x from the origin at constant speed."""
    n = int(round(length_m / (speed * dt)))
    return np.column_stack([np.arange(n + 1) * speed * dt, np.zeros(n + 1)])


# ------------------------------------------------------------------------------------------------- trace


def test_trace_validate_and_npz_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    tr = make_trace(straight(), ped_xy=rng.normal(size=(11, 3, 2)), shortest_path_m=5.0)
    assert tr.n_steps == 10 and tr.n_peds == 3
    out = tr.save_npz(tmp_path / "sub" / "ep.npz")
    assert out.exists() and [p.name for p in out.parent.iterdir()] == ["ep.npz"]
    back = EpisodeTrace.load_npz(out)
    for name in EpisodeTrace._ARRAYS:
        np.testing.assert_array_equal(getattr(back, name), getattr(tr, name))
    assert (back.outcome, back.scene, back.method, back.seed) == ("success", "corridor", "test", 7)
    assert back.dt_s == 0.5 and back.density == 0.2 and back.shortest_path_m == 5.0
    nan_sp = make_trace(straight())
    assert math.isnan(EpisodeTrace.load_npz(nan_sp.save_npz(tmp_path / "nan.npz")).shortest_path_m)


def test_trace_empty_crowd_is_normalised() -> None:
    tr = make_trace(straight(), ped_xy=np.zeros((11, 0, 2)), ped_radius=np.zeros(0))
    tr.ped_yaw = np.zeros(0)
    tr.__post_init__()
    assert tr.validate().ped_xy.shape == (11, 0, 2) and tr.ped_yaw.shape == (11, 0)


def test_trace_load_errors_name_the_file(tmp_path: Path) -> None:
    missing = tmp_path / "missing.npz"
    with pytest.raises(ValueError, match="missing.npz"):
        EpisodeTrace.load_npz(missing)
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(b"PK\x03\x04 this is not a zip")
    with pytest.raises(ValueError, match="corrupt.npz"):
        EpisodeTrace.load_npz(corrupt)
    other = tmp_path / "other.npz"
    np.savez_compressed(other, a=np.zeros(3))
    with pytest.raises(ValueError, match=r"other.npz.*lacks fields"):
        EpisodeTrace.load_npz(other)


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("robot_cmd", np.zeros((3, 2)), "robot_cmd must have shape"),
        ("ped_xy", np.zeros((11, 2, 2)), "ped_xy must have shape"),
        ("static_clearance_m", np.zeros(10), "static_clearance_m must have shape"),
        ("outcome", "crashed", "outcome must be one of"),
        ("dt_s", 0.0, "dt_s"),
        ("robot_pose", np.full((11, 3), np.nan), "non-finite"),
    ],
)
def test_trace_validate_errors(field: str, value: object, match: str) -> None:
    tr = make_trace(straight(), ped_xy=np.zeros((11, 1, 2)))
    setattr(tr, field, value)
    with pytest.raises(ValueError, match=match):
        tr.validate()


# ----------------------------------------------------------------------------------------------- metrics


def test_straight_path_basic_metrics() -> None:
    m = episode_metrics(make_trace(straight(5.0, 1.0, 0.5), shortest_path_m=5.0))
    assert list(m) == list(METRIC_KEYS)
    assert m["path_length_m"] == pytest.approx(5.0)
    assert m["nav_time_s"] == pytest.approx(5.0)
    assert m["mean_speed_mps"] == pytest.approx(1.0)
    assert m["mean_jerk_mps3"] == pytest.approx(0.0, abs=1e-9)
    assert m["path_irregularity_rad"] == pytest.approx(0.0)
    assert m["spl"] == pytest.approx(1.0)
    assert m["final_goal_distance_m"] == pytest.approx(0.0)
    assert (m["success"], m["collision"], m["timeout"]) == (1.0, 0.0, 0.0)
    assert m["tpz_s"] == 0.0 and math.isnan(m["min_ped_clearance_m"])
    assert m["personal_space_compliance"] == 1.0 and m["min_ttc_s"] == TTC_HORIZON_S
    assert m["min_static_clearance_m"] == 2.0


def test_outcome_flags_and_spl() -> None:
    xy = straight()
    m = episode_metrics(make_trace(xy, outcome="collision_pedestrian", shortest_path_m=4.0))
    assert (m["success"], m["collision"], m["collision_pedestrian"], m["collision_obstacle"]) == (0, 1, 1, 0)
    assert m["spl"] == 0.0
    m = episode_metrics(make_trace(xy, shortest_path_m=4.0))
    assert m["spl"] == pytest.approx(4.0 / 5.0)
    assert math.isnan(episode_metrics(make_trace(xy))["spl"])
    assert episode_metrics(make_trace(xy, outcome="timeout"))["timeout"] == 1.0


def test_tpz_counts_exact_steps_and_ignores_reset_state() -> None:
    dt = 0.1
    xy = straight(5.0, 1.0, dt)  # x = 0.0, 0.1, ..., 5.0
    t1 = len(xy)
    # static pedestrian at lateral offset 0.9: in zone when |dx| < sqrt((0.8 + 0.3)^2 - 0.9^2) = 0.632
    # -> x in {1.9, ..., 3.1}: 13 steps
    ped = np.broadcast_to(np.array([[2.5, 0.9]]), (t1, 1, 2)).copy()
    m = episode_metrics(make_trace(xy, dt=dt, ped_xy=ped))
    assert m["tpz_s"] == pytest.approx(13 * dt)
    assert m["min_ped_clearance_m"] == pytest.approx(0.9 - 0.3 - 0.25)
    # a pedestrian right next to the reset state only: the reset state is not a step
    ped0 = np.broadcast_to(np.array([[-0.5, 0.0]]), (t1, 1, 2)).copy()
    m0 = episode_metrics(make_trace(xy, dt=dt, ped_xy=ped0))
    assert m0["tpz_s"] == pytest.approx(5 * dt)  # x in {0.1, ..., 0.5}: 0.5 + x - 0.3 < 0.8 <=> x < 0.6


def test_head_on_ttc_matches_analytic_value() -> None:
    dt, t_steps = 0.5, 4
    t = np.arange(t_steps + 1)
    robot = np.column_stack([t * dt * 1.0, np.zeros_like(t, dtype=float)])
    ped = np.stack([10.0 - t * dt * 1.0, np.zeros(t_steps + 1)], axis=-1)[:, None, :]
    vel = np.broadcast_to(np.array([[-1.0, 0.0]]), (t_steps + 1, 1, 2)).copy()
    m = episode_metrics(
        make_trace(robot, dt=dt, ped_xy=ped, ped_vel=vel, ped_radius=np.array([0.3]), goal_xy=(20.0, 0.0))
    )
    # the last state with a motion (t = 3): gap 8.5 - 1.5 = 7 m, closing at 2 m/s, collision at 0.6 m
    assert m["min_ttc_s"] == pytest.approx((7.0 - 0.6) / 2.0)


def test_time_to_collision_cases() -> None:
    p = np.array([[5.0, 0.0], [5.0, 0.0], [0.3, 0.0], [5.0, 2.0], [50.0, 0.0]])
    v = np.array([[-1.0, 0.0], [1.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [-1.0, 0.0]])
    ttc = time_to_collision(p, v, 0.5)
    np.testing.assert_allclose(ttc, [4.5, TTC_HORIZON_S, 0.0, TTC_HORIZON_S, TTC_HORIZON_S])
    # grazing: offset exactly the collision distance -> tangent at t = 5
    assert time_to_collision(np.array([5.0, 0.5]), np.array([-1.0, 0.0]), 0.5) == pytest.approx(5.0)


def test_jerk_of_cubic_path() -> None:
    dt = 0.1
    t = np.arange(21) * dt
    xy = np.column_stack([t**3, np.zeros_like(t)])  # d3x/dt3 = 6
    assert episode_metrics(make_trace(xy, dt=dt))["mean_jerk_mps3"] == pytest.approx(6.0)
    assert episode_metrics(make_trace(xy[:3], dt=dt))["mean_jerk_mps3"] == 0.0


def test_path_irregularity_facing_sideways() -> None:
    xy = straight()
    yaw = np.full(len(xy), math.pi / 2)
    m = episode_metrics(make_trace(xy, yaw=yaw, goal_xy=(10.0, 0.0)))
    assert m["path_irregularity_rad"] == pytest.approx(math.pi / 2)


def test_zero_step_episode() -> None:
    m = episode_metrics(make_trace(np.zeros((1, 2)), outcome="timeout"))
    assert m["nav_time_s"] == 0.0 and m["path_length_m"] == 0.0
    assert math.isnan(m["mean_speed_mps"]) and math.isnan(m["min_ttc_s"])


def _reference_metrics(tr: EpisodeTrace, pz: float, ps: float) -> dict[str, float]:
    """Plain-loop versions of the vectorised pedestrian metrics."""
    xy, r = tr.robot_pose[:, :2], tr.robot_radius_m
    in_zone, compliant, clear, ttc = 0, 0, math.inf, TTC_HORIZON_S
    for t in range(tr.n_steps + 1):
        dists = [math.dist(xy[t], tr.ped_xy[t, j]) for j in range(tr.n_peds)]
        clear = min(clear, *(d - r - tr.ped_radius[j] for j, d in enumerate(dists)))
        if t >= 1:
            in_zone += any(d - r < pz for d in dists)
            compliant += all(d - r >= ps for d in dists)
        if t < tr.n_steps:
            vr = (xy[t + 1] - xy[t]) / tr.dt_s
            for j in range(tr.n_peds):
                rad = r + tr.ped_radius[j]
                p = tr.ped_xy[t, j] - xy[t]
                w = tr.ped_vel[t, j] - vr
                if np.hypot(*p) <= rad:
                    ttc = 0.0
                    continue
                # brute-force: first sampled time at which the gap closes (1 ms resolution)
                s = np.arange(0.0, TTC_HORIZON_S, 1e-3)
                hit = np.nonzero(np.hypot(p[0] + w[0] * s, p[1] + w[1] * s) <= rad)[0]
                if len(hit):
                    ttc = min(ttc, float(s[hit[0]]))
    return {
        "tpz_s": in_zone * tr.dt_s,
        "personal_space_compliance": compliant / tr.n_steps,
        "min_ped_clearance_m": clear,
        "min_ttc_s": ttc,
    }


def test_vectorised_metrics_match_loop_reference() -> None:
    rng = np.random.default_rng(3)
    dt, t_steps, n = 0.25, 30, 6
    robot = np.cumsum(np.vstack([[0.0, 0.0], rng.normal(0.2, 0.08, size=(t_steps, 2))]), axis=0)
    vel = rng.normal(0.0, 0.6, size=(t_steps + 1, n, 2))
    ped = rng.uniform(-1.0, 6.0, size=(1, n, 2)) + np.cumsum(vel * dt, axis=0)
    tr = make_trace(robot, dt=dt, ped_xy=ped, ped_vel=vel, ped_radius=rng.uniform(0.2, 0.3, n))
    got = episode_metrics(tr, private_zone_m=0.8, personal_space_m=1.2)
    ref = _reference_metrics(tr, 0.8, 1.2)
    assert got["tpz_s"] == pytest.approx(ref["tpz_s"])
    assert got["personal_space_compliance"] == pytest.approx(ref["personal_space_compliance"])
    assert got["min_ped_clearance_m"] == pytest.approx(ref["min_ped_clearance_m"])
    assert got["min_ttc_s"] == pytest.approx(ref["min_ttc_s"], abs=2e-3)
    assert 0.0 < got["tpz_s"] and got["min_ttc_s"] < TTC_HORIZON_S  # the random case exercises both


# --------------------------------------------------------------------------------------------- aggregate


def test_wilson_interval_known_value() -> None:
    low, high = wilson_interval(9, 10)
    assert low == pytest.approx(0.596, abs=5e-4) and high == pytest.approx(0.982, abs=5e-4)
    assert all(math.isnan(v) for v in wilson_interval(0, 0))
    low0, high0 = wilson_interval(0, 10)
    assert low0 == 0.0 and 0.0 < high0 < 0.35


def test_aggregate_rates_and_success_only() -> None:
    rows = [
        {"success": 1.0, "collision": 0.0, "nav_time_s": 10.0, "tpz_s": 1.0, "min_ped_clearance_m": 0.5}
    ] * 9
    rows = [dict(r) for r in rows]
    rows[0]["nav_time_s"] = 12.0
    rows.append(
        {"success": 0.0, "collision": 1.0, "nav_time_s": 100.0, "tpz_s": 50.0, "min_ped_clearance_m": -0.1}
    )
    rows[1]["min_ped_clearance_m"] = math.nan
    agg = aggregate(rows)
    assert agg["episodes"] == 10
    assert agg["success"]["mean"] == pytest.approx(0.9) and agg["success"]["n"] == 10
    assert (agg["success"]["ci95_low"], agg["success"]["ci95_high"]) == pytest.approx(
        (0.596, 0.982), abs=5e-4
    )
    assert agg["collision"]["mean"] == pytest.approx(0.1)
    nt = np.array([12.0] + [10.0] * 8)
    assert agg["nav_time_s"]["n"] == 9 and agg["nav_time_s"]["mean"] == pytest.approx(nt.mean())
    assert agg["nav_time_s"]["std"] == pytest.approx(nt.std(ddof=1))
    lo, hi = sps.t.interval(0.95, df=8, loc=nt.mean(), scale=nt.std(ddof=1) / 3.0)
    assert (agg["nav_time_s"]["ci95_low"], agg["nav_time_s"]["ci95_high"]) == pytest.approx((lo, hi))
    assert agg["tpz_s"]["mean"] == pytest.approx(1.0)
    assert agg["min_ped_clearance_m"]["n"] == 9  # nan skipped, failures kept (not success-only)
    assert agg["min_ped_clearance_m"]["mean"] == pytest.approx((0.5 * 8 - 0.1) / 9)


def test_aggregate_without_successes_gives_nan_with_n_zero() -> None:
    rows = [{"success": 0.0, "nav_time_s": 30.0, "path_length_m": 3.0, "tpz_s": 2.0, "method": "x"}] * 4
    agg = aggregate(rows)
    for key in SUCCESS_ONLY:
        assert agg[key]["n"] == 0 and math.isnan(agg[key]["mean"]) and math.isnan(agg[key]["ci95_low"])
    assert "method" not in agg
    assert agg["success"]["mean"] == 0.0 and agg["success"]["ci95_low"] == 0.0
    assert aggregate([]) == {"episodes": 0}


def test_summarize_single_value() -> None:
    s = summarize([3.0])
    assert s["mean"] == 3.0 and s["std"] == 0.0 and s["n"] == 1 and math.isnan(s["ci95_low"])


def test_aggregate_of_real_episode_rows() -> None:
    rows = [
        episode_metrics(make_trace(straight(5.0, 1.0, dt), dt=dt, shortest_path_m=5.0)) for dt in (0.5, 0.25)
    ]
    agg = aggregate(rows)
    assert agg["path_length_m"]["mean"] == pytest.approx(5.0) and agg["path_length_m"]["n"] == 2
    assert set(METRIC_KEYS) <= set(agg)


def test_paired_test() -> None:
    rng = np.random.default_rng(1)
    a = rng.normal(10.0, 1.0, 12)
    b = a - 0.5 + rng.normal(0.0, 0.1, 12)
    res = paired_test(list(a), list(b))
    assert res["n"] == 12 and res["mean_diff"] == pytest.approx(float(np.mean(a - b)))
    assert res["p_value"] == pytest.approx(sps.wilcoxon(a - b).pvalue) and res["p_value"] < 0.01
    assert math.isnan(paired_test([1, 2, 3, 4], [0, 0, 0, 0])["p_value"])
    assert math.isnan(paired_test([1.0] * 6, [1.0] * 6)["p_value"])
    with_nan = paired_test([1, 2, math.nan, 4, 5, 6, 7], [0, 0, 0, 0, 0, 0, 0])
    assert with_nan["n"] == 6 and not math.isnan(with_nan["p_value"])
    with pytest.raises(ValueError, match="equally long"):
        paired_test([1.0, 2.0], [1.0])


def test_formatting_and_markdown_table() -> None:
    assert format_mean_std({"mean": 9.031, "std": 0.4249}) == "9.03±0.42"
    assert format_mean_std({"mean": math.nan, "std": math.nan, "n": 0}) == "n/a"
    rows_ok = [{"success": 1.0, "collision": 0.0, "timeout": 0.0, "nav_time_s": 9.0, "path_length_m": 8.0,
                "tpz_s": 0.5}] * 9  # fmt: skip
    rows_bad = [{"success": 0.0, "collision": 0.0, "timeout": 1.0, "nav_time_s": 60.0, "path_length_m": 3.0,
                 "tpz_s": 5.0}]  # fmt: skip
    table = metrics_table_markdown({"ours": aggregate(rows_ok + rows_bad), "baseline": rows_bad})
    lines = table.strip().splitlines()
    assert lines[0].startswith("| Method | N | SR |") and len(lines) == 4
    assert lines[2].startswith("| ours | 10 | 90.0% [59.6, 98.2] |") and "9.00±0.00 (n=9)" in lines[2]
    assert lines[3].startswith("| baseline | 1 | 0.0% ") and lines[3].count("n/a") == 3
