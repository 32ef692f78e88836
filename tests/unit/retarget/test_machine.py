"""Puppet state table and state machine (Ciccone 2019, sections 6.2.2 and 6.3; the table is perfcap's
reconstruction, docs/design/puppet.md).

The ``Script`` helper below generates stick-end trajectories (hold still, walk, run, crouch, jumps, hovers,
releases) frame by frame with their exact velocities, and turns them into ``PuppetContext`` frames; the
tests drive ``PuppetStateMachine.step`` with them and compare the state timelines.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import pytest

from capture.errors import InvalidTransitionError, RetargetError
from retarget.jump import JumpConfig
from retarget.machine import (
    MachineConfig,
    PuppetContext,
    PuppetStateMachine,
    Transition,
)
from retarget.states import (
    ENTRY_ACTIONS,
    EXIT_ACTIONS,
    TRANSITIONS,
    PuppetAction,
    PuppetEvent,
    PuppetState,
    next_state,
)

if TYPE_CHECKING:
    from collections.abc import Callable

S = PuppetState
E = PuppetEvent
G = 9.81
CMU_131_02 = Path(__file__).resolve().parents[3].parent / "shared/traces/d_mocap_cyclic/cmu_131_02_start_walk_stop.bvh"


# --------------------------------------------------------------------------------------------------
# Trajectory generator (test helper)
# --------------------------------------------------------------------------------------------------

class Script:
    """A scripted stick-end trajectory sampled at ``fs`` Hz.

    Each method appends a segment starting where the last one ended and returns ``self``. Frames hold the
    time, the stick end position (the ground is y = 0), its exact velocity, the facing heading, the touch
    state and the crouch parameter. ``contexts()`` turns them into ``PuppetContext`` frames, adding what a
    ragdoll simulation would report: at rest when a held stick lies still on the ground, or
    ``settle`` seconds after a release.
    """

    def __init__(self, fs: float = 60.0, heading: float = 0.0) -> None:
        self.fs = fs
        self.k = 0  # next frame index
        self.pos = np.zeros(3)
        self.heading = heading
        self.touch = True
        self.crouch = 1.0
        self.object_distance = math.inf
        self.frames: list[tuple[float, np.ndarray, np.ndarray, float, bool, float, float]] = []

    @property
    def t(self) -> float:
        return self.k / self.fs

    def _emit(self, duration: float, vel: Callable[[float], np.ndarray],
              facing: Callable[[float], float] | None = None, *, stop_on_ground: bool = False) -> Script:
        """Integrate ``vel(tau)`` (tau = time into the segment) exactly enough (midpoint) for ``duration``."""
        t0 = self.t
        n = max(1, round(duration * self.fs))
        for _ in range(n):
            tau = self.t - t0
            v = vel(tau)
            h = facing(tau) if facing is not None else self.heading
            pos = self.pos.copy()
            if stop_on_ground and tau > 0 and pos[1] <= 0.0:
                pos[1] = 0.0
                self.pos = pos
                self.frames.append((self.t, pos, v, h, self.touch, self.crouch, self.object_distance))
                self.k += 1
                break
            self.frames.append((self.t, pos, v, h, self.touch, self.crouch, self.object_distance))
            self.pos = pos + vel(tau + 0.5 / self.fs) / self.fs
            self.heading = h
            self.k += 1
        self.pos[1] = max(0.0, self.pos[1])
        return self

    def _fwd(self, speed: float, heading: float | None = None) -> np.ndarray:
        h = self.heading if heading is None else heading
        return np.array([speed * math.sin(h), 0.0, speed * math.cos(h)])

    def hold(self, duration: float) -> Script:
        return self._emit(duration, lambda tau: np.zeros(3))

    def walk(self, duration: float, speed: float, bob: float = 0.02, step_hz: float = 1.8) -> Script:
        """Move along the heading with a vertical bob ``bob * sin^2`` (touches the ground every step)."""
        w = math.pi * step_hz

        def vel(tau: float) -> np.ndarray:
            v = self._fwd(speed)
            v[1] = bob * w * math.sin(2 * w * tau)  # d/dt of bob * sin^2(w tau)
            return v
        y0 = self.pos[1]
        self._emit(duration, vel)
        self.pos[1] = y0 + bob * math.sin(w * duration) ** 2 if bob else y0
        return self

    def set_crouch(self, value: float) -> Script:
        self.crouch = value
        return self

    def set_object(self, distance: float) -> Script:
        self.object_distance = distance
        return self

    def lift(self, height: float, speed: float) -> Script:
        """Straight up (or down) at a constant speed to ``height``."""
        dy = height - self.pos[1]
        return self._emit(abs(dy) / speed, lambda tau: np.array([0.0, math.copysign(speed, dy), 0.0]))

    def ballistic(self, vy0: float, vh: float = 0.0, *, duration: float | None = None, turn_rate: float = 0.0,
                  facing_rate: float = 0.0) -> Script:
        """A ballistic arc (g = 9.81) until it is back on the ground (or for ``duration``)."""
        h0 = self.heading
        vy_start = vy0

        def vel(tau: float) -> np.ndarray:
            v = self._fwd(vh, h0 + turn_rate * tau)
            v[1] = vy_start - G * tau
            return v
        facing = (lambda tau: h0 + facing_rate * tau) if facing_rate else None
        flight = duration if duration is not None else 2 * vy0 / G + 0.2
        return self._emit(flight, vel, facing, stop_on_ground=duration is None)

    def release(self) -> Script:
        self.touch = False
        return self

    def grab(self) -> Script:
        self.touch = True
        return self

    def contexts(self, *, settle: float = 0.8, noise: float = 0.0, seed: int = 0) -> list[PuppetContext]:
        rng = np.random.default_rng(seed)
        out = []
        released_at: float | None = None
        for t, pos, vel, heading, touch, crouch, obj in self.frames:
            if not touch and released_at is None:
                released_at = t
            if touch:
                released_at = None
            p = pos + rng.uniform(-noise, noise, 3) * 0.1 if noise else pos
            v = vel + rng.uniform(-noise, noise, 3) if noise else vel
            p = np.array([p[0], max(0.0, p[1]), p[2]])
            speed = float(np.linalg.norm(vel))
            at_rest = (touch and pos[1] < 0.05 and speed < 0.1) or (
                released_at is not None and t - released_at >= settle)
            out.append(PuppetContext(t=t, position=tuple(p), velocity=tuple(v), heading=heading,
                                     height=float(p[1]), touch=touch, ragdoll_at_rest=at_rest,
                                     object_distance=obj, crouch=crouch))
        return out


def run(contexts: list[PuppetContext], machine: PuppetStateMachine | None = None
        ) -> tuple[list[PuppetState], list[Transition]]:
    """Drive a machine; return the sequence of states entered (starting with the initial) and transitions."""
    m = machine if machine is not None else PuppetStateMachine()
    states = [m.state]
    transitions: list[Transition] = []
    for ctx in contexts:
        for tr in m.step(ctx):
            transitions.append(tr)
            if tr.to_state is not states[-1]:
                states.append(tr.to_state)
    return states, transitions


RAGDOLL_JUMP = [S.RELEASED, S.LOCOMOTION, S.JUMP_ANTICIPATION, S.AIRBORNE, S.RAGDOLL]
CLEAN_JUMP = [S.RELEASED, S.LOCOMOTION, S.JUMP_ANTICIPATION, S.AIRBORNE, S.LANDING, S.LOCOMOTION]


def scripts() -> dict[str, tuple[Script, list[PuppetState]]]:
    """The issue's scripted trajectories with the state sequences they must produce."""
    return {
        "hold still": (Script().hold(3.0), [S.RELEASED, S.LOCOMOTION]),
        "slow walk": (Script().walk(4.0, 0.6), [S.RELEASED, S.LOCOMOTION]),
        "run": (Script().walk(1.0, 1.5).walk(3.0, 3.5, bob=0.05, step_hz=2.8), [S.RELEASED, S.LOCOMOTION]),
        "crouch": (Script().walk(1.0, 0.8).set_crouch(0.1).walk(2.0, 0.5, bob=0.005).set_crouch(1.0).hold(1.0),
                   [S.RELEASED, S.LOCOMOTION]),
        "crouch by an object": (
            Script().walk(1.0, 0.5).set_object(0.3).set_crouch(0.1).hold(1.0).set_object(2.0).hold(1.0),
            [S.RELEASED, S.LOCOMOTION, S.INTERACT, S.LOCOMOTION]),
        "clean jump": (Script().walk(1.0, 1.2).ballistic(3.0, 1.2).walk(1.5, 1.2), CLEAN_JUMP),
        "vertical jump": (Script().hold(1.0).ballistic(2.8).hold(1.0), CLEAN_JUMP),
        "jump that rises twice": (
            Script().walk(1.0, 1.0).ballistic(3.0, 1.0, duration=0.45).ballistic(1.5, 1.0).hold(2.0),
            [*RAGDOLL_JUMP, S.GET_UP, S.LOCOMOTION]),
        "turn in the air": (
            Script().walk(1.0, 1.5).ballistic(3.0, 1.5, turn_rate=math.radians(45) / 0.4).hold(2.0),
            [*RAGDOLL_JUMP, S.GET_UP, S.LOCOMOTION]),
        "hover": (
            Script().walk(1.0, 1.0).ballistic(2.5, 0.0, duration=2.5 / G).hold(0.3).lift(0.0, 0.5).hold(2.0),
            [*RAGDOLL_JUMP, S.GET_UP, S.LOCOMOTION]),
        "release": (Script().walk(2.0, 0.8).release().hold(2.0), [S.RELEASED, S.LOCOMOTION, S.RELEASED]),
        "held up, put down, get up": (
            Script().hold(0.5).lift(0.5, 0.4).hold(1.0).lift(0.0, 0.4).hold(2.0),
            [S.RELEASED, S.LOCOMOTION, S.RAGDOLL, S.GET_UP, S.LOCOMOTION]),
        "released in the air": (
            Script().walk(1.0, 1.0).ballistic(3.0, 1.0, duration=0.35).release().hold(3.0),
            [S.RELEASED, S.LOCOMOTION, S.JUMP_ANTICIPATION, S.AIRBORNE, S.RAGDOLL, S.GET_UP, S.LOCOMOTION,
             S.RELEASED]),
    }


SCRIPTS = scripts()


# --------------------------------------------------------------------------------------------------
# The table and handle()
# --------------------------------------------------------------------------------------------------

def test_table_is_complete_and_every_state_can_be_left():
    for state in S:
        exits = {ev for (st, ev), to in TRANSITIONS.items() if st is state and to is not state}
        assert exits, f"{state} has no exit"
        assert state in ENTRY_ACTIONS and state in EXIT_ACTIONS
    targets = set(TRANSITIONS.values())
    assert targets == set(S)  # every state is reachable
    # The rows of docs/design/puppet.md's table.
    assert TRANSITIONS[(S.LOCOMOTION, E.JUMP_TRIGGER)] is S.JUMP_ANTICIPATION
    assert TRANSITIONS[(S.LOCOMOTION, E.UNSUPPORTED)] is S.RAGDOLL
    assert TRANSITIONS[(S.JUMP_ANTICIPATION, E.TAKEOFF)] is S.AIRBORNE
    assert TRANSITIONS[(S.AIRBORNE, E.INVALID_JUMP)] is S.RAGDOLL
    assert TRANSITIONS[(S.AIRBORNE, E.TOUCHDOWN)] is S.LANDING
    assert TRANSITIONS[(S.AIRBORNE, E.RELEASE)] is S.RAGDOLL
    assert TRANSITIONS[(S.LANDING, E.LANDING_DONE)] is S.LOCOMOTION
    assert TRANSITIONS[(S.RAGDOLL, E.AT_REST)] is S.GET_UP
    assert TRANSITIONS[(S.GET_UP, E.GET_UP_DONE)] is S.LOCOMOTION
    assert TRANSITIONS[(S.RELEASED, E.GRAB)] is S.LOCOMOTION
    with pytest.raises(TypeError):
        cast("Any", TRANSITIONS)[(S.RELEASED, E.TAKEOFF)] = S.AIRBORNE  # a read-only mapping, on purpose


def test_handle_returns_actions_and_rejects_events_not_in_the_table():
    m = PuppetStateMachine()
    tr = m.handle(E.GRAB, 1.0)
    assert (tr.from_state, tr.to_state, tr.event, tr.t) == (S.RELEASED, S.LOCOMOTION, E.GRAB, 1.0)
    assert tr.actions == (PuppetAction.ATTACH_STICK, PuppetAction.PLAY_BLEND_SPACE)
    assert m.held and m.entered_at == 1.0
    tr = m.handle(E.UNSUPPORTED, 2.0)
    assert tr.actions == (PuppetAction.STOP_BLEND_SPACE, PuppetAction.START_RAGDOLL)
    # A self-transition runs only the event's actions and keeps the entry time.
    tr = m.handle(E.RELEASE, 3.0)
    assert tr.to_state is S.RAGDOLL and tr.actions == (PuppetAction.DETACH_STICK,)
    assert not m.held and m.entered_at == 2.0
    with pytest.raises(InvalidTransitionError) as info:
        m.handle(E.TAKEOFF)
    assert info.value.state is S.RAGDOLL and info.value.event is E.TAKEOFF
    assert isinstance(info.value, RetargetError)
    assert m.state is S.RAGDOLL  # unchanged
    assert not m.accepts(E.TAKEOFF) and m.accepts(E.AT_REST)
    with pytest.raises(InvalidTransitionError):
        next_state(S.LANDING, E.JUMP_TRIGGER)


# --------------------------------------------------------------------------------------------------
# Scripted timelines
# --------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", list(SCRIPTS))
def test_scripted_trajectories_give_the_expected_state_sequence(name):
    script, expected = SCRIPTS[name]
    states, transitions = run(script.contexts())
    assert states == expected, [(round(tr.t, 3), tr.to_state.name, tr.reason) for tr in transitions]
    times = [tr.t for tr in transitions]
    assert times == sorted(times)


@pytest.mark.parametrize("name", list(SCRIPTS))
def test_scripted_trajectories_with_noise_do_not_flicker(name):
    """Position jitter of +-3 mm and velocity jitter of +-0.03 m/s change nothing."""
    script, expected = SCRIPTS[name]
    for seed in range(3):
        states, _ = run(script.contexts(noise=0.03, seed=seed))
        assert states == expected


def test_invalid_jump_reasons():
    reasons = {}
    for name in ("jump that rises twice", "turn in the air", "hover"):
        _, transitions = run(SCRIPTS[name][0].contexts())
        reasons[name] = [tr.reason for tr in transitions if tr.event is E.INVALID_JUMP]
    assert reasons == {"jump that rises twice": ["re_rise"], "turn in the air": ["turn"], "hover": ["stop"]}


@pytest.mark.parametrize("fs", [60.0, 45.0, 90.0])
def test_takeoff_exactly_delay_after_the_trigger(fs):
    script = Script(fs=fs).walk(1.0, 1.0).ballistic(3.0, 1.0).walk(1.0, 1.0)
    states, transitions = run(script.contexts())
    assert states == CLEAN_JUMP
    by_event = {tr.event: tr for tr in transitions}
    t0 = by_event[E.JUMP_TRIGGER].t
    assert by_event[E.TAKEOFF].t == pytest.approx(t0 + 0.2, abs=1e-12)
    assert by_event[E.LANDING_DONE].t == pytest.approx(by_event[E.TOUCHDOWN].t + 0.2, abs=1e-12)
    # The trigger came within jump_dwell (plus a frame) of the lift.
    lift = next(c.t for c in script.contexts() if c.velocity[1] > 1.0)
    assert 0.03 - 1e-9 <= t0 - lift <= 0.03 + 1.0 / fs


def test_jump_tracker_follows_the_arc():
    script = Script().walk(1.0, 1.2).ballistic(3.0, 1.2)
    m = PuppetStateMachine()
    apex = None
    for ctx in script.contexts():
        m.step(ctx)
        if m.state is S.AIRBORNE and m.jump is not None and m.jump.arc is not None:
            apex = m.jump.arc.apex
    assert apex is not None
    assert apex[1] == pytest.approx(3.0**2 / (2 * G), abs=0.01)  # the apex height of the arc
    assert apex[0] == pytest.approx(1.2 * 3.0 / G, abs=0.01)


def test_v_jump_scales_with_character_height():
    small = MachineConfig(character_height=0.35)
    assert small.v_jump_scaled == pytest.approx(0.2)
    # A lift at 0.5 m/s is a jump for a 35 cm puppet, not for a 1.75 m one.
    script = Script().hold(0.5).lift(0.3, 0.5).hold(0.5)
    assert S.JUMP_ANTICIPATION in run(script.contexts(), PuppetStateMachine(small))[0]
    assert S.JUMP_ANTICIPATION not in run(script.contexts())[0]


def test_held_above_ground_without_momentum_is_ragdoll_then_gets_up():
    script = Script().hold(0.5).lift(0.5, 0.4).hold(1.0).lift(0.0, 0.4).hold(2.0)
    ctxs = script.contexts()
    states, transitions = run(ctxs)
    assert states == [S.RELEASED, S.LOCOMOTION, S.RAGDOLL, S.GET_UP, S.LOCOMOTION]
    above = next(c.t for c in ctxs if c.height > 0.15)
    to_ragdoll = next(tr for tr in transitions if tr.to_state is S.RAGDOLL)
    assert to_ragdoll.event is E.UNSUPPORTED
    assert 0.2 - 1e-9 <= to_ragdoll.t - above <= 0.2 + 1 / 60 + 1e-9
    get_up = next(tr for tr in transitions if tr.to_state is S.GET_UP)
    done = next(tr for tr in transitions if tr.event is E.GET_UP_DONE)
    assert done.t == pytest.approx(get_up.t + 1.0, abs=1e-12)


def test_ragdoll_does_not_get_up_while_held_high():
    script = Script().hold(0.5).lift(0.5, 0.4).hold(3.0)
    contexts = [PuppetContext(**{**{f: getattr(c, f) for f in c.__slots__}, "ragdoll_at_rest": True})
                for c in script.contexts()]
    states, _ = run(contexts)
    assert states == [S.RELEASED, S.LOCOMOTION, S.RAGDOLL]


def test_interact_needs_a_crouch():
    script = Script().walk(1.0, 0.5).set_object(0.3).hold(1.0)
    assert run(script.contexts())[0] == [S.RELEASED, S.LOCOMOTION]


# --------------------------------------------------------------------------------------------------
# Hysteresis: noisy input near the thresholds
# --------------------------------------------------------------------------------------------------

def held_at(heights: np.ndarray, fs: float = 60.0, vy: np.ndarray | None = None) -> list[PuppetContext]:
    vys = np.gradient(heights, 1 / fs) if vy is None else vy
    return [PuppetContext(t=k / fs, position=(0.0, float(h), 0.0), velocity=(0.0, float(v), 0.0), heading=0.0,
                          height=float(h), touch=True) for k, (h, v) in enumerate(zip(heights, vys, strict=True))]


def test_height_dithering_across_above_ground_gives_one_ragdoll_not_a_flicker():
    t = np.arange(0, 5, 1 / 60)
    heights = 0.15 + 0.02 * np.sin(2 * np.pi * 5 * t)  # crosses 0.15 ten times a second
    states, transitions = run(held_at(heights))
    assert states == [S.RELEASED, S.LOCOMOTION, S.RAGDOLL]
    assert len(transitions) == 2


def test_short_excursions_above_the_threshold_do_not_ragdoll():
    t = np.arange(0, 5, 1 / 60)
    heights = 0.12 + 0.04 * np.sin(2 * np.pi * 4 * t)  # 0.08..0.16: brief spells above 0.15, back below 0.10
    states, _ = run(held_at(heights))
    assert states == [S.RELEASED, S.LOCOMOTION]


def test_single_frame_velocity_spikes_do_not_trigger_a_jump():
    rng = np.random.default_rng(4)
    t = np.arange(0, 5, 1 / 60)
    vy = 0.3 * np.sin(2 * np.pi * 1.8 * t)
    spikes = rng.choice(t.size, 25, replace=False)
    spikes = spikes[np.diff(np.r_[-5, np.sort(spikes)]) > 2]
    vy[spikes] = 1.2  # isolated frames above v_jump
    states, _ = run(held_at(np.zeros_like(t), vy=vy))
    assert states == [S.RELEASED, S.LOCOMOTION]


def test_touch_flicker_is_followed_but_states_settle():
    """Touch is a button: each change is an event, and nothing else moves."""
    script = Script().hold(0.5).release().hold(0.1).grab().hold(0.5)
    states, _ = run(script.contexts())
    assert states == [S.RELEASED, S.LOCOMOTION, S.RELEASED, S.LOCOMOTION]


# --------------------------------------------------------------------------------------------------
# Real data, determinism, errors, cost
# --------------------------------------------------------------------------------------------------

def cmu_root_path(path: Path) -> tuple[np.ndarray, float]:
    """Hips positions (metres) of a CMU/cgspeed BVH (1 unit = 0.0564 m) and the frame time."""
    if not path.exists():
        pytest.skip(f"CMU BVH not found at {path} (../shared/traces must sit beside the project)")
    lines = path.read_text().splitlines()
    i = lines.index("MOTION")
    dt = float(lines[i + 2].split()[-1])
    root = np.array([[float(v) for v in line.split()[:3]] for line in lines[i + 3:] if line.strip()])
    return root * 0.0564, dt


def test_real_walk_trajectory_stays_in_locomotion():
    """CMU 131_02 (start, shuffle steps, stop): the hips path as the stick end stays in locomotion."""
    root, dt = cmu_root_path(CMU_131_02)
    vel = np.gradient(root, dt, axis=0)
    height = np.maximum(0.0, root[:, 1] - np.median(root[:, 1]))  # hips bob above the standing height
    ctxs = [PuppetContext(t=k * dt, position=(float(p[0]), float(h), float(p[2])), velocity=tuple(map(float, v)),
                          heading=math.atan2(v[0], v[2]) if math.hypot(v[0], v[2]) > 0.2 else 0.0,
                          height=float(h), touch=True)
            for k, (p, v, h) in enumerate(zip(root, vel, height, strict=True))]
    states, _ = run(ctxs)
    assert states == [S.RELEASED, S.LOCOMOTION]
    assert len(ctxs) == 1247


def test_deterministic():
    ctxs = SCRIPTS["released in the air"][0].contexts(noise=0.03, seed=9)
    assert run(ctxs)[1] == run(ctxs)[1]


def test_step_rejects_time_going_backwards_and_bad_config():
    m = PuppetStateMachine()
    m.step(PuppetContext(1.0, (0, 0, 0), (0, 0, 0), 0.0, 0.0, True))
    with pytest.raises(ValueError, match="backwards"):
        m.step(PuppetContext(0.5, (0, 0, 0), (0, 0, 0), 0.0, 0.0, True))
    with pytest.raises(ValueError, match="finite"):
        m.step(PuppetContext(2.0, (0, 0, 0), (0, 0, 0), 0.0, math.nan, True))
    with pytest.raises(ValueError, match="v_jump"):
        MachineConfig(v_jump=0.0)
    with pytest.raises(ValueError, match="interact_exit_radius"):
        MachineConfig(interact_radius=1.0, interact_exit_radius=0.5)
    assert MachineConfig(jump=JumpConfig(stop_time=0.3)).jump.stop_time == 0.3


def test_handle_then_step_starts_a_jump_tracker():
    m = PuppetStateMachine(initial=S.LOCOMOTION)
    m.handle(E.JUMP_TRIGGER, 0.0)
    m.step(PuppetContext(0.0, (0, 0, 0), (0, 2.0, 0), 0.0, 0.0, True))
    assert m.jump is not None and m.jump.t0 == 0.0
    trs = m.step(PuppetContext(0.2, (0, 0.3, 0), (0, 0.1, 0), 0.0, 0.3, True))
    assert [tr.event for tr in trs] == [E.TAKEOFF]
    assert m.jump.takeoff_time == pytest.approx(0.2)


def test_scripts_played_back_to_back_on_one_machine_give_each_scripts_states():
    """One machine, never reset, through mixed scripts (locomotion, jumps, ragdoll): each part carries
    on from locomotion, where the last one ended, and enters the states it enters alone."""
    names = ("run", "clean jump", "held up, put down, get up", "released in the air")
    ctxs: list[PuppetContext] = []
    expected = [S.RELEASED, S.LOCOMOTION]
    offset = 0.0
    for name in names:
        part, states = SCRIPTS[name]
        ctxs += [PuppetContext(c.t + offset, c.position, c.velocity, c.heading, c.height, c.touch,
                               c.ragdoll_at_rest) for c in part.contexts()]
        offset = ctxs[-1].t + 1 / 60
        assert states[:2] == [S.RELEASED, S.LOCOMOTION]
        expected += states[2:]
    states, transitions = run(ctxs)
    assert states == expected, [(round(tr.t, 3), tr.to_state.name, tr.reason) for tr in transitions]
