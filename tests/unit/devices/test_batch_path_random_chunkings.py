"""The vectorised batch path gives exactly the per-chunk path's samples on real recordings, cut into
chunks at random.

Real IMU traces from ``../shared/traces`` (the x-io hand rotation, the gaitmap walk) are encoded as
the three serial kinds with a batch decoder would send them (WitMotion, BNO08x UART-RVC, text
lines), with a link that delays, bursts, drops, corrupts and splits them, differently for every
seed. The same chunks are then decoded chunk by chunk (``process_chunk``) and in random runs
(``process_chunks``, vectorised where the data allows): sequence numbers, gaps, host, device and
bus times, values, counters and clock events must be identical, as must what ``finish`` emits.
Several hundred seeded chunkings in all; a failure names its kind and seed.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest

from capture.sample import Chunk, ChunkRun, DeviceEvent, Direction, EventKind, Sample, SampleBatch
from devices import device_class
from devices.bno08x import encode_rvc_many
from devices.textline import TextLineLayout
from devices.transports import open_transport
from sim_devices.frames import witmotion_wire

if TYPE_CHECKING:
    from devices.base import Device

TRACES = Path(__file__).resolve().parents[4] / "shared" / "traces"
XIO = TRACES / "a_imu_csv" / "fusion_sensor_data.csv"
GAIT = TRACES / "a_imu_csv" / "gaitmap_walk" / "imu_sample_not_rotated.csv"
G0 = 9.80665
MS_PER_DAY = 86_400_000
TEXTLINE = {"format": "csv", "columns": "t,ax,ay,az,gx,gy,gz", "units": "ms,g,g,g,dps,dps,dps", "time": "t",
            "time_wrap": "u32"}

#: (kind, trace) pairs, and how many seeded chunkings each gets (in blocks of SEEDS_PER_TEST)
CASES = [("witmotion", "xio"), ("witmotion", "gait"), ("textline", "gait"), ("textline", "xio"),
         ("bno08x_rvc", "xio")]
BLOCKS = 4
SEEDS_PER_TEST = 15


@functools.cache
def trace(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """(t s, acc g, gyro deg/s, mag uT or None) of a real recording."""
    path = XIO if name == "xio" else GAIT
    if not path.is_file():
        pytest.skip(f"real IMU trace not found at {path} (../shared/traces must sit beside the project)")
    if name == "xio":
        d = np.genfromtxt(path, delimiter=",", skip_header=1)
        return d[:, 0], d[:, 4:7], d[:, 1:4], d[:, 7:10]
    d = np.genfromtxt(path, delimiter=",", skip_header=2)
    return d[:, 0] / 204.8, d[:, 1:4] / G0, d[:, 4:7], None  # the left foot; index at 204.8 Hz


def tilt(acc_g: np.ndarray, gyro_dps: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Roll, pitch from gravity and yaw from the integrated z rate (deg, yaw wrapped to +-180)."""
    roll = np.degrees(np.arctan2(acc_g[:, 1], acc_g[:, 2]))
    pitch = np.degrees(np.arctan2(-acc_g[:, 0], np.hypot(acc_g[:, 1], acc_g[:, 2])))
    yaw = np.concatenate([[0.0], np.cumsum(np.diff(t) * gyro_dps[1:, 2])])
    return np.stack([roll, pitch, (yaw + 180.0) % 360.0 - 180.0], axis=1)


def readings(kind: str, name: str, rng: np.random.Generator) -> tuple[dict, np.ndarray, list[bytes]]:
    """Device options, true reading times (s) and the bytes of each reading of a random slice."""
    t, acc, gyro, mag = trace(name)
    n = int(rng.integers(150, 400))
    i0 = int(rng.integers(0, len(t) - n))
    sl = slice(i0, i0 + n)
    t, acc, gyro = t[sl] - t[i0], acc[sl], gyro[sl]
    rate = round(float(1.0 / np.median(np.diff(t))), 3)
    if kind == "witmotion":
        clock = bool(rng.random() < 0.75)
        dev_ms = None
        if clock:
            start = int(rng.choice([12 * 3_600_000, MS_PER_DAY - int(rng.integers(100, 2000))]))  # midnight wrap
            dev_ms = start + np.floor(t * 1000.0)
            if rng.random() < 0.2:  # the sensor restarts its clock part way
                k = int(rng.integers(n // 4, 3 * n // 4))
                dev_ms[k:] -= dev_ms[k] - float(rng.integers(0, 50))
        eul = tilt(acc, gyro, t) if rng.random() < 0.6 else None
        mags = mag[sl] * 10.0 if mag is not None and rng.random() < 0.5 else None
        data, step = witmotion_wire(dev_ms, acc, gyro, eul, mags)
        return {"rate": rate, "device_clock": clock}, t, [data[k * step:(k + 1) * step] for k in range(n)]
    if kind == "textline":
        opts = {**TEXTLINE, "rate": rate}
        lay = TextLineLayout(opts)
        ch = {"ax": acc[:, 0] * G0, "ay": acc[:, 1] * G0, "az": acc[:, 2] * G0,
              "gx": np.radians(gyro[:, 0]), "gy": np.radians(gyro[:, 1]), "gz": np.radians(gyro[:, 2])}
        t_dev = (float(rng.integers(0, 1 << 32)) / 1000.0 if rng.random() < 0.3 else 5.0) + np.floor(t * 1000) / 1000
        t_dev = np.mod(np.round(t_dev * 1000.0), float(1 << 32)) / 1000.0  # millis() wraps at 2^32
        return opts, t, lay.encode_lines(ch, t_dev, decimals=int(rng.integers(3, 6)))
    clock = bool(rng.random() < 0.7)
    index = (np.arange(n) + int(rng.integers(0, 256))) % 256
    wire = encode_rvc_many(index, tilt(acc, gyro, t), np.clip(acc * G0, -78.0, 78.0))
    return {"device_clock": clock}, t, [row.tobytes() for row in wire]


def chunks_of(pieces: list[bytes], t_s: np.ndarray, rng: np.random.Generator) -> list[Chunk]:
    """The readings' bytes through a random link: some readings lost, latency and jitter or
    bursts, garbage now and then, the byte stream cut anywhere, a handshake write or two."""
    n = len(pieces)
    keep = np.ones(n, bool)
    for _ in range(int(rng.integers(0, 3))):
        k = int(rng.integers(1, n - 10))
        keep[k:k + int(rng.integers(1, 8))] = False
    t0 = 1_000_000_000 * int(rng.integers(1, 100))
    arrive = t0 + np.round(t_s * 1e9).astype(np.int64) + int(rng.integers(0, 5_000_000))
    if rng.random() < 0.3:
        burst = int(rng.integers(4, 17)) * 1_000_000
        arrive = t0 + ((arrive - t0) // burst + 1) * burst
    else:
        arrive = arrive + rng.integers(0, int(rng.choice([1, 500_000, 3_000_000])), n)
    arrive = np.maximum.accumulate(arrive)
    garbage = float(rng.choice([0.0, 0.0, 0.01, 0.05]))
    stream = bytearray()
    ends: list[tuple[int, int]] = []  # (end offset of a reading's bytes, its arrival)
    for k in np.flatnonzero(keep).tolist():
        if garbage and rng.random() < garbage:
            stream += rng.integers(0, 256, int(rng.integers(1, 12)), np.uint8).tobytes()
        stream += pieces[k]
        ends.append((len(stream), int(arrive[k])))
    mode = rng.integers(0, 3)  # 0: a reading per chunk, 1: random cuts, 2: big random cuts
    out: list[Chunk] = []
    pos = 0
    j = 0
    while pos < len(stream):
        if mode == 0:
            while ends[j][0] <= pos:
                j += 1
            cut = ends[j][0]
        else:
            cut = min(len(stream), pos + int(rng.integers(1, 40 if mode == 1 else 400)))
        while ends[j][0] < cut:  # the chunk arrives with the reading its last byte belongs to
            j += 1
        out.append(Chunk(bytes(stream[pos:cut]), ends[j][1]))
        pos = cut
        if rng.random() < 0.01:
            out.append(Chunk(b"\xff\xaa\x00", ends[j][1], Direction.TX))
    return out


def flatten(items: list) -> tuple[dict[str, list[tuple]], list[tuple]]:
    """Samples by stream as (seq, host, device, bus, values) rows, and the clock and protocol events."""
    res: dict[str, list[tuple]] = {}
    events = []
    for it in items:
        if type(it) is DeviceEvent and it.kind in (EventKind.CLOCK_RESET, EventKind.PROTOCOL_ERRORS):
            events.append((it.kind.value, it.t_host_ns, it.detail))
            continue
        rows = [it] if type(it) is Sample else list(it.samples()) if type(it) is SampleBatch else []
        for s in rows:
            res.setdefault(s.stream, []).append((s.seq, s.t_host_ns, s.t_device_ns, s.t_bus_ns,
                                                 np.array(s.values).tobytes()))
    return res, sorted(events)


def counters(d: Device) -> dict:
    h = d.health()
    return {k: h[k] for k in ("chunks", "bytes", "readings", "missing_time", "lost_readings", "clock_resets")} | {
        "codec": d.codec.stats.as_dict()}


@pytest.mark.parametrize("block", range(BLOCKS))
@pytest.mark.parametrize(("kind", "name"), CASES)
def test_batch_path_equals_per_chunk_path_over_random_chunkings(kind, name, block):
    batched_runs = 0
    for seed in range(block * SEEDS_PER_TEST, (block + 1) * SEEDS_PER_TEST):
        rng = np.random.default_rng([CASES.index((kind, name)), seed])
        opts, t_s, pieces = readings(kind, name, rng)
        chunks = chunks_of(pieces, t_s, rng)
        cls = device_class(kind)
        da, db = cls("x", open_transport("loop://"), opts), cls("x", open_transport("loop://"), opts)
        ref = [x for c in chunks for x in da.process_chunk(c)] + da.finish()
        got: list = []
        i = 0
        while i < len(chunks):
            n = int(rng.choice([1, 2, int(rng.integers(1, 50)), int(rng.integers(1, len(chunks) + 1))]))
            got += db.process_chunks(ChunkRun.from_chunks(chunks[i:i + n]))
            i += n
        got += db.finish()
        batched_runs += any(type(x) is SampleBatch for x in got)
        (ref_s, ref_e), (got_s, got_e) = flatten(ref), flatten(got)
        where = f"{kind} on {name}, seed {seed}"
        assert ref_s.keys() == got_s.keys(), where
        for s in ref_s:
            assert got_s[s] == ref_s[s], f"{where}: {s}"
        assert got_e == ref_e, where
        assert counters(db) == counters(da), where
    assert batched_runs >= SEEDS_PER_TEST // 3  # the vectorised path was really taken, not only the fallback
