"""Codecs of three phone apps people already use: OSC (ZIG SIM, GyrOSC-style), HyperIMU CSV, SensorServer JSON.

This module owns the syntax of the three wire formats: bytes in, typed frames out, bad input counted.
What the values mean (streams, units, signs, clocks) is ``devices.phone_apps``.

**OSC** (``OscCodec``, name ``osc``): one ``feed(data)`` is one UDP datagram, an OSC message or a
bundle (bundles may nest). It becomes one ``OscFrame``: the messages in document order, flattened
out of nested bundles, and the raw 64-bit NTP time tag of the outermost bundle (``None`` for a bare
message, 1 for "immediately"). Parsing is python-osc's (``pythonosc.osc_bundle.OscBundle`` and
``pythonosc.osc_message.OscMessage``). Not used: ``OscPacket``, which reads the wall clock and
reorders messages by it (a replay would not be deterministic), and the ``Dispatcher``, which sleeps
until a future time tag. Time tags are reported, never waited for. Before python-osc sees a
datagram, a structural check walks the bundle element sizes and reads each message's type tags
with python-osc's own ``get_string``. It enforces the bounds below, and it rejects a negative
element size, which makes python-osc's bundle parser loop forever (checked with python-osc
1.10.2), and type tags python-osc cannot decode, which it would skip without moving on, misreading
the arguments after them. After parsing, each message's size must match what its address, type
tags and arguments take. python-osc pads a float cut short at the end with zeros, which would make
up a value, so a truncated message is rejected, and so is one with trailing bytes. Arguments come back as
Python values: ``int``, ``float``, ``str``, ``bytes``, ``bool`` (``T``/``F``), ``None`` (``N``),
tuples for arrays; float32 arguments are exact Python floats of their float32 value.

**HyperIMU** (``HyperImuCodec``, name ``hyperimu``): CSV rows, the enabled sensors' values with
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

**SensorServer** (``SensorServerCodec``, name ``sensorserver``): one ``feed(data)`` is one WebSocket
text frame. A sensor event ``{"values":[...],"timestamp":ns,"accuracy":int}`` (plus ``"type"`` on
the multi-sensor path) becomes a ``SensorServerEvent``. A touch ``{"action":"ACTION_DOWN|
ACTION_MOVE|ACTION_UP","x":px,"y":px}`` becomes a ``SensorServerTouch``. Anything else (not
UTF-8, not JSON, a non-finite number, wrong types, too many values, a GPS message) is a counted
framing error. ``sensorserver_path`` builds the app's WebSocket path for a list of sensor types,
and ``SENSORSERVER_CLOSE_CODES`` says what its close codes mean.

Every codec here keeps its state in itself, so the same chunks always give the same frames.
``encode`` is the inverse of ``feed``, used by simulators and round-trip tests.
"""

from __future__ import annotations

import json
import logging
import math
import struct
from collections.abc import Sequence
from typing import Any, NamedTuple
from urllib.parse import quote

from pythonosc import osc_bundle, osc_message
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message_builder import OscMessageBuilder
from pythonosc.parsing import osc_types

from devices.codecs.base import BadMessage, MessageCodec
from devices.codecs.textline import (
    CSV,
    MAX_LINE,
    TextFrame,
    TextLineCodec,
    format_number,
)

log = logging.getLogger(__name__)

# -- OSC ------------------------------------------------------------------------------------------
#: Bounds of one OSC datagram.
OSC_MAX_DATAGRAM = 65536       # a UDP payload cannot be larger
OSC_MAX_MESSAGES = 1024        # messages (and nested bundles) per datagram
OSC_MAX_DEPTH = 8              # bundle nesting
OSC_MAX_ARGS = 256             # type tags per message
OSC_MAX_ADDRESS = 256          # characters of an address
#: Type tags python-osc decodes (others it skips without consuming their bytes).
OSC_TYPE_TAGS = frozenset("ihfdsbrmtTFN[]")
#: The raw time tag meaning "immediately".
OSC_IMMEDIATELY = 1

_BUNDLE = b"#bundle\x00"
_SIZE = struct.Struct(">i")
_TIMETAG = struct.Struct(">Q")


class OscMsg(NamedTuple):
    """One OSC message: its address and its arguments (arrays as tuples)."""

    address: str
    args: tuple[Any, ...] = ()


class OscFrame(NamedTuple):
    """One datagram: its messages in document order (nested bundles flattened) and the raw NTP time
    tag of the outermost bundle (``None`` for a bare message, ``OSC_IMMEDIATELY`` for "now")."""

    messages: tuple[OscMsg, ...]
    timetag: int | None = None


_Reject = BadMessage  # why an input is rejected


def _tuples(v: Any) -> Any:
    return tuple(_tuples(x) for x in v) if isinstance(v, list) else v


def _lists(v: Any) -> Any:
    return [_lists(x) for x in v] if isinstance(v, tuple) else v


def _check_osc_layout(data: bytes) -> None:
    """Structure check before python-osc parses ``data`` (see the module docstring).

    Raises:
        _Reject: the datagram is not a well-formed OSC packet within the bounds.
    """
    # (start, end, depth) of the elements still to look at; iterative, so nesting costs no recursion
    todo = [(0, len(data), 0)]
    count = 0
    while todo:
        start, end, depth = todo.pop()
        count += 1
        if count > OSC_MAX_MESSAGES:
            raise _Reject(f"more than {OSC_MAX_MESSAGES} elements")
        if data.startswith(_BUNDLE, start):
            if depth >= OSC_MAX_DEPTH:
                raise _Reject(f"bundles nested deeper than {OSC_MAX_DEPTH}")
            if end - start < 16:
                raise _Reject("bundle shorter than its header")
            pos = start + 16
            while pos < end:
                if end - pos < 4:
                    raise _Reject(f"truncated element size at byte {pos}")
                (size,) = _SIZE.unpack_from(data, pos)
                pos += 4
                if size <= 0 or size % 4 or size > end - pos:
                    raise _Reject(f"bad bundle element size {size} at byte {pos - 4}")
                todo.append((pos, pos + size, depth + 1))
                pos += size
        elif data.startswith(b"/", start):
            _check_osc_message(data[start:end])
        else:
            raise _Reject(f"element at byte {start} is neither an OSC message nor a bundle")


def _check_osc_message(m: bytes) -> None:
    try:
        address, idx = osc_types.get_string(m, 0)
        tags = ""
        if idx < len(m):
            tags, _ = osc_types.get_string(m, idx)
    except Exception as exc:  # noqa: BLE001 - python-osc raises ParseError, IndexError, UnicodeDecodeError
        raise _Reject(f"unreadable address or type tags ({exc})") from None
    if len(address) > OSC_MAX_ADDRESS:
        raise _Reject(f"address longer than {OSC_MAX_ADDRESS} characters")
    if not address.isprintable():
        raise _Reject("address with control characters")
    if tags:
        if not tags.startswith(","):
            raise _Reject(f"type tags of {address} do not start with ','")
        if len(tags) - 1 > OSC_MAX_ARGS:
            raise _Reject(f"{address} has more than {OSC_MAX_ARGS} type tags")
        bad = set(tags[1:]) - OSC_TYPE_TAGS
        if bad:
            raise _Reject(f"{address} has unsupported type tags {''.join(sorted(bad))!r}")


def _pad4(n: int) -> int:
    return (n + 3) & ~3


def _leaves(params: Sequence[Any]) -> list[Any]:
    out: list[Any] = []
    for p in params:
        if isinstance(p, list):
            out += _leaves(p)
        else:
            out.append(p)
    return out


def _check_osc_size(m: osc_message.OscMessage) -> None:
    """The bytes a message's parsed address, type tags and arguments take must be its size.

    python-osc pads a float cut short at the end of a message with zeros (for a sender that drops
    trailing zero bytes) and ignores bytes after the last argument. Here a truncated or overlong
    message is rejected instead, so no argument is made up.

    Raises:
        _Reject: the sizes differ.
    """
    raw = m.dgram
    address, idx = osc_types.get_string(raw, 0)
    size = _pad4(len(address.encode("utf-8")) + 1)
    if idx < len(raw):
        tags, _ = osc_types.get_string(raw, idx)
        size += _pad4(len(tags.encode("utf-8")) + 1)
        for tag, v in zip((t for t in tags[1:] if t not in "[]"), _leaves(m.params)):
            if tag in "ifrm":
                size += 4
            elif tag in "hdt":
                size += 8
            elif tag == "s":
                size += _pad4(len(v.encode("utf-8")) + 1)
            elif tag == "b":
                size += 4 + _pad4(len(v))
    if size != len(raw):
        raise _Reject(f"{address}: {len(raw)} bytes where its arguments take {size} (truncated or trailing bytes)")


def _walk(root: Any) -> list[OscMsg]:
    """Messages of a parsed python-osc bundle or message, in document order (sizes checked).

    Raises:
        _Reject: a message's size does not match its contents.
    """
    out: list[OscMsg] = []
    stack = [iter([root])]
    while stack:
        item = next(stack[-1], None)
        if item is None:
            stack.pop()
        elif isinstance(item, osc_bundle.OscBundle):
            stack.append(iter(item))
        else:
            _check_osc_size(item)
            out.append(OscMsg(item.address, tuple(_tuples(p) for p in item.params)))
    return out


class OscCodec(MessageCodec):
    """OSC datagrams (one per ``feed``) to ``OscFrame``s; see the module docstring."""

    name = "osc"

    max_bytes = OSC_MAX_DATAGRAM

    def parse(self, data: bytes) -> list[OscFrame]:
        """One whole datagram (a message or a bundle) to one frame."""
        if not data:
            raise _Reject("empty datagram")
        _check_osc_layout(data)
        try:
            if data.startswith(_BUNDLE):
                root: Any = osc_bundle.OscBundle(data)
                timetag: int | None = _TIMETAG.unpack_from(data, 8)[0]
            else:
                root = osc_message.OscMessage(data)
                timetag = None
            messages = _walk(root)
        except _Reject:
            raise
        except Exception as exc:  # noqa: BLE001 - a foreign parser: whatever it raises is bad input
            raise _Reject(f"python-osc cannot parse it ({type(exc).__name__}: {exc})") from None
        return [OscFrame(tuple(messages), timetag)]

    def reject(self, message: str, raw: bytes = b"") -> None:
        """Count a message the device layer found unusable (wrong argument count or type) as a
        framing error.

        Raises:
            ProtocolError: only in strict mode.
        """
        self._bad("framing", message, 0, raw[:200])

    def encode(self, frame: OscFrame | OscMsg) -> bytes:
        """The datagram of ``frame``, built with python-osc's builders.

        A bare ``OscMsg``, or an ``OscFrame`` with one message and no time tag, is sent as a plain
        message. Anything else goes out as a bundle with the frame's time tag (``None`` sends
        "immediately"). Python floats are sent as float32 (``f``), as the apps send them, ints as
        ``i`` (``h`` beyond 32 bits), tuples as arrays.

        Raises:
            TypeError: not an OSC frame.
            ValueError: an argument python-osc cannot encode, or a time tag out of range.
        """
        if isinstance(frame, OscMsg):
            return self._message(frame).dgram
        if not isinstance(frame, OscFrame):
            raise TypeError(f"not an OSC frame: {type(frame).__name__}")
        if frame.timetag is None and len(frame.messages) == 1:
            return self._message(frame.messages[0]).dgram
        b = OscBundleBuilder(IMMEDIATELY)
        for m in frame.messages:
            b.add_content(self._message(m))  # type: ignore[arg-type]
        dgram = bytearray(b.build().dgram)
        tt = OSC_IMMEDIATELY if frame.timetag is None else frame.timetag
        if not 0 <= tt < 1 << 64:
            raise ValueError(f"time tag {tt} is not a 64-bit NTP time")
        _TIMETAG.pack_into(dgram, 8, tt)
        return bytes(dgram)

    @staticmethod
    def _message(m: OscMsg) -> osc_message.OscMessage:
        b = OscMessageBuilder(address=m.address)
        try:
            for a in m.args:
                b.add_arg(_lists(a))
            return b.build()
        except Exception as exc:  # python-osc's BuildError, ValueError and friends
            raise ValueError(f"cannot encode {m.address}: {exc}") from exc


# -- HyperIMU -------------------------------------------------------------------------------------
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


# -- SensorServer ---------------------------------------------------------------------------------
#: Bounds of one SensorServer message.
SS_MAX_BYTES = 65536
SS_MAX_VALUES = 64
SS_MAX_TYPE = 128
SS_TOUCH_ACTIONS = ("ACTION_DOWN", "ACTION_MOVE", "ACTION_UP")
_MAX_NS = (1 << 63) - 1
_ANDROID = "android.sensor."

#: Close codes the SensorServer app sends (``SensorWebSocketServer.kt``), with what they mean to the user.
SENSORSERVER_CLOSE_CODES: dict[int, str] = {
    4001: "sensor not found: the phone has no sensor of a requested type",
    4002: "unsupported request: the app does not serve this path",
    4003: "parameter missing: the path lacks its type/types parameter",
    4004: "server stopped: the app's server was stopped on the phone",
    4005: "connection closed by the app's user",
    4006: "invalid JSON array: the types parameter is not a JSON array",
    4007: "too few sensors: the multi-sensor path needs at least two types",
    4008: "no sensor specified: the type parameter is empty",
    4009: "permission denied: the app lacks a permission (location for GPS)",
}


def sensorserver_type(name: str) -> str:
    """A sensor type's full Android name: ``accelerometer`` -> ``android.sensor.accelerometer``
    (full names, including vendor ones, are kept; case is folded, as the app matches it)."""
    n = name.strip().lower()
    return n if "." in n else _ANDROID + n


def sensorserver_path(types: Sequence[str]) -> str:
    """The app's WebSocket path (with query) for ``types``.

    One sensor type gives ``/sensor/connect?type=android.sensor.X``; two or more give
    ``/sensors/connect?types=`` and a URL-encoded JSON array; ``["touchscreen"]`` gives ``/touchscreen``.

    Raises:
        ValueError: no type, a repeated type, or touchscreen mixed with sensors.
    """
    names = [t.strip().lower() for t in types if t.strip()]
    if not names:
        raise ValueError("name at least one sensor type")
    if "touchscreen" in names:
        if len(names) > 1:
            raise ValueError("touchscreen is a connection of its own; it cannot be mixed with sensor types")
        return "/touchscreen"
    full = [sensorserver_type(t) for t in names]
    if len(set(full)) != len(full):
        raise ValueError(f"a sensor type is listed twice: {', '.join(full)}")
    if len(full) == 1:
        return "/sensor/connect?type=" + quote(full[0], safe="")
    return "/sensors/connect?types=" + quote(json.dumps(full, separators=(",", ":")), safe="")


class SensorServerEvent(NamedTuple):
    """One Android sensor event: ``type`` (``Sensor.getStringType()``, ``None`` on the single-sensor
    path), values, ``SensorEvent.timestamp`` (ns since boot) and accuracy."""

    type: str | None
    values: tuple[float, ...]
    timestamp: int
    accuracy: int


class SensorServerTouch(NamedTuple):
    """One touch from ``/touchscreen``: ``ACTION_DOWN``, ``ACTION_MOVE`` or ``ACTION_UP`` at x, y (px)."""

    action: str
    x: float
    y: float


SensorServerFrame = SensorServerEvent | SensorServerTouch


def _reject_constant(name: str) -> float:
    raise _Reject(f"non-finite number {name}")


def _ss_num(v: Any, what: str) -> float:
    if type(v) is int:
        return float(v)
    if type(v) is float and math.isfinite(v):
        return v
    raise _Reject(f"{what} is not a finite number ({type(v).__name__})")


def _ss_int(v: Any, what: str, lo: int, hi: int) -> int:
    if type(v) is not int:
        raise _Reject(f"{what} is not an integer ({type(v).__name__})")
    if not lo <= v <= hi:
        raise _Reject(f"{what}={v} out of range [{lo}, {hi}]")
    return v


class SensorServerCodec(MessageCodec):
    """SensorServer JSON text frames (one per ``feed``); see the module docstring."""

    name = "sensorserver"

    max_bytes = SS_MAX_BYTES

    def parse(self, data: bytes) -> list[SensorServerFrame]:
        try:
            obj = json.loads(data.decode("utf-8"), parse_constant=_reject_constant)
        except UnicodeDecodeError as exc:
            raise _Reject(f"not UTF-8 ({exc.reason} at byte {exc.start})") from None
        except _Reject:
            raise
        except (ValueError, RecursionError) as exc:
            raise _Reject(f"not JSON ({exc})") from None
        if not isinstance(obj, dict):
            raise _Reject(f"message is a JSON {type(obj).__name__}, not an object")
        return [self._touch(obj) if "action" in obj else self._event(obj)]

    @staticmethod
    def _event(obj: dict[str, Any]) -> SensorServerEvent:
        for key in ("values", "timestamp", "accuracy"):
            if key not in obj:
                raise _Reject(f'no "{key}": neither a sensor event nor a touch')
        vals = obj["values"]
        if not isinstance(vals, list) or not 1 <= len(vals) <= SS_MAX_VALUES:
            raise _Reject(f'"values" is not an array of 1 to {SS_MAX_VALUES} numbers')
        values = tuple(_ss_num(v, f"values[{i}]") for i, v in enumerate(vals))
        ts = _ss_int(obj["timestamp"], "timestamp", 0, _MAX_NS)
        acc = _ss_int(obj["accuracy"], "accuracy", -(1 << 31), (1 << 31) - 1)
        typ = obj.get("type")
        if typ is not None and (type(typ) is not str or not 0 < len(typ) <= SS_MAX_TYPE):
            raise _Reject(f'"type" is not a sensor type name of 1 to {SS_MAX_TYPE} characters')
        return SensorServerEvent(typ, values, ts, acc)

    @staticmethod
    def _touch(obj: dict[str, Any]) -> SensorServerTouch:
        action = obj["action"]
        if action not in SS_TOUCH_ACTIONS:
            raise _Reject(f"touch action {str(action)[:40]!r} is not one of {'|'.join(SS_TOUCH_ACTIONS)}")
        if "x" not in obj or "y" not in obj:
            raise _Reject("touch without x and y")
        return SensorServerTouch(action, _ss_num(obj["x"], "x"), _ss_num(obj["y"], "y"))

    def reject(self, message: str, raw: bytes = b"") -> None:
        """Count an event the device layer found unusable (too few values for its sensor, an
        unexpected type) as a framing error.

        Raises:
            ProtocolError: only in strict mode.
        """
        self._bad("framing", message, 0, raw[:200])

    def encode(self, frame: SensorServerFrame) -> bytes:
        """The JSON text the app sends for ``frame``.

        Raises:
            TypeError: not a SensorServer frame.
            ValueError: a non-finite value.
        """
        if isinstance(frame, SensorServerEvent):
            d: dict[str, Any] = {"values": list(frame.values), "timestamp": frame.timestamp,
                                 "accuracy": frame.accuracy}
            if frame.type is not None:
                d["type"] = frame.type
        elif isinstance(frame, SensorServerTouch):
            d = {"action": frame.action, "x": frame.x, "y": frame.y}
        else:
            raise TypeError(f"not a SensorServer frame: {type(frame).__name__}")
        return json.dumps(d, separators=(",", ":"), allow_nan=False).encode("utf-8")


__all__ = [
    "HYPERIMU_SENSORS", "OSC_IMMEDIATELY", "SENSORSERVER_CLOSE_CODES", "HyperImuCodec", "OscCodec", "OscFrame",
    "OscMsg", "SensorServerCodec", "SensorServerEvent", "SensorServerTouch", "hyperimu_columns", "hyperimu_sensor",
    "sensorserver_path", "sensorserver_type",
]
