"""Untrusted files read within bounds: ``capture.bounded_io`` itself, calibration JSON (the store and
the copies in sessions) and ``perfcap cycle`` CSV inputs. Regression tests for each bound, and
property tests: damaged real calibration documents and random or mutated real CSV files either read
or refused with a ``ConfigError``, never another exception."""

from __future__ import annotations

import json
import os
import random
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from capture.app import cycle_input
from capture.app.cycle_input import read_cycle_input
from capture.bounded_io import (
    InputLimitError,
    bounded_lines,
    json_depth,
    json_loads_bounded,
    longest_line,
    read_bounded,
)
from capture.calibration import ImuCalibration
from capture.calibration_store import (
    MAX_DOCUMENT_DEPTH,
    CalibrationStore,
    calibration_document,
    parse_calibration_document,
)
from capture.errors import ConfigError
from capture.sample import DeviceIdentity

TRACES = Path(__file__).resolve().parents[3].parent / "shared" / "traces"
FUSION = TRACES / "a_imu_csv" / "fusion_sensor_data.csv"
GAITMAP = TRACES / "a_imu_csv" / "gaitmap_walk" / "imu_sample_not_rotated.csv"
IDENT = DeviceIdentity("witmotion", "wrist")


def sparse(path: Path, size: int) -> str:
    with open(path, "wb") as f:
        f.truncate(size)
    return str(path)


# -- capture.bounded_io ----------------------------------------------------------------------------------
def test_read_bounded_reads_regular_files_up_to_the_cap_only(tmp_path):
    p = tmp_path / "f"
    p.write_bytes(b"x" * 100)
    assert read_bounded(p, 100) == b"x" * 100
    with pytest.raises(InputLimitError, match="is 100 bytes; at most 99 bytes is read"):
        read_bounded(p, 99)
    with pytest.raises(InputLimitError, match="is a directory"):
        read_bounded(tmp_path, 100)
    os.mkfifo(tmp_path / "fifo")
    with pytest.raises(InputLimitError, match="is a FIFO"):
        read_bounded(tmp_path / "fifo", 100)
    with pytest.raises(FileNotFoundError):
        read_bounded(tmp_path / "missing", 100)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=3000).map(lambda b: b.replace(b"\x00", b"\n")), st.integers(1, 64))
def test_longest_line_and_bounded_lines_agree_with_split(data, cap):
    assert longest_line(data) == max(len(x) for x in data.split(b"\n"))
    text = data.decode("latin-1")
    parts = text.split("\n")
    want = [x + "\n" for x in parts[:-1]] + ([parts[-1]] if parts[-1] else [])
    try:
        got = list(bounded_lines(text, cap, 10_000, "t"))
    except InputLimitError:
        assert longest_line(data) > cap
        return
    assert got == want


def test_json_nesting_is_refused_past_the_cap_and_past_pythons_own_parser():
    assert json_depth(json_loads_bounded("[[1, {\"a\": [2]}]]", 100, 4)) == 4
    with pytest.raises(InputLimitError, match="nests 5 levels deep; at most 4"):
        json_loads_bounded("[[[[[1]]]]]", 100, 4)
    with pytest.raises(InputLimitError, match="deeper than Python's parser goes"):
        json_loads_bounded("[" * 100_000, 1 << 20, 32)  # json.loads alone raises RecursionError
    with pytest.raises(InputLimitError, match="at most 10 bytes"):
        json_loads_bounded("[1, 2, 3, 4]", 10, 4)


# -- calibration JSON ---------------------------------------------------------------------------------------
def real_document() -> dict:
    cal = ImuCalibration(gyro_bias=(0.01, -0.02, 0.003), acc_offset=(0.1, -0.2, 0.05))
    return calibration_document(IDENT, cal, 1.7e9, "wrist")


@pytest.mark.parametrize(("text", "message"), [
    ("[" * 100_000, "deeper than Python's parser goes"),   # was RecursionError out of the store
    ('{"format": "perfcap.calibration.v1", "calibration": ' + "[" * 40 + "]" * 40 + "}", "nests 41 levels deep"),
    (" " * ((1 << 20) + 1), "at most 1.0 MiB"),
])
def test_hostile_calibration_documents_are_config_errors(text, message):
    with pytest.raises(ConfigError, match=message):
        parse_calibration_document(text, "session: imu/calibration")


def test_a_hostile_calibration_file_in_the_store_is_refused_and_listed(tmp_path):
    store = CalibrationStore(tmp_path)
    p = store.path_for(IDENT)
    sparse(p, 64 << 20)
    with pytest.raises(ConfigError, match=r"is 64\.0 MiB; at most 1\.0 MiB"):
        store.load(IDENT)
    p.unlink()
    os.mkfifo(p)   # would block the read for ever
    with pytest.raises(ConfigError, match="a FIFO, not a regular file"):
        store.load(IDENT)
    [(path, doc, err)] = store.entries()
    assert path == p and doc is None and "FIFO" in (err or "")


@pytest.mark.parametrize("field", ["yaw_offset_rad", "gyro_bias_rad_s", "acc_matrix", "mounting_wxyz"])
def test_an_integer_past_float_range_in_any_field_is_a_config_error(field):
    """(OverflowError escaped from yaw_offset_rad, found by benchmarks/bench_hostile_inputs.py)"""
    doc = real_document()
    value = doc["calibration"][field]
    if isinstance(value, list):
        value[0] = [10**400, 0, 0] if isinstance(value[0], list) else 10**400
    else:
        value = 10**400
    doc["calibration"][field] = value
    with pytest.raises(ConfigError, match=field.split("_wxyz")[0].split("_rad_s")[0]):
        parse_calibration_document(json.dumps(doc), "session: imu/calibration")


_JSON = st.recursive(st.none() | st.booleans() | st.floats() | st.integers() | st.text(max_size=8),
                     lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=6), kids, max_size=4),
                     max_leaves=20)


def _paths(doc, prefix=()):
    yield prefix
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _paths(v, (*prefix, i))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_damaged_real_calibration_documents_load_or_are_config_errors(data):
    doc = real_document()
    for _ in range(data.draw(st.integers(1, 3))):
        paths = list(_paths(doc))[1:]
        where = data.draw(st.sampled_from(paths))
        node = doc
        for k in where[:-1]:
            node = node[k]
        node[where[-1]] = data.draw(_JSON | st.sampled_from([float("nan"), 1e308, -1e308, "1e999", [[[[]]]], 10**400]))
    text = json.dumps(doc)
    if data.draw(st.booleans()):
        i = data.draw(st.integers(0, len(text)))
        text = text[:i] + data.draw(st.sampled_from(["[" * 50, "{", "]", "\"", "NaN", "1e999"])) + text[i:]
    try:
        got, cal = parse_calibration_document(text, "fuzz")
    except ConfigError:
        return
    assert isinstance(cal, ImuCalibration) and json_depth(got) <= MAX_DOCUMENT_DEPTH


# -- perfcap cycle CSV inputs -------------------------------------------------------------------------------
def test_csv_inputs_beyond_the_bounds_are_config_errors(tmp_path):
    from tests.unit.devices.test_trace_bounds import char_device

    with pytest.raises(ConfigError, match="not a regular file"):
        read_cycle_input(char_device(), None, None)
    os.mkfifo(tmp_path / "fifo.csv")
    with pytest.raises(ConfigError, match="not a regular file"):
        read_cycle_input(str(tmp_path / "fifo.csv"), None, None)   # stat, not open: a FIFO blocks
    big = sparse(tmp_path / "big.csv", cycle_input.MAX_CSV_BYTES + 1)
    with pytest.raises(ConfigError, match=r"at most 16\.0 MiB is read \(for a longer take, extract from"):
        read_cycle_input(big, None, None)
    (tmp_path / "long.csv").write_text("t,x\n" + "1" * (cycle_input.MAX_CSV_LINE + 1) + "\n")
    with pytest.raises(ConfigError, match=r"has a line of 65537 bytes"):
        read_cycle_input(str(tmp_path / "long.csv"), None, None)
    wide = ",".join(f"c{i}" for i in range(cycle_input.MAX_CSV_COLUMNS + 1))
    (tmp_path / "wide.csv").write_text(wide + "\n" + ",".join("1" * (cycle_input.MAX_CSV_COLUMNS + 1)) + "\n")
    with pytest.raises(ConfigError, match="a row of 1025 fields; at most 1024"):
        read_cycle_input(str(tmp_path / "wide.csv"), None, None)


_CELL = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.integers().map(str),
                  st.sampled_from(["", " ", "x", "1e999", "nan", '"', '"a,b"', "\ufeff", "\r"]))


@st.composite
def csv_texts(draw: st.DrawFn) -> str:
    sep = draw(st.sampled_from([",", ";", "\t"]))
    ncol = draw(st.integers(1, 6))
    head = [draw(st.sampled_from(["t", "time", "seconds_elapsed", "t_bus_ns", "x", "y", "", "gyro_x"]))
            for _ in range(ncol)]
    rows = [sep.join(head)] if draw(st.booleans()) else []
    for _ in range(draw(st.integers(0, 30))):
        rows.append(sep.join(draw(_CELL) for _ in range(draw(st.integers(max(1, ncol - 1), ncol + 1)))))
    return "\n".join(rows) + draw(st.sampled_from(["", "\n", "\r\n"]))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                   HealthCheck.function_scoped_fixture])
@given(csv_texts())
def test_random_csv_files_are_read_or_config_errors(tmp_path, text):
    p = tmp_path / "in.csv"
    p.write_text(text, encoding="utf-8", errors="surrogatepass")
    try:
        inp = read_cycle_input(str(p), None, None)
    except ConfigError:
        return
    assert inp.values.shape[0] == inp.t.shape[0] and np.all(np.isfinite(inp.values))


@pytest.mark.parametrize(("src", "some_read"), [(FUSION, True), (GAITMAP, False)], ids=["fusion", "gaitmap"])
def test_mutated_real_csv_files_are_read_or_config_errors(src, some_read, tmp_path):
    """(gaitmap's two header rows are refused however they are damaged; x-io's file is mostly read)"""
    if not src.is_file():
        pytest.skip(f"trace {src.name} not found at {src}")
    from tests.unit.devices.test_trace_bounds import mutate

    text = b"\n".join(src.read_bytes().split(b"\n")[:80])
    rng = random.Random(f"16b-{src.name}")
    p = tmp_path / "in.csv"
    read = 0
    for _ in range(150):
        p.write_bytes(mutate(rng, text))
        try:
            inp = read_cycle_input(str(p), None, None)
        except ConfigError:
            continue
        assert np.all(np.isfinite(inp.values)) and np.all(np.isfinite(inp.t))
        read += 1
    assert bool(read) == some_read
