"""Shared by the puppet tests (CLI and unit): a recorded perfcap session of the built-in phone page,
made from simulated page messages through the real page codec, ``PhonePage``, clock sync and recorder.
``conftest.py`` hands it to tests as the ``record_phone_session`` fixture."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from wait_helpers import DEADLINE_S, wait_until

if TYPE_CHECKING:
    from pathlib import Path


def record_phone_session(path: Path, duration_s: float = 3.0, touch: tuple[float, float] | None = None,
                          seed: int = 3, motion: str = "waving") -> Path:
    """A perfcap session of the built-in phone page: simulated page messages (waving motion, attitude
    every third event) through the real page codec, ``PhonePage``, clock sync and recorder. ``touch``:
    one finger down from ``touch[0]`` to ``touch[1]`` seconds after the first event (moves every 50 ms);
    ``motion``: ``waving`` or ``puppeteer`` (``sim_devices.motion.phone_motion``)."""
    import uuid

    import numpy as np

    from capture.app.orchestrator import Capture
    from capture.sample import Chunk, Direction
    from devices.codecs.phone_json import PageCodec
    from devices.transports.network import drop_hub, hub
    from sim_devices.phone_sim import page_hello, page_messages

    msgs = page_messages(duration_s, seed=seed, t0_ms=1500.0, motion=motion)
    codec = PageCodec()
    rows = []
    if touch is not None:
        times = np.arange(touch[0], touch[1] + 1e-9, 0.05)
        for k, tt in enumerate(times):
            phase = 0.0 if k == 0 else (2.0 if k == len(times) - 1 else 1.0)
            rows.append((1500.0 + 1000.0 * tt + 0.25, phase, 4.0, 200.0, 300.0, 0.0, 10.0, 10.0))
    datas = []
    for m in msgs:   # each touch goes out with the first message sent after it
        mine = tuple(r for r in rows if r[0] <= m.sent_ms)
        rows = rows[len(mine):]
        datas.append((codec.encode(m.frame._replace(touches=mine)), m.sent_ms))
    name = "puppet-test-" + uuid.uuid4().hex[:10]
    box = hub(name).inbox("page/p1")
    box.connect("test")
    t0 = time.monotonic_ns()
    box.put(Chunk(page_hello(), t0, Direction.RX))
    for data, sent_ms in datas:
        box.put(Chunk(data, t0 + int(sent_ms * 1e6) + 20_000_000, Direction.RX))

    cap = Capture([f"phone=phone@net://{name}/page/p1"], output=str(path), overwrite=True)
    try:
        cap.start()
        phone = cap.devices[0]
        wait_until(lambda: phone.transport.is_open, DEADLINE_S, "the phone's reader to open its inbox")
        box.finish()  # nothing more will come: the reader drains the inbox, then the take ends
        assert all(r.join(DEADLINE_S) for r in cap.readers), "the phone's reader did not drain its inbox"
    finally:
        cap.stop()
        drop_hub(name)
    return path
