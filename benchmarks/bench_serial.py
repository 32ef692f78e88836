"""Serial IMUs: codec decode throughput, a pty-served WT901 at 200 Hz (loss and added latency), and
the CPU cost of reading 4 ports live.

    .venv/bin/python benchmarks/bench_serial.py [--seconds 60] [--only a|b|c ...]

(a) Decode throughput per codec, offline: the same bytes decoded by the device's vectorised batch
    path (``Device.process_chunks``, what replay uses) and by the scalar path (``process_chunk``
    per chunk), frames per second. Target: >= 1 M frames/s for the vectorised decode; the full
    vectorised device path (decode + clock stamping, what replay runs) is printed beside it.
(b) ``perfcap sim serial`` (a separate process, as a real device is) serves a WitMotion at 200 Hz
    on a pty for ``--seconds`` (default 60). ``Capture`` reads it through pyserial. The simulator
    logs the host time of every write; the added latency of a reading is its arrival stamp minus
    that write time. Targets: zero lost readings, latency p99 < 2 ms. Baseline: the common
    hand-written loop that polls ``in_waiting`` every 10 ms and reads what is there.
(c) 4 simulated ports at 200 Hz read live for 15 s by one ``Capture`` (readers, bus, stats; no
    recorder): CPU time of this process divided by wall time. Target: well under 5% of one core.

Measurement script: prints figures and PASS/FAIL per target, always exits 0.
"""

from __future__ import annotations

import sys

sys.setswitchinterval(0.0005)  # as the perfcap CLI does for live work

import argparse  # noqa: E402
import os  # noqa: E402
import select  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from functools import partial  # noqa: E402

import numpy as np  # noqa: E402
import serial  # noqa: E402
from _common import check, header, pct, summary  # noqa: E402

from capture.app.orchestrator import Capture  # noqa: E402
from capture.sample import Chunk, ChunkRun  # noqa: E402
from devices import open_device  # noqa: E402
from devices.reader import ReconnectPolicy  # noqa: E402
from sim_devices.frames import ENCODERS, WavingSource  # noqa: E402

START_MS = 12 * 3_600_000


def decode_throughput() -> None:
    print("(a) decode throughput, offline (frames/s)")
    for kind in sorted(ENCODERS):
        src = WavingSource(kind, 200.0, seed=1)
        opts = src.device_options()
        pieces: list[bytes] = []
        times: list[np.ndarray] = []
        for t, p in src.blocks():
            pieces += p
            times.append(t)
            if len(pieces) >= 200_000:
                break
        t_s = np.concatenate(times)[:len(pieces)]
        # chunks as a 200 Hz link delivers them: one reading per chunk
        chunks = [Chunk(p, int(1e9 + t * 1e9)) for p, t in zip(pieces, t_s, strict=True)]
        q = "&".join(f"{k}={v}" for k, v in opts.items())
        fresh = partial(open_device, f"b={kind}@loop://?{q}")  # a new device on a loop:// port, same options

        probe = fresh()
        n_frames = sum(len(probe.codec.feed(p)) for p in pieces)
        run = ChunkRun.from_chunks(chunks)
        rest = run.slice(50, len(run))
        n_rest = n_frames * (len(chunks) - 50) / len(chunks)
        best_dec = best_vec = best_sc = float("inf")
        for _ in range(3):
            d = fresh()
            d.process_chunks(chunks[:50])  # learns the cycle layout
            t0 = time.perf_counter()
            batch = d.decode_batch(rest)
            best_dec = min(best_dec, time.perf_counter() - t0)
            assert batch is not None, f"{kind}: the vectorised decoder declined clean data"
            d = fresh()
            d.process_chunks(chunks[:50])
            t0 = time.perf_counter()
            items = d.process_chunks(rest)
            best_vec = min(best_vec, time.perf_counter() - t0)
        for _ in range(2):
            d = fresh()
            t0 = time.perf_counter()
            for c in chunks[:50_000]:
                d.process_chunk(c)
            best_sc = min(best_sc, time.perf_counter() - t0)
        sc_rate = n_frames * 50_000 / len(chunks) / best_sc
        dec_rate = n_rest / best_dec
        vec_rate = n_rest / best_vec
        batched = sum(1 for it in items if type(it).__name__ == "SampleBatch")
        print(f"   {kind}: {n_frames} frames in {len(chunks)} chunks (one reading per chunk)")
        print(f"      codec decode, vectorised   {dec_rate / 1e6:6.2f} M frames/s")
        print(f"      device path, vectorised    {vec_rate / 1e6:6.2f} M frames/s (decode + clock stamping +"
              f" {batched} sample batches: what replay runs)")
        print(f"      device path, per chunk     {sc_rate / 1e6:6.2f} M frames/s (baseline: the live path), "
              f"vectorised x{vec_rate / sc_rate:.0f}")
        check(f"{kind} vectorised decode >= 1 M frames/s", dec_rate >= 1e6, f"{dec_rate / 1e6:.2f} M frames/s")
    print()


def start_sim(link: str, rate: float, seconds: float, sent_log: str | None = None, seed: int = 1) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "capture.app.cli", "sim", "serial", "--kind", "witmotion", "--rate", str(rate),
           "--link", link, "--duration", str(seconds), "--seed", str(seed)]
    if sent_log:
        cmd += ["--sent-log", sent_log]
    p = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert p.stdout is not None
    line = p.stdout.readline().strip()
    if line != link:
        raise SystemExit(f"simulator did not start: {line} {p.stderr.read() if p.stderr else ''}")
    return p


def reading_index(t_device_ns: np.ndarray, rate: float) -> np.ndarray:
    ms = np.asarray(t_device_ns, np.int64) // 1_000_000
    return np.round((ms - START_MS) * rate / 1000.0).astype(np.int64)


def pty_latency(seconds: float) -> None:
    print(f"(b) pty-served WitMotion at 200 Hz for {seconds:.0f} s (simulator in its own process)")
    with tempfile.TemporaryDirectory() as tmp:
        link = os.path.join(tmp, "ttyWIT")
        log = os.path.join(tmp, "sent.npy")
        sim = start_sim(link, 200.0, seconds + 3, log)
        got: list[tuple[np.ndarray, np.ndarray]] = []
        from capture.bus import Overflow, Subscriber
        from capture.sample import Sample, SampleBatch

        class Keep(Subscriber):
            accepts = frozenset({Sample, SampleBatch})

            def on_item(self, item):
                if item.stream == "wrist/imu":
                    got.append((np.atleast_1d(item.t_device_ns), np.atleast_1d(item.t_host_ns)))

        cap = Capture([f"wrist=witmotion@serial://{link}?rate=200&device_clock=true"],
                      reconnect=ReconnectPolicy(initial_s=0.05, max_s=0.2))
        cap.subscribe(Keep(), policy=Overflow.NEVER_DROP, name="keep")
        rep = cap.run(seconds)
        sim.wait(30)
        sent = np.load(log)
        dev = np.concatenate([g[0] for g in got]).astype(np.int64)
        host = np.concatenate([g[1] for g in got]).astype(np.int64)
        idx = reading_index(dev, 200.0)
        t_first, t_last = host[0], host[-1]
        # readings the simulator wrote while the capture ran
        window = sent[(sent[:, 1] >= t_first) & (sent[:, 1] <= t_last)]
        pos = {int(i): k for k, i in enumerate(idx)}
        lost = [int(i) for i in window[:, 0] if int(i) not in pos]
        lat = np.array([host[pos[int(i)]] - t for i, t in window if int(i) in pos]) / 1e6
        p50, p99, p999, mx = pct(lat, 50, 99, 99.9, 100)
        d = rep.devices["wrist"]
        print(f"   readings written {len(window)}, received {len(window) - len(lost)}, lost {len(lost)};"
              f" codec errors {d['checksum_errors'] + d['framing_errors']}, reconnects {d['reconnects']}")
        print(f"   added latency (arrival stamp - write): p50 {p50:.3f} / p99 {p99:.3f} / p99.9 {p999:.3f} /"
              f" max {mx:.3f} ms")
        check("pty WitMotion 200 Hz: zero lost readings", not lost, f"{len(lost)} lost of {len(window)}")
        check("pty WitMotion 200 Hz: added latency p99 < 2 ms", p99 < 2.0, f"p99 {p99:.3f} ms")

        # baseline: the usual hand-written polling loop
        link2 = os.path.join(tmp, "ttyWIT2")
        log2 = os.path.join(tmp, "sent2.npy")
        base_s = min(10.0, seconds)
        sim2 = start_sim(link2, 200.0, base_s + 2, log2)
        ser = serial.Serial(link2, 115200, timeout=0)
        arrivals: list[tuple[int, int]] = []  # (byte offset end, stamp)
        buf = bytearray()
        t_end = time.monotonic_ns() + int(base_s * 1e9)
        while time.monotonic_ns() < t_end:
            n = ser.in_waiting
            if n:
                buf += ser.read(n)
                arrivals.append((len(buf), time.monotonic_ns()))
            time.sleep(0.01)
        ser.close()
        sim2.wait(30)
        sent2 = np.load(log2)
        # decode what the loop read, arrival by arrival, to know when each reading became available
        from devices.codecs.witmotion import TIME, WitMotionCodec
        codec = WitMotionCodec()
        sent_at = {int(i): int(t) for i, t in sent2}
        blat_l = []
        prev = 0
        for end, stamp in arrivals:
            for f in codec.feed(bytes(buf[prev:end])):
                if f.type == TIME:
                    _, _, _, hh, mi, ss, ms = f.time_fields()
                    i = round((((hh * 60 + mi) * 60 + ss) * 1000 + ms - START_MS) * 200 / 1000)
                    if i in sent_at:
                        blat_l.append((stamp - sent_at[i]) / 1e6)
            prev = end
        blat = np.array(blat_l)
        bp50, bp99 = pct(blat, 50, 99)
        print(f"   baseline (poll in_waiting every 10 ms): p50 {bp50:.3f} / p99 {bp99:.3f} ms"
              f" -> perfcap p99 is x{bp99 / p99:.0f} lower")
    print()


def live_cpu(seconds: float = 15.0) -> None:
    print(f"(c) 4 ports x 200 Hz read live for {seconds:.0f} s (readers + bus + stats, no recorder)")
    with tempfile.TemporaryDirectory() as tmp:
        links = [os.path.join(tmp, f"tty{i}") for i in range(4)]
        sims = [start_sim(link, 200.0, seconds + 3, seed=i + 1) for i, link in enumerate(links)]
        cap = Capture([f"w{i}=witmotion@serial://{link}?rate=200&device_clock=true" for i, link in enumerate(links)])
        c0, w0 = time.process_time(), time.perf_counter()
        rep = cap.run(seconds)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        for s in sims:
            s.wait(30)
        n = sum(v["samples"] for k, v in rep.streams.items() if k.endswith("/imu"))
        frac = cpu / wall
        print(f"   {n} IMU readings ({n / wall:.0f}/s), CPU {cpu:.2f} s in {wall:.1f} s = {frac * 100:.2f}% of one core"
              f" ({cpu / max(1, n) * 1e6:.1f} us per reading, all streams)")
        check("4 ports x 200 Hz live: < 5% of one core", frac < 0.05, f"{frac * 100:.2f}%")
    # baseline: the least a Python reader can do, one thread per port that only waits and reads
    with tempfile.TemporaryDirectory() as tmp:
        links = [os.path.join(tmp, f"tty{i}") for i in range(4)]
        sims = [start_sim(link, 200.0, seconds + 3, seed=i + 1) for i, link in enumerate(links)]
        for link in links:
            t_wait = time.monotonic() + 10
            while not os.path.exists(link) and time.monotonic() < t_wait:
                time.sleep(0.01)
        ports = [serial.Serial(link, timeout=0) for link in links]
        stop = threading.Event()
        got = [0] * len(ports)

        def bare(k: int, fd: int) -> None:
            while not stop.is_set():
                r, _, _ = select.select((fd,), (), (), 0.1)
                if r:
                    try:
                        got[k] += len(os.read(fd, 4096))
                    except OSError:
                        return

        threads = [threading.Thread(target=bare, args=(k, p.fileno()), daemon=True) for k, p in enumerate(ports)]
        c0, w0 = time.process_time(), time.perf_counter()
        for t in threads:
            t.start()
        time.sleep(seconds)
        stop.set()
        for t in threads:
            t.join(1)
        bcpu, bwall = time.process_time() - c0, time.perf_counter() - w0
        for p in ports:
            p.close()
        for s in sims:
            s.wait(30)
        print(f"   baseline (a bare select + os.read thread per port, no decoding): {sum(got) / 44 / bwall:.0f}"
              f" readings/s, {bcpu / bwall * 100:.2f}% of one core -> perfcap's decoding, stamping and bus cost"
              f" {(frac - bcpu / bwall) * 100:.2f}% on top")
    print()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=60.0, help="length of the pty run (b)")
    ap.add_argument("--only", choices=("a", "b", "c"), action="append",
                    help="run only these parts (repeatable); default all")
    args = ap.parse_args()
    parts = set(args.only or "abc")
    header("serial IMUs: decode throughput, pty latency, live CPU")
    if "a" in parts:
        decode_throughput()
    if "b" in parts:
        pty_latency(args.seconds)
    if "c" in parts:
        live_cpu()
    summary()


if __name__ == "__main__":
    main()
