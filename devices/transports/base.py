"""Transports: byte pipes that stamp every chunk with the host monotonic time of its arrival.

A transport knows nothing about what the bytes mean (that is the Codec's job). Real ones wrap
pyserial, hidapi or sockets; simulated ones (``synth://``, ``replay://`` in ``sim_devices``) implement
the same interface, so the code above cannot tell them apart.

This module owns the ``Transport`` base class, URL splitting, and the abilities some transports
have beyond it, declared once as runtime-checkable protocols so that callers test for them with
``isinstance`` instead of probing names: ``BatchSource`` (recorded chunks handed over many at once,
by recorded time), ``RecordedTimeline`` (recorded times re-based onto a shared host timeline) and
``SimulatorTruth`` (a simulator that knows when each reading really happened, with its
``LoopingMotion``). Live transports have none of them.
"""

from __future__ import annotations

import abc
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, runtime_checkable
from urllib.parse import parse_qsl, unquote, urlsplit

from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError
from capture.sample import Chunk, ChunkRun, Direction
from devices.options import Option, resolve_options

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence


class Transport(abc.ABC):
    """A byte pipe. Subclasses set ``scheme``, ``usage`` and ``options`` and implement the I/O methods.

    Args:
        address: the part of the URL after ``scheme://`` and before ``?``.
        options: query options (already split from device options), checked against ``options``.
        clock: the host clock used to stamp chunks.
    """

    scheme: ClassVar[str] = ""
    usage: ClassVar[str] = "SCHEME://ADDRESS"
    options: ClassVar[dict[str, Option]] = {}

    def __init__(self, address: str, options: Mapping[str, Any] | None = None, clock: Clock = MONOTONIC) -> None:
        self.address = address
        self.clock = clock
        self.opts = resolve_options(self.options, options or {}, f"{self.scheme}://{address}", self.usage)
        self._given = dict(options or {})

    @property
    def url(self) -> str:
        q = "&".join(f"{k}={v}" for k, v in self._given.items())
        return f"{self.scheme}://{self.address}" + (f"?{q}" if q else "")

    @classmethod
    def extra_options(cls, address: str) -> Mapping[str, Option]:
        """Options that depend on the address (a simulator's device model adds its own)."""
        return {}

    # -- what a device may learn from the transport before opening ---------------------------------
    def implied_kind(self) -> str | None:
        """The device kind this transport carries, if it knows (simulators and replays do)."""
        return None

    def implied_device_options(self) -> dict[str, Any]:
        """Device options implied by the source (a replay returns the recorded device's options)."""
        return {}

    def implied_name(self) -> str | None:
        return None

    def identity_hint(self) -> dict[str, Any]:
        """What the transport knows of the device's identity without opening it (USB vid, pid,
        serial number, bus address); keys are ``DeviceIdentity`` fields. Default: nothing."""
        return {}

    def present(self) -> bool | None:
        """Whether the device is there to be opened, found cheaply without opening it (a serial
        port's path exists); ``None`` when the transport cannot tell. While a device is away the
        reader polls this, so it reconnects as soon as the device returns, not at the next
        backoff step."""
        return None

    # -- I/O ----------------------------------------------------------------------------------------
    @abc.abstractmethod
    def open(self) -> None:
        """Open the pipe.

        Raises:
            DeviceNotFoundError: nothing at the address.
            DeviceInitError: it exists but cannot be opened (permissions, busy).
        """

    @abc.abstractmethod
    def close(self) -> None:
        """Close the pipe; closing twice is harmless."""

    @property
    @abc.abstractmethod
    def is_open(self) -> bool: ...

    @abc.abstractmethod
    def read(self, timeout: float) -> Chunk | None:
        """The next chunk of bytes, stamped on arrival, or ``None`` after ``timeout`` seconds.

        Raises:
            DeviceIOError: the pipe failed (unplugged, reset).
            EndOfStream: a finite source is exhausted.
        """

    def write(self, data: bytes) -> Chunk:
        """Send bytes to the device; returns the stamped TX chunk (for the session's raw log).

        Raises:
            DeviceIOError: the pipe failed.
        """
        raise ConfigError(f"{self.scheme}:// transports cannot send", source=self.url)

    def stamp_tx(self, data: bytes) -> Chunk:
        return Chunk(bytes(data), self.clock.now_ns(), Direction.TX)

    def __enter__(self) -> Transport:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# -- abilities beyond Transport ---------------------------------------------------------------------
@runtime_checkable
class BatchSource(Protocol):
    """A transport that can hand over many recorded chunks at once, in recorded-time order
    (``replay://``). ``Device.poll`` reads it in batches while ``batches`` is true, and the merged
    replay reads several sources by their next chunk's recorded time."""

    @property
    def batches(self) -> bool:
        """Whether chunks may be taken many at a time now (as fast as possible, recorded stamps);
        when false, ``read_many`` returns at most one chunk, paced like ``read``."""
        ...

    def read_many(self, timeout: float, max_chunks: int, until_ns: int | None = None) -> ChunkRun | list[Chunk]:
        """Up to ``max_chunks`` chunks; with ``until_ns``, only chunks recorded before that time
        (possibly none).

        Raises:
            DeviceIOError: the transport is closed.
            EndOfStream: the recording is over.
        """
        ...

    def first_time_ns(self) -> int | None:
        """Recorded time of the next chunk to be read, or ``None`` when there is none."""
        ...


@runtime_checkable
class RecordedTimeline(Protocol):
    """A transport replaying recorded times that can be re-based, so that several replayed devices
    play on one host timeline (``replay://``)."""

    def set_timeline(self, start_ns: int, t0_ns: int = 0) -> None:
        """Play recorded time ``t0_ns`` (0: the first chunk) at host time ``start_ns``; call before
        the device is opened."""
        ...

    @property
    def lateness_ns(self) -> Sequence[int]:
        """How late each paced chunk was delivered after its deadline, ns."""
        ...


@runtime_checkable
class LoopingMotion(Protocol):
    """Simulated motion that may repeat one gesture (``sim_devices.motion.WavingMotion``)."""

    @property
    def loop_s(self) -> float | None:
        """Mean duration of one loop, s, or ``None`` for motion that does not loop."""
        ...

    def mean_loop_s(self, d0: float, d1: float) -> float:
        """The mean loop duration over device seconds ``[d0, d1]``.

        Raises:
            ValueError: the motion has no loops, or ``d1 <= d0``.
        """
        ...


@runtime_checkable
class SimulatorTruth(Protocol):
    """A simulator that knows when each reading really happened (``synth://``, ``simhid://``), so
    the bus times a device gives can be checked against the truth."""

    @property
    def truth_ns(self) -> list[int]:
        """Host time of each true reading, ns, in the order made (filled when the simulator's
        ``truth`` option is on)."""
        ...

    @property
    def latency_ns(self) -> int:
        """The simulated fixed transport latency, ns."""
        ...

    @property
    def drift_ppm(self) -> float:
        """The simulated device clock drift, ppm (positive: the device clock runs fast)."""
        ...

    @property
    def motion(self) -> LoopingMotion | None:
        """The simulated motion, when the simulator has one."""
        ...


def split_url(url: str) -> tuple[str, str, dict[str, str]]:
    """``scheme://address?k=v&...`` -> (scheme, address, options).

    Raises:
        ConfigError: not of that form, or a key given twice.
    """
    if "://" not in url:
        raise ConfigError(f"invalid transport URL {url!r}: expected SCHEME://ADDRESS[?key=value&...]", source=url)
    try:
        parts = urlsplit(url)
    except ValueError as exc:
        raise ConfigError(f"invalid transport URL {url!r}: {exc}; expected SCHEME://ADDRESS[?key=value&...]",
                          source=url) from None
    scheme = parts.scheme.lower()
    if not scheme or not scheme.replace("+", "").replace("-", "").isalnum():
        raise ConfigError(f"invalid transport URL {url!r}: expected SCHEME://ADDRESS[?key=value&...]", source=url)
    address = unquote(parts.netloc + parts.path)  # %20 and friends: paths with spaces, '#', '?' or '%'
    if parts.fragment:
        address += "#" + unquote(parts.fragment)
    opts: dict[str, str] = {}
    try:
        pairs = parse_qsl(parts.query, keep_blank_values=True, strict_parsing=bool(parts.query))
    except ValueError:
        raise ConfigError(f"invalid options in {url!r}: expected ?key=value&key=value", source=url) from None
    for k, v in pairs:
        if k in opts:
            raise ConfigError(f"option {k!r} given twice in {url!r}", source=url)
        opts[k] = v
    return scheme, address, opts
