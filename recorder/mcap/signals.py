"""SIGTERM/SIGINT as an :class:`Interrupted` exception, and the critical sections in which it waits.

:func:`graceful_signals` turns SIGTERM/SIGINT into :class:`Interrupted` (:mod:`pipeline.core.signals`) so that
writers are closed cleanly (the writer itself installs no signal handler); :func:`critical` marks the writer's calls
into the mcap library, which a signal never interrupts.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Iterator
from types import FrameType

from pipeline.core.signals import Interrupted

log = logging.getLogger("icrowdnav")

_tls = threading.local()  # per thread: depth of critical() blocks and a deferred signal


@contextlib.contextmanager
def critical() -> Iterator[None]:
    """A block that :func:`graceful_signals` does not interrupt: a signal arriving inside it is raised on exit.

    The writer marks its calls into the mcap library with this, so that SIGTERM/SIGINT never tear a chunk or the
    summary in half: the frame being added (or the finish in progress) completes first.
    """
    _tls.depth = getattr(_tls, "depth", 0) + 1
    try:
        yield
    except BaseException as e:
        _tls.depth -= 1
        pending = getattr(_tls, "pending", None)
        if _tls.depth == 0 and pending is not None:
            _tls.pending = None
            raise Interrupted(pending) from e
        raise
    _tls.depth -= 1
    pending = getattr(_tls, "pending", None)
    if _tls.depth == 0 and pending is not None:
        _tls.pending = None
        raise Interrupted(pending)


@contextlib.contextmanager
def graceful_signals(signums: tuple[int, ...] = (signal.SIGTERM, signal.SIGINT)) -> Iterator[None]:
    """Converts SIGTERM/SIGINT into an :class:`Interrupted` exception raised in the main thread.

    The exception unwinds the ``with`` blocks in flight, so an :class:`EpisodeWriter` closes its file as a valid
    ``*.partial`` (finished episodes are already final) and the caller can log what is complete and exit with
    ``exc.exit_code``. A signal that arrives while the writer is inside the mcap library (adding a frame,
    finishing) is deferred until that call returns, so no chunk is torn. The first signal raises; further signals
    while unwinding are logged and ignored, so cleanup is not cut short (SIGKILL still works). Previous handlers
    are restored on exit. A signal ignored when the block starts (``SIG_IGN``: a job started under ``nohup`` or with
    ``&`` from a script has SIGINT ignored) is left ignored. Outside the main thread (where Python cannot install
    handlers) this is a no-op.

    The writer installs no handler itself: recording code wraps its loop in this context manager, e.g.::

        try:
            with graceful_signals():
                record_all()
        except Interrupted as e:
            log.warning("stopped by %s; finished episodes are complete", signal.Signals(e.signum).name)
            return e.exit_code

    Args:
        signums: The signals to convert.

    Yields:
        Nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    fired: list[int] = []

    def handler(signum: int, frame: FrameType | None) -> None:
        name = signal.Signals(signum).name
        if fired:
            log.warning("%s received while already stopping; finishing cleanup first", name)
            return
        fired.append(signum)
        if getattr(_tls, "depth", 0) > 0:  # the handler runs in the main thread: this is its state
            log.warning("received %s: stopping once the current MCAP write completes", name)
            _tls.pending = signum
            return
        log.warning("received %s: stopping (open episode files are closed as *.partial)", name)
        raise Interrupted(signum)

    # a signal the process was started ignoring (SIGINT under nohup or ``&`` in a script) stays ignored, as Python
    # itself leaves it and as the other stages do
    previous = {s: signal.signal(s, handler) for s in signums if signal.getsignal(s) is not signal.SIG_IGN}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)
