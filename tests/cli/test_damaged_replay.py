"""``perfcap replay`` on damaged and crafted sessions: the surviving samples are compared on their
sequence numbers and the damage is listed (streams, how many samples, seq and time ranges), not
reported as thousands of positional mismatches; a crafted few-KB session cannot make ``replay
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
from session_damage_helpers import chunk_map, make_session

from capture.sample import Chunk
from capture.session import SessionReader, SessionWriter

if TYPE_CHECKING:
    from pathlib import Path


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    p = tmp_path_factory.mktemp("replay_damage") / "take.mcap"
    make_session(p, seconds=10)
    return p


@pytest.mark.xfail(strict=False, reason="open (issue 16): on some layouts of the take's chunks the verifier reports"
                   " fewer lost samples than the flip cost (a stream's head or tail leaves no hole), and after lost"
                   " raw data the replay's clock fit starts afresh so its bus times differ")
def test_replay_of_a_damaged_session_lists_the_damage_and_verifies_the_rest(session: Path, tmp_path: Path,
                                                                           capsys) -> None:
    data = bytearray(session.read_bytes())
    # a chunk of sample blocks only, in the first half of the take, flipped inside its records (past its
    # header; not in the message index after it). Known limits, left out here: samples lost at the very end
    # of a stream leave no hole to see, and after lost raw data the replay's clock fit starts afresh, so its
    # bus times differ from the recorded ones
    chunks = chunk_map(bytes(data))
    assert len(chunks) >= 5
    candidates = [ch for ch in chunks[1:len(chunks) // 2] if ch.samples and not ch.raw]
    if not candidates:
        pytest.skip("this take's flushes put no chunk of sample blocks alone in its first half")
    c = max(candidates, key=lambda ch: ch.samples)
    assert c.samples > 0 and c.end - c.start > 200
    data[c.start + 80] ^= 0x08
    p = tmp_path / "bad.mcap"
    p.write_bytes(bytes(data))
    code, out, err = run(capsys, "replay", str(p), "--fast", "-q", "--json")
    assert code == 0, err
    ver = json.loads(out)["verification"]
    assert ver["equal"] and ver["damaged"]
    streams = ver["streams"]
    assert all(v["mismatches"] == 0 for v in streams.values())
    # a hole inside a stream is "absent"; a lost head is replayed from the surviving raw data, "not recorded"
    lost = sum(v["absent"] + v["not_recorded"] for v in streams.values())
    pristine, damaged = SessionReader(str(session)), SessionReader(str(p))
    really_lost = sum(len(pristine.samples(s)) - len(damaged.samples(s)) for s in pristine.streams)
    assert lost == really_lost <= c.samples  # every sample the flip cost is reported, and no more
    if really_lost:
        assert any(v["absent_ranges"] or v["not_recorded_ranges"] for v in streams.values())
    code, out, err = run(capsys, "replay", str(p), "--fast", "-q")
    assert code == 0 and "DAMAGED session" in out, out
    assert not really_lost or "absent from the recording" in out or "their recorded block is lost" in out, out
    assert "MISMATCH" not in out


def test_replay_of_an_intact_session_that_differs_is_still_a_mismatch(session: Path, tmp_path: Path) -> None:
    from capture.app.replay import ReplayVerifier

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
    assert res["streams"][name]["not_recorded"] + res["streams"][name]["mismatches"] > 0


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
