"""``perfcap serve`` under load: 10 phones over TLS WebSockets, and a flood of strangers.

    .venv/bin/python benchmarks/bench_serve.py [--seconds 20] [--flood-seconds 30] [--flood-rate 10000]
                                               [--only 1|2] [--no-record]

Every party runs in its own process, started by this script (the parties are the roles of
``_serve_roles.py``; the process harness and the figures' helpers are in ``_serve_common.py``):

* the service: a ``Service`` (capture.app.serve) on 127.0.0.1 with TLS, default limits, no mDNS, recording
  every message to a session, as ``perfcap serve --record`` runs it (``perfcap serve --port 0`` does not
  tell a script its port, so a small Python child builds the Service and prints its endpoints as JSON).
  Its CPU and memory are read from ``/proc/<pid>``, so only the service is counted;
* the phones: ``SimPagePhone`` tasks on one event loop (the real page protocol: hello with the token,
  batched devicemotion data, pongs), each from its own loopback source address (127.0.0.10, .11, ...,
  as phones are separate hosts; the service allows 4 connections per host);
* the flood (part 2): one asyncio process sending malformed and unauthenticated input.

1. 10 phones x 100 Hz over ``wss://`` to the service for ``--seconds`` (default 20): the page's 50 ms
   batches (200 messages/s in all) and one message per motion event (1,000 messages/s, the harder case).
   Targets: zero lost (every motion event sent is an ``imu`` sample on the bus and in the recording);
   host-side added latency p99 < 5 ms; service CPU < 30% of one core over the steady state.
   *Host-side added latency* = the time a sample is published on the bus (handed to the subscribers,
   measured by wrapping the offer of a probe subscription in the service) minus its ``t_host_ns``,
   which is the arrival stamp the gateway put on the message's ``Chunk`` when aiohttp handed the
   WebSocket message to it. It covers the inbox, the phone's reader thread, decoding and clock
   stamping; not the kernel, TLS and WebSocket parsing before the stamp, which are shown separately
   as "wire" latency (stamp minus the client's send time; one monotonic clock on one machine).
   Baseline in the same run: the same phones against a bare aiohttp TLS WebSocket server (same
   certificate and socket settings) that only stamps each message: its CPU and wire latency are the
   floor that TLS, WebSocket framing and asyncio cost before perfcap does anything.
2. A flood of ``--flood-rate`` (default 10,000) malformed or unauthenticated messages per second for
   ``--flood-seconds`` (default 30) while 2 paired phones stream at 100 Hz:
   (a) WebSocket connections whose hello has a wrong or no token (a TLS handshake each);
   (b) a client holding the token that sends garbage after its hello (binary frames and malformed
       JSON text; the gateway closes it for rate or malformed input and it reconnects at once);
   (c) HTTPS POSTs to /ingest/sensorlogger with no or a wrong token (pipelined on keep-alive);
   (d) UDP datagrams to the OSC port from a source that is not allow-listed.
   Targets: the phones lose nothing, the service's RSS stays bounded (sampled every 0.25 s), the
   service still answers /api/health. The achieved flood rate is reported as sent and as counted.
   At the flood's end and 35 s later the service reports what it holds (live WebSocket and request
   objects, timer handles, device events kept by the capture's stats), to tell retention from growth.
   ``--no-record`` runs part 1 without the recorder, to see what recording costs.

Measurement script: prints figures and PASS/FAIL per target, always exits 0.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import threading
import time
from typing import Any

import numpy as np
from _common import check, header, summary
from _serve_common import (
    OSC_ALLOW,
    PHONE_SRC,
    RETAIN_S,
    TOKEN,
    Child,
    Window,
    fmt_ms,
    http_json,
    loss_check,
    match_wire,
    pacing,
    pcts,
    proc_rss_mb,
    run_phones,
    service_arrays,
    udp_rcvbuf_errors,
)


def part1(tmp: str, seconds: float, record: bool = True) -> None:
    print(f"1. 10 phones x 100 Hz over wss:// on loopback, {seconds:.0f} s per run; the CPU window is the steady"
          f" state from 3 s after all phones connected to 1 s before they stop")
    print("   host-side added latency = publish on the bus (probe on the service's SampleBus) minus the sample's"
          " t_host_ns, the arrival stamp the gateway put on the message's Chunk;")
    print("   wire latency = that arrival stamp minus the client's monotonic time just before send_str (kernel,"
          " TLS, WebSocket, event loop: before perfcap's stamp)")
    variants = [("batch 50 ms (the page: 200 messages/s in all)", 0.05, None),
                ("one message per motion event (batch_s 0.01: 1,000 messages/s in all)", 0.01, 1505.0)]
    win_skip = (3.0, 1.0)
    for label, batch_s, t0_ms in variants:
        print()
        print(f"   -- {label}")
        # ---- baseline: bare aiohttp TLS WebSocket sink -------------------------------------------
        tag = f"sink{int(batch_s * 1000)}"
        sink = Child("sink", {"state_dir": os.path.join(tmp, "sink-state"), "out": os.path.join(tmp, f"{tag}.npz")},
                     os.path.join(tmp, f"{tag}.log"))
        try:
            sink.wait_ready(30)
            res_b, win_b, ph_b = run_phones(tmp, tag, sink, 10, batch_s, seconds, t0_ms, PHONE_SRC, win_skip)
            sink.send("stop")
            sink.expect("stopped", 30)
        finally:
            sink.close()
        arr_b = np.load(os.path.join(tmp, f"{tag}.npz"))
        arrivals = {k[4:]: arr_b[k] for k in arr_b.files}
        sends = {k[5:]: ph_b[k] for k in ph_b.files if k.startswith("send:")}
        wire_b, bad_b = match_wire(arrivals, sends, (win_b["t0_ns"], win_b["t1_ns"]))
        sent_b = sum(p["sent"] for p in res_b["phones"])
        got_b = sum(v.size for v in arrivals.values())
        print(f"   baseline, bare aiohttp TLS WebSocket server (stamps each message, nothing else): CPU"
              f" {win_b['cpu']['target'] * 100:.1f}% of one core; {got_b} of {sent_b} messages arrived;"
              f" wire latency (steady window) {fmt_ms(wire_b)}" + (f"; unmatched: {bad_b}" if bad_b else ""))
        base_cpu = win_b["cpu"]["target"]
        # ---- the service ---------------------------------------------------------------------------
        tag = f"serve{int(batch_s * 1000)}"
        sdir = os.path.join(tmp, f"{tag}-state")
        svc = Child("service", {"state_dir": sdir, "out": os.path.join(tmp, f"{tag}.npz"), "record": record},
                    os.path.join(tmp, f"{tag}.log"))
        try:
            svc.wait_ready(30)
            res, win, ph = run_phones(tmp, tag, svc, 10, batch_s, seconds, t0_ms, PHONE_SRC, win_skip)
            svc.send("stop")
            stopped = svc.expect("stopped", 60)
        finally:
            svc.close()
        report_service_run(tmp, tag, svc.ready, stopped, res, win, ph, base_cpu, wire_b, label, seconds, record)


def report_service_run(tmp: str, tag: str, ready: dict[str, Any], stopped: dict[str, Any], res: dict[str, Any],
                       win: dict[str, Any], ph: Any, base_cpu: float, wire_b: np.ndarray, label: str,
                       seconds: float, record: bool) -> None:
    host, pub = service_arrays(tmp, tag)
    ok_loss, lines = loss_check(res["phones"], stopped, ready["session"] if record else None)
    # latency over the CPU window (steady state) and over the whole run
    lat_all, lat_win = [], []
    arrivals = {}
    for stream, h in host.items():
        lat = (pub[stream] - h) / 1e6
        lat_all.append(lat)
        lat_win.append(lat[(h >= win["t0_ns"]) & (h <= win["t1_ns"])])
        dev = stream[:-4]
        pid = next((p["id"] for p in res["phones"] if p["device"] == dev), None)
        if pid is not None:
            arrivals[pid] = np.unique(h)  # one arrival stamp per message (sorted = arrival order)
    la = np.concatenate(lat_all) if lat_all else np.zeros(0)
    lw = np.concatenate(lat_win) if lat_win else np.zeros(0)
    sends = {k[5:]: ph[k] for k in ph.files if k.startswith("send:")}
    wire, bad = match_wire(arrivals, sends, (win["t0_ns"], win["t1_ns"]))
    late = pacing(ph, (win["t0_ns"], win["t1_ns"]))
    cpu = win["cpu"]["target"]
    msgs = sum(p["sent"] for p in res["phones"])
    recording = "recording every message" if record else "NOT recording"
    print(f"   perfcap serve (Service with TLS, default limits, {recording}; 10 reader threads):")
    for ln in lines:
        print(f"      {ln}")
    print(f"      host-side added latency, steady window: {fmt_ms(lw)}")
    print(f"      host-side added latency, whole run incl. connect: {fmt_ms(la)}")
    print(f"      wire latency (client send -> arrival stamp), steady window: {fmt_ms(wire)};"
          f" bare server: {fmt_ms(wire_b)}" + (f"; unmatched: {bad}" if bad else ""))
    print(f"      client pacing, steady window: send time behind schedule {fmt_ms(late)}; phones process CPU"
          f" {win['cpu']['phones'] * 100:.0f}% of one core")
    print(f"      service CPU {cpu * 100:.1f}% of one core over {win['wall']:.1f} s"
          f" ({cpu * 1e6 / max(1.0, msgs / seconds):.0f} us per message at {msgs / seconds:.0f} messages/s);"
          f" bare server {base_cpu * 100:.1f}%; service minus bare {100 * (cpu - base_cpu):.1f} points")
    print(f"      machine: {win['machine_cores']:.2f} of {os.cpu_count()} cores busy in the window, of which"
          f" {max(0.0, win['others_cores']):.2f} by other processes (not this benchmark)")
    short = "50 ms" if "50 ms" in label else "1 msg/event"
    p99 = pcts(lw)[1]
    check(f"10 phones, {short}: zero lost", ok_loss, lines[0])
    check(f"10 phones, {short}: host-side added latency p99 < 5 ms", p99 < 5.0, f"{p99:.3f} ms (steady window)")
    check(f"10 phones, {short}: service CPU < 30% of one core", cpu < 0.30, f"{cpu * 100:.1f}%")


def part2(tmp: str, flood_s: float, flood_rate: float) -> None:
    mix = {"a": 0.02, "b": 0.28, "c": 0.30, "d": 0.40}
    print(f"2. flood of {flood_rate:,.0f} malformed/unauthenticated messages/s for {flood_s:.0f} s"
          f" (targets per category: (a) WS with wrong/no token {mix['a'] * flood_rate:,.0f}/s, each a new TLS"
          f" connection, from 4 sources x 4;"
          f" (b) paired client sending garbage {mix['b'] * flood_rate:,.0f}/s, 2 connections from 127.0.0.4;"
          f" (c) POST /ingest/sensorlogger without/with a wrong token {mix['c'] * flood_rate:,.0f}/s, pipelined on 4"
          f" keep-alive TLS connections; (d) UDP to the OSC port from 127.0.0.2, allow-list {OSC_ALLOW},"
          f" {mix['d'] * flood_rate:,.0f}/s), 2 paired phones at 100 Hz (batch 50 ms) throughout")
    sdir = os.path.join(tmp, "flood-state")
    svc = Child("service", {"state_dir": sdir, "out": os.path.join(tmp, "flood.npz"), "osc": True},
                os.path.join(tmp, "flood-service.log"))
    rss: list[tuple[float, float]] = []
    stop_rss = threading.Event()
    try:
        ready = svc.wait_ready(30)

        def sample_rss() -> None:
            while not stop_rss.is_set():
                try:
                    rss.append((time.monotonic(), proc_rss_mb(svc.pid)))
                except OSError:
                    return
                stop_rss.wait(0.25)

        threading.Thread(target=sample_rss, daemon=True).start()
        lead, tail = 3.0, 4.0
        duration = lead + flood_s + tail + 1.0
        out = os.path.join(tmp, "flood-phones.npz")
        ph = Child("phones", {"page_url": ready["page_url"], "token": TOKEN, "fingerprint": ready["fingerprint"],
                              "n": 2, "rate": 100.0, "batch_s": 0.05, "duration": duration, "t0_ms": None,
                              "src": PHONE_SRC, "out": out}, os.path.join(tmp, "flood-phones.log"))
        try:
            ph.expect("streaming", 30)
            time.sleep(lead)
            _, h0 = http_json(ready["control_url"] + "/health", TOKEN)
            rej0 = dict(h0.get("rejected", {})) if isinstance(h0, dict) else {}
            port = int(ready["page_url"].rsplit(":", 1)[1].strip("/"))
            fl = Child("flood", {"rate": flood_rate, "mix": mix, "duration": flood_s, "port": port,
                                 "osc_port": ready["osc_port"]}, os.path.join(tmp, "flood.log"))
            try:
                fl.expect("flooding", 30)
                udp0 = udp_rcvbuf_errors()
                t_f0 = time.monotonic()
                w = Window({"service": svc.pid, "flood": fl.pid, "phones": ph.pid})
                fres = fl.expect("done", flood_s + 60)
                t_f1 = time.monotonic()
                win = w.end()
                time.sleep(0.5)
                udp_dropped = udp_rcvbuf_errors() - udp0
            finally:
                fl.close()
            svc.send("probe")
            probe1 = svc.expect("probe", 30)
            time.sleep(1.0)
            hs, h1 = http_json(ready["control_url"] + "/health", TOKEN)
            hs_bad, _ = http_json(ready["control_url"] + "/health", "wrong-token-0000000000")
            res = ph.expect("done", duration + 60)
        finally:
            ph.close()
        # aiohttp keeps a closed WebSocket for its heartbeat (20 s) and pong wait (10 s): look again after that
        time.sleep(max(0.0, t_f1 + RETAIN_S - time.monotonic()))
        svc.send("probe")
        probe2 = svc.expect("probe", 30)
        stop_rss.set()
        svc.send("stop")
        stopped = svc.expect("stopped", 60)
    finally:
        stop_rss.set()
        svc.close()

    # ---- flood rate -------------------------------------------------------------------------------
    sent = fres["sent"]
    ex = fres["extra"]
    tot = sum(sent.values())
    rej1 = dict(h1.get("rejected", {})) if isinstance(h1, dict) else {}
    counted = {k: rej1.get(k, 0) - rej0.get(k, 0) for k in rej1}
    wall = fres["wall_s"]
    print(f"   flood sent {tot:,} messages in {wall:.1f} s = {tot / wall:,.0f}/s (target {flood_rate:,.0f}/s):")
    for k, v in sent.items():
        print(f"      {k:20s} {v:9,d}  {v / wall:8,.0f}/s")
    print(f"      (a) closed with 4401 (token) {ex['a_closed_4401']:,}, refused 503 (too many connections)"
          f" {ex['a_refused_503']:,}, other {ex['a_other']}")
    print(f"      (b) {ex['b_connects']:,} connections, {ex['b_text']:,} text + {ex['b_binary']:,} binary frames sent;"
          f" close codes {ex['b_close_codes']}; refused at connect {ex['b_refused']}")
    print(f"      (c) {ex['c_responses']:,} responses {ex['c_status']} on {ex['c_connections']} connections")
    print(f"      (d) would-block on send {ex['d_would_block']}; dropped by the kernel, the service's receive buffer"
          f" full (RcvbufErrors, system-wide): {udp_dropped:,}")
    gdev = [v for k, v in stopped["phone_names"].items() if k.startswith("page/garbage")]
    gchunks = sum(stopped["devices"].get(d, {}).get("chunks", 0) for d in gdev)
    gerr = sum(stopped["devices"].get(d, {}).get("framing_errors", 0) for d in gdev)
    gsmp = sum(v for k, v in stopped["counts"].items() if k.split("/")[0] in gdev)
    print(f"      (b) the garbage client's text frames reached its device {', '.join(gdev) or '-'}:"
          f" {gchunks:,} messages (hello included), {gerr:,} counted as framing errors by its codec, {gsmp} samples"
          f" made of them")
    print("   refused by the service during the flood (its counters, /api/health): "
          + ", ".join(f"{k} {v:,}" for k, v in sorted(counted.items()) if v))
    print(f"   service counters at the end: {stopped['rejected']}")
    print(f"   CPU over the flood: service {win['cpu']['service'] * 100:.0f}%, flood client"
          f" {win['cpu']['flood'] * 100:.0f}%, phones {win['cpu']['phones'] * 100:.0f}% of one core;"
          f" machine {win['machine_cores']:.2f} of {os.cpu_count()} cores busy, other processes"
          f" {max(0.0, win['others_cores']):.2f}")
    # ---- memory -----------------------------------------------------------------------------------
    r = np.asarray(rss)
    before = r[r[:, 0] < t_f0, 1]
    during = r[(r[:, 0] >= t_f0) & (r[:, 0] <= t_f1)]
    after = r[r[:, 0] > t_f1, 1]
    start_mb = float(before[-1]) if before.size else float(during[0, 1])
    max_mb = float(during[:, 1].max()) if len(during) else float("nan")
    end_mb = float(during[-1, 1]) if len(during) else float("nan")
    half = t_f0 + (t_f1 - t_f0) / 2
    first = during[during[:, 0] < half, 1]
    second = during[during[:, 0] >= half, 1]
    growth2 = float(second.max() - first.max()) if first.size and second.size else float("nan")
    print(f"   in the service at the flood's end: {probe1['ws_alive']:,} WebSocketResponse and"
          f" {probe1['request_handlers']:,} RequestHandler objects alive, {probe1['timer_handles']:,} timer handles,"
          f" {probe1['stats_events']:,} device"
          f" events kept by the capture's stats; {RETAIN_S:.0f} s after it: {probe2['ws_alive']:,} /"
          f" {probe2['request_handlers']:,} / {probe2['timer_handles']:,} / {probe2['stats_events']:,}, RSS"
          f" {probe2['rss_mb']:.1f} MB")
    print(f"   service RSS: {start_mb:.1f} MB at the flood's start, max {max_mb:.1f} MB, {end_mb:.1f} MB at its end,"
          f" {float(after[-1]) if after.size else float('nan'):.1f} MB {after.size * 0.25:.1f} s later;"
          f" max of the 2nd half minus max of the 1st half {growth2:+.1f} MB ({r.shape[0]} samples, every 0.25 s)")
    # ---- the phones -------------------------------------------------------------------------------
    ok_loss, lines = loss_check(res["phones"], stopped, ready["session"])
    for ln in lines:
        print(f"   {ln}")
    host, pub = service_arrays(tmp, "flood")
    lat_f, arrivals = [], {}
    for stream, h in host.items():
        if any(p["device"] == stream[:-4] for p in res["phones"]):
            sel = (h >= win["t0_ns"]) & (h <= win["t1_ns"])
            lat_f.append((pub[stream][sel] - h[sel]) / 1e6)
            pid = next(p["id"] for p in res["phones"] if p["device"] == stream[:-4])
            arrivals[pid] = np.unique(h)
    ph = np.load(os.path.join(tmp, "flood-phones.npz"))
    wire, bad = match_wire(arrivals, {k[5:]: ph[k] for k in ph.files if k.startswith("send:")},
                           (win["t0_ns"], win["t1_ns"]))
    lat_flood = np.concatenate(lat_f) if lat_f else np.zeros(0)
    print(f"   the phones' host-side added latency during the flood: {fmt_ms(lat_flood)}")
    print(f"   their wire latency during the flood: {fmt_ms(wire)}" + (f"; unmatched: {bad}" if bad else ""))
    up = hs == 200 and isinstance(h1, dict) and h1.get("status") == "ok"
    bounded = max_mb - start_mb < 100.0 and growth2 <= max(5.0, 0.05 * start_mb)
    check(f"flood {tot / wall:,.0f}/s for {wall:.0f} s: paired phones lose nothing", ok_loss, lines[0])
    check("flood: service RSS bounded", bounded,
          f"start {start_mb:.1f}, max {max_mb:.1f}, end {end_mb:.1f} MB (bound: max - start < 100 MB and no growth"
          f" from the 1st to the 2nd half beyond max(5 MB, 5%): {growth2:+.1f} MB)")
    check("flood: service up, /api/health answers afterwards", up,
          f"HTTP {hs}, status {h1.get('status') if isinstance(h1, dict) else h1}; wrong token -> HTTP {hs_bad}")
    n_counted = sum(counted.values()) + gerr
    check(f"flood rate reached {flood_rate:,.0f}/s (the test's own condition)", tot / wall >= 0.95 * flood_rate,
          f"{tot / wall:,.0f}/s sent; {n_counted / wall:,.0f}/s reached the service's checks and were counted"
          f" (refusals + framing errors); {udp_dropped / wall:,.0f}/s datagrams dropped by the kernel before it")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="seconds per 10-phone run (default 20)")
    ap.add_argument("--flood-seconds", type=float, default=30.0, help="flood duration (default 30)")
    ap.add_argument("--flood-rate", type=float, default=10000.0, help="flood messages per second (default 10000)")
    ap.add_argument("--only", choices=("1", "2"), help="run one part")
    ap.add_argument("--no-record", action="store_true",
                    help="part 1 without recording (to see what the recorder costs)")
    a = ap.parse_args()
    header("bench_serve: perfcap serve with 10 phones over TLS WebSockets, and under a flood")
    with tempfile.TemporaryDirectory(prefix="perfcap-bench-serve-") as tmp:
        if a.only in (None, "1"):
            part1(tmp, a.seconds, record=not a.no_record)
            print()
        if a.only in (None, "2"):
            part2(tmp, a.flood_seconds, a.flood_rate)
    la = os.getloadavg()
    print(f"   load average at the end: {la[0]:.2f} {la[1]:.2f} {la[2]:.2f}")
    summary()


if __name__ == "__main__":
    main()
