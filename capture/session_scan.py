"""Reading the records of an MCAP session around damage, within bounds the file itself sets.

Owns: the record-by-record walk over a session file (``scan_records``), the resynchronisation that
skips a damaged record or chunk to the next one that parses (the summary's chunk index first, else
a forward search), the bounds on what a record may claim (every length within the file, every
chunk's decompressed size within ``chunk_budget`` and the whole file's within ``total_budget``),
and the redundant copy of a session's definitions (``perfcap.definitions``: session metadata,
devices and channels, with its own CRC) that the writer repeats so no single chunk or record holds
the only copy.

The records themselves are parsed by the ``mcap`` library's readers (``Chunk.read``,
``Channel.read``, ``breakup_chunk``, ...); this module only frames them (opcode, length) and checks
that each one consumed exactly its length, which is what lets a damaged one be told from a good one.
"""

from __future__ import annotations

import functools
import io
import json
import mmap
import re
import struct
import zlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from capture.session_file import MCAP_MAGIC

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator

DEFINITIONS = "perfcap.definitions"

#: a chunk may decompress to at most max(CHUNK_FLOOR, CHUNK_RATIO x its compressed size) ...
CHUNK_FLOOR = 32 << 20
CHUNK_RATIO = 64
#: ... and all chunks together (attempts included) to max(TOTAL_FLOOR, CHUNK_RATIO x the file size)
TOTAL_FLOOR = 128 << 20

_hdr = struct.Struct("<BQ")
# a record header whose length fits in 5 bytes (under 1 TiB): where a resync may look
_candidate = re.compile(rb"(?=[\x01-\x04\x06-\x0f][\s\S]{5}\x00\x00\x00)")


@functools.cache
def _readers() -> dict[int, Any]:
    """mcap's reader of each record type, by opcode."""
    from mcap.records import (
        Attachment,
        AttachmentIndex,
        Channel,
        Chunk,
        ChunkIndex,
        DataEnd,
        Footer,
        Header,
        MessageIndex,
        Metadata,
        MetadataIndex,
        Schema,
        Statistics,
        SummaryOffset,
    )

    return {
        0x01: Header.read, 0x02: Footer.read, 0x03: Schema.read, 0x04: Channel.read, 0x06: Chunk.read,
        0x07: MessageIndex.read, 0x08: ChunkIndex.read, 0x09: Attachment.read, 0x0A: AttachmentIndex.read,
        0x0B: Statistics.read, 0x0C: Metadata.read, 0x0D: MetadataIndex.read, 0x0E: SummaryOffset.read,
        0x0F: DataEnd.read}


def chunk_budget(compressed: int) -> int:
    return max(CHUNK_FLOOR, CHUNK_RATIO * compressed)


def total_budget(file_size: int) -> int:
    return max(TOTAL_FLOOR, CHUNK_RATIO * file_size)


def encode_definitions(defs: dict[str, Any]) -> dict[str, str]:
    """The metadata of a ``perfcap.definitions`` record: the definitions as JSON and their CRC-32."""
    text = json.dumps(defs, sort_keys=True)
    return {"json": text, "crc32": str(zlib.crc32(text.encode()))}


def decode_definitions(m: dict[str, str]) -> dict[str, Any]:
    """The definitions of a ``perfcap.definitions`` record.

    Raises:
        ValueError: the record is damaged (its CRC does not match, or it does not parse).
    """
    text = m["json"]
    if str(zlib.crc32(text.encode())) != m.get("crc32"):
        raise ValueError("CRC mismatch")
    defs = json.loads(text)
    if not isinstance(defs, dict):
        raise ValueError("not an object")
    return defs


@dataclass
class ScanResult:
    """What the walk over a file found besides the records it yielded."""

    header_profile: str | None = None
    truncated: str | None = None
    data_end: bool = False
    footer: bool = False
    summary_crc_ok: bool | None = None
    skipped_bytes: int = 0
    #: (first byte, end byte) of each region skipped as damaged
    damaged_regions: list[tuple[int, int]] = field(default_factory=list)


class RecordScanner:
    """Walks the top-level records of an MCAP file held in ``mm``.

    Args:
        mm: the file's bytes (an mmap or bytes).
        damage: called as ``damage(what, why)`` for every damaged record or region skipped.
        progress: called as ``progress(offset, size)`` now and then.
    """

    def __init__(self, mm: mmap.mmap | bytes, damage: Callable[[str, str], None],
                 progress: Callable[[int, int], Any] | None = None) -> None:
        self.mm = mm
        self.size = len(mm)
        self.damage = damage
        self.progress = progress
        self.result = ScanResult()
        self.budget = total_budget(self.size)
        self.hints: list[int] = []
        self._summary_hints()

    # -- the summary's chunk index: where chunks start, if the summary survived ---------------------
    def _summary_hints(self) -> None:
        from mcap.records import ChunkIndex, Footer

        end = self.size - len(MCAP_MAGIC) - _hdr.size - 20
        if end < len(MCAP_MAGIC) or self.mm[self.size - len(MCAP_MAGIC):] != MCAP_MAGIC:
            return
        op, length = _hdr.unpack_from(self.mm, end)
        if op != 0x02 or length != 20:
            return
        from mcap.data_stream import ReadDataStream

        footer = Footer.read(ReadDataStream(io.BytesIO(self.mm[end + _hdr.size:end + _hdr.size + 20])))
        start = footer.summary_start
        if not 0 < start < end:
            return
        if footer.summary_crc:
            crc = zlib.crc32(self.mm[start:end + _hdr.size + 16])
            self.result.summary_crc_ok = crc == footer.summary_crc
        hints = []
        for _pos, op, rec in self._walk_plain(start, end):
            if op == 0x08 and isinstance(rec, ChunkIndex) and 8 <= rec.chunk_start_offset < start:
                hints.append(rec.chunk_start_offset)
        self.hints = sorted(set(hints))

    def _walk_plain(self, start: int, end: int) -> Iterator[tuple[int, int, Any]]:
        """Records between start and end that parse; stop at the first that does not."""
        pos = start
        while pos + _hdr.size <= end:
            op, length = _hdr.unpack_from(self.mm, pos)
            if length > end - pos - _hdr.size:
                return
            rec = self._parse(pos, op, length, strict=True, decompress=False)
            if rec is None:
                return
            yield pos, op, rec
            pos += _hdr.size + length

    # -- parsing one record -------------------------------------------------------------------------
    def _parse(self, pos: int, op: int, length: int, *, strict: bool, decompress: bool = True) -> Any:
        """The record at ``pos`` parsed by mcap, or None when it does not parse exactly (damaged).
        A chunk comes back as the list of its records (decompressed within the budgets)."""
        from mcap.data_stream import ReadDataStream

        reader = _readers().get(op)
        if reader is None:
            return None
        if op == 0x06 and not self._chunk_framed(pos, length):
            return None     # (checked before the body is copied: a false resync candidate costs little)
        body = self.mm[pos + _hdr.size:pos + _hdr.size + length]
        rds = ReadDataStream(io.BytesIO(body))
        try:
            rec = reader(rds)
        except Exception:
            return None
        if strict and rds.count != length:
            return None
        if op == 0x09 and len(body) >= 4:   # mcap does not check an attachment's CRC: do it here
            (crc,) = struct.unpack_from("<I", body, len(body) - 4)
            if crc and crc != zlib.crc32(body[:-4]):
                return None
        if op == 0x02 and pos + _hdr.size + length + len(MCAP_MAGIC) != self.size:
            return None
        if op == 0x06 and decompress:
            return self._chunk_records(pos, rec)
        return rec

    def _chunk_framed(self, pos: int, length: int) -> bool:
        """Whether a chunk's own lengths (compression name, records) add up to its record length."""
        o = pos + _hdr.size + 28
        if length < 40:
            return False
        (clen,) = struct.unpack_from("<I", self.mm, o)
        if clen > length - 40:
            return False
        (dlen,) = struct.unpack_from("<Q", self.mm, o + 4 + clen)
        return 28 + 4 + clen + 8 + dlen == length

    def _chunk_records(self, pos: int, chunk: Any) -> list[Any] | None:
        from mcap.records import Chunk
        from mcap.stream_reader import breakup_chunk

        limit = chunk_budget(len(chunk.data))
        if chunk.uncompressed_size > min(limit, self.budget):
            self.damage("MCAP chunk", f"the chunk at byte {pos} claims {chunk.uncompressed_size} bytes"
                        f" uncompressed from {len(chunk.data)}: more than this file can hold (refused)")
            return None
        self.budget -= chunk.uncompressed_size
        if chunk.compression == "zstd":
            import zstandard

            try:
                declared = zstandard.frame_content_size(chunk.data)
                if declared not in (-1, chunk.uncompressed_size):
                    return None
                data = zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size)
            except zstandard.ZstdError:
                return None
        elif chunk.compression == "":
            data = chunk.data
        else:
            self.damage("MCAP chunk", f"the chunk at byte {pos} is compressed with {chunk.compression!r},"
                        " which perfcap does not write (refused)")
            return None
        if len(data) != chunk.uncompressed_size:
            return None
        plain = Chunk(compression="", data=data, message_start_time=chunk.message_start_time,
                      message_end_time=chunk.message_end_time, uncompressed_crc=chunk.uncompressed_crc,
                      uncompressed_size=chunk.uncompressed_size)
        try:
            return breakup_chunk(plain, validate_crc=True)
        except Exception:
            return None

    # -- the walk -----------------------------------------------------------------------------------
    def _resync(self, after: int) -> tuple[int, int, int, Any] | None:
        """The first record after ``after`` that parses exactly (a summary hint or a forward search)."""
        hint = next((h for h in self.hints if h > after), None)
        limit = hint if hint is not None else self.size
        for m in _candidate.finditer(self.mm, after, limit):
            p = m.start()
            op, length = _hdr.unpack_from(self.mm, p)
            if length > self.size - p - _hdr.size:
                continue
            rec = self._parse(p, op, length, strict=True)
            if rec is not None:
                return p, op, length, rec
        if hint is not None:
            op, length = _hdr.unpack_from(self.mm, hint)
            if length <= self.size - hint - _hdr.size:
                rec = self._parse(hint, op, length, strict=True)
                if rec is not None:
                    return hint, op, length, rec
            return self._resync(hint)
        return None

    def records(self) -> Iterator[tuple[int, Any]]:
        """Yield (opcode, record) for every top-level record that parses; a chunk is yielded as
        (0x06, its records). Damaged stretches are skipped to the next good record and reported."""
        pos = len(MCAP_MAGIC)
        r = self.result
        step = max(1 << 20, self.size // 100)
        next_progress = step
        while True:
            if self.progress is not None and pos >= next_progress:
                self.progress(pos, self.size)
                next_progress = pos + step
            rec: Any = None
            if pos + _hdr.size <= self.size:
                op, length = _hdr.unpack_from(self.mm, pos)
                if length <= self.size - pos - _hdr.size:
                    rec = self._parse(pos, op, length, strict=True)
            elif pos >= self.size:
                if not r.data_end:
                    r.truncated = f"file ends at byte {pos} without the MCAP footer (recording cut short)"
                return
            if rec is None:
                found = self._resync(pos)
                if found is None:
                    if r.data_end:
                        self.damage("MCAP footer", f"nothing readable after byte {pos}")
                    else:
                        r.truncated = (f"file ends inside a record at byte {pos} (recording cut short)"
                                       if pos + _hdr.size <= self.size else
                                       f"file ends at byte {pos} without the MCAP footer (recording cut short)")
                    return
                p, op, length, rec = found
                r.skipped_bytes += p - pos
                r.damaged_regions.append((pos, p))
                self.damage("MCAP region", f"bytes {pos} to {p} do not parse (skipped to the next record)")
                pos = p
            if op == 0x01:
                r.header_profile = rec.profile
            elif op == 0x0F:
                r.data_end = True
            elif op == 0x02:
                r.footer = True
                if self.progress is not None:
                    self.progress(self.size, self.size)
                return
            yield op, rec
            pos += _hdr.size + length


def open_bytes(path: str) -> tuple[Any, mmap.mmap | bytes]:
    """The file opened and mapped (bytes for an empty one). The caller closes both."""
    f = open(path, "rb")  # closed by the caller
    try:
        size = f.seek(0, io.SEEK_END)
        mm: mmap.mmap | bytes = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if size else b""
    except BaseException:
        f.close()
        raise
    return f, mm
