"""Attacks on where a session is created, shared by the tests and the campaign script.

``swap_race`` swaps a directory inside the sessions directory for a symbolic link to another
directory, in a separate process (true parallelism), as fast as it can with seeded pauses, while
this process creates sessions through it; it counts the sessions that landed outside.
``kill_during_startup`` kills a real ``perfcap record`` at a seeded moment of its start-up.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Callable

ROOT = Path(__file__).resolve().parents[2]

_SWAPPER = """
import os, random, sys
sub, hold, outside, stop, seed = sys.argv[1:6]
rng = random.Random(int(seed))
def spin():
    for _ in range(rng.randrange(0, 2000)):
        pass
swaps = 0
while not os.path.exists(stop):
    os.rename(sub, hold)
    os.symlink(outside, sub)
    spin()
    os.unlink(sub)
    os.rename(hold, sub)
    spin()
    swaps += 1
print(swaps)
"""


def swap_race(base: Path, outside: Path, attempts: int, seed: int,
              create: Callable[[str, str], object]) -> dict[str, int]:
    """``create(path, base_dir)`` ``attempts`` times with ``path`` = ``sub/take<i>.mcap`` while ``sub``
    is swapped for a link to ``outside``; returns the counts: created, refused, escapes (sessions
    found in ``outside``), swaps."""
    sub, hold, stop = base / "sub", base / "hold", base.parent / f"stop-{seed}"
    sub.mkdir()
    proc = subprocess.Popen([sys.executable, "-c", _SWAPPER, str(sub), str(hold), str(outside), str(stop), str(seed)],
                            stdout=subprocess.PIPE, text=True)
    created = refused = 0
    try:
        while not sub.is_symlink():  # the swapper runs
            time.sleep(0.001)
        streak, last = 0, None
        for i in range(attempts):
            try:
                create(f"sub/take{i}.mcap", str(base))
                created += 1
                outcome = True
            except Exception as exc:  # the refusal the create function raises (checked by the caller)
                if type(exc).__name__ not in ("ConfigError", "SessionExistsError", "SessionError"):
                    raise
                refused += 1
                outcome = False
            streak = streak + 1 if outcome == last else 1
            last = outcome
            if streak >= 10:  # the swapper is not running (a loaded machine): let it
                time.sleep(0.005)
    finally:
        stop.touch()
        out, _ = proc.communicate(timeout=60)
        stop.unlink()
    escapes = sum(1 for e in outside.iterdir() if e.name.endswith(".mcap"))
    return {"attempts": attempts, "created": created, "refused": refused, "escapes": escapes,
            "swaps": int(out.strip() or 0)}


def naive_create(path: str, base_dir: str) -> object:
    """What the service did before: a ``realpath`` check, then an ``open`` of the checked path."""
    from capture.errors import ConfigError

    base = os.path.realpath(base_dir)
    try:
        full = os.path.realpath(os.path.join(base, path))
        if os.path.commonpath([full, base]) != base:
            raise ConfigError("outside")
        with open(os.path.join(base, path), "xb") as f:
            f.write(b"x")
    except OSError:
        raise ConfigError("refused by the OS") from None
    return None


def kill_during_startup(out: Path, delay_s: float | None, timeout: float = 60.0) -> str:
    """Start ``perfcap record -o OUT`` and SIGKILL it after ``delay_s`` seconds, or (``None``) the
    moment its temporary file appears; returns what was there when it died: ``nothing``, ``part``
    (only the temporary file) or ``file`` (the session in place)."""
    cmd = [sys.executable, "-m", "capture.app.cli", "record", "-q", "-d", "synth://imu?rate=500", "--duration",
           "60", "-o", str(out)]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        if delay_s is None:
            end = time.monotonic() + timeout
            while time.monotonic() < end and proc.poll() is None:
                if any(e.name.endswith(".part") for e in out.parent.iterdir()):
                    break
        else:
            time.sleep(delay_s)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    if out.exists():
        return "file"
    return "part" if any(e.name.endswith(".part") for e in out.parent.iterdir()) else "nothing"
