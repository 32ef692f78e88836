"""Live to Foxglove: the bus on the Foxglove SDK's WebSocket server (``--foxglove[=PORT]`` of record and
serve), so the Foxglove app plots the live data and shows the 3D scene while the take runs.

What goes out is what the session writer records beside its lossless blocks (``capture.session_view``),
with the same schemas: ``/view/<stream>`` (a message per sample), ``/tf/<stream>`` (orientations and
skeletons as transforms) and ``/log`` (the event log). A message's log time is its bus time on the wall
clock: bus time plus the host-to-wall offset, taken once when the publisher starts and exactly as
``SessionWriter`` takes it (from the capture's ``Clock``); per channel it never goes back (a clock
reset that steps bus times back holds the log time, as in a session).

A stream's channels are made on its first item, from its ``StreamInfo`` as the capture declares it to
the recorder (a device's streams, a processor's outputs; a phone paired later is asked of the capture
then); its place in the 3D view follows the order in which orientation streams first send data
(``session_view.Placement``), as in a session. A stream the capture does not
know is published with generic channel names, as the recorder records it.

The publisher is a live subscriber (``Overflow.KEEP_NEWEST``): under overload the bus discards its
oldest items and counts them in the capture report, like the other live consumers; the recorder never
waits for it. The server also keeps at most a backlog of messages per connected app and drops the
oldest beyond it (the SDK's own bound).

The server listens on loopback unless told otherwise; it has no authentication, so binding another
address shows the live data to anyone who can reach the port (said with a warning). A port in use or
an address that cannot be bound is a one-line ``ConfigError``. This is the only module importing the
SDK (``foxglove``, from ``foxglove-sdk``).
"""

from __future__ import annotations

import ipaddress
import logging
import threading
from typing import TYPE_CHECKING, Any

import foxglove

from capture.app.serve.config import FOXGLOVE_PORT
from capture.bus import Overflow, Subscriber, Subscription
from capture.errors import ConfigError
from capture.sample import DeviceEvent, DeviceIdentity, Sample, SampleBatch, StreamInfo
from capture.session_view import LOG, LOG_TOPIC, Placement, encode_event, stream_views

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable

    from capture.app.orchestrator import Capture
    from capture.clock import Clock
    from capture.proto import ProtoSchema
    from capture.session_view import Encoded, ViewChannel

log = logging.getLogger(__name__)

#: where the server listens unless told otherwise
LOOPBACK = "127.0.0.1"
#: the live subscriber's queue: items waiting beyond it are discarded, oldest first, and counted
LIVE_QUEUE = 8192
#: how long stopping waits for the server to close its connections
STOP_TIMEOUT_S = 2.0
#: what the Foxglove app shows as the server's name
SERVER_NAME = "perfcap"
#: how to open it, said beside the URL
HOW_TO_OPEN = "in the Foxglove app (Open connection -> Foxglove WebSocket)"


def parse_port(text: str, flag: str = "--foxglove") -> int:
    """A ``--foxglove`` port from the command line: 0 (any free port) to 65535.

    Raises:
        ConfigError: not an integer in that range, naming the flag.
    """
    try:
        port = int(text.strip())
    except ValueError:
        raise ConfigError(f"{flag}={text!r}: expected a port number (0 = any free port)") from None
    if not 0 <= port <= 65535:
        raise ConfigError(f"{flag}={port}: a port is 0 (any free port) to 65535")
    return port


def is_loopback(host: str) -> bool:
    """``host`` is reachable from this machine only (``localhost`` or a loopback address)."""
    if host.strip().lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def ws_url(host: str, port: int) -> str:
    """The URL the Foxglove app connects to (a wildcard address is reached on loopback from here)."""
    h = host.strip("[]")
    if h in ("", "0.0.0.0"):
        h = LOOPBACK
    elif h == "::":
        h = "::1"
    return f"ws://[{h}]:{port}" if ":" in h else f"ws://{h}:{port}"


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text.removeprefix("FoxgloveError: ")


class FoxgloveServer:
    """The SDK's WebSocket server with a context of its own (so two captures in one process, or any
    other use of the SDK, never see each other's channels), listening from construction.

    Args:
        host: the address to listen on (default loopback; anything else is unauthenticated: warned).
        port: the port; 0 = any free port (``port`` then says which).

    Raises:
        ConfigError: the port is in use, or the address cannot be bound.
    """

    def __init__(self, host: str = LOOPBACK, port: int = FOXGLOVE_PORT) -> None:
        if not 0 <= port <= 65535:
            raise ConfigError(f"Foxglove server: port {port} is not 0 (any free port) to 65535")
        self.host = host
        self.context = foxglove.Context()
        try:
            self._server: Any = foxglove.start_server(name=SERVER_NAME, host=host, port=port, context=self.context)
        except (RuntimeError, OSError, ValueError) as exc:
            raise ConfigError(f"cannot listen for the Foxglove server on {host}:{port}: {_one_line(exc)}"
                              " (choose another port with --foxglove=PORT, or 0 for any free port)") from None
        self.port = int(self._server.port)
        self.url = ws_url(host, self.port)
        self._lock = threading.Lock()
        self.stopped = False
        if not is_loopback(host):
            log.warning("the Foxglove server listens on %s:%d with no authentication: anyone who can reach that"
                        " port sees the live data", host, self.port)

    def channel(self, topic: str, schema: ProtoSchema, metadata: dict[str, str] | None = None) -> foxglove.Channel:
        """A protobuf channel with ``schema`` (its name and ``FileDescriptorSet``) on this server."""
        return foxglove.Channel(topic, message_encoding="protobuf",
                                schema=foxglove.Schema(name=schema.name, encoding="protobuf", data=schema.data),
                                context=self.context, metadata=dict(metadata or {}))

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> None:
        """Stop listening and close every connection (once; later calls do nothing). An app that is
        connected but not reading can hold the SDK's close; after ``timeout_s`` the stop goes on in the
        background and perfcap does not wait for it (said once), so the capture still ends."""
        with self._lock:
            if self.stopped:
                return
            self.stopped = True
        t = threading.Thread(target=self._server.stop, name="foxglove-stop", daemon=True)
        t.start()
        t.join(timeout_s)
        if t.is_alive():
            log.warning("the Foxglove server did not close within %.0f s (a connected app that stopped reading?);"
                        " perfcap ends without waiting for it", timeout_s)


class _Live:
    """One viewable channel on the server: its SDK channel, how a batch becomes its messages, and the
    last log time it sent (log times never go back on a channel)."""

    __slots__ = ("channel", "encode", "last", "topic")

    def __init__(self, channel: foxglove.Channel, topic: str, encode: Callable[[SampleBatch, int], Encoded]) -> None:
        self.channel = channel
        self.topic = topic
        self.encode = encode
        self.last = 0


class FoxglovePublisher(Subscriber):
    """A bus subscriber publishing samples and events on a ``FoxgloveServer`` (see the module's docstring).

    Args:
        server: the listening server; it is stopped with the publisher (``stop``).
        clock: the capture's clock (the bus times' clock; the offset to the wall clock is read from it once).
        streams: the capture's streams known now, in the order the capture declares them to the recorder.
        lookup: asked for the ``StreamInfo`` of a stream first seen in the data (None: unknown).
    """

    accepts = frozenset({Sample, SampleBatch, DeviceEvent})

    def __init__(self, server: FoxgloveServer, clock: Clock, streams: Iterable[StreamInfo] = (), *,
                 lookup: Callable[[str], StreamInfo | None] | None = None) -> None:
        self.server = server
        self.clock = clock
        self.lookup = lookup
        #: UTC ns = bus ns + this (as ``SessionWriter.log_time_offset_ns``)
        self.offset_ns = round(clock.wall_time_s() * 1e9) - clock.now_ns()
        self._views: dict[str, list[ViewChannel]] = {}
        self._placement = Placement()   # where orientation frames sit in the 3D view
        self._live: dict[str, list[_Live]] = {}
        self._log = _Live(server.channel(LOG_TOPIC, LOG), LOG_TOPIC, _no_encode)
        self._failed: set[str] = set()
        #: messages sent per topic
        self.sent: dict[str, int] = {}
        for info in streams:
            self.declare(info)

    @property
    def url(self) -> str:
        return self.server.url

    def declare(self, info: StreamInfo) -> None:
        """Note a stream's views now (its channels are made on its first item); a stream already
        declared keeps its views."""
        if info.name in self._views:
            return
        views = stream_views(info, self._placement)
        self._views[info.name] = views

    def _channels(self, item: Sample | SampleBatch) -> list[_Live]:
        name = item.stream
        views = self._views.get(name)
        if views is None:
            info = self.lookup(name) if self.lookup is not None else None
            if info is None:
                n = len(item.values) if isinstance(item, Sample) else (
                    int(item.values.shape[1]) if item.values.ndim == 2 else 1)
                log.warning("foxglove: stream %s was not declared; publishing it with generic channel names", name)
                info = StreamInfo(name, "unknown", tuple(f"c{i}" for i in range(n)), ("?",) * n, None,
                                  DeviceIdentity(kind="unknown", name=name.split("/")[0]))
            self.declare(info)
            views = self._views[name]
        live = self._live[name] = [_Live(self.server.channel(v.topic, v.schema, v.metadata), v.topic, v.encode)
                                   for v in views]
        return live

    def _send(self, ch: _Live, t_bus_ns: int, data: bytes) -> None:
        t = max(t_bus_ns + self.offset_ns, ch.last, 0)
        ch.last = t
        ch.channel.log(data, log_time=t)
        self.sent[ch.topic] = self.sent.get(ch.topic, 0) + 1

    def on_item(self, item: Any) -> None:
        if type(item) is DeviceEvent:
            self._send(self._log, item.t_host_ns, encode_event(item, self.offset_ns))
            return
        live = self._live.get(item.stream)
        if live is None:
            live = self._channels(item)
        batch = item if type(item) is SampleBatch else SampleBatch.from_samples(item.stream, [item], len(item.values))
        if not len(batch):
            return
        for ch in live:
            try:
                encoded = ch.encode(batch, self.offset_ns)
            except (ValueError, TypeError, IndexError) as exc:  # a batch that does not fit its stream's views
                if ch.topic not in self._failed:
                    self._failed.add(ch.topic)
                    log.error("foxglove: %s: %s: %s (its messages are left out)", ch.topic, type(exc).__name__, exc)
                continue
            for t, data in encoded:
                self._send(ch, t, data)

    def stop(self) -> None:
        """The bus is closing: close the channels and stop the server."""
        self.close()

    def close(self) -> None:
        for chans in list(self._live.values()):
            for ch in chans:
                ch.channel.close()
        self._log.channel.close()
        self.server.stop()


def _no_encode(batch: SampleBatch, offset_ns: int) -> Encoded:  # /log is written from events, never batches
    return []


def publish_capture(cap: Capture, server: FoxgloveServer, *,
                    max_items: int = LIVE_QUEUE) -> tuple[FoxglovePublisher, Subscription]:
    """Publish a capture's bus on ``server``: subscribed now, as a live (``KEEP_NEWEST``) subscriber
    named ``foxglove``; the server stops when the capture does. Subscribe after the processors are added
    (``enable_orientation``), so their streams are known from the start.
    If subscribing fails, the server is stopped."""
    try:
        pub = FoxglovePublisher(server, cap.clock, cap.streams(), lookup=cap.stream_info)
        sub = cap.bus.subscribe(pub, policy=Overflow.KEEP_NEWEST, name="foxglove", max_items=max_items)
    except BaseException:
        server.stop()
        raise
    return pub, sub


def start(cap: Capture, host: str = LOOPBACK, port: int = FOXGLOVE_PORT) -> FoxglovePublisher:
    """A Foxglove server on ``host:port`` publishing ``cap`` (see :func:`publish_capture`).

    Raises:
        ConfigError: the port is in use, or the address cannot be bound.
    """
    pub, _ = publish_capture(cap, FoxgloveServer(host, port))
    return pub
