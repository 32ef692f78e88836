"""Phones running apps people already use, one module per app.

* ``devices.phone_apps.osc``: OSC apps over UDP (ZIG SIM, GyrOSC-style, or a custom address map),
  kind ``osc``, device ``OscPhone``; codec ``devices.codecs.osc``.
* ``devices.phone_apps.hyperimu``: HyperIMU's CSV rows over UDP or TCP, kind ``hyperimu``, device
  ``HyperImuPhone``; codec ``devices.codecs.hyperimu``.
* ``devices.phone_apps.sensorserver``: the SensorServer app, whose WebSocket server perfcap
  connects to, kind ``sensorserver``, device ``SensorServerPhone``; codec
  ``devices.codecs.sensorserver``, transport ``devices.transports.sensorserver``.

What they share (the phone frame and its units, stream declarations, ``AppDevice``) is
``devices.phone_apps.base``. Each device module owns what its app's values mean (streams, units,
signs, clocks); the codec owns the wire syntax. None of these apps is in ``../shared/traces``; the
layouts follow ``docs/design/phone-protocols.md`` (sections 1, 2 and 4). perfcap's own phone page
and Sensor Logger are ``devices.phone``.
"""
