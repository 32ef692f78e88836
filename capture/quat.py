"""Quaternion algebra, in one place for the whole project: scalar-first ``(w, x, y, z)`` unit quaternions as
plain numpy arrays of shape ``(..., 4)``, broadcast over leading axes. ``quat_mul(a, b)`` applies ``b`` first.

Pure maths with no frame convention: headings and yaw about a particular world axis belong to the code
that owns that frame (z-up sensor fusion in :mod:`capture.calibration`, y-up characters in
:mod:`retarget.timeline`). scipy's ``Rotation`` is scalar-last and is converted at its boundary.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

__all__ = [
    "cross",
    "quat_canonical",
    "quat_conj",
    "quat_exp",
    "quat_from_axis_angle",
    "quat_from_matrix",
    "quat_log",
    "quat_mul",
    "quat_normalize",
    "quat_rotate",
    "quat_slerp",
    "quat_to_matrix",
    "quat_to_matrix_components",
]




def quat_mul(a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """Hamilton product ``a * b`` (apply ``b`` first, then ``a``) of scalar-first quaternions, broadcast over
    leading axes."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def quat_conj(q: ArrayLike) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion)."""
    q = np.array(q, np.float64, copy=True)
    q[..., 1:] = -q[..., 1:]
    return q


def quat_normalize(q: ArrayLike) -> np.ndarray:
    """Unit quaternions (the sign is kept, so a blended sequence stays on its hemisphere).

    Raises:
        ValueError: if a quaternion is zero or not finite.
    """
    q = np.asarray(q, np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.all(np.isfinite(n)) or np.any(n < 1e-12):
        raise ValueError("quaternions must be finite and non-zero")
    return q / n


def quat_canonical(q: ArrayLike) -> np.ndarray:
    """Unit quaternions with a non-negative scalar part (one of the two signs of each rotation).

    Raises:
        ValueError: if a quaternion is zero or not finite.
    """
    q = quat_normalize(q)
    return np.where(q[..., :1] < 0.0, -q, q)


def cross(a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """Cross products of 3-vectors ``(..., 3)``; cheaper than ``np.cross`` on small arrays."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def quat_rotate(q: ArrayLike, v: ArrayLike) -> np.ndarray:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)``."""
    q = np.asarray(q, np.float64)
    v = np.asarray(v, np.float64)
    u = q[..., 1:]
    t = 2.0 * cross(u, v)
    return v + q[..., :1] * t + cross(u, t)


def _quadratic_form() -> np.ndarray:
    # R(q) entries as a linear map of the 16 products q_a q_b (exact for unit q, scaled by |q|^2 otherwise)
    c = np.zeros((4, 4, 3, 3))
    w, x, y, z = range(4)
    for r, signs in enumerate(((1, 1, -1, -1), (1, -1, 1, -1), (1, -1, -1, 1))):
        for a, v in zip((w, x, y, z), signs, strict=True):
            c[a, a, r, r] = v
    for a, b, r, col, v in ((x, y, 0, 1, 2), (w, z, 0, 1, -2), (x, z, 0, 2, 2), (w, y, 0, 2, 2),
                            (x, y, 1, 0, 2), (w, z, 1, 0, 2), (y, z, 1, 2, 2), (w, x, 1, 2, -2),
                            (x, z, 2, 0, 2), (w, y, 2, 0, -2), (y, z, 2, 1, 2), (w, x, 2, 1, 2)):
        c[a, b, r, col] = v
    return c.reshape(16, 9)


_Q2M = _quadratic_form()


def quat_to_matrix_components(q: np.ndarray) -> np.ndarray:
    """Component-first rotation matrices: entries ``(3, 3, ...)`` of quaternions given as ``(4, ...)`` (the fast
    layout for large batches; normalised on the fly)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    s = 2.0 / np.maximum(w * w + x * x + y * y + z * z, 1e-300)
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    return np.array([[1.0 - yy - zz, xy - wz, xz + wy],
                     [xy + wz, 1.0 - xx - zz, yz - wx],
                     [xz - wy, yz + wx, 1.0 - xx - yy]])


def _matrices_small(q: np.ndarray) -> np.ndarray:
    # fewer numpy calls than _matrix_components: faster for a handful of quaternions
    qq = (q[..., :, None] * q[..., None, :]).reshape((*q.shape[:-1], 16))
    m = (qq @ _Q2M) / np.maximum(qq[..., ::5].sum(axis=-1, keepdims=True), 1e-300)
    return m.reshape((*q.shape[:-1], 3, 3))


def quat_to_matrix(q: ArrayLike) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of quaternions ``(..., 4)`` (normalised on the fly)."""
    q = np.asarray(q, np.float64)
    if q.size <= 256:
        return _matrices_small(q)
    m = quat_to_matrix_components(np.moveaxis(q, -1, 0))
    return np.moveaxis(m, (0, 1), (-2, -1))


def _from_matrix_maps() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    # Shepperd's method as linear maps of the 9 matrix entries: four candidate (unnormalised) quaternions,
    # one per largest diagonal term, and the four terms that pick the best-conditioned candidate
    e = {f"m{r}{c}": 3 * r + c for r in range(3) for c in range(3)}
    rows = (
        ("1+m00+m11+m22", "m21-m12", "m02-m20", "m10-m01"),
        ("m21-m12", "1+m00-m11-m22", "m01+m10", "m02+m20"),
        ("m02-m20", "m01+m10", "1-m00+m11-m22", "m12+m21"),
        ("m10-m01", "m02+m20", "m12+m21", "1-m00-m11+m22"),
    )
    k = np.zeros((9, 16))
    c = np.zeros(16)
    for i, row in enumerate(rows):
        for j, expr in enumerate(row):
            for term in expr.replace("-", "+-").split("+"):
                if not term:
                    continue
                sign = -1.0 if term.startswith("-") else 1.0
                name = term.lstrip("-")
                if name == "1":
                    c[4 * i + j] += sign
                else:
                    k[e[name], 4 * i + j] += sign
    pick = np.zeros((9, 4))
    pick[[0, 4, 8], 0] = 1.0
    pick[0, 1] = pick[4, 2] = pick[8, 3] = 1.0
    return k, c, pick


_M2Q, _M2Q_CONST, _M2Q_PICK = _from_matrix_maps()


def quat_from_matrix(m: ArrayLike) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` (scalar part >= 0) of rotation matrices ``(..., 3, 3)``."""
    m = np.asarray(m, np.float64)
    lead = m.shape[:-2]
    flat = m.reshape(-1, 9)
    cand = (flat @ _M2Q + _M2Q_CONST).reshape(-1, 4, 4)
    best = np.argmax(flat @ _M2Q_PICK, axis=1)
    q = cand[np.arange(len(cand)), best]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, :1] < 0.0, -1.0, 1.0)
    return q.reshape((*lead, 4))


def quat_from_axis_angle(axis: ArrayLike, angle: ArrayLike) -> np.ndarray:
    """Quaternions turning by ``angle`` (radians) about ``axis`` (``(3,)`` or ``(..., 3)``, normalised here).

    Raises:
        ValueError: if an axis is zero.
    """
    axis = np.asarray(axis, np.float64)
    n = np.linalg.norm(axis, axis=-1, keepdims=True)
    if np.any(n < 1e-12):
        raise ValueError("rotation axis must be non-zero")
    half = 0.5 * np.asarray(angle, np.float64)[..., None]
    return np.concatenate([np.cos(half) * np.ones_like(n), np.sin(half) * axis / n], axis=-1)


def quat_slerp(a: ArrayLike, b: ArrayLike, t: ArrayLike) -> np.ndarray:
    """Spherical interpolation from ``a`` to ``b`` (the shorter way) at fraction ``t``, broadcast.

    ``t`` has the shape of the quaternions without their last axis (or broadcasts to it).
    """
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    t = np.asarray(t, np.float64)[..., None]
    d = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(d < 0.0, -b, b)
    d = np.minimum(np.abs(d), 1.0)
    theta = np.arccos(d)
    sin_t = np.sin(theta)
    small = sin_t < 1e-6
    safe = np.where(small, 1.0, sin_t)
    wa = np.where(small, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    wb = np.where(small, t, np.sin(t * theta) / safe)
    out = wa * a + wb * b
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def quat_exp(rotvec: ArrayLike) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` of rotation vectors ``(..., 3)`` (axis times angle, radians); ``w >= 0``
    for angles up to pi."""
    v = np.asarray(rotvec, np.float64)
    ang = np.linalg.norm(v, axis=-1, keepdims=True)
    small = ang < 1e-6
    # sin(ang / 2) / ang, with its series near 0
    k = np.where(small, 0.5 - ang * ang / 48.0, np.sin(0.5 * ang) / np.where(small, 1.0, ang))
    return np.concatenate([np.cos(0.5 * ang), k * v], axis=-1)


def quat_log(q: ArrayLike) -> np.ndarray:
    """Rotation vectors ``(..., 3)`` of unit quaternions, taken on the ``w >= 0`` hemisphere (angle in [0, pi])."""
    q = np.asarray(q, np.float64)
    q = np.where(q[..., :1] < 0.0, -q, q)
    w = np.clip(q[..., :1], -1.0, 1.0)
    u = q[..., 1:]
    s = np.linalg.norm(u, axis=-1, keepdims=True)
    ang = 2.0 * np.arctan2(s, w)
    small = s < 1e-9
    k = np.where(small, 2.0 / np.where(small, np.maximum(w, 1e-300), 1.0), ang / np.where(small, 1.0, s))
    return k * u
