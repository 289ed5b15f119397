"""Writing one episode MCAP: :class:`EpisodeWriter`, with the lifecycle ``start → add* → finish`` (or abort).

While open the file is ``<name>.mcap.partial``; finishing renames it to ``<name>.mcap`` (never replacing a file).
Chunks are cut at frame boundaries; the default compression and chunk size were chosen by measurement (see
:mod:`recorder.mcap.bench`). The writer installs no signal handler: wrap recording loops in
:func:`recorder.mcap.signals.graceful_signals`.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import time
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import numpy as np
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import register_schema

from pipeline.core.artifacts import fsync_dir
from pipeline.core.errors import OutputExistsError
from recorder.mcap.codecs import JSON_SCHEMAS, PROTO_TYPES
from recorder.mcap.frames import FrameEncoder
from recorder.mcap.layout import LIBRARY, METADATA_ABORTED, all_topics, dt_ns_of, partial_path_of
from recorder.mcap.signals import critical
from recorder.schema import CAMERA_NAMES, DEPTH_SCALE_M, METADATA_EPISODE, TOPIC_OCCUPANCY, EpisodeMeta, Frame

log = logging.getLogger("icrowdnav")

DEFAULT_CHUNK_SIZE = 1 << 20  # uncompressed bytes per chunk (cut at the next frame boundary); see bench.py
DEFAULT_COMPRESSION = "zstd"
COMPRESSIONS: dict[str, CompressionType] = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                                            "none": CompressionType.NONE}


class FdStream:
    """Unbuffered append-only file stream for the mcap Writer.

    Each ``write`` goes straight to the OS, so every finished chunk is in the file (page cache) as soon as it is
    written and survives a SIGKILL of the process; there is no Python-side buffer to lose.
    """

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.pos = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data)
        while view:
            n = os.write(self.fd, view)
            view = view[n:]
            self.pos += n
        return len(data)

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        pass


def publish_no_clobber(src: Path, dst: Path) -> None:
    """Atomically gives ``src`` the name ``dst``, failing (OutputExistsError) rather than replacing ``dst``.

    Hard-links ``dst`` to ``src`` (which fails if ``dst`` exists), then unlinks ``src``: a crash in between leaves
    both names on one complete file, which :mod:`recorder.doctor_mcap` reports.
    """
    try:
        os.link(src, dst)
    except FileExistsError:
        raise OutputExistsError(f"{dst} already exists; refusing to overwrite it (the new file is left as {src})") \
            from None
    except OSError as e:  # file systems without hard links: check, then rename (not atomic against a racer)
        if e.errno not in (errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EXDEV, errno.EMLINK):
            raise
        if dst.exists():
            raise OutputExistsError(f"{dst} already exists; refusing to overwrite it") from None
        os.rename(src, dst)
    else:
        os.unlink(src)
    fsync_dir(dst.parent)


WriterState = Literal["new", "open", "finished", "aborted"]


class EpisodeWriter:
    """Writes one episode to ``<name>.mcap`` with an explicit lifecycle: ``start → add* → finish``.

    While open the file is ``<name>.mcap.partial``. :meth:`finish` writes the summary, fsyncs, renames it to the
    final name (never replacing an existing file) and fsyncs the directory. As a context manager the writer starts
    on entry and finishes on a clean exit; on an exception it calls :meth:`abort`, which leaves a valid MCAP under
    the ``.partial`` name (never renamed). Chunks are cut at frame boundaries, and each finished chunk is written
    to the OS at once, so a SIGKILL loses at most the frames of the open chunk (see :func:`recover`).

    Attributes:
        final_path: ``<name>.mcap``.
        partial_path: ``<name>.mcap.partial``.
        n_frames: Frames added so far.
        frames_durable: Frames whose chunk has been written to the file (they survive a kill of the process).
        write_seconds: Wall time spent inside :meth:`start`, :meth:`add` and :meth:`finish` (for the budget).
        state: ``new``, ``open``, ``finished`` or ``aborted``.
    """

    def __init__(self, final_path: Path, meta: EpisodeMeta, occupancy: np.ndarray,
                 chunk_size: int = DEFAULT_CHUNK_SIZE, compression: str = DEFAULT_COMPRESSION) -> None:
        """Checks the arguments; nothing touches the disk before :meth:`start`.

        Args:
            final_path: Destination ``<name>.mcap``.
            meta: The episode's constant facts (written as the ``episode`` metadata record).
            occupancy: ``H x W`` bool static occupancy (``meta.occupancy_shape``), logged once at t = 0.
            chunk_size: Uncompressed bytes after which the chunk is closed at the next frame boundary.
            compression: ``zstd``, ``lz4`` or ``none``.

        Raises:
            ValueError: a bad path suffix, chunk size, compression or occupancy shape.
        """
        self.final_path = Path(final_path)
        if self.final_path.suffix != ".mcap":
            raise ValueError(f"EpisodeWriter: expected a path ending in .mcap, got {self.final_path}")
        if compression not in COMPRESSIONS:
            raise ValueError(f"EpisodeWriter compression: expected one of {list(COMPRESSIONS)}, got {compression!r}")
        if chunk_size < 1:
            raise ValueError(f"EpisodeWriter chunk_size: expected >= 1 byte, got {chunk_size}")
        occ = np.asarray(occupancy)
        if list(occ.shape) != list(meta.occupancy_shape):
            raise ValueError(f"{self.final_path}: occupancy shape {list(occ.shape)} != meta.occupancy_shape "
                             f"{list(meta.occupancy_shape)}")
        for cam in CAMERA_NAMES:
            if cam not in meta.cameras:
                raise ValueError(f"{self.final_path}: meta.cameras lacks camera {cam!r}")
        self.partial_path = partial_path_of(self.final_path)
        self.meta = meta
        self.occupancy = occ.astype(bool)
        self.chunk_size = int(chunk_size)
        self.compression = compression
        self.n_frames = 0
        self.frames_durable = 0
        self.write_seconds = 0.0
        self.state: WriterState = "new"
        self._dt_ns = dt_ns_of(meta)
        self._enc = FrameEncoder(meta)
        self._fd: int | None = None
        self._mcap: McapWriter | None = None
        self._channels: dict[str, int] = {}
        self._pending = 0  # uncompressed payload bytes in the open chunk
        self._broken = False  # an exception escaped from inside the mcap writer: the file tail is undefined
        self._last_done = False

    # lifecycle -------------------------------------------------------------------------------------------------

    def start(self) -> EpisodeWriter:
        """Creates ``<name>.mcap.partial`` and writes the header, the ``episode`` metadata and the schemas.

        Returns:
            ``self``.

        Raises:
            OutputExistsError: ``<name>.mcap`` exists, or a ``.partial`` of the same name does (a killed or
                concurrent recording; recover or delete it first).
            RuntimeError: already started.
        """
        if self.state != "new":
            raise RuntimeError(f"EpisodeWriter({self.final_path}).start(): already {self.state}")
        t0 = time.perf_counter()
        if self.final_path.exists():
            raise OutputExistsError(f"{self.final_path} already exists; refusing to overwrite a recorded episode")
        self.final_path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._fd = os.open(self.partial_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            raise OutputExistsError(
                f"{self.partial_path} already exists (an unfinished recording of this episode); recover it with "
                f"`python -m recorder.mcap.cli recover {self.partial_path}` or delete it") from None
        self.state = "open"
        try:
            self._inside_mcap(self._start_mcap)
        except BaseException as e:
            if self._mcap is not None and not self._broken:
                self.abort(type(e).__name__)  # a signal deferred past the header: leave a valid aborted file
            else:
                self._close_fd()
                self.state = "aborted"
            raise
        self.write_seconds += time.perf_counter() - t0
        return self

    def _start_mcap(self) -> None:
        assert self._fd is not None
        w = McapWriter(FdStream(self._fd), chunk_size=1 << 62, compression=COMPRESSIONS[self.compression],
                       enable_crcs=True, enable_data_crcs=True)  # chunks are cut by us, at frame boundaries
        self._mcap = w
        w.start(profile="", library=LIBRARY)
        w.add_metadata(METADATA_EPISODE, self.meta.to_metadata())  # directly after the header: survives a kill
        schema_ids: dict[str, int] = {}
        for topic in all_topics():
            if topic in JSON_SCHEMAS:
                name, data = JSON_SCHEMAS[topic]
                if name not in schema_ids:
                    schema_ids[name] = w.register_schema(name=name, encoding="jsonschema", data=data)
                self._channels[topic] = w.register_channel(topic=topic, message_encoding="json",
                                                           schema_id=schema_ids[name])
            else:
                cls = PROTO_TYPES[topic]
                name = cls.DESCRIPTOR.full_name
                if name not in schema_ids:
                    schema_ids[name] = register_schema(w, cls)
                md = ({"encoding": "16UC1", "unit": "mm", "scale_m": repr(DEPTH_SCALE_M), "invalid": "0"}
                      if topic.endswith("/depth") else {})
                self._channels[topic] = w.register_channel(topic=topic, message_encoding="protobuf",
                                                           schema_id=schema_ids[name], metadata=md)

    def add(self, frame: Frame) -> None:
        """Logs one frame (all its topics at log time ``frame.t_ns``).

        Args:
            frame: The next frame: ``step`` must be ``n_frames`` and ``t_ns`` = ``step · dt``, images of the
                cameras' size; no frame may follow one with ``done=True``.

        Raises:
            RuntimeError: the writer is not open.
            ValueError: the frame does not continue the episode or has the wrong image size/dtype (the message
                names the field, expected and actual value).
        """
        if self.state != "open":
            raise RuntimeError(f"EpisodeWriter({self.final_path}).add(): writer is {self.state}, not open")
        t0 = time.perf_counter()
        self._check_frame(frame)
        msgs = self._enc.frame_messages(frame)
        if frame.step == 0:  # first, so that it is in the first chunk
            msgs.insert(0, (TOPIC_OCCUPANCY, self._enc.grid(self.occupancy)))

        def write() -> None:
            assert self._mcap is not None
            for topic, data in msgs:
                self._mcap.add_message(self._channels[topic], log_time=frame.t_ns, data=data,
                                       publish_time=frame.t_ns, sequence=frame.step)
                self._pending += len(data)
            self.n_frames += 1
            if self._pending >= self.chunk_size:
                self._mcap.flush()  # closes the chunk at this frame boundary and writes it to the file
                self._pending = 0
                self.frames_durable = self.n_frames

        self._inside_mcap(write)
        self._last_done = bool(frame.done)
        self.write_seconds += time.perf_counter() - t0

    def _check_frame(self, fr: Frame) -> None:
        where = f"{self.partial_path}: frame {self.n_frames}"
        if fr.step != self.n_frames:
            raise ValueError(f"{where}: step expected {self.n_frames}, got {fr.step}")
        if fr.t_ns != fr.step * self._dt_ns:
            raise ValueError(f"{where}: t_ns expected step * dt = {fr.step * self._dt_ns}, got {fr.t_ns}")
        if self._last_done:
            raise ValueError(f"{where}: the previous frame had done=True; an episode ends there")
        for cam in CAMERA_NAMES:
            c = self._enc.cams[cam]
            rgb, depth = np.asarray(fr.rgb[cam]), np.asarray(fr.depth[cam])
            if rgb.shape != (c["h"], c["w"], 3) or rgb.dtype != np.uint8:
                raise ValueError(f"{where}: rgb[{cam}] expected uint8 {(c['h'], c['w'], 3)}, got {rgb.dtype} "
                                 f"{rgb.shape}")
            if depth.shape != (c["h"], c["w"]):
                raise ValueError(f"{where}: depth[{cam}] expected shape {(c['h'], c['w'])}, got {depth.shape}")

    def _inside_mcap(self, fn: Any) -> None:
        """Runs ``fn`` (which calls into the mcap writer) as a critical section (signals wait until it returns);
        an exception escaping from it marks the file tail undefined."""
        with critical():
            try:
                fn()
            except BaseException:
                self._broken = True
                raise

    def finish(self) -> Path:
        """Writes the summary and footer, fsyncs, renames to the final name and fsyncs the directory.

        Idempotent: a second call returns the final path again.

        Returns:
            ``final_path``.

        Raises:
            RuntimeError: the writer was never started, or was aborted.
            OutputExistsError: the final file appeared meanwhile (the episode stays as ``.partial``).
        """
        if self.state == "finished":
            return self.final_path
        if self.state != "open":
            raise RuntimeError(f"EpisodeWriter({self.final_path}).finish(): writer is {self.state}")
        if self._broken:
            raise RuntimeError(f"EpisodeWriter({self.final_path}).finish(): an earlier write failed; the file "
                               f"stays {self.partial_path}")
        t0 = time.perf_counter()
        with critical():  # a signal arriving now is raised once the episode is final
            try:
                self._finish_mcap()
                self._close_fd()
            except BaseException:
                self._broken = True
                self.abort()
                raise
            self.frames_durable = self.n_frames
            try:
                publish_no_clobber(self.partial_path, self.final_path)
            except BaseException:
                self.state = "aborted"  # complete and valid, but stays under the .partial name
                raise
            self.state = "finished"
            self.write_seconds += time.perf_counter() - t0
        return self.final_path

    def _finish_mcap(self) -> None:
        assert self._mcap is not None and self._fd is not None
        self._mcap.finish()
        os.fsync(self._fd)

    def abort(self, reason: str = "") -> Path | None:
        """Closes the file without publishing it: it stays ``<name>.mcap.partial``.

        If the mcap writer is in a consistent state the file gets an ``aborted`` metadata record, its summary and
        footer, so it is a valid MCAP (readable, and :func:`recover` salvages every frame in it); otherwise it
        is just closed (``recover`` salvages the complete chunks). Idempotent; a no-op after :meth:`finish`.

        Args:
            reason: Stored in the ``aborted`` metadata record (e.g. the exception type).

        Returns:
            The ``.partial`` path, or None when the writer was finished or never started.
        """
        if self.state in ("finished", "new"):
            return None
        if self.state == "aborted":
            return self.partial_path
        self.state = "aborted"
        try:
            with critical():
                if not self._broken and self._mcap is not None and self._fd is not None:
                    self._mcap.add_metadata(METADATA_ABORTED, {"reason": reason, "frames": str(self.n_frames)})
                    self._mcap.finish()
                    self.frames_durable = self.n_frames
        except Exception as e:  # the original exception matters more; the file is recoverable anyway
            log.warning("%s: could not close the MCAP cleanly (%s); recover() salvages its complete chunks",
                        self.partial_path, e)
        finally:
            self._close_fd()
        return self.partial_path

    def _close_fd(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            os.close(fd)

    def __enter__(self) -> EpisodeWriter:
        if self.state == "new":
            self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> bool:
        if exc_type is None:
            self.finish()
        else:
            self.abort(reason=exc_type.__name__)
            log.warning("%s: episode not finished (%s); left as %s with %d frames", self.final_path.name,
                        exc_type.__name__, self.partial_path.name, self.frames_durable)
        return False

    def __del__(self) -> None:  # never leak the descriptor of a writer that was dropped mid-episode
        with contextlib.suppress(Exception):
            self._close_fd()
