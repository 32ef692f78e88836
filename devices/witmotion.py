"""WitMotion WT901-family IMUs (serial, USB-serial or Bluetooth SPP).

Packets of one output cycle (time, acceleration, angular rate, angle, magnetometer, quaternion,
whichever are enabled) are gathered into one reading per stream, all with the cycle's device time.
The sensor sends a cycle's packets in increasing type order, so a type that is not larger than the
previous one starts a new cycle. The largest type that ends a cycle is learned as the cycle's last
packet, and from then on each cycle is emitted as soon as that packet arrives (no added latency);
a lost last packet only delays that one cycle.

Scalings (WT901 datasheet): acceleration ``raw/32768*16 g``, angular rate ``raw/32768*2000 deg/s``,
angle ``raw/32768*180 deg``, temperature ``raw/100 degC``, quaternion ``raw/32768``; the
magnetometer is reported in raw counts (its scale depends on the chip and calibration).

The time packet gives a millisecond of day; with ``device_clock=true`` (enable the time output on
the sensor) it is the device clock, wrapping at midnight.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from capture.sample import ChunkRun, DeviceClockSpec, StreamInfo
from devices.base import BatchReadings, Device, Reading, StreamReadings
from devices.codecs.witmotion import (
    ACC,
    ANGLE,
    GYRO,
    HEADER,
    MAG,
    PACKET_LEN,
    QUAT,
    TIME,
    WitMotionCodec,
    WitPacket,
)
from devices.options import Option

if TYPE_CHECKING:
    from collections.abc import Iterable

G = 9.80665
ACC_SCALE = 16.0 / 32768.0 * G
GYRO_SCALE = math.radians(2000.0 / 32768.0)
ANGLE_SCALE = 180.0 / 32768.0
TEMP_SCALE = 0.01
QUAT_SCALE = 1.0 / 32768.0
MS_PER_DAY = 86_400_000

IMU, EULER, MAGS, QUATS = 0, 1, 2, 3
FRAME = "sensor frame as printed on the WT901 case: x, y, z right-handed"


class WitMotionImu(Device[WitMotionCodec]):
    """A WitMotion WT901-family IMU."""

    kind = "witmotion"
    description = "WitMotion WT901-family IMU (0x55-framed packets)"
    codec_cls = WitMotionCodec
    options: ClassVar[dict[str, Option]] = {
        "rate": Option(float, 100.0, "output rate configured on the sensor, Hz", min=0.1, max=1000.0),
        "device_clock": Option(bool, False, "the sensor outputs time packets (0x50): use them as the device clock"),
    }

    def declare_streams(self) -> list[StreamInfo]:
        rate = self.opts["rate"]
        clock = DeviceClockSpec(tick_hz=1000.0, wrap_ticks=MS_PER_DAY) if self.opts["device_clock"] else None
        self._cycle: dict[int, WitPacket] = {}
        self._terminator: int | None = None
        self._order: list[int] = []
        self._cycle_order: tuple[int, ...] | None = None  # types of the last complete cycle
        return [
            self.stream_info("imu", "imu", ("ax", "ay", "az", "gx", "gy", "gz", "temp"),
                             ("m/s^2", "m/s^2", "m/s^2", "rad/s", "rad/s", "rad/s", "degC"), rate, FRAME, clock,
                             (ACC_SCALE,) * 3 + (GYRO_SCALE,) * 3 + (TEMP_SCALE,)),
            self.stream_info("euler", "euler", ("roll", "pitch", "yaw"), ("deg", "deg", "deg"), rate, FRAME, clock,
                             (ANGLE_SCALE,) * 3),
            self.stream_info("mag", "mag", ("mx", "my", "mz"), ("count", "count", "count"), rate, FRAME, clock,
                             (1.0,) * 3),
            self.stream_info("quat", "quat", ("w", "x", "y", "z"), ("1", "1", "1", "1"), rate, FRAME, clock,
                             (QUAT_SCALE,) * 4),
        ]

    def frame_to_readings(self, frame: WitPacket) -> Iterable[Reading]:
        t = frame.type
        out: list[Reading] = []
        if self._order and t <= self._order[-1]:
            # A new cycle begins: the previous one ended with the packet before this one.
            last = self._order[-1]
            if self._terminator is None or last > self._terminator:
                self._terminator = last
            out = self._emit()
        self._cycle[t] = frame
        self._order.append(t)
        if t == self._terminator:
            self._cycle_order = tuple(self._order)
            out += self._emit()
        return out

    def batch_ready(self) -> bool:
        return self._cycle_order is not None and not self._cycle and not self._order and not self.codec.buffered

    def decode_batch(self, chunks: ChunkRun) -> BatchReadings | None:
        """Vectorised decoding of clean data: whole cycles of the learned layout, no garbage.
        Anything else (a partial cycle pending, a bad byte, a different layout) returns ``None``
        and the chunks take the per-chunk path."""
        order = self._cycle_order
        if order is None or self.codec.buffered or self._cycle or self._order:
            return None
        buf = chunks.data
        n = len(buf)
        per_cycle = len(order)
        if n == 0 or n % (PACKET_LEN * per_cycle):
            return None
        a = np.frombuffer(buf, np.uint8).reshape(-1, PACKET_LEN)
        types = a[:, 1]
        if not (np.all(a[:, 0] == HEADER)
                and np.array_equal(types.reshape(-1, per_cycle),
                                   np.broadcast_to(np.array(order, np.uint8), (len(a) // per_cycle, per_cycle)))
                and np.array_equal((a[:, :10].sum(axis=1, dtype=np.uint32) & 0xFF).astype(np.uint8), a[:, 10])):
            return None
        clocked = self.streams[IMU].clock is not None
        if clocked and TIME not in order:
            return None
        ncyc = len(a) // per_cycle
        self.codec.stats.bytes_in += n
        self.codec.stats.frames += len(a)
        ends = chunks.offsets[1:]
        term_end = (np.arange(1, ncyc + 1, dtype=np.int64) * per_cycle) * PACKET_LEN - 1
        chunk = np.searchsorted(ends, term_end, side="right").astype(np.int64)
        cyc = a.reshape(ncyc, per_cycle, PACKET_LEN)

        def rows(t: int) -> np.ndarray | None:
            return cyc[:, order.index(t), 2:10] if t in order else None

        def words(t: int) -> np.ndarray | None:
            r = rows(t)
            return None if r is None else np.ascontiguousarray(r).view("<i2").reshape(ncyc, 4).astype(np.float64)

        ticks = None
        tr = rows(TIME)
        if tr is not None and clocked:
            f = tr.astype(np.int64)
            ticks = ((f[:, 3] * 60 + f[:, 4]) * 60 + f[:, 5]) * 1000 + (f[:, 6] | (f[:, 7] << 8))
        present: list[tuple[int, np.ndarray]] = []
        acc, gyr = words(ACC), words(GYRO)
        if acc is not None or gyr is not None:
            v = np.full((ncyc, 7), np.nan)
            if acc is not None:
                v[:, 0:3] = acc[:, 0:3] * ACC_SCALE
                v[:, 6] = acc[:, 3] * TEMP_SCALE
            if gyr is not None:
                v[:, 3:6] = gyr[:, 0:3] * GYRO_SCALE
            present.append((IMU, v))
        ang = words(ANGLE)
        if ang is not None:
            present.append((EULER, ang[:, 0:3] * ANGLE_SCALE))
        mag = words(MAG)
        if mag is not None:
            present.append((MAGS, mag[:, 0:3].copy()))
        q = words(QUAT)
        if q is not None:
            present.append((QUATS, q * QUAT_SCALE))
        n_streams = len(present)
        base = np.arange(ncyc, dtype=np.int64) * n_streams
        out = {si: StreamReadings(v, ticks if self.streams[si].clock is not None else None, chunk, base + k)
               for k, (si, v) in enumerate(present)}
        return BatchReadings(out)

    def _emit(self) -> list[Reading]:
        c = self._cycle
        self._cycle = {}
        self._order = []
        ticks: int | None = None
        tp = c.get(TIME)
        if tp is not None:
            _, _, _, hh, mi, ss, ms = tp.time_fields()
            ticks = ((hh * 60 + mi) * 60 + ss) * 1000 + ms
        out: list[Reading] = []
        acc, gyr = c.get(ACC), c.get(GYRO)
        if acc is not None or gyr is not None:
            nan = float("nan")
            if acc is not None:
                a = acc.words()
                av = (a[0] * ACC_SCALE, a[1] * ACC_SCALE, a[2] * ACC_SCALE)
                temp = a[3] * TEMP_SCALE
            else:
                av, temp = (nan, nan, nan), nan
            if gyr is not None:
                g = gyr.words()
                gv = (g[0] * GYRO_SCALE, g[1] * GYRO_SCALE, g[2] * GYRO_SCALE)
            else:
                gv = (nan, nan, nan)
            out.append(Reading(IMU, av + gv + (temp,), ticks))
        ang = c.get(ANGLE)
        if ang is not None:
            w = ang.words()
            out.append(Reading(EULER, (w[0] * ANGLE_SCALE, w[1] * ANGLE_SCALE, w[2] * ANGLE_SCALE), ticks))
        mag = c.get(MAG)
        if mag is not None:
            w = mag.words()
            out.append(Reading(MAGS, (float(w[0]), float(w[1]), float(w[2])), ticks))
        q = c.get(QUAT)
        if q is not None:
            w = q.words()
            out.append(Reading(QUATS, tuple(x * QUAT_SCALE for x in w), ticks))
        return out

    def drain_readings(self) -> list[Reading]:
        return self._emit() if self._cycle else []

    def reset_after_reconnect(self) -> int:
        self._cycle = {}
        self._order = []
        return super().reset_after_reconnect()


def encode_cycle(codec: WitMotionCodec, acc_g: tuple[float, float, float], gyro_dps: tuple[float, float, float],
                 angle_deg: tuple[float, float, float] | None, temp_c: float = 25.0,
                 ms_of_day: int | None = None,
                 mag: tuple[int, int, int] | None = None) -> tuple[bytes, list[WitPacket]]:
    """The bytes a WT901 sends for one output cycle (used by simulators); returns (bytes, packets)."""

    def q(v: float, full: float) -> int:
        return max(-32768, min(32767, round(v / full * 32768.0)))

    pk: list[WitPacket] = []
    if ms_of_day is not None:
        ms_of_day %= MS_PER_DAY
        hh, rem = divmod(ms_of_day, 3_600_000)
        mi, rem = divmod(rem, 60_000)
        ss, ms = divmod(rem, 1000)
        pk.append(WitPacket.from_time(26, 11, 23, hh, mi, ss, ms))
    pk.append(WitPacket.from_words(ACC, (q(acc_g[0], 16), q(acc_g[1], 16), q(acc_g[2], 16),
                                        max(-32768, min(32767, round(temp_c * 100))))))
    pk.append(WitPacket.from_words(GYRO, (q(gyro_dps[0], 2000), q(gyro_dps[1], 2000), q(gyro_dps[2], 2000), 0)))
    if angle_deg is not None:
        pk.append(WitPacket.from_words(ANGLE, (q(angle_deg[0], 180), q(angle_deg[1], 180), q(angle_deg[2], 180), 0)))
    if mag is not None:
        pk.append(WitPacket.from_words(MAG, (mag[0], mag[1], mag[2], 0)))
    return b"".join(codec.encode(p) for p in pk), pk


__all__ = ["TIME", "WitMotionImu", "encode_cycle"]
