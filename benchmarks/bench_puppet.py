"""bench_puppet: the phone puppet's per-frame cost, phone-sample-to-VMC-packet latency on loopback, the
inverse lookup's round-trip speed error and foot sliding in steady walking and running.

Baselines in the same run: the per-frame cost of FK alone (the floor of any pose output), and the
foot sliding of the raw walk/run clips played at their own speed (the best the blend can do).

    .venv/bin/python benchmarks/bench_puppet.py [--quick]
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
import threading
import time
from typing import TYPE_CHECKING

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _common import check, header, summary

from capture.app.puppet_input import attitude_quaternions
from capture.sample import DeviceIdentity, StreamInfo
from retarget.puppet import PhoneInput, PuppetRetargeter
from retarget.vmc import VmcEncoder, build_frame, decode_frame, encode_frame
from sim_devices.motion import PuppeteerMotion

if TYPE_CHECKING:
    from retarget.skeleton import Skeleton


def scripted(seconds: float, fps: float) -> list[PhoneInput]:
    """Hold, walk, run, crouch, a hop, set down: every state the per-frame budget must cover."""
    out = []
    z = 0.0
    for i in range(int(seconds * fps)):
        t = i / fps
        s = t % 12.0
        speed = 0.0 if s < 1 else 1.4 if s < 4 else 3.2 if s < 7 else 0.8
        z += speed / fps
        y = 1.3 - (0.35 if 9 <= s < 10 else 0.0)
        if 10.5 <= s < 11.0:                      # a hop
            u = s - 10.5
            y = 1.3 + max(0.0, 2.2 * u - 4.9 * u * u)
        if s >= 11.0:                             # set down (if it fell limp, it lies and gets up)
            y = 0.35
        out.append(PhoneInput(t, (1.0, 0.0, 0.0, 0.0), True, (0.0, y, z)))
    return out


def rod_inputs(seconds: float, fps: float) -> list[PhoneInput]:
    """An IMU-only phone (no position) performing the puppeteer choreography, as the page's attitude."""
    m = PuppeteerMotion()
    t = np.arange(0.0, seconds, 1.0 / fps)
    _, _, eul = m.at_many(t)
    info = StreamInfo("ph/attitude", "euler", ("alpha", "beta", "gamma"), ("deg",) * 3, None,
                      DeviceIdentity("phone", "ph"))
    q = attitude_quaternions(info, np.stack([eul[:, 2], eul[:, 0], eul[:, 1]], axis=1))
    return [PhoneInput(float(ti), tuple(qi), True) for ti, qi in zip(t, q, strict=True)]


def per_frame(p: PuppetRetargeter, inputs: list[PhoneInput]) -> tuple[np.ndarray, list[str]]:
    p.reset()
    ts = np.empty(len(inputs))
    states = []
    clock = time.perf_counter
    for i, x in enumerate(inputs):
        t0 = clock()
        f = p.step(x)
        ts[i] = clock() - t0
        states.append(f.state.name)
    return ts * 1e3, states


def fk_only(p: PuppetRetargeter, n: int) -> np.ndarray:
    rot = np.tile([1.0, 0.0, 0.0, 0.0], (p.skeleton.n_joints, 1))
    ts = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter()
        p.skeleton.fk(np.zeros(3), rot)
        ts[i] = time.perf_counter() - t0
    return ts * 1e3


def vmc_latency(p: PuppetRetargeter, inputs: list[PhoneInput]) -> np.ndarray:
    """Phone sample in -> retargeter -> VMC bundle -> UDP loopback -> decoded by a receiver thread."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(2.0)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    addr = rx.getsockname()
    names = [p.skeleton.unity_names.get(n, n) for n in p.skeleton.names]
    offsets = p.skeleton.offsets
    got: dict[float, float] = {}

    def receive() -> None:
        while True:
            try:
                data, _ = rx.recvfrom(65535)
            except OSError:
                return
            now = time.perf_counter()
            f = decode_frame(data)
            got[round(f.t, 6)] = now

    th = threading.Thread(target=receive, daemon=True)
    th.start()
    sent: dict[float, float] = {}
    p.reset()
    for x in inputs:
        t0 = time.perf_counter()
        fr = p.step(x)
        data = encode_frame(names, offsets, fr.rotations, fr.root_pos, fr.rotations[0], fr.t)
        tx.sendto(data, addr)
        sent[round(float(np.float32(fr.t)), 6)] = t0
        time.sleep(0.002)
    time.sleep(0.2)
    rx.close()
    tx.close()
    th.join(timeout=1)
    lat = [(got[k] - sent[k]) * 1e3 for k in sent if k in got]
    print(f"   VMC frames sent {len(sent)}, received and decoded {len(lat)}")
    return np.array(lat)


def foot_slide(p: PuppetRetargeter, speed: float, fps: float = 60.0) -> float:
    """Max horizontal travel of a planted foot per step (m) while the stick moves straight at ``speed``."""
    p.reset()
    sk = p.skeleton
    frames = []
    for i in range(int(10 * fps)):
        t = i / fps
        z = 0.0 if t < 1 else speed * (t - 1)
        f = p.step(PhoneInput(t, (1.0, 0.0, 0.0, 0.0), True, (0.0, 1.3, z)))
        if t > 4:
            frames.append(sk.fk(f.root_pos, f.rotations))
    return slide_of(np.array(frames), sk, fps)


def slide_of(positions: np.ndarray, sk: Skeleton, fps: float) -> float:
    """The longest slide of a planted foot, m, over joint positions ``(frames, joints, 3)``."""
    worst = 0.0
    for name in ("LeftFoot", "RightFoot"):
        j = sk.index(name)
        y, xz = positions[:, j, 1], positions[:, j, [0, 2]]
        sp = np.r_[0.0, np.linalg.norm(np.diff(xz, axis=0), axis=1) * fps]
        planted = (y < np.percentile(y, 5) + 0.01) & (sp < 0.3)
        start = None
        for i, c in enumerate(planted):
            if c and start is None:
                start = i
            if (not c or i == len(planted) - 1) and start is not None:
                if i - start > 3:
                    worst = max(worst, float(np.linalg.norm(xz[i - 1] - xz[start])))
                start = None
    return worst


def clip_slide(p: PuppetRetargeter, name: str) -> float:
    c = p.clips[name]
    adv = c.root_pos[-1] - c.root_pos[0]
    positions = np.concatenate([p.skeleton.fk(c.root_pos + k * adv, c.rotations)[:-1] for k in range(4)])
    return slide_of(positions, p.skeleton, c.fps)


def _result(ok: bool, text: str) -> None:
    label, _, detail = text.partition(": ")
    check(label, bool(ok), detail)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    header("bench_puppet: phone puppet per-frame cost, VMC latency, lookup error, foot sliding")
    t0 = time.perf_counter()
    p = PuppetRetargeter()
    print(f"   retargeter built in {(time.perf_counter() - t0) * 1e3:.0f} ms ({p.skeleton.n_joints} joints, "
          f"5 locomotion clips, 21x21 probe table measured)")

    print("\n-- per input frame: stick + state machine + mapping + blend + pose (60 Hz script: hold, walk, run,"
          " crouch, hop)")
    seconds = 24.0 if args.quick else 60.0
    inputs = scripted(seconds, 60.0)
    per_frame(p, inputs[:300])                      # warm up
    ms, states = per_frame(p, inputs)
    fk = fk_only(p, len(inputs))
    st = np.array(states)
    for name in sorted(set(states)):
        sel = ms[st == name]
        print(f"   {name:18s} {sel.size:5d} frames  p50 {np.percentile(sel, 50):.3f} ms"
              f"  p99 {np.percentile(sel, 99):.3f} ms")
    print(f"   frames {len(ms)}: p50 {np.percentile(ms, 50):.3f} ms  p99 {np.percentile(ms, 99):.3f} ms"
          f"  max {ms.max():.3f} ms   (FK alone: p50 {np.percentile(fk, 50):.3f} ms,"
          f" p99 {np.percentile(fk, 99):.3f} ms)")
    _result(float(np.percentile(ms, 99)) < 1.0, f"per-frame p99 < 1 ms for {p.skeleton.n_joints} joints, all"
            f" states: {np.percentile(ms, 99):.3f} ms")
    rod = rod_inputs(seconds, 60.0)
    rms, rstates = per_frame(p, rod)
    print(f"   IMU-only phone, the puppeteer choreography ({', '.join(dict.fromkeys(rstates))}): {len(rms)} frames"
          f" p50 {np.percentile(rms, 50):.3f} ms  p99 {np.percentile(rms, 99):.3f} ms")
    _result(float(np.percentile(rms, 99)) < 1.0,
            f"per-frame p99 < 1 ms, IMU-only phone: {np.percentile(rms, 99):.3f} ms")

    print("\n-- phone sample -> VMC bundle -> UDP loopback -> decoded")
    lat = vmc_latency(p, inputs[: 600 if args.quick else 1800])
    print(f"   latency p50 {np.percentile(lat, 50):.3f} ms  p99 {np.percentile(lat, 99):.3f} ms"
          f"  max {lat.max():.3f} ms")
    _result(float(np.percentile(lat, 99)) < 5.0 and len(lat) > 0,
           f"phone sample to VMC packet on loopback p99 < 5 ms: {np.percentile(lat, 99):.3f} ms")

    print("\n-- VMC bundle encoding, 30 bones (python-osc building every message, the baseline, vs the template"
          " it builds once)")
    names = [p.skeleton.unity_names.get(n, n) for n in p.skeleton.names]
    p.reset()
    frames = [p.step(x) for x in inputs[:200]]
    enc = VmcEncoder(names)
    for label, fn in (("python-osc per frame", lambda f: build_frame(names, p.skeleton.offsets, f.rotations,
                                                                       f.root_pos, f.rotations[0], f.t)),
                      ("template (VmcEncoder)", lambda f: enc.encode(p.skeleton.offsets, f.rotations, f.root_pos,
                                                                     f.rotations[0], f.t))):
        ts = []
        for f in frames:
            t1 = time.perf_counter()
            fn(f)
            ts.append(time.perf_counter() - t1)
        print(f"   {label:22s} p50 {np.median(ts) * 1e3:.3f} ms  p99 {np.percentile(ts, 99) * 1e3:.3f} ms")
    same = all(build_frame(names, p.skeleton.offsets, f.rotations, f.root_pos, f.rotations[0], f.t)
               == enc.encode(p.skeleton.offsets, f.rotations, f.root_pos, f.rotations[0], f.t) for f in frames)
    _result(same, f"template bundles byte-identical to python-osc's: {len(frames)} frames compared")

    print("\n-- inverse lookup round trip (the probe table measured from the blended locomotion)")
    rng = np.random.default_rng(0)
    vmax = p.table.border_speed(1.0)
    errs = []
    for _ in range(400 if args.quick else 2000):
        pv, ph = rng.uniform(0, 1, 2)
        u = p.verb.root_speed((pv, ph))
        q = p.table.query(u, ph)
        errs.append(abs(p.verb.root_speed((q.p_vel, q.p_height)) * q.speedup - u))
    e = np.array(errs)
    print(f"   {e.size} random blend points (speeds 0..{vmax:.2f} m/s): median {np.median(e):.4f} m/s,"
          f" max {e.max():.4f} m/s")
    _result(float(np.median(e)) < 0.02, f"lookup round-trip speed error median < 0.02 m/s: {np.median(e):.4f}")
    _result(float(e.max()) < 0.1, f"lookup round-trip speed error max < 0.1 m/s: {e.max():.4f}")

    print("\n-- foot sliding per step, stick moving straight at a steady speed (raw clip at its own speed"
          " beside it)")
    for name, gait, speed in (("walk", "walking", 1.4), ("run", "running", 3.4)):
        s = foot_slide(p, speed)
        raw = clip_slide(p, name)
        print(f"   {name:4s} {speed:.1f} m/s: puppet {s * 100:.2f} cm per step (raw {name} clip {raw * 100:.2f} cm)")
        _result(s < 0.01, f"foot sliding in steady {gait} < 1 cm per step: {s * 100:.2f} cm")
    slow = foot_slide(p, 0.7)
    print(f"   slow walk 0.7 m/s (a blend of idle and walk, not a steady gait of the clip set): {slow * 100:.2f} cm"
          " per step (not a target)")
    summary()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
