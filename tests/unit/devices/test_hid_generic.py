"""Descriptor-driven HID decoding (mice, pens, touch) against real traces: a hid-recorder capture,
real game-controller descriptors from the Android CTS, and evemu recordings replayed through the
simulated devices. Traces are read in place from ``../shared/traces``."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from capture.errors import (
    ConfigError,
    DeviceInitError,
    EndOfStream,
    ProtocolError,
    TraceError,
)
from capture.sample import Sample
from devices import open_device
from devices.hid.descriptor import (
    STANDARD_DESCRIPTORS,
    HidReportCodec,
    parse_descriptor,
)
from sim_devices import evemu
from sim_devices.hid_recorder import parse_hid_recording

TRACES = Path(__file__).resolve().parents[3].parent / "shared" / "traces"
B_HID = TRACES / "b_hid"
EVEMU = TRACES / "f_pen_mouse_touch" / "evemu"
ROLLER = B_HID / "hid_recorder" / "contour_rollermouse_red_doubleclick.hid"
ROLLER_EVENTS = B_HID / "hid_recorder" / "contour_rollermouse_red_leftclick.events.txt"


def need(path: Path) -> str:
    if not path.is_file():
        pytest.skip(f"trace {path.name} not found at {path} (../shared/traces must sit beside the project)")
    return str(path)


def run(url: str) -> tuple[object, list[Sample]]:
    dev = open_device(url)
    dev.open()
    out: list[Sample] = []
    try:
        for _ in range(1_000_000):
            out += [x for x in dev.poll(0.1) if isinstance(x, Sample)]
    except EndOfStream:
        pass
    finally:
        dev.close()
    return dev, out


def values(samples: list[Sample], stream: str) -> np.ndarray:
    return np.array([s.values for s in samples if s.stream == stream], dtype=float)


# -- hid-recorder capture: every report decodes to what hid-decode wrote in the comments --------------
def _commented_reports(path: str) -> list[tuple[dict[str, list[int]], bytes]]:
    """(decoded fields from the '#' line, report bytes from the E: line that follows it)."""
    out = []
    comment = None
    for line in Path(path).read_text().splitlines():
        if line.startswith("# ReportID"):
            fields: dict[str, list[int]] = {}
            for part in line.split("/", 1)[1].split("|"):
                name, _, vals = part.partition(":")
                fields[name.strip()] = [int(v) for v in vals.replace(",", " ").split()]
            comment = fields
        elif line.startswith("E:") and comment is not None:
            parts = line.split()
            out.append((comment, bytes(int(x, 16) for x in parts[3:])))
            comment = None
    return out


def test_rollermouse_reports_decode_as_hid_decode_says() -> None:
    path = need(ROLLER)
    dev = parse_hid_recording(path)[0]
    assert len(dev.rdesc) == 220 and (dev.bus, dev.vid, dev.pid) == (3, 0x0B33, 0x1004)
    layout = parse_descriptor(dev.rdesc)
    assert "mouse" in layout.classes
    expected = _commented_reports(path)
    assert len(expected) == len(dev.events) == 6
    rep = layout.reports[1]
    names = [f.name for f in rep.fields]
    for fields, data in expected:
        assert data[0] == 1 and len(data) == rep.size == 16
        dec = rep.decode(data)
        assert [dec[names.index(f"B{i}")] for i in range(1, 9)] == fields["Button"]
        assert [dec[names.index(k)] for k in ("X", "Y", "Wheel")] == fields["X"] + fields["Y"] + fields["Wheel"]
        vendor = [d for d, f in zip(dec, rep.fields, strict=True) if f.name == "Vendor Usage 1"]
        assert vendor == fields["Vendor Usage 1"]
    # the vectorised decoder agrees with the scalar one
    arr = np.frombuffer(b"".join(d for _, d in expected), np.uint8).reshape(len(expected), -1)
    assert np.array_equal(rep.decode_many(arr), np.array([rep.decode(d) for _, d in expected]))

    # and through the device kind, replayed at the recorded timing, onto the bus
    hid, samples = run(f"m=hid@simhid://{path}?realtime=false")
    buttons = values(samples, "m/buttons")
    assert buttons[:, :8].tolist() == [[float(b) for b in f["Button"]] for f, _ in expected]
    ptr = values(samples, "m/pointer")
    assert ptr[:, :3].tolist() == [[float(f["X"][0]), float(f["Y"][0]), float(f["Wheel"][0])] for f, _ in expected]
    assert hid.codec.stats.errors == 0
    times = [s.t_host_ns for s in samples if s.stream == "m/buttons"]
    rec = [t for t, _ in dev.events]
    assert np.allclose(np.diff(times) / 1e9, np.diff(rec), atol=1e-6)


def test_events_file_with_descriptor_from_another_capture() -> None:
    path, rdesc = need(ROLLER_EVENTS), need(ROLLER)
    expected = _commented_reports(path)
    _, samples = run(f"m=hid@simhid://{path}?realtime=false&rdesc_file={rdesc}")
    assert values(samples, "m/buttons")[:, :8].tolist() == [[float(b) for b in f["Button"]] for f, _ in expected]


def test_events_file_without_descriptor_is_a_trace_error() -> None:
    path = need(ROLLER_EVENTS)
    with pytest.raises(TraceError, match="no report descriptor"):
        open_device(f"hid@simhid://{path}?realtime=false")


def test_malformed_recording_names_file_and_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.hid"
    bad.write_text("R: 2 05 01\nI: 3 0b33 1004\nE: 0.000000 3 01 zz 00\n")
    with pytest.raises(TraceError) as exc:
        parse_hid_recording(str(bad))
    assert exc.value.line == 3 and str(bad) in str(exc.value)
    bad.write_text("R: 3 05 01\n")
    with pytest.raises(TraceError, match="3 bytes but holds 2"):
        parse_hid_recording(str(bad))


# -- real game-controller descriptors --------------------------------------------------------------------
def _cts(name: str) -> dict:
    text = Path(need(B_HID / "android_cts" / f"{name}.json")).read_text()
    return json.loads(re.sub(r"\b0x([0-9a-fA-F]+)\b", lambda m: str(int(m.group(1), 16)), text))


@pytest.mark.parametrize("name, rdesc_len, sizes", [
    ("sony_dualshock4_usb_register", 483, {1: 64}),
    ("sony_dualsense_usb_register", 257, {1: 64}),
    ("nintendo_switchpro_register", 170, {0x21: 49, 0x30: 49, 0x31: 362, 0x32: 362, 0x33: 362, 0x3F: 12}),
])
def test_controller_descriptors_give_the_readme_report_sizes(name: str, rdesc_len: int, sizes: dict) -> None:
    d = _cts(name)
    assert len(d["descriptor"]) == rdesc_len
    layout = parse_descriptor(bytes(d["descriptor"]))
    assert {k: r.size for k, r in layout.reports.items()} == sizes
    assert layout.classes == ()  # gamepads: no mouse, pen or touch
    with pytest.raises(ConfigError, match="no mouse, pen or touch"):
        open_device(f"hid@simhid://mouse?realtime=false&rdesc={bytes(d['descriptor']).hex()}")


def test_unparseable_descriptor_is_a_config_error() -> None:
    for bad in (b"\x05", b"\xff\xff\xff", b"\x05\x01\xc0"):
        with pytest.raises(ConfigError):
            parse_descriptor(bad)


# -- encode <-> decode ------------------------------------------------------------------------------------
@pytest.mark.parametrize("profile, classes", [("mouse", ("mouse",)), ("pen", ("pen",)), ("touch", ("touch",))])
@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_encode_decode_round_trip(profile: str, classes: tuple, data: st.DataObject) -> None:
    layout = parse_descriptor(STANDARD_DESCRIPTORS[profile])
    assert layout.classes == classes
    for rep in layout.reports.values():
        vals = {f.index: data.draw(st.integers(f.logical_min, f.logical_max)) for f in rep.fields}
        raw = rep.encode(vals)
        assert len(raw) == rep.size and raw[0] == rep.report_id
        assert rep.decode(raw) == [vals[f.index] for f in rep.fields]
        assert rep.decode_many(np.frombuffer(raw, np.uint8)[None, :])[0].tolist() == rep.decode(raw)


def test_standard_layouts_physical_units() -> None:
    pen = parse_descriptor(STANDARD_DESCRIPTORS["pen"]).reports[2]
    x = next(f for f in pen.fields if f.name == "X")
    assert x.unit == "m" and x.physical(x.logical_max) == pytest.approx(0.22352)  # 44704 counts at 200/mm
    tilt = next(f for f in pen.fields if f.name == "X Tilt")
    assert tilt.unit == "deg" and tilt.physical(-64) == -64 and tilt.physical(63) == 63
    mouse = parse_descriptor(STANDARD_DESCRIPTORS["mouse"])
    assert mouse.wheel_multiplier() == 8


# -- evemu recordings replayed through the simulated devices --------------------------------------------
def _evemu_states(path: str, codes: dict[int, str]) -> list[dict[str, int]]:
    """The absolute-axis state after each SYN_REPORT frame (what the device reports at that time)."""
    state: dict[str, int] = {}
    out = []
    for fr in evemu.parse_events(path):
        for typ, code, value in fr.events:
            if typ == evemu.EV_ABS and code in codes:
                state[codes[code]] = value
        out.append(dict(state))
    return out


def test_evemu_pen_reaches_the_bus_in_physical_units() -> None:
    path = need(EVEMU / "wacom_intuos4_6x9.stylus-drag.events")
    desc = evemu.parse_desc(need(EVEMU / "wacom_intuos4_6x9.desc"))
    dev, samples = run(f"p=hid@simhid://pen?realtime=false&evemu={path}")
    pen = values(samples, "p/pen")
    states = _evemu_states(path, {0: "x", 1: "y", 0x18: "p", 0x1A: "tx", 0x1B: "ty"})
    assert len(pen) == len(states) == 361
    width_m = 0.22352  # the simulated tablet's active area (44704 counts at 200 per mm, as the Intuos4 6x9)
    ch = dev.streams[0].channels
    ex = np.array([desc.absinfo[0].fraction(s.get("x", 0)) * width_m for s in states])
    assert np.allclose(pen[:, ch.index("x")], ex, atol=5e-6)
    pmax = max(s.get("p", 0) for s in states)
    assert pen[:, ch.index("pressure")].max() == pytest.approx(pmax / desc.absinfo[0x18].maximum)
    assert pmax == 2047
    # tilt: evdev 0..127 with 64 upright, 1 count per degree -> -64..63 deg
    tx = np.array([s.get("tx", 0) - 64 for s in states], float)
    assert np.array_equal(pen[:, ch.index("tilt_x")], tx)
    assert (pen[:, ch.index("tilt_x")].min(), pen[:, ch.index("tilt_x")].max()) == (tx.min(), tx.max())
    assert pen[:, ch.index("tip")].max() == 1.0 and dev.codec.stats.errors == 0


def test_evemu_two_finger_touch() -> None:
    path = need(EVEMU / "wacom_isdv4_e6_finger.double-center-circle.events")
    desc = evemu.parse_desc(need(EVEMU / "wacom_isdv4_e6_finger.desc"))
    dev, samples = run(f"t=hid@simhid://touch?realtime=false&evemu={path}")
    ch = dev.streams[0].channels
    touch = values(samples, "t/touch")
    two = touch[touch[:, ch.index("contact_count")] == 2]
    assert set(two[:, ch.index("contact_id")].tolist()) == {0.0, 1.0}
    assert len(two) >= 2 * 100  # two fingers down for most of the 129 frames
    # positions per slot match the recording, scaled onto the simulated 259.1 mm wide panel
    slot_x: dict[int, list[int]] = {0: [], 1: []}
    slot = 0
    for fr in evemu.parse_events(path):
        for typ, code, value in fr.events:
            if typ == evemu.EV_ABS and code == evemu.ABS_MT_SLOT:
                slot = value
            elif typ == evemu.EV_ABS and code == evemu.ABS_MT_POSITION_X:
                slot_x[slot].append(value)
    info = desc.absinfo[evemu.ABS_MT_POSITION_X]
    for cid in (0, 1):
        got = touch[touch[:, ch.index("contact_id")] == cid][:, ch.index("x")]
        assert got.max() == pytest.approx(info.fraction(max(slot_x[cid])) * 0.2591, abs=1e-4)
        assert got.min() == pytest.approx(info.fraction(min(slot_x[cid])) * 0.2591, abs=1e-4)
    assert touch[-1, ch.index("tip")] == 0.0  # the last finger lifts


def test_evemu_mouse_motion_and_buttons() -> None:
    path = need(EVEMU / "saitek_cyborg_rat5_mouse.events")
    _, samples = run(f"m=hid@simhid://mouse?realtime=false&evemu={path}")
    frames = evemu.parse_events(path)
    rel = {c: sum(v for fr in frames for t, cc, v in fr.events if t == evemu.EV_REL and cc == c) for c in (0, 1)}
    ptr = values(samples, "m/pointer")
    assert len(ptr) == len(frames) == 803
    assert ptr[:, 0].sum() == rel[0] and ptr[:, 1].sum() == rel[1]
    presses = sum(1 for fr in frames for t, c, v in fr.events if t == evemu.EV_KEY and c == evemu.BTN_LEFT and v)
    b1 = values(samples, "m/buttons")[:, 0]
    assert int(np.sum(np.diff(np.concatenate([[0.0], b1])) > 0)) == presses
    ts = np.array([s.t_host_ns for s in samples if s.stream == "m/pointer"]) / 1e9
    assert ts[-1] - ts[0] == pytest.approx(frames[-1].t - frames[0].t, abs=1e-3)


def test_synthetic_mouse_sets_the_resolution_multiplier() -> None:
    dev, samples = run("m=hid@simhid://mouse?realtime=false&duration=0.5&seed=3")
    assert dev.transport.responder.multiplier == 8  # the handshake set it to its maximum
    wheel = values(samples, "m/pointer")[:, 2]
    assert set(np.unique(wheel).tolist()) <= {0.0, 0.125}
    assert dev.streams[0].quantum[2] == 0.125


# -- robustness -------------------------------------------------------------------------------------------
@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=40), max_size=30))
def test_fuzzed_reports_never_raise_and_are_counted(reports: list[bytes]) -> None:
    codec = HidReportCodec()
    codec.set_layout(parse_descriptor(STANDARD_DESCRIPTORS["touch"]))
    frames = sum(len(codec.feed(r)) for r in reports)
    assert frames + codec.stats.errors == len(reports)
    assert frames == codec.stats.frames


def test_truncated_and_unknown_reports_are_counted() -> None:
    path = need(ROLLER)
    layout = parse_descriptor(parse_hid_recording(path)[0].rdesc)
    codec = HidReportCodec()
    codec.set_layout(layout)
    good = parse_hid_recording(path)[0].events[0][1]
    assert len(codec.feed(good)) == 1
    assert codec.feed(good[:-1]) == [] and codec.stats.framing_errors == 1
    assert codec.feed(b"\x09" + good[1:]) == [] and codec.stats.framing_errors == 2
    strict = HidReportCodec(strict=True)
    strict.set_layout(layout)
    with pytest.raises(ProtocolError):
        strict.feed(good[:3])


def test_handshake_rejects_a_descriptor_that_changes_the_declared_streams() -> None:
    path = need(ROLLER)
    rd = parse_hid_recording(path)[0].rdesc
    dev = open_device(f"hid@simhid://pen?realtime=false&rdesc={rd.hex()}")
    assert [s.name.split("/")[1] for s in dev.streams] == ["pointer", "buttons"]
    try:
        with pytest.raises(DeviceInitError, match="other streams"):
            dev.open()  # the simulated pen's own descriptor gives a pen stream, not the declared mouse
    finally:
        dev.close()


PUSH_POP_MOUSE = bytes([
    0x05, 0x01, 0x09, 0x02, 0xA1, 0x01, 0x09, 0x01, 0xA1, 0x00,
    0xA4,                    # Push
    0x66, 0x11, 0x00,        # Unit: cm
    0x55, 0x0E,              # Unit exponent -2
    0x05, 0x01, 0x09, 0x30, 0x09, 0x31, 0x15, 0x81, 0x25, 0x7F, 0x75, 0x08, 0x95, 0x02, 0x81, 0x06,
    0xB4,                    # Pop
    0x05, 0x09, 0x19, 0x01, 0x29, 0x03, 0x15, 0x00, 0x25, 0x01, 0x75, 0x01, 0x95, 0x03, 0x81, 0x02,
    0x75, 0x05, 0x95, 0x01, 0x81, 0x03,
    0xC0, 0xC0])


def test_a_descriptor_with_push_and_pop_is_laid_out():
    """hid-tools mishandles units around Push/Pop; the layout still comes out (X/Y in metres from the
    pushed unit, buttons unitless) instead of an internal error."""
    from devices.hid.descriptor import parse_descriptor

    lay = parse_descriptor(PUSH_POP_MOUSE, "push/pop mouse")
    fields = {f.name: f for r in lay.reports.values() for f in r.fields}
    assert fields["X"].unit == "m" and fields["Y"].unit == "m"
    assert "mouse" in lay.classes


@settings(max_examples=300, deadline=None)
@given(st.binary(min_size=1, max_size=120))
def test_any_bytes_as_a_descriptor_give_a_layout_or_a_config_error(blob):
    from devices.hid.descriptor import DescriptorLayout, parse_descriptor

    try:
        lay = parse_descriptor(blob, "fuzz")
    except ConfigError:
        return  # refused with the one error the device layer reports, never an internal one
    assert isinstance(lay, DescriptorLayout)
    assert all(f.name for r in lay.reports.values() for f in r.fields)
