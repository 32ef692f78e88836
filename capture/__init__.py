"""perfcap's capture core: samples with two clocks, clock sync, the sample bus, sessions, orientation and
calibration maths (``capture.*`` outside ``capture.app``, importing only ``capture``); the application
that wires every package together is ``capture.app``.

``__version__`` is perfcap's one version string: the package metadata, ``perfcap --version`` and every
session's ``perfcap_version`` read it from here.
"""

__version__ = "0.1.0"
