"""Decoders of perfcap's session channels for the ``mcap`` library's decoded reader.

``mcap.reader.make_reader(f, decoder_factories=[DecoderFactory()])`` then yields every message of a perfcap
session decoded, from sessions of any perfcap version (the blocks are self-describing):

* ``/samples/<stream>`` (protobuf ``perfcap.SampleBlock``, or ``perfcap.samples.v1`` in format 1 sessions): a
  :class:`~capture.sample.SampleBatch` (sequence numbers, host, device and bus times, values);
* ``/raw/<device>`` (protobuf ``perfcap.RawBlock``, or ``perfcap.raw.v1``): a list of
  :class:`~capture.sample.Chunk` (bytes, arrival time, direction), exactly what the transport delivered;
* ``/view/...``, ``/tf/...``, ``/log`` (protobuf, Foxglove's and perfcap's view schemas): the protobuf
  message, decoded by ``mcap-protobuf-support`` from the schema the session carries;
* ``/clock/<stream>`` and ``/events`` (``json``, with a JSON Schema or, in format 1, none): the JSON object.

Example::

    from mcap.reader import make_reader
    from capture.session_decoder import DecoderFactory

    with open("take.mcap", "rb") as f:
        for schema, channel, message, decoded in make_reader(f, decoder_factories=[DecoderFactory()]
                                                             ).iter_decoded_messages():
            ...

A damaged message raises ``ValueError`` from the decoder; :class:`capture.session.SessionReader` is the
reader that reads around damage.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any

from mcap.decoder import DecoderFactory as _McapDecoderFactory
from mcap_protobuf.decoder import DecoderFactory as _ProtobufDecoderFactory

from capture.session_blocks import (
    PROTOBUF,
    RAW_BLOCK,
    RAW_ENCODING,
    SAMPLE_BLOCK,
    SAMPLES_ENCODING,
    decode_raw_block,
    decode_raw_run,
    decode_sample_block,
    decode_samples,
)

if TYPE_CHECKING:
    from collections.abc import Callable

    from mcap.records import Schema

__all__ = ["DecoderFactory"]


def _samples(data: bytes) -> Any:
    return decode_sample_block("a perfcap sample channel", data)


def _samples_pb(data: bytes) -> Any:
    return decode_samples("a perfcap sample channel", data)


def _raw_pb(data: bytes) -> Any:
    return list(decode_raw_run(data))


def _json(data: bytes) -> Any:
    return json.loads(data)


class DecoderFactory(_McapDecoderFactory):
    """Decodes perfcap's blocks to its own types, its other protobuf channels with ``mcap-protobuf-support``
    and its JSON channels; a channel of any other encoding is left to the next factory."""

    def __init__(self) -> None:
        self._protobuf = _ProtobufDecoderFactory()

    def decoder_for(self, message_encoding: str, schema: Schema | None) -> Callable[[bytes], Any] | None:
        if message_encoding == PROTOBUF and schema is not None:
            if schema.name == SAMPLE_BLOCK.name:
                return _samples_pb
            if schema.name == RAW_BLOCK.name:
                return _raw_pb
            return self._protobuf.decoder_for(message_encoding, schema)
        if message_encoding == SAMPLES_ENCODING:
            return _samples
        if message_encoding == RAW_ENCODING:
            return decode_raw_block
        if message_encoding == "json" and (schema is None or schema.id == 0 or not schema.data
                                           or schema.encoding == "jsonschema"):
            return _json
        return None
