"""BVH (Biovision hierarchy) files in and out: ``read_bvh``/``parse_bvh`` turn a file into a ``Skeleton``
and a ``Clip``; ``write_bvh``/``format_bvh`` write a clip back. No dependency beyond numpy and scipy.

Reading accepts ROOT/JOINT/End Site blocks, OFFSET, CHANNELS in any order and any rotation order (a
``Zrotation Yrotation Xrotation`` joint turns by ``Rz @ Ry @ Rx``, intrinsic), position channels on the root
only, degrees. Lengths are multiplied by ``scale`` to give metres (the caller knows the file's unit; the
cgspeed CMU conversion uses ``CMU_SCALE``). End Sites are dropped unless ``end_sites=True``, which keeps each
as a joint named ``<parent>_end`` with an identity rotation. Any malformed input raises a one-line
``TraceError`` with the path and line number.

Writing nests the joints depth-first (children in index order; a skeleton listed in another parent-first
order reads back in that depth-first order), gives the root six channels (positions, then the rotation
order) and every other joint three;
a leaf named ``*_end`` is written as an End Site, any other leaf gets an End Site half its own bone long.
Values are written with 8 decimals, so a clip read back has the same forward kinematics within 1e-6 m.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from capture.errors import TraceError
from retarget.skeleton import Clip, Skeleton, guess_unity_names

if TYPE_CHECKING:
    from retarget._types import FloatArray

__all__ = ["CMU_SCALE", "END_SITE_SUFFIX", "format_bvh", "parse_bvh", "read_bvh", "write_bvh"]

CMU_SCALE = 0.0254 / 0.45
"""Metres per unit of the cgspeed CMU BVH conversion (CMU FAQ: units are inches / 0.45)."""

END_SITE_SUFFIX = "_end"
"""Name suffix of joints that stand for BVH End Sites."""

_ROT = {"Xrotation": "X", "Yrotation": "Y", "Zrotation": "Z"}
_POS = {"Xposition": 0, "Yposition": 1, "Zposition": 2}


class _Joint:
    __slots__ = ("channels", "line", "name", "offset", "parent")

    def __init__(self, name: str, parent: int, line: int) -> None:
        self.name = name
        self.parent = parent
        self.line = line
        self.offset: FloatArray | None = None
        self.channels: list[str] = []


class _Parser:
    """Recursive descent over the HIERARCHY tokens (each with its 1-based line number)."""

    def __init__(self, tokens: list[tuple[str, int]], end_line: int, path: str | None) -> None:
        self.tokens = tokens
        self.pos = 0
        self.end_line = end_line
        self.path = path
        self.joints: list[_Joint] = []

    def error(self, message: str, line: int | None) -> TraceError:
        return TraceError(message, path=self.path, line=line)

    def next(self, expected: str) -> tuple[str, int]:
        if self.pos >= len(self.tokens):
            raise self.error(f"unexpected end of the hierarchy, expected {expected}", self.end_line)
        tok = self.tokens[self.pos]
        self.pos += 1
        return tok

    def peek(self) -> str | None:
        return self.tokens[self.pos][0] if self.pos < len(self.tokens) else None

    def number(self, what: str) -> float:
        tok, line = self.next(what)
        try:
            v = float(tok)
        except ValueError:
            raise self.error(f"non-numeric value {tok!r} in {what}", line) from None
        if not np.isfinite(v):
            raise self.error(f"non-finite value {tok!r} in {what}", line)
        return v

    def offset(self) -> FloatArray:
        return np.array([self.number("OFFSET") for _ in range(3)])

    def expect(self, word: str, after: str) -> int:
        tok, line = self.next(f"'{word}' after {after}")
        if tok != word:
            raise self.error(f"expected '{word}' after {after}, got {tok!r}", line)
        return line

    def joint(self, kind: str, parent: int) -> None:
        name, line = self.next(f"a name after {kind}")
        if name in ("{", "}"):
            raise self.error(f"{kind} without a name", line)
        if any(j.name == name for j in self.joints):
            raise self.error(f"duplicate joint name {name!r}", line)
        me = len(self.joints)
        j = _Joint(name, parent, line)
        self.joints.append(j)
        self.expect("{", f"{kind} {name}")
        while True:
            if self.pos >= len(self.tokens):
                raise self.error(f"missing '}}' closing {kind} {name} (opened at line {line})", self.end_line)
            tok, tline = self.next("'}'")
            if tok == "OFFSET":
                j.offset = self.offset()
            elif tok == "CHANNELS":
                self.channels(j, kind, tline)
            elif tok == "JOINT":
                self.joint("JOINT", me)
            elif tok == "End":
                self.end_site(me, tline)
            elif tok == "}":
                break
            elif tok == "{":
                raise self.error(f"unexpected '{{' in {kind} {name} (missing JOINT or End Site?)", tline)
            else:
                raise self.error(f"unexpected {tok!r} in {kind} {name}", tline)
        if j.offset is None:
            raise self.error(f"{kind} {name} has no OFFSET", line)

    def channels(self, j: _Joint, kind: str, line: int) -> None:
        tok, nline = self.next("a channel count")
        try:
            n = int(tok)
        except ValueError:
            raise self.error(f"CHANNELS needs a count, got {tok!r}", nline) from None
        if not 0 <= n <= 6:
            raise self.error(f"CHANNELS count must be 0..6, got {n}", nline)
        names: list[str] = []
        while len(names) < n and self.peek() in _ROT.keys() | _POS.keys():
            names.append(self.next("a channel name")[0])
        if len(names) != n:
            found = self.peek()
            raise self.error(f"CHANNELS of {j.name} declares {n} channels but lists {len(names)}"
                             + (f" (then {found!r})" if found is not None else ""), line)
        if len(set(names)) != n:
            raise self.error(f"CHANNELS of {j.name} repeats a channel", line)
        if kind != "ROOT" and any(c in _POS for c in names):
            raise self.error(f"{j.name}: only the root may have position channels", line)
        j.channels = names

    def end_site(self, parent: int, line: int) -> None:
        tok, tline = self.next("'Site' after 'End'")
        if tok != "Site":
            raise self.error(f"expected 'Site' after 'End', got {tok!r}", tline)
        self.expect("{", "End Site")
        off = None
        while True:
            if self.pos >= len(self.tokens):
                raise self.error(f"missing '}}' closing End Site (opened at line {line})", self.end_line)
            tok, tline = self.next("'}'")
            if tok == "OFFSET":
                off = self.offset()
            elif tok == "}":
                break
            else:
                raise self.error(f"unexpected {tok!r} in End Site", tline)
        if off is None:
            raise self.error("End Site has no OFFSET", line)
        pname = self.joints[parent].name
        name = pname + END_SITE_SUFFIX
        k = 2
        while any(j.name == name for j in self.joints):
            name = f"{pname}{END_SITE_SUFFIX}{k}"
            k += 1
        j = _Joint(name, parent, line)
        j.offset = off
        j.channels = []
        j.line = -line  # negative: an End Site
        self.joints.append(j)


def _snap_fps(frame_time: float) -> float:
    fps = 1.0 / frame_time
    r = round(fps)
    return float(r) if r > 0 and abs(fps - r) <= 2e-5 * fps else fps


def parse_bvh(text: str, *, scale: float = 1.0, end_sites: bool = False, name: str = "bvh",
              path: str | None = None) -> tuple[Skeleton, Clip]:
    """Parse BVH text.

    Args:
        text: the whole file.
        scale: metres per file unit (offsets and root positions are multiplied by it).
        end_sites: keep End Sites as joints named ``<parent>_end``.
        name: the clip's name.
        path: the file name used in error messages.

    Returns:
        ``(skeleton, clip)``; the clip has no contacts, key-times ``(0, duration)`` and ``loop=False``; its
        frame rate is ``1 / Frame Time``, snapped to a whole number within 20 ppm (``.0083333`` -> 120).

    Raises:
        ValueError: if ``scale`` is not finite and > 0.
        TraceError: if the text is not a well-formed BVH file (with the line number).
    """
    if not np.isfinite(scale) or scale <= 0:
        raise ValueError(f"scale must be finite and > 0, got {scale}")
    lines = text.splitlines()
    first = next((i for i, ln in enumerate(lines) if ln.strip()), None)
    if first is None:
        raise TraceError("empty BVH file", path=path, line=1)
    if lines[first].split()[0] != "HIERARCHY":
        raise TraceError(f"expected HIERARCHY, got {lines[first].split()[0]!r}", path=path, line=first + 1)
    motion = next((i for i in range(first + 1, len(lines)) if lines[i].split()[:1] == ["MOTION"]), None)
    h_end = motion if motion is not None else len(lines)
    tokens = [(tok, i + 1) for i in range(first + 1, h_end) for tok in lines[i].split()]
    parser = _Parser(tokens, h_end + 1 if motion is not None else len(lines), path)
    tok, line = parser.next("ROOT")
    if tok != "ROOT":
        raise TraceError(f"expected ROOT, got {tok!r}", path=path, line=line)
    parser.joint("ROOT", -1)
    if parser.pos < len(tokens):
        tok, line = tokens[parser.pos]
        msg = "a second ROOT is not supported" if tok == "ROOT" else f"unexpected {tok!r} after the ROOT block"
        raise TraceError(msg, path=path, line=line)
    if motion is None:
        raise TraceError("no MOTION section", path=path, line=len(lines))
    joints = parser.joints

    # MOTION header
    body = [(i + 1, lines[i]) for i in range(motion + 1, len(lines)) if lines[i].strip()]
    if len(body) < 2:
        raise TraceError("MOTION needs 'Frames:' and 'Frame Time:' lines", path=path, line=len(lines))
    (fl, ftext), (tl, ttext) = body[0], body[1]
    head, _, value = ftext.partition(":")
    if head.strip() != "Frames":
        raise TraceError(f"expected 'Frames:', got {ftext.strip()!r}", path=path, line=fl)
    try:
        n_frames = int(value)
    except ValueError:
        raise TraceError(f"frame count {value.strip()!r} is not a whole number", path=path, line=fl) from None
    head, _, value = ttext.partition(":")
    if " ".join(head.split()) != "Frame Time":
        raise TraceError(f"expected 'Frame Time:', got {ttext.strip()!r}", path=path, line=tl)
    try:
        frame_time = float(value)
    except ValueError:
        raise TraceError(f"frame time {value.strip()!r} is not a number", path=path, line=tl) from None
    if not np.isfinite(frame_time) or frame_time <= 0:
        raise TraceError(f"frame time must be > 0, got {frame_time}", path=path, line=tl)
    if n_frames < 1:
        raise TraceError(f"a BVH clip needs at least one frame, Frames: {n_frames}", path=path, line=fl)
    rows = body[2:]
    if len(rows) < n_frames:
        raise TraceError(f"Frames: {n_frames} declared but only {len(rows)} frame lines follow",
                         path=path, line=fl)
    if len(rows) > n_frames:
        raise TraceError(f"more frame lines than the {n_frames} declared", path=path, line=rows[n_frames][0])

    # frame values
    n_ch = sum(len(j.channels) for j in joints)
    data = np.empty((n_frames, n_ch))
    for k, (ln, row) in enumerate(rows):
        parts = row.split()
        if len(parts) != n_ch:
            raise TraceError(f"frame {k} has {len(parts)} values, the hierarchy declares {n_ch} channels",
                             path=path, line=ln)
        try:
            data[k] = [float(p) for p in parts]
        except ValueError:
            bad = next(p for p in parts if not _is_float(p))
            raise TraceError(f"non-numeric value {bad!r} in frame {k}", path=path, line=ln) from None
    if not np.all(np.isfinite(data)):
        k = int(np.flatnonzero(~np.all(np.isfinite(data), axis=1))[0])
        raise TraceError(f"non-finite value in frame {k}", path=path, line=rows[k][0])

    # to skeleton and clip
    keep = [i for i, j in enumerate(joints) if end_sites or j.line > 0]
    new_index = {old: new for new, old in enumerate(keep)}
    names = tuple(joints[i].name for i in keep)
    parents = np.array([-1 if joints[i].parent < 0 else new_index[joints[i].parent] for i in keep])
    offsets = np.array([joints[i].offset for i in keep]) * scale
    skeleton = Skeleton(names, parents, offsets, guess_unity_names(names))
    root_pos = np.zeros((n_frames, 3))
    rotations = np.zeros((n_frames, len(keep), 4))
    rotations[..., 0] = 1.0
    groups: dict[str, list[tuple[int, list[int]]]] = {}
    col = 0
    for i, j in enumerate(joints):
        order = ""
        cols = []
        for c in j.channels:
            if c in _POS:
                root_pos[:, _POS[c]] = data[:, col] * scale
            else:
                order += _ROT[c]
                cols.append(col)
            col += 1
        if order:
            groups.setdefault(order, []).append((new_index[i], cols))
    for order, members in groups.items():
        angles = np.stack([data[:, cols] for _, cols in members], axis=1)       # (F, m, len(order))
        xyzw = Rotation.from_euler(order, angles.reshape(-1, len(order)), degrees=True).as_quat()
        q = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1).reshape(n_frames, len(members), 4)
        rotations[:, [m for m, _ in members]] = q
    clip = Clip(name, skeleton, _snap_fps(frame_time), root_pos, rotations)
    return skeleton, clip


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def read_bvh(path: str | Path, *, scale: float = 1.0, end_sites: bool = False,
             name: str | None = None) -> tuple[Skeleton, Clip]:
    """Read a BVH file (see ``parse_bvh``); the clip is named after the file unless ``name`` is given.

    Raises:
        OSError: if the file cannot be read.
        ValueError: if ``scale`` is not finite and > 0.
        TraceError: if the file is not well-formed BVH (with the path and line number).
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise TraceError(f"not a text file ({e.reason} at byte {e.start})", path=str(p)) from e
    return parse_bvh(text, scale=scale, end_sites=end_sites, name=name or p.stem, path=str(p))


def format_bvh(clip: Clip, *, scale: float = 1.0, order: str = "ZXY") -> str:
    """A clip as BVH text.

    Args:
        clip: the motion (its skeleton gives the hierarchy).
        scale: metres per file unit (1.0 writes metres, 0.01 centimetres).
        order: rotation channel order, a permutation of ``"XYZ"`` (``"ZXY"`` and ``"ZYX"`` are the usual).

    Returns:
        the file text.

    Raises:
        ValueError: for a bad ``scale`` or ``order``, or a joint name BVH cannot hold (empty, spaces, braces).
    """
    if not np.isfinite(scale) or scale <= 0:
        raise ValueError(f"scale must be finite and > 0, got {scale}")
    if sorted(order) != ["X", "Y", "Z"]:
        raise ValueError(f"order must be a permutation of 'XYZ', got {order!r}")
    sk = clip.skeleton
    for joint in sk.names:
        if not joint or any(c.isspace() for c in joint) or "{" in joint or "}" in joint:
            raise ValueError(f"joint name {joint!r} cannot be written to BVH")
    n = sk.n_joints
    kids: list[list[int]] = [[] for _ in range(n)]
    for j in range(1, n):
        kids[int(sk.parents[j])].append(j)
    is_end = [j > 0 and not kids[j] and sk.names[j].endswith(END_SITE_SUFFIX) for j in range(n)]
    rot_ch = " ".join(f"{a}rotation" for a in order)

    def vec(v: FloatArray) -> str:
        return " ".join(f"{x / scale:.8f}" for x in v)

    out = ["HIERARCHY"]
    channel_joints: list[int] = []

    def emit(j: int, depth: int) -> None:
        pad = "\t" * depth
        if is_end[j]:
            out.extend([f"{pad}End Site", f"{pad}{{", f"{pad}\tOFFSET {vec(sk.offsets[j])}", f"{pad}}}"])
            return
        channel_joints.append(j)
        out.append(f"{pad}{'ROOT' if j == 0 else 'JOINT'} {sk.names[j]}")
        out.append(f"{pad}{{")
        out.append(f"{pad}\tOFFSET {vec(sk.offsets[j])}")
        out.append(f"{pad}\tCHANNELS 6 Xposition Yposition Zposition {rot_ch}" if j == 0
                   else f"{pad}\tCHANNELS 3 {rot_ch}")
        for c in kids[j]:
            emit(c, depth + 1)
        if not kids[j]:
            out.extend([f"{pad}\tEnd Site", f"{pad}\t{{", f"{pad}\t\tOFFSET {vec(0.5 * sk.offsets[j])}",
                        f"{pad}\t}}"])
        out.append(f"{pad}}}")

    emit(0, 0)
    f = clip.n_frames
    q = clip.rotations[:, channel_joints]                        # (F, m, 4) scalar-first
    xyzw = np.concatenate([q[..., 1:], q[..., :1]], axis=-1).reshape(-1, 4)
    with warnings.catch_warnings():
        # at gimbal lock scipy still returns a valid angle triple; the warning is noise here
        warnings.filterwarnings("ignore", message=".*[Gg]imbal lock.*")
        eul = Rotation.from_quat(xyzw).as_euler(order, degrees=True).reshape(f, -1)
    values = np.concatenate([clip.root_pos / scale, eul], axis=1)
    out += ["MOTION", f"Frames: {f}", f"Frame Time: {1.0 / clip.fps:.10f}"]
    buf = io.StringIO()
    np.savetxt(buf, values, fmt="%.8f", delimiter=" ")
    return "\n".join(out) + "\n" + buf.getvalue()


def write_bvh(path: str | Path, clip: Clip, *, scale: float = 1.0, order: str = "ZXY") -> None:
    """Write a clip to a BVH file (see ``format_bvh``).

    Raises:
        OSError: if the file cannot be written.
        ValueError: as ``format_bvh``.
    """
    Path(path).write_text(format_bvh(clip, scale=scale, order=order), encoding="utf-8")
