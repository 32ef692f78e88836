"""Verbs (Rose 1999, *Verbs and Adverbs: Multidimensional Motion Interpolation Using Radial Basis
Functions*, Princeton PhD thesis, chapter 4): example motions blended over adverb space.

This module owns ``Verb`` and what it is built from: ``Example`` (one example motion at its adverb point),
``CurveLayout`` (the uniform cubic B-spline every example is fitted with in canonical time, section 4.2),
``VerbFrame`` (a verb evaluated at some times) and the storage and cost counts of section 4.7
(``coefficients_per_frame``, ``example_storage``, ``mrbf_storage``). The interpolants a verb blends with
are :mod:`retarget.interpolation` (``RBF``, ``MultiResolutionRBF``); their clusterings are
:mod:`retarget.clustering`.

A ``Verb`` holds examples (a motion with its key-times at an adverb point p_i). Each is reoriented to start
at X = Z = 0 with heading 0 (Alg 3.1), resampled on canonical time and fitted with the same uniform cubic
B-spline layout per channel. Channels are per-joint rotation vectors relative to a per-joint reference
rotation (hemisphere-consistent), the root translation minus its per-motion displacement trend, and the
heading minus its net-turn trend; the displacement, the net turn and the key-times are interpolated too.
At any p the blended key-times (guarded: strictly increasing) restore the timing, and the blended channels
are mapped back to unit quaternions. Evaluation is vectorised: a new p costs its basis row and a small
product for the key-times and root trend; a pose then blends only the four active control points per
channel (``Verb.pose``, the per-frame path for playback at a phase advancing by dt / ``Verb.duration(p)``).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, Protocol, overload

import numpy as np
from scipy import linalg

from capture.quat import (
    quat_conj,
    quat_exp,
    quat_log,
    quat_mul,
    quat_normalize,
    quat_slerp,
)
from retarget.interpolation import RBF, MultiResolutionRBF
from retarget.timeline import check_key_times, reorient, split_heading, verb_time

if TYPE_CHECKING:
    from collections.abc import Sequence

    from retarget._types import FloatArray, IntArray

__all__ = [
    "ClipSource",
    "CurveLayout",
    "Example",
    "Verb",
    "VerbFrame",
    "coefficients_per_frame",
    "example_storage",
    "mrbf_storage",
]


# --------------------------------------------------------------------------------------------------
# Storage and cost counts (Rose 1999, section 4.7, "Efficiency concerns")


def coefficients_per_frame(num_dofs: int, num_key_times: int) -> int:
    """Coefficients blended per frame: 4 active cubic control points per DOF plus the key-times.

    Args:
        num_dofs: NumDOF.
        num_key_times: NumKeyTimes.

    Returns:
        4 NumDOF + NumKeyTimes (walk: 4 x 44 + 4 = 180).
    """
    return 4 * num_dofs + num_key_times


def example_storage(num_dofs: int, num_cp: int, num_examples: int) -> int:
    """Coefficients stored by the raw examples: NumDOF x NumCP x n (walk: 44 x 32 x 20 = 28 160).

    Args:
        num_dofs: NumDOF.
        num_cp: control points per DOF.
        num_examples: n.

    Returns:
        The count.
    """
    return num_dofs * num_cp * num_examples


def mrbf_storage(num_dofs: int, num_cp: int, num_key_times: int, num_examples: int, num_adverbs: int) -> int:
    """Coefficients stored by a multiresolution verb with halving levels.

    (NumKeyTimes + NumCP NumDOF) spaces, each with (D + 1) linear and at most 2n radial coefficients
    (walk: 1412 x 45 = 63 540, 2.26x the examples).

    Args:
        num_dofs: NumDOF.
        num_cp: control points per DOF.
        num_key_times: NumKeyTimes.
        num_examples: n.
        num_adverbs: D.

    Returns:
        The count.
    """
    return (num_key_times + num_cp * num_dofs) * ((num_adverbs + 1) + 2 * num_examples)


# --------------------------------------------------------------------------------------------------
# Curve layout in canonical time


_B = np.array(
    [
        [-1.0, 3.0, -3.0, 1.0],
        [3.0, -6.0, 0.0, 4.0],
        [-3.0, 3.0, 3.0, 1.0],
        [1.0, 0.0, 0.0, 0.0],
    ]
) / 6.0  # row i: coefficients of f^3, f^2, f, 1 of the i-th uniform cubic B-spline piece


class CurveLayout:
    """A uniform cubic B-spline in canonical time with ``num_cp`` control points per channel.

    Non-periodic: t in [0, 1] spans num_cp - 3 segments (t clamped). Periodic: t wraps modulo 1 over
    num_cp segments, so the curve is C2 across the seam.

    Args:
        num_cp: control points per channel (>= 4).
        periodic: wrap canonical time.

    Raises:
        ValueError: num_cp < 4.
    """

    def __init__(self, num_cp: int, periodic: bool) -> None:
        if num_cp < 4:
            raise ValueError(f"need at least 4 control points, got {num_cp}")
        self.num_cp = int(num_cp)
        self.periodic = bool(periodic)
        self.segments = self.num_cp if periodic else self.num_cp - 3

    def span(self, t: FloatArray) -> tuple[IntArray, FloatArray, FloatArray]:
        """Active control points, weights and d(weights)/dt at canonical times.

        Args:
            t: (...,) canonical times.

        Returns:
            (idx (..., 4) int, w (..., 4), dw (..., 4)).
        """
        ta = np.asarray(t, dtype=float)
        ta = np.mod(ta, 1.0) if self.periodic else np.clip(ta, 0.0, 1.0)
        u = ta * self.segments
        i = np.minimum(np.floor(u), self.segments - 1)
        f = (u - i)[..., None]
        i = i.astype(int)
        idx = i[..., None] + np.arange(4)
        if self.periodic:
            idx %= self.num_cp
        powers = np.concatenate([f**3, f**2, f, np.ones_like(f)], axis=-1)
        dpowers = np.concatenate([3.0 * f**2, 2.0 * f, np.ones_like(f), np.zeros_like(f)], axis=-1)
        return idx, powers @ _B.T, (dpowers @ _B.T) * self.segments

    def design(self, t: FloatArray) -> FloatArray:
        """Design matrix: row s holds the weight of each control point at t_s.

        Args:
            t: (S,) canonical times.

        Returns:
            (S, num_cp).
        """
        idx, w, _ = self.span(np.asarray(t, dtype=float))
        out = np.zeros((idx.shape[0], self.num_cp))
        np.add.at(out, (np.arange(idx.shape[0])[:, None], idx), w)
        return out


# --------------------------------------------------------------------------------------------------
# Examples and verbs


def _resample(times: FloatArray, root_pos: FloatArray, rotations: FloatArray,
              T: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Linear root and slerped rotations at times T (clamped)."""
    Tc = np.clip(T, times[0], times[-1])
    i = np.clip(np.searchsorted(times, Tc, side="right") - 1, 0, times.size - 2)
    f = (Tc - times[i]) / (times[i + 1] - times[i])
    pos = (1.0 - f)[:, None] * root_pos[i] + f[:, None] * root_pos[i + 1]
    rot = quat_slerp(rotations[i], rotations[i + 1], np.repeat(f[:, None], rotations.shape[1], axis=1))
    return pos, rot


class ClipSource(Protocol):
    """What ``Example.from_clip`` reads from a clip (``retarget.skeleton.Clip`` is one); a ``name``
    attribute, if it has one, labels the example."""

    @property
    def duration(self) -> float:
        """Seconds from the first frame to the last."""
        ...

    @property
    def fps(self) -> float:
        """Frames per second: ``from_clip`` samples one example sample per frame by default."""
        ...

    @property
    def key_times(self) -> Sequence[float]:
        """Increasing key-times from 0 to the duration."""
        ...

    def sample(self, t: float | FloatArray) -> tuple[FloatArray, FloatArray]:
        """Root position ``(..., 3)`` and local joint rotations ``(..., J, 4)`` at time(s) ``t``."""
        ...


@dataclass(frozen=True)
class Example:
    """One example motion of a verb.

    Attributes:
        point: (D,) its location in adverb space.
        times: (F,) increasing sample times in seconds, from 0.
        root_pos: (F, 3) root position (m).
        rotations: (F, J, 4) local joint rotations, (w, x, y, z); joint 0 is the root (world).
        key_times: (N,) key-times, 0 .. duration (the last sample time or earlier).
        name: label for messages.
    """

    point: FloatArray
    times: FloatArray
    root_pos: FloatArray
    rotations: FloatArray
    key_times: FloatArray
    name: str = ""

    def __post_init__(self) -> None:
        """Validate shapes.

        Raises:
            ValueError: inconsistent shapes, times, or key-times.
        """
        object.__setattr__(self, "point", np.atleast_1d(np.asarray(self.point, dtype=float)))
        tm = np.asarray(self.times, dtype=float)
        pos = np.asarray(self.root_pos, dtype=float)
        rot = np.asarray(self.rotations, dtype=float)
        k = check_key_times(self.key_times)
        if tm.ndim != 1 or tm.size < 2 or tm[0] != 0.0 or np.any(np.diff(tm) <= 0.0):
            raise ValueError(f"example {self.name!r}: times must increase strictly from 0")
        if pos.shape != (tm.size, 3) or rot.ndim != 3 or rot.shape[0] != tm.size or rot.shape[2] != 4:
            raise ValueError(f"example {self.name!r}: root_pos (F, 3) and rotations (F, J, 4) needed")
        if k[-1] > tm[-1] + 1e-9:
            raise ValueError(f"example {self.name!r}: last key-time {k[-1]} is past the last sample {tm[-1]}")
        object.__setattr__(self, "times", tm)
        object.__setattr__(self, "root_pos", pos)
        object.__setattr__(self, "rotations", quat_normalize(rot))
        object.__setattr__(self, "key_times", k)

    @classmethod
    def from_clip(cls, clip: ClipSource, point: Sequence[float] | FloatArray | float, *,
                  samples: int | None = None) -> Example:
        """An example from a clip: a ``retarget.skeleton.Clip`` or anything else that is a ``ClipSource``.

        The clip is sampled through ``clip.sample(T)`` on a uniform grid over [0, duration].

        Args:
            clip: the clip.
            point: its adverb point.
            samples: grid size; None uses one sample per frame (at least 2).

        Returns:
            The example.

        Raises:
            ValueError: clip key-times invalid.
        """
        dur = float(clip.duration)
        n = samples if samples is not None else max(2, round(dur * float(clip.fps)) + 1)
        T = np.linspace(0.0, dur, n)
        pos, rot = clip.sample(T)
        pos = np.asarray(pos, dtype=float)
        rot = np.asarray(rot, dtype=float)
        if pos.shape != (n, 3):
            per = [clip.sample(float(x)) for x in T]
            pos = np.stack([np.asarray(a, dtype=float) for a, _ in per])
            rot = np.stack([np.asarray(b, dtype=float) for _, b in per])
        k = np.asarray(clip.key_times, dtype=float)
        k[-1] = min(k[-1], dur)
        return cls(point=np.atleast_1d(np.asarray(point, dtype=float)), times=T, root_pos=pos, rotations=rot,
                   key_times=k, name=str(getattr(clip, "name", "")))


@dataclass(frozen=True)
class VerbFrame:
    """A verb evaluated at some times (leading axes follow the query).

    Attributes:
        root_pos: (..., 3) root position in the verb's start frame (X = Z = 0, heading 0 at t = 0; Y is
            the height).
        heading: (...,) root heading in the start frame.
        root_velocity: (..., 3) d root_pos / dT in the start frame, m/s of verb time.
        heading_rate: (...,) d heading / dT.
        rotations: (..., J, 4) local rotations; joint 0 is the root tilt (its rotation with the heading
            removed): the root's world rotation is yaw_quat(heading) * rotations[..., 0, :].
        t: (...,) canonical time.
    """

    root_pos: FloatArray
    heading: FloatArray
    root_velocity: FloatArray
    heading_rate: FloatArray
    rotations: FloatArray
    t: FloatArray


class _Blend:
    """Adverb weights at one p and the small blended quantities; the full control points on demand."""

    __slots__ = ("_coef_t", "_cp", "disp", "key_list", "key_times", "turn", "weights")

    def __init__(self, weights: FloatArray, small: FloatArray, coef_t: FloatArray) -> None:
        self.weights = weights
        self.disp = small[:3]
        self.turn = float(small[3])
        k = small[4:].copy()
        k[0] = 0.0
        self.key_times = k
        self.key_list: list[float] = k.tolist()
        self._coef_t = coef_t
        self._cp: FloatArray | None = None

    @property
    def cp(self) -> FloatArray:
        """(rows, C) blended control points (periodic layouts repeat the first 3 rows at the end)."""
        if self._cp is None:
            self._cp = self._coef_t @ self.weights
        return self._cp


class Verb:
    """A parametrised motion blended from examples over adverb space.

    Args:
        examples: at least D + 1 examples with the same joint count and number of key-times.
        num_cp: B-spline control points per channel in canonical time.
        periodic: the motion is a cycle (canonical time wraps; curves are periodic).
        interpolant: "rbf" (single level) or "mrbf" (multiresolution).
        samples: canonical samples per example for the curve fit; None = max(8 num_cp, 64).
        seed: seed of the MRBF clustering.
        name: the verb's name.

    Raises:
        ValueError: too few examples, mixed dimensions or skeletons, different key-time counts,
            coincident adverb points, or an unknown interpolant.
    """

    def __init__(
        self,
        examples: Sequence[Example],
        *,
        num_cp: int = 24,
        periodic: bool = False,
        interpolant: str = "rbf",
        samples: int | None = None,
        seed: int = 0,
        name: str = "verb",
    ) -> None:
        if not examples:
            raise ValueError("a verb needs examples")
        dim = examples[0].point.size
        if any(e.point.size != dim for e in examples):
            raise ValueError("all examples need adverb points of the same dimension")
        if len(examples) < dim + 1:
            raise ValueError(f"a verb with {dim} adverbs needs at least {dim + 1} examples, got {len(examples)}")
        nj = examples[0].rotations.shape[1]
        nk = examples[0].key_times.size
        if any(e.rotations.shape[1] != nj for e in examples):
            raise ValueError("all examples need the same skeleton (joint count)")
        if any(e.key_times.size != nk for e in examples):
            raise ValueError("all examples need the same key-time sequence (count)")
        if interpolant not in ("rbf", "mrbf"):
            raise ValueError(f"interpolant must be 'rbf' or 'mrbf', got {interpolant!r}")
        self.name = name
        self.dim = int(dim)
        self.num_joints = int(nj)
        self.num_key_times = int(nk)
        self.periodic = bool(periodic)
        self.layout = CurveLayout(num_cp, periodic)
        self.examples = tuple(examples)
        self.points = np.stack([e.point for e in examples])
        s = max(8 * num_cp, 64) if samples is None else int(samples)
        ts = np.linspace(0.0, 1.0, s)

        # resample every example on canonical time; reorient (Alg 3.1); split heading from the root
        pos_all, head_all, rot_all = [], [], []
        for e in examples:
            pos, rot = _resample(e.times, e.root_pos, e.rotations, np.asarray(verb_time(ts, e.key_times)))
            h, tilt = split_heading(rot[:, 0])
            h = np.unwrap(h)
            if periodic and abs(h[-1] - h[0]) < 1e-3:
                # a cycle that does not turn: its frame is the mean heading (the way it travels), not
                # the first frame's, where the pelvis may be turned a few degrees mid-sway; otherwise
                # the whole cycle is reoriented off its path and the feet slide sideways when it is
                # played along a straight line
                h_mean, h0 = float(np.mean(h)), float(h[0])
                pos, h = reorient(pos, h - h0 + h_mean)     # rotated by -h_mean about the start
                h = h + h0 - h_mean                         # headings relative to the mean
            else:
                pos, h = reorient(pos, h)
            rot = rot.copy()
            rot[:, 0] = tilt
            pos_all.append(pos)
            head_all.append(h)
            rot_all.append(rot)
        rots = np.stack(rot_all)  # (n, S, J, 4)
        self.reference = self._references(rots)
        rel = quat_mul(quat_conj(self.reference)[None, None], rots)
        rv = self._unwrap(quat_log(rel)).reshape(len(examples), s, 3 * nj)
        disp = np.stack([p[-1] - p[0] for p in pos_all])  # (n, 3); start X = Z = 0
        disp[:, 1] = 0.0  # the height is absolute, only X and Z carry a trend
        turn = np.array([h[-1] - h[0] for h in head_all])
        res = np.stack([p - ts[:, None] * d for p, d in zip(pos_all, disp, strict=True)])
        hres = np.stack([h - ts * w for h, w in zip(head_all, turn, strict=True)])[..., None]
        channels = np.concatenate([rv, res, hres], axis=2)  # (n, S, C)
        self.num_channels = channels.shape[2]
        design = self.layout.design(ts)
        stacked = channels.transpose(1, 0, 2).reshape(s, -1)
        cps, *_ = linalg.lstsq(design, stacked, lapack_driver="gelsd")
        cps = np.asarray(cps).reshape(num_cp, len(examples), self.num_channels).transpose(1, 0, 2)
        self._fit_rms = float(np.sqrt(np.mean((np.einsum("sm,nmc->nsc", design, cps) - channels) ** 2)))
        keys = np.stack([e.key_times for e in examples])
        values = np.hstack([cps.reshape(len(examples), -1), disp, turn[:, None], keys])
        self.interpolant: RBF | MultiResolutionRBF = (
            RBF(self.points, values) if interpolant == "rbf" else MultiResolutionRBF(self.points, values, seed=seed)
        )
        coef = self.interpolant.coefficients  # (K, M C + 4 + N)
        ncp = num_cp * self.num_channels
        curves = coef[:, :ncp].reshape(-1, num_cp, self.num_channels)
        if periodic:  # repeat the first rows so that any 4 consecutive control points are a slice
            curves = np.concatenate([curves, curves[:, :3]], axis=1)
        self._coef_t = np.ascontiguousarray(curves.transpose(1, 2, 0))  # (rows, C, K)
        self._coef_small = np.ascontiguousarray(coef[:, ncp:].T)  # (4 + N, K)
        self._ref_left = self._left_matrices(self.reference)  # q = ref * e as a (J, 4, 4) matrix times e
        self._tgrid = np.linspace(0.0, 1.0, nk)  # canonical times of the key-times
        self._cache_key: bytes | None = None
        self._cache: _Blend | None = None

    @staticmethod
    def _left_matrices(q: FloatArray) -> FloatArray:
        w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
        return np.stack(
            [
                np.stack([w, -x, -y, -z], axis=-1),
                np.stack([x, w, -z, y], axis=-1),
                np.stack([y, z, w, -x], axis=-1),
                np.stack([z, -y, x, w], axis=-1),
            ],
            axis=1,
        )

    @staticmethod
    def _unwrap(rv: FloatArray) -> FloatArray:
        """Keep rotation-vector curves continuous in time where a joint passes pi from its reference.

        The hemisphere-consistent rotation vector jumps there (axis flip); v - 2 pi v/|v| or v + 2 pi v/|v|
        is the same rotation, and whichever is nearest the previous sample is kept. Joints that stay within
        pi of the reference are untouched.

        Args:
            rv: (n, S, J, 3) rotation vectors.

        Returns:
            (n, S, J, 3).
        """
        ang = np.linalg.norm(rv, axis=-1)
        if ang.max(initial=0.0) < 0.75 * np.pi:
            return rv
        out = rv.copy()
        for s in range(1, rv.shape[1]):
            prev = out[:, s - 1]
            cur = rv[:, s]
            a = np.linalg.norm(cur, axis=-1, keepdims=True)
            unit = cur / np.where(a > 1e-12, a, 1.0)
            best = cur
            best_d = np.linalg.norm(cur - prev, axis=-1)
            for k in (-2, -1, 1, 2):
                alt = cur + (2.0 * np.pi * k) * unit
                d = np.linalg.norm(alt - prev, axis=-1)
                take = d < best_d - 1e-12
                best = np.where(take[..., None], alt, best)
                best_d = np.minimum(d, best_d)
            out[:, s] = best
        return out

    @staticmethod
    def _references(rots: FloatArray) -> FloatArray:
        """Per-joint reference: hemisphere-aligned chordal mean of every sample of every example."""
        flat = rots.reshape(-1, rots.shape[2], 4)  # (n S, J, 4)
        first = flat[0]
        sign = np.where(np.sum(flat * first[None], axis=-1, keepdims=True) < 0.0, -1.0, 1.0)
        mean = (flat * sign).sum(axis=0)
        norm = np.linalg.norm(mean, axis=-1, keepdims=True)
        ref: FloatArray = np.where(norm > 1e-9, mean / np.maximum(norm, 1e-300), first)
        return ref

    # -- blending -------------------------------------------------------------------------------

    def _blend(self, p: FloatArray | Sequence[float] | float) -> _Blend:
        pa = np.asarray(p, dtype=float)
        if pa.shape != (self.dim,):
            pa = np.atleast_1d(pa)
            if pa.shape != (self.dim,):
                raise ValueError(f"verb {self.name!r} has {self.dim} adverbs, got p of shape {pa.shape}")
        key = pa.tobytes()
        if key == self._cache_key and self._cache is not None:
            return self._cache
        if not np.isfinite(pa).all():
            raise ValueError("adverbs must be finite")
        w = self.interpolant.basis_one(pa)
        blend = _Blend(w, self._coef_small @ w, self._coef_t)
        k = blend.key_list
        if any(b <= a for a, b in itertools.pairwise(k)):
            raise ValueError(
                f"verb {self.name!r}: interpolated key-times {k} at p = {pa.tolist()} are not strictly "
                "increasing (p is too far outside the examples)"
            )
        self._cache_key, self._cache = key, blend
        return blend

    def key_times(self, p: FloatArray | Sequence[float] | float) -> FloatArray:
        """Interpolated key-times at p (the guard: strictly increasing).

        Args:
            p: adverbs (D,).

        Returns:
            (N,) key-times, first 0.

        Raises:
            ValueError: wrong p, or key-times not strictly increasing at p.
        """
        return self._blend(p).key_times.copy()

    def duration(self, p: FloatArray | Sequence[float] | float) -> float:
        """Interpolated duration T^d(p) (the last key-time; a cycle's period for periodic verbs).

        Args:
            p: adverbs.

        Returns:
            Seconds.

        Raises:
            ValueError: wrong p or bad key-times.
        """
        return float(self._blend(p).key_times[-1])

    def displacement(self, p: FloatArray | Sequence[float] | float) -> FloatArray:
        """Root displacement over the whole motion (one cycle), in the start frame (Y = 0).

        Args:
            p: adverbs.

        Returns:
            (3,) metres.

        Raises:
            ValueError: wrong p or bad key-times.
        """
        return self._blend(p).disp.copy()

    def net_turn(self, p: FloatArray | Sequence[float] | float) -> float:
        """Heading change over the whole motion.

        Args:
            p: adverbs.

        Returns:
            Radians.

        Raises:
            ValueError: wrong p or bad key-times.
        """
        return self._blend(p).turn

    def root_speed(self, p: FloatArray | Sequence[float] | float) -> float:
        """Mean horizontal root speed: |displacement_xz| / duration.

        Args:
            p: adverbs.

        Returns:
            m/s.

        Raises:
            ValueError: wrong p or bad key-times.
        """
        b = self._blend(p)
        return float(math.hypot(b.disp[0], b.disp[2]) / b.key_times[-1])

    def canonical_time(self, p: FloatArray | Sequence[float] | float, T: float | FloatArray) -> float | FloatArray:
        """t(T) under the key-times at p.

        Args:
            p: adverbs.
            T: verb time(s), clamped to [0, T^d(p)].

        Returns:
            Canonical time(s).

        Raises:
            ValueError: wrong p or bad key-times.
        """
        k = self._blend(p).key_times
        out = np.interp(T, k, self._tgrid)
        return float(out) if np.ndim(T) == 0 else out

    def verb_time(self, p: FloatArray | Sequence[float] | float, t: float | FloatArray) -> float | FloatArray:
        """T(t) under the key-times at p.

        Args:
            p: adverbs.
            t: canonical time(s), clamped to [0, 1].

        Returns:
            Verb time(s).

        Raises:
            ValueError: wrong p or bad key-times.
        """
        k = self._blend(p).key_times
        out = np.interp(t, self._tgrid, k)
        return float(out) if np.ndim(t) == 0 else out

    def _canonical_rate(self, k: FloatArray, t: FloatArray) -> FloatArray:
        """dt/dT, canonical time per second of verb time, at canonical times ``t`` under key-times ``k``."""
        n = k.size - 1
        tc = np.mod(t, 1.0) if self.periodic else np.clip(t, 0.0, 1.0)
        m = np.minimum(np.floor(tc * n).astype(int), n - 1)
        rate: FloatArray = 1.0 / (n * (k[m + 1] - k[m]))
        return rate

    @overload
    def pose(self, p: FloatArray | Sequence[float] | float, t: float, *, with_position: Literal[False] = False
             ) -> tuple[FloatArray, FloatArray]: ...

    @overload
    def pose(self, p: FloatArray | Sequence[float] | float, t: float, *, with_position: Literal[True]
             ) -> tuple[FloatArray, FloatArray, FloatArray]: ...

    def pose(self, p: FloatArray | Sequence[float] | float, t: float, *, with_position: bool = False
             ) -> tuple[FloatArray, FloatArray] | tuple[FloatArray, FloatArray, FloatArray]:
        """The fast path for playback: root velocity and joint rotations at one canonical time.

        The root velocity and the root rotation are relative to the trend frame (the start frame turned
        by net_turn(p) t, which is the start frame itself for motions that do not turn), so a caller that
        owns the heading H places the root at yaw_quat(H) * rotations[0] and moves it by
        R_y(H) root_velocity.

        Args:
            p: adverbs (D,).
            t: canonical time (wraps for periodic verbs, clamped otherwise).

        Returns:
            (root_velocity (3,) m/s, rotations (J, 4) unit quaternions (w, x, y, z)); with
            ``with_position`` also the root position (3,) in the start frame (as ``sample`` gives it; its
            Y is the root height) first.

        Raises:
            ValueError: wrong p, or key-times not strictly increasing at p.
        """
        b = self._blend(p)
        tt = float(t)
        tt = tt % 1.0 if self.periodic else min(max(tt, 0.0), 1.0)
        seg = self.layout.segments
        u = tt * seg
        i = min(int(u), seg - 1)
        f = u - i
        f2, f3, g = f * f, f * f * f, 1.0 - f
        wd = np.array(
            [
                [g * g * g / 6.0, (3.0 * f3 - 6.0 * f2 + 4.0) / 6.0,
                 (-3.0 * f3 + 3.0 * f2 + 3.0 * f + 1.0) / 6.0, f3 / 6.0],
                [-0.5 * g * g * seg, (1.5 * f2 - 2.0 * f) * seg, (-1.5 * f2 + f + 0.5) * seg, 0.5 * f2 * seg],
            ]
        )
        vd = wd @ (self._coef_t[i : i + 4] @ b.weights)  # (2, C): values and d/dt
        nj = self.num_joints
        v = vd[0, : 3 * nj].reshape(nj, 3)
        ang = np.sqrt(np.einsum("ij,ij->i", v, v))
        e = np.empty((nj, 4))
        e[:, 0] = np.cos(0.5 * ang)
        e[:, 1:] = v * (0.5 * np.sinc(ang * (0.5 / math.pi)))[:, None]  # sin(|v|/2) / |v|
        rot = np.matmul(self._ref_left, e[:, :, None])[:, :, 0]
        hres = float(vd[0, 3 * nj + 3])
        c, s = math.cos(0.5 * hres), math.sin(0.5 * hres)
        w0, x0, y0, z0 = rot[0].tolist()
        rot[0] = (c * w0 - s * y0, c * x0 + s * z0, c * y0 + s * w0, c * z0 - s * x0)
        kl = b.key_list
        n = len(kl) - 1
        m = min(int(tt * n), n - 1)
        scale = 1.0 / (n * (kl[m + 1] - kl[m]))
        vx, vy, vz = ((b.disp + vd[1, 3 * nj : 3 * nj + 3]) * scale).tolist()
        if b.turn != 0.0:
            a = -b.turn * tt
            ca, sa = math.cos(a), math.sin(a)
            vx, vz = ca * vx + sa * vz, -sa * vx + ca * vz
        if with_position:
            return vd[0, 3 * nj : 3 * nj + 3] + tt * b.disp, np.array([vx, vy, vz]), rot
        return np.array([vx, vy, vz]), rot

    def sample(self, p: FloatArray | Sequence[float] | float, t: float | FloatArray) -> VerbFrame:
        """Everything at canonical time(s) t, in the start frame (t wraps for periodic verbs, without
        accumulating cycles; use ``at_time`` for that).

        Args:
            p: adverbs (D,).
            t: canonical time(s).

        Returns:
            A ``VerbFrame`` with leading axes of ``t``.

        Raises:
            ValueError: wrong p or bad key-times.
        """
        b = self._blend(p)
        ta = np.asarray(t, dtype=float)
        tw = np.mod(ta, 1.0) if self.periodic else np.clip(ta, 0.0, 1.0)
        idx, w, dw = self.layout.span(tw)
        rows = b.cp[idx]  # (..., 4, C)
        vals = np.einsum("...i,...ic->...c", w, rows)
        dvals = np.einsum("...i,...ic->...c", dw, rows)
        nj3 = 3 * self.num_joints
        rot = quat_mul(self.reference, quat_exp(vals[..., :nj3].reshape((*ta.shape, self.num_joints, 3))))
        scale = self._canonical_rate(b.key_times, tw)[..., None]
        pos = vals[..., nj3 : nj3 + 3] + tw[..., None] * b.disp
        vel = (dvals[..., nj3 : nj3 + 3] + b.disp) * scale
        heading = vals[..., nj3 + 3] + tw * b.turn
        rate = (dvals[..., nj3 + 3] + b.turn) * scale[..., 0]
        return VerbFrame(root_pos=pos, heading=heading, root_velocity=vel, heading_rate=rate, rotations=rot, t=tw)

    def at_time(self, p: FloatArray | Sequence[float] | float, T: float | FloatArray) -> VerbFrame:
        """Everything at verb time(s) T under p. Periodic verbs play on past T^d (and before 0), the root
        carrying the displacement and turn of each completed cycle; other verbs clamp T to [0, T^d].

        Args:
            p: adverbs (D,).
            T: verb time(s), seconds.

        Returns:
            A ``VerbFrame`` in the start frame.

        Raises:
            ValueError: wrong p or bad key-times.
        """
        b = self._blend(p)
        k = b.key_times
        d = float(k[-1])
        Ta = np.asarray(T, dtype=float)
        if not self.periodic:
            t = np.interp(np.clip(Ta, 0.0, d), k, self._tgrid)
            return self.sample(p, t)
        cycles = np.floor(Ta / d)
        frac = Ta - cycles * d
        t = np.interp(frac, k, self._tgrid)
        fr = self.sample(p, t)
        # after n cycles the frame has moved by sum_{k<n} R_y(k turn) disp and turned by n turn;
        # with w = Z + iX a heading a multiplies by e^{ia}
        disp_c = b.disp[2] + 1j * b.disp[0]
        rot_n = np.exp(1j * b.turn * cycles)
        step = np.exp(1j * b.turn)
        geo = np.where(abs(b.turn) < 1e-12, cycles, (1.0 - rot_n) / np.where(abs(b.turn) < 1e-12, 1.0, 1.0 - step))
        off = disp_c * geo
        local = fr.root_pos[..., 2] + 1j * fr.root_pos[..., 0]
        world = off + rot_n * local
        vloc = fr.root_velocity[..., 2] + 1j * fr.root_velocity[..., 0]
        vworld = rot_n * vloc
        pos = np.stack([world.imag, fr.root_pos[..., 1], world.real], axis=-1)
        vel = np.stack([vworld.imag, fr.root_velocity[..., 1], vworld.real], axis=-1)
        return VerbFrame(
            root_pos=pos,
            heading=fr.heading + cycles * b.turn,
            root_velocity=vel,
            heading_rate=fr.heading_rate,
            rotations=fr.rotations,
            t=fr.t,
        )

    # -- bookkeeping ----------------------------------------------------------------------------

    @property
    def fit_rms(self) -> float:
        """RMS error of the per-example B-spline fit over all channels (radians / metres)."""
        return self._fit_rms

    @property
    def coefficients_per_frame(self) -> int:
        """Coefficients one pose blends: 4 per channel plus the key-times (and 4 root-trend scalars)."""
        return coefficients_per_frame(self.num_channels, self.num_key_times) + 4

    @property
    def storage(self) -> int:
        """Coefficients the interpolant stores."""
        return int(self.interpolant.coefficients.size)

    def root_heading(self, p: FloatArray | Sequence[float] | float, t: float) -> float:
        """Root heading in the start frame at canonical time t (within one cycle).

        Args:
            p: adverbs.
            t: canonical time.

        Returns:
            Radians.

        Raises:
            ValueError: wrong p or bad key-times.
        """
        return float(self.sample(p, t).heading)
