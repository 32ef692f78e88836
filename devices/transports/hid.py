"""HID transports: one input report per chunk, plus feature and output reports for handshakes.

``HidTransportBase`` is what HID device kinds talk to. The live implementation is ``HidTransport``
(``hid://VID:PID[:SERIAL]`` or ``hid://path=...`` on hidapi); the simulated one (``simhid://``) lives in
``sim_devices`` and the session replay answers the same calls from the recording, so a device's
handshake runs unchanged against all three.

Report bytes follow hidapi: a numbered report starts with its report ID; a device without report
IDs delivers the report body alone. Feature reports are always exchanged with the report ID first
(0 for a device without IDs).
"""

from __future__ import annotations

import abc
import errno
import importlib
import os
import re
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

from capture.clock import MONOTONIC, Clock
from capture.errors import (
    ConfigError,
    DeviceInitError,
    DeviceIOError,
    DeviceNotFoundError,
    DeviceUnavailableError,
)
from capture.sample import Chunk
from devices.options import Option
from devices.transports.base import Transport

if TYPE_CHECKING:
    from collections.abc import Mapping


class HidTransportBase(abc.ABC):
    """The HID calls beyond ``Transport.read`` (input reports) and ``Transport.write`` (output
    reports) that a HID device's handshake uses. Mixed into a ``Transport`` subclass."""

    #: "usb", "bluetooth", "i2c", "spi" or "unknown", known after ``open`` (before it when enumerated)
    bus: str = "unknown"

    @abc.abstractmethod
    def get_feature_report(self, report_id: int, length: int) -> bytes:
        """Read feature report ``report_id``; ``length`` counts the report ID byte.

        Returns:
            the report, its ID first.

        Raises:
            DeviceIOError: the device failed or refused (a stall, unplugged).
            DeviceTimeoutError: no answer in time.
        """

    @abc.abstractmethod
    def send_feature_report(self, data: bytes) -> Chunk:
        """Write a feature report (its ID first); returns the stamped TX chunk for the session.

        Raises:
            DeviceIOError: the device failed or refused.
        """

    @abc.abstractmethod
    def report_descriptor(self) -> bytes:
        """The device's HID report descriptor (after ``open``).

        Raises:
            DeviceIOError: it cannot be read.
        """


# ------------------------------------------------------------------------------------------------
# Live devices on hidapi
# ------------------------------------------------------------------------------------------------

_VIDPID_RE = re.compile(r"^([0-9a-fA-F]{4}):([0-9a-fA-F]{4})(?::(.+))?$")

#: hidapi bus_type values (hidapi >= 0.13)
_BUS = {1: "usb", 2: "bluetooth", 3: "i2c", 4: "spi"}


@dataclass(frozen=True)
class KnownHid:
    vid: int
    pid: int
    name: str
    kind: str


#: devices perfcap has a kind for, by USB id (Bluetooth reports the same ids)
KNOWN_HID: tuple[KnownHid, ...] = (
    KnownHid(0x054C, 0x05C4, "Sony DualShock 4 (CUH-ZCT1)", "ds4"),
    KnownHid(0x054C, 0x09CC, "Sony DualShock 4 (CUH-ZCT2)", "ds4"),
    KnownHid(0x054C, 0x0BA0, "Sony DualShock 4 USB wireless adaptor", "ds4"),
    KnownHid(0x054C, 0x0CE6, "Sony DualSense", "dualsense"),
    KnownHid(0x054C, 0x0DF2, "Sony DualSense Edge", "dualsense"),
    KnownHid(0x057E, 0x2009, "Nintendo Switch Pro Controller", "switchpro"),
    KnownHid(0x057E, 0x2006, "Nintendo Joy-Con (L)", "joycon"),
    KnownHid(0x057E, 0x2007, "Nintendo Joy-Con (R)", "joycon"),
)

#: HID usage (page, usage) of top-level collections perfcap reads with the generic ``hid`` kind
GENERIC_USAGES: dict[tuple[int, int], str] = {
    (0x01, 0x02): "mouse",
    (0x0D, 0x01): "pen (digitizer)",
    (0x0D, 0x02): "pen",
    (0x0D, 0x04): "touch screen",
    (0x0D, 0x05): "touch pad",
}


def known_hid(vid: int | None, pid: int | None) -> KnownHid | None:
    for k in KNOWN_HID:
        if k.vid == vid and k.pid == pid:
            return k
    return None


@dataclass(frozen=True)
class HidDeviceInfo:
    """One HID interface as hidapi enumerates it."""

    path: str
    vid: int
    pid: int
    serial_number: str
    manufacturer: str
    product: str
    usage_page: int
    usage: int
    interface: int
    bus: str

    @property
    def vid_pid(self) -> str:
        return f"{self.vid:04x}:{self.pid:04x}"

    @property
    def likely_kind(self) -> str | None:
        k = known_hid(self.vid, self.pid)
        if k is not None:
            return k.kind
        if (self.usage_page, self.usage) in GENERIC_USAGES:
            return "hid"
        return None

    @property
    def url(self) -> str:
        base = f"hid://{self.vid_pid}:{self.serial_number}" if self.serial_number else f"hid://{self.vid_pid}"
        if known_hid(self.vid, self.pid) is None and self.usage_page:
            # a mouse or tablet is often one of several interfaces of its USB device: name this one
            return f"{base}?usage_page={self.usage_page}&usage={self.usage}"
        return base

    def as_dict(self) -> dict[str, Any]:
        k = known_hid(self.vid, self.pid)
        return {"path": self.path, "url": self.url, "vid_pid": self.vid_pid, "serial_number": self.serial_number,
                "manufacturer": self.manufacturer, "product": self.product, "usage_page": self.usage_page,
                "usage": self.usage, "interface": self.interface, "bus": self.bus,
                "likely_kind": self.likely_kind, "known_as": k.name if k else
                GENERIC_USAGES.get((self.usage_page, self.usage), "")}


def _hid_module() -> Any:
    """hidapi's backend: on Linux its ``hidraw`` module (the kernel's hidraw nodes: Bluetooth devices
    are listed, and a mouse or tablet keeps working on the desktop while perfcap reads it), elsewhere
    ``hid``. The ``hid`` module of the Linux wheel goes through libusb, which sees no Bluetooth device
    and detaches the kernel driver of what it opens."""
    names = ("hidraw", "hid") if sys.platform.startswith("linux") else ("hid",)
    errors = []
    for name in names:
        try:  # module names as literals: only the registries import a module named at run time
            return importlib.import_module("hidraw") if name == "hidraw" else importlib.import_module("hid")
        except ImportError as exc:
            errors.append(f"{name}: {exc}")
    raise DeviceUnavailableError(f"the hidapi package cannot be loaded ({'; '.join(errors)}); reinstall perfcap")


def hid_backend() -> str:
    """Which hidapi backend perfcap uses here (for perfcap doctor)."""
    try:
        return str(_hid_module().__name__)
    except DeviceUnavailableError as exc:
        return f"none ({exc})"


def list_hid_devices() -> list[HidDeviceInfo]:
    """HID interfaces present now (every usage of every interface), sorted by id and path."""
    hid = _hid_module()
    out = []
    for d in hid.enumerate():
        path = d.get("path", b"")
        out.append(HidDeviceInfo(
            path=path.decode(errors="replace") if isinstance(path, bytes) else str(path),
            vid=int(d.get("vendor_id") or 0), pid=int(d.get("product_id") or 0),
            serial_number=d.get("serial_number") or "", manufacturer=d.get("manufacturer_string") or "",
            product=d.get("product_string") or "", usage_page=int(d.get("usage_page") or 0),
            usage=int(d.get("usage") or 0), interface=int(d.get("interface_number", -1)),
            bus=_BUS.get(int(d.get("bus_type") or 0), "unknown")))
    return sorted(out, key=lambda i: (i.vid, i.pid, i.path))


def _hidraw_descriptor(path: str) -> bytes | None:
    """Linux: the report descriptor from sysfs, readable without opening the device."""
    name = os.path.basename(path)
    if not name.startswith("hidraw"):
        return None
    try:
        with open(f"/sys/class/hidraw/{name}/device/report_descriptor", "rb") as f:
            return f.read()
    except OSError:
        return None


class HidTransport(Transport, HidTransportBase):
    """A HID device on hidapi.

    Addresses: ``hid://VID:PID`` (the first matching interface), ``hid://VID:PID:SERIAL``, or
    ``hid://path=PATH`` (the OS path from ``perfcap devices``). The VID:PID forms are looked up again
    at every open, so a controller that reconnects over Bluetooth after USB (same ids) is the same
    device. Options pick the interface of a composite device (``usage_page``, ``usage``,
    ``interface``).
    """

    scheme: ClassVar[str] = "hid"
    usage: ClassVar[str] = "hid://VID:PID[:SERIAL] or hid://path=PATH"
    options: ClassVar[dict[str, Option]] = {
        "usage_page": Option(int, 0, "only the interface with this usage page (0 = any)", min=0, max=0xFFFF),
        "usage": Option(int, 0, "only the interface with this usage (0 = any)", min=0, max=0xFFFF),
        "interface": Option(int, -1, "only this USB interface number (-1 = any)", min=-1, max=255),
        "report_size": Option(int, 1024, "largest input report read, bytes", min=8, max=65536),
    }

    def __init__(self, address: str, options: Mapping[str, Any] | None = None, clock: Clock = MONOTONIC) -> None:
        super().__init__(address, options, clock)
        if not address:
            raise ConfigError(f"hid:// needs an address; expected {self.usage}", source=self.url)
        m = _VIDPID_RE.match(address)
        self._want: tuple[int, int, str | None] | None = None
        self._path: str | None = None
        if m:
            self._want = (int(m.group(1), 16), int(m.group(2), 16), m.group(3))
        elif address.startswith("path="):
            self._path = address[5:]
        else:
            raise ConfigError(f"hid://{address}: expected {self.usage}", source=self.url)
        self._dev: Any = None
        self.info: HidDeviceInfo | None = None
        self._last_scan_ns = -(1 << 62)
        self._last_present = False

    # -- finding the device ------------------------------------------------------------------------
    def _matches(self) -> list[HidDeviceInfo]:
        o = self.opts
        found = []
        for d in list_hid_devices():
            if self._path is not None:
                if d.path != self._path:
                    continue
            else:
                assert self._want is not None
                vid, pid, sn = self._want
                if (d.vid, d.pid) != (vid, pid) or (sn is not None and d.serial_number != sn):
                    continue
            if o["usage_page"] and d.usage_page != o["usage_page"]:
                continue
            if o["usage"] and d.usage != o["usage"]:
                continue
            if o["interface"] >= 0 and d.interface != o["interface"]:
                continue
            found.append(d)
        return found

    def _find(self) -> HidDeviceInfo:
        found = self._matches()
        if not found:
            raise DeviceNotFoundError(f"no HID device {self.address} is connected (perfcap devices lists what is"
                                      " present; perfcap doctor says why one cannot be opened)", source=self.url)
        paths = {d.path for d in found}
        if len(paths) > 1 and self._want is not None and self._want[2] is None:
            known = known_hid(self._want[0], self._want[1])
            if known is None:  # a composite device: several interfaces, the caller must choose
                choices = ", ".join(f"{d.path} (usage {d.usage_page:#06x}:{d.usage:#06x}, interface {d.interface})"
                                    for d in found)
                raise DeviceInitError(f"{len(paths)} HID interfaces match {self.address}: {choices}; choose one"
                                      " with usage_page=/usage=/interface= or hid://path=PATH", source=self.url)
        return found[0]

    def identity_hint(self) -> dict[str, Any]:
        if self._want is not None:
            vid, pid, sn = self._want
            return {"vid": vid, "pid": pid, "serial": sn}
        return {}

    def implied_kind(self) -> str | None:
        if self._want is not None:
            k = known_hid(self._want[0], self._want[1])
            return k.kind if k else None
        return None

    def present(self) -> bool | None:
        now = self.clock.now_ns()
        if now - self._last_scan_ns < 250_000_000:  # enumeration costs ~ms: at most 4 scans a second
            return self._last_present
        self._last_scan_ns = now
        try:
            self._last_present = bool(self._matches())
        except DeviceUnavailableError:
            return None
        return self._last_present

    # -- life cycle ----------------------------------------------------------------------------------
    def open(self) -> None:
        hid = _hid_module()
        info = self._find()
        dev = hid.device()
        try:
            dev.open_path(info.path.encode())
        except OSError as exc:
            raise self._open_error(info, exc) from exc
        self._dev = dev
        self.info = info
        self.bus = info.bus

    def _open_error(self, info: HidDeviceInfo, exc: BaseException) -> DeviceInitError:
        hint = ""
        node = info.path if info.path.startswith("/dev/") else ""
        if node and os.path.exists(node) and not os.access(node, os.R_OK | os.W_OK):
            hint = (f": permission denied on {node}. Install perfcap's udev rules (perfcap doctor --udev prints"
                    " them and where they go), then unplug and replug the device")
        elif getattr(exc, "errno", None) == errno.EBUSY:
            hint = ": another program holds the device"
        return DeviceInitError(f"cannot open HID device {info.vid_pid} ({info.product or 'unnamed'}) at {info.path}"
                               f"{hint or f': {exc}'}", source=self.url)

    def close(self) -> None:
        dev, self._dev = self._dev, None
        if dev is not None:
            try:
                dev.close()
            except OSError:
                pass

    @property
    def is_open(self) -> bool:
        return self._dev is not None

    def _lost(self, exc: BaseException | None, what: str) -> DeviceIOError:
        self.close()
        return DeviceIOError(f"{self.url}: {what} failed ({exc or 'device gone'}); unplugged?", source=self.url)

    # -- I/O ---------------------------------------------------------------------------------------------
    def read(self, timeout: float) -> Chunk | None:
        dev = self._dev
        if dev is None:
            raise DeviceIOError(f"{self.url}: read on a closed device", source=self.url)
        try:
            data = dev.read(self.opts["report_size"], max(1, int(timeout * 1000)))
        except (OSError, ValueError) as exc:
            raise self._lost(exc, "read") from exc
        t = self.clock.now_ns()
        if not data:
            return None
        return Chunk(bytes(data), t)

    def write(self, data: bytes) -> Chunk:
        dev = self._dev
        if dev is None:
            raise DeviceIOError(f"{self.url}: write on a closed device", source=self.url)
        chunk = self.stamp_tx(data)
        try:
            n = dev.write(bytes(data))
        except (OSError, ValueError) as exc:
            raise self._lost(exc, "output report") from exc
        if n < 0:
            raise self._lost(None, "output report")
        return chunk

    def send_feature_report(self, data: bytes) -> Chunk:
        dev = self._dev
        if dev is None:
            raise DeviceIOError(f"{self.url}: feature report on a closed device", source=self.url)
        chunk = self.stamp_tx(data)
        try:
            n = dev.send_feature_report(bytes(data))
        except (OSError, ValueError) as exc:
            raise self._lost(exc, "feature report write") from exc
        if n < 0:
            raise DeviceIOError(f"{self.url}: the device refused feature report 0x{data[0]:02x}", source=self.url)
        return chunk

    def get_feature_report(self, report_id: int, length: int) -> bytes:
        dev = self._dev
        if dev is None:
            raise DeviceIOError(f"{self.url}: feature report on a closed device", source=self.url)
        try:
            data = dev.get_feature_report(report_id, length)
        except (OSError, ValueError) as exc:
            raise DeviceIOError(f"{self.url}: feature report 0x{report_id:02x} could not be read ({exc})",
                                source=self.url) from exc
        return bytes(data)

    def report_descriptor(self) -> bytes:
        """The report descriptor: from sysfs (Linux, works before ``open``), else from hidapi."""
        info = self.info
        if info is None:
            try:
                info = self._find()
            except DeviceNotFoundError:
                info = None
        if info is not None:
            blob = _hidraw_descriptor(info.path)
            if blob:
                return blob
        dev, opened_here = self._dev, False
        if dev is None:  # before open (a generic device declares its streams from it): open briefly
            if info is None:
                raise DeviceNotFoundError(f"no HID device {self.address} is connected, so its report descriptor"
                                          " cannot be read", source=self.url)
            dev = _hid_module().device()
            try:
                dev.open_path(info.path.encode())
            except OSError as exc:
                raise self._open_error(info, exc) from exc
            opened_here = True
        try:
            return bytes(dev.get_report_descriptor())
        except (OSError, ValueError, AttributeError) as exc:
            raise DeviceIOError(f"{self.url}: the report descriptor could not be read ({exc})",
                                source=self.url) from exc
        finally:
            if opened_here:
                dev.close()
