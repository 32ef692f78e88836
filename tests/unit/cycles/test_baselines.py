"""The benchmark's peer period estimators (``benchmarks/cycle_baselines.py``): the FFT autocorrelation
finds the period of clean jittered takes, and what it does on half- and double-period structure; the
stumpy matrix-profile peer where stumpy is installed (the ``bench`` extra, not installed in CI)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from sim_devices.loops import jittered_loops

_PATH = Path(__file__).resolve().parents[3] / "benchmarks" / "cycle_baselines.py"


def _load():
    spec = importlib.util.spec_from_file_location("cycle_baselines", _PATH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


cb = _load()


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("channels", [1, 3, 12])
def test_acf_finds_the_period_of_jittered_loops(seed, channels):
    take = jittered_loops(5, channels=channels, noise=0.03, seed=seed)
    est = cb.acf_period(take.t, take.values)
    assert abs(est / take.period_s - 1) < 0.04


def test_acf_is_exact_on_a_clean_sine():
    t = np.arange(0, 4.0, 1 / 120)
    est = cb.acf_period(t, np.sin(2 * np.pi * t / 1.0))
    assert est == pytest.approx(1.0, rel=2e-3)


def test_acf_resamples_irregular_stamps():
    take = jittered_loops(4, channels=3, noise=0.02, irregular_mean_s=0.008, seed=3)
    assert np.ptp(np.diff(take.t)) > 0.01  # really irregular
    est = cb.acf_period(take.t, take.values)
    assert abs(est / take.period_s - 1) < 0.04


def test_acf_on_one_harmonic_per_channel_is_not_half():
    # one channel per harmonic 1, 2, 3 of the loop: the summed spectrum still peaks at the loop.
    for seed in range(5):
        take = jittered_loops(4, channels=3, harmonics=3, per_channel_harmonic=True, noise=0.02, seed=seed)
        est = cb.acf_period(take.t, take.values)
        assert abs(est / take.period_s - 1) < 0.05


def test_acf_reports_the_dominant_sub_period_when_it_dominates():
    # A loop made of two near-identical halves: the ACF peak at T/2 is within 0.9 of the one at T and
    # comes first, so the peer answers the half period (the weakness extract must not share).
    t = np.arange(0, 6.0, 1 / 120)
    x = np.sin(2 * np.pi * 2 * t) + 0.05 * np.sin(2 * np.pi * t)
    assert cb.acf_period(t, x) == pytest.approx(0.5, rel=0.01)
    # With a strong fundamental, the half-period structure does not fool it.
    x2 = np.sin(2 * np.pi * 2 * t) + 1.0 * np.sin(2 * np.pi * t)
    assert cb.acf_period(t, x2) == pytest.approx(1.0, rel=0.01)


def test_acf_doubling_when_alternate_loops_differ():
    # Every other loop is 40% weaker: the loops are not alike, the true repeat is two loops, and the
    # first peak at or above 0.9 of the highest is then the double period.
    t = np.arange(0, 8.0, 1 / 120)
    env = np.where((t // 1.0) % 2 == 0, 1.0, 0.2)
    x = env * np.sin(2 * np.pi * t) + 0.3 * np.sin(2 * np.pi * t / 2)
    assert cb.acf_period(t, x) == pytest.approx(2.0, rel=0.02)


def test_acf_without_a_period_is_nan():
    t = np.arange(0, 4.0, 1 / 120)
    assert np.isnan(cb.acf_period(t, np.zeros((t.size, 2))))   # no motion
    assert np.isnan(cb.acf_period(t, t[:, None] * 3.0))          # a ramp never crosses zero


def test_acf_rejects_bad_shapes():
    with pytest.raises(ValueError):
        cb.acf_period(np.arange(10.0), np.zeros((9, 2)))
    with pytest.raises(ValueError):
        cb.acf_period(np.zeros(3), np.zeros((3, 1)))


def test_nearest_neighbour_spacing_folds_whole_multiples():
    # spacings at 1, 2 and 3 periods of 100 samples, about equally often: the fundamental is 100
    rng = np.random.default_rng(0)
    idx = np.arange(600)
    k = rng.integers(1, 4, idx.size)
    nn = idx + k * 100 + rng.integers(-2, 3, idx.size)
    assert cb.mstump_spacing(nn) == pytest.approx(100.0, abs=0.5)
    assert np.isnan(cb.mstump_spacing(idx))  # every match overlaps itself: no spacing


@pytest.mark.slow  # the first mstump call of a process compiles stumpy's kernels (10-20 s)
@pytest.mark.skipif(not cb.have_stumpy(), reason="stumpy is not installed (the bench extra)")
def test_mstump_finds_the_period_of_jittered_loops():
    take = jittered_loops(5, channels=3, noise=0.03, seed=1)
    est = cb.mstump_period(take.t, take.values)
    assert abs(est / take.period_s - 1) < 0.05


def test_mstump_without_stumpy_is_nan(monkeypatch):
    monkeypatch.setattr(cb, "have_stumpy", lambda: False)
    take = jittered_loops(4, channels=2, seed=0)
    assert np.isnan(cb.mstump_period(take.t, take.values))
