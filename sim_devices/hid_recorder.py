"""hid-recorder captures (``.hid``) replayed as a simulated HID device: ``simhid:///path/file.hid``.

The format (hid-tools' ``hid-recorder``), one item per line::

    D: 0                       device index (a capture may hold several devices)
    R: 220 05 01 09 02 ...     report descriptor: length, then hex bytes
    N: Contour Design ...      name
    P: usb-0000:00:14.0-1/...  physical path
    I: 3 0b33 1004             bus (3 = USB, 5 = Bluetooth), vendor, product (hex)
    E: 000000.003905 16 01 01 ...   an input report: seconds.microseconds, length, hex bytes

Any other line (``#`` comments, hid-decode output, free text, an unknown ``X:`` prefix) is skipped,
as ``hid-replay`` skips lines it does not know: the skipped lines are counted
(``HidRecording.skipped``) and logged, never dropped silently. Lines holding only hex bytes
continue the ``R:`` or ``E:`` line before them (captures pasted from documents are often wrapped).
Files that hold only ``E:`` lines (``.events.txt``) take the descriptor (and ``I:``/``N:``) from
another capture named by the option ``rdesc_file``. A capture
is read only when it is a regular file of at most ``MAX_TRACE_BYTES`` with lines of at most
``MAX_LINE``, its descriptors and reports no longer than Linux allows, its times finite seconds;
anything else is a ``TraceError`` naming the file and line.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

from capture.bounded_io import InputLimitError, read_text_bounded
from capture.errors import TraceError
from devices.hid.bounds import HID_MAX_BUFFER_SIZE, HID_MAX_DESCRIPTOR_SIZE
from devices.options import Option
from sim_devices.hid_sim import HidResponder, trace_path

if TYPE_CHECKING:
    from collections.abc import Iterator, Mapping

log = logging.getLogger(__name__)

BUSES = {3: "usb", 5: "bluetooth", 0x18: "i2c", 0x1C: "spi"}
#: the largest capture read, its longest line, the longest R: (HID_MAX_DESCRIPTOR_SIZE) and E:
#: (HID_MAX_BUFFER_SIZE) items, and the largest time (s) taken for one
MAX_TRACE_BYTES = 64 << 20
MAX_LINE = 64 << 10
MAX_ITEM = {"R": HID_MAX_DESCRIPTOR_SIZE, "E": HID_MAX_BUFFER_SIZE}
MAX_TIME_S = 1e10
_HEX_ONLY = re.compile(r"^(?:[0-9a-fA-F]{2}\s*)+$")
#: the line types hid-replay reads; every other line is skipped (and counted)
KNOWN_TAGS = frozenset("DRNPIE")


@dataclass
class RecordedDevice:
    index: int = 0
    rdesc: bytes = b""
    name: str = ""
    phys: str = ""
    bus: int = 0
    vid: int = 0
    pid: int = 0
    #: (seconds, report)
    events: list[tuple[float, bytes]] = field(default_factory=list)


class HidRecording(dict[int, RecordedDevice]):
    """The devices of a capture by ``D:`` index, and the lines skipped: ``(line number, text)``."""

    def __init__(self) -> None:
        super().__init__()
        self.skipped: list[tuple[int, str]] = []


def _hex(tokens: list[str], path: str, n: int, what: str) -> bytes:
    try:
        return bytes(int(x, 16) for x in tokens)
    except ValueError:
        raise TraceError(f"{what}: not hex bytes: {' '.join(tokens)[:60]!r}", path=path, line=n) from None


def parse_hid_recording(path: str) -> HidRecording:
    """Parse a hid-recorder file into its devices (by ``D:`` index, 0 when there is none).

    Lines hid-replay does not know are skipped, counted in ``.skipped`` and logged.

    Raises:
        TraceError: unreadable file, malformed line, or a length that does not match the bytes.
    """
    try:
        text = read_text_bounded(path, MAX_TRACE_BYTES, MAX_LINE)
    except (OSError, InputLimitError, UnicodeDecodeError) as exc:
        raise TraceError(f"cannot read hid-recorder file: {exc}", path=path) from None
    devices = HidRecording()
    cur = devices.setdefault(0, RecordedDevice(0))
    # an R:/E: item being assembled across wrapped lines: [tag, line, declared length, bytes, time]
    pending: list[Any] | None = None

    def close() -> None:
        nonlocal pending
        if pending is None:
            return
        tag, n, length, data, t = pending
        pending = None
        if len(data) != length:
            raise TraceError(f"{tag}: line says {length} bytes but holds {len(data)}", path=path, line=n)
        if len(data) > MAX_ITEM[tag]:
            raise TraceError(f"{tag}: {len(data)} bytes, more than a {'report descriptor' if tag == 'R' else 'report'}"
                             f" can be ({MAX_ITEM[tag]})", path=path, line=n)
        if tag == "R":
            cur.rdesc = bytes(data)
        else:
            cur.events.append((t, bytes(data)))

    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line:
            continue
        if pending is not None and _HEX_ONLY.match(line):
            pending[3] += _hex(line.split(), path, n, pending[0])
            continue
        tag, sep, rest = line.partition(":")
        if not sep or tag not in KNOWN_TAGS:
            devices.skipped.append((n, line[:80]))
            continue
        close()
        parts = rest.split()
        try:
            if tag == "D":
                idx = int(parts[0])
                cur = devices.setdefault(idx, RecordedDevice(idx))
            elif tag == "R":
                pending = ["R", n, int(parts[0]), bytearray(_hex(parts[1:], path, n, "R")), 0.0]
            elif tag == "N":
                cur.name = rest.strip()
            elif tag == "P":
                cur.phys = rest.strip()
            elif tag == "I":
                cur.bus, cur.vid, cur.pid = (int(x, 16) for x in parts[:3])
            elif tag == "E":
                t = float(parts[0])
                if not abs(t) < MAX_TIME_S:  # nan, inf and 1e300 too
                    raise ValueError(t)
                pending = ["E", n, int(parts[1]), bytearray(_hex(parts[2:], path, n, "E")), t]
        except (ValueError, IndexError):
            raise TraceError(f"malformed {tag}: line {line[:60]!r}", path=path, line=n) from None
    close()
    _log_skipped(path, devices.skipped)
    if len(devices) > 1 and not devices[0].rdesc and not devices[0].events:
        del devices[0]
    return devices


def _log_skipped(path: str, skipped: list[tuple[int, str]]) -> None:
    comments = sum(1 for _, text in skipped if text.startswith("#"))
    other = [(n, text) for n, text in skipped if not text.startswith("#")]
    if comments:
        log.info("%s: skipped %d comment line(s)", path, comments)
    if other:
        n, text = other[0]
        log.warning("%s: skipped %d line(s) that are not hid-recorder items (D R N P I E), as hid-replay does;"
                    " the first, line %d: %r", path, len(other), n, text)


class HidRecorderResponder(HidResponder):
    """Replays the input reports of one device of a hid-recorder capture at their recorded times."""

    kind = "hid"
    options: ClassVar[dict[str, Option]] = {
        "rdesc_file": Option(str, "", "a hid-recorder capture whose R:/I:/N: lines describe the device"
                             " (for files that hold only E: lines)"),
        "device": Option(int, -1, "which D: device of the capture to replay (-1: the first)", min=-1),
    }

    def __init__(self, opts: Mapping[str, Any], address: str = "") -> None:
        super().__init__(opts, address)
        self.path = trace_path(address)
        devs = parse_hid_recording(self.path)
        idx = self.opts.get("device", -1)
        if idx == -1:
            idx = min(devs)
        if idx not in devs:
            raise TraceError(f"no device D: {idx} in the capture (it has {sorted(devs)})", path=self.path)
        dev = devs[idx]
        other = self.opts.get("rdesc_file") or ""
        if other:
            odevs = parse_hid_recording(other)
            src = odevs.get(idx, odevs[min(odevs)])
            dev.rdesc = dev.rdesc or src.rdesc
            dev.name = dev.name or src.name
            dev.bus, dev.vid, dev.pid = (dev.bus, dev.vid, dev.pid) if dev.vid else (src.bus, src.vid, src.pid)
        if not dev.rdesc:
            raise TraceError("the capture has no report descriptor (R: line); give one with rdesc_file=PATH",
                             path=self.path)
        self.device = dev
        self.vid = dev.vid
        self.pid = dev.pid
        self.product = dev.name
        if BUSES.get(dev.bus) in ("usb", "bluetooth"):  # the recorded bus wins over the bus option
            self.bus = BUSES[dev.bus]

    def report_descriptor(self) -> bytes:
        return self.device.rdesc

    def stream(self) -> Iterator[tuple[float, bytes]]:
        ev = self.device.events
        if not ev:
            return
        t0 = ev[0][0]
        for t, rep in ev:
            yield t - t0, rep
