"""Device kinds and the one-string device specification.

A device is named on the command line and in config by one string::

    [NAME=][KIND@]SCHEME://ADDRESS[?key=value&...]

e.g. ``wrist=witmotion@serial:///dev/ttyUSB0?baud=115200&rate=200`` or ``synth://imu?rate=200&seed=1``.
Query keys are split between the transport's options and the device kind's options; a key neither
knows is an error. ``KIND@`` may be left out when the transport implies the kind (simulators and
replays do). ``NAME`` defaults to the kind plus a number.
"""

from __future__ import annotations

import functools
import importlib
import re
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, Any

from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError, DeviceUnavailableError
from devices.base import Device, DeviceState
from devices.reader import DeviceReader, ReconnectPolicy
from devices.transports import known_schemes, open_transport, split_url, transport_class

if TYPE_CHECKING:
    from collections.abc import Mapping

#: kind -> (module, class). Out-of-tree kinds use the ``perfcap.devices`` entry-point group.
DEVICE_TYPES: dict[str, tuple[str, str]] = {
    "witmotion": ("devices.witmotion", "WitMotionImu"),
    "bno08x_rvc": ("devices.bno08x", "Bno08xRvcImu"),
    "textline": ("devices.textline", "TextLineImu"),
    "hid": ("devices.hid.generic", "GenericHid"),
    "evdev": ("devices.evdev", "EvdevInput"),
    "ds4": ("devices.hid.sony", "DualShock4"),
    "dualsense": ("devices.hid.sony", "DualSense"),
    "switchpro": ("devices.hid.nintendo", "SwitchPro"),
    "joycon": ("devices.hid.nintendo", "JoyCon"),
    "phone": ("devices.phone", "PhonePage"),
    "sensorlogger": ("devices.phone", "SensorLoggerPhone"),
    "osc": ("devices.phone_apps.osc", "OscPhone"),
    "hyperimu": ("devices.phone_apps.hyperimu", "HyperImuPhone"),
    "sensorserver": ("devices.phone_apps.sensorserver", "SensorServerPhone"),
    "lsl": ("devices.lsl", "LslInlet"),
}

SPEC_FORM = "[NAME=][KIND@]SCHEME://ADDRESS[?key=value&...]"
SPEC_EXAMPLE = "wrist=witmotion@synth://imu?rate=200&seed=1"
_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_\-]{0,63}$")
_KIND_RE = re.compile(r"^[a-z][a-z0-9_]*$")


@functools.lru_cache(maxsize=1)
def _device_entry_points() -> dict[str, Any]:
    return {ep.name: ep for ep in entry_points(group="perfcap.devices")}


def known_kinds() -> list[str]:
    return sorted(set(DEVICE_TYPES) | set(_device_entry_points()))


def device_class(kind: str) -> type[Device]:
    """The Device subclass for ``kind``.

    Raises:
        DeviceUnavailableError: unknown kind, its module cannot be imported, or what it names is not
            a Device subclass.
    """
    ep = None if kind in DEVICE_TYPES else _device_entry_points().get(kind)
    if kind not in DEVICE_TYPES and ep is None:
        raise DeviceUnavailableError(f"unknown device kind {kind!r}; known kinds: {', '.join(known_kinds())}",
                                     source=kind)
    where = ":".join(DEVICE_TYPES[kind]) if ep is None else f"entry point {ep.value}"
    try:
        if ep is None:
            mod, name = DEVICE_TYPES[kind]
            obj = getattr(importlib.import_module(mod), name)
        else:
            obj = ep.load()
    except (ImportError, AttributeError) as exc:
        raise DeviceUnavailableError(f"device kind {kind!r} cannot be loaded from {where}: {exc}",
                                     source=kind) from exc
    if not (isinstance(obj, type) and issubclass(obj, Device)):
        raise DeviceUnavailableError(f"device kind {kind!r}: {where} is {obj!r}, not a Device subclass", source=kind)
    return obj


@dataclass
class DeviceSpec:
    """A parsed device string (or config entry)."""

    url: str
    kind: str | None = None
    name: str | None = None
    options: dict[str, Any] = field(default_factory=dict)

    def __str__(self) -> str:
        s = self.url
        if self.kind:
            s = f"{self.kind}@{s}"
        return f"{self.name}={s}" if self.name else s


def _bad(text: str, why: str) -> ConfigError:
    return ConfigError(f"invalid device {text!r}: {why}; expected {SPEC_FORM}, e.g. {SPEC_EXAMPLE}", source=text)


def parse_device_spec(text: str) -> DeviceSpec:
    """Parse ``[NAME=][KIND@]SCHEME://ADDRESS[?options]``.

    Raises:
        ConfigError: the string is not of that form.
    """
    if not isinstance(text, str) or not text.strip():
        raise _bad(str(text), "empty")
    s = text.strip()
    name = kind = None
    head, sep, _ = s.partition("://")
    if not sep:
        raise _bad(text, "no SCHEME://")
    if "=" in head:
        name, _, rest_head = head.partition("=")
        s = s[len(name) + 1:]
        head = rest_head
        if not _NAME_RE.match(name):
            raise _bad(text, f"name {name!r} must start with a letter and use letters, digits, _ or -")
    if "@" in head:
        kind, _, _ = head.partition("@")
        s = s[len(kind) + 1:]
        if not _KIND_RE.match(kind):
            raise _bad(text, f"kind {kind!r} is not a kind name (known: {', '.join(known_kinds())})")
    try:
        split_url(s)
    except ConfigError as exc:
        raise _bad(text, str(exc)) from None
    return DeviceSpec(url=s, kind=kind, name=name)


def open_device(spec: DeviceSpec | str, *, clock: Clock = MONOTONIC, taken_names: set[str] | None = None,
                strict: bool = False, extra_transport_options: Mapping[str, Any] | None = None) -> Device:
    """Build a Device (transport not yet opened) from a spec.

    Query options are given to the device kind if it declares them, otherwise to the transport.

    Raises:
        ConfigError: bad string or options.
        DeviceUnavailableError: unknown kind or scheme.
    """
    if isinstance(spec, str):
        spec = parse_device_spec(spec)
    scheme, address, query = split_url(spec.url)
    tcls = transport_class(scheme)
    kind = spec.kind
    # First build the transport with its own options only, to learn an implied kind.
    given = dict(query)
    for k, v in spec.options.items():
        if k in given:
            raise ConfigError(f"device {str(spec)!r}: option {k!r} is given both in the URL and in options",
                              source=str(spec))
        given[k] = v
    t_spec = {**tcls.options, **tcls.extra_options(address)}
    t_opts = {k: v for k, v in given.items() if k in t_spec}
    if extra_transport_options:
        t_opts.update(extra_transport_options)
    transport = tcls(address, t_opts, clock=clock)
    implied = transport.implied_kind()
    if kind is None:
        kind = implied
    if kind is None:
        raise ConfigError(f"device {str(spec)!r}: the kind is needed for {scheme}:// (write KIND@{spec.url});"
                          f" known kinds: {', '.join(known_kinds())}", source=str(spec))
    dcls = device_class(kind)
    d_opts: dict[str, Any] = dict(transport.implied_device_options())
    for k, v in given.items():
        if k in t_spec:
            continue
        if k in dcls.options:
            d_opts[k] = v
        else:
            known = sorted(set(t_spec) | set(dcls.options))
            raise ConfigError(f"device {str(spec)!r}: unknown option {k!r}; {kind}@{scheme}:// takes: "
                              f"{', '.join(known) or 'no options'} (form {SPEC_FORM})", source=str(spec))
    name = spec.name or transport.implied_name()
    taken = taken_names if taken_names is not None else set()
    if name is None:
        i = 0
        while f"{kind}{i}" in taken:
            i += 1
        name = f"{kind}{i}"
    if name in taken:
        raise ConfigError(f"device name {name!r} is used twice; give each device its own NAME=", source=name)
    taken.add(name)
    return dcls(name, transport, d_opts, clock=clock, strict=strict)


__all__ = ["DEVICE_TYPES", "Device", "DeviceReader", "DeviceSpec", "DeviceState", "ReconnectPolicy",
           "device_class", "known_kinds", "known_schemes", "open_device", "open_transport", "parse_device_spec"]
