"""``perfcap devices`` lists the Linux input devices (or says why it cannot); ``perfcap record`` and
``perfcap replay`` take an evemu recording through ``simevdev://`` and the evdev kind."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from devices.transports import evdev as evdev_transport
from devices.transports.evdev import AbsInfo, Capabilities, InputDeviceInfo
from tests.cli.cli_helpers import run

TRACE = (Path(__file__).resolve().parents[2].parent / "shared" / "traces" / "f_pen_mouse_touch" / "evemu"
         / "wacom_intuos4_6x9.stylus-drag.events")


def _tablet() -> InputDeviceInfo:
    caps = Capabilities("Wacom Intuos4 6x9 Pen", 3, 0x56A, 0xB9, 0x104,
                        {1: frozenset({0x140, 0x14A}), 3: frozenset({0, 1, 0x18})},
                        {0: AbsInfo(0, 44704, 4, 0, 200), 1: AbsInfo(0, 27940, 4, 0, 200), 0x18: AbsInfo(0, 2047)})
    return InputDeviceInfo("/dev/input/event7", caps.name, 0x56A, 0xB9, 3, "usb-0000:00:14.0-1/input0", caps)


def test_devices_lists_input_devices_with_their_capabilities(capsys, monkeypatch):
    monkeypatch.setattr(evdev_transport, "list_input_devices", lambda: [_tablet()])
    code, out, _ = run(capsys, "devices")
    assert code == 0 and "input devices" in out
    assert "/dev/input/event7  [056a:00b9] Wacom Intuos4 6x9 Pen: pen tablet" in out
    assert "abs 0x0 0..44704 @200/mm" in out and "open as evdev:///dev/input/event7" in out
    assert "evdev: Linux input device" in out and "simevdev:///PATH.events" in out
    code, out, _ = run(capsys, "devices", "--json")
    doc = json.loads(out)
    (d,) = doc["input_devices"]
    assert d["vid_pid"] == "056a:00b9" and d["likely"] == "pen tablet" and d["absinfo"]["0"] == [0, 44704, 4, 0, 200]


def test_devices_says_why_it_cannot_list_input_devices(capsys, monkeypatch):
    def missing() -> list[InputDeviceInfo]:
        evdev_transport._evdev()
        return []

    monkeypatch.setitem(__import__("sys").modules, "evdev", None)  # as if python-evdev were not installed
    monkeypatch.setattr(evdev_transport, "list_input_devices", missing)
    code, out, _ = run(capsys, "devices")
    assert code == 0 and "cannot list them: evdev:// needs python-evdev" in out and "perfcap[evdev]" in out


def test_record_and_replay_an_evemu_tablet(capsys, tmp_path):
    if not TRACE.is_file():
        pytest.skip(f"trace {TRACE.name} not found (../shared/traces must sit beside the project)")
    take = str(tmp_path / "pen.mcap")
    code, _, err = run(capsys, "record", "-d", f"tab=simevdev://{TRACE}?realtime=false", "-o", take)
    assert code == 0, err
    code, out, err = run(capsys, "info", take, "--json")
    assert code == 0, err
    streams = {s["name"]: s for s in json.loads(out)["streams"]}
    assert streams["tab/pen"]["samples"] == 357  # 361 frames; 4 carry no pen event
    code, out, err = run(capsys, "replay", take, "--fast", "--json")
    assert code == 0, err + out
    assert json.loads(out)["verification"]["equal"]  # the recorded capabilities rebuilt the same streams
