"""``perfcap info``: a session's devices, streams, clocks, drops, events and damage, in a few lines."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

from capture.app.cli.common import Progress, input_file, out

if TYPE_CHECKING:
    import argparse

    from capture.app.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    i = sub.add_parser("info", help="summarise a session")
    i.add_argument("session", metavar="SESSION")
    i.add_argument("--json", action="store_true", help="one JSON object")
    i.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from capture.session import SessionReader
    from capture.summary import summarize

    input_file(args.session, "SESSION")
    prog = Progress("reading", args.json)
    reader = SessionReader(args.session, progress=prog)
    prog.done()
    s = summarize(reader)
    if args.json:
        out(json.dumps(s, default=str))
        return 0
    out(f"{s['path']}: {s['size_bytes'] / 1e6:.2f} MB, {s['duration_s']:.3f} s, perfcap {s['perfcap_version']}")
    if not s["complete"]:
        out(f"  NOT CLOSED CLEANLY: {s['truncated']}; everything before that point is readable")
    if s["damaged"]:
        out("  DAMAGED (skipped, the rest is readable): "
            + ", ".join(f"{n} x {what}" for what, n in sorted(s["damaged"].items())))
    for d in s["devices"]:
        out(f"  device {d['name']}: {d['kind']} @ {d['url']}")
        if d.get("descriptors"):  # what its handshake read: report descriptor, calibration, bus
            out(f"      descriptors: {', '.join(d['descriptors'])}")
    for st in s["streams"]:
        clk = st["clock"] or {}
        c = (f"drift {clk['drift_ppm']:+.1f} ppm, {clk['epochs']} epoch(s)" if clk and not clk.get("pseudo")
             else "no device clock (dejittered arrivals)" if clk
             else "stamped at arrival" if st["samples"] and not st["device_clock"] else "")
        lag = st.get("arrival_lag_ms")
        if lag and clk:
            c += f", bus {lag['p50']:.3f} ms (max {lag['max']:.3f}) before arrival"
        out(f"  {st['name']:24s} {st['kind']:8s} {st['samples']:8d} samples {st['rate_hz']:9.2f} Hz "
            f"{st['drops']:5d} drops  {c}")
    if s["events"]:
        out("  events: " + ", ".join(f"{k} x{v}" for k, v in sorted(s["events"].items())))
    return 0
