"""The benchmarks' timer: calls per second of a function over a wall-clock budget (after one warm-up call)."""

from __future__ import annotations

import time
from collections.abc import Callable


def throughput(step: Callable[[], object], seconds: float) -> float:
    """Calls of ``step`` per second over about ``seconds`` (after one warm-up call)."""
    step()
    n, t0 = 0, time.perf_counter()
    while True:
        step()
        n += 1
        dt = time.perf_counter() - t0
        if dt >= seconds:
            return n / dt


def time_call(fn: Callable[[], object], seconds: float) -> float:
    """Mean seconds per call of ``fn``."""
    return 1.0 / throughput(fn, seconds)
