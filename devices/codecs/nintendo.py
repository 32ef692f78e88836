"""Nintendo Switch Pro Controller and Joy-Con HID reports (sans-IO), after the public
reverse-engineered protocol notes (dekuNukem, *Nintendo_Switch_Reverse_Engineering*:
``bluetooth_hid_notes.md``, ``bluetooth_hid_subcommands_notes.md``, ``spi_flash_notes.md``,
``imu_sensor_notes.md``, ``USB-HID-Notes.md``).

Every HID input report is one chunk (report ID first), so ``feed`` decodes one report per call.

Input reports (byte offsets include the report ID):

* ``0x30`` full mode, 49 bytes (64 over USB, zero padded): 0 ID, 1 timer (8-bit, wraps), 2 battery
  (high nibble) / connection (low nibble), 3-5 buttons (right, shared, left byte), 6-8 left stick,
  9-11 right stick (two 12-bit values packed little-endian in 3 bytes), 12 vibrator report, 13-48
  three IMU samples, oldest first, each ``accel x, y, z, gyro x, y, z`` as ``<i2``.
* ``0x21`` subcommand reply: bytes 0-12 as above, 13 ACK (bit 7 set = ACK; the low bits give the
  reply data type, 0x00 = NACK), 14 echo of the subcommand ID, 15-48 reply data.
* ``0x81`` USB command reply (``0x81 <command> ...``), to the host's ``0x80 <command>`` output.
* ``0x3F`` simple HID mode (12 bytes): the default mode before the host selects ``0x30``; decoded
  as ``SimpleReport`` and otherwise ignored.

Output report ``0x01``: 0 ID, 1 global packet counter (low 4 bits, incremented per packet), 2-9
rumble data (left then right, 4 bytes each), 10 subcommand ID, 11.. arguments; 49 bytes.

IMU conversion (``ImuCalibration``), the formulas of ``imu_sensor_notes.md`` (also what the Linux
hid-nintendo driver computes), implemented exactly as::

    accel [m/s^2] = raw * 4 * 9.80665 / (acc_sens - acc_origin)        (raw is not bias-corrected)
    gyro  [rad/s] = (raw - gyro_origin) * 936 / (gyro_sens - gyro_origin) * pi / 180

with the per-axis factory (SPI 0x6020) or user (0x8028 behind magic 0xB2 0xA1 at 0x8026) values;
nominal ones are origin 0, acc_sens 16384 (so +-8 g full scale) and gyro_sens 13371 (so 0.07 deg/s
per count, +-2000 deg/s).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

from devices.codecs.base import Codec

G = 9.80665

# report IDs
OUT_RUMBLE_SUBCMD = 0x01
OUT_USB_CMD = 0x80
IN_SUBCMD_REPLY = 0x21
IN_FULL = 0x30
IN_SIMPLE = 0x3F
IN_USB_REPLY = 0x81

REPORT_LEN = 49        # 0x21, 0x30 and output 0x01 over Bluetooth (ID included)
USB_REPORT_LEN = 64    # everything over USB is padded to the 64-byte packet
SIMPLE_LEN = 12

# USB commands (0x80 xx)
USB_STATUS = 0x01
USB_HANDSHAKE = 0x02
USB_BAUD_3M = 0x03
USB_NO_TIMEOUT = 0x04  # "USB HID only": stream over USB from now on

# subcommands
SC_SET_MODE = 0x03
SC_DEVICE_INFO = 0x02
SC_SPI_READ = 0x10
SC_ENABLE_IMU = 0x40
SC_ENABLE_RUMBLE = 0x48

# SPI flash addresses
SPI_FACTORY_IMU = 0x6020      # 24 bytes
SPI_FACTORY_STICKS = 0x603D   # 18 bytes: left stick (9), right stick (9)
SPI_IMU_HORIZONTAL = 0x6080   # 6 bytes: 6-axis horizontal offsets (Pro Controller)
SPI_STICK_PARAMS = 0x6086     # 18 bytes: stick device parameters 1 (deadzone, range ratio)
SPI_USER_IMU = 0x8026         # 2 bytes magic + 24 bytes
USER_MAGIC = b"\xb2\xa1"
SPI_MAX_READ = 0x1D

#: 8 bytes of neutral rumble (left, right), as the official drivers send with every subcommand
NEUTRAL_RUMBLE = bytes((0x00, 0x01, 0x40, 0x40, 0x00, 0x01, 0x40, 0x40))

TYPE_LEFT, TYPE_RIGHT, TYPE_PRO = 1, 2, 3
TYPE_NAMES = {TYPE_LEFT: "Joy-Con (L)", TYPE_RIGHT: "Joy-Con (R)", TYPE_PRO: "Pro Controller"}

#: button bit -> name, over the 24 bits of bytes 3 (bits 0-7), 4 (8-15), 5 (16-23)
BUTTONS: tuple[tuple[int, str], ...] = (
    (0, "y"), (1, "x"), (2, "b"), (3, "a"), (4, "sr_r"), (5, "sl_r"), (6, "r"), (7, "zr"),
    (8, "minus"), (9, "plus"), (10, "rstick"), (11, "lstick"), (12, "home"), (13, "capture"),
    (16, "down"), (17, "up"), (18, "right"), (19, "left"), (20, "sr_l"), (21, "sl_l"), (22, "l"), (23, "zl"),
)

_IMU = struct.Struct("<18h")


# -- 12-bit packing -------------------------------------------------------------------------------
def unpack12(b: bytes) -> tuple[int, int]:
    """Two 12-bit values from 3 bytes (sticks and stick calibration)."""
    return b[0] | ((b[1] & 0x0F) << 8), (b[1] >> 4) | (b[2] << 4)


def pack12(a: int, b: int) -> bytes:
    if not (0 <= a <= 0xFFF and 0 <= b <= 0xFFF):
        raise ValueError(f"12-bit values out of range: {a}, {b}")
    return bytes((a & 0xFF, ((a >> 8) & 0x0F) | ((b & 0x0F) << 4), b >> 4))


# -- frames ---------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class PadState:
    """Bytes 1-12 common to 0x21 and 0x30 reports."""

    timer: int = 0
    battery: int = 8          # 0 empty, 2 critical, 4 low, 6 medium, 8 full (+1 charging)
    connection: int = 0       # low nibble of byte 2: 0x0 Pro/grip, 0x6 Joy-Con (BT); bit 0 = USB powered
    buttons: int = 0          # 24 bits, see BUTTONS
    lstick: tuple[int, int] = (2048, 2048)
    rstick: tuple[int, int] = (2048, 2048)
    vibrator: int = 0

    def to_bytes(self) -> bytes:
        return (bytes((self.timer & 0xFF, ((self.battery & 0xF) << 4) | (self.connection & 0xF)))
                + (self.buttons & 0xFFFFFF).to_bytes(3, "little")
                + pack12(*self.lstick) + pack12(*self.rstick) + bytes((self.vibrator & 0xFF,)))

    @classmethod
    def from_bytes(cls, b: bytes) -> PadState:
        """From the 12 bytes after the report ID."""
        return cls(b[0], b[1] >> 4, b[1] & 0xF, int.from_bytes(b[2:5], "little"), unpack12(b[5:8]),
                   unpack12(b[8:11]), b[11])


@dataclass(frozen=True, slots=True)
class FullReport:
    """Input report 0x30: pad state and three IMU samples (oldest first) of raw
    ``(ax, ay, az, gx, gy, gz)``."""

    state: PadState
    imu: tuple[tuple[int, int, int, int, int, int], ...]
    usb: bool = False  # padded to 64 bytes


@dataclass(frozen=True, slots=True)
class SubcommandReply:
    """Input report 0x21."""

    state: PadState
    ack: int
    subcommand: int
    data: bytes = b""
    usb: bool = False

    @property
    def acked(self) -> bool:
        return bool(self.ack & 0x80)


@dataclass(frozen=True, slots=True)
class UsbReply:
    """Input report 0x81: the answer to a USB command 0x80 ``command``."""

    command: int
    data: bytes = b""


@dataclass(frozen=True, slots=True)
class SimpleReport:
    """Input report 0x3F (simple HID mode); raw bytes after the ID."""

    data: bytes


Frame = FullReport | SubcommandReply | UsbReply | SimpleReport


# -- calibration ----------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class ImuCalibration:
    """The 24-byte IMU calibration block (factory 0x6020, user 0x8028), per axis x, y, z."""

    acc_origin: tuple[int, int, int] = (0, 0, 0)
    acc_sens: tuple[int, int, int] = (16384, 16384, 16384)
    gyro_origin: tuple[int, int, int] = (0, 0, 0)
    gyro_sens: tuple[int, int, int] = (13371, 13371, 13371)

    @classmethod
    def from_bytes(cls, b: bytes) -> ImuCalibration:
        if len(b) < 24:
            raise ValueError(f"IMU calibration needs 24 bytes, got {len(b)}")
        v = struct.unpack("<12h", bytes(b[:24]))
        return cls(v[0:3], v[3:6], v[6:9], v[9:12])

    def to_bytes(self) -> bytes:
        return struct.pack("<12h", *self.acc_origin, *self.acc_sens, *self.gyro_origin, *self.gyro_sens)

    def valid(self) -> bool:
        """Usable: every divisor positive (a blank block decodes as -1 everywhere and is not)."""
        return all(s - o > 0 for s, o in zip(self.acc_sens, self.acc_origin, strict=True)) and \
            all(s - o > 0 for s, o in zip(self.gyro_sens, self.gyro_origin, strict=True))

    def acc_scale(self) -> tuple[float, float, float]:
        """m/s^2 per count, per axis: 4 g / (acc_sens - acc_origin)."""
        x, y, z = (4.0 * G / (s - o) for s, o in zip(self.acc_sens, self.acc_origin, strict=True))
        return x, y, z

    def gyro_scale(self) -> tuple[float, float, float]:
        """rad/s per count, per axis: 936 deg/s / (gyro_sens - gyro_origin)."""
        x, y, z = (math.radians(936.0 / (s - o)) for s, o in zip(self.gyro_sens, self.gyro_origin, strict=True))
        return x, y, z

    def to_si(self, raw: tuple[int, ...]) -> tuple[float, float, float, float, float, float]:
        """Raw ``(ax, ay, az, gx, gy, gz)`` counts to ``(m/s^2 x3, rad/s x3)``."""
        a, g = self.acc_scale(), self.gyro_scale()
        return (raw[0] * a[0], raw[1] * a[1], raw[2] * a[2],
                (raw[3] - self.gyro_origin[0]) * g[0], (raw[4] - self.gyro_origin[1]) * g[1],
                (raw[5] - self.gyro_origin[2]) * g[2])

    def from_si(self, acc_ms2: tuple[float, float, float], gyro_rads: tuple[float, float, float]
                ) -> tuple[int, int, int, int, int, int]:
        """The inverse of ``to_si`` (for encoders), rounded and clipped to int16."""
        a, g = self.acc_scale(), self.gyro_scale()

        def q(v: float) -> int:
            return max(-32768, min(32767, round(v)))
        return (q(acc_ms2[0] / a[0]), q(acc_ms2[1] / a[1]), q(acc_ms2[2] / a[2]),
                q(gyro_rads[0] / g[0] + self.gyro_origin[0]), q(gyro_rads[1] / g[1] + self.gyro_origin[1]),
                q(gyro_rads[2] / g[2] + self.gyro_origin[2]))


@dataclass(frozen=True, slots=True)
class StickCalibration:
    """One stick's factory calibration: centre and the reach above / below it, per axis (12-bit)."""

    center: tuple[int, int] = (2048, 2048)
    above: tuple[int, int] = (1400, 1400)
    below: tuple[int, int] = (1400, 1400)

    @classmethod
    def from_bytes(cls, b: bytes, left: bool) -> StickCalibration:
        """From its 9 bytes: the left stick stores above, centre, below; the right one centre,
        below, above (``spi_flash_notes.md``)."""
        v = unpack12(b[0:3]) + unpack12(b[3:6]) + unpack12(b[6:9])
        if left:
            return cls((v[2], v[3]), (v[0], v[1]), (v[4], v[5]))
        return cls((v[0], v[1]), (v[4], v[5]), (v[2], v[3]))

    def to_bytes(self, left: bool) -> bytes:
        order = (self.above, self.center, self.below) if left else (self.center, self.below, self.above)
        return b"".join(pack12(*p) for p in order)

    def valid(self) -> bool:
        return all(0 < v < 0xFFF for v in (*self.center, *self.above, *self.below))

    def normalise(self, xy: tuple[int, int]) -> tuple[float, float]:
        """Raw 12-bit position to -1..1 per axis (up and right positive), clipped."""
        out = []
        for i in range(2):
            d = xy[i] - self.center[i]
            r = d / self.above[i] if d >= 0 else d / self.below[i]
            out.append(max(-1.0, min(1.0, r)))
        return out[0], out[1]

    def raw(self, norm: tuple[float, float]) -> tuple[int, int]:
        """The inverse of ``normalise`` (for encoders)."""
        out = []
        for i in range(2):
            n = max(-1.0, min(1.0, norm[i]))
            v = self.center[i] + n * (self.above[i] if n >= 0 else self.below[i])
            out.append(max(0, min(0xFFF, round(v))))
        return out[0], out[1]


def blank(b: bytes) -> bool:
    """An SPI block never written (all 0xFF)."""
    return len(b) > 0 and all(x == 0xFF for x in b)


# -- outputs --------------------------------------------------------------------------------------
def subcommand_report(counter: int, subcommand: int, args: bytes = b"", rumble: bytes = NEUTRAL_RUMBLE) -> bytes:
    """Output report 0x01 (49 bytes): counter (low 4 bits), rumble, subcommand, arguments."""
    body = bytes((OUT_RUMBLE_SUBCMD, counter & 0x0F)) + bytes(rumble[:8]).ljust(8, b"\0") + bytes((subcommand,)) + args
    if len(body) > REPORT_LEN:
        raise ValueError(f"subcommand 0x{subcommand:02x}: {len(args)} bytes of arguments do not fit")
    return body.ljust(REPORT_LEN, b"\0")


def parse_subcommand(data: bytes) -> tuple[int, int, bytes] | None:
    """``(counter, subcommand, args)`` of an output report 0x01, or None if it is not one."""
    if len(data) < 11 or data[0] != OUT_RUMBLE_SUBCMD:
        return None
    return data[1] & 0x0F, data[10], bytes(data[11:])


def usb_command(command: int) -> bytes:
    """Output report 0x80 ``command``, padded to the USB packet."""
    return bytes((OUT_USB_CMD, command)).ljust(USB_REPORT_LEN, b"\0")


def spi_read_args(address: int, length: int) -> bytes:
    if not 0 < length <= SPI_MAX_READ:
        raise ValueError(f"SPI read of {length} bytes (1..{SPI_MAX_READ})")
    return struct.pack("<IB", address, length)


def spi_reply_data(address: int, payload: bytes) -> bytes:
    """The data of a 0x10 reply: address (u32 LE), length, the bytes read."""
    return struct.pack("<IB", address, len(payload)) + bytes(payload)


def parse_spi_reply(data: bytes) -> tuple[int, int, bytes]:
    """``(address, length, payload)`` of a 0x10 reply's data."""
    if len(data) < 5:
        raise ValueError("SPI reply shorter than its 5-byte header")
    addr, n = struct.unpack_from("<IB", data)
    return addr, n, bytes(data[5:5 + n])


@dataclass(frozen=True, slots=True)
class DeviceInfo:
    """Reply data of subcommand 0x02."""

    firmware: tuple[int, int]
    type: int
    mac: bytes
    colors_in_spi: bool = True

    def to_bytes(self) -> bytes:
        return bytes((self.firmware[0], self.firmware[1], self.type, 0x02)) + bytes(self.mac[:6]) + \
            bytes((0x01, 0x01 if self.colors_in_spi else 0x00))

    @classmethod
    def from_bytes(cls, b: bytes) -> DeviceInfo:
        if len(b) < 12:
            raise ValueError(f"device info needs 12 bytes, got {len(b)}")
        return cls((b[0], b[1]), b[2], bytes(b[4:10]), b[11] == 0x01)

    @property
    def mac_str(self) -> str:
        return ":".join(f"{x:02X}" for x in self.mac)


# -- the codec ------------------------------------------------------------------------------------
@dataclass
class _Counts:
    full: int = 0
    replies: int = 0
    usb: int = 0
    simple: int = 0
    by_id: dict[int, int] = field(default_factory=dict)


class SwitchCodec(Codec):
    """Decodes one input report per ``feed``; ``encode`` builds input reports (for simulators).

    A report that is too short or has an unknown report ID is a framing error (counted, skipped;
    raised only in strict mode). Extra bytes (USB padding) are ignored.
    """

    name = "switch"

    def __init__(self, strict: bool = False) -> None:
        super().__init__(strict)
        self.counts = _Counts()

    def feed(self, data: bytes) -> list[Frame]:
        data = bytes(data)
        self.stats.bytes_in += len(data)
        if not data:  # no report id: nothing a controller sends
            self._bad("framing", "an empty report", 0, data)
            return []
        rid = data[0]
        try:
            frame = self._decode(rid, data)
        except (ValueError, IndexError, struct.error) as exc:
            self.stats.skipped_bytes += len(data)
            self._bad("framing", f"report 0x{rid:02x} of {len(data)} bytes: {exc}", 0, data)
            return []
        self.stats.frames += 1
        return [frame]

    def _decode(self, rid: int, data: bytes) -> Frame:
        n = len(data)
        if rid in (IN_FULL, IN_SUBCMD_REPLY):
            need = REPORT_LEN if rid == IN_FULL else 15
            if n < need:
                raise ValueError(f"too short (a 0x{rid:02x} report has {REPORT_LEN} bytes)")
            state = PadState.from_bytes(data[1:13])
            usb = n >= USB_REPORT_LEN
            if rid == IN_FULL:
                v = _IMU.unpack_from(data, 13)
                self.counts.full += 1
                return FullReport(state, (v[0:6], v[6:12], v[12:18]), usb)
            self.counts.replies += 1
            return SubcommandReply(state, data[13], data[14], bytes(data[15:REPORT_LEN]), usb)
        if rid == IN_USB_REPLY:
            if n < 2:
                raise ValueError("too short")
            self.counts.usb += 1
            return UsbReply(data[1], bytes(data[2:]))
        if rid == IN_SIMPLE:
            if n < SIMPLE_LEN:
                raise ValueError(f"too short (a 0x3f report has {SIMPLE_LEN} bytes)")
            self.counts.simple += 1
            return SimpleReport(bytes(data[1:SIMPLE_LEN]))
        raise ValueError("unknown report ID")

    def encode(self, frame: Frame) -> bytes:
        if isinstance(frame, FullReport):
            if len(frame.imu) != 3:
                raise ValueError("a 0x30 report carries exactly 3 IMU samples")
            out = bytes((IN_FULL,)) + frame.state.to_bytes() + _IMU.pack(*(v for s in frame.imu for v in s))
            return out.ljust(USB_REPORT_LEN if frame.usb else REPORT_LEN, b"\0")
        if isinstance(frame, SubcommandReply):
            if len(frame.data) > REPORT_LEN - 15:
                raise ValueError("reply data too long")
            out = bytes((IN_SUBCMD_REPLY,)) + frame.state.to_bytes() + bytes((frame.ack, frame.subcommand)) + frame.data
            return out.ljust(USB_REPORT_LEN if frame.usb else REPORT_LEN, b"\0")
        if isinstance(frame, UsbReply):
            return (bytes((IN_USB_REPLY, frame.command)) + frame.data).ljust(USB_REPORT_LEN, b"\0")
        if isinstance(frame, SimpleReport):
            return (bytes((IN_SIMPLE,)) + frame.data).ljust(SIMPLE_LEN, b"\0")
        raise TypeError(f"not a Switch report: {frame!r}")


def ack_for(subcommand: int) -> int:
    """The ACK byte a controller sends: 0x80, or 0x80 | reply data type for subcommands with data."""
    return {SC_DEVICE_INFO: 0x82, SC_SPI_READ: 0x90}.get(subcommand, 0x80)
