"""HID report descriptors -> field layouts; a fast decoder and its inverse, the encoder.

The descriptor is parsed by ``hid-tools`` (``hidtools.hid.ReportDescriptor``), within the bounds
of ``devices.hid.bounds`` (checked on its items before hid-tools lays them out); this module turns
what it finds into a flat ``ReportLayout`` per input report ID (bit offset, size, signedness,
logical and physical range, unit -> SI scale) once, and then decodes reports itself: one report
with ``ReportLayout.decode`` (plain integer arithmetic), many at once with ``decode_many`` (numpy).
``ReportLayout.encode`` is the exact inverse, used by simulators.

Physical values follow the HID spec: ``physical = pmin + (logical - lmin) * (pmax - pmin) /
(lmax - lmin)``, times ``10**unit_exponent`` and the unit's SI factor (cm and inch -> m, radians
-> degrees, degrees stay degrees). A field without a physical range has scale 1 in ``count``.

``classify`` names what a descriptor describes from its application collections: ``mouse``
(Generic Desktop Mouse or Pointer), ``pen`` (Digitizer Pen, or a Digitizer application with X and Y), ``touch``
(Digitizer Touch Screen or Touch Pad). ``STANDARD_DESCRIPTORS`` holds a standard-conformant
descriptor for each, used when a device's own descriptor is not known before opening.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from capture.errors import ConfigError
from devices.codecs.base import Codec
from devices.hid.bounds import HID_MAX_DESCRIPTOR_SIZE, MAX_DATA_FIELD_BITS, check_items

log = logging.getLogger(__name__)

# -- usages (page << 16 | id) ------------------------------------------------------------------------
GD = 0x01 << 16
BUTTON_PAGE = 0x09
DIGITIZER = 0x0D << 16
CONSUMER = 0x0C << 16

GD_POINTER, GD_MOUSE = GD | 0x01, GD | 0x02
GD_X, GD_Y, GD_WHEEL = GD | 0x30, GD | 0x31, GD | 0x38
GD_RES_MULTIPLIER = GD | 0x48
AC_PAN = CONSUMER | 0x0238
DIG_DIGITIZER, DIG_PEN, DIG_TOUCH_SCREEN, DIG_TOUCH_PAD = (DIGITIZER | u for u in (0x01, 0x02, 0x04, 0x05))
DIG_STYLUS, DIG_FINGER = DIGITIZER | 0x20, DIGITIZER | 0x22
DIG_TIP_PRESSURE, DIG_IN_RANGE, DIG_TOUCH = DIGITIZER | 0x30, DIGITIZER | 0x32, DIGITIZER | 0x33
DIG_X_TILT, DIG_Y_TILT = DIGITIZER | 0x3D, DIGITIZER | 0x3E
DIG_TIP_SWITCH, DIG_SECONDARY_TIP, DIG_BARREL = DIGITIZER | 0x42, DIGITIZER | 0x43, DIGITIZER | 0x44
DIG_INVERT, DIG_ERASER = DIGITIZER | 0x3C, DIGITIZER | 0x45
DIG_CONFIDENCE, DIG_WIDTH, DIG_HEIGHT = DIGITIZER | 0x47, DIGITIZER | 0x48, DIGITIZER | 0x49
DIG_CONTACT_ID, DIG_CONTACT_COUNT, DIG_CONTACT_MAX = DIGITIZER | 0x51, DIGITIZER | 0x54, DIGITIZER | 0x55

MOUSE_APPS = (GD_MOUSE, GD_POINTER)
PEN_APPS = (DIG_PEN,)
TOUCH_APPS = (DIG_TOUCH_SCREEN, DIG_TOUCH_PAD)
CLASSES = ("mouse", "pen", "touch")

_LENGTH_TO_M = {"cm": 0.01, "in": 0.0254}
_ANGLE_TO_DEG = {"deg": 1.0, "rad": 180.0 / np.pi}


def usage_name(usage: int) -> str:
    """A readable usage name from hid-tools' usage tables (``B3`` for buttons, hex if unknown)."""
    import hidtools.hid as hh

    f = hh.HidField(0, None, None, None, None, 0, usage & 0xFFFF0000, usage, 0, 0, 0, 0, 0, 0, 1, 1)
    return f.usage_name


def _unit(unit_value: int, exponent: int) -> tuple[str, float]:
    """A HID unit code and exponent -> (SI-ish unit name, factor to it); ``("", 1)`` for no unit."""
    import hidtools.hid as hh

    if not unit_value:
        return "", 1.0
    try:
        u = hh.HidUnit.from_value(unit_value)
    except Exception:  # hid-tools chokes on some codes (after Push it can pass negatives)
        return f"unit 0x{unit_value & 0xFFFFFFFF:x}", 10.0 ** exponent
    if u is None:
        return "", 1.0
    pow10 = 10.0 ** exponent
    units = {k.value if k is not None else "?": e for k, e in u.units.items()}
    if len(units) == 1:
        (name, e), = units.items()
        if e == 1 and name in _LENGTH_TO_M:
            return "m", pow10 * _LENGTH_TO_M[name]
        if e == 1 and name in _ANGLE_TO_DEG:
            return "deg", pow10 * _ANGLE_TO_DEG[name]
        if e == 1 and name == "s":
            return "s", pow10
    return "*".join(f"{n}^{e}" if e != 1 else n for n, e in units.items()), pow10


@dataclass(frozen=True)
class FieldLayout:
    """One field of a report: a variable (``count == 1``) or an array of ``count`` usage indices."""

    index: int
    usage: int  # page << 16 | id (for arrays: the collection's usage)
    name: str
    bit: int  # offset from the first byte of the report as delivered (report ID included)
    size: int
    count: int
    signed: bool
    logical_min: int
    logical_max: int
    physical_min: float
    physical_max: float
    unit: str  # "m", "deg", "s", "count", or a composite
    scale: float  # physical = (logical - logical_min) * scale + offset
    offset: float
    is_array: bool
    relative: bool
    usages: tuple[int, ...] = ()  # array: the usage of each index from logical_min on
    application: int = 0
    collection: tuple[int, int, int] = (0, 0, 0)  # hid-tools' (application, physical, logical) counters
    logical_usage: int = 0  # usage of the enclosing logical collection (Finger, Stylus), 0 if none

    @property
    def usage_page(self) -> int:
        return self.usage >> 16

    def physical(self, logical: float) -> float:
        return (logical - self.logical_min) * self.scale + self.offset

    def to_logical(self, physical: float) -> int:
        """The logical value nearest to ``physical``, clamped to the logical range."""
        v = round((physical - self.offset) / self.scale + self.logical_min) if self.scale else self.logical_min
        return int(min(max(v, self.logical_min), self.logical_max))

    def normalised(self, logical: float) -> float:
        span = self.logical_max - self.logical_min
        return (logical - self.logical_min) / span if span else 0.0


@dataclass
class ReportLayout:
    """The fields of one input report. ``report_id`` is ``None`` when the descriptor has no IDs."""

    report_id: int | None
    size: int  # bytes as delivered, report ID included
    application: int
    fields: list[FieldLayout]

    def __post_init__(self) -> None:
        self._plan = [(f.bit, f.size, (1 << f.size) - 1, f.signed, f.count) for f in self.fields]

    def find(self, usage: int, application: Iterable[int] | None = None) -> list[FieldLayout]:
        apps = tuple(application) if application is not None else None
        return [f for f in self.fields if f.usage == usage and not f.is_array
                and (apps is None or f.application in apps)]

    def decode(self, report: bytes) -> list[Any]:
        """Logical values of every field (an array field gives a tuple of its ``count`` entries).
        ``report`` must be at least ``size`` bytes (checked by the caller)."""
        big = int.from_bytes(report[:self.size], "little")
        out: list[Any] = []
        for bit, size, mask, signed, count in self._plan:
            if count == 1:
                v = (big >> bit) & mask
                if signed and size > 1 and v >> (size - 1):
                    v -= 1 << size
                out.append(v)
            else:
                vals = []
                for i in range(count):
                    v = (big >> (bit + i * size)) & mask
                    if signed and size > 1 and v >> (size - 1):
                        v -= 1 << size
                    vals.append(v)
                out.append(tuple(vals))
        return out

    def decode_many(self, reports: np.ndarray, indices: Sequence[int] | None = None) -> np.ndarray:
        """Logical values of the variable fields ``indices`` (default: all variables) for an
        ``(n, >=size)`` uint8 array of reports, as an ``(n, len(indices))`` int64 array."""
        a = np.asarray(reports, np.uint8)
        idx = [f.index for f in self.fields if f.count == 1] if indices is None else list(indices)
        out = np.empty((a.shape[0], len(idx)), np.int64)
        for j, i in enumerate(idx):
            f = self.fields[i]
            b0, b1 = f.bit // 8, (f.bit + f.size - 1) // 8 + 1
            v = np.zeros(a.shape[0], np.uint64)
            for k, b in enumerate(range(b0, b1)):
                v |= a[:, b].astype(np.uint64) << np.uint64(8 * k)
            v = (v >> np.uint64(f.bit - 8 * b0)) & np.uint64((1 << f.size) - 1)
            s = v.astype(np.int64)
            if f.signed and f.size > 1:
                s = np.where(s >= (1 << (f.size - 1)), s - (1 << f.size), s)
            out[:, j] = s
        return out

    def encode(self, values: Mapping[int, int | Sequence[int]]) -> bytes:
        """A report from logical values by field index (others 0, arrays padded with 0); the
        inverse of ``decode``. Values are masked to the field size."""
        big = 0
        for f in self.fields:
            v: Any = values.get(f.index, 0)
            vals = [v] if f.count == 1 else list(v if isinstance(v, (tuple, list)) else [v])
            for i, x in enumerate(vals[:f.count]):
                big |= (int(x) & ((1 << f.size) - 1)) << (f.bit + i * f.size)
        data = bytearray(big.to_bytes(self.size, "little"))
        if self.report_id is not None:
            data[0] = self.report_id
        return bytes(data)


@dataclass
class DescriptorLayout:
    """Every input report of a descriptor, its classes, and what the host can set (resolution
    multipliers, in feature reports)."""

    rdesc: bytes
    reports: dict[int | None, ReportLayout]
    applications: tuple[int, ...]
    classes: tuple[str, ...]
    #: feature report layout and the multiplier fields in it: (report, field) pairs
    multipliers: list[tuple[ReportLayout, FieldLayout]] = field(default_factory=list)

    @property
    def numbered(self) -> bool:
        return None not in self.reports

    def report_for(self, data: bytes) -> ReportLayout | None:
        if not data:
            return None
        return self.reports.get(data[0] if self.numbered else None)

    def wheel_multiplier(self) -> float:
        """Counts per detent of the wheel once the host sets every multiplier to its maximum."""
        m = 1.0
        for _, f in self.multipliers:
            m = max(m, f.physical(f.logical_max))
        return m

    def multiplier_reports(self) -> list[bytes]:
        """Feature reports that set every resolution multiplier to its maximum (what Linux does)."""
        by: dict[int | None, tuple[ReportLayout, dict[int, int]]] = {}
        for rep, f in self.multipliers:
            by.setdefault(rep.report_id, (rep, {}))[1][f.index] = f.logical_max
        out = []
        for rid, (rep, vals) in by.items():
            data = rep.encode(vals)
            out.append(data if rid is not None else b"\x00" + data)
        return out


def _collection(c: Any) -> tuple[int, int, int]:
    """hid-tools' (application, physical, logical) collection counters of a field as ints."""
    a, p, lg = (int(x) for x in (c or (0, 0, 0)))
    return a, p, lg


def _layout_of(report: Any, *, with_id: bool) -> ReportLayout:
    fields: list[FieldLayout] = []
    for f in report.fields:
        if f.is_const:  # padding and constant bits
            continue
        if not f.is_array and int(f.size) > MAX_DATA_FIELD_BITS:
            # a Variable item without usages, merged by hid-tools into one field of Report Size x
            # Report Count bits: padding to Linux (a field without usages is ignored), so here too
            log.debug("%d bits without a usage at bit %d laid out as padding", int(f.size), int(f.start))
            continue
        lmin, lmax = int(f.logical_min), int(f.logical_max)
        pmin, pmax = int(f.physical_min), int(f.physical_max)
        exp = int(f.unit_exp or 0)
        unit, factor = _unit(int(f.unit or 0), exp)
        if pmin == 0 and pmax == 0:
            pmin, pmax = lmin, lmax  # the spec: no physical range means physical = logical
            if not unit:
                factor = 1.0
        span = lmax - lmin
        scale = (pmax - pmin) / span * factor if span else factor
        is_array = bool(f.is_array)
        usages = tuple(int(u) for u in (f.usages or ())) if is_array else ()
        usage = int(f.usage)
        fields.append(FieldLayout(
            index=len(fields), usage=usage, name=f.usage_name if not is_array else f"{f.usage_name}[]",
            bit=int(f.start), size=int(f.size), count=int(f.count), signed=lmin < 0,
            logical_min=lmin, logical_max=lmax, physical_min=pmin * factor, physical_max=pmax * factor,
            unit=unit or "count", scale=scale, offset=pmin * factor, is_array=is_array,
            relative=bool(int(f.type) & 0x04), usages=usages, application=int(f.application or 0),
            collection=_collection(f.collection),
            logical_usage=int(f.logical or 0)))
    rid = int(report.report_ID)
    numbered = rid >= 0
    size = (int(report.bitsize) + 7) // 8
    return ReportLayout(rid if numbered else None, size, int(report.application or 0), fields)


def parse_descriptor(rdesc: bytes, source: str = "report descriptor") -> DescriptorLayout:
    """Parse a report descriptor with hid-tools into layouts.

    Raises:
        ConfigError: hid-tools cannot parse it, it leaves the bounds of ``devices.hid.bounds`` (the
            item and its offset named), or it has no input report.
    """
    import hidtools.hid as hh

    data = bytes(rdesc)
    if not data:
        raise ConfigError(f"{source}: empty HID report descriptor", source=source)
    if len(data) > HID_MAX_DESCRIPTOR_SIZE:  # refused before hid-tools copies it item by item
        check_items([], len(data), source)
    try:
        # what ReportDescriptor.from_bytes does, with the bounds checked between tokenising and laying out
        items = hh._HidRDescItem.from_bytes(list(data))
    except Exception as exc:  # hid-tools raises KeyError, IndexError, ParseError...
        raise ConfigError(f"{source}: hid-tools cannot parse the HID report descriptor ({len(data)} bytes):"
                          f" {type(exc).__name__}: {exc}", source=source) from exc
    check_items(items, len(data), source)
    try:
        rd = hh.ReportDescriptor(items)
    except Exception as exc:  # hid-tools raises KeyError, IndexError, ParseError, AssertionError...
        raise ConfigError(f"{source}: hid-tools cannot parse the HID report descriptor ({len(data)} bytes):"
                          f" {type(exc).__name__}: {exc}", source=source) from exc
    if not rd.input_reports:
        raise ConfigError(f"{source}: the HID report descriptor declares no input report", source=source)
    reports: dict[int | None, ReportLayout] = {}
    multipliers: list[tuple[ReportLayout, FieldLayout]] = []
    try:
        for rep in rd.input_reports.values():
            lay = _layout_of(rep, with_id=True)
            reports[lay.report_id] = lay
        for rep in rd.feature_reports.values():
            lay = _layout_of(rep, with_id=True)
            multipliers += [(lay, f) for f in lay.fields if f.usage == GD_RES_MULTIPLIER]
    except Exception as exc:  # what hid-tools parsed but cannot lay out is a bad descriptor too
        raise ConfigError(f"{source}: the HID report descriptor ({len(data)} bytes) cannot be laid out:"
                          f" {type(exc).__name__}: {exc}", source=source) from exc
    apps = tuple(dict.fromkeys(r.application for r in reports.values()))
    return DescriptorLayout(data, reports, apps, classify(reports.values()), multipliers)


def classify(reports: Iterable[ReportLayout]) -> tuple[str, ...]:
    """The classes (``mouse``, ``pen``, ``touch``) whose application collections hold fields."""
    found: set[str] = set()
    for rep in reports:
        for f in rep.fields:
            a = f.application
            if a in MOUSE_APPS and f.usage in (GD_X, GD_Y):
                found.add("mouse")
            elif a in PEN_APPS or a == DIG_DIGITIZER:
                if f.usage in (GD_X, GD_Y):
                    found.add("pen")
            elif a in TOUCH_APPS and f.usage in (GD_X, GD_Y, DIG_CONTACT_ID):
                found.add("touch")
    return tuple(c for c in CLASSES if c in found)


class HidReportCodec(Codec):
    """One HID input report per ``feed`` (as hidapi delivers them) -> ``(layout, logical values)``.

    A report shorter than its layout, or with an unknown report ID, is a framing error (counted,
    its bytes skipped); a longer one is decoded and the excess counted in ``long_reports``.
    """

    name = "hid-report"

    def __init__(self, strict: bool = False) -> None:
        super().__init__(strict)
        self.layout: DescriptorLayout | None = None
        self.long_reports = 0

    def set_layout(self, layout: DescriptorLayout) -> None:
        self.layout = layout

    def feed(self, data: bytes) -> list[Any]:
        st = self.stats
        st.bytes_in += len(data)
        lay = self.layout
        if lay is None:
            st.skipped_bytes += len(data)
            self._bad("framing", "no report descriptor known", st.bytes_in - len(data), bytes(data))
            return []
        rep = lay.report_for(data)
        if rep is None:
            st.skipped_bytes += len(data)
            what = f"unknown report ID 0x{data[0]:02x}" if data else "empty report"
            self._bad("framing", what, st.bytes_in - len(data), bytes(data))
            return []
        if len(data) < rep.size:
            st.skipped_bytes += len(data)
            self._bad("framing", f"report {rep.report_id} is {len(data)} bytes, its descriptor says {rep.size}",
                      st.bytes_in - len(data), bytes(data))
            return []
        if len(data) > rep.size:
            self.long_reports += 1
        st.frames += 1
        return [(rep, rep.decode(data))]

    def encode(self, frame: Any) -> bytes:
        rep: ReportLayout = frame[0]
        values = frame[1]
        if isinstance(values, Mapping):
            return rep.encode(values)
        return rep.encode(dict(enumerate(values)))


# -- standard descriptors (used by the simulators, and as the fallback layout before open) -------------
def _b(*items: int) -> bytes:
    return bytes(items)


#: A 1000 Hz mouse: 16 buttons, X/Y 16-bit relative, wheel with a resolution multiplier (1..8, a
#: feature report), AC Pan. Report ID 1 input, report ID 2 feature (the multiplier).
MOUSE_RDESC = _b(
    0x05, 0x01, 0x09, 0x02, 0xA1, 0x01,        # Usage Page (GD), Usage (Mouse), Collection (Application)
    0x85, 0x01,                                # Report ID 1
    0x09, 0x01, 0xA1, 0x00,                    # Usage (Pointer), Collection (Physical)
    0x05, 0x09, 0x19, 0x01, 0x29, 0x10,        # Usage Page (Button), Usage Min 1, Max 16
    0x15, 0x00, 0x25, 0x01, 0x75, 0x01, 0x95, 0x10, 0x81, 0x02,  # 16 x 1 bit, Input (Data,Var,Abs)
    0x05, 0x01, 0x09, 0x30, 0x09, 0x31,        # GD X, Y
    0x16, 0x01, 0x80, 0x26, 0xFF, 0x7F,        # Logical -32767..32767
    0x75, 0x10, 0x95, 0x02, 0x81, 0x06,        # 2 x 16 bit, Input (Data,Var,Rel)
    0xA1, 0x02,                                # Collection (Logical) - wheel and its multiplier
    0x09, 0x48, 0x15, 0x00, 0x25, 0x01, 0x35, 0x01, 0x45, 0x08,  # Resolution Multiplier 0..1 -> 1..8
    0x85, 0x02, 0x75, 0x02, 0x95, 0x01, 0xB1, 0x02,  # Report ID 2, Feature (2 bits)
    0x75, 0x06, 0xB1, 0x01,                    # 6 bits padding
    0x35, 0x00, 0x45, 0x00,                    # physical range back to none
    0x85, 0x01,                                # Report ID 1 again
    0x09, 0x38, 0x15, 0x81, 0x25, 0x7F, 0x75, 0x08, 0x95, 0x01, 0x81, 0x06,  # Wheel -127..127, Rel
    0xC0,                                      # End Collection (Logical)
    0x05, 0x0C, 0x0A, 0x38, 0x02,              # Consumer, AC Pan
    0x15, 0x81, 0x25, 0x7F, 0x75, 0x08, 0x95, 0x01, 0x81, 0x06,  # -127..127, Rel
    0xC0, 0xC0,                                # End Collection x2
)

#: A Wacom-like pen: 223.52 x 139.70 mm active area (X 0..44704, Y 0..27940 as on an Intuos4 6x9,
#: 200 counts per mm), pressure 0..2047, tilt -64..63 deg, in range, tip, barrel, eraser, invert.
PEN_RDESC = _b(
    0x05, 0x0D, 0x09, 0x02, 0xA1, 0x01,        # Digitizer, Usage (Pen), Collection (Application)
    0x85, 0x02,                                # Report ID 2
    0x09, 0x20, 0xA1, 0x00,                    # Usage (Stylus), Collection (Physical)
    0x09, 0x42, 0x09, 0x44, 0x09, 0x45, 0x09, 0x3C, 0x09, 0x32,  # Tip, Barrel, Eraser, Invert, In Range
    0x15, 0x00, 0x25, 0x01, 0x75, 0x01, 0x95, 0x05, 0x81, 0x02,
    0x95, 0x03, 0x81, 0x03,                    # 3 bits padding
    0x05, 0x01, 0x09, 0x30,                    # GD X
    0x55, 0x0D, 0x65, 0x11,                    # Unit Exponent -3, Unit (cm)
    0x15, 0x00, 0x27, 0xA0, 0xAE, 0x00, 0x00,  # Logical 0..44704
    0x35, 0x00, 0x46, 0x50, 0x57,              # Physical 0..22352 (x 1e-3 cm)
    0x75, 0x10, 0x95, 0x01, 0x81, 0x02,
    0x09, 0x31, 0x26, 0x24, 0x6D, 0x46, 0x92, 0x36, 0x81, 0x02,  # Y 0..27940 -> 0..13970
    0x05, 0x0D, 0x09, 0x30,                    # Tip Pressure
    0x55, 0x00, 0x65, 0x00, 0x35, 0x00, 0x45, 0x00,
    0x26, 0xFF, 0x07, 0x81, 0x02,              # 0..2047, 16 bits
    0x09, 0x3D, 0x09, 0x3E,                    # X Tilt, Y Tilt
    0x65, 0x14, 0x15, 0xC0, 0x25, 0x3F, 0x35, 0xC0, 0x45, 0x3F,  # degrees, -64..63
    0x75, 0x08, 0x95, 0x02, 0x81, 0x02,
    0xC0, 0xC0,
)

#: A touch screen, 2 contacts per report and a contact count; 2776 x 1569 counts over a
#: 259.1 x 146.5 mm panel (ISDv4 E6-like), width and height of each contact.
_FINGER = (
    0x05, 0x0D, 0x09, 0x22, 0xA1, 0x02,        # Digitizer, Usage (Finger), Collection (Logical)
    0x09, 0x42, 0x09, 0x47, 0x15, 0x00, 0x25, 0x01, 0x75, 0x01, 0x95, 0x02, 0x81, 0x02,  # Tip, Confidence
    0x95, 0x06, 0x81, 0x03,                    # padding
    0x09, 0x51, 0x25, 0x0F, 0x75, 0x08, 0x95, 0x01, 0x81, 0x02,  # Contact Identifier 0..15
    0x05, 0x01, 0x09, 0x30,                    # GD X
    0x55, 0x0E, 0x65, 0x11,                    # exponent -2, cm
    0x26, 0xD8, 0x0A, 0x35, 0x00, 0x46, 0x1F, 0x0A,  # logical 0..2776 -> physical 0..2591 (0.01 cm)
    0x75, 0x10, 0x81, 0x02,
    0x09, 0x31, 0x26, 0x21, 0x06, 0x46, 0xB9, 0x05, 0x81, 0x02,  # Y 0..1569 -> 0..1465
    0x05, 0x0D, 0x09, 0x48, 0x09, 0x49,        # Width, Height (same scale as X)
    0x26, 0xD8, 0x0A, 0x46, 0x1F, 0x0A, 0x95, 0x02, 0x81, 0x02,
    0x55, 0x00, 0x65, 0x00, 0x35, 0x00, 0x45, 0x00, 0x95, 0x01,
    0xC0,
)
TOUCH_RDESC = bytes((
    0x05, 0x0D, 0x09, 0x04, 0xA1, 0x01,        # Digitizer, Usage (Touch Screen), Collection (Application)
    0x85, 0x03,                                # Report ID 3
    *_FINGER, *_FINGER,
    0x05, 0x0D, 0x09, 0x54, 0x15, 0x00, 0x25, 0x7F, 0x75, 0x08, 0x95, 0x01, 0x81, 0x02,  # Contact Count
    0x85, 0x04, 0x09, 0x55, 0x25, 0x02, 0xB1, 0x02,  # Feature: Contact Count Maximum 2
    0xC0,
))

STANDARD_DESCRIPTORS: dict[str, bytes] = {"mouse": MOUSE_RDESC, "pen": PEN_RDESC, "touch": TOUCH_RDESC}
