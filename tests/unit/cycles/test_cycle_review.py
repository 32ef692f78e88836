"""Inputs a review found hard: sines whose period is not a whole number of samples, fast sensors,
mouse-style event streams, spiky input, long jittered takes, a performer who changes tempo."""

from __future__ import annotations

import numpy as np
import pytest

from capture.errors import NoPeriodFoundError
from capture.sample import Sample
from cycles import CycleExtractor, extract
from sim_devices.loops import jittered_loops


@pytest.mark.parametrize("period", [0.55, 0.96, 0.97, 1.1137, 1.61, 1.99])
def test_noise_free_and_quantised_sines_at_any_period(period: float) -> None:
    t = np.arange(0, 5 * period, 1 / 120)
    for x in (np.sin(2 * np.pi * t / period), np.round(2047 * np.sin(2 * np.pi * t / period)) / 2047):
        c = extract(t, x)
        assert abs(c.period_s / period - 1) < 0.01, (period, c.period_s)


@pytest.mark.parametrize("channels", [1, 2])
def test_a_1khz_sensor(channels: int) -> None:
    rng = np.random.default_rng(channels)
    t = np.arange(0, 5.0, 1 / 1000)
    x = np.stack([np.sin(2 * np.pi * t) + 0.5 * np.sin(4 * np.pi * t + 1), np.cos(2 * np.pi * t)], 1)
    x = x[:, :channels] + rng.normal(0, 0.05, (t.size, channels))
    c = extract(t, x)
    assert abs(c.period_s - 1.0) < 0.01
    # the loop keeps the input's rate
    assert abs(np.median(np.diff(c.times_s)) - 0.001) < 1e-4


def test_a_mouse_that_reports_only_changes() -> None:
    t = np.arange(0, 6.0, 1 / 1000)
    x = np.round(np.stack([200 * np.sin(2 * np.pi * t), 100 * np.sin(4 * np.pi * t + 0.5)], 1))
    changed = np.concatenate([[True], np.any(np.diff(x, axis=0) != 0, axis=1)])
    c = extract(t[changed], x[changed])
    assert abs(c.period_s - 1.0) < 0.01
    assert not any("gap" in n for n in c.notes)


def test_spiky_input_is_one_clean_error() -> None:
    rng = np.random.default_rng(29)
    x = rng.normal(0, 0.01, (500, 2))
    x[rng.choice(500, 5, replace=False)] += 5.0
    try:
        extract(np.arange(500) / 100, x)
    except NoPeriodFoundError as exc:
        assert "\n" not in str(exc)


def test_many_contiguous_loops_give_the_mean_loop() -> None:
    errs = []
    for seed in range(6):
        tk = jittered_loops(11, channels=3, noise=0.03, seed=seed)
        errs.append(abs(extract(tk.t, tk.values).period_s / tk.period_s - 1))
    assert max(errs) < 0.005, errs


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
