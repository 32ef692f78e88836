"""Simulated devices. They plug in at the Transport, so their bytes take the same Codec and Device
path as live bytes. Reached only by URL scheme through the ``perfcap.transports`` entry points
(``synth://``, ``replay://``); production code never imports this package.
"""
