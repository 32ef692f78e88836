"""``evdev://`` - a Linux input device node (``/dev/input/eventN``), read as the kernel's
``struct input_event`` records.

    evdev:///dev/input/event5                 by node
    evdev:///dev/input/by-id/usb-Wacom_...    by a stable udev link (the same device after a replug)
    evdev://056a:00b9                         the first input device with that USB vendor:product

Each read returns whole records, stamped with the host time of their arrival; the device kind
(``devices.evdev``) takes the kernel's own event times from them. On open the transport asks the
kernel for CLOCK_MONOTONIC event times (``EVIOCSCLOCKID``; ``clock=realtime`` leaves the default
realtime clock) and, with ``grab=true``, takes the device for itself (``EVIOCGRAB``: the desktop no
longer sees it). An unplug ends reads with ``DeviceIOError``; ``present`` tells the reader when the
node (or the VID:PID) is back, as for serial ports.

The capabilities (``EvdevSource``) are read with python-evdev, an optional dependency
(``pip install 'perfcap[evdev]'``); without it, opening a live device fails saying so, while the
codec and the simulated ``simevdev://`` work.
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import re
import select
import struct
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, runtime_checkable

from capture.clock import MONOTONIC, Clock
from capture.errors import DeviceInitError, DeviceIOError, DeviceNotFoundError, DeviceUnavailableError
from capture.sample import Chunk, Direction
from devices.options import Option
from devices.transports.base import Transport

if TYPE_CHECKING:
    from collections.abc import Mapping

log = logging.getLogger(__name__)

#: ioctls of linux/input.h: _IOW('E', 0xa0, int) and _IOW('E', 0x90, int)
EVIOCSCLOCKID = 0x400445A0
EVIOCGRAB = 0x40044590
CLOCK_REALTIME, CLOCK_MONOTONIC = 0, 1
EXTRA_HINT = "pip install 'perfcap[evdev]' (python-evdev)"
_VIDPID_RE = re.compile(r"^([0-9a-fA-F]{4}):([0-9a-fA-F]{4})$")
#: bytes of one ``struct input_event`` here (what the device kind's codec decodes): 24 on 64-bit Linux
EVENT_SIZE = struct.calcsize("@llHHi")
EV_KEY, EV_REL, EV_ABS = 1, 2, 3
TYPE_NAMES = {0: "syn", 1: "key", 2: "rel", 3: "abs", 4: "msc", 5: "sw", 0x11: "led", 0x12: "snd", 0x14: "rep",
              0x15: "ff"}


# -- the device's description: what the kernel says it can report ----------------------------------------
@dataclass(frozen=True)
class AbsInfo:
    """``struct input_absinfo`` without the value: the axis range, noise filter and resolution
    (units per mm for positions, per radian for rotations and tilt; 0 when the driver gives none)."""

    minimum: int
    maximum: int
    fuzz: int = 0
    flat: int = 0
    resolution: int = 0

    def fraction(self, value: float) -> float:
        span = self.maximum - self.minimum
        return (value - self.minimum) / span if span else 0.0


@dataclass
class Capabilities:
    """What an input device can report (``EVIOCGBIT``, ``EVIOCGABS``, ``EVIOCGPROP``) and who it is."""

    name: str = ""
    bus: int = 0
    vendor: int = 0
    product: int = 0
    version: int = 0
    #: event type -> its codes (EV_KEY -> the keys and buttons, EV_ABS -> the axes, ...)
    events: dict[int, frozenset[int]] = field(default_factory=dict)
    absinfo: dict[int, AbsInfo] = field(default_factory=dict)
    props: frozenset[int] = frozenset()

    FORMAT: ClassVar[int] = 1

    def codes(self, typ: int) -> frozenset[int]:
        return self.events.get(typ, frozenset())

    def to_json(self) -> str:
        doc = {"format": self.FORMAT, "name": self.name, "bus": self.bus, "vendor": self.vendor,
               "product": self.product, "version": self.version, "props": sorted(self.props),
               "events": {str(t): sorted(c) for t, c in sorted(self.events.items()) if c},
               "abs": {str(c): [a.minimum, a.maximum, a.fuzz, a.flat, a.resolution]
                       for c, a in sorted(self.absinfo.items())}}
        return json.dumps(doc, separators=(",", ":"))

    @classmethod
    def from_json(cls, text: str | bytes) -> Capabilities:
        """Raises: ValueError: not a capabilities document (the reason said)."""
        try:
            doc: Any = json.loads(text)
            if not isinstance(doc, dict) or doc.get("format") != cls.FORMAT:
                raise ValueError(f"expected an object with format {cls.FORMAT}")
            return cls(name=str(doc.get("name", "")), bus=int(doc.get("bus", 0)), vendor=int(doc.get("vendor", 0)),
                       product=int(doc.get("product", 0)), version=int(doc.get("version", 0)),
                       events={int(t): frozenset(int(c) for c in cs) for t, cs in doc.get("events", {}).items()},
                       absinfo={int(c): AbsInfo(*(int(x) for x in v[:5])) for c, v in doc.get("abs", {}).items()},
                       props=frozenset(int(p) for p in doc.get("props", [])))
        except (TypeError, ValueError, AttributeError) as exc:
            raise ValueError(f"not an evdev capabilities document: {exc}") from None




@runtime_checkable
class EvdevSource(Protocol):
    """A transport that knows its input device's capabilities before open (``evdev://``,
    ``simevdev://``)."""

    def evdev_capabilities(self) -> Capabilities:
        """The device's capabilities.

        Raises:
            DeviceNotFoundError: the device is not there.
            DeviceUnavailableError: python-evdev is missing.
        """
        ...


def _evdev() -> Any:
    try:
        import evdev
    except ImportError as exc:
        raise DeviceUnavailableError(f"evdev:// needs python-evdev, which is not installed: {EXTRA_HINT}"
                                     f" ({exc})", source="evdev") from None
    return evdev


def capabilities_of(dev: Any) -> Capabilities:
    """``Capabilities`` of an open ``evdev.InputDevice``."""
    events: dict[int, frozenset[int]] = {}
    absinfo: dict[int, AbsInfo] = {}
    for typ, codes in dev.capabilities(absinfo=True, verbose=False).items():
        cs = set()
        for c in codes:
            if isinstance(c, tuple):
                code, a = c
                absinfo[int(code)] = AbsInfo(int(a.min), int(a.max), int(a.fuzz), int(a.flat), int(a.resolution))
                cs.add(int(code))
            else:
                cs.add(int(c))
        events[int(typ)] = frozenset(cs)
    info = dev.info
    try:
        props = frozenset(int(p) for p in dev.input_props())
    except (OSError, AttributeError):
        props = frozenset()
    return Capabilities(name=str(dev.name), bus=int(info.bustype), vendor=int(info.vendor),
                        product=int(info.product), version=int(info.version), events=events, absinfo=absinfo,
                        props=props)


@dataclass
class InputDeviceInfo:
    """One ``/dev/input/event*`` node as ``perfcap devices`` lists it."""

    path: str
    name: str
    vid: int
    pid: int
    bus: int
    phys: str
    caps: Capabilities

    @property
    def url(self) -> str:
        return f"evdev://{self.path}"

    @property
    def likely(self) -> str:
        """What the capabilities say it is (pen tablet, touchscreen, touchpad, mouse, ...)."""
        keys, absc, rels = self.caps.codes(EV_KEY), set(self.caps.absinfo), self.caps.codes(EV_REL)
        if 0x140 in keys and {0, 1} <= absc:
            return "pen tablet"
        if 0x35 in absc:
            return "touchscreen" if 1 in self.caps.props else "touchpad"
        if 0x130 in keys or 0x120 in keys:
            return "gamepad or joystick"
        if {0, 1} <= set(rels):
            return "mouse"
        if 30 in keys:
            return "keyboard"
        return "input device"

    def summary(self) -> str:
        """The capabilities in one line: event types with counts, axes with range and resolution."""
        parts = [f"{TYPE_NAMES.get(t, hex(t))} x{len(c)}" for t, c in sorted(self.caps.events.items())
                 if c and t != 0]
        res = [f"abs {c:#x} {a.minimum}..{a.maximum}" + (f" @{a.resolution}/mm" if a.resolution else "")
               for c, a in sorted(self.caps.absinfo.items())[:4]]
        return ", ".join(parts + res)

    def as_dict(self) -> dict[str, Any]:
        return {"path": self.path, "name": self.name, "vid_pid": f"{self.vid:04x}:{self.pid:04x}", "bus": self.bus,
                "phys": self.phys, "likely": self.likely, "url": self.url,
                "capabilities": {TYPE_NAMES.get(t, str(t)): sorted(c) for t, c in self.caps.events.items() if c},
                "absinfo": {str(c): [a.minimum, a.maximum, a.fuzz, a.flat, a.resolution]
                            for c, a in self.caps.absinfo.items()}}


def list_input_devices() -> list[InputDeviceInfo]:
    """The input devices this user can open, with their capabilities.

    Raises:
        DeviceUnavailableError: python-evdev is missing.
    """
    evdev = _evdev()
    out = []
    for path in sorted(evdev.list_devices()):
        try:
            dev = evdev.InputDevice(path)
        except OSError as exc:
            log.debug("%s: %s", path, exc)
            continue
        try:
            caps = capabilities_of(dev)
            out.append(InputDeviceInfo(path, caps.name, caps.vendor, caps.product, caps.bus, str(dev.phys or ""),
                                       caps))
        finally:
            dev.close()
    return out


class EvdevTransport(Transport):
    """A live input device node; see the module docstring. It is an ``EvdevSource``."""

    scheme = "evdev"
    usage = "evdev:///dev/input/eventN[?grab=false&clock=monotonic] or evdev://VID:PID"
    options: ClassVar[dict[str, Option]] = {
        "grab": Option(bool, False, "take the device for this capture alone (EVIOCGRAB: the desktop stops seeing"
                       " it)"),
        "clock": Option(str, "monotonic", "the kernel clock of the event times", choices=("monotonic", "realtime")),
        "read_size": Option(int, 256, "input_event records read at most at once", min=1, max=65536),
    }

    def __init__(self, address: str, options: Mapping[str, Any] | None = None, clock: Clock = MONOTONIC) -> None:
        super().__init__(address, options, clock)
        self._fd: int | None = None
        self.path: str | None = None
        self._caps: Capabilities | None = None
        self.clock_id = CLOCK_REALTIME

    def _target(self) -> str:
        m = _VIDPID_RE.match(self.address)
        if not m:
            return self.address
        vid, pid = int(m.group(1), 16), int(m.group(2), 16)
        for d in list_input_devices():
            if (d.vid, d.pid) == (vid, pid):
                return d.path
        raise DeviceNotFoundError(f"no input device with USB id {self.address} is plugged in (perfcap devices lists"
                                  " them)", source=self.url)

    def evdev_capabilities(self) -> Capabilities:
        if self._caps is None:
            evdev = _evdev()
            target = self._target()
            try:
                dev = evdev.InputDevice(target)
            except OSError as exc:
                raise self._open_error(target, exc) from exc
            try:
                self._caps = capabilities_of(dev)
            finally:
                dev.close()
        return self._caps

    def identity_hint(self) -> dict[str, Any]:
        c = self._caps
        if c is None:
            return {"address": self.address}
        return {"vid": c.vendor or None, "pid": c.product or None, "address": self.path or self.address}

    def present(self) -> bool | None:
        if _VIDPID_RE.match(self.address):
            try:
                self._target()
                return True
            except (DeviceNotFoundError, DeviceUnavailableError):
                return False
        return os.path.exists(self.address)

    @property
    def is_open(self) -> bool:
        return self._fd is not None

    def _open_error(self, target: str, exc: OSError) -> Exception:
        if exc.errno in (errno.ENOENT, errno.ENODEV, errno.ENXIO):
            return DeviceNotFoundError(f"input device {target} is not there (unplugged?); perfcap devices lists"
                                       " the input devices present", source=self.url)
        if exc.errno in (errno.EACCES, errno.EPERM):
            return DeviceInitError(f"no permission to open {target}: add your user to the 'input' group (sudo"
                                   " usermod -aG input $USER, then log in again) or give the device a udev rule",
                                   source=self.url)
        return DeviceInitError(f"cannot open {target}: {exc}", source=self.url)

    def open(self) -> None:
        if self._fd is not None:
            return
        self.evdev_capabilities()  # python-evdev is needed for the streams; fail here, clearly, without it
        target = self._target()
        try:
            fd = os.open(target, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
        except OSError as exc:
            raise self._open_error(target, exc) from exc
        self.clock_id = CLOCK_REALTIME
        try:
            if self.opts["clock"] == "monotonic":
                fcntl.ioctl(fd, EVIOCSCLOCKID, CLOCK_MONOTONIC.to_bytes(4, "little", signed=True))
                self.clock_id = CLOCK_MONOTONIC
            if self.opts["grab"]:
                fcntl.ioctl(fd, EVIOCGRAB, (1).to_bytes(4, "little"))
        except OSError as exc:
            os.close(fd)
            if exc.errno == errno.EBUSY:
                raise DeviceInitError(f"{target} is grabbed by another program (grab=true there); close it",
                                      source=self.url) from exc
            raise DeviceInitError(f"{target}: cannot set up the device ({exc})", source=self.url) from exc
        self._fd = fd
        self.path = target
        log.debug("opened %s (%s event times%s)", target, self.opts["clock"], ", grabbed" if self.opts["grab"] else "")

    def close(self) -> None:
        fd, self._fd = self._fd, None
        if fd is not None:
            try:
                os.close(fd)  # closing releases a grab
            except OSError as exc:
                log.debug("%s: close: %s", self.path, exc)

    def read(self, timeout: float) -> Chunk | None:
        fd = self._fd
        if fd is None:
            raise DeviceIOError(f"{self.url}: read on a closed device", source=self.url)
        try:
            ready, _, _ = select.select((fd,), (), (), max(0.0, timeout))
            if not ready:
                return None
            data = os.read(fd, EVENT_SIZE * self.opts["read_size"])
        except BlockingIOError:
            return None
        except (OSError, ValueError) as exc:  # ENODEV: unplugged
            raise self._lost(str(exc)) from exc
        t = self.clock.now_ns()
        if not data:
            raise self._lost("the node reports data but returns none")
        return Chunk(data, t, Direction.RX)

    def _lost(self, why: str) -> DeviceIOError:
        gone = self.path is not None and not os.path.exists(self.path)
        return DeviceIOError(f"input device {self.path} {'vanished' if gone else 'failed'} (unplugged?): {why}",
                             source=self.url)


__all__ = ["AbsInfo", "Capabilities", "EvdevSource", "EvdevTransport", "InputDeviceInfo", "capabilities_of",
           "list_input_devices"]
