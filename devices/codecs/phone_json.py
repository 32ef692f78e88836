"""JSON message codecs of phones that push to perfcap: the built-in phone page and Sensor Logger.

Both protocols are message oriented: every ``feed(data)`` call is exactly one whole message (one
WebSocket text frame, one HTTP POST body), UTF-8 JSON, so nothing is buffered between calls. Each
message is checked strictly (types, row lengths, finite numbers or ``null``, bounded sizes) and
becomes typed frames (``NamedTuple``s); a message that is not valid JSON, has the wrong shape or an
unknown ``"type"`` is counted with ``_bad`` and dropped (``ProtocolError`` in strict mode). A bad
row or entry inside an otherwise valid message is counted and dropped alone. ``null`` numbers
become NaN. ``encode`` is the inverse (NaN becomes ``null``), used by ``sim_devices.phone_sim``.

**Phone page (v1)**, JSON text frames over the page's WebSocket (``PageCodec``, name
``phone_page``)::

    {"type":"hello","v":1,"id":ID,"ua":UA,"platform":"ios"|"android"|"other","screen":[w,h],
     "orient":angle,"t":performance.now()}                    (the host removes "token")
    {"type":"data","seq":n,"sent":ms,"orient":angle,
     "m":[[t, ax,ay,az, gx,gy,gz, ra,rb,rg, interval], ...],   devicemotion (a: without gravity,
                                                                g: including it, r: deg/s)
     "o":[[t, alpha,beta,gamma, absolute], ...],              deviceorientation (deg)
     "t":[[t, phase, id, x, y, force, rx, ry], ...]}           touches (phase 0..3, CSS px)
    {"type":"pong","h":host_ns,"t":performance.now()}
    host -> page: {"type":"welcome","device":NAME,"ping_s":s}, {"type":"ping","h":host_ns}

Times ``t`` are ``event.timeStamp`` in ms since the page's ``performance.timeOrigin``. ``absolute``
is 0/1 (``true``/``false`` is accepted too, being what the browser gives). Every page time (rows'
``t``, ``sent``, the pong's and hello's ``t``) must be in ``[0, PAGE_TIME_MAX)`` ms, ``orient`` an
angle in [-360, 360] degrees, ``screen`` sizes and ``ping_s`` within ``[0, 1e6]``: a number out of
range is refused with its reason, never passed on to the clock fit.

**Sensor Logger** HTTP push (``SensorLoggerCodec``, name ``sensorlogger``)::

    {"messageId":int,"sessionId":str,"deviceId":str,
     "payload":[{"name":str,"time":int ns (UTC epoch),"values":{...},"accuracy"?:int}, ...]}

Entries of the sensors in ``SENSORLOGGER_FIELDS`` are decoded (their values as a tuple in the order
given there); entries of other names (location, battery, network, microphone, camera, ...) are not
errors: they are counted per name in ``unknown_names`` (each name logged once) and skipped.
"""

from __future__ import annotations

import json
import logging
import math
from typing import TYPE_CHECKING, Any, NamedTuple

from devices.codecs.base import BadMessageError, MessageCodec

if TYPE_CHECKING:
    from collections.abc import Mapping

log = logging.getLogger(__name__)

#: Bounds of one phone page message.
PAGE_MAX_BYTES = 1 << 20
MAX_ROWS = 2000
MAX_TEXT = 1024
PAGE_PLATFORMS = ("ios", "android", "other")
PAGE_VERSION = 1

#: Row layouts of the page's data arrays.
MOTION_COLUMNS = ("t", "ax", "ay", "az", "gx", "gy", "gz", "ra", "rb", "rg", "interval")
ORIENTATION_COLUMNS = ("t", "alpha", "beta", "gamma", "absolute")
TOUCH_COLUMNS = ("t", "phase", "id", "x", "y", "force", "rx", "ry")
TOUCH_PHASES = (0, 1, 2, 3)  # start, move, end, cancel

#: Bounds of one Sensor Logger message (bodies with camera frames may exceed them and are dropped).
SL_MAX_BYTES = 8 << 20
SL_MAX_ENTRIES = 20_000
SL_MAX_NAMES = 64  # distinct unknown names tracked (more are lumped under "<other>")
_MAX_ID = (1 << 53) - 1  # JSON integers that survive a JavaScript number
_MAX_TIME = (1 << 63) - 1
#: the largest page time, ms (31 years since the page's time origin)
PAGE_TIME_MAX = 1e12
#: the largest Sensor Logger entry time, UTC epoch ns (year 2116; device times stay within int64)
SL_TIME_MAX = 1 << 62

#: Sensor Logger sensors this codec decodes: name -> (value keys in tuple order, how many are required).
SENSORLOGGER_FIELDS: dict[str, tuple[tuple[str, ...], int]] = {
    "accelerometer": (("x", "y", "z"), 3),
    "gyroscope": (("x", "y", "z"), 3),
    "gravity": (("x", "y", "z"), 3),
    "magnetometer": (("x", "y", "z"), 3),
    "totalacceleration": (("x", "y", "z"), 3),
    "accelerometeruncalibrated": (("x", "y", "z"), 3),
    "gyroscopeuncalibrated": (("x", "y", "z"), 3),
    "magnetometeruncalibrated": (("x", "y", "z"), 3),
    "orientation": (("qw", "qx", "qy", "qz", "roll", "pitch", "yaw"), 4),
    "barometer": (("pressure", "relativeAltitude"), 1),
}

NAN = float("nan")


# -- frames ---------------------------------------------------------------------------------------
class PageHello(NamedTuple):
    """The page's first message: who it is. ``token`` is normally removed by the host before the
    message is recorded; it is kept only if it reaches the codec."""

    id: str
    platform: str
    ua: str = ""
    screen: tuple[float, float] | None = None
    orient: float | None = None
    t: float | None = None
    v: int = PAGE_VERSION
    token: str | None = None


class PageData(NamedTuple):
    """One data message: rows as tuples of floats laid out as ``MOTION_COLUMNS``,
    ``ORIENTATION_COLUMNS`` and ``TOUCH_COLUMNS`` (NaN where the page sent ``null``)."""

    seq: int
    sent: float | None = None
    orient: float | None = None
    motion: tuple[tuple[float, ...], ...] = ()
    orientation: tuple[tuple[float, ...], ...] = ()
    touches: tuple[tuple[float, ...], ...] = ()


class PagePong(NamedTuple):
    """The page's answer to a ping: the host's ``h`` (ns) and the page's ``performance.now()`` (ms)."""

    h: int
    t: float


class PageWelcome(NamedTuple):
    """Host -> page after a good hello."""

    device: str
    ping_s: float


class PagePing(NamedTuple):
    """Host -> page clock probe (host monotonic ns)."""

    h: int


PageFrame = PageHello | PageData | PagePong | PageWelcome | PagePing


class SensorEntry(NamedTuple):
    """One payload entry: sensor name, UTC epoch ns, values in ``SENSORLOGGER_FIELDS[name]`` order."""

    name: str
    time: int
    values: tuple[float, ...]
    accuracy: int | None = None

    @property
    def fields(self) -> tuple[str, ...]:
        return SENSORLOGGER_FIELDS[self.name][0]


class SensorLoggerMessage(NamedTuple):
    """One push message with its decoded entries (in message order)."""

    message_id: int
    session_id: str
    device_id: str
    entries: tuple[SensorEntry, ...] = ()


# -- helpers --------------------------------------------------------------------------------------
_Invalid = BadMessageError  # a message (or one row or entry of it) is unusable


def _reject_constant(name: str) -> float:
    raise _Invalid(f"non-finite number {name} in JSON")


def _loads(data: bytes) -> Any:
    try:
        return json.loads(data.decode("utf-8"), parse_constant=_reject_constant)
    except _Invalid:
        raise
    except UnicodeDecodeError as exc:
        raise _Invalid(f"not UTF-8 ({exc.reason} at byte {exc.start})") from None
    except (ValueError, RecursionError) as exc:  # JSONDecodeError is a ValueError; so is a huge int
        raise _Invalid(f"not JSON ({exc})") from None


def _is_num(v: Any) -> bool:
    return (type(v) is int or type(v) is float) and math.isfinite(v)


def _num(v: Any, what: str) -> float:
    """A finite JSON number (bools are not numbers; an integer beyond float64's range is refused)."""
    if type(v) is int:
        if v.bit_length() > 1023:
            raise _Invalid(f"{what} is an integer of {v.bit_length()} bits, beyond a float's range")
        return float(v)
    if type(v) is float and math.isfinite(v):
        return v
    raise _Invalid(f"{what} is {_kind(v)}, not a finite number")


def _num_or_null(v: Any, what: str) -> float:
    return NAN if v is None else _num(v, what)


def _opt_num(obj: Mapping[str, Any], key: str, lo: float = -math.inf, hi: float = math.inf) -> float | None:
    v = obj.get(key)
    return None if v is None else _ranged(_num(v, key), key, lo, hi)


def _ranged(v: float, what: str, lo: float, hi: float) -> float:
    """``v`` if within [lo, hi]."""
    if not lo <= v <= hi:
        raise _Invalid(f"{what}={v!r} out of range [{lo:g}, {hi:g}]")
    return v


def _page_time(v: Any, what: str) -> float:
    """A page time in ms, in [0, PAGE_TIME_MAX)."""
    t = _num(v, what)
    if not 0.0 <= t < PAGE_TIME_MAX:
        raise _Invalid(f"{what}={t!r} out of range [0, {PAGE_TIME_MAX:g}) ms")
    return t


def _opt_page_time(obj: Mapping[str, Any], key: str, what: str) -> float | None:
    v = obj.get(key)
    return None if v is None else _page_time(v, what)


def _int(v: Any, what: str, lo: int = 0, hi: int = _MAX_ID) -> int:
    """A JSON integer in [lo, hi]; an integral float is accepted (JavaScript has no int type)."""
    if type(v) is float and math.isfinite(v) and v.is_integer():
        v = int(v)
    if type(v) is not int:
        raise _Invalid(f"{what} is {_kind(v)}, not an integer")
    if not lo <= v <= hi:
        raise _Invalid(f"{what}={v} out of range [{lo}, {hi}]")
    return v


def _text(v: Any, what: str, limit: int = MAX_TEXT) -> str:
    if type(v) is not str:
        raise _Invalid(f"{what} is {_kind(v)}, not a string")
    if len(v) > limit:
        raise _Invalid(f"{what} longer than {limit} characters")
    return v


def _kind(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "a boolean"
    if isinstance(v, (int, float)):
        return f"the number {v!r}"
    names: dict[type, str] = {str: "a string", list: "an array", dict: "an object"}
    return names.get(type(v), type(v).__name__)


def _json_num(v: float) -> float | None:
    """NaN (and other non-finite values) go out as ``null``."""
    return v if math.isfinite(v) else None


def _dumps(obj: Any) -> bytes:
    return json.dumps(obj, separators=(",", ":"), ensure_ascii=False, allow_nan=False).encode("utf-8")


# -- phone page -----------------------------------------------------------------------------------
class PageCodec(MessageCodec):
    """Codec of perfcap's built-in phone page protocol (v1): one JSON text frame per ``feed``."""

    name = "phone_page"

    max_bytes = PAGE_MAX_BYTES

    def parse(self, data: bytes) -> list[PageFrame]:
        obj = _loads(data)
        if not isinstance(obj, dict):
            raise _Invalid(f"message is {_kind(obj)}, not an object")
        typ = obj.get("type")
        if typ == "data":
            frame: PageFrame = self._data(obj, data)
        elif typ == "hello":
            frame = self._hello(obj)
        elif typ == "pong":
            frame = PagePong(_int(obj.get("h"), "pong h", -_MAX_TIME - 1, _MAX_TIME),
                             _page_time(obj.get("t"), "pong t"))
        elif typ == "welcome":
            frame = PageWelcome(_text(obj.get("device"), "welcome device"),
                                _ranged(_num(obj.get("ping_s"), "ping_s"), "ping_s", 0.0, 1e6))
        elif typ == "ping":
            frame = PagePing(_int(obj.get("h"), "ping h", -_MAX_TIME - 1, _MAX_TIME))
        else:
            raise _Invalid(f"unknown message type {typ!r}" if type(typ) is str
                           else f"message type is {_kind(typ)}")
        return [frame]

    @staticmethod
    def _hello(obj: Mapping[str, Any]) -> PageHello:
        v = _int(obj.get("v"), "hello v")
        if v != PAGE_VERSION:
            raise _Invalid(f"protocol version {v} is not supported (expected {PAGE_VERSION})")
        platform = _text(obj.get("platform"), "platform", 32)
        if platform not in PAGE_PLATFORMS:
            raise _Invalid(f"platform {platform!r} is not one of {'|'.join(PAGE_PLATFORMS)}")
        screen = obj.get("screen")
        scr: tuple[float, float] | None = None
        if screen is not None:
            if not isinstance(screen, list) or len(screen) != 2:
                raise _Invalid("screen is not [width, height]")
            scr = (_ranged(_num(screen[0], "screen width"), "screen width", 0.0, 1e6),
                   _ranged(_num(screen[1], "screen height"), "screen height", 0.0, 1e6))
        ua = obj.get("ua")
        token = obj.get("token")
        return PageHello(_text(obj.get("id"), "id", 128), platform, "" if ua is None else _text(ua, "ua"), scr,
                         _opt_num(obj, "orient", -360.0, 360.0), _opt_page_time(obj, "t", "hello t"), v,
                         None if token is None else _text(token, "token", 256))

    def _data(self, obj: Mapping[str, Any], data: bytes) -> PageData:
        seq = _int(obj.get("seq"), "seq")
        arrays: list[tuple[tuple[float, ...], ...]] = []
        for key, width, row in (("m", len(MOTION_COLUMNS), self._motion_row),
                                ("o", len(ORIENTATION_COLUMNS), self._orientation_row),
                                ("t", len(TOUCH_COLUMNS), self._touch_row)):
            rows = obj.get(key)
            if rows is None:
                arrays.append(())
                continue
            if not isinstance(rows, list):
                raise _Invalid(f'"{key}" is {_kind(rows)}, not an array')
            if len(rows) > MAX_ROWS:
                raise _Invalid(f'"{key}" has {len(rows)} rows (at most {MAX_ROWS})')
            good: list[tuple[float, ...]] = []
            for i, r in enumerate(rows):
                try:
                    if not isinstance(r, list) or len(r) != width:
                        raise _Invalid(f"is {_kind(r) if not isinstance(r, list) else f'{len(r)} long'}, "
                                       f"not an array of {width}")
                    good.append(row(r))
                except _Invalid as exc:
                    self._bad("framing", f'seq {seq}: row {i} of "{key}" {exc}; row dropped', 0, data[:200])
            arrays.append(tuple(good))
        return PageData(seq, _opt_page_time(obj, "sent", "sent"), _opt_num(obj, "orient", -360.0, 360.0), *arrays)

    @staticmethod
    def _time(v: Any) -> float:
        return _page_time(v, "t")

    def _motion_row(self, r: list[Any]) -> tuple[float, ...]:
        return (self._time(r[0]), *tuple(_num_or_null(x, MOTION_COLUMNS[k + 1]) for k, x in enumerate(r[1:])))

    def _orientation_row(self, r: list[Any]) -> tuple[float, ...]:
        ab = r[4]
        absolute = float(ab) if isinstance(ab, bool) else _num_or_null(ab, "absolute")
        return (self._time(r[0]), _num_or_null(r[1], "alpha"), _num_or_null(r[2], "beta"),
                _num_or_null(r[3], "gamma"), absolute)

    def _touch_row(self, r: list[Any]) -> tuple[float, ...]:
        phase = _int(r[1], "phase", 0, 3)
        tid = _int(r[2], "touch id", -_MAX_ID, _MAX_ID)
        return (self._time(r[0]), float(phase), float(tid), _num(r[3], "x"), _num(r[4], "y"),
                _num_or_null(r[5], "force"), _num_or_null(r[6], "rx"), _num_or_null(r[7], "ry"))

    def encode(self, frame: PageFrame) -> bytes:
        """The JSON text of ``frame`` (NaN as ``null``; empty arrays and ``None`` fields left out).

        Raises:
            TypeError: ``frame`` is not a phone page frame.
        """
        if isinstance(frame, PageData):
            d: dict[str, Any] = {"type": "data", "seq": frame.seq}
            if frame.sent is not None:
                d["sent"] = frame.sent
            if frame.orient is not None:
                d["orient"] = frame.orient
            if frame.motion:
                d["m"] = [[_json_num(x) for x in r] for r in frame.motion]
            if frame.orientation:
                d["o"] = [[_json_num(x) for x in r] for r in frame.orientation]
            if frame.touches:
                d["t"] = [[r[0], int(r[1]), int(r[2])] + [_json_num(x) for x in r[3:]] for r in frame.touches]
        elif isinstance(frame, PageHello):
            d = {"type": "hello", "v": frame.v}
            if frame.token is not None:
                d["token"] = frame.token
            d.update(id=frame.id, ua=frame.ua, platform=frame.platform)
            if frame.screen is not None:
                d["screen"] = list(frame.screen)
            if frame.orient is not None:
                d["orient"] = frame.orient
            if frame.t is not None:
                d["t"] = frame.t
        elif isinstance(frame, PagePong):
            d = {"type": "pong", "h": frame.h, "t": frame.t}
        elif isinstance(frame, PagePing):
            d = {"type": "ping", "h": frame.h}
        elif isinstance(frame, PageWelcome):
            d = {"type": "welcome", "device": frame.device, "ping_s": frame.ping_s}
        else:
            raise TypeError(f"not a phone page frame: {type(frame).__name__}")
        return _dumps(d)


# -- Sensor Logger --------------------------------------------------------------------------------
class SensorLoggerCodec(MessageCodec):
    """Codec of Sensor Logger's HTTP push (and MQTT) JSON: one message per ``feed``."""

    name = "sensorlogger"

    def __init__(self, strict: bool = False) -> None:
        super().__init__(strict)
        #: entries per sensor name this codec does not decode (each name logged once)
        self.unknown_names: dict[str, int] = {}

    max_bytes = SL_MAX_BYTES

    def parse(self, data: bytes) -> list[SensorLoggerMessage]:
        obj = _loads(data)
        if not isinstance(obj, dict):
            raise _Invalid(f"message is {_kind(obj)}, not an object")
        mid = _int(obj.get("messageId"), "messageId")
        sid = _text(obj.get("sessionId"), "sessionId", 256)
        did = _text(obj.get("deviceId"), "deviceId", 256)
        payload = obj.get("payload")
        if not isinstance(payload, list):
            raise _Invalid(f"payload is {_kind(payload)}, not an array")
        if len(payload) > SL_MAX_ENTRIES:
            raise _Invalid(f"payload has {len(payload)} entries (at most {SL_MAX_ENTRIES})")
        entries: list[SensorEntry] = []
        for i, e in enumerate(payload):
            try:
                ent = self._entry(e)
            except _Invalid as exc:
                self._bad("framing", f"message {mid}: payload entry {i} {exc}; entry dropped", 0, data[:200])
                continue
            if ent is not None:
                entries.append(ent)
        return [SensorLoggerMessage(mid, sid, did, tuple(entries))]

    def _entry(self, e: Any) -> SensorEntry | None:
        if not isinstance(e, dict):
            raise _Invalid(f"is {_kind(e)}, not an object")
        name = _text(e.get("name"), "name", 64)
        spec = SENSORLOGGER_FIELDS.get(name)
        if spec is None:
            self._unknown(name)
            return None
        keys, required = spec
        t = _int(e.get("time"), "time", 0, SL_TIME_MAX)
        vals = e.get("values")
        if not isinstance(vals, dict):
            raise _Invalid(f"({name}) values is {_kind(vals)}, not an object")
        out: list[float] = []
        for k, key in enumerate(keys):
            if key not in vals:
                if k < required:
                    raise _Invalid(f"({name}) has no {key!r} value")
                out.append(NAN)
            else:
                out.append(_num_or_null(vals[key], f"({name}) {key}"))
        acc = e.get("accuracy")
        return SensorEntry(name, t, tuple(out), None if acc is None else _int(acc, "accuracy", -_MAX_ID, _MAX_ID))

    def _unknown(self, name: str) -> None:
        u = self.unknown_names
        if name not in u and len(u) >= SL_MAX_NAMES:
            name = "<other>"
        if name not in u:
            u[name] = 0
            log.info("%s: sensor %r is not decoded (its entries are counted and skipped)", self.name, name)
        u[name] += 1

    def encode(self, frame: SensorLoggerMessage) -> bytes:
        """The JSON body of ``frame`` (NaN values as ``null``; optional keys left out when NaN).

        Raises:
            TypeError: ``frame`` is not a ``SensorLoggerMessage``.
            KeyError: an entry's name is not in ``SENSORLOGGER_FIELDS``.
        """
        if not isinstance(frame, SensorLoggerMessage):
            raise TypeError(f"not a Sensor Logger message: {type(frame).__name__}")
        payload = []
        for e in frame.entries:
            keys, required = SENSORLOGGER_FIELDS[e.name]
            vals = {k: _json_num(v) for i, (k, v) in enumerate(zip(keys, e.values, strict=False))
                    if i < required or math.isfinite(v)}
            d: dict[str, Any] = {"name": e.name, "time": e.time, "values": vals}
            if e.accuracy is not None:
                d["accuracy"] = e.accuracy
            payload.append(d)
        return _dumps({"messageId": frame.message_id, "sessionId": frame.session_id, "deviceId": frame.device_id,
                       "payload": payload})


__all__ = [
    "MAX_ROWS",
    "MOTION_COLUMNS",
    "ORIENTATION_COLUMNS",
    "PAGE_MAX_BYTES",
    "PAGE_TIME_MAX",
    "SENSORLOGGER_FIELDS",
    "SL_MAX_BYTES",
    "SL_MAX_ENTRIES",
    "SL_TIME_MAX",
    "TOUCH_COLUMNS",
    "PageCodec",
    "PageData",
    "PageFrame",
    "PageHello",
    "PagePing",
    "PagePong",
    "PageWelcome",
    "SensorEntry",
    "SensorLoggerCodec",
    "SensorLoggerMessage",
]
