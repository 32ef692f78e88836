"""``perfcap puppet``: a scripted trajectory CSV, a recorded phone session or a live device (a recorded
phone replayed through its codec) in; a BVH that reads back, the state timeline JSON, VMC bundles caught by
a real UDP receiver, and a summary out. Bad input is one line and exit 2, never a traceback. And the demo's
puppet step, on a recorded simulated page phone."""

from __future__ import annotations

import json
import math
import os
import socket
import threading
import time
from typing import TYPE_CHECKING

import numpy as np
import pytest
from cli_helpers import one_line, run
from wait_helpers import DEADLINE_S

from capture.app.demo import demo_puppet
from capture.app.orchestrator import Capture
from capture.session import SessionReader
from retarget.bvh import read_bvh
from retarget.skeleton import humanoid
from retarget.vmc import decode_frame

if TYPE_CHECKING:
    from pathlib import Path

HEADER = "t,px,py,pz,qw,qx,qy,qz,touch"


def walk_csv(path: Path, fs: float = 50.0) -> str:
    """Released 0.5 s, held still 0.5 s, walking forward at 1.2 m/s for 3 s, released at 5 s, 6 s in all."""
    rows = [HEADER]
    for i in range(int(6 * fs) + 1):
        t = i / fs
        z = 0.0 if t < 1.0 else 1.2 * (min(t, 4.0) - 1.0)
        rows.append(f"{t:.4f},0,1.3,{z:.5f},1,0,0,0,{1 if 0.5 <= t < 5.0 else 0}")
    path.write_text("\n".join(rows) + "\n")
    return str(path)


@pytest.fixture(scope="module")
def touched(tmp_path_factory, record_phone_session) -> str:
    return str(record_phone_session(tmp_path_factory.mktemp("s") / "touched.mcap", touch=(1.0, 2.0)))


@pytest.fixture(scope="module")
def untouched(tmp_path_factory, record_phone_session) -> str:
    return str(record_phone_session(tmp_path_factory.mktemp("s") / "demo.mcap", duration_s=2.0))


# -- trajectory -----------------------------------------------------------------------------------
def test_trajectory_to_bvh_and_timeline(tmp_path, capsys):
    csv_path = walk_csv(tmp_path / "walk.csv")
    bvh, tl = tmp_path / "walk.bvh", tmp_path / "walk.json"
    code, out, err = run(capsys, "puppet", "--input", csv_path, "-o", str(bvh), "--timeline", str(tl))
    assert code == 0, err
    assert out.splitlines()[0] == f"puppet: 361 frames at 60 Hz (6.00 s) from {csv_path}"
    assert "states: RELEASED 1.50 s, LOCOMOTION 4.50 s (2 change(s))" in out
    assert f"BVH written to {bvh} (361 frames at 60 fps, 30 joints)" in out
    skeleton, clip = read_bvh(bvh)
    assert clip.n_frames == 361 and skeleton.n_joints == humanoid().n_joints == 30
    assert clip.fps == pytest.approx(60.0)
    assert skeleton.names == humanoid().names
    # the character walked forward about as far as the phone moved (3.6 m)
    assert clip.root_pos[300, 2] - clip.root_pos[60, 2] == pytest.approx(3.6, abs=0.2)
    timeline = json.loads(tl.read_text())
    assert [e["state"] for e in timeline] == ["RELEASED", "LOCOMOTION", "RELEASED"]
    assert [e["t"] for e in timeline] == pytest.approx([0.0, 0.5, 5.0], abs=1 / 60 + 1e-9)
    assert all(set(e) == {"t", "state"} for e in timeline)


def test_rate_sets_the_frames_and_the_bvh_fps(tmp_path, capsys):
    csv_path = walk_csv(tmp_path / "walk.csv")
    bvh = tmp_path / "walk30.bvh"
    code, _out, err = run(capsys, "puppet", "--input", csv_path, "-o", str(bvh), "--rate", "30")
    assert code == 0, err
    _, clip = read_bvh(bvh)
    assert clip.n_frames == 181 and clip.fps == pytest.approx(30.0)


@pytest.mark.parametrize("fast", [False, True])
def test_vmc_to_a_real_udp_receiver(tmp_path, capsys, fast):
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.05)
    got: list[bytes] = []
    arrived: list[float] = []
    done = threading.Event()

    def receive() -> None:
        while not done.is_set():
            try:
                got.append(sock.recv(65536))
                arrived.append(time.monotonic())
            except TimeoutError:
                continue

    th = threading.Thread(target=receive, daemon=True)
    th.start()
    try:
        port = sock.getsockname()[1]
        code, out, err = run(capsys, "puppet", "--input", walk_csv(tmp_path / "walk.csv"), "--rate", "30",
                             "--vmc", f"127.0.0.1:{port}", *(["--fast"] if fast else []))
        deadline = time.monotonic() + DEADLINE_S  # the command said how many it sent: wait for those
        while len(got) < 181 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        done.set()
        th.join()
        sock.close()
    assert code == 0, err
    assert f"VMC: 181 bundle(s) sent to 127.0.0.1:{port} over UDP" in out
    frames = [decode_frame(d) for d in got]
    assert len(frames) == 181
    sk = humanoid()
    names = [sk.unity_names[n] for n in sk.names if n in sk.unity_names]
    assert all(list(f.bones) == names and f.ok == 1 for f in frames)
    assert [f.t for f in frames] == pytest.approx(np.arange(181) / 30.0, abs=1e-5)
    if not fast:  # paced as a player sends them: 6 s of frames take at least 6 s (however busy the machine)
        assert arrived[-1] - arrived[0] >= 6.0 - 0.05


def test_vmc_that_cannot_send_is_counted_and_reported_once(tmp_path, capsys):
    code, out, err = run(capsys, "puppet", "--input", walk_csv(tmp_path / "walk.csv", fs=10.0), "--rate", "10",
                         "--vmc", "255.255.255.255:39539", "--fast")
    assert code == 1
    assert "VMC: 0 bundle(s) sent to 255.255.255.255:39539 over UDP, 61 send error(s) (first: " in out
    assert one_line(err).startswith("perfcap: error: no VMC bundle could be sent to 255.255.255.255:39539")


# -- sessions and live ------------------------------------------------------------------------------
def test_session_with_touches(touched, tmp_path, capsys):
    bvh, tl = tmp_path / "s.bvh", tmp_path / "s.json"
    code, out, err = run(capsys, "puppet", "--session", touched, "-o", str(bvh), "--timeline", str(tl))
    assert code == 0, err
    first = out.splitlines()[0]
    assert first.startswith("puppet: ") and first.endswith(f"from {touched} phone/attitude")
    n = int(first.split()[1])
    assert n == math.floor(float(first.split("(")[1].split(" s)")[0]) * 60 + 0.5) + 1
    assert "note: orientation from phone/attitude (euler), no position: the phone is held at a fixed pivot" in out
    _, clip = read_bvh(bvh)
    assert clip.n_frames == n
    timeline = json.loads(tl.read_text())
    assert timeline[:2] == [{"t": 0.0, "state": "RELEASED"}, {"t": pytest.approx(1.0, abs=0.03), "state": "LOCOMOTION"}]


def test_session_without_touches_is_held_throughout(untouched, capsys):
    code, out, err = run(capsys, "puppet", "--session", untouched, "--device", "phone")
    assert code == 0, err
    assert "note: no touches recorded (phone/touch is empty): the phone counts as held throughout" in out
    assert "states: LOCOMOTION" in out     # grabbed from the first frame


def test_live_phone_replayed_matches_the_session(touched, tmp_path, capsys):
    tl_live, tl_session = tmp_path / "live.json", tmp_path / "session.json"
    code, out, err = run(capsys, "puppet", "--phone", f"replay://{touched}?device=phone&speed=0", "-q",
                         "--timeline", str(tl_live), "-o", str(tmp_path / "live.bvh"))
    assert code == 0, err
    assert "note: the puppet is grabbed while the screen of phone is touched" in out
    assert "following phone/attitude of phone" in err
    code, out2, err = run(capsys, "puppet", "--session", touched, "--timeline", str(tl_session))
    assert code == 0, err
    assert out.splitlines()[0].split(" from ")[0] == out2.splitlines()[0].split(" from ")[0]   # frames, duration
    live, recorded = json.loads(tl_live.read_text()), json.loads(tl_session.read_text())
    assert [e["state"] for e in live] == [e["state"] for e in recorded]
    assert [e["t"] for e in live] == pytest.approx([e["t"] for e in recorded], abs=1e-3)


def test_live_device_without_attitude(capsys):
    code, _, err = run(capsys, "puppet", "--phone", "wrist=synth://imu?realtime=false&duration=0.2")
    assert code == 2
    assert one_line(err) == ("perfcap: error: device wrist has no attitude stream (wrist/attitude) to drive the"
                             " puppet; its streams: wrist/imu, wrist/euler, wrist/mag, wrist/quat")


# -- bad input ----------------------------------------------------------------------------------------
@pytest.mark.parametrize(("content", "message"), [
    ("t,px,py,pz,qw,qx,qy,qz\n0,0,1,0,1,0,0,0\n", ("line 1: the columns are t,px,py,pz,qw,qx,qy,qz; expected "
                                                   "t,px,py,pz,qw,qx,qy,qz,touch")),
    (f"{HEADER}\n0,0,1,0,1,0,0,0,0\n0.1,0,1,0,1,0,zero,0,0\n", "line 3, column qy: 'zero' is not a number"),
    (f"{HEADER}\n0,0,1,0,1,0,0,0,0\n0.1,0,1,0,1,0,0,0\n", "line 3: 8 fields where the header has 9"),
    (f"{HEADER}\n0,0,1,0,0,0,0,0,0\n", "line 2: the quaternion (qw,qx,qy,qz) is zero"),
    (f"{HEADER}\n0,0,1,0,0.5,0,0,0,0\n", "line 2: the quaternion (qw,qx,qy,qz) has norm 0.5"),
    (f"{HEADER}\n0,0,1,0,1,0,0,0,0\n1,0,1,0,1,0,0,0,0\n0.5,0,1,0,1,0,0,0,0\n", "line 4: time 0.5 s does not increase"),
])
def test_malformed_trajectories(tmp_path, capsys, content, message):
    p = tmp_path / "bad.csv"
    p.write_text(content)
    code, out, err = run(capsys, "puppet", "--input", str(p), "-o", str(tmp_path / "x.bvh"))
    assert code == 2 and out == ""
    assert one_line(err).startswith(f"perfcap: error: {p} {message}")
    assert not (tmp_path / "x.bvh").exists()


@pytest.mark.parametrize(("argv", "message"), [
    (["--input", "{tmp}/missing.csv"], "{tmp}/missing.csv: no such file"),
    (["--session", "{tmp}/missing.mcap"], "{tmp}/missing.mcap: no such file"),
    (["--session", "{walk}"], "is not a session file (not MCAP)"),
    (["--input", "{walk}", "--vmc", "localhost"], "--vmc expects HOST:PORT (e.g. 127.0.0.1:39539), not 'localhost'"),
    (["--input", "{walk}", "--vmc", "127.0.0.1:99999"], "--vmc expects HOST:PORT"),
    (["--input", "{walk}", "--vmc", "localhost:\u00b2"],
     "--vmc expects HOST:PORT (e.g. 127.0.0.1:39539), not 'localhost:\u00b2'"),
    (["--input", "{walk}", "--vmc", "localhost:\u0663\u0663"], "--vmc expects HOST:PORT"),
    (["--input", "{walk}", "--vmc", "no-such-host.invalid:9"], "--vmc no-such-host.invalid:9: cannot resolve"),
    (["--input", "{walk}", "--rate", "0"], "--rate must be a frame rate in Hz between 0 and 1000, not 0.0"),
    (["--input", "{walk}", "--rate", "nan"], "--rate must be a frame rate"),
    (["--input", "{walk}", "-o", "{tmp}/no/such/dir/x.bvh"], "the folder {tmp}/no/such/dir does not exist"),
    (["--input", "{walk}", "--timeline", "{tmp}"], "--timeline {tmp} is a directory"),
    (["--input", "{walk}", "--duration", "3"], "--duration is for --phone"),
    (["--input", "{walk}", "--foxglove"], "--foxglove is for --phone"),
    (["--phone", "synth://imu", "--foxglove=70000"], "--foxglove=70000: a port is 0"),
    (["--input", "{walk}", "--device", "phone"], "--device chooses the phone of a --session"),
    (["--input", "{walk}", "--fast"], "--fast is for --vmc from an --input or a --session"),
    (["--session", "{untouched}", "--device", "pen"], ("has no attitude stream of a device 'pen'; phones with one:"
                                                      " phone")),
    (["--phone", "nonsense"], "nonsense"),
    (["--input", "{walk}", "--session", "{untouched}"], "not allowed with argument"),
    ([], "one of the arguments --phone --input --session is required"),
])
def test_bad_arguments_are_one_line(tmp_path, capsys, untouched, argv, message):
    walk = walk_csv(tmp_path / "walk.csv", fs=5.0)
    fill = {"tmp": str(tmp_path), "walk": walk, "untouched": untouched}
    code, out, err = run(capsys, "puppet", *[a.format(**fill) for a in argv])
    assert code == 2 and out == ""
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith(("usage:", " "))]
    assert len(lines) == 1, err
    assert lines[0].startswith("perfcap: error: ") and message.format(**fill) in lines[0]


def test_positions_near_the_float_limit_are_one_line(tmp_path, capsys):
    p = tmp_path / "big308.csv"
    p.write_text(f"{HEADER}\n0,0,1.3,0,1,0,0,0,1\n0.1,1.5e308,1.3,0,1,0,0,0,1\n")
    code, out, err = run(capsys, "puppet", "--input", str(p))
    assert code == 2 and out == ""
    assert one_line(err) == (f"perfcap: error: {p} line 3, column px: '1.5e308' m is out of range"
                             " (positions within +-100000 m)")


def test_an_input_the_retargeter_refuses_is_one_line(tmp_path, capsys, monkeypatch):
    from retarget.puppet import PuppetRetargeter

    def refuse(self, inp):
        raise ValueError("position must be a finite 3-vector,\n got array([inf, 1.3, 0.])")

    monkeypatch.setattr(PuppetRetargeter, "step", refuse)
    walk = walk_csv(tmp_path / "walk.csv", fs=5.0)
    code, out, err = run(capsys, "puppet", "--input", walk)
    assert code == 2 and out == ""
    assert one_line(err) == (f"perfcap: error: {walk}: the puppet cannot follow the input at 0 s (position must"
                             " be a finite 3-vector, got array([inf, 1.3, 0.]))")


@pytest.mark.parametrize(("times", "message"), [
    ("0,1e9", "the input spans 1e+09 s, 6e+10 frames at 60 Hz; at most 24 h (5184000 frames) is driven"),
    ("0,1e300", "the input spans 1e+300 s, 6e+301 frames at 60 Hz"),
])
def test_huge_time_spans_are_one_line(tmp_path, capsys, times, message):
    p = tmp_path / "long.csv"
    p.write_text(HEADER + "\n" + "".join(f"{t},0,1.3,0,1,0,0,0,1\n" for t in times.split(",")))
    code, out, err = run(capsys, "puppet", "--input", str(p))
    assert code == 2 and out == ""
    line = one_line(err)
    assert line.startswith(f"perfcap: error: {p}: the input spans ") and message in line


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="needs /proc (a folder nobody can create files in)")
@pytest.mark.parametrize("flag", ["-o", "--timeline"])
def test_an_unwritable_output_is_found_before_the_performance(tmp_path, capsys, flag):
    walk = walk_csv(tmp_path / "walk.csv", fs=5.0)
    other = {"-o": ["--timeline", str(tmp_path / "tl.json")], "--timeline": ["-o", str(tmp_path / "x.bvh")]}[flag]
    code, out, err = run(capsys, "puppet", "--input", walk, flag, "/proc/perfcap-out", *other)
    assert code == 2 and out == ""   # nothing was performed
    assert one_line(err).startswith(f"perfcap: error: {flag} /proc/perfcap-out: cannot write it (")
    assert not (tmp_path / "tl.json").exists() and not (tmp_path / "x.bvh").exists()


def test_a_failed_bvh_still_writes_the_timeline_and_vice_versa(tmp_path, capsys, monkeypatch):
    import retarget.bvh

    walk = walk_csv(tmp_path / "walk.csv", fs=10.0)
    bvh, tl = tmp_path / "walk.bvh", tmp_path / "walk.json"

    def disk_full(path, clip, **kw):
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(retarget.bvh, "write_bvh", disk_full)
        code, out, err = run(capsys, "puppet", "--input", walk, "-o", str(bvh), "--timeline", str(tl))
    assert code == 2
    assert one_line(err) == f"perfcap: error: cannot write {bvh}: No space left on device"
    assert f"timeline written to {tl}" in out and "BVH written" not in out
    assert [e["state"] for e in json.loads(tl.read_text())] == ["RELEASED", "LOCOMOTION", "RELEASED"]

    # the timeline's folder vanishes during the run: the BVH is still written
    import capture.app.puppet_run

    monkeypatch.setattr(capture.app.puppet_run, "probe_writable", lambda path, flag: None)
    gone = tmp_path / "gone"
    gone.mkdir()
    orig_run = capture.app.puppet_run.PuppetRun.step

    def step_and_remove(self, inp):
        if gone.exists():
            gone.rmdir()
        return orig_run(self, inp)

    monkeypatch.setattr(capture.app.puppet_run.PuppetRun, "step", step_and_remove)
    bvh.unlink(missing_ok=True)
    code, out, err = run(capsys, "puppet", "--input", walk, "-o", str(bvh), "--timeline", str(gone / "tl.json"))
    assert code == 2
    assert one_line(err) == f"perfcap: error: cannot write {gone / 'tl.json'}: No such file or directory"
    assert f"BVH written to {bvh}" in out and read_bvh(bvh)[1].n_frames == 361


# -- the demo's step ------------------------------------------------------------------------------------
def test_demo_puppet_writes_puppet_bvh_beside_the_session(untouched):
    line = one_line(demo_puppet(SessionReader(untouched)))
    bvh = os.path.join(os.path.dirname(untouched), "puppet.bvh")
    assert line.startswith("puppet: the phone's attitude (held throughout: the simulated phone sends no touch) drove ")
    assert line.endswith(f"; BVH {bvh}") and "states LOCOMOTION" in line
    n = int(line.split(" drove ")[1].split()[0])
    skeleton, clip = read_bvh(bvh)
    assert clip.n_frames == n > 100 and skeleton.n_joints == 30


def test_demo_puppet_failure_is_one_line(tmp_path):
    path = tmp_path / "imu.mcap"
    Capture(["wrist=synth://imu?rate=100&realtime=false&duration=0.3"], output=str(path)).run(None)
    line = one_line(demo_puppet(SessionReader(str(path))))
    assert line.startswith("puppet: not driven from the phone (ConfigError: ") and "no attitude stream" in line
    assert not (tmp_path / "puppet.bvh").exists()
