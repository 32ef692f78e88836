"""``hid``: any HID mouse, pen digitizer or touch digitizer, decoded from its report descriptor.

The streams depend on what the descriptor describes (``devices.hid.descriptor.classify``):

* mouse -> ``<name>/pointer`` (dx, dy in counts; wheel, hwheel in detents: with a Resolution
  Multiplier the handshake sets it to its maximum, as Linux does, and a wheel count is then
  ``1/multiplier`` detent) and ``<name>/buttons`` (one 0/1 channel per button);
* pen -> ``<name>/pen``: x, y (m, or 0..1 of the surface when the descriptor gives no physical
  size), pressure 0..1, tilt_x, tilt_y (deg), in_range, tip, barrel, eraser;
* touch -> ``<name>/touch``: one reading per reported contact: contact_id, tip, x, y, width, height
  (m or 0..1), contact_count (hybrid mode - the count in the first of several reports - handled).

Streams are declared before opening, so the descriptor is needed up front: the ``rdesc`` option
(hex), else the transport's ``report_descriptor()`` if it answers before open (simulators do),
else the standard layout of ``profile``. The handshake reads the real descriptor and fails if it
would change the declared streams. These devices have no clock, and they report when something
changes, not at a fixed rate: by default a reading's bus time is its report's arrival (no rate is
declared, so no counter grid is fitted to reports that pause and resume). ``rate=HZ`` declares a
device that does report at a fixed rate (a pen polled while in range, say): its arrivals are then
dejittered on that rate's grid, re-anchored at every pause.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any, ClassVar

from capture.errors import CaptureError, ConfigError, DeviceInitError
from devices.base import Reading
from devices.hid.base import HidDevice
from devices.hid.descriptor import (
    AC_PAN,
    BUTTON_PAGE,
    DIG_BARREL,
    DIG_CONTACT_COUNT,
    DIG_CONTACT_ID,
    DIG_DIGITIZER,
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
    MOUSE_APPS,
    PEN_APPS,
    STANDARD_DESCRIPTORS,
    TOUCH_APPS,
    DescriptorLayout,
    FieldLayout,
    HidReportCodec,
    ReportLayout,
    parse_descriptor,
)
from devices.options import Option
from devices.transports.hid import HidTransportBase

if TYPE_CHECKING:
    from capture.sample import StreamInfo

log = logging.getLogger(__name__)

NAN = math.nan
Plan = Callable[[list[Any]], list[Reading]]


def _idx(fields: list[FieldLayout], usage: int) -> int | None:
    for f in fields:
        if f.usage == usage and not f.is_array:
            return f.index
    return None


class _HidCodec(HidReportCodec):
    """``HidReportCodec`` that also tells its device the ID of each report its descriptor lacks (a
    framing error, as before, and an undecoded report of the device, counted per ID)."""

    def __init__(self, strict: bool = False) -> None:
        super().__init__(strict)
        self.on_unknown: Callable[[int], None] | None = None

    def feed(self, data: bytes) -> list[Any]:
        out = super().feed(data)
        if not out and data and self.on_unknown is not None and self.layout is not None \
                and self.layout.report_for(data) is None:
            self.on_unknown(data[0])
        return out


class GenericHid(HidDevice[_HidCodec]):
    """A HID mouse, pen or touch digitizer, decoded from its report descriptor.

    A report whose ID the descriptor lacks, or that holds none of the mouse, pen or touch fields
    published (a vendor report: a Wacom sends its pen in one), gives no reading: each is counted
    per ID in ``stats.undecoded`` and the first of each ID logged."""

    kind = "hid"
    description = "HID mouse, pen or touch digitizer (descriptor-driven)"
    codec_cls = _HidCodec
    codec: _HidCodec
    options: ClassVar[dict[str, Option]] = {
        "rdesc": Option(str, "", "the report descriptor as hex (else asked of the transport before open)"),
        "profile": Option(str, "auto", "which part to publish; with no descriptor known before open, the"
                          " standard layout to assume", choices=("auto", "mouse", "pen", "touch")),
        "rate": Option(float, 0.0, "fixed report rate, Hz, to dejitter arrivals on (0 = event-driven: each"
                       " reading stamped at its report's arrival)", min=0.0, max=100_000.0),
    }

    # -- the descriptor before open ------------------------------------------------------------------
    def _initial_descriptor(self) -> tuple[bytes, str]:
        hx = self.opts["rdesc"].strip()
        if hx:
            try:
                return bytes.fromhex(hx.replace(":", "").replace(" ", "")), "option rdesc"
            except ValueError:
                raise ConfigError(f"device {self.name} (hid): option rdesc is not hex bytes", source=self.name) \
                    from None
        t = self.transport
        if isinstance(t, HidTransportBase):  # live devices, simulators and replays all give it before open
            try:
                data = bytes(t.report_descriptor())
            except CaptureError as exc:
                log.info("device %s: report descriptor not available before open (%s); using the profile",
                         self.name, exc)
                data = b""
            if data:
                return data, f"{t.url}"
        profile = self.opts["profile"]
        if profile == "auto":
            profile = "mouse"
            log.warning("device %s (hid): no report descriptor before open and profile=auto: assuming a standard"
                        " mouse; give rdesc=HEX or profile=mouse|pen|touch", self.name)
        return STANDARD_DESCRIPTORS[profile], f"standard {profile} layout"

    def _classes(self, layout: DescriptorLayout, source: str) -> tuple[str, ...]:
        profile = self.opts["profile"]
        if profile != "auto":
            if profile not in layout.classes:
                raise ConfigError(f"device {self.name} (hid): profile={profile} but the report descriptor"
                                  f" ({source}) describes {', '.join(layout.classes) or 'no mouse, pen or touch'}",
                                  source=self.name)
            return (profile,)
        if not layout.classes:
            raise ConfigError(f"device {self.name} (hid): the report descriptor ({source}) describes no mouse, pen"
                              " or touch surface (applications: "
                              + ", ".join(f"0x{a:08x}" for a in layout.applications) + ")", source=self.name)
        return layout.classes

    def declare_streams(self) -> list[StreamInfo]:
        data, source = self._initial_descriptor()
        layout = parse_descriptor(data, f"device {self.name} (hid): {source}")
        return self._use_layout(layout, source)

    def _use_layout(self, layout: DescriptorLayout, source: str) -> list[StreamInfo]:
        classes = self._classes(layout, source)
        self.layout = layout
        self.codec.set_layout(layout)
        self.codec.on_unknown = self._undecoded_report
        self._multiplier = layout.wheel_multiplier()
        streams: list[StreamInfo] = []
        self._plans: dict[int | None, list[Plan]] = {}
        for cls in classes:
            getattr(self, f"_declare_{cls}")(layout, streams, self.opts["rate"] or None)
        return streams

    # -- mouse ---------------------------------------------------------------------------------------
    def _declare_mouse(self, layout: DescriptorLayout, streams: list[StreamInfo], rate: float | None) -> None:
        reports = [r for r in layout.reports.values() if any(f.application in MOUSE_APPS for f in r.fields)]
        nbuttons = 0
        for r in reports:
            for f in r.fields:
                if f.application in MOUSE_APPS and f.usage_page == BUTTON_PAGE:
                    nbuttons = max([nbuttons, *((u & 0xFFFF) for u in (f.usages if f.is_array else (f.usage,)))])
        mult = self._multiplier
        si = len(streams)
        streams.append(self.stream_info("pointer", "pointer", ("dx", "dy", "wheel", "hwheel"),
                                        ("count", "count", "detent", "detent"), rate,
                                        quantum=(1.0, 1.0, 1.0 / mult, 1.0 / mult)))
        bi = len(streams)
        streams.append(self.stream_info("buttons", "buttons", tuple(f"b{i}" for i in range(1, nbuttons + 1)),
                                        ("1",) * nbuttons, rate, quantum=(1.0,) * nbuttons))
        multiplied = {f.collection for _, f in layout.multipliers}
        for r in reports:
            mf = [f for f in r.fields if f.application in MOUSE_APPS]
            ix, iy, iw, ih = (_idx(mf, u) for u in (GD_X, GD_Y, GD_WHEEL, AC_PAN))
            if ix is None and iy is None and iw is None and ih is None and not any(
                    f.usage_page == BUTTON_PAGE for f in mf):
                continue
            wdiv = {i: (mult if r.fields[i].collection in multiplied else 1.0) for i in (iw, ih) if i is not None}
            bvars = [(f.index, (f.usage & 0xFFFF) - 1) for f in mf
                     if f.usage_page == BUTTON_PAGE and not f.is_array]
            barrs = [(f.index, f.usages, f.logical_min) for f in mf if f.usage_page == BUTTON_PAGE and f.is_array]
            self._plans.setdefault(r.report_id, []).append(
                self._mouse_plan(si, bi, nbuttons, ix, iy, iw, ih, wdiv, bvars, barrs))

    def _mouse_plan(self, si: int, bi: int, nb: int, ix: int | None, iy: int | None, iw: int | None,
                    ih: int | None, wdiv: dict[int, float], bvars: list[tuple[int, int]],
                    barrs: list[tuple[int, tuple[int, ...], int]]) -> Plan:
        def plan(v: list[Any]) -> list[Reading]:
            ptr = (float(v[ix]) if ix is not None else 0.0, float(v[iy]) if iy is not None else 0.0,
                   v[iw] / wdiv[iw] if iw is not None else 0.0, v[ih] / wdiv[ih] if ih is not None else 0.0)
            out = [Reading(si, ptr)]
            if nb:
                b = [0.0] * nb
                for i, n in bvars:
                    if v[i]:
                        b[n] = 1.0
                for i, usages, lmin in barrs:
                    for x in v[i]:
                        k = x - lmin
                        if 0 <= k < len(usages) and 0 < (usages[k] & 0xFFFF) <= nb:
                            b[(usages[k] & 0xFFFF) - 1] = 1.0
                out.append(Reading(bi, tuple(b)))
            return out
        return plan

    # -- pen -----------------------------------------------------------------------------------------
    def _declare_pen(self, layout: DescriptorLayout, streams: list[StreamInfo], rate: float | None) -> None:
        si = len(streams)
        unit_xy = "1"
        plans: list[tuple[int | None, Plan]] = []
        for r in layout.reports.values():
            pf = [f for f in r.fields if f.application in PEN_APPS or f.application == DIG_DIGITIZER]
            ix = _idx(pf, GD_X)
            if ix is None:
                continue
            f = r.fields[ix]
            if f.unit == "m":
                unit_xy = "m"
            plans.append((r.report_id, self._pen_plan(si, r, pf)))
        streams.append(self.stream_info(
            "pen", "pen", ("x", "y", "pressure", "tilt_x", "tilt_y", "in_range", "tip", "barrel", "eraser"),
            (unit_xy, unit_xy, "1", "deg", "deg", "1", "1", "1", "1"), rate))
        for rid, p in plans:
            self._plans.setdefault(rid, []).append(p)

    def _pen_plan(self, si: int, r: ReportLayout, pf: list[FieldLayout]) -> Plan:
        fields = r.fields

        def conv(usage: int, how: str) -> Callable[[list[Any]], float]:
            i = _idx(pf, usage)
            if i is None:
                return lambda v: NAN
            f = fields[i]
            if (how == "pos" and f.unit != "m") or how == "norm":
                return lambda v: f.normalised(v[i])
            if how == "bool":
                return lambda v: 1.0 if v[i] else 0.0
            return lambda v: f.physical(v[i])

        eraser = DIG_ERASER if _idx(pf, DIG_ERASER) is not None else DIG_INVERT
        convs = [conv(GD_X, "pos"), conv(GD_Y, "pos"), conv(DIG_TIP_PRESSURE, "norm"), conv(DIG_X_TILT, "phys"),
                 conv(DIG_Y_TILT, "phys"), conv(DIG_IN_RANGE, "bool"), conv(DIG_TIP_SWITCH, "bool"),
                 conv(DIG_BARREL, "bool"), conv(eraser, "bool")]

        def plan(v: list[Any]) -> list[Reading]:
            return [Reading(si, tuple(c(v) for c in convs))]
        return plan

    # -- touch ---------------------------------------------------------------------------------------
    def _declare_touch(self, layout: DescriptorLayout, streams: list[StreamInfo], rate: float | None) -> None:
        si = len(streams)
        unit_xy = "1"
        for r in layout.reports.values():
            tf = [f for f in r.fields if f.application in TOUCH_APPS]
            groups: dict[tuple[int, int, int], list[FieldLayout]] = {}
            for f in tf:
                if f.usage in (DIG_TIP_SWITCH, DIG_CONTACT_ID, GD_X, GD_Y, DIG_WIDTH, DIG_HEIGHT):
                    groups.setdefault(f.collection, []).append(f)
            contacts = [g for g in groups.values() if _idx(g, GD_X) is not None]
            if not contacts:
                continue
            if any(r.fields[ix].unit == "m" for g in contacts if (ix := _idx(g, GD_X)) is not None):
                unit_xy = "m"
            icount = _idx(tf, DIG_CONTACT_COUNT)
            self._plans.setdefault(r.report_id, []).append(self._touch_plan(si, r, contacts, icount))
        self._touch_left = 0
        streams.append(self.stream_info("touch", "touch", ("contact_id", "tip", "x", "y", "width", "height",
                                                           "contact_count"),
                                        ("1", "1", unit_xy, unit_xy, unit_xy, unit_xy, "1"), rate))

    def _touch_plan(self, si: int, r: ReportLayout, contacts: list[list[FieldLayout]], icount: int | None) -> Plan:
        fields = r.fields
        slots = []
        for g in contacts:
            def get(usage: int, g: list[FieldLayout] = g) -> tuple[int, FieldLayout] | None:
                i = _idx(g, usage)
                return None if i is None else (i, fields[i])
            slots.append(tuple(get(u) for u in (DIG_CONTACT_ID, DIG_TIP_SWITCH, GD_X, GD_Y, DIG_WIDTH, DIG_HEIGHT)))
        nslots = len(slots)

        def val(v: list[Any], spec: tuple[int, FieldLayout] | None, pos: bool) -> float:
            if spec is None:
                return NAN
            i, f = spec
            if not pos:
                return float(v[i])
            return f.physical(v[i]) if f.unit == "m" else f.normalised(v[i])

        def plan(v: list[Any]) -> list[Reading]:
            if icount is not None:
                cc = v[icount]
                if cc > 0:
                    self._touch_left = cc
                n = min(self._touch_left, nslots)
                self._touch_left -= n
                total = float(cc if cc > 0 else n)
                use = slots[:n]
            else:
                use = [s for s in slots if s[1] is None or v[s[1][0]]]
                total = float(len(use))
            return [Reading(si, (val(v, s[0], False), 1.0 if s[1] is None else float(bool(v[s[1][0]])),
                                 val(v, s[2], True), val(v, s[3], True), val(v, s[4], True), val(v, s[5], True),
                                 total)) for s in use]
        return plan

    # -- life cycle ----------------------------------------------------------------------------------
    def handshake(self) -> None:
        rd = self.hid_report_descriptor()
        if rd != self.layout.rdesc:
            new = parse_descriptor(rd, f"device {self.name} (hid): {self.transport.url}")
            old = [(s.name, s.channels, s.units) for s in self.streams]
            keep_layout, keep_plans, keep_mult = self.layout, self._plans, self._multiplier
            streams = self._use_layout(new, self.transport.url)
            if [(s.name, s.channels, s.units) for s in streams] != old:
                self.layout, self._plans, self._multiplier = keep_layout, keep_plans, keep_mult
                self.codec.set_layout(keep_layout)
                raise DeviceInitError(
                    f"device {self.name} (hid): its report descriptor gives other streams than were declared"
                    f" before open ({[s.channels for s in streams]} vs {[c for _, c, _ in old]}); pass its"
                    f" descriptor as rdesc={rd.hex()}", source=self.transport.url)
        for data in self.layout.multiplier_reports():
            try:
                self.hid_set_feature(data)
            except CaptureError as exc:
                log.warning("device %s (hid): cannot set the wheel resolution multiplier (%s); wheel values"
                            " may be %g times too small", self.name, exc, self._multiplier)

    def frame_to_readings(self, frame: Any) -> Iterable[Reading]:
        rep, values = frame
        plans = self._plans.get(rep.report_id)
        if not plans:
            self._undecoded_report(rep.report_id)
            return []
        out: list[Reading] = []
        for plan in plans:
            out += plan(values)
        return out

    def _undecoded_report(self, report_id: int | None) -> None:
        self._undecoded("a report without ID" if report_id is None else f"report 0x{report_id:02x}")
