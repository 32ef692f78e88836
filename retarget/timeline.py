"""Time and root bookkeeping for verbs and adverbs (Rose 1999, *Verbs and Adverbs*, Princeton PhD thesis,
chapter 3): key-times and canonical time (section 3.4, eq. 3.1/3.2), the lazy motion operators of sections
3.9-3.10 that only touch time or the root (affine, time-warp with a bisection inverse, excerpt,
cyclification, concatenation; Definitions 2-4, 7 and 9), the sigmoid blend (section 5.5), root
reorientation and repositioning (section 3.5, Algorithms 3.1/3.2) and headings about the character's up
axis (quaternion maths is :mod:`capture.quat`).

Conventions: seconds, metres, radians; Y is up; heading theta sends +Z to (sin theta, cos theta), so
``R_y(a)`` maps a horizontal displacement (dX, dZ) to (cos a dX + sin a dZ, -sin a dX + cos a dZ).
Quaternions are (w, x, y, z). Scalar-DOF motions (``Motion``) keep the thesis's root layout when
``root_dofs`` is true: channels 0, 1, 2 are the X, Y, Z translation and channel 3 the heading (the root's
Y rotation); every other channel is a scalar DOF.

Five formulas of the thesis are used as perfcap corrects them (``docs/design/verbs-and-adverbs.md`` gives
the reasons): the affine operator's tau(T) = tau_s + T (Definition 3); the time-warp's key-times
K = w^-1(K') (bisection) and t(T) = t'(w(T)) (Definition 4); cyclification subtracts the ramp
(T/T^d - 1/2) d, which closes the seam (Definition 9); repositioning rotates by a = dY^r, so a zero target
reproduces Algorithm 3.1 (Algorithm 3.2); a concatenation evaluates its active constituent at its local
time (Definition 7).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING

import numpy as np

from capture.quat import quat_conj, quat_exp, quat_log, quat_mul, quat_normalize

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from retarget._types import BoolArray, FloatArray

__all__ = [
    "Affine",
    "Concatenation",
    "Cyclify",
    "Excerpt",
    "Motion",
    "SampledMotion",
    "TimeWarp",
    "canonical_time",
    "check_key_times",
    "cyclify_rotations",
    "cyclify_values",
    "ease_in",
    "find_cycle",
    "heading_of",
    "linear_blend",
    "reorient",
    "reposition",
    "sigmoid_blend",
    "sigmoid_blend_slope",
    "sine_warp",
    "split_heading",
    "verb_time",
    "yaw_quat",
]


# --------------------------------------------------------------------------------------------------
# Key-times and canonical time


def check_key_times(key_times: Sequence[float] | FloatArray) -> FloatArray:
    """Validate key-times and return them as a float array.

    Args:
        key_times: K_1..K_N in verb time (seconds); K_1 = 0 and K_N = T^d.

    Returns:
        The key-times as a 1-D float array.

    Raises:
        ValueError: fewer than two key-times, not finite, K_1 != 0, or not strictly increasing.
    """
    k = np.asarray(key_times, dtype=float)
    if k.ndim != 1 or k.size < 2:
        raise ValueError(f"need at least two key-times (0 and the duration), got {k!r}")
    if not np.all(np.isfinite(k)):
        raise ValueError("key-times must be finite")
    if k[0] != 0.0:
        raise ValueError(f"the first key-time must be 0, got {k[0]}")
    if np.any(np.diff(k) <= 0.0):
        raise ValueError(f"key-times must be strictly increasing, got {k.tolist()}")
    return k


def canonical_time(T: float | FloatArray, key_times: Sequence[float] | FloatArray) -> float | FloatArray:
    """Canonical time t(T) (eq 3.1): the piecewise-linear map sending K_m to (m-1)/(N-1).

    T outside [0, T^d] is clamped. With only the key-times (0, T^d) this is t = T / T^d.

    Args:
        T: verb time, scalar or array.
        key_times: K_1..K_N (validated).

    Returns:
        t in [0, 1], with the shape of ``T``.

    Raises:
        ValueError: invalid key-times.
    """
    k = check_key_times(key_times)
    out = np.interp(T, k, np.linspace(0.0, 1.0, k.size))
    return float(out) if np.ndim(T) == 0 else out


def verb_time(t: float | FloatArray, key_times: Sequence[float] | FloatArray) -> float | FloatArray:
    """Verb time T(t) (eq 3.2), the inverse of ``canonical_time``; t outside [0, 1] is clamped.

    Args:
        t: canonical time, scalar or array.
        key_times: K_1..K_N (validated).

    Returns:
        T in [0, T^d], with the shape of ``t``.

    Raises:
        ValueError: invalid key-times.
    """
    k = check_key_times(key_times)
    out = np.interp(t, np.linspace(0.0, 1.0, k.size), k)
    return float(out) if np.ndim(t) == 0 else out


# --------------------------------------------------------------------------------------------------
# Blend functions and time-warps (non-decreasing maps [0, 1] -> [0, 1])


def sigmoid_blend(t: float | FloatArray) -> float | FloatArray:
    """The sigmoid blend alpha(t) = (cos(-pi + pi t) + 1) / 2, t clamped to [0, 1].

    It equals the sine ease 1/2 + 1/2 sin(pi (t - 1/2)), has alpha(1/2) = 1/2 and zero slope at both
    ends.

    Args:
        t: canonical time of the blend, scalar or array.

    Returns:
        alpha in [0, 1].
    """
    tc = np.clip(t, 0.0, 1.0)
    out = (np.cos(-np.pi + np.pi * tc) + 1.0) / 2.0
    return float(out) if np.ndim(t) == 0 else out


def sigmoid_blend_slope(t: float | FloatArray) -> float | FloatArray:
    """d alpha / dt of ``sigmoid_blend``: (pi / 2) sin(pi t) inside [0, 1], 0 outside.

    Args:
        t: canonical time, scalar or array.

    Returns:
        The slope.
    """
    ta = np.asarray(t, dtype=float)
    out = np.where((ta >= 0.0) & (ta <= 1.0), 0.5 * np.pi * np.sin(np.pi * ta), 0.0)
    return float(out) if np.ndim(t) == 0 else out


def linear_blend(t: float | FloatArray) -> float | FloatArray:
    """The linear blend alpha(t) = t, clamped to [0, 1].

    Args:
        t: canonical time, scalar or array.

    Returns:
        alpha.
    """
    out = np.clip(t, 0.0, 1.0)
    return float(out) if np.ndim(t) == 0 else out


def sine_warp(t: float | FloatArray) -> float | FloatArray:
    """The time-warp U(t) = 1/2 + 1/2 sin(pi (t - 1/2)) (the same function as ``sigmoid_blend``).

    Args:
        t: canonical time, scalar or array.

    Returns:
        U(t).
    """
    tc = np.clip(t, 0.0, 1.0)
    out = 0.5 + 0.5 * np.sin(np.pi * (tc - 0.5))
    return float(out) if np.ndim(t) == 0 else out


def ease_in(t: float | FloatArray) -> float | FloatArray:
    """The ease-in time-warp U(t) = t^2.

    Args:
        t: canonical time, scalar or array.

    Returns:
        U(t).
    """
    tc = np.clip(t, 0.0, 1.0)
    out = tc * tc
    return float(out) if np.ndim(t) == 0 else out


# --------------------------------------------------------------------------------------------------
# Headings about +Y (quaternions (w, x, y, z), vectorised over leading axes)


def yaw_quat(angle: float | FloatArray) -> FloatArray:
    """Quaternion of a heading: rotation by ``angle`` about +Y.

    Args:
        angle: radians, scalar or array.

    Returns:
        (..., 4).
    """
    if isinstance(angle, (float, int)):               # one heading (every frame): no array machinery
        half = 0.5 * float(angle)
        return np.array([math.cos(half), 0.0, math.sin(half), 0.0])
    h = 0.5 * np.asarray(angle, dtype=float)
    z = np.zeros_like(h)
    return np.stack([np.cos(h), z, np.sin(h), z], axis=-1)


def heading_of(q: FloatArray) -> float | FloatArray:
    """Heading of rotations: the angle of the rotated +Z axis about +Y, atan2(f_x, f_z).

    Args:
        q: (..., 4) unit quaternions.

    Returns:
        Radians in (-pi, pi], scalar for a single quaternion.
    """
    q = np.asarray(q, dtype=float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    fx = 2.0 * (x * z + w * y)
    fz = 1.0 - 2.0 * (x * x + y * y)
    out = np.arctan2(fx, fz)
    return float(out) if q.ndim == 1 else out


def split_heading(q: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Split rotations into heading and tilt: q = yaw_quat(heading) * tilt, tilt with heading 0.

    Args:
        q: (..., 4) unit quaternions (for example the root rotation of each frame).

    Returns:
        (heading (...,), tilt (..., 4)).
    """
    h = np.asarray(heading_of(q), dtype=float)
    tilt = quat_mul(yaw_quat(-h), q)
    return h, tilt


# --------------------------------------------------------------------------------------------------
# Root reorientation and repositioning (Alg 3.1 / 3.2)


def _rot_xz(a: float | FloatArray, dx: FloatArray, dz: FloatArray) -> tuple[FloatArray, FloatArray]:
    ca, sa = np.cos(a), np.sin(a)
    return ca * dx + sa * dz, -sa * dx + ca * dz


def reposition(
    root_pos: FloatArray,
    heading: FloatArray,
    start: tuple[float, float | None, float, float],
) -> tuple[FloatArray, FloatArray]:
    """Move a root trajectory so that it starts at ``start`` (Rose 1999, Alg 3.2, with a = dY^r: perfcap's
    correction of the thesis's a = -dY^r, which contradicts Alg 3.1).

    With dY^r = H_0' - H_0: X' = cos(a) dX + sin(a) dZ + X_0', Z' = -sin(a) dX + cos(a) dZ + Z_0',
    heading' = heading + dY^r, Y' = Y + (Y_0' - Y_0), where a = dY^r and (dX, dZ) are measured from
    the first frame.

    Args:
        root_pos: (F, 3) X, Y, Z of the root per frame.
        heading: (F,) root heading per frame.
        start: desired start (X_0', Y_0', Z_0', H_0'); Y_0' None keeps the height (dY^t = 0).

    Returns:
        (root_pos (F, 3), heading (F,)) repositioned.

    Raises:
        ValueError: shapes do not match or there are no frames.
    """
    pos = np.asarray(root_pos, dtype=float)
    hd = np.asarray(heading, dtype=float)
    if pos.ndim != 2 or pos.shape[1] != 3 or hd.shape != (pos.shape[0],) or pos.shape[0] == 0:
        raise ValueError(f"root_pos must be (F, 3) and heading (F,), got {pos.shape} and {hd.shape}")
    x0, y0, z0, h0 = start
    a = float(h0) - hd[0]
    nx, nz = _rot_xz(a, pos[:, 0] - pos[0, 0], pos[:, 2] - pos[0, 2])
    dy = 0.0 if y0 is None else float(y0) - pos[0, 1]
    out = np.stack([nx + x0, pos[:, 1] + dy, nz + z0], axis=1)
    return out, hd + a


def reorient(root_pos: FloatArray, heading: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Move a root trajectory to start at X = Z = 0 with heading 0, height untouched (Alg 3.1).

    X' = cos(-H_0) dX + sin(-H_0) dZ, Z' = -sin(-H_0) dX + cos(-H_0) dZ, heading' = heading - H_0.

    Args:
        root_pos: (F, 3).
        heading: (F,).

    Returns:
        (root_pos (F, 3), heading (F,)).

    Raises:
        ValueError: bad shapes.
    """
    return reposition(root_pos, heading, (0.0, None, 0.0, 0.0))


# --------------------------------------------------------------------------------------------------
# Scalar-DOF motions and the time operators


class Motion(ABC):
    """A motion in verb time: duration T^d, key-times, and scalar DOF values theta(T).

    Subclasses implement ``duration``, ``key_times`` and ``theta``; the canonical-time maps and the
    animation time tau(T) = tau_start + T come for free.

    Attributes:
        root_dofs: channels 0..3 are X, Y, Z translation and heading.
        tau_start: animation time at which the motion starts.
    """

    root_dofs: bool = True
    tau_start: float = 0.0

    @property
    @abstractmethod
    def duration(self) -> float:
        """T^d in seconds."""

    @property
    @abstractmethod
    def key_times(self) -> FloatArray:
        """K_1 = 0 .. K_N = T^d."""

    @property
    @abstractmethod
    def num_dofs(self) -> int:
        """Number of scalar channels."""

    @abstractmethod
    def theta(self, T: float | FloatArray) -> FloatArray:
        """DOF values at verb time T: (C,) for a scalar T, (..., C) for an array."""

    def t(self, T: float | FloatArray) -> float | FloatArray:
        """Canonical time of verb time T (eq 3.1)."""
        return canonical_time(T, self.key_times)

    def T(self, t: float | FloatArray) -> float | FloatArray:
        """Verb time of canonical time t (eq 3.2)."""
        return verb_time(t, self.key_times)

    def tau(self, T: float | FloatArray) -> float | FloatArray:
        """Animation time tau(T) = tau_start + T."""
        return self.tau_start + np.asarray(T, dtype=float) if np.ndim(T) else self.tau_start + float(T)

    @property
    def tau_end(self) -> float:
        """Animation time at the end, tau_start + T^d."""
        return self.tau_start + self.duration


class SampledMotion(Motion):
    """The basic operator: DOF curves sampled at increasing times, linearly interpolated.

    Args:
        times: (F,) strictly increasing sample times starting at 0; T^d = times[-1].
        values: (F, C) DOF values.
        key_times: internal and end key-times; None means (0, T^d).
        root_dofs: channels 0..3 are the root (X, Y, Z, heading).
        tau_start: animation start time.

    Raises:
        ValueError: bad shapes, times not strictly increasing from 0, key-times invalid or not
            ending at T^d, or root_dofs with fewer than 4 channels.
    """

    def __init__(
        self,
        times: FloatArray,
        values: FloatArray,
        key_times: Sequence[float] | FloatArray | None = None,
        *,
        root_dofs: bool = True,
        tau_start: float = 0.0,
    ) -> None:
        tm = np.asarray(times, dtype=float)
        v = np.asarray(values, dtype=float)
        if tm.ndim != 1 or tm.size < 2 or v.ndim != 2 or v.shape[0] != tm.size:
            raise ValueError(f"times must be (F,) with F >= 2 and values (F, C), got {tm.shape}, {v.shape}")
        if tm[0] != 0.0 or np.any(np.diff(tm) <= 0.0):
            raise ValueError("sample times must start at 0 and increase strictly")
        if root_dofs and v.shape[1] < 4:
            raise ValueError("root_dofs needs at least 4 channels (X, Y, Z, heading)")
        k = check_key_times((0.0, tm[-1]) if key_times is None else key_times)
        if not math.isclose(k[-1], tm[-1], rel_tol=0.0, abs_tol=1e-9):
            raise ValueError(f"the last key-time {k[-1]} must equal the duration {tm[-1]}")
        self._times = tm
        self._values = v
        self._key_times = k
        self.root_dofs = root_dofs
        self.tau_start = float(tau_start)

    @property
    def duration(self) -> float:
        """T^d: the last sample time."""
        return float(self._times[-1])

    @property
    def key_times(self) -> FloatArray:
        """The key-times."""
        return self._key_times.copy()

    @property
    def num_dofs(self) -> int:
        """Number of channels."""
        return int(self._values.shape[1])

    def theta(self, T: float | FloatArray) -> FloatArray:
        """Linearly interpolated values, T clamped to [0, T^d].

        Args:
            T: verb time, scalar or array.

        Returns:
            (C,) or (..., C).
        """
        Ta = np.clip(np.asarray(T, dtype=float), 0.0, self.duration)
        flat = Ta.reshape(-1)
        i = np.clip(np.searchsorted(self._times, flat, side="right") - 1, 0, self._times.size - 2)
        t0 = self._times[i]
        f = ((flat - t0) / (self._times[i + 1] - t0))[:, None]
        out: FloatArray = (1.0 - f) * self._values[i] + f * self._values[i + 1]
        return out.reshape((*Ta.shape, self.num_dofs))


class Affine(Motion):
    """Affine time scale {tau_s, s, M'}: T^d = s T'^d, K = s K', theta(T) = theta'(T / s),
    tau(T) = tau_s + T (Rose 1999, Definition 3, with perfcap's correction of tau(T); the thesis scales T
    a second time).

    Args:
        motion: M'.
        scale: s > 0.
        tau_start: tau_s.

    Raises:
        ValueError: s not positive and finite.
    """

    def __init__(self, motion: Motion, scale: float, tau_start: float = 0.0) -> None:
        if not (math.isfinite(scale) and scale > 0.0):
            raise ValueError(f"scale must be positive, got {scale}")
        self.inner = motion
        self.scale = float(scale)
        self.tau_start = float(tau_start)
        self.root_dofs = motion.root_dofs

    @property
    def duration(self) -> float:
        """s T'^d."""
        return self.scale * self.inner.duration

    @property
    def key_times(self) -> FloatArray:
        """s K'."""
        return self.scale * self.inner.key_times

    @property
    def num_dofs(self) -> int:
        """Channels of M'."""
        return self.inner.num_dofs

    def theta(self, T: float | FloatArray) -> FloatArray:
        """theta'(T / s)."""
        return self.inner.theta(np.asarray(T, dtype=float) / self.scale)


class TimeWarp(Motion):
    """Time-warp {U, M'}: w(T) = T^d U(T / T^d), theta(T) = theta'(w(T)), same duration.

    The key-times move to K = w^-1(K') (found by bisection), so t(T) = t'(w(T)) holds.

    Args:
        motion: M'.
        warp: U, non-decreasing, U(0) = 0, U(1) = 1, vectorised.
        tol: bisection tolerance in seconds.

    Raises:
        ValueError: U does not fix 0 and 1.
    """

    def __init__(self, motion: Motion, warp: Callable[[FloatArray], FloatArray], tol: float = 1e-12) -> None:
        u01 = np.asarray(warp(np.array([0.0, 1.0])), dtype=float)
        if abs(u01[0]) > 1e-12 or abs(u01[1] - 1.0) > 1e-12:
            raise ValueError(f"a time-warp must map 0 -> 0 and 1 -> 1, got {u01.tolist()}")
        self.inner = motion
        self.warp = warp
        self.tol = float(tol)
        self.root_dofs = motion.root_dofs
        self.tau_start = motion.tau_start
        kp = motion.key_times
        k = self.inverse(kp)
        k[0], k[-1] = 0.0, motion.duration
        self._key_times = k

    @property
    def duration(self) -> float:
        """Unchanged: T'^d."""
        return self.inner.duration

    @property
    def key_times(self) -> FloatArray:
        """w^-1(K')."""
        return self._key_times.copy()

    @property
    def num_dofs(self) -> int:
        """Channels of M'."""
        return self.inner.num_dofs

    def w(self, T: float | FloatArray) -> FloatArray:
        """w(T) = T^d U(T / T^d)."""
        d = self.duration
        return d * np.asarray(self.warp(np.clip(np.asarray(T, dtype=float) / d, 0.0, 1.0)), dtype=float)

    def inverse(self, Tw: float | FloatArray) -> FloatArray:
        """w^-1 by vectorised bisection (the smallest T with w(T) >= Tw).

        Args:
            Tw: warped time(s).

        Returns:
            T with w(T) = Tw within ``tol``.
        """
        target = np.atleast_1d(np.asarray(Tw, dtype=float))
        lo = np.zeros_like(target)
        hi = np.full_like(target, self.duration)
        n = max(1, math.ceil(math.log2(max(self.duration, 1e-300) / self.tol)) + 1)
        for _ in range(min(n, 200)):
            mid = 0.5 * (lo + hi)
            below = self.w(mid) < target
            lo = np.where(below, mid, lo)
            hi = np.where(below, hi, mid)
        inverse: FloatArray = 0.5 * (lo + hi)
        return inverse

    def theta(self, T: float | FloatArray) -> FloatArray:
        """theta'(w(T))."""
        return self.inner.theta(self.w(T))

    def t(self, T: float | FloatArray) -> float | FloatArray:
        """Canonical time t(T) = t'(w(T)) (perfcap's correction of Definition 4); it sends K_m to (m-1)/(N-1)."""
        out = self.inner.t(self.w(T))
        return float(out) if np.ndim(T) == 0 else out

    def T(self, t: float | FloatArray) -> float | FloatArray:
        """Verb time T(t) = w^-1(T'(t)), the inverse of ``t``."""
        out = self.inverse(self.inner.T(t))
        return float(out[0]) if np.ndim(t) == 0 else out.reshape(np.shape(t))


class Excerpt(Motion):
    """A part [T_s, T_e] of M' (Rose 1999's clip operator, Definition 2, given here in M''s verb time).

    T^d = T_e - T_s, theta(T) = theta'(T + T_s); the key-times inside the interval shift by -T_s and
    the ones outside are dropped.

    Args:
        motion: M'.
        start: T_s.
        end: T_e.

    Raises:
        ValueError: not 0 <= T_s < T_e <= T'^d.
    """

    def __init__(self, motion: Motion, start: float, end: float) -> None:
        if not (0.0 <= start < end <= motion.duration + 1e-12):
            raise ValueError(f"need 0 <= start < end <= {motion.duration}, got {start}, {end}")
        self.inner = motion
        self.start = float(start)
        self.end = float(min(end, motion.duration))
        self.root_dofs = motion.root_dofs
        self.tau_start = motion.tau_start
        k = motion.key_times
        inside = k[(k > self.start + 1e-12) & (k < self.end - 1e-12)] - self.start
        self._key_times = np.concatenate([[0.0], inside, [self.end - self.start]])

    @property
    def duration(self) -> float:
        """T_e - T_s."""
        return self.end - self.start

    @property
    def key_times(self) -> FloatArray:
        """Shifted inner key-times."""
        return self._key_times.copy()

    @property
    def num_dofs(self) -> int:
        """Channels of M'."""
        return self.inner.num_dofs

    def theta(self, T: float | FloatArray) -> FloatArray:
        """theta'(T + T_s)."""
        return self.inner.theta(np.clip(np.asarray(T, dtype=float), 0.0, self.duration) + self.start)


def _default_cycle_mask(motion: Motion) -> BoolArray:
    mask = np.ones(motion.num_dofs, dtype=bool)
    if motion.root_dofs:
        mask[[0, 2, 3]] = False  # X, Z and heading are carried by concatenation, never cyclified
    return mask


class Cyclify(Motion):
    """Cyclification (Def 9): theta_j(T) = theta'_j(T) - (T / T^d - 1/2) d_j for the selected DOFs,
    d_j = theta'_j(T^d) - theta'_j(0), so theta_j(0) = theta_j(T^d) (Rose 1999, section 3.10, with perfcap's
    correction of the ramp's sign: the thesis's sign doubles the gap at the seam).

    The velocity becomes theta'_j-dot - d_j / T^d. Root X, Z and heading are never cyclified.

    Args:
        motion: M'.
        mask: (C,) bool, the cyclified DOFs; None selects all but root X, Z and heading.

    Raises:
        ValueError: a mask of the wrong length, or one that selects root X, Z or heading.
    """

    def __init__(self, motion: Motion, mask: Sequence[bool] | BoolArray | None = None) -> None:
        c = _default_cycle_mask(motion) if mask is None else np.asarray(mask, dtype=bool)
        if c.shape != (motion.num_dofs,):
            raise ValueError(f"mask must have {motion.num_dofs} entries, got {c.shape}")
        if motion.root_dofs and np.any(c[[0, 2, 3]]):
            raise ValueError("root X, Z and heading are never cyclified")
        self.inner = motion
        self.mask = c
        self.root_dofs = motion.root_dofs
        self.tau_start = motion.tau_start
        ends = motion.theta(np.array([0.0, motion.duration]))
        self.gap = np.where(c, ends[1] - ends[0], 0.0)

    @property
    def duration(self) -> float:
        """Unchanged."""
        return self.inner.duration

    @property
    def key_times(self) -> FloatArray:
        """Unchanged."""
        return self.inner.key_times

    @property
    def num_dofs(self) -> int:
        """Channels of M'."""
        return self.inner.num_dofs

    def theta(self, T: float | FloatArray) -> FloatArray:
        """theta' minus the ramp of the seam gap."""
        Ta = np.asarray(T, dtype=float)
        ramp = (np.clip(Ta, 0.0, self.duration) / self.duration - 0.5)[..., None]
        out: FloatArray = self.inner.theta(Ta) - ramp * self.gap
        return out


def cyclify_values(values: FloatArray, mask: Sequence[bool] | BoolArray | None = None) -> FloatArray:
    """Cyclify uniformly sampled curves in place of an operator: v_k - (k/(F-1) - 1/2) d.

    Args:
        values: (F, C), first sample at T = 0 and last at T^d.
        mask: (C,) bool of cyclified channels; None cyclifies all.

    Returns:
        (F, C) with equal first and last rows on the masked channels.

    Raises:
        ValueError: bad shapes.
    """
    v = np.asarray(values, dtype=float)
    if v.ndim != 2 or v.shape[0] < 2:
        raise ValueError(f"values must be (F, C) with F >= 2, got {v.shape}")
    c = np.ones(v.shape[1], dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if c.shape != (v.shape[1],):
        raise ValueError("mask length does not match the channels")
    d = np.where(c, v[-1] - v[0], 0.0)
    ramp = np.linspace(0.0, 1.0, v.shape[0])[:, None] - 0.5
    return v - ramp * d


def cyclify_rotations(rotations: FloatArray) -> FloatArray:
    """Cyclify uniformly sampled rotations: the seam rotation g = q(T^d) q(0)^-1 (as a rotation
    vector r) is spread as exp(-(k/(F-1) - 1/2) r) q_k, so the first and last samples coincide.

    Args:
        rotations: (F, ..., 4) unit quaternions, first sample at T = 0 and last at T^d.

    Returns:
        (F, ..., 4) unit quaternions with q(0) = q(T^d) (up to sign).

    Raises:
        ValueError: bad shape.
    """
    q = np.asarray(rotations, dtype=float)
    if q.ndim < 2 or q.shape[-1] != 4 or q.shape[0] < 2:
        raise ValueError(f"rotations must be (F, ..., 4) with F >= 2, got {q.shape}")
    r = quat_log(quat_mul(q[-1], quat_conj(q[0])))
    ramp = (np.linspace(0.0, 1.0, q.shape[0]) - 0.5).reshape((-1,) + (1,) * (q.ndim - 1))
    return quat_normalize(quat_mul(quat_exp(-ramp * r), q))


def find_cycle(
    motion: Motion,
    approx_start: float,
    approx_end: float,
    window: float,
    *,
    step: float | None = None,
    mask: Sequence[bool] | BoolArray | None = None,
) -> tuple[float, float]:
    """Best-matching pair of poses near both ends of a marked cycle (cyclification steps 1-2).

    Searches T_a in [approx_start - window, approx_start + window] and T_b likewise around
    ``approx_end`` (clamped to the motion) for the pair with the least sum of squared differences over
    the cyclified DOFs.

    Args:
        motion: the motion.
        approx_start: designer's cycle start (verb time).
        approx_end: designer's cycle end.
        window: half-width of the search windows, seconds.
        step: search spacing; None uses window / 20.
        mask: DOFs compared; None uses all but root X, Z, heading.

    Returns:
        (T_a, T_b) with T_a < T_b.

    Raises:
        ValueError: an empty or inverted search.
    """
    if not (window >= 0.0 and approx_start < approx_end):
        raise ValueError("need approx_start < approx_end and window >= 0")
    c = _default_cycle_mask(motion) if mask is None else np.asarray(mask, dtype=bool)
    h = window / 20.0 if step is None else float(step)
    if h <= 0.0:
        h = 1.0 / 120.0
    ta = np.clip(np.arange(approx_start - window, approx_start + window + 0.5 * h, h), 0.0, motion.duration)
    tb = np.clip(np.arange(approx_end - window, approx_end + window + 0.5 * h, h), 0.0, motion.duration)
    va = motion.theta(ta)[:, c]
    vb = motion.theta(tb)[:, c]
    cost = ((va[:, None, :] - vb[None, :, :]) ** 2).sum(axis=-1)
    cost = np.where(ta[:, None] < tb[None, :], cost, np.inf)
    if not np.isfinite(cost).any():
        raise ValueError("no start before an end in the search windows")
    i, j = np.unravel_index(int(np.argmin(cost)), cost.shape)
    return float(ta[i]), float(tb[j])


class Concatenation(Motion):
    """Concatenation {M_0..M_n}: one after the other, T^d = sum of the durations.

    The active constituent is the last n with sum_{c<n} T^d_c <= T, evaluated at its local time
    T - sum_{c<n} T^d_c (Rose 1999, Definition 7, whose theta_c(T - T_elapsed) subtracts the local time
    instead: perfcap's correction). Each start is lined up with the previous end by Alg 3.2 in X,
    Z and heading (dY^t = 0); the other DOFs are not smoothed. Key-times shift by the accumulated
    duration.

    Args:
        motions: M_0..M_n, all with the same channels.
        tau_start: animation start time.

    Raises:
        ValueError: no motions, or different channel counts or root layouts.
    """

    def __init__(self, motions: Sequence[Motion], tau_start: float = 0.0) -> None:
        if not motions:
            raise ValueError("a concatenation needs at least one motion")
        c = motions[0].num_dofs
        if any(m.num_dofs != c or m.root_dofs != motions[0].root_dofs for m in motions):
            raise ValueError("all constituents need the same channels")
        self.parts = list(motions)
        self.root_dofs = motions[0].root_dofs
        self.tau_start = float(tau_start)
        d = np.array([m.duration for m in self.parts])
        self.starts = np.concatenate([[0.0], np.cumsum(d)])
        ks = [self.parts[0].key_times]
        for s, m in zip(self.starts[1:-1], self.parts[1:], strict=True):
            ks.append(m.key_times[1:] + s)
        self._key_times = np.concatenate(ks)
        # per constituent: (X_0', Z_0', a, X_0, Z_0) of its Alg 3.2 alignment
        self._align: list[tuple[float, float, float, float, float]] = []
        end_x, end_z, end_h = 0.0, 0.0, 0.0
        for i, m in enumerate(self.parts):
            first = m.theta(0.0)
            if not self.root_dofs:
                self._align.append((0.0, 0.0, 0.0, 0.0, 0.0))
                continue
            if i == 0:
                self._align.append((float(first[0]), float(first[2]), 0.0, float(first[0]), float(first[2])))
            else:
                a = end_h - float(first[3])
                self._align.append((end_x, end_z, a, float(first[0]), float(first[2])))
            last = self._root_world(i, m.theta(m.duration)[None, :])[0]
            end_x, end_z, end_h = float(last[0]), float(last[2]), float(last[3])

    def _root_world(self, i: int, vals: FloatArray) -> FloatArray:
        x0n, z0n, a, x0, z0 = self._align[i]
        out = vals.copy()
        if self.root_dofs:
            nx, nz = _rot_xz(a, vals[:, 0] - x0, vals[:, 2] - z0)
            out[:, 0] = nx + x0n
            out[:, 2] = nz + z0n
            out[:, 3] = vals[:, 3] + a
        return out

    @property
    def duration(self) -> float:
        """Sum of the constituents' durations."""
        return float(self.starts[-1])

    @property
    def key_times(self) -> FloatArray:
        """Union of the shifted key-times."""
        return self._key_times.copy()

    @property
    def num_dofs(self) -> int:
        """Channels."""
        return self.parts[0].num_dofs

    def active(self, T: float) -> tuple[int, float]:
        """Active constituent and its local time at T (T clamped to [0, T^d]).

        Args:
            T: verb time.

        Returns:
            (index, local time).
        """
        Tc = min(max(float(T), 0.0), self.duration)
        n = int(np.searchsorted(self.starts[:-1], Tc, side="right") - 1)
        n = min(max(n, 0), len(self.parts) - 1)
        return n, Tc - float(self.starts[n])

    def theta(self, T: float | FloatArray) -> FloatArray:
        """theta_n(T_loc), root aligned."""
        Ta = np.clip(np.asarray(T, dtype=float), 0.0, self.duration)
        flat = Ta.reshape(-1)
        idx = np.clip(np.searchsorted(self.starts[:-1], flat, side="right") - 1, 0, len(self.parts) - 1)
        out = np.empty((flat.size, self.num_dofs))
        for i in np.unique(idx):
            sel = idx == i
            local = flat[sel] - self.starts[i]
            out[sel] = self._root_world(int(i), self.parts[int(i)].theta(local).reshape(-1, self.num_dofs))
        return out.reshape((*Ta.shape, self.num_dofs))
