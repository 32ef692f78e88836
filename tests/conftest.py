"""Shared fixtures. Hardware tests are opt-in: ``--hil-device=SPEC`` (any device string, e.g.
``witmotion@serial:///dev/ttyUSB0?rate=200``); without it they skip and name the flag."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import lsl_helpers
import phone_session_helpers
import pytest
from wait_helpers import DEADLINE_S

SHARED = Path(__file__).resolve().parent.parent.parent / "shared"
TRACES = SHARED / "traces"
XIO_CSV = TRACES / "a_imu_csv" / "fusion_sensor_data.csv"

lsl_helpers.configure()  # LSL discovery stays on this machine, one session per run (before pylsl is loaded)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--hil-device", action="append", default=[], metavar="SPEC",
                     help="run hardware-in-the-loop tests against this device string (repeatable)")
    parser.addoption("--hil-serial", default=None, metavar="PORT",
                     help="a serial IMU port for HIL tests (e.g. /dev/ttyUSB0); same as --hil-device=witmotion@serial://PORT")
    parser.addoption("--hil-controller", default=None, metavar="VID:PID",
                     help="a motion controller for HID HIL tests "
                          "(054c:0ce6 DualSense, 054c:05c4 DS4, 057e:2009 Switch Pro)")
    parser.addoption("--hil-mouse", default=None, metavar="VID:PID", help="a mouse for HID HIL tests (move it)")
    parser.addoption("--hil-tablet", default=None, metavar="VID:PID", help="a pen tablet for HID HIL tests (draw)")


def _hil_hid(request: pytest.FixtureRequest, flag: str) -> str:
    v = request.config.getoption(flag)
    if not v:
        pytest.skip(f"needs real hardware: pass {flag}=VID:PID")
    return str(v)


@pytest.fixture
def hil_controller(request: pytest.FixtureRequest) -> str:
    return _hil_hid(request, "--hil-controller")


@pytest.fixture
def hil_mouse(request: pytest.FixtureRequest) -> str:
    return _hil_hid(request, "--hil-mouse")


@pytest.fixture
def hil_tablet(request: pytest.FixtureRequest) -> str:
    return _hil_hid(request, "--hil-tablet")


@pytest.fixture
def hil_devices(request: pytest.FixtureRequest) -> list[str]:
    devs = list(request.config.getoption("--hil-device"))
    port = request.config.getoption("--hil-serial")
    if port:
        devs.append(f"witmotion@serial://{port}")
    if not devs:
        pytest.skip("needs real hardware: pass --hil-device=SPEC or --hil-serial=/dev/ttyUSB0")
    return devs


@pytest.fixture
def xio_csv() -> Path:
    if not XIO_CSV.is_file():
        pytest.skip(f"real IMU trace not found at {XIO_CSV} (../shared/traces must sit beside the project)")
    return XIO_CSV


@pytest.fixture(autouse=True)
def _no_leaked_threads():
    """Every test must stop its device readers and bus subscribers."""
    yield
    deadline = time.monotonic() + DEADLINE_S
    while True:
        left = [t.name for t in threading.enumerate() if t.name.startswith(("reader-", "bus-")) and t.is_alive()]
        if not left or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    assert not left, f"threads left running: {left}"


@pytest.fixture
def session_path(tmp_path: Path) -> str:
    return os.fspath(tmp_path / "take.mcap")


@pytest.fixture(scope="session")
def record_phone_session():
    """The recorder of simulated phone-page sessions (a function: path, duration_s, touch, seed, motion;
    ``phone_session_helpers.record_phone_session``)."""
    return phone_session_helpers.record_phone_session
