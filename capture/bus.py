"""The sample bus: thread-safe publish/subscribe with a queue and an overflow policy per subscriber.

Publishers (device reader threads) call :meth:`SampleBus.publish` or :meth:`SampleBus.publish_many`;
neither ever blocks on a subscriber. Each subscriber has its own queue and its own delivery
thread, so a slow subscriber only grows (or trims) its own queue, and one that raises is counted,
logged and, after ``max_errors`` failures, detached, while every other subscriber carries on.

Overflow policies (declared per subscriber):

* ``Overflow.NEVER_DROP`` - for recorders. The queue grows; its memory is estimated and bounded
  by ``max_bytes``. Falling behind is logged loudly (warnings at 25/50/75% of the bound). Only when
  the bound itself is reached are items dropped, each one counted and the first logged as an error,
  so the host never runs out of memory silently.
* ``Overflow.KEEP_NEWEST`` - for live consumers. At most ``max_items`` wait; when full the oldest
  is discarded and counted.

Single samples and :class:`~capture.sample.SampleBatch` columns both travel; subscribers choose the
item types they accept, and items nobody accepts cost one type check per subscriber.
"""

from __future__ import annotations

import abc
import enum
import logging
import queue
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from capture.clock import MONOTONIC, Clock
from capture.sample import (
    ClockState,
    DeviceChunk,
    DeviceChunks,
    DeviceDescriptor,
    DeviceEvent,
    EventKind,
    Sample,
    SampleBatch,
)

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable

    from capture.sample import StreamInfo

log = logging.getLogger(__name__)

SAMPLES: frozenset[type] = frozenset({Sample, SampleBatch})
EVERYTHING: frozenset[type] = frozenset({Sample, SampleBatch, DeviceChunk, DeviceChunks, ClockState, DeviceEvent,
                                         DeviceDescriptor})

_STOP = object()


class Overflow(enum.Enum):
    """What a subscriber's queue does when the subscriber falls behind."""

    NEVER_DROP = "never_drop"
    KEEP_NEWEST = "keep_newest"


class Subscriber:
    """Base class for bus consumers (like python-can's ``Listener``).

    Override :meth:`on_item` (called on the subscriber's own thread, in publish order), and
    optionally :meth:`on_idle` (called every ``idle_interval_s`` while the queue is empty),
    :meth:`on_error` and :meth:`stop`.
    """

    #: Item types delivered to this subscriber.
    accepts: frozenset[type] = SAMPLES
    #: Seconds between ``on_idle`` calls when nothing arrives; ``None`` for never.
    idle_interval_s: float | None = None
    #: A processor publishes derived items back onto the bus (orientation from IMU samples). On
    #: close, processors are drained first, so what they publish last still reaches the recorder.
    publishes: bool = False
    #: Seconds a subscriber that does not need low latency (the recorder, counters) lets items
    #: gather after it has emptied its queue, instead of being woken for every item: far fewer
    #: thread wake-ups when many small items arrive (phones over the network). 0: woken per item.
    coalesce_s: float = 0.0

    def on_item(self, item: Any) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def on_idle(self) -> None:
        """Called when the queue has been empty for ``idle_interval_s``."""

    def on_error(self, exc: BaseException) -> None:
        """Called after :meth:`on_item` raised ``exc`` (the item is lost for this subscriber)."""

    def stop(self) -> None:
        """Called once on the delivery thread after the last item."""


class Processor(Subscriber, abc.ABC):
    """A subscriber that publishes derived streams back onto the bus (orientation from IMU samples, the
    puppet's pose from a phone). It declares its streams before data flows, so the recorder knows them,
    and is handed the bus's publish function."""

    @abc.abstractmethod
    def output_streams(self) -> list[StreamInfo]:
        """The streams this processor publishes."""

    @abc.abstractmethod
    def bind(self, publish: Callable[[Any], None]) -> None:
        """Where to publish what it derives (``SampleBus.publish``)."""


def item_size(item: Any) -> int:
    """Rough memory held by a queued item, for the recorder's memory bound."""
    if type(item) is Sample:
        return 200 + 24 * len(item.values)
    if type(item) is SampleBatch:
        return 200 + item.nbytes
    if type(item) is DeviceChunk:
        return 150 + len(item.chunk.data)
    if type(item) is DeviceChunks:
        return 100 + 150 * len(item.chunks) + len(item.chunks.data)
    return 300


@dataclass
class SubscriptionStats:
    """Counters of one subscription, safe to read from any thread."""

    name: str
    policy: str
    delivered: int
    dropped: int
    errors: int
    pending: int
    pending_bytes: int
    max_pending: int
    detached: bool


class Subscription:
    """One subscriber's queue, delivery thread and counters."""

    def __init__(self, bus: SampleBus, sub: Subscriber, name: str, policy: Overflow,
                 max_items: int, max_bytes: int, max_errors: int) -> None:
        self.bus = bus
        self.subscriber = sub
        self.name = name
        self.policy = policy
        self.accepts = sub.accepts
        self.max_items = max_items
        self.max_bytes = max_bytes
        self.max_errors = max_errors
        self._q: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self.delivered = 0
        self.dropped = 0
        self.errors = 0
        self.detached = False
        self.max_pending = 0
        self._mean_size = 250.0
        self._k = 0
        self._quarter = max_bytes / 4
        self._warn_level = 0
        self._thread = threading.Thread(target=self._run, name=f"bus-{name}", daemon=True)
        self._stopping = threading.Event()
        #: hand one item to this subscription (any thread): the policy's method, bound once so that
        #: publishing costs one call; a detached subscription only counts what it no longer gets
        self.offer: Callable[[Any], None] = (
            self._offer_never_drop if policy is Overflow.NEVER_DROP else self._offer_keep_newest)

    # -- publisher side (any thread) -------------------------------------------------------------

    def offer_detached(self, item: Any) -> None:
        with self._lock:
            self.dropped += 1

    def _offer_keep_newest(self, item: Any) -> None:
        q = self._q
        n = q.qsize()
        if n > self.max_pending:
            self.max_pending = n
        if n >= self.max_items:
            try:
                q.get_nowait()
                with self._lock:
                    self.dropped += 1
            except queue.Empty:
                pass
        q.put(item)

    def _offer_never_drop(self, item: Any) -> None:
        # Memory is estimated as queue length x a running mean item size (no lock on the hot path;
        # the estimate only needs to be right to a few percent to enforce a bound of megabytes).
        # Big items (batches, chunk runs) always update the mean; single samples every 16th.
        q = self._q
        n = q.qsize()
        if n > self.max_pending:
            self.max_pending = n
        if type(item) is Sample:
            self._k = (self._k + 1) & 15
            if not self._k:
                self._mean_size += (200 + 24 * len(item.values) - self._mean_size) * 0.05
        else:
            self._mean_size += (item_size(item) - self._mean_size) * 0.05
        pending = (n + 1) * self._mean_size
        if pending <= self._quarter and not self._warn_level:
            q.put(item)
            return
        warn = 0
        with self._lock:
            if pending > self.max_bytes:
                self.dropped += 1
                dropped = self.dropped
            else:
                dropped = 0
                if self._warn_level < 3 and pending * 4 > (self._warn_level + 1) * self.max_bytes:
                    self._warn_level += 1
                    warn = self._warn_level
        if dropped:
            if dropped == 1:
                log.error("subscriber %s reached its memory bound of %.0f MB and is dropping items (counted)",
                          self.name, self.max_bytes / 1e6)
                self.bus._overflowed(self)
            elif dropped % 10000 == 0:
                log.error("subscriber %s: %d items dropped at its memory bound", self.name, dropped)
            return
        if warn:
            log.warning("subscriber %s is falling behind: %.1f MB queued (%d%% of its %.0f MB bound)",
                        self.name, pending / 1e6, 25 * warn, self.max_bytes / 1e6)
        self._q.put(item)

    # -- delivery thread ---------------------------------------------------------------------------
    def _run(self) -> None:
        sub = self.subscriber
        q = self._q
        idle = sub.idle_interval_s
        never_drop = self.policy is Overflow.NEVER_DROP
        coalesce = sub.coalesce_s
        stopping = self._stopping
        while True:
            if coalesce and q.empty() and not stopping.is_set():
                stopping.wait(coalesce)  # let items gather (woken at once by unsubscribe)
            try:
                item = q.get(timeout=idle) if idle else q.get()
            except queue.Empty:
                try:
                    sub.on_idle()
                except Exception as exc:
                    self._failed(exc)
                continue
            if item is _STOP:
                break
            if never_drop and self._warn_level and q.qsize() * self._mean_size * 8 < self.max_bytes:
                with self._lock:
                    if self._warn_level:
                        log.warning("subscriber %s has caught up", self.name)
                        self._warn_level = 0
            if self.detached:
                with self._lock:
                    self.dropped += 1  # queued for a subscriber that was detached: counted, never silent
                continue
            try:
                sub.on_item(item)
                self.delivered += 1
            except Exception as exc:
                self._failed(exc)
        try:
            sub.stop()
        except Exception as exc:
            self._failed(exc)

    def _failed(self, exc: BaseException) -> None:
        self.errors += 1
        if self.errors <= 3:
            log.error("subscriber %s failed: %s: %s", self.name, type(exc).__name__, exc)
        try:
            self.subscriber.on_error(exc)
        except Exception:
            pass
        if self.errors >= self.max_errors and not self.detached:
            self.detached = True
            log.error("subscriber %s detached after %d errors; what it had queued and everything after is "
                      "counted as dropped; other subscribers continue", self.name, self.errors)
            self.bus._detached(self)

    def stats(self) -> SubscriptionStats:
        pending = self._q.qsize()
        self.max_pending = max(self.max_pending, pending)
        return SubscriptionStats(self.name, self.policy.value, self.delivered, self.dropped, self.errors,
                                 pending, int(pending * self._mean_size), self.max_pending, self.detached)

    def join(self, timeout: float | None = None) -> bool:
        """Wait until the delivery thread has finished; True if it did."""
        self._thread.join(timeout)
        return not self._thread.is_alive()


class SampleBus:
    """Fan-out of bus items from any number of publisher threads to independent subscribers.

    Args:
        clock: the host clock (used only for the overflow event's time).
        live_queue: default ``max_items`` for ``KEEP_NEWEST`` subscribers.
        recorder_max_bytes: default ``max_bytes`` for ``NEVER_DROP`` subscribers.
    """

    def __init__(self, clock: Clock = MONOTONIC, live_queue: int = 8192,
                 recorder_max_bytes: int = 1 << 30) -> None:
        self.clock = clock
        self.live_queue = live_queue
        self.recorder_max_bytes = recorder_max_bytes
        self._subs: tuple[Subscription, ...] = ()
        self._lock = threading.Lock()
        self._closed = False
        self.published = 0

    def subscribe(self, sub: Subscriber, *, policy: Overflow = Overflow.KEEP_NEWEST, name: str | None = None,
                  max_items: int | None = None, max_bytes: int | None = None, max_errors: int = 100) -> Subscription:
        """Attach a subscriber; items published from now on reach it.

        Raises:
            ValueError: the bus is closed, or a bound is not positive.
        """
        if self._closed:
            raise ValueError("bus is closed")
        s = Subscription(self, sub, name or type(sub).__name__, policy,
                         max_items if max_items is not None else self.live_queue,
                         max_bytes if max_bytes is not None else self.recorder_max_bytes, max_errors)
        if s.max_items <= 0 or s.max_bytes <= 0:
            raise ValueError("queue bounds must be positive")
        s._thread.start()
        with self._lock:
            self._subs = (*self._subs, s)
        return s

    def unsubscribe(self, s: Subscription, *, wait: bool = True, timeout: float | None = None) -> None:
        """Detach a subscription: items already queued are still delivered, then ``stop()`` runs."""
        with self._lock:
            if s not in self._subs:
                return
            self._subs = tuple(x for x in self._subs if x is not s)
        s._q.put(_STOP)
        s._stopping.set()
        if wait and threading.current_thread() is not s._thread:
            s.join(timeout)

    @property
    def subscriptions(self) -> tuple[Subscription, ...]:
        return self._subs

    def publish(self, item: Any) -> None:
        """Hand one item to every subscriber that accepts its type. Never blocks."""
        self.published += 1
        t = type(item)
        for s in self._subs:
            if t in s.accepts:
                s.offer(item)

    def publish_many(self, items: Iterable[Any]) -> None:
        """Publish several items in order."""
        subs = self._subs
        for item in items:
            self.published += 1
            t = type(item)
            for s in subs:
                if t in s.accepts:
                    s.offer(item)

    def stats(self) -> list[SubscriptionStats]:
        """Counters of every subscription, detached ones included."""
        return [s.stats() for s in self._subs]

    def _detached(self, s: Subscription) -> None:
        """A failing subscriber stays on the bus, counting (as dropped) every item it no longer gets,
        so its losses show in every report; an event tells the other subscribers (the recorder)."""
        s.offer = s.offer_detached
        ev = DeviceEvent(s.name, EventKind.FAILED, self.clock.now_ns(),
                         f"subscriber detached after {s.errors} errors; its items are counted as dropped")
        for other in self._subs:
            if other is not s and DeviceEvent in other.accepts and not other.detached:
                other.offer(ev)

    def close(self, timeout: float | None = None) -> None:
        """Drain and stop every subscriber (each gets everything already published)."""
        self._closed = True
        subs = self._subs
        for s in [s for s in subs if s.subscriber.publishes] + [s for s in subs if not s.subscriber.publishes]:
            self.unsubscribe(s, wait=True, timeout=timeout)

    def _overflowed(self, s: Subscription) -> None:
        ev = DeviceEvent(s.name, EventKind.OVERFLOW, self.clock.now_ns(),
                         f"memory bound {s.max_bytes} bytes reached; items are being dropped and counted")
        # Tell everyone else (a recorder that overflows cannot record this itself, but others can).
        for other in self._subs:
            if other is not s and DeviceEvent in other.accepts:
                other.offer(ev)

