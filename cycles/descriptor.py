"""The curve descriptor of Ciccone 2019 (ETH Diss. 25792, section 5.3, eq. 5.1-5.2), and the small numeric
helpers around it.

For samples theta_i of an N-channel curve on a uniform grid, ``h_i`` stacks the windowed sums of the
first derivative over radii 0..k and ``g_i`` the same for the second derivative, so both have
``(k + 1) N`` entries. Two instants look alike when ``d_D(i, j) = |h_i - h_j| |g_i - g_j|`` is small.
The descriptor is blind to constant offsets and, on purpose, not rotation invariant.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from cycles._types import FloatArray, IntArray

#: The descriptor radius k of eq. 5.1 (Ciccone 2019, section 5.3 uses k = 5).
K_RADIUS = 5


def derivative(x: FloatArray, t: FloatArray | float) -> FloatArray:
    """Central differences ``(x[j+1] - x[j-1]) / (t[j+1] - t[j-1])`` (eq. 5.1), one-sided at the ends.

    Args:
        x: ``(n, N)`` samples.
        t: ``(n,)`` times, or the uniform sample interval.
    """
    n = x.shape[0]
    if n < 2:
        raise ValueError("a derivative needs at least 2 samples")
    tt = np.asarray(t, np.float64)
    if tt.ndim == 0:
        tt = np.arange(n, dtype=np.float64) * float(tt)
    d = np.empty_like(x, dtype=np.float64)
    if n > 2:
        d[1:-1] = (x[2:] - x[:-2]) / (tt[2:] - tt[:-2])[:, None]
    d[0] = (x[1] - x[0]) / (tt[1] - tt[0])
    d[-1] = (x[-1] - x[-2]) / (tt[-1] - tt[-2])
    return d


def window_sums(x: FloatArray, k: int = K_RADIUS) -> FloatArray:
    """``[sum_{|j-i|<=r} x_j for r in 0..k]`` side by side: ``(n, (k + 1) N)``; windows are truncated at
    the ends."""
    n, m = x.shape
    c = np.zeros((n + 1, m))
    np.cumsum(x, axis=0, out=c[1:])
    idx = np.arange(n)
    out = np.empty((n, (k + 1) * m))
    for r in range(k + 1):
        lo = np.maximum(idx - r, 0)
        hi = np.minimum(idx + r + 1, n)
        out[:, r * m:(r + 1) * m] = c[hi] - c[lo]
    return out


def descriptors(x: FloatArray, t: FloatArray | float, k: int = K_RADIUS) -> tuple[FloatArray, FloatArray]:
    """``(h, g)``, each ``(n, (k + 1) N)``: eq. 5.2 for every sample of ``x`` ``(n, N)``."""
    d1 = derivative(x, t)
    d2 = derivative(d1, t)
    return window_sums(d1, k), window_sums(d2, k)


def distances_to(h: FloatArray, g: FloatArray, i: int | IntArray, j: slice | IntArray | None = None) -> FloatArray:
    """``d_D(i, j)`` for one ``i`` (or several, giving one row each) against all ``j`` (or the ``j`` given)."""
    hj = h if j is None else h[j]
    gj = g if j is None else g[j]
    hi = h[i]
    gi = g[i]
    if np.ndim(i) == 0:
        one: FloatArray = np.sqrt(np.sum((hj - hi) ** 2, axis=1) * np.sum((gj - gi) ** 2, axis=1))
        return one
    dh: FloatArray = np.sum((hj[None, :, :] - hi[:, None, :]) ** 2, axis=2)
    dg: FloatArray = np.sum((gj[None, :, :] - gi[:, None, :]) ** 2, axis=2)
    return np.sqrt(dh * dg)


def local_minima(d: FloatArray, radius: int = 2) -> IntArray:
    """Indices j where ``d[j]`` is the minimum of ``d`` over ``[j - radius, j + radius]``."""
    n = d.size
    if n == 0:
        return np.zeros(0, np.intp)
    pad = np.concatenate([np.full(radius, np.inf), d, np.full(radius, np.inf)])
    win = np.lib.stride_tricks.sliding_window_view(pad, 2 * radius + 1)
    return np.flatnonzero(d <= win.min(axis=1))


def parabolic_offset(y0: float, y1: float, y2: float) -> float:
    """The vertex of the parabola through (-1, y0), (0, y1), (1, y2), clipped to [-0.5, 0.5]."""
    den = y0 - 2.0 * y1 + y2
    if not den > 0:
        return 0.0
    return float(min(0.5, max(-0.5, 0.5 * (y0 - y2) / den)))


def otsu_threshold(values: FloatArray) -> float:
    """Otsu's threshold splitting ``values`` into a low and a high class (callers keep the low one): the
    split of the sorted values that maximises the between-class variance, placed midway between the
    two values it separates. Exact, for the few dozen values it is used on."""
    v = np.sort(np.asarray(values, np.float64)[np.isfinite(values)])
    if v.size < 2 or v[-1] == v[0]:
        return float(v[-1]) if v.size else float("inf")
    n = v.size
    c = np.cumsum(v)
    k = np.arange(1, n)                 # size of the low class
    m0 = c[:-1] / k
    m1 = (c[-1] - c[:-1]) / (n - k)
    between = k * (n - k) * (m0 - m1) ** 2
    between[v[1:] == v[:-1]] = -1.0     # no split between equal values
    i = int(np.argmax(between))
    return float(0.5 * (v[i] + v[i + 1]))


def distance_rows(h: FloatArray, g: FloatArray, rows: IntArray, cols: slice | IntArray | None = None,
                  soft: float = 0.0) -> FloatArray:
    """``d_D(i, j)`` for every ``i`` in ``rows`` against every ``j`` in ``cols`` (default all), as one matrix
    ``(len(rows), len(cols))``; computed with inner products, so its cost does not grow with a Python loop.

    With ``soft`` > 0 each row becomes ``|dh| |dg| + b |dh| + a |dg|``, where a and b are ``soft`` times the
    row's median ``|dh|`` and ``|dg|``. The plain product is 0 wherever *either* factor is (for a
    single sine, at the mirror instant where only the second derivatives agree) and so cannot tell
    such a point from a true match; the small linear terms can, and leave the product's ranking of
    near matches otherwise unchanged.
    """
    hj = h if cols is None else h[cols]
    gj = g if cols is None else g[cols]
    hi, gi = h[rows], g[rows]
    dh: FloatArray = np.sum(hj * hj, axis=1)[None, :] + np.sum(hi * hi, axis=1)[:, None] - 2.0 * (hi @ hj.T)
    dg: FloatArray = np.sum(gj * gj, axis=1)[None, :] + np.sum(gi * gi, axis=1)[:, None] - 2.0 * (gi @ gj.T)
    fh = np.sqrt(np.maximum(dh, 0.0))
    fg = np.sqrt(np.maximum(dg, 0.0))
    if soft <= 0:
        return fh * fg
    a = soft * np.median(fh, axis=1, keepdims=True)
    b = soft * np.median(fg, axis=1, keepdims=True)
    return fh * fg + b * fh + a * fg
