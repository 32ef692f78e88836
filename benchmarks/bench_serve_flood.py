"""``perfcap serve`` against clients that try to make it hold too much: what each flood costs it.

    .venv/bin/python benchmarks/bench_serve_flood.py [--seconds 20] [--only big,reconnect,ids,idle]

One service per flood (a ``Service`` with the default settings, TLS, recording, in its own process:
the ``service`` role of ``_serve_roles.py``), one legitimate phone streaming 100 Hz in 50 ms batches
from 127.0.0.10 throughout (the ``phones`` role), and the flood from this process, for ``--seconds``:

* ``big``: one paired address (127.0.0.4) with 4 WebSockets (its limit), each sending messages of
  just under the 64 KiB maximum as fast as it can and reconnecting at once when closed;
* ``reconnect``: one address (127.0.0.5), 4 loops of connect, hello, small messages as fast as
  possible until closed, reconnect at once: two with the same id each time, two with a new id;
* ``ids``: one address (127.0.0.6), 4 loops each pairing a new phone id, sending 5 messages and
  leaving, as fast as it goes (the slots of phones that left must go to new ones);
* ``idle``: thousands of TCP connections from 250 addresses (127.0.1.x) that never start TLS
  (half-open handshakes), and TLS connections that never send a request, each reopened as soon as the
  service closes or refuses it.

Printed per flood: the service's RSS (sampled every 0.1 s: before, peak, at the end, 5 s later),
what the flood achieved against the limits (messages accepted per second per phone id and per
address against ``--max-rate`` and its per-address multiple, ids admitted and slots held, connections
held against ``max_sockets``, refusals by reason), and what the legitimate phone lost (every motion
event it sent must be a sample on the bus and in the recording, on one connection). Target: RSS under
300 MB in every flood and the phone loses nothing. Measurement script: PASS/FAIL per target, exits 0.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import ssl
import tempfile
import threading
import time
from typing import Any

import aiohttp
from _common import check, header, summary
from _serve_common import PHONE_SRC, TOKEN, Child, http_json, loss_check, proc_rss_mb

from sim_devices.phone_sim import page_hello

RSS_TARGET_MB = 300.0
DEFAULT_RATE, DEFAULT_BURST, PER_HOST = 200.0, 400.0, 4   # the default settings' limits


class Tally:
    def __init__(self) -> None:
        self.sent = 0
        self.connects = 0
        self.welcomed = 0
        self.codes: dict[str, int] = {}
        self.ids: set[str] = set()

    def code(self, c: Any) -> None:
        k = str(c)
        self.codes[k] = self.codes.get(k, 0) + 1


def _insecure() -> ssl.SSLContext:
    ctx = ssl.create_default_context()
    ctx.check_hostname = False
    ctx.verify_mode = ssl.CERT_NONE
    return ctx


async def _session(ws_url: str, src: str, pid: str, text: str, n: int | None, tally: Tally,
                   sess: aiohttp.ClientSession) -> None:
    """One connection: hello as ``pid``, then ``n`` (None: unlimited) messages, until closed."""
    tally.connects += 1
    tally.ids.add(pid)
    try:
        ws = await sess.ws_connect(ws_url, ssl=False, autoping=True, heartbeat=None, max_msg_size=0)
    except (aiohttp.ClientError, OSError) as exc:
        tally.code(f"connect: {type(exc).__name__}")
        await asyncio.sleep(0.01)
        return
    try:
        await ws.send_str(page_hello(pid, token=TOKEN).decode())
        first = await ws.receive(timeout=10)
        if first.type is not aiohttp.WSMsgType.TEXT:
            tally.code(ws.close_code)
            return
        tally.welcomed += 1
        closed = asyncio.Event()

        async def read() -> None:  # pings, then the service's close frame
            with contextlib.suppress(Exception):
                while True:
                    m = await ws.receive()
                    if m.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.ERROR):
                        break
            closed.set()

        reader = asyncio.get_running_loop().create_task(read())
        i = 0
        while (n is None or i < n) and not closed.is_set() and not ws.closed:
            await ws.send_str(text)
            tally.sent += 1
            i += 1
            if i % 4 == 0:
                await asyncio.sleep(0)  # let the close frame in
        if n is not None and not closed.is_set():
            await ws.close()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(reader, 10)
        tally.code(ws.close_code)
    except (aiohttp.ClientError, OSError, ConnectionError, RuntimeError, TimeoutError) as exc:
        tally.code(ws.close_code or type(exc).__name__)
    finally:
        with contextlib.suppress(Exception):
            await ws.close()


async def flood_ws(kind: str, ws_url: str, seconds: float) -> Tally:
    tally = Tally()
    t_end = time.monotonic() + seconds
    big = json.dumps({"type": "data", "seq": 0, "m": [], "pad": "x" * (64 * 1024 - 200)})
    small = json.dumps({"type": "data", "seq": 0, "m": []})
    src = {"big": "127.0.0.4", "reconnect": "127.0.0.5", "ids": "127.0.0.6"}[kind]

    async def loop_(j: int) -> None:
        k = 0
        async with aiohttp.ClientSession(connector=aiohttp.TCPConnector(local_addr=(src, 0), ssl=False)) as sess:
            while time.monotonic() < t_end:
                k += 1
                if kind == "big":
                    await _session(ws_url, src, f"big-{j}", big, None, tally, sess)
                elif kind == "reconnect":
                    pid = f"rc-same-{j}" if j < 2 else f"rc-new-{j}-{k}"
                    await _session(ws_url, src, pid, small, None, tally, sess)
                else:
                    await _session(ws_url, src, f"id-{j}-{k}", small, 5, tally, sess)

    await asyncio.gather(*(loop_(j) for j in range(4)))
    return tally


async def flood_idle(port: int, seconds: float, raw_n: int = 3000, tls_n: int = 500) -> dict[str, Any]:
    """Half-open handshakes (TCP only) and TLS connections that never send a request, each reopened when
    closed, from 250 addresses."""
    t_end = time.monotonic() + seconds
    out = {"opened": 0, "closed_by_service": 0, "connect_failed": 0, "tls_failed": 0}
    ctx = _insecure()

    async def one(i: int, tls: bool) -> None:
        src = f"127.0.1.{1 + i % 250}"
        while time.monotonic() < t_end:
            try:
                r, w = await asyncio.wait_for(asyncio.open_connection(
                    "127.0.0.1", port, local_addr=(src, 0), ssl=ctx if tls else None,
                    server_hostname="perfcap" if tls else None), 15)
            except (OSError, TimeoutError, ssl.SSLError):
                out["tls_failed" if tls else "connect_failed"] += 1
                await asyncio.sleep(0.2)
                continue
            out["opened"] += 1
            try:
                left = t_end - time.monotonic()
                if left <= 0:
                    break
                data = await asyncio.wait_for(r.read(1), left)
                if not data:
                    out["closed_by_service"] += 1
            except (TimeoutError, OSError, ssl.SSLError):
                pass
            finally:
                w.close()
                with contextlib.suppress(Exception):
                    await asyncio.wait_for(w.wait_closed(), 2)

    await asyncio.gather(*(one(i, False) for i in range(raw_n)), *(one(i, True) for i in range(tls_n)))
    return out


def run_flood(tmp: str, kind: str, seconds: float) -> None:
    svc = Child("service", {"state_dir": os.path.join(tmp, f"{kind}-state"), "out": os.path.join(tmp, f"{kind}.npz")},
                os.path.join(tmp, f"{kind}-service.log"))
    rss: list[tuple[float, float]] = []
    stop_rss = threading.Event()
    try:
        ready = svc.wait_ready(30)

        def sample() -> None:
            while not stop_rss.is_set():
                try:
                    rss.append((time.monotonic(), proc_rss_mb(svc.pid)))
                except OSError:
                    return
                stop_rss.wait(0.1)

        threading.Thread(target=sample, daemon=True).start()
        lead, tail = 2.0, 6.0
        duration = lead + seconds + tail
        ph = Child("phones", {"page_url": ready["page_url"], "token": TOKEN, "fingerprint": ready["fingerprint"],
                              "n": 1, "rate": 100.0, "batch_s": 0.05, "duration": duration, "t0_ms": None,
                              "src": PHONE_SRC, "out": os.path.join(tmp, f"{kind}-phone.npz")},
                   os.path.join(tmp, f"{kind}-phone.log"))
        try:
            ph.expect("streaming", 30)
            time.sleep(lead)
            t0 = time.monotonic()
            ws_url = ready["page_url"].replace("https://", "wss://") + "ws/phone"
            port = int(ready["page_url"].rsplit(":", 1)[1].strip("/"))
            if kind == "idle":
                res: Any = asyncio.run(flood_idle(port, seconds))
            else:
                res = asyncio.run(flood_ws(kind, ws_url, seconds))
            t1 = time.monotonic()
            _, h_end = http_json(ready["control_url"] + "/health", TOKEN)
            time.sleep(5.0)
            _, h_after = http_json(ready["control_url"] + "/health", TOKEN)
            phone = ph.expect("done", duration + 60)
        finally:
            ph.close()
        stop_rss.set()
        svc.send("stop")
        stopped = svc.expect("stopped", 60)
    finally:
        stop_rss.set()
        svc.close()
    report(kind, seconds, res, rss, t0, t1, h_end, h_after, phone, stopped, ready)


def report(kind: str, seconds: float, res: Any, rss: list[tuple[float, float]], t0: float, t1: float,
           h_end: Any, h_after: Any, phone: dict[str, Any], stopped: dict[str, Any], ready: dict[str, Any]) -> None:
    before = [m for t, m in rss if t < t0]
    during = [m for t, m in rss if t0 <= t <= t1]
    after = [m for t, m in rss if t > t1]
    start = before[-1] if before else float("nan")
    peak = max(during) if during else float("nan")
    end = during[-1] if during else float("nan")
    later = after[-1] if after else float("nan")
    wall = t1 - t0
    print(f"   service RSS: {start:.1f} MB before, peak {peak:.1f} MB during, {end:.1f} MB at the end,"
          f" {later:.1f} MB {len(after) * 0.1:.0f} s later")
    rej = (h_end or {}).get("rejected", {}) if isinstance(h_end, dict) else {}
    conns = (h_end or {}).get("connections", {}) if isinstance(h_end, dict) else {}
    conns2 = (h_after or {}).get("connections", {}) if isinstance(h_after, dict) else {}
    slots = (h_end or {}).get("phone_slots", {}) if isinstance(h_end, dict) else {}
    boxes = stopped["boxes"]
    if kind == "idle":
        print(f"   flood: {res['opened']:,} connections opened ({res['opened'] / wall:,.0f}/s),"
              f" {res['closed_by_service']:,} closed by the service, {res['connect_failed']:,} TCP and"
              f" {res['tls_failed']:,} TLS attempts failed")
    else:
        t: Tally = res
        print(f"   flood: {t.connects:,} connections ({t.connects / wall:,.0f}/s), {t.welcomed:,} welcomed,"
              f" {len(t.ids):,} ids, {t.sent:,} messages sent ({t.sent / wall:,.0f}/s); close codes {t.codes}")
        prefix = {"big": "page/big-", "reconnect": "page/rc-", "ids": "page/id-"}[kind]
        mine = {k: v for k, v in boxes.items() if k.startswith(prefix)}
        acc = {k: v["received"] - v["connects"] for k, v in mine.items()}   # minus the hellos
        tot = sum(acc.values())
        top = max(acc.values(), default=0)
        print(f"   accepted by the service: {tot:,} messages = {tot / wall:,.0f}/s from the address (limit"
              f" {DEFAULT_RATE * PER_HOST:,.0f}/s + burst {DEFAULT_BURST * PER_HOST:,.0f}); busiest id {top:,} ="
              f" {top / wall:,.0f}/s (limit {DEFAULT_RATE:,.0f}/s + burst {DEFAULT_BURST:,.0f}); inboxes refused"
              f" {sum(v['dropped'] for v in mine.values()):,} messages"
              f" ({sum(v.get('dropped_bytes', 0) for v in mine.values()) / 1e6:.1f} MB)")
        bound_host = DEFAULT_RATE * PER_HOST * wall + DEFAULT_BURST * PER_HOST
        check(f"{kind}: accepted rate within the limits", tot <= bound_host
              and top <= DEFAULT_RATE * wall + DEFAULT_BURST, f"{tot / wall:,.0f}/s per address, {top / wall:,.0f}/s"
              " busiest id")
    print(f"   phone slots: {slots}")
    print(f"   connections (the gate): at the flood's end {conns}; 5 s later open {conns2.get('open')},"
          f" handshakes {conns2.get('handshakes')}")
    print("   refused by reason: " + ", ".join(f"{k} {v:,}" for k, v in sorted(rej.items())))
    ok_loss, lines = loss_check(phone["phones"], stopped, ready["session"])
    for ln in lines:
        print(f"   {ln}")
    check(f"{kind}: service RSS < {RSS_TARGET_MB:.0f} MB", peak < RSS_TARGET_MB, f"peak {peak:.1f} MB")
    check(f"{kind}: the legitimate phone loses nothing", ok_loss, lines[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="seconds per flood (default 20)")
    ap.add_argument("--only", default="big,reconnect,ids,idle", help="floods to run, comma-separated")
    a = ap.parse_args()
    header("bench_serve_flood: perfcap serve against floods that try to make it hold too much")
    with tempfile.TemporaryDirectory(prefix="perfcap-bench-flood-") as tmp:
        for kind in [k.strip() for k in a.only.split(",") if k.strip()]:
            print(f"-- {kind} ({a.seconds:.0f} s)")
            run_flood(tmp, kind, a.seconds)
            print()
    summary()


if __name__ == "__main__":
    main()
