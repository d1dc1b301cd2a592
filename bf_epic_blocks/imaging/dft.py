"""The exact direct-Fourier-transform E-field imager (NumPy or CuPy).

Conventions (docs/CONVENTIONS.md, bf_epic_blocks.conventions): positions East/North/Up metres,
pixels (l East, m North), n = sqrt(1 - l^2 - m^2) computed in float64 (full n: the data are not
phased to any centre), sign SIGMA = +1 so

    D[k, a] = w_a * B_a(s_k) * exp(-2 pi i nu (l_k x_a + m_k y_a + n_k z_a) / c) / N_A

with w_a the folded direction-independent weight (0 = flagged: the antenna is dropped), B_a the
optional voltage pattern, N_A the unflagged antennas of that channel and polarisation. The image is

    I_k = (1/T) sum_t |sum_a D[k, a] x_a(t)|^2        (cross products: F_X F_Y^*)

Two exact routes give it: "direct" (F = D X, then |F|^2 averaged over time) and "covariance"
(R = X X^H / T, then Re diag(D R D^H)); "auto" picks the cheaper by :mod:`.cost`.

Implementation notes (why it looks the way it does):

* Phases are formed in float64 as cycles and reduced to [-1/2, 1/2) before the trigonometry, so
  the fp32 operator is exact to fp32 rounding even for kilometre baselines at the horizon.
* The geometric part G[k, a] = exp(...) is shared by both polarisations; weights and 1/N_A are
  applied to the data (x'_a = w_a x_a / N_A), and an antenna-independent pattern multiplies the
  beamformed field per pixel. Only an antenna-dependent pattern needs one operator per pol.
* Antennas whose weight is zero in every channel and pol are removed from the operator; an
  antenna flagged only in some channels/pols has its data replaced by exact zeros (never 0 * NaN).
* Everything happens in the namespace of the input arrays: CuPy in, CuPy out, no host round trip.
"""
from __future__ import annotations

import logging
import math

import numpy as np

from ..conventions import SIGMA, SPEED_OF_LIGHT_M_S
from . import cost
from ._xp import get_xp
from .pixels import check_lm, n_from_lm
from .products import combine, needs_cross, resolve_products

log = logging.getLogger(__name__)

PRECISIONS = {
    "fp64": (np.float64, np.complex128),
    "fp32": (np.float32, np.complex64),
}
METHODS = ("auto", "direct", "covariance")

# Working-set cap for one chunk of intermediate results (bytes). Bounds host memory on 2-core
# CI machines; on the GPU whole gulps of case P fit well below it.
_CHUNK_BYTES = 256 * 2**20


def _check_precision(precision):
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {tuple(PRECISIONS)}, got {precision!r}")
    return PRECISIONS[precision]


def _as_positions(xyz_m, xp):
    xyz = xp.asarray(xyz_m, dtype=xp.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz_m must be shaped (nant, 3) East/North/Up metres; got shape {tuple(xyz.shape)}")
    if not bool(xp.all(xp.isfinite(xyz))):
        bad = int(xp.argmax(~xp.all(xp.isfinite(xyz), axis=1)))
        raise ValueError(f"xyz_m has a non-finite position for antenna {bad}")
    return xyz


def _as_freqs(freq_hz, xp):
    f = xp.atleast_1d(xp.asarray(freq_hz, dtype=xp.float64))
    if f.ndim != 1:
        raise ValueError(f"freq_hz must be 1-D (nchan,), got shape {tuple(f.shape)}")
    if not bool(xp.all(f > 0)) or not bool(xp.all(xp.isfinite(f))):
        raise ValueError("freq_hz must be finite and positive (Hz)")
    return f


def geometric_phase_cycles(xyz_m, freq_hz, pixels_lm):
    """Fractional phase in cycles, reduced to [-0.5, 0.5]: nu/c * (s_k . r_a), float64.

    Shapes: xyz_m (nant, 3), freq_hz (nchan,), pixels_lm (npix, 2) -> (nchan, npix, nant).
    The reduction happens in float64 before any cast, which is what keeps fp32 exact near the
    horizon and on long baselines.
    """
    xp = get_xp(xyz_m, pixels_lm)
    xyz = _as_positions(xyz_m, xp)
    f = _as_freqs(freq_hz, xp)
    lm = check_lm(pixels_lm)
    n = n_from_lm(lm[:, 0], lm[:, 1])
    # Path difference (metres) for each pixel-antenna pair, float64.
    path = lm[:, 0:1] * xyz[None, :, 0] + lm[:, 1:2] * xyz[None, :, 1] + n[:, None] * xyz[None, :, 2]
    cyc = (f[:, None, None] / SPEED_OF_LIGHT_M_S) * path[None]
    cyc -= xp.rint(cyc)
    return cyc


def geometric_operator(xyz_m, freq_hz, pixels_lm, precision="fp32"):
    """G[c, k, a] = exp(-SIGMA 2 pi i nu_c (s_k . r_a) / c), complex (nchan, npix, nant).

    Unnormalised and unweighted; trigonometry after the float64 range reduction (fp32 for
    precision "fp32": the argument is already within [-pi, pi], so this is exact to fp32).
    """
    rdt, cdt = _check_precision(precision)
    xp = get_xp(xyz_m, pixels_lm)
    ang = (2.0 * math.pi) * geometric_phase_cycles(xyz_m, freq_hz, pixels_lm)
    ang = ang.astype(rdt, copy=False)
    out = xp.empty(ang.shape, dtype=cdt)
    out.real = xp.cos(ang)
    out.imag = xp.sin(ang)
    out.imag *= -SIGMA
    return out


def _broadcast_weights(weights, nchan, nant, npol, xp):
    """Weights as a complex128 (nchan, nant, npol) array; accepts (nant,) or a 3-D broadcastable array."""
    if weights is None:
        return xp.ones((nchan, nant, npol), dtype=xp.complex128)
    w = xp.asarray(weights).astype(xp.complex128)
    if w.ndim == 1:
        w = w[None, :, None]
    if w.ndim != 3:
        raise ValueError("weights must be shaped (nant,) or broadcastable (nchan|1, nant, npol|1); "
                         f"got shape {tuple(w.shape)}")
    try:
        w = xp.broadcast_to(w, (nchan, nant, npol))
    except ValueError:
        raise ValueError(f"weights of shape {tuple(w.shape)} do not broadcast to (nchan, nant, npol) = "
                         f"{(nchan, nant, npol)}") from None
    if not bool(xp.all(xp.isfinite(w))):
        raise ValueError("weights contain NaN or inf; flag an antenna with weight 0 instead")
    return w


def _check_pattern(pattern, nchan, npix, nant, npol, xp):
    if pattern is None:
        return None
    b = xp.asarray(pattern)
    if b.ndim != 4:
        raise ValueError("pattern must be 4-D, broadcastable to (nchan, npix, nant, npol) "
                         "(use 1 for an axis it does not depend on); got shape " + str(tuple(b.shape)))
    ok = all(s in (1, t) for s, t in zip(b.shape, (nchan, npix, nant, npol)))
    if not ok:
        raise ValueError(f"pattern of shape {tuple(b.shape)} does not broadcast to (nchan, npix, nant, npol) = "
                         f"{(nchan, npix, nant, npol)}")
    if not bool(xp.all(xp.isfinite(b))):
        raise ValueError("pattern contains NaN or inf")
    return b


class DFTOperator:
    """The imaging operator D for one array, channel set and pixel set, built once, applied often.

    Parameters
    ----------
    xyz_m : (nant, 3) float      antenna positions, East/North/Up metres (NumPy or CuPy).
    freq_hz : (nchan,) float     channel centre frequencies, Hz.
    pixels_lm : (npix, 2) float  pixel directions (l East, m North); l^2 + m^2 <= 1.
    npol : int                   1 or 2 polarisations (0 = X N-S, 1 = Y E-W).
    weights : complex, optional  (nant,) or broadcastable (nchan|1, nant, npol|1): folded
                                 direction-independent gains (cable, calibration); 0 = flagged.
    pattern : complex, optional  broadcastable (nchan|1, npix, nant|1, npol|1) voltage pattern B.
    precision : "fp32" | "fp64"  operator and arithmetic precision (phases always float64).

    The arrays live where ``xyz_m``/``pixels_lm`` live (pass CuPy arrays to build on the GPU).
    """

    def __init__(self, xyz_m, freq_hz, pixels_lm, *, npol=1, weights=None, pattern=None, precision="fp32"):
        self.rdtype, self.cdtype = _check_precision(precision)
        self.precision = precision
        xp = get_xp(xyz_m, pixels_lm)
        self.xp = xp
        xyz = _as_positions(xyz_m, xp)
        f = _as_freqs(freq_hz, xp)
        lm = check_lm(xp.asarray(pixels_lm))
        if npol not in (1, 2):
            raise ValueError(f"npol must be 1 or 2, got {npol}")
        nchan, nant_in, npix = int(f.shape[0]), int(xyz.shape[0]), int(lm.shape[0])
        self.nchan, self.npol, self.npix, self.nant_in = nchan, npol, npix, nant_in
        self.freq_hz, self.pixels_lm = f, lm

        w = _broadcast_weights(weights, nchan, nant_in, npol, xp)
        live = w != 0
        keep = xp.any(live, axis=(0, 2))
        self.keep_index = xp.flatnonzero(keep)
        self.all_kept = int(self.keep_index.shape[0]) == nant_in
        self.nant = int(self.keep_index.shape[0])
        if self.nant == 0:
            raise ValueError("every antenna is flagged (all weights are 0): there is nothing to image")
        w = w[:, self.keep_index, :]
        live = live[:, self.keep_index, :]
        n_live = live.sum(axis=1)  # (nchan, npol): N_A per channel and pol
        self.n_live = n_live
        self.dead = n_live == 0
        self.any_dead = bool(xp.any(self.dead))  # host flag: result() needs no device sync per image
        if self.any_dead:
            log.warning("%d channel-pol combinations have every antenna flagged; their images are NaN",
                        int(self.dead.sum()))
        scale = xp.where(self.dead, 0.0, 1.0 / xp.maximum(n_live, 1))
        wn = w * scale[:, None, :]
        self.data_weights = wn.astype(self.cdtype)          # (nchan, nant, npol)
        self.data_live = live                                # exact-zero mask for partial flags
        self.partial_flags = not bool(xp.all(live))
        self.xyz_m = xyz[self.keep_index]

        G = geometric_operator(self.xyz_m, f, lm, precision)  # (nchan, npix, nant)
        b = _check_pattern(pattern, nchan, npix, nant_in, npol, xp)
        self.pixel_pattern = None                             # (nchan|1, npix, npol|1) or None
        if b is not None and b.shape[2] != 1:
            b = b[:, :, self.keep_index, :].astype(self.cdtype)
            # One operator per pol: G_p = G * B[..., p].
            Gp = G[:, None, :, :] * xp.moveaxis(b, 3, 1)
            self.G = xp.ascontiguousarray(xp.broadcast_to(Gp, (nchan, npol, npix, self.nant)))
        else:
            self.G = G[:, None]
            if b is not None:
                self.pixel_pattern = b[:, :, 0, :].astype(self.cdtype)
        self.shared_geometry = self.G.shape[1] == 1

    # ------------------------------------------------------------------ data preparation
    def prepare(self, efield):
        """Weighted, flag-zeroed voltages in operator precision, shaped (nchan, npol, nant, ntime).

        efield : complex (ntime, nchan, nant_in, npol) in the operator's namespace.
        """
        xp = self.xp
        if get_xp(efield) is not xp:
            raise TypeError("efield and the operator live in different array namespaces "
                            f"({type(efield).__module__} vs {xp.__name__}); move one of them")
        if efield.ndim != 4:
            raise ValueError("efield must be shaped (ntime, nchan, nant, npol); got shape " + str(tuple(efield.shape)))
        t, c, a, p = efield.shape
        if (c, a, p) != (self.nchan, self.nant_in, self.npol):
            raise ValueError(f"efield shape {tuple(efield.shape)} does not match the operator: expected "
                             f"(ntime, {self.nchan}, {self.nant_in}, {self.npol}) = (ntime, nchan, nant, npol)")
        if efield.dtype.kind != "c":
            raise TypeError(f"efield must be complex, got dtype {efield.dtype}; unpack ci4/ci8 first")
        x = efield if self.all_kept else efield[:, :, self.keep_index, :]
        x = x.astype(self.cdtype, copy=False)
        if self.partial_flags:  # exact zeros first: 0 * NaN would poison the image
            x = xp.where(self.data_live[None], x, 0)
        x = x * self.data_weights[None]
        # (T, C, A, P) -> (C, P, A, T): antennas x time matrices per channel-pol for the GEMMs.
        return xp.ascontiguousarray(x.transpose(1, 3, 2, 0))

    def accumulator(self, products=None, *, remove_autocorr=False, method="auto", ntime_hint=1024):
        """A fresh :class:`ImageAccumulator` for integrations that span several calls."""
        return ImageAccumulator(self, products, remove_autocorr=remove_autocorr, method=method,
                                ntime_hint=ntime_hint)

    def image(self, efield, products=None, *, remove_autocorr=False, method="auto"):
        """One image from all samples of ``efield``: (nchan, nprod, npix), real, operator precision."""
        acc = self.accumulator(products, remove_autocorr=remove_autocorr, method=method,
                               ntime_hint=int(efield.shape[0]))
        acc.add(efield)
        return acc.result()


class ImageAccumulator:
    """Running sums for one integration; ``add`` gulps of voltages, ``result`` the image.

    ``method`` is fixed for the integration ("auto" is resolved from ``ntime_hint``): the direct
    route keeps per-pixel sums of |F|^2 (and F_X F_Y^*), the covariance route keeps X X^H.
    """

    def __init__(self, op: DFTOperator, products=None, *, remove_autocorr=False, method="auto", ntime_hint=1024):
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        self.op = op
        self.products = resolve_products(op.npol, products)
        self.cross = needs_cross(self.products)
        # Correlation blocks (p, q): the auto-pols we need, plus XY if any cross product is asked.
        blocks = []
        if any(p in ("XX", "I", "Q") for p in self.products):
            blocks.append((0, 0))
        if op.npol == 2 and any(p in ("YY", "I", "Q") for p in self.products):
            blocks.append((1, 1))
        if self.cross:
            blocks.append((0, 1))
        self.blocks = blocks
        if method == "auto":
            method = cost.choose_method(int(ntime_hint), op.nant, op.npix, op.npol, len(blocks))
        self.method = method
        self.remove_autocorr = bool(remove_autocorr)
        self.reset()

    def reset(self):
        xp, op = self.op.xp, self.op
        self.ntime = 0
        if self.method == "covariance":
            pa = op.npol * op.nant
            self._R = xp.zeros((op.nchan, pa, pa), dtype=op.cdtype)
        else:
            self._S = xp.zeros((op.nchan, len(self.blocks), op.npix), dtype=op.cdtype)
            self._auto = xp.zeros((op.nchan, len(self.blocks), op.nant), dtype=op.cdtype)

    def add(self, efield):
        """Accumulate complex voltages (ntime, nchan, nant, npol) into the integration."""
        if efield.shape[0] == 0:
            return
        x = self.op.prepare(efield)  # (C, P, A, T)
        self.ntime += int(x.shape[-1])
        if self.method == "covariance":
            self._add_covariance(x)
        else:
            self._add_direct(x)

    def _add_covariance(self, x):
        xp = self.op.xp
        c, p, a, t = x.shape
        y = x.reshape(c, p * a, t)
        self._R += xp.matmul(y, xp.conj(y).swapaxes(1, 2))

    def _add_direct(self, x):
        xp, op = self.op.xp, self.op
        c, p, a, t = x.shape
        itemsize = np.dtype(op.cdtype).itemsize
        # Chunk channels and time so one F block stays under _CHUNK_BYTES.
        per_chan_t = op.npix * p * itemsize
        tchunk = max(1, min(t, _CHUNK_BYTES // max(1, per_chan_t)))
        cchunk = max(1, min(c, _CHUNK_BYTES // max(1, per_chan_t * tchunk)))
        for c0 in range(0, c, cchunk):
            cs = slice(c0, min(c, c0 + cchunk))
            for t0 in range(0, t, tchunk):
                xs = x[cs, :, :, t0:t0 + tchunk]
                if op.shared_geometry:
                    nt = xs.shape[-1]
                    rhs = xs.transpose(0, 2, 1, 3).reshape(xs.shape[0], a, p * nt)
                    F = xp.matmul(op.G[cs, 0], rhs).reshape(xs.shape[0], op.npix, p, nt)
                    F = F.transpose(0, 2, 1, 3)  # (c, P, K, t)
                else:
                    F = xp.matmul(op.G[cs], xs)  # (c, P, K, A) @ (c, P, A, t)
                for i, (pp, qq) in enumerate(self.blocks):
                    if pp == qq:
                        Fp = F[:, pp]
                        self._S[cs, i] += (Fp.real ** 2 + Fp.imag ** 2).sum(axis=-1)
                    else:
                        self._S[cs, i] += (F[:, pp] * xp.conj(F[:, qq])).sum(axis=-1)
        if self.remove_autocorr:
            for i, (pp, qq) in enumerate(self.blocks):
                self._auto[:, i] += (x[:, pp] * xp.conj(x[:, qq])).sum(axis=-1)

    def result(self):
        """The image (nchan, nprod, npix), real, in the operator's precision; NaN where all antennas of a
        contributing channel-pol are flagged. Raises if nothing was accumulated."""
        if self.ntime == 0:
            raise ValueError("no samples were accumulated: cannot form an image from zero time samples")
        xp, op = self.op.xp, self.op
        if self.method == "covariance":
            corr = self._image_covariance()
        else:
            corr = self._S
            if self.remove_autocorr:
                corr = corr - self._autocorr_term(self._auto)
        corr = corr / self.ntime  # (C, nblk, K)
        if op.pixel_pattern is not None:
            B = op.pixel_pattern  # (C|1, K, P|1)
            bw = []
            for pp, qq in self.blocks:
                bp = B[:, :, min(pp, B.shape[2] - 1)]
                bq = B[:, :, min(qq, B.shape[2] - 1)]
                bw.append(bp * xp.conj(bq))
            corr = corr * xp.stack(bw, axis=1)
        get = {blk: corr[:, i] for i, blk in enumerate(self.blocks)}
        xx = get.get((0, 0))
        yy = get.get((1, 1))
        xy = get.get((0, 1))
        out = combine(self.products, xx.real if xx is not None else None,
                      yy.real if yy is not None else None, xy).astype(op.rdtype, copy=False)
        if op.any_dead:
            for k, name in enumerate(self.products):
                pols = {"XX": (0,), "YY": (1,)}.get(name, tuple(range(op.npol)))
                bad = xp.any(op.dead[:, list(pols)], axis=1)
                out[bad, k, :] = xp.nan
        return out

    def _autocorr_term(self, auto):
        """sum_a D^p_ka conj(D^q_ka) sum_t x_ap conj(x_aq): (C, nblk, K); data already weighted."""
        xp, op = self.op.xp, self.op
        if op.shared_geometry:  # |G| = 1: the term is the same for every pixel
            return xp.broadcast_to(auto.sum(axis=-1)[:, :, None], auto.shape[:2] + (op.npix,))
        terms = []
        for i, (pp, qq) in enumerate(self.blocks):
            gg = op.G[:, pp] * xp.conj(op.G[:, qq])  # (C, K, A)
            terms.append(xp.matmul(gg, auto[:, i, :, None])[..., 0])
        return xp.stack(terms, axis=1)

    def _image_covariance(self):
        xp, op = self.op.xp, self.op
        R = self._R
        a = op.nant
        if self.remove_autocorr:
            R = R.copy()
            idx = xp.arange(R.shape[-1])
            R[:, idx, idx] = 0
            if len(self.blocks) and op.npol == 2:
                # the X-Y diagonal (same antenna, cross pol) is an autocorrelation term as well
                R[:, idx[:a], idx[:a] + a] = 0
                R[:, idx[:a] + a, idx[:a]] = 0
        nblk = len(self.blocks)
        itemsize = np.dtype(op.cdtype).itemsize
        cchunk = max(1, min(op.nchan, _CHUNK_BYTES // max(1, op.npix * nblk * a * itemsize)))
        out = xp.empty((op.nchan, nblk, op.npix), dtype=op.cdtype)
        for c0 in range(0, op.nchan, cchunk):
            cs = slice(c0, min(op.nchan, c0 + cchunk))
            Rc = R[cs]
            nc = Rc.shape[0]
            if op.shared_geometry:
                G = op.G[cs, 0]  # (c, K, A)
                rhs = xp.concatenate([Rc[:, pp * a:(pp + 1) * a, qq * a:(qq + 1) * a] for pp, qq in self.blocks],
                                     axis=2)  # (c, A, nblk*A)
                M = xp.matmul(G, rhs).reshape(nc, op.npix, nblk, a)
                out[cs] = (M * xp.conj(G)[:, :, None, :]).sum(axis=-1).transpose(0, 2, 1)
            else:
                for i, (pp, qq) in enumerate(self.blocks):
                    M = xp.matmul(op.G[cs, pp], Rc[:, pp * a:(pp + 1) * a, qq * a:(qq + 1) * a])
                    out[cs, i] = (M * xp.conj(op.G[cs, qq])).sum(axis=-1)
        return out


def dirty_image(efield, xyz_m, freq_hz, pixels_lm, *, remove_autocorr=False, method="auto",
                precision="fp32", products=None, weights=None, pattern=None):
    """E-field DFT image: the time mean of |sum_a D[k, a] x_a(t)|^2 (see module docstring).

    Parameters
    ----------
    efield : complex (ntime, nchan, nant, npol), NumPy or CuPy; calibrated voltages.
    xyz_m : (nant, 3) East/North/Up metres.   freq_hz : (nchan,) Hz.
    pixels_lm : (npix, 2) direction cosines (l East, m North); l^2 + m^2 > 1 is a ValueError.
    remove_autocorr : subtract the autocorrelation term exactly.
    method : "direct" (D X then |.|^2), "covariance" (Re diag(D R D^H)), or "auto" (cheaper by
             :func:`bf_epic_blocks.imaging.cost.choose_method`).
    precision : "fp32" (fp32 operator and data, float64 phases) or "fp64".
    products : None (npol=1: XX; npol=2: XX, YY), "stokes" (I, Q, U, V), "linear", "full", or
               a list of names from XX, YY, XY, YX, XYi, YXi, I, Q, U, V.
    weights : complex (nant,) or (nchan|1, nant, npol|1); 0 drops the antenna from the operator.
    pattern : complex (nchan|1, npix, nant|1, npol|1) voltage pattern folded into D.

    Returns
    -------
    float (nchan, nprod, npix) in the namespace of ``efield``, fp32 or fp64 per ``precision``.
    """
    xp = get_xp(efield)
    if efield.ndim != 4:
        raise ValueError("efield must be shaped (ntime, nchan, nant, npol); got shape " + str(tuple(efield.shape)))
    op = DFTOperator(xp.asarray(xyz_m), xp.asarray(freq_hz), xp.asarray(pixels_lm), npol=int(efield.shape[3]),
                     weights=None if weights is None else xp.asarray(weights),
                     pattern=None if pattern is None else xp.asarray(pattern), precision=precision)
    return op.image(efield, products, remove_autocorr=remove_autocorr, method=method)
