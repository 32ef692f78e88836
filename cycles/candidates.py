"""The descriptor space and the period candidates of cycle extraction (steps 2 and 3 of
:func:`cycles.extract`).

This module owns ``principal_subspace`` (wide inputs, hundreds or thousands of channels, projected on
their principal subspace by a randomised range finder, which keeps the distances the descriptor sees and
makes the cost independent of the channel count) and ``acf_candidates`` (the peaks of the summed
autocorrelation of the smoothed derivatives, blind to offsets and slow trends). Ciccone 2019, section 5.1,
sets frequency analysis aside because performed loops vary in duration; perfcap uses the autocorrelation
only as a prior for the descriptor matching of section 5.3, which decides (``docs/design/cycles.md``).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from scipy import signal

from cycles.descriptor import parabolic_offset

if TYPE_CHECKING:
    from cycles._types import FloatArray

__all__ = ["MIN_PROMINENCE", "acf_candidates", "principal_subspace"]

#: how far an autocorrelation peak must rise above the troughs on either side to be a candidate
MIN_PROMINENCE = 0.05


def principal_subspace(z: FloatArray, r: int, rng: np.random.Generator) -> FloatArray:
    """``z`` projected on (about) its top-``r`` principal subspace: same row distances up to the
    variance left out. A randomised range finder (Halko et al. 2011)."""
    d = z.shape[1]
    if d <= r:
        return z
    omega = rng.standard_normal((d, r + 8))
    q, _ = np.linalg.qr(z @ omega)
    b = q.T @ z
    ub, s, _ = np.linalg.svd(b, full_matrices=False)
    projected: FloatArray = (q @ ub[:, :r]) * s[:r]
    return projected


def acf_candidates(feat: FloatArray, lo: int, hi: int, limit: int) -> list[float]:
    """Lags (samples, sub-sample refined) of the highest peaks of the summed autocorrelation of
    ``feat``, in increasing lag order."""
    n = feat.shape[0]
    f = feat - feat.mean(axis=0)
    nfft = 1 << math.ceil(math.log2(2 * n))
    spec = np.fft.rfft(f, nfft, axis=0)
    ac = np.fft.irfft(np.sum(spec.real ** 2 + spec.imag ** 2, axis=1), nfft)[:n]
    if not ac[0] > 0:
        return []
    ac = ac / ac[0]
    # unbias the lag taper so that later repetitions are not handicapped against the first
    ac_u = ac * n / np.maximum(n - np.arange(n), 1)
    hi = min(hi, n - 2)
    if hi <= lo:
        return []
    seg = ac_u[lo - 1:hi + 2]
    # peaks that stand out from the curve around them: a wiggle of noise on the slope of the main lobe
    # (the autocorrelation falling from lag 0 at a high rate) is a local maximum but no repetition
    found, _ = signal.find_peaks(seg, height=0.05, prominence=MIN_PROMINENCE)
    pk = found[(found >= 1) & (found <= seg.size - 2)] - 1 + lo
    if pk.size == 0:
        return []
    # the earliest strong peaks (a long take has peaks at every multiple of the period, all about as
    # high), plus the highest one
    strong = pk[ac_u[pk] >= 0.5 * ac_u[pk].max()]
    top = np.union1d(strong[:limit], pk[np.argmax(ac_u[pk])])
    if top.size < limit:
        rest = np.setdiff1d(pk, top)
        top = np.union1d(top, rest[np.argsort(-ac_u[rest], kind="stable")][:limit - top.size])
    out = []
    for p in sorted(top.tolist()):
        out.append(p + parabolic_offset(-ac_u[p - 1], -ac_u[p], -ac_u[p + 1]))
    return out

