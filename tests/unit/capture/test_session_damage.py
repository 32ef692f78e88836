"""One damaged byte must not lose a session: the reader recovers channel definitions from wherever
they survive (other chunks, the summary, the writer's repeated copies), skips a damaged chunk and
counts it; and a crafted session cannot make the reader allocate or decode more than the file holds.

The sweep here is bounded for CI; ``benchmarks/session_damage.py`` runs the full campaign.
"""

from __future__ import annotations

import random
import struct
import tracemalloc
from typing import TYPE_CHECKING

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from session_damage_helpers import chunk_map, make_session, sweep, total_samples

from capture.errors import SessionError
from capture.session import SessionReader, SessionWriter
from capture.session_blocks import decode_raw_block_run, decode_sample_block
from capture.session_scan import DEFINITIONS

if TYPE_CHECKING:
    from pathlib import Path


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    p = tmp_path_factory.mktemp("damage") / "take.mcap"
    make_session(p, seconds=10)
    return p


def _first_chunk_damaged(data: bytes) -> bytearray:
    chunks = chunk_map(data)
    assert len(chunks) >= 4, "the session should hold several chunks"
    bad = bytearray(data)
    bad[(chunks[0].start + chunks[0].end) // 2] ^= 0x40
    return bad


def test_a_damaged_first_chunk_costs_only_its_own_samples(session: Path, tmp_path: Path) -> None:
    data = session.read_bytes()
    ref = total_samples(SessionReader(str(session)))
    first = chunk_map(data)[0]
    p = tmp_path / "bad.mcap"
    p.write_bytes(bytes(_first_chunk_damaged(data)))
    r = SessionReader(str(p))
    got = total_samples(r)
    assert set(got) == set(ref)
    lost = sum(len(v) for v in ref.values()) - sum(len(v) for v in got.values())
    # how the take's flushes fell decides whether its first chunk holds samples too (a busy machine: not)
    assert lost <= first.samples and (lost > 0) == (first.samples > 0)
    assert r.damaged and r.damaged_regions   # reported, not silent
    assert r.devices.keys() == SessionReader(str(session)).devices.keys()


def test_without_a_summary_the_repeated_definitions_recover_the_channels(session: Path, tmp_path: Path) -> None:
    data = session.read_bytes()
    chunks = chunk_map(data)
    cut = _first_chunk_damaged(data)[:chunks[-1].end]   # a recorder killed before the summary
    p = tmp_path / "cut.mcap"
    p.write_bytes(bytes(cut))
    r = SessionReader(str(p))
    assert r.truncated
    got = total_samples(r)
    assert sum(len(v) for v in got.values()) >= sum(c.samples for c in chunks[1:])
    assert DEFINITIONS.encode() in cut


class _OldWriter(SessionWriter):
    """A writer as perfcap wrote before it repeated its definitions."""

    def _repeat_definitions(self) -> None:
        return None


def test_old_sessions_without_repeated_definitions_still_read(tmp_path: Path) -> None:
    p = tmp_path / "old.mcap"
    make_session(p, seconds=6, writer=_OldWriter)
    data = p.read_bytes()
    assert DEFINITIONS.encode() not in data
    ref = total_samples(SessionReader(str(p)))
    bad = tmp_path / "old_bad.mcap"
    bad.write_bytes(bytes(_first_chunk_damaged(data)))
    got = total_samples(SessionReader(str(bad)))   # the summary's channel table
    assert sum(len(v) for v in got.values()) >= sum(c.samples for c in chunk_map(data)[1:])
    assert all(got[s] <= ref[s] for s in got)


def test_a_damaged_device_record_is_recovered_from_its_copy(session: Path, tmp_path: Path) -> None:
    data = bytearray(session.read_bytes())
    i = data.index(b"device:a")
    j = data.index(b'"url"', i) if b'"url"' in data[i:i + 400] else data.index(b"synth://", i)
    data[j + 2] ^= 0x01     # a byte of the device's metadata (no CRC in MCAP): parses, but differs
    p = tmp_path / "dev.mcap"
    p.write_bytes(bytes(data))
    r = SessionReader(str(p))
    good = SessionReader(str(session))
    assert r.devices["a"].url == good.devices["a"].url
    assert r.devices["a"].options == good.devices["a"].options


def test_bounded_damage_sweep(session: Path, tmp_path: Path) -> None:
    res = sweep(session, tmp_path, flips=120, blocks=20, seed=1616)
    assert res.tried >= 135
    assert res.failures == []
    assert res.lost_sessions == res.over_budget == res.silent_losses == 0


# -- crafted sessions: counts and lengths bounded by what the file holds -------------------------------
@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 2**16 - 1), st.sampled_from([4, 5]), st.binary(max_size=300))
def test_a_sample_block_count_it_cannot_hold_is_refused_before_allocating(n, c, flags, tail) -> None:
    data = struct.pack("<IHB", n, c, flags) + tail
    try:
        b = decode_sample_block("x", data)
    except (ValueError, IndexError, struct.error):
        return
    assert b.values.nbytes <= 8 * len(data) and len(b) <= len(data)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.binary(max_size=300))
def test_a_raw_block_count_it_cannot_hold_is_refused(n, tail) -> None:
    data = struct.pack("<I", n) + tail
    try:
        run = decode_raw_block_run(data)
    except (ValueError, IndexError, struct.error):
        return
    assert len(run.lengths) <= len(data)


def _record_starts(data: bytes) -> list[int]:
    pos, out = 8, []
    while pos + 9 <= len(data):
        op, length = struct.unpack_from("<BQ", data, pos)
        out.append(pos)
        if op == 0x02:
            break
        pos += 9 + length
    return out


def test_crafted_lengths_and_sizes_read_within_the_files_bounds(session: Path, tmp_path: Path) -> None:
    """Every record's length, and every chunk's claimed uncompressed size, set to hostile values:
    the reader refuses them (counted) and its peak memory stays within a bound set by the file."""
    data = session.read_bytes()
    rng = random.Random(5)
    huge = [2**63, 2**40, 2**32 - 1, len(data) * 2, len(data) - 1]
    starts = _record_starts(data)
    p = tmp_path / "crafted.mcap"
    bound = 200 * 2**20 + 40 * len(data)
    cases = 0
    for pos in rng.sample(starts, min(30, len(starts))):
        for field_off, width in ((1, 8), (9 + 16, 8)):     # record length; a chunk's uncompressed size
            if field_off == 25 and data[pos] != 0x06:
                continue
            bad = bytearray(data)
            bad[pos + field_off:pos + field_off + width] = struct.pack("<Q", rng.choice(huge))
            p.write_bytes(bytes(bad))
            tracemalloc.start()
            try:
                r = SessionReader(str(p))
                r.all_samples()
                for d in r.devices:
                    r.raw_run(d)
            except SessionError:
                pass
            finally:
                _, peak = tracemalloc.get_traced_memory()
                tracemalloc.stop()
            assert peak < bound, (pos, field_off, peak)
            cases += 1
    assert cases >= 30


def test_a_zstd_bomb_chunk_is_refused(session: Path, tmp_path: Path) -> None:
    """A chunk of 5 KB that claims (and would inflate to) 1 GiB is refused and counted."""
    import zstandard
    from mcap.data_stream import RecordBuilder
    from mcap.records import Chunk

    comp = zstandard.ZstdCompressor(level=19).compress(bytes(64 << 20))
    rb = RecordBuilder()
    Chunk(compression="zstd", data=comp, message_start_time=0, message_end_time=0,
          uncompressed_crc=0, uncompressed_size=64 << 20).write(rb)
    bomb = rb.end()
    data = session.read_bytes()
    at = chunk_map(data)[0].start
    p = tmp_path / "bomb.mcap"
    p.write_bytes(data[:at] + bomb * 20 + data[at:])
    assert len(bomb) < 8192
    tracemalloc.start()
    try:
        r = SessionReader(str(p))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 200 * 2**20
    assert r.damaged.get("MCAP chunk", 0) >= 1
    assert sum(len(v) for v in total_samples(r).values()) == sum(
        len(v) for v in total_samples(SessionReader(str(session))).values())


@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(
    st.binary(min_size=1, max_size=64),
    st.tuples(st.sampled_from([1, 2, 3, 4, 6, 7, 8, 9, 12, 15]), st.integers(0, 2**64 - 1)).map(
        lambda t: struct.pack("<BQ", *t)),
    st.tuples(st.sampled_from([1, 4, 6, 7, 9, 12]), st.integers(0, 300)).map(lambda t: struct.pack("<BQ", *t))),
    max_size=40))
def test_the_record_walk_survives_any_bytes(parts) -> None:
    """Record headers with any opcode and length among arbitrary bytes: the walk ends, every
    record it yields parsed, and whatever it skipped is reported."""
    from capture.session_file import MCAP_MAGIC
    from capture.session_scan import RecordScanner

    data = MCAP_MAGIC + b"".join(parts)
    damage: list[str] = []
    sc = RecordScanner(data, lambda what, why: damage.append(what))
    recs = list(sc.records())
    assert len(recs) <= len(data) // 9
    assert sc.result.skipped_bytes <= len(data)
    assert (sc.result.truncated is not None) or sc.result.footer or damage or sc.result.data_end
