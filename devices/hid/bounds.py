"""The bounds a HID report descriptor must keep before hid-tools lays it out.

hid-tools (``hidtools.hid.ReportDescriptor``) trusts the descriptor: a Variable main item becomes
one Python object per Report Count, an Array one list entry per usage in its Usage Minimum..Maximum
range, so a 200-byte descriptor with Report Count 0xFFFFFFFF grows without end. ``check_items``
walks the items hid-tools tokenised (the same list it then parses) and refuses, naming the item and
its byte offset, what the Linux HID core refuses or what hidraw could never deliver:

* a descriptor longer than ``HID_MAX_DESCRIPTOR_SIZE`` (4096 bytes);
* Report Size above 256 bits (Linux refuses it), or above 32 bits for a data (non-constant) field,
  the most the kernel extracts from one field (and what the decoders here handle);
* Report Count above ``HID_MAX_USAGES`` (12288), Report ID 0 or above 255;
* a report longer than ``HID_MAX_BUFFER_SIZE`` (16 KiB, its report ID byte included);
* more than ``HID_MAX_FIELDS`` (256) main items with usages in one report (the 4096 bytes already
  bound the usages before one main item to fewer than ``HID_MAX_USAGES``);
* Push deeper than ``HID_GLOBAL_STACK_SIZE`` (4), Pop or End Collection with nothing to close,
  collections nested deeper than 32 or left open at the end;
* a Usage Minimum..Maximum range over more than one usage page (65536 usages);
* more than ``MAX_VALUES`` values in all (what hid-tools makes one object for).

Everything it accepts is laid out in time and memory proportional to those bounds.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Final

from capture.errors import ConfigError

#: include/linux/hid.h
HID_MAX_DESCRIPTOR_SIZE: Final = 4096
HID_MAX_BUFFER_SIZE: Final = 16384
HID_MAX_USAGES: Final = 12288
HID_MAX_FIELDS: Final = 256
HID_GLOBAL_STACK_SIZE: Final = 4
#: drivers/hid/hid-core.c refuses a larger Report Size
MAX_REPORT_SIZE_BITS: Final = 256
#: hid_field_extract reads at most 32 bits of a field
MAX_DATA_FIELD_BITS: Final = 32
MAX_COLLECTION_DEPTH: Final = 32
MAX_USAGE_RANGE: Final = 0x10000
#: values hid-tools keeps one object for, over the whole descriptor (two full 16 KiB reports of
#: byte-wide variables; the real descriptors in the traces hold 1,393 at most). Laying out this many
#: takes about 1 s and 60 MB.
MAX_VALUES: Final = 32768


@dataclass
class _Globals:
    usage_page: int = 0
    size: int = 0
    count: int = 0

    def copy(self) -> _Globals:
        return _Globals(self.usage_page, self.size, self.count)


@dataclass
class _Locals:
    usages: int = 0
    usage_min: int = 0
    usage_max: int = 0
    usage_max_size: int = 0


@dataclass
class _Walk:
    glob: _Globals = field(default_factory=_Globals)
    stack: list[_Globals] = field(default_factory=list)
    local: _Locals = field(default_factory=_Locals)
    report_id: int = -1
    depth: int = 0
    bits: dict[tuple[str, int], int] = field(default_factory=dict)
    fields: dict[tuple[str, int], int] = field(default_factory=dict)
    values: int = 0


def _usage_range(w: _Walk) -> int:
    """How many usages hid-tools lists for the Usage Minimum..Maximum in effect (its own arithmetic)."""
    lo, hi = w.local.usage_min, w.local.usage_max
    if hi and w.local.usage_max_size <= 2 and hi & 0xFFFF0000 != w.glob.usage_page:
        hi = (hi & 0xFFFF) | w.glob.usage_page
        lo = (lo & 0xFFFF) | w.glob.usage_page
    if not (lo and hi):
        return 0
    return max(0, hi - lo + 1)


def _main(w: _Walk, kind: str, value: int, refuse: Any) -> None:
    rng = _usage_range(w)
    if rng > MAX_USAGE_RANGE:
        refuse(f"its Usage Minimum..Maximum spans {rng} usages (at most {MAX_USAGE_RANGE}, one usage page)")
    const = bool(value & 0x1)
    array = not value & 0x2
    if not const and w.glob.size > MAX_DATA_FIELD_BITS:
        refuse(f"a data field of Report Size {w.glob.size} bits (Linux reads at most {MAX_DATA_FIELD_BITS})")
    key = (kind, w.report_id)
    bits = w.bits.get(key, 8 if w.report_id >= 0 else 0) + w.glob.size * w.glob.count
    if bits > HID_MAX_BUFFER_SIZE * 8:
        refuse(f"report {max(w.report_id, 0)} ({kind}) grows to {(bits + 7) // 8} bytes"
               f" (hidraw delivers at most {HID_MAX_BUFFER_SIZE})")
    w.bits[key] = bits
    has_usages = bool(w.local.usages or rng)
    if has_usages:
        n = w.fields.get(key, 0) + 1
        if n > HID_MAX_FIELDS:
            refuse(f"report {max(w.report_id, 0)} ({kind}) has more than {HID_MAX_FIELDS} fields")
        w.fields[key] = n
    w.values += w.glob.count if has_usages and not array else 1
    if w.values > MAX_VALUES:
        refuse(f"the descriptor declares more than {MAX_VALUES} values")
    w.local = _Locals()


def check_items(items: list[Any], length: int, source: str) -> None:
    """Refuse a tokenised descriptor (hid-tools ``_HidRDescItem`` list) that leaves the bounds above.

    Raises:
        ConfigError: the first item out of bounds, by name, value and byte offset.
    """
    if length > HID_MAX_DESCRIPTOR_SIZE:
        raise ConfigError(f"{source}: the HID report descriptor is {length} bytes"
                          f" (Linux accepts at most {HID_MAX_DESCRIPTOR_SIZE})", source=source)
    w = _Walk()
    for item in items:
        name: str = item.item
        value: int = int(item.value)
        nbytes = len(item.raw_value)

        def refuse(why: str, item: Any = item, name: str = name, value: int = value) -> None:
            raise ConfigError(f"{source}: HID report descriptor item {name} ({value:#x}) at byte"
                              f" {item.index_in_report}: {why}", source=source)

        if name == "Report Size":
            if value > MAX_REPORT_SIZE_BITS:
                refuse(f"more than {MAX_REPORT_SIZE_BITS} bits per field")
            w.glob.size = value
        elif name == "Report Count":
            if value > HID_MAX_USAGES:
                refuse(f"more than {HID_MAX_USAGES} fields (HID_MAX_USAGES)")
            w.glob.count = value
        elif name == "Report ID":
            if not 0 < value < 256:
                refuse("a report ID is 1..255")
            w.report_id = value
        elif name == "Usage Page":
            w.glob.usage_page = value << 16
        elif name == "Push":
            if len(w.stack) >= HID_GLOBAL_STACK_SIZE:
                refuse(f"pushed deeper than {HID_GLOBAL_STACK_SIZE} (the global stack)")
            w.stack.append(w.glob)
            w.glob = w.glob.copy()
        elif name == "Pop":
            if not w.stack:
                refuse("nothing was pushed")
            w.glob = w.stack.pop()
        elif name == "Usage":
            w.local.usages += 1
        elif name == "Usage Minimum":
            w.local.usage_min = value | w.glob.usage_page if nbytes <= 2 else value
        elif name == "Usage Maximum":
            w.local.usage_max = value | w.glob.usage_page if nbytes <= 2 else value
            w.local.usage_max_size = nbytes
        elif name == "Collection":
            w.depth += 1
            if w.depth > MAX_COLLECTION_DEPTH:
                refuse(f"collections nested deeper than {MAX_COLLECTION_DEPTH}")
            w.local = _Locals()
        elif name == "End Collection":
            if w.depth == 0:
                refuse("no collection is open")
            w.depth -= 1
        elif name in ("Input", "Output", "Feature"):
            _main(w, name, value, refuse)
    if w.depth:
        raise ConfigError(f"{source}: the HID report descriptor leaves {w.depth} collection(s) open at its end",
                          source=source)
