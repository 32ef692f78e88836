"""``perfcap puppet``: a character on an invisible stick from a phone (live, a recorded session or a
scripted trajectory), stepped at a fixed rate: BVH, VMC over UDP and the state timeline."""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

from capture.app.cli.common import (
    EXIT_BAD_INPUT,
    EXIT_CHECK_FAILED,
    SECONDS,
    check_duration,
    err,
    foxglove_args,
    foxglove_server,
    input_file,
    live_line,
    out,
    output_file,
    stop_on_signals,
)
from capture.clock import MONOTONIC
from capture.errors import ConfigError

if TYPE_CHECKING:
    import argparse
    from collections.abc import Iterable

    from capture.app.cli.common import Subcommands
    from capture.app.puppet_run import PuppetRun
    from devices import DeviceSpec
    from retarget.puppet import PhoneInput


def add_parser(sub: Subcommands) -> None:
    from devices import SPEC_FORM

    pp = sub.add_parser("puppet", help="drive a character from a phone (live, a recorded session or a trajectory"
                        " CSV): BVH, VMC, state timeline",
                        description="A character hangs on an invisible stick from the phone: it walks, runs,"
                        " crouches and jumps as the phone moves, and falls limp when the motion fits no animation."
                        " Frames are stepped at a fixed rate. Exit 0 when driven, 1 when nothing drove it or every"
                        " VMC send failed, 2 for bad input.")
    src = pp.add_mutually_exclusive_group(required=True)
    src.add_argument("--phone", metavar="DEVICE", help=f"live from a device, as for record ({SPEC_FORM}); its"
                     " <name>/attitude stream, touches to grab")
    src.add_argument("--input", metavar="TRAJECTORY.csv", help="a scripted trajectory: columns t,px,py,pz,qw,qx,"
                     "qy,qz,touch (s, m, the phone's unit quaternion in the Y-up world, 0/1)")
    src.add_argument("--session", metavar="SESSION", help="a recorded session: the phone's attitude and touches")
    pp.add_argument("--device", metavar="NAME", help="with --session: the phone (default: the only device with an"
                    " attitude stream)")
    pp.add_argument("-o", "--output", metavar="OUT.bvh", help="write the performance as BVH (fps = --rate)")
    pp.add_argument("--vmc", metavar="HOST:PORT", help="send one VMC (OSC) bundle per frame over UDP (from a"
                    " --input or --session at the frame rate, as a player would)")
    pp.add_argument("--fast", action="store_true", help="with --vmc and --input or --session: send every frame at"
                    " once instead of at the frame rate")
    pp.add_argument("--timeline", metavar="TIMELINE.json", help='write the state changes as [{"t": s, "state":'
                    ' name}, ...]')
    pp.add_argument("--rate", type=float, default=60.0, metavar="HZ", help="frame rate (default 60)")
    pp.add_argument("--duration", type=SECONDS, metavar="SECONDS", help="with --phone: stop after this long"
                    " (default: Ctrl-C)")
    pp.add_argument("--hold", action="store_true", help="the phone counts as held throughout (touches ignored)")
    foxglove_args(pp)   # with --phone: the puppet's skeleton moving in Foxglove's 3D panel, live
    pp.add_argument("-q", "--quiet", action="store_true", help="no live status lines")
    pp.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from capture.app import puppet_run
    from capture.app.puppet_input import check_rate, read_trajectory, session_track
    from capture.app.puppet_run import PuppetRun, VmcSender, parse_host_port

    if not ((args.phone or "").strip() or args.input or args.session):   # the one source given is empty
        flag = "--phone" if args.phone is not None else "--input" if args.input is not None else "--session"
        raise ConfigError(f"{flag} is empty: give a device, a trajectory CSV or a session")
    rate = check_rate(args.rate)
    if args.duration is not None:
        if not args.phone:
            raise ConfigError("--duration is for --phone (a trajectory or a session is driven to its end)")
        check_duration(args.duration)
    if (args.foxglove is not None or args.foxglove_host) and not args.phone:
        raise ConfigError("--foxglove is for --phone (the live puppet); open a session's file in Foxglove instead")
    if args.fast and not (args.vmc and not args.phone):
        raise ConfigError("--fast is for --vmc from an --input or a --session (a live phone sets its own pace)")
    if args.device is not None and not args.session:
        raise ConfigError("--device chooses the phone of a --session")
    input_file(args.input, "--input")
    input_file(args.session, "--session")
    output_file(args.output, "-o")
    output_file(args.timeline, "--timeline")
    puppet_run.probe_writable(args.output, "-o")          # before the performance, not after it
    puppet_run.probe_writable(args.timeline, "--timeline")
    if args.vmc:
        parse_host_port(args.vmc)
    spec = None
    if args.phone:
        from devices import parse_device_spec

        spec = parse_device_spec(args.phone)
    track = None
    notes: list[str] = []
    if args.input:
        track = read_trajectory(args.input)
    elif args.session:
        from capture.session import SessionReader

        track = session_track(SessionReader(args.session), args.device)
    if track is not None:
        notes = list(track.notes)
        if args.hold and not track.held_throughout:
            from dataclasses import replace

            track = replace(track, held_throughout=True)
            notes.append("--hold: the phone counts as held throughout (touches ignored)")
    from retarget.puppet import PuppetRetargeter

    retargeter = PuppetRetargeter()
    vmc = VmcSender(args.vmc, retargeter.skeleton) if args.vmc else None
    performance = PuppetRun(retargeter, rate=rate, vmc=vmc, keep_frames=bool(args.output))
    code = 0
    try:
        if spec is not None:                # --phone (else --input or --session gave the track)
            source, code, notes = _live(args, spec, performance)
        elif track is not None:
            source = track.source
            frames: Iterable[PhoneInput] = track.resample(rate)
            if vmc is not None and not args.fast:    # a receiver expects frames at their rate, not a burst
                frames = puppet_run.paced(frames, MONOTONIC)
            for inp in frames:
                try:
                    performance.step(inp)
                except ValueError as exc:   # an input the retargeter cannot follow: bad input, one line
                    raise ConfigError(f"{source}: the puppet cannot follow the input at {inp.t:.6g} s"
                                      f" ({' '.join(str(exc).split())})") from None
    finally:
        if vmc is not None:
            vmc.close()
    if not performance.frames:
        err(f"perfcap: error: no phone orientation from {source}: the puppet was not driven")
        return EXIT_CHECK_FAILED
    out(f"puppet: {performance.frames} frames at {rate:g} Hz ({performance.duration:.2f} s) from {source}")
    for note in notes:
        out(f"  note: {note}")
    out("  states: " + ", ".join(f"{s} {t:.2f} s" for s, t in performance.state_times().items())
        + f" ({len(performance.timeline()) - 1} change(s))")
    written, unwritten = puppet_run.write_outputs(performance, args.output, args.timeline)
    for line in written:
        out(line)
    if vmc is not None:
        out(f"  VMC: {vmc.sent} bundle(s) sent to {args.vmc} over UDP"
            + (f", {vmc.errors} send error(s) (first: {vmc.first_error})" if vmc.errors else ""))
        if vmc.errors and not vmc.sent:
            err(f"perfcap: error: no VMC bundle could be sent to {args.vmc} ({vmc.first_error})")
            code = code or EXIT_CHECK_FAILED
    if unwritten:
        err(f"perfcap: error: {'; '.join(unwritten)}")
        code = EXIT_BAD_INPUT
    return code


def _live(args: argparse.Namespace, spec: DeviceSpec, performance: PuppetRun) -> tuple[str, int, list[str]]:
    """``--phone``: the device on a bus, followed until Ctrl-C, ``--duration`` or its end."""
    from capture.app.orchestrator import Capture
    from capture.app.puppet_run import PuppetFollower

    fox = foxglove_server(args)
    try:
        cap = Capture([spec], meta={"command": " ".join(sys.argv)})
    except BaseException:
        if fox is not None:
            fox.stop()
        raise
    try:
        dev = cap.devices[0]
        follower = PuppetFollower.for_device(dev.name, dev.streams, performance, hold=True if args.hold else None)
        cap.add_processor(follower, name="puppet")   # follows the phone, publishes <device>/puppet
        if fox is not None:   # the pose stream's skeleton (/tf/<device>/puppet) and the phone's streams
            from capture.app import foxglove_live

            foxglove_live.publish_capture(cap, fox)
            err(f"Foxglove: open {fox.url} {foxglove_live.HOW_TO_OPEN}; the 3D panel shows /tf/{dev.name}/puppet")
    except BaseException:
        cap.stop()
        if fox is not None:
            fox.stop()
        raise
    notes = []
    if follower.hold:
        notes.append("--hold: the phone counts as held throughout" if args.hold else
                     f"{dev.name} has no touch stream: the phone counts as held throughout")
    else:
        notes.append(f"the puppet is grabbed while the screen of {dev.name} is touched")
    err(f"puppet: following {follower.attitude.name} of {dev.name} ({dev.kind} @ {dev.transport.url})"
        + (f" for {args.duration:g} s" if args.duration else " until Ctrl-C"))
    stop = stop_on_signals()
    report = cap.run(args.duration, stop=stop, on_tick=None if args.quiet else live_line)
    if not follower.hold and not follower.touches:
        notes.append(f"no touch from {dev.name}: the puppet stayed released (--hold: held throughout)")
    if follower.skipped:
        notes.append(f"{follower.skipped} attitude sample(s) without values or out of order skipped")
    if follower.unknown_touches:
        notes.append(f"{follower.unknown_touches} touch row(s) with a phase other than 0-3 (start, move, end,"
                     " cancel) ignored")
    if follower.errors:
        notes.append(f"{follower.errors} frame(s) failed (first: {follower.first_error})")
    failed = [n for n, d in report.devices.items() if d["state"] == "failed" or not d.get("opens", 1)]
    code = 0
    for n in failed:
        err(f"perfcap: error: device {n} failed: {report.devices[n]['last_error']}")
        code = EXIT_CHECK_FAILED
    return f"{dev.name} ({follower.samples} attitude samples)", code, notes
