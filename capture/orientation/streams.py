"""The unit and frame check where IMU and magnetometer streams enter orientation fusion:
:func:`check_imu_stream` and :func:`check_mag_stream` accept or refuse a stream's kind, channels,
units and frame, naming what is wrong, and return where its axes are and the conversion to SI
(:class:`ImuChannels`, :class:`MagChannels`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from capture.calibration import G0
from capture.errors import ConfigError

if TYPE_CHECKING:
    from capture.sample import StreamInfo

_D2R = math.pi / 180.0

_ACC_UNITS = {"m/s^2": 1.0, "m/s2": 1.0, "m/s²": 1.0, "m s^-2": 1.0, "m/s/s": 1.0,
              "g": G0, "g0": G0, "gn": G0, "mg": G0 * 1e-3}
_GYRO_UNITS = {"rad/s": 1.0, "rad s^-1": 1.0, "deg/s": _D2R, "dps": _D2R, "°/s": _D2R, "degree/s": _D2R,
               "degrees/s": _D2R, "mrad/s": 1e-3}
_MAG_UNITS = {"t", "mt", "ut", "µt", "μt", "nt", "g", "gauss", "mg", "mgauss", "count", "counts", "lsb", "1", "a.u."}


@dataclass(frozen=True)
class ImuChannels:
    """Where the accelerometer and gyro are in an IMU stream's values and how to make them SI.

    Attributes:
        stream: the stream name.
        acc_idx: value columns of ax, ay, az.
        acc_scale: factor to m/s^2.
        gyro_idx: value columns of gx, gy, gz.
        gyro_scale: factor to rad/s.
    """

    stream: str
    acc_idx: tuple[int, int, int]
    acc_scale: float
    gyro_idx: tuple[int, int, int]
    gyro_scale: float

    @property
    def acc_sel(self) -> slice | list[int]:
        """Column selector of the accelerometer (a slice when the columns are consecutive)."""
        return _sel(self.acc_idx)

    @property
    def gyro_sel(self) -> slice | list[int]:
        """Column selector of the gyro (a slice when the columns are consecutive)."""
        return _sel(self.gyro_idx)


def _sel(idx: tuple[int, int, int]) -> slice | list[int]:
    return slice(idx[0], idx[0] + 3) if idx[1] == idx[0] + 1 and idx[2] == idx[0] + 2 else list(idx)


@dataclass(frozen=True)
class MagChannels:
    """Where the magnetometer is in a mag stream's values (its unit is kept; only direction matters)."""

    stream: str
    idx: tuple[int, int, int]
    unit: str


def _norm_unit(u: str) -> str:
    u = u.strip()
    return u if u in _ACC_UNITS or u in _GYRO_UNITS else u.replace(" ", "")


def _find(info: StreamInfo, names: tuple[str, str, str]) -> tuple[int, int, int]:
    lower = [c.lower() for c in info.channels]
    idx = []
    for nme in names:
        if nme not in lower:
            raise ConfigError(f"stream {info.name}: channel {nme!r} not found (channels: {', '.join(info.channels)})",
                              source=info.name)
        idx.append(lower.index(nme))
    return (idx[0], idx[1], idx[2])


def _check_frame(info: StreamInfo) -> None:
    f = (info.frame or "").lower()
    if "left-handed" in f or "left handed" in f:
        raise ConfigError(f"stream {info.name}: frame {info.frame!r} is left-handed; orientation needs a right-handed "
                          f"sensor frame (remap the axes in the device)", source=info.name)


def check_imu_stream(info: StreamInfo) -> ImuChannels:
    """Check an IMU stream at the boundary and return the conversion to rad/s and m/s^2.

    Accepted: kind ``imu``; channels ``ax ay az`` in m/s^2 or g (or mg), ``gx gy gz`` in rad/s or
    deg/s; a right-handed frame.

    Raises:
        ConfigError: wrong kind, a missing channel, a unit that is not accepted (the message names the
            stream, the channel and the unit found), axes of one sensor in different units, or a
            left-handed frame.
    """
    if info.kind != "imu":
        raise ConfigError(f"stream {info.name}: kind {info.kind!r} is not an IMU stream (kind 'imu')", source=info.name)
    _check_frame(info)
    ai = _find(info, ("ax", "ay", "az"))
    gi = _find(info, ("gx", "gy", "gz"))

    def scale(idx: tuple[int, int, int], table: dict[str, float], what: str) -> float:
        units = [_norm_unit(info.units[i]) for i in idx]
        for i, u in zip(idx, units, strict=True):
            if u not in table and u.lower() not in table:
                raise ConfigError(f"stream {info.name}: channel {info.channels[i]} has unit {info.units[i]!r}, "
                                  f"not a {what} unit ({', '.join(sorted(table))})", source=info.name)
        sc = [table.get(u, table.get(u.lower(), 0.0)) for u in units]
        if len(set(sc)) != 1:
            raise ConfigError(f"stream {info.name}: {what} channels have different units "
                              f"{[info.units[i] for i in idx]}", source=info.name)
        return sc[0]

    return ImuChannels(info.name, ai, scale(ai, _ACC_UNITS, "acceleration"), gi, scale(gi, _GYRO_UNITS, "angular rate"))


def check_mag_stream(info: StreamInfo, imu: StreamInfo | None = None) -> MagChannels:
    """Check a magnetometer stream (and that it shares the IMU's sensor frame).

    Raises:
        ConfigError: wrong kind, a missing channel, an unknown unit or different units on the three
            axes (named), a left-handed frame, or a frame that differs from the IMU stream's.
    """
    if info.kind != "mag":
        raise ConfigError(f"stream {info.name}: kind {info.kind!r} is not a magnetometer stream (kind 'mag')",
                          source=info.name)
    _check_frame(info)
    idx = _find(info, ("mx", "my", "mz"))
    units = [info.units[i].strip() for i in idx]
    for i, u in zip(idx, units, strict=True):
        if u.lower() not in _MAG_UNITS:
            raise ConfigError(f"stream {info.name}: channel {info.channels[i]} has unit {u!r}, not a magnetic-field "
                              f"unit ({', '.join(sorted(_MAG_UNITS))})", source=info.name)
    if len({u.lower() for u in units}) != 1:
        raise ConfigError(f"stream {info.name}: channels {[info.channels[i] for i in idx]} have different units "
                          f"{units}", source=info.name)
    if imu is not None and info.frame and imu.frame and info.frame != imu.frame:
        raise ConfigError(f"stream {info.name}: frame {info.frame!r} differs from {imu.name}'s {imu.frame!r}; the "
                          f"magnetometer must be remapped to the IMU frame", source=info.name)
    return MagChannels(info.name, idx, units[0])
