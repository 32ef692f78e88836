"""LSL on loopback for tests: liblsl's own configuration file, pointed at by ``LSLAPICFG``.

By default liblsl resolves streams by multicast up to site scope, so a test could see (or be seen by)
LSL streams of other programs on the network. The file written here keeps discovery to the link
(``ResolveScope = link``: multicast that no router forwards, looped back to this machine's own
sockets; ``machine`` scope would need multicast on the loopback interface, which containers often
lack, and the loopback address as a known peer alone finds only one outlet per machine, because
every outlet's responder shares one port), disables IPv6 and gives the run its own ``SessionID`` (so
parallel test runs, here or on the link, never see each other's streams) and logs errors only. liblsl
reads the file once per process, when it is first used: ``configure()`` runs at the import of the root
conftest, before any test loads pylsl, and child processes (the two-process tests) inherit the variable.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

CONFIG = """\
[ports]
IPv6 = disable

[multicast]
ResolveScope = link
KnownPeers = {{127.0.0.1}}

[lab]
SessionID = {session}

[log]
level = -2
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

