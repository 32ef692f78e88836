"""Hardware in the loop (opt-in): record real devices for two seconds and check the samples.

Run with ``pytest tests/hil --hil-device='wrist=witmotion@serial:///dev/ttyUSB0?rate=200'``."""

from __future__ import annotations

import pytest

from capture.app.orchestrator import Capture
from capture.app.replay import replay_session

pytestmark = pytest.mark.hil


def test_real_devices_record_and_replay_equal(hil_devices, session_path):
    rep = Capture(hil_devices, output=session_path).run(2.0)
    assert rep.recorder_error is None
    assert any(s["samples"] > 0 for s in rep.streams.values()), rep.devices
    for s in rep.streams.values():
        if s["samples"] > 10:
            assert s["rate_hz"] > 0
    assert replay_session(session_path, speed=0).verification["equal"]
