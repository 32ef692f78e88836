"""The transport registry: URL scheme -> Transport class.

Built-in schemes are listed in ``TRANSPORTS`` as lazy ``(module, class)`` pairs; other packages
(including perfcap's own ``sim_devices``) add schemes through the ``perfcap.transports`` entry-point
group, so production code never imports the simulators.
"""

from __future__ import annotations

import functools
import importlib
import logging
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, Any

from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError, DeviceUnavailableError
from devices.transports.base import Transport, split_url

if TYPE_CHECKING:
    from collections.abc import Mapping

log = logging.getLogger(__name__)

#: Built-in schemes.
TRANSPORTS: dict[str, tuple[str, str]] = {
    "serial": ("devices.transports.serialport", "SerialTransport"),
    "rfc2217": ("devices.transports.serialport", "Rfc2217Transport"),
    "socket": ("devices.transports.serialport", "SocketTransport"),
    "loop": ("devices.transports.serialport", "LoopTransport"),
    "hid": ("devices.transports.hid", "HidTransport"),
    "evdev": ("devices.transports.evdev", "EvdevTransport"),
    "net": ("devices.transports.network", "NetTransport"),
    "sensorserver": ("devices.transports.sensorserver", "SensorServerTransport"),
    "lsl": ("devices.transports.lsl", "LslTransport"),
}

_ENTRY_POINT_GROUP = "perfcap.transports"


@functools.lru_cache(maxsize=1)
def _entry_points() -> dict[str, Any]:
    return {ep.name: ep for ep in entry_points(group=_ENTRY_POINT_GROUP)}


def known_schemes() -> list[str]:
    return sorted(set(TRANSPORTS) | set(_entry_points()))


def transport_class(scheme: str) -> type[Transport]:
    """The class registered for ``scheme``.

    Raises:
        DeviceUnavailableError: no transport has that scheme, its module cannot be imported, or what
            it names is not a Transport subclass.
    """
    scheme = scheme.lower()
    ep = None if scheme in TRANSPORTS else _entry_points().get(scheme)
    if scheme not in TRANSPORTS and ep is None:
        raise DeviceUnavailableError(
            f"unknown transport scheme {scheme!r}; known schemes: {', '.join(known_schemes()) or 'none'}"
            " (is perfcap installed with 'pip install -e .'?)", source=scheme)
    where = ":".join(TRANSPORTS[scheme]) if ep is None else f"entry point {ep.value}"
    try:
        if ep is None:
            mod, name = TRANSPORTS[scheme]
            obj = getattr(importlib.import_module(mod), name)
        else:
            obj = ep.load()
    except (ImportError, AttributeError) as exc:
        raise DeviceUnavailableError(f"the {scheme}:// transport cannot be loaded from {where}: {exc}",
                                     source=scheme) from exc
    if not (isinstance(obj, type) and issubclass(obj, Transport)):
        raise DeviceUnavailableError(f"the {scheme}:// transport: {where} is {obj!r}, not a Transport subclass",
                                     source=scheme)
    return obj


def open_transport(url: str, *, clock: Clock = MONOTONIC, extra: Mapping[str, Any] | None = None) -> Transport:
    """A (not yet opened) transport for ``url``; ``extra`` options are merged over the URL's.

    Raises:
        ConfigError: malformed URL or options.
        DeviceUnavailableError: unknown scheme.
    """
    scheme, address, opts = split_url(url)
    if extra:
        opts.update(extra)
    cls = transport_class(scheme)
    return cls(address, opts, clock=clock)


__all__ = [
    "TRANSPORTS",
    "ConfigError",
    "Transport",
    "known_schemes",
    "open_transport",
    "split_url",
    "transport_class",
]
