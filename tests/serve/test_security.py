"""What keeps strangers out of ``perfcap serve``, tested through its real endpoints on loopback.

The page WebSocket (TLS, verified against the service's own certificate or pinned by fingerprint):
refused hellos and their close codes (4401 token, 4400 malformed), replayed tokens after rotation,
oversized messages, message floods (4429), malformed messages after the hello, too many
connections per host (503) and too many phones (4409); Sensor Logger's HTTP push (401, 413, 400);
the token-less UDP/TCP protocols (allow-lists, refused without one); the pairing token file and the
TLS certificate in the state directory. Every refusal must be counted by reason and must not
disturb an authenticated phone streaming at the same time.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import hashlib
import json
import os
import socket
import ssl
import stat
import time
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from serve_helpers import DEADLINE_S

from capture.app.serve.config import Limits, ServeConfig
from capture.app.serve.gateway import (
    CLOSE_MALFORMED,
    CLOSE_RATE,
    CLOSE_TOKEN,
    CLOSE_TOO_LARGE,
    CLOSE_TOO_MANY,
)
from capture.app.serve.security import TOKEN_FILE, AllowList, TokenStore
from capture.app.serve.service import Service
from capture.app.serve.tls import CERT_FILE, KEY_FILE, ensure_certificate
from capture.errors import ConfigError
from capture.session import SessionReader
from sim_devices.phone_client import send_udp
from sim_devices.phone_sim import page_hello, page_messages


def _tls_context(served: Any) -> ssl.SSLContext:
    """A client context that trusts only this service's self-signed certificate (hostname checked)."""
    return ssl.create_default_context(cafile=str(served.service.certificate.cert_path))


async def _close_code(ws: Any) -> int | None:
    """Read until the service closes ``ws`` (pings may come first); the code in its close frame."""
    while True:
        m = await ws.receive(timeout=DEADLINE_S)
        if m.type is aiohttp.WSMsgType.CLOSE:
            return int(m.data)
        if m.type is not aiohttp.WSMsgType.TEXT:
            return ws.close_code


def _motion_events(phone: Any) -> int:
    return sum(len(m.frame.motion) for m in phone.messages)


async def _streaming(served: Any, th: Any) -> None:
    """Until the simulated phone of ``th`` has samples on the bus (it streams while the test misbehaves)."""
    deadline = time.monotonic() + DEADLINE_S
    while not (th.phone.device and served.samples(f"{th.phone.device}/imu")):
        assert time.monotonic() < deadline, "the other phone never streamed"
        await asyncio.sleep(0.02)


def _assert_lost_nothing(served: Any, th: Any) -> None:
    """The simulated phone of ``th`` finished and every motion event it sent is on the bus."""
    assert th.join(DEADLINE_S), "the simulated phone did not finish"
    ph = th.phone
    assert ph.error is None, ph.error
    assert ph.sent == len(ph.messages) and ph.connects == 1
    n = _motion_events(ph)
    served.wait(lambda: served.samples(f"{ph.device}/imu") >= n, DEADLINE_S, f"{n} imu samples of {ph.device}")
    assert served.samples(f"{ph.device}/imu") == n
    assert served.samples(f"{ph.device}/user_acc") == n
    assert served.device(ph.device).health()["lost_messages"] == 0


# -- refused hellos -----------------------------------------------------------------------------------
HELLO_CASES = {
    # name: (first message or None for none at all, close code, counted reason)
    "no token": (page_hello("p1").decode(), CLOSE_TOKEN, "missing or wrong token"),
    "wrong token": (page_hello("p1", token="not-the-token-0123456789").decode(), CLOSE_TOKEN,
                    "missing or wrong token"),
    "empty token": (json.dumps({"type": "hello", "v": 1, "id": "p1", "token": ""}), CLOSE_TOKEN,
                    "missing or wrong token"),
    "not JSON": ("{type: hello", CLOSE_MALFORMED, "malformed hello"),
    "not a hello": (json.dumps({"type": "data", "seq": 0, "m": []}), CLOSE_MALFORMED, "malformed hello"),
    "JSON list": ("[1, 2, 3]", CLOSE_MALFORMED, "malformed hello"),
    "binary first message": (b'{"type":"hello"}', CLOSE_MALFORMED, "malformed hello"),
    "no hello in time": (None, CLOSE_TOKEN, "no hello"),
}


@pytest.mark.parametrize("case", list(HELLO_CASES))
def test_refused_hello_closes_with_its_code_and_is_counted(serve, case):
    first, code, reason = HELLO_CASES[case]
    # silence is closed after Limits.hello_timeout_s: here longer than the default, so a service that
    # ignored the setting would close sooner (a lower bound holds however busy the machine is)
    hello_timeout_s = Limits().hello_timeout_s + 1.0 if first is None else 0.3
    served = serve(limits=Limits(hello_timeout_s=hello_timeout_s))
    t0 = time.monotonic()

    async def go() -> tuple[aiohttp.WSMessage, aiohttp.WSMessage | None]:
        # every step is bounded: a refusal that never comes fails the test instead of hanging it
        async with served.client() as s:
            ws = await s.ws_connect(served.ws_url, ssl=_tls_context(served), heartbeat=None,
                                    timeout=aiohttp.ClientWSTimeout(ws_close=DEADLINE_S))
            if isinstance(first, bytes):
                await ws.send_bytes(first)
            elif first is not None:
                await ws.send_str(first)
            msg = await ws.receive(timeout=DEADLINE_S)
            after = None if ws.closed else await ws.receive(timeout=DEADLINE_S)
            await ws.close()
            return msg, after

    msg, after = asyncio.run(asyncio.wait_for(go(), 3 * DEADLINE_S))
    assert msg.type is aiohttp.WSMsgType.CLOSE, f"the service dropped the connection without a close frame: {msg}"
    assert msg.data == code, msg
    assert msg.extra  # the reason: the page shows it to the user
    assert after is None or after.type is aiohttp.WSMsgType.CLOSED, after
    if first is None:
        assert time.monotonic() - t0 >= hello_timeout_s  # Limits.hello_timeout_s, not the default
    assert served.rejected() == {reason: 1}
    status, health = served.api("GET", "/health")
    assert status == 200 and health["rejected"] == {reason: 1}
    assert served.service.capture.devices == [] and served.service.gateway.stats.accepted == 0


def test_hello_with_token_but_bad_id_is_malformed(served):
    tok = served.token

    async def go() -> aiohttp.WSMessage:
        async with served.client() as s:
            ws = await s.ws_connect(served.ws_url, ssl=_tls_context(served), heartbeat=None,
                                    timeout=aiohttp.ClientWSTimeout(ws_close=DEADLINE_S))
            await ws.send_str(json.dumps({"type": "hello", "v": 1, "id": "has spaces/and slashes", "token": tok}))
            msg = await ws.receive(timeout=DEADLINE_S)
            await ws.close()
            return msg

    msg = asyncio.run(asyncio.wait_for(go(), 3 * DEADLINE_S))
    assert msg.type is aiohttp.WSMsgType.CLOSE and msg.data == CLOSE_MALFORMED, msg
    assert served.rejected() == {"malformed hello": 1}
    assert served.service.capture.devices == []


def test_a_hello_nested_beyond_the_json_parser_is_counted_as_malformed(served):
    async def go() -> tuple[object, object]:
        async with served.client() as s:
            ws = await s.ws_connect(served.ws_url, ssl=served.ssl(), heartbeat=None)
            await ws.send_str("[" * 60000)
            msg = await ws.receive(timeout=DEADLINE_S)
            await ws.close()
            return msg.type.name, msg.data

    assert asyncio.run(go()) == ("CLOSE", CLOSE_MALFORMED)
    assert served.rejected() == {"malformed hello": 1}


def test_accepted_hello_is_recorded_without_the_token(served, tmp_path):
    path = str(tmp_path / "hello.mcap")
    served.service.start_recording(path)

    async def go() -> Any:
        async with served.client() as s:
            ws, msg = await served.page(s, "hello-check")
            await ws.close()
            return msg

    msg = asyncio.run(go())
    assert msg.type is aiohttp.WSMsgType.TEXT
    assert json.loads(msg.data) == {"type": "welcome", "device": "phone-helloche", "ping_s": 1.0}
    served.stop()
    chunks = list(SessionReader(path).raw_chunks("phone-helloche"))
    assert len(chunks) == 1
    hello = json.loads(chunks[0].data)
    assert hello["type"] == "hello" and hello["id"] == "hello-check" and hello["peer"] == "127.0.0.1"
    assert "token" not in hello
    assert served.token.encode() not in chunks[0].data


# -- token rotation -------------------------------------------------------------------------------------
def test_rotated_token_is_refused_and_open_phones_are_closed(served):
    old = served.token
    sl_url = f"{served.base_url}/ingest/sensorlogger?token="
    body = json.dumps({"messageId": 0, "sessionId": "s", "deviceId": "rot-phone", "payload": []}).encode()

    async def go() -> dict[str, Any]:
        out: dict[str, Any] = {}
        async with served.client() as s:
            ws, welcome = await served.page(s, "rot-page", token=old)
            out["welcome"] = json.loads(welcome.data)["type"]
            async with s.post(sl_url + old, data=body, ssl=served.ssl()) as r:
                out["sl_before"] = r.status
            status, rot = await asyncio.to_thread(served.api, "POST", "/token/rotate", token=old)
            out["rotate"] = (status, rot)
            out["closed"] = await _close_code(ws)  # the page socket paired with the old token
            await ws.close()
            ws2, m2 = await served.page(s, "rot-page", token=old)  # the replayed token
            out["replayed"] = (m2.type, m2.data)
            await ws2.close()
            async with s.post(sl_url + old, data=body, ssl=served.ssl()) as r:
                out["sl_after"] = r.status
            new = rot["token"]
            ws3, m3 = await served.page(s, "rot-page", token=new)
            out["new"] = json.loads(m3.data)
            await ws3.close()
            async with s.post(sl_url + new, data=body, ssl=served.ssl()) as r:
                out["sl_new"] = r.status
        return out

    out = asyncio.run(go())
    status, rot = out["rotate"]
    assert status == 200
    new = rot["token"]
    assert new != old and len(new) >= 16 and served.token == new
    assert rot["pair_url"].endswith("#t=" + new)
    assert served.service.endpoints.sensorlogger_url.endswith("?token=" + new)
    assert out["welcome"] == "welcome" and out["sl_before"] == 200
    assert out["closed"] == CLOSE_TOKEN
    assert out["replayed"] == (aiohttp.WSMsgType.CLOSE, CLOSE_TOKEN)
    assert out["sl_after"] == 401
    assert out["new"]["type"] == "welcome" and out["new"]["device"] == "phone-rotpage"  # same phone, same device
    assert out["sl_new"] == 200
    assert served.api("GET", "/health", token=old)[0] == 401
    assert served.api("GET", "/health", token=new)[0] == 200
    assert served.rejected() == {"missing or wrong token": 3}  # WS replay, Sensor Logger replay, control API
    # the rotated token is what the state directory keeps (a fixed test token is never written)
    assert (Path(served.service.state_dir) / TOKEN_FILE).read_text().strip() == new


# -- bounds on authenticated phones ------------------------------------------------------------------------
def test_oversized_message_closes_that_phone_only(serve):
    served = serve(limits=Limits(max_message_bytes=4096))
    good = served.phone("good-phone", duration_s=2.0)

    async def go() -> int | None:
        async with served.client() as s:
            ws, welcome = await served.page(s, "big-phone")
            assert json.loads(welcome.data)["type"] == "welcome"
            await _streaming(served, good)
            await ws.send_str(json.dumps({"type": "data", "seq": 0, "pad": "x" * 5000}))
            code = await _close_code(ws)
            await ws.close()
            return code

    code = asyncio.run(go())
    _assert_lost_nothing(served, good)
    box = served.service.phones.hub.get("page/big-phone")
    assert box is not None and box.received == 1  # only its hello reached its inbox
    # the page protocol: an oversized message closes with the standard 1009 (message too big), counted
    assert code == CLOSE_TOO_LARGE == 1009, f"closed with {code}, the page protocol says 1009"
    assert served.rejected() == {"message too large": 1}


def test_message_flood_closes_with_4429_and_other_phone_loses_nothing(serve):
    served = serve(limits=Limits(rate_hz=50.0, burst=20.0))
    good = served.phone("calm-phone", duration_s=2.0)  # 20 data messages/s + pongs: under the rate
    flood_msgs = page_messages(10.0, 60.0, seed=9)  # 200 valid data messages, sent as fast as possible

    async def go() -> tuple[int, Any, float]:
        async with served.client() as s:
            await _streaming(served, good)
            ws, welcome = await served.page(s, "flood-phone")
            assert json.loads(welcome.data)["type"] == "welcome"
            t0 = time.monotonic()
            n = 0
            try:
                for m in flood_msgs:
                    await ws.send_str(m.data.decode())
                    n += 1
            except ConnectionError:
                pass
            code = await _close_code(ws)
            await ws.close()
            return n, code, time.monotonic() - t0

    n, code, elapsed = asyncio.run(go())
    assert code == CLOSE_RATE
    assert served.rejected() == {"message rate exceeded": 1}
    box = served.service.phones.hub.get("page/flood-phone")
    accepted = box.received - 1  # minus its hello
    # the burst less the hello (reconnecting costs a message), plus what the rate refilled meanwhile
    assert 19 <= accepted <= 19 + 50.0 * elapsed + 1
    assert accepted < n  # the rest of the flood was refused
    _assert_lost_nothing(served, good)


def test_binary_messages_after_the_hello_are_counted_then_closed(serve):
    served = serve(limits=Limits(max_malformed=2))

    async def go() -> Any:
        async with served.client() as s:
            ws, _ = await served.page(s, "bin-phone")
            for _ in range(3):
                await ws.send_bytes(b"\x00\x01\x02")
            code = await _close_code(ws)
            await ws.close()
            return code

    assert asyncio.run(go()) == CLOSE_MALFORMED
    assert served.rejected() == {"binary message": 3}
    assert served.service.phones.hub.get("page/bin-phone").received == 1  # the hello only


def test_too_many_connections_per_host_get_503(serve):
    served = serve(limits=Limits(max_connections_per_host=2))

    async def go() -> dict[str, Any]:
        out: dict[str, Any] = {}
        async with served.client() as s:
            a, ma = await served.page(s, "conn-a")
            b, mb = await served.page(s, "conn-b")
            out["ok"] = [json.loads(ma.data)["type"], json.loads(mb.data)["type"]]
            # a third paired connection from the host: closed after its hello (4409); the pool of
            # connections still waiting for a hello is bounded separately (503 before the upgrade)
            c0, mc0 = await served.page(s, "conn-c")
            out["third"] = (mc0.type, mc0.data)
            await c0.close()
            await a.close()
            box = served.service.phones.hub.get("page/conn-a")
            deadline = time.monotonic() + DEADLINE_S
            while box.connected and time.monotonic() < deadline:  # the service noticed the close (counted
                await asyncio.sleep(0.02)                         # down before the disconnect)
            c, mc = await served.page(s, "conn-c")
            out["after"] = json.loads(mc.data)["type"]
            await b.close()
            await c.close()
        return out

    out = asyncio.run(go())
    assert out == {"ok": ["welcome", "welcome"], "third": (aiohttp.WSMsgType.CLOSE, CLOSE_TOO_MANY),
                   "after": "welcome"}
    assert served.rejected() == {"too many connections": 1}


def test_strangers_waiting_for_hello_cannot_use_up_the_phones_connections(serve):
    """Sockets that never say hello have their own bound: beyond it they get 503, and a paired phone
    still gets in."""
    served = serve(limits=Limits(max_pending_hello=3, max_connections_per_host=8, hello_timeout_s=2.0))

    async def go() -> dict[str, Any]:
        out: dict[str, Any] = {}
        async with served.client() as s:
            idle = [await s.ws_connect(served.ws_url, ssl=served.ssl()) for _ in range(3)]
            with pytest.raises(aiohttp.WSServerHandshakeError) as ei:
                await s.ws_connect(served.ws_url, ssl=served.ssl())
            out["fourth_stranger"] = ei.value.status
            for w in idle:
                await w.close()
            deadline = time.monotonic() + DEADLINE_S
            while served.service.gateway._pending and time.monotonic() < deadline:
                await asyncio.sleep(0.02)
            ws, m = await served.page(s, "paired-after-strangers")
            out["paired"] = json.loads(m.data)["type"]
            await ws.close()
        return out

    assert asyncio.run(go()) == {"fourth_stranger": 503, "paired": "welcome"}


def test_too_many_phones_closes_with_4409(serve):
    served = serve(max_phones=1)

    async def go() -> tuple[Any, Any]:
        async with served.client() as s:
            a, ma = await served.page(s, "only-phone")
            b, mb = await served.page(s, "second-phone")
            res = (json.loads(ma.data)["type"], (mb.type, mb.data))
            await a.close()
            await b.close()
            return res

    first, second = asyncio.run(go())
    assert first == "welcome"
    assert second == (aiohttp.WSMsgType.CLOSE, CLOSE_TOO_MANY)
    assert served.rejected() == {"phone not admitted": 1}
    assert [d.name for d in served.service.capture.devices] == ["phone-onlyphon"]


# -- Sensor Logger HTTP push ----------------------------------------------------------------------------
def test_sensorlogger_push_refusals(serve):
    served = serve(limits=Limits(max_push_bytes=4096))
    url = f"{served.base_url}/ingest/sensorlogger"

    def body(**kw: Any) -> bytes:
        d = {"messageId": 0, "sessionId": "s1", "deviceId": "sl-test-phone",
             "payload": [{"name": "accelerometer", "time": 1_700_000_000_000_000_000,
                          "values": {"x": 0.1, "y": 0.2, "z": 0.3}}]}
        d.update(kw)
        return json.dumps(d).encode()

    async def chunked(n: int):
        for _ in range(n):
            yield b" " * 1024

    async def go() -> dict[str, Any]:
        out: dict[str, Any] = {}
        async with served.client() as s:
            async def post(name: str, query: str, data: Any) -> None:
                async with s.post(url + query, data=data, ssl=served.ssl(),
                                  headers={"Content-Type": "application/json"}) as r:
                    out[name] = (r.status, await r.json(content_type=None))

            await post("no token", "", body())
            await post("wrong token", "?token=wrong-token-0123456789", body())
            await post("oversized", f"?token={served.token}", body(pad="x" * 8000))
            await post("oversized chunked", f"?token={served.token}", chunked(8))
            await post("no deviceId", f"?token={served.token}", json.dumps({"messageId": 0, "payload": []}))
            await post("not JSON", f"?token={served.token}", b"messageId=0&deviceId=x")
            await post("good", f"?token={served.token}", body())
        return out

    out = asyncio.run(go())
    assert {k: v[0] for k, v in out.items()} == {"no token": 401, "wrong token": 401, "oversized": 413,
                                                 "oversized chunked": 413, "no deviceId": 400, "not JSON": 400,
                                                 "good": 200}
    assert "token" in out["no token"][1]["error"]
    assert out["good"][1] == {"ok": True, "device": "sl-sltestph"}
    assert served.rejected() == {"missing or wrong token": 2, "message too large": 2, "malformed message": 2}
    assert [d.name for d in served.service.capture.devices] == ["sl-sltestph"]
    served.wait(lambda: served.samples("sl-sltestph/acc") == 1, DEADLINE_S, "the good push on the bus")
    assert served.service.gateway.stats.messages == 1


# -- token-less protocols: allow-lists -----------------------------------------------------------------------
def _zigsim_bundle(i: int) -> bytes:
    from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
    from pythonosc.osc_message_builder import OscMessageBuilder

    b = OscBundleBuilder(IMMEDIATELY)
    for addr, vals in (("accel", (0.01 * i, 0.02, -0.03)), ("gravity", (0.0, 0.0, -1.0)), ("gyro", (0.1, 0.2, 0.3))):
        m = OscMessageBuilder(address=f"/sim-uuid/{addr}")
        for v in vals:
            m.add_arg(float(v))
        b.add_content(m.build())
    return b.build().dgram


def test_osc_accepts_only_allow_listed_sources(serve, free_port, tmp_path):
    """Needs devices/phone_apps.py (kind ``osc``) for the allow-listed source's device."""
    served = serve(osc_port=free_port(), osc_allow="127.0.0.1")
    port = served.service.endpoints.osc_port
    assert port == served.service.config.osc_port
    path = str(tmp_path / "osc.mcap")
    served.service.start_recording(path)
    good = [_zigsim_bundle(i) for i in range(10)]
    bad = [_zigsim_bundle(100 + i) for i in range(7)]
    send_udp("127.0.0.1", port, bad[:3], source="127.0.0.2")  # loopback takes any 127.x source on Linux
    send_udp("127.0.0.1", port, good[:5], source="127.0.0.1")
    send_udp("127.0.0.1", port, bad[3:], source="127.0.0.2")
    send_udp("127.0.0.1", port, good[5:], source="127.0.0.1")
    served.wait(lambda: served.rejected().get("source not allow-listed", 0) + served.service.gateway.stats.messages
                >= len(good) + len(bad) or served.rejected().get("phone not admitted"), DEADLINE_S, "the datagrams")
    assert served.rejected() == {"source not allow-listed": len(bad)}
    assert served.service.gateway.stats.messages == len(good)
    assert [(d.name, d.kind) for d in served.service.capture.devices] == [("osc-127_0_0_1", "osc")]
    served.stop()
    assert [c.data for c in SessionReader(path).raw_chunks("osc-127_0_0_1")] == good


def test_hyperimu_udp_and_tcp_accept_only_allow_listed_sources(serve, free_port, tmp_path):
    """Needs devices/phone_apps.py (kind ``hyperimu``) for the allow-listed source's device."""
    served = serve(hyperimu_port=free_port(), hyperimu_tcp_port=free_port(socket.SOCK_STREAM),
                   hyperimu_allow="127.0.0.0/31")  # 127.0.0.0 and 127.0.0.1, not 127.0.0.2
    ep = served.service.endpoints
    path = str(tmp_path / "himu.mcap")
    served.service.start_recording(path)
    rows = [f"{0.1 * i:.3f},0.200,9.810,0.010,0.020,0.030,10.0,20.0,30.0\r\n".encode() for i in range(6)]
    send_udp("127.0.0.1", ep.hyperimu_port, rows[:2], source="127.0.0.2")
    # TCP from a stranger: the service hangs up without reading
    with socket.create_connection(("127.0.0.1", ep.hyperimu_tcp_port), timeout=DEADLINE_S,
                                  source_address=("127.0.0.2", 0)) as c:
        assert c.recv(100) == b""
    send_udp("127.0.0.1", ep.hyperimu_port, rows, source="127.0.0.1")
    served.wait(lambda: served.service.gateway.stats.messages >= len(rows)
                or served.rejected().get("phone not admitted"), DEADLINE_S, "the allowed datagrams")
    assert served.rejected() == {"source not allow-listed": 3}
    assert served.service.gateway.stats.messages == len(rows)
    assert [(d.name, d.kind) for d in served.service.capture.devices] == [("himu-127_0_0_1", "hyperimu")]
    served.stop()
    assert [c.data for c in SessionReader(path).raw_chunks("himu-127_0_0_1")] == rows


@pytest.mark.parametrize("fields, flag", [
    ({"osc_port": 9000}, "--osc-allow"),
    ({"osc_port": 9000, "osc_allow": " , "}, "--osc-allow"),
    ({"hyperimu_port": 9001}, "--hyperimu-allow"),
    ({"hyperimu_tcp_port": 9002}, "--hyperimu-allow"),
])
def test_token_less_protocols_refuse_to_start_without_allow_list(tmp_path, fields, flag):
    cfg = ServeConfig(host="127.0.0.1", port=0, control_port=0, mdns=False, state_dir=str(tmp_path / "st"),
                      token="x" * 20, **fields)
    with pytest.raises(ConfigError, match=flag):
        cfg.check()
    with pytest.raises(ConfigError, match=flag):
        Service(cfg)
    assert not (tmp_path / "st").exists()  # refused before anything was made


def test_allow_list_parsing():
    a = AllowList("192.168.1.0/24, 10.0.0.7,::1")
    assert a.allows("192.168.1.23") and a.allows("10.0.0.7") and a.allows("::1")
    assert a.allows("::ffff:192.168.1.5")  # an IPv4-mapped peer on a dual-stack socket
    assert not a.allows("192.168.2.1") and not a.allows("10.0.0.8") and not a.allows("not-an-ip")
    assert not AllowList("") and not AllowList(None) and not AllowList(" , ")
    assert str(AllowList("")) == "(nobody)"
    with pytest.raises(ConfigError, match=r"'phone\.local'"):
        AllowList("192.168.1.2,phone.local")


# -- the pairing token file --------------------------------------------------------------------------------
def test_token_file_is_private_and_kept_across_services(serve, tmp_path):
    state = tmp_path / "kept-state"
    a = serve(token=None, state_dir=str(state))
    tok = a.token
    f = state / TOKEN_FILE
    assert f.read_text(encoding="ascii") == tok + "\n"
    assert stat.S_IMODE(f.stat().st_mode) == 0o600
    assert stat.S_IMODE(state.stat().st_mode) & 0o077 == 0
    assert a.service.tokens.created
    assert a.api("GET", "/health", token=tok)[0] == 200
    a.stop()
    b = serve(token=None, state_dir=str(state))
    assert b.token == tok and not b.service.tokens.created
    assert a.service.endpoints.fingerprint == b.service.endpoints.fingerprint

    async def go() -> Any:
        async with b.client() as s:
            ws, m = await b.page(s, "kept-phone", token=tok)
            await ws.close()
            return json.loads(m.data)["type"]

    assert asyncio.run(go()) == "welcome"
    new = b.service.tokens.rotate()
    assert f.read_text(encoding="ascii") == new + "\n" and stat.S_IMODE(f.stat().st_mode) == 0o600
    assert TokenStore(state).token == new


def test_token_store_rules(tmp_path):
    with pytest.raises(ConfigError, match="16"):
        TokenStore(tmp_path / "a", token="short")
    s = TokenStore(tmp_path / "b", token="a-fixed-token-0123456789")
    assert s.check("a-fixed-token-0123456789") and not s.check("a-fixed-token-012345678") and not s.check(None)
    assert not (tmp_path / "b").exists()  # a fixed token is not stored
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / TOKEN_FILE).write_text("short\n")
    made = TokenStore(tmp_path / "c")
    assert made.created and len(made.token) >= 16  # a too-short stored token is replaced


def test_a_rotation_that_cannot_be_stored_keeps_the_old_token(tmp_path):
    state = tmp_path / "state"
    store = TokenStore(state)
    old = store.token
    (state / "pairing-token.tmp").mkdir()  # where the new token would be written: not writable, even as root
    with pytest.raises(ConfigError, match="cannot store the pairing token"):
        store.rotate()
    assert store.token == old and store.check(old) and store.generation == 0
    assert (state / "pairing-token").read_text().strip() == old


# -- the TLS certificate ----------------------------------------------------------------------------------
def _served_cert_fingerprint(port: int) -> str:
    ctx = ssl.create_default_context()
    ctx.check_hostname = False
    ctx.verify_mode = ssl.CERT_NONE
    with socket.create_connection(("127.0.0.1", port), timeout=DEADLINE_S) as raw, ctx.wrap_socket(raw) as tls:
        der = tls.getpeercert(binary_form=True)
    return hashlib.sha256(der).hexdigest().upper()


def _san(cert_path: Path) -> set[str]:
    from cryptography import x509

    cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    return {str(n) for n in san.get_values_for_type(x509.DNSName)} | {
        str(n) for n in san.get_values_for_type(x509.IPAddress)}


def test_certificate_names_the_public_host_and_is_kept(serve, tmp_path):
    state = tmp_path / "cert-state"
    a = serve(state_dir=str(state), public_host="10.11.12.13")
    cert = a.service.certificate
    assert a.service.endpoints.certificate_created and cert.created
    assert a.service.endpoints.page_url == f"https://10.11.12.13:{a.port}/"
    assert _san(state / CERT_FILE) == {"10.11.12.13", "127.0.0.1", "localhost"}
    assert stat.S_IMODE((state / KEY_FILE).stat().st_mode) == 0o600
    fp = a.fingerprint
    assert _served_cert_fingerprint(a.port) == fp.replace(":", "")
    # a client that trusts this certificate verifies the connection by IP (SAN 127.0.0.1)
    with socket.create_connection(("127.0.0.1", a.port), timeout=DEADLINE_S) as raw, \
            _tls_context(a).wrap_socket(raw, server_hostname="127.0.0.1") as tls:
        assert tls.version() in ("TLSv1.2", "TLSv1.3")
    a.stop()

    b = serve(state_dir=str(state), public_host="10.11.12.13")  # same host: the same certificate
    assert not b.service.endpoints.certificate_created and b.fingerprint == fp
    assert _served_cert_fingerprint(b.port) == fp.replace(":", "")
    b.stop()

    c = serve(state_dir=str(state), public_host="10.99.0.1")  # the LAN address changed: remade
    assert c.service.endpoints.certificate_created and c.fingerprint != fp
    assert _san(state / CERT_FILE) == {"10.11.12.13", "10.99.0.1", "127.0.0.1", "localhost"}
    assert _served_cert_fingerprint(c.port) == c.fingerprint.replace(":", "")


def test_certificate_is_renewed_before_it_expires(tmp_path):
    from cryptography import x509

    first = ensure_certificate(tmp_path, ["perfcap-host.local"])
    assert first.created and "perfcap-host.local" in first.names
    cert = x509.load_pem_x509_certificate(first.cert_path.read_bytes())
    assert (cert.not_valid_after_utc - cert.not_valid_before_utc).days <= 397
    soon = cert.not_valid_after_utc - dt.timedelta(days=40)
    kept = ensure_certificate(tmp_path, ["perfcap-host.local"], now=soon)
    assert not kept.created and kept.fingerprint == first.fingerprint
    late = cert.not_valid_after_utc - dt.timedelta(days=10)
    renewed = ensure_certificate(tmp_path, ["perfcap-host.local"], now=late)
    assert renewed.created and renewed.fingerprint != first.fingerprint
    (tmp_path / CERT_FILE).write_text("not a certificate")
    again = ensure_certificate(tmp_path, ["perfcap-host.local"])
    assert again.created and "perfcap-host.local" in again.names
    assert os.path.getsize(tmp_path / CERT_FILE) > 100
