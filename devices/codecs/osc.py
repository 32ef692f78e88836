"""The OSC codec of phone apps that send OSC over UDP (ZIG SIM, GyrOSC-style): datagrams in, ``OscFrame``s out.

This module owns the OSC wire syntax: bytes in, typed frames out, bad input counted. What the
values mean (streams, units, signs) is ``devices.phone_apps.osc``.

``OscCodec`` (name ``osc``): one ``feed(data)`` is one UDP datagram, an OSC message or a
bundle (bundles may nest). It becomes one ``OscFrame``: the messages in document order, flattened
out of nested bundles, and the raw 64-bit NTP time tag of the outermost bundle (``None`` for a bare
message, 1 for "immediately"). Parsing is python-osc's (``pythonosc.osc_bundle.OscBundle`` and
``pythonosc.osc_message.OscMessage``). Not used: ``OscPacket``, which reads the wall clock and
reorders messages by it (a replay would not be deterministic), and the ``Dispatcher``, which sleeps
until a future time tag. Time tags are reported, never waited for. Before python-osc sees a
datagram, a structural check walks the bundle element sizes and reads each message's type tags
with python-osc's own ``get_string``. It enforces the bounds below, and it rejects a negative
element size, which makes python-osc's bundle parser loop forever (checked with python-osc
1.10.2), and type tags python-osc cannot decode, which it would skip without moving on, misreading
the arguments after them. After parsing, each message's size must match what its address, type
tags and arguments take. python-osc pads a float cut short at the end with zeros, which would make
up a value, so a truncated message is rejected, and so is one with trailing bytes. Arguments come back as
Python values: ``int``, ``float``, ``str``, ``bytes``, ``bool`` (``T``/``F``), ``None`` (``N``),
tuples for arrays; float32 arguments are exact Python floats of their float32 value.

The codec keeps its state in itself, so the same chunks always give the same frames. ``encode``
is the inverse of ``feed``, used by simulators and round-trip tests.
"""

from __future__ import annotations

import struct
from typing import TYPE_CHECKING, Any, NamedTuple

from pythonosc import osc_bundle, osc_message
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message_builder import OscMessageBuilder
from pythonosc.parsing import osc_types

from devices.codecs.base import BadMessageError, MessageCodec

if TYPE_CHECKING:
    from collections.abc import Sequence

#: Bounds of one OSC datagram.
OSC_MAX_DATAGRAM = 65536       # a UDP payload cannot be larger
OSC_MAX_MESSAGES = 1024        # messages (and nested bundles) per datagram
OSC_MAX_DEPTH = 8              # bundle nesting
OSC_MAX_ARGS = 256             # type tags per message
OSC_MAX_ADDRESS = 256          # characters of an address
#: Type tags python-osc decodes (others it skips without consuming their bytes).
OSC_TYPE_TAGS = frozenset("ihfdsbrmtTFN[]")
#: The raw time tag meaning "immediately".
OSC_IMMEDIATELY = 1

_BUNDLE = b"#bundle\x00"
_SIZE = struct.Struct(">i")
_TIMETAG = struct.Struct(">Q")


class OscMsg(NamedTuple):
    """One OSC message: its address and its arguments (arrays as tuples)."""

    address: str
    args: tuple[Any, ...] = ()


class OscFrame(NamedTuple):
    """One datagram: its messages in document order (nested bundles flattened) and the raw NTP time
    tag of the outermost bundle (``None`` for a bare message, ``OSC_IMMEDIATELY`` for "now")."""

    messages: tuple[OscMsg, ...]
    timetag: int | None = None


_Reject = BadMessageError  # why an input is rejected


def _tuples(v: Any) -> Any:
    return tuple(_tuples(x) for x in v) if isinstance(v, list) else v


def _lists(v: Any) -> Any:
    return [_lists(x) for x in v] if isinstance(v, tuple) else v


def _check_osc_layout(data: bytes) -> None:
    """Structure check before python-osc parses ``data`` (see the module docstring).

    Raises:
        _Reject: the datagram is not a well-formed OSC packet within the bounds.
    """
    # (start, end, depth) of the elements still to look at; iterative, so nesting costs no recursion
    todo = [(0, len(data), 0)]
    count = 0
    while todo:
        start, end, depth = todo.pop()
        count += 1
        if count > OSC_MAX_MESSAGES:
            raise _Reject(f"more than {OSC_MAX_MESSAGES} elements")
        if data.startswith(_BUNDLE, start):
            if depth >= OSC_MAX_DEPTH:
                raise _Reject(f"bundles nested deeper than {OSC_MAX_DEPTH}")
            if end - start < 16:
                raise _Reject("bundle shorter than its header")
            pos = start + 16
            while pos < end:
                if end - pos < 4:
                    raise _Reject(f"truncated element size at byte {pos}")
                (size,) = _SIZE.unpack_from(data, pos)
                pos += 4
                if size <= 0 or size % 4 or size > end - pos:
                    raise _Reject(f"bad bundle element size {size} at byte {pos - 4}")
                todo.append((pos, pos + size, depth + 1))
                pos += size
        elif data.startswith(b"/", start):
            _check_osc_message(data[start:end])
        else:
            raise _Reject(f"element at byte {start} is neither an OSC message nor a bundle")


def _check_osc_message(m: bytes) -> None:
    try:
        address, idx = osc_types.get_string(m, 0)
        tags = ""
        if idx < len(m):
            tags, _ = osc_types.get_string(m, idx)
    except Exception as exc:  # python-osc raises ParseError, IndexError, UnicodeDecodeError
        raise _Reject(f"unreadable address or type tags ({exc})") from None
    if len(address) > OSC_MAX_ADDRESS:
        raise _Reject(f"address longer than {OSC_MAX_ADDRESS} characters")
    if not address.isprintable():
        raise _Reject("address with control characters")
    if tags:
        if not tags.startswith(","):
            raise _Reject(f"type tags of {address} do not start with ','")
        if len(tags) - 1 > OSC_MAX_ARGS:
            raise _Reject(f"{address} has more than {OSC_MAX_ARGS} type tags")
        bad = set(tags[1:]) - OSC_TYPE_TAGS
        if bad:
            raise _Reject(f"{address} has unsupported type tags {''.join(sorted(bad))!r}")


def _pad4(n: int) -> int:
    return (n + 3) & ~3


def _leaves(params: Sequence[Any]) -> list[Any]:
    out: list[Any] = []
    for p in params:
        if isinstance(p, list):
            out += _leaves(p)
        else:
            out.append(p)
    return out


def _check_osc_size(m: osc_message.OscMessage) -> None:
    """The bytes a message's parsed address, type tags and arguments take must be its size.

    python-osc pads a float cut short at the end of a message with zeros (for a sender that drops
    trailing zero bytes) and ignores bytes after the last argument. Here a truncated or overlong
    message is rejected instead, so no argument is made up.

    Raises:
        _Reject: the sizes differ.
    """
    raw = m.dgram
    address, idx = osc_types.get_string(raw, 0)
    size = _pad4(len(address.encode("utf-8")) + 1)
    if idx < len(raw):
        tags, _ = osc_types.get_string(raw, idx)
        size += _pad4(len(tags.encode("utf-8")) + 1)
        for tag, v in zip((t for t in tags[1:] if t not in "[]"), _leaves(m.params), strict=False):
            if tag in "ifrm":
                size += 4
            elif tag in "hdt":
                size += 8
            elif tag == "s":
                size += _pad4(len(v.encode("utf-8")) + 1)
            elif tag == "b":
                size += 4 + _pad4(len(v))
    if size != len(raw):
        raise _Reject(f"{address}: {len(raw)} bytes where its arguments take {size} (truncated or trailing bytes)")


def _walk(root: Any) -> list[OscMsg]:
    """Messages of a parsed python-osc bundle or message, in document order (sizes checked).

    Raises:
        _Reject: a message's size does not match its contents.
    """
    out: list[OscMsg] = []
    stack = [iter([root])]
    while stack:
        item = next(stack[-1], None)
        if item is None:
            stack.pop()
        elif isinstance(item, osc_bundle.OscBundle):
            stack.append(iter(item))
        else:
            _check_osc_size(item)
            out.append(OscMsg(item.address, tuple(_tuples(p) for p in item.params)))
    return out


class OscCodec(MessageCodec):
    """OSC datagrams (one per ``feed``) to ``OscFrame``s; see the module docstring."""

    name = "osc"

    max_bytes = OSC_MAX_DATAGRAM

    def parse(self, data: bytes) -> list[OscFrame]:
        """One whole datagram (a message or a bundle) to one frame."""
        if not data:
            raise _Reject("empty datagram")
        _check_osc_layout(data)
        try:
            if data.startswith(_BUNDLE):
                root: Any = osc_bundle.OscBundle(data)
                timetag: int | None = _TIMETAG.unpack_from(data, 8)[0]
            else:
                root = osc_message.OscMessage(data)
                timetag = None
            messages = _walk(root)
        except _Reject:
            raise
        except Exception as exc:  # a foreign parser: whatever it raises is bad input
            raise _Reject(f"python-osc cannot parse it ({type(exc).__name__}: {exc})") from None
        return [OscFrame(tuple(messages), timetag)]

    def reject(self, message: str, raw: bytes = b"") -> None:
        """Count a message the device layer found unusable (wrong argument count or type) as a
        framing error.

        Raises:
            ProtocolError: only in strict mode.
        """
        self._bad("framing", message, 0, raw[:200])

    def encode(self, frame: OscFrame | OscMsg) -> bytes:
        """The datagram of ``frame``, built with python-osc's builders.

        A bare ``OscMsg``, or an ``OscFrame`` with one message and no time tag, is sent as a plain
        message. Anything else goes out as a bundle with the frame's time tag (``None`` sends
        "immediately"). Python floats are sent as float32 (``f``), as the apps send them, ints as
        ``i`` (``h`` beyond 32 bits), tuples as arrays.

        Raises:
            TypeError: not an OSC frame.
            ValueError: an argument python-osc cannot encode, or a time tag out of range.
        """
        if isinstance(frame, OscMsg):
            return self._message(frame).dgram
        if not isinstance(frame, OscFrame):
            raise TypeError(f"not an OSC frame: {type(frame).__name__}")
        if frame.timetag is None and len(frame.messages) == 1:
            return self._message(frame.messages[0]).dgram
        b = OscBundleBuilder(IMMEDIATELY)
        for m in frame.messages:
            b.add_content(self._message(m))
        dgram = bytearray(b.build().dgram)
        tt = OSC_IMMEDIATELY if frame.timetag is None else frame.timetag
        if not 0 <= tt < 1 << 64:
            raise ValueError(f"time tag {tt} is not a 64-bit NTP time")
        _TIMETAG.pack_into(dgram, 8, tt)
        return bytes(dgram)

    @staticmethod
    def _message(m: OscMsg) -> osc_message.OscMessage:
        b = OscMessageBuilder(address=m.address)
        try:
            for a in m.args:
                b.add_arg(_lists(a))
            return b.build()
        except Exception as exc:  # python-osc's BuildError, ValueError and friends
            raise ValueError(f"cannot encode {m.address}: {exc}") from exc


__all__ = ["OSC_IMMEDIATELY", "OSC_MAX_ADDRESS", "OSC_MAX_ARGS", "OSC_MAX_DATAGRAM", "OSC_MAX_DEPTH",
           "OSC_MAX_MESSAGES", "OSC_TYPE_TAGS", "OscCodec", "OscFrame", "OscMsg"]
