"""Whole-session replay: every recorded device back through its codec onto a bus, on one shared
timeline, with the replayed samples checked against the recorded ones (``replay_check``), and the
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

from capture.app.orchestrator import Capture, CaptureReport
from capture.app.replay_check import ReplayVerifier, expected_from_summary
from capture.bus import Overflow, Subscriber
from capture.clock import MONOTONIC, Clock
from capture.errors import CaptureError, ConfigError, EndOfStream, SessionError
from capture.sample import DeviceEvent, EventKind
from capture.session import SessionReader
from devices import Device, DeviceState
from devices.transports.base import BatchSource, RecordedTimeline

if TYPE_CHECKING:
    import threading
    from collections.abc import Callable

log = logging.getLogger(__name__)


@dataclass
class ReplayReport:
    capture: CaptureReport
    verification: dict[str, Any] | None
    lateness_ns: list[int] = field(default_factory=list)
    recorded_span_s: float = 0.0
    replayed_span_s: float = 0.0
    stopped_early: bool = False


def session_span(reader: SessionReader) -> tuple[int, int]:
    """The earliest and latest recorded chunk times over all devices. Where damage took the first raw
    chunks but sample blocks from them survive, the start is the earliest arrival those samples recorded
    (each sample's host time is the arrival of a chunk), so the replay's timeline does not move with
    which chunks survived.

    Raises:
        SessionError: the session holds no raw data.
    """
    spans = [s for s in (reader.first_and_last_chunk_ns(d) for d in reader.devices) if s is not None]
    if not spans:
        raise SessionError(f"{reader.path} holds no raw data to replay", path=reader.path)
    t0 = min(s[0] for s in spans)
    if reader.damaged:
        heads = [int(b.t_host_ns.min()) for b in reader.sample_blocks() if len(b)]
        t0 = min([t0, *heads])
    return t0, max(s[1] for s in spans)


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
                   orientation: bool | None = None, orientation_filter: str | None = None,
                   views: bool = True) -> ReplayReport:
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
        views: the ``output`` session also holds the viewable channels (``SessionWriter``).

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
    cap = Capture(urls, output=output, overwrite=overwrite, clock=clock, views=views,
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
        verifier = ReplayVerifier(reader.all_samples(), expected=expected_from_summary(reader.summary))
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
            v["missing"] == v["not_recorded"] == v["renumbered"] == v["restamped"] == 0
            and (v["expected"] is None or v["lost"] == 0)))
            for v in result["streams"].values()) and not result["unexpected"] and not result["check_errors"]
    firsts = [c.first_bus_ns for c in cap.stats.streams.values() if c.first_bus_ns is not None]
    lasts = [c.last_bus_ns for c in cap.stats.streams.values() if c.last_bus_ns is not None]
    replayed = (max(lasts) - min(firsts)) / 1e9 if firsts and lasts else 0.0
    early = bool((stop is not None and stop.is_set()) or
                 (not loop and any(d.get("state") not in ("finished", "failed") for d in report.devices.values())))
    return ReplayReport(report, result, lateness, (t_end - t0) / 1e9, replayed, early)


__all__ = ["ReplayReport", "replay_session", "run_merged", "session_span"]
