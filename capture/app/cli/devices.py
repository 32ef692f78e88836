"""``perfcap devices``: the serial ports, HID devices and Linux input devices present, and the LSL streams that answer
within ``--lsl-timeout`` (each with the device string that opens it), the device kinds and the transports, with their
options."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

from capture.app.cli.common import out
from capture.errors import CaptureError

if TYPE_CHECKING:
    import argparse

    from capture.app.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    dv = sub.add_parser("devices", help="list serial ports, HID and input devices present, LSL streams, device kinds"
                        " and transports")
    dv.add_argument("--json", action="store_true", help="one JSON object")
    dv.add_argument("--lsl-timeout", type=float, default=1.0, metavar="S",
                    help="seconds to wait for LSL streams to answer (default 1; 0: do not look for them)")
    dv.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from devices import device_class, known_kinds, known_schemes
    from devices.options import describe
    from devices.transports import transport_class
    from devices.transports.evdev import list_input_devices
    from devices.transports.hid import list_hid_devices
    from devices.transports.lsl import list_lsl_streams
    from devices.transports.serialport import list_serial_ports

    ports = list_serial_ports()
    try:
        hids = list_hid_devices()
        hid_error = ""
    except CaptureError as exc:
        hids, hid_error = [], str(exc)
    try:
        inputs = list_input_devices()
        input_error = ""
    except CaptureError as exc:
        inputs, input_error = [], str(exc)
    lsl_error = "not looked for (--lsl-timeout 0)" if args.lsl_timeout <= 0 else ""
    try:
        streams = list_lsl_streams(args.lsl_timeout) if args.lsl_timeout > 0 else []
    except CaptureError as exc:
        streams, lsl_error = [], str(exc)
    if args.json:
        doc = {
            "serial_ports": [p.as_dict() for p in ports],
            "hid_devices": [h.as_dict() for h in hids],
            "input_devices": [i.as_dict() for i in inputs],
            **({"input_devices_error": input_error} if input_error else {}),
            "lsl_streams": [st.as_dict() for st in streams],
            **({"lsl_streams_error": lsl_error} if lsl_error else {}),
            "kinds": {k: {"description": device_class(k).description,
                          "options": {n: {"default": o.default, "help": o.help, "form": o.form()}
                                      for n, o in device_class(k).options.items()}} for k in known_kinds()},
            "transports": {sch: {"usage": transport_class(sch).usage,
                                 "options": {n: {"default": o.default, "help": o.help, "form": o.form()}
                                             for n, o in transport_class(sch).options.items()}}
                           for sch in known_schemes()},
        }
        out(json.dumps(doc, indent=2))
        return 0
    out("serial ports:")
    if not ports:
        out("  none found (a USB adapter plugged in shows up here; try perfcap sim serial for a simulated one)")
    for p in ports:
        what = p.adapter.chip if p.adapter else (p.description if p.description not in ("", "n/a") else
                                                 "built-in or unidentified UART")
        kinds = f"; likely {', '.join(p.adapter.kinds)}" if p.adapter and p.adapter.kinds else ""
        out(f"  {p.device}  [{p.vid_pid or 'no USB id'}] {what}{kinds}")
        out(f"      open as KIND@{p.url}")
        if p.latency_timer_ms and p.latency_timer_ms > 2:
            out(f"      note: FTDI latency timer is {p.latency_timer_ms} ms (readings arrive in bursts);"
                " low_latency=true (the default) asks for 1 ms")
        if p.adapter and p.adapter.note:
            out(f"      note: {p.adapter.note}")
    out("HID devices:")
    if hid_error:
        out(f"  cannot list them: {hid_error}")
    elif not hids:
        out("  none found (controllers, mice and tablets show up here; perfcap doctor explains one that does not;"
            " simhid://dualsense is a simulated one)")
    for h in hids:
        known = h.as_dict()["known_as"] or f"usage {h.usage_page:#06x}:{h.usage:#06x}"
        kind = f"; kind {h.likely_kind}" if h.likely_kind else ""
        out(f"  {h.vid_pid} {h.product or 'unnamed'} ({h.manufacturer or 'unknown maker'}) over {h.bus}: {known}{kind}")
        out(f"      open as {h.likely_kind or 'KIND'}@{h.url}" + ("" if h.serial_number else f"  or hid://path={h.path}"))
    out("input devices (Linux evdev: decoded by the kernel's drivers):")
    if input_error:
        out(f"  cannot list them: {input_error}")
    elif not inputs:
        out("  none found (pen tablets, touchpads, touchscreens and mice show up here when /dev/input/event* can be"
            " read: the 'input' group; simevdev:///PATH.events replays an evemu recording)")
    for i in inputs:
        out(f"  {i.path}  [{i.vid:04x}:{i.pid:04x}] {i.name or 'unnamed'}: {i.likely}; {i.summary()}")
        out(f"      open as {i.url}")
    out(f"LSL streams (answering within {args.lsl_timeout:g} s):")
    if lsl_error:
        out(f"  {lsl_error}")
    elif not streams:
        out("  none found (streams that other programs publish on Lab Streaming Layer show up here)")
    for st in streams:
        rate = f"{st.rate_hz:g} Hz" if st.rate_hz else "irregular rate"
        out(f"  {st.name or '(unnamed)'}  type {st.type or '-'}, {st.channels} x {st.format} at {rate};"
            f" source_id {st.source_id or '-'} on {st.host or '?'}")
        out(f"      open as {st.url}")
    out("device kinds (KIND@ in a device string):")
    for k in known_kinds():
        c = device_class(k)
        out(f"  {k}: {c.description}")
        if c.options:
            out(describe(c.options))
    out("transports (SCHEME://):")
    for sch in known_schemes():
        t = transport_class(sch)
        out(f"  {t.usage}")
        if t.options:
            out(describe(t.options))
    return 0
