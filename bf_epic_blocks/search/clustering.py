"""What the search's threshold crossings become: candidates.

:class:`Crossings` holds one push's crossings; :func:`cluster_crossings` groups crossings that are close
in time, sky position and DM (friends of friends) and keeps each group's highest S/N;
:func:`dm_sidelobe_snr` says what a bright dispersed burst puts into another DM trial (its "bow tie"),
so that the block can fold such sidelobes into the burst; :func:`refine_peak` places a candidate between
DM trials from its S/N across them.

The expected number of noise crossings, for independent Gaussian images, is exactly
``P(t_{W-1} > threshold / sqrt(1 + w / W))`` per trial (Student's t with W - 1 degrees of freedom:
the estimated mean and sigma come from W other values); :func:`expected_false_rate` gives it.
"""
from __future__ import annotations

import math

import numpy as np

from .dispersion import dm_delays

__all__ = ["Crossings", "cluster_crossings", "dm_sidelobe_snr", "expected_false_rate", "refine_peak"]

#: the part of a candidate's S/N hump across DM trials :func:`refine_peak` fits (see there)
PEAK_LEVEL = 0.6


class Crossings:
    """Threshold crossings of one push, host NumPy arrays of equal length.

    image : sequence image index at which the event starts at the reference (highest) frequency;
    end_image : the image index of the newest image in the boxcar (as pushed, before dedispersion
        alignment); series : DM-trial index (or channel with average_channels=False);
    width_index : index into ``widths``; pixel : pixel index; snr : float;
    frac : the fraction of the image's pixels over the threshold in that trial (series, value, width);
    skywide : 1 for a sky-wide crossing (``frac`` above the search's ``sky_fraction``: one crossing
    at the image's peak pixel stands for all of them), else 0.
    """

    FIELDS = ("image", "end_image", "series", "width_index", "pixel", "snr", "frac", "skywide")

    def __init__(self, **arrays):
        for k in self.FIELDS:
            setattr(self, k, np.asarray(arrays.get(k, ()), dtype=np.float64 if k in ("snr", "frac") else np.int64))

    def __len__(self):
        return int(self.snr.size)

    @classmethod
    def concat(cls, items):
        items = [c for c in items if len(c)]
        if not items:
            return cls()
        return cls(**{k: np.concatenate([getattr(c, k) for c in items]) for k in cls.FIELDS})

    def take(self, sel):
        return Crossings(**{k: getattr(self, k)[sel] for k in self.FIELDS})


def refine_peak(x, snr, level=PEAK_LEVEL, at=None):
    """Where between trials a candidate's S/N peaks: the vertex of a least-squares parabola through the
    contiguous run of trials around the highest S/N whose S/N is at least ``level`` times it, kept inside
    the run (the run's S/N-weighted mean where the fit does not curve down; the best trial where the run
    has fewer than three trials).

    x : (m,) increasing trial positions (DMs, or trial indices); snr : (m,) their S/N, NaN where unknown;
    at : the index in x of the trial the candidate was found in, or None.
    Returns a float in x's units; NaN where the peak cannot be placed: no finite S/N, a run that reaches
    the first or last trial given (the S/N is not seen to fall on both sides: a DM the band cannot
    measure, a hump cut by the trials' end, or a faint candidate whose hump does not stand out of the
    noise), or a run that does not hold ``at`` (the highest S/N nearby is another event's).

    Why: a burst wider than one image fills a boxcar over a range of trials -- a 6-image burst in the
    8-image boxcar is whole for sweeps up to two images off its own -- so the best trial is decided by
    noise and the tree's rounding anywhere on that plateau. The level: runs cut at 0.8 and 0.9 of the peak
    hold too few trials for the fit, and 0.5 reaches into the hump's uneven flanks; 0.6 did best on one
    set of simulated bursts and again on another. On a third (`tools/bench/bench_dm_accuracy.py`: 96
    channels over 19.2 MHz at 74 MHz, arrivals between images) the best trial was off by up to 4.7
    trials (rms 0.75-2.2) and this vertex by up to 1.6 (rms 0.29-0.64; within one trial for 57 of 60).
    """
    x, snr = np.asarray(x, np.float64), np.asarray(snr, np.float64)
    ok = np.isfinite(snr)
    if not ok.any():
        return float("nan")
    k = int(np.flatnonzero(ok)[np.argmax(snr[ok])])
    above = ok & (snr >= level * snr[k])
    lo = hi = k
    while lo > 0 and above[lo - 1]:
        lo -= 1
    while hi < len(x) - 1 and above[hi + 1]:
        hi += 1
    if lo == 0 or hi == len(x) - 1 or (at is not None and not lo <= at <= hi):
        return float("nan")
    xr, sr = x[lo:hi + 1], snr[lo:hi + 1]
    if len(xr) < 3:
        return float(x[k])
    a, b, _ = np.polyfit(xr - x[k], sr, 2)
    v = x[k] - b / (2 * a) if a < 0 else float(np.sum(xr * sr) / np.sum(sr))
    return float(min(max(v, xr[0]), xr[-1]))


def cluster_crossings(image, xy, series, snr, *, time_link, space_link, series_link):
    """Friends-of-friends groups of crossings; returns (labels (n,), index of each group's peak).

    Two crossings are friends when their ``image`` indices differ by at most ``time_link``, their
    sky positions ``xy`` (n, 2) (pixel-grid indices, or l/m) by at most ``space_link`` along each
    axis, and their ``series`` (DM trial) indices by at most ``series_link``. Groups are the
    connected components; each group's peak is its highest-S/N member. Host NumPy arrays.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree
    n = len(snr)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pts = np.column_stack([np.asarray(image, np.float64) / max(time_link, 1e-9),
                           np.asarray(xy, np.float64).reshape(n, 2) / max(space_link, 1e-12),
                           np.asarray(series, np.float64) / max(series_link, 1e-9)])
    pairs = cKDTree(pts).query_pairs(1.0 + 1e-9, p=np.inf, output_type="ndarray")
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)) if len(pairs) else \
        coo_matrix((n, n))
    ncomp, labels = connected_components(g, directed=False)
    snr = np.asarray(snr, np.float64)
    order = np.lexsort((-snr, labels))                 # by label, highest S/N first
    first = np.r_[True, labels[order][1:] != labels[order][:-1]]
    return labels, order[first]


def dm_sidelobe_snr(freq_hz, dt_s, bright, faint, slack=1):
    """The S/N a dispersed burst puts into a trial of another DM and time at its pixel: its DM
    sidelobe (the "bow tie" of a bright burst in DM and time).

    ``bright`` = (image, dm, width, snr): the burst as found (image: its first image at the band's
    highest channel, the search's event time); ``faint`` = (image, dm, width): the other trial's event.
    A burst of S/N S found with boxcar w_b puts into the faint trial's boxcar (w_f images from its
    sweep) the fraction of its channel-images the two sweeps share: with L_c images of overlap in
    channel c (each sweep's delays as :func:`dm_delays` rounds them, widened by ``slack`` images
    each side for the tree's rounding), S/N = S * sum_c L_c / (nchan * sqrt(w_b * w_f)).
    Independent of the noise level; 0 where the sweeps never meet in the band."""
    f = np.asarray(freq_hz, dtype=np.float64).ravel()
    (eb, dmb, wb, snr), (ef, dmf, wf) = bright, faint
    d = dm_delays([float(dmb), float(dmf)], f, dt_s)
    ab = int(eb) + d[0] - slack
    af = int(ef) + d[1] - slack
    over = np.minimum(ab + int(wb) + 2 * slack, af + int(wf) + 2 * slack) - np.maximum(ab, af)
    return float(snr) * float(np.clip(over, 0, None).sum()) / (f.size * math.sqrt(float(wb) * float(wf)))


def expected_false_rate(threshold, window, widths):
    """Probability that one (pixel, series, image) trial of boxcar width w exceeds ``threshold`` on
    independent Gaussian noise, for each w in ``widths`` (array). See the module docstring."""
    from scipy import stats
    w = np.asarray(widths, dtype=np.float64)
    return stats.t.sf(float(threshold) / np.sqrt(1.0 + w / window), df=window - 1)
