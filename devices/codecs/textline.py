"""Text lines printed by microcontroller sketches: CSV or key:value, one reading per line.

This module owns the syntax only: splitting bytes into lines, fields and numbers, and counting what
does not parse. Which field is which channel, units and time are ``devices.textline``.

Lines end in ``\\n``; a ``\\r`` before it is dropped, surrounding blanks are ignored. Two forms:

* CSV: ``1234,0.01,-0.02,9.81`` - fields split on commas, or on blanks when a line has no comma.
  Columns are positional; a line must have exactly as many fields as there are columns (one
  trailing comma is tolerated). Only the columns that are mapped are parsed.
* key:value: ``t:1234 ax:0.01, ay=-0.02`` - pairs ``KEY:VALUE`` or ``KEY=VALUE``, separated by
  blanks, commas or tabs. Keys that are not mapped are ignored; mapped keys that are missing give
  ``NaN`` (and a clear bit in ``TextFrame.present``).

With ``fmt="auto"`` a line containing ``:`` or ``=`` is key:value, any other line CSV.

Numbers are what Python's ``float`` accepts, but infinite: ``inf`` and ``1e999`` (which overflows)
are refused as framing errors, since no sensor reads them; ``nan`` stays "no value" (as an absent
key:value field is, and as ``encode`` writes one). Bad lines are skipped and counted, never raised (except
in strict mode): a line longer than ``max_line`` bytes, non-UTF-8 bytes, a mapped field that is not
a number, a wrong number of CSV fields, a repeated or missing required key, or a device-time value
out of range are *framing errors*; a line with no number in it at all (a CSV header, a boot banner
such as ``MPU6050 ready``, a blank line) or with none of the mapped keys is *skipped*
(``stats.skipped_lines``), since sketches print those on purpose.

``feed_clean`` is a vectorised decoder for runs of plain CSV lines (digits, sign, decimal point;
no exponent) that gives bit-identical values: a decimal of at most 15 significant digits is the
integer of its digits divided by a power of ten, both exact in float64, and one IEEE division is
correctly rounded, as ``float`` is.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from devices.codecs.base import Codec, CodecStats

if TYPE_CHECKING:
    from collections.abc import Sequence

log = logging.getLogger(__name__)

CSV, KV, AUTO = "csv", "kv", "auto"
FORMATS = (CSV, KV, AUTO)
MAX_LINE = 4096

_PAIR = re.compile(rb"([A-Za-z_][A-Za-z0-9_.\[\]-]*)[ \t]*[:=][ \t]*([^\s,;:=]*)")
_BLANKS_AT_DELIM = re.compile(rb"[ \t]*([,\n])[ \t]*")
_CLEAN_ALPHABET = b"0123456789.,+-\n"
_POW10_F = np.array([10.0 ** k for k in range(23)], np.float64)
_EXACT = 2 ** 53
_NOTICES = 5  # skipped lines logged at INFO before going quiet


@dataclass
class TextLineStats(CodecStats):
    """``CodecStats`` plus the lines skipped on purpose (headers, banners, unmapped lines)."""

    skipped_lines: int = 0


class TextFrame(NamedTuple):
    """One parsed line: a value per mapped field (in column order, ``NaN`` where absent) and a
    bitmask of the fields the line carried (all of them for CSV)."""

    values: tuple[float, ...]
    present: int


def _is_number(s: bytes) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def format_number(v: float) -> str:
    """A number as a sketch would print it, and as ``float`` reads back exactly: integers without a
    decimal point, others in the shortest form that round-trips."""
    if math.isfinite(v) and abs(v) < 1e16 and v == int(v):
        return "-0" if v == 0 and math.copysign(1.0, v) < 0 else str(int(v))
    return repr(float(v))


class TextLineCodec(Codec):
    """Parser and encoder of text lines (see the module docstring).

    Args:
        strict: raise ``ProtocolError`` at the first bad line instead of counting it.
        fmt: ``csv``, ``kv`` or ``auto``.
        columns: one entry per CSV column, in order: the key of that field in key:value lines, or
            ``None`` for a column that is not read.
        max_line: longest accepted line in bytes (without the line end); the buffer never holds more.
        time_field: index (among the mapped fields) of a device-time counter, which must be present
            and within ``[0, time_max)``.
        time_max: upper bound of the time counter.

    Raises:
        ValueError: bad arguments (the device layer validates user options before this).
    """

    name = "textline"

    def __init__(self, strict: bool = False, *, fmt: str = AUTO, columns: Sequence[str | None] = (),
                 max_line: int = MAX_LINE, time_field: int | None = None, time_max: float = math.inf) -> None:
        super().__init__(strict)
        if fmt not in FORMATS:
            raise ValueError(f"text-line format must be one of {', '.join(FORMATS)}, not {fmt!r}")
        if max_line < 1:
            raise ValueError("max_line must be positive")
        self.stats: TextLineStats = TextLineStats()
        self.fmt = fmt
        self.columns = tuple(columns)
        self.fields = tuple(c for c in self.columns if c is not None)
        if len(set(self.fields)) != len(self.fields):
            raise ValueError(f"text-line keys must be unique: {self.fields}")
        if time_field is not None and not 0 <= time_field < len(self.fields):
            raise ValueError(f"time_field {time_field} is not one of the {len(self.fields)} mapped fields")
        self.max_line = max_line
        self.time_field = time_field
        self.time_max = time_max
        self._ncols = len(self.columns)
        self._csv_idx = [k for k, c in enumerate(self.columns) if c is not None]
        self._kv = {c.encode("ascii"): i for i, c in enumerate(self.fields)}
        self._all = (1 << len(self.fields)) - 1
        self._tbit = 0 if time_field is None else 1 << time_field
        self._time_key = None if time_field is None else self.fields[time_field]
        self._discard = False  # dropping the rest of an over-long line, up to its newline
        self.last_format: str | None = None  # csv or kv: the form of the last line parsed
        self._fast = fmt != KV and bool(self.columns) and len(self._csv_idx) == self._ncols

    # -- decoding ------------------------------------------------------------------------------
    def feed(self, data: bytes) -> list[TextFrame]:
        """Parse more bytes; returns the frames of the lines they complete, in order.

        Raises:
            ProtocolError: only in strict mode, at the first bad line.
        """
        st = self.stats
        st.bytes_in += len(data)
        if self._discard:
            k = data.find(b"\n")
            if k < 0:
                st.skipped_bytes += len(data)
                return []
            st.skipped_bytes += k + 1
            self._discard = False
            data = data[k + 1:]
        buf = self._buf
        buf += data
        out: list[TextFrame] = []
        last = buf.rfind(b"\n")
        if last >= 0:
            off = st.bytes_in - len(buf)
            block = bytes(buf[:last + 1])
            del buf[:last + 1]
            lines = block.split(b"\n")
            lines.pop()
            line_fn = self._line
            if self._fast:
                # Fast path for the common line: every column mapped, comma-separated, all numbers
                # (so ASCII, no ':' or '='). It gives what ``_line`` gives; anything else goes there.
                nc, maxl, tf, tmax, full = self._ncols, self.max_line, self.time_field, self.time_max, self._all
                for line in lines:
                    if len(line) <= maxl:
                        fields = line.split(b",")
                        if len(fields) == nc:
                            try:
                                vals = tuple(map(float, fields))
                            except ValueError:
                                pass
                            else:
                                # all finite (NaN, infinities and sums that overflow go to ``_line``)
                                tot = sum(vals)
                                if tot - tot == 0.0 and (tf is None or 0.0 <= vals[tf] < tmax):
                                    out.append(TextFrame(vals, full))
                                    off += len(line) + 1
                                    self.last_format = CSV
                                    continue
                    line_fn(line, off, out)
                    off += len(line) + 1
            else:
                for line in lines:
                    line_fn(line, off, out)
                    off += len(line) + 1
        if len(buf) > self.max_line + 1:  # +1: room for a '\r' before the newline
            n = len(buf)
            self._bad("framing", f"line longer than {self.max_line} bytes without a newline; dropped up to the"
                      " next newline", st.bytes_in - n, bytes(buf[:64]))
            st.skipped_bytes += n
            buf.clear()
            self._discard = True
        st.frames += len(out)
        return out

    def reset(self) -> int:
        self._discard = False
        return super().reset()

    def _skip_line(self, line: bytes, why: str) -> None:
        st = self.stats
        st.skipped_lines += 1
        st.skipped_bytes += len(line) + 1
        if st.skipped_lines <= _NOTICES:
            log.info("%s: skipped %s: %r%s", self.name, why, line[:80],
                     "" if st.skipped_lines < _NOTICES else " (further skipped lines are logged at DEBUG)")
        else:
            log.debug("%s: skipped %s: %r", self.name, why, line[:80])

    def _reject(self, line: bytes, off: int, why: str) -> None:
        self._bad("framing", f"{why}; line skipped: {line[:80]!r}", off, line)
        self.stats.skipped_bytes += len(line) + 1

    def _line(self, raw: bytes, off: int, out: list[TextFrame]) -> None:
        line = raw[:-1] if raw[-1:] == b"\r" else raw
        if len(line) > self.max_line:
            self._reject(raw, off, f"line of {len(raw)} bytes is longer than {self.max_line}")
            return
        if not line.isascii():
            try:
                line.decode("utf-8")
            except UnicodeDecodeError:
                self._reject(raw, off, "line is not UTF-8 text")
                return
        s = line.strip()
        if not s:
            self._skip_line(raw, "blank line")
            return
        fmt = self.fmt
        if fmt == AUTO:
            fmt = KV if (b":" in s or b"=" in s) else CSV
        self.last_format = fmt
        vals: list[float] | tuple[float, ...]
        if fmt == CSV:
            fields = s.split(b",") if b"," in s else s.split()
            nc = self._ncols
            if len(fields) == nc + 1 and not fields[-1].strip():
                fields.pop()  # one trailing separator
            try:
                vals = [float(fields[k]) for k in self._csv_idx] if len(fields) == nc else []
            except ValueError:
                vals = []
            if len(vals) != len(self.fields) or len(fields) != nc:
                if not any(_is_number(f) for f in fields):
                    self._skip_line(raw, "line without numbers (header or message)")
                elif len(fields) != nc:
                    self._reject(raw, off, f"{len(fields)} fields where {nc} columns are configured")
                else:
                    bad = next(self.columns[k] or "?" for k in self._csv_idx if not _is_number(fields[k]))
                    self._reject(raw, off, f"field {bad!r} is not a number")
                return
            for k, v in enumerate(vals):
                if math.isinf(v):
                    self._reject(raw, off, f"field {self.fields[k]!r} is {v!r}, not a finite number")
                    return
            present = self._all
        else:
            vals = [math.nan] * len(self.fields)
            present = 0
            kv = self._kv
            for m in _PAIR.finditer(s):
                fi = kv.get(m.group(1))
                if fi is None:
                    continue
                try:
                    v = float(m.group(2))
                except ValueError:
                    self._reject(raw, off, f"value of {m.group(1).decode()!r} is not a number: {m.group(2)[:20]!r}")
                    return
                if math.isinf(v):
                    self._reject(raw, off, f"value of {m.group(1).decode()!r} is {v!r}, not a finite number")
                    return
                bit = 1 << fi
                if present & bit:
                    self._reject(raw, off, f"key {m.group(1).decode()!r} given twice")
                    return
                present |= bit
                vals[fi] = v
            if not present:
                self._skip_line(raw, "line without any configured key")
                return
            if self._tbit and not present & self._tbit:
                self._reject(raw, off, f"no time key {self._time_key!r}")
                return
        tf = self.time_field
        if tf is not None:
            t = vals[tf]
            if not 0.0 <= t < self.time_max:
                self._reject(raw, off, f"time {self.fields[tf]}={t!r} is outside [0, {self.time_max:g})")
                return
        out.append(TextFrame(tuple(vals), present))

    # -- vectorised decoding of clean CSV ---------------------------------------------------------
    def feed_clean(self, data: bytes) -> tuple[np.ndarray, np.ndarray] | None:
        """Vectorised ``feed`` for a run of plain CSV lines (fields of digits with an optional sign
        and decimal point, commas, blanks around commas, ``\\r\\n`` or ``\\n``). The run may
        complete a partial line buffered before and end in a partial line, which stays buffered.

        Returns:
            ``(values, line_end)``: float64 (n, mapped fields) exactly as ``feed`` would parse them,
            and the offset of each line's ``\\n`` in ``data``; the codec is left exactly as ``feed``
            would leave it. ``None`` (nothing consumed) for anything else: no complete line,
            key:value lines, exponents, a header, a bad line, an out-of-range time.
        """
        if self._discard or self.fmt == KV or not data or not self._ncols:
            return None
        lead = len(self._buf)
        full = bytes(self._buf) + data if lead else data
        k = full.rfind(b"\n") + 1
        if k == 0 or len(full) - k > self.max_line + 1:
            return None  # no line completed, or ``feed`` would drop an over-long partial line
        tail = full[k:]
        data = full[:k] if tail else full
        norm = data
        if b"\r" in norm:
            norm = norm.replace(b"\r\n", b"\n")
        if b" " in norm or b"\t" in norm:
            norm = _BLANKS_AT_DELIM.sub(rb"\1", norm).lstrip(b" \t")
        if norm.translate(None, _CLEAN_ALPHABET):
            return None
        res = _parse_plain_csv(norm, self._ncols)
        if res is None:
            return None
        vals, nl = res
        if norm is not data:  # blanks or CRs were removed: line ends and lengths from the original bytes
            nl = np.flatnonzero(np.frombuffer(data, np.uint8) == 10)
            if nl.shape[0] != vals.shape[0]:
                return None
        raw_len = np.diff(nl, prepend=-1) - 1
        if int(raw_len.max()) > self.max_line:
            a = np.frombuffer(data, np.uint8)
            nz = raw_len > 0
            cr = np.zeros(nl.shape[0], np.int64)
            cr[nz] = a[nl[nz] - 1] == 13
            if int((raw_len - cr).max()) > self.max_line:
                return None
        if len(self._csv_idx) != self._ncols:
            vals = vals[:, self._csv_idx]
        tf = self.time_field
        if tf is not None:
            t = vals[:, tf]
            if not bool(np.all((t >= 0.0) & (t < self.time_max))):
                return None
        st = self.stats
        st.bytes_in += len(full) - lead
        st.frames += vals.shape[0]
        self._buf[:] = tail
        if vals.shape[0]:
            self.last_format = CSV
        return vals, nl - lead

    # -- encoding ------------------------------------------------------------------------------
    def encode(self, frame: TextFrame) -> bytes:
        """The line of ``frame`` (with ``\\n``), in this codec's format (CSV for ``auto``). CSV
        writes ``0`` in unmapped columns and ``nan`` for absent fields; key:value writes only the
        fields present.

        Raises:
            ValueError: the frame has the wrong number of values.
        """
        if len(frame.values) != len(self.fields):
            raise ValueError(f"{len(frame.values)} values for {len(self.fields)} mapped fields")
        if self.fmt == KV:
            parts = [f"{k}:{format_number(v)}" for i, (k, v) in enumerate(zip(self.fields, frame.values, strict=True))
                     if frame.present >> i & 1]
            return (" ".join(parts) + "\n").encode("ascii")
        it = iter(frame.values)
        cols = []
        for _i, c in enumerate(self.columns):
            cols.append("0" if c is None else format_number(next(it)))
        return (",".join(cols) + "\n").encode("ascii")


_PARSE_BLOCK = 1 << 18  # bytes per parsing pass: keeps the temporaries in cache


def _parse_plain_csv(data: bytes, ncols: int) -> tuple[np.ndarray, np.ndarray] | None:
    """``_parse_csv_block`` over blocks of whole lines of about ``_PARSE_BLOCK`` bytes (the same
    result as one pass, about a third faster on a long replay); ``None`` if any block is."""
    n = len(data)
    if n <= _PARSE_BLOCK:
        return _parse_csv_block(data, ncols)
    vals: list[np.ndarray] = []
    ends: list[np.ndarray] = []
    off = 0
    while off < n:
        end = n if off + _PARSE_BLOCK >= n else data.rfind(b"\n", off, off + _PARSE_BLOCK) + 1
        if end <= off:  # one line longer than a block
            end = data.index(b"\n", off) + 1
        r = _parse_csv_block(data[off:end], ncols)
        if r is None:
            return None
        vals.append(r[0])
        ends.append(r[1] + off)
        off = end
    return np.concatenate(vals), np.concatenate(ends)


def _parse_csv_block(data: bytes, ncols: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Parse ``data`` (only digits, ``.+-,`` and ``\\n``; ends with ``\\n``) as lines of ``ncols``
    decimal fields. Returns (values (lines, ncols), offset of each ``\\n``), or ``None`` if a line
    has another field count, or a field is not ``[+-]digits[.digits]`` with 1 to 18 digits and a
    value of at most 2**53 units in its last place.

    Work per byte is kept to a few C passes (no per-byte cumulative sums): a field's digit count
    is its length less its sign and point, and its digits are the bytes left by ``translate``.
    """
    u = np.frombuffer(data, np.uint8)
    dpos = np.flatnonzero((u == 44) | (u == 10))
    ntok = dpos.shape[0]
    if ntok % ncols:
        return None
    is_nl = u[dpos] == 10
    if ncols == 1:
        if not bool(is_nl.all()):
            return None
    else:
        pattern = np.zeros(ncols, bool)
        pattern[-1] = True
        if not np.array_equal(is_nl.reshape(-1, ncols), np.broadcast_to(pattern, (ntok // ncols, ncols))):
            return None
    length = np.diff(dpos, prepend=-1) - 1  # bytes of each field
    nd = length.copy()
    sp = np.flatnonzero((u == 45) | (u == 43))
    if sp.size:
        stok = np.searchsorted(dpos, sp)
        start = np.where(stok > 0, dpos[np.maximum(stok - 1, 0)] + 1, 0)
        if not np.array_equal(sp, start):
            return None  # a sign that does not start its field (at most one sign per field follows)
        nd[stok] -= 1
    dots = np.flatnonzero(u == 46)
    dec = np.zeros(ntok, np.int64)
    if dots.size:
        dtok = np.searchsorted(dpos, dots)
        if dtok.size > 1 and not bool(np.all(dtok[1:] != dtok[:-1])):
            return None  # two decimal points in one field
        nd[dtok] -= 1
        dec[dtok] = dpos[dtok] - dots - 1
    if int(nd.min()) < 1 or int(nd.max()) > 18:
        return None
    digits = np.frombuffer(data.translate(None, b".,+-\n"), np.uint8) - np.uint8(48)
    nd32 = nd.astype(np.int32)
    ends = np.cumsum(nd32)
    starts = ends - nd32
    # each digit's power of ten counts down by one inside its field, from nd - 1 to 0
    step = np.full(digits.shape[0], -1, np.int32)
    step[starts] = nd32 - 1
    p = np.cumsum(step, dtype=np.int32)
    # float64 is exact here: each term is a digit times a power of ten below 1e18 (at most 53
    # significant bits) and every partial sum of a field is an integer no larger than its total.
    mant = np.add.reduceat(digits * _POW10_F[p], starts)
    if float(mant.max()) > _EXACT:
        return None
    vals = mant / _POW10_F[dec]
    if sp.size:
        neg = stok[u[sp] == 45]
        vals[neg] = -vals[neg]
    return vals.reshape(-1, ncols), dpos[is_nl]


__all__ = [
    "AUTO",
    "CSV",
    "FORMATS",
    "KV",
    "MAX_LINE",
    "TextFrame",
    "TextLineCodec",
    "TextLineStats",
    "format_number",
]
