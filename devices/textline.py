"""IMUs behind a microcontroller sketch that prints one text line per reading (``textline`` kind).

Arduino, ESP32, Pico and MicroPython sketches commonly print readings as CSV
(``1234,0.01,-0.02,9.81,0.1,0.2,0.3``) or as key:value pairs (``t:1234 ax:0.01 ay:-0.02 ...``).
This module owns what those numbers mean, configured by flat options that fit a URL query::

    textline@serial:///dev/ttyACM0?format=csv&columns=t,ax,ay,az,gx,gy,gz&units=ms,g,g,g,dps,dps,dps&time=t

(``baud`` belongs to the serial transport, not here). Options:

* ``format``: ``csv``, ``kv`` or ``auto`` (per line: ``:`` or ``=`` makes it key:value).
* ``columns``: comma-separated, one entry per CSV column in order: a channel name, ``KEY:CHANNEL``
  to read key ``KEY`` of key:value lines into ``CHANNEL``, or ``_`` / empty for a column to ignore.
  Channels ``ax ay az gx gy gz`` form the ``imu`` stream (the same names as the WitMotion ``imu``
  stream, so the same orientation code applies), ``mx my mz`` the ``mag`` stream, the ``time``
  column is the device clock, and any other name goes to the ``extra`` stream.
* ``units``: comma-separated, aligned with ``columns`` (empty entries take the default). Converted
  to SI: acceleration ``g``, ``mg`` or ``m/s^2`` (default) to m/s^2; angular rate ``dps``/``deg/s``
  or ``rad/s`` (default) to rad/s; magnetic field ``uT`` (default), ``nT``, ``mT``, ``gauss`` or
  ``mgauss`` to uT; time ``us``, ``ms`` or ``s`` (required for the time column). Extra channels
  keep their unit label unconverted.
* ``time``: the column holding the device's time (e.g. ``millis()`` or ``micros()``). Its ticks are
  microseconds whatever the unit (1 MHz device clock), so fractional ms or s keep their precision.
* ``time_wrap``: where that counter wraps, in its own unit: ``u32`` (4294967296, for ``micros()``
  and ``millis()``), ``u16``, or an integer; empty for a counter that does not wrap.
* ``rate``: the nominal line rate in Hz (needed for lost-line detection and, without a time
  column, for the pseudo clock); 0 when unknown.
* ``max_line``: the longest line accepted, bytes.

Bad lines are counted and skipped (see ``devices.codecs.textline``). Streams carry ``NaN`` for
channels that are not mapped, or that a key:value line did not carry.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from capture.errors import ConfigError
from capture.sample import ChunkRun, DeviceClockSpec, StreamInfo
from devices.base import BatchReadings, Device, Reading, StreamReadings
from devices.codecs.textline import (
    AUTO,
    FORMATS,
    KV,
    MAX_LINE,
    TextFrame,
    TextLineCodec,
)
from devices.options import Option, resolve_options

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping, Sequence

G = 9.80665
DEG = math.pi / 180.0

IMU_CHANNELS = ("ax", "ay", "az", "gx", "gy", "gz")
MAG_CHANNELS = ("mx", "my", "mz")
ACC_UNITS = {"m/s^2": 1.0, "m/s2": 1.0, "mps2": 1.0, "g": G, "mg": G * 1e-3}
GYRO_UNITS = {"rad/s": 1.0, "dps": DEG, "deg/s": DEG, "°/s": DEG}
MAG_UNITS = {"ut": 1.0, "µt": 1.0, "nt": 1e-3, "mt": 1e3, "gauss": 100.0, "mgauss": 0.1}
#: time unit -> device ticks (microseconds) per unit
TIME_UNITS = {"us": 1, "µs": 1, "ms": 1000, "s": 1_000_000}
TICK_HZ = 1e6
WRAPS = {"u32": 2 ** 32, "u16": 2 ** 16}

_KEY_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\[\]-]*$")
_CHANNEL_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
FRAME = "sensor axes as printed by the sketch"

OPTIONS: dict[str, Option] = {
    "format": Option(str, AUTO, "line format: csv, kv (key:value / key=value) or auto (per line)", choices=FORMATS),
    "columns": Option(str, ",".join(IMU_CHANNELS),
                      "CSV columns in order / keys to read: CHANNEL or KEY:CHANNEL, _ or empty to skip"),
    "units": Option(str, "", "unit per column (g|mg|m/s^2, dps|deg/s|rad/s, uT|nT|mT|gauss, us|ms|s); empty = SI"),
    "time": Option(str, "", "column with the device time (its unit in units=)"),
    "time_wrap": Option(str, "", "wrap of the time counter in its unit: u32, u16 or INT (empty: no wrap)"),
    "rate": Option(float, 0.0, "nominal lines per second (0 = unknown)", min=0.0, max=100_000.0),
    "max_line": Option(int, MAX_LINE, "longest accepted line, bytes", min=16, max=1 << 20),
}


@dataclass(frozen=True)
class _Field:
    key: str
    channel: str
    unit: str
    factor: float


@dataclass(frozen=True)
class _StreamPlan:
    suffix: str
    kind: str
    channels: tuple[str, ...]
    units: tuple[str, ...]
    fields: tuple[tuple[int, int, float], ...]  # (field index, channel position, factor)
    mask: int  # fields of this stream, as TextFrame.present bits


class TextLineLayout:
    """What the columns of a sketch's lines mean: parsed and checked from the device options.

    Simulators build one from the same options as the device and call ``encode_line`` to produce
    the bytes a sketch would print.

    Args:
        options: the ``textline`` options (strings from a URL, or typed values).
        where: names the device in error messages.

    Raises:
        ConfigError: an unknown option, or an inconsistent column / unit / time specification.
    """

    def __init__(self, options: Mapping[str, Any] | None = None, where: str = "textline") -> None:
        o = resolve_options(OPTIONS, dict(options or {}), where, "textline@URL")
        self.where = where
        self.fmt: str = o["format"]
        self.rate: float | None = o["rate"] or None
        self.max_line: int = o["max_line"]
        entries = [e.strip() for e in o["columns"].split(",")]
        units = [u.strip() for u in o["units"].split(",")] if o["units"].strip() else [""] * len(entries)
        if len(units) != len(entries):
            raise self._err(f"units= has {len(units)} entries but columns= has {len(entries)}; give one unit per"
                            " column (empty entries take the default)")
        time_name = o["time"].strip()
        self.columns: list[str | None] = []
        self.fields: list[_Field] = []
        seen_ch: set[str] = set()
        for e, unit in zip(entries, units, strict=True):
            if e in ("", "_"):
                self.columns.append(None)
                continue
            key, _, ch = e.partition(":")
            if not ch:
                ch = key
            key, ch = key.strip(), ch.strip()
            if not _KEY_RE.match(key):
                raise self._err(f"column key {key!r} must be letters, digits, _ . - [ ] starting with a letter or _")
            if not _CHANNEL_RE.match(ch) or ch == "_":
                raise self._err(f"channel name {ch!r} must be letters, digits and _, starting with a letter")
            if ch in seen_ch:
                raise self._err(f"channel {ch!r} is mapped twice in columns=")
            if key in (f.key for f in self.fields):
                raise self._err(f"key {key!r} is used twice in columns=")
            seen_ch.add(ch)
            is_time = bool(time_name) and time_name in (ch, key)
            self.columns.append(key)
            self.fields.append(self._field(key, ch, unit, is_time))
        if not self.fields:
            raise self._err("columns= maps no column (all are _ or empty)")
        # the time column
        self.time_field: int | None = None
        self.time_scale = 1
        self.wrap_ticks: int | None = None
        wrap_text = o["time_wrap"].strip().lower()
        if time_name:
            hits = [i for i, f in enumerate(self.fields) if time_name in (f.channel, f.key)]
            if not hits:
                raise self._err(f"time column {time_name!r} is not in columns={o['columns']}")
            self.time_field = hits[0]
            self.time_scale = TIME_UNITS[self.fields[hits[0]].unit]
        wrap_units: int | None = None
        if wrap_text:
            if not time_name:
                raise self._err("time_wrap= needs a time column (time=)")
            if wrap_text in WRAPS:
                wrap_units = WRAPS[wrap_text]
            else:
                try:
                    wrap_units = int(wrap_text)
                except ValueError:
                    raise self._err(f"time_wrap={o['time_wrap']!r} is not u32, u16 or an integer") from None
                if wrap_units < 2:
                    raise self._err(f"time_wrap={wrap_units} must be at least 2")
            self.wrap_ticks = wrap_units * self.time_scale
        self.wrap_units = wrap_units
        self.time_max = float(wrap_units) if wrap_units else 2.0 ** 62 / self.time_scale
        self.clock = DeviceClockSpec(TICK_HZ, self.wrap_ticks) if self.time_field is not None else None
        # streams
        plans: list[_StreamPlan] = []
        for suffix, kind, names, default_units in (("imu", "imu", IMU_CHANNELS, ("m/s^2",) * 3 + ("rad/s",) * 3),
                                                   ("mag", "mag", MAG_CHANNELS, ("uT",) * 3)):
            fl = tuple((i, names.index(f.channel), f.factor) for i, f in enumerate(self.fields) if f.channel in names)
            if fl:
                plans.append(_StreamPlan(suffix, kind, names, default_units, fl, sum(1 << i for i, _, _ in fl)))
        extra = [(i, f) for i, f in enumerate(self.fields)
                 if i != self.time_field and f.channel not in IMU_CHANNELS + MAG_CHANNELS]
        if extra:
            plans.append(_StreamPlan("extra", "extra", tuple(f.channel for _, f in extra),
                                     tuple(f.unit or "1" for _, f in extra),
                                     tuple((i, k, 1.0) for k, (i, _) in enumerate(extra)),
                                     sum(1 << i for i, _ in extra)))
        if not plans:
            raise self._err("columns= maps only the time column; map at least one channel")
        self.plans = plans

    def _err(self, why: str) -> ConfigError:
        return ConfigError(f"{self.where}: {why}", source=self.where)

    def _field(self, key: str, ch: str, unit: str, is_time: bool) -> _Field:
        u = "" if unit == "_" else unit
        lu = u.lower()
        if is_time:
            if not u:
                raise self._err(f"time column {ch!r} needs a unit in units= (us, ms or s)")
            if lu not in TIME_UNITS:
                raise self._err(f"unknown time unit {u!r} for column {ch!r}; use us, ms or s")
            return _Field(key, ch, lu, 1.0)
        for names, table, default, what in ((IMU_CHANNELS[:3], ACC_UNITS, "m/s^2", "acceleration (g, mg, m/s^2)"),
                                            (IMU_CHANNELS[3:], GYRO_UNITS, "rad/s", "angular rate (dps, deg/s, rad/s)"),
                                            (MAG_CHANNELS, MAG_UNITS, "ut", "magnetic field (uT, nT, mT, gauss)")):
            if ch in names:
                if not u:
                    return _Field(key, ch, default, 1.0)
                if lu not in table:
                    raise self._err(f"unknown unit {u!r} for {what} column {ch!r}")
                return _Field(key, ch, lu, table[lu])
        return _Field(key, ch, u, 1.0)

    # -- what the device needs -------------------------------------------------------------------
    def codec(self, strict: bool = False) -> TextLineCodec:
        """A codec parsing these columns."""
        return TextLineCodec(strict, fmt=self.fmt, columns=self.columns, max_line=self.max_line,
                             time_field=self.time_field, time_max=self.time_max)

    # -- encoding for simulators -----------------------------------------------------------------
    def frame(self, channels: Mapping[str, float], t_device_s: float | None = None,
              decimals: int | None = None) -> TextFrame:
        """The frame a sketch prints for one reading.

        Args:
            channels: SI values by channel name (``ax``.. in m/s^2, ``gx``.. in rad/s, ``mx``.. in
                uT, extra channels as they are); channels left out are not printed (key:value) or
                printed as ``nan`` (CSV).
            t_device_s: the device time in seconds (required when there is a time column); printed
                as an integer count for us and ms, wrapped at ``time_wrap``.
            decimals: round the values to this many decimals in the column's unit, as a sketch's
                ``Serial.print(x, decimals)`` does (default: print the exact shortest form).

        Raises:
            ValueError: no device time given for a layout with a time column, or an unknown channel.
        """
        known = {f.channel for f in self.fields}
        unknown = set(channels) - known
        if unknown:
            raise ValueError(f"channels {sorted(unknown)} are not in this layout ({sorted(known)})")
        vals: list[float] = []
        present = 0
        for i, f in enumerate(self.fields):
            if i == self.time_field:
                if t_device_s is None:
                    raise ValueError("this layout has a time column: give t_device_s")
                v = t_device_s * 1e6 / self.time_scale
                if self.time_scale < TIME_UNITS["s"]:
                    v = float(round(v))
                if self.wrap_units:
                    v = math.fmod(v, self.wrap_units)
            elif f.channel in channels:
                v = float(channels[f.channel]) / f.factor
                if decimals is not None and math.isfinite(v):
                    v = round(v, decimals)
            else:
                vals.append(math.nan)
                continue
            vals.append(v)
            present |= 1 << i
        return TextFrame(tuple(vals), present)

    def encode_line(self, channels: Mapping[str, float], t_device_s: float | None = None,
                    decimals: int | None = None) -> bytes:
        """The bytes (one line, with ``\\n``) a sketch prints for one reading; see ``frame``.

        Raises:
            ValueError: as ``frame``.
        """
        return self.codec().encode(self.frame(channels, t_device_s, decimals))

    def encode_lines(self, channels: Mapping[str, Sequence[float] | np.ndarray],
                     t_device_s: Sequence[float] | np.ndarray | None = None,
                     decimals: int | None = None) -> list[bytes]:
        """``encode_line`` for many readings: arrays of SI values by channel name, one entry per reading.

        Raises:
            ValueError: as ``frame``, or arrays of different lengths.
        """
        cols = {k: np.asarray(v, np.float64).tolist() for k, v in channels.items()}
        lengths = {len(v) for v in cols.values()} | ({len(t_device_s)} if t_device_s is not None else set())
        if len(lengths) > 1:
            raise ValueError(f"arrays of different lengths: {sorted(lengths)}")
        n = lengths.pop() if lengths else 0
        codec = self.codec()
        ts = None if t_device_s is None else np.asarray(t_device_s, np.float64).tolist()
        return [codec.encode(self.frame({k: v[j] for k, v in cols.items()}, None if ts is None else ts[j], decimals))
                for j in range(n)]


class TextLineImu(Device[TextLineCodec]):
    """A sketch printing IMU readings as text lines (see the module docstring)."""

    kind = "textline"
    description = "text-line IMU sketch (CSV or key:value lines; columns, units and time set by options)"
    codec_cls = TextLineCodec
    options = OPTIONS

    def declare_streams(self) -> list[StreamInfo]:
        lay = TextLineLayout(self.opts, f"device {self.name} (textline)")
        self.layout = lay
        self.codec = lay.codec(self.strict)
        self._tf = lay.time_field
        self._tscale = lay.time_scale
        self._wrap = lay.wrap_ticks
        self._plans = [(si, p.fields, (math.nan,) * len(p.channels), p.mask) for si, p in enumerate(lay.plans)]
        return [self.stream_info(p.suffix, p.kind, p.channels, p.units, lay.rate, FRAME, lay.clock)
                for p in lay.plans]

    def frame_to_readings(self, frame: TextFrame) -> Iterable[Reading]:
        v = frame.values
        t: int | None = None
        if self._tf is not None:
            t = round(v[self._tf] * self._tscale)
            if self._wrap:
                t %= self._wrap
        out: list[Reading] = []
        present = frame.present
        for si, fields, template, mask in self._plans:
            if not present & mask:
                continue
            vals = list(template)
            for fi, ci, fac in fields:
                vals[ci] = v[fi] * fac
            out.append(Reading(si, tuple(vals), t))
        return out

    # -- batch path ------------------------------------------------------------------------------
    def batch_ready(self) -> bool:
        """Plain CSV may be vectorised; a key:value stream (also in ``auto``) never is, so do not try."""
        c = self.codec
        return c.fmt != KV and c.last_format != KV

    def decode_batch(self, chunks: ChunkRun) -> BatchReadings | None:
        """Vectorised decoding of runs of plain CSV lines (``TextLineCodec.feed_clean``); anything else
        returns ``None`` and the chunks take the per-chunk path."""
        res = self.codec.feed_clean(chunks.data)
        if res is None:
            return None
        vals, nl = res
        n = vals.shape[0]
        ticks = None
        if self._tf is not None:
            ticks = np.round(vals[:, self._tf] * self._tscale).astype(np.int64)
            if self._wrap:
                ticks %= self._wrap
        chunk = np.searchsorted(chunks.offsets[1:], nl, side="right").astype(np.int64)
        n_streams = len(self._plans)
        base = np.arange(n, dtype=np.int64) * n_streams
        out: dict[int, StreamReadings] = {}
        for k, (si, fields, template, _) in enumerate(self._plans):
            v = np.full((n, len(template)), np.nan)
            for fi, ci, fac in fields:
                v[:, ci] = vals[:, fi] * fac
            out[si] = StreamReadings(v, ticks, chunk, base + k)
        return BatchReadings(out)


__all__ = ["IMU_CHANNELS", "MAG_CHANNELS", "OPTIONS", "TIME_UNITS", "TextLineImu", "TextLineLayout"]
