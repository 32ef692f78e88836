"""What the simulators' command lines (``perfcap sim serial``, ``perfcap sim phone``) share: a parser
whose usage errors are one line, exit 2, as perfcap's own, and flag types through the one value parser
(``devices.options.Option.parse``: numbers finite and within range)."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING, Any, NoReturn

from devices.options import Option, arg_type

if TYPE_CHECKING:
    from collections.abc import Callable

#: the longest time a flag takes (about 31 years): beyond it, timers and waits overflow
MAX_SECONDS = 1e9


class SimParser(argparse.ArgumentParser):
    """A usage error is one line naming ``--help``, exit 2."""

    def error(self, message: str) -> NoReturn:
        print(f"perfcap: error: {self.prog}: {' '.join(message.split())} (see {self.prog} --help)", file=sys.stderr)
        raise SystemExit(2)


def number(lo: float | None, hi: float | None, *, above: bool = False) -> Callable[[str], Any]:
    """``type=`` of a finite number flag within ``[lo, hi]`` (``above``: ``lo`` itself excluded)."""
    return arg_type(Option(float, None, "number", min=lo, max=hi, min_exclusive=above))


def whole(lo: int, hi: int) -> Callable[[str], Any]:
    """``type=`` of a whole number flag within ``[lo, hi]``."""
    return arg_type(Option(int, None, "count", min=lo, max=hi))


SEED = whole(0, 2**63 - 1)
SECONDS = number(0, MAX_SECONDS, above=True)
SECONDS_OR_ZERO = number(0, MAX_SECONDS)
