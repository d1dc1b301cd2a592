"""The exact direct-Fourier-transform E-field imager (NumPy or CuPy).

Conventions (docs/CONVENTIONS.md, bf_epic_blocks.conventions): positions East/North/Up metres,
pixels (l East, m North), n = sqrt(1 - l^2 - m^2) computed in float64 (full n: the data are not
phased to any centre), sign SIGMA = +1 so

    D[k, a] = w_a * B_a(s_k) * exp(-2 pi i nu (l_k x_a + m_k y_a + n_k z_a) / c) / N_A

with w_a the folded direction-independent weight (0 = flagged: the antenna is dropped), B_a the
optional voltage pattern, N_A the unflagged antennas of that channel and polarisation. The image is

    I_k = (1/T) sum_t |sum_a D[k, a] x_a(t)|^2        (cross products: F_X F_Y^*)

Two exact routes give it: "direct" (F = D X, then |F|^2 averaged over time) and "covariance"
(R = X X^H / T, then Re diag(D R D^H)); "auto" is the cheaper by :mod:`.cost`'s counts, and the
accuracy knob ``tolerance`` picks route and precision together (:func:`.plan.resolve` decides both).

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
from ._xp import get_xp, host_all, to_numpy
from .fused import FUSED, FusedOperator
from .gemm import (FP16, PRECISIONS, STACKED, check_precision, cmatmul, int_gram, pow2_scale, split_tf32, stack_operator,
                   stack_rhs, stacked_matmul)
from .graphs import GraphCache
from .layout import cov_rhs, direct_rhs, gram_rows
from .reduce import block_corr, group_power, product_coefficients, products_from_blocks, row_dot
from .pixels import check_lm, n_from_lm
from .products import needs_cross, resolve_products

log = logging.getLogger(__name__)

METHODS = ("auto", "direct", "covariance")

# Working-set cap for one chunk of intermediate results (bytes): bounds host memory on 2-core CI
# machines; on the GPU a whole gulp of case P (F is 840 MB for the direct route) is one chunk.
_CHUNK_BYTES = {"numpy": 256 * 2**20, "cupy": 2 * 2**30}


def _check_precision(precision):
    """(real, complex) dtypes of a precision name, wherever it can run (see :mod:`.gemm`)."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {tuple(PRECISIONS)}, got {precision!r}")
    return PRECISIONS[precision][:2]


def _as_positions(xyz_m, xp):
    xyz = xp.asarray(xyz_m, dtype=xp.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz_m must be shaped (nant, 3) East/North/Up metres; got shape {tuple(xyz.shape)}")
    if not host_all(xp.isfinite(xyz)):
        bad = int(np.argmax(~np.all(np.isfinite(to_numpy(xyz)), axis=1)))
        raise ValueError(f"xyz_m has a non-finite position for antenna {bad}")
    return xyz


def _as_freqs(freq_hz, xp):
    f = xp.atleast_1d(xp.asarray(freq_hz, dtype=xp.float64))
    if f.ndim != 1:
        raise ValueError(f"freq_hz must be 1-D (nchan,), got shape {tuple(f.shape)}")
    if not host_all(f > 0) or not host_all(xp.isfinite(f)):
        raise ValueError("freq_hz must be finite and positive (Hz)")
    return f


def _checked_geometry(xyz_m, freq_hz, pixels_lm):
    """Positions, frequencies and pixels checked and ``n`` formed on the host (small arrays; on a GPU
    each check would be a kernel to compile on a machine with an empty kernel cache, ~0.1-0.2 s each):
    (xyz (nant, 3), f (nchan,), lm (npix, 2), n (npix,)) as float64 NumPy arrays."""
    xyz = _as_positions(to_numpy(xyz_m), np)
    f = _as_freqs(to_numpy(freq_hz), np)
    lm = check_lm(to_numpy(pixels_lm))
    return xyz, f, lm, n_from_lm(lm[:, 0], lm[:, 1])


def _path_m(xyz, lm, n):
    """Path difference (metres) for each pixel-antenna pair, float64 (npix, nant)."""
    return lm[:, 0:1] * xyz[None, :, 0] + lm[:, 1:2] * xyz[None, :, 1] + n[:, None] * xyz[None, :, 2]


def geometric_phase_cycles(xyz_m, freq_hz, pixels_lm):
    """Fractional phase in cycles, reduced to [-0.5, 0.5]: nu/c * (s_k . r_a), float64.

    Shapes: xyz_m (nant, 3), freq_hz (nchan,), pixels_lm (npix, 2) -> (nchan, npix, nant), on the
    device of ``xyz_m``/``pixels_lm``. The reduction happens in float64 before any cast, which is
    what keeps fp32 exact near the horizon and on long baselines.
    """
    xp = get_xp(xyz_m, pixels_lm)
    xyz, f, lm, n = _checked_geometry(xyz_m, freq_hz, pixels_lm)
    path = xp.asarray(_path_m(xyz, lm, n))
    cyc = xp.asarray(f[:, None, None] / SPEED_OF_LIGHT_M_S) * path[None]
    cyc -= xp.rint(cyc)
    return cyc


#: G from the path on a GPU in one kernel: the same float64 steps as :func:`geometric_operator`'s
#: array form (cycles = nu/c * path, minus rint, times 2 pi: 6.283185307179586 is 2.0 * math.pi),
#: then cos/sin in the operator's type
_GEOM_SRC = {
    "complex64": ("float64 path, float64 fc, float32 sig", "complex64 out",
                  "double cyc = fc * path; cyc -= rint(cyc); const float a = (float)(6.283185307179586 * cyc);"
                  "out = complex<float>(cosf(a), sinf(a) * sig);"),
    "complex128": ("float64 path, float64 fc, float64 sig", "complex128 out",
                   "double cyc = fc * path; cyc -= rint(cyc); const double a = 6.283185307179586 * cyc;"
                   "out = complex<double>(cos(a), sin(a) * sig);"),
}
_GEOM_KERNELS = {}


def geometric_operator(xyz_m, freq_hz, pixels_lm, precision="fp32"):
    """G[c, k, a] = exp(-SIGMA 2 pi i nu_c (s_k . r_a) / c), complex (nchan, npix, nant).

    Unnormalised and unweighted; trigonometry after the float64 range reduction (fp32 for
    precision "fp32": the argument is already within [-pi, pi], so this is exact to fp32). On a GPU
    the whole (nchan, npix, nant) array is one kernel (one compile on a new machine, not eight).
    """
    _check_precision(precision)
    xp = get_xp(xyz_m, pixels_lm)
    return _geometric_from_host(xp, *_checked_geometry(xyz_m, freq_hz, pixels_lm), precision)


def _geometric_from_host(xp, xyz, f, lm, n, precision):
    """:func:`geometric_operator` from geometry already checked on the host (:func:`_checked_geometry`'s
    float64 NumPy arrays), made in ``xp``: the operator's construction passes its own checked copies
    rather than device ones that would be copied back and checked again."""
    rdt, cdt = _check_precision(precision)
    path = _path_m(xyz, lm, n)                                                    # (npix, nant) float64
    if xp.__name__ == "cupy":
        key = np.dtype(cdt).name
        if key not in _GEOM_KERNELS:
            _GEOM_KERNELS[key] = xp.ElementwiseKernel(*_GEOM_SRC[key], f"bf_geometric_{key}")
        fc = xp.asarray(f / SPEED_OF_LIGHT_M_S)[:, None, None]
        out = xp.empty((f.shape[0], lm.shape[0], xyz.shape[0]), dtype=cdt)
        _GEOM_KERNELS[key](xp.asarray(path)[None], fc, float(-SIGMA), out)
        return out
    cyc = (f[:, None, None] / SPEED_OF_LIGHT_M_S) * path[None]
    cyc -= np.rint(cyc)
    ang = ((2.0 * math.pi) * cyc).astype(rdt, copy=False)
    out = np.empty(ang.shape, dtype=cdt)
    out.real = np.cos(ang)
    out.imag = np.sin(ang)
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
    if not host_all(xp.isfinite(w)):
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
    if not host_all(xp.isfinite(b)):
        raise ValueError("pattern contains NaN or inf")
    return b


class _Selection:
    """What an operator keeps of the input: channels, antennas and live (unflagged) antenna-pols,
    as host/NumPy-or-CuPy index arrays for the layout kernels (:mod:`.layout`)."""

    def __init__(self, xp, chan, ant, live, nchan, nant):
        self.xp = xp
        self.chan = chan                      # None (all) or index array of live channels
        self.ant = ant                        # None (all) or index array of kept antennas
        self.live = live                      # None (nothing flagged) or (C', A', P) mask
        self.chan_list = None if chan is None else [int(v) for v in (chan.get() if hasattr(chan, "get") else chan)]
        self.ant_list = None if ant is None else [int(v) for v in (ant.get() if hasattr(ant, "get") else ant)]
        self.nchan, self.nant = nchan, nant
        self._dev = {}

    def device_index(self, which, n):
        if which not in self._dev:
            idx = getattr(self, which)
            self._dev[which] = (self.xp.arange(n, dtype=self.xp.int32) if idx is None
                                else self.xp.asarray(idx, dtype=self.xp.int32))
        return self._dev[which]

    def device_live(self, pols, C, A):
        key = ("live", tuple(pols))
        if key not in self._dev:
            xp = self.xp
            self._dev[key] = (xp.ones((C, A, len(pols)), xp.uint8) if self.live is None
                              else xp.ascontiguousarray(self.live[:, :, list(pols)].astype(xp.uint8)))
        return self._dev[key]


def _is_int_pairs(efield):
    """Integer voltages as (..., 2) (re, im) pairs: int8/int16 with a trailing axis of length 2."""
    return efield.dtype.kind == "i" and efield.ndim == 5 and efield.shape[-1] == 2


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
    graphs : bool                on the GPU, replay repeated :meth:`image` calls as CUDA graphs
                                 (:mod:`.graphs`; which calls: see :meth:`image`); default True.
    precision : str              GEMM precision, one of :data:`.gemm.PRECISIONS` (fp64, fp32,
                                 tf32x3, fp16x3, tf32, fp16, bf16, i8x2, i8x3; all but fp64 and fp32
                                 need a GPU, and i8x2/i8x3 4-bit integer voltages; to choose one by
                                 accuracy, see :func:`.plan.resolve`). Phases are
                                 always formed in float64; the operator is stored as complex64
                                 (complex128 for fp64) and rounded by the GEMM as the mode says.

    The arrays live where ``xyz_m``/``pixels_lm`` live (pass CuPy arrays to build on the GPU).
    Voltages given to :meth:`image` may be complex (ntime, nchan, nant, npol) or integer pairs
    (ntime, nchan, nant, npol, 2) int8 (re, im), as unpacked from ci4/ci8: the covariance route
    then forms X X^H exactly in integer arithmetic and applies the weights to it afterwards.
    """

    def __init__(self, xyz_m, freq_hz, pixels_lm, *, npol=1, weights=None, pattern=None, precision="fp32",
                 graphs=True):
        xp = get_xp(xyz_m, pixels_lm)
        # CUDA graphs for repeated image() calls (integer F-engine voltages, calibrated complex ones): see .graphs
        self.graphs = GraphCache() if graphs and xp.__name__ == "cupy" else None
        self.rdtype, self.cdtype = check_precision(precision, xp)
        self.precision = precision
        self.xp = xp
        # The bookkeeping below (checks, flags, indices, norms) is on small arrays and runs on the host;
        # its results go to the operator's device at the end. On a GPU each of these steps would be a
        # kernel of its own, and on a machine with an empty kernel cache each kernel costs a ~0.1-0.2 s
        # compile (tools/cold_start.py lists them).
        hxyz, hf, hlm, hn = _checked_geometry(xyz_m, freq_hz, pixels_lm)
        if npol not in (1, 2):
            raise ValueError(f"npol must be 1 or 2, got {npol}")
        nchan, nant_in, npix = int(hf.shape[0]), int(hxyz.shape[0]), int(hlm.shape[0])
        self.nchan, self.npol, self.npix, self.nant_in = nchan, npol, npix, nant_in
        self.freq_hz, self.pixels_lm = xp.asarray(hf), xp.asarray(hlm)

        w = _broadcast_weights(None if weights is None else to_numpy(weights), nchan, nant_in, npol, np)
        live = w != 0
        keep_index = np.flatnonzero(live.any(axis=(0, 2)))
        self.all_kept = int(keep_index.shape[0]) == nant_in
        self.nant = int(keep_index.shape[0])
        if self.nant == 0:
            raise ValueError("every antenna is flagged (all weights are 0): there is nothing to image")
        w = w[:, keep_index, :]
        live = live[:, keep_index, :]
        n_live = live.sum(axis=1)  # (nchan, npol): N_A per channel and pol
        dead = n_live == 0
        self.any_dead = bool(dead.any())  # host flag: result() needs no device sync per image
        if self.any_dead:
            log.warning("%d channel-pol combinations have every antenna flagged; their images are NaN",
                        int(dead.sum()))
        # Channels with every antenna of every pol flagged cost nothing: they are left out of the
        # GEMMs and come back as NaN images.
        chan_live = ~dead.all(axis=1)
        chan_index = None if chan_live.all() else np.flatnonzero(chan_live)
        if chan_index is not None and int(chan_index.shape[0]) == 0:
            raise ValueError("every channel has every antenna flagged: there is nothing to image")
        self.partial_flags = not bool(live.all())
        self.unit_weights = bool(((w == 0) | (w == 1)).all())
        live_sel = live if chan_index is None else live[chan_index]
        # fp16 covariance operands: R' = w R w^H / T <= 2 * 127^2 * max|w|^2, scaled by a power of two
        # into fp16's range (chosen once, on the host, from the weights)
        wmax = float(np.abs(w).max())
        self.cov_scale = 2.0 ** -math.ceil(math.log2(wmax * wmax)) if self.precision in FP16 and wmax > 0 else 1.0
        hxyz_kept = hxyz[keep_index]
        # 1/N_A is applied to the image (norm), not to the data, so that integer voltages with
        # unit weights stay integers (exact in fp16/tf32 and in integer covariances).
        norm = np.where(dead, 0.0, 1.0 / np.maximum(n_live, 1))                # (nchan, npol) float64

        self.keep_index = xp.asarray(keep_index)
        self.n_live = xp.asarray(n_live)
        self.dead = xp.asarray(dead)
        self.chan_index = None if chan_index is None else xp.asarray(chan_index)
        self.norm = xp.asarray(norm)
        self.data_weights = xp.asarray(w.astype(self.cdtype))                    # (nchan, nant, npol)
        self.weights128 = xp.asarray(w)                                          # for integer covariances
        self.data_live = xp.asarray(live)
        self.xyz_m = xp.asarray(hxyz_kept)
        live_sel = xp.asarray(live_sel) if self.partial_flags else None
        self.sel = _Selection(xp, self.chan_index, None if self.all_kept else self.keep_index, live_sel,
                              nchan, nant_in)

        G = _geometric_from_host(xp, hxyz_kept, hf, hlm, hn, "fp64" if precision == "fp64" else "fp32")  # (nchan, npix, nant)
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
        self._derived = {}
        #: the fused integer modes' operator (:mod:`.fused`), built now: never inside a graph capture
        self.fused = None
        if precision in FUSED:
            if not self.shared_geometry:
                raise ValueError(f"precision {precision!r} needs one operator for both pols; an antenna-dependent "
                                 "pattern makes one per pol: use 'fp16x3' or 'fp32'")
            self.fused = FusedOperator(self, precision)
        #: (nant_kept, npol) NaN/Inf samples zeroed so far in complex input (device array), or None
        self.nonfinite_counts = None

    # ------------------------------------------------------------------ operator forms
    def live_G(self, pol):
        """Operator of pol ``pol`` (0 when shared) for the live channels: (nchan_live, npix, nant)."""
        key = ("G", pol)
        if key not in self._derived:
            g = self.G[:, 0 if self.shared_geometry else pol]
            if self.chan_index is not None:
                g = g[self.chan_index]
            self._derived[key] = self.xp.ascontiguousarray(g)
        return self._derived[key]

    @property
    def stacked(self) -> bool:
        """Whether GEMMs run in the stacked real form (:mod:`.gemm`): the tensor-core modes on the GPU.
        (fp32 as a stacked real SGEMM is slower than cuBLAS' CGEMM, so fp32 and fp64 stay complex.)"""
        return self.precision in STACKED and self.xp.__name__ == "cupy"

    def _operator_parts(self, pol, cs):
        """The operator in the form the precision's GEMM takes, for a channel slice of the live channels."""
        if self.stacked:
            key = ("stack", pol)
            if key not in self._derived:
                self._derived[key] = stack_operator(self.live_G(pol), self.precision)
            return [p[cs] for p in self._derived[key]]
        return [self.live_G(pol)[cs]]

    def field_gemm(self, pol, rhs, cs=slice(None), *, exact=False):
        """D_pol @ rhs for live channels ``cs``: rhs complex (c, nant, n).

        Returns ``(F, stacked, scale)``: F complex (c, npix, n), or float32 (c, 2, npix, n) [re; im]
        in the stacked (tensor-core) modes; products of F must be multiplied by ``scale**2``
        (a device scalar, or None for 1) -- fp16 operands are scaled by a power of two into range.
        ``exact``: rhs is exact in the mode (integer voltages with unit weights).
        """
        parts = self._operator_parts(pol, cs)
        if not self.stacked:
            return cmatmul(parts[0], rhs, self.precision), False, None
        s = pow2_scale(rhs) if self.precision in FP16 else None
        F = stacked_matmul(parts, stack_rhs(rhs, self.precision, s), self.precision, b_exact=exact)
        return F.reshape(F.shape[0], 2, F.shape[1] // 2, F.shape[2]), True, (None if s is None else 1.0 / s)

    def field_gemm_parts(self, pol, parts, cs=slice(None), *, exact=False):
        """D_pol @ rhs with rhs already in the GEMM's operand form: a list of stacked parts (tensor-core
        modes; [hi, lo] for tf32x3; one concatenated array for fp16x3) or [complex rhs]. Returns (F, stacked) as :meth:`field_gemm`."""
        ops = self._operator_parts(pol, cs)
        if not self.stacked:
            return cmatmul(ops[0], parts[0], self.precision), False
        if self.precision == "tf32x3" and len(parts) == 1 and not exact:
            parts = list(split_tf32(parts[0]))     # (fp16x3 parts come split from cov_rhs)
        F = stacked_matmul(ops, parts, self.precision, b_exact=exact or len(parts) == 1)
        return F.reshape(F.shape[0], 2, F.shape[1] // 2, F.shape[2]), True

    def field_gemm_complex(self, pol, rhs, cs=slice(None), *, exact=False):
        """As :meth:`field_gemm`, always complex (c, npix, n) with the scale applied (rare paths)."""
        F, stacked, scale = self.field_gemm(pol, rhs, cs, exact=exact)
        if stacked:
            F = F[:, 0] + 1j * F[:, 1]
        return F if scale is None else F * scale

    def chunk_bytes(self):
        return _CHUNK_BYTES.get(self.xp.__name__, _CHUNK_BYTES["numpy"])

    # ------------------------------------------------------------------ data preparation
    def _check_efield(self, efield):
        xp = self.xp
        if get_xp(efield) is not xp:
            raise TypeError("efield and the operator live in different array namespaces "
                            f"({type(efield).__module__} vs {xp.__name__}); move one of them")
        ints = _is_int_pairs(efield)
        if efield.ndim != (5 if ints else 4):
            raise ValueError("efield must be shaped (ntime, nchan, nant, npol) complex, or (ntime, nchan, nant, "
                             "npol, 2) integer (re, im) pairs; got shape " + str(tuple(efield.shape))
                             + f" dtype {efield.dtype}")
        t, c, a, p = efield.shape[:4]
        if (c, a, p) != (self.nchan, self.nant_in, self.npol):
            raise ValueError(f"efield shape {tuple(efield.shape)} does not match the operator: expected "
                             f"(ntime, {self.nchan}, {self.nant_in}, {self.npol}) = (ntime, nchan, nant, npol)")
        if not ints and efield.dtype.kind != "c":
            raise TypeError(f"efield must be complex or integer (re, im) pairs, got dtype {efield.dtype} with "
                            f"shape {tuple(efield.shape)}; unpack ci4/ci8 first")
        return ints

    def _select(self, x):
        """Kept antennas and live channels of (T, C, A, P[, 2]) data."""
        if not self.all_kept:
            x = x[:, :, self.keep_index]
        if self.chan_index is not None:
            x = x[:, self.chan_index]
        return x

    def prepare(self, efield):
        """Weighted, flag-zeroed complex voltages, shaped (nchan_live, npol, nant, ntime).

        efield : complex (ntime, nchan, nant_in, npol) or integer pairs (..., 2), in the operator's
        namespace. The weights are applied, 1/N_A is not (see :attr:`norm`).
        """
        xp = self.xp
        ints = self._check_efield(efield)
        x = self._select(efield)
        if ints:
            x = x[..., 0].astype(self.rdtype) + 1j * x[..., 1].astype(self.rdtype)
        else:
            # NaN/Inf samples count as flagged for that sample: zeroed (never 0 * NaN) and counted per
            # antenna-pol on the device (no host sync here; dirty_image reports them)
            bad = ~xp.isfinite(x)
            cnt = bad.sum(axis=(0, 1))
            if self.nonfinite_counts is None:
                self.nonfinite_counts = xp.zeros(cnt.shape, cnt.dtype)
            self.nonfinite_counts += cnt   # in place: a replayed CUDA graph adds into the same array
            x = xp.where(bad, xp.zeros((), x.dtype), x)
        x = x.astype(self.cdtype, copy=False)
        live, w = self.data_live, self.data_weights
        if self.chan_index is not None:
            live, w = live[self.chan_index], w[self.chan_index]
        if self.partial_flags:  # exact zeros first: 0 * NaN would poison the image
            x = xp.where(live[None], x, 0)
        if not self.unit_weights:
            x = x * w[None]
        # (T, C, A, P) -> (C, P, A, T): antennas x time matrices per channel-pol for the GEMMs.
        return xp.ascontiguousarray(x.transpose(1, 3, 2, 0))

    # ------------------------------------------------------------------ imaging
    def accumulator(self, products=None, *, remove_autocorr=False, method="auto", ntime_hint=1024):
        """A fresh :class:`ImageAccumulator` for integrations that span several calls.

        ``method`` "auto" is resolved by :func:`.plan.resolve` for this operator's problem with
        ``ntime_hint`` samples per image (the cheaper route; the direct one for a fused mode)."""
        if method == "auto":
            method = self.route(products, ntime_hint)
        return ImageAccumulator(self, products, remove_autocorr=remove_autocorr, method=method,
                                ntime_hint=ntime_hint)

    def route(self, products=None, ntime=1024) -> str:
        """The route ('direct' | 'covariance') :func:`.plan.resolve` picks for this operator's precision,
        the products and ``ntime`` samples per image."""
        from .plan import Problem, resolve
        nchan = self.nchan if self.chan_index is None else int(self.chan_index.shape[0])
        problem = Problem(self.npix, self.nant, max(1, int(ntime)), max(1, nchan), self.npol, products)
        return resolve(None, device=self.xp, problem=problem, precision=self.precision).method

    def _cached_accumulator(self, products, remove_autocorr, method, ntime):
        """Accumulators for :meth:`image`, made once per (products, autocorr, route): building one makes
        small device arrays, which would cost host time on every gulp."""
        key = (tuple(resolve_products(self.npol, products)), bool(remove_autocorr), method,
               int(ntime) if method == "auto" else None)
        cache = self._derived.setdefault("accumulators", {})
        if key not in cache:
            cache[key] = self.accumulator(products, remove_autocorr=remove_autocorr, method=method, ntime_hint=ntime)
        return cache[key]

    def image(self, efield, products=None, *, remove_autocorr=False, method="auto", accumulate=None,
              decode=None, static_out=False):
        """Images of ``efield``.

        accumulate : None -> one image from all samples, (nchan, nprod, npix); an integer N ->
            one image per N consecutive samples, (ntime // N, nchan, nprod, npix), computed in one
            batched pass (direct route: one GEMM for the whole gulp, |F|^2 summed per group);
            trailing samples that do not fill an integration are not imaged.
        Real images in the operator's precision (float32, float64 for fp64).

        On the GPU, voltages of a shape seen before are imaged by replaying a CUDA graph of the first
        such call (:mod:`.graphs`; ``graphs=False`` at construction turns this off): integer voltages on
        either route, complex voltages on the covariance route with ``accumulate=None`` (there, replays
        were tested equal to eager calls bitwise, fp32 and fp16x3; on the direct route they were seen
        not to be). For complex voltages this is a trade: the gulp is first copied into the graph's
        input (case P: 67 MB, which makes a loop of calls on an idle host a few per cent slower than eager
        ones), while the host's issue work falls from ~1.3 ms to one launch, which is what a pipeline
        whose block threads share the host needs. ``graphs=False`` keeps every call eager.

        decode : None, or a function turning ``efield`` (e.g. packed ci4 bytes) into the integer
            (re, im) pairs to image; inside the graph on replays (the packed bytes are what is copied
            in, and the host issues one call fewer).
        static_out : on a graph replay, return the graph's own output (no copy); it is overwritten by
            the operator's next call, so use it on the same stream before then.
        """
        if accumulate is not None:
            n = int(accumulate) if isinstance(accumulate, (int, np.integer)) or (
                isinstance(accumulate, float) and accumulate.is_integer()) else None
            if n is None or n < 1:
                raise ValueError(f"accumulate must be a positive integer number of samples, got {accumulate!r}")
            accumulate = n
        # (one covariance image per N samples builds accumulators, with host->device copies, on
        # every call: not capturable, and not the fast route for short integrations anyway)
        if self._replays(efield, decode, products, remove_autocorr, method, accumulate):
            if decode is None:   # (with decode: checked as decoded on the first, eager, call; the key
                self._check_efield(efield)   # fixes the shape after that)
            key = (tuple(efield.shape), str(efield.dtype), tuple(resolve_products(self.npol, products)),
                   bool(remove_autocorr), method, accumulate, decode)
            caches = [self._derived, self._derived.setdefault("accumulators", {})]

            def fn(x):
                if decode is not None:
                    x = decode(x)
                    if not _is_int_pairs(x):
                        raise TypeError("decode must give integer (re, im) pairs shaped (ntime, nchan, nant, npol, 2)")
                return self._image(x, products, remove_autocorr, method, accumulate)
            return self.graphs.call(key, fn, efield, caches, static_out=static_out)
        if decode is not None:
            efield = decode(efield)
        return self._image(efield, products, remove_autocorr, method, accumulate)

    def _replays(self, efield, decode, products, remove_autocorr, method, accumulate):
        """Whether this :meth:`image` call is served by a CUDA graph (which calls are: see there)."""
        if self.graphs is None:
            return False
        if decode is not None or _is_int_pairs(efield):
            return accumulate is None or self._cached_accumulator(
                products, remove_autocorr, method, accumulate).method == "direct"
        return (accumulate is None and getattr(efield, "ndim", 0) == 4 and efield.dtype.kind == "c"
                and self._cached_accumulator(products, remove_autocorr, method,
                                             int(efield.shape[0])).method == "covariance")

    def _image(self, efield, products, remove_autocorr, method, accumulate):
        ntime = int(efield.shape[0])
        if accumulate is None:
            acc = self._cached_accumulator(products, remove_autocorr, method, ntime)
            acc.reset()
            acc.add(efield)
            out = acc.result()
            acc.reset()
            return out
        return self._cached_accumulator(products, remove_autocorr, method, accumulate).images(efield, accumulate)


class ImageAccumulator:
    """Running sums for one integration; ``add`` gulps of voltages, ``result`` the image.

    ``method`` is fixed for the integration ("auto" is resolved from ``ntime_hint``): the direct
    route keeps per-pixel sums of |F|^2 (and F_X F_Y^*), the covariance route keeps X X^H (only
    the polarisation blocks the products need; exactly, in integers, for integer voltages).
    :meth:`images` makes one image per N samples of a gulp in one batched pass.
    """

    def __init__(self, op: DFTOperator, products=None, *, remove_autocorr=False, method="auto", ntime_hint=1024):
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        self.op = op
        xp = op.xp
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
        self.pols = sorted({p for b in blocks for p in b})
        if op.precision in FUSED:
            # the fused integer modes are a direct-route kernel for the pols' own powers
            if method == "covariance" or self.cross:
                raise ValueError(f"precision {op.precision!r} images the direct route's XX/YY powers (products "
                                 f"XX, YY, I, Q); asked for method={method!r}, products {self.products}: "
                                 "use 'fp16x3' or 'fp32' for the covariance route or cross-pol products")
            method = "direct"
        if method == "auto":
            method = cost.choose_method(int(ntime_hint), op.nant, op.npix, op.npol, len(blocks))
        self.method = method
        self.remove_autocorr = bool(remove_autocorr)
        self.nchan_live = op.nchan if op.chan_index is None else int(op.chan_index.shape[0])
        # Static per-block factors of the image, made once: 1/(N_p N_q) (C', nblk, 1), and the
        # antenna-independent pattern B_p conj(B_q) (C'|1, nblk, K) if there is one.
        norm = op.norm if op.chan_index is None else op.norm[op.chan_index]
        self._blkscale = xp.stack([norm[:, p] * norm[:, q] for p, q in blocks], axis=1)[..., None].astype(op.rdtype)
        self._bw = None
        if op.pixel_pattern is not None:
            B = op.pixel_pattern if op.chan_index is None or op.pixel_pattern.shape[0] == 1 \
                else op.pixel_pattern[op.chan_index]                                 # (C'|1, K, P|1)
            self._bw = xp.stack([B[:, :, min(p, B.shape[2] - 1)] * xp.conj(B[:, :, min(q, B.shape[2] - 1)])
                                 for p, q in blocks], axis=1)
        self._bidx = [(self.pols.index(p), self.pols.index(q)) for p, q in blocks]
        self._coef = None
        self.reset()

    def reset(self):
        self.ntime = 0
        self._S = None      # direct: (C', nblk, K) sums of F_p F_q^*
        self._auto = None   # direct: (C', nblk, A) sums of x_p x_q^*
        self._R = None      # covariance, complex input: (C', nblk, A, A)
        self._W = None      # covariance, integer input: (C', R, R) int32 (GPU) / float64 (CPU) Gram sums
        self._W64 = None    # GPU: int64 bank the int32 sums are flushed to before they could overflow
        self._wn = 0        # samples in the int32 sums

    # ------------------------------------------------------------------ accumulation
    def add(self, efield):
        """Accumulate voltages (ntime, nchan, nant, npol) complex, or integer (re, im) pairs."""
        if efield.shape[0] == 0:
            return
        op = self.op
        ints = op._check_efield(efield)
        if self.method == "covariance":
            if ints:
                if self._R is not None:
                    raise TypeError("one integration cannot mix complex and integer voltages")
                self._add_int_covariance(gram_rows(efield, op.sel))
            else:
                if self._W is not None or self._W64 is not None:
                    raise TypeError("one integration cannot mix complex and integer voltages")
                self._add_covariance(op.prepare(efield))
        else:
            sums, auto = self._direct_sums(efield, ints, int(efield.shape[0]))
            if self._S is None:
                self._S, self._auto = sums[0], (None if auto is None else auto[0])
            else:
                self._S += sums[0]
                if auto is not None:
                    self._auto += auto[0]
        self.ntime += int(efield.shape[0])

    def _direct_sums(self, efield, ints, n):
        """Direct route over one gulp: ((g, C', nblk, K) sums over groups of n samples of F_p F_q^*,
        (g, C', nblk, A) autocorrelation sums or None), g = ntime // n."""
        op, xp = self.op, self.op.xp
        t = int(efield.shape[0])
        if op.fused is not None:
            return self._fused_sums(efield, ints, n)
        g = t // n
        per_chan = op.npix * len(self.pols) * t * np.dtype(op.cdtype).itemsize
        fast = ints and op.unit_weights and op.shared_geometry and per_chan <= op.chunk_bytes()
        x = op.prepare(efield) if (self.remove_autocorr or not fast) else None
        auto = xp.moveaxis(self._auto_sums(x, n), -1, 0) if self.remove_autocorr else None
        S = xp.zeros((g, self.nchan_live, len(self.blocks), op.npix), dtype=op.cdtype)
        if fast:
            # integer voltages straight into the GEMM's operand form: one transpose kernel, no copies
            rhs = direct_rhs(efield, op.sel, self.pols, op.precision, op.stacked)
            cchunk = max(1, min(self.nchan_live, op.chunk_bytes() // per_chan))
            for c0 in range(0, self.nchan_live, cchunk):
                cs = slice(c0, min(self.nchan_live, c0 + cchunk))
                F, stacked = op.field_gemm_parts(0, [rhs[cs]], cs, exact=True)
                S[:, cs] = block_corr(F, self._bidx, n, npol=len(self.pols), stacked=stacked)
            return S, auto
        for cs, t0, F, stacked, scale in self._fields(x, ints and op.unit_weights):
            nt = F.shape[-1] // len(self.pols)
            sc = None if scale is None else scale * scale
            if t0 % n == 0 and nt % n == 0:
                S[t0 // n:(t0 + nt) // n, cs] += block_corr(F, self._bidx, n, npol=len(self.pols), stacked=stacked,
                                                            scale=sc)
            else:   # a group split across time chunks (CPU memory cap): sum its parts one by one
                Fc = F[:, 0] + 1j * F[:, 1] if stacked else F
                Fc = Fc.reshape(Fc.shape[0], op.npix, len(self.pols), nt)
                for j in range(t0 // n, min(g, -(-(t0 + nt) // n))):
                    lo, hi = max(j * n, t0) - t0, min((j + 1) * n, t0 + nt) - t0
                    part = xp.ascontiguousarray(Fc[..., lo:hi]).reshape(Fc.shape[0], op.npix, -1)
                    S[j, cs] += block_corr(part, self._bidx, hi - lo, npol=len(self.pols), scale=sc)[0]
        return S, auto

    def _fused_sums(self, efield, ints, n):
        """:meth:`_direct_sums` in a fused integer mode: the GEMM and |F|^2 in one kernel (:mod:`.fused`)."""
        op, t = self.op, int(efield.shape[0])
        if not ints or not op.fused.supports(t, n):
            raise ValueError(
                f"precision {op.precision!r} images integer (re, im) voltages of at most 4 bits in groups of a "
                f"multiple of 16 samples; got {'integer' if ints else 'complex'} voltages, {t} samples in groups "
                f"of {n}: use 'fp16x3' or 'fp32'")
        S = op.fused.sums(efield, self.pols, n)                       # (g, C', nblk, K), blocks (p, p)
        auto = None
        if self.remove_autocorr:
            auto = op.xp.moveaxis(self._auto_sums(op.prepare(efield[:(t // n) * n]), n), -1, 0)
        return S, auto

    def _fields(self, x, exact):
        """Yield (channel slice, t0, F, stacked, scale) chunks of the beamformed fields.

        F: complex (c, K, P' t) or stacked float32 (c, 2, K, P' t), columns p' * t + time (p' over
        ``self.pols``); see :meth:`DFTOperator.field_gemm` for ``stacked`` and ``scale``."""
        op, xp = self.op, self.op.xp
        c, p, a, t = x.shape
        per_chan_t = op.npix * len(self.pols) * np.dtype(op.cdtype).itemsize
        tchunk = max(1, min(t, op.chunk_bytes() // max(1, per_chan_t)))
        cchunk = max(1, min(c, op.chunk_bytes() // max(1, per_chan_t * tchunk)))
        for c0 in range(0, c, cchunk):
            cs = slice(c0, min(c, c0 + cchunk))
            for t0 in range(0, t, tchunk):
                xs = x[cs, :, :, t0:t0 + tchunk]
                nc, nt = xs.shape[0], xs.shape[-1]
                if op.shared_geometry:
                    # both pols in one GEMM: (c, K, A) @ (c, A, P' t)
                    rhs = xs[:, self.pols].transpose(0, 2, 1, 3).reshape(nc, a, len(self.pols) * nt)
                    yield (cs, t0) + op.field_gemm(0, rhs, cs, exact=exact)
                else:   # antenna-dependent pattern: one operator per pol (a rarer, slower path)
                    F = xp.concatenate([op.field_gemm_complex(pp, xp.ascontiguousarray(xs[:, pp]), cs, exact=exact)
                                        for pp in self.pols], axis=-1)
                    yield cs, t0, F, False, None

    def _auto_sums(self, x, n):
        """(c, nblk, A, groups): sums over groups of n samples of x_p conj(x_q) per antenna."""
        xp = self.op.xp
        return xp.stack([group_power(x[:, pp], x[:, qq] if pp != qq else None, n).astype(self.op.cdtype)
                         for pp, qq in self.blocks], axis=1)

    def _add_covariance(self, x):
        op, xp = self.op, self.op.xp
        c, p, a, t = x.shape
        if self._R is None:
            self._R = xp.zeros((c, len(self.blocks), a, a), dtype=op.cdtype)
        prec = "fp64" if op.precision == "fp64" else "fp32"   # the data are not integers: R in fp32
        for i, (pp, qq) in enumerate(self.blocks):
            xq_h = xp.ascontiguousarray(xp.conj(x[:, qq]).swapaxes(1, 2))
            self._R[:, i] += cmatmul(x[:, pp], xq_h, prec)

    # int32 sums of 4/8-bit products: a sample adds at most 2 * 128^2 to an entry
    _INT32_SAMPLES = (2**31 - 1) // (2 * 128 * 128)

    def _add_int_covariance(self, z):
        xp = self.op.xp
        t = z.shape[-1]
        if xp is np:
            step = (2**24 - 1) // (2 * 128 * 128)     # float32 sums stay exact below 2^24
            if self._W is None:
                self._W = np.zeros((z.shape[0], z.shape[1], z.shape[1]), np.float64)
            for t0 in range(0, t, step):
                int_gram(z[..., t0:t0 + step], out=self._W, accumulate=True)
            return
        if self._W is not None and self._wn + t > self._INT32_SAMPLES:
            self._W64 = self._W.astype(xp.int64) if self._W64 is None else self._W64 + self._W
            self._W, self._wn = None, 0
        self._W = int_gram(z, out=self._W, accumulate=self._W is not None)
        self._wn += t

    # ------------------------------------------------------------------ results
    @property
    def takes_ci4(self):
        """Whether :meth:`images` takes ci4 bytes as they are (``ci4=True``): a fused integer mode's
        direct route without autocorrelation removal lays the bytes out for its kernel in one pass."""
        return self.op.fused is not None and self.method == "direct" and not self.remove_autocorr

    def images(self, efield, n, *, ci4=False, place=None, out=None):
        """One image per ``n`` consecutive samples of ``efield``: (ntime // n, nchan, nprod, npix).

        Independent of (and leaving untouched) any integration in progress. Direct route: one batched
        pass; covariance route: one exact covariance per group (chosen only for long groups).

        ci4 : ``efield`` is ci4 bytes, uint8 (ntime, nchan, nant, npol) (high nibble real), imaged
            without unpacking (only where :attr:`takes_ci4`).
        place, out : a :class:`.pixels.GridPlacement` and the float32 (ntime // n, nchan, nprod, N)
            array the images are placed into (cells with no pixel NaN; on the GPU in the same pass as
            the products). Returns ``out``."""
        op, xp = self.op, self.op.xp
        if ci4:
            if not self.takes_ci4:
                raise ValueError("ImageAccumulator.images: ci4 bytes are imaged as they are only by a fused "
                                 "integer mode's direct route without autocorrelation removal")
            t, c, a, p = efield.shape
            if efield.dtype != np.uint8 or (c, a, p) != (op.nchan, op.nant_in, op.npol):
                raise ValueError(f"ci4 bytes must be uint8 (ntime, {op.nchan}, {op.nant_in}, {op.npol}), got "
                                 f"{efield.dtype} {tuple(efield.shape)}")
            g = t // n
            if not op.fused.supports(g * n, n):
                raise ValueError(f"precision {op.precision!r} images groups of a multiple of 16 samples, got {n}")
            if self._onto_grid(n, g, place, out):
                return self._grid_images(efield[:g * n], 1.0 / n, place, out, ci4=True)
            S = op.fused.sums(efield[:g * n], self.pols, n, ci4=True)
            return self._finish(S, 1.0 / n, place=place, out=out)
        ints = op._check_efield(efield)
        g = int(efield.shape[0]) // n
        if g == 0:
            return out if out is not None else xp.zeros((0, op.nchan, len(self.products), op.npix), op.rdtype)
        efield = efield[:g * n]
        if self.method == "covariance":
            sub = ImageAccumulator(op, self.products, remove_autocorr=self.remove_autocorr, method="covariance")
            imgs = []
            for i in range(g):
                sub.add(efield[i * n:(i + 1) * n])
                imgs.append(sub.result())
                sub.reset()
            imgs = xp.stack(imgs)
            return imgs if place is None else place(imgs, out=out)
        if ints and op.precision in FUSED and not self.remove_autocorr and self._onto_grid(n, g, place, out):
            return self._grid_images(efield, 1.0 / n, place, out)
        S, auto = self._direct_sums(efield, ints, n)                        # (g, C', nblk, K)
        if auto is not None:
            S = S - self._autocorr_term(auto)
        return self._finish(S, 1.0 / n, place=place, out=out)

    def result(self):
        """The image (nchan, nprod, npix), real, in the operator's precision; NaN where all antennas of a
        contributing channel-pol are flagged. Raises if nothing was accumulated."""
        if self.ntime == 0:
            raise ValueError("no samples were accumulated: cannot form an image from zero time samples")
        if self.method == "covariance":
            return self._finish(self._image_covariance(), 1.0)   # already divided by ntime
        corr = self._S
        if self.remove_autocorr:
            corr = corr - self._autocorr_term(self._auto)
        return self._finish(corr, 1.0 / self.ntime)

    def _onto_grid(self, n, g, place, out):
        """Whether a fused mode's images of ``n`` samples go straight onto the grid (:meth:`_grid_images`):
        the Hopper kernel, 16-sample images, one product that is a real sum of the pols' powers (XX, YY, I,
        Q), every channel live, and ``out`` the float32 (g, nchan, 1, cells) array of ``place``."""
        op = self.op
        if place is None or out is None or op.precision not in FUSED or op.chan_index is not None or n != 16:
            return False
        if not op.fused.onto_grid() or len(self.products) != 1 or place.gather is None:
            return False
        coef = product_coefficients(self.products, self.blocks)          # (host: a few numbers)
        return (out.dtype == np.float32 and out.flags.c_contiguous and out.shape == (g, op.nchan, 1, place.n)
                and not bool(np.any(coef[..., 1])))

    def _grid_factor(self, factor):
        """(C', P', Kpad) float32: what the fused kernel's pol sums are multiplied by to give the product
        (the operator's scale, 1/(N_p N_q) times ``factor``, the pattern, the product's coefficient) --
        what :func:`.reduce.products_from_blocks` applies, made once per factor."""
        op, xp = self.op, self.op.xp
        key = float(factor)
        if getattr(self, "_fac_key", None) != key:
            osc = op.fused.osc                                              # (C', PA, Kpad)
            PA, K = int(osc.shape[1]), op.npix
            coef = product_coefficients(self.products, self.blocks)
            scale = self._blkscale[..., 0] * op.rdtype(factor)              # (C', nblk)
            fac = xp.zeros((osc.shape[0], len(self.pols), osc.shape[2]), xp.float32)
            for b, (p, q) in enumerate(self.blocks):
                i = self.pols.index(p)
                f = osc[:, i if PA > 1 else 0].astype(xp.float64) * (scale[:, b].astype(xp.float64) * float(coef[0, b, 0]))[:, None]
                if self._bw is not None:
                    f[:, :K] *= self._bw[:, b, :].real.astype(xp.float64)
                fac[:, i] = f
            self._fac, self._fac_key = fac, key
        return self._fac

    def _grid_images(self, efield, factor, place, out, ci4=False):
        """A fused mode's 16-sample images made straight into ``out`` (g, nchan, 1, cells) by the kernel
        (:meth:`.fused.FusedOperator.place`), each pol's share added to the cleared cells (0; NaN where no
        pixel is): no per-pol sums in memory and no products pass; dead channel-pols NaN as elsewhere."""
        op = self.op
        o3 = out.reshape(out.shape[0], out.shape[1], out.shape[3])
        place.clear(o3)
        op.fused.place(efield, self.pols, self._grid_factor(factor), place.cells, o3, ci4=ci4)
        self._fill_dead(out)
        return out

    def _finish(self, corr, factor, place=None, out=None):
        """(..., C', nblk, K) complex correlation sums, times ``factor`` -> (..., nchan, nprod, K) products;
        with a :class:`.pixels.GridPlacement` ``place``, placed into ``out`` (..., nchan, nprod, N)."""
        xp, op = self.op.xp, self.op
        # one pass: scale, 1/N_A^2, the pattern and the products' Re/Im combinations together (reduce.py);
        # on the GPU also the placement on the grid when every channel is live
        if self._coef is None:
            self._coef = xp.asarray(product_coefficients(self.products, self.blocks))
        scale = self._blkscale[..., 0] * op.rdtype(factor)
        gather = None if place is None or op.chan_index is not None or out is None else place.gather
        if gather is not None and out.dtype == np.float32 and out.flags.c_contiguous:
            products_from_blocks(corr, scale, self._coef, weight=self._bw, gather=gather, out=out)
            self._fill_dead(out)
            return out
        res = products_from_blocks(corr, scale, self._coef, weight=self._bw).astype(op.rdtype, copy=False)
        if op.chan_index is not None:
            full = xp.full(res.shape[:-3] + (op.nchan,) + res.shape[-2:], xp.nan, dtype=op.rdtype)
            full[..., op.chan_index, :, :] = res
            res = full
        self._fill_dead(res)
        return res if place is None else place(res, out=out)

    def _fill_dead(self, res):
        """NaN where all antennas of a contributing channel-pol are flagged (res: (..., nchan, nprod, cells))."""
        op, xp = self.op, self.op.xp
        if op.any_dead:
            for k, name in enumerate(self.products):
                pols = {"XX": (0,), "YY": (1,)}.get(name, tuple(range(op.npol)))
                bad = xp.any(op.dead[:, list(pols)], axis=1)
                res[..., bad, k, :] = xp.nan

    def _autocorr_term(self, auto):
        """sum_a D^p_ka conj(D^q_ka) sum_t x_ap conj(x_aq): (..., C', nblk, K); data already weighted."""
        xp, op = self.op.xp, self.op
        if op.shared_geometry:  # |G| = 1: the term is the same for every pixel
            s = auto.sum(axis=-1)
            return xp.broadcast_to(s[..., None], s.shape + (op.npix,))
        terms = []
        for i, (pp, qq) in enumerate(self.blocks):
            gg = op.live_G(pp) * xp.conj(op.live_G(qq))  # (C', K, A)
            terms.append(xp.matmul(gg, auto[..., i, :, None])[..., 0])
        return xp.stack(terms, axis=-2)

    def _gram(self):
        """The integer Gram sums W (C', R, R) (int32/int64 on the GPU, float64 on the CPU) or None."""
        if self._W64 is None:
            return self._W
        return self._W64 if self._W is None else self._W64 + self._W

    def _int_weights(self):
        op = self.op
        return op.weights128 if op.chan_index is None else op.weights128[op.chan_index]   # (C', A, P)

    def _covariance_blocks(self):
        """Weighted covariance blocks (C', nblk, A, A) complex, unnormalised (sums over time)."""
        W = self._gram()
        if W is None:
            return self._R
        op, xp = self.op, self.op.xp
        rhs = cov_rhs(W, self._int_weights(), self.blocks, op.npol, "fp64" if op.precision == "fp64" else "fp32",
                      False, unit=op.unit_weights)[0][0]                         # (C', A, nblk A)
        c, a = rhs.shape[0], rhs.shape[1]
        return xp.ascontiguousarray(rhs.reshape(c, a, len(self.blocks), a).transpose(0, 2, 1, 3))

    def _image_covariance(self):
        """(C', nblk, K): Re diag(D_p R_pq D_q^H) / ntime (complex for XY), minus the autocorrelations if asked."""
        xp, op = self.op.xp, self.op
        W = self._gram()
        nblk, a = len(self.blocks), op.nant
        itemsize = np.dtype(op.cdtype).itemsize
        c = self.nchan_live
        cchunk = max(1, min(c, op.chunk_bytes() // max(1, op.npix * nblk * a * itemsize)))
        out = xp.empty((c, nblk, op.npix), dtype=xp.complex128 if op.precision == "fp64" else xp.complex64)
        if W is not None and op.shared_geometry:
            # exact integer sums straight into the GEMM's operand form (weights, 1/T and the fp16
            # range scale applied in the same pass). The same-antenna terms stay out of the GEMM and
            # are added exactly here (|D| = 1: a constant per channel and block): the GEMM's rounding
            # is then relative to the cross-correlations, not to the much larger autocorrelations.
            s = op.cov_scale
            rhs, diag = cov_rhs(W, self._int_weights(), self.blocks, op.npol, op.precision, op.stacked,
                                scale=s / self.ntime, unit=op.unit_weights, nodiag=True)
            for c0 in range(0, c, cchunk):
                cs = slice(c0, min(c, c0 + cchunk))
                M, stacked = op.field_gemm_parts(0, [p[cs] for p in rhs], cs)
                r = row_dot(M, op.live_G(0)[cs], nblk, stacked=stacked, scale=None if s == 1 else 1.0 / s)
                if cchunk >= c:
                    out = r          # one chunk: no copy
                else:
                    out[cs] = r
            if not self.remove_autocorr:
                out = out + (diag.sum(axis=-1) / self.ntime).astype(out.dtype)[..., None]
            return out
        else:
            R = self._covariance_blocks()                         # (C', nblk, A, A) sums
            for c0 in range(0, c, cchunk):
                cs = slice(c0, min(c, c0 + cchunk))
                nc = cs.stop - cs.start
                if op.shared_geometry:
                    rhs = R[cs].transpose(0, 2, 1, 3).reshape(nc, a, nblk * a)      # [R_b0 | R_b1 | ...]
                    M, stacked, scale = op.field_gemm(0, rhs, cs)
                    out[cs] = row_dot(M, op.live_G(0)[cs], nblk, stacked=stacked, scale=scale)
                else:
                    for i, (pp, qq) in enumerate(self.blocks):
                        M = op.field_gemm_complex(pp, xp.ascontiguousarray(R[cs, i]), cs)
                        out[cs, i] = row_dot(M, op.live_G(qq)[cs], 1)[:, 0]
            out = out / self.ntime
        if self.remove_autocorr:   # the diagonal's contribution, subtracted: R itself is not copied
            out = out - self._autocorr_term(self._covariance_diag()) / self.ntime
        return out

    def _covariance_diag(self):
        """(C', nblk, A): the weighted same-antenna terms sum_t w_p x_ap conj(w_q x_aq)."""
        xp, op = self.op.xp, self.op
        W = self._gram()
        if W is None:
            return xp.diagonal(self._R, axis1=-2, axis2=-1)
        c, r, _ = W.shape
        a, P = op.nant, op.npol
        d = W.reshape(c, a, P * 2, a, P * 2)
        d = d[:, xp.arange(a), :, xp.arange(a), :]            # (A, C', 2P, 2P): same-antenna blocks
        d = xp.moveaxis(d, 0, 1).astype(xp.float64)             # (C', A, 2P, 2P)
        w = self._int_weights()
        out = []
        for p, q in self.blocks:
            re = d[:, :, 2 * p, 2 * q] + d[:, :, 2 * p + 1, 2 * q + 1]
            im = d[:, :, 2 * p + 1, 2 * q] - d[:, :, 2 * p, 2 * q + 1]
            out.append((re + 1j * im) * w[:, :, p] * xp.conj(w[:, :, q]))
        return xp.stack(out, axis=1).astype(op.cdtype)


def dirty_image(efield, xyz_m, freq_hz, pixels_lm, *, remove_autocorr=False, method="auto",
                precision=None, products=None, weights=None, pattern=None, accumulate=None, tolerance=None,
                return_plan=False):
    """E-field DFT image: the time mean of |sum_a D[k, a] x_a(t)|^2 (see module docstring).

    Parameters
    ----------
    efield : complex (ntime, nchan, nant, npol), NumPy or CuPy (or anything ``asarray`` takes);
             calibrated voltages. Integer (re, im) pairs (ntime, nchan, nant, npol, 2) int8 are
             taken as they are (the covariance route then forms X X^H exactly).
    xyz_m : (nant, 3) East/North/Up metres.   freq_hz : (nchan,) Hz.
    pixels_lm : (npix, 2) direction cosines (l East, m North); l^2 + m^2 > 1 is a ValueError.
    remove_autocorr : subtract the autocorrelation term exactly.
    tolerance : the accuracy knob: the largest acceptable error max |I - I_exact| / max I_exact; the
             fastest route x precision whose measured bound holds on this device is used. None: the
             given precision (default "fp32") on the cheaper route. Either way
             :func:`bf_epic_blocks.imaging.plan.resolve` decides.
    method : expert override of the route: "direct" (D X then |.|^2), "covariance"
             (Re diag(D R D^H)), or "auto" (the resolver's pick).
    precision : expert override of the GEMM precision, one of
             :data:`bf_epic_blocks.imaging.gemm.PRECISIONS` ("fp64", "fp32", and on a GPU "tf32x3",
             "fp16x3", "tf32", "fp16", "bf16", and for 4-bit integer voltages "i8x2", "i8x3"; phases
             are always formed in float64). With a tolerance, method and precision restrict the choice
             and are an error if nothing they allow meets it.
    products : None (npol=1: XX; npol=2: XX, YY), "stokes" (I, Q, U, V), "linear", "full", or
               a list of names from XX, YY, XY, YX, XYi, YXi, I, Q, U, V.
    weights : complex (nant,) or (nchan|1, nant, npol|1); 0 drops the antenna from the operator.
    pattern : complex (nchan|1, npix, nant|1, npol|1) voltage pattern folded into D.
    accumulate : None (one image) or N: one image per N consecutive samples.
    return_plan : also return the :class:`~bf_epic_blocks.imaging.plan.Plan` the image was made with.

    Returns
    -------
    float (nchan, nprod, npix) -- or (ntime // N, nchan, nprod, npix) with ``accumulate=N`` -- in
    the namespace of ``efield``, float32 (float64 for precision "fp64"); with ``return_plan``, the
    pair (image, plan).
    """
    from .plan import Problem, resolve
    xp = get_xp(efield)
    efield = xp.asarray(efield)
    if efield.ndim not in (4, 5):
        raise ValueError("efield must be shaped (ntime, nchan, nant, npol); got shape " + str(tuple(efield.shape)))
    nchan, nant, npol = (int(n) for n in efield.shape[1:4])
    nt = int(efield.shape[0]) if accumulate is None else int(accumulate)
    used = nant
    if weights is not None:
        w = _broadcast_weights(to_numpy(weights), nchan, nant, npol, np)
        used = max(1, int((w != 0).any(axis=(0, 2)).sum()))    # the antennas the operator keeps
    problem = Problem(int(xp.asarray(pixels_lm).shape[0]), used, max(1, nt), nchan, npol, products)
    # integer pairs are int8: 8-bit samples as far as anyone can tell (the fused modes need 4-bit ones)
    plan = resolve(tolerance, device=xp, problem=problem, input_kind="ci8" if efield.ndim == 5 else "complex",
                   precision=precision, method=method)
    op = DFTOperator(xp.asarray(xyz_m), xp.asarray(freq_hz), xp.asarray(pixels_lm), npol=npol,
                     weights=None if weights is None else xp.asarray(weights),
                     pattern=None if pattern is None else xp.asarray(pattern), precision=plan.precision)
    out = op.image(efield, products, remove_autocorr=remove_autocorr, method=plan.method, accumulate=accumulate)
    if op.nonfinite_counts is not None:
        nbad = int(op.nonfinite_counts.sum())
        if nbad:
            per = to_numpy(op.nonfinite_counts)
            worst = np.unravel_index(int(np.argmax(per)), per.shape)
            log.warning("dirty_image: %d non-finite (NaN/Inf) voltage samples were zeroed (treated as flagged); "
                        "most in kept antenna %d pol %d (%d)", nbad, worst[0], worst[1], int(per[worst]))
    return (out, plan) if return_plan else out
