"""``perfcap replay`` on damaged and crafted sessions: the surviving samples are compared reading by
reading and the damage is listed (streams, how many samples, seq and time ranges), not reported as
thousands of positional mismatches; a crafted few-KB session cannot make ``replay
--fast``, ``info`` or ``export`` grow without bound or run for minutes (checked in a child process
under an address-space limit, with a generous deadline)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from typing import TYPE_CHECKING

import pytest
from cli_helpers import run
from session_damage_helpers import VARIED, chunk_map, make_session, replay_sweep

from capture.sample import Chunk
from capture.session import SessionReader, SessionWriter

if TYPE_CHECKING:
    from pathlib import Path


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    p = tmp_path_factory.mktemp("replay_damage") / "take.mcap"
    make_session(p, seconds=10)
    return p


def test_replay_of_each_damaged_chunk_lists_the_damage_and_verifies_the_rest(session: Path, tmp_path: Path,
                                                                           capsys) -> None:
    """Every chunk of the take damaged in turn (a bit flipped inside its records): the surviving
    readings are compared and equal, the readings lost are counted exactly (against the take's
    summary), and ``perfcap replay`` says so without a mismatch."""
    from capture.app.replay import replay_session

    data = session.read_bytes()
    pristine = {s: len(b) for s, b in SessionReader(str(session)).all_samples().items()}
    worst: tuple[int, Path] | None = None
    chunks = [c for c in chunk_map(data) if c.end - c.start > 200]
    assert len(chunks) >= 5
    for i, c in enumerate(chunks):
        bad = bytearray(data)
        bad[c.start + 80] ^= 0x08
        p = tmp_path / f"bad{i}.mcap"
        p.write_bytes(bytes(bad))
        got = {s: len(b) for s, b in SessionReader(str(p)).all_samples().items()}
        ver = replay_session(str(p), speed=0).verification
        assert ver is not None and ver["equal"] and ver["damaged"], (c, ver["first_mismatch"])
        for s, v in ver["streams"].items():
            assert v["mismatches"] == 0
            assert v["lost_exact"] and v["lost"] == pristine[s] - got[s], (c, s, v)
            assert v["compared"] + v["missing"] == v["recorded"] and v["not_recorded"] <= v["lost"], (c, s, v)
        lost = sum(v["lost"] for v in ver["streams"].values())
        assert lost <= c.samples
        if lost and (worst is None or lost > worst[0]):
            worst = (lost, p)
    assert worst is not None, "no chunk of sample blocks in the take"
    code, out, err = run(capsys, "replay", str(worst[1]), "--fast", "-q", "--json")
    assert code == 0, err
    ver = json.loads(out)["verification"]
    assert ver["equal"] and sum(v["lost"] for v in ver["streams"].values()) == worst[0]
    assert any(v["lost_ranges"] for v in ver["streams"].values())
    code, out, err = run(capsys, "replay", str(worst[1]), "--fast", "-q")
    assert code == 0 and "DAMAGED session" in out and "lost with the damage" in out, out
    assert "MISMATCH" not in out and "verified: all" in out, out


def test_replay_of_randomly_damaged_untidy_takes_reports_exactly_what_was_lost(tmp_path: Path) -> None:
    """A seeded sweep of flips and zeroed blocks over a take of untidy devices (drift, jitter, no
    device clock with line noise, a clock that wraps) in small chunks, so raw data is lost in the middle
    of a stream and the replay numbers and stamps afresh: every case equal, every loss counted."""
    import logging

    p = tmp_path / "untidy.mcap"
    make_session(p, seconds=6, chunk_bytes=4096, urls=VARIED)
    logging.disable(logging.WARNING)
    try:
        res = replay_sweep(p, tmp_path, flips=60, blocks=15, seed=1616)
    finally:
        logging.disable(logging.NOTSET)
    assert res.tried >= 70
    assert res.sessions_lost == res.not_equal == res.wrong_loss == res.inconsistent == 0, res.failures[:5]
    assert res.cases_with_loss > 0   # the sweep did damage readings


def test_replay_of_an_intact_session_that_differs_is_still_a_mismatch(session: Path, tmp_path: Path) -> None:
    from capture.app.replay_check import ReplayVerifier, describe_verification

    r = SessionReader(str(session))
    rec = r.all_samples()
    v = ReplayVerifier(rec)
    for b in rec.values():
        v.on_item(b)
    assert v.result()["equal"]
    name = next(s for s, b in rec.items() if len(b) > 10)
    b = rec[name]
    shifted = type(b)(name, b.seq + 1, b.t_host_ns + 1, b.t_device_ns, b.t_bus_ns, b.values)
    v = ReplayVerifier({name: b})
    v.on_item(shifted)
    res = v.result()
    assert not res["equal"]
    assert any("MISMATCH" in line for line in describe_verification(res))


CHILD = r"""
import resource, sys
resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))
from capture.app.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _crafted(session: Path, tmp_path: Path) -> list[Path]:
    """A few KB each: raw chunks whose times jump 2^61 ns ahead, and a chunk with a sample block
    and a raw block whose counts claim far more than they hold."""
    r = SessionReader(str(session))
    dev = next(iter(r.devices))
    chunks = list(r.raw_chunks(dev))[:8]
    out = []
    p = tmp_path / "far.mcap"
    w = SessionWriter(str(p), overwrite=True, fsync=False)
    w.add_device(r.devices[dev], [r.streams[s] for s in r.devices[dev].streams if s in r.streams])
    w.write_raw(dev, chunks[:4], 0)
    w.write_raw(dev, [Chunk(c.data, c.t_ns + (1 << 61), c.direction) for c in chunks[4:]], 0)
    w.close()
    out.append(p)
    p = tmp_path / "counts.mcap"
    w = SessionWriter(str(p), overwrite=True, fsync=False)
    w.add_device(r.devices[dev], [r.streams[s] for s in r.devices[dev].streams if s in r.streams])
    w.write_raw(dev, chunks[:4], 0)
    stream = next(s for s in r.devices[dev].streams if s in r.streams)
    cid = w._channels[f"/samples/{stream}"]
    import struct
    w._add(cid, 0, struct.pack("<IHB", 2**31, 2**16 - 1, 5) + bytes(64), 0)
    raw = w._channels[f"/raw/{dev}"]
    w._add(raw, 0, struct.pack("<I", 2**32 - 1) + bytes(64), 0)
    w.close()
    out.append(p)
    return out


def test_crafted_sessions_are_bounded_in_memory_and_time(session: Path, tmp_path: Path) -> None:
    for p in _crafted(session, tmp_path):
        assert os.path.getsize(p) < 16_384
        for argv in (["replay", str(p), "--fast", "-q"], ["info", str(p)],
                     ["export", str(p), "--format", "csv", "-o", str(tmp_path / f"e_{p.stem}")]):
            proc = subprocess.run([sys.executable, "-c", CHILD, *argv], capture_output=True, text=True,
                                  timeout=120, check=False)
            assert proc.returncode in (0, 1, 2), (argv, proc.returncode, proc.stderr[-2000:])
            assert "Traceback" not in proc.stderr and "MemoryError" not in proc.stderr, proc.stderr[-2000:]
