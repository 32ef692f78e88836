"""Import formats as the reference tools read them: hid-recorder captures with free-text lines
(hid-replay skips lines it does not know; perfcap counts and logs them), single-file evemu recordings
(``evemu-record``: description and events in one file), and wheels whose sums survive the replay.
Every hid-recorder and evemu trace in ``../shared/traces`` is read in place."""

from __future__ import annotations

import random
import re
from pathlib import Path

import pytest

from capture.errors import EndOfStream
from devices import open_device
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
