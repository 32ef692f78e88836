"""Event-driven streams (mice, pens, touch surfaces: no device clock, no fixed rate) are stamped at
their reports' arrivals, dejittered only inside runs of regular arrivals, never on a counter grid:
on every real hid-recorder and evemu trace each reading's bus time is its report's recorded time
(the arrival, in these recordings) to within the dejittering, with no fitted drift and no clock
reset; with link latency and jitter it lies within the jitter of the report's true time. Seeded
sweeps of irregular and polled arrivals hold the stamping rule, the dejittering and the equality of
the per-chunk and vectorised paths."""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import pytest

from capture.app.orchestrator import Capture
from capture.clocksync import EVENT_DEJITTER_MAX_NS, ClockSync
from capture.session import SessionReader
from capture.summary import summarize
from devices import open_device

TRACES = Path(__file__).resolve().parents[3].parent / "shared" / "traces"

HID = sorted((TRACES / "b_hid" / "hid_recorder").glob("*.hid"))
EVEMU = sorted(TRACES.rglob("*.events"))


def _profile(path: Path) -> str | None:
    n = path.name
    return "mouse" if "mouse" in n else "pen" if "stylus" in n else "touch" if "finger" in n else None


def _urls() -> list[tuple[str, str]]:
    out = [(p.name, f"x=hid@simhid://{p}?realtime=false&latency_ms=0") for p in HID]
    out += [(p.name, f"x=hid@simhid://{_profile(p)}?evemu={p}&realtime=false&latency_ms=0")
            for p in EVEMU if _profile(p)]
    return out


def _record(url: str, path: Path) -> SessionReader:
    rep = Capture([url], output=str(path), fsync=False, overwrite=True).run(None)
    assert rep.recorder_error is None
    return SessionReader(str(path))


@pytest.mark.parametrize(("name", "url"), _urls() or [pytest.param("none", "", marks=pytest.mark.skip(
    reason=f"no hid-recorder or evemu traces under {TRACES} (../shared/traces must sit beside the project)"))])
def test_every_real_trace_gets_its_recorded_report_times(name: str, url: str, tmp_path: Path) -> None:
    r = _record(url, tmp_path / "t.mcap")
    n = 0
    for s, b in r.all_samples().items():
        if not len(b):
            continue
        n += len(b)
        # one report, one arrival: readings of one report end at its arrival, 1 us apart
        assert np.all(b.t_bus_ns <= b.t_host_ns) and np.all(b.t_host_ns - b.t_bus_ns < 1_000_000), s
        assert np.all(np.diff(b.t_bus_ns) >= 0), s
        assert r.streams[s].nominal_rate_hz is None
    assert n > 0, name
    assert not r.clock_states()   # nothing fitted, so no drift and no reset
    # what ``perfcap info`` says: stamped at arrival, the bus times at the recorded report times
    for st in summarize(r)["streams"]:
        if st["samples"]:
            assert st["clock"] is None and 0 <= st["arrival_lag_ms"]["min"] <= st["arrival_lag_ms"]["max"] < 1.0


@pytest.mark.parametrize("src", EVEMU[:2] or [None])
def test_with_latency_and_jitter_the_bus_time_is_the_arrival(src: Path | None, tmp_path: Path) -> None:
    if src is None or not _profile(src):
        pytest.skip(f"no evemu traces under {TRACES}")
    url = f"simhid://{_profile(src)}?evemu={src}&realtime=false&latency_ms=0.5&jitter_ms=2&truth=true&seed=4"
    dev = open_device(f"x=hid@{url}")
    dev.open()
    bus: list[int] = []
    from capture.errors import EndOfStream
    try:
        for _ in range(100_000):
            bus += [s.t_bus_ns for s in dev.poll(0.0) if hasattr(s, "t_bus_ns")]
    except EndOfStream:
        pass
    t = dev.transport
    truth, arrival = np.array(t.truth_ns), np.array(t.arrival_ns)   # type: ignore[attr-defined]
    assert len(bus) >= len(truth) > 50
    # each reading's bus time is its report's arrival (a touch report's several contacts end at it)
    got = np.array(bus)
    idx = np.searchsorted(arrival, got, side="left")
    assert np.all(idx < len(arrival)) and np.all(arrival[idx] - got < 10_000)
    late = got - truth[idx]
    assert late.min() > -10_000 and late.max() <= 2_500_000   # the latency and jitter the link added, no more


@pytest.mark.parametrize("seed", range(300))
def test_irregular_arrivals_are_stamped_at_arrival_on_both_paths(seed: int) -> None:
    rng = random.Random(seed)
    m = rng.randrange(1, 400)
    if seed % 2:   # polled runs (a period, 3 % jitter) broken by pauses: the dejittered case
        period = rng.uniform(300_000, 30_000_000)
        gaps = [int(period * rng.uniform(0.97, 1.03)) if rng.random() > 0.03 else rng.randrange(1, 10**9)
                for _ in range(m)]
    else:
        gaps = [rng.choice((rng.randrange(0, 3), rng.randrange(900_000, 1_100_000), rng.randrange(1, 2 * 10**9)))
                for _ in range(m)]
    hosts = np.cumsum(np.array(gaps, np.int64)) + 10**12
    counts = [rng.choice((1, 1, 1, rng.randrange(1, 6))) for _ in range(m)]
    a = ClockSync("s", None, None)
    per_chunk: list[int] = []
    for h, c in zip(hosts.tolist(), counts, strict=True):
        before = per_chunk[-1] if per_chunk else None
        dev, bus = a.stamp(h, None, c)
        end = bus[-1]
        # at its arrival, or dejittered inside a regular run: at most 1 ms and half a period before it
        assert dev == [None] * c and h - EVENT_DEJITTER_MAX_NS <= end <= h
        if before is None or before < end - (c - 1) * 1000:
            assert bus == [end - (c - 1 - i) * 1000 for i in range(c)]   # 1 us apart, ending at its time
        per_chunk += bus
    got = np.array(per_chunk)
    assert np.all(np.diff(got) >= 0)
    chunk_of = np.repeat(np.arange(m), counts)
    b = ClockSync("s", None, None)
    cut = rng.randrange(0, len(chunk_of) + 1)
    k = int(np.searchsorted(chunk_of, chunk_of[cut - 1] + 1)) if cut else 0   # split on a chunk boundary
    parts = []
    for lo, hi in ((0, k), (k, len(chunk_of))):
        if hi > lo:
            co = chunk_of[lo:hi]
            _, bus, _ = b.stamp_many(hosts, co, None)
            parts.append(bus)
    assert np.array_equal(np.concatenate(parts), got)


@pytest.mark.parametrize("seed", range(200))
def test_regular_runs_are_dejittered_and_a_pause_is_stamped_at_arrival(seed: int) -> None:
    """Runs of a polled device (a period of 0.5 to 20 ms, jitter up to 3 % of it) between pauses and
    single events: inside a run the bus time is nearer the true grid than the arrival and never before
    the truth by more than the jitter; the first report after a pause is stamped at its arrival."""
    rng = random.Random(seed)
    truth: list[int] = []
    arrival: list[int] = []
    first_after_pause: list[int] = []
    t = 10**12
    for _ in range(rng.randrange(1, 6)):
        period = rng.uniform(0.5e6, 20e6)
        t += rng.randrange(60_000_000, 900_000_000)   # a pause
        first_after_pause.append(len(truth))
        for k in range(rng.randrange(1, 300)):
            tt = int(t + k * period)
            truth.append(tt)
            arrival.append(max(tt + int(rng.uniform(0, 0.03) * period), arrival[-1] if arrival else 0))
        t = truth[-1]
    cs = ClockSync("s", None, None)
    bus = np.array([cs.stamp(h, None, 1)[1][0] for h in arrival])
    tr, ar = np.array(truth), np.array(arrival)
    assert np.all(bus <= ar) and np.all(ar - bus <= EVENT_DEJITTER_MAX_NS) and np.all(np.diff(bus) >= 0)
    assert np.all(bus[first_after_pause] == ar[first_after_pause])
    assert np.all(bus - tr >= -(ar - tr).max() - 16)   # never before the truth by more than the jitter
    inside = np.ones(len(tr), bool)
    for f in first_after_pause:
        inside[f:f + 9] = False
    if inside.sum() > 20:
        assert np.abs(bus - tr)[inside].mean() < 0.6 * np.abs(ar - tr)[inside].mean() + 1


def test_a_declared_rate_still_dejitters_on_its_grid(tmp_path: Path) -> None:
    r = _record("x=hid@simhid://mouse?realtime=false&duration=3&jitter_ms=3&rate=1000&truth=true",
                tmp_path / "rate.mcap")
    b = r.samples("x/pointer")
    assert r.streams["x/pointer"].nominal_rate_hz == 1000
    assert len(b) > 2000 and r.clock_states()
    jitter = b.t_host_ns - b.t_bus_ns
    assert np.median(jitter) > 500_000   # the fit takes most of the arrival jitter out
