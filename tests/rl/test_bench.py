"""rl.bench on tiny sizes: the figures exist, are finite and positive, and the CPU bounds are their combination.

Speed itself is never asserted here (figures, not timed tests: `make bench` prints them)."""

import math
from dataclasses import replace

import pytest

from rl.bench import measure_frame_pool, measure_teacher
from rl.stage import TrainConfig
from rl.vec_env import usable_cores
from sim.env import SimConfig


def test_teacher_benchmark_reports_its_cost_breakdown():
    """The batched vec env against SB3's SubprocVecEnv and one env, and the breakdown of the batched run."""
    cfg = TrainConfig()
    cfg.teacher = replace(cfg.teacher, n_envs=2, subprocess=True,
                          ppo={"n_steps": 16, "batch_size": 32, "n_epochs": 1})
    out = measure_teacher(SimConfig(max_episode_s=4.0), "hallway", 0.1, 0, cfg, 0.2)
    for key in ("teacher_env_steps_per_s", "teacher_env_steps_per_s_sb3_subproc", "teacher_env_steps_per_s_1env",
                "teacher_env_steps_speedup_vs_sb3_subproc", "teacher_collect_s_share", "teacher_collect_ms_per_step",
                "teacher_env_step_ms", "teacher_policy_ms_per_step", "teacher_update_ms_per_step",
                "teacher_update_cache_ms_per_step", "teacher_cpu_bound_steps_per_s", "teacher_loop_bound_steps_per_s"):
        assert math.isfinite(out[key]) and out[key] > 0, key
    assert 0 < out["teacher_collect_s_share"] < 1
    assert out["teacher_update_cache_ms_per_step"] < out["teacher_update_ms_per_step"]
    cores = usable_cores()
    assert out["teacher_cores"] == cores
    env, policy, update = (out["teacher_env_step_ms"], out["teacher_policy_ms_per_step"],
                           out["teacher_update_ms_per_step"])
    assert math.isclose(out["teacher_cpu_bound_steps_per_s"], 1e3 * cores / (env + policy + update), rel_tol=1e-9)
    assert math.isclose(out["teacher_loop_bound_steps_per_s"], 1e3 / (env / cores + policy + update), rel_tol=1e-9)


def test_student_ppo_benchmark_runs_the_rendered_students_ppo():
    """The rendered students' PPO fine-tuning (no_bev without an encoder, full with a random-weight one of the given
    architecture), at tiny sizes: the throughput and the update's share exist and are sane."""
    from pipeline.core.config import load_config
    from pretrain.stage import PretrainConfig
    from rl.bench import measure_student_ppo

    cfg = TrainConfig(map_cost=True)
    cfg.finetune = replace(cfg.finetune, n_envs=2, ppo={"n_steps": 16, "batch_size": 16, "n_epochs": 1})
    sim = SimConfig(max_episode_s=3.0)
    sim = replace(sim, camera=replace(sim.camera, width_px=64, height_px=48))
    out = measure_student_ppo(sim, "hallway", 0.1, 0, cfg, load_config(PretrainConfig, "pretrain", "smoke").encoder,
                              0.2)
    assert set(out) == {f"student_ppo_{k}_{v}" for k in ("env_steps_per_s", "update_share") for v in ("no_bev", "full")}
    for v in ("no_bev", "full"):
        assert math.isfinite(out[f"student_ppo_env_steps_per_s_{v}"]) and out[f"student_ppo_env_steps_per_s_{v}"] > 0
        assert 0 < out[f"student_ppo_update_share_{v}"] < 1


def test_dagger_rollout_benchmark_accounts_for_each_phase_of_a_frame():
    """A DAgger rollout frame of the default student by phase, at tiny sizes (smoke encoder, 64 x 48 cameras, 2 s
    episodes): every phase is there, they add up to the frame, the encoder and the renderer cost something; with
    native bfloat16 the same episodes in bf16 and the ratios."""
    from pipeline.core.config import load_config
    from pipeline.core.device import native_bf16
    from pretrain.stage import PretrainConfig
    from rl.bench import measure_dagger_rollout
    from rl.dagger import PHASES

    cfg = TrainConfig(map_cost=True)
    cfg.sim = replace(cfg.sim, camera=replace(cfg.sim.camera, width_px=64, height_px=48))
    cfg.dagger = replace(cfg.dagger, scenes=["hallway"], densities=[0.1])
    out = measure_dagger_rollout(cfg, load_config(PretrainConfig, "pretrain", "smoke").encoder, 0, episodes=1,
                                 episode_s=2.0)
    assert out["dagger_frames"] >= 2
    phases = [out[f"dagger_ms_per_frame_{p}"] for p in PHASES]
    assert min(phases) >= 0 and out["dagger_ms_per_frame_encode"] > 0 and out["dagger_ms_per_frame_render"] > 0
    assert math.isclose(sum(phases), out["dagger_ms_per_frame"], rel_tol=1e-9)
    assert out["dagger_encode_ms_per_frame"] == out["dagger_ms_per_frame_encode"]
    if native_bf16("cpu"):
        assert math.isclose(out["dagger_bf16_speedup"], out["dagger_ms_per_frame"] / out["dagger_bf16_ms_per_frame"])
        assert out["dagger_bf16_encode_speedup"] > 0
    else:
        assert "dagger_bf16_speedup" not in out


def test_student_device_figures_on_the_cpu(tiny_dataset):
    """The default student's DAgger update and the frozen encoder's streaming step, from a dataset's cameras only."""
    from pretrain.geometry import cameras_from_dataset
    from rl.bench import measure_student_devices

    out = measure_student_devices(cameras_from_dataset(tiny_dataset.root), TrainConfig(), ["cpu"], frames=64,
                                  encoder_steps=3)
    assert set(out) == {"student_clone_ms_per_kframe_cpu", "student_encoder_ms_cpu_b2", "student_encoder_ms_cpu_b16"}
    assert all(math.isfinite(v) and v > 0 for v in out.values())


def test_student_device_figures_name_a_pooled_fusion_that_does_not_fit_before_timing_anything(tiny_dataset):
    from pipeline.core.errors import ConfigError
    from pretrain.geometry import cameras_from_dataset
    from rl.bench import measure_student_devices

    with pytest.raises(ConfigError, match=r"^encoder\.fuse_pool: expected a divisor of both BEV grid sizes"):
        measure_student_devices(cameras_from_dataset(tiny_dataset.root), TrainConfig(), ["cpu"], frames=64,
                                fuse_pool=7)


def test_bench_main_times_the_profiles_encoder(tiny_dataset, monkeypatch, capsys):
    """``python -m rl.bench --profile P`` hands the profile's ``pretrain.encoder`` and ``train`` settings to the
    timing (the `paper` profile's student is timed with the paper's encoder, not the built-in one)."""
    import json

    import rl.bench as bench
    from pipeline.core.config import load_config
    from pretrain.stage import PretrainConfig

    seen = {}

    def fake(cameras, train_cfg, devices, frames, fuse_pool, encoder_cfg):
        seen.update(train=train_cfg, encoder=encoder_cfg, devices=devices)
        return {"student_encoder_ms_cpu_b2": 1.0}

    monkeypatch.setattr(bench, "measure_student_devices", fake)
    assert bench.main(["--dataset", str(tiny_dataset.root), "--profile", "paper", "--devices", "cpu"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert seen["encoder"] == load_config(PretrainConfig, "pretrain", "paper").encoder and seen["devices"] == ["cpu"]
    assert seen["train"].profile == "paper" and out["profile"] == "paper" and out["bev_grid_cells"] == 24000


def test_frame_pool_figures_against_the_concatenating_reference():
    """The pool's size is the frames' bytes; while pooling, the list + concatenate reference allocates about twice
    the pool, the pool itself about once, and the memory-mapped pool a few episodes (allocated memory, traced:
    it does not depend on the machine's load or the process's history; speed is not asserted)."""
    out = measure_frame_pool(frames=1000, bev_shape=(32, 30, 48), episode_frames=100)
    per_frame = 2 * 32 * 30 * 48 * 2 + 7 * 4 + 8 + 105 * 4  # bev + bev_mirror (float16), state, action, logits
    assert out["dagger_pool_gib"] == pytest.approx(1000 * per_frame / 2**30, rel=1e-6)
    for key in ("dagger_pool_concat_s", "dagger_pool_memory_s", "dagger_pool_mapped_s"):
        assert math.isfinite(out[key]) and out[key] > 0, key
    pool = out["dagger_pool_gib"]
    assert out["dagger_pool_concat_peak_gib"] > 1.9 * pool
    episode = pool / 10  # reading one episode holds it about twice (the member's bytes, then the array)
    assert pool < out["dagger_pool_memory_peak_gib"] < pool + 3 * episode
    assert out["dagger_pool_mapped_peak_gib"] < 3 * episode
    assert out["dagger_pool_peak_ratio_concat_vs_memory"] > 1.6


def test_inference_benchmark_times_the_int8_encoder_against_the_float_one():
    """measure_inference: the float student, its recompute reference and the int8 encoder's student, same run (and
    the bfloat16 encoder's, on a CPU with native bfloat16)."""
    from pipeline.core.config import load_config
    from pipeline.core.device import native_bf16
    from pretrain.stage import PretrainConfig
    from rl.bench import measure_inference
    from sim.env import CameraConfig

    sim = replace(SimConfig(max_episode_s=4.0), camera=CameraConfig(width_px=64, height_px=48))
    enc = load_config(PretrainConfig, "pretrain", "smoke").encoder
    out = measure_inference(sim, "hallway", 0.1, 0, enc, 0.2)
    for key in ("policy_inference_lookahead_ms", "policy_inference_lookahead_int8_ms", "bev_stream_step_ms",
                "bev_stream_step_int8_ms"):
        assert math.isfinite(out[key]) and out[key] > 0, key
    assert out["bev_stream_step_int8_speedup"] == out["bev_stream_step_ms"] / out["bev_stream_step_int8_ms"]
    bf16 = ("policy_inference_lookahead_bf16_ms", "bev_stream_step_bf16_ms")
    assert all(k in out for k in bf16) == native_bf16("cpu")
    for key in bf16 if native_bf16("cpu") else ():
        assert math.isfinite(out[key]) and out[key] > 0, key
