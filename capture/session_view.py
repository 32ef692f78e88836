"""Viewable channels: the bus's samples and events as messages that Foxglove, Lichtblick and any protobuf
reader show with no perfcap code. The session writer records them beside the lossless blocks, and the
live Foxglove server publishes the same messages with the same schemas.

* ``/view/<stream>``: one message per sample, schema ``perfcap.view.<stream>`` (protobuf): ``timestamp``
  (the bus time on the wall clock) and one ``double`` field per channel, named after it (the channel
  metadata ``fields`` maps field names back to channel names, ``units`` gives their units). Foxglove's
  plot panel plots ``/view/wrist/imu.ax`` against real time.
* ``/tf/<stream>``: orientation streams (kinds ``quat`` and ``orientation``, ``w x y z``) as
  ``foxglove.FrameTransform`` from ``world`` to the stream's frame, the sensors' frames 0.5 m apart
  along x in the order they first send an orientation (``Placement``), so the 3D panel shows them side
  by side; a pose stream with a skeleton (the puppet) as
  ``foxglove.FrameTransforms``, one transform per joint from its parent, so the 3D panel draws the
  skeleton moving (perfcap's characters are Y up; the first transform, ``world`` to ``<stream>``,
  stands them up in Foxglove's Z-up world).
* ``/log``: the event log as ``foxglove.Log`` (failures and protocol errors as warnings and errors).

This module owns which channels a stream gets and how a batch becomes their messages; ``capture.proto``
builds the schemas.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Log_pb2 import Log
from google.protobuf import timestamp_pb2

from capture.proto import Field, ProtoSchema, build, identifier, schema_of
from capture.sample import DeviceEvent, EventKind

if TYPE_CHECKING:
    from collections.abc import Callable

    from capture.sample import SampleBatch, StreamInfo

log = logging.getLogger(__name__)

#: kinds whose 4 channels ``w x y z`` are a sensor-to-world rotation
ORIENTATION_KINDS = frozenset({"quat", "orientation"})
#: StreamInfo.extra key of a pose stream's skeleton: JSON ``{"parents": [...], "offsets": [[x, y, z], ...]}``
SKELETON_KEY = "skeleton"
WORLD = "world"
#: spacing of the orientation frames in the 3D view, m
FRAME_SPACING_M = 0.5

FRAME_TRANSFORM = schema_of(FrameTransform)
FRAME_TRANSFORMS = schema_of(FrameTransforms)
LOG = schema_of(Log)
LOG_TOPIC = "/log"
#: the topics of the viewable channels (perfcap's own readers read the lossless ones instead)
VIEW_PREFIXES = ("/view/", "/tf/", LOG_TOPIC)

#: messages of one channel from one batch: ``(bus time ns, message bytes)`` per sample
Encoded = list[tuple[int, bytes]]


@dataclass(frozen=True)
class ViewChannel:
    """One viewable channel of a stream: its topic, schema, channel metadata, and ``encode(batch,
    offset_ns)``: the batch's messages, each with its bus time (the caller adds its own offset to make
    the log time; ``offset_ns`` puts the ``timestamp`` fields on the wall clock)."""

    topic: str
    schema: ProtoSchema
    encode: Callable[[SampleBatch, int], Encoded]
    metadata: dict[str, str] = field(default_factory=dict)


def _stamp(t_ns: int) -> timestamp_pb2.Timestamp:
    s, ns = divmod(t_ns, 1_000_000_000)
    return timestamp_pb2.Timestamp(seconds=s, nanos=ns)


def sample_view(info: StreamInfo) -> ViewChannel:
    """``/view/<stream>``: a message per sample, a double field per channel."""
    taken = {"timestamp"}
    names = [identifier(c, taken) for c in info.channels]
    ident = identifier(info.name.replace("/", "."))
    fields = [Field("timestamp", "message", message="google.protobuf.Timestamp",
                    doc="the sample's bus time on the wall clock (UTC)")]
    fields += [Field(n, "double", doc=f"{c} ({u})") for n, c, u in zip(names, info.channels, info.units, strict=True)]
    pkg = "perfcap.view"
    schema = build(pkg, f"perfcap/view/{ident}.proto",
                   [(ident, fields, f"One sample of perfcap stream {info.name} (kind {info.kind}).")],
                   deps=[timestamp_pb2.DESCRIPTOR])[ident]
    cls = schema.cls

    def encode(b: SampleBatch, offset_ns: int) -> Encoded:
        if b.values.ndim != 2 or b.values.shape[1] != len(names):
            raise ValueError(f"{b.values.shape[-1]} values a sample where stream {info.name} has {len(names)}")
        out = []
        for t, row in zip(b.t_bus_ns.tolist(), b.values.tolist(), strict=True):
            m = cls(**dict(zip(names, row, strict=True)))
            m.timestamp.seconds, m.timestamp.nanos = divmod(t + offset_ns, 1_000_000_000)
            out.append((t, m.SerializeToString()))
        return out

    meta = {"fields": json.dumps(dict(zip(names, info.channels, strict=True))),
            "units": json.dumps(dict(zip(names, info.units, strict=True))), "kind": info.kind}
    return ViewChannel(f"/view/{info.name}", schema, encode, meta)


def _finite(*v: float) -> bool:
    return all(math.isfinite(x) for x in v)


class Placement:
    """Where each orientation frame sits in the 3D view: the n-th stream to send an orientation gets
    slot n (``FRAME_SPACING_M`` apart along x), so streams that never send one take no place."""

    def __init__(self) -> None:
        self._slots: dict[str, int] = {}

    def x(self, stream: str) -> float:
        slot = self._slots.setdefault(stream, len(self._slots))
        return FRAME_SPACING_M * slot


def orientation_view(info: StreamInfo, placement: Placement) -> ViewChannel:
    """``/tf/<stream>``: the rotation as a ``FrameTransform`` from ``world`` (rows that are not finite
    are left out of this view only)."""
    frame = info.name

    def encode(b: SampleBatch, offset_ns: int) -> Encoded:
        out: Encoded = []
        x = 0.0
        for t, (w, qx, qy, qz) in zip(b.t_bus_ns.tolist(), b.values.tolist(), strict=True):
            if not _finite(w, qx, qy, qz):
                continue
            if not out:
                x = placement.x(frame)
            m = FrameTransform(timestamp=_stamp(t + offset_ns), parent_frame_id=WORLD, child_frame_id=frame)
            m.translation.x = x
            m.rotation.w, m.rotation.x, m.rotation.y, m.rotation.z = w, qx, qy, qz
            out.append((t, m.SerializeToString()))
        return out

    return ViewChannel(f"/tf/{info.name}", FRAME_TRANSFORM, encode, {"frame": frame})


def skeleton_view(info: StreamInfo, skeleton: dict[str, Any]) -> ViewChannel:
    """``/tf/<stream>`` of a pose stream (``root.x/y/z`` then ``<joint>.w/x/y/z`` per joint, local
    rotations): per sample a ``FrameTransforms`` with one transform per joint from its parent's frame."""
    parents = [int(p) for p in skeleton["parents"]]
    offsets = [tuple(float(v) for v in o) for o in skeleton["offsets"]]
    joints = [c[:-2] for c in info.channels[3::4]]
    if len(joints) != len(parents) or len(offsets) != len(parents) or len(info.channels) != 3 + 4 * len(parents):
        raise ValueError(f"stream {info.name}: its skeleton has {len(parents)} joints, its channels"
                         f" {len(info.channels)}")
    frames = [f"{info.name}/{j}" for j in joints]
    up = math.sqrt(0.5)   # +90 degrees about x: the character's Y up becomes the world's Z up

    def encode(b: SampleBatch, offset_ns: int) -> Encoded:
        out = []
        for t, row in zip(b.t_bus_ns.tolist(), b.values.tolist(), strict=True):
            if not _finite(*row):
                continue
            st = _stamp(t + offset_ns)
            msg = FrameTransforms()
            root = msg.transforms.add(timestamp=st, parent_frame_id=WORLD, child_frame_id=info.name)
            root.rotation.w, root.rotation.x = up, up
            for j, p in enumerate(parents):
                tr = msg.transforms.add(timestamp=st, parent_frame_id=info.name if p < 0 else frames[p],
                                        child_frame_id=frames[j])
                ox, oy, oz = offsets[j]
                if p < 0:
                    ox, oy, oz = ox + row[0], oy + row[1], oz + row[2]
                tr.translation.x, tr.translation.y, tr.translation.z = ox, oy, oz
                k = 3 + 4 * j
                tr.rotation.w, tr.rotation.x, tr.rotation.y, tr.rotation.z = row[k:k + 4]
            out.append((t, msg.SerializeToString()))
        return out

    return ViewChannel(f"/tf/{info.name}", FRAME_TRANSFORMS, encode, {"frames": json.dumps(frames)})


def stream_views(info: StreamInfo, placement: Placement | None = None) -> list[ViewChannel]:
    """The viewable channels of a stream: always its samples; an orientation or a skeleton's pose also
    as transforms (``placement``: where orientation frames go, shared by the streams of one take)."""
    views = [sample_view(info)]
    if info.kind in ORIENTATION_KINDS and len(info.channels) == 4:
        views.append(orientation_view(info, placement if placement is not None else Placement()))
    sk = info.extra.get(SKELETON_KEY)
    if isinstance(sk, str):
        try:
            views.append(skeleton_view(info, json.loads(sk)))
        except (KeyError, TypeError, ValueError) as exc:   # a view less, said once; the samples are kept
            log.warning("stream %s: no 3D view of its skeleton (%s)", info.name, exc)
    return views


_LEVEL = {EventKind.FAILED: Log.ERROR, EventKind.OVERFLOW: Log.ERROR, EventKind.PROTOCOL_ERRORS: Log.WARNING,
          EventKind.DISCONNECTED: Log.WARNING, EventKind.RECONNECTING: Log.WARNING,
          EventKind.CLOCK_RESET: Log.WARNING}


def _text(s: str) -> str:
    """``s`` as protobuf strings must be: valid UTF-8 (a lone surrogate, from OS or network text, replaced)."""
    return s.encode("utf-8", "replace").decode("utf-8")


def encode_event(ev: DeviceEvent, offset_ns: int) -> bytes:
    """An event as a ``foxglove.Log`` on ``/log``."""
    text = ev.kind.value + (f": {ev.detail}" if ev.detail else "")
    return bytes(Log(timestamp=_stamp(ev.t_host_ns + offset_ns), level=_LEVEL.get(ev.kind, Log.INFO),
                     message=_text(text), name=_text(ev.source)).SerializeToString())


# JSON Schemas of the JSON channels, so generic readers validate them
CLOCK_JSONSCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema", "title": "perfcap.ClockState",
    "description": "A device-to-host clock fit: bus = host_ref_ns + (device - device_ref_ns) * rate.",
    "type": "object",
    "properties": {"stream": {"type": "string"}, "t_host_ns": {"type": "integer"}, "epoch": {"type": "integer"},
                   "device_ref_ns": {"type": "integer"}, "host_ref_ns": {"type": "integer"},
                   "rate": {"type": ["number", "null"], "description": "null: not finite"},
                   "points": {"type": "integer"}, "pseudo": {"type": "boolean"},
                   "drift_ppm": {"type": ["number", "null"]}},
    "required": ["stream", "t_host_ns", "epoch", "device_ref_ns", "host_ref_ns", "rate", "points", "pseudo"],
}
EVENT_JSONSCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema", "title": "perfcap.DeviceEvent",
    "description": "Something that happened to a device or the recorder.",
    "type": "object",
    "properties": {"source": {"type": "string"}, "kind": {"enum": [k.value for k in EventKind]},
                   "t_host_ns": {"type": "integer"}, "detail": {"type": "string"}},
    "required": ["source", "kind", "t_host_ns", "detail"],
}
