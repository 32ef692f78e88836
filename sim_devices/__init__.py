"""Simulated devices. They plug in at the Transport, so their bytes take the same Codec and Device
path as live bytes. Reached only by URL scheme through the ``perfcap.transports`` entry points
(``synth://``, ``simhid://``, ``replay://``) and by ``perfcap sim``; production code never imports
this package. The simulated transports declare what they can do beyond ``Transport`` with the
protocols of ``devices.transports.base`` (``BatchSource``, ``RecordedTimeline``, ``SimulatorTruth``).
"""
