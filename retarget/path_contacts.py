"""Ground contacts of a locomotion clip, the first step of path editing (``docs/design/path-editing.md``
section 1.1): which foot is planted at each key, how many feet are (``count``), the locally maximal contact
periods that carry the path's handles, and the ballistic spans (flights) between a take-off and a landing.

A foot is planted at a key when one of its end effectors (the ankle, or the toe) is within ``height``
of that effector's floor (its 2nd-percentile height over the clip, so a rig whose toes dip below zero
still has a floor) and moves horizontally slower than ``speed``; both thresholds are given per leg length
(hip to ankle), so a child and an adult are judged alike. Per foot, gaps of up to ``close_gap_s`` are
closed and runs shorter than ``min_run_s`` dropped. A clip whose contacts are known (``Clip.contacts``,
the procedural clips) uses those. A flight is a run of no contact of at least ``min_flight_s`` whose root
height, from the last planted key to the first, fits a parabola falling at a plausible gravity (between
``g_min`` and ``g_max``), which tells a jump from a detection gap.

Known limit: on the stylised CMU take 131_02 (shuffles and kicks) ten short runs of no contact, 0.06 to
0.13 s, fall at 3.7 to 8.3 m/s^2 and pass the guard as flights; on the walk, run and jump of ``cmu_016``
only the real flights do.

Legs are found by the joint names of the rigs perfcap reads: the cgspeed CMU conversion (``LeftHip``,
``LeftKnee``, ``LeftAnkle``, ``LeftToe``), MotionBuilder CMU (``LeftUpLeg``, ``LeftLeg``, ``LeftFoot``,
``LeftToeBase``) and perfcap's humanoid (``LeftUpperLeg``, ``LeftLowerLeg``, ``LeftFoot``, ``LeftToes``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from retarget._types import BoolArray, FloatArray, IntArray
    from retarget.skeleton import Clip, Skeleton

#: leg chains by rig family: hip, knee, ankle, toe (the left side; ``Right`` for the other)
LEG_FAMILIES: tuple[tuple[str, str, str, str], ...] = (
    ("LeftHip", "LeftKnee", "LeftAnkle", "LeftToe"),
    ("LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase"),
    ("LeftUpperLeg", "LeftLowerLeg", "LeftFoot", "LeftToes"),
)
SIDES = ("left", "right")
G = 9.81


@dataclass(frozen=True)
class ContactConfig:
    """Thresholds of contact detection (defaults tuned on the CMU walk, run and jump; see the design note)."""

    height_per_leg: float = 0.048     # effector height above its floor, in leg lengths (0.04 m for 0.84 m)
    speed_per_leg: float = 0.72       # horizontal speed, leg lengths per second (0.6 m/s for 0.84 m)
    floor_percentile: float = 2.0
    close_gap_s: float = 4 / 120
    min_run_s: float = 6 / 120
    min_flight_s: float = 0.05
    g_min: float = 0.3 * G
    g_max: float = 3.0 * G

    def __post_init__(self) -> None:
        for name in ("height_per_leg", "speed_per_leg", "min_flight_s", "g_min"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"ContactConfig.{name} must be finite and > 0, not {v}")
        if not self.g_max > self.g_min:
            raise ValueError("ContactConfig.g_max must exceed g_min")


@dataclass(frozen=True)
class Leg:
    """One leg's joints (indices into the skeleton) and its length (hip to ankle at rest, metres)."""

    side: str
    hip: int
    knee: int
    ankle: int
    toe: int
    length: float


@dataclass(frozen=True)
class Flight:
    """A ballistic span: planted at key ``takeoff``, planted again at ``landing``, airborne between;
    ``g`` is the downward acceleration of the root's height fitted over it (m/s^2)."""

    takeoff: int
    landing: int
    g: float


@dataclass(frozen=True)
class Contacts:
    """What ``detect_contacts`` found: per foot a ``(F,)`` mask, the count of planted feet per key, the
    locally maximal periods (``[start, end)`` key ranges) and the flights."""

    feet: dict[str, BoolArray]
    count: IntArray
    periods: tuple[tuple[int, int], ...]
    flights: tuple[Flight, ...]
    detected: bool      # False: the clip's own contacts were used


def find_legs(skeleton: Skeleton) -> tuple[Leg, Leg]:
    """The left and right leg of a skeleton, by rig family.

    Raises:
        ValueError: no family's joints are all in the skeleton (naming the families).
    """
    names = set(skeleton.names)
    for fam in LEG_FAMILIES:
        sides = [tuple(n.replace("Left", side) for n in fam) for side in ("Left", "Right")]
        if all(n in names for chain in sides for n in chain):
            legs = []
            for side, chain in zip(SIDES, sides, strict=True):
                hip, knee, ankle, toe = (skeleton.index(n) for n in chain)
                off = np.asarray(skeleton.offsets, np.float64)
                length = float(np.linalg.norm(off[knee]) + np.linalg.norm(off[ankle]))
                legs.append(Leg(side, hip, knee, ankle, toe, length))
            return legs[0], legs[1]
    raise ValueError("no legs found: the skeleton has none of the joint sets "
                     + "; ".join("/".join(f) for f in LEG_FAMILIES))


def runs(mask: BoolArray) -> list[tuple[int, int]]:
    """The ``[start, end)`` ranges where ``mask`` is true."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist(), strict=True))


def clean(mask: BoolArray, fps: float, config: ContactConfig) -> BoolArray:
    """Gaps of up to ``close_gap_s`` closed, then runs shorter than ``min_run_s`` dropped."""
    out = mask.copy()
    gap = round(config.close_gap_s * fps)
    for a, b in runs(~out):
        if 0 < a and b < len(out) and b - a <= gap:
            out[a:b] = True
    shortest = round(config.min_run_s * fps)
    for a, b in runs(out):
        if b - a < shortest:
            out[a:b] = False
    return out


def effector_contact(pos: FloatArray, fps: float, height: float, speed: float, percentile: float) -> BoolArray:
    """``(F,)``: an effector's ``(F, 3)`` positions (Y up) within ``height`` of its floor and slower than
    ``speed`` horizontally (central differences)."""
    y = pos[:, 1]
    floor = float(np.percentile(y, percentile))
    if len(pos) > 1:
        v = np.linalg.norm(np.gradient(pos[:, [0, 2]], axis=0), axis=1) * fps
    else:
        v = np.zeros(len(pos))
    result: BoolArray = (y < floor + height) & (v < speed)
    return result


def locally_maximal_periods(count: IntArray) -> list[tuple[int, int]]:
    """Runs of constant ``count > 0`` whose count is at least both neighbouring runs' (a clip edge
    counts as lower): a walk's double stances, a run's single stances, a standing clip's whole span."""
    n = len(count)
    if n == 0:
        return []
    ch = np.flatnonzero(np.diff(count)) + 1
    starts = np.concatenate([[0], ch]).astype(np.intp)
    ends = np.concatenate([ch, [n]]).astype(np.intp)
    vals = count[starts]
    out = []
    for k in range(len(starts)):
        c = int(vals[k])
        left = int(vals[k - 1]) if k > 0 else -1
        right = int(vals[k + 1]) if k + 1 < len(vals) else -1
        if c > 0 and c >= left and c >= right:
            out.append((int(starts[k]), int(ends[k])))
    return out


def flights(count: IntArray, root_y: FloatArray, fps: float, config: ContactConfig) -> list[Flight]:
    """Runs of no contact, bounded by planted keys, at least ``min_flight_s`` long, whose root height fits
    a falling parabola with ``g`` in ``[g_min, g_max]``."""
    out = []
    for a, b in runs(count == 0):
        if a == 0 or b >= len(count) or (b - a) / fps < config.min_flight_s:
            continue
        j, k = a - 1, b
        t = (np.arange(j, k + 1) - j) / fps
        c2 = float(np.polyfit(t, root_y[j:k + 1], 2)[0])
        g = -2.0 * c2
        if config.g_min <= g <= config.g_max:
            out.append(Flight(j, k, g))
    return out


def detect_contacts(clip: Clip, config: ContactConfig | None = None) -> Contacts:
    """The ground contacts of a locomotion clip (the module docstring); the clip's own contact masks
    (``left_foot``, ``right_foot``) when it has them.

    Raises:
        ValueError: the skeleton has no legs perfcap knows, and the clip gives no contacts.
    """
    cfg = config or ContactConfig()
    fps = float(clip.fps)
    given = {side: clip.contacts.get(f"{side}_foot") for side in SIDES}
    feet: dict[str, BoolArray] = {}
    if all(m is not None for m in given.values()):
        for side in SIDES:
            m = given[side]
            assert m is not None
            feet[side] = np.asarray(m, np.bool_).copy()
        detected = False
    else:
        legs = find_legs(clip.skeleton)
        pos = clip.positions()
        for leg in legs:
            h, v = cfg.height_per_leg * leg.length, cfg.speed_per_leg * leg.length
            m = (effector_contact(pos[:, leg.ankle], fps, h, v, cfg.floor_percentile)
                 | effector_contact(pos[:, leg.toe], fps, h, v, cfg.floor_percentile))
            feet[leg.side] = clean(m, fps, cfg)
        detected = True
    count: IntArray = (feet["left"].astype(np.intp) + feet["right"].astype(np.intp))
    root_y = np.asarray(clip.root_pos, np.float64)[:, 1]
    return Contacts(feet, count, tuple(locally_maximal_periods(count)), tuple(flights(count, root_y, fps, cfg)),
                    detected)


__all__ = ["LEG_FAMILIES", "ContactConfig", "Contacts", "Flight", "Leg", "detect_contacts", "find_legs",
           "locally_maximal_periods"]
