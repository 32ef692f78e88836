"""LSL out: publish-to-receive latency and loss of ``LslPublisher`` at 17 streams x 200 Hz on loopback, beside
raw pylsl outlets pushed by a plain loop (no perfcap) in the same run.

Each run: 17 outlets in this process; inlets in a second process (this script with ``--inlets``) pulling
all of them. Every sample carries, besides its values, its sequence number and the host-monotonic moment
it was handed on (perfcap: published on the bus, so the bus queue, the publisher's thread and LSL are all
measured; raw: pushed to the outlet). The receiving process stamps each sample as it pulls it with the
same host-monotonic clock (one clock for every process of the machine), so latency = receive moment -
hand-on moment, and loss = sequence numbers never received.

    .venv/bin/python benchmarks/bench_lsl.py [--seconds 10] [--streams 17] [--rate 200]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from typing import Any

sys.path.insert(0, os.path.dirname(__file__))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

CHANNELS = ("seq", "t_handed_ns", "ax", "ay", "az", "gx", "gy")


def _lsl_config() -> None:
    """The tests' liblsl configuration (discovery kept to the link, a session of its own, so no other LSL
    program's streams are seen); the child process inherits ``LSLAPICFG``."""
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests"))
    import lsl_helpers

    lsl_helpers.configure()


# -- the receiving process -------------------------------------------------------------------------------
def inlets_main(prefix: str, n: int) -> int:
    import numpy as np
    import pylsl

    found: dict[str, Any] = {}
    end = time.monotonic() + 60
    while len(found) < n and time.monotonic() < end:
        for s in pylsl.resolve_bypred(f"starts-with(name,'{prefix}')", n, 2.0):
            found.setdefault(s.name(), s)
    inlets = {name: pylsl.StreamInlet(info, max_buflen=60, processing_flags=0) for name, info in found.items()}
    for inlet in inlets.values():
        inlet.open_stream(30)
    print(json.dumps({"ready": len(inlets)}), flush=True)
    lat: list[float] = []
    seqs: dict[str, list[float]] = {k: [] for k in inlets}
    expected: dict[str, int] | None = None
    import select

    deadline = None
    items = list(inlets.items())
    while True:
        got = 0
        for name, inlet in items:
            data, _ = inlet.pull_chunk(timeout=0.0, max_samples=1024)
            if data:
                now = time.monotonic_ns()
                arr = np.asarray(data, np.float64)
                lat.extend((now - arr[:, 1]).tolist())
                seqs[name].extend(arr[:, 0].tolist())
                got += len(data)
        if expected is None and select.select([sys.stdin], [], [], 0)[0]:
            expected = json.loads(sys.stdin.readline())
            deadline = time.monotonic() + 10
        if expected is not None and (all(len(seqs[k]) >= v for k, v in expected.items())
                                     or time.monotonic() > (deadline or 0)):
            break
        if not got:
            time.sleep(0.0002)
    lost = sum(max(0, v - len(set(seqs.get(k, [])))) for k, v in (expected or {}).items())
    a = np.asarray(lat) / 1e6
    print(json.dumps({"received": sum(len(v) for v in seqs.values()), "lost": lost,
                      "p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
                      "max": float(a.max()), "streams": len(inlets)}), flush=True)
    return 0


# -- the sending side ------------------------------------------------------------------------------------
def _child(prefix: str, n: int) -> subprocess.Popen[str]:
    p = subprocess.Popen([sys.executable, os.path.abspath(__file__), "--inlets", prefix, "--streams", str(n)],
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert p.stdout is not None
    ready = json.loads(p.stdout.readline())
    if ready.get("ready") != n:
        raise RuntimeError(f"the receiving process found {ready} of {n} streams")
    return p


def _finish(p: subprocess.Popen[str], sent: dict[str, int]) -> dict[str, Any]:
    assert p.stdin is not None and p.stdout is not None
    p.stdin.write(json.dumps(sent) + "\n")
    p.stdin.flush()
    res = json.loads(p.stdout.readline())
    p.wait(30)
    res["sent"] = sum(sent.values())
    return res


def run_perfcap(n: int, rate: float, seconds: float) -> dict[str, Any]:
    from capture.app.lsl_out import LslPublisher
    from capture.bus import Overflow, SampleBus
    from capture.clock import MonotonicClock
    from capture.sample import DeviceIdentity, Sample, StreamInfo

    clock = MonotonicClock()
    units = ("1", "ns", "m/s^2", "m/s^2", "m/s^2", "rad/s", "rad/s")
    infos = [StreamInfo(f"pc{i}/imu", "imu", CHANNELS, units, rate, DeviceIdentity("bench", f"pc{i}"))
             for i in range(n)]
    bus = SampleBus(clock)
    pub = LslPublisher(infos, clock=clock)
    sub = bus.subscribe(pub, policy=Overflow.NEVER_DROP, name="lsl")
    child = _child("pc", n)
    period = int(1e9 / rate)
    t0 = clock.now_ns() + 50_000_000
    ticks = int(seconds * rate)
    names = [s.name for s in infos]
    for k in range(ticks):
        clock.sleep_until_ns(t0 + k * period)
        for name in names:
            now = clock.now_ns()
            bus.publish(Sample(name, k, now, None, now, (float(k), float(now), 0.1, 0.2, 9.8, 0.01, 0.02)))
    res = _finish(child, dict.fromkeys(names, ticks))
    stats = sub.stats()
    bus.close()
    res["bus_dropped"] = stats.dropped
    res["max_pending"] = stats.max_pending
    return res


def run_raw(n: int, rate: float, seconds: float) -> dict[str, Any]:
    import pylsl

    outlets = []
    for i in range(n):
        info = pylsl.StreamInfo(f"raw{i}/imu", "MoCap", len(CHANNELS), rate, pylsl.cf_double64, f"raw{i}")
        outlets.append(pylsl.StreamOutlet(info))
    child = _child("raw", n)
    period = 1.0 / rate
    ticks = int(seconds * rate)
    t0 = time.monotonic() + 0.05
    for k in range(ticks):
        deadline = t0 + k * period
        while True:  # the same pacing as perfcap's clock: OS sleep, then a short spin
            left = deadline - time.monotonic()
            if left <= 0:
                break
            time.sleep(left - 0.0003 if left > 0.0003 else 0)
        for o in outlets:
            now = time.monotonic_ns()
            o.push_sample((float(k), float(now), 0.1, 0.2, 9.8, 0.01, 0.02), now / 1e9)
    res = _finish(child, {f"raw{i}/imu": ticks for i in range(n)})
    del outlets
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--streams", type=int, default=17)
    ap.add_argument("--rate", type=float, default=200.0)
    ap.add_argument("--inlets", metavar="PREFIX", help=argparse.SUPPRESS)
    args = ap.parse_args()
    _lsl_config()
    if args.inlets:
        return inlets_main(args.inlets, args.streams)
    from _common import check, header, summary

    sys.setswitchinterval(0.0005)  # as perfcap's live commands run
    header(f"LSL out: {args.streams} streams x {args.rate:g} Hz for {args.seconds:g} s on loopback, inlets in"
           " a second process")
    raw = run_raw(args.streams, args.rate, args.seconds)
    pc = run_perfcap(args.streams, args.rate, args.seconds)
    print(f"   {'':28s} {'sent':>7s} {'received':>8s} {'lost':>5s} {'p50 ms':>7s} {'p99 ms':>7s} {'max ms':>7s}")
    for label, r in (("baseline: raw pylsl loop", raw), ("perfcap LslPublisher (bus)", pc)):
        print(f"   {label:28s} {r['sent']:7d} {r['received']:8d} {r['lost']:5d} {r['p50']:7.3f} {r['p99']:7.3f}"
              f" {r['max']:7.3f}")
    print(f"   perfcap: bus queue dropped {pc['bus_dropped']}, at most {pc['max_pending']} items waiting")
    print()
    check("p99 publish-to-receive latency < 2 ms", pc["p99"] < 2.0,
          f"{pc['p99']:.3f} ms (raw pylsl {raw['p99']:.3f} ms)")
    check("no sample lost", pc["lost"] == 0 and pc["bus_dropped"] == 0 and pc["received"] == pc["sent"],
          f"{pc['lost']} lost of {pc['sent']} (raw pylsl {raw['lost']})")
    summary()
    return 0


if __name__ == "__main__":
    sys.exit(main())
