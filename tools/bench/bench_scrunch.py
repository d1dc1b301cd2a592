"""What searching the high DMs at half the time resolution would save, and what it would cost in S/N.

A prediction made before the change (none of this is in the search yet), for the whole band: 784
channels of 25 kHz from 74 MHz, one image per 0.64 ms, trials every sweep from DM 0 to 3.

Above some DM ``D1`` a channel's own smearing (8.3 us x DM x 25 kHz / f^3: 0.5 ms x DM at 74 MHz)
already spreads a burst over more than an image, so those trials could run on pairs of images summed
(1.28 ms): the channels pre-shifted by D1's delays, then a tree over the remaining sweeps at half the
rate. Cost, in units of one row-image of the full-rate tree (what ``tools/bench/bench_search.py`` times):

* full rate, DM 0..D1: the tree's rows for sweeps 0..s1 (``FDMTPlan.rows``), and its s1 + 1 trials'
  statistics;
* half rate, DM D1..Dmax: the channels summed in pairs and shifted (two adds per channel and
  image pair), a tree over (smax - s1) / 2 sweeps and its trials' statistics, each at half the rate.

The tree and the statistics are weighed by the whole band's measured GPU rates (``measured.json``
``search``: seconds per tree row-pixel-image and per trial-width-pixel-image).

S/N: a burst of intrinsic width ``w_int`` at DM d, its channel c smeared to max(w_int, smear(d, c)),
boxcar-searched (widths 1, 2, 4, 8 images at full rate; 1, 2, 4 at half) at its own trial, against
the same burst at full rate. Computed exactly for top-hat pulses on the sample grid: each channel left
off by the part of its delay a whole-sample shift cannot follow (half an image at full rate, a whole
one at half rate, at most), the arrival phase stepped through a half-rate sample; S/N ~ the band-summed
boxcar / sqrt(nchan * width).

usage: python tools/bench/bench_scrunch.py [--d1 0.75,1,1.25,1.5,2,3] [--widths-ms 0.32,0.64,2.56] [--json PATH]
"""
from __future__ import annotations

import argparse

import numpy as np

from benchlib import write_json

FREQ = 74e6 + 25e3 * np.arange(784)
DT = 16 / 25e3
DM_MAX = 3.0
WIDTHS = (1, 2, 4, 8)


def smear_s(dm, freq_hz, chan_hz=25e3):
    """A channel's own dispersion smearing (s): 8.3 us x DM x (channel width / MHz) / (f / GHz)^3."""
    return 8.3e-6 * dm * (chan_hz / 1e6) / (np.asarray(freq_hz) / 1e9) ** 3


def cost(d1, freq=FREQ, dt=DT, dm_max=DM_MAX, nw=len(WIDTHS), rates=None):
    """Seconds per second of data per pixel-equivalent, split and whole: dict with the full-rate tree
    alone (``full``), the split (``split``) and their ratio; ``rates`` (tree, statistics) per
    row-pixel-image and trial-width-pixel-image (default the GPU's in measured.json)."""
    from bf_epic_blocks.search import FDMTPlan
    from bf_epic_blocks.conventions import dispersion_delay_s
    if rates is None:
        from bf_epic_blocks.imaging.plan import load_table
        t = load_table()["search"]["gpu"]
        rates = (t["tree_s_per_row_pixel_image"], t["statistics_s_per_trial_width_pixel_image"])
    rt, rs = rates
    per_dm = float(dispersion_delay_s(1.0, freq.min(), freq.max())) / dt
    smax = int(np.rint(dm_max * per_dm))
    s1 = int(np.rint(min(d1, dm_max) * per_dm))
    ips = 1.0 / dt
    full = ips * (FDMTPlan(freq, smax).rows() * rt + (smax + 1) * nw * rs)
    lo = ips * (FDMTPlan(freq, s1).rows() * rt + (s1 + 1) * nw * rs)
    hi = 0.0
    if s1 < smax:
        s2 = -(-(smax - s1) // 2)                     # sweeps left, in half-rate images
        nw2 = max(1, nw - 1)                          # the widest boxcar is twice as long at half rate
        hi = (ips / 2) * (FDMTPlan(freq, s2).rows() * rt + (s2 + 1) * nw2 * rs + 2 * len(freq) * rt)
    return {"d1": d1, "full_s_per_s": full, "split_s_per_s": lo + hi, "ratio": (lo + hi) / full,
            "trials_full_rate": s1 + 1, "trials_half_rate": 0 if s1 >= smax else -(-(smax - s1) // 2) + 1}


def best_snr(lengths, phases, rate, widths):
    """Boxcar S/N (arbitrary units) of a band of top-hat pulses, channel c covering image-time
    [phases[c], phases[c] + lengths[c]) (in full-rate images), imaged at ``rate`` full-rate images per
    sample, at the best boxcar of ``widths`` samples and the best alignment: the band-summed series
    (each channel's overlap with each sample) against sqrt(nchan * width) -- the search's S/N."""
    nchan = len(lengths)
    t_end = int(np.ceil((phases + lengths).max() / rate)) + 2
    edges = np.arange(t_end + 1) * rate
    # overlap of [p, p + L) with each sample [edges[k], edges[k + 1])
    lo = np.maximum(edges[None, :-1], phases[:, None])
    hi = np.minimum(edges[None, 1:], (phases + lengths)[:, None])
    series = (np.clip(hi - lo, 0, None) / lengths[:, None]).sum(axis=0)       # unit fluence per channel
    best = 0.0
    for w in widths:
        if w > len(series):
            continue
        box = np.convolve(series, np.ones(w), mode="valid")
        best = max(best, float(box.max()) / np.sqrt(nchan * w * rate))
    return best


def snr_retained(dm, w_int_s, freq=FREQ, dt=DT, nphase=8, seed=1):
    """Mean and worst (over arrival phases) S/N at half rate over S/N at full rate, for a burst of
    intrinsic width ``w_int_s`` at ``dm``, each channel smeared to max(w_int, its own smearing). Each
    channel's true delay has a fractional part the search cannot follow: it shifts by whole samples,
    so after dedispersion channel c starts ``frac_c - round(frac_c)`` images off at full rate and
    ``frac_c - 2 round(frac_c / 2)`` at half rate (frac_c uniform over two images, fixed seed); the
    burst's own arrival phase steps through a half-rate sample."""
    L = np.maximum(w_int_s, smear_s(dm, freq)) / dt                              # in full-rate images
    frac = np.random.default_rng(seed).uniform(0.0, 2.0, len(freq))
    r1, r2 = frac - np.rint(frac), frac - 2 * np.rint(frac / 2)
    r = []
    for ph in np.arange(nphase) / nphase * 2:                                    # across a half-rate sample
        full = best_snr(L, ph + 2 + r1, 1, WIDTHS)
        half = best_snr(L, ph + 2 + r2, 2, WIDTHS[:-1])
        r.append(half / full)
    return float(np.mean(r)), float(np.min(r))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--d1", default="0.75,1,1.25,1.5,2,3", help="DMs above which trials run at half rate")
    ap.add_argument("--widths-ms", default="0.32,0.64,2.56", help="intrinsic burst widths")
    ap.add_argument("--json", help="write the result here")
    a = ap.parse_args(argv)
    d1s = [float(x) for x in a.d1.split(",")]
    wints = [float(x) / 1e3 for x in a.widths_ms.split(",")]
    rows = []
    print("# bench_scrunch: 784 channels from 74 MHz, 0.64-ms images, DM 0-3; cost weighed by the GPU's "
          "measured search rates; S/N at half rate / full rate for bursts at DM d1..3 (mean, worst phase)")
    hdr = "   d1  split/full  trials full/half  " + "  ".join(f"S/N {w * 1e3:.2f} ms: mean  worst" for w in wints)
    print(hdr)
    for d1 in d1s:
        c = cost(d1)
        dms = np.linspace(d1, DM_MAX, 5) if d1 < DM_MAX else np.array([])
        keep = {}
        for w in wints:
            vals = [snr_retained(d, w) for d in dms]
            keep[w] = (float(np.mean([v[0] for v in vals])) if vals else None,
                       float(np.min([v[1] for v in vals])) if vals else None)
        c["snr_half_over_full"] = {f"{w * 1e3:.2f}ms": {"mean": m, "worst": lo} for w, (m, lo) in keep.items()}
        rows.append(c)
        print(f"{d1:5.2f}  {c['ratio']:10.3f}  {c['trials_full_rate']:7d}/{c['trials_half_rate']:<7d}  "
              + "  ".join("       -      -" if m is None else f"      {m:7.3f} {lo:6.3f}" for m, lo in keep.values()))
    out = {"benchmark": "bench_scrunch", "freq_mhz": [FREQ.min() / 1e6, FREQ.max() / 1e6], "dt_s": DT,
           "dm_max": DM_MAX, "rows": rows}
    if a.json:
        write_json(a.json, out)
    return out


if __name__ == "__main__":
    main()
