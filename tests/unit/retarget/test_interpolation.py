"""The radial basis interpolant and its multiresolution form (Rose 1999, sections 4.3 and 4.6): the
kernel, the worked 1-D example of docs/design/verbs-and-adverbs.md, the kernel matrix's orientation with
unequal radii, many channels at once, and near-duplicate examples."""

from __future__ import annotations

import numpy as np
import pytest

from retarget.interpolation import RBF, MultiResolutionRBF, bspline_kernel


def test_kernel_values() -> None:
    assert bspline_kernel(0.0) == pytest.approx(2 / 3)
    assert bspline_kernel(1.0) == pytest.approx(1 / 6)
    assert bspline_kernel(-1.0) == pytest.approx(1 / 6)
    assert bspline_kernel(2.0) == 0.0
    assert bspline_kernel(3.0) == 0.0
    x = np.linspace(0.0, 2.5, 2001)
    assert np.max(np.abs(np.diff(bspline_kernel(x)))) < 1e-3  # continuous
    np.testing.assert_allclose(bspline_kernel(0.5), (4 - 6 * 0.25 + 3 * 0.125) / 6)
    np.testing.assert_allclose(bspline_kernel(1.5), 0.5**3 / 6)


def test_rbf_1d_worked_example() -> None:
    f = RBF([-10.0, 0.0, 10.0], [-1.0, 2.0, 1.0])
    np.testing.assert_allclose(f.linear[:, 0], [2 / 3, 0.1], atol=1e-12)
    np.testing.assert_allclose(f.residuals[:, 0], [-2 / 3, 4 / 3, -2 / 3], atol=1e-12)
    np.testing.assert_allclose(f.alphas, [10.0, 10.0, 10.0])
    expected = [[2 / 3, 1 / 6, 0], [1 / 6, 2 / 3, 1 / 6], [0, 1 / 6, 2 / 3]]
    np.testing.assert_allclose(f.kernel_matrix, expected, atol=1e-12)
    np.testing.assert_allclose(f.radial[:, 0], [-12 / 7, 20 / 7, -12 / 7], atol=1e-12)
    np.testing.assert_allclose(f(np.array([-10.0, 0.0, 10.0])), [-1.0, 2.0, 1.0], atol=1e-12)
    assert f(5.0) == pytest.approx(1.678571, abs=1e-6)
    assert f(40.0) == pytest.approx(4.666667, abs=1e-6)  # linear part only
    assert f(40.0) == pytest.approx(2 / 3 + 0.1 * 40, abs=1e-12)


def test_kernel_matrix_orientation_with_unequal_radii() -> None:
    p = np.array([0.0, 1.0, 5.0])
    f = RBF(p, [0.0, 1.0, -1.0])
    np.testing.assert_allclose(f.alphas, [1.0, 1.0, 4.0])
    for i2 in range(3):
        for i1 in range(3):
            assert f.kernel_matrix[i2, i1] == pytest.approx(bspline_kernel(abs(p[i2] - p[i1]) / f.alphas[i1]))
    assert not np.allclose(f.kernel_matrix, f.kernel_matrix.T)
    np.testing.assert_allclose(f(p), [0.0, 1.0, -1.0], atol=1e-12)


def test_rbf_2d_many_channels() -> None:
    rng = np.random.default_rng(7)
    pts = rng.uniform(0.0, 1.0, (7, 2))
    vals = rng.normal(size=(7, 5))
    f = RBF(pts, vals)
    np.testing.assert_allclose(f(pts), vals, atol=1e-10)
    np.testing.assert_allclose(f.basis(pts[2]) @ f.coefficients, vals[2], atol=1e-10)
    # linear data is reproduced by the linear part alone, also far outside the hull
    lin = 1.0 + pts @ np.array([2.0, -3.0])
    g = RBF(pts, lin)
    np.testing.assert_allclose(g.radial, 0.0, atol=1e-12)
    assert g(np.array([5.0, 5.0])) == pytest.approx(1.0 + 10.0 - 15.0)


def test_rbf_rejects_bad_input() -> None:
    with pytest.raises(ValueError):
        RBF(np.array([[0.0, 0.0], [1.0, 1.0]]), [1.0, 2.0])  # fewer than D + 1
    with pytest.raises(ValueError):
        RBF([0.0, 0.0, 1.0], [1.0, 2.0, 3.0])  # coincident
    with pytest.raises(ValueError):
        RBF([0.0, 1.0], [1.0, 2.0, 3.0])
    f = RBF([0.0, 1.0, 2.0], [1.0, 2.0, 0.0])
    with pytest.raises(ValueError):
        RBF([[0, 0], [1, 0], [0, 1]], [1, 2, 3])(np.array([1.0, 2.0, 3.0]))
    assert f(1.0) == pytest.approx(2.0)


def test_mrbf_is_not_thrown_by_a_near_duplicate() -> None:
    pts, vals = [-10.0, 0.0, 1.0, 10.0], [-1.0, 2.0, 2.0, 1.0]
    m = MultiResolutionRBF(pts, vals, seed=0)
    groups = [sorted(sorted(pts[i] for i in c) for c in lev.members()) for lev in m.levels]
    assert groups[0] == [[-10.0], [0.0, 1.0], [10.0]]
    assert groups[-1] == [[-10.0], [0.0], [1.0], [10.0]]
    assert len(m.levels) == 2
    np.testing.assert_allclose(sorted(m.level_points[0][:, 0]), [-10.0, 0.5, 10.0])
    np.testing.assert_allclose(m(np.array(pts)), vals, atol=1e-12)
    assert m(5.0) == pytest.approx(1.6848, abs=1e-4)
    assert RBF([-10.0, 0.0, 10.0], [-1.0, 2.0, 1.0])(5.0) == pytest.approx(1.6786, abs=1e-4)
    assert m(-5.0) == pytest.approx(0.583, abs=1e-3)
    single = RBF(pts, vals)
    np.testing.assert_allclose(single(np.array(pts)), vals, atol=1e-12)
    assert single(5.0) == pytest.approx(0.789, abs=1e-3)
    assert single(-5.0) == pytest.approx(-0.226, abs=1e-3)


def test_mrbf_2d_interpolates_and_is_seeded() -> None:
    rng = np.random.default_rng(8)
    pts = rng.uniform(0.0, 1.0, (12, 2))
    vals = np.sin(3 * pts[:, :1]) + pts[:, 1:] ** 2
    a = MultiResolutionRBF(pts, vals, seed=3)
    b = MultiResolutionRBF(pts, vals, seed=3)
    np.testing.assert_allclose(a(pts), vals, atol=1e-10)
    np.testing.assert_array_equal(a.coefficients, b.coefficients)
    counts = [lev.count for lev in a.levels]
    assert counts[0] >= 3 and counts[-1] == 12 and all(np.diff(counts) > 0)
