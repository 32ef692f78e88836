"""WitMotion WT901-family IMUs (serial, USB-serial or Bluetooth SPP).

Packets of one output cycle (time, acceleration, angular rate, angle, magnetometer, quaternion,
whichever are enabled) are gathered into one reading per stream, all with the cycle's device time.
The device learns which packet type closes a cycle from the first two cycles, then emits each
cycle as soon as its last packet arrives (no added latency).

Scalings (WT901 datasheet): acceleration ``raw/32768*16 g``, angular rate ``raw/32768*2000 deg/s``,
angle ``raw/32768*180 deg``, temperature ``raw/100 degC``, quaternion ``raw/32768``; the
magnetometer is reported in raw counts (its scale depends on the chip and calibration).

The time packet gives a millisecond of day; with ``device_clock=true`` (enable the time output on
the sensor) it is the device clock, wrapping at midnight.
"""

from __future__ import annotations

import math
from typing import Any, Iterable

from capture.sample import DeviceClockSpec, StreamInfo
from devices.base import Device, Reading
from devices.codecs.witmotion import ACC, ANGLE, GYRO, MAG, QUAT, TIME, WitMotionCodec, WitPacket
from devices.options import Option

G = 9.80665
ACC_SCALE = 16.0 / 32768.0 * G
GYRO_SCALE = math.radians(2000.0 / 32768.0)
ANGLE_SCALE = 180.0 / 32768.0
TEMP_SCALE = 0.01
QUAT_SCALE = 1.0 / 32768.0
MS_PER_DAY = 86_400_000

IMU, EULER, MAGS, QUATS = 0, 1, 2, 3
FRAME = "sensor frame as printed on the WT901 case: x, y, z right-handed"


class WitMotionImu(Device):
    """A WitMotion WT901-family IMU."""

    kind = "witmotion"
    description = "WitMotion WT901-family IMU (0x55-framed packets)"
    codec_cls = WitMotionCodec
    options = {
        "rate": Option(float, 100.0, "output rate configured on the sensor, Hz", min=0.1, max=1000.0),
        "device_clock": Option(bool, False, "the sensor outputs time packets (0x50): use them as the device clock"),
    }

    def declare_streams(self) -> list[StreamInfo]:
        rate = self.opts["rate"]
        clock = DeviceClockSpec(tick_hz=1000.0, wrap_ticks=MS_PER_DAY) if self.opts["device_clock"] else None
        self._cycle: dict[int, WitPacket] = {}
        self._terminator: int | None = None
        self._order: list[int] = []
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
        if t in self._cycle:
            # This type repeats: the previous cycle ended with the packet before it.
            if self._order:
                self._terminator = self._order[-1]
            out = self._emit()
        self._cycle[t] = frame
        self._order.append(t)
        if t == self._terminator:
            out += self._emit()
        return out

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

    def reset_after_reconnect(self) -> int:
        self._cycle = {}
        self._order = []
        return super().reset_after_reconnect()


def encode_cycle(codec: WitMotionCodec, acc_g: tuple[float, float, float], gyro_dps: tuple[float, float, float],
                 angle_deg: tuple[float, float, float] | None, temp_c: float = 25.0,
                 ms_of_day: int | None = None, mag: tuple[int, int, int] | None = None) -> tuple[bytes, list[WitPacket]]:
    """The bytes a WT901 sends for one output cycle (used by simulators); returns (bytes, packets)."""

    def q(v: float, full: float) -> int:
        return max(-32768, min(32767, int(round(v / full * 32768.0))))

    pk: list[WitPacket] = []
    if ms_of_day is not None:
        ms_of_day %= MS_PER_DAY
        hh, rem = divmod(ms_of_day, 3_600_000)
        mi, rem = divmod(rem, 60_000)
        ss, ms = divmod(rem, 1000)
        pk.append(WitPacket.from_time(26, 11, 23, hh, mi, ss, ms))
    pk.append(WitPacket.from_words(ACC, (q(acc_g[0], 16), q(acc_g[1], 16), q(acc_g[2], 16),
                                        max(-32768, min(32767, int(round(temp_c * 100)))))))
    pk.append(WitPacket.from_words(GYRO, (q(gyro_dps[0], 2000), q(gyro_dps[1], 2000), q(gyro_dps[2], 2000), 0)))
    if angle_deg is not None:
        pk.append(WitPacket.from_words(ANGLE, (q(angle_deg[0], 180), q(angle_deg[1], 180), q(angle_deg[2], 180), 0)))
    if mag is not None:
        pk.append(WitPacket.from_words(MAG, (mag[0], mag[1], mag[2], 0)))
    return b"".join(codec.encode(p) for p in pk), pk


__all__ = ["WitMotionImu", "encode_cycle", "TIME"]
