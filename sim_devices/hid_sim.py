"""``simhid://`` - simulated HID devices behind the same calls as a live hidapi device.

A *responder* plays the device: it has a report descriptor, answers feature-report reads and
writes and output reports (handshakes, subcommands) the way the real device does, and streams
input reports with their device-side times. The transport turns device time into arrival time
(clock drift, latency, jitter), paces delivery (wall clock, or a virtual clock for CI), and
injects faults: an unplug window, a device that never answers, one that answers wrongly (the
responders' ``handshake`` option).

    simhid://dualsense?seed=2&bus=bluetooth        a synthetic controller (responders below)
    simhid:///path/to/capture.hid                  a hid-recorder capture, at its recorded timing

Responder names map to ``(module, class)`` in ``RESPONDERS``; each module also holds the
responder's motion synthesis, encoded through the real codecs' encoders. With ``truth=true`` the
transport keeps when each report was really sent; that, the simulated latency and drift, and the
responder's motion are its ``SimulatorTruth`` ability (``devices.transports.base``).
"""

from __future__ import annotations

import abc
import collections
import importlib
import os
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError, DeviceIOError, DeviceNotFoundError, DeviceUnavailableError, EndOfStream
from capture.sample import Chunk, Direction
from devices.options import Option, resolve_options
from devices.transports.base import Transport
from devices.transports.hid import HidTransportBase

if TYPE_CHECKING:
    from collections.abc import Iterator, Mapping

    from devices.transports.base import SimulatorTruth
    from sim_devices.motion import WavingMotion

#: responder name -> (module, class)
RESPONDERS: dict[str, tuple[str, str]] = {
    "ds4": ("sim_devices.sony_sim", "DualShock4Responder"),
    "dualsense": ("sim_devices.sony_sim", "DualSenseResponder"),
    "switchpro": ("sim_devices.nintendo_sim", "SwitchProResponder"),
    "joycon_l": ("sim_devices.nintendo_sim", "JoyConLeftResponder"),
    "joycon_r": ("sim_devices.nintendo_sim", "JoyConRightResponder"),
    "mouse": ("sim_devices.hid_generic_sim", "MouseResponder"),
    "pen": ("sim_devices.hid_generic_sim", "PenResponder"),
    "touch": ("sim_devices.hid_generic_sim", "TouchResponder"),
    "hidrecord": ("sim_devices.hid_recorder", "HidRecorderResponder"),
}


class HidResponder(abc.ABC):
    """The device side of a simulated HID device.

    Args:
        opts: the URL options this responder declares in ``options`` (already checked), plus
            ``seed`` and ``bus`` from the transport.
        address: the URL address (a file path for file-backed responders).
    """

    #: the perfcap device kind it imitates (``simhid://dualsense`` implies ``dualsense@``)
    kind: ClassVar[str] = ""
    #: USB ids and product name (class defaults; a recorded device sets its own)
    vid: int = 0
    pid: int = 0
    product: str = ""
    #: responder-specific URL options
    options: ClassVar[dict[str, Option]] = {}
    #: the motion the responder's reports carry, when it synthesises one
    motion: WavingMotion | None = None

    def __init__(self, opts: Mapping[str, Any], address: str = "") -> None:
        self.opts = dict(opts)
        self.address = address
        self.bus: str = str(self.opts.get("bus", "usb"))
        self.serial: str = str(self.opts.get("serial", "") or f"SIM{int(self.opts.get('seed', 1)):04d}")
        self.rng = np.random.default_rng(int(self.opts.get("seed", 1)))
        self._replies: collections.deque[bytes] = collections.deque()
        #: every report the host sent, in order: ("feature" | "output", bytes)
        self.received: list[tuple[str, bytes]] = []

    # -- what the host sees --------------------------------------------------------------------------
    @abc.abstractmethod
    def report_descriptor(self) -> bytes:
        """The HID report descriptor."""

    def get_feature(self, report_id: int) -> bytes | None:
        """The feature report (its ID first), or ``None`` if the device has none by that ID."""
        return None

    def set_feature(self, data: bytes) -> None:  # noqa: B027 - an optional hook; by default nothing happens
        """A feature report written by the host (its ID first)."""

    def output(self, data: bytes) -> None:  # noqa: B027 - an optional hook
        """An output report written by the host (its ID first); answer with ``reply``."""

    def on_open(self) -> None:  # noqa: B027 - an optional hook
        """The host opened the device (again); ``bus`` may have changed (a replug over Bluetooth)."""

    def reply(self, report: bytes) -> None:
        """Queue an input report that answers the host; delivered before the next streamed one."""
        self._replies.append(bytes(report))

    def take_reply(self) -> bytes | None:
        return self._replies.popleft() if self._replies else None

    @abc.abstractmethod
    def stream(self) -> Iterator[tuple[float, bytes]]:
        """Input reports as ``(device time in s since power-on, report)``, in time order; may be
        endless. Called once per open (a replug starts a new stream); read lazily, so what it yields
        can depend on what the host has sent by then (streaming enabled by a subcommand)."""


def _responder_name(address: str) -> str:
    return "hidrecord" if address.startswith("/") or address.endswith(".hid") else address


def responder_class(name: str) -> type[HidResponder]:
    if name not in RESPONDERS:
        raise ConfigError(f"simhid://{name}: no simulated HID device of that name; known:"
                          f" {', '.join(sorted(RESPONDERS))} or simhid:///PATH.hid (a hid-recorder capture)")
    mod, cls = RESPONDERS[name]
    obj = getattr(importlib.import_module(mod), cls)
    if not (isinstance(obj, type) and issubclass(obj, HidResponder)):
        raise DeviceUnavailableError(f"simhid://{name}: {mod}.{cls} is not a HidResponder", source=name)
    return obj


class SimHidTransport(Transport, HidTransportBase):
    """A simulated HID device; see the module docstring. It is a ``SimulatorTruth``."""

    scheme = "simhid"
    usage = "simhid://NAME[?options] or simhid:///PATH.hid"
    options: ClassVar[dict[str, Option]] = {
        "seed": Option(int, 1, "motion and noise seed", min=0),
        "bus": Option(str, "usb", "the bus the device is on", choices=("usb", "bluetooth")),
        "serial": Option(str, "", "serial number (default from the seed)"),
        "realtime": Option(bool, True, "deliver at wall-clock pace (false: virtual clock, as fast as read)"),
        "duration": Option(float, 0.0, "seconds of device time, then end of stream (0 = endless)", min=0.0),
        "drift_ppm": Option(float, 0.0, "device clock runs fast by this much", min=-5000, max=5000),
        "latency_ms": Option(float, 0.5, "fixed link latency", min=0.0),
        "jitter_ms": Option(float, 0.0, "uniform extra arrival delay, 0..this", min=0.0),
        "reply_ms": Option(float, 2.0, "delay of a handshake reply", min=0.0),
        "unplug_at": Option(float, 0.0, "the device vanishes at this second after the first open (0 = never)",
                            min=0.0),
        "unplug_for": Option(float, 1.0, "and comes back after this many seconds", min=0.0),
        "truth": Option(bool, False, "keep the true time and the scheduled arrival of every streamed report (tests)"),
        "replug_bus": Option(str, "", "after an unplug the device comes back on this bus (usb|bluetooth;"
                             " empty: the same)", choices=("", "usb", "bluetooth")),
        "buffer": Option(int, 64, "reports the OS keeps for a reader that falls behind (Linux hidraw: 64); older"
                         " ones are lost and counted", min=1, max=1 << 20),
    }

    @classmethod
    def extra_options(cls, address: str) -> Mapping[str, Option]:
        try:
            return responder_class(_responder_name(address)).options
        except ConfigError:
            return {}

    def __init__(self, address: str, options: Mapping[str, Any] | None = None, clock: Clock = MONOTONIC) -> None:
        given = dict(options or {})
        cls = responder_class(_responder_name(address))
        own = {k: given.pop(k) for k in list(given) if k in cls.options and k not in self.options}
        super().__init__(address, given, clock)
        self._given = {**given, **own}
        ropts = resolve_options(cls.options, own, f"simhid://{address}", self.usage)
        self.responder = cls({**self.opts, **ropts}, address)
        self.bus = self.responder.bus
        self._open = False
        self._t_first_open: int | None = None
        self._virtual_ns = 0
        self._it: Iterator[tuple[float, bytes]] | None = None
        self._next: tuple[int, int, bytes] | None = None  # (true ns, arrival ns, report)
        self._t0 = 0
        self._last_arrival = 0
        #: with ``truth``: per streamed report, its true time (when the device sent it, on the host
        #: clock) and the arrival the transport scheduled (plus latency and jitter)
        self.truth_ns: list[int] = []
        self.arrival_ns: list[int] = []
        self.opens = 0
        #: streamed reports: sent by the device (delivered or lost), and lost in an overflowing buffer
        self.sent = 0
        self.dropped = 0
        self._due: collections.deque[tuple[int, int, bytes]] = collections.deque()

    # -- SimulatorTruth ------------------------------------------------------------------------------
    @property
    def latency_ns(self) -> int:
        """The simulated fixed link latency (option ``latency_ms``), ns."""
        return int(self.opts["latency_ms"] * 1e6)

    @property
    def drift_ppm(self) -> float:
        """The simulated device clock drift (option ``drift_ppm``), ppm."""
        return float(self.opts["drift_ppm"])

    @property
    def motion(self) -> WavingMotion | None:
        """The responder's motion (a controller's waving), or ``None`` (a recorded capture)."""
        return self.responder.motion

    # -- identity -------------------------------------------------------------------------------------
    def implied_kind(self) -> str | None:
        return self.responder.kind or None

    def identity_hint(self) -> dict[str, Any]:
        r = self.responder
        return {"vid": r.vid or None, "pid": r.pid or None, "serial": r.serial or None}

    # -- time -----------------------------------------------------------------------------------------
    def _now(self) -> int:
        return self.clock.now_ns() if self.opts["realtime"] else self._virtual_ns

    def _unplugged(self, now_ns: int) -> bool:
        if not self.opts["unplug_at"] or self._t_first_open is None:
            return False
        s = (now_ns - self._t_first_open) / 1e9
        return bool(self.opts["unplug_at"] <= s < self.opts["unplug_at"] + self.opts["unplug_for"])

    def present(self) -> bool | None:
        if self._unplugged(self._now()):
            if not self.opts["realtime"]:  # a virtual clock only moves when asked: waiting moves it
                assert self._t_first_open is not None
                self._virtual_ns = self._t_first_open + int((self.opts["unplug_at"] + self.opts["unplug_for"]) * 1e9)
            return False
        return True

    # -- life cycle -----------------------------------------------------------------------------------
    def open(self) -> None:
        now = self._now()
        if self._t_first_open is None:
            self._t_first_open = now
        elif self._unplugged(now):
            raise DeviceNotFoundError(f"{self.url}: no such HID device (simulated unplug)", source=self.url)
        if self.opens and self.opts["replug_bus"]:
            self.bus = self.responder.bus = self.opts["replug_bus"]
        self.responder.on_open()
        self._t0 = now
        self._last_arrival = now
        self._it = self.responder.stream()
        self._next = None
        self._due.clear()
        self._open = True
        self.opens += 1

    def close(self) -> None:
        self._open = False
        self._it = None

    @property
    def is_open(self) -> bool:
        return self._open

    def _check(self) -> int:
        if not self._open:
            raise DeviceIOError(f"{self.url}: the device is closed", source=self.url)
        now = self._now()
        if self._unplugged(now):
            self._open = False
            raise DeviceIOError(f"{self.url}: the device was unplugged (simulated)", source=self.url)
        return now

    def _arrival(self, t_dev_s: float) -> tuple[int, int]:
        """(true time, scheduled arrival) of a report the device sends at ``t_dev_s``."""
        o = self.opts
        true = self._t0 + int(t_dev_s / (1.0 + o["drift_ppm"] * 1e-6) * 1e9)
        t = true + int(o["latency_ms"] * 1e6)
        if o["jitter_ms"]:
            t += int(self.responder.rng.uniform(0.0, o["jitter_ms"]) * 1e6)
        return true, max(t, self._last_arrival)  # a USB pipe keeps order

    def _peek(self) -> tuple[int, int, bytes] | None:
        if self._next is None and self._due:
            self._next = self._due.popleft()
        if self._next is None and self._it is not None:
            try:
                t_dev, rep = next(self._it)
            except StopIteration:
                self._it = None
                return None
            if self.opts["duration"] and t_dev > self.opts["duration"]:
                self._it = None
                return None
            self._next = (*self._arrival(t_dev), bytes(rep))
        return self._next

    # -- I/O ----------------------------------------------------------------------------------------------
    def read(self, timeout: float) -> Chunk | None:
        now = self._check()
        rep = self.responder.take_reply()
        if rep is not None:
            t = max(now + int(self.opts["reply_ms"] * 1e6), self._last_arrival)
            if self.opts["realtime"]:
                self.clock.sleep_until_ns(t)
                t = self.clock.now_ns()
            else:
                self._virtual_ns = t
            self._last_arrival = t
            return Chunk(rep, t)
        nxt = self._peek()
        if nxt is None:
            if self._it is None:
                raise EndOfStream(f"{self.url}: end of the simulated stream")
            return None
        true, t, data = nxt
        if self.opts["realtime"]:
            if t <= now:
                true, t, data = self._overflow(now)
            deadline = now + int(timeout * 1e9)
            if t > deadline:
                self.clock.sleep_until_ns(deadline)
                return None
            self.clock.sleep_until_ns(t)
            stamp = self.clock.now_ns()
        else:
            self._virtual_ns = max(self._virtual_ns, t)
            stamp = t
        self._next = None
        self._last_arrival = t
        self.sent += 1
        if self.opts["truth"]:
            self.truth_ns.append(true)
            self.arrival_ns.append(t)
        return Chunk(data, stamp)

    def _overflow(self, now: int) -> tuple[int, int, bytes]:
        """A reader that fell behind: the OS keeps only the newest ``buffer`` reports that have
        arrived (Linux hidraw: 64 per reader); older ones are lost, as on a real device, and counted.
        Called when the next report is due; returns the oldest one kept, which is then next."""
        due: list[tuple[int, int, bytes]] = []
        later = None
        while True:
            nxt = self._peek()
            self._next = None
            if nxt is None:
                break
            if nxt[1] > now:
                later = nxt
                break
            due.append(nxt)
        keep = self.opts["buffer"]
        if len(due) > keep:
            lost = len(due) - keep
            self.dropped += lost
            self.sent += lost
            due = due[lost:]
        self._due.extend(due)
        if later is not None:
            self._due.append(later)
        nxt = self._next = self._due.popleft()  # the due report that called this, at least, is kept
        return nxt

    def write(self, data: bytes) -> Chunk:
        self._check()
        self.responder.received.append(("output", bytes(data)))
        self.responder.output(bytes(data))
        return self.stamp_tx(data)

    def send_feature_report(self, data: bytes) -> Chunk:
        self._check()
        self.responder.received.append(("feature", bytes(data)))
        self.responder.set_feature(bytes(data))
        return self.stamp_tx(data)

    def get_feature_report(self, report_id: int, length: int) -> bytes:
        self._check()
        rep = self.responder.get_feature(report_id)
        if rep is None:
            raise DeviceIOError(f"{self.url}: feature report 0x{report_id:02x} is not supported by the device",
                                source=self.url)
        return bytes(rep[:length])

    def report_descriptor(self) -> bytes:
        """Readable before open, as a live device's is (sysfs, or a brief open); not while unplugged."""
        if self._unplugged(self._now()):
            raise DeviceNotFoundError(f"{self.url}: no such HID device (simulated unplug)", source=self.url)
        return self.responder.report_descriptor()

    def stamp_tx(self, data: bytes) -> Chunk:
        return Chunk(bytes(data), self._now(), Direction.TX)


if TYPE_CHECKING:  # the ability it declares, checked by mypy
    _truth: type[SimulatorTruth] = SimHidTransport


def trace_path(address: str) -> str:
    """The file a file-backed address names, checked to exist."""
    path = address if address.startswith("/") else os.path.abspath(address)
    if not os.path.isfile(path):
        raise ConfigError(f"simhid://{address}: no such file")
    return path
