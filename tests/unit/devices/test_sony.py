"""Sony DualShock 4 and DualSense: the real report descriptors and calibration feature reports
(Android CTS traces), the calibration maths, encode/decode round trips, corrupt and fuzzed reports,
synthetic motion through ``simhid://`` over USB and Bluetooth, handshake failures, and bus-time
accuracy from the pad's sensor timestamps."""

from __future__ import annotations

import json
import logging
import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from capture.clock import ManualClock
from capture.errors import DeviceInitError, DeviceTimeoutError, ProtocolError
from capture.orientation import check_imu_stream
from capture.sample import DeviceChunk, Sample
from devices import open_device
from devices.codecs.sony import (
    BLUETOOTH,
    DS4_TICK_HZ,
    DS_TICK_HZ,
    USB,
    DualSenseCodec,
    DualShock4Codec,
    ImuCalibration,
    PadReport,
    TouchPoint,
    crc32,
    encode_calibration,
    parse_calibration,
)
from devices.hid.sony import REDUCED_PER_S, DualSense, DualShock4

hidtools_hid = pytest.importorskip("hidtools.hid")

TRACES = Path(__file__).resolve().parents[3] / ".." / "shared" / "traces" / "b_hid" / "android_cts"
G = 9.80665


def load_trace(name: str) -> dict:
    path = TRACES / name
    if not path.is_file():
        pytest.skip(f"trace not found at {path} (../shared/traces must sit beside the project)")
    text = path.read_text()
    return json.loads(re.sub(r"\b0x([0-9a-fA-F]+)\b", lambda m: str(int(m.group(1), 16)), text))


def feature(trace: dict, rid: int) -> bytes:
    return bytes(next(f["data"] for f in trace["feature_reports"] if f["id"] == rid))


@pytest.fixture(scope="module")
def ds4_trace() -> dict:
    return load_trace("sony_dualshock4_usb_register.json")


@pytest.fixture(scope="module")
def ds_trace() -> dict:
    return load_trace("sony_dualsense_usb_register.json")


# -- real descriptors and calibration -------------------------------------------------------------
def test_real_descriptors_give_the_report_sizes_the_codecs_expect(ds4_trace, ds_trace):
    rd = hidtools_hid.ReportDescriptor.from_bytes(ds4_trace["descriptor"])
    assert len(ds4_trace["descriptor"]) == 483
    assert rd.input_reports[0x01].size == DualShock4Codec.full_len == 64
    assert rd.feature_reports[0x02].size == 37 == len(feature(ds4_trace, 0x02))
    rd = hidtools_hid.ReportDescriptor.from_bytes(ds_trace["descriptor"])
    assert len(ds_trace["descriptor"]) == 257
    assert rd.input_reports[0x01].size == DualSenseCodec.full_len == 64
    assert rd.feature_reports[0x05].size == 41 == len(feature(ds_trace, 0x05))


@pytest.mark.parametrize(("name", "bus", "inputs", "features"), [
    ("ds4", USB, {0x01: 64}, {0x02: 37}),
    ("ds4", BLUETOOTH, {0x01: 10, 0x11: 78}, {0x05: 41}),
    ("dualsense", USB, {0x01: 64}, {0x05: 41}),
    ("dualsense", BLUETOOTH, {0x01: 10, 0x31: 78}, {0x05: 41}),
])
def test_simulated_descriptors_parse_and_match_the_protocol(name, bus, inputs, features):
    from sim_devices.sony_sim import ds4_descriptor, dualsense_descriptor
    blob = (ds4_descriptor if name == "ds4" else dualsense_descriptor)(bus)
    rd = hidtools_hid.ReportDescriptor.from_bytes(list(blob))
    for rid, size in inputs.items():
        assert rd.input_reports[rid].size == size
    for rid, size in features.items():
        assert rd.feature_reports[rid].size == size


def test_ds4_real_calibration_gives_readme_values_and_kernel_scales(ds4_trace):
    raw = feature(ds4_trace, 0x02)
    cal = parse_calibration(raw, "ds4", USB)
    assert cal.gyro_bias == (-8, -3, -7)
    assert (cal.gyro_plus, cal.gyro_minus) == ((8671, 8853, 9202), (-8719, -8857, -9188))
    assert (cal.speed_plus, cal.speed_minus) == (540, 540)
    assert (cal.acc_plus, cal.acc_minus) == ((8106, 8439, 8202), (-8106, -8440, -8201))
    sc = cal.scale()
    assert sc.fallback == ()
    # gyro: speed_2x / (|plus - bias| + |minus - bias|) deg/s per count
    dps = [math.degrees(g) for g in sc.gyro]
    assert dps[0] == pytest.approx(1080 / (8679 + 8711))
    assert dps[1] == pytest.approx(1080 / (8856 + 8854))
    assert dps[2] == pytest.approx(1080 / (9209 + 9181))
    assert all(1 / 17.5 < d < 1 / 15.5 for d in dps)  # about 1/16 deg/s per count, +-2000 deg/s range
    # accel: +-1 g references span 2 g; a reading at the + reference is exactly 1 g
    assert sc.acc[0] == pytest.approx(2 * G / 16212)
    for i in range(3):
        assert (cal.acc_plus[i] - sc.acc_bias[i]) * sc.acc[i] == pytest.approx(G)
        assert (cal.acc_minus[i] - sc.acc_bias[i]) * sc.acc[i] == pytest.approx(-G)
    # encoding is the inverse; the first 35 bytes (the 17 values) are byte-identical
    enc = encode_calibration(cal, "ds4", USB)
    assert enc[:35] == raw[:35] and len(enc) == len(raw)
    assert parse_calibration(enc, "ds4", USB) == cal


def test_dualsense_real_calibration_gives_readme_values(ds_trace):
    raw = feature(ds_trace, 0x05)
    cal = parse_calibration(raw, "dualsense", USB)
    flat = (*cal.gyro_bias, *(x for pm in zip(cal.gyro_plus, cal.gyro_minus, strict=True) for x in pm), cal.speed_plus,
            cal.speed_minus, *(x for pm in zip(cal.acc_plus, cal.acc_minus, strict=True) for x in pm))
    assert flat == (-1, -14, 4, 8861, -8866, 8850, -8878, 8890, -8879, 540, 540, 8187, -8187, 8067, -8295, 8199, -8196)
    sc = cal.scale()
    assert math.degrees(sc.gyro[0]) == pytest.approx(1080 / (8862 + 8865))
    assert sc.acc_bias[1] == pytest.approx(8067 - (8067 + 8295) / 2)
    enc = encode_calibration(cal, "dualsense", USB)
    assert enc[:35] == raw[:35] and len(enc) == len(raw)  # byte 35 on is not calibration


@pytest.mark.parametrize("model", ["ds4", "dualsense"])
def test_bluetooth_calibration_has_crc_and_ds4_reorders_references(ds4_trace, model):
    cal = parse_calibration(feature(ds4_trace, 0x02), "ds4", USB)
    bt = encode_calibration(cal, model, BLUETOOTH)
    assert bt[0] == 0x05 and len(bt) == 41
    assert int.from_bytes(bt[-4:], "little") == crc32(0xA3, bt[:-4])
    assert parse_calibration(bt, model, BLUETOOTH) == cal
    if model == "ds4":  # Bluetooth: pitch+, yaw+, roll+, pitch-, yaw-, roll-
        assert int.from_bytes(bt[9:11], "little", signed=True) == cal.gyro_plus[1]
    bad = bytearray(bt)
    bad[5] ^= 1
    with pytest.raises(ProtocolError, match="CRC"):
        parse_calibration(bytes(bad), model, BLUETOOTH)


def test_wrong_calibration_answers_are_named(ds4_trace):
    raw = feature(ds4_trace, 0x02)
    with pytest.raises(ProtocolError, match="report ID 0x05"):
        parse_calibration(b"\x05" + raw[1:], "ds4", USB)
    with pytest.raises(ProtocolError, match="20 bytes, expected 37"):
        parse_calibration(raw[:20], "ds4", USB)
    with pytest.raises(ProtocolError, match="empty"):
        parse_calibration(b"", "dualsense", USB)


def test_degenerate_calibration_falls_back_to_nominal_with_a_warning(caplog):
    cal = ImuCalibration((0, 0, 0), (8640, 0, 0), (-8640, 0, 0), 540, 540, (8192, 0, 0), (-8192, 0, 0))
    sc = cal.scale()
    assert sc.fallback == ("gyro y", "accel y", "gyro z", "accel z")
    assert math.degrees(sc.gyro[0]) == pytest.approx(1 / 16)  # the valid axis keeps its calibration
    assert math.degrees(sc.gyro[1]) == pytest.approx(2000 / 32768)
    assert sc.acc[2] == pytest.approx(G / 8192) and sc.acc_bias[2] == 0.0
    assert sc.acc[0] == pytest.approx(G / 8192)  # the valid axis keeps its calibration
    d = open_device("pad=simhid://dualsense?realtime=false&calibration=degenerate")
    with caplog.at_level(logging.WARNING, logger="devices.hid.sony"):
        d.open()
    try:
        assert "degenerate IMU calibration" in caplog.text and "nominal" in caplog.text
        assert d.health()["calibration_fallbacks"] == 1
        samples = run(d, 250)
        check_truth(d, samples, 1.0)
    finally:
        d.close()


# -- codec ----------------------------------------------------------------------------------------
u8 = st.integers(0, 255)
s16 = st.integers(-32768, 32767)
s16x3 = st.tuples(s16, s16, s16)
touch = st.builds(TouchPoint, st.booleans(), st.integers(0, 127), st.integers(0, 4095), st.integers(0, 4095))


def reports(model: str) -> st.SearchStrategy[PadReport]:
    nbits = 14 if model == "ds4" else 15
    return st.builds(
        PadReport, st.sampled_from([USB, BLUETOOTH]), st.tuples(u8, u8, u8, u8), st.tuples(u8, u8),
        st.integers(0, (1 << nbits) - 1), st.integers(0, 8), s16x3, s16x3,
        st.integers(0, 0xFFFF if model == "ds4" else 0xFFFFFFFF), u8, st.tuples(touch, touch),
        st.integers(0, 0x3F if model == "ds4" else 0xFF), u8 if model == "ds4" else st.just(0))


@pytest.mark.parametrize("codec_cls", [DualShock4Codec, DualSenseCodec])
@settings(max_examples=150, deadline=None)
@given(data=st.data())
def test_encode_decode_round_trip(codec_cls, data):
    f = data.draw(reports(codec_cls.model))
    c = codec_cls()
    wire = c.encode(f)
    assert len(wire) == (64 if f.bus == USB else 78)
    assert wire[0] == (0x01 if f.bus == USB else codec_cls.bt_id)
    assert c.feed(wire) == [f]
    assert c.stats.frames == 1 and c.stats.errors == 0 and c.bus_seen == f.bus


@pytest.mark.parametrize("codec_cls", [DualShock4Codec, DualSenseCodec])
def test_bad_crc_truncated_unknown_and_reduced_are_counted(codec_cls):
    c = codec_cls()
    f = PadReport(BLUETOOTH, (1, 2, 3, 4), (5, 6), 3, 8, (1, -2, 3), (-4, 5, -6), 1234)
    good = c.encode(f)
    bad = bytearray(good)
    bad[20] ^= 0x10
    assert c.feed(bytes(bad)) == []
    assert c.stats.checksum_errors == 1
    assert c.feed(good[:40]) == [] and c.feed(b"\x42" + bytes(63)) == [] and c.feed(b"") == []
    assert c.stats.framing_errors == 3
    assert c.feed(c.encode_reduced(f)) == [] and c.stats.reduced_reports == 1
    assert c.feed(good) == [f] and c.stats.frames == 1
    strict = codec_cls(strict=True)
    with pytest.raises(ProtocolError, match="CRC32"):
        strict.feed(bytes(bad))


@pytest.mark.parametrize("codec_cls", [DualShock4Codec, DualSenseCodec])
@settings(max_examples=300, deadline=None)
@given(blob=st.binary(max_size=100), rid=st.sampled_from([0x01, 0x11, 0x31, None]))
def test_fuzzed_reports_never_raise(codec_cls, blob, rid):
    c = codec_cls()
    data = blob if rid is None else bytes((rid,)) + blob
    frames = c.feed(data)
    assert len(frames) <= 1
    assert c.stats.frames + c.stats.errors + c.stats.reduced_reports == 1


# -- through simhid:// ----------------------------------------------------------------------------
def run(d, n_reports: int) -> list[tuple[bytes, list[Sample]]]:
    """Poll until ``n_reports`` RX chunks; returns (report, its samples) pairs."""
    out: list[tuple[bytes, list[Sample]]] = []
    while len(out) < n_reports:
        for it in d.poll(0.1):
            if isinstance(it, DeviceChunk):
                out.append((it.chunk.data, []))
            elif isinstance(it, Sample):
                out[-1][1].append(it)
    return out


def imu_of(pairs, name="pad") -> list[Sample]:
    return [s for _, ss in pairs for s in ss if s.stream == f"{name}/imu"]


def check_truth(d, pairs, slack: float = 0.51) -> None:
    """Every IMU sample equals the responder's true motion at its device time within ``slack`` counts."""
    resp = d.transport.responder
    imu = imu_of(pairs)
    assert len(imu) == len(pairs)
    t = np.array([round(s.t_device_ns / 1e9 * 250) / 250 for s in imu])
    assert np.allclose(t * 1e9, [s.t_device_ns for s in imu], atol=6e3)  # the tick rounding only
    gyro, acc = resp.truth(t)
    vals = np.array([s.values for s in imu])
    sc = d.scale
    assert np.all(np.abs(vals[:, 3:] - gyro) <= slack * np.array(sc.gyro))
    assert np.all(np.abs(vals[:, :3] - acc) <= slack * np.array(sc.acc))


@pytest.mark.parametrize("kind", ["ds4", "dualsense"])
@pytest.mark.parametrize("bus", [USB, BLUETOOTH])
def test_synthetic_motion_decodes_to_truth(kind, bus):
    d = open_device(f"pad=simhid://{kind}?realtime=false&bus={bus}&seed=3")
    assert isinstance(d, DualShock4 if kind == "ds4" else DualSense)
    d.open()
    try:
        assert d.bus_kind == bus
        assert d.calibration == d.transport.responder.calibration
        pairs = run(d, 600)  # 2.4 s: several DS4 timestamp wraps
        check_truth(d, pairs)
        assert pairs[0][0][0] == (0x01 if bus == USB else {"ds4": 0x11, "dualsense": 0x31}[kind])
        h = d.health()
        assert h["checksum_errors"] == h["framing_errors"] == h["lost_readings"] == h["clock_resets"] == 0
        # gravity on +y when level-ish: mean specific force ~ 1 g, mostly along y
        vals = np.array([s.values for s in imu_of(pairs)])
        assert np.linalg.norm(vals[:, :3], axis=1).mean() == pytest.approx(G, rel=0.15)
        assert vals[:, 1].mean() > 0.7 * G
        info = d.streams[0]
        check_imu_stream(info)
        assert info.clock.tick_hz == (DS4_TICK_HZ if kind == "ds4" else DS_TICK_HZ)
        sticks = [s.values for _, ss in pairs for s in ss if s.stream == "pad/sticks"]
        assert all(-1 <= v <= 1 for row in sticks for v in row)
        touch = [s.values for _, ss in pairs for s in ss if s.stream == "pad/touch"]
        assert any(r[0] == 1.0 for r in touch) and any(r[0] == 0.0 for r in touch)
        buttons = [s.values for _, ss in pairs for s in ss if s.stream == "pad/buttons"]
        assert {r[1] for r in buttons} == {0.0, 1.0}  # cross toggles every 0.5 s
        assert 0 < buttons[0][-2] <= 100
    finally:
        d.close()


def test_descriptors_and_calibration_are_kept_for_sessions():
    d = open_device("pad=simhid://ds4?realtime=false&bus=bluetooth")
    d.open()
    try:
        desc = d.descriptors()
        assert "hid.report_descriptor" in desc and "hid.feature.05" in desc
        assert parse_calibration(desc["hid.feature.05"], "ds4", BLUETOOTH) == d.calibration
    finally:
        d.close()


# -- handshake failures -----------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["ds4", "dualsense"])
def test_silent_pad_over_usb_fails_clearly(kind):
    clock = ManualClock()  # moves only when the handshake waits (a timed read jumps to its deadline)
    d = open_device(f"pad=simhid://{kind}?realtime=true&handshake=silent", clock=clock)
    t0 = clock.now_ns()
    with pytest.raises(DeviceInitError, match="did not answer the calibration feature report"):
        d.open()
    assert clock.now_ns() == t0  # a refused feature report fails at once, without waiting
    d.close()


@pytest.mark.parametrize("kind", ["ds4", "dualsense"])
@pytest.mark.parametrize("realtime", ["false", "true"])
def test_silent_pad_over_bluetooth_times_out_waiting_for_full_reports(kind, realtime):
    clock = ManualClock()  # moves only when the handshake waits (a timed read jumps to its deadline)
    d = open_device(f"pad=simhid://{kind}?realtime={realtime}&bus=bluetooth&handshake=silent&init_timeout=0.3",
                    clock=clock)
    t0 = clock.now_ns()
    with pytest.raises(DeviceTimeoutError, match="reduced reports") as ei:
        d.open()
    # bounded by init_timeout (on the device's clock) or by the reduced reports that many seconds bring
    assert clock.now_ns() - t0 <= 300_000_000
    seen = int(re.search(r"(\d+) seen", str(ei.value)).group(1))
    assert 0 < seen <= max(25, int(REDUCED_PER_S * 0.3))
    d.close()


@pytest.mark.parametrize("kind", ["ds4", "dualsense"])
@pytest.mark.parametrize(("bus", "what"), [(USB, "20 bytes, expected"), (BLUETOOTH, "bad CRC32")])
def test_wrong_answer_names_the_problem(kind, bus, what):
    d = open_device(f"pad=simhid://{kind}?realtime=false&bus={bus}&handshake=wrong")
    with pytest.raises(DeviceInitError, match=what):
        d.open()
    d.close()


# -- bus time -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["ds4", "dualsense"])
def test_sensor_timestamps_recover_bus_times_under_jitter(kind):
    drift, latency = 80.0, 0.5
    d = open_device(f"pad=simhid://{kind}?realtime=false&jitter_ms=4&truth=true&drift_ppm={drift}"
                    f"&latency_ms={latency}&seed=5")
    d.open()
    try:
        pairs = run(d, 2500)  # 10 s
    finally:
        d.close()
    imu = imu_of(pairs)
    tr = d.transport
    truth = np.array(tr.truth_ns, np.int64)      # when the pad sent each report, on the host clock
    arrival = np.array(tr.arrival_ns, np.int64)  # when it arrived: + latency + 0..4 ms jitter
    assert truth.size == arrival.size == len(imu)
    late = arrival - truth - latency * 1e6
    assert late.min() >= 0 and late.max() <= 4e6 and np.percentile(late, 99) > 3e6
    # the sensor timestamps advance with device time: truth steps are 4 ms shortened by the drift
    assert np.median(np.diff(truth)) == pytest.approx(4e6 / (1 + drift * 1e-6), abs=2)
    bus = np.array([s.t_bus_ns for s in imu])
    assert np.all(bus <= np.array([s.t_host_ns for s in imu]))
    # the lower envelope carries the fixed link latency; after 1 s of fit the rest is gone
    err = np.abs(bus - latency * 1e6 - truth)[250:]
    assert np.percentile(err, 99) < 0.5e6
    raw_err = np.abs(arrival - latency * 1e6 - truth)[250:]
    assert np.percentile(raw_err, 99) > 3e6  # what the arrival times alone would give
