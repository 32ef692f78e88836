"""``perfcap replay``: a session back through the same codecs onto a bus, checked sample by sample."""

from __future__ import annotations

import json
import math
from typing import TYPE_CHECKING

from capture.app.cli.common import (
    EXIT_CHECK_FAILED,
    NO_VIEWS_HELP,
    SECONDS,
    check_duration,
    err,
    input_file,
    live_line,
    orientation_args,
    out,
    output_file,
    seconds_since,
    settings,
    stop_on_signals,
)
from capture.clock import MONOTONIC
from capture.errors import ConfigError
from devices.options import Option, arg_type

if TYPE_CHECKING:
    import argparse

    from capture.app.cli.common import Subcommands


#: ``--speed``: a factor above 0 (``--fast`` is as fast as possible)
SPEED = arg_type(Option(float, 1.0, "speed factor", min=0, max=1e6, min_exclusive=True))


def add_parser(sub: Subcommands) -> None:
    rp = sub.add_parser("replay", help="replay a session through the same codecs and check it")
    rp.add_argument("session", metavar="SESSION")
    g = rp.add_mutually_exclusive_group()
    g.add_argument("--speed", type=SPEED, metavar="X", help="speed factor (default 1 = recorded pace)")
    g.add_argument("--fast", action="store_true", help="as fast as possible (deterministic)")
    rp.add_argument("--loop", action="store_true", help="start over at the end")
    rp.add_argument("--duration", type=SECONDS, metavar="SECONDS", help="stop after this long")
    rp.add_argument("-o", "--output", metavar="SESSION.mcap", help="record the replay to a new session")
    rp.add_argument("--overwrite", action="store_true")
    rp.add_argument("--no-views", action="store_true", help=NO_VIEWS_HELP)
    rp.add_argument("--no-verify", action="store_true", help="skip comparing with the recorded samples")
    rp.add_argument("--json", action="store_true")
    rp.add_argument("-q", "--quiet", action="store_true")
    orientation_args(rp, "compute orientation even if the session has none (default: rebuild and verify the"
                         " recorded orientation streams with the recorded filter and calibration)")
    rp.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from capture.app.replay import replay_session
    from capture.app.replay_check import describe_verification

    speed = 0.0 if args.fast else args.speed
    if speed is None:
        speed = 1.0
    if not math.isfinite(speed) or (speed <= 0 and not args.fast):
        raise ConfigError(f"--speed must be a positive factor (use --fast for as fast as possible), not {speed}")
    if args.duration is not None:
        check_duration(args.duration)
    if args.loop and args.duration is None and args.fast:
        raise ConfigError("--loop with --fast never ends; add --duration SECONDS")
    input_file(args.session, "SESSION")
    output_file(args.output, "-o")
    stop = stop_on_signals()
    t0 = MONOTONIC.now_ns()
    rep = replay_session(args.session, speed=speed, loop=args.loop, verify=not args.no_verify, output=args.output,
                         overwrite=args.overwrite, stop=stop, duration_s=args.duration,
                         on_tick=None if args.quiet else live_line, orientation=args.orientation,
                         orientation_filter=args.filter, views=settings(args).recorder.views)
    wall = seconds_since(t0)
    ver = rep.verification
    if args.json:
        import numpy as np

        late = np.array(rep.lateness_ns, dtype=float) / 1e6 if rep.lateness_ns else None
        out(json.dumps({"recorded_s": rep.recorded_span_s, "replayed_s": rep.replayed_span_s,
                        "stopped_early": rep.stopped_early, "wall_s": wall, "streams": rep.capture.streams,
                        "verification": ver,
                        "lateness_ms": None if late is None else {"p50": float(np.percentile(late, 50)),
                                                                  "p99": float(np.percentile(late, 99))}}))
    else:
        out(f"replayed {rep.replayed_span_s:.2f} s of {rep.recorded_span_s:.2f} s of recording in {wall:.2f} s"
            + (" (stopped early: compared what was replayed)" if rep.stopped_early else "")
            + (f" ({rep.recorded_span_s / wall:.0f}x real time)" if wall > 0 and speed == 0 else ""))
        for name, s in rep.capture.streams.items():
            out(f"  {name:24s} {s['samples']:8d} samples")
        if ver is not None:
            for line in describe_verification(ver, rep.stopped_early):
                out(line)
    failed = [n for n, d in rep.capture.devices.items() if d["state"] == "failed"]
    if failed:
        err(f"perfcap: error: device(s) failed during replay: {', '.join(failed)}")
        return EXIT_CHECK_FAILED
    if ver is not None and not ver["equal"] and not args.loop and not rep.stopped_early:
        err("perfcap: error: replayed samples differ from the recorded ones")
        return EXIT_CHECK_FAILED
    return 0
