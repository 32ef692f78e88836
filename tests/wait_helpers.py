"""Shared by tests that wait for something another thread or process does: wait for the condition,
never for a length of time. ``DEADLINE_S`` is generous, so it is reached only when something is
broken, never because the machine is busy."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Callable

#: How long a test waits for a condition before it calls the wait a failure.
DEADLINE_S = 60.0


def wait_until(cond: Callable[[], Any], timeout: float = DEADLINE_S, what: str = "a condition") -> Any:
    """Poll ``cond`` until it is truthy; returns its value.

    Raises:
        AssertionError: ``timeout`` seconds passed first.
    """
    end = time.monotonic() + timeout
    while True:
        v = cond()
        if v:
            return v
        if time.monotonic() > end:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.005)
