"""``replay://SESSION.mcap?device=NAME`` - a recorded device, replayed below its codec.

The transport returns the device's recorded chunks with their recorded arrival times (so the same
Codec, Device and ClockSync produce the same samples), paced by deadline sleeping with a short
final spin: in real time, at any speed factor, or as fast as possible (``speed=0``, deterministic,
for CI). ``loop=true`` starts over, shifting times by the take's length so they keep increasing.
Writes during the device's handshake are compared with the recorded TX chunks.

Several replayed devices share one timeline when given the same ``start_ns`` (host time at which
the recording's ``t0_ns`` is played); ``capture.app.replay`` does this for whole sessions. The
transport declares both abilities (``devices.transports.base``): it is a ``BatchSource`` (many
chunks at once, by recorded time) and a ``RecordedTimeline`` (``set_timeline``, ``lateness_ns``).
"""

from __future__ import annotations

import logging
from collections import deque
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError, DeviceIOError, EndOfStream, ProtocolError
from capture.sample import Chunk, ChunkRun, Direction
from capture.session import DeviceRecord, SessionReader
from devices.options import Option
from devices.transports.base import Transport
from devices.transports.hid import HidTransportBase

if TYPE_CHECKING:
    from collections.abc import Mapping

    from devices.transports.base import BatchSource, RecordedTimeline

log = logging.getLogger(__name__)


class ReplayTransport(Transport, HidTransportBase):
    """Recorded chunks of one device, replayed with their timing; see the module docstring.

    For a HID device it also answers the HID handshake calls from the recording: feature reports
    and the report descriptor from the device's descriptors (``hid.feature.XX``,
    ``hid.report_descriptor``), feature writes compared like output reports, and the bus it was on.

    It is a ``BatchSource`` and a ``RecordedTimeline``.
    """

    scheme = "replay"
    usage = "replay://SESSION.mcap?device=NAME&speed=1"
    options: ClassVar[dict[str, Option]] = {
        "device": Option(str, "", "which recorded device (needed if the session has several)"),
        "speed": Option(float, 1.0, "playback speed factor; 0 = as fast as possible", min=0.0, max=1000.0),
        "loop": Option(bool, False, "start over at the end"),
        "start_ns": Option(int, 0, "host time at which t0_ns is played (0 = when opened)"),
        "t0_ns": Option(int, 0, "recorded time played at start_ns (0 = the device's first chunk)"),
        "stamp": Option(str, "recorded", "chunk times: the recorded ones, or the time of replay", ("recorded", "now")),
        "strict": Option(bool, False, "fail when a handshake write differs from the recording"),
    }

    def __init__(self, address: str, options: Mapping[str, Any] | None = None, clock: Clock = MONOTONIC) -> None:
        super().__init__(address, options, clock)
        self.session = SessionReader.open(address)
        devs = self.session.devices
        name = self.opts["device"]
        if not name:
            if len(devs) != 1:
                raise ConfigError(f"{self.url}: the session has {len(devs)} devices ({', '.join(devs) or 'none'});"
                                  " choose one with ?device=NAME", source=self.url)
            name = next(iter(devs))
        if name not in devs:
            raise ConfigError(f"{self.url}: no device {name!r} in the session (it has: {', '.join(devs) or 'none'})",
                              source=self.url)
        self.record: DeviceRecord = devs[name]
        self._chunks: ChunkRun | None = None
        self._open = False
        self._i = 0
        self._pass = 0
        self.tx_mismatches = 0
        self.opens = 0
        self._timeline: tuple[int, int] | None = None
        #: how late each paced chunk was delivered after its deadline, ns (``RecordedTimeline``)
        self.lateness_ns: deque[int] = deque(maxlen=200_000)
        self.bus = self._recorded_bus()

    def set_timeline(self, start_ns: int, t0_ns: int = 0) -> None:
        """Play recorded time ``t0_ns`` (0: the first chunk) at host time ``start_ns``; several replayed
        devices given the same timeline stay in step. Call before the device is opened."""
        self._timeline = (start_ns, t0_ns)

    def implied_kind(self) -> str:
        return self.record.kind

    def implied_device_options(self) -> dict[str, Any]:
        return dict(self.record.options)

    def implied_name(self) -> str:
        return self.record.name

    @property
    def is_open(self) -> bool:
        return self._open

    def open(self) -> None:
        self.opens += 1
        self.bus = self._recorded_bus()
        if self._chunks is None:
            run = self.session.raw_run(self.record.name)
            self._chunks = run
            if run.all_rx:
                self._rx = run
                self._tx: deque[Chunk] = deque()
            else:
                every = list(run)
                self._rx = ChunkRun.from_chunks([c for c in every if c.direction is Direction.RX])
                self._tx = deque(c for c in every if c.direction is Direction.TX)
            self._rx_t = self._rx.t_ns
            if not len(self._rx):
                raise EndOfStream(f"{self.url}: the session holds no data for {self.record.name}", source=self.url)
            first, last = int(self._rx_t[0]), int(self._rx_t[-1])
            n = len(self._rx)
            self._span = (last - first) + ((last - first) // (n - 1) if n > 1 else 1_000_000)
            self._t0 = self.opts["t0_ns"] or first
            self._start = self._timeline[0] if self._timeline else (self.opts["start_ns"] or self.clock.now_ns())
            if self._timeline and self._timeline[1]:
                self._t0 = self._timeline[1]
        self._open = True

    def close(self) -> None:
        self._open = False

    def first_time_ns(self) -> int | None:
        """Recorded time of the next chunk to be read (for merging devices by time)."""
        if self._chunks is None or self._i >= len(self._rx):
            return None
        return int(self._rx_t[self._i]) + self._pass * self._span

    # -- HID handshake calls, answered from the recording -------------------------------------------
    def _descriptor(self, key: str) -> bytes | None:
        """The version of a descriptor that the current open recorded (the n-th open read the n-th
        version; a device that reconnected over Bluetooth after USB has one of each)."""
        versions = self.record.history.get(key)
        if not versions:
            return self.record.descriptors.get(key)
        return versions[min(max(self.opens - 1, 0), len(versions) - 1)]

    def _recorded_bus(self) -> str:
        """The bus the current open was on (``bus``, kept up to date by ``open``)."""
        return (self._descriptor("hid.bus") or b"unknown").decode(errors="replace")

    def get_feature_report(self, report_id: int, length: int) -> bytes:
        blob = self._descriptor(f"hid.feature.{report_id:02x}")
        if blob is None:
            raise DeviceIOError(f"{self.url}: feature report 0x{report_id:02x} was not recorded for"
                                f" {self.record.name}", source=self.url)
        return bytes(blob[:length])

    def send_feature_report(self, data: bytes) -> Chunk:
        return self.write(data)

    def report_descriptor(self) -> bytes:
        blob = self._descriptor("hid.report_descriptor")
        if blob is None:
            raise DeviceIOError(f"{self.url}: no report descriptor was recorded for {self.record.name}",
                                source=self.url)
        return bytes(blob)

    def write(self, data: bytes) -> Chunk:
        if not self._open:
            raise DeviceIOError(f"{self.url}: write on a closed transport", source=self.url)
        expected = self._tx.popleft() if self._tx else None
        if expected is None or expected.data != bytes(data):
            self.tx_mismatches += 1
            msg = (f"{self.url}: handshake write {bytes(data).hex()} differs from the recording "
                   f"({expected.data.hex() if expected else 'nothing recorded'})")
            if self.opts["strict"]:
                raise ProtocolError(msg)
            log.warning(msg)
        return self.stamp_tx(data)

    @property
    def batches(self) -> bool:
        """As fast as possible with recorded stamps: chunks may be handed over many at a time."""
        return bool(self.opts["speed"] == 0 and self.opts["stamp"] == "recorded")

    def read_many(self, timeout: float, max_chunks: int, until_ns: int | None = None) -> ChunkRun | list[Chunk]:
        """Up to ``max_chunks`` chunks at once (only when ``batches``; otherwise one, paced).
        With ``until_ns``, only chunks recorded before that time (possibly none)."""
        if not self.batches:
            c = self.read(timeout)
            return [] if c is None else [c]
        rx = self._next_pass_if_done()
        end = min(len(rx), self._i + max_chunks)
        if until_ns is not None:
            end = min(end, int(np.searchsorted(self._rx_t, until_ns - self._pass * self._span, side="left")))
        part = rx.slice(self._i, end) if end > self._i else None
        self._i = max(self._i, end)
        if part is None:
            return []
        shift = self._pass * self._span
        if shift:
            part = ChunkRun(part.data, part.lengths, part.t_ns + shift, part.directions)
        return part

    def _next_pass_if_done(self) -> ChunkRun:
        """The RX chunks, starting the next loop pass if this one is done.

        Raises:
            DeviceIOError: the transport is closed.
            EndOfStream: the recording is over and looping is off.
        """
        if not self._open:
            raise DeviceIOError(f"{self.url}: read on a closed transport", source=self.url)
        if self._i >= len(self._rx):
            if not self.opts["loop"]:
                raise EndOfStream(f"{self.url}: end of recording", source=self.url)
            self._i = 0
            self._pass += 1
        return self._rx

    def read(self, timeout: float) -> Chunk | None:
        c = self._next_pass_if_done()[self._i]
        shift = self._pass * self._span
        t_rec = c.t_ns + shift
        speed = self.opts["speed"]
        if speed > 0:
            deadline = self._start + int((t_rec - self._t0) / speed)
            now = self.clock.now_ns()
            if deadline - now > timeout * 1e9:
                self.clock.sleep_until_ns(now + int(timeout * 1e9))
                return None
            self.clock.sleep_until_ns(deadline)
            late = self.clock.now_ns() - deadline
            self.lateness_ns.append(late)
        self._i += 1
        if self.opts["stamp"] == "now":
            return Chunk(c.data, self.clock.now_ns(), c.direction)
        return Chunk(c.data, t_rec, c.direction) if shift else c

    @property
    def chunks_total(self) -> int:
        return 0 if self._chunks is None else len(self._rx)


if TYPE_CHECKING:  # the abilities it declares, checked by mypy
    _batches: type[BatchSource] = ReplayTransport
    _timeline: type[RecordedTimeline] = ReplayTransport
