"""``CycleFollower``: the bus subscriber that runs streaming cycle extraction on one stream while the
performer keeps looping, and hands every improved cycle to a callback (a live view, a log line, the
puppet). The extraction itself is :class:`cycles.CycleExtractor`; this only connects it to the bus.
"""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING, Any

from capture.bus import Subscriber
from capture.sample import Sample, SampleBatch
from cycles import Cycle, CycleExtractor, ExtractOptions

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

log = logging.getLogger(__name__)


class CycleFollower(Subscriber):
    """Follows ``stream`` on the bus and keeps its current best cycle.

    Args:
        stream: the stream name (``"wrist/imu"``).
        on_cycle: called on the subscriber's thread with each improved cycle.
        columns, window_s, every_s, options: as for :class:`cycles.CycleExtractor`.
    """

    coalesce_s = 0.02   # a cycle a few milliseconds later is as good: wake up per batch of items

    def __init__(self, stream: str, on_cycle: Callable[[Cycle], Any] | None = None, *,
                 columns: Sequence[int] | None = None, channels: Sequence[str] | None = None,
                 quaternions: Sequence[Sequence[int]] = (), angles: Sequence[int] = (), angle_unit: str = "rad",
                 window_s: float = 60.0, every_s: float = 0.5, options: ExtractOptions | None = None,
                 seed: int = 0) -> None:
        self.extractor = CycleExtractor(stream, columns=columns, channels=channels, quaternions=quaternions,
                                        angles=angles, angle_unit=angle_unit, window_s=window_s,
                                        every_s=every_s, options=options, seed=seed)
        self.on_cycle = on_cycle
        self._lock = threading.Lock()
        self._best: Cycle | None = None
        self.updates = 0
        self.errors = 0

    @property
    def best(self) -> Cycle | None:
        """The best cycle so far (None until two loops are in). Reading it never waits for an extraction."""
        return self._best

    def reset(self) -> None:
        """Forget the samples and the best cycle (safe while items arrive)."""
        with self._lock:
            self.extractor.reset()
            self._best = None

    def on_item(self, item: Any) -> None:
        if not isinstance(item, (Sample, SampleBatch)) or item.stream != self.extractor.stream:
            return
        with self._lock:   # held by the delivery thread and reset() only, never by readers of best
            got = self.extractor.update(item)
            if got:
                self._best = got[-1]
        for cyc in got:
            self.updates += 1
            log.info("%s: cycle %.3f s from %d loops, confidence %.2f", self.extractor.stream, cyc.period_s,
                     cyc.loops, cyc.confidence)
            if self.on_cycle is not None:
                self.on_cycle(cyc)

    def on_error(self, exc: BaseException) -> None:
        self.errors += 1
        log.warning("cycle follower on %s: %s", self.extractor.stream, exc)
