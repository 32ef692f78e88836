"""The MotionStick: an invisible stick from the phone to the grabbed object.

This module owns the MotionStick of Ciccone 2019, *Intuitive Control of Animated Scenes* (ETH Diss.
25792), section 6.2.1: a grabbed object keeps its distance and rotation relative to the phone, and the
stick shortens rather than let the object pass through the floor. How, is perfcap's
(``docs/design/puppet.md``): on grab the object's pose relative to the phone, ``X_rel = X_phone^-1 X_obj``,
and the stick length ``L0 = |X_rel.t|`` are kept; every frame the target is ``X_phone X_rel``. For
collisions the stick is ray-cast from the phone towards the object against the ground plane (and any
extra planes), and its length becomes ``L = min(L0, hit distance - clearance)``, so an object pushed into
the floor stops on it, along the same direction, and the stick returns to ``L0`` once clear. In grounded
states only the yaw of the target rotation is applied (the character stays upright); the full 6-DoF
target is always returned too (the ragdoll uses it as a spring on the held body).

Poses are 4x4 rigid transforms (numpy, metres), rotation in the upper-left 3x3 and translation in the last
column. Y is up; the heading ``theta`` turns +Z to ``(sin theta, 0, cos theta)``. Quaternions are
scalar-first ``(w, x, y, z)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

if TYPE_CHECKING:
    from collections.abc import Sequence

    from retarget._types import FloatArray

__all__ = [
    "MotionStick",
    "Plane",
    "StickTarget",
    "heading_of",
    "invert_transform",
    "make_transform",
    "pose_matrix",
    "yaw_matrix",
]

_RIGID_TOL = 1e-6



def _as_transform(x: object, name: str) -> FloatArray:
    """Check that ``x`` is a 4x4 rigid transform and return it as a float array.

    Raises:
        ValueError: wrong shape, non-finite values, a bottom row other than (0, 0, 0, 1) or a rotation block
            that is not a proper rotation.
    """
    m = np.asarray(x, dtype=float)
    if m.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 transform, got shape {m.shape}")
    # plain floats: for one 4x4 matrix this is several times cheaper than numpy's small-array calls
    rows = m.tolist()
    if not all(math.isfinite(v) for row in rows for v in row):
        raise ValueError(f"{name} has non-finite values")
    if max(abs(v - e) for v, e in zip(rows[3], (0.0, 0.0, 0.0, 1.0), strict=True)) > _RIGID_TOL:
        raise ValueError(f"{name} must have the bottom row (0, 0, 0, 1), got {m[3]}")
    (a, b, c, _), (d, e, f, _), (g, h, i, _) = rows[:3]
    gram = (a * a + d * d + g * g - 1.0, b * b + e * e + h * h - 1.0, c * c + f * f + i * i - 1.0,
            a * b + d * e + g * h, a * c + d * f + g * i, b * c + e * f + h * i)
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if max(abs(v) for v in gram) > 1e-5 or det < 0:
        raise ValueError(f"{name} rotation block is not a proper rotation")
    return m


def make_transform(rotation: object, translation: object) -> FloatArray:
    """Build a 4x4 transform from a 3x3 rotation matrix and a translation.

    Args:
        rotation: 3x3 rotation matrix.
        translation: 3-vector, metres.

    Returns:
        The 4x4 transform.

    Raises:
        ValueError: wrong shapes or not a proper rotation.
    """
    r = np.asarray(rotation, dtype=float)
    t = np.asarray(translation, dtype=float)
    if r.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"need a 3x3 rotation and a 3-vector, got {r.shape} and {t.shape}")
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = t
    return _as_transform(m, "transform")


def pose_matrix(position: object, quaternion: object) -> FloatArray:
    """Build a 4x4 transform from a position and a scalar-first unit quaternion ``(w, x, y, z)``.

    Args:
        position: 3-vector, metres.
        quaternion: ``(w, x, y, z)``; normalised here.

    Returns:
        The 4x4 transform.

    Raises:
        ValueError: wrong shapes, or a zero or non-finite quaternion.
    """
    q = np.asarray(quaternion, dtype=float)
    t = np.asarray(position, dtype=float)
    qs = q.tolist() if q.shape == (4,) else []
    norm = math.sqrt(sum(v * v for v in qs)) if qs else 0.0
    if not (math.isfinite(norm) and norm >= 1e-12):
        raise ValueError(f"quaternion must be a finite non-zero (w, x, y, z), got {quaternion!r}")
    ts = t.tolist() if t.shape == (3,) else []
    if not (ts and all(math.isfinite(v) for v in ts)):
        raise ValueError(f"position must be a finite 3-vector, got {position!r}")
    w, x, y, z = (v / norm for v in qs)
    # the rotation matrix of a unit quaternion: proper by construction, so no check is needed
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y), ts[0]],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x), ts[1]],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y), ts[2]],
                     [0.0, 0.0, 0.0, 1.0]])


def invert_transform(x: object) -> FloatArray:
    """Invert a rigid 4x4 transform (``R^T``, ``-R^T t``).

    Raises:
        ValueError: ``x`` is not a rigid 4x4 transform.
    """
    m = _as_transform(x, "transform")
    out = np.eye(4)
    out[:3, :3] = m[:3, :3].T
    out[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return out


def yaw_matrix(heading: float) -> FloatArray:
    """The 3x3 rotation by ``heading`` radians about +Y (sends +Z to ``(sin h, 0, cos h)``)."""
    c, s = math.cos(heading), math.sin(heading)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def heading_of(rotation: object) -> float:
    """The yaw of a rotation: the heading of its forward (+Z) axis projected on the ground.

    When the forward axis is (nearly) vertical, the twist about +Y of the swing-twist decomposition is used
    instead, so the heading stays defined.

    Args:
        rotation: 3x3 rotation matrix (or a 4x4 transform, whose rotation block is used).

    Returns:
        The heading in radians, in (-pi, pi].

    Raises:
        ValueError: not a 3x3 or 4x4 matrix.
    """
    r = np.asarray(rotation, dtype=float)
    if r.shape == (4, 4):
        r = r[:3, :3]
    if r.shape != (3, 3):
        raise ValueError(f"need a 3x3 rotation, got shape {r.shape}")
    fx, fz = float(r[0, 2]), float(r[2, 2])
    if math.hypot(fx, fz) > 1e-6:
        return math.atan2(fx, fz)
    _, y, _, w = Rotation.from_matrix(r).as_quat()  # scipy is scalar-last
    return 2.0 * math.atan2(y, w) if (w != 0.0 or y != 0.0) else 0.0


@dataclass(frozen=True, slots=True)
class Plane:
    """A collision plane ``{x : normal . x = offset}``; the free side is ``normal . x > offset``.

    Args:
        normal: the plane normal (normalised here), pointing to the free side.
        offset: the plane's signed distance from the origin along ``normal``, metres.

    Raises:
        ValueError: a zero or non-finite normal, or a non-finite offset.
    """

    normal: tuple[float, float, float]
    offset: float = 0.0

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=float)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) < 1e-12:
            raise ValueError(f"plane normal must be a finite non-zero 3-vector, got {self.normal!r}")
        if not math.isfinite(self.offset):
            raise ValueError(f"plane offset must be finite, got {self.offset!r}")
        n = n / np.linalg.norm(n)
        object.__setattr__(self, "normal", (float(n[0]), float(n[1]), float(n[2])))
        object.__setattr__(self, "offset", float(self.offset))

    @classmethod
    def ground(cls, height: float = 0.0) -> Plane:
        """The horizontal ground plane ``y = height`` (free side up)."""
        return cls((0.0, 1.0, 0.0), height)


@dataclass(frozen=True, slots=True)
class StickTarget:
    """Where the stick puts the object this frame.

    Attributes:
        pose: the 4x4 target to apply: the full ``X_phone X_rel`` rotation, or only its yaw when grounded;
            the translation is the (possibly shortened) stick end.
        full_pose: the full 6-DoF target at the (possibly shortened) stick end (the ragdoll spring target).
        length: the stick length used this frame, metres.
        rest_length: ``L0``, the length at grab time.
        heading: the yaw of the target rotation, radians.
        shortened: True when a plane shortened the stick this frame.
    """

    pose: FloatArray
    full_pose: FloatArray
    length: float
    rest_length: float
    heading: float
    shortened: bool


class MotionStick:
    """Holds a grabbed object at the end of an invisible stick from the phone.

    Args:
        ground_height: height of the ground plane ``y = ground_height``, metres.
        planes: extra collision planes (walls, tables), each with its normal towards the free side.
        clearance: how far the object's origin sits above its lowest point, metres (0 for a character whose
            root is between its feet). The stick stops when the object's lowest point touches a plane: the
            ray is cast against each plane moved out by ``clearance`` along its normal, which is
            ``hit distance - clearance`` measured along the normal, so it stays exact for oblique sticks.

    Raises:
        ValueError: a negative or non-finite clearance, or a non-finite ground height.
    """

    def __init__(self, *, ground_height: float = 0.0, planes: Sequence[Plane] = (),
                 clearance: float = 0.0) -> None:
        if not math.isfinite(ground_height):
            raise ValueError(f"ground_height must be finite, got {ground_height!r}")
        if not (math.isfinite(clearance) and clearance >= 0.0):
            raise ValueError(f"clearance must be finite and >= 0, got {clearance!r}")
        self.planes: tuple[Plane, ...] = (Plane.ground(ground_height), *planes)
        self.clearance = float(clearance)
        self._rel: FloatArray | None = None
        self._rest_length = 0.0

    @property
    def held(self) -> bool:
        """True between ``grab`` and ``release``."""
        return self._rel is not None

    @property
    def relative(self) -> FloatArray:
        """``X_rel = X_phone^-1 X_obj`` fixed at grab time (a copy).

        Raises:
            ValueError: nothing is held.
        """
        if self._rel is None:
            raise ValueError("the stick holds nothing")
        return self._rel.copy()

    @property
    def rest_length(self) -> float:
        """``L0 = |X_rel.t|``, metres (0 when nothing is held)."""
        return self._rest_length

    def grab(self, phone: object, obj: object) -> None:
        """Grab an object: keep its pose relative to the phone and the stick length.

        Args:
            phone: the phone's 4x4 world pose ``X_phone``.
            obj: the object's 4x4 world pose ``X_obj``.

        Raises:
            ValueError: either pose is not a rigid 4x4 transform.
        """
        x_phone = _as_transform(phone, "phone pose")
        x_obj = _as_transform(obj, "object pose")
        self._rel = invert_transform(x_phone) @ x_obj
        self._rest_length = float(np.linalg.norm(self._rel[:3, 3]))

    def release(self) -> None:
        """Let go (touch-up). Releasing when nothing is held does nothing."""
        self._rel = None
        self._rest_length = 0.0

    def ray_length(self, origin: object, direction: object, max_length: float) -> float:
        """Cast a ray against the planes and return how far the object may go along it.

        Args:
            origin: ray start (the phone), 3-vector.
            direction: unit 3-vector.
            max_length: the free length ``L0``.

        Returns:
            ``min(max_length, hit distance)`` over all planes moved out by ``clearance``; 0 when the origin is
            already behind a moved plane the ray points into.
        """
        o = np.asarray(origin, dtype=float)
        d = np.asarray(direction, dtype=float)
        length = float(max_length)
        for plane in self.planes:
            n = plane.normal
            denom = n[0] * d[0] + n[1] * d[1] + n[2] * d[2]
            if denom >= 0.0:
                continue  # moving away from (or along) the plane
            gap = n[0] * o[0] + n[1] * o[1] + n[2] * o[2] - plane.offset - self.clearance
            hit = max(0.0, gap / -denom)
            length = min(length, hit)
        return length

    def update(self, phone: object, *, grounded: bool = False) -> StickTarget:
        """The object's target for this frame.

        Args:
            phone: the phone's 4x4 world pose ``X_phone`` now.
            grounded: True in grounded states: the returned ``pose`` keeps only the yaw of the target
                rotation.

        Returns:
            The target (see ``StickTarget``).

        Raises:
            ValueError: nothing is held, or ``phone`` is not a rigid 4x4 transform.
        """
        if self._rel is None:
            raise ValueError("the stick holds nothing: grab() first")
        x_phone = _as_transform(phone, "phone pose")
        full = x_phone @ self._rel
        length = self._rest_length
        shortened = False
        if self._rest_length > 0.0:
            origin = x_phone[:3, 3]
            direction = (full[:3, 3] - origin) / self._rest_length
            length = self.ray_length(origin, direction, self._rest_length)
            if length < self._rest_length:
                shortened = True
                full[:3, 3] = origin + direction * length
        heading = heading_of(full[:3, :3])
        if grounded:
            pose = np.eye(4)
            pose[:3, :3] = yaw_matrix(heading)
            pose[:3, 3] = full[:3, 3]
        else:
            pose = full.copy()
        return StickTarget(pose=pose, full_pose=full, length=length, rest_length=self._rest_length,
                           heading=heading, shortened=shortened)
