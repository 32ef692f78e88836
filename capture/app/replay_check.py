"""Checking a replay against its recording: ``ReplayVerifier`` compares every replayed sample with
its recorded counterpart, and ``describe_verification`` says the result as ``perfcap replay``
prints it.

A reading is matched by its sequence number first. Where that fails (the number belongs to a
different reading, or to none), it is matched by its identity: its device time (its host time when
the device gives none) together with the bits of its values, if exactly one recorded reading has
that identity. So a hole in the raw data that renumbers the replayed readings after it, or a
recorded block lost to damage, shifts nothing: the rest is still compared reading by reading.

What a damaged session lost is counted against what its summary says the take held (samples and
first and last sequence number per stream), so a lost head or tail is counted as well as a hole.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from capture.bus import Subscriber
from capture.sample import NO_TIME, Sample, SampleBatch

_MIX = np.uint64(0x9E3779B97F4A7C15)


@dataclass(frozen=True)
class Expected:
    """What the take's summary says one stream held (None: not said; an older or cut-short file)."""

    samples: int | None = None
    first_seq: int | None = None
    last_seq: int | None = None


def expected_from_summary(summary: dict[str, Any] | None) -> dict[str, Expected]:
    """Per stream, what a session's ``perfcap.summary`` says was written (empty without one)."""
    if not isinstance(summary, dict):
        return {}
    c, sp_all = summary.get("samples"), summary.get("seq")
    counts: dict[str, Any] = c if isinstance(c, dict) else {}
    spans: dict[str, Any] = sp_all if isinstance(sp_all, dict) else {}
    out = {}
    for name in set(counts) | set(spans):
        n = counts.get(name)
        sp = spans.get(name)
        lo = hi = None
        if isinstance(sp, list) and len(sp) == 2 and all(isinstance(v, int) for v in sp):
            lo, hi = sp
        out[name] = Expected(n if isinstance(n, int) and n >= 0 else None, lo, hi)
    return out


def _identity(t_device: np.ndarray, t_host: np.ndarray, bits: np.ndarray) -> np.ndarray:
    """One 64-bit key per reading: its device time (host time where it has none) mixed with its value bits."""
    h = np.where(t_device != NO_TIME, t_device, t_host).view(np.uint64).copy()
    with np.errstate(over="ignore"):
        for k in range(bits.shape[1]):
            h = h * _MIX + bits[:, k].view(np.uint64)
    return h


def _same(item: SampleBatch, bits: np.ndarray, j: np.ndarray, rec: SampleBatch, rec_bits: np.ndarray,
          r: np.ndarray) -> np.ndarray:
    """Whether replayed readings ``j`` are the recorded readings ``r``: the same device time (host
    time where there is none) and the same value bits."""
    dev = item.t_device_ns[j]
    t_ok = np.where(dev != NO_TIME, dev == rec.t_device_ns[r], item.t_host_ns[j] == rec.t_host_ns[r])
    return t_ok & np.all(bits[j] == rec_bits[r], axis=1)


def _bits(values: np.ndarray) -> np.ndarray:
    v = np.ascontiguousarray(values, dtype=np.float64)
    return (v.reshape(len(v), -1) if v.ndim != 2 else v).view(np.int64)


class _Runs:
    """Runs of consecutive sequence numbers, as (first seq, last seq, first bus ns, last bus ns); at
    most ``limit`` are kept (the count is always exact, elsewhere)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.runs: list[tuple[int, int, int | None, int | None]] = []

    def add(self, seq: np.ndarray, bus: np.ndarray) -> None:
        cuts = np.flatnonzero(np.diff(seq) != 1) + 1
        for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(seq)], strict=True):
            r = self.runs
            if r and r[-1][1] + 1 == int(seq[a]):
                r[-1] = (r[-1][0], int(seq[b - 1]), r[-1][2], int(bus[b - 1]))
            elif len(r) < self.limit:
                r.append((int(seq[a]), int(seq[b - 1]), int(bus[a]), int(bus[b - 1])))

    def add_run(self, a: int, b: int, bus_a: int | None, bus_b: int | None) -> None:
        r = self.runs
        if r and r[-1][1] + 1 == a:
            r[-1] = (r[-1][0], b, r[-1][2], bus_b)
        elif len(r) < self.limit:
            r.append((a, b, bus_a, bus_b))

    def as_json(self) -> list[dict[str, list[int | None]]]:
        return [{"seq": [a, b], "bus_ns": [c, d]} for a, b, c, d in self.runs]


class _Stream:
    """One recorded stream and how far the replay has matched it."""

    def __init__(self, rec: SampleBatch, expected: Expected, limit: int) -> None:
        self.rec = rec
        self.expected = expected
        self.bits = _bits(rec.values)
        self.matched = np.zeros(len(rec), bool)
        self.order = np.argsort(rec.seq, kind="stable")
        self.sorted_seq = rec.seq[self.order]
        self.rank = np.empty(len(rec), np.int64)
        self.rank[self.order] = np.arange(len(rec))
        self.offset = 0
        self.done = False
        self.last_rank = -1
        # the replay's last matched number; devices number a take's readings from 0
        self.last_replayed: int = (expected.first_seq if expected.first_seq is not None else 0) - 1
        self._ids: tuple[np.ndarray, np.ndarray] | None = None
        self._vids: tuple[np.ndarray, np.ndarray] | None = None
        self.compared = self.mismatches = self.not_recorded = self.renumbered = 0
        self.restamped = 0
        self.restamped_max_ns = 0
        self.device_shifts: set[int] = set()   # device-time differences seen among re-stamped readings
        self.skipped = False      # the replay passed over recorded readings: its raw data has a hole
        self.extra = _Runs(limit)
        #: unknown replayed readings whose numbering is not known yet, as runs of the replay's numbers
        self.pending = _Runs(1 << 62)
        self.first_mismatch: str | None = None
        # replayed readings numbered within [lo, hi] whose recorded counterpart is lost are "not recorded";
        # past the take's last one (a cut-short file's raw data outlives its sample blocks) they are ignored
        lo = expected.first_seq
        hi = expected.last_seq if expected.last_seq is not None else (
            int(self.sorted_seq[-1]) if len(rec) else None)
        self.lo = lo if lo is not None else np.iinfo(np.int64).min
        self.hi = hi

    def by_seq(self, key: np.ndarray) -> np.ndarray:
        """Recorded index of each sequence number, -1 where there is none."""
        ss = self.sorted_seq
        if not len(ss):
            return np.full(len(key), -1, np.int64)
        pos = np.searchsorted(ss, key)
        pc = np.minimum(pos, len(ss) - 1)
        return np.where((pos < len(ss)) & (ss[pc] == key), self.order[pc], -1)

    def by_identity(self, ids: np.ndarray, with_times: bool = True) -> np.ndarray:
        """Recorded index of the one reading with each identity (its time and values, or its values
        alone), -1 where none or several have it."""
        index = self._ids if with_times else self._vids
        if index is None:
            t = self.rec.t_device_ns if with_times else np.zeros(len(self.rec), np.int64)
            rid = _identity(t, self.rec.t_host_ns if with_times else t, self.bits)
            o = np.argsort(rid, kind="stable")
            index = (rid[o], o)
            if with_times:
                self._ids = index
            else:
                self._vids = index
        srt, o = index
        if not len(srt):
            return np.full(len(ids), -1, np.int64)
        left, right = np.searchsorted(srt, ids, "left"), np.searchsorted(srt, ids, "right")
        return np.where(right - left == 1, o[np.minimum(left, len(srt) - 1)], -1)


class ReplayVerifier(Subscriber):
    """Compares replayed samples with the recorded ones, stream by stream, on the first pass.

    Matched readings must be bit-identical in values, device time and bus time, and in host time
    when the replay keeps recorded stamps. Once the replay of a stream has passed over recorded
    readings (their raw data is lost), its stamping and clock fit start afresh, so from there host
    and bus times that differ are counted as ``restamped`` (with the largest difference), not as
    mismatches; the device time and values must still be the recorded ones.
    A recorded reading that is never replayed is ``missing``; a replayed one whose recorded block is
    lost is ``not_recorded``; one matched under a different number is ``renumbered``. Batches are
    compared as whole columns.
    """

    accepts = frozenset({Sample, SampleBatch})
    #: how many missing, not-recorded or lost runs are listed per stream
    MAX_RANGES = 20

    def __init__(self, recorded: dict[str, SampleBatch], check_host_times: bool = True,
                 expected: dict[str, Expected] | None = None) -> None:
        self.recorded = recorded
        self.check_host = check_host_times
        exp = expected or {}
        # a summary lists every stream that was written: one it does not list had no readings
        none = Expected(0) if exp else Expected()
        self._s = {s: _Stream(b, exp.get(s, none), self.MAX_RANGES) for s, b in recorded.items()}
        self.unexpected: dict[str, int] = {}
        #: items the check itself failed on (a failed check never reads as "equal")
        self.errors = 0
        self.first_error: str | None = None

    def on_error(self, exc: BaseException) -> None:
        self.errors += 1
        if self.first_error is None:
            self.first_error = f"{type(exc).__name__}: {exc}"

    def on_item(self, item: Any) -> None:
        st = self._s.get(item.stream)
        if st is None:
            n = 1 if type(item) is Sample else len(item)
            self.unexpected[item.stream] = self.unexpected.get(item.stream, 0) + n
            return
        if st.done or st.hi is None:
            return  # later loop passes, or a stream of which nothing is known to have been recorded
        if type(item) is Sample:
            w = st.rec.values.shape[1] if st.rec.values.ndim == 2 else 0
            item = SampleBatch.from_samples(item.stream, [item], w)
        if len(item):
            self._compare(st, item)

    def _compare(self, st: _Stream, item: SampleBatch) -> None:
        if not self._equal_run(st, item):
            self._match(st, item)

    def _equal_run(self, st: _Stream, item: SampleBatch) -> bool:
        """The common case, checked at once: the batch is the recorded readings that follow the last
        one matched, bit for bit. False (nothing counted) when it is not."""
        n, ss = len(item), st.sorted_seq
        i0 = st.last_rank + 1
        if (st.skipped or st.pending.runs or i0 + n > len(ss) or st.hi is None
                or item.seq[0] != st.last_replayed + 1 or item.seq[-1] - item.seq[0] != n - 1):
            return False
        s0 = int(item.seq[0]) + st.offset
        if ss[i0] != s0 or ss[i0 + n - 1] != s0 + n - 1 or s0 + n - 1 >= st.hi:
            return False
        r = st.order[i0:i0 + n]
        rec = st.rec
        bits = _bits(item.values)
        if (bits.shape != (n, *st.bits.shape[1:]) or st.matched[r].any()
                or not np.array_equal(bits, st.bits[r]) or not np.array_equal(item.t_device_ns, rec.t_device_ns[r])
                or not np.array_equal(item.t_bus_ns, rec.t_bus_ns[r])
                or (self.check_host and not np.array_equal(item.t_host_ns, rec.t_host_ns[r]))):
            return False
        st.matched[r] = True
        st.compared += n
        st.last_rank = i0 + n - 1
        st.last_replayed = int(item.seq[-1])
        return True

    def _match(self, st: _Stream, item: SampleBatch) -> None:
        rec, hi = st.rec, st.hi
        assert hi is not None   # on_item skips a stream of which nothing is known
        seq = item.seq.astype(np.int64)
        guess = seq + st.offset   # each reading's number in the recording's numbering, as far as known
        ri = st.by_seq(guess)
        bits = _bits(item.values)
        width_ok = bits.shape[1:] == st.bits.shape[1:]
        same = ri >= 0   # a reading is itself when it has its recorded counterpart's identity
        if width_ok and same.any():
            j = np.flatnonzero(same)
            same[j] = _same(item, bits, j, rec, st.bits, ri[j])
        renum = np.zeros(len(seq), bool)
        trailing = np.zeros(len(seq), bool)   # unknown readings after the batch's last recognised one
        if width_ok and not same.all():
            j = np.flatnonzero(~same)
            alt = st.by_identity(_identity(item.t_device_ns[j], item.t_host_ns[j], bits[j]))
            found = alt >= 0
            found[found] = _same(item, bits, j[found], rec, st.bits, alt[found])
            alt[~found] = -1
            if not found.all():
                # by its values alone: after lost raw data a wrapping device clock may unwrap differently
                rest = np.flatnonzero(~found)
                zero = np.zeros(rest.size, np.int64)
                a2 = st.by_identity(_identity(zero, zero, bits[j[rest]]), with_times=False)
                hit = a2 >= 0
                hit[hit] = np.all(bits[j[rest[hit]]] == st.bits[a2[hit]], axis=1)
                alt[rest[hit]] = a2[hit]
                found[rest[hit]] = True
            k = j[found]
            ri[k] = alt[found]
            offs = rec.seq[alt[found]] - seq[k]
            renum[k] = offs != 0
            unknown = j[~found]
            if k.size:
                self._settle(st, int(offs[0]))   # the numbering of earlier unknown readings is now known
            if unknown.size:
                # the numbering in effect at an unknown reading is the next recognised reading's; after
                # the last one it is not known yet (a later hole may follow): it waits (``pending``)
                nxt = np.searchsorted(k, unknown)
                before = nxt < k.size
                guess[unknown[before]] = seq[unknown[before]] + offs[nxt[before]]
                trailing[unknown[~before]] = True
                if st.skipped or st.offset or renum.any():
                    # numbered afresh after lost raw data, and neither itself at its number nor known by
                    # its identity: its recorded counterpart is lost, it is not a changed reading
                    ri[unknown] = -1
                else:
                    # a reading whose time and values both differ from its number's is another reading
                    # (that one's record is lost); one that differs in one of them is a changed reading
                    u = unknown[ri[unknown] >= 0]
                    dev = item.t_device_ns[u]
                    t_differs = np.where(dev != NO_TIME, dev != rec.t_device_ns[ri[u]],
                                         item.t_host_ns[u] != rec.t_host_ns[ri[u]])
                    other = t_differs & np.any(bits[u] != st.bits[ri[u]], axis=1)
                    ri[u[other]] = -1
            if k.size:
                st.offset = int(offs[-1])
                guess[trailing] = seq[trailing] + st.offset
        mapped = guess
        if len(rec):
            mapped = np.where(ri >= 0, rec.seq[np.maximum(ri, 0)], mapped)
        # the first pass ends at the take's last reading; what follows is a later loop pass
        end = np.flatnonzero(mapped >= hi)
        if end.size:
            n = int(end[0]) + 1
            seq, ri, renum, mapped, item = seq[:n], ri[:n], renum[:n], mapped[:n], _head(item, n)
            bits, trailing = bits[:n], trailing[:n]
            st.done = True
        have = ri >= 0
        if have.any():   # a recorded reading is matched once
            h = np.flatnonzero(have)
            first = np.zeros(h.size, bool)
            first[np.unique(ri[h], return_index=True)[1]] = True
            have[h] = first & ~st.matched[ri[h]]
        wait = ~have & (ri < 0) & trailing
        if wait.any():
            st.pending.add(seq[wait], item.t_bus_ns[wait])
        extra = np.flatnonzero(~have & ~wait & (mapped >= st.lo) & (mapped <= hi))
        if extra.size:
            st.not_recorded += int(extra.size)
            st.extra.add(mapped[extra], item.t_bus_ns[extra])
        k = np.flatnonzero(have)
        if not k.size:
            return
        r = ri[k]
        st.matched[r] = True
        st.compared += int(k.size)
        st.renumbered += int(renum[k].sum())
        # passed over recorded readings (before the first matched, or between two): lost raw data
        ranks = st.rank[r]
        prev = np.r_[st.last_rank, ranks[:-1]]
        skip = ranks > prev + 1
        st.last_rank = max(st.last_rank, int(ranks.max()))
        # ... or the replay's own numbering jumps there (readings lost from both the raw data and the record)
        rs = seq[k]
        skip |= rs > np.r_[st.last_replayed, rs[:-1]] + 1
        skip |= renum[k]   # numbered afresh: raw data was lost before it
        st.last_replayed = int(rs[-1])
        after_hole = np.maximum.accumulate(skip) | st.skipped
        st.skipped = bool(after_hole[-1])
        # values and device time must be the recorded ones; after lost raw data the stamps may differ
        # (the clock fit and the device clock's unwrapping start afresh): re-stamped, not a mismatch
        vals_ok = np.all(bits[k] == st.bits[r], axis=1) if width_ok else np.zeros(k.size, bool)
        dev, rdev = item.t_device_ns[k], rec.t_device_ns[r]
        dev_ok = dev == rdev
        shift = np.abs(item.t_bus_ns[k] - rec.t_bus_ns[r])
        if self.check_host:
            shift = np.maximum(shift, np.abs(item.t_host_ns[k] - rec.t_host_ns[r]))
        exact = vals_ok & dev_ok & (shift == 0)
        restamped = vals_ok & ~exact & after_hole
        ok = exact | restamped
        if restamped.any():
            st.restamped += int(restamped.sum())
            st.restamped_max_ns = max(st.restamped_max_ns, int(shift[restamped].max()))
            moved = restamped & ~dev_ok & (dev != NO_TIME) & (rdev != NO_TIME)
            for d in np.unique(dev[moved] - rdev[moved])[:5].tolist():
                if len(st.device_shifts) < 5:
                    st.device_shifts.add(int(d))
        bad = np.flatnonzero(~ok)
        if bad.size:
            st.mismatches += int(bad.size)
            if st.first_mismatch is None:
                a, i = int(k[bad[0]]), int(r[bad[0]])
                st.first_mismatch = (
                    f"seq {int(item.seq[a])}: replayed host={int(item.t_host_ns[a])} device={int(item.t_device_ns[a])} "
                    f"bus={int(item.t_bus_ns[a])} values={tuple(item.values[a].tolist())} but recorded "
                    f"seq={int(rec.seq[i])} host={int(rec.t_host_ns[i])} device={int(rec.t_device_ns[i])} "
                    f"bus={int(rec.t_bus_ns[i])} values={tuple(rec.values[i].tolist())}")

    @staticmethod
    def _settle(st: _Stream, offset: int) -> None:
        """Count the waiting unknown readings, numbered with ``offset``, as not recorded (those the
        take's numbering covers)."""
        hi = st.hi if st.hi is not None else np.iinfo(np.int64).min
        for a, b, ba, bb in st.pending.runs:
            lo_, hi_ = max(a + offset, st.lo), min(b + offset, hi)
            if lo_ <= hi_:
                st.not_recorded += hi_ - lo_ + 1
                st.extra.add_run(lo_, hi_, ba, bb)
        st.pending.runs.clear()

    def result(self) -> dict[str, Any]:
        per = {}
        for st in self._s.values():
            self._settle(st, st.offset)
        for s, st in self._s.items():
            b = st.rec
            miss = np.flatnonzero(~st.matched)
            missing = _Runs(self.MAX_RANGES)
            if miss.size:
                o = miss[np.argsort(b.seq[miss], kind="stable")]
                missing.add(b.seq[o], b.t_bus_ns[o])
            per[s] = {"recorded": len(b), "expected": st.expected.samples, **_lost(st, self.MAX_RANGES),
                      "compared": st.compared, "mismatches": st.mismatches,
                      "missing": int(miss.size), "not_recorded": st.not_recorded, "renumbered": st.renumbered,
                      "restamped": st.restamped, "restamped_max_ns": st.restamped_max_ns,
                      "device_time_shifts_ns": sorted(st.device_shifts),
                      "missing_ranges": missing.as_json(), "not_recorded_ranges": st.extra.as_json()}
        ok = all(v["mismatches"] == 0 and v["missing"] == 0 and v["not_recorded"] == 0 and v["renumbered"] == 0
                 and v["restamped"] == 0 and (v["expected"] is None or v["lost"] == 0) for v in per.values())
        first = {s: st.first_mismatch for s, st in self._s.items() if st.first_mismatch is not None}
        return {"equal": ok and not self.unexpected and not self.errors, "streams": per,
                "unexpected": self.unexpected, "first_mismatch": first,
                "check_errors": self.errors, "first_check_error": self.first_error}


def _head(b: SampleBatch, n: int) -> SampleBatch:
    return SampleBatch(b.stream, b.seq[:n], b.t_host_ns[:n], b.t_device_ns[:n], b.t_bus_ns[:n], b.values[:n])


def _lost(st: _Stream, limit: int) -> dict[str, Any]:
    """What the recording lost of a stream: its summary's count less what survives (without a
    summary: the holes in its numbering, which also hold readings dropped live), and where: the holes,
    and a lost head or tail as far as the summary's first and last numbers say."""
    ss, b, exp = st.sorted_seq, st.rec, st.expected
    bus = b.t_bus_ns[st.order]
    ranges: list[dict[str, list[int | None]]] = []
    holes_n: int = 0
    if exp.first_seq is not None and (not len(ss) or exp.first_seq < ss[0]):
        ranges.append({"seq": [exp.first_seq, int(ss[0]) - 1 if len(ss) else exp.last_seq],
                       "bus_ns": [None, int(bus[0]) if len(ss) else None]})
    if len(ss) > 1:
        d = np.diff(ss)
        holes = np.flatnonzero(d > 1)
        holes_n = int((d[holes] - 1).sum())
        ranges += [{"seq": [int(ss[h]) + 1, int(ss[h + 1]) - 1], "bus_ns": [int(bus[h]), int(bus[h + 1])]}
                   for h in holes[:limit]]
    if exp.last_seq is not None and len(ss) and exp.last_seq > ss[-1]:
        ranges.append({"seq": [int(ss[-1]) + 1, exp.last_seq], "bus_ns": [int(bus[-1]), None]})
    lost = exp.samples - len(b) if exp.samples is not None else holes_n
    return {"lost": max(lost, 0), "lost_exact": exp.samples is not None, "lost_ranges": ranges[:limit]}


def describe_verification(ver: dict[str, Any], stopped_early: bool = False) -> list[str]:
    """The lines ``perfcap replay`` prints for a verification result: the damage a damaged session
    showed (per stream, how many samples and which seq and bus-time ranges), then either that every
    compared sample is equal or where they differ."""
    lines = []
    streams = ver["streams"]
    if ver.get("damaged"):
        lines.append("  DAMAGED session (skipped: " + ", ".join(f"{n} x {w}" for w, n in sorted(ver["damaged"].items()))
                     + "); the surviving samples are compared")
        for name, v in streams.items():
            lost_what = ("lost with the damage" if v.get("lost_exact")
                         else "absent from the recording (lost with the damage, or dropped live)")
            for key, what in (("lost", lost_what),
                              ("missing", "recorded, not replayed (their raw data is lost)"),
                              ("not_recorded", "replayed, their recorded block is lost")):
                if v.get(key):
                    lines.append(f"    {name}: {v[key]} {what}: {_spans(v[f'{key}_ranges'])}")
            if v.get("restamped"):
                ms = v["restamped_max_ns"] / 1e6
                lines.append(f"    {name}: {v['restamped']} re-stamped after lost raw data (the clock fit starts "
                             f"afresh; host and bus times at most {ms:.3f} ms from the recorded"
                             + "".join(f"; device times moved {d / 1e9:+.6f} s" for d in v["device_time_shifts_ns"])
                             + ")")
    if ver.get("check_errors"):
        lines.append(f"  NOT VERIFIED: the check failed on {ver['check_errors']} items ({ver['first_check_error']})")
        return lines
    if ver["equal"] or (stopped_early and not any(v["mismatches"] for v in streams.values())):
        n = sum(v["compared"] for v in streams.values())
        lines.append(f"verified: all {n} replayed samples equal the recorded ones"
                     + (" (re-stamped where said)" if any(v.get("restamped") for v in streams.values()) else ""))
        return lines
    for name, v in streams.items():
        if v["mismatches"] or v["missing"] or v["not_recorded"] or v["renumbered"] or v.get("restamped"):
            lines.append(f"  MISMATCH {name}: {v['mismatches']} differ, {v['missing']} not reproduced, "
                         f"{v['not_recorded']} not recorded, {v['renumbered']} numbered differently"
                         + (f", {v['restamped']} re-stamped" if v.get("restamped") else ""))
    for name, m in ver["first_mismatch"].items():
        lines.append(f"  first difference in {name}: {m}")
    return lines


def _spans(ranges: list[dict[str, list[int | None]]]) -> str:
    def t(ns: int | None) -> str:
        return "?" if ns is None else f"{ns / 1e9:.3f}"
    out = ", ".join(f"seq {r['seq'][0]}-{r['seq'][1]} (bus {t(r['bus_ns'][0])}-{t(r['bus_ns'][1])} s)"
                    for r in ranges[:3])
    return out + (" ..." if len(ranges) > 3 else "")


__all__ = ["Expected", "ReplayVerifier", "describe_verification", "expected_from_summary"]
