"""``perfcap``: the command line. ``main`` and the parser live here; each command is a module of this
package with an ``add_parser(sub)`` that declares its flags and a ``run(args)`` that puts library
objects together (record, replay, info, export, serve, demo, puppet, cycle, devices, doctor,
calibrate, sim); what they share is in ``common``.

Errors are one line on stderr and a non-zero exit (2 for bad input, 1 for a failed check or no cycle,
70 for an internal error, with ``--debug`` showing the traceback).
"""

from __future__ import annotations

import io
import logging
import os
import sys
from typing import TYPE_CHECKING

from capture import __version__
from capture.app.cli import (
    calibrate,
    cycle,
    demo,
    devices,
    doctor,
    export,
    info,
    puppet,
    record,
    replay,
    serve,
    sim,
)
from capture.app.cli.common import EXIT_BAD_INPUT, EXIT_INTERNAL, Parser
from capture.errors import CaptureError

if TYPE_CHECKING:
    import argparse
    from collections.abc import Sequence

#: the commands, in the order ``perfcap --help`` lists them
COMMANDS = (record, replay, info, export, serve, demo, puppet, cycle, devices, doctor, calibrate, sim)


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="perfcap", description="Hardware-in-the-loop performance capture.")
    p.add_argument("--version", action="version", version=f"perfcap {__version__}")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    p.add_argument("--debug", action="store_true", help="show tracebacks of internal errors")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    for command in COMMANDS:
        command.add_parser(sub)
    return p


def _live(args: argparse.Namespace) -> bool:
    """Whether the command captures live (rather than working offline on files)."""
    if args.command in ("record", "demo", "serve"):
        return True
    return (args.command == "puppet" and bool(args.phone)) or (args.command == "replay" and not args.fast)


def _undecodable(argv: Sequence[str]) -> str | None:
    """The first argument holding bytes that are not UTF-8 (``os.fsdecode`` hands them over as lone
    surrogates), shown with those bytes escaped; None when every argument is text."""
    for a in argv:
        try:
            a.encode("utf-8")
        except UnicodeEncodeError:
            return os.fsencode(a).decode("utf-8", "backslashreplace")
    return None


def _tolerant_output() -> None:
    """Output that cannot fail on text the terminal's encoding lacks (a device name in a session, a file
    name listed from a folder): such characters are written escaped, never raised as an error."""
    for stream in (sys.stdout, sys.stderr):
        if isinstance(stream, io.TextIOWrapper) and stream.errors == "strict":
            stream.reconfigure(errors="backslashreplace")


def main(argv: Sequence[str] | None = None) -> int:
    _tolerant_output()
    argv = sys.argv[1:] if argv is None else list(argv)
    bad = _undecodable(argv)
    if bad is not None:
        # a file name or value that is not UTF-8 could not be recorded in a session, shown or sent on:
        # refused where it enters, as every other bad input
        print(f"perfcap: error: the argument {bad!r} is not UTF-8 text (perfcap takes UTF-8 file names and"
              " values; rename the file)", file=sys.stderr)
        return EXIT_BAD_INPUT
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING if args.verbose == 0 else logging.INFO if args.verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="perfcap: %(levelname)s: %(message)s", stream=sys.stderr)
    if _live(args):
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
