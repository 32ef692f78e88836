"""Decoders of perfcap's session channels for the ``mcap`` library's decoded reader.

``mcap.reader.make_reader(f, decoder_factories=[DecoderFactory()])`` then yields every message of a perfcap
session decoded, from sessions of any perfcap version (the blocks are self-describing):

* ``/samples/<stream>`` (``perfcap.samples.v1``): a :class:`~capture.sample.SampleBatch` (sequence numbers,
  host, device and bus times, values);
* ``/raw/<device>`` (``perfcap.raw.v1``): a list of :class:`~capture.sample.Chunk` (bytes, arrival time,
  direction), exactly what the transport delivered;
* ``/clock/<stream>`` and ``/events`` (``json``, no schema): the JSON object.

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

from capture.session import RAW_ENCODING, SAMPLES_ENCODING, decode_raw_block, decode_sample_block

if TYPE_CHECKING:
    from collections.abc import Callable

    from mcap.records import Schema

__all__ = ["DecoderFactory"]


def _samples(data: bytes) -> Any:
    return decode_sample_block("a perfcap sample channel", data)


def _json(data: bytes) -> Any:
    return json.loads(data)


class DecoderFactory(_McapDecoderFactory):
    """Decodes perfcap's channel encodings (``perfcap.samples.v1``, ``perfcap.raw.v1``) and its schemaless
    JSON channels; any other channel is left to the next factory."""

    def decoder_for(self, message_encoding: str, schema: Schema | None) -> Callable[[bytes], Any] | None:
        if message_encoding == SAMPLES_ENCODING:
            return _samples
        if message_encoding == RAW_ENCODING:
            return decode_raw_block
        if message_encoding == "json" and (schema is None or schema.id == 0 or not schema.data):
            return _json
        return None
