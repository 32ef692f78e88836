"""BNO08x UART-RVC codec and device: the datasheet frame, frames split anywhere, garbage, false
headers and corruption with resync, the 8-bit index as a wrapping device clock, and the batch path
giving exactly the per-chunk samples."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from wait_helpers import DEADLINE_S

from capture.errors import ConfigError, ProtocolError
from capture.sample import Chunk, ChunkRun, Sample, SampleBatch
from devices import DEVICE_TYPES, device_class, open_device
from devices.bno08x import ACC_Q, Bno08xRvcImu, encode_rvc, encode_rvc_many, rvc_frame
from devices.codecs.bno08x_rvc import FRAME_LEN, Bno08xRvcCodec, RvcFrame
from devices.transports import open_transport

DATASHEET_FRAME = (Path(__file__).resolve().parents[3] / ".." / "shared" / "traces" / "c_serial_imu"
                   / "bno08x_uart_rvc_datasheet_example_frame.bin")


def device(**opts) -> Bno08xRvcImu:
    return Bno08xRvcImu("b", open_transport("loop://"), opts)


@pytest.fixture
def datasheet_frame() -> bytes:
    if not DATASHEET_FRAME.is_file():
        pytest.skip(f"datasheet frame not found at {DATASHEET_FRAME} (../shared/traces must sit beside the project)")
    return DATASHEET_FRAME.read_bytes()


def frames_of(start: int, body: list[tuple[int, ...]]) -> list[RvcFrame]:
    return [RvcFrame((start + k) & 0xFF, *b) for k, b in enumerate(body)]


def wire(frames: list[RvcFrame]) -> bytes:
    c = Bno08xRvcCodec()
    return b"".join(c.encode(f) for f in frames)


s16 = st.integers(-32768, 32767)
bodies = st.lists(st.tuples(s16, s16, s16, s16, s16, s16), min_size=1, max_size=25)


# -- the datasheet frame ------------------------------------------------------------------------
def test_datasheet_frame_decodes_and_reencodes_byte_identically(datasheet_frame):
    assert datasheet_frame.hex() == "aaaade010092ff25088dfeecffd103000000e7"
    c = Bno08xRvcCodec()
    (f,) = c.feed(datasheet_frame)
    assert f == RvcFrame(222, 1, -110, 2085, -371, -20, 977, 0, 0, 0)
    assert c.encode(f) == datasheet_frame
    assert c.stats.frames == 1 and c.stats.errors == 0 and c.buffered == 0
    # and the device turns it into degrees and m/s^2
    d = device()
    items = d.process_chunk(Chunk(datasheet_frame, 1_000_000_000))
    eul = [x for x in items if isinstance(x, Sample) and x.stream == "b/euler"]
    acc = [x for x in items if isinstance(x, Sample) and x.stream == "b/accel"]
    assert eul[0].values == pytest.approx((20.85, -1.10, 0.01), abs=1e-12)  # roll, pitch, yaw
    assert acc[0].values == pytest.approx((-371 * 9.80665e-3, -20 * 9.80665e-3, 977 * 9.80665e-3), abs=1e-12)
    assert acc[0].values[0] == pytest.approx(-3.638, abs=5e-4)  # the datasheet's own conversion
    assert eul[0].t_device_ns == 222 * 10_000_000
    # a simulator producing the same physical values produces the same bytes
    assert encode_rvc(222, (20.85, -1.10, 0.01), (-371 * ACC_Q, -20 * ACC_Q, 977 * ACC_Q)) == datasheet_frame


def test_values_are_exact_multiples_of_the_declared_quantum(datasheet_frame):
    d = device()
    for s in d.streams:
        assert s.quantum is not None and all(q > 0 for q in s.quantum)
    items = d.process_chunk(Chunk(datasheet_frame, 1))
    for x in items:
        if isinstance(x, Sample):
            q = d.streams[0 if x.stream.endswith("euler") else 1].quantum
            assert all(round(v / qq) * qq == v for v, qq in zip(x.values, q, strict=True))


def test_registered_and_streams_declared():
    assert DEVICE_TYPES["bno08x_rvc"] == ("devices.bno08x", "Bno08xRvcImu")
    assert device_class("bno08x_rvc") is Bno08xRvcImu
    d = device()
    assert [s.name for s in d.streams] == ["b/euler", "b/accel"]
    assert d.streams[0].channels == ("roll", "pitch", "yaw") and d.streams[1].channels == ("ax", "ay", "az")
    assert d.streams[0].clock.tick_hz == 100 and d.streams[0].clock.wrap_ticks == 256
    assert device(device_clock="false").streams[0].clock is None


def test_end_to_end_through_a_real_serial_transport(datasheet_frame):
    """pyserial's loop:// reads back what is written: the datasheet frame goes out, through the
    serial transport (``baud`` is its option) and the device, and comes back as samples."""
    d = open_device("b=bno08x_rvc@loop://?baud=115200")
    assert isinstance(d, Bno08xRvcImu) and d.transport.opts["baud"] == 115200
    d.open()
    try:
        d.send(datasheet_frame)
        got: list[Sample] = []
        deadline = time.monotonic() + DEADLINE_S
        while len(got) < 2 and time.monotonic() < deadline:
            got += [x for x in d.poll(0.05) if isinstance(x, Sample)]
    finally:
        d.close()
    assert [x.stream for x in got] == ["b/euler", "b/accel"]
    assert got[0].values == pytest.approx((20.85, -1.10, 0.01)) and got[1].values[2] == pytest.approx(977 * ACC_Q)


def test_bad_option_is_a_config_error():
    with pytest.raises(ConfigError, match="device_clock='maybe' is not true\\|false"):
        device(device_clock="maybe")
    with pytest.raises(ConfigError, match="unknown option 'rate'"):
        device(rate="100")


# -- splitting, garbage, corruption -------------------------------------------------------------
@settings(max_examples=150, deadline=None)
@given(st.integers(0, 255), bodies, st.lists(st.integers(1, 45), max_size=30))
def test_frames_split_at_any_boundary_decode_the_same(start, body, cuts):
    want = frames_of(start, body)
    data = wire(want)
    c = Bno08xRvcCodec()
    out, i = [], 0
    for n in cuts:
        out += c.feed(data[i:i + n])
        i += n
    out += c.feed(data[i:])
    # a first frame with a 0xAA 0xAA pair inside waits for the next header; only a lone one is left
    assert out == want or (len(want) == 1 and out == [] and c.buffered == FRAME_LEN)
    out += c.flush()
    assert out == want
    assert c.stats.errors == 0 and c.buffered == 0 and c.stats.frames == len(want)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 255), s16, s16, s16, s16, s16, s16), min_size=1, max_size=12),
       st.lists(st.integers(1, 45), max_size=20))
def test_unrelated_indices_and_splits_decode_the_same_after_flush(raw, cuts):
    """Without consecutive indices every frame goes through the ambiguity rule; a frame waiting for
    lookahead bytes comes out at ``flush``, and the result never depends on the split."""
    want = [RvcFrame(*r) for r in raw]
    data = wire(want)
    c = Bno08xRvcCodec()
    out, i = [], 0
    for n in cuts:
        out += c.feed(data[i:i + n])
        i += n
    out += c.feed(data[i:])
    out += c.flush()
    assert out == want
    assert c.stats.errors == 0 and c.buffered == 0


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=400), st.lists(st.integers(1, 60), max_size=10))
def test_random_bytes_never_raise_and_every_byte_is_accounted_for(data, cuts):
    c = Bno08xRvcCodec()
    out, i = [], 0
    for n in [*cuts, len(data)]:
        out += c.feed(data[i:i + n])
        i += n
    out += c.flush()
    st_ = c.stats
    assert st_.bytes_in == len(data) and st_.frames == len(out)
    assert FRAME_LEN * st_.frames + st_.skipped_bytes + c.buffered == len(data)
    assert c.buffered < FRAME_LEN
    if st_.skipped_bytes:
        assert st_.errors >= 1


corruptions = st.one_of(
    st.tuples(st.just("insert"), st.binary(min_size=1, max_size=40)),
    st.tuples(st.just("delete"), st.integers(1, 30)),
    st.tuples(st.just("flip"), st.integers(1, 255)),
)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 255), st.lists(st.tuples(s16, s16, s16, s16, s16, s16), min_size=4, max_size=20),
       st.integers(0, 10_000), corruptions, st.lists(st.integers(1, 45), max_size=10))
def test_corruption_is_counted_and_the_frames_after_it_are_recovered(start, body, where, corruption, cuts):
    want = frames_of(start, body)
    data = bytearray(wire(want))
    at = where % len(data)
    kind, arg = corruption
    if kind == "insert":
        data[at:at] = arg
        end = at
    elif kind == "delete":
        del data[at:at + arg]
        end = at
    else:
        data[at] ^= arg
        end = at + 1
    head = want[:at // FRAME_LEN]  # frames wholly before the corruption
    first_after = -(-(end if kind != "delete" else at + arg) // FRAME_LEN)
    tail = want[first_after:]  # frames wholly after it
    c = Bno08xRvcCodec()
    out, i = [], 0
    for n in [*cuts, len(data)]:
        out += c.feed(bytes(data[i:i + n]))
        i += n
    out += c.flush()
    if c.stats.errors == 0:
        # only possible when the bytes left are whole real frames (a cut of whole frames, which
        # shows as an index gap) plus, when the cut reached into the last frame, its unfinished rest
        assert kind == "delete"
        assert FRAME_LEN * len(out) + c.buffered == len(data) and all(f in want for f in out)
        assert c.buffered == 0 or at + arg > (len(want) - 1) * FRAME_LEN  # the cut reached the last frame
    assert out[:max(0, len(head) - 1)] == head[:max(0, len(head) - 1)]
    # every frame after the corruption comes back; at most the first one may be lost, when a false
    # candidate reaching into it passes the 8-bit checksum by chance (1 in 256)
    if len(tail) > 1:
        assert out[-(len(tail) - 1):] == tail[1:]


def test_garbage_then_valid_frames_resync():
    want = frames_of(10, [(k, -k, 2 * k, 100, -200, 1000) for k in range(5)])
    c = Bno08xRvcCodec()
    out = c.feed(b"\x00\x13garbage\xaa\x01\xaa" + wire(want))
    assert out == want
    assert c.stats.framing_errors >= 1 and c.stats.skipped_bytes == 12


def _frame_with_checksum(csum: int, start: int = 0) -> RvcFrame:
    for idx in range(start, start + 256):
        f = RvcFrame(idx & 0xFF, 1234, -567, 890, 12, -34, 1000)
        if Bno08xRvcCodec().encode(f)[-1] == csum:
            return f
    raise AssertionError("unreachable")


@pytest.mark.parametrize("locked", [False, True])
def test_a_false_header_that_passes_the_checksum_does_not_lose_the_real_frame(locked):
    """Garbage ending in 0xAA before a frame makes a candidate header one byte early. For a frame
    whose checksum is 0x56 (reserved byte 0) that candidate's checksum passes too; it must be
    recognised as false (a real frame overlaps it) so the real frame is decoded."""
    real = _frame_with_checksum(0x56)
    cand = b"\xaa" + Bno08xRvcCodec().encode(real)[:18]
    assert (sum(cand[2:18]) & 0xFF) == cand[18]  # the false candidate really is checksum-valid
    nxt = RvcFrame((real.counter + 1) & 0xFF, 1, 2, 3, 4, 5, 6)
    prev = RvcFrame((real.counter - 1) & 0xFF, 9, 9, 9, 9, 9, 9)
    head = wire([prev]) if locked else b"\x01\x02"
    data = head + b"\xaa" + wire([real, nxt])
    for split in range(len(data) + 1):
        c = Bno08xRvcCodec()
        out = c.feed(data[:split]) + c.feed(data[split:]) + c.flush()
        assert out == ([prev] if locked else []) + [real, nxt], split
        assert c.stats.errors >= 1


def test_header_pairs_inside_payloads_when_joining_mid_stream():
    """0xAA 0xAA inside a payload (yaw = -21846 is 0xAAAA) looks like a header when the reader joins
    mid-frame; the real frames that follow are still found."""
    frames = frames_of(0, [(-21846, -21846, 0, -21846, 0, 0)] * 6)
    data = wire(frames)
    for join in range(1, FRAME_LEN):
        c = Bno08xRvcCodec()
        out = c.feed(data[join:]) + c.flush()
        assert out == frames[1:], join


def test_checksum_error_counted_and_strict_mode_raises():
    good = wire(frames_of(0, [(1, 2, 3, 4, 5, 6), (7, 8, 9, 10, 11, 12)]))
    bad = bytearray(good)
    bad[5] ^= 0x40
    c = Bno08xRvcCodec()
    assert c.feed(bytes(bad)) == frames_of(1, [(7, 8, 9, 10, 11, 12)])
    assert c.stats.checksum_errors == 1
    with pytest.raises(ProtocolError) as ei:
        Bno08xRvcCodec(strict=True).feed(bytes(bad))
    assert ei.value.offset == 0 and ei.value.raw is not None and len(ei.value.raw) == FRAME_LEN


# -- encoders -----------------------------------------------------------------------------------
@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 1000), s16, s16, s16, s16, s16, s16), min_size=1, max_size=30))
def test_encode_many_equals_encode(rows):
    a = np.array(rows, np.int64)
    got = Bno08xRvcCodec.encode_many(a[:, 0], a[:, 1:4], a[:, 4:7]).tobytes()
    assert got == wire([RvcFrame(r[0] & 0xFF, *r[1:]) for r in rows])


def test_physical_encoders_agree_and_reject_out_of_range():
    rng = np.random.default_rng(3)
    eul = rng.uniform(-179, 179, (50, 3))
    acc = rng.uniform(-150, 150, (50, 3))
    many = encode_rvc_many(np.arange(50) + 250, eul, acc)
    assert many.tobytes() == b"".join(encode_rvc(250 + k, tuple(eul[k]), tuple(acc[k])) for k in range(50))
    f = Bno08xRvcCodec().feed(many.tobytes())
    assert np.allclose([(x.roll / 100, x.pitch / 100, x.yaw / 100) for x in f], eul, atol=0.005)
    assert np.allclose([(x.ax * ACC_Q, x.ay * ACC_Q, x.az * ACC_Q) for x in f], acc, atol=ACC_Q / 2)
    assert rvc_frame(300, (0, 0, 0), (0, 0, 0)).counter == 44
    with pytest.raises(ValueError, match="int16"):
        encode_rvc(0, (0, 0, 0), (400.0, 0, 0))  # 40.8 g does not fit
    with pytest.raises(ValueError, match="int16"):
        encode_rvc_many(np.arange(1), np.array([[0, 0, 400.0]]), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="finite"):
        encode_rvc_many(np.arange(1), np.array([[0, 0, np.nan]]), np.zeros((1, 3)))
    with pytest.raises(ValueError, match=r"0\.\.255"):
        Bno08xRvcCodec().encode(RvcFrame(256, 0, 0, 0, 0, 0, 0))


# -- the device: clock, lost frames, batch path ---------------------------------------------------
def stream(n: int, seed: int = 0, drop: tuple[int, int] | None = None, garbage_at: tuple[int, ...] = (),
           per_chunk: int = 3, recut: int = 0) -> tuple[list[Chunk], np.ndarray]:
    """n frames at 100 Hz (index from 0, wrapping), arriving 1-4 ms late in reads of 1..per_chunk
    frames; ``drop`` = (first, count) frames lost on the link; garbage before some frames; ``recut``:
    cut every read into pieces of at most that many bytes, anywhere (as serial reads do)."""
    rng = np.random.default_rng(seed)
    eul = rng.uniform(-90, 90, (n, 3))
    acc = rng.uniform(-20, 20, (n, 3))
    w = encode_rvc_many(np.arange(n), eul, acc)
    t = 5_000_000_000 + np.arange(n, dtype=np.int64) * 10_000_000
    keep = np.ones(n, bool)
    if drop:
        keep[drop[0]:drop[0] + drop[1]] = False
    chunks: list[Chunk] = []
    k = 0
    while k < n:
        m = int(rng.integers(1, per_chunk + 1))
        sel = [j for j in range(k, min(n, k + m)) if keep[j]]
        k += m
        if not sel:
            continue
        data = b"".join((b"\x13\xaa\x07" if j in garbage_at else b"") + w[j].tobytes() for j in sel)
        arrival = int(t[sel[-1]] + rng.integers(1_000_000, 4_000_000))
        i = 0
        while i < len(data):
            j = i + int(rng.integers(1, recut + 1)) if recut else len(data)
            chunks.append(Chunk(data[i:j], arrival))
            i = j
    return chunks, acc


def flatten(items) -> dict[str, list[tuple]]:
    res: dict[str, list[tuple]] = {}
    for it in items:
        rows = [it] if type(it) is Sample else list(it.samples()) if type(it) is SampleBatch else []
        for s in rows:
            res.setdefault(s.stream, []).append((s.seq, s.t_host_ns, s.t_device_ns, s.t_bus_ns,
                                                 np.array(s.values).tobytes()))
    return res


def test_index_clock_unwraps_over_many_wraps_and_lost_frames_are_sequence_gaps():
    chunks, acc = stream(3000, drop=(1000, 37))  # 30 s: 11 wraps of the 8-bit index
    d = device()
    items = [x for c in chunks for x in d.process_chunk(c)]
    a = [x for x in items if isinstance(x, Sample) and x.stream == "b/accel"]
    assert len(a) == 3000 - 37
    tdev = np.array([x.t_device_ns for x in a])
    steps = np.diff(tdev)
    assert set(steps.tolist()) == {10_000_000, 38 * 10_000_000}
    assert tdev[-1] - tdev[0] == 2999 * 10_000_000
    seq = np.array([x.seq for x in a])
    assert seq[-1] == 2999 and np.count_nonzero(np.diff(seq) == 38) == 1
    assert d.stats.lost_readings == 2 * 37  # euler and accel
    assert d.health()["clock_resets"] == 0
    assert np.allclose([x.values for x in a], np.delete(acc, np.s_[1000:1037], axis=0), atol=ACC_Q / 2)
    # bus times follow the true 100 Hz timing (readings are 1-4 ms late): within 1.5 ms after 3 s
    truth = 5_000_000_000 + (tdev - tdev[0])
    bus = np.array([x.t_bus_ns for x in a])
    assert np.all(np.diff(bus) >= 0)
    late = truth > truth[0] + 3_000_000_000
    assert np.max(np.abs(bus[late] - truth[late] - 1_000_000)) <= 1_500_000


def test_a_silence_longer_than_a_wrap_is_unwrapped_with_host_time():
    chunks, _ = stream(1500, drop=(700, 500), seed=2)  # 5 s lost: about two wraps of the index
    d = device()
    a = [x for c in chunks for x in d.process_chunk(c) if isinstance(x, Sample) and x.stream == "b/accel"]
    tdev = np.array([x.t_device_ns for x in a])
    assert tdev[-1] - tdev[0] == 1499 * 10_000_000
    assert d.stats.lost_readings == 2 * 500 and d.health()["clock_resets"] == 0


@pytest.mark.parametrize("garbage,recut", [((), 0), ((5, 400, 401, 1900), 0), ((), 23), ((7, 1500), 40)])
def test_batch_path_equals_per_chunk_path(garbage, recut):
    chunks, _ = stream(2000, seed=4, drop=(900, 3), garbage_at=garbage, recut=recut)
    da, db = device(), device()
    ref = flatten([x for c in chunks for x in da.process_chunk(c)])
    items = []
    for k in range(0, len(chunks), 97):
        items += db.process_chunks(ChunkRun.from_chunks(chunks[k:k + 97]))
    got = flatten(items)
    assert ref.keys() == got.keys() == {"b/euler", "b/accel"}
    for s in ref:
        assert got[s] == ref[s], s
    assert da.codec.stats.as_dict() == db.codec.stats.as_dict()
    assert da.stats.lost_readings == db.stats.lost_readings == 6
    assert any(type(x) is SampleBatch for x in items)  # the clean parts took the vectorised path
    if garbage:
        assert db.codec.stats.errors >= len(garbage)


def test_finish_emits_a_frame_still_waiting_for_lookahead():
    f = RvcFrame(0xAA, 100, 200, 300, 1, 2, 3)  # index 0xAA: 0xAA 0xAA 0xAA, ambiguous when not locked
    d = device()
    items = d.process_chunk(Chunk(Bno08xRvcCodec().encode(f), 7_000_000_000))
    assert not [x for x in items if isinstance(x, Sample)] and d.codec.buffered == FRAME_LEN
    tail = [x for x in d.finish() if isinstance(x, Sample)]
    assert [x.stream for x in tail] == ["b/euler", "b/accel"]
    assert tail[0].values == pytest.approx((3.0, 2.0, 1.0)) and tail[0].t_device_ns == 0xAA * 10_000_000
    assert d.codec.buffered == 0 and d.codec.stats.skipped_bytes == 0
