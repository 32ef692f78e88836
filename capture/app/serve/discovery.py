"""mDNS for ``perfcap serve`` (python-zeroconf): advertise the service, find phones that advertise.

* The service is ``<name>._perfcap._tcp.local.`` with TXT records ``v`` (perfcap version), ``port``
  (phone page, HTTPS), ``control`` (control API port, when it is reachable beyond loopback), ``token``
  (``1``: pairing required) and ``path`` (the page).
* SensorServer phones register ``SensorServer._websocket._tcp.local.`` (no TXT records). Found
  instances are kept in ``found``; the service connects to them when the user allows it.

Discovery is best effort: on a machine without multicast it logs why and the service runs on.
"""

from __future__ import annotations

import asyncio
import logging
import socket
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Callable

log = logging.getLogger(__name__)

SERVICE_TYPE = "_perfcap._tcp.local."
SENSORSERVER_TYPE = "_websocket._tcp.local."


@dataclass
class FoundService:
    name: str
    type: str
    addresses: list[str]
    port: int
    properties: dict[str, str | None]

    @property
    def is_sensorserver(self) -> bool:
        return self.name.lower().startswith("sensorserver")

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "type": self.type, "addresses": self.addresses, "port": self.port,
                "properties": self.properties}


class Discovery:
    """Advertises the service and browses for SensorServer phones.

    Args:
        instance: the instance name (default: ``perfcap on <hostname>``).
        addresses: addresses to advertise (the LAN address the phones use).
        port: the phone page's port.
        properties: TXT records.
        interfaces: ``"all"`` or a list of interface addresses (tests use ``["127.0.0.1"]``).
        browse: also browse for ``_websocket._tcp``.
        on_found: called (in the event loop) with each newly resolved ``FoundService``.
    """

    def __init__(self, instance: str | None, addresses: list[str], port: int, properties: dict[str, str], *,
                 interfaces: str | list[str] = "all", browse: bool = True,
                 on_found: Callable[[FoundService], None] | None = None) -> None:
        host = socket.gethostname().split(".")[0] or "perfcap"
        self.instance = (instance or f"perfcap on {host}")[:63]
        self.addresses = addresses
        self.port = port
        self.properties = properties
        self.interfaces = interfaces
        self.browse = browse
        self.on_found = on_found
        self.found: dict[str, FoundService] = {}
        self.error: str | None = None
        self.advertised: str | None = None
        self._azc: Any = None
        self._info: Any = None
        self._browser: Any = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self._host = host

    async def start(self) -> None:
        try:
            from zeroconf import InterfaceChoice, IPVersion
            from zeroconf.asyncio import (
                AsyncServiceBrowser,
                AsyncServiceInfo,
                AsyncZeroconf,
            )

            ifaces: Any = InterfaceChoice.All if self.interfaces == "all" else list(self.interfaces)
            if ifaces is not InterfaceChoice.All:
                for addr in ifaces:  # zeroconf leaks its socket on an address this machine lacks
                    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
                        try:
                            probe.bind((addr, 0))
                        except OSError as exc:
                            raise OSError(f"{addr} is not an address of this machine ({exc.strerror})") from None
            self._azc = AsyncZeroconf(interfaces=ifaces, ip_version=IPVersion.V4Only)
            self._info = AsyncServiceInfo(
                SERVICE_TYPE, f"{self.instance}.{SERVICE_TYPE}", port=self.port, properties=self.properties,
                server=f"{self._host}.local.", parsed_addresses=self.addresses)
            await self._azc.async_register_service(self._info, allow_name_change=True)
            self.advertised = self._info.name
            log.info("advertised %s on %s port %d", self._info.name, ", ".join(self.addresses), self.port)
            if self.browse:
                self._browser = AsyncServiceBrowser(self._azc.zeroconf, [SENSORSERVER_TYPE],
                                                    handlers=[self._on_change])
        except Exception as exc:
            self.error = f"{type(exc).__name__}: {exc}"
            log.warning("mDNS discovery is off: %s (phones can still connect with the printed URL)", self.error)
            await self.stop()

    def _on_change(self, zeroconf: Any, service_type: str, name: str, state_change: Any) -> None:
        from zeroconf import ServiceStateChange

        if state_change is ServiceStateChange.Removed:
            gone = self.found.pop(name, None)
            if gone is not None:
                log.info("mDNS: %s left", name)
            return
        task = asyncio.get_running_loop().create_task(self._resolve(service_type, name))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _resolve(self, service_type: str, name: str) -> None:
        from zeroconf.asyncio import AsyncServiceInfo

        info = AsyncServiceInfo(service_type, name)
        try:
            ok = await info.async_request(self._azc.zeroconf, 3000)
        except Exception as exc:
            log.info("mDNS: cannot resolve %s: %s", name, exc)
            return
        if not ok or not info.port:
            return
        found = FoundService(name.removesuffix("." + service_type), service_type, info.parsed_addresses(),
                             int(info.port), dict(info.decoded_properties))
        new = name not in self.found
        self.found[name] = found
        if new:
            log.info("mDNS: found %s at %s:%d", found.name, ",".join(found.addresses), found.port)
            if self.on_found is not None:
                try:
                    self.on_found(found)
                except Exception:
                    log.exception("mDNS: handling %s failed", name)

    async def stop(self) -> None:
        for t in list(self._tasks):
            t.cancel()
        if self._browser is not None:
            try:
                await self._browser.async_cancel()
            except Exception:
                log.debug("mDNS browser cancel failed", exc_info=True)
            self._browser = None
        if self._azc is not None:
            try:
                if self.advertised and self._info is not None:
                    # the goodbye packets: awaited, or closing cancels them and browsers keep a stale entry
                    await (await self._azc.async_unregister_service(self._info))
                await self._azc.async_close()
            except Exception:
                log.debug("mDNS close failed", exc_info=True)
            self._azc = None
            self.advertised = None
