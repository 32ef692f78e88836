"""The horizontal path solve of path editing (``retarget.path_arap``): unmoved handles give the original path
exactly and a rigid motion of all handles moves it rigidly at scale 1 (on the CMU walks and a seeded sweep of
random paths); stage 2's closed form equals the constrained least squares it stands for; the automatic scale
keeps each segment's arclength at ``s`` times the original within a few Newton steps; at ``s = 0`` a segment is
straight, spaced like the original; pulling a swaying path's ends apart at ``s = 1`` keeps the sway exactly."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from retarget.bvh import CMU_SCALE, read_bvh
from retarget.path_arap import HorizontalPath, _Segment
from retarget.path_contacts import detect_contacts
from retarget.path_handles import select_handles

TRACES = Path(__file__).resolve().parents[3].parent / "shared" / "traces" / "d_mocap_cyclic"


def cmu_path(name: str) -> tuple[np.ndarray, list[int]]:
    path = TRACES / name
    if not path.exists():
        pytest.skip(f"{path} not found (../shared/traces must sit beside the project)")
    clip = read_bvh(path, scale=CMU_SCALE, end_sites=True)[1]
    keys = [h.key for h in select_handles(clip.root_pos, clip.fps, detect_contacts(clip)) if h.kind == "path"]
    return clip.root_pos[:, [0, 2]].copy(), keys


def random_path(rng: np.random.Generator) -> tuple[np.ndarray, list[int]]:
    n = int(rng.integers(20, 400))
    heading = np.cumsum(rng.normal(0, 0.05, n))
    step = rng.uniform(0.002, 0.03, n)
    p = np.cumsum(np.column_stack([np.cos(heading), np.sin(heading)]) * step[:, None], axis=0)
    p += rng.normal(0, 0.003, p.shape)   # sway and noise
    for k in rng.integers(1, n - 1, int(rng.integers(0, 4))):   # pauses: runs of keys at one point
        p[k:k + int(rng.integers(1, 6))] = p[k]
    inner = sorted(set(rng.choice(np.arange(5, n - 5), int(rng.integers(0, max(1, n // 40))), replace=False)))
    return p, [0, *[int(k) for k in inner], n - 1]


def rot(a: float) -> np.ndarray:
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


@pytest.mark.parametrize("name", ["cmu_016/16_21_walk.bvh", "cmu_016/16_18_walk_left_turn.bvh",
                                  "cmu_131_02_start_walk_stop.bvh"])
def test_unmoved_handles_give_the_original_and_rigid_motions_move_it_rigidly(name: str) -> None:
    p, keys = cmu_path(name)
    hp = HorizontalPath(p, keys)
    r = hp.solve(p[keys])
    np.testing.assert_allclose(r.path, p, rtol=0, atol=1e-12)
    assert set(r.iterations) == {0} and set(r.scales) == {1.0}
    m, shift = rot(0.7), np.array([3.0, -2.0])
    moved = hp.solve(p[keys] @ m.T + shift)
    np.testing.assert_allclose(moved.path, p @ m.T + shift, atol=1e-6)
    np.testing.assert_allclose(moved.scales, 1.0, atol=1e-6)


def test_identity_and_rigid_motion_on_random_paths() -> None:
    rng = np.random.default_rng(1903)
    for case in range(150):
        p, keys = random_path(rng)
        hp = HorizontalPath(p, keys)
        np.testing.assert_allclose(hp.solve(p[keys]).path, p, atol=1e-12, err_msg=str(case))
        m, shift = rot(float(rng.uniform(-3, 3))), rng.uniform(-10, 10, 2)
        np.testing.assert_allclose(hp.solve(p[keys] @ m.T + shift).path, p @ m.T + shift, atol=1e-6,
                                   err_msg=str(case))


def test_stage_two_closed_form_is_the_constrained_least_squares() -> None:
    rng = np.random.default_rng(5)
    for _ in range(200):
        n = int(rng.integers(2, 30))
        p = np.cumsum(rng.normal(0, 0.1, (n + 1, 2)), axis=0)
        pb = p + rng.normal(0, 0.05, p.shape)
        chord = p[-1] - p[0] + rng.normal(0, 0.1, 2)
        s = float(rng.uniform(0, 2))
        seg = _Segment(p, pb, chord)
        # minimise sum_i w_i |x_i - s eb_i|^2 with sum_i x_i = chord, w_i = 1/|e_i|: KKT per coordinate
        w = 1.0 / np.linalg.norm(np.diff(p, axis=0), axis=1)
        kkt = np.zeros((n + 1, n + 1))
        kkt[:n, :n] = np.diag(2 * w)
        kkt[:n, n] = kkt[n, :n] = 1.0
        want = np.empty((n, 2))
        for c in (0, 1):
            rhs = np.concatenate([2 * w * s * seg.eb[:, c], [chord[c]]])
            want[:, c] = np.linalg.solve(kkt, rhs)[:n]
        np.testing.assert_allclose(seg.edges(s), want, atol=1e-9)


def test_the_scale_keeps_arclength_within_five_steps() -> None:
    p, keys = cmu_path("cmu_016/16_21_walk.bvh")
    hp = HorizontalPath(p, keys)
    rng = np.random.default_rng(12)
    worst = 0
    for _ in range(100):
        t = p[keys].copy()
        i = int(rng.integers(1, len(keys) - 1))
        t[i] += rng.uniform(-0.25, 0.25, 2)       # a step moved by up to a quarter of a metre each way
        r = hp.solve(t)
        for k, (a, b) in enumerate(itertools.pairwise(keys)):
            l0 = np.linalg.norm(np.diff(p[a:b + 1], axis=0), axis=1).sum()
            l1 = np.linalg.norm(np.diff(r.path[a:b + 1], axis=0), axis=1).sum()
            assert l1 == pytest.approx(r.scales[k] * l0, rel=1e-8)
        np.testing.assert_array_equal(r.path[keys], t)
        worst = max(worst, *r.iterations)
    assert worst <= 5


def test_scale_zero_is_a_straight_segment_spaced_like_the_original() -> None:
    p, keys = cmu_path("cmu_016/16_21_walk.bvh")
    hp = HorizontalPath(p, keys)
    r = hp.solve(p[keys], scales=[0.0] * (len(keys) - 1))
    assert all(r.floored) and set(r.scales) == {0.05}
    r0 = hp.solve(p[keys], scales=[0.05] * (len(keys) - 1))
    np.testing.assert_array_equal(r.path, r0.path)
    a, b = keys[1], keys[2]
    seg = _Segment(p[a:b + 1], hp.stage1(p[keys])[a:b + 1], p[b] - p[a])
    x = seg.edges(0.0)
    direction = (p[b] - p[a]) / np.linalg.norm(p[b] - p[a])
    np.testing.assert_allclose(x - np.outer(x @ direction, direction), 0, atol=1e-12)   # along the chord
    lengths = np.linalg.norm(np.diff(p[a:b + 1], axis=0), axis=1)
    np.testing.assert_allclose(np.linalg.norm(x, axis=1) / np.linalg.norm(x, axis=1).sum(),
                               lengths / lengths.sum(), atol=1e-12)


def test_pulling_a_swaying_path_apart_keeps_its_sway_at_scale_one() -> None:
    x = np.linspace(0, 4.2, 421)
    p = np.column_stack([x, 0.05 * np.sin(2 * np.pi * x / 1.4)])   # three sways; the chord is the x axis
    hp = HorizontalPath(p, [0, 420])
    r = hp.solve(np.array([p[0], p[-1] + [1.0, 0.0]]), scales=[1.0])
    np.testing.assert_allclose(r.path[:, 1], p[:, 1], atol=1e-9)   # lateral offsets kept exactly
    assert r.path[-1, 0] == pytest.approx(5.2)


def test_bad_paths_and_handles() -> None:
    with pytest.raises(ValueError, match="handle keys"):
        HorizontalPath(np.zeros((5, 2)), [0, 3])
    with pytest.raises(ValueError, match="finite points"):
        HorizontalPath(np.full((5, 2), np.nan), [0, 4])
