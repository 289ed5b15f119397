"""What the benchmark's episodes cost: the per-episode files, their sums per method, the report's section."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from evaluation.cost import cost_markdown, cost_path, part_cost, read_costs, summarize, write_cost


def test_costs_sum_per_method_and_leave_rendered_episodes_out_of_the_step_figures(tmp_path):
    write_cost(tmp_path, "a", method="full", steps=100, wall_s=10.0, cpu_s=9.0, load_s=2.0, rendered=False)
    write_cost(tmp_path, "b", method="full", steps=50, wall_s=5.0, cpu_s=5.0, load_s=0.0, rendered=False)
    write_cost(tmp_path, "c", method="full", steps=10, wall_s=99.0, cpu_s=99.0, load_s=0.0, rendered=True)
    write_cost(tmp_path, "d", method="dwa", steps=20, wall_s=1.0, cpu_s=0.5, load_s=0.0, rendered=False)
    cost_path(tmp_path, "e").write_text("{not json")  # a damaged file is skipped, not an error
    jobs = [SimpleNamespace(out=tmp_path, name=n) for n in "abcdef"]  # "f" never ran: no file
    rec = part_cost(jobs, wall_s=61.0, ran=4)
    full, dwa = rec["methods"]["full"], rec["methods"]["dwa"]
    assert (full["episodes"], full["timed"], full["steps"]) == (3, 2, 150)
    assert full["wall_s_per_episode"] == pytest.approx(7.5) and full["wall_ms_per_step"] == pytest.approx(100.0)
    assert full["cpu_ms_per_step"] == pytest.approx(1e3 * 14 / 150) and full["load_s"] == pytest.approx(2.0)
    assert dwa["wall_ms_per_step"] == pytest.approx(50.0)
    md = "\n".join(cost_markdown({"benchmark": rec}, {"full": "Ours (full)"}, workers=2))
    assert "| benchmark | 1.0 (4) | Ours (full) | 2 | 7.50 | 100.0 | 0.93 |" in md
    assert "| | | dwa | 1 | 1.00 | 50.0 | 0.50 |" in md


def test_nothing_timed_gives_no_section_and_only_rendered_gives_na(tmp_path):
    assert cost_markdown({"benchmark": {"wall_s": 1.0, "ran": 0, "methods": {}}}, {}, 2) == []
    write_cost(tmp_path, "v", method="full", steps=5, wall_s=3.0, cpu_s=3.0, load_s=0.0, rendered=True)
    s = summarize(read_costs([cost_path(tmp_path, "v")]))["full"]
    assert s["timed"] == 0 and s["wall_ms_per_step"] is None
    assert "| n/a | n/a | n/a |" in "\n".join(cost_markdown({"x": {"wall_s": 3.0, "ran": 1, "methods": {"full": s}}},
                                                           {}, 1))
