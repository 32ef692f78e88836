"""``perfcap``: record, replay, inspect and export capture sessions; extract motion cycles; run the
hardware-free demo.

Errors are one line on stderr and a non-zero exit (2 for bad input, 1 for a failed check or no cycle,
70 for an internal error, with ``--debug`` showing the traceback).
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
import os
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from capture import __version__
from capture.errors import CaptureError, ConfigError

log = logging.getLogger("perfcap")

EXIT_BAD_INPUT = 2
EXIT_CHECK_FAILED = 1
EXIT_INTERNAL = 70


def out(text: str = "") -> None:
    print(text, flush=True)


class Progress:
    """Progress on stderr for offline work that takes more than a second."""

    def __init__(self, label: str, quiet: bool = False) -> None:
        self.label = label
        self.quiet = quiet
        self.t0 = time.monotonic()
        self.last = 0.0
        self.shown = False

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        if self.quiet or now - self.t0 < 1.0 or now - self.last < 0.5:
            return
        self.last = now
        self.shown = True
        pct = 100.0 * done / total if total else 0.0
        print(f"\r{self.label}: {pct:5.1f}%", end="", file=sys.stderr, flush=True)

    def done(self) -> None:
        if self.shown:
            print(f"\r{self.label}: 100.0%", file=sys.stderr, flush=True)


def _stop_on_signals() -> threading.Event:
    ev = threading.Event()

    def handler(signum: int, frame: Any) -> None:
        if ev.is_set():
            return
        ev.set()
        print(f"\nperfcap: {signal.Signals(signum).name} received, stopping and flushing", file=sys.stderr)

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return ev


def _live_line(cap: Any, elapsed: float) -> None:
    parts = []
    for name, s in cap.stats.snapshot().items():
        parts.append(f"{name} {s['samples']} @ {s['rate_hz']:.0f} Hz" + (f" ({s['drops']} lost)" if s["drops"] else ""))
    for d in cap.devices:
        if d.state.value in ("opening", "reconnecting", "closed") and not d.stats.chunks:
            parts.append(f"{d.name}: waiting for the device")
        elif d.state.value == "reconnecting":
            parts.append(f"{d.name}: reconnecting")
    if not parts:
        parts.append("no devices yet (waiting for phones to connect)" if not cap.devices else "no samples yet")
    print(f"[{elapsed:6.1f} s] " + "; ".join(parts), file=sys.stderr, flush=True)


def _settings(args: argparse.Namespace) -> Any:
    from capture.app.config import load_config

    overrides: dict[str, dict[str, Any]] = {"recorder": {}}
    if getattr(args, "max_loss", None) is not None:
        overrides["recorder"]["max_loss_s"] = args.max_loss
    if getattr(args, "overwrite", False):
        overrides["recorder"]["overwrite"] = True
    if getattr(args, "orientation", None) is not None or getattr(args, "filter", None):
        overrides["orientation"] = {"enabled": getattr(args, "orientation", None), "filter": getattr(args, "filter", None)}
    if getattr(args, "calibration_dir", None):
        overrides["calibration"] = {"dir": args.calibration_dir}
    if getattr(args, "command", None) == "serve":
        overrides["serve"] = _serve_overrides(args)
    return load_config(getattr(args, "config", None), getattr(args, "profile", None), overrides)


def _check_duration(d: float | None) -> None:
    if d is not None and (not math.isfinite(d) or d <= 0):
        raise ConfigError(f"--duration must be a positive number of seconds, not {d}")


# ------------------------------------------------------------------------------------------------
def cmd_record(args: argparse.Namespace) -> int:
    from capture.app.orchestrator import Capture
    from devices import parse_device_spec

    _check_duration(args.duration)
    s = _settings(args)
    specs = [parse_device_spec(d) for d in args.device] if args.device else list(s.devices)
    if not specs:
        raise ConfigError("no devices: give -d DEVICE (e.g. -d synth://imu?rate=200) or [[devices]] in --config")
    stop = _stop_on_signals()
    cap = Capture(specs, output=args.output, overwrite=s.recorder.overwrite, max_loss_s=s.recorder.max_loss_s,
                  fsync=s.recorder.fsync, recorder_max_bytes=s.bus.recorder_max_mb << 20,
                  live_queue=s.bus.live_queue, reconnect=s.reconnect_policy(),
                  meta={"command": " ".join(sys.argv), "config": ",".join(s.sources)})
    if s.orientation.enabled:
        from capture.calibration_store import CalibrationStore

        try:
            proc = cap.enable_orientation(s.orientation.filter, s.orientation.auto_bias,
                                          store=CalibrationStore(s.calibration.dir or None))
        except BaseException:
            cap.stop()
            raise
        if proc is None:
            print("perfcap: note: --orientation: no IMU stream among the devices", file=sys.stderr)
    names = ", ".join(f"{d.name} ({d.kind} @ {d.transport.url})" for d in cap.devices)
    print(f"recording {names} to {args.output}" + (f" for {args.duration:g} s" if args.duration else
                                                   " until Ctrl-C"), file=sys.stderr)
    report = cap.run(args.duration, stop=stop, on_tick=None if args.quiet else _live_line)
    return _print_capture(report, args.json)


def _print_qr(url: str) -> None:
    """The URL as a QR code, when stdout is a terminal (a phone camera opens it)."""
    if not sys.stdout.isatty():
        return
    try:
        import qrcode

        q = qrcode.QRCode(border=1)
        q.add_data(url)
        q.make(fit=True)
        q.print_ascii(out=sys.stdout, tty=False, invert=True)
    except Exception as exc:  # noqa: BLE001 - the URL is printed as text anyway
        log.info("no QR code: %s", exc)


#: ``perfcap serve`` flags that are ``[serve]`` settings (flag dest -> key)
_SERVE_FLAGS = ("host", "port", "public_host", "control_host", "control_port", "state_dir", "sessions_dir",
                "osc_port", "osc_allow", "osc_map", "hyperimu_port", "hyperimu_tcp_port", "hyperimu_allow",
                "hyperimu_sensors", "max_phones", "max_message_kb", "max_rate", "max_connections_per_host")


def _serve_overrides(args: argparse.Namespace) -> dict[str, Any]:
    o: dict[str, Any] = {k: getattr(args, k) for k in _SERVE_FLAGS}
    if args.no_tls:
        o["tls"] = False
    if args.no_mdns:
        o["mdns"] = False
    if args.connect_sensorserver:
        o["connect_sensorserver"] = True
    if args.phone_name:
        o["phone_names"] = ",".join(args.phone_name)
    return o


def _serve_config(ss: Any) -> Any:
    """``ServeConfig`` from the ``[serve]`` settings.

    Raises:
        ConfigError: a phone name entry is malformed.
    """
    from capture.app.serve.gateway import Limits
    from capture.app.serve.service import ServeConfig

    names = {}
    for item in (i.strip() for i in ss.phone_names.split(",")):
        if not item:
            continue
        key, sep, name = item.partition("=")
        if not sep or "/" not in key or not name:
            raise ConfigError(f"phone name {item!r}: expected PROTOCOL/ID=NAME, e.g. page/5f2c0a=pocket")
        names[key.strip()] = name.strip()
    limits = Limits(max_message_bytes=ss.max_message_kb * 1024, max_push_bytes=ss.max_push_mb << 20,
                    rate_hz=ss.max_rate, burst=max(ss.max_rate * 2, 1.0), max_connections=ss.max_phones * 2,
                    max_connections_per_host=ss.max_connections_per_host)
    return ServeConfig(host=ss.host, port=ss.port, tls=ss.tls, public_host=ss.public_host,
                       control_host=ss.control_host, control_port=ss.control_port, state_dir=ss.state_dir,
                       mdns=ss.mdns, mdns_interfaces=ss.mdns_interfaces,
                       connect_sensorserver=ss.connect_sensorserver, sensorserver_types=ss.sensorserver_types,
                       osc_port=ss.osc_port, osc_allow=ss.osc_allow, osc_map=ss.osc_map,
                       hyperimu_port=ss.hyperimu_port, hyperimu_tcp_port=ss.hyperimu_tcp_port,
                       hyperimu_allow=ss.hyperimu_allow, hyperimu_sensors=ss.hyperimu_sensors,
                       max_phones=ss.max_phones, limits=limits, names=names, sessions_dir=ss.sessions_dir)


def cmd_serve(args: argparse.Namespace) -> int:
    import asyncio

    from capture.app.serve.service import Service
    from devices import parse_device_spec

    _check_duration(args.duration)
    s = _settings(args)
    cfg = _serve_config(s.serve)
    specs = [parse_device_spec(d) for d in args.device] if args.device else list(s.devices)
    if args.rotate_token:
        from capture.app.serve.security import TokenStore
        from capture.app.serve.service import default_state_dir

        TokenStore(Path(cfg.state_dir) if cfg.state_dir else default_state_dir()).rotate()
    service = Service(cfg, specs, reconnect=s.reconnect_policy(),
                      capture_options={"max_loss_s": s.recorder.max_loss_s, "fsync": s.recorder.fsync,
                                       "recorder_max_bytes": s.bus.recorder_max_mb << 20,
                                       "live_queue": s.bus.live_queue})

    if args.record:  # before anything starts, so the take has the devices' first bytes
        try:
            service.start_recording(args.record, overwrite=s.recorder.overwrite, anywhere=True)
        except BaseException:
            service.capture.stop()
            raise

    def ready(svc: Service) -> None:
        ep = svc.endpoints
        out(f"perfcap {__version__} serve")
        out(f"  phone page      {ep.page_url}   (open on the phone; same Wi-Fi)")
        out(f"  pairing link    {ep.pair_url}")
        out(f"  pairing token   {svc.tokens.token}   (shown once; rotate with --rotate-token or POST /api/token/rotate)")
        if ep.fingerprint:
            out(f"  TLS certificate SHA-256 {ep.fingerprint}")
            out("                  (self-signed: the phone warns once; check that it shows this fingerprint)")
        out(f"  Sensor Logger   push URL {ep.sensorlogger_url}")
        if ep.osc_port:
            out(f"  OSC (ZIG SIM/GyrOSC)  udp port {ep.osc_port}, map {cfg.osc_map}, from {cfg.osc_allow}")
        if ep.hyperimu_port or ep.hyperimu_tcp_port:
            out(f"  HyperIMU        udp {ep.hyperimu_port or 'off'}, tcp {ep.hyperimu_tcp_port or 'off'},"
                f" sensors {cfg.hyperimu_sensors}, from {cfg.hyperimu_allow}")
        if ep.control_url:
            out(f"  control API     {ep.control_url}  (Authorization: Bearer <token>)")
        out(f"  mDNS            {ep.advertised or 'off: ' + str(ep.mdns_error or 'disabled')}")
        _print_qr(ep.pair_url)
        if svc.capture.output:
            out(f"  recording to    {svc.capture.output}")
        out("Ctrl-C stops and flushes the recording.")
        sys.stdout.flush()

    async def main_async() -> Any:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, lambda sig=sig: (
                print(f"\nperfcap: {signal.Signals(sig).name} received, stopping and flushing", file=sys.stderr),
                service.request_stop()))
        if args.duration:
            loop.call_later(args.duration, service.request_stop)

        async def ticker() -> None:
            t0 = loop.time()
            while True:
                await asyncio.sleep(args.status_every)
                _live_line(service.capture, loop.time() - t0)

        task = loop.create_task(ticker()) if not args.quiet and args.status_every > 0 else None
        try:
            return await service.run(on_ready=ready)
        finally:
            if task is not None:
                task.cancel()

    report = asyncio.run(main_async())
    rej = service.gateway.rejected.as_dict()
    if rej:
        out("refused input: " + ", ".join(f"{k} {v}" for k, v in sorted(rej.items())))
    if report is None:
        return EXIT_BAD_INPUT
    code = _print_capture(report, args.json)
    return 0 if code == 1 and not service.capture.devices else code


def _print_capture(report: Any, as_json: bool) -> int:
    if as_json:
        out(json.dumps({"duration_s": report.duration_s, "output": report.output, "streams": report.streams,
                        "devices": report.devices, "subscribers": report.subscribers,
                        "recorder_error": report.recorder_error, "events": report.events}, default=str))
    else:
        out(f"captured {report.duration_s:.2f} s" + (f" into {report.output}" if report.output else ""))
        for name, s in report.streams.items():
            out(f"  {name:24s} {s['samples']:8d} samples  {s['rate_hz']:8.2f} Hz  {s['drops']} lost")
        for name, d in report.devices.items():
            extra = []
            if d["checksum_errors"] or d["framing_errors"]:
                extra.append(f"{d['checksum_errors'] + d['framing_errors']} bad frames, "
                             f"{d['skipped_bytes']} bytes skipped")
            if d["reconnects"]:
                extra.append(f"{d['reconnects']} reconnects")
            if d["clock_resets"]:
                extra.append(f"{d['clock_resets']} clock resets")
            out(f"  device {name}: {d['state']}, {d['chunks']} chunks, {d['bytes']} bytes"
                + (f"; {'; '.join(extra)}" if extra else ""))
        for sub in report.subscribers:
            if sub["dropped"]:
                out(f"  subscriber {sub['name']} dropped {sub['dropped']} items")
    if report.recorder_error:
        print(f"perfcap: error: recording failed: {report.recorder_error}", file=sys.stderr)
        return EXIT_CHECK_FAILED
    failed = [n for n, d in report.devices.items() if d["state"] == "failed"]
    if failed:
        print(f"perfcap: error: device(s) failed: {', '.join(failed)} (see the messages above)", file=sys.stderr)
        return EXIT_CHECK_FAILED
    never = [n for n, d in report.devices.items() if not d.get("opens", 1)]
    if never:
        for n in never:
            print(f"perfcap: error: device {n} was never opened during the take: {report.devices[n]['last_error']}",
                  file=sys.stderr)
        return EXIT_CHECK_FAILED
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from capture.app.replay import replay_session

    speed = 0.0 if args.fast else args.speed
    if speed is None:
        speed = 1.0
    if not math.isfinite(speed) or speed <= 0 and not args.fast:
        raise ConfigError(f"--speed must be a positive factor (use --fast for as fast as possible), not {speed}")
    if args.duration is not None:
        _check_duration(args.duration)
    if args.loop and args.duration is None and args.fast:
        raise ConfigError("--loop with --fast never ends; add --duration SECONDS")
    stop = _stop_on_signals()
    t0 = time.monotonic()
    rep = replay_session(args.session, speed=speed, loop=args.loop, verify=not args.no_verify, output=args.output,
                         overwrite=args.overwrite, stop=stop, duration_s=args.duration,
                         on_tick=None if args.quiet else _live_line, orientation=args.orientation,
                         orientation_filter=args.filter)
    wall = time.monotonic() - t0
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
            unver = [s for s, v in ver["streams"].items() if v.get("unverifiable")]
            if unver:
                out(f"  not verified (their recorded blocks are damaged): {', '.join(unver)}")
            if ver["equal"] or rep.stopped_early and not any(v["mismatches"] for v in ver["streams"].values()):
                n = sum(v["compared"] for v in ver["streams"].values())
                out(f"verified: all {n} replayed samples equal the recorded ones")
            else:
                for name, v in ver["streams"].items():
                    if v["mismatches"] or v["missing"]:
                        out(f"  MISMATCH {name}: {v['mismatches']} differ, {v['missing']} not reproduced")
                for name, m in ver["first_mismatch"].items():
                    out(f"  first difference in {name}: {m}")
    failed = [n for n, d in rep.capture.devices.items() if d["state"] == "failed"]
    if failed:
        print(f"perfcap: error: device(s) failed during replay: {', '.join(failed)}", file=sys.stderr)
        return EXIT_CHECK_FAILED
    if ver is not None and not ver["equal"] and not args.loop and not rep.stopped_early:
        print("perfcap: error: replayed samples differ from the recorded ones", file=sys.stderr)
        return EXIT_CHECK_FAILED
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    from capture.session import SessionReader
    from capture.summary import summarize

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
             else "no device clock (dejittered arrivals)" if clk else "")
        out(f"  {st['name']:24s} {st['kind']:8s} {st['samples']:8d} samples {st['rate_hz']:9.2f} Hz "
            f"{st['drops']:5d} drops  {c}")
    if s["events"]:
        out("  events: " + ", ".join(f"{k} x{v}" for k, v in sorted(s["events"].items())))
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from capture.sample import NO_TIME
    from capture.session import SessionReader

    prog = Progress("reading", args.quiet)
    reader = SessionReader(args.session, progress=prog)
    prog.done()
    if os.path.exists(args.output) and not os.path.isdir(args.output):
        raise ConfigError(f"{args.output} exists and is not a directory")
    os.makedirs(args.output, exist_ok=True)
    ext = args.format
    planned = [os.path.join(args.output, s.replace("/", "__") + f".{ext}") for s in reader.streams]
    planned += [os.path.join(args.output, f"_events.{ext}")]
    clash = [p for p in planned if os.path.exists(p)]
    if clash and not args.overwrite:
        raise ConfigError(f"{clash[0]} already exists (use --overwrite to replace the export)")
    batches = reader.all_samples()
    total = 0
    for name, info in reader.streams.items():
        b = batches[name]
        path = os.path.join(args.output, name.replace("/", "__") + f".{ext}")
        cols = ["seq", "t_host_ns", "t_device_ns", "t_bus_ns"] + [f"{c}[{u}]" for c, u in zip(info.channels, info.units)]
        seq, th, td, tb, vals = (b.seq.tolist(), b.t_host_ns.tolist(), b.t_device_ns.tolist(), b.t_bus_ns.tolist(),
                                 b.values.tolist())
        try:
            with open(path, "w", newline="") as f:
                if ext == "csv":
                    w = csv.writer(f)
                    w.writerow(cols)
                    for i in range(len(seq)):
                        w.writerow([seq[i], th[i], "" if td[i] == NO_TIME else td[i], tb[i], *map(repr, vals[i])])
                else:
                    for i in range(len(seq)):
                        f.write(json.dumps({"stream": name, "seq": seq[i], "t_host_ns": th[i],
                                            "t_device_ns": None if td[i] == NO_TIME else td[i], "t_bus_ns": tb[i],
                                            "values": dict(zip(info.channels, [None if math.isnan(v) else v
                                                                               for v in vals[i]]))}) + "\n")
        except OSError as exc:
            raise ConfigError(f"cannot write {path}: {exc.strerror or exc}") from None
        total += len(seq)
    ev_path = os.path.join(args.output, f"_events.{ext}")
    evs = reader.events()
    try:
        with open(ev_path, "w", newline="") as f:
            if ext == "csv":
                w = csv.writer(f)
                w.writerow(["t_host_ns", "source", "kind", "detail"])
                for e in evs:
                    w.writerow([e.get("t_host_ns"), e.get("source"), e.get("kind"), e.get("detail")])
            else:
                for e in evs:
                    f.write(json.dumps(e) + "\n")
    except OSError as exc:
        raise ConfigError(f"cannot write {ev_path}: {exc.strerror or exc}") from None
    out(f"exported {total} samples of {len(reader.streams)} streams to {args.output}/ ({ext})")
    if reader.truncated:
        out(f"note: the session was not closed cleanly ({reader.truncated}); exported what it holds")
    if reader.damaged:
        out("note: damaged parts were skipped: " + ", ".join(f"{n} x {w}" for w, n in sorted(reader.damaged.items())))
    return 0


# ------------------------------------------------------------------------------------------------
# perfcap cycle: one clean loop from a take of several performed loops
MCAP_MAGIC = b"\x89MCAP0\r\n"
CSV_TIME_COLUMNS = ("seconds_elapsed", "t", "time_s", "t_s", "time[s]", "time (s)", "time", "timestamp")
EXPORT_TIMING_COLUMNS = ("seq", "t_host_ns", "t_device_ns", "t_bus_ns")
EXIT_NO_CYCLE = 1  # the input was read but holds no cycle (as grep's 1 for "no match")


@dataclass
class _CycleInput:
    """What ``perfcap cycle`` extracts from: times (s), values (n, C) and how to read the columns."""

    source: str                          # the file, and the stream for a session
    t: Any                               # (n,) seconds (a session's: from the stream's first sample)
    values: Any                          # (n, C)
    channels: list[str]
    stream: str | None = None
    quaternions: tuple[tuple[int, int, int, int], ...] = ()
    angles: tuple[int, ...] = ()
    angle_unit: str = "rad"
    origin_ns: int | None = None         # a session's: the bus time of t = 0
    dropped: int = 0                     # rows left out (an empty or non-finite value)


def _split_columns(spec: str | None) -> list[str] | None:
    if spec is None:
        return None
    names = [c.strip() for c in spec.split(",") if c.strip()]
    if not names:
        raise ConfigError("--columns needs at least one column name (A,B,...)")
    if len(set(names)) != len(names):
        raise ConfigError(f"--columns names a column twice: {spec}")
    return names


def _pick(available: list[str], wanted: list[str], what: str) -> list[int]:
    idx = []
    for name in wanted:
        if name not in available:
            raise ConfigError(f"no column {name!r} in {what}; its columns are: {', '.join(available)}")
        idx.append(available.index(name))
    return idx


def _cycle_session_input(reader: Any, stream: str | None, columns: list[str] | None) -> _CycleInput:

    path = reader.path
    if stream is not None and stream in reader.streams:
        b = reader.samples(stream)          # only the stream asked for (sessions can be large)
        if len(b.t_bus_ns):
            return _session_stream_input(reader, stream, b, columns)
    batches = {n: reader.samples(n) for n in reader.streams}
    filled = [n for n in reader.streams if len(batches[n].t_bus_ns) > 0]
    listing = ", ".join(f"{n} ({reader.streams[n].kind})" for n in filled) or "none"
    if stream is None:
        if not filled:
            raise ConfigError(f"{path}: the session holds no samples")
        if len(filled) == 1:
            stream = filled[0]
        else:
            for kinds in (("imu",), ("quat", "orientation"), ("euler",)):
                of_kind = [n for n in filled if reader.streams[n].kind in kinds]
                if len(of_kind) == 1:
                    stream = of_kind[0]
                    break
                if of_kind:
                    break
        if stream is None:
            raise ConfigError(f"{path} has {len(filled)} streams; choose one with --stream: {listing}")
    if stream not in reader.streams:
        raise ConfigError(f"{path} has no stream {stream!r}; its streams: {listing}")
    b = batches[stream]
    if len(b.t_bus_ns) == 0:
        raise ConfigError(f"stream {stream} of {path} holds no samples; streams with samples: {listing}")
    return _session_stream_input(reader, stream, b, columns)


def _session_stream_input(reader: Any, stream: str, b: Any, columns: list[str] | None) -> _CycleInput:
    import numpy as np

    path = reader.path
    info = reader.streams[stream]
    chans = list(info.channels)
    if columns is not None:
        idx = _pick(chans, columns, f"stream {stream}")
    elif info.kind == "imu":  # the temperature is no part of the motion (and drifts on its own)
        idx = [i for i, u in enumerate(info.units) if u != "degC"] or list(range(len(chans)))
    else:
        idx = list(range(len(chans)))
    values = np.asarray(b.values, np.float64)[:, idx]
    names = [chans[i] for i in idx]
    quats: tuple[tuple[int, int, int, int], ...] = ()
    angles: tuple[int, ...] = ()
    unit = "rad"
    if info.kind in ("quat", "orientation") and all(c in names for c in ("w", "x", "y", "z")):
        w, x, y, z = (names.index(c) for c in ("w", "x", "y", "z"))
        quats = ((w, x, y, z),)
    elif info.kind == "euler":
        units = {info.units[i] for i in idx}
        angles = tuple(range(len(idx)))
        unit = "deg" if units <= {"deg"} else "rad"
    origin = int(b.t_bus_ns[0])
    t = (np.asarray(b.t_bus_ns, np.int64) - origin) / 1e9
    keep = np.all(np.isfinite(values), axis=1)
    return _CycleInput(f"{path} {stream}", t[keep], values[keep], names, stream=stream, quaternions=quats, angles=angles,
                       angle_unit=unit, origin_ns=origin, dropped=int((~keep).sum()))


def _cycle_csv_input(path: str, columns: list[str] | None) -> _CycleInput:
    import numpy as np

    try:
        with open(path, newline="", encoding="utf-8-sig") as f:   # (a BOM is not part of the first name)
            head = f.read(8192)
            f.seek(0)
            try:
                dialect: Any = csv.Sniffer().sniff(head, delimiters=",;\t")
            except csv.Error:
                dialect = csv.excel
            rows = [r for r in csv.reader(f, dialect) if r and any(c.strip() for c in r)]
    except UnicodeDecodeError:
        raise ConfigError(f"{path} is neither a perfcap session nor a text CSV file") from None
    except (OSError, csv.Error) as exc:
        raise ConfigError(f"cannot read {path}: {getattr(exc, 'strerror', None) or exc}") from None
    if not rows:
        raise ConfigError(f"{path} is empty: expected a CSV with a time column (s) and channel columns")

    def number(x: str) -> float | None:
        try:
            return float(x)
        except ValueError:
            return None

    header = any(number(c) is None for c in rows[0] if c.strip())
    names = [c.strip() for c in rows[0]] if header else [f"c{i}" for i in range(len(rows[0]))]
    body = rows[1:] if header else rows
    # a trailing delimiter on every line makes an empty, unnamed column: drop it
    while len(names) > 1 and not names[-1] and all(len(r) == len(names) and not r[-1].strip() for r in body):
        names.pop()
        body = [r[:-1] for r in body]
    if len(names) < 2:
        raise ConfigError(f"{path}: expected a time column and at least one channel column, found one column")
    lower = [n.lower() for n in names]
    t_col, t_scale = 0, 1.0
    for cand in CSV_TIME_COLUMNS:
        if cand in lower:
            t_col = lower.index(cand)
            break
    else:
        if "t_bus_ns" in lower:  # a perfcap export
            t_col, t_scale = lower.index("t_bus_ns"), 1e-9
    if columns is not None:
        idx = _pick(names, columns, path)
        if t_col in idx:
            raise ConfigError(f"--columns: {names[t_col]!r} is the time column")
    else:
        # (a perfcap export's timing columns, other clocks (Sensor Logger's epoch ns 'time' beside its
        # 'seconds_elapsed') and an IMU's temperature are no part of the motion)
        idx = [i for i, n in enumerate(lower) if i != t_col and n not in EXPORT_TIMING_COLUMNS
               and n not in CSV_TIME_COLUMNS and not n.endswith("[degc]")]
        if not idx:
            raise ConfigError(f"{path}: no channel columns besides the time column {names[t_col]!r}")
    data = np.full((len(body), len(idx) + 1), np.nan)
    for r, row in enumerate(body):
        if len(row) != len(names):
            raise ConfigError(f"{path} line {r + 1 + header}: {len(row)} fields where the header has {len(names)}")
        for j, col in enumerate([t_col, *idx]):
            cell = row[col].strip()
            if cell:
                v = number(cell)
                if v is None:
                    raise ConfigError(f"{path} line {r + 1 + header}, column {names[col]!r}: {cell!r} is not a number")
                data[r, j] = v
    keep = np.all(np.isfinite(data), axis=1)
    data = data[keep]
    if not len(data):
        raise ConfigError(f"{path}: no rows with a time and every channel")
    if t_scale == 1.0 and len(data) > 2 and float(np.median(np.diff(data[:, 0]))) >= 1e5:
        t_scale = 1e-9   # steps of more than a day: the time column counts nanoseconds (an epoch clock)
    return _CycleInput(path, data[:, 0] * t_scale, data[:, 1:], [names[i] for i in idx],
                       dropped=int((~keep).sum()))


def _cycle_input(path: str, stream: str | None, columns: list[str] | None) -> _CycleInput:
    if not os.path.exists(path):
        raise ConfigError(f"{path}: no such file")
    if os.path.isdir(path):
        raise ConfigError(f"{path} is a directory, not a session or CSV file")
    try:
        with open(path, "rb") as f:
            magic = f.read(len(MCAP_MAGIC))
    except OSError as exc:
        raise ConfigError(f"cannot read {path}: {exc.strerror or exc}") from None
    if magic == MCAP_MAGIC:
        from capture.session import SessionReader

        return _cycle_session_input(SessionReader(path), stream, columns)
    if stream is not None:
        raise ConfigError(f"--stream is for perfcap sessions; {path} is not one (for a CSV, use --columns)")
    return _cycle_csv_input(path, columns)


def extract_cycle(inp: _CycleInput, seed: int = 0) -> Any:
    """``cycles.extract`` on a read input, timed (``elapsed_ms`` is the extraction alone)."""
    from dataclasses import replace

    from cycles import extract

    t0 = time.perf_counter()
    cyc = extract(inp.t, inp.values, channels=inp.channels, quaternions=inp.quaternions, angles=inp.angles,
                  angle_unit=inp.angle_unit, seed=seed)
    return replace(cyc, elapsed_ms=(time.perf_counter() - t0) * 1e3)


def write_cycle_report(cyc: Any, path: str, title: str) -> None:
    """The report image, with its failures as one-line ``ConfigError`` s."""
    try:
        from cycles.report import write_report
    except ImportError as exc:
        raise ConfigError(f"the report needs matplotlib ({exc}); pip install 'matplotlib>=3.8'") from None
    try:
        write_report(cyc, path, title=title)
    except OSError as exc:
        raise ConfigError(f"cannot write {path}: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise ConfigError(f"cannot write the report {path}: {exc}") from None


def cmd_cycle(args: argparse.Namespace) -> int:
    from capture.errors import CycleError

    columns = _split_columns(args.columns)
    inp = _cycle_input(args.input, args.stream, columns)
    if len(inp.t) < 2:
        raise ConfigError(f"{inp.source}: {len(inp.t)} sample(s); a cycle needs several loops of motion")
    try:
        cyc = extract_cycle(inp, args.seed)
    except CycleError as exc:
        print(f"perfcap: no cycle in {inp.source}: {exc}", file=sys.stderr)
        return EXIT_NO_CYCLE
    except ValueError as exc:
        raise ConfigError(f"{inp.source}: {exc}") from None
    if args.output:
        try:
            cyc.write_csv(args.output)
        except OSError as exc:
            raise ConfigError(f"cannot write {args.output}: {exc.strerror or exc}") from None
    if args.report:
        write_cycle_report(cyc, args.report, f"{inp.source}: {len(inp.channels)} channel(s)")
    s = cyc.summary()
    if args.json:
        s.update({"input": args.input, "stream": inp.stream,
                  "time_origin_ns": inp.origin_ns, "input_samples": len(inp.t),
                  "rows_skipped": inp.dropped, "csv": args.output, "report": args.report})
        out(json.dumps(s))
        return 0
    out(f"cycle: period {cyc.period_s:.4f} s from {cyc.loops} loops, confidence {cyc.confidence:.2f}, "
        f"closure error {cyc.closure_error:.3g} sd, extracted in {cyc.elapsed_ms:.1f} ms")
    origin = "s from the stream's first sample" if inp.origin_ns is not None else "s"
    cuts = ", ".join(f"{c:.3f}" for c in cyc.cuts_s)
    out(f"  input: {inp.source}, {len(inp.channels)} channel(s) ({', '.join(inp.channels[:8])}"
        f"{', ...' if len(inp.channels) > 8 else ''}), {len(inp.t)} samples"
        + (f" ({inp.dropped} rows with empty or non-finite values skipped)" if inp.dropped else ""))
    out(f"  cuts in the input ({origin}): {cuts}")
    for note in cyc.notes:
        out(f"  note: {note}")
    if args.output:
        out(f"  loop written to {args.output} ({len(cyc.times_s)} rows: t, {len(cyc.channels)} channel(s))")
    if args.report:
        out(f"  report written to {args.report}")
    return 0


DEMO_LOOP_S = 1.2
DEMO_DEVICES = [
    # A WT901 on the wrist over USB: device clock 80 ppm fast, 2 ms of USB arrival jitter. Its wearer
    # repeats one gesture, each loop 1.2 s +- 8 % (the demo extracts the cycle from it).
    ("wrist", f"synth://imu?rate=200&seed=1&drift_ppm=80&jitter_ms=2&truth=true&loop_s={DEMO_LOOP_S}"),
    # One on the ankle through an FTDI adapter: no time packets, 16 ms latency-timer bursts, a little line noise.
    ("ankle", "synth://imu?rate=200&seed=2&device_clock=false&burst_ms=16&garbage=0.005"),
    # One on the head whose clock passes midnight two seconds in (the WT901 clock wraps daily).
    ("head", "synth://imu?rate=100&seed=3&drift_ppm=-40&jitter_ms=1&start_ms=86398000&truth=true"),
    # A DualSense over Bluetooth: the handshake reads its factory calibration; its own clock is 30 ppm
    # fast and Bluetooth adds up to 3 ms of arrival jitter.
    ("pad", "dualsense@simhid://dualsense?bus=bluetooth&seed=5&drift_ppm=30&jitter_ms=3&truth=true"),
    # A pen tablet at 200 Hz, read through its report descriptor.
    ("pen", "hid@simhid://pen?seed=6"),
]


DEMO_UNPLUG_AT, DEMO_UNPLUG_FOR = 3.0, 0.5


def _start_serial_sim(duration: float) -> tuple[Any, str] | None:
    """``perfcap sim serial`` in a child process (as a real device is outside perfcap); (process, port
    path), or None where ptys do not exist (Windows) or it fails to start (said, not hidden)."""
    import subprocess

    if os.name != "posix":
        out("  (no simulated serial port on this OS: ptys are POSIX only)")
        return None
    link = os.path.join(tempfile.mkdtemp(prefix="perfcap-demo-port-"), "ttyWT901")
    cmd = [sys.executable, "-m", "capture.app.cli", "sim", "serial", "--kind", "witmotion", "--rate", "200",
           "--seed", "4", "--link", link, "--unplug-every", str(DEMO_UNPLUG_AT), "--unplug-for", str(DEMO_UNPLUG_FOR),
           "--duration", str(duration + 30)]
    try:
        proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                text=True)
    except OSError as exc:
        out(f"  (the simulated serial port could not start: {exc}; continuing without it)")
        return None
    line = proc.stdout.readline().strip() if proc.stdout else ""
    if line != link:
        _stop_serial_sim(proc)
        out("  (the simulated serial port did not start; continuing without it)")
        return None
    return proc, link


def _stop_serial_sim(proc: Any) -> None:
    import subprocess

    try:
        if proc.stdin:
            proc.stdin.write("quit\n")
            proc.stdin.close()
        proc.wait(5)
    except (OSError, ValueError, subprocess.TimeoutExpired):
        proc.kill()
        proc.wait()
    finally:
        if proc.stdout:
            proc.stdout.close()


def _start_demo_service(devices: list[str], path: str, overwrite: bool) -> tuple[Any, Any]:
    """The demo's devices in a ``perfcap serve`` service on loopback, recording from the start."""
    import secrets

    from capture.app.serve.service import ServeConfig, Service, ServiceThread

    cfg = ServeConfig(host="127.0.0.1", port=0, control_port=-1, mdns=False,
                      state_dir=tempfile.mkdtemp(prefix="perfcap-demo-serve-"), token=secrets.token_urlsafe(18),
                      names={"page/demo-phone": "phone"})
    service = Service(cfg, devices)
    try:
        service.capture.start_recording(path, overwrite=overwrite, meta={"command": "perfcap demo"})
    except BaseException:
        service.capture.stop()
        raise
    return service, ServiceThread(service).start()


def _start_demo_phone(service: Any, duration: float) -> Any:
    """A simulated phone running the built-in page, through the service's real TLS WebSocket."""
    from importlib.metadata import entry_points

    eps = {ep.name: ep for ep in entry_points(group="perfcap.sims")}
    if "phone" not in eps:
        log.warning("no simulated phone (is perfcap installed with pip install -e .?)")
        return None
    mod = eps["phone"].load().__module__
    import importlib

    m = importlib.import_module(mod)
    ep = service.endpoints
    url = ep.page_url.replace("https://", "wss://").replace("http://", "ws://") + "ws/phone"
    # the phone performs the puppeteer's choreography, so the demo's puppet walks, runs, hops and crouches
    phone = m.SimPagePhone(url, service.tokens.token, "demo-phone", rate_hz=60.0, duration_s=duration + 1.0,
                           seed=7, fingerprint=ep.fingerprint or None, motion="puppeteer")
    return m.PhoneThread(phone).start()


def cmd_demo(args: argparse.Namespace) -> int:
    from capture.app.replay import replay_session
    from capture.session import SessionReader
    from capture.summary import summarize

    _check_duration(args.duration)
    path = args.output or os.path.join(tempfile.mkdtemp(prefix="perfcap-demo-"), "demo.mcap")
    devices = list(DEMO_DEVICES)
    sim = _start_serial_sim(args.duration)
    if sim is not None:
        devices.append(("hand", f"witmotion@serial://{sim[1]}?rate=200&device_clock=true"))
    out(f"perfcap {__version__} demo: {len(devices)} simulated IMUs through the real codec, clock sync, bus and"
        " recorder")
    for name, url in devices:
        out(f"  {name:6s} {url}")
    if sim is not None:
        out(f"  (hand is a WT901 served on a pty by 'perfcap sim serial' in another process, read through pyserial;"
            f" it is unplugged {DEMO_UNPLUG_AT:g} s in for {DEMO_UNPLUG_FOR:g} s)")
    out("  phone  the built-in phone page, simulated: 60 Hz devicemotion over a WebSocket with TLS to the service"
        " on loopback (token, certificate pinned)")
    stop = _stop_on_signals()
    phone = None
    try:
        service, st = _start_demo_service([f"{n}={u}" for n, u in devices], path, args.overwrite)
        cap = service.capture
        follow = _demo_follower(cap)
        try:
            phone = _start_demo_phone(service, args.duration)
            t0 = time.monotonic()
            next_tick = 1.0
            while not stop.is_set():
                elapsed = time.monotonic() - t0
                if elapsed >= args.duration:
                    break
                stop.wait(min(0.05, args.duration - elapsed))
                if not args.quiet and elapsed >= next_tick:
                    _live_line(cap, elapsed)
                    next_tick += 1.0
        finally:
            if phone is not None:
                phone.stop()
            report = st.stop()
    finally:
        if sim is not None:
            _stop_serial_sim(sim[0])
    code = _print_capture(report, False)
    if code:
        return code
    reader = SessionReader(path)
    s = summarize(reader)
    # The simulator knows when each reading really happened: compare the bus times with that.
    accuracy: dict[str, float] = {}
    for d in cap.devices:
        truth = getattr(d.transport, "truth_ns", None)
        if truth and f"{d.name}/imu" in reader.streams:
            import numpy as np

            b = reader.samples(f"{d.name}/imu")
            lat = int(float(getattr(d.transport, "opts", {}).get("latency_ms", 0.0)) * 1e6)
            tt = np.sort(np.asarray(truth, np.int64)) + lat
            # each sample against the true reading time nearest to it (readings are >= 4 ms apart, errors
            # far smaller), so readings a handshake consumed do not shift the pairing
            j = np.clip(np.searchsorted(tt, b.t_bus_ns), 1, len(tt) - 1)
            near = np.where(np.abs(tt[j - 1] - b.t_bus_ns) < np.abs(tt[j] - b.t_bus_ns), tt[j - 1], tt[j])
            true_t = near
            err = np.abs(b.t_bus_ns - true_t)
            settled = err[true_t >= true_t[0] + 1_000_000_000] if len(true_t) else err
            if settled.size:
                accuracy[d.name] = float(np.percentile(settled, 99)) / 1e6
    if phone is not None and phone.phone.t0_host_ns is not None and "phone/imu" in reader.streams:
        import numpy as np

        b = reader.samples("phone/imu")
        ph = phone.phone
        true_t = ph.t0_host_ns + b.t_device_ns - int(ph.t0_ms * 1e6)  # page event time -> host clock
        err = np.abs(b.t_bus_ns - true_t)
        settled = err[true_t >= true_t[0] + 1_000_000_000]
        if settled.size:
            accuracy["phone"] = float(np.percentile(settled, 99)) / 1e6
    out(f"\nsession {path}: {s['size_bytes'] / 1024:.0f} KiB for {(s['raw_bytes'] or 0) / 1024:.0f} KiB of raw device bytes")
    truth = {"wrist": 80.0, "head": -40.0, "pad": 30.0}
    for st in s["streams"]:
        if not st["name"].endswith("/imu"):
            continue
        clk = st["clock"] or {}
        dev = st["device"]
        if clk.get("pseudo"):
            desc = "no device clock: bus times from the dejittered arrival pattern"
        else:
            desc = f"device clock fitted at {clk.get('drift_ppm', 0):+.1f} ppm (simulated {truth.get(dev, 0):+.0f}), " \
                   f"{clk.get('epochs', 1)} epoch(s)"
            if dev in accuracy:
                desc += f"; bus times within {accuracy[dev]:.2f} ms of the true reading times (p99, after the first second)"
        if dev == "phone" and phone is not None:
            desc += f"; {phone.phone.events} events sent, over TLS + WebSocket"
        if dev == "hand" and sim is not None and st["drops"]:
            desc += f"; its drops are the readings sent during the {DEMO_UNPLUG_FOR:g} s it was unplugged"
        out(f"  {st['name']:12s} {st['samples']:6d} samples {st['rate_hz']:7.2f} Hz  {st['drops']} drops  {desc}")
    rep = replay_session(path, speed=0)
    ver = rep.verification or {}
    n = sum(v["compared"] for v in ver.get("streams", {}).values())
    if ver.get("equal"):
        out(f"replayed the session through the same codecs: all {n} samples equal the recorded ones")
    else:
        out(f"replay differs from the recording: {ver.get('first_mismatch')}")
        return EXIT_CHECK_FAILED
    _demo_cycle(reader, cap)
    if follow is not None:
        first = follow[1]
        if first:
            t_first, c_first = first[0]
            out(f"  live: following wrist/imu on the bus, the first cycle came {t_first:.1f} s into the take"
                f" ({c_first.loops} loops, {c_first.period_s:.3f} s), then improved {len(first) - 1} time(s)")
        else:
            out(f"  live: following wrist/imu on the bus, no cycle during the take"
                f" ({follow[0].extractor.last_error or 'too few loops'})")
    _demo_puppet(reader)
    out(f"\nnext: perfcap info {path}   |   perfcap replay {path} --speed 2   |   "
        f"perfcap export {path} --format csv -o export/   |   perfcap cycle {path} --stream wrist/imu")
    return 0


def _demo_follower(cap: Any) -> tuple[Any, list[tuple[float, Any]]] | None:
    """Streaming cycle extraction on the live bus while the demo runs: when did a cycle first come,
    and how often did it improve."""
    from capture.app.cycle_follow import CycleFollower

    got: list[tuple[float, Any]] = []
    t0 = time.monotonic()
    try:
        follower = CycleFollower("wrist/imu", lambda c: got.append((time.monotonic() - t0, c)),
                                 columns=[0, 1, 2, 3, 4, 5])
        cap.subscribe(follower, name="cycle-follower")
    except (CaptureError, ValueError) as exc:
        log.warning("no live cycle follower: %s", exc)
        return None
    return follower, got


def _demo_cycle(reader: Any, cap: Any) -> None:
    """The cycle of the wrist's repeated gesture, from the recorded session, against the simulator's
    truth (the mean loop duration over the recorded span); the loop CSV and the report beside the
    session. A failure is one line: the demo goes on."""
    from capture.errors import CycleError

    name = "wrist/imu"
    folder = os.path.dirname(os.path.abspath(reader.path))
    png, loop_csv = os.path.join(folder, "wrist_cycle.png"), os.path.join(folder, "wrist_cycle.csv")
    try:
        inp = _cycle_session_input(reader, name, None)
        cyc = extract_cycle(inp)
    except (CycleError, ConfigError, ValueError) as exc:
        out(f"cycle: no cycle extracted from {name} ({exc})")
        return
    truth = ""
    wrist = next((d for d in cap.devices if d.name == "wrist"), None)
    tr = getattr(wrist, "transport", None)
    motion, readings = getattr(tr, "motion", None), getattr(tr, "truth_ns", None)
    if motion is not None and getattr(motion, "loop_s", None) and readings and inp.origin_ns is not None:
        # bus time -> device seconds (the first reading is device second 0); the simulated mean loop
        # duration over the recorded span, in host seconds as the bus times are
        opts = getattr(tr, "opts", {})
        drift = float(opts.get("drift_ppm", 0.0)) * 1e-6
        lat_ns = float(opts.get("latency_ms", 0.0)) * 1e6
        d0 = (inp.origin_ns - lat_ns - readings[0]) / 1e9 * (1.0 + drift)
        d1 = d0 + float(inp.t[-1]) * (1.0 + drift)
        mean_s = motion.mean_loop_s(d0, d1) / (1.0 + drift)
        truth = f" (simulated: {mean_s:.4f} s mean loop, {100.0 * (cyc.period_s / mean_s - 1.0):+.2f} %)"
    out(f"cycle: the wrist repeats a gesture ({DEMO_LOOP_S:g} s +- 8 % per loop): period {cyc.period_s:.4f} s"
        f"{truth} from {cyc.loops} loops of {name}, confidence {cyc.confidence:.2f}, in {cyc.elapsed_ms:.0f} ms")
    try:
        cyc.write_csv(loop_csv)
        write_cycle_report(cyc, png, f"perfcap demo: the wrist's gesture ({name})")
    except (ConfigError, OSError) as exc:
        out(f"  (the loop or its report could not be written: {exc})")
        return
    out(f"  loop written to {loop_csv}; report (the aligned loops and the cycle per channel) {png}")


# ------------------------------------------------------------------------------------------------
# perfcap puppet: a character on an invisible stick from a phone
def _check_writable(path: str | None, flag: str) -> None:
    if path is None:
        return
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise ConfigError(f"{flag} {path}: the folder {folder} does not exist")
    if os.path.isdir(path):
        raise ConfigError(f"{flag} {path} is a directory")


def _puppet_outputs(run: Any, args: argparse.Namespace) -> tuple[list[str], list[str]]:
    """Write the BVH and the timeline, each whether or not the other could be written.

    Returns:
        (what was written, as summary lines; what could not be, one message each).
    """
    from retarget.bvh import write_bvh

    lines, errors = [], []
    if args.output:
        clip = run.clip(os.path.splitext(os.path.basename(args.output))[0] or "puppet")
        try:
            write_bvh(args.output, clip)
        except OSError as exc:
            errors.append(f"cannot write {args.output}: {exc.strerror or exc}")
        else:
            lines.append(f"  BVH written to {args.output} ({clip.n_frames} frames at {clip.fps:g} fps,"
                         f" {clip.skeleton.n_joints} joints)")
    if args.timeline:
        tl = run.timeline()
        try:
            with open(args.timeline, "w", encoding="utf-8") as f:
                f.write("[\n" + ",\n".join(" " + json.dumps(e) for e in tl) + "\n]\n")
        except OSError as exc:
            errors.append(f"cannot write {args.timeline}: {exc.strerror or exc}")
        else:
            lines.append(f"  timeline written to {args.timeline} ({len(tl)} entries)")
    return lines, errors


def cmd_puppet(args: argparse.Namespace) -> int:
    from capture.app.puppet_run import (
        PuppetRun,
        VmcSender,
        check_rate,
        parse_host_port,
        probe_writable,
        read_trajectory,
        session_track,
    )

    rate = check_rate(args.rate)
    if args.duration is not None:
        if not args.phone:
            raise ConfigError("--duration is for --phone (a trajectory or a session is driven to its end)")
        _check_duration(args.duration)
    if args.device is not None and not args.session:
        raise ConfigError("--device chooses the phone of a --session")
    _check_writable(args.output, "-o")
    _check_writable(args.timeline, "--timeline")
    probe_writable(args.output, "-o")          # before the performance, not after it
    probe_writable(args.timeline, "--timeline")
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
    run = PuppetRun(retargeter, rate=rate, vmc=vmc, keep_frames=bool(args.output))
    code = 0
    try:
        if track is None:
            source, code, notes = _puppet_live(args, spec, run)
        else:
            source = track.source
            for inp in track.resample(rate):
                try:
                    run.step(inp)
                except ValueError as exc:   # an input the retargeter cannot follow: bad input, one line
                    raise ConfigError(f"{source}: the puppet cannot follow the input at {inp.t:.6g} s"
                                      f" ({' '.join(str(exc).split())})") from None
    finally:
        if vmc is not None:
            vmc.close()
    if not run.frames:
        print(f"perfcap: error: no phone orientation from {source}: the puppet was not driven", file=sys.stderr)
        return EXIT_CHECK_FAILED
    out(f"puppet: {run.frames} frames at {rate:g} Hz ({run.duration:.2f} s) from {source}")
    for note in notes:
        out(f"  note: {note}")
    out("  states: " + ", ".join(f"{s} {t:.2f} s" for s, t in run.state_times().items())
        + f" ({len(run.timeline()) - 1} change(s))")
    written, unwritten = _puppet_outputs(run, args)
    for line in written:
        out(line)
    if vmc is not None:
        out(f"  VMC: {vmc.sent} bundle(s) sent to {args.vmc} over UDP"
            + (f", {vmc.errors} send error(s) (first: {vmc.first_error})" if vmc.errors else ""))
        if vmc.errors and not vmc.sent:
            print(f"perfcap: error: no VMC bundle could be sent to {args.vmc} ({vmc.first_error})", file=sys.stderr)
            code = code or EXIT_CHECK_FAILED
    if unwritten:
        print(f"perfcap: error: {'; '.join(unwritten)}", file=sys.stderr)
        code = EXIT_BAD_INPUT
    return code


def _puppet_live(args: argparse.Namespace, spec: Any, run: Any) -> tuple[str, int, list[str]]:
    """``--phone``: the device on a bus, followed until Ctrl-C, ``--duration`` or its end."""
    from capture.app.orchestrator import Capture
    from capture.app.puppet_run import PuppetFollower

    cap = Capture([spec], meta={"command": " ".join(sys.argv)})
    try:
        dev = cap.devices[0]
        follower = PuppetFollower.for_device(dev.name, dev.streams, run, hold=True if args.hold else None)
        cap.add_processor(follower, name="puppet")   # follows the phone, publishes <device>/puppet
    except BaseException:
        cap.stop()
        raise
    notes = []
    if follower.hold:
        notes.append("--hold: the phone counts as held throughout" if args.hold else
                     f"{dev.name} has no touch stream: the phone counts as held throughout")
    else:
        notes.append(f"the puppet is grabbed while the screen of {dev.name} is touched")
    print(f"puppet: following {follower.attitude.name} of {dev.name} ({dev.kind} @ {dev.transport.url})"
          + (f" for {args.duration:g} s" if args.duration else " until Ctrl-C"), file=sys.stderr)
    stop = _stop_on_signals()
    report = cap.run(args.duration, stop=stop, on_tick=None if args.quiet else _live_line)
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
        print(f"perfcap: error: device {n} failed: {report.devices[n]['last_error']}", file=sys.stderr)
        code = EXIT_CHECK_FAILED
    return f"{dev.name} ({follower.samples} attitude samples)", code, notes


def _demo_puppet(reader: Any) -> None:
    """The puppet driven by the simulated phone's recorded attitude; ``puppet.bvh`` beside the session.
    A failure is one line: the demo goes on."""
    import numpy as np

    from capture.app.puppet_run import PuppetRun, session_track
    from retarget.bvh import write_bvh

    path = os.path.join(os.path.dirname(os.path.abspath(reader.path)), "puppet.bvh")
    try:
        track = session_track(reader, "phone")
        run = PuppetRun(rate=60.0)                      # builds the blend and its probe table
        frames = track.resample(60.0)
        t0 = time.perf_counter()
        run.run(frames)
        ms = (time.perf_counter() - t0) * 1e3 / max(run.frames, 1)
        clip = run.clip("puppet")
        write_bvh(path, clip)
    except Exception as exc:  # noqa: BLE001 - the demo goes on; the reason is said in one line
        out(f"puppet: not driven from the phone ({type(exc).__name__}: {exc})")
        return
    ground = np.hypot(np.diff(clip.root_pos[:, 0]), np.diff(clip.root_pos[:, 2])) * clip.fps
    held = "held throughout: the simulated phone sends no touch" if track.held_throughout else "grabbed by touch"
    out(f"puppet: the phone's attitude ({held}) drove {run.frames} frames at 60 Hz ({ms:.2f} ms each): the character "
        f"covered {ground.sum() / clip.fps:.1f} m at up to {np.percentile(ground, 95):.1f} m/s; states "
        + " -> ".join(run.states_visited()) + f"; BVH {path}")


def cmd_doctor(args: argparse.Namespace) -> int:
    from devices.doctor import RULES_NAME, diagnose, udev_rules

    if args.udev:
        out(udev_rules().rstrip())
        out(f"# save as /etc/udev/rules.d/{RULES_NAME}, then: sudo udevadm control --reload-rules &&"
            " sudo udevadm trigger, and replug the device")
        return 0
    rep = diagnose()
    if args.json:
        out(json.dumps(rep.as_dict(), indent=2))
        return 0 if rep.ok else 1
    if rep.usb:
        out(f"USB: {len(rep.usb)} device(s); known to perfcap: "
            + (", ".join(f"{u['known_as']} [{u['vid_pid']}]" for u in rep.usb if u["known_as"]) or "none"))
    for f in rep.findings:
        mark = "ok  " if f.ok else "FAIL"
        out(f"{mark} {f.what} at {f.where}" + (f" -> {f.kind}@{f.url}" if f.ok and f.kind and f.url else ""))
        if not f.ok:
            out(f"     problem: {f.problem}")
            for line in f.fix.splitlines():
                out(f"     {line}")
    for n in rep.notes:
        out(f"note: {n}")
    return 0 if rep.ok else 1


def cmd_devices(args: argparse.Namespace) -> int:
    from devices import device_class, known_kinds, known_schemes
    from devices.options import describe
    from devices.transports import transport_class
    from devices.transports.hid import list_hid_devices
    from devices.transports.serialport import list_serial_ports

    ports = list_serial_ports()
    try:
        hids = list_hid_devices()
        hid_error = ""
    except CaptureError as exc:
        hids, hid_error = [], str(exc)
    if args.json:
        doc = {
            "serial_ports": [p.as_dict() for p in ports],
            "hid_devices": [h.as_dict() for h in hids],
            "kinds": {k: {"description": device_class(k).description,
                          "options": {n: {"default": o.default, "help": o.help, "form": o.form()}
                                      for n, o in device_class(k).options.items()}} for k in known_kinds()},
            "transports": {sch: {"usage": transport_class(sch).usage,
                                 "options": {n: {"default": o.default, "help": o.help, "form": o.form()}
                                             for n, o in transport_class(sch).options.items()}}
                           for sch in known_schemes()},
        }
        out(json.dumps(doc, indent=2))
        return 0
    out("serial ports:")
    if not ports:
        out("  none found (a USB adapter plugged in shows up here; try perfcap sim serial for a simulated one)")
    for p in ports:
        what = p.adapter.chip if p.adapter else (p.description if p.description not in ("", "n/a") else
                                                 "built-in or unidentified UART")
        kinds = f"; likely {', '.join(p.adapter.kinds)}" if p.adapter and p.adapter.kinds else ""
        out(f"  {p.device}  [{p.vid_pid or 'no USB id'}] {what}{kinds}")
        out(f"      open as KIND@{p.url}")
        if p.latency_timer_ms and p.latency_timer_ms > 2:
            out(f"      note: FTDI latency timer is {p.latency_timer_ms} ms (readings arrive in bursts);"
                " low_latency=true (the default) asks for 1 ms")
        if p.adapter and p.adapter.note:
            out(f"      note: {p.adapter.note}")
    out("HID devices:")
    if hid_error:
        out(f"  cannot list them: {hid_error}")
    elif not hids:
        out("  none found (controllers, mice and tablets show up here; perfcap doctor explains one that does not;"
            " simhid://dualsense is a simulated one)")
    for h in hids:
        known = h.as_dict()["known_as"] or f"usage {h.usage_page:#06x}:{h.usage:#06x}"
        kind = f"; kind {h.likely_kind}" if h.likely_kind else ""
        out(f"  {h.vid_pid} {h.product or 'unnamed'} ({h.manufacturer or 'unknown maker'}) over {h.bus}: {known}{kind}")
        out(f"      open as {h.likely_kind or 'KIND'}@{h.url}" + ("" if h.serial_number else f"  or hid://path={h.path}"))
    out("device kinds (KIND@ in a device string):")
    for k in known_kinds():
        c = device_class(k)
        out(f"  {k}: {c.description}")
        if c.options:
            out(describe(c.options))
    out("transports (SCHEME://):")
    for sch in known_schemes():
        t = transport_class(sch)
        out(f"  {t.usage}")
        if t.options:
            out(describe(t.options))
    return 0


def _collect_imu(spec: Any, seconds: float, s: Any, what: str) -> tuple[Any, dict[str, Any]]:
    """Read one device for ``seconds``: (the device, arrays t_s, acc m/s^2, gyro rad/s, mag and mag_t
    or None)."""
    import numpy as np

    from capture.bus import Overflow, Subscriber
    from capture.orientation import check_imu_stream
    from capture.app.orchestrator import Capture
    from capture.sample import Sample, SampleBatch

    cap = Capture([spec], reconnect=s.reconnect_policy())
    dev = cap.devices[0]
    imus = [x for x in dev.streams if x.kind == "imu"]
    if not imus:
        cap.stop()
        raise ConfigError(f"device {dev.name} ({dev.kind}) has no IMU stream (accelerometer and gyro) to calibrate")
    try:
        ch = check_imu_stream(imus[0])
    except ConfigError:
        cap.stop()
        raise
    mag_name = next((x.name for x in dev.streams if x.kind == "mag"), None)
    got: dict[str, list[Any]] = {imus[0].name: [], mag_name or "": []}

    class Keep(Subscriber):
        accepts = frozenset({Sample, SampleBatch})

        def on_item(self, item: Any) -> None:
            if item.stream in got:
                if type(item) is Sample:
                    got[item.stream].append((np.array([item.t_bus_ns]), np.array([item.values], float)))
                else:
                    got[item.stream].append((item.t_bus_ns, item.values))

    cap.subscribe(Keep(), Overflow.NEVER_DROP, "calibrate")
    print(f"perfcap calibrate: {what}; reading {dev.name} for {seconds:g} s ...", file=sys.stderr, flush=True)
    rep = cap.run(seconds, stop=_stop_on_signals())
    if rep.devices[dev.name]["state"] == "failed":
        raise ConfigError(f"device {dev.name} failed while calibrating (see the messages above)")
    rows = got[imus[0].name]
    if not rows:
        raise ConfigError(f"no readings from {dev.name} in {seconds:g} s: is it streaming?")
    t = np.concatenate([r[0] for r in rows]) / 1e9
    v = np.concatenate([r[1] for r in rows])
    data = {"t": t, "acc": v[:, list(ch.acc_idx)] * ch.acc_scale, "gyro": v[:, list(ch.gyro_idx)] * ch.gyro_scale,
            "mag": None, "mag_t": None}
    mrows = got.get(mag_name or "", [])
    if mag_name and mrows:
        data["mag"] = np.concatenate([r[1] for r in mrows])[:, :3]
        data["mag_t"] = np.concatenate([r[0] for r in mrows]) / 1e9
    return dev, data


def _yaw_reset(cal: Any, spec: Any, seconds: float, s: Any) -> Any:
    """The calibration with a yaw offset that makes the heading held during the still period zero.

    Heading is only reproducible from one session to the next against magnetic north, so this
    needs a magnetometer (the calibration's hard/soft-iron fit is applied first)."""

    from capture.calibration import still_bias
    from capture.orientation import DEFAULT_FILTER, OrientationFilter

    dev, d = _collect_imu(spec, seconds, s, "yaw reset: point the body the way that should be heading zero and"
                          " keep still")
    if d["mag"] is None:
        raise ConfigError(f"device {dev.name} has no magnetometer stream: without one a heading does not carry"
                          " over between sessions, so there is nothing to reset against")
    still_bias(d["gyro"], d["acc"], d["t"], source=dev.name)  # checks it was held still
    acc, gyro, _ = cal.apply(d["acc"], d["gyro"])
    f = OrientationFilter(DEFAULT_FILTER)
    f.add_mag(d["mag_t"], cal.apply_mag(d["mag"]))
    r = f.update_many(d["t"], gyro, acc)
    return cal.with_yaw_reset(r.q[-1])


def cmd_calibrate(args: argparse.Namespace) -> int:
    import numpy as np

    from capture.calibration import (
        ImuCalibration,
        fit_accelerometer,
        fit_magnetometer,
        mounting_from_gravity,
        still_bias,
        still_poses,
    )
    from capture.calibration_store import CalibrationStore
    from devices import open_device, parse_device_spec

    s = _settings(args)
    store = CalibrationStore(s.calibration.dir or None)
    if args.list:
        entries = store.entries()
        if args.json:
            out(json.dumps([{"file": str(p), "document": d, "error": e} for p, d, e in entries], default=str))
            return 0
        out(f"calibrations in {store.dir}:" + ("" if entries else " none"))
        for p, d, e in entries:
            out(f"  {p.name}: " + (f"DAMAGED: {e}" if e else f"{d['identity']['kind']} {d['identity']['name']}"
                                   f" ({d.get('note') or 'no note'})"))
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
    steps = [x for x in ("gyro", "accel", "mag", "mounting", "yaw") if getattr(args, x)]
    if not steps:
        raise ConfigError("say what to calibrate: --gyro (hold still), --accel (still poses), --mag (rotate in all"
                          " directions), --mounting (reference pose), --yaw (face heading zero); or --show,"
                          " --clear, --list")
    _check_duration(args.seconds)
    report: dict[str, Any] = {}
    cal = current
    if args.gyro:
        dev, d = _collect_imu(spec, args.seconds, s, "gyro bias: keep the sensor still")
        sb = still_bias(d["gyro"], d["acc"], d["t"], source=dev.name)
        cal = cal.with_gyro_bias(sb.bias)
        report["gyro_bias_dps"] = np.degrees(sb.bias).round(4).tolist()
        report["gyro_bias_stderr_dps"] = np.degrees(sb.stderr).round(5).tolist()
        out(f"gyro bias {np.degrees(sb.bias).round(4).tolist()} deg/s (+- {np.degrees(sb.stderr).max():.4f}) from"
            f" {sb.n} still samples over {sb.duration_s:.1f} s")
    if args.accel:
        dev, d = _collect_imu(spec, args.seconds, s, f"accelerometer: rest the sensor in {args.poses} different"
                              " orientations (faces up and down), a few seconds each, turning between them")
        poses = still_poses(d["t"], d["acc"], d["gyro"])
        fit = fit_accelerometer(poses, source=dev.name)
        from dataclasses import replace
        cal = replace(cal, acc_offset=tuple(fit.offset), acc_matrix=tuple(map(tuple, fit.matrix)))
        report["accel"] = {"poses": fit.poses, "distinct": fit.distinct, "model": fit.model,
                           "residual_rms": fit.residual_rms, "raw_rms": fit.raw_rms}
        out(f"accelerometer ({fit.model}, {fit.distinct} orientations): |g| error rms {fit.raw_rms:.4f} ->"
            f" {fit.residual_rms:.4f} m/s^2")
    if args.mag:
        dev, d = _collect_imu(spec, args.seconds, s, "magnetometer: turn the sensor slowly through every direction")
        if d["mag"] is None:
            raise ConfigError(f"device {dev.name} has no magnetometer stream")
        mf = fit_magnetometer(d["mag"], source=dev.name)
        from dataclasses import replace
        cal = replace(cal, mag_hard_iron=tuple(mf.hard_iron), mag_soft_iron=tuple(map(tuple, mf.soft_iron)))
        report["mag"] = {"model": mf.model, "coverage": mf.coverage, "spread_before": mf.spread_before,
                         "spread_after": mf.spread_after}
        out(f"magnetometer ({mf.model}, coverage {mf.coverage:.0%}): field magnitude spread {mf.spread_before:.1%}"
            f" -> {mf.spread_after:.1%}")
    if args.mounting:
        dev, d = _collect_imu(spec, args.seconds, s, "mounting: stand in the reference pose and keep still")
        sb = still_bias(d["gyro"], d["acc"], d["t"], source=dev.name)  # also checks it was still
        del sb
        from dataclasses import replace
        cal = replace(cal, mounting=mounting_from_gravity(d["acc"].mean(axis=0)))
        report["mounting"] = list(cal.mounting)
        out(f"mounting (sensor -> segment) {np.round(cal.mounting, 4).tolist()}")
    if args.yaw:
        cal = _yaw_reset(cal, spec, args.seconds, s)
        report["yaw_offset_deg"] = round(float(np.degrees(cal.yaw_offset_rad)), 3)
        out(f"yaw reset: headings are now measured from this direction (offset {report['yaw_offset_deg']} deg"
            " from magnetic north)")
    from dataclasses import replace
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


def cmd_sim(args: argparse.Namespace) -> int:
    from importlib.metadata import entry_points

    sims = {ep.name: ep for ep in entry_points(group="perfcap.sims")}
    if args.what not in sims:
        raise ConfigError(f"no simulator {args.what!r}; known: {', '.join(sorted(sims)) or 'none'}"
                          " (is perfcap installed with pip install -e .?)")
    return int(sims[args.what].load()(args.args))


# ------------------------------------------------------------------------------------------------
class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> Any:  # one line plus the usage, exit 2
        self.print_usage(sys.stderr)
        print(f"perfcap: error: {message}", file=sys.stderr)
        raise SystemExit(EXIT_BAD_INPUT)


def _orientation_args(p: argparse.ArgumentParser, help_on: str) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--orientation", action="store_true", default=None, help=help_on)
    g.add_argument("--no-orientation", dest="orientation", action="store_false", help="no orientation fusion")
    p.add_argument("--filter", choices=["fusion", "madgwick", "mahony", "ekf"],
                   help="orientation filter (default fusion: x-io's Fusion, chosen by measurement)")


def build_parser() -> argparse.ArgumentParser:
    from devices import SPEC_EXAMPLE, SPEC_FORM

    p = _Parser(prog="perfcap", description="Hardware-in-the-loop performance capture.")
    p.add_argument("--version", action="version", version=f"perfcap {__version__}")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    p.add_argument("--debug", action="store_true", help="show tracebacks of internal errors")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)

    r = sub.add_parser("record", help="record devices to a session file")
    r.add_argument("-d", "--device", action="append", metavar="DEVICE",
                   help=f"a device: {SPEC_FORM}, e.g. {SPEC_EXAMPLE} (repeatable)")
    r.add_argument("--config", metavar="FILE", help="TOML settings (and [[devices]])")
    r.add_argument("--profile", metavar="NAME", help="a profile from config/ (default, lab, ci)")
    r.add_argument("--duration", type=float, metavar="SECONDS", help="stop after this long (default: Ctrl-C)")
    r.add_argument("-o", "--output", required=True, metavar="SESSION.mcap")
    r.add_argument("--overwrite", action="store_true", help="replace an existing session file")
    r.add_argument("--max-loss", type=float, metavar="SECONDS", help="most data a crash may lose (default 1 s)")
    r.add_argument("--json", action="store_true", help="print the report as JSON")
    r.add_argument("-q", "--quiet", action="store_true", help="no live status lines")
    _orientation_args(r, "record orientation, gravity and linear acceleration of every IMU (with its stored"
                         " calibration)")
    r.add_argument("--calibration-dir", metavar="DIR", help="where calibrations are stored (perfcap calibrate)")
    r.set_defaults(func=cmd_record)

    rp = sub.add_parser("replay", help="replay a session through the same codecs and check it")
    rp.add_argument("session", metavar="SESSION")
    g = rp.add_mutually_exclusive_group()
    g.add_argument("--speed", type=float, metavar="X", help="speed factor (default 1 = recorded pace)")
    g.add_argument("--fast", action="store_true", help="as fast as possible (deterministic)")
    rp.add_argument("--loop", action="store_true", help="start over at the end")
    rp.add_argument("--duration", type=float, metavar="SECONDS", help="stop after this long")
    rp.add_argument("-o", "--output", metavar="SESSION.mcap", help="record the replay to a new session")
    rp.add_argument("--overwrite", action="store_true")
    rp.add_argument("--no-verify", action="store_true", help="skip comparing with the recorded samples")
    rp.add_argument("--json", action="store_true")
    rp.add_argument("-q", "--quiet", action="store_true")
    _orientation_args(rp, "compute orientation even if the session has none (default: rebuild and verify the"
                          " recorded orientation streams with the recorded filter and calibration)")
    rp.set_defaults(func=cmd_replay)

    i = sub.add_parser("info", help="summarise a session")
    i.add_argument("session", metavar="SESSION")
    i.add_argument("--json", action="store_true", help="one JSON object")
    i.set_defaults(func=cmd_info)

    e = sub.add_parser("export", help="export samples and events as CSV or JSON lines")
    e.add_argument("session", metavar="SESSION")
    e.add_argument("--format", required=True, choices=["csv", "jsonl"])
    e.add_argument("-o", "--output", required=True, metavar="DIR")
    e.add_argument("--overwrite", action="store_true")
    e.add_argument("-q", "--quiet", action="store_true")
    e.set_defaults(func=cmd_export)

    sv = sub.add_parser("serve", help="the capture service: phones (built-in page, Sensor Logger, OSC, HyperIMU, "
                        "SensorServer), control API, mDNS")
    sv.add_argument("-d", "--device", action="append", metavar="DEVICE", help="also capture this device")
    sv.add_argument("--record", metavar="SESSION.mcap", help="record from the start (else POST /api/record/start)")
    sv.add_argument("--overwrite", action="store_true", help="replace an existing --record file")
    sv.add_argument("--sessions-dir", help="where POST /api/record/start puts sessions without a path")
    sv.add_argument("--host", help="address the phone endpoints listen on (default all)")
    sv.add_argument("--port", type=int, help="phone page / WebSocket / Sensor Logger port (HTTPS)")
    sv.add_argument("--public-host", help="address phones use to reach this machine (default: detected LAN address)")
    sv.add_argument("--no-tls", action="store_true", help="plain HTTP (browsers then refuse motion sensors)")
    sv.add_argument("--control-host", help="control API address (default loopback only)")
    sv.add_argument("--control-port", type=int, help="control API port (-1: none)")
    sv.add_argument("--state-dir", help="where the token and certificate are kept")
    sv.add_argument("--rotate-token", action="store_true", help="make a new pairing token before starting")
    sv.add_argument("--no-mdns", action="store_true", help="do not advertise or browse with mDNS")
    sv.add_argument("--connect-sensorserver", action="store_true",
                    help="connect to SensorServer phones found by mDNS without asking")
    sv.add_argument("--osc-port", type=int, help="OSC UDP port (ZIG SIM, GyrOSC); off by default")
    sv.add_argument("--osc-allow", help="addresses allowed to send OSC (needed with --osc-port)")
    sv.add_argument("--osc-map", help="OSC address map: zigsim, gyrosc or a custom map")
    sv.add_argument("--hyperimu-port", type=int, help="HyperIMU UDP port; off by default")
    sv.add_argument("--hyperimu-tcp-port", type=int, help="HyperIMU TCP port; off by default")
    sv.add_argument("--hyperimu-allow", help="addresses allowed to send HyperIMU CSV")
    sv.add_argument("--hyperimu-sensors",
                    help="HyperIMU's enabled sensors, in the app's order")
    sv.add_argument("--phone-name", action="append", metavar="PROTOCOL/ID=NAME",
                    help="a fixed device name for a phone (e.g. page/5f2c0a...=pocket)")
    sv.add_argument("--max-phones", type=int, help="phone devices the service may create (default 32)")
    sv.add_argument("--max-message-kb", type=int, help="largest message accepted (KiB)")
    sv.add_argument("--max-rate", type=float, help="messages per second per client")
    sv.add_argument("--max-connections-per-host", type=int)
    sv.add_argument("--duration", type=float, metavar="SECONDS", help="stop after this long")
    sv.add_argument("--status-every", type=float, default=5.0, help="seconds between status lines (0: none)")
    sv.add_argument("--config", metavar="FILE")
    sv.add_argument("--profile", metavar="NAME")
    sv.add_argument("-q", "--quiet", action="store_true")
    sv.add_argument("--json", action="store_true", help="final report as JSON")
    sv.set_defaults(func=cmd_serve)

    d = sub.add_parser("demo", help="hardware-free demo: simulated devices -> bus -> session -> replay")
    d.add_argument("--duration", type=float, default=5.0, metavar="SECONDS")
    d.add_argument("-o", "--output", metavar="SESSION.mcap", help="where to keep the demo session")
    d.add_argument("--overwrite", action="store_true")
    d.add_argument("-q", "--quiet", action="store_true")
    d.set_defaults(func=cmd_demo)

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
    pp.add_argument("--vmc", metavar="HOST:PORT", help="send one VMC (OSC) bundle per frame over UDP")
    pp.add_argument("--timeline", metavar="TIMELINE.json", help='write the state changes as [{"t": s, "state":'
                    ' name}, ...]')
    pp.add_argument("--rate", type=float, default=60.0, metavar="HZ", help="frame rate (default 60)")
    pp.add_argument("--duration", type=float, metavar="SECONDS", help="with --phone: stop after this long"
                    " (default: Ctrl-C)")
    pp.add_argument("--hold", action="store_true", help="the phone counts as held throughout (touches ignored)")
    pp.add_argument("-q", "--quiet", action="store_true", help="no live status lines")
    pp.set_defaults(func=cmd_puppet)

    cy = sub.add_parser("cycle", help="one clean closed loop from a take of several performed loops",
                        description="Extract one clean closed loop from a take in which a motion was performed"
                        " several times. Exit 0 with the cycle, 1 when the input holds no cycle (no motion, or"
                        " it does not repeat), 2 for bad input.")
    cy.add_argument("input", metavar="INPUT", help="a perfcap session (.mcap) or a CSV: a time column in seconds"
                    " (t, time or time_s, else the first column) and channel columns")
    cy.add_argument("--stream", metavar="NAME", help="the session stream (default: its only one, or its only IMU"
                    " stream)")
    cy.add_argument("--columns", metavar="A,B,...", help="only these channels (CSV columns or stream channels)")
    cy.add_argument("-o", "--output", metavar="LOOP.csv", help="write the loop as CSV (t, then the channels)")
    cy.add_argument("--report", metavar="REPORT.png", help="draw the aligned input loops and the cycle per channel")
    cy.add_argument("--json", action="store_true", help="one JSON object")
    cy.add_argument("--seed", type=int, default=0, help="seed of the extraction's random choices (default 0)")
    cy.set_defaults(func=cmd_cycle)

    dv = sub.add_parser("devices", help="list serial ports and HID devices present, device kinds and transports")
    dv.add_argument("--json", action="store_true", help="one JSON object")
    dv.set_defaults(func=cmd_devices)

    dr = sub.add_parser("doctor", help="which capture devices are present, which cannot be opened and why")
    dr.add_argument("--udev", action="store_true", help="print perfcap's udev rules file and where it goes")
    dr.add_argument("--json", action="store_true", help="one JSON object")
    dr.set_defaults(func=cmd_doctor)

    c = sub.add_parser("calibrate", help="calibrate an IMU (gyro bias, accelerometer, magnetometer, mounting)")
    c.add_argument("-d", "--device", metavar="DEVICE", help=f"the device, as for record ({SPEC_FORM})")
    c.add_argument("--gyro", action="store_true", help="gyro bias from an explicit still period")
    c.add_argument("--accel", action="store_true", help="accelerometer offset and scale from still poses")
    c.add_argument("--poses", type=int, default=6, help="orientations asked for by --accel (default 6)")
    c.add_argument("--mag", action="store_true", help="magnetometer hard and soft iron from a rotation dance")
    c.add_argument("--mounting", action="store_true", help="mounting rotation from a still reference pose")
    c.add_argument("--yaw", action="store_true",
                   help="yaw reset: the heading held still now becomes zero (needs a magnetometer)")
    c.add_argument("--seconds", type=float, default=5.0, help="how long to read for each step (default 5)")
    c.add_argument("--show", action="store_true", help="print the stored calibration")
    c.add_argument("--clear", action="store_true", help="remove the stored calibration")
    c.add_argument("--list", action="store_true", help="list stored calibrations")
    c.add_argument("--dry-run", action="store_true", help="measure and print, do not store")
    c.add_argument("--calibration-dir", metavar="DIR", help="where calibrations are stored")
    c.add_argument("--config", metavar="FILE")
    c.add_argument("--profile", metavar="NAME")
    c.add_argument("--json", action="store_true")
    c.set_defaults(func=cmd_calibrate)

    sm = sub.add_parser("sim", help="serve a simulated device (perfcap sim serial --help)", add_help=False)
    sm.add_argument("what", metavar="DEVICE", help="serial")
    sm.add_argument("args", nargs=argparse.REMAINDER)
    sm.set_defaults(func=cmd_sim)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING if args.verbose == 0 else logging.INFO if args.verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="perfcap: %(levelname)s: %(message)s", stream=sys.stderr)
    if args.command in ("record", "demo", "serve") or args.command == "puppet" and args.phone or args.command == "replay" and not args.fast:
        # Live work: a shorter interpreter switch interval lets reader and delivery threads wake
        # within ~0.5 ms while another thread is busy encoding (the default 5 ms would dominate the
        # latency tail). Offline work keeps the default, which is faster for it.
        sys.setswitchinterval(0.0005)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_BAD_INPUT
    try:
        return int(args.func(args))
    except CaptureError as exc:
        print(f"perfcap: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("perfcap: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0
    except Exception as exc:
        if args.debug:
            raise
        print(f"perfcap: internal error: {type(exc).__name__}: {exc} (rerun with --debug for details; "
              "please report it)", file=sys.stderr)
        return EXIT_INTERNAL

