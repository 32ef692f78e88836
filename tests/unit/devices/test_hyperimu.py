"""HyperIMU (``HyperImuCodec``, ``HyperImuPhone``): CSV rows over UDP or TCP.

There are no real HyperIMU recordings in ``../shared/traces``, so the rows here are written from the
documented format (``docs/design/phone-protocols.md`` section 4: the HIMUServer README's example
row, its ``@`` file header, the HypeRIMU example's header row and epoch-ms timestamp column).
Multi-row datagrams, ``#`` row ends, and TCP streams re-split at every byte boundary are built
from those rows.
"""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from capture.errors import ConfigError, ProtocolError
from capture.sample import Chunk, Direction, Sample
from devices.codecs.hyperimu import HyperImuCodec
from devices.codecs.textline import TextFrame
from devices.phone_apps.hyperimu import HYPERIMU_CLOCK, HyperImuPhone
from devices.transports import open_transport
from sim_devices.phone_apps_sim import hyperimu_rows

# The HIMUServer README's example row: accelerometer, gyroscope, magnetometer (3 values each).
README_ROW = b"0.123,0.586,0.2637,0.259,-0.5963,9.815,5.36,0.00,0.00 \r\n"
# Rows laid out as the HypeRIMU example file with a timestamp: epoch ms first, then
# gyroscope, accelerometer, magnetic field (Java's Float.toString, so exponents occur).
HEADER = (b"@ HyperIMU - ianovir - 2017\r\n"
          b"@ Date: Sat Nov 11 15:39:03 GMT+01:00 2017, Sampling Time: 50ms\r\n"
          b"\r\n"
          b"timestamp,MPL_Gyroscope.x,MPL_Gyroscope.y,MPL_Gyroscope.z,MPL_Accelerometer.x,MPL_Accelerometer.y,"
          b"MPL_Accelerometer.z,MPL_Magnetic_Field.x,MPL_Magnetic_Field.y,MPL_Magnetic_Field.z\r\n")
TS_ROWS = (b"1510411143791,0.004627242,0.43825644,0.19575885,-1.1764508,3.1069257,9.461885,-785.457,-655.622,-1005.397\r\n"  # noqa: E501
           b"1510411143845,0.46269095,-0.42673826,0.1584746,-1.6020203,2.477849,10.143634,-786.357,-656.072,-1005.697\r\n"
           b"1510411143897,-4.4906617E-4,-0.19664116,0.11905981,-0.9106945,3.0883706,9.331401,-788.156,-658.171,-1005.847\r\n"
           b"1510411143951,-4.4906617E-4,-0.19664116,0.11905981,-0.9106945,3.0883706,9.331401,-788.156,-658.171,-1005.847\r\n")
TS_OPTS = {"sensors": "gyroscope,accelerometer,magnetic_field", "timestamp": True, "rate": 20}


def device(strict: bool = False, **opts) -> HyperImuPhone:
    return HyperImuPhone("himu", open_transport("loop://"), opts, strict=strict)


def run(dev: HyperImuPhone, chunks: list[bytes], t0: int = 10**9, period: int = 50_000_000) -> list:
    out = []
    for i, d in enumerate(chunks):
        out += dev.process_chunk(Chunk(d, t0 + i * period, Direction.RX))
    return out


def samples(items, stream: str | None = None) -> list[Sample]:
    return [x for x in items if isinstance(x, Sample) and (stream is None or x.stream == f"himu/{stream}")]


def readings(items) -> list[tuple]:
    """What a reading is independent of arrival times: stream, sequence, values, device time
    (per stream: chunks with several readings publish them grouped by stream)."""
    return sorted((s.stream, s.seq, s.values, s.t_device_ns) for s in samples(items))


# -- decoding -------------------------------------------------------------------------------------
def test_the_readme_row_decodes_to_exact_values():
    dev = device()
    assert [(s.name, s.kind, s.clock, s.nominal_rate_hz) for s in dev.streams] == [
        ("himu/imu", "imu", None, None), ("himu/mag", "mag", None, None)]
    items = run(dev, [README_ROW])
    assert samples(items, "imu")[0].values == (0.123, 0.586, 0.2637, 0.259, -0.5963, 9.815)
    assert samples(items, "mag")[0].values == (5.36, 0.0, 0.0)
    assert samples(items)[0].t_device_ns is None


def test_timestamped_rows_after_the_file_header():
    dev = device(**TS_OPTS)
    assert [(s.name, s.clock, s.nominal_rate_hz) for s in dev.streams] == [
        ("himu/imu", HYPERIMU_CLOCK, 20.0), ("himu/mag", HYPERIMU_CLOCK, 20.0)]
    items = run(dev, [HEADER + TS_ROWS])
    imu = samples(items, "imu")
    # the imu stream is accelerometer then gyroscope, whatever the app's order
    assert imu[0].values == (-1.1764508, 3.1069257, 9.461885, 0.004627242, 0.43825644, 0.19575885)
    assert imu[2].values[3] == -4.4906617e-4
    assert [s.seq for s in imu] == [0, 1, 2, 3]  # the held repeat is recorded
    assert imu[3].values == imu[2].values
    assert samples(items, "mag")[1].values == (-786.357, -656.072, -1005.697)
    # device ticks are the ms column exactly (the bus's ns conversion is float, good to < 1 us here)
    frames = HyperImuCodec(sensors=("gyroscope", "accelerometer", "magnetometer"), timestamp=True).feed(TS_ROWS)
    assert [r.ticks for f in frames for r in dev.frame_to_readings(f)][::2] == [1510411143791, 1510411143845,
                                                                            1510411143897, 1510411143951]
    t = [s.t_device_ns for s in imu]
    assert [b - a for a, b in itertools.pairwise(t)] == pytest.approx([54_000_000, 52_000_000, 54_000_000], abs=1000)
    st_ = dev.codec.stats
    assert st_.errors == 0 and st_.skipped_lines == 4  # two @ lines, a blank line, the header row
    assert dev.stats.lost_readings == 0


def test_hash_row_ends_and_several_rows_per_datagram():
    rows = [(0.5 * i, 0.25, 9.75, 0.0, 0.125, -0.125, 20.0, -5.0, 40.0) for i in range(5)]
    a = run(device(), [hyperimu_rows(rows, end=b"#")])
    b = run(device(), [hyperimu_rows(rows[:2]), hyperimu_rows(rows[2:])])
    assert readings(a) == readings(b)
    assert [s.values for s in samples(a, "imu")] == [r[:6] for r in rows]


@pytest.mark.parametrize("sensors, streams", [
    ("accelerometer", [("acc", "acc")]),
    ("gyroscope,_", [("gyro", "gyro")]),
    ("linear_acceleration,gravity,magnetometer", [("mag", "mag"), ("user_acc", "acc"), ("phone_gravity", "acc")]),
    ("orientation", [("attitude", "euler")]),
    ("rotation_vector,orientation", [("attitude", "quat"), ("attitude_euler", "euler")]),
])
def test_streams_follow_the_sensors(sensors, streams):
    dev = device(sensors=sensors)
    assert [(s.name.split("/")[1], s.kind) for s in dev.streams] == streams
    assert not any(s.name.endswith(("/orientation", "/gravity", "/linear_acc")) for s in dev.streams)


def test_rotation_vector_orientation_mac_and_gps():
    dev = device(sensors="rotation_vector,_,orientation", timestamp=True, mac=True, gps=True)
    assert [s.name for s in dev.streams] == ["himu/attitude", "himu/attitude_euler", "himu/gps"]
    items = run(dev, [b"1510411143791,a4:5e:60:c1:22:0f,0.5,0.25,0.5,9,9,9,129.75,-0.25,0.125,48.5,11.25,520.5\r\n"])
    (att,) = samples(items, "attitude")
    assert att.values == (math.sqrt(1 - 0.25 - 0.0625 - 0.25), 0.5, 0.25, 0.5)
    assert samples(items, "attitude_euler")[0].values == (129.75, -0.25, 0.125)
    assert samples(items, "gps")[0].values == (48.5, 11.25, 520.5)
    assert att.t_device_ns == pytest.approx(1510411143791 * 1_000_000, abs=1000)
    assert dev.health()["mac"] == "a4:5e:60:c1:22:0f"


def test_a_mac_first_row_is_data_and_its_header_is_skipped():
    dev = device(sensors="accelerometer", mac=True)
    items = run(dev, [(b"mac,MPL_Accelerometer.x,MPL_Accelerometer.y,MPL_Accelerometer.z\r\n"
                       b"a4:5e:60:c1:22:0f,0.5,0.25,9.75\r\n")])
    assert samples(items, "acc")[0].values == (0.5, 0.25, 9.75)
    assert dev.codec.stats.skipped_lines == 1 and dev.codec.stats.errors == 0


def test_a_row_starting_with_nan_is_data():
    items = run(device(sensors="accelerometer"), [b"NaN,0.5,0.25\r\n"])
    v = samples(items, "acc")[0].values
    assert math.isnan(v[0]) and v[1:] == (0.5, 0.25)


# -- TCP reassembly -------------------------------------------------------------------------------
def test_rows_split_at_every_byte_boundary_give_the_same_readings():
    stream = HEADER + TS_ROWS
    whole = readings(run(device(**TS_OPTS), [stream]))
    assert len(whole) == 8
    for i in range(1, len(stream)):
        assert readings(run(device(**TS_OPTS), [stream[:i], stream[i:]])) == whole, i
    assert readings(run(device(**TS_OPTS), [bytes([b]) for b in stream])) == whole


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(1, len(HEADER + TS_ROWS) - 1), max_size=30, unique=True), st.booleans())
def test_rows_split_anywhere_give_the_same_readings(cuts, hash_end):
    stream = HEADER + TS_ROWS
    if hash_end:
        stream = stream.replace(b"\r\n", b"#")
    cuts = sorted(cuts)
    parts = [stream[a:b] for a, b in zip([0, *cuts], [*cuts, len(stream)], strict=True)]
    dev = device(**TS_OPTS)
    assert readings(run(dev, parts)) == readings(run(device(**TS_OPTS), [stream]))
    assert dev.codec.stats.errors == 0


# -- bad input ------------------------------------------------------------------------------------
@pytest.mark.parametrize("row, why", [
    (b"0.1,0.2,9.8,0.01,0.02\r\n", "5 fields where 9"),
    (b"0.1,0.2,9.8,0.01,0.02,0.03,10,20,30,40\r\n", "10 fields where 9"),
    (b"0.1,0.2,9.8,0.01,zero,0.03,10,20,30\r\n", "not a number"),
    (b"??,!!\r\n", "without a number"),
    (b"0.1,0.2,\xff\xfe,0.01,0.02,0.03,10,20,30\r\n", "not UTF-8"),
])
def test_bad_rows_are_counted_errors(row, why, caplog):
    dev = device()
    items = run(dev, [row + README_ROW])
    assert dev.codec.stats.framing_errors == 1
    assert len(samples(items, "imu")) == 1
    assert why in caplog.text
    with pytest.raises(ProtocolError, match=why):
        run(device(strict=True), [row])


def test_overlong_lines_are_capped_and_counted():
    dev = device(max_line=64)
    items = run(dev, [b"1" * 50, b"2" * 50, b"3" * 50, b"\r\n" + README_ROW])
    assert dev.codec.stats.framing_errors == 1
    assert dev.codec.buffered <= 64 + 1
    assert len(samples(items, "imu")) == 1


def test_a_bad_timestamp_is_counted():
    dev = device(sensors="accelerometer", timestamp=True)
    run(dev, [b"-5,0.5,0.25,9.75\r\n", b"1e300,0.5,0.25,9.75\r\n", b"1510411143791,0.5,0.25,9.75\r\n"])
    assert dev.codec.stats.framing_errors == 2 and dev.stats.readings == 1


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=120), max_size=8))
def test_garbage_is_counted_and_never_raises(chunks):
    dev = device(sensors="accelerometer", timestamp=True, mac=True, gps=True)
    items = run(dev, [*chunks, b"\r\n1510411143791,02:00:00:00:00:00,0.5,0.25,9.75,1,2,3\r\n"])
    assert samples(items, "acc")[-1].values == (0.5, 0.25, 9.75)


@pytest.mark.parametrize("opts, what", [
    ({"sensors": "accelerometer,barometer"}, "unknown HyperIMU sensor 'barometer'"),
    ({"sensors": "gyroscope,gyroscope"}, "listed twice"),
    ({"sensors": "_"}, "no sensor or GPS column"),
    ({"rate": -1}, "rate"),
    ({"sensors": "accelerometer", "colour": "red"}, "unknown option"),
])
def test_bad_options_are_config_errors(opts, what):
    with pytest.raises(ConfigError, match=what):
        device(**opts)


# -- round trip and replay ------------------------------------------------------------------------
def test_codec_round_trip():
    c = HyperImuCodec(sensors=("accelerometer", "_", "gyroscope"), timestamp=True, mac=True, gps=True)
    frames = [TextFrame((1510411143791.0 + 50 * i, 0.1 * i, -0.5, 9.81, 1e-5, -2.5e-7, 3.0, 48.1, 11.5, 520.0),
                        (1 << 10) - 1) for i in range(4)]
    for end in (b"\r\n", b"#"):
        data = b"".join(c.encode(f, mac="02:00:00:00:00:00", end=end) for f in frames)
        assert HyperImuCodec(sensors=("accelerometer", "_", "gyroscope"), timestamp=True, mac=True,
                             gps=True).feed(data) == frames


def test_refeeding_the_same_chunks_gives_identical_samples():
    stream = HEADER + TS_ROWS * 20 + b"bad,row\r\n0.1,0.2\r\n" + TS_ROWS
    chunks = [Chunk(stream[i:i + 37], 10**9 + i * 1_000_003, Direction.RX) for i in range(0, len(stream), 37)]
    runs = []
    for _ in range(2):
        dev = device(**TS_OPTS)
        runs.append(repr([x for c in chunks for x in dev.process_chunk(c)]))
    assert runs[0] == runs[1] and "himu/imu" in runs[0]
