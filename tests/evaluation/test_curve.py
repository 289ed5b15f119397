"""A learning curve across separate trainings, paired on the acceptance seeds (evaluation.curve)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from evaluation import curve

CELLS = ("office_lobby", "warehouse")


def _checkpoint(root: Path, name: str, episodes: int, successes: dict[str, list[int]]) -> Path:
    """A training's checkpoint as ``train`` leaves it: metrics.json (its budget) and the acceptance rows."""
    d = root / name
    d.mkdir()
    (d / "metrics.json").write_text(json.dumps({"variant": "vint", "budget": {"episodes": episodes, "frames": 0}}))
    rows = [{"scene": scene, "density": 0.1, "seed": 10000 + k, "success": float(s), "tpz_s": 0.0}
            for scene, ss in successes.items() for k, s in enumerate(ss)]
    (d / "acceptance_episodes.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return d


def test_points_are_sorted_by_budget_and_each_is_tested_against_the_previous_and_the_first(tmp_path, capsys):
    # given out of order; 10 seeds per cell; the 300-episode point gains 4 seeds and loses 1 against the 100 one
    c600 = _checkpoint(tmp_path, "c600", 600, {"office_lobby": [1] * 8 + [0] * 2, "warehouse": [1] * 6 + [0] * 4})
    c100 = _checkpoint(tmp_path, "c100", 100, {"office_lobby": [0, 1] + [0] * 8, "warehouse": [1] * 2 + [0] * 8})
    c300 = _checkpoint(tmp_path, "c300", 300, {"office_lobby": [1, 0] + [1] * 3 + [0] * 5,
                                               "warehouse": [1] * 3 + [0] * 7})
    out = tmp_path / "figs" / "curve.png"
    assert curve.main([str(c600), str(c100), str(c300), "--budget", "budget.episodes", "--unit", "episodes",
                       "--out", str(out), "--json", str(tmp_path / "c.json")]) == 0
    rows = json.loads((tmp_path / "c.json").read_text())["rows"]
    assert [r["budget"] for r in rows] == [100, 300, 600]
    assert [r["pooled_sr"] for r in rows] == pytest.approx([0.15, 0.35, 0.70])
    assert rows[1]["table"] == {"office_lobby@0.1": {"n": 10, "sr": 0.4}, "warehouse@0.1": {"n": 10, "sr": 0.3}}
    assert (rows[1]["vs_previous"]["a_only"], rows[1]["vs_previous"]["b_only"]) == (5, 1)
    assert (rows[2]["vs_first"]["a_only"], rows[2]["vs_first"]["b_only"], rows[2]["vs_first"]["n"]) == (11, 0, 20)
    assert rows[2]["vs_first"]["p_value"] < 0.01 and "vs_previous" not in rows[0]
    lo, hi = rows[0]["pooled_wilson95"]
    assert lo < 0.15 < hi
    text = capsys.readouterr().out
    assert "| 300 | 0.40 | 0.30 | 0.35 [" in text and "5 / 1, p = " in text
    assert out.is_file() and out.stat().st_size > 0


@pytest.mark.parametrize("metrics, expected", [
    ({"budget": {"frames": 5}}, "got no key 'episodes'"),
    ({"budget": {"episodes": "many"}}, "expected a finite number, got 'many'"),
    ({"budget": {"episodes": float("nan")}}, "expected a finite number, got nan"),
])
def test_a_missing_or_non_numeric_budget_is_named_and_nothing_is_written(tmp_path, capsys, metrics, expected):
    a = _checkpoint(tmp_path, "a", 100, {"office_lobby": [1, 0]})
    b = _checkpoint(tmp_path, "b", 300, {"office_lobby": [1, 1]})
    (b / "metrics.json").write_text(json.dumps(metrics))
    assert curve.main([str(a), str(b), "--budget", "budget.episodes", "--json", str(tmp_path / "c.json")]) == 2
    err = capsys.readouterr().err
    assert f"{b / 'metrics.json'}: --budget budget.episodes" in err and expected in err
    assert not (tmp_path / "c.json").exists()


def test_checkpoints_accepted_on_different_episodes_are_refused(tmp_path, capsys):
    a = _checkpoint(tmp_path, "a", 100, {"office_lobby": [1, 0, 1]})
    b = _checkpoint(tmp_path, "b", 300, {"office_lobby": [1, 1], "warehouse": [0]})
    assert curve.main([str(a), str(b), "--budget", "budget.episodes", "--out", str(tmp_path / "c.png")]) == 2
    err = capsys.readouterr().err
    assert str(b) in err and "not a paired curve" in err and not (tmp_path / "c.png").exists()
    missing = tmp_path / "nothing"
    missing.mkdir()
    (missing / "metrics.json").write_text(json.dumps({"budget": {"episodes": 1}}))
    assert curve.main([str(a), str(missing), "--budget", "budget.episodes"]) == 2
    assert "acceptance_episodes.jsonl" in capsys.readouterr().err
