"""The HyperIMU codec: the app's CSV rows over UDP or TCP in, ``TextFrame``s out.

This module owns the HyperIMU row syntax: bytes in, typed frames out, bad input counted. What the
values mean (streams, units, clock) is ``devices.phone_apps.hyperimu``.

``HyperImuCodec`` (name ``hyperimu``): CSV rows, the enabled sensors' values with
3 per sensor, in the app's order, optionally led by an epoch-ms timestamp and a MAC address and
followed by GPS latitude, longitude, altitude. Each row ends with CR LF or ``#`` (the app's setting,
both accepted). Several rows may share a datagram, and over TCP a row may be split across chunks,
so lines are reassembled (this is ``devices.codecs.textline.TextLineCodec`` with ``#`` turned into
a line end and HyperIMU's header rules). Lines starting with ``@`` (the app's file header) and
header rows starting with a letter (``timestamp,MPL_Gyroscope.x,...``) are skipped and counted in
``stats.skipped_lines``, not as errors. A row with the wrong number of columns, a value that is
not a number, a line with no number at all, an over-long line (``max_line``) or an out-of-range
timestamp is a counted framing error. NMEA sentences (the app's last option) are not supported:
their extra columns make a row's count wrong.

The codec keeps its state in itself, so the same chunks always give the same frames. ``encode``
is the inverse of ``feed``, used by simulators and round-trip tests.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from devices.codecs.textline import (
    CSV,
    MAX_LINE,
    TextFrame,
    TextLineCodec,
    format_number,
)

if TYPE_CHECKING:
    from collections.abc import Sequence

#: HyperIMU sensors a row can carry (3 values each), with ``_`` for a sensor whose 3 columns are
#: read past. ``magnetic_field`` is an alias of ``magnetometer``.
HYPERIMU_SENSORS = ("accelerometer", "gyroscope", "magnetometer", "linear_acceleration", "gravity",
                    "rotation_vector", "orientation", "_")
HYPERIMU_ALIASES = {"magnetic_field": "magnetometer"}
HYPERIMU_TIME_MAX = float(2 ** 53)  # epoch ms as an exact float
_MAX_MAC = 64


def _is_number(s: bytes) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def hyperimu_sensor(name: str) -> str:
    """The canonical name of a HyperIMU sensor (lower case, aliases resolved).

    Raises:
        ValueError: not a known sensor name.
    """
    n = name.strip().lower()
    n = HYPERIMU_ALIASES.get(n, n)
    if n not in HYPERIMU_SENSORS:
        raise ValueError(f"unknown HyperIMU sensor {name!r}; known: {', '.join(HYPERIMU_SENSORS)} "
                         f"(_ skips a sensor's three columns)")
    return n


def hyperimu_columns(sensors: Sequence[str], timestamp: bool = False, mac: bool = False,
                     gps: bool = False) -> list[str | None]:
    """The row's columns: a key per parsed column (``t``, ``<sensor>.x|y|z``, ``lat lon alt``),
    ``None`` for columns read past (the MAC address, ``_`` sensors).

    Raises:
        ValueError: an unknown or repeated sensor, or no column to parse.
    """
    cols: list[str | None] = []
    if timestamp:
        cols.append("t")
    if mac:
        cols.append(None)
    seen: set[str] = set()
    for s in sensors:
        n = hyperimu_sensor(s)
        if n == "_":
            cols += [None] * 3
            continue
        if n in seen:
            raise ValueError(f"HyperIMU sensor {n!r} is listed twice")
        seen.add(n)
        cols += [f"{n}.x", f"{n}.y", f"{n}.z"]
    if gps:
        cols += ["lat", "lon", "alt"]
    if not any(c is not None and c != "t" for c in cols):
        raise ValueError("the HyperIMU layout has no sensor or GPS column to read")
    return cols


class HyperImuCodec(TextLineCodec):
    """HyperIMU CSV rows (see the module docstring): a ``TextLineCodec`` in CSV mode whose columns
    follow the app's settings, with ``#`` as a second row end and HyperIMU's header rules.

    Args:
        strict: raise ``ProtocolError`` at the first bad row instead of counting it.
        sensors: the enabled sensors in the app's order (``HYPERIMU_SENSORS``).
        timestamp: rows start with an epoch-ms timestamp (a parsed field, the first).
        mac: rows carry a MAC address (after the timestamp); it is kept in ``last_mac``.
        gps: rows end with latitude, longitude, altitude.
        max_line: longest accepted row in bytes.

    Raises:
        ValueError: an unknown or repeated sensor name, or nothing to parse.
    """

    name = "hyperimu"

    def __init__(self, strict: bool = False, *, sensors: Sequence[str] = ("accelerometer", "gyroscope", "magnetometer"),
                 timestamp: bool = False, mac: bool = False, gps: bool = False, max_line: int = MAX_LINE) -> None:
        cols = hyperimu_columns(sensors, timestamp, mac, gps)
        super().__init__(strict, fmt=CSV, columns=cols, max_line=max_line, time_field=0 if timestamp else None,
                         time_max=HYPERIMU_TIME_MAX)
        self.sensors = tuple(hyperimu_sensor(s) for s in sensors)
        self.timestamp = timestamp
        self.mac = mac
        self.gps = gps
        self._mac_col = (1 if timestamp else 0) if mac else None
        #: the MAC address of the last good row (``mac`` layouts)
        self.last_mac: str | None = None

    def feed(self, data: bytes) -> list[TextFrame]:
        """Parse more bytes (a datagram, or any piece of a TCP stream); returns the rows completed.

        Raises:
            ProtocolError: only in strict mode, at the first bad row.
        """
        return super().feed(bytes(data).replace(b"#", b"\n"))

    def _line(self, raw: bytes, off: int, out: list[TextFrame]) -> None:
        line = raw[:-1] if raw[-1:] == b"\r" else raw
        s = line.strip()
        if s[:1] == b"@":
            self._skip_line(raw, "header line")
            return
        if s and len(line) <= self.max_line:
            fields = s.split(b",")
            first = fields[0].strip()
            numbers = any(_is_number(f) for f in fields)
            # a header row starts with a letter: "timestamp,MPL_Gyroscope.x,..."; a data row may too
            # ("NaN", or a MAC address in the first column), but it has numbers
            if first[:1].isalpha() and (not numbers or not (self._mac_col == 0 or _is_number(first))):
                self._skip_line(raw, "header row")
                return
            if not numbers:
                self._reject(raw, off, "row without a number")
                return
            mc = self._mac_col
            if mc is not None and len(fields) == self._ncols:
                mac = fields[mc].strip()
                if not mac or len(mac) > _MAX_MAC:
                    self._reject(raw, off, "empty or over-long MAC address column")
                    return
                n = len(out)
                super()._line(raw, off, out)
                if len(out) > n:
                    self.last_mac = mac.decode("utf-8", "replace")
                return
        super()._line(raw, off, out)

    def encode(self, frame: TextFrame, mac: str = "02:00:00:00:00:00", end: bytes = b"\r\n") -> bytes:
        """The row of ``frame`` as HyperIMU sends it (values in the codec's parsed-field order).

        Args:
            frame: values of the parsed fields (timestamp first when there is one).
            mac: the MAC column's text (``mac`` layouts).
            end: the row end, ``\\r\\n`` or ``#``.

        Raises:
            ValueError: the wrong number of values, or a bad row end.
        """
        if end not in (b"\r\n", b"#"):
            raise ValueError("a HyperIMU row ends with \\r\\n or #")
        if len(frame.values) != len(self.fields):
            raise ValueError(f"{len(frame.values)} values for {len(self.fields)} fields")
        it = iter(frame.values)
        cols: list[str] = []
        for k, c in enumerate(self.columns):
            if c is None:
                cols.append(mac if k == self._mac_col else "0.0")
            elif c == "t":
                cols.append(str(int(next(it))))
            else:
                cols.append(format_number(next(it)))
        return ",".join(cols).encode("ascii") + end


__all__ = ["HYPERIMU_ALIASES", "HYPERIMU_SENSORS", "HYPERIMU_TIME_MAX", "HyperImuCodec", "hyperimu_columns",
           "hyperimu_sensor"]
