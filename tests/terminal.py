"""Children started as a terminal starts them, whatever started pytest.

A shell without job control starts a background command (``cmd &`` in a script, as a CI runner or ``nohup … &``
may) with SIGINT ignored, its children inherit that, and Python — and the pipeline's stages — keep an inherited
``SIG_IGN``. Tests that send SIGINT to a child (Ctrl-C) start it with :func:`sigint_as_in_a_terminal` as the
``preexec_fn``, so the child sees SIGINT at its default, as in a terminal's foreground run.
"""

from __future__ import annotations

import signal


def sigint_as_in_a_terminal() -> None:
    """``preexec_fn``: SIGINT at its default disposition in the child (Python then turns it into KeyboardInterrupt)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
