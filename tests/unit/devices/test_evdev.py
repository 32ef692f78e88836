"""The evdev device kind: the input_event codec, the streams from the capabilities, every real evemu
trace through ``simevdev://`` (frame counts of ../shared/traces/f_pen_mouse_touch/README.md and
b_hid/README.md, ranges, units, bus times at the recorded kernel times), a session that replays to the
same samples, and a live uinput device read through ``evdev://`` (skipped where /dev/uinput is missing)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from capture.app.orchestrator import Capture
from capture.app.replay import replay_session
from capture.errors import ConfigError, DeviceNotFoundError, EndOfStream
from capture.sample import Sample
from capture.session import SessionReader
from devices import open_device
from devices.evdev import (
    CAPS_DESCRIPTOR,
    EV_ABS,
    EV_KEY,
    EV_REL,
    EV_SYN,
    EVENT_SIZE,
    REL_WHEEL,
    REL_WHEEL_HI_RES,
    REL_X,
    REL_Y,
    SYN_DROPPED,
    SYN_REPORT,
    AbsInfo,
    Capabilities,
    EvdevCodec,
    EvdevFrame,
    EvdevInput,
    pack_event,
)
from devices.transports.evdev import EvdevTransport
from sim_devices import evemu
from sim_devices.evdev_sim import SimEvdevTransport

TRACES = Path(__file__).resolve().parents[3].parent / "shared" / "traces"
F_EVEMU = TRACES / "f_pen_mouse_touch" / "evemu"
XBOX = TRACES / "b_hid" / "evemu" / "madcatz_wired_xbox360_controller.evemu"

#: trace -> SYN_REPORT frames, as the READMEs give them
FRAMES = {
    "wacom_intuos4_6x9.stylus-move.events": 444,
    "wacom_intuos4_6x9.stylus-drag.events": 361,
    "wacom_isdv4_e6_finger.single-center-circle.events": 84,
    "wacom_isdv4_e6_finger.double-center-circle.events": 129,
    "saitek_cyborg_rat5_mouse.events": 803,
    "madcatz_wired_xbox360_controller.evemu": 234,
}


def trace(name: str) -> Path:
    p = (XBOX if name.endswith(".evemu") else F_EVEMU / name)
    if not p.is_file():
        pytest.skip(f"trace {name} not found at {p} (../shared/traces must sit beside the project)")
    return p


def run(url: str) -> tuple[EvdevInput, list[Sample]]:
    dev = open_device(url)
    assert isinstance(dev, EvdevInput)
    dev.open()
    out: list[Sample] = []
    try:
        for _ in range(100_000):
            out += [x for x in dev.poll(0.1) if isinstance(x, Sample)]
    except EndOfStream:
        pass
    finally:
        dev.close()
    return dev, out


def col(dev: EvdevInput, samples: list[Sample], stream: str, channel: str) -> np.ndarray:
    si = next(s for s in dev.streams if s.name == f"{dev.name}/{stream}")
    i = si.channels.index(channel)
    return np.array([s.values[i] for s in samples if s.stream == si.name], float)


def units(dev: EvdevInput, stream: str) -> dict[str, str]:
    si = next(s for s in dev.streams if s.name == f"{dev.name}/{stream}")
    return dict(zip(si.channels, si.units, strict=True))


# -- codec ---------------------------------------------------------------------------------------------
def test_records_are_the_kernels_and_frames_end_at_syn_report() -> None:
    assert EVENT_SIZE == 24  # 64-bit Linux: two longs, two u16, one s32
    c = EvdevCodec()
    frames = [EvdevFrame(1_000_000 + 4000 * i, [(EV_REL, REL_X, i), (EV_REL, REL_Y, -i)]) for i in range(5)]
    data = b"".join(c.encode(f) for f in frames)
    got: list[EvdevFrame] = []
    for i in range(0, len(data), 7):  # split anywhere: records are joined across reads
        got += c.feed(data[i:i + 7])
    assert got == frames and c.buffered == 0 and c.stats.errors == 0


def test_syn_dropped_drops_to_the_next_report_counts_and_marks_a_resync() -> None:
    c = EvdevCodec()
    data = (pack_event(10, EV_REL, REL_X, 1) + pack_event(10, EV_SYN, SYN_REPORT, 0)
            + pack_event(20, EV_REL, REL_X, 2) + pack_event(20, EV_SYN, SYN_DROPPED, 0)
            + pack_event(30, EV_REL, REL_X, 3) + pack_event(30, EV_SYN, SYN_REPORT, 0)
            + pack_event(40, EV_REL, REL_X, 4) + pack_event(40, EV_SYN, SYN_REPORT, 0))
    frames = c.feed(data)
    assert [(f.ticks, f.events, f.resync) for f in frames] == [(10, [(EV_REL, REL_X, 1)], False),
                                                              (40, [(EV_REL, REL_X, 4)], True)]
    assert c.dropped == 1 and c.stats.framing_errors == 1


def test_a_record_that_is_not_the_kernels_is_a_framing_error() -> None:
    c = EvdevCodec()
    bad = pack_event(5, 0x7F, 0, 0)
    frames = c.feed(bad + pack_event(6, EV_KEY, 0x110, 1) + pack_event(6, EV_SYN, SYN_REPORT, 0))
    assert frames == [EvdevFrame(6, [(EV_KEY, 0x110, 1)])] and c.stats.framing_errors == 1


def test_capabilities_round_trip_as_json() -> None:
    caps = Capabilities("pen", 3, 0x56A, 0xB9, 1, {EV_KEY: frozenset({0x140, 0x14A}), EV_ABS: frozenset({0, 1})},
                        {0: AbsInfo(0, 44704, 4, 0, 200), 1: AbsInfo(0, 27940, 4, 0, 200)}, frozenset({1}))
    assert Capabilities.from_json(caps.to_json()) == caps
    with pytest.raises(ValueError, match="capabilities"):
        Capabilities.from_json("[1]")


# -- the streams from the capabilities -----------------------------------------------------------------
def _device(caps: Capabilities) -> EvdevInput:
    """A device of these capabilities (on a simulated transport, which the caps option overrides)."""
    return EvdevInput("d", SimEvdevTransport(str(trace("saitek_cyborg_rat5_mouse.events"))), {"caps": caps.to_json()})


def test_pen_in_metres_from_the_resolution_and_tilt_in_degrees_from_radians() -> None:
    caps = Capabilities("pen", events={EV_KEY: frozenset({0x140, 0x14A, 0x14B}), EV_ABS: frozenset()},
                        absinfo={0: AbsInfo(0, 44704, 0, 0, 200), 1: AbsInfo(0, 27940, 0, 0, 200),
                                 0x18: AbsInfo(0, 2047), 0x1A: AbsInfo(-64, 63, 0, 0, 57)})
    d = _device(caps)
    assert units(d, "pen")["x"] == "m" and units(d, "pen")["tilt_x"] == "deg"
    (r,) = d.frame_to_readings(EvdevFrame(7, [(EV_ABS, 0, 20000), (EV_ABS, 1, 100), (EV_ABS, 0x18, 2047),
                                              (EV_ABS, 0x1A, 57), (EV_KEY, 0x140, 1), (EV_KEY, 0x14A, 1)]))
    v = dict(zip(d.streams[0].channels, r.values, strict=True))
    assert v["x"] == pytest.approx(0.1) and v["y"] == pytest.approx(0.0005) and v["pressure"] == 1.0
    assert v["tilt_x"] == pytest.approx(np.degrees(1.0)) and np.isnan(v["tilt_y"])
    assert (v["in_range"], v["tip"], v["barrel"], v["eraser"]) == (1.0, 1.0, 0.0, 0.0) and r.ticks == 7


def test_hi_res_wheel_is_summed_and_the_legacy_wheel_ignored() -> None:
    caps = Capabilities("m", events={EV_REL: frozenset({REL_X, REL_Y, REL_WHEEL, REL_WHEEL_HI_RES})})
    d = _device(caps)
    (r,) = d.frame_to_readings(EvdevFrame(1, [(EV_REL, REL_WHEEL_HI_RES, 60), (EV_REL, REL_WHEEL_HI_RES, 60),
                                              (EV_REL, REL_WHEEL, 1), (EV_REL, REL_X, 300), (EV_REL, REL_X, 300)]))
    assert r.values == (600.0, 0.0, 1.0, 0.0)
    (r,) = d.frame_to_readings(EvdevFrame(2, [(EV_REL, REL_WHEEL_HI_RES, 30)]))
    assert r.values[2] == 0.25


def test_no_capabilities_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="keys"):
        _device(Capabilities("nothing"))


# -- every real trace ------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(FRAMES))
def test_every_trace_frame_by_frame_at_its_kernel_times(name: str) -> None:
    path = trace(name)
    latency_ms = 0.3
    dev, samples = run(f"x=simevdev://{path}?realtime=false&latency_ms={latency_ms}")
    frames = evemu.parse_events(str(path))
    assert len(frames) == FRAMES[name] == dev.codec.stats.frames
    assert dev.codec.stats.errors == 0 and dev.stats.decode_errors == 0 and dev.stats.bad_readings == 0
    assert not dev.stats.undecoded and dev.stats.missing_time == 0
    # every frame with a decodable event gives at least one reading; a device time per reading, the kernel's
    ticks = {round(f.t * 1e6) for f in frames}
    assert {s.t_device_ns // 1000 for s in samples} <= ticks
    t0_dev = round(frames[0].t * 1e6) * 1000
    t0_host = dev.transport.arrival_ns(0) - int(latency_ms * 1e6)  # type: ignore[attr-defined]
    for stream in {s.stream for s in samples}:
        got = [s for s in samples if s.stream == stream]
        bus = np.array([s.t_bus_ns for s in got])
        dv = np.array([s.t_device_ns for s in got])
        host = np.array([s.t_host_ns for s in got])
        assert np.all(np.diff(bus) >= 0), stream
        assert np.all(bus <= host), stream
        # the bus time is the recorded kernel time (on the host timeline) within 1 ms
        assert np.max(np.abs((bus - t0_host) - (dv - t0_dev))) < 1_000_000, stream
        assert np.all(np.diff(np.array([s.seq for s in got])) == 1), stream


def test_intuos4_pen_in_a_vendor_report_reaches_the_bus() -> None:
    """The README's 056a:00b9 sends its pen in a vendor HID report (hid:// gives 0 samples); the
    kernel's wacom driver decodes it."""
    dev, samples = run(f"p=simevdev://{trace('wacom_intuos4_6x9.stylus-drag.events')}?realtime=false")
    assert dev.identity.vid_pid == "056a:00b9"
    desc = evemu.parse_desc(str(F_EVEMU / "wacom_intuos4_6x9.desc"))
    u = units(dev, "pen")
    assert (u["x"], u["pressure"], u["tilt_x"]) == ("1", "1", "deg")  # this recording's driver gave no resolution
    x, pr, tip = col(dev, samples, "pen", "x"), col(dev, samples, "pen", "pressure"), col(dev, samples, "pen", "tip")
    assert len(x) >= 350 and np.nanmax(x) <= 1.0 and np.nanmin(x) >= 0.0
    assert pr.min() == 0.0 and pr.max() == 1.0  # PRESSURE 0-2047
    assert tip.max() == 1.0
    frames = evemu.parse_events(str(F_EVEMU / "wacom_intuos4_6x9.stylus-drag.events"))
    xs = [v for f in frames for t, c, v in f.events if (t, c) == (EV_ABS, 0)]
    assert np.nanmax(x) == pytest.approx(desc.absinfo[0].fraction(max(xs)))
    tilt = col(dev, samples, "pen", "tilt_x")
    tx = [v for f in frames for t, c, v in f.events if (t, c) == (EV_ABS, 0x1A)]
    assert (np.nanmin(tilt), np.nanmax(tilt)) == (min(tx) - 64, max(tx) - 64)  # one count per degree about 64


def test_intuos4_hover_ranges_as_the_readme_says() -> None:
    dev, samples = run(f"p=simevdev://{trace('wacom_intuos4_6x9.stylus-move.events')}?realtime=false")
    x, y = col(dev, samples, "pen", "x"), col(dev, samples, "pen", "y")
    assert np.nanmax(x) == pytest.approx(28679 / 44704) and np.nanmax(y) == pytest.approx(1.0)
    tx, ty = col(dev, samples, "pen", "tilt_x"), col(dev, samples, "pen", "tilt_y")
    assert (np.nanmin(tx), np.nanmax(tx)) == (0 - 64, 106 - 64) and (np.nanmin(ty), np.nanmax(ty)) == (-64, 55 - 64)
    rng = col(dev, samples, "pen", "in_range")
    assert set(rng.tolist()) == {0.0, 1.0}  # BTN_TOOL_PEN in and out
    assert col(dev, samples, "pen", "tip").max() == 0.0  # hovering only
    bus = np.array([s.t_bus_ns for s in samples if s.stream == "p/pen"])
    assert (bus[-1] - bus[0]) / 1e9 == pytest.approx(2.22, abs=0.01)
    assert np.median(np.diff(bus)) == pytest.approx(4e6, rel=0.05)  # 250 Hz


def test_two_fingers_by_slot_and_tracking_id() -> None:
    dev, samples = run(f"t=simevdev://{trace('wacom_isdv4_e6_finger.double-center-circle.events')}?realtime=false")
    slot, tid, tip = (col(dev, samples, "touch", c) for c in ("slot", "tracking_id", "tip"))
    assert set(slot.tolist()) == {0.0, 1.0}
    assert len(set(tid[slot == 0].tolist())) == 1 and len(set(tid[slot == 1].tolist())) == 1
    assert set(tid[slot == 0].tolist()) != set(tid[slot == 1].tolist())
    for s in (0.0, 1.0):  # each finger comes down and lifts
        t = tip[slot == s]
        assert t[0] == 1.0 and t[-1] == 0.0
    assert units(dev, "touch")["x"] == "1"


def test_one_finger_circle_in_the_readme_range() -> None:
    dev, samples = run(f"t=simevdev://{trace('wacom_isdv4_e6_finger.single-center-circle.events')}?realtime=false")
    x, y, tip = (col(dev, samples, "touch", c) for c in ("x", "y", "tip"))
    down = tip == 1.0
    # the README's X 1136-1638, Y 527-899 are the single-touch ABS_X/Y (fuzz-filtered); the slot's
    # ABS_MT_POSITION_X/Y, which the stream carries, span 1134-1641 and 525-901
    assert x[down].min() == pytest.approx(1134 / 2776) and x[down].max() == pytest.approx(1641 / 2776)
    assert y[down].min() == pytest.approx(525 / 1569) and y[down].max() == pytest.approx(901 / 1569)
    assert tip[-1] == 0.0


def test_mouse_counts_and_buttons() -> None:
    path = trace("saitek_cyborg_rat5_mouse.events")
    dev, samples = run(f"m=simevdev://{path}?realtime=false")
    frames = evemu.parse_events(str(path))
    dx, dy = col(dev, samples, "pointer", "dx"), col(dev, samples, "pointer", "dy")
    assert dx.sum() == sum(v for f in frames for t, c, v in f.events if (t, c) == (EV_REL, REL_X))
    assert dy.sum() == sum(v for f in frames for t, c, v in f.events if (t, c) == (EV_REL, REL_Y))
    assert (dx.min(), dx.max(), dy.min(), dy.max()) == (-2, 3, -4, 4)
    presses = sum(1 for f in frames for t, c, v in f.events if (t, c) == (EV_KEY, 0x110) and v)
    left = col(dev, samples, "buttons", "left")
    assert int(np.sum(np.diff(np.concatenate([[0.0], left])) > 0)) == presses > 0
    bus = np.array([s.t_bus_ns for s in samples if s.stream == "m/pointer"])
    assert np.median(np.diff(bus)) == pytest.approx(2e6, rel=0.05)  # 500 Hz in motion


def test_gamepad_axes_and_buttons() -> None:
    dev, samples = run(f"g=simevdev://{trace('madcatz_wired_xbox360_controller.evemu')}?realtime=false")
    assert dev.identity.vid_pid == "0738:4716"
    y, ry = col(dev, samples, "axes", "y"), col(dev, samples, "axes", "ry")
    assert (np.nanmin(y), np.nanmax(y)) == (-471, -314) and (np.nanmin(ry), np.nanmax(ry)) == (-1490, -1412)
    assert col(dev, samples, "buttons", "east").max() == 1.0  # button 0x131
    assert set(col(dev, samples, "axes", "hat0y")[~np.isnan(col(dev, samples, "axes", "hat0y"))].tolist()) \
        >= {-1.0, 1.0}


# -- sessions: the capabilities recorded, the replay the same -----------------------------------------------
def test_session_records_the_capabilities_and_replays_to_the_same_samples(tmp_path: Path) -> None:
    out = str(tmp_path / "pen.mcap")
    url = f"pen=simevdev://{trace('wacom_intuos4_6x9.stylus-drag.events')}?realtime=false"
    rep = Capture([url], output=out, fsync=False).run(None)
    assert rep.recorder_error is None
    r = SessionReader(out)
    rec = r.devices["pen"]
    caps = Capabilities.from_json(rec.descriptors[CAPS_DESCRIPTOR])
    assert caps.vendor == 0x56A and caps.absinfo[0] == AbsInfo(0, 44704, 4, 0, 0)
    assert Capabilities.from_json(rec.options["caps"]) == caps
    assert len(r.samples("pen/pen")) >= 350
    v = replay_session(out, speed=0)
    assert v.verification["equal"], v.verification["first_mismatch"]


# -- live: evdev:// ----------------------------------------------------------------------------------------
def test_a_missing_node_is_not_found(tmp_path: Path) -> None:
    pytest.importorskip("evdev", reason="python-evdev is not installed (pip install 'perfcap[evdev]')")
    t = EvdevTransport(f"{tmp_path}/event99")
    assert t.present() is False
    with pytest.raises(DeviceNotFoundError, match="not there"):
        t.open()


def _uinput():  # type: ignore[no-untyped-def]
    evdev = pytest.importorskip("evdev", reason="python-evdev is not installed (pip install 'perfcap[evdev]')")
    if not os.path.exists("/dev/uinput"):
        pytest.skip("/dev/uinput is missing (no uinput module in this kernel or container): no virtual input device")
    if not os.access("/dev/uinput", os.W_OK):
        pytest.skip("/dev/uinput is there but not writable by this user")
    return evdev


def test_uinput_pen_read_through_evdev_into_a_capture(tmp_path: Path) -> None:
    evdev = _uinput()
    e = evdev.ecodes
    caps = {e.EV_KEY: [e.BTN_TOOL_PEN, e.BTN_TOUCH, e.BTN_STYLUS],
            e.EV_ABS: [(e.ABS_X, evdev.AbsInfo(0, 0, 20000, 0, 0, 100)),
                       (e.ABS_Y, evdev.AbsInfo(0, 0, 10000, 0, 0, 100)),
                       (e.ABS_PRESSURE, evdev.AbsInfo(0, 0, 1023, 0, 0, 0))]}
    try:
        ui = evdev.UInput(caps, name="perfcap test pen", vendor=0x1234, product=0x5678)
    except (OSError, evdev.UInputError) as exc:
        pytest.skip(f"cannot create a uinput device: {exc}")
    import threading
    import time
    with ui:
        time.sleep(0.5)  # udev makes the node
        path = ui.device.path
        out = str(tmp_path / "live.mcap")
        cap = Capture([f"pen=evdev://{path}"], output=out, fsync=False)
        stop = threading.Event()

        def emit() -> None:
            time.sleep(0.5)
            for i in range(50):
                ui.write(e.EV_KEY, e.BTN_TOOL_PEN, 1)
                ui.write(e.EV_ABS, e.ABS_X, 100 * i)
                ui.write(e.EV_ABS, e.ABS_Y, 5000)
                ui.write(e.EV_ABS, e.ABS_PRESSURE, 10 * i)
                ui.syn()
                time.sleep(0.004)
            time.sleep(0.3)
            stop.set()

        th = threading.Thread(target=emit)
        th.start()
        rep = cap.run(None, stop=stop)
        th.join()
    assert rep.recorder_error is None
    b = SessionReader(out).samples("pen/pen")
    assert len(b) == 50
    x = b.values[:, 0]
    assert x[-1] == pytest.approx(4900 / 100 / 1000)  # 100 units per mm -> m
    assert np.all(np.diff(b.t_bus_ns) > 0) and np.all(b.t_bus_ns <= b.t_host_ns)
    assert np.all(b.t_host_ns - b.t_bus_ns < 50_000_000)
    # the kernel's times on CLOCK_MONOTONIC (EVIOCSCLOCKID), the host's clock: taken before the arrival
    assert np.all(b.t_device_ns <= b.t_host_ns) and np.all(b.t_host_ns - b.t_device_ns < 50_000_000)


def test_live_transport_reads_kernel_records_and_comes_back_after_an_unplug(tmp_path: Path) -> None:
    """The evdev:// transport on a FIFO standing in for /dev/input/eventN (no uinput needed): whole
    records in, the kernel's times as device times, an unplug a DeviceIOError, ``present`` false
    until the node is back, then a reopen reads again."""
    from capture.clock import MONOTONIC
    from capture.errors import DeviceInitError, DeviceIOError

    node = tmp_path / "event42"
    os.mkfifo(node)
    caps = Capabilities("fifo pen", 3, 0x1234, 0x5678, 1, {EV_KEY: frozenset({0x140, 0x14A})},
                        {0: AbsInfo(0, 20000, 0, 0, 100), 1: AbsInfo(0, 10000, 0, 0, 100)})
    t = EvdevTransport(str(node), {"clock": "realtime"})
    t._caps = caps  # what python-evdev would have read from a real node
    dev = EvdevInput("pen", t)
    assert [s.name for s in dev.streams] == ["pen/pen"] and dev.streams[0].units[:2] == ("m", "m")
    assert t.present() is True
    dev.open()
    w = os.open(node, os.O_WRONLY | os.O_NONBLOCK)
    now_us = MONOTONIC.now_ns() // 1000
    c = EvdevCodec()
    frames = [EvdevFrame(now_us + 5000 * i, [(EV_KEY, 0x140, 1), (EV_ABS, 0, 1000 * i), (EV_ABS, 1, 500)])
              for i in range(10)]
    os.write(w, b"".join(c.encode(f) for f in frames))
    got: list[Sample] = []
    for _ in range(50):
        got += [x for x in dev.poll(0.05) if isinstance(x, Sample)]
        if len(got) == 10:
            break
    assert [s.t_device_ns for s in got] == [f.ticks * 1000 for f in frames]
    assert [s.values[0] for s in got] == pytest.approx([i * 1000 / 100 / 1000 for i in range(10)])
    assert all(s.t_bus_ns <= s.t_host_ns for s in got)
    os.close(w)  # the device goes away
    node.unlink()
    with pytest.raises(DeviceIOError, match="vanished"):
        for _ in range(50):
            dev.poll(0.05)
    dev.close()
    assert t.present() is False
    with pytest.raises(DeviceNotFoundError):
        t.open()
    os.mkfifo(node)  # and comes back
    assert t.present() is True
    dev.reset_after_reconnect()
    dev.open()
    w = os.open(node, os.O_WRONLY | os.O_NONBLOCK)
    os.write(w, c.encode(EvdevFrame(now_us + 100_000, [(EV_ABS, 0, 7)])))
    more: list[Sample] = []
    for _ in range(50):
        more += [x for x in dev.poll(0.05) if isinstance(x, Sample)]
        if more:
            break
    assert more[0].t_device_ns == (now_us + 100_000) * 1000 and more[0].seq == 10
    os.close(w)
    dev.close()
    # a node that is not an input device cannot take EVIOCSCLOCKID: said, not a crash
    t2 = EvdevTransport(str(node))
    t2._caps = caps
    with pytest.raises(DeviceInitError, match="cannot set up"):
        t2.open()
