"""``perfcap demo`` as a user runs it from a fresh clone (no hardware, no ../shared beside the cwd), and its
session as the field's tools see it: a generic check written without perfcap's code
(``tests/generic_mcap_check.py``: every channel decodes with ``mcap-protobuf-support`` or as JSON against its
JSON Schema, log times on the wall clock and monotonic per channel, no publish time after its log time) and the
official TypeScript reader (``@mcap/core``, ``tests/js_reader_helpers.py``) reading every message."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from typing import TYPE_CHECKING

import generic_mcap_check
import js_reader_helpers
import pytest
from mcap.reader import make_reader

if TYPE_CHECKING:
    from pathlib import Path


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, subprocess.CompletedProcess[str]]:
    tmp = tmp_path_factory.mktemp("demo")
    env = {k: v for k, v in os.environ.items() if not k.startswith("PERFCAP_")}
    p = subprocess.run([sys.executable, "-m", "capture.app.cli", "demo", "--duration", "2", "-q",
                        "-o", str(tmp / "demo.mcap")], cwd=tmp, env=env, capture_output=True, text=True,
                       timeout=300, check=False)
    return tmp / "demo.mcap", p


def test_console_script_and_demo_run_without_shared(demo: tuple[Path, subprocess.CompletedProcess[str]]) -> None:
    path, p = demo
    assert p.returncode == 0, p.stderr
    assert "all" in p.stdout and "equal the recorded ones" in p.stdout
    assert "Traceback" not in p.stderr
    assert "ERROR" not in p.stderr, p.stderr  # e.g. a subscriber failing on an item is logged, not raised
    p2 = subprocess.run([sys.executable, "-m", "capture.app.cli", "info", str(path), "--json"],
                        capture_output=True, text=True, timeout=300, check=False)
    s = json.loads(p2.stdout)
    # hand: pty serial IMU; pad, pen: simulated HID; phone: the page over TLS + WebSocket
    assert {x["device"] for x in s["streams"]} == {"wrist", "ankle", "head", "hand", "pad", "pen", "phone"}


def test_the_demo_session_passes_the_generic_check(demo: tuple[Path, subprocess.CompletedProcess[str]]) -> None:
    path, p = demo
    assert p.returncode == 0, p.stderr
    rep = generic_mcap_check.check(path)
    assert rep.problems == []
    topics = set(rep.messages)
    devices = {"wrist", "ankle", "head", "hand", "pad", "pen", "phone"}
    # every device's raw bytes and samples, every sample stream viewable, every IMU's orientation in 3D, the log
    assert {t.split("/")[2] for t in topics if t.startswith("/raw/")} == devices
    streams = {t.removeprefix("/samples/") for t in topics if t.startswith("/samples/")}
    assert streams and streams == {t.removeprefix("/view/") for t in topics if t.startswith("/view/")}
    assert {t for t in topics if t.startswith("/tf/")} >= {f"/tf/{d}/orientation" for d in ("wrist", "ankle",
                                                                                            "head", "pad")}
    assert rep.schemas["/tf/wrist/orientation"] == "protobuf:foxglove.FrameTransform"
    assert rep.schemas["/log"] == "protobuf:foxglove.Log" and rep.messages["/log"] > 0
    assert rep.schemas["/events"] == "json:perfcap.DeviceEvent"
    for stream in streams:   # one message per sample
        assert rep.messages[f"/view/{stream}"] >= rep.messages[f"/samples/{stream}"]


def test_the_typescript_reader_reads_every_message(demo: tuple[Path, subprocess.CompletedProcess[str]]) -> None:
    path, p = demo
    assert p.returncode == 0, p.stderr
    ts = js_reader_helpers.read_session(path)
    with path.open("rb") as f:
        py = sum(1 for _ in make_reader(f).iter_messages(log_time_order=False))
    assert ts["error"] is None and ts["complete"] and ts["reader"] == "indexed"
    assert ts["messageCount"] == py > 0
    assert ts["logTimesMonotonic"] and not ts["publishAfterLog"]
    assert ts["profile"] == "perfcap" and "perfcap.session" in ts["metadata"]
