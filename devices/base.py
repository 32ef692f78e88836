"""Devices join a Transport and a Codec and turn bytes into samples with two clocks.

This module owns the device layer's machinery, the same for every kind: ``Device``, the model class
("driver" in other projects), generic in its codec; the per-chunk path (``process_chunk``) and the
vectorised batch path (``process_chunks`` with a kind's ``decode_batch``); the stamping of readings
through one ``ClockSync`` per clock domain and their sequence numbers, whose gaps show lost
readings (one implementation for both paths). ``devices.reader`` holds the thread that polls a
device and its reconnect policy. A kind's module (``devices.witmotion``, ...) declares its streams,
performs its handshake and maps codec frames to readings.

No message can end a device: ``process_chunk`` is the one place where a chunk is decoded (codec,
``frame_to_readings``, ``send_ticks``, stamping); an exception in it is that chunk's error, counted
in ``stats.decode_errors`` and as a codec framing error, logged with a rate limit, reported as a
``PROTOCOL_ERRORS`` event (strict mode raises a ``ProtocolError``). Readings with an infinite value
or ticks outside their clock (its wrap, or ``MAX_DEVICE_NS``) are refused there, counted in
``stats.bad_readings``. Codecs refuse bad numbers themselves, with their reason; this is the net.
"""

from __future__ import annotations

import abc
import enum
import logging
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Final, Generic, NamedTuple, TypeVar

import numpy as np

from capture.clock import MONOTONIC, Clock
from capture.clocksync import ClockSync
from capture.errors import ProtocolError
from capture.sample import (
    NO_TIME,
    Chunk,
    ChunkRun,
    DeviceChunk,
    DeviceChunks,
    DeviceEvent,
    DeviceIdentity,
    Direction,
    EventKind,
    Sample,
    SampleBatch,
    StreamInfo,
)
from devices.codecs.base import Codec
from devices.options import Option, resolve_options
from devices.transports.base import BatchSource, Transport

log = logging.getLogger(__name__)
RECV_LOGGING_LEVEL = 9  # per-sample logging, below DEBUG
#: A device-time step of this many nominal periods or more between two readings of a stream is a
#: jump of the device clock, not lost readings: no gap is left in the sequence numbers for it.
GAP_LIMIT: Final = 10_000
#: the largest device time, ns, a reading may carry (about 146 years; int64 holds twice that)
MAX_DEVICE_NS: Final = 2 ** 62
#: decode errors logged at WARNING: the first ones, then one in this many (all are counted)
_LOG_FIRST: Final = 5
_LOG_EVERY: Final = 1000


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
    #: chunks whose decode raised (each dropped, counted, logged with a rate limit)
    decode_errors: int = 0
    #: readings refused: an infinite value, or device ticks the stream's clock cannot carry
    bad_readings: int = 0
    last_seen_ns: int | None = None
    #: what arrived but the device kind cannot decode into any reading, by what it was (a HID kind:
    #: ``"report 0x05"``), each counted; the first of each kind is logged (``Device._undecoded``)
    undecoded: dict[str, int] = field(default_factory=dict)


#: the codec class of a device kind (``Device[WitMotionCodec]``), so ``device.codec`` has its type; a
#: bare ``Device`` is ``Device[Codec]`` (a TypeVar default: PEP 696, in ``typing`` from Python 3.13)
if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping

    import typing_extensions

    CodecT = typing_extensions.TypeVar("CodecT", bound=Codec, default=Codec)
else:
    CodecT = TypeVar("CodecT", bound=Codec)


class Device(abc.ABC, Generic[CodecT]):
    """Base class of every device kind, generic in its codec.

    Args:
        name: unique device name on the bus (streams are ``<name>/<stream>``).
        transport: the byte pipe (not yet opened).
        options: device options (checked against ``options``).
        clock: host clock.
        strict: re-raise protocol errors instead of counting and resynchronising.
    """

    kind: ClassVar[str] = ""
    description: ClassVar[str] = ""
    codec_cls: type[CodecT]
    options: ClassVar[dict[str, Option]] = {}
    #: keyword arguments for the ClockSync of each device clock (``capture.clocksync.ClockSync``), e.g.
    #: ``{"window_s": 60.0}`` for a phone whose messages arrive with tens of ms of jitter
    clock_sync_options: ClassVar[dict[str, Any]] = {}
    #: streams on the same device clock share one clock fit even at different rates (a phone's
    #: motion, orientation and touch events all carry the page's clock): more points for the fit,
    #: and the one-clock fast path. Off by default: it would change the bus times of sessions
    #: recorded by devices whose streams were fitted separately.
    one_fit_per_clock: ClassVar[bool] = False

    def __init__(self, name: str, transport: Transport, options: Mapping[str, Any] | None = None,
                 clock: Clock = MONOTONIC, strict: bool = False) -> None:
        self.name = name
        self.transport = transport
        #: the transport as a ``BatchSource`` when it is one (checked once: ``isinstance`` on a
        #: protocol costs microseconds, too much for every poll)
        self._batch_source: BatchSource | None = transport if isinstance(transport, BatchSource) else None
        self.clock = clock
        self.strict = strict
        self.opts = resolve_options(self.options, options or {}, f"device {name} ({self.kind})",
                                    f"{self.kind}@URL")
        self._given_options = dict(options or {})
        self.codec: CodecT = self.codec_cls(strict=strict)
        self.state = DeviceState.CLOSED
        self.stats = DeviceStats()
        #: successful opens (handshake done); 0 at the end of a take means the device never came
        self.opens = 0
        #: why the last open attempt failed, for reports
        self.last_error: str | None = None
        hint = {k: v for k, v in transport.identity_hint().items() if v is not None}
        self.identity = DeviceIdentity(kind=self.kind, name=name, url=transport.url, **hint)
        self.streams: list[StreamInfo] = self.declare_streams()
        self._build_domains()
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
        self.opens += 1
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
        """Read from the transport and return the bus items it yields (raw chunks first, then
        samples, events and clock states). Transports that can hand over many chunks at once
        (a ``BatchSource`` whose ``batches`` is on: an as-fast-as-possible replay) are read in
        batches and decoded with ``process_chunks``.

        Raises:
            DeviceIOError: the transport failed.
            EndOfStream: a finite source ended.
            ProtocolError: only in strict mode.
        """
        src = self._batch_source
        if src is not None and src.batches:
            chunks = src.read_many(timeout, 4096)
            return self.process_chunks(chunks) if len(chunks) else []
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
        cst = self.codec.stats
        errs_before = cst.errors
        stamped: list[Any] = []
        try:
            frames = self.codec.feed(chunk.data)
            if frames:
                readings = self._checked([r for f in frames for r in self.frame_to_readings(f)])
                send = self.send_ticks(frames)
                if send is not None and not self._ticks_ok(self._send_stream, send):
                    self._refused("bad_readings", f"send time of {send!r:.40} ticks is outside the device clock")
                    send = None
                self._stamp_readings(readings, chunk.t_ns, stamped, send)
        except ProtocolError:
            if self.strict:
                raise
            self._decode_failed("protocol error", chunk)
        except Exception as exc:  # one bad message must never end the device
            if self.strict:
                raise ProtocolError(f"{self.name}: decoding failed: {type(exc).__name__}: {exc}",
                                    raw=bytes(chunk.data[:200])) from exc
            self._decode_failed(f"{type(exc).__name__}: {exc}", chunk)
        if cst.errors != errs_before:
            out.append(DeviceEvent(self.name, EventKind.PROTOCOL_ERRORS, chunk.t_ns,
                                   f"{cst.errors} errors, {cst.skipped_bytes} bytes skipped"))
        out += stamped
        return out

    def _decode_failed(self, why: str, chunk: Chunk) -> None:
        """Count a chunk whose decode raised as one error (the device goes on)."""
        self._refused("decode_errors", f"a chunk of {len(chunk.data)} bytes could not be decoded ({why[:300]}); "
                      "dropped, the device goes on")

    def _refused(self, counter: str, why: str) -> None:
        """Count one refusal in ``stats.<counter>`` and as a codec framing error; log the first few,
        then one in ``_LOG_EVERY``."""
        n = getattr(self.stats, counter) + 1
        setattr(self.stats, counter, n)
        self.codec.stats.framing_errors += 1
        if n <= _LOG_FIRST or n % _LOG_EVERY == 0:
            log.warning("device %s: %s (%d so far, all counted in %s)", self.name, why, n, counter)
            log.debug("traceback of device %s", self.name, exc_info=True)
        else:
            log.debug("device %s: %s", self.name, why)

    def _undecoded(self, what: str) -> None:
        """Count one ``what`` (e.g. ``"report 0x05"``) that arrived but gives no reading in
        ``stats.undecoded``; log a warning the first time of each (of the first few kinds)."""
        und = self.stats.undecoded
        n = und.get(what, 0) + 1
        und[what] = n
        if n == 1 and len(und) <= _LOG_FIRST:
            log.warning("device %s (%s): %s arrived but this device kind cannot decode it (no reading;"
                        " each counted in undecoded)", self.name, self.kind, what)

    def _ticks_ok(self, si: int, tk: Any) -> bool:
        """Whether ``tk`` is an integer (not a bool) within stream ``si``'s clock."""
        if type(tk) is not int and (isinstance(tk, bool) or not isinstance(tk, (int, np.integer))):
            return False
        lo, hi = self._tick_range[si]
        return lo <= int(tk) < hi

    def _checked(self, readings: list[Reading]) -> list[Reading]:
        """``readings`` without those the streams cannot carry, each counted: an infinite value (NaN
        is "no value" and passes), or ticks outside the stream's clock. Ticks on a stream without a clock
        are not its time (a WitMotion sends time packets whether or not they are used): they are dropped
        and the reading kept."""
        tick_range = self._tick_range
        for r in readings:  # the common case: all good, checked cheaply
            tot, tk = sum(r.values), r.ticks
            if tot - tot != 0.0 and any(map(math.isinf, r.values)):
                break
            if tk is not None and (type(tk) is not int or not tick_range[r.stream][0] <= tk < tick_range[r.stream][1]):
                break
        else:
            return readings
        good: list[Reading] = []
        for r in readings:
            name = self._names[r.stream]
            if r.ticks is not None and self.streams[r.stream].clock is None:
                r = r._replace(ticks=None)  # noqa: PLW2901 (the same reading, without the ticks it cannot use)
            if any(math.isinf(v) for v in r.values):
                self._refused("bad_readings", f"{name}: a reading with an infinite value {r.values!r:.200}; refused")
            elif r.ticks is not None and not self._ticks_ok(r.stream, r.ticks):
                self._refused("bad_readings", f"{name}: device time {r.ticks!r:.40} ticks is outside the stream's "
                              f"clock {tick_range[r.stream]}; refused")
            else:
                good.append(r)
        return good

    def send_ticks(self, frames: list[Any]) -> int | None:
        """Raw device-clock ticks at which the message that carried ``frames`` was sent, when the
        protocol says (the phone page's ``sent``). The clock fit then pairs the chunk's arrival with
        it instead of with the newest reading. For devices whose clocked streams share one clock.
        Default: ``None``."""
        return None

    def drain_readings(self) -> list[Reading]:
        """Readings the device has assembled but not yet emitted (e.g. a cycle whose last packet
        would only be recognised by the next one). Called at the end of a take. Default: none."""
        return []

    def finish(self) -> list[Any]:
        """End of the take (end of stream, or stop): emit pending readings, stamped with the last
        arrival, and count bytes of an unfinished frame as skipped. Returns bus items."""
        out: list[Any] = []
        left = self.codec.buffered
        if left:
            self.codec.reset()
            log.info("device %s: %d bytes of an unfinished frame at the end of the take (counted as skipped)",
                     self.name, left)
        try:
            readings = self._checked(self.drain_readings())
            if readings and self.stats.last_seen_ns is not None:
                self._stamp_readings(readings, self.stats.last_seen_ns, out)
        except Exception as exc:  # the end of a take must not fail on one bad pending reading
            if self.strict:
                raise ProtocolError(f"{self.name}: decoding pending readings failed: {type(exc).__name__}: "
                                    f"{exc}") from exc
            self._decode_failed(f"pending readings: {type(exc).__name__}: {exc}", Chunk(b"", 0))
            return []
        return out

    # -- batch path ------------------------------------------------------------------------------
    def batch_ready(self) -> bool:
        """Whether ``decode_batch`` could accept data now (cheap; e.g. the frame layout is learned)."""
        return False

    def decode_batch(self, chunks: ChunkRun) -> BatchReadings | None:
        """Decode many RX chunks at once with numpy, or return ``None`` to use the per-chunk path.

        A device that overrides this must produce exactly what ``process_chunk`` would, and leave
        its codec and assembly state as ``process_chunk`` would have left it. The default has no
        vectorised decoder.
        """
        return None

    def process_chunks(self, chunks: list[Chunk] | ChunkRun) -> list[Any]:
        """Decode many chunks into bus items: ``SampleBatch`` columns when the device has a
        vectorised decoder and the data is clean, otherwise chunk by chunk. Either way the samples
        are identical to what ``process_chunk`` gives."""
        run = chunks if isinstance(chunks, ChunkRun) else ChunkRun.from_chunks(list(chunks))
        out: list[Any] = []
        i = 0
        total = len(run)
        size = total
        dirs = run.directions
        while i < total:
            if not self.batch_ready() or dirs[i]:
                out += self.process_chunk(run[i])
                i += 1
                continue
            stop = min(total, i + size)
            tx = np.flatnonzero(dirs[i:stop])
            if tx.size:
                stop = i + int(tx[0])
            part = run.slice(i, stop)
            try:
                batch = self.decode_batch(part) if len(part) > 1 else None
            except Exception as exc:  # the per-chunk path decodes that part, and counts its errors
                log.debug("device %s: the batch decoder failed (%s: %s); decoding %d chunks one by one",
                          self.name, type(exc).__name__, exc, len(part))
                for k in range(i, stop):
                    out += self.process_chunk(run[k])
                i = stop
                size = total
                continue
            if batch is None:
                if len(part) <= 1:
                    out += self.process_chunk(run[i])  # a bad or partial spot: byte-exact scalar path
                    i += 1
                    size = total
                else:
                    size = max(1, len(part) // 2)
                continue
            out += self._emit_batch(part, batch)
            i += len(part)
            size = total
        return out

    # -- stamping: clock domains, device and bus times, sequence numbers --------------------------
    # One implementation for both paths. ``_stamp_readings`` stamps the readings one chunk completed
    # (the live path, and whatever ``finish`` drains); ``_emit_batch`` stamps a decoded run of
    # chunks with numpy (``process_chunks``). Both take the device's clock domains in the same
    # order (device clocks by index, then pseudo clocks), give each domain its readings in emission
    # order, and number each stream's readings by the same rule (``GAP_LIMIT``), so they give
    # identical samples; ``tests/unit/devices/test_batch_path*.py`` hold them to it.
    def _build_domains(self) -> None:
        """One ClockSync per device clock (streams of one device share it), one per pseudo-clocked
        stream; and each stream's numbering state."""
        self._domains: list[ClockSync] = []
        self._domain_of: list[int] = []
        keys: dict[Any, int] = {}
        for i, s in enumerate(self.streams):
            key: Any = ("stream", i) if s.clock is None else s.clock if self.one_fit_per_clock else (
                s.clock, s.nominal_rate_hz)
            if key not in keys:
                keys[key] = len(self._domains)
                opts = self.clock_sync_options if s.clock is not None else {}
                self._domains.append(ClockSync(s.name, s.clock, s.nominal_rate_hz, **opts))
            self._domain_of.append(keys[key])
        shared = [d for d in self._domains if not d.pseudo]
        if len(shared) == 1:
            shared[0].stream = self.name
        self._domain_epochs = [-1] * len(self._domains)
        #: one domain: no regrouping, and samples keep their emission order
        self._single_domain = len(self._domains) == 1
        #: the streams of each domain
        self._members: list[list[int]] = [[] for _ in self._domains]
        for i, d in enumerate(self._domain_of):
            self._members[d].append(i)
        n = len(self.streams)
        self._names = [s.name for s in self.streams]
        #: nominal period of each stream, ns (0: no nominal rate, so no gap is ever inferred)
        self._periods = [1e9 / s.nominal_rate_hz if s.nominal_rate_hz else 0.0 for s in self.streams]
        #: device ticks a reading that lacks them is given after the previous one, and where they wrap
        self._tick_steps = [round(s.clock.tick_hz / s.nominal_rate_hz) if s.clock is not None and s.nominal_rate_hz
                            else 1 for s in self.streams]
        self._tick_wraps = [s.clock.wrap_ticks if s.clock is not None else None for s in self.streams]
        #: the ticks each stream's readings may carry, [lo, hi): a wrapping clock's counter range, else
        #: what stays within +-MAX_DEVICE_NS of device time; none on a stream without a clock
        self._tick_range: list[tuple[int, int]] = [
            (0, 0) if s.clock is None else (0, s.clock.wrap_ticks) if s.clock.wrap_ticks
            else (-int(MAX_DEVICE_NS * s.clock.tick_hz / 1e9), int(MAX_DEVICE_NS * s.clock.tick_hz / 1e9))
            for s in self.streams]
        #: the stream whose clock a message's send time (``send_ticks``) is on: the first clocked one
        self._send_stream = next((i for i, s in enumerate(self.streams) if s.clock is not None), 0)
        self._seq = [0] * n
        self._last_ticks: list[int | None] = [None] * n
        self._last_dev: list[int | None] = [None] * n
        self._epochs = [-1] * n  # clock epoch each stream last saw

    def _epoch_changed(self, d: int, epoch: int, t: int, out: list[Any]) -> None:
        self._domain_epochs[d] = epoch
        if epoch > 0:
            out.append(DeviceEvent(self.name, EventKind.CLOCK_RESET, t,
                                   f"{self._domains[d].stream}: clock epoch {epoch}"))

    def _stamp_readings(self, readings: list[Reading], t: int, out: list[Any],
                        send_ticks: int | None = None) -> list[Any]:
        """Stamp the readings that completed in a chunk that arrived at ``t``; append bus items to
        ``out``: clock-reset events, then the samples (in emission order on a device with one
        clock domain, else stream by stream), then clock states."""
        if not readings:
            return out
        domains = self._domains
        if self._single_domain:
            dom = domains[0]
            if dom.pseudo:
                devs, bus = dom.stamp(t, None, len(readings))
            else:
                last_ticks = self._last_ticks
                ticks: list[int] = []
                for r in readings:  # _ticks_of, inline on the common path
                    tk = r.ticks
                    if tk is None:
                        tk = self._fill_ticks(r.stream)
                    last_ticks[r.stream] = tk
                    ticks.append(tk)
                devs, bus = dom.stamp(t, ticks, send_ticks=send_ticks)
            ep = dom.epoch
            if ep != self._domain_epochs[0]:
                self._epoch_changed(0, ep, t, out)
            self._number(readings, devs, bus, ep, t, out)
            cs = dom.pop_state(t)
            if cs is not None:
                out.append(cs)
            return out
        # several domains: the readings by stream (in order of first appearance), each domain
        # stamped once with its readings in emission order, then numbered stream by stream
        domain_of = self._domain_of
        groups: dict[int, list[Reading]] = {}
        for r in readings:
            g = groups.get(r.stream)
            if g is None:
                g = groups[r.stream] = []
            g.append(r)
        times: dict[int, tuple[list[int | None], list[int]]] = {}
        touched: list[int] = []
        for d in sorted({domain_of[si] for si in groups if not domains[domain_of[si]].pseudo}):
            dom = domains[d]
            members = self._members[d]
            if len(members) == 1:
                si = members[0]
                times[si] = dom.stamp(t, self._ticks_of(groups[si]), send_ticks=send_ticks)
            else:
                sel = [r for r in readings if domain_of[r.stream] == d]
                devs, bus = dom.stamp(t, self._ticks_of(sel), send_ticks=send_ticks)
                for si in members:
                    if si in groups:
                        times[si] = ([], [])
                for r, dv, b in zip(sel, devs, bus):  # noqa: B905 - equal lengths, hot path
                    tl = times[r.stream]
                    tl[0].append(dv)
                    tl[1].append(b)
            if dom.epoch != self._domain_epochs[d]:
                self._epoch_changed(d, dom.epoch, t, out)
            touched.append(d)
        for si, rs in groups.items():
            d = domain_of[si]
            dom = domains[d]
            if dom.pseudo:
                times[si] = dom.stamp(t, None, len(rs))
                if dom.epoch != self._domain_epochs[d]:
                    self._epoch_changed(d, dom.epoch, t, out)
                touched.append(d)
        for si, rs in groups.items():
            devs, bus = times[si]
            self._number(rs, devs, bus, domains[domain_of[si]].epoch, t, out)
        for d in touched:
            cs = domains[d].pop_state(t)
            if cs is not None:
                out.append(cs)
        return out

    def _number(self, readings: list[Reading], devs: list[int | None], bus: list[int], epoch: int, t: int,
                out: list[Any]) -> None:
        """Samples of stamped readings (one domain's, or one stream's), appended to ``out`` with their
        sequence numbers: a device-time step of k nominal periods (1 < k < ``GAP_LIMIT``) between two
        readings of a stream means k - 1 readings were lost before the host, and leaves a gap of that
        size; no gap is inferred at a stream's first reading, across a clock reset (a new
        ``epoch``) or without a device time. ``_emit_batch`` applies the same rule to arrays."""
        names = self._names
        seqs = self._seq
        last_devs = self._last_dev
        epochs = self._epochs
        periods = self._periods
        st = self.stats
        append = out.append
        # equal lengths; zip's strict keyword would cost 0.15 us a call on the live path
        for r, dv, b in zip(readings, devs, bus):  # noqa: B905
            si = r.stream
            if epochs[si] != epoch:
                epochs[si] = epoch
                last_devs[si] = None
            seq = seqs[si]
            if dv is not None:
                ld = last_devs[si]
                period = periods[si]
                if ld is not None and period:
                    k = round((dv - ld) / period)
                    if 1 < k < GAP_LIMIT:
                        seq += k - 1
                        st.lost_readings += k - 1
                last_devs[si] = dv
            append(Sample(names[si], seq, t, dv, b, r.values))
            seqs[si] = seq + 1
        st.readings += len(readings)

    def _ticks_of(self, readings: list[Reading]) -> list[int]:
        """Device ticks of readings on device clocks; a reading that lacks them (a lost time packet)
        gets its stream's previous ticks plus one nominal period, counted in ``stats.missing_time``."""
        last_ticks = self._last_ticks
        out: list[int] = []
        for r in readings:
            tk = r.ticks
            if tk is None:
                tk = self._fill_ticks(r.stream)
            last_ticks[r.stream] = tk
            out.append(tk)
        return out

    def _fill_ticks(self, si: int) -> int:
        """Ticks for a reading of stream ``si`` that lacks them: the previous ones plus one nominal
        period (wrapped), counted in ``stats.missing_time``."""
        self.stats.missing_time += 1
        last = self._last_ticks[si]
        tk = (0 if last is None else last) + self._tick_steps[si]
        wrap = self._tick_wraps[si]
        return tk % wrap if wrap else tk

    def _emit_batch(self, chunks: ChunkRun, batch: BatchReadings) -> list[Any]:
        """``_stamp_readings`` for a decoded run of chunks, with numpy: the raw chunks, then per
        stream its clock-reset events and one ``SampleBatch``, then clock states."""
        out: list[Any] = [DeviceChunks(self.name, chunks)]
        st = self.stats
        st.chunks += len(chunks)
        st.bytes += len(chunks.data)
        hosts = chunks.t_ns
        st.last_seen_ns = int(hosts[-1])
        streams = batch.streams
        res: dict[int, tuple[np.ndarray | None, np.ndarray, np.ndarray]] = {}
        touched: list[int] = []
        for d, members in self._batch_domains(batch):
            dom = self._domains[d]
            if dom.pseudo:
                (si,) = members
                res[si] = dom.stamp_many(hosts, streams[si].chunk, None)
            else:
                # the domain's readings in emission order, stamped at once, then back to their streams
                emit = np.concatenate([streams[si].emit for si in members])
                order = np.argsort(emit, kind="stable")
                chunk_of = np.concatenate([streams[si].chunk for si in members])[order]
                ticks = np.concatenate([self._batch_ticks(si, streams[si].ticks) for si in members])[order]
                dev, bus, ep = dom.stamp_many(hosts, chunk_of, ticks)
                inv = np.empty_like(order)
                inv[order] = np.arange(order.size)
                o = 0
                for si in members:
                    idx = inv[o:o + streams[si].chunk.size]
                    res[si] = (None if dev is None else dev[idx], bus[idx], ep[idx])
                    o += idx.size
            touched.append(d)
        for si, sr in streams.items():
            dev, bus, ep = res[si]
            n = sr.chunk.size
            if n == 0:
                continue
            dmn = self._domain_of[si]
            # clock epochs: events, and no lost-reading gaps across a reset
            prev_ep = np.empty_like(ep)
            prev_ep[0] = self._epochs[si]
            prev_ep[1:] = ep[:-1]
            new_ep = ep != prev_ep
            for j in np.flatnonzero(new_ep).tolist():
                if ep[j] != self._domain_epochs[dmn]:
                    self._epoch_changed(dmn, int(ep[j]), int(hosts[sr.chunk[j]]), out)
            self._epochs[si] = int(ep[-1])
            seq = self._seq[si] + np.arange(n, dtype=np.int64)
            period = self._periods[si]
            if dev is not None and period:
                # ``_number``'s rule on arrays: a step of k periods, 1 < k < GAP_LIMIT, means k - 1
                # readings were lost, except at a stream's first reading or across a clock reset
                last = self._last_dev[si]
                prev = np.empty_like(dev)
                prev[0] = dev[0] if last is None else last
                prev[1:] = dev[:-1]
                k = np.round((dev - prev) / period)
                gaps = np.where((k > 1) & (k < GAP_LIMIT), k - 1, 0).astype(np.int64)
                gaps[new_ep] = 0
                if last is None:
                    gaps[0] = 0
                seq += np.cumsum(gaps)
                st.lost_readings += int(gaps.sum())
                self._last_dev[si] = int(dev[-1])
            self._seq[si] = int(seq[-1]) + 1
            st.readings += n
            tdev = np.full(n, NO_TIME, np.int64) if dev is None else dev
            out.append(SampleBatch(self._names[si], seq, hosts[sr.chunk], tdev, bus, sr.values))
        t_last = int(hosts[-1])
        for d in touched:
            cs = self._domains[d].pop_state(t_last)
            if cs is not None:
                out.append(cs)
        return out

    def _batch_domains(self, batch: BatchReadings) -> list[tuple[int, list[int]]]:
        """The clock domains a batch touches with their streams, in ``_stamp_readings``' order:
        device clocks by domain index, then pseudo clocks in the order of their streams."""
        domain_of = self._domain_of
        clocked: dict[int, list[int]] = {}
        pseudo: list[tuple[int, list[int]]] = []
        for si in batch.streams:
            d = domain_of[si]
            if self._domains[d].pseudo:
                pseudo.append((d, [si]))
            else:
                clocked.setdefault(d, []).append(si)
        return [(d, clocked[d]) for d in sorted(clocked)] + pseudo

    def _batch_ticks(self, si: int, ticks: np.ndarray | None) -> np.ndarray:
        if ticks is None or ticks.size == 0:
            raise ValueError(f"{self.streams[si].name}: a batch decoder must give ticks for a clocked stream")
        self._last_ticks[si] = int(ticks[-1])
        return ticks

    # -- state ----------------------------------------------------------------------------------
    def reset_after_reconnect(self) -> int:
        """Forget partial frames after the pipe was reopened; returns bytes discarded."""
        return self.codec.reset()

    def clock_states(self) -> list[Any]:
        t = self.clock.now_ns()
        return [s for s in (sync.state(t) for sync in self._domains) if s is not None]

    def health(self) -> dict[str, Any]:
        """Counters for status displays and session summaries."""
        return {"state": self.state.value, **self.stats.__dict__, "undecoded": dict(self.stats.undecoded),
                **self.codec.stats.as_dict(),
                "clock_resets": sum(s.resets for s in self._domains), "opens": self.opens,
                "last_error": self.last_error}


class StreamReadings(NamedTuple):
    """Vectorised readings of one stream from ``Device.decode_batch``."""

    values: np.ndarray        # float64 (n, channels)
    ticks: np.ndarray | None  # int64 (n,) raw device ticks, or None for streams without a clock
    chunk: np.ndarray         # int64 (n,) index of the chunk whose bytes completed each reading
    emit: np.ndarray          # int64 (n,) emission order across the device's streams


@dataclass
class BatchReadings:
    streams: dict[int, StreamReadings]
