"""A write that fails (disk full, file size limit) ends the recording cleanly: the file is cut back to
its last flush and holds exactly what the recorder says it saved; ``perfcap record`` stops at once
(not at ``--duration``), says what is in the file and what is not, and exits 1; ``perfcap serve``
stops that recording, reports it, and keeps serving.

The failures are real: the kernel refuses writes past a file size limit (``RLIMIT_FSIZE``, SIGXFSZ
ignored: ``EFBIG``), in a child process, at seeded random byte offsets.
"""

from __future__ import annotations

import json
import queue
import re
import signal
import subprocess
import threading
import time
import urllib.error
import urllib.request
from typing import TYPE_CHECKING, Any

from wait_helpers import DEADLINE_S
from write_failure_helpers import ROOT, limited_perfcap, run_trials

from capture.session import SessionReader

if TYPE_CHECKING:
    from pathlib import Path


def test_a_write_failure_at_any_offset_leaves_exactly_what_the_recorder_says(tmp_path):
    """The property, over 40 seeded limits (from inside the header to past the whole take): the
    recorder's saved count is what the file gives back, a failure is reported once, and a take
    that could not even write its header leaves no file and no temporary file."""
    trials = run_trials(16, 40, tmp_path, timeout=300)
    assert len(trials) == 40
    failed = [t for t in trials if t["created"] and t["failed"]]
    assert failed and [t for t in trials if t["created"] and not t["failed"]]  # both kinds were tried
    for t in trials:
        assert t["leftovers"] == [], t
        if not t["created"]:
            assert not t["exists"] and "cannot create" in t["error"], t
            continue
        assert t["exact"] and t["saved"] == t["read"], t
        assert set(t["declared"]) == {"ok"}, t  # declaring a device never raises, even into a failed file
        assert t["damaged"] == {}, t
        assert all(t["received"][s] >= n for s, n in t["saved"].items()), t
        if t["failed"]:
            assert t["on_failed"] == 1 and "File too large" in t["failed"], t
            assert not t["complete"] and t["size"] <= t["limit"], t
        else:
            assert t["on_failed"] == 0 and t["complete"] and t["saved"] == t["received"], t


def test_record_stops_at_a_write_failure_and_says_what_the_file_keeps(tmp_path):
    out = tmp_path / "full.mcap"
    p = subprocess.run(limited_perfcap(150_000, "record", "-q", "--json", "-d", "a=synth://imu?rate=1000",
                                       "--duration", "600", "--max-loss", "0.2", "-o", str(out)),
                       cwd=ROOT, capture_output=True, text=True, timeout=DEADLINE_S * 5, check=False)
    assert p.returncode == 1, p.stderr
    assert "Traceback" not in p.stderr and "recording failed" in p.stderr, p.stderr
    rep = json.loads(p.stdout)
    assert rep["duration_s"] < 600  # it stopped at the failure, not at --duration
    r = SessionReader(str(out))
    read = {s: len(r.samples(s)) for s in r.streams if len(r.samples(s))}
    assert rep["saved"] == read and rep["saved_exact"]
    for s, n in read.items():
        assert rep["streams"][s]["samples"] >= n
        assert rep["not_saved"].get(s, 0) <= rep["streams"][s]["samples"] - n
    kept = sum(read.values())
    assert f"keeps {kept} of " in p.stderr, p.stderr
    assert not [e for e in tmp_path.iterdir() if e.name.endswith(".part")]


def _lines(stream: Any, q: queue.Queue) -> None:
    for line in stream:
        q.put(line)
    q.put(None)


def _api(url: str, token: str, method: str, path: str, body: Any = None) -> tuple[int, Any]:
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url + path, data=data, method=method,
                                 headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=DEADLINE_S) as r:
            return r.status, json.loads(r.read() or b"null")
    except urllib.error.HTTPError as e:
        with e:
            return e.code, json.loads(e.read() or b"null")


def test_serve_stops_a_failed_recording_and_keeps_serving(tmp_path: Path):
    from capture.app.serve.security import TOKEN_FILE

    state, sessions = tmp_path / "state", tmp_path / "sessions"
    sessions.mkdir()
    cmd = limited_perfcap(100_000, "serve", "--port", "0", "--control-port", "0", "--no-mdns", "--no-tls",
                          "--host", "127.0.0.1", "--state-dir", str(state), "--sessions-dir", str(sessions),
                          "--status-every", "0", "-d", "a=synth://imu?rate=1000",
                          "--record", str(sessions / "first.mcap"))
    with subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        try:
            q: queue.Queue = queue.Queue()
            threading.Thread(target=_lines, args=(proc.stdout, q), daemon=True).start()
            text, end = "", time.monotonic() + DEADLINE_S
            while "Ctrl-C stops" not in text:
                line = q.get(timeout=max(0.1, end - time.monotonic()))
                assert line is not None, text
                text += line
            m = re.search(r"control API\s+(\S+)", text)
            assert m, text
            url, token = m.group(1), (state / TOKEN_FILE).read_text().strip()
            end = time.monotonic() + DEADLINE_S
            while True:  # the recording fails once the file reaches 100 kB
                health = _api(url, token, "GET", "/health")[1]
                if health["last_recording"] is not None or time.monotonic() > end:
                    break
                time.sleep(0.1)
            last = health["last_recording"]
            assert last is not None and "File too large" in last["error"], health
            assert health["status"] == "ok" and health["recording"] is None
            assert last["saved"] == sum(len(SessionReader(last["output"]).samples(s))
                                        for s in SessionReader(last["output"]).streams)
            assert last["output"] == str(sessions / "first.mcap")
            status, ans = _api(url, token, "POST", "/record/stop")
            assert status == 409 and "failed" in ans["error"], ans
            # still serving: another take starts
            status, ans = _api(url, token, "POST", "/record/start", {"path": "second.mcap"})
            assert (status, ans) == (200, {"recording": str(sessions / "second.mcap")}), ans
            proc.send_signal(signal.SIGTERM)
            rc = proc.wait(timeout=DEADLINE_S)
            err = proc.stderr.read() if proc.stderr else ""
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert "Traceback" not in err, err
    assert "failed (" in err and "still serving" in err, err
    assert rc in (0, 1), err
    assert SessionReader(str(sessions / "second.mcap")).meta["command"] == "perfcap serve"
