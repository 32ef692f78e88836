"""``evdev``: a Linux input device as the kernel's drivers decode it (pen tablets, touchpads,
touchscreens, mice, gamepads), from ``struct input_event`` frames (``EvdevCodec``, below).

The streams follow the device's capabilities (``Capabilities``), known before the first event:
the ``caps`` option (JSON, as a session records it), else the transport's (``EvdevSource``):

* ``pointer`` (REL axes): dx, dy (counts), wheel, hwheel (detents; with the hi-res wheel codes the
  hi-res counts, summed over the frame, / 120, and the legacy codes ignored);
* ``pen`` (BTN_TOOL_PEN with ABS_X/Y): x, y (m from the axes' resolution, units per mm; 0..1 of the
  surface when the driver gives none), pressure 0..1, tilt_x, tilt_y (deg: from the resolution,
  units per radian; without one, the Wacom convention of one count per degree about the centre),
  distance 0..1 (x, y and tilt NaN until the kernel first reports them; pressure and distance
  from their minimum), in_range (a pen or eraser tool in proximity), tip, barrel (BTN_STYLUS),
  barrel2 (BTN_STYLUS2), eraser; one reading per frame that changes the pen;
* ``touch`` (multitouch protocol B slots, or a single-touch ABS_X/Y with BTN_TOUCH): one reading per
  contact changed in a frame: slot, tracking_id (of the contact, kept on its lifting), tip (0 when
  the contact lifts), x, y (as the pen), touch_major (in x's units), pressure 0..1 (NaN without);
* ``axes`` (other ABS axes: sticks, triggers, wheels): raw counts (NaN until first reported), one
  reading per frame that moves one;
* ``buttons`` (other keys and buttons): 0/1 (2 = autorepeat) per key, one reading per frame that
  changes one.

Every reading's device time is the kernel's event time (taken in the interrupt, before any queue),
a device clock of microsecond ticks (CLOCK_MONOTONIC when the transport sets EVIOCSCLOCKID, else
the realtime clock), so bus times come from the clock fit of every stream together. MSC events and
codes no stream carries give no reading; the latter are counted in ``stats.undecoded``. After a
SYN_DROPPED (``EvdevCodec``) the contacts are forgotten: a contact that was down is reported again
at its next change.

The codec (``EvdevCodec``): a read of an evdev node gives whole ``struct input_event`` records:
``struct timeval`` (``tv_sec``, ``tv_usec`` as native longs), ``__u16 type``, ``__u16 code``,
``__s32 value``: 24 bytes on 64-bit Linux. The transports hand over exactly those bytes (sessions
record what the kernel gave) and the codec turns them into ``EvdevFrame``\\ s, one per SYN_REPORT,
timed by that event's kernel timestamp in microseconds. A SYN_DROPPED (the kernel's buffer
overflowed) drops the events up to the next SYN_REPORT, counts one framing error and marks the next
frame ``resync``. The event codes are the kernel's (``linux/input-event-codes.h``), defined here so
that nothing but the live transport needs python-evdev. The capabilities (``Capabilities``, from
the transport: event codes, absinfo min, max, fuzz, flat, resolution, properties) travel as JSON: the
``caps`` option and the ``evdev.capabilities`` descriptor of a session, so a replay rebuilds the
same streams.
"""

from __future__ import annotations

import logging
import math
import struct
from typing import TYPE_CHECKING, Any, ClassVar, NamedTuple

from capture.errors import ConfigError
from capture.sample import DeviceClockSpec
from devices.base import Device, Reading
from devices.codecs.base import Codec
from devices.options import Option
from devices.transports.evdev import AbsInfo, Capabilities, EvdevSource

if TYPE_CHECKING:
    from collections.abc import Iterable

    from capture.sample import StreamInfo

log = logging.getLogger(__name__)

#: struct input_event on this machine (native long time fields): 24 bytes on 64-bit Linux
EVENT = struct.Struct("@llHHi")
EVENT_SIZE = EVENT.size

EV_SYN, EV_KEY, EV_REL, EV_ABS, EV_MSC, EV_SW, EV_LED, EV_SND, EV_REP, EV_FF = 0, 1, 2, 3, 4, 5, 0x11, 0x12, 0x14, 0x15
EV_MAX = 0x1F
SYN_REPORT, SYN_CONFIG, SYN_MT_REPORT, SYN_DROPPED = 0, 1, 2, 3
REL_X, REL_Y, REL_HWHEEL, REL_WHEEL, REL_WHEEL_HI_RES, REL_HWHEEL_HI_RES = 0, 1, 6, 8, 11, 12
ABS_X, ABS_Y, ABS_PRESSURE, ABS_DISTANCE, ABS_TILT_X, ABS_TILT_Y, ABS_MISC = 0x00, 0x01, 0x18, 0x19, 0x1A, 0x1B, 0x28
ABS_MT_SLOT, ABS_MT_TOUCH_MAJOR, ABS_MT_TOUCH_MINOR = 0x2F, 0x30, 0x31
ABS_MT_POSITION_X, ABS_MT_POSITION_Y, ABS_MT_TRACKING_ID, ABS_MT_PRESSURE = 0x35, 0x36, 0x39, 0x3A
ABS_MT_FIRST, ABS_MT_LAST = 0x2F, 0x3E
BTN_LEFT = 0x110
BTN_TOOL_PEN, BTN_TOOL_RUBBER, BTN_TOOL_BRUSH, BTN_TOOL_PENCIL, BTN_TOOL_AIRBRUSH = 0x140, 0x141, 0x142, 0x143, 0x144
BTN_TOOL_FINGER, BTN_TOOL_MOUSE, BTN_TOOL_LENS, BTN_TOOL_QUINTTAP = 0x145, 0x146, 0x147, 0x148
BTN_STYLUS3, BTN_TOUCH, BTN_STYLUS, BTN_STYLUS2 = 0x149, 0x14A, 0x14B, 0x14C
BTN_TOOL_DOUBLETAP, BTN_TOOL_TRIPLETAP, BTN_TOOL_QUADTAP = 0x14D, 0x14E, 0x14F
MSC_SERIAL, MSC_SCAN, MSC_TIMESTAMP = 0, 4, 5
INPUT_PROP_POINTER, INPUT_PROP_DIRECT, INPUT_PROP_BUTTONPAD = 0, 1, 2
#: a hi-res wheel count is 1/120 of a detent (the kernel's convention)
HI_RES_PER_DETENT = 120

TYPE_NAMES = {EV_SYN: "syn", EV_KEY: "key", EV_REL: "rel", EV_ABS: "abs", EV_MSC: "msc", EV_SW: "sw",
              EV_LED: "led", EV_SND: "snd", EV_REP: "rep", EV_FF: "ff"}
_KEY_NAMES = {
    0x110: "left", 0x111: "right", 0x112: "middle", 0x113: "side", 0x114: "extra", 0x115: "forward",
    0x116: "back", 0x117: "task",
    0x130: "south", 0x131: "east", 0x132: "c", 0x133: "north", 0x134: "west", 0x135: "z", 0x136: "tl",
    0x137: "tr", 0x138: "tl2", 0x139: "tr2", 0x13A: "select", 0x13B: "start", 0x13C: "mode", 0x13D: "thumbl",
    0x13E: "thumbr",
    0x140: "tool_pen", 0x141: "tool_rubber", 0x142: "tool_brush", 0x143: "tool_pencil", 0x144: "tool_airbrush",
    0x145: "tool_finger", 0x146: "tool_mouse", 0x147: "tool_lens", 0x148: "tool_quinttap", 0x149: "stylus3",
    0x14A: "touch", 0x14B: "stylus", 0x14C: "stylus2", 0x14D: "tool_doubletap", 0x14E: "tool_tripletap",
    0x14F: "tool_quadtap",
    **{0x100 + i: f"btn_{i}" for i in range(10)},
}
_ABS_NAMES = {0x00: "x", 0x01: "y", 0x02: "z", 0x03: "rx", 0x04: "ry", 0x05: "rz", 0x06: "throttle",
              0x07: "rudder", 0x08: "wheel", 0x09: "gas", 0x0A: "brake", 0x10: "hat0x", 0x11: "hat0y",
              0x12: "hat1x", 0x13: "hat1y", 0x14: "hat2x", 0x15: "hat2y", 0x16: "hat3x", 0x17: "hat3y",
              0x18: "pressure", 0x19: "distance", 0x1A: "tilt_x", 0x1B: "tilt_y", 0x1C: "tool_width",
              0x20: "volume", 0x21: "profile", 0x28: "misc"}


def key_name(code: int) -> str:
    """A channel name for a key or button code (``left``, ``south``, ``key_0x1e``)."""
    return _KEY_NAMES.get(code, f"key_{code:#x}")


def abs_name(code: int) -> str:
    return _ABS_NAMES.get(code, f"abs_{code:#x}")


class EvdevFrame(NamedTuple):
    """The events of one SYN_REPORT: kernel time in microseconds (of the SYN_REPORT) and the
    ``(type, code, value)`` events before it, in order; ``resync`` after a SYN_DROPPED."""

    ticks: int
    events: list[tuple[int, int, int]]
    resync: bool = False


def pack_event(ticks_us: int, typ: int, code: int, value: int) -> bytes:
    sec, usec = divmod(int(ticks_us), 1_000_000)
    return EVENT.pack(sec, usec, typ, code, value)


class EvdevCodec(Codec):
    """``struct input_event`` bytes -> ``EvdevFrame`` per SYN_REPORT (see the module docstring).
    A record that cannot be the kernel's (an event type beyond EV_MAX, microseconds of a second or
    more) is a framing error, dropped. ``dropped`` counts SYN_DROPPEDs."""

    name = "evdev"

    def __init__(self, strict: bool = False) -> None:
        super().__init__(strict)
        self._events: list[tuple[int, int, int]] = []
        self._dropping = False
        self._resync = False
        self.dropped = 0

    def feed(self, data: bytes) -> list[EvdevFrame]:
        self.stats.bytes_in += len(data)
        buf = self._buf
        buf += data
        n = len(buf) - len(buf) % EVENT_SIZE
        if not n:
            return []
        out: list[EvdevFrame] = []
        events = self._events
        off = 0
        for sec, usec, typ, code, value in EVENT.iter_unpack(memoryview(buf)[:n]):
            if typ > EV_MAX or not 0 <= usec < 1_000_000:
                self._bad("framing", f"not a kernel input_event (type {typ:#x}, usec {usec})", off,
                          bytes(buf[off:off + EVENT_SIZE]))
                self.stats.skipped_bytes += EVENT_SIZE
            elif typ == EV_SYN:
                if code == SYN_REPORT:
                    if self._dropping:
                        self._dropping = False
                        self._resync = True
                    else:
                        out.append(EvdevFrame(sec * 1_000_000 + usec, events, self._resync))
                        self._resync = False
                    events = []
                elif code == SYN_DROPPED:
                    self.dropped += 1
                    self.stats.skipped_bytes += EVENT_SIZE * (len(events) + 1)
                    self._bad("framing", "SYN_DROPPED: the kernel's buffer overflowed; events up to the next"
                              " SYN_REPORT dropped", off, b"")
                    events = []
                    self._dropping = True
            elif not self._dropping:
                events.append((typ, code, value))
            off += EVENT_SIZE
        del buf[:n]
        self._events = events
        self.stats.frames += len(out)
        return out

    def reset(self) -> int:
        n = super().reset() + EVENT_SIZE * len(self._events)
        self._events = []
        self._dropping = False
        self._resync = True
        return n

    @property
    def buffered(self) -> int:
        return len(self._buf) + EVENT_SIZE * len(self._events)

    def encode(self, frame: EvdevFrame) -> bytes:
        """The records of ``frame``, each at its time, then its SYN_REPORT."""
        return b"".join(pack_event(frame.ticks, t, c, v) for t, c, v in frame.events) + \
            pack_event(frame.ticks, EV_SYN, SYN_REPORT, 0)


# -- the device kind ------------------------------------------------------------------------------------

NAN = math.nan
#: the kernel's event times: microseconds
KERNEL_CLOCK = DeviceClockSpec(tick_hz=1e6)
CAPS_DESCRIPTOR = "evdev.capabilities"

_PEN_TOOLS = (BTN_TOOL_PEN, BTN_TOOL_RUBBER, BTN_TOOL_BRUSH, BTN_TOOL_PENCIL, BTN_TOOL_AIRBRUSH)
_PEN_KEYS = frozenset((*_PEN_TOOLS, BTN_TOUCH, BTN_STYLUS, BTN_STYLUS2, BTN_STYLUS3))
_PEN_ABS = frozenset((ABS_X, ABS_Y, ABS_PRESSURE, ABS_DISTANCE, ABS_TILT_X, ABS_TILT_Y))
_FINGER_KEYS = frozenset((BTN_TOUCH, BTN_TOOL_FINGER, BTN_TOOL_DOUBLETAP, BTN_TOOL_TRIPLETAP, BTN_TOOL_QUADTAP,
                          BTN_TOOL_QUINTTAP))
PEN_CHANNELS = ("x", "y", "pressure", "tilt_x", "tilt_y", "distance", "in_range", "tip", "barrel", "barrel2",
                "eraser")
TOUCH_CHANNELS = ("slot", "tracking_id", "tip", "x", "y", "touch_major", "pressure")


class _Scale:
    """One position axis: to m from its resolution (units per mm), else to 0..1 of its range."""

    def __init__(self, info: AbsInfo | None) -> None:
        self.info = info or AbsInfo(0, 0)
        self.unit = "m" if self.info.resolution > 0 else "1"

    def __call__(self, v: float) -> float:
        i = self.info
        return (v - i.minimum) / i.resolution / 1000.0 if i.resolution > 0 else i.fraction(v)

    def size(self, v: float) -> float:
        """A length along the axis (a contact's width), in the same unit."""
        i = self.info
        span = i.maximum - i.minimum
        return v / i.resolution / 1000.0 if i.resolution > 0 else (v / span if span else 0.0)


def _tilt_deg(info: AbsInfo | None, v: int) -> float:
    if info is None:
        return NAN
    centre = (info.minimum + info.maximum + 1) // 2
    if info.resolution > 0:
        return math.degrees((v - centre) / info.resolution)
    return float(v - centre)


class EvdevInput(Device[EvdevCodec]):
    """A Linux input device through its kernel driver; see the module docstring."""

    kind = "evdev"
    description = "Linux input device (evdev): pen tablets, touchpads, touchscreens, mice, gamepads, by kernel time"
    codec_cls = EvdevCodec
    codec: EvdevCodec
    one_fit_per_clock = True
    options: ClassVar[dict[str, Option]] = {
        "caps": Option(str, "", "the device's capabilities as JSON (sessions record them; else asked of the"
                       " transport before open)"),
    }

    # -- streams from the capabilities ---------------------------------------------------------------
    def _capabilities(self) -> Capabilities:
        text = self.opts["caps"].strip()
        if text:
            try:
                return Capabilities.from_json(text)
            except ValueError as exc:
                raise ConfigError(f"device {self.name} (evdev): option caps: {exc}", source=self.name) from None
        t = self.transport
        if isinstance(t, EvdevSource):
            return t.evdev_capabilities()
        raise ConfigError(f"device {self.name} (evdev): {t.url} is not an evdev source and no caps=JSON was given;"
                          " open it as evdev:///dev/input/eventN or simevdev:///PATH.events", source=self.name)

    def declare_streams(self) -> list[StreamInfo]:
        caps = self.caps = self._capabilities()
        self._caps_json = caps.to_json()
        keys, rels, absc = caps.codes(EV_KEY), caps.codes(EV_REL), set(caps.absinfo) | caps.codes(EV_ABS)
        ai = caps.absinfo.get
        streams: list[StreamInfo] = []
        used_keys: set[int] = set()
        used_abs: set[int] = set()
        self._pointer = self._pen = self._touch = self._axes = self._buttons = -1
        self._hires = REL_WHEEL_HI_RES in rels, REL_HWHEEL_HI_RES in rels
        if rels:
            self._pointer = len(streams)
            q = tuple(1.0 / HI_RES_PER_DETENT if h else 1.0 for h in self._hires)
            streams.append(self.stream_info("pointer", "pointer", ("dx", "dy", "wheel", "hwheel"),
                                            ("count", "count", "detent", "detent"), None, clock=KERNEL_CLOCK,
                                            quantum=(1.0, 1.0, *q)))
        if BTN_TOOL_PEN in keys and ABS_X in absc and ABS_Y in absc:
            self._pen = len(streams)
            self._px, self._py = _Scale(ai(ABS_X)), _Scale(ai(ABS_Y))
            streams.append(self.stream_info("pen", "pen", PEN_CHANNELS,
                                            (self._px.unit, self._py.unit, "1", "deg", "deg", "1", "1", "1", "1",
                                             "1", "1"), None, clock=KERNEL_CLOCK))
            used_keys |= _PEN_KEYS & keys
            used_abs |= _PEN_ABS & absc
        self._mt = ABS_MT_POSITION_X in absc and ABS_MT_POSITION_Y in absc
        single = not self._mt and self._pen < 0 and ABS_X in absc and ABS_Y in absc and BTN_TOUCH in keys
        if self._mt or single:
            self._touch = len(streams)
            xc, yc = (ABS_MT_POSITION_X, ABS_MT_POSITION_Y) if self._mt else (ABS_X, ABS_Y)
            self._tx, self._ty = _Scale(ai(xc)), _Scale(ai(yc))
            self._tpressure = ai(ABS_MT_PRESSURE if self._mt else ABS_PRESSURE)
            streams.append(self.stream_info("touch", "touch", TOUCH_CHANNELS,
                                            ("1", "1", "1", self._tx.unit, self._ty.unit, self._tx.unit, "1"),
                                            None, clock=KERNEL_CLOCK))
            used_keys |= _FINGER_KEYS & keys
            used_abs |= {c for c in absc if ABS_MT_FIRST <= c <= ABS_MT_LAST}
            if self._pen < 0:
                used_abs |= {ABS_X, ABS_Y, ABS_PRESSURE} & absc  # the single-touch emulation of contact 0
        self._axis_codes = sorted(c for c in absc if c not in used_abs and c != ABS_MISC
                                  and not ABS_MT_FIRST <= c <= ABS_MT_LAST)
        if self._axis_codes:
            self._axes = len(streams)
            streams.append(self.stream_info("axes", "axes", tuple(abs_name(c) for c in self._axis_codes),
                                            ("count",) * len(self._axis_codes), None, clock=KERNEL_CLOCK,
                                            quantum=(1.0,) * len(self._axis_codes)))
        self._key_codes = sorted(keys - used_keys)
        if self._key_codes:
            self._buttons = len(streams)
            streams.append(self.stream_info("buttons", "buttons", tuple(key_name(c) for c in self._key_codes),
                                            ("1",) * len(self._key_codes), None, clock=KERNEL_CLOCK,
                                            quantum=(1.0,) * len(self._key_codes)))
        if not streams:
            raise ConfigError(f"device {self.name} (evdev): {caps.name or 'the device'} reports no keys, relative"
                              " or absolute axes", source=self.name)
        self._axis_index = {c: i for i, c in enumerate(self._axis_codes)}
        self._key_index = {c: i for i, c in enumerate(self._key_codes)}
        self._reset_state()
        return streams

    def _reset_state(self) -> None:
        self._pen_abs: dict[int, int] = {}
        self._pen_keys: dict[int, int] = {}
        #: NaN until the kernel reports the axis (it sends changes only, and the value before the first
        #: event is not in the recording)
        self._axis_values = [NAN] * len(self._axis_codes)
        self._key_values = [0.0] * len(self._key_codes)
        self._forget_contacts()

    def _forget_contacts(self) -> None:
        self._slot = 0
        #: per slot: tracking id (-1: no contact), x, y, touch major, pressure (raw)
        self._slots: dict[int, list[int]] = {}
        self._st_touch = 0

    @property
    def device_options(self) -> dict[str, Any]:
        """The options as given, with the capabilities, so a replay rebuilds the same streams."""
        return {**self._given_options, "caps": self._caps_json}

    def descriptors(self) -> dict[str, bytes]:
        return {CAPS_DESCRIPTOR: self._caps_json.encode()}

    def reset_after_reconnect(self) -> int:
        n = super().reset_after_reconnect()
        self._forget_contacts()
        return n

    # -- frames to readings ----------------------------------------------------------------------------
    def frame_to_readings(self, frame: EvdevFrame) -> Iterable[Reading]:
        if frame.resync:
            self._forget_contacts()
        ticks = frame.ticks
        dx = dy = wl = wh = wlh = whh = 0
        rel = pen = axes = keys = False
        touched: list[int] = []
        st_changed = False
        for typ, code, value in frame.events:
            if typ == EV_REL and self._pointer >= 0:
                rel = True
                if code == REL_X:
                    dx += value
                elif code == REL_Y:
                    dy += value
                elif code == REL_WHEEL:
                    wl += value
                elif code == REL_HWHEEL:
                    wh += value
                elif code == REL_WHEEL_HI_RES:
                    wlh += value
                elif code == REL_HWHEEL_HI_RES:
                    whh += value
                else:
                    self._undecoded(f"rel {code:#x}")
            elif typ == EV_ABS:
                if self._touch >= 0 and self._mt and ABS_MT_FIRST <= code <= ABS_MT_LAST:
                    if code == ABS_MT_SLOT:
                        self._slot = value
                        continue
                    s = self._slots.get(self._slot)
                    if s is None:
                        s = self._slots[self._slot] = [-1, 0, 0, 0, 0, -1]
                    if code == ABS_MT_TRACKING_ID:
                        if value >= 0:
                            s[0] = s[5] = value
                        else:
                            s[0] = -1
                    elif code == ABS_MT_POSITION_X:
                        s[1] = value
                    elif code == ABS_MT_POSITION_Y:
                        s[2] = value
                    elif code == ABS_MT_TOUCH_MAJOR:
                        s[3] = value
                    elif code == ABS_MT_PRESSURE:
                        s[4] = value
                    else:
                        continue  # other contact fields (minor, orientation, tool type) carry no channel
                    if self._slot not in touched:
                        touched.append(self._slot)
                elif self._pen >= 0 and code in _PEN_ABS:
                    self._pen_abs[code] = value
                    pen = True
                elif code in self._axis_index:
                    self._axis_values[self._axis_index[code]] = float(value)
                    axes = True
                elif self._touch >= 0 and not self._mt and code in (ABS_X, ABS_Y, ABS_PRESSURE):
                    s = self._slots.setdefault(0, [-1, 0, 0, 0, 0, 0])
                    s[{ABS_X: 1, ABS_Y: 2, ABS_PRESSURE: 4}[code]] = value
                    st_changed = True
                elif not (self._mt and ABS_MT_FIRST <= code <= ABS_MT_LAST) and code not in (ABS_X, ABS_Y, ABS_MISC):
                    self._undecoded(f"abs {code:#x}")
            elif typ == EV_KEY:
                if self._pen >= 0 and code in _PEN_KEYS:
                    self._pen_keys[code] = value
                    pen = True
                elif code in self._key_index:
                    self._key_values[self._key_index[code]] = float(value)
                    keys = True
                elif self._touch >= 0 and code in _FINGER_KEYS:
                    if code == BTN_TOUCH and not self._mt:
                        s = self._slots.setdefault(0, [-1, 0, 0, 0, 0, 0])
                        s[0] = 0 if value else -1
                        st_changed = True
                else:
                    self._undecoded(f"key {code:#x}")
            elif typ != EV_MSC:
                self._undecoded(f"event type {typ:#x} code {code:#x}")
        out: list[Reading] = []
        if rel:
            wheel = wlh / HI_RES_PER_DETENT if self._hires[0] else float(wl)
            hwheel = whh / HI_RES_PER_DETENT if self._hires[1] else float(wh)
            out.append(Reading(self._pointer, (float(dx), float(dy), wheel, hwheel), ticks))
        if pen:
            out.append(Reading(self._pen, self._pen_values(), ticks))
        if touched or st_changed:
            for slot in (touched or [0]):
                out.append(Reading(self._touch, self._contact_values(slot), ticks))
        if axes:
            out.append(Reading(self._axes, tuple(self._axis_values), ticks))
        if keys:
            out.append(Reading(self._buttons, tuple(self._key_values), ticks))
        return out

    def _pen_values(self) -> tuple[float, ...]:
        a, k, ai = self._pen_abs, self._pen_keys, self.caps.absinfo
        pinfo, dinfo = ai.get(ABS_PRESSURE), ai.get(ABS_DISTANCE)
        return (self._px(a[ABS_X]) if ABS_X in a else NAN, self._py(a[ABS_Y]) if ABS_Y in a else NAN,
                pinfo.fraction(a.get(ABS_PRESSURE, pinfo.minimum)) if pinfo else NAN,
                _tilt_deg(ai.get(ABS_TILT_X), a[ABS_TILT_X]) if ABS_TILT_X in a else NAN,
                _tilt_deg(ai.get(ABS_TILT_Y), a[ABS_TILT_Y]) if ABS_TILT_Y in a else NAN,
                dinfo.fraction(a.get(ABS_DISTANCE, dinfo.minimum)) if dinfo else NAN,
                1.0 if any(k.get(t, 0) for t in _PEN_TOOLS) else 0.0,
                1.0 if k.get(BTN_TOUCH, 0) else 0.0,
                1.0 if k.get(BTN_STYLUS, 0) else 0.0,
                1.0 if k.get(BTN_STYLUS2, 0) else 0.0,
                1.0 if k.get(BTN_TOOL_RUBBER, 0) else 0.0)

    def _contact_values(self, slot: int) -> tuple[float, ...]:
        s = self._slots.get(slot) or [-1, 0, 0, 0, 0, -1]
        p = self._tpressure
        return (float(slot), float(s[5] if s[0] < 0 else s[0]), 0.0 if s[0] < 0 else 1.0,
                self._tx(s[1]), self._ty(s[2]), self._tx.size(s[3]),
                p.fraction(s[4]) if p is not None else NAN)
