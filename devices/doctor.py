"""``perfcap doctor``: which capture devices are plugged in, which ones perfcap cannot open, and why.

USB devices are listed with pyusb (when libusb is available), HID interfaces with hidapi and serial
ports with pyserial. For each device perfcap knows, the check says whether its device node can be
opened by this user, and if not, the udev rule that fixes it (the rules file perfcap ships, or a
one-line rule for that VID:PID).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

from devices.transports.hid import KNOWN_HID, HidDeviceInfo, hid_backend, known_hid, list_hid_devices
from devices.transports.serialport import known_adapter, list_serial_ports

RULES_NAME = "70-perfcap.rules"


def udev_rules() -> str:
    """The udev rules file shipped with perfcap."""
    return resources.files("devices.hid").joinpath("udev", RULES_NAME).read_text()


def rule_for(vid: int, pid: int, hidraw: bool = True) -> str:
    """A one-line udev rule granting the seat user (and plugdev) access to one VID:PID, USB and Bluetooth."""
    if hidraw:
        return (f'KERNEL=="hidraw*", ATTRS{{idVendor}}=="{vid:04x}", ATTRS{{idProduct}}=="{pid:04x}", MODE="0660",'
                f' GROUP="plugdev", TAG+="uaccess"\n'
                f'KERNEL=="hidraw*", KERNELS=="0005:{vid:04X}:{pid:04X}.*", MODE="0660", GROUP="plugdev",'
                f' TAG+="uaccess"')
    return f'SUBSYSTEM=="tty", ATTRS{{idVendor}}=="{vid:04x}", ATTRS{{idProduct}}=="{pid:04x}", TAG+="uaccess"'


@dataclass
class Finding:
    """One device and what stands between it and perfcap."""

    what: str
    where: str
    ok: bool
    problem: str = ""
    fix: str = ""
    kind: str | None = None
    url: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass
class Report:
    findings: list[Finding] = field(default_factory=list)
    usb: list[dict[str, Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return all(f.ok for f in self.findings)

    def as_dict(self) -> dict[str, Any]:
        return {"ok": self.ok, "findings": [f.as_dict() for f in self.findings], "usb": self.usb,
                "notes": self.notes}


def _node_access(path: str) -> tuple[bool, str]:
    if not path.startswith("/dev/"):
        return True, ""  # not a device node (macOS/Windows paths): hidapi decides at open
    if not os.path.exists(path):
        return False, f"{path} does not exist"
    if os.access(path, os.R_OK | os.W_OK):
        return True, ""
    st = os.stat(path)
    return False, (f"{path} is not readable and writable by you (mode {st.st_mode & 0o777:o}, uid {st.st_uid},"
                   f" gid {st.st_gid})")


def _usb_devices() -> tuple[list[dict[str, Any]], str]:
    try:
        import usb.core
    except ImportError as exc:
        return [], f"pyusb is not installed ({exc})"
    try:
        devs = list(usb.core.find(find_all=True))
    except Exception as exc:
        return [], f"USB devices cannot be listed with pyusb: {exc} (is libusb-1.0 installed?)"
    out = []
    for d in devs:
        vid, pid = int(d.idVendor), int(d.idProduct)
        k = known_hid(vid, pid)
        a = known_adapter(vid, pid)
        out.append({"vid_pid": f"{vid:04x}:{pid:04x}", "bus": int(getattr(d, "bus", 0) or 0),
                    "address": int(getattr(d, "address", 0) or 0),
                    "known_as": k.name if k else (a.chip if a else ""), "kind": k.kind if k else None})
    return out, ""


def diagnose() -> Report:
    """Look at every USB, HID and serial device; never raises."""
    rep = Report()
    rep.usb, usb_note = _usb_devices()
    if usb_note:
        rep.notes.append(usb_note + "; the USB listing is only a cross-check: HID and serial devices are listed"
                         " without it")
    rep.notes.append(f"hidapi backend: {hid_backend()}")
    try:
        hids = list_hid_devices()
    except Exception as exc:
        hids = []
        rep.notes.append(f"HID devices cannot be listed: {exc}")
    seen_hid: set[tuple[int, int]] = set()
    by_path: dict[str, HidDeviceInfo] = {}
    for h in hids:
        by_path.setdefault(h.path, h)
    for h in by_path.values():
        if h.likely_kind is None:
            continue
        seen_hid.add((h.vid, h.pid))
        ok, problem = _node_access(h.path)
        name = f"{h.product or 'HID device'} [{h.vid_pid}] over {h.bus}"
        rep.findings.append(Finding(name, h.path, ok, problem, "" if ok else
                                    "install perfcap's udev rules (perfcap doctor --udev) or this rule:\n"
                                    + rule_for(h.vid, h.pid), h.likely_kind, h.url))
    # known controllers seen on USB without a HID interface perfcap can see
    for u in rep.usb:
        if u["kind"] and tuple(int(x, 16) for x in u["vid_pid"].split(":")) not in seen_hid:
            rep.findings.append(Finding(f"{u['known_as']} [{u['vid_pid']}]",
                                        f"USB bus {u['bus']} device {u['address']}",
                                        False, "it is on USB but hidapi lists no HID interface for it",
                                        "check that the kernel's HID driver is loaded (lsmod | grep hid) and that"
                                        " another program has not claimed it", u["kind"]))
    for p in list_serial_ports():
        ok, problem = _node_access(p.device)
        kinds = p.adapter.kinds if p.adapter else ()
        fix = ""
        if not ok:
            rule = (f", or this rule:\n{rule_for(p.vid, p.pid, hidraw=False)}"
                    if p.vid is not None and p.pid is not None else "")
            fix = "add yourself to the dialout group (sudo usermod -aG dialout $USER, then log in again)" + rule
        rep.findings.append(Finding(f"serial port {p.description or p.device} [{p.vid_pid or 'no USB id'}]", p.device,
                                    ok, problem, fix, kinds[0] if kinds else None, p.url))
    if not rep.findings:
        rep.notes.append("no capture device found: plug one in, or try a simulated one (perfcap demo, simhid://dualsense,"
                         " perfcap sim serial)")
    known = ", ".join(sorted({k.name for k in KNOWN_HID}))
    rep.notes.append(f"controllers perfcap knows by USB id: {known}; mice, pens and touch surfaces are read"
                     " from their report descriptors (kind hid)")
    return rep
