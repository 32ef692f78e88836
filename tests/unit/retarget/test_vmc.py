"""VMC frames: python-osc bundles a VMC receiver decodes, with Unity's axes."""

from __future__ import annotations

import socket

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pythonosc.osc_bundle import OscBundle
from scipy.spatial.transform import Rotation

from retarget.vmc import (
    VmcEncoder,
    build_frame,
    decode_frame,
    encode_frame,
    to_unity_position,
    to_unity_quaternion,
)


def random_frame(rng: np.random.Generator, n: int) -> tuple[list[str], np.ndarray, np.ndarray]:
    names = [f"Bone{i}" for i in range(n)]
    pos = rng.normal(size=(n, 3))
    q = Rotation.random(n, random_state=int(rng.integers(1 << 30))).as_quat()[:, [3, 0, 1, 2]]
    return names, pos, q


def test_round_trip_through_a_real_udp_socket() -> None:
    rng = np.random.default_rng(0)
    names, pos, rot = random_frame(rng, 30)
    data = encode_frame(names, pos, rot, np.array([1.0, 0.0, 2.0]), np.array([1.0, 0, 0, 0]), 1.25)
    assert OscBundle.dgram_is_bundle(data)
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        rx.bind(("127.0.0.1", 0))
        rx.settimeout(2.0)
        tx.sendto(data, rx.getsockname())
        got, _ = rx.recvfrom(65535)
    finally:
        rx.close()
        tx.close()
    f = decode_frame(got)
    assert f.ok == 1 and f.t == pytest.approx(1.25)
    assert f.root[:3] == pytest.approx((-1.0, 0.0, 2.0))
    assert set(f.bones) == set(names)
    for i, n in enumerate(names):
        b = np.array(f.bones[n])
        np.testing.assert_allclose(b[:3], to_unity_position(pos[i]), atol=1e-6)   # OSC floats are 32-bit
        np.testing.assert_allclose(b[3:], to_unity_quaternion(rot[i]), atol=1e-6)


def test_unity_conversion_is_a_mirror_of_x() -> None:
    # a rotation about Y by +30 deg (right-handed) is -30 deg about Y in Unity's left-handed frame with
    # x mirrored; applying it to a mirrored vector gives the mirrored result
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = Rotation.random(random_state=int(rng.integers(1 << 30))).as_quat()[[3, 0, 1, 2]]
        v = rng.normal(size=3)
        rotated = Rotation.from_quat(q[[1, 2, 3, 0]]).apply(v)
        u = to_unity_quaternion(q)                 # x y z w
        # in Unity (left-handed) the same quaternion algebra applies to mirrored coordinates
        mirrored = Rotation.from_quat(u).apply(to_unity_position(v))
        np.testing.assert_allclose(mirrored, to_unity_position(rotated), atol=1e-12)


def test_bad_frames_raise_value_error() -> None:
    with pytest.raises(ValueError):
        encode_frame(["a"], np.zeros((2, 3)), np.zeros((1, 4)), np.zeros(3), np.array([1.0, 0, 0, 0]), 0.0)
    with pytest.raises(ValueError):
        encode_frame(["a"], np.full((1, 3), np.nan), np.array([[1.0, 0, 0, 0]]), np.zeros(3),
                     np.array([1.0, 0, 0, 0]), 0.0)
    with pytest.raises(ValueError):
        decode_frame(b"/VMC/Ext/OK\x00")
    with pytest.raises(ValueError):
        decode_frame(b"#bundle\x00" + b"\x00" * 8 + b"\x00\x00\x00\x40garbage")


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 40), t=st.floats(-1e6, 1e6),
       name_len=st.integers(1, 13))
def test_the_template_encoder_writes_the_bytes_python_osc_builds(seed: int, n: int, t: float, name_len: int) -> None:
    # names of every padding length (OSC strings pad to 4 bytes), values of every size
    rng = np.random.default_rng(seed)
    _, pos, rot = random_frame(rng, n)
    names = [f"B{i}".ljust(name_len + i % 4, "x") for i in range(n)]
    pos *= 10.0 ** rng.integers(-3, 4)
    root_pos, root_rot = rng.normal(size=3) * 100.0, rot[0]
    enc = VmcEncoder(names)
    assert enc.encode(pos, rot, root_pos, root_rot, t) == build_frame(names, pos, rot, root_pos, root_rot, t)
    # the template is reused: a second frame is encoded from scratch, not patched over the first
    pos2 = pos[::-1].copy()
    assert enc.encode(pos2, rot, root_pos, root_rot, t + 1) == build_frame(names, pos2, rot, root_pos, root_rot,
                                                                          t + 1)


def test_the_encoder_refuses_bad_names_and_shapes() -> None:
    with pytest.raises(ValueError, match="names"):
        VmcEncoder(["Hips", ""])
    enc = VmcEncoder(["Hips", "Spine"])
    with pytest.raises(ValueError, match="2 bones"):
        enc.encode(np.zeros((3, 3)), np.zeros((3, 4)), np.zeros(3), np.array([1.0, 0, 0, 0]), 0.0)
    with pytest.raises(ValueError, match="finite"):
        enc.encode(np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1)), np.zeros(3), np.array([1.0, 0, 0, 0]),
                   float("inf"))
