"""``perfcap serve``: the capture service (phones over the built-in page, Sensor Logger, OSC, HyperIMU
and SensorServer; the control API; mDNS), its endpoints and pairing link printed, recording on demand."""

from __future__ import annotations

import logging
import os
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from capture import __version__
from capture.app.cli.common import (
    EXIT_BAD_INPUT,
    NO_VIEWS_HELP,
    SECONDS,
    SECONDS_OR_ZERO,
    check_duration,
    live_line,
    out,
    print_capture,
    seconds_since,
    settings,
)
from capture.app.schema import add_flags, flag_values
from capture.app.serve.config import FOXGLOVE_PORT, ServeConfig
from capture.clock import MONOTONIC
from capture.errors import ConfigError
from devices.options import shown

if TYPE_CHECKING:
    import argparse

    from capture.app.cli.common import Subcommands
    from capture.app.serve.service import Service

log = logging.getLogger(__name__)


def add_parser(sub: Subcommands) -> None:
    sv = sub.add_parser("serve", help="the capture service: phones (built-in page, Sensor Logger, OSC, HyperIMU, "
                        "SensorServer), control API, mDNS")
    sv.add_argument("-d", "--device", action="append", metavar="DEVICE", help="also capture this device")
    sv.add_argument("--record", metavar="SESSION.mcap", help="record from the start (else POST /api/record/start)")
    sv.add_argument("--overwrite", action="store_true", help="replace an existing --record file")
    sv.add_argument("--no-views", action="store_true", help=NO_VIEWS_HELP)
    sv.add_argument("--rotate-token", action="store_true", help="make a new pairing token before starting")
    add_flags(sv, ServeConfig)  # one flag per [serve] setting (capture.app.serve.config)
    _bare_flag(sv, "--foxglove", str(FOXGLOVE_PORT))  # --foxglove alone: the Foxglove app's default port
    sv.add_argument("--duration", type=SECONDS, metavar="SECONDS", help="stop after this long")
    sv.add_argument("--status-every", type=SECONDS_OR_ZERO, default=5.0, help="seconds between status lines (0: none)")
    sv.add_argument("--config", metavar="FILE")
    sv.add_argument("--profile", metavar="NAME")
    sv.add_argument("-q", "--quiet", action="store_true")
    sv.add_argument("--json", action="store_true", help="final report as JSON")
    sv.set_defaults(func=run)


def _bare_flag(parser: argparse.ArgumentParser, flag: str, const: str) -> None:
    """Let a setting's flag also be given without a value (``--foxglove`` means ``--foxglove=8765``)."""
    for action in parser._actions:
        if flag in action.option_strings:
            action.nargs, action.const = "?", const
            return
    raise ValueError(f"no flag {flag}")


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
    except Exception as exc:
        log.info("no QR code: %s", exc)


def _check_host(flag: str, host: str) -> None:
    """A listening or advertised host is an address or a host name (labels of at most 63 characters).

    Raises:
        ConfigError: naming the flag.
    """
    if not host:
        return
    try:
        host.encode("idna")
    except UnicodeError:
        raise ConfigError(f"{flag} {shown(host)} is not a host name or an address") from None


def run(args: argparse.Namespace) -> int:
    import asyncio

    from capture.app.serve.service import Service
    from devices import parse_device_spec

    check_duration(args.duration)
    s = settings(args, serve=flag_values(args, ServeConfig))
    cfg = s.serve
    for flag, host in (("--host", cfg.host), ("--control-host", cfg.control_host), ("--public-host", cfg.public_host),
                       ("--foxglove-host", cfg.foxglove_host)):
        _check_host(flag, host)
    if cfg.sessions_dir and not os.path.isdir(cfg.sessions_dir):  # "": the default, made on first use
        raise ConfigError(f"sessions_dir {cfg.sessions_dir} (--sessions-dir, [serve] sessions_dir or"
                          " PERFCAP_SERVE_SESSIONS_DIR) is not a folder")
    if cfg.state_dir and os.path.lexists(cfg.state_dir) and not os.path.isdir(cfg.state_dir):
        raise ConfigError(f"state_dir {cfg.state_dir} (--state-dir, [serve] state_dir or PERFCAP_SERVE_STATE_DIR)"
                          " is not a folder")
    specs = [parse_device_spec(d) for d in args.device] if args.device else list(s.devices)
    if args.rotate_token:
        from capture.app.serve.security import TokenStore
        from capture.app.serve.service import default_state_dir

        TokenStore(Path(cfg.state_dir) if cfg.state_dir else default_state_dir()).rotate()
    if cfg.lsl:
        from capture.app.lsl_out import load_pylsl

        load_pylsl()  # a machine without liblsl is told so before anything starts
    service = Service(cfg, specs, reconnect=s.reconnect_policy(),
                      capture_options={"max_loss_s": s.recorder.max_loss_s, "fsync": s.recorder.fsync,
                                       "views": s.recorder.views,
                                       "recorder_max_bytes": s.bus.recorder_max_mb << 20,
                                       "live_queue": s.bus.live_queue})

    if cfg.lsl:  # before the capture starts: the outlets of the devices given exist before data flows
        from capture.app.lsl_out import publish_capture

        try:
            publish_capture(service.capture)
        except BaseException:
            service.capture.stop()
            raise

    fox = None
    if cfg.foxglove >= 0:  # before any file is made: a port in use leaves nothing behind
        from capture.app import foxglove_live

        try:
            fox = foxglove_live.FoxgloveServer(cfg.foxglove_host, cfg.foxglove)
            foxglove_live.publish_capture(service.capture, fox)  # it stops with the capture
        except BaseException:
            service.capture.stop()
            raise

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
        out(f"  pairing token   {svc.tokens.token}   (shown once; rotate with --rotate-token or"
            " POST /api/token/rotate)")
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
        if fox is not None:
            out(f"  Foxglove        open {fox.url} {foxglove_live.HOW_TO_OPEN}")
        _print_qr(ep.pair_url)
        if svc.capture.output:
            out(f"  recording to    {svc.capture.output}")
        out("Ctrl-C stops and flushes the recording.")
        sys.stdout.flush()

    async def main_async() -> Any:
        loop = asyncio.get_running_loop()
        def on_signal(sig: signal.Signals) -> None:
            print(f"\nperfcap: {sig.name} received, stopping and flushing", file=sys.stderr)
            service.request_stop()

        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, on_signal, sig)
        if args.duration:
            loop.call_later(args.duration, service.request_stop)

        async def ticker() -> None:
            t0 = MONOTONIC.now_ns()
            while True:
                await asyncio.sleep(args.status_every)
                live_line(service.capture, seconds_since(t0))

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
    code = print_capture(report, args.json)
    return 0 if code == 1 and not service.capture.devices else code
