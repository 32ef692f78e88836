"""VMC (Virtual Motion Capture protocol) frames over OSC: the puppet's pose as live avatar input for
VSeeFace, VMC-aware Unity/Unreal scenes, Warudo and the like.

One OSC bundle per frame, built with python-osc:

* ``/VMC/Ext/OK 1`` (the model is loaded),
* ``/VMC/Ext/T <seconds>``,
* ``/VMC/Ext/Root/Pos "root" px py pz qx qy qz qw`` (world position and rotation of the character),
* ``/VMC/Ext/Bone/Pos <Unity HumanBodyBones name> px py pz qx qy qz qw`` per mapped bone (local position
  and rotation in the parent bone's frame).

Coordinates: perfcap is right-handed with Y up and the character facing +Z; Unity is left-handed with
Y up and +Z forward. The conversion mirrors the X axis: positions ``(x, y, z) -> (-x, y, z)`` and
quaternions ``(w, x, y, z) -> (w, x, -y, -z)``. Encoding and decoding are pure: the socket that sends the
bytes lives with the retargeter.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
from pythonosc import osc_bundle, osc_message
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message import OscMessage
from pythonosc.osc_message_builder import OscMessageBuilder

ROOT_NAME = "root"


def to_unity_position(p: np.ndarray) -> np.ndarray:
    """Right-handed (perfcap) to left-handed (Unity) positions, ``(..., 3)``."""
    out = np.array(p, np.float64, copy=True)
    out[..., 0] = -out[..., 0]
    return out


def to_unity_quaternion(q: np.ndarray) -> np.ndarray:
    """Right-handed (perfcap, w x y z) to left-handed (Unity) rotations, returned as (x, y, z, w)."""
    q = np.asarray(q, np.float64)
    return np.stack([q[..., 1], -q[..., 2], -q[..., 3], q[..., 0]], axis=-1)


def _message(address: str, args: list[object]) -> OscMessage:
    b = OscMessageBuilder(address=address)
    for a in args:
        if isinstance(a, str):
            b.add_arg(a, OscMessageBuilder.ARG_TYPE_STRING)
        elif isinstance(a, int):
            b.add_arg(a, OscMessageBuilder.ARG_TYPE_INT)
        else:
            b.add_arg(float(a), OscMessageBuilder.ARG_TYPE_FLOAT)
    return b.build()


def encode_frame(names: list[str] | tuple[str, ...], local_pos: np.ndarray, local_rot: np.ndarray,
                 root_pos: np.ndarray, root_rot: np.ndarray, t: float) -> bytes:
    """One frame as an OSC bundle.

    Args:
        names: Unity HumanBodyBones names of the bones sent, in order.
        local_pos: ``(B, 3)`` each bone's position in its parent's frame (metres, perfcap axes).
        local_rot: ``(B, 4)`` each bone's local rotation (w, x, y, z).
        root_pos: ``(3,)`` the character's world position.
        root_rot: ``(4,)`` its world rotation (w, x, y, z).
        t: the frame time (seconds).

    Raises:
        ValueError: mismatched shapes or non-finite values.
    """
    lp = np.asarray(local_pos, np.float64)
    lr = np.asarray(local_rot, np.float64)
    if lp.shape != (len(names), 3) or lr.shape != (len(names), 4):
        raise ValueError(f"{len(names)} bones need (B,3) positions and (B,4) rotations, not {lp.shape}, {lr.shape}")
    if not (np.all(np.isfinite(lp)) and np.all(np.isfinite(lr)) and np.all(np.isfinite(root_pos))
            and np.all(np.isfinite(root_rot)) and np.isfinite(t)):
        raise ValueError("a VMC frame needs finite values")
    up, ur = to_unity_position(lp), to_unity_quaternion(lr)
    rp, rr = to_unity_position(np.asarray(root_pos)), to_unity_quaternion(np.asarray(root_rot))
    bundle = OscBundleBuilder(IMMEDIATELY)
    bundle.add_content(_message("/VMC/Ext/OK", [1]))
    bundle.add_content(_message("/VMC/Ext/T", [float(t)]))
    bundle.add_content(_message("/VMC/Ext/Root/Pos", [ROOT_NAME, *rp.tolist(), *rr.tolist()]))
    for i, name in enumerate(names):
        bundle.add_content(_message("/VMC/Ext/Bone/Pos", [name, *up[i].tolist(), *ur[i].tolist()]))
    return bundle.build().dgram


@dataclass(frozen=True)
class VmcFrame:
    """A decoded frame (Unity axes, quaternions x y z w as sent)."""

    ok: int
    t: float
    root: tuple[float, ...]
    bones: dict[str, tuple[float, ...]]


def decode_frame(data: bytes) -> VmcFrame:
    """Parse a bundle made by :func:`encode_frame` (for receivers and tests).

    Raises:
        ValueError: not a VMC frame bundle.
    """
    if not OscBundle.dgram_is_bundle(data):
        raise ValueError("not an OSC bundle")
    try:
        bundle = OscBundle(data)
    except (osc_bundle.ParseError, osc_message.ParseError, ValueError, IndexError, struct.error) as exc:
        raise ValueError(f"malformed OSC bundle: {exc}") from None
    ok, t, root = None, None, None
    bones: dict[str, tuple[float, ...]] = {}
    for msg in bundle:
        if not isinstance(msg, OscMessage):
            continue
        p = list(msg.params)
        if msg.address == "/VMC/Ext/OK":
            ok = int(p[0])
        elif msg.address == "/VMC/Ext/T":
            t = float(p[0])
        elif msg.address == "/VMC/Ext/Root/Pos":
            root = tuple(float(x) for x in p[1:8])
        elif msg.address == "/VMC/Ext/Bone/Pos":
            bones[str(p[0])] = tuple(float(x) for x in p[1:8])
    if ok is None or t is None or root is None:
        raise ValueError("a VMC frame needs /VMC/Ext/OK, /VMC/Ext/T and /VMC/Ext/Root/Pos")
    return VmcFrame(ok=ok, t=t, root=root, bones=bones)
