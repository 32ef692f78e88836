"""``perfcap demo``: hardware-free, simulated devices -> bus -> session -> replay, then the wrist's cycle
and the phone's puppet (``capture.app.demo``), said as it goes."""

from __future__ import annotations

import os
import tempfile
from typing import TYPE_CHECKING

from capture import __version__
from capture.app.cli.common import (
    EXIT_CHECK_FAILED,
    SECONDS,
    check_duration,
    live_line,
    out,
    output_file,
    print_capture,
    seconds_since,
    stop_on_signals,
)
from capture.clock import MONOTONIC

if TYPE_CHECKING:
    import argparse

    from capture.app.cli.common import Subcommands
    from capture.app.demo import PhoneSim


def add_parser(sub: Subcommands) -> None:
    d = sub.add_parser("demo", help="hardware-free demo: simulated devices -> bus -> session -> replay")
    d.add_argument("--duration", type=SECONDS, default=5.0, metavar="SECONDS")
    d.add_argument("-o", "--output", metavar="SESSION.mcap", help="where to keep the demo session")
    d.add_argument("--overwrite", action="store_true")
    d.add_argument("-q", "--quiet", action="store_true")
    d.add_argument("--lsl", action="store_true", help="also publish every stream as a Lab Streaming Layer outlet")
    d.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from capture.app import demo
    from capture.app.replay import replay_session
    from capture.session import SessionReader
    from capture.summary import summarize

    check_duration(args.duration)
    output_file(args.output, "-o")
    if args.lsl:
        from capture.app.lsl_out import load_pylsl

        load_pylsl()  # a machine without liblsl is told so before anything starts
    path = args.output or os.path.join(tempfile.mkdtemp(prefix="perfcap-demo-"), "demo.mcap")
    devices = list(demo.DEMO_DEVICES)
    stop = stop_on_signals()
    phone: PhoneSim | None = None
    serial = demo.start_serial_sim(args.duration, out)
    try:   # from here on, every child is stopped and reaped whatever happens
        if serial is not None:
            devices.append(("hand", f"witmotion@serial://{serial.port}?rate=200&device_clock=true"))
        out(f"perfcap {__version__} demo: {len(devices)} simulated IMUs through the real codec, clock sync, bus"
            " and recorder")
        for name, url in devices:
            out(f"  {name:6s} {url}")
        if serial is not None:
            out(f"  (hand is a WT901 served on a pty by 'perfcap sim serial' in another process, read through"
                f" pyserial; it is unplugged every {demo.DEMO_UNPLUG_EVERY:g} s for {demo.DEMO_UNPLUG_FOR:g} s)")
        out("  phone  the built-in phone page, simulated by 'perfcap sim phone' in another process: 60 Hz"
            " devicemotion over a WebSocket with TLS to the service on loopback (token, certificate pinned)")
        service, st = demo.start_service([f"{n}={u}" for n, u in devices], path, args.overwrite)
        cap = service.capture
        follow = demo.follow_wrist(cap)
        try:
            if args.lsl:
                from capture.app.lsl_out import publish_capture

                lsl_pub, _ = publish_capture(cap)
                out(f"  lsl    every stream as a Lab Streaming Layer outlet ({len(lsl_pub.streams)} now, the"
                    " phone's when it pairs)")
            phone = demo.start_phone(service, args.duration, stop)
            t0 = MONOTONIC.now_ns()
            next_tick = 1.0
            while not stop.is_set():
                elapsed = seconds_since(t0)
                if elapsed >= args.duration:
                    break
                stop.wait(min(0.05, args.duration - elapsed))
                if not args.quiet and elapsed >= next_tick:
                    live_line(cap, elapsed)
                    next_tick += 1.0
        finally:
            if phone is not None:
                phone.stop()
            report = st.stop()
    finally:
        if serial is not None:
            serial.stop()
    code = print_capture(report, False)
    if code:
        return code
    reader = SessionReader(path)
    s = summarize(reader)
    accuracy = demo.bus_time_accuracy(cap, reader, phone)
    out(f"\nsession {path}: {s['size_bytes'] / 1024:.0f} KiB for {(s['raw_bytes'] or 0) / 1024:.0f} KiB of raw"
        " device bytes")
    unplugs = int(report.devices.get("hand", {}).get("reconnects", 0))
    for line in demo.stream_lines(s, accuracy, phone, serial, unplugs):
        out(line)
    rep = replay_session(path, speed=0)
    ver = rep.verification or {}
    n = sum(v["compared"] for v in ver.get("streams", {}).values())
    if ver.get("equal"):
        out(f"replayed the session through the same codecs: all {n} samples equal the recorded ones")
    else:
        out(f"replay differs from the recording: {ver.get('first_mismatch')}")
        return EXIT_CHECK_FAILED
    for line in demo.demo_cycle(reader, cap):
        out(line)
    if follow is not None:
        out(follow.line())
    out(demo.demo_puppet(reader))
    out(f"\nnext: perfcap info {path}   |   perfcap replay {path} --speed 2   |   "
        f"perfcap export {path} --format csv -o export/   |   perfcap cycle {path} --stream wrist/imu")
    out(f"      or open {path} in Foxglove: plot /view/wrist/imu.ax, the 3D panel shows /tf/<device>/orientation"
        " (docs/foxglove.md)")
    return 0
