"""Structure-aware fuzzing of whole devices (not only their codecs), shared by the CI test
(``tests/unit/devices/test_device_fuzz.py``) and the larger campaign (``benchmarks/fuzz_devices.py``).

For each device kind, ``KINDS`` builds the real device object and a list of valid messages, from
the simulators in ``sim_devices`` and from real bytes in ``/work/shared/traces``. ``fuzz_kind``
mutates copies of them by their structure (a JSON tree, CSV fields, OSC arguments, the words of a
binary frame with its checksum fixed so the bad value reaches the decoder): numbers become
nan/inf/1e308/-1e308/1e999/huge integers/negative/wrong types, fields are dropped or duplicated,
messages truncated, bytes flipped. Each mutated message is put between two valid ones and
everything goes through ``Device.process_chunk``, the path a ``DeviceReader`` polls; then the same
chunks go through a real ``DeviceReader`` onto a ``SampleBus``. What is checked:

* no exception leaves the device (an *escape*), and the reader ends FINISHED, never FAILED;
* no sample with an infinite value is delivered;
* every mutated message is accounted for: it gave samples or moved a counter in ``health()``
  (an error, a skipped line, a lost message, a decoded frame...), or left bytes buffered on a
  stream transport; one that did none of these is *silent*;
* every valid message gives exactly the samples it gives a device that never saw a bad one.
"""

from __future__ import annotations

import collections
import json
import math
import random
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from capture.bus import Overflow, SampleBus, Subscriber
from capture.errors import EndOfStream
from capture.sample import Chunk, Direction, Sample, SampleBatch
from devices import open_device
from devices.base import DeviceState
from devices.reader import DeviceReader, ReconnectPolicy
from devices.transports import open_transport
from devices.transports.base import Transport

if TYPE_CHECKING:
    from collections.abc import Callable

    from devices.base import Device

TRACES = Path(__file__).resolve().parents[2] / "shared" / "traces"
if not TRACES.is_dir():
    TRACES = Path("/work/shared/traces")

# -- hostile values ---------------------------------------------------------------------------------
#: JSON number texts (some are not valid JSON, on purpose: json.loads would map NaN/Infinity)
HOSTILE_JSON = ["NaN", "Infinity", "-Infinity", "1e308", "-1e308", "1e999", "-1e999", "1e305", "5e-324",
                str(2 ** 64), str(-(2 ** 63) - 1), str(2 ** 63 - 1), str(2 ** 62), str(2 ** 53 - 1), str(2 ** 53),
                "999999999999", "9" * 400, "-1", "0", "-0.0", "1.5", '"1"', "null", "true",
                "[]", "{}", '"x"', "[1e308]"]
#: text-line field texts
HOSTILE_TEXT = [b"inf", b"-inf", b"nan", b"Infinity", b"1e999", b"-1e999", b"1e308", b"-1e308", b"1e305",
                b"9" * 30, b"9" * 400, b"-1", b"0", b"", b"x", b"0x10", b"1_000", b"\xd9\xa1", b"--1", b"1e",
                b"+", b".", b"1.2.3", b" ", b"\x00"]


def _flip(rng: random.Random, data: bytes) -> bytes:
    b = bytearray(data)
    if not b:
        return bytes([rng.randrange(256)])
    for _ in range(rng.randint(1, 4)):
        b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
    return bytes(b)


def _truncate(rng: random.Random, data: bytes) -> bytes:
    return data[:rng.randrange(len(data))] if data else data


def _bytes_level(rng: random.Random, data: bytes) -> bytes:
    op = rng.randrange(4)
    if op == 0:
        return _flip(rng, data)
    if op == 1:
        return _truncate(rng, data)
    if op == 2:  # a slice repeated
        if not data:
            return data
        i = rng.randrange(len(data))
        j = rng.randrange(i, len(data) + 1)
        return data[:j] + data[i:j] + data[j:]
    i = rng.randrange(len(data) + 1)
    return data[:i] + bytes(rng.randrange(256) for _ in range(rng.randint(1, 8))) + data[i:]


# -- JSON -----------------------------------------------------------------------------------------
_MARK = "\u0000hostile\u0000"


def _paths(obj: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [path]
    if isinstance(obj, dict):
        for k, v in obj.items():
            out += _paths(v, (*path, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out += _paths(v, (*path, i))
    return out


def _get(obj: Any, path: tuple[Any, ...]) -> Any:
    for p in path:
        obj = obj[p]
    return obj


def mutate_json(rng: random.Random, data: bytes) -> bytes:
    """A structural mutation of one JSON message (or, one time in five, a byte-level one)."""
    if rng.random() < 0.2:
        return _bytes_level(rng, data)
    obj = json.loads(data)
    paths = [p for p in _paths(obj) if p]
    if not paths:
        return _bytes_level(rng, data)
    # numbers are the most interesting leaves: pick them more often
    nums = [p for p in paths if type(_get(obj, p)) in (int, float)]
    # the message's own fields (ids, times) as often as anything deep inside it
    top = [p for p in paths if len(p) == 1]
    path = (rng.choice(top) if rng.random() < 0.3 else rng.choice(nums) if nums and rng.random() < 0.7
            else rng.choice(paths))
    parent, key = _get(obj, path[:-1]), path[-1]
    op = rng.randrange(10)
    hostile = rng.choice(HOSTILE_JSON)
    if op <= 5:  # a hostile value in its place
        parent[key] = _MARK
    elif op == 6:  # dropped
        del parent[key]
    elif op == 7:  # duplicated: a key given twice (the second hostile), an array element twice
        if isinstance(parent, dict):
            text = json.dumps(obj, allow_nan=True)
            k = json.dumps(key)
            return text.replace(k + ":", f"{k}:{hostile},{k}:", 1).encode() if k + ":" in text else text.encode()
        parent.insert(key, parent[key])
    elif op == 8:  # wrapped in an array / an object
        parent[key] = [parent[key]] if rng.random() < 0.5 else {"v": parent[key]}
    else:  # a number scaled far out
        v = parent[key]
        if type(v) in (int, float):
            parent[key] = v * rng.choice([1e300, -1e300, 1e20, -1.0, 2 ** 64])
        else:
            parent[key] = _MARK
    text = json.dumps(obj, allow_nan=True)
    return text.replace(json.dumps(_MARK), hostile, 1).encode()


# -- text lines -------------------------------------------------------------------------------------
def mutate_line(rng: random.Random, data: bytes) -> bytes:
    """A structural mutation of one text line (CSV fields; the line end kept), or a byte-level one."""
    end = b"\r\n" if data.endswith(b"\r\n") else b"\n" if data.endswith(b"\n") else b""
    body = data[:len(data) - len(end)]
    if rng.random() < 0.2:
        return _bytes_level(rng, body) + end
    fields = body.split(b",")
    i = rng.randrange(len(fields))
    op = rng.randrange(8)
    if op <= 4:
        fields[i] = rng.choice(HOSTILE_TEXT)
    elif op == 5:
        del fields[i]
    elif op == 6:
        fields.insert(i, fields[i])
    else:
        try:
            v = float(fields[i])
        except ValueError:
            v = 1.0
        fields[i] = repr(v * rng.choice([1e300, -1e300, 1e20, -1.0])).encode()
    return b",".join(fields) + end


# -- OSC ----------------------------------------------------------------------------------------------
def _osc_args(data: bytes, base: int = 0) -> list[tuple[int, str]]:
    """(offset, type tag) of the 4- and 8-byte arguments in an OSC message or bundle."""
    out: list[tuple[int, str]] = []
    if data.startswith(b"#bundle\0"):
        pos = 16
        while pos + 4 <= len(data):
            (size,) = struct.unpack_from(">i", data, pos)
            if size <= 0 or pos + 4 + size > len(data):
                break
            out += _osc_args(data[pos + 4:pos + 4 + size], base + pos + 4)
            pos += 4 + size
        return out
    try:
        a_end = data.index(b"\0")
        pos = (a_end + 4) & ~3
        t_end = data.index(b"\0", pos)
    except ValueError:
        return out
    tags = data[pos + 1:t_end].decode("ascii", "replace")
    pos = (t_end + 4) & ~3
    for t in tags:
        if t in "ifc":
            out.append((base + pos, t))
            pos += 4
        elif t in "dht":
            out.append((base + pos, t))
            pos += 8
        elif t in "sS":
            try:
                pos = (data.index(b"\0", pos) + 4) & ~3
            except ValueError:
                break
        elif t == "b":
            (n,) = struct.unpack_from(">i", data, pos) if pos + 4 <= len(data) else (0,)
            pos += 4 + ((n + 3) & ~3)
    return out


_F32 = [math.nan, math.inf, -math.inf, 3.4e38, -3.4e38, 1e-45, 0.0]
_F64 = [math.nan, math.inf, -math.inf, 1e308, -1e308, 5e-324]
_I32 = [2 ** 31 - 1, -(2 ** 31), -1, 0]


def mutate_osc(rng: random.Random, data: bytes) -> bytes:
    """An OSC datagram with one argument replaced by a hostile value (its type tag kept, or changed),
    or a byte-level mutation."""
    args = _osc_args(data)
    if not args or rng.random() < 0.25:
        return _bytes_level(rng, data)
    off, tag = rng.choice(args)
    b = bytearray(data)
    if tag == "f":
        b[off:off + 4] = struct.pack(">f", rng.choice(_F32))
    elif tag == "i":
        b[off:off + 4] = struct.pack(">i", rng.choice(_I32))
    elif tag == "d":
        b[off:off + 8] = struct.pack(">d", rng.choice(_F64))
    else:
        b[off:off + 8] = struct.pack(">q", rng.choice([2 ** 63 - 1, -(2 ** 63), -1]))
    if rng.random() < 0.2:  # the tag changed to another of the same size
        i = data.find(b",")
        j = data.find(tag.encode(), i) if i >= 0 else -1
        if j > 0:
            b[j] = ord(rng.choice("ifcd"))
    return bytes(b)


# -- binary frames --------------------------------------------------------------------------------------
_WORDS = [0x7FFF, 0x8000, 0xFFFF, 0x0000, 0x0001]


def binary_mutator(checksum: Callable[[bytearray], None] | None = None, start: int = 0,
                   ) -> Callable[[random.Random, bytes], bytes]:
    """Mutations of a binary frame: a 16-bit word (past ``start``) set to an extreme, with the
    frame's checksum then fixed by ``checksum`` (so the value reaches the decoder) most of the time;
    or a byte-level mutation."""

    def mutate(rng: random.Random, data: bytes) -> bytes:
        if len(data) < start + 2 or rng.random() < 0.3:
            return _bytes_level(rng, data)
        b = bytearray(data)
        for _ in range(rng.randint(1, 3)):
            i = rng.randrange(start, len(b) - 1)
            struct.pack_into("<H", b, i, rng.choice(_WORDS))
        if checksum is not None and rng.random() < 0.8:
            checksum(b)
        return bytes(b)

    return mutate


def _rvc_sum(b: bytearray) -> None:
    # BNO08x RVC: 0xAAAA, 15 payload bytes (2..16), checksum byte 18 = sum of 2..17
    for k in range(0, len(b) - 18, 19):
        b[k + 18] = sum(b[k + 2:k + 18]) & 0xFF


def _wit_sum(b: bytearray) -> None:
    for k in range(0, len(b) - 10, 11):
        b[k + 10] = sum(b[k:k + 10]) & 0xFF


# -- device kinds -----------------------------------------------------------------------------------------
@dataclass
class Kind:
    """A device kind to fuzz: how to build it, its valid messages, how to mutate one."""

    name: str
    codec: str
    #: the device on a given transport (``None``: a HID kind, built by ``make`` with its simulator)
    build: Callable[[Transport], Device] | None
    good: list[bytes]
    mutate: Callable[[random.Random, bytes], bytes]
    #: bytes transport (serial, TCP): bytes of a mutated frame may wait for the next chunk
    stream: bool = False
    #: appended to a mutated message on a line transport (a line ends there)
    end: bytes = b""
    period_ns: int = 10_000_000
    #: renumber valid message ``i`` (its id ``2 * i``) so that a mutated message between two valid
    #: ones can carry the id in between (``2 * i + 1``): JSON kinds with message ids
    renumber: Callable[[bytes, int], bytes] | None = None
    #: a HID kind: the device opened on its simulator (handshake done)
    hid_url: str | None = None
    #: samples of the valid messages a bad one may cost (a report without a checksum whose timer
    #: is damaged makes the next report's samples look repeated: counted, not silent)
    lost_per_input: int = 0

    def make(self) -> Device:
        """A fresh device ready for ``process_chunk``."""
        if self.build is not None:
            return self.build(open_transport("loop://"))
        d = open_device(str(self.hid_url))
        d.open()
        d.close()  # the handshake's calibration and layout stay; reports are fed by the fuzzer
        return d


def _page_kind() -> Kind:
    from devices.codecs.phone_json import PageCodec
    from devices.phone import PhonePage
    from sim_devices.phone_sim import page_hello, page_messages, page_pong

    codec = PageCodec()
    msgs = [page_hello()] + [m.data for m in page_messages(4.0, touches=True)]
    msgs.insert(5, page_pong(10**12 + 5 * 10_000_000, 1600.0))

    def renumber(data: bytes, n: int) -> bytes:
        (f,) = codec.feed(data)
        return codec.encode(f._replace(seq=n)) if hasattr(f, "seq") else data

    return Kind("phone page", "phone_page", lambda tr: PhonePage("ph", tr, {}), msgs,
                mutate_json, period_ns=50_000_000, renumber=renumber)


def _sensorlogger_kind() -> Kind:
    from devices.codecs.phone_json import SensorLoggerCodec
    from devices.phone import SensorLoggerPhone
    from sim_devices.phone_sim import dispel_to_sensorlogger

    path = TRACES / "e_smartphone" / "dispel_ads_iphonex_sbt_utt_example.json"
    msgs = [m.body for m in dispel_to_sensorlogger(path)][:60]
    codec = SensorLoggerCodec()

    def renumber(data: bytes, n: int) -> bytes:
        (f,) = codec.feed(data)
        return codec.encode(f._replace(message_id=n))

    return Kind("Sensor Logger push (DISPEL iPhone trace)", "sensorlogger",
                lambda tr: SensorLoggerPhone("sl", tr, {"rate": 20}), msgs, mutate_json,
                period_ns=500_000_000, renumber=renumber)


def _sensorserver_kind() -> Kind:
    from devices.phone_apps.sensorserver import SensorServerPhone
    from sim_devices.phone_apps_sim import sensorserver_event, sensorserver_touch

    acc, gyro = "android.sensor.accelerometer", "android.sensor.gyroscope"
    msgs: list[bytes] = []
    for i in range(120):
        t = 123_456_789_000 + i * 5_000_000
        msgs.append(sensorserver_event((0.1 * i, -0.2, 9.8), t, sensor_type=acc))
        msgs.append(sensorserver_event((0.01, 0.02 * i, -0.03), t + 1000, sensor_type=gyro))
        if i % 10 == 0:
            msgs.append(sensorserver_touch("ACTION_MOVE", 10.0 + i, 20.0))
    return Kind("SensorServer", "sensorserver",
                lambda tr: SensorServerPhone("ss", tr, {"types": f"{acc},{gyro}"}), msgs,
                mutate_json, period_ns=2_500_000)


def _hyperimu_kind() -> Kind:
    from devices.phone_apps.hyperimu import HyperImuPhone
    from sim_devices.phone_apps_sim import hyperimu_rows

    rows = [[0.1 * i, -0.2, 9.8, 0.01, 0.02, -0.03 * i, 20.0, -5.0, 40.0] for i in range(200)]
    ts = [1_700_000_000_000 + 20 * i for i in range(200)]
    msgs = [hyperimu_rows([r], timestamps=[t]) for r, t in zip(rows, ts, strict=True)]
    return Kind("HyperIMU", "hyperimu",
                lambda tr: HyperImuPhone("himu", tr, {"timestamp": True, "rate": 50}), msgs,
                mutate_line, stream=True, end=b"\r\n", period_ns=20_000_000)


def _osc_kind() -> Kind:
    from devices.phone_apps.osc import OscPhone
    from sim_devices.phone_apps_sim import zigsim_bundle

    msgs = [zigsim_bundle("my-phone_1", accel=(0.01 * i, -0.02, 0.03), gravity=(0.0, -0.99, -0.1),
                          gyro=(0.1, 0.2 * i, -0.3), quaternion=(0.0, 0.0, 0.0, 1.0),
                          touches=[(0.5, -0.25)] if i % 5 == 0 else ())
            for i in range(200)]
    return Kind("OSC (ZIG SIM)", "osc", lambda tr: OscPhone("zs", tr, {}), msgs, mutate_osc,
                period_ns=16_666_667)


def _textline_kind() -> Kind:
    from devices.textline import TextLineImu

    path = TRACES / "a_imu_csv" / "fusion_sensor_data.csv"
    with path.open("rb") as f:
        lines = [next(f) for _ in range(302)]  # the header and 300 rows of the real x-io recording
    opts = {"format": "csv", "columns": "t,gx,gy,gz,ax,ay,az,mx,my,mz",
            "units": "s,dps,dps,dps,g,g,g,uT,uT,uT", "time": "t", "rate": "100"}
    return Kind("text-line IMU (x-io CSV trace)", "textline",
                lambda tr: TextLineImu("s", tr, opts), lines, mutate_line, stream=True,
                end=b"\n")


def _rvc_kind() -> Kind:
    from devices.bno08x import Bno08xRvcImu, encode_rvc

    real = (TRACES / "c_serial_imu" / "bno08x_uart_rvc_datasheet_example_frame.bin").read_bytes()
    msgs = [real] + [encode_rvc(i % 256, (1.0 * (i % 90), -2.0, 3.5), (0.1, -0.2, 9.8)) for i in range(1, 300)]
    return Kind("BNO08x UART-RVC", "bno08x_rvc", lambda tr: Bno08xRvcImu("b", tr, {}), msgs,
                binary_mutator(_rvc_sum, start=2), stream=True)


def _witmotion_kind() -> Kind:
    from devices.codecs.witmotion import WitMotionCodec
    from devices.witmotion import WitMotionImu, encode_cycle

    codec = WitMotionCodec()
    msgs = [encode_cycle(codec, (0.01 * (i % 50), -0.02, 1.0), (1.0, -2.0, 0.5 * (i % 7)), (10.0, -5.0, 90.0),
                         ms_of_day=1000 + 10 * i)[0] for i in range(300)]
    return Kind("WitMotion WT901", "witmotion",
                lambda tr: WitMotionImu("w", tr, {"device_clock": True, "rate": 100}), msgs,
                binary_mutator(_wit_sum), stream=True)


def _hid_kind(name: str, codec: str, url: str, limit: int = 400, lost_per_input: int = 0) -> Kind:
    """A HID kind from a simulated (``simhid://``) or recorded device: its RX reports, after the
    handshake, are the valid messages."""
    dev = open_device(url)
    dev.open()
    reports: list[bytes] = []
    try:
        while len(reports) < limit:
            for it in dev.poll(0.1):
                ch = getattr(it, "chunk", None)
                if isinstance(ch, Chunk) and ch.direction is Direction.RX:
                    reports.append(ch.data)
    except EndOfStream:
        pass
    finally:
        dev.close()
    return Kind(name, codec, None, reports, binary_mutator(None, start=1), period_ns=4_000_000, hid_url=url,
                lost_per_input=lost_per_input)


def _kinds() -> dict[str, Callable[[], Kind]]:
    roller = TRACES / "b_hid" / "hid_recorder" / "contour_rollermouse_red_doubleclick.hid"
    return {
        "textline": _textline_kind,
        "bno08x": _rvc_kind,
        "witmotion": _witmotion_kind,
        "sony": lambda: _hid_kind("Sony DualShock 4 (USB)", "sony", "pad=simhid://ds4?realtime=false&bus=usb&seed=3"),
        "dualsense": lambda: _hid_kind("Sony DualSense (USB)", "sony",
                                       "pad=simhid://dualsense?realtime=false&bus=usb&seed=3"),
        # its timer byte says which of a report's three IMU samples are new (overlapping_samples)
        "nintendo": lambda: _hid_kind("Nintendo Switch Pro (Bluetooth)", "nintendo",
                                      "pad=switchpro@simhid://switchpro?realtime=false&bus=bluetooth&seed=3",
                                      lost_per_input=2),
        "hid_generic": lambda: _hid_kind("generic HID mouse", "hid", "m=hid@simhid://mouse?realtime=false&seed=3"),
        "hid_recorded": lambda: _hid_kind("generic HID (real hid-recorder capture)", "hid",
                                          f"m=hid@simhid://{roller}?realtime=false"),
        "phone": _page_kind,
        "hyperimu": _hyperimu_kind,
        "osc": _osc_kind,
        "sensorserver": _sensorserver_kind,
        "sensorlogger": _sensorlogger_kind,
    }


KINDS = _kinds()

# -- running ------------------------------------------------------------------------------------------------
#: health() entries that move with any input, so they do not show that a message was accounted for
_NEUTRAL = {"chunks", "bytes", "bytes_in", "last_seen_ns", "readings", "rtt_last_ns", "rtt_min_ns",
            "page_offset_ns", "opens", "state", "last_error"}


def _counters(dev: Device) -> dict[str, Any]:
    return {k: v for k, v in dev.health().items() if k not in _NEUTRAL}


def _n_samples(items: list[Any]) -> int:
    return sum(1 if isinstance(x, Sample) else len(x.seq) if isinstance(x, SampleBatch) else 0 for x in items)


@dataclass
class FuzzResult:
    kind: str
    codec: str
    lost_per_input: int = 0
    inputs: int = 0
    escapes: int = 0
    silent: int = 0
    #: samples of the valid messages (as a device that sees only those gives them), and how many of
    #: them the fuzzed device did not give
    good_samples: int = 0
    good_lost: int = 0
    #: samples delivered with an infinite value (no sensor reads one)
    inf_delivered: int = 0
    #: chunks whose decode raised, caught by the device layer's net (``stats.decode_errors``) rather
    #: than refused by the codec with its reason
    net_caught: int = 0
    reader_state: str = ""
    samples: int = 0
    bus_samples: int = 0
    examples: list[str] = field(default_factory=list)

    def problems(self) -> list[str]:
        out = []
        if self.escapes:
            out.append(f"{self.escapes} escape(s)")
        if self.silent:
            out.append(f"{self.silent} silent drop(s)")
        if self.inf_delivered:
            out.append(f"{self.inf_delivered} sample(s) with an infinite value delivered")
        if self.good_lost > self.lost_per_input * self.inputs:
            out.append(f"{self.good_lost} of {self.good_samples} samples of valid messages not delivered")
        if self.reader_state and self.reader_state != DeviceState.FINISHED.value:
            out.append(f"reader ended {self.reader_state}")
        if self.reader_state and self.bus_samples != self.samples and not self.escapes:
            out.append(f"the bus got {self.bus_samples} samples, process_chunk gave {self.samples}")
        return out


def script(kind: Kind, n: int, seed: int) -> list[tuple[bytes, bool, int]]:
    """The chunks to feed: (data, is it a mutated message, index of the valid message) with valid
    messages cycling through ``kind.good`` and a mutated one before each of the first ``n``."""
    rng = random.Random(seed)
    good = kind.good
    out: list[tuple[bytes, bool, int]] = []
    for j in range(max(n, len(good))):
        gi = j % len(good)
        g = good[gi]
        if kind.renumber is not None:
            g = kind.renumber(g, 2 * j + 2)
        if j < n:
            src = good[rng.randrange(len(good))]
            if kind.renumber is not None:
                src = kind.renumber(src, 2 * j + 1)
            bad = kind.mutate(rng, src)
            while kind.stream and not bad:  # no bytes is no message on a byte stream
                bad = kind.mutate(rng, src)
            out.append((bad + kind.end, True, -1))
        out.append((g, False, gi))
    return out


def _keys(items: list[Any]) -> list[tuple[str, tuple[Any, ...]]]:
    """What identifies a sample whatever came before it: its stream and values (NaN as None)."""
    return [(x.stream, tuple(None if v != v else v for v in x.values)) for x in items if isinstance(x, Sample)]


def fuzz_kind(key: str, n: int, seed: int = 1, reader: bool = True, kind: Kind | None = None) -> FuzzResult:
    """Fuzz one device kind with ``n`` mutated messages (see the module docstring)."""
    kind = kind or KINDS[key]()
    res = FuzzResult(kind.name, kind.codec, kind.lost_per_input)
    chunks = script(kind, n, seed)
    timed = [Chunk(data, 10**12 + i * kind.period_ns, Direction.RX) for i, (data, _, _) in enumerate(chunks)]
    # the samples of the valid messages given to a device that sees nothing else
    ref = kind.make()
    want: collections.Counter[tuple[str, tuple[Any, ...]]] = collections.Counter()
    for ch, (_, bad, _) in zip(timed, chunks, strict=True):
        if not bad:
            want.update(_keys(ref.process_chunk(ch)))
    want.update(_keys(ref.finish()))
    dev = kind.make()
    got: collections.Counter[tuple[str, tuple[Any, ...]]] = collections.Counter()
    for ch, (data, bad, _) in zip(timed, chunks, strict=True):
        before = _counters(dev) if bad else None
        try:
            items = dev.process_chunk(ch)
        except Exception as exc:  # an escape: what the fuzzer looks for
            res.escapes += 1
            if len(res.examples) < 5:
                res.examples.append(f"escape {type(exc).__name__}: {exc} on {data[:160]!r}")
            continue
        res.samples += _n_samples(items)
        got.update(_keys(items))
        inf = [x for x in items if isinstance(x, Sample) and any(math.isinf(v) for v in x.values)]
        if inf:
            res.inf_delivered += len(inf)
            if len(res.examples) < 5:
                res.examples.append(f"infinite value delivered: {inf[0]} from {data[:160]!r}")
        if bad:
            res.inputs += 1
            if not _n_samples(items) and _counters(dev) == before and not (kind.stream and dev.codec.buffered):
                res.silent += 1
                if len(res.examples) < 5:
                    res.examples.append(f"silent: {data[:160]!r}")
    try:
        tail = dev.finish()
    except Exception as exc:
        res.escapes += 1
        res.examples.append(f"escape at the end: {type(exc).__name__}: {exc}")
        tail = []
    res.samples += _n_samples(tail)
    got.update(_keys(tail))
    missing = want - got
    res.net_caught = int(dev.health().get("decode_errors", 0))
    res.good_lost = sum(missing.values())
    res.good_samples = sum(want.values())
    if missing and len(res.examples) < 5:
        res.examples.append(f"{res.good_lost} sample(s) of valid messages missing, e.g. {next(iter(missing))}")
    if reader and kind.build is not None:
        res.reader_state, res.bus_samples = run_reader(kind, timed)
    return res


class ScriptTransport(Transport):
    """Hands out a list of chunks, then ends (``EndOfStream``): a finite source for a reader."""

    scheme = "fuzzscript"

    def __init__(self, chunks: list[Chunk]) -> None:
        super().__init__("fuzz")
        self._chunks = chunks
        self._i = 0
        self._open = False

    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False

    @property
    def is_open(self) -> bool:
        return self._open

    def write(self, data: bytes) -> Chunk:
        return self.stamp_tx(data)

    def read(self, timeout: float) -> Chunk | None:
        if self._i >= len(self._chunks):
            raise EndOfStream("script done")
        self._i += 1
        return self._chunks[self._i - 1]


class _Count(Subscriber):
    """Counts the samples that reach it over the bus."""

    def __init__(self) -> None:
        self.samples = 0

    def on_item(self, item: Any) -> None:
        self.samples += _n_samples([item])


def run_reader(kind: Kind, chunks: list[Chunk]) -> tuple[str, int]:
    """The chunks through a real ``DeviceReader`` and ``SampleBus`` (a fresh device on a transport
    that hands them out, then ends); returns the state the device ends in (``finished``) and the
    samples a subscriber received."""
    assert kind.build is not None
    dev = kind.build(ScriptTransport(chunks))
    bus = SampleBus()
    count = _Count()
    bus.subscribe(count, policy=Overflow.NEVER_DROP)
    rd = DeviceReader(dev, bus, ReconnectPolicy(enabled=False))
    rd.start()
    if not rd.join(120):
        rd.stop()
        bus.close(30)
        return "hung", count.samples
    bus.close(60)
    return dev.state.value, count.samples
