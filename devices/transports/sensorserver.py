"""``sensorserver://HOST:PORT?types=...``: the Android SensorServer app's WebSocket server, with perfcap as its client.

The SensorServer app *is* a WebSocket server; this transport is its client (``websockets``'
synchronous client, one per device thread), and every text frame is one chunk. This module owns
the app's connection protocol: which path subscribes to which sensor types (``sensorserver_path``)
and what the app's close codes mean (``SENSORSERVER_CLOSE_CODES``). What the messages say is the
codec's (``devices.codecs.sensorserver``), what the values mean the device's
(``devices.phone_apps.sensorserver``).
"""

from __future__ import annotations

import json
import logging
from typing import TYPE_CHECKING, Any, ClassVar
from urllib.parse import quote

from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError, DeviceInitError, DeviceIOError, DeviceNotFoundError
from capture.sample import Chunk, Direction
from devices.options import Option
from devices.transports.base import Transport

if TYPE_CHECKING:
    from collections.abc import Sequence

log = logging.getLogger(__name__)

_ANDROID = "android.sensor."

#: Close codes the SensorServer app sends (``SensorWebSocketServer.kt``), with what they mean to the user.
SENSORSERVER_CLOSE_CODES: dict[int, str] = {
    4001: "sensor not found: the phone has no sensor of a requested type",
    4002: "unsupported request: the app does not serve this path",
    4003: "parameter missing: the path lacks its type/types parameter",
    4004: "server stopped: the app's server was stopped on the phone",
    4005: "connection closed by the app's user",
    4006: "invalid JSON array: the types parameter is not a JSON array",
    4007: "too few sensors: the multi-sensor path needs at least two types",
    4008: "no sensor specified: the type parameter is empty",
    4009: "permission denied: the app lacks a permission (location for GPS)",
}


def sensorserver_type(name: str) -> str:
    """A sensor type's full Android name: ``accelerometer`` -> ``android.sensor.accelerometer``
    (full names, including vendor ones, are kept; case is folded, as the app matches it)."""
    n = name.strip().lower()
    return n if "." in n else _ANDROID + n


def sensorserver_path(types: Sequence[str]) -> str:
    """The app's WebSocket path (with query) for ``types``.

    One sensor type gives ``/sensor/connect?type=android.sensor.X``; two or more give
    ``/sensors/connect?types=`` and a URL-encoded JSON array; ``["touchscreen"]`` gives ``/touchscreen``.

    Raises:
        ValueError: no type, a repeated type, or touchscreen mixed with sensors.
    """
    names = [t.strip().lower() for t in types if t.strip()]
    if not names:
        raise ValueError("name at least one sensor type")
    if "touchscreen" in names:
        if len(names) > 1:
            raise ValueError("touchscreen is a connection of its own; it cannot be mixed with sensor types")
        return "/touchscreen"
    full = [sensorserver_type(t) for t in names]
    if len(set(full)) != len(full):
        raise ValueError(f"a sensor type is listed twice: {', '.join(full)}")
    if len(full) == 1:
        return "/sensor/connect?type=" + quote(full[0], safe="")
    return "/sensors/connect?types=" + quote(json.dumps(full, separators=(",", ":")), safe="")


class SensorServerTransport(Transport):
    """The SensorServer app's WebSocket server on a phone: ``sensorserver://HOST:PORT?types=a,b``."""

    scheme = "sensorserver"
    usage = "sensorserver://HOST:PORT?types=accelerometer,gyroscope"
    options: ClassVar[dict[str, Option]] = {
        "types": Option(str, "accelerometer,gyroscope", "sensors to subscribe to (Android sensor type names)"),
        "open_timeout": Option(float, 5.0, "seconds to wait for the phone to accept the connection", min=0.1,
                               max=120.0),
        "max_message": Option(int, 65536, "largest message accepted, bytes", min=256, max=16 << 20),
    }

    def __init__(self, address: str, options: dict[str, Any] | None = None, clock: Clock = MONOTONIC) -> None:
        super().__init__(address, options, clock)
        host, sep, port = address.rpartition(":")
        if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise ConfigError(f"invalid sensorserver:// address {address!r}; expected {self.usage}", source=address)
        self.host = host.strip("[]")
        self.port = int(port)
        self.types = [t.strip() for t in str(self.opts["types"]).split(",") if t.strip()]
        try:
            self.path = sensorserver_path(self.types)
        except ValueError as exc:
            raise ConfigError(f"{self.url}: {exc}; expected {self.usage}", source=self.url) from None
        self._ws: Any = None

    def implied_kind(self) -> str | None:
        return "sensorserver"

    def implied_device_options(self) -> dict[str, Any]:
        return {"types": ",".join(self.types)}

    def identity_hint(self) -> dict[str, Any]:
        return {"address": f"{self.host}:{self.port}"}

    @property
    def ws_url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}{self.path}"

    def open(self) -> None:
        from websockets.exceptions import (
            InvalidHandshake,
            InvalidURI,
            WebSocketException,
        )
        from websockets.sync.client import connect

        try:
            conn = connect(self.ws_url, open_timeout=self.opts["open_timeout"],
                           max_size=self.opts["max_message"], compression=None)
            # entered as a context manager (websockets 17.1 deprecates the bare call); closed in close()
            self._ws = conn.__enter__()
        except (ConnectionRefusedError, TimeoutError) as exc:
            raise DeviceNotFoundError(f"SensorServer at {self.host}:{self.port} does not answer ({exc}); is the app's"
                                      " server started and the phone on this network?", source=self.url) from exc
        except (OSError, InvalidURI, InvalidHandshake, WebSocketException) as exc:
            raise DeviceInitError(f"SensorServer at {self.host}:{self.port}: {exc}", source=self.url) from exc

    def close(self) -> None:
        ws, self._ws = self._ws, None
        if ws is not None:
            try:
                ws.close()
            except Exception:
                log.debug("sensorserver close failed", exc_info=True)

    @property
    def is_open(self) -> bool:
        return self._ws is not None

    def read(self, timeout: float) -> Chunk | None:
        from websockets.exceptions import ConnectionClosed

        ws = self._ws
        if ws is None:
            raise DeviceIOError(f"{self.url}: not open", source=self.url)
        try:
            msg = ws.recv(timeout=timeout)
        except TimeoutError:
            return None
        except ConnectionClosed as exc:
            code = exc.rcvd.code if exc.rcvd is not None else None
            why = SENSORSERVER_CLOSE_CODES.get(code or 0, exc.rcvd.reason if exc.rcvd else "connection lost")
            raise DeviceIOError(f"SensorServer at {self.host}:{self.port} closed the connection"
                                f"{f' ({code})' if code else ''}: {why}", source=self.url) from exc
        except OSError as exc:
            raise DeviceIOError(f"SensorServer at {self.host}:{self.port}: {exc}", source=self.url) from exc
        t = self.clock.now_ns()
        data = msg.encode() if isinstance(msg, str) else bytes(msg)
        return Chunk(data, t, Direction.RX)


__all__ = ["SENSORSERVER_CLOSE_CODES", "SensorServerTransport", "sensorserver_path", "sensorserver_type"]
