"""Crash-safe file and directory writing.

* :func:`atomic_write_bytes` / :func:`atomic_write_text` / :func:`atomic_write_json` / :func:`atomic_save_npz`
  write a file so that a reader sees either the old content or the complete new content, never a torn file.
* :class:`OutputDir` gives a stage a directory to write into and publishes it under its final name only when
  the stage finished without an exception, so a crash at any point never leaves a half-written output
  directory and never loses the previous one before the new one is complete.
"""

from __future__ import annotations

import contextlib
import glob
import json
import logging
import math
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Literal

from pipeline.core.errors import InputMissingError, OutputExistsError

log = logging.getLogger("icrowdnav")

OutputMode = Literal["new", "overwrite", "resume"]
OUTPUT_MODES: tuple[str, ...] = ("new", "overwrite", "resume")

FILE_MODE = 0o644  # published files are world-readable (mkstemp would leave 0600)
ATOMIC_SUFFIX = ".tmp"  # the temporary files of atomic_write_with: .<target>.<pid>.<random>.tmp


def fsync_dir(directory: Path) -> None:
    """Flushes a directory entry to disk (no-op where directories cannot be opened, e.g. Windows)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write_bytes(path: Path, data: bytes) -> Path:
    """Writes ``data`` to ``path`` atomically.

    The bytes go to a temporary file in the same directory, which is flushed, fsynced and then renamed over
    ``path`` with :func:`os.replace`; finally the directory is fsynced. On any failure the temporary file is
    removed and ``path`` keeps its previous content (or stays absent).

    Args:
        path: Destination file. Missing parent directories are created.
        data: The complete new file content.

    Returns:
        ``path``.
    """
    return atomic_write_with(path, lambda f: f.write(data))


def atomic_save_npz(path: Path, arrays: dict[str, Any]) -> Path:
    """Writes ``arrays`` as an uncompressed ``.npz`` archive (:func:`numpy.savez`) to ``path`` atomically (see
    :func:`atomic_write_bytes`; the archive is written straight into the temporary file, not held in memory).

    Args:
        path: Destination file (its name is kept as given: no ``.npz`` is appended).
        arrays: Array name -> array (anything :func:`numpy.savez` accepts).

    Returns:
        ``path``.
    """
    import numpy as np  # the kernel imports no numpy at import time (see _json_default): only this writer needs it

    return atomic_write_with(path, lambda f: np.savez(f, **arrays))


def atomic_write_with(path: Path, write: Callable[[IO[bytes]], object]) -> Path:
    """The atomic pattern of :func:`atomic_write_bytes` for any writer: ``write(f)`` fills a temporary file in the
    same directory (a binary file object, e.g. an SB3 model's ``save``), which is flushed, fsynced, renamed over
    ``path``; then the directory is fsynced. Returns ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # the writer's pid is in the name, so that a resumed run can tell a dead writer's leftover (a SIGKILL between
    # the create and the rename) from a live one's file: see stale_atomic_temps
    fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.{os.getpid()}.", suffix=ATOMIC_SUFFIX)
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, FILE_MODE)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    fsync_dir(path.parent)
    return path


def stale_atomic_temps(directory: Path, recursive: bool = True) -> list[Path]:
    """The temporary files of :func:`atomic_write_with` in ``directory`` (and its subdirectories when ``recursive``)
    whose writing process is gone: what a writer killed between creating its temporary file and renaming it over the
    target left behind.

    Their names are ``.<target>.<pid>.<random>.tmp``; one whose pid is still alive (or that does not parse) is
    kept. Returns them sorted; nothing is deleted here.
    """
    out = []
    pattern = f".*{ATOMIC_SUFFIX}"
    for p in sorted(Path(directory).rglob(pattern) if recursive else Path(directory).glob(pattern)):
        parts = p.name[: -len(ATOMIC_SUFFIX)].rsplit(".", 2)  # [".<target>", "<pid>", "<random>"]
        if len(parts) == 3 and parts[1].isdigit() and p.is_file() and not pid_alive(int(parts[1])):
            out.append(p)
    return out


def atomic_write_text(path: Path, text: str, encoding: str = "utf-8") -> Path:
    """Writes ``text`` to ``path`` atomically (see :func:`atomic_write_bytes`).

    Args:
        path: Destination file.
        text: The complete new file content.
        encoding: Text encoding.

    Returns:
        ``path``.
    """
    return atomic_write_bytes(path, text.encode(encoding))


def _json_default(obj: Any) -> Any:
    """Makes paths, numpy scalars/arrays, sets and tuples JSON-serialisable."""
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if hasattr(obj, "tolist"):  # numpy arrays and scalars, without importing numpy
        return obj.tolist()
    if isinstance(obj, set | frozenset):
        return sorted(obj)
    raise TypeError(f"object of type {type(obj).__name__} is not JSON serialisable: {obj!r}")


def json_safe(obj: Any) -> Any:
    """JSON-safe copy: nan/inf floats become None."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if hasattr(obj, "item") and not isinstance(obj, str):
        return json_safe(obj.item())
    return obj


def atomic_write_json(path: Path, data: Any) -> Path:
    """Writes ``data`` as JSON (indent 2, sorted keys, trailing newline) to ``path`` atomically.

    Args:
        path: Destination file.
        data: JSON-serialisable data; paths and numpy values are converted.

    Returns:
        ``path``.
    """
    text = json.dumps(data, indent=2, sort_keys=True, default=_json_default) + "\n"
    return atomic_write_text(path, text)


def require_input(path: Path, what: str, hint: str = "") -> Path:
    """Checks that an input file or directory exists.

    Args:
        path: The path a stage is about to read.
        what: What it is, for the message (e.g. ``"rollout dataset"``).
        hint: Optional advice appended to the message (e.g. which command produces it).

    Returns:
        ``path``.

    Raises:
        InputMissingError: ``path`` does not exist.
    """
    path = Path(path)
    if not path.exists():
        raise InputMissingError(f"missing {what}: {path}" + (f"; {hint}" if hint else ""))
    return path


def pid_alive(pid: int) -> bool:
    """Whether a process with this id exists (a process of another user counts as alive)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return False
    if not Path("/proc/self/stat").exists():  # no procfs (not Linux): kill() is all we know
        return True
    try:  # a zombie (killed, not yet reaped) exists but will never write again
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False  # it was reaped meanwhile
    except IndexError:
        return True


def _is_nonempty(path: Path) -> bool:
    """Whether ``path`` exists and is anything but an empty directory."""
    if not path.exists() and not path.is_symlink():
        return False
    if path.is_dir() and not path.is_symlink():
        return any(path.iterdir())
    return True


def _remove(path: Path) -> None:
    """Removes a file, link or directory tree if it exists."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists() or path.is_symlink():
        with contextlib.suppress(OSError):
            path.unlink()


class OutputDir:
    """Context manager giving a stage a crash-safe output directory.

    Modes:
        ``new``: ``final`` must be absent or an empty directory (else :class:`OutputExistsError`). The stage
            writes into a staging directory ``.<name>.staging-<pid>`` next to ``final``, which is renamed to
            ``final`` on a clean exit.
        ``overwrite``: like ``new`` but an existing ``final`` is replaced on a clean exit: it is first renamed
            to ``.<name>.old-<pid>``, the staging directory is renamed into place, and only then is the old
            one deleted.
        ``resume``: the stage writes directly into ``final`` (created if missing) and is responsible for
            continuing from what is already there.

    On an exception inside the ``with`` block the staging directory is deleted, ``final`` is untouched, and
    the exception propagates. On entry, staging/old directories left next to ``final`` by dead processes
    are cleaned up (an old directory whose replacement never reached ``final`` is restored).

    Attributes:
        final: The published output directory.
        mode: One of ``new``, ``overwrite``, ``resume``.
        path: Where the stage writes (the staging directory, or ``final`` when resuming).
    """

    def __init__(self, final: Path, mode: OutputMode = "new") -> None:
        """Initialises the context manager (nothing touches the disk before ``__enter__``).

        Args:
            final: The output directory to publish.
            mode: ``new``, ``overwrite`` or ``resume``.

        Raises:
            ValueError: ``mode`` is not one of the three modes.
        """
        if mode not in OUTPUT_MODES:
            raise ValueError(f"OutputDir mode: expected one of {', '.join(OUTPUT_MODES)}, got {mode!r}")
        self.final = Path(final)
        self.mode: OutputMode = mode
        pid = os.getpid()
        self.staging = self.final.parent / f".{self.final.name}.staging-{pid}"
        self.old = self.final.parent / f".{self.final.name}.old-{pid}"
        self.path = self.final if mode == "resume" else self.staging
        self._entered = False

    def _cleanup_stale(self) -> None:
        """Removes staging dirs of dead processes; restores or removes their ``.old`` dirs."""
        parent = self.final.parent
        if not parent.is_dir():
            return
        name = self.final.name
        for kind in ("old", "staging"):
            prefix = f".{name}.{kind}-"
            for entry in sorted(parent.glob(f"{glob.escape(prefix)}*")):
                suffix = entry.name[len(prefix) :]
                if not suffix.isdigit():
                    continue
                pid = int(suffix)
                if pid != os.getpid() and pid_alive(pid):
                    continue
                if pid == os.getpid() and kind == "staging":
                    continue  # our own leftover staging dir is removed in __enter__
                if kind == "old" and not self.final.exists():
                    log.warning("restoring %s from %s left by an interrupted overwrite", self.final, entry)
                    os.rename(entry, self.final)
                else:
                    log.info("removing stale %s", entry)
                    _remove(entry)

    def __enter__(self) -> OutputDir:
        """Checks the mode's precondition and creates the directory the stage writes into.

        Returns:
            ``self``; write into ``self.path``.

        Raises:
            OutputExistsError: mode ``new`` and ``final`` exists and is not an empty directory, or mode
                ``resume`` and ``final`` exists but is not a directory.
        """
        if self._entered:
            raise RuntimeError(f"OutputDir({self.final}) is not re-entrant")
        self._created = [p for p in (self.final, *self.final.parents) if not p.exists()]
        self._cleanup_stale()
        if self.mode == "new" and _is_nonempty(self.final):
            raise OutputExistsError(
                f"output directory {self.final} already exists; pass --overwrite to replace it "
                "or --resume to continue it"
            )
        if self.mode == "resume":
            if self.final.exists() and not self.final.is_dir():
                raise OutputExistsError(
                    f"output path {self.final} exists but is not a directory; cannot resume it"
                )
            self.final.mkdir(parents=True, exist_ok=True)
            for p in stale_atomic_temps(self.final):  # a killed run's half-written file: never part of the output
                log.info("removing stale %s", p)
                p.unlink(missing_ok=True)
        else:
            self.final.parent.mkdir(parents=True, exist_ok=True)
            _remove(self.staging)
            self.staging.mkdir()
        self._entered = True
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> bool:
        """Publishes the staging directory on success; discards it on an exception (which propagates).

        Returns:
            False, so that an exception raised inside the block propagates.
        """
        self._entered = False
        if self.mode == "resume":
            return False
        if exc_type is not None:
            _remove(self.staging)
            self._remove_created_parents()
            return False
        try:
            self._publish()
        except BaseException:
            _remove(self.staging)
            raise
        # again after publishing: a killed earlier run whose process was still dying when this one started (SIGKILL
        # lands asynchronously, e.g. on a process in disk sleep) has left its staging dir by now
        try:
            self._cleanup_stale()
        except OSError as e:  # the output is published; a leftover is only untidy
            log.warning("could not remove stale directories next to %s: %s", self.final, e)
        return False

    def _remove_created_parents(self) -> None:
        """After a failure: the parent folders this run created, if still empty (deepest first)."""
        for p in getattr(self, "_created", []):
            if p != self.final:
                with contextlib.suppress(OSError):
                    p.rmdir()

    def _publish(self) -> None:
        """Moves the staging directory to ``final`` (replacing an existing one in mode ``overwrite``)."""
        final = self.final
        if final.exists() or final.is_symlink():
            if self.mode == "new":
                if _is_nonempty(final):
                    raise OutputExistsError(
                        f"output directory {final} was created by someone else while this stage ran; "
                        "pass --overwrite to replace it"
                    )
                final.rmdir()
                os.rename(self.staging, final)
            else:
                _remove(self.old)
                os.rename(final, self.old)
                try:
                    os.rename(self.staging, final)
                except BaseException:
                    os.rename(self.old, final)  # put the previous output back
                    raise
                fsync_dir(final.parent)
                _remove(self.old)
        else:
            os.rename(self.staging, final)
        fsync_dir(final.parent)
