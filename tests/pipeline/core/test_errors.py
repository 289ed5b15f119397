"""pipeline.core.errors: one ``error:`` line and the exit status for every tool's ``main``."""

from __future__ import annotations

import pytest

from pipeline.core.errors import ConfigError, StoppedError, reports_errors


def test_a_user_error_becomes_one_line_on_stderr_and_exit_2(capsys):
    @reports_errors
    def main(argv=None):
        raise ConfigError("--x: expected a number\nin 0..1, got 'a'")

    assert main(["--x", "a"]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err == "error: --x: expected a number in 0..1, got 'a'\n"


def test_a_stop_exits_with_its_signal_status(capsys):
    @reports_errors
    def main(argv=None):
        raise StoppedError("stopped by SIGTERM after 3 of 5 episodes", exit_code=143)

    assert main([]) == 143
    assert capsys.readouterr().err == "error: stopped by SIGTERM after 3 of 5 episodes\n"


def test_success_passes_the_status_through_and_a_bug_keeps_its_traceback():
    @reports_errors
    def ok(argv=None):
        """Doc kept."""
        return 1

    @reports_errors
    def buggy(argv=None):
        raise ZeroDivisionError

    assert ok([]) == 1 and ok.__doc__ == "Doc kept."
    with pytest.raises(ZeroDivisionError):
        buggy([])
