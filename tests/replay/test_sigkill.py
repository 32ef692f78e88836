"""A recording killed with SIGKILL mid-take stays readable up to its last flush: at most
``--max-loss`` seconds are lost, and the readable part replays exactly."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from capture.app.replay import replay_session
from capture.session import SessionReader


@pytest.mark.parametrize("max_loss", [1.0, 0.3])
def test_sigkill_loses_at_most_max_loss(tmp_path, max_loss):
    out = str(tmp_path / "killed.mcap")
    proc = subprocess.Popen(
        [sys.executable, "-m", "capture.app.cli", "record", "-q", "-d", "a=synth://imu?rate=200&jitter_ms=1",
         "-d", "b=synth://imu?rate=100&device_clock=false&seed=2", "--duration", "60", "--max-loss", str(max_loss),
         "-o", out],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and (not os.path.exists(out) or os.path.getsize(out) < 20_000):
            time.sleep(0.05)
        time.sleep(1.5)
        t_kill = time.monotonic_ns()
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    r = SessionReader(out)
    assert r.truncated is not None and r.summary is None
    for stream in ("a/imu", "b/imu"):
        b = r.samples(stream)
        assert len(b) > 100
        lost_s = (t_kill - int(b.t_host_ns[-1])) / 1e9
        assert lost_s <= max_loss, f"{stream}: {lost_s:.3f} s lost"
    rep = replay_session(out, speed=0)
    assert rep.verification["equal"], rep.verification["first_mismatch"]
