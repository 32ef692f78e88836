"""``synth://`` - synthetic devices that encode generated motion through a real codec and deliver
the bytes through the Transport interface, with the timing faults real links have.

``synth://imu?rate=200&seed=1`` is a WitMotion WT901 waving on a wrist. Options model the link:
device clock drift, fixed latency, arrival jitter, FTDI-style bursts, garbage bytes, an unplug
window and a device clock reset. With ``realtime=false`` it runs on a virtual host clock as fast
as the reader asks (deterministic, for CI); ``truth=true`` keeps the true host time of every
reading so tests can measure clock-sync error end to end.
"""

from __future__ import annotations

import random
from typing import Any, Mapping

from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError, DeviceIOError, DeviceNotFoundError, EndOfStream
from capture.sample import Chunk
from devices.codecs.witmotion import WitMotionCodec
from devices.options import Option
from devices.transports.base import Transport
from devices.witmotion import encode_cycle
from sim_devices.motion import WavingMotion

KINDS = {"imu": "witmotion"}


class SynthTransport(Transport):
    """Synthetic device bytes; see the module docstring."""

    scheme = "synth"
    usage = "synth://imu?rate=HZ&seed=N"
    options = {
        "rate": Option(float, 200.0, "readings per second", min=1.0, max=2000.0),
        "seed": Option(int, 1, "motion and noise seed"),
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
    }

    def __init__(self, address: str, options: Mapping[str, Any] | None = None, clock: Clock = MONOTONIC) -> None:
        super().__init__(address, options, clock)
        if address not in KINDS:
            raise ConfigError(f"synth://{address}: unknown synthetic device; known: {', '.join(KINDS)}"
                              f" (form {self.usage})", source=self.url)
        o = self.opts
        self.motion = WavingMotion(o["seed"])
        self.codec = WitMotionCodec()
        self._rng = random.Random(o["seed"] * 7919 + 1)
        self._open = False
        self._i = 0
        self._t0: int | None = None
        self.truth_ns: list[int] = []
        self._queue: list[tuple[int, bytes]] = []  # (arrival ns, bytes) ready to deliver
        self._virtual_now = 0

    def implied_kind(self) -> str:
        return KINDS[self.address]

    def implied_device_options(self) -> dict[str, Any]:
        return {"rate": self.opts["rate"], "device_clock": self.opts["device_clock"]}

    @property
    def is_open(self) -> bool:
        return self._open

    def _host_ns(self, seconds: float) -> int:
        assert self._t0 is not None
        return self._t0 + int(round(seconds * 1e9))

    def _unplugged(self, now_ns: int) -> bool:
        o = self.opts
        if not o["unplug_at"] or self._t0 is None:
            return False
        s = (now_ns - self._t0) / 1e9
        return o["unplug_at"] <= s < o["unplug_at"] + o["unplug_for"]

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
        """Generate readings whose delivery time is at or before ``horizon_ns`` (plus one burst)."""
        o = self.opts
        rate = o["rate"]
        drift = o["drift_ppm"] * 1e-6
        lat = o["latency_ms"] * 1e6
        jit = o["jitter_ms"] * 1e6
        burst = o["burst_ms"] * 1e6
        while True:
            if o["duration"] and self._i / rate >= o["duration"]:
                return
            dev_s = self._i / rate
            true_host = self._host_ns(dev_s / (1.0 + drift))
            if burst:
                rel = true_host - self._t0  # type: ignore[operator]
                deliver = self._t0 + (int(rel // burst) + 1) * int(burst)  # type: ignore[operator]
            else:
                deliver = true_host
            arrival = int(deliver + lat + (self._rng.uniform(0, jit) if jit else 0.0))
            if self._queue and arrival < self._queue[-1][0]:
                arrival = self._queue[-1][0]  # a byte pipe keeps order
            if arrival > horizon_ns and not (self._queue and arrival == self._queue[-1][0]):
                return
            ms = None
            if o["device_clock"]:
                dev_ms = dev_s * 1000.0
                if o["reset_at"] and dev_s >= o["reset_at"]:
                    dev_ms = (dev_s - o["reset_at"]) * 1000.0
                else:
                    dev_ms += o["start_ms"]
                ms = int(dev_ms)
            m = self.motion.at(dev_s)
            data, _ = encode_cycle(self.codec, m.acc_g, m.gyro_dps, m.euler_deg, 25.0, ms)
            if o["garbage"] and self._rng.random() < o["garbage"]:
                data = bytes(self._rng.randrange(256) for _ in range(self._rng.randrange(1, 12))) + data
            if o["truth"]:
                self.truth_ns.append(true_host)
            self._queue.append((arrival, data))
            self._i += 1

    def read(self, timeout: float) -> Chunk | None:
        if not self._open:
            raise DeviceIOError(f"{self.url}: read on a closed transport", source=self.url)
        o = self.opts
        if o["realtime"]:
            now = self.clock.now_ns()
            if self._unplugged(now):
                self._open = False
                self._queue.clear()
                raise DeviceIOError(f"{self.url}: device disconnected (simulated unplug)", source=self.url)
            deadline = now + int(timeout * 1e9)
            if not self._queue:
                self._produce_until(deadline)
            if not self._queue:
                if o["duration"] and self._i / o["rate"] >= o["duration"]:
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
        if not self._queue:
            self._produce_until(self._virtual_now)
            if not self._queue:
                self._produce_until(2**62)
            if not self._queue:
                raise EndOfStream(f"{self.url}: synthetic take finished", source=self.url)
        arrival = self._queue[0][0]
        self._virtual_now = max(self._virtual_now, arrival)
        return self._take(arrival, arrival)

    def _take(self, arrival: int, stamp: int) -> Chunk:
        """Everything that arrives at ``arrival`` (one burst) as one chunk."""
        parts = []
        while self._queue and self._queue[0][0] <= arrival:
            parts.append(self._queue.pop(0)[1])
        return Chunk(b"".join(parts), stamp)
