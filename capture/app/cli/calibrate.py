"""``perfcap calibrate``: an IMU's gyro bias, accelerometer, magnetometer, mounting and heading, measured
step by step (``capture.app.calibrate``) and stored per device identity; or the stored ones shown,
listed or removed."""

from __future__ import annotations

import json
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from capture.app.cli.common import SECONDS, check_duration, count, err, folder_arg, out, settings, stop_on_signals
from capture.errors import ConfigError

if TYPE_CHECKING:
    import argparse

    from capture.app.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    from devices import SPEC_FORM

    c = sub.add_parser("calibrate", help="calibrate an IMU (gyro bias, accelerometer, magnetometer, mounting)")
    c.add_argument("-d", "--device", metavar="DEVICE", help=f"the device, as for record ({SPEC_FORM})")
    c.add_argument("--gyro", action="store_true", help="gyro bias from an explicit still period")
    c.add_argument("--accel", action="store_true", help="accelerometer offset and scale from still poses")
    c.add_argument("--poses", type=count(1, 100), default=6, help="orientations asked for by --accel (default 6)")
    c.add_argument("--mag", action="store_true", help="magnetometer hard and soft iron from a rotation dance")
    c.add_argument("--mounting", action="store_true", help="mounting rotation from a still reference pose")
    c.add_argument("--yaw", action="store_true",
                   help="yaw reset: the heading held still now becomes zero (needs a magnetometer)")
    c.add_argument("--seconds", type=SECONDS, default=5.0, help="how long to read for each step (default 5)")
    c.add_argument("--show", action="store_true", help="print the stored calibration")
    c.add_argument("--clear", action="store_true", help="remove the stored calibration")
    c.add_argument("--list", action="store_true", help="list stored calibrations")
    c.add_argument("--dry-run", action="store_true", help="measure and print, do not store")
    c.add_argument("--calibration-dir", metavar="DIR", help="where calibrations are stored")
    c.add_argument("--config", metavar="FILE")
    c.add_argument("--profile", metavar="NAME")
    c.add_argument("--json", action="store_true")
    c.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from capture.app.calibrate import STEPS, collect_imu
    from capture.calibration import ImuCalibration
    from capture.calibration_store import CalibrationStore
    from devices import open_device, parse_device_spec

    folder_arg(args.calibration_dir, "--calibration-dir")
    s = settings(args)
    folder_arg(s.calibration.dir, "calibration dir")
    store = CalibrationStore(s.calibration.dir or None)
    if args.list:
        entries = store.entries()
        if args.json:
            out(json.dumps([{"file": str(p), "document": d, "error": e} for p, d, e in entries], default=str))
            return 0
        out(f"calibrations in {store.dir}:" + ("" if entries else " none"))
        for p, d, e in entries:
            if d is None:
                out(f"  {p.name}: DAMAGED: {e}")
            else:
                out(f"  {p.name}: {d['identity']['kind']} {d['identity']['name']} ({d.get('note') or 'no note'})")
        return 0
    if not args.device:
        raise ConfigError("give the device to calibrate with -d DEVICE (or --list)")
    spec = parse_device_spec(args.device)
    probe = open_device(spec)  # identity only: not opened
    ident = probe.identity
    current = store.load(ident) or ImuCalibration(device=ident.name)
    if args.show or args.clear:
        if args.clear:
            gone = store.remove(ident)
            out(f"{'removed' if gone else 'no calibration at'} {store.path_for(ident)}")
            return 0
        out(json.dumps({"file": str(store.path_for(ident)), "calibration": json.loads(current.to_json())}, indent=2))
        return 0
    given = vars(args)
    steps = [x for x in STEPS if given[x]]
    if not steps:
        raise ConfigError("say what to calibrate: --gyro (hold still), --accel (still poses), --mag (rotate in all"
                          " directions), --mounting (reference pose), --yaw (face heading zero); or --show,"
                          " --clear, --list")
    check_duration(args.seconds)
    report: dict[str, Any] = {}
    cal = current
    for step in steps:
        what, fit = STEPS[step]
        take = collect_imu(spec, args.seconds, s, what.format(poses=args.poses), stop_on_signals(), announce=err)
        res = fit(cal, take)
        cal = res.calibration
        report.update(res.report)
        out(res.line)
    cal = replace(cal, device=ident.name, note=f"perfcap calibrate --{' --'.join(steps)}")
    if args.dry_run:
        out("dry run: not stored")
    else:
        path = store.save(ident, cal, note=cal.note)
        out(f"stored in {path}; perfcap record --orientation applies it to {ident.name} (and replays keep it)")
        report["file"] = str(path)
    if args.json:
        out(json.dumps(report, default=float))
    return 0
