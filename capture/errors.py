"""Every exception perfcap raises on purpose, in one tree.

::

    CaptureError(Exception)                      .source, .code (appended to the message)
     ├─ ConfigError(CaptureError, ValueError)    bad device string, config file or option
     ├─ DeviceError
     │   ├─ DeviceUnavailableError(DeviceError, NotImplementedError)  unknown kind/scheme, missing dep
     │   ├─ DeviceNotFoundError                   nothing at that address
     │   ├─ DeviceInitError                       open or handshake failed
     │   ├─ DeviceIOError                         the byte pipe failed (wraps OSError ``from``)
     │   ├─ DeviceTimeoutError(DeviceError, TimeoutError)
     │   └─ EndOfStream                           a finite source (replay, synth) has no more bytes
     ├─ ProtocolError (.offset, .raw)             a codec met bytes it cannot parse
     ├─ SessionError (.path)                      a session file cannot be written or read
     │   └─ SessionExistsError(SessionError, FileExistsError)
     ├─ TraceError (.path, .line)                 a text trace is malformed
     ├─ CycleError                                 no clean cycle could be extracted
     │   ├─ NoMotionError                          the input does not move
     │   └─ NoPeriodFoundError                     the input moves but does not repeat (or too few loops)
     └─ RetargetError → InvalidTransitionError (.state, .event)

Foreign exceptions are translated at the transport and file boundaries with ``raise ... from``.
Misused arguments stay plain ``ValueError``/``TypeError``.
"""

from __future__ import annotations


class CaptureError(Exception):
    """Base of all perfcap errors.

    Args:
        message: what went wrong, in one line a user can act on.
        source: the device, stream, file or key the error is about.
        code: an optional machine-readable code, appended to the message.
    """

    def __init__(self, message: str, *, source: str | None = None, code: str | None = None) -> None:
        self.source = source
        self.code = code
        text = message if code is None else f"{message} [{code}]"
        super().__init__(text)


class ConfigError(CaptureError, ValueError):
    """A device string, config file, URL option or CLI argument is invalid."""


class DeviceError(CaptureError):
    """A device could not be used."""


class DeviceUnavailableError(DeviceError, NotImplementedError):
    """The kind or scheme is unknown here, or a dependency is missing."""


class DeviceNotFoundError(DeviceError):
    """Nothing answers at the given address."""


class DeviceInitError(DeviceError):
    """Opening or the handshake failed."""


class DeviceIOError(DeviceError):
    """Reading or writing the byte pipe failed (the device may have been unplugged)."""


class DeviceTimeoutError(DeviceError, TimeoutError):
    """The device did not answer in time."""


class EndOfStream(DeviceError):  # noqa: N818 - the end of a finite source, not a failure
    """A finite source (a replayed session, a synthetic take with a duration) is exhausted."""


class ProtocolError(CaptureError):
    """A codec met bytes it cannot parse.

    Args:
        message: what was wrong.
        offset: byte offset of the problem in the codec's input, when known.
        raw: the offending bytes, when known.
    """

    def __init__(self, message: str, *, offset: int | None = None, raw: bytes | None = None,
                 source: str | None = None, code: str | None = None) -> None:
        super().__init__(message, source=source, code=code)
        self.offset = offset
        self.raw = raw


class SessionError(CaptureError):
    """A session file cannot be written or read."""

    def __init__(self, message: str, *, path: str | None = None, code: str | None = None) -> None:
        super().__init__(message, source=path, code=code)
        self.path = path


class SessionExistsError(SessionError, FileExistsError):
    """The output session already exists and overwriting was not asked for."""


class TraceError(CaptureError):
    """A text trace is malformed."""

    def __init__(self, message: str, *, path: str | None = None, line: int | None = None) -> None:
        where = f"{path}:{line}: " if path and line else (f"{path}: " if path else "")
        super().__init__(where + message, source=path)
        self.path = path
        self.line = line


class CycleError(CaptureError):
    """No clean cycle could be extracted from the input."""


class NoMotionError(CycleError):
    """The input is constant (or every channel is): there is nothing to loop."""


class NoPeriodFoundError(CycleError):
    """The input moves but no period repeats consistently over at least two loops."""


class RetargetError(CaptureError):
    """The retargeting layer was misused."""


class InvalidTransitionError(RetargetError):
    """A state machine got an event its current state does not accept."""

    def __init__(self, message: str, *, state: object = None, event: object = None) -> None:
        super().__init__(message)
        self.state = state
        self.event = event
