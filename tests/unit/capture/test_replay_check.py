"""``ReplayVerifier`` on families of damaged recordings, built as arrays so that the truth is known
exactly: recorded blocks lost (head, middle, tail), raw data lost (the replay passes over readings,
may number the rest afresh and stamp them afresh, a wrapping device clock unwrapped differently),
readings without a device clock, readings that repeat, and replays split into random batches.
Every lost, missing and not-recorded reading must be counted as such, every surviving one compared
and equal; a replay that really differs must still be a mismatch."""

from __future__ import annotations

import random

import numpy as np
import pytest

from capture.app.replay_check import Expected, ReplayVerifier, describe_verification, expected_from_summary
from capture.sample import NO_TIME, Sample, SampleBatch

PERIOD = 5_000_000


def _take(rng: random.Random, n: int, clock: bool, constant: bool = False) -> SampleBatch:
    seq = np.arange(n, dtype=np.int64)
    host = 1_000_000_000 + seq * PERIOD // 4 * 4   # several readings may share a chunk's host time
    host = host - host % (4 * PERIOD) if rng.random() < 0.5 else host
    dev = (7_000_000 + seq * PERIOD) if clock else np.full(n, NO_TIME, np.int64)
    vals = (np.zeros((n, 3)) if constant else
            np.random.default_rng(rng.randrange(1 << 30)).normal(size=(n, 3)).round(6))
    return SampleBatch("d/imu", seq, host.astype(np.int64), dev.astype(np.int64), host.astype(np.int64) + 11, vals)


def _sub(b: SampleBatch, keep: np.ndarray) -> SampleBatch:
    return SampleBatch(b.stream, b.seq[keep], b.t_host_ns[keep], b.t_device_ns[keep], b.t_bus_ns[keep], b.values[keep])


def _feed(v: ReplayVerifier, b: SampleBatch, rng: random.Random) -> None:
    """The replay in random batches, some of them single ``Sample`` items."""
    i = 0
    while i < len(b):
        n = rng.choice((1, 2, rng.randrange(1, 400)))
        part = _sub(b, np.arange(i, min(i + n, len(b))))
        if len(part) == 1 and rng.random() < 0.5:
            v.on_item(next(part.samples()))
        else:
            v.on_item(part)
        i += n


def _runs(rng: random.Random, n: int, k: int) -> np.ndarray:
    """A mask of up to ``k`` random runs over ``n`` readings (sometimes at the very head or tail)."""
    m = np.zeros(n, bool)
    for _ in range(rng.randrange(k + 1)):
        w = rng.randrange(1, max(2, n // 6))
        at = rng.choice((0, n - w, rng.randrange(max(1, n - w))))
        m[max(at, 0):at + w] = True
    return m


CASES = 400


@pytest.mark.parametrize("seed", range(CASES))
def test_damage_is_counted_and_the_rest_compared(seed: int) -> None:
    rng = random.Random(seed)
    n = rng.randrange(5, 900)
    clock = rng.random() < 0.75
    pristine = _take(rng, n, clock)
    lost = _runs(rng, n, 3)                  # recorded blocks lost to the damage
    raw_lost = _runs(rng, n, 2) if rng.random() < 0.6 else np.zeros(n, bool)
    recorded = _sub(pristine, ~lost)
    summary = rng.random() < 0.8            # the summary survived
    exp = {"d/imu": Expected(n, 0, n - 1)} if summary else None
    # the replay: readings whose raw data survived; after the first raw hole its numbering may start
    # afresh (renumbered) and its stamps differ (re-stamped); a wrapping clock may unwrap differently
    rep = _sub(pristine, ~raw_lost)
    hole = np.flatnonzero(raw_lost)
    after = np.zeros(len(rep), bool)
    if hole.size:
        after = rep.seq > hole[0]
        if not clock or rng.random() < 0.5:   # without a device clock no gap is inferred: always
            rep.seq[after] -= int(raw_lost.sum())
        if rng.random() < 0.5:
            rep.t_bus_ns[after] += rng.randrange(1, 30_000_000)
            rep.t_host_ns[after] += rng.choice((0, PERIOD))
        if clock and rng.random() < 0.3:
            rep.t_device_ns[after] -= 86_400_000_000_000
    v = ReplayVerifier({"d/imu": recorded}, expected=exp)
    _feed(v, rep, rng)
    res = v.result()
    s = res["streams"]["d/imu"]
    survived = ~lost
    replayed = ~raw_lost
    truth_lost = int(lost.sum())
    if summary:
        assert s["lost"] == truth_lost and s["lost_exact"]
        covered = sum(r["seq"][1] - r["seq"][0] + 1 for r in s["lost_ranges"])
        assert covered == truth_lost or len(s["lost_ranges"]) == ReplayVerifier.MAX_RANGES
    else:
        assert s["lost"] <= truth_lost and not s["lost_exact"]
    assert s["mismatches"] == 0, res["first_mismatch"]
    assert s["missing"] == int((survived & ~replayed).sum())
    assert s["compared"] == int((survived & replayed).sum())
    # a replayed reading whose recorded block is lost is "not recorded", except past the last surviving
    # reading of a take without a summary (a cut-short file's raw data outlives its sample blocks)
    pos = np.arange(n)
    within = pos <= (n - 1 if summary else (pos[survived].max() if survived.any() else -1))
    want_nr = int((lost & replayed & within).sum())
    # without a device clock the renumbered readings are recognised by their values where they are unique
    assert s["not_recorded"] == want_nr, (s, want_nr)
    if truth_lost == 0 and not raw_lost.any():
        assert res["equal"]
    if summary and (truth_lost or (survived & raw_lost).any()):
        assert not res["equal"]   # without the session's damage flag, damage is never "equal"
    describe_verification({**res, "damaged": {"x": 1}})


def test_a_replay_that_differs_is_a_mismatch_even_after_damage() -> None:
    rng = random.Random(3)
    rec = _take(rng, 300, True)
    exp = {"d/imu": Expected(300, 0, 299)}
    for at in (0, 150, 299):
        rep = _sub(rec, np.arange(300))
        rep.values[at, 1] += 1e-3
        v = ReplayVerifier({"d/imu": _sub(rec, np.arange(300) != 40)}, expected=exp)  # one block lost
        v.on_item(rep)
        res = v.result()
        assert res["streams"]["d/imu"]["mismatches"] == 1 and not res["equal"], at
    # a device time that differs before any raw data was lost is a mismatch, not a re-stamp
    rep = _sub(rec, np.arange(300))
    rep.t_device_ns[10] += 1
    v = ReplayVerifier({"d/imu": rec}, expected=exp)
    v.on_item(rep)
    assert v.result()["streams"]["d/imu"]["mismatches"] == 1


def test_readings_that_repeat_are_matched_on_their_numbers() -> None:
    rng = random.Random(5)
    rec = _take(rng, 200, False, constant=True)   # no device clock, every value the same
    v = ReplayVerifier({"d/imu": rec}, expected={"d/imu": Expected(200, 0, 199)})
    _feed(v, rec, rng)
    res = v.result()
    assert res["equal"] and res["streams"]["d/imu"]["compared"] == 200


def test_a_failed_check_is_not_verified() -> None:
    rng = random.Random(7)
    rec = _take(rng, 50, True)
    v = ReplayVerifier({"d/imu": rec})
    v.on_error(ValueError("boom"))
    v.on_item(rec)
    res = v.result()
    assert not res["equal"] and res["check_errors"] == 1
    assert any("NOT VERIFIED" in line and "boom" in line for line in describe_verification(res))


def test_the_summary_says_what_each_stream_held() -> None:
    exp = expected_from_summary({"samples": {"a": 10, "b": -1, "c": "x"}, "seq": {"a": [3, 12], "b": [1]}})
    assert exp["a"] == Expected(10, 3, 12)
    assert exp["b"] == Expected(None, None, None) and exp["c"] == Expected(None, None, None)
    assert expected_from_summary(None) == {} and expected_from_summary({"samples": 3}) == {}
    # a stream the summary does not list had no readings: a replayed one is "not recorded"
    rec = SampleBatch("d/x", np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64),
                      np.zeros(0, np.int64), np.zeros((0, 3)))
    v = ReplayVerifier({"d/x": rec}, expected={"other": Expected(5, 0, 4)})
    v.on_item(Sample("d/x", 0, 1, 2, 3, (1.0, 2.0, 3.0)))
    s = v.result()["streams"]["d/x"]
    assert s["lost"] == 0 and s["lost_exact"] and s["not_recorded"] == 0
