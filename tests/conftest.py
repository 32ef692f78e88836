"""Shared fixtures. Hardware tests are opt-in: ``--hil-device=SPEC`` (any device string, e.g.
``witmotion@serial:///dev/ttyUSB0?rate=200``); without it they skip and name the flag."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parent.parent.parent / "shared"
TRACES = SHARED / "traces"
XIO_CSV = TRACES / "a_imu_csv" / "fusion_sensor_data.csv"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--hil-device", action="append", default=[], metavar="SPEC",
                     help="run hardware-in-the-loop tests against this device string (repeatable)")
    parser.addoption("--hil-serial", default=None, metavar="PORT",
                     help="a serial IMU port for HIL tests (e.g. /dev/ttyUSB0); same as --hil-device=witmotion@serial://PORT")


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
    deadline = time.monotonic() + 5.0
    while True:
        left = [t.name for t in threading.enumerate() if t.name.startswith(("reader-", "bus-")) and t.is_alive()]
        if not left or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    assert not left, f"threads left running: {left}"


@pytest.fixture
def session_path(tmp_path: Path) -> str:
    return os.fspath(tmp_path / "take.mcap")
