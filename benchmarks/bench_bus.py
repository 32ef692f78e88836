"""SampleBus throughput (1 publisher -> 3 counting subscribers) and latency under a 5 kHz live load
with a real SessionRecorder attached.

    .venv/bin/python benchmarks/bench_bus.py [--quick]

Measurement script: prints figures and PASS/FAIL per target, always exits 0.
"""

from __future__ import annotations

import sys

sys.setswitchinterval(0.0005)  # as the perfcap CLI does

import os  # noqa: E402
import queue  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from _common import check, header, pct, run_sample_load, summary  # noqa: E402

from capture.bus import Overflow, SampleBus, Subscriber  # noqa: E402
from capture.sample import NO_TIME, Sample, SampleBatch  # noqa: E402

QUICK = "--quick" in sys.argv
N_SAMPLES = 100_000 if QUICK else 300_000
BATCH = 1000
N_BATCHES = 1000 if QUICK else 3000
LOAD_S = 3.0 if QUICK else 10.0


class Counter(Subscriber):
    """A light subscriber: counts what it receives (samples, not batches)."""

    def __init__(self) -> None:
        self.n = 0

    def on_item(self, item: Any) -> None:
        self.n += 1 if type(item) is Sample else len(item)


def bus_throughput(items: list[Any], n_samples: int, policy: Overflow) -> tuple[float, list[int], list[int]]:
    """Samples/s from the first publish until all 3 subscribers have everything (bus.close() drains)."""
    bus = SampleBus()
    subs = [Counter() for _ in range(3)]
    kw: dict[str, Any] = {}
    if policy is Overflow.KEEP_NEWEST:
        kw["max_items"] = len(items) + 10  # large enough that nothing is dropped: we measure delivery
    handles = [bus.subscribe(s, policy=policy, name=f"count{i}", **kw) for i, s in enumerate(subs)]
    publish = bus.publish
    t0 = time.perf_counter()
    for it in items:
        publish(it)
    bus.close()  # returns once every subscriber has received everything and stopped
    t1 = time.perf_counter()
    dropped = [h.dropped for h in handles]
    return n_samples / (t1 - t0), [s.n for s in subs], dropped


def queue_baseline(n: int) -> float:
    """Bare queue.SimpleQueue of tuples: one producer fanning out to 3 consumer threads."""
    qs: list[queue.SimpleQueue[Any]] = [queue.SimpleQueue() for _ in range(3)]
    counts = [0, 0, 0]
    stop = object()

    def consumer(k: int) -> None:
        q = qs[k]
        c = 0
        while True:
            it = q.get()
            if it is stop:
                break
            c += 1
        counts[k] = c

    items = [("s", i, i, None, i, (0.0,) * 7) for i in range(n)]
    ths = [threading.Thread(target=consumer, args=(k,), daemon=True) for k in range(3)]
    for t in ths:
        t.start()
    q0, q1, q2 = (q.put for q in qs)
    t0 = time.perf_counter()
    for it in items:
        q0(it)
        q1(it)
        q2(it)
    for q in qs:
        q.put(stop)
    for t in ths:
        t.join()
    t1 = time.perf_counter()
    assert counts == [n, n, n], counts
    return n / (t1 - t0)


def make_samples(n: int) -> list[Sample]:
    v = (0.1, -0.2, 9.81, 0.01, 0.02, -0.03, 25.0)
    return [Sample("d0/imu", i, 1_000_000 + i * 4_000_000, None, 1_000_000 + i * 4_000_000, v) for i in range(n)]


def make_batches(nb: int, size: int) -> list[SampleBatch]:
    out = []
    vals = np.random.default_rng(1).normal(size=(size, 7))
    for b in range(nb):
        seq = np.arange(b * size, (b + 1) * size, dtype=np.int64)
        t = seq * 4_000_000
        out.append(SampleBatch("d0/imu", seq, t, np.full(size, NO_TIME, np.int64), t.copy(), vals))
    return out


def main() -> None:
    header("bench_bus: SampleBus throughput and live latency" + (" (quick)" if QUICK else ""))

    # ---- 1a: one by one --------------------------------------------------------------------------
    print(f"1a. {N_SAMPLES} pre-built Samples published one by one -> 3 counting subscribers")
    base = queue_baseline(N_SAMPLES)
    print(f"    baseline  queue.SimpleQueue x3, 1 producer + 3 consumers : {base:12,.0f} samples/s")
    samples = make_samples(N_SAMPLES)
    rates = {}
    for pol in (Overflow.KEEP_NEWEST, Overflow.NEVER_DROP):
        r, got, dropped = bus_throughput(samples, N_SAMPLES, pol)
        rates[pol] = r
        ok = got == [N_SAMPLES] * 3 and dropped == [0, 0, 0]
        print(f"    SampleBus {pol.name:11s} (all delivered: {ok}, dropped {dropped})     : {r:12,.0f} samples/s"
              f"  ({r / base:.2f}x baseline)")
    r = rates[Overflow.KEEP_NEWEST]
    check("bus one-by-one throughput, light (KEEP_NEWEST) subscribers", r >= 200_000,
          f"{r:,.0f} samples/s (target >= 200,000; baseline {base:,.0f})")
    r = rates[Overflow.NEVER_DROP]
    check("extra: same with NEVER_DROP subscribers", r >= 200_000,
          f"{r:,.0f} samples/s (same target applied; baseline {base:,.0f})")
    del samples

    # ---- 1b: batches ----------------------------------------------------------------------------
    print()
    print(f"1b. {N_BATCHES} SampleBatches of {BATCH} samples -> 3 counting subscribers (samples counted)")
    batches = make_batches(N_BATCHES, BATCH)
    nb = N_BATCHES * BATCH
    brates = {}
    for pol in (Overflow.KEEP_NEWEST, Overflow.NEVER_DROP):
        r, got, dropped = bus_throughput(batches, nb, pol)
        brates[pol] = r
        ok = got == [nb] * 3 and dropped == [0, 0, 0]
        print(f"    SampleBus {pol.name:11s} (all delivered: {ok})  : {r:14,.0f} samples/s  ({r / base:.1f}x the"
              " one-by-one queue baseline)")
    print(f"    (baseline for batches: the same bare queue moving the {BATCH}-sample batches as single objects:"
          f" {queue_baseline(N_BATCHES) * BATCH:,.0f} samples/s)")
    r = brates[Overflow.KEEP_NEWEST]
    check("bus batch throughput, light (KEEP_NEWEST) subscribers", r >= 2_000_000,
          f"{r:,.0f} samples/s (target >= 2,000,000)")
    r = brates[Overflow.NEVER_DROP]
    check("extra: same with NEVER_DROP subscribers", r >= 2_000_000, f"{r:,.0f} samples/s (same target applied)")
    del batches

    # ---- 2: latency under the 5 kHz live load ----------------------------------------------------
    print()
    print(f"2.  5 kHz live load for {LOAD_S:.0f} s: 17 threads x 250 Hz + 1 x 1000 Hz, Sample by Sample,"
          " MonotonicClock().sleep_until_ns pacing;")
    print("    subscribers: latency probe (KEEP_NEWEST) + SessionRecorder to a temp .mcap (NEVER_DROP)")
    bare = run_sample_load(None, LOAD_S)
    b50, b99, b999, bmax = pct(bare.lat_ms, 50, 99, 99.9, 100)
    print("    baseline (same 18 paced threads -> one bare queue.SimpleQueue -> 1 consumer thread, no recorder):")
    print(f"      latency (ms): p50 {b50:.3f}  p99 {b99:.3f}  p99.9 {b999:.3f}  max {bmax:.3f}"
          f"  (n={bare.lat_ms.size}); process CPU {bare.cpu_frac * 100:.0f}% of one core")
    with tempfile.TemporaryDirectory(prefix="perfcap-bench-") as tmp:
        res = run_sample_load(os.path.join(tmp, "load.mcap"), LOAD_S)
    p50, p99, p999, pmax = pct(res.lat_ms, 50, 99, 99.9, 100)
    lp50, lp99 = pct(res.pub_late_ms, 50, 99)
    print("    SampleBus + latency probe + SessionRecorder:")
    print(f"      published {res.published} samples in {res.duration_s:.2f} s ({res.published / res.duration_s:,.0f}/s;"
          f" expected {res.expected})")
    print(f"      latency (ms): p50 {p50:.3f}  p99 {p99:.3f}  p99.9 {p999:.3f}  max {pmax:.3f}"
          f"  (n={res.lat_ms.size}, probe dropped {res.probe_dropped})")
    print(f"      publisher wake-up lateness vs deadline (ms): p50 {lp50:.3f}  p99 {lp99:.3f}")
    print(f"      recorder: dropped {res.rec_dropped}, max queue {res.rec_max_pending} items"
          f" ({res.rec_max_pending_bytes / 1e3:.0f} kB), file {res.file_bytes / 1e3:.0f} kB,"
          f" drain+close {res.close_s * 1e3:.0f} ms, failed={res.extra['recorder_failed']}")
    print(f"      process CPU: {res.cpu_frac * 100:.0f}% of one core (of {(os.cpu_count() or 1) * 100}%);"
          f" baseline {bare.cpu_frac * 100:.0f}%")
    check("live latency p50", p50 <= 0.1, f"{p50:.3f} ms (target <= 0.1 ms; bare-queue baseline {b50:.3f})")
    check("live latency p99", p99 <= 0.5, f"{p99:.3f} ms (target <= 0.5 ms; bare-queue baseline {b99:.3f})")
    check("live latency p99.9", p999 <= 2.0, f"{p999:.3f} ms (target <= 2 ms; bare-queue baseline {b999:.3f})")
    check("recorder drops under 5 kHz load", res.rec_dropped == 0, f"{res.rec_dropped} (target 0)")
    print(f"   [info] process CPU {res.cpu_frac * 100:.0f}% of one core with the bus and recorder,"
          f" {bare.cpu_frac * 100:.0f}% for the paced publishers on a bare queue")
    summary()


if __name__ == "__main__":
    main()
