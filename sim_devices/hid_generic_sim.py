"""Simulated HID mouse, pen and touch screen (``simhid://mouse``, ``simhid://pen``, ``simhid://touch``).

Each has a standard-conformant report descriptor (``devices.hid.descriptor.STANDARD_DESCRIPTORS``)
and encodes its input reports from field values through ``ReportLayout.encode`` (the inverse of
the decoder the ``hid`` device kind uses). The values come from seeded synthetic motion, or with
``evemu=PATH`` from an evemu recording (single-file, or ``.events`` with its ``.desc`` beside it): one report per
SYN_REPORT frame at the recorded time; absolute axes are mapped in physical units when the
recording gives their resolution, else by their fraction of the evdev range onto the descriptor's
logical range; relative axes and keys one to one, wheels with their sums kept.

The mouse has a wheel Resolution Multiplier (feature report 2, 1 or 8 counts per detent): once the
host sets it, wheel and AC Pan are sent in 1/8 detents.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, ClassVar

from capture.errors import ConfigError
from devices.hid.descriptor import (
    AC_PAN,
    DIG_BARREL,
    DIG_CONFIDENCE,
    DIG_CONTACT_COUNT,
    DIG_CONTACT_ID,
    DIG_ERASER,
    DIG_HEIGHT,
    DIG_IN_RANGE,
    DIG_INVERT,
    DIG_TIP_PRESSURE,
    DIG_TIP_SWITCH,
    DIG_WIDTH,
    DIG_X_TILT,
    DIG_Y_TILT,
    GD_WHEEL,
    GD_X,
    GD_Y,
    STANDARD_DESCRIPTORS,
    FieldLayout,
    ReportLayout,
    parse_descriptor,
)
from devices.options import Option
from sim_devices import evemu
from sim_devices.hid_sim import HidResponder, trace_path

if TYPE_CHECKING:
    from collections.abc import Iterator, Mapping


def _field(rep: ReportLayout, usage: int, nth: int = 0) -> FieldLayout:
    return [f for f in rep.fields if f.usage == usage and not f.is_array][nth]


def _frac_to_logical(f: FieldLayout, frac: float) -> int:
    v = round(f.logical_min + min(max(frac, 0.0), 1.0) * (f.logical_max - f.logical_min))
    return int(v)


def _clamp(f: FieldLayout, v: float) -> int:
    return int(min(max(round(v), f.logical_min), f.logical_max))


#: the most reports one evemu frame becomes when its wheel counts do not fit one report
MAX_WHEEL_REPORTS = 256


class _LayoutResponder(HidResponder):
    profile: ClassVar[str] = ""
    default_rate: ClassVar[float] = 100.0
    kind = "hid"
    vid = 0x1209  # pid.codes open-source vendor ID
    options: ClassVar[dict[str, Option]] = {
        "evemu": Option(str, "", "replay this evemu recording (single-file, or .events with its .desc beside it)"),
        "report_rate": Option(float, 0.0, "report rate of the synthetic motion, Hz (0 = the device's default)", min=0.0,
                       max=8000.0),
    }

    def __init__(self, opts: Mapping[str, Any], address: str = "") -> None:
        super().__init__(opts, address)
        self.rdesc = STANDARD_DESCRIPTORS[self.profile]
        self.layout = parse_descriptor(self.rdesc, f"simhid://{self.profile}")
        self.report = next(iter(self.layout.reports.values()))
        self.rate = float(self.opts.get("report_rate") or self.default_rate)
        path = str(self.opts.get("evemu") or "")
        self.evemu_path = trace_path(path) if path else ""
        self.evemu_dev: evemu.EvemuDevice | None = None
        if path:
            self.evemu_dev = evemu.description_for(self.evemu_path)
            if self.evemu_dev is None:
                raise ConfigError(f"simhid://{self.profile}: {self.evemu_path} holds no device description"
                                  " (N:/I:/A: lines) and there is no .desc file beside it")

    def report_descriptor(self) -> bytes:
        return self.rdesc

    def _abs(self, code: int, value: int, f: FieldLayout) -> int:
        """An evdev absolute value as the field's logical value: in the recording's physical units
        when its ``A:`` line gives a resolution (counts per mm) and the field is a length, else by its
        fraction of the evdev range (a resolution of 0 says the kernel does not know the size)."""
        info = self.evemu_dev.absinfo.get(code) if self.evemu_dev else None
        if info is None:
            return _clamp(f, value)
        if info.resolution > 0 and f.unit == "m":
            return f.to_logical((value - info.minimum) / info.resolution / 1000.0)
        return _frac_to_logical(f, info.fraction(value))

    def stream(self) -> Iterator[tuple[float, bytes]]:
        if self.evemu_path:
            frames = evemu.parse_events(self.evemu_path)
            if not frames:
                return
            t0 = frames[0].t
            state = self._new_state()
            for fr in frames:
                for rep in self._frame_reports(state, fr.events):
                    yield fr.t - t0, rep
        else:
            yield from self._synthetic()

    def _new_state(self) -> dict[str, Any]:
        return {}

    def _frame_reports(self, state: dict[str, Any], events: list[tuple[int, int, int]]) -> list[bytes]:
        raise NotImplementedError

    def _synthetic(self) -> Iterator[tuple[float, bytes]]:
        raise NotImplementedError


class MouseResponder(_LayoutResponder):
    """A 1000 Hz mouse: 16 buttons, 16-bit X/Y, wheel and AC Pan with a resolution multiplier."""

    profile = "mouse"
    default_rate = 1000.0
    pid = 0x0001
    product = "perfcap simulated mouse"

    def __init__(self, opts: Mapping[str, Any], address: str = "") -> None:
        super().__init__(opts, address)
        r = self.report
        self.fx, self.fy = _field(r, GD_X), _field(r, GD_Y)
        self.fw, self.fh = _field(r, GD_WHEEL), _field(r, AC_PAN)
        self.fbuttons = [f for f in r.fields if f.usage_page == 0x09]
        self.mult_report, self.mult_field = self.layout.multipliers[0]
        self.mult_on = 0

    @property
    def multiplier(self) -> int:
        return int(self.mult_field.physical(self.mult_on))

    def set_feature(self, data: bytes) -> None:
        if data and data[0] == self.mult_report.report_id and len(data) >= self.mult_report.size:
            self.mult_on = self.mult_report.decode(data)[self.mult_field.index]

    def get_feature(self, report_id: int) -> bytes | None:
        if report_id == self.mult_report.report_id:
            return self.mult_report.encode({self.mult_field.index: self.mult_on})
        return None

    def encode(self, dx: int, dy: int, wheel: float, hwheel: float, buttons: int) -> bytes:
        """A report; wheel and hwheel in detents (sent in 1/multiplier steps)."""
        m = self.multiplier
        return self._encode_counts(dx, dy, round(wheel * m), round(hwheel * m), buttons)

    def _encode_counts(self, dx: int, dy: int, wheel: int, hwheel: int, buttons: int) -> bytes:
        vals: dict[int, int] = {self.fx.index: _clamp(self.fx, dx), self.fy.index: _clamp(self.fy, dy),
                                self.fw.index: _clamp(self.fw, wheel), self.fh.index: _clamp(self.fh, hwheel)}
        for i, f in enumerate(self.fbuttons):
            vals[f.index] = (buttons >> i) & 1
        return self.report.encode(vals)

    def _wheel_counts(self, state: dict[str, Any], key: str, units: int) -> int:
        """Counts to send for ``units`` 1/120 detents (REL_*_HI_RES units): the part that does not
        make a whole 1/multiplier step is carried to the next frame, so the sum is kept."""
        total = state[key] + units * self.multiplier  # in 1/120 counts
        counts = (total + 60) // 120
        state[key] = total - counts * 120
        return counts

    def _new_state(self) -> dict[str, Any]:
        return {"buttons": 0, "wheel_rest": 0, "hwheel_rest": 0}

    def _frame_reports(self, state: dict[str, Any], events: list[tuple[int, int, int]]) -> list[bytes]:
        """One report for a frame, more when its wheel counts do not fit the wheel fields (the
        wheels are never clipped: the sums of REL_WHEEL, or of REL_WHEEL_HI_RES when the frame has
        it, are kept across the reports)."""
        dx = dy = 0
        wheel = hwheel = 0
        hi_w: int | None = None
        hi_h: int | None = None
        for typ, code, value in events:
            if typ == evemu.EV_REL:
                if code == evemu.REL_X:
                    dx += value
                elif code == evemu.REL_Y:
                    dy += value
                elif code == evemu.REL_WHEEL:
                    wheel += value
                elif code == evemu.REL_HWHEEL:
                    hwheel += value
                elif code == evemu.REL_WHEEL_HI_RES:
                    hi_w = (hi_w or 0) + value
                elif code == evemu.REL_HWHEEL_HI_RES:
                    hi_h = (hi_h or 0) + value
            elif typ == evemu.EV_KEY and 0x110 <= code < 0x110 + len(self.fbuttons):
                bit = 1 << (code - 0x110)
                state["buttons"] = state["buttons"] | bit if value else state["buttons"] & ~bit
        w = self._wheel_counts(state, "wheel_rest", hi_w if hi_w is not None else wheel * 120)
        h = self._wheel_counts(state, "hwheel_rest", hi_h if hi_h is not None else hwheel * 120)
        out = []
        for _ in range(MAX_WHEEL_REPORTS):
            cw, ch = _clamp(self.fw, w), _clamp(self.fh, h)
            out.append(self._encode_counts(dx, dy, cw, ch, state["buttons"]))
            w, h, dx, dy = w - cw, h - ch, 0, 0
            if (not w and not h) or (not cw and not ch):
                break
        # what did not fit in MAX_WHEEL_REPORTS reports is sent with the next frame, not dropped
        state["wheel_rest"] += w * 120
        state["hwheel_rest"] += h * 120
        return out

    def _synthetic(self) -> Iterator[tuple[float, bytes]]:
        rng = self.rng
        period = 1.0 / self.rate
        ph = rng.uniform(0, 2 * math.pi, 2)
        f = rng.uniform(0.3, 1.5, 2)
        speed = rng.uniform(2000, 6000)  # counts per second
        rx = ry = 0.0
        buttons = 0
        k = 0
        while True:
            t = k * period
            vx = speed * math.cos(2 * math.pi * f[0] * t + ph[0])
            vy = speed * math.sin(2 * math.pi * f[1] * t + ph[1])
            rx += vx * period
            ry += vy * period
            dx, dy = round(rx), round(ry)
            rx -= dx
            ry -= dy
            wheel = 1.0 / 8 if k % 97 == 0 else 0.0
            if k % 500 == 0:
                buttons ^= 1
            yield t, self.encode(dx, dy, wheel, 0.0, buttons)
            k += 1


class PenResponder(_LayoutResponder):
    """A Wacom-like pen: X/Y over 223.52 x 139.70 mm, pressure 0..2047, tilt +-64 deg, switches."""

    profile = "pen"
    default_rate = 200.0
    pid = 0x0002
    product = "perfcap simulated pen"

    def __init__(self, opts: Mapping[str, Any], address: str = "") -> None:
        super().__init__(opts, address)
        r = self.report
        self.f = {k: _field(r, u) for k, u in (("x", GD_X), ("y", GD_Y), ("pressure", DIG_TIP_PRESSURE),
                                                ("tilt_x", DIG_X_TILT), ("tilt_y", DIG_Y_TILT),
                                                ("in_range", DIG_IN_RANGE), ("tip", DIG_TIP_SWITCH),
                                                ("barrel", DIG_BARREL), ("eraser", DIG_ERASER),
                                                ("invert", DIG_INVERT))}

    def encode(self, logical: Mapping[str, int]) -> bytes:
        return self.report.encode({self.f[k].index: v for k, v in logical.items()})

    def _new_state(self) -> dict[str, Any]:
        return dict.fromkeys(self.f, 0)

    def _frame_reports(self, state: dict[str, Any], events: list[tuple[int, int, int]]) -> list[bytes]:
        axes = {evemu.ABS_X: "x", evemu.ABS_Y: "y", evemu.ABS_PRESSURE: "pressure", evemu.ABS_TILT_X: "tilt_x",
                evemu.ABS_TILT_Y: "tilt_y"}
        keys = {evemu.BTN_TOUCH: "tip", evemu.BTN_STYLUS: "barrel"}
        for typ, code, value in events:
            if typ == evemu.EV_ABS and code in axes:
                k = axes[code]
                state[k] = self._abs(code, value, self.f[k])
            elif typ == evemu.EV_KEY:
                if code in keys:
                    state[keys[code]] = 1 if value else 0
                elif code in (evemu.BTN_TOOL_PEN, evemu.BTN_TOOL_RUBBER):
                    state["in_range"] = 1 if value else 0
                    rubber = 1 if value and code == evemu.BTN_TOOL_RUBBER else 0
                    state["invert"] = rubber
        state["eraser"] = state["invert"] & state["tip"]
        return [self.encode(state)]

    def _synthetic(self) -> Iterator[tuple[float, bytes]]:
        rng = self.rng
        period = 1.0 / self.rate
        fx, fy = self.f["x"], self.f["y"]
        cx, cy = rng.uniform(0.3, 0.7), rng.uniform(0.3, 0.7)
        w = 2 * math.pi * rng.uniform(0.3, 1.0)
        k = 0
        while True:
            t = k * period
            touching = math.sin(2 * math.pi * 0.25 * t) > -0.3
            x = cx + 0.2 * math.cos(w * t)
            y = cy + 0.2 * math.sin(w * t)
            p = max(0.0, math.sin(2 * math.pi * 0.5 * t)) if touching else 0.0
            yield t, self.encode({
                "x": _frac_to_logical(fx, x), "y": _frac_to_logical(fy, y),
                "pressure": _frac_to_logical(self.f["pressure"], p),
                "tilt_x": _clamp(self.f["tilt_x"], 30 * math.sin(w * t)),
                "tilt_y": _clamp(self.f["tilt_y"], 20 * math.cos(w * t)),
                "in_range": 1, "tip": int(touching and p > 0), "barrel": int(k % 400 < 20)})
            k += 1


class TouchResponder(_LayoutResponder):
    """A touch screen: 2 contacts per report, contact count (hybrid mode for more contacts)."""

    profile = "touch"
    default_rate = 100.0
    pid = 0x0003
    product = "perfcap simulated touch screen"

    def __init__(self, opts: Mapping[str, Any], address: str = "") -> None:
        super().__init__(opts, address)
        r = self.report
        self.slots = [{k: _field(r, u, i) for k, u in (("tip", DIG_TIP_SWITCH), ("confidence", DIG_CONFIDENCE),
                                                       ("id", DIG_CONTACT_ID), ("x", GD_X), ("y", GD_Y),
                                                       ("w", DIG_WIDTH), ("h", DIG_HEIGHT))}
                      for i in range(len(_fields(r, GD_X)))]
        self.fcount = _field(r, DIG_CONTACT_COUNT)

    def encode_contacts(self, contacts: list[dict[str, int]]) -> list[bytes]:
        """Reports for contacts given as logical values (keys tip, id, x, y, w, h), hybrid mode
        when there are more contacts than slots: the count in the first report, 0 in the others."""
        out = []
        n = len(self.slots)
        for start in range(0, max(len(contacts), 1), n):
            vals: dict[int, int] = {self.fcount.index: len(contacts) if start == 0 else 0}
            for slot, c in zip(self.slots, contacts[start:start + n], strict=False):
                vals[slot["confidence"].index] = 1
                for k, v in c.items():
                    vals[slot[k].index] = v
            out.append(self.report.encode(vals))
        return out

    def _new_state(self) -> dict[str, Any]:
        return {"slot": 0, "slots": {}}

    def _frame_reports(self, state: dict[str, Any], events: list[tuple[int, int, int]]) -> list[bytes]:
        slots: dict[int, dict[str, Any]] = state["slots"]
        f0 = self.slots[0]
        axes = {evemu.ABS_MT_POSITION_X: ("x", f0["x"]), evemu.ABS_MT_POSITION_Y: ("y", f0["y"]),
                evemu.ABS_MT_TOUCH_MAJOR: ("w", f0["w"]), evemu.ABS_MT_TOUCH_MINOR: ("h", f0["h"])}
        for typ, code, value in events:
            if typ != evemu.EV_ABS:
                continue
            if code == evemu.ABS_MT_SLOT:
                state["slot"] = value
                continue
            s = slots.setdefault(state["slot"], {"tracking": -1, "x": 0, "y": 0, "w": 0, "h": 0, "ended": False})
            if code == evemu.ABS_MT_TRACKING_ID:
                if value < 0 and s["tracking"] >= 0:
                    s["ended"] = True
                s["tracking"] = value
            elif code in axes:
                k, f = axes[code]
                s[k] = self._abs(code, value, f)
        contacts = []
        for sid in sorted(slots):
            s = slots[sid]
            if s["tracking"] >= 0 or s["ended"]:
                contacts.append({"tip": 1 if s["tracking"] >= 0 else 0, "id": sid % 16, "x": s["x"], "y": s["y"],
                                 "w": s["w"], "h": s["h"]})
                s["ended"] = False
        if not contacts:
            return []
        return self.encode_contacts(contacts)

    def _synthetic(self) -> Iterator[tuple[float, bytes]]:
        rng = self.rng
        period = 1.0 / self.rate
        fx, fy = self.slots[0]["x"], self.slots[0]["y"]
        w = 2 * math.pi * rng.uniform(0.3, 1.0)
        k = 0
        while True:
            t = k * period
            contacts = []
            for i in range(2):
                a = w * t + i * math.pi
                contacts.append({"tip": 1, "id": i, "x": _frac_to_logical(fx, 0.5 + 0.2 * math.cos(a)),
                                 "y": _frac_to_logical(fy, 0.5 + 0.2 * math.sin(a)), "w": 100, "h": 100})
            for rep in self.encode_contacts(contacts):
                yield t, rep
            k += 1


def _fields(rep: ReportLayout, usage: int) -> list[FieldLayout]:
    return [f for f in rep.fields if f.usage == usage and not f.is_array]
