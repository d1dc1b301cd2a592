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
Each route is an object of :mod:`.routes` (``add`` a gulp, ``result`` the image); :class:`DFTOperator`
holds what they share (the operator, the weights, the GEMMs).

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
import weakref

import numpy as np

from ..conventions import SIGMA, SPEED_OF_LIGHT_M_S
from ._xp import get_xp, host_all, to_numpy
from .fused import FUSED, FusedOperator
from .gemm import (FP16, PRECISIONS, STACKED, check_precision, cmatmul, pow2_scale, split_tf32, stack_operator, stack_rhs,
                   stacked_matmul)
from .graphs import GraphCache
from .pixels import check_lm, n_from_lm
from .products import resolve_products
from .routes import METHODS, ImageAccumulator, make_route  # noqa: F401 (METHODS, ImageAccumulator: public names)

log = logging.getLogger(__name__)

# Working-set cap for one chunk of intermediate results (bytes): bounds host memory on small CPU
# machines; on the GPU a whole gulp of a station-sized problem is one chunk.
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
    return _geometric_from_path(xp, _path_m(xyz, lm, n), f, precision)


def _geometric_from_path(xp, path, f, precision):
    """:func:`geometric_operator` (nchan, npix, nant) in ``xp`` from the path differences ``path`` (:func:`_path_m`,
    float64 (npix, nant), on the host or, for CuPy, already on the device) and host frequencies ``f``."""
    rdt, cdt = _check_precision(precision)
    if xp.__name__ == "cupy":
        key = np.dtype(cdt).name
        if key not in _GEOM_KERNELS:
            _GEOM_KERNELS[key] = xp.ElementwiseKernel(*_GEOM_SRC[key], f"bf_geometric_{key}")
        fc = xp.asarray(f / SPEED_OF_LIGHT_M_S)[:, None, None]
        out = xp.empty((f.shape[0],) + tuple(path.shape), dtype=cdt)
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


def _unit(w) -> bool:
    """Whether host weights ``w`` are all 0 or 1 (the routes' exact integer paths need that)."""
    return bool(((w == 0) | (w == 1)).all())


def _cov_scale(w, precision) -> float:
    """The power of two that scales fp16 covariance operands into range for host weights ``w``:
    R' = w R w^H / T <= 2 * 127^2 * max|w|^2 (chosen on the host, from the weights); 1 in other modes."""
    wmax = float(np.abs(w).max())
    return 2.0 ** -math.ceil(math.log2(wmax * wmax)) if precision in FP16 and wmax > 0 else 1.0


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
                                 tf32x3, fp16x3, tf32, fp16, bf16, i8x1, i8x2, i8x3; all but fp64 and
                                 fp32 need a GPU, and i8x1/i8x2/i8x3 4-bit integer voltages; to choose one by
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
        # compile (tools/bench/cold_start.py lists them).
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
        self.unit_weights = _unit(w)
        live_sel = live if chan_index is None else live[chan_index]
        self.cov_scale = _cov_scale(w, self.precision)
        hxyz_kept = hxyz[keep_index]
        # 1/N_A is applied to the image (norm), not to the data, so that integer voltages with
        # unit weights stay integers (exact in fp16/tf32 and in integer covariances).
        norm = np.where(dead, 0.0, 1.0 / np.maximum(n_live, 1))                # (nchan, npol) float64

        self.keep_index = xp.asarray(keep_index)
        self.n_live = xp.asarray(n_live)
        self.dead = xp.asarray(dead)
        self.chan_index = None if chan_index is None else xp.asarray(chan_index)
        self.norm = xp.asarray(norm)
        # host copies of what a new gain solution is checked against and folded with (reweight): reading
        # them back from the device would wait for the stream's queued images
        self._host = {"keep": keep_index, "live": live, "w": w, "chan": chan_index}
        self.data_weights = xp.asarray(w.astype(self.cdtype))                    # (nchan, nant, npol)
        self.weights128 = xp.asarray(w)                                          # for integer covariances
        self.data_live = xp.asarray(live)
        self.xyz_m = xp.asarray(hxyz_kept)
        live_sel = xp.asarray(live_sel) if self.partial_flags else None
        self.sel = _Selection(xp, self.chan_index, None if self.all_kept else self.keep_index, live_sel,
                              nchan, nant_in)

        self._host_geometry = (hxyz_kept, hf)          # float64 host copies: repoint() forms new phases from them
        self._host_pixels = (np.array(hlm), np.array(hn))
        self._path = None                               # the pixels' path differences, where phases() forms them
        # The fused integer modes image from their int8 pieces alone: on a GPU the phases (4.8 GB at the
        # whole band) are not held but formed a chunk of channels at a time whenever the pieces are made
        # (here, a new gain solution, pixels moved), and whole only for a route that asks for them (live_G).
        held = not (precision in FUSED and xp.__name__ == "cupy")
        #: (nchan, 1|npol, npix, nant) operator, or None where not held (:meth:`phases`), and
        #: (nchan|1, npix, npol|1) or None: an antenna-independent pattern
        self.G, self.pixel_pattern = self._pixel_operator(hlm, hn, pattern, phases=held)
        self.shared_geometry = self.G is None or self.G.shape[1] == 1
        self._derived = {}
        self._routes = weakref.WeakSet()    # routes made from this operator (they add themselves): repoint() refreshes them
        #: the fused integer modes' operator (:mod:`.fused`), built now: never inside a graph capture
        self.fused = None
        if precision in FUSED:
            if not self.shared_geometry:
                raise ValueError(f"precision {precision!r} needs one operator for both pols; an antenna-dependent "
                                 "pattern makes one per pol: use 'fp16x3' or 'fp32'")
            self.fused = FusedOperator(self, precision)
        #: (nant_kept, npol) NaN/Inf samples zeroed so far in complex input (device array), or None
        self.nonfinite_counts = None

    def _pixel_operator(self, hlm, hn, pattern, phases=True):
        """(G, pixel_pattern) for pixels ``hlm`` (host float64, ``hn`` their n): G (nchan, 1|npol, npix, nant)
        with an antenna-dependent pattern folded in (one operator per pol), else the geometry alone (None
        when ``phases`` is False) and the pattern (nchan|1, npix, npol|1) kept apart (or None)."""
        xp, (hxyz, hf) = self.xp, self._host_geometry
        npix = int(hlm.shape[0])
        b = _check_pattern(pattern, self.nchan, npix, self.nant_in, self.npol, xp)
        G = _geometric_from_host(xp, hxyz, hf, hlm, hn, "fp64" if self.precision == "fp64" else "fp32") \
            if phases or (b is not None and b.shape[2] != 1) else None
        if b is not None and b.shape[2] != 1:
            b = b[:, :, self.keep_index, :].astype(self.cdtype)
            Gp = G[:, None, :, :] * xp.moveaxis(b, 3, 1)          # one operator per pol: G_p = G * B[..., p]
            return xp.ascontiguousarray(xp.broadcast_to(Gp, (self.nchan, self.npol, npix, self.nant))), None
        return (None if G is None else G[:, None]), (None if b is None else b[:, :, 0, :].astype(self.cdtype))

    def repoint(self, pixels_lm, pattern=None, first=0):
        """Point the operator's pixels at new directions, in place: the phases where it holds them (and
        ``pattern``, given for the new pixels as to the constructor) are formed again into the arrays that
        held them, with
        every form derived from them (the GEMMs' operands, the fused modes' int8 pieces, the routes'
        pattern factors), so routes made from this operator and the CUDA graphs replaying its images
        stay valid. A tracking imager moves its pixels this way (:class:`~..blocks.engines.DFTEngine`)
        instead of building a new operator and route (which costs the graphs' captures again).

        pixels_lm : (npix - first, 2) the new directions of pixels ``first`` .. npix - 1 (all of them by
        default; an operator keeps its pixel count), the others unchanged -- a grid's pixels with a
        watchlist's directions after them move only the directions' rows;  pattern : as the
        constructor's for those pixels, of the same kind (none, antenna-independent, or
        antenna-dependent) as the operator was built with."""
        xp = self.xp
        first = int(first)
        hlm = check_lm(to_numpy(pixels_lm))
        if not 0 <= first < self.npix or hlm.shape != (self.npix - first, 2):
            raise ValueError(f"repoint: {hlm.shape[0]} pixels given to an operator of {self.npix} "
                             f"(from its pixel {first}); "
                             "an operator keeps its pixel count (build another for another count)")
        hn = n_from_lm(hlm[:, 0], hlm[:, 1])
        G, bp = self._pixel_operator(hlm, hn, pattern, phases=self.G is not None)
        rows = (slice(None), slice(None), slice(first, None))
        if (G is not None and G.shape != self.G[rows].shape) or (G is None) != (self.G is None) \
                or (bp is None) != (self.pixel_pattern is None):
            raise ValueError("repoint: the pattern is not of the kind the operator was built with "
                             f"(operator {None if self.G is None else tuple(self.G.shape)}, pattern per pixel: "
                             f"{self.pixel_pattern is not None})")
        if G is not None:
            self.G[rows] = G
        self._host_pixels[0][first:] = hlm
        self._host_pixels[1][first:] = hn
        if self._path is not None:      # the moved pixels' rows only (each row is its pixel's alone)
            self._path[first:] = self.xp.asarray(_path_m(self._host_geometry[0], hlm, hn))
        if bp is not None:
            self.pixel_pattern[:, first:] = bp
        self.pixels_lm[first:] = xp.asarray(hlm)
        for key, old in self._derived.items():      # ("G", pol), ("stack", pol); "accumulators": the routes'
            if not isinstance(key, tuple):
                continue
            if key[0] == "G":
                old[:, first:] = self._live_G(key[1])[:, first:]
            elif key[0] == "stack":
                for o, n in zip(old, stack_operator(self.live_G(key[1]), self.precision)):
                    o[...] = n
        if self.fused is not None:
            self.fused.requantise(self, first)
        for route in list(self._routes):
            route.refresh()

    def reweight(self, weights):
        """New direction-independent weights (a new gain solution folded in) for the same inputs, in place:
        the weights the data are multiplied by, the integer covariances' weights and the fused modes'
        int8 pieces are formed again into the arrays that held them, and the routes refresh what they
        keep, so routes and their captured CUDA graphs stay valid and no GBs are let go and made again.
        On a GPU it is a few launches (the fused modes' int8 pieces in one kernel) and nothing is read back
        from the device (host copies), so the work is queued behind the images already asked for and the
        imager's thread never waits for them.

        weights : as the constructor's, on the host (NumPy): a device array is read back, which waits for the
        queued work. Returns True when done; False, with the operator unchanged, when
        the new weights flag or unflag an input (N_A, the kept antennas and the live channels depend on
        which weights are zero), turn unit weights into others or back (the routes chose their exact
        integer paths by that), change the fp16 operands' range scale, or make the pols' weights differ
        where a fused mode shared one operator between them: those need a new operator."""
        xp = self.xp
        w = _broadcast_weights(to_numpy(weights), self.nchan, self.nant_in, self.npol, np)
        kidx = self._host["keep"]
        dropped = np.ones(self.nant_in, bool)
        dropped[kidx] = False
        if (w[:, dropped, :] != 0).any():
            return False
        w = w[:, kidx, :]
        if not np.array_equal(w != 0, self._host["live"]):
            return False
        if _unit(w) != self.unit_weights or _cov_scale(w, self.precision) != self.cov_scale:
            return False
        chan = self._host["chan"]
        if self.fused is not None and not self.fused.can_reweight(w if chan is None else w[chan]):
            return False
        self._host["w"] = w
        self.data_weights[...] = xp.asarray(w.astype(self.cdtype))
        self.weights128[...] = xp.asarray(w)
        if self.fused is not None:
            self.fused.reweight(self)
        for route in list(self._routes):
            route.refresh()
        return True

    def live_weights_host(self):
        """The kept antennas' weights of the live channels, (C', A_kept, P) complex128 NumPy (host copy)."""
        chan = self._host["chan"]
        return self._host["w"] if chan is None else self._host["w"][chan]

    # ------------------------------------------------------------------ operator forms
    def phases(self, cs=slice(None), first=0):
        """(c, npix, nant) complex: the geometric operator of the live channels ``cs`` (a slice), from the
        operator's phases where it holds them, else formed from its host geometry (bit-equal: the same
        element-wise arithmetic). For one operator shared by the pols (``shared_geometry``).
        first : where the phases are formed, only pixels ``first`` .. npix - 1: (c, npix - first, nant)."""
        if self.G is not None:
            return self.live_G(0)[cs, int(first):]
        hxyz, hf = self._host_geometry
        chan = self._host["chan"]
        f = (hf if chan is None else hf[chan])[cs]
        precision = "fp64" if self.precision == "fp64" else "fp32"
        # the path differences formed (and copied to the GPU) once per pixel set (6.7 MB at 3,264 pixels x
        # 256 stands), not once per chunk: a solution's pieces are made ~20 chunks at a time
        if self._path is None:
            self._path = self.xp.asarray(_path_m(hxyz, *self._host_pixels))
        return _geometric_from_path(self.xp, self._path[int(first):], f, precision)

    def _live_G(self, pol):
        if self.G is None:       # a route asks for the whole operator: formed now, and held from now on
            self.G = self._pixel_operator(*self._host_pixels, None)[0]
        g = self.G[:, 0 if self.shared_geometry else pol]
        return g if self.chan_index is None else g[self.chan_index]

    def live_G(self, pol):
        """Operator of pol ``pol`` (0 when shared) for the live channels: (nchan_live, npix, nant)."""
        key = ("G", pol)
        if key not in self._derived:
            self._derived[key] = self.xp.ascontiguousarray(self._live_G(pol))
        return self._derived[key]

    @property
    def stacked(self) -> bool:
        """Whether GEMMs run in the stacked real form (:mod:`.gemm`): the tensor-core modes on the GPU.
        (fp32 and fp64 stay complex: cuBLAS' CGEMM is faster than fp32 as a stacked real SGEMM.)"""
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
        """A fresh route (:mod:`.routes`: ``add``, ``result``, ``images``, ``reset``) for integrations that
        span several calls.

        ``method`` "auto" is resolved by :func:`.plan.resolve` for this operator's problem with
        ``ntime_hint`` samples per image (the cheaper route; the direct one for a fused mode)."""
        if method == "auto":
            method = self.route(products, ntime_hint)
        return make_route(self, products, remove_autocorr=remove_autocorr, method=method, ntime_hint=ntime_hint)

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
        either route, complex voltages on the covariance route with ``accumulate=None`` (there replays equal
        eager calls bitwise, fp32 and fp16x3; on the direct route they do not). For complex voltages
        this is a trade: the gulp is first copied into the graph's input, which makes a loop of calls
        on an idle host a little slower than eager ones, while the host's issue work falls to one
        launch, which is what a pipeline whose block threads share the host needs. ``graphs=False``
        keeps every call eager.

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
             "fp16x3", "tf32", "fp16", "bf16", and for 4-bit integer voltages "i8x1", "i8x2", "i8x3"; phases
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
