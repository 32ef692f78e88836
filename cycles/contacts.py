"""Planar contacts on a cycle: Ciccone 2019's MoCurve contacts (chapter 5, section 5.4.3, eq. 5.12).

This module owns ``project_to_plane`` (points on or below a contact plane snapped onto it),
``contact_intervals`` (the runs of contact frames of a loop, merged across the seam), ``fix_sliding`` (the
items in contact share one root-relative velocity lambda, their contact stretches are rebuilt by
integrating it, the rest of each curve is re-scaled so the joins stay continuous, and the root moves
against lambda, so feet in contact do not slide and the character travels) and its ``ContactResult``.
The thesis leaves the headless details open (the plane, how lambda is fitted, where the integration
starts, how the rest of the curve is scaled); perfcap's choices are in ``docs/design/cycles.md``. Frame
arrays follow :mod:`cycles.edit`'s conventions.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.interpolate import splantider, splev, splrep

from cycles._checks import finite_array, loop_frames, positive_finite, unit_vector

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from cycles._types import BoolArray, FloatArray

__all__ = ["ContactResult", "contact_intervals", "fix_sliding", "project_to_plane"]


def project_to_plane(
    P: FloatArray,
    point: Sequence[float] | FloatArray = (0.0, 0.0, 0.0),
    normal: Sequence[float] | FloatArray = (0.0, 1.0, 0.0),
    eps: float = 0.0,
) -> tuple[FloatArray, BoolArray]:
    """Snap the points on or below a plane onto it: ``p <- p - ((p - p0) . n) n``.

    A point is in contact when its signed distance ``(p - p0) . n`` (``n`` normalised) is at most
    ``eps``; those points are projected, all others are returned unchanged.

    Args:
        P: ``(m, 3)`` points.
        point: a point ``p0`` on the plane (default the origin).
        normal: the plane normal, pointing away from the solid side (default ``+y``); any length.
        eps: contact tolerance in length units (default 0: on or below the plane).

    Returns:
        ``(P', mask)``: the projected copy and the ``(m,)`` boolean contact mask.

    Raises:
        ValueError: ``P`` is not ``(m, 3)`` and finite, ``normal`` is zero, or ``point``/``eps`` are not
            finite.
    """
    arr = finite_array(P, "P", (2,))
    if arr.shape[1] != 3:
        raise ValueError(f"P must be (m, 3), got shape {arr.shape}")
    p0 = finite_array(point, "point", (1,))
    if p0.shape != (3,):
        raise ValueError(f"point must have 3 components, got shape {p0.shape}")
    n = unit_vector(normal, "normal")
    e = float(eps)
    if not math.isfinite(e):
        raise ValueError("eps must be finite")
    dist = (arr - p0) @ n
    mask = dist <= e
    out = arr.copy()
    out[mask] -= np.outer(dist[mask], n)
    return out, mask


def contact_intervals(mask: BoolArray | Sequence[bool]) -> list[tuple[int, int]]:
    """The runs of consecutive contact frames of a loop, merged across the seam.

    ``mask`` covers the loop's ``n`` distinct frames (frame ``n`` would be frame 0 again). Each run is a
    half-open ``(start, stop)``, frames ``start .. stop - 1``; a run that ends at frame ``n - 1`` and one
    that starts at frame 0 are one interval across the seam, reported with ``stop > n`` (its frames are
    ``range(start, stop)`` modulo ``n``). A mask that is all true is the single interval ``(0, n)``.

    Args:
        mask: ``(n,)`` booleans, true where the item is in contact.

    Returns:
        The intervals, ordered by ``start``.

    Raises:
        ValueError: ``mask`` is not one-dimensional.
    """
    arr = np.asarray(mask, dtype=bool)
    if arr.ndim != 1:
        raise ValueError(f"mask must be one-dimensional, got shape {arr.shape}")
    n = arr.size
    if n == 0 or not arr.any():
        return []
    if arr.all():
        return [(0, n)]
    edges = np.diff(np.concatenate([[0], arr.astype(np.int8), [0]]))
    starts = np.flatnonzero(edges == 1)
    stops = np.flatnonzero(edges == -1)
    runs = [(int(a), int(b)) for a, b in zip(starts, stops, strict=True)]
    if len(runs) > 1 and runs[0][0] == 0 and runs[-1][1] == n:
        head = runs.pop(0)
        start, _ = runs.pop()
        runs.append((start, n + head[1]))
    return sorted(runs)


@dataclass(frozen=True, eq=False)
class ContactResult:
    """What ``fix_sliding`` returns.

    Attributes:
        items: name -> ``(m + 1, 3)`` new root-relative positions: contact frames projected and rebuilt
            from ``lam``, the rest of each curve re-scaled so the joins stay continuous.
        root: ``(m + 1, 3)`` new world root positions; its in-plane part moves with velocity ``-lam``,
            its height above the plane is the input's.
        lam: ``(m + 1, 3)`` the shared root-relative contact velocity at each frame (in the plane).
        intervals: name -> contact intervals of that item, as ``contact_intervals`` reports them.
        scales: name -> the length factor ``s_l`` of each interval (1 where it is undefined).
        displacement: ``(3,)`` root travel per cycle, ``-integral of lam over the period``.
    """

    items: dict[str, FloatArray]
    root: FloatArray
    lam: FloatArray
    intervals: dict[str, list[tuple[int, int]]]
    scales: dict[str, list[float]] = field(default_factory=dict)
    displacement: FloatArray = field(default_factory=lambda: np.zeros(3))


class _PeriodicVelocity:
    """A periodic in-plane velocity curve ``lam(t)`` and its running integral ``int_0^t lam``."""

    def __init__(self, times: FloatArray, samples: FloatArray, period: float, smoothing: float) -> None:
        # samples: (k, 2) plane coordinates at the distinct times (0 <= times < period).
        self.period = period
        self._t0 = 0.0
        self._cycle = np.zeros(2)
        self._const: FloatArray | None = None
        self._tck: list[tuple[FloatArray, FloatArray, int]] = []
        self._anti: list[tuple[FloatArray, FloatArray, int]] = []
        if samples.shape[0] < 4:
            self._const = samples.mean(axis=0) if samples.shape[0] else np.zeros(2)
            return
        x = np.append(times, times[0] + period)
        rms = float(np.sqrt(np.mean(samples**2)))
        s = samples.shape[0] * (smoothing * rms) ** 2
        for c in range(samples.shape[1]):
            y = np.append(samples[:, c], samples[0, c])
            with warnings.catch_warnings():
                # FITPACK warns when a smoothing target is hard to meet; the spline it returns is
                # still periodic and usable.
                warnings.simplefilter("ignore", RuntimeWarning)
                tck = splrep(x, y, per=True, s=s)
            self._tck.append(tck)
            self._anti.append(splantider(tck))
        self._t0 = float(times[0])
        self._cycle = np.array([float(splev(self._t0 + period, a) - splev(self._t0, a)) for a in self._anti])

    def _wrap(self, t: FloatArray) -> tuple[FloatArray, FloatArray]:
        loops = np.floor((t - self._t0) / self.period)
        return t - loops * self.period, loops

    def value(self, t: FloatArray) -> FloatArray:
        """``(len(t), 2)`` velocity at times ``t`` (any real values)."""
        if self._const is not None:
            return np.broadcast_to(self._const, (t.size, 2)).copy()
        tt, _ = self._wrap(t)
        return np.column_stack([splev(tt, tck) for tck in self._tck])

    def _primitive(self, t: FloatArray) -> FloatArray:
        """A continuous antiderivative on the whole real line (it grows by one loop's integral per loop)."""
        tt, loops = self._wrap(t)
        return np.column_stack(
            [splev(tt, anti) + loops * cycle for anti, cycle in zip(self._anti, self._cycle, strict=True)]
        )

    def integral(self, t: FloatArray) -> FloatArray:
        """``(len(t), 2)`` integral of the velocity from 0 to each ``t`` (any real values)."""
        if self._const is not None:
            return np.outer(t, self._const)
        return np.asarray(self._primitive(t) - self._primitive(np.zeros(1)))


def _plane_basis(n: FloatArray) -> FloatArray:
    """``(2, 3)`` orthonormal in-plane axes for unit normal ``n``."""
    helper = np.eye(3)[int(np.argmin(np.abs(n)))]
    u = np.cross(n, helper)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(n, u)])


@dataclass(frozen=True)
class _ContactMap:
    """The affine map ``p -> centre + M (p - centre)`` that re-scales the flight next to one contact."""

    centre: FloatArray
    matrix: FloatArray
    first: int  # first contact frame (unwrapped)
    last: int  # last contact frame (unwrapped)

    def __call__(self, p: FloatArray) -> FloatArray:
        return np.asarray(self.centre + (p - self.centre) @ self.matrix.T)


def _rebuild_item(
    p: FloatArray,
    runs: list[tuple[int, int]],
    lam: _PeriodicVelocity,
    basis: FloatArray,
    n: FloatArray,
    dt: float,
) -> tuple[FloatArray, list[float]]:
    """Steps 3-4 of ``fix_sliding`` for one item: integrate ``lam`` over its contacts, re-scale its flights.

    Args:
        p: ``(m + 1, 3)`` closed root-relative positions, already projected at the contact frames.
        runs: the item's contact intervals (``contact_intervals``).
        lam: the shared contact velocity.
        basis: ``(2, 3)`` in-plane axes.
        n: unit plane normal.
        dt: frame duration.

    Returns:
        The rebuilt ``(m + 1, 3)`` positions and the length factor ``s_l`` of each interval.
    """
    m = p.shape[0] - 1
    out = p.copy()
    if not runs:
        return out, []

    def integral(t: FloatArray) -> FloatArray:
        return np.asarray(lam.integral(t) @ basis)

    maps: list[_ContactMap] = []
    scales: list[float] = []
    for start, stop in runs:
        frames = np.arange(start, stop)
        frame_t = np.arange(start, stop, dtype=np.float64) * dt
        lo, hi = start, stop - 1
        mid = 0.5 * (lo + hi)
        f = math.floor(mid)
        centre = (1.0 - (mid - f)) * p[f % m] + (mid - f) * p[(f + 1) % m]
        centre_tan = centre - (centre @ n) * n
        at_mid = integral(np.array([mid * dt]))
        # eq. 5.12 from the midpoint: in-plane part integrated, height kept (on the plane).
        rebuilt = centre_tan + (integral(frame_t) - at_mid) + np.outer(p[frames % m] @ n, n)
        out[frames % m] = rebuilt
        if stop - start >= m:  # in contact all around: the closing frame continues the integration
            out[m] = centre_tan + (integral(np.array([m * dt])) - at_mid)[0] + (p[0] @ n) * n
        # s_l: how much the contact's extent along d = mean lam direction changed.
        mean_lam = (lam.value(frame_t) @ basis).mean(axis=0)
        norm = float(np.linalg.norm(mean_lam))
        s_l, d = 1.0, np.zeros(3)
        if norm > 1e-12 and hi > lo:
            d = mean_lam / norm
            old = float(d @ (p[hi % m] - p[lo % m]))
            new = float(d @ (rebuilt[-1] - rebuilt[0]))
            if abs(old) > 1e-12 * max(1.0, float(np.max(np.abs(p)))) and new / old > 0:
                s_l = new / old
        scales.append(s_l)
        maps.append(_ContactMap(centre, np.eye(3) + (s_l - 1.0) * np.outer(d, d), lo, hi))

    if runs[0][1] - runs[0][0] >= m:
        return out, scales
    # Each flight joins the end of contact k to the start of contact k + 1 (the next loop's first one
    # after the last): blend the two maps linearly in time, then spread what is left of the gap at
    # either join linearly over the flight, so the curve meets the rebuilt contacts exactly.
    for k, here in enumerate(maps):
        there = maps[(k + 1) % len(maps)]
        join = there.first + (m if k + 1 == len(maps) else 0)
        gap = join - here.last
        if gap <= 1:
            continue
        flight = np.arange(here.last + 1, join)
        u = ((flight - here.last) / gap)[:, None]
        src = p[flight % m]
        moved = (1.0 - u) * here(src) + u * there(src)
        miss_here = out[here.last % m] - here(p[here.last % m])
        miss_there = out[join % m] - there(p[join % m])
        out[flight % m] = moved + (1.0 - u) * miss_here + u * miss_there
    out[m] = out[0]
    return out, scales


def fix_sliding(
    items: Mapping[str, FloatArray],
    root: FloatArray,
    period: float,
    point: Sequence[float] | FloatArray = (0.0, 0.0, 0.0),
    normal: Sequence[float] | FloatArray = (0.0, 1.0, 0.0),
    eps: float = 0.0,
    smoothing: float = 0.0,
    contacts: Mapping[str, BoolArray] | None = None,
) -> ContactResult:
    """Make items in contact with a plane stop sliding, and move the root so the character travels.

    Implements Ciccone 2019's contacts (section 5.4.3, eq. 5.12) on one cycle of ``m`` frames at times
    ``i * period / m``; steps 2 to 4 fill in what the thesis leaves open (``docs/design/cycles.md``):

    1. Each item's world position (root + root-relative) is projected onto the plane where it is within
       ``eps`` of it (``project_to_plane``), or at the frames ``contacts`` marks for it (the thesis's
       user-selected curve section); its contact intervals come from ``contact_intervals``.
    2. ``lam(t)``, the one root-relative velocity shared by all items in contact, is the mean of their
       in-plane root-relative velocities (periodic central differences) at each contact frame, fitted
       with a periodic spline (``splrep(per=True)``) so it is also defined in flight.
    3. Each contact interval is rebuilt by integrating ``lam`` from the interval's midpoint, which stays
       where it was: ``p(t) = p(t_mid) + int_{t_mid}^t lam``. Its height stays on the plane.
    4. The length of the contact along ``d`` (the normalised mean of ``lam`` over it) changes by
       ``s_l``; the non-contact frames are mapped with ``c + (I + (s_l - 1) d d^T)(p - c)`` about the
       contact midpoint ``c`` (blended linearly in time between the two contacts a flight joins), and any
       gap left at the joins is spread linearly over the flight, so the curve stays continuous.
    5. The root's in-plane position moves with velocity ``-lam`` from its position at frame 0 (its
       height is kept), so it travels ``-int_0^T lam`` per cycle and an item in contact has zero world
       velocity.

    With no contact at all, nothing changes (``lam`` is zero). An item in contact at every frame is
    rebuilt over the whole cycle and is closed only if ``lam`` integrates to zero.

    Args:
        items: name -> ``(m + 1, 3)`` closed root-relative positions (last row == first row).
        root: ``(m + 1, 3)`` world root positions at the same frames.
        period: the cycle duration ``T`` (seconds).
        point: a point on the contact plane.
        normal: the plane normal (up; any length).
        eps: contact tolerance: world points within ``eps`` of the plane (or below it) are in contact.
        smoothing: RMS deviation allowed between the ``lam`` spline and its samples, as a fraction of
            the samples' RMS; 0 interpolates them.
        contacts: optional name -> ``(m,)`` (or closed ``(m + 1,)``) booleans marking the frames where
            that item is in contact (from gait events or a selection); those items skip the ``eps``
            test and are projected onto the plane at exactly those frames.

    Returns:
        A ``ContactResult``.

    Raises:
        ValueError: no items, arrays not ``(m + 1, 3)`` and finite, shapes disagree, an item is not
            closed, ``m < 3``, ``contacts`` names an unknown item or has the wrong length, or
            ``period``, ``eps`` or ``smoothing`` are invalid.
    """
    if not items:
        raise ValueError("fix_sliding needs at least one item")
    base = finite_array(root, "root", (2,))
    if base.shape[1] != 3 or base.shape[0] < 4:
        raise ValueError(f"root must be (m + 1, 3) with m >= 3, got shape {base.shape}")
    m = base.shape[0] - 1
    rel: dict[str, FloatArray] = {}
    for name, arr in items.items():
        a = finite_array(arr, f"items[{name!r}]", (2,))
        if a.shape != base.shape:
            raise ValueError(f"items[{name!r}] has shape {a.shape}, root has {base.shape}")
        loop_frames(a, True, f"items[{name!r}]")
        rel[name] = a
    T = positive_finite(period, "period")
    sm = float(smoothing)
    if not (math.isfinite(sm) and sm >= 0):
        raise ValueError(f"smoothing must be non-negative and finite, got {smoothing!r}")
    p0 = finite_array(point, "point", (1,))
    if p0.shape != (3,):
        raise ValueError(f"point must have 3 components, got shape {p0.shape}")
    n = unit_vector(normal, "normal")
    e = float(eps)
    if not math.isfinite(e):
        raise ValueError("eps must be finite")
    given: dict[str, BoolArray] = {}
    for name, marks in (contacts or {}).items():
        if name not in rel:
            raise ValueError(f"contacts names {name!r}, which is not an item")
        mk = np.asarray(marks)
        if mk.dtype != np.bool_ or mk.shape not in ((m,), (m + 1,)):
            raise ValueError(f"contacts[{name!r}] must be {m} or {m + 1} booleans, got {mk.dtype} {mk.shape}")
        given[name] = mk[:m].copy()

    dt = T / m
    times = np.arange(m + 1) * dt
    basis = _plane_basis(n)  # rows u, v

    # 1. Contacts, in world space, on the distinct frames 0..m-1.
    projected: dict[str, FloatArray] = {}
    intervals: dict[str, list[tuple[int, int]]] = {}
    masks: dict[str, BoolArray] = {}
    for name, a in rel.items():
        world = base[:m] + a[:m]
        if name in given:
            mask = given[name]
            world[mask] -= np.outer((world[mask] - p0) @ n, n)
        else:
            world, mask = project_to_plane(world, p0, n, e)
        p = a.copy()  # frames out of contact keep their exact input values
        p[:m][mask] = world[mask] - base[:m][mask]
        p[m] = p[0]
        projected[name] = p
        masks[name] = mask
        intervals[name] = contact_intervals(mask)

    if not any(masks[k].any() for k in masks):
        return ContactResult(
            items={k: v.copy() for k, v in rel.items()},
            root=base.copy(),
            lam=np.zeros((m + 1, 3)),
            intervals=intervals,
            scales={k: [] for k in rel},
            displacement=np.zeros(3),
        )

    # 2. The shared contact velocity: mean in-plane root-relative velocity of the items in contact.
    total = np.zeros((m, 2))
    count = np.zeros(m)
    for name, p in projected.items():
        q = p[:m]
        vel = (np.roll(q, -1, axis=0) - np.roll(q, 1, axis=0)) / (2.0 * dt)
        mask = masks[name]
        total[mask] += vel[mask] @ basis.T
        count[mask] += 1
    have = count > 0
    lam_curve = _PeriodicVelocity(times[:m][have], total[have] / count[have, None], T, sm)

    # 3-4. Rebuild each item's contacts and re-scale its flights.
    out_items: dict[str, FloatArray] = {}
    scales: dict[str, list[float]] = {}
    for name, p in projected.items():
        out_items[name], scales[name] = _rebuild_item(p, intervals[name], lam_curve, basis, n, dt)

    # 5. The root travels against the contact velocity.
    heights = np.outer(base @ n, n)
    start_tan = base[0] - (base[0] @ n) * n
    new_root = heights + start_tan - lam_curve.integral(times) @ basis
    lam = lam_curve.value(times) @ basis
    lam[m] = lam[0]
    return ContactResult(
        items=out_items,
        root=new_root,
        lam=lam,
        intervals=intervals,
        scales=scales,
        displacement=-(lam_curve.integral(np.array([T])) @ basis)[0],
    )

