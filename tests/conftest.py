"""Shared fixtures. Hardware tests are opt-in: ``--hil-device=SPEC`` (any device string, e.g.
``witmotion@serial:///dev/ttyUSB0?rate=200``); without it they skip and name the flag."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import pytest
from wait_helpers import DEADLINE_S, wait_until

SHARED = Path(__file__).resolve().parent.parent.parent / "shared"
TRACES = SHARED / "traces"
XIO_CSV = TRACES / "a_imu_csv" / "fusion_sensor_data.csv"


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


# -- a recorded session of the simulated phone page (puppet tests: CLI and unit) ------------------


def _record_phone_session(path: Path, duration_s: float = 3.0, touch: tuple[float, float] | None = None,
                          seed: int = 3, motion: str = "waving") -> Path:
    """A perfcap session of the built-in phone page: simulated page messages (waving motion, attitude
    every third event) through the real page codec, ``PhonePage``, clock sync and recorder. ``touch``:
    one finger down from ``touch[0]`` to ``touch[1]`` seconds after the first event (moves every 50 ms);
    ``motion``: ``waving`` or ``puppeteer`` (``sim_devices.motion.phone_motion``)."""
    import uuid

    import numpy as np

    from capture.app.orchestrator import Capture
    from capture.sample import Chunk, Direction
    from devices.codecs.phone_json import PageCodec
    from devices.transports.network import drop_hub, hub
    from sim_devices.phone_sim import page_hello, page_messages

    msgs = page_messages(duration_s, seed=seed, t0_ms=1500.0, motion=motion)
    codec = PageCodec()
    rows = []
    if touch is not None:
        times = np.arange(touch[0], touch[1] + 1e-9, 0.05)
        for k, tt in enumerate(times):
            phase = 0.0 if k == 0 else (2.0 if k == len(times) - 1 else 1.0)
            rows.append((1500.0 + 1000.0 * tt + 0.25, phase, 4.0, 200.0, 300.0, 0.0, 10.0, 10.0))
    datas = []
    for m in msgs:   # each touch goes out with the first message sent after it
        mine = tuple(r for r in rows if r[0] <= m.sent_ms)
        rows = rows[len(mine):]
        datas.append((codec.encode(m.frame._replace(touches=mine)), m.sent_ms))
    name = "puppet-test-" + uuid.uuid4().hex[:10]
    box = hub(name).inbox("page/p1")
    box.connect("test")
    t0 = time.monotonic_ns()
    box.put(Chunk(page_hello(), t0, Direction.RX))
    for data, sent_ms in datas:
        box.put(Chunk(data, t0 + int(sent_ms * 1e6) + 20_000_000, Direction.RX))

    cap = Capture([f"phone=phone@net://{name}/page/p1"], output=str(path), overwrite=True)
    try:
        cap.start()
        phone = cap.devices[0]
        wait_until(lambda: phone.transport.is_open, DEADLINE_S, "the phone's reader to open its inbox")
        box.finish()  # nothing more will come: the reader drains the inbox, then the take ends
        assert all(r.join(DEADLINE_S) for r in cap.readers), "the phone's reader did not drain its inbox"
    finally:
        cap.stop()
        drop_hub(name)
    return path


@pytest.fixture(scope="session")
def record_phone_session():
    """The recorder of simulated phone-page sessions (a function: path, duration_s, touch, seed, motion)."""
    return _record_phone_session
