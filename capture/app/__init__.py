"""The application layer: the only place that wires perfcap's packages together.

It owns the command line (``cli/``, one module per command), the capture service (``serve/``),
the ``Capture`` orchestration of devices, bus and recorder, whole-session replay, config
loading, the puppet runner, the cycle follower and cycle inputs, export, the calibration
workflow and the demo. Everything below it (``capture``'s core, ``devices``, ``cycles``,
``retarget``) never imports it.
"""
