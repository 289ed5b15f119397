"""The benchmark harness: same seeds → same episodes, report generation from fixture rows, long-horizon start/goal,
one episode through the harness (trace, figure, MCAP), bad input."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from evaluation.harness import Job, initial_state, make_env, reset_options, run_episode
from evaluation.methods import MethodSpec, resolve_methods
from evaluation.report import paired, report_markdown, results, results_csv, shape_checks
from pipeline.core.errors import ConfigError, InputMissingError
from sim.env import CrowdNavEnv, SimConfig

TINY = SimConfig(max_episode_s=2.0, camera=replace(SimConfig().camera, width_px=64, height_px=48))
ROOT = Path(__file__).resolve().parents[2]


def test_same_seed_list_gives_the_same_episodes_for_two_methods(tmp_path):
    expert, dwa = resolve_methods(["expert", "dwa"], tmp_path)
    assert expert.obs_mode != dwa.obs_mode  # privileged vs rendered envs
    for seed in (20_000, 20_001):
        states = []
        for m in (expert, dwa):
            job = Job(m, TINY, "office_lobby", 0.2, seed, tmp_path)
            env = make_env(job)
            env.reset(seed=seed, options=reset_options(job))
            states.append(initial_state(env))
            env.close()
        assert len(states[0]["peds"]) > 0
        for k in states[0]:
            np.testing.assert_array_equal(states[0][k], states[1][k], err_msg=k)


def test_given_start_and_goal_override_the_sampled_pair():
    env = CrowdNavEnv(config=replace(TINY, scene="office_floor", density=0.0, obs_mode="state"))
    env.reset(seed=1, options={"start": [3.0, 10.0], "goal": [27.0, 10.0]})
    np.testing.assert_allclose(env.robot[:2], [3.0, 10.0])
    np.testing.assert_allclose(env.goal, [27.0, 10.0])
    assert env.shortest_path_m == pytest.approx(24.0, abs=0.3)
    s = env.robot_state(np.array([env.robot[0] + np.cos(env.robot[2]) * 2, env.robot[1] + np.sin(env.robot[2]) * 2]))
    np.testing.assert_allclose(s[:3], [2.0, 0.0, 2.0], atol=1e-5)  # a point 2 m straight ahead
    env.close()


def test_one_episode_writes_trace_figure_and_a_readable_mcap(tmp_path):
    from mcap.reader import make_reader

    (dwa,) = resolve_methods(["dwa"], tmp_path)
    row = run_episode(Job(dwa, TINY, "office_lobby", 0.1, 7, tmp_path, figure=True, mcap=True))
    name = "office_lobby_d0.1_s7_dwa"
    assert row["method"] == "dwa" and row["seed"] == 7 and row["steps"] > 0
    assert {"success", "collision", "timeout", "tpz_s", "path_length_m", "nav_time_s"} <= set(row)
    for f in (tmp_path / "traces" / f"{name}.npz", tmp_path / "figures" / f"{name}.png"):
        assert f.stat().st_mode & 0o777 == 0o644, f  # shareable outputs (mkstemp alone would leave 0600)
    with open(tmp_path / "mcap" / f"{name}.mcap", "rb") as fh:
        reader = make_reader(fh)
        topics = {c.topic for c in reader.get_summary().channels.values()}
        n = sum(1 for _ in reader.iter_messages(topics=["/robot/state"]))
    assert "/robot/state" in topics and n == row["steps"] + 1


def test_methods_that_read_no_poses_skip_the_detector_and_drive_the_same(tmp_path):
    """DWA (depth) and ViNT-style (RGB) read no detected poses: their envs run no pose detector — the observation
    has no poses — and the episode is the one the detector's env gives, row for row; an episode logged to MCAP
    keeps the detector (the log holds the detections)."""
    from rl.baselines import BASELINES

    (dwa,) = resolve_methods(["dwa"], tmp_path)
    assert not dwa.poses and not BASELINES["vint"].poses and BASELINES["drl_vo"].poses
    job = Job(dwa, TINY, "office_lobby", 0.2, 11, tmp_path / "a")
    env = make_env(job)
    obs, _ = env.reset(seed=11, options=reset_options(job))
    assert "poses" not in obs and "pose_mask" not in obs and "depth_left" in obs
    assert set(obs) == set(env.observation_space.spaces)
    env.close()
    assert make_env(replace(job, mcap=True)).unwrapped.cfg.detect_poses
    with_detector = run_episode(replace(job, method=replace(dwa, poses=True), out=tmp_path / "b"))
    assert run_episode(job) == with_detector and with_detector["steps"] > 0


def test_rendered_episode_of_a_privileged_method_gives_the_same_row_and_a_video(tmp_path):
    """The expert keeps its privileged world when the episode is rendered for a video and a log (its driver has
    no BEV panel: the video goes without it), and drives exactly as without rendering."""
    (expert,) = resolve_methods(["expert"], tmp_path)
    plain = run_episode(Job(expert, TINY, "office_lobby", 0.1, 7, tmp_path / "a"))
    shown = run_episode(Job(expert, TINY, "office_lobby", 0.1, 7, tmp_path / "b", video=True, mcap=True))
    assert shown == plain
    assert (tmp_path / "b" / "videos" / "office_lobby_d0.1_s7_expert.mp4").stat().st_size > 0
    assert (tmp_path / "b" / "mcap" / "office_lobby_d0.1_s7_expert.mcap").stat().st_size > 0


def _rows() -> list[dict]:
    """Hand-built episodes: full succeeds on seeds 0..7 of 10, no_i2 on 0..3, dwa on none (collisions)."""
    rows = []
    for seed in range(10):
        for m, ok in (("full", seed < 8), ("no_i2", seed < 4), ("dwa", False)):
            rows.append({"method": m, "scene": "office_lobby", "density": 0.2, "seed": seed, "outcome": "x",
                         "success": int(ok), "collision": int(not ok), "timeout": 0,
                         "nav_time_s": 10.0 + seed if ok else float("nan"),
                         "path_length_m": 6.0 if ok else float("nan"),
                         "tpz_s": 1.0 if m == "full" else 2.0})
    return rows


def test_report_from_fixture_rows():
    rows = _rows()
    res = results(rows)
    assert res["office_lobby@0.2"]["full"]["success"]["mean"] == pytest.approx(0.8)
    assert res["office_lobby@0.2"]["full"]["success"]["n"] == 10
    pr = paired(rows)["office_lobby@0.2"]
    assert pr["no_i2"]["sr"]["a_only"] == 4 and pr["no_i2"]["sr"]["b_only"] == 0
    assert pr["no_i2"]["sr"]["p_value"] == pytest.approx(0.125)  # exact McNemar: 2 * 0.5^4
    assert pr["dwa"]["sr"]["p_value"] == pytest.approx(2 * 0.5 ** 8)
    assert pr["no_i2"]["tpz_s"]["mean_diff"] == pytest.approx(-1.0)
    assert pr["no_i2"]["tpz_s"]["n"] == 10 and pr["no_i2"]["tpz_s_success"]["n"] == 4  # no_i2 finished seeds 0..3
    checks = "\n".join(shape_checks(res))
    assert "SR full 0.80 ≥ no_i2 0.40 — as in the paper" in checks
    assert "TPZ full 1.00 s < w/o I² 2.00 s — as in the paper" in checks
    md = report_markdown(rows, {"full": "iCrowdNav (full)"}, "# test")
    assert "| iCrowdNav (full) | 10 | 80.0%" in md and "## Paired comparisons" in md
    assert "office_lobby@0.2,full,success,10,0.8" in results_csv(res)


def test_unknown_method_and_missing_checkpoint_are_clear_errors(tmp_path):
    with pytest.raises(ConfigError, match="unknown method 'sarl'"):
        resolve_methods(["sarl"], tmp_path)
    with pytest.raises(InputMissingError, match="no finished policy checkpoint"):
        resolve_methods(["full"], tmp_path)
    assert isinstance(resolve_methods(["expert"], tmp_path)[0], MethodSpec)
    expert, = resolve_methods(["expert"], tmp_path, encoder_precision="int8")  # only saved policies take it
    assert expert.encoder_precision is None


def test_auto_encoder_precision_resolves_once_on_this_machine(monkeypatch):
    import pretrain.quantize as quantize
    from evaluation.stage import EvalConfig, encoder_precision_of

    assert encoder_precision_of(EvalConfig()) is None  # none: every student as trained
    monkeypatch.setattr(quantize, "native_bf16", lambda device: True)
    assert encoder_precision_of(EvalConfig(encoder_precision="auto")) == "bf16"
    monkeypatch.setattr(quantize, "native_bf16", lambda device: False)
    assert encoder_precision_of(EvalConfig(encoder_precision="auto")) == "fp32"
    assert encoder_precision_of(EvalConfig(encoder_precision="int8")) == "int8"


@pytest.mark.parametrize("args,match", [
    (["--methods", "[expert, nosuch]"], "unknown method 'nosuch'"),
    (["--methods", "[full]"], "no finished policy checkpoint"),
    (["--scenes", "[]"], "eval.scenes: expected at least one scene"),
    (["--scenarios", "[nosuch]"], "unknown scenario 'nosuch'"),
    (["--scenarios", "[{bad}]"], "config key 'pedestrians[0].waypoints[0]': expected a waypoint outside every"),
    (["--scenarios", "[{nan}]"], "config key 'goal[0]': expected a finite number"),
    (["--goals", "0"], "eval.goals: expected an integer in [1, 10000], got 0"),
    (["--cue_twins", "[nosuch]"], "unknown scenario 'nosuch'"),
    (["--shield_s", "5"], "eval.shield_s: expected none or 0 (off) .. 2.0 s, got 5"),
    (["--shield_s", "nan"], "config key 'shield_s': expected a finite number, got nan"),
    (["--ray_files", "nfs"], "eval.ray_files: expected one of ['shared', 'transfer'], got 'nfs'"),
    (["--method_episodes", "{{dwa: 0}}"], "eval.method_episodes.dwa: expected an integer in [1, 10000], got 0"),
    (["--method_episodes", "{{dwa: 2.5}}"], "method_episodes"),
    (["--method_episodes", "{{nosuch: 1}}"], "eval.method_episodes: expected method names of"),
    (["--sample_tau", "0"], "eval.sample_tau: expected none (argmax) or a temperature in [0.01, 100], got 0.0"),
    (["--encoder_precision", "fp16"], "eval.encoder_precision: expected one of ['auto', 'fp32', 'bf16', 'int8'], got 'fp16'"),
])
def test_eval_cli_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, args, match):
    """Through the CLI entry point in this process (``python -m pipeline`` itself is tested in test_cli)."""
    from pipeline import cli

    data = yaml.safe_load((ROOT / "sim" / "scenarios" / "blind_corner.yaml").read_text())
    bad = {**data, "name": "bad", "pedestrians": [{**data["pedestrians"][0], "waypoints": [[3.0, 6.0]]}]}
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(bad))
    (tmp_path / "nan.yaml").write_text(yaml.safe_dump({**data, "name": "nan", "goal": [float("nan"), 1.5]}))
    args = [a.format(bad=tmp_path / "bad.yaml", nan=tmp_path / "nan.yaml") for a in args]
    rc = cli.main(["eval", "--profile", "smoke", "--data-dir", str(tmp_path), *args])
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("error: ")]
    assert rc == 2 and len(errors) == 1, err
    assert match in errors[0] and "Traceback" not in err
    assert not (tmp_path / "eval").exists()


@pytest.mark.parametrize("damage", ["bytes", "nan"])
def test_damaged_checkpoint_is_one_named_error_before_any_episode(tmp_path, damage):
    """Damaged tensor bytes under an intact header (the manifest's sha256 differs) or NaN weights (saved so: the hash
    matches) stop eval in its input check, naming the file: no episode runs, no MCAP is left half-written."""
    import struct

    import torch

    from evaluation.stage import EvalConfig
    from pipeline.core.errors import CorruptArtifactError
    from pipeline.core.manifest import Manifest, hash_tree
    from pipeline.verbs.eval import run
    from pretrain.checkpoint import save_safetensors

    ck = tmp_path / "checkpoints" / "policy" / "teacher"
    ck.mkdir(parents=True)
    model = torch.nn.Linear(4, 4)
    if damage == "nan":
        with torch.no_grad():
            model.weight[2, 1] = float("nan")
    w = ck / "policy.safetensors"
    save_safetensors(model, w)
    (ck / "policy.json").write_text(json.dumps({"kind": "teacher", "observation_space": {}, "net": {}}))
    (ck / "config.yaml").write_text("seed: 0\n")
    Manifest(stage="train", params={}, config_hash="0" * 64, seed=0, outputs=hash_tree(ck)).write(ck / "manifest.json")
    if damage == "bytes":
        data = bytearray(w.read_bytes())
        data[-4:] = struct.pack("<f", 7.0)  # the last weight: finite, wrong
        w.write_bytes(bytes(data))
    cfg = EvalConfig(data_dir=str(tmp_path), methods=["teacher"], scenes=["office_lobby"], densities=[0.1], goals=1,
                     trials=1, workers=1, figures=0, videos=1, sim=TINY, progress=False)
    want = "expected sha256" if damage == "bytes" else "tensor 'weight' has 1 non-finite"
    with pytest.raises(CorruptArtifactError, match=f"{w}: {want}"):
        run(cfg)
    assert not (tmp_path / "eval").exists()


def test_results_json_is_written_by_a_tiny_run(tmp_path):
    from evaluation.stage import EvalConfig
    from pipeline.verbs.eval import run

    cfg = EvalConfig(data_dir=str(tmp_path), methods=["expert"], scenes=["office_lobby"], densities=[0.1],
                     goals=1, trials=2, routing_scenes=["warehouse_routing"], scenarios=["head_on"],
                     cue_twins=["head_on"], scenario_trials=1, workers=1, figures=0, videos=0, sim=TINY,
                     progress=False)
    cfg.long_horizon = replace(cfg.long_horizon, maps=["office_floor"], runs=1, max_episode_s=2.0)
    run(cfg)
    out = tmp_path / "eval" / "benchmark"
    res = json.loads((out / "results.json").read_text())
    assert res["office_lobby@0.1"]["expert"]["episodes"] == 2
    seeds = json.loads((out / "seeds.json").read_text())
    assert seeds["benchmark"]["seeds"] == [20_000, 20_001] and len(seeds["long_horizon"]["office_floor"]) == 1
    assert (out / "long_horizon" / "office_floor_gvg.png").is_file() and (out / "report.md").is_file()
    rows = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    assert [(r["goal"], r["trial"]) for r in rows] == [(0, 0), (0, 1)]
    routed = [json.loads(line) for line in (out / "routing" / "episodes.jsonl").read_text().splitlines()]
    assert [r["scene"] for r in routed] == ["warehouse_routing"] * 2
    assert "Warehouse routing" in (out / "report.md").read_text()
    (sc,) = [json.loads(line) for line in (out / "scenarios" / "episodes.jsonl").read_text().splitlines()]
    assert sc["scene"] == "head_on" and {"collision_scripted", "min_clearance_scripted_m", "reaction_time_s"} <= set(sc)
    assert "Scenario suite" in (out / "report.md").read_text()
    assert (out / "scenarios" / "figures" / f"sc_head_on_d0_s{sc['seed']}_expert.png").is_file()
    # its no-cue twin: the same trial without the walker's head lead, the two runs' commands compared
    (tw,) = [json.loads(line) for line in (out / "scenarios" / "cue_twins.jsonl").read_text().splitlines()]
    assert (tw["scene"], tw["seed"], tw["method"]) == ("head_on", sc["seed"], "expert")
    assert tw["twin_identical_before_cue"] == 1.0 and tw["min_clearance_scripted_m"] == sc["min_clearance_scripted_m"]
    assert (out / "scenarios" / "nocue" / "traces" / f"scnc_head_on_d0_s{sc['seed']}_expert.npz").is_file()
    assert "The cue alone" in (out / "report.md").read_text()
    assert (out / "scenarios" / "figures" / "cue_twin_head_on.png").is_file()
    assert (out / "scenarios" / "figures" / "cue_timing.png").is_file()  # when each method answered, every trial
    # what each part cost: every episode timed, its steps those of its row
    cost = json.loads((out / "cost.json").read_text())
    assert set(cost["parts"]) == {"benchmark", "routing", "scenarios", "no-cue twins", "long horizon"}
    bench = cost["parts"]["benchmark"]
    assert bench["ran"] == 2 and bench["wall_s"] > 0
    assert bench["methods"]["expert"]["timed"] == 2 and bench["methods"]["expert"]["steps"] == sum(
        r["steps"] for r in rows)
    assert bench["methods"]["expert"]["wall_ms_per_step"] > 0
    assert "## Compute" in (out / "report.md").read_text()
    assert not any("wall" in k or "cpu" in k for k in rows[0])  # timings stay out of the deterministic rows
    # a killed run: the manifest never came and one episode's row is missing; --resume runs only that episode
    (out / "manifest.json").unlink()
    rows = sorted((out / "rows").glob("office_lobby_*.json"))
    assert len(rows) == 2 and len(list((out / "rows").glob("lh_*.json"))) == 1
    assert len(list((out / "rows").glob("route_warehouse_routing_*.json"))) == 2
    kept = rows[0].stat().st_mtime_ns
    rows[1].unlink()
    from pipeline.core.errors import OutputExistsError

    with pytest.raises(OutputExistsError, match="--resume"):
        run(cfg)
    run(replace(cfg, resume=True))
    assert rows[0].stat().st_mtime_ns == kept and rows[1].is_file() and (out / "manifest.json").is_file()
    res2 = json.loads((out / "results.json").read_text())
    resumed = json.loads((out / "cost.json").read_text())["parts"]["benchmark"]
    assert resumed["ran"] == 1 and resumed["methods"]["expert"]["timed"] == 2  # the kept episode's timing stays
    assert res2["office_lobby@0.1"]["expert"]["success"] == res["office_lobby@0.1"]["expert"]["success"]


def test_a_capped_method_runs_a_paired_subset_on_distinct_goals(tmp_path):
    """``method_episodes``: the capped method's episodes are the cell's first in trial-major order — trial 0 of the
    first goals — each the same (seed, scene seed) episode the uncapped methods run, with the first one's figure."""
    from evaluation.stage import EvalConfig, _capped_text, benchmark_jobs

    cfg = EvalConfig(data_dir=str(tmp_path), methods=["expert", "dwa"], scenes=["office_lobby"], densities=[0.1, 0.2],
                     goals=4, trials=3, method_episodes={"dwa": 6}, routing_scenes=[], scenarios=[], figures=1,
                     videos=0, sim=TINY, progress=False)
    cfg.validate()
    specs = resolve_methods(cfg.methods, tmp_path)
    jobs = benchmark_jobs(cfg, specs, tmp_path)
    by = {m: [(j.density, j.seed, j.scene_seed, j.extra["goal"], j.extra["trial"]) for j in jobs if j.method.name == m]
          for m in cfg.methods}
    assert len(by["expert"]) == 2 * 12 and len(by["dwa"]) == 2 * 6
    assert set(by["dwa"]) < set(by["expert"])
    assert sorted((g, t) for d, _, _, g, t in by["dwa"] if d == 0.1) == [(0, 0), (0, 1), (1, 0), (1, 1), (2, 0),
                                                                        (3, 0)]
    assert [j.figure for j in jobs if j.method.name == "dwa"] == [True] + [False] * 5 + [True] + [False] * 5
    assert "`dwa` N = 6" in _capped_text(cfg, specs) and _capped_text(replace(cfg, method_episodes={}), specs) == ""
    assert replace(cfg, method_episodes={"dwa": 50}).episodes_of("dwa") == 12  # a cap above goals x trials: all
    # routing_method_episodes: another cap in the routing cells only (the paper's cells keep method_episodes')
    routed = replace(cfg, routing_scenes=["warehouse_routing"], method_episodes={"dwa": 6, "expert": 12},
                     routing_method_episodes={"dwa": 2, "expert": 5})
    route_jobs = benchmark_jobs(routed, specs, tmp_path, routed.routing_scenes, route=True)
    assert [sum(j.method.name == m for j in route_jobs) for m in ("expert", "dwa")] == [2 * 5, 2 * 2]
    assert benchmark_jobs(routed, specs, tmp_path) == jobs  # the paper's cells unchanged
    assert "`expert` N = 12 (5 in the routing cells), `dwa` N = 6 (2 in the routing cells)" in _capped_text(routed,
                                                                                                          specs)
    # a method without a method_episodes cap runs every routing episode: --method_episodes '{}' uncaps all
    uncapped = replace(routed, method_episodes={})
    assert uncapped.episodes_of("dwa", routing=True) == 12 and _capped_text(uncapped, specs) == ""
    with pytest.raises(ConfigError, match="eval.routing_method_episodes.dwa: expected an integer"):
        replace(routed, routing_method_episodes={"dwa": 0}).validate()


def test_sr_figure_tolerates_intervals_that_miss_the_mean_by_rounding(tmp_path):
    from evaluation.report import plot_sr

    res = {"a@0.1": {"m": {"success": {"mean": 1.0, "ci95_low": 0.7, "ci95_high": 1.0 - 1e-12}},
                     "n": {"success": {"mean": 0.0, "ci95_low": 1e-17, "ci95_high": 0.3}}}}
    plot_sr(res, {}, tmp_path / "sr.png")
    assert (tmp_path / "sr.png").stat().st_size > 0



def test_cue_twin_rows_read_back_from_the_row_cache(tmp_path):
    """Rows re-read on --resume hold null where a trial's cue never came: the twin row is still made (no
    divergence timed), and an older row without ``scripted_peds`` reads every pedestrian of a crowd-free trial."""
    from evaluation.stage import cue_twin_rows

    env = CrowdNavEnv(scenario="head_on", density=0.0, obs_mode="state", info_level="basic")
    env.reset(seed=0)
    for _ in range(5):
        env.step(env.encode_command(0.6, 0.0))
    for d, prefix in ((tmp_path / "sc", "sc_"), (tmp_path / "sc" / "nocue", "scnc_")):
        (d / "traces").mkdir(parents=True)
        env.trace(method="dwa").save_npz(d / "traces" / f"{prefix}head_on_d0_s7_dwa.npz")
    row = {"method": "dwa", "scene": "head_on", "density": 0.0, "seed": 7, "trial": 0, "success": 0.0,
           "collision_scripted": 0.0, "min_clearance_scripted_m": 2.0, "cue_onset_s": None, "cue_lead_s": None}
    (out,) = cue_twin_rows([row], [row], tmp_path / "sc", tmp_path / "sc" / "nocue")
    assert np.isnan(out["cue_divergence_s"]) and out["cue_anticipated"] == 0.0 and out["scripted_peds"] == [0]
    with pytest.raises(ConfigError, match="scripted_peds"):
        cue_twin_rows([{**row, "density": 0.1}], [{**row, "density": 0.1}], tmp_path / "sc", tmp_path / "sc" / "nocue")
