"""The perfcap command line: each command on good input, and bad input giving one clear line and
a non-zero exit, never a traceback."""

from __future__ import annotations

import json
import os

import pytest
from cli_helpers import run

from capture.app.cli import main
from capture.app.orchestrator import Capture

FAST = "realtime=false&duration=2"


@pytest.fixture
def take(tmp_path, capsys):
    path = str(tmp_path / "t.mcap")
    code, _out, err = run(capsys, "record", "-q", "-d", f"a=synth://imu?rate=200&{FAST}",
                         "-d", f"b=synth://imu?rate=100&device_clock=false&seed=2&{FAST}", "-o", path)
    assert code == 0, err
    return path


def test_record_info_json(take, capsys):
    code, out, _ = run(capsys, "info", take, "--json")
    assert code == 0
    info = json.loads(out)
    assert info["complete"] is True and 1.9 < info["duration_s"] < 2.1
    by = {s["name"]: s for s in info["streams"]}
    assert {"name", "kind", "samples", "rate_hz", "drops"} <= set(by["a/imu"])
    assert by["a/imu"]["samples"] == 400 and by["a/imu"]["kind"] == "imu" and by["a/imu"]["drops"] == 0
    assert by["b/imu"]["rate_hz"] == pytest.approx(100, rel=0.01)
    code, out, _ = run(capsys, "info", take)
    assert code == 0 and "a/imu" in out and "drift" in out


def test_replay_fast_verifies(take, capsys):
    code, out, _ = run(capsys, "replay", take, "--fast", "-q")
    assert code == 0 and "verified: all 1200 replayed samples equal" in out
    code, out, _ = run(capsys, "replay", take, "--fast", "-q", "--json")
    assert json.loads(out)["verification"]["equal"] is True


def test_replay_realtime_speed(take, capsys):
    code, out, _ = run(capsys, "replay", take, "--speed", "0.8", "-q", "--json")
    r = json.loads(out)
    assert code == 0 and r["verification"]["equal"]
    # a paced replay never runs ahead of its schedule, however busy the machine: at 0.8x the 2 s take
    # takes at least 2.5 s (played at 1x or faster, it would take less)
    assert r["wall_s"] >= r["recorded_s"] / 0.8


def test_paced_replay_stopped_early_is_not_a_mismatch(tmp_path, capsys):
    s = tmp_path / "s.mcap"
    Capture(["a=synth://imu?rate=100&realtime=false&duration=3"], output=str(s), fsync=False).run(None)
    code, out, err = run(capsys, "replay", str(s), "--duration", "0.4", "-q", "--json")
    assert code == 0, err
    r = json.loads(out)
    # what was replayed before the stop is compared (it is equal), not called a mismatch for the rest
    assert r["stopped_early"] and 0.0 < r["replayed_s"] < r["recorded_s"] and r["recorded_s"] > 2.9
    assert all(v["mismatches"] == 0 for v in r["verification"]["streams"].values())


@pytest.mark.parametrize("fmt", ["csv", "jsonl"])
def test_export(take, tmp_path, capsys, fmt):
    d = str(tmp_path / "exp")
    code, _out, _ = run(capsys, "export", take, "--format", fmt, "-o", d)
    assert code == 0
    files = sorted(os.listdir(d))
    assert f"a__imu.{fmt}" in files and f"_events.{fmt}" in files
    with open(os.path.join(d, f"a__imu.{fmt}")) as f:
        lines = f.read().splitlines()
    if fmt == "csv":
        assert lines[0].startswith("seq,t_host_ns,t_device_ns,t_bus_ns,ax[m/s^2]") and len(lines) == 401
    else:
        row = json.loads(lines[0])
        assert row["seq"] == 0 and set(row["values"]) == {"ax", "ay", "az", "gx", "gy", "gz", "temp"}
        assert len(lines) == 400
    code, _, err = run(capsys, "export", take, "--format", fmt, "-o", d)
    assert code == 2 and "already exists" in err
    assert run(capsys, "export", take, "--format", fmt, "-o", d, "--overwrite")[0] == 0


def test_devices_lists_kinds_and_transports(capsys):
    code, out, _ = run(capsys, "devices")
    assert code == 0 and "witmotion" in out and "synth://imu" in out and "replay://" in out


@pytest.mark.parametrize("argv,match", [
    (["record", "-d", "bogus", "-o", "{tmp}/x.mcap"], "expected [NAME=][KIND@]SCHEME://"),
    (["record", "-d", "synth://imu?rte=1", "-o", "{tmp}/x.mcap"], "unknown option 'rte'"),
    (["record", "-d", "nokind@synth://imu", "-o", "{tmp}/x.mcap"], "unknown device kind"),
    (["record", "-d", "witmotion@nope://x", "-o", "{tmp}/x.mcap"], "unknown transport scheme"),
    (["record", "-o", "{tmp}/x.mcap"], "no devices"),
    (["record", "-d", "synth://imu", "--duration", "-1", "-o", "{tmp}/x.mcap"], "--duration: '-1' must be within (0,"),
    (["record", "-d", "synth://imu", "--duration", "nan", "-o", "{tmp}/x.mcap"], "--duration: 'nan' is not NUMBER"),
    (["record", "-d", "synth://imu", "--duration", "1", "-o", "{tmp}/x.mcap", "--config", "{tmp}/none.toml"],
     "no such config file"),
    (["record", "-d", "synth://imu", "--duration", "1", "-o", "{tmp}/x.mcap", "--profile", "nope"], "unknown profile"),
    (["record", "-d", "synth://imu", "--duration", "1", "-o", "{tmp}"], "is a directory"),
    (["record", "-d", "synth://imu", "--duration", "1", "-o", "{tmp}/no/such/dir/x.mcap"], "cannot create"),
    (["record", "-d", "synth://imu", "--duration", "1", "-o", "{tmp}/x.mcap", "--max-loss", "0"], "max_loss_s"),
    (["replay", "{tmp}/none.mcap"], "no such file"),
    (["replay", "{tmp}/text.mcap", "--fast"], "not a session file"),
    (["replay", "{tmp}", "--fast"], "is a directory"),
    (["replay", "{tmp}/text.mcap", "--speed", "0"], "--speed: '0' must be within (0,"),
    (["info", "{tmp}/none.mcap"], "no such file"),
    (["info", "{tmp}/text.mcap"], "not a session file"),
    (["export", "{tmp}/none.mcap", "--format", "csv", "-o", "{tmp}/e"], "no such file"),
    (["export", "{tmp}/text.mcap", "--format", "csv", "-o", "{tmp}/e"], "not a session file"),
])
def test_bad_input_is_one_clear_line(tmp_path, capsys, argv, match):
    (tmp_path / "text.mcap").write_text("this is not a session\n")
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    code, _out, err = run(capsys, *argv)
    assert code == 2
    lines = [ln for ln in err.splitlines() if ln.startswith("perfcap: error:")]
    assert len(lines) == 1 and match in lines[0], err


@pytest.mark.parametrize("argv,match", [
    (["record", "-d", "synth://imu"], "required: -o"),
    (["export", "x.mcap", "--format", "xml", "-o", "d"], "invalid choice: 'xml'"),
    (["replay", "x.mcap", "--speed", "fast"], "--speed: 'fast' is not NUMBER (finite)"),
    (["replay", "x.mcap", "--speed", "2", "--fast"], "not allowed with"),
    (["frobnicate"], "invalid choice"),
])
def test_usage_errors(capsys, argv, match):
    with pytest.raises(SystemExit) as ei:
        main(argv)
    err = capsys.readouterr().err
    assert ei.value.code == 2 and match in err and "Traceback" not in err


def test_existing_output_is_refused(take, capsys):
    code, _, err = run(capsys, "record", "-q", "-d", f"synth://imu?{FAST}", "-o", take)
    assert code == 2 and "already exists (use --overwrite" in err
    code, _, err = run(capsys, "record", "-q", "-d", f"synth://imu?{FAST}", "-o", take, "--overwrite")
    assert code == 0


def test_record_from_config_file(tmp_path, capsys):
    cfg = tmp_path / "rig.toml"
    cfg.write_text(f'[[devices]]\nname = "w"\nurl = "synth://imu?{FAST}"\n[recorder]\nfsync = false\n')
    out = str(tmp_path / "c.mcap")
    code, o, err = run(capsys, "record", "-q", "--config", str(cfg), "-o", out, "--json")
    assert code == 0, err
    assert json.loads(o)["streams"]["w/imu"]["samples"] == 400  # 200 Hz for 2 s


def test_failed_device_is_reported_with_nonzero_exit(tmp_path, capsys):
    out = str(tmp_path / "f.mcap")
    code, _, err = run(capsys, "record", "-q", "-d", f"replay://{tmp_path}/gone.mcap", "-o", out)
    assert code == 2 and "no such file" in err


def test_a_device_that_never_opens_is_reported_and_fails_the_take(capsys, tmp_path):
    """An absent controller: the reason is logged while perfcap waits for it, and the take ends
    with an error naming the device and the reason (not an empty recording and exit 0)."""
    out = str(tmp_path / "t.mcap")
    code = main(["record", "-d", "pad=simhid://dualsense?handshake=silent&init_timeout=0.2", "-o", out,
                 "--duration", "1"])
    err = capsys.readouterr().err
    assert code == 1
    assert "device pad was never opened during the take" in err and "calibration feature report" in err
