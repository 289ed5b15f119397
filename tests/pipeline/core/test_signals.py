"""Tests of pipeline.core.signals: SIGTERM as an exception for the length of a stage run (the CLI's behaviour end to
end: tests/pipeline/test_cli.py::test_a_signalled_stage_stops_its_pool_and_says_what_is_kept)."""

from __future__ import annotations

import os
import pickle
import signal
import threading
import time

import pytest

from pipeline.core.signals import Interrupted, exit_code, signal_name, sigterm_raises


def test_sigterm_raises_once_then_restores_the_previous_handler() -> None:
    before = signal.getsignal(signal.SIGTERM)
    unwound = []
    with pytest.raises(Interrupted) as ei, sigterm_raises():
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1.0)  # the handler raises here
        finally:  # a second SIGTERM while unwinding does not cut the cleanup short
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
            unwound.append(True)
    assert unwound == [True] and isinstance(ei.value, KeyboardInterrupt)
    assert (signal_name(ei.value), exit_code(ei.value)) == ("SIGTERM", 143)
    assert signal.getsignal(signal.SIGTERM) is before


def test_interrupts_name_their_signal_and_status_and_pickle() -> None:
    assert (signal_name(KeyboardInterrupt()), exit_code(KeyboardInterrupt())) == ("SIGINT", 130)
    e = pickle.loads(pickle.dumps(Interrupted(signal.SIGTERM)))  # a pool worker's exception reaches the parent
    assert type(e) is Interrupted and e.signum == signal.SIGTERM and e.exit_code == 143


def test_a_blocked_sigterm_is_unblocked_for_the_run_and_blocked_again_after() -> None:
    """A process started with SIGTERM blocked (the mask is inherited through fork and exec) is still stopped by
    ``kill``: the run unblocks it — a SIGTERM pending from before raises at once — and restores the mask after."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    try:
        # pending on this thread (a signal to the process would go to any other thread that does not block it)
        signal.pthread_kill(threading.main_thread().ident, signal.SIGTERM)
        time.sleep(0.05)
        body = []
        with pytest.raises(Interrupted), sigterm_raises():
            body.append(True)  # not reached: the pending signal is delivered on entry
        assert body == [] and signal.SIGTERM in signal.pthread_sigmask(signal.SIG_BLOCK, [])
        with sigterm_raises():
            assert signal.SIGTERM not in signal.pthread_sigmask(signal.SIG_BLOCK, [])
        assert signal.SIGTERM in signal.pthread_sigmask(signal.SIG_BLOCK, [])
    finally:
        signal.sigtimedwait({signal.SIGTERM}, 0)  # a signal left pending (a failed run) must not end pytest
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
