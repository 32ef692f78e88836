"""Format 2's protobuf blocks and the viewable channels (``capture.session_blocks``, ``capture.session_view``):
a seeded sweep of random batches (values of every kind: quantised, NaN, infinities, negative zero, huge, device
times present, absent or mixed with none) comes back bit for bit; random stream and channel names always make a
valid schema that a generic protobuf decoder reads; the 3D views carry the rotations and the skeleton's frames."""

from __future__ import annotations

import json

import numpy as np
import pytest
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory

from capture.proto import identifier
from capture.sample import NO_TIME, Chunk, DeviceIdentity, Direction, SampleBatch, StreamInfo
from capture.session_blocks import decode_raw_run, decode_samples, encode_raw, encode_samples
from capture.session_view import SKELETON_KEY, Placement, encode_event, stream_views

DEV = DeviceIdentity("synth", "d")


def _values(rng: np.random.Generator, n: int, c: int) -> tuple[np.ndarray, tuple[float, ...]]:
    vals = np.empty((n, c))
    quantum = []
    for j in range(c):
        kind = rng.integers(0, 5)
        q = float(2.0 ** -rng.integers(0, 16)) if kind < 2 else float(rng.choice([0.0, 0.1, 1e-3]))
        if kind == 0:      # exact multiples of a power-of-two quantum: stored as integer steps
            vals[:, j] = rng.integers(-2**40, 2**40, n) * q
        elif kind == 1:    # a quantum declared but broken by a few odd values
            vals[:, j] = rng.integers(-1000, 1000, n) * q
            vals[rng.integers(0, n, max(1, n // 7)), j] = rng.normal(size=max(1, n // 7))
        else:
            vals[:, j] = rng.normal(0, 10.0 ** rng.integers(-20, 20), n)
        specials = rng.random(n) < 0.05
        vals[specials, j] = rng.choice([np.nan, np.inf, -np.inf, -0.0, 0.0, 1e308, -5e-324], int(specials.sum()))
        quantum.append(q)
    return vals, tuple(quantum)


def _batch(rng: np.random.Generator) -> tuple[SampleBatch, tuple[float, ...]]:
    n = int(rng.integers(1, 300))
    c = int(rng.integers(0, 9))
    t0 = int(rng.integers(-2**62, 2**62))
    bus = t0 + np.cumsum(rng.integers(-10**6, 10**7, n))   # clock resets step bus times back
    dev_mode = rng.integers(0, 3)
    dev = (np.full(n, NO_TIME, np.int64) if dev_mode == 0 else rng.integers(-2**63, 2**63 - 1, n, dtype=np.int64))
    if dev_mode == 2:
        dev[rng.random(n) < 0.3] = NO_TIME
    vals, q = _values(rng, n, c)
    return SampleBatch("s/x", np.cumsum(rng.integers(0, 5, n)), bus + rng.integers(0, 10**7, n), dev,
                       bus.astype(np.int64), vals), q


def test_sample_blocks_come_back_bit_for_bit_on_a_random_sweep() -> None:
    rng = np.random.default_rng(18)
    for case in range(400):
        b, q = _batch(rng)
        out = decode_samples("s/x", encode_samples(b, q if case % 3 else None))
        for col in ("seq", "t_host_ns", "t_device_ns", "t_bus_ns"):
            np.testing.assert_array_equal(getattr(out, col), getattr(b, col), err_msg=f"case {case} {col}")
        assert out.values.shape == b.values.shape
        assert (out.values.view(np.int64) == b.values.view(np.int64)).all(), f"case {case}"   # every bit


def test_raw_blocks_come_back_exactly_on_a_random_sweep() -> None:
    rng = np.random.default_rng(19)
    for _ in range(300):
        n = int(rng.integers(1, 200))
        t = int(rng.integers(0, 2**62)) + np.cumsum(rng.integers(0, 10**8, n))
        chunks = [Chunk(rng.bytes(int(rng.integers(0, 80))), int(t[i]), Direction(int(rng.random() < 0.1)))
                  for i in range(n)]
        assert list(decode_raw_run(encode_raw(chunks))) == chunks


def test_a_damaged_block_is_a_value_error_never_another() -> None:
    rng = np.random.default_rng(20)
    good = [encode_samples(*_batch(rng)) for _ in range(30)]
    raw = [encode_raw([Chunk(rng.bytes(20), i, Direction.RX) for i in range(50)]) for _ in range(10)]
    for _ in range(500):
        data = bytearray((good + raw)[int(rng.integers(0, 40))])
        for _ in range(int(rng.integers(1, 4))):
            if rng.random() < 0.5 and len(data) > 1:
                del data[int(rng.integers(0, len(data))):]
            elif data:
                data[int(rng.integers(0, len(data)))] ^= int(rng.integers(1, 256))
        for dec in (lambda d: decode_samples("s/x", d), decode_raw_run):
            try:
                dec(bytes(data))
            except ValueError:
                pass


_ALPHABET = [*"abcXYZ019_.-/ é#", "timestamp", "__", "1st"]


def test_any_stream_and_channel_names_make_a_schema_a_generic_decoder_reads() -> None:
    rng = np.random.default_rng(21)
    factory = DecoderFactory()
    for case in range(200):
        c = int(rng.integers(1, 12))
        channels = tuple("".join(rng.choice(_ALPHABET, int(rng.integers(1, 6)))) for _ in range(c))
        name = "".join(rng.choice(_ALPHABET, int(rng.integers(1, 8)))) + "/s"
        info = StreamInfo(name, "imu", channels, ("u",) * c, 100.0, DEV)
        view = stream_views(info)[0]
        vals = rng.normal(size=(3, c))
        b = SampleBatch(name, np.arange(3), np.arange(3), np.full(3, NO_TIME), np.arange(3) * 10, vals)
        schema = Schema(id=case + 1, name=view.schema.name, encoding="protobuf", data=view.schema.data)
        dec = factory.decoder_for("protobuf", schema)
        assert dec is not None
        for (t, data), row in zip(view.encode(b, 5), vals, strict=True):
            m = dec(data)
            fields = [f.name for f in m.DESCRIPTOR.fields]
            assert fields[0] == "timestamp" and len(set(fields)) == c + 1
            assert [getattr(m, f) for f in fields[1:]] == row.tolist()
            assert m.timestamp.seconds * 10**9 + m.timestamp.nanos == t + 5
        names = json.loads(view.metadata["fields"])
        assert list(names.values()) == list(channels)


def test_identifiers_are_valid_and_unique() -> None:
    taken: set[str] = set()
    out = [identifier(n, taken) for n in ["a.b", "a_b", "a b", "9", "", "a_b"]]
    assert len(set(out)) == len(out)
    assert all(o[0].isalpha() or o[0] == "_" for o in out)


def test_orientation_streams_are_frame_transforms_and_non_finite_rows_are_left_out() -> None:
    info = StreamInfo("wrist/orientation", "orientation", ("w", "x", "y", "z"), ("1",) * 4, 200.0, DEV)
    placement = Placement()
    quiet = stream_views(StreamInfo("ankle/quat", "quat", ("w", "x", "y", "z"), ("1",) * 4, 200.0, DEV), placement)
    placement.x("pad/orientation")
    placement.x("head/orientation")   # two streams sent orientations first; the quiet one never sends
    views = stream_views(info, placement)
    assert len(quiet) == 2
    assert [v.topic for v in views] == ["/view/wrist/orientation", "/tf/wrist/orientation"]
    tf = views[1]
    assert tf.schema.name == "foxglove.FrameTransform"
    q = np.array([[1, 0, 0, 0], [np.nan, 0, 0, 0], [0.5, 0.5, 0.5, 0.5]], float)
    b = SampleBatch(info.name, np.arange(3), np.arange(3), np.full(3, NO_TIME), np.array([10, 20, 30]), q)
    msgs = tf.encode(b, 1_000)
    assert [t for t, _ in msgs] == [10, 30]
    m = tf.schema.cls.FromString(msgs[1][1])
    assert (m.parent_frame_id, m.child_frame_id) == ("world", "wrist/orientation")
    assert (m.rotation.w, m.rotation.x, m.rotation.y, m.rotation.z) == (0.5, 0.5, 0.5, 0.5)
    assert m.translation.x == pytest.approx(1.0)


def test_a_skeleton_pose_is_one_transform_per_joint_from_its_parent() -> None:
    joints = ("hips", "spine", "head")
    channels = ("root.x", "root.y", "root.z", *(f"{j}.{c}" for j in joints for c in "wxyz"))
    sk = {"parents": [-1, 0, 1], "offsets": [[0, 0, 0], [0, 0.1, 0], [0, 0.3, 0]]}
    info = StreamInfo("phone/puppet", "pose", channels, ("m",) * 3 + ("1",) * 12, 60.0, DEV,
                      extra={SKELETON_KEY: json.dumps(sk)})
    tf = stream_views(info)[1]
    assert tf.topic == "/tf/phone/puppet" and tf.schema.name == "foxglove.FrameTransforms"
    row = np.array([1.0, 0.9, 2.0, 1, 0, 0, 0, 0.7071, 0.7071, 0, 0, 1, 0, 0, 0])
    b = SampleBatch(info.name, np.arange(1), np.arange(1), np.full(1, NO_TIME), np.array([5]), row[None, :])
    (_, data), = tf.encode(b, 0)
    m = tf.schema.cls.FromString(data)
    got = [(t.parent_frame_id, t.child_frame_id, t.translation.x, t.translation.y, t.translation.z)
           for t in m.transforms]
    up = m.transforms[0].rotation   # Y up stood up in Foxglove's Z-up world: +90 degrees about x
    assert (up.w, up.x, up.y, up.z) == pytest.approx((0.5**0.5, 0.5**0.5, 0, 0))
    assert got == [("world", "phone/puppet", 0.0, 0.0, 0.0),
                   ("phone/puppet", "phone/puppet/hips", 1.0, 0.9, 2.0),
                   ("phone/puppet/hips", "phone/puppet/spine", 0.0, 0.1, 0.0),
                   ("phone/puppet/spine", "phone/puppet/head", 0.0, 0.3, 0.0)]
    assert m.transforms[2].rotation.w == pytest.approx(0.7071)


def test_a_skeleton_that_does_not_fit_its_channels_costs_only_its_3d_view(caplog: pytest.LogCaptureFixture) -> None:
    info = StreamInfo("p/puppet", "pose", ("root.x", "root.y", "root.z", "a.w", "a.x", "a.y", "a.z"),
                      ("m",) * 3 + ("1",) * 4, 60.0, DEV, extra={SKELETON_KEY: json.dumps({"parents": [-1, 0],
                                                                                          "offsets": [[0] * 3] * 2})})
    assert [v.topic for v in stream_views(info)] == ["/view/p/puppet"]
    assert "no 3D view" in caplog.text


def test_events_are_foxglove_logs_with_levels() -> None:
    from foxglove_schemas_protobuf.Log_pb2 import Log

    from capture.sample import DeviceEvent, EventKind

    m = Log.FromString(encode_event(DeviceEvent("pad", EventKind.FAILED, 7, "no reply"), 100))
    assert (m.level, m.name, m.message) == (Log.ERROR, "pad", "failed: no reply")
    assert m.timestamp.nanos == 107
    assert Log.FromString(encode_event(DeviceEvent("pad", EventKind.OPENED, 7), 0)).level == Log.INFO


def test_odd_inputs_cost_the_views_at_most_never_the_recording(tmp_path, caplog: pytest.LogCaptureFixture) -> None:
    """A batch wider than its stream, an event with a lone surrogate, a clock fit whose rate is not finite and
    an empty batch: the take is written, its blocks kept, the file passes the generic check, and perfcap's
    reader keeps none of the viewable channels' messages (it reads the blocks)."""
    import generic_mcap_check

    from capture.sample import ClockState, DeviceEvent, EventKind
    from capture.session import SessionReader, SessionWriter

    info = StreamInfo("d/imu", "imu", ("ax", "ay"), ("m/s^2",) * 2, 100.0, DEV)
    w = SessionWriter(str(tmp_path / "odd.mcap"), fsync=False)
    w.add_stream(info)
    ok = SampleBatch(info.name, np.arange(3), np.arange(3), np.full(3, NO_TIME), np.arange(3) + 10, np.ones((3, 2)))
    wide = SampleBatch(info.name, np.arange(3, 5), np.arange(3, 5), np.full(2, NO_TIME), np.arange(2) + 20,
                       np.ones((2, 3)))
    w.write_samples(ok, 0)
    w.write_samples(wide, 0)
    w.write_event(DeviceEvent("d\ud800", EventKind.NOTE, 30, "bad \udcff text"), 0)
    w.write_clock(ClockState("d", 40, 0, 0, 0, float("nan"), 0, True), 0)
    w.write_clock(ClockState("d", 41, 0, 0, 0, float("inf"), 0, True), 0)
    w.close()
    assert w.views_skipped == 2 and "not viewable" in caplog.text
    assert generic_mcap_check.check(tmp_path / "odd.mcap").problems == []
    r = SessionReader(str(tmp_path / "odd.mcap"))
    assert [len(b) for b in r.sample_blocks()] == [3]   # the wide block is read as damaged, as in format 1
    assert r.damaged and r.encoding("/samples/d/imu") == "protobuf"
    assert r.encoding("/view/d/imu") is None and r.encoding("/log") is None   # not kept
    assert [c["rate"] for c in r.clock_states()] == [None, None]
    assert decode_samples("x", encode_samples(SampleBatch.from_samples("x", [], 2))).values.shape == (0, 2)
