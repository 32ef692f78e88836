"""The control API of ``perfcap serve``: small HTTP/JSON, on loopback by default, token required.

``Authorization: Bearer <pairing token>`` on every request.

* ``GET /api/health``: status, uptime, recording, counts of phones and refused input, mDNS state.
* ``GET /api/devices``: per device: state, rate, drops, clock offset and drift, last seen, peer.
* ``POST /api/record/start`` (JSON body optional: ``{"path": "take1.mcap", "overwrite": false}``) and
  ``POST /api/record/stop``. The path is a name inside the sessions directory, never reached through a
  link (``Service.start_recording``): a bad one is a 400, an existing file a 409, each with its reason.
* ``POST /api/token/rotate``: a new pairing token (returned once); the old one stops working and
  phones that used it are disconnected.
* ``POST /api/sensorserver`` ``{"host": "192.168.1.40", "port": 8080, "types": "accelerometer,gyroscope"}``:
  connect to a SensorServer phone.
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
from typing import TYPE_CHECKING, Any

from aiohttp import web

from capture.errors import CaptureError, ConfigError, SessionExistsError

if TYPE_CHECKING:
    from capture.app.serve.service import Service

log = logging.getLogger(__name__)

JSON = "application/json"

_HOST_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9.\-:]{0,252}$")
_TYPES_RE = re.compile(r"^[A-Za-z0-9_.]+(,[A-Za-z0-9_.]+)*$")
_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_\-]{0,63}$")


def control_app(service: Service) -> web.Application:
    @web.middleware
    async def auth(request: web.Request, handler: Any) -> web.StreamResponse:
        header = request.headers.get("Authorization", "")
        token = header[7:].strip() if header[:7].lower() == "bearer " else None
        if not service.tokens.check(token):
            service.gateway.rejected.count("missing or wrong token", request.remote, "control API")
            return web.json_response({"error": "missing or wrong token: send 'Authorization: Bearer <token>'"},
                                     status=401)
        try:
            return await handler(request)
        except web.HTTPException:
            raise
        except SessionExistsError as exc:
            return web.json_response({"error": str(exc)}, status=409)
        except ConfigError as exc:
            return web.json_response({"error": str(exc)}, status=409 if "already" in str(exc) or
                                     "not recording" in str(exc) else 400)
        except CaptureError as exc:
            return web.json_response({"error": str(exc)}, status=500)
        except (OSError, ValueError) as exc:  # a path the OS refuses (missing directory, NUL byte, ...)
            return web.json_response({"error": f"{type(exc).__name__}: {exc}"}, status=400)

    async def body(request: web.Request) -> dict[str, Any]:
        if not request.can_read_body:
            return {}
        try:
            data = json.loads(await request.read() or b"{}")
        except ValueError:
            raise web.HTTPBadRequest(text='{"error": "the body must be JSON"}', content_type=JSON) from None
        if not isinstance(data, dict):
            raise web.HTTPBadRequest(text='{"error": "the body must be a JSON object"}', content_type=JSON)
        return data

    async def health(request: web.Request) -> web.Response:
        return web.json_response(service.health())

    async def devices(request: web.Request) -> web.Response:
        return web.json_response({"devices": service.devices_info()})

    async def record_start(request: web.Request) -> web.Response:
        b = await body(request)
        path = b.get("path")
        overwrite = b.get("overwrite", False)
        if path is not None and not isinstance(path, str):
            raise ConfigError('path must be a string, e.g. {"path": "take1.mcap"}')
        if not isinstance(overwrite, bool):
            raise ConfigError("overwrite must be true or false (JSON booleans)")
        loop = asyncio.get_running_loop()  # creating the file may block: not on the event loop
        out = await loop.run_in_executor(None, lambda: service.start_recording(path, overwrite=overwrite))
        return web.json_response({"recording": out})

    async def record_stop(request: web.Request) -> web.Response:
        loop = asyncio.get_running_loop()  # the recorder drains and fsyncs: not on the event loop
        return web.json_response(await loop.run_in_executor(None, service.stop_recording))

    async def rotate(request: web.Request) -> web.Response:
        tok = await service.rotate_token()
        return web.json_response({"token": tok, "pair_url": service.endpoints.pair_url})

    async def sensorserver(request: web.Request) -> web.Response:
        b = await body(request)
        host, port, types, name = b.get("host"), b.get("port"), b.get("types"), b.get("name")
        if (not isinstance(host, str) or not _HOST_RE.match(host) or type(port) is not int
                or not 0 < port < 65536):
            raise ConfigError('expected {"host": "192.168.1.40", "port": 8080}'
                              ' (a host name or address, a port 1-65535)')
        if types is not None and (not isinstance(types, str) or not _TYPES_RE.match(types)):
            raise ConfigError('types must be sensor type names separated by commas, e.g. "accelerometer,gyroscope"')
        if name is not None and (not isinstance(name, str) or not _NAME_RE.match(name)):
            raise ConfigError("name must start with a letter and use letters, digits, _ or - (at most 64)")
        name = service.add_sensorserver(host, port, types, name)
        return web.json_response({"device": name})

    app = web.Application(middlewares=[auth], client_max_size=64 * 1024)
    app.router.add_get("/api/health", health)
    app.router.add_get("/api/devices", devices)
    app.router.add_post("/api/record/start", record_start)
    app.router.add_post("/api/record/stop", record_stop)
    app.router.add_post("/api/token/rotate", rotate)
    app.router.add_post("/api/sensorserver", sensorserver)
    return app
