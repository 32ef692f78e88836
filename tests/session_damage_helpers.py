"""Damage sweeps over a real multi-chunk session, shared by the CI test
(``tests/unit/capture/test_session_damage.py``) and the full campaign
(``benchmarks/session_damage.py``).

``make_session`` records a session of several synthetic devices (several streams, several MCAP
chunks) through the real recorder; ``chunk_map`` lists its chunks and the samples each holds, read
with the ``mcap`` library from the pristine file; ``sweep`` damages copies of it (single-byte flips,
zeroed blocks, at seeded random offsets), reads each with ``SessionReader`` and compares what came
back with what the damaged chunks held.
"""

from __future__ import annotations

import functools
import io
import os
import random
import struct
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from capture.app.orchestrator import Capture
from capture.errors import SessionError
from capture.session import SessionReader, SessionWriter
from capture.session_blocks import SAMPLES_ENCODING, decode_samples

if TYPE_CHECKING:
    from pathlib import Path


#: devices whose clocks and framing are as untidy as real ones: drift and jitter, no device clock with
#: bursts and line noise, a device clock that starts a second before it wraps
VARIED = ("a=synth://imu?rate=200&drift_ppm=80&jitter_ms=2&{d}",
          "b=synth://imu?rate=100&device_clock=false&burst_ms=16&garbage=0.01&seed=2&{d}",
          "c=synth://imu?rate=50&start_ms=86399000&seed=3&{d}")


def make_session(path: Path | str, seconds: int = 10, max_loss_s: float = 0.1, chunk_bytes: int = 32 << 10,
                 writer: type[SessionWriter] = SessionWriter, urls: tuple[str, ...] | None = None) -> None:
    """A session of three synthetic devices (``urls``, with ``{d}`` for the duration options; default:
    tidy ones) in chunks of ``chunk_bytes`` (as many as a long take has, however fast this machine
    records), written by ``writer``."""
    import capture.app.orchestrator as orch

    d = f"realtime=false&duration={seconds}"
    urls = urls or ("a=synth://imu?rate=200&{d}", "b=synth://imu?rate=100&seed=2&{d}",
                    "c=synth://imu?rate=50&seed=3&{d}")
    names = vars(orch)
    saved = names["SessionWriter"]
    names["SessionWriter"] = functools.partial(writer, chunk_bytes=chunk_bytes)
    try:
        Capture([u.format(d=d) for u in urls],
                output=str(path), fsync=False, overwrite=True, max_loss_s=max_loss_s).run(None)
    finally:
        names["SessionWriter"] = saved


@dataclass
class ChunkInfo:
    start: int
    end: int          # end of the chunk and of its message indexes
    samples: int      # samples in its sample blocks
    raw: int = 0      # raw device chunks in it


def chunk_map(data: bytes) -> list[ChunkInfo]:
    """The chunks of a pristine session and the samples each holds."""
    from mcap.reader import make_reader
    from mcap.records import Message
    from mcap.stream_reader import breakup_chunk

    reader = make_reader(io.BytesIO(data))
    summary = reader.get_summary()
    assert summary is not None
    samples_ids = {c.id: c.message_encoding for c in summary.channels.values() if c.topic.startswith("/samples/")}
    raw_ids = {c.id for c in summary.channels.values() if c.topic.startswith("/raw/")}
    out = []
    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk
    for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        body = data[ci.chunk_start_offset + 9:ci.chunk_start_offset + ci.chunk_length]
        ch = Chunk.read(ReadDataStream(io.BytesIO(body)))
        records = [r for r in breakup_chunk(ch) if isinstance(r, Message)]
        n = sum(struct.unpack_from("<I", r.data)[0] if samples_ids[r.channel_id] == SAMPLES_ENCODING
                else len(decode_samples("x", r.data)) for r in records if r.channel_id in samples_ids)
        out.append(ChunkInfo(ci.chunk_start_offset, ci.chunk_start_offset + ci.chunk_length
                             + ci.message_index_length, n, sum(r.channel_id in raw_ids for r in records)))
    return out


def total_samples(reader: SessionReader) -> dict[str, set[int]]:
    return {s: set(reader.samples(s).seq.tolist()) for s in reader.streams}


@dataclass
class SweepResult:
    tried: int = 0
    lost_sessions: int = 0
    over_budget: int = 0          # cases that lost more than the damaged chunks held
    damaged_reported: int = 0     # cases where samples were lost and the reader said so
    silent_losses: int = 0        # cases that lost samples without reporting damage
    max_lost: int = 0
    max_lost_allowed: int = 0     # the damaged chunks' samples in the case that lost the most
    largest_chunk: int = 0
    failures: list[str] = field(default_factory=list)


def sweep(pristine: Path, work: Path, *, flips: int, blocks: int, block_bytes: int = 4096,
          seed: int = 16) -> SweepResult:
    """Damage copies of ``pristine`` and read each; see ``SweepResult``."""
    data = pristine.read_bytes()
    chunks = chunk_map(data)
    ref = total_samples(SessionReader(str(pristine)))
    n_ref = sum(len(v) for v in ref.values())
    res = SweepResult(largest_chunk=max(c.samples for c in chunks))
    rng = random.Random(seed)
    cases = [("flip", rng.randrange(len(data)), 1) for _ in range(flips)]
    cases += [("zero", rng.randrange(len(data) - block_bytes), block_bytes) for _ in range(blocks)]
    path = work / "damaged.mcap"
    for kind, at, width in cases:
        bad = bytearray(data)
        if kind == "flip":
            bad[at] ^= 1 << rng.randrange(8)
        else:
            bad[at:at + width] = bytes(width)
        if bad == data:
            continue
        res.tried += 1
        path.write_bytes(bytes(bad))
        os.utime(path, ns=(res.tried, res.tried))
        allowed = sum(c.samples for c in chunks if c.start < at + width and at < c.end)
        what = f"{kind} at byte {at} (+{width})"
        try:
            r = SessionReader(str(path))
            got = total_samples(r)
        except SessionError as exc:
            res.lost_sessions += 1
            res.failures.append(f"{what}: session lost: {exc}")
            continue
        extra = [s for s in got if s not in ref or not got[s] <= ref[s]]
        if extra:
            res.failures.append(f"{what}: samples that were never recorded in {extra}")
        lost = n_ref - sum(len(v) for v in got.values())
        if lost > res.max_lost:
            res.max_lost, res.max_lost_allowed = lost, allowed
        if lost > allowed:
            res.over_budget += 1
            res.failures.append(f"{what}: lost {lost} samples, the damaged chunks held {allowed}")
        if lost:
            if r.damaged:
                res.damaged_reported += 1
            else:
                res.silent_losses += 1
                res.failures.append(f"{what}: lost {lost} samples without reporting damage")
    return res


@dataclass
class ReplaySweepResult:
    """``replay --fast`` (``replay_session`` at speed 0) on damaged copies: per case, the verdict must be
    "equal" (no surviving reading differs) and the loss reported must be what the damage really cost."""

    tried: int = 0
    sessions_lost: int = 0        # the damaged copy could not be replayed at all
    not_equal: int = 0            # cases with a mismatch, an unexpected stream or a failed check
    wrong_loss: int = 0           # reported lost differs from pristine less damaged (summary intact)
    inexact: int = 0              # cases whose summary was lost (loss counted from holes: a lower bound)
    inconsistent: int = 0         # compared + missing != recorded, or more not-recorded than lost
    cases_with_loss: int = 0
    cases_renumbered: int = 0
    cases_restamped: int = 0
    restamped_max_ns: int = 0
    failures: list[str] = field(default_factory=list)


def replay_sweep(pristine: Path, work: Path, *, flips: int, blocks: int, block_bytes: int = 4096,
                 seed: int = 16) -> ReplaySweepResult:
    """Damage copies of ``pristine`` (single-bit flips, zeroed blocks, at seeded random offsets),
    replay each as fast as possible with verification and check the report against the truth read
    from the pristine and the damaged file; see ``ReplaySweepResult``."""
    from capture.app.replay import replay_session

    data = pristine.read_bytes()
    ref = {s: len(b) for s, b in SessionReader(str(pristine)).all_samples().items()}
    res = ReplaySweepResult()
    rng = random.Random(seed)
    cases = [("flip", rng.randrange(len(data)), 1) for _ in range(flips)]
    cases += [("zero", rng.randrange(len(data) - block_bytes), block_bytes) for _ in range(blocks)]
    path = work / "replay_damaged.mcap"
    for kind, at, width in cases:
        bad = bytearray(data)
        if kind == "flip":
            bad[at] ^= 1 << rng.randrange(8)
        else:
            bad[at:at + width] = bytes(width)
        if bad == data:
            continue
        res.tried += 1
        path.write_bytes(bytes(bad))
        os.utime(path, ns=(res.tried, res.tried))
        what = f"{kind} at byte {at} (+{width})"
        try:
            got = {s: len(b) for s, b in SessionReader(str(path)).all_samples().items()}
            ver = replay_session(str(path), speed=0).verification
        except SessionError as exc:
            res.sessions_lost += 1
            res.failures.append(f"{what}: not replayed: {exc}")
            continue
        assert ver is not None
        if not ver["equal"]:
            res.not_equal += 1
            res.failures.append(f"{what}: not equal: {ver['first_mismatch'] or ver['unexpected']} "
                                f"{ver.get('first_check_error') or ''}")
        streams = ver["streams"]
        exact = all(v["lost_exact"] for v in streams.values())
        res.inexact += not exact
        res.cases_with_loss += any(v["lost"] for v in streams.values())
        res.cases_renumbered += any(v["renumbered"] for v in streams.values())
        if any(v["restamped"] for v in streams.values()):
            res.cases_restamped += 1
            res.restamped_max_ns = max(res.restamped_max_ns, *(v["restamped_max_ns"] for v in streams.values()))
        for s, v in streams.items():
            really = ref.get(s, 0) - got.get(s, 0)
            if (v["lost"] != really) if v["lost_exact"] else (v["lost"] > really):
                res.wrong_loss += 1
                res.failures.append(f"{what}: {s} reported {v['lost']} lost, really {really}")
            if v["compared"] + v["missing"] != v["recorded"] or v["not_recorded"] > v["lost"]:
                res.inconsistent += 1
                res.failures.append(f"{what}: {s} inconsistent: {v}")
    return res
