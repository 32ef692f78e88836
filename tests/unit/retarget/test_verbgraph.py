"""Transitions and the verb graph (Rose 1999, sections 5.2 and 5.5; docs/design/verbs-and-adverbs.md):
duration and end poses, the sigmoid blend, a root that does not swing, eq. 5.2, step-size independence,
adverb changes that never move the root backwards, design-time checks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from capture.errors import RetargetError
from capture.quat import quat_exp, quat_mul
from retarget.adverbs import Example, Verb
from retarget.timeline import sigmoid_blend, yaw_quat
from retarget.verbgraph import BlendedTransition, Transition, VerbGraph

JOINTS = 6


def example(
    point: float,
    speed: float,
    period: float,
    *,
    turn_rate: float = 0.0,
    amp: float = 0.4,
    frames: int = 121,
    keys: tuple[float, ...] = (0.5,),
) -> Example:
    """A motion over ``period`` seconds: the root moves ahead at ``speed`` while turning at ``turn_rate``
    (rad/s, positive = towards +X), and the joints swing once per period."""
    T = np.linspace(0.0, period, frames)
    h = turn_rate * T
    if turn_rate:
        x = speed * (1.0 - np.cos(h)) / turn_rate
        z = speed * np.sin(h) / turn_rate
    else:
        x, z = 0.0 * T, speed * T
    pos = np.stack([x, 0.9 + 0.02 * np.sin(4 * np.pi * T / period), z], axis=1)
    rv = np.zeros((frames, JOINTS, 3))
    rv[:, 1:, 0] = amp * np.sin(2 * np.pi * T[:, None] / period + np.arange(1, JOINTS))
    rot = quat_exp(rv)
    rot[:, 0] = quat_mul(yaw_quat(h), quat_exp(np.stack([0.03 * np.sin(2 * np.pi * T / period), 0 * T, 0 * T], 1)))
    return Example((point,), T, pos, rot, [0.0, *(k * period for k in keys), period])


def walk_verb() -> Verb:
    return Verb([example(0.0, 1.0, 1.2), example(1.0, 2.0, 0.8, amp=0.7)], periodic=True, name="walk")


def idle_verb() -> Verb:
    return Verb([example(0.0, 0.0, 2.0, amp=0.1), example(1.0, 0.05, 2.0, amp=0.15)], periodic=True, name="idle")


def graph(seed: int = 7) -> VerbGraph:
    verbs = {"walk": walk_verb(), "idle": idle_verb()}
    trs = [
        Transition("walk", "walk", 0.9, 1.0, 0.0, 0.1, weight=3.0),
        Transition("walk", "idle", 0.4, 0.6, 0.1, 0.3, weight=1.0),
        Transition("idle", "idle", 0.8, 1.0, 0.0, 0.2, weight=1.0),
        Transition("idle", "walk", 0.5, 0.7, 0.0, 0.2, weight=2.0),
    ]
    return VerbGraph(verbs, trs, seed=seed)


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return 2.0 * np.arccos(np.clip(np.abs(np.sum(a * b, axis=-1)), 0.0, 1.0))


# -- transitions --------------------------------------------------------------------------------


def test_transition_duration_and_end_poses() -> None:
    a = Verb([example(0.0, 1.0, 2.0, keys=()), example(1.0, 1.5, 2.0, keys=())], name="a")
    b = Verb([example(0.0, 0.5, 3.0, keys=(), amp=0.8), example(1.0, 0.7, 3.0, keys=(), amp=0.9)], name="b")
    tr = Transition("a", "b", 0.2, 0.4, 0.2, 0.4)  # 0.4 s of A, 0.6 s of B
    bt = BlendedTransition(tr, a, np.array([0.0]), b, np.array([0.0]))
    assert bt.duration == pytest.approx(0.5)
    assert bt.a_offset == pytest.approx(0.4) and bt.b_offset == pytest.approx(0.6)
    start, end = bt.frame(0.0), bt.frame(bt.duration)
    fa = a.at_time([0.0], 0.4)
    fb = b.at_time([0.0], 0.6 + 0.5)
    np.testing.assert_allclose(angle_between(start.rotations, fa.rotations), 0.0, atol=1e-7)
    np.testing.assert_allclose(angle_between(end.rotations, fb.rotations), 0.0, atol=1e-7)
    assert start.root_pos[1] == pytest.approx(fa.root_pos[1]) and end.root_pos[1] == pytest.approx(fb.root_pos[1])
    np.testing.assert_allclose(start.root_velocity[[0, 2]], fa.root_velocity[[0, 2]], atol=1e-9)
    np.testing.assert_allclose(end.root_velocity[[0, 2]], fb.root_velocity[[0, 2]], atol=1e-9)
    assert bt.frame(0.25).alpha == pytest.approx(0.5)
    assert float(start.alpha) == 0.0 and float(end.alpha) == 1.0
    assert bt.usage_source(0.5) == "a" and bt.usage_source(0.5001) == "b"
    np.testing.assert_allclose(bt.root(0.0)[0], [0.0, 0.0], atol=1e-15)
    # B resumes where the transition leaves it
    assert bt.exit_time_b() == pytest.approx(1.1 / 3.0)


def test_sigmoid_is_the_default_blend() -> None:
    tr = Transition("a", "b", 0.1, 0.2, 0.3, 0.4)
    assert tr.blend is sigmoid_blend and tr.name == "a->b"
    for bad in [(0.2, 0.1, 0.0, 1.0), (0.0, 1.0, -0.1, 0.5), (0.0, 1.2, 0.0, 0.5)]:
        with pytest.raises(ValueError):
            Transition("a", "b", *bad)
    with pytest.raises(ValueError):
        Transition("a", "b", 0.1, 0.2, 0.3, 0.4, weight=-1.0)


def test_root_blended_through_a_turn_does_not_swing() -> None:
    turn = Verb([example(0.0, 1.0, 2.0, turn_rate=1.5, keys=()), example(1.0, 1.0, 2.0, turn_rate=2.0, keys=())])
    straight = Verb([example(0.0, 1.0, 2.0, keys=()), example(1.0, 1.2, 2.0, keys=())])
    tr = Transition("turn", "straight", 0.3, 0.8, 0.1, 0.6, blend=sigmoid_blend)
    p = np.array([0.0])
    bt = BlendedTransition(tr, turn, p, straight, p)
    T = np.linspace(0.0, bt.duration, 400)
    xz, h = bt.root(T)
    # the heading only ever turns one way and settles; the path curves one way only
    assert np.all(np.diff(h) >= -1e-12)
    v = np.diff(xz, axis=0)
    cross = v[:-1, 1] * v[1:, 0] - v[:-1, 0] * v[1:, 1]  # > 0: turning towards +X
    assert np.all(cross >= -1e-12)
    # speed stays that of the two motions (both walk at 1 m/s)
    speed = np.linalg.norm(v, axis=1) / np.diff(T)
    np.testing.assert_allclose(speed, 1.0, atol=5e-3)
    # it never comes back sideways: with heading in [0, pi) the X velocity keeps its sign
    assert np.all(v[:, 0] >= -1e-12) and h[-1] < math.pi
    # blending positions instead (B lined up at A's start by Alg 3.2) swings the path back sideways
    fa = turn.at_time(p, T + bt.a_offset)
    fb = straight.at_time(p, T + bt.b_offset)
    a0 = fa.heading[0]
    pa = fa.root_pos[:, [0, 2]] - fa.root_pos[0, [0, 2]]
    ca, sa = math.cos(-a0), math.sin(-a0)
    pa = np.stack([ca * pa[:, 0] + sa * pa[:, 1], -sa * pa[:, 0] + ca * pa[:, 1]], 1)
    pb = fb.root_pos[:, [0, 2]] - fb.root_pos[0, [0, 2]]
    alpha = sigmoid_blend(T / bt.duration)[:, None]
    naive = (1 - alpha) * pa + alpha * pb
    dx = np.diff(naive[:, 0])
    assert dx.max() > 1e-4 and dx.min() < -1e-4  # out to the side, then back


# -- verb-graph timing --------------------------------------------------------------------------


def test_tau_out_eq_5_2() -> None:
    slow = Verb([example(0.0, 1.0, 2.0, keys=()), example(1.0, 1.0, 2.0, keys=())], periodic=True)
    g = VerbGraph({"slow": slow}, [Transition("slow", "slow", 0.9, 1.0, 0.0, 0.1)])
    actor = g.add_actor("a", "slow", tau=3.0, t_start=0.15)
    assert slow.verb_time([0.5], actor.t_out) == pytest.approx(1.8)
    assert slow.verb_time([0.5], actor.t_in) == pytest.approx(0.3)
    assert g.tau_out(actor) == pytest.approx(4.5)
    g.update("a", 4.49)
    assert actor.front == "slow"
    g.update("a", 4.5)
    assert isinstance(actor.front, Transition) and actor.tau_in == pytest.approx(4.5)


@pytest.mark.parametrize("steps", [1000, 37])
def test_step_size_independence(steps: int) -> None:
    one = graph(seed=11)
    one.add_actor("x", "walk", adverbs={"walk": [0.3], "idle": [0.5]}, heading=0.4, position=(1.0, -2.0))
    many = graph(seed=11)
    many.add_actor("x", "walk", adverbs={"walk": [0.3], "idle": [0.5]}, heading=0.4, position=(1.0, -2.0))
    a = one.update("x", 10.0)
    taus = np.sort(np.random.default_rng(steps).uniform(0.0, 10.0, steps - 1)) if steps != 1000 else None
    grid = np.linspace(0.0, 10.0, 1001)[1:] if taus is None else np.append(taus, 10.0)
    for tau in grid:
        b = many.update("x", float(tau))
    assert b.tau == a.tau == 10.0
    np.testing.assert_allclose(b.root_pos, a.root_pos, atol=1e-9, rtol=0)
    assert b.heading == pytest.approx(a.heading, abs=1e-9)
    np.testing.assert_allclose(b.rotations, a.rotations, atol=1e-9, rtol=0)
    assert list(one.actors["x"].history) == list(many.actors["x"].history)
    assert len(one.actors["x"].history) > 6  # several verbs and transitions were played
    assert {"walk->walk", "walk->idle"} & set(one.actors["x"].history)
    assert np.linalg.norm(a.root_pos - [1.0, a.root_pos[1], -2.0]) > 3.0  # it walked


def test_motion_is_continuous_across_items() -> None:
    g = graph(seed=3)
    g.add_actor("x", "walk", adverbs={"walk": [1.0]})
    dt = 1.0 / 120.0
    prev = g.update("x", 0.0)
    for k in range(1, 1201):
        cur = g.update("x", k * dt)
        step = np.linalg.norm((cur.root_pos - prev.root_pos)[[0, 2]])
        assert step <= 2.2 * dt  # never faster than the fast walk (2 m/s), no jumps at hand-overs
        assert angle_between(cur.rotations, prev.rotations).max() < 0.15
        prev = cur
    assert {"walk->idle", "idle"} <= set(g.actors["x"].history)


# -- changing p ---------------------------------------------------------------------------------


def test_changing_adverbs_never_moves_the_root_backwards() -> None:
    g = VerbGraph({"walk": walk_verb()}, [Transition("walk", "walk", 0.9, 1.0, 0.0, 0.1)])
    eps = 2.0
    actor = g.add_actor("x", "walk", adverbs={"walk": [0.0]}, adverb_rate=eps)
    dt = 1.0 / 60.0
    prev_z, prev_p = g.update("x", 0.0).root_pos[2], 0.0
    for k in range(1, 601):
        if k % 18 == 0:
            g.set_adverbs("x", "walk", [1.0 - round(prev_p)])
        z = g.update("x", k * dt).root_pos[2]
        p = float(actor.adverbs["walk"][0])
        assert abs(p - prev_p) <= eps * dt + 1e-12
        assert z >= prev_z - 1e-12
        prev_z, prev_p = z, p
    assert prev_z > 6.0
    # evaluating the root absolutely under the new p instead would jump back when p drops
    v = walk_verb()
    T = 0.5
    assert v.at_time([0.0], T).root_pos[2] < v.at_time([1.0], T).root_pos[2] - 0.3


def test_request_and_errors() -> None:
    g = graph(seed=1)
    g.add_actor("x", "walk")
    g.update("x", 0.1)
    tr = g.request("x", "idle")
    assert tr.name == "walk->idle"
    for k in range(1, 300):
        g.update("x", 0.1 + k / 60.0)
    hist = list(g.actors["x"].history)
    assert hist[:3] == ["walk", "walk->idle", "idle"]
    with pytest.raises(ValueError):
        g.update("x", 1.0)  # backwards
    with pytest.raises(ValueError):
        g.request("x", "nowhere")
    with pytest.raises(ValueError):
        g.update("nobody", 5.0)
    with pytest.raises(ValueError):
        g.add_actor("x", "walk")
    with pytest.raises(ValueError):
        g.set_adverbs("x", "walk", [0.1, 0.2])
    lone = VerbGraph(
        {"walk": walk_verb(), "idle": idle_verb()}, [Transition("walk", "idle", 0.2, 0.3, 0.0, 0.1, weight=0.0)]
    )
    lone.add_actor("y", "walk")
    lone.update("y", 0.5)  # past the only exit (never taken automatically), no self-transition to loop
    assert lone.actors["y"].front == "walk"
    with pytest.raises(RetargetError):
        lone.request("y", "idle")


def test_design_time_checks() -> None:
    verbs = {"walk": walk_verb(), "idle": idle_verb()}
    with pytest.raises(ValueError, match="after its last exit"):
        VerbGraph(verbs, [Transition("walk", "idle", 0.4, 0.6, 0.5, 0.9),
                          Transition("idle", "walk", 0.5, 0.7, 0.0, 0.2)])
    with pytest.raises(ValueError):
        VerbGraph(verbs, [Transition("walk", "run", 0.4, 0.6, 0.1, 0.3)])
    with pytest.raises(ValueError):
        VerbGraph(verbs, [], start_verbs=["run"])


def test_a_verb_without_exits_holds_its_end() -> None:
    verbs = {"walk": walk_verb(), "idle": idle_verb()}
    g = VerbGraph(verbs, [Transition("walk", "idle", 0.4, 0.6, 0.1, 0.3)])
    g.add_actor("x", "walk")
    last = None
    for tau in (1.0, 5.0, 9.0):
        last_pose = g.update("x", tau)
        if last is not None:
            np.testing.assert_allclose(last_pose.root_pos, last.root_pos, atol=1e-12)
        last = last_pose if tau >= 5.0 else None
    assert g.actors["x"].hold and g.actors["x"].front == "idle"
