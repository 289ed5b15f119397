"""Reading complete episode MCAPs: footer, summary and data-section CRC validation, :class:`EpisodeReader` /
:func:`read_episode` / :func:`count_frames` (frames back as :class:`recorder.schema.Frame`), and the scanner
:func:`scan_episode` / :func:`episode_summary` (a CRC-checked pass that records problems, for the doctor).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk

from pipeline.core.errors import CorruptArtifactError, InputMissingError
from recorder.mcap.codecs import expected_schema_name
from recorder.mcap.exceptions import DECODE_ERRORS, CorruptMcapError
from recorder.mcap.frames import decode_frame, decode_grid
from recorder.mcap.layout import (
    MAGIC,
    METADATA_ABORTED,
    METADATA_RECOVERY,
    all_topics,
    dt_ns_of,
    frame_topics,
)
from recorder.schema import METADATA_EPISODE, TOPIC_OCCUPANCY, TOPIC_REWARD, TOPIC_ROBOT, EpisodeMeta, Frame

_FOOTER_RECORD_SIZE = 1 + 8 + 8 + 8 + 4  # opcode, length, summary_start, summary_offset_start, summary_crc
_DATA_END_RECORD_SIZE = 1 + 8 + 4


# --------------------------------------------------------------------------------------------------------------
# reading complete files


@dataclass
class _Index:
    """What the seeking reader learned from a complete file's summary."""

    header: Header
    metadata: dict[str, dict[str, str]]
    channels: dict[int, Channel]
    schemas: dict[int, Schema]
    topic_of: dict[int, str]
    chunks: list[tuple[int, int]]  # (chunk_start_offset, chunk_length), in file order
    message_counts: dict[str, int]
    message_start_time: int
    message_end_time: int
    size: int


def require_file(path: Path) -> Path:
    path = Path(path)
    if not path.exists():
        raise InputMissingError(f"missing episode MCAP: {path}")
    if not path.is_file():
        raise InputMissingError(f"episode MCAP {path} is not a regular file")
    return path


def _read_exact(f: io.BufferedReader, offset: int, n: int, path: Path, what: str) -> bytes:
    f.seek(offset)
    data = f.read(n)
    if len(data) != n:
        raise CorruptMcapError(path, f"truncated: {what} needs {n} bytes, file ends after {len(data)}", offset)
    return data


def _open_index(f: io.BufferedReader, path: Path) -> _Index:
    """Validates magic, footer, summary CRC and data-section CRC of a complete file and reads its summary."""
    size = os.fstat(f.fileno()).st_size
    min_size = 2 * len(MAGIC) + _FOOTER_RECORD_SIZE
    if size < min_size:
        raise CorruptMcapError(path, f"not a complete MCAP file: {size} bytes (< {min_size})")
    if _read_exact(f, 0, len(MAGIC), path, "leading magic") != MAGIC:
        raise CorruptMcapError(path, "not an MCAP file (bad leading magic)", 0)
    tail_off = size - len(MAGIC)
    if _read_exact(f, tail_off, len(MAGIC), path, "trailing magic") != MAGIC:
        raise CorruptMcapError(path, "truncated or unfinished MCAP (no trailing magic; a killed recording? "
                               "rename it to *.mcap.partial and run recover)", tail_off)
    foot_off = tail_off - _FOOTER_RECORD_SIZE
    raw_footer = _read_exact(f, foot_off, _FOOTER_RECORD_SIZE, path, "footer")
    opcode, length = struct.unpack_from("<BQ", raw_footer)
    if opcode != Opcode.FOOTER or length != 20:
        raise CorruptMcapError(path, "truncated or damaged MCAP (no footer record before the trailing magic)",
                               foot_off)
    footer = Footer.read(ReadDataStream(io.BytesIO(raw_footer[9:])))
    if footer.summary_start == 0 or not len(MAGIC) < footer.summary_start <= foot_off:
        raise CorruptMcapError(path, f"footer has no usable summary (summary_start={footer.summary_start})", foot_off)
    summary_bytes = _read_exact(f, footer.summary_start, foot_off - footer.summary_start, path, "summary")
    if footer.summary_crc != 0:
        crc = zlib.crc32(raw_footer[:-4], zlib.crc32(summary_bytes))
        if crc != footer.summary_crc:
            raise CorruptMcapError(path, f"summary CRC mismatch (expected {footer.summary_crc:#010x}, got "
                                   f"{crc:#010x})", footer.summary_start)
    f.seek(0)
    reader = SeekingReader(f, validate_crcs=True, record_size_limit=size)
    summary = reader.get_summary()
    if summary is None or summary.statistics is None:
        raise CorruptMcapError(path, "MCAP summary lacks statistics", footer.summary_start)
    # data-section CRC (the DataEnd record sits right before the summary): catches damage anywhere in the data,
    # including metadata and message indexes that reading chunks alone would not touch
    de_off = footer.summary_start - _DATA_END_RECORD_SIZE
    raw_de = _read_exact(f, de_off, _DATA_END_RECORD_SIZE, path, "DataEnd record")
    if raw_de[0] != Opcode.DATA_END:
        raise CorruptMcapError(path, "no DataEnd record before the summary", de_off)
    data_end = DataEnd.read(ReadDataStream(io.BytesIO(raw_de[9:])))
    header = reader.get_header()
    metadata: dict[str, dict[str, str]] = {}
    for mi in summary.metadata_indexes:
        rec = _record_at(f, mi.offset, path, size)
        if not isinstance(rec, Metadata):
            raise CorruptMcapError(path, f"metadata index points at a {type(rec).__name__}", mi.offset)
        metadata[rec.name] = dict(rec.metadata)
    chunks = sorted((ci.chunk_start_offset, ci.chunk_length) for ci in summary.chunk_indexes)
    topic_of = {cid: ch.topic for cid, ch in summary.channels.items()}
    counts = {topic_of.get(cid, f"<channel {cid}>"): n
              for cid, n in summary.statistics.channel_message_counts.items()}
    idx = _Index(header=header, metadata=metadata, channels=dict(summary.channels), schemas=dict(summary.schemas),
                 topic_of=topic_of, chunks=chunks, message_counts=counts,
                 message_start_time=summary.statistics.message_start_time,
                 message_end_time=summary.statistics.message_end_time, size=size)
    if data_end.data_section_crc != 0:
        f.seek(0)
        crc, remaining = 0, de_off
        while remaining > 0:
            block = f.read(min(remaining, 1 << 22))
            if not block:
                break
            crc = zlib.crc32(block, crc)
            remaining -= len(block)
        if crc != data_end.data_section_crc:
            for off, _ in idx.chunks:  # name the damaged chunk when the damage is inside one
                list(_chunk_messages(f, path, off, size))
            raise CorruptMcapError(path, f"data section CRC mismatch (expected {data_end.data_section_crc:#010x}, "
                                   f"got {crc:#010x}); the damage is outside the chunk payloads, in bytes "
                                   f"[0, {de_off})")
    return idx


def _record_at(f: io.BufferedReader, offset: int, path: Path, size: int) -> Any:
    """Parses the single record at ``offset`` (Header, Metadata or Chunk)."""
    head = _read_exact(f, offset, 9, path, "record header")
    opcode, length = struct.unpack("<BQ", head)
    if offset + 9 + length > size:
        raise CorruptMcapError(path, f"record length {length} runs past the end of the file ({size} bytes)", offset)
    body = _read_exact(f, offset + 9, length, path, "record")
    stream = ReadDataStream(io.BytesIO(body))
    if opcode == Opcode.METADATA:
        return Metadata.read(stream)
    if opcode == Opcode.CHUNK:
        return Chunk.read(stream)
    if opcode == Opcode.HEADER:
        return Header.read(stream)
    raise CorruptMcapError(path, f"unexpected record opcode {opcode:#04x}", offset)


def _chunk_messages(f: io.BufferedReader, path: Path, offset: int, size: int) -> list[Message]:
    """The messages of the chunk at ``offset``, after decompression and CRC validation."""
    try:
        chunk = _record_at(f, offset, path, size)
        if not isinstance(chunk, Chunk):
            raise CorruptMcapError(path, f"chunk index points at a {type(chunk).__name__}", offset)
        records = breakup_chunk(chunk, validate_crc=True)
    except CorruptMcapError:
        raise
    except DECODE_ERRORS as e:
        kind = "CRC mismatch" if "crc" in str(e).lower() else "cannot be decoded"
        raise CorruptMcapError(path, f"damaged chunk ({kind}: {type(e).__name__}: {e})", offset) from e
    return [r for r in records if isinstance(r, Message)]


def _guard(path: Path, what: str) -> contextlib.AbstractContextManager[None]:
    """Re-raises decoder exceptions as CorruptMcapError naming ``path``."""

    @contextlib.contextmanager
    def cm() -> Iterator[None]:
        try:
            yield
        except (CorruptArtifactError, InputMissingError):
            raise
        except DECODE_ERRORS as e:
            raise CorruptMcapError(path, f"{what}: {type(e).__name__}: {e}") from e

    return cm()


def _check_episode_channels(idx: _Index, path: Path) -> dict[str, int]:
    """topic → channel id, checking every topic exists with the expected schema."""
    by_topic = {ch.topic: cid for cid, ch in idx.channels.items()}
    for topic in all_topics():
        if topic not in by_topic:
            raise CorruptMcapError(path, f"not an episode log: no channel {topic}")
        ch = idx.channels[by_topic[topic]]
        schema = idx.schemas.get(ch.schema_id)
        want = expected_schema_name(topic)
        if schema is None or schema.name != want:
            raise CorruptMcapError(path, f"channel {topic}: expected schema {want}, got "
                                   f"{schema.name if schema else 'none'}")
    return by_topic


def _iter_frame_messages(path: Path, idx: _Index, f: io.BufferedReader) -> Iterator[tuple[int, dict[str, bytes]]]:
    """(log_time, topic → payload) per frame, reading chunks in file order with CRC validation.

    Raises:
        CorruptMcapError: a damaged chunk, a message on an unknown channel, log times going backwards or a topic
            logged twice in one frame.
    """
    cur_t: int | None = None
    cur: dict[str, bytes] = {}
    for off, _ in idx.chunks:
        for m in _chunk_messages(f, path, off, idx.size):
            topic = idx.topic_of.get(m.channel_id)
            if topic is None:
                raise CorruptMcapError(path, f"message on unknown channel {m.channel_id}", off)
            if cur_t is None or m.log_time != cur_t:
                if cur_t is not None:
                    if m.log_time < cur_t:
                        raise CorruptMcapError(path, f"log time goes backwards ({m.log_time} ns after {cur_t} ns)",
                                               off)
                    yield cur_t, cur
                cur_t, cur = m.log_time, {}
            if topic in cur:
                raise CorruptMcapError(path, f"topic {topic} logged twice at t={m.log_time} ns", off)
            cur[topic] = m.data
    if cur_t is not None:
        yield cur_t, cur



class EpisodeReader:
    """Reads a complete episode MCAP back into frames (a seeking reader with CRC validation).

    Opening validates the magic, footer, summary CRC and data-section CRC and reads the metadata and the occupancy
    grid; :meth:`frames` then validates every chunk's CRC as it reads it. No file handle is held between calls.

    Attributes:
        path: The file.
        meta: The :class:`EpisodeMeta` from the ``episode`` metadata record.
        occupancy: ``H x W`` bool static occupancy (True = obstacle), as :class:`recorder.drive.Episode` has it.
        n_frames: Frames in the file (from the summary statistics).
        metadata: Every metadata record, name → str map (``episode``, and ``aborted``/``recovery`` if present).
        library: The MCAP header's library string.
        message_counts: topic → message count (summary statistics).

    Raises (on construction):
        InputMissingError: the file does not exist.
        CorruptMcapError: the file is truncated, fails a CRC check or is not an episode log.
    """

    def __init__(self, path: Path) -> None:
        self.path = require_file(Path(path))
        with open(self.path, "rb") as f, _guard(self.path, "cannot read the MCAP summary"):
            self._idx = _open_index(f, self.path)
            self._by_topic = _check_episode_channels(self._idx, self.path)
            if METADATA_EPISODE not in self._idx.metadata:
                raise CorruptMcapError(self.path, f"no '{METADATA_EPISODE}' metadata record")
            try:
                self.meta = EpisodeMeta.from_metadata(self._idx.metadata[METADATA_EPISODE])
            except (TypeError, ValueError) as e:
                raise CorruptMcapError(self.path, f"'{METADATA_EPISODE}' metadata is malformed: {e}") from e
            self.occupancy = self._read_occupancy(f)
        self.metadata = self._idx.metadata
        self.library = self._idx.header.library
        self.message_counts = dict(self._idx.message_counts)
        self.n_frames = int(self.message_counts.get(TOPIC_ROBOT, 0))

    def _read_occupancy(self, f: io.BufferedReader) -> np.ndarray:
        """The grid logged at t = 0 (the first message of this writer's first chunk; other writers may put it
        later in frame 0, so chunks are read until the frame at t = 0 is over)."""
        if not self._idx.chunks:
            raise CorruptMcapError(self.path, "no chunks: the episode has no frames")
        cid = self._by_topic[TOPIC_OCCUPANCY]
        for off, _ in self._idx.chunks:
            for m in _chunk_messages(f, self.path, off, self._idx.size):
                if m.channel_id == cid and m.log_time == 0:
                    try:
                        return decode_grid(m.data, list(self.meta.occupancy_shape))
                    except DECODE_ERRORS as e:
                        raise CorruptMcapError(self.path, f"{TOPIC_OCCUPANCY}: {e}", off) from e
                if m.log_time > 0:
                    raise CorruptMcapError(self.path, f"no {TOPIC_OCCUPANCY} message at t = 0", off)
        raise CorruptMcapError(self.path, f"no {TOPIC_OCCUPANCY} message at t = 0")

    def frames(self) -> Iterator[Frame]:
        """Yields the frames in log-time order, equal to what was written (depth within 0.5 mm).

        Raises:
            CorruptMcapError: a chunk fails its CRC, a frame misses topics or a payload does not decode.
        """
        dt = dt_ns_of(self.meta)
        with open(self.path, "rb") as f:
            k = 0
            for t, msgs in _iter_frame_messages(self.path, self._idx, f):
                missing = [tp for tp in frame_topics(first=t == 0) if tp not in msgs]
                if missing:
                    raise CorruptMcapError(self.path, f"frame at t={t} ns misses topics {missing}")
                if t != k * dt:
                    raise CorruptMcapError(self.path, f"frame {k} has log time {t} ns, expected {k * dt} ns")
                try:
                    fr = decode_frame(msgs, t)
                except DECODE_ERRORS as e:
                    raise CorruptMcapError(self.path, f"frame at t={t} ns does not decode: "
                                           f"{type(e).__name__}: {e}") from e
                yield fr
                k += 1

    def __len__(self) -> int:
        return self.n_frames


def read_episode(path: Path) -> tuple[EpisodeMeta, np.ndarray, Iterator[Frame]]:
    """Opens a complete episode MCAP.

    Args:
        path: ``<name>.mcap``.

    Returns:
        ``(meta, occupancy H x W bool, frames)`` where ``frames`` lazily yields the :class:`Frame` objects.

    Raises:
        InputMissingError: the file does not exist.
        CorruptMcapError: the file is truncated, fails a CRC check or is not an episode log (also while
            iterating the frames).
    """
    r = EpisodeReader(path)
    return r.meta, r.occupancy, r.frames()


def count_frames(path: Path) -> int:
    """Frames in a complete episode MCAP, from its (CRC-checked) summary without decompressing chunks."""
    return EpisodeReader(path).n_frames


# --------------------------------------------------------------------------------------------------------------
# scanning (doctor, summaries)


@dataclass
class EpisodeScan:
    """What a full CRC-validated pass over an episode file found (images are not decoded).

    Attributes:
        path: The file.
        meta: The episode metadata, or None when the record is missing or malformed.
        metadata_names: Names of all metadata records.
        library: The MCAP header's library string.
        log_times: Log time of each frame, ns, in file order.
        steps: ``step`` of each frame from /robot/state (−1 where missing).
        missing: ``(log_time, [topics])`` for each frame that misses topics.
        done: ``done`` of each frame from /episode/reward (False where missing).
        outcome: The last frame's outcome.
        topic_counts: topic → message count (counted, not taken from the summary).
        size_bytes: File size.
    """

    path: Path
    meta: EpisodeMeta | None
    metadata_names: list[str]
    library: str
    log_times: list[int] = field(default_factory=list)
    steps: list[int] = field(default_factory=list)
    missing: list[tuple[int, list[str]]] = field(default_factory=list)
    done: list[bool] = field(default_factory=list)
    outcome: str = ""
    topic_counts: dict[str, int] = field(default_factory=dict)
    size_bytes: int = 0

    @property
    def n_frames(self) -> int:
        return len(self.log_times)


def scan_episode(path: Path) -> EpisodeScan:
    """Reads every chunk of a complete episode MCAP with CRC validation, decoding only the small JSON topics.

    Unlike :class:`EpisodeReader` it does not stop at the first missing topic or bad time step: it records them
    (``missing``, ``log_times``, ``steps``) for :mod:`recorder.doctor_mcap`.

    Raises:
        InputMissingError: the file does not exist.
        CorruptMcapError: the file cannot be opened or a chunk fails its CRC / does not decode.
    """
    path = require_file(Path(path))
    with open(path, "rb") as f, _guard(path, "cannot scan"):
        idx = _open_index(f, path)
        meta: EpisodeMeta | None = None
        if METADATA_EPISODE in idx.metadata:
            with contextlib.suppress(TypeError, ValueError):
                meta = EpisodeMeta.from_metadata(idx.metadata[METADATA_EPISODE])
        scan = EpisodeScan(path=path, meta=meta, metadata_names=sorted(idx.metadata), library=idx.header.library,
                           size_bytes=idx.size)
        for t, msgs in _iter_frame_messages(path, idx, f):
            scan.log_times.append(t)
            for topic in msgs:
                scan.topic_counts[topic] = scan.topic_counts.get(topic, 0) + 1
            miss = [tp for tp in frame_topics(first=t == 0) if tp not in msgs]
            if miss:
                scan.missing.append((t, miss))
            try:
                step = json.loads(msgs[TOPIC_ROBOT])["step"] if TOPIC_ROBOT in msgs else -1
                rew = json.loads(msgs[TOPIC_REWARD]) if TOPIC_REWARD in msgs else {}
            except DECODE_ERRORS as e:
                raise CorruptMcapError(path, f"frame at t={t} ns: JSON does not decode: {e}") from e
            scan.steps.append(int(step))
            scan.done.append(bool(rew.get("done", False)))
            scan.outcome = str(rew.get("outcome", ""))
    return scan


def episode_summary(path: Path) -> dict[str, Any]:
    """A CRC-validated summary of a complete episode MCAP.

    Returns:
        ``{"path", "n_frames", "outcome", "done", "duration_s", "topics": {topic: count}, "bytes", "scene",
        "seed", "aborted", "recovered"}``; ``duration_s`` is the last log time in seconds.

    Raises:
        InputMissingError, CorruptMcapError: as :func:`scan_episode`.
    """
    s = scan_episode(path)
    return {"path": str(s.path), "n_frames": s.n_frames, "outcome": s.outcome, "done": bool(s.done and s.done[-1]),
            "duration_s": (s.log_times[-1] / 1e9) if s.log_times else 0.0, "topics": dict(sorted(s.topic_counts.items())),
            "bytes": s.size_bytes, "scene": s.meta.scene if s.meta else None, "seed": s.meta.seed if s.meta else None,
            "aborted": METADATA_ABORTED in s.metadata_names, "recovered": METADATA_RECOVERY in s.metadata_names}
