"""The puppet's state machine: a pure transition function and the per-frame event derivation.

This module owns *when* the puppet changes state (Ciccone 2019, ETH Diss. 25792, chapter 6: the state
machine of section 6.2.2 and the jump of section 6.3). The table itself lives in ``retarget.states``; here:

* ``PuppetStateMachine.handle(event)`` looks the event up in ``TRANSITIONS``, switches state and returns a
  ``Transition`` with the actions the retargeter must run (exit, event, entry). An event the table does not
  accept raises ``InvalidTransitionError``.
* ``PuppetStateMachine.step(context)`` derives events from one frame of input (``PuppetContext``: time,
  stick end position, velocity and heading, its height above the ground, whether the touchscreen is held,
  and what the ragdoll and environment report) and applies them. Thresholds have hysteresis and minimum
  dwell times so noisy input near a threshold does not make states flicker:

  - *held above the ground*: a Schmitt trigger, on above ``above_ground`` (0.15 m), off below
    ``above_ground - ground_hysteresis``; it must stay on for ``unsupported_dwell`` in a grounded state
    before ``UNSUPPORTED`` (-> ragdoll);
  - *jump trigger*: ``v_up > v_jump`` (1.0 m/s scaled by the character's height) for ``jump_dwell`` while
    in locomotion; the takeoff follows exactly ``anticipation`` (0.2 s) after the trigger, and the
    ``Transition`` carries that exact time even when the frame arrives later;
  - *airborne*: a ``JumpTracker`` started at the lift applies the invalid-jump rules; ground contact
    (height at most ``contact_height``) while descending is the touchdown; the landing crouch lasts
    ``landing`` (0.2 s);
  - *ragdoll*: at rest on the ground (reported by the physics) and released or the stick near the ground,
    for ``rest_dwell``, -> get-up; the get-up clip lasts ``get_up_duration``;
  - *touch*: touch-up in a grounded state -> released, in the air -> ragdoll; in ragdoll and get-up grab
    and release only move the stick (self-transitions).

  Several transitions can follow in one frame (get-up done, then released when not held); each carries
  the time it happened. The machine is deterministic and never reads a clock: time comes in the context.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from capture.errors import InvalidTransitionError
from retarget.jump import JumpConfig, JumpPhase, JumpTracker
from retarget.states import (
    ENTRY_ACTIONS,
    EVENT_ACTIONS,
    EXIT_ACTIONS,
    PuppetAction,
    PuppetEvent,
    PuppetState,
    next_state,
)

__all__ = [
    "MachineConfig",
    "PuppetContext",
    "PuppetStateMachine",
    "Transition",
]

#: Two times closer than this are the same instant (due times computed by addition).
_TIME_EPS = 1e-9
#: At most this many transitions are chained in one frame.
_MAX_CHAIN = 4

_HELD_GROUNDED = frozenset({PuppetState.LOCOMOTION, PuppetState.JUMP_ANTICIPATION, PuppetState.LANDING,
                            PuppetState.INTERACT})


@dataclass(frozen=True, slots=True)
class Transition:
    """One state change (or self-transition) and what to do about it.

    Attributes:
        from_state: the state left.
        to_state: the state entered (the same for a self-transition).
        event: the event that caused it.
        actions: exit actions of ``from_state``, then the event's, then entry actions of ``to_state``
            (only the event's for a self-transition).
        t: when it happened, seconds (None when ``handle`` was called before any time was known).
        reason: a detail, e.g. the invalid-jump rule that fired (``"re_rise"``, ``"turn"``, ...).
    """

    from_state: PuppetState
    to_state: PuppetState
    event: PuppetEvent
    actions: tuple[PuppetAction, ...]
    t: float | None = None
    reason: str | None = None


@dataclass(frozen=True, slots=True)
class PuppetContext:
    """One frame of input to the state machine.

    Attributes:
        t: time, seconds (non-decreasing from frame to frame).
        position: stick end (target) position, metres, world frame, Y up.
        velocity: stick end velocity, m/s.
        heading: facing heading of the stick target, radians.
        height: stick end height above the ground below it, metres.
        touch: the touchscreen is held (the puppet is grabbed).
        ragdoll_at_rest: the ragdoll physics reports the body at rest on the ground.
        object_distance: distance to the nearest manipulable object, metres (inf when none).
        crouch: the crouch blend parameter ``p_height`` (0 fully crouched, 1 standing).
        interaction_done: the current interaction (pick-up, roll) has finished.
        speedup: how much faster than its own pace the locomotion must play to keep up with the stick (1
            inside the feasible set; ``u_vel / u'_vel`` beyond it).
    """

    t: float
    position: tuple[float, float, float]
    velocity: tuple[float, float, float]
    heading: float
    height: float
    touch: bool
    ragdoll_at_rest: bool = False
    object_distance: float = math.inf
    crouch: float = 1.0
    interaction_done: bool = False
    speedup: float = 1.0


@dataclass(frozen=True, slots=True)
class MachineConfig:
    """Thresholds and durations of the state machine.

    Ciccone 2019 (section 6.3) says what triggers a jump (lifting the phone fast enough), that a short
    forced delay builds the anticipation squat and that a valid jump lands with a very short crouch, but
    gives no number: every default here is perfcap's choice (``docs/design/puppet.md``).

    Attributes:
        character_height: the puppet's height, metres; ``v_jump`` scales with it.
        reference_height: the height ``v_jump`` is given for, metres.
        v_jump: lift speed that triggers a jump at the reference height, m/s (1.0).
        jump_dwell: ``v_up`` must exceed the scaled ``v_jump`` this long, s (rejects one-frame spikes).
        anticipation: squat delay between trigger and takeoff, s (0.2).
        landing: landing crouch, s (0.2).
        above_ground: stick height above which the puppet counts as held above the ground, m (0.15).
        ground_hysteresis: it is back on the ground only below ``above_ground - ground_hysteresis``, m.
        unsupported_dwell: held above the ground this long (no jump) -> ragdoll, s; also how long the stick
            may race faster than ``max_speedup`` times the fastest clip.
        max_speedup: the most the locomotion plays faster than its own pace (the out-of-range speed-up
            of section 6.2.3, capped); a stick dragged faster than that fits no animation -> ragdoll
            (perfcap's addition).
        near_ground: in ragdoll, a held stick this low counts as near the ground, m.
        rest_dwell: the ragdoll must be at rest (and released or near the ground) this long, s.
        get_up_duration: the get-up clip's duration, s.
        interact_radius: an object closer than this can be interacted with, m.
        interact_exit_radius: the interaction ends beyond this distance, m (hysteresis).
        crouch_threshold: interaction needs ``crouch`` below this.
        interact_dwell: near and crouched this long -> interact, s.
        jump: the invalid-jump thresholds (also ``contact_height`` for the touchdown).
    """

    character_height: float = 1.75
    reference_height: float = 1.75
    v_jump: float = 1.0
    jump_dwell: float = 0.03
    anticipation: float = 0.2
    landing: float = 0.2
    above_ground: float = 0.15
    ground_hysteresis: float = 0.05
    unsupported_dwell: float = 0.2
    max_speedup: float = 2.0
    near_ground: float = 0.10
    rest_dwell: float = 0.1
    get_up_duration: float = 1.0
    interact_radius: float = 0.5
    interact_exit_radius: float = 0.7
    crouch_threshold: float = 0.3
    interact_dwell: float = 0.1
    jump: JumpConfig = field(default_factory=JumpConfig)

    def __post_init__(self) -> None:
        for name in ("character_height", "reference_height", "v_jump"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"MachineConfig.{name} must be finite and > 0, got {v!r}")
        for name in ("jump_dwell", "anticipation", "landing", "above_ground", "ground_hysteresis",
                     "unsupported_dwell", "max_speedup", "near_ground", "rest_dwell", "get_up_duration",
                     "interact_radius", "interact_exit_radius", "crouch_threshold", "interact_dwell"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"MachineConfig.{name} must be finite and >= 0, got {v!r}")
        if self.ground_hysteresis > self.above_ground:
            raise ValueError("ground_hysteresis must not exceed above_ground")
        if self.max_speedup < 1.0:
            raise ValueError(f"MachineConfig.max_speedup must be >= 1, got {self.max_speedup!r}")
        if self.interact_exit_radius < self.interact_radius:
            raise ValueError("interact_exit_radius must be >= interact_radius")

    @property
    def v_jump_scaled(self) -> float:
        """``v_jump`` scaled by ``character_height / reference_height``, m/s."""
        return self.v_jump * self.character_height / self.reference_height


class PuppetStateMachine:
    """The puppet's state machine (see the module docstring).

    Args:
        config: thresholds and durations.
        initial: the state to start in (default ``RELEASED``: nothing holds the puppet).

    Attributes:
        state: the active state.
        held: whether the stick holds the puppet (follows GRAB and RELEASE).
        jump: the tracker of the current jump while anticipating or airborne, else None.
        entered_at: when the active state was entered, seconds (None before any time is known).
    """

    def __init__(self, config: MachineConfig | None = None, *,
                 initial: PuppetState = PuppetState.RELEASED) -> None:
        self.config = config if config is not None else MachineConfig()
        self.state = initial
        self.held = initial is not PuppetState.RELEASED
        self.jump: JumpTracker | None = None
        self.entered_at: float | None = None
        self._t: float | None = None
        self._above = False
        self._above_since = 0.0
        #: (time, position, velocity, heading) of the first frame of the current lift above v_jump.
        self._lift_start: tuple[float, tuple[float, float, float], tuple[float, float, float], float] | None = None
        self._rest_since: float | None = None
        self._near_since: float | None = None
        self._fast_since: float | None = None

    # ------------------------------------------------------------------------------------------------
    # The pure part: table lookup and actions
    # ------------------------------------------------------------------------------------------------

    def handle(self, event: PuppetEvent, t: float | None = None, *, reason: str | None = None) -> Transition:
        """Apply one event.

        Args:
            event: the event.
            t: when it happened, seconds (default: the last frame's time).
            reason: an optional detail recorded in the transition.

        Returns:
            The ``Transition`` with its actions.

        Raises:
            InvalidTransitionError: the active state does not accept ``event``.
        """
        source = self.state
        target = next_state(source, event)
        when = self._t if t is None else t
        if target is source:
            actions = EVENT_ACTIONS.get(event, ())
        else:
            actions = EXIT_ACTIONS[source] + EVENT_ACTIONS.get(event, ()) + ENTRY_ACTIONS[target]
            self.entered_at = when
            if target not in (PuppetState.JUMP_ANTICIPATION, PuppetState.AIRBORNE):
                self.jump = None
        if event is PuppetEvent.GRAB:
            self.held = True
        elif event is PuppetEvent.RELEASE:
            self.held = False
        self.state = target
        return Transition(source, target, event, actions, when, reason)

    def accepts(self, event: PuppetEvent) -> bool:
        """True when the active state accepts ``event``."""
        try:
            next_state(self.state, event)
        except InvalidTransitionError:
            return False
        return True

    # ------------------------------------------------------------------------------------------------
    # Per-frame event derivation
    # ------------------------------------------------------------------------------------------------

    def step(self, ctx: PuppetContext) -> list[Transition]:
        """Derive the events of one frame and apply them.

        Args:
            ctx: this frame's input.

        Returns:
            The transitions that happened, in order (usually none).

        Raises:
            ValueError: time went backwards or non-finite input.
        """
        t = ctx.t
        if not (math.isfinite(t) and math.isfinite(ctx.height) and math.isfinite(ctx.heading)
                and all(math.isfinite(v) for v in ctx.position) and all(math.isfinite(v) for v in ctx.velocity)):
            raise ValueError(f"context values must be finite, got {ctx!r}")
        if len(ctx.position) != 3 or len(ctx.velocity) != 3:
            raise ValueError(f"position and velocity must be 3-vectors, got {ctx!r}")
        if self._t is not None and t < self._t:
            raise ValueError(f"time went backwards: {t} after {self._t}")
        if self.entered_at is None:
            self.entered_at = t
        self._t = t
        self._observe(ctx)
        out: list[Transition] = []
        for _ in range(_MAX_CHAIN):
            derived = self._derive(ctx)
            if derived is None:
                break
            event, when, reason = derived
            out.append(self._apply(event, when, reason, ctx))
        return out

    def _observe(self, ctx: PuppetContext) -> None:
        """Update the hysteresis and dwell trackers from one frame (whatever the state)."""
        cfg = self.config
        t = ctx.t
        h = ctx.height
        if not self._above and h > cfg.above_ground:
            self._above, self._above_since = True, t
        elif self._above and h < cfg.above_ground - cfg.ground_hysteresis:
            self._above = False
        vy = float(ctx.velocity[1])
        if vy > cfg.v_jump_scaled:
            if self._lift_start is None:
                pos = (float(ctx.position[0]), float(ctx.position[1]), float(ctx.position[2]))
                vel = (float(ctx.velocity[0]), vy, float(ctx.velocity[2]))
                self._lift_start = (t, pos, vel, ctx.heading)
        else:
            self._lift_start = None
        resting = ctx.ragdoll_at_rest and (not ctx.touch or h < cfg.near_ground)
        if resting:
            if self._rest_since is None:
                self._rest_since = t
        else:
            self._rest_since = None
        if ctx.speedup > cfg.max_speedup:
            if self._fast_since is None:
                self._fast_since = t
        else:
            self._fast_since = None
        near = ctx.object_distance < cfg.interact_radius and ctx.crouch < cfg.crouch_threshold
        if near:
            if self._near_since is None:
                self._near_since = t
        else:
            self._near_since = None
        if self.state in (PuppetState.JUMP_ANTICIPATION, PuppetState.AIRBORNE):
            if self.jump is None:  # the event came through handle(): start the jump here
                self.jump = JumpTracker(t, ctx.position, ctx.velocity, ctx.heading, cfg.jump)
            self.jump.update(t, ctx.position, ctx.velocity, ctx.heading, h)

    def _dwelt(self, since: float | None, dwell: float, t: float) -> bool:
        """True when a condition true since ``since`` (counted from the state's entry) lasted ``dwell``."""
        if since is None:
            return False
        start = since if self.entered_at is None else max(since, self.entered_at)
        return t - start >= dwell - _TIME_EPS

    def _derive(self, ctx: PuppetContext) -> tuple[PuppetEvent, float, str | None] | None:
        """The next event this frame implies for the active state, with its time, or None."""
        cfg = self.config
        t = ctx.t
        state = self.state
        entered = self.entered_at if self.entered_at is not None else t
        s = PuppetState
        e = PuppetEvent
        if state is s.RELEASED:
            return (e.GRAB, t, None) if ctx.touch else None
        if state in _HELD_GROUNDED and not ctx.touch:
            return e.RELEASE, t, None
        if state is s.LOCOMOTION:
            if self._lift_start is not None and self._dwelt(self._lift_start[0], cfg.jump_dwell, t):
                return e.JUMP_TRIGGER, t, None
            if self._above and self._dwelt(self._above_since, cfg.unsupported_dwell, t):
                return e.UNSUPPORTED, t, None
            if self._dwelt(self._fast_since, cfg.unsupported_dwell, t):
                return e.UNSUPPORTED, t, "too_fast"
            if self._dwelt(self._near_since, cfg.interact_dwell, t):
                return e.NEAR_OBJECT, t, None
            return None
        if state is s.JUMP_ANTICIPATION:
            due = entered + cfg.anticipation
            return (e.TAKEOFF, due, None) if t >= due - _TIME_EPS else None
        if state is s.AIRBORNE:
            if not ctx.touch:
                return e.RELEASE, t, None
            jump = self.jump
            if jump is not None and jump.invalid is not None:
                return e.INVALID_JUMP, t, jump.invalid.value
            descending = ctx.velocity[1] < 0.0 or (jump is not None and jump.phase is JumpPhase.DESCENDING)
            if ctx.height <= cfg.jump.contact_height and descending:
                return e.TOUCHDOWN, t, None
            return None
        if state is s.LANDING:
            due = entered + cfg.landing
            return (e.LANDING_DONE, due, None) if t >= due - _TIME_EPS else None
        if state in (s.RAGDOLL, s.GET_UP):
            if ctx.touch != self.held:
                return (e.GRAB if ctx.touch else e.RELEASE), t, None
            if state is s.RAGDOLL:
                return (e.AT_REST, t, None) if self._dwelt(self._rest_since, cfg.rest_dwell, t) else None
            due = entered + cfg.get_up_duration
            return (e.GET_UP_DONE, due, None) if t >= due - _TIME_EPS else None
        # INTERACT
        if self._above and self._dwelt(self._above_since, cfg.unsupported_dwell, t):
            return e.UNSUPPORTED, t, None
        if ctx.interaction_done or ctx.object_distance > cfg.interact_exit_radius:
            return e.INTERACT_DONE, t, None
        return None

    def _apply(self, event: PuppetEvent, when: float, reason: str | None, ctx: PuppetContext) -> Transition:
        """Apply a derived event and set up what the entered state needs."""
        tr = self.handle(event, when, reason=reason)
        if tr.to_state is PuppetState.JUMP_ANTICIPATION and tr.from_state is not tr.to_state:
            start = self._lift_start
            if start is None:
                self.jump = JumpTracker(ctx.t, ctx.position, ctx.velocity, ctx.heading, self.config.jump)
            else:
                self.jump = JumpTracker(start[0], start[1], start[2], start[3], self.config.jump)
            self.jump.update(ctx.t, ctx.position, ctx.velocity, ctx.heading, ctx.height)
            self._lift_start = None
        elif tr.to_state is PuppetState.AIRBORNE and self.jump is not None:
            self.jump.takeoff(when)
        return tr
