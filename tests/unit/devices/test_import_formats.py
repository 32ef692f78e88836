"""Import formats as the reference tools read them: hid-recorder captures with free-text lines
(hid-replay skips lines it does not know; perfcap counts and logs them), single-file evemu recordings
(``evemu-record``: description and events in one file), and wheels whose sums survive the replay.
Every hid-recorder and evemu trace in ``../shared/traces`` is read in place."""

from __future__ import annotations

import random
import re
from pathlib import Path

import pytest

from capture.errors import ConfigError, EndOfStream
from capture.sample import Sample
from devices import open_device
from sim_devices import evemu
from sim_devices.hid_recorder import KNOWN_TAGS, parse_hid_recording

TRACES = Path(__file__).resolve().parents[3].parent / "shared" / "traces"
HID_TRACES = sorted(TRACES.rglob("*.hid"))
_WORDS = ["note", "left click", "Bus 003 Device 012", "hid-decode:", "ok", "ReportID: 1 / X: 0", "--", "::",
          "Ünïcode", "x=1", "Q: unknown prefix", "ZZ: two letters", "# comment", "#", "12 zz", "0x05 0x01"]


def need(paths: list[Path]) -> list[Path]:
    if not paths:
        pytest.skip(f"no traces found under {TRACES} (../shared/traces must sit beside the project)")
    return paths


def _free_line(rng: random.Random) -> str:
    """A line hid-replay does not know: not 'X:' with X a known tag and not only hex bytes."""
    while True:
        line = " ".join(rng.choice(_WORDS) for _ in range(rng.randint(1, 4)))
        tag, sep, _ = line.strip().partition(":")
        if (sep and tag in KNOWN_TAGS) or re.fullmatch(r"(?:[0-9a-fA-F]{2}\s*)+", line.strip()):
            continue
        return line


@pytest.mark.parametrize("seed", range(20))
def test_free_text_lines_in_real_hid_recorder_traces_are_skipped_and_counted(seed, tmp_path, caplog):
    for src in need(HID_TRACES):
        base = parse_hid_recording(str(src))
        lines = src.read_text().splitlines()
        rng = random.Random(f"h17-{seed}-{src.name}")
        inserted = rng.randint(1, 12)
        for _ in range(inserted):
            lines.insert(rng.randint(0, len(lines)), _free_line(rng))
        path = tmp_path / src.name
        path.write_text("\n".join(lines) + "\n")
        with caplog.at_level("INFO", logger="sim_devices.hid_recorder"):
            got = parse_hid_recording(str(path))
        assert len(got.skipped) == len(base.skipped) + inserted
        assert sorted(got) == sorted(base)
        for idx in base:
            assert got[idx].rdesc == base[idx].rdesc and got[idx].events == base[idx].events
            assert (got[idx].name, got[idx].vid, got[idx].pid) == (base[idx].name, base[idx].vid, base[idx].pid)
        assert f"{path}: skipped" in caplog.text  # logged, never silent


@pytest.mark.parametrize("src", HID_TRACES, ids=lambda p: p.name)
def test_every_real_hid_recorder_trace_replays(src):
    dev = open_device(f"hid@simhid://{src}?realtime=false")
    dev.open()
    n = 0
    try:
        for _ in range(100_000):
            n += len(dev.poll(0.1))
    except EndOfStream:
        pass
    finally:
        dev.close()
    assert n >= len(parse_hid_recording(str(src))[0].events)


# -- evemu: single-file recordings -----------------------------------------------------------------------
EVEMU_EVENTS = sorted(TRACES.rglob("*.events"))
EVEMU_SINGLE = sorted(TRACES.rglob("*.evemu"))
#: the simulated device each real evemu recording replays through (by file-name prefix)
SIM_FOR = {"saitek": "mouse", "wacom_intuos4": "pen", "wacom_isdv4": "touch"}


def _sim(path: Path) -> str | None:
    return next((k for p, k in SIM_FOR.items() if path.name.startswith(p)), None)


def _replay(url: str) -> list[tuple[str, tuple[float, ...]]]:
    dev = open_device(url)
    dev.open()
    out = []
    try:
        for _ in range(1_000_000):
            out += [(s.stream, tuple(float(v) for v in s.values)) for s in dev.poll(0.1) if isinstance(s, Sample)]
    except EndOfStream:
        pass
    finally:
        dev.close()
    return out


@pytest.mark.parametrize("src", EVEMU_EVENTS, ids=lambda p: p.name)
def test_real_evemu_trace_as_a_single_file_decodes_as_the_two_file_form(src, tmp_path):
    desc = evemu.desc_for(str(src))
    assert desc is not None, f"no .desc beside {src}"
    single = tmp_path / (src.stem + ".evemu")  # no .desc beside it in tmp_path
    single.write_text(Path(desc).read_text() + src.read_text())
    assert evemu.description_for(str(single)) == evemu.parse_desc(desc)
    assert evemu.description_for(str(src)) == evemu.parse_desc(desc)
    frames = evemu.parse_events(str(src))
    assert frames and evemu.parse_events(str(single)) == frames
    kind = _sim(src)
    if kind:
        two = _replay(f"hid@simhid://{kind}?realtime=false&evemu={src}")
        assert two and _replay(f"hid@simhid://{kind}?realtime=false&evemu={single}") == two


@pytest.mark.parametrize("src", EVEMU_SINGLE, ids=lambda p: p.name)
def test_real_single_file_evemu_recording_holds_its_description_and_events(src, tmp_path):
    dev = evemu.description_for(str(src))
    assert dev is not None and dev.name and dev.vendor and dev.absinfo
    frames = evemu.parse_events(str(src))
    assert frames
    # split into the two-file form: the same description and the same events
    text = src.read_text().splitlines()
    (tmp_path / "dev.desc").write_text("\n".join(x for x in text if not x.startswith("E:")) + "\n")
    (tmp_path / "dev.events").write_text("\n".join(x for x in text if x.startswith("E:")) + "\n")
    assert evemu.description_for(str(tmp_path / "dev.events")) == dev
    assert evemu.parse_events(str(tmp_path / "dev.events")) == frames
    # it replays as a pointer device would (its buttons and axes the mouse does not have are ignored)
    assert _replay(f"hid@simhid://mouse?realtime=false&evemu={src}")


def test_an_events_file_without_any_description_is_a_clear_error(tmp_path):
    bare = tmp_path / "bare.events"
    bare.write_text("E: 0.000000 0002 0000 1\nE: 0.000000 0000 0000 0\n")
    with pytest.raises(ConfigError, match="holds no device description"):
        open_device(f"hid@simhid://mouse?realtime=false&evemu={bare}")


# -- wheels: never clipped, sums kept ----------------------------------------------------------------------
def _mouse(multiplier_on: bool):
    from sim_devices.hid_generic_sim import MouseResponder

    m = MouseResponder({"seed": 1})
    if multiplier_on:
        m.set_feature(m.mult_report.encode({m.mult_field.index: 1}))
    return m


@pytest.mark.parametrize("multiplier_on", [False, True])
@pytest.mark.parametrize("seed", range(10))
def test_wheel_sums_of_rel_wheel_and_hi_res_sequences_are_kept_exactly(seed, multiplier_on):
    rng = random.Random(f"h17-wheel-{seed}")
    mouse = _mouse(multiplier_on)
    m = mouse.multiplier
    step = 120 // m  # REL_WHEEL_HI_RES units in one count
    state = mouse._new_state()
    want = {evemu.REL_WHEEL_HI_RES: 0, evemu.REL_HWHEEL_HI_RES: 0}
    got = {evemu.REL_WHEEL_HI_RES: 0, evemu.REL_HWHEEL_HI_RES: 0}
    for _ in range(300):
        events = []
        for lo, hi in ((evemu.REL_WHEEL, evemu.REL_WHEEL_HI_RES), (evemu.REL_HWHEEL, evemu.REL_HWHEEL_HI_RES)):
            kind = rng.choice(["none", "detents", "hi_res", "big"])
            if kind == "detents":
                v = rng.randint(-5, 5)
                events.append((evemu.EV_REL, lo, v))
                want[hi] += 120 * v
            elif kind in ("hi_res", "big"):
                v = rng.randint(-20_000, 20_000) if kind == "big" else rng.randint(-300, 300)
                events += [(evemu.EV_REL, hi, v), (evemu.EV_REL, lo, v // 120)]  # the kernel sends both
                want[hi] += v
        rng.shuffle(events)
        for rep in mouse._frame_reports(state, events):
            vals = mouse.report.decode(rep)
            got[evemu.REL_WHEEL_HI_RES] += int(vals[mouse.fw.index]) * step
            got[evemu.REL_HWHEEL_HI_RES] += int(vals[mouse.fh.index]) * step
        for code, key in ((evemu.REL_WHEEL_HI_RES, "wheel_rest"), (evemu.REL_HWHEEL_HI_RES, "hwheel_rest")):
            # what is sent plus what waits for a whole count is what was recorded, at every frame
            assert got[code] + state[key] // m == want[code] and abs(state[key]) <= 60
    # sums that are whole counts come out exactly
    for code, key in ((evemu.REL_WHEEL_HI_RES, "wheel_rest"), (evemu.REL_HWHEEL_HI_RES, "hwheel_rest")):
        if want[code] % step == 0:
            assert got[code] == want[code] and state[key] == 0


def test_a_wheel_spin_beyond_the_report_field_is_split_not_clipped():
    mouse = _mouse(True)
    state = mouse._new_state()
    reps = mouse._frame_reports(state, [(evemu.EV_REL, evemu.REL_WHEEL_HI_RES, 120 * 100)])  # 800 counts
    assert len(reps) > 1 and sum(int(mouse.report.decode(r)[mouse.fw.index]) for r in reps) == 800


def test_an_evemu_value_beyond_32_bits_is_a_trace_error(tmp_path):
    from capture.errors import TraceError

    bad = tmp_path / "bad.events"
    bad.write_text(f"E: 0.000000 0002 0008 {1 << 40}\nE: 0.000000 0000 0000 0\n")
    with pytest.raises(TraceError, match="not a 32-bit evdev value"):
        evemu.parse_events(str(bad))


# -- evemu pens and touch: the recording's resolution gives the physical units -----------------------------
#: the position codes of each kind and the smallest resolution (counts/mm) that keeps the real
#: recordings' ranges inside the simulated device's active area
_POSITION = {"pen": ((evemu.ABS_X, evemu.ABS_Y), 200),
             "touch": ((evemu.ABS_MT_POSITION_X, evemu.ABS_MT_POSITION_Y), 11)}


def _with_resolution(desc_text: str, res: dict[int, int]) -> str:
    out = []
    for line in desc_text.splitlines():
        parts = line.split()
        if parts[:1] == ["A:"] and int(parts[1], 16) in res:
            parts = [*parts[:6], *(["0"] * (6 - len(parts))), str(res[int(parts[1], 16)])][:7]
            out.append(" ".join(parts))
        else:
            out.append(line)
    return "\n".join(out) + "\n"


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("src", [p for p in EVEMU_EVENTS if _sim(p) in _POSITION], ids=lambda p: p.name)
def test_evemu_pen_and_touch_positions_use_the_recordings_resolution(src, seed, tmp_path):
    kind = _sim(src)
    assert kind
    codes, rmin = _POSITION[kind]
    rng = random.Random(f"h17-res-{seed}-{src.name}")
    res = {c: rng.randint(rmin, 2 * rmin) for c in codes}
    desc_path = evemu.desc_for(str(src))
    assert desc_path
    single = tmp_path / (src.stem + ".evemu")
    single.write_text(_with_resolution(Path(desc_path).read_text(), res) + src.read_text())
    desc = evemu.description_for(str(single))
    assert desc and all(desc.absinfo[c].resolution == res[c] for c in codes)
    dev = open_device(f"d=hid@simhid://{kind}?realtime=false&evemu={single}")
    dev.open()
    samples: list[Sample] = []
    try:
        for _ in range(1_000_000):
            samples += [s for s in dev.poll(0.1) if isinstance(s, Sample)]
    except EndOfStream:
        pass
    finally:
        dev.close()
    ch = dev.streams[0].channels
    xs = [s.values[ch.index("x")] for s in samples if s.stream == f"d/{kind}"]
    recorded = [v for fr in evemu.parse_events(str(src)) for t, c, v in fr.events
                if t == evemu.EV_ABS and c == codes[0]]
    info = desc.absinfo[codes[0]]
    step = max(f.scale for f in dev.codec.layout.reports[next(iter(dev.codec.layout.reports))].fields
               if f.unit == "m")  # one logical count of the simulated device, m
    # the recorded extremes, in mm from the range's minimum at the recording's resolution
    assert max(xs) == pytest.approx((max(recorded) - info.minimum) / info.resolution / 1000, abs=step)
    assert min(xs) == pytest.approx((min(recorded) - info.minimum) / info.resolution / 1000, abs=step)
