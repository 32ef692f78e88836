"""Whole-session replay: every recorded device back through its codec onto a bus, on one shared
timeline, with the replayed samples checked against the recorded ones (``ReplayVerifier``), and the
merged fast path that drives every device from one thread by recorded time (``run_merged``).

Replay is reached through the ``replay://`` transport (which lives with the simulators); this
module only builds the URLs and uses the abilities the transport declares (``BatchSource``,
``RecordedTimeline``), so production code still never imports ``sim_devices``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any
from urllib.parse import quote

import numpy as np

from capture.app.orchestrator import Capture, CaptureReport
from capture.bus import Overflow, Subscriber
from capture.clock import MONOTONIC, Clock
from capture.errors import CaptureError, ConfigError, EndOfStream, SessionError
from capture.sample import DeviceEvent, EventKind, Sample, SampleBatch
from capture.session import SessionReader
from devices import Device, DeviceState
from devices.transports.base import BatchSource, RecordedTimeline

if TYPE_CHECKING:
    import threading
    from collections.abc import Callable

log = logging.getLogger(__name__)


class ReplayVerifier(Subscriber):
    """Compares replayed samples with the recorded ones, stream by stream, on the first pass.

    Samples are matched on their sequence numbers, not their positions: a recorded block that was
    lost to damage leaves replayed samples with no recorded counterpart (``not_recorded``), a lost
    raw block leaves recorded samples that are never replayed (``missing``), and neither shifts the
    comparison of the rest. When a hole in the raw data renumbers the replayed samples after it,
    the numbering is re-anchored on the recorded host time. Matched samples must be bit-identical
    in values, sequence number, device time and bus time; host times too when the replay keeps
    recorded stamps. Batches are compared as whole columns.
    """

    accepts = frozenset({Sample, SampleBatch})
    #: how many missing or not-recorded runs are listed per stream
    MAX_RANGES = 20

    def __init__(self, recorded: dict[str, SampleBatch], check_host_times: bool = True) -> None:
        self.recorded = recorded
        self.check_host = check_host_times
        self.compared: dict[str, int] = dict.fromkeys(recorded, 0)
        self.mismatches: dict[str, int] = dict.fromkeys(recorded, 0)
        self.first_mismatch: dict[str, str] = {}
        self.unexpected: dict[str, int] = {}
        self._bits = {s: np.ascontiguousarray(b.values).view(np.int64) for s, b in recorded.items()}
        self._matched = {s: np.zeros(len(b), bool) for s, b in recorded.items()}
        self._order = {s: np.argsort(b.seq, kind="stable") for s, b in recorded.items()}
        self._sorted_seq = {s: b.seq[self._order[s]] for s, b in recorded.items()}
        self._offset: dict[str, int] = dict.fromkeys(recorded, 0)
        self._done: set[str] = set()
        self._extra: dict[str, list[tuple[int, int, int, int]]] = {s: [] for s in recorded}
        self.not_recorded: dict[str, int] = dict.fromkeys(recorded, 0)
        #: samples matched only after re-anchoring (their replayed numbers differ from the recorded)
        self.renumbered: dict[str, int] = dict.fromkeys(recorded, 0)

    def _lookup(self, stream: str, seq: np.ndarray) -> np.ndarray:
        """Recorded index of each replayed seq (after the offset), -1 where there is none."""
        ss = self._sorted_seq[stream]
        key = seq + self._offset[stream]
        pos = np.searchsorted(ss, key)
        pos_c = np.minimum(pos, max(len(ss) - 1, 0))
        found = (pos < len(ss)) & (ss[pos_c] == key) if len(ss) else np.zeros(len(seq), bool)
        return np.where(found, self._order[stream][pos_c] if len(ss) else -1, -1)

    def _reanchor(self, stream: str, item: SampleBatch) -> None:
        """After a hole in the raw data the replayed numbering may be shifted: find the recorded
        sample with the first replayed sample's host time and number from there."""
        rec = self.recorded[stream]
        j = int(np.searchsorted(rec.t_host_ns, item.t_host_ns[0]))
        if j < len(rec) and rec.t_host_ns[j] == item.t_host_ns[0] and not self._matched[stream][j]:
            self._offset[stream] = int(rec.seq[j]) - int(item.seq[0])

    def on_item(self, item: Any) -> None:
        rec = self.recorded.get(item.stream)
        if rec is None:
            n = 1 if type(item) is Sample else len(item)
            self.unexpected[item.stream] = self.unexpected.get(item.stream, 0) + n
            return
        s = item.stream
        if s in self._done or not len(rec):
            return  # later loop passes, or readings past a truncated recording's last block
        if type(item) is Sample:
            item = SampleBatch.from_samples(s, [item], rec.values.shape[1] if rec.values.ndim == 2 else 0)
        if not len(item):
            return
        idx = self._lookup(s, item.seq)
        if idx[0] < 0 or (self.check_host and rec.t_host_ns[idx[0]] != item.t_host_ns[0]):
            self._reanchor(s, item)
            idx = self._lookup(s, item.seq)
        have = idx >= 0
        have[have] &= ~self._matched[s][idx[have]]   # a recorded sample is matched once
        # past the recording's last sample: a truncated recording's raw data outlives its blocks
        extra = np.flatnonzero(~have & (item.seq + self._offset[s] <= self._sorted_seq[s][-1]))
        if extra.size:
            self.not_recorded[s] += int(extra.size)
            self._note_runs(self._extra[s], item.seq[extra], item.t_bus_ns[extra])
        if not have.any():
            return
        k = np.flatnonzero(have)
        ri = idx[k]
        self._matched[s][ri] = True
        self.compared[s] += int(k.size)
        ok = (item.t_device_ns[k] == rec.t_device_ns[ri]) & (item.t_bus_ns[k] == rec.t_bus_ns[ri])
        if self._offset[s]:
            self.renumbered[s] += int(k.size)
        if self.check_host:
            ok &= item.t_host_ns[k] == rec.t_host_ns[ri]
        vals = np.ascontiguousarray(item.values[k])
        if vals.shape[1:] != rec.values.shape[1:]:
            ok[:] = False
        else:
            ok &= np.all(vals.view(np.int64) == self._bits[s][ri], axis=1)
        bad = np.flatnonzero(~ok)
        if bad.size:
            self.mismatches[s] += int(bad.size)
            if s not in self.first_mismatch:
                j, i = int(k[bad[0]]), int(ri[bad[0]])
                self.first_mismatch[s] = (
                    f"seq {int(item.seq[j])}: replayed host={int(item.t_host_ns[j])} device={int(item.t_device_ns[j])} "
                    f"bus={int(item.t_bus_ns[j])} values={tuple(item.values[j].tolist())} but recorded "
                    f"seq={int(rec.seq[i])} host={int(rec.t_host_ns[i])} device={int(rec.t_device_ns[i])} "
                    f"bus={int(rec.t_bus_ns[i])} values={tuple(rec.values[i].tolist())}")
        if self._matched[s][-1]:
            self._done.add(s)   # the first pass reached the recording's end

    def _note_runs(self, runs: list[tuple[int, int, int, int]], seq: np.ndarray, bus: np.ndarray) -> None:
        """Add (first seq, last seq, first bus ns, last bus ns) runs of consecutive seqs."""
        cuts = np.flatnonzero(np.diff(seq) != 1) + 1
        for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(seq)], strict=True):
            if runs and runs[-1][1] + 1 == int(seq[a]):
                runs[-1] = (runs[-1][0], int(seq[b - 1]), runs[-1][2], int(bus[b - 1]))
            elif len(runs) < self.MAX_RANGES:
                runs.append((int(seq[a]), int(seq[b - 1]), int(bus[a]), int(bus[b - 1])))

    def result(self) -> dict[str, Any]:
        per = {}
        for s, b in self.recorded.items():
            miss = np.flatnonzero(~self._matched[s])
            runs: list[tuple[int, int, int, int]] = []
            if miss.size:
                order = miss[np.argsort(b.seq[miss], kind="stable")]
                self._note_runs(runs, b.seq[order], b.t_bus_ns[order])
            ss = self._sorted_seq[s]
            holes = np.flatnonzero(np.diff(ss) > 1)
            bus = b.t_bus_ns[self._order[s]]
            per[s] = {"recorded": len(b),
                      "absent": int((np.diff(ss)[holes] - 1).sum()) if holes.size else 0,
                      "absent_ranges": [{"seq": [int(ss[h]) + 1, int(ss[h + 1]) - 1],
                                         "bus_ns": [int(bus[h]), int(bus[h + 1])]}
                                        for h in holes[:self.MAX_RANGES]],
                      "compared": self.compared[s], "mismatches": self.mismatches[s],
                      "missing": int(miss.size), "not_recorded": self.not_recorded[s],
                      "renumbered": self.renumbered[s],
                      "missing_ranges": [{"seq": [r[0], r[1]], "bus_ns": [r[2], r[3]]} for r in runs],
                      "not_recorded_ranges": [{"seq": [r[0], r[1]], "bus_ns": [r[2], r[3]]}
                                              for r in self._extra[s]]}
        ok = all(v["mismatches"] == 0 and v["missing"] == 0 and v["not_recorded"] == 0 and v["renumbered"] == 0
                 for v in per.values()) and not self.unexpected
        return {"equal": ok, "streams": per, "unexpected": self.unexpected, "first_mismatch": self.first_mismatch}


@dataclass
class ReplayReport:
    capture: CaptureReport
    verification: dict[str, Any] | None
    lateness_ns: list[int] = field(default_factory=list)
    recorded_span_s: float = 0.0
    replayed_span_s: float = 0.0
    stopped_early: bool = False


def describe_verification(ver: dict[str, Any], stopped_early: bool = False) -> list[str]:
    """The lines ``perfcap replay`` prints for a verification result: the damage a damaged session
    showed (per stream, how many samples and which seq and bus-time ranges), then either that every
    compared sample is equal or where they differ."""
    lines = []
    if ver.get("damaged"):
        lines.append("  DAMAGED session (skipped: " + ", ".join(f"{n} x {w}" for w, n in sorted(ver["damaged"].items()))
                     + "); the surviving samples are compared")
        for name, v in ver["streams"].items():
            for key, what in (("absent", "absent from the recording (lost with the damage, or dropped live)"),
                              ("missing", "recorded, not replayed (their raw data is lost)"),
                              ("not_recorded", "replayed, their recorded block is lost")):
                if v.get(key):
                    spans = ", ".join(f"seq {r['seq'][0]}-{r['seq'][1]} (bus {r['bus_ns'][0] / 1e9:.3f}-"
                                      f"{r['bus_ns'][1] / 1e9:.3f} s)" for r in v[f"{key}_ranges"][:3])
                    more = " ..." if len(v[f"{key}_ranges"]) > 3 else ""
                    lines.append(f"    {name}: {v[key]} {what}: {spans}{more}")
    if ver["equal"] or (stopped_early and not any(v["mismatches"] for v in ver["streams"].values())):
        n = sum(v["compared"] for v in ver["streams"].values())
        lines.append(f"verified: all {n} replayed samples equal the recorded ones")
        return lines
    for name, v in ver["streams"].items():
        if v["mismatches"] or v["missing"] or v["not_recorded"] or v["renumbered"]:
            lines.append(f"  MISMATCH {name}: {v['mismatches']} differ, {v['missing']} not reproduced, "
                         f"{v['not_recorded']} not recorded, {v['renumbered']} numbered differently")
    for name, m in ver["first_mismatch"].items():
        lines.append(f"  first difference in {name}: {m}")
    return lines


def session_span(reader: SessionReader) -> tuple[int, int]:
    """The earliest and latest recorded chunk times over all devices.

    Raises:
        SessionError: the session holds no raw data.
    """
    spans = [s for s in (reader.first_and_last_chunk_ns(d) for d in reader.devices) if s is not None]
    if not spans:
        raise SessionError(f"{reader.path} holds no raw data to replay", path=reader.path)
    return min(s[0] for s in spans), max(s[1] for s in spans)


def run_merged(cap: Capture, duration_s: float | None = None, window_s: float = 5.0,
               stop: threading.Event | None = None,
               on_tick: Callable[[Capture, float], None] | None = None, tick_s: float = 1.0) -> CaptureReport:
    """Drive every device of ``cap`` from this one thread, merged by recorded time: no reader threads,
    so no contention between them, and a deterministic order on the bus.

    Sources that may be read as fast as possible (``BatchSource.batches``: an as-fast-as-possible
    replay) are read in ``window_s`` steps of recorded time and decoded in vectorised runs. Paced
    sources (a replay at a speed factor) are read chunk by chunk, always the device whose next chunk is
    due first; the transport sleeps until that chunk's deadline. Every transport must be a
    ``BatchSource`` (as ``replay://`` is).

    Raises:
        ConfigError: a device's transport cannot be driven this way.
    """
    sources: dict[str, BatchSource] = {}
    for d in cap.devices:
        if not isinstance(d.transport, BatchSource):
            raise ConfigError(f"device {d.name}: its transport cannot be driven by recorded time")
        sources[d.name] = d.transport
    bus, clock = cap.bus, cap.clock
    t_start = cap.start_driven()
    publish_many = bus.publish_many
    active: list[Device] = []
    next_tick = t_start + int(tick_s * 1e9)

    def finished(d: Device) -> None:
        publish_many(d.finish())
        d.state = DeviceState.FINISHED
        bus.publish(DeviceEvent(d.name, EventKind.FINISHED, clock.now_ns(), "source exhausted"))
        active.remove(d)

    def time_up() -> bool:
        now = clock.now_ns()
        nonlocal next_tick
        if on_tick and now >= next_tick:
            on_tick(cap, (now - t_start) / 1e9)
            next_tick = now + int(tick_s * 1e9)
        return (stop is not None and stop.is_set()) or (
            duration_s is not None and now - t_start >= duration_s * 1e9)

    try:
        for d in cap.devices:
            try:
                publish_many(d.open())
            except EndOfStream:
                d.state = DeviceState.FINISHED
                bus.publish(DeviceEvent(d.name, EventKind.FINISHED, clock.now_ns(), "empty"))
                continue
            bus.publish(DeviceEvent(d.name, EventKind.STREAMING, clock.now_ns()))
            active.append(d)
        batched = [d for d in active if sources[d.name].batches]
        firsts = [t for t in (sources[d.name].first_time_ns() for d in batched) if t is not None]
        step = int(window_s * 1e9)
        edge = (min(firsts) if firsts else 0) + step
        while active and not time_up():
            # as-fast-as-possible sources: everything up to the window edge, vectorised
            for d in [d for d in active if sources[d.name].batches]:
                try:
                    while True:
                        chunks = sources[d.name].read_many(0.0, 1 << 20, edge)
                        if not len(chunks):
                            break
                        publish_many(d.process_chunks(chunks))
                except EndOfStream:
                    finished(d)
            edge += step
            # a stretch of recorded time with nothing in it (a pause, or a crafted time far ahead) is
            # jumped over, not walked through in window steps
            ahead = [t for t in (sources[d.name].first_time_ns() for d in active if sources[d.name].batches)
                     if t is not None]
            if ahead and min(ahead) >= edge:
                edge = min(ahead) + step
            # paced sources: chunk by chunk, the earliest first, until the window edge
            paced = [d for d in active if not sources[d.name].batches]
            while paced and not time_up():
                times = [(sources[d.name].first_time_ns(), i) for i, d in enumerate(paced)]
                due = [(t, i) for t, i in times if t is not None]
                t_next, i = min(due) if due else (None, 0)
                d = paced[i]
                try:
                    items = d.poll(0.1)
                except EndOfStream:
                    finished(d)
                    paced.remove(d)
                    continue
                if items:
                    publish_many(items)
                if t_next is None:
                    continue
                if batched and t_next >= edge:
                    break
    except CaptureError as exc:
        log.error("replay stopped: %s", exc)
        raise
    finally:
        for d in cap.devices:
            if d in active:  # stopped early: still emit what the device had assembled
                publish_many(d.finish())
            try:
                d.close()
            except CaptureError:
                pass
            bus.publish_many(d.clock_states())
        report = cap.stop()
    return report


def replay_session(path: str, *, speed: float = 1.0, loop: bool = False, verify: bool = True,
                   output: str | None = None, overwrite: bool = False, stop: threading.Event | None = None,
                   on_tick: Callable[[Capture, float], None] | None = None, duration_s: float | None = None,
                   clock: Clock = MONOTONIC, subscribers: list[tuple[Subscriber, Overflow]] | None = None,
                   orientation: bool | None = None, orientation_filter: str | None = None) -> ReplayReport:
    """Replay every device of a session.

    Args:
        path: the session file.
        speed: 1 = recorded pace, 2 = twice as fast, 0 = as fast as possible.
        loop: start over at the end (runs until ``stop`` or ``duration_s``).
        verify: compare replayed samples with the recorded ones.
        output: record the replay to a new session.
        orientation: run orientation fusion. None (default): when the session holds orientation
            streams, rebuild them with the recorded filter and calibration, and verify them too.
            True: also for a session recorded without it (new streams, not verified). False: never.
        orientation_filter: filter for new orientation streams (default: the recorded one, else fusion).

    Raises:
        SessionError: unreadable session, or nothing to replay.
    """
    reader = SessionReader.open(path)
    if not reader.devices:
        raise SessionError(f"{path} has no devices to replay", path=path)
    if reader.truncated:
        log.warning("%s was not closed cleanly (%s); replaying what it holds", path, reader.truncated)
    t0, t_end = session_span(reader)
    q = quote(path, safe="/:._-~")
    urls = [f"{name}=replay://{q}?device={quote(name)}&speed={speed!r}&loop={'true' if loop else 'false'}"
            for name in reader.devices]
    cap = Capture(urls, output=output, overwrite=overwrite, clock=clock,
                  meta={"replay_of": path, "speed": repr(speed)})
    recorded_orient = {n: i for n, i in reader.streams.items() if i.kind == "orientation"}
    new_streams: set[str] = set()
    if orientation or (orientation is None and recorded_orient):
        from capture.app.orchestrator import CALIBRATION_KEY
        from capture.calibration_store import parse_calibration_document

        first = next(iter(recorded_orient.values()), None)
        flt = orientation_filter or (str(first.extra.get("filter") or "") if first else "") or "fusion"
        auto = bool(first.extra.get("auto_bias", False)) if first and first.extra else True
        cals = {}
        for name, rec in reader.devices.items():
            blob = rec.descriptors.get(CALIBRATION_KEY)
            if blob is not None:
                try:
                    cals[name] = parse_calibration_document(blob, f"{path}: {name}/{CALIBRATION_KEY}")[1]
                except ConfigError as exc:
                    log.error("%s (replaying without that calibration)", exc)
        proc = cap.enable_orientation(flt, auto, calibrations=cals)
        if proc is not None:
            new_streams = {o.name for o in proc.output_streams()} - set(reader.streams)
    verifier = None
    if verify:
        verifier = ReplayVerifier(reader.all_samples())
        cap.subscribe(verifier, Overflow.NEVER_DROP, "verifier")
    for sub, pol in subscribers or []:
        cap.subscribe(sub, pol)
    # One timeline for every device, fixed after all setup so the first chunks are not late.
    start = clock.now_ns() + 20_000_000
    for d in cap.devices:
        if isinstance(d.transport, RecordedTimeline):
            d.transport.set_timeline(start, t0)
    if speed == 0 and loop:
        report = cap.run(duration_s, stop=stop, on_tick=on_tick)  # endless vectorised loops: reader threads
    else:
        report = run_merged(cap, duration_s, stop=stop, on_tick=on_tick)
    lateness: list[int] = []
    for d in cap.devices:
        if isinstance(d.transport, RecordedTimeline):
            lateness.extend(d.transport.lateness_ns)
    result = verifier.result() if verifier else None
    if result is not None:
        # A damaged session: the samples that survive on both sides are compared; the holes the
        # damage left (recorded samples never replayed, replayed ones whose recorded block is lost)
        # are reported, not counted as differences.
        result["damaged"] = dict(reader.damaged)
        for name in new_streams:  # computed now, never recorded: nothing to compare with
            result["unexpected"].pop(name, None)
        holes_ok = bool(reader.damaged)
        result["equal"] = all(v["mismatches"] == 0 and (holes_ok or (
            v["missing"] == 0 and v["not_recorded"] == 0 and v["renumbered"] == 0))
            for v in result["streams"].values()) and not result["unexpected"]
    firsts = [c.first_bus_ns for c in cap.stats.streams.values() if c.first_bus_ns is not None]
    lasts = [c.last_bus_ns for c in cap.stats.streams.values() if c.last_bus_ns is not None]
    replayed = (max(lasts) - min(firsts)) / 1e9 if firsts and lasts else 0.0
    early = bool((stop is not None and stop.is_set()) or
                 (not loop and any(d.get("state") not in ("finished", "failed") for d in report.devices.values())))
    return ReplayReport(report, result, lateness, (t_end - t0) / 1e9, replayed, early)


__all__ = ["ReplayReport", "ReplayVerifier", "describe_verification", "replay_session", "run_merged", "session_span"]
