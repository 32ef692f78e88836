"""Transports: byte pipes that stamp every chunk with the host monotonic time of its arrival.

A transport knows nothing about what the bytes mean (that is the Codec's job). Real ones wrap
pyserial, hidapi or sockets; simulated ones (``synth://``, ``replay://`` in ``sim_devices``) implement
the same interface, so the code above cannot tell them apart.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar
from collections.abc import Mapping
from urllib.parse import parse_qsl, unquote, urlsplit

from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError
from capture.sample import Chunk, Direction
from devices.options import Option, resolve_options


class Transport(abc.ABC):
    """A byte pipe. Subclasses set ``scheme``, ``usage`` and ``options`` and implement the I/O methods.

    Args:
        address: the part of the URL after ``scheme://`` and before ``?``.
        options: query options (already split from device options), checked against ``options``.
        clock: the host clock used to stamp chunks.
    """

    scheme: ClassVar[str] = ""
    usage: ClassVar[str] = "SCHEME://ADDRESS"
    options: ClassVar[dict[str, Option]] = {}

    def __init__(self, address: str, options: Mapping[str, Any] | None = None, clock: Clock = MONOTONIC) -> None:
        self.address = address
        self.clock = clock
        self.opts = resolve_options(self.options, options or {}, f"{self.scheme}://{address}", self.usage)
        self._given = dict(options or {})

    @property
    def url(self) -> str:
        q = "&".join(f"{k}={v}" for k, v in self._given.items())
        return f"{self.scheme}://{self.address}" + (f"?{q}" if q else "")

    @classmethod
    def extra_options(cls, address: str) -> Mapping[str, Option]:
        """Options that depend on the address (a simulator's device model adds its own)."""
        return {}

    # -- what a device may learn from the transport before opening ---------------------------------
    def implied_kind(self) -> str | None:
        """The device kind this transport carries, if it knows (simulators and replays do)."""
        return None

    def implied_device_options(self) -> dict[str, Any]:
        """Device options implied by the source (a replay returns the recorded device's options)."""
        return {}

    def implied_name(self) -> str | None:
        return None

    def identity_hint(self) -> dict[str, Any]:
        """What the transport knows of the device's identity without opening it (USB vid, pid,
        serial number, bus address); keys are ``DeviceIdentity`` fields. Default: nothing."""
        return {}

    def present(self) -> bool | None:
        """Whether the device is there to be opened, found cheaply without opening it (a serial
        port's path exists); ``None`` when the transport cannot tell. While a device is away the
        reader polls this, so it reconnects as soon as the device returns, not at the next
        backoff step."""
        return None

    # -- I/O ----------------------------------------------------------------------------------------
    @abc.abstractmethod
    def open(self) -> None:
        """Open the pipe.

        Raises:
            DeviceNotFoundError: nothing at the address.
            DeviceInitError: it exists but cannot be opened (permissions, busy).
        """

    @abc.abstractmethod
    def close(self) -> None:
        """Close the pipe; closing twice is harmless."""

    @property
    @abc.abstractmethod
    def is_open(self) -> bool: ...

    @abc.abstractmethod
    def read(self, timeout: float) -> Chunk | None:
        """The next chunk of bytes, stamped on arrival, or ``None`` after ``timeout`` seconds.

        Raises:
            DeviceIOError: the pipe failed (unplugged, reset).
            EndOfStream: a finite source is exhausted.
        """

    def write(self, data: bytes) -> Chunk:
        """Send bytes to the device; returns the stamped TX chunk (for the session's raw log).

        Raises:
            DeviceIOError: the pipe failed.
        """
        raise ConfigError(f"{self.scheme}:// transports cannot send", source=self.url)

    def stamp_tx(self, data: bytes) -> Chunk:
        return Chunk(bytes(data), self.clock.now_ns(), Direction.TX)

    def __enter__(self) -> Transport:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def split_url(url: str) -> tuple[str, str, dict[str, str]]:
    """``scheme://address?k=v&...`` -> (scheme, address, options).

    Raises:
        ConfigError: not of that form, or a key given twice.
    """
    if "://" not in url:
        raise ConfigError(f"invalid transport URL {url!r}: expected SCHEME://ADDRESS[?key=value&...]", source=url)
    try:
        parts = urlsplit(url)
    except ValueError as exc:
        raise ConfigError(f"invalid transport URL {url!r}: {exc}; expected SCHEME://ADDRESS[?key=value&...]",
                          source=url) from None
    scheme = parts.scheme.lower()
    if not scheme or not scheme.replace("+", "").replace("-", "").isalnum():
        raise ConfigError(f"invalid transport URL {url!r}: expected SCHEME://ADDRESS[?key=value&...]", source=url)
    address = unquote(parts.netloc + parts.path)  # %20 and friends: paths with spaces, '#', '?' or '%'
    if parts.fragment:
        address += "#" + unquote(parts.fragment)
    opts: dict[str, str] = {}
    try:
        pairs = parse_qsl(parts.query, keep_blank_values=True, strict_parsing=bool(parts.query))
    except ValueError:
        raise ConfigError(f"invalid options in {url!r}: expected ?key=value&key=value", source=url) from None
    for k, v in pairs:
        if k in opts:
            raise ConfigError(f"option {k!r} given twice in {url!r}", source=url)
        opts[k] = v
    return scheme, address, opts
