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

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass
class RagdollSettings:
    """Physical constants (SI units)."""

    gravity: float = 9.81
    damping: float = 1.5          # 1/s, velocity damping in the air
    friction: float = 8.0         # 1/s, horizontal damping while touching the ground
    radius: float = 0.05          # joint radius against the ground (m)
    max_bend_deg: float = 150.0   # joint limit: angle between a bone and its parent bone
    hold_rate: float = 60.0       # 1/s: how fast the held joint closes on the stick's end
    iterations: int = 10          # constraint passes per step
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

    def __init__(self, parents: np.ndarray, offsets: np.ndarray, settings: RagdollSettings | None = None,
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
        self._rest_seen = np.zeros((j, 3))
        self.children = [np.flatnonzero(self.parents == i) for i in range(j)]

    def start(self, positions: np.ndarray, velocities: np.ndarray | None = None, dt: float = 1 / 60) -> None:
        """Take over from an animated pose: world joint positions ``(J, 3)`` and their velocities."""
        p = np.asarray(positions, np.float64)
        if p.shape != self.pos.shape or not np.all(np.isfinite(p)):
            raise ValueError(f"positions must be finite, shape {self.pos.shape}")
        v = np.zeros_like(p) if velocities is None else np.asarray(velocities, np.float64)
        self.pos = p.copy()
        self.prev = p - v * dt
        self._still = 0.0

    def step(self, dt: float, hold: tuple[int, np.ndarray] | None = None) -> np.ndarray:
        """Advance ``dt`` seconds; ``hold`` = (joint, target position) while the player holds it.

        Returns:
            The joint positions ``(J, 3)`` (a view: copy to keep).
        """
        if not dt > 0:
            raise ValueError("dt must be positive")
        s = self.s
        vel = (self.pos - self.prev) / dt
        acc = np.zeros_like(self.pos)
        acc[:, 1] -= s.gravity
        on_ground = self.pos[:, 1] <= self.ground_y + s.radius + 1e-4
        acc -= s.damping * vel
        acc[on_ground, 0] -= s.friction * vel[on_ground, 0]
        acc[on_ground, 2] -= s.friction * vel[on_ground, 2]
        new = self.pos + vel * dt + acc * dt * dt
        self.prev = self.pos
        self.pos = new
        # the held joint is pulled towards the stick's end as a position constraint (unconditionally
        # stable for any dt, unlike a stiff explicit spring); it carries the whole body
        w = 1.0 - math.exp(-s.hold_rate * dt / s.iterations) if hold is not None else 0.0
        for _ in range(s.iterations):
            if hold is not None:
                i, target = hold
                self.pos[i] += (np.asarray(target, np.float64) - self.pos[i]) * w
            self._bones()
            self._limits()
            self._ground()
        speed = np.max(np.linalg.norm(self.pos - self.prev, axis=1)) / dt
        self._still = self._still + dt if speed < s.rest_speed else 0.0
        return self.pos

    def _bones(self) -> None:
        c = self.bones
        p = self.parents[c]
        d = self.pos[c] - self.pos[p]
        n = np.linalg.norm(d, axis=1)
        ok = n > 1e-9
        corr = np.zeros_like(d)
        corr[ok] = d[ok] * ((n[ok] - self.lengths[c][ok]) / n[ok])[:, None] * 0.5
        # equal masses: each end moves half the way (sequentially for stability)
        for k in range(c.size):
            self.pos[c[k]] -= corr[k]
            self.pos[p[k]] += corr[k]

    def _limits(self) -> None:
        if self.limited.size == 0:
            return
        j = self.limited
        g = self.gp[j]
        d = self.pos[j] - self.pos[g]
        n = np.linalg.norm(d, axis=1)
        short = (n < self.min_dist) & (n > 1e-9)
        for k in np.flatnonzero(short):
            push = d[k] / n[k] * (self.min_dist[k] - n[k]) * 0.5
            self.pos[j[k]] += push
            self.pos[g[k]] -= push

    def _ground(self) -> None:
        floor = self.ground_y + self.s.radius
        below = self.pos[:, 1] < floor
        self.pos[below, 1] = floor

    @property
    def at_rest(self) -> bool:
        """Still (every joint slower than ``rest_speed``) for ``rest_time`` and lying near the ground."""
        return self._still >= self.s.rest_time and float(self.pos[:, 1].min()) <= self.ground_y + 2 * self.s.radius

    def rotations(self) -> tuple[np.ndarray, np.ndarray]:
        """The pose as the skeleton's root position ``(3,)`` and local rotations ``(J, 4)`` (w, x, y, z)."""
        jn = self.parents.size
        world = [Rotation.identity()] * jn
        for i in range(jn):
            ch = self.children[i]
            ch = ch[self.lengths[ch] > 1e-9]
            if ch.size == 0:
                world[i] = world[self.parents[i]] if self.parents[i] >= 0 else Rotation.identity()
                continue
            cur = self.pos[ch] - self.pos[i]
            rest = self.offsets[ch]
            if ch.size == 1:
                world[i] = _swing(rest[0], cur[0])
            else:
                rot, _ = Rotation.align_vectors(cur, rest)
                world[i] = rot
        local = np.empty((jn, 4))
        for i in range(jn):
            p = self.parents[i]
            r = world[i] if p < 0 else world[p].inv() * world[i]
            q = r.as_quat()
            local[i] = (q[3], q[0], q[1], q[2])
        return self.pos[0].copy(), local


def _swing(a: np.ndarray, b: np.ndarray) -> Rotation:
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
