"""Nintendo Switch Pro Controller (057e:2009) and Joy-Cons (L 057e:2006, R 057e:2007).

Handshake (``devices.codecs.nintendo`` has the wire formats):

1. the report descriptor (kept for sessions);
2. over USB only (``self.hid.bus == "usb"``): ``0x80 0x01`` status (MAC), ``0x80 0x02`` handshake,
   ``0x80 0x03`` 3 Mbit baud, ``0x80 0x02`` again, ``0x80 0x04`` (USB HID only, no reply). From then on
   subcommands go as the same output report ``0x01`` as over Bluetooth, as SDL and Linux
   hid-nintendo do (the ``0x80 0x92`` UART wrapper is only needed before ``0x80 0x04``);
3. subcommand 0x02 device info (firmware, type, MAC); SPI reads (0x10) of the factory IMU
   calibration 0x6020, the user IMU calibration 0x8026 (used when its magic 0xB2 0xA1 is there),
   the factory stick calibration 0x603D, the 6-axis horizontal offsets 0x6080 and the stick
   parameters 0x6086; enable IMU (0x40 0x01); input mode full (0x03 0x30).

Each subcommand waits for the 0x21 reply (0x30/0x3F reports that arrive meanwhile are recorded and
skipped) for ``reply_timeout`` seconds, then is sent once more (``retries``); silence gives
``DeviceTimeoutError``. A reply to another subcommand, a NACK (after the retry), or an SPI reply for
another address or length gives ``DeviceInitError``. An unset (all 0xFF) or unusable factory
calibration falls back to nominal values with a warning, counted in ``calibration_fallbacks``.

Time. Each 0x30 report carries three IMU samples, oldest first, taken 5 ms apart (200 Hz), and is
sent every 15 ms over Bluetooth (over USB the reports come faster, about every 8 ms, so consecutive
reports can repeat samples). Assumption: the timer byte counts one tick per IMU sample (5 ms,
200 Hz) and the newest sample is taken at the report's timer value. So the device clock is
``DeviceClockSpec(200, 256)`` (wraps every 1.28 s) and the samples of a report get ticks
``timer - 2, timer - 1, timer``: three ``Reading``s, never averaged, each with its own device and
bus time; a dropped report is a 15 ms gap (3 lost readings). Samples at ticks already emitted
(overlapping USB reports) are skipped and counted in ``overlapping_samples``.

Axes (the ``imu`` stream's frame). The sensor frame of ``imu_sensor_notes.md``: for the Pro
Controller lying flat, x toward the triggers, y to the left, z up out of the face (at rest the
accelerometer reads +g on z); right-handed. The Joy-Con (R) IMU is mounted turned 180 deg about x
relative to the Joy-Con (L), so for it y and z are negated: both Joy-Cons report in the Joy-Con (L)
sensor frame, and a left and a right Joy-Con moved together read the same. (This mounting is taken
from the public notes and driver behaviour, not measured here.)
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any, ClassVar

from capture.errors import DeviceInitError, DeviceTimeoutError
from capture.sample import DeviceClockSpec, DeviceDescriptor, StreamInfo
from devices.base import Reading
from devices.codecs import nintendo as sw
from devices.codecs.nintendo import (
    FullReport,
    ImuCalibration,
    StickCalibration,
    SubcommandReply,
    SwitchCodec,
)
from devices.hid.base import HidDevice
from devices.options import Option

if TYPE_CHECKING:
    from collections.abc import Iterable

log = logging.getLogger(__name__)

TICK_HZ = 200.0
TIMER_WRAP = 256
IMU_RATE_HZ = 200.0
REPORT_RATE_HZ = 1000.0 / 15.0
IMU, STICKS, BUTTONS = 0, 1, 2

PID_LEFT, PID_RIGHT, PID_PRO = 0x2006, 0x2007, 0x2009

PRO_FRAME = ("Switch IMU sensor frame (dekuNukem imu_sensor_notes): controller flat, x toward the triggers, "
             "y left, z up out of the face; right-handed")
JOYCON_FRAME = ("Joy-Con (L) IMU sensor frame (dekuNukem imu_sensor_notes); a Joy-Con (R) has y and z negated to "
                "match (its sensor is turned 180 deg about x); right-handed")


class _SwitchBase(HidDevice[SwitchCodec]):
    codec_cls = SwitchCodec
    frame_text: ClassVar[str] = PRO_FRAME
    stick_channels: ClassVar[tuple[str, ...]] = ("lx", "ly", "rx", "ry")
    options: ClassVar[dict[str, Option]] = {
        "reply_timeout": Option(float, 0.5, "seconds to wait for each subcommand reply", min=0.01, max=10.0),
        "retries": Option(int, 1, "times a subcommand is sent again after no reply or a NACK", min=0, max=5),
    }

    def declare_streams(self) -> list[StreamInfo]:
        clock = DeviceClockSpec(tick_hz=TICK_HZ, wrap_ticks=TIMER_WRAP)
        self._counter = 0
        self._last_tick: int | None = None
        self.overlapping_samples = 0
        self.calibration_fallbacks = 0
        self.imu_cal = ImuCalibration()
        self.imu_cal_source = "nominal"
        self.sticks_cal = (StickCalibration(), StickCalibration())
        self.stick_deadzone = 0
        self.info: sw.DeviceInfo | None = None
        self.controller_type = sw.TYPE_PRO
        return [
            self.stream_info("imu", "imu", ("ax", "ay", "az", "gx", "gy", "gz"), ("m/s^2",) * 3 + ("rad/s",) * 3,
                             IMU_RATE_HZ, self.frame_text, clock),
            self.stream_info("sticks", "sticks", self.stick_channels, ("1",) * len(self.stick_channels),
                             REPORT_RATE_HZ, "stick deflection, right and up positive, -1..1", clock),
            self.stream_info("buttons", "buttons", tuple(n for _, n in sw.BUTTONS), ("1",) * len(sw.BUTTONS),
                             REPORT_RATE_HZ, None, clock),
        ]

    # -- handshake ----------------------------------------------------------------------------------
    def handshake(self) -> None:
        self._counter = 0
        self._last_tick = None
        self.hid_report_descriptor()
        if str(self.hid.bus) == "usb":
            self._usb_setup()
        info_data = self.subcommand(sw.SC_DEVICE_INFO, b"", "device info (0x02)").data
        try:
            self.info = sw.DeviceInfo.from_bytes(info_data)
        except ValueError as exc:
            raise DeviceInitError(f"device {self.name} ({self.kind}): bad device info reply: {exc}",
                                  source=self.transport.url) from exc
        self.controller_type = self._check_type(self.info.type)
        log.info("device %s: Nintendo %s, firmware %d.%02d, MAC %s", self.name,
                 sw.TYPE_NAMES.get(self.info.type, f"type {self.info.type}"), *self.info.firmware, self.info.mac_str)
        self._read_calibration()
        self.subcommand(sw.SC_ENABLE_IMU, b"\x01", "enable IMU (0x40)")
        self.subcommand(sw.SC_SET_MODE, bytes((sw.IN_FULL,)), "input mode 0x30 (0x03)")

    def _check_type(self, t: int) -> int:
        if t != sw.TYPE_PRO:
            raise DeviceInitError(f"device {self.name}: it says it is a {sw.TYPE_NAMES.get(t, f'type {t}')}, not a "
                                  f"Pro Controller; use kind joycon", source=self.transport.url)
        return t

    def _usb_setup(self) -> None:
        for cmd, what in ((sw.USB_STATUS, "USB status (0x80 0x01)"), (sw.USB_HANDSHAKE, "USB handshake (0x80 0x02)"),
                          (sw.USB_BAUD_3M, "USB baud rate (0x80 0x03)"),
                          (sw.USB_HANDSHAKE, "USB handshake (0x80 0x02)")):
            self._usb_command(cmd, what)
        self.hid_output(sw.usb_command(sw.USB_NO_TIMEOUT))  # no reply

    def _usb_command(self, cmd: int, what: str) -> bytes:
        timeout = self.opts["reply_timeout"]
        for attempt in range(self.opts["retries"] + 1):
            self.hid_output(sw.usb_command(cmd))
            try:
                return self.hid_wait_for(lambda d: len(d) >= 2 and d[0] == sw.IN_USB_REPLY and d[1] == cmd,
                                         timeout, what)
            except DeviceTimeoutError:
                if attempt == self.opts["retries"]:
                    raise
                log.info("device %s: no answer to %s, sending it again", self.name, what)
        raise AssertionError("unreachable")

    def subcommand(self, sc: int, args: bytes, what: str) -> SubcommandReply:
        """Send a subcommand and return its ACKed 0x21 reply.

        Raises:
            DeviceTimeoutError: no reply after the retries.
            DeviceInitError: a reply to another subcommand, or a NACK after the retries.
        """
        timeout = self.opts["reply_timeout"]
        tries = self.opts["retries"] + 1
        codec = SwitchCodec()
        others: list[int] = []  # replies to other subcommands (late answers to an earlier send): skipped

        def ours(d: bytes) -> bool:
            if len(d) < 15 or d[0] != sw.IN_SUBCMD_REPLY:
                return False
            if d[14] != sc:
                others.append(d[14])
                return False
            return True

        for attempt in range(tries):
            self.hid_output(sw.subcommand_report(self._counter, sc, args))
            self._counter = (self._counter + 1) & 0x0F
            try:
                raw = self.hid_wait_for(ours, timeout, f"subcommand {what}")
            except DeviceTimeoutError as exc:
                if attempt < tries - 1:
                    log.info("device %s: no reply to subcommand %s, sending it again", self.name, what)
                    continue
                if others:
                    raise DeviceInitError(
                        f"device {self.name} ({self.kind}): subcommand {what} was only ever answered with replies to"
                        f" other subcommands ({', '.join(f'0x{x:02x}' for x in sorted(set(others)))}), sent {tries}"
                        " time(s)", source=self.transport.url) from None
                raise DeviceTimeoutError(f"{exc} (sent {tries} time(s))", source=self.transport.url) from None
            rep = codec.feed(raw)[0]
            assert isinstance(rep, SubcommandReply)
            if not rep.acked:
                if attempt == tries - 1:
                    raise DeviceInitError(f"device {self.name} ({self.kind}): subcommand {what} was refused (NACK, "
                                          f"ack byte 0x{rep.ack:02x}) {tries} time(s)", source=self.transport.url)
                log.info("device %s: subcommand %s refused (NACK), sending it again", self.name, what)
                time.sleep(0.01)
                continue
            return rep
        raise AssertionError("unreachable")

    def spi_read(self, address: int, length: int, what: str) -> bytes:
        """Read SPI flash; the reply must echo the address and length.

        Raises:
            DeviceInitError: the reply is for another address or length, or short.
        """
        rep = self.subcommand(sw.SC_SPI_READ, sw.spi_read_args(address, length),
                              f"SPI read of {what} at 0x{address:04x}")
        try:
            addr, n, payload = sw.parse_spi_reply(rep.data)
        except ValueError as exc:
            raise DeviceInitError(f"device {self.name}: SPI read of {what}: {exc}", source=self.transport.url) from exc
        if addr != address or n != length or len(payload) != length:
            raise DeviceInitError(f"device {self.name} ({self.kind}): SPI read of {what} at 0x{address:04x} ({length} "
                                  f"bytes) was answered for 0x{addr:04x} ({n} bytes)", source=self.transport.url)
        self._pending.append(DeviceDescriptor(self.name, f"switch.spi.{address:04x}", payload, self.clock.now_ns()))
        return payload

    def _fallback(self, what: str, why: str) -> None:
        self.calibration_fallbacks += 1
        log.warning("device %s (%s): %s %s; using nominal values", self.name, self.kind, what, why)

    def _read_calibration(self) -> None:
        factory = self.spi_read(sw.SPI_FACTORY_IMU, 24, "factory IMU calibration")
        user = self.spi_read(sw.SPI_USER_IMU, 26, "user IMU calibration")
        cal, src = ImuCalibration(), "nominal"
        if user[:2] == sw.USER_MAGIC and ImuCalibration.from_bytes(user[2:]).valid():
            cal, src = ImuCalibration.from_bytes(user[2:]), "user"
        elif sw.blank(factory):
            self._fallback("factory IMU calibration", "is blank (all 0xFF)")
        elif not ImuCalibration.from_bytes(factory).valid():
            self._fallback("factory IMU calibration", f"is unusable ({factory.hex()})")
        else:
            cal, src = ImuCalibration.from_bytes(factory), "factory"
        self.imu_cal, self.imu_cal_source = cal, src
        sticks = self.spi_read(sw.SPI_FACTORY_STICKS, 18, "factory stick calibration")
        self.spi_read(sw.SPI_IMU_HORIZONTAL, 6, "6-axis horizontal offsets")
        params = self.spi_read(sw.SPI_STICK_PARAMS, 18, "stick parameters")
        cals = []
        for i, left in ((0, True), (1, False)):
            c = StickCalibration.from_bytes(sticks[9 * i:9 * i + 9], left)
            if not c.valid():
                if self._uses_stick(left):
                    self._fallback(f"factory {'left' if left else 'right'} stick calibration", "is blank or unusable")
                c = StickCalibration()
            cals.append(c)
        self.sticks_cal = (cals[0], cals[1])
        self.stick_deadzone = 0 if sw.blank(params) else sw.unpack12(params[3:6])[0]
        self._pending.append(DeviceDescriptor(self.name, "switch.imu_calibration", cal.to_bytes(), self.clock.now_ns()))
        log.info("device %s: %s IMU calibration %s", self.name, src, cal)

    def _uses_stick(self, left: bool) -> bool:
        return True

    # -- decoding -----------------------------------------------------------------------------------
    def _axes(self, v: tuple[float, ...]) -> tuple[float, ...]:
        return v

    def _stick_values(self, rep: FullReport) -> tuple[float, ...]:
        return self.sticks_cal[0].normalise(rep.state.lstick) + self.sticks_cal[1].normalise(rep.state.rstick)

    def frame_to_readings(self, frame: Any) -> Iterable[Reading]:
        if not isinstance(frame, FullReport):
            return ()
        timer = frame.state.timer
        # how many of the three samples are new (overlapping reports repeat samples)
        new = 3
        if self._last_tick is not None:
            d = (timer - self._last_tick) % TIMER_WRAP
            if d < 3:
                new = d
                self.overlapping_samples += 3 - d
        self._last_tick = timer
        out = []
        cal = self.imu_cal
        for j in range(3 - new, 3):
            out.append(Reading(IMU, self._axes(cal.to_si(frame.imu[j])), (timer - 2 + j) % TIMER_WRAP))
        b = frame.state.buttons
        out.append(Reading(STICKS, self._stick_values(frame), timer))
        out.append(Reading(BUTTONS, tuple(float((b >> bit) & 1) for bit, _ in sw.BUTTONS), timer))
        return out

    def health(self) -> dict[str, Any]:
        return {**super().health(), "overlapping_samples": self.overlapping_samples,
                "calibration_fallbacks": self.calibration_fallbacks, "imu_calibration": self.imu_cal_source}


class SwitchPro(_SwitchBase):
    """Nintendo Switch Pro Controller over USB or Bluetooth: IMU (3 samples per report), sticks, buttons."""

    kind = "switchpro"
    description = "Nintendo Switch Pro Controller (057e:2009), USB or Bluetooth"


class JoyCon(_SwitchBase):
    """A Joy-Con (L or R) over Bluetooth; the right one's IMU axes are turned into the left one's frame."""

    kind = "joycon"
    description = "Nintendo Joy-Con L (057e:2006) or R (057e:2007), Bluetooth"
    frame_text = JOYCON_FRAME
    stick_channels = ("x", "y")
    options: ClassVar[dict[str, Option]] = {
        **_SwitchBase.options,
        "side": Option(str, "auto", "which Joy-Con (auto: from the device info, else the product ID)",
                       choices=("auto", "left", "right")),
    }

    def _check_type(self, t: int) -> int:
        side = self.opts["side"]
        if side == "auto":
            if t in (sw.TYPE_LEFT, sw.TYPE_RIGHT):
                return t
            pid = self.identity.pid
            if pid in (PID_LEFT, PID_RIGHT):
                log.warning("device %s: device info type %d is not a Joy-Con; side from the product ID 0x%04x",
                            self.name, t, pid)
                return sw.TYPE_LEFT if pid == PID_LEFT else sw.TYPE_RIGHT
            raise DeviceInitError(f"device {self.name}: it says it is a {sw.TYPE_NAMES.get(t, f'type {t}')}, not a "
                                  f"Joy-Con; use kind switchpro, or side=left|right", source=self.transport.url)
        want = sw.TYPE_LEFT if side == "left" else sw.TYPE_RIGHT
        if t in (sw.TYPE_LEFT, sw.TYPE_RIGHT) and t != want:
            raise DeviceInitError(f"device {self.name}: side={side} but it says it is a {sw.TYPE_NAMES[t]}",
                                  source=self.transport.url)
        return want

    @property
    def side(self) -> str:
        return "right" if self.controller_type == sw.TYPE_RIGHT else "left"

    def _uses_stick(self, left: bool) -> bool:
        return left == (self.controller_type == sw.TYPE_LEFT)

    def _axes(self, v: tuple[float, ...]) -> tuple[float, ...]:
        if self.controller_type == sw.TYPE_RIGHT:
            return (v[0], -v[1], -v[2], v[3], -v[4], -v[5])
        return v

    def _stick_values(self, rep: FullReport) -> tuple[float, ...]:
        if self.controller_type == sw.TYPE_RIGHT:
            return self.sticks_cal[1].normalise(rep.state.rstick)
        return self.sticks_cal[0].normalise(rep.state.lstick)
