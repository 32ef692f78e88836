"""Inputs ``cycles.extract`` must handle: sines whose period is not a whole number of samples (also
quantised), a 1 kHz sensor, a mouse that reports only changes, spiky noise (one clean error), and long
takes of many jittered loops."""

from __future__ import annotations

import numpy as np
import pytest

from capture.errors import NoPeriodFoundError
from cycles import extract
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
