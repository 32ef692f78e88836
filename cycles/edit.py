"""Editing a cycle's MoCurves: spatial edits, temporal re-timing and planar contacts.

The cycle-editing operations of the MoCurve interface of Ciccone 2019, *Intuitive Control of Animated
Scenes* (ETH Diss. 25792), chapter 5, section 5.4. ``cycles.edit`` is the one import for all three kinds
of edit; this module owns the spatial ones and re-exports the other two from their modules. Every
function works on numpy arrays holding one cycle sampled on frames ``0..m`` and returns new arrays (inputs
are never modified):

* **Spatial edits** (section 5.4.1, eq. 5.6; here): a change made at frame ``i`` spreads to the frames
  within ``tau`` of it with the Gaussian weight ``exp(-sigma (i - j)^2)``, wrapping around the loop.
  ``edit_translation`` adds the weighted offset, ``edit_rotation`` applies ``exp(w_j log dR) R_j`` to unit
  quaternions and ``edit_scale`` multiplies by ``factor ** w_j`` so scales stay positive. The thesis
  leaves sigma open; perfcap's default makes the weight 0.01 at ``tau`` (``docs/design/cycles.md``).
* **Temporal re-timing** (section 5.4.2, eq. 5.7-5.11; :mod:`cycles.retiming`): ``retime`` solves the
  thesis's quadratic programme for new frame times as a bounded linear least-squares problem on the frame
  steps; ``retimed_frames`` evaluates the curve at the new times.
* **Contacts** (section 5.4.3, eq. 5.12; :mod:`cycles.contacts`): ``project_to_plane`` snaps points onto a
  contact plane, ``contact_intervals`` finds the runs of contact frames (across the loop seam too) and
  ``fix_sliding`` gives the items in contact one shared root-relative velocity and moves the root against
  it, so feet in contact do not slide and the character travels.

Frame arrays come in two forms. A curve of ``m`` distinct frames (``closed=False``) is the loop's frames
``0..m-1``; frame ``m`` would be frame 0 again. A *closed* curve has ``m + 1`` rows whose last row repeats
the first (the form a ``Cycle`` stores); edits keep the two equal.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from cycles._checks import as_int, finite_array, loop_frames, positive_finite
from cycles.contacts import ContactResult, contact_intervals, fix_sliding, project_to_plane
from cycles.retiming import retime, retimed_frames

if TYPE_CHECKING:
    from cycles._types import FloatArray

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


def falloff_weights(m: int, i: int, tau: int, sigma: float | None = None) -> FloatArray:
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
    m = as_int(m, "m")
    i = as_int(i, "i")
    tau = as_int(tau, "tau")
    if m < 1:
        raise ValueError(f"m must be at least 1, got {m}")
    if not 0 <= i < m:
        raise ValueError(f"frame i={i} is outside 0..{m - 1}")
    if tau < 0:
        raise ValueError(f"tau must be non-negative, got {tau}")
    if sigma is not None:
        sigma = positive_finite(sigma, "sigma")
    elif tau > 0:
        sigma = math.log(1.0 / EDGE_WEIGHT) / tau**2
    else:
        sigma = 1.0  # irrelevant: only distance 0 is inside the window
    j = np.arange(m)
    raw = np.abs(j - i)
    dist = np.minimum(raw, m - raw)
    w: FloatArray = np.exp(-sigma * dist.astype(np.float64) ** 2)
    w[dist > tau] = 0.0
    return w


def _edit_frame(i: int, m: int, closed: bool) -> int:
    i = as_int(i, "i")
    top = m if closed else m - 1
    if not 0 <= i <= top:
        raise ValueError(f"frame i={i} is outside 0..{top}")
    return i % m


def edit_translation(
    P: FloatArray,
    i: int,
    delta: FloatArray | float,
    tau: int,
    sigma: float | None = None,
    *,
    closed: bool = False,
) -> FloatArray:
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
    arr = finite_array(P, "P", (1, 2))
    d = finite_array(delta, "delta", (0, 1))
    if d.shape != arr.shape[1:]:
        raise ValueError(f"delta has shape {d.shape} but each frame of P has shape {arr.shape[1:]}")
    m = loop_frames(arr, closed, "P")
    w = falloff_weights(m, _edit_frame(i, m, closed), tau, sigma)
    out = arr.copy()
    out[:m] += np.multiply.outer(w, d)
    if closed:
        out[m] = out[0]
    return out


def edit_rotation(
    Q: FloatArray,
    i: int,
    dq: FloatArray,
    tau: int,
    sigma: float | None = None,
    *,
    closed: bool = False,
) -> FloatArray:
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
    q = finite_array(Q, "Q", (2,))
    if q.shape[1] != 4:
        raise ValueError(f"Q must have 4 columns (w, x, y, z), got shape {q.shape}")
    norms = np.linalg.norm(q, axis=1)
    if np.any(norms < 1e-12):
        raise ValueError("Q holds a zero quaternion")
    q = np.asarray(q / norms[:, None])
    d = finite_array(dq, "dq", (1,))
    if d.shape != (4,) or np.linalg.norm(d) < 1e-12:
        raise ValueError("dq must be a non-zero quaternion (w, x, y, z)")
    m = loop_frames(q, closed, "Q", quaternion=True)
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
    S: FloatArray,
    i: int,
    factor: FloatArray | float,
    tau: int,
    sigma: float | None = None,
    *,
    closed: bool = False,
) -> FloatArray:
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
    arr = finite_array(S, "S", (1, 2))
    f = finite_array(factor, "factor", (0, 1))
    if np.any(arr <= 0):
        raise ValueError("S must be positive")
    if np.any(f <= 0):
        raise ValueError("factor must be positive")
    if f.shape != arr.shape[1:]:
        raise ValueError(f"factor has shape {f.shape} but each frame of S has shape {arr.shape[1:]}")
    m = loop_frames(arr, closed, "S")
    w = falloff_weights(m, _edit_frame(i, m, closed), tau, sigma)
    out = arr.copy()
    out[:m] = arr[:m] * np.exp(np.multiply.outer(w, np.log(f)))
    if closed:
        out[m] = out[0]
    return out


