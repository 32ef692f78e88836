"""The bad-input sweep: every flag of every ``perfcap`` command (walked from ``build_parser()`` and the
simulators' own parsers), every positional argument, config files and ``PERFCAP_*`` variables, each given
hostile values, run in this process. Each run must exit 0, 1 (a documented runtime failure) or 2 (bad
input), never 70 (internal error), never with a traceback; an exit 2 says one line ``perfcap: error: ...``
on stderr and leaves no new file behind.

``test_bad_input_sweep.py`` runs a seeded sample in CI; run the whole campaign with its figures::

    .venv/bin/python tests/cli/bad_input_sweep.py [--cases N] [--seed S] [--only COMMAND]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import logging
import os
import random
import signal
import sys
import tempfile
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Iterator

#: a file name whose bytes are not UTF-8, as Python hands it over in argv (os.fsdecode's surrogates)
UNDECODABLE = os.fsdecode(b"take-\xff\xfe.mcap")

#: values no flag should turn into an internal error ("{dir}" and the like are filled in per workspace)
HOSTILE: tuple[str, ...] = (
    "nan", "inf", "-inf", "-1", "0", "1e309", "1e300", "-1e300", "9" * 5000, "", " ", "0x10", "1_000",
    UNDECODABLE, "/proc/x", "/proc/self/status", "{out}/nonexistent/x", "{dir}", "{fifo}", "/dev/zero",
    "{out}/new.file", "\u00e9\u20ac", "a=b=c", "synth://imu?rate=nan",
)

#: the environment's settings variables that are not ``[section] key`` settings
NOT_SETTINGS = ("PERFCAP_SIM_TOKEN",)

FAST_IMU = "synth://imu?realtime=false&duration=0.2"

#: a quick, valid run of each command; a case changes one flag or argument of it ("{...}": the workspace)
BASES: dict[str, list[str]] = {
    "record": ["record", "-q", "-d", FAST_IMU, "-o", "{out}/r.mcap"],
    "replay": ["replay", "{session}", "--fast", "-q"],
    "info": ["info", "{session}"],
    "export": ["export", "{session}", "--format", "csv", "-o", "{out}/e"],
    "serve": ["serve", "-q", "--port", "0", "--control-port", "-1", "--no-mdns", "--no-tls",
              "--state-dir", "{state}", "--sessions-dir", "{out}", "--duration", "0.05"],
    "demo": ["demo", "-q", "--duration", "0.5", "-o", "{out}/demo.mcap"],
    "puppet": ["puppet", "--input", "{traj}", "-q"],
    "cycle": ["cycle", "{cyc}"],
    "devices": ["devices"],
    "doctor": ["doctor"],
    "calibrate": ["calibrate", "--list", "--calibration-dir", "{out}/cal"],
    "sim serial": ["sim", "serial", "--duration", "0.05"],
    "sim phone": ["sim", "phone", "--url", "ws://127.0.0.1:9/ws/phone", "--token", "t", "--duration", "0.05"],
}

#: commands that start other processes or wait on the network: the campaign's, not CI's
SLOW_COMMANDS = ("demo", "sim phone")


@dataclass(frozen=True)
class Case:
    """One run: ``argv`` (with workspace placeholders), an environment to add, a config file's text."""

    what: str
    argv: tuple[str, ...]
    env: tuple[tuple[str, str], ...] = ()
    toml: str | None = None


@dataclass
class Outcome:
    case: Case
    code: int
    out: str
    err: str
    interrupted: bool
    problems: list[str] = field(default_factory=list)


# -- the cases ----------------------------------------------------------------------------------------
def _sub_parsers() -> dict[str, argparse.ArgumentParser]:
    from capture.app.cli import build_parser
    from sim_devices import phone_client, serial_sim

    top = build_parser()
    sub = next(a for a in top._actions if isinstance(a, argparse._SubParsersAction))
    parsers = dict(sub.choices)
    del parsers["sim"]
    for name, module in (("sim serial", serial_sim), ("sim phone", phone_client)):
        if hasattr(module, "build_parser"):   # (a perfcap before the sweep: its simulators are not walked)
            parsers[name] = module.build_parser()
    return parsers


def _with(base: list[str], parser: argparse.ArgumentParser, action: argparse.Action, value: str | None) -> list[str]:
    """``base`` with ``action`` given ``value`` (replacing it, and anything exclusive with it)."""
    n_lead = 2 if base[0] == "sim" else 1
    lead, rest = base[:n_lead], base[n_lead:]
    drop = {action}
    for g in parser._mutually_exclusive_groups:
        if action in g._group_actions:
            drop |= set(g._group_actions)
    flags = {s: a for a in parser._actions for s in a.option_strings}
    kept: list[str] = []
    positionals: list[str] = []
    i = 0
    while i < len(rest):
        tok = rest[i]
        a = flags.get(tok)
        if a is None:
            positionals.append(tok)
            i += 1
            continue
        takes = a.nargs != 0
        if a not in drop:
            kept += rest[i:i + (2 if takes else 1)]
        i += 2 if takes else 1
    if action.option_strings:
        extra = [action.option_strings[-1]] + ([] if value is None else [value])
        return lead + positionals + kept + extra
    pos_actions = [a for a in parser._actions if not a.option_strings]
    idx = pos_actions.index(action)
    positionals = positionals + [""] * (idx + 1 - len(positionals))
    positionals[idx] = value or ""
    return lead + positionals + kept


def flag_cases() -> list[Case]:
    """Every flag and positional argument of every command with every hostile value (flags without a
    value: given once)."""
    cases = []
    for name, parser in _sub_parsers().items():
        base = BASES[name]
        cases.append(Case(f"{name}: as is", tuple(base)))
        for action in parser._actions:
            if isinstance(action, argparse._HelpAction | argparse._VersionAction):
                continue
            label = action.option_strings[-1] if action.option_strings else action.dest
            if name == "sim serial" and action.dest in ("what", "args"):
                continue
            if action.option_strings and action.nargs == 0:
                cases.append(Case(f"{name} {label}", tuple(_with(base, parser, action, None))))
                continue
            for v in HOSTILE:
                cases.append(Case(f"{name} {label} {v[:20]!r}", tuple(_with(base, parser, action, v))))
    return cases


def _toml_values() -> list[str]:
    return ["nan", "inf", "-inf", "-1", "0", "1e300", "9" * 30, "'x'", "''", "'\\u0000'", "'/proc/x'",
            "'{out}/nonexistent/x'", "true", "[]", "[1, 2]", "{}", "{ a = 1 }", "1979-05-27T07:32:00Z", "'\\ud800'"]


def config_cases() -> list[Case]:
    """Config files: every key of every section with hostile values, unknown keys and sections, deep nesting,
    odd device entries, huge and binary files."""
    from capture.app.config import SECTIONS
    from capture.app.schema import setting_fields

    base = (*tuple(BASES["record"]), "--config", "{out}/c.toml")
    texts: list[tuple[str, str]] = []
    for sec, cls in SECTIONS.items():
        for f, _ in setting_fields(cls):
            texts += [(f"[{sec}] {f.name} = {v[:12]}", f"[{sec}]\n{f.name} = {v}\n") for v in _toml_values()]
        texts.append((f"[{sec}] unknown key", f"[{sec}]\nno_such_key = 1\n"))
        texts.append((f"{sec} = 1", f"{sec} = 1\n"))
    for depth in (10, 100, 500, 1000, 5000, 50_000):
        texts.append((f"nested arrays {depth}", "a = " + "[" * depth + "]" * depth + "\n"))
        texts.append((f"nested tables {depth}", "a = " + "{b = " * depth + "1" + "}" * depth + "\n"))
        texts.append((f"dotted key {depth}", "[bus]\n" + ".".join(["k"] * depth) + " = 1\n"))
        texts.append((f"nested options {depth}", "[[devices]]\nurl = 'synth://imu'\noptions = { rate = "
                      + "[" * min(depth, 900) + "]" * min(depth, 900) + " }\n"))
    texts += [
        ("unknown section", "[nope]\nx = 1\n"),
        ("devices string", "devices = 'synth://imu'\n"),
        ("devices bad", "devices = ['x', 3]\n"),
        ("device nan rate", "[[devices]]\nurl = 'synth://imu'\noptions = { rate = nan }\n"),
        ("device inf rate", "[[devices]]\nurl = 'synth://imu'\noptions = { rate = inf }\n"),
        ("device list rate", "[[devices]]\nurl = 'synth://imu'\noptions = { rate = [1] }\n"),
        ("device nul url", "[[devices]]\nurl = 'synth://imu\\u0000'\n"),
        ("device name", "[[devices]]\nname = '../x'\nurl = 'synth://imu'\n"),
        ("huge int", "[bus]\nlive_queue = " + "9" * 5000 + "\n"),
        ("huge file", "# " + "x" * (8 << 20) + "\n"),
        ("binary", "\x00\x01\x02\udcff"),
        ("bom", "\ufeff[bus]\nlive_queue = 5\n"),
    ]
    return [Case(f"config: {what}", base, toml=text) for what, text in texts]


def env_cases() -> list[Case]:
    """``PERFCAP_*`` variables: every setting with hostile values, misspelt and unknown names."""
    from capture.app.config import SECTIONS
    from capture.app.schema import setting_fields

    base = tuple(BASES["record"])
    cases = []
    values = ["nan", "inf", "-1", "0", "1e309", "9" * 5000, "", " ", "x", UNDECODABLE, "/proc/x", "{out}/nonexistent/x"]
    for sec, cls in SECTIONS.items():
        for f, _ in setting_fields(cls):
            var = f"PERFCAP_{sec.upper()}_{f.name.upper()}"
            cases += [Case(f"env {var}={v[:12]!r}", base, env=((var, v),)) for v in values]
    for var in ("PERFCAP_RECORDER_MAX_LOSS", "PERFCAP_RECORDR_MAX_LOSS_S", "PERFCAP_MAX_LOSS_S", "PERFCAP_",
                "PERFCAP_X", "PERFCAP_SERVE", "PERFCAP_BUS__LIVE_QUEUE", "PERFCAP_SIM_TOKN"):
        cases.append(Case(f"env {var}", base, env=((var, "1"),)))
    return cases


def all_cases(include_slow: bool = False) -> list[Case]:
    cases = flag_cases() + config_cases() + env_cases()
    if not include_slow:
        cases = [c for c in cases if not any(c.what.startswith(f"{s} ") or c.what.startswith(f"{s}:")
                                             for s in SLOW_COMMANDS)]
    return cases


# -- the workspace ------------------------------------------------------------------------------------
class Workspace:
    """Files the cases refer to: a short session, a trajectory, a looping CSV, a FIFO, a folder, an output
    folder (checked for leftovers) and the service's state folder."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.out = root / "out"
        self.out.mkdir()
        (root / "dir").mkdir()
        os.mkfifo(root / "fifo")
        self.state = root / "state"
        self.values = {"{out}": str(self.out), "{dir}": str(root / "dir"), "{fifo}": str(root / "fifo"),
                       "{state}": str(self.state), "{session}": str(root / "session.mcap"),
                       "{traj}": str(root / "traj.csv"), "{cyc}": str(root / "cyc.csv")}
        self._trajectory(root / "traj.csv")
        self._loops(root / "cyc.csv")
        made = run_case(self, Case("make the session", ("record", "-q", "-d", FAST_IMU, "-o", "{session}")))
        if made.code != 0:
            raise RuntimeError(f"cannot record the sweep's session: {made.err}")

    @staticmethod
    def _trajectory(path: Path) -> None:
        rows = ["t,px,py,pz,qw,qx,qy,qz,touch"]
        rows += [f"{i / 60:.4f},0,1,0,1,0,0,0,{1 if 10 < i < 50 else 0}" for i in range(60)]
        path.write_text("\n".join(rows) + "\n")

    @staticmethod
    def _loops(path: Path) -> None:
        import math

        rows = ["t,a,b"] + [f"{i / 100:.3f},{math.sin(i / 100 * 2 * math.pi):.5f},{math.cos(i / 50 * math.pi):.5f}"
                            for i in range(600)]
        path.write_text("\n".join(rows) + "\n")

    def fill(self, text: str) -> str:
        for k, v in self.values.items():
            text = text.replace(k, v)
        return text

    def listing(self) -> set[str]:
        return {str(p.relative_to(self.out)) for p in self.out.rglob("*")}

    def clean(self) -> None:
        import shutil

        for p in self.out.iterdir():
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()


@contextlib.contextmanager
def _environment(add: dict[str, str]) -> Iterator[None]:
    """This process's environment with ``add`` and without the user's own ``PERFCAP_*`` settings."""
    saved = dict(os.environ)
    try:
        for k in [k for k in os.environ if k.startswith("PERFCAP_")]:
            del os.environ[k]
        os.environ.update(add)
        yield
    finally:
        os.environ.clear()
        os.environ.update(saved)


def run_case(ws: Workspace, case: Case, interrupt_after_s: float = 5.0) -> Outcome:
    """``case`` run in this process (a Ctrl-C after ``interrupt_after_s`` for one that was accepted and
    runs on), checked."""
    from capture.app.cli import main

    argv = [ws.fill(a) for a in case.argv]
    if case.toml is not None:
        Path(ws.fill("{out}/c.toml")).write_bytes(ws.fill(case.toml).encode("utf-8", "surrogateescape"))
    before = ws.listing()
    out, err = io.StringIO(), io.StringIO()
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    fired = threading.Event()

    def interrupt() -> None:
        fired.set()
        os.kill(os.getpid(), signal.SIGINT)

    timer = threading.Timer(interrupt_after_s, interrupt)
    root = logging.getLogger()
    saved_handlers, saved_level = root.handlers[:], root.level
    root.handlers = []                       # main's basicConfig then logs to this run's stderr
    stdin, cwd = sys.stdin, os.getcwd()
    code: int
    try:
        sys.stdin = io.StringIO("")
        os.chdir(ws.out)                     # relative outputs land where leftovers are looked for
        with _environment({k: ws.fill(v) for k, v in case.env}), contextlib.redirect_stdout(out), \
                contextlib.redirect_stderr(err):
            timer.start()
            try:
                code = main(argv)
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            except KeyboardInterrupt:
                code = 130
            finally:
                timer.cancel()
    finally:
        sys.stdin = stdin
        os.chdir(cwd)
        root.handlers, root.level = saved_handlers, saved_level
        for s, h in handlers.items():
            signal.signal(s, h)
    res = Outcome(case, code, out.getvalue(), err.getvalue(), fired.is_set())
    res.problems = check(res)
    if code == 2:
        new = ws.listing() - before - {"c.toml"}
        if new:
            res.problems.append(f"exit 2 left files behind: {sorted(new)}")
    ws.clean()
    return res


def check(res: Outcome) -> list[str]:
    """What is wrong with an outcome (nothing: it is a clean 0, 1 or 2)."""
    problems = []
    allowed = {0, 1, 2} | ({130} if res.interrupted else set())
    if res.code not in allowed:
        problems.append(f"exit {res.code}")
    if "Traceback" in res.err or "Traceback" in res.out:
        problems.append("a traceback")
    if "internal error" in res.err:
        problems.append("an internal error")
    if res.code == 2:
        lines = [ln for ln in res.err.splitlines() if ln.strip()]
        if len(lines) != 1 or not lines[0].startswith("perfcap: error: "):
            problems.append(f"exit 2 said in {len(lines)} lines, not one 'perfcap: error:' line")
    return problems


def sample(cases: list[Case], n: int, seed: int) -> list[Case]:
    """``n`` cases drawn with ``seed``, every command's 'as is' run among them."""
    rng = random.Random(seed)
    keep = [c for c in cases if c.what.endswith(": as is")]
    rest = [c for c in cases if c not in keep]
    return keep + rng.sample(rest, min(max(n - len(keep), 0), len(rest)))


def main(argv: list[str] | None = None) -> int:
    import time

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", type=int, default=0, help="how many (default: all)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--only", help="cases whose label starts with this")
    p.add_argument("--slow", action="store_true", help="also demo and sim phone (other processes, network)")
    p.add_argument("--exclude", action="append", default=[], metavar="VALUE",
                   help="leave out the cases given this value (e.g. {fifo} for a perfcap that blocks on one)")
    p.add_argument("-v", "--verbose", action="store_true", help="print every failing case's stderr")
    a = p.parse_args(argv)
    cases = all_cases(include_slow=a.slow)
    if a.exclude:
        cases = [c for c in cases if not any(x in c.argv or any(x == v for _, v in c.env) for x in a.exclude)]
    if a.only:
        cases = [c for c in cases if c.what.startswith(a.only)]
    if a.cases:
        cases = sample(cases, a.cases, a.seed)
    codes: dict[int, int] = {}
    bad: list[Outcome] = []
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="perfcap-sweep-") as tmp:
        ws = Workspace(Path(tmp))
        for c in cases:
            if a.verbose:
                print(f".... {c.what}", flush=True)
            r = run_case(ws, c)
            codes[r.code] = codes.get(r.code, 0) + 1
            if r.problems:
                bad.append(r)
                print(f"FAIL {c.what}: {'; '.join(r.problems)}", flush=True)
                if a.verbose:
                    print("     " + "\n     ".join(r.err.strip().splitlines()[-4:]), flush=True)
            elif r.interrupted:
                print(f"INTERRUPTED {c.what}: exit {r.code} after a Ctrl-C", flush=True)
    internal = sum(1 for r in bad if r.code == 70 or "internal error" in r.problems)
    print(f"cases {len(cases)} in {time.monotonic() - t0:.1f} s; exits "
          + ", ".join(f"{k}: {v}" for k, v in sorted(codes.items()))
          + f"; failing {len(bad)} (internal errors {internal})")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
