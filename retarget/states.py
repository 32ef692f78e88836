"""The puppet's states, the events that move it between them, and the transition table.

This module owns *what* the phone puppet can be doing and nothing about *when*: ``PuppetState``,
``PuppetEvent``, the one table ``TRANSITIONS`` that says which event moves which state where, and the
animation actions each state asks for on entry and exit (``ENTRY_ACTIONS``, ``EXIT_ACTIONS``,
``EVENT_ACTIONS``). Deriving events from the phone input (thresholds, hysteresis, timers) is
``retarget.machine``'s job; applying the actions (blend space, ragdoll, IK) is the retargeter's.

The states follow Ciccone 2019, *Intuitive Control of Animated Scenes* (ETH Diss. 25792), chapter 6
(PuppetPhone): section 6.2.2 (a state machine with a ragdoll as the default state for input no animation
fits) and section 6.3 (the clips of the prototype, the jump with its anticipation and landing crouch).
The thesis draws its state machine only as a figure (Fig. 6.6) and names few of its events, so the table
below is perfcap's reconstruction; ``docs/design/puppet.md`` says what comes from where:

* ``LOCOMOTION`` (5-clip blend space): lift fast -> ``JUMP_ANTICIPATION``; held above the ground with no
  jump -> ``RAGDOLL``; object nearby while crouched -> ``INTERACT``; touch-up -> ``RELEASED``.
* ``JUMP_ANTICIPATION`` (squat, fixed delay): delay elapsed -> ``AIRBORNE``; touch-up -> ``RELEASED``.
* ``AIRBORNE`` (mid-jump clip on the fitted parabola): invalid jump or touch-up -> ``RAGDOLL``; ground
  contact while descending -> ``LANDING``.
* ``LANDING`` (short crouch): crouch done -> ``LOCOMOTION``; touch-up -> ``RELEASED``.
* ``RAGDOLL`` (the default for input no clip fits): at rest on the ground and (released or stick near the
  ground) -> ``GET_UP``; grab and release only move the spring on the held body (self-transitions).
* ``GET_UP`` (clip): clip done -> ``LOCOMOTION``; grab and release are self-transitions.
* ``INTERACT`` (pick up / roll with hand IK): done or moved away -> ``LOCOMOTION``; held above the ground ->
  ``RAGDOLL``; touch-up -> ``RELEASED``.
* ``RELEASED`` (not held, standing): grab -> ``LOCOMOTION``.
"""

from __future__ import annotations

import enum
from types import MappingProxyType
from typing import TYPE_CHECKING, Final

from capture.errors import InvalidTransitionError

if TYPE_CHECKING:
    from collections.abc import Mapping

__all__ = [
    "ENTRY_ACTIONS",
    "EVENT_ACTIONS",
    "EXIT_ACTIONS",
    "GROUNDED_STATES",
    "TRANSITIONS",
    "PuppetAction",
    "PuppetEvent",
    "PuppetState",
    "next_state",
]


class PuppetState(enum.Enum):
    """What the puppet is doing; exactly one is active."""

    LOCOMOTION = "locomotion"
    JUMP_ANTICIPATION = "jump_anticipation"
    AIRBORNE = "airborne"
    LANDING = "landing"
    RAGDOLL = "ragdoll"
    GET_UP = "get_up"
    INTERACT = "interact"
    RELEASED = "released"


class PuppetEvent(enum.Enum):
    """Something that happened to the puppet or its input; events switch states."""

    GRAB = "grab"                          # touch-down on the puppet
    RELEASE = "release"                    # touch-up
    JUMP_TRIGGER = "jump_trigger"          # v_up > v_jump while grounded
    TAKEOFF = "takeoff"                    # the anticipation delay elapsed
    INVALID_JUMP = "invalid_jump"          # one of the three invalid-jump rules fired
    TOUCHDOWN = "touchdown"                # ground contact while descending
    LANDING_DONE = "landing_done"          # the landing crouch finished
    UNSUPPORTED = "unsupported"            # held above the ground with no jump momentum, or dragged too fast
    AT_REST = "at_rest"                    # ragdoll at rest on the ground, released or stick near the ground
    GET_UP_DONE = "get_up_done"            # the get-up clip finished
    NEAR_OBJECT = "near_object"            # a manipulable object is close and the puppet is crouched
    INTERACT_DONE = "interact_done"        # the interaction finished or the puppet moved away


class PuppetAction(enum.Enum):
    """What the retargeter should do on a transition (the machine itself has no side effects)."""

    ATTACH_STICK = "attach_stick"          # the MotionStick grabs the puppet (keep X_rel and L0)
    DETACH_STICK = "detach_stick"          # the MotionStick lets go
    PLAY_BLEND_SPACE = "play_blend_space"  # the 5-clip locomotion blend, driven by PuppetMapping
    STOP_BLEND_SPACE = "stop_blend_space"
    PLAY_IDLE = "play_idle"                # standing, not held
    PLAY_ANTICIPATION = "play_anticipation"  # squat before the takeoff
    START_JUMP_ARC = "start_jump_arc"      # follow the fitted parabola with the mid-jump clip
    STOP_JUMP_ARC = "stop_jump_arc"
    PLAY_LANDING = "play_landing"          # the short landing crouch
    START_RAGDOLL = "start_ragdoll"        # physics on; the stick target becomes a 6-DoF spring
    STOP_RAGDOLL = "stop_ragdoll"
    PLAY_GET_UP = "play_get_up"
    START_HAND_IK = "start_hand_ik"        # hands onto the object
    STOP_HAND_IK = "stop_hand_ik"


S = PuppetState
E = PuppetEvent
A = PuppetAction

#: The whole state table, in one place: (state, event) -> next state. A pair not listed is invalid.
TRANSITIONS: Final[Mapping[tuple[PuppetState, PuppetEvent], PuppetState]] = MappingProxyType({
    (S.LOCOMOTION, E.JUMP_TRIGGER): S.JUMP_ANTICIPATION,
    (S.LOCOMOTION, E.UNSUPPORTED): S.RAGDOLL,
    (S.LOCOMOTION, E.NEAR_OBJECT): S.INTERACT,
    (S.LOCOMOTION, E.RELEASE): S.RELEASED,
    (S.JUMP_ANTICIPATION, E.TAKEOFF): S.AIRBORNE,
    (S.JUMP_ANTICIPATION, E.RELEASE): S.RELEASED,
    (S.AIRBORNE, E.INVALID_JUMP): S.RAGDOLL,
    (S.AIRBORNE, E.TOUCHDOWN): S.LANDING,
    (S.AIRBORNE, E.RELEASE): S.RAGDOLL,
    (S.LANDING, E.LANDING_DONE): S.LOCOMOTION,
    (S.LANDING, E.RELEASE): S.RELEASED,
    (S.RAGDOLL, E.AT_REST): S.GET_UP,
    (S.RAGDOLL, E.GRAB): S.RAGDOLL,
    (S.RAGDOLL, E.RELEASE): S.RAGDOLL,
    (S.GET_UP, E.GET_UP_DONE): S.LOCOMOTION,
    (S.GET_UP, E.GRAB): S.GET_UP,
    (S.GET_UP, E.RELEASE): S.GET_UP,
    (S.INTERACT, E.INTERACT_DONE): S.LOCOMOTION,
    (S.INTERACT, E.UNSUPPORTED): S.RAGDOLL,
    (S.INTERACT, E.RELEASE): S.RELEASED,
    (S.RELEASED, E.GRAB): S.LOCOMOTION,
})

#: States in which the character stands on the ground (touch-up there means RELEASED, not RAGDOLL;
#: the MotionStick applies only the yaw of its target).
GROUNDED_STATES: Final[frozenset[PuppetState]] = frozenset({
    S.LOCOMOTION, S.JUMP_ANTICIPATION, S.LANDING, S.INTERACT, S.RELEASED, S.GET_UP,
})

#: Actions run when a state is entered (not on self-transitions).
ENTRY_ACTIONS: Final[Mapping[PuppetState, tuple[PuppetAction, ...]]] = MappingProxyType({
    S.LOCOMOTION: (A.PLAY_BLEND_SPACE,),
    S.JUMP_ANTICIPATION: (A.PLAY_ANTICIPATION,),
    S.AIRBORNE: (A.START_JUMP_ARC,),
    S.LANDING: (A.PLAY_LANDING,),
    S.RAGDOLL: (A.START_RAGDOLL,),
    S.GET_UP: (A.PLAY_GET_UP,),
    S.INTERACT: (A.START_HAND_IK,),
    S.RELEASED: (A.PLAY_IDLE,),
})

#: Actions run when a state is left (not on self-transitions).
EXIT_ACTIONS: Final[Mapping[PuppetState, tuple[PuppetAction, ...]]] = MappingProxyType({
    S.LOCOMOTION: (A.STOP_BLEND_SPACE,),
    S.JUMP_ANTICIPATION: (),
    S.AIRBORNE: (A.STOP_JUMP_ARC,),
    S.LANDING: (),
    S.RAGDOLL: (A.STOP_RAGDOLL,),
    S.GET_UP: (),
    S.INTERACT: (A.STOP_HAND_IK,),
    S.RELEASED: (),
})

#: Actions an event asks for whatever the states (the stick follows the touch).
EVENT_ACTIONS: Final[Mapping[PuppetEvent, tuple[PuppetAction, ...]]] = MappingProxyType({
    E.GRAB: (A.ATTACH_STICK,),
    E.RELEASE: (A.DETACH_STICK,),
})

del S, E, A


def next_state(state: PuppetState, event: PuppetEvent) -> PuppetState:
    """Look up where ``event`` takes ``state`` in ``TRANSITIONS``.

    Args:
        state: the current state.
        event: the event that happened.

    Returns:
        The next state (equal to ``state`` for a self-transition).

    Raises:
        InvalidTransitionError: the table has no entry for ``(state, event)``.
    """
    try:
        return TRANSITIONS[(state, event)]
    except KeyError:
        raise InvalidTransitionError(
            f"event {event.name} is not accepted in state {state.name}", state=state, event=event
        ) from None
