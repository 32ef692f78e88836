"""Devices join a Transport and a Codec and turn bytes into samples with two clocks.

``Device`` is the model class ("driver" in other projects): it declares its streams, performs its
handshake, maps codec frames to readings, and stamps them through one ``ClockSync`` per stream.
``DeviceReader`` is the one thread per device that polls it, publishes onto the bus, and carries
the reconnect policy: an unplugged device is retried with backoff and comes back with the same
stream names, sequence numbering and calibration; the gap is an event in the session.
"""

from __future__ import annotations

import abc
import enum
import logging
import threading
from dataclasses import dataclass
from typing import Any, ClassVar, Iterable, Mapping, NamedTuple

from capture.bus import SampleBus
from capture.clock import MONOTONIC, Clock
from capture.clocksync import ClockSync
from capture.errors import CaptureError, DeviceError, EndOfStream, ProtocolError
from capture.sample import (
    Chunk,
    DeviceChunk,
    DeviceEvent,
    DeviceIdentity,
    Direction,
    EventKind,
    Sample,
    StreamInfo,
)
from devices.codecs.base import Codec
from devices.options import Option, resolve_options
from devices.transports.base import Transport

log = logging.getLogger(__name__)
RECV_LOGGING_LEVEL = 9  # per-sample logging, below DEBUG


class DeviceState(enum.Enum):
    CLOSED = "closed"
    OPENING = "opening"
    STREAMING = "streaming"
    RECONNECTING = "reconnecting"
    FINISHED = "finished"
    FAILED = "failed"


class Reading(NamedTuple):
    """One decoded reading: index of its stream in ``Device.streams``, values, raw device ticks."""

    stream: int
    values: tuple[float, ...]
    ticks: int | None = None


@dataclass
class DeviceStats:
    chunks: int = 0
    bytes: int = 0
    readings: int = 0
    reconnects: int = 0
    missing_time: int = 0
    lost_readings: int = 0
    last_seen_ns: int | None = None


class Device(abc.ABC):
    """Base class of every device kind.

    Args:
        name: unique device name on the bus (streams are ``<name>/<stream>``).
        transport: the byte pipe (not yet opened).
        options: device options (checked against ``options``).
        clock: host clock.
        strict: re-raise protocol errors instead of counting and resynchronising.
    """

    kind: ClassVar[str] = ""
    description: ClassVar[str] = ""
    codec_cls: ClassVar[type[Codec]]
    options: ClassVar[dict[str, Option]] = {}

    def __init__(self, name: str, transport: Transport, options: Mapping[str, Any] | None = None,
                 clock: Clock = MONOTONIC, strict: bool = False) -> None:
        self.name = name
        self.transport = transport
        self.clock = clock
        self.strict = strict
        self.opts = resolve_options(self.options, options or {}, f"device {name} ({self.kind})",
                                    f"{self.kind}@URL")
        self._given_options = dict(options or {})
        self.codec = self.codec_cls(strict=strict)
        self.state = DeviceState.CLOSED
        self.stats = DeviceStats()
        self.identity = DeviceIdentity(kind=self.kind, name=name, url=transport.url)
        self.streams: list[StreamInfo] = self.declare_streams()
        self._seq = [0] * len(self.streams)
        self._syncs = [ClockSync(s.name, s.clock, s.nominal_rate_hz) for s in self.streams]
        self._last_ticks: list[int | None] = [None] * len(self.streams)
        self._last_dev: list[int | None] = [None] * len(self.streams)
        self._epochs = [-1] * len(self.streams)
        self._reported_errors = 0

    # -- what subclasses provide -----------------------------------------------------------------
    @abc.abstractmethod
    def declare_streams(self) -> list[StreamInfo]:
        """The streams this device publishes (known before the first byte, so sessions can declare them)."""

    @abc.abstractmethod
    def frame_to_readings(self, frame: Any) -> Iterable[Reading]:
        """Readings carried by one codec frame (possibly none, possibly several)."""

    def handshake(self) -> None:
        """Talk to the device after opening (enable streaming, read calibration). Default: nothing."""

    def descriptors(self) -> dict[str, bytes]:
        """Blobs that describe the device (report descriptors, calibration), stored in sessions."""
        return {}

    def stream_info(self, suffix: str, kind: str, channels: tuple[str, ...], units: tuple[str, ...],
                    rate: float | None, frame: str | None = None, clock: Any = None,
                    quantum: tuple[float, ...] | None = None) -> StreamInfo:
        return StreamInfo(f"{self.name}/{suffix}", kind, channels, units, rate, self.identity, frame, clock,
                          quantum)

    # -- life cycle --------------------------------------------------------------------------------
    @property
    def device_options(self) -> dict[str, Any]:
        """The options as given (for sessions and replays)."""
        return dict(self._given_options)

    def open(self) -> list[Any]:
        """Open the transport and run the handshake; returns the items to publish (TX chunks, events).

        Raises:
            DeviceError: the device cannot be opened or the handshake failed.
        """
        self.state = DeviceState.OPENING
        self._pending: list[Any] = []
        self.transport.open()
        self.handshake()
        self.state = DeviceState.STREAMING
        self._pending.append(DeviceEvent(self.name, EventKind.OPENED, self.clock.now_ns(), self.transport.url))
        out, self._pending = self._pending, []
        return out

    def send(self, data: bytes) -> None:
        """Write to the device; the TX chunk is recorded with the device's raw data."""
        chunk = self.transport.write(data)
        self._pending.append(DeviceChunk(self.name, chunk))

    def close(self) -> None:
        try:
            self.transport.close()
        finally:
            if self.state not in (DeviceState.FINISHED, DeviceState.FAILED):
                self.state = DeviceState.CLOSED

    def poll(self, timeout: float) -> list[Any]:
        """Read one chunk and return the bus items it yields (raw chunk first, then samples, clock states).

        Raises:
            DeviceIOError: the transport failed.
            EndOfStream: a finite source ended.
            ProtocolError: only in strict mode.
        """
        chunk = self.transport.read(timeout)
        if chunk is None:
            return []
        return self.process_chunk(chunk)

    def process_chunk(self, chunk: Chunk) -> list[Any]:
        """Decode one chunk (from the live transport or a recorded session) into bus items."""
        out: list[Any] = [DeviceChunk(self.name, chunk)]
        if chunk.direction is not Direction.RX:
            return out
        st = self.stats
        st.chunks += 1
        st.bytes += len(chunk.data)
        st.last_seen_ns = chunk.t_ns
        errs_before = self.codec.stats.errors
        frames = self.codec.feed(chunk.data)
        if self.codec.stats.errors != errs_before:
            out.append(DeviceEvent(self.name, EventKind.PROTOCOL_ERRORS, chunk.t_ns,
                                   f"{self.codec.stats.errors} errors, {self.codec.stats.skipped_bytes} bytes skipped"))
        if not frames:
            return out
        groups: dict[int, list[Reading]] = {}
        for f in frames:
            for r in self.frame_to_readings(f):
                groups.setdefault(r.stream, []).append(r)
        t = chunk.t_ns
        for si, rs in groups.items():
            info = self.streams[si]
            sync = self._syncs[si]
            if info.clock is None:
                devs, bus = sync.stamp(t, None, len(rs))
            else:
                ticks = self._ticks_of(si, rs)
                devs, bus = sync.stamp(t, ticks)
            seq = self._seq[si]
            name = info.name
            period = 1e9 / info.nominal_rate_hz if info.nominal_rate_hz else 0.0
            if sync.epoch != self._epochs[si]:
                self._epochs[si] = sync.epoch
                self._last_dev[si] = None
                if sync.epoch > 0:
                    out.append(DeviceEvent(self.name, EventKind.CLOCK_RESET, t, f"{name}: clock epoch {sync.epoch}"))
            last_dev = self._last_dev[si]
            for r, d, b in zip(rs, devs, bus):
                if d is not None and period:
                    # A device-time step of k periods means k-1 readings were lost before the host:
                    # leave a gap of that size in the sequence numbers.
                    if last_dev is not None:
                        k = round((d - last_dev) / period)
                        if 1 < k < 10_000:
                            seq += k - 1
                            st.lost_readings += k - 1
                    last_dev = d
                out.append(Sample(name, seq, t, d, b, r.values))
                seq += 1
            self._last_dev[si] = last_dev
            self._seq[si] = seq
            st.readings += len(rs)
            cs = sync.pop_state(t)
            if cs is not None:
                out.append(cs)
        return out

    def _ticks_of(self, si: int, rs: list[Reading]) -> list[int]:
        """Device ticks of readings; a reading that lacks one (a lost time packet) gets the previous
        tick plus one nominal period, counted in ``stats.missing_time``."""
        info = self.streams[si]
        last = self._last_ticks[si]
        step = round(info.clock.tick_hz / info.nominal_rate_hz) if info.clock and info.nominal_rate_hz else 1
        wrap = info.clock.wrap_ticks if info.clock else None
        out: list[int] = []
        for r in rs:
            if r.ticks is None:
                self.stats.missing_time += 1
                if last is None:
                    last = 0
                tk = last + step
                if wrap:
                    tk %= wrap
            else:
                tk = r.ticks
            out.append(tk)
            last = tk
        self._last_ticks[si] = last
        return out

    def reset_after_reconnect(self) -> int:
        """Forget partial frames after the pipe was reopened; returns bytes discarded."""
        return self.codec.reset()

    def clock_states(self) -> list[Any]:
        t = self.clock.now_ns()
        return [s for s in (sync.state(t) for sync in self._syncs) if s is not None]

    def health(self) -> dict[str, Any]:
        """Counters for status displays and session summaries."""
        return {"state": self.state.value, **self.stats.__dict__, **self.codec.stats.as_dict(),
                "clock_resets": sum(s.resets for s in self._syncs)}


@dataclass(frozen=True)
class ReconnectPolicy:
    """How a reader retries an unplugged device: exponential backoff from ``initial_s`` to ``max_s``;
    ``give_up_after_s`` (None = never) ends the device as FAILED."""

    enabled: bool = True
    initial_s: float = 0.2
    max_s: float = 5.0
    factor: float = 2.0
    give_up_after_s: float | None = None


class DeviceReader:
    """The thread that polls one device and publishes what it yields onto the bus."""

    def __init__(self, device: Device, bus: SampleBus, policy: ReconnectPolicy = ReconnectPolicy(),
                 poll_timeout: float = 0.1) -> None:
        self.device = device
        self.bus = bus
        self.policy = policy
        self.poll_timeout = poll_timeout
        self._stop = threading.Event()
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=f"reader-{device.name}", daemon=True)

    def start(self) -> DeviceReader:
        self._thread.start()
        return self

    def stop(self, timeout: float | None = 5.0) -> None:
        self._stop.set()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)

    def join(self, timeout: float | None = None) -> bool:
        self._thread.join(timeout)
        return not self._thread.is_alive()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def _event(self, kind: EventKind, detail: str = "") -> None:
        self.bus.publish(DeviceEvent(self.device.name, kind, self.device.clock.now_ns(), detail))

    def _run(self) -> None:
        dev = self.device
        publish_many = self.bus.publish_many
        try:
            try:
                publish_many(dev.open())
            except DeviceError as exc:
                if not self._reconnect(exc, first=True):
                    return
            self._event(EventKind.STREAMING)
            while not self._stop.is_set():
                try:
                    items = dev.poll(self.poll_timeout)
                except EndOfStream:
                    dev.state = DeviceState.FINISHED
                    self._event(EventKind.FINISHED, "source exhausted")
                    return
                except ProtocolError:
                    raise
                except DeviceError as exc:
                    if not self._reconnect(exc):
                        return
                    continue
                if items:
                    publish_many(items)
            dev.state = DeviceState.CLOSED
        except CaptureError as exc:
            self.error = exc
            dev.state = DeviceState.FAILED
            log.error("device %s failed: %s", dev.name, exc)
            self._event(EventKind.FAILED, str(exc))
        except Exception as exc:  # noqa: BLE001 - a bug in one device must not take the others down
            self.error = exc
            dev.state = DeviceState.FAILED
            log.exception("device %s stopped by an internal error", dev.name)
            self._event(EventKind.FAILED, f"internal error: {type(exc).__name__}: {exc}")
        finally:
            try:
                dev.close()
            except DeviceError as exc:
                log.warning("device %s: close failed: %s", dev.name, exc)
            try:
                self.bus.publish_many(dev.clock_states())
            except Exception:  # noqa: BLE001
                log.exception("device %s: final clock state not published", dev.name)

    def _reconnect(self, exc: BaseException, first: bool = False) -> bool:
        """Retry until the device is back (True) or the policy gives up / stop is asked (False)."""
        dev = self.device
        pol = self.policy
        t_lost = dev.clock.now_ns()
        if not first:
            log.warning("device %s lost: %s", dev.name, exc)
            self._event(EventKind.DISCONNECTED, str(exc))
        if not pol.enabled:
            if first:
                raise exc
            dev.state = DeviceState.FAILED
            self._event(EventKind.FAILED, f"disconnected and reconnect is off: {exc}")
            self.error = exc
            return False
        dev.state = DeviceState.RECONNECTING
        self._event(EventKind.RECONNECTING, str(exc))
        delay = pol.initial_s
        while not self._stop.wait(delay):
            try:
                dev.transport.close()
            except DeviceError:
                pass
            try:
                items = dev.open()
            except DeviceError as again:
                elapsed = (dev.clock.now_ns() - t_lost) / 1e9
                if pol.give_up_after_s is not None and elapsed > pol.give_up_after_s:
                    dev.state = DeviceState.FAILED
                    self.error = again
                    self._event(EventKind.FAILED, f"gave up after {elapsed:.1f} s: {again}")
                    return False
                log.debug("device %s still away: %s", dev.name, again)
                delay = min(pol.max_s, delay * pol.factor)
                continue
            dropped = dev.reset_after_reconnect()
            dev.stats.reconnects += 1
            self.bus.publish_many(items)
            gap = (dev.clock.now_ns() - t_lost) / 1e9
            self._event(EventKind.RECONNECTED, f"gap {gap:.3f} s; {dropped} partial bytes discarded")
            log.warning("device %s is back after %.2f s", dev.name, gap)
            return True
        return False
