"""Orientation filters: accuracy against optical motion capture, agreement with Fusion, yaw drift
after automatic gyro-bias calibration, and throughput (filter and bus processor).

    .venv/bin/python benchmarks/bench_fusion.py [--quick]

Data, read in place from ``../shared/traces/a_imu_csv`` (never copied into the repository):

* ``gaitmap_walk/``: two foot IMUs at 204.8 Hz (no magnetometer), ground-truth foot orientation
  from optical mocap per stride (strides follow ``stride_events_sample.csv``; the quaternions are
  world -> foot; mocap frame = int(start * 100 / 204.8) + sample, 0 ms lag, per the trace README).
* ``fusion_sensor_data.csv``: an x-io IMU with magnetometer, ~99 Hz with jitter.

How accuracy is evaluated (what is fitted and what is not):

* Each filter runs once, continuously, over the whole recording of a foot, exactly as in
  production (initialised from the first accelerometer reading; dt from the timestamps
  ``index / 204.8``). Nothing is re-initialised per stride.
* Its sensor -> world orientation is interpolated (slerp) at each mocap sample time.
* Fitted, per foot, on *half* the strides and evaluated on the other half (2-fold cross validation
  on even/odd strides): one mounting rotation sensor -> foot (3 parameters) and one tilt of the
  mocap world's vertical against gravity (2 parameters). Closed-form start (Wahba on the rotation
  axes of within-stride motion), then scipy least squares on the angle error.
* Per stride, as gaitmap's evaluation does, the world heading reference is aligned at the stride's
  *first* mocap sample only (one yaw angle per stride, from the ground truth). Without a
  magnetometer heading is unobservable, so this is the only per-stride freedom; the tilt and all
  the motion within the stride are the filter's.
* Also reported (B, gaitmap style): the stride's whole initial orientation taken from the ground
  truth, so only the motion within the stride is the filter's (same fitted mounting).
* Error = rotation angle between ground truth and estimate at every mocap sample; per stride the
  RMS over its samples; reported as median and p90 over strides.

Yaw drift: the heading part of the error (twist about world z) per stride, with one alignment at
the first stride (same fitted mounting, all strides), regressed against time: the slope in deg/s
and its standard error. Raw gyro vs gyro minus the automatic bias estimate
(:func:`capture.calibration.estimate_gyro_bias` on the whole recording), and vs Fusion's own
gyro-offset learner.

Measurement script: prints figures and PASS/FAIL per target, always exits 0.
"""

from __future__ import annotations

import csv
import math
import os
import sys
import time
from itertools import pairwise
from pathlib import Path

import numpy as np
from _common import check, header, pct, summary
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation, Slerp

from capture.calibration import GyroBiasEstimator, fit_magnetometer, still_bias
from capture.orientation import FILTERS, OrientationFilter, OrientationProcessor
from capture.quat import quat_conj, quat_mul
from capture.sample import NO_TIME, DeviceIdentity, Sample, SampleBatch, StreamInfo

ROOT = Path(__file__).resolve().parent.parent
TRACES = ROOT.parent / "shared" / "traces" / "a_imu_csv"
XIO = TRACES / "fusion_sensor_data.csv"
GAIT = TRACES / "gaitmap_walk"
FS = 204.8
G = 9.80665
QUICK = "--quick" in sys.argv


# ------------------------------------------------------------------------------------------------
# data

def load_xio() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    d = np.loadtxt(XIO, delimiter=",", skiprows=1)
    return d[:, 0], np.radians(d[:, 1:4]), d[:, 4:7] * G, d[:, 7:10]


def load_gait() -> tuple[dict, dict, dict]:
    d = np.loadtxt(GAIT / "imu_sample_not_rotated.csv", delimiter=",", skiprows=2)
    imu = {"left": (d[:, 1:4], np.radians(d[:, 4:7])), "right": (d[:, 7:10], np.radians(d[:, 10:13]))}
    ev: dict[str, list[dict[str, float]]] = {}
    with open(GAIT / "stride_events_sample.csv") as f:
        for row in csv.DictReader(f):
            ev.setdefault(row["foot"], []).append({k: float(v) for k, v in row.items() if k != "foot"})
    gt: dict[str, dict[int, list[list[float]]]] = {}
    with open(GAIT / "orientation_sample.csv") as f:
        r = csv.reader(f)
        next(r)
        for fields in r:
            gt.setdefault(fields[0].split("_")[0], {}).setdefault(int(fields[1]), []).append(
                [float(x) for x in fields[3:7]])
    gtq = {foot: {s: np.array(v) for s, v in dd.items()} for foot, dd in gt.items()}
    return imu, ev, gtq


# ------------------------------------------------------------------------------------------------
# gait evaluation

class GaitEval:
    """Estimated vs mocap foot orientation, per stride (see the module docstring).

    ``A`` is the filter's sensor -> world orientation at the mocap samples, ``G`` the ground truth
    (foot -> mocap world). The fitted model is ``G ~ tilt * A * mount^-1``: ``mount`` the sensor ->
    foot mounting rotation, ``tilt`` the tilt of the mocap world's vertical against gravity.
    """

    def __init__(self, q_est: np.ndarray, events: list[dict[str, float]], gt: dict[int, np.ndarray]) -> None:
        n = q_est.shape[0]
        tt = np.arange(n) / FS
        sl = Slerp(tt, Rotation.from_quat(q_est, scalar_first=True))
        ts, gts, sid = [], [], []
        for k, e in enumerate(events):
            q = gt[int(e["s_id"])]
            t = (int(e["start"] * 100 / FS) + np.arange(len(q))) / 100.0
            keep = t <= tt[-1]
            ts.append(t[keep])
            gts.append(q[keep])
            sid.append(np.full(int(keep.sum()), k))
        self.t = np.concatenate(ts)
        self.sid = np.concatenate(sid)
        self.ns = len(events)
        self.first = np.r_[0, np.flatnonzero(np.diff(self.sid)) + 1]
        self.A = sl(self.t)                                   # sensor -> world (estimate)
        self.G = Rotation.from_quat(np.concatenate(gts)).inv()  # foot -> mocap world (scipy: scalar last)

    def _est(self, mount: Rotation, tilt: Rotation) -> Rotation:
        return tilt * self.A * mount.inv()

    def errors(self, mount: Rotation, tilt: Rotation, full_init: bool = False) -> np.ndarray:
        """Angle error per mocap sample. Per stride the heading is aligned at its first sample, or with
        ``full_init`` the whole orientation (gaitmap style: only the motion within the stride is the filter's)."""
        est = self._est(mount, tilt)
        offset = self.G[self.first] * est[self.first].inv()   # per stride, truth vs estimate at its start
        if full_init:
            align = offset
        else:
            qd = offset.as_quat()
            align = Rotation.from_euler("z", (2 * np.arctan2(qd[:, 2], qd[:, 3]))[:, None])
        return np.degrees((self.G.inv() * (align[self.sid] * est)).magnitude())

    def stride_rms(self, e: np.ndarray) -> np.ndarray:
        return np.sqrt(np.bincount(self.sid, e * e, self.ns) / np.bincount(self.sid, None, self.ns))

    def _init_mounting(self, mask: np.ndarray) -> Rotation:
        # within a stride, G0^-1 G(t) = mount (A0^-1 A(t)) mount^-1: rotation axes map by the mounting
        rf, rs = [], []
        for k in np.unique(self.sid[mask]):
            idx = np.flatnonzero(self.sid == k)
            i0 = idx[0]
            for i in idx[5::5]:
                a = (self.G[i0].inv() * self.G[i]).as_rotvec()
                b = (self.A[i0].inv() * self.A[i]).as_rotvec()
                if np.linalg.norm(a) > 0.2:
                    rf.append(a)
                    rs.append(b)
        r, _ = Rotation.align_vectors(np.array(rf), np.array(rs))
        return r

    def fit(self, strides: list[int]) -> tuple[Rotation, Rotation]:
        mask = np.isin(self.sid, strides)
        mount0 = self._init_mounting(mask)

        def res(p: np.ndarray) -> np.ndarray:
            return self.errors(Rotation.from_rotvec(p[:3]), Rotation.from_rotvec([p[3], p[4], 0.0]))[mask]

        r = least_squares(res, np.r_[mount0.as_rotvec(), 0.0, 0.0], x_scale=0.1)
        return Rotation.from_rotvec(r.x[:3]), Rotation.from_rotvec([r.x[3], r.x[4], 0.0])

    def cross_validated(self) -> tuple[np.ndarray, np.ndarray, list[tuple[Rotation, Rotation]]]:
        """Per-stride RMS with heading-only alignment, and with full initial orientation (same fits)."""
        even, odd = list(range(0, self.ns, 2)), list(range(1, self.ns, 2))
        out = np.empty(self.ns)
        out_full = np.empty(self.ns)
        fits = []
        for train, test in ((even, odd), (odd, even)):
            mount, tilt = self.fit(train)
            fits.append((mount, tilt))
            out[test] = self.stride_rms(self.errors(mount, tilt))[test]
            out_full[test] = self.stride_rms(self.errors(mount, tilt, full_init=True))[test]
        return out, out_full, fits

    def heading_drift(self, mount: Rotation, tilt: Rotation) -> tuple[float, float, np.ndarray, np.ndarray]:
        """Slope (deg/s) and its standard error of the per-stride heading error, one alignment."""
        offset = self.G * self._est(mount, tilt).inv()
        qd = offset.as_quat()
        h = np.degrees(np.unwrap(2 * np.arctan2(qd[:, 2], qd[:, 3])))
        hs = np.array([np.median(h[self.sid == k]) for k in range(self.ns)])
        ts = np.array([np.median(self.t[self.sid == k]) for k in range(self.ns)])
        hs -= hs[0]
        p, cov = np.polyfit(ts, hs, 1, cov=True)
        return float(p[0]), float(math.sqrt(cov[0, 0])), ts, hs


def run_filter(kind: str, t: np.ndarray, gyro: np.ndarray, acc: np.ndarray, mag: np.ndarray | None = None,
               **settings: object) -> tuple[np.ndarray, float]:
    f = OrientationFilter(kind, **settings)
    t0 = time.perf_counter()
    q = f.update_many(t, gyro, acc, mag).q
    return q, time.perf_counter() - t0


def angle_deg(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    d = quat_mul(quat_conj(q1), q2)
    return np.degrees(2 * np.arctan2(np.linalg.norm(d[:, 1:], axis=1), np.abs(d[:, 0])))


# ------------------------------------------------------------------------------------------------
# sections

def section_gait() -> tuple[dict[str, dict[str, float]], dict]:
    print("-- orientation accuracy on the gaitmap foot IMUs (204.8 Hz, no magnetometer) vs optical mocap")
    print("   fitted per foot on half the strides, evaluated on the other half (2-fold): mounting rotation (3) +")
    print("   mocap-vertical tilt (2); per stride: heading aligned at its first mocap sample."
          " Per-stride RMS error, deg.")
    imu, ev, gt = load_gait()
    out: dict[str, dict[str, float]] = {}
    pooled: dict[str, list[float]] = {}
    keep = {}
    print("   A = heading aligned per stride (tilt is the filter's); B = gaitmap style, the stride's initial"
          " orientation")
    print("   taken from the ground truth (only the motion within the stride is the filter's)")
    print(f"   {'filter':10s} {'foot':6s} {'A median':>8s} {'p90':>6s} {'max':>6s} {'B median':>8s} {'p90':>6s}"
          f"  strides  fitted tilt (deg)  run time")
    for kind in FILTERS:
        for foot in ("left", "right"):
            acc, gyr = imu[foot]
            t = np.arange(acc.shape[0]) / FS
            q, el = run_filter(kind, t, gyr, acc)
            e = GaitEval(q, ev[foot], gt[foot])
            rms, rms_b, fits = e.cross_validated()
            med, p90, mx = pct(rms, 50, 90, 100)
            med_b, p90_b = pct(rms_b, 50, 90)
            out.setdefault(kind, {})[foot] = med
            out[kind][foot + "_p90"] = p90
            out[kind][foot + "_B"] = med_b
            out[kind][foot + "_B_p90"] = p90_b
            pooled.setdefault(kind, []).extend(rms.tolist())
            tilt = "/".join(f"{np.degrees(np.linalg.norm(w.as_rotvec())):.2f}" for _, w in fits)
            print(f"   {kind:10s} {foot:6s} {med:8.2f} {p90:6.2f} {mx:6.2f} {med_b:8.2f} {p90_b:6.2f}  {e.ns:7d}"
                  f"  {tilt:>17s}  {el:6.2f} s")
            if kind == "fusion":
                keep[foot] = (e, fits)
    for foot in ("left", "right"):
        check(f"gait orientation accuracy (A), fusion (default), {foot} foot", out["fusion"][foot] <= 3.5,
              f"median per-stride RMS {out['fusion'][foot]:.2f} deg, p90 {out['fusion'][foot + '_p90']:.2f} "
              f"(target <= 3.5; mocap noise floor ~3.3)")
        check(f"gait orientation accuracy (B, gaitmap style), fusion (default), {foot} foot",
              out["fusion"][foot + "_B"] <= 3.5,
              f"median per-stride RMS {out['fusion'][foot + '_B']:.2f} deg, p90 {out['fusion'][foot + '_B_p90']:.2f} "
              f"(target <= 3.5)")
    print("   [info] A, both feet pooled (57 strides), median per-stride RMS: "
          + ", ".join(f"{k} {np.median(v):.2f}" for k, v in pooled.items()))
    for foot, (e, fits) in keep.items():
        err = e.errors(*fits[0])
        phase = np.concatenate([np.linspace(0, 1, int(np.sum(e.sid == k)), endpoint=False) for k in range(e.ns)])
        bins = [0, 0.1, 0.3, 0.5, 0.7, 0.9, 1.0]
        prof = [float(np.median(err[(phase >= a) & (phase < b)])) for a, b in pairwise(bins)]
        print(f"   [info] fusion {foot}: median error by stride phase (0 = mid-stance, min_vel) "
              + ", ".join(f"{a:.1f}-{b:.1f}: {v:.2f}" for (a, b), v in zip(pairwise(bins), prof, strict=True)))
    both = np.median([out["fusion"]["left"], out["fusion"]["right"]])
    print(f"   [info] fusion, median of the two feet's medians: {both:.2f} deg")
    print()
    return out, keep


def section_drift() -> None:
    print("-- yaw drift on the gait recording (heading error vs mocap, per stride, slope over 38 s)")
    imu, ev, gt = load_gait()
    print(f"   {'foot':6s} {'gyro':50s} {'slope deg/s':>12s} {'+- se':>7s}  bias subtracted (deg/s)")
    res: dict[str, dict[str, float]] = {}
    for foot in ("left", "right"):
        acc, gyr = imu[foot]
        t = np.arange(acc.shape[0]) / FS
        be = GyroBiasEstimator()
        be.update(t, gyr, acc)
        est = be.finish()
        periods = ", ".join(f"{a:.2f}-{b:.2f} s" for a, b in be.still_periods())
        print(f"   {foot}: auto estimate {np.round(np.degrees(est.bias), 3).tolist()} deg/s, std "
              f"{np.round(np.degrees(est.std), 3).tolist()}, confidence {est.confidence:.2f};"
              f" still periods found: {periods}")
        sb = still_bias(gyr[:140], acc[:140])
        applied = est.bias if est.confidence >= 0.9 else np.zeros(3)
        q_raw, _ = run_filter("fusion", t, gyr, acc)
        e = GaitEval(q_raw, ev[foot], gt[foot])
        mount, tilt = e.fit(list(range(e.ns)))  # the mounting is a constant of the recording: fitted once on raw
        variants = [("raw gyro", gyr, {}, None),
                    ("auto bias as the processor applies it (conf>=0.9)", gyr - applied, {}, applied),
                    ("auto bias estimate, applied regardless", gyr - est.bias, {}, est.bias),
                    ("explicit still period (first 0.68 s, still_bias)", gyr - sb.bias, {}, sb.bias),
                    ("fusion gyro_offset learner", gyr, {"gyro_offset": True}, None)]
        for label, g, st, bias in variants:
            q, _ = run_filter("fusion", t, g, acc, None, **st)
            slope, se, _, _ = GaitEval(q, ev[foot], gt[foot]).heading_drift(mount, tilt)
            res.setdefault(foot, {})[label] = slope
            bs = "" if bias is None else str(np.round(np.degrees(bias), 3).tolist())
            print(f"   {foot:6s} {label:50s} {slope:+12.4f} {se:7.4f}  {bs}")
        res[foot]["se"] = se
    for foot in ("left", "right"):
        a = abs(res[foot]["auto bias as the processor applies it (conf>=0.9)"])
        check(f"yaw drift after auto bias, {foot} foot", a < 0.01,
              f"|slope| {a:.4f} deg/s (raw {abs(res[foot]['raw gyro']):.4f}; the standard error of a slope measured "
              f"this way is ~{res[foot]['se']:.3f} deg/s; target < 0.01)")
    print()


def section_xio() -> None:
    print("-- fusion_sensor_data.csv (x-io, ~99 Hz with jitter): every filter vs fusion, angle difference, deg")
    t, gyr, acc, mag = load_xio()
    sl_all = slice(500, None)           # after 5 s of convergence
    sl_clean = slice(500, 10000)        # before the magnetic disturbance Fusion rejects (samples 10000-13000)
    print(f"   {'mode':5s} {'filter':10s} {'all: median':>11s} {'p95':>7s}   {'no disturbance: median':>22s}"
          f" {'p95':>7s}   {'samples/s':>9s}")
    for use_mag in (True, False):
        ref, el = run_filter("fusion", t, gyr, acc, mag if use_mag else None)
        mode = "MARG" if use_mag else "IMU"
        print(f"   {mode:5s} {'fusion':10s} {'(reference)':>11s} {'':7s}   {'':22s} {'':7s}   {len(t) / el:9.0f}")
        for kind in FILTERS[1:]:
            q, el = run_filter(kind, t, gyr, acc, mag if use_mag else None)
            d = angle_deg(ref, q)
            a50, a95 = pct(d[sl_all], 50, 95)
            c50, c95 = pct(d[sl_clean], 50, 95)
            print(f"   {mode:5s} {kind:10s} {a50:11.2f} {a95:7.2f}   {c50:22.2f} {c95:7.2f}   {len(t) / el:9.0f}")
    f = fit_magnetometer(mag[:10000])
    fa = fit_magnetometer(mag)
    print(f"   magnetometer fit (first 10,000 readings, before the disturbance): model {f.model}, hard iron "
          f"{np.round(f.hard_iron, 2).tolist()} uT, field {f.field:.1f} uT, coverage {f.coverage:.2f}, |m| spread "
          f"(std/mean) {f.spread_before * 100:.2f}% -> {f.spread_after * 100:.2f}%")
    print(f"   magnetometer fit (all readings, disturbance trimmed as outliers: {len(mag) - fa.inliers}): model "
          f"{fa.model}, field {fa.field:.1f}, |m| spread {fa.spread_before * 100:.2f}% -> {fa.spread_after * 100:.2f}%")
    print()


def _imu_info(name: str, rate: float) -> StreamInfo:
    return StreamInfo(name, "imu", ("ax", "ay", "az", "gx", "gy", "gz", "temp"),
                      ("m/s^2",) * 3 + ("rad/s",) * 3 + ("degC",), rate,
                      DeviceIdentity(kind="bench", name=name.split("/", maxsplit=1)[0]), "sensor frame")


def section_throughput() -> None:
    print("-- throughput (2 shared cores: medians of repeated runs)")
    t, gyr, acc, mag = load_xio()
    n = len(t)
    reps = 3 if QUICK else 5
    # filter alone
    rates = []
    for _ in range(reps):
        _, el = run_filter("fusion", t, gyr, acc)
        rates.append(n / el)
    fusion_rate = float(np.median(rates))
    rates_m = []
    for _ in range(reps):
        _, el = run_filter("fusion", t, gyr, acc, mag)
        rates_m.append(n / el)
    # baseline: ahrs Madgwick in a plain per-sample loop (library only, no wrapper)
    from ahrs.filters import Madgwick

    base = []
    m_n = 2000
    for _ in range(reps):
        f = Madgwick()
        q = np.array([1.0, 0.0, 0.0, 0.0])
        dts = np.diff(t[: m_n + 1])
        t0 = time.perf_counter()
        for i in range(m_n):
            q = f.updateIMU(q, gyr[i + 1], acc[i + 1], dt=dts[i])
        base.append(m_n / (time.perf_counter() - t0))
    base_rate = float(np.median(base))
    print(f"   OrientationFilter('fusion').update_many, IMU: {fusion_rate:,.0f} samples/s; with magnetometer: "
          f"{np.median(rates_m):,.0f} samples/s")
    print(f"   baseline: ahrs Madgwick.updateIMU in a per-sample loop: {base_rate:,.0f} samples/s "
          f"({fusion_rate / base_rate:.0f}x slower than fusion)")
    check("fusion filter throughput", fusion_rate >= 100_000, f"{fusion_rate:,.0f} samples/s (target >= 100,000)")

    # the processor: 17 streams at 200 Hz, 10 s of data, fed as SampleBatch items of 20 samples and as Samples
    streams = [f"d{i}/imu" for i in range(17)]
    rate = 200.0
    secs = 4.0 if QUICK else 10.0
    per = int(rate * secs)
    idx = np.arange(per) % n
    vals = np.hstack([acc[idx], gyr[idx], np.full((per, 1), 25.0)])
    tb = (np.arange(per) * (1e9 / rate)).astype(np.int64) + 10**12
    total = per * len(streams)
    out_count = [0]

    def sink(item: object) -> None:
        out_count[0] += 1

    def run_batches(bsz: int) -> float:
        p = OrientationProcessor([_imu_info(s, rate) for s in streams], "fusion")
        p.bind(sink)
        items = []
        for s in streams:
            for k in range(0, per, bsz):
                sl = slice(k, k + bsz)
                m = tb[sl].shape[0]
                items.append(SampleBatch(s, np.arange(k, k + m, dtype=np.int64), tb[sl], np.full(m, NO_TIME, np.int64),
                                         tb[sl], vals[sl]))
        items.sort(key=lambda b: int(b.t_bus_ns[0]))
        c0 = time.process_time()
        for it in items:
            p.on_item(it)
        return time.process_time() - c0

    def run_samples() -> float:
        p = OrientationProcessor([_imu_info(s, rate) for s in streams], "fusion")
        p.bind(sink)
        rows = vals.tolist()
        items = [Sample(s, k, int(tb[k]), None, int(tb[k]), tuple(rows[k])) for k in range(per) for s in streams]
        c0 = time.process_time()
        for it in items:
            p.on_item(it)
        return time.process_time() - c0

    for bsz in (20, 200):
        cpu = float(np.median([run_batches(bsz) for _ in range(reps)]))
        sps = total / cpu
        frac = (17 * 200) / sps
        print(f"   OrientationProcessor, 17 streams x 200 Hz as SampleBatch items of {bsz}: {sps:,.0f} samples/s"
              f" of CPU -> 17 IMUs at 200 Hz cost {frac * 100:.1f}% of one core")
        if bsz == 20:
            check("processor, 17 IMUs x 200 Hz in batches of 20 (100 ms)", frac < 0.05,
                  f"{frac * 100:.2f}% of one core (target < 5%)")
    cpu = float(np.median([run_samples() for _ in range(max(1, reps - 2))]))
    sps = total / cpu
    print(f"   OrientationProcessor, one Sample at a time: {sps:,.0f} samples/s -> 17 IMUs at 200 Hz cost "
          f"{3400 / sps * 100:.1f}% of one core")
    print()


def main() -> None:
    header("bench_fusion: orientation filters - accuracy, agreement, yaw drift, throughput")
    if not XIO.is_file() or not GAIT.is_dir():
        print(f"   traces not found under {TRACES} (../shared/traces must sit beside the project)")
        return
    print(f"   data: {TRACES}")
    print()
    section_gait()
    section_drift()
    section_xio()
    section_throughput()
    summary()


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
