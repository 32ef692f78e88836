"""Shared by the ``perfcap serve`` tests: the fixed pairing token, waiting for a condition (``wait_until``,
from ``wait_helpers``) and free ports on 127.0.0.1."""

from __future__ import annotations

import socket
from typing import Any

from wait_helpers import DEADLINE_S, wait_until

#: The pairing token of every test service (a fixed token is never written to the state dir).
TOKEN = "serve-tests-token-0123456789"


class _Current:
    """Sentinel: the service's current token."""


CURRENT: Any = _Current()


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A port nobody listens on at the moment (UDP by default) on 127.0.0.1."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


__all__ = ["CURRENT", "DEADLINE_S", "TOKEN", "free_port", "wait_until"]
