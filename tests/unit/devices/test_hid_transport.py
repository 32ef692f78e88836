"""The hidapi transport without hardware: address forms, errors, enumeration, doctor, udev rules."""

from __future__ import annotations

import re

import pytest

from capture.app.cli import main
from capture.errors import ConfigError, DeviceNotFoundError
from devices import open_device
from devices.doctor import diagnose, rule_for, udev_rules
from devices.transports.hid import KNOWN_HID, HidTransport, known_hid, list_hid_devices


def test_address_forms_and_implied_kinds():
    assert HidTransport("054c:0ce6").implied_kind() == "dualsense"
    assert HidTransport("057e:2009:AB12").identity_hint() == {"vid": 0x057E, "pid": 0x2009, "serial": "AB12"}
    assert HidTransport("path=/dev/hidraw3").implied_kind() is None
    for bad in ("", "054c", "zz:yy", "054c:0ce6x"):
        with pytest.raises(ConfigError):
            HidTransport(bad)


def test_an_absent_device_is_a_clear_not_found_error_and_not_present():
    t = HidTransport("1234:5678")
    assert t.present() is False
    with pytest.raises(DeviceNotFoundError, match="perfcap devices"):
        t.open()
    # through the device string, the kind is implied by the USB id of a known controller
    assert open_device("pad=hid://054c:05c4").kind == "ds4"


def test_linux_uses_the_hidraw_backend_and_enumeration_is_wellformed():
    """hidapi's libusb backend sees no Bluetooth device and detaches the kernel driver of a mouse it
    opens; on Linux perfcap must use the hidraw one."""
    import sys

    from devices.transports.hid import hid_backend

    if sys.platform.startswith("linux"):
        assert hid_backend() == "hidraw"
    for d in list_hid_devices():
        assert re.fullmatch(r"[0-9a-f]{4}:[0-9a-f]{4}", d.vid_pid)
        assert d.url.startswith("hid://")


def test_known_controllers_have_distinct_ids_and_kinds():
    ids = [(k.vid, k.pid) for k in KNOWN_HID]
    assert len(ids) == len(set(ids))
    assert known_hid(0x054C, 0x0CE6).kind == "dualsense" and known_hid(0x1234, 0x5678) is None


def test_udev_rules_cover_every_known_controller_over_usb_and_bluetooth():
    rules = [line for line in udev_rules().splitlines() if line and not line.startswith("#")]
    assert all(("KERNEL==" in r or "SUBSYSTEM==" in r) and 'TAG+="uaccess"' in r for r in rules)
    text = "\n".join(rules)
    for k in KNOWN_HID:
        usb = [r for r in rules if f'ATTRS{{idVendor}}=="{k.vid:04x}"' in r and f"{k.pid:04x}" in r]
        bt = [r for r in rules if f"0005:{k.vid:04X}:{k.pid:04X}" in r]
        assert usb, f"no USB rule for {k.name}"
        if k.pid != 0x0BA0:  # the USB wireless adaptor has no Bluetooth side
            assert bt, f"no Bluetooth rule for {k.name}"
    assert "056a" in text  # Wacom tablets
    one = rule_for(0x046D, 0xC077)
    assert 'ATTRS{idVendor}=="046d"' in one and "0005:046D:C077" in one


def test_doctor_runs_on_any_machine(capsys):
    rep = diagnose()
    assert rep.notes  # at least the list of known controllers
    code = main(["doctor"])
    out = capsys.readouterr().out
    assert code == (0 if rep.ok else 1) and "controllers perfcap knows" in out and "hidapi backend" in out
    assert main(["doctor", "--udev"]) == 0
    assert "70-perfcap.rules" in capsys.readouterr().out
