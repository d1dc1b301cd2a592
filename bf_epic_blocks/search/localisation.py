"""Where on the sky a candidate is, and what it puts elsewhere: the array's power pattern.

:func:`beam_power` and :class:`ArrayBeam` give what a unit point source puts into the images (full 3-D
antenna positions, no w approximation; :class:`ArrayBeam` as the imager makes each product, for many
source positions at once); :func:`locate_point_source` fits the point source that best explains an
event's S/N on every pixel. Host NumPy, float64.
"""
from __future__ import annotations

import numpy as np

from ..conventions import SPEED_OF_LIGHT_M_S

__all__ = ["beam_power", "ArrayBeam", "locate_point_source"]


def beam_power(xyz_m, freq_hz, lm_from, lm_to, *, remove_autocorr=False):
    """The array's power pattern: what a unit point source at ``lm_from`` (2,) puts into the image at
    the directions ``lm_to`` (n, 2), relative to its own peak, channel mean (host float64, (n,)).

    ``|sum_a exp(2 pi i nu/c r_a . (s_to - s_from))|^2 / N^2`` for the N antennas ``xyz_m`` (N, 3)
    (East/North/Up metres, unit weights, the full 3-D positions: no w approximation), s = (l, m, n);
    with ``remove_autocorr`` the image's own definition without the N self terms,
    ``(|sum|^2 - N) / (N^2 - N)``. 1 at ``lm_from``; a sidelobe of a burst of S/N S at ``lm_from``
    reaches about ``S * beam_power`` at ``lm_to`` (as far as the pixels' noise levels agree).
    """
    xyz = np.asarray(xyz_m, np.float64).reshape(-1, 3)
    f = np.atleast_1d(np.asarray(freq_hz, np.float64))
    n_ant = len(xyz)
    if n_ant == 0:
        return np.zeros(len(np.atleast_2d(lm_to)))
    ds = _s_of(lm_to) - _s_of(lm_from)                                 # (n, 3)
    phase = (2.0 * np.pi / SPEED_OF_LIGHT_M_S) * f[:, None, None] * (ds @ xyz.T)[None]   # (nchan, n, N)
    p = np.abs(np.exp(1j * phase).sum(axis=2)) ** 2                    # (nchan, n)
    if remove_autocorr:
        return ((p - n_ant) / max(n_ant * n_ant - n_ant, 1)).mean(axis=0)
    return (p / (n_ant * n_ant)).mean(axis=0)


class ArrayBeam:
    """The array's power pattern from any sky direction to a fixed set of pixels, as the imager makes
    it: what a unit point source at ``lm_from`` puts into each pixel's Stokes I image.

    ``sum_p w_p |B_p(q)|^2 |sum_a exp(2 pi i nu/c r_a . (s_q - s_from))|^2 / N_p^2`` (channel mean),
    for the antennas ``ants[p]`` (N_p, 3) of each polarisation p (East/North/Up metres, full 3-D:
    no w approximation), weights ``w_p`` summing to 1, and the imager's antenna-independent voltage
    pattern ``B_p`` at each pixel (``pattern_power`` (npix,) = sum_p w_p |B_p|^2, or None for 1).
    With ``remove_autocorr`` the N_p self terms are left out, ``(|sum|^2 - N_p) / (N_p^2 - N_p)``.

    The pixels' phase factors are made once (``max_channels`` channels evenly through the band stand
    for all of them; a narrow band's beam hardly changes across it), so many source positions cost
    one matrix product: :meth:`at`.
    """

    def __init__(self, ants, weights, freq_hz, lm_pixels, *, pattern_power=None, remove_autocorr=False,
                 max_channels=4):
        f = np.atleast_1d(np.asarray(freq_hz, np.float64))
        f = f[np.unique(np.rint(np.linspace(0, f.size - 1, min(int(max_channels), f.size))).astype(int))]
        self.k = 2.0 * np.pi * f / SPEED_OF_LIGHT_M_S                              # (C,) rad / m
        w = np.asarray(weights, np.float64)
        self.weights = w / w.sum()
        self.ants = [np.asarray(a, np.float64).reshape(-1, 3) for a in ants]
        self.remove_autocorr = bool(remove_autocorr)
        self.lm = np.asarray(lm_pixels, np.float64).reshape(-1, 2)
        sq = _s_of(self.lm)                                                        # (npix, 3)
        # exp(-i k r_a . s_q), (C, npix, N_p) per polarisation, complex64 (a beam to ~1e-6 is plenty)
        self._e = [np.exp(-1j * self.k[:, None, None] * (sq @ a.T)[None]).astype(np.complex64) for a in self.ants]
        self.pattern_power = None if pattern_power is None else np.asarray(pattern_power, np.float64)

    def at(self, lm_from):
        """(npos, npix) float64: the beam from each of the directions ``lm_from`` (npos, 2)."""
        s = _s_of(lm_from)                                                         # (npos, 3)
        out = np.zeros((len(s), len(self.lm)))
        for a, e, w in zip(self.ants, self._e, self.weights):
            n = len(a)
            if n == 0:
                continue
            v = np.exp(1j * self.k[:, None, None] * (a @ s.T)[None]).astype(np.complex64)   # (C, N_p, npos)
            p = np.abs(np.matmul(e, v)) ** 2                                       # (C, npix, npos)
            p = ((p - n) / max(n * n - n, 1)) if self.remove_autocorr else p / (n * n)
            out += w * p.mean(axis=0).T
        if self.pattern_power is not None:
            out *= self.pattern_power[None, :]
        return out


def _s_of(lm):
    """(n, 3) unit vectors (l, m, n) of directions (n, 2); n = 0 beyond the horizon."""
    lm = np.atleast_2d(np.asarray(lm, np.float64))
    return np.column_stack([lm, np.sqrt(np.clip(1.0 - (lm * lm).sum(axis=1), 0.0, None))])


def locate_point_source(snr_image, sigma, beam, lm0, radius, *, steps=13, levels=3):
    """Where on the sky a point source must be to make ``snr_image`` through ``beam``.

    snr_image : (npix,) an event's S/N at each pixel (its boxcar against its window);
    sigma : (npix,) those pixels' noise (the window's sigma, flux units); beam : :class:`ArrayBeam`
    on the same pixels; lm0 : (2,) where to look (the event's peak pixel); radius : half-width of the
    square searched about ``lm0`` (l, m units; a grid's cell: on a grid coarser than the beam a
    source between pixels shows in its nearest one at a small fraction of its peak).

    The model is ``snr(q) = A beam(t -> q) / sigma(q)``; for each trial position t the amplitude A is
    the least-squares one and the fit's score is the S/N variance it explains,
    ``(sum y m)^2 / sum m^2`` with ``m = beam / sigma``. A ``steps`` x ``steps`` grid of positions,
    refined ``levels - 1`` times about the best one. Returns ``(lm (2,), model (npix,) the fitted
    S/N at every pixel, explained fraction of sum y^2)``; pixels whose sigma is not > 0 or whose S/N
    is not finite take no part (their model is 0).
    """
    y = np.asarray(snr_image, np.float64)
    inv = np.zeros_like(y)
    sg = np.asarray(sigma, np.float64)
    ok = np.isfinite(y) & np.isfinite(sg) & (sg > 0)
    inv[ok] = 1.0 / sg[ok]
    y = np.where(ok, y, 0.0)
    centre, r = np.asarray(lm0, np.float64).reshape(2), float(radius)
    best = None
    for _ in range(max(1, int(levels))):
        g = np.linspace(-r, r, int(steps))
        t = centre + np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
        t = t[(t * t).sum(axis=1) < 1.0]                     # above the horizon
        if not len(t):
            break
        m = beam.at(t) * inv[None, :]                        # (npos, npix)
        ym, mm = m @ y, (m * m).sum(axis=1)
        score = np.where(mm > 0, ym * ym / np.where(mm > 0, mm, 1.0), -np.inf)
        score[ym <= 0] = -np.inf                             # a source adds power
        i = int(np.argmax(score))
        if best is None or score[i] >= best[0]:
            best = (score[i], t[i], ym[i] / mm[i] * m[i] if mm[i] > 0 else np.zeros_like(y))
        centre, r = best[1], 2.0 * r / (int(steps) - 1)
    yy = float(np.sum(y * y))
    if best is None or not np.isfinite(best[0]):
        return np.asarray(lm0, np.float64).reshape(2), np.zeros_like(y), 0.0
    return best[1], best[2], float(best[0] / yy) if yy > 0 else 0.0
