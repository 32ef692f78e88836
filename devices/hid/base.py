"""``HidDevice``: the base of HID device kinds.

It wraps the handshake calls so that everything the device says during a handshake is kept:

* output and feature reports sent are TX chunks in the session (``hid_output``, ``hid_set_feature``);
* input reports read during the handshake (subcommand replies) are RX chunks in the session, in
  order, and are not decoded as samples (``hid_read``);
* feature reports read (factory calibration, firmware info) are device descriptors named
  ``hid.feature.XX`` (hex report ID), and the report descriptor is ``hid.report_descriptor``.

A replay answers ``get_feature_report`` from those descriptors, compares writes with the recorded
TX chunks and hands the recorded handshake replies back in order, so a handshake and the
calibration it read are reproduced exactly without the device.
"""

from __future__ import annotations

from typing import Any

from capture.errors import DeviceInitError, DeviceTimeoutError
from capture.sample import Chunk, DeviceChunk, DeviceDescriptor
from devices.base import CodecT, Device
from devices.transports.hid import HidTransportBase

REPORT_DESCRIPTOR_KEY = "hid.report_descriptor"
BUS_KEY = "hid.bus"


def feature_key(report_id: int) -> str:
    return f"hid.feature.{report_id:02x}"


class HidDevice(Device[CodecT]):
    """A Device whose transport is a HID transport (``hid://``, ``simhid://`` or a HID replay)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._features: dict[int, bytes] = {}
        self._rdesc: bytes | None = None

    @property
    def hid(self) -> HidTransportBase:
        t = self.transport
        if not isinstance(t, HidTransportBase):
            raise DeviceInitError(f"device {self.name} ({self.kind}) needs a HID transport (hid://, simhid:// or a"
                                  f" replay of one), not {t.url}", source=t.url)
        return t

    def open(self) -> list[Any]:
        """Open, note the bus (USB or Bluetooth) for sessions, then run the handshake."""
        self._pending = []
        items = super().open()
        bus = str(self.hid.bus)
        return [DeviceDescriptor(self.name, BUS_KEY, bus.encode(), self.clock.now_ns()), *items]

    # -- handshake helpers ---------------------------------------------------------------------------
    def hid_output(self, data: bytes) -> None:
        """Send an output report (its ID first); recorded as a TX chunk."""
        self.send(data)

    def hid_set_feature(self, data: bytes) -> None:
        """Send a feature report (its ID first); recorded as a TX chunk."""
        chunk = self.hid.send_feature_report(bytes(data))
        self._pending.append(DeviceChunk(self.name, chunk))

    def hid_get_feature(self, report_id: int, length: int) -> bytes:
        """Read a feature report; kept as the descriptor ``hid.feature.XX`` for sessions and replay."""
        data = bytes(self.hid.get_feature_report(report_id, length))
        self._features[report_id] = data
        self._pending.append(DeviceDescriptor(self.name, feature_key(report_id), data, self.clock.now_ns()))
        return data

    def hid_read(self, timeout: float) -> Chunk | None:
        """Read one input report during the handshake; recorded as an RX chunk, not decoded."""
        chunk = self.transport.read(timeout)
        if chunk is not None:
            self._pending.append(DeviceChunk(self.name, chunk))
        return chunk

    def hid_wait_for(self, accept: Any, timeout: float, what: str) -> bytes:
        """Read input reports until ``accept(report) -> bool`` holds; the others (streaming reports
        that arrive meanwhile) are recorded and skipped.

        Raises:
            DeviceTimeoutError: nothing accepted within ``timeout`` seconds.
        """
        deadline = self.clock.now_ns() + int(timeout * 1e9)
        while True:
            left = (deadline - self.clock.now_ns()) / 1e9
            if left <= 0:
                raise DeviceTimeoutError(f"device {self.name} ({self.kind}): no answer to {what} within"
                                         f" {timeout:g} s; is it a {self.kind}, and awake?", source=self.transport.url)
            chunk = self.hid_read(min(left, 0.05))
            if chunk is not None and accept(chunk.data):
                return chunk.data

    def hid_report_descriptor(self) -> bytes:
        """The report descriptor, read once per open; kept for sessions."""
        self._rdesc = bytes(self.hid.report_descriptor())
        self._pending.append(DeviceDescriptor(self.name, REPORT_DESCRIPTOR_KEY, self._rdesc, self.clock.now_ns()))
        return self._rdesc

    def descriptors(self) -> dict[str, bytes]:
        out = dict(super().descriptors())
        if self._rdesc is not None:
            out[REPORT_DESCRIPTOR_KEY] = self._rdesc
        for rid, data in sorted(self._features.items()):
            out[feature_key(rid)] = data
        return out
