"""Phones running HyperIMU, streaming CSV rows over UDP or TCP (kind ``hyperimu``).

This module owns what HyperIMU's values mean: streams, units and the clock. The row syntax is
``devices.codecs.hyperimu``. The app is not in ``../shared/traces``; the layout follows
``docs/design/phone-protocols.md`` (section 4), and its open questions are noted where they matter.

``HyperImuPhone`` (kind ``hyperimu``): rows over UDP or TCP (``HyperImuCodec``). Options are
``sensors`` (the app's enabled sensors, in its order; each gives 3 values in Android units),
``timestamp`` (rows start with epoch ms, the device clock at 1 kHz; whether that is sample or send
time is an open question), ``mac``, ``gps`` and ``rate``. Streams: ``imu`` when accelerometer and
gyroscope are both enabled (else ``acc`` or ``gyro``), ``mag`` (uT), ``user_acc``
(linear_acceleration), ``phone_gravity``, ``attitude``, ``gps`` (lat, lon in deg, alt in m).
``attitude`` is a quaternion w, x, y, z from the rotation vector, with w = sqrt(1 - x^2 - y^2 - z^2)
as Android's ``getQuaternionFromVector`` computes it. With only the orientation sensor enabled it is
kind ``euler`` (azimuth, pitch, roll in deg); when both are enabled, orientation goes to
``attitude_euler``. Without a timestamp the streams have the pseudo clock at ``rate`` (0: stamped
at arrival).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, ClassVar

from capture.errors import ConfigError
from capture.sample import DeviceClockSpec, StreamInfo
from devices.base import Reading
from devices.codecs.hyperimu import HYPERIMU_SENSORS, HyperImuCodec, hyperimu_sensor
from devices.codecs.textline import MAX_LINE, TextFrame
from devices.options import Option
from devices.phone_apps.base import (
    ACC_CHANNELS,
    ACC_UNITS,
    GYRO_CHANNELS,
    GYRO_UNITS,
    IMU_CHANNELS,
    IMU_UNITS,
    MAG_CHANNELS,
    QUAT_CHANNELS,
    AppDevice,
    StreamDecl,
    quat_from_vector,
)

if TYPE_CHECKING:
    from collections.abc import Iterable, Sequence

HYPERIMU_CLOCK = DeviceClockSpec(tick_hz=1000.0)


class HyperImuPhone(AppDevice[HyperImuCodec]):
    """A phone running HyperIMU, streaming CSV rows over UDP or TCP."""

    kind = "hyperimu"
    description = "HyperIMU app (Android): CSV rows of the enabled sensors over UDP or TCP"
    codec_cls = HyperImuCodec
    options: ClassVar[dict[str, Option]] = {
        "sensors": Option(str, "accelerometer,gyroscope,magnetometer",
                          "the sensors enabled in the app, in its order (3 values each): "
                          + ", ".join(HYPERIMU_SENSORS) + " (_ skips one)"),
        "timestamp": Option(bool, False, "rows start with a timestamp (epoch ms; the device clock)"),
        "mac": Option(bool, False, "rows carry the MAC address (after the timestamp)"),
        "gps": Option(bool, False, "rows end with GPS latitude, longitude, altitude"),
        "rate": Option(float, 0.0, "rows per second (1000 / the app's sampling time in ms); 0 = unknown",
                       min=0.0, max=10_000.0),
        "max_line": Option(int, MAX_LINE, "longest accepted row, bytes", min=64, max=1 << 20),
    }

    def declare_streams(self) -> list[StreamInfo]:
        where = f"device {self.name} (hyperimu)"
        o = self.opts
        names = [s.strip() for s in str(o["sensors"]).split(",")]
        try:
            sensors = [hyperimu_sensor(s) for s in names]
            self.codec = HyperImuCodec(self.strict, sensors=sensors, timestamp=o["timestamp"], mac=o["mac"],
                                       gps=o["gps"], max_line=o["max_line"])
        except ValueError as exc:
            raise ConfigError(f"{where}: sensors={o['sensors']!r}: {exc}; expected sensors=NAME,NAME,... in the "
                              "app's order", source=where) from None
        fields = self.codec.fields
        at = {s: fields.index(f"{s}.x") for s in sensors if s != "_"}
        decls: list[StreamDecl] = []
        #: (stream, [(field index, channel position)], rotation vector?)
        self._plans: list[tuple[int, tuple[tuple[int, int], ...], bool]] = []

        def add(decl: StreamDecl, parts: Sequence[tuple[int, int]], rv: bool = False) -> None:
            self._plans.append((len(decls), tuple(parts), rv))
            decls.append(decl)

        def xyz(s: str, off: int = 0) -> list[tuple[int, int]]:
            return [(at[s] + k, off + k) for k in range(3)]

        if "accelerometer" in at and "gyroscope" in at:
            add(StreamDecl("imu", "imu", IMU_CHANNELS, IMU_UNITS), xyz("accelerometer") + xyz("gyroscope", 3))
        elif "accelerometer" in at:
            add(StreamDecl("acc", "acc", ACC_CHANNELS, ACC_UNITS), xyz("accelerometer"))
        elif "gyroscope" in at:
            add(StreamDecl("gyro", "gyro", GYRO_CHANNELS, GYRO_UNITS), xyz("gyroscope"))
        if "magnetometer" in at:
            add(StreamDecl("mag", "mag", MAG_CHANNELS, ("uT",) * 3), xyz("magnetometer"))
        if "linear_acceleration" in at:
            add(StreamDecl("user_acc", "acc", ACC_CHANNELS, ACC_UNITS), xyz("linear_acceleration"))
        if "gravity" in at:
            add(StreamDecl("phone_gravity", "acc", ACC_CHANNELS, ACC_UNITS), xyz("gravity"))
        if "rotation_vector" in at:
            add(StreamDecl("attitude", "quat", QUAT_CHANNELS, ("1",) * 4,
                      "Android rotation vector: phone frame relative to east-north-up"),
                xyz("rotation_vector", 1), rv=True)
        if "orientation" in at:
            add(StreamDecl("attitude_euler" if "rotation_vector" in at else "attitude", "euler",
                      ("azimuth", "pitch", "roll"), ("deg",) * 3, "Android orientation sensor angles"),
                xyz("orientation"))
        if o["gps"]:
            g = fields.index("lat")
            add(StreamDecl("gps", "gps", ("lat", "lon", "alt"), ("deg", "deg", "m"), "WGS84"),
                [(g, 0), (g + 1, 1), (g + 2, 2)])
        self._tf = 0 if o["timestamp"] else None
        return self._declare(decls, o["rate"] or None, HYPERIMU_CLOCK if o["timestamp"] else None)

    def frame_to_readings(self, frame: TextFrame) -> Iterable[Reading]:
        v = frame.values
        ticks = None if self._tf is None else round(v[self._tf])
        out: list[Reading] = []
        for si, parts, rv in self._plans:
            if rv:
                x, y, z = (v[fi] for fi, _ in parts)
                out.append(Reading(si, quat_from_vector(x, y, z), ticks))
            else:
                out.append(Reading(si, tuple(v[fi] for fi, _ in parts), ticks))
        return out

    def health(self) -> dict[str, Any]:
        """Base counters plus ``skipped_lines`` (headers, blank lines) and ``mac`` (the last MAC seen)."""
        h = super().health()
        h.update(mac=self.codec.last_mac)
        return h


__all__ = ["HYPERIMU_CLOCK", "HyperImuPhone"]
