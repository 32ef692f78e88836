"""Codecs: sans-IO parsers (bytes -> frames) with encoders (frames -> bytes) for simulators."""
