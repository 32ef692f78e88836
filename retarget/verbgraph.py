"""The verb graph (Rose 1999, *Verbs and Adverbs*, Princeton PhD thesis, chapter 5): transitions between
verbs and the per-actor queue that plays them.

This module owns ``Transition`` (section 5.5, Def 10: a blend function, a region of verb A and a region of verb B in
canonical time), ``BlendedTransition`` (a transition evaluated under fixed adverbs: duration T^d = mean of
the two region durations; non-root DOFs blended by slerp with alpha(t); the root from the blended
heading-relative velocities and turn rates, integrated once on a fixed grid, so the path does not swing;
usage from A while t <= 0.5 and from B after), and ``VerbGraph`` with its ``Actor`` state (section 5.2,
Eq 5.3) and UpdateQueue / PositionDOFs / UpdateVerbGraph (Alg 5.1-5.3).

The root (X, Z, heading) only ever moves by deltas evaluated under the current adverbs, rotated into the
world by the item's Alg 3.2 angle, so changing p never makes the root jump or backtrack, and stepping a
span of time in one step or in many gives the same pose (the deltas telescope). Adverbs move towards
their targets at most ``adverb_rate`` x dt per update. One deliberate change from Alg 5.1: after a
transition, verb B resumes at t_B(T_B^s + T^d), where the transition left it (this is t_B^e when the two
regions last equally long; resuming at t_B^e otherwise makes the pose jump).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.interpolate import CubicSpline

from capture.errors import RetargetError
from capture.quat import quat_mul, quat_slerp
from retarget._types import FloatArray
from retarget.timeline import sigmoid_blend, yaw_quat

if TYPE_CHECKING:
    from retarget.adverbs import Verb, VerbFrame

__all__ = ["Actor", "ActorPose", "BlendedTransition", "Transition", "TransitionFrame", "VerbGraph"]

BlendFunction = Callable[[float | FloatArray], float | FloatArray]


@dataclass(frozen=True, eq=False)
class Transition:
    """A transition from verb ``source`` to verb ``target`` (Def 10), regions in canonical time.

    Attributes:
        source: verb A.
        target: verb B (may equal A: a cycle).
        a_start: t_A^s, where A starts to blend out (the exit point).
        a_end: t_A^e.
        b_start: t_B^s, where B starts to blend in.
        b_end: t_B^e.
        blend: alpha(t), non-decreasing [0, 1] -> [0, 1].
        weight: designer weight for automatic choice; 0 = never chosen automatically.
        name: label; defaults to "A->B".
    """

    source: str
    target: str
    a_start: float
    a_end: float
    b_start: float
    b_end: float
    blend: BlendFunction = sigmoid_blend
    weight: float = 1.0
    name: str = ""

    def __post_init__(self) -> None:
        """Validate the regions.

        Raises:
            ValueError: a region not inside [0, 1] with start < end, or a negative weight.
        """
        for s, e, which in ((self.a_start, self.a_end, "A"), (self.b_start, self.b_end, "B")):
            if not (0.0 <= s < e <= 1.0):
                raise ValueError(f"transition region {which} must satisfy 0 <= start < end <= 1, got [{s}, {e}]")
        if not (self.weight >= 0.0 and math.isfinite(self.weight)):
            raise ValueError(f"weight must be >= 0, got {self.weight}")
        if not self.name:
            object.__setattr__(self, "name", f"{self.source}->{self.target}")


@dataclass(frozen=True)
class TransitionFrame:
    """A transition evaluated at transition time(s) T, in the transition's own frame (origin at A's root
    at the start, heading 0 = A's heading at the start).

    Attributes:
        root_pos: (..., 3) X, Z from the integrated path; Y the alpha-blend of the heights.
        heading: (...,) integrated heading.
        root_velocity: (..., 3) horizontal velocity of the path (Y: 0).
        heading_rate: (...,) blended turn rate.
        rotations: (..., J, 4) slerped local rotations; joint 0 is the root tilt.
        alpha: (...,) blend weight of B.
        t: (...,) canonical time of the transition.
    """

    root_pos: FloatArray
    heading: FloatArray
    root_velocity: FloatArray
    heading_rate: FloatArray
    rotations: FloatArray
    alpha: FloatArray
    t: FloatArray


def _rot_y(a: float | FloatArray, x: FloatArray, z: FloatArray) -> tuple[FloatArray, FloatArray]:
    ca, sa = np.cos(a), np.sin(a)
    return ca * x + sa * z, -sa * x + ca * z


class BlendedTransition:
    """A transition under fixed adverbs of A and B.

    Args:
        transition: the transition.
        verb_a: verb A.
        p_a: A's adverbs.
        verb_b: verb B.
        p_b: B's adverbs.
        grid: samples of the fixed integration grid of the root path.

    Attributes:
        duration: T^d = ((T_A^e - T_A^s) + (T_B^e - T_B^s)) / 2.
        a_offset: T_A^s.
        b_offset: T_B^s.

    Raises:
        ValueError: bad adverbs, or verbs with different joint counts.
    """

    def __init__(
        self,
        transition: Transition,
        verb_a: Verb,
        p_a: FloatArray,
        verb_b: Verb,
        p_b: FloatArray,
        *,
        grid: int = 257,
    ) -> None:
        if verb_a.num_joints != verb_b.num_joints:
            raise ValueError("a transition needs verbs over the same skeleton")
        self.transition = transition
        self.verb_a, self.verb_b = verb_a, verb_b
        self.p_a = np.atleast_1d(np.asarray(p_a, dtype=float)).copy()
        self.p_b = np.atleast_1d(np.asarray(p_b, dtype=float)).copy()
        ka = np.asarray(verb_a.verb_time(self.p_a, np.array([transition.a_start, transition.a_end])))
        kb = np.asarray(verb_b.verb_time(self.p_b, np.array([transition.b_start, transition.b_end])))
        self.a_offset = float(ka[0])
        self.b_offset = float(kb[0])
        self.duration = 0.5 * (float(ka[1] - ka[0]) + float(kb[1] - kb[0]))
        T = np.linspace(0.0, self.duration, grid)
        fa, fb, alpha = self._ends(T)
        va_x, va_z = _rot_y(-fa.heading, fa.root_velocity[:, 0], fa.root_velocity[:, 2])
        vb_x, vb_z = _rot_y(-fb.heading, fb.root_velocity[:, 0], fb.root_velocity[:, 2])
        vx = (1.0 - alpha) * va_x + alpha * vb_x
        vz = (1.0 - alpha) * va_z + alpha * vb_z
        omega = (1.0 - alpha) * fa.heading_rate + alpha * fb.heading_rate
        self._heading = CubicSpline(T, omega).antiderivative()
        h = self._heading(T)
        wx, wz = _rot_y(h, vx, vz)
        self._path = CubicSpline(T, np.stack([wx, wz], axis=1)).antiderivative()
        self._velocity = self._path.derivative()
        self._turn_rate = self._heading.derivative()

    def _ends(self, T: FloatArray) -> tuple[VerbFrame, VerbFrame, FloatArray]:
        fa = self.verb_a.at_time(self.p_a, T + self.a_offset)
        fb = self.verb_b.at_time(self.p_b, T + self.b_offset)
        t = np.clip(np.asarray(T, dtype=float) / self.duration, 0.0, 1.0)
        alpha = np.asarray(self.transition.blend(t), dtype=float)
        return fa, fb, alpha

    def root(self, T: float | FloatArray) -> tuple[FloatArray, FloatArray]:
        """The root path: horizontal position (X, Z) and heading at transition time(s) T (clamped).

        Args:
            T: transition time(s), seconds.

        Returns:
            (xz (..., 2), heading (...,)), zero at T = 0.
        """
        Tc = np.clip(np.asarray(T, dtype=float), 0.0, self.duration)
        return self._path(Tc), self._heading(Tc)

    def frame(self, T: float | FloatArray) -> TransitionFrame:
        """Everything at transition time(s) T (clamped to [0, T^d]).

        Args:
            T: seconds.

        Returns:
            A ``TransitionFrame``.
        """
        Tc = np.clip(np.asarray(T, dtype=float), 0.0, self.duration)
        fa, fb, alpha = self._ends(Tc)
        xz, h = self.root(Tc)
        vxz = self._velocity(Tc)
        y = (1.0 - alpha) * fa.root_pos[..., 1] + alpha * fb.root_pos[..., 1]
        rot = quat_slerp(fa.rotations, fb.rotations, alpha[..., None] * np.ones(fa.rotations.shape[:-1]))
        return TransitionFrame(
            root_pos=np.stack([xz[..., 0], y, xz[..., 1]], axis=-1),
            heading=h,
            root_velocity=np.stack([vxz[..., 0], np.zeros_like(y), vxz[..., 1]], axis=-1),
            heading_rate=self._turn_rate(Tc),
            rotations=rot,
            alpha=alpha,
            t=Tc / self.duration,
        )

    def usage_source(self, t: float) -> str:
        """The verb whose usage and constraints apply at canonical time t: A while t <= 0.5, then B.

        Args:
            t: canonical time of the transition.

        Returns:
            The verb name.
        """
        return self.transition.source if t <= 0.5 else self.transition.target

    def exit_time_b(self) -> float:
        """Canonical time of B where the transition leaves it: t_B(T_B^s + T^d) (within one cycle).

        Returns:
            t in [0, 1].
        """
        T = self.b_offset + self.duration
        d = self.verb_b.duration(self.p_b)
        if self.verb_b.periodic:
            T = T - math.floor(T / d) * d if T > d else T
        return float(self.verb_b.canonical_time(self.p_b, min(T, d)))


@dataclass(frozen=True)
class ActorPose:
    """An actor's pose.

    Attributes:
        tau: animation time.
        root_pos: (3,) world root position.
        heading: world heading.
        rotations: (J, 4) joint rotations; joint 0 is the root's world rotation.
        item: name of the playing queue item (a verb or a transition).
        usage: the verb whose usage and constraints apply.
        t: canonical time in the playing item.
    """

    tau: float
    root_pos: FloatArray
    heading: float
    rotations: FloatArray
    item: str
    usage: str
    t: float


QueueItem = str | Transition


@dataclass
class Actor:
    """Per-actor state (Eq 5.3): times, the queue and the pose.

    Attributes:
        name: the actor.
        tau_now: current animation time.
        t_in: canonical entry time of the front item.
        t_out: canonical exit time of the front item.
        tau_in: animation time at which the front item started.
        queue: (v t)*v or (t v)*t v, never empty.
        adverbs: current adverbs per verb.
        targets: adverb targets per verb (approached at ``adverb_rate``).
        adverb_rate: largest |dp| per second (inf: immediate).
        root_xz: world X, Z of the root.
        height: root Y.
        heading: world heading.
        frame_angle: the Alg 3.2 angle of the front item (world heading minus item heading).
        rotations: (J, 4) last joint rotations (root: world).
        hold: the front item has no exit; the actor holds its last pose.
        usage: the verb whose usage and constraints apply now.
        item_t: canonical time in the front item.
        history: the names of the last items entered (at most 256).
    """

    name: str
    tau_now: float
    t_in: float
    t_out: float
    tau_in: float
    queue: deque[QueueItem]
    adverbs: dict[str, FloatArray]
    targets: dict[str, FloatArray]
    adverb_rate: float
    root_xz: FloatArray
    height: float
    heading: float
    frame_angle: float
    rotations: FloatArray
    hold: bool = False
    usage: str = ""
    item_t: float = 0.0
    history: deque[str] = field(default_factory=lambda: deque(maxlen=256))

    @property
    def front(self) -> QueueItem:
        """The playing item."""
        return self.queue[0]

    def pose(self) -> ActorPose:
        """The current pose.

        Returns:
            An ``ActorPose`` (arrays copied).
        """
        f = self.front
        return ActorPose(
            tau=self.tau_now,
            root_pos=np.array([self.root_xz[0], self.height, self.root_xz[1]]),
            heading=self.heading,
            rotations=self.rotations.copy(),
            item=f if isinstance(f, str) else f.name,
            usage=self.usage,
            t=self.item_t,
        )


class VerbGraph:
    """Verbs, transitions and start verbs; plays actors through them (Alg 5.1-5.3).

    Args:
        verbs: the verbs by name.
        transitions: the transitions.
        start_verbs: verbs an actor may start in (None: all).
        seed: seed of the automatic choice of exits.
        grid: integration grid of transition root paths.

    Raises:
        ValueError: unknown verbs, verbs over different skeletons, or a transition that enters a verb
            after that verb's last exit.
    """

    def __init__(
        self,
        verbs: Mapping[str, Verb],
        transitions: Sequence[Transition],
        start_verbs: Sequence[str] | None = None,
        *,
        seed: int = 0,
        grid: int = 257,
    ) -> None:
        if not verbs:
            raise ValueError("a verb graph needs verbs")
        self.verbs = dict(verbs)
        joints = {v.num_joints for v in self.verbs.values()}
        if len(joints) != 1:
            raise ValueError("all verbs must share one skeleton")
        self.transitions = tuple(transitions)
        for tr in self.transitions:
            if tr.source not in self.verbs or tr.target not in self.verbs:
                raise ValueError(f"transition {tr.name} names an unknown verb")
        self.start_verbs = tuple(self.verbs) if start_verbs is None else tuple(start_verbs)
        if any(s not in self.verbs for s in self.start_verbs):
            raise ValueError("unknown start verb")
        for tr in self.transitions:
            exits = [x.a_start for x in self.transitions if x.source == tr.target]
            if exits and tr.b_end > max(exits):
                raise ValueError(
                    f"transition {tr.name} enters {tr.target} at {tr.b_end}, after its last exit {max(exits)}"
                )
        self.rng = np.random.default_rng(seed)
        self.grid = int(grid)
        self.actors: dict[str, Actor] = {}
        self._blends: dict[tuple[int, bytes, bytes], BlendedTransition] = {}

    # -- helpers --------------------------------------------------------------------------------

    def exits(self, verb: str) -> list[Transition]:
        """Transitions leaving ``verb``.

        Args:
            verb: the verb.

        Returns:
            The transitions, in declaration order.
        """
        return [tr for tr in self.transitions if tr.source == verb]

    def blended(self, actor: Actor, tr: Transition) -> BlendedTransition:
        """``tr`` under the actor's current adverbs (cached per adverb values).

        Args:
            actor: the actor.
            tr: the transition.

        Returns:
            The blended transition.
        """
        pa, pb = actor.adverbs[tr.source], actor.adverbs[tr.target]
        key = (id(tr), pa.tobytes(), pb.tobytes())
        bt = self._blends.get(key)
        if bt is None:
            if len(self._blends) > 256:
                self._blends.clear()
            bt = BlendedTransition(tr, self.verbs[tr.source], pa, self.verbs[tr.target], pb, grid=self.grid)
            self._blends[key] = bt
        return bt

    def _front_time(self, actor: Actor, t: float) -> float:
        """T_0(t): the verb time at canonical time ``t`` of the item at the front of the queue (Q_0)."""
        f = actor.front
        if isinstance(f, str):
            return float(self.verbs[f].verb_time(actor.adverbs[f], t))
        return t * self.blended(actor, f).duration

    def tau_out(self, actor: Actor) -> float:
        """End of the front item under the current adverbs: tau_in + T_0(t_out) - T_0(t_in) (Eq 5.2).

        Args:
            actor: the actor.

        Returns:
            Animation time (inf while the actor holds a verb with no exit).
        """
        if actor.hold:
            return math.inf
        return actor.tau_in + self._front_time(actor, actor.t_out) - self._front_time(actor, actor.t_in)

    def _local(self, actor: Actor, T: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, float]:
        """Root (xz, height, heading) and rotations of the front item at item times T (2 values)."""
        f = actor.front
        if isinstance(f, str):
            fr = self.verbs[f].at_time(actor.adverbs[f], T)
            xz = fr.root_pos[:, [0, 2]]
            return xz, fr.root_pos[:, 1], fr.heading, fr.rotations[-1], float(fr.t[-1])
        bt = self.blended(actor, f)
        fr2 = bt.frame(T)
        return fr2.root_pos[:, [0, 2]], fr2.root_pos[:, 1], fr2.heading, fr2.rotations[-1], float(fr2.t[-1])

    def _set_frame(self, actor: Actor) -> None:
        T = self._front_time(actor, actor.t_in)
        _, _, h, _, _ = self._local(actor, np.array([T, T]))
        actor.frame_angle = actor.heading - float(h[0])

    def _choose_exit(self, verb: str, t_from: float) -> Transition | None:
        cands = [tr for tr in self.exits(verb) if tr.a_start >= t_from and tr.weight > 0.0]
        if not cands:
            return None
        w = np.array([tr.weight for tr in cands])
        return cands[int(self.rng.choice(len(cands), p=w / w.sum()))]

    def _extend(self, actor: Actor) -> None:
        """Continuability: a front verb that is the last item gets an exit and its target appended."""
        if len(actor.queue) == 1 and isinstance(actor.front, str):
            tr = self._choose_exit(actor.front, actor.t_in)
            if tr is not None:
                actor.queue.extend([tr, tr.target])

    @staticmethod
    def _next_exit(actor: Actor) -> Transition:
        nxt = actor.queue[1]
        if not isinstance(nxt, Transition):
            raise RetargetError(f"actor {actor.name!r}: queue items must alternate verbs and transitions")
        return nxt

    def _enter(self, actor: Actor) -> None:
        """Set t_out, hold and the Alg 3.2 frame of a new front item (t_in already set)."""
        f = actor.front
        if isinstance(f, str):
            self._extend(actor)
            if len(actor.queue) > 1:
                actor.t_out = max(self._next_exit(actor).a_start, actor.t_in)
                actor.hold = False
            else:
                actor.t_out = 1.0
                actor.hold = True
        else:
            actor.t_out = 1.0
            actor.hold = False
        actor.history.append(f if isinstance(f, str) else f.name)
        self._set_frame(actor)

    # -- public API -----------------------------------------------------------------------------

    def add_actor(
        self,
        name: str,
        verb: str,
        *,
        tau: float = 0.0,
        t_start: float = 0.0,
        position: Sequence[float] = (0.0, 0.0),
        heading: float = 0.0,
        adverbs: Mapping[str, Sequence[float] | FloatArray] | None = None,
        adverb_rate: float = math.inf,
    ) -> Actor:
        """Place an actor in a start verb.

        Args:
            name: actor name (unique).
            verb: a start verb.
            tau: animation time now.
            t_start: canonical time to enter the verb at.
            position: world (X, Z) of the root.
            heading: world heading.
            adverbs: initial adverbs per verb; others start at the mean of their examples' points.
            adverb_rate: largest |dp| per second when adverbs change (inf: immediate).

        Returns:
            The actor (also in ``actors``).

        Raises:
            ValueError: duplicate actor, not a start verb, bad t_start, bad adverbs or rate.
        """
        if name in self.actors:
            raise ValueError(f"actor {name!r} exists")
        if verb not in self.start_verbs:
            raise ValueError(f"{verb!r} is not a start verb")
        if not 0.0 <= t_start <= 1.0:
            raise ValueError("t_start must be in [0, 1]")
        if not adverb_rate > 0.0:
            raise ValueError("adverb_rate must be positive")
        p = {k: v.points.mean(axis=0) for k, v in self.verbs.items()}
        for k, val in (adverbs or {}).items():
            if k not in self.verbs:
                raise ValueError(f"unknown verb {k!r}")
            arr = np.atleast_1d(np.asarray(val, dtype=float))
            if arr.shape != (self.verbs[k].dim,):
                raise ValueError(f"verb {k!r} takes {self.verbs[k].dim} adverbs")
            p[k] = arr.copy()
        nj = next(iter(self.verbs.values())).num_joints
        actor = Actor(
            name=name,
            tau_now=float(tau),
            t_in=float(t_start),
            t_out=1.0,
            tau_in=float(tau),
            queue=deque([verb]),
            adverbs=p,
            targets={k: v.copy() for k, v in p.items()},
            adverb_rate=float(adverb_rate),
            root_xz=np.asarray(position, dtype=float).copy(),
            height=0.0,
            heading=float(heading),
            frame_angle=0.0,
            rotations=np.tile([1.0, 0.0, 0.0, 0.0], (nj, 1)),
        )
        self._enter(actor)
        T = self._front_time(actor, actor.t_in)
        _, y, _h, rot, t = self._local(actor, np.array([T, T]))
        actor.height = float(y[-1])
        actor.rotations = rot.copy()
        actor.rotations[0] = quat_mul(yaw_quat(actor.heading), rot[0])
        actor.usage, actor.item_t = verb, t
        self.actors[name] = actor
        return actor

    def set_adverbs(self, name: str, verb: str, p: Sequence[float] | FloatArray) -> None:
        """Set the adverb target of one verb for an actor (reached at the actor's adverb rate).

        Args:
            name: actor.
            verb: verb.
            p: target adverbs.

        Raises:
            ValueError: unknown actor or verb, or wrong dimension.
        """
        actor = self._actor(name)
        if verb not in self.verbs:
            raise ValueError(f"unknown verb {verb!r}")
        arr = np.atleast_1d(np.asarray(p, dtype=float))
        if arr.shape != (self.verbs[verb].dim,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"verb {verb!r} takes {self.verbs[verb].dim} finite adverbs")
        actor.targets[verb] = arr.copy()

    def request(self, name: str, verb: str) -> Transition:
        """Queue a change to ``verb`` as soon as the graph allows.

        The tentative tail of the queue (automatic choices not yet playing) is dropped; the earliest
        achievable direct transition from the current (or, during a transition, the next) verb is used,
        or a self-transition first when the direct one is already behind in this cycle.

        Args:
            name: actor.
            verb: the requested verb.

        Returns:
            The direct transition queued.

        Raises:
            ValueError: unknown actor or verb, or no transition leads there.
            RetargetError: the transition exists but cannot be reached from the current state.
        """
        actor = self._actor(name)
        if verb not in self.verbs:
            raise ValueError(f"unknown verb {verb!r}")
        if isinstance(actor.front, str):
            base = actor.front
            fr = self.verbs[base]
            T_now = self._front_time(actor, actor.t_in) + (actor.tau_now - actor.tau_in)
            t_from = float(fr.canonical_time(actor.adverbs[base], T_now))
            keep = 1
        else:
            tr0 = actor.front
            base = tr0.target
            t_from = tr0.b_end
            keep = 2
        direct = [tr for tr in self.exits(base) if tr.target == verb]
        if not direct:
            raise ValueError(f"no transition from {base!r} to {verb!r}")
        chain: list[QueueItem] = []
        ok = [tr for tr in direct if tr.a_start >= t_from]
        if ok:
            chosen = min(ok, key=lambda tr: tr.a_start)
        else:
            loops = [tr for tr in self.exits(base) if tr.target == base and tr.a_start >= t_from]
            if not loops:
                raise RetargetError(f"{base!r} is past every exit to {verb!r} and has no self-transition")
            loop = min(loops, key=lambda tr: tr.a_start)
            after = [tr for tr in direct if tr.a_start >= loop.b_end]
            if not after:
                raise RetargetError(f"no exit from {base!r} to {verb!r} after its self-transition")
            chosen = min(after, key=lambda tr: tr.a_start)
            chain = [loop, base]
        while len(actor.queue) > keep:
            actor.queue.pop()
        actor.queue.extend([*chain, chosen, verb])
        if keep == 1:
            actor.t_out = max(self._next_exit(actor).a_start, actor.t_in)
            actor.hold = False
        return chosen

    def update(self, name: str, tau_next: float) -> ActorPose:
        """UpdateVerbGraph (Alg 5.3): advance an actor to ``tau_next``.

        Adverbs first move towards their targets by at most adverb_rate x dt; then, while tau_next reaches
        the end of the front item, the DOFs are positioned at that end and the queue advances; finally the
        DOFs are positioned at tau_next.

        Args:
            name: actor.
            tau_next: animation time, not before the actor's current time.

        Returns:
            The pose at ``tau_next``.

        Raises:
            ValueError: unknown actor or time going backwards.
            RetargetError: the queue does not advance (zero-length items looping).
        """
        actor = self._actor(name)
        if not tau_next >= actor.tau_now:
            raise ValueError(f"time must not go backwards ({tau_next} < {actor.tau_now})")
        self._move_adverbs(actor, tau_next - actor.tau_now)
        for _ in range(100_000):
            end = self.tau_out(actor)
            if tau_next < end:
                break
            self._position(actor, end)
            self._update_queue(actor, end)
        else:
            raise RetargetError(f"actor {name!r}: the verb graph does not advance")
        self._position(actor, tau_next)
        return actor.pose()

    # -- the algorithms -------------------------------------------------------------------------

    def _actor(self, name: str) -> Actor:
        try:
            return self.actors[name]
        except KeyError:
            raise ValueError(f"unknown actor {name!r}") from None

    def _move_adverbs(self, actor: Actor, dt: float) -> None:
        for k, target in actor.targets.items():
            cur = actor.adverbs[k]
            d = target - cur
            n = float(np.linalg.norm(d))
            if n == 0.0:
                continue
            lim = actor.adverb_rate * dt
            actor.adverbs[k] = target.copy() if n <= lim else cur + d * (lim / n)

    def _position(self, actor: Actor, tau: float) -> None:
        """PositionDOFs (Alg 5.2): root by deltas under the current adverbs, the rest absolute."""
        T_in = self._front_time(actor, actor.t_in)
        T = np.array([T_in + (actor.tau_now - actor.tau_in), T_in + (tau - actor.tau_in)])
        if actor.hold:  # no exit: the item stops at its end and the actor holds that pose
            T = np.minimum(T, self._front_time(actor, actor.t_out))
        xz, y, h, rot, t = self._local(actor, T)
        dx, dz = _rot_y(actor.frame_angle, xz[1, 0] - xz[0, 0], xz[1, 1] - xz[0, 1])
        actor.root_xz = actor.root_xz + np.array([dx, dz])
        actor.heading += float(h[1] - h[0])
        actor.height = float(y[1])
        rotations = rot.copy()
        rotations[0] = quat_mul(yaw_quat(actor.heading), rot[0])
        actor.rotations = rotations
        f = actor.front
        actor.usage = f if isinstance(f, str) else self.blended(actor, f).usage_source(t)
        actor.item_t = t
        actor.tau_now = float(tau)

    def _update_queue(self, actor: Actor, tau_out: float) -> None:
        """UpdateQueue (Alg 5.1): pop the front item and enter the next at tau_in = tau_out."""
        left = actor.queue.popleft()
        if not actor.queue:  # cannot happen for (v t)*v queues; keep the verb rather than empty the queue
            actor.queue.append(left if isinstance(left, str) else left.target)
        actor.tau_in = tau_out
        if isinstance(left, Transition):
            bt = self.blended(actor, left)
            actor.t_in = bt.exit_time_b()
        else:
            actor.t_in = 0.0
        self._enter(actor)
