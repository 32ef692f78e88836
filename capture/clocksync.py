"""Online per-stream mapping of a device clock onto the host monotonic clock.

Host arrival times are the device times mapped to the host plus a delay that is never negative:
USB polling, Bluetooth connection intervals, Wi-Fi aggregation and FTDI latency timers only ever
make bytes *late*. So the mapping is the **lower envelope** of the points
``(device time, arrival - device time)``, not a least-squares line through them (which would be
biased by the mean delay and thrown by every burst).

How ``ClockSync`` fits it:

* Per point it keeps only the lowest point of each ``bin_s`` bin (the least-delayed arrival),
  for the last ``window_s`` seconds.
* Every ``refit_s`` it takes the lower convex hull of those bin minima and chooses the hull edge
  above the window's mean device time: the line that lies under every point and minimises the sum
  of implied delays (the linear-programming optimum). Its slope is the drift.
* Between refits, a point that lands *below* the line moves the line down at once.
* Readings in one chunk get their own device times, so a batch is spread out correctly; only the
  newest reading of a chunk constrains the fit (it is the least delayed).
* A sender that batches (a phone page posting every 50 ms) sends its newest reading some time after
  taking it, and that age is not a network delay: the fit would learn it as part of the offset
  and from the rare messages sent right after a reading, which also makes the drift noisy. When the
  message says when it was sent on the device clock, pass that as ``send_ticks``: the arrival is
  then paired with the send time (or the newest reading, if that is later) and the age drops out.
* Device clocks that wrap are unwrapped using the host time elapsed (so even a gap longer than one
  wrap period counts the wraps right), and a jump that disagrees with the host clock by more than
  ``reset_tolerance_s`` starts a new *epoch* (device reset or power cycle).
* Device clocks that follow a wall clock (a phone app's UTC times) can be *stepped* by less than
  that (NTP, the network's time). With ``step_s`` set, such a step starts a new epoch too, keeping
  the fitted rate: at once when the device clock jumps ahead (a point more than ``step_s`` below
  the line, which no network delay can cause), and when it jumps back once every point for
  ``step_confirm_s`` of host time lies more than ``step_s`` above the line (a stall or a burst of
  late messages ends sooner). Without it a step is neither: the line follows a forward step at
  once, but the window then mixes points from both sides of it, and the fit is wrong until the
  window has passed the step (about ``window_s`` seconds). With ``step_s`` set, lateness beyond
  ``reset_tolerance_s`` needs the same confirmation: a Wi-Fi stall of a few seconds delivers its
  messages late, in a burst, and they keep their device times instead of starting two epochs.
* Streams without a device clock get a pseudo clock: the reading counter at the nominal rate. The
  fit then recovers the true rate and dejitters arrivals; a delay beyond the gap threshold (a
  stall, a reconnect, dropped readings) re-anchors it.
* Streams with neither a device clock nor a nominal rate report when something happens (a mouse,
  a touch surface): no grid fits them, so each reading's bus time is its chunk's arrival (several
  in one chunk end at it, 1 us apart), never before the previous one.

Bus times never exceed the arrival time of their chunk and never go backwards within an epoch.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import numpy as np

from capture.sample import ClockState, DeviceClockSpec

if TYPE_CHECKING:
    from collections.abc import Sequence

log = logging.getLogger(__name__)


def lower_hull(xs: Sequence[float] | np.ndarray, ys: Sequence[float] | np.ndarray) -> list[int]:
    """Indices of the lower convex hull of points with strictly increasing x (collinear middle points
    excluded).

    Vectorised: every middle point not strictly below the segment joining its neighbours cannot be
    a hull vertex, so all of them are dropped at once, until none is left (usually a few passes).
    Andrew's monotone chain finishes the rare inputs that need many passes.
    """
    x = np.asarray(xs, np.float64)
    y = np.asarray(ys, np.float64)
    idx = np.arange(x.shape[0])
    for _ in range(24):
        if idx.shape[0] <= 2:
            return idx.tolist()
        xo, yo = x[idx[:-2]], y[idx[:-2]]
        dxa, dya = x[idx[1:-1]] - xo, y[idx[1:-1]] - yo
        bad = dxa * (y[idx[2:]] - yo) - dya * (x[idx[2:]] - xo) <= 0
        if not bad.any():
            return idx.tolist()
        keep = np.ones(idx.shape[0], bool)
        keep[1:-1] = ~bad
        idx = idx[keep]
    return _monotone_chain(x, y, idx.tolist())


def _monotone_chain(x: np.ndarray, y: np.ndarray, order: list[int]) -> list[int]:
    xs, ys = x.tolist(), y.tolist()
    hull: list[int] = []
    for i in order:
        xi, yi = xs[i], ys[i]
        while len(hull) >= 2:
            o, a = hull[-2], hull[-1]
            if (xs[a] - xs[o]) * (yi - ys[o]) - (ys[a] - ys[o]) * (xi - xs[o]) <= 0:
                hull.pop()
            else:
                break
        hull.append(i)
    return hull


_LOOKAHEAD = 512
#: regular arrival intervals that make a run of an event-driven stream, whose grid dejitters it
EVENT_RUN = 8
#: the most an event-driven reading is moved before its arrival by dejittering
EVENT_DEJITTER_MAX_NS = 1_000_000


class _BinRing:
    """The last ``n`` per-bin extreme points (x, y), oldest first, in preallocated arrays."""

    __slots__ = ("_count", "_head", "_n", "_x", "_y")

    def __init__(self, n: int) -> None:
        self._x = [0.0] * n
        self._y = [0.0] * n
        self._n = n
        self._count = 0
        self._head = 0  # next row to write

    def clear(self) -> None:
        self._count = 0
        self._head = 0

    def append(self, point: tuple[float, float]) -> None:
        h = self._head
        self._x[h], self._y[h] = point
        h += 1
        self._head = 0 if h == self._n else h
        if self._count < self._n:
            self._count += 1

    def __len__(self) -> int:
        return self._count

    def with_point(self, point: tuple[float, float]) -> np.ndarray:
        """The stored points in order, then ``point``: an (m + 1, 2) array."""
        n, c, h = self._n, self._count, self._head
        out = np.empty((c + 1, 2), np.float64)
        if c < n:
            out[:c, 0] = self._x[:c]
            out[:c, 1] = self._y[:c]
        else:
            out[:n, 0] = self._x[h:] + self._x[:h]
            out[:n, 1] = self._y[h:] + self._y[:h]
        out[c] = point
        return out


def _first_per_run(hits: np.ndarray, run_id: np.ndarray) -> np.ndarray:
    """The first of ``hits`` (sorted indices) in each run; every run has at least one hit."""
    r = run_id[hits]
    keep = np.empty(r.shape[0], bool)
    keep[0] = True
    np.not_equal(r[1:], r[:-1], out=keep[1:])
    return hits[keep]


class ClockSync:
    """Maps the readings of one clock domain (a device clock, or one stream's pseudo clock) to bus time.

    ``stamp`` handles one chunk; ``stamp_many`` handles many chunks at once with numpy and gives
    bit-identical results (offline replay uses it; ``tests/unit/capture/test_clocksync.py`` checks
    the equality).

    Args:
        stream: the domain's name (for logs and states).
        clock: the device clock, or ``None`` for streams without one.
        nominal_rate_hz: the configured rate; needed for a pseudo clock.
        window_s: how much history the fit uses.
        bin_s: the bin over which only the least-delayed point is kept.
        refit_s: how often (device time) the line is refitted from the hull.
        reset_tolerance_s: a disagreement between device and host elapsed time beyond this starts a
            new epoch. Clipped to a quarter of the wrap period for fast-wrapping counters.
        gap_s: for pseudo clocks, a delay beyond this (plus twice the largest recent delay)
            re-anchors (default: 4 periods, at least 50 ms).
        step_s: device clocks only: a step of the device clock larger than this starts a new epoch
            (see the module docstring), and late arrivals beyond ``reset_tolerance_s`` need
            ``step_confirm_s`` of confirmation before they do. ``None`` (default): only
            ``reset_tolerance_s`` applies, both ways. Choose it above the delays the link adds for
            ``step_confirm_s`` in a row.
        step_confirm_s: how long (host time) every point must lie ``step_s`` above the line before
            a backward step is believed; forward steps are also only believed once an epoch is
            this old (before that, the line is still settling onto the least-delayed arrivals).
    """

    def __init__(self, stream: str, clock: DeviceClockSpec | None, nominal_rate_hz: float | None, *,
                 window_s: float | None = None, bin_s: float = 0.1, refit_s: float = 2.0,
                 reset_tolerance_s: float = 1.0, gap_s: float | None = None, step_s: float | None = None,
                 step_confirm_s: float = 2.0) -> None:
        self.stream = stream
        self.pseudo = clock is None
        self._period_ns = 1e9 / nominal_rate_hz if nominal_rate_hz else 0.0
        if clock is None and nominal_rate_hz:
            clock = DeviceClockSpec(tick_hz=float(nominal_rate_hz))
        self.spec = clock
        self._ns_per_tick = 1e9 / clock.tick_hz if clock else 0.0
        # Whole ns per tick (1 kHz, 1 MHz, 1 GHz clocks): ticks -> ns in integers, exact even for
        # epoch-based device times (~1.7e18 ns), where float64 would round to 256 ns.
        npt_int = round(self._ns_per_tick)
        self._npt_int = npt_int if clock and npt_int >= 1 and npt_int * clock.tick_hz == 1e9 else 0
        self._wrap = clock.wrap_ticks if clock else None
        tol_ns = reset_tolerance_s * 1e9
        if self._wrap:
            tol_ns = min(tol_ns, 0.25 * self._wrap * self._ns_per_tick)
        self._tol_ns = tol_ns
        self._step_ns = step_s * 1e9 if step_s and not self.pseudo else 0.0
        self._confirm_ns = step_confirm_s * 1e9
        self._above_host: int | None = None  # host time of the first point of a run above the line
        self._epoch_host = 0
        if window_s is None:
            window_s = 4.0 if self.pseudo else 20.0
        # Bins and refits are anchored to absolute device time (integer ns), so the fit does not
        # depend on which reading happened to start an epoch or how reads were split.
        self._bin_ns = max(1, round(bin_s * 1e9))
        self._refit_ns = max(1, round(refit_s * 1e9))
        n = max(2, math.ceil(window_s / bin_s))
        self._mins = _BinRing(n)
        self._maxs = _BinRing(n)
        self._gap_ns = (gap_s * 1e9) if gap_s is not None else max(50e6, 4 * self._period_ns)
        self._last_raw: int | None = None
        self._wraps = 0
        self._counter = 0
        self._last_host = 0
        self.epoch = -1
        self.resets = 0
        self.points = 0
        self._state_dirty = False
        self._new_epoch_pending = True
        self._last_bus = -(2**62)
        self._delay_hi = 0.0
        self._arrivals: list[int] = []   # an event-driven stream's last EVENT_RUN arrivals

    # -- epochs -------------------------------------------------------------------------------
    def _start_epoch(self, dev_ns: int, host_ns: int, keep_rate: bool = False) -> None:
        self.epoch += 1
        self._x0 = dev_ns
        self._y0 = host_ns - dev_ns
        self._a = 0.0
        if not keep_rate:
            self._b = 0.0
        self._above_host = None
        self._epoch_host = host_ns
        self._mins.clear()
        self._maxs.clear()
        self._bin = dev_ns // self._bin_ns
        self._bin_min = (0.0, 0.0)
        self._bin_max = (0.0, 0.0)
        self._refit_slot = dev_ns // self._refit_ns
        self._last_host = host_ns
        self._last_dev = dev_ns
        self._delay_hi = 0.0
        self.points = 0
        self._last_bus = -(2**62)
        self._new_epoch_pending = False
        self._state_dirty = True

    # -- public -------------------------------------------------------------------------------
    def stamp(self, t_host_ns: int, ticks: Sequence[int] | None, n: int = 1, *,
              send_ticks: int | None = None) -> tuple[list[int | None], list[int]]:
        """Times for the ``n`` readings that arrived in one chunk at ``t_host_ns``.

        Args:
            t_host_ns: arrival time of the chunk.
            ticks: raw device timestamps of the readings, oldest first, or ``None`` if the domain
                has no device clock.
            n: number of readings (used when ``ticks`` is None).
            send_ticks: raw device time at which the message was sent, when the protocol carries
                it (same clock as ``ticks``). The fit then pairs the arrival with it (or with the
                newest reading if that is later) instead of with the newest reading.

        Returns:
            ``(t_device_ns, t_bus_ns)`` lists, one entry per reading. ``t_device_ns`` entries are
            ``None`` for streams without a device clock.

        Raises:
            ValueError: ticks given to a domain without a device clock.
        """
        if ticks is not None:
            n = len(ticks)
            if self.pseudo:
                raise ValueError(f"{self.stream}: device ticks given to a stream declared without a device clock")
            if n == 0:
                return [], []
            if send_ticks is None:
                devs = self._unwrap(ticks, t_host_ns)
                point = devs[-1]
            else:
                devs = self._unwrap([*ticks, send_ticks], t_host_ns)
                point = max(devs.pop(), devs[-1])
            out_dev: list[int | None] = list(devs)
        else:
            if send_ticks is not None:
                raise ValueError(f"{self.stream}: a send time given to a stream declared without a device clock")
            if n <= 0:
                return [], []
            if self.spec is None:  # no clock, no nominal rate: an event-driven stream
                return [None] * n, self._irregular(self._event_time(t_host_ns), n)
            c0 = self._counter
            self._counter += n
            p = self._period_ns
            devs = [round((c0 + i) * p) for i in range(n)]
            out_dev = [None] * n
            point = devs[-1]
        self._observe(point, t_host_ns)
        rate = 1.0 + self._b
        base = self._x0 + self._y0 + self._a
        bus: list[int] = []
        last = self._last_bus
        x0 = self._x0
        for d in devs:
            b = int(base + (d - x0) * rate)
            if b > t_host_ns:
                b = t_host_ns
            if b < last:
                b = last
            bus.append(b)
            last = b
        self._last_bus = last
        return out_dev, bus

    def stamp_many(self, t_host_ns: np.ndarray, chunk_of: np.ndarray, ticks: np.ndarray | None,
                   send_ticks: np.ndarray | None = None) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
        """``stamp`` for many chunks at once, bit-identical to calling it chunk by chunk.

        Args:
            t_host_ns: int64 arrival time of each chunk (chunks without readings are allowed).
            chunk_of: int64 chunk index of each reading, non-decreasing.
            ticks: int64 raw device ticks of each reading, or ``None`` without a device clock.
            send_ticks: int64 raw device send time of each chunk (indexed like ``t_host_ns``), as
                ``stamp``'s ``send_ticks``; ``None`` when the messages carry none.

        Returns:
            ``(t_device_ns or None, t_bus_ns, epoch of each reading)``.
        """
        t_host_ns = np.asarray(t_host_ns, np.int64)
        chunk_of = np.asarray(chunk_of, np.int64)
        n = chunk_of.shape[0]
        if n == 0:
            e = np.empty(0, np.int64)
            return (None if ticks is None else e), e, e
        # chunks that carry readings, and the index of each one's last reading
        brk = np.empty(n, bool)
        brk[:-1] = chunk_of[1:] != chunk_of[:-1]
        brk[-1] = True
        last_idx = np.flatnonzero(brk)
        first_idx = np.empty_like(last_idx)
        first_idx[0] = 0
        first_idx[1:] = last_idx[:-1] + 1
        hosts = t_host_ns[chunk_of[last_idx]]
        pts_dev: np.ndarray | None = None
        if ticks is not None:
            if self.pseudo:
                raise ValueError(f"{self.stream}: device ticks given to a stream declared without a device clock")
            ticks = np.asarray(ticks, np.int64)
            if send_ticks is None:
                devs = self._unwrap_many(ticks, first_idx, hosts)
            else:
                # unwrap each chunk's send time right after its readings, as ``stamp`` does
                m = last_idx.shape[0]
                rank = np.repeat(np.arange(m), last_idx - first_idx + 1)
                merged = np.empty(n + m, np.int64)
                merged[np.arange(n) + rank] = ticks
                send_pos = last_idx + np.arange(m) + 1
                merged[send_pos] = np.asarray(send_ticks, np.int64)[chunk_of[last_idx]]
                both = self._unwrap_many(merged, first_idx + np.arange(m), hosts)
                devs = both[np.arange(n) + rank]
                pts_dev = np.maximum(both[send_pos], devs[last_idx])
            out_dev: np.ndarray | None = devs
        elif send_ticks is not None:
            raise ValueError(f"{self.stream}: a send time given to a stream declared without a device clock")
        elif self.spec is None:
            bus = np.empty(n, np.int64)
            ends = self._event_times(hosts)
            if last_idx.shape[0] == n:   # one reading per chunk (a HID report), as _irregular does it
                out = np.maximum.accumulate(np.r_[self._last_bus + 1, ends])[1:]
                bus[:] = np.minimum(out, ends)
                self._last_bus = int(bus[-1])
            else:
                for f, l_, h in zip(first_idx.tolist(), last_idx.tolist(), ends.tolist(), strict=True):
                    bus[f:l_ + 1] = self._irregular(h, l_ - f + 1)
            return None, bus, np.full(n, self.epoch, np.int64)
        else:
            c0 = self._counter
            self._counter += n
            devs = np.round((c0 + np.arange(n, dtype=np.int64)).astype(np.float64) * self._period_ns).astype(np.int64)
            out_dev = None
        bus = np.empty(n, np.int64)
        epochs = np.empty(n, np.int64)
        if pts_dev is None:
            pts_dev = devs[last_idx]
        m = len(last_idx)
        i = 0
        while i < m:
            if self._new_epoch_pending:
                self._scalar_chunk(i, devs, pts_dev, first_idx, last_idx, hosts, bus, epochs)
                i += 1
                continue
            r = self._vector_segment(i, devs, pts_dev, first_idx, last_idx, hosts, bus, epochs)
            if r < m:
                self._scalar_chunk(r, devs, pts_dev, first_idx, last_idx, hosts, bus, epochs)
                r += 1
            i = r
        return out_dev, bus, epochs

    def state(self, t_host_ns: int) -> ClockState | None:
        """The current fit, or ``None`` before the first reading."""
        if self.epoch < 0 or self.spec is None:
            return None
        return ClockState(self.stream, t_host_ns, self.epoch, int(self._x0),
                          round(self._x0 + self._y0 + self._a), 1.0 + self._b, self.points, self.pseudo)

    def pop_state(self, t_host_ns: int) -> ClockState | None:
        """The fit if it changed since the last call (for recording the clock-sync history)."""
        if not self._state_dirty:
            return None
        self._state_dirty = False
        return self.state(t_host_ns)

    def predict_bus_ns(self, dev_ns: int) -> int:
        """Bus time of a device time under the current fit (no clamping)."""
        return int(self._x0 + self._y0 + self._a + (dev_ns - self._x0) * (1.0 + self._b))

    # -- internals ----------------------------------------------------------------------------
    def _event_times(self, hosts: np.ndarray) -> np.ndarray:
        """When each chunk of an event-driven stream happened: its arrival, or, where the last
        ``EVENT_RUN`` intervals up to it are regular (all within 10 % of their median, a period of
        0.25 to 50 ms: a polled mouse in motion, a pen in range), the earliest time the run's grid
        allows (the lower envelope of the run's arrivals projected on to it with the run's mean
        period, so never earlier than the truth by more than the arrivals' jitter), at most
        ``EVENT_DEJITTER_MAX_NS`` and half a period before the arrival. A pause or an irregular
        interval ends the run at once. Each chunk depends only on the arrivals before it, so the
        per-chunk and vectorised paths agree however the chunks are split."""
        w = EVENT_RUN
        a = np.concatenate([np.array(self._arrivals, np.int64), hosts]) if self._arrivals else hosts
        out = hosts.copy()
        start = max(w, a.size - hosts.size)   # positions in ``a`` that have a full window and are new
        if a.size > w and start < a.size:
            iv = np.diff(a[start - w:]).astype(np.float64)       # the w intervals up to each new position
            win = np.lib.stride_tricks.sliding_window_view(iv, w)
            med = np.median(win, axis=1)
            ok = ((win >= 0.9 * med[:, None]) & (win <= 1.1 * med[:, None])).all(axis=1)
            ok &= (med >= 250_000) & (med <= 50_000_000)
            if ok.any():
                base = int(a[start - w])   # times relative to it: float64 keeps whole ns
                rel = (a[start - w:] - base).astype(np.float64)
                prev = np.lib.stride_tricks.sliding_window_view(rel[:-1], w)
                span = win.sum(axis=1) / w   # the period over the run: its own error shrinks as 1/w
                pred = (prev + (w - np.arange(w))[None, :] * span[:, None]).min(axis=1)
                cur = rel[w:]
                floor = cur - np.minimum(EVENT_DEJITTER_MAX_NS, med / 2)
                dej = np.clip(np.floor(pred), floor, cur).astype(np.int64) + base
                out[start - (a.size - hosts.size):] = np.where(ok, dej, a[start:])
        self._arrivals = a[-w:].tolist()
        return out

    def _event_time(self, h: int) -> int:
        """``_event_times`` for one chunk, in plain Python (the live path: a few us, not a numpy
        round trip); the same float operations on the same integer-valued floats, so the same result."""
        w = EVENT_RUN
        arr = self._arrivals
        out = h
        if len(arr) == w:
            seq = [*arr, h]
            iv = [float(seq[i + 1] - seq[i]) for i in range(w)]
            srt = sorted(iv)
            med = (srt[w // 2 - 1] + srt[w // 2]) / 2
            if 250_000 <= med <= 50_000_000 and all(0.9 * med <= v <= 1.1 * med for v in iv):
                base = seq[0]
                span = sum(iv) / w
                pred = min(float(seq[j] - base) + (w - j) * span for j in range(w))
                cur = float(h - base)
                floor = cur - min(EVENT_DEJITTER_MAX_NS, med / 2)
                out = int(min(max(math.floor(pred), floor), cur)) + base
            arr.pop(0)
        arr.append(h)
        return out

    def _irregular(self, t_host_ns: int, n: int) -> list[int]:
        # Event-driven streams with no clock and no nominal rate: keep order, 1 us apart, ending at
        # the chunk's time (``_event_times``).
        first = max(t_host_ns - (n - 1) * 1000, self._last_bus + 1)
        out = [min(first + 1000 * i, t_host_ns) for i in range(n)]
        self._last_bus = out[-1]
        return out

    def _unwrap(self, ticks: Sequence[int], t_host_ns: int) -> list[int]:
        out: list[int] = []
        wrap = self._wrap
        npt = self._ns_per_tick
        for i, tick in enumerate(ticks):
            raw = int(tick)
            if self._last_raw is not None and wrap:
                step = raw - self._last_raw
                expected = (t_host_ns - self._last_host) / npt if i == 0 and self.epoch >= 0 else 0.0
                k = round((expected - step) / wrap)
                if k > 0:
                    self._wraps += k
            self._last_raw = raw
            total = raw + self._wraps * wrap if wrap else raw
            out.append(total * self._npt_int if self._npt_int else round(total * npt))
        return out

    def _unwrap_many(self, raw: np.ndarray, first_idx: np.ndarray, hosts: np.ndarray) -> np.ndarray:
        wrap = self._wrap
        npt = self._ns_per_tick
        if wrap:
            prev = np.empty_like(raw)
            prev[1:] = raw[:-1]
            prev[0] = raw[0] if self._last_raw is None else self._last_raw
            step = raw - prev
            expected = np.zeros(raw.shape[0], np.float64)
            prev_host = np.empty_like(hosts)
            prev_host[1:] = hosts[:-1]
            prev_host[0] = self._last_host
            exp_first = (hosts - prev_host) / npt
            if self.epoch < 0:
                exp_first[0] = 0.0
            expected[first_idx] = exp_first
            k = np.round((expected - step) / wrap).astype(np.int64)
            k[k < 0] = 0
            if self._last_raw is None:
                k[0] = 0
            wraps = self._wraps + np.cumsum(k)
            self._wraps = int(wraps[-1])
            total = raw + wraps * wrap
        else:
            total = raw
        self._last_raw = int(raw[-1])
        if self._npt_int:
            return total.astype(np.int64) * self._npt_int
        return np.round(total.astype(np.float64) * npt).astype(np.int64)

    def _scalar_chunk(self, c: int, devs: np.ndarray, pts_dev: np.ndarray, first_idx: np.ndarray,
                      last_idx: np.ndarray, hosts: np.ndarray, bus: np.ndarray, epochs: np.ndarray) -> None:
        f, l_ = int(first_idx[c]), int(last_idx[c])
        host = int(hosts[c])
        dl = devs[f:l_ + 1].tolist()
        self._observe(int(pts_dev[c]), host)
        rate = 1.0 + self._b
        base = self._x0 + self._y0 + self._a
        last = self._last_bus
        x0 = self._x0
        for j, d in enumerate(dl):
            b = int(base + (d - x0) * rate)
            if b > host:
                b = host
            if b < last:
                b = last
            bus[f + j] = b
            last = b
        self._last_bus = last
        epochs[f:l_ + 1] = self.epoch

    def _vector_segment(self, i: int, devs: np.ndarray, pts_dev: np.ndarray, first_idx: np.ndarray,
                        last_idx: np.ndarray, hosts: np.ndarray, bus: np.ndarray, epochs: np.ndarray) -> int:
        """Observe chunk points i.. until the first that resets or refits; returns its index.

        Looks ahead at most ``_LOOKAHEAD`` points: a prefix with no stopping point is processed
        exactly as the per-point code would, so the caller just continues after it.
        """
        d = pts_dev[i:i + _LOOKAHEAD]
        h = hosts[i:i + _LOOKAHEAD]
        x0, y0, b = self._x0, self._y0, self._b
        xi = d - x0
        x = xi.astype(np.float64)
        y = (h - d - y0).astype(np.float64)
        cand = np.empty(x.size + 1)
        cand[0] = self._a
        np.subtract(y, b * x, out=cand[1:])
        a_all = np.minimum.accumulate(cand)
        a_before = a_all[:-1]
        a_after = a_all[1:]
        s0 = float(x0 + y0)
        pred = ((s0 + a_before) + x * (1.0 + b)).astype(np.int64)
        delay = h - pred
        prev = np.empty_like(d)
        prev[0] = self._last_dev
        prev[1:] = d[:-1]
        stop = (d < prev) | (delay < -self._tol_ns) | (delay > self._tol_ns)
        if self.pseudo:
            stop |= delay > self._gap_ns + 2 * self._delay_hi
        stop |= (d // self._refit_ns) != self._refit_slot
        if self._step_ns:  # points that may be a step, or start or extend a run above: per point
            stop |= (delay > self._step_ns) | (delay < -self._step_ns)
        hit = np.flatnonzero(stop)
        k = int(hit[0]) if hit.size else len(d)
        if k == 0:
            return i
        xs, ys = x[:k], y[:k]
        # bins: the same updates the per-point code makes (a new bin starts at its first point; the
        # earliest strictly lower / higher point of a bin replaces its min / max)
        bins = d[:k] // self._bin_ns
        newrun = np.empty(k, bool)
        newrun[0] = True
        np.not_equal(bins[1:], bins[:-1], out=newrun[1:])
        starts = np.flatnonzero(newrun)
        run_id = np.cumsum(newrun) - 1
        mins = np.minimum.reduceat(ys, starts)
        maxs = np.maximum.reduceat(ys, starts)
        first_min = _first_per_run(np.flatnonzero(ys == mins[run_id]), run_id)
        first_max = _first_per_run(np.flatnonzero(ys == maxs[run_id]), run_id)
        for bi, jmin, jmax in zip(bins[starts].tolist(), first_min.tolist(), first_max.tolist(), strict=True):
            ymin, ymax = float(ys[jmin]), float(ys[jmax])
            if bi != self._bin:
                self._mins.append(self._bin_min)
                self._maxs.append(self._bin_max)
                self._bin = bi
                self._bin_min = (float(xs[jmin]), ymin)
                self._bin_max = (float(xs[jmax]), ymax)
            else:
                if ymin < self._bin_min[1]:
                    self._bin_min = (float(xs[jmin]), ymin)
                if ymax > self._bin_max[1]:
                    self._bin_max = (float(xs[jmax]), ymax)
        a_new = float(a_after[k - 1])
        if a_new < self._a:
            self._state_dirty = True
        self._a = a_new
        self.points += k
        self._above_host = None  # these points were all within step_s of the line
        self._last_dev = int(d[k - 1])
        self._last_host = int(h[k - 1])
        # bus times of the readings of these chunks
        f, l_ = int(first_idx[i]), int(last_idx[i + k - 1])
        rc = np.repeat(np.arange(k), last_idx[i:i + k] - first_idx[i:i + k] + 1)
        base = s0 + a_after[rc]
        raw = (base + (devs[f:l_ + 1] - x0).astype(np.float64) * (1.0 + b)).astype(np.int64)
        np.minimum(raw, h[rc], out=raw)
        raw[0] = max(raw[0], self._last_bus)
        out = np.maximum.accumulate(raw)
        bus[f:l_ + 1] = out
        self._last_bus = int(out[-1])
        epochs[f:l_ + 1] = self.epoch
        return i + k

    def _observe(self, dev: int, host: int) -> None:
        if self._new_epoch_pending:
            self._start_epoch(dev, host)
        else:
            delay = host - self.predict_bus_ns(dev)
            back = dev < self._last_dev
            # with step_s, lateness alone (a network stall) needs the confirmation of a backward step
            if back or delay < -self._tol_ns or (delay > self._tol_ns and not self._step_ns):
                self.resets += 1
                log.info("%s: clock epoch %d ends (device %s, delay %.1f ms)", self.stream, self.epoch,
                         "went back" if back else "jumped", delay / 1e6)
                self._start_epoch(dev, host)
            elif self.pseudo and delay > self._gap_ns + 2 * self._delay_hi:
                self.resets += 1
                log.info("%s: arrival gap of %.1f ms; pseudo clock re-anchored", self.stream, delay / 1e6)
                self._start_epoch(dev, host)
            elif self._step_ns:
                self._check_step(dev, host, delay)
        self.points += 1
        self._last_host = host
        self._last_dev = dev
        x = float(dev - self._x0)
        y = float(host - dev - self._y0)
        cand = y - self._b * x
        if cand < self._a:
            self._a = cand  # the line was above a real point: move it down now
            self._state_dirty = True
        bi = dev // self._bin_ns
        if bi != self._bin:
            self._mins.append(self._bin_min)
            self._maxs.append(self._bin_max)
            self._bin = bi
            self._bin_min = (x, y)
            self._bin_max = (x, y)
        elif self.points == 1:
            self._bin_min = (x, y)
            self._bin_max = (x, y)
        else:
            if y < self._bin_min[1]:
                self._bin_min = (x, y)
            if y > self._bin_max[1]:
                self._bin_max = (x, y)
        slot = dev // self._refit_ns
        if slot != self._refit_slot:
            self._refit()
            self._refit_slot = slot

    def _check_step(self, dev: int, host: int, delay: float) -> None:
        """``step_s`` detection for one point (its delay from the current line)."""
        if delay > self._step_ns:
            if self._above_host is None:
                self._above_host = host
            elif host - self._above_host >= self._confirm_ns:
                self.resets += 1
                log.info("%s: clock epoch %d ends (device clock stepped back by about %.1f ms)", self.stream,
                         self.epoch, delay / 1e6)
                self._start_epoch(dev, host, keep_rate=True)
            return
        self._above_host = None
        if delay < -self._step_ns and self.points >= 3 and host - self._epoch_host >= self._confirm_ns:
            self.resets += 1
            log.info("%s: clock epoch %d ends (device clock stepped ahead by about %.1f ms)", self.stream,
                     self.epoch, -delay / 1e6)
            self._start_epoch(dev, host, keep_rate=True)

    def _refit(self) -> None:
        pts = self._mins.with_point(self._bin_min)
        xs, ys = pts[:, 0], pts[:, 1]
        if pts.shape[0] < 3 or xs[-1] - xs[0] < 1e9:
            b = self._b
            a = float(np.min(ys - b * xs))
        else:
            hull = lower_hull(xs, ys)
            hx = xs[hull]
            j = min(int(np.searchsorted(hx[1:], float(xs.mean()), side="left")), len(hull) - 2)
            i0, i1 = hull[j], hull[j + 1]
            b = float((ys[i1] - ys[i0]) / (xs[i1] - xs[i0]))
            a = float(ys[i0] - b * xs[i0])
        self._a, self._b = a, b
        mx = self._maxs.with_point(self._bin_max)
        self._delay_hi = max(0.0, float(np.max(mx[:, 1] - (a + b * mx[:, 0]))))
        self._state_dirty = True
