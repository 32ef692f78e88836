"""Whole-session replay: every recorded device back through its codec onto a bus, on one shared
timeline, with the replayed samples checked against the recorded ones.

Replay is reached through the ``replay://`` transport (which lives with the simulators); this
module only builds the URLs, so production code still never imports ``sim_devices``.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from typing import Any
from collections.abc import Callable
from urllib.parse import quote

from capture.bus import Overflow, Subscriber
from capture.clock import MONOTONIC, Clock
from capture.errors import SessionError
from capture.app.orchestrator import Capture, CaptureReport
import numpy as np

from capture.sample import Sample, SampleBatch
from capture.session import SessionReader

log = logging.getLogger(__name__)


class ReplayVerifier(Subscriber):
    """Compares replayed samples with the recorded ones, stream by stream, on the first pass.

    Values must be bit-identical, and so must the sequence number, device time and bus time; host
    times too when the replay keeps recorded stamps. Batches are compared as whole columns.
    """

    accepts = frozenset({Sample, SampleBatch})

    def __init__(self, recorded: dict[str, SampleBatch], check_host_times: bool = True) -> None:
        self.recorded = recorded
        self.check_host = check_host_times
        self.compared: dict[str, int] = {s: 0 for s in recorded}
        self.mismatches: dict[str, int] = {s: 0 for s in recorded}
        self.first_mismatch: dict[str, str] = {}
        self.unexpected: dict[str, int] = {}
        self._bits = {s: np.ascontiguousarray(b.values).view(np.int64) for s, b in recorded.items()}

    def on_item(self, item: Any) -> None:
        rec = self.recorded.get(item.stream)
        if rec is None:
            self.unexpected[item.stream] = self.unexpected.get(item.stream, 0) + (1 if type(item) is Sample else len(item))
            return
        if type(item) is Sample:
            item = SampleBatch.from_samples(item.stream, [item], rec.values.shape[1] if rec.values.ndim == 2 else 0)
        i = self.compared[item.stream]
        n = min(len(item), len(rec) - i)
        if n <= 0:
            return  # later loop passes, or readings past a truncated recording's last block
        self.compared[item.stream] = i + n
        sl = slice(i, i + n)
        ok = (item.seq[:n] == rec.seq[sl]) & (item.t_device_ns[:n] == rec.t_device_ns[sl]) \
            & (item.t_bus_ns[:n] == rec.t_bus_ns[sl])
        if self.check_host:
            ok &= item.t_host_ns[:n] == rec.t_host_ns[sl]
        vals = np.ascontiguousarray(item.values[:n])
        if vals.shape[1:] != rec.values.shape[1:]:
            ok[:] = False
        else:
            ok &= np.all(vals.view(np.int64) == self._bits[item.stream][sl], axis=1)
        bad = np.flatnonzero(~ok)
        if bad.size:
            self.mismatches[item.stream] += int(bad.size)
            if item.stream not in self.first_mismatch:
                j = int(bad[0])
                self.first_mismatch[item.stream] = (
                    f"seq {int(item.seq[j])}: replayed host={int(item.t_host_ns[j])} device={int(item.t_device_ns[j])} "
                    f"bus={int(item.t_bus_ns[j])} values={tuple(item.values[j].tolist())} but recorded "
                    f"seq={int(rec.seq[i + j])} host={int(rec.t_host_ns[i + j])} device={int(rec.t_device_ns[i + j])} "
                    f"bus={int(rec.t_bus_ns[i + j])} values={tuple(rec.values[i + j].tolist())}")

    def result(self) -> dict[str, Any]:
        per = {}
        for s, b in self.recorded.items():
            per[s] = {"recorded": len(b), "compared": self.compared[s], "mismatches": self.mismatches[s],
                      "missing": len(b) - self.compared[s]}
        ok = all(v["mismatches"] == 0 and v["missing"] == 0 for v in per.values()) and not self.unexpected
        return {"equal": ok, "streams": per, "unexpected": self.unexpected, "first_mismatch": self.first_mismatch}


@dataclass
class ReplayReport:
    capture: CaptureReport
    verification: dict[str, Any] | None
    lateness_ns: list[int] = field(default_factory=list)
    recorded_span_s: float = 0.0
    replayed_span_s: float = 0.0
    stopped_early: bool = False


def session_span(reader: SessionReader) -> tuple[int, int]:
    """The earliest and latest recorded chunk times over all devices.

    Raises:
        SessionError: the session holds no raw data.
    """
    spans = [s for s in (reader.first_and_last_chunk_ns(d) for d in reader.devices) if s is not None]
    if not spans:
        raise SessionError(f"{reader.path} holds no raw data to replay", path=reader.path)
    return min(s[0] for s in spans), max(s[1] for s in spans)


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
        from capture.calibration_store import parse_calibration_document
        from capture.errors import ConfigError
        from capture.app.orchestrator import CALIBRATION_KEY

        first = next(iter(recorded_orient.values()), None)
        flt = orientation_filter or (first.extra.get("filter") if first and first.extra else None) or "fusion"
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
        set_timeline = getattr(d.transport, "set_timeline", None)
        if set_timeline is not None:
            set_timeline(start, t0)
    if speed == 0 and loop:
        report = cap.run(duration_s, stop=stop, on_tick=on_tick)  # endless vectorised loops: reader threads
    else:
        report = cap.run_merged(duration_s, stop=stop, on_tick=on_tick)
    lateness: list[int] = []
    for d in cap.devices:
        lateness.extend(getattr(d.transport, "lateness_ns", []))
    result = verifier.result() if verifier else None
    if result is not None:
        # Streams whose recorded blocks (or whose device's raw blocks) were damaged cannot be compared.
        bad = {t for t in reader.damaged if t.startswith("block of ")}
        for s, v in result["streams"].items():
            dev = s.split("/")[0]
            if f"block of /samples/{s}" in bad or f"block of /raw/{dev}" in bad:
                v["unverifiable"] = True
        for name in new_streams:  # computed now, never recorded: nothing to compare with
            result["unexpected"].pop(name, None)
        result["equal"] = all(v.get("unverifiable") or (v["mismatches"] == 0 and v["missing"] == 0)
                              for v in result["streams"].values()) and not result["unexpected"]
    firsts = [c.first_bus_ns for c in cap.stats.streams.values() if c.first_bus_ns is not None]
    lasts = [c.last_bus_ns for c in cap.stats.streams.values() if c.last_bus_ns is not None]
    replayed = (max(lasts) - min(firsts)) / 1e9 if firsts and lasts else 0.0
    early = bool((stop is not None and stop.is_set()) or
                 (not loop and any(d.get("state") not in ("finished", "failed") for d in report.devices.values())))
    return ReplayReport(report, result, lateness, (t_end - t0) / 1e9, replayed, early)


__all__ = ["ReplayReport", "ReplayVerifier", "replay_session", "session_span"]
