"""mDNS for ``perfcap serve`` with real zeroconf on the loopback interface.

A zeroconf browser finds the service (``_perfcap._tcp.local.``, TXT v, port, token=1) and sees it
leave when it stops; the service finds a SensorServer phone advertised as
``SensorServer._websocket._tcp.local.`` (a local ``websockets`` server speaking the app's JSON), lists
it in ``health()["mdns"]["found"]``, and with ``connect_sensorserver=True`` connects and records its
samples. Multicast on loopback is probed first; without it the tests skip and say so.
"""

from __future__ import annotations

import asyncio
import socket
import time
from typing import Any

import numpy as np
import pytest
from serve_helpers import DEADLINE_S

from capture import __version__
from capture.session import SessionReader

GROUP = "224.0.0.251"


def _loopback_multicast_works() -> str | None:
    """None when a multicast datagram sent on 127.0.0.1 comes back to a member on 127.0.0.1; else why not."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    try:
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        rx.bind(("", 0))
        member = socket.inet_aton(GROUP) + socket.inet_aton("127.0.0.1")
        rx.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, member)
        rx.settimeout(10.0)  # the echo is immediate where multicast works
        tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
        tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        tx.sendto(b"perfcap-mdns-probe", (GROUP, rx.getsockname()[1]))
        data, _ = rx.recvfrom(64)
        return None if data == b"perfcap-mdns-probe" else "an unexpected datagram came back"
    except OSError as exc:
        return f"{type(exc).__name__}: {exc}"
    finally:
        rx.close()
        tx.close()


@pytest.fixture(scope="module")
def loopback_multicast() -> None:
    why = _loopback_multicast_works()
    if why is not None:
        pytest.skip(f"multicast on the loopback interface does not work in this sandbox ({why}); "
                    "mDNS tests need a multicast datagram sent on 127.0.0.1 to loop back")


class Mdns:
    """A zeroconf peer on 127.0.0.1: browses and advertises, in the calling thread's event loop."""

    def __init__(self) -> None:
        from zeroconf import IPVersion
        from zeroconf.asyncio import AsyncZeroconf

        self.azc = AsyncZeroconf(interfaces=["127.0.0.1"], ip_version=IPVersion.V4Only)
        self.events: asyncio.Queue[tuple[str, str]] = asyncio.Queue()
        self._browsers: list[Any] = []
        self._infos: list[Any] = []

    def browse(self, service_type: str) -> None:
        from zeroconf.asyncio import AsyncServiceBrowser

        def on_change(zeroconf: Any, service_type: str, name: str, state_change: Any) -> None:
            self.events.put_nowait((state_change.name, name))

        self._browsers.append(AsyncServiceBrowser(self.azc.zeroconf, [service_type], handlers=[on_change]))

    async def next_event(self, state: str, timeout: float = DEADLINE_S) -> str:
        async def wait() -> str:
            while True:
                st, name = await self.events.get()
                if st == state:
                    return name

        return await asyncio.wait_for(wait(), timeout)

    async def advertise(self, service_type: str, instance: str, port: int) -> None:
        from zeroconf.asyncio import AsyncServiceInfo

        info = AsyncServiceInfo(service_type, f"{instance}.{service_type}", port=port, properties={},
                                server="fake-phone.local.", parsed_addresses=["127.0.0.1"])
        await self.azc.async_register_service(info)
        self._infos.append(info)

    async def close(self) -> None:
        for b in self._browsers:
            await b.async_cancel()
        for info in self._infos:
            await self.azc.async_unregister_service(info)
        await self.azc.async_close()


def test_a_zeroconf_browser_finds_the_service(serve, loopback_multicast):
    served = serve(mdns=True, mdns_interfaces="127.0.0.1")
    ep = served.service.endpoints
    assert ep.mdns_error is None and ep.advertised and ep.advertised.endswith("._perfcap._tcp.local.")
    assert served.api("GET", "/health")[1]["mdns"]["advertised"] == ep.advertised

    async def go() -> dict[str, Any]:
        mdns = Mdns()
        try:
            mdns.browse("_perfcap._tcp.local.")
            name = await mdns.next_event("Added")
            while name != ep.advertised:  # another perfcap on this machine
                name = await mdns.next_event("Added")
            info = await mdns.azc.async_get_service_info("_perfcap._tcp.local.", name, 3000)
            out = {"port": info.port, "props": dict(info.decoded_properties), "addresses": info.parsed_addresses()}
            await asyncio.to_thread(served.stop)
            out["removed"] = await mdns.next_event("Removed", 5.0)  # goodbye when the service stops
            return out
        finally:
            await mdns.close()

    out = asyncio.run(go())
    assert out["port"] == ep.port and out["addresses"] == ["127.0.0.1"]
    assert out["props"] == {"v": __version__, "port": str(ep.port), "token": "1", "path": "/", "tls": "1"}
    assert out["removed"] == ep.advertised


def test_the_service_lists_a_sensorserver_phone_it_finds(serve, loopback_multicast, fake_sensorserver):
    served = serve(mdns=True, mdns_interfaces="127.0.0.1")  # connect_sensorserver off: list, don't connect

    async def go() -> list[dict[str, Any]]:
        mdns = Mdns()
        try:
            await mdns.advertise("_websocket._tcp.local.", "SensorServer", fake_sensorserver.port)
            deadline = time.monotonic() + DEADLINE_S
            while time.monotonic() < deadline:
                found = served.service.health()["mdns"]["found"]
                if found:
                    return found
                await asyncio.sleep(0.05)
            return []
        finally:
            await mdns.close()

    found = asyncio.run(go())
    assert found == [{"name": "SensorServer", "type": "_websocket._tcp.local.", "addresses": ["127.0.0.1"],
                      "port": fake_sensorserver.port, "properties": {}}]
    assert served.service.capture.devices == [] and fake_sensorserver.paths == []


def test_connect_sensorserver_connects_to_the_phone_it_finds(serve, loopback_multicast, fake_sensorserver, tmp_path):
    """Needs devices/phone_apps.py (kind ``sensorserver``)."""
    served = serve(mdns=True, mdns_interfaces="127.0.0.1", connect_sensorserver=True)
    path = str(tmp_path / "found.mcap")
    served.service.start_recording(path)
    n = fake_sensorserver.n_events

    def names() -> list[str]:
        return [d.name for d in served.service.capture.devices]

    async def go() -> None:
        mdns = Mdns()
        try:
            await mdns.advertise("_websocket._tcp.local.", "SensorServer", fake_sensorserver.port)
            await asyncio.to_thread(served.wait, lambda: names() and served.samples(f"{names()[0]}/gyro") == n,
                                    10, "the SensorServer phone's samples")
        finally:
            await mdns.close()

    asyncio.run(go())
    (name,) = names()
    dev = served.device(name)
    assert dev.kind == "sensorserver"
    assert dev.transport.url.startswith(f"sensorserver://127.0.0.1:{fake_sensorserver.port}")
    served.wait(lambda: served.samples(f"{name}/acc") == n, DEADLINE_S, "every accelerometer event")
    served.stop()
    r = SessionReader(path)
    acc = r.samples(f"{name}/acc")
    sent = fake_sensorserver.sent["android.sensor.accelerometer"]
    assert acc.t_device_ns.tolist() == [t for t, _ in sent]
    np.testing.assert_array_equal(acc.values, np.array([v for _, v in sent]))


def test_service_runs_on_when_mdns_cannot_start(serve):
    """Discovery is best effort: an interface address this machine does not have makes zeroconf fail;
    the service says why (health) and serves phones anyway."""
    served = serve(mdns=True, mdns_interfaces="203.0.113.7")  # TEST-NET-3: not an address of this machine
    ep = served.service.endpoints
    assert ep.advertised is None and ep.mdns_error and "Error" in ep.mdns_error
    status, h = served.api("GET", "/health")
    assert status == 200 and h["mdns"]["advertised"] is None and h["mdns"]["error"] == ep.mdns_error
    th = served.phone("after-mdns", duration_s=0.5)
    assert th.join(DEADLINE_S) and th.phone.error is None and th.phone.device == "phone-aftermdn"
