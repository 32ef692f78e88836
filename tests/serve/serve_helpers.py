"""Shared by the ``perfcap serve`` tests: the fixed pairing token, waiting for a condition (``wait_until``,
from ``wait_helpers``), free ports on 127.0.0.1, ``Served`` (a running service and its real endpoints:
the control API over HTTP with urllib, the page WebSocket over TLS with aiohttp, the certificate
pinned by its fingerprint, and simulated phones) and ``FakeSensorServer`` (the SensorServer app's
WebSocket server, speaking its JSON). ``conftest.py`` turns them into fixtures."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import socket
import threading
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from wait_helpers import DEADLINE_S, wait_until

from sim_devices.phone_client import PhoneThread, SimPagePhone
from sim_devices.phone_sim import page_hello

if TYPE_CHECKING:
    from collections.abc import AsyncIterator
    from pathlib import Path

    from capture.app.serve.service import Service, ServiceThread

log = logging.getLogger(__name__)

#: The pairing token of every test service (a fixed token is never written to the state dir).
TOKEN = "serve-tests-token-0123456789"


class _Current:
    """Sentinel: the service's current token."""


CURRENT: Any = _Current()


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A port nobody listens on at the moment (UDP by default) on 127.0.0.1."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


PhoneRunner = PhoneThread  # a simulated phone on its own event loop in a thread


@dataclass
class Served:
    """A running service and its endpoints."""

    service: Service
    thread: ServiceThread
    tmp: Path
    phones: list[PhoneRunner] = field(default_factory=list)
    stopped: bool = False
    report: Any = None

    # -- endpoints -----------------------------------------------------------------------------------
    @property
    def token(self) -> str:
        return self.service.tokens.token

    @property
    def port(self) -> int:
        return self.service.endpoints.port

    @property
    def ws_url(self) -> str:
        return f"wss://127.0.0.1:{self.port}/ws/phone"

    @property
    def base_url(self) -> str:
        return f"https://127.0.0.1:{self.port}"

    @property
    def fingerprint(self) -> str:
        return self.service.endpoints.fingerprint

    @property
    def control_url(self) -> str:
        return self.service.endpoints.control_url

    def ssl(self) -> Any:
        """aiohttp's ``ssl=`` argument pinning this service's certificate."""
        import aiohttp

        return aiohttp.Fingerprint(bytes.fromhex(self.fingerprint.replace(":", "")))

    # -- control API -----------------------------------------------------------------------------
    def api(self, method: str, path: str, *, token: Any = CURRENT, body: Any = None, data: bytes | None = None,
            auth: str | None = None, timeout: float = DEADLINE_S) -> tuple[int, Any]:
        """One control API request (``path`` after ``/api``); returns (status, decoded JSON)."""
        headers = {}
        if auth is not None:
            headers["Authorization"] = auth
        elif token is not None:
            headers["Authorization"] = "Bearer " + (self.token if token is CURRENT else token)
        if body is not None:
            data = json.dumps(body).encode()
        if data is not None:
            headers["Content-Type"] = "application/json"
        req = urllib.request.Request(self.control_url + path, data=data, method=method, headers=headers)
        try:
            with urllib.request.urlopen(req, timeout=timeout) as r:
                return r.status, json.loads(r.read() or b"null")
        except urllib.error.HTTPError as e:
            with e:
                raw = e.read()
            try:
                return e.code, json.loads(raw or b"null")
            except ValueError:
                return e.code, raw.decode("utf-8", "replace")

    # -- phones ----------------------------------------------------------------------------------
    def phone(self, phone_id: str, **kw: Any) -> PhoneRunner:
        """A ``SimPagePhone`` streaming to this service over TLS (certificate pinned), started."""
        th = PhoneRunner(SimPagePhone(self.ws_url, kw.pop("token", self.token), phone_id,
                                      fingerprint=self.fingerprint, **kw)).start()
        self.phones.append(th)
        return th

    @staticmethod
    @contextlib.asynccontextmanager
    async def client() -> AsyncIterator[Any]:
        """An aiohttp ``ClientSession`` that is closed with its TLS connections fully shut down: the
        loop runs on briefly after closing, so no socket outlives ``asyncio.run`` (a ResourceWarning)."""
        import aiohttp

        async with aiohttp.ClientSession() as session:
            yield session
        await asyncio.sleep(0.1)

    async def page(self, session: Any, phone_id: str, token: Any = CURRENT) -> tuple[Any, Any]:
        """Open the page WebSocket and say hello; returns (ws, the first message back)."""
        ws = await session.ws_connect(self.ws_url, ssl=self.ssl(), autoping=True, heartbeat=None)
        tok = self.token if token is CURRENT else token
        await ws.send_str(page_hello(phone_id, token=tok).decode())
        return ws, await ws.receive(timeout=DEADLINE_S)

    def samples(self, stream: str) -> int:
        """Samples of ``stream`` the bus has carried so far."""
        return int(self.service.capture.stats.snapshot().get(stream, {}).get("samples", 0))

    def device(self, name: str) -> Any:
        return self.service.capture.device(name)

    def rejected(self) -> dict[str, int]:
        return self.service.gateway.rejected.as_dict()

    wait = staticmethod(wait_until)

    def stop(self, phones_first: bool = True) -> Any:
        """Stop gracefully (idempotent); returns the capture report.

        Args:
            phones_first: stop the simulated phones before the service (False: the service stops
                while they stream, and closes them).
        """
        if not self.stopped:
            self.stopped = True
            try:
                if phones_first:
                    for ph in self.phones:
                        ph.stop(DEADLINE_S)
            finally:
                self.report = self.thread.stop()
        for ph in self.phones:
            ph.stop(DEADLINE_S)
        return self.report


class FakeSensorServer:
    """The SensorServer app's WebSocket server as a phone runs it, on 127.0.0.1 (``websockets``).

    On ``/sensors/connect?types=[...]`` (URL-encoded JSON array) or ``/sensor/connect?type=...`` it
    sends ``n_events`` events per type, one JSON text frame each, as the app does:
    ``{"values": [...], "timestamp": <ns since boot>, "accuracy": 3, "type": "android.sensor.X"}``
    (``type`` only on the multi-sensor path), 200 Hz of device time, then keeps the connection
    open. Other paths are closed with the app's 4002. ``sent[type]`` lists (timestamp, values).
    """

    def __init__(self, n_events: int = 100) -> None:
        self.n_events = n_events
        self.paths: list[str] = []
        self.sent: dict[str, list[tuple[int, tuple[float, ...]]]] = {}
        self.port = 0
        self._ready = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread = threading.Thread(target=lambda: asyncio.run(self._main()), name="fake-sensorserver",
                                        daemon=True)

    @staticmethod
    def values(sensor: str, i: int) -> tuple[float, ...]:
        if sensor == "android.sensor.accelerometer":
            return (0.5 * math.sin(i / 7.0), 0.25 + 0.001 * i, 9.80665 - 0.002 * i)
        return (0.01 * i, -0.02 * math.cos(i / 5.0), 0.03)

    async def _handler(self, ws: Any) -> None:
        from urllib.parse import parse_qs, urlsplit

        path = ws.request.path
        self.paths.append(path)
        u = urlsplit(path)
        q = parse_qs(u.query)
        if u.path.lower() == "/sensors/connect" and "types" in q:
            types, multi = list(json.loads(q["types"][0])), True
        elif u.path.lower() == "/sensor/connect" and "type" in q:
            types, multi = [q["type"][0]], False
        else:
            await ws.close(4002, "unsupported path")
            return
        from websockets.exceptions import ConnectionClosed

        t0 = 5_000_000_000_000  # ns since the phone booted
        try:
            for i in range(self.n_events):
                for typ in types:
                    ev: dict[str, Any] = {"values": list(self.values(typ, i)), "timestamp": t0 + i * 5_000_000,
                                          "accuracy": 3}
                    if multi:
                        ev["type"] = typ
                    await ws.send(json.dumps(ev))
                    self.sent.setdefault(typ, []).append((ev["timestamp"], tuple(ev["values"])))
                await asyncio.sleep(0.002)
        except ConnectionClosed:  # the client left early: what was sent is in self.sent
            return
        await ws.wait_closed()

    async def _main(self) -> None:
        from websockets.asyncio.server import serve

        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        async with serve(self._handler, "127.0.0.1", 0, compression=None) as server:
            self.port = int(next(iter(server.sockets)).getsockname()[1])
            self._ready.set()
            await self._stop.wait()

    def start(self) -> FakeSensorServer:
        self._thread.start()
        if not self._ready.wait(DEADLINE_S):
            raise RuntimeError("the fake SensorServer did not start")
        return self

    def stop(self) -> None:
        if self._loop is not None and self._stop is not None and self._thread.is_alive():
            with contextlib.suppress(RuntimeError):
                self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(DEADLINE_S)


__all__ = ["CURRENT", "DEADLINE_S", "TOKEN", "FakeSensorServer", "PhoneRunner", "Served", "free_port", "wait_until"]
