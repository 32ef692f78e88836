"""``PuppetRetargeter``: a phone's motion in, a character's pose out (Ciccone 2019, *Intuitive Control of
Animated Scenes*, ETH Diss. 25792, chapter 6, PuppetPhone).

Each input frame (time, phone position if known, phone orientation, touch) goes through:

1. the **MotionStick** (``retarget.stick``): on touch-down the character is grabbed at the end of an
   invisible stick; every frame the stick gives the target (shortened against the ground);
2. the **state machine** (``retarget.machine``, the table in ``retarget.states``): locomotion, jump
   anticipation, airborne, landing, ragdoll (the default for input no animation fits), get-up, released;
3. per state, the **pose**: locomotion blends the five locomotion clips with the verbs-and-adverbs
   engine (``retarget.adverbs.Verb`` over adverbs (speed, height)), choosing the adverbs from the stick's
   speed and height through the measured probe table (``retarget.mapping``), so the feet do not slide; the
   jump plays the mid-jump clip along the stick's path; the ragdoll is simulated (``retarget.ragdoll``)
   and pulled by the stick while held; get-up plays its clip where the ragdoll came to rest;
4. a short sigmoid **crossfade** (slerp per joint) whenever the state changes, as the verb graph blends
   transitions.

A phone that reports no position (an IMU-only phone) is treated as held at a fixed pivot: turning it
sweeps the stick's end, like a fishing rod. The retargeter is deterministic and reads no clock: time
comes with the input. Its only side effects are the optional VMC datagrams (``retarget.vmc``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from capture.quat import quat_mul, quat_slerp
from retarget.adverbs import Example, Verb
from retarget.clips import default_clips
from retarget.machine import (
    MachineConfig,
    PuppetContext,
    PuppetStateMachine,
    Transition,
)
from retarget.mapping import AxisMap, ProbeTable, PuppetMapping
from retarget.ragdoll import Ragdoll
from retarget.skeleton import Clip, Skeleton, humanoid
from retarget.states import PuppetState
from retarget.stick import MotionStick, pose_matrix
from retarget.timeline import sigmoid_blend, yaw_quat

if TYPE_CHECKING:
    from retarget._types import FloatArray
    from retarget.mapping import BlendQuery

#: Adverb points of the locomotion clips in blend space (p_vel, p_height): Ciccone 2019, section 6.2.3, Fig. 6.3.
LOCOMOTION_POINTS: dict[str, tuple[float, float]] = {
    "idle": (0.0, 1.0), "walk": (0.5, 1.0), "run": (1.0, 1.0), "crouch_idle": (0.0, 0.0), "crouch_walk": (1.0, 0.0),
}


@dataclass(frozen=True)
class PhoneInput:
    """One input frame.

    Attributes:
        t: time, seconds (non-decreasing).
        quaternion: the phone's orientation in the world (w, x, y, z; Y up).
        touch: the touchscreen is held.
        position: the phone's world position (m), or None for a phone that knows only its orientation.
    """

    t: float
    quaternion: tuple[float, float, float, float]
    touch: bool
    position: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class PuppetFrame:
    """The character at one input frame."""

    t: float
    state: PuppetState
    root_pos: FloatArray          # (3,) world position of the root (Hips)
    rotations: FloatArray         # (J, 4) local rotations, joint 0 in the world
    transitions: tuple[Transition, ...]
    blend: tuple[float, float]    # (p_vel, p_height) used this frame
    speedup: float


@dataclass
class PuppetConfig:
    """Settings of the retargeter (metres, seconds).

    Attributes:
        height: character height.
        pivot: where a phone without position is held.
        crouch: maps the stick end's height (as a share of the standing root height) to p_height.
        crossfade: seconds of the pose blend when the state changes.
        num_cp: B-spline control points per channel of the locomotion verb (enough to keep the feet's
            plant and lift sharp: 24 smooths them into centimetres of sliding).
        follow_s: time constant with which the walking root closes its distance to the stick's end (it
            moves with the animation's own velocity, corrected this gently, so the feet do not slide).
        hold_joint: the joint the stick holds in the ragdoll.
        turn_s: on the ground the character turns to face where the stick's end moves (the clips walk
            forwards), and back to the stick's yaw when it stops, closing its heading error with this time
            constant. For a phone without position (the fishing rod, whose yaw is spent sweeping the end
            round the pivot) it keeps its heading when the end stops.
        turn_speed: the end must move faster than this (m/s) for the character to face its travel.
        machine: state machine thresholds (its character height follows ``height``).
    """

    height: float = 1.75
    pivot: tuple[float, float, float] = (0.0, 1.3, 0.0)
    crouch: AxisMap = field(default_factory=lambda: AxisMap(0.6, 0.95))
    crossfade: float = 0.2
    follow_s: float = 1.5
    num_cp: int = 64
    hold_joint: str = "Chest"
    turn_s: float = 0.15
    turn_speed: float = 0.3
    machine: MachineConfig | None = None


class PuppetRetargeter:
    """Drives a character from phone input frames.

    Args:
        config: settings.
        skeleton: the character (default ``humanoid(config.height)``).
        clips: the clip set (default ``default_clips(skeleton)``): idle, walk, run, crouch_idle,
            crouch_walk, get_up, mid_jump.

    Raises:
        ValueError: a clip is missing or does not fit the skeleton.
    """

    def __init__(self, config: PuppetConfig | None = None, *, skeleton: Skeleton | None = None,
                 clips: dict[str, Clip] | None = None) -> None:
        self.config = config or PuppetConfig()
        self.skeleton = skeleton or humanoid(self.config.height)
        self.clips = clips or default_clips(self.skeleton)
        missing = [n for n in (*LOCOMOTION_POINTS, "get_up", "mid_jump") if n not in self.clips]
        if missing:
            raise ValueError(f"the puppet needs the clips {missing}")
        # locomotion verb: every example on the same canonical timeline (one cycle, key-times 0 and T)
        examples = []
        for name, point in LOCOMOTION_POINTS.items():
            clip = self.clips[name]
            clip = replace(clip, key_times=(0.0, clip.duration))
            examples.append(Example.from_clip(clip, point))
        self.verb = Verb(examples, periodic=True, num_cp=self.config.num_cp, name="locomotion")
        self.table = ProbeTable.measure(lambda v, h: self.verb.root_speed((v, h)))
        self.mapping = PuppetMapping(self.table, self.config.crouch)
        self.stand_height = float(self.verb.sample((0.0, 1.0), 0.0).root_pos[1])
        mc = self.config.machine or MachineConfig(character_height=self.config.height,
                                                   get_up_duration=self.clips["get_up"].duration)
        self.machine = PuppetStateMachine(mc)
        self._clearance = 0.5 * self.stand_height
        self.stick = MotionStick(clearance=self._clearance)
        self.ragdoll = Ragdoll(self.skeleton.parents, self.skeleton.offsets)
        self.hold_index = self.skeleton.index(self.config.hold_joint)
        self.reset()

    def reset(self) -> None:
        """Back to a released character standing at the origin, facing +Z."""
        self.t: float | None = None
        self.position = np.array([0.0, self.stand_height, 1.5])
        self.heading = 0.0
        self.phase = 0.0
        self.velocity = np.zeros(3)
        self._last_target: FloatArray | None = None
        self._last_rot = self.verb.pose((0.0, 1.0), 0.0)[1]
        self._last_root = self.position.copy()
        self._fade_from: tuple[FloatArray, FloatArray] | None = None
        self._fade_at = 0.0
        self._state_at = 0.0
        self._jump_offset = np.zeros(3)
        self._get_up_base = np.zeros(3)
        self._hold_offset = np.zeros(3)
        self._prev_joints: FloatArray | None = None
        self._touch = False
        self.machine = PuppetStateMachine(self.machine.config)
        self.stick.release()
        self.mapping.reset()

    # -- the frame

    def step(self, inp: PhoneInput) -> PuppetFrame:
        """One input frame in, the character's pose out.

        Raises:
            ValueError: time going backwards, or a non-finite input.
        """
        t = float(inp.t)
        q = np.asarray(inp.quaternion, np.float64)
        if not (math.isfinite(t) and np.all(np.isfinite(q)) and np.linalg.norm(q) > 1e-6):
            raise ValueError("a phone frame needs a finite time and a non-zero orientation")
        if self.t is not None and t < self.t:
            raise ValueError(f"time went backwards ({t} after {self.t})")
        dt = 0.0 if self.t is None else t - self.t
        self.t = t
        pos = np.asarray(inp.position if inp.position is not None else self.config.pivot, np.float64)
        x_phone = pose_matrix(pos, q / np.linalg.norm(q))

        # grab / release: the stick holds the character's root where it stands
        if inp.touch and not self._touch:
            x_obj = pose_matrix(self.position, yaw_quat(self.heading))
            self.stick.grab(x_phone, x_obj)
            if self.machine.state is PuppetState.RAGDOLL:   # the held joint stays where it lies
                self._hold_offset = self.ragdoll.pos[self.hold_index] - self.ragdoll.pos[0]
        elif not inp.touch and self._touch:
            self.stick.release()
        self._touch = bool(inp.touch)

        state = self.machine.state
        grounded = state in (PuppetState.LOCOMOTION, PuppetState.JUMP_ANTICIPATION, PuppetState.LANDING)
        # the ground shortens the stick so the standing root stays up; a limp body may lie on the floor
        self.stick.clearance = self.ragdoll.s.radius if state is PuppetState.RAGDOLL else self._clearance
        if self.stick.held:
            target = self.stick.update(x_phone, grounded=grounded)
            end = target.pose[:3, 3].copy()
            heading = float(target.heading)
        else:
            end = self.position.copy()
            heading = self.heading
        prev_end = end if self._last_target is None else self._last_target
        if self._last_target is not None and dt > 0:
            v = (end - self._last_target) / dt
            a = 1.0 - math.exp(-dt / 0.05)            # 50 ms smoothing of the finite difference
            self.velocity = self.velocity + a * (v - self.velocity)
        self._last_target = end
        if inp.position is None:                       # the rod: the phone's yaw is spent sweeping
            heading = self._facing(dt, self.heading)
        elif grounded:
            heading = self._facing(dt, heading)

        lift = max(0.0, float(end[1]) - self.stand_height)
        u_height = float(end[1]) / self.stand_height
        blend = self.mapping.update(t, float(np.hypot(self.velocity[0], self.velocity[2])), u_height)
        ctx = PuppetContext(t=t, position=(float(end[0]), float(end[1]), float(end[2])),
                            velocity=(float(self.velocity[0]), float(self.velocity[1]), float(self.velocity[2])),
                            heading=heading,
                            height=lift, touch=bool(inp.touch), ragdoll_at_rest=self.ragdoll.at_rest,
                            crouch=float(blend.p_height), speedup=float(blend.speedup))
        transitions = tuple(self.machine.step(ctx))
        new_state = self.machine.state
        if transitions:
            self._on_transitions(transitions, t, prev_end)
        root, rot, p_used, speedup = self._pose(new_state, t, dt, end, heading, blend)
        root, rot = self._crossfade(t, root, rot)
        self.position = root.copy()
        if new_state in (PuppetState.LOCOMOTION, PuppetState.JUMP_ANTICIPATION, PuppetState.LANDING,
                         PuppetState.AIRBORNE):
            self.heading = heading
        self._last_root, self._last_rot = root, rot
        return PuppetFrame(t=t, state=new_state, root_pos=root, rotations=rot, transitions=transitions,
                           blend=p_used, speedup=speedup)

    def _on_transitions(self, transitions: tuple[Transition, ...], t: float, prev_end: FloatArray) -> None:
        last = transitions[-1].to_state
        self._fade_from = (self._last_root.copy(), self._last_rot.copy())
        self._fade_at = t
        self._state_at = t
        if last is PuppetState.RAGDOLL:
            joints = self.skeleton.fk(self._last_root, self._last_rot)
            vel = np.tile(self.velocity, (joints.shape[0], 1))
            self.ragdoll.start(joints, vel)
            self._hold_offset = joints[self.hold_index] - self._last_root   # the stick holds the root
            self._fade_from = None                      # physics takes over from the current pose
        elif last is PuppetState.AIRBORNE:
            # the jump follows the stick's end from wherever the character took off (no jump to the end)
            self._jump_offset = np.array([self.position[0] - prev_end[0], 0.0, self.position[2] - prev_end[2]])
        elif last is PuppetState.GET_UP:
            hips = self.ragdoll.pos[0]
            self._get_up_base = np.array([hips[0], 0.0, hips[2]])

    def _pose(self, state: PuppetState, t: float, dt: float, end: FloatArray, heading: float,
              blend: BlendQuery) -> tuple[FloatArray, FloatArray, tuple[float, float], float]:
        yaw = yaw_quat(heading)
        if state is PuppetState.LOCOMOTION:
            p = (float(blend.p_vel), float(blend.p_height))
            speedup = min(float(blend.speedup), self.machine.config.max_speedup)
            dur = self.verb.duration(p)
            self.phase = (self.phase + dt * speedup / dur) % 1.0
            pos, vel, rot = self.verb.pose(p, self.phase, with_position=True)
            rot[0] = quat_mul(yaw, rot[0])
            # the root moves with the blended motion's own velocity (so planted feet stay planted), and
            # is drawn gently towards the stick's end so it follows it without sliding the feet
            step = _rotate(yaw, np.asarray(vel, np.float64)) * speedup * dt
            err = np.array([end[0] - self.position[0], 0.0, end[2] - self.position[2]])
            k = min(1.0, dt / self.config.follow_s)
            root = np.array([self.position[0] + step[0] + k * err[0], float(pos[1]),
                             self.position[2] + step[2] + k * err[2]])
            return root, rot, p, speedup
        if state in (PuppetState.JUMP_ANTICIPATION, PuppetState.LANDING, PuppetState.INTERACT):
            # the squat carries on at the stick's ground speed (a running jump does not stop to crouch)
            p = (0.0, 0.0)
            pos, _, rot = self.verb.pose(p, self.phase, with_position=True)
            rot[0] = quat_mul(yaw, rot[0])
            glide = 0.0 if state is PuppetState.INTERACT else dt
            return np.array([self.position[0] + self.velocity[0] * glide, float(pos[1]),
                             self.position[2] + self.velocity[2] * glide]), rot, p, 1.0
        if state is PuppetState.AIRBORNE:
            clip = self.clips["mid_jump"]
            _, rot = clip.sample(self._jump_clip_time(t, end, clip))
            rot = np.array(rot, np.float64)
            rot[0] = quat_mul(yaw, rot[0])
            return end + self._jump_offset, rot, (0.0, 1.0), 1.0
        if state is PuppetState.RAGDOLL:
            hold = (self.hold_index, end + self._hold_offset) if self.stick.held else None
            if dt > 0:
                self.ragdoll.step(dt, hold)
            root, rot = self.ragdoll.rotations()
            return root, rot, (0.0, 1.0), 1.0
        if state is PuppetState.GET_UP:
            clip = self.clips["get_up"]
            root, rot = clip.sample(min(t - self._state_at, clip.duration))
            rot = np.array(rot, np.float64)
            rot[0] = quat_mul(yaw_quat(self.heading), rot[0])
            off = yaw_quat(self.heading)
            r = _rotate(off, np.asarray(root, np.float64) - np.asarray(clip.root_pos[0], np.float64))
            return self._get_up_base + r + np.array([0.0, float(clip.root_pos[0][1]), 0.0]), rot, (0.0, 1.0), 1.0
        # RELEASED: idle where it stands
        p = (0.0, 1.0)
        pos, _, rot = self.verb.pose(p, self.phase, with_position=True)
        self.phase = (self.phase + dt / self.verb.duration(p)) % 1.0
        rot[0] = quat_mul(yaw_quat(self.heading), rot[0])
        return np.array([self.position[0], float(pos[1]), self.position[2]]), rot, p, 1.0

    def _jump_clip_time(self, t: float, end: FloatArray, clip: Clip) -> float:
        """Where the mid-jump clip is: the fitted parabola's apex drives it (Ciccone 2019, section 6.3), the
        clip's middle key-time (the tuck) at the apex, its end at the height the jump started from; by time
        since takeoff while the fit has no apex yet."""
        jump = self.machine.jump
        arc = jump.arc if jump is not None else None
        apex_key = clip.key_times[1] if len(clip.key_times) > 2 else 0.5 * clip.duration
        if jump is None or arc is None or arc.apex is None or not arc.apex[0] > 0:
            return min(t - self._state_at, clip.duration)
        if arc.parameter == "distance":
            ux, uz = jump.direction
            x = (float(end[0]) - jump.start[0]) * ux + (float(end[2]) - jump.start[2]) * uz
        else:
            x = t - jump.t0
        return float(min(max(apex_key * x / arc.apex[0], 0.0), clip.duration))

    def _facing(self, dt: float, still_heading: float) -> float:
        """The grounded character's heading: it turns to face where the stick's end goes while that moves
        faster than ``turn_speed`` (so it never walks backwards or sideways on forward-walking clips),
        else to ``still_heading`` (the stick's yaw; for the rod, where it faces), in ``turn_s``."""
        vx, vz = float(self.velocity[0]), float(self.velocity[2])
        moving = math.hypot(vx, vz) >= self.config.turn_speed
        goal = math.atan2(vx, vz) if moving else still_heading
        if dt <= 0:
            return self.heading if moving else still_heading
        err = (goal - self.heading + math.pi) % (2 * math.pi) - math.pi
        return self.heading + err * (1.0 - math.exp(-dt / self.config.turn_s))

    def _crossfade(self, t: float, root: FloatArray, rot: FloatArray) -> tuple[FloatArray, FloatArray]:
        if self._fade_from is None:
            return root, rot
        u = (t - self._fade_at) / self.config.crossfade
        if u >= 1.0:
            self._fade_from = None
            return root, rot
        a = float(sigmoid_blend(max(0.0, u)))
        r0, q0 = self._fade_from
        # the pose and the root's height blend; the root's ground position is the new state's (which
        # starts where the old one left it), so it neither stops nor rushes at the change
        out = root.copy()
        out[1] = r0[1] + a * (root[1] - r0[1])
        return out, quat_slerp(q0, rot, a)


def _rotate(q: FloatArray, v: FloatArray) -> FloatArray:
    """``v`` rotated by the unit quaternion ``q`` (w, x, y, z)."""
    w, x, y, z = (float(c) for c in q)
    vx, vy, vz = (float(c) for c in v)
    tx, ty, tz = y * vz - z * vy + w * vx, z * vx - x * vz + w * vy, x * vy - y * vx + w * vz
    return np.array([vx + 2.0 * (y * tz - z * ty), vy + 2.0 * (z * tx - x * tz), vz + 2.0 * (x * ty - y * tx)])
