"""A real iPhone recording (DISPEL / Konectom JSON, ``../shared/traces/e_smartphone``) replayed as
Sensor Logger HTTP push: ``phone_sim.dispel_to_sensorlogger`` -> ``SensorLoggerCodec`` ->
``SensorLoggerPhone.process_chunk`` with synthetic host arrival times (newest sample of the message +
a constant latency + seeded jitter, with clock drift). Every sample comes out, with the file's values
and times, and the clock fit puts it within a few ms of its true time."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from scipy.signal import find_peaks

from capture.sample import Chunk, Direction, Sample
from devices.phone import SensorLoggerPhone
from devices.transports import open_transport
from sim_devices.motion import G
from sim_devices.phone_sim import (
    dispel_samples,
    dispel_to_sensorlogger,
    synthetic_arrivals,
)

TRACE = (Path(__file__).resolve().parents[2] / ".." / "shared" / "traces" / "e_smartphone"
         / "dispel_ads_iphonex_sbt_utt_example.json")
HOST0 = 5 * 10**12
LATENCY_MS = 25.0
JITTER_MS = 15.0
DRIFT_PPM = 40.0


@pytest.fixture(scope="module")
def trace() -> Path:
    if not TRACE.is_file():
        pytest.skip(f"iPhone trace not found at {TRACE} (../shared/traces must sit beside the project)")
    return TRACE


def replay(trace: Path, standardised: bool = False, batch_s: float = 0.5):
    pushes = dispel_to_sensorlogger(trace, batch_s=batch_s, standardised=standardised)
    hosts = synthetic_arrivals([p.t_last_ns for p in pushes], seed=11, host0_ns=HOST0, latency_ms=LATENCY_MS,
                               jitter_ms=JITTER_MS, drift_ppm=DRIFT_PPM)
    chunks = [Chunk(p.body, h, Direction.RX) for p, h in zip(pushes, hosts, strict=True)]
    dev = SensorLoggerPhone("iphone", open_transport("loop://"),
                            {"rate": 20, "platform": "standardised" if standardised else "ios"})
    items = [x for c in chunks for x in dev.process_chunk(c)]
    by: dict[str, list[Sample]] = defaultdict(list)
    for x in items:
        if isinstance(x, Sample):
            by[x.stream.split("/", 1)[1]].append(x)
    return dev, chunks, pushes, items, by


@pytest.fixture(scope="module")
def run(trace):
    return replay(trace)


def cols(samples: list[Sample]):
    return (np.array([s.t_device_ns for s in samples], np.int64), np.array([s.t_bus_ns for s in samples], np.int64),
            np.array([s.values for s in samples], np.float64))


def test_every_sample_comes_out_with_the_files_values_and_times(trace, run):
    dev, chunks, pushes, _, by = run
    rec = dispel_samples(trace)
    assert rec.device["model"] == "iPhone X" and [lv.name for lv in rec.levels] == ["sbt", "utt"]
    assert rec.n_acc == 1228 and rec.n_gyro == 1228  # the README's 600 + 628
    assert len(by["acc"]) == len(by["phone_gravity"]) == rec.n_acc
    assert len(by["gyro"]) == rec.n_gyro
    assert not by.keys() - {"acc", "gyro", "phone_gravity"}
    acc_ts = np.concatenate([lv.acc_ts_ms for lv in rec.levels]) * 1_000_000
    gyro_ts = np.concatenate([lv.gyro_ts_ms for lv in rec.levels]) * 1_000_000
    ua = np.concatenate([lv.user_acc_g for lv in rec.levels])
    gr = np.concatenate([lv.gravity_g for lv in rec.levels])
    rot = np.concatenate([lv.rotation_rad_s for lv in rec.levels])
    td, _, v = cols(by["acc"])
    # device time: the sample's ns epoch (the clock sync works in float64 ns: exact to 256 ns at 1.6e18)
    assert np.abs(td - acc_ts).max() <= 256
    # platform=ios: CoreMotion's signs flipped into the accelerometer convention, g -> m/s^2
    np.testing.assert_allclose(v, -(ua * G), rtol=1e-12, atol=0)
    td, _, v = cols(by["phone_gravity"])
    np.testing.assert_allclose(v, -(gr * G), rtol=1e-12, atol=0)
    td, _, v = cols(by["gyro"])
    assert np.abs(td - gyro_ts).max() <= 256
    np.testing.assert_allclose(v, rot, rtol=1e-12, atol=0)
    h = dev.health()
    assert h["framing_errors"] == 0 and h["lost_messages"] == 0 and h["duplicate_messages"] == 0
    assert h["frames"] == len(pushes) == len(chunks) and h["readings"] == 3 * 1228


def test_rate_is_20_hz(run):
    by = run[4]
    for name in ("acc", "gyro"):
        td = cols(by[name])[0]
        dt = np.diff(td)
        dt = dt[dt < 1e9]  # not across the pause between the two test parts
        assert np.median(dt) == pytest.approx(50e6, abs=1e6)
        assert 1e9 / dt.mean() == pytest.approx(20.0, rel=0.01)


def test_standing_part_is_still_and_the_phone_is_upright(trace, run):
    by = run[4]
    rec = dispel_samples(trace)
    n = len(rec.levels[0].acc_ts_ms)
    acc = cols(by["acc"])[2][:n]
    gyro = cols(by["gyro"])[2][:n]
    grav = cols(by["phone_gravity"])[2][:n]
    assert np.linalg.norm(acc, axis=1).max() < 0.25  # m/s^2: within +-0.012 g per axis
    assert np.linalg.norm(gyro, axis=1).max() < 0.1  # rad/s
    # X axis vertical: the accelerometer-convention gravity reads -g along x (x points down)
    g_mean = grav.mean(axis=0)
    assert np.linalg.norm(g_mean) == pytest.approx(G, rel=0.01)
    assert g_mean[0] == pytest.approx(-0.998 * G, rel=0.01)
    # and the walking part is not still
    assert np.linalg.norm(cols(by["acc"])[2][n:], axis=1).max() > 10.0


def test_u_turns_every_3_9_s(trace, run):
    by = run[4]
    rec = dispel_samples(trace)
    n = len(rec.levels[0].gyro_ts_ms)
    td, _, v = cols(by["gyro"][n:])
    t = (td - td[0]) / 1e9
    w = np.convolve(np.linalg.norm(v, axis=1), np.ones(10) / 10, mode="same")  # 0.5 s smoothing
    turns = t < 24.0  # the U-turns; handling follows near the end
    peaks, _ = find_peaks(w[turns], height=1.5, distance=40)
    assert t[peaks] == pytest.approx([5.3, 9.1, 13.1, 17.0, 20.9], abs=0.3)  # the README's turn times
    assert np.diff(t[peaks]) == pytest.approx([3.9] * 4, abs=0.35)
    x = w[turns] - w[turns].mean()
    ac = np.correlate(x, x, "full")[len(x) - 1:]
    lag = np.arange(len(ac)) * 0.05
    band = (lag > 2.0) & (lag < 6.0)
    assert lag[band][np.argmax(ac[band])] == pytest.approx(3.9, abs=0.2)


def test_bus_times_are_monotonic_and_close_to_the_true_times(run):
    dev, _, pushes, _, by = run
    d0 = pushes[0].t_last_ns
    for name, ss in by.items():
        td, tb, _ = cols(ss)
        assert np.all(np.diff(tb) >= 0), name
        th = np.array([s.t_host_ns for s in ss])
        assert np.all(tb <= th), name
        true = HOST0 + (td - d0) * (1 + DRIFT_PPM * 1e-6) + LATENCY_MS * 1e6  # the least-delayed arrival
        settled = td >= td[0] + 10e9
        err = (tb - true)[settled] / 1e6
        assert np.abs(err).max() < 3.0, (name, np.abs(err).max())
        assert np.percentile(np.abs(err), 99) < 2.5, name
    assert dev.health()["clock_resets"] == 0


def test_refeeding_the_chunks_gives_identical_samples(trace, run):
    _, chunks, _, items, _ = run
    again = SensorLoggerPhone("iphone", open_transport("loop://"), {"rate": 20, "platform": "ios"})
    items2 = [x for c in chunks for x in again.process_chunk(c)]
    s1 = [x for x in items if isinstance(x, Sample)]
    s2 = [x for x in items2 if isinstance(x, Sample)]
    assert s1 == s2  # no NaN in this trace, so tuple equality is exact


def test_standardised_bodies_give_the_same_samples(trace, run):
    """With "Standardise Units & Frames" on the app negates the accelerations itself; the device's
    default platform takes them as sent, so the samples are the same."""
    _, _, _, _, by_std = replay(trace, standardised=True)
    by = run[4]
    for name in ("acc", "gyro", "phone_gravity"):
        a, b = cols(by[name]), cols(by_std[name])
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_allclose(a[2], b[2], rtol=1e-12, atol=0)
