"""Skeleton, Clip, forward kinematics, the Bezier spine and BVH reading/writing (the CMU BVH traces are read
in place from ``../shared/traces/d_mocap_cyclic/``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from capture.errors import TraceError
from capture.quat import (
    quat_from_axis_angle,
    quat_to_matrix,
)
from retarget.bvh import (
    CMU_SCALE,
    END_SITE_SUFFIX,
    format_bvh,
    parse_bvh,
    read_bvh,
    write_bvh,
)
from retarget.clips import default_clips
from retarget.skeleton import (
    HUMANOID_JOINTS,
    UNITY_HUMAN_BONES,
    Clip,
    Skeleton,
    bezier_control,
    bezier_spine,
    guess_unity_names,
    humanoid,
)

TRACES = Path(__file__).resolve().parents[3].parent / "shared" / "traces" / "d_mocap_cyclic"
CMU = {"cmu_131_01_start_walk_stop.bvh": 994, "cmu_131_02_start_walk_stop.bvh": 1247}


def cmu_path(name: str) -> Path:
    path = TRACES / name
    if not path.exists():
        pytest.skip(f"CMU BVH not found at {path} (../shared/traces must sit beside the project)")
    return path


def random_quats(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    n = int(np.prod(shape))
    xyzw = Rotation.random(n, random_state=int(rng.integers(1 << 31))).as_quat()
    return np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1).reshape((*shape, 4))


def naive_fk(sk: Skeleton, root: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One frame, joint by joint, with scipy rotation matrices: the reference for Skeleton.fk."""
    n = sk.n_joints
    pos = np.zeros((n, 3))
    world = np.zeros((n, 3, 3))
    for j in range(n):
        local = Rotation.from_quat(q[j][[1, 2, 3, 0]]).as_matrix()
        p = sk.parents[j]
        if p < 0:
            world[j] = local
            pos[j] = root + sk.offsets[j]
        else:
            world[j] = world[p] @ local
            pos[j] = pos[p] + world[p] @ sk.offsets[j]
    return pos, world


def same_rotation(a: np.ndarray, b: np.ndarray, tol: float = 1e-9) -> bool:
    """Quaternions equal up to sign."""
    return bool(np.all(np.abs(np.abs(np.sum(a * b, axis=-1)) - 1.0) < tol))


# --------------------------------------------------------------------------------------------- humanoid


def test_humanoid_has_30_unity_named_joints_and_stands() -> None:
    sk = humanoid()
    assert sk.n_joints == HUMANOID_JOINTS == 30
    assert sk.names[0] == "Hips" and sk.parents[0] == -1
    for name in ("Spine", "Chest", "UpperChest", "Neck", "Head", "LeftShoulder", "RightUpperArm",
                 "LeftLowerArm", "RightHand", "LeftUpperLeg", "RightLowerLeg", "LeftFoot", "RightToes"):
        assert sk.unity_names[name] == name
    assert set(sk.unity_names.values()) <= set(UNITY_HUMAN_BONES)
    rest = sk.rest_positions()
    ground = rest[:, 1].min()
    assert ground == pytest.approx(rest[sk.index("LeftToes"), 1])
    # the hips are 0.56 of the height above the balls of the feet (+1.5 cm), the head joint near 0.91 h
    assert rest[0, 1] - ground == pytest.approx(0.98 - 0.015, abs=1e-9)
    assert rest[sk.index("Head"), 1] - ground + 0.015 == pytest.approx(1.59, abs=1e-9)
    # left is +X (facing +Z, Y up), arms out in a T-pose
    assert rest[sk.index("LeftHand"), 0] > 0.6 > -0.6 > rest[sk.index("RightHand"), 0]
    tall = humanoid(2.0)
    np.testing.assert_allclose(tall.offsets, sk.offsets * 2.0 / 1.75)
    with pytest.raises(ValueError):
        humanoid(0.0)


def test_skeleton_validates_its_arrays() -> None:
    names = ("a", "b", "c")
    off = np.zeros((3, 3))
    Skeleton(names, [-1, 0, 1], off)
    with pytest.raises(ValueError, match="shape"):
        Skeleton(names, [-1, 0], off)
    with pytest.raises(ValueError, match="shape"):
        Skeleton(names, [-1, 0, 1], np.zeros((3, 2)))
    with pytest.raises(ValueError, match="root"):
        Skeleton(names, [0, -1, 1], off)
    with pytest.raises(ValueError, match="parent"):
        Skeleton(names, [-1, 2, 0], off)
    with pytest.raises(ValueError, match="unique"):
        Skeleton(("a", "a", "c"), [-1, 0, 1], off)
    with pytest.raises(ValueError, match="finite"):
        Skeleton(names, [-1, 0, 1], np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match="HumanBodyBones"):
        Skeleton(names, [-1, 0, 1], off, {"a": "Pelvis"})
    with pytest.raises(ValueError, match="unknown"):
        Skeleton(names, [-1, 0, 1], off, {"z": "Hips"})
    with pytest.raises(ValueError, match="same"):
        Skeleton(names, [-1, 0, 1], off, {"a": "Hips", "b": "Hips"})
    sk = Skeleton(names, [-1, 0, 1], off)
    assert sk.children("a") == (1,) and sk.index("c") == 2
    with pytest.raises(ValueError, match="no joint"):
        sk.index("d")
    with pytest.raises(ValueError):  # read-only arrays keep the frozen skeleton frozen
        sk.offsets[0, 0] = 1.0


# ---------------------------------------------------------------------------------------------------- FK


@pytest.mark.parametrize("frames", [1, 3, 40])
def test_fk_matches_a_joint_by_joint_reference(frames: int) -> None:
    """Both FK paths (few frames: 4x4 pointer jumping; many: level by level) against scipy, one frame at a time."""
    rng = np.random.default_rng(frames)
    sk = humanoid()
    q = random_quats(rng, (frames, sk.n_joints))
    root = rng.normal(size=(frames, 3))
    pos, world = sk.fk(root, q, world_rotations=True)
    for f in range(frames):
        ref_pos, ref_world = naive_fk(sk, root[f], q[f])
        np.testing.assert_allclose(pos[f], ref_pos, atol=1e-12)
        np.testing.assert_allclose(quat_to_matrix(world[f]), ref_world, atol=1e-12)
    single = sk.fk(root[0], q[0])
    assert single.shape == (sk.n_joints, 3)
    np.testing.assert_allclose(single, pos[0], atol=1e-12)


def test_fk_identity_is_the_rest_pose_and_shapes_are_checked() -> None:
    sk = humanoid()
    ident = np.tile([1.0, 0, 0, 0], (sk.n_joints, 1))
    np.testing.assert_allclose(sk.fk(np.array([1.0, 2.0, 3.0]), ident), sk.rest_positions() + np.array([1, 2, 3]))
    with pytest.raises(ValueError, match="expected"):
        sk.fk(np.zeros(3), ident[:-1])
    with pytest.raises(ValueError, match="expected"):
        sk.fk(np.zeros((2, 3)), np.stack([ident] * 3))


def test_with_bone_lengths_stretches_named_bones_only() -> None:
    sk = humanoid()
    long_neck = sk.with_bone_lengths({"Head": 1.5})
    rest, new = sk.rest_positions(), long_neck.rest_positions()
    head_bone = np.linalg.norm(sk.offsets[sk.index("Head")])
    assert np.linalg.norm(new[sk.index("Head")] - rest[sk.index("Head")]) == pytest.approx(0.5 * head_bone)
    np.testing.assert_array_equal(new[sk.index("LeftHand")], rest[sk.index("LeftHand")])
    assert long_neck.unity_names == sk.unity_names and long_neck.names == sk.names
    f = np.ones(sk.n_joints)
    f[sk.index("LeftLowerLeg")] = 0.5
    short = sk.with_bone_lengths(f)
    assert short.bone_lengths()[sk.index("LeftLowerLeg")] == pytest.approx(0.5 * 0.43)
    for bad in ({"Head": 0.0}, {"Head": np.inf}, {"Tail": 2.0}, np.ones(3)):
        with pytest.raises(ValueError):
            sk.with_bone_lengths(bad)


# -------------------------------------------------------------------------------------------------- clip


def simple_clip(loop: bool = False) -> Clip:
    sk = Skeleton(("root", "tip"), [-1, 0], [[0, 0, 0], [0, 1, 0]])
    q = np.zeros((3, 2, 4))
    q[..., 0] = 1.0
    q[1, 0] = quat_from_axis_angle([0, 0, 1], np.pi / 2)
    q[2, 0] = quat_from_axis_angle([0, 0, 1], np.pi)
    root = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    return Clip("turn", sk, 10.0, root, q, loop=loop)


def test_clip_samples_by_slerp_and_wraps_loops() -> None:
    clip = simple_clip()
    assert clip.duration == pytest.approx(0.2) and clip.key_times == (0.0, 0.2)
    root, rot = clip.sample(0.05)
    np.testing.assert_allclose(root, [0.5, 0, 0])
    assert same_rotation(rot[0], quat_from_axis_angle([0, 0, 1], np.pi / 4))
    # exact at frame times, held outside a one-shot
    r2, q2 = clip.sample(np.array([0.1, -1.0, 5.0]))
    np.testing.assert_allclose(r2, [[1, 0, 0], [0, 0, 0], [2, 0, 0]])
    assert same_rotation(q2[0], clip.rotations[1]) and same_rotation(q2[2], clip.rotations[2])
    # a loop carries the root on by the cycle displacement
    loop = simple_clip(loop=True)
    r3, _ = loop.sample(0.25)
    np.testing.assert_allclose(r3, [2.5, 0, 0])
    assert loop.root_speed() == pytest.approx(10.0)


def test_clip_validates_shapes_quaternions_and_key_times() -> None:
    c = simple_clip()
    args = (c.name, c.skeleton, c.fps, c.root_pos, c.rotations)
    with pytest.raises(ValueError, match="rotations"):
        Clip(c.name, c.skeleton, c.fps, c.root_pos, c.rotations[:, :1])
    with pytest.raises(ValueError, match="root_pos"):
        Clip(c.name, c.skeleton, c.fps, c.root_pos[:2], c.rotations)
    with pytest.raises(ValueError, match="unit"):
        Clip(c.name, c.skeleton, c.fps, c.root_pos, c.rotations * 2)
    with pytest.raises(ValueError, match="fps"):
        Clip(c.name, c.skeleton, 0.0, c.root_pos, c.rotations)
    with pytest.raises(ValueError, match="key_times"):
        Clip(*args, key_times=(0.0, 0.15, 0.1, 0.2))
    with pytest.raises(ValueError, match="key_times"):
        Clip(*args, key_times=(0.0, 0.1))
    with pytest.raises(ValueError, match="contacts"):
        Clip(*args, contacts={"left_foot": np.ones(2, bool)})
    with pytest.raises(TypeError):
        Clip(c.name, cast("Any", "skeleton"), c.fps, c.root_pos, c.rotations)  # a name, not a Skeleton: refused
    with pytest.raises(ValueError):
        c.root_pos[0, 0] = 3.0


# ------------------------------------------------------------------------------------------ Bezier spine


def test_bezier_spine_spec_item_26() -> None:
    p1 = bezier_control([0, 0, 0], [0, 1, 0], [0, 1, 0])
    np.testing.assert_allclose(p1, [0, 0.5, 0])
    pts = bezier_spine([0, 0, 0], [0, 1, 0], [0, 1, 0], np.linspace(0, 1, 11))
    np.testing.assert_allclose(pts[:, [0, 2]], 0.0, atol=1e-15)  # collinear: a straight spine
    np.testing.assert_allclose(pts[:, 1], np.linspace(0, 1, 11), atol=1e-15)
    np.testing.assert_allclose(bezier_control([0, 0, 0], [0.5, 0.8, 0], [0, 1, 0], b=0.3), [0.175, 0.43, 0])
    ends = bezier_spine([0, 0, 0], [0.5, 0.8, 0], [0, 1, 0], [0.0, 1.0])
    np.testing.assert_allclose(ends, [[0, 0, 0], [0.5, 0.8, 0]])
    with pytest.raises(ValueError):
        bezier_control([0, 0, 0], [0, 1, 0], [0, 1, 0], b=1.5)
    with pytest.raises(ValueError):
        bezier_spine([0, 0, 0], [0, 1, 0], [0, 1, 0], 1.2)


def test_unity_name_guesses_for_foreign_rigs() -> None:
    cmu = guess_unity_names(["Hips", "LHipJoint", "LeftHip", "LeftKnee", "LeftCollar", "LeftShoulder"])
    assert cmu == {"Hips": "Hips", "LeftHip": "LeftUpperLeg", "LeftKnee": "LeftLowerLeg",
                   "LeftCollar": "LeftShoulder", "LeftShoulder": "LeftUpperArm"}
    mixamo = guess_unity_names(["mixamorig:Hips", "mixamorig:Spine1", "mixamorig:LeftUpLeg",
                                "mixamorig:LeftForeArm", "mixamorig:LeftShoulder", "Tail"])
    assert mixamo == {"mixamorig:Hips": "Hips", "mixamorig:Spine1": "Chest",
                      "mixamorig:LeftUpLeg": "LeftUpperLeg", "mixamorig:LeftForeArm": "LeftLowerArm",
                      "mixamorig:LeftShoulder": "LeftShoulder"}


# ---------------------------------------------------------------------------------------------- BVH read


@pytest.mark.parametrize("name", sorted(CMU))
def test_reads_the_cmu_traces(name: str) -> None:
    sk, clip = read_bvh(cmu_path(name), scale=CMU_SCALE)
    assert clip.n_frames == CMU[name]
    assert sk.n_joints == 31 and clip.fps == 120.0
    assert clip.name == Path(name).stem and clip.loop is False
    sk_e, _ = read_bvh(cmu_path(name), scale=CMU_SCALE, end_sites=True)
    assert sk_e.n_joints == 38 and sum(n.endswith(END_SITE_SUFFIX) for n in sk_e.names) == 7
    # the first frame is a standing human: feet below the hips, head above, hips about 0.95 m up
    pos = clip.positions()
    first = pos[0]
    y = {n: first[sk.index(n), 1] for n in ("Hips", "Head", "LeftAnkle", "RightAnkle", "LeftToe", "Neck")}
    assert y["Head"] > y["Neck"] > y["Hips"] > y["LeftAnkle"] and y["Hips"] > y["RightAnkle"]
    assert 0.8 < y["Hips"] - min(y["LeftToe"], y["LeftAnkle"]) < 1.1
    assert 0.3 < y["Head"] - y["Hips"] < 0.7
    # the whole take stays on the floor (within a few cm) and the subject walks somewhere
    assert pos[..., 1].min() > -0.05
    assert np.linalg.norm((clip.root_pos[-1] - clip.root_pos[0])[[0, 2]]) > 1.0
    assert sk.unity_names["LeftKnee"] == "LeftLowerLeg"


def test_cmu_round_trip_write_read() -> None:
    _, clip = read_bvh(cmu_path("cmu_131_01_start_walk_stop.bvh"), scale=CMU_SCALE)
    ref = clip.positions()
    for order in ("ZXY", "ZYX"):
        sk2, back = parse_bvh(format_bvh(clip, scale=CMU_SCALE, order=order), scale=CMU_SCALE)
        assert sk2.names == clip.skeleton.names and back.fps == clip.fps
        np.testing.assert_allclose(sk2.offsets, clip.skeleton.offsets, atol=1e-9)
        assert np.abs(back.positions() - ref).max() < 1e-6
        assert same_rotation(back.rotations, clip.rotations, tol=1e-9)


def test_end_sites_round_trip_as_end_sites(tmp_path: Path) -> None:
    sk, clip = read_bvh(cmu_path("cmu_131_02_start_walk_stop.bvh"), scale=CMU_SCALE, end_sites=True)
    out = tmp_path / "take.bvh"
    write_bvh(out, clip, scale=CMU_SCALE)
    text = out.read_text()
    assert text.count("End Site") == 7 and text.count("JOINT") == 30
    sk2, back = read_bvh(out, scale=CMU_SCALE, end_sites=True)
    assert sk2.names == sk.names
    assert np.abs(back.positions() - clip.positions()).max() < 1e-6


def test_default_clips_round_trip(tmp_path: Path) -> None:
    for name, clip in default_clips().items():
        path = tmp_path / f"{name}.bvh"
        write_bvh(path, clip, scale=0.01)  # centimetres, as most tools expect
        sk, back = read_bvh(path, scale=0.01)
        assert sk.names == clip.skeleton.names and back.n_frames == clip.n_frames and back.fps == 60.0
        assert sk.unity_names == clip.skeleton.unity_names
        assert np.abs(back.positions() - clip.positions()).max() < 1e-6
        assert same_rotation(back.rotations, clip.rotations, tol=1e-9)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), joints=st.integers(1, 12), frames=st.integers(1, 6),
       order=st.sampled_from(["ZXY", "ZYX", "XYZ", "YXZ"]), fps=st.sampled_from([24.0, 30.0, 60.0, 120.0]))
def test_random_rotations_round_trip(seed: int, joints: int, frames: int, order: str, fps: float) -> None:
    rng = np.random.default_rng(seed)
    parents = [-1] + [int(rng.integers(0, j)) for j in range(1, joints)]
    sk = Skeleton(tuple(f"J{j}" for j in range(joints)), parents, rng.normal(scale=0.3, size=(joints, 3)))
    q = random_quats(rng, (frames, joints))
    if frames > 1:  # include gimbal-lock poses: middle angle of the written order at +-90 degrees
        q[1, 0] = Rotation.from_euler(order, [30, 90, -40], degrees=True).as_quat()[[3, 0, 1, 2]]
    clip = Clip("random", sk, fps, rng.normal(size=(frames, 3)), q)
    sk2, back = parse_bvh(format_bvh(clip, order=order))
    # BVH nests joints depth-first, so a tree listed in another parent-first order reads back reordered
    perm = [sk2.index(n) for n in sk.names]
    assert back.fps == fps and sorted(sk2.names) == sorted(sk.names)
    assert [sk2.names[p] if p >= 0 else None for p in sk2.parents[perm]] == \
        [sk.names[p] if p >= 0 else None for p in sk.parents]
    np.testing.assert_allclose(sk2.offsets[perm], sk.offsets, atol=1e-8)
    assert np.abs(back.positions()[:, perm] - clip.positions()).max() < 1e-6
    assert same_rotation(back.rotations[:, perm], clip.rotations, tol=1e-9)


def test_rotation_orders_and_scale_follow_the_file() -> None:
    text = """HIERARCHY
ROOT hip
{
  OFFSET 0 0 0
  CHANNELS 6 Xrotation Yposition Xposition Zposition Yrotation Zrotation
  JOINT knee
  {
    OFFSET 0 -10 0
    CHANNELS 2 Yrotation Xrotation
    End Site
    {
      OFFSET 0 -10 0
    }
  }
}
MOTION
Frames: 1
Frame Time: 0.04
10 100 1 2 20 30 40 50
"""
    sk, clip = parse_bvh(text, scale=0.01, end_sites=True)
    assert sk.names == ("hip", "knee", "knee_end") and clip.fps == 25.0
    np.testing.assert_allclose(clip.root_pos[0], [0.01, 1.0, 0.02])
    expect = Rotation.from_euler("XYZ", [10, 20, 30], degrees=True).as_quat()[[3, 0, 1, 2]]
    assert same_rotation(clip.rotations[0, 0], expect)
    expect = Rotation.from_euler("YX", [40, 50], degrees=True).as_quat()[[3, 0, 1, 2]]
    assert same_rotation(clip.rotations[0, 1], expect)
    np.testing.assert_allclose(sk.offsets[1], [0, -0.1, 0])


# ------------------------------------------------------------------------------------------ BVH errors

GOOD = """HIERARCHY
ROOT Hips
{
\tOFFSET 0 0 0
\tCHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
\tJOINT Leg
\t{
\t\tOFFSET 0 -1 0
\t\tCHANNELS 3 Zrotation Yrotation Xrotation
\t\tEnd Site
\t\t{
\t\t\tOFFSET 0 -1 0
\t\t}
\t}
}
MOTION
Frames: 2
Frame Time: 0.0083333
0 1 0 0 0 0 10 0 0
0 1 1 0 0 0 20 0 0
"""


def mutate(old: str, new: str) -> str:
    assert old in GOOD
    return GOOD.replace(old, new, 1)


@pytest.mark.parametrize(("text", "line", "words"), [
    (mutate("\t{\n\t\tOFFSET 0 -1 0\n\t\tCHANNELS", "\t\tOFFSET 0 -1 0\n\t\tCHANNELS"), 7, "expected '{'"),
    (mutate("\t\t}\n\t}\n}", "\t\t}\n}"), 15, "missing '}'"),
    (mutate("CHANNELS 3 Zrotation Yrotation Xrotation", "CHANNELS 3 Zrotation Yrotation"), 9, "declares 3"),
    (mutate("0 1 1 0 0 0 20 0 0", "0 1 1 0 0 0 20 0"), 20, "has 8 values"),
    (mutate("0 1 1 0 0 0 20 0 0", "0 1 1 0 0 x 20 0 0"), 20, "non-numeric"),
    (mutate("Frames: 2", "Frames: 3"), 17, "only 2 frame lines"),
    (mutate("Frames: 2", "Frames: 1"), 20, "more frame lines"),
    (mutate("Frames: 2", "Frames: two"), 17, "whole number"),
    (mutate("Frame Time: 0.0083333", "Frame Time: 0"), 18, "frame time"),
    (mutate("OFFSET 0 -1 0\n\t\tCHANNELS", "OFFSET 0 -one 0\n\t\tCHANNELS"), 8, "non-numeric"),
    (mutate("CHANNELS 3 Zrotation Yrotation Xrotation", "CHANNELS 6 Xposition Yposition Zposition "
            "Zrotation Yrotation Xrotation"), 9, "only the root"),
    (mutate("CHANNELS 3 Zrotation Yrotation Xrotation", "CHANNELS 3 Zrotation Zrotation Xrotation"), 9,
     "repeats"),
    (mutate("\t\tEnd Site", "\t\tEnd Sight"), 10, "'Site'"),
    (mutate("HIERARCHY", "HIERARCHIES"), 1, "expected HIERARCHY"),
    (mutate("MOTION\n", "MOVEMENT\n"), 16, "unexpected 'MOVEMENT'"),
    (GOOD.split("MOTION", maxsplit=1)[0], 15, "no MOTION"),
    ("", 1, "empty"),
])
def test_malformed_bvh_raises_a_one_line_trace_error(text: str, line: int, words: str) -> None:
    with pytest.raises(TraceError) as info:
        parse_bvh(text, path="take.bvh")
    err = info.value
    assert err.line == line and err.path == "take.bvh"
    assert words in str(err) and "\n" not in str(err)
    assert str(err).startswith(f"take.bvh:{line}: ")


def test_the_good_bvh_parses_and_a_binary_file_is_a_trace_error(tmp_path: Path) -> None:
    sk, clip = parse_bvh(GOOD)
    assert sk.names == ("Hips", "Leg") and clip.n_frames == 2 and clip.fps == 120.0
    path = tmp_path / "noise.bvh"
    path.write_bytes(b"\xff\xfe\x00HIERARCHY\x80")
    with pytest.raises(TraceError, match="not a text file"):
        read_bvh(path)
    with pytest.raises(ValueError, match="scale"):
        parse_bvh(GOOD, scale=0.0)


def test_format_bvh_refuses_bad_arguments() -> None:
    clip = simple_clip()
    with pytest.raises(ValueError, match="order"):
        format_bvh(clip, order="ZZY")
    with pytest.raises(ValueError, match="scale"):
        format_bvh(clip, scale=-1.0)
    sk = Skeleton(("root", "a tip"), [-1, 0], [[0, 0, 0], [0, 1, 0]])
    with pytest.raises(ValueError, match="cannot be written"):
        format_bvh(Clip("x", sk, 10.0, clip.root_pos, clip.rotations))
