"""Simulated Nintendo Switch Pro Controller and Joy-Cons for ``simhid://switchpro``,
``simhid://joycon_l`` and ``simhid://joycon_r``.

Each responder has its own report descriptor (written here, plausible for the bus), an SPI flash
image holding factory calibration written with the codec's encoders (seeded offsets around the
nominal values; ``user_cal=true`` also writes a user IMU calibration, which then is what the
sensor data is encoded with), answers the USB ``0x80`` commands (USB only) and the subcommands
0x02, 0x10, 0x03, 0x40, 0x48, 0x30 in 0x21 replies, and streams:

* before input mode 0x30 with the IMU enabled: a 0x3F simple-mode report every 0.5 s (the real pad
  sends them on button changes);
* after: a 0x30 report every 15 ms whose three IMU samples are the seeded ``WavingMotion`` at
  ``t - 10 ms``, ``t - 5 ms`` and ``t`` (never averaged), timer byte ``round(t / 5 ms) mod 256``.

``handshake=``: ``ok``; ``silent`` (never answers anything); ``wrong`` (every reply echoes another
subcommand ID); ``wrong_spi`` (SPI replies for another address); ``nack`` (device info refused);
``blank_calibration`` (factory IMU and stick calibration all 0xFF; the sensor is then encoded with
nominal calibration). ``drop_every=N`` drops every Nth 0x30 report (a gap, not a shift).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from devices.codecs import nintendo as sw
from devices.codecs.nintendo import (
    FullReport,
    ImuCalibration,
    PadState,
    StickCalibration,
    SubcommandReply,
    SwitchCodec,
)
from devices.options import Option
from sim_devices.hid_sim import HidResponder
from sim_devices.motion import G, WavingMotion

if TYPE_CHECKING:
    from collections.abc import Iterator, Mapping

REPORT_PERIOD_S = 0.015
SAMPLE_PERIOD_S = 0.005
IDLE_PERIOD_S = 0.5


# -- a tiny report descriptor writer --------------------------------------------------------------
def _item(prefix: int, value: int | None = None, size: int | None = None) -> bytes:
    """A short item: ``prefix`` is tag and type (the low two bits, the size, are filled in)."""
    if value is None:
        return bytes((prefix,))
    if size is None:
        size = 1 if 0 <= value <= 0xFF else 2 if 0 <= value <= 0xFFFF else 4
    code = {1: 1, 2: 2, 4: 3}[size]
    return bytes((prefix | code,)) + (value & ((1 << (8 * size)) - 1)).to_bytes(size, "little")


def _vendor_report(rid: int, count: int, main: int) -> bytes:
    """A vendor-defined report of ``count`` bytes; ``main`` 0x80 input, 0x90 output."""
    return (_item(0x84, rid) + _item(0x08, rid) + _item(0x74, 8) + _item(0x94, count) + _item(main, 0x02))


def switch_report_descriptor(usb: bool) -> bytes:
    n = 63 if usb else 48
    d = _item(0x04, 0x01) + _item(0x08, 0x04) + _item(0xA0, 0x01)           # Generic Desktop, Joystick, App
    d += _item(0x04, 0xFF01, 2)                                             # vendor page 0xFF01
    for rid in (sw.IN_SUBCMD_REPLY, sw.IN_FULL, 0x31):
        d += _vendor_report(rid, n if rid != 0x31 else 361, 0x80)
    if usb:
        d += _vendor_report(sw.IN_USB_REPLY, 63, 0x80)
    # 0x3F simple mode: 16 buttons, a hat, 4 16-bit axes
    d += _item(0x84, sw.IN_SIMPLE) + _item(0x04, 0x09) + _item(0x18, 1) + _item(0x28, 16)
    d += _item(0x14, 0) + _item(0x24, 1) + _item(0x74, 1) + _item(0x94, 16) + _item(0x80, 0x02)
    d += _item(0x04, 0x01) + _item(0x08, 0x39) + _item(0x24, 7) + _item(0x74, 4) + _item(0x94, 1) + _item(0x80, 0x42)
    d += _item(0x74, 4) + _item(0x94, 1) + _item(0x80, 0x01)
    d += _item(0x08, 0x30) + _item(0x08, 0x31) + _item(0x08, 0x33) + _item(0x08, 0x34)
    d += _item(0x14, 0) + _item(0x24, 0xFFFF, 4) + _item(0x74, 16) + _item(0x94, 4) + _item(0x80, 0x02)
    d += _item(0x04, 0xFF01, 2)
    for rid in (sw.OUT_RUMBLE_SUBCMD, 0x10, 0x11):
        d += _vendor_report(rid, 48, 0x90)
    if usb:
        d += _vendor_report(sw.OUT_USB_CMD, 63, 0x90)
    return d + _item(0xC0)


class _SwitchResponder(HidResponder):
    vid = 0x057E
    ctype: ClassVar[int] = sw.TYPE_PRO
    connection: ClassVar[int] = 0x0
    motion: WavingMotion
    options: ClassVar[dict[str, Option]] = {
        "handshake": Option(str, "ok", "how the controller answers the handshake",
                            choices=("ok", "silent", "wrong", "wrong_spi", "nack", "blank_calibration")),
        "user_cal": Option(bool, False, "the SPI flash also holds a user IMU calibration (used for the sensor data)"),
        "drop_every": Option(int, 0, "drop every Nth 0x30 report (0 = none)", min=0),
    }

    def __init__(self, opts: Mapping[str, Any], address: str = "") -> None:
        super().__init__(opts, address)
        seed = int(self.opts.get("seed", 1))
        self.mode = str(self.opts.get("handshake", "ok"))
        self.motion = WavingMotion(seed)
        r = self.rng
        self.mac = bytes((0x98, 0xB6)) + bytes(int(x) for x in r.integers(0, 256, 4))
        self.factory_cal = self._random_cal()
        self.user_cal = self._random_cal()
        self.stick_cal = (StickCalibration((2100, 1950), (1500, 1450), (1480, 1520)),
                          StickCalibration((1990, 2070), (1440, 1510), (1530, 1470)))
        self.spi = bytearray(b"\xff" * 0x9000)
        blank = self.mode == "blank_calibration"
        if not blank:
            self._spi_write(sw.SPI_FACTORY_IMU, self.factory_cal.to_bytes())
            self._spi_write(sw.SPI_FACTORY_STICKS, self.stick_cal[0].to_bytes(True) + self.stick_cal[1].to_bytes(False))
        self._spi_write(sw.SPI_IMU_HORIZONTAL, bytes((0x50, 0xFD, 0x00, 0x00, 0xC6, 0x0F)))
        self._spi_write(sw.SPI_STICK_PARAMS, sw.pack12(0x0F, 0x30) + sw.pack12(0xAE, 0x0E1) + sw.pack12(0x4D, 0x4D) * 4)
        if self.opts.get("user_cal"):
            self._spi_write(sw.SPI_USER_IMU, sw.USER_MAGIC + self.user_cal.to_bytes())
        #: the calibration the sensor data is encoded with (what a correct host uses)
        self.true_cal = self.user_cal if self.opts.get("user_cal") else ImuCalibration() if blank else self.factory_cal
        self.codec = SwitchCodec()
        self.usb_ready = False
        self.usb_only = False
        self.imu_on = False
        self.input_mode = sw.IN_SIMPLE
        self._t = 0.0
        self.subcommands: list[int] = []

    def _random_cal(self) -> ImuCalibration:
        """Calibration like a real unit's: small origins, sensitivities near the nominal ones."""
        r = self.rng

        def three(lo: int, hi: int, base: int = 0) -> tuple[int, int, int]:
            v = [base + int(x) for x in r.integers(lo, hi, 3)]
            return v[0], v[1], v[2]
        return ImuCalibration(three(-300, 300), three(-200, 200, 16384), three(-40, 40), three(-150, 150, 13371))

    def _spi_write(self, addr: int, data: bytes) -> None:
        self.spi[addr:addr + len(data)] = data

    def report_descriptor(self) -> bytes:
        return switch_report_descriptor(self.bus == "usb")

    # -- axes -------------------------------------------------------------------------------------
    def mount(self, acc: np.ndarray, gyro: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sensor-frame values from reported-frame ones (the identity except for the Joy-Con R)."""
        return acc, gyro

    def truth(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The true specific force (m/s^2) and angular rate (rad/s), in the frame the host reports,
        at device times ``t`` (s)."""
        acc_g, gyro_dps, _ = self.motion.at_many(np.asarray(t, np.float64))
        return acc_g * G, np.radians(gyro_dps)

    # -- host -> device -----------------------------------------------------------------------------
    def _state(self) -> PadState:
        return PadState(timer=round(self._t / SAMPLE_PERIOD_S) & 0xFF, battery=8, connection=self.connection | (
            1 if self.bus == "usb" else 0))

    def _answer(self, sc: int, ack: int, data: bytes = b"") -> None:
        if self.mode == "wrong":
            sc = (sc + 1) & 0xFF
        self.reply(self.codec.encode(SubcommandReply(self._state(), ack, sc, data, self.bus == "usb")))

    def output(self, data: bytes) -> None:
        if self.mode == "silent" or not data:
            return
        if data[0] == sw.OUT_USB_CMD and len(data) >= 2:
            if self.bus != "usb":
                return
            cmd = data[1]
            if cmd == sw.USB_STATUS:
                self.reply(self.codec.encode(sw.UsbReply(cmd, bytes((0x00, self.ctype)) + self.mac[::-1])))
            elif cmd in (sw.USB_HANDSHAKE, sw.USB_BAUD_3M):
                self.usb_ready = True
                self.reply(self.codec.encode(sw.UsbReply(cmd)))
            elif cmd == sw.USB_NO_TIMEOUT:
                self.usb_only = True
            return
        parsed = sw.parse_subcommand(data)
        if parsed is None:
            return
        if self.bus == "usb" and not self.usb_ready:
            return  # the UART link behind USB is not up yet
        _, sc, args = parsed
        self.subcommands.append(sc)
        if sc == sw.SC_DEVICE_INFO:
            if self.mode == "nack":
                self._answer(sc, 0x00)
                return
            self._answer(sc, sw.ack_for(sc), sw.DeviceInfo((4, 0x33), self.ctype, self.mac).to_bytes())
        elif sc == sw.SC_SPI_READ:
            addr = int.from_bytes(args[0:4], "little")
            n = min(args[4], sw.SPI_MAX_READ)
            payload = bytes(self.spi[addr:addr + n]).ljust(n, b"\xff")
            if self.mode == "wrong_spi":
                addr += 0x10
            self._answer(sc, sw.ack_for(sc), sw.spi_reply_data(addr, payload))
        elif sc == sw.SC_ENABLE_IMU:
            self.imu_on = bool(args[:1]) and args[0] != 0
            self._answer(sc, 0x80)
        elif sc == sw.SC_SET_MODE:
            self.input_mode = args[0] if args else sw.IN_SIMPLE
            self._answer(sc, 0x80)
        else:
            self._answer(sc, 0x80)

    @property
    def streaming(self) -> bool:
        return self.imu_on and self.input_mode == sw.IN_FULL and (self.bus != "usb" or self.usb_only)

    # -- device -> host -----------------------------------------------------------------------------
    def full_report(self, t: float) -> bytes:
        """The 0x30 report sent at device time ``t`` (s)."""
        ts = t + SAMPLE_PERIOD_S * np.arange(-2, 1)
        acc, gyro = self.mount(*self.truth(ts))
        imu = tuple(self.true_cal.from_si(tuple(acc[i]), tuple(gyro[i])) for i in range(3))
        ph = 2 * math.pi * 0.3 * t
        lst = self.stick_cal[0].raw((0.8 * math.sin(ph), 0.6 * math.cos(ph)))
        rst = self.stick_cal[1].raw((-0.5 * math.cos(ph), 0.9 * math.sin(ph)))
        buttons = (1 << 3) if int(t / 0.25) % 2 else 0
        state = PadState(round(t / SAMPLE_PERIOD_S) & 0xFF, 8, self.connection | (1 if self.bus == "usb" else 0),
                         buttons, lst, rst, 0)
        return self.codec.encode(FullReport(state, imu, self.bus == "usb"))

    def stream(self) -> Iterator[tuple[float, bytes]]:
        self._t = 0.0
        k = 0
        drop = int(self.opts.get("drop_every", 0))
        while True:
            if self.streaming:
                self._t += REPORT_PERIOD_S
                k += 1
                if drop and k % drop == 0:
                    continue
                yield self._t, self.full_report(self._t)
            else:
                self._t += IDLE_PERIOD_S
                yield self._t, self.codec.encode(sw.SimpleReport(bytes((0, 0, 8)) + b"\x00\x80" * 4))


class SwitchProResponder(_SwitchResponder):
    kind = "switchpro"
    pid = 0x2009
    product = "Pro Controller"
    ctype = sw.TYPE_PRO


class JoyConLeftResponder(_SwitchResponder):
    kind = "joycon"
    pid = 0x2006
    product = "Joy-Con (L)"
    ctype = sw.TYPE_LEFT
    connection = 0xE


class JoyConRightResponder(_SwitchResponder):
    kind = "joycon"
    pid = 0x2007
    product = "Joy-Con (R)"
    ctype = sw.TYPE_RIGHT
    connection = 0xE

    def mount(self, acc: np.ndarray, gyro: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The right Joy-Con's sensor is turned 180 deg about x: y and z negated."""
        flip = np.array([1.0, -1.0, -1.0])
        return acc * flip, gyro * flip
