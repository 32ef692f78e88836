"""A check of an MCAP file as a generic viewer sees it, written without perfcap's code (only ``mcap``,
``mcap-protobuf-support`` and ``jsonschema``): every channel has a schema a viewer understands and every
message decodes with it (protobuf with its ``FileDescriptorSet``, or JSON valid against its JSON Schema);
log times are on the wall clock and monotonic per channel; no publish time is later than its log time.
``tests/test_generic_check_is_generic.py`` holds this module to importing nothing of perfcap's."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import jsonschema
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

if TYPE_CHECKING:
    from pathlib import Path

#: log times a wall clock can give: after 2020-01-01 and not in the future (beyond a day of skew)
EARLIEST_NS = 1_577_836_800 * 10**9


@dataclass
class Report:
    messages: dict[str, int] = field(default_factory=dict)
    schemas: dict[str, str] = field(default_factory=dict)    # topic -> "encoding:schema name"
    problems: list[str] = field(default_factory=list)
    first_log_ns: dict[str, int] = field(default_factory=dict)
    last_log_ns: dict[str, int] = field(default_factory=dict)

    def problem(self, text: str) -> None:
        if len(self.problems) < 50:
            self.problems.append(text)


def check(path: Path) -> Report:
    rep = Report()
    latest = time.time_ns() + 86_400 * 10**9
    protobuf = DecoderFactory()
    decoders: dict[int, object] = {}
    validators: dict[int, jsonschema.protocols.Validator] = {}
    with path.open("rb") as f:
        for schema, channel, msg in make_reader(f).iter_messages(log_time_order=False):
            topic = channel.topic
            rep.messages[topic] = rep.messages.get(topic, 0) + 1
            if schema is None:
                rep.problem(f"{topic}: no schema")
                continue
            rep.schemas[topic] = f"{channel.message_encoding}:{schema.name}"
            try:
                if channel.message_encoding == "protobuf" and schema.encoding == "protobuf":
                    dec = decoders.get(channel.id)
                    if dec is None:
                        dec = decoders[channel.id] = protobuf.decoder_for("protobuf", schema)
                    if dec is None:
                        rep.problem(f"{topic}: the protobuf decoder refuses schema {schema.name}")
                        continue
                    dec(msg.data)  # type: ignore[operator]
                elif channel.message_encoding == "json" and schema.encoding == "jsonschema":
                    v = validators.get(channel.id)
                    if v is None:
                        js = json.loads(schema.data)
                        cls = jsonschema.validators.validator_for(js)
                        cls.check_schema(js)
                        v = validators[channel.id] = cls(js)
                    v.validate(json.loads(msg.data))
                else:
                    rep.problem(f"{topic}: message encoding {channel.message_encoding!r} with a"
                                f" {schema.encoding!r} schema is not one a generic viewer decodes")
                    continue
            except Exception as exc:
                rep.problem(f"{topic}: message {msg.sequence} does not decode: {type(exc).__name__}: {exc}")
                continue
            if not EARLIEST_NS <= msg.log_time <= latest:
                rep.problem(f"{topic}: log time {msg.log_time} is not on the wall clock")
            if msg.publish_time > msg.log_time:
                rep.problem(f"{topic}: publish time {msg.publish_time} after log time {msg.log_time}")
            last = rep.last_log_ns.get(topic)
            if last is not None and msg.log_time < last:
                rep.problem(f"{topic}: log time steps back from {last} to {msg.log_time}")
            rep.first_log_ns.setdefault(topic, msg.log_time)
            rep.last_log_ns[topic] = msg.log_time
    return rep
