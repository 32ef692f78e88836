"""A recording killed with SIGKILL mid-take stays readable up to its last flush, and the readable
part replays exactly; the recorder keeps the file at most ``--max-loss`` seconds behind the take.

The kill is a real one, of a real ``perfcap record``; how far behind the file is kept is checked on
the recorder's own clock (a ``ManualClock``), so no wall-clock window decides it on a busy machine.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
from wait_helpers import DEADLINE_S

from capture.app.replay import replay_session
from capture.clock import ManualClock
from capture.errors import SessionError
from capture.recorder import SessionRecorder
from capture.session import SessionReader, SessionWriter
from devices import open_device


@pytest.mark.parametrize("max_loss", [1.0, 0.3])
def test_sigkill_leaves_a_readable_session_that_replays_exactly(tmp_path, max_loss):
    out = str(tmp_path / "killed.mcap")
    proc = subprocess.Popen(
        [sys.executable, "-m", "capture.app.cli", "record", "-q", "-d", "a=synth://imu?rate=200&jitter_ms=1",
         "-d", "b=synth://imu?rate=100&device_clock=false&seed=2", "--duration", "600", "--max-loss", str(max_loss),
         "-o", out],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        # a few seconds of both devices on disk (about 75 kB a second with the viewable channels), however long
        # that takes
        deadline = time.monotonic() + DEADLINE_S
        while time.monotonic() < deadline and (not os.path.exists(out) or os.path.getsize(out) < 200_000):
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        proc.wait(DEADLINE_S)
    finally:
        if proc.poll() is None:
            proc.kill()
        assert proc.stderr is not None
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    r = SessionReader(out)
    assert r.truncated is not None and r.summary is None
    for stream in ("a/imu", "b/imu"):
        assert len(r.samples(stream)) > 100, stream
    rep = replay_session(out, speed=0)
    assert rep.verification["equal"], rep.verification["first_mismatch"]


@pytest.mark.parametrize("max_loss", [1.0, 0.3])
def test_the_file_on_disk_is_never_more_than_max_loss_behind(tmp_path, max_loss):
    """What a SIGKILL would leave at any moment (the file as the OS has it): every sample older than
    ``max_loss`` on the recorder's clock. A simulated device paced on the same manual clock feeds it."""
    clock = ManualClock()
    t_start = clock.now_ns()
    dev = open_device("a=synth://imu?rate=200&jitter_ms=1", clock=clock)
    writer = SessionWriter(str(tmp_path / "live.mcap"), fsync=False)
    rec = SessionRecorder(writer, max_loss_s=max_loss, clock=clock)
    rec.add_device(dev.name, dev.kind, dev.transport.url, dev.device_options, dev.identity, dev.streams)
    snapshot = str(tmp_path / "as-killed.mcap")
    checked = 0
    try:
        for item in dev.open():
            rec.on_item(item)
        polls = 0
        while clock.now_ns() - t_start < 5e9:  # 5 s of the take, one reading (5 ms) a poll
            for item in dev.poll(0.1):
                rec.on_item(item)
            polls += 1
            if polls % 7:
                continue
            shutil.copyfile(writer.path, snapshot)
            try:
                imu = SessionReader(snapshot).samples("a/imu")
                newest = int(imu.t_host_ns[-1]) if len(imu) else t_start
            except SessionError:  # nothing flushed yet
                newest = t_start
            assert clock.now_ns() - newest <= max_loss * 1e9, (polls, (clock.now_ns() - newest) / 1e9)
            checked += 1
    finally:
        rec.stop()
        dev.close()
    assert checked >= 100
