"""Key-times, canonical time, the time operators, cyclification, concatenation and root repositioning
(Rose 1999, chapter 3, with perfcap's corrections; docs/design/verbs-and-adverbs.md)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from capture.quat import quat_exp, quat_log, quat_mul, quat_rotate, quat_slerp
from retarget.timeline import (
    Affine,
    Concatenation,
    Cyclify,
    Excerpt,
    SampledMotion,
    TimeWarp,
    canonical_time,
    cyclify_rotations,
    cyclify_values,
    ease_in,
    find_cycle,
    heading_of,
    reorient,
    reposition,
    sigmoid_blend,
    sigmoid_blend_slope,
    sine_warp,
    split_heading,
    verb_time,
    yaw_quat,
)

TRACES = Path(__file__).resolve().parents[3].parent / "shared" / "traces" / "d_mocap_cyclic"


def ramp_motion(duration: float = 1.0, key_times: list[float] | None = None, n: int = 201) -> SampledMotion:
    """Root walking +Z at 1 m/s with a sine height; DOF 4 = T / T^d, DOF 5 = sin(2 pi T / T^d) + T."""
    T = np.linspace(0.0, duration, n)
    vals = np.stack(
        [0.0 * T, 0.9 + 0.01 * np.sin(T), T, 0.0 * T, T / duration, np.sin(2 * np.pi * T / duration) + T], axis=1
    )
    return SampledMotion(T, vals, key_times)


# -- key-times ---------------------------------------------------------------------------------


def test_key_times_eq_3_1_and_3_2() -> None:
    k = [0.0, 0.4, 1.0, 1.2]
    assert canonical_time(0.4, k) == pytest.approx(1 / 3)
    assert canonical_time(0.7, k) == pytest.approx(0.5)
    assert canonical_time(1.2, k) == pytest.approx(1.0)
    assert verb_time(0.5, k) == pytest.approx(0.7)
    assert verb_time(0.25, [0.0, 2.0]) == pytest.approx(0.5)
    T = np.random.default_rng(1).uniform(0.0, 1.2, 50)
    np.testing.assert_allclose(verb_time(canonical_time(T, k), k), T, atol=1e-12)


@pytest.mark.parametrize("bad", [[0.0], [0.1, 1.0], [0.0, 0.5, 0.5, 1.0], [0.0, 1.0, 0.8], [0.0, math.nan]])
def test_key_times_rejected(bad: list[float]) -> None:
    with pytest.raises(ValueError):
        canonical_time(0.5, bad)


# -- reorient / reposition ---------------------------------------------------------------------


def test_reorient_example() -> None:
    pos = np.array([[1.0, 0.9, 2.0], [2.0, 0.95, 2.0]])
    head = np.array([math.pi / 2, math.pi / 2])
    out, h = reorient(pos, head)
    np.testing.assert_allclose(out[1], [0.0, 0.95, 1.0], atol=1e-12)
    np.testing.assert_allclose(h, [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(out[0], [0.0, 0.9, 0.0], atol=1e-12)


def test_reposition_with_zero_target_is_reorient() -> None:
    rng = np.random.default_rng(2)
    pos = np.cumsum(rng.normal(size=(40, 3)), axis=0)
    head = np.cumsum(rng.normal(scale=0.2, size=40))
    a_pos, a_h = reorient(pos, head)
    b_pos, b_h = reposition(pos, head, (0.0, None, 0.0, 0.0))
    np.testing.assert_allclose(a_pos, b_pos, atol=1e-12)
    np.testing.assert_allclose(a_h, b_h, atol=1e-12)


def test_reposition_rotates_by_plus_delta_heading() -> None:
    # walking straight ahead (+Z at heading 0) repositioned to heading pi/2 must walk +X, ahead of it
    pos = np.stack([np.zeros(5), np.full(5, 0.9), np.arange(5.0)], axis=1)
    out, h = reposition(pos, np.zeros(5), (3.0, 1.0, -1.0, math.pi / 2))
    np.testing.assert_allclose(out[:, 0], 3.0 + np.arange(5.0), atol=1e-12)
    np.testing.assert_allclose(out[:, 2], -1.0, atol=1e-12)
    np.testing.assert_allclose(out[:, 1], 1.0)
    np.testing.assert_allclose(h, math.pi / 2)
    # and the heading convention: heading pi/2 sends +Z to +X
    np.testing.assert_allclose(quat_rotate(yaw_quat(h[0]), [0.0, 0.0, 1.0]), [1.0, 0.0, 0.0], atol=1e-12)


def test_split_heading_round_trip() -> None:
    rng = np.random.default_rng(3)
    h = rng.uniform(-3.0, 3.0, 20)
    tilt = quat_exp(rng.normal(scale=0.3, size=(20, 3)) * np.array([1.0, 0.0, 1.0]))
    q = quat_mul(yaw_quat(h), tilt)
    hh, tt = split_heading(q)
    np.testing.assert_allclose(np.abs(np.sum(quat_mul(yaw_quat(hh), tt) * q, axis=-1)), 1.0, atol=1e-12)
    np.testing.assert_allclose(heading_of(tt), 0.0, atol=1e-12)
    np.testing.assert_allclose(quat_exp(quat_log(q)) * np.sign(q[:, :1]), q, atol=1e-12)


# -- affine ------------------------------------------------------------------------------------


def test_affine() -> None:
    m = ramp_motion(1.0, [0.0, 0.3, 1.0])
    a = Affine(m, 2.0, tau_start=3.0)
    assert a.duration == pytest.approx(2.0)
    np.testing.assert_allclose(a.theta(1.0), m.theta(0.5))
    np.testing.assert_allclose(a.key_times, 2.0 * m.key_times)
    assert a.tau(a.duration) == pytest.approx(a.tau_end)
    assert a.tau(a.duration) == pytest.approx(5.0)  # tau_s + T (the fix), not tau_s + s T = 7
    assert a.t(0.6) == pytest.approx(m.t(0.3))
    with pytest.raises(ValueError):
        Affine(m, 0.0)


# -- time-warp and blend functions -------------------------------------------------------------


def test_sine_warp_and_sigmoid() -> None:
    assert sine_warp(0.0) == pytest.approx(0.0, abs=1e-15)
    assert sine_warp(1.0) == pytest.approx(1.0)
    assert sine_warp(0.25) == pytest.approx(0.146447, abs=1e-6)
    assert sigmoid_blend(0.25) == pytest.approx(sine_warp(0.25), abs=1e-15)
    assert sigmoid_blend(0.5) == pytest.approx(0.5)
    assert sigmoid_blend_slope(0.0) == pytest.approx(0.0, abs=1e-15)
    assert sigmoid_blend_slope(1.0) == pytest.approx(0.0, abs=1e-15)
    h = 1e-6
    assert (sigmoid_blend(h) - sigmoid_blend(0.0)) / h < 1e-5
    assert (sigmoid_blend(1.0) - sigmoid_blend(1.0 - h)) / h < 1e-5
    assert np.all(np.diff(sigmoid_blend(np.linspace(0, 1, 101))) >= 0.0)


def test_time_warp_key_times_and_values() -> None:
    m = ramp_motion(2.0, [0.0, 0.5, 1.0, 2.0])
    w = TimeWarp(m, sine_warp)
    assert w.duration == pytest.approx(2.0)
    assert w.key_times[2] == pytest.approx(1.0, abs=1e-9)  # a key-time at T^d / 2 does not move
    np.testing.assert_allclose(w.w(w.key_times), m.key_times, atol=1e-9)  # K = w^-1(K')
    T = np.linspace(0.0, 2.0, 17)
    np.testing.assert_allclose(w.theta(T), m.theta(w.w(T)))
    np.testing.assert_allclose(w.t(T), m.t(w.w(T)), atol=1e-9)  # t(T) = t'(w(T))
    np.testing.assert_allclose(w.t(w.key_times), [0.0, 1 / 3, 2 / 3, 1.0], atol=1e-9)
    np.testing.assert_allclose(w.T(w.t(T)), T, atol=1e-9)
    e = TimeWarp(m, ease_in)
    assert e.key_times[1] == pytest.approx(1.0, abs=1e-9)  # K' = 0.5 = T^d (1/2)^2 -> T = 1.0
    with pytest.raises(ValueError):
        TimeWarp(m, lambda t: 0.5 * t)


# -- cyclification -----------------------------------------------------------------------------


def test_cyclify_ramp_becomes_constant() -> None:
    m = ramp_motion(1.5)
    c = Cyclify(m)
    T = np.linspace(0.0, 1.5, 31)
    np.testing.assert_allclose(c.theta(T)[:, 4], 0.5, atol=1e-12)
    ends = c.theta(np.array([0.0, 1.5]))
    np.testing.assert_allclose(ends[0, [1, 4, 5]], ends[1, [1, 4, 5]], atol=1e-12)
    np.testing.assert_allclose(c.theta(T)[:, [0, 2, 3]], m.theta(T)[:, [0, 2, 3]])  # X, Z, heading kept
    with pytest.raises(ValueError):
        Cyclify(m, mask=[True] * 6)


def test_cyclify_any_input_closes_the_seam() -> None:
    rng = np.random.default_rng(4)
    T = np.linspace(0.0, 1.0, 50)
    vals = np.cumsum(rng.normal(size=(50, 7)), axis=0)
    m = SampledMotion(T, vals)
    c = Cyclify(m)
    ends = c.theta(np.array([0.0, 1.0]))
    mask = c.mask
    np.testing.assert_allclose(ends[0, mask], ends[1, mask], atol=1e-12)
    # with the source's sign the gap would double instead
    gap = vals[-1] - vals[0]
    wrong = vals[-1] + 0.5 * gap - (vals[0] - 0.5 * gap)
    assert np.all(np.abs(wrong[mask]) > np.abs(gap[mask]) * 1.99)
    np.testing.assert_allclose(cyclify_values(vals)[0], cyclify_values(vals)[-1], atol=1e-12)


def test_cyclify_rotations_closes_the_seam() -> None:
    rng = np.random.default_rng(5)
    rv = np.cumsum(rng.normal(scale=0.1, size=(60, 4, 3)), axis=0)
    q = quat_exp(rv)
    c = cyclify_rotations(q)
    np.testing.assert_allclose(np.abs(np.sum(c[0] * c[-1], axis=-1)), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(c, axis=-1), 1.0, atol=1e-12)
    # the correction is spread: neighbouring samples stay as close as in the input (plus the spread)
    step_in = np.arccos(np.clip(np.abs(np.sum(q[1:] * q[:-1], -1)), 0, 1)).max()
    step_out = np.arccos(np.clip(np.abs(np.sum(c[1:] * c[:-1], -1)), 0, 1)).max()
    assert step_out < step_in + 0.05


def test_find_cycle_and_cyclify_real_walk() -> None:
    path = TRACES / "cmu_131_01_start_walk_stop.bvh"
    if not path.exists():
        pytest.skip(f"CMU walk not found at {path} (../shared/traces must sit beside the project)")
    from retarget.bvh import CMU_SCALE, read_bvh

    _, clip = read_bvh(path, scale=CMU_SCALE)
    h, tilt = split_heading(clip.rotations[:, 0])
    rel = quat_log(clip.rotations[:, 1:])
    vals = np.concatenate([clip.root_pos, np.unwrap(h)[:, None], quat_log(tilt), rel.reshape(clip.n_frames, -1)], 1)
    m = SampledMotion(clip.times, vals)
    # a rough designer's cycle mark in the steady walk (the gait period here is a little over 1 s)
    rough = (3.0, 4.1)
    ta, tb = find_cycle(m, *rough, window=0.25)
    mask = np.ones(vals.shape[1], dtype=bool)
    mask[[0, 2, 3]] = False
    before = np.sum((m.theta(rough[0]) - m.theta(rough[1]))[mask] ** 2)
    after = np.sum((m.theta(ta) - m.theta(tb))[mask] ** 2)
    assert after <= before
    cyc = Cyclify(Excerpt(m, ta, tb))
    ends = cyc.theta(np.array([0.0, cyc.duration]))
    np.testing.assert_allclose(ends[0, mask], ends[1, mask], atol=1e-9)
    assert 0.8 < cyc.duration < 1.6


# -- concatenation -----------------------------------------------------------------------------


def test_concatenation() -> None:
    m0 = ramp_motion(1.0, [0.0, 0.5, 1.0])
    T1 = np.linspace(0.0, 0.5, 51)
    turn = np.stack([np.sin(T1), 0.9 + 0 * T1, np.cos(T1) + 5.0, 0.3 + T1, 2 * T1, T1**2], axis=1)
    m1 = SampledMotion(T1, turn, [0.0, 0.2, 0.5])
    c = Concatenation([m0, m1])
    assert c.duration == pytest.approx(1.5)
    np.testing.assert_allclose(c.key_times, [0.0, 0.5, 1.0, 1.2, 1.5])
    np.testing.assert_allclose(c.theta(1.2)[4:], m1.theta(0.2)[4:])  # theta_1(T_loc), the fix
    assert c.active(1.2)[0] == 1 and c.active(1.2)[1] == pytest.approx(0.2)
    end0 = m0.theta(1.0)
    start1 = c.theta(1.0)
    np.testing.assert_allclose(start1[[0, 2, 3]], end0[[0, 2, 3]], atol=1e-12)  # root lined up
    # M_1's own displacement is turned by the heading difference (Alg 3.2, a = dY^r)
    a = end0[3] - m1.theta(0.0)[3]
    d_local = m1.theta(0.5)[[0, 2]] - m1.theta(0.0)[[0, 2]]
    d_world = c.theta(1.5)[[0, 2]] - c.theta(1.0)[[0, 2]]
    rot = np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])
    np.testing.assert_allclose(d_world, rot @ d_local, atol=1e-12)
    with pytest.raises(ValueError):
        Concatenation([])


def test_excerpt_key_times() -> None:
    m = ramp_motion(2.0, [0.0, 0.5, 1.2, 2.0])
    e = Excerpt(m, 0.4, 1.5)
    np.testing.assert_allclose(e.key_times, [0.0, 0.1, 0.8, 1.1])
    np.testing.assert_allclose(e.theta(0.3), m.theta(0.7))


def test_slerp_endpoints_and_unit_norm() -> None:
    rng = np.random.default_rng(6)
    a = quat_exp(rng.normal(size=(10, 3)))
    b = quat_exp(rng.normal(size=(10, 3)))
    np.testing.assert_allclose(quat_slerp(a, b, 0.0), a, atol=1e-12)
    np.testing.assert_allclose(np.abs(np.sum(quat_slerp(a, b, 1.0) * b, -1)), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(quat_slerp(a, b, 0.3), axis=-1), 1.0, atol=1e-12)
