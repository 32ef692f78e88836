"""The calibration workflow behind ``perfcap calibrate``: read one device for a few seconds while the
performer holds it still, rests it in several poses or turns it through every direction, and fit the
gyro bias, accelerometer, magnetometer, mounting and heading (the maths is ``capture.calibration``).

Each step returns the updated calibration, what it measured (for ``--json``) and one summary line.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from capture.bus import Overflow, Subscriber
from capture.errors import ConfigError
from capture.sample import Sample, SampleBatch

if TYPE_CHECKING:
    import threading

    from capture.app.config import Settings
    from capture.calibration import ImuCalibration
    from devices import DeviceSpec

#: what a step tells the performer before it reads (the CLI prints it on stderr)
Announce = Callable[[str], None]


@dataclass
class ImuTake:
    """A few seconds of one device: times (s), acceleration (m/s^2), angular rate (rad/s), and the
    magnetometer's readings and times where it has one."""

    device: str
    t: np.ndarray
    acc: np.ndarray
    gyro: np.ndarray
    mag: np.ndarray | None = None
    mag_t: np.ndarray | None = None


@dataclass
class StepResult:
    calibration: ImuCalibration
    report: dict[str, Any]
    line: str


def _vec3(a: np.ndarray) -> tuple[float, float, float]:
    return float(a[0]), float(a[1]), float(a[2])


def _mat3(a: np.ndarray) -> tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]:
    return _vec3(a[0]), _vec3(a[1]), _vec3(a[2])


class _Keep(Subscriber):
    """Keeps the samples of the named streams."""

    accepts = frozenset({Sample, SampleBatch})

    def __init__(self, names: list[str]) -> None:
        self.got: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {n: [] for n in names}

    def on_item(self, item: Any) -> None:
        rows = self.got.get(item.stream)
        if rows is None:
            return
        if type(item) is Sample:
            rows.append((np.array([item.t_bus_ns]), np.array([item.values], float)))
        else:
            rows.append((item.t_bus_ns, item.values))


def collect_imu(spec: DeviceSpec, seconds: float, s: Settings, what: str, stop: threading.Event,
                announce: Announce) -> ImuTake:
    """Read one device for ``seconds`` (or until ``stop``).

    Raises:
        ConfigError: the device has no IMU stream, fails, or sends nothing.
    """
    from capture.app.orchestrator import Capture
    from capture.orientation import check_imu_stream

    cap = Capture([spec], reconnect=s.reconnect_policy())
    dev = cap.devices[0]
    imus = [x for x in dev.streams if x.kind == "imu"]
    if not imus:
        cap.stop()
        raise ConfigError(f"device {dev.name} ({dev.kind}) has no IMU stream (accelerometer and gyro) to calibrate")
    try:
        ch = check_imu_stream(imus[0])
    except ConfigError:
        cap.stop()
        raise
    mag_name = next((x.name for x in dev.streams if x.kind == "mag"), None)
    keep = _Keep([imus[0].name] + ([mag_name] if mag_name else []))
    cap.subscribe(keep, Overflow.NEVER_DROP, "calibrate")
    announce(f"perfcap calibrate: {what}; reading {dev.name} for {seconds:g} s ...")
    rep = cap.run(seconds, stop=stop)
    if rep.devices[dev.name]["state"] == "failed":
        raise ConfigError(f"device {dev.name} failed while calibrating (see the messages above)")
    rows = keep.got[imus[0].name]
    if not rows:
        raise ConfigError(f"no readings from {dev.name} in {seconds:g} s: is it streaming?")
    t = np.concatenate([r[0] for r in rows]) / 1e9
    v = np.concatenate([r[1] for r in rows])
    take = ImuTake(dev.name, t, v[:, list(ch.acc_idx)] * ch.acc_scale, v[:, list(ch.gyro_idx)] * ch.gyro_scale)
    mrows = keep.got.get(mag_name or "", [])
    if mag_name and mrows:
        take.mag = np.concatenate([r[1] for r in mrows])[:, :3]
        take.mag_t = np.concatenate([r[0] for r in mrows]) / 1e9
    return take


def gyro_step(cal: ImuCalibration, take: ImuTake) -> StepResult:
    """Gyro bias from a still period."""
    from capture.calibration import still_bias

    sb = still_bias(take.gyro, take.acc, take.t, source=take.device)
    bias = np.degrees(sb.bias)
    return StepResult(cal.with_gyro_bias(sb.bias),
                      {"gyro_bias_dps": bias.round(4).tolist(),
                       "gyro_bias_stderr_dps": np.degrees(sb.stderr).round(5).tolist()},
                      f"gyro bias {bias.round(4).tolist()} deg/s (+- {np.degrees(sb.stderr).max():.4f}) from"
                      f" {sb.n} still samples over {sb.duration_s:.1f} s")


def accel_step(cal: ImuCalibration, take: ImuTake) -> StepResult:
    """Accelerometer offset and scale from still poses."""
    from capture.calibration import fit_accelerometer, still_poses

    fit = fit_accelerometer(still_poses(take.t, take.acc, take.gyro), source=take.device)
    return StepResult(replace(cal, acc_offset=_vec3(fit.offset), acc_matrix=_mat3(fit.matrix)),
                      {"accel": {"poses": fit.poses, "distinct": fit.distinct, "model": fit.model,
                                 "residual_rms": fit.residual_rms, "raw_rms": fit.raw_rms}},
                      f"accelerometer ({fit.model}, {fit.distinct} orientations): |g| error rms {fit.raw_rms:.4f} ->"
                      f" {fit.residual_rms:.4f} m/s^2")


def mag_step(cal: ImuCalibration, take: ImuTake) -> StepResult:
    """Magnetometer hard and soft iron from a rotation through every direction."""
    from capture.calibration import fit_magnetometer

    if take.mag is None:
        raise ConfigError(f"device {take.device} has no magnetometer stream")
    mf = fit_magnetometer(take.mag, source=take.device)
    return StepResult(replace(cal, mag_hard_iron=_vec3(mf.hard_iron), mag_soft_iron=_mat3(mf.soft_iron)),
                      {"mag": {"model": mf.model, "coverage": mf.coverage, "spread_before": mf.spread_before,
                               "spread_after": mf.spread_after}},
                      f"magnetometer ({mf.model}, coverage {mf.coverage:.0%}): field magnitude spread"
                      f" {mf.spread_before:.1%} -> {mf.spread_after:.1%}")


def mounting_step(cal: ImuCalibration, take: ImuTake) -> StepResult:
    """The mounting rotation (sensor -> segment) from a still reference pose."""
    from capture.calibration import mounting_from_gravity, still_bias

    still_bias(take.gyro, take.acc, take.t, source=take.device)  # checks it was held still
    cal = replace(cal, mounting=mounting_from_gravity(take.acc.mean(axis=0)))
    return StepResult(cal, {"mounting": list(cal.mounting)},
                      f"mounting (sensor -> segment) {np.round(cal.mounting, 4).tolist()}")


def yaw_step(cal: ImuCalibration, take: ImuTake) -> StepResult:
    """A yaw offset that makes the heading held during the still period zero.

    Heading is only reproducible from one session to the next against magnetic north, so this needs
    a magnetometer (the calibration's hard/soft-iron fit is applied first).

    Raises:
        ConfigError: no magnetometer, or the device was not held still.
    """
    from capture.calibration import still_bias
    from capture.orientation import DEFAULT_FILTER, OrientationFilter

    if take.mag is None or take.mag_t is None:
        raise ConfigError(f"device {take.device} has no magnetometer stream: without one a heading does not carry"
                          " over between sessions, so there is nothing to reset against")
    still_bias(take.gyro, take.acc, take.t, source=take.device)  # checks it was held still
    acc, gyro, _ = cal.apply(take.acc, take.gyro)
    f = OrientationFilter(DEFAULT_FILTER)
    f.add_mag(take.mag_t, cal.apply_mag(take.mag))
    r = f.update_many(take.t, gyro, acc)
    cal = cal.with_yaw_reset(r.q[-1])
    offset = round(float(np.degrees(cal.yaw_offset_rad)), 3)
    return StepResult(cal, {"yaw_offset_deg": offset},
                      f"yaw reset: headings are now measured from this direction (offset {offset} deg"
                      " from magnetic north)")


#: step name -> (what the performer is asked to do, the fit)
STEPS: dict[str, tuple[str, Callable[[ImuCalibration, ImuTake], StepResult]]] = {
    "gyro": ("gyro bias: keep the sensor still", gyro_step),
    "accel": ("accelerometer: rest the sensor in {poses} different orientations (faces up and down), a few seconds"
              " each, turning between them", accel_step),
    "mag": ("magnetometer: turn the sensor slowly through every direction", mag_step),
    "mounting": ("mounting: stand in the reference pose and keep still", mounting_step),
    "yaw": ("yaw reset: point the body the way that should be heading zero and keep still", yaw_step),
}
