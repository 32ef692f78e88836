"""Hostile trace files for the simulators' readers (evemu, hid-recorder, ``synth://imu?csv=``): devices,
FIFOs, oversized and line-less files refused with a clear error before they are read; mutated real
traces from ``../shared/traces`` either parsed within bounds or refused with a ``TraceError`` /
``ConfigError``; and the worst of them refused under a 1 GiB address-space limit."""

from __future__ import annotations

import math
import os
import random
import re
import stat
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from capture.errors import ConfigError, EndOfStream, TraceError
from devices.hid.bounds import HID_MAX_BUFFER_SIZE, HID_MAX_DESCRIPTOR_SIZE
from devices.transports import open_transport
from sim_devices import evemu, synth
from sim_devices.hid_recorder import MAX_TRACE_BYTES, parse_hid_recording

ROOT = Path(__file__).resolve().parents[3]
TRACES = ROOT.parent / "shared" / "traces"
ROLLER = TRACES / "b_hid" / "hid_recorder" / "contour_rollermouse_red_doubleclick.hid"
EVEMU = [TRACES / "f_pen_mouse_touch" / "evemu" / "saitek_cyborg_rat5_mouse.events",
         TRACES / "f_pen_mouse_touch" / "evemu" / "saitek_cyborg_rat5_mouse.desc",
         TRACES / "b_hid" / "evemu" / "madcatz_wired_xbox360_controller.evemu"]
FUSION = TRACES / "a_imu_csv" / "fusion_sensor_data.csv"


def need(path: Path) -> bytes:
    if not path.is_file():
        pytest.skip(f"trace {path.name} not found at {path} (../shared/traces must sit beside the project)")
    return path.read_bytes()


def char_device() -> str:
    """``/dev/zero`` (endless), or another character device if a test run elsewhere removed it."""
    for p in ("/dev/zero", "/dev/full", "/dev/null"):
        if os.path.exists(p) and stat.S_ISCHR(os.stat(p).st_mode):
            return p
    pytest.skip("no character device to read")


@pytest.fixture
def fifo(tmp_path: Path) -> str:
    p = tmp_path / "fifo"
    os.mkfifo(p)
    return str(p)


def sparse(tmp_path: Path, size: int, name: str = "big") -> str:
    p = tmp_path / name
    with open(p, "wb") as f:
        f.truncate(size)
    return str(p)


def readers():
    return [("evemu events", evemu.parse_events, TraceError), ("evemu desc", evemu.parse_desc, TraceError),
            ("hid-recorder", parse_hid_recording, TraceError),
            ("synth csv", lambda p: open_transport(f"synth://imu?csv={p}&realtime=false"), ConfigError)]


@pytest.mark.parametrize(("name", "read", "error"), readers())
def test_devices_fifos_oversized_and_line_less_files_are_refused(name, read, error, fifo, tmp_path):
    with pytest.raises(error, match="character device, not a regular file"):
        read(char_device())
    with pytest.raises(error, match="a FIFO, not a regular file"):
        read(fifo)  # refused without opening it for reading (which would wait for a writer)
    cap = synth.MAX_CSV_BYTES if name == "synth csv" else MAX_TRACE_BYTES
    with pytest.raises(error, match=r"is 33\.0 MiB; at most 32\.0 MiB|is 65\.0 MiB; at most 64\.0 MiB"):
        read(sparse(tmp_path, cap + (1 << 20)))
    with pytest.raises(error, match="line of"):
        read(sparse(tmp_path, 1 << 20, "zeros"))  # a million NUL bytes, no line end


@pytest.mark.parametrize("t", ["nan", "inf", "-inf", "1e300"])
def test_times_that_are_not_seconds_are_refused(t, tmp_path):
    ev = tmp_path / "t.events"
    ev.write_text(f"E: 0.000000 0002 0000 1\nE: {t} 0000 0000 0\n")
    with pytest.raises(TraceError, match=rf"t\.events:2: malformed event line 'E: {t} .*not a time"):
        evemu.parse_events(str(ev))
    hid = tmp_path / "t.hid"
    hid.write_text(f"R: 2 09 30\nE: {t} 1 01\n")
    with pytest.raises(TraceError, match=r"t\.hid:2: malformed E: line"):
        parse_hid_recording(str(hid))


def test_reports_and_descriptors_longer_than_linux_allows_are_refused(tmp_path):
    hid = tmp_path / "long.hid"
    n = HID_MAX_BUFFER_SIZE + 1
    hid.write_text(f"R: 2 09 30\nE: 0.0 {n} " + "00 " * n + "\n")
    with pytest.raises(TraceError, match=r"E: 16385 bytes, more than a report can be \(16384\)"):
        parse_hid_recording(str(hid))
    n = HID_MAX_DESCRIPTOR_SIZE + 1
    hid.write_text(f"R: {n}\n" + "09 30\n" * (n // 2) + "c0\n")
    with pytest.raises(TraceError, match=r"R: 4097 bytes, more than a report descriptor can be \(4096\)"):
        parse_hid_recording(str(hid))


# -- mutated real traces -------------------------------------------------------------------------------
_NUMBER = re.compile(rb"-?\d+(?:\.\d+)?|\b[0-9a-f]{2}\b")
_ODD = [b"nan", b"inf", b"1e999", b"-1e308", b"99999999999999999999", b"0x", b"-", b"", b"ff " * 5000,
        b"4294967295", b"18446744073709551616"]


def mutate(rng: random.Random, text: bytes) -> bytes:
    """Structure-aware damage: numbers replaced by odd ones, lines repeated, merged, cut or swapped,
    bytes flipped."""
    b = bytearray(text)
    for _ in range(rng.randint(1, 6)):
        op = rng.randrange(6)
        if op == 0:
            nums = list(_NUMBER.finditer(bytes(b)))
            if nums:
                m = rng.choice(nums)
                b[m.start():m.end()] = rng.choice(_ODD)
        elif op == 1 and b:
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
        elif op in (2, 3, 4):
            lines = bytes(b).split(b"\n")
            i = rng.randrange(len(lines))
            if op == 2:
                lines[i:i] = [lines[i]] * rng.randint(1, 200)
            elif op == 3 and i + 1 < len(lines):
                lines[i:i + 2] = [lines[i] + b" " + lines[i + 1]]
            else:
                j = rng.randrange(len(lines))
                lines[i], lines[j] = lines[j], lines[i]
            b = bytearray(b"\n".join(lines))
        else:
            del b[rng.randrange(len(b) + 1):]
    return bytes(b)


def _within_bounds(out: object) -> None:
    if isinstance(out, list):  # evemu frames
        assert all(math.isfinite(f.t) and abs(f.t) < evemu.MAX_TIME_S for f in out)
    elif isinstance(out, dict):  # hid-recorder devices
        for dev in out.values():
            assert len(dev.rdesc) <= HID_MAX_DESCRIPTOR_SIZE
            assert all(math.isfinite(t) and len(r) <= HID_MAX_BUFFER_SIZE for t, r in dev.events)


MUTATIONS = 150  # per trace


def _play_csv(path: str) -> None:
    """Open ``synth://imu?csv=path`` and read what it plays (at most 100 chunks)."""
    t = open_transport(f"synth://imu?csv={path}&realtime=false")
    t.open()
    try:
        for _ in range(100):
            t.read(0.01)
    except EndOfStream:
        pass
    finally:
        t.close()


@pytest.mark.parametrize("which", ["hid-recorder", "evemu-events", "evemu-desc", "evemu-xbox", "synth-csv"])
def test_mutated_real_traces_parse_within_bounds_or_are_refused(which, tmp_path):
    src, read, error = {
        "hid-recorder": (ROLLER, parse_hid_recording, TraceError),
        "evemu-events": (EVEMU[0], evemu.parse_events, TraceError),
        "evemu-desc": (EVEMU[1], evemu.parse_desc, TraceError),
        "evemu-xbox": (EVEMU[2], evemu.parse_events, TraceError),
        "synth-csv": (FUSION, _play_csv, ConfigError),
    }[which]
    text = need(src)
    if which == "synth-csv":
        text = b"\n".join(text.split(b"\n")[:60])  # the header and a few rows are enough to damage
    rng = random.Random(f"16b-{which}")
    path = tmp_path / src.name
    parsed = refused = 0
    for _ in range(MUTATIONS):
        path.write_bytes(mutate(rng, text))
        try:
            out = read(str(path))
        except error:
            refused += 1
            continue
        _within_bounds(out)
        parsed += 1
    assert parsed + refused == MUTATIONS and parsed


def test_hostile_trace_files_are_refused_under_a_1_gib_address_space_limit(tmp_path, fifo):
    """A full-size line-less file for each reader, /dev/zero and a FIFO: each refused, in a process that
    may not map more than 1 GiB (the unbounded readers grew until stopped, or waited for ever)."""
    big = sparse(tmp_path, MAX_TRACE_BYTES)
    csv = sparse(tmp_path, synth.MAX_CSV_BYTES, "csv")
    dev = char_device()
    code = textwrap.dedent(f"""
        import resource
        resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))
        from capture.errors import ConfigError, EndOfStream, TraceError
        from devices.transports import open_transport
        from sim_devices import evemu
        from sim_devices.hid_recorder import parse_hid_recording
        cases = [(evemu.parse_events, p) for p in ({big!r}, {dev!r}, {fifo!r})]
        cases += [(parse_hid_recording, p) for p in ({big!r}, {dev!r}, {fifo!r})]
        cases += [(lambda p: open_transport("synth://imu?csv=" + p), p) for p in ({csv!r}, {dev!r}, {fifo!r})]
        for read, p in cases:
            try:
                read(p)
                print("accepted", p)
            except (ConfigError, TraceError) as exc:
                print("refused:", exc)
        # VmHWM: this process image's own peak (ru_maxrss carries a big parent's peak over fork and exec)
        peak = [ln for ln in open("/proc/self/status") if ln.startswith("VmHWM:")]
        print("maxrss_kib", int(peak[0].split()[1]))
    """)
    env = {"PATH": "/usr/bin:/bin", "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env,
                         cwd=ROOT, check=False)
    assert res.returncode == 0, res.stderr
    assert res.stdout.count("refused:") == 9 and "accepted" not in res.stdout, res.stdout
    rss_kib = int(res.stdout.split("maxrss_kib")[1])
    assert rss_kib < 512 * 1024


def test_dispel_phone_recordings_are_read_within_bounds(tmp_path, fifo):
    from sim_devices.phone_sim import dispel_samples

    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000)   # json.loads alone raised RecursionError
    for path, message in ((char_device(), "character device"), (fifo, "a FIFO"), (str(deep), "nests deeper"),
                          (sparse(tmp_path, (64 << 20) + 1), r"at most 64\.0 MiB")):
        with pytest.raises(ValueError, match=message):
            dispel_samples(path)
