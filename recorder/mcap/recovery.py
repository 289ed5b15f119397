"""Salvage of unfinished episodes: :func:`recover` copies the complete frames of a ``*.mcap.partial`` (a killed or
aborted recording) into a new, valid ``<name>.recovered.mcap``.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk
from mcap.writer import Writer as McapWriter

from pipeline.core.errors import OutputExistsError
from recorder.mcap.exceptions import DECODE_ERRORS, CorruptMcapError
from recorder.mcap.layout import LIBRARY, MAGIC, METADATA_RECOVERY, dt_ns_of, frame_topics, recovered_path_of
from recorder.mcap.reader import EpisodeReader, require_file
from recorder.mcap.writer import (
    COMPRESSIONS,
    DEFAULT_CHUNK_SIZE,
    DEFAULT_COMPRESSION,
    FdStream,
    publish_no_clobber,
)
from recorder.schema import METADATA_EPISODE, EpisodeMeta

log = logging.getLogger("icrowdnav")


@dataclass
class _Salvage:
    """What a linear pass over a possibly truncated file recovered."""

    metadata: list[Metadata] = field(default_factory=list)
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: list[Message] = field(default_factory=list)
    chunks_ok: int = 0
    stop_offset: int = 0
    stop_reason: str = "end of file"
    complete: bool = False


def _linear_salvage(path: Path) -> _Salvage:
    """Reads records front to back without seeking, keeping every complete, CRC-valid chunk before the damage.

    Stops at the first incomplete record (the file ends inside it), the first chunk that fails its CRC or does
    not decompress, or the footer. Chunks after damage are not used, so an episode never gets a hole.
    """
    out = _Salvage()
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if f.read(len(MAGIC)) != MAGIC:
            raise CorruptMcapError(path, "not an MCAP file (bad leading magic); nothing to salvage", 0)
        off = len(MAGIC)
        while True:
            out.stop_offset = off
            head = f.read(9)
            if len(head) < 9:
                out.stop_reason = "file ends" + (" inside a record header" if head else "")
                return out
            opcode, length = struct.unpack("<BQ", head)
            if length > size - off - 9:
                out.stop_reason = f"file ends inside a {_opname(opcode)} record ({length} bytes)"
                return out
            body = f.read(length)
            stream = ReadDataStream(io.BytesIO(body))
            try:
                if opcode == Opcode.CHUNK:
                    records = breakup_chunk(Chunk.read(stream), validate_crc=True)
                    for r in records:
                        if isinstance(r, Schema):
                            out.schemas[r.id] = r
                        elif isinstance(r, Channel):
                            out.channels[r.id] = r
                        elif isinstance(r, Message):
                            out.messages.append(r)
                    out.chunks_ok += 1
                elif opcode == Opcode.METADATA:
                    out.metadata.append(Metadata.read(stream))
                elif opcode == Opcode.FOOTER:
                    out.complete = True
                    out.stop_reason = "footer (the file is complete)"
                    return out
                elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):  # unchunked schema/channel records
                    r = Schema.read(stream) if opcode == Opcode.SCHEMA else Channel.read(stream)
                    (out.schemas if isinstance(r, Schema) else out.channels)[r.id] = r  # type: ignore[index]
                elif opcode == Opcode.DATA_END:
                    out.stop_reason = "end of the data section"
                    return out  # the summary holds nothing that is not already salvaged
            except DECODE_ERRORS as e:
                out.stop_reason = f"damaged {_opname(opcode)} record ({type(e).__name__}: {e})"
                return out
            off += 9 + length


def _opname(opcode: int) -> str:
    try:
        return Opcode(opcode).name.lower()
    except ValueError:
        return f"unknown (opcode {opcode:#04x})"


def recover(partial_path: Path, *, chunk_size: int = DEFAULT_CHUNK_SIZE,
            compression: str = DEFAULT_COMPRESSION) -> Path:
    """Salvages the complete frames of an unfinished episode into a new, valid ``<name>.recovered.mcap``.

    A linear (non-seeking) pass keeps every complete, CRC-valid chunk up to the first damage (see
    :func:`_linear_salvage`); frames are the log times whose full topic set is present, and only the leading run of
    complete frames (t = 0, dt, 2 dt, ...) is kept, so a trailing incomplete frame is dropped. Payloads are copied
    byte for byte; the ``episode`` metadata is kept and a ``recovery`` record says what was salvaged. The result
    is written to a temporary name, re-opened with CRC validation and read through, and then published without
    ever replacing an existing file. The ``.partial`` is left untouched.

    Args:
        partial_path: ``<name>.mcap.partial`` (any MCAP path works, e.g. a truncated copy).
        chunk_size, compression: As for :class:`EpisodeWriter`.

    Returns:
        The recovered file ``<name>.recovered.mcap``.

    Raises:
        InputMissingError: ``partial_path`` does not exist.
        OutputExistsError: ``<name>.recovered.mcap`` exists already.
        CorruptMcapError: not an MCAP, no ``episode`` metadata, or not a single complete frame to salvage.
    """
    src = require_file(Path(partial_path))
    dst = recovered_path_of(src)
    if dst.exists():
        raise OutputExistsError(f"{dst} already exists; refusing to overwrite it (delete it to recover {src} again)")
    sal = _linear_salvage(src)
    meta_rec = next((m for m in sal.metadata if m.name == METADATA_EPISODE), None)
    if meta_rec is None:
        raise CorruptMcapError(src, f"no '{METADATA_EPISODE}' metadata record before the damage "
                               f"({sal.stop_reason}); nothing to salvage", sal.stop_offset)
    try:
        meta = EpisodeMeta.from_metadata(dict(meta_rec.metadata))
    except (TypeError, ValueError) as e:
        raise CorruptMcapError(src, f"'{METADATA_EPISODE}' metadata is malformed: {e}") from e
    dt = dt_ns_of(meta)
    topic_of = {cid: ch.topic for cid, ch in sal.channels.items()}
    by_time: dict[int, dict[str, Message]] = {}
    for m in sal.messages:
        topic = topic_of.get(m.channel_id)
        if topic is not None:
            by_time.setdefault(m.log_time, {}).setdefault(topic, m)
    n = 0
    while n * dt in by_time and all(tp in by_time[n * dt] for tp in frame_topics(first=n == 0)):
        n += 1
    if n == 0:
        raise CorruptMcapError(src, f"no complete frame before the damage ({sal.chunks_ok} complete chunks, "
                               f"stopped at: {sal.stop_reason}); nothing to salvage", sal.stop_offset)
    dropped = len([t for t in by_time if t >= n * dt])

    tmp = dst.with_name(f".{dst.name}.tmp-{os.getpid()}")
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        w = McapWriter(FdStream(fd), chunk_size=1 << 62, compression=COMPRESSIONS[compression],
                       enable_crcs=True, enable_data_crcs=True)
        w.start(profile="", library=LIBRARY)
        w.add_metadata(METADATA_EPISODE, dict(meta_rec.metadata))
        w.add_metadata(METADATA_RECOVERY, {"source": src.name, "frames_salvaged": str(n),
                                           "complete_chunks": str(sal.chunks_ok), "stopped_at": sal.stop_reason,
                                           "stop_offset": str(sal.stop_offset),
                                           "incomplete_frames_dropped": str(dropped)})
        new_schema: dict[int, int] = {}
        for sid in sorted(sal.schemas):
            s = sal.schemas[sid]
            new_schema[sid] = w.register_schema(name=s.name, encoding=s.encoding, data=s.data)
        new_channel: dict[str, int] = {}
        for cid in sorted(sal.channels):
            ch = sal.channels[cid]
            if ch.topic in new_channel:
                continue
            new_channel[ch.topic] = w.register_channel(topic=ch.topic, message_encoding=ch.message_encoding,
                                                       schema_id=new_schema.get(ch.schema_id, 0),
                                                       metadata=dict(ch.metadata))
        pending = 0
        for k in range(n):
            wanted = set(frame_topics(first=k == 0))
            for topic, m in by_time[k * dt].items():  # in the source's order
                if topic not in wanted:
                    continue
                w.add_message(new_channel[topic], log_time=m.log_time, data=m.data, publish_time=m.publish_time,
                              sequence=m.sequence)
                pending += len(m.data)
            if pending >= chunk_size:
                w.flush()
                pending = 0
        w.finish()
        os.fsync(fd)
    except BaseException:
        os.close(fd)
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    os.close(fd)
    try:  # verify before publishing: CRCs, summary and every frame decode
        r = EpisodeReader(tmp)
        got = sum(1 for _ in r.frames())
        if got != n:
            raise CorruptMcapError(tmp, f"recovered file holds {got} frames, expected {n}")
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    publish_no_clobber(tmp, dst)
    log.info("recovered %d frames (t = 0 .. %.2f s) of %s into %s; %d complete chunks, stopped at: %s",
             n, (n - 1) * dt / 1e9, src.name, dst.name, sal.chunks_ok, sal.stop_reason)
    return dst
