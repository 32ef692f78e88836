"""A simulated serial device behind a pseudo-terminal, opened by the real pyserial code.

``PtySerialDevice`` creates a pty pair, puts a stable symlink to its slave end at ``path`` (as udev
does with ``/dev/serial/by-id/...``) and streams a ``FrameSource``'s bytes into the master end at
the readings' times. A reader opens ``path`` with ``serial:///that/path`` exactly as it would a USB
adapter. Faults, on command or on a schedule:

- **unplug / replug**: the pty is closed (the reader's next read fails with EIO, as when a USB
  adapter is pulled) and the symlink removed; on replug a new pty appears at the same path.
  Readings due while unplugged are never sent (``lost_unplugged``).
- **garbage**: random bytes between frames. **drop**: the next N bytes vanish (a UART overrun).
- **stall**: the device goes quiet for S seconds, then continues (its readings are late, not lost).
- **burst**: FTDI-style batching: bytes are held until ``burst_bytes`` have gathered or
  ``burst_ms`` has passed since the first of them, then written at once.

Every reading written while a reader has the port open is logged in ``sent`` as (reading index,
host time of the write), so a test can check that nothing was lost outside the unplugged windows
and measure latency end to end. As with a real adapter, bytes sent while no program has the port
open are lost (``unheard``), and bytes a reader does not take in time (a full pty buffer) are
counted in ``overrun_bytes``, never blocked on.

``perfcap sim serial --kind witmotion`` runs one from the command line (see ``main``).
"""

from __future__ import annotations

import errno
import logging
import math
import os
import queue
import select
import sys
import tempfile
import threading
import tty
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from capture.clock import MONOTONIC, Clock
from capture.errors import CaptureError, ConfigError
from sim_devices.cli_args import SECONDS, SECONDS_OR_ZERO, SEED, SimParser, number, whole
from sim_devices.frames import ENCODERS, FrameSource, SessionSource, WavingSource

if TYPE_CHECKING:
    import argparse
    from collections.abc import Callable, Sequence

log = logging.getLogger(__name__)


@dataclass
class SimStats:
    readings_sent: int = 0
    bytes_sent: int = 0
    lost_unplugged: int = 0
    garbage_bytes: int = 0
    dropped_bytes: int = 0
    overrun_bytes: int = 0
    unplugs: int = 0
    replugs: int = 0
    stalls: int = 0
    unheard: int = 0  # readings sent while no reader had the port open (lost, as on real hardware)
    unheard_bytes: int = 0
    host_bytes: int = 0  # bytes the reader wrote to the device (commands)
    unplugged_windows: list[tuple[int, int | None]] = field(default_factory=list)  # host ns


class PtySerialDevice:
    """A serial device on a pty; see the module docstring.

    Args:
        source: what the device sends.
        path: where the stable symlink goes (default: a new temporary directory, ``ttySIM0``).
        clock: host clock (pacing and the ``sent`` log).
        burst_ms: FTDI latency-timer batching (0 = write each reading as it is due).
        burst_bytes: a burst is written as soon as this many bytes have gathered.
        garbage: probability of random bytes before a reading.
        unplug_every / unplug_for: scheduled unplugs (seconds; 0 = none).
        seed: fault randomness.
        speed: time factor (2 = twice as fast as real time).
    """

    def __init__(self, source: FrameSource, path: str | None = None, *, clock: Clock = MONOTONIC,
                 burst_ms: float = 0.0, burst_bytes: int = 62, garbage: float = 0.0,
                 unplug_every: float = 0.0, unplug_for: float = 1.0, seed: int = 1, speed: float = 1.0) -> None:
        if speed <= 0:
            raise ConfigError("speed must be positive")
        self.source = source
        self.clock = clock
        self._tmpdir: str | None = None
        if path is None:
            self._tmpdir = tempfile.mkdtemp(prefix="perfcap-sim-")
            path = os.path.join(self._tmpdir, "ttySIM0")
        self.path = os.path.abspath(path)
        if os.path.lexists(self.path) and not _stale_port_link(self.path):
            # the port is a symlink the simulator owns: it replaces and removes it, so it never takes the
            # place of a file, a folder, a device (``--link /dev/zero`` would remove /dev/zero) or another
            # link (a udev ``/dev/serial/by-id`` name); only a link to a pseudo-terminal, an earlier run's
            # port, is taken over
            raise ConfigError(f"{self.path} exists and is not an earlier simulated port: the simulated port "
                              "needs a path of its own")
        self.burst_ns = int(burst_ms * 1e6)
        self.burst_bytes = max(1, burst_bytes)
        self.garbage = garbage
        self.unplug_every = unplug_every
        self.unplug_for = unplug_for
        self.speed = speed
        self.rng = np.random.default_rng(seed)
        self.stats = SimStats()
        self.sent: list[tuple[int, int]] = []
        self.host_data = bytearray()
        self._master: int | None = None
        self._poll: Any = None
        self.slave_name: str | None = None
        self._cmds: queue.SimpleQueue[tuple[str, float]] = queue.SimpleQueue()
        self._stop = threading.Event()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"sim-serial-{os.path.basename(self.path)}",
                                        daemon=True)
        self.error: BaseException | None = None
        self._plug()

    # -- public control -------------------------------------------------------------------------------
    def device_url(self, kind: str | None = None, **options: Any) -> str:
        """The device string a reader uses for this simulator."""
        opts = {**self.source.device_options(), **options}
        q = "&".join(f"{k}={str(v).lower() if isinstance(v, bool) else v}" for k, v in opts.items())
        return f"{kind or self.source.kind}@serial://{self.path}" + (f"?{q}" if q else "")

    def start(self) -> PtySerialDevice:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.ident is not None:
            self._thread.join(5.0)
        self._unplug(record=False)
        if self._tmpdir is not None:
            try:
                os.rmdir(self._tmpdir)
            except OSError:
                pass

    def __enter__(self) -> PtySerialDevice:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def finished(self) -> bool:
        """The source ran out (finite sources only)."""
        return self._done.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        return self._done.wait(timeout)

    def unplug(self) -> None:
        self._cmds.put(("unplug", 0.0))

    def replug(self) -> None:
        self._cmds.put(("replug", 0.0))

    def inject_garbage(self, n: int = 16) -> None:
        self._cmds.put(("garbage", float(n)))

    def drop_bytes(self, n: int) -> None:
        self._cmds.put(("drop", float(n)))

    def stall(self, seconds: float) -> None:
        self._cmds.put(("stall", float(seconds)))

    def set_burst(self, ms: float) -> None:
        self._cmds.put(("burst", float(ms)))

    @property
    def plugged(self) -> bool:
        return self._master is not None

    # -- the pty ----------------------------------------------------------------------------------------
    def _plug(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no CR/LF translation: bytes pass as they are
        self.slave_name = os.ttyname(slave)
        os.close(slave)  # while no reader has the port open, the master sees a hang-up (see _heard)
        os.set_blocking(master, False)
        self._master = master
        self._poll = select.poll()
        self._poll.register(master, select.POLLHUP)
        tmp = self.path + ".new"
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        os.symlink(self.slave_name, tmp)
        try:
            os.replace(tmp, self.path)  # atomic: the path never points at a dead pty
        except OSError:
            os.unlink(tmp)              # (the path is a folder, say): no link left behind
            os.close(master)
            self._master = None
            raise
        log.debug("sim serial at %s -> %s", self.path, self.slave_name)

    def _unplug(self, record: bool = True) -> None:
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass
        was = self._master is not None
        if self._master is not None:
            try:
                os.close(self._master)
            except OSError:
                pass
        self._master = None
        if record and was:
            self.stats.unplugs += 1
            self.stats.unplugged_windows.append((self.clock.now_ns(), None))

    def _replug(self) -> None:
        if self._master is not None:
            return
        self._plug()
        self.stats.replugs += 1
        if self.stats.unplugged_windows and self.stats.unplugged_windows[-1][1] is None:
            start, _ = self.stats.unplugged_windows[-1]
            self.stats.unplugged_windows[-1] = (start, self.clock.now_ns())

    def _heard(self) -> bool:
        """Whether a reader has the port open now. Bytes sent while nobody listens are lost, as
        with a USB adapter whose port is closed (``unheard``)."""
        return self._master is not None and not self._poll.poll(0)

    def _write(self, data: bytes) -> bool:
        """Write to the port; returns whether a reader had it open."""
        fd = self._master
        if fd is None or not data:
            return False
        if not self._heard():
            self.stats.unheard_bytes += len(data)
            return False
        try:
            n = os.write(fd, data)
        except BlockingIOError:
            n = 0
        except OSError as exc:
            if exc.errno == errno.EIO:  # nobody has the port open and the buffer is gone
                n = 0
            else:
                raise
        self.stats.bytes_sent += n
        if n < len(data):
            self.stats.overrun_bytes += len(data) - n
        return True

    def _drain_host(self) -> None:
        fd = self._master
        if fd is None:
            return
        while True:
            try:
                got = os.read(fd, 4096)
            except (BlockingIOError, OSError):
                return
            if not got:
                return
            self.stats.host_bytes += len(got)
            if len(self.host_data) < 1 << 20:
                self.host_data += got

    # -- the streaming thread ---------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            self._stream()
        except BaseException as exc:  # reported to the owner, never a silent death
            self.error = exc
            log.error("simulated serial device at %s stopped: %s", self.path, exc)
        finally:
            self._done.set()

    def _stream(self) -> None:
        clock = self.clock
        t0 = clock.now_ns()
        shift = 0  # stalls push everything later
        pending = bytearray()
        pending_ends: list[tuple[int, int]] = []  # (reading index, end offset in pending)
        first_pending = 0
        drop = 0
        next_unplug = t0 + int(self.unplug_every * 1e9) if self.unplug_every else None
        replug_at: int | None = None
        idx = 0
        inv_speed = 1.0 / self.speed

        def flush(now: int, everything: bool) -> None:
            """Write the held bytes (whole bursts only unless ``everything``); a reading counts as
            sent when its last byte is written."""
            nonlocal first_pending
            n = len(pending) if everything else (len(pending) // self.burst_bytes) * self.burst_bytes
            if n == 0:
                return
            heard = self._write(bytes(pending[:n]))
            del pending[:n]
            k = 0
            while k < len(pending_ends) and pending_ends[k][1] <= n:
                if heard:
                    self.sent.append((pending_ends[k][0], now))
                k += 1
            del pending_ends[:k]
            for j, (i, end) in enumerate(pending_ends):
                pending_ends[j] = (i, end - n)
            if heard:
                self.stats.readings_sent += k
            else:
                self.stats.unheard += k
            first_pending = now

        for times, pieces in self.source.blocks():
            for t, piece in zip(times.tolist(), pieces, strict=True):  # one byte string per reading
                due = t0 + shift + int(t * inv_speed * 1e9)
                while True:  # wait for the reading's time, serving commands, bursts and the schedule
                    if self._stop.is_set():
                        return
                    now = clock.now_ns()
                    self._drain_host()
                    while not self._cmds.empty():
                        cmd, arg = self._cmds.get()
                        if cmd == "unplug":
                            pending.clear()
                            pending_ends.clear()
                            self._unplug()
                        elif cmd == "replug":
                            self._replug()
                            replug_at = None
                        elif cmd == "garbage":
                            g = self.rng.integers(0, 256, int(arg), np.uint8).tobytes()
                            self.stats.garbage_bytes += len(g)
                            self._write(g)
                        elif cmd == "drop":
                            drop += int(arg)
                        elif cmd == "stall":
                            shift += int(arg * 1e9)
                            due += int(arg * 1e9)
                            self.stats.stalls += 1
                        elif cmd == "burst":
                            flush(now, True)
                            self.burst_ns = int(arg * 1e6)
                    if next_unplug is not None and now >= next_unplug and self.plugged:
                        pending.clear()
                        pending_ends.clear()
                        self._unplug()
                        replug_at = now + int(self.unplug_for * 1e9)
                        next_unplug += int(self.unplug_every * 1e9)
                    if replug_at is not None and now >= replug_at:
                        self._replug()
                        replug_at = None
                    if pending and self.burst_ns and now >= first_pending + self.burst_ns:
                        flush(now, True)
                    if now >= due:
                        break
                    wake = due
                    if pending and self.burst_ns:
                        wake = min(wake, first_pending + self.burst_ns)
                    if replug_at is not None:
                        wake = min(wake, replug_at)
                    if next_unplug is not None:
                        wake = min(wake, next_unplug)
                    clock.sleep_until_ns(min(wake, now + 20_000_000))
                if not self.plugged:
                    self.stats.lost_unplugged += 1
                    idx += 1
                    continue
                out = piece  # what goes on the wire: the reading, after the faults
                if self.garbage and self.rng.random() < self.garbage:
                    g = self.rng.integers(0, 256, int(self.rng.integers(1, 12)), np.uint8).tobytes()
                    self.stats.garbage_bytes += len(g)
                    out = g + out
                if drop:
                    k = min(drop, len(out))
                    out = out[k:]
                    drop -= k
                    self.stats.dropped_bytes += k
                now = clock.now_ns()
                if self.burst_ns:
                    if not pending:
                        first_pending = now
                    pending += out
                    pending_ends.append((idx, len(pending)))
                    if len(pending) >= self.burst_bytes:
                        flush(now, False)
                elif self._write(out):
                    self.sent.append((idx, clock.now_ns()))
                    self.stats.readings_sent += 1
                else:
                    self.stats.unheard += 1
                idx += 1
        flush(clock.now_ns(), True)


def build_parser() -> argparse.ArgumentParser:
    """The flags of ``perfcap sim serial``."""
    p = SimParser(prog="perfcap sim serial",
                                description="Serve a simulated serial IMU on a pty; open the printed path with"
                                            " perfcap record -d KIND@serial://PATH (or any serial program).")
    p.add_argument("--kind", default="witmotion", choices=sorted(ENCODERS),
                   help=f"device to simulate: {', '.join(sorted(ENCODERS))}")
    p.add_argument("--rate", type=number(0, 5000, above=True), default=200.0,
                   help="readings per second (default 200)")
    p.add_argument("--seed", type=SEED, default=1)
    p.add_argument("--no-device-clock", action="store_true", help="do not send device time stamps")
    p.add_argument("--still", action="store_true", help="the device lies still (for perfcap calibrate)")
    p.add_argument("--heading", type=number(-360, 360), default=None, metavar="DEG",
                   help="witmotion: also send a magnetometer; a --still device faces this heading")
    p.add_argument("--gyro-bias", default="0,0,0", metavar="X,Y,Z", help="gyro offset the sensor adds, deg/s")
    p.add_argument("--gyro-noise", type=number(0, 1e4), default=0.0, metavar="DPS", help="gyro white noise, deg/s")
    p.add_argument("--session", help="play a recorded session's raw bytes instead of synthetic motion")
    p.add_argument("--device", help="which device of --session")
    p.add_argument("--loop", action="store_true", help="loop --session")
    p.add_argument("--link", help="path of the port symlink (default: a temporary directory)")
    p.add_argument("--burst-ms", type=number(0, 1e4), default=0.0, help="FTDI-style batching every this many ms")
    p.add_argument("--burst-bytes", type=whole(1, 1 << 20), default=62)
    p.add_argument("--garbage", type=number(0, 1), default=0.0, help="probability of garbage before a reading")
    p.add_argument("--unplug-every", type=SECONDS_OR_ZERO, default=0.0, help="unplug every this many seconds")
    p.add_argument("--unplug-for", type=SECONDS, default=1.0, help="... for this long")
    p.add_argument("--duration", type=SECONDS_OR_ZERO, default=0.0,
                   help="stop after this many seconds (0 = until Ctrl-C)")
    p.add_argument("--sent-log", metavar="FILE.npy", help="at the end, save (reading index, host write time ns)"
                   " of every reading sent, for latency and loss checks")
    return p


def _check_writable(path: str) -> None:
    """``--sent-log`` can be written at the end: its folder exists and it is no folder, FIFO or device.

    Raises:
        ConfigError: saying why not.
    """
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise ConfigError(f"--sent-log {path}: the folder {folder} does not exist")
    if os.path.lexists(path) and not os.path.isfile(path):
        raise ConfigError(f"--sent-log {path} exists and is not a file")
    if not os.access(folder, os.W_OK):
        raise ConfigError(f"--sent-log {path}: the folder {folder} is not writable")


def _stale_port_link(path: str) -> bool:
    """Whether ``path`` is a symlink to a pseudo-terminal (what a simulated port leaves behind)."""
    try:
        return os.path.islink(path) and os.readlink(path).startswith("/dev/pts/")
    except OSError:
        return False


COMMANDS = "unplug | replug | garbage N | drop N | stall SECONDS | burst MS | quit"


def main(argv: Sequence[str] | None = None) -> int:
    """``perfcap sim serial ...``: serve until Ctrl-C, ``--duration`` or ``quit`` on stdin.

    Fault commands are read from stdin, one per line: ``unplug``, ``replug``, ``garbage N``,
    ``drop N``, ``stall SECONDS``, ``burst MS``, ``quit``.
    """
    args = build_parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    try:
        if args.session:
            if os.path.exists(args.session) and not (os.path.isfile(args.session) or os.path.isdir(args.session)):
                raise ConfigError(f"--session {args.session} is not a file (a FIFO or a device)")
            src: FrameSource = SessionSource(args.session, args.device, loop=args.loop)
        else:
            if args.rate <= 0 or args.rate > 5000:
                raise ConfigError("--rate must be within (0, 5000]")
            try:
                bias = tuple(float(x) for x in args.gyro_bias.split(","))
            except ValueError:
                bias = ()
            if len(bias) != 3 or not all(math.isfinite(b) and abs(b) <= 1e4 for b in bias):
                raise ConfigError(f"--gyro-bias {args.gyro_bias!r}: expected X,Y,Z in deg/s (finite, at most 1e4)")
            src = WavingSource(args.kind, args.rate, args.seed, device_clock=not args.no_device_clock,
                               amplitude_deg=0.0 if args.still else 40.0, gyro_bias_dps=bias,
                               gyro_noise_dps=args.gyro_noise, heading_deg=args.heading)
        if args.sent_log:
            _check_writable(args.sent_log)
        sim = PtySerialDevice(src, args.link, burst_ms=args.burst_ms, burst_bytes=args.burst_bytes,
                              garbage=args.garbage, unplug_every=args.unplug_every, unplug_for=args.unplug_for,
                              seed=args.seed)
    except (CaptureError, OSError) as exc:
        print(f"perfcap: error: sim serial: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    sim.start()
    print(sim.path, flush=True)
    print(f"# {src.kind} on {sim.path} (pty {sim.slave_name}); read it with:\n"
          f"#   perfcap record -d '{sim.device_url()}' -o take.mcap\n"
          f"# commands on stdin: {COMMANDS}", file=sys.stderr, flush=True)
    stop = threading.Event()
    with_arg: dict[str, Callable[[float], None]] = {
        "garbage": lambda n: sim.inject_garbage(int(n)), "drop": lambda n: sim.drop_bytes(int(n)),
        "stall": sim.stall, "burst": sim.set_burst}

    def commands() -> None:
        try:
            for line in sys.stdin:
                run_command(line)
        except (OSError, ValueError) as exc:  # no readable stdin (closed, or not a stream): no commands
            print(f"# commands off: standard input cannot be read ({exc})", file=sys.stderr, flush=True)

    def run_command(line: str) -> None:
        words = line.split()
        if not words:
            return
        try:
            arg = float(words[1]) if len(words) > 1 else None
            cmd = words[0]
            if cmd == "quit":
                stop.set()
                return
            if cmd == "unplug":
                sim.unplug()
            elif cmd == "replug":
                sim.replug()
            elif cmd in with_arg and arg is not None and arg >= 0:
                with_arg[cmd](arg)
            else:
                raise ValueError
            print(f"# {line.strip()}: ok", file=sys.stderr, flush=True)
        except ValueError:
            print(f"# unknown command {line.strip()!r}; commands: {COMMANDS}", file=sys.stderr, flush=True)

    threading.Thread(target=commands, daemon=True).start()
    t_end = MONOTONIC.now_ns() + int(args.duration * 1e9) if args.duration > 0 else None
    try:
        while not stop.is_set() and not sim.finished and (t_end is None or MONOTONIC.now_ns() < t_end):
            stop.wait(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        sim.stop()
    if args.sent_log:
        try:
            np.save(args.sent_log, np.array(sim.sent, np.int64).reshape(-1, 2))
        except OSError as exc:
            print(f"perfcap sim serial: cannot write --sent-log {args.sent_log}: {exc.strerror or exc}",
                  file=sys.stderr)
            return 1
    s = sim.stats
    print(f"# sent {s.readings_sent} readings ({s.bytes_sent} bytes); {s.lost_unplugged} while unplugged;"
          f" {s.unplugs} unplugs; {s.overrun_bytes} bytes not taken by a reader", file=sys.stderr)
    if sim.error is not None:
        print(f"perfcap sim serial: {sim.error}", file=sys.stderr)
        return 1
    return 0


__all__ = ["PtySerialDevice", "SimStats", "main"]
