"""Contact detection for path editing (``retarget.path_contacts``, issue 19's first step) on the real CMU takes
(a walk, a walk with a turn, a run, a forward jump) and perfcap's procedural clips: double stances of a walk,
single stances and flights of a run, the one flight of a jump at the gravity it fell with; agreement with the
procedural clips' known contacts; the same answer for any placement of the take on the floor (a seeded sweep);
the locally maximal periods of random contact counts."""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path

import numpy as np
import pytest

from capture.quat import quat_from_axis_angle, quat_mul
from retarget.bvh import CMU_SCALE, read_bvh
from retarget.clips import default_clips
from retarget.path_contacts import ContactConfig, detect_contacts, find_legs, locally_maximal_periods
from retarget.skeleton import Clip, Skeleton

CMU = Path(__file__).resolve().parents[3].parent / "shared" / "traces" / "d_mocap_cyclic" / "cmu_016"


def cmu(name: str) -> Clip:
    path = CMU / name
    if not path.exists():
        pytest.skip(f"{path} not found (../shared/traces must sit beside the project)")
    return read_bvh(path, scale=CMU_SCALE, end_sites=True)[1]


def test_a_walk_has_its_double_stances_and_no_flight() -> None:
    c = detect_contacts(cmu("16_21_walk.bvh"))
    assert c.detected and not c.flights
    assert len(c.periods) == 5 and all(int(c.count[a]) == 2 for a, _ in c.periods)
    # between two double stances one foot stands, the other swings: left and right alternate
    stance = []
    for (_, b), (a, _) in zip(c.periods[:-1], c.periods[1:], strict=True):
        assert (c.count[b:a] == 1).all()
        stance.append("left" if c.feet["left"][b:a].all() else "right")
    assert all(x != y for x, y in itertools.pairwise(stance)), stance


def test_a_walk_with_a_turn_keeps_every_step() -> None:
    c = detect_contacts(cmu("16_18_walk_left_turn.bvh"))
    assert not c.flights and len(c.periods) == 8 and all(int(c.count[a]) == 2 for a, _ in c.periods)


def test_a_run_is_single_stances_and_flights_at_the_right_gravity() -> None:
    clip = cmu("16_35_run.bvh")
    c = detect_contacts(clip)
    assert len(c.periods) == 4 and all(int(c.count[a]) == 1 for a, _ in c.periods)
    assert len(c.flights) == 3
    for f in c.flights:
        assert 0.15 <= (f.landing - f.takeoff) / clip.fps <= 0.25
        assert 8.0 <= f.g <= 11.0
        assert c.count[f.takeoff] > 0 and c.count[f.landing] > 0 and not c.count[f.takeoff + 1:f.landing].any()


def test_a_forward_jump_has_one_flight_falling_at_g() -> None:
    clip = cmu("16_06_forward_jump.bvh")
    c = detect_contacts(clip)
    assert len(c.flights) == 1
    f = c.flights[0]
    assert 0.40 <= (f.landing - f.takeoff) / clip.fps <= 0.45 and 9.0 <= f.g <= 11.0
    assert len(c.periods) == 2   # standing before take-off and after landing


@pytest.mark.parametrize("name", ["walk", "run", "crouch_walk"])
def test_procedural_clips_use_their_contacts_and_detection_agrees(name: str) -> None:
    clip = default_clips()[name]
    given = detect_contacts(clip)
    assert not given.detected
    for side in ("left", "right"):
        np.testing.assert_array_equal(given.feet[side], clip.contacts[f"{side}_foot"])
    found = detect_contacts(dataclasses.replace(clip, contacts={}))
    assert found.detected
    for side in ("left", "right"):
        assert float(np.mean(found.feet[side] == given.feet[side])) >= 0.9, side


def _placed(clip: Clip, yaw: float, shift: np.ndarray) -> Clip:
    q = quat_from_axis_angle([0.0, 1.0, 0.0], yaw)
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    rots = clip.rotations.copy()
    rots[:, 0] = quat_mul(q, rots[:, 0])
    return dataclasses.replace(clip, root_pos=clip.root_pos @ rot.T + shift, rotations=rots)


def test_the_same_contacts_wherever_the_take_is_on_the_floor() -> None:
    """A seeded sweep of turns about the vertical and shifts along the floor (and of its height, which moves
    the floors with it): the masks do not change."""
    clip = cmu("16_21_walk.bvh")
    want = detect_contacts(clip)
    rng = np.random.default_rng(19)
    for _ in range(40):
        moved = _placed(clip, float(rng.uniform(-np.pi, np.pi)), rng.uniform(-50, 50, 3))
        got = detect_contacts(moved)
        for side in ("left", "right"):
            assert int(np.sum(got.feet[side] != want.feet[side])) <= 2, side   # float rounding at a threshold
        assert len(got.periods) == len(want.periods)


def test_locally_maximal_periods_on_random_counts() -> None:
    rng = np.random.default_rng(7)
    for _ in range(500):
        count = np.repeat(rng.integers(0, 4, int(rng.integers(1, 12))), rng.integers(1, 6, 1)).astype(np.intp)
        count = np.repeat(count, rng.integers(1, 4, len(count)))
        periods = locally_maximal_periods(count)
        ch = np.flatnonzero(np.diff(count)) + 1
        starts, ends = np.concatenate([[0], ch]), np.concatenate([ch, [len(count)]])
        for k, (a, b) in enumerate(zip(starts, ends, strict=True)):
            c = int(count[a])
            left = int(count[starts[k - 1]]) if k else -1
            right = int(count[starts[k + 1]]) if k + 1 < len(starts) else -1
            assert ((int(a), int(b)) in periods) == (c > 0 and c >= left and c >= right)


def test_legs_by_rig_family_and_a_clear_error_without_them() -> None:
    left, right = find_legs(cmu("16_21_walk.bvh").skeleton)
    assert (left.side, right.side) == ("left", "right") and 0.8 < left.length < 0.9
    bare = Skeleton(("root", "a"), np.array([-1, 0]), np.array([[0.0, 0, 0], [0, 1.0, 0]]))
    with pytest.raises(ValueError, match="no legs found"):
        find_legs(bare)
    with pytest.raises(ValueError, match="height_per_leg"):
        ContactConfig(height_per_leg=0.0)
