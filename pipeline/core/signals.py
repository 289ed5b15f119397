"""A signal as an exception: :class:`Interrupted` (a :class:`KeyboardInterrupt` that knows its signal) and
:func:`sigterm_raises`, which the CLI wraps every stage run in.

Python's default SIGTERM ends the process where it stands: no ``finally`` runs, no line says what was kept. Raised
as an exception instead, SIGTERM unwinds a run exactly as Ctrl-C does — the local pool is stopped
(:func:`pipeline.core.executor.stop_pool`), Ray tasks are cancelled, an in-place output keeps every finished piece —
and the CLI prints one ``error:`` line and exits 143. Pool workers reset SIGTERM to its default when they start
(:func:`pipeline.core.executor.process_pool`): a worker must still die on it. The recorder refines this for its MCAP
writers (:func:`recorder.mcap.signals.graceful_signals` defers a signal until a write completes).
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from types import FrameType


class Interrupted(KeyboardInterrupt):  # noqa: N818 - named like KeyboardInterrupt, which it extends
    """A signal (SIGTERM, SIGINT) turned into an exception.

    Derives from :class:`KeyboardInterrupt` so that ``except Exception`` does not swallow it and code that already
    handles Ctrl-C handles SIGTERM the same way.

    Attributes:
        signum: The signal number.
        exit_code: ``128 + signum``, the conventional exit status after that signal.
    """

    def __init__(self, signum: int) -> None:
        self.signum = int(signum)
        self.exit_code = 128 + self.signum
        super().__init__(f"interrupted by {signal.Signals(signum).name}")

    def __reduce__(self) -> tuple:
        """Pickles by signal number (a pool worker's exception travels to the main process)."""
        return type(self), (self.signum,)


def signal_name(exc: BaseException) -> str:
    """The signal an interrupt came from: ``SIGTERM`` for :class:`Interrupted` by it, ``SIGINT`` for Ctrl-C."""
    return signal.Signals(exc.signum).name if isinstance(exc, Interrupted) else "SIGINT"


def exit_code(exc: BaseException) -> int:
    """The exit status a shell reports for a process stopped by ``exc``'s signal (130 for a plain Ctrl-C)."""
    return exc.exit_code if isinstance(exc, Interrupted) else 128 + signal.SIGINT


@contextlib.contextmanager
def sigterm_raises() -> Iterator[None]:
    """Inside the block, SIGTERM raises :class:`Interrupted` in the main thread (once: a second SIGTERM while the
    run unwinds is ignored, so its cleanup is not cut short; SIGKILL still works). SIGTERM is unblocked inside the
    block (a mask inherited from whatever started the process would keep ``kill`` from reaching the run); the
    previous handler and mask are restored on exit. Outside the main thread (where Python cannot install handlers)
    this does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    fired: list[int] = []

    def handler(signum: int, frame: FrameType | None) -> None:
        if fired:
            return
        fired.append(signum)
        raise Interrupted(signum)

    previous = signal.signal(signal.SIGTERM, handler)
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, [])  # the current mask, unchanged
    try:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})  # a SIGTERM pending since before raises here
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)
