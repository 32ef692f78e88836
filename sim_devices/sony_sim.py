"""Simulated DualShock 4 and DualSense for ``simhid://ds4`` and ``simhid://dualsense``.

Each responder has its own report descriptor (written for the simulator, per bus), its own factory
calibration (plausible values drawn from the seed, encoded by ``devices.codecs.sony``), and streams
input reports at 250 Hz built by the codec's encoder from ``WavingMotion``. The sensor timestamp
advances with device time, so the transport's ``drift_ppm`` shows up in clock sync.

Over Bluetooth the pad sends the reduced 10-byte report 0x01 until the host reads the calibration
feature report, then the full report (0x11 / 0x31), as the real pads do.

Options:

* ``handshake=ok|silent|wrong``: ``silent`` never answers the calibration read over USB (the
  transport reports a failed feature read) and, over Bluetooth, answers it but never starts full
  reports; ``wrong`` answers with a short report over USB and a bad CRC over Bluetooth.
* ``calibration=factory|degenerate``: ``degenerate`` has zero gyro and accel spans (the device falls
  back to nominal scaling); the streamed raw values then follow the nominal scale.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from devices.codecs.sony import (
    BLUETOOTH,
    DS4_TICK_HZ,
    DS4_TICK_WRAP,
    DS_TICK_HZ,
    DS_TICK_WRAP,
    USB,
    DualSenseCodec,
    DualShock4Codec,
    ImuCalibration,
    ImuScale,
    PadReport,
    TouchPoint,
    calibration_report,
    encode_calibration,
)
from devices.options import Option
from sim_devices.hid_sim import HidResponder
from sim_devices.motion import G, WavingMotion

if TYPE_CHECKING:
    from collections.abc import Iterable, Iterator, Mapping

RATE_HZ = 250.0
BLOCK = 250


# -- report descriptor items ------------------------------------------------------------------------
def _item(prefix: int, value: int | None = None, size: int | None = None) -> bytes:
    if value is None:
        return bytes((prefix,))
    if size is None:
        size = 1 if -128 <= value <= 255 else 2
    code = {1: 1, 2: 2, 4: 3}[size]
    return bytes((prefix | code,)) + (value & ((1 << (8 * size)) - 1)).to_bytes(size, "little")


def usage_page(v: int) -> bytes:
    return _item(0x04, v, 2 if v > 0xFF else 1)


def usage(v: int) -> bytes:
    return _item(0x08, v)


def report_id(v: int) -> bytes:
    return _item(0x84, v)


def fields(size: int, count: int, lo: int = 0, hi: int = 255) -> bytes:
    return _item(0x14, lo, 1) + _item(0x24, hi, 2 if hi > 127 else 1) + _item(0x74, size) + _item(0x94, count)


INPUT, OUTPUT, FEATURE = 0x80, 0x90, 0xB0


def main(kind: int, flags: int = 0x02) -> bytes:
    return _item(kind, flags)


def vendor(rid: int, kind: int, nbytes: int, use: int) -> bytes:
    """A report of ``nbytes`` opaque vendor bytes."""
    return report_id(rid) + usage_page(0xFF00) + usage(use) + fields(8, nbytes) + main(kind)


def gamepad_head(axes: tuple[int, ...], trailing_axes: tuple[int, ...], vendor_bits: int, buttons: int) -> bytes:
    """Sticks/triggers as 8-bit axes, a hat, buttons, some vendor bits, then more axes."""
    out = usage_page(0x01)
    for a in axes:
        out += usage(a)
    out += fields(8, len(axes)) + main(INPUT)
    out += usage(0x39) + fields(4, 1, 0, 7) + main(INPUT, 0x42)
    out += usage_page(0x09) + _item(0x18, 1) + _item(0x28, buttons) + fields(1, buttons, 0, 1) + main(INPUT)
    out += usage_page(0xFF00) + usage(0x20) + fields(vendor_bits and 1, vendor_bits, 0, 1) + main(INPUT)
    if trailing_axes:
        out += usage_page(0x01)
        for a in trailing_axes:
            out += usage(a)
        out += fields(8, len(trailing_axes)) + main(INPUT)
    return out


def collection(body: bytes) -> bytes:
    return usage_page(0x01) + usage(0x05) + _item(0xA0, 0x01) + body + bytes((0xC0,))


def ds4_descriptor(bus: str) -> bytes:
    x, y, z, rx, ry, rz = 0x30, 0x31, 0x32, 0x33, 0x34, 0x35
    head = gamepad_head((x, y, z, rz), (rx, ry), 6, 14)   # 9 bytes: sticks, hat+buttons+counter, triggers
    if bus == USB:
        body = (report_id(0x01) + head + usage_page(0xFF00) + usage(0x21) + fields(8, 54) + main(INPUT)
                + vendor(0x05, OUTPUT, 31, 0x22) + vendor(0x02, FEATURE, 36, 0x24)
                + vendor(0xA3, FEATURE, 48, 0x25))
    else:
        body = (report_id(0x01) + head + vendor(0x11, INPUT, 77, 0x26) + vendor(0x11, OUTPUT, 77, 0x27)
                + vendor(0x05, FEATURE, 40, 0x28) + vendor(0xA3, FEATURE, 48, 0x25))
    return collection(body)


def dualsense_descriptor(bus: str) -> bytes:
    x, y, z, rx, ry, rz = 0x30, 0x31, 0x32, 0x33, 0x34, 0x35
    if bus == USB:
        head = usage_page(0x01)
        for a in (x, y, rx, ry, z, rz):
            head += usage(a)
        head += fields(8, 6) + main(INPUT) + usage_page(0xFF00) + usage(0x20) + fields(8, 1) + main(INPUT)
        head += usage_page(0x01) + usage(0x39) + fields(4, 1, 0, 7) + main(INPUT, 0x42)
        head += usage_page(0x09) + _item(0x18, 1) + _item(0x28, 15) + fields(1, 15, 0, 1) + main(INPUT)
        head += usage_page(0xFF00) + usage(0x21) + fields(1, 13, 0, 1) + main(INPUT)
        body = (report_id(0x01) + head + usage(0x22) + fields(8, 52) + main(INPUT)
                + vendor(0x02, OUTPUT, 47, 0x23) + vendor(0x05, FEATURE, 40, 0x24) + vendor(0x20, FEATURE, 63, 0x25))
    else:
        head = gamepad_head((x, y, z, rz), (rx, ry), 6, 14)
        body = (report_id(0x01) + head + vendor(0x31, INPUT, 77, 0x26) + vendor(0x31, OUTPUT, 77, 0x27)
                + vendor(0x05, FEATURE, 40, 0x28) + vendor(0x20, FEATURE, 63, 0x25))
    return collection(body)


# -- pad frame motion ------------------------------------------------------------------------------
def pad_motion(motion: WavingMotion, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """True gyro (rad/s) and specific force (m/s^2) in the pad frame at device times ``t`` (s).

    ``WavingMotion``'s sensor z (up when level) becomes the pad's y (out of the face), its y the
    pad's -z: a proper rotation, so the frame stays right-handed."""
    acc_g, gyro_dps, _ = motion.at_many(t)

    def remap(v: np.ndarray) -> np.ndarray:
        return np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)

    return np.radians(remap(gyro_dps)), remap(acc_g) * G


def _xyz(values: Iterable[int]) -> tuple[int, int, int]:
    x, y, z = values
    return x, y, z


class _SonyResponder(HidResponder):
    model: ClassVar[str] = ""
    codec_cls: ClassVar[type[DualShock4Codec | DualSenseCodec]]
    tick_hz: ClassVar[float] = 0.0
    wrap: ClassVar[int] = 0
    motion: WavingMotion
    options: ClassVar[dict[str, Option]] = {
        "handshake": Option(str, "ok", "how the pad answers the calibration read", choices=("ok", "silent", "wrong")),
        "calibration": Option(str, "factory", "factory calibration, or a degenerate one (zero spans)",
                              choices=("factory", "degenerate")),
    }

    def __init__(self, opts: Mapping[str, Any], address: str = "") -> None:
        super().__init__(opts, address)
        self.codec = self.codec_cls()
        self.handshake = str(self.opts.get("handshake", "ok"))
        self.calibration = self._make_calibration(str(self.opts.get("calibration", "factory")))
        self.scale: ImuScale = self.calibration.scale()
        self.motion = WavingMotion(int(self.opts.get("seed", 1)))
        self.full = self.bus == USB

    def on_open(self) -> None:
        # over Bluetooth the pad starts in reduced reports until the host reads the calibration
        self.full = self.bus == USB

    def _make_calibration(self, which: str) -> ImuCalibration:
        r = self.rng
        if which == "degenerate":
            return ImuCalibration((0, 0, 0), (0, 0, 0), (0, 0, 0), 540, 540, (0, 0, 0), (0, 0, 0))
        bias = _xyz(int(v) for v in r.integers(-15, 16, 3))
        plus = _xyz(int(v) for v in r.integers(8600, 9250, 3))
        minus = _xyz(-p + int(v) for p, v in zip(plus, r.integers(-40, 41, 3), strict=True))
        accp = _xyz(int(v) for v in r.integers(8050, 8450, 3))
        accm = _xyz(-a + int(v) for a, v in zip(accp, r.integers(-100, 101, 3), strict=True))
        return ImuCalibration(bias, plus, minus, 540, 540, accp, accm)

    def truth(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """True gyro (rad/s) and acceleration (m/s^2) in the pad frame at device times ``t``."""
        return pad_motion(self.motion, np.asarray(t, np.float64))

    # -- host side -------------------------------------------------------------------------------------
    def get_feature(self, report_id: int) -> bytes | None:
        rid, _ = calibration_report(self.model, self.bus)
        if report_id != rid:
            return None
        if self.handshake == "silent" and self.bus == USB:
            return None
        rep = encode_calibration(self.calibration, self.model, self.bus)
        if self.handshake == "wrong":
            if self.bus == USB:
                return rep[:20]
            bad = bytearray(rep)
            bad[-1] ^= 0x5A
            return bytes(bad)
        if self.bus == BLUETOOTH and self.handshake == "ok":
            self.full = True
        return rep

    # -- streaming -------------------------------------------------------------------------------------
    def stream(self) -> Iterator[tuple[float, bytes]]:
        bt = self.bus == BLUETOOTH
        status = self._status()
        k = 0
        while True:
            t = (k + np.arange(BLOCK)) / RATE_HZ
            gyro, acc = self.truth(t)
            graw, araw = self.scale.to_raw(gyro, acc)
            lx = np.clip(np.rint(128 + 100 * np.sin(2 * math.pi * 0.3 * t)), 0, 255).astype(int)
            ry = np.clip(np.rint(128 + 90 * np.cos(2 * math.pi * 0.2 * t)), 0, 255).astype(int)
            l2 = np.clip(np.rint(127.5 + 127.5 * np.sin(2 * math.pi * 0.5 * t)), 0, 255).astype(int)
            for i in range(BLOCK):
                n = k + i
                ti = float(t[i])
                phase = n % 250
                touching = phase < 100
                touch = (TouchPoint(touching, (n // 250) & 0x7F, int(200 + 10 * phase), int(300 + 2 * phase)),
                         TouchPoint(False, 0, 0, 0))
                f = PadReport(
                    USB if not bt else BLUETOOTH,
                    (int(lx[i]), 128, 128, int(ry[i])), (int(l2[i]), 0),
                    (1 << 1) if (n // 125) % 2 else 0, (n // 500) % 9,
                    (int(graw[i, 0]), int(graw[i, 1]), int(graw[i, 2])),
                    (int(araw[i, 0]), int(araw[i, 1]), int(araw[i, 2])),
                    round(ti * self.tick_hz) % self.wrap, status, touch, n & 0xFF if self.model == "dualsense"
                    else n & 0x3F, 0)
                if bt and not self.full:
                    yield ti, self.codec.encode_reduced(f)
                else:
                    yield ti, self.codec.encode(f)
            k += BLOCK

    def _status(self) -> int:
        raise NotImplementedError


class DualShock4Responder(_SonyResponder):
    kind = "ds4"
    vid = 0x054C
    pid = 0x09CC
    product = "Wireless Controller (simulated DualShock 4)"
    model = "ds4"
    codec_cls = DualShock4Codec
    tick_hz = DS4_TICK_HZ
    wrap = DS4_TICK_WRAP
    options: ClassVar[dict[str, Option]] = {
        **_SonyResponder.options,
        "model": Option(str, "zct2", "CUH-ZCT1 (054c:05c4) or CUH-ZCT2 (054c:09cc)", choices=("zct1", "zct2")),
    }

    def __init__(self, opts: Mapping[str, Any], address: str = "") -> None:
        super().__init__(opts, address)
        if self.opts.get("model") == "zct1":
            self.pid = 0x05C4

    def report_descriptor(self) -> bytes:
        return ds4_descriptor(self.bus)

    def _status(self) -> int:
        return 0x19 if self.bus == USB else 0x08  # USB: cable, 95 %; Bluetooth: 85 %


class DualSenseResponder(_SonyResponder):
    kind = "dualsense"
    vid = 0x054C
    pid = 0x0CE6
    product = "DualSense Wireless Controller (simulated)"
    model = "dualsense"
    codec_cls = DualSenseCodec
    tick_hz = DS_TICK_HZ
    wrap = DS_TICK_WRAP

    def report_descriptor(self) -> bytes:
        return dualsense_descriptor(self.bus)

    def _status(self) -> int:
        return 0x18 if self.bus == USB else 0x07  # USB: charging, 85 %; Bluetooth: 75 %


__all__ = ["DualSenseResponder", "DualShock4Responder", "ds4_descriptor", "dualsense_descriptor", "pad_motion"]
