"""The ragdoll: gravity, rigid bones, the ground, joint limits, the held joint, and back to rotations."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retarget.ragdoll import Ragdoll, RagdollSettings

# hips, spine, head, left hip joint, left knee, left foot, right hip joint, right knee, right foot
PARENTS = np.array([-1, 0, 1, 0, 3, 4, 0, 6, 7])
OFFSETS = np.array([[0, 0, 0], [0, 0.3, 0], [0, 0.3, 0], [0.1, 0, 0], [0, -0.45, 0], [0, -0.45, 0],
                    [-0.1, 0, 0], [0, -0.45, 0], [0, -0.45, 0]], float)


def fk(root: np.ndarray, local: np.ndarray) -> np.ndarray:
    world = [Rotation.identity()] * len(PARENTS)
    pos = np.zeros((len(PARENTS), 3))
    for i, p in enumerate(PARENTS):
        r = Rotation.from_quat(local[i][[1, 2, 3, 0]])
        if p < 0:
            world[i], pos[i] = r, root
        else:
            world[i] = world[p] * r
            pos[i] = pos[p] + world[p].apply(OFFSETS[i])
    return pos


def standing(height: float = 1.0) -> np.ndarray:
    pos = np.zeros((len(PARENTS), 3))
    for i, p in enumerate(PARENTS):
        pos[i] = (pos[p] if p >= 0 else np.array([0.0, height, 0.0])) + (OFFSETS[i] if p >= 0 else 0)
    return pos


def bone_lengths(pos: np.ndarray) -> np.ndarray:
    return np.linalg.norm(pos[1:] - pos[PARENTS[1:]], axis=1)


def test_falls_and_comes_to_rest_on_the_ground_with_rigid_bones() -> None:
    rd = Ragdoll(PARENTS, OFFSETS)
    start = standing(1.5)
    rd.start(start, np.tile([0.5, 0.0, 0.2], (9, 1)))
    t = 0.0
    while not rd.at_rest and t < 10.0:
        rd.step(1 / 120)
        t += 1 / 120
    assert rd.at_rest, t
    assert t > 0.5                                   # it fell first
    assert rd.pos[:, 1].min() >= -1e-9               # nothing below the ground
    assert rd.pos[:, 1].max() < 0.5                  # lying, not standing
    np.testing.assert_allclose(bone_lengths(rd.pos), np.linalg.norm(OFFSETS[1:], axis=1), rtol=0.02)


def test_joint_limits_hold() -> None:
    s = RagdollSettings(max_bend_deg=90.0)
    rd = Ragdoll(PARENTS, OFFSETS, s)
    pos = standing(1.2)
    pos[5] = pos[4] + np.array([0, 0.45, 0.0])       # foot folded back onto the thigh: 180 deg
    rd.start(pos)
    for _ in range(240):
        rd.step(1 / 120)
    p = rd.pos
    for j, par, g in ((5, 4, 3), (8, 7, 6), (2, 1, 0)):
        a = p[par] - p[g]
        b = p[j] - p[par]
        bend = np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))
        assert bend <= 90.0 + 5.0, (j, bend)


def test_held_joint_follows_the_stick_end() -> None:
    rd = Ragdoll(PARENTS, OFFSETS)
    rd.start(standing(1.0))
    target = np.array([0.5, 2.0, 0.3])
    for _ in range(600):
        rd.step(1 / 120, hold=(2, target))
    # hanging by the head under gravity: close to the target, body below it, feet clear: not at rest
    assert np.linalg.norm(rd.pos[2] - target) < 0.1
    assert rd.pos[5, 1] < rd.pos[2, 1] and rd.pos[8, 1] < rd.pos[2, 1]
    assert rd.pos[:, 1].min() > 0.2
    assert not rd.at_rest
    # lowered until the feet are down and held still there: at rest (the player may let it get up)
    target = np.array([0.5, 1.55, 0.3])
    for _ in range(600):
        rd.step(1 / 120, hold=(2, target))
    assert rd.pos[:, 1].min() < 0.1 and rd.pos[0, 1] > 0.5
    assert rd.at_rest


def test_rotations_reproduce_the_particles() -> None:
    rd = Ragdoll(PARENTS, OFFSETS)
    rd.start(standing(1.5), np.tile([0.3, 1.0, -0.4], (9, 1)))
    for _ in range(50):
        rd.step(1 / 120)
    root, local = rd.rotations()
    np.testing.assert_allclose(np.linalg.norm(local, axis=1), 1.0, atol=1e-12)
    pos = fk(root, local)
    # the hips (three children) by least squares, so the pelvis triangle within a couple of cm; the
    # single-child chains below each hip joint exactly relative to it
    assert np.max(np.linalg.norm(pos - rd.pos, axis=1)) < 0.05
    for a, b in ((3, 4), (4, 5), (6, 7), (7, 8), (1, 2)):
        np.testing.assert_allclose(pos[b] - pos[a], rd.pos[b] - rd.pos[a], atol=0.01)


def test_bad_arguments() -> None:
    with pytest.raises(ValueError):
        Ragdoll(np.array([0, 0]), np.zeros((2, 3)))
    rd = Ragdoll(PARENTS, OFFSETS)
    with pytest.raises(ValueError):
        rd.start(np.zeros((3, 3)))
    with pytest.raises(ValueError):
        rd.step(0.0)
