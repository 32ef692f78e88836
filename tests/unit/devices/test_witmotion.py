"""WitMotion codec and device: exact round trip, frames split anywhere, garbage and checksum
errors counted with resync, strict mode, cycle assembly, and real motion from a recorded IMU."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from capture.app.orchestrator import Capture
from capture.errors import EndOfStream, ProtocolError
from capture.sample import Chunk, Sample
from capture.session import SessionReader
from devices import open_device
from devices.codecs.witmotion import ACC, ANGLE, GYRO, WitMotionCodec, WitPacket
from devices.codecs.witmotion import TIME as TIME_T
from devices.witmotion import ACC_SCALE, GYRO_SCALE, encode_cycle

words = st.tuples(*[st.integers(-32768, 32767)] * 4)
packets = st.lists(st.tuples(st.sampled_from([ACC, GYRO, ANGLE, 0x54, 0x59]), words), min_size=1, max_size=30)


def stream_of(pk):
    c = WitMotionCodec()
    return b"".join(c.encode(WitPacket.from_words(t, w)) for t, w in pk)


@settings(max_examples=100, deadline=None)
@given(packets, st.lists(st.integers(1, 40), max_size=20))
def test_frames_split_at_any_boundary_decode_the_same(pk, cuts):
    data = stream_of(pk)
    c = WitMotionCodec()
    out, i = [], 0
    for n in cuts:
        out += c.feed(data[i:i + n])
        i += n
    out += c.feed(data[i:])
    assert [(p.type, p.words()) for p in out] == [(t, w) for t, w in pk]
    assert c.stats.errors == 0 and c.buffered == 0


@settings(max_examples=100, deadline=None)
@given(packets, st.binary(min_size=1, max_size=30), st.integers(0, 29))
def test_garbage_is_skipped_counted_and_later_frames_survive(pk, garbage, where):
    data = stream_of(pk)
    at = min(where, len(pk)) * 11
    c = WitMotionCodec()
    out = c.feed(data[:at] + garbage + data[at:])
    got = [(p.type, p.words()) for p in out]
    # every packet after the garbage that the garbage could not swallow is recovered
    want = [(t, w) for t, w in pk]
    tail = want[min(where, len(pk)):]
    assert got[:min(where, len(pk))] == want[:min(where, len(pk))]
    assert got[-len(tail) + 1:] == tail[1:] if len(tail) > 1 else True
    assert c.stats.skipped_bytes >= 1 or got == want


def test_checksum_error_counted_and_strict_mode_raises():
    good = stream_of([(ACC, (1, 2, 3, 4)), (GYRO, (5, 6, 7, 8))])
    bad = bytearray(good)
    bad[10] ^= 0xFF
    c = WitMotionCodec()
    out = c.feed(bytes(bad))
    assert [p.type for p in out] == [GYRO]
    assert c.stats.checksum_errors == 1
    with pytest.raises(ProtocolError) as ei:
        WitMotionCodec(strict=True).feed(bytes(bad))
    assert ei.value.offset == 0 and ei.value.raw is not None


def test_encode_rejects_non_packets():
    with pytest.raises(ValueError):
        WitMotionCodec().encode(WitPacket(0x10, b"\0" * 8))


def _device(url="synth://imu?realtime=false&duration=1"):
    d = open_device(url)
    d.open()
    return d


def test_cycle_values_and_device_time():
    d = _device("w=witmotion@synth://imu?realtime=false&duration=0.1&rate=100")
    codec = WitMotionCodec()
    data, _ = encode_cycle(codec, (0.5, -0.25, 1.0), (100.0, -200.0, 0.0), (10.0, 20.0, -30.0), 21.5, 12_345_678)
    data2, _ = encode_cycle(codec, (0, 0, 1), (0, 0, 0), (0, 0, 0), 21.5, 12_345_688)
    items = d.process_chunk(Chunk(data + data2, 5_000_000_000))
    imu = [x for x in items if isinstance(x, Sample) and x.stream == "w/imu"]
    eul = [x for x in items if isinstance(x, Sample) and x.stream == "w/euler"]
    assert len(imu) == 2 and len(eul) == 2
    ax, _ay, az, gx, _gy, _gz, temp = imu[0].values
    assert ax == pytest.approx(0.5 * 9.80665, abs=ACC_SCALE) and az == pytest.approx(9.80665, abs=ACC_SCALE)
    assert gx == pytest.approx(math.radians(100), abs=GYRO_SCALE) and temp == pytest.approx(21.5)
    assert eul[0].values == pytest.approx((10.0, 20.0, -30.0), abs=0.01)
    assert imu[0].t_device_ns == 12_345_678 * 1_000_000
    assert imu[1].t_device_ns - imu[0].t_device_ns == 10_000_000
    assert imu[0].t_bus_ns < imu[1].t_bus_ns <= 5_000_000_000
    d.close()


def test_lost_time_packet_is_extrapolated_and_counted():
    d = _device("w=witmotion@synth://imu?realtime=false&duration=0.1&rate=100&device_clock=true")
    codec = WitMotionCodec()
    chunks = []
    for i in range(5):
        data, _pk = encode_cycle(codec, (0, 0, 1), (0, 0, 0), (0, 0, 0), 20, 1000 + 10 * i)
        if i == 3:
            data = data[11:]  # the time packet of cycle 3 was lost
        chunks.append(data)
    items = d.process_chunk(Chunk(b"".join(chunks), 9_000_000_000))
    imu = [x for x in items if isinstance(x, Sample) and x.stream == "w/imu"]
    assert [x.t_device_ns // 1_000_000 for x in imu] == [1000, 1010, 1020, 1030, 1040]
    assert d.stats.missing_time == 2  # one reading each in the imu and euler streams
    d.close()


def test_real_imu_recording_through_codec_and_device(xio_csv):
    """x-io Fusion example data (real IMU, 13,514 readings with real timing gaps) encoded as WT901
    bytes, parsed by the real codec and device: values within quantisation, gaps seen as drops."""
    rows = np.genfromtxt(xio_csv, delimiter=",", skip_header=1)
    d = _device(f"synth://imu?csv={xio_csv}&realtime=false&latency_ms=2&jitter_ms=3&seed=4&truth=true")
    got = []
    with pytest.raises(EndOfStream):
        while True:
            got += [x for x in d.poll(0.1) if isinstance(x, Sample) and x.stream.endswith("/imu")]
    assert len(got) == len(rows)
    vals = np.array([g.values for g in got])
    assert np.max(np.abs(vals[:, 3:6] - np.radians(rows[:, 1:4]))) <= GYRO_SCALE
    assert np.max(np.abs(vals[:, 0:3] - rows[:, 4:7] * 9.80665)) <= ACC_SCALE
    tdev = np.array([g.t_device_ns for g in got], dtype=np.int64)
    tdev_rows = ((rows[:, 0] - rows[0, 0]) * 1000).astype(np.int64) * 1_000_000
    assert np.all(np.abs((tdev - tdev[0]) - tdev_rows) <= 1_000_000)
    # the recording's own dropouts (dt of 20-30 ms at 99 Hz) become sequence gaps
    seq = np.array([g.seq for g in got])
    gaps = int(seq[-1] - seq[0] + 1 - len(seq))
    dt = np.diff(rows[:, 0])
    expected = int(np.sum(np.maximum(np.round(dt / np.median(dt)) - 1, 0)))
    assert gaps == d.stats.lost_readings and abs(gaps - expected) <= 3 and gaps > 0
    # bus times follow the real, irregular timing: within the 1 ms resolution of the WT901 clock
    # (after the fit's first 5 s), against the true time of each reading plus the 2 ms link latency
    truth = np.array(d.transport.truth_ns) + 2_000_000
    bus = np.array([g.t_bus_ns for g in got])
    assert np.all(np.diff(bus) >= 0)
    settled = truth > truth[0] + 5_000_000_000
    err = np.abs(bus[settled] - truth[settled])
    assert np.percentile(err, 99) <= 1_000_000 and err.max() <= 1_500_000
    d.close()


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.sampled_from([TIME_T, ACC, GYRO, ANGLE, 0x54, 0x59]), st.binary(min_size=8, max_size=8)),
                min_size=1, max_size=40))
def test_encode_many_equals_encode(pk):
    c = WitMotionCodec()
    types = np.array([t for t, _ in pk], np.uint8)
    payloads = np.frombuffer(b"".join(p for _, p in pk), np.uint8).reshape(len(pk), 8)
    assert WitMotionCodec.encode_many(types, payloads).tobytes() == b"".join(c.encode(WitPacket(t, p)) for t, p in pk)


def test_last_pending_cycle_of_a_take_is_emitted(tmp_path):
    """A device that sent one cycle and vanished: the cycle is not lost at the end of the take."""
    s = tmp_path / "s.mcap"
    # one cycle only: nothing after it tells the device the cycle is complete
    Capture(["a=synth://imu?rate=100&realtime=false&duration=0.005"], output=str(s), fsync=False).run(None)
    r = SessionReader(str(s))
    assert len(r.samples("a/imu")) == 1 and len(r.samples("a/euler")) == 1
    assert os.path.getsize(s) > 0


def test_time_packets_without_the_device_clock_keep_every_reading():
    # a WitMotion outputs time packets by default; without device_clock=true they are not the stream's
    # time, and the readings they come with are kept (arrival-stamped), none refused as bad
    d = _device("w=witmotion@synth://imu?realtime=false&duration=0.1&rate=100&device_clock=false")
    assert all(s.clock is None for s in d.streams)
    codec = WitMotionCodec()
    data = b"".join(encode_cycle(codec, (0, 0, 1), (0, 0, 0), (0, 0, 0), 20, 43_200_000 + 10 * i)[0]
                    for i in range(6))
    items = d.process_chunk(Chunk(data, 9_000_000_000))
    imu = [x for x in items if isinstance(x, Sample) and x.stream == "w/imu"]
    assert len(imu) == 6 and all(x.t_device_ns is None for x in imu)
    assert d.stats.bad_readings == 0 and d.codec.stats.framing_errors == 0
    d.close()
