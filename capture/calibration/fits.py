"""The fits that produce a calibration: the mounting from a still pose
(:func:`mounting_from_gravity`), the accelerometer offset and scale/misalignment from several still
poses (:func:`fit_accelerometer`, :class:`AccelFit`), and the magnetometer hard and soft iron from a
rotation dance (:func:`fit_magnetometer`, :class:`MagFit`), each refined by scipy least squares."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from capture.calibration.frames import G0
from capture.errors import ConfigError

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

log = logging.getLogger(__name__)


def mounting_from_gravity(acc_still: ArrayLike, segment_down: ArrayLike = (0.0, 0.0, -1.0),
                          sensor_forward: ArrayLike | None = None,
                          segment_forward: ArrayLike = (1.0, 0.0, 0.0)) -> tuple[float, float, float, float]:
    """Mounting rotation (sensor -> segment) from a still pose: the rotation that maps the measured
    gravity direction onto the segment's down axis.

    The accelerometer at rest reads the reaction to gravity (pointing up), so gravity in the sensor
    frame is ``-acc``. With only gravity the rotation about the down axis is free: the smallest
    rotation is returned, unless ``sensor_forward`` (a sensor axis that should point along
    ``segment_forward``) fixes it.

    Args:
        acc_still: mean accelerometer reading (3,) or samples (n, 3) of the still pose, any unit.
        segment_down: the segment axis that points down in that pose.
        sensor_forward: optional sensor-frame direction that should map onto ``segment_forward``.
        segment_forward: see ``sensor_forward``.

    Returns:
        The mounting quaternion ``(w, x, y, z)``.

    Raises:
        ConfigError: the accelerometer reading is zero or not finite, or the forward axis is
            parallel to gravity.
    """
    a = np.asarray(acc_still, np.float64)
    if a.ndim == 2:
        a = a.mean(axis=0)
    n = float(np.linalg.norm(a)) if a.shape == (3,) else 0.0
    if not (n > 0 and math.isfinite(n)):
        raise ConfigError(f"mounting reset needs a non-zero, finite accelerometer reading, got {a.tolist()}")
    down_s = -a / n
    down_b = np.asarray(segment_down, np.float64)
    down_b = down_b / np.linalg.norm(down_b)
    if sensor_forward is None:
        r, _ = Rotation.align_vectors(down_b[None, :], down_s[None, :])
    else:
        f = np.asarray(sensor_forward, np.float64)
        if np.linalg.norm(np.cross(f, down_s)) < 1e-3 * np.linalg.norm(f):
            raise ConfigError("mounting reset: the sensor forward axis is parallel to gravity")
        r, _ = Rotation.align_vectors(np.stack([down_b, np.asarray(segment_forward, np.float64)]),
                                      np.stack([down_s, f]), weights=[np.inf, 1.0])
    q = r.as_quat(scalar_first=True)
    if q[0] < 0:
        q = -q
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


@dataclass(frozen=True)
class AccelFit:
    """Accelerometer calibration from still poses: ``acc_c = matrix @ (acc - offset)``.

    Attributes:
        offset: m/s^2 (3,).
        matrix: 3x3 (upper triangular for the ``full`` model, diagonal for ``diagonal``).
        residual_rms: rms of ``|acc_c| - g`` over the poses, m/s^2.
        raw_rms: the same before calibration.
        poses: poses used; distinct: distinct orientations among them.
        model: ``full`` or ``diagonal``.
    """

    offset: np.ndarray
    matrix: np.ndarray
    residual_rms: float
    raw_rms: float
    poses: int
    distinct: int
    model: str


def _distinct_directions(u: np.ndarray, min_angle_deg: float) -> int:
    reps: list[np.ndarray] = []
    c = math.cos(math.radians(min_angle_deg))
    for v in u:
        if all(float(v @ r) < c for r in reps):
            reps.append(v)
    return len(reps)


def fit_accelerometer(poses: ArrayLike, *, g: float = G0, model: str = "auto", min_angle_deg: float = 20.0,
                      source: str | None = None) -> AccelFit:
    """Offset and scale/misalignment of an accelerometer from its mean readings in several still
    orientations (least squares on ``|matrix @ (a - offset)| = g`` with scipy).

    Args:
        poses: (k, 3) mean readings, m/s^2, one per still orientation (see :func:`still_poses`).
        g: the local gravity, m/s^2.
        model: ``diagonal`` (offset + 3 scales, 6 unknowns), ``full`` (offset + upper-triangular
            scale/misalignment, 9 unknowns) or ``auto`` (``full`` from 12 distinct orientations).
        min_angle_deg: poses closer than this count as the same orientation.
        source: the stream, for error messages.

    Raises:
        ConfigError: too few distinct orientations for the model, an axis never seen pointing both
            up and down, non-finite data, or an unknown model.
    """
    a = np.asarray(poses, np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ConfigError(f"accelerometer fit: poses must be (k, 3), got {a.shape}", source=source)
    if not np.all(np.isfinite(a)):
        raise ConfigError("accelerometer fit: poses contain non-finite values", source=source)
    if model not in ("auto", "full", "diagonal"):
        raise ConfigError(f"accelerometer fit: unknown model {model!r} (auto, full, diagonal)", source=source)
    norms = np.linalg.norm(a, axis=1)
    if np.any(norms <= 0):
        raise ConfigError("accelerometer fit: a pose reads zero", source=source)
    u = a / norms[:, None]
    distinct = _distinct_directions(u, min_angle_deg)
    if model == "auto":
        model = "full" if distinct >= 12 else "diagonal"
    need = 9 if model == "full" else 6
    if distinct < need:
        raise ConfigError(f"accelerometer fit ({model}) needs at least {need} distinct still orientations "
                          f"(>{min_angle_deg:.0f} deg apart), got {distinct} of {a.shape[0]} poses: turn the sensor "
                          f"to more faces and hold each still", source=source)
    missing = [f"{'+' if s > 0 else '-'}{'xyz'[i]}" for i in range(3) for s in (1, -1)
               if not np.any(s * u[:, i] >= 0.5)]
    if missing:
        raise ConfigError(f"accelerometer fit: orientations too similar: no pose with the {', '.join(missing)} "
                          f"axis pointing (within 60 deg) up; every axis must be seen both up and down", source=source)
    iu = np.triu_indices(3)
    diag_pos = [0, 3, 5]  # positions of the diagonal among the upper-triangular entries

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        off = p[:3]
        mat = np.zeros((3, 3))
        if model == "full":
            mat[iu] = p[3:9]
        else:
            mat[np.diag_indices(3)] = p[3:6]
        return off, mat

    def res(p: np.ndarray) -> np.ndarray:
        off, mat = unpack(p)
        r: np.ndarray = np.linalg.norm((a - off) @ mat.T, axis=1) - g
        return r

    p0 = np.zeros(9 if model == "full" else 6)
    if model == "full":
        p0[3:][diag_pos] = 1.0
    else:
        p0[3:6] = 1.0
    r = least_squares(res, p0, x_scale="jac")
    off, mat = unpack(r.x)
    rms = float(np.sqrt(np.mean(res(r.x) ** 2)))
    raw = float(np.sqrt(np.mean((norms - g) ** 2)))
    if rms > 0.05 * g:
        log.warning("accelerometer fit residual %.3f m/s^2 is large: were the poses still?", rms)
    return AccelFit(off, mat, rms, raw, int(a.shape[0]), distinct, model)


@dataclass(frozen=True)
class MagFit:
    """Magnetometer hard- and soft-iron calibration: ``mag_c = soft_iron @ (mag - hard_iron)``.

    Attributes:
        hard_iron: (3,) in the input unit.
        soft_iron: symmetric 3x3 (a multiple of identity for the ``sphere`` model); calibrated
            readings have magnitude ``field``.
        field: fitted field magnitude, input unit.
        model: ``ellipsoid`` (hard + soft iron) or ``sphere`` (hard iron only).
        coverage: fraction of 100 evenly spread directions with a sample within 25 deg (around the
            fitted centre), 0-1.
        planarity: smallest / largest eigenvalue of the centred readings' covariance (0 for a dance
            in one plane, about 1 for a full sphere).
        residual_rms: rms of ``|mag_c| / field - 1`` over the inliers.
        spread_before: std / mean of ``|mag|`` before (inliers).
        spread_after: std / mean of ``|mag_c|`` after (inliers).
        inliers: samples kept (outliers, i.e. magnetic disturbances, are trimmed at 4 robust sigmas).
    """

    hard_iron: np.ndarray
    soft_iron: np.ndarray
    field: float
    model: str
    coverage: float
    planarity: float
    residual_rms: float
    spread_before: float
    spread_after: float
    inliers: int


def _fib_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z * z)
    phi = math.pi * (3 - math.sqrt(5)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _coverage(d: np.ndarray, angle_deg: float = 25.0) -> float:
    grid = _fib_sphere(100)
    c = math.cos(math.radians(angle_deg))
    hit = np.zeros(len(grid), bool)
    for k in range(0, len(d), 4096):
        hit |= (grid @ d[k:k + 4096].T >= c).any(axis=1)
    return float(hit.mean())


def _sphere_fit(x: np.ndarray) -> np.ndarray:
    """Algebraic sphere fit: centre (3,)."""
    A = np.column_stack([2 * x, np.ones(len(x))])  # |x|^2 = A (2c, r^2 - |c|^2)
    p: np.ndarray = np.linalg.lstsq(A, (x * x).sum(axis=1), rcond=None)[0]
    return p[:3]


def fit_magnetometer(mag: ArrayLike, *, model: str = "auto", min_coverage: float = 0.25,
                     min_planarity: float = 0.05, ellipsoid_coverage: float = 0.5, min_samples: int = 50,
                     source: str | None = None) -> MagFit:
    """Hard- and soft-iron fit from a rotation dance: an algebraic ellipsoid (or sphere) fit, refined
    by scipy least squares on the radial error, with outliers (magnetic disturbances) trimmed.

    A full ellipsoid (9 unknowns) is only determined when the readings cover the sphere; from a
    partial dance (a hand-held sensor turned mostly about one axis) it is ill-conditioned, so
    ``auto`` fits the ellipsoid when coverage >= ``ellipsoid_coverage`` and planarity >= 0.2 and
    only the hard iron (a sphere, 4 unknowns) otherwise.

    Args:
        mag: (n, 3) raw magnetometer readings (NaN rows are dropped).
        model: ``auto``, ``ellipsoid`` or ``sphere``.
        min_coverage: least direction coverage accepted (see :class:`MagFit`).
        min_planarity: least planarity accepted (a dance in one plane cannot fix the offset
            perpendicular to it).
        ellipsoid_coverage: coverage from which ``auto`` fits soft iron too.
        min_samples: fewest samples accepted.
        source: the stream, for error messages.

    Raises:
        ConfigError: too few samples, poor coverage or a planar dance (the message gives the
            figures and what to do), an ellipsoid asked for but not determined, or an unknown model.
    """
    if model not in ("auto", "ellipsoid", "sphere"):
        raise ConfigError(f"magnetometer fit: unknown model {model!r} (auto, ellipsoid, sphere)", source=source)
    m = np.asarray(mag, np.float64)
    if m.ndim != 2 or m.shape[1] != 3:
        raise ConfigError(f"magnetometer fit: mag must be (n, 3), got {m.shape}", source=source)
    m = m[np.isfinite(m).all(axis=1)]
    if m.shape[0] < min_samples:
        raise ConfigError(f"magnetometer fit needs at least {min_samples} readings, got {m.shape[0]}", source=source)
    mc0 = m.mean(axis=0)
    scale = float(np.median(np.linalg.norm(m - mc0, axis=1))) or 1.0
    x = (m - mc0) / scale
    c = _sphere_fit(x)
    d = x - c
    cov = _coverage(d / np.linalg.norm(d, axis=1, keepdims=True))
    ev = np.linalg.eigvalsh(np.cov(d.T))
    planarity = float(ev[0] / ev[2]) if ev[2] > 0 else 0.0
    if cov < min_coverage:
        raise ConfigError(f"magnetometer fit: poor coverage: the readings span {cov:.2f} of all directions, need "
                          f"{min_coverage:.2f}; rotate the sensor slowly through every orientation (a figure-of-eight "
                          f"about all axes)", source=source)
    if planarity < min_planarity:
        raise ConfigError(f"magnetometer fit: the dance stayed in one plane (planarity {planarity:.3f}, need "
                          f"{min_planarity:.2f}), so the offset across that plane is unknown; tilt the sensor out of "
                          f"the plane too", source=source)
    if model == "auto":
        model = "ellipsoid" if cov >= ellipsoid_coverage and planarity >= 0.2 else "sphere"
    iu = np.triu_indices(3)
    if model == "ellipsoid":
        # the quadric x^T A x + 2 b^T x = 1 by linear least squares, D v = 1, v = (A's six entries, b)
        D = np.column_stack([x[:, 0] ** 2, x[:, 1] ** 2, x[:, 2] ** 2,
                             2 * x[:, 0] * x[:, 1], 2 * x[:, 0] * x[:, 2], 2 * x[:, 1] * x[:, 2],
                             2 * x[:, 0], 2 * x[:, 1], 2 * x[:, 2]])
        v, *_ = np.linalg.lstsq(D, np.ones(len(x)), rcond=None)
        A = np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
        if not np.all(np.linalg.eigvalsh(A) > 0):
            raise ConfigError(f"magnetometer fit: the readings do not determine an ellipsoid (coverage {cov:.2f}); "
                              f"use model='sphere' (hard iron only) or rotate through more orientations", source=source)
        c = -np.linalg.solve(A, v[6:9])
        k = 1.0 + float(c @ A @ c)
        if k <= 0:
            raise ConfigError("magnetometer fit: degenerate ellipsoid", source=source)
        w, V = np.linalg.eigh(A / k)
        p = np.concatenate([c, (V @ np.diag(np.sqrt(w)) @ V.T)[iu]])
    else:
        p = np.concatenate([c, [1.0 / float(np.median(np.linalg.norm(d, axis=1)))]])

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if model == "sphere":
            return p[:3], p[3] * np.eye(3)
        S = np.zeros((3, 3))  # the soft iron of mag_c = S (mag - hard)
        S[iu] = p[3:]
        return p[:3], S + S.T - np.diag(np.diag(S))

    def res(p: np.ndarray, xs: np.ndarray) -> np.ndarray:
        cc, S = unpack(p)
        r: np.ndarray = np.linalg.norm((xs - cc) @ S.T, axis=1) - 1.0
        return r

    inl = np.ones(len(x), bool)
    for _ in range(4):
        p = least_squares(res, p, args=(x[inl],), loss="soft_l1", f_scale=0.05).x
        e = res(p, x)
        med = float(np.median(e[inl]))
        mad = 1.4826 * float(np.median(np.abs(e[inl] - med))) + 1e-12
        new = np.abs(e - med) <= 4 * mad
        if np.array_equal(new, inl):
            break
        inl = new
    cc, S = unpack(p)
    det = float(np.linalg.det(S))
    if not det > 0 or not np.all(np.linalg.eigvalsh(S) > 0):
        raise ConfigError("magnetometer fit: the fitted soft-iron matrix is not positive definite", source=source)
    hard = mc0 + cc * scale
    # scaled so calibrated magnitudes equal the geometric-mean radius of the raw ellipsoid
    field_ = scale * det ** (-1.0 / 3.0)
    soft = S * (field_ / scale)
    mi = m[inl]
    before = np.linalg.norm(mi, axis=1)
    after = np.linalg.norm((mi - hard) @ soft.T, axis=1)
    return MagFit(hard, soft, field_, model, cov, planarity, float(np.sqrt(np.mean((after / field_ - 1.0) ** 2))),
                  float(before.std() / before.mean()), float(after.std() / after.mean()), int(inl.sum()))
