"""The embedded default clip set, generated procedurally for the ``humanoid()`` skeleton so the puppet needs
no downloads: ``default_clips()`` returns idle, walk, run, crouch_idle, crouch_walk, get_up and mid_jump.

Locomotion is planned, not keyframed. Each foot follows a plan in the world: in stance the ball of the foot
(the Toes joint) stays where it touched down while the heel rolls up before toe-off; in swing the ankle
travels to the next foothold on an arc that comes down steeply, landing flat with no horizontal velocity.
The root advances along +Z at the clip's constant speed, sways towards the stance foot and bobs; the bob
curve is lowered until every planned ankle is within reach (99.5% of the leg in stance). The legs are then
solved with analytic two-bone IK (knees towards the pelvis's forward direction), arms swing against the
legs, the spine counter-rotates the pelvis and the head keeps looking ahead. A loop starts at the left
foot's touch-down; its key-times are the touch-downs. get_up (lying on the back to the idle pose) and
mid_jump (a tucked airborne pose) interpolate a few key poses with monotone cubic curves and use the same
IK. Every clip starts with the root at X = Z = 0, facing +Z. Everything is deterministic. Lengths and
speeds scale with the leg length of the skeleton (1 for ``humanoid(1.75)``); durations do not.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.interpolate import PchipInterpolator

from capture.quat import (
    quat_conj,
    quat_from_axis_angle,
    quat_from_matrix,
    quat_mul,
    quat_rotate,
)
from retarget.skeleton import Clip, Skeleton, humanoid

if TYPE_CHECKING:
    from retarget._types import BoolArray, FloatArray

__all__ = ["CLIP_NAMES", "DEFAULT_FPS", "GAITS", "Gait", "default_clips"]

DEFAULT_FPS = 60.0
"""Frame rate of the generated clips."""

CLIP_NAMES = ("idle", "walk", "run", "crouch_idle", "crouch_walk", "get_up", "mid_jump")
"""The clips ``default_clips`` returns, in this order."""

_REF_LEG = 0.86          # thigh + shin of humanoid(1.75), metres
_BALL_H = 0.015          # height of the ball-of-foot joint above the ground with the foot flat (ref. size)
_STAND_REACH = 0.997     # standing: hip-to-ankle distance as a fraction of the leg length
_STANCE_REACH = 0.995    # locomotion, foot on the ground
_SWING_REACH = 0.999     # locomotion, foot in the air
_ARC_POW = 1.0          # swing lift ~ sin(pi s)**_ARC_POW: 1 comes down steeply, keeping late swing in reach
_TOES_UP = 10.0          # degrees of toes-up just before a touch-down
_SIDES = ("Left", "Right")
_X = np.array([1.0, 0.0, 0.0])
_Y = np.array([0.0, 1.0, 0.0])
_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Gait:
    """The plan of one locomotion loop (lengths for the 1.75 m reference humanoid; angles in degrees).

    Args:
        speed: root speed along +Z, m/s.
        cycle: seconds per loop (two steps).
        duty: fraction of the cycle each foot is on the ground (> 0.5 walks, < 0.5 has a flight phase).
        lift: height of the swing arc of the ankle, m.
        lift_skew: exponent on the swing phase of the lift arc (< 1 peaks early, heel kicked up).
        heel_off: fraction of the stance after which the heel starts rising.
        toe_off_pitch: foot pitch at toe-off (heel up), degrees.
        ball_ahead: ball of the foot ahead of the hip at mid-stance, m.
        bob: pelvis bob amplitude, m (> 0 highest at mid-stance, < 0 lowest there, as in running).
        sway: lateral pelvis sway towards the stance foot, m.
        half_width: lateral distance of each foot from the mid-line, m.
        max_height: cap on the root height as a fraction of the standing root height (crouching).
        yaw: pelvis yaw amplitude, degrees (the leading leg's hip forward).
        tilt: forward pelvis tilt, degrees.
        lean: extra forward lean of the spine, degrees.
        arm_swing: arm swing amplitude, degrees.
        arm_forward: constant forward arm raise, degrees.
        elbow: mean elbow flexion, degrees.
        elbow_swing: elbow flexion amplitude, degrees.
    """

    speed: float
    cycle: float
    duty: float
    lift: float
    lift_skew: float
    heel_off: float
    toe_off_pitch: float
    ball_ahead: float
    bob: float
    sway: float
    half_width: float
    max_height: float
    yaw: float
    tilt: float
    lean: float
    arm_swing: float
    arm_forward: float
    elbow: float
    elbow_swing: float


GAITS: dict[str, Gait] = {
    "walk": Gait(speed=1.4, cycle=1.0, duty=0.6, lift=0.07, lift_skew=1.0, heel_off=0.45, toe_off_pitch=50.0,
                 ball_ahead=0.02, bob=0.02, sway=0.02, half_width=0.095, max_height=1.0, yaw=6.0, tilt=3.0,
                 lean=2.0, arm_swing=16.0, arm_forward=0.0, elbow=15.0, elbow_swing=8.0),
    "run": Gait(speed=3.5, cycle=0.7, duty=0.36, lift=0.22, lift_skew=0.55, heel_off=0.3, toe_off_pitch=60.0,
                ball_ahead=-0.04, bob=-0.025, sway=0.01, half_width=0.07, max_height=1.0, yaw=10.0, tilt=8.0,
                lean=6.0, arm_swing=35.0, arm_forward=5.0, elbow=80.0, elbow_swing=12.0),
    "crouch_walk": Gait(speed=0.8, cycle=1.2, duty=0.65, lift=0.06, lift_skew=0.8, heel_off=0.5,
                        toe_off_pitch=25.0, ball_ahead=0.14, bob=0.01, sway=0.02, half_width=0.12,
                        max_height=0.66, yaw=5.0, tilt=22.0, lean=14.0, arm_swing=10.0, arm_forward=20.0,
                        elbow=40.0, elbow_swing=5.0),
}
"""The three locomotion loops (walk 1.4 m/s, run 3.5 m/s, crouch_walk 0.8 m/s)."""


# ------------------------------------------------------------------------------------------------- rig


class _Rig:
    """What the generator needs to know about a humanoid skeleton."""

    def __init__(self, sk: Skeleton) -> None:
        ref = humanoid()
        missing = [n for n in ref.names if n not in sk.names]
        if missing:
            raise ValueError(f"default clips need the humanoid() joints; missing {missing}")
        self.sk = sk
        off = sk.offsets
        self.leg = {s: (sk.index(f"{s}UpperLeg"), sk.index(f"{s}LowerLeg"), sk.index(f"{s}Foot"),
                        sk.index(f"{s}Toes")) for s in _SIDES}
        _, knee, ankle, toes = self.leg["Left"]
        self.l1 = float(np.linalg.norm(off[knee]))
        self.l2 = float(np.linalg.norm(off[ankle]))
        self.k = (self.l1 + self.l2) / _REF_LEG
        self.toes_off = {s: off[self.leg[s][3]].copy() for s in _SIDES}
        self.hip_off = {s: off[self.leg[s][0]].copy() for s in _SIDES}
        self.ball_h = _BALL_H * self.k
        self.ankle_h = self.ball_h - float(off[toes][1])
        # rest frames of thigh and shin (bone along -y', knee hinge x'), to map solved frames to rotations
        self.rest_frame = {}
        for s in _SIDES:
            _, knee_j, ankle_j, _ = self.leg[s]
            self.rest_frame[s] = (_frame(-off[knee_j], _X), _frame(-off[ankle_j], _X))
        # standing root height: feet flat under the hips, legs at _STAND_REACH of full length
        hip_y = float(self.hip_off["Left"][1])
        self.stand_y = self.ankle_h - hip_y + _STAND_REACH * (self.l1 + self.l2)


def _frame(y_axis: FloatArray, x_hint: FloatArray) -> FloatArray:
    """Orthonormal frame(s) ``(..., 3, 3)`` with columns x, y, z: y along ``y_axis``, x from ``x_hint``."""
    y = y_axis / np.linalg.norm(y_axis, axis=-1, keepdims=True)
    x = x_hint - np.sum(x_hint * y, axis=-1, keepdims=True) * y
    x = x / np.linalg.norm(x, axis=-1, keepdims=True)
    z = np.cross(x, y)
    return np.stack([x, y, z], axis=-1)


def _rx(deg: FloatArray | float) -> FloatArray:
    return quat_from_axis_angle(_X, np.radians(deg))


def _ry(deg: FloatArray | float) -> FloatArray:
    return quat_from_axis_angle(_Y, np.radians(deg))


def _rz(deg: FloatArray | float) -> FloatArray:
    return quat_from_axis_angle(_Z, np.radians(deg))


def _two_bone(hip: FloatArray, ankle: FloatArray, pole: FloatArray, l1: float, l2: float
              ) -> tuple[FloatArray, FloatArray]:
    """Knee positions and the hinge axis for hip/ankle targets ``(F, 3)`` (knee bent towards ``pole``)."""
    v = ankle - hip
    d = np.linalg.norm(v, axis=1, keepdims=True)
    u = v / d
    dc = np.clip(d, abs(l1 - l2) + 1e-9, (l1 + l2) * (1 - 1e-9))
    n = pole - np.sum(pole * u, axis=1, keepdims=True) * u
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    a = (l1 * l1 - l2 * l2 + dc * dc) / (2 * dc)
    h = np.sqrt(np.maximum(l1 * l1 - a * a, 0.0))
    knee = hip + a * u + h * n
    hinge = np.cross(n, u)
    return knee, hinge / np.linalg.norm(hinge, axis=1, keepdims=True)


@dataclass
class _Pose:
    """Per-frame inputs of the pose solver (``F`` frames)."""

    root: FloatArray                         # (F, 3)
    local: dict[str, FloatArray]             # joint -> (F, 4) local rotation (Hips: world)
    ankle: dict[str, FloatArray]             # side -> (F, 3) ankle target
    foot: dict[str, FloatArray]              # side -> (F, 4) foot world rotation
    head: FloatArray | None = None           # (F, 4) head world rotation (keeps the gaze level)


def _solve(rig: _Rig, pose: _Pose) -> FloatArray:
    """Local rotations ``(F, J, 4)`` realising the pose: given locals, IK legs, feet and head in the world."""
    sk = rig.sk
    f = len(pose.root)
    n = sk.n_joints
    ident = np.tile([1.0, 0.0, 0.0, 0.0], (f, 1))
    rot = np.tile(ident[:, None, :], (1, n, 1))
    wq = np.empty((f, n, 4))
    wp = np.empty((f, n, 3))
    world_goal: dict[int, FloatArray] = {}
    if pose.head is not None:
        world_goal[sk.index("Head")] = pose.head
    legs = {rig.leg[s][0]: s for s in _SIDES}
    for j, name in enumerate(sk.names):
        p = int(sk.parents[j])
        if p < 0:
            local = pose.local.get(name, ident)
            wp[:, j] = pose.root + sk.offsets[j]
        else:
            wp[:, j] = wp[:, p] + quat_rotate(wq[:, p], sk.offsets[j])
            if j in legs:
                side = legs[j]
                _, knee_j, ankle_j, _ = rig.leg[side]
                pole = quat_rotate(wq[:, 0], _Z)
                knee, hinge = _two_bone(wp[:, j], pose.ankle[side], pole, rig.l1, rig.l2)
                rest_thigh, rest_shin = rig.rest_frame[side]
                thigh = quat_from_matrix(_frame(wp[:, j] - knee, hinge) @ rest_thigh.T)
                shin = quat_from_matrix(_frame(knee - pose.ankle[side], hinge) @ rest_shin.T)
                world_goal[knee_j] = shin
                world_goal[ankle_j] = pose.foot[side]
                local = quat_mul(quat_conj(wq[:, p]), thigh)
            elif j in world_goal:
                local = quat_mul(quat_conj(wq[:, p]), world_goal[j])
            else:
                local = pose.local.get(name, ident)
        rot[:, j] = local
        wq[:, j] = quat_mul(wq[:, p], local) if p >= 0 else local
    return rot


def _arms(f: int, swing_left: FloatArray, forward: float, elbow_left: FloatArray, elbow_right: FloatArray,
          down: float = 80.0, swing_right: FloatArray | None = None) -> dict[str, FloatArray]:
    """Upper and lower arm locals: hanging ``down`` degrees from the T-pose, swung about X (+ = backwards)."""
    if swing_right is None:
        swing_right = -swing_left
    out = {}
    for side, sign, swing, elbow in (("Left", 1.0, swing_left, elbow_left), ("Right", -1.0, swing_right,
                                                                               elbow_right)):
        out[f"{side}UpperArm"] = quat_mul(_rx(np.broadcast_to(swing - forward, (f,))),
                                          np.broadcast_to(_rz(-sign * down), (f, 4)))
        out[f"{side}LowerArm"] = _ry(-sign * np.broadcast_to(elbow, (f,)))
    return out


def _touch_down_times(contacts: dict[str, BoolArray], fps: float) -> tuple[float, ...]:
    """0, the time of every frame where a contact starts, and the duration."""
    n_frames = len(next(iter(contacts.values())))
    events = {i for c in contacts.values() for i in np.flatnonzero(c[1:] & ~c[:-1]) + 1}
    return tuple(sorted({0.0, (n_frames - 1) / fps} | {i / fps for i in events if i < n_frames - 1}))


# ------------------------------------------------------------------------------------------- locomotion


def _smoothstep(x: FloatArray) -> FloatArray:
    x = np.clip(x, 0.0, 1.0)
    y: FloatArray = x * x * (3.0 - 2.0 * x)
    return y


def _min_jerk(x: FloatArray) -> FloatArray:
    x = np.clip(x, 0.0, 1.0)
    y: FloatArray = x ** 3 * (10.0 - 15.0 * x + 6.0 * x * x)
    return y


def _foot_plan(rig: _Rig, g: Gait, n: int, side: str) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray]:
    """Ankle position ``(F, 3)``, foot pitch (degrees, + = heel up), toes pitch and stance mask of one foot.

    In stance the ball of the foot stays on its foothold and the foot pivots about it; in swing the ankle
    goes from its toe-off position to the next touch-down position (minimum-jerk forward, lifted on an arc
    that comes down steeply, landing flat with no horizontal velocity).
    """
    k = rig.k
    v = g.speed * k
    i = np.arange(n + 1)
    shift = 0 if side == "Left" else n // 2
    phase = ((i - shift) % n) / n                      # 0 at this foot's touch-down
    cycle_idx = np.floor((i - shift) / n)
    stance = phase < g.duty
    t_down = (cycle_idx * n + shift) / DEFAULT_FPS       # time of the latest touch-down
    x = (1.0 if side == "Left" else -1.0) * g.half_width * k
    ball_z = v * (t_down + g.duty * g.cycle / 2) + g.ball_ahead * k
    # stance pitch rises from heel_off to toe_off_pitch at toe-off
    h = np.clip((phase / g.duty - g.heel_off) / (1 - g.heel_off), 0.0, 1.0)
    pitch_stance = g.toe_off_pitch * h * h
    ball = np.stack([np.full(n + 1, x), np.full(n + 1, rig.ball_h), ball_z], axis=1)
    toes = rig.toes_off[side]
    ankle_stance = ball - quat_rotate(_rx(pitch_stance), toes)
    # swing: from the toe-off ankle to the next (flat) touch-down ankle
    s = np.clip((phase - g.duty) / (1 - g.duty), 0.0, 1.0)
    lo = np.array([x, rig.ball_h, 0.0]) - quat_rotate(_rx(g.toe_off_pitch), toes)
    td = np.array([x, rig.ball_h, 0.0]) - toes
    lo_z = ball_z[:, None] + lo[2]
    td_z = ball_z[:, None] + v * g.cycle + td[2]
    swing_z = lo_z[:, 0] + (td_z - lo_z)[:, 0] * _min_jerk(s)
    blend = _smoothstep(s)
    swing_y = lo[1] + (td[1] - lo[1]) * blend + g.lift * k * np.sin(np.pi * s ** g.lift_skew) ** _ARC_POW
    ankle_swing = np.stack([np.full(n + 1, x), swing_y, swing_z], axis=1)
    ankle = np.where(stance[:, None], ankle_stance, ankle_swing)
    pitch_swing = (g.toe_off_pitch * (1 - _smoothstep(s / 0.5))
                   - _TOES_UP * np.where(s > 0.5, np.sin(np.pi * (s - 0.5) * 2) ** 2, 0.0))
    pitch = np.where(stance, pitch_stance, pitch_swing)
    return ankle, pitch, np.maximum(pitch, 0.0), stance


def _locomotion(rig: _Rig, name: str, g: Gait) -> Clip:
    k = rig.k
    n = round(g.cycle * DEFAULT_FPS)
    if n % 2:
        raise ValueError(f"{name}: the cycle must be an even number of frames")
    f = n + 1
    i = np.arange(f)
    t = i / DEFAULT_FPS
    ph = i / n                                          # left foot phase, 0 (and 1) at left touch-down
    two_pi = 2 * np.pi
    plans = {s: _foot_plan(rig, g, n, s) for s in _SIDES}
    # pelvis orientation: yaw brings the leading leg's hip forward, tilt leans it
    yaw = -g.yaw * np.cos(two_pi * ph)
    pelvis = quat_mul(_ry(yaw), _rx(np.full(f, g.tilt)))
    root = np.zeros((f, 3))
    root[:, 0] = g.sway * k * np.sin(two_pi * ph)
    root[:, 2] = g.speed * k * t
    ankles, feet = {}, {}
    for s in _SIDES:
        ankles[s], pitch, _, _ = plans[s]
        feet[s] = _rx(pitch)
    # root height: bob shape shifted down until every stance ankle is within reach (and capped)
    shape = g.bob * k * np.cos(2 * two_pi * (ph - g.duty / 2))
    bound = np.full(f, np.inf)
    for s in _SIDES:
        # stance: the ankle within 99.5% of the leg; swing: within reach at all (the foot follows its arc)
        reach = np.where(plans[s][3], _STANCE_REACH, _SWING_REACH) * (rig.l1 + rig.l2)
        hoff = quat_rotate(pelvis, rig.hip_off[s])
        hip_xz = root[:, [0, 2]] + hoff[:, [0, 2]]
        dxz = np.linalg.norm(hip_xz - ankles[s][:, [0, 2]], axis=1)
        up = ankles[s][:, 1] - hoff[:, 1] + np.sqrt(np.maximum(reach ** 2 - dxz ** 2, 0.0))
        bound = np.minimum(bound, up)
    base = min(float(np.min(bound - shape)), g.max_height * rig.stand_y - abs(g.bob) * k)
    root[:, 1] = base + shape
    # spine counter-rotation and lean, head level
    spine = quat_mul(_ry(-yaw * 0.4), _rx(np.full(f, g.lean / 3)))
    local = {"Hips": pelvis, "Spine": spine, "Chest": spine, "UpperChest": spine}
    swing = g.arm_swing * np.cos(two_pi * ph)                    # left arm back while the left leg leads
    elbow_l = g.elbow + g.elbow_swing * np.cos(two_pi * ph)
    elbow_r = g.elbow - g.elbow_swing * np.cos(two_pi * ph)
    local.update(_arms(f, swing, g.arm_forward, elbow_l, elbow_r))
    for s in _SIDES:
        local[f"{s}Toes"] = _rx(-plans[s][2])
    pose = _Pose(root, local, ankles, feet, head=_rx(np.full(f, 5.0 if g.tilt > 10 else 0.0)))
    rot = _solve(rig, pose)
    contacts = {"left_foot": plans["Left"][3], "right_foot": plans["Right"][3]}
    return Clip(name, rig.sk, DEFAULT_FPS, root, rot, contacts, _touch_down_times(contacts, DEFAULT_FPS),
                loop=True)


# ------------------------------------------------------------------------------------------------ idles


def _standing(rig: _Rig, t: FloatArray, crouch: bool) -> _Pose:
    """Idle (or crouched idle) pose at times ``t`` (2 s breathing and weight-shift cycle)."""
    k = rig.k
    f = len(t)
    w = 2 * np.pi * t / 2.0
    breath = np.sin(w)
    root = np.zeros((f, 3))
    root[:, 0] = (0.012 if not crouch else 0.008) * k * np.sin(w)
    if crouch:
        root[:, 1] = 0.62 * rig.stand_y + 0.004 * k * breath
        half_w, ankle_z, tilt, lean, forward, elbow, head = 0.14, 0.10, 25.0, 15.0, 25.0, 45.0, 10.0
    else:
        root[:, 1] = rig.stand_y - 0.003 * k * (1 - np.cos(w))
        half_w, ankle_z, tilt, lean, forward, elbow, head = 0.11, 0.0, 0.0, 0.0, 0.0, 10.0, 0.0
    pelvis = _rx(np.full(f, tilt))
    spine = _rx(lean / 3 - 1.0 * breath)
    chest = _rx(lean / 3 + 1.5 * breath)
    local = {"Hips": pelvis, "Spine": spine, "Chest": chest, "UpperChest": spine}
    for s, sign in (("Left", 1.0), ("Right", -1.0)):
        local[f"{s}Shoulder"] = _rz(sign * 1.5 * breath)
    swing = 2.0 * breath
    local.update(_arms(f, swing, forward, np.full(f, elbow), np.full(f, elbow), swing_right=swing))
    ankles, feet = {}, {}
    for s, sign in (("Left", 1.0), ("Right", -1.0)):
        ankles[s] = np.tile([sign * half_w * k, rig.ankle_h, ankle_z * k], (f, 1))
        feet[s] = np.tile([1.0, 0.0, 0.0, 0.0], (f, 1))
    return _Pose(root, local, ankles, feet, head=_rx(np.full(f, head)))


def _idle(rig: _Rig, name: str, crouch: bool) -> Clip:
    f = round(2.0 * DEFAULT_FPS) + 1
    t = np.arange(f) / DEFAULT_FPS
    pose = _standing(rig, t, crouch)
    rot = _solve(rig, pose)
    on = np.ones(f, dtype=bool)
    return Clip(name, rig.sk, DEFAULT_FPS, pose.root, rot, {"left_foot": on, "right_foot": on.copy()},
                loop=True)


# -------------------------------------------------------------------------------------- keyframed clips


def _pchip(times: list[float], values: list[float], t: FloatArray) -> FloatArray:
    return np.asarray(PchipInterpolator(times, values)(t), np.float64)


def _get_up(rig: _Rig) -> Clip:
    """From lying on the back (head towards -Z, feet towards +Z) to the idle's first pose in 1.5 s.

    The root starts at X = Z = 0 and ends 0.35 m (reference size) further along +Z, above the feet.
    """
    k = rig.k
    duration = 1.5
    f = round(duration * DEFAULT_FPS) + 1
    # the key poses are spaced on a warped clock (smoothstep) so the clip starts and ends at rest
    t = duration * _smoothstep(np.arange(f) / DEFAULT_FPS / duration)
    dz = 0.35 * k
    end = _standing(rig, np.zeros(1), crouch=False)
    end.root[:, 2] += dz
    for s in _SIDES:
        end.ankle[s][:, 2] += dz
    keys = [0.0, 0.35, 0.7, 1.0, 1.5]
    root_y = _pchip(keys, [0.10 * k, 0.12 * k, 0.12 * k, 0.50 * k, float(end.root[0, 1])], t)
    root_z = _pchip(keys, [0.0, 0.0, 0.0, 0.23 * k, dz], t)
    root = np.stack([np.zeros(f), root_y, root_z], axis=1)
    pelvis = _rx(_pchip(keys, [-90.0, -45.0, -25.0, 25.0, 0.0], t))
    flex = _pchip(keys, [0.0, 40.0, 45.0, 20.0, 0.0], t)
    spine = _rx(flex / 3)
    local = {"Hips": pelvis, "Spine": spine, "Chest": spine, "UpperChest": spine,
             "Head": _rx(_pchip(keys, [10.0, 5.0, 0.0, 10.0, 0.0], t))}
    arm_fwd = _pchip(keys, [0.0, 40.0, 70.0, 60.0, 0.0], t)
    elbow = _pchip(keys, [10.0, 20.0, 20.0, 25.0, 10.0], t)
    local.update(_arms(f, -arm_fwd, 0.0, elbow, elbow, swing_right=-arm_fwd))
    ankle_y = _pchip(keys, [0.06 * k, 0.06 * k, rig.ankle_h, rig.ankle_h, rig.ankle_h], t)
    ankle_z = _pchip(keys, [0.88 * k, 0.85 * k, dz, dz, dz], t)
    foot_pitch = _pchip(keys, [-75.0, -60.0, 0.0, 0.0, 0.0], t)
    ankles, feet = {}, {}
    for s in _SIDES:
        x = float(end.ankle[s][0, 0])
        ankles[s] = np.stack([np.full(f, x), ankle_y, ankle_z], axis=1)
        feet[s] = _rx(foot_pitch)
    rot = _solve(rig, _Pose(root, local, ankles, feet))
    # the last frame is the idle's first pose (moved along Z): same solver, same inputs
    rot[-1] = _solve(rig, end)[0]
    root[-1] = end.root[0]
    pos = rig.sk.fk(root, rot)
    # planted: on the ground (ball or heel) and not dragged (ankle slower than 5 cm/s, pulling the feet in
    # is a slide, not a contact to lock)
    contacts = {}
    for s, key in (("Left", "left_foot"), ("Right", "right_foot")):
        _, _, ankle_j, toes_j = rig.leg[s]
        low = (pos[:, toes_j, 1] < rig.ball_h + 0.02 * k) | (pos[:, ankle_j, 1] < rig.ankle_h + 0.02 * k)
        speed = np.linalg.norm(np.gradient(pos[:, ankle_j], axis=0), axis=1) * DEFAULT_FPS
        contacts[key] = low & (speed < 0.05 * k)
    # key-times: when the warped clock passes the key poses (the inverse of the smoothstep)
    y = np.array(keys) / duration
    key_times = duration * (0.5 - np.sin(np.arcsin(1.0 - 2.0 * y) / 3.0))
    key_times[0], key_times[-1] = 0.0, duration
    return Clip("get_up", rig.sk, DEFAULT_FPS, root, rot, contacts, tuple(key_times), loop=False)


def _mid_jump(rig: _Rig) -> Clip:
    """A short airborne clip: extended after take-off, tucked at the apex, reaching down for the landing."""
    k = rig.k
    f = round(0.5 * DEFAULT_FPS) + 1
    t = np.arange(f) / DEFAULT_FPS
    keys = [0.0, 0.25, 0.5]
    root = np.zeros((f, 3))
    root[:, 1] = rig.stand_y
    pelvis = _rx(_pchip(keys, [5.0, 15.0, 8.0], t))
    spine = _rx(_pchip(keys, [2.0, 12.0, 5.0], t) / 3)
    local = {"Hips": pelvis, "Spine": spine, "Chest": spine, "UpperChest": spine}
    arm_fwd = _pchip(keys, [30.0, 100.0, 50.0], t)
    elbow = _pchip(keys, [20.0, 45.0, 25.0], t)
    local.update(_arms(f, -arm_fwd, 0.0, elbow, elbow, down=70.0, swing_right=-arm_fwd))
    drop = _pchip(keys, [0.76, 0.45, 0.72], t) * k
    ahead = _pchip(keys, [-0.10, 0.08, 0.10], t) * k
    pitch = _pchip(keys, [40.0, 15.0, 8.0], t)
    ankles, feet = {}, {}
    hip_y = float(rig.hip_off["Left"][1])
    for s in _SIDES:
        x = float(rig.hip_off[s][0]) * 1.1
        ankles[s] = np.stack([np.full(f, x), rig.stand_y + hip_y - drop, ahead], axis=1)
        feet[s] = _rx(pitch)
        local[f"{s}Toes"] = _rx(-0.3 * pitch)
    rot = _solve(rig, _Pose(root, local, ankles, feet, head=_rx(np.full(f, 5.0))))
    off = np.zeros(f, dtype=bool)
    return Clip("mid_jump", rig.sk, DEFAULT_FPS, root, rot, {"left_foot": off, "right_foot": off.copy()},
                tuple(keys), loop=False)


# ---------------------------------------------------------------------------------------------- public


def default_clips(skeleton: Skeleton | None = None) -> dict[str, Clip]:
    """The seven default clips, generated for ``skeleton`` (default ``humanoid()``).

    Loops (``loop=True``): idle (2 s, breathing), walk (1.4 m/s, 1.0 s cycle), run (3.5 m/s, 0.7 s),
    crouch_idle (2 s) and crouch_walk (0.8 m/s, 1.2 s); walk, run and crouch_walk start at the left foot's
    touch-down and their key-times are the touch-downs. One-shots: get_up (1.5 s, lying on the back to the
    idle's first pose, 0.35 m further along +Z; key-times at its key poses; contacts where a foot rests
    still on the floor, not while the feet are dragged in) and mid_jump (0.5 s; key-time at the tuck). All at
    ``DEFAULT_FPS``; speeds and lengths scale with the skeleton's leg length relative to ``humanoid(1.75)``.

    Args:
        skeleton: a skeleton with (at least) the joints of ``humanoid()``.

    Returns:
        name -> clip, in the order of ``CLIP_NAMES``.

    Raises:
        ValueError: if the skeleton lacks a humanoid joint.
    """
    rig = _Rig(skeleton if skeleton is not None else humanoid())
    return {
        "idle": _idle(rig, "idle", crouch=False),
        "walk": _locomotion(rig, "walk", GAITS["walk"]),
        "run": _locomotion(rig, "run", GAITS["run"]),
        "crouch_idle": _idle(rig, "crouch_idle", crouch=True),
        "crouch_walk": _locomotion(rig, "crouch_walk", GAITS["crouch_walk"]),
        "get_up": _get_up(rig),
        "mid_jump": _mid_jump(rig),
    }
