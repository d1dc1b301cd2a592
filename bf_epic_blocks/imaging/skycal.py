"""Direction-independent gains from the sky (the A_s of docs/CONVENTIONS.md), as pure functions.

Data model (docs/CONVENTIONS.md; sigma = +1). After the cable term is removed, input
a (one stand, one polarisation p) carries an unknown complex gain g_a(nu), and the covariance is

    R_ab = <x_a x_b*> = g_a g_b* M_ab + N_ab,
    M_ab = sum_s F_sp exp(+2 pi i nu s_hat . (r_a - r_b) / c),     F_sp = (S_s / 2) |B_p(s_hat)|^2

with S_s a model source's flux density (Stokes I, Jy), B_p the antenna's voltage pattern and N_ab what
the model lacks: receiver noise (on a = b only), diffuse Galactic emission (mostly on short baselines),
sources not in the model. Arrays here are shaped (..., nant, nant) with any leading batch, in practice
(nchan, npol): one independent problem per channel and polarisation; cross-polarisation terms are not
used.

Method: StEFCal (Salvini & Wijnholds 2014, A&A 571, A97), alternating least squares in closed form:
with the other inputs held, input p's gain minimising sum_q W_pq |R_pq - g_p M_pq g_q*|^2 is

    g_p = sum_q W_pq R_pq conj(M_pq) g_q  /  sum_q W_pq |M_pq|^2 |g_q|^2,

all inputs at once, and every second iterate is averaged with the one before (which makes the
iteration converge where the plain update oscillates). Why this method: each iteration is two batched
matrix-vector products over every channel and polarisation at once (O(N^2) per problem, no matrix
inversion, no per-input loop), the same lines on NumPy and CuPy; it is the inner loop of AARTFAAC's
real-time WALS (Wijnholds et al.), which adds per-direction terms that a direction-independent gain
against a fixed model does not need.

Robustness (what the model lacks):

* the autocorrelations (a = b) carry the receiver noise and are never used (W_aa = 0);
* baselines shorter than ``min_baseline_lambda`` wavelengths get W = 0: they are dominated by the
  diffuse Galactic emission, which a point-source model lacks;
* the diffuse emission is not confined to short baselines at a compact station: at LWA-SV and 74 MHz
  the Galactic sky is ~1e6 Jy per antenna against Cyg A's 1.7e4, and its correlation on 10-15
  wavelength baselines is still half Cyg A's. So the model can carry a second term, the analytic
  Galactic sky's covariance (:func:`bf_epic_blocks.sky.model.diffuse_model`), whose scale per channel
  and polarisation is fitted with the gains (``extra``, :func:`fit_scale`): the flux scale stays the
  catalogue's, and a diffuse model right in shape but not in brightness does no harm;
* inputs are screened by their health (:func:`input_health`) and the solve repeated without the bad
  ones: deaf (|g| far below its peers': no sky in it), noisy (power per unit gain far above its peers'),
  residual (the model does not fit it: a solution that will not converge on that input);
* per-channel solutions are regularised across the band (:func:`smooth_across_channels`): a delay and
  a phase per input (the physics of a cable), times a slowly varying complex bandpass (a running mean
  over ``smooth_channels`` channels once the delay is removed).

Unobservable: one phase per channel and polarisation (fixed here by a reference input, whose gain is
made real and positive). The amplitude scale is observable and set by the model's fluxes: calibrated
images are in Jy on the model's flux scale.

Output convention (docs/CONVENTIONS.md): gain tables hold CORRECTIONS, 1 / g, multiplied onto
the cable-corrected voltages; 0 flags an input.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..conventions import SPEED_OF_LIGHT_M_S
from ..cuda import get_kernel, register
from ._xp import Workspace, get_xp, to_numpy

register("imaging/skycal.cu")

__all__ = ["SolveSettings", "Solution", "clip_fraction", "model_covariance", "baseline_weights", "stefcal", "fit_scale", "reference_phase",
           "smooth_across_channels", "input_health", "solve_gains", "gain_error", "CovarianceSums",
           "REASONS"]

#: Flag reasons, in the order they are decided (an input keeps the first that applies).
REASONS = ("station", "saturated", "no-power", "deaf", "noisy", "residual", "few-baselines")


def clip_fraction(power, lo=-8.5, hi=7.5):
    """Fraction of a 4-bit input's real and imaginary samples past the converter's range, for complex
    Gaussian voltages of mean power ``power`` (4-bit units^2, both parts): each part has variance
    power / 2 and clips beyond [lo, hi] (the levels -8 .. 7). float64, power's shape."""
    from math import erfc, sqrt
    sig = np.sqrt(np.maximum(np.asarray(power, np.float64), 1e-300) / 2.0)
    f = np.vectorize(lambda s: 0.5 * erfc(hi / (s * sqrt(2))) + 0.5 * erfc(-lo / (s * sqrt(2))))
    return f(sig)


@dataclass(frozen=True)
class SolveSettings:
    """What the solver does; every field is a pipeline YAML key under ``calibration.solve``.

    min_baseline_lambda : baselines shorter than this (wavelengths, 3-D length) are not used.
    max_iter, tol : StEFCal's iteration limit and its convergence test (relative change of the gains).
    deaf_below : an input whose median |g| is below this fraction of the inputs' median is 'deaf'.
    noisy_above : an input whose median power / |g|^2 exceeds this multiple of the inputs' median is 'noisy'.
    residual_above : an input whose relative model residual exceeds this multiple of the median is 'residual'.
    smooth_channels : width (channels) of the running mean across the band once each input's delay is
        removed; 1 keeps per-channel solutions; >= nchan fits one delay, phase and amplitude per input.
    max_delay_s : the delay search spans +- this (seconds); it is also held within the channel spacing's
        ambiguity (1 / (2 channel spacing)).
    reference : the reference input's stand index (0-based row of the station table), or -1 for the
        good input with the largest median |g|.
    min_good_fraction : fewer good inputs than this fraction (of those the station does not flag) per
        polarisation is a failed solution.
    """
    min_baseline_lambda: float = 4.0
    max_iter: int = 200
    tol: float = 1e-6
    deaf_below: float = 0.3
    noisy_above: float = 3.0
    residual_above: float = 4.0
    smooth_channels: int = 16
    max_delay_s: float = 2e-6
    reference: int = -1
    min_good_fraction: float = 0.5

    def __post_init__(self):
        checks = {"min_baseline_lambda": self.min_baseline_lambda >= 0, "max_iter": self.max_iter >= 2,
                  "tol": self.tol > 0, "deaf_below": 0 <= self.deaf_below < 1, "noisy_above": self.noisy_above > 1,
                  "residual_above": self.residual_above > 1, "smooth_channels": self.smooth_channels >= 1,
                  "max_delay_s": self.max_delay_s >= 0, "min_good_fraction": 0 < self.min_good_fraction <= 1}
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError("SolveSettings: out of range: " + ", ".join(f"{k}={getattr(self, k)!r}" for k in bad))

    def to_dict(self):
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


@dataclass
class Solution:
    """One solve's result, on the host (NumPy).

    gains : complex128 (nchan, nant, npol), the solved g (referenced, smoothed; 0 where flagged).
    corrections : complex128 (nchan, nant, npol), 1 / g, 0 where flagged: what a gain table holds.
    flags : bool (nant, npol), True = flagged (any reason, the station's own included).
    reasons : str (nant, npol), '' for good inputs, else one of :data:`REASONS`.
    quality : float64 arrays (nant, npol): ``gain_amp`` (median over channels of |g|), ``residual``
        (relative model residual), ``power`` (median autocorrelation), ``power_per_gain``; and per
        (nchan, npol): ``converged`` (bool), ``delay_s`` (nant, npol) of the smoothing fit.
    info : iterations, reference input, baselines used, good inputs, settings.
    """
    gains: np.ndarray
    corrections: np.ndarray
    flags: np.ndarray
    reasons: np.ndarray
    quality: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    def summary(self) -> str:
        nant, npol = self.flags.shape
        counts = {r: int((self.reasons == r).sum()) for r in REASONS if (self.reasons == r).any()}
        good = ~self.flags
        amp = self.quality.get("gain_amp")
        med = float(np.median(amp[good])) if amp is not None and good.any() else float("nan")
        conv = self.quality.get("converged")
        return (f"{int(good.sum())}/{nant * npol} inputs good"
                + (f" (flagged: {', '.join(f'{k} {v}' for k, v in counts.items())})" if counts else "")
                + f", median |g| {med:.4g}, iterations {self.info.get('iterations')}"
                + (f", {int(conv.sum())}/{conv.size} channel-pols converged" if conv is not None else ""))


def _phases(xyz_m, freq_hz, lmn):
    """exp(+2 pi i nu s.r / c), complex128 (nchan, nsrc, nant), phases reduced in float64."""
    path = np.asarray(lmn, np.float64) @ np.asarray(xyz_m, np.float64).T                  # (nsrc, nant) m
    return _cycles_exp(np, np.asarray(freq_hz, np.float64)[:, None, None] / SPEED_OF_LIGHT_M_S, path[None],
                       np.complex128)


def model_covariance(xyz_m, freq_hz, lmn, flux_pol, xp=np, dtype=None):
    """The model covariance M, (nchan, npol, nant, nant) complex, in the namespace ``xp``.

    xyz_m : (nant, 3) East, North, Up metres; freq_hz : (nchan,); lmn : (nsrc, 3) direction cosines;
    flux_pol : (nchan, nsrc, npol) apparent flux per polarisation, F = (S / 2) |B_p|^2 (Jy).
    dtype : complex128 (default) or complex64. Phases are formed in float64 on the host.
    """
    a = _phases(xyz_m, freq_hz, lmn)                                                        # (c, s, a)
    f = np.asarray(flux_pol, np.float64)
    nchan, nsrc, npol = f.shape
    nant = a.shape[2]
    dtype = dtype or xp.complex128
    if nsrc == 0:
        return xp.zeros((nchan, npol, nant, nant), dtype)
    ad = xp.asarray(a.astype(dtype))
    out = xp.empty((nchan, npol, nant, nant), dtype)
    for p in range(npol):
        fa = ad * xp.asarray(f[:, :, p, None].astype(np.float64)).astype(dtype)           # (c, s, a)
        out[:, p] = xp.matmul(fa.swapaxes(1, 2), xp.conj(ad))                              # (c, a, a)
    return out


def baseline_weights(xyz_m, freq_hz, min_baseline_lambda, xp=np, dtype=np.float64):
    """``dtype`` (nchan, nant, nant): 1 for baselines of at least ``min_baseline_lambda`` wavelengths, else 0
    (the diagonal always 0). The length is the 3-D one (float64). A solver of complex64 covariances keeps
    them in float32 (the values are exact in either): half the bytes, and no copy a solve."""
    xyz = np.asarray(xyz_m, np.float64)
    d = np.sqrt(((xyz[:, None, :] - xyz[None, :, :]) ** 2).sum(-1))                         # (a, a) m
    lam = SPEED_OF_LIGHT_M_S / np.asarray(freq_hz, np.float64)
    w = (d[None] >= min_baseline_lambda * lam[:, None, None]).astype(dtype)
    idx = np.arange(xyz.shape[0])
    w[:, idx, idx] = 0
    return xp.asarray(w)


#: bytes of covariances (channels x pols x nant^2) the solver's per-channel steps (StEFCal, the diffuse
#: term's scale, the health figures) take at a time: their temporaries are a few arrays of that size, so
#: that a solve adds a few chunks to what it holds rather than a few whole covariances
SOLVE_CHUNK_BYTES = 128 * 2**20


def model_chunk(M, extra, scale, cs):
    """The model of the channels ``cs`` (a slice): M[cs], or with a fitted term M[cs] + scale[cs] E[cs]
    (M, E complex (nchan, npol, nant, nant); scale (nchan, npol)). A chunk at a time, so that the model
    with its term is never a whole covariance-sized array beside M and E."""
    if extra is None:
        return M[cs]
    return M[cs] + scale[cs, :, None, None] * extra[cs]


def solve_chunks(R):
    """Slices of R's leading (channel) axis, each at most :data:`SOLVE_CHUNK_BYTES` of R (at least one
    channel)."""
    nchan = int(R.shape[0])
    step = max(1, SOLVE_CHUNK_BYTES // max(1, R[:1].nbytes))
    return [slice(c0, min(nchan, c0 + step)) for c0 in range(0, nchan, step)]


def stefcal(R, M, W, g0=None, *, max_iter=200, tol=1e-6):
    """StEFCal (module docstring): gains g with R ~ g g^H (.) M where W > 0, batched.

    R, M : complex (..., nant, nant); W : real (..., nant, nant) broadcastable (0 = unused).
    g0 : complex (..., nant) start (default ones). Returns (g (..., nant), iterations, converged
    (...) bool). An input with no usable baseline gets g = 0.
    """
    xp = get_xp(R)
    P = W * R * xp.conj(M)
    Q = W * (M.real ** 2 + M.imag ** 2)
    batch, nant = R.shape[:-2], R.shape[-1]
    g = xp.ones(batch + (nant,), R.dtype) if g0 is None else xp.array(g0, dtype=R.dtype)
    conv = np.zeros(batch, bool)
    it = 0
    for it in range(1, max_iter + 1):
        num = xp.matmul(P, g[..., None])[..., 0]
        den = xp.matmul(Q, (g.real ** 2 + g.imag ** 2)[..., None])[..., 0]
        gn = xp.where(den > 0, num / xp.where(den > 0, den, 1), 0)
        if it % 2 == 0:
            gn = 0.5 * (gn + g)
            change = xp.linalg.norm(gn - g, axis=-1) / xp.maximum(xp.linalg.norm(gn, axis=-1), 1e-300)
            g = gn
            conv = to_numpy(change <= tol)
            if conv.all():
                break
        else:
            g = gn
    return g, it, conv


def reference_phase(g, ref):
    """g with each (channel, pol)'s phase set so that input ``ref[pol]`` is real and positive.

    g : complex (nchan, npol, nant); ref : int (npol,) input index per polarisation."""
    xp = get_xp(g)
    gr = xp.stack([g[:, p, int(r)] for p, r in enumerate(ref)], axis=1)                    # (c, p)
    ph = xp.where(xp.abs(gr) > 0, xp.conj(gr) / xp.maximum(xp.abs(gr), 1e-300), 1)
    return g * ph[..., None]


def _cycles_exp(xp, a, b, dtype):
    """exp(2 pi i a b) in ``dtype``, formed where ``xp`` computes: the cycles a b in float64, reduced to
    [-1/2, 1/2] before the exponential (a whole band's delay-search table is ~5e5 exponentials: formed
    beside the data, not copied across the bus)."""
    cyc = xp.asarray(a, xp.float64) * xp.asarray(b, xp.float64)
    cyc = cyc - xp.rint(cyc)
    return xp.exp((2j * math.pi) * cyc).astype(dtype)


def _median0(a):
    """The median over axis 0 where ``a`` lives, as a NumPy array (a GPU's arrays come back reduced)."""
    return to_numpy(get_xp(a).median(a, axis=0))


def smooth_across_channels(g, freq_hz, valid, window, max_delay_s):
    """Regularise per-channel gains across the band: a delay per input, then a running complex mean.

    g : complex (nchan, npol, nant); valid : bool (nchan, npol, nant) (solutions to trust).
    For each input the delay tau maximising |sum_c g_c exp(+2 pi i nu_c tau)| over a grid (1/8 of the
    band's resolution, within +-max_delay_s and the channel spacing's ambiguity, refined by a parabola)
    is removed, the result averaged over ``window`` channels (valid ones only), and the delay put back:
    a cable's delay and phase, times a slowly varying bandpass. Returns (smoothed g, delay_s (npol, nant)).
    Channels with no valid neighbour in the window get 0.
    """
    xp = get_xp(g)
    f = np.asarray(freq_hz, np.float64)
    nchan = f.size
    v = valid.astype(g.real.dtype)
    if nchan < 2 or window <= 1:
        return xp.where(valid, g, 0), np.zeros(g.shape[1:], np.float64)
    df = float(np.min(np.abs(np.diff(f))))
    bw = float(f.max() - f.min()) + df
    tmax = min(max_delay_s, 0.5 / df)
    step = 1.0 / (8.0 * bw)
    ntau = 2 * int(math.ceil(tmax / step)) + 1 if tmax > 0 else 1
    taus = (np.arange(ntau) - ntau // 2) * step
    fc = f - f.mean()                                    # centred: the fitted phase is the band-centre one
    E = _cycles_exp(xp, fc[:, None], taus[None, :], g.dtype)                                # (c, ntau)
    gv = (g * v).transpose(1, 2, 0)                                                         # (p, a, c)
    power = xp.abs(xp.matmul(gv, E))                                                        # (p, a, ntau)
    k = to_numpy(xp.argmax(power, axis=-1))
    pw = to_numpy(power)
    tau = taus[k]
    if ntau >= 3:   # parabolic refinement on the grid's neighbours
        km, kp = np.clip(k - 1, 0, ntau - 1), np.clip(k + 1, 0, ntau - 1)
        y0 = np.take_along_axis(pw, k[..., None], -1)[..., 0]
        ym = np.take_along_axis(pw, km[..., None], -1)[..., 0]
        yp = np.take_along_axis(pw, kp[..., None], -1)[..., 0]
        den = ym - 2 * y0 + yp
        inner = (k > 0) & (k < ntau - 1) & (den < 0)
        tau = tau + np.where(inner, 0.5 * (ym - yp) / np.where(inner, den, 1) * step, 0.0)
    rot = _cycles_exp(xp, fc[:, None, None], tau[None], g.dtype)                           # (c, p, a)
    r = g * rot * v                                                                         # (c, p, a)
    w = int(min(window, nchan))
    # running sums over channels (valid ones only): a box of w channels centred on each
    cs = xp.concatenate([xp.zeros((1,) + r.shape[1:], r.dtype), xp.cumsum(r, axis=0)])
    cv = xp.concatenate([xp.zeros((1,) + v.shape[1:], v.dtype), xp.cumsum(v, axis=0)])
    lo = np.clip(np.arange(nchan) - (w - 1) // 2, 0, None)
    hi = np.clip(lo + w, None, nchan)
    lo = np.clip(hi - w, 0, None)
    lo_d, hi_d = xp.asarray(lo), xp.asarray(hi)
    num = cs[hi_d] - cs[lo_d]
    cnt = cv[hi_d] - cv[lo_d]
    sm = xp.where(cnt > 0, num / xp.where(cnt > 0, cnt, 1), 0)
    return sm * xp.conj(rot), tau


def _abs2(z):
    """|z|^2 of a complex array, without the square root."""
    return z.real ** 2 + z.imag ** 2


def input_health(R, M, W, g, live, extra=None, scale=None):
    """Per-input figures, (nant, npol) float64 each, from the median over channels.

    R, M : complex (nchan, npol, nant, nant); W : (nchan, nant, nant) or broadcastable; g : (nchan, npol,
    nant); live : bool (npol, nant) inputs in the solve; extra, scale : None, or a model term E (R's shape)
    and its scale (nchan, npol): the model is then M + scale E, formed a chunk of channels at a time
    (:func:`model_chunk`). Returns a dict: ``gain_amp`` |g|, ``power`` the autocorrelation,
    ``power_per_gain`` power / |g|^2, ``residual`` sum_q W |R - g g* M|^2 / sum_q W |g g* M|^2 over the
    live inputs q, ``baselines`` the number of live baselines of weight > 0.
    """
    xp = get_xp(R)
    nant = R.shape[-1]
    idx = xp.arange(nant)
    lv = xp.asarray(live).astype(R.real.dtype)                                              # (p, a)
    W4 = W[:, None] if W.ndim == 3 else W
    ref = xp.empty(R.shape[:-1], R.real.dtype)
    res = xp.empty(R.shape[:-1], R.real.dtype)
    nbl = xp.empty(R.shape[:-1], xp.int64)
    for cs in solve_chunks(R):                       # a few (nant, nant) temporaries a chunk of channels
        Wl = (W4 if W4.shape[0] == 1 else W4[cs]) * lv[None, :, :, None] * lv[None, :, None, :]
        fit = g[cs, ..., :, None] * xp.conj(g[cs, ..., None, :])
        fit *= model_chunk(M, extra, scale, cs)
        ref[cs] = xp.sum(Wl * _abs2(fit), axis=-1)
        fit -= R[cs]                                                                        # -(the residual)
        res[cs] = xp.sum(Wl * _abs2(fit), axis=-1)
        nbl[cs] = xp.sum(Wl > 0, axis=-1)
        del fit, Wl
    rel = xp.where(ref > 0, res / xp.where(ref > 0, ref, 1), np.inf)
    power = R[..., idx, idx].real
    amp = xp.abs(g)
    ppg = xp.where(amp > 0, power / xp.where(amp > 0, amp, 1) ** 2, np.inf)
    med = lambda a: _median0(a).T                                                           # (c, p, a) -> (a, p)
    return {"gain_amp": med(amp), "power": med(power), "power_per_gain": med(ppg), "residual": med(rel),
            "baselines": med(nbl)}


def _choose_reference(amp, good, reference):
    """Reference input index per pol: ``reference`` if good, else the good input with the largest |g|."""
    ref = []
    for p in range(good.shape[1]):
        if reference >= 0 and good[reference, p]:
            ref.append(int(reference))
        else:
            a = np.where(good[:, p], amp[:, p], -np.inf)
            ref.append(int(np.argmax(a)))
    return np.array(ref)


def _robust_median(x, good):
    """Median of x over good inputs, per pol: (npol,)."""
    return np.array([np.median(x[good[:, p], p]) if good[:, p].any() else np.nan for p in range(x.shape[1])])


def fit_scale(R, M, E, g, W):
    """The scale s >= 0 per (channel, pol) minimising sum W |R - g g* (M + s E)|^2 with g held:
    s = Re sum W conj(A) (R - g g* M) / sum W |A|^2, A = g g* E. Returns float (nchan, npol).

    Formed as quadratic forms in g and a = |g|^2 (an identity, no approximation): with X = W conj(E),
    num = Re [g^H (X . R) g - a^T (X . M) a] and den = a^T (W |E|^2) a, so that no (nant, nant) product
    of the gains is ever made (three elementwise products and three batched matrix-vector products
    instead of ten full-size passes)."""
    xp = get_xp(R)
    a = _abs2(g)                                                                            # (..., nant)
    X = W * xp.conj(E)

    def quad(A, v):          # v^H A v, batched over the leading axes
        return xp.sum(xp.conj(v) * xp.matmul(A, v[..., None])[..., 0], axis=-1)
    num = (quad(X * R, g) - quad(X * M, a.astype(R.dtype))).real
    den = quad(W * _abs2(E), a).real
    return xp.clip(xp.where(den > 0, num / xp.where(den > 0, den, 1), 0), 0, None)


def solve_gains(R, M, xyz_m, freq_hz, station_flags=None, settings: SolveSettings | None = None, *, rounds=4,
                weights=None, extra=None, fits=2, g0=None, extra_scale0=None, saturated=None, flags0=None):
    """Gains, flags and quality from covariances R against the model M (module docstring).

    R, M : complex (nchan, npol, nant, nant), NumPy or CuPy (the solve runs where they live); R is the
        time-averaged covariance of the cable-corrected voltages. xyz_m : (nant, 3); freq_hz : (nchan,).
    station_flags : bool (nant, npol), inputs not to use (the station's flags, zero cable weights).
    weights : :func:`baseline_weights` for these positions, channels and ``min_baseline_lambda``, made
        once by a caller that solves often (None: made here).
    extra : None, or a model term E (R's shape) whose scale per channel and polarisation is fitted
        (:func:`fit_scale`, alternating with the gains ``fits`` times per round): the diffuse sky, whose
        analytic model's brightness is known to tens of per cent (:func:`bf_epic_blocks.sky.model.diffuse_model`).
        The flux scale stays the point sources' (M's). The fitted scales are ``info['extra_scale']``.
    saturated : bool (nant, npol), inputs whose samples clip too often to be trusted (flagged
        'saturated' and left out; :func:`clip_fraction`).
    g0, extra_scale0 : a start: the gains (nchan, npol, nant) and extra scales (nchan, npol) of the last
        solution (a live solver's; the gains drift slowly, so StEFCal then needs a few iterations).
    flags0 : str (nant, npol), the last solution's reasons: inputs it found deaf, noisy, residual or with
        few baselines start flagged, so that a round that flags nothing new ends the solve (a live solver's
        steady state: one round instead of two). Such an input comes back only in a solve without
        ``flags0``; a live solver makes one every minute.
    Returns a :class:`Solution` (NumPy). Raises ValueError when too few inputs remain good in a
    polarisation (:attr:`SolveSettings.min_good_fraction`) or no channel-pol converges.
    """
    s = settings or SolveSettings()
    xp = get_xp(R)
    nchan, npol, nant, _ = R.shape
    if M.shape != R.shape:
        raise ValueError(f"solve_gains: R is shaped {R.shape}, the model {M.shape}")
    sflag = np.zeros((nant, npol), bool) if station_flags is None else np.array(station_flags, bool)
    reasons = np.full((nant, npol), "", dtype=object)
    reasons[sflag] = "station"
    if saturated is not None:
        sat = np.asarray(saturated, bool) & ~sflag
        reasons[sat] = "saturated"
        sflag = sflag | sat
    idx = np.arange(nant)
    powr = _median0(R[..., idx, idx].real).T                                               # (a, p)
    nopow = ~sflag & ~(np.isfinite(powr) & (powr > 0))
    reasons[nopow] = "no-power"
    if flags0 is not None:
        f0 = np.asarray(flags0).astype(str)
        carried = (reasons == "") & np.isin(f0, ("deaf", "noisy", "residual", "few-baselines"))
        reasons[carried] = f0[carried]
    W = baseline_weights(xyz_m, freq_hz, s.min_baseline_lambda, xp=xp) if weights is None else weights
    W = W.astype(R.real.dtype, copy=False)
    if not bool(to_numpy(xp.any(W > 0))):
        raise ValueError(f"solve_gains: no baseline is longer than min_baseline_lambda = {s.min_baseline_lambda} "
                         f"wavelengths at {float(np.max(freq_hz)) / 1e6:.3f} MHz")
    mpow = _median0(xp.abs(M[..., idx, idx])).T                          # the point sources alone
    if not np.any(mpow > 0):
        raise ValueError("solve_gains: the model is empty (no source above the horizon, or zero flux)")
    g = xp.ones((nchan, npol, nant), R.dtype) if g0 is None else xp.array(g0, dtype=R.dtype)
    iters = 0
    conv = np.zeros((nchan, npol), bool)
    scale = None
    chunks = solve_chunks(R)
    if extra is not None:
        scale = xp.ones((nchan, npol), R.real.dtype) if extra_scale0 is None else \
            xp.asarray(extra_scale0).astype(R.real.dtype)
    for _ in range(rounds):
        good = reasons == ""
        live = xp.asarray(good.T)                                                           # (p, a)
        # channels are independent until the health figures: each chunk of channels runs its fits (StEFCal,
        # alternating with the diffuse term's scale) on its own, so that their temporaries are a chunk's
        most = 0
        for cs in chunks:
            Wl = (W if W.shape[0] == 1 else W[cs])[:, None] * live[None, :, :, None] * live[None, :, None, :]
            n = 0
            Mc = model_chunk(M, extra, scale, cs)
            for _ in range(fits if extra is not None else 1):
                gc, it, conv[cs] = stefcal(R[cs], Mc, Wl, g[cs], max_iter=s.max_iter, tol=s.tol)
                g[cs] = gc * live[None]
                n += it
                if extra is not None:
                    scale[cs] = fit_scale(R[cs], M[cs], extra[cs], g[cs], Wl)
                    Mc = model_chunk(M, extra, scale, cs)
            most = max(most, n)
            del Wl, Mc
        iters += most
        h = input_health(R, M, W, g, good.T, extra, scale)
        new = np.zeros_like(good)
        amp_med = _robust_median(h["gain_amp"], good)
        ppg_med = _robust_median(h["power_per_gain"], good)
        res_med = _robust_median(h["residual"], good)
        deaf = good & (h["gain_amp"] < s.deaf_below * amp_med)
        reasons[deaf] = "deaf"
        noisy = good & ~deaf & (h["power_per_gain"] > s.noisy_above * ppg_med)
        reasons[noisy] = "noisy"
        resid = good & ~deaf & ~noisy & (h["residual"] > s.residual_above * res_med)
        reasons[resid] = "residual"
        few = good & ~deaf & ~noisy & ~resid & (h["baselines"] < 3)
        reasons[few] = "few-baselines"
        new = deaf | noisy | resid | few
        if not new.any():
            break
    good = reasons == ""
    base = ~sflag
    for p in range(npol):
        if good[:, p].sum() < max(3, s.min_good_fraction * base[:, p].sum()):
            raise ValueError(f"solve_gains: only {int(good[:, p].sum())} of {int(base[:, p].sum())} inputs of pol {p} "
                             f"are good (need {s.min_good_fraction:.0%}); flags: "
                             + ", ".join(f"{r} {int((reasons[:, p] == r).sum())}" for r in REASONS
                                         if (reasons[:, p] == r).any()))
    if not conv.any():
        raise ValueError(f"solve_gains: StEFCal did not converge in any channel ({s.max_iter} iterations, tol {s.tol})")
    ref = _choose_reference(h["gain_amp"], good, s.reference)
    g = reference_phase(g, ref)
    valid = xp.asarray(np.broadcast_to(good.T[None], (nchan, npol, nant)) & conv[:, :, None])
    gs, tau = smooth_across_channels(g, freq_hz, valid, s.smooth_channels, s.max_delay_s)
    gs = gs.astype(xp.complex128).transpose(0, 2, 1)                                        # (c, a, p)
    amp = xp.abs(gs)
    keep = xp.asarray(good)[None] & (amp > 1e-6 * xp.nanmax(amp))     # a NaN gain is not kept
    gs = xp.where(keep, gs, 0)
    corr = xp.where(keep, 1.0 / xp.where(keep, gs, 1), 0)
    gs, corr = to_numpy(gs), to_numpy(corr)
    quality = {k: np.asarray(v, np.float64) for k, v in h.items()}
    quality.update(converged=conv, delay_s=np.asarray(tau, np.float64).T)
    flags = reasons != ""
    info = {"iterations": iters, "reference": ref.tolist(), "good_inputs": int(good.sum()),
            "extra_scale": None if scale is None else to_numpy(scale).tolist(),
            "baselines_used": int(to_numpy(xp.sum(W > 0))) // 2, "settings": s.to_dict()}
    return Solution(gs.astype(np.complex128), corr.astype(np.complex128), flags, reasons.astype(str), quality, info)


def gain_error(corrections, true_gains, good):
    """rms over good inputs of |c g / <c g> - 1|: the residual gain error of a solution.

    corrections, true_gains : complex (nchan, nant, npol); good : bool (nant, npol). The unobservable
    per-(channel, pol) phase and scale are removed by dividing by the complex median (real and imaginary
    parts separately) of c g over the good inputs. Returns (rms, per-input rms (nant, npol))."""
    e = np.asarray(corrections) * np.asarray(true_gains)
    out = np.zeros(e.shape)
    for p in range(e.shape[2]):
        sel = good[:, p]
        ref = np.median(e[:, sel, p].real, axis=1) + 1j * np.median(e[:, sel, p].imag, axis=1)
        out[:, :, p] = np.abs(e[:, :, p] / ref[:, None] - 1)
    per = np.sqrt(np.mean(out ** 2, axis=0))
    return float(np.sqrt(np.mean(per[good] ** 2))), per


class CovarianceSums:
    """Time-summed covariances of raw voltages, (nchan, npol, nant, nant), for the solver.

    ``add(x)`` takes a gulp (ntime, nchan, nant, npol) of complex voltages, or with ``ci4=True`` of 4-bit
    bytes (uint8, high nibble real). Integer voltages are summed exactly: per polarisation the Gram
    matrix of the rows [re; im] of every input (cuBLAS int8 GEMMs summed in int32 on a GPU,
    :func:`~.gemm.int_gram`; float32 GEMMs of sums kept below 2^24 on the CPU), held as integers across
    gulps and turned into complex covariances when read (``sum``, ``mean()``) or before an int32 sum could
    overflow. Complex voltages go through complex GEMMs. Cross-polarisation terms are not formed.
    ``sum`` is complex128 on the CPU, complex64 on a GPU (the solver's arrays share the card with the
    imager's).
    """

    #: samples an int32 Gram entry holds safely: 4-bit products are at most 64 per sample
    INT32_SAMPLES = (2**31 - 1) // 64

    def __init__(self, nchan, nant, npol, xp=np, chunk=128):
        self.xp, self.shape, self.chunk = xp, (nchan, npol, nant, nant), int(chunk)
        self._sum = xp.zeros(self.shape, xp.complex128 if xp is np else xp.complex64)
        self._gram = {}          # channel chunk start -> (npol, c, 2 nant, 2 nant) integer sums
        self._gram_n = 0
        self.ntime = 0
        self._count = None       # (nchan, nant, nant) samples each baseline kept, where some were flagged
        # a GPU's int8 rows of a chunk: one array for every gulp, since arrays made and freed each gulp split
        # the pool's blocks that the imager's own arrays need under a pool limit
        self._rows = Workspace()

    def reset(self):
        self._sum[...] = 0
        self._gram, self._gram_n = {}, 0
        self.ntime = 0
        self._count = None

    @property
    def sum(self):
        self._flush()
        return self._sum

    def mean(self):
        """The mean covariance: the sums over the samples each baseline kept (all of them, unless
        :meth:`add` was told of flagged ones), 0 where a baseline kept none."""
        if self.ntime == 0:
            raise ValueError("no samples accumulated")
        if self._count is None:
            return self.sum / self.ntime
        xp = self.xp
        n = self._count[:, None].astype(self._sum.real.dtype)
        return xp.where(n > 0, self.sum / xp.where(n > 0, n, 1), 0)

    def add(self, x, ci4=False, used=None, block=1):
        """Add a gulp. ``used``: None (every sample counts), or float (nt // block, nchan, nant), 1 where an
        input's samples of a block of ``block`` frames were kept, 0 where they were flagged (and are
        zeros): each baseline's mean is then over the samples both its inputs kept (counted by a GEMM of
        these masks per channel)."""
        xp = self.xp
        nt = int(x.shape[0])
        if nt == 0:
            return
        if used is not None:
            u = xp.ascontiguousarray(xp.asarray(used, xp.float32).transpose(1, 0, 2))        # (c, nj, a)
            n = xp.matmul(u.swapaxes(-1, -2), u).astype(xp.float64) * float(block)      # (c, a, a)
            if self._count is None:
                self._count = xp.full(n.shape, float(self.ntime))
            self._count += n
        elif self._count is not None:
            self._count += float(nt)
        if ci4:
            if self._gram_n + nt > self.INT32_SAMPLES:
                self._flush()
            self._add_ci4(x)
            self._gram_n += nt
        else:
            xc = xp.ascontiguousarray(x.transpose(1, 3, 2, 0)).astype(xp.complex64)         # (c, p, a, t)
            self._sum += xp.matmul(xc, xp.conj(xc).swapaxes(-1, -2)).astype(self._sum.dtype)
        self.ntime += nt

    def _add_ci4(self, b):
        from types import SimpleNamespace

        from .fused import _ci4_pairs
        from .gemm import int_gram
        from .layout import gram_rows
        xp = self.xp
        T, C, A, P = b.shape
        sel = SimpleNamespace(chan=None, ant=None, live=None)
        for c0 in range(0, C, self.chunk):   # channel chunks bound the temporaries
            c1 = min(C, c0 + self.chunk)
            if xp is not np:
                first = c0 not in self._gram
                if first:
                    self._gram[c0] = xp.empty((P, c1 - c0, 2 * A, 2 * A), xp.int32)
                G = self._gram[c0]
                Tp = -(-T // 16) * 16             # cuBLAS' integer GEMMs want time in multiples of 4
                # the lease is let go at once, so that the next chunk's take uses this array again (one
                # stream: the uses run in order)
                rows = self._rows.take(xp, (c1 - c0, A, 2, Tp), xp.int8)[0]
                bc = xp.ascontiguousarray(b)
                for p in range(P):
                    # (t, c, a) bytes -> rows (c, a, re/im, t) in one pass (skycal.cu)
                    get_kernel("imaging/skycal.cu", "skycal_rows")(
                        ((A + 31) // 32, (Tp + 31) // 32, c1 - c0), (32, 8),
                        (bc, rows, np.int32(T), np.int32(C), np.int32(A), np.int32(P), np.int32(c0), np.int32(p),
                         np.int32(Tp)))
                    int_gram(rows.reshape(c1 - c0, 2 * A, Tp), out=G[p], accumulate=not first)
                continue
            pairs = _ci4_pairs(np.ascontiguousarray(b[:, c0:c1]))                           # (t, c, a, p, 2)
            if c0 not in self._gram:
                self._gram[c0] = np.zeros((P, c1 - c0, 2 * A, 2 * A))
            G = self._gram[c0]
            step = (2**24 - 1) // 128          # float32 sums of 4-bit products stay exact below 2^24
            for t0 in range(0, T, step):
                rows = gram_rows(pairs[t0:t0 + step], sel).reshape(c1 - c0, A, P, 2, -1)     # (c, a, p, ri, t)
                for p in range(P):
                    G[p] += int_gram(np.ascontiguousarray(rows[:, :, p]).reshape(c1 - c0, 2 * A, -1))

    def _flush(self):
        """Integer Gram sums -> complex covariances: R = (rr + ii) + i (ir - ri), rows (input, re/im)."""
        for c0, G in self._gram.items():
            P, c, A2 = G.shape[0], G.shape[1], G.shape[2]
            A = A2 // 2
            g = G.reshape(P, c, A, 2, A, 2)
            for p in range(P):
                re = (g[p, :, :, 0, :, 0] + g[p, :, :, 1, :, 1]).astype(self._sum.real.dtype)
                im = (g[p, :, :, 1, :, 0] - g[p, :, :, 0, :, 1]).astype(self._sum.real.dtype)
                self._sum[c0:c0 + c, p] += re + 1j * im
        self._gram, self._gram_n = {}, 0
