"""Paired comparison of two runs' per-episode rows (evaluation.compare)."""

from __future__ import annotations

import gzip
import json

import pytest

from evaluation import compare
from pipeline.core.errors import CorruptArtifactError, InputMissingError


def _rows(successes: list[int], scene: str = "office_lobby") -> list[dict]:
    return [{"scene": scene, "density": 0.1, "seed": 10000 + k, "success": float(s), "tpz_s": 1.0 + k % 3,
             "nav_time_s": 9.0, "path_length_m": 6.0} for k, s in enumerate(successes)]


def _write(path, rows):
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def test_pairs_by_seed_and_counts_the_discordant_pairs(tmp_path, capsys):
    a = _rows([1] * 20 + [1] * 10)  # a succeeds where b fails on the last 10 seeds
    b = _rows([1] * 20 + [0] * 10)
    _write(tmp_path / "a.jsonl", a)
    (tmp_path / "run_b").mkdir()
    _write(tmp_path / "run_b" / "acceptance_episodes.jsonl", list(reversed(b)))  # order does not matter
    assert compare.main([str(tmp_path / "a.jsonl"), str(tmp_path / "run_b"), "--labels", "new,old",
                         "--json", str(tmp_path / "c.json")]) == 0
    res = json.loads((tmp_path / "c.json").read_text())
    sr = res["cells"]["office_lobby@0.1"]["old"]["sr"]
    assert (sr["a_only"], sr["b_only"], sr["n"]) == (10, 0, 30) and sr["p_value"] < 0.01
    assert res["pooled"]["sr"]["sr_diff"] == pytest.approx(1 / 3)
    assert "| office_lobby@0.1 | 30 | 1.00 | 0.67 | 10 / 0 |" in capsys.readouterr().out



def test_tpz_is_tested_over_all_pairs_and_over_the_pairs_both_finished(tmp_path, capsys):
    """A run whose failed episodes end early (little time near people) has lower TPZ over all pairs; over the
    pairs both finished the two are level: the two tests are reported side by side."""
    a = _rows([1] * 30)
    b = [{**r, "tpz_s": 0.5} if k >= 20 else r for k, r in enumerate(_rows([1] * 20 + [0] * 10))]
    _write(tmp_path / "a.jsonl", a)
    _write(tmp_path / "b.jsonl", b)
    assert compare.main([str(tmp_path / "a.jsonl"), str(tmp_path / "b.jsonl"), "--json", str(tmp_path / "c.json")]) == 0
    cell = json.loads((tmp_path / "c.json").read_text())["cells"]["office_lobby@0.1"]["b"]
    assert cell["tpz_s"]["n"] == 30 and cell["tpz_s"]["mean_diff"] > 0 and cell["tpz_s"]["p_value"] < 0.01
    assert cell["tpz_s_success"]["n"] == 20 and cell["tpz_s_success"]["mean_diff"] == 0
    out = capsys.readouterr().out
    assert "TPZ Wilcoxon p, pairs both finished |" in out and "| 0.290 | 0.005 | — |" in out

def test_failure_outcomes_are_tested_pooled_where_both_runs_carry_them(tmp_path, capsys):
    def rows(outcomes: list[str], scene: str) -> list[dict]:
        return [{**r, "collision": float(o == "c"), "timeout": float(o == "t"), "mean_jerk_mps3": 2.0 if o == "c" else 1.0}
                for r, o in zip(_rows([int(o == "s") for o in outcomes], scene), outcomes, strict=True)]

    a = rows(["c"] * 6 + ["s"] * 14, "office_lobby") + rows(["c"] * 4 + ["t"] * 2 + ["s"] * 14, "warehouse")
    b = rows(["s"] * 6 + ["s"] * 14, "office_lobby") + rows(["t"] * 4 + ["t"] * 2 + ["s"] * 14, "warehouse")
    b = [{k: v for k, v in r.items() if k != "mean_jerk_mps3"} if r["scene"] == "warehouse" else r for r in b]
    res = compare.compare(a, b, ("argmax", "sampled"))
    col, tmo = res["outcomes"]["collision"], res["outcomes"]["timeout"]
    assert (col["count_a"], col["count_b"], col["a_only"], col["b_only"], col["n"]) == (10, 0, 10, 0, 40)
    assert col["p_value"] == pytest.approx(2 * 0.5 ** 10)
    assert (tmo["count_a"], tmo["count_b"], tmo["a_only"], tmo["b_only"]) == (2, 6, 0, 4)
    assert "collision_pedestrian" not in res["outcomes"]  # neither run's rows carry it
    assert res["means"] == {}  # one run's warehouse rows lack the jerk: no mean over part of the pairs
    assert "| collision | 10 | 0 | 10 / 0 | 0.002 |" in compare.markdown(res)


def test_a_run_of_several_methods_is_compared_on_the_one_named(tmp_path, capsys):
    """An eval run of two methods holds both methods' rows on the same seeds: without ``--methods`` they would be
    paired as one run (the SR of their mixture), so that is a named error; with it, each side is one method's."""
    run = _write(tmp_path / "episodes.jsonl", [{**r, "method": "full"} for r in _rows([1] * 20)]
                 + [{**r, "method": "dwa"} for r in _rows([0] * 5 + [1] * 15)])
    alone = _write(tmp_path / "no_bev.jsonl", [{**r, "method": "no_bev"} for r in _rows([1] * 10 + [0] * 10)])
    assert compare.main([str(alone), str(run)]) == 2
    err = capsys.readouterr().err
    assert "2 methods ['dwa', 'full']" in err and "--methods" in err
    assert compare.main([str(alone), str(run), "--methods", "no_bev,full", "--labels", "no_bev,full"]) == 0
    assert "| office_lobby@0.1 | 20 | 0.50 | 1.00 | 0 / 10 |" in capsys.readouterr().out
    assert compare.main([str(run), str(run), "--methods", "dwa,full", "--labels", "dwa,full"]) == 0
    assert "| office_lobby@0.1 | 20 | 0.75 | 1.00 | 0 / 5 |" in capsys.readouterr().out
    assert compare.main([str(alone), str(run), "--methods", "no_bev,vint"]) == 2
    assert "has no rows of method 'vint' (it holds ['dwa', 'full'])" in capsys.readouterr().err
    assert compare.main([str(alone), str(run), "--methods", "full"]) == 2
    assert "two comma-separated method names" in capsys.readouterr().err


def test_bad_inputs_are_named_errors(tmp_path, capsys):
    with pytest.raises(InputMissingError, match="no per-episode rows"):
        compare.read_rows(tmp_path)
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"scene": "x"}\n')
    with pytest.raises(CorruptArtifactError, match="lacks"):
        compare.read_rows(bad)
    other = _write(tmp_path / "other.jsonl", _rows([1, 0], scene="warehouse"))
    good = _write(tmp_path / "good.jsonl", _rows([1, 0]))
    assert compare.main([str(good), str(other)]) == 2
    assert "share no" in capsys.readouterr().err
    assert compare.main([str(good), str(good), "--labels", "same,same"]) == 2


def test_archived_gzipped_rows_compare_as_the_plain_file(tmp_path, capsys):
    """docs/runs/ keeps the rows of the runs docs/results.md cites gzipped, so a later run on another machine can be
    paired with them: a ``.jsonl.gz`` reads as its plain file; a damaged one is a named error."""
    a = _write(tmp_path / "a.jsonl", _rows([1] * 20 + [1] * 10))
    b = _write(tmp_path / "b.jsonl", _rows([1] * 20 + [0] * 10))
    b_gz = tmp_path / "b.jsonl.gz"
    b_gz.write_bytes(gzip.compress(b.read_bytes()))
    assert compare.read_rows(b_gz) == compare.read_rows(b)
    assert compare.main([str(a), str(b_gz), "--labels", "new,archived"]) == 0
    assert "| office_lobby@0.1 | 30 | 1.00 | 0.67 | 10 / 0 |" in capsys.readouterr().out
    (tmp_path / "torn.jsonl.gz").write_bytes(b_gz.read_bytes()[:-20])
    with pytest.raises(CorruptArtifactError, match="torn.jsonl.gz: not a gzip file of JSON rows"):
        compare.read_rows(tmp_path / "torn.jsonl.gz")
    assert compare.main([str(a), str(tmp_path / "torn.jsonl.gz")]) == 2
    assert "torn.jsonl.gz" in capsys.readouterr().err


def test_an_unfinished_eval_run_compares_on_its_finished_benchmark_episodes(tmp_path, caplog):
    """A run killed (or still running) before its episodes.jsonl: its rows/ cache, without the scenario rows, pairs
    with a finished run on the episodes both have; a run with no finished episode is a named error."""
    run = tmp_path / "eval" / "partial"
    (run / "rows").mkdir(parents=True)
    for r in _rows([1] * 5 + [0] * 5):  # benchmark rows carry their goal and trial
        (run / "rows" / f"{r['scene']}_d0.1_s{r['seed']}_full.json").write_text(json.dumps({**r, "goal": 0, "trial": 0}))
    (run / "rows" / "route_warehouse_routing_d0.1_s10000_full.json").write_text(
        json.dumps({**_rows([1], scene="warehouse_routing")[0], "goal": 0, "trial": 0}))
    (run / "rows" / "sc_blind_corner_d0.1_s10000_full.json").write_text(
        json.dumps({**_rows([1], scene="blind_corner")[0], "trial": 0}))
    rows = compare.read_rows(run)
    assert sorted(r["seed"] for r in rows) == list(range(10000, 10010))
    assert "unfinished eval run (no episodes.jsonl): comparing its 10 finished benchmark episodes" in caplog.text
    _write(tmp_path / "done.jsonl", _rows([1] * 10 + [0] * 20))
    res = compare.compare(compare.read_rows(tmp_path / "done.jsonl"), rows, ("done", "partial"))
    assert res["cells"]["office_lobby@0.1"]["partial"]["sr"]["n"] == 10
    assert res["sr"] == {"done": {"office_lobby@0.1": 1.0}, "partial": {"office_lobby@0.1": 0.5}}  # over the pairs
    empty = tmp_path / "eval" / "empty"
    (empty / "rows").mkdir(parents=True)
    with pytest.raises(InputMissingError, match="no finished benchmark episode yet"):
        compare.read_rows(empty)


def test_replicates_are_matched_each_on_their_own_and_pooled(tmp_path, capsys):
    """``--also A B``: a second training's pair of runs on the same seeds is matched within itself (never with the
    first pair's episodes of the same seed), its cells are tagged, and the pooled test sums both replicates'
    discordant pairs."""
    r1a, r1b = _write(tmp_path / "1a.jsonl", _rows([1] * 6 + [0] * 14)), _write(tmp_path / "1b.jsonl", _rows([0] * 20))
    r2a, r2b = _write(tmp_path / "2a.jsonl", _rows([0] * 20)), _write(tmp_path / "2b.jsonl", _rows([0] * 16 + [1] * 4))
    assert compare.main([str(r1a), str(r1b), "--also", str(r2a), str(r2b), "--json", str(tmp_path / "c.json")]) == 0
    res = json.loads((tmp_path / "c.json").read_text())
    assert set(res["cells"]) == {"office_lobby [1]@0.1", "office_lobby [2]@0.1"}
    one, two = (res["cells"][f"office_lobby [{k}]@0.1"]["b"]["sr"] for k in (1, 2))
    assert (one["a_only"], one["b_only"], two["a_only"], two["b_only"]) == (6, 0, 0, 4)
    pooled = res["pooled"]["sr"]
    assert (pooled["n"], pooled["a_only"], pooled["b_only"]) == (40, 6, 4)
    assert pooled["sr_diff"] == pytest.approx(2 / 40)
    assert "| office_lobby [2]@0.1 | 20 | 0.00 | 0.20 | 0 / 4 |" in capsys.readouterr().out
    _write(tmp_path / "other.jsonl", _rows([1] * 20, scene="warehouse"))
    assert compare.main([str(r1a), str(r1b), "--also", str(r2a), str(tmp_path / "other.jsonl")]) == 2
    assert "--also" in capsys.readouterr().err


def test_cells_are_also_pooled_per_density_and_per_scene(tmp_path, capsys):
    """Besides all cells at once, the pairs are pooled per density and per scene (a replicate's cells joining their
    scene); a grouping with one group only (every row at one density), or with one cell in each group, is left out."""
    def rows(successes: list[int], scene: str, density: float) -> list[dict]:
        return [{**r, "density": density} for r in _rows(successes, scene)]

    a = rows([1] * 10, "office_lobby", 0.1) + rows([1] * 10, "warehouse", 0.1) + rows([0] * 10, "warehouse", 0.2)
    b = rows([1] * 4 + [0] * 6, "office_lobby", 0.1) + rows([1] * 8 + [0] * 2, "warehouse", 0.1) + \
        rows([0] * 7 + [1] * 3, "warehouse", 0.2)
    res = compare.compare(a, b, ("full", "no_bev"))
    by_d, by_s = res["pooled_by"]["density"], res["pooled_by"]["scene"]
    assert set(by_d) == {"0.1", "0.2"} and set(by_s) == {"office_lobby", "warehouse"}
    assert (by_d["0.1"]["n_cells"], by_d["0.1"]["sr"]["n"], by_d["0.1"]["sr"]["a_only"], by_d["0.1"]["sr"]["b_only"]) \
        == (2, 20, 8, 0)
    assert (by_d["0.2"]["sr"]["a_only"], by_d["0.2"]["sr"]["b_only"]) == (0, 3)
    assert (by_s["warehouse"]["n_cells"], by_s["warehouse"]["sr"]["a_only"], by_s["warehouse"]["sr"]["b_only"]) \
        == (2, 2, 3)
    assert by_d["0.1"]["sr"]["p_value"] == pytest.approx(2 * 0.5 ** 8)
    text = compare.markdown(res)
    assert "| pooled by density |" in text and "| 0.1 | 2 | 20 | +0.400 | 8 / 0 | 0.008 |" in text
    # replicates: the tagged cells of one scene pool together; one density only -> no density grouping
    one = compare.compare(compare.replicate(rows([1] * 10, "warehouse", 0.1), 1)
                          + compare.replicate(rows([1] * 10, "warehouse", 0.1), 2),
                          compare.replicate(rows([0] * 10, "warehouse", 0.1), 1)
                          + compare.replicate(rows([1] * 10, "warehouse", 0.1), 2), ("full", "no_bev"))
    assert "density" not in one["pooled_by"] and "scene" not in one["pooled_by"]
    per_cell = compare.compare(rows([1] * 10, "warehouse", 0.1) + rows([1] * 10, "office_lobby", 0.1),
                               rows([0] * 10, "warehouse", 0.1) + rows([1] * 10, "office_lobby", 0.1), ("full", "no_bev"))
    assert per_cell["pooled_by"] == {}  # scenes of one cell each: the per-cell table already says it


def test_two_timed_eval_runs_are_compared_on_what_their_paired_episodes_cost(tmp_path, capsys):
    from evaluation.cost import write_cost

    for run, ms in (("fp32", 60.0), ("int8", 40.0)):
        d = tmp_path / run
        d.mkdir()
        rows = [{**r, "method": "full"} for r in _rows([1] * 6)]
        _write(d / "episodes.jsonl", rows)
        for k, r in enumerate(rows):
            steps = 50 + 10 * k  # episodes of different lengths: the per-step cost divides them out
            write_cost(d, f"office_lobby_d0.1_s{r['seed']}_full", method="full", steps=steps, wall_s=ms * steps / 1e3,
                       cpu_s=0.9 * ms * steps / 1e3, load_s=0.0, rendered=k == 5)  # the rendered one left out
    assert compare.main([str(tmp_path / "fp32"), str(tmp_path / "int8"), "--labels", "fp32,int8",
                         "--json", str(tmp_path / "c.json")]) == 0
    cost = json.loads((tmp_path / "c.json").read_text())["cost"]
    assert cost["pairs"] == 5 and cost["wall_ms_per_step"] == pytest.approx([60.0, 40.0])
    assert cost["wall_ratio"] == pytest.approx(1.5) and cost["median_episode_ratio"] == pytest.approx(1.5)
    assert cost["cpu_ratio"] == pytest.approx(1.5)
    assert "fp32 60.0 ms, int8 40.0 ms, fp32 / int8 = 1.50" in capsys.readouterr().out
    # an untimed run (rows files only): no cost comparison, the rest as before
    assert compare.main([str(tmp_path / "fp32" / "episodes.jsonl"), str(tmp_path / "int8"), "--json",
                         str(tmp_path / "d.json")]) == 0
    assert "cost" not in json.loads((tmp_path / "d.json").read_text())
