"""The control API of ``perfcap serve`` over real HTTP (urllib) on loopback: the bearer token on every
endpoint, what ``/api/health`` and ``/api/devices`` say about a phone streaming through TLS, recording
start/stop (with the session replayed afterwards), and connecting a SensorServer phone.
"""

from __future__ import annotations

import glob
import os
import time

import numpy as np
import pytest
from serve_helpers import DEADLINE_S

from capture import __version__
from capture.app.replay import replay_session
from capture.session import SessionReader

ENDPOINTS = [
    ("GET", "/health", None),
    ("GET", "/devices", None),
    ("POST", "/record/start", {"path": "never.mcap"}),
    ("POST", "/record/stop", None),
    ("POST", "/token/rotate", None),
    ("POST", "/sensorserver", {"host": "127.0.0.1", "port": 9}),
]


def _motion(phone, n_messages: int | None = None) -> np.ndarray:
    """Every devicemotion row the simulated phone generated (in its first ``n_messages`` messages): t,
    a xyz, g xyz, rotation rate, interval."""
    return np.array([r for m in phone.messages[:n_messages] for r in m.frame.motion], dtype=float)


def test_every_endpoint_requires_the_bearer_token(served, tmp_path):
    token = served.token
    assert served.control_url.startswith("http://127.0.0.1:")  # loopback by default
    refusals = 0
    for method, path, body in ENDPOINTS:
        for auth in (None, "Bearer wrong-token-0123456789", f"Basic {token}", f"Token {token}", "Bearer ",
                     f"Bearer {token[:-1]}"):
            status, answer = served.api(method, path, token=None, auth=auth, body=body)
            assert status == 401, (method, path, auth, status, answer)
            assert "token" in answer["error"]
            refusals += 1
    assert served.rejected() == {"missing or wrong token": refusals}
    # nothing happened behind the refusals
    assert served.token == token
    assert not (tmp_path / "never.mcap").exists() and served.service.capture.recorder is None
    assert served.service.capture.devices == []
    # the scheme is case-insensitive (RFC 6750); the right token opens every endpoint
    status, health = served.api("GET", "/health", auth=f"bearer {token}")
    assert status == 200 and health["rejected"] == {"missing or wrong token": refusals}


def test_health_and_devices_describe_a_streaming_phone(served):
    t_start = time.monotonic()
    th = served.phone("ctl-phone-1", duration_s=60.0)  # streams until it is stopped below
    ph = th.phone
    served.wait(lambda: ph.device and served.samples(f"{ph.device}/imu") >= 60, DEADLINE_S, "1 s of motion")
    status, h = served.api("GET", "/health")
    assert status == 200
    assert h["status"] == "ok" and h["version"] == __version__ and h["uptime_s"] > 0
    assert h["recording"] is None and h["devices"] == 1 and h["phones_connected"] == 1
    assert h["messages"] >= 20 and h["rejected"] == {} and h["token_required"] is True
    assert h["tls_fingerprint"] == served.fingerprint
    assert h["mdns"] == {"advertised": None, "error": None, "found": []}

    # the rate is measured on bus times: a phone held up at the start (a busy machine) sends its first
    # messages in a burst whose bus times bunch, so the measured rate settles at 60 Hz as the take goes on
    body = served.wait(lambda: (b := served.api("GET", "/devices")[1]) and 50.0 <= b["devices"][0]["rate_hz"] <= 70.0
                       and b, DEADLINE_S, "the page's 60 Hz devicemotion rate")
    assert len(body["devices"]) == 1
    d = body["devices"][0]
    name = ph.device
    assert name == "phone-ctlphone"
    assert (d["name"], d["kind"], d["state"], d["connected"], d["peer"]) == (name, "phone", "streaming", True,
                                                                              "127.0.0.1")
    assert d["url"] == f"net://{served.service.hub_name}/page/ctl-phone-1"
    assert d["drops"] == {"lost_readings": 0, "stream_gaps": 0, "protocol_errors": 0, "queue_refused": 0}
    assert 0 <= d["last_seen_s_ago"] <= time.monotonic() - t_start and d["reconnects"] == 0
    assert set(d["streams"]) == {f"{name}/{s}" for s in ("imu", "user_acc", "attitude", "touch")}
    # the clock fit of the motion streams: host time minus page time, as the simulated phone knows it
    truth_ms = (ph.t0_host_ns - ph.t0_ms * 1e6) / 1e6
    clocks = {c["stream"]: c for c in d["clock"]}  # named after the device when its streams share one fit
    imu_clock = clocks.get(f"{name}/imu") or clocks[name]
    assert imu_clock["pseudo"] is False and imu_clock["points"] > 0
    assert abs(imu_clock["offset_ms"] - truth_ms) < 10.0, (imu_clock, truth_ms)
    assert abs(imu_clock["drift_ppm"]) < 5000

    th.stop(DEADLINE_S)
    assert th.join(DEADLINE_S) and ph.error is None
    n = len(_motion(ph, ph.sent))
    n_orient = sum(len(m.frame.orientation) for m in ph.messages[:ph.sent])
    served.wait(lambda: served.samples(f"{name}/imu") == n, DEADLINE_S, "every motion event")
    served.wait(lambda: not served.api("GET", "/devices")[1]["devices"][0]["connected"], DEADLINE_S,
                "the phone to leave")
    d = served.api("GET", "/devices")[1]["devices"][0]
    assert d["samples"] == 2 * n + n_orient
    assert {k: v["samples"] for k, v in d["streams"].items()} == {
        f"{name}/imu": n, f"{name}/user_acc": n, f"{name}/attitude": n_orient, f"{name}/touch": 0}
    assert d["drops"] == {"lost_readings": 0, "stream_gaps": 0, "protocol_errors": 0, "queue_refused": 0}
    assert served.api("GET", "/health")[1]["phones_connected"] == 0


def test_record_start_stop_and_replay(served, tmp_path):
    path = str(tmp_path / "take1.mcap")
    status, ans = served.api("POST", "/record/start", body={"path": path})
    assert (status, ans) == (200, {"recording": path})
    assert os.path.exists(path)
    assert served.api("GET", "/health")[1]["recording"] == path
    status, ans = served.api("POST", "/record/start", body={"path": str(tmp_path / "take2.mcap")})
    assert status == 409 and "already recording" in ans["error"]
    assert not (tmp_path / "take2.mcap").exists()

    th = served.phone("rec-phone", duration_s=1.5)
    assert th.join(DEADLINE_S) and th.phone.error is None
    ph = th.phone
    motion = _motion(ph)
    n = len(motion)
    served.wait(lambda: served.samples(f"{ph.device}/imu") == n, DEADLINE_S, "every motion event on the bus")

    status, summary = served.api("POST", "/record/stop")
    assert status == 200
    assert summary["output"] == path and summary["error"] is None
    assert summary["samples"][f"{ph.device}/imu"] == n and summary["samples"][f"{ph.device}/user_acc"] == n
    status, ans = served.api("POST", "/record/stop")
    assert (status, ans) == (409, {"error": "not recording"})
    assert served.api("GET", "/health")[1]["recording"] is None

    r = SessionReader(path)
    imu = r.samples(f"{ph.device}/imu")
    assert len(imu) == n
    np.testing.assert_array_equal(imu.values, np.column_stack([motion[:, 4:7], np.radians(motion[:, 7:10])]))
    rep = replay_session(path, speed=0)
    assert rep.verification is not None and rep.verification["equal"], rep.verification
    assert rep.verification["streams"][f"{ph.device}/imu"]["compared"] == n

    # an existing file is not replaced unless asked
    status, ans = served.api("POST", "/record/start", body={"path": path})
    assert status == 409 and path in ans["error"]
    status, ans = served.api("POST", "/record/start", body={"path": path, "overwrite": True})
    assert (status, ans) == (200, {"recording": path})
    assert served.api("POST", "/record/stop")[0] == 200
    # no path: a new session in the sessions directory
    status, ans = served.api("POST", "/record/start", data=b"")
    assert status == 200 and os.path.dirname(ans["recording"]) == str(tmp_path)
    assert os.path.basename(ans["recording"]).startswith("perfcap-") and os.path.exists(ans["recording"])
    assert served.api("POST", "/record/stop")[1]["output"] == ans["recording"]
    assert glob.glob(str(tmp_path / "perfcap-*.mcap")) == [ans["recording"]]


@pytest.mark.parametrize("data, what", [(b"{not json", "JSON"), (b"[1, 2]", "object"), (b'{"path": 5}', "string")])
def test_record_start_rejects_a_bad_body(served, data, what):
    status, ans = served.api("POST", "/record/start", data=data)
    assert status == 400 and what in ans["error"]
    assert served.service.capture.recorder is None


def test_control_api_checks_its_arguments(served, tmp_path):
    assert served.api("POST", "/record/start", body={"path": "a.mcap", "overwrite": "false"})[0] == 400
    assert served.api("POST", "/record/start", body={"path": "../../etc/x.mcap"})[0] == 400
    assert served.api("POST", "/record/start", body={"path": "/tmp/elsewhere.mcap"})[0] == 400
    assert served.api("POST", "/record/start", body={"path": "no/such/dir/a.mcap"})[0] in (400, 500)
    for bad in ({"host": "127.0.0.1", "port": 8080, "name": 5}, {"host": "127.0.0.1", "port": True},
                {"host": "127.0.0.1", "port": 8080, "types": "accelerometer&open_timeout=0.1"},
                {"host": "a b", "port": 8080}, {"host": "127.0.0.1", "port": 70000}):
        assert served.api("POST", "/sensorserver", body=bad)[0] == 400, bad
    assert served.service.capture.devices == []  # nothing was added behind a refusal
    code, ans = served.api("POST", "/record/start", body={"path": "inside.mcap"})
    assert code == 200 and ans["recording"] == os.path.realpath(tmp_path / "inside.mcap")
    assert served.api("POST", "/record/stop")[0] == 200


@pytest.mark.parametrize("path, says", [
    ("", "empty"), ("..", "'..'"), ("../x.mcap", "'..'"), ("/etc/x.mcap", "outside"), ("a\u0000b.mcap", "NUL"),
    (".x.mcap", "'.'"), ("x.txt", ".mcap"), ("sub/", "directory"), ("link/x.mcap", "symbolic link"),
    ("none/x.mcap", "no directory none"), (5, "string"), ([], "string"), ({"a": 1}, "string"), (True, "string"),
])
def test_record_start_refuses_a_bad_path_with_400_and_its_reason(served, tmp_path, path, says):
    (tmp_path / "link").symlink_to(tmp_path.parent)
    status, ans = served.api("POST", "/record/start", body={"path": path})
    assert status == 400 and says in ans["error"], (status, ans)
    assert served.service.capture.recorder is None
    assert not list(tmp_path.parent.glob("*.mcap")) and not list(tmp_path.glob("*.mcap"))


def test_record_start_overwrites_only_a_perfcap_session(served, tmp_path):
    notes = tmp_path / "notes.mcap"
    notes.write_bytes(b"my notes")
    for ow in (False, True):
        status, ans = served.api("POST", "/record/start", body={"path": "notes.mcap", "overwrite": ow})
        assert status == 409 and "not a perfcap session" in ans["error"], ans
    assert notes.read_bytes() == b"my notes"
    assert served.api("POST", "/record/start", body={"path": "take.mcap"})[0] == 200
    assert served.api("POST", "/record/stop")[0] == 200
    status, ans = served.api("POST", "/record/start", body={"path": "take.mcap", "overwrite": True})
    assert (status, ans) == (200, {"recording": str(tmp_path / "take.mcap")})
    assert served.api("POST", "/record/stop")[0] == 200


def test_the_default_sessions_directory_is_private_and_not_the_working_directory(tmp_path, monkeypatch):
    from capture.app.serve.config import ServeConfig
    from capture.app.serve.service import Service

    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    monkeypatch.chdir(tmp_path)
    svc = Service(ServeConfig(state_dir=str(tmp_path / "state"), token="t" * 32, mdns=False))
    try:
        out = svc.start_recording()
        assert os.path.dirname(out) == str(tmp_path / "data" / "perfcap" / "sessions")
        assert (os.stat(os.path.dirname(out)).st_mode & 0o777) == 0o700
        assert svc.stop_recording()["output"] == out
        assert not list(tmp_path.glob("*.mcap"))
    finally:
        svc.capture.stop()


def test_sensorserver_endpoint_connects_a_phone(served, fake_sensorserver, tmp_path):
    """Needs devices/phone_apps.py (kind ``sensorserver``)."""
    for bad in ({"host": "127.0.0.1"}, {"port": 8080}, {"host": 5, "port": 8080}, {"host": "127.0.0.1", "port": "80"}):
        status, ans = served.api("POST", "/sensorserver", body=bad)
        assert status == 400 and "host" in ans["error"], (bad, ans)
    path = str(tmp_path / "ss.mcap")
    served.service.start_recording(path)
    status, ans = served.api("POST", "/sensorserver", body={"host": "127.0.0.1", "port": fake_sensorserver.port,
                                                            "types": "accelerometer,gyroscope"})
    assert status == 200, ans
    name = ans["device"]
    n = fake_sensorserver.n_events
    served.wait(lambda: served.samples(f"{name}/acc") == n and served.samples(f"{name}/gyro") == n, DEADLINE_S,
                "every SensorServer event on the bus")
    assert fake_sensorserver.paths == [
        "/sensors/connect?types=%5B%22android.sensor.accelerometer%22%2C%22android.sensor.gyroscope%22%5D"]
    d = {x["name"]: x for x in served.api("GET", "/devices")[1]["devices"]}[name]
    assert d["kind"] == "sensorserver" and d["url"].startswith(f"sensorserver://127.0.0.1:{fake_sensorserver.port}")
    assert d["samples"] == 2 * n and d["drops"]["protocol_errors"] == 0
    served.stop()
    r = SessionReader(path)
    for stream, typ in (("acc", "android.sensor.accelerometer"), ("gyro", "android.sensor.gyroscope")):
        b = r.samples(f"{name}/{stream}")
        sent = fake_sensorserver.sent[typ]
        assert b.t_device_ns.tolist() == [t for t, _ in sent]
        np.testing.assert_array_equal(b.values, np.array([v for _, v in sent]))
