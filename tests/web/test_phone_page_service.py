"""The built-in phone page end to end: headless Chromium loads it from the real ``perfcap serve``
service over HTTPS (its self-signed certificate), pairs with the token in the link, and synthetic
motion, orientation and touch events dispatched in the page arrive on the bus through TLS, the
WebSocket, the gateway, the phone's inbox, the page codec and its device, and in the recording."""

from __future__ import annotations

import itertools
import math
import os
from typing import Any

import pytest
from wait_helpers import DEADLINE_S, wait_until

from capture.app.serve.config import ServeConfig
from capture.app.serve.service import Service, ServiceThread
from capture.bus import Subscriber
from capture.sample import Sample, SampleBatch
from capture.session import SessionReader

TOKEN = "browser-test-token-0123456789"


class Collect(Subscriber):
    accepts = frozenset({Sample, SampleBatch})

    def __init__(self) -> None:
        self.samples: list[Sample] = []

    def on_item(self, item: Any) -> None:
        if type(item) is Sample:
            self.samples.append(item)
        else:
            self.samples.extend(item.samples())

    def of(self, suffix: str) -> list[Sample]:
        return [s for s in list(self.samples) if s.stream.endswith(suffix)]


@pytest.fixture
def service(tmp_path):
    svc = Service(ServeConfig(host="127.0.0.1", port=0, control_port=-1, mdns=False, state_dir=str(tmp_path / "st"),
                              token=TOKEN))
    svc.capture.start_recording(str(tmp_path / "take.mcap"))
    col = Collect()
    svc.capture.subscribe(col, name="collect")
    th = ServiceThread(svc).start()
    yield svc, th, col, str(tmp_path / "take.mcap")
    th.stop()


def wait_for(what: str, cond: Any) -> Any:
    return wait_until(cond, DEADLINE_S, what)


MOTION_JS = """(vals) => {
  const out = [];
  for (const v of vals) {
    const before = performance.now();
    window.dispatchEvent(new DeviceMotionEvent("devicemotion", {
      acceleration: {x: v[0], y: v[1], z: v[2]},
      accelerationIncludingGravity: {x: v[3], y: v[4], z: v[5]},
      rotationRate: {alpha: v[6], beta: v[7], gamma: v[8]},
      interval: 16}));
    out.push([before, performance.now()]);
  }
  return out;
}"""


def test_page_from_the_service_streams_to_the_bus_over_tls(service, page, console_errors):
    svc, th, col, path = service
    ep = svc.endpoints
    assert ep.page_url.startswith("https://") and ep.fingerprint
    url = ep.pair_url.replace(ep.page_url.split("://", 1)[1].split(":", 1)[0], "127.0.0.1", 1)
    page.goto(url)
    assert page.evaluate("location.protocol") == "https:"
    assert page.evaluate("window.perfcap.start()") is True
    page.wait_for_function("window.perfcap.state === 'live'")
    device = page.evaluate("window.perfcap.device")
    assert device and device.startswith("phone-")

    vals = [[0.5 + i, -1.0, 0.25, 1.5 + i, 9.5, -2.0, 90.0, -45.0, 180.0 + i] for i in range(30)]
    times = page.evaluate(MOTION_JS, vals)
    page.evaluate("""() => window.dispatchEvent(new DeviceOrientationEvent("deviceorientation",
                     {alpha: 12.5, beta: -30.25, gamma: 5.5, absolute: false}))""")
    box = page.locator("#pad").bounding_box()
    assert box is not None
    page.touchscreen.tap(round(box["x"] + box["width"] / 2), round(box["y"] + box["height"] / 2))

    imu = wait_for("30 imu samples", lambda: len(col.of("/imu")) >= 30 and col.of("/imu"))
    assert [s.stream for s in imu] == [f"{device}/imu"] * 30
    d2r = math.pi / 180.0
    for s, v in zip(imu, vals, strict=True):  # accelerationIncludingGravity, rotationRate deg/s -> rad/s about x, y, z
        assert s.values == pytest.approx((v[3], v[4], v[5], v[6] * d2r, v[7] * d2r, v[8] * d2r))
    user = wait_for("user_acc", lambda: len(col.of("/user_acc")) >= 30 and col.of("/user_acc"))
    assert [tuple(s.values) for s in user] == [tuple(v[:3]) for v in vals]
    # device time = the event's timeStamp (the page's clock); bus times follow it in order
    for s, (before, after) in zip(imu, times, strict=True):  # event.timeStamp: made during dispatch (0.1 ms resolution)
        assert before * 1e6 - 1e5 <= s.t_device_ns <= after * 1e6 + 1e5
    assert all(a.t_bus_ns <= b.t_bus_ns for a, b in itertools.pairwise(imu))
    assert all(s.t_bus_ns <= s.t_host_ns for s in imu)
    att = wait_for("attitude", lambda: col.of("/attitude"))
    assert att[0].values == pytest.approx((12.5, -30.25, 5.5), abs=1e-9) or att[0].values[:3] == pytest.approx(
        (12.5, -30.25, 5.5))
    touch = wait_for("touch start and end", lambda: len(col.of("/touch")) >= 2 and col.of("/touch"))
    assert touch[0].values[0] == 0 and touch[-1].values[0] in (2, 3)  # phase: start ... end
    assert not console_errors

    # the recording holds the same samples, and replays through the same codec. (The page leaves
    # first: a page reconnecting while the loop closes leaves a half-open TLS socket that asyncio
    # reports as unclosed, which this suite treats as an error.)
    page.goto("about:blank")
    th.stop()
    r = SessionReader(path)
    rec = r.samples(f"{device}/imu")
    assert len(rec) == len(col.of("/imu")) == 30
    dev = r.devices[device]
    assert dev.kind == "phone" and "token" not in str(dev.options)
    raw = b"".join(c.data for c in r.raw_chunks(device))
    assert TOKEN.encode() not in raw, "the pairing token must never be recorded"
    from capture.app.replay import replay_session

    rep = replay_session(path, speed=0)
    assert rep.verification and rep.verification["equal"], rep.verification
    assert os.path.getsize(path) > 0
