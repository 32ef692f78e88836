"""StreamStats, the live per-stream counter every capture runs: events stay bounded even when a
device sends garbage for hours (each protocol-error event is counted per device, not kept)."""

from __future__ import annotations

from capture.app.orchestrator import StreamStats
from capture.sample import DeviceEvent, EventKind, Sample


def test_protocol_error_events_are_counted_per_device_and_not_kept():
    st = StreamStats()
    for i in range(5000):
        st.on_item(DeviceEvent("phone-a" if i % 2 else "phone-b", EventKind.PROTOCOL_ERRORS, i, f"{i} errors"))
    st.on_item(DeviceEvent("phone-a", EventKind.DISCONNECTED, 6000, "gone"))
    assert st.protocol_error_events == {"phone-a": 2500, "phone-b": 2500}
    assert [e.kind for e in st.events] == [EventKind.DISCONNECTED]


def test_other_events_are_kept_up_to_the_bound_and_the_rest_counted():
    st = StreamStats()
    n = StreamStats.MAX_EVENTS + 7
    for i in range(n):
        st.on_item(DeviceEvent("pad", EventKind.RECONNECTED, i, "back"))
    assert len(st.events) == StreamStats.MAX_EVENTS
    assert st.events_not_kept == 7
    assert st.events[0].t_host_ns == 0  # the first ones are kept (the start of a take explains the rest)


def test_samples_still_counted_between_events():
    st = StreamStats()
    st.on_item(Sample("phone-a/imu", 0, 10, None, 10, (0.0,)))
    st.on_item(DeviceEvent("phone-a", EventKind.PROTOCOL_ERRORS, 11, "1 errors"))
    st.on_item(Sample("phone-a/imu", 2, 20, None, 20, (0.0,)))
    snap = st.snapshot()["phone-a/imu"]
    assert snap["samples"] == 2 and snap["drops"] == 1
