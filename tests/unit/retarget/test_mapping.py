"""Mappings from phone input to blend parameters (Ciccone 2019, section 6.2.3, eq. 6.1-6.2; docs/design/puppet.md):
the linear axis map, IDW exact hits and equidistant probes, the probe table's round trip and the out-of-range
speed-up."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import Delaunay

from retarget.mapping import AxisMap, OneEuroFilter, ProbeTable, PuppetMapping, idw

# Mock clips at the blend-space points of Fig. 6.3 (p_vel, p_height), with made-up speeds and durations.
CLIP_POINTS = np.array([[0.0, 1.0], [0.5, 1.0], [1.0, 1.0], [0.0, 0.0], [1.0, 0.0]])  # idle walk run cidle cwalk
CLIP_SPEEDS = np.array([0.0, 1.4, 3.5, 0.0, 0.8])
CLIP_DURATIONS = np.array([2.0, 1.0, 0.7, 2.0, 1.2])


class MockBlender:
    """Barycentric weights on the Delaunay triangulation of the clip points; speed = sum w stride / sum w dur."""

    def __init__(self) -> None:
        self.tri = Delaunay(CLIP_POINTS)
        self.strides = CLIP_SPEEDS * CLIP_DURATIONS

    def weights(self, p_vel: float, p_height: float) -> np.ndarray:
        p = np.array([p_vel, p_height])
        simplex = int(self.tri.find_simplex(p, tol=1e-9))
        assert simplex >= 0, p
        tr = self.tri.transform[simplex]
        b = tr[:2] @ (p - tr[2])
        w = np.zeros(len(CLIP_POINTS))
        w[self.tri.simplices[simplex]] = np.r_[b, 1.0 - b.sum()]
        return w

    def speed(self, p_vel: float, p_height: float) -> float:
        w = self.weights(p_vel, p_height)
        return float(w @ self.strides / (w @ CLIP_DURATIONS))


@pytest.fixture(scope="module")
def blender() -> MockBlender:
    return MockBlender()


@pytest.fixture(scope="module")
def table(blender: MockBlender) -> ProbeTable:
    return ProbeTable.measure(blender.speed, n=21, q=7.0)


def test_linear_axis_map():
    m = AxisMap(0.3, 1.2)
    for u, p in [(0.3, 0.0), (0.75, 0.5), (1.2, 1.0), (2.0, 1.0), (0.0, 0.0)]:
        assert m(u) == pytest.approx(p, abs=1e-12)
    np.testing.assert_allclose(m.map_array([0.3, 0.75, 1.2, 2.0, 0.0]), [0, 0.5, 1, 1, 0], atol=1e-12)
    assert AxisMap(1.0, 0.0)(0.25) == pytest.approx(0.75)  # a decreasing map is allowed
    with pytest.raises(ValueError, match="a != b"):
        AxisMap(1.0, 1.0)
    with pytest.raises(ValueError, match="NaN"):
        m(math.nan)


def test_exact_probe_hit_returns_the_probe(table: ProbeTable):
    checked = 0
    for k in range(len(table.probes_p)):
        i, j = divmod(k, 21)
        p = table.lookup(table.speeds[i, j], table.probes_p[k, 1])
        if np.count_nonzero(np.all(np.abs(table.probes_u - table.probes_u[k]) < 1e-12, axis=1)) == 1:
            np.testing.assert_array_equal(p, table.probes_p[k])
            checked += 1
    assert checked >= 400  # nearly every probe has its own u*


def test_generic_idw_exact_hit_and_equidistant_mean():
    probes_u = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    probes_p = np.array([[0.1, 0.9], [0.7, 0.2], [0.4, 0.4], [1.0, 0.0]])
    np.testing.assert_array_equal(idw(probes_u[2], probes_u, probes_p), probes_p[2])
    np.testing.assert_allclose(idw([0.5, 0.5], probes_u, probes_p), probes_p.mean(axis=0), atol=1e-15)
    # Equidistant on a circle of radius 1e-3 (q = 7 would overflow in linear space at tiny d, not here).
    ang = np.linspace(0, 2 * np.pi, 7, endpoint=False)
    ring = np.column_stack([np.cos(ang), np.sin(ang)]) * 1e-3
    vals = np.arange(14.0).reshape(7, 2)
    np.testing.assert_allclose(idw([0.0, 0.0], ring, vals), vals.mean(axis=0), rtol=1e-12)
    # Two probes sharing the hit u*: their mean.
    np.testing.assert_allclose(idw([1.0, 1.0], np.vstack([probes_u, [1.0, 1.0]]),
                                   np.vstack([probes_p, [0.0, 1.0]])), [0.5, 0.5])
    # Far queries do not underflow to 0/0: d^-7 = 1e-350 is 0 in floating point, not in log space.
    out = idw([1e50, 0.0], probes_u, probes_p, q=7)
    np.testing.assert_allclose(out, probes_p.mean(axis=0), atol=1e-12)
    # Batches equal single calls.
    qs = np.array([[0.2, 0.3], [0.9, 0.1]])
    np.testing.assert_allclose(idw(qs, probes_u, probes_p), [idw(x, probes_u, probes_p) for x in qs])
    with pytest.raises(ValueError, match="q must"):
        idw([0, 0], probes_u, probes_p, q=0)
    with pytest.raises(ValueError, match="dimension"):
        idw([0, 0, 0], probes_u, probes_p)


def test_round_trip_speed_error_with_the_mock_clips(blender: MockBlender, table: ProbeTable):
    grid = np.linspace(0.0, 1.0, 61)
    errors = []
    for pv in grid:
        for ph in grid:
            target = blender.speed(pv, ph)
            q = table.query(target, ph)
            assert not q.projected and q.speedup == 1.0
            errors.append(abs(blender.speed(q.p_vel, q.p_height) - target))
    rng = np.random.default_rng(1)
    for pv, ph in rng.random((500, 2)):
        target = blender.speed(pv, ph)
        q = table.query(target, ph)
        errors.append(abs(blender.speed(q.p_vel, q.p_height) - target))
    errors = np.array(errors)
    med, worst = float(np.median(errors)), float(errors.max())
    print(f"round-trip speed error: median {med:.4f} m/s, max {worst:.4f} m/s over {errors.size} queries")
    assert med < 0.02
    assert worst < 0.1


def test_border_is_curved(table: ProbeTable):
    """The p_vel = 1 border is not a straight line in u-space (thesis Fig. 6.4)."""
    b = table.border
    straight = b[0, 0] + (b[-1, 0] - b[0, 0]) * b[:, 1]
    assert np.max(np.abs(b[:, 0] - straight)) > 0.05


def test_out_of_range_projects_and_speeds_up(table: ProbeTable):
    assert table.v_max == pytest.approx(3.5)
    q = table.query(5.0, 1.0)
    assert q.projected
    assert q.p_vel == 1.0 and q.p_height == pytest.approx(1.0)
    assert q.speedup == pytest.approx(5.0 / 3.5, abs=1e-12)
    assert round(q.speedup, 4) == 1.4286
    inside = table.query(2.0, 1.0)
    assert not inside.projected and inside.speedup == 1.0
    on_border = table.query(3.5, 1.0)
    assert on_border.speedup == 1.0 and on_border.p_vel == 1.0
    # Crouched and too fast: projected onto the curved border, factor >= 1, p_vel = 1.
    for h in np.linspace(0, 1, 11):
        speed = table.border_speed(h) * 1.3 + 0.05
        r = table.query(speed, h)
        assert r.projected and r.p_vel == 1.0 and r.speedup >= 1.0
        assert r.speedup == pytest.approx(speed / (table.border_speed(r.p_height)), rel=1e-9)
    # Height outside [0, 1] is clamped first.
    assert table.query(0.5, 1.7).height == 1.0


def test_probe_table_rejects_bad_grids():
    with pytest.raises(ValueError, match="grid"):
        ProbeTable(np.ones(5))
    with pytest.raises(ValueError, match=">= 0"):
        ProbeTable(-np.ones((3, 3)))
    with pytest.raises(ValueError, match="must move"):
        ProbeTable(np.zeros((3, 3)))
    table = ProbeTable(np.array([[0.0, 0.0], [1.0, 2.0]]))
    with pytest.raises(ValueError, match="speed"):
        table.query(-1.0, 0.5)


def test_one_euro_filter_smooths_noise_and_follows_steps():
    rng = np.random.default_rng(3)
    f = OneEuroFilter(min_cutoff=1.0, beta=0.5)
    t = np.arange(0, 4, 1 / 60)
    raw = np.where(t < 2, 1.0, 3.0) + rng.normal(0, 0.05, t.size)
    out = np.array([f(ti, xi) for ti, xi in zip(t, raw, strict=True)])
    still = (t > 1.0) & (t < 2.0)
    assert np.std(out[still]) < 0.4 * np.std(raw[still])
    assert abs(out[-1] - 3.0) < 0.05  # it reached the new level
    assert f(t[-1], 100.0) == out[-1]  # dt = 0: the last output
    with pytest.raises(ValueError, match="backwards"):
        f(0.0, 1.0)
    f.reset()
    assert f(10.0, 7.0) == 7.0


def test_puppet_mapping_bundle(table: ProbeTable):
    mapping = PuppetMapping(table, AxisMap(0.3, 1.2))
    raw = mapping.map(1.4, 1.2)  # walking speed at full height -> about the walk clip
    assert raw.p_height == pytest.approx(1.0, abs=0.02)
    assert raw.p_vel == pytest.approx(0.5, abs=0.05)
    crouched = mapping.map(0.0, 0.3)
    assert crouched.p_height == pytest.approx(0.0, abs=0.02) and crouched.p_vel == pytest.approx(0.0, abs=0.02)
    # Smoothed updates converge to the raw mapping of a steady input.
    out = None
    for k in range(240):
        out = mapping.update(k / 60, 1.4, 1.2)
    assert out is not None and out.p_vel == pytest.approx(raw.p_vel, abs=1e-6)
    fast = PuppetMapping(table, AxisMap(0.3, 1.2), smoothing=False).update(0.0, 7.0, 1.2)
    assert fast.speedup == pytest.approx(2.0)


def test_lookup_plays_the_requested_speed_anywhere_in_the_input_range(blender: MockBlender, table: ProbeTable):
    """Inside the feasible set the blend itself has the speed; beyond its border the border's clip,
    sped up, has it: parameters stay in the blend space and only a projection speeds up."""
    rng = np.random.default_rng(5)
    errors = []
    projected = 0
    for s, h in rng.random((2000, 2)) * (3.5, 1.0):
        q = table.query(float(s), float(h))
        assert 0.0 <= q.p_vel <= 1.0 and 0.0 <= q.p_height <= 1.0
        assert q.speedup >= 1.0 and (q.speedup == 1.0 or q.projected)
        projected += q.projected
        errors.append(abs(blender.speed(q.p_vel, q.p_height) * q.speedup - s))
    assert 0 < projected < 2000  # crouched, the border is slower than 3.5 m/s
    assert float(np.median(errors)) < 0.02 and max(errors) < 0.1
