"""Re-timing a cycle: the temporal manipulation of Ciccone 2019's MoCurves (chapter 5, section 5.4.2,
eq. 5.7-5.11).

This module owns ``retime`` (new frame times that meet dragged keypoint times while keeping the period
and the motion's own timing: the thesis's quadratic programme, solved here as a bounded linear least-squares
problem on the frame steps) and ``retimed_frames`` (the curve evaluated at the new times). How the
programme becomes a least-squares problem, and the choices the thesis leaves open (the first step's
smoothness term wraps around the loop; frame 0 is pinned unless it is dragged), are in
``docs/design/cycles.md``. Frame arrays follow :mod:`cycles.edit`'s conventions.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from scipy.interpolate import CubicSpline
from scipy.optimize import lsq_linear
from scipy.sparse.linalg import spsolve

from cycles._checks import as_int, finite_array, loop_frames, positive_finite

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from cycles._types import BoolArray, FloatArray

__all__ = ["retime", "retimed_frames"]


def _check_times(t: object, name: str, *, strict: bool) -> FloatArray:
    arr = finite_array(t, name, (1,))
    if arr.size < 3:
        raise ValueError(f"{name} needs at least 3 frame times (frames 0..m with m >= 2)")
    steps = np.diff(arr)
    if strict and np.any(steps <= 0):
        raise ValueError(f"{name} must be strictly increasing")
    if np.any(steps < 0):
        raise ValueError(f"{name} must be non-decreasing")
    if not arr[-1] > arr[0]:
        raise ValueError(f"{name} must span a positive duration")
    return arr


def _retime_system(
    t: FloatArray,
    constraints: dict[int, float],
    period: float,
    weights: tuple[float, float, float, float],
) -> tuple[sp.csr_matrix, FloatArray, bool]:
    """The least-squares system ``min |A x - b|^2`` of eq. 5.11 in the step variables.

    ``x = (d_0 .. d_{m-1}[, t*_0])``: the frame steps ``d_i = t*_{i+1} - t*_i`` and, when frame 0 is
    constrained, the free start time (otherwise ``t*_0 = t_0`` is a constant). Row blocks: E_C, E_T,
    E_V, E_S, each scaled by the square root of its weight.
    """
    w_c, w_t, w_v, w_s = (math.sqrt(w) for w in weights)
    m = t.size - 1
    free_start = 0 in constraints
    n = m + 1 if free_start else m
    # E_C: t*_c = t*_0 + sum_{k<c} d_k should meet the target.
    frames = sorted(constraints)
    cols = [np.arange(c) for c in frames]
    if free_start:
        cols = [np.append(cc, m) for cc in cols]
    counts = [cc.size for cc in cols]
    rows = np.repeat(np.arange(len(frames)), counts)
    e_c = sp.csr_matrix(
        (np.full(rows.size, w_c), (rows, np.concatenate(cols) if cols else np.zeros(0, int))),
        shape=(len(frames), n),
    )
    offset = 0.0 if free_start else float(t[0])
    b_c = w_c * (np.array([constraints[c] for c in frames], dtype=np.float64) - offset)
    # E_T: the steps add up to the period.
    e_t = sp.csr_matrix((np.full(m, w_t), (np.zeros(m, int), np.arange(m))), shape=(1, n))
    b_t = np.array([w_t * period])
    # E_V: each step stays near the current one.
    e_v = w_v * sp.eye(m, n, format="csr")
    b_v = w_v * np.diff(t)
    # E_S: each step stays near the previous one, cyclically (d_{-1} = d_{m-1}).
    previous = np.roll(np.arange(m), 1)
    e_s = w_s * (sp.eye(m, n) - sp.csr_matrix((np.ones(m), (np.arange(m), previous)), shape=(m, n)))
    b_s = np.zeros(m)
    A = sp.vstack([e_c, e_t, e_v, e_s], format="csr")
    return A, np.concatenate([b_c, b_t, b_v, b_s]), free_start


def _solve_on_free(A: sp.csr_matrix, b: FloatArray, free: BoolArray) -> FloatArray:
    """Exact least-squares solution for the ``free`` variables, the others held at 0.

    Uses the augmented system ``[[I, A_F], [A_F^T, 0]] [r; x_F] = [b; 0]`` (sparse LU), which is as
    accurate as a QR solve and never forms ``A^T A``.
    """
    a_f = A[:, free]
    r, f = a_f.shape
    kkt = sp.bmat([[sp.eye(r), a_f], [a_f.T, None]], format="csc")
    # The system is symmetric: a minimum-degree ordering on A + A^T keeps the LU sparse even with the
    # dense E_C/E_T rows (about 20x faster than the default COLAMD at m = 1000).
    sol = spsolve(kkt, np.concatenate([b, np.zeros(f)]), permc_spec="MMD_AT_PLUS_A")
    x = np.zeros(A.shape[1])
    x[free] = sol[r:]
    return x


def retime(
    t: FloatArray,
    constraints: Mapping[int, float],
    period: float | None = None,
    w_c: float = 1e4,
    w_t: float = 1e4,
    w_v: float = 1.0,
    w_s: float = 1.0,
) -> FloatArray:
    """New frame times that meet dragged keypoint times while keeping the motion's timing (eq. 5.7-5.11).

    Minimises ``w_c E_C + w_t E_T + w_v E_V + w_s E_S`` over ``t* = (t*_0 .. t*_m)`` subject to
    ``t*_{i+1} >= t*_i``, where E_C pulls each constrained frame to its target time, E_T keeps
    ``t*_m - t*_0`` at the period, E_V keeps each step near the current step and E_S keeps neighbouring
    steps alike (cyclically: the first step is compared with the last). Substituting the steps
    ``d_i = t*_{i+1} - t*_i >= 0`` makes it a bounded linear least-squares problem
    (``scipy.optimize.lsq_linear`` on sparse matrices); the active set it finds is then re-solved exactly,
    so an unconstrained or already-feasible problem returns its exact minimiser. ``t*_0`` is pinned to
    ``t_0`` unless frame 0 is constrained. Contradictory constraints are not an error: the solution
    compromises (for example two frames pulled past each other end up at the same time). E_S compares
    neighbouring steps in absolute terms, as eq. 5.10 is written, so uneven input steps are evened out a
    little even without constraints; on a uniform grid with no constraints ``t* = t``.

    Args:
        t: ``(m + 1,)`` current frame times, non-decreasing, ``m >= 2``.
        constraints: frame index ``0..m`` -> target time (``phi_P(s_i^c)`` of the thesis).
        period: the loop duration ``T``; default ``t[-1] - t[0]``.
        w_c: weight of E_C (constraints); the thesis uses ``10^4`` times ``w_v``.
        w_t: weight of E_T (period).
        w_v: weight of E_V (keep the current steps).
        w_s: weight of E_S (smooth steps); may be 0.

    Returns:
        ``(m + 1,)`` new frame times: frame ``i`` shows the curve at source time ``t*_i`` (see
        ``retimed_frames``).

    Raises:
        ValueError: ``t`` is too short, not finite or decreasing; a constraint index is not an integer in
            ``0..m`` or its target is not finite; a weight is not positive and finite (``w_s`` may be
            0); ``period`` is not positive and finite.
    """
    times = _check_times(t, "t", strict=False)
    m = times.size - 1
    cons: dict[int, float] = {}
    for key, target in constraints.items():
        k = as_int(key, "constraint frame")
        if not 0 <= k <= m:
            raise ValueError(f"constraint frame {k} is outside 0..{m}")
        try:
            value = float(target)
        except (TypeError, ValueError) as err:
            raise ValueError(f"constraint target for frame {k} must be a number, got {target!r}") from err
        if not math.isfinite(value):
            raise ValueError(f"constraint target for frame {k} must be finite, got {target!r}")
        cons[k] = value
    T = float(times[-1] - times[0]) if period is None else positive_finite(period, "period")
    weights = (
        positive_finite(w_c, "w_c"),
        positive_finite(w_t, "w_t"),
        positive_finite(w_v, "w_v"),
        float(w_s),
    )
    if not (math.isfinite(weights[3]) and weights[3] >= 0):
        raise ValueError(f"w_s must be non-negative and finite, got {w_s!r}")

    A, b, free_start = _retime_system(times, cons, T, weights)
    n = A.shape[1]
    lower = np.zeros(n)
    if free_start:
        lower[m] = -np.inf
    fit = lsq_linear(A, b, bounds=(lower, np.full(n, np.inf)), tol=1e-10)
    x = np.maximum(fit.x, lower)

    # Polish: re-solve exactly with the active steps held at 0; keep it if it is still optimal.
    active = np.zeros(n, dtype=bool)
    active[:m] = fit.active_mask[:m] < 0
    exact = _solve_on_free(A, b, ~active)
    grad = A.T @ (A @ exact - b)
    step_tol = 1e-9 * T
    grad_tol = 1e-6 * (1.0 + float(np.max(np.abs(A.T @ b))))
    if np.all(exact[:m] >= -step_tol) and np.all(grad[active] >= -grad_tol):
        x = exact
        x[:m] = np.maximum(x[:m], 0.0)

    start = x[m] if free_start else float(times[0])
    return np.concatenate([[start], start + np.cumsum(x[:m])])


def retimed_frames(
    values: FloatArray,
    t: FloatArray,
    t_star: FloatArray,
    *,
    quaternions: Sequence[tuple[int, int, int, int]] = (),
) -> FloatArray:
    """The curve as played with new frame times: frame ``i`` shows it at source time ``t_star[i]``.

    The closed curve ``values`` (sampled at ``t``) is interpolated with a periodic cubic spline, and
    ``t_star`` is taken modulo the period ``t[-1] - t[0]``. The last output row equals the first only
    when ``t_star[-1] - t_star[0]`` is a whole number of periods (``retime`` meets the period to about
    ``1e-5`` of it).

    Args:
        values: ``(m + 1, C)`` (or ``(m + 1,)``) closed curve; the last row equals the first.
        t: ``(m + 1,)`` strictly increasing times of ``values``.
        t_star: ``(k,)`` source times to show, usually ``retime(t, ...)``.
        quaternions: column groups ``(w, x, y, z)`` holding unit quaternions (kept in one hemisphere
            from frame to frame); renormalised after interpolation.

    Returns:
        ``(k, C)`` (or ``(k,)``) values at the new times.

    Raises:
        ValueError: shapes disagree, values or times are not finite, ``t`` is not strictly increasing,
            the curve is not closed, or a quaternion group is out of range.
    """
    times = _check_times(t, "t", strict=True)
    vals = finite_array(values, "values", (1, 2))
    if vals.shape[0] != times.size:
        raise ValueError(f"values has {vals.shape[0]} rows but t has {times.size} times")
    loop_frames(vals, True, "values")
    ts = finite_array(t_star, "t_star", (1,))
    groups = [tuple(as_int(c, "quaternion column") for c in g) for g in quaternions]
    width = vals.shape[1] if vals.ndim == 2 else 1
    for g in groups:
        if len(g) != 4 or vals.ndim != 2 or not all(0 <= c < width for c in g):
            raise ValueError(f"quaternion columns {g} are not 4 columns of values")
    closed = vals.copy()
    closed[-1] = closed[0]  # exact equality for the periodic spline
    spline = CubicSpline(times, closed, bc_type="periodic", axis=0)
    T = float(times[-1] - times[0])
    out = np.asarray(spline(times[0] + np.mod(ts - times[0], T)))
    for g in groups:
        idx = list(g)
        out[:, idx] /= np.linalg.norm(out[:, idx], axis=1, keepdims=True)
    return out


