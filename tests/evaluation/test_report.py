"""evaluation.report: the cue-twin timing comparison (the rest of the report is exercised by test_eval.py)."""

from __future__ import annotations

import math

import numpy as np
from scipy.stats import wilcoxon

from evaluation.report import cue_timing_test, cue_twin_table, plot_cue_timing


def _row(method: str, seed: int, div: float) -> dict:
    return {"scene": "crossing_turn", "method": method, "seed": seed, "cue_divergence_s": div,
            "cue_anticipated": float(math.isfinite(div) and div < 0.7), "cue_divergence_safer": 1.0 if
            math.isfinite(div) else math.nan, "min_clearance_scripted_m": 0.4, "twin_min_clearance_scripted_m": 0.4,
            "collision_scripted": 0.0, "twin_collision_scripted": 0.0, "twin_identical_before_cue": 1.0}


# full responds 0.1 s after the onset in every trial, the other method later in most; steps of 0.1 s carry the
# float error of a step count times dt (0.30000000000000004 and the like), which must tie exactly after rounding
FULL = [0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.2, math.nan, 0.1]
OTHER = [0.5, 0.6, 0.30000000000000004, 0.7, 0.1 + 1e-12, 0.9, 0.4, 0.1, 0.3, math.nan]


def test_cue_timing_test_compares_the_trials_in_which_both_changed_course():
    a = [_row("full", s, d) for s, d in enumerate(FULL)]
    b = [_row("no_i2", s, d) for s, d in enumerate(OTHER)]
    t = cue_timing_test(a, b)
    d = np.round(np.array(FULL[:8]), 6) - np.round(np.array(OTHER[:8]), 6)
    assert t["n"] == 8  # the two trials with a NaN (no response) on either side are left out
    assert (t["earlier"], t["later"]) == (6, 1)  # the 0.1 vs 0.1 + 1e-12 pair ties after rounding
    assert t["median_diff"] == float(np.median(d)) < 0
    assert t["p_value"] == float(wilcoxon(d).pvalue)
    few = cue_timing_test(a[:4], b[:4])
    assert few["n"] == 4 and math.isnan(few["p_value"])  # fewer than 5 pairs: no p-value


def test_cue_twin_table_reports_when_each_method_responds_against_the_reference():
    rows = [_row("full", s, d) for s, d in enumerate(FULL)] + [_row("no_i2", s, d) for s, d in enumerate(OTHER)]
    text = "\n".join(cue_twin_table(rows, {"full": "full", "no_i2": "w/o I²"}))
    tests = text.split("both changed |", 1)[1]  # the comparison table after the per-method one
    line = next(x for x in tests.splitlines() if x.startswith("| crossing_turn | w/o I² | 10 |"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[5:8] == ["8", f"{np.median(np.array(FULL[:8]) - np.round(OTHER[:8], 6)):+.2f}", "6 / 1"]
    assert "full − other" in text


def test_plot_cue_timing_draws_every_trial_of_every_scenario(tmp_path):
    rows = [_row("full", s, d) for s, d in enumerate(FULL)] + [_row("no_i2", s, d) for s, d in enumerate(OTHER)]
    rows += [{**r, "scene": "blind_corner"} for r in rows]
    rows = [{**r, "cue_lead_s": 0.7} for r in rows]
    path = tmp_path / "cue_timing.png"
    plot_cue_timing(rows, {"no_i2": "w/o I²"}, path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
