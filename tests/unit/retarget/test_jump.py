"""Jump parabola and invalid-jump rules (Ciccone 2019, section 6.3, eq. 6.3 as perfcap corrects it; see
docs/design/puppet.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from retarget.jump import (
    InvalidJump,
    JumpConfig,
    JumpPhase,
    JumpTracker,
    Parabola,
    fit_arc,
    fit_parabola,
)

G = 9.81
FS = 120.0


def thesis_b(x0, y0, xt, yt, slope):
    """Eq. 6.3's b as printed in the thesis (with the wrong sign on 2 xt (yt - y0))."""
    return (slope * (x0**2 - xt**2) - 2 * xt * (yt - y0)) / (xt - x0) ** 2


def test_parabola_numbers():
    p = fit_parabola(0.0, 0.0, 1.0, 1.0, 0.0)
    assert (p.a, p.b, p.c) == pytest.approx((-1.0, 2.0, 0.0), abs=1e-12)
    assert p.apex == pytest.approx((1.0, 1.0), abs=1e-12)
    q = fit_parabola(1.0, 0.0, 2.0, 3.0, 2.0)
    assert (q.a, q.b, q.c) == pytest.approx((-1.0, 6.0, -5.0), abs=1e-12)
    assert q.apex == pytest.approx((3.0, 4.0), abs=1e-12)
    assert thesis_b(1.0, 0.0, 2.0, 3.0, 2.0) == pytest.approx(-18.0)
    assert q.b != pytest.approx(-18.0)


def test_parabola_interpolates_its_constraints():
    rng = np.random.default_rng(11)
    for x0, y0, xt, yt, s in rng.normal(0, 2, (200, 5)):
        if abs(xt - x0) < 1e-3:
            continue
        p = fit_parabola(x0, y0, xt, yt, s)
        assert p(x0) == pytest.approx(y0, abs=1e-7)
        assert p(xt) == pytest.approx(yt, abs=1e-7)
        assert p.slope(xt) == pytest.approx(s, abs=1e-7)
        # c = y0 - a x0^2 - b x0 expanded over the common denominator
        c_expanded = (xt**2 * y0 + x0**2 * yt - 2 * x0 * xt * yt + s * x0 * xt * (xt - x0)) / (xt - x0) ** 2
        assert p.c == pytest.approx(c_expanded, abs=1e-7)


def test_apex_only_for_downward_parabolas_and_degenerate_fit():
    assert Parabola(1.0, 0.0, 0.0).apex is None
    assert Parabola(0.0, 1.0, 0.0).apex is None
    with pytest.raises(ValueError, match="xt != x0"):
        fit_parabola(1.0, 0.0, 1.0, 1.0, 0.0)
    with pytest.raises(ValueError, match="finite"):
        fit_parabola(0.0, 0.0, 1.0, math.nan, 0.0)


def test_fit_arc_distance_and_vertical_time_fallback():
    vx, vy = 1.5, 3.0
    tau = 0.25
    arc = fit_arc(dt=tau, dx=vx * tau, dy=vy * tau - G / 2 * tau**2, vx=vx, vy=vy - G * tau)
    assert arc is not None and arc.parameter == "distance"
    assert arc.parabola.a == pytest.approx(-G / (2 * vx**2))
    assert arc.apex == pytest.approx((vx * vy / G, vy**2 / (2 * G)))
    # Nearly vertical (1 cm sideways): time parameterisation, y(t) with a = -g/2.
    vert = fit_arc(dt=tau, dx=0.01, dy=vy * tau - G / 2 * tau**2, vx=0.04, vy=vy - G * tau)
    assert vert is not None and vert.parameter == "time"
    assert vert.parabola.a == pytest.approx(-G / 2)
    assert vert.apex == pytest.approx((vy / G, vy**2 / (2 * G)))
    assert fit_arc(dt=0.0, dx=0.0, dy=0.0, vx=0.0, vy=3.0) is None


def ballistic(vh, vy0, duration, *, heading=0.0, turn_rate=0.0, start=(0.0, 0.0, 0.0)):
    """Frames (t, pos, vel, facing) of a ballistic arc along a heading that may turn at turn_rate."""
    out = []
    x, z = start[0], start[2]
    for k in range(round(duration * FS) + 1):
        t = k / FS
        h = heading + turn_rate * t
        y = start[1] + vy0 * t - G / 2 * t * t
        vel = (vh * math.sin(h), vy0 - G * t, vh * math.cos(h))
        out.append((t, (x, y, z), vel, heading))
        x += vel[0] / FS
        z += vel[2] / FS
    return out


def run_tracker(frames, takeoff=0.2, config=None):
    t0, p0, v0, h0 = frames[0]
    tr = JumpTracker(t0, p0, v0, h0, config)
    for t, p, v, h in frames[1:]:
        if tr.takeoff_time is None and t >= t0 + takeoff - 1e-9:
            tr.takeoff(t0 + takeoff)
        tr.update(t, p, v, h, max(0.0, p[1]))
    return tr


def test_clean_arc_stays_valid():
    frames = ballistic(1.2, 3.0, 0.6)
    tr = run_tracker(frames)
    assert tr.valid and tr.phase is JumpPhase.DESCENDING
    assert tr.arc is not None and tr.arc.apex is not None
    assert tr.arc.apex[1] == pytest.approx(3.0**2 / (2 * G), abs=0.01)
    # Vertical jump: valid too, on the time parameterisation.
    vertical = run_tracker(ballistic(0.0, 3.0, 0.6))
    assert vertical.valid and vertical.arc is not None and vertical.arc.parameter == "time"


def test_rise_fall_rise_is_invalid():
    frames = ballistic(1.0, 3.0, 0.4)  # past the apex at 0.306 s
    t_end, p_end, _, _ = frames[-1]
    frames += [(t_end + k / FS, (p_end[0], p_end[1] + 0.02 * k, p_end[2]), (0.0, 1.2, 1.0), 0.0)
               for k in range(1, 10)]
    tr = run_tracker(frames)
    assert tr.invalid is InvalidJump.RE_RISE


def test_velocity_jitter_at_the_apex_is_not_a_second_rise():
    rng = np.random.default_rng(2)
    tr = JumpTracker(0.0, (0, 0, 0), (0.0, 2.0, 1.0), 0.0)  # travelling along +Z
    tr.takeoff(0.2)
    t = 0.0
    for vy in [2.0, 1.0, 0.3, -0.06, *list(rng.uniform(-0.049, 0.049, 30)), -0.5, -1.5]:
        t += 1 / FS
        tr.update(t, (0.0, 0.3, t), (0.0, vy, 1.0), 0.0, 0.3)
    # It descended, then jittered within +-0.05 m/s: no second apex.
    assert tr.phase is JumpPhase.DESCENDING
    assert tr.invalid is None


@pytest.mark.parametrize("kind", ["travel", "facing"])
def test_45_degree_turn_in_the_air_is_invalid(kind):
    if kind == "travel":
        frames = ballistic(1.5, 3.0, 0.5, turn_rate=math.radians(45) / 0.5)
    else:
        frames = [(t, p, v, math.radians(90) * t) for t, p, v, _ in ballistic(1.5, 3.0, 0.5)]
    tr = run_tracker(frames, takeoff=0.0)  # in the air from the first frame: no anticipation
    assert tr.invalid is InvalidJump.TURN
    assert tr.invalid_time is not None
    # It fired when the change passed 30 degrees, not before.
    rate = math.radians(45) / 0.5 if kind == "travel" else math.radians(90)
    assert tr.invalid_time == pytest.approx(math.radians(30) / rate, abs=1.5 / FS)


def test_turn_below_30_degrees_is_fine():
    tr = run_tracker(ballistic(1.5, 3.0, 0.5, turn_rate=math.radians(25) / 0.5), takeoff=0.0)
    assert tr.valid


@pytest.mark.parametrize("seed", range(12))
def test_a_turn_on_the_ground_before_the_takeoff_is_no_turn_in_the_air(seed):
    """During the anticipation the character turns (any amount) to face its travel; from the takeoff it flies
    straight: valid. The same turn after the takeoff is invalid."""
    rng = np.random.default_rng(seed)
    turn = math.radians(float(rng.uniform(45, 180))) * float(rng.choice([-1.0, 1.0]))
    travel = float(rng.uniform(-math.pi, math.pi))
    ground = [(k / FS, (0.0, 0.0, 0.0), (1.2 * math.sin(travel), 0.0, 1.2 * math.cos(travel)),
               travel - turn + turn * min(1.0, k / (0.15 * FS))) for k in range(round(0.2 * FS))]
    air = [(0.2 + t, p, v, travel) for t, p, v, _ in ballistic(1.2, 3.0, 0.5, heading=travel)][1:]
    assert run_tracker([*ground, *air], takeoff=0.2).valid
    late = [(t, p, v, h + (turn if t > 0.35 else 0.0)) for t, p, v, h in [*ground, *air]]
    late_tr = run_tracker(late, takeoff=0.2)
    assert late_tr.invalid is InvalidJump.TURN and late_tr.invalid_time > 0.35


def test_hover_is_invalid_after_015_s():
    frames = ballistic(0.0, 2.0, 2.0 / G)  # up to the apex, about 0.204 s
    t_end, p_end, _, _ = frames[-1]
    frames += [(t_end + k / FS, p_end, (0.0, 0.0, 0.0), 0.0) for k in range(1, int(0.3 * FS) + 1)]
    tr = run_tracker(frames)
    assert tr.invalid is InvalidJump.STOP
    slow_since = next(t for t, _, v, _ in frames if math.hypot(*v) < 0.1)  # just before the apex
    assert tr.invalid_time is not None
    assert 0.15 < tr.invalid_time - slow_since <= 0.15 + 1.5 / FS


def test_no_apex_allowed_only_in_the_first_01_s_after_takeoff():
    # A steady straight lift at 1.5 m/s: a = 0 all along.
    frames = [(k / FS, (0.0, 1.5 * k / FS, 0.5 * k / FS), (0.0, 1.5, 0.5), 0.0) for k in range(int(0.5 * FS))]
    tr = run_tracker(frames, takeoff=0.2)
    assert tr.invalid is InvalidJump.NO_APEX
    assert tr.invalid_time is not None and 0.3 < tr.invalid_time <= 0.3 + 1.5 / FS


def test_airborne_too_long_is_invalid():
    # Glide level at constant height after rising: none of the three rules fires, but it is no jump.
    frames = ballistic(1.0, 2.0, 2.0 / G)
    t_end, p_end, _, _ = frames[-1]
    frames += [(t_end + k / FS, (p_end[0], p_end[1], p_end[2] + k / FS), (0.0, 0.0, 1.0), 0.0)
               for k in range(1, int(2.0 * FS))]
    assert run_tracker(frames).invalid is InvalidJump.TOO_LONG


def test_tracker_errors():
    tr = JumpTracker(1.0, (0, 0, 0), (0, 2, 0), 0.0)
    with pytest.raises(ValueError, match="before the trigger"):
        tr.takeoff(0.5)
    tr.update(1.1, (0, 0.1, 0), (0, 1, 0), 0.0, 0.1)
    with pytest.raises(ValueError, match="backwards"):
        tr.update(1.05, (0, 0.1, 0), (0, 1, 0), 0.0, 0.1)
    with pytest.raises(ValueError, match="3-vector"):
        tr.update(1.2, (0, 0.1), (0, 1, 0), 0.0, 0.1)
    with pytest.raises(ValueError, match="JumpConfig"):
        JumpConfig(stop_time=-1.0)
