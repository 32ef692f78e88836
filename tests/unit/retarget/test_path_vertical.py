"""The vertical solve of path editing (``retarget.path_vertical``): unmoved handles give the original heights
exactly, a constant lift moves the curve exactly so, and so does a lift growing linearly along the arclength
where no tangent is kept (the shear frame's invariances); a lifted handle reaches its height with the kept
tangents holding and its neighbours following smoothly. On the CMU walk and a seeded sweep of random height
profiles with pauses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from retarget.bvh import CMU_SCALE, read_bvh
from retarget.path_contacts import detect_contacts
from retarget.path_handles import select_handles
from retarget.path_vertical import VerticalPath

TRACES = Path(__file__).resolve().parents[3].parent / "shared" / "traces" / "d_mocap_cyclic"


def walk() -> tuple[np.ndarray, np.ndarray, list[int], list[int]]:
    path = TRACES / "cmu_016" / "16_21_walk.bvh"
    if not path.exists():
        pytest.skip(f"{path} not found (../shared/traces must sit beside the project)")
    clip = read_bvh(path, scale=CMU_SCALE, end_sites=True)[1]
    hs = [h for h in select_handles(clip.root_pos, clip.fps, detect_contacts(clip)) if h.kind == "path"]
    xz = clip.root_pos[:, [0, 2]]
    a = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xz, axis=0), axis=1))])
    keys = [h.key for h in hs]
    return a, clip.root_pos[:, 1].copy(), keys, keys[1:-1]


def random_profile(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, list[int], list[int]]:
    n = int(rng.integers(20, 300))
    a = np.concatenate([[0.0], np.cumsum(rng.uniform(0, 0.02, n - 1) * (rng.random(n - 1) > 0.1))])
    y = 0.95 + 0.03 * np.sin(a * rng.uniform(3, 9)) + rng.normal(0, 0.002, n)
    inner = sorted(int(k) for k in rng.choice(np.arange(4, n - 4), int(rng.integers(0, max(1, n // 30))),
                                              replace=False))
    inner = [k for i, k in enumerate(inner) if i == 0 or k - inner[i - 1] > 3]
    return a, y, [0, *inner, n - 1], inner


def test_identity_constant_and_linear_lifts_are_exact_on_the_walk() -> None:
    a, y, keys, tangents = walk()
    v = VerticalPath(a, y, keys, tangents)
    np.testing.assert_array_equal(v.solve(np.zeros(len(keys))), y)
    np.testing.assert_allclose(v.solve(np.full(len(keys), 0.3)), y + 0.3, atol=1e-9)
    slope = 0.1   # a ramp along the path: the shear frame keeps it where no tangent is held level
    free = VerticalPath(a, y, keys)
    np.testing.assert_allclose(free.solve(slope * a[keys]), y + slope * a, atol=1e-9)


def test_a_lifted_handle_reaches_its_height_and_keeps_its_tangent() -> None:
    a, y, keys, tangents = walk()
    v = VerticalPath(a, y, keys, tangents)
    lifts = np.zeros(len(keys))
    lifts[3] = 0.1
    out = v.solve(lifts)
    np.testing.assert_allclose(out[keys], y[keys] + lifts, atol=1e-12)
    for h in tangents:
        assert out[h + 1] - out[h - 1] == pytest.approx(y[h + 1] - y[h - 1], abs=1e-12)
    rise = out - y
    assert rise[keys[2]:keys[4] + 1].min() >= -1e-9 and rise.max() <= 0.1 + 0.02   # neighbours follow, little overshoot
    assert np.abs(rise[: keys[1] + 1]).max() < 0.02 and np.abs(rise[keys[5]:]).max() < 0.02   # far keys barely move


def test_the_invariances_on_random_profiles() -> None:
    rng = np.random.default_rng(197)
    for case in range(200):
        a, y, keys, tangents = random_profile(rng)
        v = VerticalPath(a, y, keys, tangents)
        np.testing.assert_array_equal(v.solve(np.zeros(len(keys))), y, err_msg=str(case))
        c, slope = float(rng.uniform(-1, 1)), float(rng.uniform(-0.5, 0.5))
        np.testing.assert_allclose(v.solve(np.full(len(keys), c)), y + c, atol=1e-8, err_msg=str(case))
        ramp = VerticalPath(a, y, keys).solve(c + slope * a[keys])
        np.testing.assert_allclose(ramp, y + c + slope * a, atol=1e-8, err_msg=str(case))
        lifts = rng.normal(0, 0.05, len(keys))
        out = v.solve(lifts)
        np.testing.assert_allclose(out[keys], y[keys] + lifts, atol=1e-12, err_msg=str(case))
        for h in tangents:
            assert out[h + 1] - out[h - 1] == pytest.approx(y[h + 1] - y[h - 1], abs=1e-9), case


def test_bad_inputs() -> None:
    a = np.linspace(0, 1, 10)
    with pytest.raises(ValueError, match="handle keys"):
        VerticalPath(a, np.zeros(10), [0, 5])
    with pytest.raises(ValueError, match="non-decreasing"):
        VerticalPath(a[::-1], np.zeros(10), [0, 9])
    with pytest.raises(ValueError, match="tangent keys"):
        VerticalPath(a, np.zeros(10), [0, 9], [4])
    with pytest.raises(ValueError, match="one per handle"):
        VerticalPath(a, np.zeros(10), [0, 9]).solve(np.zeros(3))
