"""``perfcap sim NAME``: a simulated device served as a real one is (a serial IMU on a pty, a phone on
the network), from the ``perfcap.sims`` entry points, so perfcap itself never imports a simulator."""

from __future__ import annotations

import argparse
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, cast

from capture.errors import ConfigError

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from capture.app.cli.common import Subcommands

SIMS_GROUP = "perfcap.sims"


def add_parser(sub: Subcommands) -> None:
    sm = sub.add_parser("sim", help="serve a simulated device (perfcap sim serial --help)", add_help=False)
    sm.add_argument("what", metavar="DEVICE", help="serial")
    sm.add_argument("args", nargs=argparse.REMAINDER)
    sm.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    sims = {ep.name: ep for ep in entry_points(group=SIMS_GROUP)}
    if args.what not in sims:
        raise ConfigError(f"no simulator {args.what!r}; known: {', '.join(sorted(sims)) or 'none'}"
                          " (is perfcap installed with pip install -e .?)")
    main = sims[args.what].load()
    if not callable(main):
        raise ConfigError(f"the {args.what!r} simulator's entry point is not a command")
    return int(cast("Callable[[Sequence[str]], int]", main)(args.args))
