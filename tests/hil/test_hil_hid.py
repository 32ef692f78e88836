"""Hardware in the loop (opt-in): real HID devices through hidapi.

    pytest tests/hil/test_hil_hid.py --hil-controller=054c:0ce6     # move the controller
    pytest tests/hil/test_hil_hid.py --hil-mouse=046d:c077          # move the mouse
    pytest tests/hil/test_hil_hid.py --hil-tablet=056a:00b9         # draw with the pen
"""

from __future__ import annotations

import numpy as np
import pytest

from capture.app.orchestrator import Capture
from capture.app.replay import replay_session
from capture.session import SessionReader

pytestmark = pytest.mark.hil


def test_real_controller_imu_at_its_native_rate_with_device_time(hil_controller, session_path):
    rep = Capture([f"pad=hid://{hil_controller}"], output=session_path).run(3.0)
    assert rep.recorder_error is None and rep.devices["pad"]["state"] != "failed", rep.devices
    imu = SessionReader(session_path).samples("pad/imu")
    assert len(imu) > 100
    assert imu.t_device_ns is not None  # the controller's own clock drives the timestamps
    assert np.all(np.diff(imu.t_bus_ns) >= 0)  # never back (capture/clocksync.py); reports may share an arrival
    acc = imu.values[:, 0:3]
    assert 5.0 < float(np.median(np.linalg.norm(acc, axis=1))) < 15.0  # gravity in m/s^2: calibration applied
    assert replay_session(session_path, speed=0).verification["equal"]


@pytest.mark.parametrize("which", ["mouse", "tablet"])
def test_real_pointer_devices_record_and_replay(which, request, session_path):
    vidpid = request.getfixturevalue(f"hil_{which}")
    rep = Capture([f"{which}=hid@hid://{vidpid}"], output=session_path).run(3.0)
    assert rep.recorder_error is None and rep.devices[which]["state"] != "failed", rep.devices
    assert any(s["samples"] > 0 for s in rep.streams.values()), "no reports: move the device during the test"
    assert replay_session(session_path, speed=0).verification["equal"]
