"""``perfcap export``: a session's samples and events as CSV or JSON lines (``capture.app.export``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from capture.app.cli.common import EXIT_CHECK_FAILED, Progress, err, input_file, out, output_file

if TYPE_CHECKING:
    import argparse

    from capture.app.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    e = sub.add_parser("export", help="export samples and events as CSV or JSON lines")
    e.add_argument("session", metavar="SESSION")
    e.add_argument("--format", required=True, choices=["csv", "jsonl"])
    e.add_argument("-o", "--output", required=True, metavar="DIR")
    e.add_argument("--overwrite", action="store_true")
    e.add_argument("-q", "--quiet", action="store_true")
    e.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from capture.app.export import export_session
    from capture.session import SessionReader

    input_file(args.session, "SESSION")
    output_file(args.output, "-o")
    prog = Progress("reading", args.quiet)
    reader = SessionReader(args.session, progress=prog)
    prog.done()
    res = export_session(reader, args.output, args.format, overwrite=args.overwrite)
    folder = args.output.rstrip("/")          # "take/" is said as "take/", not "take//"
    out(f"exported {res.samples} samples of {res.streams} streams to {folder}/ ({args.format})")
    for note in res.notes:
        out(f"note: {note}")
    if not res.samples:
        err(f"perfcap: error: {args.session} holds no samples to export (its events were written)")
        return EXIT_CHECK_FAILED
    return 0
