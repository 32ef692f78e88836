"""Campaign figures for where sessions are created and how a failed disk ends a take (issue 16):

* symbolic-link swap races: sessions created through a directory another process swaps for a link
  to outside, with this project's SessionWriter and with the old realpath-then-open check;
* write failures at seeded byte offsets (RLIMIT_FSIZE): trials whose saved count differs from
  what SessionReader reads back, or that leave a temporary file;
* SIGKILLs of a real ``perfcap record`` during start-up: next takes that were blocked.

Run: ``.venv/bin/python tests/replay/campaign_sessions.py [--races 10] [--trials 500] [--kills 30]``
"""

from __future__ import annotations

import argparse
import random
import shutil
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from recording_path_helpers import kill_during_startup, naive_create, swap_race
from write_failure_helpers import run_trials

from capture.errors import SessionExistsError
from capture.session import SessionReader, SessionWriter


def _take(path: str, base_dir: str | None = None, overwrite: bool = False) -> None:
    SessionWriter(path, base_dir=base_dir, overwrite=overwrite, fsync=False).close({})


def races(n: int, attempts: int = 300) -> None:
    for name, create in (("SessionWriter (O_NOFOLLOW walk)", _take), ("old realpath check, then open", naive_create)):
        tot = {"attempts": 0, "created": 0, "escapes": 0, "swaps": 0}
        for seed in range(n):
            root = Path(tempfile.mkdtemp())
            try:
                (root / "s").mkdir()
                (root / "o").mkdir()
                r = swap_race(root / "s", root / "o", attempts, seed, create)
            finally:
                shutil.rmtree(root)
            for k in tot:
                tot[k] += r[k]
        print(f"swap races, {name}: {tot['escapes']} escapes in {tot['attempts']} attempts over {n} races"
              f" ({tot['created']} created, {tot['swaps']} swaps)")


def failures(n: int) -> None:
    root = Path(tempfile.mkdtemp())
    try:
        trials = []
        for seed in range(0, n, 100):
            d = root / str(seed)
            d.mkdir()
            trials += run_trials(seed, min(100, n - seed), d, timeout=1800)
    finally:
        shutil.rmtree(root)
    made = [t for t in trials if t["created"]]
    failed = [t for t in made if t["failed"]]
    wrong = [t for t in made if t["saved"] != t["read"] or not t["exact"] or (t["failed"] and t["on_failed"] != 1)]
    left = [t for t in trials if t["leftovers"] or (not t["created"] and t["exists"])]
    lo, hi = min(t["limit"] for t in trials), max(t["limit"] for t in trials)
    print(f"write failures: {len(trials)} offsets tried ({lo}..{hi} bytes): {len(trials) - len(made)} failed while"
          f" creating, {len(failed)} mid-take, {len(made) - len(failed)} took no failure;"
          f" {len(wrong)} with saved != read back, {len(left)} leaving a file or temporary file behind")


def kills(n: int) -> None:
    rng = random.Random(16)
    root = Path(tempfile.mkdtemp())
    seen: dict[str, int] = {}
    blocked = needed_overwrite = 0
    try:
        for i in range(n):
            out = root / f"take{i}.mcap"
            delay = None if i % 3 == 1 else rng.uniform(0.0, 2.5)
            left = kill_during_startup(out, delay)
            seen[left] = seen.get(left, 0) + 1
            try:
                _take(str(out))
            except SessionExistsError as exc:
                if "cut short" not in str(exc):
                    blocked += 1
                    continue
                needed_overwrite += 1
                _take(str(out), overwrite=True)
            SessionReader(str(out))
            if list(root.glob(".*.part")):
                blocked += 1
    finally:
        shutil.rmtree(root)
    print(f"SIGKILL during start-up: {n} kills (left: {seen}); {blocked} next takes blocked, {needed_overwrite}"
          " found an earlier take cut short and replaced it with --overwrite")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--races", type=int, default=10)
    ap.add_argument("--trials", type=int, default=500)
    ap.add_argument("--kills", type=int, default=30)
    a = ap.parse_args()
    races(a.races)
    failures(a.trials)
    kills(a.kills)


if __name__ == "__main__":
    main()
