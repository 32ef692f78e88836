"""Session files: block codecs round-trip exactly; writer refuses to overwrite; reader copes with
files cut anywhere (a killed recorder) and rejects things that are not sessions."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from capture.errors import SessionError, SessionExistsError
from capture.sample import NO_TIME, Chunk, DeviceIdentity, Direction, SampleBatch, StreamInfo
from capture.session import DeviceRecord, SessionReader, SessionWriter
from capture.session_blocks import decode_raw_block, decode_sample_block, encode_raw_block, encode_sample_block

Q = 16.0 / 32768.0 * 9.80665


@st.composite
def batches(draw):
    n = draw(st.integers(0, 60))
    c = draw(st.integers(1, 5))
    ints = st.integers(-(2**62), 2**62)
    seq = np.array(draw(st.lists(ints, min_size=n, max_size=n)), np.int64)
    th = np.array(draw(st.lists(ints, min_size=n, max_size=n)), np.int64)
    td = np.array(draw(st.lists(st.one_of(ints, st.just(NO_TIME)), min_size=n, max_size=n)), np.int64)
    tb = np.array(draw(st.lists(ints, min_size=n, max_size=n)), np.int64)
    quantized = draw(st.booleans())
    if quantized:
        raw = draw(st.lists(st.integers(-32768, 32767), min_size=n * c, max_size=n * c))
        vals = np.array([r * Q for r in raw], np.float64).reshape(n, c)
    else:
        fl = st.floats(allow_nan=True, allow_infinity=True, width=64)
        vals = np.array(draw(st.lists(fl, min_size=n * c, max_size=n * c)), np.float64).reshape(n, c)
    return SampleBatch("d/s", seq, th, td, tb, vals), (Q,) * c if draw(st.booleans()) else None


@settings(max_examples=150, deadline=None)
@given(batches())
def test_sample_block_roundtrip_is_exact(bq):
    b, quantum = bq
    out = decode_sample_block("d/s", encode_sample_block(b, quantum))
    assert np.array_equal(out.seq, b.seq) and np.array_equal(out.t_host_ns, b.t_host_ns)
    assert np.array_equal(out.t_device_ns, b.t_device_ns) and np.array_equal(out.t_bus_ns, b.t_bus_ns)
    assert out.values.shape == b.values.shape
    # bit-exact, NaN payloads and signed zeros included
    assert out.values.tobytes() == np.ascontiguousarray(b.values).tobytes()


def test_quantized_columns_are_smaller():
    raw = np.cumsum(np.random.default_rng(1).integers(-30, 30, (2000, 3)), axis=0)
    vals = raw * Q
    b = SampleBatch("d/s", np.arange(2000), np.arange(2000) * 5_000_000, np.full(2000, NO_TIME),
                    np.arange(2000) * 5_000_000, vals)
    import zstandard

    def size(q):
        return len(zstandard.compress(encode_sample_block(b, q)))

    assert size((Q,) * 3) < 0.6 * size(None)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.binary(max_size=64), st.integers(0, 2**62), st.sampled_from(list(Direction))),
                min_size=1, max_size=40))
def test_raw_block_roundtrip(items):
    chunks = [Chunk(d, t, dr) for d, t, dr in items]
    assert decode_raw_block(encode_raw_block(chunks)) == chunks


def _write(path, n_blocks=50, overwrite=False):
    w = SessionWriter(path, overwrite=overwrite, fsync=False)
    ident = DeviceIdentity("witmotion", "d", "synth://imu")
    info = StreamInfo("d/imu", "imu", ("a", "b"), ("1", "1"), 100.0, ident)
    w.add_device(DeviceRecord("d", "witmotion", "synth://imu", {"rate": 100.0}, {"kind": "witmotion"},
                              ["d/imu"], {"descriptor": b"\x01\x02"}), [info])
    for k in range(n_blocks):
        seq = np.arange(k * 10, k * 10 + 10)
        t = 1_000_000_000 + seq * 10_000_000
        w.write_raw("d", [Chunk(bytes([i % 256]) * 11, int(x)) for i, x in enumerate(t)], 0)
        w.write_samples(SampleBatch("d/imu", seq, t, np.full(10, NO_TIME), t, np.c_[seq, -seq].astype(float)), 0)
        w.flush()
    return w


def test_writer_refuses_to_overwrite(tmp_path):
    p = str(tmp_path / "a.mcap")
    _write(p).close()
    with pytest.raises(SessionExistsError, match="already exists"):
        SessionWriter(p)
    _write(p, overwrite=True).close()
    with pytest.raises(SessionError, match="directory"):
        SessionWriter(str(tmp_path))


def test_complete_session_reads_back(tmp_path):
    p = str(tmp_path / "a.mcap")
    _write(p).close({"ok": True})
    r = SessionReader(p)
    assert r.truncated is None
    assert r.summary == {"ok": True}
    assert r.devices["d"].descriptors == {"descriptor": b"\x01\x02"}
    assert r.devices["d"].options == {"rate": 100.0}
    b = r.samples("d/imu")
    assert len(b) == 500 and np.array_equal(b.seq, np.arange(500))
    assert len(list(r.raw_chunks("d"))) == 500


def test_session_cut_anywhere_keeps_every_flushed_block(tmp_path):
    p = str(tmp_path / "a.mcap")
    w = _write(p, n_blocks=30)
    w._f.flush()  # simulate a kill: no footer
    with open(p, "rb") as f:
        data = f.read()
    w._f.close()
    full = len(data)
    prev = -1
    for cut in [*range(full // 3, full, max(1, full // 40)), full]:
        q = tmp_path / f"cut{cut}.mcap"
        q.write_bytes(data[:cut])
        q = str(q)
        r = SessionReader(q)
        assert r.truncated is not None
        n = len(r.samples("d/imu"))
        assert n >= prev  # more file, never less data
        prev = n
        if n:
            assert np.array_equal(r.samples("d/imu").seq, np.arange(n))
    assert prev == 300


@pytest.mark.parametrize("content", [b"", b"hello world, not a session", b"\x89MCAP0\r\n" + b"\x00" * 3])
def test_not_a_session_is_a_clear_error(tmp_path, content):
    p = tmp_path / "x.mcap"
    p.write_bytes(content)
    with pytest.raises(SessionError):
        SessionReader(str(p))


def test_missing_and_directory_paths(tmp_path):
    with pytest.raises(SessionError, match="no such file"):
        SessionReader(str(tmp_path / "nope.mcap"))
    with pytest.raises(SessionError, match="directory"):
        SessionReader(str(tmp_path))


def test_an_mcap_that_is_not_perfcap(tmp_path):
    from mcap.writer import Writer

    p = tmp_path / "other.mcap"
    with open(p, "wb") as f:
        w = Writer(f)
        w.start()
        w.finish()
    with pytest.raises(SessionError, match="not a perfcap session"):
        SessionReader(str(p))
    assert os.path.getsize(p) > 0
