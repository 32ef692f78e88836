"""What the phone-app devices share: the phone frame and its channels, stream declarations, the
rotation-vector quaternion, bounded name tallies and ``AppDevice``, their common base.

This module owns the conventions all three apps' devices follow (``devices.phone_apps.osc``,
``devices.phone_apps.hyperimu``, ``devices.phone_apps.sensorserver``): accelerations in m/s^2 with
+9.81 on z lying flat, screen up, as an Android accelerometer reads; angular rates in rad/s;
quaternions w, x, y, z; the stream names the fusion processor reserves; and that errors the device
layer finds in decoded frames are reported like the codec's own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from capture.sample import Chunk, DeviceClockSpec, DeviceEvent, EventKind, StreamInfo
from devices.base import CodecT, Device

if TYPE_CHECKING:
    from collections.abc import Sequence

G0 = 9.80665
NAN = float("nan")
FRAME = "phone frame: x right, y up the screen, z out of the screen (right-handed)"
ACC_CHANNELS = ("ax", "ay", "az")
ACC_UNITS = ("m/s^2",) * 3
GYRO_CHANNELS = ("gx", "gy", "gz")
GYRO_UNITS = ("rad/s",) * 3
IMU_CHANNELS = ACC_CHANNELS + GYRO_CHANNELS
IMU_UNITS = ACC_UNITS + GYRO_UNITS
MAG_CHANNELS = ("mx", "my", "mz")
QUAT_CHANNELS = ("w", "x", "y", "z")
#: Stream names the fusion processor publishes, which phone devices must not use.
RESERVED_STREAMS = ("orientation", "gravity", "linear_acc")
#: Distinct unmatched addresses / unexpected types tracked by name (more are lumped under "<other>").
MAX_TRACKED = 256


@dataclass(frozen=True)
class StreamDecl:
    """A stream a device declares."""

    suffix: str
    kind: str
    channels: tuple[str, ...]
    units: tuple[str, ...]
    frame: str | None = FRAME
    regular: bool = True  # has the nominal rate (touch streams are irregular)


def quat_from_vector(x: float, y: float, z: float) -> tuple[float, float, float, float]:
    """Android's ``getQuaternionFromVector``: w from a unit rotation vector's x, y, z."""
    return (math.sqrt(max(0.0, 1.0 - x * x - y * y - z * z)), x, y, z)


class NameTally:
    """Counts per name, bounded; says whether a name is new (to log it once)."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}

    def add(self, name: str) -> bool:
        if name not in self.counts and len(self.counts) >= MAX_TRACKED:
            name = "<other>"
        n = self.counts.get(name, 0)
        self.counts[name] = n + 1
        return n == 0

    @property
    def total(self) -> int:
        return sum(self.counts.values())


class AppDevice(Device[CodecT]):
    """Common parts: streams from ``StreamDecl``s, and errors the device layer finds (counted by the
    codec's ``reject``) reported like the codec's own."""

    def _declare(self, decls: Sequence[StreamDecl], rate: float | None,
                 clock: DeviceClockSpec | None) -> list[StreamInfo]:
        return [self.stream_info(d.suffix, d.kind, d.channels, d.units, rate if d.regular else None, d.frame,
                                 clock if d.regular else None) for d in decls]

    def process_chunk(self, chunk: Chunk) -> list[Any]:
        before = self.codec.stats.errors
        out = super().process_chunk(chunk)
        st = self.codec.stats
        if st.errors != before and not any(isinstance(x, DeviceEvent) and x.kind is EventKind.PROTOCOL_ERRORS
                                           for x in out):
            out.insert(1, DeviceEvent(self.name, EventKind.PROTOCOL_ERRORS, chunk.t_ns,
                                      f"{st.errors} errors, {st.skipped_bytes} bytes skipped"))
        return out


__all__ = ["ACC_CHANNELS", "ACC_UNITS", "FRAME", "G0", "GYRO_CHANNELS", "GYRO_UNITS", "IMU_CHANNELS", "IMU_UNITS",
           "MAG_CHANNELS", "MAX_TRACKED", "NAN", "QUAT_CHANNELS", "RESERVED_STREAMS", "AppDevice", "NameTally",
           "StreamDecl", "quat_from_vector"]
