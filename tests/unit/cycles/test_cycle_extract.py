"""Cycle extraction (``cycles.extract``, Ciccone 2019 section 5.3 as perfcap implements it, see
docs/design/cycles.md): the descriptor and eq. 5.3, noise-free and jittered loops (never a half or double
period, partial ends never averaged), closure, what must fail, determinism and time scaling, irregular
stamps, quaternions and Euler angles, wide inputs, gaps, layering, and the real gaitmap walk on which the
thesis's plain period search finds nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest
from gait_helpers import GAIT_IMU, GAIT_MOCAP, gait_strides

from capture.errors import NoMotionError, NoPeriodFoundError
from cycles import Cycle, ExtractOptions, extract, layer_onto
from cycles.descriptor import descriptors, distance_rows, distances_to, otsu_threshold
from cycles.matching import smallest_feasible_period
from sim_devices.loops import jittered_loops


def rel_err(c: Cycle, truth: float) -> float:
    return c.period_s / truth - 1.0


# -- the descriptor


def test_descriptor_is_offset_invariant_and_has_6n_entries() -> None:
    rng = np.random.default_rng(1)
    x = np.cumsum(rng.normal(size=(200, 3)), axis=0)
    h, g = descriptors(x, 1 / 120)
    h2, g2 = descriptors(x + np.array([5.0, -3.0, 1e3]), 1 / 120)
    assert h.shape == g.shape == (200, 6 * 3)
    np.testing.assert_allclose(h2, h, rtol=0, atol=1e-8)
    np.testing.assert_allclose(g2, g, rtol=0, atol=1e-5)
    d = distance_rows(h, g, np.arange(200))
    d2 = distance_rows(h2, g2, np.arange(200))
    np.testing.assert_allclose(d2, d, rtol=1e-6, atol=1e-6)
    assert np.allclose(np.diag(d), 0.0, atol=1e-6)
    np.testing.assert_allclose(d, d.T, rtol=1e-9, atol=1e-9)
    # the matrix form agrees with the direct one
    np.testing.assert_allclose(d[17], distances_to(h, g, 17), rtol=1e-6, atol=1e-6)


def test_descriptor_distance_is_a_product() -> None:
    # same first derivative window, different second: the product is 0 where either factor is
    x = np.zeros((50, 1))
    h, g = descriptors(x, 1.0)
    assert np.all(distances_to(h, g, 10) == 0)


def test_otsu_splits_two_clusters() -> None:
    v = np.concatenate([np.full(10, 1.0), np.full(5, 10.0)])
    thr = otsu_threshold(v)
    assert 1.0 < thr < 10.0


# -- noise-free sines


@pytest.mark.parametrize("period", [0.8, 1.0, 1.3])
def test_noise_free_sine(period: float) -> None:
    t = np.arange(0, 4 * period, 1 / 120)
    c = extract(t, np.sin(2 * np.pi * t / period))
    t0 = period * 120
    raw = c.raw_period_s * 120
    assert t0 - math.ceil(t0 / 8) <= raw <= t0 + 1, raw   # eq. 5.3: the smallest feasible T
    assert abs(rel_err(c, period)) < 0.005
    assert c.loops >= 3


def test_eq_5_3_smallest_feasible_period() -> None:
    matches = np.array([0, 100, 200, 300, 400], float)
    assert smallest_feasible_period(matches, 0.0, 0.0, 400.0, 12, 200) in range(88, 101)
    # a missing occurrence makes the exact period infeasible on the absolute grid (why chaining exists)
    assert smallest_feasible_period(np.array([0, 100, 300, 400.0]), 0.0, 0.0, 400.0, 60, 140) is None


# -- jittered harmonic loops


@pytest.mark.parametrize("seed", range(8))
def test_three_harmonic_channels(seed: int) -> None:
    tk = jittered_loops(4, channels=3, harmonics=3, per_channel_harmonic=True, noise=0.02, seed=seed)
    c = extract(tk.t, tk.values)
    assert abs(rel_err(c, tk.period_s)) < 0.03
    assert abs(c.raw_period_s / tk.period_s - 1) < 0.08 or math.isnan(c.raw_period_s)
    assert c.period_s > 0.7 * tk.period_s   # never a half period


@pytest.mark.parametrize("loops,least", [(3, 2), (6, 5)])
def test_loops_used_and_partial_ends_never_averaged(loops: int, least: int) -> None:
    for seed in range(4):
        tk = jittered_loops(loops, channels=3, noise=0.02, seed=seed)
        c = extract(tk.t, tk.values)
        assert c.loops >= least
        cuts = np.sort(c.cuts_s)
        for a, b in c.loop_spans_s:
            assert cuts[0] - 1e-9 <= a < b <= cuts[-1] + 1e-9
            # a loop runs from one cut to the next
            assert np.min(np.abs(cuts - a)) < 1e-9 and np.min(np.abs(cuts - b)) < 1e-9
            assert not np.any((cuts > a + 1e-9) & (cuts < b - 1e-9))


def test_double_frequency_channel_is_not_a_half_period() -> None:
    for seed in range(6):
        rng = np.random.default_rng(seed)
        t = np.arange(0, 4.0, 1 / 120)
        x = np.stack([np.sin(2 * np.pi * t + rng.uniform(0, 6)), 1.5 * np.sin(4 * np.pi * t + rng.uniform(0, 6))], 1)
        c = extract(t, x + rng.normal(0, 0.02, x.shape))
        assert abs(rel_err(c, 1.0)) < 0.01, c.period_s


@pytest.mark.parametrize("noise", [0.02, 0.05])
def test_shape_matches_the_template(noise: float) -> None:
    for seed, loops in [(0, 3), (1, 4), (2, 5)]:
        tk = jittered_loops(loops, channels=2, noise=noise, seed=seed)
        c = extract(tk.t, tk.values)
        ph = np.linspace(0, 1, 400, endpoint=False)
        truth = tk.template(ph)
        got = c.at(ph * c.period_s)
        rms = min(float(np.sqrt(np.mean((np.roll(truth, s, axis=0) - got) ** 2))) for s in range(400))
        assert rms <= 0.12, rms


# -- closure


def test_stitching_closes_the_loop_spreading_the_gap() -> None:
    tk = jittered_loops(4, channels=3, noise=0.05, seed=3)
    c = extract(tk.t, tk.values)
    assert np.max(np.abs(c.values[0] - c.values[-1])) <= 1e-9
    assert c.aligned is not None
    avg = c.aligned.mean(axis=0)
    # each end moved by half the gap
    np.testing.assert_allclose(c.values[0], 0.5 * (avg[0] + avg[-1]), atol=1e-9)
    assert c.closure_error >= 0
    # the periodic spline is C1 at the seam
    eps = 1e-5
    d0 = (c.at(eps) - c.at(-eps)) / (2 * eps)
    d1 = (c.at(c.period_s + eps) - c.at(c.period_s - eps)) / (2 * eps)
    np.testing.assert_allclose(d0, d1, atol=1e-6)


# -- what must fail, and what need not


def test_constant_input_is_no_motion() -> None:
    t = np.arange(0, 3, 0.01)
    with pytest.raises(NoMotionError):
        extract(t, np.full((t.size, 2), 3.5))


@pytest.mark.parametrize("kind", ["white", "walk", "ramp"])
def test_non_periodic_input_has_no_period(kind: str) -> None:
    for seed in range(5):
        rng = np.random.default_rng(seed)
        t = np.arange(600) / 120
        if kind == "white":
            x = rng.normal(size=(600, 3))
        elif kind == "walk":
            x = np.cumsum(rng.normal(size=(600, 3)), axis=0)
        else:
            x = np.outer(t, [1.0, 2.0, 3.0]) + 0.01 * rng.normal(size=(600, 3))
        with pytest.raises(NoPeriodFoundError) as ei:
            extract(t, x)
        assert "\n" not in str(ei.value)


def test_chirp_may_be_accepted() -> None:
    # loops from 1.0 s to 1.4 s: the warp absorbs the timing change, so acceptance is allowed
    durs = np.linspace(1.0, 1.4, 5)
    bounds = np.concatenate([[0], np.cumsum(durs)])
    t = np.arange(0, bounds[-1], 1 / 120)
    k = np.clip(np.searchsorted(bounds, t, side="right") - 1, 0, 4)
    ph = k + (t - bounds[k]) / durs[k]
    x = np.stack([np.sin(2 * np.pi * ph), np.cos(4 * np.pi * ph)], 1)
    try:
        c = extract(t, x)
    except NoPeriodFoundError:
        return
    assert 0.95 <= c.period_s <= 1.45


def test_too_short_and_malformed_inputs() -> None:
    with pytest.raises(NoPeriodFoundError):
        extract(np.arange(5) / 100, np.arange(5.0))
    with pytest.raises(ValueError):
        extract(np.arange(10), np.zeros((9, 2)))
    with pytest.raises(ValueError):
        extract(np.arange(10), np.zeros((10, 2)), channels=["a"])
    with pytest.raises(ValueError):
        extract(np.arange(10), np.zeros((10, 4)), quaternions=[(0, 1, 2)])
    with pytest.raises(ValueError):
        ExtractOptions(min_consistency=1.5)


# -- determinism, time scaling, irregular stamps


def test_bit_identical_for_a_seed_and_scales_with_time() -> None:
    tk = jittered_loops(5, channels=4, noise=0.03, seed=11)
    a = extract(tk.t, tk.values, seed=3)
    b = extract(tk.t, tk.values, seed=3)
    assert a.period_s == b.period_s and np.array_equal(a.values, b.values) and np.array_equal(a.cuts_s, b.cuts_s)
    s = 2.5
    c = extract(tk.t * s, tk.values, seed=3)
    # equal up to rounding: the descriptor sees derivatives in other units, so the anchors that align
    # the loops may settle a fraction of a sample apart (0.1 % of the period here, a tenth of a sample)
    assert abs(c.period_s / (a.period_s * s) - 1) < 2e-3
    assert c.loops == a.loops
    phase = np.linspace(0.0, 1.0, 200, endpoint=False)
    np.testing.assert_allclose(c.at(phase * c.period_s), a.at(phase * a.period_s), atol=0.02)


def test_irregular_timestamps_agree_with_a_uniform_grid() -> None:
    for seed in range(4):
        uni = jittered_loops(4, channels=3, noise=0.01, time_jitter=0.0, seed=seed, rate_hz=125.0)
        irr = jittered_loops(4, channels=3, noise=0.01, seed=seed, irregular_mean_s=0.008)
        cu = extract(uni.t, uni.values)
        ci = extract(irr.t, irr.values)
        dt = float(np.median(np.diff(irr.t)))
        assert abs(ci.period_s - cu.period_s) <= 1.5 * dt, (ci.period_s, cu.period_s, dt)
        assert abs(rel_err(ci, irr.period_s)) < 0.02


# -- quaternions


def quat_take(flips: bool, seed: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    rng = np.random.default_rng(seed)
    tk = jittered_loops(4, channels=2, noise=0.0, seed=seed)
    ang = np.radians(170.0) * np.sin(2 * np.pi * tk.phase_at(tk.t))
    half = ang / 2
    q = np.stack([np.cos(half), np.zeros_like(half), np.sin(half), np.zeros_like(half)], 1)
    if flips:
        q[rng.random(q.shape[0]) < 0.3] *= -1
    vals = np.concatenate([q, tk.values], axis=1)
    return tk.t, vals, tk.period_s


def test_quaternion_flips_do_not_change_the_period() -> None:
    t, v, truth = quat_take(False)
    t2, v2, _ = quat_take(True)
    a = extract(t, v, quaternions=[(0, 1, 2, 3)])
    b = extract(t2, v2, quaternions=[(0, 1, 2, 3)])
    assert abs(a.period_s - b.period_s) < 1e-9
    assert abs(rel_err(a, truth)) < 0.01
    norms = np.linalg.norm(b.values[:, :4], axis=1)
    assert np.max(np.abs(norms - 1)) < 1e-9
    assert np.max(np.abs(np.linalg.norm(b.at(np.linspace(0, 3, 50))[:, :4], axis=1) - 1)) < 1e-9
    # the cycle swings about +-170 degrees, as performed
    w = np.abs(b.values[:, 0])
    assert np.degrees(2 * np.arccos(np.clip(w.min(), 0, 1))) > 150


def test_euler_angles_are_unwrapped() -> None:
    tk = jittered_loops(4, channels=1, noise=0.0, seed=2)
    deg = 175.0 * np.sin(2 * np.pi * tk.phase_at(tk.t)) + 90.0
    wrapped = (deg + 180.0) % 360.0 - 180.0            # jumps at +-180
    c = extract(tk.t, np.stack([wrapped, tk.values[:, 0]], 1), angles=[0], angle_unit="deg")
    assert abs(rel_err(c, tk.period_s)) < 0.01
    assert np.max(np.abs(np.diff(c.values[:, 0]))) < 30   # continuous, in degrees


# -- wide inputs complete


@pytest.mark.parametrize("channels", [254, 2611])
def test_wide_inputs(channels: int) -> None:
    tk = jittered_loops(4, channels=channels, noise=0.03, seed=5)
    c = extract(tk.t, tk.values)
    assert c.values.shape[1] == channels
    assert abs(rel_err(c, tk.period_s)) < 0.01


# -- gaps and notes


def test_a_gap_is_a_break_no_loop_crosses() -> None:
    tk = jittered_loops(8, channels=2, noise=0.02, seed=4)
    keep = (tk.t < 0.5) | (tk.t > 1.0)
    c = extract(tk.t[keep], tk.values[keep])
    assert any("gap" in n for n in c.notes)
    # the half loop before the gap holds no loop; none is cut across the gap
    assert c.loop_spans_s.min() >= 1.0
    assert abs(rel_err(c, tk.period_s)) < 0.03


def test_loops_on_both_sides_of_a_gap_keep_their_times() -> None:
    tk = jittered_loops(8, channels=3, noise=0.02, seed=5)
    cut = tk.boundaries_s[4] + 0.3 * tk.period_s
    t = np.where(tk.t < cut, tk.t, tk.t + 20.0)    # the recording stopped for 20 s
    c = extract(t, tk.values)
    spans = c.loop_spans_s
    assert np.any(spans[:, 1] <= cut) and np.any(spans[:, 0] >= cut + 20.0)
    assert not np.any((spans[:, 0] < cut) & (spans[:, 1] > cut + 20.0))
    # each cut is a time of the input: the performer's loop phase there is the same everywhere
    ph = np.mod(tk.phase_at(np.where(c.cuts_s < cut, c.cuts_s, c.cuts_s - 20.0)), 1.0)
    assert np.ptp(np.angle(np.exp(2j * np.pi * (ph - ph[0])))) / (2 * np.pi) < 0.05
    assert abs(rel_err(c, tk.period_s)) < 0.01


def test_unsorted_duplicated_and_nan_samples_are_dropped_with_a_note() -> None:
    tk = jittered_loops(4, channels=2, noise=0.02, seed=6)
    t = np.concatenate([tk.t, tk.t[:10]])
    v = np.concatenate([tk.values, tk.values[:10]])
    v[50, 1] = np.nan
    perm = np.random.default_rng(0).permutation(t.size)
    c = extract(t[perm], v[perm])
    assert any("repeated" in n for n in c.notes) and any("non-finite" in n for n in c.notes)
    assert abs(rel_err(c, tk.period_s)) < 0.02


# -- layering


def test_layering_aligns_to_the_master_clock() -> None:
    # master: a loop of 1.0 s. A second layer is performed while the master plays back, the playback
    # starting at t = 0.3 s of the new take; the performer follows it at its tempo.
    t = np.arange(0, 6.0, 1 / 120)
    master = extract(t, np.stack([np.sin(2 * np.pi * t), np.cos(4 * np.pi * t)], 1))
    start = 0.3
    ph = t - start
    new = extract(t, np.stack([np.cos(2 * np.pi * ph), np.sin(6 * np.pi * ph)], 1))
    layered = layer_onto(new, master, master_start_s=start)
    assert layered.period_s == pytest.approx(master.period_s)
    # played together from master time 0, the layer shows what the performer did at that point of the
    # playback: at master time tau, the new take at start + tau
    tt = np.linspace(0, master.period_s, 200, endpoint=False)
    truth = np.stack([np.cos(2 * np.pi * tt), np.sin(6 * np.pi * tt)], 1)
    np.testing.assert_allclose(layered.at(tt), truth, atol=0.02)
    # and the master itself starts at its first cut
    m0 = master.loop_spans_s[0, 0]
    expected = np.stack([np.sin(2 * np.pi * (tt + m0)), np.cos(4 * np.pi * (tt + m0))], 1)
    np.testing.assert_allclose(master.at(tt), expected,
                               atol=0.02)


# -- the real gaitmap walk (eq. 5.3 on its absolute grid finds nothing here)


def _gait() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[str]]:
    f = GAIT_IMU / "imu_sample_not_rotated.csv"
    m = GAIT_MOCAP / "mocap_sample.csv"
    if not f.exists() or not m.exists():
        pytest.skip(f"gaitmap walk not found at {GAIT_IMU} (../shared/traces must sit beside the project)")
    imu = np.genfromtxt(f, delimiter=",", skip_header=2)
    mo = np.genfromtxt(m, delimiter=",", skip_header=2)
    hdr = m.read_text().splitlines()[0].split(",")
    return imu[:, 0] / 204.8, imu[:, 1:], mo[:, 0] / 100.0, mo, hdr


@pytest.mark.parametrize("foot", ["left", "right"])
@pytest.mark.parametrize("source", ["imu", "mocap"])
def test_gaitmap_walk_whole_take(foot: str, source: str) -> None:
    t_imu, imu, t_mo, mo, hdr = _gait()
    if source == "imu":
        t, x = t_imu, imu[:, 0:6] if foot == "left" else imu[:, 6:12]
    else:
        cols = [i for i, h in enumerate(hdr) if h.startswith(foot[0].upper() + "_")]
        t, x = t_mo, mo[:, cols]
    b = gait_strides(foot)
    truth = float(np.median(b[:, 1] - b[:, 0]))
    c = extract(t, x)
    assert abs(rel_err(c, truth)) < 0.005, (c.period_s, truth)
    assert c.loops >= 20
    # the cuts fall at one gait phase: circular spread of their phase in the annotated strides
    ph = []
    for cut in c.cuts_s:
        k = np.flatnonzero((b[:, 0] <= cut) & (b[:, 1] > cut))
        if k.size:
            ph.append((cut - b[k[0], 0]) / (b[k[0], 1] - b[k[0], 0]))
    assert len(ph) >= 20
    r = abs(np.mean(np.exp(2j * np.pi * np.array(ph))))
    assert np.sqrt(-2 * np.log(r)) / (2 * np.pi) < 0.05
