"""Shared by the ``perfcap serve`` tests: the fixed pairing token, polling and free ports on 127.0.0.1."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from typing import Any

#: The pairing token of every test service (a fixed token is never written to the state dir).
TOKEN = "serve-tests-token-0123456789"


class _Current:
    """Sentinel: the service's current token."""


CURRENT: Any = _Current()


def wait_until(cond: Callable[[], Any], timeout: float = 10.0, what: str = "a condition") -> Any:
    """Poll ``cond`` until it is truthy; returns its value.

    Raises:
        AssertionError: ``timeout`` passed first.
    """
    end = time.monotonic() + timeout
    while True:
        v = cond()
        if v:
            return v
        if time.monotonic() > end:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.02)


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A port nobody listens on at the moment (UDP by default) on 127.0.0.1."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
