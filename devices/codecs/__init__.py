"""Codecs: sans-IO parsers (bytes -> frames) with encoders (frames -> bytes) for simulators.

One module per wire protocol, each owning that protocol's syntax (``base`` the ``Codec`` interface):
``witmotion``, ``bno08x_rvc``, ``textline``, ``sony``, ``nintendo``, ``phone_json`` (perfcap's phone
page and Sensor Logger), ``osc``, ``hyperimu`` and ``sensorserver``. What the values mean is the
device kind's module, in ``devices``.
"""
