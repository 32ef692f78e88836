"""Session files: MCAP, written as a take happens and readable even if the writer was killed.

Layout of a perfcap session (MCAP profile ``perfcap``):

* metadata ``perfcap.session``: format version, perfcap version, start wall time, host, command.
* metadata ``device:<name>``: kind, transport URL, options, identity, stream names; descriptors
  (report descriptors, calibration) as attachments ``<name>/<key>``.
* channel ``/raw/<device>`` (protobuf ``perfcap.RawBlock``): every transport chunk with its arrival
  time and direction, in blocks.
* channel ``/samples/<stream>`` (protobuf ``perfcap.SampleBlock``, channel metadata ``stream_info``):
  decoded samples in column blocks (seq, host, device and bus times, values), lossless.
* channels ``/view/<stream>``, ``/tf/<stream>`` and ``/log`` (protobuf, ``capture.session_view``): the
  same samples and events as messages Foxglove and other viewers show with no perfcap code.
* channel ``/clock/<stream>`` (JSON with a JSON Schema): the clock-sync fit each time it changes.
* channel ``/events`` (JSON with a JSON Schema): device state changes, protocol errors, overflows, notes.
* metadata ``perfcap.summary`` when the take ended cleanly.

Format 1 sessions (before the viewable channels) stored the blocks in perfcap's own encodings
(``perfcap.raw.v1``, ``perfcap.samples.v1``, in ``capture.session_blocks``) and JSON without schemas; they
read as before.

Every message's MCAP log time, and its publish time, is its first time (a block's first bus time, a
chunk's arrival, an event's time) on the wall clock in UTC ns, never before the channel's previous one:
host time + ``log_time_offset_ns`` from ``perfcap.session`` (sessions written before it carry host times
there). perfcap's readers do not use them; viewers place the messages on their timeline by them.

The definitions (session metadata, devices, channels) are repeated outside the chunks as CRC-checked
``perfcap.definitions`` metadata after the flushes that follow a change, so no single chunk or
record holds the only copy (``session_scan`` reads around damage).

Blocks are columnar (int64 columns delta-coded, values of a quantum as integers) so zstd compresses
them to about the size of the raw bytes. Every block is a separate MCAP message, and the writer
closes an MCAP chunk and flushes the file at least every ``flush_interval_s``, so a killed recorder
loses at most that much.
"""

from __future__ import annotations

import json
import logging
import math
import os
import socket
import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, BinaryIO, ClassVar, cast

import numpy as np

from capture.clock import MONOTONIC
from capture.errors import SessionError
from capture.sample import (
    Chunk,
    ChunkRun,
    ClockState,
    DeviceEvent,
    SampleBatch,
    StreamInfo,
)
from capture.session_blocks import (
    PROTOBUF,
    RAW_BLOCK,
    RAW_ENCODING,
    SAMPLE_BLOCK,
    SAMPLES_ENCODING,
    concat_runs,
    decode_raw_block_run,
    decode_raw_run,
    decode_sample_block,
    decode_samples,
    encode_raw,
    encode_samples,
    raw_block_span,
)
from capture.session_file import MCAP_MAGIC, PendingSession, resolve_target
from capture.session_view import (
    CLOCK_JSONSCHEMA,
    EVENT_JSONSCHEMA,
    LOG,
    LOG_TOPIC,
    VIEW_PREFIXES,
    Placement,
    encode_event,
    stream_views,
)

if TYPE_CHECKING:
    from collections.abc import Iterator

log = logging.getLogger(__name__)

FORMAT_VERSION = "2"
#: session metadata key: MCAP log time minus host time, ns (sessions before it used the host time itself)
LOG_TIME_OFFSET_KEY = "log_time_offset_ns"
# ---------------------------------------------------------------------------------------------------
@dataclass
class DeviceRecord:
    """What a session knows about one device."""

    name: str
    kind: str
    url: str
    options: dict[str, Any]
    identity: dict[str, Any]
    streams: list[str]
    descriptors: dict[str, bytes] = field(default_factory=dict)
    #: every version of each descriptor in recording order (a device that reconnects over another
    #: bus, or re-reads its calibration, adds one per open); ``descriptors`` holds the latest
    history: dict[str, list[bytes]] = field(default_factory=dict)


class SessionWriter:
    """Writes one session file.

    The file is created safely (see ``capture.session_file``): under a temporary name until its
    header is on disk, then linked into place, so a recorder killed while starting leaves nothing
    under ``path``; exclusively unless ``overwrite``, which replaces only a perfcap session (or an
    empty file). When a write fails (disk full, I/O error), the file is cut back to the last
    ``flush`` and ``failed`` says why; nothing more is written.

    Args:
        path: the ``.mcap`` file to create (with ``base_dir``: a name inside it).
        overwrite: replace an existing perfcap session (otherwise ``SessionExistsError``).
        chunk_bytes: MCAP chunk size before compression.
        fsync: fsync the file at every flush (survives power loss, not only a killed process).
        meta: extra session metadata (command line, config).
        wall_time_s: the wall clock at the start (default: now).
        host_now_ns: the host clock (the one samples are stamped on) when ``wall_time_s`` was read
            (default: the monotonic clock now). Together they map the host clock to UTC: every message's
            MCAP log time is its time on the wall clock, so a viewer's timeline shows when it happened.
        base_dir: confine ``path`` to this directory, never following a link on the way (``perfcap
            serve``'s sessions directory).
        views: also write the viewable channels (``/view``, ``/tf``, ``/log``; ``capture.session_view``);
            without them the session holds the same data, in channels only perfcap's decoders read.

    Raises:
        ConfigError: the path is malformed or leaves ``base_dir`` (see ``resolve_target``).
        SessionExistsError: ``path`` exists and ``overwrite`` is false, or it is not a perfcap session.
        SessionError: the file cannot be created.
    """

    def __init__(self, path: str, *, overwrite: bool = False, chunk_bytes: int = 4 << 20, fsync: bool = True,
                 meta: dict[str, str] | None = None, wall_time_s: float | None = None,
                 base_dir: str | None = None, host_now_ns: int | None = None, views: bool = True) -> None:
        self.fsync = fsync
        self.views = views
        target = resolve_target(path, base_dir)
        try:
            pending = PendingSession(target, overwrite)
        except BaseException:
            target.close()
            raise
        self.path = pending.path
        self._f = pending.file
        self.closed = False
        try:
            self._start(chunk_bytes, meta, wall_time_s, host_now_ns)
            self._sync()   # the header on disk before the file has its name
            pending.publish()
        except OSError as exc:
            pending.discard()
            raise SessionError(f"cannot create {self.path}: {exc.strerror or exc}", path=self.path) from exc
        except BaseException:
            pending.discard()
            raise

    @property
    def failed(self) -> OSError | None:
        """The write error that stopped this file, if any (the file is then cut back to the last flush)."""
        return self._f.error

    def _sync(self) -> None:
        self._f.flush()
        if self.fsync:
            self._f.sync()
        self._f.commit()

    def _start(self, chunk_bytes: int, meta: dict[str, str] | None, wall_time_s: float | None,
               host_now_ns: int | None) -> None:
        from mcap.writer import CompressionType, Writer

        # the mcap writer uses write, tell and flush: what SessionFile has
        self._w = Writer(cast("BinaryIO", self._f), chunk_size=chunk_bytes, compression=CompressionType.ZSTD)
        self._w.start(profile="perfcap", library="perfcap")
        from capture import __version__
        host0 = MONOTONIC.now_ns() if host_now_ns is None else host_now_ns
        wall0 = wall_time_s if wall_time_s is not None else MONOTONIC.wall_time_s()
        #: MCAP log time = host time + this (UTC ns); recorded, so a reader can map back
        self.log_time_offset_ns = round(wall0 * 1e9) - host0
        m = {"format_version": FORMAT_VERSION, "perfcap_version": __version__, "host": socket.gethostname(),
             "start_wall_time_s": repr(wall0), LOG_TIME_OFFSET_KEY: str(self.log_time_offset_ns)}
        m.update(meta or {})
        self._w.add_metadata("perfcap.session", m)
        self._note_definitions("session", m)
        self._raw_schema = self._w.register_schema(RAW_BLOCK.name, PROTOBUF, RAW_BLOCK.data)
        self._smp_schema = self._w.register_schema(SAMPLE_BLOCK.name, PROTOBUF, SAMPLE_BLOCK.data)
        self._clock_schema = self._w.register_schema("perfcap.ClockState", "jsonschema",
                                                     json.dumps(CLOCK_JSONSCHEMA).encode())
        self._schemas: dict[tuple[str, bytes], int] = {}
        self._channels: dict[str, int] = {}
        self._quantum: dict[str, tuple[float, ...] | None] = {}
        #: per stream: (channel id, encode) of each viewable channel
        self._views: dict[str, list[tuple[int, Any]]] = {}
        self._placement = Placement()   # where orientation frames sit in the 3D view
        self._events = self._w.register_channel("/events", "json", self._w.register_schema(
            "perfcap.DeviceEvent", "jsonschema", json.dumps(EVENT_JSONSCHEMA).encode()))
        if self.views:
            self._log = self._channel(LOG_TOPIC, PROTOBUF, self._schema(LOG.name, LOG.data))
        self._seqs: dict[int, int] = {}
        self._last_log: dict[int, int] = {}
        self.bytes_raw = 0
        #: samples left out of the viewable channels (their blocks are written): batches whose width is
        #: not their stream's
        self.views_skipped = 0
        self.closed = False

    def _schema(self, name: str, data: bytes) -> int:
        sid = self._schemas.get((name, data))
        if sid is None:
            sid = self._schemas[(name, data)] = self._w.register_schema(name, PROTOBUF, data)
        return sid

    def _channel(self, topic: str, encoding: str, schema: int, metadata: dict[str, str] | None = None) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            cid = self._w.register_channel(topic, encoding, schema, metadata or {})
            self._note_definitions("channels", {"topic": topic, "encoding": encoding, "metadata": metadata or {}},
                                   str(cid))
            self._channels[topic] = cid
        return cid

    def add_device(self, rec: DeviceRecord, streams: list[StreamInfo]) -> None:
        self._w.add_metadata(f"device:{rec.name}", {
            "kind": rec.kind, "url": rec.url, "options": json.dumps(rec.options, sort_keys=True),
            "identity": json.dumps(rec.identity, sort_keys=True), "streams": json.dumps(rec.streams)})
        self._note_definitions("devices", {"kind": rec.kind, "url": rec.url, "options": rec.options,
                                           "identity": rec.identity, "streams": rec.streams}, rec.name)
        for key, blob in rec.descriptors.items():
            self._w.add_attachment(0, 0, f"{rec.name}/{key}", "application/octet-stream", blob)
        self._channel(f"/raw/{rec.name}", PROTOBUF, self._raw_schema, {"device": rec.name, "kind": rec.kind})
        for s in streams:
            self.add_stream(s)

    def add_descriptor(self, device: str, key: str, blob: bytes) -> None:
        """Attach one more descriptor to a declared device (e.g. the calibration in use)."""
        self._w.add_attachment(0, 0, f"{device}/{key}", "application/octet-stream", blob)

    def add_stream(self, info: StreamInfo) -> None:
        self._quantum[info.name] = info.quantum
        self._channel(f"/samples/{info.name}", PROTOBUF, self._smp_schema, {"stream_info": info.to_json()})
        if info.name in self._views or not self.views:
            return
        views = stream_views(info, self._placement)
        self._views[info.name] = [(self._channel(v.topic, PROTOBUF, self._schema(v.schema.name, v.schema.data),
                                                 v.metadata), v.encode) for v in views]

    def has_stream(self, name: str) -> bool:
        return f"/samples/{name}" in self._channels

    def _add(self, cid: int, t: int, data: bytes, now_ns: int) -> None:
        # log time: the message's first time (a block's first bus time, a chunk's arrival, an event's
        # time) on the wall clock, never before the channel's previous one (a clock reset may step bus
        # times back); publish time the same, as it is published at its time in the take's timeline
        # (``now_ns``, when the recorder wrote it, is later by the recorder's batching)
        seq = self._seqs.get(cid, 0)
        self._seqs[cid] = seq + 1
        log = max(t + self.log_time_offset_ns, self._last_log.get(cid, 0), 0)
        self._last_log[cid] = log
        self._w.add_message(cid, log_time=log, data=data, publish_time=log, sequence=seq)

    def write_raw(self, device: str, chunks: list[Chunk], now_ns: int) -> None:
        cid = self._channels.get(f"/raw/{device}")
        if cid is None:
            cid = self._channel(f"/raw/{device}", PROTOBUF, self._raw_schema, {"device": device, "kind": ""})
        self.bytes_raw += sum(len(c.data) for c in chunks)
        self._add(cid, chunks[0].t_ns, encode_raw(chunks), now_ns)

    def write_samples(self, batch: SampleBatch, now_ns: int) -> None:
        cid = self._channels[f"/samples/{batch.stream}"]
        self._add(cid, int(batch.t_bus_ns[0]), encode_samples(batch, self._quantum.get(batch.stream)), now_ns)
        for vid, encode in self._views.get(batch.stream, ()):
            try:
                msgs = encode(batch, self.log_time_offset_ns)
            except (ValueError, TypeError, IndexError) as exc:   # a batch its stream does not describe: block kept
                self.views_skipped += len(batch)
                if self.views_skipped == len(batch):
                    log.warning("%s: samples of %s not viewable (%s); their lossless block is kept, and further"
                                " ones are counted", self.path, batch.stream, exc)
                continue
            for t, data in msgs:
                self._add(vid, t, data, now_ns)

    def write_clock(self, state: ClockState, now_ns: int) -> None:
        cid = self._channel(f"/clock/{state.stream}", "json", self._clock_schema)
        d = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in state.to_dict().items()}
        self._add(cid, state.t_host_ns, json.dumps(d).encode(), now_ns)

    def write_event(self, ev: DeviceEvent, now_ns: int) -> None:
        self._add(self._events, ev.t_host_ns, json.dumps(ev.to_dict()).encode(), now_ns)
        if self.views:
            self._add(self._log, ev.t_host_ns, encode_event(ev, self.log_time_offset_ns), now_ns)

    # -- redundant definitions: no single chunk or record holds the only copy -----------------------
    #: session metadata, devices and channels, as the CRC-checked ``perfcap.definitions`` copy holds them
    _defs: dict[str, Any] | None = None
    #: copies still to write (each change is written after the next two flushes, a chunk apart)
    _defs_due: int = 0

    def _note_definitions(self, section: str, value: Any, key: str | None = None) -> None:
        if self._defs is None:
            self._defs = {"session": {}, "devices": {}, "channels": {}}
        if key is None:
            self._defs[section] = value
        else:
            self._defs[section][key] = value
        self._defs_due = 2

    def _repeat_definitions(self) -> None:
        """After a flush: one more copy of the definitions, if they changed within the last two."""
        if self._defs is None or self._defs_due <= 0:
            return
        self._defs_due -= 1
        from capture.session_scan import DEFINITIONS, encode_definitions

        defs = dict(self._defs)
        defs["channels"] = {**defs["channels"], str(self._events): {"topic": "/events", "encoding": "json",
                                                                     "metadata": {}}}
        self._w.add_metadata(DEFINITIONS, encode_definitions(defs))
        self._w.flush()

    def flush(self) -> None:
        """Close the current MCAP chunk and push it to the disk (fsync if asked); what is on disk then
        is complete, and a later failure cuts the file back to it.

        Raises:
            SessionError: the disk write failed (the file is cut back to the previous flush).
        """
        try:
            self._w.flush()
            self._repeat_definitions()
            self._sync()
        except OSError as exc:
            raise SessionError(f"writing {self.path} failed: {exc.strerror or exc}", path=self.path) from exc

    def close(self, summary: dict[str, Any] | None = None) -> None:
        """Write the summary and the MCAP footer and close the file.

        Raises:
            SessionError: the disk write failed (the file is cut back to the last flush, and closed).
        """
        if self.closed:
            return
        self.closed = True
        try:
            if summary is not None:
                self._w.add_metadata("perfcap.summary", {"json": json.dumps(summary, sort_keys=True, default=str)})
            self._w.finish()
            self._sync()
        except OSError as exc:
            raise SessionError(f"closing {self.path} failed: {exc.strerror or exc}", path=self.path) from exc
        finally:
            self._f.close()

    def abort(self) -> None:
        """Stop after a failure: the file is cut back to the last flush (complete records only, no
        footer: readers see a take cut short) and closed."""
        if not self.closed:
            self.closed = True
            self._f.abort()

    @property
    def cut_back(self) -> bool:
        """After a failure: the file holds exactly what the last flush had (False: it may hold more)."""
        return self._f.cut_back


# ---------------------------------------------------------------------------------------------------
@dataclass
class _Scan:
    meta: dict[str, str] = field(default_factory=dict)
    summary: dict[str, Any] | None = None
    devices: dict[str, DeviceRecord] = field(default_factory=dict)
    streams: dict[str, StreamInfo] = field(default_factory=dict)
    truncated: str | None = None
    bytes_read: int = 0


class SessionReader:
    """Reads a session, complete, cut short (a killed recorder) or damaged: everything up to the last
    complete MCAP chunk is returned and ``truncated`` says why reading stopped early. A damaged
    record or chunk is skipped to the next one that parses and costs only its own blocks: channel,
    device and session definitions are recovered from the chunks, the summary or the writer's
    repeated copies (``damaged`` counts what was skipped, ``damaged_regions`` says where). Every
    count and length the file states is bounded by what the file can hold (``session_scan``).

    The file is read once, in the constructor; the blocks are kept in memory (compressed by the
    column encoding, not decoded) and decoded on demand; the viewable channels' messages are not kept
    (they repeat the blocks for viewers). ``SessionReader.open`` shares one reader per
    unchanged file, so replaying many devices of one session reads it once.

    Args:
        path: the session file.
        progress: called as ``progress(bytes_read, file_size)`` while reading.

    Raises:
        SessionError: the file does not exist, is not readable, or is not a perfcap session.
    """

    _cache: ClassVar[dict[tuple[str, int, int], SessionReader]] = {}
    _cache_lock = threading.Lock()

    def __init__(self, path: str, progress: Any = None) -> None:
        self.path = path
        if not os.path.exists(path):
            raise SessionError(f"{path}: no such file", path=path)
        if os.path.isdir(path):
            raise SessionError(f"{path} is a directory, not a session file", path=path)
        self.size = os.path.getsize(path)
        scan = _Scan()
        self.damaged: dict[str, int] = {}
        #: (first byte, end byte) of each stretch of the file skipped as damaged
        self.damaged_regions: list[tuple[int, int]] = []
        self._msgs: dict[str, list[bytes]] = {}
        #: the message encoding of each topic (blocks of format 1 and 2 differ)
        self._enc: dict[str, str] = {}
        self._read(scan, progress)
        self._scan = scan

    @classmethod
    def open(cls, path: str) -> SessionReader:
        """A shared reader for ``path`` (read again only if the file changed)."""
        try:
            st = os.stat(path)
        except OSError:
            return cls(path)  # raises the right SessionError
        key = (os.path.abspath(path), st.st_size, st.st_mtime_ns)
        with cls._cache_lock:
            r = cls._cache.get(key)
            if r is None:
                r = cls(path)
                if len(cls._cache) >= 4:
                    cls._cache.pop(next(iter(cls._cache)))
                cls._cache[key] = r
            return r

    @property
    def meta(self) -> dict[str, str]:
        return self._scan.meta

    @property
    def summary(self) -> dict[str, Any] | None:
        return self._scan.summary

    @property
    def devices(self) -> dict[str, DeviceRecord]:
        return self._scan.devices

    @property
    def streams(self) -> dict[str, StreamInfo]:
        return self._scan.streams

    def encoding(self, topic: str) -> str | None:
        """The message encoding of a topic's channel (format 1 blocks: ``perfcap.*.v1``; format 2: ``protobuf``)."""
        return self._enc.get(topic)

    @property
    def truncated(self) -> str | None:
        """Why reading stopped before the footer (a killed recorder), or ``None`` for a complete file."""
        return self._scan.truncated

    def _damage(self, what: str, why: BaseException | str, n: int = 1) -> None:
        """Count a damaged record or block (skipped, never fatal); log the first of each kind."""
        seen = self.damaged.get(what, 0)
        self.damaged[what] = seen + n
        if seen == 0:
            log.warning("%s: damaged %s skipped (%s); further ones are counted", self.path, what,
                        why if isinstance(why, str) else f"{type(why).__name__}: {why}")

    def _read(self, scan: _Scan, progress: Any = None) -> None:
        """Read every record that survives; fill ``scan`` and the messages by topic.

        Records are walked by ``session_scan.RecordScanner``: a record or chunk that does not parse
        exactly (or whose CRC does not match) is skipped to the next one that does, counted in
        ``damaged`` and its byte range kept in ``damaged_regions``. Channel definitions are taken
        from wherever they survive: the chunks (CRC-checked), the writer's repeated
        ``perfcap.definitions`` copies (CRC-checked), then the summary section; so a damaged chunk
        costs its own messages only.
        """
        from mcap.records import Attachment, Channel, Message, Metadata

        from capture.session_scan import DEFINITIONS, RecordScanner, decode_definitions, open_bytes

        try:
            f, mm = open_bytes(self.path)
        except OSError as exc:
            raise SessionError(f"cannot read {self.path}: {exc.strerror or exc}", path=self.path) from exc
        chunk_ch: dict[int, tuple[str, str, dict[str, str]]] = {}
        summary_ch: dict[int, tuple[str, str, dict[str, str]]] = {}
        by_channel: dict[int, list[bytes]] = {}
        #: channels perfcap's readers do not read (the viewable ones): their messages are not kept
        unread: set[int] = set()
        metas: list[Any] = []
        attachments: list[Any] = []
        try:
            head, tail = bytes(mm[:8]), bytes(mm[-8:])
            if head != MCAP_MAGIC and (len(mm) < 64 or tail != MCAP_MAGIC):
                raise SessionError(f"{self.path} is not a session file (not MCAP)", path=self.path)
            if head != MCAP_MAGIC:
                self._damage("MCAP magic", "the first 8 bytes are not MCAP's (the footer's are)")
            scanner = RecordScanner(mm, self._damage, progress)
            for op, rec in scanner.records():
                if op == 0x06:
                    for r in rec:
                        if isinstance(r, Message):
                            if r.channel_id not in unread:
                                by_channel.setdefault(r.channel_id, []).append(r.data)
                        elif isinstance(r, Channel):
                            chunk_ch.setdefault(r.id, (r.topic, r.message_encoding, r.metadata))
                            if r.topic.startswith(VIEW_PREFIXES):
                                unread.add(r.id)
                elif op == 0x04 and isinstance(rec, Channel):
                    summary_ch.setdefault(rec.id, (rec.topic, rec.message_encoding, rec.metadata))
                elif op == 0x0C and isinstance(rec, Metadata):
                    metas.append(rec)
                elif op == 0x09 and isinstance(rec, Attachment):
                    attachments.append(rec)
        finally:
            if not isinstance(mm, bytes):
                mm.close()
            f.close()
        res = scanner.result
        scan.truncated = res.truncated
        self.damaged_regions = res.damaged_regions
        defs: dict[str, Any] = {}
        for m in metas:
            if m.name == DEFINITIONS:  # each copy holds all definitions so far: merged, the latest wins
                try:
                    d = decode_definitions(m.metadata)
                except (KeyError, TypeError, ValueError) as exc:
                    self._damage("definitions copy", exc)
                    continue
                for section in ("devices", "channels"):
                    if isinstance(d.get(section), dict):
                        defs.setdefault(section, {}).update(d[section])
                if "session" in d:
                    defs["session"] = d["session"]
                continue
            try:
                self._metadata(scan, m.name, m.metadata)
            except (KeyError, TypeError, ValueError) as exc:
                self._damage(f"metadata record {m.name!r}", exc)
        channels = dict(summary_ch)
        if res.summary_crc_ok is False and summary_ch:
            self._damage("summary section", "its CRC does not match (its channels used only as a last resort)")
        for k, c in (defs.get("channels") or {}).items():
            try:
                channels[int(k)] = (str(c["topic"]), str(c["encoding"]), dict(c["metadata"]))
            except (KeyError, TypeError, ValueError) as exc:
                self._damage("definitions copy", exc)
        channels.update(chunk_ch)
        self._recover_definitions(scan, defs, res.header_profile, channels)
        for cid, datas in by_channel.items():
            ch = channels.get(cid)
            if ch is not None and ch[0].startswith(VIEW_PREFIXES):
                continue
            if ch is None:
                self._damage("block of a channel whose definition is lost", f"channel {cid}", len(datas))
                continue
            self._msgs.setdefault(ch[0], []).extend(datas)
            self._enc.setdefault(ch[0], ch[1])
        for _cid, (topic, _enc, meta) in sorted(channels.items()):
            if topic.startswith("/samples/"):
                try:
                    info = StreamInfo.from_json(meta["stream_info"])
                except (KeyError, TypeError, ValueError) as exc:
                    self._damage("stream description", exc)
                    continue
                scan.streams.setdefault(info.name, info)
        for a in attachments:
            dev, _, key = a.name.partition("/")
            if dev in scan.devices:
                scan.devices[dev].descriptors[key] = a.data
                scan.devices[dev].history.setdefault(key, []).append(a.data)

    def _recover_definitions(self, scan: _Scan, defs: dict[str, Any], profile: str | None,
                             channels: dict[int, tuple[str, str, dict[str, str]]]) -> None:
        """Session and device records from the CRC-checked copy where the originals are lost or
        differ from it (a metadata record has no CRC of its own).

        Raises:
            SessionError: nothing in the file says it is a perfcap session.
        """
        sess = defs.get("session")
        if isinstance(sess, dict) and all(isinstance(v, str) for v in sess.values()) and "format_version" in sess:
            if scan.meta != sess:
                if scan.meta:
                    self._damage("session metadata", "it differs from its CRC-checked copy (the copy is used)")
                else:
                    self._damage("session metadata", "lost; recovered from its copy")
                scan.meta = dict(sess)
        for name, d in (defs.get("devices") or {}).items():
            try:
                rec = DeviceRecord(str(name), str(d["kind"]), str(d["url"]), dict(d["options"]),
                                   dict(d["identity"]), [str(s) for s in d["streams"]])
            except (KeyError, TypeError, ValueError) as exc:
                self._damage("definitions copy", exc)
                continue
            old = scan.devices.get(rec.name)
            if old is None or (old.kind, old.url, old.options, old.identity, old.streams) != (
                    rec.kind, rec.url, rec.options, rec.identity, rec.streams):
                self._damage("device record", "lost or differing from its CRC-checked copy (the copy is used)")
                scan.devices[rec.name] = rec
        if "format_version" not in scan.meta:
            perfcap = profile == "perfcap" or any(enc in (RAW_ENCODING, SAMPLES_ENCODING) or "stream_info" in m
                                                 for _t, enc, m in channels.values())
            if not perfcap:
                raise SessionError(f"{self.path} is an MCAP file but not a perfcap session", path=self.path)
            self._damage("session metadata", "lost (no copy survived)")
            scan.meta = {"format_version": FORMAT_VERSION}

    @staticmethod
    def _metadata(scan: _Scan, name: str, m: dict[str, str]) -> None:
        if name == "perfcap.session":
            scan.meta = dict(m)
        elif name == "perfcap.summary":
            scan.summary = json.loads(m["json"])
        elif name.startswith("device:"):
            dn = name[len("device:"):]
            scan.devices[dn] = DeviceRecord(dn, m["kind"], m["url"], json.loads(m["options"]),
                                            json.loads(m["identity"]), json.loads(m["streams"]))

    # -- data access ---------------------------------------------------------------------------------
    def _decoded(self, topic: str, decode: Any) -> Iterator[Any]:
        for data in self._msgs.get(topic, ()):
            try:
                out = decode(data)
            except Exception as exc:
                self._damage(f"block of {topic}", exc)
                continue
            yield out

    def _raw_runs(self, device: str) -> Iterator[ChunkRun]:
        topic = f"/raw/{device}"
        return self._decoded(topic, decode_raw_block_run if self._enc.get(topic) == RAW_ENCODING else decode_raw_run)

    def raw_chunks(self, device: str) -> Iterator[Chunk]:
        """Every recorded chunk of a device, in order (damaged blocks skipped and counted)."""
        for run in self._raw_runs(device):
            yield from run

    def raw_run(self, device: str) -> ChunkRun:
        """Every recorded chunk of a device as one ``ChunkRun``."""
        runs = list(self._raw_runs(device))
        if not runs:
            e = np.empty(0, np.int64)
            return ChunkRun(b"", e, e.copy(), np.empty(0, np.uint8))
        return concat_runs(runs)

    def first_and_last_chunk_ns(self, device: str) -> tuple[int, int] | None:
        topic = f"/raw/{device}"
        if self._enc.get(topic) == RAW_ENCODING:
            spans = list(self._decoded(topic, raw_block_span))
        else:
            spans = [(int(r.t_ns[0]), int(r.t_ns[-1])) for r in self._raw_runs(device) if len(r)]
        if not spans:
            return None
        return spans[0][0], spans[-1][1]

    def sample_blocks(self, streams: set[str] | None = None) -> Iterator[SampleBatch]:
        """The decoded sample blocks of ``streams`` (default all); a block that does not decode, or whose
        width is not its stream's channel count, is skipped and counted as damaged."""
        names = self.streams if streams is None else streams
        for name in names:
            info = self.streams.get(name)
            width = len(info.channels) if info is not None else None

            v1 = self._enc.get(f"/samples/{name}") == SAMPLES_ENCODING

            def decode(data: bytes, name: str = name, width: int | None = width, v1: bool = v1) -> SampleBatch:
                b = decode_sample_block(name, data) if v1 else decode_samples(name, data)
                if width is not None and b.values.shape[1] != width:
                    raise ValueError(f"sample block of {name} holds {b.values.shape[1]} channels, its stream"
                                     f" declares {width}")
                return b

            yield from self._decoded(f"/samples/{name}", decode)

    def samples(self, stream: str) -> SampleBatch:
        """All decoded samples of one stream as one batch."""
        blocks = list(self.sample_blocks({stream}))
        if not blocks:
            ch = len(self.streams[stream].channels) if stream in self.streams else 0
            return SampleBatch.from_samples(stream, [], ch)
        return SampleBatch.concat(blocks)

    def all_samples(self) -> dict[str, SampleBatch]:
        return {s: self.samples(s) for s in self.streams}

    def clock_states(self, stream: str | None = None) -> list[dict[str, Any]]:
        out: list[dict[str, Any]] = []
        for topic in list(self._msgs):
            if topic.startswith("/clock/") and (stream is None or topic == f"/clock/{stream}"):
                out += self._decoded(topic, json.loads)
        return out

    def events(self) -> list[dict[str, Any]]:
        return list(self._decoded("/events", json.loads))
