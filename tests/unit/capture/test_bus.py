"""Sample bus: fan-out, overflow policies, drop counting, isolation of slow and failing subscribers."""

from __future__ import annotations

import logging
import threading

import numpy as np
import pytest

from capture.bus import EVERYTHING, Overflow, SampleBus, Subscriber
from capture.sample import NO_TIME, DeviceEvent, EventKind, Sample, SampleBatch


class Collect(Subscriber):
    accepts = EVERYTHING

    def __init__(self, gate: threading.Event | None = None) -> None:
        self.items: list = []
        self.gate = gate
        self.stopped = False

    def on_item(self, item):
        if self.gate is not None:
            self.gate.wait(10)
        self.items.append(item)

    def stop(self):
        self.stopped = True


def s(i: int, stream: str = "d/imu") -> Sample:
    return Sample(stream, i, 1000 + i, None, 1000 + i, (float(i),))


def test_every_subscriber_gets_everything_in_order():
    bus = SampleBus()
    subs = [Collect() for _ in range(3)]
    for c in subs:
        bus.subscribe(c)
    for i in range(1000):
        bus.publish(s(i))
    bus.close()
    for c in subs:
        assert [x.seq for x in c.items] == list(range(1000))
        assert c.stopped


def test_batches_travel_and_accepts_filters_types():
    bus = SampleBus()
    only_samples = Collect()
    only_samples.accepts = frozenset({Sample, SampleBatch})
    everything = Collect()
    bus.subscribe(only_samples)
    bus.subscribe(everything)
    b = SampleBatch("d/imu", np.arange(5), np.arange(5), np.full(5, NO_TIME), np.arange(5), np.zeros((5, 2)))
    bus.publish(b)
    bus.publish(DeviceEvent("d", EventKind.NOTE, 1))
    bus.close()
    assert only_samples.items == [b]
    assert len(everything.items) == 2


def test_live_subscriber_keeps_newest_and_counts_drops_without_stalling_others():
    bus = SampleBus()
    gate = threading.Event()
    slow = Collect(gate)
    fast = Collect()
    live = bus.subscribe(slow, policy=Overflow.KEEP_NEWEST, max_items=10, name="slow")
    bus.subscribe(fast, policy=Overflow.NEVER_DROP, name="fast")
    for i in range(500):
        bus.publish(s(i))  # returns although 'slow' is blocked
    stats = live.stats()
    gate.set()
    bus.close()
    assert [x.seq for x in fast.items] == list(range(500))
    assert stats.dropped > 0
    assert live.dropped + len(slow.items) == 500
    # what the slow one got is the oldest (in flight) plus the newest ones
    assert slow.items[-1].seq == 499
    assert [x.seq for x in slow.items] == sorted(x.seq for x in slow.items)


def test_recorder_policy_never_drops_below_its_bound():
    bus = SampleBus()
    gate = threading.Event()
    rec = Collect(gate)
    sub = bus.subscribe(rec, policy=Overflow.NEVER_DROP, max_bytes=1 << 30)
    for i in range(20000):
        bus.publish(s(i))
    assert sub.stats().pending > 10000  # it grew instead of dropping
    gate.set()
    bus.close()
    assert sub.dropped == 0 and len(rec.items) == 20000


def test_recorder_bound_reached_is_counted_logged_and_announced(caplog):
    bus = SampleBus()
    gate = threading.Event()
    rec = Collect(gate)
    other = Collect()
    sub = bus.subscribe(rec, policy=Overflow.NEVER_DROP, max_bytes=50_000, name="recorder")
    bus.subscribe(other, policy=Overflow.NEVER_DROP, name="other")
    with caplog.at_level(logging.WARNING):
        for i in range(2000):
            bus.publish(s(i))
    gate.set()
    bus.close()
    assert sub.dropped > 0
    assert len(rec.items) + sub.dropped == 2000
    assert any("falling behind" in r.message for r in caplog.records)
    assert any("memory bound" in r.message and r.levelno == logging.ERROR for r in caplog.records)
    overflow = [x for x in other.items if isinstance(x, DeviceEvent) and x.kind is EventKind.OVERFLOW]
    assert len(overflow) == 1 and overflow[0].source == "recorder"


def test_crashing_subscriber_is_counted_then_detached_others_continue(caplog):
    class Boom(Subscriber):
        def __init__(self):
            self.errors = []

        def on_item(self, item):
            raise RuntimeError("bug in a subscriber")

        def on_error(self, exc):
            self.errors.append(exc)

    bus = SampleBus()
    boom = Boom()
    boom.accepts = frozenset({Sample})
    ok = Collect()
    b = bus.subscribe(boom, max_errors=5, name="boom")
    bus.subscribe(ok)
    with caplog.at_level(logging.ERROR):
        for i in range(100):
            bus.publish(s(i))
        listed = [x.name for x in bus.stats()]
        bus.close()
    assert len([x for x in ok.items if isinstance(x, Sample)]) == 100
    assert b.errors == 5 and b.detached
    assert len(boom.errors) == 5
    # still in the reports, and every item it did not get is counted as dropped
    assert "boom" in listed and b.dropped == 95
    failed = [x for x in ok.items if isinstance(x, DeviceEvent) and x.kind is EventKind.FAILED]
    assert len(failed) == 1 and failed[0].source == "boom"
    assert any("detached" in r.message for r in caplog.records)


def test_concurrent_publishers_lose_nothing():
    bus = SampleBus()
    rec = Collect()
    bus.subscribe(rec, policy=Overflow.NEVER_DROP)

    def pub(k):
        for i in range(2000):
            bus.publish(s(i, f"d{k}/imu"))

    ts = [threading.Thread(target=pub, args=(k,)) for k in range(8)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    bus.close()
    assert len(rec.items) == 16000
    for k in range(8):
        assert [x.seq for x in rec.items if x.stream == f"d{k}/imu"] == list(range(2000))


def test_idle_callback_and_bad_bounds():
    class Idle(Subscriber):
        idle_interval_s = 0.01

        def __init__(self):
            self.idles = threading.Event()

        def on_item(self, item):
            pass

        def on_idle(self):
            self.idles.set()

    bus = SampleBus()
    i = Idle()
    bus.subscribe(i)
    assert i.idles.wait(5)
    with pytest.raises(ValueError):
        bus.subscribe(Collect(), max_items=0)
    bus.close()
    with pytest.raises(ValueError):
        bus.subscribe(Collect())
