"""LSL out (``capture.app.lsl_out``): what an outlet declares, bus times on LSL's clock, batches as
chunks (a seeded sweep, no network), and on loopback every bus sample received by an inlet, equal, with
its timestamp, and the outlets gone when the capture stops."""

from __future__ import annotations

import random
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pylsl
import pytest
from lsl_helpers import resolve_by_name
from pylsl.util import LostError
from wait_helpers import DEADLINE_S, wait_until

from capture.app.cli import main
from capture.app.lsl_out import (
    INPUT_KINDS,
    MOCAP_KINDS,
    ClockOffset,
    LslPublisher,
    batch_chunks,
    channel_type,
    load_pylsl,
    lsl_stream_info,
    lsl_time,
    lsl_times,
    lsl_type,
    outlet_spec,
    publish_capture,
    source_id,
    xml_text,
)
from capture.app.orchestrator import Capture
from capture.bus import SAMPLES, Overflow, SampleBus, Subscriber
from capture.errors import ConfigError
from capture.sample import NO_TIME, DeviceIdentity, Sample, SampleBatch, StreamInfo

SEED = 18
ODD = ["", " ", "a b", "<x>", "&amp;", "\"q'", "é", "µT", "°C", "m/s^2", "温度", "tab\there", "nl\nx", "\x01ctl",
       "\ud800lone", "]]>", "x" * 200, "\u2028", "\U0001f600"]


def _text(rng: random.Random) -> str:
    if rng.random() < 0.5:
        return rng.choice(ODD)
    return "".join(chr(rng.choice([rng.randrange(32, 127), rng.randrange(0, 0x3000)])) for _ in range(rng.randrange(8)))


def _identity(rng: random.Random) -> DeviceIdentity:
    return DeviceIdentity(rng.choice(["witmotion", "phone", "hid", "", _text(rng)]), rng.choice(["wrist", "a", "p1"]),
                          url=rng.choice(["", "synth://imu?rate=200&seed=1", _text(rng)]),
                          serial=rng.choice([None, "", "SN-1", _text(rng)]),
                          vid=rng.choice([None, 0x54c]), pid=rng.choice([None, 0xce6]),
                          address=rng.choice([None, "192.168.1.5", _text(rng)]))


def _info(rng: random.Random) -> StreamInfo:
    n = rng.randrange(1, 12)
    kind = rng.choice([*sorted(MOCAP_KINDS), *sorted(INPUT_KINDS), "baro", "unknown", "", _text(rng)])
    return StreamInfo(f"{rng.choice(['wrist', 'a-1', 'p'])}/{rng.choice(['imu', 'x y', _text(rng) or 's'])}", kind,
                      tuple(_text(rng) for _ in range(n)), tuple(_text(rng) for _ in range(n)),
                      rng.choice([None, 200.0, 0.5, 1000.0, 0.0, float("nan")]), _identity(rng),
                      frame=rng.choice([None, "", "x fwd, z up", _text(rng)]))


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    """``perfcap ARGV`` in this process: (exit code, stdout, stderr), never a traceback."""
    try:
        code = main(list(argv))
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    o = capsys.readouterr()
    assert "Traceback" not in o.err and "Traceback" not in o.out, o.err
    return code, o.out, o.err


def _desc(xml: str) -> ET.Element:
    desc = ET.fromstring(xml).find("desc")
    assert desc is not None
    return desc


# -- the pure parts: a seeded sweep ------------------------------------------------------------------
def test_kind_to_lsl_type():
    for k in MOCAP_KINDS:
        assert lsl_type(k) == "MoCap"
    for k in INPUT_KINDS:
        assert lsl_type(k) == "Input"
    assert lsl_type("baro") == "baro" and lsl_type("") == "perfcap"
    assert channel_type("imu", "ax", "m/s^2") == "Acceleration"
    assert channel_type("imu", "gx", "rad/s") == "AngularVelocity"
    assert channel_type("imu", "temp", "degC") == "Temperature"
    assert channel_type("quat", "w", "1") == "Orientation"
    rng = random.Random(SEED)
    for _ in range(300):
        k = _text(rng)
        t = lsl_type(k)
        assert t and (t in ("MoCap", "Input") or t == k or (k == "" and t == "perfcap"))
        assert channel_type(k, _text(rng), _text(rng))


def test_xml_text_leaves_only_what_xml_carries():
    rng = random.Random(SEED)
    for _ in range(500):
        s = _text(rng)
        x = xml_text(s)
        assert len(x) == len(s)
        x.encode("utf-8")  # no lone surrogate left
        ET.fromstring(f"<a>{x.replace('&', '&amp;').replace('<', '&lt;').replace('>', '&gt;')}</a>")
        if all(c >= " " or c in "\t\n\r" for c in s) and not any(0xD800 <= ord(c) <= 0xDFFF for c in s):
            assert x == s


def test_outlet_description_from_random_stream_infos():
    """Odd channel names and units reach the XML of the stream's description as they were (where XML can
    carry them), in order, with the kind, the frame and perfcap as the manufacturer."""
    rng = random.Random(SEED)
    for _ in range(300):
        info = _info(rng)
        spec = outlet_spec(info, "host-1")
        assert spec == outlet_spec(info, "host-1")  # stable: the same stream, the same source_id and all
        assert spec.channel_count == len(info.channels) == len(spec.channels)
        r = info.nominal_rate_hz
        assert spec.nominal_srate == (r if r is not None and r == r and r > 0 else 0.0)
        si = lsl_stream_info(spec, pylsl)
        assert (si.name(), si.type(), si.channel_count(), si.source_id()) == (
            xml_text(info.name), xml_text(lsl_type(info.kind)), len(info.channels), spec.source_id)
        assert si.channel_format() == pylsl.cf_double64
        desc = _desc(si.as_xml())
        chans = desc.findall("channels/channel")
        assert [(c.findtext("label") or "") for c in chans] == [xml_text(c) for c in info.channels]
        assert [(c.findtext("unit") or "") for c in chans] == [xml_text(u) for u in info.units]
        assert [(c.findtext("type") or "") for c in chans] == [
            xml_text(channel_type(info.kind, c, u)) for c, u in zip(info.channels, info.units, strict=True)]
        assert desc.findtext("acquisition/manufacturer") == "perfcap"
        assert (desc.findtext("perfcap/kind") or "") == xml_text(info.kind)
        assert (desc.findtext("perfcap/frame") or "") == xml_text(info.frame or "")


def test_source_id_is_stable_and_tells_streams_and_devices_apart():
    dev = DeviceIdentity("witmotion", "wrist", url="synth://imu?rate=200&seed=1")
    a = StreamInfo("wrist/imu", "imu", ("ax",), ("m/s^2",), 200.0, dev)
    b = StreamInfo("wrist/euler", "euler", ("roll",), ("deg",), 200.0, dev)
    assert source_id(a, "h") == source_id(StreamInfo("wrist/imu", "imu", ("ax",), ("m/s^2",), 200.0, dev), "h")
    assert len({source_id(a, "h"), source_id(b, "h"), source_id(a, "other-host")}) == 3
    s1 = StreamInfo("w/imu", "imu", ("ax",), ("1",), None, DeviceIdentity("bno08x", "w", url="serial:///dev/a",
                                                                          serial="S1"))
    s2 = StreamInfo("w/imu", "imu", ("ax",), ("1",), None, DeviceIdentity("bno08x", "w", url="serial:///dev/b",
                                                                          serial="S1"))
    assert source_id(s1, "h") == source_id(s2, "h")  # the same device on another port is the same source


def _batch(rng: random.Random, n: int, c: int) -> SampleBatch:
    t0 = rng.randrange(0, 1 << 50)
    tb = t0 + np.cumsum(np.array([rng.randrange(1, 10_000_000) for _ in range(n)], np.int64))
    seq = np.arange(n, dtype=np.int64)
    vals = np.array([[rng.uniform(-1e6, 1e6) for _ in range(c)] for _ in range(n)], np.float64).reshape(n, c)
    if rng.random() < 0.3:
        vals = np.asfortranarray(vals)  # not C-contiguous: the chunk must be
    return SampleBatch("s/x", seq, tb - 1000, np.full(n, NO_TIME, np.int64), tb, vals)


def test_batches_as_chunks_random_sizes():
    rng = random.Random(SEED)
    for _ in range(400):
        n, c = rng.randrange(0, 300), rng.randrange(1, 9)
        b = _batch(rng, n, c)
        off = rng.randrange(-(1 << 45), 1 << 45)
        most = rng.choice([1, 7, 64, 4096])
        chunks = list(batch_chunks(b, off, most))
        assert all(0 < len(v) <= most and v.shape[1] == c and v.flags.c_contiguous and len(t) == len(v)
                   for v, t in chunks)
        vals = np.concatenate([v for v, _ in chunks]) if chunks else np.empty((0, c))
        times = np.concatenate([t for _, t in chunks]) if chunks else np.empty(0)
        assert np.array_equal(vals, b.values) and len(times) == n
        assert [float(x) for x in times] == [lsl_time(int(t), off) for t in b.t_bus_ns]
        assert np.array_equal(lsl_times(b.t_bus_ns, off), times)
        for t, tb in zip(times[:5], b.t_bus_ns[:5], strict=False):
            assert abs(t * 1e9 - (int(tb) + off)) <= abs(t) * 1e9 * 2.3e-16 + 1  # one rounding, no more


class _FakeClocks:
    """A bus clock (ns) and an LSL clock (s) `offset_ns` apart, each read taking a random while."""

    def __init__(self, rng: random.Random, offset_ns: int) -> None:
        self.rng = rng
        self.t = rng.randrange(1 << 40)
        self.offset_ns = offset_ns
        self.lsl_read_at: list[int] = []

    def _step(self) -> None:
        self.t += self.rng.choice([50, 80, 200, 5_000, 90_000])

    def now_ns(self) -> int:
        self._step()
        return self.t

    def lsl(self) -> float:
        self._step()
        self.lsl_read_at.append(self.t)
        return (self.t + self.offset_ns) / 1e9

    def sleep_until_ns(self, deadline_ns: int) -> None:
        self.t = max(self.t, deadline_ns)

    def wall_time_s(self) -> float:
        return self.t / 1e9


def test_clock_offset_is_within_half_the_narrowest_bracket():
    rng = random.Random(SEED)
    for _ in range(300):
        true = rng.randrange(-(1 << 44), 1 << 44)
        clk = _FakeClocks(rng, true)
        off, width = ClockOffset(clk, clk.lsl, reads=rng.randrange(1, 30)).measure()
        assert width > 0
        # the float seconds of the LSL clock carry ~0.1 ns at these magnitudes
        assert abs(off - true) <= width // 2 + 1 + 1e-6 * abs(clk.t + true) * 1e-6


# -- pylsl cannot load: one line, never a traceback -----------------------------------------------------
class _Broken:
    """A finder that makes ``import pylsl`` fail as a broken liblsl does."""

    def find_spec(self, name, path=None, target=None):
        if name == "pylsl":
            raise RuntimeError("LSL binary library file was not found.\nDetails...")
        return None


def test_pylsl_missing_or_broken_is_a_config_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "pylsl", None)
    with pytest.raises(ConfigError, match="needs pylsl"):
        load_pylsl()
    monkeypatch.delitem(sys.modules, "pylsl")
    monkeypatch.setattr(sys, "meta_path", [_Broken(), *sys.meta_path])
    with pytest.raises(ConfigError, match=r"liblsl .* cannot be loaded: LSL binary library file was not found\."
                                          r" \(set PYLSL_LIB"):
        load_pylsl()


@pytest.mark.parametrize("argv", [("record", "-q", "-d", "synth://imu", "--duration", "1"),
                                  ("serve", "-q", "--duration", "1", "--no-mdns", "--port", "0",
                                   "--control-port", "-1"),
                                  ("demo", "-q", "--duration", "1")])
def test_cli_without_liblsl_says_so_in_one_line(argv, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "pylsl", None)
    args = [*argv, "--lsl"] + (["-o", str(tmp_path / "t.mcap")] if argv[0] == "record" else [])
    code, _out, err = run(capsys, *args)
    assert code != 0
    assert [ln for ln in err.splitlines() if ln.strip()] == [
        "perfcap: error: --lsl needs pylsl (import of pylsl halted; None in sys.modules); install it with:"
        " pip install pylsl"]
    assert not (tmp_path / "t.mcap").exists()  # told before anything was made


def test_serve_lsl_is_a_setting_and_a_flag():
    from capture.app.cli import build_parser
    from capture.app.config import load_config
    from capture.app.schema import flag_values
    from capture.app.serve.config import ServeConfig

    args = build_parser().parse_args(["serve", "--lsl"])
    assert flag_values(args, ServeConfig) == {"lsl": True}
    assert load_config(env={"PERFCAP_SERVE_LSL": "true"}).serve.lsl is True
    assert ServeConfig().lsl is False


# -- on loopback -----------------------------------------------------------------------------------------
class _Collect(Subscriber):
    """Everything the bus delivered, per stream: (t_bus_ns, values) rows."""

    accepts = SAMPLES

    def __init__(self) -> None:
        self.t: dict[str, list[int]] = {}
        self.v: dict[str, list[tuple[float, ...]]] = {}

    def on_item(self, item):
        t, v = self.t.setdefault(item.stream, []), self.v.setdefault(item.stream, [])
        if type(item) is Sample:
            t.append(item.t_bus_ns)
            v.append(tuple(item.values))
        else:
            t += item.t_bus_ns.tolist()
            v += [tuple(r) for r in item.values.tolist()]


def _inlet(name: str) -> pylsl.StreamInlet:
    # recover=False: a stream that ends raises LostError at the next pull instead of waiting for it to return
    inlet = pylsl.StreamInlet(resolve_by_name(name), max_buflen=360, recover=False, processing_flags=0)
    inlet.open_stream(DEADLINE_S)
    return inlet


def _pull_all(inlet: pylsl.StreamInlet, n: int) -> tuple[np.ndarray, np.ndarray]:
    rows: list[list[float]] = []
    times: list[float] = []

    def got_all() -> bool:
        data, ts = inlet.pull_chunk(timeout=0.2, max_samples=4096)
        rows.extend(data)
        times.extend(ts)
        assert len(rows) <= n, "more samples than were pushed"
        return len(rows) == n

    wait_until(got_all, what=f"{n} samples from the LSL inlet")
    data, _ = inlet.pull_chunk(timeout=0.3)
    assert not data, "more samples than were pushed"
    return np.array(rows, np.float64), np.array(times, np.float64)


def _check_times(times: np.ndarray, t_bus: list[int], offsets: list[int]) -> None:
    """Each timestamp is its bus time plus a measured offset, to float precision (well under 1 us)."""
    exp = np.array(t_bus, np.int64)
    err = np.min(np.abs(times[:, None] * 1e9 - (exp[:, None] + np.array(offsets, np.int64)[None, :])), axis=1)
    assert float(err.max()) < 1000.0, err.max()


def test_capture_streams_reach_lsl_inlets_whole(tmp_path):
    """A capture of simulated IMUs with the publisher subscribed: each stream's inlet receives every sample
    the bus delivered (exact count, equal values), stamped with its bus time plus the measured offset, and
    the description has the labels, units and types; the outlets end with the capture."""
    cap = Capture(["wrist=synth://imu?rate=200&seed=1&duration=1.5", "ankle=synth://imu?rate=100&seed=2&duration=1.5"],
                  output=str(tmp_path / "t.mcap"))
    try:
        coll = _Collect()
        cap.subscribe(coll, policy=Overflow.NEVER_DROP, name="collect")
        pub, _ = publish_capture(cap, remeasure_s=0.05)
        names = pub.streams
        assert names == sorted(s.name for d in cap.devices for s in d.streams)
        inlets = {n: _inlet(n) for n in names}
    except BaseException:
        cap.stop()
        raise
    info = inlets["wrist/imu"].info(DEADLINE_S)
    assert (info.type(), info.nominal_srate(), info.channel_format()) == ("MoCap", 200.0, pylsl.cf_double64)
    assert info.get_channel_labels() == ["ax", "ay", "az", "gx", "gy", "gz", "temp"]
    assert info.get_channel_units() == ["m/s^2"] * 3 + ["rad/s"] * 3 + ["degC"]
    assert info.get_channel_types() == ["Acceleration"] * 3 + ["AngularVelocity"] * 3 + ["Temperature"]
    assert _desc(info.as_xml()).findtext("perfcap/kind") == "imu"
    assert info.source_id() == pub.specs["wrist/imu"].source_id

    cap.start()
    try:
        wait_until(lambda: not any(r.alive for r in cap.readers), what="the simulated devices to end")

        def drained() -> bool:
            return (all(s.pending == 0 for s in cap.bus.stats())
                    and pub.pushed == {n: len(coll.t.get(n, [])) for n in names})

        wait_until(drained, what="the publisher to push what the bus delivered")
        offsets = [o for _, o, _ in pub.offsets]
        assert len(offsets) > 1  # measured again while it ran
        for n in names:   # pulled while the outlets are open: everything pushed is in flight or received
            expected = len(coll.t.get(n, []))
            if not expected:
                continue
            vals, times = _pull_all(inlets[n], expected)
            assert np.array_equal(vals, np.array(coll.v[n], np.float64)), n
            _check_times(times, coll.t[n], offsets)
        assert sum(pub.pushed.values()) > 500
    finally:
        report = cap.stop()
    assert next(s for s in report.subscribers if s["name"] == "lsl")["dropped"] == 0
    assert report.saved is not None
    assert {n: report.saved.get(n, 0) for n in names} == pub.pushed   # the session has what LSL got
    assert pub.closed
    for n in names:   # every outlet closed with the capture: its inlet learns the stream is lost
        with pytest.raises(LostError):
            inlets[n].pull_chunk(timeout=DEADLINE_S)
    del inlets


def test_samples_and_batches_on_a_bare_bus_and_a_stream_seen_late():
    """Single samples go out one by one and batches as chunks, each stamped (t_bus + offset) / 1e9; a
    stream nobody declared gets its outlet at its first sample, from the lookup (or generic channels)."""
    dev = DeviceIdentity("test", "t1")
    info = StreamInfo("t1/x", "imu", ("a", "b", "c"), ("m/s^2", "rad/s", "1"), 100.0, dev)
    late = StreamInfo("t1/late", "baro", ("p",), ("Pa",), None, dev)
    bus = SampleBus()
    pub = LslPublisher([info], lookup=lambda n: late if n == late.name else None, remeasure_s=3600)
    bus.subscribe(pub, policy=Overflow.NEVER_DROP, name="lsl")
    try:
        inlet = _inlet("t1/x")
        rng = random.Random(SEED)
        t = 10_000_000_000
        t_bus: list[int] = []
        rows: list[tuple[float, ...]] = []
        for k in range(60):
            if rng.random() < 0.5:
                t += rng.randrange(1, 20_000_000)
                v = (rng.uniform(-9, 9), rng.uniform(-9, 9), float(k))
                bus.publish(Sample("t1/x", k, t, None, t, v))
                t_bus.append(t)
                rows.append(v)
            else:
                n = rng.randrange(1, 40)
                ts = t + np.cumsum(np.array([rng.randrange(1, 9_000_000) for _ in range(n)], np.int64))
                t = int(ts[-1])
                vals = np.array([[rng.uniform(-1e3, 1e3) for _ in range(3)] for _ in range(n)])
                bus.publish(SampleBatch("t1/x", np.arange(n, dtype=np.int64), ts, np.full(n, NO_TIME, np.int64),
                                        ts, vals))
                t_bus += ts.tolist()
                rows += [tuple(r) for r in vals.tolist()]
        bus.publish(Sample("t1/late", 0, t, None, t, (101325.0,)))
        bus.publish(Sample("t1/nobody", 0, t, None, t, (1.0, 2.0)))
        vals, times = _pull_all(inlet, len(rows))
        assert np.array_equal(vals, np.array(rows))
        _check_times(times, t_bus, [pub.offset_ns])
        assert [float(x) for x in times[:3]] == [lsl_time(x, pub.offset_ns) for x in t_bus[:3]]
        wait_until(lambda: pub.pushed.get("t1/nobody") == 1, what="the undeclared streams to be published")
        assert pub.specs["t1/late"].type == "baro" and pub.specs["t1/late"].nominal_srate == 0.0
        assert [c[0] for c in pub.specs["t1/nobody"].channels] == ["c0", "c1"]
        assert pub.pushed == {"t1/x": len(rows), "t1/late": 1, "t1/nobody": 1}
    finally:
        bus.close()
    assert pub.closed and not pub._outlets


def test_offset_is_measured_against_lsl_clock():
    pub = LslPublisher(lsl=pylsl, remeasure_s=3600)
    try:
        _, off, width = pub.offsets[-1]
        assert off == pub.offset_ns
        # measured, and (both being the host's monotonic clock on this platform) small: the bracket bounds it
        from capture.clock import MONOTONIC

        a = MONOTONIC.now_ns()
        lsl_now = pylsl.local_clock()
        b = MONOTONIC.now_ns()
        assert abs(lsl_now * 1e9 - ((a + b) / 2 + off)) <= (b - a) / 2 + width / 2 + 1e6
    finally:
        pub.close()

