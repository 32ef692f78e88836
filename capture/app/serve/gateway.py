"""The phone-facing side of ``perfcap serve``: every network endpoint a phone talks to.

* ``GET /`` the built-in phone page; ``GET /ws/phone`` its WebSocket (token in the first message);
  ``POST /ingest/sensorlogger?token=...`` Sensor Logger's HTTP push. One aiohttp application, served
  over HTTPS (browsers give motion sensors only to secure pages).
* OSC (ZIG SIM, GyrOSC-style apps) and HyperIMU CSV over UDP, HyperIMU over TCP. These protocols
  cannot carry a token, so they are off unless enabled, and then take only allow-listed sources.

The gateway authenticates, bounds (message size, message rate, connections per host and in total)
and stamps each message with its arrival time, then hands it as one ``Chunk`` to the phone's inbox
(``devices.transports.network``); decoding happens in the phone's device reader, like any device.
Refused input is counted by reason (``Rejections``) and never reaches a device. A ``PhoneRegistry``
(the service) decides which device a phone is and creates it the first time it is seen.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import re
from dataclasses import dataclass, field
from importlib import resources
from typing import TYPE_CHECKING, Any, Protocol

from aiohttp import WSCloseCode, WSMsgType, web

from capture.app.serve.config import Limits
from capture.app.serve.connections import ConnectionGate, GatedSite
from capture.app.serve.security import AllowList, RateBook, Rejections, TokenStore
from capture.clock import MONOTONIC, Clock
from capture.sample import Chunk, Direction

if TYPE_CHECKING:
    import ssl

    from devices.transports.network import Inbox

log = logging.getLogger(__name__)

#: WebSocket close codes the page understands (see capture/app/serve/static/phone.html). An oversized
#: message is closed by aiohttp itself with the standard 1009 (message too big).
CLOSE_MALFORMED = 4400
CLOSE_TOKEN = 4401
CLOSE_TOO_MANY = 4409
CLOSE_REPLACED = 4408   # the same phone id connected again: the older socket stops (no retry)
CLOSE_SHUTDOWN = 4410
CLOSE_TOO_LARGE = 1009
CLOSE_RATE = 4429

_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._\-]{0,63}$")


class PhoneRegistry(Protocol):
    def admit(self, protocol: str, remote_id: str, peer: str, info: dict[str, Any]) -> tuple[str, Inbox] | None:
        """The (device name, connected inbox) for this phone, creating its device the first time;
        None when no more phones are allowed."""


@dataclass
class GatewayStats:
    connections: int = 0
    accepted: int = 0
    messages: int = 0
    by_protocol: dict[str, int] = field(default_factory=dict)


def page_html() -> bytes:
    return resources.files("capture.app.serve").joinpath("static/phone.html").read_bytes()


class Gateway:
    """The phone endpoints. ``app()`` is the HTTPS application; ``start_udp``/``start_tcp`` open the
    token-less protocols.

    Args:
        registry: maps phones to devices.
        tokens: the pairing token.
        limits: per-client bounds.
        clock: stamps arrivals.
    """

    def __init__(self, registry: PhoneRegistry, tokens: TokenStore, limits: Limits | None = None,
                 clock: Clock = MONOTONIC) -> None:
        self.registry = registry
        self.tokens = tokens
        self.limits = limits or Limits()
        self.clock = clock
        self.rejected = Rejections()
        self.stats = GatewayStats()
        self._sockets: dict[str, tuple[web.WebSocketResponse, int]] = {}  # page id -> (ws, token generation)
        self._per_host: dict[str, int] = {}
        self._open = 0
        self._pending = 0
        self._pending_host: dict[str, int] = {}
        self._tcp_current: dict[tuple[str, str], object] = {}
        self._servers: list[Any] = []
        self._transports: list[Any] = []
        self._closing = False
        self._page = page_html()
        lim = self.limits
        # message rates by phone (PROTOCOL/ID) and by source address, kept across reconnects; an address
        # may carry as many phones as it may hold connections
        self.rates = RateBook(lim.rate_hz, lim.burst)
        k = lim.max_connections_per_host
        self.host_rates = RateBook(lim.rate_hz * k, lim.burst * k)
        burst = max(lim.byte_burst, lim.max_message_bytes, lim.max_push_bytes)  # any one message fits
        self.byte_rates = RateBook(lim.byte_rate, burst)
        self.host_byte_rates = RateBook(lim.byte_rate * k, burst * k)
        self.gate: ConnectionGate | None = None
        self._tcp_open: dict[str, int] = {}

    def _allow(self, key: str, host: str, t: int, nbytes: int = 0) -> bool:
        """One message of ``nbytes`` from phone ``key`` at address ``host``: within their message and byte
        rates? (A refused message costs nothing.)"""
        if not (self.rates.allow(key, t) and self.host_rates.allow(host, t)):
            return False
        if nbytes:
            if not self.byte_rates.allow(key, t, nbytes):
                return False
            if not self.host_byte_rates.allow(host, t, nbytes):
                return False
        return True

    def _over_budget(self, inbox: Inbox, host: str, what: str) -> None:
        self.rejected.count("inbox byte budget exceeded", host,
                            f"{what}: {inbox.queued_bytes} bytes waiting to be decoded, budget {inbox.max_bytes}")

    def site(self, runner: web.BaseRunner, host: str, port: int, ssl_context: ssl.SSLContext | None) -> GatedSite:
        """The phone port's site: its connections pass the gate (caps, TLS, handshake timeout)."""
        factory = runner.server
        assert factory is not None, "runner.setup() first"
        self.gate = ConnectionGate(self.limits, self.rejected, ssl_context, factory)
        return GatedSite(runner, host, port, self.gate)

    @web.middleware
    async def _arrived(self, request: web.Request, handler: Any) -> web.StreamResponse:
        if self.gate is not None:
            self.gate.established(request.transport)  # a request came: the handshake is over
        resp: web.StreamResponse = await handler(request)
        return resp

    # -- HTTPS application -----------------------------------------------------------------------
    def app(self) -> web.Application:
        app = web.Application(client_max_size=max(self.limits.max_message_bytes, self.limits.max_push_bytes),
                              middlewares=[self._arrived])
        app.router.add_get("/", self._page_handler)
        app.router.add_get("/phone", self._page_handler)
        app.router.add_get("/ws/phone", self._ws_phone)
        app.router.add_post("/ingest/sensorlogger", self._sensorlogger)
        return app

    async def _page_handler(self, request: web.Request) -> web.Response:
        return web.Response(body=self._page, content_type="text/html", charset="utf-8",
                            headers={"Cache-Control": "no-store", "Referrer-Policy": "no-referrer",
                                     "X-Content-Type-Options": "nosniff"})

    def _host_of(self, request: web.Request) -> str:
        return request.remote or "?"

    async def _ws_phone(self, request: web.Request) -> web.StreamResponse:
        host = self._host_of(request)
        lim = self.limits
        if self._closing:
            return web.Response(status=503, text="perfcap serve is shutting down\n")
        # Connections still waiting for their hello have their own, separate bound (and a short
        # timeout), so strangers who never send a token cannot use up the phones' connections.
        if self._pending >= lim.max_pending_hello or self._pending_host.get(host, 0) >= lim.max_connections_per_host:
            self.rejected.count("too many connections", host, "waiting for hello")
            return web.Response(status=503, text="too many connections\n")
        # No aiohttp heartbeat: it re-arms on the close frame of a refused client and keeps the dead
        # socket ~30 s (a flood of refused connections then grows memory). The gateway's own pings
        # and the receive timeout in _pump find dead peers instead.
        ws = web.WebSocketResponse(max_msg_size=lim.max_message_bytes, heartbeat=None, autoping=True,
                                   compress=False, receive_timeout=None)
        await ws.prepare(request)
        self.stats.connections += 1
        inbox: Inbox | None = None
        phone_id = ""
        ping_task: asyncio.Task[Any] | None = None
        counted = False
        self._pending += 1
        self._pending_host[host] = self._pending_host.get(host, 0) + 1
        try:
            try:
                hello = await self._hello(ws, host)
            finally:
                self._pending -= 1
                _dec(self._pending_host, host)
            if hello is None:
                return ws
            if self._open >= lim.max_connections or self._per_host.get(host, 0) >= lim.max_connections_per_host:
                self.rejected.count("too many connections", host)
                await ws.close(code=CLOSE_TOO_MANY, message=b"too many connections")
                return ws
            self._open += 1
            self._per_host[host] = self._per_host.get(host, 0) + 1
            counted = True
            phone_id, info = hello
            admitted = self.registry.admit("page", phone_id, host, info)
            if admitted is None:
                self.rejected.count("phone not admitted", host, "too many phones, or its device cannot be made")
                await ws.close(code=CLOSE_TOO_MANY, message=b"this service takes no more phones")
                return ws
            name, inbox = admitted
            old = self._sockets.get(phone_id)
            self._sockets[phone_id] = (ws, self.tokens.generation)
            if old is not None and not old[0].closed:
                await old[0].close(code=CLOSE_REPLACED, message=b"this phone connected again (another tab?)")
            t = self.clock.now_ns()
            inbox.put(Chunk(json.dumps(info, separators=(",", ":")).encode(), t, Direction.RX))
            await ws.send_str(json.dumps({"type": "welcome", "device": name, "ping_s": lim.ping_s}))
            self.stats.accepted += 1
            ping_task = asyncio.get_running_loop().create_task(self._pinger(ws))
            await self._pump(ws, inbox, host, f"page/{phone_id}")
        finally:
            if ping_task is not None:
                ping_task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await ping_task
            if counted:
                self._open -= 1
                _dec(self._per_host, host)
            if phone_id and self._sockets.get(phone_id, (None,))[0] is ws:
                del self._sockets[phone_id]
                if inbox is not None:
                    inbox.disconnect("the phone page closed its connection")
        return ws

    async def _hello(self, ws: web.WebSocketResponse, host: str) -> tuple[str, dict[str, Any]] | None:
        try:
            msg = await ws.receive(timeout=self.limits.hello_timeout_s)
        except TimeoutError:
            self.rejected.count("no hello", host)
            await ws.close(code=CLOSE_TOKEN, message=b"no hello with a pairing token")
            return None
        if msg.type is WSMsgType.ERROR or msg.type is WSMsgType.CLOSE or msg.type is WSMsgType.CLOSED:
            if msg.type is WSMsgType.ERROR:
                self.rejected.count("oversized or broken message", host, str(msg.data))
            return None
        if msg.type is not WSMsgType.TEXT:
            self.rejected.count("malformed hello", host, "not text")
            await ws.close(code=CLOSE_MALFORMED, message=b"the first message must be a JSON hello")
            return None
        try:
            hello = json.loads(msg.data)
        except (ValueError, RecursionError):  # RecursionError: "[[[[..." nested beyond the parser
            hello = None
        if not isinstance(hello, dict) or hello.get("type") != "hello":
            self.rejected.count("malformed hello", host)
            await ws.close(code=CLOSE_MALFORMED, message=b"the first message must be a JSON hello")
            return None
        if not self.tokens.check(hello.get("token")):
            self.rejected.count("missing or wrong token", host)
            await ws.close(code=CLOSE_TOKEN, message=b"missing or wrong pairing token")
            return None
        pid = hello.get("id")
        if not isinstance(pid, str) or not _ID_RE.match(pid):
            self.rejected.count("malformed hello", host, "bad id")
            await ws.close(code=CLOSE_MALFORMED, message=b"hello.id must be 1-64 letters, digits, '.', '_' or '-'")
            return None
        if not self._allow(f"page/{pid}", host, self.clock.now_ns()):  # reconnecting costs a message too
            self.rejected.count("message rate exceeded", host, "at hello")
            await ws.close(code=CLOSE_RATE, message=b"message rate exceeded")
            return None
        info = {k: v for k, v in hello.items() if k != "token"}  # a session never holds the token
        info["peer"] = host
        return pid, info

    async def _pinger(self, ws: web.WebSocketResponse) -> None:
        while not ws.closed:
            await asyncio.sleep(self.limits.ping_s)
            with contextlib.suppress(ConnectionError, RuntimeError):
                await ws.send_str(f'{{"type":"ping","h":{self.clock.now_ns()}}}')

    async def _pump(self, ws: web.WebSocketResponse, inbox: Inbox, host: str, key: str) -> None:
        lim = self.limits
        clock = self.clock
        gen = self.tokens.generation
        allow = self._allow
        malformed = 0
        put = inbox.put
        stats = self.stats
        idle_s = max(10.0 * lim.ping_s, 10.0)  # the page answers a ping every ping_s: silence = dead link
        while True:
            try:
                msg = await ws.receive(timeout=idle_s)
            except TimeoutError:
                self.rejected.count("silent connection", host, f"nothing for {idle_s:g} s")
                await ws.close(code=WSCloseCode.GOING_AWAY, message=b"no messages; is the phone still there?")
                break
            if msg.type in (WSMsgType.CLOSE, WSMsgType.CLOSING, WSMsgType.CLOSED):
                break
            t = clock.now_ns()
            if msg.type is WSMsgType.TEXT:
                if not allow(key, host, t, len(msg.data)):
                    self.rejected.count("message rate exceeded", host)
                    await ws.close(code=CLOSE_RATE, message=b"message rate exceeded")
                    break
                if self.tokens.generation != gen:
                    await ws.close(code=CLOSE_TOKEN, message=b"the pairing token was rotated; pair again")
                    break
                if not put(Chunk(msg.data.encode(), t, Direction.RX)):
                    # the phone sends more than its device decodes: refused (counted) and closed with the
                    # rate code, so the page retries later and the socket's buffers go too
                    self._over_budget(inbox, host, key)
                    await ws.close(code=CLOSE_RATE, message=b"sending faster than the service decodes")
                    break
                stats.messages += 1
            elif msg.type is WSMsgType.BINARY:
                malformed += 1
                self.rejected.count("binary message", host)
                if malformed > lim.max_malformed:
                    await ws.close(code=CLOSE_MALFORMED, message=b"too many malformed messages")
                    break
            elif msg.type is WSMsgType.ERROR:
                err = msg.data
                if getattr(err, "code", None) == WSCloseCode.MESSAGE_TOO_BIG:
                    # aiohttp has already closed the socket with 1009 (message too big)
                    self.rejected.count("message too large", host, str(err))
                else:
                    self.rejected.count("broken message", host, str(err))
                break

    async def close_phones(self, code: int, reason: str) -> None:
        """Close every page socket (token rotation, shutdown)."""
        for ws, _ in list(self._sockets.values()):
            if not ws.closed:
                with contextlib.suppress(Exception):
                    await ws.close(code=code, message=reason.encode())

    async def _sensorlogger(self, request: web.Request) -> web.Response:
        host = self._host_of(request)
        if not self.tokens.check(request.query.get("token")):
            self.rejected.count("missing or wrong token", host, "sensorlogger")
            return web.json_response({"error": "missing or wrong token: push to .../ingest/sensorlogger?token=..."},
                                     status=401)
        t = self.clock.now_ns()
        if not self.host_rates.allow(host, t):
            self.rejected.count("message rate exceeded", host, "sensorlogger")
            return web.json_response({"error": "too many requests"}, status=429)
        cap = self.limits.max_push_bytes
        if request.content_length is not None and request.content_length > cap:
            self.rejected.count("message too large", host, "sensorlogger")
            return web.json_response({"error": f"body over {cap} bytes"}, status=413)
        try:
            body = await request.read()
        except web.HTTPRequestEntityTooLarge:
            self.rejected.count("message too large", host, "sensorlogger")
            return web.json_response({"error": f"body over {cap} bytes"}, status=413)
        if len(body) > cap:
            self.rejected.count("message too large", host, "sensorlogger")
            return web.json_response({"error": f"body over {cap} bytes"}, status=413)
        t = self.clock.now_ns()
        try:
            obj = json.loads(body)
            did = obj.get("deviceId") if isinstance(obj, dict) else None
        except (ValueError, RecursionError):
            did = None
        if not isinstance(did, str) or not did:
            self.rejected.count("malformed message", host, "sensorlogger body without deviceId")
            return web.json_response({"error": "expected Sensor Logger JSON with deviceId"}, status=400)
        rid = re.sub(r"[^A-Za-z0-9._\-]", "-", did)[:64]
        key = f"sensorlogger/{rid}"
        if not (self.rates.allow(key, t) and self.byte_rates.allow(key, t, len(body))
                and self.host_byte_rates.allow(host, t, len(body))):
            self.rejected.count("message rate exceeded", host, "sensorlogger")
            return web.json_response({"error": "too many requests"}, status=429)
        admitted = self.registry.admit("sensorlogger", rid, host, {"deviceId": did, "peer": host})
        if admitted is None:
            self.rejected.count("phone not admitted", host, "sensorlogger")
            return web.json_response({"error": "too many phones on this service"}, status=503)
        if not admitted[1].put(Chunk(body, t, Direction.RX)):
            self._over_budget(admitted[1], host, "sensorlogger")
            return web.json_response({"error": "sending faster than the service decodes; retry later"}, status=429)
        self.stats.messages += 1
        return web.json_response({"ok": True, "device": admitted[0]})

    # -- token-less protocols --------------------------------------------------------------------
    async def start_udp(self, protocol: str, host: str, port: int, allow: AllowList) -> int:
        """Listen for ``protocol`` datagrams (``osc`` or ``hyperimu``); returns the bound port."""
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(
            lambda: _DatagramIngest(self, protocol, allow), local_addr=(host, port))
        self._transports.append(transport)
        return int(transport.get_extra_info("sockname")[1])

    async def start_tcp(self, protocol: str, host: str, port: int, allow: AllowList) -> int:
        """Listen for ``protocol`` over TCP (HyperIMU's TCP mode); returns the bound port."""
        server = await asyncio.start_server(lambda r, w: self._tcp_client(protocol, allow, r, w), host, port,
                                            limit=self.limits.max_message_bytes)
        self._servers.append(server)
        return int(server.sockets[0].getsockname()[1])

    async def _tcp_client(self, protocol: str, allow: AllowList, reader: asyncio.StreamReader,
                          writer: asyncio.StreamWriter) -> None:
        host = str(writer.get_extra_info("peername")[0])
        counted = False
        try:
            if not allow.allows(host):
                self.rejected.count("source not allow-listed", host, protocol)
                return
            lim = self.limits
            if (sum(self._tcp_open.values()) >= lim.max_connections
                    or self._tcp_open.get(host, 0) >= lim.max_connections_per_host):
                self.rejected.count("too many connections", host, f"{protocol} TCP")
                return
            self._tcp_open[host] = self._tcp_open.get(host, 0) + 1
            counted = True
            admitted = self.registry.admit(protocol, host, host, {"peer": host})
            if admitted is None:
                self.rejected.count("phone not admitted", host, protocol)
                return
            inbox = admitted[1]
            me = object()
            self._tcp_current[(protocol, host)] = me  # the newest connection of a host is its phone
            key = f"{protocol}-tcp/{host}"  # TCP delivers arbitrary pieces of the stream: 4 x the rate
            idle_s = max(10.0 * self.limits.ping_s, 10.0)
            while not self._closing:
                try:
                    data = await asyncio.wait_for(reader.read(self.limits.max_message_bytes), idle_s)
                except TimeoutError:
                    self.rejected.count("silent connection", host, f"{protocol} TCP: nothing for {idle_s:g} s")
                    break
                if not data:
                    break
                t = self.clock.now_ns()
                n = len(data)
                if not (self.rates.allow(key, t, 0.25) and self.host_rates.allow(host, t, 0.25)
                        and self.byte_rates.allow(key, t, n) and self.host_byte_rates.allow(host, t, n)):
                    self.rejected.count("message rate exceeded", host, protocol)
                    break
                if not inbox.put(Chunk(data, t, Direction.RX)):
                    self._over_budget(inbox, host, f"{protocol} TCP")
                    break
                self.stats.messages += 1
            if self._tcp_current.get((protocol, host)) is me:  # an older socket closing is not the phone leaving
                del self._tcp_current[(protocol, host)]
                inbox.disconnect(f"{protocol} TCP connection from {host} closed")
        except (ConnectionError, OSError) as exc:
            log.info("%s TCP client %s: %s", protocol, host, exc)
        finally:
            if counted:
                _dec(self._tcp_open, host)
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()

    async def stop(self) -> None:
        """Stop listening and close phone connections; what was received stays in the inboxes."""
        self._closing = True
        for t in self._transports:
            t.close()
        for s in self._servers:
            s.close()
        await self.close_phones(CLOSE_SHUTDOWN, "perfcap serve is shutting down")
        for s in self._servers:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(s.wait_closed(), 2.0)


def _dec(counts: dict[str, int], key: str) -> None:
    n = counts.get(key, 1) - 1
    if n > 0:
        counts[key] = n
    else:
        counts.pop(key, None)


class _DatagramIngest(asyncio.DatagramProtocol):
    """One UDP port of a token-less protocol: allow-list, size and rate per source host."""

    def __init__(self, gw: Gateway, protocol: str, allow: AllowList) -> None:
        self.gw = gw
        self.protocol = protocol
        self.allow = allow
        self._boxes: dict[str, Inbox] = {}

    def datagram_received(self, data: bytes, addr: tuple[Any, ...]) -> None:
        gw = self.gw
        host = str(addr[0])
        t = gw.clock.now_ns()
        inbox = self._boxes.get(host)
        if inbox is None or inbox.released:  # new, or its slot was given up while it was away
            self._boxes.pop(host, None)
            if not self.allow.allows(host):
                gw.rejected.count("source not allow-listed", host, self.protocol)
                return
            if len(data) > gw.limits.max_message_bytes:
                gw.rejected.count("message too large", host, self.protocol)
                return
            admitted = gw.registry.admit(self.protocol, host, host, {"peer": host})
            if admitted is None:
                gw.rejected.count("phone not admitted", host, self.protocol)
                return
            inbox = self._boxes[host] = admitted[1]
        if len(data) > gw.limits.max_message_bytes:
            gw.rejected.count("message too large", host, self.protocol)
            return
        if not gw._allow(f"{self.protocol}/{host}", host, t, len(data)):
            gw.rejected.count("message rate exceeded", host, self.protocol)
            return
        if not inbox.connected:
            gw.registry.admit(self.protocol, host, host, {"peer": host})  # back: connected, heard from now
        if not inbox.put(Chunk(data, t, Direction.RX)):
            gw._over_budget(inbox, host, self.protocol)  # no connection to close: the datagram is dropped
            return
        gw.stats.messages += 1

    def error_received(self, exc: Exception) -> None:
        log.info("%s UDP: %s", self.protocol, exc)
