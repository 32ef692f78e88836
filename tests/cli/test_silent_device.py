"""A device that sends data but yields no sample says so (issue 17): a warning naming the device and
the report IDs its kind cannot decode, the count per ID in its health, and ``perfcap record`` exits 1
with a line saying why; a take in which some reports decode exits 0 and lists the others.

The family: the real hid-recorder trace in ``../shared/traces`` (read in place), and captures written
here with its real descriptor and seeded random report IDs, some absent from the descriptor, some
in it but outside what the ``hid`` kind publishes (the keyboard and consumer reports of the mouse,
as a Wacom's vendor pen report)."""

from __future__ import annotations

import json
import os
import random
import threading
import tty
from pathlib import Path

import pytest

from devices.hid.descriptor import parse_descriptor
from sim_devices.hid_recorder import parse_hid_recording
from tests.cli.cli_helpers import run

ROLLER = Path(__file__).resolve().parents[3] / "shared" / "traces" / "b_hid" / "hid_recorder" / \
    "contour_rollermouse_red_doubleclick.hid"
#: the report IDs of the roller mouse's descriptor the ``hid`` kind does not publish (keyboard, consumer)
NOT_PUBLISHED = (2, 3)


def _roller() -> tuple[bytes, list[bytes]]:
    if not ROLLER.exists():
        pytest.skip(f"trace {ROLLER} is not here")
    dev = next(iter(parse_hid_recording(str(ROLLER)).values()))
    return dev.rdesc, [bytes(r) for _, r in dev.events]


def _write(path: Path, rdesc: bytes, reports: list[bytes]) -> str:
    lines = [f"R: {len(rdesc)} {rdesc.hex(' ')}", "N: test capture", "I: 3 0b33 1004"]
    lines += [f"E: {i // 1000:06d}.{(i % 1000) * 1000:06d} {len(r)} {r.hex(' ')}" for i, r in enumerate(reports)]
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def _take(capsys, tmp_path: Path, capture: str) -> tuple[int, dict, str]:
    out = str(tmp_path / "t.mcap")
    code, stdout, err = run(capsys, "record", "-q", "--json", "--overwrite", "--duration", "5",
                            "-d", f"m=hid@simhid://{capture}?realtime=false", "-o", out)
    return code, json.loads(stdout), err


def _undecodable(rng: random.Random, rdesc: bytes, n: int) -> tuple[list[bytes], set[int]]:
    """``n`` reports, each a random ID absent from the descriptor or one it has but not published."""
    layout = parse_descriptor(rdesc, "test")
    sizes = {rid: r.size for rid, r in layout.reports.items()}
    reps, ids = [], set()
    for _ in range(n):
        if rng.random() < 0.5:
            rid = rng.choice(NOT_PUBLISHED)
            size = sizes[rid]
        else:
            rid = rng.choice([i for i in range(1, 256) if i not in sizes])
            size = rng.randint(1, 64)
        ids.add(rid)
        reps.append(bytes([rid]) + rng.randbytes(size - 1))
    return reps, ids


def test_the_real_trace_records_and_exits_0(capsys, tmp_path):
    _roller()
    code, rep, err = _take(capsys, tmp_path, str(ROLLER))
    assert code == 0, err
    assert rep["silent"] == {} and rep["devices"]["m"]["undecoded"] == {}
    assert rep["streams"]["m/buttons"]["samples"] == 6


@pytest.mark.parametrize("seed", range(6))
def test_a_device_whose_reports_all_fail_to_decode_fails_the_take(capsys, caplog, tmp_path, seed):
    rdesc, _ = _roller()
    rng = random.Random(seed)
    reps, ids = _undecodable(rng, rdesc, rng.randint(1, 30))
    code, rep, err = _take(capsys, tmp_path, _write(tmp_path / "c.hid", rdesc, reps))
    assert code == 1
    names = {f"report 0x{i:02x}" for i in ids}
    assert set(rep["devices"]["m"]["undecoded"]) == names
    assert sum(rep["devices"]["m"]["undecoded"].values()) == len(reps)
    line = next(ln for ln in err.splitlines() if ln.startswith("perfcap: error: device m "))
    assert "no sample was recorded" in line and all(n in line for n in names)
    # a warning during the take names the device and each ID, once (of the first five IDs)
    warned = [r.getMessage() for r in caplog.records if "this device kind cannot decode it" in r.getMessage()]
    assert len(warned) == min(5, len(names))
    assert all(w.startswith("device m (hid): report 0x") for w in warned)
    assert len({w.split(" arrived")[0] for w in warned}) == len(warned)


@pytest.mark.parametrize("seed", range(6))
def test_some_decoded_reports_make_a_good_take_that_lists_the_others(capsys, tmp_path, seed):
    rdesc, real = _roller()
    rng = random.Random(100 + seed)
    bad, ids = _undecodable(rng, rdesc, rng.randint(1, 20))
    good = [rng.choice(real) for _ in range(rng.randint(1, 10))]
    reps = bad + good
    rng.shuffle(reps)
    code, rep, err = _take(capsys, tmp_path, _write(tmp_path / "c.hid", rdesc, reps))
    assert code == 0, err
    assert rep["silent"] == {}
    assert rep["streams"]["m/buttons"]["samples"] == len(good)
    assert set(rep["devices"]["m"]["undecoded"]) == {f"report 0x{i:02x}" for i in ids}


def test_the_text_summary_lists_what_was_not_decoded(capsys, tmp_path):
    rdesc, real = _roller()
    reps = [bytes([0x09]) + bytes(4)] * 3 + real
    out = str(tmp_path / "t.mcap")
    code, stdout, _ = run(capsys, "record", "-q", "--duration", "5",
                          "-d", f"m=hid@simhid://{_write(tmp_path / 'c.hid', rdesc, reps)}?realtime=false", "-o", out)
    assert code == 0
    assert "not decoded: report 0x09 (3x)" in stdout


@pytest.mark.parametrize("seed", range(3))
def test_a_serial_device_that_gets_only_noise_fails_the_take(capsys, tmp_path, seed):
    """Not a HID kind: a WitMotion on a pty that gets only random bytes (no 0x55 header, so no
    frame) says what it received (chunks, bytes, frames) and the take exits 1."""
    rng = random.Random(seed)
    noise = bytes(b for b in rng.randbytes(4096) if b != 0x55)
    master, slave = os.openpty()
    tty.setraw(slave)
    done = threading.Event()

    def feed() -> None:
        while not done.is_set():
            os.write(master, noise[: rng.randint(16, len(noise))])
            done.wait(0.02)

    t = threading.Thread(target=feed, daemon=True)
    t.start()
    try:
        code, stdout, err = run(capsys, "record", "-q", "--json", "--duration", "1.5",
                                "-d", f"wt=witmotion@serial://{os.ttyname(slave)}", "-o", str(tmp_path / "t.mcap"))
    finally:
        done.set()
        t.join(10)
        os.close(master)
        os.close(slave)
    assert code == 1, err
    rep = json.loads(stdout)
    assert rep["devices"]["wt"]["bytes"] > 0 and set(rep["silent"]) == {"wt"}
    line = next(ln for ln in err.splitlines() if ln.startswith("perfcap: error: device wt "))
    assert "no sample was recorded" in line and "bytes" in line and "0 frames decoded" in line
