"""``perfcap doctor``: which capture devices are present, which cannot be opened and why, with the fix
(permissions, udev rules, drivers, a device busy in another program)."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

from capture.app.cli.common import out

if TYPE_CHECKING:
    import argparse

    from capture.app.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    dr = sub.add_parser("doctor", help="which capture devices are present, which cannot be opened and why")
    dr.add_argument("--udev", action="store_true", help="print perfcap's udev rules file and where it goes")
    dr.add_argument("--json", action="store_true", help="one JSON object")
    dr.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from devices.doctor import RULES_NAME, diagnose, udev_rules

    if args.udev:
        out(udev_rules().rstrip())
        out(f"# save as /etc/udev/rules.d/{RULES_NAME}, then: sudo udevadm control --reload-rules &&"
            " sudo udevadm trigger, and replug the device")
        return 0
    rep = diagnose()
    if args.json:
        out(json.dumps(rep.as_dict(), indent=2))
        return 0 if rep.ok else 1
    if rep.usb:
        out(f"USB: {len(rep.usb)} device(s); known to perfcap: "
            + (", ".join(f"{u['known_as']} [{u['vid_pid']}]" for u in rep.usb if u["known_as"]) or "none"))
    for f in rep.findings:
        mark = "ok  " if f.ok else "FAIL"
        out(f"{mark} {f.what} at {f.where}" + (f" -> {f.kind}@{f.url}" if f.ok and f.kind and f.url else ""))
        if not f.ok:
            out(f"     problem: {f.problem}")
            for line in f.fix.splitlines():
                out(f"     {line}")
    for n in rep.notes:
        out(f"note: {n}")
    return 0 if rep.ok else 1
