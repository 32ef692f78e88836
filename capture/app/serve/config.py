"""The one definition of ``perfcap serve``'s settings: ``ServeConfig``.

Every field made with ``capture.app.schema.setting`` is a ``[serve]`` key in a config file, a
``PERFCAP_SERVE_<KEY>`` environment variable and a ``perfcap serve`` flag (``--osc-port``;
``--no-tls`` for a setting on by default, ``--connect-sensorserver`` for one off by default); its
type, default, help, range and choices are written once, here, and the file schema
(``capture.app.config``) and the flags (``capture.app.schema.add_flags``) are derived from them.

The few fields that are not settings (a fixed token, exact ``Limits``, fixed names) are for programs
that build a service in code (tests, the demo).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from capture.app.schema import parse_value, setting, setting_fields
from capture.errors import ConfigError

#: a host name or an address: what may go in URLs and the certificate
#: the protocols whose phones ``phone_names`` can name (``capture.app.serve.service.PHONE_KINDS``)
PHONE_PROTOCOLS = ("page", "sensorlogger", "osc", "hyperimu")
#: a device name (``devices._NAME_RE``)
_DEVICE_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_\-]{0,63}$")
_PUBLIC_HOST_RE = re.compile(r"^[A-Za-z0-9.\-:]{1,253}$")
#: the port of a bare ``--foxglove`` (``perfcap serve`` and ``record``): the Foxglove app's default
FOXGLOVE_PORT = 8765


@dataclass
class Limits:
    """Bounds per client. ``rate_hz`` and ``burst`` are messages per second per phone (its id, kept
    across reconnects); a source address may send ``max_connections_per_host`` times that. What a phone
    may have waiting to be decoded is bounded in bytes (``inbox_bytes``). ``Limits()`` are the limits the
    default settings give (``ServeConfig().client_limits()``)."""

    max_message_bytes: int = 64 * 1024   # WebSocket and UDP messages
    max_push_bytes: int = 4 << 20        # one Sensor Logger POST (a batch period of every sensor)
    rate_hz: float = 200.0
    burst: float = 400.0
    max_connections: int = 64            # paired WebSockets in total: 2 x max_phones
    max_connections_per_host: int = 4    # paired WebSockets (and HyperIMU TCP sockets) per address
    hello_timeout_s: float = 3.0
    max_pending_hello: int = 64    # connections waiting for their hello, in total
    max_malformed: int = 20        # per connection before it is closed
    ping_s: float = 1.0
    inbox_bytes: int = 4 << 20     # per phone: received, not yet decoded (beyond: refused, closed with 4429)
    byte_rate: float = float(1 << 20)  # bytes per second per phone (an address: max_connections_per_host x)
    byte_burst: float = float(4 << 20)  # at least the largest message or push
    max_sockets: int = 256         # TCP connections the phone port holds, in any state
    max_sockets_per_host: int = 16
    max_handshakes: int = 64       # connections in their TLS + HTTP handshake, in total
    handshake_timeout_s: float = 10.0   # accept to first HTTP request (TLS included)
    idle_timeout_s: float = 30.0   # an HTTP connection with no request in flight
    phone_timeout_s: float = 60.0  # a phone gone (or silent) this long gives up its slot



@dataclass
class ServeConfig:
    """Everything ``perfcap serve`` listens on and how."""

    host: str = setting("0.0.0.0", "address the phone endpoints listen on (default all)")
    port: int = setting(8443, "phone page / WebSocket / Sensor Logger port (HTTPS)", min=0, max=65535)
    public_host: str = setting("", "address phones use to reach this machine (default: detected LAN address)")
    tls: bool = setting(True, "serve the phone endpoints over HTTPS (browsers give motion sensors only to secure"
                        " pages)", flag_help="plain HTTP (browsers then refuse motion sensors)")
    control_host: str = setting("127.0.0.1", "control API address (default loopback only)")
    control_port: int = setting(8780, "control API port (-1: none)", min=-1, max=65535)
    state_dir: str = setting("", "where the token and certificate are kept (default $XDG_DATA_HOME/perfcap/serve)")
    sessions_dir: str = setting("", "the only directory POST /api/record/start writes sessions in (default"
                                " $XDG_DATA_HOME/perfcap/sessions)")
    mdns: bool = setting(True, "advertise the service and browse for SensorServer phones with mDNS",
                         flag_help="do not advertise or browse with mDNS")
    mdns_interfaces: str = setting("all", "interfaces mDNS uses: all, or comma-separated interface addresses")
    connect_sensorserver: bool = setting(False, "connect to SensorServer phones found by mDNS without asking")
    sensorserver_types: str = setting("accelerometer,gyroscope", "the sensors asked of SensorServer phones")
    osc_port: int = setting(0, "OSC UDP port (ZIG SIM, GyrOSC); off by default", min=0, max=65535)
    osc_allow: str = setting("", "addresses allowed to send OSC (needed with --osc-port)")
    osc_map: str = setting("zigsim", "OSC address map: zigsim, gyrosc or a custom map")
    hyperimu_port: int = setting(0, "HyperIMU UDP port; off by default", min=0, max=65535)
    hyperimu_tcp_port: int = setting(0, "HyperIMU TCP port; off by default", min=0, max=65535)
    hyperimu_allow: str = setting("", "addresses allowed to send HyperIMU CSV")
    hyperimu_sensors: str = setting("accelerometer,gyroscope,magnetometer",
                                    "HyperIMU's enabled sensors, in the app's order")
    phone_names: str = setting("", "a fixed device name for a phone (e.g. page/5f2c0a...=pocket)",
                               flag="--phone-name", metavar="PROTOCOL/ID=NAME", repeat=True)
    max_phones: int = setting(32, "phone devices the service may create (default 32)", min=1, max=10_000)
    max_message_kb: int = setting(64, "largest message accepted (KiB)", min=1, max=1 << 20)
    max_push_mb: int = setting(4, "largest Sensor Logger push accepted (MiB)", min=1, max=1024)
    max_rate: float = setting(200.0, "messages per second per phone (an address: max_connections_per_host times"
                              " that)", min=0.1, max=1e6)
    max_rate_kb: int = setting(1024, "KiB per second per phone (an address: max_connections_per_host times that)",
                               min=1, max=1 << 30)
    max_connections_per_host: int = setting(4, "paired phone connections one address may hold open", min=1,
                                            max=10_000)
    max_inbox_mb: int = setting(4, "what one phone may have waiting to be decoded (MiB); beyond it its messages"
                                " are refused and its connection closed (4429)", min=1, max=1024)
    max_sockets: int = setting(256, "TCP connections the phone port holds, in any state", min=1, max=100_000)
    max_sockets_per_host: int = setting(16, "TCP connections one address may hold on the phone port", min=1,
                                        max=100_000)
    max_handshakes: int = setting(64, "connections in their TLS and HTTP handshake at once", min=1, max=100_000)
    handshake_timeout_s: float = setting(10.0, "seconds from connecting to the first HTTP request, TLS included",
                                         min=0.1, max=3600.0)
    idle_timeout_s: float = setting(30.0, "seconds an HTTP connection may stay open with no request", min=0.1,
                                    max=86_400.0)
    phone_timeout_s: float = setting(60.0, "seconds a phone may be gone or silent before its slot is given to"
                                     " another phone", min=1.0, max=86_400.0)
    foxglove: int = setting(-1, f"the Foxglove app's live WebSocket server on this port (a bare --foxglove:"
                            f" {FOXGLOVE_PORT}; 0: any free port; -1: off)", min=-1, max=65535, metavar="PORT")
    foxglove_host: str = setting("127.0.0.1", "address the Foxglove server listens on (default loopback only;"
                                 " it has no authentication)")
    lsl: bool = setting(False, "publish every stream (phones included) as a Lab Streaming Layer outlet")
    # -- not settings: for a service built in code ---------------------------------------------------
    token: str | None = None        # a fixed token (tests); None = the stored one
    limits: Limits | None = None    # exact limits; None = from the max_* settings
    names: dict[str, str] = field(default_factory=dict)   # fixed names besides phone_names

    def phone_name_map(self) -> dict[str, str]:
        """``phone_names`` (``PROTOCOL/ID=NAME,...``) and ``names``, by ``PROTOCOL/ID``.

        Raises:
            ConfigError: a phone name entry is malformed: not PROTOCOL/ID=NAME, an unknown protocol, a
                name that is no device name, or a phone or a name given twice.
        """
        out: dict[str, str] = {}
        for item in (i.strip() for i in self.phone_names.split(",")):
            if not item:
                continue
            key, sep, name = item.partition("=")
            key, name = key.strip(), name.strip()
            protocol, slash, remote = key.partition("/")
            if not sep or not slash or not remote.strip() or not name:
                raise ConfigError(f"phone name {item!r}: expected PROTOCOL/ID=NAME, e.g. page/5f2c0a=pocket")
            if protocol not in PHONE_PROTOCOLS:
                raise ConfigError(f"phone name {item!r}: unknown protocol {protocol!r}; expected one of"
                                  f" {', '.join(PHONE_PROTOCOLS)}")
            if not _DEVICE_NAME_RE.match(name):
                raise ConfigError(f"phone name {item!r}: the name must start with a letter and use letters, digits,"
                                  " _ or - (at most 64)")
            if key in out or name in out.values():
                raise ConfigError(f"phone name {item!r}: {'that phone' if key in out else 'that name'} is named"
                                  " twice")
            out[key] = name
        out.update(self.names)
        return out

    def client_limits(self) -> Limits:
        """``limits``, or the limits the ``max_*`` settings give."""
        if self.limits is not None:
            return self.limits
        return Limits(max_message_bytes=self.max_message_kb * 1024, max_push_bytes=self.max_push_mb << 20,
                      rate_hz=self.max_rate, burst=max(self.max_rate * 2, 1.0), max_connections=self.max_phones * 2,
                      max_connections_per_host=self.max_connections_per_host, inbox_bytes=self.max_inbox_mb << 20,
                      byte_rate=float(self.max_rate_kb << 10),
                      byte_burst=float(max(2 * (self.max_rate_kb << 10), self.max_push_mb << 20,
                                           self.max_message_kb << 10)),
                      max_sockets=self.max_sockets, max_sockets_per_host=self.max_sockets_per_host,
                      max_handshakes=self.max_handshakes, handshake_timeout_s=self.handshake_timeout_s,
                      idle_timeout_s=self.idle_timeout_s, phone_timeout_s=self.phone_timeout_s)

    def check(self) -> None:
        """Every setting within its type and range, and the combinations that need each other.

        Raises:
            ConfigError: the first problem found.
        """
        from capture.app.serve.security import AllowList

        for f, opt in setting_fields(ServeConfig):
            parse_value(opt, f"serve.{f.name}", getattr(self, f.name), "serve settings", from_text=False)
        if self.public_host and not _PUBLIC_HOST_RE.match(self.public_host):
            raise ConfigError(f"public host {self.public_host!r} is not a host name or address (ASCII letters, digits,"
                              " '.', '-', ':')")
        if self.osc_port and not AllowList(self.osc_allow):
            raise ConfigError("OSC cannot carry a pairing token, so --osc-port needs --osc-allow with the phones' "
                              "addresses (e.g. --osc-allow 192.168.1.23 or 192.168.1.0/24)")
        if (self.hyperimu_port or self.hyperimu_tcp_port) and not AllowList(self.hyperimu_allow):
            raise ConfigError("HyperIMU cannot carry a pairing token, so --hyperimu-port needs --hyperimu-allow with "
                              "the phones' addresses (e.g. --hyperimu-allow 192.168.1.23)")
        if self.max_sockets_per_host <= self.max_connections_per_host:
            raise ConfigError(f"--max-sockets-per-host ({self.max_sockets_per_host}) must be more than"
                              f" --max-connections-per-host ({self.max_connections_per_host}): a phone needs a"
                              " connection for its page besides its WebSocket")
        self.phone_name_map()


