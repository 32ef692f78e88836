"""Motion-cycle extraction (issue #6): speed, accuracy and real gait, beside two peers in the same run.

    .venv/bin/python benchmarks/bench_cycles.py            # a few minutes (stumpy's mstump dominates)
    .venv/bin/python benchmarks/bench_cycles.py --quick    # fewer repeats and cases, mstump only where short

Targets (issue #6):

* speed, the whole pipeline ``cycles.extract``: 254 channels x 4 loops at 120 Hz in at most 30 ms,
  7,804 channels x 4 loops in at most 1 s (median of repeated runs); 1, 12 and 2,611 channels are
  timed too;
* accuracy on jittered synthetic loops (3-6 loops, +-10% loop durations, noise 0.03, 1, 3 and 12
  channels, plus harmonic takes: three channels carrying the loop's first, second and third harmonics,
  so that parts of a loop look alike, the case for which Ciccone 2019, section 5.3, takes the median
  period over several seeds): median period error under 0.5%, max under 3%, never a half, double
  (error beyond +-30%) or missing answer;
* real data, the gaitmap walk (each foot's IMU and each foot's mocap markers, the whole take with
  its turn): period within 0.5% of the median annotated stride, cuts at a consistent gait phase.

**Peers** (``cycle_baselines.py``): the FFT autocorrelation (channels standardised, power spectra
summed, first peak at or above 0.9 of the highest after the first zero crossing, parabolic
refinement), the frequency analysis that Ciccone 2019, section 5.1, sets aside because performed
loops vary in duration (``docs/design/cycles.md``), and stumpy's multi-dimensional matrix profile
(``stumpy.mstump``, window 0.5 s; the period is the fundamental of the nearest-neighbour spacings of
the all-dimension profile). stumpy is the ``bench`` extra (``pip install -e .[bench]``); without it
its columns read n/a. Its numba JIT (the first call in a process) is timed separately and excluded
from its per-call times. mstump runs (median of 5 / 3 runs up to 254 channels, once above) where it
should finish within a minute (10 s with ``--quick``), judged from the previous size's time scaled as
channels^1.2; otherwise "skipped". Its parallel numba kernels suffer most from other work on the machine.

**Data.** Speed and accuracy use ``sim_devices.loops.jittered_loops``: the truth is the take's
``period_s`` (the mean loop duration). The speed takes are 4 loops of a nominal 1 s at 120 Hz (about
480 samples), noise 0.03. The gait truth is the median annotated stride duration per foot
(``stride_borders_sample.csv``, sample indices at 204.8 Hz in both folders, also for the 100 Hz mocap;
checked below from the spans). Cut consistency: each cut time's phase inside the annotated stride
that contains it, ``(cut - start) / (end - start)``; the circular standard deviation of those phases
is printed in % of a stride (a gait event at one phase gives a small spread), and the benchmark's
threshold for "consistent" is 5% of a stride (about 55 ms).

Wall times are medians of repeated runs with ``time.perf_counter``; other work on the machine skews
them (the header prints the load). Measurement script: prints PASS/FAIL per target, always exits 0.
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cycle_baselines as cb
import numpy as np
from _common import check, header, summary

from sim_devices.loops import jittered_loops

if TYPE_CHECKING:
    from collections.abc import Callable

    from cycles import Cycle

_extract: Callable[..., Cycle] | None = None
EXTRACT_ERR = ""
try:
    from cycles import extract
except ImportError as _exc:  # pragma: no cover - depends on the tree
    EXTRACT_ERR = f"cycles.extract is not available ({_exc})"
else:
    _extract = extract

ROOT = Path(__file__).resolve().parent.parent
TRACES = ROOT.parent / "shared" / "traces"
IMU_DIR = TRACES / "a_imu_csv" / "gaitmap_walk"
MOCAP_DIR = TRACES / "d_mocap_cyclic" / "gaitmap_walk"
IMU_HZ = 204.8
MOCAP_HZ = 100.0

SPEED_SIZES = (1, 12, 254, 2611, 7804)
SPEED_TARGETS_S = {254: 0.030, 7804: 1.0}
MSTUMP_LIMIT_S = 60.0
MSTUMP_LIMIT_QUICK_S = 10.0
WRONG_MULTIPLE = 0.30      # |error| beyond this is a half / double (or worse) answer
ACC_MEDIAN = 0.005
ACC_MAX = 0.03
GAIT_TOL = 0.005
PHASE_SPREAD_MAX = 5.0     # % of a stride


def have_extract() -> bool:
    return _extract is not None


def extract_period(t: np.ndarray, x: np.ndarray) -> Cycle:
    """``cycles.extract`` with its defaults (seed 0)."""
    if _extract is None:
        raise RuntimeError(EXTRACT_ERR)
    return _extract(t, x)


def timed(fn: Callable[[], Any], reps: int) -> tuple[float, Any, str]:
    """Median wall time of ``reps`` calls, the last result, and the error text if a call raised."""
    times = []
    out: Any = None
    for _ in range(max(1, reps)):
        t0 = time.perf_counter()
        try:
            out = fn()
        except Exception as exc:  # a benchmark reports, it does not crash
            return time.perf_counter() - t0, None, f"{type(exc).__name__}: {exc}"
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out, ""


def fmt_s(s: float) -> str:
    if not math.isfinite(s):
        return "n/a"
    return f"{s * 1e3:.1f} ms" if s < 1.0 else f"{s:.2f} s"


def ratio(a: float, b: float) -> str:
    return f"{a / b:.1f}x" if math.isfinite(a) and math.isfinite(b) and b > 0 else "n/a"


def fmt_err(e: float) -> str:
    return "n/a" if not math.isfinite(e) else f"{e * 100:+.2f}%"


# ---------------------------------------------------------------------------------------------- speed


def bench_speed(quick: bool) -> None:
    print("-- speed: whole pipeline on 4 jittered loops at 120 Hz (noise 0.03), median wall time")
    if cb.have_stumpy():
        t0 = time.perf_counter()
        cb.mstump_warmup()
        print(f"   stumpy's numba JIT (first mstump call in this process, excluded below): "
              f"{time.perf_counter() - t0:.1f} s")
    else:
        print("   stumpy is not installed (pip install -e .[bench]): mstump columns n/a")
    if not have_extract():
        print(f"   {EXTRACT_ERR}: extract columns n/a")
    limit = MSTUMP_LIMIT_QUICK_S if quick else MSTUMP_LIMIT_S
    print(f"   {'channels':>8} {'samples':>7} {'extract':>10} {'(reps)':>6} {'err':>7} {'ACF':>9} {'err':>7} "
          f"{'mstump':>10} {'err':>7} {'extract/ACF':>11} {'mstump/extract':>14}")
    last_mstump: tuple[int, float] | None = None
    results: dict[int, float] = {}
    for n_ch in SPEED_SIZES:
        take = jittered_loops(4, channels=n_ch, rate_hz=120.0, noise=0.03, seed=1)
        truth = take.period_s
        big = n_ch >= 2000
        reps = (3 if big else 7) if quick else (5 if big else 21)
        te, cyc, err = (timed(partial(extract_period, take.t, take.values), reps) if have_extract()
                        else (float("nan"), None, EXTRACT_ERR))
        if err:
            te = float("nan")
        e_ext = cyc.period_s / truth - 1 if cyc is not None else float("nan")
        ta, pa, _ = timed(partial(cb.acf_period, take.t, take.values), reps)
        e_acf = pa / truth - 1 if pa is not None else float("nan")
        tm, e_m, m_txt = float("nan"), float("nan"), "n/a"
        if cb.have_stumpy():
            # the previous size's time, extrapolated as channels^1.2 (on an idle 2-core machine mstump took
            # 1.4 s at 254 channels, 7.2 s at 1,000 and 19 s at 2,611; with another process busy on one
            # core its parallel kernels ran up to 30x slower)
            est = 0.0 if last_mstump is None else last_mstump[1] * (n_ch / last_mstump[0]) ** 1.2
            if est > limit:
                m_txt = f"skipped (>{limit:.0f} s)"
            else:
                m_reps = 1 if n_ch > 254 or quick else (3 if n_ch == 254 else 5)
                tm, pm, _ = timed(partial(cb.mstump_period, take.t, take.values), m_reps)
                e_m = pm / truth - 1 if pm is not None else float("nan")
                m_txt = fmt_s(tm)
                last_mstump = (n_ch, tm)
        results[n_ch] = te
        print(f"   {n_ch:>8} {take.t.size:>7} {fmt_s(te):>10} {reps:>6} {fmt_err(e_ext):>7} {fmt_s(ta):>9} "
              f"{fmt_err(e_acf):>7} {m_txt:>10} {fmt_err(e_m):>7} "
              f"{ratio(te, ta):>11} {ratio(tm, te):>14}")
        if err:
            print(f"            extract failed: {err}")
    for n_ch, target in SPEED_TARGETS_S.items():
        te = results.get(n_ch, float("nan"))
        check(f"extract speed, {n_ch} channels x 4 loops <= {fmt_s(target)}",
              math.isfinite(te) and te <= target,
              f"median {fmt_s(te)}" if math.isfinite(te) else (EXTRACT_ERR or "extract failed"))
    print()


# ---------------------------------------------------------------------------------------------- accuracy


@dataclass
class Case:
    loops: int
    channels: int
    seed: int
    period: float
    harmonic: bool = False

    def take(self) -> Any:
        if self.harmonic:  # harmonics 1, 2, 3 of the loop (amplitudes 1, 1/2, 1/3), one per channel, noise 0.02
            return jittered_loops(self.loops, period_s=self.period, channels=3, harmonics=3, noise=0.02,
                                  time_jitter=0.2, per_channel_harmonic=True, seed=1000 + self.seed)
        return jittered_loops(self.loops, period_s=self.period, channels=self.channels, noise=0.03,
                              seed=100 * self.loops + 10 * self.channels + self.seed)

    def label(self) -> str:
        kind = "harm" if self.harmonic else f"{self.channels:>2}ch"
        return f"{self.loops} loops {kind} T={self.period:.2f} s seed {self.seed}"


@dataclass
class Tally:
    errors: list[float] = field(default_factory=list)     # answers within +-30%
    wrong: list[tuple[str, float]] = field(default_factory=list)
    missing: list[tuple[str, str]] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)

    def add(self, label: str, est: float | None, truth: float, why: str = "") -> None:
        if est is None or not math.isfinite(est):
            self.missing.append((label, why or "no answer (NaN)"))
            return
        e = est / truth - 1
        if abs(e) > WRONG_MULTIPLE:
            self.wrong.append((label, e))
        else:
            self.errors.append(e)

    def med(self) -> float:
        return float(np.median(np.abs(self.errors))) if self.errors else float("nan")

    def max(self) -> float:
        return float(np.max(np.abs(self.errors))) if self.errors else float("nan")


def cases(quick: bool) -> list[Case]:
    periods = (0.8, 1.0, 1.3, 0.9, 1.15)
    seeds = range(2) if quick else range(5)
    out = [Case(lp, ch, s, periods[s % len(periods)]) for lp in (3, 4, 5, 6) for ch in (1, 3, 12) for s in seeds]
    out += [Case(lp, 3, s, 1.0, harmonic=True) for lp in (3, 4, 5, 6) for s in (range(2) if quick else range(3))]
    return out


def bench_accuracy(quick: bool) -> None:
    cs = cases(quick)
    print(f"-- accuracy: {len(cs)} jittered takes (3-6 loops, +-10% loop durations, noise 0.03, 1/3/12 channels,"
          f" nominal T 0.8-1.3 s at 120 Hz; plus {sum(c.harmonic for c in cs)} harmonic takes: one harmonic"
          f" per channel, noise 0.02); truth = mean loop duration")
    methods: dict[str, Callable[[np.ndarray, np.ndarray], float]] = {}
    if have_extract():
        methods["extract"] = lambda t, x: float(extract_period(t, x).period_s)
    methods["ACF"] = cb.acf_period
    if cb.have_stumpy():
        methods["mstump"] = cb.mstump_period
    groups: dict[str, Callable[[Case], bool]] = {
        "1 ch": lambda c: not c.harmonic and c.channels == 1,
        "3 ch": lambda c: not c.harmonic and c.channels == 3,
        "12 ch": lambda c: not c.harmonic and c.channels == 12,
        "harmonic": lambda c: c.harmonic}
    tallies = {name: Tally() for name in methods}
    by_group = {(name, g): Tally() for name in methods for g in groups}
    for c in cs:
        take = c.take()
        for name, fn in methods.items():
            t0 = time.perf_counter()
            try:
                est, why = fn(take.t, take.values), ""
            except Exception as exc:  # a failure is counted as a missing answer
                est, why = None, f"{type(exc).__name__}: {exc}"
            tallies[name].seconds.append(time.perf_counter() - t0)
            tallies[name].add(c.label(), est, take.period_s, why)
            for g, sel in groups.items():
                if sel(c):
                    by_group[(name, g)].add(c.label(), est, take.period_s, why)
    print(f"   {'method':<8} {'median |err|':>12} {'max |err|':>10} {'half/double':>11} {'missing':>8} "
          f"{'median time':>11}   median |err| by group (" + ", ".join(groups) + ")")
    for name, tl in tallies.items():
        per = "  ".join(f"{fmt_err(by_group[(name, g)].med()).lstrip('+'):>6}" for g in groups)
        print(f"   {name:<8} {fmt_err(tl.med()).lstrip('+'):>12} {fmt_err(tl.max()).lstrip('+'):>10} "
              f"{len(tl.wrong):>11} {len(tl.missing):>8} {fmt_s(float(np.median(tl.seconds))):>11}   {per}")
    if not have_extract():
        print(f"   extract: n/a ({EXTRACT_ERR})")
    for name, tl in tallies.items():
        for lbl, e in tl.wrong:
            print(f"   {name}: wrong multiple on {lbl}: {fmt_err(e)}")
        for lbl, why in tl.missing[:5]:
            print(f"   {name}: no answer on {lbl}: {why}")
        if len(tl.missing) > 5:
            print(f"   {name}: ... {len(tl.missing) - 5} more without an answer")
    if "extract" in tallies:
        tl = tallies["extract"]
        acf = tallies["ACF"]
        check(f"extract accuracy, median |period error| < {ACC_MEDIAN:.1%}", tl.med() < ACC_MEDIAN,
              f"{fmt_err(tl.med()).lstrip('+')} over {len(tl.errors)} answers (ACF {fmt_err(acf.med()).lstrip('+')})")
        check(f"extract accuracy, max |period error| < {ACC_MAX:.0%}", tl.max() < ACC_MAX,
              f"{fmt_err(tl.max()).lstrip('+')} (ACF {fmt_err(tallies['ACF'].max()).lstrip('+')})")
        check("extract accuracy, no half/double/missing answer", not tl.wrong and not tl.missing,
              f"{len(tl.wrong)} half/double, {len(tl.missing)} missing of {len(cs)} "
              f"(ACF {len(tallies['ACF'].wrong)} / {len(tallies['ACF'].missing)})")
    else:
        for lbl in (f"median |period error| < {ACC_MEDIAN:.1%}", f"max |period error| < {ACC_MAX:.0%}",
                    "no half/double/missing answer"):
            check(f"extract accuracy, {lbl}", False, EXTRACT_ERR)
    print()


# ---------------------------------------------------------------------------------------------- real gait


def read_two_row_csv(path: Path) -> tuple[list[str], list[str], np.ndarray]:
    """A gaitmap CSV: two header rows (group, axis), first column the sample index."""
    with path.open(newline="") as f:
        r = csv.reader(f)
        top = next(r)
        sub = next(r)
    data = np.loadtxt(path, delimiter=",", skiprows=2)
    return top, sub, data


def read_strides(path: Path) -> dict[str, np.ndarray]:
    """Stride borders per foot: ``(k, 2)`` start and end sample indices."""
    out: dict[str, list[tuple[int, int]]] = {}
    with path.open(newline="") as f:
        for row in csv.DictReader(f):
            out.setdefault(row["foot"], []).append((int(row["start"]), int(row["end"])))
    return {k: np.asarray(sorted(v), np.float64) for k, v in out.items()}


def cut_phases(cuts: np.ndarray, strides_s: np.ndarray) -> np.ndarray:
    """Phase in [0, 1) of each cut inside the annotated stride that contains it (cuts outside are dropped)."""
    out = []
    for c in np.asarray(cuts, np.float64):
        inside = np.flatnonzero((strides_s[:, 0] <= c) & (c < strides_s[:, 1]))
        if inside.size:
            s, e = strides_s[inside[0]]
            out.append((c - s) / (e - s))
    return np.asarray(out)


def circ_std_pct(phases: np.ndarray) -> float:
    """Circular standard deviation of phases (1 = one stride), in % of a stride."""
    if phases.size == 0:
        return float("nan")
    r = float(abs(np.mean(np.exp(2j * np.pi * phases))))
    return float(np.sqrt(-2.0 * np.log(max(r, 1e-300))) / (2 * np.pi) * 100)


def circ_mean(phases: np.ndarray) -> float:
    return float(np.angle(np.mean(np.exp(2j * np.pi * phases))) / (2 * np.pi) % 1.0) if phases.size else float("nan")


def bench_gait(quick: bool) -> None:
    print("-- real data: the gaitmap walk (about 28-30 strides per foot, a 180 degree turn in the middle)")
    need = [IMU_DIR / "imu_sample_not_rotated.csv", IMU_DIR / "stride_borders_sample.csv",
            MOCAP_DIR / "mocap_sample.csv", MOCAP_DIR / "stride_borders_sample.csv"]
    missing = [str(p) for p in need if not p.exists()]
    if missing:
        print(f"   skipped: {', '.join(missing)} not found (../shared/traces must sit beside the project)")
        print()
        return
    top, sub, imu = read_two_row_csv(need[0])
    mtop, _, mocap = read_two_row_csv(need[2])
    strides = read_strides(need[1])
    strides_m = read_strides(need[3])
    n_imu, n_mo = imu.shape[0], mocap.shape[0]
    ends = max(float(s[:, 1].max()) for s in strides_m.values())
    same = all(np.array_equal(strides[k], strides_m[k]) for k in strides) and strides.keys() == strides_m.keys()
    print(f"   IMU {n_imu} samples at {IMU_HZ} Hz = {n_imu / IMU_HZ:.2f} s; mocap {n_mo} frames at {MOCAP_HZ:.0f} Hz"
          f" = {n_mo / MOCAP_HZ:.2f} s; stride files identical in both folders: {same}")
    print(f"   stride borders: last end = sample {ends:.0f}: as {IMU_HZ} Hz indices {ends / IMU_HZ:.2f} s (inside both"
          f" takes), as {MOCAP_HZ:.0f} Hz frames {ends / MOCAP_HZ:.2f} s (beyond the mocap take, which has {n_mo}"
          f" frames) -> the mocap folder's borders are {IMU_HZ} Hz indices too")
    if not np.all(np.diff(imu[:, 0]) == 1) or not np.all(np.diff(mocap[:, 0]) == 1):
        print("   note: a sample-index column is not consecutive")
    t_imu = imu[:, 0] / IMU_HZ
    t_mo = mocap[:, 0] / MOCAP_HZ
    side = {"left": ("left_sensor", "L_"), "right": ("right_sensor", "R_")}
    rows = []
    for foot, (sensor, prefix) in side.items():
        s_idx = strides[foot]
        truth = float(np.median(s_idx[:, 1] - s_idx[:, 0])) / IMU_HZ
        s_s = s_idx / IMU_HZ
        imu_cols = [i for i in range(1, len(top)) if top[i] == sensor]
        mo_cols = [i for i in range(1, len(mtop)) if mtop[i].startswith(prefix)]
        print(f"   {foot} foot: {len(s_idx)} annotated strides, median {truth:.4f} s (truth), spread"
              f" {np.min(s_idx[:, 1] - s_idx[:, 0]) / IMU_HZ:.3f}-{np.max(s_idx[:, 1] - s_idx[:, 0]) / IMU_HZ:.3f} s;"
              f" IMU channels {'/'.join(sub[i] for i in imu_cols)}; mocap channels"
              f" {' '.join(sorted({mtop[i] for i in mo_cols}))} x/y/z")
        for source, t, x in (("IMU", t_imu, imu[:, imu_cols]), ("mocap", t_mo, mocap[:, mo_cols])):
            rows.append((foot, source, truth, s_s, t, x))
    results = []
    for foot, source, truth, s_s, t, x in rows:
        if have_extract():
            te, cyc, err = timed(partial(extract_period, t, x), 1)
        else:
            te, cyc, err = float("nan"), None, EXTRACT_ERR
        e_ext = cyc.period_s / truth - 1 if cyc is not None else float("nan")
        e_acf = cb.acf_period(t, x) / truth - 1
        # information: the walk's out-and-back trend hides the strides from the ACF on positions
        e_vel = cb.acf_period(t, np.gradient(x, t, axis=0)) / truth - 1 if source == "mocap" else float("nan")
        tm, e_m = float("nan"), float("nan")
        if cb.have_stumpy() and not (quick and source == "IMU"):
            tm, pm, _ = timed(partial(cb.mstump_period, t, x), 1)
            e_m = pm / truth - 1 if pm is not None else float("nan")
        ph = cut_phases(cyc.cuts_s, s_s) if cyc is not None else np.empty(0)
        results.append((foot, source, truth, te, cyc, err, e_ext, e_acf, e_vel, tm, e_m, ph))
    print(f"   {'foot':<6} {'input':<6} {'truth':>8} {'extract':>8} {'time':>8} {'loops':>5} {'cuts in/all':>11} "
          f"{'phase':>6} {'spread':>7} {'ACF':>8} {'ACF vel':>8} {'mstump':>8} {'mstump time':>11}")
    for foot, source, truth, te, cyc, err, e_ext, e_acf, e_vel, tm, e_m, ph in results:
        cuts_txt = f"{ph.size}/{len(cyc.cuts_s)}" if cyc is not None else "n/a"
        loops_txt = str(cyc.loops) if cyc is not None else "n/a"
        print(f"   {foot:<6} {source:<6} {truth:>7.4f}s {fmt_err(e_ext):>8} {fmt_s(te):>8} {loops_txt:>5} "
              f"{cuts_txt:>11} {circ_mean(ph) * 100:>5.1f}% {circ_std_pct(ph):>6.2f}% {fmt_err(e_acf):>8} "
              f"{fmt_err(e_vel):>8} {fmt_err(e_m):>8} {('n/a' if not math.isfinite(tm) else fmt_s(tm)):>11}")
        if err:
            print(f"          extract failed: {err}")
    print("   phase = circular mean of (cut - stride start) / stride duration over the cuts inside annotated strides;")
    print("   spread = its circular std, % of a stride; ACF vel = the ACF on the marker velocities (information only:")
    print("   on the positions the walk's out-and-back trend hides the strides from the ACF)")
    for foot, source, _, _, _, err, e_ext, e_acf, _, _, e_m, ph in results:
        check(f"gait {foot} {source}: extract period within {GAIT_TOL:.1%} of the median stride",
              math.isfinite(e_ext) and abs(e_ext) <= GAIT_TOL,
              err or f"{fmt_err(e_ext)} (ACF {fmt_err(e_acf)}, mstump {fmt_err(e_m)})")
        spread = circ_std_pct(ph)
        check(f"gait {foot} {source}: cuts at one gait phase (circular std <= {PHASE_SPREAD_MAX:.0f}% of a stride)",
              math.isfinite(spread) and spread <= PHASE_SPREAD_MAX,
              err or f"{spread:.2f}% over {ph.size} cuts inside annotated strides")
    print()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true",
                    help="fewer repeats and cases; mstump only where it takes under 10 s, not on the IMU takes")
    args = ap.parse_args()
    header("bench_cycles: motion-cycle extraction vs FFT autocorrelation and stumpy mstump")
    if not have_extract():
        print(f"   NOTE: {EXTRACT_ERR}; the extract figures are n/a and its targets FAIL\n")
    bench_speed(args.quick)
    bench_accuracy(args.quick)
    bench_gait(args.quick)
    summary()


if __name__ == "__main__":
    main()
