"""perfcap capture core: samples with two clocks, clock sync, the sample bus, sessions, replay."""

__version__ = "0.1.0"
