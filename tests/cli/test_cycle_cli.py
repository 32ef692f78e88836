"""``perfcap cycle``: a take of several performed loops in (a CSV or a recorded session), one clean
loop out (summary, ``--json``, ``-o`` CSV, ``--report`` PNG); input without a cycle or bad input is one
line and a non-zero exit, never a traceback. And the demo's cycle."""

from __future__ import annotations

import csv
import json
import os
import struct
import subprocess
import sys

import numpy as np
import pytest
from cli_helpers import one_line, run

import cycles
from sim_devices.loops import jittered_loops
from sim_devices.motion import WavingMotion

KEYS = {"period_s", "loops", "confidence", "cuts_s", "closure_error", "elapsed_ms"}
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def write_csv(path, header, rows):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        if header:
            w.writerow(header)
        w.writerows(rows)
    return str(path)


@pytest.fixture
def take():
    return jittered_loops(5, period_s=0.8, jitter=0.1, rate_hz=120, channels=3, seed=11)


@pytest.fixture
def take_csv(tmp_path, take):
    return write_csv(tmp_path / "take.csv", ["time_s", "a", "b", "c"],
                     [[repr(float(t)), *map(repr, map(float, v))] for t, v in zip(take.t, take.values, strict=True)])


def test_csv_in_json_out(take, take_csv, capsys):
    code, out, err = run(capsys, "cycle", take_csv, "--json")
    assert code == 0, err
    assert len(out.strip().splitlines()) == 1
    s = json.loads(out)
    assert KEYS <= set(s)
    assert s["period_s"] == pytest.approx(take.period_s, rel=0.03)
    assert s["loops"] >= 2 and 0.0 <= s["confidence"] <= 1.0 and s["confidence"] > 0.5
    assert s["channels"] == ["a", "b", "c"]
    assert s["elapsed_ms"] > 0.0 and s["closure_error"] >= 0.0
    cuts = np.array(s["cuts_s"])
    assert len(cuts) >= 2 and np.all(np.diff(cuts) > 0)
    assert take.t[0] <= cuts[0] and cuts[-1] <= take.t[-1]
    # the cuts fall one loop apart
    assert np.median(np.diff(cuts)) == pytest.approx(take.period_s, rel=0.1)


def test_human_summary(take_csv, capsys):
    code, out, err = run(capsys, "cycle", take_csv)
    assert code == 0, err
    assert out.startswith("cycle: period ") and "loops" in out and "confidence" in out and "cuts" in out
    assert "closure error" in out


def test_loop_csv_round_trip(take, take_csv, tmp_path, capsys):
    loop = str(tmp_path / "loop.csv")
    code, out, err = run(capsys, "cycle", take_csv, "-o", loop, "--json", "--seed", "3")
    assert code == 0, err
    with open(loop, newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["t", "a", "b", "c"]
    data = np.array(rows[1:], dtype=float)
    s = json.loads(out)
    assert data[0, 0] == 0.0 and data[-1, 0] == pytest.approx(s["period_s"], rel=1e-12)
    np.testing.assert_array_equal(data[0, 1:], data[-1, 1:])  # a closed loop
    # exactly the cycle the library extracts from the same input with the same seed
    ref = cycles.extract(take.t, take.values, channels=["a", "b", "c"], seed=3)
    np.testing.assert_array_equal(data[:, 0], ref.times_s)
    np.testing.assert_array_equal(data[:, 1:], ref.values)


def test_report_is_a_png(take_csv, tmp_path, capsys):
    png = tmp_path / "report.png"
    code, out, err = run(capsys, "cycle", take_csv, "--report", str(png))
    assert code == 0, err
    head = png.read_bytes()[:24]
    assert head[:8] == PNG_MAGIC and head[12:16] == b"IHDR"
    width, height = struct.unpack(">II", head[16:24])
    assert width >= 500 and height >= 300
    assert png.stat().st_size > 20_000  # drawn curves, not an empty canvas
    assert str(png) in out


def test_columns_pick_channels(take_csv, capsys):
    code, out, err = run(capsys, "cycle", take_csv, "--columns", "c,a", "--json")
    assert code == 0, err
    assert json.loads(out)["channels"] == ["c", "a"]


def test_headerless_csv_uses_the_first_column_as_time(take, tmp_path, capsys):
    p = write_csv(tmp_path / "plain.csv", None,
                  [[float(t), float(v[0])] for t, v in zip(take.t, take.values, strict=True)])
    code, out, err = run(capsys, "cycle", p, "--json")
    assert code == 0, err
    s = json.loads(out)
    assert s["ok"] is True
    assert s["channels"] == ["c1"] and s["period_s"] == pytest.approx(take.period_s, rel=0.03)


@pytest.fixture
def looping_session(tmp_path, capsys):
    path = str(tmp_path / "loop.mcap")
    code, _, err = run(capsys, "record", "-q", "-d", "w=synth://imu?rate=200&seed=1&loop_s=1.2&realtime=false"
                       "&duration=6", "-o", path)
    assert code == 0, err
    # the simulator's truth: the mean loop duration over the 6 s of device time recorded
    return path, WavingMotion(1, loop_s=1.2).mean_loop_s(0.0, 6.0 - 1 / 200)


def test_session_from_a_looping_synth_imu(looping_session, capsys):
    path, truth = looping_session
    code, out, err = run(capsys, "cycle", path, "--json")
    assert code == 0, err
    s = json.loads(out)
    assert s["stream"] == "w/imu"  # the only IMU stream (beside w/euler)
    assert s["channels"] == ["ax", "ay", "az", "gx", "gy", "gz"]  # not the temperature
    assert abs(s["period_s"] / truth - 1.0) < 0.01, (s["period_s"], truth)
    assert abs(s["period_s"] / 1.2 - 1.0) < 0.05
    assert s["loops"] >= 3 and s["confidence"] > 0.8


def test_session_euler_stream_in_degrees(looping_session, capsys):
    path, truth = looping_session
    code, out, err = run(capsys, "cycle", path, "--stream", "w/euler", "--json")
    assert code == 0, err
    s = json.loads(out)
    assert s["channels"] == ["roll", "pitch", "yaw"]
    assert abs(s["period_s"] / truth - 1.0) < 0.01, (s["period_s"], truth)


def test_session_orientation_quaternions(tmp_path, capsys):
    """The fused orientation (w, x, y, z) is extracted as rotations: unit quaternions out."""
    path = str(tmp_path / "q.mcap")
    code, _, err = run(capsys, "record", "-q", "--orientation", "-d", "w=synth://imu?rate=200&seed=2&loop_s=1.2"
                       "&realtime=false&duration=6", "-o", path)
    assert code == 0, err
    loop = tmp_path / "q_loop.csv"
    code, out, err = run(capsys, "cycle", path, "--stream", "w/orientation", "-o", str(loop), "--json")
    assert code == 0, err
    s = json.loads(out)
    truth = WavingMotion(2, loop_s=1.2).mean_loop_s(0.0, 6.0 - 1 / 200)
    assert s["channels"] == ["w", "x", "y", "z"]
    assert abs(s["period_s"] / truth - 1.0) < 0.01, (s["period_s"], truth)
    q = np.loadtxt(loop, delimiter=",", skiprows=1)[:, 1:]
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-9)


def test_session_stream_choice_and_unknown_stream(tmp_path, capsys):
    path = str(tmp_path / "two.mcap")
    fast = "realtime=false&duration=1"
    code, _, err = run(capsys, "record", "-q", "-d", f"a=synth://imu?{fast}", "-d", f"b=synth://imu?seed=2&{fast}",
                       "-o", path)
    assert code == 0, err
    code, out, err = run(capsys, "cycle", path)
    assert code == 2 and out == ""
    line = one_line(err)
    assert "--stream" in line and "a/imu" in line and "b/imu" in line
    code, _, err = run(capsys, "cycle", path, "--stream", "c/imu")
    assert code == 2 and "no stream 'c/imu'" in one_line(err)
    code, _, err = run(capsys, "cycle", path, "--stream", "a/imu", "--columns", "gx,nope")
    assert code == 2 and "no column 'nope'" in one_line(err)


def test_white_noise_has_no_cycle(tmp_path, capsys):
    rng = np.random.default_rng(5)
    t = np.arange(1200) / 120.0
    p = write_csv(tmp_path / "noise.csv", ["t", "x", "y"], [[ti, *rng.standard_normal(2)] for ti in t])
    code, out, err = run(capsys, "cycle", p)
    assert code == 1 and out == ""
    assert "no cycle" in one_line(err)


@pytest.mark.parametrize("kind", ["white noise", "random walk", "still"])
@pytest.mark.parametrize("seed", range(3))
def test_json_says_no_cycle_as_one_object_too(tmp_path, capsys, kind, seed):
    rng = np.random.default_rng(seed)
    t = np.arange(1500) / 100.0
    # (the random walk of seed 1 was once taken as periodic; tests/unit/cycles/test_extract_sweeps.py
    # holds the family)
    x = (rng.standard_normal((t.size, 2)) if kind == "white noise"
         else np.cumsum(rng.standard_normal((t.size, 2)), axis=0) if kind == "random walk"
         else np.full((t.size, 2), 1.5))
    p = write_csv(tmp_path / "in.csv", ["t", "x", "y"], [[ti, *row] for ti, row in zip(t, x, strict=True)])
    code, out, err = run(capsys, "cycle", p, "--json")
    assert code == 1 and "no cycle" in one_line(err)
    s = json.loads(out)  # one object on stdout, as on success
    assert s["ok"] is False and s["error"] == "no cycle" and s["reason"] in one_line(err)
    assert s["input"] == p and s["input_samples"] == t.size and s["stream"] is None


def test_constant_input_does_not_move(tmp_path, capsys):
    p = write_csv(tmp_path / "still.csv", ["time", "x"], [[i / 100.0, 1.5] for i in range(500)])
    code, out, err = run(capsys, "cycle", p)
    assert code == 1 and out == ""
    assert "does not move" in one_line(err)


def test_free_waving_session_has_no_cycle(tmp_path, capsys):
    """The synthetic IMU without loop_s waves on several incommensurate frequencies: no cycle."""
    path = str(tmp_path / "free.mcap")
    code, _, err = run(capsys, "record", "-q", "-d", "w=synth://imu?realtime=false&duration=5", "-o", path)
    assert code == 0, err
    code, out, err = run(capsys, "cycle", path, "--report", str(tmp_path / "r.png"))
    assert code == 1 and out == "" and "no cycle" in one_line(err)
    assert not (tmp_path / "r.png").exists()


@pytest.mark.parametrize("content, match", [
    (None, "no such file"),
    ("", "is empty"),
    ("t,x\n0,1\n0.1,abc\n", "line 3, column 'x': 'abc' is not a number"),
    ("t,x\n0,1,2\n", "3 fields where the header has 2"),
    ("time\n0\n1\n", "found one column"),
    (b"\xff\xfe\x00\x81binary\x00\x9c", "neither a perfcap session nor a text CSV"),
])
def test_bad_input_is_one_line(tmp_path, capsys, content, match):
    p = tmp_path / "in.csv"
    if isinstance(content, bytes):
        p.write_bytes(content)
    elif content is not None:
        p.write_text(content)
    code, out, err = run(capsys, "cycle", str(p))
    assert code == 2 and out == ""
    assert match in one_line(err)


def test_bad_columns_and_unwritable_outputs(take_csv, tmp_path, capsys):
    code, _, err = run(capsys, "cycle", take_csv, "--columns", "a,zz")
    assert code == 2 and "no column 'zz'" in one_line(err) and "time_s, a, b, c" in err
    code, _, err = run(capsys, "cycle", take_csv, "--columns", "time_s")
    assert code == 2 and "time column" in one_line(err)
    code, _, err = run(capsys, "cycle", take_csv, "--stream", "x/imu")
    assert code == 2 and "--stream is for perfcap sessions" in one_line(err)
    missing = tmp_path / "no" / "such" / "dir"
    code, _, err = run(capsys, "cycle", take_csv, "--report", str(missing / "r.png"))
    assert code == 2 and "cannot write" in one_line(err)
    code, _, err = run(capsys, "cycle", take_csv, "-o", str(missing / "loop.csv"))
    assert code == 2 and "cannot write" in one_line(err)
    code, _, err = run(capsys, "cycle", str(tmp_path))
    assert code == 2 and "is a directory" in one_line(err)


def test_demo_extracts_the_wrists_cycle(tmp_path):
    """The demo's wrist repeats a 1.2 s gesture: the demo finds its period against the simulator's truth
    and writes the report and the loop beside the session."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PERFCAP_")}
    session = tmp_path / "demo.mcap"
    p = subprocess.run([sys.executable, "-m", "capture.app.cli", "demo", "--duration", "4", "-q", "-o", str(session)],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=180, check=False)
    assert p.returncode == 0, p.stderr
    assert "Traceback" not in p.stderr
    line = next(ln for ln in p.stdout.splitlines() if ln.startswith("cycle:"))
    found = float(line.split("period ")[1].split(" s")[0])
    truth = float(line.split("simulated: ")[1].split(" s")[0])
    assert abs(found / truth - 1.0) < 0.01, line
    assert (tmp_path / "wrist_cycle.png").read_bytes()[:8] == PNG_MAGIC
    with open(tmp_path / "wrist_cycle.csv", newline="") as f:
        assert next(csv.reader(f)) == ["t", "ax", "ay", "az", "gx", "gy", "gz"]
    assert str(tmp_path / "wrist_cycle.png") in p.stdout
    # the streaming follower on the live bus had a cycle during the take
    # (during the 4 s take it usually has one after about 3 s; on a loaded machine it may not, and
    # then says why, which is fine too)
    live = next(ln for ln in p.stdout.splitlines() if "live: following wrist/imu" in ln)
    assert "the first cycle came" in live or "no cycle during the take (" in live, live


@pytest.mark.parametrize("style", ["bom_no_header", "semicolons", "tabs", "trailing_comma", "sensor_logger"])
def test_csv_dialects(take, tmp_path, capsys, style):
    rows = [[float(t), *map(float, v)] for t, v in zip(take.t, take.values, strict=True)]
    path = tmp_path / f"{style}.csv"
    if style == "bom_no_header":
        text = "\ufeff" + "\n".join(",".join(map(repr, r)) for r in rows) + "\n"
    elif style in ("semicolons", "tabs"):
        sep = ";" if style == "semicolons" else "\t"
        text = sep.join(["t", "a", "b", "c"]) + "\n" + "\n".join(sep.join(map(repr, r)) for r in rows) + "\n"
    elif style == "trailing_comma":
        text = "t,a,b,c,\n" + "\n".join(",".join(map(repr, r)) + "," for r in rows) + "\n"
    else:   # Sensor Logger: epoch nanoseconds, then seconds since the start, then z, y, x
        text = "time,seconds_elapsed,z,y,x\n" + "\n".join(
            f"{int(1.7e18 + r[0] * 1e9)},{r[0]!r},{r[3]!r},{r[2]!r},{r[1]!r}" for r in rows) + "\n"
    path.write_text(text, encoding="utf-8")
    code, out, err = run(capsys, "cycle", str(path), "--json")
    assert code == 0, err
    s = json.loads(out)
    assert abs(s["period_s"] / take.period_s - 1) < 0.02
    assert len(s["channels"]) == 3 and not any("time" in c or "seconds" in c for c in s["channels"])
