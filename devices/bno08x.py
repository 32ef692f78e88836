"""BNO08x (BNO080/BNO085/BNO086) IMUs in UART-RVC mode (the PS0 pin strapped high).

The sensor runs its own fusion and streams, at a fixed 100 Hz over 115200 baud, its orientation as
yaw/pitch/roll (derived from its rotation vector; yaw is relative to the heading at reset) plus the
accelerometer. It reports no angular rate.

Streams:

* ``euler``: ``roll, pitch, yaw`` in degrees (the same channel order as the WitMotion ``euler``
  stream, so consumers treat both alike; on the wire the order is yaw, pitch, roll). Datasheet
  convention (BNO080 datasheet 1000-3927, UART-RVC): yaw is the rotation about Z since reset
  (+-180 deg), pitch about Y (+-90 deg), roll about X (+-180 deg), counter-clockwise positive, and
  the orientation is obtained by applying yaw, then pitch, then roll: intrinsic Z-Y'-X''
  Tait-Bryan angles, ``R = Rz(yaw) Ry(pitch) Rx(roll)`` in the sensor frame of the datasheet's
  figure 4-1 (or as remapped by the system orientation FRS record). Quantum 0.01 deg.
* ``accel``: ``ax, ay, az`` in m/s^2 (gravity included), ``mg * 9.80665e-3``, quantum 9.80665e-3, so
  sessions store the integers losslessly.

Device clock. The 8-bit frame index counts frames at 100 Hz, so it is a 100 Hz clock wrapping every
2.56 s (``DeviceClockSpec(100, 256)``): clock sync gets device time, and lost frames show as
sequence gaps. ``ClockSync`` unwraps it with the host time elapsed between reads, which is right
as long as the host's view of the elapsed time is off by less than half a wrap (1.28 s): arrival
jitter, reads of several frames and long silences with the sensor still counting (frames lost on
the link show as sequence gaps of the right size) are all fine. Limits: a host stall that returns
more than about 1.28 s of backlog in one read miscounts a wrap (``ClockSync`` compares the elapsed
host time up to the chunk's arrival with the step to the chunk's *first* frame), which shows as a
clock reset and a 2.56 s jump of device time; and the reset tolerance is a quarter wrap (0.64 s
instead of 1 s), so a chunk whose newest frame arrives that late starts a new clock epoch.
``device_clock=false`` uses the nominal 100 Hz pseudo clock instead.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from capture.sample import ChunkRun, DeviceClockSpec, StreamInfo
from devices.base import BatchReadings, Device, Reading, StreamReadings
from devices.codecs.bno08x_rvc import FRAME_LEN, Bno08xRvcCodec, RvcFrame
from devices.options import Option

if TYPE_CHECKING:
    from collections.abc import Iterable

G = 9.80665
RATE_HZ = 100.0
ANGLE_Q = 0.01          # deg per count
ACC_Q = G * 1e-3        # m/s^2 per mg
INDEX_WRAP = 256

EULER, ACCEL = 0, 1
FRAME = ("BNO08x sensor frame (datasheet figure 4-1, or as remapped by the FRS system orientation); "
         "euler: intrinsic Z-Y'-X'' (yaw, then pitch, then roll), counter-clockwise positive, yaw since reset")


class Bno08xRvcImu(Device[Bno08xRvcCodec]):
    """A BNO08x IMU streaming UART-RVC frames."""

    kind = "bno08x_rvc"
    description = "BNO08x IMU in UART-RVC mode (19-byte 0xAAAA frames at 100 Hz, 115200 baud)"
    codec_cls = Bno08xRvcCodec
    options: ClassVar[dict[str, Option]] = {
        "device_clock": Option(bool, True, "use the 8-bit frame index as a 100 Hz device clock (wraps every 2.56 s)"),
    }

    def declare_streams(self) -> list[StreamInfo]:
        clock = DeviceClockSpec(tick_hz=RATE_HZ, wrap_ticks=INDEX_WRAP) if self.opts["device_clock"] else None
        self._clocked = clock is not None
        self._tail: list[Reading] = []
        return [
            self.stream_info("euler", "euler", ("roll", "pitch", "yaw"), ("deg", "deg", "deg"), RATE_HZ, FRAME,
                             clock, (ANGLE_Q,) * 3),
            self.stream_info("accel", "accel", ("ax", "ay", "az"), ("m/s^2",) * 3, RATE_HZ, FRAME, clock,
                             (ACC_Q,) * 3),
        ]

    def frame_to_readings(self, frame: RvcFrame) -> Iterable[Reading]:
        t = frame.counter if self._clocked else None
        return (Reading(EULER, (frame.roll * ANGLE_Q, frame.pitch * ANGLE_Q, frame.yaw * ANGLE_Q), t),
                Reading(ACCEL, (frame.ax * ACC_Q, frame.ay * ACC_Q, frame.az * ACC_Q), t))

    # -- batch path ------------------------------------------------------------------------------
    def batch_ready(self) -> bool:
        return self.codec.locked

    def decode_batch(self, chunks: ChunkRun) -> BatchReadings | None:
        """Vectorised decoding of a clean run (frames continuing the locked stream, split anywhere);
        anything else returns ``None`` and the chunks take the per-chunk path."""
        res = self.codec.feed_clean(chunks.data)
        if res is None:
            return None
        a, lead = res
        m = a.shape[0]
        w = np.ascontiguousarray(a[:, 3:15]).view("<i2").reshape(m, 6).astype(np.float64)
        eul = w[:, [2, 1, 0]] * ANGLE_Q
        acc = w[:, 3:6] * ACC_Q
        ticks = a[:, 2].astype(np.int64) if self._clocked else None
        ends = (np.arange(1, m + 1, dtype=np.int64) * FRAME_LEN) - 1 - lead
        chunk = np.searchsorted(chunks.offsets[1:], ends, side="right").astype(np.int64)
        base = np.arange(m, dtype=np.int64) * 2
        return BatchReadings({EULER: StreamReadings(eul, ticks, chunk, base),
                              ACCEL: StreamReadings(acc, ticks, chunk, base + 1)})

    # -- end of take / reconnect -------------------------------------------------------------------
    def finish(self) -> list[Any]:
        """Decide a last frame that was waiting for lookahead bytes, then end the take as usual."""
        frames = self.codec.flush()
        self._tail = [r for f in frames for r in self.frame_to_readings(f)]
        return super().finish()

    def drain_readings(self) -> list[Reading]:
        out, self._tail = self._tail, []
        return out


def rvc_frame(index: int, euler_deg: tuple[float, float, float], acc_ms2: tuple[float, float, float]) -> RvcFrame:
    """The frame a BNO08x sends for one reading (for simulators).

    Args:
        index: frame counter (taken modulo 256); at 100 Hz, ``round(t_device_s * 100)``.
        euler_deg: ``(roll, pitch, yaw)`` in degrees (the ``euler`` stream's channel order).
        acc_ms2: ``(ax, ay, az)`` in m/s^2, gravity included.

    Raises:
        ValueError: a value does not fit the wire format (|angle| > 327.67 deg, |acc| > 32.767 g).
    """
    def q(v: float, step: float) -> int:
        r = round(float(v) / step)
        if not -32768 <= r <= 32767:
            raise ValueError(f"{v} does not fit an int16 of {step}")
        return r

    roll, pitch, yaw = euler_deg
    return RvcFrame(index & 0xFF, q(yaw, ANGLE_Q), q(pitch, ANGLE_Q), q(roll, ANGLE_Q),
                    q(acc_ms2[0], ACC_Q), q(acc_ms2[1], ACC_Q), q(acc_ms2[2], ACC_Q))


def encode_rvc(index: int, euler_deg: tuple[float, float, float], acc_ms2: tuple[float, float, float]) -> bytes:
    """The 19 wire bytes of one reading; arguments as for ``rvc_frame``.

    Raises:
        ValueError: a value does not fit the wire format.
    """
    return Bno08xRvcCodec().encode(rvc_frame(index, euler_deg, acc_ms2))


def encode_rvc_many(index: np.ndarray, euler_deg: np.ndarray, acc_ms2: np.ndarray) -> np.ndarray:
    """Many readings at once, vectorised; the same bytes as ``encode_rvc`` reading by reading.

    Args:
        index: (n,) frame counters (modulo 256).
        euler_deg: (n, 3) ``roll, pitch, yaw`` in degrees.
        acc_ms2: (n, 3) acceleration in m/s^2.

    Returns:
        (n, 19) uint8; ``.tobytes()`` is the wire stream, ``[k].tobytes()`` one frame.

    Raises:
        ValueError: a value does not fit the wire format.
    """
    e = np.asarray(euler_deg, np.float64)
    a = np.asarray(acc_ms2, np.float64)
    if not (np.isfinite(e).all() and np.isfinite(a).all()):
        raise ValueError("RVC angles and accelerations must be finite")
    ang = np.clip(np.round(e[:, [2, 1, 0]] / ANGLE_Q), -2.0**40, 2.0**40).astype(np.int64)
    acc = np.clip(np.round(a / ACC_Q), -2.0**40, 2.0**40).astype(np.int64)
    return Bno08xRvcCodec.encode_many(np.asarray(index, np.int64), ang, acc)


__all__ = ["ACC_Q", "ANGLE_Q", "RATE_HZ", "Bno08xRvcImu", "encode_rvc", "encode_rvc_many", "rvc_frame"]
