"""The codec of ``lsl://`` frames, and what an LSL stream's XML description says.

The frame layout is the transport's (``devices.transports.lsl``: one frame per pulled chunk of
samples, a header with its CRC-32, the samples' LSL timestamps and values, the payload's CRC-32);
this codec parses it from any chunking of the bytes and ``encode`` writes it. A frame whose header
is damaged (bad CRC, an unknown version or format, counts that do not match its length) or whose
payload fails its CRC is one counted error; the codec then looks for the next magic from the byte
after the bad frame's start, so the frames before and after the damage are kept (a frame cut short
holds the bytes after it until as many as it claims have come and its CRC fails; the frames among
them are then recovered).

``parse_info_xml`` reads LSL's stream description (``<info>``: name, type, channel_count,
nominal_srate, channel_format, source_id, hostname, and ``desc/channels/channel/label|unit``), which
sessions keep so a replay declares the same streams with no LSL present.
"""

from __future__ import annotations

import struct
import xml.etree.ElementTree as ET
import zlib
from dataclasses import dataclass
from typing import ClassVar, Final, NamedTuple

import numpy as np

from capture.errors import ConfigError
from devices.codecs.base import Codec
from devices.transports.lsl import FORMAT_CODES, FORMATS, HEADER, HEADER_SIZE, MAGIC, VERSION, pack_frame

#: the largest payload accepted, bytes (a header claiming more is damaged)
MAX_PAYLOAD: Final = 64 << 20
#: the most channels accepted
MAX_CHANNELS: Final = 1 << 16
_U32 = struct.Struct("<I")


class LslFrame(NamedTuple):
    """One pulled chunk: ``timestamps`` (n,) float64 LSL seconds; ``values`` an (n, channels) array
    of the stream's type, or for a string stream n tuples of ``channels`` str."""

    fmt: int
    channels: int
    timestamps: np.ndarray
    values: np.ndarray | tuple[tuple[str, ...], ...]


class _BadFrameError(Exception):
    """Why a frame is refused (counted by ``feed``)."""


class LslCodec(Codec):
    """Parses ``lsl://`` frames (module docstring); ``encode`` is their writer."""

    name: ClassVar[str] = "lsl"

    def __init__(self, strict: bool = False) -> None:
        super().__init__(strict)
        #: looking for the next frame after garbage or a bad frame (already counted once)
        self._resync = False

    def reset(self) -> int:
        self._resync = False
        return super().reset()

    def feed(self, data: bytes) -> list[LslFrame]:
        buf = self._buf
        buf += data
        self.stats.bytes_in += len(data)
        out: list[LslFrame] = []
        pos = 0
        while True:
            start = buf.find(MAGIC, pos)
            if start < 0:  # keep what could be the start of a magic
                keep = max(pos, len(buf) - (len(MAGIC) - 1))
                if keep > pos:
                    self._skip(pos, keep, buf)
                pos = keep
                break
            if start > pos:
                self._skip(pos, start, buf)
            pos = start
            if len(buf) - pos < HEADER_SIZE:
                break
            try:
                size = self._frame_size(buf, pos)
                if len(buf) - pos < size:
                    break
                frame = self._parse(bytes(buf[pos:pos + size]))
            except _BadFrameError as exc:
                self._bad("checksum" if "CRC" in str(exc) else "framing", str(exc), pos, bytes(buf[pos:pos + 64]))
                self.stats.skipped_bytes += 1
                self._resync = True  # the bytes up to the next magic are this error's, not another
                pos += 1
                continue
            self._resync = False
            out.append(frame)
            self.stats.frames += 1
            pos += size
        del buf[:pos]
        return out

    def _skip(self, a: int, b: int, buf: bytearray) -> None:
        self.stats.skipped_bytes += b - a
        if not self._resync:
            self._resync = True
            self._bad("framing", f"{b - a} bytes that are not an LSL frame", a, bytes(buf[a:min(b, a + 64)]))

    @staticmethod
    def _frame_size(buf: bytearray, pos: int) -> int:
        """The whole frame's length from a header at ``pos`` (checked)."""
        head = bytes(buf[pos:pos + HEADER.size])
        (crc,) = _U32.unpack_from(buf, pos + HEADER.size)
        if zlib.crc32(head) != crc:
            raise _BadFrameError("LSL frame header fails its CRC")
        _, version, fmt, _, channels, n, length = HEADER.unpack(head)
        if version != VERSION:
            raise _BadFrameError(f"LSL frame of version {version} (this codec reads {VERSION})")
        if fmt not in FORMATS:
            raise _BadFrameError(f"LSL frame of unknown channel format {fmt}")
        if not 1 <= channels <= MAX_CHANNELS:
            raise _BadFrameError(f"LSL frame of {channels} channels")
        dtype = FORMATS[fmt][1]
        fixed = n * 8 + n * channels * (np.dtype(dtype).itemsize if dtype else 4)
        if length > MAX_PAYLOAD or (length != fixed if dtype else length < fixed):
            raise _BadFrameError(f"LSL frame of {n} samples x {channels} channels cannot hold {length} payload bytes")
        return HEADER_SIZE + length + 4

    @staticmethod
    def _parse(frame: bytes) -> LslFrame:
        _, _, fmt, _, channels, n, length = HEADER.unpack_from(frame)
        payload = frame[HEADER_SIZE:HEADER_SIZE + length]
        (crc,) = _U32.unpack_from(frame, HEADER_SIZE + length)
        if zlib.crc32(payload) != crc:
            raise _BadFrameError("LSL frame payload fails its CRC")
        ts = np.frombuffer(payload, "<f8", n).astype(np.float64)
        if n and not np.isfinite(ts).all():
            raise _BadFrameError("LSL frame with a timestamp that is not finite")
        dtype = FORMATS[fmt][1]
        if dtype is not None:
            values = np.frombuffer(payload, dtype, n * channels, n * 8).reshape(n, channels)
            return LslFrame(fmt, channels, ts, values)
        rows: list[tuple[str, ...]] = []
        pos = n * 8
        try:
            for _ in range(n):
                row = []
                for _ in range(channels):
                    (k,) = _U32.unpack_from(payload, pos)
                    if pos + 4 + k > length:
                        raise _BadFrameError("LSL frame with a string longer than its payload")
                    row.append(payload[pos + 4:pos + 4 + k].decode("utf-8"))
                    pos += 4 + k
                rows.append(tuple(row))
        except (struct.error, UnicodeDecodeError) as exc:
            raise _BadFrameError(f"LSL frame with bad string values ({exc})") from None
        if pos != length:
            raise _BadFrameError(f"LSL frame with {length - pos} bytes after its strings")
        return LslFrame(fmt, channels, ts, tuple(rows))

    def encode(self, frame: LslFrame) -> bytes:
        return pack_frame(frame.fmt, frame.channels, frame.timestamps, frame.values)


# -- the stream description --------------------------------------------------------------------------
@dataclass(frozen=True)
class LslDescription:
    """What an LSL stream says about itself. ``rate_hz`` is None for an irregular stream (LSL's 0)."""

    name: str
    type: str
    channel_count: int
    rate_hz: float | None
    format: str
    source_id: str
    hostname: str
    labels: tuple[str, ...]
    units: tuple[str, ...]
    #: what a perfcap sender says of the stream (``desc/perfcap``): its kind and frame ("" from others)
    kind: str = ""
    frame: str = ""

    @property
    def format_code(self) -> int:
        return FORMAT_CODES[self.format]


def parse_info_xml(xml: str, where: str = "LSL stream description") -> LslDescription:
    """The description in LSL's stream XML; labels and units are "" where the XML has none.

    Raises:
        ConfigError: it is not LSL's XML, or its channel count, rate or format is unusable.
    """
    try:
        root = ET.fromstring(xml)  # the sender's own description (no entity expansion)
    except ET.ParseError as exc:
        raise ConfigError(f"{where}: not XML ({exc})") from None
    if root.tag != "info":
        raise ConfigError(f"{where}: not an LSL stream description (<{root.tag}>, not <info>)")

    def text(el: ET.Element | None, tag: str) -> str:
        c = None if el is None else el.find(tag)
        return (c.text or "").strip() if c is not None else ""

    try:
        count = int(text(root, "channel_count"))
        rate = float(text(root, "nominal_srate") or 0)
    except ValueError:
        raise ConfigError(f"{where}: channel_count or nominal_srate is not a number") from None
    fmt = text(root, "channel_format")
    if not 1 <= count <= MAX_CHANNELS or not (rate >= 0 and rate < float("inf")):
        raise ConfigError(f"{where}: {count} channels at {rate} Hz cannot be a stream")
    if fmt not in FORMAT_CODES:
        raise ConfigError(f"{where}: unknown channel format {fmt!r} (LSL's: {', '.join(FORMAT_CODES)})")
    chans = root.findall("desc/channels/channel")[:count]
    labels = [text(c, "label") for c in chans] + [""] * (count - len(chans))
    units = [text(c, "unit") for c in chans] + [""] * (count - len(chans))
    meta = root.find("desc/perfcap")
    return LslDescription(text(root, "name"), text(root, "type"), count, rate or None, fmt,
                          text(root, "source_id"), text(root, "hostname"), tuple(labels), tuple(units),
                          text(meta, "kind"), text(meta, "frame"))


__all__ = ["MAX_PAYLOAD", "LslCodec", "LslDescription", "LslFrame", "parse_info_xml"]
