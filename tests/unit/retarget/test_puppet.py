"""PuppetRetargeter end to end: scripted phone trajectories through the stick, the state machine, the
blended clips and the ragdoll give the expected state timelines and sound poses."""

from __future__ import annotations

import math

import numpy as np
import pytest

from retarget.puppet import PhoneInput, PuppetRetargeter
from retarget.states import PuppetState as S


@pytest.fixture(scope="module")
def puppet() -> PuppetRetargeter:
    return PuppetRetargeter()


def yaw(deg: float) -> tuple[float, float, float, float]:
    a = math.radians(deg) / 2
    return (math.cos(a), 0.0, math.sin(a), 0.0)


def run(p: PuppetRetargeter, path, seconds: float, fps: float = 60.0) -> list:
    """path(t) -> (position, yaw_deg, touch)."""
    p.reset()
    frames = []
    for i in range(int(seconds * fps)):
        t = i / fps
        pos, deg, touch = path(t)
        frames.append(p.step(PhoneInput(t, yaw(deg), touch, tuple(pos))))
    return frames


def timeline(frames: list) -> list[S]:
    out: list[S] = []
    for f in frames:
        if not out or out[-1] is not f.state:
            out.append(f.state)
    return out


def test_hold_still_is_locomotion_at_idle(puppet: PuppetRetargeter) -> None:
    fr = run(puppet, lambda t: ((0, 1.3, 0), 0.0, t > 0.2), 3.0)
    assert timeline(fr) == [S.RELEASED, S.LOCOMOTION]
    assert fr[-1].blend[0] < 0.05 and fr[-1].blend[1] > 0.95
    for f in fr:
        assert np.all(np.isfinite(f.rotations)) and np.allclose(np.linalg.norm(f.rotations, axis=1), 1, atol=1e-9)


@pytest.mark.parametrize("speed,lo,hi", [(0.7, 0.2, 0.45), (1.4, 0.45, 0.55), (3.0, 0.8, 1.0)])
def test_walk_and_run_follow_the_stick(puppet: PuppetRetargeter, speed: float, lo: float, hi: float) -> None:
    fr = run(puppet, lambda t: ((0, 1.3, max(0.0, t - 1) * speed), 0.0, True), 6.0)
    assert timeline(fr)[-1] is S.LOCOMOTION and S.RAGDOLL not in timeline(fr)
    assert lo <= fr[-1].blend[0] <= hi
    # the character keeps up with the stick (it is drawn to it, at the animation's own pace)
    grabbed_z = 1.5
    assert abs(fr[-1].root_pos[2] - (grabbed_z + 5 * speed)) < 0.3 * speed + 0.1
    # its speed matches over the last 2 s
    z = np.array([f.root_pos[2] for f in fr[-120:]])
    assert abs((z[-1] - z[0]) / (119 / 60) - speed) < 0.05 * speed + 0.02


def test_crouch_when_the_stick_goes_down(puppet: PuppetRetargeter) -> None:
    fr = run(puppet, lambda t: ((0, 1.3 - 0.35 * min(1.0, max(0.0, t - 1)), 0), 0.0, True), 4.0)
    assert timeline(fr) == [S.LOCOMOTION]      # held from the first frame
    assert fr[-1].blend[1] < 0.3
    assert fr[-1].root_pos[1] < fr[0].root_pos[1] - 0.1


def jump_path(rise_twice: bool = False, turn: float = 0.0, hover: bool = False):
    def path(t: float):
        if t < 1.0:
            return (0, 1.3, 0), 0.0, True
        s = t - 1.0
        z = 1.0 * s
        if hover and s > 0.35:      # stops in the air, where it was (0.27 m up, still rising)
            return (0, 1.3 + 2.5 * 0.35 - 0.5 * 9.81 * 0.35 ** 2, 0.35), 0.0, True
        v0 = 2.5
        y = 1.3 + v0 * s - 0.5 * 9.81 * s * s
        if rise_twice and s > 0.35:
            y = 1.3 + v0 * 0.35 - 0.5 * 9.81 * 0.35 ** 2 + 1.5 * (s - 0.35)
        deg = turn * min(1.0, max(0.0, (s - 0.35) / 0.1))   # turning once airborne
        return (0, max(1.3, y), z), deg, True
    return path


def test_a_clean_jump_lands(puppet: PuppetRetargeter) -> None:
    fr = run(puppet, jump_path(), 3.5)
    tl = timeline(fr)
    assert tl[:4] == [S.LOCOMOTION, S.JUMP_ANTICIPATION, S.AIRBORNE, S.LANDING], tl
    assert tl[-1] is S.LOCOMOTION and S.RAGDOLL not in tl
    t_anti = next(f.t for f in fr if f.state is S.JUMP_ANTICIPATION)
    t_air = next(f.t for f in fr if f.state is S.AIRBORNE)
    assert abs((t_air - t_anti) - 0.2) <= 1 / 60 + 1e-9       # the anticipation squat


@pytest.mark.parametrize(("kind", "reason"), [("rise_twice", "re_rise"), ("turn", "turn"), ("hover", "stop")])
def test_invalid_jumps_fall_limp(puppet: PuppetRetargeter, kind: str, reason: str) -> None:
    path = jump_path(rise_twice=kind == "rise_twice", turn=45.0 if kind == "turn" else 0.0, hover=kind == "hover")
    fr = run(puppet, path, 2.5)
    tl = timeline(fr)
    assert S.AIRBORNE in tl and S.RAGDOLL in tl, tl
    assert tl.index(S.RAGDOLL) > tl.index(S.AIRBORNE)
    limp = next(tr for f in fr for tr in f.transitions if tr.to_state is S.RAGDOLL)
    assert limp.reason == reason


def test_ragdoll_held_up_then_put_down_gets_up(puppet: PuppetRetargeter) -> None:
    # lifted 0.6 m without jump momentum: ragdoll (hanging from the stick); put down and let go: it
    # lies still, then gets up and stands
    def path(t: float):
        if t < 1.0:
            return (0, 1.3, 0), 0.0, True
        if t < 3.0:
            return (0, 1.3 + 0.6 * min(1.0, (t - 1.0) / 1.5), 0), 0.0, True
        return (0, 1.3, 0), 0.0, False
    fr = run(puppet, path, 12.0)
    tl = timeline(fr)
    assert S.RAGDOLL in tl and S.GET_UP in tl, tl
    assert tl.index(S.GET_UP) > tl.index(S.RAGDOLL)
    assert tl[-1] in (S.RELEASED, S.LOCOMOTION)
    ragdoll = [f for f in fr if f.state is S.RAGDOLL]
    joints = puppet.skeleton.fk(ragdoll[-1].root_pos, ragdoll[-1].rotations)
    assert joints[:, 1].min() > -0.05                        # nothing through the floor
    final = puppet.skeleton.fk(fr[-1].root_pos, fr[-1].rotations)
    assert final[puppet.skeleton.index("Head"), 1] > 1.4     # standing again
    # where it lay: the get-up moves the character by its clip's own root travel only
    lay = ragdoll[-1].root_pos
    get_up = [f for f in fr if f.state is S.GET_UP]
    clip = puppet.clips["get_up"]
    travel = float(np.linalg.norm((clip.root_pos[-1] - clip.root_pos[0])[[0, 2]]))
    for f in get_up + fr[-10:]:
        assert np.hypot(f.root_pos[0] - lay[0], f.root_pos[2] - lay[2]) < travel + 0.6


def test_held_still_at_the_grab_height_after_falling_limp_gets_up(puppet: PuppetRetargeter) -> None:
    # lifted without jump momentum (ragdoll), then brought back to the grab height and held there still:
    # the feet are down, so it gets up although the player never lets go or pushes the phone lower
    def path(t: float):
        if t < 1.0 or t >= 3.0:
            return (0, 1.3, 0), 0.0, True
        return (0, 1.3 + 0.6 * math.sin(math.pi * (t - 1.0) / 2.0), 0), 0.0, True
    tl = timeline(run(puppet, path, 12.0))
    assert S.RAGDOLL in tl and S.GET_UP in tl and tl[-1] is S.LOCOMOTION, tl


@pytest.mark.parametrize("direction", [(1.0, 0.0), (0.0, -1.0), (-0.7071, 0.7071)])
def test_the_character_walks_forwards_whichever_way_the_stick_goes(puppet: PuppetRetargeter,
                                                                    direction: tuple[float, float]) -> None:
    # sideways, backwards and diagonally: it turns to face its travel and keeps up, feet not moonwalking
    speed = 1.4
    dx, dz = direction
    fr = run(puppet, lambda t: ((dx * speed * max(0.0, t - 1), 1.3, dz * speed * max(0.0, t - 1)), 0.0, True), 6.0)
    assert S.RAGDOLL not in timeline(fr)
    last = fr[-1]
    end = np.array([dx, 0.0, dz]) * speed * 5.0 + np.array([0.0, 0.0, 1.5])
    assert np.hypot(last.root_pos[0] - end[0], last.root_pos[2] - end[2]) < 0.5
    assert abs(math.remainder(puppet.heading - math.atan2(dx, dz), 2 * math.pi)) < math.radians(5)


def test_state_changes_neither_stop_nor_rush_the_root(puppet: PuppetRetargeter) -> None:
    # a running jump: the root's ground speed stays near the stick's through anticipation, flight and landing
    def path(t: float):
        z = 2.5 * t
        s = t - 2.0
        y = 1.3 + (2.5 * s - 4.905 * s * s if 0 <= s <= 0.5 else 0.0)
        return (0, y, z), 0.0, True
    fr = run(puppet, path, 4.0)
    tl = timeline(fr)
    assert S.AIRBORNE in tl and S.RAGDOLL not in tl, tl
    z = np.array([f.root_pos[2] for f in fr])
    v = np.diff(z) * 60.0
    window = v[int(1.5 * 60):int(3.5 * 60)]
    assert window.min() > 0.5 and window.max() < 5.0, (window.min(), window.max())


def test_release_while_grounded(puppet: PuppetRetargeter) -> None:
    fr = run(puppet, lambda t: ((0, 1.3, 0), 0.0, 0.2 < t < 2.0), 3.0)
    assert timeline(fr) == [S.RELEASED, S.LOCOMOTION, S.RELEASED]


def test_time_must_not_go_back(puppet: PuppetRetargeter) -> None:
    puppet.reset()
    puppet.step(PhoneInput(1.0, (1.0, 0, 0, 0), False))
    with pytest.raises(ValueError):
        puppet.step(PhoneInput(0.5, (1.0, 0, 0, 0), False))
    with pytest.raises(ValueError):
        puppet.step(PhoneInput(2.0, (0.0, 0, 0, 0), False))


def test_the_parabolas_apex_drives_the_mid_jump_clip(puppet: PuppetRetargeter) -> None:
    # a high jump (apex 0.61 s after the trigger, 0.41 s after takeoff, past the crossfade): at the stick's
    # apex the pose is the clip's tuck (its middle key-time), and the clip does not run on by time alone
    v0 = 6.0

    def path(t: float):
        s = max(0.0, t - 1.0)
        return (0, max(1.3, 1.3 + v0 * s - 4.905 * s * s), 1.0 * s), 0.0, True
    fr = run(puppet, path, 2.5)
    assert S.AIRBORNE in timeline(fr) and S.RAGDOLL not in timeline(fr)
    clip = puppet.clips["mid_jump"]
    apex = min((f for f in fr if f.state is S.AIRBORNE), key=lambda f: abs(f.t - (1.0 + v0 / 9.81)))
    _, tuck = clip.sample(clip.key_times[1])
    np.testing.assert_allclose(np.abs(np.sum(apex.rotations[1:] * tuck[1:], axis=1)), 1.0, atol=2e-3)


def test_regrabbing_a_lying_ragdoll_does_not_yank_it(puppet: PuppetRetargeter) -> None:
    # lifted limp, let go (it falls and lies), grabbed again from above: the held chest stays where it lies
    def path(t: float):
        if t < 1.0:
            return (0, 1.3, 0), 0.0, True
        if t < 3.0:
            return (0, 1.3 + 0.6 * min(1.0, (t - 1.0) / 1.5), 0), 0.0, True
        return (0, 1.9, 0), 0.0, t >= 3.5
    fr = run(puppet, path, 3.6)
    assert fr[-1].state is S.RAGDOLL
    chest = puppet.skeleton.index(puppet.config.hold_joint)
    k = next(i for i, f in enumerate(fr) if f.t >= 3.5)
    before, after = (puppet.skeleton.fk(f.root_pos, f.rotations)[chest] for f in (fr[k - 1], fr[k + 3]))
    assert before[1] < 0.3                                    # it was lying
    assert np.linalg.norm(after - before) < 0.1


def test_a_stick_racing_faster_than_any_gait_falls_limp(puppet: PuppetRetargeter) -> None:
    # 12 m/s along the ground: more than twice the run's pace fits no animation -> ragdoll ("too_fast");
    # until then the clips play at most twice as fast
    fr = run(puppet, lambda t: ((0, 1.3, 12.0 * max(0.0, t - 1.0)), 0.0, True), 2.5)
    tl = timeline(fr)
    assert tl == [S.LOCOMOTION, S.RAGDOLL], tl
    limp = next(tr for f in fr for tr in f.transitions if tr.to_state is S.RAGDOLL)
    assert limp.reason == "too_fast"
    assert max(f.speedup for f in fr) <= 2.0 + 1e-12


def jump_towards(direction_deg: float, speed: float, run_up: bool, turn_in_air: float = 0.0):
    """The phone jumps (2.5 m/s up) towards ``direction_deg`` at ``speed`` m/s, from a standstill or after a
    1 s run-up at that speed; its yaw stays 0 (the character turns to face its travel), or turns by
    ``turn_in_air`` degrees once airborne."""
    d = math.radians(direction_deg)
    ux, uz = math.sin(d), math.cos(d)

    def path(t: float):
        lead = min(1.0, max(0.0, t - 0.5)) * speed if run_up else 0.0
        if t < 1.5:
            return (ux * lead, 1.3, uz * lead), 0.0, True
        s = t - 1.5
        h = lead + speed * s
        y = 1.3 + 2.5 * s - 0.5 * 9.81 * s * s
        return (ux * h, max(1.3, y), uz * h), turn_in_air * min(1.0, max(0.0, (s - 0.35) / 0.1)), True
    return path


@pytest.mark.parametrize("run_up", [False, True])
@pytest.mark.parametrize("speed", [0.0, 0.8, 1.5, 3.0])
def test_standing_walking_and_running_jumps_in_every_direction_land(puppet: PuppetRetargeter, speed: float,
                                                                    run_up: bool) -> None:
    for direction in range(0, 360, 45):
        tl = timeline(run(puppet, jump_towards(direction, speed, run_up), 3.5))
        assert S.AIRBORNE in tl and S.LANDING in tl and S.RAGDOLL not in tl, (direction, tl)


@pytest.mark.parametrize("speed", [0.8, 3.0])
def test_a_turn_in_the_air_still_falls_limp_in_every_direction(puppet: PuppetRetargeter, speed: float) -> None:
    for direction in range(0, 360, 90):
        fr = run(puppet, jump_towards(direction, speed, True, turn_in_air=60.0), 2.5)
        limp = [tr.reason for f in fr for tr in f.transitions if tr.to_state is S.RAGDOLL]
        assert limp[:1] == ["turn"], (direction, timeline(fr))
