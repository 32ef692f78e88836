"""``synth://`` - synthetic devices that encode generated motion through a real codec and deliver
the bytes through the Transport interface, with the timing faults real links have.

``synth://imu?rate=200&seed=1`` is a WitMotion WT901 waving on a wrist; with ``loop_s=1.2`` the
wrist repeats one gesture, each loop 1.2 s +- ``loop_jitter`` (8 %) long (a performance to extract a
cycle from; ``transport.motion.mean_loop_s(d0, d1)`` is the truth);
``synth://imu?csv=PATH`` plays a recorded IMU CSV instead (x-io/Fusion layout: time in s, gyroscope
x/y/z in deg/s, accelerometer x/y/z in g), at the recording's own timestamps, gaps included. Options model the link:
device clock drift, fixed latency, arrival jitter, FTDI-style bursts, garbage bytes, an unplug
window and a device clock reset. With ``realtime=false`` it runs on a virtual host clock as fast
as the reader asks (deterministic, for CI); ``truth=true`` keeps the true host time of every
reading so tests can measure clock-sync error end to end. What the simulator knows of the truth
(``truth_ns``, ``latency_ns``, ``drift_ppm``, ``motion``) is its ``SimulatorTruth`` ability
(``devices.transports.base``).
"""

from __future__ import annotations

import io
import warnings
from collections import deque
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from capture.bounded_io import InputLimitError, longest_line, read_bounded
from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError, DeviceIOError, DeviceNotFoundError, EndOfStream
from capture.sample import Chunk
from devices.codecs.witmotion import WitMotionCodec
from devices.options import Option
from devices.transports.base import Transport
from sim_devices.frames import witmotion_wire
from sim_devices.motion import WavingMotion

if TYPE_CHECKING:
    from collections.abc import Mapping

    from devices.transports.base import SimulatorTruth

KINDS = {"imu": "witmotion"}


class SynthTransport(Transport):
    """Synthetic device bytes; see the module docstring. It is a ``SimulatorTruth``."""

    scheme = "synth"
    usage = "synth://imu?rate=HZ&seed=N"
    options: ClassVar[dict[str, Option]] = {
        "rate": Option(float, 200.0, "readings per second", min=1.0, max=2000.0),
        "seed": Option(int, 1, "motion and noise seed", min=0),
        "device_clock": Option(bool, True, "send time packets (a device clock)"),
        "drift_ppm": Option(float, 0.0, "device clock runs fast by this much", min=-5000, max=5000),
        "latency_ms": Option(float, 1.0, "fixed link latency", min=0.0),
        "jitter_ms": Option(float, 0.0, "uniform extra arrival delay, 0..this", min=0.0),
        "burst_ms": Option(float, 0.0, "deliver in bursts every this many ms (FTDI latency timer)", min=0.0),
        "duration": Option(float, 0.0, "seconds of device time, then end of stream (0 = endless)", min=0.0),
        "realtime": Option(bool, True, "deliver at wall-clock pace (false: virtual clock, as fast as read)"),
        "start_ms": Option(int, 12 * 3_600_000, "device clock at start, ms of day (wraps at midnight)", min=0),
        "reset_at": Option(float, 0.0, "device clock restarts from 0 at this device second (0 = never)", min=0.0),
        "garbage": Option(float, 0.0, "probability of random bytes injected before a chunk", min=0.0, max=1.0),
        "unplug_at": Option(float, 0.0, "the device vanishes at this second (0 = never)", min=0.0),
        "unplug_for": Option(float, 1.0, "and comes back after this many seconds", min=0.0),
        "truth": Option(bool, False, "keep true host times of readings (tests)"),
        "csv": Option(str, "", "play this IMU CSV (time s, gyro xyz deg/s, accel xyz g) instead of synthetic motion"),
        "loop_s": Option(float, 0.0, "repeat one gesture, each loop this many seconds on average (0 = free waving)",
                         min=0.0, max=3600.0),
        "loop_jitter": Option(float, 0.08, "each loop lasts loop_s times 1 +- up to this", min=0.0, max=0.5),
    }

    def __init__(self, address: str, options: Mapping[str, Any] | None = None, clock: Clock = MONOTONIC) -> None:
        super().__init__(address, options, clock)
        if address not in KINDS:
            raise ConfigError(f"synth://{address}: unknown synthetic device; known: {', '.join(KINDS)}"
                              f" (form {self.usage})", source=self.url)
        o = self.opts
        self.motion = WavingMotion(o["seed"], loop_s=o["loop_s"] or None, loop_jitter=o["loop_jitter"])
        self._csv = _load_imu_csv(o["csv"], self.url) if o["csv"] else None
        self.codec = WitMotionCodec()
        if self._csv is not None:
            dt = np.diff(self._csv[:, 0])
            self._csv_rate = round(1.0 / float(np.median(dt)), 3) if dt.size else 100.0
        self._nrng = np.random.default_rng(o["seed"] * 7919 + 1)
        self._last_arrival = 0
        self._open = False
        self._i = 0
        self._t0: int | None = None
        #: with ``truth``: the true host time of every reading made (``SimulatorTruth``)
        self.truth_ns: list[int] = []
        self._queue: deque[tuple[int, bytes, int]] = deque()  # (arrival, bytes, true time) to deliver
        self._virtual_now = 0

    # -- SimulatorTruth ------------------------------------------------------------------------------
    @property
    def latency_ns(self) -> int:
        """The simulated fixed link latency (option ``latency_ms``), ns."""
        return int(self.opts["latency_ms"] * 1e6)

    @property
    def drift_ppm(self) -> float:
        """The simulated device clock drift (option ``drift_ppm``), ppm."""
        return float(self.opts["drift_ppm"])

    def implied_kind(self) -> str:
        return KINDS[self.address]

    def implied_device_options(self) -> dict[str, Any]:
        rate = self.opts["rate"]
        if self._csv is not None:
            rate = self._csv_rate
        return {"rate": rate, "device_clock": self.opts["device_clock"]}

    @property
    def is_open(self) -> bool:
        return self._open

    def _host_ns(self, seconds: float) -> int:
        assert self._t0 is not None
        return self._t0 + round(seconds * 1e9)

    def _unplugged(self, now_ns: int) -> bool:
        o = self.opts
        if not o["unplug_at"] or self._t0 is None:
            return False
        s = (now_ns - self._t0) / 1e9
        return bool(o["unplug_at"] <= s < o["unplug_at"] + o["unplug_for"])

    def open(self) -> None:
        now = self.clock.now_ns()
        if self._t0 is None:
            self._t0 = now
            self._virtual_now = now
        elif self.opts["realtime"] and self._unplugged(now):
            raise DeviceNotFoundError(f"{self.url}: no such device (simulated unplug)", source=self.url)
        self._open = True

    def close(self) -> None:
        self._open = False

    def _now(self) -> int:
        return self.clock.now_ns() if self.opts["realtime"] else self._virtual_now

    def _produce_until(self, horizon_ns: int) -> None:
        """Generate readings (in 0.1 s blocks) until one arrives after ``horizon_ns``."""
        while not self._queue or self._queue[-1][0] <= horizon_ns:
            if self._produce_block() < 0:
                return

    def _produce_block(self) -> int:
        """One block of readings: motion, device clock, link timing and wire bytes, all with numpy.
        Returns how many readings were made, or -1 when the take is over."""
        o = self.opts
        rate = o["rate"]
        csv = self._csv
        n_block = max(1, int(rate * 0.1))
        i0 = self._i
        if csv is not None:
            if i0 >= len(csv):
                return -1
            idx = np.arange(i0, min(len(csv), i0 + n_block))
            dev_s = csv[idx, 0] - csv[0, 0]
        else:
            idx = np.arange(i0, i0 + n_block)
            dev_s = idx / rate
        if o["duration"]:
            keep = dev_s < o["duration"]
            if not keep.any():
                return -1
            idx, dev_s = idx[keep], dev_s[keep]
        drift = o["drift_ppm"] * 1e-6
        t0 = self._t0
        assert t0 is not None
        true_host = t0 + np.round(dev_s / (1.0 + drift) * 1e9).astype(np.int64)
        self._i = int(idx[-1]) + 1
        made = idx.size
        if o["unplug_at"]:
            away = (dev_s >= o["unplug_at"]) & (dev_s < o["unplug_at"] + o["unplug_for"])
            idx, dev_s, true_host = idx[~away], dev_s[~away], true_host[~away]  # these never reach the host
            if idx.size == 0:
                return made
        n = idx.size
        burst = int(o["burst_ms"] * 1e6)
        deliver = (t0 + ((true_host - t0) // burst + 1) * burst) if burst else true_host
        arrival = deliver + int(o["latency_ms"] * 1e6)
        if o["jitter_ms"]:
            arrival = arrival + self._nrng.uniform(0, o["jitter_ms"] * 1e6, n).astype(np.int64)
        prev = self._queue[-1][0] if self._queue else self._last_arrival
        arrival = np.maximum.accumulate(np.maximum(arrival, prev))  # a byte pipe keeps order
        self._last_arrival = int(arrival[-1])
        dev_ms = None
        if o["device_clock"]:
            dev_ms = dev_s * 1000.0
            if o["reset_at"]:
                dev_ms = np.where(dev_s >= o["reset_at"], (dev_s - o["reset_at"]) * 1000.0, dev_ms + o["start_ms"])
            else:
                dev_ms = dev_ms + o["start_ms"]
        if csv is not None:
            acc, gyro, eul = csv[idx, 4:7], csv[idx, 1:4], None
        else:
            acc, gyro, eul = self.motion.at_many(dev_s)
        data, step = witmotion_wire(dev_ms, acc, gyro, eul)
        garbage = o["garbage"]
        bad = self._nrng.random(n) < garbage if garbage else None
        if o["truth"]:
            self.truth_ns += true_host.tolist()
        q = self._queue
        for k, (a, th) in enumerate(zip(arrival.tolist(), true_host.tolist(), strict=True)):
            piece = data[k * step:(k + 1) * step]
            if bad is not None and bad[k]:
                piece = self._nrng.integers(0, 256, int(self._nrng.integers(1, 12)), np.uint8).tobytes() + piece
            q.append((a, piece, th))
        return made

    def read(self, timeout: float) -> Chunk | None:
        if not self._open:
            raise DeviceIOError(f"{self.url}: read on a closed transport", source=self.url)
        o = self.opts
        if o["realtime"]:
            now = self.clock.now_ns()
            if self._unplugged(now):
                self._open = False
                # what was taken before the unplug but not yet delivered is lost with the device
                assert self._t0 is not None  # set at the first open; _unplugged is False before it
                cut = self._t0 + int(self.opts["unplug_at"] * 1e9)
                self._queue = deque(e for e in self._queue if e[2] >= cut)
                raise DeviceIOError(f"{self.url}: device disconnected (simulated unplug)", source=self.url)
            deadline = now + int(timeout * 1e9)
            if not self._queue:
                self._produce_until(deadline)
            if not self._queue:
                if self._finished():
                    raise EndOfStream(f"{self.url}: synthetic take finished", source=self.url)
                self.clock.sleep_until_ns(deadline)
                return None
            arrival = self._queue[0][0]
            if arrival > deadline:
                self.clock.sleep_until_ns(deadline)
                return None
            self.clock.sleep_until_ns(arrival)
            return self._take(arrival, self.clock.now_ns())
        # virtual clock: deliver the next chunk at once, stamped with its simulated arrival
        while not self._queue:
            if self._produce_block() < 0:
                raise EndOfStream(f"{self.url}: synthetic take finished", source=self.url)
        arrival = self._queue[0][0]
        self._virtual_now = max(self._virtual_now, arrival)
        return self._take(arrival, arrival)

    def _finished(self) -> bool:
        if self._csv is not None:
            return self._i >= len(self._csv)
        return bool(self.opts["duration"]) and self._i / self.opts["rate"] >= self.opts["duration"]

    def _take(self, arrival: int, stamp: int) -> Chunk:
        """Everything that arrives at ``arrival`` (one burst) as one chunk."""
        parts = []
        while self._queue and self._queue[0][0] <= arrival:
            parts.append(self._queue.popleft()[1])
        return Chunk(b"".join(parts), stamp)


if TYPE_CHECKING:  # the ability it declares, checked by mypy
    _truth: type[SimulatorTruth] = SynthTransport


#: the largest IMU CSV played (the x-io recording in the traces is 1.4 MB) and its longest line
MAX_CSV_BYTES = 32 << 20
MAX_CSV_LINE = 4096
#: what a recorded IMU can hold: times (s), gyroscope (deg/s) and accelerometer (g) magnitudes, rates
MAX_CSV_TIME_S = 1e10
MAX_CSV_VALUE = 1e6
MIN_CSV_RATE, MAX_CSV_RATE = 0.1, 100_000.0


def _load_imu_csv(path: str, url: str) -> np.ndarray:
    """Rows of (time s, gyro xyz deg/s, accel xyz g) from an x-io/Fusion-layout CSV with a header row.

    Only a regular file of at most ``MAX_CSV_BYTES`` with lines of at most ``MAX_CSV_LINE`` bytes is
    read (``csv=/dev/zero``, a FIFO, or a file with no line ends is refused, not read for ever), and
    only finite times and readings within ``MAX_CSV_TIME_S``, ``MAX_CSV_VALUE`` and the rates are played.

    Raises:
        ConfigError: unreadable, beyond those bounds, or not such a CSV.
    """
    try:
        raw = read_bounded(path, MAX_CSV_BYTES)
    except OSError as exc:
        raise ConfigError(f"{url}: cannot read {path}: {exc.strerror or exc}", source=url) from None
    except InputLimitError as exc:
        raise ConfigError(f"{url}: not played: {exc}", source=url) from None
    longest = longest_line(raw)
    if longest > MAX_CSV_LINE:
        raise ConfigError(f"{url}: {path} has a line of {longest} bytes (an IMU CSV line is at most {MAX_CSV_LINE})",
                          source=url)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # "Empty input file" and the like: refused, not a warning
            # (loadtxt, not genfromtxt: a 32 MB file takes 1/10 the time and memory)
            data = np.loadtxt(io.BytesIO(raw), delimiter=",", skiprows=1, usecols=range(7), ndmin=2)
    except (ValueError, UserWarning) as exc:
        raise ConfigError(f"{url}: {path} is not an IMU CSV (time, gyro x/y/z, accel x/y/z): {exc}",
                          source=url) from None
    data = np.atleast_2d(data)
    if data.shape[0] == 0 or data.shape[1] < 7 or not np.all(np.isfinite(data)):
        raise ConfigError(f"{url}: {path} has no usable rows (need time, gyro x/y/z, accel x/y/z)", source=url)
    dt = np.diff(data[:, 0])
    if np.any(dt <= 0):
        raise ConfigError(f"{url}: {path}: times must increase", source=url)
    if np.abs(data[:, 0]).max() >= MAX_CSV_TIME_S or np.abs(data[:, 1:7]).max() > MAX_CSV_VALUE:
        raise ConfigError(f"{url}: {path}: times beyond {MAX_CSV_TIME_S:g} s or readings beyond"
                          f" {MAX_CSV_VALUE:g} deg/s or g (not an IMU recording)", source=url)
    if dt.size and not MIN_CSV_RATE <= 1.0 / float(np.median(dt)) <= MAX_CSV_RATE:
        raise ConfigError(f"{url}: {path}: readings {float(np.median(dt)):g} s apart (an IMU CSV has"
                          f" {MIN_CSV_RATE:g}..{MAX_CSV_RATE:g} per second)", source=url)
    return data
