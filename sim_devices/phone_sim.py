"""Message builders for the phone protocols: the built-in page and Sensor Logger's HTTP push.

Pure functions, no networking: they return the bytes a phone would send (built with the real
encoders of ``devices.codecs.phone_json``) together with the frames they encode, so tests and the
service's simulators can compare what comes out of the devices with what went in.

* ``page_hello``, ``page_pong`` and ``page_messages``: the page's messages; ``page_messages``
  synthesises a phone motion (``sim_devices.motion``: waving, or a puppeteer's) as devicemotion events at a given
  rate with jittered, coarsened ``event.timeStamp``s, batched every 50 ms like the page does, plus
  deviceorientation events and optionally a swipe of touches.
* ``dispel_samples`` and ``dispel_to_sensorlogger``: a real iPhone recording in the DISPEL /
  Konectom JSON format (``../shared/traces/e_smartphone/``: CoreMotion user acceleration and
  gravity in g, rotation rate in rad/s, ``ts`` epoch ms, 20 Hz) as Sensor Logger push bodies with
  the samples' real times (``time`` = ``ts`` * 1e6 ns).
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from capture.bounded_io import json_loads_bounded, read_bounded
from devices.codecs.phone_json import (
    PageCodec,
    PageData,
    PageHello,
    PagePong,
    SensorEntry,
    SensorLoggerCodec,
    SensorLoggerMessage,
)
from sim_devices.motion import G, phone_motion

if TYPE_CHECKING:
    from collections.abc import Sequence
    from pathlib import Path

_PAGE = PageCodec()
_SL = SensorLoggerCodec()

DEFAULT_UA = ("Mozilla/5.0 (Linux; Android 14; Pixel 8) AppleWebKit/537.36 (KHTML, like Gecko) "
              "Chrome/124.0.0.0 Mobile Safari/537.36")


# -- phone page -----------------------------------------------------------------------------------
class PageMessage(NamedTuple):
    """One page message: its bytes, the frame they encode and the page time it was sent (ms)."""

    data: bytes
    frame: PageData
    sent_ms: float


def page_hello(page_id: str = "sim-page-0001", platform: str = "android", ua: str = DEFAULT_UA,
               screen: tuple[float, float] | None = (412.0, 915.0), orient: float | None = 0.0,
               t: float | None = 0.0, token: str | None = None) -> bytes:
    """The page's hello (with ``token`` when given, as the page sends it; the host removes it)."""
    return _PAGE.encode(PageHello(page_id, platform, ua, screen, orient, t, 1, token))


def page_pong(h: int, t: float) -> bytes:
    """The page's answer to ``{"type":"ping","h":h}`` at page time ``t`` (ms)."""
    return _PAGE.encode(PagePong(h, t))


def _coarsen(t: np.ndarray, resolution_ms: float) -> np.ndarray:
    return np.round(t / resolution_ms) * resolution_ms if resolution_ms > 0 else t


def page_messages(duration_s: float, rate_hz: float = 60.0, *, batch_s: float = 0.05, seed: int = 1,
                  t0_ms: float = 1500.0, seq0: int = 0, jitter_ms: float = 0.3, resolution_ms: float = 0.005,
                  orientation_every: int = 3, touches: bool = False, invert_acc: bool = False,
                  null_acceleration: bool = False, motion: str = "waving") -> list[PageMessage]:
    """Synthetic page data messages: a phone motion (``sim_devices.motion.phone_motion``) as devicemotion
    events.

    Event ``k`` has ``timeStamp`` ``t0_ms + k * 1000 / rate_hz`` plus seeded jitter, rounded to
    ``resolution_ms`` (browsers coarsen it). Values: ``accelerationIncludingGravity`` = the specific
    force in m/s^2 (Android convention, +z when lying flat), ``acceleration`` = that minus gravity,
    ``rotationRate`` alpha/beta/gamma = the body rate about x/y/z in deg/s, ``interval`` the nominal
    period. Every ``orientation_every``-th event also gives a deviceorientation event (the motion's
    yaw, roll and pitch). The events of each ``batch_s`` window go out in one message, sent at the
    window's end, with ``seq`` counting from ``seq0``.

    Args:
        duration_s: how long the page streams.
        rate_hz: devicemotion rate.
        batch_s: message period (the page sends every ~50 ms).
        seed: motion and jitter seed.
        t0_ms: page time of the first event (ms since the page's time origin).
        seq0: ``seq`` of the first message.
        jitter_ms: uniform +- jitter of event times.
        resolution_ms: timestamp resolution.
        orientation_every: deviceorientation every n-th motion event (0: none).
        touches: add a one-finger swipe (start, moves, end) in the middle of the take.
        invert_acc: send both accelerations with the opposite sign (like old iOS Safari).
        null_acceleration: send ``acceleration`` as nulls (browsers without gravity separation).
        motion: ``waving`` (seeded free waving) or ``puppeteer`` (the puppet choreography).

    Returns:
        The messages in send order.
    """
    rnd = np.random.default_rng(seed)
    n = max(0, round(duration_s * rate_hz))
    period = 1000.0 / rate_hz
    t_ms = t0_ms + np.arange(n) * period + rnd.uniform(-jitter_ms, jitter_ms, n)
    t_ms = _coarsen(np.maximum.accumulate(t_ms), resolution_ms)
    acc_g, gyro_dps, eul = phone_motion(motion, seed).at_many((t_ms - t0_ms) / 1000.0)
    phi, theta = np.radians(eul[:, 0]), np.radians(eul[:, 1])
    grav = np.stack([-np.sin(theta), np.cos(theta) * np.sin(phi), np.cos(theta) * np.cos(phi)], axis=1) * G
    inc = acc_g * G
    user = inc - grav
    sign = -1.0 if invert_acc else 1.0
    user = np.full_like(user, np.nan) if null_acceleration else sign * user
    cols = np.column_stack([t_ms, user, sign * inc, gyro_dps, np.full(n, period)])
    motion_rows: list[tuple[float, ...]] = [tuple(r) for r in cols.tolist()]
    orientation: list[tuple[float, ...]] = []
    if orientation_every > 0:
        for k in range(0, n, orientation_every):
            alpha = float(eul[k, 2] % 360.0)
            orientation.append((float(t_ms[k]) + 0.5, alpha, float(eul[k, 0]), float(eul[k, 1]), 0.0))
    touch_rows: list[tuple[float, ...]] = []
    if touches and n > 4:
        k0 = n // 3
        steps = 6
        for j in range(steps + 1):
            phase = 0 if j == 0 else (2 if j == steps else 1)
            touch_rows.append((float(t_ms[k0 + j]) + 1.0, float(phase), 7.0, 100.0 + 30.0 * j, 400.0 - 10.0 * j,
                               0.0, 12.5, 12.5))
    rows: list[tuple[float, str, tuple[float, ...]]] = (
        [(r[0], "m", r) for r in motion_rows] + [(r[0], "o", r) for r in orientation]
        + [(r[0], "t", r) for r in touch_rows])
    out: list[PageMessage] = []
    if not rows:
        return out
    b = batch_s * 1000.0
    w0 = math.floor(t0_ms / b)
    groups: dict[int, dict[str, list[tuple[float, ...]]]] = {}
    for t, key, r in rows:
        groups.setdefault(math.floor(t / b) - w0, {"m": [], "o": [], "t": []})[key].append(r)
    seq = seq0
    for w in sorted(groups):
        g = groups[w]
        sent = float(_coarsen(np.array((w0 + w + 1) * b + 0.7), resolution_ms))
        frame = PageData(seq, sent, 0.0, *(tuple(sorted(g[k])) for k in ("m", "o", "t")))
        out.append(PageMessage(_PAGE.encode(frame), frame, sent))
        seq += 1
    return out


# -- DISPEL / Konectom iPhone recordings -----------------------------------------------------------
@dataclass
class DispelLevel:
    """One level (test part) of a DISPEL recording: accelerometer and gyroscope samples."""

    name: str
    acc_ts_ms: np.ndarray        # int64 (n,)
    user_acc_g: np.ndarray       # (n, 3) CoreMotion userAcceleration, g (iOS sign)
    gravity_g: np.ndarray        # (n, 3) CoreMotion gravity, g (iOS sign: toward the earth)
    gyro_ts_ms: np.ndarray       # int64 (m,)
    rotation_rad_s: np.ndarray   # (m, 3) CoreMotion rotationRate, rad/s
    begin_ms: int | None = None


@dataclass
class DispelRecording:
    levels: list[DispelLevel]
    device: dict[str, Any] = field(default_factory=dict)

    @property
    def n_acc(self) -> int:
        return sum(len(lv.acc_ts_ms) for lv in self.levels)

    @property
    def n_gyro(self) -> int:
        return sum(len(lv.gyro_ts_ms) for lv in self.levels)


def _measurements(sensor: dict[str, Any], keys: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    ts: list[int] = []
    vals: list[list[float]] = []
    for m in sensor["measurements"]:
        d = {v["name"]: v["value"] for v in m["values"]}
        ts.append(int(d["ts"]))
        vals.append([float(d[k]) for k in keys])
    return np.array(ts, np.int64), np.array(vals, np.float64).reshape(len(ts), len(keys))


MAX_DISPEL_BYTES = 64 << 20
MAX_DISPEL_DEPTH = 64


def dispel_samples(path: str | Path) -> DispelRecording:
    """The accelerometer and gyroscope samples of a DISPEL / Konectom JSON recording, per level.

    Raises:
        OSError: the file cannot be read.
        ValueError: it is not a DISPEL recording with accelerometer and gyroscope measurements, or it
            is not a regular file of at most ``MAX_DISPEL_BYTES`` nested at most ``MAX_DISPEL_DEPTH``.
    """
    # (the real recordings are 0.9 and 2.3 MB; InputLimitError is a ValueError)
    doc = json_loads_bounded(read_bounded(path, MAX_DISPEL_BYTES), MAX_DISPEL_BYTES, MAX_DISPEL_DEPTH)
    try:
        levels_in = doc["mobileEvaluationTest"]["levels"]
    except (KeyError, TypeError):
        raise ValueError(f"{path}: not a DISPEL recording (no mobileEvaluationTest.levels)") from None
    levels = []
    for i, lv in enumerate(levels_in):
        name = next((c.get("value") for c in lv.get("contexts", []) if c.get("name") == "levelType"), f"level{i}")
        sensors = {s["name"]: s for s in lv.get("sensors", [])}
        if "accelerometer" not in sensors or "gyroscope" not in sensors:
            raise ValueError(f"{path}: level {name} lacks accelerometer or gyroscope measurements")
        ats, av = _measurements(sensors["accelerometer"], ("userAccelerationX", "userAccelerationY",
                                                          "userAccelerationZ", "gravityX", "gravityY", "gravityZ"))
        gts, gv = _measurements(sensors["gyroscope"], ("x", "y", "z"))
        begin = lv.get("beginTimestamp")
        levels.append(DispelLevel(str(name), ats, av[:, :3], av[:, 3:], gts, gv,
                                  None if begin is None else int(begin)))
    return DispelRecording(levels, dict(doc.get("mobileDevice") or {}))


class PushMessage(NamedTuple):
    """One Sensor Logger push body, the message it encodes and the times of its first and last sample."""

    body: bytes
    message: SensorLoggerMessage
    t_first_ns: int
    t_last_ns: int


def dispel_to_sensorlogger(path: str | Path, batch_s: float = 0.5, *, standardised: bool = False,
                           session_id: str = "dispel-session", device_id: str = "dispel-iphone-x",
                           first_message_id: int = 0) -> list[PushMessage]:
    """A DISPEL iPhone recording as the Sensor Logger push messages an iPhone would have sent.

    Each sample gives an ``accelerometer`` entry (user acceleration, m/s^2), a ``gravity`` entry
    (m/s^2) and a ``gyroscope`` entry (rad/s), with ``time`` = ``ts`` ms * 1e6. The samples of each
    ``batch_s`` window of epoch time go in one message (windows without samples send nothing;
    ``messageId`` counts messages). Inside a message entries are grouped by sensor (all
    accelerometer entries, then gravity, then gyroscope), as per-sensor buffers would give, so the
    receiver must order them by time itself.

    Args:
        path: the DISPEL JSON file.
        batch_s: the app's push period.
        standardised: "Standardise Units & Frames" on (Android signs: accelerations negated from
            CoreMotion's); off (the app's default on iOS) sends CoreMotion's signs.
        session_id: ``sessionId`` of every message.
        device_id: ``deviceId`` of every message.
        first_message_id: ``messageId`` of the first message.

    Returns:
        The messages in send order.

    Raises:
        ValueError: ``batch_s`` is not positive, or the file is not a DISPEL recording.
    """
    if not batch_s > 0:
        raise ValueError(f"batch_s must be positive, not {batch_s!r}")
    rec = dispel_samples(path)
    s = -G if standardised else G
    entries: list[tuple[int, int, SensorEntry]] = []  # (window, sensor order, entry)
    w_ns = round(batch_s * 1e9)
    for lv in rec.levels:
        for ts, ua, gr in zip(lv.acc_ts_ms.tolist(), lv.user_acc_g.tolist(), lv.gravity_g.tolist(), strict=True):
            t = ts * 1_000_000
            entries.append((t // w_ns, 0, SensorEntry("accelerometer", t, tuple(x * s for x in ua))))
            entries.append((t // w_ns, 1, SensorEntry("gravity", t, tuple(x * s for x in gr))))
        for ts, r in zip(lv.gyro_ts_ms.tolist(), lv.rotation_rad_s.tolist(), strict=True):
            t = ts * 1_000_000
            entries.append((t // w_ns, 2, SensorEntry("gyroscope", t, tuple(r))))
    entries.sort(key=lambda x: (x[0], x[1], x[2].time))
    out: list[PushMessage] = []
    mid = first_message_id
    i = 0
    while i < len(entries):
        j = i
        w = entries[i][0]
        while j < len(entries) and entries[j][0] == w:
            j += 1
        batch = tuple(e for _, _, e in entries[i:j])
        msg = SensorLoggerMessage(mid, session_id, device_id, batch)
        times = [e.time for e in batch]
        out.append(PushMessage(_SL.encode(msg), msg, min(times), max(times)))
        mid += 1
        i = j
    return out


def synthetic_arrivals(t_last_ns: Sequence[int], *, seed: int = 5, host0_ns: int = 10**12, latency_ms: float = 25.0,
                       jitter_ms: float = 15.0, drift_ppm: float = 0.0) -> list[int]:
    """Host arrival times for messages whose newest sample is at ``t_last_ns`` (device ns): the
    device time mapped onto a host monotonic clock starting at ``host0_ns`` (with ``drift_ppm``),
    plus a constant ``latency_ms`` and seeded uniform jitter in ``[0, jitter_ms)``; never before
    the previous arrival (one connection delivers in order)."""
    rnd = random.Random(seed)
    d0 = t_last_ns[0] if t_last_ns else 0
    out: list[int] = []
    last = -(2**62)
    for t in t_last_ns:
        h = (host0_ns + round((t - d0) * (1.0 + drift_ppm * 1e-6))
             + round((latency_ms + rnd.uniform(0, jitter_ms)) * 1e6))
        h = max(h, last)
        out.append(h)
        last = h
    return out


__all__ = [
    "DEFAULT_UA",
    "DispelLevel",
    "DispelRecording",
    "PageMessage",
    "PushMessage",
    "dispel_samples",
    "dispel_to_sensorlogger",
    "page_hello",
    "page_messages",
    "page_pong",
    "synthetic_arrivals",
]
