"""Phones that push their sensors to perfcap: the built-in phone page and the Sensor Logger app.

Both turn one network message (one chunk) into readings with the phone's own sample times, so
batched delivery is spread out by device time and the clock fit sees the newest sample of each
message (``capture.clocksync``). Readings of one message are emitted in device-time order.

``PhonePage`` (kind ``phone``) decodes the page protocol (``devices.codecs.phone_json``):

* ``imu`` (kind ``imu``): ``accelerationIncludingGravity`` (m/s^2) and ``rotationRate`` converted
  from deg/s to rad/s, alpha -> gx, beta -> gy, gamma -> gz (alpha is about the device x axis in
  all shipping browsers);
* ``user_acc`` (kind ``acc``): ``acceleration`` (gravity removed);
* ``attitude`` (kind ``euler``): deviceorientation alpha, beta, gamma in degrees (irregular);
* ``touch`` (kind ``touch``): phase (0 start, 1 move, 2 end, 3 cancel), id, x, y (CSS px), force,
  rx, ry (CSS px) (irregular).

All four share one device clock, ``event.timeStamp`` in microseconds (ticks = round(t_ms * 1000));
the motion streams have the ``rate`` option as nominal rate, so they form one clock domain and the
irregular streams another. ``null`` values become NaN; an event whose values are all ``null`` (a
desktop browser without sensors) gives no reading for that stream. The hello message fills
``info`` (id, ua, platform, screen, orientation angle); data ``seq`` gaps count as lost messages
and pongs give round-trip and offset estimates, all in ``health()``.

``SensorLoggerPhone`` (kind ``sensorlogger``) decodes Sensor Logger's HTTP push: ``acc``
(calibrated, gravity removed), ``gyro``, ``phone_gravity``, ``mag`` (uT), ``attitude`` (quaternion
w x y z from qw qx qy qz), ``total_acc`` (Android's ``totalacceleration``, gravity included) and
``baro`` (pressure in Pa, relative altitude in m; irregular). The device clock is the entries'
``time``, UTC epoch ns of the phone's wall clock. ``messageId`` gaps count as lost messages; a
repeated or older ``messageId`` (a retried POST, a late one) is counted and dropped, since its samples
were delivered already or would go back in time; so is one implausibly far ahead (``MAX_ID_JUMP``,
``id_jumps``), which would otherwise make every later message late, unless the next one follows it.
The ``platform`` option sets the sign convention: ``standardised`` (default) and ``android`` take
values as sent (Android convention: lying flat, screen up, gravity and acceleration read +z, as an
accelerometer does); ``ios`` negates
acceleration, gravity and total acceleration (iOS sends them with the opposite sign when
"Standardise Units & Frames" is off, the app's default). Gyroscope and magnetometer are the same on
both; the attitude is passed on as the app reports it (its reference frame differs by platform).
Sensors not mapped to a stream are counted in ``health()["unused_entries"]``.
"""

from __future__ import annotations

import collections
import logging
import math
from typing import TYPE_CHECKING, Any, ClassVar

from capture.clock import MONOTONIC, Clock
from capture.sample import Chunk, DeviceClockSpec, StreamInfo
from devices.base import Device, Reading
from devices.codecs.phone_json import (
    PageCodec,
    PageData,
    PageHello,
    PagePong,
    SensorLoggerCodec,
    SensorLoggerMessage,
)
from devices.options import Option

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping

    from devices.transports.base import Transport

log = logging.getLogger(__name__)

FRAME = "phone frame: x right, y up the screen, z out of the screen (right-handed)"
ACC_CHANNELS = ("ax", "ay", "az")
ACC_UNITS = ("m/s^2",) * 3

#: The page's clock: ``event.timeStamp`` / ``performance.now()`` (ms since the page's time origin) in us.
PAGE_CLOCK = DeviceClockSpec(tick_hz=1e6)
#: Sensor Logger's clock: ``time``, UTC epoch ns of the phone's wall clock.
SENSORLOGGER_CLOCK = DeviceClockSpec(tick_hz=1e9)

_DEG = math.pi / 180.0


def _all_nan(v: tuple[float, ...]) -> bool:
    return all(math.isnan(x) for x in v)


class PhonePage(Device[PageCodec]):
    """A phone running perfcap's built-in web page."""

    kind = "phone"
    description = "perfcap's phone web page: devicemotion, deviceorientation and touches over a WebSocket"
    codec_cls = PageCodec
    options: ClassVar[dict[str, Option]] = {
        "rate": Option(float, 60.0, "nominal devicemotion rate of the phone's browser, Hz", min=1.0, max=1000.0),
        "invert_acc": Option(bool, False, "flip the sign of both accelerations (for browsers that report them "
                             "inverted, such as older iOS Safari; check by laying the phone flat: +z expected)"),
    }

    IMU, USER_ACC, ATTITUDE, TOUCH = 0, 1, 2, 3
    #: tens of ms of network jitter: a longer fit window steadies the drift; step_s keeps a Wi-Fi
    #: stall of seconds from starting clock epochs (the page clock itself never steps)
    clock_sync_options: ClassVar[dict[str, Any]] = {"window_s": 60.0, "step_s": 0.05}
    one_fit_per_clock = True
    #: a data seq step larger than this is a new numbering (counted in ``seq_restarts``), not lost messages
    MAX_SEQ_JUMP = 1_000_000

    def __init__(self, name: str, transport: Transport, options: Mapping[str, Any] | None = None,
                 clock: Clock = MONOTONIC, strict: bool = False) -> None:
        super().__init__(name, transport, options, clock, strict)
        #: what the page said about itself in its hello (id, ua, platform, screen, orient, ...)
        self.info: dict[str, Any] = {}
        self.hellos = 0
        self.lost_messages = 0
        self.seq_restarts = 0
        self.pongs = 0
        self.rtt_last_ns: int | None = None
        self.rtt_min_ns: int | None = None
        #: host monotonic ns minus page ms-clock (as ns), from the pong with the smallest round trip
        self.page_offset_ns: int | None = None
        self._last_seq: int | None = None
        self._chunk_t: int | None = None
        self._sign = -1.0 if self.opts["invert_acc"] else 1.0

    def declare_streams(self) -> list[StreamInfo]:
        rate = self.opts["rate"]
        return [
            self.stream_info("imu", "imu", (*ACC_CHANNELS, "gx", "gy", "gz"), ACC_UNITS + ("rad/s",) * 3, rate,
                             FRAME, PAGE_CLOCK),
            self.stream_info("user_acc", "acc", ACC_CHANNELS, ACC_UNITS, rate, FRAME, PAGE_CLOCK),
            self.stream_info("attitude", "euler", ("alpha", "beta", "gamma"), ("deg", "deg", "deg"), None,
                             "W3C deviceorientation: intrinsic Z-X'-Y'' angles of the phone frame", PAGE_CLOCK),
            self.stream_info("touch", "touch", ("phase", "id", "x", "y", "force", "rx", "ry"),
                             ("1", "1", "px", "px", "1", "px", "px"), None,
                             "CSS pixels from the top left of the page's viewport", PAGE_CLOCK),
        ]

    def process_chunk(self, chunk: Chunk) -> list[Any]:
        self._chunk_t = chunk.t_ns  # for the round trip of pongs
        return super().process_chunk(chunk)

    def send_ticks(self, frames: list[Any]) -> int | None:
        """The data message's ``sent`` (``performance.now()`` at ``ws.send``) in clock ticks."""
        for f in reversed(frames):
            if isinstance(f, PageData) and f.sent is not None:
                return round(f.sent * 1000.0)
        return None

    def frame_to_readings(self, frame: Any) -> Iterable[Reading]:
        if isinstance(frame, PageData):
            return self._data(frame)
        if isinstance(frame, PageHello):
            self.hellos += 1
            self.info.update(id=frame.id, ua=frame.ua, platform=frame.platform, screen=frame.screen,
                             orient=frame.orient, hello_t_ms=frame.t, version=frame.v)
            log.info("phone %s: page %s (%s) says hello: %s", self.name, frame.id, frame.platform, frame.ua[:120])
        elif isinstance(frame, PagePong):
            self._pong(frame)
        return []

    def _data(self, f: PageData) -> list[Reading]:
        last = self._last_seq
        if last is not None:
            if f.seq - last > self.MAX_SEQ_JUMP:  # not a gap of lost messages: a new numbering
                self.seq_restarts += 1
                log.info("phone %s: data seq jumped from %d to %d", self.name, last, f.seq)
            elif f.seq > last + 1:
                self.lost_messages += f.seq - last - 1
                log.debug("phone %s: %d message(s) lost before seq %d", self.name, f.seq - last - 1, f.seq)
            elif f.seq <= last:
                self.seq_restarts += 1
                log.info("phone %s: data seq went from %d to %d (page reloaded?)", self.name, last, f.seq)
        self._last_seq = f.seq
        if f.orient is not None:
            self.info["orient"] = f.orient
        s = self._sign
        out: list[Reading] = []
        for r in f.motion:
            tk = round(r[0] * 1000.0)
            imu = (s * r[4], s * r[5], s * r[6], r[7] * _DEG, r[8] * _DEG, r[9] * _DEG)
            if not _all_nan(imu):
                out.append(Reading(self.IMU, imu, tk))
            user = (s * r[1], s * r[2], s * r[3])
            if not _all_nan(user):
                out.append(Reading(self.USER_ACC, user, tk))
        for r in f.orientation:
            v = (r[1], r[2], r[3])
            if not _all_nan(v):
                out.append(Reading(self.ATTITUDE, v, round(r[0] * 1000.0)))
            if not math.isnan(r[4]):
                self.info["orientation_absolute"] = bool(r[4])
        for r in f.touches:
            out.append(Reading(self.TOUCH, r[1:], round(r[0] * 1000.0)))
        out.sort(key=lambda x: x.ticks or 0)  # stable: readings of one event keep their order (ticks always set)
        return out

    def _pong(self, p: PagePong) -> None:
        self.pongs += 1
        t = self._chunk_t
        if t is None or t < p.h:
            return
        rtt = t - p.h
        self.rtt_last_ns = rtt
        if self.rtt_min_ns is None or rtt <= self.rtt_min_ns:
            self.rtt_min_ns = rtt
            self.page_offset_ns = (p.h + t) // 2 - round(p.t * 1e6)

    def health(self) -> dict[str, Any]:
        """Base counters plus ``lost_messages`` (data ``seq`` gaps), ``seq_restarts``, ``hellos``,
        ``pongs`` and the round-trip estimates (ns)."""
        h = super().health()
        h.update(lost_messages=self.lost_messages, seq_restarts=self.seq_restarts, hellos=self.hellos,
                 pongs=self.pongs, rtt_last_ns=self.rtt_last_ns, rtt_min_ns=self.rtt_min_ns,
                 page_offset_ns=self.page_offset_ns)
        return h


class SensorLoggerPhone(Device[SensorLoggerCodec]):
    """A phone running the Sensor Logger app with HTTP push to perfcap."""

    kind = "sensorlogger"
    description = "Sensor Logger app (iOS/Android) HTTP push: accelerometer, gyroscope, gravity, magnetometer, ..."
    codec_cls = SensorLoggerCodec
    options: ClassVar[dict[str, Option]] = {
        "rate": Option(float, 100.0, "sampling frequency set in the app, Hz", min=0.1, max=1000.0),
        "platform": Option(str, "standardised", "sign convention of the values: standardised (the app's "
                           "'Standardise Units & Frames' on) and android take them as sent; ios negates the "
                           "accelerations and gravity", choices=("standardised", "android", "ios")),
    }

    ACC, GYRO, GRAVITY, MAG, ATTITUDE, TOTAL_ACC, BARO = range(7)
    #: 1 s batches: a longer fit window; the phone's wall clock can be stepped (NTP): new epoch
    clock_sync_options: ClassVar[dict[str, Any]] = {"window_s": 60.0, "step_s": 0.05}
    one_fit_per_clock = True
    #: recent messageIds remembered to tell a duplicate from a late message
    RECENT_IDS = 256
    #: a messageId this far ahead of the last is not believed on its own (one bad message would
    #: make every later one "late"): it is dropped and counted in ``id_jumps``, unless the next
    #: message continues from it (within ``RECENT_IDS``), which then starts the new numbering
    MAX_ID_JUMP = 100_000

    def __init__(self, name: str, transport: Transport, options: Mapping[str, Any] | None = None,
                 clock: Clock = MONOTONIC, strict: bool = False) -> None:
        super().__init__(name, transport, options, clock, strict)
        #: deviceId and sessionId of the messages
        self.info: dict[str, Any] = {}
        self.lost_messages = 0
        self.duplicate_messages = 0
        self.late_messages = 0
        self.sessions = 0
        #: entries of decoded sensors that no stream takes (uncalibrated variants), per name
        self.unused: dict[str, int] = {}
        self._session: str | None = None
        self._last_id: int | None = None
        self._recent: collections.deque[int] = collections.deque(maxlen=self.RECENT_IDS)
        self.id_jumps = 0
        self._jump: int | None = None  # the last messageId refused as a jump
        s = -1.0 if self.opts["platform"] == "ios" else 1.0
        # name -> (stream, per-value factors, how many values)
        self._map: dict[str, tuple[int, tuple[float, ...], int]] = {
            "accelerometer": (self.ACC, (s, s, s), 3),
            "gyroscope": (self.GYRO, (1.0, 1.0, 1.0), 3),
            "gravity": (self.GRAVITY, (s, s, s), 3),
            "magnetometer": (self.MAG, (1.0, 1.0, 1.0), 3),
            "orientation": (self.ATTITUDE, (1.0, 1.0, 1.0, 1.0), 4),
            "totalacceleration": (self.TOTAL_ACC, (s, s, s), 3),
            "barometer": (self.BARO, (100.0, 1.0), 2),  # hPa -> Pa
        }

    def declare_streams(self) -> list[StreamInfo]:
        rate = self.opts["rate"]
        c = SENSORLOGGER_CLOCK
        return [
            self.stream_info("acc", "acc", ACC_CHANNELS, ACC_UNITS, rate, FRAME, c),
            self.stream_info("gyro", "gyro", ("gx", "gy", "gz"), ("rad/s",) * 3, rate, FRAME, c),
            self.stream_info("phone_gravity", "acc", ACC_CHANNELS, ACC_UNITS, rate, FRAME, c),
            self.stream_info("mag", "mag", ("mx", "my", "mz"), ("uT",) * 3, rate, FRAME, c),
            self.stream_info("attitude", "quat", ("w", "x", "y", "z"), ("1",) * 4, rate,
                             "phone frame relative to the OS's reference frame (platform dependent)", c),
            self.stream_info("total_acc", "acc", ACC_CHANNELS, ACC_UNITS, rate, FRAME, c),
            self.stream_info("baro", "baro", ("pressure", "rel_alt"), ("Pa", "m"), None, None, c),
        ]

    def frame_to_readings(self, frame: SensorLoggerMessage) -> Iterable[Reading]:
        if not self._accept(frame):
            return []
        out: list[Reading] = []
        m = self._map
        for e in sorted(frame.entries, key=lambda x: x.time):  # stable
            spec = m.get(e.name)
            if spec is None:
                self.unused[e.name] = self.unused.get(e.name, 0) + 1
                continue
            si, k, n = spec
            v = e.values
            out.append(Reading(si, tuple(v[i] * k[i] for i in range(n)), e.time))
        return out

    def _accept(self, f: SensorLoggerMessage) -> bool:
        """Session and messageId bookkeeping; False for a message to drop."""
        if f.session_id != self._session:
            if self._session is not None:
                log.info("sensorlogger %s: new session %s (was %s)", self.name, f.session_id, self._session)
            self._session = f.session_id
            self.sessions += 1
            self._last_id = None
            self._recent.clear()
            self.info["session_id"] = f.session_id
        if self.info.get("device_id") != f.device_id:
            if "device_id" in self.info:
                log.warning("sensorlogger %s: deviceId changed from %s to %s", self.name, self.info["device_id"],
                            f.device_id)
            self.info["device_id"] = f.device_id
        last = self._last_id
        mid = f.message_id
        if last is not None:
            if mid <= last:
                if mid in self._recent:
                    self.duplicate_messages += 1
                    log.debug("sensorlogger %s: duplicate message %d dropped", self.name, mid)
                else:
                    self.late_messages += 1
                    log.info("sensorlogger %s: message %d arrived after %d; dropped", self.name, mid, last)
                return False
            if mid - last > self.MAX_ID_JUMP:
                jump = self._jump
                self._jump = mid
                if jump is None or not 0 < mid - jump <= self.RECENT_IDS:
                    self.id_jumps += 1
                    log.warning("sensorlogger %s: messageId jumped from %d to %d; message dropped (the numbering "
                                "moves there only if the next message follows it)", self.name, last, mid)
                    return False
                log.warning("sensorlogger %s: messageIds go on from %d (they were at %d)", self.name, mid, last)
            elif mid > last + 1:
                self.lost_messages += mid - last - 1
                log.debug("sensorlogger %s: %d message(s) lost before %d", self.name, mid - last - 1, mid)
        self._last_id = mid
        self._recent.append(mid)
        return True

    def health(self) -> dict[str, Any]:
        """Base counters plus message bookkeeping (``lost_messages``, ``duplicate_messages``,
        ``late_messages``, ``id_jumps``, ``sessions``) and entry counts the streams do not take
        (``unknown_entries`` from the codec, ``unused_entries``)."""
        h = super().health()
        codec = self.codec
        h.update(lost_messages=self.lost_messages, duplicate_messages=self.duplicate_messages,
                 late_messages=self.late_messages, id_jumps=self.id_jumps, sessions=self.sessions,
                 unknown_entries=sum(codec.unknown_names.values()), unknown_names=dict(codec.unknown_names),
                 unused_entries=sum(self.unused.values()))
        return h


__all__ = ["FRAME", "PAGE_CLOCK", "SENSORLOGGER_CLOCK", "PhonePage", "SensorLoggerPhone"]
