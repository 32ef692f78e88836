"""The generic session check (``tests/generic_mcap_check.py``) stands for a viewer with no perfcap code: it
imports nothing of perfcap's, by any route."""

from __future__ import annotations

import ast
from pathlib import Path

PROJECT = ("capture", "devices", "cycles", "retarget", "sim_devices")


def test_the_generic_check_imports_no_perfcap_code() -> None:
    tree = ast.parse((Path(__file__).parent / "generic_mcap_check.py").read_text())
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names.append(node.module or "")
        elif isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", "")) in (
                "__import__", "import_module"):
            names.append("dynamic import")
    assert names and not [n for n in names if n.split(".")[0] in PROJECT or n == "dynamic import"], names
