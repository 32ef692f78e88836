"""Switch Pro Controller and Joy-Cons: the real Pro descriptor against the codec's report sizes,
encode/decode round trips, the handshake over USB and Bluetooth against the simulated controllers,
three IMU samples per 0x30 report at their own times (checked against the synthetic truth), the
timer wrap, dropped reports as gaps, the failure paths, and fuzzed reports counted, never raised."""

from __future__ import annotations

import json
import logging
import math
import re
from pathlib import Path

import numpy as np
import pytest
from hidtools.hid import ReportDescriptor
from hypothesis import given, settings
from hypothesis import strategies as st

from capture.clock import ManualClock
from capture.errors import DeviceInitError, DeviceTimeoutError, EndOfStream
from capture.sample import Chunk, Sample
from devices import open_device
from devices.codecs import nintendo as sw
from devices.codecs.nintendo import (
    FullReport,
    ImuCalibration,
    PadState,
    StickCalibration,
    SubcommandReply,
    SwitchCodec,
)
from sim_devices.nintendo_sim import switch_report_descriptor

TRACE = Path("/work/shared/traces/b_hid/android_cts/nintendo_switchpro_register.json")
G = 9.80665


def load_trace() -> dict:
    text = TRACE.read_text()
    return json.loads(re.sub(r"\b0x([0-9a-fA-F]+)\b", lambda m: str(int(m.group(1), 16)), text))


def run(url: str) -> tuple[object, list[Sample]]:
    dev = open_device(url)
    dev.open()
    out: list[Sample] = []
    try:
        while True:
            out += [x for x in dev.poll(0.1) if isinstance(x, Sample)]
    except EndOfStream:
        pass
    return dev, out


# -- descriptor -----------------------------------------------------------------------------------
@pytest.mark.skipif(not TRACE.exists(),
                    reason="Switch Pro trace not found (../shared/traces must sit beside the project)")
def test_real_pro_descriptor_report_sizes_match_the_codec():
    tr = load_trace()
    assert (tr["vid"], tr["pid"]) == (0x057E, 0x2009)
    rd = ReportDescriptor.from_bytes(bytes(tr["descriptor"]))
    assert rd.input_reports[sw.IN_FULL].size == sw.REPORT_LEN
    assert rd.input_reports[sw.IN_SUBCMD_REPLY].size == sw.REPORT_LEN
    assert rd.input_reports[sw.IN_SIMPLE].size == sw.SIMPLE_LEN
    assert rd.output_reports[sw.OUT_RUMBLE_SUBCMD].size == len(sw.subcommand_report(0, sw.SC_DEVICE_INFO))
    # the synthetic stubs of the trace use the documented output layout: subcommand at byte 10
    checked = 0
    for o in tr["outputs"]:
        out = bytes(o["output"])
        if out[0] != sw.OUT_RUMBLE_SUBCMD or len(o.get("response", [])) < 15:
            continue  # rumble-only (0x10) or no reply
        parsed = sw.parse_subcommand(out)
        assert parsed is not None and parsed[1] == o["response"][14]
        checked += 1
    assert checked >= 5


@pytest.mark.parametrize("usb", [False, True])
def test_sim_descriptor_parses_and_matches_the_codec(usb):
    rd = ReportDescriptor.from_bytes(switch_report_descriptor(usb))
    n = sw.USB_REPORT_LEN if usb else sw.REPORT_LEN
    assert rd.input_reports[sw.IN_FULL].size == n
    assert rd.input_reports[sw.IN_SUBCMD_REPLY].size == n
    assert rd.input_reports[sw.IN_SIMPLE].size == sw.SIMPLE_LEN
    assert rd.output_reports[sw.OUT_RUMBLE_SUBCMD].size == sw.REPORT_LEN
    assert (sw.IN_USB_REPLY in rd.input_reports) == usb


# -- round trips ----------------------------------------------------------------------------------
u12 = st.integers(0, 0xFFF)
s16 = st.integers(-32768, 32767)
states = st.builds(PadState, st.integers(0, 255), st.integers(0, 15), st.integers(0, 15), st.integers(0, 0xFFFFFF),
                   st.tuples(u12, u12), st.tuples(u12, u12), st.integers(0, 255))


@settings(max_examples=150, deadline=None)
@given(states, st.tuples(*[st.tuples(*[s16] * 6)] * 3), st.booleans())
def test_full_report_round_trip(state, imu, usb):
    c = SwitchCodec()
    data = c.encode(FullReport(state, imu, usb))
    assert len(data) == (64 if usb else 49) and data[0] == 0x30
    assert c.feed(data) == [FullReport(state, imu, usb)]


@settings(max_examples=100, deadline=None)
@given(states, st.integers(0, 255), st.integers(0, 255), st.binary(max_size=34))
def test_subcommand_reply_round_trip(state, ack, sc, data):
    c = SwitchCodec()
    (rep,) = c.feed(c.encode(SubcommandReply(state, ack, sc, data)))
    assert (rep.state, rep.ack, rep.subcommand, rep.data) == (state, ack, sc, data.ljust(34, b"\0"))


@settings(max_examples=100, deadline=None)
@given(st.tuples(*[st.integers(-32768, 32767)] * 12))
def test_imu_calibration_bytes_round_trip(v):
    cal = ImuCalibration(v[0:3], v[3:6], v[6:9], v[9:12])
    assert ImuCalibration.from_bytes(cal.to_bytes()) == cal


@settings(max_examples=100, deadline=None)
@given(st.tuples(u12, u12), st.tuples(u12, u12), st.tuples(u12, u12), st.booleans())
def test_stick_calibration_bytes_round_trip(c, a, b, left):
    cal = StickCalibration(c, a, b)
    raw = cal.to_bytes(left)
    assert len(raw) == 9 and StickCalibration.from_bytes(raw, left) == cal


def test_calibration_formulas():
    nominal = ImuCalibration()
    # 4096 counts are 1 g at the nominal +-8 g range; 1 gyro count is 936/13371 = 0.07 deg/s
    si = nominal.to_si((4096, 0, -4096, 1, 0, -13371))
    assert si[0] == pytest.approx(G) and si[2] == pytest.approx(-G)
    assert si[3] == pytest.approx(math.radians(936 / 13371))
    assert si[5] == pytest.approx(-math.radians(936))
    cal = ImuCalibration((100, 0, 0), (16484, 16384, 16384), (20, 0, 0), (13391, 13371, 13371))
    a = cal.to_si((4096, 0, 0, 20 + 13371, 0, 0))
    assert a[0] == pytest.approx(4096 * 4 * G / 16384)       # raw * 4 g / (sens - origin)
    assert a[3] == pytest.approx(math.radians(936.0))       # (raw - origin) * 936 / (sens - origin)
    assert cal.from_si(a[:3], a[3:]) == (4096, 0, 0, 20 + 13371, 0, 0)
    assert not ImuCalibration.from_bytes(b"\xff" * 24).valid()


def test_stick_normalise():
    cal = StickCalibration((2000, 2100), (1500, 1400), (1000, 1200))
    assert cal.normalise((3500, 2100)) == (1.0, 0.0)
    assert cal.normalise((1000, 900)) == (-1.0, -1.0)
    assert cal.normalise((4095, 0)) == (1.0, -1.0)  # clipped
    assert cal.normalise(cal.raw((0.25, -0.5))) == pytest.approx((0.25, -0.5), abs=1e-3)


# -- handshake -------------------------------------------------------------------------------------
def subcommands_sent(responder) -> list[tuple[int, bytes]]:
    out = []
    for kind, data in responder.received:
        p = sw.parse_subcommand(data) if kind == "output" else None
        if p is not None:
            out.append((p[1], p[2][:5] if p[1] == sw.SC_SPI_READ else p[2][:1]))
    return out


EXPECTED = [
    (sw.SC_DEVICE_INFO, b"\0"),
    (sw.SC_SPI_READ, sw.spi_read_args(0x6020, 24)),
    (sw.SC_SPI_READ, sw.spi_read_args(0x8026, 26)),
    (sw.SC_SPI_READ, sw.spi_read_args(0x603D, 18)),
    (sw.SC_SPI_READ, sw.spi_read_args(0x6080, 6)),
    (sw.SC_SPI_READ, sw.spi_read_args(0x6086, 18)),
    (sw.SC_ENABLE_IMU, b"\x01"),
    (sw.SC_SET_MODE, b"\x30"),
]


@pytest.mark.parametrize("bus", ["usb", "bluetooth"])
def test_handshake_sequence(bus):
    dev = open_device(f"pad=switchpro@simhid://switchpro?realtime=false&bus={bus}")
    dev.open()
    r = dev.transport.responder
    outs = [d for k, d in r.received if k == "output"]
    usb_cmds = [d[1] for d in outs if d[0] == sw.OUT_USB_CMD]
    if bus == "usb":
        assert usb_cmds == [0x01, 0x02, 0x03, 0x02, 0x04]
        assert all(d[0] == sw.OUT_USB_CMD for d in outs[:5])  # before any subcommand
    else:
        assert usb_cmds == []
    assert subcommands_sent(r) == EXPECTED
    counters = [d[1] for d in outs if d[0] == sw.OUT_RUMBLE_SUBCMD]
    assert counters == [i & 0xF for i in range(len(EXPECTED))]  # the 4-bit global packet counter
    assert dev.imu_cal == r.factory_cal and dev.imu_cal_source == "factory"
    assert dev.sticks_cal == r.stick_cal
    assert dev.info.mac == r.mac and dev.info.type == sw.TYPE_PRO
    dev.close()


def test_user_calibration_is_used_when_present():
    dev, samples = run("pad=switchpro@simhid://switchpro?realtime=false&bus=bluetooth&user_cal=true&duration=0.3")
    r = dev.transport.responder
    assert dev.imu_cal_source == "user" and dev.imu_cal == r.user_cal != r.factory_cal
    check_against_truth(r, [s for s in samples if s.stream == "pad/imu"], r.user_cal)


# -- motion, time ---------------------------------------------------------------------------------
def check_against_truth(responder, imu: list[Sample], cal: ImuCalibration) -> None:
    t = np.array([s.t_device_ns for s in imu]) / 1e9
    got = np.array([s.values for s in imu])
    acc, gyro = responder.truth(t)
    # within half a count (plus float noise) at each sample's own device time
    assert np.all(np.abs(got[:, :3] - acc) <= np.array(cal.acc_scale()) * 0.5 + 1e-9)
    assert np.all(np.abs(got[:, 3:] - gyro) <= np.array(cal.gyro_scale()) * 0.5 + 1e-9)


@pytest.mark.parametrize("bus", ["usb", "bluetooth"])
def test_motion_three_samples_per_report_at_their_own_times(bus):
    dev, samples = run(f"pad=switchpro@simhid://switchpro?realtime=false&bus={bus}&duration=3&seed=4")
    r = dev.transport.responder
    imu = [s for s in samples if s.stream == "pad/imu"]
    sticks = [s for s in samples if s.stream == "pad/sticks"]
    assert len(imu) == 3 * len(sticks) and len(sticks) == 199
    # three per report (same arrival), 5 ms apart, the last one at the report's own device time
    by_arrival: dict[int, list[Sample]] = {}
    for s in imu:
        by_arrival.setdefault(s.t_host_ns, []).append(s)
    assert all(len(g) == 3 for g in by_arrival.values())
    stick_dev = {s.t_host_ns: s.t_device_ns for s in sticks}
    for host, g in by_arrival.items():
        assert [s.t_device_ns - g[0].t_device_ns for s in g] == [0, 5_000_000, 10_000_000]
        assert g[-1].t_device_ns == stick_dev[host]
    dts = np.diff([s.t_device_ns for s in imu])
    assert np.all(dts == 5_000_000)  # 3 s: the 8-bit timer wrapped twice without a jump
    assert imu[-1].t_device_ns > 2 * 256 * 5_000_000
    assert [s.seq for s in imu] == list(range(len(imu)))
    assert all(np.diff([s.t_bus_ns for s in imu]) >= 0)
    check_against_truth(r, imu, r.factory_cal)
    # never averaged: the mean of a report's three samples misses the truth at the report time
    g = np.array([[s.values for s in grp] for grp in by_arrival.values()])
    t_rep = np.array([grp[-1].t_device_ns for grp in by_arrival.values()]) / 1e9
    _, gyro = r.truth(t_rep)
    assert np.max(np.abs(g[:, :, 3:].mean(axis=1) - gyro)) > 10 * max(r.factory_cal.gyro_scale())
    assert dev.stats.lost_readings == 0 and dev.codec.stats.errors == 0


def test_dropped_reports_are_gaps():
    dev, samples = run("pad=switchpro@simhid://switchpro?realtime=false&bus=bluetooth&duration=1.5&drop_every=7")
    imu = [s for s in samples if s.stream == "pad/imu"]
    dts = np.diff([s.t_device_ns for s in imu])
    dropped = int(np.sum(dts == 20_000_000))
    assert dropped >= 13 and set(dts.tolist()) == {5_000_000, 20_000_000}
    assert dev.stats.lost_readings == 5 * dropped  # per drop: 3 IMU samples, 1 sticks and 1 buttons reading
    seqs = [s.seq for s in imu]
    assert seqs[-1] == len(imu) - 1 + 3 * dropped
    check_against_truth(dev.transport.responder, imu, dev.transport.responder.factory_cal)


def test_overlapping_reports_are_not_repeated():
    dev = open_device("pad=switchpro@simhid://switchpro?realtime=false&bus=bluetooth")
    dev.open()
    r = dev.transport.responder
    a, b = r.full_report(0.300), r.full_report(0.305)  # 5 ms apart: two of three samples repeat
    n1 = [x for x in dev.process_chunk(Chunk(a, 10**9)) if isinstance(x, Sample) and x.stream == "pad/imu"]
    n2 = [x for x in dev.process_chunk(Chunk(b, 10**9 + 5_000_000)) if isinstance(x, Sample) and x.stream == "pad/imu"]
    assert len(n1) == 3 and len(n2) == 1 and dev.overlapping_samples == 2
    assert n2[0].t_device_ns - n1[-1].t_device_ns == 5_000_000


def test_joycons_left_and_right_read_the_same_motion():
    dl, sl = run("j=joycon@simhid://joycon_l?realtime=false&bus=bluetooth&duration=0.6&seed=3")
    dr, sr = run("j=joycon@simhid://joycon_r?realtime=false&bus=bluetooth&duration=0.6&seed=3")
    assert (dl.side, dr.side) == ("left", "right")
    il = [s for s in sl if s.stream == "j/imu"]
    ir = [s for s in sr if s.stream == "j/imu"]
    assert len(il) == len(ir) > 100
    assert [s.t_device_ns for s in il] == [s.t_device_ns for s in ir]
    check_against_truth(dl.transport.responder, il, dl.imu_cal)
    check_against_truth(dr.transport.responder, ir, dr.imu_cal)
    # the right one's raw y, z are the negatives of the left one's: same values after the remap
    assert np.allclose([s.values for s in il], [s.values for s in ir], atol=0.01)
    sticks = [s for s in sr if s.stream == "j/sticks"]
    assert len(sticks[0].values) == 2 and all(-1 <= v <= 1 for s in sticks for v in s.values)


def test_joycon_side_checks():
    with pytest.raises(DeviceInitError, match="not a Joy-Con"):
        open_device("j=joycon@simhid://switchpro?realtime=false&bus=bluetooth").open()
    with pytest.raises(DeviceInitError, match="side=left"):
        open_device("j=joycon@simhid://joycon_r?realtime=false&bus=bluetooth&side=left").open()
    with pytest.raises(DeviceInitError, match="use kind joycon"):
        open_device("p=switchpro@simhid://joycon_l?realtime=false&bus=bluetooth").open()


# -- failures ------------------------------------------------------------------------------------
@pytest.mark.parametrize("bus", ["usb", "bluetooth"])
def test_silent_controller_times_out_bounded(bus):
    clock = ManualClock()  # moves only when the handshake waits (a timed read jumps to its deadline)
    dev = open_device(f"pad=switchpro@simhid://switchpro?realtime=true&bus={bus}&handshake=silent&reply_timeout=0.1",
                      clock=clock)
    t0 = clock.now_ns()
    with pytest.raises(DeviceTimeoutError, match="no answer to" if bus == "bluetooth" else "0x80 0x01"):
        dev.open()
    assert clock.now_ns() - t0 == pytest.approx(2 * 100_000_000, abs=1_000_000)  # 2 attempts x 0.1 s


@pytest.mark.parametrize("mode,match", [("wrong", r"only ever answered with replies to other subcommands \(0x03\)"),
                                        ("wrong_spi", r"SPI read of factory IMU calibration at 0x6020 .* 0x6030"),
                                        ("nack", r"device info \(0x02\) was refused \(NACK")])
def test_wrong_answers_are_named(mode, match):
    clock = ManualClock()  # moves only when the handshake waits (a timed read jumps to its deadline)
    dev = open_device(f"pad=switchpro@simhid://switchpro?realtime=true&bus=bluetooth&handshake={mode}"
                      "&reply_timeout=0.5&retries=1", clock=clock)
    t0 = clock.now_ns()
    with pytest.raises(DeviceInitError, match=match):
        dev.open()
    # bounded: a wrong reply is skipped while the right one may still come, for at most the retries
    assert clock.now_ns() - t0 <= 2 * 500_000_000 + 1_000_000  # (retries + 1) x reply_timeout


def test_blank_calibration_falls_back_to_nominal_with_warnings(caplog):
    with caplog.at_level(logging.WARNING, logger="devices.hid.nintendo"):
        dev, samples = run("pad=switchpro@simhid://switchpro?realtime=false&bus=bluetooth"
                           "&handshake=blank_calibration&duration=0.3")
    assert dev.imu_cal == ImuCalibration() and dev.imu_cal_source == "nominal"
    assert dev.calibration_fallbacks == 3  # IMU, left stick, right stick
    assert "blank (all 0xFF)" in caplog.text and "using nominal values" in caplog.text
    assert dev.health()["calibration_fallbacks"] == 3
    check_against_truth(dev.transport.responder, [s for s in samples if s.stream == "pad/imu"], ImuCalibration())


# -- fuzz --------------------------------------------------------------------------------------------
@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=70))
def test_fuzzed_reports_never_raise(data):
    c = SwitchCodec()
    frames = c.feed(data)
    assert len(frames) + c.stats.errors == 1  # an empty report is counted too


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 48), st.binary(min_size=0, max_size=70))
def test_truncated_and_fuzzed_reports_through_the_device_are_counted(cut, junk):
    dev = open_device("pad=switchpro@simhid://switchpro?realtime=false&bus=bluetooth")
    dev.open()
    good = dev.transport.responder.full_report(0.3)
    dev.process_chunk(Chunk(good[:cut], 10**9))
    assert dev.codec.stats.framing_errors == 1
    dev.process_chunk(Chunk(junk, 10**9 + 1))
    out = dev.process_chunk(Chunk(good, 10**9 + 2))
    assert len([x for x in out if isinstance(x, Sample) and x.stream == "pad/imu"]) in (0, 1, 2, 3)
