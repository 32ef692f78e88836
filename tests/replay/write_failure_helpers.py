"""Real write failures for tests and the campaign script: a process whose file size limit
(``RLIMIT_FSIZE``, with ``SIGXFSZ`` ignored) makes the kernel refuse, with ``EFBIG``, any write past a
chosen byte offset, as a full disk refuses one with ``ENOSPC`` (same path in the writer: ``os.write``
raises ``OSError``).

``recorder_trials`` runs in such a child: one recording per seeded random limit, a simulated device
on a ``ManualClock`` feeding a ``SessionRecorder``; each trial says what the recorder claims the file
holds and what ``SessionReader`` reads back from it.
"""

from __future__ import annotations

import json
import os
import random
import resource
import signal
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

#: ``python LIMITED LIMIT ARGS...`` runs ``perfcap ARGS...`` with writes past LIMIT bytes refused
LIMITED = (
    "import resource, runpy, signal, sys\n"
    "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
    "resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[1]), resource.RLIM_INFINITY))\n"
    "sys.argv = ['perfcap', *sys.argv[2:]]\n"
    "runpy.run_module('capture.app.cli', run_name='__main__', alter_sys=True)\n"
)


def limited_perfcap(limit: int, *args: str) -> list[str]:
    """The command line of ``perfcap ARGS`` whose files may not grow past ``limit`` bytes."""
    return [sys.executable, "-c", LIMITED, str(limit), *args]


def run_trials(seed: int, n: int, directory: Path, timeout: float) -> list[dict]:
    """``recorder_trials`` in a child process (the limit is per process); its results."""
    code = (f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); import write_failure_helpers as h;"
            f" h.recorder_trials({seed}, {n}, {str(directory)!r})")
    p = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=timeout,
                       check=False)
    assert p.returncode == 0, p.stderr[-3000:]
    return [json.loads(line) for line in p.stdout.splitlines() if line.startswith("{")]


def recorder_trials(seed: int, n: int, directory: str) -> None:
    """One JSON line per trial on stdout (see the module docstring)."""
    import logging

    from capture.clock import ManualClock
    from capture.errors import SessionError
    from capture.recorder import SessionRecorder
    from capture.session import SessionReader, SessionWriter
    from devices import open_device

    logging.disable(logging.CRITICAL)  # each failure logs an error: expected here
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    inf = resource.RLIM_INFINITY
    rng = random.Random(seed)
    for i in range(n):
        # offsets from inside the header to past the end of a whole take (about 130 kB)
        limit = rng.randint(1, 400) if rng.random() < 0.2 else rng.randint(400, 200_000)
        path = os.path.join(directory, f"take{i}.mcap")
        fsync = rng.random() < 0.3
        max_loss = rng.choice([0.1, 0.3, 1.0])
        take_s = rng.uniform(1.0, 6.0)
        res: dict = {"trial": i, "limit": limit, "fsync": fsync, "max_loss_s": max_loss}
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, inf))
        clock = ManualClock()
        dev = open_device(f"a=synth://imu?rate=500&seed={i}", clock=clock)
        try:
            try:
                writer = SessionWriter(path, fsync=fsync)
            except SessionError as exc:
                res.update(created=False, error=str(exc), exists=os.path.exists(path))
                continue
            rec = SessionRecorder(writer, max_loss_s=max_loss, clock=clock)
            calls: list[str] = []
            rec.on_failed = lambda e, calls=calls: calls.append(str(e))
            rec.add_device(dev.name, dev.kind, dev.transport.url, dev.device_options, dev.identity, dev.streams)
            t0 = clock.now_ns()
            for item in dev.open():
                rec.on_item(item)
            declare_at = rng.uniform(0.0, take_s) * 1e9  # a device declared mid-take (serve admits phones so)
            declared = []
            while rec.failed is None and clock.now_ns() - t0 < take_s * 1e9:
                for item in dev.poll(0.1):
                    rec.on_item(item)
                if not declared and clock.now_ns() - t0 >= declare_at:
                    declared.append(_declare_other(rec, clock, "b"))
            declared.append(_declare_other(rec, clock, "c"))  # after the take (or its failure): never raises
            rec.stop()
            resource.setrlimit(resource.RLIMIT_FSIZE, (inf, inf))
            r = SessionReader(path)
            read = {s: len(r.samples(s)) for s in r.streams}
            res.update(created=True, failed=None if rec.failed is None else str(rec.failed), on_failed=len(calls),
                       saved={s: v for s, v in rec.saved.items() if v}, read={s: v for s, v in read.items() if v},
                       received=rec.received, exact=rec.saved_exact, size=os.path.getsize(path),
                       complete=r.truncated is None, damaged=r.damaged, declared=declared)
        finally:
            resource.setrlimit(resource.RLIMIT_FSIZE, (inf, inf))
            dev.close()
            res["leftovers"] = sorted(e for e in os.listdir(directory) if e.endswith(".part"))
            print(json.dumps(res), flush=True)


def _declare_other(rec, clock, name: str) -> str:
    """Declare another device to ``rec``; what it raised ("ok" if nothing)."""
    from devices import open_device

    other = open_device(f"{name}=synth://imu?rate=100", clock=clock)
    try:
        rec.add_device(other.name, other.kind, other.transport.url, other.device_options, other.identity,
                       other.streams)
        return "ok"
    except Exception as exc:
        return f"{type(exc).__name__}: {exc}"
    finally:
        other.close()
