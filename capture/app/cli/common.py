"""What every ``perfcap`` command shares: exit codes, output, progress and live status lines, stopping
on signals, settings from config and flags, argument checks and the capture report.

Errors are one line on stderr and a non-zero exit (2 for bad input, 1 for a failed check or no cycle,
70 for an internal error, with ``--debug`` showing the traceback).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import stat
import sys
import threading
from typing import TYPE_CHECKING, Any, NoReturn

from capture.clock import MONOTONIC
from capture.errors import ConfigError
from devices.options import Option, arg_type, shown

if TYPE_CHECKING:
    from collections.abc import Callable
    from types import FrameType

    from capture.app.config import Settings
    from capture.app.foxglove_live import FoxgloveServer
    from capture.app.orchestrator import Capture, CaptureReport

EXIT_BAD_INPUT = 2
EXIT_CHECK_FAILED = 1
EXIT_INTERNAL = 70
EXIT_NO_CYCLE = 1  # the input was read but holds no cycle (as grep's 1 for "no match")


def out(text: str = "") -> None:
    print(text, flush=True)


def err(text: str) -> None:
    """One line on stderr."""
    print(text, file=sys.stderr, flush=True)


def seconds_since(t0_ns: int) -> float:
    return (MONOTONIC.now_ns() - t0_ns) / 1e9


class Progress:
    """Progress on stderr for offline work that takes more than a second."""

    def __init__(self, label: str, quiet: bool = False) -> None:
        self.label = label
        self.quiet = quiet
        self.t0 = MONOTONIC.now_ns()
        self.last = 0.0
        self.shown = False

    def __call__(self, done: int, total: int) -> None:
        now = seconds_since(self.t0)
        if self.quiet or now < 1.0 or now - self.last < 0.5:
            return
        self.last = now
        self.shown = True
        pct = 100.0 * done / total if total else 0.0
        print(f"\r{self.label}: {pct:5.1f}%", end="", file=sys.stderr, flush=True)

    def done(self) -> None:
        if self.shown:
            print(f"\r{self.label}: 100.0%", file=sys.stderr, flush=True)


def stop_on_signals() -> threading.Event:
    """An event set by the first SIGINT or SIGTERM (which is said on stderr)."""
    ev = threading.Event()

    def handler(signum: int, frame: FrameType | None) -> None:
        if ev.is_set():
            return
        ev.set()
        print(f"\nperfcap: {signal.Signals(signum).name} received, stopping and flushing", file=sys.stderr)

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return ev


def live_line(cap: Capture, elapsed: float) -> None:
    """One status line on stderr: every stream's count, rate and losses, and devices still waiting."""
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


def foxglove_args(p: argparse.ArgumentParser) -> None:
    """``--foxglove[=PORT]`` and ``--foxglove-host`` (``record``, ``puppet --phone``; serve's come from its
    settings)."""
    from capture.app.serve.config import FOXGLOVE_PORT

    p.add_argument("--foxglove", nargs="?", const=str(FOXGLOVE_PORT), metavar="PORT",
                   help="also serve the live data to the Foxglove app (its WebSocket connection) on this port"
                        f" (bare: {FOXGLOVE_PORT}; 0: any free port)")
    p.add_argument("--foxglove-host", metavar="HOST", help="address the --foxglove server listens on (default"
                   " 127.0.0.1, this machine only; it has no authentication)")


def foxglove_server(args: argparse.Namespace) -> FoxgloveServer | None:
    """The ``--foxglove`` server, listening (None without the flag).

    Raises:
        ConfigError: a bad port, ``--foxglove-host`` without ``--foxglove``, or the port cannot be bound.
    """
    if args.foxglove is None:
        if args.foxglove_host:
            raise ConfigError("--foxglove-host needs --foxglove[=PORT]")
        return None
    from capture.app.foxglove_live import LOOPBACK, FoxgloveServer, parse_port

    return FoxgloveServer(args.foxglove_host or LOOPBACK, parse_port(args.foxglove))


#: ``--no-views`` of the commands that record (``[recorder] views = false``)
NO_VIEWS_HELP = ("record the lossless channels only, not the viewable ones Foxglove shows (/view, /tf, /log):"
                 " about a third of the disk ([recorder] views)")


def settings(args: argparse.Namespace, serve: dict[str, Any] | None = None) -> Settings:
    """The settings of a command: its flags over ``PERFCAP_*`` over ``--config``/``--profile`` over the
    defaults (``serve``: the ``[serve]`` values its flags give)."""
    from capture.app.config import load_config

    overrides: dict[str, dict[str, Any]] = {"recorder": {}}
    given = vars(args)
    if given.get("max_loss") is not None:
        overrides["recorder"]["max_loss_s"] = given["max_loss"]
    if given.get("overwrite"):
        overrides["recorder"]["overwrite"] = True
    if given.get("no_views"):
        overrides["recorder"]["views"] = False
    if given.get("orientation") is not None or given.get("filter"):
        overrides["orientation"] = {"enabled": given.get("orientation"), "filter": given.get("filter")}
    if given.get("calibration_dir"):
        overrides["calibration"] = {"dir": given["calibration_dir"]}
    if serve is not None:
        overrides["serve"] = serve
    return load_config(given.get("config"), given.get("profile"), overrides)


def _stat(path: str | None, what: str) -> os.stat_result | None:
    """What ``path`` is, or None when it is not given or not there (left to its reader or maker)."""
    if not path:
        return None
    try:
        return os.stat(path)
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise ConfigError(f"{what} {shown(path)}: {exc.strerror or exc}") from None


def input_file(path: str | None, what: str) -> None:
    """Refuse, before anything opens it, an input that is there but is no regular file: a FIFO or a
    device would block the read or never end (``/dev/zero``). A missing file or a folder is left to the
    reader, which says so in its own words.

    Raises:
        ConfigError: ``path`` is a FIFO, a device or a socket, or cannot be looked at.
    """
    st = _stat(path, what)
    if st is None:
        return
    if not (stat.S_ISREG(st.st_mode) or stat.S_ISDIR(st.st_mode)):
        kind = ("a FIFO" if stat.S_ISFIFO(st.st_mode) else "a socket" if stat.S_ISSOCK(st.st_mode)
                else "a device")
        raise ConfigError(f"{what} {path} is {kind}, not a file")


def output_file(path: str | None, what: str) -> None:
    """Refuse an output that is there but is no regular file or folder (writing to a FIFO blocks until
    someone reads it; to a device, it is no file).

    Raises:
        ConfigError: as :func:`input_file`.
    """
    input_file(path, what)


def folder_arg(path: str | None, what: str) -> None:
    """Refuse a folder flag that names something else than a folder, or a name the system cannot take
    (too long, through a file). A folder not there yet is left to be made.

    Raises:
        ConfigError: saying why.
    """
    st = _stat(path, what)
    if st is None:
        return
    if not stat.S_ISDIR(st.st_mode):
        raise ConfigError(f"{what} {path} is not a folder")


def check_duration(d: float | None) -> None:
    if d is not None and (not math.isfinite(d) or d <= 0):
        raise ConfigError(f"--duration must be a positive number of seconds, not {d}")


def print_capture(report: CaptureReport, as_json: bool) -> int:
    """The capture report on stdout; the exit code it deserves (a failed recording or device: 1)."""
    if as_json:
        out(json.dumps({"duration_s": report.duration_s, "output": report.output, "streams": report.streams,
                        "devices": report.devices, "subscribers": report.subscribers,
                        "recorder_error": report.recorder_error, "events": report.events,
                        "saved": report.saved, "not_saved": report.not_saved, "saved_exact": report.saved_exact,
                        "silent": report.silent},
                       default=str))
    else:
        rec_failed = report.recorder_error is not None and report.saved is not None
        out(f"captured {report.duration_s:.2f} s" + (f" into {report.output}" if report.output else ""))
        for name, s in report.streams.items():
            line = f"  {name:24s} {s['samples']:8d} samples  {s['rate_hz']:8.2f} Hz  {s['drops']} lost"
            if rec_failed and report.saved is not None:
                kept = report.saved.get(name, 0)
                line += (f"; {'at least ' if not report.saved_exact else ''}{kept} in the file,"
                         f" {max(0, s['samples'] - kept)} not saved")
            out(line)
        for name, d in report.devices.items():
            extra = []
            if d["checksum_errors"] or d["framing_errors"]:
                extra.append(f"{d['checksum_errors'] + d['framing_errors']} bad frames, "
                             f"{d['skipped_bytes']} bytes skipped")
            if d["reconnects"]:
                extra.append(f"{d['reconnects']} reconnects")
            if d["clock_resets"]:
                extra.append(f"{d['clock_resets']} clock resets")
            if d.get("undecoded"):
                extra.append("not decoded: " + ", ".join(f"{k} ({n}x)" for k, n in sorted(d["undecoded"].items())))
            out(f"  device {name}: {d['state']}, {d['chunks']} chunks, {d['bytes']} bytes"
                + (f"; {'; '.join(extra)}" if extra else ""))
        for sub in report.subscribers:
            if sub["dropped"]:
                out(f"  subscriber {sub['name']} dropped {sub['dropped']} items")
    if report.recorder_error:
        err(f"perfcap: error: recording failed: {report.recorder_error}")
        if report.saved is not None:
            kept = sum(report.saved.values())
            captured = sum(s["samples"] for s in report.streams.values())
            err(f"perfcap: the take was stopped; {report.output} keeps {'at least ' if not report.saved_exact else ''}"
                f"{kept} of {captured} samples (those up to its last flush); {max(0, captured - kept)} are not saved")
        return EXIT_CHECK_FAILED
    failed = [n for n, d in report.devices.items() if d["state"] == "failed"]
    if failed:
        err(f"perfcap: error: device(s) failed: {', '.join(failed)} (see the messages above)")
        return EXIT_CHECK_FAILED
    never = [n for n, d in report.devices.items() if not d.get("opens", 1)]
    if never:
        for n in never:
            err(f"perfcap: error: device {n} was never opened during the take: {report.devices[n]['last_error']}")
        return EXIT_CHECK_FAILED
    if report.silent:
        for n, why in report.silent.items():
            err(f"perfcap: error: device {n} {why}")
        return EXIT_CHECK_FAILED
    return 0


class Parser(argparse.ArgumentParser):
    """A usage error is one line naming the command's ``--help``, exit 2."""

    def error(self, message: str) -> NoReturn:
        print(f"perfcap: error: {' '.join(message.split())} (see {self.prog} --help)", file=sys.stderr)
        raise SystemExit(EXIT_BAD_INPUT)


#: the longest time a flag takes (about 31 years): beyond it, timers and waits overflow
MAX_SECONDS = 1e9
#: ``type=`` of a flag in seconds above 0 (``--duration``), through the one value parser (``Option.parse``)
SECONDS = arg_type(Option(float, None, "seconds", min=0, max=MAX_SECONDS, min_exclusive=True))
#: ``type=`` of a flag in seconds, 0 included (``--status-every 0``: none)
SECONDS_OR_ZERO = arg_type(Option(float, None, "seconds", min=0, max=MAX_SECONDS))
#: ``type=`` of a seed (numpy takes non-negative seeds)
SEED = arg_type(Option(int, 0, "seed", min=0, max=2**128))


def count(lo: int, hi: int) -> Callable[[str], Any]:
    """``type=`` of a whole number flag within ``[lo, hi]``."""
    return arg_type(Option(int, None, "count", min=lo, max=hi))


def orientation_args(p: argparse.ArgumentParser, help_on: str) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--orientation", action="store_true", default=None, help=help_on)
    g.add_argument("--no-orientation", dest="orientation", action="store_false", help="no orientation fusion")
    p.add_argument("--filter", choices=["fusion", "madgwick", "mahony", "ekf"],
                   help="orientation filter (default fusion: x-io's Fusion, chosen by measurement)")


if TYPE_CHECKING:
    #: what ``build_parser`` hands each command module's ``add_parser``
    Subcommands = argparse._SubParsersAction[argparse.ArgumentParser]
