"""Every bad input is one clear line and exit 2: the issue's cases one by one, and a seeded sample of the
sweep over every flag of every command, config files and ``PERFCAP_*`` variables (``bad_input_sweep``;
the whole campaign: ``.venv/bin/python tests/cli/bad_input_sweep.py``)."""

from __future__ import annotations

import math
import os

import pytest
from bad_input_sweep import UNDECODABLE, Case, Workspace, all_cases, run_case, sample
from cli_helpers import one_line, run

from capture.app.config import load_config
from capture.app.schema import parse_value, setting_fields
from capture.errors import ConfigError
from devices.options import BadValueError, Option

FAST = "synth://imu?realtime=false&duration=0.2"
#: cases of the CI sample (the campaign runs them all, about 3,700)
CI_CASES = 100


def _error(err: str) -> str:
    line = one_line(err)
    assert line.startswith("perfcap: error: "), err
    return line


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Workspace:
    return Workspace(tmp_path_factory.mktemp("sweep"))


# -- the cases ----------------------------------------------------------------------------
@pytest.mark.parametrize("text", ["a = " + "[" * 5000 + "]" * 5000, "a = " + "{b = " * 3000 + "1" + "}" * 3000,
                                  "[bus]\n" + ".".join(["k"] * 20000) + " = 1"])
def test_deeply_nested_toml_is_one_line(tmp_path, capsys, text):
    cfg = tmp_path / "deep.toml"
    cfg.write_text(text + "\n")
    code, _, err = run(capsys, "record", "-q", "-d", FAST, "-o", str(tmp_path / "x.mcap"), "--config", str(cfg))
    assert code == 2 and str(cfg) in _error(err)
    assert not (tmp_path / "x.mcap").exists()


def test_undecodable_file_names_are_refused(tmp_path, capsys):
    out = os.path.join(str(tmp_path), UNDECODABLE)
    code, _, err = run(capsys, "record", "-q", "-d", FAST, "-o", out)
    assert code == 2 and "not UTF-8" in _error(err) and "\\xff" in err
    assert os.listdir(tmp_path) == []
    code, _, err = run(capsys, "info", out)
    assert code == 2 and "not UTF-8" in _error(err)


def test_export_into_proc_is_one_line(tmp_path, capsys):
    session = str(tmp_path / "s.mcap")
    assert run(capsys, "record", "-q", "-d", FAST, "-o", session)[0] == 0
    for folder in ("/proc/x", "/proc/self/status", "/proc/self/fd/0/x"):
        code, _, err = run(capsys, "export", session, "--format", "csv", "-o", folder)
        assert code == 2 and folder in _error(err)


@pytest.mark.parametrize("flag,value", [("--rate", "nan"), ("--rate", "inf"), ("--rate", "0"), ("--garbage", "2"),
                                        ("--duration", "-1"), ("--burst-bytes", "0"), ("--seed", "-1"),
                                        ("--heading", "nan"), ("--gyro-bias", "nan,0,0")])
def test_sim_serial_refuses_bad_numbers(capsys, flag, value):
    code, _, err = run(capsys, "sim", "serial", flag, value, "--duration" if flag != "--duration" else "--loop",
                       *(["0.05"] if flag != "--duration" else []))
    assert code == 2 and flag in _error(err)


def test_sim_serial_never_takes_the_place_of_a_file(tmp_path, capsys):
    """``--link`` names the simulator's own symlink: an existing file, folder, FIFO, device or another link
    (a udev ``/dev/serial/by-id`` name) is left alone; only an earlier run's link to a pty is taken over."""
    keep = tmp_path / "keep.txt"
    keep.write_text("mine")
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    other_link = tmp_path / "by-id"
    other_link.symlink_to(keep)
    for path in (keep, tmp_path, fifo, "/dev/zero", other_link):
        code, _, err = run(capsys, "sim", "serial", "--link", str(path), "--duration", "0.05")
        assert code == 2 and "is not an earlier simulated port" in _error(err)
    assert keep.read_text() == "mine" and fifo.exists() and os.path.exists("/dev/zero")
    assert os.readlink(other_link) == str(keep)
    stale = tmp_path / "ttySIM0"
    stale.symlink_to("/dev/pts/999")  # what a killed simulator leaves behind
    code, _, err = run(capsys, "sim", "serial", "--link", str(stale), "--duration", "0.05")
    assert code == 0, err


@pytest.mark.parametrize("argv,match", [
    (["--sessions-dir", "{tmp}/none"], "sessions_dir {tmp}/none"),
    (["--state-dir", "/proc/self/status"], "is not a folder"),
    (["--status-every", "-1"], "--status-every: '-1' must be within [0,"),
    (["--status-every", "nan"], "--status-every: 'nan' is not NUMBER"),
    (["--duration", "inf"], "--duration: 'inf' is not NUMBER"),
    (["--host", "a" * 70], "--host"),
    (["--phone-name", "page/abc=bad/name"], "the name must start with a letter"),
    (["--phone-name", "pager/abc=pocket"], "unknown protocol 'pager'"),
    (["--phone-name", "page/a=pocket", "--phone-name", "page/b=pocket"], "that name is named twice"),
    (["--phone-name", "page/=pocket"], "expected PROTOCOL/ID=NAME"),
])
def test_serve_refuses_bad_settings(tmp_path, capsys, argv, match):
    code, _, err = run(capsys, "serve", "-q", "--port", "0", "--control-port", "-1", "--no-mdns", "--no-tls",
                       "--state-dir", str(tmp_path / "state"), "--duration", "0.05",
                       *(a.replace("{tmp}", str(tmp_path)) for a in argv))
    assert code == 2 and match.replace("{tmp}", str(tmp_path)) in _error(err)


@pytest.mark.parametrize("var,match", [
    ("PERFCAP_RECORDR_MAX_LOSS_S", "did you mean PERFCAP_RECORDER_MAX_LOSS_S?"),
    ("PERFCAP_RECORDER_MAXLOSS_S", "did you mean PERFCAP_RECORDER_MAX_LOSS_S?"),
    ("PERFCAP_BUS_SIZE", "[bus] takes: live_queue"),
    ("PERFCAP_FOO", "PERFCAP_<SECTION>_<KEY>"),
])
def test_unknown_perfcap_variables_are_errors(tmp_path, capsys, monkeypatch, var, match):
    monkeypatch.setenv(var, "0.5")
    code, _, err = run(capsys, "record", "-q", "-d", FAST, "-o", str(tmp_path / "x.mcap"))
    assert code == 2 and var in _error(err) and match in err
    assert not (tmp_path / "x.mcap").exists()


def test_the_simulators_variable_is_known():
    assert load_config(env={"PERFCAP_SIM_TOKEN": "t"}).recorder.max_loss_s == 1.0


def test_undecodable_variable_is_refused():
    with pytest.raises(ConfigError, match="PERFCAP_CALIBRATION_DIR is not UTF-8"):
        load_config(env={"PERFCAP_CALIBRATION_DIR": UNDECODABLE})


def test_fifos_and_devices_are_refused_not_waited_on(tmp_path, capsys):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    for argv in (["info", str(fifo)], ["replay", str(fifo), "--fast"], ["info", "/dev/zero"],
                 ["record", "-q", "-d", FAST, "-o", str(fifo)], ["record", "-q", "-d", FAST, "-o", "x.mcap",
                                                                "--config", str(fifo)],
                 ["export", str(fifo), "--format", "csv", "-o", str(tmp_path / "e")],
                 ["puppet", "--input", "/dev/zero"], ["cycle", str(fifo)]):
        code, _, err = run(capsys, *argv)
        assert code == 2 and ("FIFO" in _error(err) or "device" in err), (argv, err)
        assert "not valid TOML" not in err


def test_usage_errors_are_one_line(capsys):
    code, _, err = run(capsys, "record", "-d", FAST)
    assert code == 2 and "the following arguments are required: -o" in _error(err)
    assert "(see perfcap record --help)" in err


def test_a_huge_config_file_is_refused_unread(tmp_path, capsys):
    cfg = tmp_path / "big.toml"
    cfg.write_text("# " + "x" * (2 << 20) + "\n")
    code, _, err = run(capsys, "record", "-q", "-d", FAST, "-o", str(tmp_path / "x.mcap"), "--config", str(cfg))
    assert code == 2 and "larger than 1 MiB" in _error(err)


# -- one parser: non-finite numbers refused wherever options and settings are parsed -----------------------
@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "1e999", float("nan"), float("inf"), math.inf * -1])
def test_non_finite_numbers_are_refused_by_the_one_parser(value):
    with pytest.raises(BadValueError):
        Option(float, 1.0, "x").parse(value)
    with pytest.raises(BadValueError):
        Option(int, 1, "x").parse(value)
    from capture.app.config import SECTIONS

    for cls in SECTIONS.values():
        for f, opt in setting_fields(cls):
            if opt.type in (int, float):
                with pytest.raises(ConfigError, match=f.name):
                    parse_value(opt, f.name, value, "test", from_text=isinstance(value, str))


@pytest.mark.parametrize("value", ["a\x00b", UNDECODABLE])
def test_text_with_nul_or_undecodable_bytes_is_refused(value):
    with pytest.raises(BadValueError) as ei:
        Option(str, "", "x").parse(value)
    assert ei.value.problem == "text"


def test_messages_stay_short_whatever_the_value(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[[devices]]\nurl = 'synth://imu'\noptions = { rate = " + "[" * 900 + "]" * 900 + " }\n")
    with pytest.raises(ConfigError) as ei:
        load_config(cfg, env={})
    assert len(str(ei.value)) < 400


# -- the class: every flag, config key and variable with hostile values ---------------------------------
def test_every_flag_of_every_command_is_walked():
    """The sweep reaches every flag of every command (so a new flag is swept too)."""
    from capture.app.cli import build_parser

    labels = {c.what for c in all_cases(include_slow=True)}
    sub = build_parser()._subparsers._group_actions[0].choices   # the commands' parsers
    for name, parser in sub.items():
        if name == "sim":
            continue
        for a in parser._actions:
            if a.option_strings and a.option_strings[-1] not in ("--help",):
                assert any(w.startswith(f"{name} {a.option_strings[-1]}") for w in labels), (name, a.option_strings)


def test_seeded_sample_of_the_sweep(workspace: Workspace):
    """A seeded sample of the campaign: each run exits 0, 1 or 2, never 70, never a traceback; an exit 2 is
    one 'perfcap: error:' line and leaves no file."""
    cases = sample(all_cases(), CI_CASES, seed=16)
    failures = []
    for c in cases:
        r = run_case(workspace, c, interrupt_after_s=10.0)
        if r.problems:
            failures.append(f"{c.what}: {'; '.join(r.problems)}: {r.err.strip()[-300:]}")
    assert not failures, "\n".join(failures)


def test_a_case_of_the_sweep_is_checked(workspace: Workspace):
    """The harness itself: a refused value is seen as one line and exit 2."""
    r = run_case(workspace, Case("nan duration", ("record", "-q", "-d", FAST, "--duration", "nan", "-o", "{out}/x")))
    assert r.code == 2 and not r.problems, r
