"""The parties of ``bench_serve.py``, each in its own process, started by ``_serve_common.Child`` as
``python benchmarks/_serve_roles.py --role ROLE --cfg JSON`` (not a benchmark itself, nor run by hand):

* ``service``: the real ``Service`` (capture.app.serve) on 127.0.0.1 with TLS, default limits, no mDNS,
  recording every message as ``perfcap serve --record`` does, with a latency probe on its bus;
* ``sink``: the baseline, a bare aiohttp TLS WebSocket server (same certificate and socket settings)
  that only stamps each message;
* ``phones``: ``SimPagePhone`` tasks on one event loop, each from its own loopback source address;
* ``flood``: malformed and unauthenticated input at a set rate, in four categories (part 2).

Each tells the benchmark what happens in JSON lines on stdout (``ready``, ``streaming``, ``done``,
``stopped``...), takes commands on stdin (the service: ``probe``, ``stop``) and saves its arrays to the
``.npz`` file its configuration names.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import sys
import time
from typing import TYPE_CHECKING, Any

import numpy as np
from _serve_common import DATA_PREFIX, OSC_ALLOW, TOKEN, jprint, proc_rss_mb

if TYPE_CHECKING:
    from collections.abc import Callable


# ================================================================================================
# role: service (the real Service, with a latency probe on its bus)
# ================================================================================================
def role_service(cfg: dict[str, Any]) -> None:
    import logging

    sys.setswitchinterval(cfg.get("switchinterval", 0.0005))  # as the perfcap CLI does for serve
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from capture.app.serve.config import ServeConfig
    from capture.app.serve.service import Service, ServiceThread
    from capture.bus import Overflow, Subscriber
    from capture.sample import Sample, SampleBatch

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

    sub.offer = offer
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
                    "stats_events": len(svc.capture.stats.events), "rss_mb": proc_rss_mb(os.getpid())})
    before = {"health": svc.health()}
    rep = st.stop()
    boxes = {k: {"received": b.received, "dropped": b.dropped, "connects": b.connects, "dropped_bytes": b.dropped_bytes}
             for k, b in svc.phones.hub.inboxes().items()}
    arrays: dict[str, np.ndarray] = {}
    for name, r in rows.items():
        a = np.asarray(r, np.int64).reshape(-1, 2)
        arrays[f"host:{name}"] = a[:, 0]
        arrays[f"pub:{name}"] = a[:, 1]
    np.savez(cfg["out"], allow_pickle=False, **arrays)
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
        port = runner.addresses[0][1]
        jprint({"event": "ready", "pid": os.getpid(), "page_url": f"https://127.0.0.1:{port}/",
                "fingerprint": cert.fingerprint})
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(None, sys.stdin.readline)
        await runner.cleanup()

    asyncio.run(main())
    np.savez(cfg["out"], allow_pickle=False, **{f"arr:{k}": np.asarray(v, np.int64) for k, v in arrivals.items()})
    jprint({"event": "stopped", "messages": {k: len(v) for k, v in arrivals.items()}})


# ================================================================================================
# role: phones (SimPagePhone tasks on one loop, each from its own loopback address)
# ================================================================================================
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

    class TimedPhone(SimPagePhone):
        def __init__(self, *a: Any, **k: Any) -> None:
            super().__init__(*a, **k)
            self.send_ns: list[int] = []

        async def _connect(self, session: Any) -> Any:
            ws = await super()._connect(session)
            return None if ws is None else _TimedWS(ws, self.send_ns)

    url = cfg["page_url"].replace("https://", "wss://") + "ws/phone"
    # each phone from its own loopback address: phones are separate hosts
    phones = [TimedPhone(url, cfg["token"], f"bench{k:02d}", rate_hz=cfg["rate"], duration_s=cfg["duration"],
                         seed=k + 1, fingerprint=cfg["fingerprint"], batch_s=cfg["batch_s"],
                         local_addr=f"127.0.0.{cfg['src'] + k}")
              for k in range(cfg["n"])]
    if cfg.get("t0_ms") is not None:
        for p in phones:
            p.t0_ms = cfg["t0_ms"]

    async def main() -> None:
        tasks = [asyncio.create_task(p.run()) for p in phones]
        t_end = time.monotonic() + 15.0
        while not all(p.device for p in phones) and time.monotonic() < t_end and not all(t.done() for t in tasks):
            await asyncio.sleep(0.01)
        jprint({"event": "streaming", "t_ns": time.monotonic_ns(), "connected": sum(1 for p in phones if p.device)})
        res = await asyncio.gather(*tasks, return_exceptions=True)
        for p, r in zip(phones, res, strict=True):
            if isinstance(r, BaseException) and p.error is None:
                p.error = r

    c0, w0 = time.process_time(), time.monotonic()
    asyncio.run(main())
    cpu = (time.process_time() - c0) / (time.monotonic() - w0)
    arrays: dict[str, np.ndarray] = {}
    out = []
    for p in phones:
        arrays[f"send:{p.phone_id}"] = np.asarray(p.send_ns, np.int64)
        msgs = p.messages[:len(p.send_ns)]
        sched = p.truth_ns(np.asarray([m.sent_ms for m in msgs], float)) if msgs else np.zeros(0)
        arrays[f"sched:{p.phone_id}"] = np.asarray(sched, np.int64)
        out.append({"id": p.phone_id, "device": p.device, "sent": p.sent, "events": p.events, "pongs": p.pongs,
                    "connects": p.connects, "close_code": p.close_code, "error": None if p.error is None
                    else f"{type(p.error).__name__}: {p.error}"})
    np.savez(cfg["out"], allow_pickle=False, **arrays)
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
    sent = dict.fromkeys(("a_ws_bad_token", "b_ws_garbage", "c_post_no_token", "d_udp_not_allowed"), 0)
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
                                status = code[9:].decode()
                                extra["c_status"][status] = extra["c_status"].get(status, 0) + c
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


ROLES: dict[str, Callable[[dict[str, Any]], None]] = {
    "service": role_service, "sink": role_sink, "phones": role_phones, "flood": role_flood}


def main() -> None:
    ap = argparse.ArgumentParser(description="one party of benchmarks/bench_serve.py, which starts it")
    ap.add_argument("--role", choices=sorted(ROLES), required=True)
    ap.add_argument("--cfg", required=True, help="the role's configuration, as JSON")
    a = ap.parse_args()
    ROLES[a.role](json.loads(a.cfg))


if __name__ == "__main__":
    main()
