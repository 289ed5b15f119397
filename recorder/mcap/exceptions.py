"""The error of a damaged episode MCAP, and the exceptions that decoders raise on damaged bytes."""

from __future__ import annotations

import struct
from pathlib import Path

from google.protobuf.message import DecodeError
from mcap.exceptions import McapError

from pipeline.core.errors import CorruptArtifactError

# Everything a damaged file can make the mcap/protobuf/json/zstd/lz4 decoders raise. Caught only around decoding
# and re-raised as CorruptMcapError naming the file; any other exception is a bug and propagates.
DECODE_ERRORS: tuple[type[BaseException], ...] = (McapError, struct.error, ValueError, KeyError, IndexError,
                                                  EOFError, DecodeError, OverflowError, MemoryError,
                                                  UnicodeDecodeError, RuntimeError, TypeError)
try:  # zstandard.ZstdError derives from Exception only
    import zstandard

    DECODE_ERRORS = (*DECODE_ERRORS, zstandard.ZstdError)
except ImportError:  # pragma: no cover - zstandard is a dependency of mcap here
    pass


class CorruptMcapError(CorruptArtifactError):
    """An episode MCAP exists but is truncated, fails a CRC check or does not hold a well-formed episode.

    Attributes:
        path: The file.
        offset: Byte offset of the damaged record where known, else None.
    """

    def __init__(self, path: Path | str, what: str, offset: int | None = None) -> None:
        self.path = Path(path)
        self.offset = offset
        where = f" at byte offset {offset}" if offset is not None else ""
        super().__init__(f"{self.path}: {what}{where}")
