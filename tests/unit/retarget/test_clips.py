"""The embedded default clips: shapes, closed loops, planted feet (sliding measured with Skeleton.fk), root
speeds, key-times at the touch-downs, get-up ending in the idle pose, the tucked mid-jump."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from retarget.clips import CLIP_NAMES, DEFAULT_FPS, GAITS, default_clips
from retarget.skeleton import Clip, Skeleton, humanoid

LOCOMOTION = {"walk": (1.4, 1.0), "run": (3.5, 0.7), "crouch_walk": (0.8, 1.2)}
DURATIONS = {"idle": 2.0, "walk": 1.0, "run": 0.7, "crouch_idle": 2.0, "crouch_walk": 1.2, "get_up": 1.5,
             "mid_jump": 0.5}
FEET = (("Left", "left_foot"), ("Right", "right_foot"))


@pytest.fixture(scope="module")
def clips() -> dict[str, Clip]:
    return default_clips()


def stance_runs(contact: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) frame ranges where the contact is on."""
    d = np.diff(np.r_[0, contact.astype(int), 0])
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True))


def two_cycles(clip: Clip) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """FK positions and contacts of a loop played twice (the root carried on), so no stance is cut."""
    pos = clip.skeleton.fk(clip.root_pos, clip.rotations)
    assert isinstance(pos, np.ndarray)
    advance = clip.root_pos[-1] - clip.root_pos[0]
    both = np.concatenate([pos[:-1], pos + advance], axis=0)
    contacts = {k: np.concatenate([c[:-1], c]) for k, c in clip.contacts.items()}
    return both, contacts


def foot_sliding(clip: Clip) -> list[float]:
    """Per complete stance: the largest distance the ball of the foot (the Toes joint, the pivot on the
    ground) moves from where it touched down, in metres."""
    pos, contacts = two_cycles(clip)
    sk = clip.skeleton
    out = []
    for side, key in FEET:
        toes = pos[:, sk.index(f"{side}Toes")]
        for a, b in stance_runs(contacts[key]):
            if a == 0 or b == len(toes):
                continue  # cut by the ends of the two cycles
            out.append(float(np.linalg.norm(toes[a:b] - toes[a], axis=1).max()))
    return out


def test_seven_clips_of_the_right_shape(clips: dict[str, Clip]) -> None:
    assert tuple(clips) == CLIP_NAMES
    sk = humanoid()
    for name, clip in clips.items():
        assert clip.name == name and clip.fps == DEFAULT_FPS
        assert clip.skeleton.names == sk.names
        np.testing.assert_allclose(clip.skeleton.offsets, sk.offsets)
        f = clip.n_frames
        assert clip.duration == pytest.approx(DURATIONS[name])
        assert clip.rotations.shape == (f, 30, 4) and clip.root_pos.shape == (f, 3)
        assert np.all(np.isfinite(clip.rotations)) and np.all(np.isfinite(clip.root_pos))
        np.testing.assert_allclose(np.linalg.norm(clip.rotations, axis=-1), 1.0, atol=1e-12)
        assert set(clip.contacts) == {"left_foot", "right_foot"}
        assert all(c.dtype == bool and c.shape == (f,) for c in clip.contacts.values())
        assert clip.loop == (name not in ("get_up", "mid_jump"))
        # verbs-and-adverbs start state: X = Z = 0
        assert clip.root_pos[0, 0] == pytest.approx(0.0, abs=1e-12)
        assert clip.root_pos[0, 2] == pytest.approx(0.0, abs=1e-12)


def test_loops_close_and_advance_at_their_speed(clips: dict[str, Clip]) -> None:
    for name, clip in clips.items():
        if not clip.loop:
            continue
        pos = clip.positions()
        advance = clip.root_pos[-1] - clip.root_pos[0]
        assert np.abs(pos[-1] - advance - pos[0]).max() < 1e-3, name
        speed = LOCOMOTION.get(name, (0.0, 0.0))[0]
        np.testing.assert_allclose(advance, [0.0, 0.0, speed * clip.duration], atol=1e-9)
        assert clip.root_speed() == pytest.approx(speed, abs=0.02)
        # constant speed along +Z, no drift sideways over the loop
        np.testing.assert_allclose(np.diff(clip.root_pos[:, 2]), speed / clip.fps, atol=1e-12)
        # joint rotations close too (up to sign)
        assert np.all(np.abs(np.sum(clip.rotations[0] * clip.rotations[-1], axis=-1)) > 1 - 1e-9)


@pytest.mark.parametrize("name", sorted(LOCOMOTION))
def test_feet_do_not_slide_in_stance(clips: dict[str, Clip], name: str) -> None:
    clip = clips[name]
    slides = foot_sliding(clip)
    assert len(slides) >= 2  # a complete stance of each foot
    assert max(slides) < 0.01
    # and the stance foot is really on the ground: the ball at its resting height
    pos, contacts = two_cycles(clip)
    sk = clip.skeleton
    for side, key in FEET:
        toes_y = pos[:, sk.index(f"{side}Toes"), 1]
        np.testing.assert_allclose(toes_y[contacts[key]], 0.015, atol=1e-9)
        assert toes_y.min() > 0.015 - 1e-9  # nothing goes through the floor


def test_idles_keep_both_feet_planted(clips: dict[str, Clip]) -> None:
    for name in ("idle", "crouch_idle"):
        clip = clips[name]
        assert all(c.all() for c in clip.contacts.values())
        pos = clip.positions()
        for side, _ in FEET:
            for joint in ("Foot", "Toes"):
                p = pos[:, clip.skeleton.index(f"{side}{joint}")]
                assert np.abs(p - p[0]).max() < 1e-9
        # breathing: the chest moves a little, the root only millimetres
        chest = pos[:, clip.skeleton.index("UpperChest")]
        assert 0.001 < np.ptp(chest[:, 2]) < 0.05
        assert np.ptp(clip.root_pos[:, 1]) < 0.01


def test_gait_structure_and_key_times(clips: dict[str, Clip]) -> None:
    for name, (speed, cycle) in LOCOMOTION.items():
        clip = clips[name]
        g = GAITS[name]
        assert (g.speed, g.cycle) == (speed, cycle)
        left, right = clip.contacts["left_foot"], clip.contacts["right_foot"]
        # the loop starts at the left touch-down; each foot touches down once per cycle
        assert left[0] and not left[-2]
        rising = {k: np.flatnonzero(c[1:] & ~c[:-1]) + 1 for k, c in clip.contacts.items()}
        assert len(rising["left_foot"]) == 1 and rising["left_foot"][0] == clip.n_frames - 1
        assert len(rising["right_foot"]) == 1
        # key-times: 0, the right touch-down, the duration (= the next left touch-down)
        kt = clip.key_times
        assert kt[0] == 0.0 and kt[-1] == pytest.approx(clip.duration)
        assert all(b > a for a, b in itertools.pairwise(kt))
        assert kt == pytest.approx((0.0, rising["right_foot"][0] / clip.fps, clip.duration))
        assert kt[1] == pytest.approx(cycle / 2)
        # duty factors: a walk has double support, a run a flight phase
        assert left.mean() == pytest.approx(g.duty, abs=2 / clip.n_frames)
        if g.duty > 0.5:
            assert np.any(left & right) and not np.any(~left & ~right)
        else:
            assert np.any(~left & ~right) and not np.any(left & right)


def test_arms_swing_against_the_legs_and_the_body_is_upright(clips: dict[str, Clip]) -> None:
    for name in LOCOMOTION:
        clip = clips[name]
        pos = clip.positions()
        sk = clip.skeleton
        rel = pos - clip.root_pos[:, None, :]
        hand = rel[:, sk.index("LeftHand"), 2]
        ankle = rel[:, sk.index("LeftFoot"), 2]
        assert np.corrcoef(hand, ankle)[0, 1] < -0.5, name
        assert np.all(pos[:, sk.index("Head"), 1] > pos[:, 0, 1] + 0.3)
        assert np.all(pos[:, sk.index("LeftFoot"), 1] < pos[:, 0, 1] - 0.3)
        # hips bob: the root height changes, by centimetres
        assert 0.01 < np.ptp(clip.root_pos[:, 1]) < 0.08
    # crouching walks lower than walking
    assert clips["crouch_walk"].root_pos[:, 1].max() < clips["walk"].root_pos[:, 1].min() - 0.2
    assert clips["crouch_idle"].root_pos[:, 1].max() < clips["idle"].root_pos[:, 1].min() - 0.2


def test_get_up_goes_from_lying_to_the_idle_pose(clips: dict[str, Clip]) -> None:
    get_up, idle = clips["get_up"], clips["idle"]
    sk = get_up.skeleton
    pos = get_up.positions()
    first = pos[0]
    # lying on the back: everything within 0.3 m of the floor, head and feet far apart along Z
    assert first[:, 1].max() < 0.3
    assert first[sk.index("Head"), 2] < first[0, 2] < first[sk.index("LeftFoot"), 2]
    # ends in the idle's first pose, having moved 0.35 m along +Z (towards where its feet were)
    idle_first = idle.positions()[0]
    moved = get_up.root_pos[-1] - idle.root_pos[0]
    np.testing.assert_allclose(moved, [0.0, 0.0, 0.35], atol=1e-12)
    assert np.abs(pos[-1] - moved - idle_first).max() < 0.02
    assert get_up.key_times[0] == 0.0 and get_up.key_times[-1] == pytest.approx(1.5)
    assert pos[..., 1].min() > 0.0  # nothing under the floor
    # the feet rest, are dragged in, then planted for the rise: contacts only where they stand still
    for side, key in FEET:
        contact = get_up.contacts[key]
        assert not contact[get_up.n_frames // 4]
        ankle = pos[:, sk.index(f"{side}Foot")]
        runs = stance_runs(contact)
        a, b = runs[-1]
        assert b == get_up.n_frames and b - a > get_up.n_frames // 3
        for a, b in runs:
            assert np.abs(ankle[a:b] - ankle[a]).max() < 0.01
    # the head comes up from the floor to standing height, never dipping back to the floor on the way
    head_y = pos[:, sk.index("Head"), 1]
    assert head_y[0] < 0.3 and head_y[-1] > 1.4
    assert np.all(head_y[get_up.n_frames // 3:] > 0.5)


def test_mid_jump_is_airborne_and_tucks(clips: dict[str, Clip]) -> None:
    clip = clips["mid_jump"]
    sk = clip.skeleton
    assert not any(c.any() for c in clip.contacts.values())
    assert clip.key_times == pytest.approx((0.0, 0.25, 0.5))
    pos = clip.positions()
    knee = pos[:, sk.index("LeftLowerLeg")]
    hip = pos[:, sk.index("LeftUpperLeg")]
    ankle = pos[:, sk.index("LeftFoot")]
    u, v = hip - knee, ankle - knee
    bend = 180 - np.degrees(np.arccos(np.sum(u * v, 1) / np.linalg.norm(u, axis=1) / np.linalg.norm(v, axis=1)))
    mid = clip.n_frames // 2
    assert bend[mid] > bend[0] + 30 and bend[mid] > bend[-1] + 30
    assert pos[mid, sk.index("LeftFoot"), 1] > pos[0, sk.index("LeftFoot"), 1] + 0.2
    assert pos[..., 1].min() > 0.0


def test_clips_are_deterministic_and_follow_the_skeleton_size(clips: dict[str, Clip]) -> None:
    again = default_clips()
    for name, clip in clips.items():
        np.testing.assert_array_equal(again[name].rotations, clip.rotations)
        np.testing.assert_array_equal(again[name].root_pos, clip.root_pos)
    small = default_clips(humanoid(1.5))
    k = 1.5 / 1.75
    assert small["walk"].root_speed() == pytest.approx(1.4 * k)
    assert max(foot_sliding(small["run"])) < 0.01
    np.testing.assert_allclose(small["idle"].root_pos, clips["idle"].root_pos * k, atol=1e-12)


def test_default_clips_need_a_humanoid() -> None:
    sk = Skeleton(("Hips", "Spine"), [-1, 0], [[0, 0, 0], [0, 0.1, 0]])
    with pytest.raises(ValueError, match="missing"):
        default_clips(sk)
