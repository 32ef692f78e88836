"""LSL on loopback for tests: liblsl's own configuration file, pointed at by ``LSLAPICFG``.

By default liblsl resolves streams by multicast on every interface, so a test could see (or be seen
by) LSL streams of other programs on the network and could fail where multicast is filtered. The file
written here keeps discovery on this machine (``ResolveScope = machine``, the loopback address as the
one known peer), disables IPv6 and gives the run its own ``SessionID`` (so parallel test runs on one
machine never see each other's streams) and logs warnings only. liblsl reads the file once per process,
when it is first used: ``configure()`` runs at the import of the root conftest, before any test loads pylsl, and child
processes (the two-process tests) inherit the variable.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

CONFIG = """\
[ports]
IPv6 = disable

[multicast]
ResolveScope = machine
KnownPeers = {{127.0.0.1}}

[lab]
SessionID = {session}

[log]
level = -1
"""


def configure() -> Path:
    """Write this run's liblsl configuration (once) and point ``LSLAPICFG`` at it; returns the file."""
    given = os.environ.get("LSLAPICFG")
    if given:
        return Path(given)
    path = Path(tempfile.mkdtemp(prefix="perfcap-lsl-")) / "lsl_api.cfg"
    path.write_text(CONFIG.format(session=f"perfcap-test-{os.getpid()}"))
    os.environ["LSLAPICFG"] = str(path)
    return path


def resolve_by_name(name: str, timeout: float = 60.0) -> object:
    """The ``pylsl.StreamInfo`` of the one stream called ``name`` in this run's session, resolved with a
    predicate and retried until ``timeout`` (same-host discovery of many outlets can take several
    rounds); never a sleep. Raises ``AssertionError`` when it is not found in time."""
    import time

    import pylsl

    end = time.monotonic() + timeout
    pred = f"name='{name}'"
    while True:
        found = pylsl.resolve_bypred(pred, 1, 2.0)
        if found:
            return found[0]
        if time.monotonic() > end:
            raise AssertionError(f"LSL stream {name!r} not resolved within {timeout} s")


def gone(name: str, wait_s: float = 0.5) -> bool:
    """True when no stream called ``name`` answers within ``wait_s``."""
    import pylsl

    return not pylsl.resolve_bypred(f"name='{name}'", 0, wait_s)
