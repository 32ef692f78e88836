"""The built-in phone page (``capture/app/serve/static/phone.html``) in headless Chromium, against a small
server written here that speaks the page protocol v1 (hello, welcome, data, ping/pong, close codes).

This checks the page on its own; the end-to-end test through ``perfcap serve`` (TLS, devices, bus)
lives with the service. Motion and touch events are synthetic, dispatched inside the page, and a
real tap comes from Playwright's touchscreen.
"""

from __future__ import annotations

import asyncio
import json
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest
from aiohttp import WSMsgType, web
from wait_helpers import DEADLINE_S

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator

    from playwright.sync_api import Page

PAGE = Path(__file__).resolve().parents[2] / "capture" / "app" / "serve" / "static" / "phone.html"
TOKEN = "Zq3-pairing_token-7f"
DEVICE = "phone-test"
BIG_H = 2**53 + 1  # a host ns value a JS number cannot hold: the page must echo it digit for digit
TOKEN_MESSAGE = ("the pairing token is missing or wrong: open the link or scan the QR code that "
                 "perfcap serve printed")


class ProtocolServer:
    """Serves the page at ``/`` and protocol v1 at ``/ws/phone`` on 127.0.0.1 (plain http), from an
    asyncio loop in a background thread. Every text frame received is kept as (connection, raw text)."""

    def __init__(self, token: str) -> None:
        self.token = token
        self.hold = False  # while True, each new socket is closed at once with 1013 (try again later)
        self.ping_s = 60.0  # announced in the welcome; long, so the page's watchdog stays quiet by default
        self.connections = 0
        self.messages: list[tuple[int, str]] = []
        self.closes: list[tuple[int, int | None]] = []  # (connection, close code the page sent or None)
        self._cond = threading.Condition()
        self._ws: web.WebSocketResponse | None = None
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="phone-page-server", daemon=True)
        self._runner: web.AppRunner | None = None
        self.url = ""

    # -- lifecycle (called from the test thread) --
    def start(self) -> None:
        self._thread.start()
        self._call(self._start())

    def stop(self) -> None:
        # Everything runs in the server thread: while Playwright's sync API is alive, the main thread
        # already counts as running an event loop (Playwright's), so run_until_complete() there raises.
        try:
            self._call(self._stop())
        finally:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(DEADLINE_S)
            self._loop.close()

    def _call(self, coro: Any, timeout: float = DEADLINE_S) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(timeout)

    async def _start(self) -> None:
        app = web.Application()
        app.router.add_get("/", self._page)
        app.router.add_get("/ws/phone", self._phone)
        self._runner = web.AppRunner(app)
        await self._runner.setup()
        site = web.TCPSite(self._runner, "127.0.0.1", 0)
        await site.start()
        host, port = self._runner.addresses[0][:2]
        self.url = f"http://{host}:{port}/"

    async def _stop(self) -> None:
        if self._ws is not None:
            await self._ws.close(code=1001, message=b"test over")
        assert self._runner is not None
        await self._runner.cleanup()
        await self._loop.shutdown_asyncgens()

    # -- handlers (server thread) --
    async def _page(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(PAGE, headers={"Cache-Control": "no-store"})

    async def _phone(self, request: web.Request) -> web.StreamResponse:
        ws = web.WebSocketResponse(max_msg_size=1 << 20)
        await ws.prepare(request)
        with self._cond:
            self.connections += 1
            conn = self.connections
            self._cond.notify_all()
        if self.hold:
            await ws.close(code=1013, message=b"try again later")
            return ws
        first = await ws.receive(timeout=DEADLINE_S)
        if first.type != WSMsgType.TEXT:
            await ws.close(code=4400, message=b"expected hello")
            return ws
        self._record(conn, first.data)
        hello = json.loads(first.data)
        if hello.get("type") != "hello" or hello.get("v") != 1:
            await ws.close(code=4400, message=b"expected hello v1")
            return ws
        if hello.get("token") != self.token:
            await ws.close(code=4401, message=b"missing or wrong token")
            return ws
        self._ws = ws
        # The tests send their own pings (none unless a test does).
        await ws.send_str(json.dumps({"type": "welcome", "device": DEVICE, "ping_s": self.ping_s}))
        async for msg in ws:
            if msg.type == WSMsgType.TEXT:
                self._record(conn, msg.data)
        with self._cond:
            self.closes.append((conn, ws.close_code))
            self._cond.notify_all()
        if self._ws is ws:
            self._ws = None
        return ws

    def _record(self, conn: int, text: str) -> None:
        with self._cond:
            self.messages.append((conn, text))
            self._cond.notify_all()

    # -- test-side helpers --
    def send(self, obj: dict[str, Any]) -> None:
        assert self._ws is not None, "no page connected"
        self._call(self._ws.send_str(json.dumps(obj)))

    def drop(self, code: int = 1001) -> None:
        """Close the page's socket from the server side."""
        ws = self._ws
        assert ws is not None, "no page connected"
        self._ws = None
        self._call(ws.close(code=code, message=b"server-side drop"))

    def wait(self, what: str, pred: Callable[[list[tuple[int, str]]], Any], timeout: float = DEADLINE_S) -> Any:
        """Wait until ``pred(messages)`` is truthy and return its value."""
        with self._cond:
            out = self._cond.wait_for(lambda: pred(list(self.messages)), timeout)
            assert out, f"timed out waiting for {what}; received: {self.messages[-10:]}"
            return out

    def of_type(self, kind: str) -> list[tuple[int, dict[str, Any]]]:
        with self._cond:
            msgs = list(self.messages)
        return [(c, m) for c, m in ((c, json.loads(t)) for c, t in msgs) if m.get("type") == kind]

    def rows(self, key: str) -> list[list[Any]]:
        return [row for _, m in self.of_type("data") for row in m.get(key, [])]


def wait_rows(server: ProtocolServer, key: str, n: int, timeout: float = DEADLINE_S) -> list[list[Any]]:
    return server.wait(f"{n} {key!r} rows", lambda _: len(server.rows(key)) >= n and server.rows(key), timeout)


@pytest.fixture
def server() -> Iterator[ProtocolServer]:
    if not PAGE.is_file():
        pytest.fail(f"the phone page is missing: {PAGE}")
    s = ProtocolServer(TOKEN)
    s.start()
    try:
        yield s
    finally:
        s.stop()


def open_live(page: Page, server: ProtocolServer, token: str = TOKEN) -> None:
    """Open the page with the token in the fragment, start it without a tap, wait for the welcome."""
    page.goto(server.url + "#t=" + token)
    assert page.evaluate("window.perfcap.start()") is True
    page.wait_for_function("window.perfcap.state === 'live'")


MOTION_JS = """(vals) => {
  const out = [];
  for (const v of vals) {
    const before = performance.now();
    window.dispatchEvent(new DeviceMotionEvent("devicemotion", {
      acceleration: {x: v[0], y: v[1], z: v[2]},
      accelerationIncludingGravity: {x: v[3], y: v[4], z: v[5]},
      rotationRate: {alpha: v[6], beta: v[7], gamma: v[8]},
      interval: v[9]}));
    out.push([before, performance.now()]);
  }
  return out;
}"""


def motion_values(k0: int, n: int) -> list[list[float]]:
    """Distinct, exactly representable values for n motion events (k0 tags the batch)."""
    return [[k0 + i + 0.25, -1.5, 0.125, 0.5, 9.75, -(k0 + i), 10.0 * i, -2.5, k0 + 0.5, 16.0] for i in range(n)]


def dispatch_motion(page: Page, vals: list[list[float]]) -> list[list[float]]:
    return page.evaluate(MOTION_JS, vals)


def dispatched(rows: list[list[Any]], vals: list[list[float]]) -> list[list[Any]]:
    """The rows whose values are one of ``vals`` (a real sensor could add rows of its own)."""
    keys = [tuple(v) for v in vals]
    return [r for r in rows if tuple(r[1:]) in keys]


def test_hello_welcome_and_identity_survive_a_reload(server, page, console_errors):
    page.goto(server.url + "#t=" + TOKEN)
    assert page.evaluate("location.hash") == "", "the token must leave the address bar"
    assert TOKEN not in page.url
    assert page.evaluate("window.perfcap.state") == "idle"
    assert server.connections == 0, "nothing connects before Start"

    t_before = page.evaluate("performance.now()")
    assert page.evaluate("window.perfcap.start()") is True
    page.wait_for_function("window.perfcap.state === 'live'")
    assert json.loads(server.messages[0][1])["type"] == "hello", "hello comes first"
    hello = server.of_type("hello")[0][1]
    assert hello["v"] == 1 and hello["token"] == TOKEN
    stored = page.evaluate("localStorage.getItem('perfcap.phone.id')")
    assert hello["id"] == stored and len(stored) >= 16
    assert hello["ua"] == page.evaluate("navigator.userAgent")
    assert hello["platform"] == "other"  # desktop Linux Chromium's user agent
    assert hello["screen"] == page.evaluate("[screen.width, screen.height]")
    assert hello["orient"] == page.evaluate("screen.orientation.angle")
    assert t_before <= hello["t"] <= page.evaluate("performance.now()")

    assert page.evaluate("window.perfcap.device") == DEVICE
    page.wait_for_function(f"document.getElementById('s-device').textContent === {DEVICE!r}")
    assert DEVICE in page.inner_text("#msg")
    assert page.get_by_role("button", name="Running").is_disabled()

    # Read-only: tests (or stray scripts) cannot overwrite the state.
    page.evaluate("window.perfcap.dropped = 99; window.perfcap = null")
    assert page.evaluate("window.perfcap.dropped") == 0

    page.reload()  # the fragment is gone now: the token comes from sessionStorage, the id from localStorage
    assert page.evaluate("location.hash") == ""
    assert page.evaluate("window.perfcap.start()") is True
    page.wait_for_function("window.perfcap.state === 'live'")
    hellos = server.wait("a second hello", lambda _: len(server.of_type("hello")) >= 2 and server.of_type("hello"))
    (c1, h1), (c2, h2) = hellos
    assert c2 > c1 and h2["id"] == h1["id"] and h2["token"] == TOKEN
    assert console_errors == []


def test_motion_orientation_and_touch_arrive_as_rows(server, page, console_errors):
    open_live(page, server)
    vals = motion_values(1, 5)
    windows = dispatch_motion(page, vals)
    o_window = page.evaluate("""() => {
      const before = performance.now();
      window.dispatchEvent(new DeviceOrientationEvent("deviceorientation",
        {alpha: 123.5, beta: -45.25, gamma: 10.75, absolute: true}));
      return [before, performance.now()];
    }""")
    t_windows = page.evaluate("""() => {
      const pad = document.getElementById("pad"), out = [];
      const mk = (x, y) => new Touch({identifier: 7, target: pad, clientX: x, clientY: y,
                                      force: 0.5, radiusX: 3, radiusY: 4});
      for (const [type, x, y] of [["touchstart", 100, 400], ["touchmove", 120, 410], ["touchend", 120, 410]]) {
        const t = mk(x, y), before = performance.now();
        const live = type === "touchend" ? [] : [t];
        pad.dispatchEvent(new TouchEvent(type, {changedTouches: [t], touches: live, targetTouches: live,
                                                bubbles: true, cancelable: true}));
        out.push([before, performance.now()]);
      }
      return out;
    }""")
    box = page.locator("#pad").bounding_box()
    assert box is not None
    tap = (round(box["x"] + box["width"] / 2), round(box["y"] + box["height"] / 2))
    page.touchscreen.tap(*tap)  # a real (trusted) touch through the browser's input pipeline

    m_rows = server.wait("the 5 motion rows", lambda _: len(dispatched(server.rows("m"), vals)) >= 5
                         and dispatched(server.rows("m"), vals))
    assert [r[1:] for r in m_rows] == vals  # order and values (m/s^2, deg/s, ms) unchanged
    for row, (before, after) in zip(m_rows, windows, strict=True):
        assert before <= row[0] <= after, "t is event.timeStamp, ms since performance.timeOrigin"

    # wait for the dispatched row itself: the browser may send an orientation row of its own first
    def ours(_: object) -> list[list[Any]]:
        return [r for r in server.rows("o") if r[1:] == [123.5, -45.25, 10.75, 1]]

    o_rows = server.wait("the dispatched orientation row", ours)
    assert len(o_rows) == 1 and o_window[0] <= o_rows[0][0] <= o_window[1]

    t_rows = server.wait("5 touch rows", lambda _: len(server.rows("t")) >= 5 and server.rows("t"))
    synthetic = [r for r in t_rows if r[2] == 7]
    assert [r[1:] for r in synthetic] == [[0, 7, 100, 400, 0.5, 3, 4], [1, 7, 120, 410, 0.5, 3, 4],
                                          [2, 7, 120, 410, 0.5, 3, 4]]
    for row, (before, after) in zip(synthetic, t_windows, strict=True):
        assert before <= row[0] <= after
    tapped = [r for r in t_rows if r[2] != 7]
    assert [r[1] for r in tapped] == [0, 2]  # start, end
    assert all(abs(r[3] - tap[0]) <= 1 and abs(r[4] - tap[1]) <= 1 for r in tapped)
    assert tapped[0][0] <= tapped[1][0]

    data = [m for _, m in server.of_type("data")]
    assert [m["seq"] for m in data] == list(range(len(data)))
    for m in data:
        assert set(m) <= {"type", "seq", "sent", "orient", "m", "o", "t"}
        assert all(m.get(k) != [] for k in ("m", "o", "t")), "only non-empty arrays are sent"
        assert m["orient"] == 0
        assert all(m["sent"] >= row[0] for k in ("m", "o", "t") for row in m.get(k, []))

    state = page.evaluate("(({start, ...rest}) => rest)(window.perfcap)")
    assert state["motionEvents"] >= 5 and state["orientationEvents"] >= 1 and state["touchEvents"] >= 5
    assert state["sent"] == len(data) and state["seq"] == len(data) and state["queued"] == 0
    assert state["dropped"] == 0 and state["lastClose"] is None
    page.wait_for_function("document.getElementById('s-sensors').textContent === 'motion ok'")
    assert console_errors == []


def test_ping_is_answered_with_the_same_h(server, page, console_errors):
    open_live(page, server)
    t0 = page.evaluate("performance.now()")
    server.send({"type": "ping", "h": BIG_H})
    _conn, raw = server.wait("a pong", lambda msgs: next((m for m in msgs if '"pong"' in m[1]), None))
    assert f'"h":{BIG_H}' in raw.replace(" ", ""), "h must come back digit for digit"
    pong = json.loads(raw)
    assert pong["h"] == BIG_H and pong["type"] == "pong"
    assert t0 <= pong["t"] <= page.evaluate("performance.now()")
    assert console_errors == []


def test_wrong_token_is_refused_with_a_plain_message(server, page, console_errors):
    page.goto(server.url + "#t=not-the-token")
    page.evaluate("window.perfcap.start()")
    page.wait_for_function("window.perfcap.state === 'stopped'")
    assert page.evaluate("window.perfcap.lastClose.code") == 4401
    assert TOKEN_MESSAGE in page.inner_text("#msg")
    assert page.get_by_role("button", name="Reconnect").is_enabled()
    page.wait_for_timeout(1500)
    assert server.connections == 1, "a refused token is not retried on its own"
    assert console_errors == []


def test_missing_token_says_so_before_start(server, page, console_errors):
    page.goto(server.url)
    assert "No pairing token" in page.inner_text("#msg")
    page.evaluate("window.perfcap.start()")
    page.wait_for_function("window.perfcap.state === 'stopped'")
    assert server.of_type("hello")[0][1]["token"] == ""
    assert TOKEN_MESSAGE in page.inner_text("#msg")
    assert console_errors == []


def test_reconnect_sends_the_queued_rows_with_continuing_seq(server, page, console_errors):
    open_live(page, server)
    first = motion_values(1, 3)
    dispatch_motion(page, first)
    server.wait("the first rows", lambda _: len(dispatched(server.rows("m"), first)) == 3)
    page.wait_for_function("window.perfcap.queued === 0")

    server.hold = True  # reconnects are turned away (1013) until released
    server.drop(1001)
    page.wait_for_function("window.perfcap.state !== 'live'")
    second = motion_values(100, 6)
    for i, v in enumerate(second, 1):  # several batches while offline: each row in its own
        dispatch_motion(page, [v])
        page.wait_for_function(f"window.perfcap.queued >= {i}")
    assert page.evaluate("window.perfcap.lastClose.code") in (1001, 1013)
    server.wait("a refused retry (with backoff)", lambda _: server.connections >= 2)

    server.hold = False
    page.wait_for_function("window.perfcap.state === 'live'")
    rows = server.wait("the queued rows", lambda _: len(dispatched(server.rows("m"), second)) == 6
                       and dispatched(server.rows("m"), second))
    assert [r[1:] for r in rows] == second

    data = server.of_type("data")
    assert [m["seq"] for _, m in data] == list(range(len(data))), "seq continues, nothing lost or repeated"
    conns = sorted({c for c, _ in data})
    assert len(conns) == 2
    later = [c for c, m in server.messages if c == conns[1]]
    assert json.loads(server.messages[[c for c, _ in server.messages].index(conns[1])][1])["type"] == "hello"
    assert len(later) >= 2
    assert page.evaluate("window.perfcap.queued") == 0 and page.evaluate("window.perfcap.dropped") == 0
    assert console_errors == []


PERMISSION_FAKE = """(answer) => {
  window.__asked = [];
  for (const C of [DeviceMotionEvent, DeviceOrientationEvent]) {
    C.requestPermission = () => {
      // window.event is the click only during its dispatch: a call put off to a timer or a later task
      // (e.g. after awaiting anything real) sees no event, and iOS would reject it.
      window.__asked.push([C.name, window.event ? window.event.type : null]);
      return Promise.resolve(answer);
    };
  }
}"""


@pytest.mark.parametrize("answer", ["denied", "granted"])
def test_ios_permission_prompt_is_asked_inside_the_tap(server, page, console_errors, answer):
    page.add_init_script(f"({PERMISSION_FAKE})({json.dumps(answer)})")
    page.goto(server.url + "#t=" + TOKEN)
    page.click("#start")
    assert page.evaluate("window.__asked") == [["DeviceMotionEvent", "click"], ["DeviceOrientationEvent", "click"]]
    if answer == "denied":
        page.wait_for_function("window.perfcap.state === 'denied'")
        assert "Motion access was denied" in page.inner_text("#msg")
        assert page.get_by_role("button", name="Start").is_enabled()
        assert server.connections == 0
    else:
        page.wait_for_function("window.perfcap.state === 'live'")
        vals = motion_values(7, 1)
        dispatch_motion(page, vals)
        server.wait("a motion row", lambda _: dispatched(server.rows("m"), vals))
    assert console_errors == []


@pytest.mark.slow
def test_a_silent_server_is_left_and_rejoined(server, page, console_errors):
    """No ping for max(5 s, 4 x ping_s): the page assumes a dead link (Wi-Fi change) and reconnects."""
    server.ping_s = 1.0
    open_live(page, server)
    page.wait_for_function("window.perfcap.lastClose !== null")
    assert page.evaluate("window.perfcap.lastClose.text").startswith("no ping from perfcap serve")
    server.wait("a second hello", lambda _: len(server.of_type("hello")) >= 2)
    page.wait_for_function("window.perfcap.state === 'live'")
    assert console_errors == []
