"""``perfcap serve`` as a user runs it: a subprocess that prints how to pair and stops on its own,
stops on SIGTERM with everything a phone sent recorded, records from its first sample with
``--record``, and refuses bad flags with one line and bad phone options at start."""

from __future__ import annotations

import hashlib
import json
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from serve_helpers import DEADLINE_S, TOKEN

from capture.app.serve.config import ServeConfig
from capture.app.serve.security import TOKEN_FILE
from capture.app.serve.service import Service
from capture.app.serve.tls import CERT_FILE
from capture.errors import ConfigError
from capture.session import SessionReader

ROOT = Path(__file__).resolve().parents[2]
SERVE = [sys.executable, "-m", "capture.app.cli", "serve", "--port", "0", "--control-port", "0", "--no-mdns"]


def _env(tmp_path: Path) -> dict[str, str]:
    """The user's environment without perfcap settings, with data and config dirs under ``tmp_path``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PERFCAP_")}
    env.update(XDG_DATA_HOME=str(tmp_path / "xdg-data"), XDG_CONFIG_HOME=str(tmp_path / "xdg-config"))
    return env


def _cert_fingerprint(state: Path) -> str:
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding

    der = x509.load_pem_x509_certificate((state / CERT_FILE).read_bytes()).public_bytes(Encoding.DER)
    return hashlib.sha256(der).hexdigest().upper()


def _field(text: str, label: str) -> str:
    m = re.search(rf"^\s*{re.escape(label)}\s+(\S+)", text, re.MULTILINE)
    assert m, f"no {label!r} line in:\n{text}"
    return m.group(1)


def test_serve_prints_pairing_details_and_stops_after_duration(tmp_path):
    state = tmp_path / "state"
    t0 = time.monotonic()
    p = subprocess.run([*SERVE, "--state-dir", str(state), "--duration", "3"], cwd=ROOT, env=_env(tmp_path),
                       capture_output=True, text=True, timeout=300, check=False)
    elapsed = time.monotonic() - t0
    assert p.returncode == 0, p.stderr  # it stopped on its own (the subprocess timeout is only a deadline)
    assert "Traceback" not in p.stderr
    assert elapsed >= 3.0  # not before --duration
    token = (state / TOKEN_FILE).read_text().strip()
    page = _field(p.stdout, "phone page")
    m = re.fullmatch(r"https://([^/:]+):(\d+)/", page)
    assert m and int(m.group(2)) > 0, page
    assert _field(p.stdout, "pairing link") == f"{page}#t={token}"
    assert _field(p.stdout, "pairing token") == token
    assert _field(p.stdout, "TLS certificate SHA-256").replace(":", "") == _cert_fingerprint(state)
    sl_url = f"https://{m.group(1)}:{m.group(2)}/ingest/sensorlogger?token={token}"
    assert _field(p.stdout, "Sensor Logger   push URL") == sl_url
    assert re.fullmatch(r"http://127\.0\.0\.1:\d+/api", _field(p.stdout, "control API"))
    assert re.search(r"^\s*mDNS\s+off", p.stdout, re.MULTILINE)


def _lines(stream, q: queue.Queue) -> None:
    for line in stream:
        q.put(line)
    q.put(None)


def _ready_banner(q: queue.Queue, timeout: float = DEADLINE_S) -> str:
    """stdout up to the line that says the service is ready."""
    text = ""
    end = time.monotonic() + timeout
    while "Ctrl-C stops" not in text:
        line = q.get(timeout=max(0.1, end - time.monotonic()))
        assert line is not None, f"perfcap serve ended before it was ready:\n{text}"
        text += line
    return text


def test_sigterm_while_a_phone_streams_keeps_everything_it_sent(tmp_path, sim_phone, wait_until):
    state, session = tmp_path / "state", tmp_path / "take.mcap"
    cmd = [*SERVE, "--host", "127.0.0.1", "--state-dir", str(state), "--record", str(session),
           "--status-every", "0"]
    with subprocess.Popen(cmd, cwd=ROOT, env=_env(tmp_path), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          text=True) as proc:
        try:
            q: queue.Queue = queue.Queue()
            threading.Thread(target=_lines, args=(proc.stdout, q), daemon=True).start()
            banner = _ready_banner(q)
            assert _field(banner, "recording to") == str(session)
            page, token = _field(banner, "phone page"), _field(banner, "pairing token")
            fp = _field(banner, "TLS certificate SHA-256")
            url = page.replace("https://", "wss://") + "ws/phone"
            phone = sim_phone(url, token, "cli-phone", duration_s=30.0, fingerprint=fp).phone
            wait_until(lambda: phone.sent >= 25, DEADLINE_S, "the phone streaming")
            sent_before = phone.sent  # every one of these must be in the session
            proc.send_signal(signal.SIGTERM)
            rc = proc.wait(timeout=DEADLINE_S)
            err = proc.stderr.read()
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert rc == 0, err
    assert "SIGTERM received, stopping and flushing" in err and "Traceback" not in err
    r = SessionReader(str(session))
    assert r.truncated is None and r.summary is not None
    name = phone.device
    assert name == "phone-cliphone" and list(r.devices) == [name]
    seqs = [json.loads(c.data)["seq"] for c in r.raw_chunks(name) if json.loads(c.data).get("type") == "data"]
    assert seqs == list(range(len(seqs))) and len(seqs) >= sent_before, (len(seqs), sent_before)
    motion = np.array([row for m in phone.messages[:len(seqs)] for row in m.frame.motion])
    imu = r.samples(f"{name}/imu")
    assert len(imu) == len(motion)
    np.testing.assert_array_equal(imu.values[:, :3], motion[:, 4:7])


#: case -> (flags, a regex the one error line must match: it names what is wrong)
BAD_FLAGS = {
    "OSC without allow-list": (["--osc-port", "9000"], r"--osc-allow"),
    "HyperIMU without allow-list": (["--hyperimu-port", "9001"], r"--hyperimu-allow"),
    "HyperIMU TCP without allow-list": (["--hyperimu-tcp-port", "9002"], r"--hyperimu-allow"),
    "bad allow-list entry": (["--osc-port", "9000", "--osc-allow", "phone.local"], r"'phone\.local'"),
    "port out of range": (["--port", "70000"], r"port.*70000"),
    "control port out of range": (["--control-port", "-5"], r"control.port.*-5"),
    "rate not positive": (["--max-rate", "0"], r"max.rate"),
    "bad phone name": (["--phone-name", "pocket"], r"'pocket'.*PROTOCOL/ID=NAME"),
    "bad duration": (["--duration", "-1"], r"--duration"),
}


def test_bad_flag_values_give_one_line_and_exit_2(tmp_path):
    results = {}
    procs = {}
    try:
        for case, (flags, _) in BAD_FLAGS.items():
            state = tmp_path / re.sub(r"\W", "_", case)
            cmd = [*SERVE, "--state-dir", str(state), *flags]
            procs[case] = (state, subprocess.Popen(cmd, cwd=ROOT, env=_env(tmp_path), stdout=subprocess.PIPE,
                                                   stderr=subprocess.PIPE, text=True))
        for case, (state, proc) in procs.items():
            out, err = proc.communicate(timeout=60)
            results[case] = (proc.returncode, out, err, state.exists())
    finally:
        for _, proc in procs.values():
            if proc.poll() is None:
                proc.kill()
            proc.communicate()
    for case, (rc, out, err, made_state) in results.items():
        lines = err.splitlines()
        assert rc == 2, (case, rc, err)
        assert len(lines) == 1 and lines[0].startswith("perfcap: error: "), (case, err)
        assert re.search(BAD_FLAGS[case][1], lines[0]), (case, lines[0])
        assert out == "", (case, out)
        assert not made_state, f"{case}: the state directory was made before the refusal"


def test_a_malformed_flag_is_one_line_naming_the_flag(tmp_path):
    p = subprocess.run([*SERVE, "--state-dir", str(tmp_path / "st"), "--port", "eighty"], cwd=ROOT,
                       env=_env(tmp_path), capture_output=True, text=True, timeout=60, check=False)
    assert p.returncode == 2 and "Traceback" not in p.stderr and p.stdout == ""
    expected = r"perfcap: error: command line: --port = 'eighty' must be an integer"
    assert re.fullmatch(expected, p.stderr.strip()), p.stderr
    assert not (tmp_path / "st").exists()


def test_bad_phone_options_are_an_error_at_start(tmp_path):
    with pytest.raises(ConfigError, match="osc"):
        Service(ServeConfig(host="127.0.0.1", port=0, control_port=-1, mdns=False, state_dir=str(tmp_path),
                            token=TOKEN, osc_port=9, osc_allow="127.0.0.1", osc_map="zigsimm"))
    with pytest.raises(ConfigError, match="hyperimu"):
        Service(ServeConfig(host="127.0.0.1", port=0, control_port=-1, mdns=False, state_dir=str(tmp_path),
                            token=TOKEN, hyperimu_port=9, hyperimu_allow="127.0.0.1", hyperimu_sensors="accel"))
    with pytest.raises(ConfigError, match="already names"):
        Service(ServeConfig(host="127.0.0.1", port=0, control_port=-1, mdns=False, state_dir=str(tmp_path),
                            token=TOKEN, names={"page/x": "wrist"}), ["wrist=synth://imu?realtime=false"])


def test_serve_record_has_the_first_samples(tmp_path):
    out = tmp_path / "take.mcap"
    p = subprocess.run([sys.executable, "-m", "capture.app.cli", "serve", "--port", "0", "--control-port", "-1",
                        "--no-mdns", "--state-dir", str(tmp_path / "st"), "--duration", "1.5", "-q",
                        "--record", str(out), "-d", "imu=synth://imu?rate=100&seed=3&realtime=false&duration=1"],
                       capture_output=True, text=True, timeout=300, check=False, cwd=Path(__file__).parent)
    assert p.returncode == 0, p.stderr
    # the device sends its 100 readings as soon as it is read: a recorder attached late would miss them
    b = SessionReader(str(out)).samples("imu/imu")
    assert b.seq.tolist() == list(range(100))
