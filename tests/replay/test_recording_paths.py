"""Where sessions are created: a path given to ``perfcap serve`` cannot lead outside its sessions
directory (not even through a directory swapped for a link between a check and the open), new
files are created exclusively, ``overwrite`` replaces only perfcap sessions, and a take killed
while starting leaves nothing that blocks the next one.
"""

from __future__ import annotations

import os
import random
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from recording_path_helpers import kill_during_startup, swap_race

from capture.errors import ConfigError, SessionError, SessionExistsError
from capture.session import SessionReader, SessionWriter
from capture.session_file import is_session_header


def _take(path: str, base_dir: str | None = None, overwrite: bool = False) -> str:
    w = SessionWriter(path, base_dir=base_dir, overwrite=overwrite, fsync=False)
    w.close({})
    return w.path


def test_a_directory_swapped_for_a_link_never_leads_outside(tmp_path):
    base, outside = tmp_path / "sessions", tmp_path / "outside"
    base.mkdir()
    outside.mkdir()
    res = swap_race(base, outside, 300, seed=16, create=_take)
    assert res["escapes"] == 0, res
    assert res["created"] > 0 and res["refused"] > 0 and res["swaps"] > 0, res  # the race was on
    inside = list(base.rglob("*.mcap"))
    assert len(inside) == res["created"]
    assert not list(base.rglob(".*.part"))


_PARTS = ["..", ".", "", "sub", "link", "a.mcap", ".h.mcap", "file.mcap", "x.txt", "a\0b.mcap", "nodir", "/"]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.sampled_from(_PARTS), min_size=0, max_size=4), st.booleans(), st.booleans())
def test_any_path_is_created_inside_the_sessions_directory_or_refused(parts, absolute, overwrite):
    """The class: a path made of any of these pieces either names a new file inside the sessions
    directory or is refused with a clear error; nothing outside is created or changed."""
    root = Path(tempfile.mkdtemp())
    try:
        base, outside = root / "sessions", root / "outside"
        (base / "sub").mkdir(parents=True)
        outside.mkdir()
        (outside / "a.mcap").write_bytes(b"precious")
        (base / "link").symlink_to(outside)
        (base / "file.mcap").write_bytes(b"not a session")
        path = "/".join(parts)
        if absolute:
            path = str(base) + "/" + path
        before = {p: p.read_bytes() for p in (outside / "a.mcap", base / "file.mcap")}
        try:
            made = _take(path, str(base), overwrite)
        except (ConfigError, SessionExistsError) as exc:
            assert str(exc)
        else:
            real = os.path.realpath(made)
            assert real.startswith(str(base) + os.sep) and real.endswith(".mcap"), (path, made)
            assert "link" not in Path(made).relative_to(base).parts
            assert SessionReader(made).meta["format_version"]
        assert {p: p.read_bytes() for p in before} == before
        assert sorted(e.name for e in outside.iterdir()) == ["a.mcap"]
    finally:
        shutil.rmtree(root)


@pytest.mark.parametrize("path, says", [
    ("", "empty"), ("..", "'..'"), ("../x.mcap", "'..'"), ("sub/../../x.mcap", "'..'"), ("/etc/x.mcap", "outside"),
    ("a\0b.mcap", "NUL"), (".hidden.mcap", "'.'"), ("x.txt", ".mcap"), ("sub/", "directory"), (".", "directory"),
    ("nodir/x.mcap", "no directory nodir"), ("link/x.mcap", "symbolic link"), ("file/x.mcap", "not a directory"),
])
def test_bad_paths_are_refused_with_their_reason(tmp_path, path, says):
    base = tmp_path / "s"
    base.mkdir()
    (base / "link").symlink_to(tmp_path)
    (base / "file").write_bytes(b"")
    with pytest.raises(ConfigError) as ei:
        _take(path, str(base))
    assert says in str(ei.value)
    assert sorted(e.name for e in tmp_path.iterdir()) == ["s"]


def test_overwrite_replaces_only_perfcap_sessions(tmp_path):
    sess = _take(str(tmp_path / "take.mcap"))
    with pytest.raises(SessionExistsError, match=r"already exists \(use --overwrite to replace it; it is a perfcap"):
        _take(sess)
    _take(sess, overwrite=True)
    assert SessionReader(sess).summary == {}

    other = tmp_path / "notes.mcap"
    other.write_bytes(b"my notes")
    for ow in (False, True):
        with pytest.raises(SessionExistsError, match="not a perfcap session"):
            _take(str(other), overwrite=ow)
    assert other.read_bytes() == b"my notes"

    target = tmp_path / "target"
    target.write_bytes(b"keep")
    (tmp_path / "l.mcap").symlink_to(target)
    with pytest.raises(SessionExistsError, match="symbolic link"):
        _take(str(tmp_path / "l.mcap"), overwrite=True)
    assert target.read_bytes() == b"keep"

    with pytest.raises(SessionExistsError, match="a directory"):
        _take(str(tmp_path), overwrite=True)

    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(SessionExistsError, match="an empty file"):
        _take(str(empty))
    _take(str(empty), overwrite=True)
    assert is_session_header(empty.read_bytes())

    cut = tmp_path / "cut.mcap"
    w = SessionWriter(str(cut), fsync=False)
    w.flush()
    w.abort()  # as a take that failed or was killed
    with pytest.raises(SessionExistsError, match="cut short"):
        _take(str(cut))
    _take(str(cut), overwrite=True)
    assert not list(tmp_path.glob(".*.part"))


def test_temporary_files_of_dead_writers_are_removed_and_live_ones_kept(tmp_path):
    stale = tmp_path / ".take.mcap.0123abcd.part"
    stale.write_bytes(b"\x89MCAP0\r\n")  # a writer killed before it put its file in place
    live = SessionWriter(str(tmp_path / "take.mcap"), fsync=False)  # removes the stale one
    assert not stale.exists()
    # a writer that has not put its file in place yet holds its temporary file's lock
    import fcntl

    held = tmp_path / ".other.mcap.feedf00d.part"
    fd = os.open(held, os.O_CREAT | os.O_WRONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        _take(str(tmp_path / "other.mcap"))
        assert held.exists()
    finally:
        os.close(fd)
    live.close({})


def test_a_record_killed_while_starting_never_blocks_the_next_take(tmp_path):
    """Real ``perfcap record`` processes SIGKILLed at seeded moments of their start-up (at once, while
    importing, the moment the temporary file exists, once the file is in place): what is left is
    nothing, a hidden temporary file, or a readable session, never an empty file; the next take to
    the same path succeeds, or says the file is an earlier take cut short (then --overwrite)."""
    rng = random.Random(16)
    seen: dict[str, int] = {}
    for i, delay in enumerate([0.0, None, rng.uniform(0.1, 1.0), None, rng.uniform(0.5, 2.5)]):
        out = tmp_path / f"take{i}.mcap"
        left = kill_during_startup(out, delay)
        seen[left] = seen.get(left, 0) + 1
        if left == "file":
            assert out.stat().st_size > 0 and is_session_header(out.read_bytes()[:512])
            SessionReader(str(out))  # readable
        try:
            _take(str(out))
        except SessionExistsError as exc:
            assert left == "file" and "cut short" in str(exc), (left, exc)
            _take(str(out), overwrite=True)
        except SessionError as exc:
            raise AssertionError(f"second take after a kill ({left}): {exc}") from exc
        assert SessionReader(str(out)).summary == {}
        assert not list(tmp_path.glob(".*.part")), (left, list(tmp_path.iterdir()))
    assert "part" in seen or "nothing" in seen, seen
