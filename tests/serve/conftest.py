"""Fixtures for the ``perfcap serve`` tests: a real service on loopback in a ``ServiceThread``.

* ``serve(**config)`` starts a ``Service`` on 127.0.0.1 with ephemeral ports (phone page ``port=0``,
  control API ``control_port=0``), mDNS off, a fresh state directory under ``tmp_path`` and the fixed
  pairing token ``TOKEN``; any ``ServeConfig`` field can be overridden. ``served`` is one such service
  with the defaults. Every service, and every simulated phone started through it, is stopped at
  teardown. What a test gets is a ``Served`` (``serve_helpers``): the real endpoints.
* ``sim_phone`` starts ``SimPagePhone``s against any URL (a ``perfcap serve`` subprocess).
* ``fake_sensorserver``: a running ``FakeSensorServer`` (``serve_helpers``), the SensorServer app.
* ``wait_until`` and ``free_port``: polling and free ports on 127.0.0.1, as fixtures.

The classes and functions themselves live in ``serve_helpers``; nothing imports this module.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import pytest
from serve_helpers import TOKEN, FakeSensorServer, PhoneRunner, Served, free_port, wait_until

from capture.app.serve.config import Limits, ServeConfig
from capture.app.serve.service import Service, ServiceThread
from sim_devices.phone_client import SimPagePhone

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator
    from pathlib import Path


@pytest.fixture
def serve(tmp_path: Path) -> Iterator[Callable[..., Served]]:
    """Factory: ``serve(**ServeConfig overrides)`` -> a started ``Served``; all stopped at teardown.
    ``clock=`` gives the service a clock (a ``ManualClock`` to hold rates and timeouts still)."""
    started: list[Served] = []

    def make(clock: Any = None, **overrides: Any) -> Served:
        cfg: dict[str, Any] = {"host": "127.0.0.1", "port": 0, "control_port": 0, "mdns": False,
                               "state_dir": str(tmp_path / "state"), "token": TOKEN,
                               "sessions_dir": str(tmp_path), "limits": Limits()}
        cfg.update(overrides)
        svc = Service(ServeConfig(**cfg)) if clock is None else Service(ServeConfig(**cfg), clock=clock)
        th = ServiceThread(svc).start()
        s = Served(svc, th, tmp_path)
        started.append(s)
        return s

    yield make
    for s in reversed(started):
        s.stop()


@pytest.fixture
def fake_sensorserver() -> Iterator[FakeSensorServer]:
    """A running ``FakeSensorServer`` (100 events per type), stopped at teardown."""
    ss = FakeSensorServer().start()
    yield ss
    ss.stop()


@pytest.fixture
def sim_phone() -> Iterator[Callable[..., PhoneRunner]]:
    """Factory: ``sim_phone(url, token, phone_id, **SimPagePhone options)`` -> a started ``PhoneRunner``
    for a service this test did not start through ``serve`` (e.g. a ``perfcap serve`` subprocess)."""
    runners: list[PhoneRunner] = []

    def make(url: str, token: str | None, phone_id: str, **kw: Any) -> PhoneRunner:
        r = PhoneRunner(SimPagePhone(url, token, phone_id, **kw)).start()
        runners.append(r)
        return r

    yield make
    for r in runners:
        r.stop()


@pytest.fixture(name="wait_until")
def wait_until_fixture() -> Callable[..., Any]:
    """``wait_until(cond, timeout, what)``: poll until ``cond()`` is truthy (AssertionError on timeout)."""
    return wait_until


@pytest.fixture(name="free_port")
def free_port_fixture() -> Callable[..., int]:
    """``free_port(kind=socket.SOCK_DGRAM)``: a port free on 127.0.0.1 right now."""
    return free_port


@pytest.fixture
def served(serve: Callable[..., Served]) -> Served:
    """A service with the default test configuration."""
    return serve()
