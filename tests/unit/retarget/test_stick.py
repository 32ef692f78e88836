"""MotionStick (Ciccone 2019, section 6.2.1; docs/design/puppet.md): the grabbed object keeps its distance and
rotation relative to the phone, and the stick shortens against the floor and grows back."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retarget.stick import (
    MotionStick,
    Plane,
    heading_of,
    invert_transform,
    make_transform,
    pose_matrix,
    yaw_matrix,
)


def phone_at(position, yaw=0.0, pitch=0.0, roll=0.0) -> np.ndarray:
    """A phone pose: yaw about +Y, then pitch about its X, then roll about its Z (intrinsic)."""
    rot = Rotation.from_euler("YXZ", [yaw, pitch, roll]).as_matrix()
    return make_transform(rot, position)


def test_rotate_phone_about_its_vertical_axis_keeps_distance_and_relative_pose():
    # Phone 1.2 m up, pitched down 40 degrees; the object 1.5 m away, also rotated.
    phone = phone_at((0.3, 1.2, -0.4), yaw=0.2, pitch=math.radians(40))
    obj = make_transform(Rotation.from_euler("Y", 1.1).as_matrix(),
                         phone[:3, 3] + phone[:3, :3] @ np.array([0.0, 0.0, 1.5]))
    stick = MotionStick(ground_height=-10.0)  # floor far away: no collision in this test
    stick.grab(phone, obj)
    assert stick.rest_length == pytest.approx(1.5, abs=1e-12)
    rel0 = stick.relative
    # Rotate the phone 30 degrees about its own vertical (local Y) axis.
    turned = phone @ make_transform(Rotation.from_euler("Y", math.radians(30)).as_matrix(), (0, 0, 0))
    target = stick.update(turned)
    assert np.linalg.norm(target.pose[:3, 3] - turned[:3, 3]) == pytest.approx(1.5, abs=1e-12)
    np.testing.assert_allclose(invert_transform(turned) @ target.pose, rel0, atol=1e-12)
    assert not target.shortened and target.length == pytest.approx(1.5)
    # The object really moved (it swung round with the phone).
    assert np.linalg.norm(target.pose[:3, 3] - obj[:3, 3]) > 0.5


def test_pushed_below_the_floor_stops_on_it_and_recovers():
    phone = phone_at((0.0, 1.0, 0.0))
    obj = make_transform(np.eye(3), (0.0, 1.0, 1.5))  # straight ahead, 1.5 m
    stick = MotionStick()  # ground y = 0
    stick.grab(phone, obj)
    l0 = stick.rest_length
    # Pitch the phone down until the free stick end would be 0.2 m below the floor.
    pitch = math.asin(1.2 / 1.5)
    down = phone_at((0.0, 1.0, 0.0), pitch=pitch)
    free_end = down[:3, 3] + down[:3, :3] @ np.array([0.0, 0.0, 1.5])
    assert free_end[1] == pytest.approx(-0.2, abs=1e-12)
    target = stick.update(down)
    end = target.pose[:3, 3]
    assert end[1] == pytest.approx(0.0, abs=1e-6)
    assert target.shortened and target.length < l0
    direction_free = (free_end - down[:3, 3]) / np.linalg.norm(free_end - down[:3, 3])
    direction_now = (end - down[:3, 3]) / np.linalg.norm(end - down[:3, 3])
    np.testing.assert_allclose(direction_now, direction_free, atol=1e-12)
    assert target.length == pytest.approx(1.0 / math.sin(pitch), abs=1e-9)  # the ray hits y=0 there
    # Lift again: the stick is back to L0.
    up = stick.update(phone_at((0.0, 1.0, 0.0), pitch=math.radians(10)))
    assert up.length == pytest.approx(l0) and not up.shortened
    assert np.linalg.norm(up.pose[:3, 3] - np.array([0.0, 1.0, 0.0])) == pytest.approx(l0)


def test_clearance_keeps_the_lowest_point_on_the_floor_for_an_oblique_stick():
    stick = MotionStick(clearance=0.1)
    phone = phone_at((0.0, 1.0, 0.0))
    stick.grab(phone, make_transform(np.eye(3), (0.0, 1.0, 2.0)))
    target = stick.update(phone_at((0.0, 1.0, 0.0), pitch=math.radians(60)))
    assert target.pose[1, 3] == pytest.approx(0.1, abs=1e-9)  # origin 0.1 above the floor, bottom on it


def test_extra_plane_wall_shortens_the_stick():
    wall = Plane((0.0, 0.0, -1.0), -1.0)  # the wall z = 1, free side z < 1
    stick = MotionStick(planes=(wall,))
    phone = phone_at((0.0, 1.0, 0.0))
    stick.grab(phone, make_transform(np.eye(3), (0.0, 1.0, -1.5)))  # behind the phone
    turned = phone_at((0.0, 1.0, 0.0), yaw=math.pi)  # now the object points at the wall
    target = stick.update(turned)
    assert target.pose[2, 3] == pytest.approx(1.0, abs=1e-9)
    assert target.length == pytest.approx(1.0)


def test_grounded_applies_only_the_yaw():
    stick = MotionStick(ground_height=-10.0)
    phone = phone_at((0.0, 1.0, 0.0))
    stick.grab(phone, make_transform(np.eye(3), (0.0, 1.0, 1.0)))
    tilted = phone_at((0.0, 1.0, 0.0), yaw=0.7, pitch=0.4, roll=0.3)
    target = stick.update(tilted, grounded=True)
    np.testing.assert_allclose(target.pose[:3, 1], (0.0, 1.0, 0.0), atol=1e-12)  # stays upright
    full_forward = target.full_pose[:3, 2]
    assert target.heading == pytest.approx(math.atan2(full_forward[0], full_forward[2]))
    np.testing.assert_allclose(target.pose[:3, :3], yaw_matrix(target.heading), atol=1e-12)
    np.testing.assert_allclose(target.pose[:3, 3], target.full_pose[:3, 3])
    # Not grounded: the full rotation.
    np.testing.assert_allclose(stick.update(tilted).pose, target.full_pose, atol=1e-12)


def test_heading_convention_and_vertical_forward_fallback():
    assert heading_of(yaw_matrix(0.5)) == pytest.approx(0.5)
    np.testing.assert_allclose(yaw_matrix(math.pi / 2) @ (0, 0, 1), (1, 0, 0), atol=1e-12)
    # Forward axis straight down: the twist about Y is used.
    look_down = Rotation.from_euler("YX", [0.8, math.pi / 2]).as_matrix()
    assert heading_of(look_down) == pytest.approx(0.8, abs=1e-9)


def test_pose_matrix_scalar_first_quaternion():
    half = math.radians(90) / 2
    m = pose_matrix((1.0, 2.0, 3.0), (math.cos(half), 0.0, math.sin(half), 0.0))  # 90 deg about +Y
    np.testing.assert_allclose(m[:3, :3] @ (0, 0, 1), (1, 0, 0), atol=1e-12)
    np.testing.assert_allclose(m[:3, 3], (1, 2, 3))


def test_release_and_errors():
    stick = MotionStick()
    with pytest.raises(ValueError, match="holds nothing"):
        stick.update(np.eye(4))
    stick.grab(np.eye(4), make_transform(np.eye(3), (0, 0, 1)))
    assert stick.held
    stick.release()
    assert not stick.held and stick.rest_length == 0.0
    with pytest.raises(ValueError, match="4x4"):
        stick.grab(np.eye(3), np.eye(4))
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValueError, match="rotation"):
        stick.grab(bad, np.eye(4))
    with pytest.raises(ValueError, match="clearance"):
        MotionStick(clearance=-1.0)
    with pytest.raises(ValueError, match="normal"):
        Plane((0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="quaternion"):
        pose_matrix((0, 0, 0), (0, 0, 0, 0))


def test_zero_length_stick_follows_the_phone():
    stick = MotionStick()
    phone = phone_at((0.0, 1.0, 0.0))
    stick.grab(phone, phone)
    moved = phone_at((0.5, 1.2, 0.1), yaw=0.3)
    np.testing.assert_allclose(stick.update(moved).pose, moved, atol=1e-12)
