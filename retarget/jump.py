"""The jump: the side-view parabola refitted every frame, and the rules that make a jump invalid.

This module owns the jump of Ciccone 2019, *Intuitive Control of Animated Scenes* (ETH Diss. 25792),
section 6.3: a side-view parabola (eq. 6.3) refitted every frame whose apex drives the jump animation, and
three rules that send an invalid jump to the ragdoll. Eq. 6.3 is used as perfcap corrects it (its b has
the wrong sign on one term and its c does not follow from the fit's conditions; the derivation is in
``docs/design/puppet.md``), and every threshold is perfcap's, the thesis giving none:

* ``fit_parabola``: ``y = a x^2 + b x + c`` through the start ``(x0, y0)`` and the current point
  ``(xt, yt)`` with the current slope ``y't``::

      a = (y't (xt - x0) - yt + y0) / (xt - x0)^2
      b = (y't (x0^2 - xt^2) + 2 xt (yt - y0)) / (xt - x0)^2     (perfcap's correction of the sign)
      c = y0 - a x0^2 - b x0                                   (the parabola through the start point)

  and its apex ``(-b / 2a, y(-b / 2a))`` when ``a < 0``.
* ``fit_arc``: ``x`` is the horizontal displacement along the takeoff direction and the slope is
  ``v_y / v_x``; when the puppet has moved less than 2 cm sideways (a vertical jump) or has no speed along
  that direction, the same fit runs on time instead, ``y(t)`` with slope ``v_y``.
* ``JumpTracker``: follows one jump from its trigger and applies the thesis's three invalid-jump rules
  with perfcap's thresholds: (1) it rises again after starting to descend (``v_y`` below -0.05 m/s starts the
  descent, above +0.05 m/s after that is a second rise); (2) it turns in the air (facing or travel heading
  more than 30 degrees from the takeoff's: measured from ``takeoff()``, so the turn on the ground during the
  anticipation does not count, nor a facing that turns towards the travel direction at takeoff; a caller
  without an anticipation marks the takeoff at the trigger); (3) it stops in the air (speed below 0.1 m/s for more than
  0.15 s while above the ground). A fitted ``a >= 0`` (no apex) is allowed only during the first 0.1 s
  after takeoff, and (perfcap's addition) a jump airborne for more than 1.5 s is invalid too.

Units: metres, seconds, radians; Y is up, heading ``theta`` sends +Z to ``(sin theta, 0, cos theta)``.
Nothing here reads a clock: time comes with every update.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Iterable

__all__ = [
    "InvalidJump",
    "JumpArc",
    "JumpConfig",
    "JumpPhase",
    "JumpTracker",
    "Parabola",
    "fit_arc",
    "fit_parabola",
]


@dataclass(frozen=True, slots=True)
class Parabola:
    """``y = a x^2 + b x + c``."""

    a: float
    b: float
    c: float

    def __call__(self, x: float) -> float:
        """Evaluate the parabola at ``x``."""
        return (self.a * x + self.b) * x + self.c

    def slope(self, x: float) -> float:
        """``dy/dx`` at ``x``."""
        return 2.0 * self.a * x + self.b

    @property
    def apex(self) -> tuple[float, float] | None:
        """``(-b / 2a, y(-b / 2a))`` when the parabola opens downwards (``a < 0``), else None."""
        if not self.a < 0.0:
            return None
        x = -self.b / (2.0 * self.a)
        return x, self(x)


def fit_parabola(x0: float, y0: float, xt: float, yt: float, slope: float) -> Parabola:
    """Fit ``y = a x^2 + b x + c`` through ``(x0, y0)`` and ``(xt, yt)`` with slope ``slope`` at ``xt``.

    Args:
        x0: start abscissa.
        y0: start height.
        xt: current abscissa.
        yt: current height.
        slope: ``y'`` at ``xt``.

    Returns:
        The parabola (eq. 6.3 with the corrected ``b`` and ``c``).

    Raises:
        ValueError: ``xt == x0`` (no parabola is defined) or a non-finite argument.
    """
    for v in (x0, y0, xt, yt, slope):
        if not math.isfinite(v):
            raise ValueError(f"fit_parabola arguments must be finite, got {(x0, y0, xt, yt, slope)!r}")
    dx = xt - x0
    if dx == 0.0:
        raise ValueError("fit_parabola needs xt != x0")
    dx2 = dx * dx
    a = (slope * dx - yt + y0) / dx2
    b = (slope * (x0 * x0 - xt * xt) + 2.0 * xt * (yt - y0)) / dx2
    c = y0 - a * x0 * x0 - b * x0
    return Parabola(a, b, c)


@dataclass(frozen=True, slots=True)
class JumpArc:
    """The jump path fitted at one frame.

    Attributes:
        parabola: the fit; its abscissa is ``parameter``.
        parameter: ``"distance"`` (metres along the takeoff direction from the start) or ``"time"``
            (seconds since the start), the vertical-jump fallback.
        apex: the apex ``(x, y)`` in the same parameter, or None while the fit has no apex (``a >= 0``).
    """

    parabola: Parabola
    parameter: str
    apex: tuple[float, float] | None


def fit_arc(*, dt: float, dx: float, dy: float, vx: float, vy: float,
            vertical_threshold: float = 0.02, min_vx: float = 1e-3) -> JumpArc | None:
    """Fit the jump path from the start to the current point (the start is the origin of both axes).

    Args:
        dt: seconds since the start.
        dx: horizontal displacement along the takeoff direction, metres.
        dy: height change since the start, metres.
        vx: current horizontal speed along the takeoff direction, m/s.
        vy: current vertical speed, m/s.
        vertical_threshold: below this ``|dx|`` (m) the fit runs on time (perfcap's 2 cm).
        min_vx: below this ``|vx|`` (m/s) the slope ``vy / vx`` is meaningless and the fit runs on time.

    Returns:
        The arc, or None at the start itself (``dt == 0``).

    Raises:
        ValueError: ``dt < 0`` or non-finite arguments.
    """
    if not all(math.isfinite(v) for v in (dt, dx, dy, vx, vy)):
        raise ValueError("fit_arc arguments must be finite")
    if dt < 0.0:
        raise ValueError(f"dt must be >= 0, got {dt}")
    if abs(dx) >= vertical_threshold and abs(vx) >= min_vx:
        par = fit_parabola(0.0, 0.0, dx, dy, vy / vx)
        return JumpArc(par, "distance", par.apex)
    if dt == 0.0:
        return None
    par = fit_parabola(0.0, 0.0, dt, dy, vy)
    return JumpArc(par, "time", par.apex)


class JumpPhase(enum.Enum):
    """Where the jump is on its arc (with hysteresis on ``v_y``)."""

    RISING = "rising"
    DESCENDING = "descending"


class InvalidJump(enum.Enum):
    """Why a jump was found invalid."""

    RE_RISE = "re_rise"    # rose again after descending (more than one apex)
    TURN = "turn"          # turned in the air
    STOP = "stop"          # stopped in the air
    NO_APEX = "no_apex"    # the fitted arc still has no apex after the grace period
    TOO_LONG = "too_long"  # airborne longer than any jump lasts (our addition)


@dataclass(frozen=True, slots=True)
class JumpConfig:
    """Thresholds of the invalid-jump rules of Ciccone 2019, section 6.3 (the values are perfcap's; the thesis
    names the rules only).

    Attributes:
        vy_hysteresis: ``v_y`` below ``-vy_hysteresis`` starts the descent; above ``+vy_hysteresis`` after
            that is a second rise, m/s.
        max_turn: largest allowed heading change in the air, radians (30 degrees).
        min_travel_speed: the travel direction is compared only while the horizontal speed, at takeoff and
            now, is at least this, m/s (below it the direction is noise; our choice).
        stop_speed: below this speed the puppet counts as stopped, m/s.
        stop_time: stopped for longer than this while above the ground is invalid, s.
        no_apex_grace: how long after takeoff ``a >= 0`` is allowed, s.
        contact_height: at or below this height above the ground the puppet touches the ground, m.
        vertical_threshold: below this sideways displacement the arc is fitted on time, m.
        flat_tolerance: ``a`` above ``-flat_tolerance`` counts as ``a >= 0`` (rounding of a straight line).
        max_airtime: airborne longer than this after takeoff is invalid, s (our addition: a stick that
            glides level at constant height breaks none of the three rules but is no jump; 1.5 s is a
            2.8 m high jump).
    """

    vy_hysteresis: float = 0.05
    max_turn: float = math.radians(30.0)
    min_travel_speed: float = 0.3
    stop_speed: float = 0.1
    stop_time: float = 0.15
    no_apex_grace: float = 0.1
    contact_height: float = 0.02
    vertical_threshold: float = 0.02
    flat_tolerance: float = 1e-9
    max_airtime: float = 1.5

    def __post_init__(self) -> None:
        for name in ("vy_hysteresis", "max_turn", "min_travel_speed", "stop_speed", "stop_time",
                     "no_apex_grace", "contact_height", "vertical_threshold", "flat_tolerance", "max_airtime"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"JumpConfig.{name} must be finite and >= 0, got {v!r}")


def _wrap(angle: float) -> float:
    """Wrap an angle to (-pi, pi]."""
    return math.atan2(math.sin(angle), math.cos(angle))


def _vec3(v: Iterable[float], name: str) -> tuple[float, float, float]:
    try:
        x, y, z = (float(c) for c in v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a 3-vector, got {v!r}") from None
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise ValueError(f"{name} must be finite, got {v!r}")
    return x, y, z


class JumpTracker:
    """Follows one jump from its trigger: fits the arc each frame and applies the invalid-jump rules.

    The start ``(x0, y0)`` of the parabola is the position at the trigger; the takeoff direction is the
    horizontal velocity there (or the facing heading when the puppet barely moves sideways). The verdict
    is latched: once invalid, a jump stays invalid with its first reason.

    Args:
        t: trigger time, seconds.
        position: stick end position at the trigger, metres (3-vector).
        velocity: stick end velocity at the trigger, m/s.
        heading: facing heading at the trigger, radians.
        config: the thresholds.

    Raises:
        ValueError: non-finite inputs.
    """

    def __init__(self, t: float, position: Iterable[float], velocity: Iterable[float], heading: float,
                 config: JumpConfig | None = None) -> None:
        if not (math.isfinite(t) and math.isfinite(heading)):
            raise ValueError(f"t and heading must be finite, got {t!r}, {heading!r}")
        self.config = config if config is not None else JumpConfig()
        self.t0 = float(t)
        self.start = _vec3(position, "position")
        vx, vy, vz = _vec3(velocity, "velocity")
        self.heading0 = float(heading)
        horiz = math.hypot(vx, vz)
        if horiz >= self.config.min_travel_speed:
            self.direction = (vx / horiz, vz / horiz)
            self.travel_heading0: float | None = math.atan2(vx, vz)
        else:
            self.direction = (math.sin(heading), math.cos(heading))
            self.travel_heading0 = None
        self.phase = JumpPhase.DESCENDING if vy < -self.config.vy_hysteresis else JumpPhase.RISING
        self.takeoff_time: float | None = None
        self.invalid: InvalidJump | None = None
        self.invalid_time: float | None = None
        self.arc: JumpArc | None = None
        self._t = self.t0
        self._stopped_since: float | None = None
        self._anchor_pending = False             # takeoff() was called: the next update sets the anchors

    @property
    def valid(self) -> bool:
        """False once one of the rules fired."""
        return self.invalid is None

    def takeoff(self, t: float) -> None:
        """Mark the takeoff (end of the anticipation); starts the no-apex grace period.

        Raises:
            ValueError: ``t`` before the trigger.
        """
        if not (math.isfinite(t) and t >= self.t0):
            raise ValueError(f"takeoff time {t!r} is before the trigger at {self.t0}")
        self.takeoff_time = float(t)
        # the turn rule measures from the first frame in the air: during the anticipation the character
        # turns on the ground to face its travel, and that is no turn in the air
        self._anchor_pending = True

    def _fail(self, reason: InvalidJump, t: float) -> None:
        if self.invalid is None:
            self.invalid = reason
            self.invalid_time = t

    def update(self, t: float, position: Iterable[float], velocity: Iterable[float], heading: float,
               height: float) -> InvalidJump | None:
        """Advance the tracker by one frame.

        Args:
            t: the frame's time, seconds (non-decreasing).
            position: stick end position, metres.
            velocity: stick end velocity, m/s.
            heading: facing heading, radians.
            height: stick end height above the ground, metres.

        Returns:
            The reason the jump is invalid (latched), or None while it is valid.

        Raises:
            ValueError: time went backwards or non-finite inputs.
        """
        if not (math.isfinite(t) and math.isfinite(heading) and math.isfinite(height)):
            raise ValueError(f"t, heading and height must be finite, got {t!r}, {heading!r}, {height!r}")
        if t < self._t:
            raise ValueError(f"time went backwards: {t} after {self._t}")
        self._t = t
        cfg = self.config
        px, py, pz = _vec3(position, "position")
        vx, vy, vz = _vec3(velocity, "velocity")
        dxw, dzw = px - self.start[0], pz - self.start[2]
        ux, uz = self.direction
        self.arc = fit_arc(dt=t - self.t0, dx=dxw * ux + dzw * uz, dy=py - self.start[1],
                           vx=vx * ux + vz * uz, vy=vy, vertical_threshold=cfg.vertical_threshold)
        # (1) more than one apex, with hysteresis on v_y.
        if self.phase is JumpPhase.RISING:
            if vy < -cfg.vy_hysteresis:
                self.phase = JumpPhase.DESCENDING
        elif vy > cfg.vy_hysteresis:
            self._fail(InvalidJump.RE_RISE, t)
        # (2) turning in the air, from the takeoff: facing, and travel direction while it is defined.
        horiz = math.hypot(vx, vz)
        if self._anchor_pending:
            self._anchor_pending = False
            self.heading0 = heading
            self.travel_heading0 = math.atan2(vx, vz) if horiz >= cfg.min_travel_speed else None
        elif self.takeoff_time is not None:
            # facing: turned from the takeoff's, and (when it travels) away from its travel too, so a
            # character still turning to face where it goes is not turning in the air
            ref = self.travel_heading0
            if abs(_wrap(heading - self.heading0)) > cfg.max_turn and (
                    ref is None or abs(_wrap(heading - ref)) > cfg.max_turn):
                self._fail(InvalidJump.TURN, t)
            if (self.travel_heading0 is not None and horiz >= cfg.min_travel_speed
                    and abs(_wrap(math.atan2(vx, vz) - self.travel_heading0)) > cfg.max_turn):
                self._fail(InvalidJump.TURN, t)
        # (3) stopping in the air.
        speed = math.sqrt(vx * vx + vy * vy + vz * vz)
        if speed < cfg.stop_speed and height > cfg.contact_height:
            if self._stopped_since is None:
                self._stopped_since = t
            elif t - self._stopped_since > cfg.stop_time:
                self._fail(InvalidJump.STOP, t)
        else:
            self._stopped_since = None
        # No apex after the grace period.
        if (self.takeoff_time is not None and t - self.takeoff_time > cfg.no_apex_grace
                and self.arc is not None and self.arc.parabola.a > -cfg.flat_tolerance):
            self._fail(InvalidJump.NO_APEX, t)
        if self.takeoff_time is not None and t - self.takeoff_time > cfg.max_airtime:
            self._fail(InvalidJump.TOO_LONG, t)
        return self.invalid
