"""The ``net://`` transport: phones that stream to perfcap through ``perfcap serve``.

``net://HUB/PROTOCOL/ID`` is the transport of a phone that *sends to* perfcap (the built-in page over
a WebSocket, Sensor Logger's HTTP push, OSC or HyperIMU datagrams). The network side lives in
``perfcap serve`` (``capture.app.serve.gateway``): it authenticates each message, stamps it with the host
monotonic time of its arrival and puts it, as one ``Chunk``, into the phone's ``Inbox`` on a ``Hub``.
The phone's device reader takes chunks out through this transport, like bytes from a serial port.
A phone that drops off (socket closed) makes ``read`` fail once its queued messages are drained, so
the reader's reconnect policy applies unchanged: the phone comes back under the same device, stream
names and sequence numbering when it reconnects with the same id.

The other direction, the SensorServer app's WebSocket server that perfcap connects to, is
``devices.transports.sensorserver``.
"""

from __future__ import annotations

import collections
import logging
import threading
from typing import TYPE_CHECKING, Any, ClassVar

from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError, DeviceIOError, DeviceNotFoundError, EndOfStream
from devices.transports.base import Transport

if TYPE_CHECKING:
    from capture.sample import Chunk
    from devices.options import Option

log = logging.getLogger(__name__)


#: what a queued chunk costs besides its bytes (the Chunk, its bytes object, the deque slot), so that
#: many tiny messages are bounded by the byte budget as well as a few large ones
CHUNK_OVERHEAD = 160


class Inbox:
    """Messages received for one remote device, waiting for its reader thread.

    Bounded in bytes: what is queued and not yet read (each chunk's bytes plus ``CHUNK_OVERHEAD``) stays
    within ``max_bytes``, except that an empty inbox always takes one message (whose size the sender's
    own bound limits). A message beyond the budget is refused by ``put`` (counted in ``dropped`` and
    ``dropped_bytes``, and logged), never an unbounded queue; the caller decides what the sender hears.
    """

    def __init__(self, key: str, max_chunks: int = 65536, label: str | None = None,
                 max_bytes: int = 64 << 20) -> None:
        self.key = key
        self.label = label or key  # PROTOCOL/ID, for messages
        self.max_chunks = max_chunks
        self.max_bytes = max_bytes
        self.queued_bytes = 0
        self.dropped_bytes = 0
        self.last_ns: int | None = None  # arrival time of the newest message put
        self.released = False            # its phone's slot was given up: the sender must be admitted again
        self._q: collections.deque[Chunk] = collections.deque()
        self._cv = threading.Condition(threading.Lock())
        self._waiting = False
        self.connected = False
        self.finished = False
        self.peer: str | None = None
        self.reason = "not connected yet"
        self.received = 0
        self.dropped = 0
        self.connects = 0
        self.info: dict[str, Any] = {}

    def connect(self, peer: str | None) -> None:
        """The remote end is there (a socket opened, a first datagram came)."""
        with self._cv:
            self.connected = True
            self.finished = False
            self.peer = peer
            self.connects += 1
            self._cv.notify_all()

    def disconnect(self, reason: str) -> None:
        """The remote end went away; the reader sees it after draining what was received."""
        with self._cv:
            self.connected = False
            self.reason = reason
            self._cv.notify_all()

    def finish(self) -> None:
        """No more messages will come (the service is shutting down): the reader drains and ends."""
        with self._cv:
            self.finished = True
            self.connected = False
            self.reason = "the service stopped"
            self._cv.notify_all()

    def put(self, chunk: Chunk) -> bool:
        """Queue a received message; False (counted) when it would exceed the byte budget or the count."""
        cost = len(chunk.data) + CHUNK_OVERHEAD
        with self._cv:
            q = self._q
            if q and (self.queued_bytes + cost > self.max_bytes or len(q) >= self.max_chunks):
                self.dropped += 1
                self.dropped_bytes += len(chunk.data)
                if self.dropped == 1 or self.dropped % 1000 == 0:
                    log.error("%s: %d message(s) refused so far: %d bytes waiting to be decoded, budget %d"
                              " (the reader is behind what the phone sends)", self.key, self.dropped,
                              self.queued_bytes, self.max_bytes)
                return False
            q.append(chunk)
            self.queued_bytes += cost
            self.last_ns = chunk.t_ns
            self.received += 1
            if self._waiting:
                self._cv.notify()
            return True

    def __len__(self) -> int:
        return len(self._q)

    def get(self, timeout: float) -> Chunk | None:
        """The next message, or None after ``timeout`` seconds.

        Raises:
            EndOfStream: the inbox was finished and is empty.
            DeviceIOError: the remote end is disconnected and everything it sent has been read.
        """
        with self._cv:
            q = self._q
            if q:
                return self._pop()
            if self.finished:
                raise EndOfStream(f"{self.key}: {self.reason}", source=self.key)
            if not self.connected:
                raise DeviceIOError(self.not_connected(), source=self.key)
            self._waiting = True
            try:
                self._cv.wait(timeout)
            finally:
                self._waiting = False
            if q:
                return self._pop()
            if self.finished:
                raise EndOfStream(f"{self.key}: {self.reason}", source=self.key)
            if not self.connected:
                raise DeviceIOError(self.not_connected(), source=self.key)
            return None

    def _pop(self) -> Chunk:
        c = self._q.popleft()
        self.queued_bytes -= len(c.data) + CHUNK_OVERHEAD
        return c

    def not_connected(self) -> str:
        return f"phone {self.label} is not connected ({self.reason})"


class Hub:
    """The inboxes of one service, by ``PROTOCOL/ID``."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._boxes: dict[str, Inbox] = {}
        self._lock = threading.Lock()

    def inbox(self, key: str) -> Inbox:
        with self._lock:
            box = self._boxes.get(key)
            if box is None:
                box = self._boxes[key] = Inbox(f"{self.name}/{key}", label=key)
            return box

    def get(self, key: str) -> Inbox | None:
        return self._boxes.get(key)

    def drop(self, key: str) -> Inbox | None:
        """Forget ``key``'s inbox (its phone's slot was released); marked ``released`` for whoever holds it."""
        with self._lock:
            box = self._boxes.pop(key, None)
        if box is not None:
            box.released = True
        return box

    def inboxes(self) -> dict[str, Inbox]:
        with self._lock:
            return dict(self._boxes)

    def finish_all(self) -> None:
        for box in self.inboxes().values():
            box.finish()


_HUBS: dict[str, Hub] = {}
_HUBS_LOCK = threading.Lock()


def hub(name: str) -> Hub:
    """The process-wide hub called ``name`` (created on first use)."""
    with _HUBS_LOCK:
        h = _HUBS.get(name)
        if h is None:
            h = _HUBS[name] = Hub(name)
        return h


def drop_hub(name: str) -> None:
    with _HUBS_LOCK:
        _HUBS.pop(name, None)


class NetTransport(Transport):
    """A phone that streams to ``perfcap serve``: ``net://HUB/PROTOCOL/ID``."""

    scheme = "net"
    usage = "net://HUB/PROTOCOL/ID  (e.g. net://serve/page/6f1c...; made by perfcap serve for each phone)"
    options: ClassVar[dict[str, Option]] = {}

    def __init__(self, address: str, options: dict[str, Any] | None = None, clock: Clock = MONOTONIC) -> None:
        super().__init__(address, options, clock)
        parts = address.split("/", 2)
        if len(parts) != 3 or not all(parts):
            raise ConfigError(f"invalid net:// address {address!r}; expected {self.usage}", source=address)
        self.hub_name, self.protocol, self.remote_id = parts
        self._box: Inbox | None = None

    @property
    def key(self) -> str:
        return f"{self.protocol}/{self.remote_id}"

    def identity_hint(self) -> dict[str, Any]:
        return {"serial": self.remote_id, "address": self.key}

    def present(self) -> bool | None:
        box = hub(self.hub_name).get(self.key)
        # finished counts as present: the reader then opens at once and learns that the source ended
        return bool(box is not None and (box.connected or box.finished))

    def open(self) -> None:
        box = hub(self.hub_name).inbox(self.key)
        if box.finished:
            raise EndOfStream(f"{self.key}: {box.reason}", source=self.url)
        if not box.connected and not len(box):
            raise DeviceNotFoundError(box.not_connected(), source=self.url)
        self._box = box

    def close(self) -> None:
        self._box = None

    @property
    def is_open(self) -> bool:
        return self._box is not None

    def read(self, timeout: float) -> Chunk | None:
        box = self._box
        if box is None:
            raise DeviceIOError(f"{self.url}: not open", source=self.url)
        return box.get(timeout)
