"""evemu recordings (evdev level): the device description (``.desc``) and the events (``.events``),
or both in one file as ``evemu-record`` writes them (``description_for`` finds the description).

``.desc``: ``N:`` name, ``I: bus vendor product version`` (hex), ``P:``/``B:`` bitmasks,
``A: code min max fuzz flat [res]`` (``B:`` lines give ``bits``, the codes of each event type;
``P:`` lines ``props``); ``.events``: ``E: sec.usec type code value`` (type and code
hex, value decimal). ``#`` starts a comment. ``frames`` groups events into SYN_REPORT frames, each
with its time and the events in it, which the HID simulators encode into one report per frame.
A file is read only when it is a regular file of at most ``MAX_TRACE_BYTES`` with lines of at most
``MAX_LINE``; anything else is a ``TraceError``, as is a time that is not finite seconds.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

from capture.bounded_io import InputLimitError, read_text_bounded
from capture.errors import TraceError

EV_SYN, EV_KEY, EV_REL, EV_ABS, EV_MSC = 0, 1, 2, 3, 4
EV_MAX = 0x1F
SYN_REPORT = 0
REL_X, REL_Y, REL_HWHEEL, REL_WHEEL, REL_WHEEL_HI_RES, REL_HWHEEL_HI_RES = 0, 1, 6, 8, 11, 12
ABS_X, ABS_Y, ABS_PRESSURE, ABS_DISTANCE, ABS_TILT_X, ABS_TILT_Y = 0x00, 0x01, 0x18, 0x19, 0x1A, 0x1B
ABS_MT_SLOT, ABS_MT_TOUCH_MAJOR, ABS_MT_TOUCH_MINOR = 0x2F, 0x30, 0x31
ABS_MT_POSITION_X, ABS_MT_POSITION_Y, ABS_MT_TRACKING_ID = 0x35, 0x36, 0x39
BTN_LEFT, BTN_TOOL_PEN, BTN_TOOL_RUBBER, BTN_TOUCH, BTN_STYLUS, BTN_STYLUS2 = 0x110, 0x140, 0x141, 0x14A, 0x14B, 0x14C


@dataclass
class AbsInfo:
    minimum: int
    maximum: int
    fuzz: int = 0
    flat: int = 0
    resolution: int = 0

    def fraction(self, value: float) -> float:
        span = self.maximum - self.minimum
        return (value - self.minimum) / span if span else 0.0


@dataclass
class EvemuDevice:
    name: str = ""
    bus: int = 0
    vendor: int = 0
    product: int = 0
    version: int = 0
    absinfo: dict[int, AbsInfo] = field(default_factory=dict)
    #: event type -> the codes its ``B:`` bitmask lines set (evdev capabilities)
    bits: dict[int, set[int]] = field(default_factory=dict)
    #: input properties (``P:`` bitmask: INPUT_PROP_POINTER, _DIRECT, ...)
    props: set[int] = field(default_factory=set)


@dataclass
class Frame:
    """The events of one SYN_REPORT frame: ``(type, code, value)`` in order, at time ``t`` (s)."""

    t: float
    events: list[tuple[int, int, int]]


#: the largest recording read (the evemu traces in ../shared/traces are 2 kB..300 kB) and its longest line
MAX_TRACE_BYTES = 64 << 20
MAX_LINE = 64 << 10
#: event times beyond this many seconds (about 300 years) are not a recording's
MAX_TIME_S = 1e10


def _lines(path: str) -> list[tuple[int, str]]:
    try:
        text = read_text_bounded(path, MAX_TRACE_BYTES, MAX_LINE)
    except (OSError, InputLimitError, UnicodeDecodeError) as exc:
        raise TraceError(f"cannot read evemu file: {exc}", path=path) from None
    out = []
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if line:
            out.append((n, line))
    return out


def _mask(parts: list[str]) -> list[int]:
    """Bitmask bytes (hex, 00..ff)."""
    out = [int(x, 16) for x in parts]
    if any(not 0 <= b <= 0xFF for b in out):
        raise ValueError("a bitmask byte is not 00..ff")
    return out


def parse_desc(path: str) -> EvemuDevice:
    """Parse an evemu ``.desc`` (or the header of an ``.events`` file that carries one).

    Raises:
        TraceError: a malformed ``I:``, ``B:``, ``P:`` or ``A:`` line (file and line named).
    """
    dev = EvemuDevice()
    offsets: dict[int, int] = {}  # a type's bitmask continues over several B: lines, 8 bytes each
    prop_off = 0
    for n, line in _lines(path):
        tag, _, rest = line.partition(":")
        parts = rest.split()
        try:
            if tag == "N":
                dev.name = rest.strip()
            elif tag == "I":
                dev.bus, dev.vendor, dev.product, dev.version = (int(x, 16) for x in parts[:4])
            elif tag == "B":
                if not parts:
                    raise ValueError("needs a type and its bitmask bytes")
                typ, mask = int(parts[0], 16), _mask(parts[1:])
                if not 0 <= typ <= EV_MAX:
                    raise ValueError(f"event type {typ:#x} beyond EV_MAX")
                off = offsets.get(typ, 0)
                codes = dev.bits.setdefault(typ, set())
                codes.update(off + 8 * i + b for i, byte in enumerate(mask) for b in range(8) if byte >> b & 1)
                offsets[typ] = off + 8 * len(mask)
            elif tag == "P":
                mask = _mask(parts)
                dev.props.update(prop_off + 8 * i + b for i, byte in enumerate(mask) for b in range(8) if byte >> b & 1)
                prop_off += 8 * len(mask)
            elif tag == "A":
                vals = [int(x) for x in parts[1:]]
                if len(vals) < 2:
                    raise ValueError("needs code min max")
                dev.absinfo[int(parts[0], 16)] = AbsInfo(*vals[:5])
        except (ValueError, TypeError) as exc:
            raise TraceError(f"malformed {tag}: line {line!r} ({exc})", path=path, line=n) from None
    return dev


def parse_events(path: str) -> list[Frame]:
    """The ``E:`` lines of an evemu recording, grouped into SYN_REPORT frames.

    Raises:
        TraceError: a malformed ``E:`` line (file and line named).
    """
    frames: list[Frame] = []
    cur: list[tuple[int, int, int]] = []
    for n, line in _lines(path):
        if not line.startswith("E:"):
            continue
        parts = line[2:].split()
        try:
            if len(parts) != 4:
                raise ValueError(f"expected 'E: sec.usec type code value', got {len(parts)} fields")
            t = float(parts[0])
            if not abs(t) < MAX_TIME_S:  # nan, inf and 1e300 too
                raise ValueError(f"time {parts[0]} is not a time in seconds")
            typ, code, value = int(parts[1], 16), int(parts[2], 16), int(parts[3])
            if not -(1 << 31) <= value < 1 << 31:
                raise ValueError(f"value {value} is not a 32-bit evdev value")
        except ValueError as exc:
            raise TraceError(f"malformed event line {line!r} ({exc})", path=path, line=n) from None
        if typ == EV_SYN and code == SYN_REPORT:
            frames.append(Frame(t, cur))
            cur = []
        elif typ != EV_SYN:
            cur.append((typ, code, value))
    return frames


def desc_for(events_path: str) -> str | None:
    """The ``.desc`` file that pairs with an ``.events`` file: in the same folder, the longest
    ``.desc`` name whose stem starts the events file's name."""
    folder, base = os.path.split(os.path.abspath(events_path))
    best = None
    try:
        names = os.listdir(folder)
    except OSError:
        return None
    for nm in names:
        if nm.endswith(".desc") and base.startswith(nm[:-5]) and (best is None or len(nm) > len(best)):
            best = nm
    return os.path.join(folder, best) if best else None


def has_description(dev: EvemuDevice) -> bool:
    """Whether a parsed file held a device description (``N:``, ``I:`` or ``A:`` lines)."""
    return bool(dev.name or dev.vendor or dev.product or dev.bus or dev.absinfo)


def description_for(events_path: str) -> EvemuDevice | None:
    """The device description of a recording: its own ``N:``/``I:``/``A:`` lines when it holds them
    (a single-file ``evemu-record`` recording), else the ``.desc`` beside it (``desc_for``), else None.

    Raises:
        TraceError: an unreadable file or a malformed description line.
    """
    own = parse_desc(events_path)
    if has_description(own):
        return own
    desc = desc_for(events_path)
    return parse_desc(desc) if desc else None
