"""The harness of ``bench_serve.py`` (not a benchmark itself): its parties as processes, what is read
of them from ``/proc``, and the figures computed from what they save.

* ``Child`` runs one party (a role of ``_serve_roles.py``) in its own process: JSON lines on its
  stdout, commands on its stdin, its stderr in a log file;
* ``Window``: the CPU of some processes and of the whole machine over a time window;
* ``run_phones``: simulated phones streaming to a service or to the bare baseline server;
* ``loss_check``, ``match_wire``, ``pacing``, ``fmt_ms``: loss, wire latency, the phones' pacing and
  latency percentiles.

Both ``bench_serve.py`` and ``_serve_roles.py`` import it as ``_serve_common`` (they run with
``benchmarks/`` on ``sys.path``).
"""

from __future__ import annotations

import json
import os
import queue
import subprocess
import sys
import threading
import time
from typing import Any

import numpy as np

TOKEN = "bench-serve-pairing-token-0123"
OSC_ALLOW = "192.0.2.7"  # TEST-NET-1: nobody on this machine, so every loopback datagram is refused
PHONE_SRC = 10           # phones send from 127.0.0.10, .11, ...
DATA_PREFIX = '{"type":"data"'
CLK_TCK = os.sysconf("SC_CLK_TCK")
RETAIN_S = 35.0          # part 2 looks at the service's memory again this long after the flood
ROLES_SCRIPT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "_serve_roles.py")


def jprint(obj: dict[str, Any]) -> None:
    """One JSON line on stdout, as a role tells the benchmark what happened."""
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


# ================================================================================================
# the parties' processes
# ================================================================================================
class Child:
    """A role in its own process: JSON lines on stdout, stderr to a log file.

    ``ready`` holds the role's ``ready`` line (its endpoints) once ``wait_ready`` has seen it.
    """

    def __init__(self, role: str, cfg: dict[str, Any], log_path: str) -> None:
        self.log_path = log_path
        self._log = open(log_path, "w")  # the child's stderr for its whole life; closed in close()
        self.p = subprocess.Popen([sys.executable, ROLES_SCRIPT, "--role", role, "--cfg", json.dumps(cfg)],
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._log, text=True)
        self.pid = self.p.pid
        self.ready: dict[str, Any] = {}
        self._q: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.p.stdout is not None
        for line in self.p.stdout:
            self._q.put(line)
        self._q.put(None)

    def expect(self, event: str, timeout: float) -> dict[str, Any]:
        t_end = time.monotonic() + timeout
        while True:
            try:
                line = self._q.get(timeout=max(0.01, t_end - time.monotonic()))
            except queue.Empty:
                raise RuntimeError(f"{event!r} not seen in {timeout:.0f} s; see {self.log_path}") from None
            if line is None:
                with open(self.log_path) as f:
                    tail = f.read()[-3000:]
                raise RuntimeError(f"process ended before {event!r}; see {self.log_path}:\n{tail}")
            try:
                obj = json.loads(line)
            except ValueError:
                continue
            if obj.get("event") == event:
                return obj

    def wait_ready(self, timeout: float) -> dict[str, Any]:
        """Wait for the role's ``ready`` line and keep it in ``ready``."""
        self.ready = self.expect("ready", timeout)
        return self.ready

    def send(self, line: str) -> None:
        assert self.p.stdin is not None
        self.p.stdin.write(line + "\n")
        self.p.stdin.flush()

    def close(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait(5)
        self._log.close()


def proc_cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        rest = f.read().rsplit(")", 1)[1].split()
    return (int(rest[11]) + int(rest[12])) / CLK_TCK


def proc_rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def udp_rcvbuf_errors() -> int:
    """Datagrams the kernel dropped because a socket's receive buffer was full (system-wide)."""
    with open("/proc/net/snmp") as f:
        rows = [ln.split() for ln in f if ln.startswith("Udp:")]
    return int(rows[1][rows[0].index("RcvbufErrors")])


def machine_jiffies() -> tuple[int, int]:
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    return sum(v), v[3] + v[4]


class Window:
    """CPU of some processes and of the whole machine over a time window."""

    def __init__(self, pids: dict[str, int]) -> None:
        self.pids = pids
        self.t0 = time.monotonic()
        self.t0_ns = time.monotonic_ns()
        self.c0 = {k: proc_cpu_s(p) for k, p in pids.items()}
        self.m0 = machine_jiffies()

    def end(self) -> dict[str, Any]:
        wall = time.monotonic() - self.t0
        cpu = {k: (proc_cpu_s(p) - self.c0[k]) / wall for k, p in self.pids.items()}
        m1 = machine_jiffies()
        tot, idle = m1[0] - self.m0[0], m1[1] - self.m0[1]
        busy_cores = (1.0 - idle / max(1, tot)) * (os.cpu_count() or 1)
        return {"wall": wall, "cpu": cpu, "t0_ns": self.t0_ns, "t1_ns": time.monotonic_ns(),
                "machine_cores": busy_cores, "others_cores": busy_cores - sum(cpu.values())}


# ================================================================================================
# figures
# ================================================================================================
def pcts(a: np.ndarray, qs: tuple[float, ...] = (50, 99, 99.9, 100)) -> list[float]:
    if a.size == 0:
        return [float("nan")] * len(qs)
    return [float(x) for x in np.percentile(a, qs)]


def fmt_ms(a: np.ndarray) -> str:
    p50, p99, p999, mx = pcts(a)
    return f"p50 {p50:.3f}  p99 {p99:.3f}  p99.9 {p999:.3f}  max {mx:.3f} ms (n={a.size})"


def match_wire(arrivals: dict[str, np.ndarray], sends: dict[str, np.ndarray],
               window: tuple[int, int] | None = None) -> tuple[np.ndarray, list[str]]:
    """Per message: arrival stamp minus the client's send time (messages matched by order), for the
    messages that arrived in ``window`` (monotonic ns) if given."""
    out, bad = [], []
    for key, arr in arrivals.items():
        snd = sends.get(key)
        if snd is None or snd.size != arr.size:
            bad.append(f"{key}: {0 if snd is None else snd.size} sent, {arr.size} arrived")
            continue
        sel = slice(None) if window is None else (arr >= window[0]) & (arr <= window[1])
        out.append((arr[sel] - snd[sel]) / 1e6)
    return (np.concatenate(out) if out else np.zeros(0)), bad


def pacing(ph: Any, window: tuple[int, int]) -> np.ndarray:
    """The phones' send time behind their schedule (ms), for sends in ``window``."""
    out = []
    for k in ph.files:
        if k.startswith("send:"):
            snd, sch = ph[k], ph["sched:" + k[5:]]
            snd = snd[:sch.size]
            sel = (snd >= window[0]) & (snd <= window[1])
            out.append((snd[sel] - sch[sel]) / 1e6)
    return np.concatenate(out) if out else np.zeros(0)


def run_phones(tmp: str, tag: str, target: Child, n: int, batch_s: float, duration: float, t0_ms: float | None,
               src: int, window: tuple[float, float]) -> tuple[dict[str, Any], dict[str, Any], np.lib.npyio.NpzFile]:
    """Phones against ``target`` (service or sink, ready); returns (phones result, CPU window, phone arrays)."""
    ep = target.ready
    out = os.path.join(tmp, f"{tag}-phones.npz")
    cfg = {"page_url": ep["page_url"], "token": TOKEN, "fingerprint": ep["fingerprint"], "n": n, "rate": 100.0,
           "batch_s": batch_s, "duration": duration, "t0_ms": t0_ms, "src": src, "out": out}
    ph = Child("phones", cfg, os.path.join(tmp, f"{tag}-phones.log"))
    try:
        st = ph.expect("streaming", 30)
        if st["connected"] != n:
            print(f"   !! only {st['connected']} of {n} phones connected")
        time.sleep(window[0])
        w = Window({"target": target.pid, "phones": ph.pid})
        time.sleep(max(0.5, duration - window[0] - window[1]))
        win = w.end()
        res = ph.expect("done", duration + 60)
    finally:
        ph.close()
    return res, win, np.load(out)


def service_arrays(tmp: str, tag: str) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    a = np.load(os.path.join(tmp, f"{tag}.npz"))
    host = {k[5:]: a[k] for k in a.files if k.startswith("host:")}
    pub = {k[4:]: a[k] for k in a.files if k.startswith("pub:")}
    return host, pub


def loss_check(phones: list[dict[str, Any]], stopped: dict[str, Any], session: str | None) -> tuple[bool, list[str]]:
    """Every motion event sent is an imu sample on the bus and in the recording (if any), with no refusals."""
    from capture.session import SessionReader

    reader = SessionReader(session) if session else None
    lines, ok = [], True
    tot_ev = tot_bus = tot_rec = 0
    for p in phones:
        dev = p["device"]
        stream = f"{dev}/imu"
        bus = stopped["counts"].get(stream, 0)
        if reader is None:
            rec = bus
        else:
            rec = len(reader.samples(stream)) if stream in reader.streams else 0
        d = stopped["devices"].get(dev, {})
        box = stopped["boxes"].get(f"page/{p['id']}", {})
        tot_ev += p["events"]
        tot_bus += bus
        tot_rec += rec
        bad = (bus != p["events"] or rec != p["events"] or d.get("lost_messages", 0) or d.get("lost_readings", 0)
               or box.get("dropped", 0) or p["connects"] != 1 or p["error"] or d.get("framing_errors", 0))
        if bad:
            ok = False
            lines.append(f"{p['id']} -> {dev}: {p['events']} events sent in {p['sent']} messages, {bus} imu samples on"
                         f" the bus, {rec} recorded; seq gaps {d.get('lost_messages')}, lost readings"
                         f" {d.get('lost_readings')}, inbox refused {box.get('dropped')}, connects {p['connects']},"
                         f" close code {p['close_code']}, error {p['error']}")
    rec_drop = stopped["subscribers"].get("recorder", {}).get("dropped", 0)
    if rec_drop or stopped.get("recorder_error"):
        ok = False
        lines.append(f"recorder dropped {rec_drop}, error {stopped.get('recorder_error')}")
    lines.insert(0, f"{tot_ev} motion events sent by {len(phones)} phones; {tot_bus} imu samples on the bus;"
                    + (f" {tot_rec} in the recording; recorder drops {rec_drop}" if reader else " (not recording)"))
    return ok, lines


def http_json(url: str, token: str | None, timeout: float = 10.0) -> tuple[int, Any]:
    import urllib.error
    import urllib.request

    req = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"} if token else {})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, json.load(r)
    except urllib.error.HTTPError as exc:
        return exc.code, None
    except (OSError, ValueError) as exc:
        return 0, str(exc)
