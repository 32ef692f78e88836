"""Cycle extraction over seeded families of takes that nobody tuned for (issue 17): never a half, a third,
a double or a missing answer on jittered takes whose higher harmonics may dominate; never a period in a
random walk; one long pause (a held pose or a stopped recording) keeps the loops on both sides; and on
real walks the stride or the lap wins, not a multiple of it.

The families are ``sim_devices.loops.random_harmonic_take``, ``random_walk_take`` and ``paused_take``;
``benchmarks/bench_cycle_sweep.py`` runs them beside the autocorrelation baseline and on seeds beyond
these. Each test sweeps every seed and reports all the failures at once.
"""

from __future__ import annotations

import numpy as np
import pytest
from gait_helpers import IMU_HZ, TRACES, gait_imu, gait_strides

from capture.errors import NoMotionError, NoPeriodFoundError
from cycles import extract
from sim_devices.loops import paused_take, random_harmonic_take, random_walk_take

IPHONE = TRACES / "e_smartphone" / "dispel_ads_iphonex_sbt_utt_example.json"

#: a period further than this from the truth is a gross error (a half is -50 %, a double +100 %)
GROSS = 0.1


def _period(t: np.ndarray, x: np.ndarray) -> float | str:
    try:
        return extract(t, x).period_s
    except (NoPeriodFoundError, NoMotionError) as exc:
        return str(exc)


def test_jittered_takes_never_give_a_gross_error() -> None:
    bad = []
    for seed in range(1000):
        tk = random_harmonic_take(seed)
        got = _period(tk.t, tk.values)
        if isinstance(got, str) or abs(got / tk.period_s - 1) > GROSS:
            bad.append((seed, tk.about, got if isinstance(got, str) else round(got / tk.period_s, 3)))
    assert not bad, bad


def test_random_walks_are_never_periodic() -> None:
    accepted = []
    for seed in range(1000):
        tk = random_walk_take(seed)
        got = _period(tk.t, tk.values)
        if not isinstance(got, str):
            accepted.append((seed, tk.about, round(got, 3)))
    assert not accepted, accepted


def test_one_long_pause_keeps_the_loops_on_both_sides() -> None:
    bad = []
    for seed in range(300):
        tk = paused_take(seed)
        try:
            c = extract(tk.t, tk.values)
        except NoPeriodFoundError as exc:
            bad.append((seed, tk.about, str(exc)))
            continue
        a, b = tk.about["pause_from"], tk.about["pause_to"]
        spans = c.loop_spans_s
        both = bool(np.any(spans[:, 1] <= a + 1e-9) and np.any(spans[:, 0] >= b - 1e-9))
        # no loop is averaged across the pause, and the period is the loops' on both sides
        across = bool(np.any((spans[:, 0] < a - 1e-9) & (spans[:, 1] > b + 1e-9)))
        if not both or across or abs(c.period_s / tk.period_s - 1) > 0.03:
            bad.append((seed, tk.about, round(c.period_s / tk.period_s, 4), both, across))
    # A known limit (docs/design/cycles.md): a single channel, whose value and slope recur inside a
    # loop, may fail to pick its loops up after the pause: 2 of these 300 seeds, both one channel.
    assert len(bad) <= 3 and all(b[1]["channels"] == 1 for b in bad), bad


def _truth(foot: str) -> float:
    b = gait_strides(foot)
    return float(np.median(b[:, 1] - b[:, 0]))


@pytest.mark.parametrize("foot", ["left", "right"])
@pytest.mark.parametrize("kind", ["held", "stopped"])
def test_a_real_walk_with_a_30_s_pause_uses_both_halves(foot: str, kind: str) -> None:
    t, data, sensor, _ = gait_imu()
    cols = [i for i, name in enumerate(sensor) if name == f"{foot}_sensor"]
    x = data[:, cols]
    half, pause = x.shape[0] // 2, 30.0
    if kind == "held":   # the walker stands still for 30 s: the sensor still reports, at rest
        rng = np.random.default_rng(0)
        n = int(pause * IMU_HZ)
        rest = np.median(x[:200], axis=0) + rng.normal(0.0, 0.02, (n, x.shape[1])) * x.std(axis=0)
        x = np.vstack([x[:half], rest, x[half:]])
        t = np.arange(x.shape[0]) / IMU_HZ
    else:                # the recording was stopped for 30 s
        t = np.concatenate([t[:half], t[half:] + pause])
    c = extract(t, x)
    split, resume = t[half - 1], t[half - 1] + pause
    assert np.any(c.loop_spans_s[:, 1] <= split) and np.any(c.loop_spans_s[:, 0] >= resume)
    assert abs(c.period_s / _truth(foot) - 1) < 0.01, (c.period_s, _truth(foot))


@pytest.mark.parametrize("foot", ["left", "right"])
def test_a_real_gyroscope_walk_gives_the_stride_not_a_multiple(foot: str) -> None:
    t, data, sensor, axis = gait_imu()
    cols = [i for i, name in enumerate(sensor) if name == f"{foot}_sensor" and axis[i].startswith("gyr")]
    assert len(cols) == 3
    c = extract(t, data[:, cols])
    assert abs(c.period_s / _truth(foot) - 1) < 0.01, (c.period_s, _truth(foot))
    assert c.loops >= 20


@pytest.mark.parametrize("signals", ["gyroscope", "acceleration and gravity"])
def test_a_real_phone_u_turn_walk_gives_the_lap_not_a_multiple(signals: str) -> None:
    # Walking back and forth with the phone on the body, turning every ~3.9 s (the trace's README):
    # the lap repeats five or six times; twice the lap repeats as well but only twice.
    if not IPHONE.exists():
        pytest.skip(f"{IPHONE} not found (../shared/traces must sit beside the project)")
    from sim_devices.phone_sim import dispel_samples

    utt = next(lv for lv in dispel_samples(IPHONE).levels if lv.name == "utt")
    if signals == "gyroscope":
        t, x = (utt.gyro_ts_ms - utt.gyro_ts_ms[0]) / 1000.0, utt.rotation_rad_s
    else:
        t, x = (utt.acc_ts_ms - utt.acc_ts_ms[0]) / 1000.0, np.hstack([utt.user_acc_g, utt.gravity_g])
    c = extract(t, x)
    assert 3.6 < c.period_s < 4.2 and c.loops >= 4, (c.period_s, c.loops)
