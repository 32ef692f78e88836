"""What one client may cost ``perfcap serve``: bytes waiting in its inbox, messages per second across
reconnects (per phone id and per address), phone slots, and TCP connections and handshakes.

Rates and slot timeouts run on a ``ManualClock`` where a test needs exact counts: nothing refills
unless the test advances it, so what a client gets is a count, not a race with the wall clock.
The last tests are seeded property loops over the accounting itself (``Inbox``, ``RateBook``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import random
import socket
import ssl
import time
from typing import Any

import aiohttp
import pytest
from serve_helpers import DEADLINE_S

from capture.app.serve.config import Limits, ServeConfig
from capture.app.serve.gateway import CLOSE_RATE, CLOSE_SHUTDOWN, CLOSE_TOO_MANY
from capture.app.serve.security import RateBook
from capture.clock import ManualClock
from capture.errors import ConfigError
from capture.sample import Chunk, Direction
from devices.transports.network import CHUNK_OVERHEAD, Inbox
from sim_devices.phone_sim import page_hello


async def _close_code(ws: Any) -> int | None:
    """Read until the service closes ``ws`` (pings may come first); the code in its close frame."""
    while True:
        m = await ws.receive(timeout=DEADLINE_S)
        if m.type is aiohttp.WSMsgType.CLOSE:
            return int(m.data)
        if m.type is not aiohttp.WSMsgType.TEXT:
            return ws.close_code


async def _streaming(served: Any, th: Any) -> None:
    """Until the simulated phone of ``th`` has samples on the bus."""
    deadline = time.monotonic() + DEADLINE_S
    while not (th.phone.device and served.samples(f"{th.phone.device}/imu")):
        assert time.monotonic() < deadline, "the other phone never streamed"
        await asyncio.sleep(0.02)


def _assert_lost_nothing(served: Any, th: Any) -> None:
    """The simulated phone of ``th`` finished, never reconnected, and every motion event it sent is on the bus."""
    assert th.join(DEADLINE_S), "the simulated phone did not finish"
    ph = th.phone
    assert ph.error is None, ph.error
    assert ph.sent == len(ph.messages) and ph.connects == 1
    n = sum(len(m.frame.motion) for m in ph.messages)
    served.wait(lambda: served.samples(f"{ph.device}/imu") >= n, DEADLINE_S, f"{n} imu samples of {ph.device}")
    assert served.samples(f"{ph.device}/imu") == n
    assert served.device(ph.device).health()["lost_messages"] == 0


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


@contextlib.asynccontextmanager
async def _client(src: str = "127.0.0.1") -> Any:
    """An aiohttp session whose connections come from ``src`` (loopback has 127.0.0.0/8)."""
    conn = aiohttp.TCPConnector(local_addr=(src, 0))
    async with aiohttp.ClientSession(connector=conn) as s:
        yield s
    await asyncio.sleep(0.1)


async def _page(served: Any, s: Any, phone_id: str) -> tuple[Any, Any]:
    ws = await s.ws_connect(served.ws_url, ssl=served.ssl(), autoping=True, heartbeat=None)
    await ws.send_str(page_hello(phone_id, token=served.token).decode())
    return ws, await ws.receive(timeout=DEADLINE_S)


async def _send_until_closed(ws: Any, n: int, text: str) -> int | None:
    with contextlib.suppress(ConnectionError):
        for _ in range(n):
            await ws.send_str(text)
    code = await _close_code(ws)
    await ws.close()
    return code


def _data(pad: int = 0) -> str:
    return json.dumps({"type": "data", "seq": 0, "m": [], "pad": "x" * pad})


# -- the byte budget ------------------------------------------------------------------------------------
def test_a_phone_beyond_its_byte_budget_is_refused_counted_and_closed_with_4429(serve):
    budget = 256 * 1024
    served = serve(limits=Limits(inbox_bytes=budget))
    good = served.phone("good-phone", duration_s=2.0, local_addr="127.0.0.2")
    msg = _data(16 * 1024)

    async def go() -> int | None:
        async with _client() as s:
            await _streaming(served, good)
            ws, welcome = await _page(served, s, "big-phone")
            # its reader stops decoding (taken out of the capture): what it sends now waits in its inbox
            served.service.capture.remove_device(json.loads(welcome.data)["device"], timeout=DEADLINE_S)
            return await _send_until_closed(ws, 64, msg)  # 1 MiB: four times the budget

    assert asyncio.run(go()) == CLOSE_RATE
    box = served.service.phones.hub.get("page/big-phone")
    assert served.rejected() == {"inbox byte budget exceeded": 1}
    assert box.dropped == 1 and box.dropped_bytes == len(msg)
    assert box.queued_bytes <= budget < box.queued_bytes + len(msg) + CHUNK_OVERHEAD  # full: the next did not fit
    _assert_lost_nothing(served, good)


# -- rates across reconnects ------------------------------------------------------------------------------
def test_the_rate_survives_reconnects_per_phone_and_per_address(serve):
    clock = ManualClock()  # frozen: no bucket refills unless advanced
    served = serve(limits=Limits(rate_hz=5.0, burst=10.0, max_connections_per_host=4), clock=clock)
    rejected: list[int | None] = []

    async def session(src: str, phone_id: str) -> int:
        """Connect, hello, 30 messages; how many of them (hello included) the service took."""
        box = served.service.phones.hub.get(f"page/{phone_id}")
        before = box.received if box is not None else 0
        async with _client(src) as s:
            ws, first = await _page(served, s, phone_id)
            if first.type is aiohttp.WSMsgType.CLOSE:
                rejected.append(int(first.data))
                await ws.close()
            else:
                rejected.append(await _send_until_closed(ws, 30, _data()))
        box = served.service.phones.hub.get(f"page/{phone_id}")
        return (box.received if box is not None else 0) - before

    async def go() -> dict[str, Any]:
        out: dict[str, Any] = {}
        out["first"] = await session("127.0.0.1", "rc-phone")
        out["again"] = [await session("127.0.0.1", "rc-phone") for _ in range(3)]
        out["new ids"] = [await session("127.0.0.1", f"rc-new-{i}") for i in range(6)]
        out["other address"] = await session("127.0.0.3", "rc-far")
        clock.advance(1_000_000_000)  # one second: 5 messages for the phone, 20 for its address
        out["a second later"] = await session("127.0.0.1", "rc-phone")
        return out

    out = asyncio.run(go())
    assert out["first"] == 10                       # its burst, the hello included
    assert out["again"] == [0, 0, 0]                # reconnecting buys nothing: the hello itself is refused
    assert sum(out["new ids"]) == 4 * 10 - 10       # new ids share the address's bucket (4 phones' worth)
    assert out["new ids"][:3] == [10, 10, 10] and out["new ids"][3:] == [0, 0, 0]
    assert out["other address"] == 10               # another address is not held back by the flood
    assert out["a second later"] == 5
    assert set(rejected) == {CLOSE_RATE}


def test_the_byte_rate_bounds_what_a_phone_sends_in_bytes(serve):
    clock = ManualClock()
    served = serve(limits=Limits(byte_rate=10_000.0, byte_burst=100_000.0, max_push_bytes=65536), clock=clock)
    msg = _data(20_000)

    async def go() -> int | None:
        async with _client() as s:
            ws, _ = await _page(served, s, "bytes-phone")
            return await _send_until_closed(ws, 10, msg)

    assert asyncio.run(go()) == CLOSE_RATE
    box = served.service.phones.hub.get("page/bytes-phone")
    assert box.received - 1 == 100_000 // len(msg) == 4  # the byte burst, in messages of this size
    assert served.rejected() == {"message rate exceeded": 1}


def test_sockets_per_address_must_leave_room_for_the_page():
    with pytest.raises(ConfigError, match="max-sockets-per-host"):
        ServeConfig(max_sockets_per_host=4, max_connections_per_host=4).check()


# -- phone slots -----------------------------------------------------------------------------------------------
def test_slots_of_phones_that_left_go_to_new_phones_and_come_back(serve):
    clock = ManualClock()
    served = serve(max_phones=2, limits=Limits(phone_timeout_s=60.0), clock=clock)
    phones = served.service.phones

    def closed(phone_id: str) -> None:
        served.wait(lambda: not phones.hub.get(f"page/{phone_id}").connected, DEADLINE_S, f"{phone_id} gone")

    async def go() -> dict[str, Any]:
        out: dict[str, Any] = {}
        async with _client() as s:
            a, ma = await _page(served, s, "slot-a")
            b, _ = await _page(served, s, "slot-b")
            out["a"] = json.loads(ma.data)["device"]
            await a.close()
            closed("slot-a")
            c, mc = await _page(served, s, "slot-c")      # both slots taken, but slot-a has left
            out["c"] = json.loads(mc.data)["type"]
            a2, ma2 = await _page(served, s, "slot-a")    # b and c are here: no slot for a
            out["a while full"] = (ma2.type, ma2.data)
            await a2.close()
            await c.close()
            closed("slot-c")
            a3, ma3 = await _page(served, s, "slot-a")    # back, into c's slot, as the same device
            out["a back"] = json.loads(ma3.data)["device"]
            await a3.close()
            for i in range(8):                            # one phone after another: each gets in
                w, m = await _page(served, s, f"slot-many-{i}")
                out.setdefault("many", []).append(json.loads(m.data)["type"])
                await w.close()
                closed(f"slot-many-{i}")
                out.setdefault("devices", []).append(len(served.service.capture.devices))
            await b.close()
        return out

    out = asyncio.run(go())
    assert out["c"] == "welcome"
    assert out["a while full"] == (aiohttp.WSMsgType.CLOSE, CLOSE_TOO_MANY)
    assert out["a back"] == out["a"]
    assert out["many"] == ["welcome"] * 8
    assert max(out["devices"]) <= 2
    assert served.rejected().get("phone not admitted") == 1
    # nobody needs the slots now: they are kept until the phones have been gone for the timeout
    served.wait(lambda: not any(phones.hub.get(k).connected for k in phones.devices), DEADLINE_S, "all gone")
    held = len(phones.devices)
    assert phones.sweep() == [] and len(phones.devices) == held
    clock.advance(61_000_000_000)
    assert len(phones.sweep()) == held
    assert phones.devices == {} and served.service.capture.devices == []
    assert served.service.health()["phone_slots"]["held"] == 0


def test_a_silent_datagram_phone_gives_up_its_slot(serve, free_port):
    clock = ManualClock()
    port = free_port()
    served = serve(osc_port=port, osc_allow="127.0.0.1", max_phones=1, limits=Limits(phone_timeout_s=30.0),
                   clock=clock)
    phones = served.service.phones
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u:
        u.sendto(_zigsim_bundle(0), ("127.0.0.1", port))
        served.wait(lambda: "osc/127.0.0.1" in phones.devices, DEADLINE_S, "the OSC phone admitted")
        # a phone with messages still to decode is not gone, however long ago they came: wait for its reader
        box = phones.hub.get("osc/127.0.0.1")
        served.wait(lambda: box is not None and len(box) == 0, DEADLINE_S, "the OSC phone's datagram decoded")
        assert phones.sweep() == []
        clock.advance(31_000_000_000)
        assert phones.sweep() == ["osc/127.0.0.1"]
        u.sendto(_zigsim_bundle(1), ("127.0.0.1", port))   # it comes back: admitted again, same device
        served.wait(lambda: "osc/127.0.0.1" in phones.devices, DEADLINE_S, "the OSC phone back")
    assert served.rejected() == {}


# -- connections and handshakes ------------------------------------------------------------------------------------
def _raw(port: int, src: str = "127.0.0.1") -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=DEADLINE_S, source_address=(src, 0))
    return s


def _closed_by_server(s: socket.socket) -> bool:
    """Blocks until the server ends the connection (EOF or reset): True; False if it sends data."""
    try:
        return s.recv(1) == b""
    except (ConnectionResetError, TimeoutError):
        return True
    except ssl.SSLError:
        return True


def test_half_open_handshakes_are_capped(serve):
    served = serve(limits=Limits(max_handshakes=3, handshake_timeout_s=10 * DEADLINE_S, max_sockets_per_host=16))
    gate = served.service.gateway.gate
    idle = [_raw(served.port) for _ in range(3)]              # TCP connected, no TLS ClientHello
    served.wait(lambda: gate.handshakes == 3, DEADLINE_S, "three handshakes in progress")
    fourth = _raw(served.port)
    assert _closed_by_server(fourth)                          # reset at accept: over the cap
    for s in [*idle, fourth]:
        s.close()
    served.wait(lambda: gate.open == 0 and gate.handshakes == 0, DEADLINE_S, "the gate holding nothing")
    assert served.rejected() == {"too many handshakes": 1, "TLS handshake failed": 3}  # they left mid-handshake
    ph = served.phone("after-handshakes", duration_s=1.0)     # the slots given back: a phone gets in
    _assert_lost_nothing(served, ph)
    info = served.service.health()["connections"]
    assert info["refused"] == 1 and info["peak_handshakes"] == 3


def test_handshakes_that_never_finish_are_timed_out(serve):
    served = serve(limits=Limits(handshake_timeout_s=1.0))
    gate = served.service.gateway.gate
    idle = [_raw(served.port) for _ in range(3)]              # no TLS ClientHello
    for s in idle:
        assert _closed_by_server(s)                           # closed by the handshake timeout
        s.close()
    ctx = ssl.create_default_context()                        # TLS done, no HTTP request: the same deadline
    ctx.check_hostname = False
    ctx.verify_mode = ssl.CERT_NONE
    with ctx.wrap_socket(_raw(served.port), server_hostname="perfcap") as t:
        assert _closed_by_server(t)
    served.wait(lambda: gate.open == 0 and gate.handshakes == 0, DEADLINE_S, "the gate holding nothing")
    assert served.rejected() == {"handshake timeout": 4}
    assert served.service.health()["connections"]["timed_out"] == 4


def test_connections_are_capped_per_address_and_in_total(serve):
    served = serve(limits=Limits(max_sockets=6, max_sockets_per_host=4, max_handshakes=64,
                                 handshake_timeout_s=DEADLINE_S))
    gate = served.service.gateway.gate
    near = [_raw(served.port, "127.0.0.5") for _ in range(4)]
    served.wait(lambda: gate.open == 4, DEADLINE_S, "four connections held")
    over = _raw(served.port, "127.0.0.5")
    assert _closed_by_server(over)
    far = [_raw(served.port, "127.0.0.6") for _ in range(2)]
    served.wait(lambda: gate.open == 6, DEADLINE_S, "six connections held")
    full = _raw(served.port, "127.0.0.7")
    assert _closed_by_server(full)
    rej = served.rejected()
    assert rej == {"too many connections from one address": 1, "too many connections": 1}
    for s in [*near, over, *far, full]:
        s.close()
    served.wait(lambda: gate.open == 0, DEADLINE_S, "the closed connections given back")
    assert gate.per_host() == {}


# -- the accounting, as properties ----------------------------------------------------------------------------------
def test_inbox_budget_property_random_sizes_and_drains():
    """Seeded: random message sizes, puts and reads. What waits never exceeds the budget (one message
    over it when the inbox was empty), the byte count is exact, every refusal is counted, and a second
    inbox fed at the same time is never refused."""
    for seed in range(40):
        rnd = random.Random(seed)
        budget = rnd.choice([1024, 8192, 65536])
        box, calm = Inbox("flood", max_bytes=budget), Inbox("calm", max_bytes=budget)
        box.connect("h")
        calm.connect("h2")
        held: list[int] = []
        refused = refused_bytes = 0
        for i in range(600):
            op = rnd.random()
            if op < 0.7:
                n = rnd.choice([0, 1, 10, 100, 1000, 5000, 70000])
                ok = box.put(Chunk(b"x" * n, i, Direction.RX))
                cost = n + CHUNK_OVERHEAD
                assert ok == (not held or sum(held) + cost <= budget)
                if ok:
                    held.append(cost)
                else:
                    refused += 1
                    refused_bytes += n
                assert calm.put(Chunk(b"c" * 50, i, Direction.RX))
                assert calm.get(0.0) is not None
            elif held:
                c = box.get(0.0)
                assert c is not None and len(c.data) + CHUNK_OVERHEAD == held.pop(0)
            assert box.queued_bytes == sum(held)
            assert box.queued_bytes <= budget or len(held) == 1
        assert box.dropped == refused and box.dropped_bytes == refused_bytes
        assert calm.dropped == 0


def test_rate_book_property_reconnects_ids_and_addresses():
    """Seeded: messages at random times from random phone ids on one flooding address, with random
    reconnects (which change nothing: the buckets are the phone's and the address's). Over any run a
    phone gets at most burst + rate x elapsed, the address k x that, and a calm phone on another
    address sending within its rate is never refused."""
    rate, burst, k = 20.0, 10.0, 4
    for seed in range(30):
        rnd = random.Random(seed)
        ids, hosts = RateBook(rate, burst, max_keys=rnd.choice([8, 64, 4096])), RateBook(rate * k, burst * k)
        t0 = t = 1_000_000_000
        got: dict[str, int] = {}
        calm_next = t0
        n_ids = rnd.choice([1, 3, 50])
        for _ in range(3000):
            t += rnd.choice([0, 0, 100_000, 1_000_000, 20_000_000])
            pid = f"p{rnd.randrange(n_ids)}"
            if ids.allow(pid, t) and hosts.allow("flood-host", t):
                got[pid] = got.get(pid, 0) + 1
            while calm_next <= t:                     # the calm phone: half its rate, its own address
                assert ids.allow("calm", calm_next) and hosts.allow("calm-host", calm_next)
                calm_next += int(2e9 / rate)
        elapsed = (t - t0) / 1e9
        assert sum(got.values()) <= k * (burst + rate * elapsed) + 1e-6
        if ids.evicted == 0:
            assert all(v <= burst + rate * elapsed + 1e-6 for v in got.values())


def test_rate_book_forgets_full_buckets_first():
    book = RateBook(10.0, 5.0, max_keys=3)
    t = 0
    for key in ("a", "b", "c"):
        for _ in range(5):
            assert book.allow(key, t)
    t += 10_000_000_000  # all full again
    assert book.allow("d", t) and len(book) == 1 and book.evicted == 0
    for key in ("e", "f"):
        book.allow(key, t)             # one token each: full again 0.1 s later
    t += 200_000_000
    for _ in range(5):
        assert book.allow("d", t)      # refilled to 5 meanwhile
    assert not book.allow("d", t)      # d is empty
    book.allow("g", t)                 # e and f are full: forgotten; d is kept, still empty
    assert len(book) == 2 and not book.allow("d", t) and book.evicted == 0


def test_stopping_closes_paired_phones_properly_and_gives_every_connection_back(serve):
    """The gate resets only connections still in their handshake when the service stops: a paired
    phone hears the shutdown close code, and nothing is left held."""
    served = serve()
    gate = served.service.gateway.gate
    half_open = _raw(served.port)
    served.wait(lambda: gate.handshakes == 1, DEADLINE_S, "one handshake in progress")

    async def go() -> int | None:
        async with _client() as s:
            ws, welcome = await _page(served, s, "shutdown-phone")
            assert json.loads(welcome.data)["type"] == "welcome"
            stopper = asyncio.get_running_loop().run_in_executor(None, served.stop)
            code = await _close_code(ws)
            await ws.close()
            await stopper
            return code

    assert asyncio.run(go()) == CLOSE_SHUTDOWN
    assert _closed_by_server(half_open)
    half_open.close()
    assert gate.open == 0 and gate.handshakes == 0


def test_plain_http_goes_through_the_gate_too(serve):
    served = serve(tls=False, limits=Limits(handshake_timeout_s=1.0))
    gate = served.service.gateway.gate

    async def go() -> Any:
        async with _client() as s:
            ws = await s.ws_connect(f"ws://127.0.0.1:{served.port}/ws/phone", autoping=True, heartbeat=None)
            await ws.send_str(page_hello("plain-phone", token=served.token).decode())
            first = await ws.receive(timeout=DEADLINE_S)
            for _ in range(5):
                await ws.send_str(_data())
            await ws.close()
            return json.loads(first.data)["type"]

    assert asyncio.run(go()) == "welcome"
    box = served.service.phones.hub.get("page/plain-phone")
    served.wait(lambda: not box.connected, DEADLINE_S, "the plain phone gone")
    assert box.received == 1 + 5
    silent = _raw(served.port)                   # plain TCP, no request: the same handshake deadline
    assert _closed_by_server(silent)
    silent.close()
    assert served.rejected() == {"handshake timeout": 1}
    served.wait(lambda: gate.open == 0, DEADLINE_S, "every connection given back")
