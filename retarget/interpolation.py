"""Scattered-data interpolation over adverb space (Rose 1999, *Verbs and Adverbs*, Princeton PhD thesis,
chapter 4): the radial basis interpolant of section 4.3 and its multiresolution form of section 4.6.

This module owns the cubic B-spline radial function (``bspline_kernel``), ``RBF`` (eq. 4.2-4.5: a linear
part fitted by SVD least squares, then radial functions B(|p - p_i| / alpha_i), alpha_i the distance from
p_i to its nearest other example, whose weights interpolate the linear part's residuals; the system
D r = residuals is solved directly, its rows the examples and its columns the basis functions) and
``MultiResolutionRBF`` (eq. 4.8-4.10: the same from coarse clusters to single examples, each level fitting
what the coarser ones leave). The clusterings come from :mod:`retarget.clustering`. Where perfcap departs
from the thesis (the kernel matrix's index order, a direct solve instead of Gauss-Seidel, a cluster
standing for its members' means) is in ``docs/design/verbs-and-adverbs.md``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING

import numpy as np
from scipy import linalg

from retarget.clustering import Clustering, as_points, basic_clustering, improved_clustering

if TYPE_CHECKING:
    from collections.abc import Sequence

    from retarget._types import FloatArray

__all__ = ["RBF", "MultiResolutionRBF", "bspline_kernel"]


def bspline_kernel(x: FloatArray | float) -> FloatArray | float:
    """The cubic B-spline radial function, support radius 2.

    B(x) = (4 - 6x^2 + 3|x|^3) / 6 for |x| < 1, (2 - |x|)^3 / 6 for |x| < 2, 0 otherwise; B(0) = 2/3 and
    B(1) = 1/6.

    Args:
        x: scaled distance(s).

    Returns:
        B(x) with the shape of ``x``.
    """
    a = np.abs(np.asarray(x, dtype=float))
    out = (np.maximum(2.0 - a, 0.0) ** 3 - 4.0 * np.maximum(1.0 - a, 0.0) ** 3) / 6.0
    return float(out) if np.ndim(x) == 0 else out


def _as_query(p: FloatArray | Sequence[float] | float, dim: int) -> tuple[FloatArray, bool]:
    """Queries as (Q, D) and whether a single point was given."""
    a = np.asarray(p, dtype=float)
    if a.ndim == 0:
        if dim != 1:
            raise ValueError(f"a scalar adverb needs a 1-D adverb space, this one is {dim}-D")
        return a.reshape(1, 1), True
    if a.ndim == 1:
        if dim == 1 and a.size != 1:
            return a[:, None], False
        if a.size != dim:
            raise ValueError(f"adverb point must have {dim} entries, got {a.size}")
        return a[None, :], True
    if a.ndim == 2 and a.shape[1] == dim:
        return a, False
    raise ValueError(f"adverb points must be (Q, {dim}), got {a.shape}")


def _nearest_other(points: FloatArray) -> FloatArray:
    d = np.linalg.norm(points[:, None, :] - points[None, :, :], axis=-1)
    np.fill_diagonal(d, np.inf)
    alpha: FloatArray = d.min(axis=1)
    if np.any(alpha <= 0.0):
        raise ValueError("two interpolation points coincide; examples must be well separated")
    return alpha


def _kernel_matrix(points: FloatArray, alpha: FloatArray) -> FloatArray:
    """D[i2, i1] = B(|p_i2 - p_i1| / alpha_i1): row = example, column = basis function."""
    d = np.linalg.norm(points[:, None, :] - points[None, :, :], axis=-1)
    return np.asarray(bspline_kernel(d / alpha[None, :]))


class _Interpolant(ABC):
    """f(p) = basis(p) @ coefficients, with basis = [1, p_1..p_D, radial terms...]. Subclasses (``RBF``,
    ``MultiResolutionRBF``) provide the basis."""

    dim: int
    coefficients: FloatArray
    _scalar: bool

    @abstractmethod
    def basis(self, p: FloatArray | Sequence[float] | float) -> FloatArray:
        """The basis row(s) at p."""

    def __call__(self, p: FloatArray | Sequence[float] | float) -> FloatArray | float:
        """Evaluate at one point (returns (M,) or a float for scalar data) or at (Q, D) points.

        Args:
            p: adverb point(s).

        Returns:
            Interpolated values.

        Raises:
            ValueError: wrong dimension.
        """
        q, single = _as_query(p, self.dim)
        out = self._basis_q(q) @ self.coefficients
        if self._scalar:
            out = out[:, 0]
            return float(out[0]) if single else out
        return out[0] if single else out

    @abstractmethod
    def _basis_q(self, q: FloatArray) -> FloatArray:
        """The basis rows at the (Q, D) points q."""


def _linear_fit(points: FloatArray, values: FloatArray) -> FloatArray:
    """Least squares [1, p] a = v by SVD (gelsd)."""
    a_mat = np.hstack([np.ones((points.shape[0], 1)), points])
    coef, *_ = linalg.lstsq(a_mat, values, lapack_driver="gelsd")
    return np.asarray(coef)


class RBF(_Interpolant):
    """Radial basis interpolant over adverb space (eq 4.2-4.5).

    b(p) = sum_i r_i B(|p - p_i| / alpha_i) + a_0 + sum_l a_l p_l. The linear part is the least-squares
    hyperplane (SVD); the radial part interpolates its residuals exactly, with alpha_i the distance from
    p_i to its nearest other example and the system D r = residuals solved directly.

    Args:
        points: (n, D) example locations (or (n,) for D = 1).
        values: (n,) or (n, M) example values; each column is an independent problem.

    Attributes:
        dim: D.
        points: (n, D).
        linear: (D + 1, M) a_0, a_1..a_D.
        residuals: (n, M) values minus the linear part at the examples.
        alphas: (n,) radial scales.
        kernel_matrix: (n, n) D[i2, i1].
        radial: (n, M) r.
        coefficients: (D + 1 + n, M) stacked [linear; radial].

    Raises:
        ValueError: mismatched shapes, fewer than D + 1 examples, or coincident points.
    """

    def __init__(self, points: FloatArray | Sequence[float], values: FloatArray | Sequence[float]) -> None:
        pts = as_points(points)
        v = np.asarray(values, dtype=float)
        self._scalar = v.ndim == 1
        v = v.reshape(v.shape[0], -1) if v.ndim >= 1 else v
        if v.shape[0] != pts.shape[0]:
            raise ValueError(f"{pts.shape[0]} points but {v.shape[0]} values")
        n, d = pts.shape
        if n < d + 1:
            raise ValueError(f"need at least D + 1 = {d + 1} examples, got {n}")
        self.dim = d
        self.points = pts
        self.linear = _linear_fit(pts, v)
        self.residuals = v - np.hstack([np.ones((n, 1)), pts]) @ self.linear
        self.alphas = _nearest_other(pts)
        self.kernel_matrix = _kernel_matrix(pts, self.alphas)
        self.radial = np.asarray(linalg.solve(self.kernel_matrix, self.residuals))
        self.coefficients = np.vstack([self.linear, self.radial])

    def _basis_q(self, q: FloatArray) -> FloatArray:
        dist = np.linalg.norm(q[:, None, :] - self.points[None, :, :], axis=-1)
        return np.hstack([np.ones((q.shape[0], 1)), q, bspline_kernel(dist / self.alphas)])

    def basis_one(self, p: FloatArray) -> FloatArray:
        """``basis`` for one validated (D,) point, without the argument checks (the fast path)."""
        x = np.sqrt(((self.points - p) ** 2).sum(axis=1)) / self.alphas
        return np.concatenate(([1.0], p, (np.maximum(2.0 - x, 0.0) ** 3 - 4.0 * np.maximum(1.0 - x, 0.0) ** 3) / 6.0))

    def basis(self, p: FloatArray | Sequence[float] | float) -> FloatArray:
        """Basis row(s) [1, p, B(|p - p_i| / alpha_i)]: f(p) = basis(p) @ coefficients.

        Args:
            p: adverb point(s).

        Returns:
            (D + 1 + n,) or (Q, D + 1 + n).

        Raises:
            ValueError: wrong dimension.
        """
        q, single = _as_query(p, self.dim)
        b = self._basis_q(q)
        return b[0] if single else b


class MultiResolutionRBF(_Interpolant):
    """Multiresolution radial basis interpolant (eq 4.8-4.10).

    Level 0 is the coarse clustering of ``improved_clustering``; each further level roughly doubles the
    cluster count, and the finest level is every example on its own. A cluster stands for the mean of its
    members' positions and values. The linear part is fitted on the level-0 clusters; then, coarse to fine,
    each level's radial coefficients interpolate what the linear part and all coarser levels leave at that
    level's cluster centres (radius: distance to the nearest other centre of the level). The result
    interpolates every example and is not thrown by near-duplicate examples.

    Args:
        points: (n, D) or (n,).
        values: (n,) or (n, M).
        max_cost: coarse clustering cost target; None = 0.1 x the diagonal of the points' bounding box.
        max_clusters: cap for the coarse level; None = n - 1 (at least D + 1).
        seed: seed of the clustering RNG.
        restarts: clustering restarts.

    Attributes:
        levels: the ``Clustering`` of each level, coarse to fine.
        level_points: (k_c, D) centres per level.
        level_alphas: radial scales per level.
        level_radial: (k_c, M) coefficients per level.
        linear: (D + 1, M).
        coefficients: (D + 1 + sum k_c, M).

    Raises:
        ValueError: fewer than D + 1 examples, or coincident examples.
    """

    def __init__(
        self,
        points: FloatArray | Sequence[float],
        values: FloatArray | Sequence[float],
        *,
        max_cost: float | None = None,
        max_clusters: int | None = None,
        seed: int = 0,
        restarts: int = 32,
    ) -> None:
        pts = as_points(points)
        v = np.asarray(values, dtype=float)
        self._scalar = v.ndim == 1
        v = v.reshape(v.shape[0], -1)
        n, d = pts.shape
        if v.shape[0] != n:
            raise ValueError(f"{n} points but {v.shape[0]} values")
        if n < d + 1:
            raise ValueError(f"need at least D + 1 = {d + 1} examples, got {n}")
        _nearest_other(pts)  # rejects coincident examples
        self.dim = d
        self.points = pts
        rng = np.random.default_rng(seed)
        extent = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
        cost = 0.1 * extent if max_cost is None else float(max_cost)
        cap = max(d + 1, n - 1) if max_clusters is None else int(max_clusters)
        cap = min(cap, n)
        levels = [improved_clustering(pts, max_cost=cost, max_clusters=cap, rng=rng, restarts=restarts)]
        while levels[-1].count < n:
            k = min(2 * levels[-1].count, n)
            if k == n:
                levels.append(Clustering(labels=np.arange(n), centres=pts.copy(), cost=0.0))
            else:
                levels.append(basic_clustering(pts, k, rng=rng, restarts=restarts))
        self.levels = levels
        means = [np.stack([v[c.labels == j].mean(axis=0) for j in range(c.count)]) for c in levels]
        self.linear = _linear_fit(levels[0].centres, means[0])
        self.level_points: list[FloatArray] = []
        self.level_alphas: list[FloatArray] = []
        self.level_radial: list[FloatArray] = []
        for c, target in zip(levels, means, strict=True):
            centres = c.centres
            so_far = self._evaluate_partial(centres)
            alpha = _nearest_other(centres)
            r = np.asarray(linalg.solve(_kernel_matrix(centres, alpha), target - so_far))
            self.level_points.append(centres)
            self.level_alphas.append(alpha)
            self.level_radial.append(r)
        self.coefficients = np.vstack([self.linear, *self.level_radial])

    def _evaluate_partial(self, q: FloatArray) -> FloatArray:
        out = np.hstack([np.ones((q.shape[0], 1)), q]) @ self.linear
        for pts, alpha, r in zip(self.level_points, self.level_alphas, self.level_radial, strict=True):
            dist = np.linalg.norm(q[:, None, :] - pts[None, :, :], axis=-1)
            out = out + np.asarray(bspline_kernel(dist / alpha)) @ r
        return out

    def basis_one(self, p: FloatArray) -> FloatArray:
        """``basis`` for one validated (D,) point, without the argument checks (the fast path)."""
        row: FloatArray = self._basis_q(p[None, :])[0]
        return row

    def _basis_q(self, q: FloatArray) -> FloatArray:
        parts = [np.ones((q.shape[0], 1)), q]
        for pts, alpha in zip(self.level_points, self.level_alphas, strict=True):
            dist = np.linalg.norm(q[:, None, :] - pts[None, :, :], axis=-1)
            parts.append(np.asarray(bspline_kernel(dist / alpha)))
        return np.hstack(parts)

    def basis(self, p: FloatArray | Sequence[float] | float) -> FloatArray:
        """Basis row(s): f(p) = basis(p) @ coefficients.

        Args:
            p: adverb point(s).

        Returns:
            (K,) or (Q, K).

        Raises:
            ValueError: wrong dimension.
        """
        q, single = _as_query(p, self.dim)
        b = self._basis_q(q)
        return b[0] if single else b

