"""Editing a cycle's MoCurves: spatial edits, temporal re-timing and planar contacts.

This module owns the cycle-editing operations of the MoCurve interface (Ciccone 2019, §5.4; spec
``cycles-and-puppet.md`` section 2). Every function works on numpy arrays holding one cycle sampled on
frames ``0..m`` and returns new arrays (inputs are never modified):

* **Spatial edits** (2.1, eq. 5.6): a change made at frame ``i`` spreads to the frames within ``tau`` of
  it with the Gaussian weight ``exp(-sigma (i - j)^2)``, wrapping around the loop. ``edit_translation``
  adds the weighted offset, ``edit_rotation`` applies ``exp(w_j log dR) R_j`` to unit quaternions and
  ``edit_scale`` multiplies by ``factor ** w_j`` so scales stay positive.
* **Temporal re-timing** (2.2, eq. 5.7-5.11): ``retime`` solves the thesis's quadratic programme for new
  frame times as a bounded linear least-squares problem on the frame steps; ``retimed_frames`` evaluates
  the curve at the new times.
* **Contacts** (2.3, eq. 5.12): ``project_to_plane`` snaps points onto a contact plane,
  ``contact_intervals`` finds the runs of contact frames (across the loop seam too) and ``fix_sliding``
  gives the items in contact one shared root-relative velocity and moves the root against it, so feet in
  contact do not slide and the character travels.

Frame arrays come in two forms. A curve of ``m`` distinct frames (``closed=False``) is the loop's frames
``0..m-1``; frame ``m`` would be frame 0 again. A *closed* curve has ``m + 1`` rows whose last row repeats
the first (the form a ``Cycle`` stores); edits keep the two equal.
"""

from __future__ import annotations

import math
import operator
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.interpolate import CubicSpline, splantider, splev, splrep
from scipy.optimize import lsq_linear
from scipy.sparse.linalg import spsolve
from scipy.spatial.transform import Rotation

__all__ = [
    "ContactResult",
    "contact_intervals",
    "edit_rotation",
    "edit_scale",
    "edit_translation",
    "falloff_weights",
    "fix_sliding",
    "project_to_plane",
    "retime",
    "retimed_frames",
]

#: Weight at distance ``tau`` with the default sigma (``sigma = ln(100) / tau^2``).
EDGE_WEIGHT = 0.01


# --------------------------------------------------------------------------------------------------
# Argument checks
# --------------------------------------------------------------------------------------------------


def _as_int(value: object, name: str) -> int:
    """``value`` as a Python int; bools, floats and other non-integers are refused with ValueError."""
    try:
        number = operator.index(value)  # type: ignore[arg-type]
    except TypeError as err:
        raise ValueError(f"{name} must be an integer, got {value!r}") from err
    if value is True or value is False:
        raise ValueError(f"{name} must be an integer, got {value!r}")
    return number


def _finite_array(values: object, name: str, ndim: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim not in ndim:
        raise ValueError(f"{name} must have {' or '.join(map(str, ndim))} dimensions, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    return arr


def _positive_finite(value: float, name: str) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be positive and finite, got {value!r}")
    return v


def _unit(vector: object, name: str) -> np.ndarray:
    v = _finite_array(vector, name, (1,))
    if v.shape != (3,):
        raise ValueError(f"{name} must have 3 components, got shape {v.shape}")
    norm = float(np.linalg.norm(v))
    if norm < 1e-12:
        raise ValueError(f"{name} must not be the zero vector")
    return v / norm


# --------------------------------------------------------------------------------------------------
# 2.1 Spatial edits
# --------------------------------------------------------------------------------------------------


def falloff_weights(m: int, i: int, tau: int, sigma: float | None = None) -> np.ndarray:
    """How much an edit at frame ``i`` moves each frame of a loop of ``m`` frames (eq. 5.6).

    Frame ``j`` gets ``exp(-sigma * dist(i, j)^2)`` if its circular distance ``dist`` to ``i`` (frames
    wrap modulo ``m``, so an edit at frame 0 reaches frames ``m-tau..m-1``) is at most ``tau``, and 0
    otherwise. Frame ``i`` itself gets 1.

    Args:
        m: the number of distinct frames in the loop (at least 1).
        i: the edited frame, ``0 <= i < m``.
        tau: the falloff radius in frames (``>= 0``; 0 edits frame ``i`` alone).
        sigma: the Gaussian rate; by default ``ln(100) / tau^2``, so the weight is 0.01 at distance
            ``tau`` (the thesis leaves sigma open).

    Returns:
        ``(m,)`` weights in ``[0, 1]``.

    Raises:
        ValueError: ``m``, ``i`` or ``tau`` is not an integer in range, or ``sigma`` is not positive
            and finite.
    """
    m = _as_int(m, "m")
    i = _as_int(i, "i")
    tau = _as_int(tau, "tau")
    if m < 1:
        raise ValueError(f"m must be at least 1, got {m}")
    if not 0 <= i < m:
        raise ValueError(f"frame i={i} is outside 0..{m - 1}")
    if tau < 0:
        raise ValueError(f"tau must be non-negative, got {tau}")
    if sigma is not None:
        sigma = _positive_finite(sigma, "sigma")
    elif tau > 0:
        sigma = math.log(1.0 / EDGE_WEIGHT) / tau**2
    else:
        sigma = 1.0  # irrelevant: only distance 0 is inside the window
    j = np.arange(m)
    raw = np.abs(j - i)
    dist = np.minimum(raw, m - raw)
    w: np.ndarray = np.exp(-sigma * dist.astype(np.float64) ** 2)
    w[dist > tau] = 0.0
    return w


def _loop_frames(values: np.ndarray, closed: bool, name: str, *, quaternion: bool = False) -> int:
    """The number of distinct frames ``m`` in ``values``, checking the closing row if ``closed``."""
    rows = int(values.shape[0])
    if not closed:
        if rows < 1:
            raise ValueError(f"{name} has no frames")
        return rows
    if rows < 2:
        raise ValueError(f"a closed {name} needs at least 2 rows (frames 0..m with m >= 1)")
    first, last = values[0], values[-1]
    scale = max(1.0, float(np.max(np.abs(values))))
    tol = 1e-9 * scale
    same = bool(np.all(np.abs(last - first) <= tol))
    if quaternion and not same:
        same = bool(np.all(np.abs(last + first) <= tol))
    if not same:
        raise ValueError(f"closed=True but the last row of {name} differs from the first")
    return rows - 1


def _edit_frame(i: int, m: int, closed: bool) -> int:
    i = _as_int(i, "i")
    top = m if closed else m - 1
    if not 0 <= i <= top:
        raise ValueError(f"frame i={i} is outside 0..{top}")
    return i % m


def edit_translation(
    P: np.ndarray,
    i: int,
    delta: np.ndarray | float,
    tau: int,
    sigma: float | None = None,
    *,
    closed: bool = False,
) -> np.ndarray:
    """Move frame ``i`` of a curve by ``delta`` and its neighbours by less (eq. 5.6).

    Frame ``j`` moves by ``w_j * delta`` with ``w = falloff_weights(m, i, tau, sigma)``. Works for
    positions and for any additive channel (a scalar curve with a scalar ``delta``).

    Args:
        P: ``(m, d)`` (or ``(m,)``) curve values; ``(m + 1, ...)`` with ``closed=True``.
        i: the edited frame (with ``closed=True``, ``m`` is accepted as frame 0).
        delta: ``(d,)`` (or scalar) offset applied at frame ``i``.
        tau: falloff radius in frames.
        sigma: Gaussian rate (default ``ln(100) / tau^2``).
        closed: ``P`` repeats frame 0 as its last row; the two stay equal.

    Returns:
        The edited copy of ``P``.

    Raises:
        ValueError: shapes disagree, values are not finite, ``closed`` is set but the ends differ, or
            ``i``, ``tau`` or ``sigma`` are invalid.
    """
    arr = _finite_array(P, "P", (1, 2))
    d = _finite_array(delta, "delta", (0, 1))
    if d.shape != arr.shape[1:]:
        raise ValueError(f"delta has shape {d.shape} but each frame of P has shape {arr.shape[1:]}")
    m = _loop_frames(arr, closed, "P")
    w = falloff_weights(m, _edit_frame(i, m, closed), tau, sigma)
    out = arr.copy()
    out[:m] += np.multiply.outer(w, d)
    if closed:
        out[m] = out[0]
    return out


def edit_rotation(
    Q: np.ndarray,
    i: int,
    dq: np.ndarray,
    tau: int,
    sigma: float | None = None,
    *,
    closed: bool = False,
) -> np.ndarray:
    """Rotate frame ``i`` of a rotation curve by ``dq`` and its neighbours by a fraction of it.

    Frame ``j`` becomes ``exp(w_j log dR) R_j``: the same axis as ``dR``, ``w_j`` of its angle, applied
    on the left (in the parent frame). Frames outside the window are returned unchanged. Each output
    quaternion keeps the sign (hemisphere) of its input, so the curve does not flip.

    Args:
        Q: ``(m, 4)`` unit quaternions, scalar first ``(w, x, y, z)``; ``(m + 1, 4)`` with ``closed=True``.
            Rows are renormalised before use.
        i: the edited frame (with ``closed=True``, ``m`` is accepted as frame 0).
        dq: ``(4,)`` the change at frame ``i`` as a quaternion ``(w, x, y, z)``; any non-zero norm.
        tau: falloff radius in frames.
        sigma: Gaussian rate (default ``ln(100) / tau^2``).
        closed: ``Q`` repeats frame 0 (or its negative) as its last row; they stay equal (up to that sign).

    Returns:
        The edited ``(rows, 4)`` unit quaternions ``(w, x, y, z)``.

    Raises:
        ValueError: wrong shapes, non-finite or zero quaternions, open ends with ``closed=True``, or
            invalid ``i``, ``tau`` or ``sigma``.
    """
    q = _finite_array(Q, "Q", (2,))
    if q.shape[1] != 4:
        raise ValueError(f"Q must have 4 columns (w, x, y, z), got shape {q.shape}")
    norms = np.linalg.norm(q, axis=1)
    if np.any(norms < 1e-12):
        raise ValueError("Q holds a zero quaternion")
    q = np.asarray(q / norms[:, None])
    d = _finite_array(dq, "dq", (1,))
    if d.shape != (4,) or np.linalg.norm(d) < 1e-12:
        raise ValueError("dq must be a non-zero quaternion (w, x, y, z)")
    m = _loop_frames(q, closed, "Q", quaternion=True)
    w = falloff_weights(m, _edit_frame(i, m, closed), tau, sigma)
    out = q.copy()
    hit = np.flatnonzero(w > 0)
    log_dr = Rotation.from_quat(d[[1, 2, 3, 0]]).as_rotvec()
    steps = Rotation.from_rotvec(w[hit, None] * log_dr[None, :])
    new = (steps * Rotation.from_quat(q[hit][:, [1, 2, 3, 0]])).as_quat()[:, [3, 0, 1, 2]]
    flip = np.sum(new * q[hit], axis=1) < 0
    new[flip] *= -1.0
    out[hit] = new / np.linalg.norm(new, axis=1, keepdims=True)
    if closed:
        sign = 1.0 if float(np.dot(q[m], q[0])) >= 0 else -1.0
        out[m] = sign * out[0]
    return out


def edit_scale(
    S: np.ndarray,
    i: int,
    factor: np.ndarray | float,
    tau: int,
    sigma: float | None = None,
    *,
    closed: bool = False,
) -> np.ndarray:
    """Scale frame ``i`` of a scale curve by ``factor`` and its neighbours by less, in log space.

    Frame ``j`` becomes ``S_j * factor ** w_j`` (``log S_j += w_j log factor``), so positive scales stay
    positive.

    Args:
        S: ``(m, d)`` (or ``(m,)``) positive scales; ``(m + 1, ...)`` with ``closed=True``.
        i: the edited frame (with ``closed=True``, ``m`` is accepted as frame 0).
        factor: ``(d,)`` (or scalar) positive factor applied at frame ``i``.
        tau: falloff radius in frames.
        sigma: Gaussian rate (default ``ln(100) / tau^2``).
        closed: ``S`` repeats frame 0 as its last row; the two stay equal.

    Returns:
        The edited copy of ``S``.

    Raises:
        ValueError: scales or factors not positive and finite, shapes disagree, open ends with
            ``closed=True``, or invalid ``i``, ``tau`` or ``sigma``.
    """
    arr = _finite_array(S, "S", (1, 2))
    f = _finite_array(factor, "factor", (0, 1))
    if np.any(arr <= 0):
        raise ValueError("S must be positive")
    if np.any(f <= 0):
        raise ValueError("factor must be positive")
    if f.shape != arr.shape[1:]:
        raise ValueError(f"factor has shape {f.shape} but each frame of S has shape {arr.shape[1:]}")
    m = _loop_frames(arr, closed, "S")
    w = falloff_weights(m, _edit_frame(i, m, closed), tau, sigma)
    out = arr.copy()
    out[:m] = arr[:m] * np.exp(np.multiply.outer(w, np.log(f)))
    if closed:
        out[m] = out[0]
    return out


# --------------------------------------------------------------------------------------------------
# 2.2 Temporal re-timing
# --------------------------------------------------------------------------------------------------


def _check_times(t: object, name: str, *, strict: bool) -> np.ndarray:
    arr = _finite_array(t, name, (1,))
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
    t: np.ndarray,
    constraints: dict[int, float],
    period: float,
    weights: tuple[float, float, float, float],
) -> tuple[sp.csr_matrix, np.ndarray, bool]:
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


def _solve_on_free(A: sp.csr_matrix, b: np.ndarray, free: np.ndarray) -> np.ndarray:
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
    t: np.ndarray,
    constraints: Mapping[int, float],
    period: float | None = None,
    w_c: float = 1e4,
    w_t: float = 1e4,
    w_v: float = 1.0,
    w_s: float = 1.0,
) -> np.ndarray:
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
        k = _as_int(key, "constraint frame")
        if not 0 <= k <= m:
            raise ValueError(f"constraint frame {k} is outside 0..{m}")
        try:
            value = float(target)
        except (TypeError, ValueError) as err:
            raise ValueError(f"constraint target for frame {k} must be a number, got {target!r}") from err
        if not math.isfinite(value):
            raise ValueError(f"constraint target for frame {k} must be finite, got {target!r}")
        cons[k] = value
    T = float(times[-1] - times[0]) if period is None else _positive_finite(period, "period")
    weights = (
        _positive_finite(w_c, "w_c"),
        _positive_finite(w_t, "w_t"),
        _positive_finite(w_v, "w_v"),
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
    values: np.ndarray,
    t: np.ndarray,
    t_star: np.ndarray,
    *,
    quaternions: Sequence[tuple[int, int, int, int]] = (),
) -> np.ndarray:
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
    vals = _finite_array(values, "values", (1, 2))
    if vals.shape[0] != times.size:
        raise ValueError(f"values has {vals.shape[0]} rows but t has {times.size} times")
    _loop_frames(vals, True, "values")
    ts = _finite_array(t_star, "t_star", (1,))
    groups = [tuple(_as_int(c, "quaternion column") for c in g) for g in quaternions]
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


# --------------------------------------------------------------------------------------------------
# 2.3 Contacts
# --------------------------------------------------------------------------------------------------


def project_to_plane(
    P: np.ndarray,
    point: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
    normal: Sequence[float] | np.ndarray = (0.0, 1.0, 0.0),
    eps: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Snap the points on or below a plane onto it: ``p <- p - ((p - p0) . n) n``.

    A point is in contact when its signed distance ``(p - p0) . n`` (``n`` normalised) is at most
    ``eps``; those points are projected, all others are returned unchanged.

    Args:
        P: ``(m, 3)`` points.
        point: a point ``p0`` on the plane (default the origin).
        normal: the plane normal, pointing away from the solid side (default ``+y``); any length.
        eps: contact tolerance in length units (default 0: on or below the plane).

    Returns:
        ``(P', mask)``: the projected copy and the ``(m,)`` boolean contact mask.

    Raises:
        ValueError: ``P`` is not ``(m, 3)`` and finite, ``normal`` is zero, or ``point``/``eps`` are not
            finite.
    """
    arr = _finite_array(P, "P", (2,))
    if arr.shape[1] != 3:
        raise ValueError(f"P must be (m, 3), got shape {arr.shape}")
    p0 = _finite_array(point, "point", (1,))
    if p0.shape != (3,):
        raise ValueError(f"point must have 3 components, got shape {p0.shape}")
    n = _unit(normal, "normal")
    e = float(eps)
    if not math.isfinite(e):
        raise ValueError("eps must be finite")
    dist = (arr - p0) @ n
    mask = dist <= e
    out = arr.copy()
    out[mask] -= np.outer(dist[mask], n)
    return out, mask


def contact_intervals(mask: np.ndarray) -> list[tuple[int, int]]:
    """The runs of consecutive contact frames of a loop, merged across the seam.

    ``mask`` covers the loop's ``n`` distinct frames (frame ``n`` would be frame 0 again). Each run is a
    half-open ``(start, stop)``, frames ``start .. stop - 1``; a run that ends at frame ``n - 1`` and one
    that starts at frame 0 are one interval across the seam, reported with ``stop > n`` (its frames are
    ``range(start, stop)`` modulo ``n``). A mask that is all true is the single interval ``(0, n)``.

    Args:
        mask: ``(n,)`` booleans, true where the item is in contact.

    Returns:
        The intervals, ordered by ``start``.

    Raises:
        ValueError: ``mask`` is not one-dimensional.
    """
    arr = np.asarray(mask, dtype=bool)
    if arr.ndim != 1:
        raise ValueError(f"mask must be one-dimensional, got shape {arr.shape}")
    n = arr.size
    if n == 0 or not arr.any():
        return []
    if arr.all():
        return [(0, n)]
    edges = np.diff(np.concatenate([[0], arr.astype(np.int8), [0]]))
    starts = np.flatnonzero(edges == 1)
    stops = np.flatnonzero(edges == -1)
    runs = [(int(a), int(b)) for a, b in zip(starts, stops, strict=True)]
    if len(runs) > 1 and runs[0][0] == 0 and runs[-1][1] == n:
        head = runs.pop(0)
        start, _ = runs.pop()
        runs.append((start, n + head[1]))
    return sorted(runs)


@dataclass(frozen=True, eq=False)
class ContactResult:
    """What ``fix_sliding`` returns.

    Attributes:
        items: name -> ``(m + 1, 3)`` new root-relative positions: contact frames projected and rebuilt
            from ``lam``, the rest of each curve re-scaled so the joins stay continuous.
        root: ``(m + 1, 3)`` new world root positions; its in-plane part moves with velocity ``-lam``,
            its height above the plane is the input's.
        lam: ``(m + 1, 3)`` the shared root-relative contact velocity at each frame (in the plane).
        intervals: name -> contact intervals of that item, as ``contact_intervals`` reports them.
        scales: name -> the length factor ``s_l`` of each interval (1 where it is undefined).
        displacement: ``(3,)`` root travel per cycle, ``-integral of lam over the period``.
    """

    items: dict[str, np.ndarray]
    root: np.ndarray
    lam: np.ndarray
    intervals: dict[str, list[tuple[int, int]]]
    scales: dict[str, list[float]] = field(default_factory=dict)
    displacement: np.ndarray = field(default_factory=lambda: np.zeros(3))


class _PeriodicVelocity:
    """A periodic in-plane velocity curve ``lam(t)`` and its running integral ``int_0^t lam``."""

    def __init__(self, times: np.ndarray, samples: np.ndarray, period: float, smoothing: float) -> None:
        # samples: (k, 2) plane coordinates at the distinct times (0 <= times < period).
        self.period = period
        self._t0 = 0.0
        self._cycle = np.zeros(2)
        self._const: np.ndarray | None = None
        self._tck: list[tuple[np.ndarray, np.ndarray, int]] = []
        self._anti: list[tuple[np.ndarray, np.ndarray, int]] = []
        if samples.shape[0] < 4:
            self._const = samples.mean(axis=0) if samples.shape[0] else np.zeros(2)
            return
        x = np.append(times, times[0] + period)
        rms = float(np.sqrt(np.mean(samples**2)))
        s = samples.shape[0] * (smoothing * rms) ** 2
        for c in range(samples.shape[1]):
            y = np.append(samples[:, c], samples[0, c])
            with warnings.catch_warnings():
                # FITPACK warns when a smoothing target is hard to meet; the spline it returns is
                # still periodic and usable.
                warnings.simplefilter("ignore", RuntimeWarning)
                tck = splrep(x, y, per=True, s=s)
            self._tck.append(tck)
            self._anti.append(splantider(tck))
        self._t0 = float(times[0])
        self._cycle = np.array([float(splev(self._t0 + period, a) - splev(self._t0, a)) for a in self._anti])

    def _wrap(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        loops = np.floor((t - self._t0) / self.period)
        return t - loops * self.period, loops

    def value(self, t: np.ndarray) -> np.ndarray:
        """``(len(t), 2)`` velocity at times ``t`` (any real values)."""
        if self._const is not None:
            return np.broadcast_to(self._const, (t.size, 2)).copy()
        tt, _ = self._wrap(t)
        return np.column_stack([splev(tt, tck) for tck in self._tck])

    def _primitive(self, t: np.ndarray) -> np.ndarray:
        """A continuous antiderivative on the whole real line (it grows by one loop's integral per loop)."""
        tt, loops = self._wrap(t)
        return np.column_stack(
            [splev(tt, anti) + loops * cycle for anti, cycle in zip(self._anti, self._cycle, strict=True)]
        )

    def integral(self, t: np.ndarray) -> np.ndarray:
        """``(len(t), 2)`` integral of the velocity from 0 to each ``t`` (any real values)."""
        if self._const is not None:
            return np.outer(t, self._const)
        return np.asarray(self._primitive(t) - self._primitive(np.zeros(1)))


def _plane_basis(n: np.ndarray) -> np.ndarray:
    """``(2, 3)`` orthonormal in-plane axes for unit normal ``n``."""
    helper = np.eye(3)[int(np.argmin(np.abs(n)))]
    u = np.cross(n, helper)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(n, u)])


@dataclass(frozen=True)
class _ContactMap:
    """The affine map ``p -> centre + M (p - centre)`` that re-scales the flight next to one contact."""

    centre: np.ndarray
    matrix: np.ndarray
    first: int  # first contact frame (unwrapped)
    last: int  # last contact frame (unwrapped)

    def __call__(self, p: np.ndarray) -> np.ndarray:
        return np.asarray(self.centre + (p - self.centre) @ self.matrix.T)


def _rebuild_item(
    p: np.ndarray,
    runs: list[tuple[int, int]],
    lam: _PeriodicVelocity,
    basis: np.ndarray,
    n: np.ndarray,
    dt: float,
) -> tuple[np.ndarray, list[float]]:
    """Steps 3-4 of ``fix_sliding`` for one item: integrate ``lam`` over its contacts, re-scale its flights.

    Args:
        p: ``(m + 1, 3)`` closed root-relative positions, already projected at the contact frames.
        runs: the item's contact intervals (``contact_intervals``).
        lam: the shared contact velocity.
        basis: ``(2, 3)`` in-plane axes.
        n: unit plane normal.
        dt: frame duration.

    Returns:
        The rebuilt ``(m + 1, 3)`` positions and the length factor ``s_l`` of each interval.
    """
    m = p.shape[0] - 1
    out = p.copy()
    if not runs:
        return out, []

    def integral(t: np.ndarray) -> np.ndarray:
        return np.asarray(lam.integral(t) @ basis)

    maps: list[_ContactMap] = []
    scales: list[float] = []
    for start, stop in runs:
        frames = np.arange(start, stop)
        lo, hi = start, stop - 1
        mid = 0.5 * (lo + hi)
        f = math.floor(mid)
        centre = (1.0 - (mid - f)) * p[f % m] + (mid - f) * p[(f + 1) % m]
        centre_tan = centre - (centre @ n) * n
        at_mid = integral(np.array([mid * dt]))
        # eq. 5.12 from the midpoint: in-plane part integrated, height kept (on the plane).
        rebuilt = centre_tan + (integral(frames * dt) - at_mid) + np.outer(p[frames % m] @ n, n)
        out[frames % m] = rebuilt
        if stop - start >= m:  # in contact all around: the closing frame continues the integration
            out[m] = centre_tan + (integral(np.array([m * dt])) - at_mid)[0] + (p[0] @ n) * n
        # s_l: how much the contact's extent along d = mean lam direction changed.
        mean_lam = (lam.value(frames * dt) @ basis).mean(axis=0)
        norm = float(np.linalg.norm(mean_lam))
        s_l, d = 1.0, np.zeros(3)
        if norm > 1e-12 and hi > lo:
            d = mean_lam / norm
            old = float(d @ (p[hi % m] - p[lo % m]))
            new = float(d @ (rebuilt[-1] - rebuilt[0]))
            if abs(old) > 1e-12 * max(1.0, float(np.max(np.abs(p)))) and new / old > 0:
                s_l = new / old
        scales.append(s_l)
        maps.append(_ContactMap(centre, np.eye(3) + (s_l - 1.0) * np.outer(d, d), lo, hi))

    if runs[0][1] - runs[0][0] >= m:
        return out, scales
    # Each flight joins the end of contact k to the start of contact k + 1 (the next loop's first one
    # after the last): blend the two maps linearly in time, then spread what is left of the gap at
    # either join linearly over the flight, so the curve meets the rebuilt contacts exactly.
    for k, here in enumerate(maps):
        there = maps[(k + 1) % len(maps)]
        join = there.first + (m if k + 1 == len(maps) else 0)
        gap = join - here.last
        if gap <= 1:
            continue
        flight = np.arange(here.last + 1, join)
        u = ((flight - here.last) / gap)[:, None]
        src = p[flight % m]
        moved = (1.0 - u) * here(src) + u * there(src)
        miss_here = out[here.last % m] - here(p[here.last % m])
        miss_there = out[join % m] - there(p[join % m])
        out[flight % m] = moved + (1.0 - u) * miss_here + u * miss_there
    out[m] = out[0]
    return out, scales


def fix_sliding(
    items: Mapping[str, np.ndarray],
    root: np.ndarray,
    period: float,
    point: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
    normal: Sequence[float] | np.ndarray = (0.0, 1.0, 0.0),
    eps: float = 0.0,
    smoothing: float = 0.0,
    contacts: Mapping[str, np.ndarray] | None = None,
) -> ContactResult:
    """Make items in contact with a plane stop sliding, and move the root so the character travels.

    Implements spec 2.3 (eq. 5.12) on one cycle of ``m`` frames at times ``i * period / m``:

    1. Each item's world position (root + root-relative) is projected onto the plane where it is within
       ``eps`` of it (``project_to_plane``), or at the frames ``contacts`` marks for it (the thesis's
       user-selected curve section); its contact intervals come from ``contact_intervals``.
    2. ``lam(t)``, the one root-relative velocity shared by all items in contact, is the mean of their
       in-plane root-relative velocities (periodic central differences) at each contact frame, fitted
       with a periodic spline (``splrep(per=True)``) so it is also defined in flight.
    3. Each contact interval is rebuilt by integrating ``lam`` from the interval's midpoint, which stays
       where it was: ``p(t) = p(t_mid) + int_{t_mid}^t lam``. Its height stays on the plane.
    4. The length of the contact along ``d`` (the normalised mean of ``lam`` over it) changes by
       ``s_l``; the non-contact frames are mapped with ``c + (I + (s_l - 1) d d^T)(p - c)`` about the
       contact midpoint ``c`` (blended linearly in time between the two contacts a flight joins), and any
       gap left at the joins is spread linearly over the flight, so the curve stays continuous.
    5. The root's in-plane position moves with velocity ``-lam`` from its position at frame 0 (its
       height is kept), so it travels ``-int_0^T lam`` per cycle and an item in contact has zero world
       velocity.

    With no contact at all, nothing changes (``lam`` is zero). An item in contact at every frame is
    rebuilt over the whole cycle and is closed only if ``lam`` integrates to zero.

    Args:
        items: name -> ``(m + 1, 3)`` closed root-relative positions (last row == first row).
        root: ``(m + 1, 3)`` world root positions at the same frames.
        period: the cycle duration ``T`` (seconds).
        point: a point on the contact plane.
        normal: the plane normal (up; any length).
        eps: contact tolerance: world points within ``eps`` of the plane (or below it) are in contact.
        smoothing: RMS deviation allowed between the ``lam`` spline and its samples, as a fraction of
            the samples' RMS; 0 interpolates them.
        contacts: optional name -> ``(m,)`` (or closed ``(m + 1,)``) booleans marking the frames where
            that item is in contact (from gait events or a selection); those items skip the ``eps``
            test and are projected onto the plane at exactly those frames.

    Returns:
        A ``ContactResult``.

    Raises:
        ValueError: no items, arrays not ``(m + 1, 3)`` and finite, shapes disagree, an item is not
            closed, ``m < 3``, ``contacts`` names an unknown item or has the wrong length, or
            ``period``, ``eps`` or ``smoothing`` are invalid.
    """
    if not items:
        raise ValueError("fix_sliding needs at least one item")
    base = _finite_array(root, "root", (2,))
    if base.shape[1] != 3 or base.shape[0] < 4:
        raise ValueError(f"root must be (m + 1, 3) with m >= 3, got shape {base.shape}")
    m = base.shape[0] - 1
    rel: dict[str, np.ndarray] = {}
    for name, arr in items.items():
        a = _finite_array(arr, f"items[{name!r}]", (2,))
        if a.shape != base.shape:
            raise ValueError(f"items[{name!r}] has shape {a.shape}, root has {base.shape}")
        _loop_frames(a, True, f"items[{name!r}]")
        rel[name] = a
    T = _positive_finite(period, "period")
    sm = float(smoothing)
    if not (math.isfinite(sm) and sm >= 0):
        raise ValueError(f"smoothing must be non-negative and finite, got {smoothing!r}")
    p0 = _finite_array(point, "point", (1,))
    if p0.shape != (3,):
        raise ValueError(f"point must have 3 components, got shape {p0.shape}")
    n = _unit(normal, "normal")
    e = float(eps)
    if not math.isfinite(e):
        raise ValueError("eps must be finite")
    given: dict[str, np.ndarray] = {}
    for name, marks in (contacts or {}).items():
        if name not in rel:
            raise ValueError(f"contacts names {name!r}, which is not an item")
        mk = np.asarray(marks)
        if mk.dtype != np.bool_ or mk.shape not in ((m,), (m + 1,)):
            raise ValueError(f"contacts[{name!r}] must be {m} or {m + 1} booleans, got {mk.dtype} {mk.shape}")
        given[name] = mk[:m].copy()

    dt = T / m
    times = np.arange(m + 1) * dt
    basis = _plane_basis(n)  # rows u, v

    # 1. Contacts, in world space, on the distinct frames 0..m-1.
    projected: dict[str, np.ndarray] = {}
    intervals: dict[str, list[tuple[int, int]]] = {}
    masks: dict[str, np.ndarray] = {}
    for name, a in rel.items():
        world = base[:m] + a[:m]
        if name in given:
            mask = given[name]
            world[mask] -= np.outer((world[mask] - p0) @ n, n)
        else:
            world, mask = project_to_plane(world, p0, n, e)
        p = a.copy()  # frames out of contact keep their exact input values
        p[:m][mask] = world[mask] - base[:m][mask]
        p[m] = p[0]
        projected[name] = p
        masks[name] = mask
        intervals[name] = contact_intervals(mask)

    if not any(masks[k].any() for k in masks):
        return ContactResult(
            items={k: v.copy() for k, v in rel.items()},
            root=base.copy(),
            lam=np.zeros((m + 1, 3)),
            intervals=intervals,
            scales={k: [] for k in rel},
            displacement=np.zeros(3),
        )

    # 2. The shared contact velocity: mean in-plane root-relative velocity of the items in contact.
    total = np.zeros((m, 2))
    count = np.zeros(m)
    for name, p in projected.items():
        q = p[:m]
        vel = (np.roll(q, -1, axis=0) - np.roll(q, 1, axis=0)) / (2.0 * dt)
        mask = masks[name]
        total[mask] += vel[mask] @ basis.T
        count[mask] += 1
    have = count > 0
    lam_curve = _PeriodicVelocity(times[:m][have], total[have] / count[have, None], T, sm)

    # 3-4. Rebuild each item's contacts and re-scale its flights.
    out_items: dict[str, np.ndarray] = {}
    scales: dict[str, list[float]] = {}
    for name, p in projected.items():
        out_items[name], scales[name] = _rebuild_item(p, intervals[name], lam_curve, basis, n, dt)

    # 5. The root travels against the contact velocity.
    heights = np.outer(base @ n, n)
    start_tan = base[0] - (base[0] @ n) * n
    new_root = heights + start_tan - lam_curve.integral(times) @ basis
    lam = lam_curve.value(times) @ basis
    lam[m] = lam[0]
    return ContactResult(
        items=out_items,
        root=new_root,
        lam=lam,
        intervals=intervals,
        scales=scales,
        displacement=-(lam_curve.integral(np.array([T])) @ basis)[0],
    )
