"""Fuzzing campaign: structure-aware mutations through every device kind (issue 16).

    .venv/bin/python benchmarks/fuzz_devices.py [--inputs 20000] [--seed 1] [--only KIND ...]

For each device kind (serial IMUs: text-line, BNO08x RVC, WitMotion; HID: Sony DS4 and DualSense,
Nintendo, generic (simulated and a real hid-recorder capture); phone page JSON, HyperIMU, OSC,
SensorServer, Sensor Logger push), ``--inputs`` mutated messages, each between two valid ones,
go through the real device object (``Device.process_chunk``), then the same chunks through a real
``DeviceReader`` and ``SampleBus`` (not for HID kinds, whose handshake needs their simulator).
The harness is ``tests/device_fuzz_helpers.py`` (the CI test, ``tests/unit/devices/
test_device_fuzz.py``, runs 400 per kind). Printed per device and per codec: inputs; escapes
(exceptions out of the device); silent drops (a mutated message that gave no sample and moved no
counter); samples of the valid messages not delivered; samples delivered with an infinite value
(``inf``); chunks whose exception the device layer's net caught (``net``: the codec should have
refused them with a reason); the reader's end state and whether the bus got every sample.
Targets: no escape, no silent drop, no infinite value, the reader FINISHED with every sample on the
bus, and no valid sample lost (but what a kind's ``lost_per_input`` allows: a damaged Nintendo
timer byte makes up to two samples of the next report look repeated, counted in
``overlapping_samples``).

Measurement script: prints figures and PASS/FAIL per target, always exits 0.
"""

from __future__ import annotations

import argparse
import collections
import logging
import sys
import time
from pathlib import Path

from _common import check, header, summary

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from device_fuzz_helpers import KINDS, FuzzResult, fuzz_kind


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--inputs", type=int, default=20_000, help="mutated messages per device kind")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--only", nargs="*", choices=sorted(KINDS), help="these device kinds only")
    args = ap.parse_args()
    if args.inputs < 1:
        ap.error("--inputs must be at least 1")
    logging.disable(logging.CRITICAL)  # every refusal is logged (rate-limited); only the figures matter here
    header(f"device fuzzing: {args.inputs} mutated messages per device kind, seed {args.seed}")
    print(f"   {'device kind':44s} {'codec':12s} {'inputs':>7s} {'escapes':>7s} {'silent':>6s} "
          f"{'valid lost':>14s} {'inf':>4s} {'net':>4s} {'reader':>8s} {'bus ok':>6s} {'s':>6s}")
    results: list[FuzzResult] = []
    for key in args.only or list(KINDS):
        t0 = time.monotonic()
        r = fuzz_kind(key, args.inputs, seed=args.seed)
        dt = time.monotonic() - t0
        results.append(r)
        bus = "-" if not r.reader_state else "yes" if r.bus_samples == r.samples else "NO"
        print(f"   {r.kind:44s} {r.codec:12s} {r.inputs:7d} {r.escapes:7d} {r.silent:6d} "
              f"{r.good_lost:6d}/{r.good_samples:<7d} {r.inf_delivered:4d} {r.net_caught:4d} "
              f"{r.reader_state or '-':>8s} {bus:>6s} {dt:6.1f}")
        for e in r.examples[:3]:
            print(f"      {e[:200]}")
    print()
    per_codec: dict[str, list[int]] = collections.defaultdict(lambda: [0, 0, 0])
    for r in results:
        c = per_codec[r.codec]
        c[0] += r.inputs
        c[1] += r.escapes
        c[2] += r.silent
    print("   per codec: " + "; ".join(f"{k} {v[0]} inputs, {v[1]} escapes, {v[2]} silent"
                                        for k, v in sorted(per_codec.items())))
    total = sum(r.inputs for r in results)
    print(f"   total: {total} mutated messages through {len(results)} device kinds, "
          f"{sum(r.escapes for r in results)} escapes")
    print()
    for r in results:
        check(f"{r.kind}", not r.problems(), "; ".join(r.problems()) or
              f"{r.inputs} inputs, no escape, none silent, {r.good_lost} of {r.good_samples} valid samples lost"
              + (f", reader {r.reader_state}, {r.bus_samples} samples on the bus" if r.reader_state else ""))
    summary()


if __name__ == "__main__":
    main()
