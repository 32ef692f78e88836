"""``lsl``: a Lab Streaming Layer stream as a perfcap device (``lsl://NAME``, kind implied).

One stream, ``<name>/<suffix>`` (the suffix: option ``stream``, else the LSL type in lower case,
else ``data``), of kind ``lsl``, with one channel per LSL channel: named from the labels in the
stream's description (``desc/channels/channel/label``, made into names and unique), else ``c0`` to
``cN-1``, with the units given there. The sender's LSL timestamps are the device clock, in ns
(seconds x 1e9, rounded; no wrap), fitted to the bus clock like any device's; a stream of nominal
rate 0 (LSL's irregular rate) has no rate. Numeric formats only: a string stream (markers) is
refused with a clear error. A stream another perfcap publishes (``--lsl``) says its kind and frame in
its description (``desc/perfcap``): it keeps them, and its suffix is the sender's (``a/imu`` arrives
as ``<name>/imu`` of kind ``imu``), so orientation fusion and the 3D view treat it as the sender did.

The streams are declared before the first byte, from the stream's XML description: the ``info``
option (a session keeps it with the device's options, so ``replay://`` declares the same streams
with no LSL present), else asked of the ``lsl://`` transport, which resolves the stream. The XML is
also kept as the device descriptor ``lsl.info`` at every open (a restarted sender's new one too).
"""

from __future__ import annotations

import dataclasses
import re
from typing import TYPE_CHECKING, Any, ClassVar

from capture.errors import ConfigError, DeviceInitError, DeviceUnavailableError
from capture.sample import DeviceClockSpec, DeviceDescriptor
from devices.base import Device, Reading
from devices.codecs.lsl import LslCodec, LslDescription, LslFrame, parse_info_xml
from devices.options import Option
from devices.transports.lsl import LslTransport

if TYPE_CHECKING:
    from collections.abc import Iterable

    from capture.sample import StreamInfo

INFO_KEY = "lsl.info"
#: LSL timestamps are seconds; device ticks are ns
LSL_CLOCK = DeviceClockSpec(tick_hz=1e9)
_NOT_NAME = re.compile(r"[^A-Za-z0-9_]+")


def channel_names(labels: Iterable[str]) -> tuple[str, ...]:
    """Channel names from LSL labels: letters, digits and ``_`` (others made ``_``), unique (a repeat
    gets ``_2``, ``_3``, ...); ``c<i>`` for a channel without a usable label."""
    out: list[str] = []
    seen: set[str] = set()
    for i, label in enumerate(labels):
        base = _NOT_NAME.sub("_", label).strip("_") or f"c{i}"
        name, k = base, 1
        while name in seen:
            k += 1
            name = f"{base}_{k}"
        seen.add(name)
        out.append(name)
    return tuple(out)


def lsl_ticks(timestamp_s: float) -> int:
    """An LSL timestamp (s) as device ticks (ns)."""
    return round(timestamp_s * 1e9)


class LslInlet(Device[LslCodec]):
    """A numeric LSL stream; see the module docstring."""

    kind = "lsl"
    description = "a Lab Streaming Layer stream (lsl://NAME); the sender's LSL timestamps are its clock"
    codec_cls = LslCodec
    options: ClassVar[dict[str, Option]] = {
        "stream": Option(str, "", "the bus stream's suffix (default: the LSL type in lower case, else data)"),
        "info": Option(str, "", "the stream's LSL XML description (sessions keep it; else asked of lsl://)"),
    }

    def _initial_xml(self) -> tuple[str, str]:
        xml = self.opts["info"]
        if xml:
            return xml, "option info"
        t = self.transport
        if isinstance(t, LslTransport):
            return t.stream_xml(), t.url
        raise ConfigError(f"device {self.name} (lsl): needs an lsl:// transport or the info option (the stream's"
                          f" LSL XML description), not {t.url}", source=self.name)

    def declare_streams(self) -> list[StreamInfo]:
        xml, source = self._initial_xml()
        desc = parse_info_xml(xml, f"device {self.name} (lsl): {source}")
        if desc.format == "string":
            raise DeviceUnavailableError(
                f"device {self.name}: the LSL stream {desc.name!r} carries strings (markers), which lsl:// does not"
                " read; only numeric streams (float32, double64, int8..int64) are supported", source=self.name)
        self._xml = xml
        self.desc = desc
        sender = desc.name.rpartition("/")[2] if desc.kind else ""
        suffix = (self.opts["stream"] or _NOT_NAME.sub("_", sender).strip("_")
                  or _NOT_NAME.sub("_", desc.type.lower()).strip("_") or "data")
        info = self.stream_info(suffix, desc.kind or "lsl", channel_names(desc.labels), desc.units, desc.rate_hz,
                                frame=desc.frame or None, clock=LSL_CLOCK)
        extra: dict[str, str | bool] = {"lsl_name": desc.name, "lsl_type": desc.type, "lsl_format": desc.format,
                                        "lsl_source_id": desc.source_id, "lsl_host": desc.hostname}
        return [dataclasses.replace(info, extra=extra)]

    @property
    def device_options(self) -> dict[str, Any]:
        """The options as given, with the stream's description (``info``), so a replay declares the
        same streams."""
        return {**self._given_options, "info": self._xml}

    def descriptors(self) -> dict[str, bytes]:
        return {**super().descriptors(), INFO_KEY: self._xml.encode()}

    def handshake(self) -> None:
        """Check that the stream opened is the one declared (after a reconnect: a restarted sender),
        and keep its description."""
        t = self.transport
        if not isinstance(t, LslTransport):
            return
        xml = t.stream_xml()
        now = parse_info_xml(xml, f"device {self.name} (lsl): {t.url}")
        d = self.desc
        if (now.channel_count, now.format) != (d.channel_count, d.format):
            raise DeviceInitError(f"device {self.name}: the LSL stream now has {now.channel_count} channels of"
                                  f" {now.format}, not the {d.channel_count} of {d.format} declared", source=t.url)
        self._xml = xml
        self._pending.append(DeviceDescriptor(self.name, INFO_KEY, xml.encode(), self.clock.now_ns()))

    def frame_to_readings(self, frame: LslFrame) -> Iterable[Reading]:
        if frame.fmt != self.desc.format_code or frame.channels != self.desc.channel_count:
            self._undecoded(f"a frame of {frame.channels} channels of format {frame.fmt}")
            return []
        rows = frame.values.astype("f8").tolist() if not isinstance(frame.values, tuple) else []
        return [Reading(0, tuple(row), lsl_ticks(ts)) for row, ts in zip(rows, frame.timestamps.tolist(),
                                                                          strict=True)]


__all__ = ["INFO_KEY", "LSL_CLOCK", "LslDescription", "LslInlet", "channel_names", "lsl_ticks"]
