"""What ``perfcap info`` says about a session: per-stream counts, measured rates and drops,
devices, clock fits, events, and whether the file was closed cleanly."""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any

import numpy as np

from capture.sample import NO_TIME

if TYPE_CHECKING:
    from capture.session import SessionReader


def summarize(reader: SessionReader) -> dict[str, Any]:
    """A JSON-ready summary of a session (see ``perfcap info --json``)."""
    batches = reader.all_samples()
    streams: list[dict[str, Any]] = []
    t_min: int | None = None
    t_max: int | None = None
    for name, info in reader.streams.items():
        b = batches.get(name)
        n = len(b) if b is not None else 0
        rate = 0.0
        drops = 0
        has_dev = False
        lag_ms: dict[str, float] | None = None
        if b is not None and n:
            tb = b.t_bus_ns
            t_min = int(tb[0]) if t_min is None else min(t_min, int(tb[0]))
            t_max = int(tb[-1]) if t_max is None else max(t_max, int(tb[-1]))
            span = (int(tb[-1]) - int(tb[0])) / 1e9
            rate = (n - 1) / span if span > 0 and n > 1 else 0.0
            seq = b.seq
            drops = int((seq[-1] - seq[0] + 1) - n)
            has_dev = bool((b.t_device_ns != NO_TIME).any())
            lag = (b.t_host_ns - tb) / 1e6
            lag_ms = {"p50": round(float(np.median(lag)), 3), "max": round(float(lag.max()), 3),
                      "min": round(float(lag.min()), 3)}
        streams.append({
            "name": name, "kind": info.kind, "device": info.device.name, "device_kind": info.device.kind,
            "samples": n, "rate_hz": round(rate, 3), "nominal_rate_hz": info.nominal_rate_hz, "drops": drops,
            "channels": list(info.channels), "units": list(info.units), "device_clock": has_dev,
            # how long before its chunk arrived each reading's bus time lies (latency and jitter taken
            # out by the clock fit; 0 for a reading stamped at its arrival)
            "arrival_lag_ms": lag_ms,
        })
    clocks: dict[str, dict[str, Any]] = {}
    for st in reader.clock_states():
        c = clocks.setdefault(st["stream"], {"updates": 0})
        c["updates"] += 1
        c["drift_ppm"] = round(st["drift_ppm"], 2)
        c["epochs"] = st["epoch"] + 1
        c["pseudo"] = st["pseudo"]
    for st in streams:  # a device clock is shared by the device's streams; a pseudo clock is per stream
        st["clock"] = clocks.get(st["name"]) or clocks.get(st["device"]) or None
    events = reader.events()
    kinds: dict[str, int] = {}
    for e in events:
        kinds[e["kind"]] = kinds.get(e["kind"], 0) + 1
    summ = reader.summary or {}
    return {
        "path": reader.path,
        "size_bytes": os.path.getsize(reader.path),
        "complete": reader.truncated is None,
        "truncated": reader.truncated,
        "duration_s": round((t_max - t_min) / 1e9, 6) if t_min is not None and t_max is not None else 0.0,
        "start_wall_time_s": float(reader.meta.get("start_wall_time_s", "0") or 0),
        "perfcap_version": reader.meta.get("perfcap_version"),
        "devices": [{"name": d.name, "kind": d.kind, "url": d.url, "options": d.options,
                     "descriptors": sorted(d.descriptors)} for d in reader.devices.values()],
        "streams": streams,
        "clock_sync": clocks,
        "events": kinds,
        "damaged": dict(reader.damaged),
        "raw_bytes": summ.get("raw_bytes"),
        "recorder_dropped": summ.get("recorder_dropped", 0 if summ else None),
    }


def drop_total(summary: dict[str, Any]) -> int:
    return int(sum(s["drops"] for s in summary["streams"])) + int(summary.get("recorder_dropped") or 0)


__all__ = ["drop_total", "summarize"]
