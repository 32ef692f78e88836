"""The phone puppet's inputs, as a :class:`PhoneTrack` (times, orientations in perfcap's Y-up world,
positions when known, touch changes): :func:`read_trajectory` reads a trajectory CSV
(``t,px,py,pz,qw,qx,qy,qz,touch``) and :func:`session_track` a recorded session's phone streams;
:meth:`PhoneTrack.resample` turns either into input frames at a fixed rate (linear positions, slerped
orientations, the touch state last set at or before each frame).

Phone orientation: the phone streams give the phone's attitude in a Z-up world (the W3C
deviceorientation angles alpha, beta, gamma (intrinsic Z-X'-Y'', degrees) in East-North-Up; Android's
orientation angles azimuth, pitch, roll (HyperIMU), turned into alpha, beta, gamma as Chromium does; the
quaternion of Android's rotation vector and iOS's CoreMotion attitude, Z vertical; perfcap's own
``<dev>/orientation``, ENU). They are turned into perfcap's world (Y up) by a -90 degree rotation about
X: up becomes +Y, north becomes -Z, east stays +X. A trajectory CSV is already in perfcap's world.
A phone without position is held at the retargeter's pivot (``PuppetConfig.pivot``).

Touch: a touch stream's rows have a ``phase`` (0 start, 1 move, 2 end, 3 cancel) and, on streams that
track several fingers (the built-in page), an ``id``; the phone is held while any touch is down. Without
touches (no touch stream, or one that recorded nothing) the phone counts as held throughout.

Nothing here reads the OS clock: time comes with the input (CSV seconds, bus times).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from capture.errors import ConfigError
from capture.quat import quat_mul, quat_slerp
from retarget.puppet import PhoneInput

if TYPE_CHECKING:
    from collections.abc import Sequence

    from capture.sample import StreamInfo
    from capture.session import SessionReader

__all__ = [
    "ATTITUDE_STREAMS",
    "EULER_ANDROID",
    "EULER_W3C",
    "TRAJECTORY_COLUMNS",
    "Z_UP_TO_Y_UP",
    "PhoneTrack",
    "TouchState",
    "attitude_quaternions",
    "check_rate",
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


class TouchState:
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
    st = TouchState()
    v = np.atleast_2d(np.asarray(values, np.float64))
    ids = v[:, i].tolist() if i is not None else [0.0] * len(v)
    held = np.array([st.apply(float(a), float(b)) for a, b in zip(v[:, p].tolist(), ids, strict=True)], bool)
    return np.asarray(t, np.float64), held


def unknown_touch_phases(values: np.ndarray, channels: Sequence[str] = ("phase", "id")) -> int:
    """How many touch rows have a phase other than 0-3 (ignored by :func:`touch_changes`).

    Raises:
        ConfigError: ``channels`` has no ``phase``.
    """
    p, _ = touch_columns(channels)
    phase = np.atleast_2d(np.asarray(values, np.float64))[:, p]
    return int((~np.isin(phase, (0.0, 1.0, 2.0, 3.0))).sum())


def _phone_device(reader: SessionReader, device: str | None) -> tuple[str, StreamInfo]:
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


def session_track(reader: SessionReader, device: str | None = None) -> PhoneTrack:
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

