"""The Codec interface: sans-IO, no clock, no threads, no I/O.

``feed(bytes) -> list[frame]`` keeps its own buffer, so frames split across reads are joined, and
after garbage it resynchronises, counting what it skipped. ``encode(frame) -> bytes`` is the exact
inverse, used by simulators and to send commands.
"""

from __future__ import annotations

import abc
import logging
from dataclasses import asdict, dataclass
from typing import Any, ClassVar

from capture.errors import ProtocolError

log = logging.getLogger(__name__)


@dataclass
class CodecStats:
    """Counters a codec keeps about its input."""

    bytes_in: int = 0
    frames: int = 0
    checksum_errors: int = 0
    framing_errors: int = 0
    skipped_bytes: int = 0

    @property
    def errors(self) -> int:
        return self.checksum_errors + self.framing_errors

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class Codec(abc.ABC):
    """Base class for protocol parsers.

    Args:
        strict: raise ``ProtocolError`` on the first bad frame instead of counting and resyncing.
    """

    name: ClassVar[str] = ""

    def __init__(self, strict: bool = False) -> None:
        self.strict = strict
        self.stats = CodecStats()
        self._buf = bytearray()

    @abc.abstractmethod
    def feed(self, data: bytes) -> list[Any]:
        """Parse more bytes; returns the complete frames found, in order.

        Raises:
            ProtocolError: only in strict mode, at the first bad frame.
        """

    @abc.abstractmethod
    def encode(self, frame: Any) -> bytes:
        """The bytes of ``frame`` on the wire."""

    def reset(self) -> int:
        """Forget any partial frame (after a reconnect); returns how many bytes were discarded."""
        n = len(self._buf)
        self._buf.clear()
        self.stats.skipped_bytes += n
        return n

    @property
    def buffered(self) -> int:
        return len(self._buf)

    def _bad(self, kind: str, message: str, offset: int, raw: bytes) -> None:
        if kind == "checksum":
            self.stats.checksum_errors += 1
        else:
            self.stats.framing_errors += 1
        if self.strict:
            raise ProtocolError(f"{self.name}: {message}", offset=offset, raw=raw)
        n = self.stats.errors
        if n == 1 or n % 1000 == 0:
            log.warning("%s: %s (at byte %d; %d bad frame(s) so far, resynchronising; all are counted)",
                        self.name, message, offset, n)
        else:
            log.debug("%s: %s (at byte %d)", self.name, message, offset)


class BadMessageError(ValueError):
    """Why one message is dropped; raised inside ``MessageCodec.parse`` and counted by ``feed``."""


class MessageCodec(Codec):
    """A codec for message transports (a WebSocket frame, an HTTP body, a UDP datagram): each
    ``feed`` is exactly one whole message, so nothing is buffered between calls. ``parse`` turns
    one message into frames or raises ``BadMessageError``; ``feed`` bounds the size and counts a bad
    message as one framing error with its bytes skipped.
    """

    #: the largest message accepted, bytes
    max_bytes: ClassVar[int] = 1 << 20

    def feed(self, data: bytes) -> list[Any]:
        """Parse one whole message; returns its frames, or none if it was bad (counted).

        Raises:
            ProtocolError: only in strict mode, on a bad message.
        """
        data = bytes(data)
        self.stats.bytes_in += len(data)
        if len(data) > self.max_bytes:
            return self.drop(f"message of {len(data)} bytes exceeds {self.max_bytes}", data)
        try:
            frames = self.parse(data)
        except BadMessageError as exc:
            return self.drop(str(exc), data)
        self.stats.frames += len(frames)
        return frames

    @abc.abstractmethod
    def parse(self, data: bytes) -> list[Any]:
        """The frames of one message.

        Raises:
            BadMessageError: the message is unusable (it is dropped and counted).
        """

    def drop(self, why: str, data: bytes) -> list[Any]:
        """Count ``data`` as one bad message (its bytes skipped); returns no frames."""
        self.stats.skipped_bytes += len(data)
        self._bad("framing", f"{why}; message dropped", 0, data[:200])
        return []

