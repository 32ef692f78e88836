"""Defects a review of the service found, each pinned by the behaviour it broke: nested JSON in a
hello, control API argument checks, the recording path kept in the sessions directory, a token
rotation that cannot be stored, bad phone options found at start, a host's older HyperIMU TCP
socket closing, and ``serve --record`` missing the first samples."""

from __future__ import annotations

import asyncio
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from serve_helpers import TOKEN, wait_until

from capture.errors import ConfigError
from capture.app.serve.gateway import CLOSE_MALFORMED
from capture.app.serve.security import AllowList, TokenStore
from capture.app.serve.config import ServeConfig
from capture.app.serve.service import Service
from capture.session import SessionReader
from sim_devices.phone_apps_sim import hyperimu_rows


def test_a_hello_nested_beyond_the_json_parser_is_counted_as_malformed(served):
    async def go() -> tuple[object, object]:
        async with served.client() as s:
            ws = await s.ws_connect(served.ws_url, ssl=served.ssl(), heartbeat=None)
            await ws.send_str("[" * 60000)
            msg = await ws.receive(timeout=10)
            await ws.close()
            return msg.type.name, msg.data

    assert asyncio.run(go()) == ("CLOSE", CLOSE_MALFORMED)
    assert served.rejected() == {"malformed hello": 1}


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


def test_a_rotation_that_cannot_be_stored_keeps_the_old_token(tmp_path):
    state = tmp_path / "state"
    store = TokenStore(state)
    old = store.token
    (state / "pairing-token.tmp").mkdir()  # where the new token would be written: not writable, even as root
    with pytest.raises(ConfigError, match="cannot store the pairing token"):
        store.rotate()
    assert store.token == old and store.check(old) and store.generation == 0
    assert (state / "pairing-token").read_text().strip() == old


def test_bad_phone_options_are_an_error_at_start(tmp_path):
    with pytest.raises(ConfigError, match="osc"):
        Service(ServeConfig(host="127.0.0.1", port=0, control_port=-1, mdns=False, state_dir=str(tmp_path),
                            token=TOKEN, osc_port=9, osc_allow="127.0.0.1", osc_map="zigsimm"))
    with pytest.raises(ConfigError, match="hyperimu"):
        Service(ServeConfig(host="127.0.0.1", port=0, control_port=-1, mdns=False, state_dir=str(tmp_path),
                            token=TOKEN, hyperimu_port=9, hyperimu_allow="127.0.0.1", hyperimu_sensors="accel"))
    with pytest.raises(ConfigError, match="already names"):
        Service(ServeConfig(host="127.0.0.1", port=0, control_port=-1, mdns=False, state_dir=str(tmp_path),
                            token=TOKEN, names={"page/x": "wrist"}), ["wrist=synth://imu?realtime=false"])


def test_an_older_hyperimu_tcp_socket_closing_does_not_disconnect_the_phone(serve):
    served = serve(hyperimu_allow="127.0.0.1")
    svc = served.service
    # a free port for HyperIMU TCP, opened through the gateway itself (in config 0 means off)
    fut = asyncio.run_coroutine_threadsafe(
        svc.gateway.start_tcp("hyperimu", "127.0.0.1", 0, AllowList("127.0.0.1")), svc._loop)
    port = fut.result(10)
    rows = hyperimu_rows([[0, 0, 9.8, 0.1, 0.2, 0.3, 10, 20, 30]] * 5)
    old = socket.create_connection(("127.0.0.1", port))
    old.sendall(rows)
    wait_until(lambda: svc.phones.hub.get("hyperimu/127.0.0.1") is not None, 5, "the phone")
    new = socket.create_connection(("127.0.0.1", port))
    time.sleep(0.2)
    old.close()  # the phone reconnected; its old socket goes away later
    time.sleep(0.3)
    box = svc.phones.hub.get("hyperimu/127.0.0.1")
    assert box is not None and box.connected
    new.sendall(rows)
    time.sleep(0.2)
    new.close()
    wait_until(lambda: not box.connected, 5, "the disconnect of the newest socket")


def test_serve_record_has_the_first_samples(tmp_path):
    out = tmp_path / "take.mcap"
    p = subprocess.run([sys.executable, "-m", "capture.app.cli", "serve", "--port", "0", "--control-port", "-1",
                        "--no-mdns", "--state-dir", str(tmp_path / "st"), "--duration", "1.5", "-q",
                        "--record", str(out), "-d", "imu=synth://imu?rate=100&seed=3"],
                       capture_output=True, text=True, timeout=60, cwd=Path(__file__).parent)
    assert p.returncode == 0, p.stderr
    b = SessionReader(str(out)).samples("imu/imu")
    assert len(b) > 50 and int(b.seq[0]) == 0
