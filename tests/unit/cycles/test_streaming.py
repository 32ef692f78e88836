"""``CycleExtractor``: cycle extraction fed sample by sample or in batches from the bus. It reports once
two loops are in and again when it improves, agrees with ``cycles.extract`` in batch mode, keeps to its
window, extracts every ``every_s`` of data (not per sample), and follows a performer who changes tempo."""

from __future__ import annotations

import numpy as np

from capture.sample import Sample, SampleBatch
from cycles import Cycle, CycleExtractor, extract
from sim_devices.loops import jittered_loops


def rel_err(c: Cycle, truth: float) -> float:
    return c.period_s / truth - 1.0


def test_streaming_reports_once_two_loops_are_in_and_improves() -> None:
    tk = jittered_loops(7, channels=3, noise=0.02, seed=8)
    ex = CycleExtractor("hand/imu", every_s=0.25)
    reports: list[tuple[float, Cycle]] = []
    for i, (t, v) in enumerate(zip(tk.t, tk.values, strict=True)):
        s = Sample("hand/imu", i, int(t * 1e9), None, int(t * 1e9), tuple(v))
        for c in ex.update(s):
            reports.append((float(t), c))
        ex.update(Sample("other/imu", i, 0, None, int(t * 1e9), (0.0,)))  # ignored
    assert reports, ex.last_error
    first_t, first = reports[0]
    assert first_t >= tk.boundaries_s[2] - 0.3    # not before two loops were performed
    assert first.loops >= 2
    last = reports[-1][1]
    assert last.loops >= first.loops and ex.best is last
    assert abs(rel_err(last, tk.period_s)) < 0.02
    # the batch mode of the same extractor, given the same samples, agrees with the array function
    ex.reset()
    assert ex.best is None and ex.attempts == 0
    samples = [Sample("hand/imu", i, int(t * 1e9), None, int(t * 1e9), tuple(v))
               for i, (t, v) in enumerate(zip(tk.t, tk.values, strict=True))]
    batch = ex.extract(samples)
    direct = extract(np.array([s.t_bus_ns for s in samples]) / 1e9, tk.values)
    assert batch.period_s == direct.period_s and batch.loops == direct.loops


def test_streaming_batches_and_window() -> None:
    tk = jittered_loops(12, channels=2, noise=0.02, seed=9)
    ex = CycleExtractor("s", window_s=5.0, every_s=1.0)
    got = []
    for lo in range(0, tk.t.size, 60):
        sl = slice(lo, lo + 60)
        n = tk.t[sl].size
        tb = (tk.t[sl] * 1e9).astype(np.int64)
        b = SampleBatch("s", np.arange(lo, lo + n), tb, np.full(n, -1, np.int64), tb, tk.values[sl])
        got += [(float(tk.t[sl][-1]), c) for c in ex.update(b)]
    assert got and ex.best is not None
    for now, c in got:   # each extraction used only the last window_s seconds
        assert c.loop_spans_s.min() >= now - 5.0 - 1e-6
    # one extraction per every_s (1 s) of data: 12 s of data, first at 1 s
    assert 10 <= ex.attempts <= 12


def test_streaming_follows_a_change_of_tempo() -> None:
    # 1.0 s loops for 40 s, then 1.3 s loops: with a 15 s window the best cycle follows
    t = np.arange(0, 70.0, 1 / 100)
    ph = np.where(t < 40, t / 1.0, 40 + (t - 40) / 1.3)
    x = np.stack([np.sin(2 * np.pi * ph), np.cos(4 * np.pi * ph)], 1)
    ex = CycleExtractor("s", window_s=15.0, every_s=1.0)
    for i, (ti, xi) in enumerate(zip(t, x, strict=True)):
        ex.update(Sample("s", i, int(ti * 1e9), None, int(ti * 1e9), tuple(xi)))
        if abs(ti - 39.0) < 0.005:
            assert ex.best is not None and abs(ex.best.period_s - 1.0) < 0.02
    assert ex.best is not None and abs(ex.best.period_s - 1.3) < 0.03
    # extractions ran every 1 s of data, not per sample
    assert 60 <= ex.attempts <= 72
