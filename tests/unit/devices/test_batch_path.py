"""The vectorised batch path (offline replay) gives exactly the samples of the per-chunk path, on
clean and messy data; and a byte stream re-split at random boundaries decodes to the same samples."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from capture.errors import EndOfStream
from capture.sample import Chunk, ChunkRun, Sample, SampleBatch
from devices import open_device

SCENARIOS = {
    "clean": "rate=200&drift_ppm=80&jitter_ms=2",
    "bursts_no_clock": "rate=200&device_clock=false&burst_ms=16",
    "garbage": "rate=100&garbage=0.05&jitter_ms=1",
    "midnight_wrap": "rate=100&start_ms=86399500&jitter_ms=3",
    "clock_reset": "rate=200&reset_at=1.5&jitter_ms=1",
    "fast_1khz": "rate=1000&jitter_ms=0.5&burst_ms=4",
}


@functools.lru_cache(maxsize=64)
def chunks_of(query: str, seconds: float = 3.0, seed: int = 1) -> tuple[list[Chunk], dict]:
    d = open_device(f"synth://imu?{query}&realtime=false&duration={seconds}&seed={seed}")
    d.transport.open()
    out = []
    try:
        while True:
            out.append(d.transport.read(0.1))
    except EndOfStream:
        pass
    return out, d.transport.implied_device_options()


def flatten(items) -> dict[str, list[tuple]]:
    res: dict[str, list[tuple]] = {}
    for it in items:
        if type(it) is Sample:
            rows = [it]
        elif type(it) is SampleBatch:
            rows = list(it.samples())
        else:
            continue
        for s in rows:
            res.setdefault(s.stream, []).append(
                (s.seq, s.t_host_ns, s.t_device_ns, s.t_bus_ns, np.array(s.values).tobytes()))
    return res


def per_chunk(chunks, opts):
    d = open_device(f"x=witmotion@synth://imu?rate={opts['rate']}&device_clock={opts['device_clock']}")
    out = []
    for c in chunks:
        out += d.process_chunk(c)
    return flatten(out), d


def batched(chunks, opts, cuts):
    d = open_device(f"x=witmotion@synth://imu?rate={opts['rate']}&device_clock={opts['device_clock']}")
    out = []
    i = 0
    for n in [*cuts, len(chunks)]:
        part = chunks[i:i + n]
        i += n
        if part:
            out += d.process_chunks(ChunkRun.from_chunks(part))
    return flatten(out), d


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_batch_path_equals_per_chunk_path(name):
    chunks, opts = chunks_of(SCENARIOS[name])
    ref, da = per_chunk(chunks, opts)
    got, db = batched(chunks, opts, [1, 7, 300, 64])
    assert ref.keys() == got.keys()
    for s in ref:
        assert got[s] == ref[s], s
    assert da.stats.lost_readings == db.stats.lost_readings
    assert da.health()["clock_resets"] == db.health()["clock_resets"]
    assert da.codec.stats.as_dict() == db.codec.stats.as_dict()
    if name != "garbage":
        # the clean parts really took the vectorised path
        items = db.process_chunks(ChunkRun.from_chunks(chunks_of(SCENARIOS[name], 1.0, seed=2)[0]))
        assert any(type(x) is SampleBatch for x in items) or name == "clock_reset"


@settings(max_examples=20, deadline=None)
@given(st.sampled_from(sorted(SCENARIOS)), st.lists(st.integers(3, 97), min_size=1, max_size=60), st.integers(0, 2))
def test_bytes_resplit_at_random_boundaries_decode_the_same(name, sizes, seed):
    """Serial reads split bytes anywhere: cut every arrival into random pieces, all with the time of
    that arrival. Values, sequence numbers, host and device times are then identical. Bus times can
    differ, because the fit is causal: a reading now alone in its read is stamped before the
    burst's least-delayed reading has lowered the line. The difference is the size of that
    correction: at most one burst while the fit starts, and under 0.1 ms (a fifth of the accuracy
    target) after the first second."""
    chunks, opts = chunks_of(SCENARIOS[name], 2.5, seed)
    ref, _ = per_chunk(chunks, opts)
    pieces, k = [], 0
    for c in chunks:
        i = 0
        while i < len(c.data):
            n = sizes[k % len(sizes)]
            k += 1
            pieces.append(Chunk(c.data[i:i + n], c.t_ns))
            i += n
    got, _ = per_chunk(pieces, opts)
    gotb, _ = batched(pieces, opts, [len(pieces) // 3])
    for s in ref:
        assert [(r[0], r[1], r[2], r[4]) for r in got[s]] == [(r[0], r[1], r[2], r[4]) for r in ref[s]], s
        bus_ref = np.array([r[3] for r in ref[s]])
        bus_got = np.array([r[3] for r in got[s]])
        late = bus_ref > bus_ref[0] + 1_000_000_000
        if "reset" not in name:
            assert np.max(np.abs(bus_got[late] - bus_ref[late]), initial=0) <= 100_000, s
        assert np.max(np.abs(bus_got - bus_ref)) <= 20_000_000, s
        assert gotb[s] == got[s], s  # and the batch path equals the per-chunk path on the new split
