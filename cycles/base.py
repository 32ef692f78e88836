"""``CycleExtractor``: cycle extraction fed sample by sample (live, from the bus) or in one batch.

While a performer keeps looping, :meth:`CycleExtractor.update` collects the stream's samples and, every
``every_s`` seconds of new data, extracts again from the last ``window_s`` seconds. Once two loops are
in it reports a cycle; after that it reports again whenever the new extraction is better: more loops
at a similar confidence, or a clearly higher confidence. ``best`` always holds the current best cycle.

It sees only :class:`~capture.sample.Sample` and :class:`~capture.sample.SampleBatch` items, never
devices; the time base is the bus time.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from capture.errors import CycleError, NoPeriodFoundError
from capture.sample import Sample, SampleBatch
from cycles.extraction import ExtractOptions, extract

if TYPE_CHECKING:
    from collections.abc import Iterable, Sequence

    from cycles._types import FloatArray
    from cycles.cycle import Cycle

log = logging.getLogger(__name__)


@dataclass
class _Buffer:
    t: FloatArray
    v: FloatArray
    n: int = 0

    def append(self, t: FloatArray, v: FloatArray) -> None:
        k = t.size
        if self.n + k > self.t.size:
            cap = max(2 * self.t.size, self.n + k)
            t2 = np.empty(cap)
            v2 = np.empty((cap, self.v.shape[1]))
            t2[:self.n], v2[:self.n] = self.t[:self.n], self.v[:self.n]
            self.t, self.v = t2, v2
        self.t[self.n:self.n + k] = t
        self.v[self.n:self.n + k] = v
        self.n += k

    def drop_before(self, t0: float) -> None:
        i = int(np.searchsorted(self.t[:self.n], t0))
        if i > 0:
            self.t[:self.n - i] = self.t[i:self.n]
            self.v[:self.n - i] = self.v[i:self.n]
            self.n -= i


class CycleExtractor:
    """Streaming and batch cycle extraction for one stream.

    Args:
        stream: the stream to follow (``"wrist/imu"``); ``None`` takes the first stream it is given.
        columns: the stream's channel indices to use (default all).
        channels: names of those channels (for the cycle).
        quaternions, angles, angle_unit: as for :func:`cycles.extract`, indexing the selected columns.
        window_s: only the last this many seconds are used (bounds the cost of each extraction).
        every_s: seconds of new data between extractions.
        options: extraction options.
        seed: extraction seed.

    Raises:
        ValueError: a non-positive window or interval.
    """

    def __init__(self, stream: str | None = None, *, columns: Sequence[int] | None = None,
                 channels: Sequence[str] | None = None, quaternions: Sequence[Sequence[int]] = (),
                 angles: Sequence[int] = (), angle_unit: str = "rad", window_s: float = 60.0,
                 every_s: float = 0.5, options: ExtractOptions | None = None, seed: int = 0) -> None:
        if not window_s > 0 or not every_s > 0:
            raise ValueError("window_s and every_s must be positive")
        self.stream = stream
        self.columns = None if columns is None else list(columns)
        self.channels = None if channels is None else tuple(channels)
        self.quaternions = tuple(tuple(q) for q in quaternions)
        self.angles = tuple(angles)
        self.angle_unit = angle_unit
        self.window_s = float(window_s)
        self.every_s = float(every_s)
        self.options = options
        self.seed = seed
        self.reset()

    def reset(self) -> None:
        """Forget every sample and the current best cycle."""
        self._buf: _Buffer | None = None
        self._next_at: float | None = None
        self.best: Cycle | None = None
        #: Extractions tried, and the reason the last one found nothing (None after a success).
        self.attempts = 0
        self.last_error: str | None = None

    # -- input

    def _take(self, item: Sample | SampleBatch) -> tuple[FloatArray, FloatArray] | None:
        if self.stream is None:
            self.stream = item.stream
        if item.stream != self.stream:
            return None
        if isinstance(item, SampleBatch):
            t = np.asarray(item.t_bus_ns, np.float64) / 1e9
            v = np.asarray(item.values, np.float64)
        else:
            t = np.array([item.t_bus_ns / 1e9])
            v = np.asarray(item.values, np.float64)[None, :]
        if self.columns is not None:
            v = v[:, self.columns]
        return t, v

    def update(self, item: Sample | SampleBatch) -> list[Cycle]:
        """Add a sample or a batch; returns ``[cycle]`` when the best cycle improved, else ``[]``.

        Items of other streams are ignored. Extraction failures (not enough loops yet) are kept in
        :attr:`last_error`, never raised.
        """
        got = self._take(item)
        if got is None or got[0].size == 0:
            return []
        t, v = got
        if self._buf is None:
            self._buf = _Buffer(np.empty(1024), np.empty((1024, v.shape[1])))
            self._next_at = float(t[0]) + self.every_s
        elif v.shape[1] != self._buf.v.shape[1]:
            raise ValueError(f"{self.stream}: {v.shape[1]} channels after {self._buf.v.shape[1]}")
        self._buf.append(t, v)
        now = float(t[-1])
        assert self._next_at is not None
        if now < self._next_at:
            return []
        self._next_at = now + self.every_s
        self._buf.drop_before(now - self.window_s)
        return self._try()

    def _try(self) -> list[Cycle]:
        assert self._buf is not None
        b = self._buf
        self.attempts += 1
        try:
            cyc = extract(b.t[:b.n], b.v[:b.n], channels=self.channels, quaternions=self.quaternions,
                          angles=self.angles, angle_unit=self.angle_unit, seed=self.seed, options=self.options)
        except CycleError as e:
            self.last_error = str(e)
            log.debug("%s: no cycle yet: %s", self.stream, e)
            return []
        self.last_error = None
        best = self.best
        # the best cycle goes stale when the performer changed the motion: its loops have left the
        # window, or the new period disagrees with it
        stale = best is not None and (float(best.loop_spans_s[0, 0]) < float(b.t[0])
                                      or abs(cyc.period_s / best.period_s - 1.0) > 0.1)
        if best is None or stale or (cyc.loops > best.loops and cyc.confidence >= best.confidence - 0.05) \
                or cyc.confidence > best.confidence + 0.02:
            self.best = cyc
            return [cyc]
        return []

    # -- batch

    def extract(self, samples: Iterable[Sample | SampleBatch]) -> Cycle:
        """All of ``samples`` at once (the stream's samples in the last ``window_s`` seconds are not
        a limit here: everything given is used).

        Raises:
            NoMotionError, NoPeriodFoundError: as :func:`cycles.extract`.
        """
        ts: list[FloatArray] = []
        vs: list[FloatArray] = []
        for item in samples:
            got = self._take(item)
            if got is not None:
                ts.append(got[0])
                vs.append(got[1])
        if not ts:
            raise NoPeriodFoundError(f"no samples of {self.stream or 'any stream'}")
        return extract(np.concatenate(ts), np.concatenate(vs), channels=self.channels,
                       quaternions=self.quaternions, angles=self.angles, angle_unit=self.angle_unit,
                       seed=self.seed, options=self.options)
