"""LSL out: every bus stream as a Lab Streaming Layer outlet (``--lsl`` of record, serve and demo).

One outlet per stream, made when the stream is declared (``LslPublisher.declare``, from the capture's
devices and processors before data flows) or, for a stream that appears later (a phone pairing with
``perfcap serve``), when its first sample arrives, its ``StreamInfo`` then asked of the capture. What an
outlet says about itself (:func:`outlet_spec`) is a pure function of the ``StreamInfo``:

* name ``<device>/<stream>``; type from the kind (:func:`lsl_type`): the motion kinds are LSL's
  conventional ``MoCap``, human-input kinds (mice, pens, touch, sticks, buttons) ``Input`` (a choice of
  perfcap's: LSL has no convention for them), any other kind its own name; the kind itself is kept in
  the description;
* the channel count, the nominal rate (0, LSL's irregular rate, when the stream has none) and the
  channel format ``double64``: bus values are float64, and float32 would round them (a quantised
  device's exact values, large counters), for a cost that is nothing at motion-capture rates (17
  streams x 200 Hz x 7 channels is under 200 kB/s);
* a ``source_id`` built from the host name, the device's identity and the stream name, the same
  at every start with the same devices, so LabRecorder reconnects to the stream after a restart;
* the description: ``<channels><channel><label/><unit/><type/></channel>...</channels>``,
  ``<acquisition><manufacturer>perfcap</manufacturer>...</acquisition>`` and ``<perfcap>`` with the
  kind, the frame and the device.

Every sample is pushed with its bus time mapped onto LSL's clock. Bus times are perfcap's host
monotonic nanoseconds (``capture.clock``); LSL's clock is ``pylsl.local_clock()`` seconds. They may be
the same clock, but that is measured, not assumed (:class:`ClockOffset`: the bus clock read before and
after LSL's, the narrowest of several brackets kept, measured again every ``remeasure_s``), and a
sample's LSL time is ``(t_bus_ns + offset_ns) / 1e9``. A ``SampleBatch`` goes out as one chunk with a
time per sample, a ``Sample`` as one sample.

The publisher is subscribed with ``Overflow.NEVER_DROP``: LSL consumers (LabRecorder) expect no sample
lost, and a live ``KEEP_NEWEST`` queue would discard the oldest when behind. Its queue is bounded in
memory (``MAX_BYTES``); only at that bound does the bus drop, counting every item and logging the
first, like the recorder's.

pylsl (which carries liblsl) is loaded only when an outlet is wanted; a machine where it cannot load
gets one ``ConfigError`` line, never a traceback.
"""

from __future__ import annotations

import logging
import math
import re
import socket
import threading
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from capture.bus import SAMPLES, Overflow, Subscriber, Subscription
from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError, DeviceUnavailableError
from capture.sample import DeviceIdentity, Sample, SampleBatch, StreamInfo

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Iterator
    from types import ModuleType

    from capture.app.orchestrator import Capture

log = logging.getLogger(__name__)

#: what ``acquisition/manufacturer`` says
MANUFACTURER = "perfcap"
#: the memory bound of the publisher's never-drop queue (bytes)
MAX_BYTES = 256 << 20
#: seconds of data an outlet keeps for a slow inlet (liblsl's own buffer)
MAX_BUFFERED_S = 360

#: perfcap kinds that are motion: LSL's (XDF's) conventional content type for motion capture
MOCAP_KINDS = frozenset({"imu", "accel", "acc", "gyro", "mag", "euler", "quat", "orientation", "gravity",
                         "linear_acc", "pose"})
#: human-input kinds (LSL has no convention for them: perfcap's choice)
INPUT_KINDS = frozenset({"pointer", "pen", "touch", "axes", "buttons", "sticks"})


#: characters XML 1.0 cannot carry (and lone surrogates, which are no UTF-8): each becomes U+FFFD
_NOT_XML = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\ud800-\udfff\ufffe\uffff]")


def xml_text(text: str) -> str:
    """``text`` as an XML 1.0 element's text can carry it (liblsl writes the description as XML): the
    characters it cannot (control characters, NUL, lone surrogates) replaced by U+FFFD."""
    return _NOT_XML.sub("\ufffd", text)


def lsl_type(kind: str) -> str:
    """The LSL content type of a perfcap stream kind: ``MoCap``, ``Input``, else the kind itself (or
    ``perfcap`` for an empty kind: LSL types should not be empty)."""
    if kind in MOCAP_KINDS:
        return "MoCap"
    if kind in INPUT_KINDS:
        return "Input"
    return kind or "perfcap"


#: a channel's type from its unit (lower case), for the motion units perfcap uses
_UNIT_TYPES = {"m/s^2": "Acceleration", "m/s2": "Acceleration", "g": "Acceleration", "rad/s": "AngularVelocity",
               "deg/s": "AngularVelocity", "dps": "AngularVelocity", "ut": "MagneticField",
               "gauss": "MagneticField", "pa": "Pressure", "hpa": "Pressure", "degc": "Temperature",
               "c": "Temperature", "°c": "Temperature", "m": "Position"}


def channel_type(kind: str, label: str, unit: str) -> str:
    """A channel's ``<type>``: what the value measures, from the kind and the unit (``Acceleration``,
    ``AngularVelocity``, ``Orientation``, ``MagneticField``, ...), else the kind."""
    if kind in ("quat", "orientation", "euler"):
        return "Orientation"
    if kind == "mag":
        return "MagneticField"
    if label.lower() in ("temp", "temperature"):
        return "Temperature"
    return _UNIT_TYPES.get(unit.strip().lower(), kind or "perfcap")


def _identity_key(dev: DeviceIdentity) -> str:
    """What names a device across restarts: its serial number, else its USB ids and address, else the
    URL it was opened with."""
    parts = [dev.kind]
    if dev.serial:
        parts.append(f"serial={dev.serial}")
    else:
        if dev.vid_pid:
            parts.append(f"usb={dev.vid_pid}")
        if dev.address:
            parts.append(f"addr={dev.address}")
        if len(parts) == 1:
            parts.append(dev.url or dev.name)
    return ",".join(parts)


def source_id(info: StreamInfo, host: str) -> str:
    """The outlet's ``source_id``: host, stream name and device identity, stable across restarts."""
    return f"perfcap:{host}:{info.name}:{_identity_key(info.device)}"


@dataclass(frozen=True)
class OutletSpec:
    """Everything an outlet declares, independent of pylsl."""

    name: str
    type: str
    channel_count: int
    nominal_srate: float
    source_id: str
    #: (label, unit, type) per channel
    channels: tuple[tuple[str, str, str], ...]
    #: ``<acquisition>`` children
    acquisition: tuple[tuple[str, str], ...]
    #: ``<perfcap>`` children (the kind, the frame, the device)
    perfcap: tuple[tuple[str, str], ...]


def outlet_spec(info: StreamInfo, host: str) -> OutletSpec:
    """What the outlet of ``info`` declares (see the module's docstring)."""
    rate = info.nominal_rate_hz
    srate = float(rate) if rate is not None and math.isfinite(rate) and rate > 0 else 0.0
    x = xml_text
    chans = tuple((x(c), x(u), x(channel_type(info.kind, c, u)))
                  for c, u in zip(info.channels, info.units, strict=True))
    dev = info.device
    acq = [("manufacturer", MANUFACTURER), ("model", x(dev.kind))]
    if dev.serial:
        acq.append(("serial_number", x(dev.serial)))
    meta = [("kind", info.kind), ("stream", info.name), ("device", dev.name), ("device_kind", dev.kind),
            ("url", dev.url), ("frame", info.frame or ""), ("clock", "bus time (host monotonic) mapped to LSL")]
    return OutletSpec(x(info.name), x(lsl_type(info.kind)), len(info.channels), srate, x(source_id(info, host)),
                      chans, tuple(acq), tuple((k, x(v)) for k, v in meta))


def lsl_stream_info(spec: OutletSpec, lsl: ModuleType) -> Any:
    """The ``pylsl.StreamInfo`` of ``spec``, description included (no outlet yet: nothing on the network)."""
    si = lsl.StreamInfo(spec.name, spec.type, spec.channel_count, spec.nominal_srate, lsl.cf_double64,
                        spec.source_id)
    desc = si.desc()
    chans = desc.append_child("channels")
    for label, unit, typ in spec.channels:
        ch = chans.append_child("channel")
        ch.append_child_value("label", label)
        ch.append_child_value("unit", unit)
        ch.append_child_value("type", typ)
    acq = desc.append_child("acquisition")
    for k, v in spec.acquisition:
        acq.append_child_value(k, v)
    meta = desc.append_child("perfcap")
    for k, v in spec.perfcap:
        meta.append_child_value(k, v)
    return si


def lsl_times(t_bus_ns: np.ndarray, offset_ns: int) -> np.ndarray:
    """LSL timestamps (float64 seconds) of bus times (int64 ns): ``(t_bus_ns + offset_ns) / 1e9``, the
    sum taken in integers so that no nanosecond is lost before the one rounding to float."""
    return (t_bus_ns.astype(np.int64) + np.int64(offset_ns)) / 1e9


def lsl_time(t_bus_ns: int, offset_ns: int) -> float:
    """One bus time (int ns) on LSL's clock: ``(t_bus_ns + offset_ns) / 1e9``."""
    return (t_bus_ns + offset_ns) / 1e9


def batch_chunks(batch: SampleBatch, offset_ns: int, max_samples: int = 4096
                 ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """A batch as LSL chunks of at most ``max_samples``: (values, C-contiguous float64 (n, channels);
    timestamps, float64 (n,))."""
    n = len(batch)
    if n == 0:
        return
    values = np.ascontiguousarray(batch.values, dtype=np.float64).reshape(n, -1)
    times = lsl_times(batch.t_bus_ns, offset_ns)
    for i in range(0, n, max_samples):
        yield values[i:i + max_samples], times[i:i + max_samples]


class ClockOffset:
    """The offset from the bus clock (ns) to LSL's (``local_clock()`` seconds), measured by bracketed
    reads: bus clock, LSL clock, bus clock; of ``reads`` tries the narrowest bracket is kept, and the
    offset is LSL's reading minus the bracket's middle. Its error is at most half the bracket's width."""

    def __init__(self, clock: Clock, lsl_clock: Callable[[], float], reads: int = 25) -> None:
        self.clock = clock
        self.lsl_clock = lsl_clock
        self.reads = max(1, reads)

    def measure(self) -> tuple[int, int]:
        """``(offset_ns, bracket_width_ns)``."""
        now = self.clock.now_ns
        lsl = self.lsl_clock
        best_w = -1
        best_off = 0
        for _ in range(self.reads):
            a = now()
            t = lsl()
            b = now()
            w = b - a
            if best_w < 0 or w < best_w:
                best_w = w
                best_off = round(t * 1e9) - (a + (w >> 1))
        return best_off, best_w


def load_pylsl() -> ModuleType:
    """pylsl with its liblsl (as ``lsl://`` loads it), or a one-line ``ConfigError`` saying why it cannot be used.

    Raises:
        ConfigError: pylsl is missing or its library cannot load.
    """
    from devices.transports.lsl import load_pylsl as load

    try:
        return load("--lsl")
    except DeviceUnavailableError as exc:
        raise ConfigError(str(exc)) from None


class LslPublisher(Subscriber):
    """A bus subscriber publishing every sample stream as an LSL outlet (see the module's docstring).

    Args:
        streams: stream infos to declare now.
        lookup: asked for the ``StreamInfo`` of a stream first seen in the data (None: unknown; it is
            then published with generic channel names, as the recorder records it).
        clock: the bus clock (the capture's).
        host: the host name in source ids (default: this machine's).
        remeasure_s: seconds between clock-offset measurements.
        lsl: the pylsl module (default: loaded, see :func:`load_pylsl`).

    Raises:
        ConfigError: pylsl cannot be loaded.
    """

    accepts = SAMPLES
    idle_interval_s = 0.5

    def __init__(self, streams: Iterable[StreamInfo] = (), *, lookup: Callable[[str], StreamInfo | None] | None = None,
                 clock: Clock = MONOTONIC, host: str | None = None, remeasure_s: float = 10.0,
                 lsl: ModuleType | None = None) -> None:
        self.lsl = lsl if lsl is not None else load_pylsl()
        self.clock = clock
        self.host = host or socket.gethostname() or "localhost"
        self.lookup = lookup
        self.remeasure_ns = int(remeasure_s * 1e9)
        self._offset = ClockOffset(clock, self.lsl.local_clock)
        self._lock = threading.Lock()
        self._outlets: dict[str, Any] = {}
        self.specs: dict[str, OutletSpec] = {}
        #: streams that cannot be published (no channels), logged once
        self._skipped: set[str] = set()
        #: samples pushed per stream
        self.pushed: dict[str, int] = {}
        #: ``(t_bus_ns, offset_ns, width_ns)`` of every offset measurement (the latest in force)
        self.offsets: deque[tuple[int, int, int]] = deque(maxlen=4096)
        self.offset_ns = 0
        self._next_measure = 0
        self.closed = False
        self._measure()
        for info in streams:
            self.declare(info)

    # -- clock -----------------------------------------------------------------------------------
    def _measure(self) -> None:
        off, width = self._offset.measure()
        t = self.clock.now_ns()
        self.offsets.append((t, off, width))
        if len(self.offsets) > 1 and abs(off - self.offset_ns) > max(width, 1000) + 1000:
            log.info("lsl: bus-to-LSL clock offset moved by %.1f us", (off - self.offset_ns) / 1e3)
        self.offset_ns = off
        self._next_measure = t + self.remeasure_ns

    # -- outlets ---------------------------------------------------------------------------------
    def declare(self, info: StreamInfo) -> None:
        """Make the outlet of ``info`` now (a stream already declared keeps its outlet)."""
        with self._lock:
            if self.closed or info.name in self._outlets or info.name in self._skipped:
                return
            if not info.channels:
                self._skipped.add(info.name)
                log.warning("lsl: stream %s has no channels; it is not published", info.name)
                return
            spec = outlet_spec(info, self.host)
            self._outlets[info.name] = self._make_outlet(spec)
            self.specs[info.name] = spec
            self.pushed.setdefault(info.name, 0)

    def _make_outlet(self, spec: OutletSpec) -> Any:
        return self.lsl.StreamOutlet(lsl_stream_info(spec, self.lsl), 0, MAX_BUFFERED_S)

    def _outlet_for(self, item: Sample | SampleBatch) -> Any:
        name = item.stream
        outlet = self._outlets.get(name)
        if outlet is not None or name in self._skipped:
            return outlet
        info = self.lookup(name) if self.lookup is not None else None
        if info is None:
            if isinstance(item, Sample):
                n = len(item.values)
            else:
                n = int(item.values.shape[1]) if item.values.ndim == 2 else 1
            log.warning("lsl: stream %s was not declared; publishing it with generic channel names", name)
            dev, _, _ = name.partition("/")
            info = StreamInfo(name, "unknown", tuple(f"c{i}" for i in range(n)), ("?",) * n, None,
                              DeviceIdentity("unknown", dev))
        self.declare(info)
        return self._outlets.get(name)

    # -- subscriber ------------------------------------------------------------------------------
    def on_item(self, item: Any) -> None:
        outlet = self._outlet_for(item)
        if outlet is None:
            return
        if self.clock.now_ns() >= self._next_measure:
            self._measure()
        off = self.offset_ns
        if type(item) is Sample:
            outlet.push_sample(item.values, (item.t_bus_ns + off) / 1e9)
            self.pushed[item.stream] += 1
        else:
            for values, times in batch_chunks(item, off):
                outlet.push_chunk(values, times.tolist())  # a list: one time per sample (pylsl's form)
            self.pushed[item.stream] += len(item)

    def on_idle(self) -> None:
        if self.clock.now_ns() >= self._next_measure:
            self._measure()

    def stop(self) -> None:
        """Close every outlet (inlets see the streams end)."""
        self.close()

    def close(self) -> None:
        with self._lock:
            self.closed = True
            outlets, self._outlets = self._outlets, {}
        outlets.clear()  # the last reference: liblsl destroys each outlet now

    @property
    def streams(self) -> list[str]:
        return sorted(self.specs)


def publish_capture(cap: Capture, *, host: str | None = None, remeasure_s: float = 10.0,
                    max_bytes: int = MAX_BYTES) -> tuple[LslPublisher, Subscription]:
    """Subscribe an ``LslPublisher`` to a capture: the outlets of every stream known now (devices and
    processors) are made at once, those of streams added later at their first sample. Subscribe after
    the processors are added (``enable_orientation``), so their outlets exist before data flows too.

    Raises:
        ConfigError: pylsl cannot be loaded.
    """
    infos = cap.streams()
    pub = LslPublisher(infos, lookup=cap.stream_info, clock=cap.clock, host=host,
                       remeasure_s=remeasure_s)
    sub = cap.bus.subscribe(pub, policy=Overflow.NEVER_DROP, name="lsl", max_bytes=max_bytes)
    return pub, sub
