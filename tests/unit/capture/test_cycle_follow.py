"""CycleFollower: streaming cycle extraction on the live bus, fed by a real (simulated) device through
its codec, clock sync and reader thread."""

from __future__ import annotations

from typing import TYPE_CHECKING

from capture.app.cycle_follow import CycleFollower
from capture.app.orchestrator import Capture
from sim_devices.motion import WavingMotion

if TYPE_CHECKING:
    from cycles import Cycle


def test_follower_reports_improving_cycles_from_a_looping_imu() -> None:
    got: list[Cycle] = []
    cap = Capture(["w=synth://imu?rate=200&seed=4&loop_s=1.0&realtime=false&duration=8"])
    follower = CycleFollower("w/imu", got.append, columns=[0, 1, 2, 3, 4, 5], every_s=0.5)
    cap.subscribe(follower, name="cycles")
    report = cap.run(None)
    assert report.streams["w/imu"]["samples"] > 1500
    assert got, follower.extractor.last_error
    assert follower.updates == len(got) and follower.errors == 0
    assert got[0].loops >= 2
    assert got[-1].loops >= got[0].loops
    best = follower.best
    assert best is got[-1]
    truth = WavingMotion(4, loop_s=1.0).mean_loop_s(0.0, 8.0)
    assert abs(best.period_s / truth - 1) < 0.02
    assert best.channels == ("c0", "c1", "c2", "c3", "c4", "c5")


def test_follower_ignores_other_streams_and_is_quiet_without_loops() -> None:
    got: list[Cycle] = []
    cap = Capture(["a=synth://imu?rate=100&seed=1&realtime=false&duration=3",
                   "b=synth://imu?rate=100&seed=2&realtime=false&duration=3&loop_s=0.8"])
    follower = CycleFollower("a/imu", got.append, columns=[3, 4, 5])
    cap.subscribe(follower, name="cycles")
    cap.run(None)
    # a waves freely (no loops): nothing reported, the reason kept
    assert got == [] and follower.best is None
    assert follower.extractor.attempts > 0 and follower.extractor.last_error
