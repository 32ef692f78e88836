"""The ``lsl://`` transport: a Lab Streaming Layer inlet as a byte pipe.

``lsl://NAME`` resolves the LSL stream of that name; ``lsl://?type=EEG&source_id=abc`` (any of
``name``, ``type`` and ``source_id`` as options, the address being ``name``) resolves the stream
that has all of them. The resolve waits up to ``timeout`` seconds; nothing found is a
``DeviceUnavailableError`` that names the query.

LSL hands over samples, not bytes, so this transport writes each pulled chunk of samples as one
frame of bytes, stamped with its arrival like any other transport's chunk; sessions record those
frames and ``replay://`` feeds them back through the same codec (``devices.codecs.lsl``) and device
(``devices.lsl``), with no LSL present. The frame, all little-endian::

    offset  size  field
    0       4     magic b"LSLc"
    4       1     version (1)
    5       1     channel format, LSL's code: 1 float32, 2 double64, 3 string, 4 int32,
                  5 int16, 6 int8, 7 int64
    6       2     reserved (0)
    8       4     channel count (>= 1)
    12      4     sample count n
    16      4     payload length, bytes
    20      4     CRC-32 of bytes 0..19
    24      ...   payload: n float64 LSL timestamps (seconds, the sender's clock), then the n x
                  channels values in sample order: numeric formats as their own type; strings as
                  u32 length + UTF-8 bytes each
    ...     4     CRC-32 of the payload

This module owns that layout (``pack_frame``; the codec parses it and its ``encode`` is this), the
transport, the listing of the LSL streams present for ``perfcap devices`` (``list_lsl_streams``)
and the loading of pylsl (which carries liblsl), done only when an LSL stream is wanted. The full
stream description (LSL's XML, with ``desc/channels``) is asked of the sender before open
(``stream_xml``) so the device can declare its streams before the first byte.

An inlet is made with LSL's silent recovery off: a sender that goes away makes ``read`` fail, so
the reader's reconnect policy gives the usual DISCONNECTED and RECONNECTED events; ``open`` then
resolves the stream again (by its ``source_id`` too, when it has one), and refuses a stream whose
channel count or format changed.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Final
from urllib.parse import quote

import numpy as np

from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError, DeviceInitError, DeviceIOError, DeviceUnavailableError
from capture.sample import Chunk
from devices.options import Option
from devices.transports.base import Transport

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence
    from types import ModuleType

MAGIC: Final = b"LSLc"
VERSION: Final = 1
#: how long a resolve that found its stream waits for a second one answering the same query, s
AMBIGUITY_WAIT_S = 0.5
#: magic, version, format, reserved, channels, count, payload length; then the header's CRC-32
HEADER: Final = struct.Struct("<4sBBHIII")
HEADER_SIZE: Final = HEADER.size + 4
STRING: Final = 3
#: LSL channel format code -> (LSL's name, little-endian numpy dtype; None for strings)
FORMATS: Final[dict[int, tuple[str, str | None]]] = {
    1: ("float32", "<f4"), 2: ("double64", "<f8"), 3: ("string", None), 4: ("int32", "<i4"),
    5: ("int16", "<i2"), 6: ("int8", "<i1"), 7: ("int64", "<i8"),
}
FORMAT_CODES: Final = {name: code for code, (name, _) in FORMATS.items()}
_U32 = struct.Struct("<I")


def pack_frame(fmt: int, channels: int, timestamps: Sequence[float] | np.ndarray,
               values: np.ndarray | Sequence[Sequence[bytes | str]]) -> bytes:
    """One frame (see the module docstring) of ``len(timestamps)`` samples.

    Args:
        fmt: LSL channel format code.
        channels: values per sample.
        timestamps: the samples' LSL times, s.
        values: numeric formats: an array of ``(n, channels)``; strings: ``n`` rows of ``channels``
            values (bytes as sent, or str, written as UTF-8).

    Raises:
        ValueError: an unknown format, or values that do not match the counts.
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown LSL channel format {fmt}")
    ts = np.ascontiguousarray(timestamps, dtype="<f8")
    n = int(ts.size)
    dtype = FORMATS[fmt][1]
    if dtype is not None:
        arr = np.ascontiguousarray(values, dtype=dtype)
        if arr.size != n * channels:
            raise ValueError(f"{arr.size} values for {n} samples of {channels} channels")
        payload = ts.tobytes() + arr.tobytes()
    else:
        parts = [ts.tobytes()]
        rows = list(values)
        if len(rows) != n or any(len(r) != channels for r in rows):
            raise ValueError(f"string values are not {n} samples of {channels} channels")
        for row in rows:
            for v in row:
                b = v.encode() if isinstance(v, str) else bytes(v)
                parts += (_U32.pack(len(b)), b)
        payload = b"".join(parts)
    head = HEADER.pack(MAGIC, VERSION, fmt, 0, channels, n, len(payload))
    return b"".join((head, _U32.pack(zlib.crc32(head)), payload, _U32.pack(zlib.crc32(payload))))


def load_pylsl(why: str = "lsl://") -> ModuleType:
    """pylsl with its liblsl, or a one-line ``DeviceUnavailableError`` saying why it cannot load."""
    try:
        import pylsl
    except ImportError as exc:
        raise DeviceUnavailableError(f"{why} needs pylsl ({exc}); install it with: pip install pylsl",
                                     source="lsl") from None
    except (OSError, RuntimeError) as exc:  # the bundled liblsl cannot be loaded
        raise DeviceUnavailableError(f"{why}: liblsl (shipped in pylsl's wheel) cannot be loaded: "
                                     f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"
                                     " (set PYLSL_LIB to a liblsl build, or reinstall pylsl)", source="lsl") from None
    return pylsl


def _literal(value: str) -> str:
    """``value`` as an XPath 1.0 string literal (which has no escapes)."""
    if "'" not in value:
        return f"'{value}'"
    if '"' not in value:
        return f'"{value}"'
    raise ConfigError(f"lsl://: {value!r} holds both kinds of quote, which an LSL query cannot match",
                      source="lsl")


@dataclass(frozen=True)
class LslStreamListing:
    """One LSL stream found on the network, for ``perfcap devices``."""

    name: str
    type: str
    channels: int
    rate_hz: float | None
    format: str
    source_id: str
    host: str

    @property
    def url(self) -> str:
        """The device string that opens this stream."""
        q = f"?source_id={quote(self.source_id, safe='')}" if self.source_id else ""
        return f"lsl://{quote(self.name, safe='')}{q}"

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "type": self.type, "channels": self.channels, "rate_hz": self.rate_hz,
                "format": self.format, "source_id": self.source_id, "host": self.host, "url": self.url}


def _listing(info: Any) -> LslStreamListing:
    rate = float(info.nominal_srate())
    return LslStreamListing(info.name(), info.type(), int(info.channel_count()), rate if rate > 0 else None,
                            FORMATS.get(int(info.channel_format()), (f"format {info.channel_format()}", None))[0],
                            info.source_id(), info.hostname())


def list_lsl_streams(timeout: float = 1.0) -> list[LslStreamListing]:
    """The LSL streams that answer within ``timeout`` seconds, by name.

    Raises:
        DeviceUnavailableError: pylsl cannot be loaded.
    """
    lsl = load_pylsl("listing LSL streams")
    found = {i.uid(): _listing(i) for i in lsl.resolve_streams(wait_time=timeout)}
    return sorted(found.values(), key=lambda s: (s.name, s.type, s.source_id, s.host))


class LslTransport(Transport):
    """An LSL inlet: every pulled chunk of samples is one frame of bytes (module docstring)."""

    scheme: ClassVar[str] = "lsl"
    usage: ClassVar[str] = "lsl://NAME or lsl://?type=TYPE&source_id=ID (any of name, type, source_id)"
    options: ClassVar[dict[str, Option]] = {
        "name": Option(str, "", "the stream's LSL name (the same as the address)"),
        "type": Option(str, "", "the stream's LSL type (EEG, MoCap, ...)"),
        "source_id": Option(str, "", "the stream's LSL source_id"),
        "hostname": Option(str, "", "the host the stream comes from (as perfcap devices lists it)"),
        "timeout": Option(float, 2.0, "seconds to wait for the stream when resolving it", min=0.05, max=600.0),
        "max_samples": Option(int, 1024, "most samples per pulled chunk", min=1, max=1 << 20),
        "buffer_s": Option(int, 360, "the inlet's buffer, s of samples (x100 samples at an irregular rate)",
                           min=1, max=86400),
    }

    def __init__(self, address: str, options: Mapping[str, Any] | None = None, clock: Clock = MONOTONIC) -> None:
        super().__init__(address, options, clock)
        name = self.opts["name"]
        if address and name and address != name:
            raise ConfigError(f"{self.url}: the address names stream {address!r} but name={name!r}; give one",
                              source=self.url)
        self.query: dict[str, str] = {k: v for k, v in (("name", address or name), ("type", self.opts["type"]),
                                                         ("source_id", self.opts["source_id"]),
                                                         ("hostname", self.opts["hostname"])) if v}
        if not self.query:
            raise ConfigError(f"lsl:// needs a stream to look for; expected {self.usage}", source=self.url)
        self._pred = " and ".join(f"{k}={_literal(v)}" for k, v in self.query.items())
        self._inlet: Any = None
        self._ready: Any = None   # an inlet made to read the description, kept for the first open
        self._xml: str | None = None
        #: what the first stream resolved was: (source_id, channel count, format code)
        self._first: tuple[str, int, int] | None = None
        self._fmt = 0
        self._channels = 0

    @property
    def query_text(self) -> str:
        return ", ".join(f"{k}={v!r}" for k, v in self.query.items())

    def implied_kind(self) -> str:
        return "lsl"

    def implied_name(self) -> str | None:
        name = self.query.get("name", "")
        clean = "".join(c if c.isascii() and (c.isalnum() or c in "_-") else "_" for c in name)[:64]
        return clean if clean[:1].isascii() and clean[:1].isalpha() else None

    # -- resolving -----------------------------------------------------------------------------------
    def _resolve(self) -> Any:
        """A new inlet on the stream the query names (its description read).

        Raises:
            DeviceUnavailableError: pylsl cannot load, or no such stream answered in time.
            DeviceInitError: it is not the stream first opened (its channels or format changed).
        """
        lsl = load_pylsl()
        timeout = self.opts["timeout"]
        pred = self._pred
        if self._first is not None and self._first[0] and "source_id" not in self.query:
            pred += f" and source_id={_literal(self._first[0])}"
        found = lsl.resolve_bypred(pred, 1, timeout)
        if not found:
            raise DeviceUnavailableError(f"no LSL stream with {self.query_text} answered within {timeout:g} s"
                                         " (perfcap devices lists the LSL streams it sees)", source=self.url)
        info = found[0]
        if self._first is None:
            self._refuse_ambiguity(lsl, pred, timeout)
        fmt, channels = int(info.channel_format()), int(info.channel_count())
        if self._first is not None and self._first[1:] != (channels, fmt):
            raise DeviceInitError(f"{self.url}: the LSL stream came back with {channels} channels of format {fmt},"
                                  f" not {self._first[1]} of format {self._first[2]}; restart the capture",
                                  source=self.url)
        try:
            inlet = lsl.StreamInlet(info, max_buflen=self.opts["buffer_s"], recover=False)
            full = inlet.info(timeout)
        except Exception as exc:  # liblsl's errors (lost, timeout) are plain RuntimeErrors
            raise DeviceUnavailableError(f"the LSL stream with {self.query_text} did not give its description"
                                         f" ({type(exc).__name__}: {exc})", source=self.url) from exc
        if self._first is None:
            self._first = (info.source_id(), channels, fmt)
        self._fmt, self._channels = fmt, channels
        self._xml = full.as_xml()
        return inlet

    def _refuse_ambiguity(self, lsl: Any, pred: str, timeout: float) -> None:
        """More than one stream answering the query (two hosts whose devices have the same names) is an
        error that lists them, never one of them picked at random.

        Raises:
            DeviceUnavailableError: naming each stream that answered and how to choose one.
        """
        more = {i.uid(): i for i in lsl.resolve_bypred(pred, 2, min(timeout, AMBIGUITY_WAIT_S))}
        if len(more) < 2:
            return
        seen = "; ".join(f"{i.name()} from {i.hostname()} (source_id {i.source_id()})" for i in more.values())
        raise DeviceUnavailableError(f"{len(more)} LSL streams answer {self.query_text}: {seen}; choose one with"
                                     " hostname=HOST or source_id=ID", source=self.url)

    def stream_xml(self) -> str:
        """The stream's full LSL description (XML), resolving it if not done yet.

        Raises:
            DeviceUnavailableError: no such stream answered in time.
        """
        if self._xml is None:
            self._ready = self._resolve()
        assert self._xml is not None
        return self._xml

    # -- life cycle ------------------------------------------------------------------------------------
    def open(self) -> None:
        inlet, self._ready = self._ready, None
        if inlet is None:
            inlet = self._resolve()
        try:
            inlet.open_stream(self.opts["timeout"])
        except Exception as exc:  # liblsl's errors are plain RuntimeErrors
            raise DeviceUnavailableError(f"the LSL stream with {self.query_text} could not be opened"
                                         f" ({type(exc).__name__}: {exc})", source=self.url) from exc
        self._inlet = inlet

    def close(self) -> None:
        inlet, self._inlet = self._inlet, None
        self._ready = None
        if inlet is not None:
            try:
                inlet.close_stream()
            except Exception:  # closing a lost stream may fail; it is closed either way
                pass

    @property
    def is_open(self) -> bool:
        return self._inlet is not None

    def read(self, timeout: float) -> Chunk | None:
        inlet = self._inlet
        if inlet is None:
            raise DeviceIOError(f"{self.url}: read on a closed inlet", source=self.url)
        try:
            values, stamps = inlet.pull_chunk(timeout=max(0.0, timeout), max_samples=self.opts["max_samples"],
                                              min_samples=1, as_numpy=True)
        except Exception as exc:  # pylsl's LostError and friends are RuntimeErrors
            self.close()
            raise DeviceIOError(f"{self.url}: the LSL stream was lost ({type(exc).__name__}: {exc})",
                                source=self.url) from exc
        t = self.clock.now_ns()
        if not len(stamps):
            return None
        return Chunk(pack_frame(self._fmt, self._channels, stamps, values), t)


__all__ = ["FORMATS", "FORMAT_CODES", "HEADER", "HEADER_SIZE", "MAGIC", "STRING", "VERSION", "LslStreamListing",
           "LslTransport", "list_lsl_streams", "load_pylsl", "pack_frame"]
