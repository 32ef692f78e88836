"""MCAP log times of a session are wall-clock UTC (host time plus the recorded offset), monotonic per channel,
and no message is published after its log time, so a viewer's timeline shows when the take happened."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from mcap.reader import make_reader

from capture.app.orchestrator import Capture
from capture.session import LOG_TIME_OFFSET_KEY, SessionReader
from capture.session_blocks import SAMPLES_ENCODING
from capture.session_decoder import DecoderFactory

if TYPE_CHECKING:
    from pathlib import Path


def test_log_times_are_wall_clock_and_monotonic_per_channel(tmp_path: Path) -> None:
    out = tmp_path / "t.mcap"
    before = time.time_ns()
    rep = Capture(["w=witmotion@synth://imu?realtime=false&duration=2&rate=100&device_clock=true",
                   "a=synth://imu?rate=100&seed=1&realtime=false&duration=2"], output=str(out), fsync=False).run(None)
    after = time.time_ns()
    assert rep.recorder_error is None
    last: dict[int, int] = {}
    n = 0
    offset = None
    with out.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for meta in reader.iter_metadata():
            if meta.name == "perfcap.session":
                offset = int(meta.metadata[LOG_TIME_OFFSET_KEY])
        assert offset is not None
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            n += 1
            assert before - 5_000_000_000 <= message.log_time <= after + 5_000_000_000, channel.topic
            assert message.publish_time <= message.log_time
            assert message.log_time >= last.get(channel.id, 0), channel.topic
            last[channel.id] = message.log_time
            if channel.message_encoding == SAMPLES_ENCODING:
                # a block's log time is its first bus time on the wall clock
                assert message.log_time == int(decoded.t_bus_ns[0]) + offset
    assert n > 10
    # perfcap's own reading is unchanged
    assert sum(len(b) for b in SessionReader(str(out)).all_samples().values()) > 400
