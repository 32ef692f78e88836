"""The hardware-free demo behind ``perfcap demo``: simulated devices through the real codecs, clock
sync, bus and recorder, in a ``perfcap serve`` service on loopback; then the session replayed and
checked, the wrist's cycle extracted and the puppet driven from the phone.

Simulated devices are reached only as a user reaches them: by URL scheme (``synth://``, ``simhid://``)
and by ``perfcap sim`` in child processes (a WT901 on a pty, a phone running the built-in page over
TLS). What a simulator knows of the truth (when each reading really happened, its loop durations)
comes through the ``SimulatorTruth`` ability its transport declares, or on the simulated phone's
standard output.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import secrets
import signal
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from capture.clock import MONOTONIC
from capture.errors import CaptureError, ConfigError, CycleError
from devices.transports.base import SimulatorTruth

if TYPE_CHECKING:
    from capture.app.cycle_follow import CycleFollower
    from capture.app.orchestrator import Capture
    from capture.app.serve.service import Service, ServiceThread
    from capture.session import SessionReader
    from cycles import Cycle

log = logging.getLogger(__name__)

#: where the demo's lines go (the CLI prints them)
Say = Callable[[str], None]

DEMO_LOOP_S = 1.2
DEMO_DEVICES = [
    # A WT901 on the wrist over USB: device clock 80 ppm fast, 2 ms of USB arrival jitter. Its wearer
    # repeats one gesture, each loop 1.2 s +- 8 % (the demo extracts the cycle from it).
    ("wrist", f"synth://imu?rate=200&seed=1&drift_ppm=80&jitter_ms=2&truth=true&loop_s={DEMO_LOOP_S}"),
    # One on the ankle through an FTDI adapter: no time packets, 16 ms latency-timer bursts, a little line noise.
    ("ankle", "synth://imu?rate=200&seed=2&device_clock=false&burst_ms=16&garbage=0.005"),
    # One on the head whose clock passes midnight two seconds in (the WT901 clock wraps daily).
    ("head", "synth://imu?rate=100&seed=3&drift_ppm=-40&jitter_ms=1&start_ms=86398000&truth=true"),
    # A DualSense over Bluetooth: the handshake reads its factory calibration; its own clock is 30 ppm
    # fast and Bluetooth adds up to 3 ms of arrival jitter.
    ("pad", "dualsense@simhid://dualsense?bus=bluetooth&seed=5&drift_ppm=30&jitter_ms=3&truth=true"),
    # A pen tablet at 200 Hz, read through its report descriptor.
    ("pen", "hid@simhid://pen?seed=6"),
]
#: the simulated drift of each device's clock, ppm (what the fit should find)
DEMO_DRIFT_PPM = {"wrist": 80.0, "head": -40.0, "pad": 30.0}
DEMO_UNPLUG_EVERY, DEMO_UNPLUG_FOR = 3.0, 0.5
PHONE_ID = "demo-phone"


def _perfcap(*args: str) -> list[str]:
    """The command line of ``perfcap ARGS`` with this interpreter (as installed or not)."""
    return [sys.executable, "-m", "capture.app.cli", *args]


def _stop_child(proc: subprocess.Popen[str], how: str | None = None, timeout: float = 5.0) -> str:
    """Stop a child (``how``: a line for its stdin, else SIGTERM) and return the rest of its output."""
    rest = ""
    try:
        if how is not None and proc.stdin:
            proc.stdin.write(how)
            proc.stdin.close()
        elif proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        rest, _ = proc.communicate(timeout=timeout)
    except (OSError, ValueError, subprocess.TimeoutExpired):
        proc.kill()
        proc.wait()
    finally:
        if proc.stdout:
            proc.stdout.close()
    return rest or ""


@dataclass
class SerialSim:
    """``perfcap sim serial`` in a child process, as a real device is outside perfcap."""

    proc: subprocess.Popen[str]
    port: str

    def stop(self) -> None:
        _stop_child(self.proc, "quit\n")


def start_serial_sim(duration: float, say: Say) -> SerialSim | None:
    """A WT901 served on a pty; None where ptys do not exist (Windows) or it fails to start (said,
    not hidden)."""
    if os.name != "posix":
        say("  (no simulated serial port on this OS: ptys are POSIX only)")
        return None
    link = os.path.join(tempfile.mkdtemp(prefix="perfcap-demo-port-"), "ttyWT901")
    cmd = _perfcap("sim", "serial", "--kind", "witmotion", "--rate", "200", "--seed", "4", "--link", link,
                   "--unplug-every", str(DEMO_UNPLUG_EVERY), "--unplug-for", str(DEMO_UNPLUG_FOR),
                   "--duration", str(duration + 30))
    try:
        proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                text=True)
    except OSError as exc:
        say(f"  (the simulated serial port could not start: {exc}; continuing without it)")
        return None
    line = proc.stdout.readline().strip() if proc.stdout else ""
    if line != link:
        _stop_child(proc, "quit\n")
        say("  (the simulated serial port did not start; continuing without it)")
        return None
    return SerialSim(proc, link)


def start_service(devices: list[str], path: str, overwrite: bool) -> tuple[Service, ServiceThread]:
    """The demo's devices in a ``perfcap serve`` service on loopback, recording from the start."""
    from capture.app.serve.config import ServeConfig
    from capture.app.serve.service import Service, ServiceThread

    cfg = ServeConfig(host="127.0.0.1", port=0, control_port=-1, mdns=False,
                      state_dir=tempfile.mkdtemp(prefix="perfcap-demo-serve-"), token=secrets.token_urlsafe(18),
                      names={f"page/{PHONE_ID}": "phone"})
    service = Service(cfg, devices)
    try:
        # orientation of every IMU, so the session's 3D view (``/tf/...``) shows each sensor turning
        service.capture.enable_orientation("fusion")
        service.capture.start_recording(path, overwrite=overwrite, meta={"command": "perfcap demo"})
    except BaseException:
        service.capture.stop()
        raise
    return service, ServiceThread(service).start()


@dataclass
class PhoneSim:
    """``perfcap sim phone`` in a child process: the built-in page over the service's real TLS WebSocket.
    It says when its page clock started (host monotonic time, shared by every process of the machine),
    so page times map to the host clock, and at the end how many motion events it sent."""

    proc: subprocess.Popen[str]
    t0_host_ns: int
    t0_ms: float
    events: int = 0

    def stop(self) -> None:
        for line in _stop_child(self.proc).splitlines():
            try:
                self.events = int(json.loads(line).get("events", self.events))
            except (ValueError, AttributeError):
                log.debug("simulated phone said %r", line)


#: seconds the demo waits for its simulated phone to pair before it goes on without it
PHONE_START_S = 20.0


def start_phone(service: Service, duration: float, stop: threading.Event) -> PhoneSim | None:
    """The simulated phone, performing the puppeteer's choreography (so the demo's puppet walks, runs,
    hops and crouches), once it has paired; None (with the reason logged) when it does not pair within
    ``PHONE_START_S`` or ``stop`` is set meanwhile."""
    ep = service.endpoints
    url = ep.page_url.replace("https://", "wss://").replace("http://", "ws://") + "ws/phone"
    cmd = _perfcap("sim", "phone", "--url", url, "--id", PHONE_ID, "--rate", "60", "--duration",
                   str(duration + 1.0), "--seed", "7", "--motion", "puppeteer", "--report")
    if ep.fingerprint:
        cmd += ["--fingerprint", ep.fingerprint]
    env = dict(os.environ, PERFCAP_SIM_TOKEN=service.tokens.token)   # not on a command line others can read
    errors = tempfile.TemporaryFile("w+")   # why it did not start, if it does not (a pipe could fill up)
    try:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=errors, text=True,
                                env=env)
    except OSError as exc:
        errors.close()
        log.warning("no simulated phone: %s", exc)
        return None
    first: queue.Queue[str] = queue.Queue()
    out = proc.stdout
    threading.Thread(target=lambda: first.put(out.readline() if out else ""), name="demo-phone-start",
                     daemon=True).start()
    deadline = MONOTONIC.now_ns() + int(PHONE_START_S * 1e9)
    line: str | None = None
    while line is None and not stop.is_set() and MONOTONIC.now_ns() < deadline:
        with contextlib.suppress(queue.Empty):
            line = first.get(timeout=0.1)
    try:
        if line:
            start = json.loads(line)
            errors.close()
            return PhoneSim(proc, int(start["t0_host_ns"]), float(start["t0_ms"]))
    except (ValueError, KeyError, TypeError):
        pass
    _stop_child(proc)
    errors.seek(0)
    said = [ln for ln in errors.read().splitlines() if ln.strip()]
    errors.close()
    why = "stopped" if stop.is_set() else said[-1] if said else f"it did not pair within {PHONE_START_S:g} s"
    log.warning("the demo goes on without its simulated phone (%s)", why)
    return None


def _p99_after_first_second(t_bus_ns: np.ndarray, true_ns: np.ndarray) -> float | None:
    """p99 of |bus time - true time| (ms), leaving out the clock fit's first second."""
    err = np.abs(t_bus_ns - true_ns)
    settled = err[true_ns >= true_ns[0] + 1_000_000_000] if len(true_ns) else err
    return float(np.percentile(settled, 99)) / 1e6 if settled.size else None


def bus_time_accuracy(cap: Capture, reader: SessionReader, phone: PhoneSim | None) -> dict[str, float]:
    """Per device, how close the recorded bus times are to when each reading really happened (p99, ms,
    after the first second), for the devices whose simulator knows."""
    accuracy: dict[str, float] = {}
    for d in cap.devices:
        tr = d.transport
        if isinstance(tr, SimulatorTruth) and tr.truth_ns and f"{d.name}/imu" in reader.streams:
            b = reader.samples(f"{d.name}/imu")
            tt = np.sort(np.asarray(tr.truth_ns, np.int64)) + tr.latency_ns
            # each sample against the true reading time nearest to it (readings are >= 4 ms apart, errors
            # far smaller), so readings a handshake consumed do not shift the pairing
            j = np.clip(np.searchsorted(tt, b.t_bus_ns), 1, len(tt) - 1)
            near = np.where(np.abs(tt[j - 1] - b.t_bus_ns) < np.abs(tt[j] - b.t_bus_ns), tt[j - 1], tt[j])
            p99 = _p99_after_first_second(b.t_bus_ns, near)
            if p99 is not None:
                accuracy[d.name] = p99
    if phone is not None and "phone/imu" in reader.streams:
        b = reader.samples("phone/imu")
        true_t = phone.t0_host_ns + b.t_device_ns - int(phone.t0_ms * 1e6)  # page event time -> host clock
        p99 = _p99_after_first_second(b.t_bus_ns, true_t)
        if p99 is not None:
            accuracy["phone"] = p99
    return accuracy


def stream_lines(summary: dict[str, Any], accuracy: dict[str, float], phone: PhoneSim | None,
                 serial: SerialSim | None, unplugs: int = 1) -> list[str]:
    """One line per IMU stream of the session: samples, rate, drops and how its clock was fitted."""
    lines = []
    for st in summary["streams"]:
        if not st["name"].endswith("/imu"):
            continue
        clk = st["clock"] or {}
        dev = st["device"]
        if clk.get("pseudo"):
            desc = "no device clock: bus times from the dejittered arrival pattern"
        else:
            desc = f"device clock fitted at {clk.get('drift_ppm', 0):+.1f} ppm (simulated " \
                   f"{DEMO_DRIFT_PPM.get(dev, 0):+.0f}), {clk.get('epochs', 1)} epoch(s)"
            if dev in accuracy:
                desc += (f"; bus times within {accuracy[dev]:.2f} ms of the true reading times"
                         " (p99, after the first second)")
        if dev == "phone" and phone is not None:
            desc += f"; {phone.events} events sent, over TLS + WebSocket"
        if dev == "hand" and serial is not None and st["drops"]:
            desc += (f"; its drops are the readings sent while it was unplugged ({unplugs} time(s),"
                     f" {DEMO_UNPLUG_FOR:g} s each)")
        lines.append(f"  {st['name']:12s} {st['samples']:6d} samples {st['rate_hz']:7.2f} Hz  {st['drops']} drops"
                     f"  {desc}")
    return lines


@dataclass
class LiveFollow:
    """Streaming cycle extraction on the live bus while the demo runs: when a cycle first came
    (seconds into the take) and each improvement."""

    t0_ns: int = field(default_factory=MONOTONIC.now_ns)
    cycles: list[tuple[float, Cycle]] = field(default_factory=list)
    follower: CycleFollower | None = None

    def got(self, c: Cycle) -> None:
        self.cycles.append(((MONOTONIC.now_ns() - self.t0_ns) / 1e9, c))

    def line(self) -> str:
        if self.cycles:
            t_first, c_first = self.cycles[0]
            return (f"  live: following wrist/imu on the bus, the first cycle came {t_first:.1f} s into the take"
                    f" ({c_first.loops} loops, {c_first.period_s:.3f} s), then improved {len(self.cycles) - 1}"
                    " time(s)")
        why = self.follower.extractor.last_error if self.follower is not None else None
        return f"  live: following wrist/imu on the bus, no cycle during the take ({why or 'too few loops'})"


def follow_wrist(cap: Capture) -> LiveFollow | None:
    from capture.app.cycle_follow import CycleFollower

    live = LiveFollow()
    try:
        live.follower = CycleFollower("wrist/imu", live.got, columns=[0, 1, 2, 3, 4, 5])
        cap.subscribe(live.follower, name="cycle-follower")
    except (CaptureError, ValueError) as exc:
        log.warning("no live cycle follower: %s", exc)
        return None
    return live


def demo_cycle(reader: SessionReader, cap: Capture) -> list[str]:
    """The cycle of the wrist's repeated gesture, from the recorded session, against the simulator's
    truth (the mean loop duration over the recorded span); the loop CSV and the report beside the
    session. A failure is one line: the demo goes on."""
    from capture.app.cycle_input import extract_cycle, session_cycle_input, write_cycle_report

    name = "wrist/imu"
    folder = os.path.dirname(os.path.abspath(reader.path))
    png, loop_csv = os.path.join(folder, "wrist_cycle.png"), os.path.join(folder, "wrist_cycle.csv")
    try:
        inp = session_cycle_input(reader, name, None)
        cyc = extract_cycle(inp)
    except (CycleError, ConfigError, ValueError) as exc:
        return [f"cycle: no cycle extracted from {name} ({exc})"]
    truth = ""
    wrist = cap.device("wrist")
    tr = wrist.transport if wrist is not None else None
    if isinstance(tr, SimulatorTruth) and tr.motion is not None and tr.motion.loop_s and tr.truth_ns \
            and inp.origin_ns is not None:
        # bus time -> device seconds (the first reading is device second 0); the simulated mean loop
        # duration over the recorded span, in host seconds as the bus times are
        drift = tr.drift_ppm * 1e-6
        d0 = (inp.origin_ns - tr.latency_ns - tr.truth_ns[0]) / 1e9 * (1.0 + drift)
        d1 = d0 + float(inp.t[-1]) * (1.0 + drift)
        mean_s = tr.motion.mean_loop_s(d0, d1) / (1.0 + drift)
        truth = f" (simulated: {mean_s:.4f} s mean loop, {100.0 * (cyc.period_s / mean_s - 1.0):+.2f} %)"
    lines = [f"cycle: the wrist repeats a gesture ({DEMO_LOOP_S:g} s +- 8 % per loop): period {cyc.period_s:.4f} s"
             f"{truth} from {cyc.loops} loops of {name}, confidence {cyc.confidence:.2f}, in {cyc.elapsed_ms:.0f} ms"]
    try:
        cyc.write_csv(loop_csv)
        write_cycle_report(cyc, png, f"perfcap demo: the wrist's gesture ({name})")
    except (ConfigError, OSError) as exc:
        lines.append(f"  (the loop or its report could not be written: {exc})")
        return lines
    lines.append(f"  loop written to {loop_csv}; report (the aligned loops and the cycle per channel) {png}")
    return lines


def demo_puppet(reader: SessionReader) -> str:
    """The puppet driven by the simulated phone's recorded attitude; ``puppet.bvh`` beside the session.
    A failure is one line: the demo goes on."""
    from capture.app.puppet_input import session_track
    from capture.app.puppet_run import PuppetRun
    from retarget.bvh import write_bvh

    path = os.path.join(os.path.dirname(os.path.abspath(reader.path)), "puppet.bvh")
    try:
        track = session_track(reader, "phone")
        run = PuppetRun(rate=60.0)                      # builds the blend and its probe table
        frames = track.resample(60.0)
        t0 = MONOTONIC.now_ns()
        run.run(frames)
        ms = (MONOTONIC.now_ns() - t0) / 1e6 / max(run.frames, 1)
        if run.frames < 2:
            return f"puppet: not driven from the phone (its take gave {run.frames} frame(s))"
        clip = run.clip("puppet")
        write_bvh(path, clip)
        ground = np.hypot(np.diff(clip.root_pos[:, 0]), np.diff(clip.root_pos[:, 2])) * clip.fps
    except Exception as exc:   # the demo goes on whatever failed here; the reason is said in one line
        return f"puppet: not driven from the phone ({type(exc).__name__}: {exc})"
    held = "held throughout: the simulated phone sends no touch" if track.held_throughout else "grabbed by touch"
    return (f"puppet: the phone's attitude ({held}) drove {run.frames} frames at 60 Hz ({ms:.2f} ms each): the"
            f" character covered {ground.sum() / clip.fps:.1f} m at up to {np.percentile(ground, 95):.1f} m/s;"
            " states " + " -> ".join(run.states_visited()) + f"; BVH {path}")
