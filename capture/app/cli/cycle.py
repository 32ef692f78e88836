"""``perfcap cycle``: one clean closed loop from a take of several performed loops (a session stream or
a CSV), as CSV, JSON and a report image."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

from capture.app.cli.common import EXIT_NO_CYCLE, SEED, err, input_file, out, output_file
from capture.errors import ConfigError, CycleError

if TYPE_CHECKING:
    import argparse

    from capture.app.cli.common import Subcommands
    from capture.app.cycle_input import CycleInput


def add_parser(sub: Subcommands) -> None:
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
    cy.add_argument("--seed", type=SEED, default=0, help="seed of the extraction's random choices (default 0)")
    cy.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from capture.app.cycle_input import extract_cycle, read_cycle_input, split_columns, write_cycle_report

    input_file(args.input, "INPUT")
    output_file(args.output, "-o")
    output_file(args.report, "--report")
    columns = split_columns(args.columns)
    inp = read_cycle_input(args.input, args.stream, columns)
    if len(inp.t) < 2:
        raise ConfigError(f"{inp.source}: {len(inp.t)} sample(s); a cycle needs several loops of motion")
    try:
        cyc = extract_cycle(inp, args.seed)
    except CycleError as exc:
        err(f"perfcap: no cycle in {inp.source}: {exc}")
        if args.json:  # a script reading stdout gets an object either way, and "ok" says which
            out(json.dumps({"ok": False, "error": "no cycle", "reason": str(exc), **_input_fields(args, inp)}))
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
        out(json.dumps({"ok": True, **s, **_input_fields(args, inp), "csv": args.output, "report": args.report}))
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


def _input_fields(args: argparse.Namespace, inp: CycleInput) -> dict[str, object]:
    """What ``--json`` says of the input, on success and on failure alike."""
    return {"input": args.input, "stream": inp.stream, "time_origin_ns": inp.origin_ns,
            "input_samples": len(inp.t), "rows_skipped": inp.dropped}
