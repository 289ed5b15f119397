"""Timers: the benchmarks' calls per second of a function over a wall-clock budget (after one warm-up call), and
the per-phase clock a training loop reports where its time goes with (:class:`PhaseClock`)."""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

T = TypeVar("T")


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


class PhaseClock:
    """Wall seconds spent in named phases of a loop, summed over calls: where one episode's time goes.

    ``with clock("encode"): ...`` adds the block's wall time to ``clock.seconds["encode"]``; :meth:`wrap` times
    every call of a function the same way. Phases may nest (a render inside an env step): each is summed on its
    own, so a caller that wants exclusive shares subtracts the inner ones (:func:`rl.dagger.episode_phases`)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0

    def wrap(self, name: str, fn: Callable[..., T]) -> Callable[..., T]:
        """``fn`` timed as phase ``name`` on every call."""
        @functools.wraps(fn)
        def timed(*args: Any, **kwargs: Any) -> T:
            with self(name):
                return fn(*args, **kwargs)
        return timed
