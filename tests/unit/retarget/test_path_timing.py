"""The timewarp of path editing (``retarget.path_timing``): unchanged paths keep their times exactly;
a walk's path stretched uniformly by ``s`` at the Froude/Alexander speed ratio ``s^(5/6)`` lasts ``s^(1/6)``
as long (the thesis's combination, beta 0.5 each, with no turn); slow keys keep their timing; every step stays
above its floor on a seeded sweep of random edits; the stride ratio spline holds its knots."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from retarget.bvh import CMU_SCALE, read_bvh
from retarget.path_timing import TimeWarp, alexander_stride, froude, speed_ratio, stride_ratio_per_key

TRACES = Path(__file__).resolve().parents[3].parent / "shared" / "traces" / "d_mocap_cyclic"


def walk() -> tuple[np.ndarray, np.ndarray]:
    path = TRACES / "cmu_016" / "16_21_walk.bvh"
    if not path.exists():
        pytest.skip(f"{path} not found (../shared/traces must sit beside the project)")
    clip = read_bvh(path, scale=CMU_SCALE, end_sites=True)[1]
    return clip.times[1:] - clip.times[1], clip.root_pos[1:, [0, 2]].copy()   # row 0 is a rest pose


def test_an_unchanged_path_keeps_its_times_exactly() -> None:
    t, p = walk()
    w = TimeWarp(t).solve(p, p, np.ones(len(t)))
    np.testing.assert_allclose(w.times, t, atol=1e-12)
    assert w.clamped == 0


@pytest.mark.parametrize("s", [0.5, 0.8, 1.25, 2.0])
def test_a_uniform_stretch_lasts_s_to_the_sixth(s: float) -> None:
    t, p = walk()
    rho = speed_ratio(np.full(len(t), s))
    assert rho[0] == pytest.approx(s ** (5 / 6))
    w = TimeWarp(t).solve(p, s * p, rho)
    np.testing.assert_allclose(w.times, t * s ** (1 / 6), rtol=1e-9, atol=1e-12)


def test_random_paths_and_edits() -> None:
    rng = np.random.default_rng(1906)
    for case in range(150):
        n = int(rng.integers(5, 300))
        t = np.concatenate([[0.0], np.cumsum(rng.uniform(0.004, 0.02, n - 1))])
        p = np.cumsum(rng.normal(0, 0.01, (n, 2)), axis=0)
        tw = TimeWarp(t)
        np.testing.assert_allclose(tw.solve(p, p, np.ones(n)).times, t, atol=1e-10, err_msg=str(case))
        ph = p + rng.normal(0, 0.01, p.shape)
        rho = rng.uniform(0.5, 2.0, n)
        out = tw.solve(ph, p, rho)
        assert out.times[0] == 0 and np.all(np.diff(out.times) >= 0.05 * np.diff(t) - 1e-15), case
        assert np.isfinite(out.times).all()


def test_slow_keys_keep_their_timing() -> None:
    t = np.linspace(0, 2, 201)
    p = np.zeros((201, 2))
    p[:, 0] = np.where(t < 1, 0.001 * t, 0.001 + 1.2 * (t - 1))   # standing (1 mm/s), then walking at 1.2 m/s
    w = TimeWarp(t).solve(p, 2 * p, speed_ratio(np.full(201, 2.0)))
    # away from the change of pace the standing keys keep their steps; near it the central sums' odd/even
    # freedom (held by the smoothness term) lets the walking part's longer steps reach a few keys back
    far = t < 0.6
    np.testing.assert_allclose(np.diff(w.times)[far[:-1]], np.diff(t)[far[:-1]], rtol=1e-2)
    stand = t < 0.95
    np.testing.assert_allclose(np.diff(w.times)[stand[:-1]], np.diff(t)[stand[:-1]], rtol=5e-2)
    walking = t > 1.1
    assert np.diff(w.times)[walking[:-1]].mean() == pytest.approx(0.01 * 2 ** (1 / 6), rel=1e-2)


def test_the_stride_ratio_spline_goes_through_its_knots_and_holds_at_the_ends() -> None:
    a = np.linspace(0, 4, 401)
    keys = [0, 100, 200, 300, 400]
    sig = stride_ratio_per_key(a, keys, [1.0, 1.5, 0.8, 1.2])
    for k, (i, j) in enumerate(itertools.pairwise(keys)):
        assert sig[(i + j) // 2] == pytest.approx([1.0, 1.5, 0.8, 1.2][k], abs=1e-9)
    assert sig[0] == pytest.approx(1.0) and sig[-1] == pytest.approx(1.2)
    assert set(stride_ratio_per_key(a, [0, 400], [1.3]).tolist()) == {1.3}
    with pytest.raises(ValueError, match="segments"):
        stride_ratio_per_key(a, keys, [1.0])


def test_the_stride_law() -> None:
    assert froude(1.4, 0.9) == pytest.approx(1.4**2 / (9.81 * 0.9))
    # Alexander: stride grows with speed as Fr^0.3, so speed goes as stride^(5/3)
    l1, l2 = alexander_stride(1.0, 0.9), alexander_stride(2.0, 0.9)
    assert l2 / l1 == pytest.approx(2 ** 0.6)
    assert (l2 / l1) ** (5 / 3) == pytest.approx(2.0)
