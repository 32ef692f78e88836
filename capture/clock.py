"""The only place perfcap reads the OS clock.

``Clock`` is a protocol with ``now_ns()`` (host monotonic nanoseconds), ``sleep_until_ns()`` and
``wall_time_s()`` (seconds since the epoch, for metadata only).
``MonotonicClock`` is the real one; ``ManualClock`` is advanced by hand in tests, so nothing
in a test sleeps.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol, runtime_checkable


@runtime_checkable
class Clock(Protocol):
    """Host monotonic time in integer nanoseconds."""

    def now_ns(self) -> int: ...

    def sleep_until_ns(self, deadline_ns: int) -> None: ...

    def wall_time_s(self) -> float:
        """Wall-clock seconds since the epoch, for session metadata only (never for samples)."""
        ...


class MonotonicClock:
    """The host's monotonic clock, with a deadline sleep precise to tens of microseconds.

    ``sleep_until_ns`` sleeps with the OS until ``spin_ns`` before the deadline, then spins on the
    clock (yielding the interpreter lock between reads). A plain ``sleep(period)`` loop drifts by
    several percent; this does not accumulate error because every deadline is absolute.
    """

    def __init__(self, spin_ns: int = 300_000) -> None:
        self.spin_ns = spin_ns

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep_until_ns(self, deadline_ns: int) -> None:
        remaining = deadline_ns - time.monotonic_ns()
        if remaining > self.spin_ns:
            time.sleep((remaining - self.spin_ns) / 1e9)
        while time.monotonic_ns() < deadline_ns:
            time.sleep(0)

    def wall_time_s(self) -> float:
        """Wall-clock seconds since the epoch, for session metadata only (never for samples)."""
        return time.time()


class ManualClock:
    """A clock that only moves when told to; ``sleep_until_ns`` jumps to the deadline."""

    def __init__(self, start_ns: int = 1_000_000_000) -> None:
        self._t = start_ns
        self._lock = threading.Lock()

    def now_ns(self) -> int:
        return self._t

    def advance(self, dt_ns: int) -> int:
        with self._lock:
            self._t += dt_ns
            return self._t

    def set(self, t_ns: int) -> None:
        with self._lock:
            self._t = t_ns

    def sleep_until_ns(self, deadline_ns: int) -> None:
        with self._lock:
            if deadline_ns > self._t:
                self._t = deadline_ns

    def wall_time_s(self) -> float:
        return self._t / 1e9


MONOTONIC = MonotonicClock()
