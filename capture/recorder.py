"""The session recorder: a bus subscriber that never drops, writing everything to a session file.

It buffers items per channel and encodes them as column blocks every ``encode_interval_s`` (short,
so no single encoding step holds the interpreter lock for long), and closes an MCAP chunk and
flushes the file every ``flush_interval_s`` (half of ``max_loss_s``), so a recorder killed with
SIGKILL loses at most ``max_loss_s`` of data.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, cast

from capture.bus import EVERYTHING, Subscriber
from capture.clock import MONOTONIC, Clock
from capture.errors import SessionError
from capture.sample import (
    Chunk,
    ClockState,
    DeviceChunk,
    DeviceChunks,
    DeviceDescriptor,
    DeviceEvent,
    DeviceIdentity,
    Sample,
    SampleBatch,
    StreamInfo,
)
from capture.session import DeviceRecord, SessionWriter

log = logging.getLogger(__name__)


class SessionRecorder(Subscriber):
    """Records raw chunks, samples, clock states and events.

    Args:
        writer: the open session file.
        max_loss_s: the most data a crash may lose; the file is flushed every half of this.
        encode_interval_s: how often buffered items are encoded into blocks.
        clock: host clock.
    """

    accepts = EVERYTHING
    idle_interval_s = 0.05
    coalesce_s = 0.02  # it writes in blocks anyway: no need to wake for every item

    def __init__(self, writer: SessionWriter, *, max_loss_s: float = 1.0, encode_interval_s: float = 0.1,
                 clock: Clock = MONOTONIC) -> None:
        if max_loss_s <= 0:
            raise ValueError("max_loss_s must be positive")
        self.writer = writer
        self.clock = clock
        # Devices may be declared while the take runs (serve adds phones as they pair); the writer is
        # touched under this lock by both the declaring thread and the recorder's own thread.
        self._wlock = threading.Lock()
        self.flush_ns = int(max_loss_s * 0.5e9)
        self.encode_ns = int(min(encode_interval_s, max_loss_s / 4) * 1e9)
        self._raw: dict[str, list[Chunk]] = {}
        self._smp: dict[str, list[Sample | SampleBatch]] = {}
        self._ctrl: list[ClockState | DeviceDescriptor | DeviceEvent] = []
        self._channels: dict[str, int] = {}
        now = clock.now_ns()
        self._next_encode = now + self.encode_ns
        self._next_flush = now + self.flush_ns
        self.counts: dict[str, int] = {}
        self.raw_chunks = 0
        self.failed: SessionError | None = None
        self.summary_extra: dict[str, Any] = {}
        #: set by whoever subscribes the recorder, so the summary can include its drop count
        self.subscription: Any = None

    # -- declaration -----------------------------------------------------------------------------
    def add_device(self, name: str, kind: str, url: str, options: dict[str, Any], identity: DeviceIdentity,
                   streams: list[StreamInfo], descriptors: dict[str, bytes] | None = None) -> None:
        """Declare a device before its reader starts (so its channels exist when data comes)."""
        rec = DeviceRecord(name, kind, url, options, _identity_dict(identity), [s.name for s in streams],
                           dict(descriptors or {}))
        with self._wlock:
            for s in streams:
                self._channels[s.name] = len(s.channels)
            self.writer.add_device(rec, streams)

    def add_stream(self, info: StreamInfo) -> None:
        """Declare a derived stream (fusion output and the like)."""
        with self._wlock:
            self._channels[info.name] = len(info.channels)
            self.writer.add_stream(info)

    # -- subscriber ------------------------------------------------------------------------------
    def on_item(self, item: Any) -> None:
        t = type(item)
        if t is Sample or t is SampleBatch:
            lst = self._smp.get(item.stream)
            if lst is None:
                lst = self._smp[item.stream] = []
                if item.stream not in self._channels:
                    self._undeclared(item)
            lst.append(item)
        elif t is DeviceChunk or t is DeviceChunks:
            lst2 = self._raw.get(item.device)
            if lst2 is None:
                lst2 = self._raw[item.device] = []
            if t is DeviceChunk:
                lst2.append(item.chunk)
            else:
                lst2 += item.chunks
        else:
            self._ctrl.append(item)
        now = self.clock.now_ns()
        if now >= self._next_encode:
            self._tick(now)

    def on_idle(self) -> None:
        self._tick(self.clock.now_ns())

    def _undeclared(self, item: Sample | SampleBatch) -> None:
        n = len(item.values) if isinstance(item, Sample) else int(item.values.shape[1])
        log.warning("recorder: stream %s was not declared; recording it with generic channel names", item.stream)
        dev = item.stream.split("/")[0]
        info = StreamInfo(item.stream, "unknown", tuple(f"c{i}" for i in range(n)), ("?",) * n, None,
                          DeviceIdentity(kind="unknown", name=dev))
        self.add_stream(info)

    def _tick(self, now: int) -> None:
        if self.failed is not None:
            return
        try:
            with self._wlock:
                self._tick_locked(now)
        except Exception as exc:
            self.failed = exc if isinstance(exc, SessionError) else SessionError(
                f"internal error while writing {self.writer.path}: {type(exc).__name__}: {exc}", path=self.writer.path)
            log.error("recorder: %s; recording stopped, data up to the last flush is kept", self.failed)

    def _tick_locked(self, now: int) -> None:
        if now >= self._next_encode:
            self.encode(now)
            self._next_encode = now + self.encode_ns
        if now >= self._next_flush:
            self.writer.flush()
            self._next_flush = now + self.flush_ns

    def encode(self, now: int) -> None:
        """Turn everything buffered into blocks in the writer."""
        w = self.writer
        for dev, chunks in self._raw.items():
            if chunks:
                w.write_raw(dev, chunks, now)
                self.raw_chunks += len(chunks)
                self._raw[dev] = []
        for stream, items in self._smp.items():
            if not items:
                continue
            time.sleep(0)  # let device and delivery threads in between streams
            self._smp[stream] = []
            ch = self._channels[stream]
            blocks: list[SampleBatch] = []
            run: list[Sample] = []
            for it in items:
                if type(it) is Sample:
                    run.append(it)
                else:
                    if run:
                        blocks.append(SampleBatch.from_samples(stream, run, ch))
                        run = []
                    blocks.append(cast("SampleBatch", it))   # the stream's items are samples and batches
            if run:
                blocks.append(SampleBatch.from_samples(stream, run, ch))
            batch = SampleBatch.concat(blocks)
            w.write_samples(batch, now)
            self.counts[stream] = self.counts.get(stream, 0) + len(batch)
        ctrl, self._ctrl = self._ctrl, []
        for c in ctrl:
            if isinstance(c, ClockState):
                w.write_clock(c, now)
            elif isinstance(c, DeviceDescriptor):
                w.add_descriptor(c.device, c.key, c.data)
            else:
                w.write_event(c, now)

    def on_error(self, exc: BaseException) -> None:
        log.error("recorder: %s", exc)

    def stop(self) -> None:
        """Write what is left and close the file with its summary."""
        if self.failed is not None:
            return
        try:
            with self._wlock:
                self.encode(self.clock.now_ns())
            if self.subscription is not None:
                st = self.subscription.stats()
                self.summary_extra["recorder_dropped"] = st.dropped
                self.summary_extra["recorder_max_pending"] = st.max_pending
            self.writer.close({"samples": self.counts, "raw_chunks": self.raw_chunks,
                               "raw_bytes": self.writer.bytes_raw, **self.summary_extra})
        except Exception as exc:
            self.failed = exc if isinstance(exc, SessionError) else SessionError(
                f"internal error while closing {self.writer.path}: {type(exc).__name__}: {exc}", path=self.writer.path)
            log.error("recorder: %s", self.failed)


def _identity_dict(identity: DeviceIdentity) -> dict[str, Any]:
    return {f: getattr(identity, f) for f in identity.__dataclass_fields__}
