"""Architecture rules (STYLE.md R1): production code never imports sim_devices; the kernel imports
nothing else from the project; cycles/retarget see only samples (and the quaternion maths)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("capture", "devices", "cycles", "retarget", "sim_devices")


def imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name.split(".")[0] if a.name.split(".")[0] not in PACKAGES else a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
    return out


def project_imports(pkg: str) -> dict[str, set[str]]:
    res = {}
    for f in (ROOT / pkg).rglob("*.py"):
        res[str(f.relative_to(ROOT))] = {m for m in imports(f) if m.split(".")[0] in PACKAGES}
    return res


def test_production_code_never_imports_sim_devices():
    for pkg in ("capture", "devices", "cycles", "retarget"):
        for f, mods in project_imports(pkg).items():
            assert not any(m.startswith("sim_devices") for m in mods), f"{f} imports sim_devices"


def test_kernel_imports_only_kernel():
    kernel = {"capture.sample", "capture.clock", "capture.errors", "capture.clocksync", "capture.quat"}
    for name in kernel:
        f = ROOT / (name.replace(".", "/") + ".py")
        mods = {m for m in imports(f) if m.split(".")[0] in PACKAGES}
        assert mods <= kernel, f"{name} imports {mods - kernel}"


def test_cycles_and_retarget_see_only_samples():
    for pkg in ("cycles", "retarget"):
        for f, mods in project_imports(pkg).items():
            assert mods <= {"capture.sample", "capture.errors", "capture.quat"} | {m for m in mods if m.startswith(pkg)}, f


def test_only_clock_reads_the_os_clock():
    allowed = {"capture/clock.py", "capture/app/cli/__init__.py"}
    for pkg in ("capture", "devices", "sim_devices", "cycles", "retarget"):
        for f in (ROOT / pkg).rglob("*.py"):
            rel = str(f.relative_to(ROOT))
            if rel in allowed:
                continue
            text = f.read_text()
            for call in ("time.monotonic", "time.time(", "time.perf_counter", "datetime.now"):
                assert call not in text, f"{rel} reads the OS clock ({call})"


def test_quaternion_maths_lives_in_one_place():
    """One concept, one place (STYLE.md): the Hamilton product is written only in capture/quat.py."""
    for pkg in ("capture", "devices", "cycles", "retarget", "sim_devices"):
        for f in (ROOT / pkg).rglob("*.py"):
            rel = str(f.relative_to(ROOT))
            if rel == "capture/quat.py":
                continue
            tree = ast.parse(f.read_text(), rel)
            defs = {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
            assert not defs & {"quat_mul", "qmul", "_qmul", "quat_slerp", "qslerp", "quat_rotate"}, rel
