"""Sony DualShock 4 (``ds4``) and DualSense (``dualsense``) over USB or Bluetooth.

USB and Bluetooth are the same device to the user: the same streams, channels and units; only the
report layout differs, and the codec reads either. The bus comes from the HID transport
(``hid.bus``); when it says "unknown" it is told by the first input report (0x11/0x31 or a 10-byte
0x01 means Bluetooth).

Handshake: read the report descriptor, then the IMU calibration feature report (DS4: 0x02 over
USB, 0x05 over Bluetooth with CRC; DualSense: 0x05). Over Bluetooth that read also switches the pad
from the reduced 0x01 report to the full one (0x11 / 0x31), so the handshake then waits for the
first full report. Every failure is bounded (``init_timeout``) and named:

* no answer to the feature read -> ``DeviceInitError`` (``DeviceTimeoutError`` if the transport
  timed out);
* an answer with the wrong ID, length or CRC -> ``DeviceInitError`` saying which;
* Bluetooth, but only reduced reports keep coming -> ``DeviceTimeoutError``.

Streams (all on the pad's sensor clock):

* ``imu``: ``ax ay az`` in m/s^2 (gravity included) and ``gx gy gz`` in rad/s, scaled with the
  factory calibration (see ``devices.codecs.sony``). Sensor frame (right-handed), the pad held in
  front of the player: x to the right, y out of the face (up when the pad lies flat face up, so
  it reads +1 g on y at rest), z toward the player (away from the triggers); gyro positive
  counter-clockwise about each axis.
* ``sticks``: ``lx ly rx ry`` in -1..1 (x right, y up) and ``l2 r2`` in 0..1.
* ``buttons``: one 0/1 channel per button (``square cross circle triangle l1 r1 l2 r2 share
  options l3 r3 ps touchpad mute``; ``share`` is "create" on a DualSense, ``mute`` is always 0 on a
  DS4), ``dpad_x dpad_y`` (-1, 0, 1; y up), ``battery`` (%, steps of 10) and ``charging`` (0/1).
* ``touch``: two contacts ``t0_active t0_id t0_x t0_y t1_...`` in touchpad counts (DS4
  1920 x 942, DualSense 1920 x 1080; x right, y down).

Device clock. DS4: the u16 sensor timestamp in units of 16/3 us (187.5 kHz), wrapping every
0.35 s; clock sync unwraps it with the host's elapsed time, so a host stall longer than about a
quarter of a wrap (87 ms) shows as a clock reset. DualSense: the u32 sensor timestamp in 1/3 us
(3 MHz), wrapping every 23.9 minutes. Rates are nominal 250 Hz (Bluetooth varies with the link).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any, ClassVar

from capture.errors import (
    DeviceInitError,
    DeviceIOError,
    DeviceTimeoutError,
    ProtocolError,
)
from capture.sample import DeviceChunk, DeviceClockSpec, StreamInfo
from devices.base import Reading
from devices.codecs.sony import (
    BLUETOOTH,
    BUTTONS,
    DS4_TICK_HZ,
    DS4_TICK_WRAP,
    DS_TICK_HZ,
    DS_TICK_WRAP,
    HAT,
    USB,
    DualSenseCodec,
    DualShock4Codec,
    ImuCalibration,
    ImuScale,
    PadReport,
    battery_of,
    calibration_report,
    parse_calibration,
)
from devices.hid.base import HidDevice
from devices.options import Option

if TYPE_CHECKING:
    from collections.abc import Iterable

log = logging.getLogger(__name__)

RATE_HZ = 250.0
IMU, STICKS, BUTTONS_STREAM, TOUCH = 0, 1, 2, 3
FRAME = ("pad sensor frame, right-handed: x right, y out of the face (up when lying flat), z toward the player; "
         "gyro counter-clockwise positive")
STICK_CH = ("lx", "ly", "rx", "ry", "l2", "r2")
BUTTON_CH = (*BUTTONS, "dpad_x", "dpad_y", "battery", "charging")
TOUCH_CH = ("t0_active", "t0_id", "t0_x", "t0_y", "t1_active", "t1_id", "t1_x", "t1_y")
#: reduced reports tolerated while waiting for the first full Bluetooth report, per second of timeout
REDUCED_PER_S = 250


class _SonyPad(HidDevice[DualShock4Codec | DualSenseCodec]):
    """Shared parts of the two pads."""

    model: ClassVar[str] = ""
    tick_hz: ClassVar[float] = 0.0
    wrap: ClassVar[int] = 0
    full_bt_id: ClassVar[int] = 0
    options: ClassVar[dict[str, Option]] = {
        "init_timeout": Option(float, 1.0, "seconds to wait for the pad during the handshake", min=0.01, max=60.0),
    }

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.calibration: ImuCalibration | None = None
        self.scale: ImuScale | None = None
        self.bus_kind: str = "unknown"
        self.calibration_fallbacks = 0

    def declare_streams(self) -> list[StreamInfo]:
        clock = DeviceClockSpec(tick_hz=self.tick_hz, wrap_ticks=self.wrap)
        return [
            self.stream_info("imu", "imu", ("ax", "ay", "az", "gx", "gy", "gz"),
                             ("m/s^2",) * 3 + ("rad/s",) * 3, RATE_HZ, FRAME, clock),
            self.stream_info("sticks", "sticks", STICK_CH, ("1",) * 6, RATE_HZ, "x right, y up", clock,
                             (1 / 127.5,) * 4 + (1 / 255,) * 2),
            self.stream_info("buttons", "buttons", BUTTON_CH, ("1",) * (len(BUTTONS) + 2) + ("%", "1"), RATE_HZ,
                             None, clock),
            self.stream_info("touch", "touch", TOUCH_CH, ("1", "1", "count", "count") * 2, RATE_HZ,
                             "touchpad counts, x right, y down", clock, (1.0,) * 8),
        ]

    # -- handshake ---------------------------------------------------------------------------------
    def _what(self) -> str:
        return f"device {self.name} ({self.kind}, {self.transport.url})"

    def handshake(self) -> None:
        self.hid_report_descriptor()
        timeout = float(self.opts["init_timeout"])
        bus = str(self.hid.bus)
        if bus not in (USB, BLUETOOTH):
            bus = self._bus_from_reports(timeout)
        self.bus_kind = bus
        rid, length = calibration_report(self.model, bus)
        try:
            data = self.hid_get_feature(rid, length)
        except DeviceTimeoutError as exc:
            raise DeviceTimeoutError(f"{self._what()}: no answer to the calibration feature report 0x{rid:02x}"
                                     f" ({bus}): {exc}", source=self.transport.url) from exc
        except DeviceIOError as exc:
            raise DeviceInitError(f"{self._what()}: the pad did not answer the calibration feature report 0x{rid:02x}"
                                  f" ({bus}): {exc}; is it a {self.kind}, connected over {bus}?",
                                  source=self.transport.url) from exc
        try:
            cal = parse_calibration(data, self.model, bus)
        except ProtocolError as exc:
            raise DeviceInitError(f"{self._what()}: wrong answer: {exc}", source=self.transport.url) from exc
        self.set_calibration(cal)
        if bus == BLUETOOTH:
            self._wait_full_reports(timeout)

    def set_calibration(self, cal: ImuCalibration) -> None:
        """Use ``cal`` for the IMU stream; a degenerate one falls back to nominal (logged, counted)."""
        self.calibration = cal
        self.scale = cal.scale()
        if self.scale.fallback:
            self.calibration_fallbacks += 1
            log.warning("%s: degenerate IMU calibration (zero span on %s); using the nominal scale for those axes "
                        "(gyro 2000 deg/s full scale, accel 8192 counts/g): readings may be off by a few percent",
                        self._what(), ", ".join(self.scale.fallback))

    def _bus_from_reports(self, timeout: float) -> str:
        """USB or Bluetooth from the first input report (the transport did not say)."""
        deadline = self.clock.now_ns() + int(timeout * 1e9)
        while self.clock.now_ns() < deadline:
            chunk = self.hid_read(min(0.05, max(0.0, (deadline - self.clock.now_ns()) / 1e9)))
            if chunk is None or not chunk.data:
                continue
            d = chunk.data
            if d[0] == self.full_bt_id or (d[0] == 0x01 and len(d) == 10):
                return BLUETOOTH
            if d[0] == 0x01:
                return USB
        raise DeviceTimeoutError(f"{self._what()}: no input report within {timeout:g} s, so USB or Bluetooth"
                                 " cannot be told", source=self.transport.url)

    def _wait_full_reports(self, timeout: float) -> None:
        """Bluetooth: wait until the pad sends full reports (it does after the calibration read)."""
        deadline = self.clock.now_ns() + int(timeout * 1e9)
        reduced = 0
        limit = max(25, int(REDUCED_PER_S * timeout))
        while True:
            left = (deadline - self.clock.now_ns()) / 1e9
            if left <= 0 or reduced >= limit:
                raise DeviceTimeoutError(
                    f"{self._what()}: the pad answered the calibration read but kept sending reduced reports"
                    f" (0x01, no motion data; {reduced} seen) instead of full 0x{self.full_bt_id:02x} reports"
                    f" within {timeout:g} s", source=self.transport.url)
            chunk = self.transport.read(min(left, 0.05))
            if chunk is None or not chunk.data:
                continue
            if chunk.data[0] == self.full_bt_id:
                # the first full report is motion like any other: decoded, not swallowed by the
                # handshake (so a replay that does not re-run this handshake decodes the same)
                self._pending += self.process_chunk(chunk)
                return
            self._pending.append(DeviceChunk(self.name, chunk))  # kept in the session, not decoded
            reduced += 1

    # -- decoding ----------------------------------------------------------------------------------
    def frame_to_readings(self, f: PadReport) -> Iterable[Reading]:
        sc = self.scale
        if sc is None:  # decoding a session without the calibration descriptor
            self.set_calibration(ImuCalibration((0, 0, 0), (0, 0, 0), (0, 0, 0), 0, 0, (0, 0, 0), (0, 0, 0)))
            sc = self.scale
            assert sc is not None
        t = f.timestamp
        lx, ly, rx, ry = f.sticks
        sticks = ((lx - 127.5) / 127.5, (127.5 - ly) / 127.5, (rx - 127.5) / 127.5, (127.5 - ry) / 127.5,
                  f.triggers[0] / 255.0, f.triggers[1] / 255.0)
        bits = f.buttons
        dx, dy = HAT[f.hat]
        level, charging = battery_of(self.model, f.status)
        buttons = (*(float((bits >> i) & 1) for i in range(len(BUTTONS))), float(dx), float(dy), level,
                   float(charging))
        p, q = f.touch
        touch = (float(p.active), float(p.id), float(p.x), float(p.y),
                 float(q.active), float(q.id), float(q.x), float(q.y))
        return (Reading(IMU, sc.convert(f.gyro, f.accel), t), Reading(STICKS, sticks, t),
                Reading(BUTTONS_STREAM, buttons, t), Reading(TOUCH, touch, t))

    def health(self) -> dict[str, Any]:
        h = super().health()
        h["reduced_reports"] = self.codec.stats.reduced_reports
        h["calibration_fallbacks"] = self.calibration_fallbacks
        h["bus"] = self.bus_kind
        return h


class DualShock4(_SonyPad):
    """Sony DualShock 4 (CUH-ZCT1/ZCT2, and the USB wireless adaptor) over USB or Bluetooth."""

    kind = "ds4"
    description = "Sony DualShock 4 over USB (report 0x01) or Bluetooth (0x11), IMU at 250 Hz"
    codec_cls = DualShock4Codec
    model = "ds4"
    tick_hz = DS4_TICK_HZ
    wrap = DS4_TICK_WRAP
    full_bt_id = 0x11


class DualSense(_SonyPad):
    """Sony DualSense (and Edge) over USB or Bluetooth."""

    kind = "dualsense"
    description = "Sony DualSense over USB (report 0x01) or Bluetooth (0x31), IMU at 250 Hz"
    codec_cls = DualSenseCodec
    model = "dualsense"
    tick_hz = DS_TICK_HZ
    wrap = DS_TICK_WRAP
    full_bt_id = 0x31


__all__ = ["FRAME", "RATE_HZ", "DualSense", "DualShock4"]
