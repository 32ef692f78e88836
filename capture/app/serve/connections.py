"""The phone port's TCP connections: how many are held, by whom, and for how long before they say
anything.

asyncio accepts every connection and, with TLS, runs its handshake before the application sees it;
neither is bounded, and an idle TLS socket costs about 300 KB. So the phone port is served by a
``GatedSite``: each accepted socket reaches ``ConnectionGate`` first, which

* refuses it at once (the socket is reset, nothing is allocated for it) when the port already holds
  ``max_sockets`` connections, its address ``max_sockets_per_host``, or ``max_handshakes`` are still
  in their handshake;
* runs the TLS handshake itself (``loop.start_tls``) and then hands the connection to aiohttp;
* closes a connection whose first HTTP request has not arrived ``handshake_timeout_s`` after it was
  accepted (TLS included: a half-open handshake and a silent TLS socket end the same way).

Every refusal and timeout is counted in the gateway's ``Rejections``. Idle HTTP keep-alive connections
are closed by aiohttp after ``idle_timeout_s`` (the runner's keep-alive timeout); paired WebSockets by
the gateway's own hello and silence timeouts.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

from aiohttp import web

if TYPE_CHECKING:
    import ssl
    from collections.abc import Callable

    from capture.app.serve.config import Limits
    from capture.app.serve.security import Rejections

log = logging.getLogger(__name__)


@dataclass
class GateStats:
    accepted: int = 0
    refused: int = 0
    timed_out: int = 0
    tls_failed: int = 0
    peak_open: int = 0
    peak_handshakes: int = 0


class _Conn(asyncio.Protocol):
    """One accepted socket: first the gate's protocol on the raw socket, then (through TLS) the
    forwarding protocol in front of aiohttp's handler, so the gate sees the connection end."""

    def __init__(self, gate: ConnectionGate) -> None:
        self.gate = gate
        self.host = "?"
        self.raw: asyncio.Transport | None = None
        self.app_transport: asyncio.BaseTransport | None = None
        self.handler: asyncio.Protocol | None = None
        self.handshaking = False
        self.counted = False
        self.made = False
        self.closed = False
        self.timer: asyncio.TimerHandle | None = None
        self.task: asyncio.Task[None] | None = None
        self._early: list[bytes] = []  # decrypted before the handover (the request right behind the handshake)
        self._early_eof = False

    # -- on the raw socket --------------------------------------------------------------------------
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        if self.raw is None:
            self.raw = cast("asyncio.Transport", transport)  # a TCP server's transports are Transports
            self.gate._accepted(self)
            return
        self._app_made(transport)  # the TLS transport, from ConnectionGate._start_tls

    def data_received(self, data: bytes) -> None:
        if self.handler is not None and self.made:
            self.handler.data_received(data)
        elif not self.closed:
            self._early.append(data)

    def eof_received(self) -> bool | None:
        if self.handler is not None and self.made:
            return self.handler.eof_received()
        self._early_eof = True
        return None

    def pause_writing(self) -> None:
        if self.handler is not None and self.made:
            self.handler.pause_writing()

    def resume_writing(self) -> None:
        if self.handler is not None and self.made:
            self.handler.resume_writing()

    def connection_lost(self, exc: Exception | None) -> None:
        if self.handler is not None and self.made:
            self.handler.connection_lost(exc)
        self.gate._gone(self)

    # -- handing over -------------------------------------------------------------------------------
    def _app_made(self, transport: asyncio.BaseTransport) -> None:
        self.app_transport = transport
        self.handler = self.gate.handler_factory()
        self.made = True
        self.gate._by_transport[id(transport)] = self
        self.handler.connection_made(transport)
        early, self._early = self._early, []
        for data in early:
            self.handler.data_received(data)
        if self._early_eof:
            self.handler.eof_received()

    def abort(self) -> None:
        for t in (self.app_transport, self.raw):
            if isinstance(t, asyncio.Transport):
                with contextlib.suppress(Exception):
                    t.abort()


class ConnectionGate:
    """Admission, TLS and the handshake deadline for one listening port (see the module docstring).

    Args:
        limits: ``max_sockets``, ``max_sockets_per_host``, ``max_handshakes``, ``handshake_timeout_s``.
        rejected: where refusals are counted.
        ssl_context: TLS for the port, or None for plain HTTP.
        handler_factory: makes the application's protocol for a connection (aiohttp's ``runner.server``).
    """

    def __init__(self, limits: Limits, rejected: Rejections, ssl_context: ssl.SSLContext | None,
                 handler_factory: Callable[[], asyncio.Protocol]) -> None:
        self.limits = limits
        self.rejected = rejected
        self.ssl_context = ssl_context
        self.handler_factory = handler_factory
        self.stats = GateStats()
        self._conns: set[_Conn] = set()
        self._per_host: dict[str, int] = {}
        self._handshakes = 0
        self._by_transport: dict[int, _Conn] = {}
        self._closing = False

    @property
    def open(self) -> int:
        """Connections held now, in any state."""
        return len(self._conns)

    @property
    def handshakes(self) -> int:
        """Connections still in their TLS or HTTP handshake."""
        return self._handshakes

    def per_host(self) -> dict[str, int]:
        return dict(self._per_host)

    def protocol(self) -> asyncio.Protocol:
        return _Conn(self)

    def _accepted(self, c: _Conn) -> None:
        raw = c.raw
        assert raw is not None
        raw.pause_reading()  # nothing is read before the handshake owns the socket (or it is refused)
        peer = raw.get_extra_info("peername")
        c.host = str(peer[0]) if peer else "?"
        lim = self.limits
        why = ("the service is stopping" if self._closing else
               "too many connections" if len(self._conns) >= lim.max_sockets else
               "too many connections from one address" if self._per_host.get(c.host, 0) >= lim.max_sockets_per_host
               else "too many handshakes" if self._handshakes >= lim.max_handshakes else None)
        if why is not None:
            self.stats.refused += 1
            self.rejected.count(why, c.host, "TCP connection reset at accept")
            c.closed = True
            raw.abort()
            return
        self.stats.accepted += 1
        c.counted = True
        self._conns.add(c)
        self._per_host[c.host] = self._per_host.get(c.host, 0) + 1
        c.handshaking = True
        self._handshakes += 1
        st = self.stats
        st.peak_open = max(st.peak_open, len(self._conns))
        st.peak_handshakes = max(st.peak_handshakes, self._handshakes)
        loop = asyncio.get_running_loop()
        c.timer = loop.call_later(lim.handshake_timeout_s, self._expire, c)
        if self.ssl_context is None:
            raw.set_protocol(c)
            c._app_made(raw)
            raw.resume_reading()
        else:
            c.task = loop.create_task(self._start_tls(c))

    async def _start_tls(self, c: _Conn) -> None:
        raw = c.raw
        assert raw is not None and self.ssl_context is not None
        loop = asyncio.get_running_loop()
        try:
            tls = await loop.start_tls(raw, c, self.ssl_context, server_side=True,
                                       ssl_handshake_timeout=self.limits.handshake_timeout_s)
        except asyncio.CancelledError:
            c.abort()
            self._gone(c)
            raise
        except Exception as exc:  # ssl.SSLError, a reset, asyncio's handshake timeout: the peer's doing
            if not c.closed:
                self.stats.tls_failed += 1
                self.rejected.count("TLS handshake failed", c.host, f"{type(exc).__name__}: {exc}")
                c.abort()
                self._gone(c)
            return
        if c.closed or tls is None:
            if tls is not None:
                tls.abort()
            return
        c.connection_made(tls)

    def _expire(self, c: _Conn) -> None:
        c.timer = None
        if c.closed or not c.handshaking:
            return
        self.stats.timed_out += 1
        self.rejected.count("handshake timeout", c.host,
                            f"no HTTP request {self.limits.handshake_timeout_s:g} s after connecting")
        c.abort()
        self._gone(c)

    def _gone(self, c: _Conn) -> None:
        if c.closed:
            return
        c.closed = True
        if c.timer is not None:
            c.timer.cancel()
            c.timer = None
        if c.handshaking:
            c.handshaking = False
            self._handshakes -= 1
        if c.app_transport is not None:
            self._by_transport.pop(id(c.app_transport), None)
        if c.counted:
            self._conns.discard(c)
            n = self._per_host.get(c.host, 1) - 1
            if n > 0:
                self._per_host[c.host] = n
            else:
                self._per_host.pop(c.host, None)
        c._early = []

    def established(self, transport: asyncio.BaseTransport | None) -> None:
        """A request arrived on ``transport``: its connection's handshake is over."""
        c = self._by_transport.get(id(transport)) if transport is not None else None
        if c is not None and c.handshaking:
            c.handshaking = False
            self._handshakes -= 1
            if c.timer is not None:
                c.timer.cancel()
                c.timer = None

    def middleware(self) -> Any:
        """An aiohttp middleware that tells the gate each request arrived (not-found paths included)."""

        @web.middleware
        async def mark(request: web.Request, handler: Any) -> web.StreamResponse:
            self.established(request.transport)
            resp: web.StreamResponse = await handler(request)
            return resp

        return mark

    def stop_accepting(self) -> None:
        """Admit no more connections and reset those still in their handshake; established ones are
        left to their handlers, so paired phones hear a proper close."""
        self._closing = True
        for c in [c for c in self._conns if c.handshaking]:
            if c.task is not None and not c.task.done():
                c.task.cancel()
            c.abort()
            self._gone(c)

    def close_all(self) -> None:
        """Stop admitting and reset every connection still held (the service has stopped)."""
        self._closing = True
        for c in list(self._conns):
            if c.task is not None and not c.task.done():
                c.task.cancel()
            c.abort()
            self._gone(c)


class GatedSite(web.BaseSite):
    """An aiohttp site on ``host:port`` whose connections pass through a ``ConnectionGate``."""

    def __init__(self, runner: web.BaseRunner, host: str, port: int, gate: ConnectionGate, *,
                 backlog: int = 128) -> None:
        super().__init__(runner, backlog=backlog)
        self._gate_host = host
        self._gate_port = port
        self.gate = gate
        self.bound_port = port

    @property
    def name(self) -> str:
        scheme = "https" if self.gate.ssl_context is not None else "http"
        return f"{scheme}://{self._gate_host}:{self.bound_port}"

    async def start(self) -> None:
        await super().start()
        loop = asyncio.get_running_loop()
        self._server = server = await loop.create_server(self.gate.protocol, self._gate_host, self._gate_port,
                                                         backlog=self._backlog)
        socks = list(server.sockets or ())
        if socks:
            self.bound_port = int(socks[0].getsockname()[1])

    async def stop(self) -> None:
        self.gate.stop_accepting()
        await super().stop()
