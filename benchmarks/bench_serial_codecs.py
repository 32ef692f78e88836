"""Decode throughput of the BNO08x UART-RVC and text-line codecs, scalar and vectorised.

    .venv/bin/python benchmarks/bench_serial_codecs.py

Frames per second of:

* ``codec.feed`` (the per-chunk path a live device uses), fed in 4 KiB reads;
* ``codec.feed_clean`` (the vectorised decoder offline replay uses on clean runs), fed in blocks
  of 64 KiB and 1 MiB of whole frames, and in one 20 MB block (memory-bound);
* the whole device: ``process_chunk`` per chunk and ``process_chunks`` on runs of 4096 chunks
  (decoding, clock sync and sample building), on 120-byte serial reads.

Data: 1,000,000 BNO08x frames (random angles and accelerations, consecutive indices), and
400,000 sketch lines ``millis,ax,ay,az,gx,gy,gz`` printed with 4 and 3 decimals (about 50 bytes),
as CSV and as key:value. Target (offline replay): >= 1,000,000 frames/s vectorised.

Measurement script: prints figures and PASS/FAIL per target, always exits 0.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np
from _common import check, header, summary

from capture.sample import Chunk, ChunkRun
from devices.bno08x import Bno08xRvcImu, encode_rvc_many
from devices.codecs.bno08x_rvc import FRAME_LEN, Bno08xRvcCodec
from devices.textline import TextLineImu, TextLineLayout
from devices.transports import open_transport

if TYPE_CHECKING:
    from collections.abc import Callable

TARGET = 1_000_000
OPTS = {"format": "csv", "columns": "t,ax,ay,az,gx,gy,gz", "units": "ms,g,g,g,dps,dps,dps", "time": "t",
        "time_wrap": "u32", "rate": "100"}


def best_rate(n: int, fn: Callable[[], object], repeat: int = 3) -> float:
    """Items per second of the fastest of ``repeat`` runs of ``fn`` (which handles ``n`` items)."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return n / best


def blocks(data: bytes, size: int, sep: bytes | None = None, frame: int | None = None) -> list[bytes]:
    """``data`` cut into blocks of about ``size`` bytes of whole frames: of ``frame`` bytes each, or
    lines ending in ``sep``; with neither, plain ``size``-byte blocks."""
    out = []
    i = 0
    while i < len(data):
        if frame:
            j = min(len(data), i + max(frame, size // frame * frame))
        elif sep:
            j = data.rfind(sep, i, i + size) + 1
            if j <= i:  # a line longer than the block: cut after its end
                j = data.find(sep, i) + 1
        else:
            j = i + size
        out.append(data[i:j])
        i = j
    return out


def chunks_of(data: bytes, size: int, period_ns: int) -> list[Chunk]:
    return [Chunk(data[i:i + size], 1_000_000_000 + (i // size) * period_ns) for i in range(0, len(data), size)]


def bench_bno() -> None:
    n = 1_000_000
    rng = np.random.default_rng(1)
    wire = encode_rvc_many(np.arange(n), rng.uniform(-179, 179, (n, 3)), rng.uniform(-30, 30, (n, 3))).tobytes()
    print(f"-- BNO08x UART-RVC: {n:,} frames, {len(wire) / 1e6:.1f} MB")

    def scalar() -> None:
        c = Bno08xRvcCodec()
        for b in blocks(wire, 4096, frame=1):
            c.feed(b)

    r_scalar = best_rate(n, scalar, 1)
    print(f"   codec.feed, 4 KiB reads:                 {r_scalar:>12,.0f} frames/s")
    rates = {}
    for label, size in (("64 KiB", 1 << 16), ("1 MiB", 1 << 20), ("one 19 MB block", len(wire))):
        bl = blocks(wire[FRAME_LEN:], size, frame=FRAME_LEN)

        def vec(bl: list[bytes] = bl) -> None:
            c = Bno08xRvcCodec()
            c.feed(wire[:FRAME_LEN])  # lock on the stream, as the per-chunk path does first
            for b in bl:
                if c.feed_clean(b) is None:
                    raise RuntimeError("clean data declined")

        rates[label] = best_rate(n - 1, vec)
        print(f"   codec.feed_clean, {label + ':':<22} {rates[label]:>12,.0f} frames/s")
    check("BNO08x vectorised decode >= 1 M frames/s (1 MiB blocks)", rates["1 MiB"] >= TARGET,
          f"{rates['1 MiB']:,.0f} frames/s ({rates['1 MiB'] / r_scalar:.0f}x the scalar codec)")
    m = 100_000
    ch = chunks_of(wire[:m * FRAME_LEN], 120, 6_300_000)

    def per_chunk() -> None:
        d = Bno08xRvcImu("b", open_transport("loop://"))
        for c in ch:
            d.process_chunk(c)

    def batched() -> None:
        d = Bno08xRvcImu("b", open_transport("loop://"))
        for k in range(0, len(ch), 4096):
            d.process_chunks(ChunkRun.from_chunks(ch[k:k + 4096]))

    print(f"   device process_chunk, 120 B reads:       {best_rate(m, per_chunk, 1):>12,.0f} frames/s "
          "(2 samples each, clock sync included)")
    print(f"   device process_chunks, 4096-chunk runs:  {best_rate(m, batched, 1):>12,.0f} frames/s")


def bench_textline() -> None:
    n = 400_000
    rng = np.random.default_rng(2)
    lay = TextLineLayout(OPTS)
    t = np.arange(n) / 100.0
    v = rng.normal(0, 5, (n, 6))
    acc, gyr = v[:, :3] / 9.80665, v[:, 3:] * 57.29577951308232
    csv = "".join(f"{round(t[i] * 1000)},{acc[i, 0]:.4f},{acc[i, 1]:.4f},{acc[i, 2]:.4f},"
                  f"{gyr[i, 0]:.3f},{gyr[i, 1]:.3f},{gyr[i, 2]:.3f}\n" for i in range(n)).encode()
    kv = "".join(f"t:{round(t[i] * 1000)} ax:{acc[i, 0]:.4f} ay:{acc[i, 1]:.4f} az:{acc[i, 2]:.4f} "
                 f"gx:{gyr[i, 0]:.3f} gy:{gyr[i, 1]:.3f} gz:{gyr[i, 2]:.3f}\n" for i in range(n)).encode()
    print(f"-- text lines: {n:,} lines, CSV {len(csv) / n:.1f} B/line, key:value {len(kv) / n:.1f} B/line")

    def scalar(data: bytes, fmt: str) -> Callable[[], None]:
        def run() -> None:
            c = TextLineLayout({**OPTS, "format": fmt}).codec()
            for b in blocks(data, 4096):
                c.feed(b)
        return run

    r_csv = best_rate(n, scalar(csv, "csv"), 1)
    r_auto = best_rate(n, scalar(csv, "auto"), 1)
    r_kv = best_rate(n, scalar(kv, "kv"), 1)
    print(f"   codec.feed CSV, 4 KiB reads:             {r_csv:>12,.0f} lines/s (format=auto: {r_auto:,.0f})")
    print(f"   codec.feed key:value, 4 KiB reads:       {r_kv:>12,.0f} lines/s")
    rates = {}
    for label, size in (("64 KiB", 1 << 16), ("1 MiB", 1 << 20), (f"one {len(csv) / 1e6:.0f} MB block", len(csv))):
        bl = blocks(csv, size, sep=b"\n")

        def vec(bl: list[bytes] = bl) -> None:
            c = lay.codec()
            for b in bl:
                if c.feed_clean(b) is None:
                    raise RuntimeError("clean data declined")

        rates[label] = best_rate(n, vec)
        print(f"   codec.feed_clean CSV, {label + ':':<18} {rates[label]:>12,.0f} lines/s")
    best = max(rates["64 KiB"], rates["1 MiB"])
    check("text-line vectorised CSV decode >= 1 M lines/s (best of 64 KiB / 1 MiB blocks)", best >= TARGET,
          f"{best:,.0f} lines/s ({best / r_csv:.1f}x the scalar codec)")
    m = 100_000
    ch = chunks_of(csv[:csv.index(b"\n", len(csv) * m // n) + 1], 120, 2_400_000)
    m = sum(c.data.count(b"\n") for c in ch)

    def per_chunk() -> None:
        d = TextLineImu("s", open_transport("loop://"), OPTS)
        for c in ch:
            d.process_chunk(c)

    def batched() -> None:
        d = TextLineImu("s", open_transport("loop://"), OPTS)
        for k in range(0, len(ch), 4096):
            d.process_chunks(ChunkRun.from_chunks(ch[k:k + 4096]))

    print(f"   device process_chunk, 120 B reads:       {best_rate(m, per_chunk, 1):>12,.0f} lines/s "
          "(clock sync included)")
    print(f"   device process_chunks, 4096-chunk runs:  {best_rate(m, batched, 1):>12,.0f} lines/s")


def main() -> None:
    header("serial codecs: BNO08x UART-RVC and text lines, decode throughput")
    bench_bno()
    print()
    bench_textline()
    summary()


if __name__ == "__main__":
    main()
