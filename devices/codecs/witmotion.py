"""WitMotion WT901-family serial protocol (JY901, WT901C, HWT901B, WT61 and kin).

Each packet is 11 bytes: ``0x55``, a type byte, 8 data bytes (four little-endian int16 words, or
for the time packet YY MM DD hh mm ss and a uint16 millisecond), and a checksum equal to the low
byte of the sum of the first ten bytes. Types used here (datasheet scalings in
``devices.witmotion``)::

    0x50 time      0x51 acceleration (+ temperature)   0x52 angular rate
    0x53 angle     0x54 magnetometer                   0x59 quaternion

Other types in 0x50-0x5F are valid frames the device may carry; they are returned as frames too.
"""

from __future__ import annotations

import struct
from typing import NamedTuple

import numpy as np

from devices.codecs.base import Codec

HEADER = 0x55
TIME, ACC, GYRO, ANGLE, MAG, QUAT = 0x50, 0x51, 0x52, 0x53, 0x54, 0x59
KNOWN_TYPES = frozenset(range(0x50, 0x60))
PACKET_LEN = 11

_words = struct.Struct("<4h")
_time = struct.Struct("<6BH")


class WitPacket(NamedTuple):
    """One WitMotion packet: its type byte and its 8 data bytes."""

    type: int
    data: bytes

    def words(self) -> tuple[int, int, int, int]:
        return _words.unpack(self.data)

    def time_fields(self) -> tuple[int, int, int, int, int, int, int]:
        """(YY, MM, DD, hh, mm, ss, ms) of a time packet."""
        return _time.unpack(self.data)

    @classmethod
    def from_words(cls, type_: int, w: tuple[int, int, int, int]) -> WitPacket:
        return cls(type_, _words.pack(*w))

    @classmethod
    def from_time(cls, yy: int, mo: int, dd: int, hh: int, mi: int, ss: int, ms: int) -> WitPacket:
        return cls(TIME, _time.pack(yy, mo, dd, hh, mi, ss, ms))


class WitMotionCodec(Codec):
    """Parser and encoder of WitMotion 0x55-framed packets."""

    name = "witmotion"

    def feed(self, data: bytes) -> list[WitPacket]:
        buf = self._buf
        buf += data
        self.stats.bytes_in += len(data)
        out: list[WitPacket] = []
        i = 0
        n = len(buf)
        consumed_base = self.stats.bytes_in - n
        while n - i >= PACKET_LEN:
            if buf[i] != HEADER:
                j = buf.find(HEADER, i + 1)
                skip = (j if j >= 0 else n) - i
                self._bad("framing", f"{skip} byte(s) outside any packet", consumed_base + i, bytes(buf[i:i + skip]))
                self.stats.skipped_bytes += skip
                i += skip
                continue
            t = buf[i + 1]
            if t not in KNOWN_TYPES:
                self._bad("framing", f"unknown packet type 0x{t:02x}", consumed_base + i, bytes(buf[i:i + 2]))
                self.stats.skipped_bytes += 1
                i += 1
                continue
            if (sum(buf[i:i + 10]) & 0xFF) != buf[i + 10]:
                self._bad("checksum", f"checksum mismatch in packet type 0x{t:02x}", consumed_base + i,
                          bytes(buf[i:i + PACKET_LEN]))
                self.stats.skipped_bytes += 1
                i += 1
                continue
            out.append(WitPacket(t, bytes(buf[i + 2:i + 10])))
            i += PACKET_LEN
        if i:
            del buf[:i]
        # A tail with no header byte can never start a packet; drop it now (counted) rather than keep it.
        if buf and HEADER not in buf:
            self._bad("framing", f"{len(buf)} byte(s) outside any packet", self.stats.bytes_in - len(buf), bytes(buf))
            self.stats.skipped_bytes += len(buf)
            buf.clear()
        self.stats.frames += len(out)
        return out

    @staticmethod
    def encode_many(types: np.ndarray, payloads: np.ndarray) -> np.ndarray:
        """Many packets at once: ``types`` (n,) and ``payloads`` (n, 8) uint8 -> (n, 11) uint8 wire bytes
        (the same bytes ``encode`` gives packet by packet)."""
        n = types.shape[0]
        out = np.empty((n, PACKET_LEN), np.uint8)
        out[:, 0] = HEADER
        out[:, 1] = types
        out[:, 2:10] = payloads
        out[:, 10] = (out[:, :10].sum(axis=1, dtype=np.uint32) & 0xFF).astype(np.uint8)
        return out

    def encode(self, frame: WitPacket) -> bytes:
        if len(frame.data) != 8 or frame.type not in KNOWN_TYPES:
            raise ValueError(f"not a WitMotion packet: {frame!r}")
        body = bytes((HEADER, frame.type)) + frame.data
        return body + bytes((sum(body) & 0xFF,))
