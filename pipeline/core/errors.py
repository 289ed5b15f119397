"""Exception hierarchy of the pipeline.

Every error a user can cause (a bad config value, a missing input, an output that already exists, a damaged
artifact) is an :class:`ICrowdNavError`. The CLI prints such an error as exactly one line
``error: <message>`` and exits with status 2, so each message must be one self-explanatory line that names the
file or config key involved together with the expected and the actual value. Any other exception is a bug
and is allowed to propagate with its traceback.
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from typing import Any


class ICrowdNavError(Exception):
    """Base class of all user-facing pipeline errors (printed as one ``error:`` line by the CLI)."""

    def __str__(self) -> str:
        """Returns the message collapsed onto one line."""
        return " ".join(super().__str__().split("\n"))


class ConfigError(ICrowdNavError):
    """A config key, value, profile or command-line argument is invalid."""


class InputMissingError(ICrowdNavError):
    """A file or directory that a stage reads does not exist."""


class OutputExistsError(ICrowdNavError):
    """A stage would write into an output directory that already exists (and is not up to date)."""


class CorruptArtifactError(ICrowdNavError):
    """A file written by the pipeline exists but cannot be read back (bad JSON, missing fields, ...)."""


class StoppedError(ICrowdNavError):
    """The run was stopped by a signal (Ctrl-C, SIGTERM) after saving what it finished; the CLI prints the message
    as its ``error:`` line and exits with :attr:`exit_code` (``128 + signal number``: 130 for Ctrl-C, 143 for
    SIGTERM), the status a shell reports for a process stopped by that signal."""

    def __init__(self, message: str, exit_code: int = 130):
        super().__init__(message)
        self.exit_code = exit_code


def reports_errors(main: Callable[..., int]) -> Callable[..., int]:
    """Decorates a tool's ``main(argv) -> int`` with the rule above, written once for every tool: an
    :class:`ICrowdNavError` it raises becomes one ``error: <message>`` line on stderr and its exit status (2;
    a :class:`StoppedError`'s own ``exit_code``). Any other exception propagates with its traceback."""

    @functools.wraps(main)
    def wrapper(*args: Any, **kwargs: Any) -> int:
        try:
            return main(*args, **kwargs)
        except StoppedError as e:
            print(f"error: {e}", file=sys.stderr)
            return e.exit_code
        except ICrowdNavError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2

    return wrapper
