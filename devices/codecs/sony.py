"""Sony DualShock 4 and DualSense input reports and IMU calibration (sans-IO).

Written from the public description of the protocol (Linux ``hid-playstation``/``hid-sony``
behaviour); every HID input report is one ``feed`` call, its report ID first.

Input reports (``feed``):

* DS4 USB ``0x01``, 64 bytes: the common block at byte 1, touch data at byte 33.
* DS4 Bluetooth ``0x11``, 78 bytes: two header bytes, the common block at byte 3, touch data at
  byte 35, CRC32 (``zlib.crc32`` over ``0xA1`` + bytes 0..73) little-endian in bytes 74..77.
* DS4/DualSense Bluetooth *reduced* ``0x01``, 10 bytes (sticks, buttons, triggers, no IMU): sent
  until the host reads the calibration feature report. Recognised and counted in
  ``stats.reduced_reports``; yields no frame.
* DualSense USB ``0x01``, 64 bytes: the common block at byte 1.
* DualSense Bluetooth ``0x31``, 78 bytes: a tag byte, the common block at byte 2, CRC32 as above.

Anything else (unknown report ID, wrong length) is a framing error, a bad CRC a checksum error;
both are counted and never raise unless the codec is strict.

Calibration (``parse_calibration``): DS4 feature ``0x02`` over USB (37 bytes) or ``0x05`` over
Bluetooth (41 bytes, CRC32 with seed ``0xA3`` in the last 4 bytes, the +/- gyro references in a
different order), DualSense ``0x05`` (41 bytes; over Bluetooth the last 4 bytes are the CRC32).
``ImuCalibration.scale()`` gives per-axis factors the way the kernel driver computes them:

* gyro ``deg/s = raw * (speed_plus + speed_minus) / (|plus - bias| + |minus - bias|)`` (the
  firmware reports a bias-corrected rate; the bias only moves the reference points);
* accel ``g = (raw - (plus - (plus - minus) / 2)) * 2 / (plus - minus)``.

A zero denominator falls back to the nominal scale (gyro 2000 deg/s full scale, i.e. 1/16.384
deg/s per count; accel 8192 counts per g), and ``ImuScale.fallback`` names the axes.
"""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from capture.errors import ProtocolError
from devices.codecs.base import Codec, CodecStats

G = 9.80665
INPUT_CRC_SEED = 0xA1
OUTPUT_CRC_SEED = 0xA2
FEATURE_CRC_SEED = 0xA3

USB = "usb"
BLUETOOTH = "bluetooth"

#: nominal scales used when a calibration is degenerate
NOMINAL_GYRO_DEG_PER_COUNT = 2000.0 / 32768.0
NOMINAL_ACC_COUNTS_PER_G = 8192.0

DS4_TICK_HZ = 3e6 / 16.0     # 5.333 us per tick
DS4_TICK_WRAP = 1 << 16
DS_TICK_HZ = 3e6             # 0.333 us per tick
DS_TICK_WRAP = 1 << 32

DS4_TOUCH_W, DS4_TOUCH_H = 1920, 942
DS_TOUCH_W, DS_TOUCH_H = 1920, 1080

#: button bit order of ``PadReport.buttons`` (same for both pads; DS4 has no mute)
BUTTONS = ("square", "cross", "circle", "triangle", "l1", "r1", "l2", "r2", "share", "options", "l3", "r3",
           "ps", "touchpad", "mute")
#: hat value (0..7 clockwise from up; 8 = released) -> (dpad_x, dpad_y), y up
HAT = ((0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1), (-1, 0), (-1, 1), (0, 0))


def crc32(seed: int, data: bytes | bytearray) -> int:
    """The PlayStation CRC32: ``zlib.crc32`` over the seed byte then the data."""
    return zlib.crc32(bytes(data), zlib.crc32(bytes((seed,))))


@dataclass(frozen=True, slots=True)
class TouchPoint:
    active: bool
    id: int
    x: int
    y: int


NO_TOUCH = TouchPoint(False, 0, 0, 0)


@dataclass(frozen=True, slots=True)
class PadReport:
    """One full input report, in wire units.

    ``bus`` is ``"usb"`` or ``"bluetooth"`` (which layout it came in), ``sticks`` are ``lx, ly, rx,
    ry`` (0..255, y down as on the wire), ``triggers`` ``l2, r2`` (0..255), ``buttons`` the bits of
    ``BUTTONS``, ``hat`` 0..8, ``gyro``/``accel`` raw s16 (x, y, z), ``timestamp`` the raw sensor
    timestamp, ``status`` the raw battery byte, ``counter`` the report counter (DS4: 6 bits,
    DualSense: 8 bits), ``temperature`` the raw DS4 sensor temperature byte (DualSense: 0).
    """

    bus: str
    sticks: tuple[int, int, int, int]
    triggers: tuple[int, int]
    buttons: int
    hat: int
    gyro: tuple[int, int, int]
    accel: tuple[int, int, int]
    timestamp: int
    status: int = 0
    touch: tuple[TouchPoint, TouchPoint] = (NO_TOUCH, NO_TOUCH)
    counter: int = 0
    temperature: int = 0


@dataclass
class SonyCodecStats(CodecStats):
    reduced_reports: int = 0


def _touch_decode(b: bytes | bytearray, o: int) -> TouchPoint:
    c, x0, xy, y1 = b[o], b[o + 1], b[o + 2], b[o + 3]
    return TouchPoint(not (c & 0x80), c & 0x7F, x0 | ((xy & 0x0F) << 8), (xy >> 4) | (y1 << 4))


def _touch_encode(p: TouchPoint) -> bytes:
    x, y = p.x & 0xFFF, p.y & 0xFFF
    return bytes(((0 if p.active else 0x80) | (p.id & 0x7F), x & 0xFF, (x >> 8) | ((y & 0x0F) << 4), y >> 4))


class _SonyCodec(Codec):
    """Shared parts; subclasses give the layouts."""

    model: ClassVar[str] = ""
    usb_id: ClassVar[int] = 0x01
    bt_id: ClassVar[int] = 0
    full_len: ClassVar[int] = 64
    bt_len: ClassVar[int] = 78
    reduced_len: ClassVar[int] = 10
    button_mask2: ClassVar[int] = 0x03

    def __init__(self, strict: bool = False) -> None:
        super().__init__(strict)
        self.stats: SonyCodecStats = SonyCodecStats()
        #: layout of the last full report ("usb" or "bluetooth"), None before the first
        self.bus_seen: str | None = None

    def feed(self, data: bytes) -> list[PadReport]:
        b = bytes(data)
        self.stats.bytes_in += len(b)
        if not b:
            self._bad("framing", "empty report", 0, b)
            return []
        rid = b[0]
        n = len(b)
        if rid == self.usb_id and n == self.full_len:
            out = self._decode(b, USB)
        elif rid == self.usb_id and n == self.reduced_len:
            self.stats.reduced_reports += 1
            return []
        elif rid == self.bt_id and n == self.bt_len:
            want = int.from_bytes(b[-4:], "little")
            got = crc32(INPUT_CRC_SEED, b[:-4])
            if want != got:
                self.stats.skipped_bytes += n
                self._bad("checksum", f"report 0x{rid:02x}: CRC32 0x{want:08x}, computed 0x{got:08x}", 0, b)
                return []
            out = self._decode(b, BLUETOOTH)
        elif rid in (self.usb_id, self.bt_id):
            self.stats.skipped_bytes += n
            self._bad("framing", f"report 0x{rid:02x} of {n} bytes (expected {self._lengths(rid)})", 0, b)
            return []
        else:
            self.stats.skipped_bytes += n
            self._bad("framing", f"unknown report ID 0x{rid:02x} ({n} bytes)", 0, b)
            return []
        self.stats.frames += 1
        self.bus_seen = out.bus
        return [out]

    def _lengths(self, rid: int) -> str:
        if rid == self.usb_id:
            return f"{self.full_len} over USB or {self.reduced_len} (reduced, Bluetooth)"
        return f"{self.bt_len}"

    def encode(self, frame: PadReport) -> bytes:
        if frame.bus == BLUETOOTH:
            body = bytearray(self._encode_bt_body(frame))
            body += crc32(INPUT_CRC_SEED, body).to_bytes(4, "little")
            return bytes(body)
        return self._encode_usb(frame)

    def encode_reduced(self, frame: PadReport) -> bytes:
        """The 10-byte reduced Bluetooth report 0x01 (sticks, buttons, triggers) for ``frame``."""
        b0, b1, b2 = self._button_bytes(frame)
        lx, ly, rx, ry = frame.sticks
        return bytes((self.usb_id, lx, ly, rx, ry, b0, b1, b2 | ((frame.counter & 0x3F) << 2),
                      frame.triggers[0], frame.triggers[1]))

    # -- helpers --------------------------------------------------------------------------------
    def _button_bytes(self, f: PadReport) -> tuple[int, int, int]:
        bt = f.buttons
        return ((f.hat & 0x0F) | ((bt & 0x0F) << 4), (bt >> 4) & 0xFF, (bt >> 12) & self.button_mask2)

    def _buttons_of(self, b0: int, b1: int, b2: int) -> tuple[int, int]:
        return (b0 >> 4) | (b1 << 4) | ((b2 & self.button_mask2) << 12), min(b0 & 0x0F, 8)

    def _decode(self, b: bytes, bus: str) -> PadReport:
        raise NotImplementedError

    def _encode_usb(self, f: PadReport) -> bytes:
        raise NotImplementedError

    def _encode_bt_body(self, f: PadReport) -> bytes:
        raise NotImplementedError


_S16x6 = struct.Struct("<6h")


def _s16(v: int) -> int:
    return max(-32768, min(32767, int(v)))


class DualShock4Codec(_SonyCodec):
    """DualShock 4 input reports (USB 0x01, Bluetooth 0x11 and the reduced Bluetooth 0x01)."""

    name = "ds4"
    model = "ds4"
    bt_id = 0x11
    button_mask2 = 0x03

    def _decode(self, b: bytes, bus: str) -> PadReport:
        c = 1 if bus == USB else 3
        t = c + 32 + 1  # first touch report: timestamp byte, then two points
        buttons, hat = self._buttons_of(b[c + 4], b[c + 5], b[c + 6])
        v = _S16x6.unpack_from(b, c + 12)
        return PadReport(bus, (b[c], b[c + 1], b[c + 2], b[c + 3]), (b[c + 7], b[c + 8]), buttons, hat,
                         v[0:3], v[3:6], b[c + 9] | (b[c + 10] << 8), b[c + 29],
                         (_touch_decode(b, t + 1), _touch_decode(b, t + 5)), b[c + 6] >> 2, b[c + 11])

    def _common(self, f: PadReport) -> bytearray:
        b0, b1, b2 = self._button_bytes(f)
        c = bytearray(32)
        c[0:4] = bytes(f.sticks)
        c[4], c[5], c[6] = b0, b1, b2 | ((f.counter & 0x3F) << 2)
        c[7], c[8] = f.triggers
        c[9:11] = (f.timestamp & 0xFFFF).to_bytes(2, "little")
        c[11] = f.temperature & 0xFF
        _S16x6.pack_into(c, 12, *(_s16(x) for x in (*f.gyro, *f.accel)))
        c[29] = f.status & 0xFF
        return c

    def _touch_block(self, f: PadReport, n_reports: int) -> bytes:
        first = bytes(((f.timestamp >> 8) & 0xFF,)) + _touch_encode(f.touch[0]) + _touch_encode(f.touch[1])
        empty = bytes(1) + _touch_encode(NO_TOUCH) * 2
        return bytes((1,)) + first + empty * (n_reports - 1)

    def _encode_usb(self, f: PadReport) -> bytes:
        out = bytes((0x01,)) + self._common(f) + self._touch_block(f, 3)
        return out + bytes(64 - len(out))

    def _encode_bt_body(self, f: PadReport) -> bytes:
        out = bytes((0x11, 0xC0, 0x00)) + self._common(f) + self._touch_block(f, 4)
        return out + bytes(74 - len(out))


class DualSenseCodec(_SonyCodec):
    """DualSense input reports (USB 0x01, Bluetooth 0x31 and the reduced Bluetooth 0x01)."""

    name = "dualsense"
    model = "dualsense"
    bt_id = 0x31
    button_mask2 = 0x07

    def _decode(self, b: bytes, bus: str) -> PadReport:
        c = 1 if bus == USB else 2
        buttons, hat = self._buttons_of(b[c + 7], b[c + 8], b[c + 9])
        v = _S16x6.unpack_from(b, c + 15)
        return PadReport(bus, (b[c], b[c + 1], b[c + 2], b[c + 3]), (b[c + 4], b[c + 5]), buttons, hat,
                         v[0:3], v[3:6], int.from_bytes(b[c + 27:c + 31], "little"), b[c + 52],
                         (_touch_decode(b, c + 32), _touch_decode(b, c + 36)), b[c + 6], 0)

    def _common(self, f: PadReport) -> bytearray:
        b0, b1, b2 = self._button_bytes(f)
        c = bytearray(63)
        c[0:4] = bytes(f.sticks)
        c[4], c[5] = f.triggers
        c[6] = f.counter & 0xFF
        c[7], c[8], c[9] = b0, b1, b2
        _S16x6.pack_into(c, 15, *(_s16(x) for x in (*f.gyro, *f.accel)))
        c[27:31] = (f.timestamp & 0xFFFFFFFF).to_bytes(4, "little")
        c[32:36] = _touch_encode(f.touch[0])
        c[36:40] = _touch_encode(f.touch[1])
        c[52] = f.status & 0xFF
        return c

    def _encode_usb(self, f: PadReport) -> bytes:
        return bytes((0x01,)) + self._common(f)

    def _encode_bt_body(self, f: PadReport) -> bytes:
        out = bytes((0x31, (f.counter << 4) & 0xF0)) + self._common(f)
        return out + bytes(74 - len(out))


# ------------------------------------------------------------------------------------------------
# Calibration
# ------------------------------------------------------------------------------------------------

_CAL = struct.Struct("<17h")


@dataclass(frozen=True)
class ImuScale:
    """Per-axis conversion of raw counts: ``gyro_rad_s = raw * gyro``, ``acc_ms2 = (raw - acc_bias) * acc``."""

    gyro: tuple[float, float, float]
    acc: tuple[float, float, float]
    acc_bias: tuple[float, float, float]
    #: axes that fell back to the nominal scale (degenerate calibration), e.g. ``("gyro x",)``
    fallback: tuple[str, ...] = ()

    def convert(self, gyro: tuple[int, int, int], accel: tuple[int, int, int]) -> tuple[float, ...]:
        """``(ax, ay, az, gx, gy, gz)`` in m/s^2 and rad/s."""
        g, a, ab = self.gyro, self.acc, self.acc_bias
        return ((accel[0] - ab[0]) * a[0], (accel[1] - ab[1]) * a[1], (accel[2] - ab[2]) * a[2],
                gyro[0] * g[0], gyro[1] * g[1], gyro[2] * g[2])

    def to_raw(self, gyro_rad_s: np.ndarray, acc_ms2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The inverse (for simulators): (n, 3) SI values -> (n, 3) int raw counts, clipped to s16."""
        g = np.rint(np.asarray(gyro_rad_s, np.float64) / np.asarray(self.gyro))
        a = np.rint(np.asarray(acc_ms2, np.float64) / np.asarray(self.acc) + np.asarray(self.acc_bias))
        return (np.clip(g, -32768, 32767).astype(np.int64), np.clip(a, -32768, 32767).astype(np.int64))


@dataclass(frozen=True)
class ImuCalibration:
    """The factory IMU calibration of a DS4 or DualSense (raw s16 values)."""

    gyro_bias: tuple[int, int, int]
    gyro_plus: tuple[int, int, int]
    gyro_minus: tuple[int, int, int]
    speed_plus: int
    speed_minus: int
    acc_plus: tuple[int, int, int]
    acc_minus: tuple[int, int, int]

    def scale(self) -> ImuScale:
        """Conversion factors; degenerate axes fall back to nominal (named in ``fallback``)."""
        speed_2x = self.speed_plus + self.speed_minus
        gyro: list[float] = []
        acc: list[float] = []
        acc_bias: list[float] = []
        fb: list[str] = []
        for i, ax in enumerate("xyz"):
            den = abs(self.gyro_plus[i] - self.gyro_bias[i]) + abs(self.gyro_minus[i] - self.gyro_bias[i])
            if den == 0 or speed_2x == 0:
                fb.append(f"gyro {ax}")
                gyro.append(math.radians(NOMINAL_GYRO_DEG_PER_COUNT))
            else:
                gyro.append(math.radians(speed_2x / den))
            rng = self.acc_plus[i] - self.acc_minus[i]
            if rng == 0:
                fb.append(f"accel {ax}")
                acc.append(G / NOMINAL_ACC_COUNTS_PER_G)
                acc_bias.append(0.0)
            else:
                acc.append(2.0 * G / rng)
                acc_bias.append(self.acc_plus[i] - rng / 2.0)
        return ImuScale((gyro[0], gyro[1], gyro[2]), (acc[0], acc[1], acc[2]),
                        (acc_bias[0], acc_bias[1], acc_bias[2]), tuple(fb))


def calibration_report(model: str, bus: str) -> tuple[int, int]:
    """``(report ID, length incl. the ID)`` of the calibration feature report."""
    if model == "ds4":
        return (0x05, 41) if bus == BLUETOOTH else (0x02, 37)
    if model == "dualsense":
        return 0x05, 41
    raise ValueError(f"unknown model {model!r}")


def parse_calibration(data: bytes, model: str, bus: str) -> ImuCalibration:
    """Parse the calibration feature report (its ID first).

    Raises:
        ProtocolError: wrong report ID, wrong length or (Bluetooth) a bad CRC; the message says which.
    """
    rid, length = calibration_report(model, bus)
    b = bytes(data)
    what = f"{model} calibration feature report 0x{rid:02x} ({bus})"
    if not b:
        raise ProtocolError(f"{what}: empty answer", raw=b)
    if b[0] != rid:
        raise ProtocolError(f"{what}: the answer has report ID 0x{b[0]:02x}", raw=b)
    if len(b) != length:
        raise ProtocolError(f"{what}: {len(b)} bytes, expected {length}", raw=b)
    if bus == BLUETOOTH:
        want = int.from_bytes(b[-4:], "little")
        got = crc32(FEATURE_CRC_SEED, b[:-4])
        if want != got:
            raise ProtocolError(f"{what}: bad CRC32 0x{want:08x}, computed 0x{got:08x}", raw=b)
    v = _CAL.unpack_from(b, 1)
    if model == "ds4" and bus == BLUETOOTH:
        plus, minus = (v[3], v[4], v[5]), (v[6], v[7], v[8])
    else:
        plus, minus = (v[3], v[5], v[7]), (v[4], v[6], v[8])
    return ImuCalibration((v[0], v[1], v[2]), plus, minus, v[9], v[10], (v[11], v[13], v[15]),
                          (v[12], v[14], v[16]))


def encode_calibration(cal: ImuCalibration, model: str, bus: str) -> bytes:
    """The calibration feature report for ``cal`` (the inverse of ``parse_calibration``)."""
    rid, length = calibration_report(model, bus)
    gyro: tuple[int, ...]
    if model == "ds4" and bus == BLUETOOTH:
        gyro = (*cal.gyro_plus, *cal.gyro_minus)
    else:
        gyro = tuple(x for pm in zip(cal.gyro_plus, cal.gyro_minus, strict=True) for x in pm)
    acc = tuple(x for pm in zip(cal.acc_plus, cal.acc_minus, strict=True) for x in pm)
    out = bytearray(length)
    out[0] = rid
    _CAL.pack_into(out, 1, *cal.gyro_bias, *gyro, cal.speed_plus, cal.speed_minus, *acc)
    if bus == BLUETOOTH:
        out[-4:] = crc32(FEATURE_CRC_SEED, out[:-4]).to_bytes(4, "little")
    return bytes(out)


def battery_of(model: str, status: int) -> tuple[float, bool]:
    """``(level in %, charging)`` from the raw status byte (an estimate in steps of 10 %)."""
    level = status & 0x0F
    if model == "ds4":
        cable = bool(status & 0x10)
        if cable:
            return (100.0, False) if level >= 11 else (float(min(level * 10 + 5, 100)), True)
        return float(min(level * 10 + 5, 100)), False
    charge = status >> 4
    if charge == 2:
        return 100.0, False
    return float(min(level * 10 + 5, 100)), charge == 1


__all__ = ["BLUETOOTH", "BUTTONS", "DS4_TICK_HZ", "DS4_TICK_WRAP", "DS_TICK_HZ", "DS_TICK_WRAP", "HAT", "NO_TOUCH",
           "USB", "DualSenseCodec", "DualShock4Codec", "ImuCalibration", "ImuScale", "PadReport", "TouchPoint",
           "battery_of", "calibration_report", "crc32", "encode_calibration", "parse_calibration"]
