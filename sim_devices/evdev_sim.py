"""``simevdev://`` - an evemu recording replayed as the kernel's ``struct input_event`` records.

    simevdev:///path/to/tablet.stylus-drag.events     events with the .desc beside them
    simevdev:///path/to/controller.evemu              a single-file evemu-record recording

Each SYN_REPORT frame of the recording (``sim_devices.evemu``) becomes one chunk of input_event
bytes carrying the recorded event times, as a read of ``/dev/input/eventN`` gives them, so the real
``EvdevCodec`` and ``evdev`` device kind decode it. The capabilities come from the description
(``B:`` and ``A:`` lines), widened by the codes the events use. A frame arrives ``latency_ms`` after
its recorded time (plus up to ``jitter_ms``), counted from the open: at wall-clock pace, or on a
virtual clock, as fast as read (``realtime=false``, for CI).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError, DeviceIOError, EndOfStream, TraceError
from capture.sample import Chunk, Direction
from devices.evdev import EV_ABS, EV_SYN, AbsInfo, Capabilities, EvdevCodec, EvdevFrame
from devices.options import Option
from devices.transports.base import Transport
from sim_devices import evemu

if TYPE_CHECKING:
    from collections.abc import Mapping


def capabilities_from_evemu(dev: evemu.EvemuDevice, frames: list[evemu.Frame]) -> Capabilities:
    """The capabilities an evemu description gives, widened by the codes its events use."""
    events: dict[int, set[int]] = {t: set(c) for t, c in dev.bits.items() if t != EV_SYN}
    for fr in frames:
        for typ, code, _ in fr.events:
            events.setdefault(typ, set()).add(code)
    absinfo = {c: AbsInfo(a.minimum, a.maximum, a.fuzz, a.flat, a.resolution) for c, a in dev.absinfo.items()}
    for c in events.get(EV_ABS, set()):
        absinfo.setdefault(c, AbsInfo(-(1 << 31), (1 << 31) - 1))
    events.setdefault(EV_ABS, set()).update(absinfo)
    return Capabilities(name=dev.name, bus=dev.bus, vendor=dev.vendor, product=dev.product, version=dev.version,
                        events={t: frozenset(c) for t, c in events.items() if c}, absinfo=absinfo,
                        props=frozenset(dev.props))


class SimEvdevTransport(Transport):
    """An evemu recording as an input device node; see the module docstring. It is an
    ``EvdevSource`` (``devices.transports.evdev``)."""

    scheme = "simevdev"
    usage = "simevdev:///PATH.events[?realtime=true&latency_ms=0.2]"
    options: ClassVar[dict[str, Option]] = {
        "realtime": Option(bool, True, "deliver at wall-clock pace (false: virtual clock, as fast as read)"),
        "latency_ms": Option(float, 0.2, "how long after its kernel time a frame arrives", min=0.0, max=10_000.0),
        "jitter_ms": Option(float, 0.0, "uniform extra arrival delay, 0..this", min=0.0, max=10_000.0),
        "seed": Option(int, 1, "jitter seed", min=0),
        "loop": Option(bool, False, "start over at the end (times keep increasing)"),
    }

    def __init__(self, address: str, options: Mapping[str, Any] | None = None, clock: Clock = MONOTONIC) -> None:
        super().__init__(address, options, clock)
        if not address:
            raise ConfigError("simevdev:// needs the path of an evemu recording", source=self.url)
        try:
            desc = evemu.description_for(address)
            self.frames = evemu.parse_events(address)
        except TraceError as exc:
            raise ConfigError(f"{self.url}: {exc}", source=self.url) from None
        if desc is None:
            raise ConfigError(f"{self.url}: the recording has no device description (N:/I:/B:/A: lines) and no"
                              " .desc file beside it", source=self.url)
        if not self.frames:
            raise ConfigError(f"{self.url}: the recording holds no SYN_REPORT frame", source=self.url)
        self.caps = capabilities_from_evemu(desc, self.frames)
        self._codec = EvdevCodec()
        self._open = False
        self._i = 0
        self._pass = 0
        self._virtual_ns = 0
        self._t0_ns = 0
        self.opens = 0
        t = [round(f.t * 1e6) for f in self.frames]
        self._ticks = t
        n = len(t)
        self._span_us = (t[-1] - t[0]) + ((t[-1] - t[0]) // (n - 1) if n > 1 else 1000)
        self._rng = np.random.default_rng(self.opts["seed"])

    # -- what the device learns before open -------------------------------------------------------------
    def evdev_capabilities(self) -> Capabilities:
        return self.caps

    def implied_kind(self) -> str:
        return "evdev"

    def identity_hint(self) -> dict[str, Any]:
        return {"vid": self.caps.vendor or None, "pid": self.caps.product or None}

    def present(self) -> bool:
        return True

    # -- I/O ---------------------------------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._open

    def _now(self) -> int:
        return self.clock.now_ns() if self.opts["realtime"] else self._virtual_ns

    def open(self) -> None:
        if not self.opts["realtime"] and not self.opens:
            self._virtual_ns = self.clock.now_ns()
        self._t0_ns = self._now()
        self._i = 0
        self._pass = 0
        self._open = True
        self.opens += 1

    def close(self) -> None:
        self._open = False

    def frame_bytes(self, i: int, shift_us: int = 0) -> bytes:
        """Frame ``i`` as input_event records at its recorded time (shifted by ``shift_us``)."""
        fr = self.frames[i]
        return self._codec.encode(EvdevFrame(self._ticks[i] + shift_us, fr.events))

    def arrival_ns(self, i: int, shift_us: int = 0) -> int:
        """When frame ``i`` arrives on the host clock (without jitter)."""
        return self._t0_ns + (self._ticks[i] + shift_us - self._ticks[0]) * 1000 + \
            int(self.opts["latency_ms"] * 1e6)

    def read(self, timeout: float) -> Chunk | None:
        if not self._open:
            raise DeviceIOError(f"{self.url}: read on a closed device", source=self.url)
        if self._i >= len(self.frames):
            if not self.opts["loop"]:
                raise EndOfStream(f"{self.url}: the recording is over", source=self.url)
            self._i = 0
            self._pass += 1
        shift = self._pass * self._span_us
        jitter = int(self._rng.uniform(0.0, self.opts["jitter_ms"]) * 1e6) if self.opts["jitter_ms"] else 0
        due = self.arrival_ns(self._i, shift) + jitter
        if self.opts["realtime"]:
            now = self.clock.now_ns()
            if due > now + timeout * 1e9:
                self.clock.sleep_until_ns(now + int(timeout * 1e9))
                return None
            self.clock.sleep_until_ns(due)
        else:
            self._virtual_ns = max(self._virtual_ns, due)
            due = self._virtual_ns
        data = self.frame_bytes(self._i, shift)
        self._i += 1
        return Chunk(data, due, Direction.RX)
