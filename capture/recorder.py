"""The session recorder: a bus subscriber that never drops, writing everything to a session file.

It buffers items per channel and encodes them as column blocks every ``encode_interval_s`` (short,
so no single encoding step holds the interpreter lock for long), and closes an MCAP chunk and
flushes the file every ``flush_interval_s`` (half of ``max_loss_s``), so a recorder killed with
SIGKILL loses at most ``max_loss_s`` of data.

A write that fails (disk full, file size limit, I/O error) ends the recording: the file is cut back
to the last flush, ``failed`` says why, ``saved`` says what the file holds (per stream, exactly: the
counts at the last flush), ``received`` what came in, and ``on_failed`` is called once (the capture
stops the take, ``perfcap serve`` stops that recording). Nothing more is buffered after a failure.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING, Any, cast

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

if TYPE_CHECKING:
    from collections.abc import Callable

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
        self._fail_lock = threading.Lock()
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
        #: first and last sequence number written per stream (so a reader can tell a lost head or tail)
        self.seq_span: dict[str, tuple[int, int]] = {}
        self.raw_chunks = 0
        #: samples per stream that came in (saved or not)
        self.received: dict[str, int] = {}
        #: samples per stream and raw chunks in the file as of the last flush (after a clean close: all)
        self.saved: dict[str, int] = {}
        self.saved_raw_chunks = 0
        #: ``saved`` is exact (False after a failure whose file could not be cut back: at least that)
        self.saved_exact = True
        self.failed: SessionError | None = None
        #: called once, from the recorder's thread, when the recording fails
        self.on_failed: Callable[[SessionError], None] | None = None
        self.summary_extra: dict[str, Any] = {}
        #: set by whoever subscribes the recorder, so the summary can include its drop count
        self.subscription: Any = None

    # -- declaration -----------------------------------------------------------------------------
    def add_device(self, name: str, kind: str, url: str, options: dict[str, Any], identity: DeviceIdentity,
                   streams: list[StreamInfo], descriptors: dict[str, bytes] | None = None) -> None:
        """Declare a device before its reader starts (so its channels exist when data comes)."""
        rec = DeviceRecord(name, kind, url, options, _identity_dict(identity), [s.name for s in streams],
                           dict(descriptors or {}))
        self._declare(lambda: self.writer.add_device(rec, streams), {s.name: len(s.channels) for s in streams})

    def add_stream(self, info: StreamInfo) -> None:
        """Declare a derived stream (fusion output and the like)."""
        self._declare(lambda: self.writer.add_stream(info), {info.name: len(info.channels)})

    def _declare(self, write: Callable[[], None], channels: dict[str, int]) -> None:
        """Declare under the writer's lock; a write that fails ends the recording like any other (the
        caller, e.g. a phone being admitted, goes on: its data is counted as not saved)."""
        with self._wlock:
            self._channels.update(channels)
            if self.failed is not None:
                return
            try:
                write()
                return
            except Exception as exc:
                error = exc
        self._fail(error, "writing")

    # -- subscriber ------------------------------------------------------------------------------
    def on_item(self, item: Any) -> None:
        t = type(item)
        if t is Sample or t is SampleBatch:
            self.received[item.stream] = self.received.get(item.stream, 0) + (1 if t is Sample else len(item))
            if self.failed is not None:
                return  # counted as received, never saved
            lst = self._smp.get(item.stream)
            if lst is None:
                lst = self._smp[item.stream] = []
                if item.stream not in self._channels:
                    self._undeclared(item)
            lst.append(item)
        elif self.failed is not None:
            return
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
            self._fail(exc, "writing")

    def _tick_locked(self, now: int) -> None:
        if now >= self._next_encode:
            self.encode(now)
            self._next_encode = now + self.encode_ns
        if now >= self._next_flush:
            self.writer.flush()
            self._saved_now()
            self._next_flush = now + self.flush_ns

    def _saved_now(self) -> None:
        """Everything encoded so far is on disk (the writer just flushed)."""
        self.saved = dict(self.counts)
        self.saved_raw_chunks = self.raw_chunks

    def _fail(self, exc: Exception, doing: str) -> None:
        """The recording ends: the file is cut back to the last flush and closed; say what it holds."""
        with self._fail_lock:
            if self.failed is not None:
                return  # another thread's write failed first
            self._fail_locked(exc, doing)
        cb, failed = self.on_failed, self.failed
        if cb is not None and failed is not None:
            try:
                cb(failed)
            except Exception:
                log.exception("recorder: the failure handler failed")

    def _fail_locked(self, exc: Exception, doing: str) -> None:
        self.failed = exc if isinstance(exc, SessionError) else SessionError(
            f"internal error while {doing} {self.writer.path}: {type(exc).__name__}: {exc}", path=self.writer.path)
        self._raw, self._smp, self._ctrl = {}, {}, []
        self.writer.abort()
        if not self.writer.cut_back:
            self._count_saved_from_file()
        held = sum(self.saved.values())
        log.error("recorder: %s; recording stopped: the file keeps %s%d samples (up to its last flush), the rest"
                  " is not saved", self.failed, "" if self.saved_exact else "at least ", held)

    def _count_saved_from_file(self) -> None:
        """The file could not be cut back: count what it holds by reading it."""
        from capture.session import SessionReader

        try:
            r = SessionReader(self.writer.path)
            self.saved = {s: len(r.samples(s)) for s in r.streams if s in self.counts}
            self.saved_raw_chunks = sum(len(r.raw_run(d)) for d in r.devices)
        except Exception as exc:
            self.saved_exact = False
            log.warning("recorder: %s cannot be read back (%s); it holds at least what its last flush had",
                        self.writer.path, exc)

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
            if len(batch):
                lo, hi = int(batch.seq.min()), int(batch.seq.max())
                span = self.seq_span.get(stream)
                self.seq_span[stream] = (lo, hi) if span is None else (min(span[0], lo), max(span[1], hi))
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
            self.writer.close({"samples": self.counts, "seq": {k: list(v) for k, v in self.seq_span.items()},
                               "raw_chunks": self.raw_chunks,
                               "raw_bytes": self.writer.bytes_raw, **self.summary_extra})
            self._saved_now()
        except Exception as exc:
            self._fail(exc, "closing")

    def not_saved(self) -> dict[str, int]:
        """Samples per stream that came in but are not in the file."""
        return {s: n - self.saved.get(s, 0) for s, n in self.received.items() if n > self.saved.get(s, 0)}


def _identity_dict(identity: DeviceIdentity) -> dict[str, Any]:
    return {f: getattr(identity, f) for f in identity.__dataclass_fields__}
