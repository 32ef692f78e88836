"""The character model the puppet moves: ``Skeleton`` (joint tree, rest offsets, forward kinematics, Unity
bone names, stretched bones), ``Clip`` (root path and local joint rotations over time, foot contacts and
key-times), the default ``humanoid()`` and the quadratic Bezier spine of the variable-bone-length puppet.

Conventions: metres, seconds, radians; quaternions are scalar-first ``(w, x, y, z)`` (scipy's ``Rotation``
is scalar-last and is converted at the boundary); Y is up and the character faces +Z, so its left is +X.
A joint's offset is the bone from its parent to it, in the parent's frame at rest; a joint's local rotation
turns everything below it. With every local rotation the identity the humanoid stands in a T-pose.
Quaternion maths is :mod:`capture.quat`.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal, overload

import numpy as np

from capture.quat import (
    quat_from_matrix,
    quat_slerp,
    quat_to_matrix,
    quat_to_matrix_components,
)

if TYPE_CHECKING:
    from retarget._types import BoolArray, FloatArray, IntArray

__all__ = [
    "HUMANOID_JOINTS",
    "UNITY_HUMAN_BONES",
    "Clip",
    "Skeleton",
    "bezier_control",
    "bezier_spine",
    "guess_unity_names",
    "humanoid",
]

# ------------------------------------------------------------------------------------------------ names

UNITY_HUMAN_BONES: tuple[str, ...] = (
    "Hips", "Spine", "Chest", "UpperChest", "Neck", "Head", "Jaw", "LeftEye", "RightEye",
    *(f"{side}{bone}" for side in ("Left", "Right") for bone in (
        "Shoulder", "UpperArm", "LowerArm", "Hand", "UpperLeg", "LowerLeg", "Foot", "Toes",
        *(f"{finger}{seg}" for finger in ("Thumb", "Index", "Middle", "Ring", "Little")
          for seg in ("Proximal", "Intermediate", "Distal")))),
)
"""Unity's ``HumanBodyBones`` names (the VMC protocol's bone names)."""

# The cgspeed/CMU BVH conversion: "LeftShoulder" there is the upper arm, so it is recognised as a whole.
_CMU_UNITY = {
    "Hips": "Hips", "LeftHip": "LeftUpperLeg", "LeftKnee": "LeftLowerLeg", "LeftAnkle": "LeftFoot",
    "LeftToe": "LeftToes", "RightHip": "RightUpperLeg", "RightKnee": "RightLowerLeg",
    "RightAnkle": "RightFoot", "RightToe": "RightToes", "lowerback": "Spine", "Chest": "Chest",
    "Chest2": "UpperChest", "Neck": "Neck", "Head": "Head", "LeftCollar": "LeftShoulder",
    "LeftShoulder": "LeftUpperArm", "LeftElbow": "LeftLowerArm", "LeftWrist": "LeftHand",
    "RightCollar": "RightShoulder", "RightShoulder": "RightUpperArm", "RightElbow": "RightLowerArm",
    "RightWrist": "RightHand", "LThumb": "LeftThumbProximal", "RThumb": "RightThumbProximal",
}
# Mixamo-style names (after any "prefix:" is dropped).
_MIXAMO_UNITY = {
    "UpLeg": "UpperLeg", "Leg": "LowerLeg", "ToeBase": "Toes", "Arm": "UpperArm", "ForeArm": "LowerArm",
}


def guess_unity_names(names: tuple[str, ...] | list[str]) -> dict[str, str]:
    """Map joint names of a foreign rig to Unity ``HumanBodyBones`` names where the rig is recognised.

    Recognised: names that already are Unity names, the cgspeed/CMU BVH rig (``LeftCollar``/``LHipJoint``)
    and Mixamo-style names (``LeftUpLeg``, ``LeftForeArm``, ``Spine1``, optionally with a ``prefix:``).
    Unrecognised joints are left out.

    Args:
        names: the joint names.

    Returns:
        joint name -> Unity bone name, each Unity name used at most once.
    """
    names = list(names)
    unity = set(UNITY_HUMAN_BONES)
    out: dict[str, str] = {}
    if "LeftCollar" in names or "LHipJoint" in names:
        out = {n: _CMU_UNITY[n] for n in names if n in _CMU_UNITY}
    else:
        spine_n = {"Spine": "Spine", "Spine1": "Chest", "Spine2": "UpperChest"}
        for n in names:
            base = n.rsplit(":", 1)[-1]
            if base in spine_n:
                cand = spine_n[base]
            elif base in unity:
                cand = base
            else:
                side = "Left" if base.startswith("Left") else "Right" if base.startswith("Right") else ""
                rest = base[len(side):]
                cand = f"{side}{_MIXAMO_UNITY[rest]}" if side and rest in _MIXAMO_UNITY else ""
            if cand in unity:
                out[n] = cand
    used: set[str] = set()
    result = {}
    for n, u in out.items():
        if u not in used:
            used.add(u)
            result[n] = u
    return result


# --------------------------------------------------------------------------------------------- skeleton

_FEW_FRAMES = 16  # up to this many frames FK composes 4x4 transforms; beyond, it goes level by level


@dataclass(frozen=True, eq=False)
class Skeleton:
    """A joint tree in parent-before-child order with rest offsets.

    Args:
        names: joint names, unique, the root first.
        parents: ``(J,)`` parent index per joint, ``-1`` for the root (only joint 0), each smaller than
            the joint's own index.
        offsets: ``(J, 3)`` metres, the bone from the parent to the joint in the parent's frame at rest;
            the root's offset is added to the root position.
        unity_names: joint name -> Unity ``HumanBodyBones`` name for the joints that have one.

    Raises:
        ValueError: on a shape, order, name or value that breaks the above.
    """

    names: tuple[str, ...]
    parents: IntArray
    offsets: FloatArray
    unity_names: Mapping[str, str] = field(default_factory=dict)
    # derived in __post_init__: joint name -> index, and the two forward-kinematics schedules
    _index: dict[str, int] = field(init=False, repr=False)
    _jumps: tuple[IntArray, ...] = field(init=False, repr=False)
    _levels: tuple[tuple[IntArray, IntArray, FloatArray], ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        names = tuple(str(n) for n in self.names)
        if not names:
            raise ValueError("a skeleton needs at least one joint")
        if len(set(names)) != len(names):
            raise ValueError("joint names must be unique")
        parents = np.array(self.parents, dtype=np.int64).reshape(-1)
        offsets = np.array(self.offsets, dtype=np.float64)
        n = len(names)
        if parents.shape != (n,):
            raise ValueError(f"parents must have shape ({n},), got {parents.shape}")
        if offsets.shape != (n, 3):
            raise ValueError(f"offsets must have shape ({n}, 3), got {offsets.shape}")
        if not np.all(np.isfinite(offsets)):
            raise ValueError("offsets must be finite")
        if parents[0] != -1:
            raise ValueError("joint 0 must be the root (parent -1)")
        idx = np.arange(n)
        if np.any(parents[1:] < 0) or np.any(parents[1:] >= idx[1:]):
            raise ValueError("every non-root joint needs a parent listed before it")
        unity = dict(self.unity_names)
        bad = [k for k in unity if k not in names]
        if bad:
            raise ValueError(f"unity_names has unknown joints: {bad}")
        known = set(UNITY_HUMAN_BONES)
        bad = [v for v in unity.values() if v not in known]
        if bad:
            raise ValueError(f"unity_names has names that are not Unity HumanBodyBones: {bad}")
        if len(set(unity.values())) != len(unity):
            raise ValueError("unity_names maps two joints to the same Unity bone")
        parents.setflags(write=False)
        offsets.setflags(write=False)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "parents", parents)
        object.__setattr__(self, "offsets", offsets)
        object.__setattr__(self, "unity_names", unity)
        object.__setattr__(self, "_index", {name: i for i, name in enumerate(names)})
        # pointer jumping for forward kinematics: after step k every joint's transform covers 2**k
        # ancestors, so a chain of depth d takes ceil(log2(d + 1)) batched matrix products
        ptr = np.append(np.where(parents < 0, n, parents), n)
        jumps = []
        while np.any(ptr[:n] != n):
            jumps.append(ptr.copy())
            ptr = ptr[ptr]
        object.__setattr__(self, "_jumps", tuple(jumps))
        # level by level (all joints of one depth at once) for many frames
        depth = np.zeros(n, dtype=np.int64)
        for j in range(1, n):
            depth[j] = depth[parents[j]] + 1
        levels = []
        for d in range(1, int(depth.max()) + 1):
            js = np.flatnonzero(depth == d)
            levels.append((js, parents[js], np.ascontiguousarray(offsets[js].T)[None, :, :, None]))
        object.__setattr__(self, "_levels", tuple(levels))

    def __repr__(self) -> str:
        return f"Skeleton({len(self.names)} joints, root={self.names[0]!r})"

    def __len__(self) -> int:
        return len(self.names)

    @property
    def n_joints(self) -> int:
        """Number of joints."""
        return len(self.names)

    def index(self, name: str) -> int:
        """Index of a joint.

        Raises:
            ValueError: if there is no joint of that name.
        """
        try:
            return self._index[name]
        except KeyError:
            raise ValueError(f"no joint named {name!r}") from None

    def children(self, joint: str | int) -> tuple[int, ...]:
        """Indices of the direct children of a joint (by name or index)."""
        j = self.index(joint) if isinstance(joint, str) else int(joint)
        return tuple(int(i) for i in np.flatnonzero(self.parents == j))

    def bone_lengths(self) -> FloatArray:
        """``(J,)`` length of the bone ending at each joint (the root's offset length for the root)."""
        lengths: FloatArray = np.linalg.norm(self.offsets, axis=1)
        return lengths

    def rest_positions(self) -> FloatArray:
        """``(J, 3)`` world positions with every rotation the identity and the root position at 0."""
        return self.fk(np.zeros(3), np.tile([1.0, 0.0, 0.0, 0.0], (len(self.names), 1)))

    def with_bone_lengths(self, scale: Mapping[str, float] | FloatArray) -> Skeleton:
        """A copy with stretched (or shrunk) bones, e.g. a longer neck for a bigger head.

        Args:
            scale: factor per joint, as ``{joint name: factor}`` (others keep 1) or a ``(J,)`` array.
                The factor of joint ``j`` scales the bone from its parent to ``j`` (its offset).

        Returns:
            the new skeleton (same names, parents and Unity names).

        Raises:
            ValueError: for an unknown joint name, a wrong shape, or a factor that is not finite and > 0.
        """
        n = len(self.names)
        if isinstance(scale, Mapping):
            f = np.ones(n)
            for name, v in scale.items():
                f[self.index(name)] = float(v)
        else:
            f = np.asarray(scale, np.float64)
            if f.shape != (n,):
                raise ValueError(f"scale must have shape ({n},), got {f.shape}")
        if not np.all(np.isfinite(f)) or np.any(f <= 0):
            raise ValueError("bone length factors must be finite and > 0")
        return Skeleton(self.names, self.parents, self.offsets * f[:, None], dict(self.unity_names))

    @overload
    def fk(self, root_pos: FloatArray, rotations: FloatArray, *, world_rotations: Literal[False] = False
           ) -> FloatArray: ...

    @overload
    def fk(self, root_pos: FloatArray, rotations: FloatArray, *, world_rotations: Literal[True]
           ) -> tuple[FloatArray, FloatArray]: ...

    def fk(self, root_pos: FloatArray, rotations: FloatArray, *, world_rotations: bool = False
           ) -> FloatArray | tuple[FloatArray, FloatArray]:
        """Forward kinematics, vectorised over frames.

        Args:
            root_pos: ``(3,)`` or ``(F, 3)`` root position (the root's offset is added).
            rotations: ``(J, 4)`` or ``(F, J, 4)`` local joint rotations (unit quaternions).
            world_rotations: also return the world rotation of every joint.

        Returns:
            world positions ``(J, 3)`` or ``(F, J, 3)``; with ``world_rotations`` a pair
            ``(positions, rotations (..., J, 4))``.

        Raises:
            ValueError: if the shapes do not fit the skeleton or each other.
        """
        root_pos = np.asarray(root_pos, np.float64)
        rotations = np.asarray(rotations, np.float64)
        n = len(self.names)
        single = rotations.ndim == 2
        if single:
            if rotations.shape != (n, 4) or root_pos.shape != (3,):
                raise ValueError(f"expected root_pos (3,) and rotations ({n}, 4), got {root_pos.shape} "
                                 f"and {rotations.shape}")
            rotations = rotations[None]
            root_pos = root_pos[None]
        elif rotations.ndim != 3 or rotations.shape[1:] != (n, 4) or root_pos.shape != (rotations.shape[0], 3):
            raise ValueError(f"expected root_pos (F, 3) and rotations (F, {n}, 4), got {root_pos.shape} "
                             f"and {rotations.shape}")
        f = rotations.shape[0]
        if f <= _FEW_FRAMES:
            pos, world = self._fk_jumps(root_pos, rotations)
        else:
            pos, world = self._fk_levels(root_pos, rotations)
        if single:
            pos = pos[0]
            world = world[0]
        if world_rotations:
            return pos, quat_from_matrix(world)
        return pos

    def _fk_jumps(self, root_pos: FloatArray, rotations: FloatArray) -> tuple[FloatArray, FloatArray]:
        # few frames: 4x4 transforms composed by pointer jumping (a few batched matrix products)
        n = len(self.names)
        a = np.zeros((rotations.shape[0], n + 1, 4, 4))
        a[:, :n, :3, :3] = quat_to_matrix(rotations)
        a[:, :n, :3, 3] = self.offsets
        a[:, 0, :3, 3] += root_pos
        a[:, :, 3, 3] = 1.0
        a[:, n, :3, :3] = np.eye(3)
        for ptr in self._jumps:
            a = np.matmul(a.take(ptr, axis=1), a)
        return a[:, :n, :3, 3].copy(), a[:, :n, :3, :3]

    def _fk_levels(self, root_pos: FloatArray, rotations: FloatArray) -> tuple[FloatArray, FloatArray]:
        # many frames: component-first arrays (3, 3, J, F), one depth level at a time
        n = len(self.names)
        local = quat_to_matrix_components(np.ascontiguousarray(rotations.transpose(2, 1, 0)))
        world = np.empty_like(local)
        pos = np.empty((3, n, rotations.shape[0]))
        world[:, :, 0] = local[:, :, 0]
        pos[:, 0] = (root_pos + self.offsets[0]).T
        for js, ps, off in self._levels:
            wp = world[:, :, ps]
            world[:, :, js] = (wp[:, :, None] * local[:, :, js][None]).sum(axis=1)
            pos[:, js] = pos[:, ps] + (wp * off).sum(axis=1)
        return pos.transpose(2, 1, 0).copy(), world.transpose(3, 2, 0, 1)


# ------------------------------------------------------------------------------------------------- clip


@dataclass(frozen=True, eq=False)
class Clip:
    """A motion on a skeleton: root path and local joint rotations sampled at ``fps``.

    Args:
        name: what the clip is ("walk", a file stem, ...).
        skeleton: the skeleton it animates.
        fps: frames per second (> 0).
        root_pos: ``(F, 3)`` root position per frame, metres.
        rotations: ``(F, J, 4)`` local joint rotations; normalised here (norms must be within 1e-3 of 1).
        contacts: ``{"left_foot": (F,) bool, "right_foot": ...}`` ground contacts, when known.
        key_times: increasing seconds from 0 to the duration (foot touch-downs for locomotion);
            empty means ``(0, duration)``.
        loop: whether the last frame joins the first (the root advancing by ``root_pos[-1] - root_pos[0]``).

    Raises:
        ValueError: on a shape or value that breaks the above.
        TypeError: if ``skeleton`` is not a ``Skeleton``.
    """

    name: str
    skeleton: Skeleton
    fps: float
    root_pos: FloatArray
    rotations: FloatArray
    contacts: Mapping[str, BoolArray] = field(default_factory=dict)
    key_times: tuple[float, ...] = ()
    loop: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.skeleton, Skeleton):
            raise TypeError("skeleton must be a Skeleton")
        fps = float(self.fps)
        if not np.isfinite(fps) or fps <= 0:
            raise ValueError(f"fps must be finite and > 0, got {self.fps}")
        root = np.array(self.root_pos, np.float64)
        rot = np.array(self.rotations, np.float64)
        j = self.skeleton.n_joints
        if rot.ndim != 3 or rot.shape[1:] != (j, 4) or rot.shape[0] < 1:
            raise ValueError(f"rotations must have shape (F, {j}, 4), got {rot.shape}")
        f = rot.shape[0]
        if root.shape != (f, 3):
            raise ValueError(f"root_pos must have shape ({f}, 3), got {root.shape}")
        if not (np.all(np.isfinite(root)) and np.all(np.isfinite(rot))):
            raise ValueError("root_pos and rotations must be finite")
        norms = np.linalg.norm(rot, axis=-1)
        if np.any(np.abs(norms - 1.0) > 1e-3):
            raise ValueError("rotations must be unit quaternions")
        rot /= norms[..., None]
        contacts = {}
        for k, v in dict(self.contacts).items():
            a = np.array(v, dtype=bool)
            if a.shape != (f,):
                raise ValueError(f"contacts[{k!r}] must have shape ({f},), got {a.shape}")
            a.setflags(write=False)
            contacts[str(k)] = a
        duration = (f - 1) / fps
        kt = tuple(float(t) for t in self.key_times) or ((0.0, duration) if f > 1 else (0.0,))
        tol = 1e-9 * max(1.0, duration)
        if abs(kt[0]) > tol or abs(kt[-1] - duration) > tol:
            raise ValueError(f"key_times must start at 0 and end at the duration {duration}, got {kt}")
        if any(b <= a for a, b in itertools.pairwise(kt)):
            raise ValueError(f"key_times must increase, got {kt}")
        kt = (0.0, *kt[1:-1], duration) if len(kt) > 1 else (0.0,)
        root.setflags(write=False)
        rot.setflags(write=False)
        object.__setattr__(self, "fps", fps)
        object.__setattr__(self, "root_pos", root)
        object.__setattr__(self, "rotations", rot)
        object.__setattr__(self, "contacts", contacts)
        object.__setattr__(self, "key_times", kt)
        object.__setattr__(self, "loop", bool(self.loop))

    def __repr__(self) -> str:
        return (f"Clip({self.name!r}, {self.n_frames} frames at {self.fps:g} fps, "
                f"{self.duration:.3f} s, loop={self.loop})")

    @property
    def n_frames(self) -> int:
        """Number of frames."""
        return int(self.rotations.shape[0])

    @property
    def duration(self) -> float:
        """Seconds from the first frame to the last."""
        return (self.n_frames - 1) / self.fps

    @property
    def times(self) -> FloatArray:
        """``(F,)`` frame times in seconds."""
        return np.arange(self.n_frames) / self.fps

    def positions(self) -> FloatArray:
        """``(F, J, 3)`` world joint positions of every frame."""
        return self.skeleton.fk(self.root_pos, self.rotations)

    def sample(self, t: float | FloatArray) -> tuple[FloatArray, FloatArray]:
        """The pose at time(s) ``t``, interpolated (linear root, slerp rotations).

        A looping clip wraps ``t`` and carries the root on by one cycle displacement per wrap, so playing
        it continuously walks on; a non-looping clip holds its first and last frames outside its span.

        Args:
            t: seconds, a scalar or an array.

        Returns:
            ``(root_pos (3,), rotations (J, 4))`` for a scalar, ``((N, 3), (N, J, 4))`` for ``N`` times.
        """
        t_arr = np.asarray(t, np.float64)
        scalar = t_arr.ndim == 0
        t_arr = np.atleast_1d(t_arr)
        n = self.n_frames
        if n == 1 or self.duration <= 0:
            root = np.repeat(self.root_pos[:1], len(t_arr), 0)
            rot = np.repeat(self.rotations[:1], len(t_arr), 0)
            return (root[0], rot[0]) if scalar else (root, rot)
        shift = np.zeros((len(t_arr), 3))
        if self.loop:
            cycles = np.floor(t_arr / self.duration)
            t_arr = t_arr - cycles * self.duration
            shift = cycles[:, None] * (self.root_pos[-1] - self.root_pos[0])
        u = np.clip(t_arr * self.fps, 0.0, n - 1)
        i0 = np.minimum(np.floor(u).astype(np.int64), n - 2)
        a = u - i0
        root = self.root_pos[i0] * (1 - a)[:, None] + self.root_pos[i0 + 1] * a[:, None] + shift
        rot = quat_slerp(self.rotations[i0], self.rotations[i0 + 1], np.broadcast_to(a[:, None],
                                                                                      (len(a), self.skeleton.n_joints)))
        return (root[0], rot[0]) if scalar else (root, rot)

    def root_speed(self) -> float:
        """Mean horizontal root speed in m/s: the net X-Z displacement over the duration (0 for one frame)."""
        if self.duration <= 0:
            return 0.0
        d = self.root_pos[-1] - self.root_pos[0]
        return float(np.hypot(d[0], d[2]) / self.duration)


# --------------------------------------------------------------------------------------------- humanoid

HUMANOID_JOINTS = 30
"""Joint count of ``humanoid()``: hips, spine (3), neck, head, and per side shoulder, upper arm, lower arm,
hand, four finger roots (thumb, index, middle, little), upper leg, lower leg, foot and toes."""

_REF_HEIGHT = 1.75

# Offsets for a 1.75 m character (metres, in the T-pose, +X is the character's left). Standing straight the
# ankle is 0.07 m and the ball of the foot (Toes) 0.015 m above the ground, the hips 0.98 m.
_HUMANOID_LEFT = (
    # name, parent, offset
    ("Shoulder", "UpperChest", (0.03, 0.10, -0.01)),
    ("UpperArm", "Shoulder", (0.15, 0.02, 0.0)),
    ("LowerArm", "UpperArm", (0.29, 0.0, 0.0)),
    ("Hand", "LowerArm", (0.25, 0.0, 0.0)),
    ("ThumbProximal", "Hand", (0.03, -0.01, 0.03)),
    ("IndexProximal", "Hand", (0.09, 0.0, 0.025)),
    ("MiddleProximal", "Hand", (0.095, 0.0, 0.005)),
    ("LittleProximal", "Hand", (0.08, 0.0, -0.035)),
)
_HUMANOID_LEGS = (
    ("UpperLeg", "Hips", (0.09, -0.05, 0.0)),
    ("LowerLeg", "UpperLeg", (0.0, -0.43, 0.0)),
    ("Foot", "LowerLeg", (0.0, -0.43, 0.0)),
    ("Toes", "Foot", (0.0, -0.055, 0.13)),
)
_HUMANOID_SPINE = (
    ("Hips", None, (0.0, 0.0, 0.0)),
    ("Spine", "Hips", (0.0, 0.10, 0.0)),
    ("Chest", "Spine", (0.0, 0.12, 0.0)),
    ("UpperChest", "Chest", (0.0, 0.12, 0.0)),
    ("Neck", "UpperChest", (0.0, 0.15, -0.01)),
    ("Head", "Neck", (0.0, 0.12, 0.01)),
)


def humanoid(height: float = _REF_HEIGHT) -> Skeleton:
    """The default 30-joint humanoid (``HUMANOID_JOINTS``), proportions scaled to ``height``.

    Joint names are Unity ``HumanBodyBones`` names, so ``unity_names`` maps each joint to itself. The root
    (Hips) offset is zero; standing straight the root is ``0.56 * height`` above the ground.

    Args:
        height: standing height in metres (top of the head).

    Returns:
        the skeleton, joints in parent-before-child order.

    Raises:
        ValueError: if ``height`` is not finite and > 0.
    """
    height = float(height)
    if not np.isfinite(height) or height <= 0:
        raise ValueError(f"height must be finite and > 0, got {height}")
    k = height / _REF_HEIGHT
    rows: list[tuple[str, str | None, tuple[float, float, float]]] = list(_HUMANOID_SPINE)
    for side, sx in (("Left", 1.0), ("Right", -1.0)):
        for name, parent, (x, y, z) in _HUMANOID_LEFT:
            par = parent if parent == "UpperChest" else side + parent
            rows.append((side + name, par, (sx * x, y, z)))
    for side, sx in (("Left", 1.0), ("Right", -1.0)):
        for name, parent, (x, y, z) in _HUMANOID_LEGS:
            par = parent if parent == "Hips" else side + parent
            rows.append((side + name, par, (sx * x, y, z)))
    names = tuple(r[0] for r in rows)
    index = {n: i for i, n in enumerate(names)}
    parents = np.array([-1 if r[1] is None else index[r[1]] for r in rows])
    offsets = np.array([r[2] for r in rows]) * k
    return Skeleton(names, parents, offsets, {n: n for n in names})


# ------------------------------------------------------------------------------------------ Bezier spine


def bezier_control(p_pelvis: FloatArray, p_chest: FloatArray, p_up: FloatArray, b: float = 0.3) -> FloatArray:
    """The middle control point of the spine curve (Ciccone 2019, section 6.3, eq. 6.4; the thesis uses b = 0.3).

    ``p1 = (p_pelvis + (1 - b) p_chest + b p_up) / 2``; with the chest upright (``p_chest == p_up``) it is
    the midpoint and the spine is straight.

    Args:
        p_pelvis: ``(3,)`` pelvis position (P0).
        p_chest: ``(3,)`` chest position (P2).
        p_up: ``(3,)`` where the chest would be if the character stood upright.
        b: how much the curve leans back towards upright, in ``[0, 1]``.

    Returns:
        ``(3,)`` the control point P1.

    Raises:
        ValueError: if ``b`` is outside ``[0, 1]`` or a point is not a finite 3-vector.
    """
    pts = [np.asarray(p, np.float64) for p in (p_pelvis, p_chest, p_up)]
    if any(p.shape != (3,) or not np.all(np.isfinite(p)) for p in pts):
        raise ValueError("points must be finite 3-vectors")
    if not 0.0 <= b <= 1.0:
        raise ValueError(f"b must be in [0, 1], got {b}")
    p0, p2, pu = pts
    return (p0 + (1.0 - b) * p2 + b * pu) / 2.0


def bezier_spine(p_pelvis: FloatArray, p_chest: FloatArray, p_up: FloatArray, s: FloatArray | float, *,
                 b: float = 0.3) -> FloatArray:
    """Points on the quadratic Bezier spine from pelvis to chest (variable bone lengths, Ciccone 2019, section 6.3).

    ``B(s) = (1-s)^2 P0 + 2 s (1-s) P1 + s^2 P2`` with ``P1 = bezier_control(...)``.

    Args:
        p_pelvis: ``(3,)`` P0.
        p_chest: ``(3,)`` P2.
        p_up: ``(3,)`` the upright chest position.
        s: curve parameter(s) in ``[0, 1]`` (0 at the pelvis, 1 at the chest).
        b: the lean-back weight of eq. 6.4.

    Returns:
        ``(3,)`` for a scalar ``s``, else ``(N, 3)``.

    Raises:
        ValueError: if ``s`` leaves ``[0, 1]`` or ``bezier_control`` refuses the points.
    """
    p1 = bezier_control(p_pelvis, p_chest, p_up, b)
    s_arr = np.asarray(s, np.float64)
    if np.any(~np.isfinite(s_arr)) or np.any(s_arr < 0) or np.any(s_arr > 1):
        raise ValueError("s must lie in [0, 1]")
    s1 = s_arr[..., None]
    p0 = np.asarray(p_pelvis, np.float64)
    p2 = np.asarray(p_chest, np.float64)
    return (1 - s1) ** 2 * p0 + 2 * s1 * (1 - s1) * p1 + s1 ** 2 * p2
