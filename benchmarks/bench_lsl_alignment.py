"""Bus-time alignment between two perfcap processes joined by LSL (issue 18's "beyond one machine").

    .venv/bin/python benchmarks/bench_lsl_alignment.py [--devices 9] [--seconds 10]

Host A (a child process): ``perfcap record --lsl`` of N realtime ``synth://imu?rate=200`` devices (each an
``imu`` and a ``euler`` stream at 200 Hz: 18 streams for N = 9, the issue's 17 x 200 Hz load and one more).
Host B (another child): ``perfcap record`` of every one of A's streams from ``lsl://<device>/<stream>``.
Both share this machine's monotonic clock, so for every sample B recorded, B's bus time minus A's bus time of
the same sample (matched by its values, which LSL carries exactly as float64) is the alignment error LSL
transport and B's clock fit leave. Also: samples A recorded during B's take that B does not have (lost).
Baseline in the same run: the same measurement with one device (two streams), the load-free figure.

liblsl's discovery is kept to this link with a session of its own (the tests' ``lsl_api.cfg``,
``tests/lsl_helpers.py``). Measurement script: prints figures and PASS/FAIL per target, always exits 0.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import check, header, pct, summary

from capture.session import SessionReader


def run(n: int, seconds: float, tmp: Path, env: dict[str, str]) -> dict[str, float]:
    a_path, b_path = tmp / f"a{n}.mcap", tmp / f"b{n}.mcap"
    devs = [f"d{i}=synth://imu?rate=200&seed={i + 1}&jitter_ms=1" for i in range(n)]
    dargs = [a for d in devs for a in ("-d", d)]
    a = subprocess.Popen([sys.executable, "-m", "capture.app.cli", "record", "-q", *dargs, "--lsl",
                          "--duration", str(seconds + 30), "-o", str(a_path)],
                         stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env)
    assert a.stderr is not None
    while "LSL outlets" not in (line := a.stderr.readline()):
        if not line:
            raise SystemExit(f"host A did not start: {a.stderr.read()}")
    streams = [f"d{i}/{s}" for i in range(n) for s in ("imu", "euler")]
    remote = [a for k, s in enumerate(streams) for a in ("-d", f"r{k}=lsl://{s}?timeout=20")]
    b = subprocess.run([sys.executable, "-m", "capture.app.cli", "record", "-q", *remote, "--duration", str(seconds),
                        "-o", str(b_path)], capture_output=True, text=True, env=env, timeout=seconds + 120, check=False)
    a.terminate()
    a.communicate(timeout=60)
    if b.returncode != 0:
        raise SystemExit(f"host B failed: {b.stderr}")
    ra, rb = SessionReader(str(a_path)), SessionReader(str(b_path))
    errs, lost, got_n = [], 0, 0
    for k, s in enumerate(streams):
        sent = ra.samples(s)
        got = rb.samples(next(x for x in rb.streams if x.startswith(f"r{k}/")))
        rows = {r.tobytes(): i for i, r in enumerate(sent.values)}
        idx = np.array([rows[r.tobytes()] for r in got.values])
        got_n += len(idx)
        lost += int(idx[-1] - idx[0] + 1 - len(np.unique(idx)))
        e = (got.t_bus_ns - sent.t_bus_ns[idx]) / 1e6
        errs.append(np.abs(e[got.t_bus_ns >= got.t_bus_ns[0] + 1_000_000_000]))   # after the fit's first second
    all_e = np.concatenate(errs)
    p50, p99, mx = pct(all_e, 50, 99, 100)
    return {"streams": len(streams), "samples": got_n, "lost": lost, "p50": p50, "p99": p99, "max": mx}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--devices", type=int, default=9)
    ap.add_argument("--seconds", type=float, default=10.0)
    args = ap.parse_args()
    header(f"bench_lsl_alignment: two perfcap processes over LSL, {2 * args.devices} streams x 200 Hz")
    with tempfile.TemporaryDirectory(prefix="perfcap-bench-lsl-") as tmp:
        sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
        import lsl_helpers  # the tests' liblsl configuration: discovery on this link, a session of its own

        lsl_helpers.configure()
        env = {k: v for k, v in os.environ.items() if not k.startswith("PERFCAP_")}
        t0 = time.monotonic()
        base = run(1, args.seconds, Path(tmp), env)
        res = run(args.devices, args.seconds, Path(tmp), env)
        for label, r in (("baseline, 1 device", base), (f"{args.devices} devices", res)):
            print(f"{label}: {r['streams']} streams, {r['samples']} samples received by B, lost {r['lost']};"
                  f" |bus time B - bus time A| ms: p50 {r['p50']:.3f}  p99 {r['p99']:.3f}  max {r['max']:.3f}")
        check("alignment p99 between the two processes", res["p99"] < 1.0, f"{res['p99']:.3f} ms (target < 1 ms)")
        check("samples lost at that load", res["lost"] == 0, f"{res['lost']} (target 0)")
        print(f"   ({time.monotonic() - t0:.0f} s)")
    summary()


if __name__ == "__main__":
    main()
