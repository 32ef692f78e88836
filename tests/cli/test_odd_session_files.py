"""The commands on session files that are damaged, are not sessions at all, or have odd names: paths
with spaces and URL characters replay; flipped bytes are read around (info, export, replay), never a
traceback; text and empty files are said not to be MCAP; an export target that cannot be written is
one clear line."""

from __future__ import annotations

import random

import pytest
from cli_helpers import run

from capture.app.orchestrator import Capture
from capture.session import SessionReader

FAST = "realtime=false&duration=2"


@pytest.mark.parametrize("name", ["my takes/take 1.mcap", "x%41.mcap", "a#b.mcap", "q?.mcap"])
def test_replay_paths_with_spaces_and_url_characters(tmp_path, capsys, name):
    path = tmp_path / name
    path.parent.mkdir(parents=True, exist_ok=True)
    Capture([f"a=synth://imu?{FAST}"], output=str(path), fsync=False).run(None)
    code, out, err = run(capsys, "replay", str(path), "--fast", "-q")
    assert code == 0 and "equal the recorded ones" in out, err


def test_damaged_session_is_read_around_the_damage(tmp_path, capsys):
    good = tmp_path / "good.mcap"
    Capture([f"a=synth://imu?rate=200&{FAST}", f"b=synth://imu?rate=100&seed=2&{FAST}"],
            output=str(good), fsync=False).run(None)
    data = bytearray(good.read_bytes())
    n_ref = len(SessionReader(str(good)).samples("a/imu"))
    rng = random.Random(7)
    for k in range(12):
        bad = bytearray(data)
        for _ in range(3):
            i = rng.randrange(64, len(bad))
            bad[i] ^= 0xFF
        p = tmp_path / f"bad{k}.mcap"
        p.write_bytes(bytes(bad))
        for argv in (["info", str(p)], ["info", str(p), "--json"], ["replay", str(p), "--fast", "-q"],
                     ["export", str(p), "--format", "csv", "-o", str(tmp_path / f"e{k}")]):
            code, _out, err = run(capsys, *argv)
            assert code in (0, 1, 2), (argv, code, err)
            if code == 2:
                assert err.startswith("perfcap: error:"), err
        r = SessionReader(str(p))   # never lost: definitions survive in the summary and their copies
        assert "a/imu" in r.streams and len(r.samples("a/imu")) <= n_ref


def test_text_and_empty_files_are_not_mcap(tmp_path, capsys):
    for name, content in (("t.mcap", b"hello\n"), ("e.mcap", b"")):
        (tmp_path / name).write_bytes(content)
        code, _, err = run(capsys, "info", str(tmp_path / name))
        assert code == 2 and "not a session file (not MCAP)" in err


def test_export_events_file_that_is_a_directory(tmp_path, capsys):
    s = tmp_path / "s.mcap"
    Capture([f"a=synth://imu?{FAST}"], output=str(s), fsync=False).run(None)
    d = tmp_path / "exp"
    (d / "_events.csv").mkdir(parents=True)
    code, _, err = run(capsys, "export", str(s), "--format", "csv", "-o", str(d), "--overwrite")
    assert code == 2 and "cannot write" in err
