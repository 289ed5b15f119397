"""``icrowdnav timings``: every finished stage's wall from its manifest, in finishing order, sums and span; a damaged
manifest is named, the others still listed."""

from __future__ import annotations

import json

from pipeline.core.manifest import Manifest
from pipeline.verbs.timings import main, stage_timings


def _stage(root, out, stage, finished, wall, command=("icrowdnav",), dirty=False, total=0.0, invocations=1):
    (root / out).mkdir(parents=True)
    Manifest(stage=stage, params={}, config_hash="0" * 64, seed=0, created_utc=finished, git_commit="abcdef0123",
             git_dirty=dirty, duration_s=wall, command=list(command), wall_total_s=total,
             invocations=invocations).write(root / out / "manifest.json")


def test_stages_are_listed_in_finishing_order_with_sum_and_span(tmp_path, capsys):
    _stage(tmp_path, "checkpoints/bev", "pretrain", "2026-11-27T10:40:00Z", 2400.0, dirty=True)
    _stage(tmp_path, "raw/expert", "record", "2026-11-27T10:00:00Z", 120.0)
    # resumed: 3 s to finish what two earlier invocations (10 min in all) had done
    _stage(tmp_path, "eval/benchmark", "eval", "2026-11-27T12:00:00Z", 3.0, ("icrowdnav", "eval", "--resume"),
           total=603.0, invocations=3)
    rows, errors = stage_timings(tmp_path)
    assert not errors and [r["stage"] for r in rows] == ["record", "pretrain", "eval"]
    assert main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "| pretrain | checkpoints/bev | abcdef0+ | 2026-11-27 10:40:00 | 40.0 min | 1 |" in out
    assert "| eval | eval/benchmark | abcdef0 | 2026-11-27 12:00:00 | 10.1 min | 3 (the last 3 s) |" in out
    # 2 + 40 + 10.05 min of walls; from 09:58 (the record's start) to 12:00
    assert "3 stages: sum of walls 52.0 min (0.87 h); from the first start to the last finish 122.0 min (2.03 h)" in out
    assert main([str(tmp_path), "--json"]) == 0
    assert [r["wall_s"] for r in json.loads(capsys.readouterr().out)] == [120.0, 2400.0, 603.0]


def test_a_damaged_manifest_is_named_and_the_rest_still_listed(tmp_path, capsys):
    _stage(tmp_path, "raw/expert", "record", "2026-11-27T10:00:00Z", 120.0)
    (tmp_path / "eval" / "x").mkdir(parents=True)
    (tmp_path / "eval" / "x" / "manifest.json").write_text("{")
    assert main([str(tmp_path)]) == 1
    cap = capsys.readouterr()
    assert "| record |" in cap.out and "eval/x/manifest.json" in cap.err and cap.err.startswith("error: ")
    assert main([str(tmp_path / "nope")]) == 2 and "not a directory" in capsys.readouterr().err
    assert main(["--bad"]) == 2


def test_a_students_dagger_loop_is_shown_and_a_damaged_iteration_named(tmp_path, capsys):
    """After the stages, each student's DAgger loop from its iterations' ``done.json`` (timed ones; a ``done.json``
    of older code without ``timing`` is skipped), in iteration order, then its final cloning when it ran; an
    unreadable ``done.json`` is named, exit 1."""
    from rl.dagger import PHASES, iteration_timing

    _stage(tmp_path, "checkpoints/policy/full", "train", "2026-11-27T10:00:00Z", 600.0)
    phase = dict.fromkeys(PHASES, 0.0) | {"encode": 2.0}
    for k in (0, 1, 10):  # iteration 10 sorts after 1
        it = tmp_path / "checkpoints" / "policy" / "full" / "dagger" / f"iter_{k}"
        it.mkdir(parents=True)
        timing = iteration_timing({"rollout": 30.0, "clone": 10.0}, [{"frames": 200, "phase_s": phase}], 200, False)
        (it / "done.json").write_text(json.dumps({"iteration": k, "frames": 200, "aggregate_frames": 200 * (k + 1),
                                                  "timing": timing}))
    assert main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "DAgger loop of `full` (checkpoints/policy/full/dagger)" in out
    assert out.index("| 1 | 200 (400) |") < out.index("| 10 | 200 (2,200) |")
    assert "600 frames in 2.0 min: the loop 5.0 frames/s, its rollouts 6.7 frames/s" in out
    assert "Final cloning" not in out
    fin = tmp_path / "checkpoints" / "policy" / "full" / "dagger" / "final"  # dagger.final_clone after the loop
    fin.mkdir()
    (fin / "done.json").write_text(json.dumps({"frames": 2200, "clone_samples": 17600, "seed": 3,
                                               "seconds": {"pool": 6.0, "clone": 54.0}}))
    assert main([str(tmp_path)]) == 0
    assert ("Final cloning (dagger/final): a fresh student on 2,200 frames, 17,600 samples in 1.0 min (pool 6 s, "
            "cloning 54 s: 3.07 ms per sample)") in capsys.readouterr().out
    (fin / "done.json").write_text("{")
    assert main([str(tmp_path)]) == 1 and "final/done.json: unreadable" in capsys.readouterr().err
    (fin / "done.json").unlink()
    (tmp_path / "checkpoints" / "policy" / "full" / "dagger" / "iter_1" / "done.json").write_text("{")
    assert main([str(tmp_path)]) == 1
    captured = capsys.readouterr()
    assert "iter_1/done.json: unreadable" in captured.err and "| 10 | 200 (2,200) |" in captured.out
