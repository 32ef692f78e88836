"""Hostile inputs to the parsers of untrusted files: how many fuzzed inputs each parser took, how many it
refused with its clear error, how many escaped with another exception (the target: none), the slowest
input and the memory it grew by, and the crafted worst case of each bound (Report Count 0xFFFFFFFF, the
most values a descriptor may declare, full-size line-less traces, full-size CSVs, deep JSON).

Each parser runs in its own process (so its peak RSS is its own) under RLIMIT_AS 2 GiB:

    .venv/bin/python benchmarks/bench_hostile_inputs.py [--n 2000] [--only descriptor|traces|synth|cycle|calibration]

Inputs are seeded: the same command gives the same inputs. The structure-aware generators are the
ones the tests use (``tests/unit/devices/test_hid_bounds.py``, ``test_trace_bounds.py``).
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import random
import resource
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from capture.clock import MONOTONIC  # noqa: E402

if TYPE_CHECKING:
    from collections.abc import Callable

TRACES = ROOT.parent / "shared" / "traces"
FAMILIES = ("descriptor", "traces", "synth", "cycle", "calibration")


def rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


class Campaign:
    def __init__(self, name: str, expected: tuple[type[BaseException], ...]) -> None:
        self.name, self.expected = name, expected
        self.n = self.refused = self.escaped = 0
        self.max_ms = 0.0
        self.escapes: list[str] = []

    def run(self, fn: Callable[[], Any]) -> None:
        self.n += 1
        t0 = MONOTONIC.now_ns()
        try:
            fn()
        except self.expected:
            self.refused += 1
        except Exception as exc:  # the figure this campaign exists to measure
            self.escaped += 1
            self.escapes.append(f"{type(exc).__name__}: {str(exc)[:100]}")
        self.max_ms = max(self.max_ms, (MONOTONIC.now_ns() - t0) / 1e6)


def crafted(name: str, fn: Callable[[], Any], expected: tuple[type[BaseException], ...]) -> dict[str, Any]:
    before = rss_mib()
    t0 = MONOTONIC.now_ns()
    try:
        fn()
        outcome = "accepted"
    except expected as exc:
        outcome = f"refused: {str(exc)[-90:]}"
    except Exception as exc:
        outcome = f"ESCAPED {type(exc).__name__}: {exc}"
    return {"case": name, "ms": round((MONOTONIC.now_ns() - t0) / 1e6, 1),
            "rss_growth_mib": round(rss_mib() - before, 1), "outcome": outcome}


def sparse(path: str, size: int) -> str:
    with open(path, "wb") as f:
        f.truncate(size)
    return path


# -- families --------------------------------------------------------------------------------------------
def descriptor_family(n: int, tmp: str) -> tuple[list[Campaign], list[dict[str, Any]]]:
    from capture.errors import ConfigError
    from devices.hid.descriptor import parse_descriptor
    from tests.unit.devices.test_hid_bounds import _TAGS, HUGE_200, _item, _mutate, assert_within_bounds, mouse
    from tests.unit.devices.test_hid_bounds import real_descriptors as reals

    rng = random.Random(16)
    big = [0, 1, 8, 16, 32, 33, 255, 256, 257, 12288, 12289, 0xFFFF, 0x10000, 0xFFFFFFFF]

    def structured() -> bytes:
        """Mostly well-formed: Push/Pop and collections mostly balanced, report IDs mostly valid; sizes,
        counts and usage ranges small, with one value in ten at or past a bound."""
        out = bytearray(_item(0x04, 1, 1) + _item(0x08, 2, 1) + _item(0xA0, 1, 1))
        pushed, depth = 0, 1
        names = sorted(_TAGS)
        weights = [4 if n in ("rsize", "rcount", "usage", "input", "feature", "umin", "umax") else 1 for n in names]
        for _ in range(rng.randint(0, 60)):
            name = rng.choices(names, weights)[0]
            if ((name == "pop" and not pushed) or (name == "end" and not depth)) and rng.random() < 0.9:
                continue
            pushed += {"push": 1, "pop": -1}.get(name, 0)
            depth += {"coll": 1, "end": -1}.get(name, 0)
            if name in ("rsize", "rcount", "umin", "umax", "usage"):
                v = rng.choice(big) if rng.random() < 0.1 else rng.getrandbits(rng.choice([1, 2, 3, 4, 5, 8]))
            elif name in ("input", "output", "feature"):
                v = rng.randrange(0x200)
            elif name == "rid":
                v = rng.randrange(1, 256) if rng.random() < 0.95 else rng.choice([0, 256, 0xFFFF])
            else:
                v = rng.randrange(0x10000)
            out += _item(_TAGS[name], v, rng.choice([0, 1, 2, 4]))
        return bytes(out + b"\xc0" * max(0, depth if rng.random() < 0.95 else depth - 1))

    def check(blob: bytes) -> None:
        assert_within_bounds(parse_descriptor(blob, "campaign"))

    s, m = Campaign("HID descriptor, structure-aware random", (ConfigError,)), Campaign(
        "HID descriptor, mutated real", (ConfigError,))
    real = list(reals().values())
    for _ in range(n):
        blob = structured()
        s.run(lambda blob=blob: check(blob))
        r = _mutate(rng, rng.choice(real))
        m.run(lambda r=r: check(r))
    body = [0x09, 0x30, 0x95, 0x01, 0x81, 0x02]
    for rid in range(2, 4):  # 2 x 12288 + 1 values: just within MAX_VALUES
        body += [0x85, rid, 0x09, 0x30, 0x96, 0x00, 0x30, 0xB1, 0x02]
    cases = [crafted("200-byte descriptor, Report Count 0xFFFFFFFF", lambda: parse_descriptor(HUGE_200, "x"),
                     (ConfigError,)),
             crafted("24,577 values (the most laid out)", lambda: parse_descriptor(mouse(*body), "x"), (ConfigError,))]
    return [s, m], cases


def traces_family(n: int, tmp: str) -> tuple[list[Campaign], list[dict[str, Any]]]:
    from capture.errors import TraceError
    from sim_devices import evemu
    from sim_devices.hid_recorder import MAX_TRACE_BYTES, parse_hid_recording
    from tests.unit.devices.test_trace_bounds import _within_bounds, mutate

    rng = random.Random(16)
    srcs = [("hid-recorder", TRACES / "b_hid" / "hid_recorder" / "contour_rollermouse_red_doubleclick.hid",
             parse_hid_recording),
            ("evemu events", TRACES / "f_pen_mouse_touch" / "evemu" / "saitek_cyborg_rat5_mouse.events",
             evemu.parse_events),
            ("evemu desc", TRACES / "f_pen_mouse_touch" / "evemu" / "wacom_intuos4_6x9.desc", evemu.parse_desc)]
    out = []
    for label, src, read in srcs:
        c = Campaign(f"{label}, mutated real", (TraceError,))
        text = src.read_bytes()
        p = os.path.join(tmp, src.name)
        for _ in range(n):
            with open(p, "wb") as f:
                f.write(mutate(rng, text))
            c.run(lambda read=read, p=p: _within_bounds(read(p)))
        out.append(c)
    big = sparse(os.path.join(tmp, "big.hid"), MAX_TRACE_BYTES)
    fifo = os.path.join(tmp, "fifo")
    os.mkfifo(fifo)
    cases = [crafted(f"{what} of {name}", lambda r=r, p=p: r(p), (TraceError,))
             for name, p in (("64 MiB, no line end", big), ("/dev/zero", "/dev/zero"), ("a FIFO", fifo))
             for what, r in (("hid-recorder", parse_hid_recording), ("evemu", evemu.parse_events))]
    return out, cases


def _fusion_head(lines: int) -> bytes:
    return b"\n".join((TRACES / "a_imu_csv" / "fusion_sensor_data.csv").read_bytes().split(b"\n")[:lines])


def _valid_imu_csv(path: str, size: int, columns: int = 7) -> str:
    with open(path, "w") as f:
        f.write(",".join(f"c{i}" for i in range(columns)) + "\n")
        i, written = 0, 0
        while written < size - 16 * columns:
            row = f"{i * 0.01:.2f}," + ",".join("0.5" for _ in range(columns - 1)) + "\n"
            f.write(row)
            written += len(row)
            i += 1
    return path


def synth_family(n: int, tmp: str) -> tuple[list[Campaign], list[dict[str, Any]]]:
    from capture.errors import ConfigError
    from sim_devices import synth
    from tests.unit.devices.test_trace_bounds import _play_csv, mutate

    rng = random.Random(16)
    c = Campaign("synth://imu?csv=, mutated real (opened, 100 reads)", (ConfigError,))
    text = _fusion_head(60)
    p = os.path.join(tmp, "in.csv")
    for _ in range(n):
        with open(p, "wb") as f:
            f.write(mutate(rng, text))
        c.run(lambda: _play_csv(p))
    full = _valid_imu_csv(os.path.join(tmp, "full.csv"), synth.MAX_CSV_BYTES)
    cases = [crafted("synth csv=/dev/zero", lambda: _play_csv("/dev/zero"), (ConfigError,)),
             crafted("synth csv= 32 MiB, no line end", lambda: _play_csv(sparse(os.path.join(tmp, "z"), 32 << 20)),
                     (ConfigError,)),
             crafted("synth csv= 32 MiB valid IMU rows (the largest played)", lambda: _play_csv(full), (ConfigError,))]
    return [c], cases


def cycle_family(n: int, tmp: str) -> tuple[list[Campaign], list[dict[str, Any]]]:
    from capture.app import cycle_input
    from capture.app.cycle_input import read_cycle_input
    from capture.errors import ConfigError
    from tests.unit.devices.test_trace_bounds import mutate

    rng = random.Random(16)
    c = Campaign("perfcap cycle CSV, mutated real", (ConfigError,))
    text = _fusion_head(80)
    p = os.path.join(tmp, "in.csv")
    for _ in range(n):
        with open(p, "wb") as f:
            f.write(mutate(rng, text))
        c.run(lambda: read_cycle_input(p, None, None))
    wide = _valid_imu_csv(os.path.join(tmp, "wide.csv"), cycle_input.MAX_CSV_BYTES, columns=1024)
    tall = _valid_imu_csv(os.path.join(tmp, "tall.csv"), cycle_input.MAX_CSV_BYTES, columns=4)
    cases = [crafted("cycle CSV 16 MiB, 1024 columns (the widest read)", lambda: read_cycle_input(wide, None, None),
                     (ConfigError,)),
             crafted("cycle CSV 16 MiB, 4 columns (the most rows read)", lambda: read_cycle_input(tall, None, None),
                     (ConfigError,)),
             crafted("cycle CSV /dev/zero", lambda: read_cycle_input("/dev/zero", None, None), (ConfigError,))]
    return [c], cases


def calibration_family(n: int, tmp: str) -> tuple[list[Campaign], list[dict[str, Any]]]:
    from capture.calibration_store import parse_calibration_document
    from capture.errors import ConfigError
    from tests.unit.capture.test_bounded_inputs import _paths, real_document

    rng = random.Random(16)
    odd: list[Any] = [None, True, 0, -1, 1e308, -1e308, float("nan"), "x", "1e999", [], {}, [[[[]]]], [1, 2, 3],
                      [[1, 0, 0], [0, 1, 0], [0, 0, 1]], 10**400, "perfcap.calibration.v1"]
    c = Campaign("calibration JSON, damaged real", (ConfigError,))
    for _ in range(n):
        doc = real_document()
        for _ in range(rng.randint(1, 3)):
            where = rng.choice(list(_paths(doc))[1:])
            node = doc
            for k in where[:-1]:
                node = node[k]
            node[where[-1]] = copy.deepcopy(rng.choice(odd))  # (a shared list would make a cycle)
        try:
            text = json.dumps(doc)
        except ValueError:
            continue
        if rng.random() < 0.3:
            i = rng.randrange(len(text) + 1)
            text = text[:i] + rng.choice(["[" * 50, "{", "]", '"', "NaN", "1e999"]) + text[i:]
        c.run(lambda text=text: parse_calibration_document(text, "campaign"))
    cases = [crafted("1 MiB of '['", lambda: parse_calibration_document("[" * (1 << 20), "x"), (ConfigError,)),
             crafted("1 MiB list of numbers", lambda: parse_calibration_document(
                 '{"format": "perfcap.calibration.v1", "calibration": [' + "1," * 500_000 + "1]}", "x"),
                 (ConfigError,))]
    return [c], cases


def child(family: str, n: int) -> None:
    resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))
    fn = {"descriptor": descriptor_family, "traces": traces_family, "synth": synth_family, "cycle": cycle_family,
          "calibration": calibration_family}[family]
    base = rss_mib()
    with tempfile.TemporaryDirectory() as tmp:
        campaigns, cases = fn(n, tmp)
    print(json.dumps({"campaigns": [{"parser": c.name, "inputs": c.n, "refused": c.refused, "escaped": c.escaped,
                                     "max_ms": round(c.max_ms, 1), "escapes": c.escapes[:5]} for c in campaigns],
                      "cases": cases, "peak_rss_mib": round(rss_mib(), 1), "base_rss_mib": round(base, 1)}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=2000, help="fuzzed inputs per campaign")
    ap.add_argument("--only", choices=FAMILIES)
    ap.add_argument("--child", choices=FAMILIES, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        child(a.child, a.n)
        return
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    ok = True
    print(f"{'parser':58} {'inputs':>7} {'refused':>8} {'escaped':>8} {'max ms':>8}")
    for fam in [a.only] if a.only else FAMILIES:
        res = subprocess.run([sys.executable, __file__, "--child", fam, "--n", str(a.n)], capture_output=True,
                             text=True, env=env, cwd=ROOT, check=False)
        if res.returncode:
            print(f"{fam}: the campaign process failed ({res.returncode}): {res.stderr[-2000:]}")
            ok = False
            continue
        r = json.loads(res.stdout.strip().splitlines()[-1])
        for c in r["campaigns"]:
            print(f"{c['parser']:58} {c['inputs']:7d} {c['refused']:8d} {c['escaped']:8d} {c['max_ms']:8.1f}")
            for e in c["escapes"]:
                print(f"    escaped: {e}")
            ok = ok and not c["escaped"]
        for k in r["cases"]:
            print(f"  crafted: {k['case']}: {k['ms']} ms, +{k['rss_growth_mib']} MiB RSS, {k['outcome']}")
            ok = ok and not k["outcome"].startswith("ESCAPED")
        print(f"  {fam} process: peak RSS {r['peak_rss_mib']} MiB (after imports {r['base_rss_mib']} MiB)")
    print("PASS: no input escaped its parser's error" if ok else "FAIL: an input escaped (see above)")


if __name__ == "__main__":
    main()
