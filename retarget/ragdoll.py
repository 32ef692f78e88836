"""A simple physical ragdoll: the puppet's default state when no animation fits the input.

The skeleton's joints become point masses (position Verlet) joined by rigid bones (iterated distance
constraints), pulled by gravity, stopped by the ground (with friction) and kept within joint limits (a
bone may bend at most ``max_bend`` away from its parent bone, enforced as a minimum distance between a
joint's grandparent and the joint). While the player still holds the puppet, the held joint is pulled
towards the MotionStick's end (a position constraint, stable at any time step). Every step is
deterministic for a given input.

:meth:`Ragdoll.rotations` turns the particle positions back into the skeleton's local rotations (each
bone swung from its rest direction; joints with several children aligned to all of them by least
squares), so the ragdoll feeds the same pose outputs (bus, BVH, VMC) as the animation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from capture.quat import cross, quat_from_matrix

if TYPE_CHECKING:
    from retarget._types import FloatArray, IntArray


@dataclass
class RagdollSettings:
    """Physical constants (SI units)."""

    gravity: float = 9.81
    damping: float = 1.5          # 1/s, velocity damping in the air
    friction: float = 8.0         # 1/s, horizontal damping while touching the ground
    radius: float = 0.05          # joint radius against the ground (m)
    max_bend_deg: float = 150.0   # joint limit: angle between a bone and its parent bone
    hold_rate: float = 60.0       # 1/s: how fast the held joint closes on the stick's end
    iterations: int = 5           # constraint passes per step
    rest_speed: float = 0.08      # m/s: below this (every joint) for rest_time it is at rest
    rest_time: float = 0.3


class Ragdoll:
    """Point-mass ragdoll of a skeleton.

    Args:
        parents: ``(J,)`` parent index per joint, -1 for the root; parents come before children.
        offsets: ``(J, 3)`` rest bone vectors (each joint's position relative to its parent at rest).
        settings: physical constants.
        ground_y: height of the ground plane.

    Raises:
        ValueError: malformed skeleton arrays.
    """

    def __init__(self, parents: IntArray, offsets: FloatArray, settings: RagdollSettings | None = None,
                 ground_y: float = 0.0) -> None:
        self.parents = np.asarray(parents, np.int64)
        self.offsets = np.asarray(offsets, np.float64)
        j = self.parents.size
        if self.offsets.shape != (j, 3) or j < 2 or self.parents[0] != -1:
            raise ValueError("a ragdoll needs (J,) parents with the root first and (J, 3) offsets")
        if np.any(self.parents[1:] >= np.arange(1, j)) or np.any(self.parents[1:] < 0):
            raise ValueError("parents must come before their children")
        self.s = settings or RagdollSettings()
        self.ground_y = float(ground_y)
        self.lengths = np.linalg.norm(self.offsets, axis=1)
        self.bones = np.flatnonzero(self.parents >= 0)
        # joint limits as a minimum grandparent-joint distance (law of cosines at the parent)
        gp = np.array([self.parents[p] if p >= 0 else -1 for p in self.parents])
        self.limited = np.flatnonzero((gp >= 0) & (self.lengths > 1e-6))
        self.limited = self.limited[self.lengths[self.parents[self.limited]] > 1e-6]
        a = self.lengths[self.parents[self.limited]]
        b = self.lengths[self.limited]
        interior = math.radians(180.0 - self.s.max_bend_deg)      # smallest angle at the parent
        self.min_dist = np.sqrt(np.maximum(a * a + b * b - 2 * a * b * math.cos(interior), 0.0))
        self.gp = gp
        self.pos = np.zeros((j, 3))
        self.prev = np.zeros((j, 3))
        self._still = 0.0
        self._held = False
        self.children = [np.flatnonzero(self.parents == i) for i in range(j)]
        # one Jacobi pass over every constraint at once: rows of ``_diff`` give each constraint's vector
        # (child minus parent for a bone, joint minus grandparent for a limit); ``_spread`` sends half of
        # each correction to either end, bone corrections relaxed by the joint's bone count
        nb, nl = self.bones.size, self.limited.size
        self._diff = np.zeros((nb + nl, j))
        self._diff[np.arange(nb), self.bones] = 1.0
        self._diff[np.arange(nb), self.parents[self.bones]] = -1.0
        self._diff[nb + np.arange(nl), self.limited] = 1.0
        self._diff[nb + np.arange(nl), self.gp[self.limited]] = -1.0
        degree = np.bincount(np.concatenate([self.bones, self.parents[self.bones]]), minlength=j)
        relax = np.ones((j, nb + nl))
        relax[:, :nb] = (1.0 / np.maximum(degree, 1))[:, None]
        self._spread = -0.5 * self._diff.T * relax
        self._target = np.concatenate([self.lengths[self.bones], self.min_dist])
        self._slack = np.where(np.arange(nb + nl) >= nb, 0.0, np.inf)   # a limit only pushes apart
        self._single = np.array([i for i in range(j) if self.children[i].size == 1
                                 and self.lengths[self.children[i][0]] > 1e-9], dtype=np.int64)
        self._single_child = np.array([self.children[i][0] for i in self._single], dtype=np.int64)
        real = [ch[self.lengths[ch] > 1e-9] for ch in self.children]
        multi = [i for i in range(j) if real[i].size > 1]
        # the first child is the main bone, the second the one farthest from its line (fixes the roll)
        self._multi = np.array(multi, dtype=np.int64)
        self._multi_a = np.array([real[i][0] for i in multi], dtype=np.int64)
        self._multi_b = np.array([real[i][int(np.argmax([np.linalg.norm(np.cross(
            self.offsets[real[i][0]] / self.lengths[real[i][0]], self.offsets[c])) for c in real[i]]))]
            for i in multi], dtype=np.int64)
        leaves = [i for i in range(j) if real[i].size == 0 and self.parents[i] >= 0]
        source = []
        for i in leaves:
            a = int(self.parents[i])
            while a in leaves:
                a = int(self.parents[a])
            source.append(a)
        self._leaves = np.array(leaves, dtype=np.int64)
        self._leaf_source = np.array(source, dtype=np.int64)
        self._identity = np.tile(np.eye(3), (j, 1, 1))
        # the rest-pose halves of rotations(): unit rest bones and rest triads
        rest = self.offsets[self._single_child]
        self._single_rest = rest / np.maximum(np.linalg.norm(rest, axis=1, keepdims=True), 1e-12)
        self._multi_rest = (_frames(self.offsets[self._multi_a], self.offsets[self._multi_b])
                            if multi else np.zeros((0, 3, 3)))

    def start(self, positions: FloatArray, velocities: FloatArray | None = None, dt: float = 1 / 60) -> None:
        """Take over from an animated pose: world joint positions ``(J, 3)`` and their velocities."""
        p = np.asarray(positions, np.float64)
        if p.shape != self.pos.shape or not np.all(np.isfinite(p)):
            raise ValueError(f"positions must be finite, shape {self.pos.shape}")
        v = np.zeros_like(p) if velocities is None else np.asarray(velocities, np.float64)
        self.pos = p.copy()
        self.prev = p - v * dt
        self._still = 0.0

    def step(self, dt: float, hold: tuple[int, FloatArray] | None = None) -> FloatArray:
        """Advance ``dt`` seconds; ``hold`` = (joint, target position) while the player holds it.

        Returns:
            The joint positions ``(J, 3)`` (a view: copy to keep).
        """
        if not dt > 0:
            raise ValueError("dt must be positive")
        s = self.s
        disp = self.pos - self.prev                    # velocity * dt (position Verlet)
        # damping everywhere, friction on the horizontal axes of joints touching the ground; gravity
        keep = np.full_like(disp, 1.0 - s.damping * dt)
        on_ground = self.pos[:, 1] <= self.ground_y + s.radius + 1e-4
        keep[on_ground, 0::2] -= s.friction * dt
        new = self.pos + disp * keep
        new[:, 1] -= s.gravity * dt * dt
        self._held = hold is not None
        self.prev = self.pos
        self.pos = new
        # the held joint is pulled towards the stick's end as a position constraint (unconditionally
        # stable for any dt, unlike a stiff explicit spring); it carries the whole body
        w = 1.0 - math.exp(-s.hold_rate * dt / s.iterations) if hold is not None else 0.0
        floor = self.ground_y + s.radius
        pos = self.pos
        for _ in range(s.iterations):
            if hold is not None:
                i, target = hold
                pos[i] += (np.asarray(target, np.float64) - pos[i]) * w
            self._constraints(pos)
            np.maximum(pos[:, 1], floor, out=pos[:, 1])     # the ground
        moved = pos - self.prev
        still = float(np.einsum("ij,ij->i", moved, moved).max()) < (s.rest_speed * dt) ** 2
        self._still = self._still + dt if still else 0.0
        return self.pos

    def _constraints(self, pos: FloatArray) -> None:
        # bones (rigid: any error corrected) and joint limits (only a joint nearer its grandparent than
        # the limit allows is pushed out), every correction from the same positions, summed per joint
        d = self._diff @ pos
        n = np.sqrt(np.einsum("ij,ij->i", d, d))
        # |d| = n, so d * err / n stays bounded however short d is (two joints at one place: no push)
        scale = np.minimum(n - self._target, self._slack) / np.maximum(n, 1e-12)
        pos += self._spread @ (d * scale[:, None])

    @property
    def at_rest(self) -> bool:
        """Still (every joint slower than ``rest_speed``) for ``rest_time`` and touching the ground: lying, or
        hanging still from the stick with its feet down. A body hanging clear of the ground is not at rest."""
        return (self._still >= self.s.rest_time
                and float(self.pos[:, 1].min()) <= self.ground_y + 2 * self.s.radius)

    def rotations(self) -> tuple[FloatArray, FloatArray]:
        """The pose as the skeleton's root position ``(3,)`` and local rotations ``(J, 4)`` (w, x, y, z)."""
        world = self._identity.copy()                   # world rotation matrices (J, 3, 3)
        # joints with one child: the smallest rotation taking the rest bone onto the current one
        if self._single.size:
            world[self._single] = _swing_matrices(self._single_rest,
                                                  self.pos[self._single_child] - self.pos[self._single])
        # joints with several children (hips, chest, hands): the first child's bone exactly, the roll
        # about it from the second (the triad method), all at once
        if self._multi.size:
            world[self._multi] = _triad(self._multi_rest, self.pos[self._multi_a] - self.pos[self._multi],
                                        self.pos[self._multi_b] - self.pos[self._multi])
        world[self._leaves] = world[self._leaf_source]  # leaves (no bone to aim) follow their parent
        local = world.copy()
        local[self.bones] = np.einsum("nji,njk->nik", world[self.parents[self.bones]], world[self.bones])
        local = quat_from_matrix(local)
        return self.pos[0].copy(), local


def _frames(a: FloatArray, b: FloatArray) -> FloatArray:
    e1 = a / np.linalg.norm(a, axis=1, keepdims=True)
    e3 = cross(e1, b)
    e3 = e3 / np.maximum(np.linalg.norm(e3, axis=1, keepdims=True), 1e-12)
    e2 = cross(e3, e1)
    return np.stack([e1, e2, e3], axis=2)          # columns


def _triad(rest: FloatArray, ca: FloatArray, cb: FloatArray) -> FloatArray:
    """Rotation matrices of the rotations taking the rest triads ``rest`` (``_frames`` of the rest
    directions) to the current directions (ca, cb): the first onto ``ca`` exactly, the plane of the two as
    close as possible."""
    rotations: FloatArray = np.einsum("nij,nkj->nik", _frames(ca, cb), rest)
    return rotations


def _swing_matrices(a: FloatArray, b: FloatArray) -> FloatArray:
    """Rotation matrices ``(n, 3, 3)`` of the smallest rotations taking the unit directions ``a`` onto ``b``:
    ``c I + [v]x + v v^T / (1 + c)`` with ``v = a x b``, ``c = a . b`` (a half turn for opposite ones)."""
    b = b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-12)
    v = cross(a, b)
    c = np.einsum("ij,ij->i", a, b)
    opposite = c < -1.0 + 1e-9
    k = 1.0 / np.where(opposite, 1.0, 1.0 + c)
    m = v[:, :, None] * (v * k[:, None])[:, None, :]
    m[:, 0, 0] += c
    m[:, 1, 1] += c
    m[:, 2, 2] += c
    m[:, 0, 1] -= v[:, 2]
    m[:, 1, 0] += v[:, 2]
    m[:, 0, 2] += v[:, 1]
    m[:, 2, 0] -= v[:, 1]
    m[:, 1, 2] -= v[:, 0]
    m[:, 2, 1] += v[:, 0]
    for i in np.flatnonzero(opposite):
        m[i] = _swing(a[i], b[i]).as_matrix()
    return m


def _swing(a: FloatArray, b: FloatArray) -> Rotation:
    """The smallest rotation taking direction ``a`` to direction ``b``."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    c = float(np.dot(a, b))
    if s < 1e-12:
        if c > 0:
            return Rotation.identity()
        perp = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(perp) < 1e-6:
            perp = np.cross(a, [0.0, 1.0, 0.0])
        return Rotation.from_rotvec(perp / np.linalg.norm(perp) * math.pi)
    return Rotation.from_rotvec(axis / s * math.atan2(s, c))
