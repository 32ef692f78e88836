"""Tests for ``cycles.edit``: MoCurve spatial edits, temporal re-timing and planar contacts.

Ciccone 2019, section 5.4 (eq. 5.6, 5.7-5.11 and 5.12) as perfcap implements it
(docs/design/cycles.md): the falloff weights, re-timing with and without (contradictory) constraints,
contacts that stop sliding, plus wrap-around, closure, argument checks, a synthetic walk with a stance
on each foot, and one real stride of the gaitmap optical-marker walk
(``../shared/traces/d_mocap_cyclic/gaitmap_walk/``, read in place).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cycles.edit import (
    ContactResult,
    contact_intervals,
    edit_rotation,
    edit_scale,
    edit_translation,
    falloff_weights,
    fix_sliding,
    project_to_plane,
    retime,
    retimed_frames,
)

TRACES = Path(__file__).resolve().parents[3].parent / "shared" / "traces"
GAITMAP = TRACES / "d_mocap_cyclic" / "gaitmap_walk"
MOCAP_HZ = 100.0  # optical markers
IMU_HZ = 204.8  # the stride annotations count IMU samples


def _wxyz(rot: Rotation) -> np.ndarray:
    return np.roll(rot.as_quat(), 1, axis=-1)


def _rot(q_wxyz: np.ndarray) -> Rotation:
    return Rotation.from_quat(np.roll(np.asarray(q_wxyz), -1, axis=-1))


# ------------------------------------------------------------------------------------------------
# 2.1 Spatial edits
# ------------------------------------------------------------------------------------------------


class TestFalloffWeights:
    def test_spec_14_values_at_frame_10(self):
        w = falloff_weights(60, 10, 3, sigma=math.log(100) / 9)
        expected = [0.010, 0.129, 0.599, 1.0, 0.599, 0.129, 0.010]
        np.testing.assert_allclose(w[7:14], expected, atol=5e-4)
        assert w[10] == 1.0
        assert np.all(np.delete(w, np.arange(7, 14)) == 0.0)

    def test_default_sigma_is_the_spec_proposal(self):
        np.testing.assert_array_equal(falloff_weights(60, 10, 3), falloff_weights(60, 10, 3, math.log(100) / 9))
        # weight 0.01 exactly at distance tau, for any tau
        for tau in (1, 2, 5, 9):
            w = falloff_weights(40, 20, tau)
            assert w[20 + tau] == pytest.approx(0.01, rel=1e-12)
            assert w[20 - tau] == pytest.approx(0.01, rel=1e-12)
            assert w[20 + tau + 1] == 0.0

    def test_edit_at_frame_0_wraps_to_the_last_frames(self):
        m = 60
        w = falloff_weights(m, 0, 3)
        assert set(np.flatnonzero(w)) == {m - 3, m - 2, m - 1, 0, 1, 2, 3}
        np.testing.assert_allclose(w[[m - 1, m - 2, m - 3]], w[[1, 2, 3]], rtol=0, atol=0)
        np.testing.assert_allclose(w[[m - 3, m - 2, m - 1, 0, 1, 2, 3]], falloff_weights(m, 10, 3)[7:14])

    def test_edit_at_last_frame_wraps_forward(self):
        w = falloff_weights(30, 29, 2)
        assert set(np.flatnonzero(w)) == {27, 28, 29, 0, 1}

    def test_custom_sigma(self):
        w = falloff_weights(20, 5, 4, sigma=0.5)
        np.testing.assert_allclose(w[1:10], np.exp(-0.5 * np.arange(-4, 5) ** 2))

    def test_tau_zero_edits_one_frame(self):
        w = falloff_weights(12, 4, 0)
        np.testing.assert_array_equal(w, np.eye(12)[4])

    def test_window_wider_than_the_loop_uses_the_circular_distance(self):
        m = 7
        w = falloff_weights(m, 0, 10, sigma=0.1)
        dist = np.minimum(np.arange(m), m - np.arange(m))
        np.testing.assert_allclose(w, np.exp(-0.1 * dist**2))
        assert np.all(w > 0)

    @pytest.mark.parametrize(
        ("m", "i", "tau", "sigma"),
        [
            (0, 0, 1, None),
            (10, 10, 1, None),
            (10, -1, 1, None),
            (10, 2, -1, None),
            (10, 2.0, 1, None),
            (10, 2, 1.5, None),
            (10, True, 1, None),
            (10, 2, 1, 0.0),
            (10, 2, 1, -1.0),
            (10, 2, 1, math.inf),
            (10, 2, 1, math.nan),
        ],
    )
    def test_bad_arguments(self, m, i, tau, sigma):
        with pytest.raises(ValueError):
            falloff_weights(m, i, tau, sigma)

    def test_numpy_integers_are_accepted(self):
        np.testing.assert_array_equal(falloff_weights(np.int64(60), np.int32(10), np.int16(3)),
                                      falloff_weights(60, 10, 3))


class TestEditTranslation:
    def test_scalar_curve_gets_the_rbf_weights(self):
        P = np.zeros(60)
        out = edit_translation(P, 10, 1.0, 3)
        np.testing.assert_array_equal(out, falloff_weights(60, 10, 3))
        assert np.all(P == 0), "input modified in place"

    def test_vector_offset_and_untouched_frames(self):
        rng = np.random.default_rng(1)
        P = rng.normal(size=(50, 3))
        before = P.copy()
        delta = np.array([0.5, -1.0, 2.0])
        out = edit_translation(P, 49, delta, 4)
        np.testing.assert_array_equal(P, before)
        w = falloff_weights(50, 49, 4)
        np.testing.assert_allclose(out - P, np.outer(w, delta), atol=1e-15)
        np.testing.assert_array_equal(out[w == 0], P[w == 0])
        np.testing.assert_allclose(out[49], P[49] + delta)

    def test_closed_curve_keeps_its_closure_when_editing_near_the_seam(self):
        m = 40
        t = np.linspace(0, 1, m + 1)
        P = np.column_stack([np.cos(2 * np.pi * t), np.sin(2 * np.pi * t), t * 0])
        P[-1] = P[0]
        for i in (0, 1, m - 1, m):
            out = edit_translation(P, i, np.array([0.0, 0.0, 1.0]), 3, closed=True)
            assert out.shape == (m + 1, 3)
            np.testing.assert_array_equal(out[-1], out[0])
            assert out[i % m, 2] == 1.0
        out = edit_translation(P, m, np.array([0.0, 0.0, 1.0]), 3, closed=True)
        np.testing.assert_array_equal(out, edit_translation(P, 0, np.array([0.0, 0.0, 1.0]), 3, closed=True))

    def test_closed_edit_matches_the_open_edit_on_the_distinct_frames(self):
        rng = np.random.default_rng(2)
        P = rng.normal(size=(21, 2))
        P[-1] = P[0]
        a = edit_translation(P, 19, np.array([1.0, 2.0]), 3, closed=True)
        b = edit_translation(P[:-1], 19, np.array([1.0, 2.0]), 3)
        np.testing.assert_array_equal(a[:-1], b)

    @pytest.mark.parametrize(
        ("P", "i", "delta", "kwargs"),
        [
            (np.zeros((10, 3)), 10, np.ones(3), {}),
            (np.zeros((10, 3)), 0, np.ones(2), {}),
            (np.zeros((10, 3)), 0, 1.0, {}),
            (np.full((10, 3), np.nan), 0, np.ones(3), {}),
            (np.zeros((10, 3)), 0, np.array([1.0, np.inf, 0.0]), {}),
            (np.zeros((2, 3, 4)), 0, np.ones((3, 4)), {}),
            (np.arange(30.0).reshape(10, 3), 0, np.ones(3), {"closed": True}),  # ends differ
            (np.zeros((1, 3)), 0, np.ones(3), {"closed": True}),
            (np.zeros((10, 3)), 11, np.ones(3), {"closed": True}),
            (np.zeros((10, 3)), 0, np.ones(3), {"sigma": -1.0}),
        ],
    )
    def test_bad_arguments(self, P, i, delta, kwargs):
        with pytest.raises(ValueError):
            edit_translation(P, i, delta, 2, **kwargs)


class TestEditRotation:
    @staticmethod
    def curve(m: int, seed: int = 3) -> np.ndarray:
        angles = np.linspace(0, 2 * np.pi, m, endpoint=False)
        rot = Rotation.from_euler("zyx", np.column_stack([np.sin(angles), 0.3 * np.cos(angles), 0.2 + 0 * angles]))
        return _wxyz(rot)

    def test_edited_frame_gets_the_full_rotation_and_norms_stay_one(self):
        Q = self.curve(30)
        dq = _wxyz(Rotation.from_rotvec([0.0, 0.0, 0.8]))
        out = edit_rotation(Q, 5, dq, 3)
        np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-12)
        expected = _rot(dq) * _rot(Q[5])
        assert (expected.inv() * _rot(out[5])).magnitude() < 1e-12

    def test_neighbours_turn_by_their_weight_about_the_same_axis(self):
        Q = self.curve(30)
        axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
        dq = _wxyz(Rotation.from_rotvec(1.2 * axis))
        out = edit_rotation(Q, 0, dq, 3)
        w = falloff_weights(30, 0, 3)
        for j in range(30):
            step = _rot(out[j]) * _rot(Q[j]).inv()  # applied on the left
            np.testing.assert_allclose(step.as_rotvec(), w[j] * 1.2 * axis, atol=1e-12)
        # frames outside the window are unchanged (up to renormalisation); the window wrapped to 27..29
        assert set(np.flatnonzero(w)) == {27, 28, 29, 0, 1, 2, 3}
        np.testing.assert_allclose(out[w == 0], Q[w == 0], rtol=0, atol=1e-15)

    def test_scalar_first_convention(self):
        Q = np.tile([1.0, 0.0, 0.0, 0.0], (8, 1))
        dq = np.array([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])  # 90 deg about z
        out = edit_rotation(Q, 2, dq, 0)
        np.testing.assert_allclose(out[2], dq, atol=1e-15)
        np.testing.assert_array_equal(out[np.arange(8) != 2], Q[np.arange(8) != 2])

    def test_hemisphere_of_the_input_is_kept(self):
        Q = self.curve(20)
        Q[::2] *= -1.0  # same rotations, alternating signs
        out = edit_rotation(Q, 4, _wxyz(Rotation.from_rotvec([0.0, 0.1, 0.0])), 5)
        assert np.all(np.sum(out * Q, axis=1) > 0)

    def test_non_unit_input_is_renormalised(self):
        Q = self.curve(10) * 3.0
        out = edit_rotation(Q, 0, np.array([2.0, 0.0, 0.0, 0.0]), 2)  # identity edit, non-unit dq
        np.testing.assert_allclose(out, Q / 3.0, atol=1e-15)

    def test_closed_curve_keeps_last_equal_first(self):
        Q = self.curve(24)
        closed = np.vstack([Q, Q[0]])
        dq = _wxyz(Rotation.from_rotvec([0.3, -0.2, 0.1]))
        for i in (0, 1, 23, 24):
            out = edit_rotation(closed, i, dq, 4, closed=True)
            np.testing.assert_array_equal(out[-1], out[0])
        flipped = np.vstack([Q, -Q[0]])
        out = edit_rotation(flipped, 0, dq, 4, closed=True)
        np.testing.assert_array_equal(out[-1], -out[0])

    @pytest.mark.parametrize(
        ("Q", "dq", "kwargs"),
        [
            (np.zeros((10, 4)), np.array([1.0, 0, 0, 0]), {}),
            (np.tile([1.0, 0, 0, 0], (10, 1)), np.zeros(4), {}),
            (np.tile([1.0, 0, 0, 0], (10, 1)), np.array([1.0, 0, 0]), {}),
            (np.tile([1.0, 0, 0], (10, 1)), np.array([1.0, 0, 0, 0]), {}),
            (np.tile([1.0, 0, 0, 0], (10, 1)), np.array([np.nan, 0, 0, 0]), {}),
            (np.vstack([np.tile([1.0, 0, 0, 0], (9, 1)), [0, 1.0, 0, 0]]), np.array([1.0, 0, 0, 0]), {"closed": True}),
        ],
    )
    def test_bad_arguments(self, Q, dq, kwargs):
        with pytest.raises(ValueError):
            edit_rotation(Q, 0, dq, 2, **kwargs)


class TestEditScale:
    def test_multiplicative_in_log_space_and_positive(self):
        S = np.full((30, 3), 2.0)
        out = edit_scale(S, 3, np.array([4.0, 0.25, 1.0]), 3)
        w = falloff_weights(30, 3, 3)
        np.testing.assert_allclose(out, 2.0 * np.column_stack([4.0**w, 0.25**w, np.ones(30)]), rtol=1e-14)
        assert np.all(out > 0)
        np.testing.assert_allclose(out[3], [8.0, 0.5, 2.0])
        assert np.all(S == 2.0)

    def test_extreme_shrink_stays_positive_and_inverse_edit_undoes(self):
        S = np.linspace(0.5, 3.0, 16)
        tiny = edit_scale(S, 0, 1e-12, 5)
        assert np.all(tiny > 0)
        back = edit_scale(tiny, 0, 1e12, 5)
        np.testing.assert_allclose(back, S, rtol=1e-10)

    def test_closed(self):
        S = np.abs(np.sin(np.linspace(0, np.pi, 11))) + 1.0
        S[-1] = S[0]
        out = edit_scale(S, 9, 3.0, 2, closed=True)
        assert out[-1] == out[0]
        assert out[0] == pytest.approx(S[0] * 3.0 ** falloff_weights(10, 9, 2)[0])

    @pytest.mark.parametrize(
        ("S", "factor"),
        [
            (np.zeros((5, 2)) + np.array([1.0, 0.0]), np.ones(2)),
            (np.full((5, 2), -1.0), np.ones(2)),
            (np.ones((5, 2)), np.array([1.0, 0.0])),
            (np.ones((5, 2)), np.array([1.0, -2.0])),
            (np.ones((5, 2)), np.ones(3)),
            (np.ones((5, 2)), np.array([np.inf, 1.0])),
        ],
    )
    def test_bad_arguments(self, S, factor):
        with pytest.raises(ValueError):
            edit_scale(S, 0, factor, 1)


# ------------------------------------------------------------------------------------------------
# 2.2 Temporal re-timing
# ------------------------------------------------------------------------------------------------


def _objective(ts, t, constraints, period, w=(1e4, 1e4, 1.0, 1.0)):
    """Eq. 5.11 written out directly in the frame times (independent of the solver's step form)."""
    d, d0 = np.diff(ts), np.diff(t)
    e_c = sum((ts[i] - c) ** 2 for i, c in constraints.items())
    e_t = (ts[-1] - ts[0] - period) ** 2
    e_v = np.sum((d - d0) ** 2)
    e_s = np.sum((d - np.roll(d, 1)) ** 2)
    return w[0] * e_c + w[1] * e_t + w[2] * e_v + w[3] * e_s


def _assert_optimal(ts, t, constraints, period, pinned=True):
    """No feasible nearby step pattern lowers the objective (a KKT check by perturbation)."""
    rng = np.random.default_rng(7)
    f0 = _objective(ts, t, constraints, period)
    d = np.diff(ts)
    for h in (1e-3, 1e-5):
        for _ in range(40):
            dn = np.maximum(d + h * rng.normal(size=d.size), 0.0)
            start = ts[0] if pinned else ts[0] + h * rng.normal()
            trial = np.concatenate([[start], start + np.cumsum(dn)])
            assert _objective(trial, t, constraints, period) >= f0 - 1e-9 * max(1.0, f0)


class TestRetime:
    def test_spec_15(self):
        t = np.arange(61.0)
        ts = retime(t, {0: 0.0, 15: 20.0})
        assert ts.shape == (61,)
        assert abs(ts[15] - 20.0) < 1e-3
        assert abs(ts[60] - ts[0] - 60.0) < 1e-3
        steps = np.diff(ts)
        assert np.all(steps >= 0)
        assert steps[:15].mean() > 1.0
        assert steps[15:].mean() < 1.0
        # the prototype's figures
        assert ts[15] == pytest.approx(19.99995, abs=2e-5)
        assert steps.min() == pytest.approx(0.88, abs=0.01)
        assert steps.max() == pytest.approx(1.36, abs=0.01)
        _assert_optimal(ts, t, {0: 0.0, 15: 20.0}, 60.0, pinned=False)

    def test_spec_16_no_constraints_is_the_identity(self):
        t = np.arange(61.0)
        np.testing.assert_allclose(retime(t, {}), t, rtol=0, atol=1e-9)

    def test_no_constraints_non_uniform_times_are_smoothed_not_kept(self):
        # E_S (eq. 5.10) compares neighbouring steps in absolute terms, so without constraints uneven
        # steps are evened out a little; the start, the period and the order are kept.
        rng = np.random.default_rng(4)
        t = np.concatenate([[0.3], 0.3 + np.cumsum(rng.uniform(0.005, 0.02, 120))])
        ts = retime(t, {})
        assert ts[0] == 0.3
        assert ts[-1] - ts[0] == pytest.approx(t[-1] - t[0], abs=1e-6)
        assert np.all(np.diff(ts) >= 0)
        def roughness(x):
            return np.sum((np.diff(x) - np.roll(np.diff(x), 1)) ** 2)

        assert roughness(ts) < 0.5 * roughness(t)
        _assert_optimal(ts, t, {}, t[-1] - t[0])

    def test_spec_16_contradictory_constraints(self):
        t = np.arange(61.0)
        ts = retime(t, {15: 20.0, 16: 15.0})
        assert ts[15] == pytest.approx(ts[16], abs=1e-9)
        assert ts[15] == pytest.approx(17.5, abs=1e-3)
        assert np.all(np.diff(ts) >= 0)
        assert ts[0] == 0.0  # pinned: frame 0 is not constrained
        _assert_optimal(ts, t, {15: 20.0, 16: 15.0}, 60.0)

    def test_constraint_at_frame_0_frees_the_start(self):
        t = np.arange(31.0)
        ts = retime(t, {0: 5.0})
        np.testing.assert_allclose(ts, t + 5.0, rtol=0, atol=1e-9)

    def test_constraint_at_the_closing_frame(self):
        t = np.linspace(0.0, 1.0, 41)
        ts = retime(t, {40: 1.2})
        # E_T and E_C disagree by 0.2 with equal weights: the end meets them halfway.
        assert ts[-1] == pytest.approx(1.1, abs=1e-3)
        assert np.all(np.diff(ts) >= 0)

    def test_period_override(self):
        t = np.arange(61.0)
        ts = retime(t, {}, period=30.0)
        assert ts[-1] - ts[0] == pytest.approx(30.0, abs=0.01)
        np.testing.assert_allclose(np.diff(ts), np.diff(ts)[0], atol=1e-9)  # uniform compression

    def test_weights_change_the_compromise(self):
        t = np.arange(61.0)
        strict = retime(t, {15: 20.0}, w_c=1e6)
        loose = retime(t, {15: 20.0}, w_c=1.0)
        assert abs(strict[15] - 20.0) < abs(loose[15] - 20.0)
        assert 15.0 < loose[15] < 20.0
        no_smooth = retime(t, {15: 20.0}, w_s=0.0)
        assert np.all(np.diff(no_smooth) >= 0)

    @pytest.mark.parametrize("m", [240, 1000])
    def test_large_cycles_with_active_bounds(self, m):
        t = np.linspace(0.0, 2.0, m + 1)
        cons = {m // 4: 0.8, m // 4 + 1: 0.5, m // 2: 0.9, m // 2 + 3: 0.85, 3 * m // 4: 1.9}
        ts = retime(t, cons)
        steps = np.diff(ts)
        assert np.all(steps >= 0)
        assert np.sum(steps == 0) >= 2  # two pairs pulled past each other meet
        assert ts[m // 4] == pytest.approx(ts[m // 4 + 1])
        assert ts[-1] - ts[0] == pytest.approx(2.0, abs=1e-3)
        assert ts[3 * m // 4] == pytest.approx(1.9, abs=1e-3)
        _assert_optimal(ts, t, cons, 2.0)

    def test_input_is_not_modified(self):
        t = np.arange(11.0)
        before = t.copy()
        retime(t, {3: 4.0})
        np.testing.assert_array_equal(t, before)

    @pytest.mark.parametrize(
        ("t", "constraints", "kwargs"),
        [
            (np.arange(61.0), {61: 1.0}, {}),
            (np.arange(61.0), {-1: 1.0}, {}),
            (np.arange(61.0), {1.5: 1.0}, {}),
            (np.arange(61.0), {"3": 1.0}, {}),
            (np.arange(61.0), {3: math.nan}, {}),
            (np.arange(61.0), {3: math.inf}, {}),
            (np.arange(61.0), {3: None}, {}),
            (np.arange(61.0), {3: "soon"}, {}),
            (np.arange(2.0), {}, {}),
            (np.array([0.0, 2.0, 1.0, 3.0]), {}, {}),
            (np.zeros(5), {}, {}),
            (np.array([0.0, 1.0, np.nan]), {}, {}),
            (np.arange(10.0).reshape(5, 2), {}, {}),
            (np.arange(61.0), {}, {"period": 0.0}),
            (np.arange(61.0), {}, {"period": -1.0}),
            (np.arange(61.0), {}, {"w_c": 0.0}),
            (np.arange(61.0), {}, {"w_t": -1.0}),
            (np.arange(61.0), {}, {"w_v": 0.0}),
            (np.arange(61.0), {}, {"w_s": -1.0}),
            (np.arange(61.0), {}, {"w_s": math.nan}),
        ],
    )
    def test_bad_arguments(self, t, constraints, kwargs):
        with pytest.raises(ValueError):
            retime(t, constraints, **kwargs)


class TestRetimedFrames:
    def test_identity_times_give_the_curve_back(self):
        t = np.linspace(0.0, 1.0, 33)
        values = np.column_stack([np.sin(2 * np.pi * t), np.cos(4 * np.pi * t)])
        values[-1] = values[0]
        np.testing.assert_allclose(retimed_frames(values, t, t), values, atol=1e-12)

    def test_frame_shows_the_source_time_modulo_the_period(self):
        t = np.arange(61.0)
        values = np.sin(2 * np.pi * t / 60.0)
        values[-1] = values[0]
        ts = retime(t, {0: 0.0, 15: 20.0})
        out = retimed_frames(values, t, ts)
        assert out.shape == (61,)
        assert out[15] == pytest.approx(np.sin(2 * np.pi * 20.0 / 60.0), abs=1e-4)
        # times past the period wrap
        late = retimed_frames(values, t, np.array([75.0, -45.0]))
        np.testing.assert_allclose(late, np.sin(2 * np.pi * 15.0 / 60.0), atol=1e-5)

    def test_quaternion_columns_are_renormalised(self):
        t = np.linspace(0.0, 1.0, 25)
        q = _wxyz(Rotation.from_rotvec(np.outer(np.sin(2 * np.pi * t), [0.0, 0.0, 1.5])))
        q[-1] = q[0]
        values = np.column_stack([t * 0 + 1.0, q])
        out = retimed_frames(values, t, t + 0.013, quaternions=[(1, 2, 3, 4)])
        np.testing.assert_allclose(np.linalg.norm(out[:, 1:], axis=1), 1.0, atol=1e-12)

    @pytest.mark.parametrize(
        ("values", "t", "t_star", "kwargs"),
        [
            (np.arange(5.0), np.arange(5.0), np.arange(5.0), {}),  # not closed
            (np.zeros(5), np.arange(6.0), np.arange(5.0), {}),
            (np.zeros(5), np.array([0.0, 1, 1, 2, 3]), np.arange(5.0), {}),  # repeated time
            (np.zeros(5), np.arange(5.0), np.array([0.0, np.nan]), {}),
            (np.zeros((5, 2)), np.arange(5.0), np.arange(5.0), {"quaternions": [(0, 1, 2, 3)]}),
        ],
    )
    def test_bad_arguments(self, values, t, t_star, kwargs):
        with pytest.raises(ValueError):
            retimed_frames(values, t, t_star, **kwargs)


# ------------------------------------------------------------------------------------------------
# 2.3 Contacts
# ------------------------------------------------------------------------------------------------


class TestProjectToPlane:
    def test_spec_17_below_is_projected_exactly_and_above_is_untouched(self):
        rng = np.random.default_rng(5)
        P = rng.normal(size=(200, 3))
        out, mask = project_to_plane(P)
        np.testing.assert_array_equal(mask, P[:, 1] <= 0)
        assert np.all(out[mask, 1] == 0.0)
        np.testing.assert_array_equal(out[mask][:, [0, 2]], P[mask][:, [0, 2]])
        np.testing.assert_array_equal(out[~mask], P[~mask])
        assert not np.shares_memory(out, P)

    def test_eps_and_offset_plane(self):
        P = np.array([[0.0, 1.05, 0.0], [1.0, 1.2, 2.0], [2.0, 0.5, 0.0]])
        out, mask = project_to_plane(P, point=(0.0, 1.0, 0.0), eps=0.1)
        np.testing.assert_array_equal(mask, [True, False, True])
        np.testing.assert_allclose(out[[0, 2], 1], 1.0, atol=0)
        np.testing.assert_array_equal(out[1], P[1])

    def test_tilted_plane(self):
        rng = np.random.default_rng(6)
        P = rng.normal(size=(100, 3))
        n = np.array([1.0, 2.0, 2.0])  # not unit: normalised inside
        p0 = np.array([0.1, -0.2, 0.3])
        out, mask = project_to_plane(P, p0, n)
        unit = n / 3.0
        dist = (P - p0) @ unit
        np.testing.assert_array_equal(mask, dist <= 0)
        np.testing.assert_allclose((out[mask] - p0) @ unit, 0.0, atol=1e-14)
        moved = out[mask] - P[mask]
        np.testing.assert_allclose(np.cross(moved, unit), 0.0, atol=1e-14)

    @pytest.mark.parametrize(
        ("P", "kwargs"),
        [
            (np.zeros((4, 2)), {}),
            (np.zeros(3), {}),
            (np.zeros((4, 3)), {"normal": (0.0, 0.0, 0.0)}),
            (np.zeros((4, 3)), {"normal": (0.0, 1.0)}),
            (np.zeros((4, 3)), {"point": (0.0, np.nan, 0.0)}),
            (np.zeros((4, 3)), {"eps": math.nan}),
            (np.full((4, 3), np.inf), {}),
        ],
    )
    def test_bad_arguments(self, P, kwargs):
        with pytest.raises(ValueError):
            project_to_plane(P, **kwargs)


class TestContactIntervals:
    def test_runs(self):
        mask = np.array([0, 1, 1, 0, 0, 1, 0, 1, 1, 1, 0], dtype=bool)
        assert contact_intervals(mask) == [(1, 3), (5, 6), (7, 10)]

    def test_runs_touching_both_ends_merge_across_the_seam(self):
        mask = np.array([1, 1, 0, 0, 1, 0, 0, 1, 1, 1], dtype=bool)
        assert contact_intervals(mask) == [(4, 5), (7, 12)]
        (start, stop) = contact_intervals(mask)[1]
        assert list(np.arange(start, stop) % mask.size) == [7, 8, 9, 0, 1]

    def test_run_touching_one_end_only(self):
        assert contact_intervals(np.array([1, 1, 0, 0, 0], dtype=bool)) == [(0, 2)]
        assert contact_intervals(np.array([0, 0, 0, 1, 1], dtype=bool)) == [(3, 5)]

    def test_all_and_nothing(self):
        assert contact_intervals(np.ones(7, dtype=bool)) == [(0, 7)]
        assert contact_intervals(np.zeros(7, dtype=bool)) == []
        assert contact_intervals(np.zeros(0, dtype=bool)) == []

    def test_bad_arguments(self):
        with pytest.raises(ValueError):
            contact_intervals(np.ones((3, 3), dtype=bool))


def _foot(times, period, stance_start, stance_len, v_rel, x_mid, lift=0.12, dip=0.002):
    """Root-relative forward position and world height of one foot of a synthetic walk.

    Stance lasts ``stance_len`` of the cycle from phase ``stance_start``; the foot moves backwards
    relative to the root at ``v_rel`` (negative) and dips up to ``dip`` below the ground (which the
    projection must remove); the swing brings it forward smoothly and lifts it by ``lift``.
    """
    phase = np.mod(times / period - stance_start, 1.0)
    stance = phase < stance_len
    duration = stance_len * period
    x = np.empty_like(times)
    y = np.empty_like(times)
    s = phase[stance] * period
    x[stance] = x_mid - v_rel * duration / 2 + v_rel * s
    y[stance] = -dip * np.sin(np.pi * s / duration)
    u = (phase[~stance] - stance_len) / (1 - stance_len)
    a, b = x_mid + v_rel * duration / 2, x_mid - v_rel * duration / 2
    x[~stance] = a + (b - a) * (u - np.sin(2 * np.pi * u) / (2 * np.pi))
    y[~stance] = lift * np.sin(np.pi * u) ** 2
    return x, y


def _walk(m=120, period=1.2):
    times = np.arange(m + 1) * period / m
    root = np.column_stack(
        [
            1.25 * times,
            0.9 + 0.02 * np.cos(4 * np.pi * times / period),
            0.01 * np.sin(2 * np.pi * times / period),
        ]
    )
    # different root-relative stance velocities: the feet slide at different speeds
    lx, ly = _foot(times, period, 0.8, 0.6, -1.1, 0.05)  # left stance crosses the loop seam
    rx, ry = _foot(times, period, 0.3, 0.6, -1.4, -0.02)
    items = {
        "left": np.column_stack([lx, ly - root[:, 1], np.full(m + 1, 0.1)]),
        "right": np.column_stack([rx, ry - root[:, 1], np.full(m + 1, -0.1)]),
        "hand": np.column_stack([0.2 * np.sin(2 * np.pi * times / period), np.full(m + 1, 0.3), np.full(m + 1, 0.25)]),
    }
    items["hand"][-1] = items["hand"][0]
    return root, items


def _contact_speeds(world, intervals, m, dt):
    """World speeds between consecutive contact frames of each interval (unwrapped across the seam)."""
    speeds = []
    for start, stop in intervals:
        for j in range(start, stop - 1):
            a, b = (j, j + 1) if j + 1 <= m else (j - m, j + 1 - m)
            speeds.append(np.linalg.norm(world[b] - world[a]) / dt)
    return np.array(speeds)


class TestFixSliding:
    def test_spec_17_two_feet_stop_sliding_and_the_root_travels(self):
        m, period = 120, 1.2
        root, items = _walk(m, period)
        dt = period / m
        res = fix_sliding(items, root, period)
        assert isinstance(res, ContactResult)
        # a stance on each foot; the left one crosses the seam
        assert len(res.intervals["left"]) == 1 and len(res.intervals["right"]) == 1
        assert res.intervals["left"][0][1] > m  # stop past the last frame
        assert res.intervals["right"][0][1] <= m
        assert res.intervals["hand"] == []
        # before: both feet slide in the world
        for name in ("left", "right"):
            before = _contact_speeds(root + items[name], res.intervals[name], m, dt)
            assert before.max() > 0.05
        # after: every contact frame is still in the world
        for name in ("left", "right"):
            after = _contact_speeds(res.root + res.items[name], res.intervals[name], m, dt)
            assert after.size > 60
            assert after.max() < 1e-6
        # root displacement per cycle = -integral of lambda (periodic trapezoid over the frames)
        integral = res.lam[:m].sum(axis=0) * dt
        np.testing.assert_allclose(res.root[m] - res.root[0], -integral, atol=1e-3 * np.abs(integral).max())
        np.testing.assert_allclose(res.root[m] - res.root[0], res.displacement, atol=1e-12)
        # it walks forward by about the stance speed times the period
        assert 1.1 * period < res.displacement[0] < 1.4 * period
        np.testing.assert_allclose(res.displacement[1:], 0.0, atol=1e-12)

    def test_lambda_is_the_mean_contact_velocity(self):
        m, period = 120, 1.2
        root, items = _walk(m, period)
        res = fix_sliding(items, root, period)
        frames = np.arange(m)
        only_left = frames[(frames < 20) | (frames > 110)]  # left stance, right in swing
        only_right = frames[(frames > 50) & (frames < 90)]
        np.testing.assert_allclose(res.lam[only_left, 0], -1.1, atol=1e-9)
        np.testing.assert_allclose(res.lam[only_right, 0], -1.4, atol=1e-9)
        both = frames[(frames > 38) & (frames < 44)]  # double support
        np.testing.assert_allclose(res.lam[both, 0], -1.25, atol=1e-9)
        np.testing.assert_allclose(res.lam[:, 1:], 0.0, atol=1e-12)  # in the plane
        np.testing.assert_array_equal(res.lam[m], res.lam[0])

    def test_curves_stay_closed_continuous_and_on_the_ground(self):
        m, period = 120, 1.2
        root, items = _walk(m, period)
        res = fix_sliding(items, root, period)
        for name in ("left", "right"):
            out = res.items[name]
            np.testing.assert_array_equal(out[m], out[0])
            step_before = np.linalg.norm(np.diff(items[name], axis=0), axis=1).max()
            step_after = np.linalg.norm(np.diff(out, axis=0), axis=1).max()
            assert step_after < 1.5 * step_before  # no jump at the joins
            world = res.root + out
            for start, stop in res.intervals[name]:
                idx = np.arange(start, stop) % m
                np.testing.assert_allclose(world[idx, 1], 0.0, atol=1e-12)
            assert len(res.scales[name]) == 1
            assert 0.5 < res.scales[name][0] < 1.5
        # left slid slower than lambda on average (scaled up), right faster (scaled down)
        assert res.scales["left"][0] > 1.0 > res.scales["right"][0]
        # the hand never touches: its root-relative curve is unchanged; the root height is kept
        np.testing.assert_array_equal(res.items["hand"], items["hand"])
        np.testing.assert_allclose(res.root[:, 1], root[:, 1], atol=1e-15)

    def test_no_contact_changes_nothing(self):
        m, period = 60, 1.0
        root, items = _walk(m, period)
        lifted = {k: v + np.array([0.0, 2.0, 0.0]) for k, v in items.items()}
        res = fix_sliding(lifted, root, period)
        assert all(v == [] for v in res.intervals.values())
        np.testing.assert_array_equal(res.root, root)
        for k, curve in lifted.items():
            np.testing.assert_array_equal(res.items[k], curve)
        assert np.all(res.lam == 0)

    def test_explicit_contact_masks(self):
        m, period = 120, 1.2
        root, items = _walk(m, period)
        masks = {"left": (root + items["left"])[:m, 1] <= 0}
        auto = fix_sliding(items, root, period)
        given = fix_sliding(items, root, period, contacts=masks)
        assert given.intervals == auto.intervals
        np.testing.assert_allclose(given.root, auto.root, atol=1e-12)
        # a mask that marks a swing frame as contact pins that frame too
        masks2 = {"hand": np.r_[np.ones(10, bool), np.zeros(m - 10, bool)]}
        res = fix_sliding(items, root, period, contacts=masks2)
        assert res.intervals["hand"] == [(0, 10)]
        speeds = _contact_speeds(res.root + res.items["hand"], [(0, 10)], m, period / m)
        assert speeds.max() < 1e-6

    def test_item_with_two_contacts_per_cycle(self):
        m, period = 120, 1.2
        dt = period / m
        root, items = _walk(m, period)
        mask = np.zeros(m + 1, dtype=bool)  # closed form (m + 1 flags) is accepted too
        mask[10:20] = True
        mask[60:75] = True
        res = fix_sliding(items, root, period, contacts={"hand": mask})
        assert res.intervals["hand"] == [(10, 20), (60, 75)]
        assert len(res.scales["hand"]) == 2
        out = res.items["hand"]
        speeds = _contact_speeds(res.root + out, res.intervals["hand"], m, dt)
        assert speeds.size == 9 + 14
        assert speeds.max() < 1e-6
        np.testing.assert_array_equal(out[m], out[0])
        # both flights end where the rebuilt contacts begin: no in-plane jump anywhere (the height jumps
        # because the hand, 1.2 m up, is projected onto the ground where it is marked in contact)
        plane = [0, 2]
        bound = max(np.abs(np.diff(items["hand"][:, plane], axis=0)).max(), np.abs(res.lam).max() * dt)
        assert np.abs(np.diff(out[:, plane], axis=0)).max() < 1.5 * bound
        np.testing.assert_allclose((res.root + out)[mask, 1], 0.0, atol=1e-12)

    def test_smoothing_still_stops_sliding(self):
        m, period = 120, 1.2
        root, items = _walk(m, period)
        res = fix_sliding(items, root, period, smoothing=0.05)
        for name in ("left", "right"):
            speeds = _contact_speeds(res.root + res.items[name], res.intervals[name], m, period / m)
            assert speeds.max() < 1e-6
        integral = res.lam[:m].sum(axis=0) * period / m
        np.testing.assert_allclose(res.displacement, -integral, atol=2e-3)

    def test_inputs_are_not_modified(self):
        root, items = _walk(60, 1.0)
        copies = {k: v.copy() for k, v in items.items()}
        root_copy = root.copy()
        fix_sliding(items, root, 1.0)
        np.testing.assert_array_equal(root, root_copy)
        for k in items:
            np.testing.assert_array_equal(items[k], copies[k])

    def test_bad_arguments(self):
        root, items = _walk(60, 1.0)
        with pytest.raises(ValueError):
            fix_sliding({}, root, 1.0)
        with pytest.raises(ValueError):
            fix_sliding(items, root[:-1], 1.0)
        with pytest.raises(ValueError):
            fix_sliding(items, root[:, :2], 1.0)
        with pytest.raises(ValueError):
            fix_sliding(items, root, 0.0)
        with pytest.raises(ValueError):
            fix_sliding(items, root, 1.0, normal=(0.0, 0.0, 0.0))
        with pytest.raises(ValueError):
            fix_sliding(items, root, 1.0, smoothing=-1.0)
        with pytest.raises(ValueError):
            fix_sliding(items, root, 1.0, eps=math.nan)
        open_curve = dict(items, left=items["left"] + np.linspace(0, 1, 61)[:, None])
        with pytest.raises(ValueError, match="differs from the first"):
            fix_sliding(open_curve, root, 1.0)
        with pytest.raises(ValueError):
            fix_sliding(dict(items, left=np.full((61, 3), np.nan)), root, 1.0)
        with pytest.raises(ValueError):
            fix_sliding(items, root, 1.0, contacts={"tail": np.ones(60, bool)})
        with pytest.raises(ValueError):
            fix_sliding(items, root, 1.0, contacts={"left": np.ones(59, bool)})
        with pytest.raises(ValueError):
            fix_sliding(items, root, 1.0, contacts={"left": np.ones(60)})


# ------------------------------------------------------------------------------------------------
# Real data: one stride of the gaitmap optical-marker walk
# ------------------------------------------------------------------------------------------------


def _gaitmap() -> tuple[np.ndarray, list[dict[str, str]]]:
    markers = GAITMAP / "mocap_sample.csv"
    events = GAITMAP / "stride_events_sample.csv"
    for path in (markers, events):
        if not path.is_file():
            pytest.skip(f"gaitmap trace not found at {path} (../shared/traces must sit beside the project)")
    raw = np.genfromtxt(markers, delimiter=",", skip_header=2)
    xyz = raw[:, 1:].reshape(len(raw), 6, 3) / 1000.0  # mm -> m; markers L_TOE R_TOE L_FCC R_FCC R_FM5 L_FM5
    with events.open(newline="") as f:
        rows = list(csv.DictReader(f))
    return xyz, rows


def _real_stride():
    """The 4th annotated left stride as a closed cycle: root-relative foot markers, a straight root.

    The root moves at the stride's mean marker velocity; each marker's root-relative curve is closed by
    the thesis's linear stitching (eq. 5.5). Stance masks come from the annotated toe-off / initial
    contact events of each foot.
    """
    xyz, rows = _gaitmap()
    left = [r for r in rows if r["foot"] == "left"]
    start, end = (round(float(left[3][k]) * MOCAP_HZ / IMU_HZ) for k in ("start", "end"))
    seg = xyz[start : end + 1]
    m = end - start
    period = m / MOCAP_HZ
    times = np.arange(m + 1) / MOCAP_HZ
    centre = seg.mean(axis=1)
    velocity = (centre[-1] - centre[0]) / period
    root = centre[0] + np.outer(times, velocity)
    root[:, 2] = 0.9
    frames = np.arange(start, end) * IMU_HZ / MOCAP_HZ  # in event units

    def stance(foot: str) -> np.ndarray:
        ok = np.ones(m, dtype=bool)
        for r in rows:
            if r["foot"] == foot:
                ok &= ~((frames > float(r["tc"])) & (frames < float(r["ic"])))
        return ok

    items, masks = {}, {}
    for name, col, foot in (("L_FM5", 5, "left"), ("R_FM5", 4, "right"), ("L_TOE", 0, "left"), ("R_TOE", 1, "right")):
        rel = seg[:, col] - root
        rel = rel + np.outer(times / period - 0.5, rel[0] - rel[-1])
        items[name] = rel
        masks[name] = stance(foot)
    return items, root, period, masks, velocity * period


class TestRealStride:
    def test_markers_stop_sliding_and_the_root_covers_the_stride(self):
        items, root, period, masks, stride = _real_stride()
        m = root.shape[0] - 1
        dt = period / m
        heights = np.concatenate([(root + items[k])[:m][masks[k], 2] for k in items])
        ground = float(np.median(heights))
        res = fix_sliding(items, root, period, point=(0.0, 0.0, ground), normal=(0.0, 0.0, 1.0), contacts=masks)
        for name in items:
            assert res.intervals[name], f"{name} has no stance"
            before = _contact_speeds(root + items[name], res.intervals[name], m, dt)
            after = _contact_speeds(res.root + res.items[name], res.intervals[name], m, dt)
            assert np.mean(before) > 0.1  # the annotated stances slide against a straight root
            assert after.max() < 1e-6
            np.testing.assert_array_equal(res.items[name][m], res.items[name][0])
        integral = res.lam[:m].sum(axis=0) * dt
        np.testing.assert_allclose(res.displacement, -integral, atol=2e-3 * np.linalg.norm(integral))
        # travel: the stride's direction, and its length to within 15% (stance markers roll and
        # slide a little in the real world, which the shared velocity averages in)
        travel = res.displacement[:2]
        cos = travel @ stride[:2] / (np.linalg.norm(travel) * np.linalg.norm(stride[:2]))
        assert cos > 0.99
        assert 0.85 < np.linalg.norm(travel) / np.linalg.norm(stride[:2]) < 1.05

    def test_spatial_and_temporal_edits_on_a_real_stride(self):
        items, _, period, _, _ = _real_stride()
        curve = items["L_TOE"]
        m = curve.shape[0] - 1
        times = np.linspace(0.0, period, m + 1)
        lifted = edit_translation(curve, m - 1, np.array([0.0, 0.0, 0.05]), 6, closed=True)
        np.testing.assert_array_equal(lifted[m], lifted[0])
        assert lifted[m - 1, 2] - curve[m - 1, 2] == pytest.approx(0.05)
        assert lifted[0, 2] - curve[0, 2] == pytest.approx(0.05 * 100 ** (-1 / 36))
        # hold the swing's apex longer: the frame at 40% of the stride shows the 30% time
        k = round(0.4 * m)
        ts = retime(times, {0: 0.0, k: times[round(0.3 * m)]})
        assert ts[k] == pytest.approx(times[round(0.3 * m)], abs=1e-3 * period)
        assert np.all(np.diff(ts) >= 0)
        out = retimed_frames(curve, times, ts)
        assert out.shape == curve.shape
        np.testing.assert_allclose(out[k], curve[round(0.3 * m)], atol=2e-3)
        np.testing.assert_allclose(out[m], out[0], atol=1e-3)
