"""Serial ports on pyserial: USB-serial adapters, on-board USB CDC, Bluetooth SPP, and pyserial's
URL handlers (``socket://``, ``rfc2217://``, ``loop://``).

Addresses::

    serial:///dev/ttyUSB0?baud=115200            a device path (COM3 on Windows)
    serial://1a86:7523?baud=921600               the one USB adapter with that VID:PID
    serial://1a86:7523:A50285BI                  ... and that USB serial number
    rfc2217://10.0.0.5:4000   socket://10.0.0.5:7000   loop://

A VID:PID address is looked up again at every open, so an adapter that comes back under another
``/dev/ttyUSB*`` name after an unplug is found again. A chunk is every byte the OS has when the
reader wakes, stamped with the host monotonic time right after the read returns. On POSIX the
reader waits in ``select`` and reads the file descriptor directly: one system call per chunk, and
an unplug (EIO, or "ready but no data") is noticed on the next read.
"""

from __future__ import annotations

import errno
import logging
import os
import re
import select
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import serial
from serial.tools import list_ports

from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError, DeviceInitError, DeviceIOError, DeviceNotFoundError
from capture.sample import Chunk, Direction
from devices.options import Option
from devices.transports.base import Transport

if TYPE_CHECKING:
    from collections.abc import Mapping

log = logging.getLogger(__name__)

_VIDPID_RE = re.compile(r"^([0-9a-fA-F]{4}):([0-9a-fA-F]{4})(?::(.+))?$")


@dataclass(frozen=True)
class KnownAdapter:
    """A USB VID:PID perfcap recognises: the chip, and the device kinds usually behind it."""

    chip: str
    kinds: tuple[str, ...] = ()
    note: str = ""


#: USB serial adapters and boards seen in IMU rigs. ``pid`` None matches any product of the vendor.
KNOWN_ADAPTERS: dict[tuple[int, int | None], KnownAdapter] = {
    (0x1A86, 0x7523): KnownAdapter("WCH CH340/CH341", ("witmotion", "textline"),
                                   "WitMotion's USB-serial cable; also cheap Arduino clones"),
    (0x1A86, 0x55D4): KnownAdapter("WCH CH9102", ("witmotion", "textline")),
    (0x1A86, 0x7522): KnownAdapter("WCH CH340K", ("witmotion", "textline")),
    (0x10C4, 0xEA60): KnownAdapter("Silicon Labs CP210x", ("witmotion", "bno08x_rvc", "textline"),
                                   "WitMotion Bluetooth/USB dongles; ESP32 dev boards"),
    (0x0403, 0x6001): KnownAdapter("FTDI FT232R", ("bno08x_rvc", "textline"),
                                   "16 ms latency timer by default: low_latency=true asks for 1 ms"),
    (0x0403, 0x6015): KnownAdapter("FTDI FT-X", ("bno08x_rvc", "textline"), "16 ms latency timer by default"),
    (0x0403, 0x6014): KnownAdapter("FTDI FT232H", ("textline",), "16 ms latency timer by default"),
    (0x0403, 0x6010): KnownAdapter("FTDI FT2232", ("textline",), "16 ms latency timer by default"),
    (0x067B, 0x2303): KnownAdapter("Prolific PL2303", ("witmotion", "textline")),
    (0x2341, None): KnownAdapter("Arduino", ("textline",), "boards reset when the port opens (DTR)"),
    (0x2A03, None): KnownAdapter("Arduino (arduino.org)", ("textline",)),
    (0x239A, None): KnownAdapter("Adafruit board", ("textline", "bno08x_rvc")),
    (0x2E8A, None): KnownAdapter("Raspberry Pi RP2040/RP2350", ("textline",)),
    (0x303A, None): KnownAdapter("Espressif ESP32 USB", ("textline",)),
    (0x16C0, 0x0483): KnownAdapter("Teensy", ("textline",)),
    (0x0483, 0x5740): KnownAdapter("STM32 virtual COM port", ("textline",)),
}


def known_adapter(vid: int | None, pid: int | None) -> KnownAdapter | None:
    if vid is None:
        return None
    return KNOWN_ADAPTERS.get((vid, pid)) or KNOWN_ADAPTERS.get((vid, None))


@dataclass(frozen=True)
class SerialPortInfo:
    """One serial port the OS lists, with what perfcap recognises about it."""

    device: str
    description: str
    vid: int | None
    pid: int | None
    serial_number: str | None
    manufacturer: str | None
    product: str | None
    location: str | None
    adapter: KnownAdapter | None
    latency_timer_ms: int | None

    @property
    def vid_pid(self) -> str | None:
        return None if self.vid is None or self.pid is None else f"{self.vid:04x}:{self.pid:04x}"

    @property
    def url(self) -> str:
        """The address that finds this port again after a replug (VID:PID[:serial]) or its path."""
        if self.vid_pid and self.serial_number:
            return f"serial://{self.vid_pid}:{self.serial_number}"
        return f"serial://{self.device}"

    def as_dict(self) -> dict[str, Any]:
        return {"device": self.device, "url": self.url, "description": self.description, "vid_pid": self.vid_pid,
                "serial_number": self.serial_number, "manufacturer": self.manufacturer, "product": self.product,
                "location": self.location, "chip": self.adapter.chip if self.adapter else None,
                "likely_kinds": list(self.adapter.kinds) if self.adapter else [],
                "note": self.adapter.note if self.adapter else "", "latency_timer_ms": self.latency_timer_ms}


def _latency_timer(device: str) -> int | None:
    """The FTDI latency timer (Linux sysfs), which batches bytes into bursts of up to this many ms."""
    p = Path("/sys/bus/usb-serial/devices") / Path(device).name / "latency_timer"
    try:
        return int(p.read_text().strip())
    except (OSError, ValueError):
        return None


def list_serial_ports() -> list[SerialPortInfo]:
    """Serial ports present now, with known adapters recognised by VID:PID."""
    out = []
    for p in sorted(list_ports.comports(), key=lambda p: p.device):
        out.append(SerialPortInfo(p.device, p.description or "", p.vid, p.pid, p.serial_number, p.manufacturer,
                                  p.product, p.location, known_adapter(p.vid, p.pid), _latency_timer(p.device)))
    return out


def resolve_usb_address(address: str) -> tuple[str, SerialPortInfo]:
    """``VID:PID[:SERIAL]`` -> the device path of the one matching port.

    Raises:
        DeviceNotFoundError: no port matches (unplugged).
        DeviceInitError: several match and no serial number tells them apart.
    """
    m = _VIDPID_RE.match(address)
    if m is None:
        raise ConfigError(f"serial://{address}: not VID:PID[:SERIAL]", source=address)
    vid, pid, sn = int(m.group(1), 16), int(m.group(2), 16), m.group(3)
    found = [p for p in list_serial_ports() if p.vid == vid and p.pid == pid
             and (sn is None or p.serial_number == sn)]
    if not found:
        raise DeviceNotFoundError(f"no serial port with USB id {address} is plugged in"
                                  " (perfcap devices lists what is present)", source=address)
    if len(found) > 1:
        choices = ", ".join(f"{p.device} (serial {p.serial_number or 'none'})" for p in found)
        raise DeviceInitError(f"{len(found)} ports match USB id {address}: {choices}; add the serial number"
                              f" (serial://{m.group(1)}:{m.group(2)}:SERIAL) or use the device path",
                              source=address)
    return found[0].device, found[0]


def port_info(path: str) -> SerialPortInfo | None:
    """What the OS lists for ``path`` (symlinks such as /dev/serial/by-id/... resolved), if anything."""
    try:
        real = os.path.realpath(path)
    except OSError:
        real = path
    for p in list_serial_ports():
        if p.device in (path, real):
            return p
    return None


class SerialTransport(Transport):
    """A serial port; see the module docstring for the address forms."""

    scheme: ClassVar[str] = "serial"
    usage: ClassVar[str] = ("serial:///dev/ttyUSB0?baud=115200, serial://VID:PID[:SERIAL]?baud=N,"
                            " rfc2217://HOST:PORT or socket://HOST:PORT")
    options: ClassVar[dict[str, Option]] = {
        "baud": Option(int, 115200, "bits per second", min=50, max=12_000_000),
        "bytesize": Option(int, 8, "data bits", min=5, max=8),
        "parity": Option(str, "N", "parity", choices=("N", "E", "O", "M", "S")),
        "stopbits": Option(float, 1.0, "stop bits (1, 1.5 or 2)", min=1.0, max=2.0),
        "rtscts": Option(bool, False, "hardware flow control"),
        "dtr": Option(str, "default", "DTR line on open (Arduino boards reset when it rises)",
                      choices=("default", "on", "off")),
        "exclusive": Option(bool, True, "lock the port so no other program reads it at the same time"),
        "low_latency": Option(bool, True, "ask the driver for low latency (FTDI: 1 ms instead of 16 ms bursts)"),
        "read_size": Option(int, 65536, "largest chunk read at once, bytes", min=1, max=1 << 24),
    }

    def __init__(self, address: str, options: Mapping[str, Any] | None = None, clock: Clock = MONOTONIC) -> None:
        super().__init__(address, options, clock)
        if not address:
            raise ConfigError(f"{self.scheme}:// needs an address; expected {self.usage}", source=self.url)
        o = self.opts
        if o["stopbits"] not in (1.0, 1.5, 2.0):
            raise ConfigError(f"{self.url}: stopbits must be 1, 1.5 or 2", source=self.url)
        self._ser: Any = None
        self._fd: int | None = None
        self._timeout: float | None = None
        self.path: str | None = None  # what was opened last
        self.port: SerialPortInfo | None = None
        self.bytes_in = 0
        self.bytes_out = 0
        self._last_scan_ns = -(1 << 62)
        self._last_present = False

    # -- what the address says about the device ----------------------------------------------------
    @property
    def is_url_handler(self) -> bool:
        return self.scheme != "serial"

    def _target(self) -> str:
        """The path or pyserial URL to open now (VID:PID looked up again)."""
        if self.is_url_handler:
            return f"{self.scheme}://{self.address}"
        if _VIDPID_RE.match(self.address) and not os.path.exists(self.address):
            path, info = resolve_usb_address(self.address)
            self.port = info
            return path
        return self.address

    def identity_hint(self) -> dict[str, Any]:
        """USB vendor, product and serial number of the port, when the OS lists it (no I/O on the port)."""
        info = self.port
        if info is None and not self.is_url_handler:
            try:
                info = (resolve_usb_address(self.address)[1] if _VIDPID_RE.match(self.address)
                        else port_info(self.address))
            except (DeviceNotFoundError, DeviceInitError):
                info = None
        if info is None:
            return {}
        return {"vid": info.vid, "pid": info.pid, "serial": info.serial_number, "address": info.location}

    def present(self) -> bool | None:
        if self.is_url_handler:
            return None
        if _VIDPID_RE.match(self.address) and not os.path.exists(self.address):
            now = self.clock.now_ns()
            if now - self._last_scan_ns >= 250_000_000:  # a USB rescan reads sysfs: at most 4 per second
                self._last_scan_ns = now
                try:
                    resolve_usb_address(self.address)
                    self._last_present = True
                except (DeviceNotFoundError, DeviceInitError):
                    self._last_present = False
            return self._last_present
        return os.path.exists(self.address)

    # -- I/O ----------------------------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._ser is not None and bool(self._ser.is_open)

    def open(self) -> None:
        if self.is_open:
            return
        target = self._target()
        o = self.opts
        kw: dict[str, Any] = {"baudrate": o["baud"], "bytesize": o["bytesize"], "parity": o["parity"],
                                  "stopbits": o["stopbits"] if o["stopbits"] != 1.5 else serial.STOPBITS_ONE_POINT_FIVE,
                                  "rtscts": o["rtscts"], "timeout": 0.1, "write_timeout": 1.0, "do_not_open": True}
        if o["stopbits"] in (1.0, 2.0):
            kw["stopbits"] = int(o["stopbits"])
        try:
            ser = serial.serial_for_url(target, **kw)
            if os.name == "posix" and not self.is_url_handler:
                ser.exclusive = o["exclusive"]
            if o["dtr"] != "default":
                ser.dtr = o["dtr"] == "on"
            ser.open()
        except (ValueError, serial.SerialException, OSError) as exc:
            raise self._open_error(target, exc) from exc
        self._ser = ser
        self.path = target
        self._timeout = 0.1
        if self.port is None and not self.is_url_handler:
            self.port = port_info(target)
        if o["low_latency"] and hasattr(ser, "set_low_latency_mode"):
            try:
                ser.set_low_latency_mode(True)
            except (OSError, ValueError, AttributeError) as exc:  # ptys and some drivers cannot: harmless
                log.debug("%s: low-latency mode not available: %s", target, exc)
        fd = None
        if os.name == "posix" and type(ser).__name__ == "Serial" and hasattr(ser, "fd"):
            fd = ser.fd
        self._fd = fd
        log.debug("opened %s at %d baud (%s)", target, o["baud"], "fd" if fd is not None else "pyserial read")

    def _open_error(self, target: str, exc: BaseException) -> Exception:
        err = getattr(exc, "errno", None)
        text = str(exc)
        if err in (errno.ENOENT, errno.ENODEV, errno.ENXIO) or "No such file" in text:
            return DeviceNotFoundError(f"serial port {target} is not there (unplugged?); perfcap devices lists the"
                                       " ports present", source=self.url)
        if err in (errno.EACCES, errno.EPERM) or "Permission denied" in text:
            who = "the 'dialout' group (sudo usermod -aG dialout $USER, then log in again)" \
                if sys.platform.startswith("linux") else "your user"
            return DeviceInitError(f"no permission to open {target}: add {who}", source=self.url)
        if err in (errno.EBUSY, errno.EAGAIN) or "busy" in text.lower() or "exclusive" in text.lower():
            return DeviceInitError(f"{target} is in use by another program (close it, or pass exclusive=false"
                                   " to share at your own risk)", source=self.url)
        if isinstance(exc, ValueError):
            return ConfigError(f"{self.url}: {exc}", source=self.url)
        return DeviceInitError(f"cannot open {target}: {exc}", source=self.url)

    def close(self) -> None:
        ser, self._ser, self._fd = self._ser, None, None
        if ser is not None:
            try:
                ser.close()
            except (OSError, serial.SerialException) as exc:
                log.debug("%s: close: %s", self.path, exc)

    def read(self, timeout: float) -> Chunk | None:
        ser = self._ser
        if ser is None:
            raise DeviceIOError(f"{self.url}: read on a closed port", source=self.url)
        fd = self._fd
        if fd is not None:
            try:
                ready, _, _ = select.select((fd,), (), (), max(0.0, timeout))
                if not ready:
                    return None
                data = os.read(fd, self.opts["read_size"])
            except (OSError, ValueError) as exc:
                raise self._lost(exc) from exc
            t = self.clock.now_ns()
            if not data:
                raise self._lost(None)
        else:
            try:
                if timeout != self._timeout:
                    ser.timeout = self._timeout = timeout
                n = ser.in_waiting
                data = ser.read(min(n, self.opts["read_size"]) if n else 1)
                if data:
                    more = ser.in_waiting
                    if more:
                        data += ser.read(min(more, self.opts["read_size"]))
            except (OSError, serial.SerialException) as exc:
                raise self._lost(exc) from exc
            t = self.clock.now_ns()
            if not data:
                return None
        self.bytes_in += len(data)
        return Chunk(data, t, Direction.RX)

    def _lost(self, exc: BaseException | None) -> DeviceIOError:
        why = "the port reports data but returns none" if exc is None else str(exc)
        gone = self.path is not None and not self.is_url_handler and not os.path.exists(self.path)
        return DeviceIOError(f"serial port {self.path} {'vanished' if gone else 'failed'} (unplugged?): {why}",
                             source=self.url)

    def write(self, data: bytes) -> Chunk:
        ser = self._ser
        if ser is None:
            raise DeviceIOError(f"{self.url}: write on a closed port", source=self.url)
        chunk = self.stamp_tx(data)
        try:
            ser.write(data)
            ser.flush()
        except (OSError, serial.SerialException) as exc:
            raise self._lost(exc) from exc
        self.bytes_out += len(data)
        return chunk


class Rfc2217Transport(SerialTransport):
    """A serial port shared over the network by an RFC 2217 server (ser2net, pyserial's own)."""

    scheme = "rfc2217"


class SocketTransport(SerialTransport):
    """Raw bytes over TCP, as pyserial's ``socket://`` (ESP32/ser2net bridges)."""

    scheme = "socket"


class LoopTransport(SerialTransport):
    """pyserial's ``loop://``: what is written is read back (self-tests)."""

    scheme = "loop"

    def __init__(self, address: str, options: Mapping[str, Any] | None = None, clock: Clock = MONOTONIC) -> None:
        super().__init__(address or "loop", options, clock)

    def _target(self) -> str:
        return "loop://"


__all__ = [
    "KNOWN_ADAPTERS",
    "KnownAdapter",
    "SerialPortInfo",
    "SerialTransport",
    "known_adapter",
    "list_serial_ports",
    "port_info",
    "resolve_usb_address",
]
