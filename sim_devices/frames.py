"""Frame sources for simulated serial devices: what a device would send, reading by reading, as
wire bytes made by the real codecs' encoders.

A source yields blocks of ``(t_s, pieces)``: the time of each reading in seconds from the start
of the take (device time) and the bytes the device sends for it. ``synth://`` and the pty-backed
serial simulator (``sim_devices.serial_sim``) both draw from these, so a simulated WT901 sends the
same bytes whichever way it is reached. Synthetic sources are endless; a recorded session's raw
chunks are finite (and may loop).
"""

from __future__ import annotations

import abc
from typing import TYPE_CHECKING, Any

import numpy as np

from capture.errors import ConfigError
from devices.codecs.witmotion import ACC, ANGLE, GYRO, MAG, TIME, WitMotionCodec
from sim_devices.motion import WavingMotion

if TYPE_CHECKING:
    from collections.abc import Iterator

    from devices.textline import TextLineLayout

MS_PER_DAY = 86_400_000


def witmotion_wire(dev_ms: np.ndarray | None, acc_g: np.ndarray, gyro_dps: np.ndarray,
                   eul_deg: np.ndarray | None, mag: np.ndarray | None = None,
                   temp_c: float = 25.0) -> tuple[bytes, int]:
    """WT901 output cycles for ``n`` readings, encoded with numpy: [time], acc, gyro, [angle], [mag].

    Args:
        dev_ms: device clock of each reading, ms of day (``None``: no time packets).
        acc_g, gyro_dps, eul_deg, mag: (n, 3) arrays; mag in raw counts.

    Returns:
        (wire bytes of all cycles back to back, bytes per cycle).
    """
    n = acc_g.shape[0]
    types: list[int] = []
    payloads: list[np.ndarray] = []
    if dev_ms is not None:
        ms = np.asarray(dev_ms, np.int64) % MS_PER_DAY
        hh, rem = np.divmod(ms, 3_600_000)
        mi, rem = np.divmod(rem, 60_000)
        ss, msec = np.divmod(rem, 1000)
        tp = np.zeros((n, 8), np.uint8)
        tp[:, 0], tp[:, 1], tp[:, 2] = 26, 11, 23
        tp[:, 3], tp[:, 4], tp[:, 5] = hh, mi, ss
        tp[:, 6], tp[:, 7] = msec & 0xFF, msec >> 8
        types.append(TIME)
        payloads.append(tp)

    def words(v: np.ndarray, full: float | None, fourth: int = 0) -> np.ndarray:
        w = np.zeros((n, 4), "<i2")
        w[:, :3] = np.clip(np.round(v if full is None else v / full * 32768.0), -32768, 32767)
        w[:, 3] = fourth
        return w.view(np.uint8).reshape(n, 8)

    types += [ACC, GYRO]
    payloads += [words(acc_g, 16.0, round(temp_c * 100)), words(gyro_dps, 2000.0)]
    if eul_deg is not None:
        types.append(ANGLE)
        payloads.append(words(eul_deg, 180.0))
    if mag is not None:
        types.append(MAG)
        payloads.append(words(mag, None))
    per_cycle = len(types)
    wire = WitMotionCodec.encode_many(np.tile(np.array(types, np.uint8), n),
                                      np.stack(payloads, axis=1).reshape(n * per_cycle, 8))
    return wire.tobytes(), per_cycle * 11


class FrameSource(abc.ABC):
    """What a simulated device sends; see the module docstring."""

    kind: str = ""

    @abc.abstractmethod
    def device_options(self) -> dict[str, Any]:
        """The device options a reader needs for these bytes (rate, device clock, ...)."""

    @abc.abstractmethod
    def blocks(self) -> Iterator[tuple[np.ndarray, list[bytes]]]:
        """Blocks of (reading times in s from the start, bytes per reading), in time order."""


class WavingSource(FrameSource):
    """Synthetic hand-held motion (``WavingMotion``) at a fixed rate, encoded for one device kind.

    Args:
        kind: device kind whose wire format to produce.
        rate: readings per second.
        seed: motion seed.
        device_clock: include the device's own time stamps where the protocol has them.
        start_ms: device clock at the start (ms of day for WitMotion).
        block_s: readings generated per block, in seconds.
        amplitude_deg: size of the waving (0: the device lies still, tilted a little).
        gyro_bias_dps: a constant gyro offset the sensor adds (x, y, z), as real MEMS gyros do.
        gyro_noise_dps: white noise on each gyro axis (standard deviation).
        heading_deg: a WT901 also sends magnetometer packets, of a field of 20 uT north and 45 uT
            down (10 counts per uT; north is +y of the ENU world frame), and a still device faces
            this heading (its yaw). ``None``: no magnetometer.
    """

    #: the simulated earth field, ENU, in magnetometer counts
    EARTH_FIELD = (0.0, 200.0, -450.0)

    def __init__(self, kind: str = "witmotion", rate: float = 200.0, seed: int = 1, device_clock: bool = True,
                 start_ms: int = 12 * 3_600_000, block_s: float = 0.1, amplitude_deg: float = 40.0,
                 gyro_bias_dps: tuple[float, float, float] = (0.0, 0.0, 0.0), gyro_noise_dps: float = 0.0,
                 heading_deg: float | None = None) -> None:
        if kind not in ENCODERS:
            raise ConfigError(f"no simulated serial device of kind {kind!r}; known: {', '.join(sorted(ENCODERS))}")
        self.kind = kind
        self.rate = rate
        self.device_clock = device_clock
        self.start_ms = start_ms
        self.motion = WavingMotion(seed, amplitude_deg=amplitude_deg)
        self.still = amplitude_deg == 0
        self.bias = np.asarray(gyro_bias_dps, np.float64)
        self.noise = gyro_noise_dps
        self.rng = np.random.default_rng(seed + 1000)
        self.block = max(1, round(rate * block_s))
        self.heading = heading_deg
        #: the text-line layout its encoder made on first use (kind ``textline``)
        self.textline_layout: TextLineLayout | None = None

    def sense(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the sensor measures at times ``t``: specific force (g), angular rate (deg/s, with the
        bias and noise), roll/pitch/yaw (deg); a still device rests tilted by 10 and -5 degrees."""
        if self.still:
            n = t.size
            roll, pitch = np.radians(10.0), np.radians(-5.0)
            acc = np.tile([-np.sin(pitch), np.cos(pitch) * np.sin(roll), np.cos(pitch) * np.cos(roll)], (n, 1))
            gyro = np.zeros((n, 3))
            eul = np.tile([10.0, -5.0, self.heading or 0.0], (n, 1))
        else:
            acc, gyro, eul = self.motion.at_many(t)
        gyro = gyro + self.bias
        if self.noise:
            gyro = gyro + self.rng.normal(0.0, self.noise, gyro.shape)
        return acc, gyro, eul

    def sense_mag(self, eul_deg: np.ndarray) -> np.ndarray:
        """Magnetometer counts in the sensor frame for roll/pitch/yaw (deg, ZYX, sensor -> ENU)."""
        from scipy.spatial.transform import Rotation

        r = Rotation.from_euler("ZYX", eul_deg[:, ::-1], degrees=True)
        return np.asarray(r.inv().apply(np.asarray(self.EARTH_FIELD)), np.float64)

    def device_options(self) -> dict[str, Any]:
        return ENCODERS[self.kind].device_options(self)

    def blocks(self) -> Iterator[tuple[np.ndarray, list[bytes]]]:
        i = 0
        enc = ENCODERS[self.kind]
        while True:
            t = np.arange(i, i + self.block) / self.rate
            yield t, enc.encode(self, i, t)
            i += self.block


class _Encoder(abc.ABC):
    @abc.abstractmethod
    def device_options(self, src: WavingSource) -> dict[str, Any]: ...

    @abc.abstractmethod
    def encode(self, src: WavingSource, i0: int, t: np.ndarray) -> list[bytes]: ...


class _WitMotionEncoder(_Encoder):
    def device_options(self, src: WavingSource) -> dict[str, Any]:
        return {"rate": src.rate, "device_clock": src.device_clock}

    def encode(self, src: WavingSource, i0: int, t: np.ndarray) -> list[bytes]:
        acc, gyro, eul = src.sense(t)
        dev_ms = (src.start_ms + np.floor(t * 1000.0)) if src.device_clock else None
        mag = src.sense_mag(eul) if src.heading is not None else None
        data, step = witmotion_wire(dev_ms, acc, gyro, eul, mag)
        return [data[k * step:(k + 1) * step] for k in range(t.size)]


class _Bno08xRvcEncoder(_Encoder):
    """BNO08x UART-RVC at its fixed 100 Hz: roll/pitch/yaw and acceleration; the frame counter is the
    device clock."""

    def device_options(self, src: WavingSource) -> dict[str, Any]:
        return {"device_clock": src.device_clock}

    def encode(self, src: WavingSource, i0: int, t: np.ndarray) -> list[bytes]:
        from devices.bno08x import encode_rvc_many

        acc, _, eul = src.sense(t)
        eul = (eul + 180.0) % 360.0 - 180.0
        wire = encode_rvc_many(np.arange(i0, i0 + t.size) % 256, eul, acc * 9.80665)
        return [row.tobytes() for row in wire]


TEXTLINE_OPTIONS = {"format": "csv", "columns": "t,ax,ay,az,gx,gy,gz", "units": "ms,g,g,g,dps,dps,dps",
                    "time": "t", "time_wrap": "u32"}


class _TextLineEncoder(_Encoder):
    """An Arduino sketch printing ``millis(),ax,ay,az,gx,gy,gz`` (g and deg/s, 4 decimals)."""

    def device_options(self, src: WavingSource) -> dict[str, Any]:
        return {**TEXTLINE_OPTIONS, "rate": src.rate}

    def encode(self, src: WavingSource, i0: int, t: np.ndarray) -> list[bytes]:
        from devices.textline import TextLineLayout

        layout = src.textline_layout
        if layout is None:
            layout = src.textline_layout = TextLineLayout(self.device_options(src))
        acc, gyro, _ = src.sense(t)
        acc = acc * 9.80665
        gyro = np.radians(gyro)
        ch = {"ax": acc[:, 0], "ay": acc[:, 1], "az": acc[:, 2], "gx": gyro[:, 0], "gy": gyro[:, 1], "gz": gyro[:, 2]}
        return layout.encode_lines(ch, np.floor(t * 1000.0) / 1000.0, decimals=4)


#: device kind -> how to encode synthetic motion for it. Other serial kinds add themselves here.
ENCODERS: dict[str, _Encoder] = {"witmotion": _WitMotionEncoder(), "bno08x_rvc": _Bno08xRvcEncoder(),
                                 "textline": _TextLineEncoder()}


class SessionSource(FrameSource):
    """The raw bytes a device sent in a recorded perfcap session, at their recorded arrival times.

    Args:
        path: session file.
        device: device name in the session (default: the only one).
        loop: start again at the end.

    Raises:
        ConfigError: the session cannot be read, or the device is not in it.
    """

    def __init__(self, path: str, device: str | None = None, loop: bool = False) -> None:
        from capture.errors import SessionError
        from capture.session import SessionReader
        try:
            reader = SessionReader.open(path)
        except (SessionError, OSError) as exc:
            raise ConfigError(f"cannot read session {path}: {exc}") from None
        devs = reader.devices
        if device is None:
            if len(devs) != 1:
                raise ConfigError(f"{path} has {len(devs)} devices ({', '.join(devs)}); name one")
            device = next(iter(devs))
        if device not in devs:
            raise ConfigError(f"{path} has no device {device!r}; it has {', '.join(devs) or 'none'}")
        rec = devs[device]
        self.kind = rec.kind
        self._options = dict(rec.options)
        chunks = [c for c in reader.raw_chunks(device) if c.direction.name == "RX"]
        if not chunks:
            raise ConfigError(f"{path}: device {device} has no received bytes to play")
        t0 = chunks[0].t_ns
        self._t = np.array([(c.t_ns - t0) / 1e9 for c in chunks])
        self._data = [c.data for c in chunks]
        self.loop = loop

    def device_options(self) -> dict[str, Any]:
        return dict(self._options)

    def blocks(self) -> Iterator[tuple[np.ndarray, list[bytes]]]:
        offset = 0.0
        span = float(self._t[-1]) + (float(np.median(np.diff(self._t))) if self._t.size > 1 else 0.01)
        while True:
            for k in range(0, self._t.size, 256):
                yield self._t[k:k + 256] + offset, self._data[k:k + 256]
            if not self.loop:
                return
            offset += span


__all__ = ["ENCODERS", "FrameSource", "SessionSource", "WavingSource", "witmotion_wire"]
