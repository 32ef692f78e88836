"""``perfcap serve``: the long-running capture service.

The service owns one ``Capture`` (bus, configured devices, recorder) and runs, in one asyncio loop:
the phone gateway over HTTPS (page, WebSocket, Sensor Logger push), the optional token-less UDP/TCP
ports, the control API on loopback, and mDNS (advertise ``_perfcap._tcp``, browse for SensorServer).
Each phone becomes a device on the bus the first time it is seen (``PhoneDevices.admit``), under a
name that stays the same when it reconnects.

Shutdown (SIGTERM, Ctrl-C, ``stop()``) first stops listening, then lets every phone reader drain what
was already received, then closes the bus, so the recorder writes everything that came in.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import os
import re
import socket
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from aiohttp import web

from capture import __version__
from capture.app.orchestrator import DEFAULT_RECONNECT, Capture
from capture.app.serve.discovery import Discovery, FoundService
from capture.app.serve.gateway import CLOSE_TOKEN, Gateway
from capture.app.serve.security import AllowList, TokenStore
from capture.app.serve.tls import Certificate, ensure_certificate
from capture.clock import MONOTONIC, Clock
from capture.errors import CaptureError, ConfigError, SessionExistsError
from devices import DeviceSpec, ReconnectPolicy
from devices.transports.network import Inbox, NetTransport, drop_hub, hub

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping, Sequence

    from capture.app.serve.config import ServeConfig
    from devices.base import Device
    from devices.reader import DeviceReader

log = logging.getLogger(__name__)

#: gateway protocol -> device kind
PHONE_KINDS: dict[str, str] = {"page": "phone", "sensorlogger": "sensorlogger", "osc": "osc", "hyperimu": "hyperimu"}
_NAME_PREFIX = {"page": "phone", "sensorlogger": "sl", "osc": "osc", "hyperimu": "himu"}
_hub_ids = itertools.count()


def default_state_dir(env: Mapping[str, str] | None = None) -> Path:
    env = os.environ if env is None else env
    base = env.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share")
    return Path(base) / "perfcap" / "serve"


def lan_address() -> str:
    """The address other machines on the LAN most likely reach this one at (no packet is sent);
    127.0.0.1 when there is no network."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.connect(("192.0.2.1", 9))  # TEST-NET-1: only picks the outgoing interface
        return str(s.getsockname()[0])
    except OSError:
        return "127.0.0.1"
    finally:
        s.close()


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host and not host.startswith("[") else host



class PhoneDevices:
    """Which device each phone is: created on first sight, the same one on every reconnect.

    A phone holds one of ``max_phones`` slots while it is known. A phone that has gone (its socket
    closed, or nothing from it for ``phone_timeout_s``: datagram and HTTP-push phones have no socket
    to close) gives its slot up: at once when a new phone needs one and every slot is taken (the
    longest gone first), else after ``phone_timeout_s``. Its device then leaves the capture (what it
    recorded stays); if it comes back, it gets the same device again, under the same name and
    continuing its sequence numbers, as long as it is among the last ``max_phones`` released.

    Args:
        capture: the capture phones are added to.
        hub_name: the hub their ``net://`` transports read from.
        names: fixed device names by ``PROTOCOL/ID`` (e.g. ``{"page/5f2c...": "pocket"}``).
        options: device options per protocol (e.g. the OSC address map).
        max_phones: how many phones may hold a slot at once.
        inbox_bytes: each phone's byte budget (what it may have waiting to be decoded).
        phone_timeout_s: how long a phone may be gone or silent before its slot is released.
        clock: when phones were last heard of.
    """

    def __init__(self, capture: Capture, hub_name: str, names: Mapping[str, str] | None = None,
                 options: Mapping[str, Mapping[str, Any]] | None = None, max_phones: int = 32,
                 inbox_bytes: int = 4 << 20, phone_timeout_s: float = 60.0, clock: Clock = MONOTONIC) -> None:
        self.capture = capture
        self.hub = hub(hub_name)
        self.names = dict(names or {})
        self.options = {k: dict(v) for k, v in (options or {}).items()}
        self.max_phones = max_phones
        self.inbox_bytes = inbox_bytes
        self.timeout_ns = int(phone_timeout_s * 1e9)
        self.clock = clock
        self.devices: dict[str, str] = {}  # PROTOCOL/ID -> device name, for the phones holding a slot
        self.peers: dict[str, str] = {}
        self.seen: dict[str, int] = {}     # PROTOCOL/ID -> when last admitted (ns)
        self.released = 0
        self._retired: dict[str, tuple[Device, list[DeviceReader]]] = {}  # released, oldest first
        self._lock = threading.Lock()

    def _name_for(self, protocol: str, remote_id: str) -> str:
        key = f"{protocol}/{remote_id}"
        if key in self.names:
            return self.names[key]
        base = f"{_NAME_PREFIX[protocol]}-" + re.sub(r"[^A-Za-z0-9]", "", remote_id)[:8].lower()
        if protocol in ("osc", "hyperimu"):
            base = f"{_NAME_PREFIX[protocol]}-" + re.sub(r"[^A-Za-z0-9]", "_", remote_id)[:40]
        taken = {d.name for d in self.capture.devices} | {d.name for d, _ in self._retired.values()}
        name, i = base, 2
        while name in taken:
            name, i = f"{base}-{i}", i + 1
        return name

    def admit(self, protocol: str, remote_id: str, peer: str, info: dict[str, Any]) -> tuple[str, Inbox] | None:
        key = f"{protocol}/{remote_id}"
        with self._lock:
            name = self.devices.get(key)
            if name is None:
                if len(self.devices) >= self.max_phones and not self._release_one_gone():
                    return None
                box = self.hub.inbox(key)
                box.max_bytes = self.inbox_bytes
                box.connect(peer)  # before the reader's first open
                box.info = dict(info)
                try:
                    dev = self._device_for(key, protocol, remote_id)
                except CaptureError as exc:
                    log.error("phone %s (%s) cannot be added: %s", key, peer, exc)
                    box.disconnect(str(exc))
                    self.hub.drop(key)
                    return None
                name = dev.name
                self.devices[key] = name
                log.warning("phone %s connected from %s: device %s", key, peer, name)
            else:
                box = self.hub.inbox(key)
                if not box.connected:
                    log.warning("phone %s (device %s) is back, from %s", key, name, peer)
                box.connect(peer)
                box.info = dict(info)
            self.peers[name] = peer
            self.seen[key] = self.clock.now_ns()
            return name, box

    def _device_for(self, key: str, protocol: str, remote_id: str) -> Device:
        old = self._retired.pop(key, None)
        if old is not None:
            dev, readers = old
            if not any(r.alive for r in readers):
                try:
                    return self.capture.add_device(dev)  # the same device: its name and sequence numbers
                except ConfigError:
                    pass  # its name was taken meanwhile: a new device
        spec = DeviceSpec(url=f"net://{self.hub.name}/{key}", kind=PHONE_KINDS[protocol],
                          name=self._name_for(protocol, remote_id), options=dict(self.options.get(protocol, {})))
        return self.capture.add_device(spec)

    def _gone_since(self, key: str, now_ns: int) -> int | None:
        """How long (ns) phone ``key`` has been gone, or None while it is there (connected and heard
        from within the timeout, or still with messages to decode)."""
        box = self.hub.get(key)
        last = max(self.seen.get(key, 0), (box.last_ns or 0) if box is not None else 0)
        if box is None:
            return now_ns - last
        if len(box):
            return None
        if box.connected:
            if now_ns - last < self.timeout_ns:
                return None
            box.disconnect(f"nothing received for {self.timeout_ns / 1e9:g} s")
        return now_ns - last

    def _release_one_gone(self) -> bool:
        now = self.clock.now_ns()
        gone = [(g, k) for k in self.devices if (g := self._gone_since(k, now)) is not None]
        if not gone:
            return False
        self._release(max(gone)[1], "a new phone needed its slot")
        return True

    def _release(self, key: str, why: str) -> None:
        name = self.devices.pop(key)
        self.seen.pop(key, None)
        self.peers.pop(name, None)
        self.hub.drop(key)
        readers = [r for r in self.capture.readers if r.device.name == name]
        dev = self.capture.remove_device(name, timeout=0.0)  # its reader stops on its own thread
        if dev is not None:
            self._retired[key] = (dev, readers)
            while len(self._retired) > self.max_phones:
                del self._retired[next(iter(self._retired))]
        self.released += 1
        log.warning("phone %s (device %s) released its slot: %s", key, name, why)

    def sweep(self) -> list[str]:
        """Release the slots of phones gone longer than the timeout; returns their keys."""
        with self._lock:
            now = self.clock.now_ns()
            out = [k for k in self.devices if (g := self._gone_since(k, now)) is not None and g >= self.timeout_ns]
            for k in out:
                self._release(k, f"gone for {self.timeout_ns / 1e9:g} s")
            return out


@dataclass
class Endpoints:
    """Where the service listens, known once it runs."""

    page_url: str = ""          # without the token
    pair_url: str = ""          # with the token in the fragment
    port: int = 0
    control_url: str = ""
    sensorlogger_url: str = ""
    osc_port: int = 0
    hyperimu_port: int = 0
    hyperimu_tcp_port: int = 0
    fingerprint: str = ""
    certificate_created: bool = False
    advertised: str | None = None
    mdns_error: str | None = None


class Service:
    """The capture service (see the module docstring).

    Args:
        config: what to listen on.
        devices: configured devices (any device string), started with the service.
        reconnect: reconnect policy for every device.
        clock: host clock.
        capture_options: passed to ``Capture`` (recorder bounds and the like).
    """

    def __init__(self, config: ServeConfig, devices: Sequence[DeviceSpec | str] = (), *,
                 reconnect: ReconnectPolicy = DEFAULT_RECONNECT, clock: Clock = MONOTONIC,
                 capture_options: Mapping[str, Any] | None = None) -> None:
        config.check()
        self.config = config
        self.clock = clock
        self.state_dir = Path(config.state_dir) if config.state_dir else default_state_dir()
        self.tokens = TokenStore(self.state_dir, config.token)
        self.capture = Capture(list(devices), allow_empty=True, reconnect=reconnect, clock=clock,
                               **dict(capture_options or {}))
        self.hub_name = f"serve{next(_hub_ids)}"
        opts: dict[str, dict[str, Any]] = {"osc": {"map": config.osc_map},
                                           "hyperimu": {"sensors": config.hyperimu_sensors}}
        self._check_phone_options(opts)
        names = config.phone_name_map()
        taken = {d.name for d in self.capture.devices} & set(names.values())
        if taken:
            self.capture.stop()
            raise ConfigError(f"phone name(s) {', '.join(sorted(taken))} are already names of configured devices")
        limits = config.client_limits()
        self.phones = PhoneDevices(self.capture, self.hub_name, names, opts, config.max_phones,
                                   inbox_bytes=limits.inbox_bytes, phone_timeout_s=limits.phone_timeout_s, clock=clock)
        self.gateway = Gateway(self.phones, self.tokens, limits, clock)
        self.endpoints = Endpoints()
        self.discovery: Discovery | None = None
        self.certificate: Certificate | None = None
        self._runners: list[web.AppRunner] = []
        self._sites: list[web.BaseSite] = []
        self._sweeper: asyncio.Task[None] | None = None
        self._stop: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._t0 = 0
        self.stopped = False
        self.report: Any = None
        #: how the last recording ended (``Capture.stop_recording``'s answer), for the API and status
        self.last_recording: dict[str, Any] | None = None
        self._record_lock = threading.Lock()
        self.capture.on_recording_failed = self._recording_failed

    def _check_phone_options(self, opts: Mapping[str, Mapping[str, Any]]) -> None:
        """Build each enabled token-less protocol's device once, so a bad map or sensor list is an
        error now, not a log line per datagram later."""
        from devices import open_device

        enabled = {"osc": self.config.osc_port, "hyperimu": self.config.hyperimu_port or self.config.hyperimu_tcp_port}
        for proto, on in enabled.items():
            if not on:
                continue
            try:
                open_device(DeviceSpec(url=f"net://check/{proto}/x", kind=PHONE_KINDS[proto], name="check",
                                       options=dict(opts.get(proto, {}))))
            except CaptureError as exc:
                self.capture.stop()
                raise ConfigError(f"{proto}: {exc}") from None

    # -- control ---------------------------------------------------------------------------------
    def sessions_dir(self) -> str:
        """Where sessions given without a path (or with a relative one) go: ``sessions_dir``, else
        ``$XDG_DATA_HOME/perfcap/sessions`` (created, private to the user, on first use)."""
        if self.config.sessions_dir:
            return os.path.realpath(self.config.sessions_dir)
        d = default_state_dir().parent / "sessions"
        try:
            d.mkdir(mode=0o700, parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(f"cannot create the sessions directory {d}: {exc.strerror or exc}") from None
        return os.path.realpath(d)

    def start_recording(self, path: str | None = None, overwrite: bool = False, *, anywhere: bool = False) -> str:
        """Start recording to ``path`` (default: a new ``perfcap-<time>.mcap`` in the sessions
        directory) and return the file's path. Unless ``anywhere`` (the operator's own command line),
        ``path`` is a name inside the sessions directory (relative, or absolute inside it), since every
        paired phone holds the token: it is opened without following links on the way, ``..`` and
        hidden names are refused, it ends in ``.mcap``, and ``overwrite`` replaces only a perfcap
        session (see ``capture.session_file``).

        Raises:
            ConfigError: already recording, or the path is malformed or leaves the sessions directory.
            SessionExistsError: the file exists (and ``overwrite`` is false, or it is no perfcap session).
            SessionError: the file cannot be created.
        """
        meta = {"command": "perfcap serve"}
        if anywhere and path is not None:
            out = self.capture.start_recording(path, overwrite=overwrite, meta=meta)
        elif path is None:
            base = self.sessions_dir()
            stamp = int(MONOTONIC.wall_time_s())
            for i in range(1, 100):  # two takes in one second: -2, -3, ...
                name = f"perfcap-{stamp}.mcap" if i == 1 else f"perfcap-{stamp}-{i}.mcap"
                try:
                    out = self.capture.start_recording(name, meta=meta, base_dir=base)
                    break
                except SessionExistsError:
                    continue
            else:
                raise SessionExistsError(f"perfcap-{stamp}-*.mcap: 99 sessions already exist in {base}", path=base)
        else:
            out = self.capture.start_recording(path, overwrite=overwrite, meta=meta, base_dir=self.sessions_dir())
        log.warning("recording to %s", out)
        return out

    def stop_recording(self) -> dict[str, Any]:
        """Finish the recording; returns ``Capture.stop_recording``'s answer.

        Raises:
            ConfigError: nothing is being recorded (the message says how the last recording ended).
        """
        with self._record_lock:
            try:
                res = self.capture.stop_recording()
            except ConfigError:
                last = self.last_recording
                if last is not None and last.get("error"):
                    raise ConfigError(f"not recording: the last recording, {last['output']}, failed and was"
                                      f" stopped: {last['error']}") from None
                raise
            self.last_recording = res
        if res["error"]:
            log.error("recording %s closed after a failure: %s", res["output"], res["error"])
        else:
            log.warning("recording %s closed", res["output"])
        return res

    def _recording_failed(self, exc: Exception) -> None:
        """The recorder's write failed (called from its thread): stop that recording from another
        thread (the recorder's own cannot wait for itself), say so, and keep serving."""
        rec = self.capture.recorder

        def stop_it() -> None:
            with self._record_lock:
                if self.capture.recorder is not rec or rec is None:
                    return  # stopped meanwhile
                try:
                    res = self.capture.stop_recording()
                except ConfigError:
                    return
                self.last_recording = res
            kept, lost = sum(res["samples"].values()), sum(res["not_saved"].values())
            log.error("recording %s failed (%s) and was stopped: the file keeps %d samples, %d came in after its"
                      " last flush and are not saved; still serving (POST /api/record/start starts another)",
                      res["output"], res["error"], kept, lost)

        threading.Thread(target=stop_it, name="perfcap-serve-record-failed", daemon=True).start()

    async def rotate_token(self) -> str:
        tok = self.tokens.rotate()
        await self.gateway.close_phones(CLOSE_TOKEN, "the pairing token was rotated; pair again")
        self._update_urls()
        return tok

    def devices_info(self) -> list[dict[str, Any]]:
        snap = self.capture.stats.snapshot()
        now = self.clock.now_ns()
        out = []
        for d in list(self.capture.devices):
            h = d.health()
            streams = {s.name: snap.get(s.name, {"samples": 0, "rate_hz": 0.0, "drops": 0}) for s in d.streams}
            box = self.phones.hub.get(d.transport.key) if isinstance(d.transport, NetTransport) else None
            clocks = []
            for cs in d.clock_states():
                clocks.append({"stream": cs.stream, "offset_ms": (cs.host_ref_ns - cs.device_ref_ns) / 1e6,
                               "drift_ppm": round(cs.drift_ppm, 2), "epoch": cs.epoch, "pseudo": cs.pseudo,
                               "points": cs.points})
            last = h.get("last_seen_ns")
            out.append({
                "name": d.name, "kind": d.kind, "url": d.transport.url, "state": h["state"],
                "connected": None if box is None else box.connected, "peer": self.phones.peers.get(d.name),
                "rate_hz": max((s["rate_hz"] for s in streams.values()), default=0.0),
                "samples": sum(s["samples"] for s in streams.values()),
                "drops": {"lost_readings": h.get("lost_readings", 0),
                          "stream_gaps": sum(s["drops"] for s in streams.values()),
                          "protocol_errors": h.get("checksum_errors", 0) + h.get("framing_errors", 0),
                          "queue_refused": 0 if box is None else box.dropped},
                "clock": clocks,
                "last_seen_s_ago": None if last is None else round((now - last) / 1e9, 3),
                "reconnects": h.get("reconnects", 0),
                "streams": streams,
            })
        return out

    def _last_recording_info(self) -> dict[str, Any] | None:
        last = self.last_recording
        if last is None:
            return None
        return {"output": last["output"], "error": last["error"], "saved": sum(last["samples"].values()),
                "not_saved": sum(last["not_saved"].values())}

    def health(self) -> dict[str, Any]:
        return {"status": "ok" if not self.stopped else "stopping", "version": __version__,
                "uptime_s": round((self.clock.now_ns() - self._t0) / 1e9, 3) if self._t0 else 0.0,
                "recording": self.capture.output if self.capture.recorder is not None else None,
                "last_recording": self._last_recording_info(),
                "devices": len(self.capture.devices),
                "phones_connected": sum(1 for b in self.phones.hub.inboxes().values() if b.connected),
                "messages": self.gateway.stats.messages, "rejected": self.gateway.rejected.as_dict(),
                "connections": self._connections_info(),
                "phone_slots": {"max": self.phones.max_phones, "held": len(self.phones.devices),
                                "released": self.phones.released},
                "token_required": True, "tls_fingerprint": self.endpoints.fingerprint,
                "mdns": {"advertised": self.endpoints.advertised, "error": self.endpoints.mdns_error,
                         "found": [f.as_dict() for f in (self.discovery.found.values() if self.discovery else [])]}}

    def _connections_info(self) -> dict[str, int]:
        gate = self.gateway.gate
        if gate is None:
            return {}
        st = gate.stats
        return {"open": gate.open, "handshakes": gate.handshakes, "peak_open": st.peak_open,
                "peak_handshakes": st.peak_handshakes, "accepted": st.accepted, "refused": st.refused,
                "timed_out": st.timed_out, "tls_failed": st.tls_failed}

    def add_sensorserver(self, host: str, port: int, types: str | None = None, name: str | None = None) -> str:
        """Connect to a SensorServer phone (found by mDNS or given by the user); returns the device name."""
        types = types or self.config.sensorserver_types
        h = f"[{host}]" if ":" in host else host
        dev = self.capture.add_device(DeviceSpec(url=f"sensorserver://{h}:{int(port)}?types={types}",
                                                 kind="sensorserver", name=name))
        log.warning("SensorServer %s:%d: device %s", host, port, dev.name)
        return dev.name

    def _on_found(self, found: FoundService) -> None:
        if not found.is_sensorserver:
            return
        if not self.config.connect_sensorserver:
            log.warning("found %s at %s:%d; connect with POST /api/sensorserver (or serve --connect-sensorserver)",
                        found.name, found.addresses[0] if found.addresses else "?", found.port)
            return
        if found.addresses:
            with contextlib.suppress(CaptureError):
                self.add_sensorserver(found.addresses[0], found.port)

    # -- running ---------------------------------------------------------------------------------
    def _update_urls(self) -> None:
        ep = self.endpoints
        if ep.page_url:
            ep.pair_url = f"{ep.page_url}#t={self.tokens.token}"
            scheme = "https" if self.config.tls else "http"
            host = ep.page_url.split("://", 1)[1].split("/", 1)[0]  # HOST:PORT as in the page URL
            ep.sensorlogger_url = f"{scheme}://{host}/ingest/sensorlogger?token={self.tokens.token}"

    async def start(self) -> Endpoints:
        """Start listening (and the configured devices).

        Raises:
            ConfigError: a port is taken, or the certificate cannot be made.
        """
        from capture.app.serve.control import control_app

        cfg = self.config
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self._t0 = self.clock.now_ns()
        public = cfg.public_host or (lan_address() if cfg.host in ("0.0.0.0", "::", "") else cfg.host)
        ssl_ctx = None
        if cfg.tls:
            self.certificate = ensure_certificate(self.state_dir, [public])
            ssl_ctx = self.certificate.server_context()
            self.endpoints.fingerprint = self.certificate.fingerprint
            self.endpoints.certificate_created = self.certificate.created
        self.capture.start()
        try:
            port = await self._site(self.gateway.app(), cfg.host, cfg.port, ssl_ctx, "phone page", gated=True)
            self._sweeper = asyncio.get_running_loop().create_task(self._sweep_phones())
            scheme = "https" if cfg.tls else "http"
            self.endpoints.port = port
            self.endpoints.page_url = f"{scheme}://{_url_host(public)}:{port}/"
            self._update_urls()
            if cfg.control_port >= 0:
                cport = await self._site(control_app(self), cfg.control_host, cfg.control_port, None, "control API")
                self.endpoints.control_url = f"http://{_url_host(cfg.control_host)}:{cport}/api"
                if cfg.control_host not in ("127.0.0.1", "::1", "localhost"):
                    log.warning("the control API listens on %s, not only on this machine; it still needs the token",
                                cfg.control_host)
            if cfg.osc_port:
                self.endpoints.osc_port = await self._bind(self.gateway.start_udp("osc", cfg.host, cfg.osc_port,
                                                                                  AllowList(cfg.osc_allow)), "OSC")
            if cfg.hyperimu_port:
                self.endpoints.hyperimu_port = await self._bind(self.gateway.start_udp(
                    "hyperimu", cfg.host, cfg.hyperimu_port, AllowList(cfg.hyperimu_allow)), "HyperIMU UDP")
            if cfg.hyperimu_tcp_port:
                self.endpoints.hyperimu_tcp_port = await self._bind(self.gateway.start_tcp(
                    "hyperimu", cfg.host, cfg.hyperimu_tcp_port, AllowList(cfg.hyperimu_allow)), "HyperIMU TCP")
            if cfg.mdns:
                props = {"v": __version__, "port": str(port), "token": "1", "path": "/",
                         "tls": "1" if cfg.tls else "0"}
                ep = self.endpoints
                for key, val in (("osc", ep.osc_port), ("hyperimu", ep.hyperimu_port),
                                 ("hyperimu_tcp", ep.hyperimu_tcp_port)):
                    if val:
                        props[key] = str(val)
                if ep.control_url and cfg.control_host not in ("127.0.0.1", "::1", "localhost"):
                    props["control"] = ep.control_url.rsplit(":", 1)[1].split("/", 1)[0]
                ifaces: Any = "all" if cfg.mdns_interfaces == "all" else [
                    i.strip() for i in cfg.mdns_interfaces.split(",") if i.strip()]
                self.discovery = Discovery(None, [public], port, props, interfaces=ifaces, on_found=self._on_found)
                await self.discovery.start()
                self.endpoints.advertised = self.discovery.advertised
                self.endpoints.mdns_error = self.discovery.error
        except BaseException:
            await self._close_network()
            self.capture.stop()
            raise
        return self.endpoints

    async def _bind(self, coro: Any, what: str) -> int:
        try:
            return int(await coro)
        except OSError as exc:
            raise ConfigError(f"cannot listen for {what}: {exc}") from None

    async def _sweep_phones(self) -> None:
        """Give up the slots of phones gone longer than the phone timeout, every few seconds."""
        period = min(5.0, self.gateway.limits.phone_timeout_s / 4)
        while True:
            await asyncio.sleep(period)
            try:
                self.phones.sweep()
            except CaptureError as exc:
                log.error("releasing the slots of phones that left: %s", exc)

    async def _site(self, app: web.Application, host: str, port: int, ssl_ctx: Any, what: str,
                    gated: bool = False) -> int:
        keepalive = self.gateway.limits.idle_timeout_s if gated else 75.0
        runner = web.AppRunner(app, access_log=None, handle_signals=False, shutdown_timeout=2.0,
                               keepalive_timeout=keepalive)
        await runner.setup()
        self._runners.append(runner)
        site: web.BaseSite
        if gated:  # the phone port: connections capped, TLS run by the gate, handshakes timed out
            site = self.gateway.site(runner, host, port, ssl_ctx)
        else:
            site = web.TCPSite(runner, host, port, ssl_context=ssl_ctx, backlog=128)
        self._sites.append(site)
        try:
            await site.start()
        except OSError as exc:
            raise ConfigError(f"cannot listen for the {what} on {host}:{port}: {exc.strerror or exc} "
                              f"(choose another port)") from None
        server = site._server  # the bound socket tells the real port when 0 was asked for
        socks = getattr(server, "sockets", None) or []
        return int(socks[0].getsockname()[1]) if socks else port

    def request_stop(self) -> None:
        """Ask a running service to stop (thread-safe)."""
        loop = self._loop
        if loop is not None and self._stop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self._stop.set)
            except RuntimeError:  # the loop closed in between: the service has stopped already
                pass

    async def wait(self) -> None:
        assert self._stop is not None
        await self._stop.wait()

    async def _close_network(self) -> None:
        # First stop accepting (a phone reconnecting right now must not slip in), then close the
        # phones' sockets, then wait for their handlers.
        if self._sweeper is not None:
            self._sweeper.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._sweeper
            self._sweeper = None
        for site in self._sites:
            with contextlib.suppress(Exception):
                await site.stop()
        self._sites = []
        with contextlib.suppress(Exception):
            await self.gateway.stop()
        if self.discovery is not None:
            await self.discovery.stop()
        for r in self._runners:
            with contextlib.suppress(Exception):
                await r.cleanup()
        if self._runners:
            # TLS connections close with a close_notify exchange: give the peers a moment, or the
            # loop ends first and their sockets are left to the garbage collector
            await asyncio.sleep(0.25)
        self._runners = []
        if self.gateway.gate is not None:
            self.gateway.gate.close_all()  # whatever the handlers did not close (a handshake cut short)
        self._close_stragglers()

    def _close_stragglers(self) -> None:
        """Close connections on our ports that no handler owns: a browser's speculative connection
        still in its TLS handshake is accepted by asyncio but never reaches aiohttp, and
        ``Server.close()`` leaves it open (Python < 3.13 has no ``Server.close_clients``)."""
        ports = {p for p in (self.endpoints.port, self.endpoints.hyperimu_tcp_port) if p}
        if self.endpoints.control_url:
            with contextlib.suppress(ValueError):
                ports.add(int(self.endpoints.control_url.rsplit(":", 1)[1].split("/", 1)[0]))
        transports = getattr(asyncio.get_running_loop(), "_transports", None)  # selector loops keep them
        if not ports or transports is None:
            return
        for t in list(transports.values()):
            try:
                if t is not None and not t.is_closing() and (t.get_extra_info("sockname") or (None, None))[1] in ports:
                    t.close()
            except (AttributeError, OSError, IndexError, TypeError):
                continue

    async def stop(self) -> Any:
        """Stop listening, drain what phones sent, stop devices, close the recording. Returns the
        capture report."""
        if self.stopped:
            return self.report
        self.stopped = True
        await self._close_network()
        box_hub = self.phones.hub
        box_hub.finish_all()  # readers drain their inboxes, then end
        readers = [r for r in self.capture.readers if isinstance(r.device.transport, NetTransport)]
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(None, lambda: [r.join(10.0) for r in readers])
        for key, box in box_hub.inboxes().items():
            if len(box):  # a reader that did not finish in time: say what it leaves unrecorded
                log.error("phone %s: %d received message(s) not decoded before shutdown (reader too slow)",
                          key, len(box))
        self.report = await loop.run_in_executor(None, self.capture.stop)
        drop_hub(self.hub_name)
        return self.report

    async def run(self, on_ready: Callable[[Service], None] | None = None) -> Any:
        """Start, wait until ``request_stop()`` (or a signal handler) says stop, then stop."""
        try:
            await self.start()
            if on_ready is not None:
                on_ready(self)
            await self.wait()
        finally:
            report = await self.stop()
        return report


class ServiceThread:
    """A service on its own event loop in a background thread (the demo and tests use it).

    ``start()`` returns once it listens (or raises what stopped it); ``stop()`` stops it gracefully.
    """

    def __init__(self, service: Service) -> None:
        self.service = service
        self._ready = threading.Event()
        self.error: BaseException | None = None
        self.report: Any = None
        self._thread = threading.Thread(target=self._main, name="perfcap-serve", daemon=True)

    def _main(self) -> None:
        async def body() -> None:
            try:
                self.report = await self.service.run(on_ready=lambda s: self._ready.set())
            finally:
                self._ready.set()

        try:
            asyncio.run(body())
        except BaseException as exc:
            self.error = exc
            self._ready.set()

    def start(self, timeout: float = 20.0) -> ServiceThread:
        self._thread.start()
        if not self._ready.wait(timeout):
            raise CaptureError("perfcap serve did not start in time")
        if self.error is not None:
            raise self.error
        return self

    def stop(self, timeout: float = 30.0) -> Any:
        if not self._thread.is_alive():
            return self.report
        self.service.request_stop()
        self._thread.join(timeout)
        if self.error is not None and not isinstance(self.error, CaptureError):
            raise self.error
        return self.report
