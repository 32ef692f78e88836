"""Architecture rules (docs/architecture.md), checked on the syntax tree of every product module.

The layers, each importing only from the layers below it::

    capture.app                              application: the only place that wires packages together
    devices, cycles, retarget, sim_devices   domain (never import capture.app)
    capture (outside capture.app)            core: imports only capture.*
    capture.{sample,clock,errors,quat,clocksync}   kernel: imports nothing else from the project

cycles and retarget see only the kernel; no product code reaches sim_devices by any route (an import,
importlib, or loading an entry point outside the scheme and simulator registries); only ``Clock``
reads the OS clock, whatever the module is imported as. Each rule is a function returning its
violations, and each is shown failing on a module written to break it.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("capture", "devices", "cycles", "retarget", "sim_devices")
PRODUCT = ("capture", "devices", "cycles", "retarget")
KERNEL = frozenset({"capture.sample", "capture.clock", "capture.errors", "capture.quat", "capture.clocksync"})
#: modules that may load plugins by entry point: the transport, device-kind and simulator registries
REGISTRIES = frozenset({"devices/__init__.py", "devices/transports/__init__.py", "capture/app/cli/sim.py"})
CLOCK_MODULE = "capture/clock.py"
#: what reads the OS clock: functions of ``time`` and the "now" constructors of ``datetime``
TIME_READS = frozenset({"time", "time_ns", "monotonic", "monotonic_ns", "perf_counter", "perf_counter_ns",
                        "process_time", "process_time_ns", "thread_time", "thread_time_ns", "clock_gettime",
                        "clock_gettime_ns", "localtime", "gmtime", "ctime", "asctime", "strftime"})
DATETIME_READS = frozenset({"now", "utcnow", "today"})


@dataclass(frozen=True)
class Module:
    rel: str          # path from the project root, e.g. "capture/bus.py"
    name: str         # dotted name, e.g. "capture.bus"
    tree: ast.Module

    @classmethod
    def parse(cls, rel: str, text: str) -> Module:
        name = rel[:-3].replace("/", ".").removesuffix(".__init__")
        return cls(rel, name, ast.parse(text, rel))


def product_modules(packages: tuple[str, ...] = PACKAGES) -> list[Module]:
    mods = []
    for pkg in packages:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            rel = f.relative_to(ROOT).as_posix()
            mods.append(Module.parse(rel, f.read_text(encoding="utf-8")))
    return mods


def _called_name(call: ast.Call) -> str:
    f = call.func
    return f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""


def _constant_text(node: ast.AST) -> str | None:
    """A string the code spells out: a literal, or literals joined with ``+`` (``"sim" + "_devices"``)."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add):
        a, b = _constant_text(node.left), _constant_text(node.right)
        return None if a is None or b is None else a + b
    return None


#: calls that import a module named by a string
IMPORT_CALLS = frozenset({"import_module", "__import__", "resolve_name", "run_module", "find_spec"})


def project_imports(m: Module) -> set[str]:
    """The project modules ``m`` imports (absolute or relative, at any depth of the file, by statement or
    by a call such as ``importlib.import_module("devices.base")``)."""
    out: set[str] = set()
    importers = set(IMPORT_CALLS)   # and what they are called here: `from importlib import import_module as im`
    for node in ast.walk(m.tree):
        if isinstance(node, ast.ImportFrom) and node.module in ("importlib", "pkgutil", "runpy"):
            importers |= {a.asname for a in node.names if a.name in IMPORT_CALLS and a.asname}
        elif isinstance(node, ast.Assign) and isinstance(node.value, ast.Attribute | ast.Name):
            leaf = node.value.attr if isinstance(node.value, ast.Attribute) else node.value.id
            if leaf in IMPORT_CALLS:
                importers |= {t.id for t in node.targets if isinstance(t, ast.Name)}
    for node in ast.walk(m.tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = m.name.split(".")
                if not m.rel.endswith("__init__.py"):
                    base = base[:-1]
                base = base[: len(base) - node.level + 1]
                mod = ".".join([*base, node.module] if node.module else base)
            else:
                mod = node.module or ""
            out.add(mod)
            out |= {f"{mod}.{a.name}" for a in node.names}  # `from capture import app` imports capture.app
        elif isinstance(node, ast.Call) and _called_name(node) in importers and node.args:
            name = _constant_text(node.args[0])
            if name is not None:
                out.add(name.replace(":", "."))
    return {i for i in out if i.split(".")[0] in PACKAGES}


def _within(mod: str, pkg: str) -> bool:
    return mod == pkg or mod.startswith(pkg + ".")


# -- the rules ------------------------------------------------------------------------------------------
def core_imports_only_capture(m: Module) -> list[str]:
    if not _within(m.name, "capture") or _within(m.name, "capture.app"):
        return []
    return [f"{m.rel} imports {i}" for i in sorted(project_imports(m))
            if not _within(i, "capture") or _within(i, "capture.app")]


def domain_never_imports_the_app(m: Module) -> list[str]:
    if _within(m.name, "capture"):
        return []
    return [f"{m.rel} imports {i}" for i in sorted(project_imports(m)) if _within(i, "capture.app")]


def cycles_and_retarget_see_only_the_kernel(m: Module) -> list[str]:
    pkg = m.name.split(".")[0]
    if pkg not in ("cycles", "retarget"):
        return []
    return [f"{m.rel} imports {i}" for i in sorted(project_imports(m))
            if not _within(i, pkg) and not any(_within(i, k) for k in KERNEL)
            and i != "capture"]   # `from capture.quat import ...` also records "capture.quat.<name>"


def devices_see_only_the_core(m: Module) -> list[str]:
    """Device kinds, transports and codecs build on the core, never on the puppet or cycles."""
    if not _within(m.name, "devices"):
        return []
    return [f"{m.rel} imports {i}" for i in sorted(project_imports(m))
            if not (_within(i, "devices") or (_within(i, "capture") and not _within(i, "capture.app")))]


def transports_never_import_codecs_or_kinds(m: Module) -> list[str]:
    """A transport is a byte pipe: it knows nothing of what the bytes mean."""
    if not _within(m.name, "devices.transports"):
        return []
    return [f"{m.rel} imports {i}" for i in sorted(project_imports(m))
            if _within(i, "devices") and not (_within(i, "devices.transports") or _within(i, "devices.options")
                                             or i == "devices")]


def simulators_see_only_the_core_and_devices(m: Module) -> list[str]:
    """Simulators encode through the devices' codecs and read sessions; they never reach the app, cycles
    or the puppet."""
    if not _within(m.name, "sim_devices"):
        return []
    return [f"{m.rel} imports {i}" for i in sorted(project_imports(m))
            if not (_within(i, "sim_devices") or _within(i, "devices")
                    or (_within(i, "capture") and not _within(i, "capture.app")))]


def kernel_imports_only_the_kernel(m: Module) -> list[str]:
    if m.name not in KERNEL:
        return []
    return [f"{m.rel} imports {i}" for i in sorted(project_imports(m))
            if not any(_within(i, k) for k in KERNEL) and i != "capture"]


def _docstrings(tree: ast.Module) -> set[int]:
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                ids.add(id(first.value))
    return ids


#: the one entry-point group each registry may load
REGISTRY_GROUPS = {"devices/__init__.py": "perfcap.devices", "devices/transports/__init__.py": "perfcap.transports",
                   "capture/app/cli/sim.py": "perfcap.sims"}


def _module_constants(tree: ast.Module) -> dict[str, str]:
    out = {}
    for node in tree.body:
        if isinstance(node, ast.Assign | ast.AnnAssign) and node.value is not None:
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            text = _constant_text(node.value)
            for t in targets:
                if isinstance(t, ast.Name) and text is not None:
                    out[t.id] = text
    return out


def product_never_reaches_sim_devices(m: Module) -> list[str]:
    if _within(m.name, "sim_devices"):
        return []
    bad = [f"{m.rel} imports {i}" for i in sorted(project_imports(m)) if _within(i, "sim_devices")]
    docs = _docstrings(m.tree)
    consts = _module_constants(m.tree)
    group = REGISTRY_GROUPS.get(m.rel)
    for node in ast.walk(m.tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs \
                and "sim_devices" in node.value:
            bad.append(f"{m.rel}:{node.lineno} names sim_devices in code ({node.value[:40]!r})")
        names_ep = (isinstance(node, ast.Name) and node.id in ("entry_points", "EntryPoint", "EntryPoints")) or (
            isinstance(node, ast.Attribute) and node.attr in ("entry_points", "EntryPoint", "EntryPoints"))
        if names_ep and group is None:
            bad.append(f"{m.rel}:{node.lineno} reaches entry points: only the registries may")
        if not isinstance(node, ast.Call):
            continue
        called = _called_name(node)
        if called == "entry_points" and group is not None:
            given = [k.value for k in node.keywords if k.arg == "group"]
            text = None
            if len(given) == 1:
                v = given[0]
                text = _constant_text(v) if not isinstance(v, ast.Name) else consts.get(v.id)
            if text != group:
                bad.append(f"{m.rel}:{node.lineno} loads entry points of another group than {group}")
        if called in IMPORT_CALLS and group is None and not (node.args and _constant_text(node.args[0])):
            bad.append(f"{m.rel}:{node.lineno} imports a module named at run time: only the registries may")
    return bad


def _is_time_module(node: ast.AST, time_names: set[str]) -> bool:
    """``time`` under any name: an alias, ``importlib.import_module("time")``, ``sys.modules["time"]``."""
    if isinstance(node, ast.Name):
        return node.id in time_names
    if isinstance(node, ast.Call) and _called_name(node) in IMPORT_CALLS and node.args:
        return _constant_text(node.args[0]) == "time"
    if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Attribute) and node.value.attr == "modules":
        return _constant_text(node.slice) == "time"
    return False


def only_clock_reads_the_os_clock(m: Module) -> list[str]:
    if m.rel == CLOCK_MODULE:
        return []
    time_names: set[str] = set()       # what the time module is called here
    datetime_names: set[str] = set()   # ... and the datetime module, and its datetime/date classes
    bad = []
    nodes = list(ast.walk(m.tree))
    for node in nodes:
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name == "time":
                    time_names.add(a.asname or "time")
                elif a.name == "datetime":
                    datetime_names.add(a.asname or "datetime")
                elif a.name == "timeit":
                    bad.append(f"{m.rel}:{node.lineno} imports timeit (its timers read the OS clock)")
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module in ("time", "datetime", "timeit"):
            for a in node.names:
                if node.module == "timeit" or (node.module == "time" and (a.name in TIME_READS or a.name == "*")):
                    bad.append(f"{m.rel}:{node.lineno} imports {node.module}.{a.name}")
                elif node.module == "datetime" and a.name in ("datetime", "date", "*"):
                    datetime_names.add(a.asname or a.name)
    for _ in range(3):   # names bound to those: `clk = time`, `d = datetime.datetime`, `t = import_module("time")`
        for node in nodes:
            if isinstance(node, ast.Assign):
                targets = [t.id for t in node.targets if isinstance(t, ast.Name)]
                if _is_time_module(node.value, time_names):
                    time_names.update(targets)
                elif (isinstance(node.value, ast.Name) and node.value.id in datetime_names) or (
                        isinstance(node.value, ast.Attribute) and isinstance(node.value.value, ast.Name)
                        and node.value.value.id in datetime_names and node.value.attr in ("datetime", "date")):
                    datetime_names.update(targets)
    for node in nodes:
        if isinstance(node, ast.Call) and _called_name(node) == "getattr" and node.args \
                and _is_time_module(node.args[0], time_names):
            bad.append(f"{m.rel}:{node.lineno} reads the time module by name")
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "time" \
                and not node.args:
            owner = node.func.value   # an event loop's clock: loop.time(), asyncio.get_running_loop().time()
            if (isinstance(owner, ast.Name) and "loop" in owner.id.lower()) or (
                    isinstance(owner, ast.Call) and _called_name(owner) in ("get_running_loop", "get_event_loop")):
                bad.append(f"{m.rel}:{node.lineno} reads the event loop's clock ({ast.unparse(node)})")
        if not isinstance(node, ast.Attribute):
            continue
        base = node.value
        if _is_time_module(base, time_names) and node.attr in TIME_READS:
            bad.append(f"{m.rel}:{node.lineno} reads the OS clock ({ast.unparse(node)})")
        elif node.attr in DATETIME_READS and (
                (isinstance(base, ast.Name) and base.id in datetime_names)
                or (isinstance(base, ast.Attribute) and isinstance(base.value, ast.Name)
                    and base.value.id in datetime_names and base.attr in ("datetime", "date"))):
            bad.append(f"{m.rel}:{node.lineno} reads the OS clock ({ast.unparse(node)})")
    return bad


RULES = [core_imports_only_capture, domain_never_imports_the_app, cycles_and_retarget_see_only_the_kernel,
         devices_see_only_the_core, transports_never_import_codecs_or_kinds, simulators_see_only_the_core_and_devices,
         kernel_imports_only_the_kernel, product_never_reaches_sim_devices, only_clock_reads_the_os_clock]


@pytest.mark.parametrize("rule", RULES, ids=lambda r: r.__name__)
def test_the_code_keeps_the_rule(rule):
    packages = PRODUCT if rule is product_never_reaches_sim_devices else PACKAGES
    bad = [v for m in product_modules(packages) for v in rule(m)]
    assert not bad, "\n".join(bad)


def test_the_kernel_exists_as_named():
    for name in KERNEL:
        assert (ROOT / (name.replace(".", "/") + ".py")).is_file(), name


# -- each rule fails when broken ------------------------------------------------------------------------
BROKEN = [
    (core_imports_only_capture, "capture/bus.py", "from devices import open_device\n"),
    (core_imports_only_capture, "capture/session.py", "def f():\n    from capture.app.config import load_config\n"),
    (core_imports_only_capture, "capture/orientation/fusion.py", "from ...retarget import skeleton\n"),
    (domain_never_imports_the_app, "devices/base.py", "import capture.app.orchestrator\n"),
    (domain_never_imports_the_app, "retarget/puppet.py", "from capture import app\n"),
    (cycles_and_retarget_see_only_the_kernel, "cycles/edit.py", "from capture.bus import SampleBus\n"),
    (cycles_and_retarget_see_only_the_kernel, "retarget/vmc.py", "from devices.base import Device\n"),
    (kernel_imports_only_the_kernel, "capture/sample.py", "from capture.session import SessionReader\n"),
    (core_imports_only_capture, "capture/bus.py", "import importlib\nm = importlib.import_module('devices.base')\n"),
    (core_imports_only_capture, "capture/bus.py", "m = __import__('retarget' + '.puppet')\n"),
    (domain_never_imports_the_app, "devices/base.py", "from importlib import import_module as im\nim('capture.app')\n"),
    (cycles_and_retarget_see_only_the_kernel, "cycles/edit.py", "import importlib\nload = importlib.import_module\n"
     "load('capture.bus')\n"),
    (devices_see_only_the_core, "devices/phone.py", "from retarget.puppet import PuppetRetargeter\n"),
    (devices_see_only_the_core, "devices/hid/generic.py", "import cycles\n"),
    (transports_never_import_codecs_or_kinds, "devices/transports/serialport.py", "import devices.codecs.witmotion\n"),
    (transports_never_import_codecs_or_kinds, "devices/transports/network.py", "from devices.phone import PhonePage\n"),
    (simulators_see_only_the_core_and_devices, "sim_devices/loops.py", "from cycles import extract\n"),
    (simulators_see_only_the_core_and_devices, "sim_devices/synth.py", "from capture.app.demo import DEMO_DEVICES\n"),
    (product_never_reaches_sim_devices, "capture/app/demo.py", "from sim_devices.phone_client import SimPagePhone\n"),
    (product_never_reaches_sim_devices, "capture/app/demo.py",
     "import importlib\nm = importlib.import_module('sim_devices.phone_client')\n"),
    (product_never_reaches_sim_devices, "capture/app/demo.py",
     "import importlib\nmod = ep.load().__module__\nm = importlib.import_module(mod)\n"),
    (product_never_reaches_sim_devices, "capture/app/demo.py",
     "from importlib.metadata import entry_points\nmain = entry_points(group='perfcap.sims')['phone'].load()\n"),
    (product_never_reaches_sim_devices, "devices/phone.py", "MOD = 'sim_devices.phone_sim'\n"),
    (product_never_reaches_sim_devices, "capture/app/demo.py",
     "from importlib.metadata import distribution\nep = distribution('perfcap').entry_points[0].load()\n"),
    (product_never_reaches_sim_devices, "capture/app/demo.py",
     "import importlib.metadata as md\neps = md.entry_points\nmain = eps(group='perfcap.sims')\n"),
    (product_never_reaches_sim_devices, "capture/app/demo.py",
     "from importlib.metadata import EntryPoint\nEntryPoint('p', 'x:main', 'perfcap.sims').load()\n"),
    (product_never_reaches_sim_devices, "capture/app/demo.py", "import pkgutil\nf = pkgutil.resolve_name(NAME)\n"),
    (product_never_reaches_sim_devices, "devices/__init__.py",
     "from importlib.metadata import entry_points\nsims = entry_points(group='perfcap.sims')\n"),
    (only_clock_reads_the_os_clock, "capture/recorder.py", "import time as _t\nt = _t.monotonic()\n"),
    (only_clock_reads_the_os_clock, "devices/base.py", "from time import perf_counter\n"),
    (only_clock_reads_the_os_clock, "capture/app/cli/record.py", "import time\nt = time.time()\n"),
    (only_clock_reads_the_os_clock, "capture/app/serve/tls.py",
     "import datetime as _dt\nnow = _dt.datetime.now(_dt.UTC)\n"),
    (only_clock_reads_the_os_clock, "sim_devices/synth.py", "from datetime import datetime as D\nD.utcnow()\n"),
    (only_clock_reads_the_os_clock, "capture/bus.py", "import timeit\nt = timeit.default_timer()\n"),
    (only_clock_reads_the_os_clock, "capture/bus.py", "from time import *\nt = monotonic()\n"),
    (only_clock_reads_the_os_clock, "capture/bus.py", "import time\nclk = time\nt = clk.monotonic_ns()\n"),
    (only_clock_reads_the_os_clock, "capture/bus.py", "import time\nt = getattr(time, 'monotonic')()\n"),
    (only_clock_reads_the_os_clock, "capture/bus.py", "import importlib\nt = importlib.import_module('time').time()\n"),
    (only_clock_reads_the_os_clock, "capture/bus.py", "import sys\nt = sys.modules['time'].perf_counter()\n"),
    (only_clock_reads_the_os_clock, "capture/app/cli/serve.py", "import asyncio\nasyncio.get_running_loop().time()\n"),
    (only_clock_reads_the_os_clock, "capture/app/cli/serve.py", "t0 = loop.time()\n"),
    (only_clock_reads_the_os_clock, "capture/bus.py", "import datetime\nd = datetime.datetime\nd.now()\n"),
]


@pytest.mark.parametrize(("rule", "rel", "code"), BROKEN, ids=[f"{r.__name__}:{p}" for r, p, _ in BROKEN])
def test_each_rule_fails_when_broken(rule, rel, code):
    assert rule(Module.parse(rel, code)), f"{rule.__name__} let this through in {rel}:\n{code}"


def test_what_the_rules_allow():
    """Sleeping is no clock read, a docstring may name sim_devices, the kernel may import itself."""
    assert not only_clock_reads_the_os_clock(Module.parse("capture/recorder.py", "import time\ntime.sleep(0)\n"))
    assert not product_never_reaches_sim_devices(
        Module.parse("devices/transports/__init__.py", '"""Simulators live in sim_devices."""\n'
                     "from importlib.metadata import entry_points\neps = entry_points(group='perfcap.transports')\n"))
    assert not kernel_imports_only_the_kernel(Module.parse("capture/clocksync.py", "from capture.sample import X\n"))
    assert not core_imports_only_capture(Module.parse("capture/app/demo.py", "from devices import open_device\n"))


def test_quaternion_maths_lives_in_one_place():
    """One concept, one place: the Hamilton product is written only in capture/quat.py."""
    for m in product_modules():
        if m.rel == "capture/quat.py":
            continue
        defs = {n.name for n in ast.walk(m.tree) if isinstance(n, ast.FunctionDef)}
        assert not defs & {"quat_mul", "qmul", "_qmul", "quat_slerp", "qslerp", "quat_rotate"}, m.rel


# -- docs/architecture.md stays true ----------------------------------------------------------------------
ARCHITECTURE = ROOT / "docs" / "architecture.md"


def named_paths(text: str) -> list[str]:
    """Every module or package path docs/architecture.md names: whole paths (``capture/app/cli/``), and
    in a table row the bare file names after the row's first path (``fusion.py`` of ``capture/orientation/``)."""
    import re

    out = []
    for line in text.splitlines():
        base: str | None = None
        for tok in re.findall(r"`([^`\s]+)`", line):
            if tok.split("/")[0] in PACKAGES and (tok.endswith((".py", "/"))):
                out.append(tok)
                if line.startswith("|") and base is None:
                    base = tok if tok.endswith("/") else tok.rsplit("/", 1)[0] + "/"
            elif line.startswith("|") and base is not None and re.fullmatch(r"[a-z_0-9]+\.py", tok):
                out.append(base + tok)
    return out


def test_the_architecture_page_names_only_what_exists():
    text = ARCHITECTURE.read_text(encoding="utf-8")
    names = named_paths(text)
    assert len(names) > 50
    missing = [n for n in names if not (ROOT / n).exists()]
    assert not missing, f"docs/architecture.md names what does not exist: {missing}"


def test_the_architecture_page_names_every_package():
    named = {n.rstrip("/") for n in named_paths(ARCHITECTURE.read_text(encoding="utf-8"))}
    packages = {p.parent.relative_to(ROOT).as_posix() for pkg in PACKAGES for p in (ROOT / pkg).rglob("__init__.py")}
    assert packages <= named, f"docs/architecture.md does not name {sorted(packages - named)}"


def test_named_paths_resolves_bare_names_in_a_row():
    row = "| `capture/orientation/` | the filter (`filter.py`) and `nothere.py` |"
    assert named_paths(row) == ["capture/orientation/", "capture/orientation/filter.py",
                                "capture/orientation/nothere.py"]

