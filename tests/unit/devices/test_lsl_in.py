"""LSL in: ``lsl://`` streams recorded and replayed like any device.

Live tests use real pylsl outlets in this process, on loopback (``lsl_helpers`` configures liblsl at
the root conftest), and skip only when pylsl cannot load; the codec sweep needs no LSL. Bus times
are held to the sender's timestamps mapped onto the host clock within ``BUS_TOLERANCE_NS`` (the
clock fit's lower envelope sits on the least-delayed arrivals: a few ms here, the rest is room for a
busy machine); nothing asserts how long anything took.
"""

from __future__ import annotations

import gc
import json
import sys
import time
import uuid

import numpy as np
import pylsl  # a dependency, liblsl in its wheel: not loading is a failure, never a skip
import pytest
from wait_helpers import DEADLINE_S, wait_until

from capture.app.cli import main as cli_main
from capture.app.orchestrator import Capture
from capture.app.replay import replay_session
from capture.errors import DeviceUnavailableError
from capture.sample import Chunk, DeviceEvent, EventKind, Sample
from capture.session import SessionReader
from devices import DeviceSpec, DeviceState, open_device
from devices.codecs.lsl import LslCodec, LslFrame, parse_info_xml
from devices.lsl import channel_names
from devices.transports.lsl import FORMATS, pack_frame

RATE = 200.0
N_PUSHED = 300  # 1.5 s at 200 Hz
LABELS = ("acc x", "acc y", "acc z", "gyro x", "gyro y", "gyro z")
UNITS = ("m/s^2",) * 3 + ("rad/s",) * 3
#: how far a bus time may be from the sender's timestamp mapped onto the host clock (measured here:
#: 0.1 to 1.3 ms, with two busy processes beside the test); the median must be within a tenth of it
BUS_TOLERANCE_NS = 100_000_000


def _outlet(name: str, channels: int = 6, rate: float = RATE, fmt: str = "float32",
            labels: tuple[str, ...] = LABELS, units: tuple[str, ...] = UNITS, stype: str = "MoCap"):
    info = pylsl.StreamInfo(name, stype, channels, rate, fmt, f"src-{name}")
    chans = info.desc().append_child("channels")
    for label, unit in zip(labels, units, strict=True):
        c = chans.append_child("channel")
        c.append_child_value("label", label)
        c.append_child_value("unit", unit)
    return pylsl.StreamOutlet(info)


def _resolving(make, what: str):
    """``make()`` retried while the stream is not resolved yet (same-host discovery can miss a try)."""
    end = time.monotonic() + DEADLINE_S
    while True:
        try:
            return make()
        except DeviceUnavailableError:
            if time.monotonic() > end:
                raise AssertionError(f"{what} was never resolved") from None


def _lsl_offset_ns() -> int:
    """Host monotonic ns minus LSL clock ns, from the narrowest of a few brackets."""
    best = None
    for _ in range(50):
        a = time.monotonic_ns()
        lsl_ns = pylsl.local_clock() * 1e9
        b = time.monotonic_ns()
        if best is None or b - a < best[0]:
            best = (b - a, (a + b) // 2 - round(lsl_ns))
    assert best is not None
    return best[1]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A 6-channel 200 Hz float32 outlet pushed in real time with explicit timestamps, recorded by
    ``Capture`` from ``lsl://NAME``; the outlet is gone when the fixture returns."""
    name = f"perfcap-in-{uuid.uuid4().hex[:8]}"
    path = str(tmp_path_factory.mktemp("lsl") / "take.mcap")
    outlet = _outlet(name)
    cap = _resolving(lambda: Capture([f"imu=lsl://{name}?timeout=2"], output=path, fsync=False), name)
    dev = cap.devices[0]
    rng = np.random.default_rng(18)
    values = rng.normal(0, 10, (N_PUSHED, 6)).astype(np.float32)
    cap.start()
    try:
        wait_until(lambda: dev.state is DeviceState.STREAMING, DEADLINE_S, "the inlet to open")
        t0 = pylsl.local_clock() + 0.02
        stamps = [t0 + i / RATE for i in range(N_PUSHED)]
        for i, ts in enumerate(stamps):
            while pylsl.local_clock() < ts:
                time.sleep(0.0005)
            outlet.push_sample(values[i].tolist(), ts)
        wait_until(lambda: dev.stats.readings >= N_PUSHED, DEADLINE_S, "every pushed sample")
        offset = _lsl_offset_ns()
    finally:
        rep = cap.stop()
    del outlet
    gc.collect()
    return {"path": path, "values": values, "stamps": stamps, "offset": offset, "report": rep}


def test_every_pushed_sample_is_recorded_with_the_senders_timestamps(recorded):
    r = SessionReader.open(recorded["path"])
    info = r.streams["imu/mocap"]
    assert info.channels == ("acc_x", "acc_y", "acc_z", "gyro_x", "gyro_y", "gyro_z")
    assert info.units == UNITS
    assert info.nominal_rate_hz == RATE and info.kind == "lsl" and info.extra["lsl_format"] == "float32"
    b = r.samples("imu/mocap")
    assert np.array_equal(b.seq, np.arange(N_PUSHED))
    assert np.array_equal(b.values, recorded["values"].astype(np.float64))
    expected_dev = np.array([round(ts * 1e9) for ts in recorded["stamps"]], dtype=np.int64)
    assert np.array_equal(b.t_device_ns, expected_dev)
    mapped = expected_dev + recorded["offset"]
    err = b.t_bus_ns - mapped
    assert np.abs(err).max() < BUS_TOLERANCE_NS, f"bus - mapped LSL time: {err.min()} .. {err.max()} ns"
    assert abs(float(np.median(err))) < BUS_TOLERANCE_NS / 10, f"median bus - mapped LSL time: {np.median(err)} ns"
    assert (b.t_bus_ns <= b.t_host_ns).all()
    assert r.devices["imu"].kind == "lsl" and "lsl.info" in r.devices["imu"].descriptors
    assert recorded["report"].devices["imu"]["framing_errors"] == 0


def test_replay_is_bit_identical_with_no_lsl(recorded, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pylsl", None)  # any use of LSL in the replay would fail
    out = str(tmp_path / "again.mcap")
    rep = replay_session(recorded["path"], speed=0, output=out)
    assert rep.verification is not None and rep.verification["equal"], rep.verification
    a, b = SessionReader.open(recorded["path"]).samples("imu/mocap"), SessionReader.open(out).samples("imu/mocap")
    for col in ("seq", "t_host_ns", "t_device_ns", "t_bus_ns", "values"):
        assert np.array_equal(getattr(a, col), getattr(b, col)), col
    assert SessionReader.open(out).streams["imu/mocap"].channels == SessionReader.open(recorded["path"]).streams[
        "imu/mocap"].channels


@pytest.mark.parametrize("url", ["lsl://nobody-{u}?timeout=0.2", "lsl://?type=Nope{u}&source_id=zz{u}&timeout=0.2"])
def test_no_stream_is_a_clear_error(url):
    url = url.format(u=uuid.uuid4().hex[:6])
    with pytest.raises(DeviceUnavailableError) as ei:
        open_device(url)
    msg = str(ei.value)
    assert "no LSL stream with" in msg and ("nobody-" in msg or ("Nope" in msg and "zz" in msg))


@pytest.fixture
def own_logging():
    """``main`` configures logging to the stderr of its call; give the root logger back afterwards."""
    import logging

    root = logging.getLogger()
    saved, level = root.handlers[:], root.level
    root.handlers = []
    yield
    root.handlers, root.level = saved, level


def test_no_stream_on_the_command_line_is_one_line(tmp_path, capsys, own_logging):
    rc = cli_main(["record", "-d", f"lsl://nobody-{uuid.uuid4().hex[:6]}?timeout=0.2", "--duration", "0.5",
                   "-o", str(tmp_path / "x.mcap")])
    err = capsys.readouterr().err
    assert rc != 0 and "no LSL stream with name='nobody-" in err and "Traceback" not in err


def test_string_streams_are_refused_clearly():
    name = f"markers-{uuid.uuid4().hex[:6]}"
    outlet = pylsl.StreamOutlet(pylsl.StreamInfo(name, "Markers", 1, 0, "string", f"src-{name}"))
    try:
        end = time.monotonic() + DEADLINE_S
        while True:
            with pytest.raises(DeviceUnavailableError) as ei:
                open_device(f"lsl://{name}?timeout=1")
            if "strings" in str(ei.value) or time.monotonic() > end:
                break
        assert "strings (markers)" in str(ei.value)
    finally:
        del outlet


def test_two_streams_answering_one_name_are_an_error_that_lists_them():
    """Two hosts whose devices have the same names publish streams of one name: lsl://NAME refuses to pick
    one at random, lists both, and source_id= chooses."""
    name = f"twin-{uuid.uuid4().hex[:6]}"
    a = pylsl.StreamOutlet(pylsl.StreamInfo(name, "MoCap", 2, 100.0, "float32", f"host-a-{name}"))
    b = pylsl.StreamOutlet(pylsl.StreamInfo(name, "MoCap", 2, 100.0, "float32", f"host-b-{name}"))
    try:
        end = time.monotonic() + DEADLINE_S
        msg = ""
        while "2 LSL streams answer" not in msg and time.monotonic() < end:
            try:
                open_device(f"lsl://{name}?timeout=5").close()
            except DeviceUnavailableError as exc:
                msg = str(exc)
        assert "2 LSL streams answer" in msg and f"host-a-{name}" in msg and f"host-b-{name}" in msg, msg
        assert "source_id=" in msg
        dev = _resolving(lambda: open_device(f"lsl://{name}?source_id=host-b-{name}&timeout=5"), "host b's twin")
        try:
            assert dev.streams[0].extra["lsl_source_id"] == f"host-b-{name}"
        finally:
            dev.close()
    finally:
        del a, b


def test_irregular_int_stream_and_lost_sender(tmp_path):
    """An int16 stream at LSL's irregular rate has no rate; the sender going away and coming back is
    DISCONNECTED then RECONNECTED, like any device."""
    from devices import ReconnectPolicy

    name = f"irr-{uuid.uuid4().hex[:6]}"
    mk = lambda: _outlet(name, 2, 0.0, "int16", ("a", "a"), ("", "count"), "Counts")  # noqa: E731
    outlet = mk()
    path = str(tmp_path / "irr.mcap")
    cap = _resolving(lambda: Capture([f"lsl://{name}?timeout=2"], output=path, fsync=False,
                                     reconnect=ReconnectPolicy(initial_s=0.05, max_s=0.2)), name)
    dev = cap.devices[0]
    assert dev.name == name and dev.streams[0].nominal_rate_hz is None
    assert dev.streams[0].channels == ("a", "a_2") and dev.streams[0].units == ("", "count")
    cap.start()
    try:
        wait_until(lambda: dev.state is DeviceState.STREAMING, DEADLINE_S, "the inlet to open")
        for i in range(10):
            outlet.push_sample([i, -i], pylsl.local_clock())
        wait_until(lambda: dev.stats.readings >= 10, DEADLINE_S, "the first samples")
        del outlet
        gc.collect()
        wait_until(lambda: dev.state is not DeviceState.STREAMING, DEADLINE_S, "the loss to be seen")
        outlet = mk()
        wait_until(lambda: dev.stats.reconnects == 1 and dev.state is DeviceState.STREAMING, DEADLINE_S,
                   "the reconnect")
        for i in range(10, 20):
            outlet.push_sample([i, -i], pylsl.local_clock())
        wait_until(lambda: dev.stats.readings >= 20, DEADLINE_S, "samples after the reconnect")
    finally:
        rep = cap.stop()
        del outlet
    kinds = [e["kind"] for e in rep.events if e["source"] == name]
    assert "disconnected" in kinds and "reconnected" in kinds
    b = SessionReader.open(path).samples(f"{name}/counts")
    assert b.values[:, 0].tolist() == list(range(20)) and b.values[:, 1].tolist() == [-i for i in range(20)]


def test_perfcap_devices_lists_an_outlet(capsys, own_logging):
    name = f"listed-{uuid.uuid4().hex[:6]}"
    outlet = _outlet(name)
    try:
        end = time.monotonic() + DEADLINE_S
        while True:
            assert cli_main(["devices", "--json", "--lsl-timeout", "1"]) == 0
            doc = json.loads(capsys.readouterr().out)
            mine = [s for s in doc["lsl_streams"] if s["name"] == name]
            if mine or time.monotonic() > end:
                break
        assert mine == [{"name": name, "type": "MoCap", "channels": 6, "rate_hz": RATE, "format": "float32",
                         "source_id": f"src-{name}", "host": mine[0]["host"], "url": f"lsl://{name}?source_id=src-{name}"}]
        assert mine[0]["host"]
        assert cli_main(["devices", "--lsl-timeout", "1"]) == 0
        assert "LSL streams" in capsys.readouterr().out
    finally:
        del outlet


# -- codec level: no LSL needed --------------------------------------------------------------------------
def _xml(channels: int, fmt: str = "float32", rate: float = 100.0, labels: list[str] | None = None) -> str:
    chans = "".join(f"<channel><label>{lb}</label><unit>u{i}</unit></channel>" for i, lb in enumerate(labels or []))
    return (f"<?xml version='1.0'?><info><name>t</name><type>Test</type><channel_count>{channels}</channel_count>"
            f"<nominal_srate>{rate}</nominal_srate><channel_format>{fmt}</channel_format><source_id>s</source_id>"
            f"<hostname>h</hostname><desc><channels>{chans}</channels></desc></info>")


def test_description_and_channel_names():
    d = parse_info_xml(_xml(3, "int32", 0.0, ["x", "x", ""]))
    assert d.rate_hz is None and d.format_code == 4 and d.labels == ("x", "x", "") and d.units == ("u0", "u1", "u2")
    assert channel_names(d.labels) == ("x", "x_2", "c2")
    assert channel_names(["a b", "a_b", "é!"]) == ("a_b", "a_b_2", "c2")
    assert parse_info_xml(_xml(2)).labels == ("", "")


def _random_frame(rng: np.random.Generator, fmt: int, channels: int) -> LslFrame:
    n = int(rng.integers(0, 40))
    ts = np.sort(rng.uniform(0, 1e6, n))
    dtype = FORMATS[fmt][1]
    if dtype is None:
        alphabet = ["a", "Z", " ", "\x00", "é", "🎭", "LSLc", ""]
        rows = tuple(tuple("".join(rng.choice(alphabet, int(rng.integers(0, 5)))) for _ in range(channels))
                     for _ in range(n))
        return LslFrame(fmt, channels, ts, rows)
    info = np.iinfo(dtype) if np.dtype(dtype).kind == "i" else None
    if info is not None:
        vals = rng.integers(info.min, info.max, (n, channels), dtype=np.int64, endpoint=True).astype(dtype)
    else:
        vals = rng.normal(0, 1e3, (n, channels)).astype(dtype)
    return LslFrame(fmt, channels, ts, vals)


def _same(a: LslFrame, b: LslFrame) -> bool:
    if (a.fmt, a.channels) != (b.fmt, b.channels) or not np.array_equal(a.timestamps, b.timestamps):
        return False
    if isinstance(a.values, tuple):
        return a.values == b.values
    return np.array_equal(np.asarray(a.values).reshape(-1, a.channels), np.asarray(b.values))


def _feed_chunked(codec: LslCodec, data: bytes, rng: np.random.Generator) -> list[LslFrame]:
    out: list[LslFrame] = []
    i = 0
    while i < len(data):
        k = int(rng.integers(1, 200)) if rng.random() < 0.7 else int(rng.integers(1, len(data) + 1))
        out += codec.feed(data[i:i + k])
        i += k
    return out


def test_random_chunkings_counts_channels_and_formats_decode_exactly():
    rng = np.random.default_rng(1818)
    for case in range(300):
        fmt = int(rng.choice(list(FORMATS)))
        channels = int(rng.integers(1, 33))
        frames = [_random_frame(rng, fmt, channels) for _ in range(int(rng.integers(1, 6)))]
        codec = LslCodec()
        data = b"".join(codec.encode(f) for f in frames)
        got = _feed_chunked(codec, data, rng)
        assert len(got) == len(frames) and all(_same(a, b) for a, b in zip(frames, got, strict=True)), case
        assert codec.stats.errors == 0 and codec.buffered == 0


def test_corrupted_frames_are_counted_and_lose_nothing_before_the_damage():
    rng = np.random.default_rng(1819)
    for case in range(300):
        fmt = int(rng.choice(list(FORMATS)))
        channels = int(rng.integers(1, 9))
        frames = [_random_frame(rng, fmt, channels) for _ in range(int(rng.integers(2, 6)))]
        blobs = [pack_frame(f.fmt, f.channels, f.timestamps, f.values) for f in frames]
        k = int(rng.integers(0, len(frames)))
        bad = bytearray(blobs[k])
        how = rng.choice(["flip", "truncate", "garbage", "header"])
        lost = [k]
        if how == "flip":
            for j in rng.integers(0, len(bad), int(rng.integers(1, 4))):
                bad[j] ^= int(rng.integers(1, 256))
        elif how == "header":
            bad[int(rng.integers(4, 24))] ^= 0xFF
        elif how == "truncate":
            del bad[int(rng.integers(1, len(bad))):]
        else:
            bad = bytearray(rng.integers(0, 256, int(rng.integers(1, 100)), dtype=np.uint8).tobytes()) + bad
            lost = []
        # the stream goes on after the damage: a frame cut short is known bad once as many bytes as it
        # claimed have come, and the frames held meanwhile are then recovered
        tail = [_random_frame(rng, fmt, channels) for _ in range(2)]
        while sum(len(codec_blob) for codec_blob in map(LslCodec().encode, tail)) < len(blobs[k]):
            tail.append(_random_frame(rng, fmt, channels))
        codec = LslCodec()
        data = b"".join(blobs[:k]) + bytes(bad) + b"".join(blobs[k + 1:]) + b"".join(map(codec.encode, tail))
        got = _feed_chunked(codec, data, rng)  # never raises
        want = [f for i, f in enumerate(frames) if i not in lost] + tail
        assert all(_same(a, b) for a, b in zip(frames[:k], got[:k], strict=True)), (case, how)
        assert len(got) == len(want) and all(_same(a, b) for a, b in zip(want, got, strict=True)), (case, how)
        assert codec.stats.errors >= 1 and codec.buffered == 0, (case, how)


def test_a_malformed_chunk_is_a_counted_protocol_error():
    dev = open_device(DeviceSpec(url="loop://", kind="lsl", name="x", options={"info": _xml(2, "double64")}))
    assert dev.streams[0].name == "x/test" and dev.streams[0].channels == ("c0", "c1")
    good = pack_frame(2, 2, [1.5, 1.505], np.array([[1.0, 2.0], [3.0, 4.0]]))
    items = dev.process_chunk(Chunk(good[:-1] + bytes([good[-1] ^ 1]), 10))
    assert any(isinstance(i, DeviceEvent) and i.kind is EventKind.PROTOCOL_ERRORS for i in items)
    assert not any(isinstance(i, Sample) for i in items)
    items = dev.process_chunk(Chunk(good, 20))
    samples = [i for i in items if isinstance(i, Sample)]
    assert [s.values for s in samples] == [(1.0, 2.0), (3.0, 4.0)]
    assert [s.t_device_ns for s in samples] == [1_500_000_000, 1_505_000_000]
    assert dev.codec.stats.errors == 1


def test_the_stream_suffix_option_and_the_kept_description():
    dev = open_device(DeviceSpec(url="loop://", kind="lsl", name="y", options={"info": _xml(1), "stream": "eeg"}))
    assert dev.streams[0].name == "y/eeg" and dev.device_options["info"] == _xml(1)
    assert dev.descriptors()["lsl.info"] == _xml(1).encode()
