"""Shared by the CLI tests: run ``perfcap`` in-process and read what it printed."""

from __future__ import annotations

from typing import Any

from capture.app.cli import main


def run(capsys: Any, *argv: str) -> tuple[int, str, str]:
    """``perfcap ARGV`` in this process: (exit code, stdout, stderr); never a traceback in either."""
    try:
        code = main(list(argv))
    except SystemExit as exc:   # argparse's usage errors
        # as the interpreter exits: None is 0, an int is itself, anything else (a message) is 1
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    o = capsys.readouterr()
    assert "Traceback" not in o.err and "Traceback" not in o.out, o.err
    return code, o.out, o.err


def one_line(text: str) -> str:
    """The only non-blank line of ``text`` (asserts there is exactly one)."""
    lines = [ln for ln in text.splitlines() if ln.strip()]
    assert len(lines) == 1, text
    return lines[0]
