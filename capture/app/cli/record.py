"""``perfcap record``: devices to a session file, with live status lines and the capture report."""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

from capture.app.cli.common import (
    NO_VIEWS_HELP,
    SECONDS,
    check_duration,
    err,
    folder_arg,
    foxglove_args,
    foxglove_server,
    live_line,
    orientation_args,
    output_file,
    print_capture,
    settings,
    stop_on_signals,
)
from capture.errors import ConfigError

if TYPE_CHECKING:
    import argparse

    from capture.app.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    from devices import SPEC_EXAMPLE, SPEC_FORM

    r = sub.add_parser("record", help="record devices to a session file")
    r.add_argument("-d", "--device", action="append", metavar="DEVICE",
                   help=f"a device: {SPEC_FORM}, e.g. {SPEC_EXAMPLE} (repeatable)")
    r.add_argument("--config", metavar="FILE", help="TOML settings (and [[devices]])")
    r.add_argument("--profile", metavar="NAME", help="a profile from config/ (default, lab, ci)")
    r.add_argument("--duration", type=SECONDS, metavar="SECONDS", help="stop after this long (default: Ctrl-C)")
    r.add_argument("-o", "--output", required=True, metavar="SESSION.mcap")
    r.add_argument("--overwrite", action="store_true", help="replace an existing session file")
    r.add_argument("--no-views", action="store_true", help=NO_VIEWS_HELP)
    r.add_argument("--max-loss", type=float, metavar="SECONDS", help="most data a crash may lose (default 1 s)")
    r.add_argument("--json", action="store_true", help="print the report as JSON")
    r.add_argument("-q", "--quiet", action="store_true", help="no live status lines")
    orientation_args(r, "record orientation, gravity and linear acceleration of every IMU (with its stored"
                        " calibration)")
    r.add_argument("--calibration-dir", metavar="DIR", help="where calibrations are stored (perfcap calibrate)")
    r.add_argument("--lsl", action="store_true", help="also publish every stream as a Lab Streaming Layer outlet"
                   " (LabRecorder records them aligned with other LSL sources)")
    foxglove_args(r)
    r.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from capture.app.orchestrator import Capture
    from capture.calibration_store import CalibrationStore
    from devices import parse_device_spec

    check_duration(args.duration)
    output_file(args.output, "-o")
    folder_arg(args.calibration_dir, "--calibration-dir")
    s = settings(args)
    specs = [parse_device_spec(d) for d in args.device] if args.device else list(s.devices)
    if not specs:
        raise ConfigError("no devices: give -d DEVICE (e.g. -d synth://imu?rate=200) or [[devices]] in --config")
    if args.lsl:
        from capture.app.lsl_out import load_pylsl

        load_pylsl()  # a machine without liblsl is told so before any file is made
    fox = foxglove_server(args)  # before any file is made: a port in use leaves nothing behind
    stop = stop_on_signals()
    cap = Capture(specs, output=args.output, overwrite=s.recorder.overwrite, max_loss_s=s.recorder.max_loss_s,
                  fsync=s.recorder.fsync, views=s.recorder.views, recorder_max_bytes=s.bus.recorder_max_mb << 20,
                  live_queue=s.bus.live_queue, reconnect=s.reconnect_policy(),
                  meta={"command": " ".join(sys.argv), "config": ",".join(s.sources)})
    if s.orientation.enabled:
        try:
            proc = cap.enable_orientation(s.orientation.filter, s.orientation.auto_bias,
                                          store=CalibrationStore(s.calibration.dir or None))
        except BaseException:
            cap.stop()
            raise
        if proc is None:
            err("perfcap: note: --orientation: no IMU stream among the devices")
    if args.lsl:  # after the processors, so their streams have outlets before data flows too
        from capture.app.lsl_out import publish_capture

        try:
            pub, _ = publish_capture(cap)
        except BaseException:
            cap.stop()
            raise
        err(f"publishing {len(pub.streams)} streams as LSL outlets: {', '.join(pub.streams)}")
    if fox is not None:  # after the processors, so their streams take their places in the 3D view
        from capture.app import foxglove_live

        try:
            foxglove_live.publish_capture(cap, fox)
        except BaseException:
            cap.stop()
            raise
        err(f"Foxglove: open {fox.url} {foxglove_live.HOW_TO_OPEN}")
    names = ", ".join(f"{d.name} ({d.kind} @ {d.transport.url})" for d in cap.devices)
    err(f"recording {names} to {args.output}" + (f" for {args.duration:g} s" if args.duration else " until Ctrl-C"))
    report = cap.run(args.duration, stop=stop, on_tick=None if args.quiet else live_line)
    return print_capture(report, args.json)

