"""Simulated phones on the network: they talk to ``perfcap serve`` through its real endpoints.

* ``SimPagePhone``: the built-in page, as a phone browser would run it: a WebSocket over TLS to
  ``/ws/phone`` (the service's self-signed certificate pinned by fingerprint, or not checked),
  hello with the pairing token, then the page's data messages (``sim_devices.phone_sim``) at the
  page's own pace, and an answer to every ping. ``truth_ns`` maps each event's page time to the
  host clock, so a test or the demo can measure the bus-time error.
* ``post_sensorlogger`` / ``send_udp``: Sensor Logger pushes and OSC/HyperIMU datagrams.

``perfcap sim phone --url wss://HOST:PORT/ws/phone --token T`` runs a ``SimPagePhone`` from the
command line (another terminal, another machine); ``--report`` says on stdout when its page clock
started and, at the end, what it sent (``perfcap demo`` runs it so).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import signal
import socket
import sys
import threading
from typing import TYPE_CHECKING, Any

from capture.clock import MONOTONIC, Clock
from sim_devices.cli_args import SECONDS, SEED, SimParser, number
from sim_devices.motion import PHONE_MOTIONS, phone_motion
from sim_devices.phone_sim import page_hello, page_messages, page_pong

if TYPE_CHECKING:
    import argparse
    from collections.abc import Sequence

    from sim_devices.phone_sim import PageMessage

log = logging.getLogger(__name__)

#: where ``perfcap sim phone`` finds the pairing token when ``--token`` is not given
TOKEN_ENV = "PERFCAP_SIM_TOKEN"
#: seconds a simulated phone waits to connect and be welcomed before it gives up
CONNECT_TIMEOUT_S = 30.0
#: seconds a stop request (SIGTERM) waits for a clean close before the phone's run is cancelled
STOP_GRACE_S = 2.0


def _ssl_arg(fingerprint: str | None, url: str) -> Any:
    import aiohttp

    if not url.startswith(("wss:", "https:")):
        return None
    if fingerprint:
        return aiohttp.Fingerprint(bytes.fromhex(fingerprint.replace(":", "")))
    return False  # a simulator on loopback: no check (the real page's browser asks the user)


class SimPagePhone:
    """A phone running the built-in page.

    Args:
        url: ``wss://HOST:PORT/ws/phone``.
        token: the pairing token (``None``: send none, to test refusal).
        phone_id: the page's stable id.
        rate_hz: devicemotion rate.
        duration_s: how long it streams (None: until ``stop()``, in 60 s blocks of motion).
        seed: motion seed.
        fingerprint: the service's certificate SHA-256, pinned when given.
        drop_at_s: close the socket this many seconds in (a Wi-Fi drop); the page reconnects after
            ``drop_for_s`` and resends what it queued meanwhile, as the real page does.
        clock: host clock (for ``truth_ns``).
        local_addr: the source address its connections bind to, so that several simulated phones
            on one machine look like separate hosts (127.0.0.10, .11, ... on loopback); None: the
            system's choice.

    ``messages`` holds the page messages of the current run (what it sends, in order, with each
    one's page send time), once ``run()`` has started.
    """

    def __init__(self, url: str, token: str | None, phone_id: str = "sim-phone", *, rate_hz: float = 60.0,
                 duration_s: float | None = 10.0, seed: int = 1, fingerprint: str | None = None,
                 drop_at_s: float | None = None, drop_for_s: float = 0.5, batch_s: float = 0.05,
                 clock: Clock = MONOTONIC, motion: str = "waving", local_addr: str | None = None) -> None:
        phone_motion(motion)                           # an unknown motion fails here, not in the loop
        self.url = url
        self.token = token
        self.phone_id = phone_id
        self.rate_hz = rate_hz
        self.duration_s = duration_s
        self.seed = seed
        self.fingerprint = fingerprint
        self.drop_at_s = drop_at_s
        self.drop_for_s = drop_for_s
        self.batch_s = batch_s
        self.clock = clock
        self.motion = motion
        self.local_addr = local_addr
        self.messages: list[PageMessage] = []
        self.sent = 0
        self.events = 0
        self.pongs = 0
        self.device: str | None = None
        self.close_code: int | None = None
        self.close_reason = ""
        self.connects = 0
        self.t0_host_ns: int | None = None
        self.t0_ms = 1500.0
        self._stop = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self.error: BaseException | None = None

    def page_ms(self) -> float:
        assert self.t0_host_ns is not None
        return self.t0_ms + (self.clock.now_ns() - self.t0_host_ns) / 1e6

    def truth_ns(self, page_t_ms: Any) -> Any:
        """Host time at which an event with page time ``page_t_ms`` happened."""
        assert self.t0_host_ns is not None
        return self.t0_host_ns + (page_t_ms - self.t0_ms) * 1e6

    async def _connect(self, session: Any) -> Any:
        ws = await session.ws_connect(self.url, ssl=_ssl_arg(self.fingerprint, self.url), autoping=True,
                                      heartbeat=None, max_msg_size=1 << 20)
        self.connects += 1
        await ws.send_str(page_hello(self.phone_id, token=self.token, t=self.page_ms()).decode())
        msg = await ws.receive(timeout=10)
        if msg.type.name != "TEXT":
            self.close_code = ws.close_code
            self.close_reason = str(msg.extra or "")
            await ws.close()
            return None
        welcome = json.loads(msg.data)
        self.device = welcome.get("device")
        return ws

    async def _answer(self, ws: Any) -> None:
        async for msg in ws:
            if msg.type.name != "TEXT":
                break
            try:
                m = json.loads(msg.data)
            except ValueError:
                continue
            if m.get("type") == "ping":
                await ws.send_str(page_pong(int(m["h"]), self.page_ms()).decode())
                self.pongs += 1
        if ws.close_code is not None:
            self.close_code = ws.close_code

    async def run(self) -> None:
        import aiohttp

        self._loop = asyncio.get_running_loop()
        self.t0_host_ns = self.clock.now_ns()
        total = self.duration_s if self.duration_s is not None else 3600.0
        msgs = page_messages(total, self.rate_hz, batch_s=self.batch_s, seed=self.seed, t0_ms=self.t0_ms,
                             motion=self.motion)
        self.messages = msgs
        connector = None if self.local_addr is None else aiohttp.TCPConnector(local_addr=(self.local_addr, 0))
        # a service that accepts the connection but never answers must not hold the phone for minutes
        timeout = aiohttp.ClientTimeout(sock_connect=CONNECT_TIMEOUT_S, sock_read=None)
        async with aiohttp.ClientSession(connector=connector, timeout=timeout) as session:
            ws = await asyncio.wait_for(self._connect(session), CONNECT_TIMEOUT_S)
            if ws is None:
                return
            reader = asyncio.get_running_loop().create_task(self._answer(ws))
            dropped = False
            queue: list[Any] = []  # PageMessages held while the link is down
            try:
                for m in msgs:
                    wait = (m.sent_ms - self.page_ms()) / 1e3
                    if wait > 0:
                        with contextlib.suppress(asyncio.TimeoutError):
                            await asyncio.wait_for(self._stop.wait(), wait)
                    if self._stop.is_set():
                        break
                    if (self.drop_at_s is not None and not dropped
                            and m.sent_ms - self.t0_ms >= self.drop_at_s * 1e3):
                        dropped = True
                        await ws.close()
                        reader.cancel()
                        back_at = m.sent_ms + self.drop_for_s * 1e3
                        ws = None
                        queue.append(m)
                        while self.page_ms() < back_at:
                            await asyncio.sleep(0.01)
                        ws = await self._connect(session)
                        if ws is None:
                            return
                        reader = asyncio.get_running_loop().create_task(self._answer(ws))
                        continue
                    if ws.closed:
                        self.close_code = ws.close_code
                        break
                    for q in queue:  # what was queued while away, first
                        await ws.send_str(q.data.decode())
                        self.sent += 1
                        self.events += len(q.frame.motion)
                    queue.clear()
                    await ws.send_str(m.data.decode())
                    self.sent += 1
                    self.events += len(m.frame.motion)
            finally:
                if ws is not None and not ws.closed:
                    await ws.close()
                reader.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await reader
        await asyncio.sleep(0.1)  # let the TLS transport finish closing before the loop ends (aiohttp advice)

    def stop(self) -> None:
        """Ask a running phone to stop (thread-safe; harmless once it has ended)."""
        loop = self._loop
        if loop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self._stop.set)
            except RuntimeError:  # its loop closed in between: it has ended
                pass


class PhoneThread:
    """Runs a simulated phone's ``run()`` on its own event loop in a thread."""

    def __init__(self, phone: SimPagePhone) -> None:
        self.phone = phone
        self._thread = threading.Thread(target=self._main, name=f"sim-{phone.phone_id}", daemon=True)

    def _main(self) -> None:
        try:
            asyncio.run(self.phone.run())
        except BaseException as exc:  # reported by join()
            self.phone.error = exc
            log.warning("simulated phone %s stopped: %s: %s", self.phone.phone_id, type(exc).__name__, exc)

    def start(self) -> PhoneThread:
        self._thread.start()
        return self

    def join(self, timeout: float | None = None) -> bool:
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def stop(self, timeout: float = 10.0) -> None:
        if self._thread.is_alive():
            self.phone.stop()
        self._thread.join(timeout)


def post_sensorlogger(url: str, body: bytes, fingerprint: str | None = None, timeout: float = 10.0) -> tuple[int, Any]:
    """POST one Sensor Logger body (``url`` includes ``?token=``); returns (status, JSON answer)."""
    import aiohttp

    async def go() -> tuple[int, Any]:
        async with aiohttp.ClientSession() as s:
            async with s.post(url, data=body, ssl=_ssl_arg(fingerprint, url),
                              headers={"Content-Type": "application/json"},
                              timeout=aiohttp.ClientTimeout(total=timeout)) as r:
                try:
                    res = r.status, await r.json(content_type=None)
                except ValueError:
                    res = r.status, None
        await asyncio.sleep(0.1)  # let the TLS transport finish closing before the loop ends
        return res

    return asyncio.run(go())


def send_udp(host: str, port: int, datagrams: Sequence[bytes], source: str = "127.0.0.1") -> int:
    """Send datagrams from ``source``; returns how many were sent."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((source, 0))
        for d in datagrams:
            s.sendto(d, (host, port))
    return len(datagrams)


def build_parser() -> argparse.ArgumentParser:
    """The flags of ``perfcap sim phone``."""
    p = SimParser(prog="perfcap sim phone",
                                description="a simulated phone running perfcap's page, streaming to perfcap serve")
    p.add_argument("--url", required=True, help="wss://HOST:PORT/ws/phone (as printed by perfcap serve)")
    p.add_argument("--token", help=f"the pairing token printed by perfcap serve (default: ${TOKEN_ENV})")
    p.add_argument("--fingerprint", help="the certificate fingerprint printed by perfcap serve (pinned)")
    p.add_argument("--id", default="sim-phone", help="the phone's id")
    p.add_argument("--rate", type=number(0, 1000, above=True), default=60.0, help="devicemotion rate, Hz")
    p.add_argument("--duration", type=SECONDS, default=30.0, help="seconds")
    p.add_argument("--seed", type=SEED, default=1)
    p.add_argument("--motion", choices=PHONE_MOTIONS, default="waving",
                   help="waving: seeded free waving; puppeteer: a choreography for perfcap puppet (walk, run, "
                        "hop, crouch)")
    p.add_argument("--report", action="store_true",
                   help="JSON lines on stdout: once paired, when the page clock started (t0_host_ns on the host's"
                        " monotonic clock, t0_ms on the page's), then at the end what was sent; SIGTERM stops it"
                        " cleanly")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    p = build_parser()
    a = p.parse_args(argv)
    token = a.token if a.token is not None else os.environ.get(TOKEN_ENV)
    if not token:
        p.error(f"the pairing token: give --token or set {TOKEN_ENV}")
    phone = SimPagePhone(a.url, token, a.id, rate_hz=a.rate, duration_s=a.duration, seed=a.seed,
                         fingerprint=a.fingerprint, motion=a.motion)

    async def go() -> None:
        loop = asyncio.get_running_loop()
        task = loop.create_task(phone.run())

        def stop() -> None:  # a clean close if it can, cancelled if it is stuck (connecting, say)
            phone.stop()
            loop.call_later(STOP_GRACE_S, task.cancel)

        for sig in (signal.SIGTERM, signal.SIGINT):
            with contextlib.suppress(NotImplementedError, RuntimeError):   # (no signal handlers on Windows)
                loop.add_signal_handler(sig, stop)
        if a.report:   # once paired, so whoever waits for this line knows the phone is streaming
            while (phone.t0_host_ns is None or phone.device is None) and not task.done():
                await asyncio.sleep(0.001)
            if phone.device is not None:
                print(json.dumps({"t0_host_ns": phone.t0_host_ns, "t0_ms": phone.t0_ms, "device": phone.device}),
                      flush=True)
        with contextlib.suppress(asyncio.CancelledError):
            await task

    try:
        asyncio.run(go())
    except KeyboardInterrupt:
        return 130
    except Exception as exc:  # one line for the user
        print(f"perfcap sim phone: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    if phone.device is None and not phone.close_code:
        print(f"perfcap sim phone: not paired with {a.url} (no welcome within {CONNECT_TIMEOUT_S:g} s, or stopped)",
              file=sys.stderr)
        return 1
    if phone.close_code and phone.device is None:
        print(f"perfcap sim phone: refused ({phone.close_code}): {phone.close_reason}", file=sys.stderr)
        return 1
    if a.report:
        print(json.dumps({"sent": phone.sent, "events": phone.events, "device": phone.device}), flush=True)
    print(f"sent {phone.sent} messages ({phone.events} motion events) as device {phone.device}", file=sys.stderr)
    return 0
