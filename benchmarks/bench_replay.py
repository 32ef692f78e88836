"""Session replay: as fast as possible (speed 0) and in real time (speed 1).

    .venv/bin/python benchmarks/bench_replay.py

(a) 17 synthetic IMUs (200 Hz, virtual clock, 10 s of device time) are recorded to a temp session,
    then replayed with ``replay_session(path, speed=0)``: recorded seconds per wall second (end to
    end, as ``perfcap replay --fast`` reports it, and for the pipeline phase alone), and the
    verification. Baseline: one pass decoding every sample block of the file (``all_samples()``).
(b) Real-time replay (speed 1) of a 5 s session of 3 realtime synthetic IMUs, with the replay
    recorded to a second session (a recorder on the bus); and of the first 5 s of the 17-device
    session (a busy bus). A timing subscriber notes when every raw chunk reaches the bus; the
    duration error compares the wall span first->last chunk with the recorded span, and the
    per-chunk lateness is ``ReplayReport.lateness_ns``. Baseline: a plain ``time.sleep(gap)``
    pacer over the same chunk timestamps.

Measurement script: prints figures and PASS/FAIL per target, always exits 0.
"""

from __future__ import annotations

import sys

sys.setswitchinterval(0.0005)  # as the perfcap CLI does

import os  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from _common import check, header, pct, summary  # noqa: E402

from capture.app.orchestrator import Capture  # noqa: E402
from capture.app.replay import replay_session  # noqa: E402
from capture.bus import Overflow, Subscriber  # noqa: E402
from capture.sample import DeviceChunk, Direction  # noqa: E402
from capture.session import SessionReader  # noqa: E402

N_FAST = 17
FAST_S = 10
RT_DEVICES = 3
RT_S = 5.0
REPEAT = 5


class ChunkTimes(Subscriber):
    """Notes the wall time at which each replayed RX chunk reaches this subscriber."""

    accepts = frozenset({DeviceChunk})

    def __init__(self) -> None:
        self.rows: list[tuple[int, int]] = []

    def on_item(self, item: Any) -> None:
        if item.chunk.direction is Direction.RX:
            self.rows.append((time.monotonic_ns(), item.chunk.t_ns))


def recorded_chunk_times(path: str) -> np.ndarray:
    r = SessionReader(path)
    ts = [c.t_ns for d in r.devices for c in r.raw_chunks(d) if c.direction is Direction.RX]
    return np.sort(np.asarray(ts, np.int64))


def sleep_pacer(ts: np.ndarray) -> tuple[float, np.ndarray]:
    """Baseline: deliver each chunk after time.sleep(gap to the previous one). Returns (span error, lateness ns)."""
    n = len(ts)
    wall = np.empty(n, np.int64)
    prev = ts[0]
    wall[0] = time.monotonic_ns()
    for i in range(1, n):
        gap = ts[i] - prev
        prev = ts[i]
        if gap > 0:
            time.sleep(gap / 1e9)
        wall[i] = time.monotonic_ns()
    span = ts[-1] - ts[0]
    err = ((wall[-1] - wall[0]) - span) / span
    late = (wall - wall[0]) - (ts - ts[0])
    return err, late


def realtime_replay(path: str, out_path: str | None, duration_s: float | None, verify: bool) -> dict[str, Any]:
    timer = ChunkTimes()
    t0 = time.monotonic()
    rep = replay_session(path, speed=1.0, output=out_path, overwrite=True, verify=verify, duration_s=duration_s,
                         subscribers=[(timer, Overflow.NEVER_DROP)])
    wall = time.monotonic() - t0
    rows = np.asarray(timer.rows, np.int64)
    order = np.argsort(rows[:, 1], kind="stable")
    w, t = rows[order, 0], rows[order, 1]
    span_rec = int(t[-1] - t[0])
    span_wall = int(w.max() - w.min())
    late = np.asarray(rep.lateness_ns, dtype=float) / 1e6
    # Steady state: the wall-minus-recorded offset of each chunk's bus arrival after the first 0.5 s.
    off = (w - t).astype(float)
    steady = (t - t[0]) >= 500_000_000
    base_off = float(np.median(off[steady]))
    slope = float(np.polyfit((t[steady] - t[0]) / 1e9, (w[steady] - w[0]) / 1e9, 1)[0])
    return {"rep": rep, "wall": wall, "span_rec": span_rec, "span_wall": span_wall,
            "err": (span_wall - span_rec) / span_rec, "late_ms": late, "n": len(t),
            "first_late_ms": late[:5].tolist() if late.size else [],
            "start_ms": (off[0] - base_off) / 1e6, "rate_ppm": (slope - 1.0) * 1e6,
            "steady_ms": (off[steady] - base_off) / 1e6, "startup_late_n": int(np.sum(off - base_off > 1e6))}


def report_rt(label: str, r: dict[str, Any], base_err: float, base_late: np.ndarray) -> None:
    l50, l99, lmax = pct(r["late_ms"], 50, 99, 100)
    s50, s99, smax = pct(np.abs(r["steady_ms"]), 50, 99, 100)
    b99 = pct(np.abs(base_late) / 1e6, 99)[0]
    ver = r["rep"].verification
    print(f"    {label}: {r['n']} RX chunks; recorded span {r['span_rec'] / 1e9:.4f} s, wall span first->last chunk"
          f" {r['span_wall'] / 1e9:.4f} s; replay_session() took {r['wall']:.2f} s")
    print(f"      duration error {r['err'] * 100:+.4f}%   (baseline sleep pacer {base_err * 100:+.4f}%)")
    print(f"      transport lateness (ms, ReplayReport.lateness_ns): p50 {l50:.3f}  p99 {l99:.3f}  max {lmax:.3f}"
          f"  (n={r['late_ms'].size}); first chunks of the first device: "
          f"{', '.join(f'{x:.1f}' for x in r['first_late_ms'])}")
    print(f"      start-up: the first chunk reached the bus {r['start_ms']:.1f} ms behind the steady-state timeline;"
          f" {r['startup_late_n']} chunks were > 1 ms behind it (catch-up)")
    print(f"      steady state (after the first 0.5 s): rate error {r['rate_ppm']:+.1f} ppm; bus arrival vs timeline"
          f" |ms| p50 {s50:.3f}  p99 {s99:.3f}  max {smax:.3f}   (sleep pacer, all chunks: p99 {b99:.3f} ms)")
    if ver is not None:
        print(f"      verification equal: {ver['equal']}")
    check(f"real-time duration error, {label}", abs(r["err"]) < 0.001,
          f"{r['err'] * 100:+.4f}% (target < 0.1%; sleep-pacer baseline {base_err * 100:+.4f}%)")
    check(f"real-time lateness p99, {label}", l99 < 1.0, f"{l99:.3f} ms (target < 1 ms)")


def main() -> None:
    header("bench_replay: session replay, as fast as possible and in real time")
    with tempfile.TemporaryDirectory(prefix="perfcap-bench-") as tmp:
        # ---- (a) as fast as possible ------------------------------------------------------------
        fast = os.path.join(tmp, "fast17.mcap")
        urls = [f"d{n}=synth://imu?rate=200&seed={n}&realtime=false&duration={FAST_S}" for n in range(N_FAST)]
        t0 = time.monotonic()
        Capture(urls, output=fast).run(None)
        rec_wall = time.monotonic() - t0
        size = os.path.getsize(fast)
        print(f"(a) recorded {N_FAST} x synth imu 200 Hz, {FAST_S} s (virtual clock) in {rec_wall:.2f} s wall;"
              f" {size / 1e6:.2f} MB")
        t0 = time.monotonic()
        nsamp = sum(len(b) for b in SessionReader(fast).all_samples().values())
        base_wall = time.monotonic() - t0
        # as `perfcap replay --fast` runs: the interpreter's default switch interval (the CLI sets
        # the short 0.5 ms one only for live work and paced replay)
        sys.setswitchinterval(0.005)
        runs = []
        for _ in range(REPEAT):  # the replay itself is short: median of REPEAT runs
            t0 = time.monotonic()
            rep = replay_session(fast, speed=0)
            runs.append((time.monotonic() - t0, rep.capture.duration_s, rep))
        runs.sort(key=lambda x: x[0])
        wall, pipe, rep = runs[len(runs) // 2]
        walls = ", ".join(f"{w:.3f}" for w, _, _ in runs)
        span = rep.recorded_span_s
        ver = rep.verification or {}
        ncmp = sum(v["compared"] for v in ver.get("streams", {}).values())
        print(f"    replay_session(speed=0), median of {REPEAT} runs (walls {walls} s): {span:.2f} s of recording in"
              f" {wall:.3f} s wall -> {span / wall:.1f}x real time end to end")
        print(f"      of which the pipeline (readers started -> all drained) {pipe:.3f} s -> {span / pipe:.1f}x;"
              f" setup and teardown {wall - pipe:.3f} s")
        print(f"      verification equal: {ver.get('equal')} ({ncmp} samples compared)")
        print(f"    baseline: one pass decoding every sample block ({nsamp} samples): {base_wall:.3f} s ->"
              f" {span / base_wall:.1f}x real time")
        check("fast replay speed (end to end)", span / wall >= 100,
              f"{span / wall:.1f}x real time (target >= 100x; pipeline only {span / pipe:.1f}x;"
              f" one-pass read baseline {span / base_wall:.1f}x)")
        check("fast replay verification", bool(ver.get("equal")), f"equal={ver.get('equal')} ({ncmp} samples)")
        nv = []
        for _ in range(REPEAT):
            t0 = time.monotonic()
            rep_nv = replay_session(fast, speed=0, verify=False)
            nv.append(time.monotonic() - t0)
        wall_nv = sorted(nv)[len(nv) // 2]
        sys.setswitchinterval(0.0005)  # back to the CLI's setting for paced replay
        nchunks = sum(d["chunks"] for d in rep_nv.capture.devices.values())
        print(f"    [info] without verification (median of {REPEAT}): {wall_nv:.3f} s wall ({span / wall_nv:.1f}x),"
              f" pipeline {rep_nv.capture.duration_s:.2f} s ="
              f" {rep_nv.capture.duration_s / nchunks * 1e6:.0f} us per chunk ({nchunks} chunks);"
              f" 100x would need <= {span / 100 / nchunks * 1e6:.1f} us per chunk end to end")

        # ---- (b) real time ----------------------------------------------------------------------
        print()
        rt = os.path.join(tmp, "rt3.mcap")
        urls = [f"d{n}=synth://imu?rate=200&seed={n}&jitter_ms=1" for n in range(RT_DEVICES)]
        Capture(urls, output=rt).run(RT_S)
        ts = recorded_chunk_times(rt)
        base_err, base_late = sleep_pacer(ts)
        print(f"(b) real-time replay (speed 1); baseline: time.sleep(gap) pacer over the same {len(ts)} chunk times:"
              f" duration error {base_err * 100:+.4f}%")
        r1 = realtime_replay(rt, os.path.join(tmp, "rt3-replay.mcap"), None, True)
        report_rt(f"{RT_DEVICES} realtime synth devices, {RT_S:.0f} s, replay recorded", r1, base_err, base_late)
        ts17 = recorded_chunk_times(fast)
        ts17 = ts17[ts17 - ts17[0] <= int(RT_S * 1e9)]
        base_err17, base_late17 = sleep_pacer(ts17)
        r2 = realtime_replay(fast, None, RT_S, False)
        report_rt(f"first {RT_S:.0f} s of the {N_FAST}-device session", r2, base_err17, base_late17)
    summary()


if __name__ == "__main__":
    main()
