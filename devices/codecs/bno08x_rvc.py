"""BNO08x (BNO080/BNO085/BNO086) UART-RVC frames: parsing, resynchronisation and encoding.

In UART-RVC mode the sensor streams one 19-byte frame every 10 ms at 115200 baud::

    0xAA 0xAA  index  yaw  pitch  roll  ax  ay  az  MI  MR  reserved  checksum
      header    u8    s16  s16    s16   s16 s16 s16 u8  u8    u8         u8

All s16 are little-endian; angles in 0.01 degree, accelerations in mg. ``index`` counts frames
(8 bits). The checksum is the low byte of the sum of bytes 2..17 (index to reserved). This module
owns the byte level only; what the numbers mean is ``devices.bno08x``.

Resynchronisation. ``0xAA`` is an ordinary byte inside payloads, so a ``0xAA 0xAA`` pair is only a
*candidate* header and a 1-byte checksum passes by chance once in 256 tries. A candidate whose
checksum fails is skipped one byte at a time. A candidate whose checksum passes is accepted at once
when it directly follows the previous frame and carries the next index (the normal streaming case:
no added latency). Otherwise, if another ``0xAA 0xAA`` pair lies inside it (a real frame may start
there), it is accepted only when the next frame's header follows it, or when no overlapping
candidate has a valid checksum; if one does, the first candidate was a false header and is
dropped, so the real frame behind it survives. Those decisions wait for the bytes they need, so the
frames found never depend on how the bytes were split into reads; ``flush`` decides with what is
there at the end of a take.
"""

from __future__ import annotations

import logging
import struct
from typing import NamedTuple

import numpy as np

from devices.codecs.base import Codec

log = logging.getLogger(__name__)  # codec errors are logged by Codec._bad (devices.codecs.base)

HEADER_BYTE = 0xAA
HEADER = b"\xaa\xaa"
FRAME_LEN = 19

_body = struct.Struct("<B6h3B")  # counter, yaw, pitch, roll, ax, ay, az, MI, MR, reserved (bytes 2..17)
_S16 = (-32768, 32767)


class RvcFrame(NamedTuple):
    """One UART-RVC frame, raw integers as on the wire.

    ``counter`` is the datasheet's *Index*, the 8-bit frame count (named so as not to shadow
    ``tuple.index``). ``yaw``, ``pitch``, ``roll`` are in 0.01 degree; ``ax``, ``ay``, ``az`` in
    mg; ``mi`` (motion intent), ``mr`` (motion request) and ``reserved`` are the three trailing
    bytes (all zero on BNO080 firmware).
    """

    counter: int
    yaw: int
    pitch: int
    roll: int
    ax: int
    ay: int
    az: int
    mi: int = 0
    mr: int = 0
    reserved: int = 0


class Bno08xRvcCodec(Codec):
    """Parser and encoder of BNO08x UART-RVC frames (see the module docstring)."""

    name = "bno08x_rvc"

    def __init__(self, strict: bool = False) -> None:
        super().__init__(strict)
        self._next_index: int | None = None  # index expected at buffer start when it directly follows a frame
        self._in_run = False  # inside a run of skipped bytes (counted once however it is split)

    # -- decoding ------------------------------------------------------------------------------
    def feed(self, data: bytes) -> list[RvcFrame]:
        """Parse more bytes; returns the frames completed by them, in order.

        Raises:
            ProtocolError: only in strict mode, at the first bad or skipped byte run.
        """
        self._buf += data
        self.stats.bytes_in += len(data)
        return self._parse(final=False)

    def flush(self) -> list[RvcFrame]:
        """Decide frames that still wait for lookahead bytes, as if the stream ended here (end of a
        take). Bytes that cannot form a frame stay buffered (``reset`` counts them as skipped).

        Raises:
            ProtocolError: only in strict mode.
        """
        return self._parse(final=True)

    def reset(self) -> int:
        self._next_index = None
        self._in_run = False
        return super().reset()

    @property
    def locked(self) -> bool:
        """Whether the next byte is expected to start a frame (the last one ended cleanly)."""
        return self._next_index is not None

    @property
    def next_index(self) -> int | None:
        """The index the next frame should carry, when locked."""
        return self._next_index

    def _skip(self, start: int, stop: int, base: int, why: str) -> None:
        """Drop buf[start:stop] (garbage between frames): one framing error per run of skipped bytes."""
        n = stop - start
        if not self._in_run:
            self._in_run = True
            self._bad("framing", f"{n} byte(s) outside any frame ({why})", base + start,
                      bytes(self._buf[start:stop]))
        self.stats.skipped_bytes += n

    def _parse(self, final: bool) -> list[RvcFrame]:
        buf = self._buf
        n = len(buf)
        base = self.stats.bytes_in - n
        out: list[RvcFrame] = []
        nxt = self._next_index
        unpack = _body.unpack_from
        i = 0
        while i < n:
            if buf[i] != HEADER_BYTE or (i + 1 < n and buf[i + 1] != HEADER_BYTE):
                j = buf.find(HEADER, i + 1)
                if j < 0:
                    j = n - 1 if buf[n - 1] == HEADER_BYTE else n
                self._skip(i, j, base, "no 0xAA 0xAA header")
                nxt = None
                i = j
                continue
            if n - i < FRAME_LEN:
                break  # a header, or its first byte, and not yet the whole frame
            if (sum(buf[i + 2:i + 18]) & 0xFF) != buf[i + 18]:
                self._in_run = False
                self._bad("checksum", "checksum mismatch", base + i, bytes(buf[i:i + FRAME_LEN]))
                self.stats.skipped_bytes += 1
                nxt = None
                i += 1
                continue
            idx = buf[i + 2]
            if nxt is None or idx != nxt:
                ok = self._resolve(buf, i, n, final)
                if ok is None:
                    break  # the decision needs bytes that have not arrived yet
                if not ok:
                    self._in_run = False
                    self._bad("framing", "false header: a valid frame overlaps this candidate", base + i,
                              bytes(buf[i:i + FRAME_LEN]))
                    self.stats.skipped_bytes += 1
                    nxt = None
                    i += 1
                    continue
            self._in_run = False
            out.append(RvcFrame._make(unpack(buf, i + 2)))
            i += FRAME_LEN
            nxt = (idx + 1) & 0xFF
        if i:
            del buf[:i]
        self._next_index = nxt
        self.stats.frames += len(out)
        return out

    @staticmethod
    def _resolve(buf: bytearray, i: int, n: int, final: bool) -> bool | None:
        """Whether the checksum-valid candidate at ``i`` (not following a frame) is a real frame;
        ``None`` when that needs bytes not yet in ``buf`` (never when ``final``)."""
        end = i + FRAME_LEN
        if n == end and buf[end - 1] == HEADER_BYTE and not final:
            return None  # a header may start at the checksum byte: need the byte after it
        overlaps: list[int] = []
        j = buf.find(HEADER, i + 1, min(n, end + 1))
        while j >= 0:
            overlaps.append(j)
            j = buf.find(HEADER, j + 1, min(n, end + 1))
        if not overlaps:
            return True
        if n >= end + 2:
            if buf[end] == HEADER_BYTE and buf[end + 1] == HEADER_BYTE:
                return True  # the next frame's header follows: confirmed
        elif not final:
            return None
        for j in overlaps:
            if n < j + FRAME_LEN:
                if final:
                    continue
                return None
            if (sum(buf[j + 2:j + 18]) & 0xFF) == buf[j + 18]:
                return False
        return True

    def feed_clean(self, data: bytes) -> tuple[np.ndarray, int] | None:
        """Vectorised ``feed`` for a clean run: the stream the codec is locked on continues with
        whole frames back to back (consecutive indices, valid checksums), possibly completing a
        partial frame buffered before and ending in the start of the next one.

        Returns:
            ``(frames, lead)``: the completed frames as an ``(n, 19)`` uint8 array, and how many of
            their bytes came from the buffer (so frame ``k`` ends at ``(k + 1) * 19 - 1 - lead`` in
            ``data``). The codec is left exactly as ``feed`` would leave it. ``None`` for anything
            else (nothing consumed).
        """
        nxt = self._next_index
        if nxt is None or not data:
            return None
        lead = len(self._buf)
        full = bytes(self._buf) + data if lead else data
        m = len(full) // FRAME_LEN
        cut = m * FRAME_LEN
        tail = full[cut:]
        # a partial frame left at the end must be one ``feed`` would keep waiting on
        if tail and (tail[0] != HEADER_BYTE or (len(tail) > 1 and tail[1] != HEADER_BYTE)):
            return None
        if m == 0:
            return None
        a = np.frombuffer(full, np.uint8, cut).reshape(m, FRAME_LEN)
        if not (np.all(a[:, 0] == HEADER_BYTE) and np.all(a[:, 1] == HEADER_BYTE)):
            return None
        if not np.array_equal((a[:, 2:18].sum(axis=1, dtype=np.uint32) & 0xFF).astype(np.uint8), a[:, 18]):
            return None
        want = ((nxt + np.arange(m, dtype=np.int64)) & 0xFF).astype(np.uint8)
        if not np.array_equal(a[:, 2], want):
            return None
        self.stats.bytes_in += len(data)
        self.stats.frames += m
        self._buf[:] = tail
        self._next_index = (int(a[-1, 2]) + 1) & 0xFF
        self._in_run = False
        return a, lead

    # -- encoding ------------------------------------------------------------------------------
    def encode(self, frame: RvcFrame) -> bytes:
        """The 19 wire bytes of ``frame``.

        Raises:
            ValueError: a field is out of its range (u8 or s16).
        """
        f = frame
        for name, v in zip(("yaw", "pitch", "roll", "ax", "ay", "az"), f[1:7], strict=True):
            if not _S16[0] <= v <= _S16[1]:
                raise ValueError(f"RVC frame field {name}={v} is outside the int16 range")
        for name, v in (("counter", f.counter), ("mi", f.mi), ("mr", f.mr), ("reserved", f.reserved)):
            if not 0 <= v <= 255:
                raise ValueError(f"RVC frame field {name}={v} is outside 0..255")
        body = _body.pack(*f)
        return HEADER + body + bytes((sum(body) & 0xFF,))

    @staticmethod
    def encode_many(index: np.ndarray, angles: np.ndarray, accel: np.ndarray,
                    tail: np.ndarray | None = None) -> np.ndarray:
        """Many frames at once (the same bytes ``encode`` gives frame by frame).

        Args:
            index: (n,) frame indices (taken modulo 256).
            angles: (n, 3) raw yaw, pitch, roll in 0.01 degree (wire order).
            accel: (n, 3) raw x, y, z acceleration in mg.
            tail: (n, 3) MI, MR, reserved bytes, or ``None`` for zeros.

        Returns:
            (n, 19) uint8 wire bytes.

        Raises:
            ValueError: shapes disagree or a value is outside int16.
        """
        idx = np.asarray(index, np.int64)
        n = idx.shape[0]
        words = np.empty((n, 6), np.int64)
        words[:, 0:3] = angles
        words[:, 3:6] = accel
        if words.size and (words.min() < _S16[0] or words.max() > _S16[1]):
            raise ValueError("RVC angles and accelerations must fit int16")
        out = np.empty((n, FRAME_LEN), np.uint8)
        out[:, 0] = HEADER_BYTE
        out[:, 1] = HEADER_BYTE
        out[:, 2] = (idx & 0xFF).astype(np.uint8)
        out[:, 3:15] = words.astype("<i2").view(np.uint8).reshape(n, 12)
        out[:, 15:18] = 0 if tail is None else np.asarray(tail, np.uint8)
        out[:, 18] = (out[:, 2:18].sum(axis=1, dtype=np.uint32) & 0xFF).astype(np.uint8)
        return out


__all__ = ["FRAME_LEN", "HEADER", "HEADER_BYTE", "Bno08xRvcCodec", "RvcFrame"]
