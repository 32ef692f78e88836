"""What travels on the sample bus: samples with two clocks, their stream metadata, raw chunks,
clock-sync states and device events.

Every reading keeps three times, all integer nanoseconds:

* ``t_device_ns`` - the device's own clock, unwrapped (``None`` when the device has none);
* ``t_host_ns``   - the host monotonic time at which the bytes carrying it arrived;
* ``t_bus_ns``    - the host-monotonic time of the reading itself, from the online
  device-to-host clock fit (``capture.clocksync``). Use this one to align streams.

``Sample`` is a ``NamedTuple`` rather than a frozen dataclass: it is immutable and is built at C
speed, which the one-by-one publishing path needs. ``SampleBatch`` carries many readings of one
stream as numpy columns for the vectorised paths.
"""

from __future__ import annotations

import enum
import json
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

if TYPE_CHECKING:
    from collections.abc import Iterator

#: Sentinel used in int64 columns for "no device timestamp".
NO_TIME: int = np.iinfo(np.int64).min


class Sample(NamedTuple):
    """One reading of one stream."""

    stream: str
    seq: int
    t_host_ns: int
    t_device_ns: int | None
    t_bus_ns: int
    values: tuple[float, ...]


@dataclass(frozen=True, slots=True, eq=False)
class SampleBatch:
    """Many readings of one stream, as columns. ``t_device_ns`` uses ``NO_TIME`` for missing times."""

    stream: str
    seq: np.ndarray          # int64 (n,)
    t_host_ns: np.ndarray    # int64 (n,)
    t_device_ns: np.ndarray  # int64 (n,), NO_TIME where the device gave none
    t_bus_ns: np.ndarray     # int64 (n,)
    values: np.ndarray       # float64 (n, channels)

    def __len__(self) -> int:
        return int(self.seq.shape[0])

    @property
    def nbytes(self) -> int:
        return int(self.seq.nbytes + self.t_host_ns.nbytes + self.t_device_ns.nbytes
                   + self.t_bus_ns.nbytes + self.values.nbytes)

    def samples(self) -> Iterator[Sample]:
        """The batch as single samples (for consumers that want them one by one)."""
        tdev = self.t_device_ns.tolist()
        for i, (s, th, tb, v) in enumerate(zip(self.seq.tolist(), self.t_host_ns.tolist(),
                                                self.t_bus_ns.tolist(), self.values.tolist(), strict=True)):
            td = tdev[i]
            yield Sample(self.stream, s, th, None if td == NO_TIME else td, tb, tuple(v))

    @classmethod
    def from_samples(cls, stream: str, samples: list[Sample], channels: int) -> SampleBatch:
        """Columns from a list of samples of one stream."""
        n = len(samples)
        if n == 0:
            e = np.empty(0, np.int64)
            return cls(stream, e, e.copy(), e.copy(), e.copy(), np.empty((0, channels)))
        _, seq, th, td, tb, vals = zip(*samples, strict=True)  # C-level transposition
        tdev = [NO_TIME if x is None else x for x in td] if None in td else td
        return cls(stream, np.array(seq, np.int64), np.array(th, np.int64), np.array(tdev, np.int64),
                   np.array(tb, np.int64), np.array(vals, np.float64).reshape(n, channels))

    @classmethod
    def concat(cls, batches: list[SampleBatch]) -> SampleBatch:
        b0 = batches[0]
        if len(batches) == 1:
            return b0
        return cls(b0.stream, np.concatenate([b.seq for b in batches]),
                   np.concatenate([b.t_host_ns for b in batches]),
                   np.concatenate([b.t_device_ns for b in batches]),
                   np.concatenate([b.t_bus_ns for b in batches]),
                   np.concatenate([b.values for b in batches]))


@dataclass(frozen=True, slots=True)
class DeviceIdentity:
    """Who a device is, so a reconnect or a replay is recognised as the same device."""

    kind: str
    name: str
    url: str = ""
    serial: str | None = None
    vid: int | None = None
    pid: int | None = None
    address: str | None = None

    @property
    def vid_pid(self) -> str | None:
        return None if self.vid is None or self.pid is None else f"{self.vid:04x}:{self.pid:04x}"


@dataclass(frozen=True, slots=True)
class DeviceClockSpec:
    """How a device counts time: ``tick_hz`` ticks per second, wrapping at ``wrap_ticks`` (if it wraps)."""

    tick_hz: float
    wrap_ticks: int | None = None


@dataclass(frozen=True, slots=True)
class StreamInfo:
    """Metadata of one stream.

    Args:
        name: unique on the bus, ``<device>/<stream>`` (e.g. ``wrist/imu``).
        kind: what the values are (``imu``, ``euler``, ``mag``, ``quat``, ...).
        channels: one name per value column.
        units: one unit per channel (SI unless the name says otherwise).
        nominal_rate_hz: the rate the device is configured for, or ``None`` if irregular.
        device: the device identity.
        frame: the coordinate frame of vector channels, in words.
        clock: the device clock, or ``None`` when readings carry no device time.
        quantum: per channel, the step the device quantises to when every value is an exact
            ``integer * quantum`` in float64 (lets sessions store them as integers, losslessly);
            0.0 for channels without one. ``None`` for none at all.
    """

    name: str
    kind: str
    channels: tuple[str, ...]
    units: tuple[str, ...]
    nominal_rate_hz: float | None
    device: DeviceIdentity
    frame: str | None = None
    clock: DeviceClockSpec | None = None
    quantum: tuple[float, ...] | None = None
    extra: dict[str, str | bool] = field(default_factory=dict)   # kept as JSON: what made the stream

    def __post_init__(self) -> None:
        if len(self.channels) != len(self.units):
            raise ValueError(f"stream {self.name}: {len(self.channels)} channels but {len(self.units)} units")
        if self.quantum is not None and len(self.quantum) != len(self.channels):
            raise ValueError(f"stream {self.name}: {len(self.channels)} channels but {len(self.quantum)} quanta")

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> StreamInfo:
        d: dict[str, Any] = json.loads(text)
        dev = DeviceIdentity(**d.pop("device"))
        clk = d.pop("clock")
        q = d.pop("quantum", None)
        return cls(device=dev, clock=None if clk is None else DeviceClockSpec(**clk),
                   quantum=None if q is None else tuple(q),
                   channels=tuple(d.pop("channels")), units=tuple(d.pop("units")), **d)


class Direction(enum.IntEnum):
    """Which way a raw chunk went: from the device (RX) or to it (TX)."""

    RX = 0
    TX = 1


class Chunk(NamedTuple):
    """Bytes as a transport delivered them, stamped with the host monotonic time of arrival."""

    data: bytes
    t_ns: int
    direction: Direction = Direction.RX


class DeviceChunk(NamedTuple):
    """A raw chunk on the bus, tagged with the device it came from (what the recorder stores)."""

    device: str
    chunk: Chunk


class ChunkRun:
    """Many chunks as columns: their bytes concatenated, their lengths, arrival times and directions.

    Offline replay hands these to devices so that a whole run is decoded with numpy, without one
    Python object per chunk; ``run[i]`` and iteration give ordinary ``Chunk``s when needed.
    """

    __slots__ = ("_offsets", "data", "directions", "lengths", "t_ns")

    def __init__(self, data: bytes, lengths: np.ndarray, t_ns: np.ndarray, directions: np.ndarray) -> None:
        self.data = data
        self.lengths = lengths
        self.t_ns = t_ns
        self.directions = directions
        self._offsets: np.ndarray | None = None

    @classmethod
    def from_chunks(cls, chunks: list[Chunk]) -> ChunkRun:
        n = len(chunks)
        return cls(b"".join(c.data for c in chunks), np.fromiter((len(c.data) for c in chunks), np.int64, n),
                   np.fromiter((c.t_ns for c in chunks), np.int64, n),
                   np.fromiter((int(c.direction) for c in chunks), np.uint8, n))

    @property
    def offsets(self) -> np.ndarray:
        """Start offset of each chunk in ``data``, plus the total at the end."""
        if self._offsets is None:
            o = np.zeros(len(self.lengths) + 1, np.int64)
            np.cumsum(self.lengths, out=o[1:])
            self._offsets = o
        return self._offsets

    @property
    def all_rx(self) -> bool:
        return not bool(self.directions.any())

    def __len__(self) -> int:
        return int(self.lengths.shape[0])

    def __getitem__(self, i: int) -> Chunk:
        o = self.offsets
        return Chunk(self.data[o[i]:o[i + 1]], int(self.t_ns[i]), Direction(int(self.directions[i])))

    def slice(self, start: int, stop: int) -> ChunkRun:
        o = self.offsets
        stop = min(stop, len(self))
        return ChunkRun(self.data[o[start]:o[stop]], self.lengths[start:stop], self.t_ns[start:stop],
                        self.directions[start:stop])

    def __iter__(self) -> Iterator[Chunk]:
        o = self.offsets.tolist()
        d = self.data
        dirs = (Direction.RX, Direction.TX)
        for i, (t, dr) in enumerate(zip(self.t_ns.tolist(), self.directions.tolist(), strict=True)):
            yield Chunk(d[o[i]:o[i + 1]], t, dirs[dr])


class DeviceChunks(NamedTuple):
    """Many raw chunks of one device at once (the batch decoding path publishes these)."""

    device: str
    chunks: ChunkRun


class ClockState(NamedTuple):
    """A device-to-host clock fit at one moment: ``bus = host_ref + (device - device_ref) * rate``."""

    stream: str
    t_host_ns: int
    epoch: int
    device_ref_ns: int
    host_ref_ns: int
    rate: float
    points: int
    pseudo: bool

    @property
    def drift_ppm(self) -> float:
        """How fast the device clock runs relative to the host, ppm (positive: the device is fast)."""
        return (1.0 / self.rate - 1.0) * 1e6 if self.rate > 0 else float("nan")

    def to_dict(self) -> dict[str, Any]:
        d = self._asdict()
        d["drift_ppm"] = self.drift_ppm
        return d


class EventKind(str, enum.Enum):  # noqa: UP042 - str() and format() of a member keep their meaning
    OPENED = "opened"
    STREAMING = "streaming"
    DISCONNECTED = "disconnected"
    RECONNECTING = "reconnecting"
    RECONNECTED = "reconnected"
    FINISHED = "finished"
    FAILED = "failed"
    CLOCK_RESET = "clock_reset"
    PROTOCOL_ERRORS = "protocol_errors"
    OVERFLOW = "overflow"
    NOTE = "note"


class DeviceEvent(NamedTuple):
    """Something that happened to a device (or the recorder), kept in the session's event log."""

    source: str
    kind: EventKind
    t_host_ns: int
    detail: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"source": self.source, "kind": self.kind.value, "t_host_ns": self.t_host_ns, "detail": self.detail}


class DeviceDescriptor(NamedTuple):
    """A blob that describes a device, learned while it runs (a HID report descriptor, a factory
    calibration read in the handshake); stored with the device in the session, the latest winning."""

    device: str
    key: str
    data: bytes
    t_host_ns: int


#: Everything the bus carries.
BusItem = Sample | SampleBatch | DeviceChunk | DeviceChunks | ClockState | DeviceEvent | DeviceDescriptor
