"""The lossless blocks of a session as protobuf messages (channel encoding ``protobuf``): raw chunks
(``perfcap.RawBlock``) and decoded samples (``perfcap.SampleBlock``), columnar and delta-coded, so a
generic protobuf reader decodes them with the schema the session carries and perfcap decodes them to
numpy columns exactly (every int64 and every float64 bit comes back).

Sessions of format 1 stored the same columns in perfcap's own encodings (``perfcap.raw.v1``,
``perfcap.samples.v1``, in ``capture.session``); readers decode both (``decode_raw``, ``decode_samples``
dispatch on the channel encoding).
"""

from __future__ import annotations

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
    vals = np.asarray(b.values, np.float64).reshape(n, -1)
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
    seq = _undelta(m.seq, n, f"sample block of {stream}: host times")
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
