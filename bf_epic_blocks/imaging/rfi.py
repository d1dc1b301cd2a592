"""Interference detection by spectral kurtosis (SK), a broadband impulse detector and channel lists, as pure
functions. The derivations are in docs/design/rfi.md.

Conventions:

* Voltages are shaped (ntime, nchan, ninput...) (ninput: any trailing axes, e.g. (nstand, npol)); complex,
  or 'ci4' bytes of that shape (one byte per complex sample: high nibble real, low nibble imaginary, 4-bit
  two's complement, levels -8 .. 7: the project's codec, ``runtime.dtypes.unpack_complex``).
* Power is |x|^2 in the data's own units (4-bit units^2 for ci4: at most 128 per sample).
* A block is m consecutive time samples of one (channel, input). Its power sums are
  S1 = sum |x|^2, S2 = sum |x|^4, and its SK is the generalised estimator of Nita & Gary (2010, MNRAS 406,
  L60) for one spectrum per sample (N = 1) of complex voltages (d = 1):
  SK = (m + 1) / (m - 1) * (m S2 / S1^2 - 1). For stationary complex Gaussian noise E[SK] = 1 exactly
  and Var[SK] = 4 m^2 / ((m - 1)(m + 2)(m + 3)). A steady carrier lowers the SK (towards 0 as it
  dominates), power switching on and off within the block raises it.
* 4-bit noise is not Gaussian: each part is a Gaussian of std ``sigma`` (quantiser units) rounded to
  the nearest level and clipped to -8 .. 7 (what ``runtime.dtypes.pack_ci4`` does). Its SK has a mean and
  spread that depend on sigma (the mean falls below 1 once clipping starts: 0.88 at sigma = 3, 0.53 at
  sigma = 5), which :func:`expected_sk` and :func:`sk_thresholds` give from the block's own mean power
  S1 / m.
* Thresholds are for a false-alarm rate ``far``: the probability that a block of pure noise is flagged,
  split equally between the low and the high tail, from the Pearson law with the SK's first four moments
  (type IV for the SK at m >= 32; type III, a shifted gamma, from three where the moments leave type IV's
  region). Gaussian noise: exact moments; 4-bit noise: a delta-method expansion on the exact moments of
  the quantised power, Monte-Carlo-checked (tests/test_rfi.py) to within a factor 2 of ``far`` for
  m >= 256 and sigma >= 0.4 (m = 64: sigma >= 0.7).
* Flag reasons (int8): 0 clean, 1 low SK (carrier-like), 2 high SK (impulse-like), 3 no power (S1 = 0, or
  a quantised block of nearly all zeros, mean power below :func:`min_mean_power`).

Per-block arithmetic runs on the arrays' namespace (NumPy or CuPy); the threshold tables (481 power levels
per (m, far, bits), ~0.1 s) are made once on the host with SciPy's special functions and cached.
"""
from __future__ import annotations

import functools
import math
import os
from fractions import Fraction
from pathlib import Path

import numpy as np
from scipy import special

from ..cuda import get_kernel, register
from ._xp import get_xp, to_numpy

__all__ = ["COUNTED", "REASONS", "apply_flags", "band_power", "block_power", "broadband_flags", "channel_mask",
           "expected_sk", "min_mean_power", "parse_bad_freq_list", "power_sums", "quantised_power_moments", "sk_code",
           "sk_flags", "sk_thresholds", "spectral_kurtosis"]

register("imaging/rfi.cu")

#: Names of the flag reasons of :func:`sk_flags`, by code.
REASONS = ("clean", "low-sk", "high-sk", "no-power")

#: The least block length for quantised noise (bits set): the delta-method moments are expansions in 1/m.
MIN_M_QUANTISED = 64

#: Orville's frequency flags: a listed frequency flags the channels whose centre lies within this of it.
ORVILLE_HALF_WIDTH_HZ = 100e3

# The sigma grid of the quantised tables. Below 0.3 (E[P] = 0.19 for 4 bits) most samples are 0 and the SK
# is a lattice that no four-moment law describes: sk_flags calls such blocks 'no-power'. Above 200 every
# sample is clipped (E[P] within 2% of its limit 113); block powers above the grid take its end's values.
_SIGMA_GRID = np.geomspace(0.3, 200.0, 481)
_SIGMA_STEP = _SIGMA_GRID[1] / _SIGMA_GRID[0]
_PAD = 8


# ------------------------------------------------------------------------------------------------ power sums

def _ci4_power_lut():
    """|x|^2 of each of the 256 ci4 bytes, int32 (256,): high nibble real, low imaginary, two's complement."""
    b = np.arange(256, dtype=np.int16)
    re, im = ((b >> 4) ^ 8) - 8, ((b & 0x0F) ^ 8) - 8
    return (re * re + im * im).astype(np.int32)


_CI4_POWER = _ci4_power_lut()


def power_sums(x, m, *, ci4=False):
    """Per-block power sums (S1, S2) = (sum |x|^2, sum |x|^4) over blocks of ``m`` time samples.

    x : complex (ntime, nchan, ninput...), or with ``ci4=True`` the ci4 bytes of that shape (uint8, or the
        structured ``[('re_im', u1)]`` of a host ring). ntime must be a multiple of m: a trailing partial
        block is an error, not silently dropped (a streaming caller gulps in multiples of m).
    m : samples per block (>= 2).

    Returns float64 (S1, S2), each (ntime // m, nchan, ninput...), in the data's units^2 and ^4, on x's
    device. For ci4 each byte is decoded by one gather from a 256-entry table of |x|^2 and the sums are
    integers formed in int64, hence exact (|x|^2 <= 128); float64 keeps them exact (to m < 2^39), and the SK's
    m S2 / S1^2 - 1 is a difference of numbers near 2 whose rounding in float32 (1e-7) would not matter
    either. The outputs are m times smaller than the input, so their width costs nothing. Complex input is
    squared in its own precision and summed in float64.
    """
    m = _check_m(m)
    xp = get_xp(x)
    if x.ndim < 1 or x.shape[0] % m:
        raise ValueError(f"power_sums: ntime = {x.shape[0] if x.ndim else 0} is not a multiple of m = {m}; "
                         f"give whole blocks (trim the input or gulp in multiples of m)")
    nblk = x.shape[0] // m
    if ci4:
        names = getattr(x.dtype, "names", None)
        if names:
            x = x[names[0]]
        if x.dtype.itemsize != 1:
            raise TypeError(f"power_sums: ci4 data must be one byte per sample, got dtype {x.dtype}")
        p = xp.asarray(_CI4_POWER)[x.view(xp.uint8)]
        p = p.reshape((nblk, m) + x.shape[1:])
        s1 = p.sum(axis=1, dtype=xp.int64).astype(xp.float64)
        s2 = (p * p).sum(axis=1, dtype=xp.int64).astype(xp.float64)
        return s1, s2
    if not xp.iscomplexobj(x):
        raise TypeError(f"power_sums: x must be complex voltages (or ci4 bytes with ci4=True), got {x.dtype}")
    p = (x.real * x.real + x.imag * x.imag).reshape((nblk, m) + x.shape[1:])
    return p.sum(axis=1, dtype=xp.float64), (p * p).sum(axis=1, dtype=xp.float64)


def block_power(x, m, a, *, ci4=False, group=1, skip=None):
    """(S1, S2, Sa): the power sums of :func:`power_sums` over the whole blocks of ``m`` samples, and the
    power summed over the whole short blocks of ``a`` samples and over each ``group`` adjacent inputs, in
    one pass.

    x : as :func:`power_sums` (any ntime: samples past the last whole block are left out of that block's
        sums); its last axis is the one ``group`` sums over (a stand's pols: group = npol).
    group : inputs summed into Sa (a power of 2 up to 32 that divides the last axis).
    skip : None, or bool (ntime // a,): short blocks left out of S1 and S2 (not out of Sa), e.g. those a
        broadband impulse hit.
    Returns float64 S1, S2 (ntime // m, nchan, ninput...) and float32 Sa (ntime // a, nchan, ...,
    ninput_last // group). On a GPU, ci4 bytes are read once by one kernel (``rfi.cu``), never widened
    to a power array; elsewhere :func:`power_sums` twice."""
    m, a, group = _check_m(m), int(a), int(group)
    if a < 1:
        raise ValueError(f"a (samples per short block) must be >= 1, got {a!r}")
    if group < 1 or group > 32 or group & (group - 1) or (x.ndim > 1 and x.shape[-1] % group):
        raise ValueError(f"group must be a power of 2 up to 32 dividing the last axis ({x.shape[-1]}), got {group!r}")
    xp = get_xp(x)
    T = int(x.shape[0])
    nb, ns = T // m, T // a
    tail = tuple(x.shape[1:-1]) + ((x.shape[-1] // group,) if x.ndim > 1 else ())
    if skip is not None:
        skip = np.asarray(skip, bool).reshape(-1)
        if skip.shape[0] != ns:
            raise ValueError(f"skip must have one entry per whole short block ({ns}), got {skip.shape[0]}")
    if ci4 and xp is not np:
        names = getattr(x.dtype, "names", None)
        b = xp.ascontiguousarray((x[names[0]] if names else x).view(xp.uint8))
        K = int(np.prod(b.shape[1:])) if b.ndim > 1 else 1
        if K % 4 == 0 and b.data.ptr % 4 == 0 and m % a == 0:
            s1 = xp.zeros((nb,) + tuple(b.shape[1:]), xp.float64)
            s2 = xp.zeros_like(s1)
            sh = xp.empty((ns,) + tail, xp.float32)
            sk = None
            if skip is not None:
                sk = xp.asarray(np.concatenate([skip, np.zeros(1, bool)]).astype(np.uint8))  # frames past ns a
            chunk = a * min(max(1, -(-T // (4 * a))), max(1, 2 ** 16 // a))   # ~4 chunks: ~K threads; int32 sums
            if K and T and (nb or ns):
                get_kernel("imaging/rfi.cu", "rfi_block_power")(
                    ((K // 4 + 255) // 256, -(-T // chunk)), (256,),
                    (b, s1, s2, sh, sk if sk is not None else np.uint64(0), np.int64(K // 4), np.int32(T),
                     np.int32(m), np.int32(a), np.int32(group), np.int32(chunk)))
            return s1, s2, sh
    if skip is not None and nb:
        keep = np.ones(T, bool)
        keep[:ns * a] = ~np.repeat(skip, a)
        k = xp.asarray(keep[:nb * m]).reshape((nb * m,) + (1,) * (x.ndim - 1))
        xs = x[:nb * m]
        names = getattr(xs.dtype, "names", None)
        xs = xs[names[0]] if names else xs          # a structured ci4 host array: its bytes
        S1, S2 = power_sums(xp.where(k, xs, xp.zeros((), xs.dtype)), m, ci4=ci4)
    else:
        S1, S2 = power_sums(x[:nb * m], m, ci4=ci4) if nb else (xp.zeros((0,) + x.shape[1:]),) * 2
    sh = _short_sums(x[:ns * a], a, ci4) if ns else xp.zeros((0,) + x.shape[1:], xp.float32)
    if group > 1:
        sh = sh.reshape(sh.shape[:-1] + (sh.shape[-1] // group, group)).sum(axis=-1, dtype=xp.float32)
    return S1, S2, sh


def _short_sums(x, a, ci4):
    xp = get_xp(x)
    if ci4:
        names = getattr(x.dtype, "names", None)
        p = xp.asarray(_CI4_POWER)[(x[names[0]] if names else x).view(xp.uint8)]
    else:
        p = x.real * x.real + x.imag * x.imag
    return p.reshape((x.shape[0] // a, a) + x.shape[1:]).sum(axis=1, dtype=xp.float64).astype(xp.float32)


def spectral_kurtosis(S1, S2, m):
    """The SK estimator (module docstring) of blocks of m samples, float64 shaped like S1.

    S1, S2 : per-block sum |x|^2 and sum |x|^4 (:func:`power_sums`). NaN where S1 == 0 (the caller flags
    such a block 'no-power')."""
    m = _check_m(m)
    xp = get_xp(S1, S2)
    S1 = xp.asarray(S1, dtype=xp.float64)
    S2 = xp.asarray(S2, dtype=xp.float64)
    empty = S1 == 0
    s1 = xp.where(empty, 1.0, S1)
    sk = (m + 1.0) / (m - 1.0) * (m * S2 / (s1 * s1) - 1.0)
    return xp.where(empty, xp.nan, sk)


# ---------------------------------------------------------------------------------- statistics of the SK

def _levels(bits):
    if isinstance(bits, bool) or not isinstance(bits, (int, np.integer)) or not 2 <= int(bits) <= 8:
        raise ValueError(f"bits must be an integer 2 .. 8 (or None for unquantised noise), got {bits!r}")
    half = 2 ** (int(bits) - 1)
    return np.arange(-half, half, dtype=np.float64)


def _level_probabilities(sigma, bits):
    """(levels (L,), probabilities sigma.shape + (L,)) of round-to-nearest then clip of N(0, sigma^2).
    Level k takes (k - 1/2, k + 1/2), the end levels everything beyond; positive levels are computed from
    the upper tail so that small probabilities keep their digits."""
    lv = _levels(bits)
    s = np.asarray(sigma, np.float64)[..., None]
    below = np.where(lv < lv[-1], special.ndtr((lv + 0.5) / s), 1.0) - \
        np.where(lv > lv[0], special.ndtr((lv - 0.5) / s), 0.0)
    above = special.ndtr((0.5 - lv) / s) - np.where(lv < lv[-1], special.ndtr((-0.5 - lv) / s), 0.0)
    return lv, np.where(lv > 0, above, below)


def quantised_power_moments(sigma, bits=4, *, kmax=4):
    """Exact raw moments E[P^k], k = 1 .. kmax, of P = a^2 + b^2 for quantised complex Gaussian noise.

    a, b : independent, each N(0, sigma^2) (sigma in quantiser units, i.e. level spacings) rounded to the
    nearest of the ``bits``-bit two's-complement levels -2^(bits-1) .. 2^(bits-1) - 1 and clipped to them.
    sigma : float array (any shape, > 0). Returns float64 sigma.shape + (kmax,), on the host (NumPy).
    E[P^k] = sum_j C(k, j) E[a^2j] E[b^2(k-j)], each E[a^2j] a sum over the levels' probabilities.
    """
    sigma = np.asarray(sigma, np.float64)
    if not np.all(sigma > 0):
        raise ValueError("quantised_power_moments: sigma must be > 0")
    lv, prob = _level_probabilities(sigma, bits)
    even = np.stack([(prob * lv ** (2 * j)).sum(-1) for j in range(kmax + 1)], axis=-1)   # E[a^2j]
    return np.stack([sum(math.comb(k, j) * even[..., j] * even[..., k - j] for j in range(k + 1))
                     for k in range(1, kmax + 1)], axis=-1)


@functools.cache
def _gaussian_sk_moments(m):
    """(mean, variance, skewness, excess kurtosis) of the SK of m exponential powers (complex Gaussian
    noise), exact.

    P_i / S1 is uniform on the simplex (Dirichlet(1, ..., 1)) and independent of S1, so Q = S2 / S1^2 =
    sum u_i^2 has E[prod u_i^a_i] = prod a_i! / m^(sum a_i) (rising factorial); E[Q^k] sums that over the
    set partitions of k indices (docs/design/rfi.md). Rational arithmetic: the central moments are
    differences of numbers near 1 that are O(1/m^2) apart."""
    def rising(n):
        return math.prod(range(m, m + n))

    def falling(n):
        return math.prod(range(m - n + 1, m + 1))
    eq = [Fraction(1), Fraction(2 * m, rising(2)),
          Fraction(24 * m + 4 * falling(2), rising(4)),
          Fraction(720 * m + 3 * 48 * falling(2) + 8 * falling(3), rising(6)),
          Fraction(40320 * m + (4 * 1440 + 3 * 576) * falling(2) + 6 * 96 * falling(3) + 16 * falling(4),
                   rising(8))]
    central = [sum(math.comb(k, j) * eq[j] * (-eq[1]) ** (k - j) for j in range(k + 1)) for k in range(5)]
    s = Fraction(m + 1, m - 1) * m                     # SK = s Q - (m + 1)/(m - 1)
    mean = s * eq[1] - Fraction(m + 1, m - 1)
    var = s ** 2 * central[2]
    skew = float(s ** 3 * central[3]) / float(var) ** 1.5
    exkurt = float(s ** 4 * central[4] / var ** 2 - 3)
    return float(mean), float(var), skew, exkurt


def _central_comoments(raw):
    """Cumulant tensors K2 (..., 2, 2), K3 (..., 2, 2, 2), K4 (..., 2, 2, 2, 2) of Y = (P, P^2), from the
    raw moments E[P^k], k = 1 .. 8 (raw[..., k - 1])."""
    mu = [np.ones_like(raw[..., 0])] + [raw[..., k] for k in range(8)]
    m1, m2 = mu[1], mu[2]

    def cm(a, b):     # E[(P - m1)^a (P^2 - m2)^b]
        return sum(math.comb(a, i) * math.comb(b, j) * (-m1) ** (a - i) * (-m2) ** (b - j) * mu[i + 2 * j]
                   for i in range(a + 1) for j in range(b + 1))
    shape = raw.shape[:-1]
    K2, K3, K4 = (np.empty(shape + (2,) * n) for n in (2, 3, 4))
    for idx in np.ndindex((2,) * 2):
        K2[(...,) + idx] = cm(2 - sum(idx), sum(idx))
    for idx in np.ndindex((2,) * 3):
        K3[(...,) + idx] = cm(3 - sum(idx), sum(idx))
    for i, j, k, l in np.ndindex((2,) * 4):
        K4[..., i, j, k, l] = (cm(4 - (i + j + k + l), i + j + k + l) - K2[..., i, j] * K2[..., k, l]
                               - K2[..., i, k] * K2[..., j, l] - K2[..., i, l] * K2[..., j, k])
    return K2, K3, K4


def _delta_moments(raw, m, f1=0.0, f2=0.0, f3=0.0):
    """(mean, variance, skewness, excess kurtosis) of r = SK - f(S1/m) for blocks of m iid powers with raw
    moments ``raw`` (..., 8), by the delta method on the block means X = (A, B) = (S1/m, S2/m).

    SK = c (B / A^2 - 1), c = (m + 1)/(m - 1); f is a function of the block's mean power with derivatives
    f1, f2, f3 at E[P] (all 0: the SK itself). With r's derivatives G_i, H_ij, D_ijk at E[X] and the cumulants
    K2/m, K3/m^2, K4/m^3 of X (those of Y = (P, P^2) over powers of m), v = K2 G:

    E[r]  = r + H_ij K2_ij / 2m                                                   + O(1/m^2)
    Var r = G K2 G / m + (G_i H_jk K3_ijk + tr(H K2 H K2) / 2 + D_ijk v_i K2_jk) / m^2   + O(1/m^3)
    k3    = (G_i G_j G_k K3_ijk + 3 v H v) / m^2                                  + O(1/m^3)
    k4    = (G^4 K4 + 12 G_i G_j K3_ijk H_kl v_l + 12 v H K2 H v + 4 D_ijk v_i v_j v_k) / m^3 + O(1/m^4)

    (docs/design/rfi.md derives them)."""
    K2, K3, K4 = _central_comoments(raw)
    A, B = raw[..., 0], raw[..., 1]
    c = (m + 1.0) / (m - 1.0)
    shape = A.shape
    G = np.stack(np.broadcast_arrays(-2 * c * B / A ** 3 - f1, c / A ** 2), axis=-1)
    H = np.zeros(shape + (2, 2))
    H[..., 0, 0] = 6 * c * B / A ** 4 - f2
    H[..., 0, 1] = H[..., 1, 0] = -2 * c / A ** 3
    D = np.zeros(shape + (2, 2, 2))
    D[..., 0, 0, 0] = -24 * c * B / A ** 5 - f3
    D[..., 0, 0, 1] = D[..., 0, 1, 0] = D[..., 1, 0, 0] = 6 * c / A ** 4
    es = functools.partial(np.einsum, optimize=True)
    v = es("...ij,...j->...i", K2, G)
    HK = es("...ij,...jk->...ik", H, K2)
    mean = c * (B / A ** 2 - 1) + es("...ij,...ij->...", H, K2) / (2 * m)
    var = (es("...i,...i->...", G, v) / m
           + (es("...i,...jk,...ijk->...", G, H, K3) + 0.5 * es("...ij,...ji->...", HK, HK)
              + es("...ijk,...i,...jk->...", D, v, K2)) / m ** 2)
    vHv = es("...i,...ij,...j->...", v, H, v)
    k3 = (es("...i,...j,...k,...ijk->...", G, G, G, K3) + 3 * vHv) / m ** 2
    k4 = (es("...i,...j,...k,...l,...ijkl->...", G, G, G, G, K4)
          + 12 * es("...i,...j,...ijk,...kl,...l->...", G, G, K3, H, v)
          + 12 * es("...i,...ij,...jk,...kl,...l->...", v, H, K2, H, v)
          + 4 * es("...ijk,...i,...j,...k->...", D, v, v, v)) / m ** 3
    return mean, var, k3 / var ** 1.5, k4 / var ** 2


@functools.lru_cache(maxsize=32)
def _quantised_table(m, bits):
    """Tables on the sigma grid, host float64 (n,) each: E[P] (increasing); the SK's mean and std at that
    sigma; and the mean, std, skewness and excess kurtosis of the SK's departure from its mean at the
    block's measured power, r = SK - f(S1/m) with f(E[P]) = E[SK]: what a threshold set from each block's
    own power faces (the SK and the power are correlated once the quantiser clips).

    The delta method's O(1/m) relative errors in the variance, skewness and kurtosis are scaled away by
    the ratio of exact to delta-method values for unquantised noise at the same m (exact there), which
    the quantised power resembles where it matters; Monte Carlo tests hold the result."""
    sig = np.concatenate([_SIGMA_GRID[0] / _SIGMA_STEP ** np.arange(_PAD, 0, -1), _SIGMA_GRID,
                          _SIGMA_GRID[-1] * _SIGMA_STEP ** np.arange(1, _PAD + 1)])   # padded: derivatives
    raw = quantised_power_moments(sig, bits, kmax=8)
    ep = raw[:, 0]
    if not np.all(np.diff(ep) > 0):
        raise RuntimeError("quantised mean power is not increasing on the sigma grid")   # pragma: no cover
    with np.errstate(invalid="ignore"):          # the padding below sigma = 0.3 may go negative; dropped
        mean, var, _, _ = _delta_moments(raw, m)
        f1 = np.gradient(mean, ep)
        f2 = np.gradient(f1, ep)
        f3 = np.gradient(f2, ep)
        rmean, rvar, rskew, rkurt = _delta_moments(raw, m, f1, f2, f3)
    exact = _gaussian_sk_moments(m)
    approx = [float(v) for v in _delta_moments(np.array([float(math.factorial(k)) for k in range(1, 9)]), m)]
    var, rvar = var * (exact[1] / approx[1]), rvar * (exact[1] / approx[1])
    rskew = rskew * (exact[2] / approx[2])
    rkurt = rkurt * (exact[3] / approx[3])
    keep = slice(_PAD, _PAD + _SIGMA_GRID.size)
    return tuple(np.ascontiguousarray(v[keep]) for v in (ep, mean, np.sqrt(var), rmean, np.sqrt(rvar), rskew, rkurt))


def _pearson3_tails(mean, std, skew, p):
    """(lo, hi) with P(X < lo) = P(X > hi) = p for the Pearson type III law of the given moments (host).

    Skewness gamma > 0: X = loc + theta G, G ~ Gamma(k), k = 4 / gamma^2, theta = std gamma / 2,
    loc = mean - k theta; gamma < 0 is the mirror image; |gamma| < 1e-8 the normal law."""
    mean, std, skew = (np.asarray(v, np.float64) for v in (mean, std, skew))
    a = np.maximum(np.abs(skew), 1e-8)
    k = 4.0 / a ** 2
    theta = std * a / 2.0
    q_lo = special.gammaincinv(k, p) - k                 # (G - k) at the tails, G's mean removed
    q_hi = special.gammainccinv(k, p) - k
    normal = np.abs(skew) < 1e-8
    z = special.ndtri(1.0 - p)
    lo = np.where(normal, mean - z * std, np.where(skew > 0, mean + theta * q_lo, mean - theta * q_hi))
    hi = np.where(normal, mean + z * std, np.where(skew > 0, mean + theta * q_hi, mean - theta * q_lo))
    return lo, hi


def _pearson4_params(mean, std, skew, exkurt):
    """Pearson type IV (r, nu, a, lam) for the four moments (Heinrich 2004, CDF note 6820), and whether the
    moments lie in the type IV region (0 < kappa < 1, r > 3): density ~ [1 + ((x - lam)/a)^2]^-(r/2 + 1)
    exp(-nu arctan((x - lam)/a))."""
    b1 = skew ** 2
    b2 = exkurt + 3.0
    den = 2 * b2 - 3 * b1 - 6
    with np.errstate(divide="ignore", invalid="ignore"):
        r = 6 * (b2 - b1 - 1) / den
        disc = 16 * (r - 1) - b1 * (r - 2) ** 2
        ok = (den > 0) & np.isfinite(r) & (r > 3) & (disc > 0) & (r < 1e6)
        sq = np.sqrt(np.where(ok, disc, 1.0))
        nu = np.where(ok, -r * (r - 2) * skew / sq, 0.0)
        a = std * sq / 4
        lam = mean - (r - 2) * skew * std / 4
    return r, nu, a, lam, ok


def _pearson4_tails(r, nu, a, lam, p, npts=4001):
    """(lo, hi) tail quantiles at probability p of Pearson IV laws (vectors of parameters, host).

    With x = lam + a tan(t) the density in t on (-pi/2, pi/2) is cos(t)^r exp(-nu t): smooth and bounded, so
    its CDF is a cumulative trapezoid on a grid around the mode (+-40 widths, within the interval)."""
    r, nu, a, lam = (np.atleast_1d(np.asarray(v, np.float64)) for v in (r, nu, a, lam))
    t0 = np.arctan(-nu / r)
    w = 1.0 / np.sqrt(r * (1 + (nu / r) ** 2))
    lo_t = np.maximum(-np.pi / 2, t0 - 40 * w)
    hi_t = np.minimum(np.pi / 2, t0 + 40 * w)
    u = np.linspace(0.0, 1.0, npts)
    t = lo_t[:, None] + (hi_t - lo_t)[:, None] * u[None, :]
    with np.errstate(divide="ignore"):
        logd = r[:, None] * np.log(np.maximum(np.cos(t), 0.0)) - nu[:, None] * t
    d = np.exp(logd - logd.max(axis=1, keepdims=True))
    cdf = np.concatenate([np.zeros((t.shape[0], 1)),
                          np.cumsum(0.5 * (d[:, 1:] + d[:, :-1]) * np.diff(t, axis=1), axis=1)], axis=1)
    cdf /= cdf[:, -1:]
    tq_lo = np.array([np.interp(p, cdf[i], t[i]) for i in range(t.shape[0])])
    tq_hi = np.array([np.interp(1.0 - p, cdf[i], t[i]) for i in range(t.shape[0])])
    return lam + a * np.tan(tq_lo), lam + a * np.tan(tq_hi)


def _noise_tails(mean, std, skew, exkurt, p):
    """(lo, hi) noise thresholds at tail probability p from four moments: Pearson type IV where the moments
    lie in its region (the SK's, for m >= ~24), else type III from the first three (host, vectorised)."""
    mean, std, skew, exkurt = np.broadcast_arrays(*(np.asarray(v, np.float64) for v in (mean, std, skew, exkurt)))
    lo, hi = _pearson3_tails(mean, std, skew, p)
    lo, hi = np.array(lo, ndmin=1), np.array(hi, ndmin=1)
    r, nu, a, lam, ok = (np.atleast_1d(v) for v in _pearson4_params(mean, std, skew, exkurt))
    if ok.any():
        lo4, hi4 = _pearson4_tails(r[ok], nu[ok], a[ok], lam[ok], p)
        lo[ok.ravel()] = lo4
        hi[ok.ravel()] = hi4
    return lo.reshape(mean.shape), hi.reshape(mean.shape)


@functools.lru_cache(maxsize=64)
def _gaussian_thresholds(m, far):
    mean, var, skew, exkurt = _gaussian_sk_moments(m)
    return tuple(float(v) for v in _noise_tails(mean, math.sqrt(var), skew, exkurt, far / 2.0))


@functools.lru_cache(maxsize=64)
def _threshold_table(m, far, bits):
    ep, _, _, rmean, rstd, rskew, rkurt = _quantised_table(m, bits)
    lo, hi = _noise_tails(rmean, rstd, rskew, rkurt, far / 2.0)
    return ep, lo, hi


_DEVICE_TABLES: dict = {}


def _tables_on(xp, tables):
    """A cached table tuple's arrays on xp's current device, copied there once (a streaming flagger asks
    for them every gulp)."""
    if xp is np:
        return tables
    key = (id(tables), xp.cuda.Device().id)
    hit = _DEVICE_TABLES.get(key)
    if hit is None or hit[0] is not tables:      # the entry holds the tuple, so its id is not reused
        hit = _DEVICE_TABLES[key] = (tables, tuple(xp.asarray(t) for t in tables))
    return hit[1]


def expected_sk(mean_power, m, bits=4, *, measured=True):
    """(mean, std) of the SK of noise blocks of m samples whose mean power per sample is ``mean_power``.

    bits=None: unquantised complex Gaussian noise, whatever its power: mean 1 and variance
    4 m^2 / ((m - 1)(m + 2)(m + 3)) (Nita & Gary 2010), exact (the SK is then independent of the power);
    floats when mean_power is None, else arrays shaped like it.

    bits=4 (or another width): quantised noise (module docstring). mean_power in quantiser units^2.
    measured=True (what :func:`sk_flags` uses): the SK's moments given that the block's own S1 / m is
    mean_power (a block's SK and its power are correlated once clipping starts, and its thresholds follow
    its own measured power); measured=False: the moments for noise whose expected power E[|x|^2] is
    mean_power. The noise's sigma is found by interpolation in a fine table of E[P] against sigma, and the SK's
    moments there by the delta method on the exact moments of the quantised power (docs/design/rfi.md;
    an expansion in 1/m: m >= 64 is required). float64 arrays shaped like mean_power, on its device;
    powers beyond the table (sigma < 0.3 or > 200) take its ends' values.
    """
    m = _check_m(m, bits)
    if bits is None:
        mean, var, _, _ = _gaussian_sk_moments(m)
        return _like(mean_power, mean, math.sqrt(var))
    if mean_power is None:
        raise ValueError("expected_sk: quantised noise (bits set) needs the block mean power")
    xp = get_xp(mean_power)
    ep, mean, std, rmean, rstd, _, _ = _tables_on(xp, _quantised_table(m, int(bits)))
    if measured:
        mean, std = rmean, rstd
    mp = xp.asarray(mean_power, dtype=xp.float64)
    return xp.interp(mp, ep, mean), xp.interp(mp, ep, std)


def sk_thresholds(far, m, mean_power=None, bits=4):
    """(lo, hi): SK thresholds that pure noise crosses with total probability ``far`` (far / 2 each side).

    far : false-alarm probability per block, 0 < far < 1. m : samples per block.
    bits=None: complex Gaussian noise; floats (or arrays like mean_power when given), from the Pearson law
    (type IV; type III where m < ~24 leaves type IV's region) with the SK's exact first four moments.
    bits=4: quantised noise whose block mean power S1 / m is ``mean_power`` (quantiser units^2, required;
    m >= 64); float64 arrays shaped like it, on its device, interpolated in a table of thresholds against
    E[P] made once per (m, far, bits) on the host (~0.1 s) from the moments of :func:`expected_sk`
    (measured=True) and the skewness and kurtosis of the same expansion.
    """
    m = _check_m(m, bits)
    far = float(far)
    if not 0.0 < far < 1.0:
        raise ValueError(f"far must be in (0, 1), got {far!r}")
    if bits is None:
        return _like(mean_power, *_gaussian_thresholds(m, far))
    if mean_power is None:
        raise ValueError("sk_thresholds: quantised noise (bits set) needs the block mean power")
    xp = get_xp(mean_power)
    ep, lo, hi = _tables_on(xp, _threshold_table(m, far, int(bits)))
    mp = xp.asarray(mean_power, dtype=xp.float64)
    return xp.interp(mp, ep, lo), xp.interp(mp, ep, hi)


@functools.cache
def min_mean_power(bits=4):
    """The least block mean power (quantiser units^2) whose quantised SK has a noise law here: E[P] at
    sigma = 0.3 (0.19 for 4 bits). Below it most samples are 0; :func:`sk_flags` calls such blocks
    'no-power'."""
    return float(quantised_power_moments(_SIGMA_GRID[0], bits, kmax=1)[0])


def sk_flags(S1, S2, m, far, bits=4):
    """Flag blocks whose SK is outside the noise's thresholds for false-alarm rate ``far``.

    S1, S2 : per-block power sums (:func:`power_sums`), any shape (nblock, nchan, ninput...).
    m : samples per block (the recommended 1024 is 41 ms of 25 kHz channels); far : the probability that a
    block of pure noise is flagged (e.g. 1e-3).
    bits=4 for F-engine ci4 data (each block's thresholds follow its own mean power S1 / m, in 4-bit
    units^2), None for unquantised data (one pair of thresholds).
    Returns (flag bool, reason int8), both shaped like S1, on its device: reason 0 clean, 1 low SK
    (carrier-like), 2 high SK (impulse-like), 3 no power (S1 == 0; for quantised data also a mean power
    below :func:`min_mean_power`, a block of nearly all zeros); flag = reason != 0 (:data:`REASONS`).
    """
    xp = get_xp(S1, S2)
    sk = spectral_kurtosis(S1, S2, m)
    mean_power = xp.asarray(S1, dtype=xp.float64) / m
    lo, hi = sk_thresholds(far, m, mean_power if bits is not None else None, bits)
    no_power = xp.isnan(sk)
    if bits is not None:
        no_power = no_power | (mean_power < min_mean_power(bits))
    reason = xp.where(sk < lo, 1, xp.where(sk > hi, 2, 0))
    reason = xp.where(no_power, 3, reason).astype(xp.int8)
    return reason != 0, reason


def sk_code(S1, S2, m, far, bits=4):
    """Per (block, channel, stand): bit 0 where the SK of any of the stand's pols is low, bit 1 where high
    (:func:`sk_flags`' reasons 1 and 2; a block with no power sets neither).

    S1, S2 : (nblock, nchan, nstand, npol) power sums (:func:`power_sums`). Returns uint8 (nblock, nchan,
    nstand) on S1's device. On a GPU one kernel (``rfi.cu``: ``rfi_sk_code``) does it, with the thresholds
    of every possible block power tabulated once: a quantised block's S1 is an integer 0 .. 128 m, and its
    thresholds are :func:`sk_thresholds` at mean power S1 / m, the numbers :func:`sk_flags` interpolates."""
    m = _check_m(m, bits)
    xp = get_xp(S1, S2)
    if xp is np or S1.ndim != 4:
        _, r = sk_flags(S1, S2, m, far, bits)
        r = r.reshape(r.shape[:3] + (-1,))
        return ((r == 1).any(axis=3) | ((r == 2).any(axis=3) << 1)).astype(np.uint8)
    lo, hi = _tables_on(xp, _sk_code_table(m, float(far), bits))
    s1 = xp.ascontiguousarray(S1, dtype=xp.float64)
    s2 = xp.ascontiguousarray(S2, dtype=xp.float64)
    code = xp.empty(S1.shape[:3], xp.uint8)
    n = int(code.size)
    min_s1 = m * min_mean_power(bits) if bits is not None else 0.0
    if n:
        get_kernel("imaging/rfi.cu", "rfi_sk_code")(
            ((n + 255) // 256,), (256,), (s1, s2, lo, hi, code, np.int64(n), np.int32(S1.shape[3]), np.float64(m),
                                          np.int64(lo.size), np.float64(min_s1)))
    return code


@functools.lru_cache(maxsize=16)
def _sk_code_table(m, far, bits):
    """(lo, hi) host float64: one pair (Gaussian noise) or, for quantised noise, per block power S1 = 0 ..
    2^(2 bits - 1) m (|x|^2 <= 2^(2 bits - 1) a sample), the thresholds at mean power S1 / m."""
    if bits is None:
        lo, hi = _gaussian_thresholds(m, far)
        return np.array([lo]), np.array([hi])
    s1 = np.arange(2 ** (2 * int(bits) - 1) * m + 1, dtype=np.float64)
    return tuple(np.ascontiguousarray(v) for v in sk_thresholds(far, m, s1 / m, bits))


# ----------------------------------------------------------------------------------------- broadband impulses

#: per-input impulse statistic: about this many groups of adjacent channels (:func:`broadband_flags`)
CHANNEL_GROUPS = 64


def broadband_flags(power, threshold_sigma=6.0, *, per_input=False):
    """Short blocks holding a broadband impulse: power raised across the band at once.

    power : (nblock, nchan, ninput...) power per short block (e.g. S1 of :func:`power_sums` with m = 16),
        channel and input.
    Band-wide (``per_input`` False): each channel's power summed over the inputs is divided by its median
        over the nblock blocks; per input (``per_input`` True): each (channel, input)'s power by its mean
        over the blocks. The ratio is averaged over groups of g = max(1, nchan // :data:`CHANNEL_GROUPS`)
        adjacent channels (the first nchan // g groups; a channel with no power counts as 1), and a block's
        (or block and input's) statistic is the median over the groups: a carrier switching on in fewer
        than half the groups leaves it alone (the SK's to flag), a spark across the band raises it. With
        nchan <= 2 CHANNEL_GROUPS that is the median over the channels; at the whole band it sorts ~64
        group means instead of every channel.
    A block (or block and input) is flagged where its statistic exceeds its median over the blocks +
    threshold_sigma * 1.4826 * MAD (1.4826 MAD is the standard deviation of Gaussian scatter; the
    reference holds while fewer than half the blocks are hit).
    Returns bool (nblock,) or (nblock, ninput...) with per_input, on power's device. Needs nblock >= 3.
    """
    xp = get_xp(power)
    if power.ndim < 2 or power.shape[0] < 3:
        raise ValueError(f"broadband_flags: power must be (nblock >= 3, nchan, ninput...), got shape "
                         f"{tuple(power.shape)}")
    if not threshold_sigma > 0:
        raise ValueError(f"threshold_sigma must be > 0, got {threshold_sigma!r}")
    power = xp.asarray(power, dtype=xp.float32)          # short-block powers are integers below 2^24
    rest = power.shape[2:] if per_input else ()
    nb, nchan = int(power.shape[0]), int(power.shape[1])
    g = max(1, nchan // CHANNEL_GROUPS)
    if xp is not np and nb <= 128 and nchan // g <= 128 and g <= 64:
        return _broadband_flags_gpu(power, threshold_sigma, per_input).reshape((nb,) + rest)
    if per_input:
        power = power.reshape(power.shape[0], power.shape[1], -1)
        ref = power.mean(axis=0, dtype=xp.float32)                      # (nchan, ninput)
    else:
        power = power.reshape(power.shape[0], power.shape[1], -1).sum(axis=2, dtype=xp.float32)[:, :, None]
        ref = _median_axis1(power.reshape(1, power.shape[0], -1)).reshape(power.shape[1:])   # (nchan, 1)
    live = ref > 0                                                       # channels (and inputs) with power
    ratio = xp.where(live, power / xp.where(live, ref, xp.float32(1.0)), xp.float32(1.0))
    stat = _group_median(ratio)                                          # (nblock, ninput | 1)
    med = _median_axis1(stat[None])                                      # (1, ninput | 1)
    mad = _median_axis1(xp.abs(stat - med)[None])
    return (stat > med + xp.float32(threshold_sigma * 1.4826) * mad).reshape((stat.shape[0],) + rest)


def _broadband_flags_gpu(power, threshold_sigma, per_input):
    """:func:`broadband_flags` on a GPU in five kernels or fewer (``rfi.cu``: the group means of the ratios,
    the medians, the robust threshold), the array form's numbers: (nb, ninput | 1) bool."""
    xp = get_xp(power)
    nb, nchan = int(power.shape[0]), int(power.shape[1])
    p3 = xp.ascontiguousarray(power.reshape(nb, nchan, -1))
    ref = None
    if not per_input:
        if p3.shape[2] > 1:
            p3 = p3.sum(axis=2, dtype=xp.float32)
        p3 = p3.reshape(nb, nchan, 1)
        ref = _median_axis1(p3.reshape(1, nb, nchan))                 # (1, nchan): each channel's median
    nin = int(p3.shape[2])
    g = max(1, nchan // CHANNEL_GROUPS)
    ng = nchan // g
    if ref is None:                                                      # each (channel, input)'s mean
        ref = xp.empty((nchan, nin), xp.float32)
        get_kernel("imaging/rfi.cu", "rfi_block_mean")(
            ((nchan * nin + 255) // 256,), (256,), (p3, ref, np.int32(nb), np.int64(nchan * nin)))
    means = xp.empty((nb, ng, nin), xp.float32)
    get_kernel("imaging/rfi.cu", "rfi_group_means")(
        ((nb * ng * nin + 255) // 256,), (256,), (p3, xp.ascontiguousarray(ref), means, np.int32(nb), np.int32(nchan),
                                                  np.int32(nin), np.int32(g), np.int32(ng)))
    stat = _median_axis1(means)                                          # (nb, nin)
    flags = xp.empty((nb, nin), xp.uint8)
    get_kernel("imaging/rfi.cu", "rfi_robust_flags")(
        ((32 * nin + 255) // 256,), (256,), (stat, flags, np.int32(nb), np.int32(nin),
                                             np.float32(threshold_sigma * 1.4826)))
    return flags.view(xp.bool_)


def band_power(power, own, live):
    """The band-wide impulse detector's power: (nblock, nchan, 1) float32, each short block's power summed
    over the live stands, where fewer than half the live stands sparked on their own (``own``) without
    those stands and scaled up to all the live stands.

    power : (nblock, nchan, nstand) float32 short-block powers (integers: sums exact in any order).
    own : bool (nblock, nstand) stands flagged by their own impulse detector; live : bool (nstand,) stands
    in use (the rest are left out of both sums: a dead stand's spark is not data).
    One stand's spark, 40 times its noise, raises a 24-stand array's total by more than half and would
    otherwise flag every stand; where half or more sparked at once, the spark is the sky's and the plain
    sum is kept. On a GPU one kernel (``rfi.cu``: ``rfi_band_power``); this function's array form is the
    definition."""
    xp = get_xp(power)
    nb, nchan, nst = (int(v) for v in power.shape)
    if xp is not np:
        out = xp.empty((nb, nchan), xp.float32)
        if nb * nchan:
            get_kernel("imaging/rfi.cu", "rfi_band_power")(
                ((32 * nb * nchan + 255) // 256,), (256,),
                (xp.ascontiguousarray(power, dtype=xp.float32), xp.ascontiguousarray(own, dtype=xp.uint8),
                 xp.ascontiguousarray(live, dtype=xp.uint8), out, np.int32(nb), np.int32(nchan), np.int32(nst)))
        return out[..., None]
    live = xp.asarray(live, bool)
    P = xp.where(live[None, None, :], power, xp.float32(0.0))
    nl = xp.maximum(live.sum(), 1).astype(xp.float32)
    own = own & live[None, :]
    k = own.sum(axis=1).astype(xp.float32)                               # (nblock,)
    total = P.sum(axis=2)
    kept = xp.where(own[:, None, :], xp.float32(0.0), P).sum(axis=2) * (nl / xp.maximum(nl - k, 1))[:, None]
    return xp.where((2 * k < nl)[:, None], kept, total)[..., None]


def _median_axis1(x):
    """x (R, L, C) float32 -> its median over axis 1, (R, C) float32 (NumPy's rule: the mean of the two middle
    values for even L). On a GPU with L <= 128 one kernel ranks each column's values, a warp a column
    (``rfi.cu``), where CuPy's median sorts the whole array."""
    xp = get_xp(x)
    R, L, C = (int(v) for v in x.shape)
    if xp is np or L > 128 or L == 0:
        return xp.median(x, axis=1).astype(xp.float32)
    out = xp.empty((R, C), xp.float32)
    if R * C:
        get_kernel("imaging/rfi.cu", "rfi_median_axis1")(
            ((32 * R * C + 255) // 256,), (256,), (xp.ascontiguousarray(x, dtype=xp.float32), out, np.int32(R),
                                              np.int32(L), np.int32(C)))
    return out


def _group_median(ratio):
    """ratio (nblock, nchan, rest) -> the median over groups of g = max(1, nchan // CHANNEL_GROUPS) adjacent
    channels (the first nchan // g) of the ratio's mean in each group, (nblock, rest) float32."""
    xp = get_xp(ratio)
    nb, nchan = int(ratio.shape[0]), int(ratio.shape[1])
    g = max(1, nchan // CHANNEL_GROUPS)
    ng = nchan // g
    r = ratio[:, :ng * g].reshape(nb, ng, g, -1)
    means = r.mean(axis=2, dtype=xp.float32) if g > 1 else r[:, :, 0]
    return _median_axis1(means)


#: what :func:`apply_flags` counts, in the order of its last axis
COUNTED = ("static", "sk-low", "sk-high", "impulse", "impulse-stand", "spread", "any")


def apply_flags(x, out, sk_code, which, impulse, impulse_stand, static, live, a, spread_max):
    """Combine the detectors' flags per (short block, channel, stand), copy the voltages with the flagged
    stands' samples zeroed, and count.

    x, out : (n, nchan, nstand, B) uint8, the voltages' bytes (B bytes per stand: its pols' samples, in
        any sample format: zero bytes are zero voltages); out[:n] is written.
    sk_code : uint8 (nsk, nchan, nstand): bit 0 a low SK, bit 1 a high SK (in either pol).
    which : int (ns,) the SK block of each short block, -1 where untested (host or device array).
    impulse : bool (ns,) band-wide impulses; impulse_stand : bool (ns, nstand) one stand's own.
    static : bool (nchan,) listed channels; live : bool (nstand,) stands in use (the rest are counted by no
        reason here, and zeroed only by the array-wide reasons).
    a : frames per short block j, frames [j a, min(n, (j + 1) a)); ns = ceil(n / a).
    spread_max : where more than this many live stands are flagged by their own detectors (SK, own
        impulse) in a (short block, channel), every stand is ('spread').
    A stand-sample is flagged when its channel is listed, its stand's own detectors fired, a band-wide
    impulse hit, or the spread rule applies.
    Returns int32 (ns, nchan, 7): the live stands flagged, per :data:`COUNTED` reason (each its own mask;
    'spread' only where the stand's own detectors did not fire; 'any' the union), per (short block,
    channel): multiply by the short blocks' frames for stand-samples. On a GPU with uint8 data, one kernel
    (``rfi.cu``: ``rfi_apply_flags``) reads and writes the voltages once; this function's array form is
    the definition and the CPU's path."""
    xp = get_xp(x)
    n, nchan, nstand = (int(v) for v in x.shape[:3])
    ns = -(-n // int(a))
    if xp is not np and x.dtype == np.uint8 and x.flags.c_contiguous and out.flags.c_contiguous:
        cnt = xp.empty((ns, nchan, len(COUNTED)), xp.int32)
        B = int(np.prod(x.shape[3:])) if x.ndim > 3 else 1
        if n and nchan and nstand:
            u8 = xp.uint8
            get_kernel("imaging/rfi.cu", "rfi_apply_flags")(
                (nchan, ns), (256,),
                (x, out, xp.ascontiguousarray(sk_code, dtype=u8), xp.asarray(which, xp.int32), xp.asarray(impulse, u8),
                 xp.ascontiguousarray(xp.asarray(impulse_stand, u8)), xp.asarray(static, u8), xp.asarray(live, u8),
                 cnt, np.int32(n), np.int32(nchan), np.int32(nstand), np.int32(B), np.int32(a),
                 np.float32(spread_max), np.int32((nstand * B) % 4 == 0 and x.data.ptr % 4 == 0
                                                  and out.data.ptr % 4 == 0)), shared_mem=nstand)
        return cnt
    which = to_numpy(which).astype(np.int32)
    w = xp.asarray(np.maximum(which, 0))
    tested = xp.asarray(which >= 0)[:, None, None]
    code = xp.asarray(sk_code)[w] * tested if sk_code.shape[0] else xp.zeros((ns, nchan, nstand), xp.uint8)
    lo, hi = (code & 1) > 0, (code & 2) > 0
    imp_st = xp.asarray(impulse_stand, bool)[:, None, :]
    lv = xp.asarray(live, bool)[None, None, :]
    own = (lo | hi | imp_st) & lv
    wide = (own.sum(axis=2) > spread_max)[:, :, None]
    spread = wide & ~own
    st = xp.asarray(static, bool)[None, :, None]
    imp = xp.asarray(impulse, bool)[:, None, None]
    bad = st | own | imp | spread
    masks = (st, lo, hi, imp, imp_st, spread, bad)
    cnt = xp.stack([xp.broadcast_to(mk & lv, bad.shape).sum(axis=2) for mk in masks], axis=-1).astype(xp.int32)
    tail = (1,) * (x.ndim - 3)
    per_frame = xp.repeat(bad, a, axis=0)[:n]
    out[:n] = xp.where(per_frame.reshape(per_frame.shape + tail), xp.zeros((), x.dtype), x)
    return cnt


# ----------------------------------------------------------------------------------------- frequency lists

def parse_bad_freq_list(text_or_path, *, half_width_hz=ORVILLE_HALF_WIDTH_HZ):
    """Frequency ranges to flag, [(lo_hz, hi_hz), ...], from an Orville bad-frequency list.

    The format of lwa-project/orville_wideband_imager's ``bad_freq.txt`` (read by its ``FlaggerOp``): one
    frequency in MHz per line; lines starting with '#' are comments; a listed frequency f flags the channels
    whose centre is within 100 kHz of it, here the range (f - half_width_hz, f + half_width_hz).
    Also accepted: a range as two numbers "lo hi" in MHz (space or comma between), blank lines, and a
    comment after '#' on any line. Orville silently skips lines it cannot read; here such a line is a
    ValueError naming the line, and a list with no frequency at all is an error ("no ranges").

    text_or_path : a pathlib.Path, a str naming an existing file, or the list's text.
    """
    if isinstance(text_or_path, Path) or (isinstance(text_or_path, str) and "\n" not in text_or_path
                                          and os.path.isfile(text_or_path)):
        name = str(text_or_path)
        text = Path(text_or_path).read_text()
    elif isinstance(text_or_path, str):
        name, text = "bad-frequency list", text_or_path
    else:
        raise TypeError(f"parse_bad_freq_list: expected a path or the list's text, got {type(text_or_path)}")
    if not half_width_hz >= 0:
        raise ValueError(f"half_width_hz must be >= 0, got {half_width_hz!r}")
    ranges = []
    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.replace(",", " ").split()
        try:
            values = [float(f) for f in fields]
        except ValueError:
            values = []
        if len(values) not in (1, 2) or not all(math.isfinite(v) and v > 0 for v in values):
            raise ValueError(f"{name}, line {n}: {raw.strip()!r} is not a frequency in MHz or a range "
                             f"'lo hi' in MHz")
        if len(values) == 1:
            f = values[0] * 1e6
            ranges.append((f - half_width_hz, f + half_width_hz))
        else:
            lo, hi = values[0] * 1e6, values[1] * 1e6
            if not lo < hi:
                raise ValueError(f"{name}, line {n}: {raw.strip()!r}: the range's low end is not below its high end")
            ranges.append((lo, hi))
    if not ranges:
        raise ValueError(f"{name}: no ranges (every line is blank or a comment)")
    return ranges


def channel_mask(freq_hz, ranges, chan_bw_hz):
    """bool (nchan,): True for channels overlapping any of ``ranges``.

    freq_hz : (nchan,) channel centres (Hz); ranges : [(lo_hz, hi_hz), ...] (:func:`parse_bad_freq_list`);
    chan_bw_hz : channel width (Hz). A channel spans (f - bw/2, f + bw/2) and is flagged if that open
    interval meets an open range (lo, hi): touching an edge is not overlap. chan_bw_hz = 0 tests the centre
    alone, which is exactly Orville's rule (|f - listed| < 100 kHz) for ranges parsed from its list."""
    xp = get_xp(freq_hz)
    f = xp.asarray(freq_hz, dtype=xp.float64)
    if not chan_bw_hz >= 0:
        raise ValueError(f"chan_bw_hz must be >= 0, got {chan_bw_hz!r}")
    r = np.asarray(ranges, np.float64).reshape(-1, 2)
    if r.shape[0] == 0:
        return xp.zeros(f.shape, bool)
    lo, hi = xp.asarray(r[:, 0]), xp.asarray(r[:, 1])
    half = 0.5 * float(chan_bw_hz)
    return ((f[:, None] + half > lo) & (f[:, None] - half < hi)).any(axis=1)


def _like(shape_of, *values):
    """``values`` as floats (``shape_of`` None), or as arrays shaped like ``shape_of`` on its device: the
    Gaussian law's numbers, which do not depend on the block's power."""
    if shape_of is None:
        return values
    xp = get_xp(shape_of)
    shape = xp.asarray(shape_of).shape
    return tuple(xp.full(shape, v) for v in values)


def _check_m(m, bits=None):
    if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 2:
        raise ValueError(f"m (samples per block) must be an integer >= 2, got {m!r}")
    if bits is not None and m < MIN_M_QUANTISED:
        raise ValueError(f"m = {m}: the quantised SK's noise law (an expansion in 1/m) needs m >= "
                         f"{MIN_M_QUANTISED} (256 or more recommended)")
    return int(m)
