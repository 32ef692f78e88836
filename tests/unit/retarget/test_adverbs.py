"""Verbs (Rose 1999, ch. 4): the storage counts of section 4.7, and a ``Verb`` built from examples (at
least D + 1 of them, guarded key-times, examples reproduced, timing blended, unit rotations, turning
verbs, a multiresolution verb, real clips, poses anywhere in the puppet's blend space)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from capture.quat import quat_exp, quat_mul, quat_slerp
from retarget.adverbs import (
    Example,
    Verb,
    coefficients_per_frame,
    example_storage,
    mrbf_storage,
)
from retarget.timeline import split_heading, verb_time, yaw_quat

TRACES = Path(__file__).resolve().parents[3].parent / "shared" / "traces" / "d_mocap_cyclic"


def walk_example(
    point: tuple[float, ...],
    speed: float,
    period: float,
    *,
    joints: int = 30,
    frames: int = 61,
    crouch: float = 0.0,
    start: tuple[float, float, float] = (0.0, 0.0, 0.0),
    key_frac: float = 0.45,
) -> Example:
    """A synthetic walk cycle: the root goes straight ahead from ``start`` (x, z, heading) at ``speed``,
    bobs twice per cycle, and every joint swings with an amplitude that grows with speed."""
    T = np.linspace(0.0, period, frames)
    ph = 2.0 * np.pi * T / period
    x0, z0, h0 = start
    pos = np.stack(
        [x0 + speed * T * math.sin(h0), 0.9 - crouch + 0.02 * np.sin(2 * ph), z0 + speed * T * math.cos(h0)], axis=1
    )
    rv = np.zeros((frames, joints, 3))
    j = np.arange(1, joints)
    rv[:, 1:, 0] = (0.3 + 0.15 * speed + crouch) * np.sin(ph[:, None] + 0.3 * j)
    rv[:, 1:, 2] = 0.1 * np.cos(ph[:, None] + 0.2 * j)
    rot = quat_exp(rv)
    rot[:, 0] = quat_mul(yaw_quat(np.full(frames, h0)), quat_exp(np.stack([0.05 * np.sin(2 * ph), 0 * ph, 0 * ph], 1)))
    return Example(point=point, times=T, root_pos=pos, rotations=rot, key_times=[0.0, key_frac * period, period])


def locomotion_examples(joints: int = 30) -> list[Example]:
    """The puppet's five clips at (speed, height): idle, walk, run, crouch_idle, crouch_walk."""
    return [
        walk_example((0.0, 1.0), 0.0, 2.0, joints=joints),
        walk_example((0.5, 1.0), 1.4, 1.0, joints=joints),
        walk_example((1.0, 1.0), 3.5, 0.7, joints=joints),
        walk_example((0.0, 0.0), 0.0, 2.0, joints=joints, crouch=0.3),
        walk_example((1.0, 0.0), 0.8, 1.2, joints=joints, crouch=0.3),
    ]


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return 2.0 * np.arccos(np.clip(np.abs(np.sum(a * b, axis=-1)), 0.0, 1.0))


# -- counts ------------------------------------------------------------------------------------


def test_storage_counts() -> None:
    assert coefficients_per_frame(44, 4) == 180
    assert example_storage(44, 32, 20) == 28_160
    assert mrbf_storage(44, 32, 4, 20, 4) == 63_540
    assert mrbf_storage(44, 32, 4, 20, 4) / example_storage(44, 32, 20) == pytest.approx(2.26, abs=0.005)


# -- verbs ------------------------------------------------------------------------------------


def test_verb_needs_d_plus_1_examples() -> None:
    ex = locomotion_examples(joints=4)
    with pytest.raises(ValueError, match="at least 3"):
        Verb(ex[:2])
    Verb(ex[:3], periodic=True)
    with pytest.raises(ValueError):
        Verb([ex[0], ex[1], walk_example((0.5,), 1.0, 1.0, joints=4)])  # mixed dimensions
    with pytest.raises(ValueError):
        Verb([ex[0], ex[1], walk_example((0.2, 0.2), 1.0, 1.0, joints=5)])  # other skeleton


def test_verb_key_time_guard() -> None:
    a = walk_example((0.0,), 1.0, 1.0, joints=3, key_frac=0.2)
    b = walk_example((1.0,), 1.0, 1.0, joints=3, key_frac=0.8)
    v = Verb([a, b])
    np.testing.assert_allclose(v.key_times(0.5), [0.0, 0.5, 1.0], atol=1e-12)
    v.key_times(1.2)  # still increasing
    with pytest.raises(ValueError, match="strictly increasing"):
        v.key_times(2.0)  # 0.2 + 0.6 * 2 = 1.4 > 1
    with pytest.raises(ValueError):
        v.pose(-1.0, 0.5)
    with pytest.raises(ValueError):
        v.duration((0.5, 0.5))


def test_verb_reproduces_examples() -> None:
    ex = locomotion_examples()
    v = Verb(ex, periodic=True, num_cp=24)
    assert v.fit_rms < 1e-3
    t = np.linspace(0.0, 0.98, 25)
    for e in ex:
        p = e.point
        assert v.duration(p) == pytest.approx(e.key_times[-1], abs=1e-12)
        np.testing.assert_allclose(v.key_times(p), e.key_times, atol=1e-12)
        speed = np.hypot(*(e.root_pos[-1] - e.root_pos[0])[[0, 2]]) / e.times[-1]
        assert v.root_speed(p) == pytest.approx(speed, abs=1e-9)
        fr = v.sample(p, t)
        T = np.asarray(verb_time(t, e.key_times))
        ref_pos = np.stack([np.interp(T, e.times, e.root_pos[:, k]) for k in range(3)], axis=1)
        np.testing.assert_allclose(fr.root_pos, ref_pos - [ref_pos[0, 0], 0, ref_pos[0, 2]], atol=2e-3)
        i = np.clip(np.searchsorted(e.times, T, side="right") - 1, 0, e.times.size - 2)
        f = (T - e.times[i]) / (e.times[i + 1] - e.times[i])
        ref_rot = quat_slerp(e.rotations[i], e.rotations[i + 1], np.repeat(f[:, None], 30, axis=1))
        assert angle_between(fr.rotations[:, 1:], ref_rot[:, 1:]).max() < 5e-3  # B-spline fit vs slerp
        _, tilt = split_heading(ref_rot[:, 0])
        assert angle_between(fr.rotations[:, 0], tilt).max() < 5e-3


def test_verb_blends_timing_and_stays_unit() -> None:
    v = Verb(locomotion_examples(), periodic=True)
    p = (0.2, 0.73)
    k = v.key_times(p)
    assert np.all(np.diff(k) > 0)
    assert 0.7 < v.duration(p) < 2.0
    assert 0.0 <= v.root_speed(p) < 3.5
    vel, rot = v.pose(p, 0.3)
    assert vel.shape == (3,) and rot.shape == (30, 4)
    np.testing.assert_allclose(np.linalg.norm(rot, axis=1), 1.0, atol=1e-12)
    # pose and sample agree; the velocity is d root_pos / dT
    fr = v.sample(p, 0.3)
    np.testing.assert_allclose(vel, fr.root_velocity, atol=1e-12)
    h = 1e-5
    T = v.verb_time(p, 0.3)
    fwd = v.at_time(p, np.array([T - h, T + h]))
    np.testing.assert_allclose((fwd.root_pos[1] - fwd.root_pos[0]) / (2 * h), vel, atol=1e-4)
    np.testing.assert_allclose(np.abs(np.sum(rot[1:] * fr.rotations[1:], -1)), 1.0, atol=1e-12)
    # a periodic verb plays on: one duration later the root is one displacement further
    a = v.at_time(p, 0.4)
    b = v.at_time(p, 0.4 + v.duration(p))
    np.testing.assert_allclose(b.root_pos - a.root_pos, v.displacement(p), atol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(a.rotations * b.rotations, -1)), 1.0, atol=1e-12)


def test_verb_hemisphere_consistent() -> None:
    ex = locomotion_examples(joints=6)
    flipped = []
    sign = np.where(np.random.default_rng(10).random((61, 6, 1)) < 0.5, -1.0, 1.0)
    for e in ex:
        flipped.append(Example(e.point, e.times, e.root_pos, e.rotations * sign, e.key_times))
    a, b = Verb(ex, periodic=True), Verb(flipped, periodic=True)
    for p in [(0.3, 0.3), (0.9, 0.6)]:
        for t in (0.1, 0.55):
            np.testing.assert_allclose(np.abs(np.sum(a.pose(p, t)[1] * b.pose(p, t)[1], -1)), 1.0, atol=1e-9)


def test_turning_verb_trend_frame() -> None:
    # examples that turn left while walking: the net turn is interpolated and the velocity that pose()
    # gives is in the turning frame (so it stays straight ahead)
    def turning(point: float, rate: float) -> Example:
        T = np.linspace(0.0, 1.0, 201)
        h = rate * T
        xz = np.stack([(1 - np.cos(h)) / rate, np.sin(h) / rate], 1) if rate else np.stack([0 * T, T], 1)
        pos = np.stack([xz[:, 0], 0.9 + 0 * T, xz[:, 1]], 1)
        rot = np.tile([1.0, 0, 0, 0], (201, 2, 1))
        rot[:, 0] = yaw_quat(h)
        return Example((point,), T, pos, rot, [0.0, 1.0])

    v = Verb([turning(0.0, 0.5), turning(1.0, 1.0)], periodic=False)
    assert v.net_turn(0.5) == pytest.approx(0.75, abs=1e-9)
    for t in (0.2, 0.5, 0.9):
        vel, rot = v.pose(0.5, t)
        # straight ahead in the turning frame; the blended path averages two unit-speed arcs whose
        # directions differ by (1.0 - 0.5) t, so its speed is cos of half that
        assert vel[2] == pytest.approx(math.cos(0.25 * t), abs=2e-3) and abs(vel[0]) < 2e-3
        np.testing.assert_allclose(np.abs(rot[0, 0]), 1.0, atol=1e-3)


def test_mrbf_verb() -> None:
    ex = locomotion_examples(joints=8)
    ex.append(walk_example((0.55, 1.0), 1.5, 0.98, joints=8))  # a near-duplicate of walk
    v = Verb(ex, periodic=True, interpolant="mrbf", seed=1)
    for e in ex:
        assert v.duration(e.point) == pytest.approx(e.key_times[-1], abs=1e-9)
    assert v.storage == v.interpolant.coefficients.size
    assert v.coefficients_per_frame == 4 * v.num_channels + 3 + 4


def test_verb_from_real_clips() -> None:
    paths = [TRACES / f"cmu_131_0{i}_start_walk_stop.bvh" for i in (1, 2)]
    for path in paths:
        if not path.exists():
            pytest.skip(f"CMU walk not found at {path} (../shared/traces must sit beside the project)")
    from retarget.bvh import CMU_SCALE, read_bvh

    clips = [read_bvh(p, scale=CMU_SCALE)[1] for p in paths]
    ex = [Example.from_clip(c, (float(i),)) for i, c in enumerate(clips)]
    v = Verb(ex, num_cp=160, name="start_walk_stop")
    assert v.num_joints == 31
    # joints whose captured rotation is continuous (the CMU thumbs flip by ~pi between frames)
    steps = [angle_between(c.rotations[1:], c.rotations[:-1]).max(axis=0) for c in clips]
    smooth = np.flatnonzero(np.maximum(*steps) < 0.5)
    assert smooth.size >= 25
    for c, e in zip(clips, ex, strict=True):
        assert v.duration(e.point) == pytest.approx(c.duration, abs=1e-9)
        assert v.root_speed(e.point) == pytest.approx(c.root_speed(), rel=1e-6)
        for t in (0.2, 0.5, 0.8):
            _, rot = c.sample(t * c.duration)
            _, r = v.pose(e.point, t)
            err = angle_between(r[smooth[smooth > 0]], rot[smooth[smooth > 0]])
            assert np.median(err) < 0.01 and err.max() < 0.1
    mid = v.duration(0.5)
    assert mid == pytest.approx(0.5 * (clips[0].duration + clips[1].duration), abs=1e-9)
    _, r = v.pose(0.5, 0.5)
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 1.0, atol=1e-12)


def test_poses_anywhere_in_the_puppets_blend_space_are_unit_and_timed_between_the_examples() -> None:
    # the puppet blends 5 clips over (speed, height) for a 30-joint skeleton every frame, with p moving
    v = Verb(locomotion_examples(joints=30), periodic=True)
    rng = np.random.default_rng(11)
    ps = rng.uniform(0.0, 1.0, (200, 2))
    for i in range(200):
        vel, rot = v.pose(ps[i], (i % 97) / 97)
        assert vel.shape == (3,) and np.all(np.isfinite(vel)) and rot.shape == (30, 4)
        np.testing.assert_allclose(np.linalg.norm(rot, axis=1), 1.0, atol=1e-12)
        assert 0.7 <= v.duration(ps[i]) <= 2.0  # between the run's and the idles' cycle lengths
