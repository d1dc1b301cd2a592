"""Tree dedispersion (the fast dispersion measure transform, FDMT; Zackay & Ofek 2017) of image series.

Why: incoherent dedispersion by shifted sums costs ``ntrial x nchan`` adds per pixel and image. At the
whole band's cadence (784 channels of LWA-SV, 0.64-ms images, DM 0-3: a sweep of ~1,875 images, so
~1,876 trials one image apart) that is ~1.5e6 adds per pixel-image; the tree needs ~``ntrial x
log2(nchan)`` (~2e4; 17,090 rows of shifted adds against 1,470,000 for 784 channels and sweeps
0-1,875). This module is the transform only (array code, NumPy or CuPy; one gather-add per merge).
:mod:`.transient`'s streaming search still dedisperses by shifted sums per (DM, channel); running it
on this transform, over pixel chunks, is what the whole band needs next.

Definitions (images, channels sorted by frequency; f in any unit)
-------------------------------------------------------------------
For a range R of channels a..b (a the lowest frequency) and a sweep d (images between the arrival at
f_b and at f_a), channel c of R is read ``back_R(d, c)`` images before the range's newest time:

    A_R[d, t] = sum_{c in R} I_c(t - back_R(d, c)),   back_R(d, a) = 0,  back_R(d, b) = d.

A single channel has d = 0 only. Two ranges L = a..m-1 and U = m..b merge as

    A_R[d, t] = A_L[d_L, t] + A_U[d_U, t - o],
    d_L = rint(d * (f_a^-2 - f_{m-1}^-2) / (f_a^-2 - f_b^-2)),
    o   = rint(d * (f_a^-2 - f_m^-2)     / (f_a^-2 - f_b^-2)),   d_U = d - o,

so every trial's highest channel sits exactly d images back and the others within a rounding or two
of the dispersion curve, whose delay ~f^-2: measured, at most 1 image off ``rint(d (f_a^-2 -
f_c^-2) / (f_a^-2 - f_b^-2))`` for 40 channels and at most 2 (mean 0.35) for 784 channels and
sweeps to 1,875 (:func:`effective_back` gives each channel's read offset exactly). Ranges are split in halves; the plan (which d each
range must provide) is made top-down from the trials asked for.

Cost and memory: one shifted add per (range, d) of its level, ``sum_levels sum_R (dmax_R + 1)``
rows of ``T x npix`` (~ntrial x log2(nchan) rows); the largest array is the last level's
``(ntrial, T, npix)``, so callers bound memory by passing pixels in chunks.
"""
from __future__ import annotations

import numpy as np

from ._xp import get_xp

__all__ = ["FDMTPlan", "fdmt", "effective_back"]


class FDMTPlan:
    """The merge tables for channels at ``freq`` (any order; any unit) and sweeps ``0 .. dmax`` images
    across the band (every integer; the trials are rows of the result).

    ``order`` sorts the channels by frequency (ascending); ``levels`` is a list, bottom-up, of merges
    ``(range, (lo_range, hi_range, row_L (n,), row_U (n,), o (n,)))`` per range of that level, each
    range a pair of channel indices (first, last) in sorted order, ``row_*`` the rows of the halves'
    arrays that hold the sweeps d_L and d_U (made here, once, not on every transform).
    """

    def __init__(self, freq, dmax):
        f = np.asarray(freq, dtype=np.float64).ravel()
        if f.size == 0 or not np.all(f > 0):
            raise ValueError(f"freq: expected positive channel frequencies, got {freq!r}")
        if int(dmax) != dmax or dmax < 0:
            raise ValueError(f"dmax: expected the largest sweep in whole images (>= 0), got {dmax!r}")
        self.order = np.argsort(f, kind="stable")
        self.f = f[self.order]
        self.nchan, self.dmax = f.size, int(dmax)
        self.k = self.f ** -2.0                                   # delay ~ k; k decreases with f
        # top-down: which sweeps each range must provide
        need = {(0, self.nchan - 1): np.arange(self.dmax + 1)}
        merges = {}                                               # range -> (L, U, dL, dU, o)
        stack = [(0, self.nchan - 1)]
        while stack:
            a, b = stack.pop()
            d = need[(a, b)]
            if a == b:
                continue
            m = (a + b + 1) // 2
            span = self.k[a] - self.k[b]
            if span <= 0:                                         # equal frequencies: no sweep inside
                dL, o = np.zeros_like(d), np.zeros_like(d)
            else:
                dL = np.rint(d * (self.k[a] - self.k[m - 1]) / span).astype(np.int64)
                o = np.rint(d * (self.k[a] - self.k[m]) / span).astype(np.int64)
            dU = d - o
            L, U = (a, m - 1), (m, b)
            merges[(a, b)] = (L, U, dL, dU, o)
            for rng, dd in ((L, dL), (U, dU)):
                if rng[0] == rng[1]:
                    dd = np.zeros(1, np.int64)
                need[rng] = np.union1d(need.get(rng, np.zeros(0, np.int64)), dd)
                stack.append(rng)
        self.need = need
        # group merges by level (depth from the leaves), bottom-up
        def depth(r):
            return 0 if r[0] == r[1] else 1 + max(depth(merges[r][0]), depth(merges[r][1]))
        by = {}
        for r in merges:
            by.setdefault(depth(r), []).append(r)

        def sweeps(r):
            return np.zeros(1, np.int64) if r[0] == r[1] else need[r]

        def rows(r):
            L, U, dL, dU, o = merges[r]
            return L, U, np.searchsorted(sweeps(L), dL), np.searchsorted(sweeps(U), dU), o
        self.levels = [[(r, rows(r)) for r in sorted(by[k])] for k in sorted(by)]

    def rows(self):
        """Shifted-add rows the transform does (its cost in units of one T x npix add)."""
        return int(sum(len(m[1][2]) for lvl in self.levels for m in lvl))


def fdmt(images, plan: FDMTPlan):
    """Dedispersed series for every sweep 0 .. plan.dmax: ``images`` (nchan, T, npix) -> (dmax + 1, T,
    npix), same dtype and array namespace; row d, time t is ``sum_c I_c(t - back(d, c))``
    (:func:`effective_back`), complete for t >= plan.dmax (earlier times lack the higher channels'
    past: those terms count as 0)."""
    xp = get_xp(images)
    x = xp.asarray(images)
    if x.ndim != 3 or x.shape[0] != plan.nchan:
        raise ValueError(f"images: expected (nchan={plan.nchan}, T, npix), got shape {tuple(x.shape)}")
    T = x.shape[1]
    if not np.array_equal(plan.order, np.arange(plan.nchan)):
        x = x[xp.asarray(plan.order)]
    # state: range -> (array (n sweeps it holds, T, npix)); leaves hold sweep 0; the sweeps of a range
    # are plan.need[range], sorted
    state = {(c, c): x[c][None] for c in range(plan.nchan)}
    t = np.arange(T)
    for level in plan.levels:
        for rng, (L, U, rowL, rowU, o) in level:
            aL, aU = state.pop(L), state.pop(U)
            # A_U read o images back, zero before its first time: one gather from a zero-padded copy
            oc = np.minimum(o, T)
            pad = int(oc.max()) if oc.size else 0
            if pad:
                aU = xp.concatenate([xp.zeros((aU.shape[0], pad) + aU.shape[2:], aU.dtype), aU], axis=1)
            tix = xp.asarray(t[None, :] - oc[:, None] + pad)                     # (n, T)
            state[rng] = aL[xp.asarray(rowL)] + aU[xp.asarray(rowU)[:, None], tix]
    return state[(0, plan.nchan - 1)]


def effective_back(plan: FDMTPlan):
    """(dmax + 1, nchan) int64: how many images before t each channel (in the caller's order) is read
    for trial d -- what :func:`fdmt` sums, from the same merge tables."""
    back = {(c, c): np.zeros((1, 1), np.int64) for c in range(plan.nchan)}       # (n sweeps, channels)
    for level in plan.levels:
        for rng, (L, U, rowL, rowU, o) in level:
            bL = back.pop(L)[rowL]
            bU = back.pop(U)[rowU] + o[:, None]
            back[rng] = np.concatenate([bL, bU], axis=1)
    top = back[(0, plan.nchan - 1)]
    out = np.empty_like(top)
    out[:, plan.order] = top
    return out
