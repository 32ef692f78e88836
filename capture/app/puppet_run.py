"""Driving the phone puppet: the wiring between phone input (``capture.app.puppet_input``) and
``retarget.puppet.PuppetRetargeter``.

What this module owns:

* :class:`PuppetRun`: steps the retargeter, keeps the frames (a BVH ``Clip`` at the fixed rate), the
  state timeline and the time spent in each state, and sends each frame as VMC through a
  :class:`VmcSender` (UDP, send errors counted, never raised);
* :class:`PuppetFollower`: the bus subscriber that does the same live, stepping the retargeter on the
  fixed-rate grid of the phone's bus times as its attitude samples arrive;
* the outputs: the BVH and the state timeline (:func:`write_outputs`), and the checks made before a
  performance (:func:`probe_writable`, :func:`parse_host_port`).

Nothing here reads the OS clock: time comes with the input (CSV seconds, bus times).
"""

from __future__ import annotations

import json
import logging
import os
import socket
from collections import deque
from typing import TYPE_CHECKING, Any

import numpy as np

from capture.app.puppet_input import (
    ATTITUDE_STREAMS,
    GRID_SLACK_NS,
    TouchState,
    attitude_quaternions,
    check_rate,
    touch_columns,
)
from capture.bus import Processor
from capture.errors import ConfigError
from capture.quat import quat_conj, quat_mul, quat_rotate, quat_slerp
from capture.sample import Sample, SampleBatch, StreamInfo
from capture.session_view import SKELETON_KEY
from retarget.puppet import PhoneInput, PuppetFrame, PuppetRetargeter
from retarget.skeleton import Clip, Skeleton
from retarget.timeline import split_heading, yaw_quat
from retarget.vmc import VmcEncoder

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Iterator, Sequence

    from capture.clock import Clock

log = logging.getLogger(__name__)

__all__ = ["PuppetFollower", "PuppetRun", "VmcSender", "paced", "parse_host_port", "probe_writable", "write_outputs"]


# ------------------------------------------------------------------------------------------------ outputs
def write_outputs(run: PuppetRun, bvh: str | None, timeline: str | None) -> tuple[list[str], list[str]]:
    """Write the BVH and the timeline, each whether or not the other could be written.

    Returns:
        (what was written, as summary lines; what could not be, one message each).
    """
    from retarget.bvh import write_bvh

    lines, errors = [], []
    if bvh:
        clip = run.clip(os.path.splitext(os.path.basename(bvh))[0] or "puppet")
        try:
            write_bvh(bvh, clip)
        except OSError as exc:
            errors.append(f"cannot write {bvh}: {exc.strerror or exc}")
        else:
            lines.append(f"  BVH written to {bvh} ({clip.n_frames} frames at {clip.fps:g} fps,"
                         f" {clip.skeleton.n_joints} joints)")
    if timeline:
        tl = run.timeline()
        try:
            with open(timeline, "w", encoding="utf-8") as f:
                f.write("[\n" + ",\n".join(" " + json.dumps(e) for e in tl) + "\n]\n")
        except OSError as exc:
            errors.append(f"cannot write {timeline}: {exc.strerror or exc}")
        else:
            lines.append(f"  timeline written to {timeline} ({len(tl)} entries)")
    return lines, errors


def probe_writable(path: str | None, flag: str) -> None:
    """Check before a performance that an output file can be written: its folder exists, it is no
    folder, and it opens for appending (created, and removed again, when it does not exist yet; an
    existing file is left as it is).

    Args:
        path: the output (None: nothing to check).
        flag: its option, for the message.

    Raises:
        ConfigError: it cannot be written, saying why.
    """
    if not path:
        return
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise ConfigError(f"{flag} {path}: the folder {folder} does not exist")
    if os.path.isdir(path):
        raise ConfigError(f"{flag} {path} is a directory")
    existed = os.path.lexists(path)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NONBLOCK, 0o666)
    except OSError as exc:
        raise ConfigError(f"{flag} {path}: cannot write it ({exc.strerror or exc})") from None
    os.close(fd)
    if not existed:
        try:
            os.remove(path)
        except OSError:
            log.debug("could not remove the probe of %s", path)


def parse_host_port(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[v6]:PORT`` for IPv6) as (host, port); the port in ASCII digits.

    Raises:
        ConfigError: not of that form.
    """
    s = str(text).strip()
    host, sep, port = s.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    digits = port.isascii() and port.isdigit()          # isdigit alone takes '²' and '٣'
    if not sep or not host or not digits or not 0 < int(port) < 65536 or (":" in host and "[" not in s):
        raise ConfigError(f"--vmc expects HOST:PORT (e.g. 127.0.0.1:39539), not {text!r}")
    return host, int(port)


class VmcSender:
    """One VMC bundle per frame over UDP to ``HOST:PORT`` (``retarget.vmc.VmcEncoder``): the skeleton's
    joints that have a Unity name, local positions = the skeleton's offsets, local rotations = the
    frame's. The root is the character's ground point: the hips' position at height 0 and the heading
    (yaw about +Y) of their rotation; the hips (joint 0) are sent relative to it (the rest of their
    rotation, and their height), so a receiver composing root and hips turns the character once. Send
    errors are counted (and the first logged), never raised.

    Args:
        target: ``HOST:PORT``.
        skeleton: the character.

    Raises:
        ConfigError: a malformed target, or a host that does not resolve.
    """

    def __init__(self, target: str, skeleton: Skeleton) -> None:
        self.target = target
        host, port = parse_host_port(target)
        try:
            info = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        except (socket.gaierror, UnicodeError) as exc:
            raise ConfigError(f"--vmc {target}: cannot resolve {host!r} ({exc})") from None
        family, _, _, _, addr = info[0]
        self.address = addr
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        unity = skeleton.unity_names
        self.index = [i for i, n in enumerate(skeleton.names) if n in unity]
        self.names = [unity[skeleton.names[i]] for i in self.index]
        self.local_pos = np.asarray(skeleton.offsets, np.float64)[self.index]
        self.hips_offset = np.asarray(skeleton.offsets[0], np.float64)
        self.encoder = VmcEncoder(self.names)
        self.sent = 0
        self.errors = 0
        self.first_error: str | None = None

    def root_and_hips(self, frame: PuppetFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The frame's root (position, rotation) and the hips relative to it (position, rotation).

        Raises:
            ValueError: a frame without finite hips.
        """
        q_hips = np.asarray(frame.rotations[0], np.float64)
        p_hips = np.asarray(frame.root_pos, np.float64) + self.hips_offset
        if not (np.isfinite(q_hips).all() and np.isfinite(p_hips).all()):
            raise ValueError("a VMC frame needs finite values")
        heading, tilt = split_heading(q_hips)             # q_hips = yaw(heading) * tilt
        root_rot = yaw_quat(float(heading))
        root_pos = np.array([p_hips[0], 0.0, p_hips[2]])
        return root_pos, root_rot, quat_rotate(quat_conj(root_rot), p_hips - root_pos), tilt

    def send(self, frame: PuppetFrame) -> bool:
        """Send one frame; False (counted) when it could not be encoded or sent."""
        try:
            root_pos, root_rot, hips_pos, hips_rot = self.root_and_hips(frame)
            local_pos, local_rot = self.local_pos, frame.rotations[self.index]
            if self.index and self.index[0] == 0:
                local_pos, local_rot = local_pos.copy(), np.array(local_rot, np.float64)
                local_pos[0], local_rot[0] = hips_pos, hips_rot
            else:                                         # no hips bone: the root carries their pose
                root_pos, root_rot = root_pos + quat_rotate(root_rot, hips_pos), quat_mul(root_rot, hips_rot)
            data = self.encoder.encode(local_pos, local_rot, root_pos, root_rot, frame.t)
            self.sock.sendto(data, self.address)
        except (OSError, ValueError) as exc:
            self.errors += 1
            if self.first_error is None:
                self.first_error = f"{type(exc).__name__}: {exc}"
                log.warning("VMC to %s: %s (further errors are counted)", self.target, self.first_error)
            return False
        self.sent += 1
        return True

    def close(self) -> None:
        self.sock.close()


def paced(inputs: Iterable[PhoneInput], clock: Clock) -> Iterator[PhoneInput]:
    """``inputs`` at their own pace, as a player sends them: each one when ``clock`` has reached the take's
    start plus its time since the first (a late one goes at once; no frame is skipped)."""
    start_ns: int | None = None
    t0 = 0.0
    for inp in inputs:
        if start_ns is None:
            start_ns, t0 = clock.now_ns(), inp.t
        else:
            clock.sleep_until_ns(start_ns + round((inp.t - t0) * 1e9))
        yield inp


class PuppetRun:
    """A performance: input frames through the retargeter, with what the outputs need.

    Args:
        retargeter: the retargeter (default: a new ``PuppetRetargeter()``).
        rate: the fixed frame rate the inputs come at (the BVH's fps).
        vmc: where each frame is sent, if anywhere.
        keep_frames: keep the poses (for :meth:`clip`).

    Raises:
        ConfigError: a bad rate.
    """

    def __init__(self, retargeter: PuppetRetargeter | None = None, *, rate: float = 60.0,
                 vmc: VmcSender | None = None, keep_frames: bool = True) -> None:
        self.retargeter = retargeter or PuppetRetargeter()
        self.rate = check_rate(rate)
        self.vmc = vmc
        self.keep_frames = keep_frames
        self.frames = 0
        self.t0: float | None = None
        self.t_last: float | None = None
        self._root: list[np.ndarray] = []
        self._rot: list[np.ndarray] = []
        self._timeline: list[list[Any]] = []   # [t, state name]
        self._before_first = False

    def step(self, inp: PhoneInput) -> PuppetFrame:
        """One input frame.

        Raises:
            ValueError: as ``PuppetRetargeter.step`` (time going backwards, a non-finite input).
        """
        frame = self.retargeter.step(inp)
        if self.t0 is None:
            self.t0 = frame.t
            first = frame.transitions[0].from_state if frame.transitions else frame.state
            self._timeline.append([frame.t, first.name])
            self._before_first = True
        for tr in frame.transitions:
            if tr.from_state is not tr.to_state:
                self._change(frame.t if tr.t is None else float(tr.t), tr.to_state.name)
                self._before_first = False
        self._before_first = False
        self.t_last = frame.t
        self.frames += 1
        if self.keep_frames:
            self._root.append(np.array(frame.root_pos, np.float64))
            self._rot.append(np.array(frame.rotations, np.float64))
        if self.vmc is not None:
            self.vmc.send(frame)
        return frame

    def _change(self, t: float, state: str) -> None:
        tl = self._timeline
        t = max(t, tl[-1][0])
        if self._before_first and t - tl[0][0] < 1e-9:
            tl[0][1] = state                   # the state before the first frame is no part of the timeline
        else:
            tl.append([t, state])

    def run(self, inputs: Iterable[PhoneInput]) -> PuppetRun:
        """Step every input frame; returns self."""
        for inp in inputs:
            self.step(inp)
        return self

    @property
    def duration(self) -> float:
        """Seconds from the first frame to the last."""
        return 0.0 if self.t0 is None or self.t_last is None else self.t_last - self.t0

    def timeline(self) -> list[dict[str, Any]]:
        """The state changes, ``[{"t": seconds, "state": name}, ...]``, the first at the first frame."""
        return [{"t": round(float(t), 6), "state": s} for t, s in self._timeline]

    def state_times(self) -> dict[str, float]:
        """Seconds spent in each state (the last one until the last frame), in order of first visit."""
        out: dict[str, float] = {}
        tl = self._timeline
        for k, (t, s) in enumerate(tl):
            end = tl[k + 1][0] if k + 1 < len(tl) else (self.t_last if self.t_last is not None else t)
            out[s] = out.get(s, 0.0) + max(0.0, float(end) - float(t))
        return out

    def states_visited(self) -> list[str]:
        """State names in the order they were first entered."""
        return list(dict.fromkeys(s for _, s in self._timeline))

    def clip(self, name: str = "puppet") -> Clip:
        """The performance as a clip at the fixed rate (fps = rate).

        Raises:
            ValueError: no frames, or the frames were not kept.
        """
        if not self._root:
            raise ValueError("no frames to export" if self.keep_frames else "the frames were not kept")
        return Clip(name, self.retargeter.skeleton, self.rate, np.stack(self._root), np.stack(self._rot))


# ------------------------------------------------------------------------------------------------ live
class PuppetFollower(Processor):
    """Drives a :class:`PuppetRun` from a phone's live samples on the bus, and puts the poses back on it.

    Frames are stepped on a fixed-rate grid of bus time starting at the first attitude sample: each
    attitude sample steps every grid time up to its own, the orientation slerped from the sample before.
    Touch samples queue touch changes, applied at the first frame at or after their time.

    As a processor (``Capture.add_processor``) it publishes the pose stream ``<device>/puppet`` (kind
    ``pose``): one sample per frame at the frame's bus time, values the root position (``root.x/y/z``, m)
    then each joint's local rotation (``<joint>.w/x/y/z``), so recorders, dashboards and bridges get the
    character like any other stream.

    Args:
        device: the phone's device name.
        attitude: its attitude stream (``<device>/attitude``: euler or quat).
        run: where frames go.
        touch: its touch stream (``<device>/touch``), if it has one.
        hold: the phone counts as held throughout (touches ignored).

    Raises:
        ConfigError: ``attitude`` is not an attitude stream, or ``touch`` has no phase channel.
    """

    accepts = frozenset({Sample, SampleBatch})

    def __init__(self, device: str, attitude: StreamInfo, run: PuppetRun, *, touch: StreamInfo | None = None,
                 hold: bool = False) -> None:
        attitude_quaternions(attitude, np.zeros((0, len(attitude.channels))))   # checks the stream
        self.device = device
        self.attitude = attitude
        self.touch_stream = touch.name if touch is not None else f"{device}/touch"
        self._phase_col, self._id_col = touch_columns(touch.channels if touch is not None else ("phase", "id"))
        self.run = run
        self.hold = hold
        self.period_ns = 1e9 / run.rate
        self.origin_ns: int | None = None
        self.next_k = 0
        self._prev: tuple[int, np.ndarray] | None = None
        self._touch = TouchState()
        self._pending: deque[tuple[int, float, float]] = deque()
        self._held = False
        self.samples = 0
        self.touches = 0
        self.skipped = 0
        self.errors = 0
        self.first_error: str | None = None
        sk = run.retargeter.skeleton
        channels = ("root.x", "root.y", "root.z", *(f"{j}.{c}" for j in sk.names for c in "wxyz"))
        skeleton = json.dumps({"parents": np.asarray(sk.parents).tolist(), "offsets": np.asarray(sk.offsets).tolist()})
        self.pose = StreamInfo(f"{device}/puppet", "pose", channels, ("m",) * 3 + ("1",) * (4 * sk.n_joints),
                               run.rate, attitude.device, extra={SKELETON_KEY: skeleton})
        self._publish: Callable[[Any], None] | None = None
        self.published = 0

    def output_streams(self) -> list[StreamInfo]:
        """The pose stream this follower publishes once bound (see the class)."""
        return [self.pose]

    def bind(self, publish: Callable[[Any], None]) -> None:
        """Set the bus's publish callable (``Capture.add_processor`` does)."""
        self._publish = publish
        self.publishes = True          # drained before the other subscribers when the bus closes

    @classmethod
    def for_device(cls, device: str, streams: Sequence[StreamInfo], run: PuppetRun, *,
                   hold: bool | None = None) -> PuppetFollower:
        """The follower of a device's streams; ``hold`` None: held throughout when it has no touch stream.

        Raises:
            ConfigError: the device has no attitude stream.
        """
        by_name = {s.name: s for s in streams}
        info = next((by_name[f"{device}/{leaf}"] for leaf in ATTITUDE_STREAMS if f"{device}/{leaf}" in by_name), None)
        if info is None:
            raise ConfigError(f"device {device} has no attitude stream ({device}/attitude) to drive the puppet;"
                              f" its streams: {', '.join(by_name) or 'none'}")
        touch = by_name.get(f"{device}/touch")
        return cls(device, info, run, touch=touch, hold=touch is None if hold is None else hold)

    @property
    def t_s(self) -> float:
        """Seconds of phone time followed so far."""
        return self.run.duration

    @property
    def unknown_touches(self) -> int:
        """Touch rows applied so far whose phase was not 0-3 (ignored)."""
        return self._touch.unknown

    def on_item(self, item: Any) -> None:
        stream = item.stream
        if stream == self.attitude.name:
            if type(item) is Sample:
                self._attitude(np.array([item.t_bus_ns], np.int64), np.array([item.values], np.float64))
            else:
                self._attitude(np.asarray(item.t_bus_ns, np.int64), np.asarray(item.values, np.float64))
        elif stream == self.touch_stream and not self.hold:
            if type(item) is Sample:
                rows: list[tuple[int, list[float]]] = [(int(item.t_bus_ns), list(item.values))]
            else:
                rows = list(zip(np.asarray(item.t_bus_ns).tolist(), np.asarray(item.values).tolist(), strict=True))
            p, i = self._phase_col, self._id_col
            for t, v in rows:
                self._pending.append((int(t), float(v[p]), 0.0 if i is None else float(v[i])))
            self.touches += len(rows)

    def _attitude(self, t_ns: np.ndarray, values: np.ndarray) -> None:
        q = attitude_quaternions(self.attitude, values)
        for t, qi in zip(t_ns.tolist(), q, strict=True):
            self.samples += 1
            if not np.all(np.isfinite(qi)) or (self._prev is not None and t <= self._prev[0]):
                self.skipped += 1
                continue
            if self.origin_ns is None or self._prev is None:
                self.origin_ns = t
                self._frame(t, qi)
                self.next_k = 1
            else:
                t_prev, q_prev = self._prev
                while True:
                    g = self.origin_ns + round(self.next_k * self.period_ns)
                    if g > t + GRID_SLACK_NS:
                        break
                    self._frame(g, quat_slerp(q_prev, qi, min(1.0, (g - t_prev) / (t - t_prev))))
                    self.next_k += 1
            self._prev = (t, qi)

    def _frame(self, g_ns: int, q: np.ndarray) -> None:
        pend = self._pending
        while pend and pend[0][0] <= g_ns:
            _, phase, ident = pend.popleft()
            self._held = self._touch.apply(phase, ident)
        assert self.origin_ns is not None
        inp = PhoneInput((g_ns - self.origin_ns) / 1e9, tuple(q.tolist()), self.hold or self._held, None)
        try:
            frame = self.run.step(inp)
        except ValueError as exc:
            self.on_error(exc)
            return
        if self._publish is not None:
            values = (*frame.root_pos.tolist(), *np.asarray(frame.rotations, np.float64).ravel().tolist())
            self._publish(Sample(self.pose.name, self.published, g_ns, None, g_ns, values))
            self.published += 1

    def on_error(self, exc: BaseException) -> None:
        self.errors += 1
        if self.first_error is None:
            self.first_error = f"{type(exc).__name__}: {exc}"
            log.warning("puppet follower on %s: %s (further errors are counted)", self.attitude.name,
                        self.first_error)
