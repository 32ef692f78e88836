"""Damage campaign on a realistic multi-chunk session: random single-byte flips and zeroed blocks.

Records a session of three synthetic IMUs (several streams, many MCAP chunks) through the real
recorder, damages copies of it at seeded random offsets and reads each with ``SessionReader``. For
each case the samples that come back are compared with what the pristine file holds and with what
the damaged chunks held. Target: no session lost, no case losing more than the damaged chunks'
samples, no loss without the damage reported. Then the replay side: damaged copies of that take and
of a take of untidy devices in 4 KiB chunks (drift, jitter, no device clock with line noise, a clock
that wraps) are replayed as fast as possible with verification; target: every case "equal" (no
surviving reading differs) and the loss reported exactly what the damage cost; and ``perfcap replay
--fast`` runs on a sample of copies (no traceback, exit 0 or 1). The CI tests (``tests/unit/capture/
test_session_damage.py``, ``tests/cli/test_damaged_replay.py``) run bounded parts of this.

Measurement script: prints figures and PASS/FAIL per target, always exits 0.
"""

from __future__ import annotations

import argparse
import logging
import random
import shutil
import sys
import tempfile
import time
from pathlib import Path

from _common import check, header, summary

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from session_damage_helpers import VARIED, ReplaySweepResult, chunk_map, make_session, replay_sweep, sweep


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--flips", type=int, default=1000)
    ap.add_argument("--blocks", type=int, default=100)
    ap.add_argument("--block-bytes", type=int, default=4096)
    ap.add_argument("--seconds", type=int, default=30, help="length of the recorded session")
    ap.add_argument("--replays", type=int, default=40, help="damaged copies also replayed with replay --fast")
    ap.add_argument("--replay-flips", type=int, default=500, help="flips replayed and verified, per take")
    ap.add_argument("--replay-blocks", type=int, default=50, help="zeroed blocks replayed and verified, per take")
    ap.add_argument("--seed", type=int, default=16)
    args = ap.parse_args()
    logging.disable(logging.WARNING)   # one warning per damaged case otherwise
    header("session damage: single-byte flips and zeroed blocks")
    work = Path(tempfile.mkdtemp(prefix="perfcap_damage_"))
    pristine = work / "take.mcap"
    make_session(pristine, seconds=args.seconds)
    chunks = chunk_map(pristine.read_bytes())
    print(f"   session: {pristine.stat().st_size} bytes, {len(chunks)} chunks, "
          f"{sum(c.samples for c in chunks)} samples (largest chunk {max(c.samples for c in chunks)})")
    t0 = time.perf_counter()
    res = sweep(pristine, work, flips=args.flips, blocks=0, seed=args.seed)
    blk = sweep(pristine, work, flips=0, blocks=args.blocks, block_bytes=args.block_bytes, seed=args.seed + 1)
    wall = time.perf_counter() - t0
    for label, r in (("flips", res), (f"zeroed {args.block_bytes} B blocks", blk)):
        print(f"   {label}: tried {r.tried}, sessions lost {r.lost_sessions}, cases over the damaged chunks' "
              f"samples {r.over_budget}, losses not reported {r.silent_losses}, cases that lost samples "
              f"{r.damaged_reported + r.silent_losses}, max samples lost {r.max_lost} (the damaged chunks "
              f"held {r.max_lost_allowed}; largest chunk {r.largest_chunk})")
        for f in r.failures[:5]:
            print(f"      {f}")
    print(f"   {wall:.1f} s for {res.tried + blk.tried} cases")
    check("flips tried", res.tried >= min(args.flips, 1000) * 0.99, f"{res.tried}")
    check("blocks tried", blk.tried >= min(args.blocks, 100) * 0.99, f"{blk.tried}")
    check("no session lost", res.lost_sessions + blk.lost_sessions == 0,
          f"{res.lost_sessions + blk.lost_sessions} lost")
    check("loss at most the damaged chunks'", res.over_budget + blk.over_budget == 0,
          f"{res.over_budget + blk.over_budget} cases over")
    check("every loss reported", res.silent_losses + blk.silent_losses == 0,
          f"{res.silent_losses + blk.silent_losses} silent")
    replay_verified(pristine, work, args)
    replay_sample(pristine, work, args)
    shutil.rmtree(work, ignore_errors=True)
    summary()


def replay_verified(pristine: Path, work: Path, args: argparse.Namespace) -> None:
    """Replay damaged copies with verification and check each report against the truth."""
    untidy = work / "untidy.mcap"
    make_session(untidy, seconds=args.seconds, chunk_bytes=4096, urls=VARIED)
    t0 = time.perf_counter()
    total = ReplaySweepResult()
    for label, take in (("tidy take, 32 KiB chunks", pristine), ("untidy take, 4 KiB chunks", untidy)):
        r = replay_sweep(take, work, flips=args.replay_flips, blocks=args.replay_blocks,
                         block_bytes=args.block_bytes, seed=args.seed + 3)
        print(f"   replay, {label} ({len(chunk_map(take.read_bytes()))} chunks): {r.tried} cases, not equal "
              f"{r.not_equal}, loss misreported {r.wrong_loss}, inconsistent {r.inconsistent}, not replayed "
              f"{r.sessions_lost}; {r.cases_with_loss} lost readings, {r.cases_renumbered} renumbered, "
              f"{r.cases_restamped} re-stamped (at most {r.restamped_max_ns / 1e6:.1f} ms), {r.inexact} "
              "with the summary lost (loss a lower bound)")
        for f in r.failures[:5]:
            print(f"      {f[:300]}")
        for k in ("tried", "sessions_lost", "not_equal", "wrong_loss", "inconsistent"):
            setattr(total, k, getattr(total, k) + getattr(r, k))
    print(f"   {time.perf_counter() - t0:.1f} s for {total.tried} replays")
    check("damaged replays verified equal", total.not_equal + total.sessions_lost == 0,
          f"{total.not_equal} not equal, {total.sessions_lost} not replayed of {total.tried}")
    check("loss reported exactly", total.wrong_loss + total.inconsistent == 0,
          f"{total.wrong_loss} misreported, {total.inconsistent} inconsistent")


def replay_sample(pristine: Path, work: Path, args: argparse.Namespace) -> None:
    """``perfcap replay --fast`` on damaged copies: no traceback, a verdict (exit 0 or 1)."""
    import contextlib
    import io

    from capture.app.cli import main as cli

    data = pristine.read_bytes()
    rng = random.Random(args.seed + 2)
    bad_exits = 0
    p = work / "replayed.mcap"
    for k in range(args.replays):
        bad = bytearray(data)
        if k % 2:
            bad[rng.randrange(len(bad))] ^= 1 << rng.randrange(8)
        else:
            at = rng.randrange(len(bad) - args.block_bytes)
            bad[at:at + args.block_bytes] = bytes(args.block_bytes)
        p.write_bytes(bytes(bad))
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = cli(["replay", str(p), "--fast", "-q"])
        if code not in (0, 1) or "Traceback" in err.getvalue():
            bad_exits += 1
            print(f"      replay case {k}: exit {code}: {err.getvalue()[-300:]}")
    check("replay --fast on damaged copies", bad_exits == 0, f"{args.replays} replayed, {bad_exits} bad exits")


if __name__ == "__main__":
    main()
