"""Phones streaming into ``perfcap serve`` through its real network path, checked sample by sample.

* A simulated phone page (``SimPagePhone``: TLS WebSocket, hello, 50 ms batches of devicemotion and
  deviceorientation, pongs): every motion event becomes one ``imu`` and one ``user_acc`` sample with
  the values ``phone_sim`` generated, converted as ``devices/phone.py`` documents, and a bus time
  within a few ms of when the event really happened (``SimPagePhone.truth_ns``).
* A phone that drops off and reconnects keeps its device and loses nothing.
* The real iPhone recording in ``../shared/traces/e_smartphone/`` pushed as Sensor Logger HTTP POSTs
  arrives complete, raw and decoded.
* Stopping the service records everything that was received, up to the moment of the stop.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import ssl
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from serve_helpers import DEADLINE_S, wait_until

from capture.app.serve.security import AllowList
from capture.session import SessionReader
from sim_devices.motion import G
from sim_devices.phone_apps_sim import hyperimu_rows
from sim_devices.phone_sim import dispel_samples, dispel_to_sensorlogger, page_messages

TRACE = (Path(__file__).resolve().parents[2] / ".." / "shared" / "traces" / "e_smartphone"
         / "dispel_ads_iphonex_sbt_utt_example.json")


@pytest.fixture
def trace() -> Path:
    if not TRACE.is_file():
        pytest.skip(f"iPhone trace not found at {TRACE} (../shared/traces must sit beside the project)")
    return TRACE


def _rows(phone, key: str = "motion") -> np.ndarray:
    return np.array([r for m in phone.messages for r in getattr(m.frame, key)], dtype=float)


def _data_seqs(chunks) -> list[int]:
    out = []
    for c in chunks:
        m = json.loads(c.data)
        if m.get("type") == "data":
            out.append(m["seq"])
    return out


def _bus_error_ms(phone, batch, t_ms: np.ndarray) -> np.ndarray:
    return (batch.t_bus_ns - phone.truth_ns(t_ms)) / 1e6


def test_page_phone_motion_arrives_complete_exact_and_on_time(served, tmp_path):
    path = str(tmp_path / "page.mcap")
    served.service.start_recording(path)
    th = served.phone("ingest-phone", duration_s=3.0)
    assert th.join(DEADLINE_S)
    ph = th.phone
    assert ph.error is None and ph.sent == len(ph.messages) and ph.connects == 1
    motion = _rows(ph)
    n = len(motion)
    assert n == 180  # 3 s of 60 Hz
    served.wait(lambda: served.samples(f"{ph.device}/imu") == n, DEADLINE_S, "every motion event on the bus")
    dev = served.device(ph.device)
    h = dev.health()
    assert (h["lost_messages"], h["seq_restarts"], h["hellos"], h["framing_errors"]) == (0, 0, 1, 0)
    assert h["pongs"] == ph.pongs >= 2  # one ping per second
    assert dev.info["id"] == "ingest-phone" and dev.info["platform"] == "android"
    served.stop()

    r = SessionReader(path)
    imu, user = r.samples(f"{ph.device}/imu"), r.samples(f"{ph.device}/user_acc")
    assert len(imu) == len(user) == n
    # devices/phone.py: imu = accelerationIncludingGravity (m/s^2) + rotationRate deg/s -> rad/s
    # (alpha -> gx, beta -> gy, gamma -> gz); user_acc = acceleration; device ticks = round(t_ms * 1000) us
    np.testing.assert_array_equal(imu.values, np.column_stack([motion[:, 4:7], np.radians(motion[:, 7:10])]))
    np.testing.assert_array_equal(user.values, motion[:, 1:4])
    ticks_ns = np.round(motion[:, 0] * 1000.0).astype(np.int64) * 1000
    np.testing.assert_array_equal(imu.t_device_ns, ticks_ns)
    np.testing.assert_array_equal(user.t_bus_ns, imu.t_bus_ns)
    # capture/clocksync.py: bus times never pass their arrival and never go back; on a busy machine several
    # events can arrive at once before the fit settles, and then share the arrival time
    assert np.all(np.diff(imu.seq) == 1) and np.all(np.diff(imu.t_bus_ns) >= 0)
    # bus time vs the moment the event happened on the phone, once the clock fit has a second of data
    err = _bus_error_ms(ph, imu, motion[:, 0])
    settled = motion[:, 0] >= motion[0, 0] + 1000.0
    assert np.percentile(np.abs(err[settled]), 99) < 5.0, np.abs(err[settled]).max()
    assert abs(np.median(err[settled])) < 3.0
    # raw: the hello (token removed), then every data message in order, pongs in between
    chunks = list(r.raw_chunks(ph.device))
    assert json.loads(chunks[0].data)["type"] == "hello" and served.token.encode() not in chunks[0].data
    assert _data_seqs(chunks) == list(range(len(ph.messages)))


def test_page_orientation_shares_the_motion_clock(served, tmp_path):
    """``devices/phone.py``: all four page streams share one device clock (``event.timeStamp``), so a
    deviceorientation event must get the same bus time as a devicemotion event of the same page time."""
    path = str(tmp_path / "orient.mcap")
    served.service.start_recording(path)
    th = served.phone("orient-phone", duration_s=2.0)
    assert th.join(DEADLINE_S) and th.phone.error is None
    ph = th.phone
    orient = _rows(ph, "orientation")
    served.wait(lambda: served.samples(f"{ph.device}/attitude") == len(orient), DEADLINE_S, "every orientation event")
    served.stop()
    att = SessionReader(path).samples(f"{ph.device}/attitude")
    assert len(att) == len(orient) == 40
    np.testing.assert_array_equal(att.values, orient[:, 1:4])
    err = _bus_error_ms(ph, att, orient[:, 0])
    settled = orient[:, 0] >= orient[0, 0] + 1000.0
    assert np.percentile(np.abs(err[settled]), 99) < 5.0, (
        f"attitude bus times are {np.median(err[settled]):.1f} ms (median) after the events")


def test_reconnecting_phone_keeps_its_device_and_loses_nothing(served, tmp_path):
    path = str(tmp_path / "drop.mcap")
    served.service.start_recording(path)
    th = served.phone("wobbly-phone", duration_s=2.5, drop_at_s=1.0, drop_for_s=0.4)
    assert th.join(DEADLINE_S)
    ph = th.phone
    assert ph.error is None and ph.connects == 2 and ph.sent == len(ph.messages)
    motion = _rows(ph)
    n = len(motion)
    served.wait(lambda: served.samples(f"{ph.device}/imu") == n, DEADLINE_S, "every motion event on the bus")
    assert [d.name for d in served.service.capture.devices] == [ph.device] == ["phone-wobblyph"]
    box = served.service.phones.hub.get("page/wobbly-phone")
    assert box.connects == 2 and box.dropped == 0
    h = served.device(ph.device).health()
    assert (h["lost_messages"], h["seq_restarts"], h["hellos"], h["lost_readings"]) == (0, 0, 2, 0)
    served.stop()
    r = SessionReader(path)
    imu = r.samples(f"{ph.device}/imu")
    np.testing.assert_array_equal(imu.values, np.column_stack([motion[:, 4:7], np.radians(motion[:, 7:10])]))
    assert np.all(np.diff(imu.seq) == 1)
    chunks = list(r.raw_chunks(ph.device))
    assert _data_seqs(chunks) == list(range(len(ph.messages)))
    assert [json.loads(c.data)["type"] for c in chunks].count("hello") == 2
    # the simulator's own count of motion events sent (printed by `perfcap demo`)
    assert ph.events == n, f"SimPagePhone.events says {ph.events}, but it sent {n} motion events"


def test_an_older_hyperimu_tcp_socket_closing_does_not_disconnect_the_phone(serve):
    served = serve(hyperimu_allow="127.0.0.1")
    svc = served.service
    # a free port for HyperIMU TCP, opened through the gateway itself (in config 0 means off)
    fut = asyncio.run_coroutine_threadsafe(
        svc.gateway.start_tcp("hyperimu", "127.0.0.1", 0, AllowList("127.0.0.1")), svc._loop)
    port = fut.result(DEADLINE_S)
    rows = hyperimu_rows([[0, 0, 9.8, 0.1, 0.2, 0.3, 10, 20, 30]] * 5)
    with socket.create_connection(("127.0.0.1", port)) as old, contextlib.ExitStack() as later:
        old.sendall(rows)
        wait_until(lambda: svc.phones.hub.get("hyperimu/127.0.0.1") is not None, DEADLINE_S, "the phone")
        box = svc.phones.hub.get("hyperimu/127.0.0.1")
        new = later.enter_context(socket.create_connection(("127.0.0.1", port)))
        wait_until(lambda: box.connects == 2, DEADLINE_S, "the phone's new socket")
        # the phone reconnected; its old socket goes away later: once the service has closed its end
        # too, it has seen the old one leave
        old.shutdown(socket.SHUT_WR)
        old.settimeout(DEADLINE_S)
        try:
            assert old.recv(1) == b""
        except ConnectionResetError:
            pass
        assert box.connected
        n = box.received
        new.sendall(rows)
        wait_until(lambda: box.received > n, DEADLINE_S, "the rows on the new socket")
        assert box.connected
    wait_until(lambda: not box.connected, DEADLINE_S, "the disconnect of the newest socket")


def test_sensorlogger_push_of_the_real_iphone_trace_arrives_complete(served, trace, tmp_path):
    pushes = dispel_to_sensorlogger(trace, batch_s=0.5)
    rec = dispel_samples(trace)
    path = str(tmp_path / "sl.mcap")
    served.service.start_recording(path)
    url = f"{served.base_url}/ingest/sensorlogger?token={served.token}"
    ctx = ssl.create_default_context(cafile=str(served.service.certificate.cert_path))  # the app checks TLS

    async def go() -> list[tuple[int, dict]]:
        out = []
        async with served.client() as s:
            for p in pushes:
                async with s.post(url, data=p.body, ssl=ctx, headers={"Content-Type": "application/json"}) as r:
                    out.append((r.status, await r.json()))
        return out

    answers = asyncio.run(go())
    assert answers == [(200, {"ok": True, "device": "sl-dispelip"})] * len(pushes)
    name = "sl-dispelip"
    served.wait(lambda: served.samples(f"{name}/gyro") == rec.n_gyro and served.samples(f"{name}/acc") == rec.n_acc,
                10, "every trace sample on the bus")
    h = served.device(name).health()
    assert (h["lost_messages"], h["duplicate_messages"], h["late_messages"], h["framing_errors"]) == (0, 0, 0, 0)
    served.stop()

    r = SessionReader(path)
    assert [c.data for c in r.raw_chunks(name)] == [p.body for p in pushes]  # every POST body, raw, in order
    acc_t = np.concatenate([lv.acc_ts_ms for lv in rec.levels]) * 1_000_000
    gyro_t = np.concatenate([lv.gyro_ts_ms for lv in rec.levels]) * 1_000_000
    ua = np.concatenate([lv.user_acc_g for lv in rec.levels]) * G
    grav = np.concatenate([lv.gravity_g for lv in rec.levels]) * G
    rot = np.concatenate([lv.rotation_rad_s for lv in rec.levels])
    ia, ig = np.argsort(acc_t, kind="stable"), np.argsort(gyro_t, kind="stable")
    for stream, t, v in (("acc", acc_t[ia], ua[ia]), ("phone_gravity", acc_t[ia], grav[ia]),
                         ("gyro", gyro_t[ig], rot[ig])):
        b = r.samples(f"{name}/{stream}")
        assert len(b) == len(t), stream
        np.testing.assert_array_equal(b.t_device_ns, t)
        # sent with CoreMotion's signs and the device's default platform "standardised": taken as sent
        np.testing.assert_allclose(b.values, v, rtol=1e-12, atol=0, err_msg=stream)


def test_stop_records_everything_received_up_to_the_stop(served, tmp_path):
    path = str(tmp_path / "stop.mcap")
    served.service.start_recording(path)
    streaming = served.phone("steady-phone", duration_s=30.0)  # still streaming when the service stops
    burst = page_messages(6.0, 60.0, seed=4)  # 120 data messages, sent back to back just before the stop
    backlog: list[int] = []

    async def go() -> None:
        async with served.client() as s:
            ws, welcome = await served.page(s, "burst-phone")
            assert json.loads(welcome.data)["type"] == "welcome"
            for m in burst:
                await ws.send_str(m.data.decode())
            box = served.service.phones.hub.get("page/burst-phone")
            deadline = time.monotonic() + DEADLINE_S
            while box.received < 1 + len(burst) and time.monotonic() < deadline:
                await asyncio.sleep(0.002)
            assert box.received == 1 + len(burst)
            backlog.append(len(box))  # received but not yet decoded when the stop comes
            stopper = threading.Thread(target=served.stop, kwargs={"phones_first": False})
            stopper.start()
            while True:  # the service says it is shutting down
                m = await ws.receive(timeout=DEADLINE_S)
                if m.type.name != "TEXT":
                    break
            await ws.close()
            await asyncio.to_thread(stopper.join, DEADLINE_S)

    served.wait(lambda: served.samples("phone-steadyph/imu") >= 60, DEADLINE_S, "the steady phone streaming")
    asyncio.run(go())
    assert served.report is not None  # stopped, with its capture report
    steady_box = served.service.phones.hub.get("page/steady-phone")
    r = SessionReader(path)
    # the burst: every message it sent, and every motion event in them
    chunks = list(r.raw_chunks("phone-burstpho"))
    assert _data_seqs(chunks) == list(range(len(burst)))
    assert len(r.samples("phone-burstpho/imu")) == sum(len(m.frame.motion) for m in burst)
    # the phone streaming across the stop: every message the gateway took is in the session, decoded
    steady = list(r.raw_chunks("phone-steadyph"))
    assert len(steady) == steady_box.received
    seqs = _data_seqs(steady)
    assert seqs == list(range(len(seqs))) and len(seqs) >= 3
    sent = streaming.phone.messages[:len(seqs)]
    assert len(r.samples("phone-steadyph/imu")) == sum(len(m.frame.motion) for m in sent)
    assert r.summary is not None and r.truncated is None  # closed cleanly
    assert len(backlog) == 1
