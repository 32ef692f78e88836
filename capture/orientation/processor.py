"""The bus processor: :class:`OrientationProcessor`, a subscriber that runs an
:class:`~capture.orientation.filter.OrientationFilter` per IMU stream (with its device's
calibration, its paired magnetometer stream and, if asked, automatic gyro bias) and publishes
``<dev>/orientation``, ``<dev>/gravity`` and ``<dev>/linear_acc``, a ``Sample`` for a ``Sample``
and a ``SampleBatch`` for a ``SampleBatch``."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from capture.bus import SAMPLES, Processor
from capture.calibration import G0, GyroBiasEstimator, ImuCalibration
from capture.errors import ConfigError
from capture.orientation.filter import DEFAULT_FILTER, OrientationFilter
from capture.orientation.streams import check_imu_stream, check_mag_stream
from capture.sample import Sample, SampleBatch, StreamInfo

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping

    from capture.orientation.streams import ImuChannels, MagChannels

log = logging.getLogger(__name__)


@dataclass
class _Track:
    info: StreamInfo
    chans: ImuChannels
    flt: OrientationFilter
    cal: ImuCalibration
    out: tuple[StreamInfo, StreamInfo, StreamInfo]
    mag: MagChannels | None = None
    origin_ns: int | None = None
    seq: int = 0
    bias_est: GyroBiasEstimator | None = None
    auto_bias: np.ndarray | None = None
    auto_bias_checked_s: float = -math.inf
    fast: bool = False  # Samples take the scalar path (Fusion, no magnetometer, no auto bias)


def _prefix(name: str) -> str:
    return name.rsplit("/", 1)[0] if "/" in name else name


class OrientationProcessor(Processor):
    """Bus subscriber: orientation, gravity and linear acceleration for one or more IMU streams.

    For every IMU input ``<dev>/imu`` it publishes ``<dev>/orientation`` (kind ``orientation``,
    channels ``w x y z``: body -> world ENU), ``<dev>/gravity`` and ``<dev>/linear_acc`` (m/s^2, in
    the body frame: the sensor frame unless the calibration has a mounting rotation), each sample
    with the input's t_host/t_device/t_bus times and its own seq. A ``Sample`` in gives ``Sample``s
    out, a ``SampleBatch`` gives ``SampleBatch``es, with identical values either way. A mag stream
    among the inputs is paired with the IMU stream of the same device (``<dev>/...``) and held at
    its own rate. dt comes from ``t_bus_ns`` (the device clock mapped to host time).

    Args:
        inputs: the IMU streams (kind ``imu``) and optional magnetometer streams (kind ``mag``).
        filter: the filter kind (see :class:`OrientationFilter`).
        calibrations: per-device calibration, keyed by IMU stream name, device prefix (``<dev>``),
            device serial or device name (looked up in that order).
        auto_bias: also estimate the gyro bias from stillness (:class:`GyroBiasEstimator`) and
            subtract it once its confidence reaches ``auto_bias_confidence``.
        auto_bias_confidence: see ``auto_bias``.
        **settings: filter settings (see :class:`OrientationFilter`); ``nominal_rate_hz`` defaults to
            each stream's.

    Raises:
        ConfigError: an input fails the unit/frame check, a mag stream has no IMU stream of the same
            device, two inputs would publish the same output name, or a filter setting is invalid.
    """

    accepts = SAMPLES

    def __init__(self, inputs: list[StreamInfo], filter: str = DEFAULT_FILTER,  # noqa: A002 - public keyword
                 calibrations: Mapping[str, ImuCalibration] | None = None, *, auto_bias: bool = False,
                 auto_bias_confidence: float = 0.9, **settings: Any) -> None:
        self.filter_kind = filter
        self._publish: Callable[[Any], None] | None = None
        self._tracks: dict[str, _Track] = {}
        self._mag_to_track: dict[str, _Track] = {}
        self.auto_bias_confidence = auto_bias_confidence
        cals = dict(calibrations or {})
        imus = [i for i in inputs if i.kind != "mag"]
        mags = [i for i in inputs if i.kind == "mag"]
        if not imus:
            raise ConfigError("orientation processor needs at least one IMU stream (kind 'imu')")
        used: dict[str, str] = {}
        for info in imus:
            ch = check_imu_stream(info)
            pre = _prefix(info.name)
            st = dict(settings)
            if st.get("nominal_rate_hz") is None and info.nominal_rate_hz:
                st["nominal_rate_hz"] = float(info.nominal_rate_hz)
            flt = OrientationFilter(filter, **st)
            cal = self._find_cal(cals, info)
            frame_note = ("sensor frame" if cal.mounting == (1.0, 0.0, 0.0, 0.0)
                          else "body (segment) frame via the mounting")
            extra = {"source": info.name, "filter": filter}
            outs = (
                StreamInfo(f"{pre}/orientation", "orientation", ("w", "x", "y", "z"), ("1", "1", "1", "1"),
                           info.nominal_rate_hz, info.device,
                           "quaternion rotating body-frame vectors into the world frame ENU (x east, y north, z up); "
                           "Hamilton, scalar first", info.clock, None, dict(extra)),
                StreamInfo(f"{pre}/gravity", "gravity", ("x", "y", "z"), ("m/s^2",) * 3, info.nominal_rate_hz,
                           info.device, f"{frame_note} of {info.name}; the accelerometer reading due to gravity (up)",
                           info.clock, None, dict(extra)),
                StreamInfo(f"{pre}/linear_acc", "linear_acc", ("x", "y", "z"), ("m/s^2",) * 3, info.nominal_rate_hz,
                           info.device, f"{frame_note} of {info.name}; accelerometer minus gravity", info.clock, None,
                           dict(extra)),
            )
            for o in outs:
                if o.name in used or o.name in {i.name for i in inputs}:
                    raise ConfigError(f"orientation output {o.name} of {info.name} collides with "
                                      f"{used.get(o.name, 'an input stream')}", source=info.name)
                used[o.name] = info.name
            tr = _Track(info, ch, flt, cal, outs)
            if auto_bias:
                tr.bias_est = GyroBiasEstimator()
            self._tracks[info.name] = tr
        by_prefix = {_prefix(t.info.name): t for t in self._tracks.values()}
        for info in mags:
            mtr = by_prefix.get(_prefix(info.name))
            if mtr is None:
                raise ConfigError(f"magnetometer stream {info.name} has no IMU stream of the same device among the "
                                  f"inputs ({', '.join(self._tracks)})", source=info.name)
            if mtr.mag is not None:
                raise ConfigError(f"IMU stream {mtr.info.name} has two magnetometer streams "
                                  f"({mtr.mag.stream}, {info.name})", source=info.name)
            mtr.mag = check_mag_stream(info, mtr.info)
            self._mag_to_track[info.name] = mtr
        for tr in self._tracks.values():
            tr.fast = filter == "fusion" and tr.mag is None and tr.bias_est is None and not settings.get("gyro_offset")
        self.samples_in = 0
        self.samples_out = 0
        self.mag_in = 0
        self.ignored_items = 0
        self.items_in = 0

    @staticmethod
    def _find_cal(cals: dict[str, ImuCalibration], info: StreamInfo) -> ImuCalibration:
        for key in (info.name, _prefix(info.name), info.device.serial, info.device.name):
            if key and key in cals:
                return cals[key]
        return ImuCalibration()

    # -- wiring ----------------------------------------------------------------------------------
    def output_streams(self) -> list[StreamInfo]:
        """The streams this processor publishes (declare them before data flows)."""
        return [o for t in self._tracks.values() for o in t.out]

    def bind(self, publish: Callable[[Any], None]) -> None:
        """Set the publish callable (called once before data flows)."""
        self._publish = publish

    def set_calibration(self, stream: str, cal: ImuCalibration) -> None:
        """Replace the calibration of an IMU input (e.g. after a yaw or mounting reset).

        Raises:
            KeyError: ``stream`` is not an IMU input.
        """
        self._tracks[stream].cal = cal

    def filter_of(self, stream: str) -> OrientationFilter:
        """The filter of an IMU input (for its counters and state)."""
        return self._tracks[stream].flt

    # -- data ------------------------------------------------------------------------------------
    def on_item(self, item: Any) -> None:
        """Process one ``Sample`` or ``SampleBatch`` (items of other streams are counted and ignored).

        Raises:
            RuntimeError: :meth:`bind` was not called.
        """
        if self._publish is None:
            raise RuntimeError("OrientationProcessor.bind(publish) was not called")
        tr = self._tracks.get(item.stream)
        if tr is None:
            mt = self._mag_to_track.get(item.stream)
            if mt is None:
                self.ignored_items += 1  # not ours (including our own outputs)
                return
            self._on_mag(mt, item)
            return
        self.items_in += 1
        if type(item) is Sample:
            if tr.fast:
                self._run_one(tr, item)
            else:
                self._run(tr, np.asarray([item.values], np.float64), np.asarray([item.t_bus_ns], np.int64), item)
        else:
            self._run(tr, np.asarray(item.values, np.float64), np.asarray(item.t_bus_ns, np.int64), item)

    def _t_s(self, tr: _Track, t_ns: np.ndarray) -> np.ndarray:
        if tr.origin_ns is None:
            tr.origin_ns = int(t_ns[0])
        return (t_ns - tr.origin_ns) / 1e9

    def _on_mag(self, tr: _Track, item: Any) -> None:
        assert tr.mag is not None
        if type(item) is Sample:
            v = np.asarray([item.values], np.float64)
            t_ns = np.asarray([item.t_bus_ns], np.int64)
        else:
            v = np.asarray(item.values, np.float64)
            t_ns = np.asarray(item.t_bus_ns, np.int64)
        if v.shape[0] == 0:
            return
        m = v[:, list(tr.mag.idx)]
        m = tr.cal.apply_mag(m)
        self.mag_in += v.shape[0]
        tr.flt.add_mag(self._t_s(tr, t_ns), m)

    def _run_one(self, tr: _Track, item: Sample) -> None:
        """One Sample with Fusion: the arithmetic of :meth:`_run` on plain floats (same results)."""
        v = item.values
        ch = tr.chans
        i0, i1, i2 = ch.acc_idx
        sc = ch.acc_scale
        ax, ay, az = v[i0] * sc, v[i1] * sc, v[i2] * sc
        j0, j1, j2 = ch.gyro_idx
        sc = ch.gyro_scale
        gx, gy, gz = v[j0] * sc, v[j1] * sc, v[j2] * sc
        cal = tr.cal
        if not cal.sensor_identity:
            (ax, ay, az), (gx, gy, gz) = cal.apply_one((ax, ay, az), (gx, gy, gz))
        if tr.origin_ns is None:
            tr.origin_ns = item.t_bus_ns
        t = (item.t_bus_ns - tr.origin_ns) / 1e9
        q, _ = tr.flt.update_one(t, (gx, gy, gz), (ax, ay, az))
        w, x, y, z = q
        g0 = G0
        grav = (2.0 * (x * z - w * y) * g0, 2.0 * (y * z + w * x) * g0, (w * w - x * x - y * y + z * z) * g0)
        lin = (ax - grav[0], ay - grav[1], az - grav[2])
        if not cal.body_identity:
            q = tuple(cal.body_orientation(np.array([q]))[0].tolist())
            grav = tuple(cal.to_body(np.array([grav]))[0].tolist())
            lin = tuple(cal.to_body(np.array([lin]))[0].tolist())
        self.samples_in += 1
        self.samples_out += 1
        pub = self._publish
        assert pub is not None
        o_q, o_g, o_l = tr.out
        s0 = tr.seq
        tr.seq = s0 + 1
        th, td, tb = item.t_host_ns, item.t_device_ns, item.t_bus_ns
        pub(Sample(o_q.name, s0, th, td, tb, q))
        pub(Sample(o_g.name, s0, th, td, tb, grav))
        pub(Sample(o_l.name, s0, th, td, tb, lin))

    def _run(self, tr: _Track, v: np.ndarray, t_ns: np.ndarray, item: Any) -> None:
        n = v.shape[0]
        if n == 0:
            return
        ch = tr.chans
        acc = v[:, ch.acc_sel] * ch.acc_scale
        gyro = v[:, ch.gyro_sel] * ch.gyro_scale
        cal = tr.cal
        if not cal.sensor_identity:
            acc, gyro, _ = cal.apply(acc, gyro)
        t = self._t_s(tr, t_ns)
        if tr.bias_est is not None:
            self._auto_bias(tr, t, gyro, acc)
            if tr.auto_bias is not None:
                gyro = gyro - tr.auto_bias
        res = tr.flt.update_many(t, gyro, acc)
        if cal.body_identity:
            q, grav, lin = res.q, res.gravity, res.linear_acc
        else:
            q = cal.body_orientation(res.q)
            grav = cal.to_body(res.gravity)
            lin = cal.to_body(res.linear_acc)
        self.samples_in += n
        self.samples_out += n
        pub = self._publish
        assert pub is not None
        o_q, o_g, o_l = tr.out
        s0 = tr.seq
        tr.seq += n
        if type(item) is Sample:
            th, td, tb = item.t_host_ns, item.t_device_ns, item.t_bus_ns
            pub(Sample(o_q.name, s0, th, td, tb, tuple(q[0].tolist())))
            pub(Sample(o_g.name, s0, th, td, tb, tuple(grav[0].tolist())))
            pub(Sample(o_l.name, s0, th, td, tb, tuple(lin[0].tolist())))
        else:
            seq = np.arange(s0, s0 + n, dtype=np.int64)
            pub(SampleBatch(o_q.name, seq, item.t_host_ns, item.t_device_ns, item.t_bus_ns, q))
            pub(SampleBatch(o_g.name, seq, item.t_host_ns, item.t_device_ns, item.t_bus_ns, grav))
            pub(SampleBatch(o_l.name, seq, item.t_host_ns, item.t_device_ns, item.t_bus_ns, lin))

    def _auto_bias(self, tr: _Track, t: np.ndarray, gyro: np.ndarray, acc: np.ndarray) -> None:
        est = tr.bias_est
        assert est is not None
        est.update(t, gyro, acc)
        if t[-1] - tr.auto_bias_checked_s >= 1.0:  # the estimate costs up to ~1 ms: once a second
            tr.auto_bias_checked_s = float(t[-1])
            e = est.estimate
            if e.confidence >= self.auto_bias_confidence:
                if tr.auto_bias is None:
                    log.info("%s: auto gyro bias %s deg/s (confidence %.2f, %d still periods)", tr.info.name,
                             np.round(np.degrees(e.bias), 3).tolist(), e.confidence, e.periods)
                tr.auto_bias = e.bias.copy()

    def auto_bias(self, stream: str) -> np.ndarray | None:
        """The automatic bias applied to an IMU input (rad/s), or ``None`` while not confident."""
        return self._tracks[stream].auto_bias

    def stats(self) -> dict[str, Any]:
        """Counters: items and samples in and out, mag readings, ignored items, and per input its
        filter's counters (gaps skipped, non-increasing, rejected inputs, mag use)."""
        per = {name: tr.flt.stats() for name, tr in self._tracks.items()}
        return {"items_in": self.items_in, "samples_in": self.samples_in, "samples_out": self.samples_out,
                "mag_in": self.mag_in, "ignored_items": self.ignored_items,
                "gaps_skipped": sum(p["gaps"] for p in per.values()),
                "rejected_inputs": sum(p["rejected"] + p["non_increasing"] for p in per.values()),
                "streams": per}

    @property
    def gaps_skipped(self) -> int:
        """Gaps not integrated across, over every input."""
        return sum(tr.flt.gaps for tr in self._tracks.values())

    @property
    def rejected_inputs(self) -> int:
        """Samples not integrated (invalid gyro or time not after the previous), over every input."""
        return sum(tr.flt.rejected + tr.flt.non_increasing for tr in self._tracks.values())
