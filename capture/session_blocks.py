"""The lossless blocks of a session as protobuf messages (channel encoding ``protobuf``): raw chunks
(``perfcap.RawBlock``) and decoded samples (``perfcap.SampleBlock``), columnar and delta-coded, so a
generic protobuf reader decodes them with the schema the session carries and perfcap decodes them to
numpy columns exactly (every int64 and every float64 bit comes back).

Sessions of format 1 stored the same columns in perfcap's own encodings (``perfcap.raw.v1``,
``perfcap.samples.v1``: the second half of this module, kept so they stay readable); ``SessionReader``
picks the decoder by the channel's encoding.
"""

from __future__ import annotations

import struct
from typing import Any, cast

import numpy as np
from google.protobuf.message import DecodeError

from capture.proto import Field, build
from capture.sample import NO_TIME, Chunk, ChunkRun, SampleBatch

PROTOBUF = "protobuf"

_DELTA = "delta-coded modulo 2^64: the first value, then each value minus the previous one"
_SCHEMAS = build("perfcap", "perfcap/blocks.proto", [
    ("RawBlock", [
        Field("arrival_ns", "sint64", True, doc=f"host-monotonic arrival time of each chunk, ns, {_DELTA}"),
        Field("direction", "bytes", doc="one byte per chunk: 0 received from the device, 1 sent to it"),
        Field("length", "uint32", True, doc="the byte count of each chunk"),
        Field("data", "bytes", doc="the chunks' bytes, concatenated in order"),
    ], "Transport chunks of one device, in arrival order, exactly as the transport delivered them."),
    ("Column", [
        Field("quantum", "double", doc="> 0: every value is step * quantum exactly (steps used); 0: values used"),
        Field("step", "sint64", True, doc=f"the values as integers of the quantum, {_DELTA}"),
        Field("value", "double", True, doc="the values"),
    ], "One value channel of a sample block."),
    ("SampleBlock", [
        Field("seq", "sint64", True, doc=f"sequence number of each sample, {_DELTA}"),
        Field("t_host_ns", "sint64", True, doc=f"host-monotonic arrival time, ns, {_DELTA}"),
        Field("t_device_ns", "sint64", True, doc=f"device time, ns (-2^63: none), {_DELTA}; empty: no device times"),
        Field("t_bus_ns", "sint64", True, doc=f"bus time (host-monotonic, from the clock fit), ns, {_DELTA}"),
        Field("column", "message", True, message="perfcap.Column", doc="the value channels, in the stream's order"),
    ], "Consecutive samples of one stream, as columns."),
])
RAW_BLOCK = _SCHEMAS["RawBlock"]
SAMPLE_BLOCK = _SCHEMAS["SampleBlock"]
_Raw = RAW_BLOCK.cls
_Samples = SAMPLE_BLOCK.cls
_Column = _SCHEMAS["Column"].cls


def _delta(a: np.ndarray) -> list[int]:
    if a.size == 0:
        return []
    d = np.empty(a.shape, np.int64)
    d[0] = a[0]
    np.subtract(a[1:], a[:-1], out=d[1:])     # wraps modulo 2^64 like the sum that undoes it
    return cast("list[int]", d.tolist())


def _undelta(values: Any, n: int, what: str) -> np.ndarray:
    d = np.fromiter(values, np.int64, -1)
    if d.shape[0] != n:
        raise ValueError(f"{what}: {d.shape[0]} values where the block has {n}")
    return np.cumsum(d, dtype=np.int64)


def encode_raw(chunks: list[Chunk]) -> bytes:
    n = len(chunks)
    m = _Raw(direction=bytes(int(c.direction) for c in chunks), data=b"".join(c.data for c in chunks))
    m.arrival_ns.extend(_delta(np.fromiter((c.t_ns for c in chunks), np.int64, n)))
    m.length.extend([len(c.data) for c in chunks])
    return m.SerializeToString()


def decode_raw_run(data: bytes) -> ChunkRun:
    """A ``perfcap.RawBlock`` as a ``ChunkRun``.

    Raises:
        ValueError: the block does not parse or its columns disagree.
    """
    try:
        m = _Raw.FromString(bytes(data))
    except DecodeError as exc:
        raise ValueError(f"raw block does not parse: {exc}") from exc
    n = len(m.length)
    lens = np.fromiter(m.length, np.int64, n)
    t = _undelta(m.arrival_ns, n, "raw block arrival times")
    dirs = np.frombuffer(m.direction, np.uint8).copy()
    if dirs.shape[0] != n:
        raise ValueError(f"raw block: {dirs.shape[0]} directions for {n} chunks")
    if n and int(dirs.max()) > 1:
        raise ValueError("raw block has an unknown direction")
    if int(lens.sum()) != len(m.data):
        raise ValueError(f"raw block length mismatch ({int(lens.sum())} != {len(m.data)})")
    return ChunkRun(bytes(m.data), lens, t, dirs)


def _columns(vals: np.ndarray, quantum: tuple[float, ...] | None) -> list[object]:
    """Per channel: integer steps where every value is an exact ``step * quantum`` (and no zero is
    negative, whose sign the integer would lose), else the float64 values."""
    n, c = vals.shape
    out = []
    for j in range(c):
        v = vals[:, j]
        q = float(quantum[j]) if quantum else 0.0
        if q > 0 and n:
            with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
                k = np.round(v / q)
                ok = bool(np.all(np.abs(k) < 2.0**53) and np.all(k * q == v)
                          and not np.any((v == 0) & np.signbit(v)))
            if ok:
                col = _Column(quantum=q)
                col.step.extend(_delta(k.astype(np.int64)))
                out.append(col)
                continue
        col = _Column()
        col.value.extend(v.tolist())
        out.append(col)
    return out


def encode_samples(b: SampleBatch, quantum: tuple[float, ...] | None = None) -> bytes:
    """A batch as a ``perfcap.SampleBlock`` (channels with an exact quantum stored as integer steps)."""
    n = len(b)
    vals = np.asarray(b.values, np.float64)
    if vals.ndim != 2:
        vals = vals.reshape(n, -1)
    m = _Samples(column=_columns(vals, quantum))
    m.seq.extend(_delta(b.seq))
    m.t_host_ns.extend(_delta(b.t_host_ns))
    if n and bool((b.t_device_ns != NO_TIME).any()):
        m.t_device_ns.extend(_delta(b.t_device_ns))
    m.t_bus_ns.extend(_delta(b.t_bus_ns))
    return m.SerializeToString()


def decode_samples(stream: str, data: bytes) -> SampleBatch:
    """A ``perfcap.SampleBlock`` as a batch of ``stream``.

    Raises:
        ValueError: the block does not parse or its columns disagree.
    """
    try:
        m = _Samples.FromString(bytes(data))
    except DecodeError as exc:
        raise ValueError(f"sample block of {stream} does not parse: {exc}") from exc
    n = len(m.seq)
    seq = _undelta(m.seq, n, f"sample block of {stream}: sequence numbers")
    th = _undelta(m.t_host_ns, n, f"sample block of {stream}: host times")
    tb = _undelta(m.t_bus_ns, n, f"sample block of {stream}: bus times")
    td = (_undelta(m.t_device_ns, n, f"sample block of {stream}: device times") if len(m.t_device_ns)
          else np.full(n, NO_TIME, np.int64))
    vals = np.empty((n, len(m.column)), np.float64)
    for j, col in enumerate(m.column):
        if col.quantum > 0:
            vals[:, j] = _undelta(col.step, n, f"sample block of {stream}: column {j}").astype(np.float64) * col.quantum
        else:
            v = np.fromiter(col.value, np.float64, -1)
            if v.shape[0] != n:
                raise ValueError(f"sample block of {stream}: column {j} has {v.shape[0]} values for {n} samples")
            vals[:, j] = v
    return SampleBatch(stream, seq, th, td, tb, vals)


# -- format 1: perfcap's own block encodings (sessions written before the protobuf blocks) ----------------
RAW_ENCODING = "perfcap.raw.v1"
SAMPLES_ENCODING = "perfcap.samples.v1"

RAW_SCHEMA_DOC = (
    "perfcap raw block v1, little-endian: u32 n; i64[n] arrival host-monotonic ns, delta-coded (first absolute);"
    " u8[n] direction (0 rx from device, 1 tx to device); u32[n] byte counts; then the chunks' bytes concatenated."
)
SAMPLES_SCHEMA_DOC = (
    "perfcap sample block v1, little-endian: u32 n; u16 channels; u8 flags (bit0 device times present,"
    " bit2 column-wise values); i64[n] seq, i64[n] host ns, [i64[n] device ns (INT64_MIN = none)], i64[n] bus ns,"
    " each delta-coded modulo 2^64 (first absolute); then per channel: u8 mode; mode 0: f64[n] as 8 byte planes"
    " (all first bytes, then all second bytes, ...); mode 1: f64 quantum, i32[n] integers delta-coded, value ="
    " integer * quantum exactly."
)

_hdr_raw = struct.Struct("<I")
_hdr_samples = struct.Struct("<IHB")


def _delta_v1(a: np.ndarray) -> bytes:
    if a.size == 0:
        return b""
    d = np.empty_like(a)
    d[0] = a[0]
    np.subtract(a[1:], a[:-1], out=d[1:])
    return d.astype("<i8", copy=False).tobytes()


def _undelta_v1(buf: bytes | memoryview, n: int) -> np.ndarray:
    d = np.frombuffer(buf, "<i8", n).astype(np.int64)
    return np.cumsum(d, dtype=np.int64)


def encode_raw_block(chunks: list[Chunk]) -> bytes:
    n = len(chunks)
    t = np.fromiter((c.t_ns for c in chunks), np.int64, n)
    dirs = np.fromiter((int(c.direction) for c in chunks), np.uint8, n)
    lens = np.fromiter((len(c.data) for c in chunks), np.uint32, n)
    return b"".join([_hdr_raw.pack(n), _delta_v1(t), dirs.tobytes(), lens.astype("<u4").tobytes(),
                     *[c.data for c in chunks]])


def decode_raw_block_run(data: bytes) -> ChunkRun:
    """A raw block as a ``ChunkRun`` (no per-chunk objects)."""
    data = bytes(data)
    mv = memoryview(data)
    if len(mv) < _hdr_raw.size:
        raise ValueError(f"raw block of {len(mv)} bytes, shorter than its header")
    (n,) = _hdr_raw.unpack_from(mv, 0)
    o = _hdr_raw.size
    if o + 13 * n > len(data):   # a count the block cannot hold: refused before anything is allocated
        raise ValueError(f"raw block claims {n} chunks in {len(data)} bytes")
    t = _undelta_v1(mv[o:o + 8 * n], n)
    o += 8 * n
    dirs = np.frombuffer(mv[o:o + n], np.uint8).copy()
    o += n
    lens = np.frombuffer(mv[o:o + 4 * n], "<u4").astype(np.int64)
    o += 4 * n
    if int(lens.sum()) != len(data) - o:
        raise ValueError(f"raw block length mismatch ({int(lens.sum())} != {len(data) - o})")
    if n and int(dirs.max()) > 1:
        raise ValueError("raw block has an unknown direction")
    return ChunkRun(data[o:], lens, t, dirs)


def concat_runs(runs: list[ChunkRun]) -> ChunkRun:
    if len(runs) == 1:
        return runs[0]
    return ChunkRun(b"".join(r.data for r in runs), np.concatenate([r.lengths for r in runs]),
                    np.concatenate([r.t_ns for r in runs]), np.concatenate([r.directions for r in runs]))


def decode_raw_block(data: bytes) -> list[Chunk]:
    """A raw block as a list of ``Chunk``s."""
    return list(decode_raw_block_run(data))




def raw_block_span(data: bytes) -> tuple[int, int]:
    """First and last chunk times of a raw block, without decoding the chunks."""
    (n,) = _hdr_raw.unpack_from(data, 0)
    if n == 0 or _hdr_raw.size + 13 * n > len(data):
        raise ValueError(f"raw block claims {n} chunks in {len(data)} bytes")
    t = _undelta_v1(memoryview(data)[_hdr_raw.size:_hdr_raw.size + 8 * n], n)
    return int(t[0]), int(t[-1])


_q = struct.Struct("<Bd")


def _value_columns(vals: np.ndarray, quantum: tuple[float, ...] | None) -> list[bytes]:
    """Per channel: mode 1 (exact integers of a quantum, delta-coded int32) where possible, else mode 0
    (float64 byte planes). Vectorised across channels: a handful of numpy calls per block."""
    n, c = vals.shape
    if c == 0:
        return []
    quant_ok = np.zeros(c, bool)
    q = np.asarray(quantum if quantum else (0.0,) * c, np.float64)
    if n and quantum and (q > 0).any():
        qs = np.where(q > 0, q, 1.0)
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            k = np.round(vals / qs)
            exact = np.all(k * qs == vals, axis=0) & (q > 0)
            if exact.any():
                kk = k[:, exact]
                fits = np.all(np.abs(kk) < 2**31, axis=0)
                ki = np.where(np.isfinite(kk), kk, 0).astype(np.int64)
                d = np.empty_like(ki)
                d[0] = ki[0]
                np.subtract(ki[1:], ki[:-1], out=d[1:])
                fits &= np.all(np.abs(d) < 2**31, axis=0)
                idx = np.flatnonzero(exact)
                quant_ok[idx[fits]] = True
                d32 = {int(j): d[:, m].astype("<i4") for m, j in enumerate(idx) if fits[m]}
    planes = None
    if not quant_ok.all():
        planes = np.ascontiguousarray(vals.T, dtype="<f8").view(np.uint8).reshape(c, n, 8).transpose(0, 2, 1)
    out = []
    for j in range(c):
        if quant_ok[j]:
            out.append(_q.pack(1, float(q[j])) + d32[j].tobytes())
        elif planes is not None:    # (not quantised: its float64 planes)
            out.append(b"\x00" + planes[j].tobytes())
    return out


def encode_sample_block(b: SampleBatch, quantum: tuple[float, ...] | None = None) -> bytes:
    """Encode a batch; channels with a quantum whose values are exact multiples of it are stored as integers."""
    n = len(b)
    vals = np.asarray(b.values, dtype=np.float64)
    if vals.ndim != 2:
        vals = vals.reshape(n, -1)
    c = vals.shape[1]
    has_dev = bool(n and (b.t_device_ns != NO_TIME).any())
    flags = (1 if has_dev else 0) | 4
    parts = [_hdr_samples.pack(n, c, flags), _delta_v1(b.seq), _delta_v1(b.t_host_ns)]
    if has_dev:
        parts.append(_delta_v1(b.t_device_ns))
    parts.append(_delta_v1(b.t_bus_ns))
    parts += _value_columns(vals, quantum)
    return b"".join(parts)


def decode_sample_block(stream: str, data: bytes) -> SampleBatch:
    mv = memoryview(data)
    if len(mv) < _hdr_samples.size:
        raise ValueError(f"sample block of {stream}: {len(mv)} bytes, shorter than its header")
    n, c, flags = _hdr_samples.unpack_from(mv, 0)
    if not flags & 4:
        raise ValueError(f"sample block of {stream}: unknown value layout (flags {flags})")
    o = _hdr_samples.size
    k = 4 if flags & 1 else 3
    # counts the block cannot hold are refused before anything is allocated (each channel takes at
    # least 1 + 4n bytes)
    if o + 8 * n * k + c * (1 + 4 * n) > len(data):
        raise ValueError(f"sample block of {stream} claims {n} samples of {c} channels in {len(data)} bytes")
    times = np.cumsum(np.frombuffer(mv[o:o + 8 * n * k], "<i8").reshape(k, n), axis=1, dtype=np.int64)
    o += 8 * n * k
    seq, th = times[0], times[1]
    if flags & 1:
        td, tb = times[2], times[3]
    else:
        td, tb = np.full(n, NO_TIME, np.int64), times[2]
    vals = np.empty((n, c), np.float64)
    stride_q = _q.size + 4 * n
    j = 0
    while j < c:
        if o >= len(mv):
            raise ValueError(f"sample block of {stream} ends after {j} of its {c} columns")
        mode = mv[o]
        if mode == 1:
            # a run of integer columns: decode them together
            m = 1
            while j + m < c and o + m * stride_q < len(data) and mv[o + m * stride_q] == 1:
                m += 1
            block = np.frombuffer(mv[o:o + m * stride_q], np.uint8).reshape(m, stride_q)
            quanta = block[:, 1:_q.size].copy().view("<f8").reshape(m)
            ints = block[:, _q.size:].copy().view("<i4").reshape(m, n)
            vals[:, j:j + m] = (np.cumsum(ints, axis=1, dtype=np.int64).astype(np.float64) * quanta[:, None]).T
            o += m * stride_q
            j += m
        elif mode == 0:
            raw = np.frombuffer(mv[o + 1:o + 1 + 8 * n], np.uint8)
            vals[:, j] = raw.reshape(8, n).T.copy().view("<f8").reshape(n)
            o += 1 + 8 * n
            j += 1
        else:
            raise ValueError(f"sample block of {stream}: unknown column mode {mode}")
    if o != len(data):
        raise ValueError(f"sample block length mismatch for {stream}")
    return SampleBatch(stream, seq, th, td, tb, vals)
