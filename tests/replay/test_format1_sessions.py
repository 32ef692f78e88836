"""Sessions written before format 2 (``tests/data/format1_session.mcap``: blocks in perfcap's own v1 encodings,
JSON without schemas, no viewable channels) still read, replay bit for bit and export."""

from __future__ import annotations

from pathlib import Path

from capture.app.replay import replay_session
from capture.session import SessionReader
from capture.session_blocks import SAMPLES_ENCODING

FORMAT1 = Path(__file__).resolve().parents[1] / "data" / "format1_session.mcap"


def test_a_format_1_session_reads_and_replays_exactly() -> None:
    r = SessionReader(str(FORMAT1))
    assert r.meta["format_version"] == "1" and not r.damaged
    assert all(r.encoding(f"/samples/{s}") == SAMPLES_ENCODING for s in r.streams if len(r.samples(s)))
    counts = {s: len(b) for s, b in r.all_samples().items()}
    assert counts["w/imu"] == 100 and counts["pad/imu"] > 200
    ver = replay_session(str(FORMAT1), speed=0).verification
    assert ver is not None and ver["equal"], ver["first_mismatch"]
    assert sum(v["compared"] for v in ver["streams"].values()) == sum(counts.values())


def test_a_format_1_session_exports(tmp_path: Path, capsys) -> None:
    from capture.app.cli import main

    assert main(["export", str(FORMAT1), "--format", "csv", "-o", str(tmp_path / "out")]) == 0
    files = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert any("imu" in f for f in files)
