"""Hostile HID report descriptors: each bound of ``devices.hid.bounds`` refused with the item and its
offset named, real descriptors still laid out, structure-aware random and mutated real descriptors
either laid out within the bounds or refused with a ``ConfigError``, and the Report Count
0xFFFFFFFF descriptor refused under a 1 GiB address-space limit."""

from __future__ import annotations

import json
import random
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from capture.errors import ConfigError
from devices.hid import bounds
from devices.hid.descriptor import STANDARD_DESCRIPTORS, DescriptorLayout, parse_descriptor

TRACES = Path(__file__).resolve().parents[3].parent / "shared" / "traces" / "b_hid"
ROOT = Path(__file__).resolve().parents[3]

# a mouse prefix: Usage Page (GD), Usage (Mouse), Collection (Application), buttons 1..3 of 1 bit
_PREFIX = bytes([0x05, 0x01, 0x09, 0x02, 0xA1, 0x01, 0x05, 0x09, 0x19, 0x01, 0x29, 0x03,
                 0x15, 0x00, 0x25, 0x01, 0x75, 0x01])
#: the issue's case: Report Count 0xFFFFFFFF (a 4-byte item at byte 18), then Input (Data,Var,Abs)
HUGE_COUNT = _PREFIX + bytes([0x97, 0xFF, 0xFF, 0xFF, 0xFF, 0x81, 0x02, 0xC0])
HUGE_200 = HUGE_COUNT + b"\x09\x30" * 87  # 200 bytes, as in the issue


def mouse(*body: int, end: bool = True) -> bytes:
    """The mouse prefix, ``body``, End Collection."""
    return _PREFIX + bytes(body) + (b"\xc0" if end else b"")


def real_descriptors() -> dict[str, bytes]:
    out = dict(STANDARD_DESCRIPTORS)
    cts = TRACES / "android_cts"
    for p in sorted(cts.glob("*.json")) if cts.is_dir() else []:
        text = re.sub(r"\b0x([0-9a-fA-F]+)\b", lambda m: str(int(m.group(1), 16)), p.read_text())
        out[p.stem] = bytes(json.loads(text)["descriptor"])
    hid = TRACES / "hid_recorder" / "contour_rollermouse_red_doubleclick.hid"
    if hid.is_file():
        from sim_devices.hid_recorder import parse_hid_recording

        out[hid.stem] = parse_hid_recording(str(hid))[0].rdesc
    return out


def assert_within_bounds(lay: DescriptorLayout) -> None:
    values = 0
    for rep in lay.reports.values():
        assert rep.size <= bounds.HID_MAX_BUFFER_SIZE
        for f in rep.fields:
            assert 0 <= f.size <= bounds.MAX_DATA_FIELD_BITS
            assert f.count <= bounds.HID_MAX_USAGES
            assert len(f.usages) <= bounds.MAX_USAGE_RANGE
            assert f.bit + f.size * f.count <= rep.size * 8
            values += 1
    assert values <= bounds.MAX_VALUES


def test_report_count_0xffffffff_is_refused_naming_the_item_and_its_offset():
    with pytest.raises(ConfigError, match=r"Report Count \(0xffffffff\) at byte 18: more than 12288"):
        parse_descriptor(HUGE_COUNT, "hostile")


@pytest.mark.parametrize(("blob", "message"), [
    (mouse(0x76, 0x01, 0x01, 0x95, 0x01, 0x81, 0x03), r"Report Size \(0x101\) at byte 18: more than 256 bits"),
    (mouse(0x75, 0x21, 0x95, 0x01, 0x81, 0x02), r"Input \(0x2\) at byte 22: a data field of Report Size 33"),
    (mouse(0x85, 0x00, 0x95, 0x01, 0x81, 0x02), r"Report ID \(0x0\) at byte 18: a report ID is 1..255"),
    (mouse(0x86, 0x00, 0x01, 0x95, 0x01, 0x81, 0x02), r"Report ID \(0x100\) at byte 18"),
    (mouse(*[0xA4] * 5), r"Push \(0x0\) at byte 22: pushed deeper than 4"),
    (mouse(0xB4), r"Pop \(0x0\) at byte 18: nothing was pushed"),
    (bytes([0xC0]), r"End Collection \(0x0\) at byte 0: no collection is open"),
    (mouse(0x95, 0x03, 0x81, 0x02, end=False), r"leaves 1 collection\(s\) open"),
    (mouse(*[0xA1, 0x02] * 32), r"Collection \(0x2\) at byte 80: collections nested deeper than 32"),
    # Usage Minimum 1, Usage Maximum 0x10001 (4-byte forms): an array of 65537 usages
    (mouse(0x1B, 0x01, 0, 0, 0, 0x2B, 0x01, 0, 0x01, 0, 0x75, 0x08, 0x95, 0x01, 0x81, 0x00),
     r"Input \(0x0\) at byte 32: its Usage Minimum..Maximum spans 65537 usages"),
    # 12288 x 16 bits = 24 KiB in one report
    (mouse(0x75, 0x10, 0x96, 0x00, 0x30, 0x81, 0x03), r"Input \(0x3\) at byte 23: report 0 \(Input\) grows to 24576"),
])
def test_each_bound_is_refused_with_the_item_and_its_offset(blob, message):
    with pytest.raises(ConfigError, match=message):
        parse_descriptor(blob, "hostile")


def test_more_than_256_fields_in_one_report_are_refused():
    blob = mouse(0x95, 0x01, *[0x09, 0x30, 0x81, 0x02] * 257)
    with pytest.raises(ConfigError, match=r"report 0 \(Input\) has more than 256 fields"):
        parse_descriptor(blob, "hostile")


def test_more_values_than_the_bound_are_refused_across_reports():
    # 6 feature reports of 12288 one-bit variables with a usage: 73,728 values (12 KiB of bits in all)
    body = [0x09, 0x30, 0x95, 0x01, 0x81, 0x02]
    for rid in range(2, 8):
        body += [0x85, rid, 0x09, 0x30, 0x96, 0x00, 0x30, 0xB1, 0x02]
    with pytest.raises(ConfigError, match=rf"more than {bounds.MAX_VALUES} values"):
        parse_descriptor(mouse(*body), "hostile")


def test_a_descriptor_longer_than_linux_accepts_is_refused_before_it_is_tokenised():
    with pytest.raises(ConfigError, match=r"is 4097 bytes \(Linux accepts at most 4096\)"):
        parse_descriptor(b"\x09\x30" * 2048 + b"\xc0", "hostile")


_FULL = (0x95, 0x03, 0x81, 0x02, 0x75, 0x05, 0x95, 0x01, 0x81, 0x03,  # 3 buttons, 5 bits padding
         0x75, 0x08, 0x96, 0x00, 0x30, 0x81, 0x03, 0x96, 0xFF, 0x0F, 0x81, 0x03,  # 12288 + 4095 bytes padding
         *[0xA4] * 4, *[0xB4] * 4)


def test_the_limits_themselves_are_accepted_and_one_bit_more_is_not():
    lay = parse_descriptor(mouse(*_FULL), "at the limits")
    assert lay.reports[None].size == bounds.HID_MAX_BUFFER_SIZE
    assert_within_bounds(lay)
    with pytest.raises(ConfigError, match=r"report 0 \(Input\) grows to 16385 bytes"):
        parse_descriptor(mouse(*_FULL, 0x75, 0x01, 0x95, 0x01, 0x81, 0x03), "one bit more")


@pytest.mark.parametrize("name", sorted(real_descriptors()))
def test_real_descriptors_are_within_the_bounds(name):
    assert_within_bounds(parse_descriptor(real_descriptors()[name], name))


# -- structure-aware random descriptors ----------------------------------------------------------------
_SIZES = st.sampled_from([0, 1, 2, 4])
_BIG = st.one_of(st.integers(0, 40), st.sampled_from([255, 256, 257, 12288, 12289, 0xFFFF, 0x10000, 0xFFFFFFFF]),
                 st.integers(0, 0xFFFFFFFF))
_TAGS = {"page": 0x04, "lmin": 0x14, "lmax": 0x24, "pmin": 0x34, "pmax": 0x44, "uexp": 0x54, "unit": 0x64,
         "rsize": 0x74, "rid": 0x84, "rcount": 0x94, "push": 0xA4, "pop": 0xB4, "usage": 0x08, "umin": 0x18,
         "umax": 0x28, "input": 0x80, "output": 0x90, "feature": 0xB0, "coll": 0xA0, "end": 0xC0}


def _item(tag: int, value: int, nbytes: int) -> bytes:
    nbytes = max(nbytes, (value.bit_length() + 7) // 8) if value else nbytes
    nbytes = 4 if nbytes > 2 else nbytes
    code = {0: 0, 1: 1, 2: 2, 4: 3}[nbytes]
    return bytes([tag | code]) + (value & ((1 << (8 * nbytes)) - 1)).to_bytes(nbytes, "little")


@st.composite
def descriptors(draw: st.DrawFn) -> bytes:
    """Valid item headers with random payload sizes and values: report sizes and counts near and past
    the bounds, random nesting, Push/Pop, usage ranges, every main item type."""
    out = bytearray(_item(0x04, 1, 1) + _item(0x08, 2, 1) + _item(0xA0, 1, 1))
    for _ in range(draw(st.integers(0, 40))):
        name = draw(st.sampled_from(sorted(_TAGS)))
        if name in ("rsize", "rcount", "umin", "umax", "usage"):
            value = draw(_BIG)
        elif name in ("input", "output", "feature"):
            value = draw(st.integers(0, 0x1FF))
        else:
            value = draw(st.integers(0, 0xFFFF))
        out += _item(_TAGS[name], value, draw(_SIZES))
    if draw(st.booleans()):
        out += b"\xc0"
    return bytes(out)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(descriptors())
def test_structured_random_descriptors_are_laid_out_within_bounds_or_refused(blob):
    try:
        lay = parse_descriptor(blob, "fuzz")
    except ConfigError:
        return
    assert_within_bounds(lay)


MUTATIONS = 80  # per real descriptor


def _mutate(rng: random.Random, blob: bytes) -> bytes:
    b = bytearray(blob)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(5)
        i = rng.randrange(len(b)) if b else 0
        if op == 0 and b:
            b[i] ^= 1 << rng.randrange(8)
        elif op == 1 and b:
            b[i] = rng.choice([0x00, 0xFF, 0x7F, 0x80])
        elif op == 2:  # a 4-byte Report Count or Report Size with a large value
            b[i:i] = bytes([rng.choice([0x97, 0x77, 0x2B, 0x1B])]) + rng.getrandbits(32).to_bytes(4, "little")
        elif op == 3:  # repeat a slice (nesting, Push, fields)
            j = min(len(b), i + rng.randint(1, 16))
            b[i:i] = b[i:j] * rng.randint(2, 40)
        else:
            del b[i:i + rng.randint(1, 8)]
    return bytes(b[:bounds.HID_MAX_DESCRIPTOR_SIZE + 64])


def test_mutated_real_descriptors_are_laid_out_within_bounds_or_refused():
    rng = random.Random(16)
    laid = refused = 0
    for name, blob in real_descriptors().items():
        for _ in range(MUTATIONS):
            try:
                lay = parse_descriptor(_mutate(rng, blob), name)
            except ConfigError:
                refused += 1
                continue
            assert_within_bounds(lay)
            laid += 1
    assert laid and refused  # both outcomes are exercised


def test_report_count_0xffffffff_is_refused_under_a_1_gib_address_space_limit():
    """Without the bounds hid-tools grows until the limit stops it (MemoryError, not a ConfigError);
    with them the descriptor is refused at once, well inside 1 GiB."""
    code = textwrap.dedent(f"""
        import resource
        resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))
        from capture.errors import ConfigError
        from devices.hid.descriptor import parse_descriptor
        try:
            parse_descriptor(bytes.fromhex({HUGE_200.hex()!r}), "hostile")
        except ConfigError as exc:
            print("refused:", exc)
        # VmHWM: this process image's own peak (ru_maxrss carries a big parent's peak over fork and exec)
        peak = [ln for ln in open("/proc/self/status") if ln.startswith("VmHWM:")]
        print("maxrss_kib", int(peak[0].split()[1]))
    """)
    env = {"PATH": "/usr/bin:/bin", "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env,
                         cwd=ROOT, check=False)
    assert res.returncode == 0, res.stderr
    assert "refused:" in res.stdout and "Report Count (0xffffffff) at byte 18" in res.stdout
    rss_kib = int(res.stdout.split("maxrss_kib")[1])
    assert rss_kib < 512 * 1024  # grew by nothing like the report count


def test_a_data_variable_without_usages_is_padding_as_in_linux_not_a_48_bit_field():
    """hid-tools merges such an item into one field of Report Size x Report Count bits (found by the
    mutation test); Linux ignores a main item without usages, and so does the layout."""
    blob = bytes([0x05, 0x01, 0x09, 0x05, 0xA1, 0x01, 0x09, 0x30, 0x15, 0x00, 0x26, 0xFF, 0x00, 0x75, 0x08,
                  0x95, 0x01, 0x81, 0x02, 0x95, 0x06, 0x81, 0x02, 0xC0])
    lay = parse_descriptor(blob, "usage-less variable")
    rep = lay.reports[None]
    assert [f.name for f in rep.fields] == ["X"] and rep.size == 7
    assert rep.decode_many(np.zeros((3, 7), np.uint8)).shape == (3, 1)
