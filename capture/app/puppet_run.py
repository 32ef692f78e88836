"""Driving the phone puppet: the wiring between phone input and ``retarget.puppet.PuppetRetargeter``.

What this module owns:

* the inputs, as a :class:`PhoneTrack` (times, orientations in perfcap's Y-up world, positions when
  known, touch changes): :func:`read_trajectory` reads a trajectory CSV (``t,px,py,pz,qw,qx,qy,qz,touch``)
  and :func:`session_track` a recorded session's phone streams; :meth:`PhoneTrack.resample` turns
  either into input frames at a fixed rate (linear positions, slerped orientations, the touch state
  last set at or before each frame);
* :class:`PuppetRun`: steps the retargeter, keeps the frames (a BVH ``Clip`` at the fixed rate), the
  state timeline and the time spent in each state, and sends each frame as VMC through a
  :class:`VmcSender` (UDP, send errors counted, never raised);
* :class:`PuppetFollower`: the bus subscriber that does the same live, stepping the retargeter on the
  fixed-rate grid of the phone's bus times as its attitude samples arrive.

Phone orientation: the phone streams give the phone's attitude in a Z-up world (the W3C
deviceorientation angles alpha, beta, gamma (intrinsic Z-X'-Y'', degrees) in East-North-Up; Android's
orientation angles azimuth, pitch, roll (HyperIMU), turned into alpha, beta, gamma as Chromium does; the
quaternion of Android's rotation vector and iOS's CoreMotion attitude, Z vertical; perfcap's own
``<dev>/orientation``, ENU). They are turned into perfcap's world (Y up) by a -90 degree rotation about
X: up becomes +Y, north becomes -Z, east stays +X. A trajectory CSV is already in perfcap's world.
A phone without position is held at the retargeter's pivot (``PuppetConfig.pivot``).

Touch: a touch stream's rows have a ``phase`` (0 start, 1 move, 2 end, 3 cancel) and, on streams that
track several fingers (the built-in page), an ``id``; the phone is held while any touch is down. Without touches (no touch stream, or one that recorded nothing) the
phone counts as held throughout.

Nothing here reads the OS clock: time comes with the input (CSV seconds, bus times).
"""

from __future__ import annotations

import csv
import logging
import math
import os
import socket
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from capture.bus import Subscriber
from capture.errors import ConfigError
from capture.quat import quat_conj, quat_mul, quat_rotate, quat_slerp
from capture.sample import Sample, SampleBatch, StreamInfo
from retarget.puppet import PhoneInput, PuppetFrame, PuppetRetargeter
from retarget.skeleton import Clip, Skeleton
from retarget.timeline import split_heading, yaw_quat
from retarget.vmc import VmcEncoder

log = logging.getLogger(__name__)

__all__ = [
    "ATTITUDE_STREAMS",
    "EULER_ANDROID",
    "EULER_W3C",
    "TRAJECTORY_COLUMNS",
    "Z_UP_TO_Y_UP",
    "PhoneTrack",
    "PuppetFollower",
    "PuppetRun",
    "VmcSender",
    "attitude_quaternions",
    "parse_host_port",
    "probe_writable",
    "read_trajectory",
    "session_track",
    "touch_changes",
    "touch_columns",
    "unknown_touch_phases",
]

#: The columns of a trajectory CSV (any order; a header line is required).
TRAJECTORY_COLUMNS = ("t", "px", "py", "pz", "qw", "qx", "qy", "qz", "touch")
#: A phone's orientation streams, by preference: the phone's own attitude, else perfcap's fusion.
ATTITUDE_STREAMS = ("attitude", "orientation")
#: Euler attitude channels: W3C deviceorientation, and Android's orientation angles.
EULER_W3C = ("alpha", "beta", "gamma")
EULER_ANDROID = ("azimuth", "pitch", "roll")
#: Z-up world (ENU) to perfcap's Y-up world: -90 degrees about X (w, x, y, z).
Z_UP_TO_Y_UP = np.array([math.sqrt(0.5), -math.sqrt(0.5), 0.0, 0.0])
#: Largest accepted deviation of a CSV quaternion's norm from 1 (rows are normalised).
UNIT_TOLERANCE = 0.01
#: A live sample this close before a frame time counts as at it (bus times are whole nanoseconds).
GRID_SLACK_NS = 1000
#: Highest --rate accepted, Hz.
MAX_RATE = 1000.0
#: Longest input driven, seconds (24 h): more is no performance, and its frames would not fit in memory.
MAX_SPAN_S = 24 * 3600.0
#: Largest accepted CSV position coordinate, metres.
MAX_POSITION = 1e5
#: A median step between samples from this long (seconds) to 1000 suggests times written in milliseconds.
MS_STEP_S = 5.0


def check_rate(rate: float) -> float:
    """The fixed frame rate, checked.

    Raises:
        ConfigError: not a finite rate in (0, 1000] Hz.
    """
    r = float(rate)
    if not (math.isfinite(r) and 0.0 < r <= MAX_RATE):
        raise ConfigError(f"--rate must be a frame rate in Hz between 0 and {MAX_RATE:g}, not {rate}")
    return r


# ------------------------------------------------------------------------------------------------ inputs
@dataclass(frozen=True, eq=False)
class PhoneTrack:
    """A phone's motion, ready to resample.

    Attributes:
        source: what it was read from (for messages).
        t: ``(N,)`` strictly increasing seconds.
        quaternions: ``(N, 4)`` unit (w, x, y, z), the phone in perfcap's world (Y up).
        positions: ``(N, 3)`` metres, or None for a phone that knows only its orientation.
        touch_t: ``(M,)`` non-decreasing seconds of touch changes.
        touch: ``(M,)`` the held state from ``touch_t[i]`` on (not held before the first).
        held_throughout: ignore ``touch``: the phone is held all along.
        notes: what a user should know about how the input was read.
    """

    source: str
    t: np.ndarray
    quaternions: np.ndarray
    positions: np.ndarray | None = None
    touch_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    touch: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    held_throughout: bool = False
    notes: tuple[str, ...] = ()

    @property
    def duration(self) -> float:
        """Seconds from the first sample to the last."""
        return float(self.t[-1]) - float(self.t[0]) if len(self.t) else 0.0   # Python floats: inf, no warning

    def frame_times(self, rate: float) -> np.ndarray:
        """The fixed-rate grid from the first sample to the last (inclusive where it falls on it).

        Raises:
            ConfigError: the input spans more than :data:`MAX_SPAN_S` (24 h of frames at ``rate``).
        """
        span = self.duration
        if not span <= MAX_SPAN_S:                        # also inf and nan
            ms = "; the times look like milliseconds: write them in seconds" if _looks_like_ms(self.t) else ""
            raise ConfigError(f"{self.source}: the input spans {span:g} s, {span * rate:.3g} frames at {rate:g} Hz;"
                              f" at most {MAX_SPAN_S / 3600:g} h ({MAX_SPAN_S * rate:.0f} frames) is driven{ms}")
        n = math.floor(span * rate + 1e-9) + 1
        return float(self.t[0]) + np.arange(n) / rate

    def resample(self, rate: float) -> list[PhoneInput]:
        """Input frames at ``rate`` Hz: linear positions, slerped orientations, touch as last set.

        Raises:
            ConfigError: a bad rate, or an input spanning more than 24 h.
        """
        rate = check_rate(rate)
        g = self.frame_times(rate)
        t = self.t
        if len(t) == 1:
            q = np.repeat(self.quaternions[:1], len(g), axis=0)
        else:
            i = np.clip(np.searchsorted(t, g, side="right") - 1, 0, len(t) - 2)
            frac = np.clip((g - t[i]) / (t[i + 1] - t[i]), 0.0, 1.0)
            q = quat_slerp(self.quaternions[i], self.quaternions[i + 1], frac)
        if self.positions is None:
            pos: np.ndarray | None = None
        else:
            pos = np.stack([np.interp(g, t, self.positions[:, k]) for k in range(3)], axis=1)
        if self.held_throughout:
            held = np.ones(len(g), bool)
        else:
            j = np.searchsorted(self.touch_t, g, side="right") - 1
            held = np.where(j >= 0, self.touch[np.maximum(j, 0)] if len(self.touch) else False, False)
        qs, gs, hs = q.tolist(), g.tolist(), held.tolist()
        ps = pos.tolist() if pos is not None else None
        return [PhoneInput(gs[k], tuple(qs[k]), bool(hs[k]), None if ps is None else tuple(ps[k]))
                for k in range(len(gs))]


def _median_step(t: np.ndarray) -> float:
    with np.errstate(over="ignore", invalid="ignore"):
        return float(np.median(np.diff(t))) if len(t) > 1 else 0.0


def _looks_like_ms(t: np.ndarray) -> bool:
    """Sample times whose median step is 5 to 1000 "seconds": a phone's milliseconds written as seconds."""
    return MS_STEP_S <= _median_step(t) <= 1000.0


def read_trajectory(path: str) -> PhoneTrack:
    """A trajectory CSV: a header with the columns ``t,px,py,pz,qw,qx,qy,qz,touch`` (any order), then
    one row per sample: seconds (strictly increasing), metres, the phone's unit quaternion in perfcap's
    world (Y up) and touch 0 or 1. Blank lines and lines starting with ``#`` are skipped. The position
    cells may be empty on every row: a phone that knows only its orientation. Positions are bounded
    (:data:`MAX_POSITION` metres).

    Raises:
        ConfigError: the file is missing or unreadable, or a row is malformed or out of range (with its
            line number).
    """
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            rows = [(reader.line_num, r) for r in reader]
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise ConfigError(f"{path} is a directory, not a trajectory CSV") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path} is not a text CSV file") from None
    except (OSError, csv.Error) as exc:
        raise ConfigError(f"cannot read {path}: {getattr(exc, 'strerror', None) or exc}") from None
    rows = [(n, r) for n, r in rows if r and any(c.strip() for c in r) and not r[0].lstrip().startswith("#")]
    expected = ",".join(TRAJECTORY_COLUMNS)
    if not rows:
        raise ConfigError(f"{path} is empty: expected a header {expected} and one row per sample")
    head_line, head = rows[0]
    names = [c.strip().lower() for c in head]
    while len(names) > len(TRAJECTORY_COLUMNS) and names[-1] == "":   # a trailing delimiter
        names.pop()
    if sorted(names) != sorted(TRAJECTORY_COLUMNS):
        raise ConfigError(f"{path} line {head_line}: the columns are {','.join(names)}; expected {expected}")
    col = [names.index(c) for c in TRAJECTORY_COLUMNS]
    body = rows[1:]
    if not body:
        raise ConfigError(f"{path}: a header and no samples")
    data = np.empty((len(body), len(TRAJECTORY_COLUMNS)))
    no_pos = np.zeros(len(body), bool)
    for r, (line, row) in enumerate(body):
        cells = [c.strip() for c in row]
        while len(cells) > len(names) and cells[-1] == "":
            cells.pop()
        if len(cells) != len(names):
            raise ConfigError(f"{path} line {line}: {len(cells)} fields where the header has {len(names)}")
        empty_pos = [cells[col[k]] == "" for k in (1, 2, 3)]
        if all(empty_pos):
            no_pos[r] = True
        for k, name in enumerate(TRAJECTORY_COLUMNS):
            cell = cells[col[k]]
            if k in (1, 2, 3) and all(empty_pos):
                data[r, k] = math.nan
                continue
            try:
                v = float(cell)
            except ValueError:
                raise ConfigError(f"{path} line {line}, column {name}: {cell!r} is not a number") from None
            if not math.isfinite(v):
                raise ConfigError(f"{path} line {line}, column {name}: {cell!r} is not a finite number")
            if k in (1, 2, 3) and abs(v) > MAX_POSITION:
                raise ConfigError(f"{path} line {line}, column {name}: {cell!r} m is out of range"
                                  f" (positions within +-{MAX_POSITION:g} m)")
            data[r, k] = v
        if data[r, 8] not in (0.0, 1.0):
            raise ConfigError(f"{path} line {line}, column touch: {cells[col[8]]!r}; expected 0 or 1")
        norm = float(np.linalg.norm(data[r, 4:8]))
        if norm < 1e-9:
            raise ConfigError(f"{path} line {line}: the quaternion (qw,qx,qy,qz) is zero")
        if abs(norm - 1.0) > UNIT_TOLERANCE:
            raise ConfigError(f"{path} line {line}: the quaternion (qw,qx,qy,qz) has norm {norm:.4g};"
                              " expected a unit quaternion")
        if r and not data[r, 0] > data[r - 1, 0]:
            raise ConfigError(f"{path} line {line}: time {data[r, 0]:g} s does not increase"
                              f" (the row before is at {data[r - 1, 0]:g} s)")
    if no_pos.any() and not no_pos.all():
        line = body[int(np.argmax(no_pos != no_pos[0]))][0]
        raise ConfigError(f"{path} line {line}: px,py,pz must be given on every row or left empty on every row")
    q = data[:, 4:8] / np.linalg.norm(data[:, 4:8], axis=1, keepdims=True)
    notes = ["no phone position (px,py,pz empty): the phone is held at a fixed pivot"] if no_pos.all() else []
    if _looks_like_ms(data[:, 0]):
        notes.append(f"the times step by a median {_median_step(data[:, 0]):g} s: if they are"
                     " milliseconds, write them in seconds")
    return PhoneTrack(path, data[:, 0].copy(), q, None if no_pos.all() else data[:, 1:4].copy(),
                      data[:, 0].copy(), data[:, 8] > 0.5, False, tuple(notes))


def attitude_quaternions(info: StreamInfo, values: np.ndarray) -> np.ndarray:
    """An attitude stream's rows as unit quaternions in perfcap's world (Y up); NaN rows where a value
    is missing (null) or the quaternion is zero.

    Args:
        info: the stream: kind ``euler`` or ``quat`` / ``orientation`` (channels w, x, y, z), in a Z-up
            world. The euler convention is chosen by the channel names: ``alpha, beta, gamma`` are W3C
            deviceorientation angles (intrinsic Z-X'-Y''); ``azimuth, pitch, roll`` are Android's
            (``SensorManager.getOrientation``: azimuth clockwise from north, pitch about -X), read as
            Chromium does for deviceorientation: alpha = -azimuth, beta = -pitch, gamma = roll. Degrees
            or radians by the stream's units.
        values: ``(n, channels)``.

    Raises:
        ConfigError: the stream is neither, or its euler channels name no known convention.
    """
    v = np.atleast_2d(np.asarray(values, np.float64))
    ch = list(info.channels)
    if info.kind == "euler" and len(ch) >= 3:
        names = tuple(c.lower() for c in ch[:3])
        if names == EULER_W3C:
            sign = np.array([1.0, 1.0, 1.0])
        elif names == EULER_ANDROID:
            sign = np.array([-1.0, -1.0, 1.0])
        else:
            raise ConfigError(f"stream {info.name}: euler angles {', '.join(ch[:3])} are of no known convention"
                              f" (expected {', '.join(EULER_W3C)} (W3C) or {', '.join(EULER_ANDROID)} (Android))")
        deg = all(u == "deg" for u in info.units[:3])
        ang = v[:, :3] * sign
        ok = np.all(np.isfinite(ang), axis=1)
        q = np.full((len(v), 4), np.nan)
        if ok.any():
            half = 0.5 * (np.radians(ang[ok]) if deg else ang[ok])
            c, s = np.cos(half), np.sin(half)
            z = np.zeros(len(half))
            qz = np.stack([c[:, 0], z, z, s[:, 0]], axis=1)     # alpha about Z
            qx = np.stack([c[:, 1], s[:, 1], z, z], axis=1)     # then beta about the new X
            qy = np.stack([c[:, 2], z, s[:, 2], z], axis=1)     # then gamma about the new Y
            q[ok] = quat_mul(quat_mul(qz, qx), qy)
    elif info.kind in ("quat", "orientation") and all(c in ch for c in ("w", "x", "y", "z")):
        q = v[:, [ch.index(c) for c in ("w", "x", "y", "z")]].copy()
        n = np.linalg.norm(q, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            q = np.where((n > 1e-9)[:, None], q / n[:, None], np.nan)
    else:
        raise ConfigError(f"stream {info.name} ({info.kind}: {', '.join(ch)}) is not an attitude"
                          " (euler alpha, beta, gamma or azimuth, pitch, roll, or a w, x, y, z quaternion)")
    return quat_mul(Z_UP_TO_Y_UP, q)


class _TouchState:
    """Which touches are down (by id), from touch rows (phase, id, ...); rows with a phase other than
    0-3 change nothing and are counted (``unknown``)."""

    def __init__(self) -> None:
        self.down: set[float] = set()
        self.unknown = 0

    def apply(self, phase: float, ident: float) -> bool:
        if phase in (0.0, 1.0):
            self.down.add(ident)
        elif phase in (2.0, 3.0):
            self.down.discard(ident)
        else:
            self.unknown += 1
        return bool(self.down)


def touch_columns(channels: Sequence[str]) -> tuple[int, int | None]:
    """Where a touch stream keeps its phase and its finger id (None: one finger only).

    Raises:
        ConfigError: no ``phase`` channel.
    """
    ch = list(channels)
    if "phase" not in ch:
        raise ConfigError(f"a touch stream needs a phase channel; its channels: {', '.join(ch)}")
    return ch.index("phase"), ch.index("id") if "id" in ch else None


def touch_changes(t: np.ndarray, values: np.ndarray, channels: Sequence[str] = ("phase", "id")
                  ) -> tuple[np.ndarray, np.ndarray]:
    """A touch stream's rows as (times, held after each row); a row whose phase is not 0-3 changes
    nothing (:func:`unknown_touch_phases` counts them).

    Raises:
        ConfigError: ``channels`` has no ``phase``.
    """
    p, i = touch_columns(channels)
    st = _TouchState()
    v = np.atleast_2d(np.asarray(values, np.float64))
    ids = v[:, i].tolist() if i is not None else [0.0] * len(v)
    held = np.array([st.apply(float(a), float(b)) for a, b in zip(v[:, p].tolist(), ids)], bool)
    return np.asarray(t, np.float64), held


def unknown_touch_phases(values: np.ndarray, channels: Sequence[str] = ("phase", "id")) -> int:
    """How many touch rows have a phase other than 0-3 (ignored by :func:`touch_changes`).

    Raises:
        ConfigError: ``channels`` has no ``phase``.
    """
    p, _ = touch_columns(channels)
    phase = np.atleast_2d(np.asarray(values, np.float64))[:, p]
    return int((~np.isin(phase, (0.0, 1.0, 2.0, 3.0))).sum())


def _phone_device(reader: Any, device: str | None) -> tuple[str, StreamInfo]:
    streams: dict[str, StreamInfo] = reader.streams
    found: dict[str, StreamInfo] = {}
    for name, info in streams.items():
        dev, _, leaf = name.rpartition("/")
        if leaf in ATTITUDE_STREAMS and dev and (dev not in found or leaf == ATTITUDE_STREAMS[0]):
            found[dev] = info
    if device is not None:
        if device not in found:
            raise ConfigError(f"{reader.path} has no attitude stream of a device {device!r}; phones with one: "
                              f"{', '.join(sorted(found)) or 'none'}")
        return device, found[device]
    if not found:
        listing = ", ".join(f"{n} ({s.kind})" for n, s in streams.items()) or "none"
        raise ConfigError(f"{reader.path} holds no phone attitude stream (<device>/attitude); its streams: {listing}")
    phones = [d for d, i in found.items() if i.name.endswith("/" + ATTITUDE_STREAMS[0])]
    if len(phones) == 1:                       # a phone beside IMUs with fused orientation
        return phones[0], found[phones[0]]
    if len(found) > 1:
        raise ConfigError(f"{reader.path} has several phones ({', '.join(sorted(found))}); choose one with --device")
    dev = next(iter(found))
    return dev, found[dev]


def session_track(reader: Any, device: str | None = None) -> PhoneTrack:
    """A recorded phone's motion: its attitude stream for orientation (no position: the retargeter holds
    it at a pivot) and its touch stream for the grab; times in seconds from the first attitude sample.

    Args:
        reader: a ``capture.session.SessionReader``.
        device: the phone's device name (default: the only device with an attitude stream).

    Raises:
        ConfigError: no (or an ambiguous) phone, or no usable attitude samples.
    """
    dev, info = _phone_device(reader, device)
    b = reader.samples(info.name)
    q = attitude_quaternions(info, b.values) if len(b.t_bus_ns) else np.zeros((0, 4))
    tb = np.asarray(b.t_bus_ns, np.int64)
    keep = np.all(np.isfinite(q), axis=1)
    tb, q = tb[keep], q[keep]
    if len(tb) == 0:
        raise ConfigError(f"{reader.path}: {info.name} holds no usable attitude samples")
    # strictly increasing times (a repeated bus time adds nothing to interpolate)
    inc = np.concatenate([[True], tb[1:] > np.maximum.accumulate(tb)[:-1]])
    tb, q = tb[inc], q[inc]
    origin = int(tb[0])
    notes = [f"orientation from {info.name} ({info.kind}), no position: the phone is held at a fixed pivot"]
    dropped = int((~keep).sum())
    if dropped:
        notes.append(f"{dropped} attitude sample(s) without values skipped")
    unordered = int((~inc).sum())
    if unordered:
        notes.append(f"{unordered} attitude sample(s) out of order or at a repeated time skipped")
    touch_name = f"{dev}/touch"
    tt, th = np.zeros(0), np.zeros(0, bool)
    held_throughout = True
    if touch_name in reader.streams:
        tbt = reader.samples(touch_name)
        if len(tbt.t_bus_ns):
            order = np.argsort(np.asarray(tbt.t_bus_ns, np.int64), kind="stable")
            tt, th = touch_changes((np.asarray(tbt.t_bus_ns, np.int64)[order] - origin) / 1e9,
                                   np.asarray(tbt.values)[order], reader.streams[touch_name].channels)
            held_throughout = False
            unknown = unknown_touch_phases(tbt.values, reader.streams[touch_name].channels)
            if unknown:
                notes.append(f"{unknown} touch row(s) of {touch_name} with a phase other than 0-3 (start, move,"
                             " end, cancel) ignored")
    if held_throughout:
        notes.append(f"no touches recorded ({touch_name} {'is empty' if touch_name in reader.streams else 'absent'}):"
                     " the phone counts as held throughout")
    return PhoneTrack(f"{reader.path} {info.name}", (tb - origin) / 1e9, q, None, tt, th, held_throughout,
                      tuple(notes))


# ------------------------------------------------------------------------------------------------ outputs
def probe_writable(path: str | None, flag: str) -> None:
    """Check before a performance that an output file can be written: it is opened for appending
    (created, and removed again, when it does not exist yet; an existing file is left as it is).

    Args:
        path: the output (None: nothing to check).
        flag: its option, for the message.

    Raises:
        ConfigError: it cannot be opened for writing.
    """
    if not path:
        return
    existed = os.path.lexists(path)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NONBLOCK, 0o666)
    except OSError as exc:
        raise ConfigError(f"{flag} {path}: cannot write it ({exc.strerror or exc})") from None
    os.close(fd)
    if not existed:
        try:
            os.remove(path)
        except OSError:
            log.debug("could not remove the probe of %s", path)


def parse_host_port(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[v6]:PORT`` for IPv6) as (host, port); the port in ASCII digits.

    Raises:
        ConfigError: not of that form.
    """
    s = str(text).strip()
    host, sep, port = s.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    digits = port.isascii() and port.isdigit()          # isdigit alone takes '²' and '٣'
    if not sep or not host or not digits or not 0 < int(port) < 65536 or (":" in host and "[" not in s):
        raise ConfigError(f"--vmc expects HOST:PORT (e.g. 127.0.0.1:39539), not {text!r}")
    return host, int(port)


class VmcSender:
    """One VMC bundle per frame over UDP to ``HOST:PORT`` (``retarget.vmc.VmcEncoder``): the skeleton's
    joints that have a Unity name, local positions = the skeleton's offsets, local rotations = the
    frame's. The root is the character's ground point: the hips' position at height 0 and the heading
    (yaw about +Y) of their rotation; the hips (joint 0) are sent relative to it (the rest of their
    rotation, and their height), so a receiver composing root and hips turns the character once. Send
    errors are counted (and the first logged), never raised.

    Args:
        target: ``HOST:PORT``.
        skeleton: the character.

    Raises:
        ConfigError: a malformed target, or a host that does not resolve.
    """

    def __init__(self, target: str, skeleton: Skeleton) -> None:
        self.target = target
        host, port = parse_host_port(target)
        try:
            info = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        except (socket.gaierror, UnicodeError) as exc:
            raise ConfigError(f"--vmc {target}: cannot resolve {host!r} ({exc})") from None
        family, _, _, _, addr = info[0]
        self.address = addr
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        unity = skeleton.unity_names
        self.index = [i for i, n in enumerate(skeleton.names) if n in unity]
        self.names = [unity[skeleton.names[i]] for i in self.index]
        self.local_pos = np.asarray(skeleton.offsets, np.float64)[self.index]
        self.hips_offset = np.asarray(skeleton.offsets[0], np.float64)
        self.encoder = VmcEncoder(self.names)
        self.sent = 0
        self.errors = 0
        self.first_error: str | None = None

    def root_and_hips(self, frame: PuppetFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The frame's root (position, rotation) and the hips relative to it (position, rotation).

        Raises:
            ValueError: a frame without finite hips.
        """
        q_hips = np.asarray(frame.rotations[0], np.float64)
        p_hips = np.asarray(frame.root_pos, np.float64) + self.hips_offset
        if not (np.isfinite(q_hips).all() and np.isfinite(p_hips).all()):
            raise ValueError("a VMC frame needs finite values")
        heading, tilt = split_heading(q_hips)             # q_hips = yaw(heading) * tilt
        root_rot = yaw_quat(float(heading))
        root_pos = np.array([p_hips[0], 0.0, p_hips[2]])
        return root_pos, root_rot, quat_rotate(quat_conj(root_rot), p_hips - root_pos), tilt

    def send(self, frame: PuppetFrame) -> bool:
        """Send one frame; False (counted) when it could not be encoded or sent."""
        try:
            root_pos, root_rot, hips_pos, hips_rot = self.root_and_hips(frame)
            local_pos, local_rot = self.local_pos, frame.rotations[self.index]
            if self.index and self.index[0] == 0:
                local_pos, local_rot = local_pos.copy(), np.array(local_rot, np.float64)
                local_pos[0], local_rot[0] = hips_pos, hips_rot
            else:                                         # no hips bone: the root carries their pose
                root_pos, root_rot = root_pos + quat_rotate(root_rot, hips_pos), quat_mul(root_rot, hips_rot)
            data = self.encoder.encode(local_pos, local_rot, root_pos, root_rot, frame.t)
            self.sock.sendto(data, self.address)
        except (OSError, ValueError) as exc:
            self.errors += 1
            if self.first_error is None:
                self.first_error = f"{type(exc).__name__}: {exc}"
                log.warning("VMC to %s: %s (further errors are counted)", self.target, self.first_error)
            return False
        self.sent += 1
        return True

    def close(self) -> None:
        self.sock.close()


class PuppetRun:
    """A performance: input frames through the retargeter, with what the outputs need.

    Args:
        retargeter: the retargeter (default: a new ``PuppetRetargeter()``).
        rate: the fixed frame rate the inputs come at (the BVH's fps).
        vmc: where each frame is sent, if anywhere.
        keep_frames: keep the poses (for :meth:`clip`).

    Raises:
        ConfigError: a bad rate.
    """

    def __init__(self, retargeter: PuppetRetargeter | None = None, *, rate: float = 60.0,
                 vmc: VmcSender | None = None, keep_frames: bool = True) -> None:
        self.retargeter = retargeter or PuppetRetargeter()
        self.rate = check_rate(rate)
        self.vmc = vmc
        self.keep_frames = keep_frames
        self.frames = 0
        self.t0: float | None = None
        self.t_last: float | None = None
        self._root: list[np.ndarray] = []
        self._rot: list[np.ndarray] = []
        self._timeline: list[list[Any]] = []   # [t, state name]
        self._before_first = False

    def step(self, inp: PhoneInput) -> PuppetFrame:
        """One input frame.

        Raises:
            ValueError: as ``PuppetRetargeter.step`` (time going backwards, a non-finite input).
        """
        frame = self.retargeter.step(inp)
        if self.t0 is None:
            self.t0 = frame.t
            first = frame.transitions[0].from_state if frame.transitions else frame.state
            self._timeline.append([frame.t, first.name])
            self._before_first = True
        for tr in frame.transitions:
            if tr.from_state is not tr.to_state:
                self._change(frame.t if tr.t is None else float(tr.t), tr.to_state.name)
                self._before_first = False
        self._before_first = False
        self.t_last = frame.t
        self.frames += 1
        if self.keep_frames:
            self._root.append(np.array(frame.root_pos, np.float64))
            self._rot.append(np.array(frame.rotations, np.float64))
        if self.vmc is not None:
            self.vmc.send(frame)
        return frame

    def _change(self, t: float, state: str) -> None:
        tl = self._timeline
        t = max(t, tl[-1][0])
        if self._before_first and t - tl[0][0] < 1e-9:
            tl[0][1] = state                   # the state before the first frame is no part of the timeline
        else:
            tl.append([t, state])

    def run(self, inputs: Iterable[PhoneInput]) -> PuppetRun:
        """Step every input frame; returns self."""
        for inp in inputs:
            self.step(inp)
        return self

    @property
    def duration(self) -> float:
        """Seconds from the first frame to the last."""
        return 0.0 if self.t0 is None or self.t_last is None else self.t_last - self.t0

    def timeline(self) -> list[dict[str, Any]]:
        """The state changes, ``[{"t": seconds, "state": name}, ...]``, the first at the first frame."""
        return [{"t": round(float(t), 6), "state": s} for t, s in self._timeline]

    def state_times(self) -> dict[str, float]:
        """Seconds spent in each state (the last one until the last frame), in order of first visit."""
        out: dict[str, float] = {}
        tl = self._timeline
        for k, (t, s) in enumerate(tl):
            end = tl[k + 1][0] if k + 1 < len(tl) else (self.t_last if self.t_last is not None else t)
            out[s] = out.get(s, 0.0) + max(0.0, float(end) - float(t))
        return out

    def states_visited(self) -> list[str]:
        """State names in the order they were first entered."""
        return list(dict.fromkeys(s for _, s in self._timeline))

    def clip(self, name: str = "puppet") -> Clip:
        """The performance as a clip at the fixed rate (fps = rate).

        Raises:
            ValueError: no frames, or the frames were not kept.
        """
        if not self._root:
            raise ValueError("no frames to export" if self.keep_frames else "the frames were not kept")
        return Clip(name, self.retargeter.skeleton, self.rate, np.stack(self._root), np.stack(self._rot))


# ------------------------------------------------------------------------------------------------ live
class PuppetFollower(Subscriber):
    """Drives a :class:`PuppetRun` from a phone's live samples on the bus, and puts the poses back on it.

    Frames are stepped on a fixed-rate grid of bus time starting at the first attitude sample: each
    attitude sample steps every grid time up to its own, the orientation slerped from the sample before.
    Touch samples queue touch changes, applied at the first frame at or after their time.

    As a processor (``Capture.add_processor``) it publishes the pose stream ``<device>/puppet`` (kind
    ``pose``): one sample per frame at the frame's bus time, values the root position (``root.x/y/z``, m)
    then each joint's local rotation (``<joint>.w/x/y/z``), so recorders, dashboards and bridges get the
    character like any other stream.

    Args:
        device: the phone's device name.
        attitude: its attitude stream (``<device>/attitude``: euler or quat).
        run: where frames go.
        touch: its touch stream (``<device>/touch``), if it has one.
        hold: the phone counts as held throughout (touches ignored).

    Raises:
        ConfigError: ``attitude`` is not an attitude stream, or ``touch`` has no phase channel.
    """

    accepts = frozenset({Sample, SampleBatch})

    def __init__(self, device: str, attitude: StreamInfo, run: PuppetRun, *, touch: StreamInfo | None = None,
                 hold: bool = False) -> None:
        attitude_quaternions(attitude, np.zeros((0, len(attitude.channels))))   # checks the stream
        self.device = device
        self.attitude = attitude
        self.touch_stream = touch.name if touch is not None else f"{device}/touch"
        self._phase_col, self._id_col = touch_columns(touch.channels if touch is not None else ("phase", "id"))
        self.run = run
        self.hold = hold
        self.period_ns = 1e9 / run.rate
        self.origin_ns: int | None = None
        self.next_k = 0
        self._prev: tuple[int, np.ndarray] | None = None
        self._touch = _TouchState()
        self._pending: deque[tuple[int, float, float]] = deque()
        self._held = False
        self.samples = 0
        self.touches = 0
        self.skipped = 0
        self.errors = 0
        self.first_error: str | None = None
        sk = run.retargeter.skeleton
        channels = ("root.x", "root.y", "root.z", *(f"{j}.{c}" for j in sk.names for c in "wxyz"))
        self.pose = StreamInfo(f"{device}/puppet", "pose", channels, ("m",) * 3 + ("1",) * (4 * sk.n_joints),
                               run.rate, attitude.device)
        self._publish: Any = None
        self.published = 0

    def output_streams(self) -> list[StreamInfo]:
        """The pose stream this follower publishes once bound (see the class)."""
        return [self.pose]

    def bind(self, publish: Any) -> None:
        """Set the bus's publish callable (``Capture.add_processor`` does)."""
        self._publish = publish
        self.publishes = True          # drained before the other subscribers when the bus closes

    @classmethod
    def for_device(cls, device: str, streams: Sequence[StreamInfo], run: PuppetRun, *,
                   hold: bool | None = None) -> PuppetFollower:
        """The follower of a device's streams; ``hold`` None: held throughout when it has no touch stream.

        Raises:
            ConfigError: the device has no attitude stream.
        """
        by_name = {s.name: s for s in streams}
        info = next((by_name[f"{device}/{leaf}"] for leaf in ATTITUDE_STREAMS if f"{device}/{leaf}" in by_name), None)
        if info is None:
            raise ConfigError(f"device {device} has no attitude stream ({device}/attitude) to drive the puppet;"
                              f" its streams: {', '.join(by_name) or 'none'}")
        touch = by_name.get(f"{device}/touch")
        return cls(device, info, run, touch=touch, hold=touch is None if hold is None else hold)

    @property
    def t_s(self) -> float:
        """Seconds of phone time followed so far."""
        return self.run.duration

    @property
    def unknown_touches(self) -> int:
        """Touch rows applied so far whose phase was not 0-3 (ignored)."""
        return self._touch.unknown

    def on_item(self, item: Any) -> None:
        stream = item.stream
        if stream == self.attitude.name:
            if type(item) is Sample:
                self._attitude(np.array([item.t_bus_ns], np.int64), np.array([item.values], np.float64))
            else:
                self._attitude(np.asarray(item.t_bus_ns, np.int64), np.asarray(item.values, np.float64))
        elif stream == self.touch_stream and not self.hold:
            if type(item) is Sample:
                rows: list[tuple[int, list[float]]] = [(int(item.t_bus_ns), list(item.values))]
            else:
                rows = list(zip(np.asarray(item.t_bus_ns).tolist(), np.asarray(item.values).tolist()))
            p, i = self._phase_col, self._id_col
            for t, v in rows:
                self._pending.append((int(t), float(v[p]), 0.0 if i is None else float(v[i])))
            self.touches += len(rows)

    def _attitude(self, t_ns: np.ndarray, values: np.ndarray) -> None:
        q = attitude_quaternions(self.attitude, values)
        for t, qi in zip(t_ns.tolist(), q):
            self.samples += 1
            if not np.all(np.isfinite(qi)) or (self._prev is not None and t <= self._prev[0]):
                self.skipped += 1
                continue
            if self.origin_ns is None:
                self.origin_ns = t
                self._frame(t, qi)
                self.next_k = 1
            else:
                t_prev, q_prev = self._prev  # type: ignore[misc]
                while True:
                    g = self.origin_ns + round(self.next_k * self.period_ns)
                    if g > t + GRID_SLACK_NS:
                        break
                    self._frame(g, quat_slerp(q_prev, qi, min(1.0, (g - t_prev) / (t - t_prev))))
                    self.next_k += 1
            self._prev = (t, qi)

    def _frame(self, g_ns: int, q: np.ndarray) -> None:
        pend = self._pending
        while pend and pend[0][0] <= g_ns:
            _, phase, ident = pend.popleft()
            self._held = self._touch.apply(phase, ident)
        assert self.origin_ns is not None
        inp = PhoneInput((g_ns - self.origin_ns) / 1e9, tuple(q.tolist()), self.hold or self._held, None)
        try:
            frame = self.run.step(inp)
        except ValueError as exc:
            self.on_error(exc)
            return
        if self._publish is not None:
            values = (*frame.root_pos.tolist(), *np.asarray(frame.rotations, np.float64).ravel().tolist())
            self._publish(Sample(self.pose.name, self.published, g_ns, None, g_ns, values))
            self.published += 1

    def on_error(self, exc: BaseException) -> None:
        self.errors += 1
        if self.first_error is None:
            self.first_error = f"{type(exc).__name__}: {exc}"
            log.warning("puppet follower on %s: %s (further errors are counted)", self.attitude.name,
                        self.first_error)
