"""``pipeline.core.timing.PhaseClock``: wall seconds per named phase, summed over calls, nested phases each on their
own, a call that raises still counted."""

from __future__ import annotations

import time

import pytest

from pipeline.core.timing import PhaseClock


def test_phases_sum_over_calls_and_nest_independently():
    clock = PhaseClock()
    for _ in range(2):
        with clock("outer"):
            time.sleep(0.01)
            with clock("inner"):
                time.sleep(0.02)
    assert set(clock.seconds) == {"outer", "inner"}
    assert clock.seconds["inner"] >= 0.04
    assert clock.seconds["outer"] >= clock.seconds["inner"] + 0.02  # the inner time is inside the outer's


def test_a_wrapped_function_returns_its_value_and_a_raising_call_is_still_timed():
    clock = PhaseClock()

    def slow(x, *, y):
        time.sleep(0.01)
        if x < 0:
            raise ValueError("negative")
        return x + y

    timed = clock.wrap("slow", slow)
    assert timed(1, y=2) == 3 and timed.__name__ == "slow"
    with pytest.raises(ValueError, match="negative"):
        timed(-1, y=0)
    assert clock.seconds["slow"] >= 0.02
