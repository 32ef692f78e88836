"""Shared helpers of the perfcap benchmarks (not a benchmark itself).

Scripts in this folder import it as ``_common`` (they run with ``benchmarks/`` on ``sys.path``).
"""

from __future__ import annotations

import os
import platform
import queue
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from capture.bus import Overflow, SampleBus, Subscriber
from capture.clock import MonotonicClock
from capture.recorder import SessionRecorder
from capture.sample import DeviceIdentity, Sample, StreamInfo
from capture.session import SessionWriter

RESULTS: list[tuple[str, bool]] = []


def header(title: str) -> None:
    print(f"== {title}")
    print(f"   {time.strftime('%Y-%m-%d %H:%M:%S')}  host={platform.node()}  nproc={os.cpu_count()}  "
          f"python={platform.python_version()}  {platform.machine()}  switchinterval={sys.getswitchinterval()}")
    print(f"   code: {code_version()}")
    la = os.getloadavg()
    busy = machine_busy()
    print(f"   load average at start: {la[0]:.2f} {la[1]:.2f} {la[2]:.2f}; CPU busy over the last 0.5 s: "
          + ("n/a" if busy is None else f"{busy * 100:.0f}% of the machine")
          + " (other work on the machine skews timings)")
    print()


def machine_busy(interval_s: float = 0.5) -> float | None:
    """Fraction of all CPUs busy (any process) over ``interval_s``, from /proc/stat; None if unavailable."""
    def read() -> tuple[int, int]:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
        idle = v[3] + (v[4] if len(v) > 4 else 0)
        return sum(v), idle
    try:
        t0, i0 = read()
        time.sleep(interval_s)
        t1, i1 = read()
    except (OSError, ValueError, IndexError):
        return None
    return 1.0 - (i1 - i0) / max(1, t1 - t0)


def code_version() -> str:
    """The git commit of the code measured, and whether tracked files differ from it."""
    import subprocess

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        # check=False: outside a git checkout (or without git) the version is reported as unknown
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True,
                             timeout=10, check=False).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, timeout=10, check=False).stdout.split("\n")
        changed = [ln[3:] for ln in dirty if ln.strip()]
    except (OSError, subprocess.SubprocessError):
        return "unknown (no git)"
    if not rev:
        return "unknown (not a git checkout)"
    return rev + (f" + uncommitted changes in {', '.join(changed)}" if changed else " (clean)")


def check(label: str, ok: bool, detail: str) -> bool:
    RESULTS.append((label, ok))
    print(f"   [{'PASS' if ok else 'FAIL'}] {label}: {detail}")
    return ok


def summary() -> None:
    n_fail = sum(1 for _, ok in RESULTS if not ok)
    print()
    print(f"== {len(RESULTS) - n_fail} PASS, {n_fail} FAIL"
          + (": " + ", ".join(lbl for lbl, ok in RESULTS if not ok) if n_fail else ""))


def pct(a: Any, *qs: float) -> list[float]:
    arr = np.asarray(a, dtype=float)
    if arr.size == 0:
        return [float("nan")] * len(qs)
    return [float(x) for x in np.percentile(arr, qs)]


# ------------------------------------------------------------------------------------------------
# The 5 kHz aggregate live load: 17 x 250 Hz + 1 x 1000 Hz publishers, sample-level (no devices).

IMU_CHANNELS = ("ax", "ay", "az", "gx", "gy", "gz", "temp")
IMU_UNITS = ("m/s^2",) * 3 + ("rad/s",) * 3 + ("degC",)


def load_streams() -> list[tuple[str, float]]:
    return [(f"d{i}/imu", 250.0) for i in range(17)] + [("mouse/pointer", 1000.0)]


def stream_info(name: str, rate: float) -> StreamInfo:
    dev = name.split("/", maxsplit=1)[0]
    return StreamInfo(name, "imu", IMU_CHANNELS, IMU_UNITS, rate, DeviceIdentity(kind="bench", name=dev))


class LatencyProbe(Subscriber):
    """Live subscriber: publish-to-delivery latency (the publisher puts its publish time in t_host_ns)."""

    def __init__(self) -> None:
        self.lat_ns: list[int] = []

    def on_item(self, item: Any) -> None:
        self.lat_ns.append(time.monotonic_ns() - item.t_host_ns)


@dataclass
class LoadResult:
    duration_s: float
    published: int
    expected: int
    lat_ms: np.ndarray
    probe_dropped: int
    rec_dropped: int
    rec_max_pending: int
    rec_max_pending_bytes: int
    cpu_frac: float
    pub_late_ms: np.ndarray
    file_bytes: int
    close_s: float
    extra: dict[str, Any] = field(default_factory=dict)


class _BareQueue:
    """Baseline transport: one queue.SimpleQueue and one consumer thread measuring latency (no bus)."""

    def __init__(self) -> None:
        self.q: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.lat_ns: list[int] = []
        self.t = threading.Thread(target=self._run, daemon=True)
        self.t.start()

    def _run(self) -> None:
        get = self.q.get
        lat = self.lat_ns
        while True:
            it = get()
            if it is None:
                return
            lat.append(time.monotonic_ns() - it[2])

    def close(self) -> None:
        self.q.put(None)
        self.t.join()


def run_sample_load(path: str | None, duration_s: float = 10.0, spin_ns: int | None = None) -> LoadResult:
    """17 threads at 250 Hz + 1 at 1 kHz publish ``Sample``s with deadline sleeping; a KEEP_NEWEST
    latency probe and a real SessionRecorder (NEVER_DROP) to ``path`` are subscribed.

    With ``path=None`` it is the baseline: the same paced threads put tuples on one bare
    ``queue.SimpleQueue`` read by one thread that measures the latency (no bus, no recorder)."""
    streams = load_streams()
    base = path is None
    if path is None:
        bq = _BareQueue()
    else:
        bus = SampleBus()
        probe = LatencyProbe()
        probe_sub = bus.subscribe(probe, policy=Overflow.KEEP_NEWEST, name="latency")
        writer = SessionWriter(path, overwrite=True)
        rec = SessionRecorder(writer)
        for name, rate in streams:
            rec.add_stream(stream_info(name, rate))
        rec_sub = bus.subscribe(rec, policy=Overflow.NEVER_DROP, name="recorder")
        rec.subscription = rec_sub

    clock = MonotonicClock() if spin_ns is None else MonotonicClock(spin_ns=spin_ns)
    start_ns = time.monotonic_ns() + 50_000_000
    end_ns = start_ns + int(duration_s * 1e9)
    lateness: list[list[int]] = [[] for _ in streams]
    counts = [0] * len(streams)
    values = (0.1, -0.2, 9.81, 0.01, 0.02, -0.03, 25.0)

    def publisher(k: int, name: str, rate: float) -> None:
        period = int(1e9 / rate)
        # stagger the streams inside one period so they do not all wake together
        t_next = start_ns + (k * period) // len(streams)
        seq = 0
        late = lateness[k]
        publish = bq.q.put if base else bus.publish
        mono = time.monotonic_ns
        while t_next < end_ns:
            clock.sleep_until_ns(t_next)
            t = mono()
            publish((name, seq, t, None, t, values) if base else Sample(name, seq, t, None, t, values))
            late.append(t - t_next)
            seq += 1
            t_next += period
        counts[k] = seq

    threads = [threading.Thread(target=publisher, args=(k, n, r), name=f"pub-{n}", daemon=True)
               for k, (n, r) in enumerate(streams)]
    max_pending = 0
    max_pending_bytes = 0
    for t in threads:
        t.start()
    time.sleep(max(0.0, (start_ns - time.monotonic_ns()) / 1e9))
    cpu0 = time.process_time()
    w0 = time.monotonic()
    while any(t.is_alive() for t in threads):
        if not base:
            st = rec_sub.stats()  # also updates the subscription's max_pending (it is only sampled here)
            max_pending = max(max_pending, st.pending)
            max_pending_bytes = max(max_pending_bytes, st.pending_bytes)
        time.sleep(0.02)
    for t in threads:
        t.join()
    cpu1 = time.process_time()
    w1 = time.monotonic()
    published = sum(counts)
    expected = sum(int(duration_s * r) for _, r in streams)
    if path is None:
        bq.close()
        return LoadResult(
            duration_s=w1 - w0, published=published, expected=expected,
            lat_ms=np.asarray(bq.lat_ns, dtype=float) / 1e6, probe_dropped=0, rec_dropped=0,
            rec_max_pending=0, rec_max_pending_bytes=0, cpu_frac=(cpu1 - cpu0) / (w1 - w0),
            pub_late_ms=np.asarray([x for lst in lateness for x in lst], dtype=float) / 1e6,
            file_bytes=0, close_s=0.0)
    st_probe = probe_sub.stats()
    st_rec = rec_sub.stats()
    c0 = time.monotonic()
    bus.close()
    close_s = time.monotonic() - c0
    return LoadResult(
        duration_s=w1 - w0, published=published, expected=expected,
        lat_ms=np.asarray(probe.lat_ns, dtype=float) / 1e6,
        probe_dropped=st_probe.dropped, rec_dropped=st_rec.dropped,
        rec_max_pending=max(max_pending, st_rec.max_pending), rec_max_pending_bytes=max_pending_bytes,
        cpu_frac=(cpu1 - cpu0) / (w1 - w0),
        pub_late_ms=np.asarray([x for lst in lateness for x in lst], dtype=float) / 1e6,
        file_bytes=os.path.getsize(path), close_s=close_s,
        extra={"recorded": dict(rec.counts), "recorder_failed": rec.failed},
    )
