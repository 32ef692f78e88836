"""Phone apps that send OSC over UDP: ZIG SIM, GyrOSC-style, or a custom address map (kind ``osc``).

This module owns what the OSC apps' values mean: the address maps, streams, units and signs. The
wire syntax is ``devices.codecs.osc``. None of these apps is in ``../shared/traces``; the layouts
follow ``docs/design/phone-protocols.md`` (section 1).

``OscPhone`` (kind ``osc``): one chunk is one UDP datagram (``OscCodec``). Option ``map`` picks the
address map:

* ``zigsim`` (default): ZIG SIM's ``[/ZIGSIM]/<uuid>/<command>``. ``accel`` is CoreMotion's user
  acceleration and ``gravity`` its gravity, both in g. They become ``user_acc`` and ``phone_gravity``
  (m/s^2), and ``imu`` ax..az = (accel + gravity) * 9.80665, the accelerometer's reading. ``gyro``
  (rad/s) becomes ``imu`` gx..gz. ``quaternion`` x, y, z, w becomes ``attitude`` w, x, y, z.
  ``touch<i>1``/``touch<i>2`` (x, y from -1 to 1 about the screen centre), ``touchradius<i>`` (px)
  and ``touchforce<i>`` become ``touch`` readings (slot, x, y, radius, force), one per slot. Slots
  are list positions and shift when a finger lifts; a slot with no messages has no finger on it.
  ``deviceinfo`` fills ``info``. Option ``uuid`` (empty: any) accepts only that ZIG SIM device UUID;
  other UUIDs are counted in ``health()["foreign_uuids"]`` and dropped.
* ``gyrosc``: ``<prefix>/rrate`` (rad/s) goes to ``imu`` gx..gz. ``<prefix>/accel`` (unit per
  ``accel_unit``, default g; taken to be the raw accelerometer with gravity) goes to ``imu`` ax..az.
  ``<prefix>/grav`` goes to ``phone_gravity``. ``<prefix>/quat`` goes to ``attitude`` w, x, y, z;
  its argument order is ``quat_order``, a permutation of ``wxyz`` (default ``wxyz``; receivers in the
  wild disagree). ``<prefix>/gyro`` (attitude pitch, roll, yaw in rad) goes to ``euler`` in degrees.
  ``prefix`` defaults to ``/gyrosc``.
* a custom map ``ADDRESS:STREAM:CHANNELS[:SCALE]`` entries joined by ``;``, e.g.
  ``map=/acc:imu:ax,ay,az:9.80665;/gyro:imu:gx,gy,gz``. ADDRESS is an exact OSC address
  (``/`` and letters, digits, ``_ . -``). STREAM is a stream name (lower case; ``imu``, ``acc``,
  ``user_acc``, ``phone_gravity``, ``gyro``, ``mag``, ``attitude``, ``euler`` and ``touch`` get
  their usual kind and units, any other name kind ``extra`` with unit ``1``). CHANNELS names one
  channel per OSC argument, in order (``_`` reads past an argument). ``imu`` takes ``ax ay az gx gy
  gz`` and ``attitude`` takes ``w x y z``. SCALE (default 1) multiplies the values into the
  stream's unit. Several addresses may feed one stream: their values of one datagram make one reading.

The presets' acceleration and gravity signs follow ``platform``. ``ios`` (default: ZIG SIM Pro
and GyrOSC are iOS apps) negates them, since CoreMotion reads -1 g on z lying flat, screen up.
``android`` takes them as sent. Either way perfcap's convention holds: +9.81 m/s^2 on z lying
flat, as an Android accelerometer reads. Check it at pairing (lay the phone flat).

The messages of one datagram form a snapshot: one reading per stream they touch, channels they
did not carry left NaN. A held value the app repeats is still a reading. If an address comes twice
in one datagram, the snapshot so far is emitted and a new one starts there. OSC carries no device
clock (ZIG SIM's bundle time tag is not set, and time tags are never waited for). So the streams
have ``clock=None`` and nominal rate ``rate``. The default is 60 Hz, ZIG SIM's highest message
rate and the one to use for capture; the app ships at 10 Hz, so set ``rate`` to the app's setting.
The pseudo clock dejitters the arrivals, and ``rate=0`` stamps readings at arrival. ``touch`` is
always irregular. Unmatched addresses are counted per address in ``health()["unmatched"]`` and
logged once each. A mapped message with the wrong number or type of arguments counts as a framing
error (``OscCodec.reject``), as a malformed datagram does.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError
from devices.base import Reading
from devices.codecs.osc import OscCodec, OscFrame, OscMsg
from devices.options import Option
from devices.phone_apps.base import (
    ACC_CHANNELS,
    ACC_UNITS,
    FRAME,
    G0,
    IMU_CHANNELS,
    IMU_UNITS,
    NAN,
    QUAT_CHANNELS,
    RESERVED_STREAMS,
    AppDevice,
    NameTally,
    StreamDecl,
)

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping

    from capture.sample import StreamInfo
    from devices.transports.base import Transport

log = logging.getLogger(__name__)

OSC_MAP_FORM = ("map=zigsim, map=gyrosc, or map=ADDRESS:STREAM:CHANNELS[:SCALE];... "
                "(e.g. map=/acc:imu:ax,ay,az:9.80665;/gyro:imu:gx,gy,gz)")
OSC_PRESETS = ("zigsim", "gyrosc")
OSC_MAX_ENTRIES = 64
_ADDRESS_RE = re.compile(r"^(/[A-Za-z0-9_.\-]+)+$")
_STREAM_RE = re.compile(r"^[a-z][a-z0-9_]{0,31}$")
_CHANNEL_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,31}$")
_UUID_RE = re.compile(r"^[-_0-9A-Za-z]{0,128}$")
_ZIGSIM_RE = re.compile(r"^(?:/ZIGSIM)?/([-_0-9A-Za-z]+)/([A-Za-z0-9_]+)$")

#: Options that only some maps take.
_PRESET_OPTIONS: dict[str, tuple[str, ...]] = {
    "uuid": ("zigsim",), "platform": ("zigsim", "gyrosc"), "prefix": ("gyrosc",), "accel_unit": ("gyrosc",),
    "quat_order": ("gyrosc",),
}

#: Streams a custom map may name, with their kind, unit and (for imu/attitude) fixed channels.
_CUSTOM_KINDS: dict[str, tuple[str, str, tuple[str, ...] | None]] = {
    "imu": ("imu", "", IMU_CHANNELS),
    "acc": ("acc", "m/s^2", None),
    "user_acc": ("acc", "m/s^2", None),
    "phone_gravity": ("acc", "m/s^2", None),
    "gyro": ("gyro", "rad/s", None),
    "mag": ("mag", "uT", None),
    "attitude": ("quat", "1", QUAT_CHANNELS),
    "euler": ("euler", "deg", None),
    "touch": ("touch", "1", None),
}

_TOUCH_DECL = StreamDecl("touch", "touch", ("slot", "x", "y", "radius", "force"), ("1", "1", "1", "px", "1"),
                    "ZIG SIM touch: slot = list position; x, y from -1 to 1 about the screen centre; radius px",
                    regular=False)


@dataclass(frozen=True)
class OscRoute:
    """Where one mapped address's arguments go.

    ``positions`` has one entry per argument: the channel it fills, or ``None`` to read past it.
    Touch routes (ZIG SIM) fill field ``field`` of slot ``slot`` of the touch stream instead.
    """

    key: str
    stream: int
    positions: tuple[int | None, ...]
    scale: float = 1.0
    slot: int | None = None
    field: int = 0


def parse_osc_map(text: str, where: str = "osc") -> list[tuple[str, str, tuple[str, ...], float]]:
    """Entries ``(address, stream, channels, scale)`` of a custom map (see the module docstring).

    Raises:
        ConfigError: the text is not of the form ``OSC_MAP_FORM``, with what is wrong.
    """
    def bad(why: str) -> ConfigError:
        return ConfigError(f"{where}: bad OSC map entry: {why}; expected {OSC_MAP_FORM}", source=where)

    entries: list[tuple[str, str, tuple[str, ...], float]] = []
    seen: set[str] = set()
    for raw in text.split(";"):
        e = raw.strip()
        if not e:
            continue
        parts = [p.strip() for p in e.split(":")]
        if not 3 <= len(parts) <= 4:
            raise bad(f"{e!r} has {len(parts)} ':'-separated parts, not 3 or 4")
        address, stream, chans = parts[:3]
        if not _ADDRESS_RE.match(address):
            raise bad(f"address {address!r} is not /name[/name...] (letters, digits, _ . -)")
        if address in seen:
            raise bad(f"address {address} is mapped twice")
        seen.add(address)
        if not _STREAM_RE.match(stream):
            raise bad(f"stream {stream!r} is not a lower-case name (a-z, 0-9, _)")
        if stream in RESERVED_STREAMS:
            raise bad(f"stream {stream!r} is reserved for the fusion processor's output")
        channels = tuple(c.strip() for c in chans.split(","))
        for c in channels:
            if c != "_" and not _CHANNEL_RE.match(c):
                raise bad(f"channel {c!r} is not a name (letters, digits, _) or _ to skip an argument")
        if all(c == "_" for c in channels):
            raise bad(f"{address} maps no channel")
        scale = 1.0
        if len(parts) == 4:
            try:
                scale = float(parts[3])
            except ValueError:
                raise bad(f"scale {parts[3]!r} is not a number") from None
            if not math.isfinite(scale) or scale == 0.0:
                raise bad(f"scale {parts[3]!r} must be a finite non-zero number")
        entries.append((address, stream, channels, scale))
        if len(entries) > OSC_MAX_ENTRIES:
            raise bad(f"more than {OSC_MAX_ENTRIES} entries")
    if not entries:
        raise bad("no entry")
    return entries


class OscLayout:
    """The address map of an ``OscPhone``: its streams and where each address goes.

    Args:
        opts: the resolved ``OscPhone`` options.
        given: the option keys the user gave (to refuse options of another map).
        where: names the device in error messages.

    Raises:
        ConfigError: a bad map, prefix, quaternion order or UUID, or an option of another map.
    """

    def __init__(self, opts: Mapping[str, Any], given: Iterable[str] = (), where: str = "osc") -> None:
        text = str(opts["map"]).strip()
        self.where = where
        self.preset = text if text in OSC_PRESETS else "custom"
        for k in sorted(set(given) & set(_PRESET_OPTIONS)):
            if self.preset not in _PRESET_OPTIONS[k]:
                raise ConfigError(f"{where}: option {k} applies to map={' or map='.join(_PRESET_OPTIONS[k])} only, "
                                  f"not to map={text[:60]}", source=where)
        self.uuid: str = str(opts["uuid"]).strip()
        if not _UUID_RE.match(self.uuid):
            raise ConfigError(f"{where}: uuid={self.uuid!r} is not a ZIG SIM device UUID (letters, digits, - _)",
                              source=where)
        sign = -1.0 if opts["platform"] == "ios" else 1.0
        #: the ZIG SIM device UUID of the last accepted message
        self.last_uuid: str | None = None
        self.exact: dict[str, OscRoute] = {}
        self.zig: dict[str, OscRoute] = {}
        self.derived_imu: tuple[int, int, int] | None = None  # (imu, user_acc, phone_gravity) for ZIG SIM
        if self.preset == "zigsim":
            self._zigsim(sign)
        elif self.preset == "gyrosc":
            self._gyrosc(opts, sign)
        else:
            self._custom(parse_osc_map(text, where))

    def _zigsim(self, sign: float) -> None:
        self.decls = [StreamDecl("imu", "imu", IMU_CHANNELS, IMU_UNITS),
                      StreamDecl("user_acc", "acc", ACC_CHANNELS, ACC_UNITS),
                      StreamDecl("phone_gravity", "acc", ACC_CHANNELS, ACC_UNITS),
                      StreamDecl("attitude", "quat", QUAT_CHANNELS, ("1",) * 4,
                            "CoreMotion attitude: phone frame relative to the reference frame set in the app"),
                      _TOUCH_DECL]
        imu, user, grav, att, touch = range(5)
        self.zig = {
            "accel": OscRoute("accel", user, (0, 1, 2), sign * G0),
            "gravity": OscRoute("gravity", grav, (0, 1, 2), sign * G0),
            "gyro": OscRoute("gyro", imu, (3, 4, 5)),
            "quaternion": OscRoute("quaternion", att, (1, 2, 3, 0)),  # x, y, z, w
        }
        for i in range(10):
            for key, field in ((f"touch{i}1", 0), (f"touch{i}2", 1), (f"touchradius{i}", 2), (f"touchforce{i}", 3)):
                self.zig[key] = OscRoute(key, touch, (0,), slot=i, field=field)
        self.derived_imu = (imu, user, grav)

    def _gyrosc(self, opts: Mapping[str, Any], sign: float) -> None:
        prefix = str(opts["prefix"]).strip().rstrip("/")
        if not _ADDRESS_RE.match(prefix):
            raise ConfigError(f"{self.where}: prefix={opts['prefix']!r} is not an OSC address like /gyrosc or "
                              "/gyrosc/phone1", source=self.where)
        order = str(opts["quat_order"]).strip().lower()
        if sorted(order) != ["w", "x", "y", "z"]:
            raise ConfigError(f"{self.where}: quat_order={opts['quat_order']!r} must be an order of the letters "
                              "w x y z, e.g. wxyz or xyzw", source=self.where)
        unit = G0 if opts["accel_unit"] == "g" else 1.0
        self.decls = [StreamDecl("imu", "imu", IMU_CHANNELS, IMU_UNITS),
                      StreamDecl("phone_gravity", "acc", ACC_CHANNELS, ACC_UNITS),
                      StreamDecl("attitude", "quat", QUAT_CHANNELS, ("1",) * 4,
                            "CoreMotion attitude: phone frame relative to the app's reference frame"),
                      StreamDecl("euler", "euler", ("pitch", "roll", "yaw"), ("deg",) * 3,
                            "CoreMotion attitude angles (pitch about x, roll about y, yaw about z)")]
        imu, grav, att, eul = range(4)
        for name, route in (("rrate", (imu, (3, 4, 5), 1.0)), ("accel", (imu, (0, 1, 2), sign * unit)),
                            ("grav", (grav, (0, 1, 2), sign * unit)),
                            ("quat", (att, tuple(QUAT_CHANNELS.index(c) for c in order), 1.0)),
                            ("gyro", (eul, (0, 1, 2), 180.0 / math.pi))):
            addr = f"{prefix}/{name}"
            self.exact[addr] = OscRoute(addr, *route)

    def _custom(self, entries: list[tuple[str, str, tuple[str, ...], float]]) -> None:
        names: list[str] = []
        chans: dict[str, list[str]] = {}
        for _, stream, _channels, _ in entries:
            if stream not in chans:
                names.append(stream)
                fixed = _CUSTOM_KINDS.get(stream, ("extra", "1", None))[2]
                chans[stream] = list(fixed) if fixed else []
        owner: dict[tuple[str, str], str] = {}
        for address, stream, channels, _ in entries:
            fixed = _CUSTOM_KINDS.get(stream, ("extra", "1", None))[2]
            for c in channels:
                if c == "_":
                    continue
                if fixed and c not in fixed:
                    raise ConfigError(f"{self.where}: stream {stream} takes channels {' '.join(fixed)}, not {c!r};"
                                      f" expected {OSC_MAP_FORM}", source=self.where)
                if (stream, c) in owner:
                    raise ConfigError(f"{self.where}: channel {stream}.{c} is fed by both {owner[stream, c]} and "
                                      f"{address}", source=self.where)
                owner[stream, c] = address
                if c not in chans[stream]:
                    chans[stream].append(c)
        self.decls = []
        for s in names:
            kind, unit, _ = _CUSTOM_KINDS.get(s, ("extra", "1", None))
            ch = tuple(chans[s])
            units = IMU_UNITS if s == "imu" else (unit,) * len(ch)
            self.decls.append(StreamDecl(s, kind, ch, units, FRAME if kind in ("imu", "acc", "gyro", "mag") else None,
                                    regular=kind != "touch"))
        for address, stream, channels, scale in entries:
            si = names.index(stream)
            ch = self.decls[si].channels
            self.exact[address] = OscRoute(address, si, tuple(None if c == "_" else ch.index(c) for c in channels),
                                           scale)

    def route(self, address: str) -> tuple[OscRoute | None, str | None]:
        """``(route, None)`` for a mapped address; ``(None, uuid)`` for a ZIG SIM address of another
        device; ``(None, None)`` for an address the map does not know."""
        r = self.exact.get(address)
        if r is not None or self.preset != "zigsim":
            return r, None
        m = _ZIGSIM_RE.match(address)
        if m is None:
            return None, None
        uuid, cmd = m.groups()
        if self.uuid and uuid != self.uuid:
            return None, uuid
        self.last_uuid = uuid
        return self.zig.get(cmd), None


def zigsim_uuid(frame: OscFrame) -> str | None:
    """The ZIG SIM device UUID of a decoded datagram (its first ZIG SIM-shaped address), or None.

    For a receiver that routes datagrams by (source address, UUID) before they reach a device. Any
    two-level address ``/a/b`` is ZIG SIM-shaped (``a`` is the UUID), so use it for ZIG SIM ports only.
    """
    for m in frame.messages:
        hit = _ZIGSIM_RE.match(m.address)
        if hit is not None:
            return hit.group(1)
    return None


class OscPhone(AppDevice[OscCodec]):
    """A phone app sending OSC over UDP: ZIG SIM, GyrOSC-style, or a custom address map."""

    kind = "osc"
    description = "phone app sending OSC over UDP (ZIG SIM, GyrOSC-style, or a custom address map)"
    codec_cls = OscCodec
    options: ClassVar[dict[str, Option]] = {
        "map": Option(str, "zigsim", "address map: zigsim, gyrosc, or ADDRESS:STREAM:CHANNELS[:SCALE];... "
                      "(e.g. /acc:imu:ax,ay,az:9.80665;/gyro:imu:gx,gy,gz)"),
        "uuid": Option(str, "", "zigsim: the device UUID to accept (empty: any)"),
        "prefix": Option(str, "/gyrosc", "gyrosc: the address prefix set in the app"),
        "accel_unit": Option(str, "g", "gyrosc: unit of /accel and /grav", choices=("g", "m/s^2")),
        "quat_order": Option(str, "wxyz", "gyrosc: order of /quat's arguments (a permutation of wxyz)"),
        "platform": Option(str, "ios", "presets: ios negates acceleration and gravity (CoreMotion's sign), android "
                           "takes them as sent; lying flat, screen up must read +z", choices=("ios", "android")),
        "rate": Option(float, 60.0, "the app's message rate, Hz (ZIG SIM: 1, 10, 30 or 60); 0 = unknown, readings "
                       "stamped at arrival", min=0.0, max=1000.0),
    }

    def __init__(self, name: str, transport: Transport, options: Mapping[str, Any] | None = None,
                 clock: Clock = MONOTONIC, strict: bool = False) -> None:
        super().__init__(name, transport, options, clock, strict)
        #: what the app said about itself (ZIG SIM deviceinfo; the last ZIG SIM UUID seen)
        self.info: dict[str, Any] = {}
        self.unmatched = NameTally()
        self.foreign_uuids = NameTally()
        self.bad_args = 0
        self.snapshots = 0

    def declare_streams(self) -> list[StreamInfo]:
        self.layout = OscLayout(self.opts, self._given_options, f"device {self.name} (osc)")
        rate = self.opts["rate"] or None
        return self._declare(self.layout.decls, rate, None)

    def frame_to_readings(self, frame: OscFrame) -> Iterable[Reading]:
        out: list[Reading] = []
        snap: dict[str, tuple[OscRoute, tuple[float, ...]]] = {}
        lay = self.layout
        for m in frame.messages:
            route, foreign = lay.route(m.address)
            if route is None:
                self._unmatched(m, foreign)
                continue
            vals = self._values(route, m)
            if vals is None:
                continue
            if route.key in snap:
                self._finish(snap, out)
                snap = {}
            snap[route.key] = (route, vals)
        if snap:
            self._finish(snap, out)
        return out

    def _unmatched(self, m: OscMsg, foreign: str | None) -> None:
        if foreign is not None:
            if self.foreign_uuids.add(foreign):
                log.warning("osc %s: ZIG SIM device %s is not the one configured (uuid=%s); its messages are "
                            "dropped (counted)", self.name, foreign, self.layout.uuid)
            return
        address = m.address
        if self.layout.preset == "zigsim" and address.endswith("/deviceinfo") and self.layout.last_uuid is not None \
                and _ZIGSIM_RE.match(address):
            # name, uuid, os, os version, screen width and height (px)
            keys = ("name", "uuid", "os", "osversion", "width", "height")
            self.info.update({k: str(a)[:128] for k, a in zip(keys, m.args, strict=False)})
            return
        if self.unmatched.add(address[:128]):
            log.info("osc %s: address %s is not in map %s; ignored (counted in health()['unmatched'])",
                     self.name, address[:128], self.layout.preset)

    def _values(self, route: OscRoute, m: OscMsg) -> tuple[float, ...] | None:
        """The arguments as floats (NaN where read past), or None (counted) if they do not fit."""
        n = len(route.positions)
        args = m.args
        ok = len(args) == n and all(
            p is None or ((type(a) is float or type(a) is int) and math.isfinite(a))
            for p, a in zip(route.positions, args, strict=True))
        if not ok:
            self.bad_args += 1
            self.codec.reject(f"{m.address} needs {n} finite number(s), got {len(args)} argument(s) "
                                  f"{tuple(type(a).__name__ for a in args[:8])}; message dropped")
            return None
        return tuple(NAN if p is None else float(a) for p, a in zip(route.positions, args, strict=True))

    def _finish(self, snap: Mapping[str, tuple[OscRoute, tuple[float, ...]]], out: list[Reading]) -> None:
        """Readings of one snapshot, in stream order (touch slots in slot order)."""
        self.snapshots += 1
        rows: dict[int, list[float]] = {}
        touches: dict[int, list[float]] = {}
        touch_stream = -1
        for route, vals in snap.values():
            if route.slot is not None:
                touch_stream = route.stream
                touches.setdefault(route.slot, [NAN] * 4)[route.field] = vals[0]
                continue
            row = rows.get(route.stream)
            if row is None:
                row = rows[route.stream] = [NAN] * len(self.streams[route.stream].channels)
            k = route.scale
            for p, v in zip(route.positions, vals, strict=True):
                if p is not None:
                    row[p] = v * k
        if self.layout.derived_imu is not None:
            imu, user, grav = self.layout.derived_imu
            if user in rows and grav in rows:
                row = rows.setdefault(imu, [NAN] * 6)
                u, g = rows[user], rows[grav]
                row[0:3] = [u[0] + g[0], u[1] + g[1], u[2] + g[2]]
        for si in sorted(rows):
            out.append(Reading(si, tuple(rows[si])))
        for slot in sorted(touches):
            out.append(Reading(touch_stream, (float(slot), *touches[slot])))

    def health(self) -> dict[str, Any]:
        """Base counters plus ``snapshots``, ``unmatched`` (per address), ``foreign_uuids`` (ZIG SIM
        messages of other devices) and ``bad_args`` (mapped messages with unusable arguments)."""
        h = super().health()
        h.update(snapshots=self.snapshots, unmatched=dict(self.unmatched.counts),
                 unmatched_messages=self.unmatched.total, foreign_uuids=dict(self.foreign_uuids.counts),
                 bad_args=self.bad_args, info=dict(self.info), uuid=self.layout.last_uuid)
        return h


__all__ = ["OSC_MAP_FORM", "OSC_PRESETS", "OscLayout", "OscPhone", "OscRoute", "parse_osc_map", "zigsim_uuid"]
