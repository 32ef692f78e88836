"""``DeviceReader``, the one thread per device that polls it and publishes onto the bus, and its reconnect
policy: an unplugged device is retried with backoff and comes back with the same stream names, sequence
numbering and calibration; the gap is an event in the session.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING

from capture.errors import CaptureError, DeviceError, EndOfStream, ProtocolError
from capture.sample import DeviceEvent, EventKind
from devices.base import Device, DeviceState

if TYPE_CHECKING:
    from capture.bus import SampleBus

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReconnectPolicy:
    """How a reader retries an unplugged device: exponential backoff from ``initial_s`` to ``max_s``;
    ``give_up_after_s`` (None = never) ends the device as FAILED."""

    enabled: bool = True
    initial_s: float = 0.2
    max_s: float = 5.0
    factor: float = 2.0
    give_up_after_s: float | None = None


class DeviceReader:
    """The thread that polls one device and publishes what it yields onto the bus."""

    def __init__(self, device: Device, bus: SampleBus, policy: ReconnectPolicy = ReconnectPolicy(),
                 poll_timeout: float = 0.1) -> None:
        self.device = device
        self.bus = bus
        self.policy = policy
        self.poll_timeout = poll_timeout
        self.presence_poll_s = 0.02
        self._stop = threading.Event()
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=f"reader-{device.name}", daemon=True)

    def start(self) -> DeviceReader:
        self._thread.start()
        return self

    def stop(self, timeout: float | None = 5.0) -> None:
        self._stop.set()
        if self._thread.ident is not None and threading.current_thread() is not self._thread:
            self._thread.join(timeout)

    def join(self, timeout: float | None = None) -> bool:
        self._thread.join(timeout)
        return not self._thread.is_alive()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def _event(self, kind: EventKind, detail: str = "") -> None:
        self.bus.publish(DeviceEvent(self.device.name, kind, self.device.clock.now_ns(), detail))

    def _run(self) -> None:
        dev = self.device
        publish_many = self.bus.publish_many
        try:
            try:
                publish_many(dev.open())
            except DeviceError as exc:
                if not self._reconnect(exc, first=True):
                    return
            self._event(EventKind.STREAMING)
            while not self._stop.is_set():
                try:
                    items = dev.poll(self.poll_timeout)
                except EndOfStream:
                    publish_many(dev.finish())
                    dev.state = DeviceState.FINISHED
                    self._event(EventKind.FINISHED, "source exhausted")
                    return
                except ProtocolError:
                    raise
                except DeviceError as exc:
                    if not self._reconnect(exc):
                        return
                    continue
                if items:
                    publish_many(items)
            publish_many(dev.finish())
            dev.state = DeviceState.CLOSED
        except CaptureError as exc:
            self.error = exc
            dev.state = DeviceState.FAILED
            log.error("device %s failed: %s", dev.name, exc)
            self._event(EventKind.FAILED, str(exc))
        except Exception as exc:  # a bug in one device must not take the others down
            self.error = exc
            dev.state = DeviceState.FAILED
            log.error("device %s stopped by an internal error: %s: %s (rerun with -vv for the traceback)",
                      dev.name, type(exc).__name__, exc)
            log.debug("traceback of the internal error in device %s", dev.name, exc_info=True)
            self._event(EventKind.FAILED, f"internal error: {type(exc).__name__}: {exc}")
        finally:
            try:
                dev.close()
            except DeviceError as exc:
                log.warning("device %s: close failed: %s", dev.name, exc)
            try:
                self.bus.publish_many(dev.clock_states())
            except Exception:
                log.exception("device %s: final clock state not published", dev.name)

    def _reconnect(self, exc: BaseException, first: bool = False) -> bool:
        """Retry until the device is back (True) or the policy gives up / stop is asked (False)."""
        dev = self.device
        pol = self.policy
        t_lost = dev.clock.now_ns()
        dev.last_error = str(exc)
        if not first:
            log.warning("device %s lost: %s", dev.name, exc)
            self._event(EventKind.DISCONNECTED, str(exc))
        elif pol.enabled:
            log.warning("device %s cannot be opened: %s; waiting for it (it is opened as soon as it appears)",
                        dev.name, exc)
        if not pol.enabled:
            if first:
                raise exc
            dev.state = DeviceState.FAILED
            self._event(EventKind.FAILED, f"disconnected and reconnect is off: {exc}")
            self.error = exc
            return False
        dev.state = DeviceState.RECONNECTING
        self._event(EventKind.RECONNECTING, str(exc))
        delay = pol.initial_s
        was_present = dev.transport.present()
        while True:
            go = self._wait_for_device(delay, was_present)
            if go is None:
                return False
            was_present = go
            try:
                dev.transport.close()
            except DeviceError:
                pass
            try:
                items = dev.open()
            except EndOfStream:  # the source ended while the device was away (a service shutting down)
                dev.state = DeviceState.FINISHED
                self._event(EventKind.FINISHED, "source ended while the device was away")
                return False
            except DeviceError as again:
                elapsed = (dev.clock.now_ns() - t_lost) / 1e9
                if pol.give_up_after_s is not None and elapsed > pol.give_up_after_s:
                    dev.state = DeviceState.FAILED
                    self.error = again
                    self._event(EventKind.FAILED, f"gave up after {elapsed:.1f} s: {again}")
                    return False
                if str(again) != dev.last_error:  # a new reason is news; the same one again is not
                    log.warning("device %s still cannot be opened: %s", dev.name, again)
                dev.last_error = str(again)
                delay = min(pol.max_s, delay * pol.factor)
                continue
            dropped = dev.reset_after_reconnect()
            dev.stats.reconnects += 1
            self.bus.publish_many(items)
            gap = (dev.clock.now_ns() - t_lost) / 1e9
            self._event(EventKind.RECONNECTED, f"gap {gap:.3f} s; {dropped} partial bytes discarded")
            log.warning("device %s is back after %.2f s", dev.name, gap)
            return True

    def _wait_for_device(self, delay: float, was_present: bool | None) -> bool | None:
        """Wait ``delay`` seconds before the next open attempt, but go at once when the transport
        sees the device come back (absent -> present). Returns whether it is present now (None:
        stop was asked)."""
        transport = self.device.transport
        if was_present is None:
            return None if self._stop.wait(delay) else False
        step = min(self.presence_poll_s, delay) if delay > 0 else 0.0
        steps = max(1, math.ceil(delay / step)) if step > 0 else 1
        present: bool | None = was_present
        for _ in range(steps):
            if self._stop.wait(step):
                return None
            present = transport.present()
            if present and not was_present:
                return True
            if present is not None:
                was_present = present
        return bool(present)
