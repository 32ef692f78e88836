"""``perfcap serve`` under load: 10 phones over TLS WebSockets, and a flood of strangers.

    .venv/bin/python benchmarks/bench_serve.py [--seconds 20] [--flood-seconds 30] [--flood-rate 10000]
                                               [--only 1|2] [--no-record]

Every party runs in its own process, started by this script with ``--role``:

* the service: a ``Service`` (capture.app.serve) on 127.0.0.1 with TLS, default limits, no mDNS, recording
  every message to a session, as ``perfcap serve --record`` runs it (``perfcap serve --port 0`` does not
  tell a script its port, so a small Python child builds the Service and prints its endpoints as JSON).
  Its CPU and memory are read from ``/proc/<pid>``, so only the service is counted;
* the phones: ``SimPagePhone`` tasks on one event loop (the real page protocol: hello with the token,
  batched devicemotion data, pongs), each from its own loopback source address (127.0.0.10, .11, ...,
  as phones are separate hosts; the service allows 4 connections per host);
* the flood (part 2): one asyncio process sending malformed and unauthenticated input.

1. 10 phones x 100 Hz over ``wss://`` to the service for ``--seconds`` (default 20): the page's 50 ms
   batches (200 messages/s in all) and one message per motion event (1,000 messages/s, the harder case).
   Targets: zero lost (every motion event sent is an ``imu`` sample on the bus and in the recording);
   host-side added latency p99 < 5 ms; service CPU < 30% of one core over the steady state.
   *Host-side added latency* = the time a sample is published on the bus (handed to the subscribers,
   measured by wrapping the offer of a probe subscription in the service) minus its ``t_host_ns``,
   which is the arrival stamp the gateway put on the message's ``Chunk`` when aiohttp handed the
   WebSocket message to it. It covers the inbox, the phone's reader thread, decoding and clock
   stamping; not the kernel, TLS and WebSocket parsing before the stamp, which are shown separately
   as "wire" latency (stamp minus the client's send time; one monotonic clock on one machine).
   Baseline in the same run: the same phones against a bare aiohttp TLS WebSocket server (same
   certificate and socket settings) that only stamps each message: its CPU and wire latency are the
   floor that TLS, WebSocket framing and asyncio cost before perfcap does anything.
2. A flood of ``--flood-rate`` (default 10,000) malformed or unauthenticated messages per second for
   ``--flood-seconds`` (default 30) while 2 paired phones stream at 100 Hz:
   (a) WebSocket connections whose hello has a wrong or no token (a TLS handshake each);
   (b) a client holding the token that sends garbage after its hello (binary frames and malformed
       JSON text; the gateway closes it for rate or malformed input and it reconnects at once);
   (c) HTTPS POSTs to /ingest/sensorlogger with no or a wrong token (pipelined on keep-alive);
   (d) UDP datagrams to the OSC port from a source that is not allow-listed.
   Targets: the phones lose nothing, the service's RSS stays bounded (sampled every 0.25 s), the
   service still answers /api/health. The achieved flood rate is reported as sent and as counted.
   At the flood's end and 35 s later the service reports what it holds (live WebSocket and request
   objects, timer handles, device events kept by the capture's stats), to tell retention from growth.
   ``--no-record`` runs part 1 without the recorder, to see what recording costs.

Measurement script: prints figures and PASS/FAIL per target, always exits 0.
"""

from __future__ import annotations

import argparse
import asyncio
import contextvars
import json
import os
import queue
import socket
import subprocess
import sys
import tempfile
import threading
import time
from typing import Any

import numpy as np

TOKEN = "bench-serve-pairing-token-0123"
OSC_ALLOW = "192.0.2.7"  # TEST-NET-1: nobody on this machine, so every loopback datagram is refused
PHONE_SRC = 10           # phones send from 127.0.0.10, .11, ...
DATA_PREFIX = '{"type":"data"'
CLK_TCK = os.sysconf("SC_CLK_TCK")
RETAIN_S = 35.0          # part 2 looks at the service's memory again this long after the flood


def jprint(obj: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


# ================================================================================================
# role: service (the real Service, with a latency probe on its bus)
# ================================================================================================
def role_service(cfg: dict[str, Any]) -> None:
    import logging

    sys.setswitchinterval(cfg.get("switchinterval", 0.0005))  # as the perfcap CLI does for serve
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from capture.bus import Overflow, Subscriber
    from capture.sample import Sample, SampleBatch
    from capture.app.serve.config import ServeConfig
    from capture.app.serve.service import Service, ServiceThread

    osc_port = 0
    if cfg.get("osc"):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
            osc_port = s.getsockname()[1]
    conf = ServeConfig(host="127.0.0.1", port=0, control_port=0, mdns=False, state_dir=cfg["state_dir"],
                       token=TOKEN, osc_port=osc_port, osc_allow=OSC_ALLOW if osc_port else "")
    svc = Service(conf)

    class Probe(Subscriber):
        """Only its subscription is used: the offer below sees each item as it is published (on the
        reader thread) and keeps nothing in a queue, so the probe adds no delivery thread wake-ups."""

        accepts = frozenset({Sample, SampleBatch})

        def on_item(self, item: Any) -> None:  # never called: nothing is queued
            pass

    sub = svc.capture.subscribe(Probe(), Overflow.KEEP_NEWEST, "bench-probe")
    rows: dict[str, list[tuple[int, int]]] = {}   # imu stream -> (t_host_ns, publish time)
    counts: dict[str, int] = {}
    mono = time.monotonic_ns

    def offer(item: Any) -> None:  # called by SampleBus.publish_many on the reader thread
        t = mono()
        if type(item) is Sample:
            st = item.stream
            counts[st] = counts.get(st, 0) + 1
            if st.endswith("/imu"):
                r = rows.get(st)
                if r is None:
                    r = rows[st] = []
                r.append((item.t_host_ns, t))
        elif type(item) is SampleBatch:
            counts[item.stream] = counts.get(item.stream, 0) + len(item)

    sub.offer = offer  # type: ignore[method-assign]
    os.makedirs(cfg["state_dir"], exist_ok=True)
    session = os.path.join(cfg["state_dir"], "serve.mcap")
    if cfg.get("record", True):
        svc.capture.start_recording(session)
    st = ServiceThread(svc).start()
    ep = svc.endpoints
    jprint({"event": "ready", "pid": os.getpid(), "page_url": ep.page_url, "control_url": ep.control_url,
            "fingerprint": ep.fingerprint, "osc_port": ep.osc_port, "session": session})
    for line in sys.stdin:
        cmd = line.strip()
        if cmd == "stop":
            break
        if cmd == "probe":  # what the service holds in memory (objects alive, kept events)
            import collections
            import gc

            gc.collect()
            c = collections.Counter(type(o).__name__ for o in gc.get_objects())
            jprint({"event": "probe", "ws_alive": c["WebSocketResponse"], "request_handlers": c["RequestHandler"],
                    "timer_handles": c["TimerHandle"],
                    "stats_events": len(getattr(svc.capture.stats, "events", ())), "rss_mb": proc_rss_mb(os.getpid())})
    before = {"health": svc.health()}
    rep = st.stop()
    boxes = {k: {"received": b.received, "dropped": b.dropped, "connects": b.connects}
             for k, b in svc.phones.hub.inboxes().items()}
    arrays: dict[str, np.ndarray] = {}
    for name, r in rows.items():
        a = np.asarray(r, np.int64).reshape(-1, 2)
        arrays[f"host:{name}"] = a[:, 0]
        arrays[f"pub:{name}"] = a[:, 1]
    np.savez(cfg["out"], **arrays)
    subs = {s["name"]: {"dropped": s["dropped"], "delivered": s.get("delivered")} for s in rep.subscribers}
    jprint({"event": "stopped", "counts": counts, "devices": rep.devices, "boxes": boxes,
            "rejected": svc.gateway.rejected.as_dict(), "messages": svc.gateway.stats.messages,
            "connections": svc.gateway.stats.connections, "accepted": svc.gateway.stats.accepted,
            "health_before_stop": before["health"], "subscribers": subs,
            "recorder_error": rep.recorder_error, "phone_names": dict(svc.phones.devices)})


# ================================================================================================
# role: sink (baseline: a bare aiohttp TLS WebSocket server that only stamps messages)
# ================================================================================================
def role_sink(cfg: dict[str, Any]) -> None:
    from pathlib import Path

    from aiohttp import WSMsgType, web

    from capture.app.serve.tls import ensure_certificate

    sys.setswitchinterval(0.0005)
    cert = ensure_certificate(Path(cfg["state_dir"]), ["127.0.0.1"])
    arrivals: dict[str, list[int]] = {}

    async def ws_phone(request: web.Request) -> web.StreamResponse:
        ws = web.WebSocketResponse(max_msg_size=64 * 1024, heartbeat=20.0, autoping=True, compress=False)
        await ws.prepare(request)
        msg = await ws.receive(timeout=5.0)
        pid = json.loads(msg.data)["id"]
        await ws.send_str(json.dumps({"type": "welcome", "device": pid, "ping_s": 1.0}))
        arr = arrivals.setdefault(pid, [])
        mono = time.monotonic_ns
        async for m in ws:
            if m.type is WSMsgType.TEXT:
                arr.append(mono())
        return ws

    async def main() -> None:
        app = web.Application(client_max_size=64 * 1024)
        app.router.add_get("/ws/phone", ws_phone)
        runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await runner.setup()
        site = web.TCPSite(runner, "127.0.0.1", 0, ssl_context=cert.server_context(), backlog=128)
        await site.start()
        port = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]
        jprint({"event": "ready", "pid": os.getpid(), "page_url": f"https://127.0.0.1:{port}/",
                "fingerprint": cert.fingerprint})
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(None, sys.stdin.readline)
        await runner.cleanup()

    asyncio.run(main())
    np.savez(cfg["out"], **{f"arr:{k}": np.asarray(v, np.int64) for k, v in arrivals.items()})
    jprint({"event": "stopped", "messages": {k: len(v) for k, v in arrivals.items()}})


# ================================================================================================
# role: phones (SimPagePhone tasks on one loop, each from its own loopback address)
# ================================================================================================
_SOURCE: contextvars.ContextVar[str | None] = contextvars.ContextVar("bench_source", default=None)


def _patch_client_source() -> None:
    """Make every ``aiohttp.ClientSession()`` made in a task bind to that task's source address."""
    import aiohttp

    orig = aiohttp.ClientSession

    def session(*a: Any, **k: Any) -> Any:
        addr = _SOURCE.get()
        if addr and "connector" not in k:
            k["connector"] = aiohttp.TCPConnector(local_addr=(addr, 0))
        return orig(*a, **k)

    aiohttp.ClientSession = session  # type: ignore[misc,assignment]


class _TimedWS:
    """A client WebSocket that notes the monotonic time just before each data message is sent."""

    def __init__(self, ws: Any, sends: list[int]) -> None:
        self._ws = ws
        self._sends = sends

    def __getattr__(self, name: str) -> Any:
        return getattr(self._ws, name)

    def __aiter__(self) -> Any:
        return self._ws.__aiter__()

    async def send_str(self, data: str, *a: Any, **k: Any) -> None:
        if data.startswith(DATA_PREFIX):
            self._sends.append(time.monotonic_ns())
        await self._ws.send_str(data, *a, **k)


def role_phones(cfg: dict[str, Any]) -> None:
    from sim_devices.phone_client import SimPagePhone

    _patch_client_source()

    class TimedPhone(SimPagePhone):
        def __init__(self, *a: Any, **k: Any) -> None:
            super().__init__(*a, **k)
            self.send_ns: list[int] = []

        async def _connect(self, session: Any) -> Any:
            ws = await super()._connect(session)
            return None if ws is None else _TimedWS(ws, self.send_ns)

    url = cfg["page_url"].replace("https://", "wss://") + "ws/phone"
    phones = [TimedPhone(url, cfg["token"], f"bench{k:02d}", rate_hz=cfg["rate"], duration_s=cfg["duration"],
                         seed=k + 1, fingerprint=cfg["fingerprint"], batch_s=cfg["batch_s"])
              for k in range(cfg["n"])]
    if cfg.get("t0_ms") is not None:
        for p in phones:
            p.t0_ms = cfg["t0_ms"]

    async def main() -> None:
        tasks = []
        for k, p in enumerate(phones):
            _SOURCE.set(f"127.0.0.{cfg['src'] + k}")
            tasks.append(asyncio.create_task(p.run()))
        _SOURCE.set(None)
        t_end = time.monotonic() + 15.0
        while not all(p.device for p in phones) and time.monotonic() < t_end and not all(t.done() for t in tasks):
            await asyncio.sleep(0.01)
        jprint({"event": "streaming", "t_ns": time.monotonic_ns(), "connected": sum(1 for p in phones if p.device)})
        res = await asyncio.gather(*tasks, return_exceptions=True)
        for p, r in zip(phones, res):
            if isinstance(r, BaseException) and p.error is None:
                p.error = r

    c0, w0 = time.process_time(), time.monotonic()
    asyncio.run(main())
    cpu = (time.process_time() - c0) / (time.monotonic() - w0)
    arrays = {}
    out = []
    for p in phones:
        arrays[f"send:{p.phone_id}"] = np.asarray(p.send_ns, np.int64)
        msgs = getattr(p, "messages", [])[:len(p.send_ns)]
        sched = p.truth_ns(np.asarray([m.sent_ms for m in msgs], float)) if msgs else np.zeros(0)
        arrays[f"sched:{p.phone_id}"] = np.asarray(sched, np.int64)
        out.append({"id": p.phone_id, "device": p.device, "sent": p.sent, "events": p.events, "pongs": p.pongs,
                    "connects": p.connects, "close_code": p.close_code, "error": None if p.error is None
                    else f"{type(p.error).__name__}: {p.error}"})
    np.savez(cfg["out"], **arrays)
    jprint({"event": "done", "phones": out, "cpu_frac": cpu})


# ================================================================================================
# role: flood
# ================================================================================================
_GARBAGE_TEXT = ['{"type":"data","seq":', "not json at all", '{"type":"data","seq":"x","m":[[1,2]]}',
                 "[1,2,3", "null", '{"type":"hello"', "\x00\x01\x02garbage\xff", '{"m":' + "9" * 200]


def role_flood(cfg: dict[str, Any]) -> None:
    import random
    import ssl

    import aiohttp

    from sim_devices.phone_sim import page_hello

    rate = cfg["rate"]
    mix = cfg["mix"]           # share per category
    dur = cfg["duration"]
    host, port = "127.0.0.1", cfg["port"]
    ws_url = f"wss://127.0.0.1:{port}/ws/phone"
    sent = {k: 0 for k in ("a_ws_bad_token", "b_ws_garbage", "c_post_no_token", "d_udp_not_allowed")}
    extra: dict[str, Any] = {"a_refused_503": 0, "a_closed_4401": 0, "a_other": {}, "b_connects": 0,
                             "b_close_codes": {}, "b_binary": 0, "b_text": 0, "c_responses": 0, "c_status": {},
                             "d_would_block": 0, "b_refused": 0, "c_connections": 0}
    rnd = random.Random(7)
    ctx = ssl.create_default_context()
    ctx.check_hostname = False
    ctx.verify_mode = ssl.CERT_NONE

    def due(share: float, t0: float) -> int:
        return int(rate * share * (time.monotonic() - t0))

    async def udp(t0: float, t_end: float) -> None:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.2", 0))
        s.setblocking(False)
        payloads = [b"/ZIGSIM/x/accel\x00,fff\x00" + bytes(rnd.getrandbits(8) for _ in range(n))
                    for n in (12, 40, 100, 180)]
        dst = (host, cfg["osc_port"])
        k = 0
        while time.monotonic() < t_end:
            n = due(mix["d"], t0) - sent["d_udp_not_allowed"]
            for _ in range(max(0, n)):
                try:
                    s.sendto(payloads[k & 3], dst)
                    sent["d_udp_not_allowed"] += 1
                except BlockingIOError:
                    extra["d_would_block"] += 1
                    break
                k += 1
            await asyncio.sleep(0.005)
        s.close()

    async def posts(t0: float, t_end: float, conns: int = 4, cap: int = 128) -> None:
        body = json.dumps({"messageId": 1, "sessionId": "x", "deviceId": "intruder",
                           "payload": [{"name": "accelerometer", "time": 1, "values": {"x": 0, "y": 0, "z": 9.8}}]})
        reqs = []
        for path in ("/ingest/sensorlogger", "/ingest/sensorlogger?token=wrong-token-0123456789"):
            reqs.append((f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                         f"Content-Length: {len(body)}\r\n\r\n{body}").encode())
        share = mix["c"] / conns

        async def one(i: int) -> None:
            while time.monotonic() < t_end:
                try:
                    r, w = await asyncio.open_connection(host, port, ssl=ctx, local_addr=("127.0.0.3", 0))
                except OSError:
                    await asyncio.sleep(0.05)
                    continue
                extra["c_connections"] += 1
                mine = {"sent": 0, "resp": 0}
                base = due(share, t0)

                async def read(r: asyncio.StreamReader = r, mine: dict[str, int] = mine) -> None:
                    tail = b""
                    while True:
                        data = await r.read(65536)
                        if not data:
                            return
                        buf = tail + data
                        n = buf.count(b"HTTP/1.1 ")
                        for code in (b"HTTP/1.1 401", b"HTTP/1.1 400", b"HTTP/1.1 429", b"HTTP/1.1 413"):
                            c = buf.count(code)
                            if c:
                                extra["c_status"][code[9:].decode()] = extra["c_status"].get(code[9:].decode(), 0) + c
                        mine["resp"] += n
                        extra["c_responses"] += n
                        tail = buf[-12:]
                        # do not count a status line twice across the boundary
                        if b"HTTP/1.1 " in tail:
                            tail = b""

                rt = asyncio.create_task(read())
                try:
                    while time.monotonic() < t_end and not rt.done():
                        n = due(share, t0) - base - mine["sent"]
                        n = min(n, cap - (mine["sent"] - mine["resp"]))
                        if n > 0:
                            w.write(b"".join(reqs[(mine["sent"] + j) & 1] for j in range(n)))
                            mine["sent"] += n
                            sent["c_post_no_token"] += n
                            await w.drain()
                        await asyncio.sleep(0.005)
                    # let the answers to what was sent come back
                    t_wait = time.monotonic() + 2.0
                    while mine["resp"] < mine["sent"] and time.monotonic() < t_wait and not rt.done():
                        await asyncio.sleep(0.01)
                except (ConnectionError, OSError):
                    pass
                finally:
                    rt.cancel()
                    w.close()

        await asyncio.gather(*(one(i) for i in range(conns)))

    async def bad_token(t0: float, t_end: float, sources: int = 4, per_source: int = 4) -> None:
        async def worker(src: str, j: int) -> None:
            async with aiohttp.ClientSession(connector=aiohttp.TCPConnector(local_addr=(src, 0))) as sess:
                while time.monotonic() < t_end:
                    if sent["a_ws_bad_token"] >= due(mix["a"], t0):
                        await asyncio.sleep(0.002)
                        continue
                    sent["a_ws_bad_token"] += 1
                    tok = None if sent["a_ws_bad_token"] % 2 else "wrong-token-" + "x" * 20
                    try:
                        ws = await sess.ws_connect(ws_url, ssl=False, autoping=True, heartbeat=None)
                    except aiohttp.WSServerHandshakeError as exc:
                        if exc.status == 503:
                            extra["a_refused_503"] += 1
                        else:
                            extra["a_other"][str(exc.status)] = extra["a_other"].get(str(exc.status), 0) + 1
                        continue
                    except (aiohttp.ClientError, OSError) as exc:
                        extra["a_other"][type(exc).__name__] = extra["a_other"].get(type(exc).__name__, 0) + 1
                        await asyncio.sleep(0.01)
                        continue
                    try:
                        await ws.send_str(page_hello(f"intruder{j}", token=tok).decode())
                        await ws.receive(timeout=5.0)
                        if ws.close_code == 4401:
                            extra["a_closed_4401"] += 1
                        else:
                            extra["a_other"][str(ws.close_code)] = extra["a_other"].get(str(ws.close_code), 0) + 1
                    except (TimeoutError, aiohttp.ClientError, OSError) as exc:
                        extra["a_other"][type(exc).__name__] = extra["a_other"].get(type(exc).__name__, 0) + 1
                    finally:
                        await ws.close()

        await asyncio.gather(*(worker(f"127.0.0.{20 + s}", s * per_source + j)
                               for s in range(sources) for j in range(per_source)))

    async def garbage(t0: float, t_end: float, clients: int = 2) -> None:
        share = mix["b"] / clients
        junk = [bytes(rnd.getrandbits(8) for _ in range(n)) for n in (16, 64, 256)]

        async def client(i: int) -> None:
            async with aiohttp.ClientSession(connector=aiohttp.TCPConnector(local_addr=("127.0.0.4", 0))) as sess:
                mine = 0
                while time.monotonic() < t_end:
                    try:
                        ws = await sess.ws_connect(ws_url, ssl=False, autoping=True, heartbeat=None)
                    except aiohttp.WSServerHandshakeError:
                        extra["b_refused"] += 1
                        await asyncio.sleep(0.01)
                        continue
                    except (aiohttp.ClientError, OSError):
                        await asyncio.sleep(0.01)
                        continue
                    extra["b_connects"] += 1
                    try:
                        await ws.send_str(page_hello(f"garbage{i}", token=TOKEN).decode())
                        msg = await ws.receive(timeout=5.0)
                        if msg.type is not aiohttp.WSMsgType.TEXT:
                            continue

                        async def drain(ws: Any = ws) -> None:
                            async for _ in ws:
                                pass

                        dt = asyncio.create_task(drain())
                        while time.monotonic() < t_end and not ws.closed and not dt.done():
                            n = due(share, t0) - mine
                            for _ in range(max(0, n)):
                                if ws.closed:
                                    break
                                if mine % 10 == 9:
                                    await ws.send_bytes(junk[mine % 3])
                                    extra["b_binary"] += 1
                                else:
                                    await ws.send_str(_GARBAGE_TEXT[mine % len(_GARBAGE_TEXT)])
                                    extra["b_text"] += 1
                                mine += 1
                                sent["b_ws_garbage"] += 1
                            await asyncio.sleep(0.005)
                        dt.cancel()
                    except (TimeoutError, aiohttp.ClientError, OSError):
                        pass
                    finally:
                        code = ws.close_code
                        extra["b_close_codes"][str(code)] = extra["b_close_codes"].get(str(code), 0) + 1
                        await ws.close()
                    # a closed client catches up from where the clock is, not with a burst
                    mine = max(mine, due(share, t0) - 1)

        await asyncio.gather(*(client(i) for i in range(clients)))

    async def main() -> dict[str, Any]:
        t0 = time.monotonic()
        t_end = t0 + dur
        jprint({"event": "flooding", "t_ns": time.monotonic_ns()})
        await asyncio.gather(udp(t0, t_end), posts(t0, t_end), bad_token(t0, t_end), garbage(t0, t_end))
        return {"wall_s": time.monotonic() - t0}

    c0 = time.process_time()
    w = asyncio.run(main())
    jprint({"event": "done", "sent": sent, "extra": extra, "wall_s": w["wall_s"],
            "cpu_frac": (time.process_time() - c0) / w["wall_s"]})


# ================================================================================================
# orchestration
# ================================================================================================
class Child:
    """A role in its own process: JSON lines on stdout, stderr to a log file."""

    def __init__(self, role: str, cfg: dict[str, Any], log_path: str) -> None:
        self.log_path = log_path
        self._log = open(log_path, "w")  # noqa: SIM115 - the child's stderr for its whole life; closed in close()
        self.p = subprocess.Popen([sys.executable, os.path.abspath(__file__), "--role", role, "--cfg", json.dumps(cfg)],
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._log, text=True)
        self.pid = self.p.pid
        self._q: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.p.stdout is not None
        for line in self.p.stdout:
            self._q.put(line)
        self._q.put(None)

    def expect(self, event: str, timeout: float) -> dict[str, Any]:
        t_end = time.monotonic() + timeout
        while True:
            try:
                line = self._q.get(timeout=max(0.01, t_end - time.monotonic()))
            except queue.Empty:
                raise RuntimeError(f"{event!r} not seen in {timeout:.0f} s; see {self.log_path}") from None
            if line is None:
                with open(self.log_path) as f:
                    tail = f.read()[-3000:]
                raise RuntimeError(f"process ended before {event!r}; see {self.log_path}:\n{tail}")
            try:
                obj = json.loads(line)
            except ValueError:
                continue
            if obj.get("event") == event:
                return obj

    def send(self, line: str) -> None:
        assert self.p.stdin is not None
        self.p.stdin.write(line + "\n")
        self.p.stdin.flush()

    def close(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait(5)
        self._log.close()


def proc_cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        rest = f.read().rsplit(")", 1)[1].split()
    return (int(rest[11]) + int(rest[12])) / CLK_TCK


def proc_rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def udp_rcvbuf_errors() -> int:
    """Datagrams the kernel dropped because a socket's receive buffer was full (system-wide)."""
    with open("/proc/net/snmp") as f:
        rows = [ln.split() for ln in f if ln.startswith("Udp:")]
    return int(rows[1][rows[0].index("RcvbufErrors")])


def machine_jiffies() -> tuple[int, int]:
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    return sum(v), v[3] + v[4]


class Window:
    """CPU of some processes and of the whole machine over a time window."""

    def __init__(self, pids: dict[str, int]) -> None:
        self.pids = pids
        self.t0 = time.monotonic()
        self.t0_ns = time.monotonic_ns()
        self.c0 = {k: proc_cpu_s(p) for k, p in pids.items()}
        self.m0 = machine_jiffies()

    def end(self) -> dict[str, Any]:
        wall = time.monotonic() - self.t0
        cpu = {k: (proc_cpu_s(p) - self.c0[k]) / wall for k, p in self.pids.items()}
        m1 = machine_jiffies()
        tot, idle = m1[0] - self.m0[0], m1[1] - self.m0[1]
        busy_cores = (1.0 - idle / max(1, tot)) * (os.cpu_count() or 1)
        return {"wall": wall, "cpu": cpu, "t0_ns": self.t0_ns, "t1_ns": time.monotonic_ns(),
                "machine_cores": busy_cores, "others_cores": busy_cores - sum(cpu.values())}


def pcts(a: np.ndarray, qs: tuple[float, ...] = (50, 99, 99.9, 100)) -> list[float]:
    if a.size == 0:
        return [float("nan")] * len(qs)
    return [float(x) for x in np.percentile(a, qs)]


def fmt_ms(a: np.ndarray) -> str:
    p50, p99, p999, mx = pcts(a)
    return f"p50 {p50:.3f}  p99 {p99:.3f}  p99.9 {p999:.3f}  max {mx:.3f} ms (n={a.size})"


def match_wire(arrivals: dict[str, np.ndarray], sends: dict[str, np.ndarray],
               window: tuple[int, int] | None = None) -> tuple[np.ndarray, list[str]]:
    """Per message: arrival stamp minus the client's send time (messages matched by order), for the
    messages that arrived in ``window`` (monotonic ns) if given."""
    out, bad = [], []
    for key, arr in arrivals.items():
        snd = sends.get(key)
        if snd is None or snd.size != arr.size:
            bad.append(f"{key}: {0 if snd is None else snd.size} sent, {arr.size} arrived")
            continue
        sel = slice(None) if window is None else (arr >= window[0]) & (arr <= window[1])
        out.append((arr[sel] - snd[sel]) / 1e6)
    return (np.concatenate(out) if out else np.zeros(0)), bad


def pacing(ph: Any, window: tuple[int, int]) -> np.ndarray:
    """The phones' send time behind their schedule (ms), for sends in ``window``."""
    out = []
    for k in ph.files:
        if k.startswith("send:"):
            snd, sch = ph[k], ph["sched:" + k[5:]]
            snd = snd[:sch.size]
            sel = (snd >= window[0]) & (snd <= window[1])
            out.append((snd[sel] - sch[sel]) / 1e6)
    return np.concatenate(out) if out else np.zeros(0)


def run_phones(tmp: str, tag: str, target: Child, n: int, batch_s: float, duration: float, t0_ms: float | None,
               src: int, window: tuple[float, float]) -> tuple[dict[str, Any], dict[str, Any], np.lib.npyio.NpzFile]:
    """Phones against ``target`` (service or sink); returns (phones result, CPU window, phone arrays)."""
    ep = target.ready
    out = os.path.join(tmp, f"{tag}-phones.npz")
    cfg = {"page_url": ep["page_url"], "token": TOKEN, "fingerprint": ep["fingerprint"], "n": n, "rate": 100.0,
           "batch_s": batch_s, "duration": duration, "t0_ms": t0_ms, "src": src, "out": out}
    ph = Child("phones", cfg, os.path.join(tmp, f"{tag}-phones.log"))
    try:
        st = ph.expect("streaming", 30)
        if st["connected"] != n:
            print(f"   !! only {st['connected']} of {n} phones connected")
        time.sleep(window[0])
        w = Window({"target": target.pid, "phones": ph.pid})
        time.sleep(max(0.5, duration - window[0] - window[1]))
        win = w.end()
        res = ph.expect("done", duration + 60)
    finally:
        ph.close()
    return res, win, np.load(out)


def part1(tmp: str, seconds: float, record: bool = True) -> None:
    print(f"1. 10 phones x 100 Hz over wss:// on loopback, {seconds:.0f} s per run; the CPU window is the steady"
          f" state from 3 s after all phones connected to 1 s before they stop")
    print("   host-side added latency = publish on the bus (probe on the service's SampleBus) minus the sample's"
          " t_host_ns, the arrival stamp the gateway put on the message's Chunk;")
    print("   wire latency = that arrival stamp minus the client's monotonic time just before send_str (kernel,"
          " TLS, WebSocket, event loop: before perfcap's stamp)")
    variants = [("batch 50 ms (the page: 200 messages/s in all)", 0.05, None),
                ("one message per motion event (batch_s 0.01: 1,000 messages/s in all)", 0.01, 1505.0)]
    win_skip = (3.0, 1.0)
    for label, batch_s, t0_ms in variants:
        print()
        print(f"   -- {label}")
        # ---- baseline: bare aiohttp TLS WebSocket sink -------------------------------------------
        tag = f"sink{int(batch_s * 1000)}"
        sink = Child("sink", {"state_dir": os.path.join(tmp, "sink-state"), "out": os.path.join(tmp, f"{tag}.npz")},
                     os.path.join(tmp, f"{tag}.log"))
        try:
            sink.ready = sink.expect("ready", 30)  # type: ignore[attr-defined]
            res_b, win_b, ph_b = run_phones(tmp, tag, sink, 10, batch_s, seconds, t0_ms, PHONE_SRC, win_skip)
            sink.send("stop")
            sink.expect("stopped", 30)
        finally:
            sink.close()
        arr_b = np.load(os.path.join(tmp, f"{tag}.npz"))
        arrivals = {k[4:]: arr_b[k] for k in arr_b.files}
        sends = {k[5:]: ph_b[k] for k in ph_b.files if k.startswith("send:")}
        wire_b, bad_b = match_wire(arrivals, sends, (win_b["t0_ns"], win_b["t1_ns"]))
        sent_b = sum(p["sent"] for p in res_b["phones"])
        got_b = sum(v.size for v in arrivals.values())
        print(f"   baseline, bare aiohttp TLS WebSocket server (stamps each message, nothing else): CPU"
              f" {win_b['cpu']['target'] * 100:.1f}% of one core; {got_b} of {sent_b} messages arrived;"
              f" wire latency (steady window) {fmt_ms(wire_b)}" + (f"; unmatched: {bad_b}" if bad_b else ""))
        base_cpu = win_b["cpu"]["target"]
        # ---- the service ---------------------------------------------------------------------------
        tag = f"serve{int(batch_s * 1000)}"
        sdir = os.path.join(tmp, f"{tag}-state")
        svc = Child("service", {"state_dir": sdir, "out": os.path.join(tmp, f"{tag}.npz"), "record": record},
                    os.path.join(tmp, f"{tag}.log"))
        try:
            svc.ready = svc.expect("ready", 30)  # type: ignore[attr-defined]
            res, win, ph = run_phones(tmp, tag, svc, 10, batch_s, seconds, t0_ms, PHONE_SRC, win_skip)
            svc.send("stop")
            stopped = svc.expect("stopped", 60)
        finally:
            svc.close()
        report_service_run(tmp, tag, svc.ready, stopped, res, win, ph, base_cpu, wire_b, label,  # type: ignore[attr-defined]
                           seconds, record)


def service_arrays(tmp: str, tag: str) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    a = np.load(os.path.join(tmp, f"{tag}.npz"))
    host = {k[5:]: a[k] for k in a.files if k.startswith("host:")}
    pub = {k[4:]: a[k] for k in a.files if k.startswith("pub:")}
    return host, pub


def loss_check(phones: list[dict[str, Any]], stopped: dict[str, Any], session: str | None) -> tuple[bool, list[str]]:
    """Every motion event sent is an imu sample on the bus and in the recording (if any), with no refusals."""
    from capture.session import SessionReader

    reader = SessionReader(session) if session else None
    lines, ok = [], True
    tot_ev = tot_bus = tot_rec = 0
    for p in phones:
        dev = p["device"]
        stream = f"{dev}/imu"
        bus = stopped["counts"].get(stream, 0)
        if reader is None:
            rec = bus
        else:
            rec = len(reader.samples(stream)) if stream in reader.streams else 0
        d = stopped["devices"].get(dev, {})
        box = stopped["boxes"].get(f"page/{p['id']}", {})
        tot_ev += p["events"]
        tot_bus += bus
        tot_rec += rec
        bad = (bus != p["events"] or rec != p["events"] or d.get("lost_messages", 0) or d.get("lost_readings", 0)
               or box.get("dropped", 0) or p["connects"] != 1 or p["error"] or d.get("framing_errors", 0))
        if bad:
            ok = False
            lines.append(f"{p['id']} -> {dev}: {p['events']} events sent in {p['sent']} messages, {bus} imu samples on"
                         f" the bus, {rec} recorded; seq gaps {d.get('lost_messages')}, lost readings"
                         f" {d.get('lost_readings')}, inbox refused {box.get('dropped')}, connects {p['connects']},"
                         f" close code {p['close_code']}, error {p['error']}")
    rec_drop = stopped["subscribers"].get("recorder", {}).get("dropped", 0)
    if rec_drop or stopped.get("recorder_error"):
        ok = False
        lines.append(f"recorder dropped {rec_drop}, error {stopped.get('recorder_error')}")
    lines.insert(0, f"{tot_ev} motion events sent by {len(phones)} phones; {tot_bus} imu samples on the bus;"
                    + (f" {tot_rec} in the recording; recorder drops {rec_drop}" if reader else " (not recording)"))
    return ok, lines


def report_service_run(tmp: str, tag: str, ready: dict[str, Any], stopped: dict[str, Any], res: dict[str, Any],
                       win: dict[str, Any], ph: Any, base_cpu: float, wire_b: np.ndarray, label: str,
                       seconds: float, record: bool) -> None:
    host, pub = service_arrays(tmp, tag)
    ok_loss, lines = loss_check(res["phones"], stopped, ready["session"] if record else None)
    # latency over the CPU window (steady state) and over the whole run
    lat_all, lat_win = [], []
    arrivals = {}
    for stream, h in host.items():
        lat = (pub[stream] - h) / 1e6
        lat_all.append(lat)
        lat_win.append(lat[(h >= win["t0_ns"]) & (h <= win["t1_ns"])])
        dev = stream[:-4]
        pid = next((p["id"] for p in res["phones"] if p["device"] == dev), None)
        if pid is not None:
            arrivals[pid] = np.unique(h)  # one arrival stamp per message (sorted = arrival order)
    la = np.concatenate(lat_all) if lat_all else np.zeros(0)
    lw = np.concatenate(lat_win) if lat_win else np.zeros(0)
    sends = {k[5:]: ph[k] for k in ph.files if k.startswith("send:")}
    wire, bad = match_wire(arrivals, sends, (win["t0_ns"], win["t1_ns"]))
    late = pacing(ph, (win["t0_ns"], win["t1_ns"]))
    cpu = win["cpu"]["target"]
    msgs = sum(p["sent"] for p in res["phones"])
    print(f"   perfcap serve (Service with TLS, default limits, {'recording every message' if record else 'NOT recording'};"
          f" 10 reader threads):")
    for ln in lines:
        print(f"      {ln}")
    print(f"      host-side added latency, steady window: {fmt_ms(lw)}")
    print(f"      host-side added latency, whole run incl. connect: {fmt_ms(la)}")
    print(f"      wire latency (client send -> arrival stamp), steady window: {fmt_ms(wire)}; bare server: {fmt_ms(wire_b)}"
          + (f"; unmatched: {bad}" if bad else ""))
    print(f"      client pacing, steady window: send time behind schedule {fmt_ms(late)}; phones process CPU"
          f" {win['cpu']['phones'] * 100:.0f}% of one core")
    print(f"      service CPU {cpu * 100:.1f}% of one core over {win['wall']:.1f} s"
          f" ({cpu * 1e6 / max(1.0, msgs / seconds):.0f} us per message at {msgs / seconds:.0f} messages/s);"
          f" bare server {base_cpu * 100:.1f}%; service minus bare {100 * (cpu - base_cpu):.1f} points")
    print(f"      machine: {win['machine_cores']:.2f} of {os.cpu_count()} cores busy in the window, of which"
          f" {max(0.0, win['others_cores']):.2f} by other processes (not this benchmark)")
    short = "50 ms" if "50 ms" in label else "1 msg/event"
    p99 = pcts(lw)[1]
    check(f"10 phones, {short}: zero lost", ok_loss, lines[0])
    check(f"10 phones, {short}: host-side added latency p99 < 5 ms", p99 < 5.0, f"{p99:.3f} ms (steady window)")
    check(f"10 phones, {short}: service CPU < 30% of one core", cpu < 0.30, f"{cpu * 100:.1f}%")


# ------------------------------------------------------------------------------------------------
def http_json(url: str, token: str | None, timeout: float = 10.0) -> tuple[int, Any]:
    import urllib.error
    import urllib.request

    req = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"} if token else {})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, json.load(r)
    except urllib.error.HTTPError as exc:
        return exc.code, None
    except (OSError, ValueError) as exc:
        return 0, str(exc)


def part2(tmp: str, flood_s: float, flood_rate: float) -> None:
    mix = {"a": 0.02, "b": 0.28, "c": 0.30, "d": 0.40}
    print(f"2. flood of {flood_rate:,.0f} malformed/unauthenticated messages/s for {flood_s:.0f} s (targets per category:"
          f" (a) WS with wrong/no token {mix['a'] * flood_rate:,.0f}/s, each a new TLS connection, from 4 sources x 4;"
          f" (b) paired client sending garbage {mix['b'] * flood_rate:,.0f}/s, 2 connections from 127.0.0.4;"
          f" (c) POST /ingest/sensorlogger without/with a wrong token {mix['c'] * flood_rate:,.0f}/s, pipelined on 4"
          f" keep-alive TLS connections; (d) UDP to the OSC port from 127.0.0.2, allow-list {OSC_ALLOW},"
          f" {mix['d'] * flood_rate:,.0f}/s), 2 paired phones at 100 Hz (batch 50 ms) throughout")
    sdir = os.path.join(tmp, "flood-state")
    svc = Child("service", {"state_dir": sdir, "out": os.path.join(tmp, "flood.npz"), "osc": True},
                os.path.join(tmp, "flood-service.log"))
    rss: list[tuple[float, float]] = []
    stop_rss = threading.Event()
    try:
        ready = svc.ready = svc.expect("ready", 30)  # type: ignore[attr-defined]

        def sample_rss() -> None:
            while not stop_rss.is_set():
                try:
                    rss.append((time.monotonic(), proc_rss_mb(svc.pid)))
                except OSError:
                    return
                stop_rss.wait(0.25)

        threading.Thread(target=sample_rss, daemon=True).start()
        lead, tail = 3.0, 4.0
        duration = lead + flood_s + tail + 1.0
        out = os.path.join(tmp, "flood-phones.npz")
        ph = Child("phones", {"page_url": ready["page_url"], "token": TOKEN, "fingerprint": ready["fingerprint"],
                              "n": 2, "rate": 100.0, "batch_s": 0.05, "duration": duration, "t0_ms": None,
                              "src": PHONE_SRC, "out": out}, os.path.join(tmp, "flood-phones.log"))
        try:
            ph.expect("streaming", 30)
            time.sleep(lead)
            _, h0 = http_json(ready["control_url"] + "/health", TOKEN)
            rej0 = dict(h0.get("rejected", {})) if isinstance(h0, dict) else {}
            port = int(ready["page_url"].rsplit(":", 1)[1].strip("/"))
            fl = Child("flood", {"rate": flood_rate, "mix": mix, "duration": flood_s, "port": port,
                                 "osc_port": ready["osc_port"]}, os.path.join(tmp, "flood.log"))
            try:
                fl.expect("flooding", 30)
                udp0 = udp_rcvbuf_errors()
                t_f0 = time.monotonic()
                w = Window({"service": svc.pid, "flood": fl.pid, "phones": ph.pid})
                fres = fl.expect("done", flood_s + 60)
                t_f1 = time.monotonic()
                win = w.end()
                time.sleep(0.5)
                udp_dropped = udp_rcvbuf_errors() - udp0
            finally:
                fl.close()
            svc.send("probe")
            probe1 = svc.expect("probe", 30)
            time.sleep(1.0)
            hs, h1 = http_json(ready["control_url"] + "/health", TOKEN)
            hs_bad, _ = http_json(ready["control_url"] + "/health", "wrong-token-0000000000")
            res = ph.expect("done", duration + 60)
        finally:
            ph.close()
        # aiohttp keeps a closed WebSocket for its heartbeat (20 s) and pong wait (10 s): look again after that
        time.sleep(max(0.0, t_f1 + RETAIN_S - time.monotonic()))
        svc.send("probe")
        probe2 = svc.expect("probe", 30)
        stop_rss.set()
        svc.send("stop")
        stopped = svc.expect("stopped", 60)
    finally:
        stop_rss.set()
        svc.close()

    # ---- flood rate -------------------------------------------------------------------------------
    sent = fres["sent"]
    ex = fres["extra"]
    tot = sum(sent.values())
    rej1 = dict(h1.get("rejected", {})) if isinstance(h1, dict) else {}
    counted = {k: rej1.get(k, 0) - rej0.get(k, 0) for k in rej1}
    wall = fres["wall_s"]
    print(f"   flood sent {tot:,} messages in {wall:.1f} s = {tot / wall:,.0f}/s (target {flood_rate:,.0f}/s):")
    for k, v in sent.items():
        print(f"      {k:20s} {v:9,d}  {v / wall:8,.0f}/s")
    print(f"      (a) closed with 4401 (token) {ex['a_closed_4401']:,}, refused 503 (too many connections)"
          f" {ex['a_refused_503']:,}, other {ex['a_other']}")
    print(f"      (b) {ex['b_connects']:,} connections, {ex['b_text']:,} text + {ex['b_binary']:,} binary frames sent;"
          f" close codes {ex['b_close_codes']}; refused at connect {ex['b_refused']}")
    print(f"      (c) {ex['c_responses']:,} responses {ex['c_status']} on {ex['c_connections']} connections")
    print(f"      (d) would-block on send {ex['d_would_block']}; dropped by the kernel, the service's receive buffer"
          f" full (RcvbufErrors, system-wide): {udp_dropped:,}")
    gdev = [v for k, v in stopped["phone_names"].items() if k.startswith("page/garbage")]
    gchunks = sum(stopped["devices"].get(d, {}).get("chunks", 0) for d in gdev)
    gerr = sum(stopped["devices"].get(d, {}).get("framing_errors", 0) for d in gdev)
    gsmp = sum(v for k, v in stopped["counts"].items() if k.split("/")[0] in gdev)
    print(f"      (b) the garbage client's text frames reached its device {', '.join(gdev) or '-'}: {gchunks:,} messages"
          f" (hello included), {gerr:,} counted as framing errors by its codec, {gsmp} samples made of them")
    print("   refused by the service during the flood (its counters, /api/health): "
          + ", ".join(f"{k} {v:,}" for k, v in sorted(counted.items()) if v))
    print(f"   service counters at the end: {stopped['rejected']}")
    print(f"   CPU over the flood: service {win['cpu']['service'] * 100:.0f}%, flood client"
          f" {win['cpu']['flood'] * 100:.0f}%, phones {win['cpu']['phones'] * 100:.0f}% of one core;"
          f" machine {win['machine_cores']:.2f} of {os.cpu_count()} cores busy, other processes"
          f" {max(0.0, win['others_cores']):.2f}")
    # ---- memory -----------------------------------------------------------------------------------
    r = np.asarray(rss)
    before = r[r[:, 0] < t_f0, 1]
    during = r[(r[:, 0] >= t_f0) & (r[:, 0] <= t_f1)]
    after = r[r[:, 0] > t_f1, 1]
    start_mb = float(before[-1]) if before.size else float(during[0, 1])
    max_mb = float(during[:, 1].max()) if len(during) else float("nan")
    end_mb = float(during[-1, 1]) if len(during) else float("nan")
    half = t_f0 + (t_f1 - t_f0) / 2
    first = during[during[:, 0] < half, 1]
    second = during[during[:, 0] >= half, 1]
    growth2 = float(second.max() - first.max()) if first.size and second.size else float("nan")
    print(f"   in the service at the flood's end: {probe1['ws_alive']:,} WebSocketResponse and {probe1['request_handlers']:,}"
          f" RequestHandler objects alive, {probe1['timer_handles']:,} timer handles, {probe1['stats_events']:,} device"
          f" events kept by the capture's stats; {RETAIN_S:.0f} s after it: {probe2['ws_alive']:,} /"
          f" {probe2['request_handlers']:,} / {probe2['timer_handles']:,} / {probe2['stats_events']:,}, RSS"
          f" {probe2['rss_mb']:.1f} MB")
    print(f"   service RSS: {start_mb:.1f} MB at the flood's start, max {max_mb:.1f} MB, {end_mb:.1f} MB at its end,"
          f" {float(after[-1]) if after.size else float('nan'):.1f} MB {after.size * 0.25:.1f} s later;"
          f" max of the 2nd half minus max of the 1st half {growth2:+.1f} MB ({r.shape[0]} samples, every 0.25 s)")
    # ---- the phones -------------------------------------------------------------------------------
    ok_loss, lines = loss_check(res["phones"], stopped, ready["session"])
    for ln in lines:
        print(f"   {ln}")
    host, pub = service_arrays(tmp, "flood")
    lat_f, arrivals = [], {}
    for stream, h in host.items():
        if any(p["device"] == stream[:-4] for p in res["phones"]):
            sel = (h >= win["t0_ns"]) & (h <= win["t1_ns"])
            lat_f.append((pub[stream][sel] - h[sel]) / 1e6)
            pid = next(p["id"] for p in res["phones"] if p["device"] == stream[:-4])
            arrivals[pid] = np.unique(h)
    ph = np.load(os.path.join(tmp, "flood-phones.npz"))
    wire, bad = match_wire(arrivals, {k[5:]: ph[k] for k in ph.files if k.startswith("send:")},
                           (win["t0_ns"], win["t1_ns"]))
    print(f"   the phones' host-side added latency during the flood: {fmt_ms(np.concatenate(lat_f) if lat_f else np.zeros(0))}")
    print(f"   their wire latency during the flood: {fmt_ms(wire)}" + (f"; unmatched: {bad}" if bad else ""))
    up = hs == 200 and isinstance(h1, dict) and h1.get("status") == "ok"
    bounded = max_mb - start_mb < 100.0 and growth2 <= max(5.0, 0.05 * start_mb)
    check(f"flood {tot / wall:,.0f}/s for {wall:.0f} s: paired phones lose nothing", ok_loss, lines[0])
    check("flood: service RSS bounded", bounded,
          f"start {start_mb:.1f}, max {max_mb:.1f}, end {end_mb:.1f} MB (bound: max - start < 100 MB and no growth"
          f" from the 1st to the 2nd half beyond max(5 MB, 5%): {growth2:+.1f} MB)")
    check("flood: service up, /api/health answers afterwards", up,
          f"HTTP {hs}, status {h1.get('status') if isinstance(h1, dict) else h1}; wrong token -> HTTP {hs_bad}")
    n_counted = sum(counted.values()) + gerr
    check(f"flood rate reached {flood_rate:,.0f}/s (the test's own condition)", tot / wall >= 0.95 * flood_rate,
          f"{tot / wall:,.0f}/s sent; {n_counted / wall:,.0f}/s reached the service's checks and were counted"
          f" (refusals + framing errors); {udp_dropped / wall:,.0f}/s datagrams dropped by the kernel before it")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--role", help=argparse.SUPPRESS)
    ap.add_argument("--cfg", help=argparse.SUPPRESS)
    ap.add_argument("--seconds", type=float, default=20.0, help="seconds per 10-phone run (default 20)")
    ap.add_argument("--flood-seconds", type=float, default=30.0, help="flood duration (default 30)")
    ap.add_argument("--flood-rate", type=float, default=10000.0, help="flood messages per second (default 10000)")
    ap.add_argument("--only", choices=("1", "2"), help="run one part")
    ap.add_argument("--no-record", action="store_true", help="part 1 without recording (to see what the recorder costs)")
    a = ap.parse_args()
    if a.role:
        {"service": role_service, "sink": role_sink, "phones": role_phones, "flood": role_flood}[a.role](
            json.loads(a.cfg))
        return
    header("bench_serve: perfcap serve with 10 phones over TLS WebSockets, and under a flood")
    with tempfile.TemporaryDirectory(prefix="perfcap-bench-serve-") as tmp:
        if a.only in (None, "1"):
            part1(tmp, a.seconds, record=not a.no_record)
            print()
        if a.only in (None, "2"):
            part2(tmp, a.flood_seconds, a.flood_rate)
    la = os.getloadavg()
    print(f"   load average at the end: {la[0]:.2f} {la[1]:.2f} {la[2]:.2f}")
    summary()


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from _common import check, header, summary

    main()
