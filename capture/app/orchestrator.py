"""A capture run: devices -> readers -> bus -> recorder (and live subscribers), started and stopped
together. ``perfcap record``, ``perfcap demo`` and ``perfcap replay`` are thin layers over it.
"""

from __future__ import annotations

import json
import logging
import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from capture.bus import Overflow, Processor, SampleBus, Subscriber, Subscription
from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError
from capture.recorder import SessionRecorder
from capture.sample import DeviceEvent, EventKind, Sample, SampleBatch
from capture.session import SessionWriter
from devices import Device, DeviceReader, DeviceSpec, ReconnectPolicy, open_device

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping, Sequence

    from capture.calibration import ImuCalibration
    from capture.calibration_store import CalibrationStore
    from capture.orientation import OrientationProcessor
    from capture.sample import StreamInfo

log = logging.getLogger(__name__)

#: the reconnect policy of a capture that is given none (retry with backoff, never give up)
DEFAULT_RECONNECT = ReconnectPolicy()


@dataclass
class StreamCounter:
    samples: int = 0
    gaps: int = 0
    missing: int = 0
    last_seq: int = -1
    first_bus_ns: int | None = None
    last_bus_ns: int | None = None

    @property
    def rate_hz(self) -> float:
        if self.first_bus_ns is None or self.last_bus_ns is None or self.samples < 2:
            return 0.0
        span = (self.last_bus_ns - self.first_bus_ns) / 1e9
        return (self.samples - 1) / span if span > 0 else 0.0


class StreamStats(Subscriber):
    """A live consumer: per-stream counts, measured rate and sequence gaps (drops before the bus)."""

    accepts = frozenset({Sample, SampleBatch, DeviceEvent})
    coalesce_s = 0.02  # counters read about once a second: no need to wake for every item

    #: events kept for the report (protocol-error events are counted per device, not kept: a device
    #: sending garbage would otherwise grow this without bound)
    MAX_EVENTS = 10_000

    def __init__(self) -> None:
        self.streams: dict[str, StreamCounter] = {}
        self.events: list[DeviceEvent] = []
        self.events_not_kept = 0
        self.protocol_error_events: dict[str, int] = {}
        self._lock = threading.Lock()

    def on_item(self, item: Any) -> None:
        if type(item) is DeviceEvent:
            if item.kind is EventKind.PROTOCOL_ERRORS:
                self.protocol_error_events[item.source] = self.protocol_error_events.get(item.source, 0) + 1
            elif len(self.events) < self.MAX_EVENTS:
                self.events.append(item)
            else:
                self.events_not_kept += 1
            return
        c = self.streams.get(item.stream)
        if c is None:
            c = self.streams[item.stream] = StreamCounter()
        seqs: tuple[int, ...]
        if type(item) is Sample:
            seqs = (item.seq,)
            c.samples += 1
            first_b = last_b = item.t_bus_ns
        else:
            seqs = (int(item.seq[0]), int(item.seq[-1])) if len(item) else ()
            c.samples += len(item)
            if not len(item):
                return
            first_b, last_b = int(item.t_bus_ns[0]), int(item.t_bus_ns[-1])
        if seqs:
            if c.last_seq >= 0 and seqs[0] != c.last_seq + 1:
                c.gaps += 1
                c.missing += max(0, seqs[0] - c.last_seq - 1)
            c.last_seq = seqs[-1]
        if c.first_bus_ns is None:
            c.first_bus_ns = first_b
        c.last_bus_ns = last_b

    def snapshot(self) -> dict[str, dict[str, Any]]:
        return {k: {"samples": v.samples, "rate_hz": round(v.rate_hz, 2), "drops": v.missing}
                for k, v in sorted(self.streams.items())}


@dataclass
class CaptureReport:
    duration_s: float
    devices: dict[str, dict[str, Any]]
    streams: dict[str, dict[str, Any]]
    subscribers: list[dict[str, Any]]
    output: str | None
    recorder_error: str | None = None
    events: list[dict[str, Any]] = field(default_factory=list)
    #: samples per stream in the session file (None: nothing recorded)
    saved: dict[str, int] | None = None
    #: samples per stream that came to the recorder but are not in the file (a failed recording)
    not_saved: dict[str, int] = field(default_factory=dict)
    #: ``saved`` is exact (False: the file holds at least that)
    saved_exact: bool = True
    #: devices that sent data but gave no sample in the take: name -> what they sent (one line)
    silent: dict[str, str] = field(default_factory=dict)


def silent_devices(devices: Sequence[Device], streams: dict[str, dict[str, Any]]) -> dict[str, str]:
    """The devices that received data in the take but published no sample on any of their streams,
    each with a line saying what arrived and, when the kind counted them, what it could not decode."""
    out: dict[str, str] = {}
    for d in devices:
        st = d.stats
        if not st.chunks or any(streams.get(s.name, {}).get("samples", 0) for s in d.streams):
            continue
        why = f"sent {st.chunks} chunks ({st.bytes} bytes) but no sample was recorded from it"
        if st.undecoded:
            why += ": its kind cannot decode " + ", ".join(
                f"{k} ({n}x)" for k, n in sorted(st.undecoded.items()))
        else:
            fs = d.codec.stats
            why += f": {fs.frames} frames decoded, {fs.errors} errors, {st.readings} readings"
        out[d.name] = why
    return out


CALIBRATION_KEY = "calibration.json"


def build_orientation(devices: Sequence[Device], filter: str, auto_bias: bool,  # noqa: A002 - as the CLI's --filter
                      calibrations: Mapping[str, ImuCalibration]) -> OrientationProcessor | None:
    """An ``OrientationProcessor`` over every IMU stream of ``devices`` (with each device's
    magnetometer where its units allow), or None when no device has an IMU stream."""
    from capture.orientation import OrientationProcessor, check_mag_stream

    inputs = []
    for d in devices:
        imus = [s for s in d.streams if s.kind == "imu"]
        if not imus:
            continue
        inputs += imus
        for s in d.streams:
            if s.kind == "mag":
                try:
                    check_mag_stream(s, imus[0])
                except ConfigError as exc:
                    log.info("%s is not used for orientation: %s", s.name, exc)
                    continue
                inputs.append(s)
    if not inputs:
        return None
    proc = OrientationProcessor(inputs, filter, calibrations, auto_bias=auto_bias)
    for o in proc.output_streams():
        o.extra["auto_bias"] = auto_bias  # so a replay rebuilds the same processor
    return proc


class Capture:
    """Devices on one bus, optionally recorded.

    Args:
        devices: device specs/strings, or already built ``Device`` objects.
        output: session file to record to, or ``None``.
        overwrite: replace an existing session file.
        max_loss_s: recorder flush bound (see ``SessionRecorder``).
        fsync: fsync the session file at each flush.
        recorder_max_bytes: memory bound of the recorder's queue.
        live_queue: queue length of live subscribers.
        reconnect: reconnect policy for all devices.
        meta: extra session metadata.

    Raises:
        ConfigError: a device string or option is invalid (nothing has been started).
        DeviceUnavailableError: unknown kind or scheme.
        SessionExistsError / SessionError: the output cannot be created.
    """

    def __init__(self, devices: Sequence[Device | DeviceSpec | str], *, output: str | None = None,
                 overwrite: bool = False, max_loss_s: float = 1.0, fsync: bool = True,
                 recorder_max_bytes: int = 1 << 30, live_queue: int = 8192,
                 reconnect: ReconnectPolicy = DEFAULT_RECONNECT, meta: dict[str, str] | None = None,
                 clock: Clock = MONOTONIC, allow_empty: bool = False, views: bool = True) -> None:
        if not devices and not allow_empty:
            raise ConfigError("no devices given; add at least one with -d DEVICE (e.g. -d synth://imu)")
        self.clock = clock
        names: set[str] = set()
        self.devices: list[Device] = []
        for d in devices:
            if isinstance(d, Device):
                if d.name in names:
                    raise ConfigError(f"device name {d.name!r} is used twice")
                names.add(d.name)
                self.devices.append(d)
            else:
                self.devices.append(open_device(d, clock=clock, taken_names=names))
        self.output = output
        self.recorder: SessionRecorder | None = None
        self._max_loss_s = max_loss_s
        self._fsync = fsync
        #: sessions also hold the viewable channels (``SessionWriter``'s ``views``)
        self.views = views
        self.reconnect = reconnect
        self._lock = threading.RLock()  # devices and the recorder change together (serve adds phones live)
        #: set when the recording fails (a write error): ``run`` ends the take
        self.recording_failed = threading.Event()
        #: called (from the recorder's thread) with the error when a recording fails; ``perfcap serve``
        #: stops that recording and keeps serving
        self.on_recording_failed: Callable[[Exception], None] | None = None
        writer = None
        if output is not None:  # before any thread starts: a bad path must leave nothing running
            writer = SessionWriter(output, overwrite=overwrite, fsync=fsync, meta=meta,
                                   wall_time_s=clock.wall_time_s(), host_now_ns=clock.now_ns(), views=views)
        self.bus = SampleBus(clock, live_queue=live_queue, recorder_max_bytes=recorder_max_bytes)
        self.processors: list[Processor] = []
        self.orientation: OrientationProcessor | None = None
        try:
            self.stats = StreamStats()
            self.bus.subscribe(self.stats, policy=Overflow.KEEP_NEWEST, name="stats")
            if writer is not None:
                self._attach_recorder(writer)
        except BaseException:
            self.bus.close()
            if writer is not None and not writer.closed:
                writer.close()
            raise
        self.readers = [DeviceReader(d, self.bus, reconnect) for d in self.devices]
        self._t_start = 0
        self._stopped = False
        self._report: CaptureReport | None = None

    def _attach_recorder(self, writer: SessionWriter) -> SessionRecorder:
        rec = SessionRecorder(writer, max_loss_s=self._max_loss_s, clock=self.clock)
        rec.on_failed = self._recorder_failed
        for d in self.devices:
            rec.add_device(d.name, d.kind, d.transport.url, d.device_options, d.identity, d.streams, d.descriptors())
        for proc in self.processors:
            for info in proc.output_streams():
                rec.add_stream(info)
        sub = self.bus.subscribe(rec, policy=Overflow.NEVER_DROP, name="recorder")
        rec.subscription = sub
        self.recorder = rec
        return rec

    def add_device(self, device: Device | DeviceSpec | str) -> Device:
        """Add a device to a capture, running or not (``perfcap serve`` adds each phone as it pairs).
        It is declared to the recorder before its reader starts, so its first bytes are recorded.

        Raises:
            ConfigError: bad spec, or the name is taken.
            DeviceUnavailableError: unknown kind or scheme.
        """
        with self._lock:
            names = {d.name for d in self.devices}
            if isinstance(device, Device):
                if device.name in names:
                    raise ConfigError(f"device name {device.name!r} is used twice")
                dev = device
            else:
                dev = open_device(device, clock=self.clock, taken_names=names)
            if self.recorder is not None:
                self.recorder.add_device(dev.name, dev.kind, dev.transport.url, dev.device_options, dev.identity,
                                         dev.streams, dev.descriptors())
            self.devices.append(dev)
            reader = DeviceReader(dev, self.bus, self.reconnect)
            self.readers.append(reader)
            if self._t_start and not self._stopped:
                reader.start()
            return dev

    def remove_device(self, name: str, timeout: float | None = 5.0) -> Device | None:
        """Take a device out of a capture (``perfcap serve`` gives up the slot of a phone that left):
        its reader is told to stop (and waited for up to ``timeout`` seconds; 0 = not waited for), it
        closes the device, and what it published stays on the bus and in the recording. The device may
        be added again later (``add_device``), under its name, continuing its sequence numbers.

        Returns:
            the removed device, or None if no device has that name.
        """
        with self._lock:
            dev = self.device(name)
            if dev is None:
                return None
            self.devices.remove(dev)
            readers = [r for r in self.readers if r.device is dev]
            self.readers = [r for r in self.readers if r.device is not dev]
        for r in readers:
            r.stop(timeout)
        return dev

    def device(self, name: str) -> Device | None:
        for d in self.devices:
            if d.name == name:
                return d
        return None

    def streams(self) -> list[StreamInfo]:
        """Every stream of the capture in the order it declares them to its recorder: the devices', then
        the processors' outputs (live outputs take their channels from here)."""
        return [s for d in list(self.devices) for s in d.streams] + [s for p in list(self.processors)
                                                                     for s in p.output_streams()]

    def stream_info(self, name: str) -> StreamInfo | None:
        """A stream of the capture by name (None: unknown; a stream published by nobody it knows)."""
        return next((s for s in self.streams() if s.name == name), None)

    @property
    def recording(self) -> bool:
        return self.recorder is not None and not self._stopped

    def _recorder_failed(self, exc: Exception) -> None:
        self.recording_failed.set()  # (the recorder has logged what the file keeps)
        cb = self.on_recording_failed
        if cb is not None:
            cb(exc)

    def start_recording(self, output: str, *, overwrite: bool = False, meta: dict[str, str] | None = None,
                        base_dir: str | None = None) -> str:
        """Start recording a running (or not yet started) capture into a new session file; every
        device is declared, and what the bus carries from now on is written. Returns the file's path
        (with ``base_dir``: the path inside it).

        Args:
            output: the session file.
            overwrite: replace an existing perfcap session.
            meta: extra session metadata.
            base_dir: confine ``output`` to this directory (see ``SessionWriter``).

        Raises:
            ConfigError: a recording is already running, or the path is malformed or leaves ``base_dir``.
            SessionExistsError / SessionError: the file cannot be created.
        """
        with self._lock:
            if self.recorder is not None:
                raise ConfigError(f"already recording to {self.output}; stop that recording first")
            writer = SessionWriter(output, overwrite=overwrite, fsync=self._fsync, meta=meta,
                                   wall_time_s=self.clock.wall_time_s(), host_now_ns=self.clock.now_ns(),
                                   base_dir=base_dir, views=self.views)
            try:
                self._attach_recorder(writer)
            except BaseException:
                if not writer.closed:
                    writer.close()
                raise
            self.output = writer.path
            self.recording_failed.clear()
            return writer.path

    def stop_recording(self) -> dict[str, Any]:
        """Finish the current recording: everything already on the bus is written, the file closed.
        Returns ``{"output", "samples", "error", "not_saved"}``: ``samples`` per stream are what the
        file holds, ``not_saved`` what came in but is not in it (a failed recording).

        Raises:
            ConfigError: nothing is being recorded.
        """
        with self._lock:
            rec = self.recorder
            if rec is None:
                raise ConfigError("not recording")
            self.bus.unsubscribe(rec.subscription, wait=True)
            self.recorder = None
            out, self.output = self.output, None
        return {"output": out, "samples": dict(rec.saved),
                "error": None if rec.failed is None else str(rec.failed), "not_saved": rec.not_saved()}

    def subscribe(self, sub: Subscriber, policy: Overflow = Overflow.KEEP_NEWEST,
                  name: str | None = None) -> Subscription:
        return self.bus.subscribe(sub, policy=policy, name=name)

    def add_processor(self, proc: Processor, name: str | None = None) -> Subscription:
        """Attach a processor: a subscriber that publishes derived streams (``output_streams()``,
        declared to the recorder now) back onto the bus through ``bind(publish)``. It never drops
        input, and it is drained before the recorder when the capture stops.

        Raises:
            ConfigError: the capture has already started, or an output stream name is taken.
        """
        if self._t_start:
            raise ConfigError("processors must be added before the capture starts")
        taken = {s.name for d in self.devices for s in d.streams}
        for info in proc.output_streams():
            if info.name in taken:
                raise ConfigError(f"processor {name or type(proc).__name__}: stream {info.name} already exists")
            taken.add(info.name)
            if self.recorder is not None:
                self.recorder.add_stream(info)
        proc.bind(self.bus.publish)
        proc.publishes = True  # drained before the recorder on close (see Subscriber.publishes)
        self.processors.append(proc)
        return self.bus.subscribe(proc, policy=Overflow.NEVER_DROP, name=name or type(proc).__name__)

    def enable_orientation(self, filter: str = "fusion", auto_bias: bool = True,  # noqa: A002 - as --filter
                           calibrations: Mapping[str, ImuCalibration] | None = None,
                           store: CalibrationStore | None = None) -> OrientationProcessor | None:
        """Orientation fusion on every IMU stream (see ``capture.orientation``), with each device's
        calibration: from ``calibrations`` (by device name), else from ``store`` (a
        ``CalibrationStore``, by device identity). The calibration used is recorded with the device,
        so a replay re-applies exactly it. Returns the processor, or None if no stream is an IMU.

        Raises:
            ConfigError: a stored calibration is damaged, or a stream fails the unit/frame check.
        """
        from capture.calibration_store import calibration_document

        cals: dict[str, ImuCalibration] = dict(calibrations or {})
        for d in self.devices:
            if d.name not in cals and store is not None and any(s.kind == "imu" for s in d.streams):
                cal = store.load(d.identity)
                if cal is not None:
                    log.info("device %s: calibration from %s", d.name, store.path_for(d.identity))
                    cals[d.name] = cal
        proc = build_orientation(self.devices, filter, auto_bias, cals)
        if proc is None:
            return None
        if self.recorder is not None:
            for d in self.devices:
                if d.name in cals:
                    doc = calibration_document(d.identity, cals[d.name], None, "in use for this take")
                    self.recorder.writer.add_descriptor(d.name, CALIBRATION_KEY, json.dumps(doc).encode())
        self.add_processor(proc, name="orientation")
        self.orientation = proc
        return proc

    def start(self) -> Capture:
        with self._lock:
            self._t_start = self.clock.now_ns()
            for r in self.readers:
                r.start()
        return self

    def run(self, duration_s: float | None, stop: threading.Event | None = None,
            on_tick: Callable[[Capture, float], None] | None = None, tick_s: float = 1.0) -> CaptureReport:
        """Start, wait for ``duration_s`` (None: until every device finished or ``stop`` is set), stop."""
        stop = stop or threading.Event()
        self.start()
        try:
            next_tick = tick_s
            while True:
                elapsed = (self.clock.now_ns() - self._t_start) / 1e9
                if duration_s is not None and elapsed >= duration_s:
                    break
                if not any(r.alive for r in self.readers):
                    break
                if self.recording_failed.is_set():
                    break  # a write failed: the take ends now, not at its duration
                wait = 0.05 if duration_s is None else max(0.0, min(0.05, duration_s - elapsed))
                if stop.wait(wait):
                    break
                if on_tick and elapsed >= next_tick:
                    on_tick(self, elapsed)
                    next_tick += tick_s
        finally:
            report = self.stop()
        return report

    def start_driven(self) -> int:
        """Mark the capture started for a caller that drives every device from its own thread (the
        merged replay, ``capture.app.replay.run_merged``) instead of reader threads; returns the start
        time (host ns)."""
        with self._lock:
            self._t_start = self.clock.now_ns()
        return self._t_start

    def stop(self) -> CaptureReport:
        """Stop readers, drain every subscriber (the recorder writes everything), close the session."""
        if self._stopped and self._report is not None:
            return self._report
        with self._lock:
            self._stopped = True
        for r in list(self.readers):
            r.stop()
        elapsed = (self.clock.now_ns() - self._t_start) / 1e9 if self._t_start else 0.0
        subs = [s.__dict__ for s in self.bus.stats()]
        self.bus.close()
        rec_err = None
        rec = self.recorder
        if rec is not None and rec.failed is not None:
            rec_err = str(rec.failed)
        streams = self.stats.snapshot()
        self._report = CaptureReport(
            duration_s=elapsed,
            devices={d.name: d.health() for d in self.devices},
            streams=streams,
            subscribers=subs,
            output=self.output,
            recorder_error=rec_err,
            events=[e.to_dict() for e in self.stats.events if e.kind not in (EventKind.PROTOCOL_ERRORS,)],
            saved=None if rec is None else dict(rec.saved),
            not_saved={} if rec is None else rec.not_saved(),
            saved_exact=True if rec is None else rec.saved_exact,
            silent=silent_devices(self.devices, streams),
        )
        return self._report
