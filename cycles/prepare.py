"""Preparing a take for cycle extraction, and mapping the result back to the take's columns.

This module owns step 1 of :func:`cycles.extract` (Ciccone 2019 leaves it out: section 5.3 starts from
clean vectors on a uniform grid; perfcap's choices are in ``docs/design/cycles.md``): ``prepare`` leaves
out non-finite samples and repeated stamps, keeps every stretch between gaps (one after another, their
starts and times in ``Prepared.starts`` and ``start_t``; ``Prepared.times`` maps rows back), resamples
irregular stamps to a uniform grid, unwraps Euler angles and maps each quaternion to rotation vectors about the
take's chordal mean (hemisphere-continuous), so that everything after works on plain vectors;
``to_input`` undoes the mapping for the finished loop. ``interp_rows`` and ``at_positions`` are the linear
interpolation the other steps share.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from capture.errors import NoPeriodFoundError

if TYPE_CHECKING:
    from collections.abc import Sequence

    from cycles._types import FloatArray, IntArray

__all__ = ["MIN_STRETCH", "Prepared", "at_positions", "interp_rows", "prepare", "to_input"]

#: the fewest samples a stretch between gaps needs to be kept
MIN_STRETCH = 8


@dataclass
class Prepared:
    t0: float
    dt: float
    x: FloatArray                     # (n, W) working columns
    columns: list[tuple[str, list[int], list[int]]]  # (kind, input cols, working cols)
    q_refs: dict[int, Rotation]       # working col start -> reference rotation
    angle_scale: float
    notes: list[str]
    # the stretches of the take between gaps, one after the other in x: the row each starts at and
    # its time; the grid step of x (``dt`` is the matching's step, which extract may change)
    starts: IntArray = field(default_factory=lambda: np.zeros(1, np.intp))
    start_t: FloatArray = field(default_factory=lambda: np.zeros(1))
    grid_dt: float = 0.0

    def times(self, rows: FloatArray) -> FloatArray:
        """The input's times of (fractional) rows of ``x``: each row in its stretch's time base."""
        r = np.asarray(rows, np.float64)
        i = np.clip(np.searchsorted(self.starts, np.floor(r + 1e-9), side="right") - 1, 0, self.starts.size - 1)
        out: FloatArray = self.start_t[i] + (r - self.starts[i]) * self.grid_dt
        return out


def prepare(t: FloatArray, v: FloatArray, quaternions: Sequence[Sequence[int]], angles: Sequence[int],
             angle_unit: str, gap_factor: float, min_gap_s: float = 0.1) -> Prepared:
    c = v.shape[1]
    notes: list[str] = []
    finite = np.isfinite(t) & np.all(np.isfinite(v), axis=1)
    if not finite.all():
        notes.append(f"{int((~finite).sum())} sample(s) with a missing or non-finite value left out")
        t, v = t[finite], v[finite]
    order = np.argsort(t, kind="stable")
    t, v = t[order], v[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    if not keep.all():
        notes.append(f"{int((~keep).sum())} sample(s) with a repeated time stamp left out")
        t, v = t[keep], v[keep]
    if t.size < 8:
        raise NoPeriodFoundError(f"only {t.size} usable samples: a cycle needs several loops of motion")
    dt_all = np.diff(t)
    # A gap is an interval far beyond the usual ones: gap_factor times the median for a steady rate,
    # but measured against the 95th percentile when the stamps are irregular by nature (a phone's
    # sensor events), so ordinary long intervals do not split the take.
    med = float(np.median(dt_all))
    # Short holds (a mouse reports only changes, so it is silent while the hand turns round) are not
    # gaps: nothing shorter than min_gap_s splits the take; it is interpolated over.
    usual = max(med, float(np.percentile(dt_all, 95)) if np.percentile(dt_all, 95) > 1.5 * med else med)
    gap_at = max(gap_factor * usual, min_gap_s)
    gaps = np.flatnonzero(dt_all > gap_at)
    dt = med if usual == med else float(np.mean(dt_all[dt_all <= gap_factor * usual]))
    # Every stretch between gaps is kept (a performer who stops the recording and starts again loops
    # on both sides); the stretches follow one another in x, and the matching treats each joint as a
    # break that no loop crosses. Stretches too short for any loop (under MIN_STRETCH samples) are
    # left out.
    bounds = np.concatenate([[0], gaps + 1, [t.size]])
    pieces = [(int(a), int(b)) for a, b in itertools.pairwise(bounds) if b - a >= MIN_STRETCH]
    if gaps.size:
        dropped = int(t.size - sum(b - a for a, b in pieces))
        notes.append(f"the take has {gaps.size} gap(s) longer than {gap_at:.3g} s (the longest"
                     f" {float(dt_all[gaps].max()):.3g} s); its {len(pieces)} stretch(es) are matched as one"
                     f" take with breaks no loop crosses"
                     + (f"; {dropped} sample(s) in stretches too short for a loop left out" if dropped else ""))
        if not pieces:
            raise NoPeriodFoundError("no stretch of the take without a gap is long enough for a cycle")
        steps_in = np.concatenate([np.diff(t[a:b]) for a, b in pieces])
        dt = float(np.median(steps_in)) if usual == med else float(np.mean(steps_in))
    if sum(b - a for a, b in pieces) < 8:
        raise NoPeriodFoundError("no stretch of the take without a gap is long enough for a cycle")

    qcols = [list(q) for q in quaternions]
    flat_q = [i for q in qcols for i in q]
    for q in qcols:
        if len(q) != 4 or len(set(q)) != 4:
            raise ValueError(f"a quaternion is 4 distinct columns (w, x, y, z), not {q}")
    angle_cols = list(angles)
    all_special = flat_q + angle_cols
    if len(set(all_special)) != len(all_special) or any(not 0 <= i < c for i in all_special):
        raise ValueError("quaternion and angle columns must be distinct, existing columns")
    if angle_unit not in ("rad", "deg"):
        raise ValueError("angle_unit must be 'rad' or 'deg'")
    angle_scale = math.pi / 180.0 if angle_unit == "deg" else 1.0

    columns: list[tuple[str, list[int], list[int]]] = []
    q_refs: dict[int, Rotation] = {}
    blocks: list[tuple[list[int], FloatArray]] = []   # (working columns, values) of quats and angles
    lin_in: list[int] = []
    lin_w: list[int] = []
    w = 0
    qstart = {q[0]: q for q in qcols}
    flat_set, angle_set = set(flat_q), set(angle_cols)
    for i in range(c):
        if i in flat_set and i not in qstart:
            continue
        if i in qstart:
            q = qstart[i]
            quat = v[:, q].astype(np.float64)
            norm = np.linalg.norm(quat, axis=1)
            if np.any(norm < 1e-6):
                raise ValueError(f"quaternion columns {q} hold a zero quaternion")
            quat = quat / norm[:, None]
            # hemisphere continuity: q and -q are one rotation
            flips = np.cumprod(np.where(np.sum(quat[1:] * quat[:-1], axis=1) < 0, -1.0, 1.0))
            quat[1:] *= flips[:, None]
            m = quat.T @ quat
            ref = np.linalg.eigh(m)[1][:, -1]   # chordal mean
            r_ref = Rotation.from_quat(ref[[1, 2, 3, 0]])
            rv = (r_ref.inv() * Rotation.from_quat(quat[:, [1, 2, 3, 0]])).as_rotvec()
            blocks.append(([w, w + 1, w + 2], rv))
            columns.append(("quat", q, [w, w + 1, w + 2]))
            q_refs[w] = r_ref
            w += 3
        elif i in angle_set:
            blocks.append(([w], np.unwrap(v[:, i].astype(np.float64) * angle_scale)[:, None]))
            columns.append(("angle", [i], [w]))
            w += 1
        else:
            lin_in.append(i)
            lin_w.append(w)
            w += 1
    if lin_in:
        columns.append(("linear", lin_in, lin_w))
    x = np.empty((v.shape[0], w))
    x[:, lin_w] = v[:, lin_in]
    for wc, val in blocks:
        x[:, wc] = val

    rows, starts, start_t = [], [], []
    at = 0
    for a, b in pieces:
        ts, xs = t[a:b], x[a:b]
        steps = np.diff(ts)
        if np.max(np.abs(steps - dt)) > 1e-3 * dt:
            m = math.floor((ts[-1] - ts[0]) / dt + 1e-9) + 1
            xs = interp_rows(ts, xs, ts[0] + dt * np.arange(m))
        rows.append(xs)
        starts.append(at)
        start_t.append(float(ts[0]))
        at += xs.shape[0]
    x = rows[0] if len(rows) == 1 else np.concatenate(rows)
    return Prepared(t0=start_t[0], dt=dt, x=np.ascontiguousarray(x), columns=columns, q_refs=q_refs,
                    angle_scale=angle_scale, notes=notes, starts=np.asarray(starts, np.intp),
                    start_t=np.asarray(start_t), grid_dt=dt)


def interp_rows(t: FloatArray, x: FloatArray, at: FloatArray) -> FloatArray:
    """Linear interpolation of every column of ``x`` (sampled at ``t``) at times ``at``."""
    j = np.clip(np.searchsorted(t, at, side="right"), 1, t.size - 1)
    w = ((at - t[j - 1]) / (t[j] - t[j - 1]))[:, None]
    return x[j - 1] * (1.0 - w) + x[j] * w


def at_positions(x: FloatArray, pos: FloatArray) -> FloatArray:
    """Rows of ``x`` at fractional sample positions ``pos`` (linear interpolation)."""
    n = x.shape[0]
    p = np.clip(pos, 0.0, n - 1.0)
    j = np.minimum(p.astype(np.int64), n - 2)
    w = (p - j)[:, None]
    rows: FloatArray = x[j] * (1.0 - w) + x[j + 1] * w
    return rows


def to_input(work: Prepared, y: FloatArray, c: int) -> FloatArray:
    """Working columns back to the input's columns and units."""
    out = np.empty((y.shape[0], c))
    for kind, cols, wc in work.columns:
        if kind == "quat":
            r = work.q_refs[wc[0]] * Rotation.from_rotvec(y[:, wc])
            q = r.as_quat()[:, [3, 0, 1, 2]]
            # keep the hemisphere of the reference (w >= 0 relative to it) so loops stay continuous
            out[:, cols] = q
        elif kind == "angle":
            out[:, cols[0]] = y[:, wc[0]] / work.angle_scale
        else:
            out[:, cols] = y[:, wc]
    return out

