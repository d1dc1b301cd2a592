"""RFIFlagBlock: interference detected in the voltages and zeroed before anything images or solves.

Thin adapter over :mod:`bf_epic_blocks.imaging.rfi`. Per gulp, on the ring's device (NumPy or CuPy, one
code path):

* **spectral kurtosis** per (block of ``block_frames`` samples, channel, stand, pol), thresholds for the
  false-alarm rate ``far`` from the 4-bit noise law (``ci4`` data) or the Gaussian one; a stand is flagged
  in a (block, channel) where either of its pols is: ``sk-low`` (a carrier), ``sk-high`` (bursty power);
* **impulses**: the power of each short block (one image's frames) summed over the band and the stands,
  against the gulp's median and robust spread: ``impulse`` flags every stand for that short block; the
  same per stand (``impulse-stand``) flags one stand's own spikes on that stand only;
* **static lists**: channels overlapping ``bad_freq_mhz`` ranges or an Orville ``bad_freq.txt``
  (``static``), flagged for the whole run.

Flagged (frame, channel, stand) samples are written as zeros (both pols), so every reader after this block
leaves them out: the imager's beams sum over the stands left, a channel wholly flagged images as zeros that
the band averages skip (:mod:`.integrate`), the transient search sees no power where there was
interference, and the gain solver's covariances lose those samples. The dtype passes through (4-bit data
stay 4-bit: zero is the byte 0).

``flag_stats``: per reason, the stand-samples flagged (a stand-sample: one stand, both pols, one channel,
one frame), the stand-samples seen, and per channel the fraction flagged; ``waterfall()``: flagged fraction
(time row, channel), rows merged in pairs as a long run grows so that memory stays bounded.
"""
from __future__ import annotations

import logging

import numpy as np

from ..imaging import rfi
from . import _compat
from ..runtime.dtypes import ci4_bytes
from ._compat import bfp, span_array, unpack_complex
from .headers import derived_header, efield_layout

log = logging.getLogger(__name__)

#: flag reasons counted, in the order of ``flag_stats['flagged']``
REASONS = ("static", "sk-low", "sk-high", "impulse", "impulse-stand", "spread")

#: waterfall rows kept before adjacent rows are merged (the time resolution halves)
MAX_ROWS = 2048


class RFIFlagBlock(bfp.TransformBlock):
    """Interference flags from the voltages (see the module docstring).

    Parameters
    ----------
    iring : E-field ring (labels time, freq, station, pol); ci4, ci8 or complex float.
    far : false-alarm rate of the spectral-kurtosis test, in (0, 1).
    block_frames : samples per spectral-kurtosis block (>= 64); a gulp's last, shorter block is tested as
        it is when it holds at least 64 samples, else left unflagged by the SK test (counted ``untested``).
    impulse_frames : samples per short block of the impulse detector (the imager's ``accumulate``).
    impulse_sigma : threshold of the impulse detector in robust standard deviations.
    bad_freq_ranges : [(lo_hz, hi_hz), ...] always flagged.
    spread : where more than this fraction of the live stands is flagged in a (frame, channel), every
        stand is (reason ``spread``): the interference is the array's, and an image of part of the array
        would be (n / N_A)^2 of the whole's.
    Output: the voltages with flagged stand-samples zeroed; header ``flagging`` records the settings and
    the static channels.
    """

    def __init__(self, iring, far=1e-3, block_frames=1024, impulse_frames=16, impulse_sigma=6.0,
                 bad_freq_ranges=(), spread=0.1, *args, **kwargs):
        super().__init__(iring, *args, **kwargs)
        if not 0.0 < float(far) < 1.0:
            raise ValueError(f"RFIFlagBlock: far (false-alarm rate) must be in (0, 1), got {far!r}")
        if int(block_frames) < rfi.MIN_M_QUANTISED:
            raise ValueError(f"RFIFlagBlock: block_frames must be >= {rfi.MIN_M_QUANTISED}, got {block_frames!r}")
        if int(impulse_frames) < 1 or not impulse_sigma > 0:
            raise ValueError(f"RFIFlagBlock: impulse_frames >= 1 and impulse_sigma > 0, got {impulse_frames!r}, "
                             f"{impulse_sigma!r}")
        if not 0.0 <= float(spread) < 1.0:
            raise ValueError(f"RFIFlagBlock: spread must be in [0, 1), got {spread!r}")
        self.far, self.block_frames, self.spread = float(far), int(block_frames), float(spread)
        self.impulse_frames, self.impulse_sigma = int(impulse_frames), float(impulse_sigma)
        self.bad_freq_ranges = [tuple(map(float, r)) for r in bad_freq_ranges]
        self.flag_stats = {"seen": 0, "flagged": dict.fromkeys(REASONS, 0), "flagged_any": 0, "untested": 0,
                           "gulps": 0}
        self._rows, self._row_frames, self._pending = [], None, None
        self._chan_flagged = None

    def define_valid_input_spaces(self):
        return "any"

    def on_sequence(self, iseq):
        ihdr = iseq.header
        lay = efield_layout(ihdr, "RFIFlagBlock")
        self._lay = lay
        space = _compat.space_of(self.irings[0]) if hasattr(self, "irings") else "system"
        if space == "cuda":
            import cupy
            self._xp = cupy
        else:
            self._xp = np
        nchan = lay["nchan"]
        freq = np.asarray(lay["freq_hz"], np.float64)
        bw = float(np.median(np.diff(freq))) if nchan > 1 else float(lay.get("chan_bw_hz", 25e3))
        static = rfi.channel_mask(freq, self.bad_freq_ranges, abs(bw)) if self.bad_freq_ranges else \
            np.zeros(nchan, bool)
        if static.all():
            raise ValueError(f"RFIFlagBlock: the bad-frequency list covers every channel ({nchan}, "
                             f"{freq.min() / 1e6:.3f}-{freq.max() / 1e6:.3f} MHz): there is nothing left to image")
        self._static_host = static
        self._static = self._xp.asarray(static)
        self._bits = 4 if lay["dtype"] == "ci4" else None
        self._flagged_stands = lay["flags"].any(axis=1)            # the station's own: never counted here
        if self._chan_flagged is None or self._chan_flagged.shape[0] != nchan:
            self._chan_flagged = np.zeros(nchan, np.int64)
            self._chan_seen = 0
        ohdr = derived_header(ihdr)
        ohdr["flagging"] = {"far": self.far, "block_frames": self.block_frames,
                            "impulse_frames": self.impulse_frames, "impulse_sigma": self.impulse_sigma,
                            "static_channels": int(static.sum())}
        log.info("RFIFlagBlock %s: spectral kurtosis in blocks of %d frames (false-alarm rate %g, %s noise law), "
                 "impulses in %d-frame blocks at %g sigma, %d channels on the static list",
                 ihdr.get("name"), self.block_frames, self.far, "4-bit" if self._bits else "Gaussian",
                 self.impulse_frames, self.impulse_sigma, int(static.sum()))
        return ohdr

    def _power_sums(self, raw, m):
        if self._lay["dtype"] == "ci4" and raw.dtype == np.uint8:
            return rfi.power_sums(raw, m, ci4=True)
        return rfi.power_sums(unpack_complex(raw, self._lay["dtype"]), m)

    def _plain(self, a):
        """A span array as plain numbers (n, nchan, nstand, npol[, bytes]): ci4 as its bytes, other packed
        integer pairs as bytes on a last axis, so that zeroing is one ``where``."""
        if self._lay["dtype"] == "ci4":
            return ci4_bytes(a)
        if getattr(a.dtype, "names", None):
            return a.view(self._xp.uint8).reshape(tuple(a.shape) + (-1,))
        return a

    def flags(self, raw):
        """keep (n, nchan, nstand) bool and per-reason masks for one gulp ``raw`` (n, nchan, nstand, npol...).

        Impulses are found first, and the short blocks they flag across the band are left out of the
        spectral-kurtosis sums (each block's SK then uses the samples left), so that a 1-ms spark costs its
        own milliseconds and not the 41 ms of every block it falls in."""
        xp = self._xp
        n, nchan, nstand = raw.shape[:3]
        m, A = self.block_frames, self.impulse_frames
        masks = {"static": xp.broadcast_to(self._static[None, :, None], (n, nchan, nstand))}
        # impulses: short blocks of A frames, needing three to form a reference
        imp = xp.zeros((n, nchan, nstand), bool)
        imp_st = xp.zeros((n, nchan, nstand), bool)
        ns = n // A
        allf_host = np.zeros(ns, bool)
        if ns >= 3:
            S1, _ = self._power_sums(raw[:ns * A], A)
            S1 = S1.reshape(S1.shape[:3] + (-1,)).sum(axis=3)                  # (ns, nchan, nstand)
            S1 = xp.where(self._static[None, :, None], 0.0, S1)               # listed channels carry no weight
            allf = rfi.broadband_flags(S1, self.impulse_sigma)                 # (ns,)
            per = rfi.broadband_flags(S1, self.impulse_sigma, per_input=True)  # (ns, nstand)
            imp[:ns * A] = xp.repeat(allf, A)[:, None, None]
            imp_st[:ns * A] = xp.repeat(per & ~allf[:, None], A, axis=0)[:, None, :]
            allf_host = _host(allf).astype(bool)
        masks["impulse"], masks["impulse-stand"] = imp, imp_st
        # spectral kurtosis: whole blocks of m and a last shorter block of at least 64 samples, without the
        # impulses' short blocks
        sk_low = xp.zeros((n, nchan, nstand), bool)
        sk_high = xp.zeros((n, nchan, nstand), bool)
        hit = np.zeros(n, bool)
        hit[:ns * A] = np.repeat(allf_host, A)
        x = raw
        if hit.any():
            k = xp.asarray(~hit).reshape((n,) + (1,) * (raw.ndim - 1))
            x = xp.where(k, raw, xp.zeros((), raw.dtype))
        pos = 0
        while pos < n:
            mm = min(m, n - pos)
            if mm < rfi.MIN_M_QUANTISED:
                self.flag_stats["untested"] += mm * nchan * nstand
                break
            nb = (n - pos) // mm
            S1, S2 = self._power_sums(x[pos:pos + nb * mm], mm)
            reason = xp.zeros(S1.shape, xp.int8)
            used = mm - hit[pos:pos + nb * mm].reshape(nb, mm).sum(axis=1)     # samples left per block
            for u in np.unique(used):
                if u < rfi.MIN_M_QUANTISED:
                    continue                                                   # mostly impulse: flagged as such
                sel = np.flatnonzero(used == u)
                _, r = rfi.sk_flags(S1[sel], S2[sel], int(u), self.far, bits=self._bits)
                reason[xp.asarray(sel)] = r
            reason = reason.reshape(reason.shape[:3] + (-1,))               # (nb, nchan, nstand, npol)
            sk_low[pos:pos + nb * mm] = xp.repeat((reason == 1).any(axis=3), mm, axis=0)
            sk_high[pos:pos + nb * mm] = xp.repeat((reason == 2).any(axis=3), mm, axis=0)
            pos += nb * mm
        masks["sk-low"], masks["sk-high"] = sk_low, sk_high
        # interference that many stands see (a transmitter, a spark) is the array's: its (frame, channel)
        # is flagged for every stand, so that an image never sums a part of the array (whose beam would be
        # (n / N_A)^2 of the whole's); a few stands' own interference stays on those stands
        per_stand = sk_low | sk_high | imp_st
        nlive = max(1, int((~self._flagged_stands).sum()))
        wide = per_stand.sum(axis=2) > self.spread * nlive                   # (n, nchan)
        masks["spread"] = xp.broadcast_to(wide[:, :, None], (n, nchan, nstand)) & ~per_stand
        bad = masks["static"] | per_stand | imp | masks["spread"]
        return ~bad, masks

    def on_data(self, ispan, ospan):
        raw = self._plain(span_array(ispan))
        out = self._plain(span_array(ospan))
        n = int(raw.shape[0])
        xp = self._xp
        with _compat.stream_context():
            keep, masks = self.flags(raw)
            live = xp.asarray(~self._flagged_stands)[None, None, :]
            k = keep.reshape(keep.shape + (1,) * (raw.ndim - 3))
            out[:n] = xp.where(k, raw, xp.zeros((), raw.dtype))
            # one transfer per gulp: the counts by reason, and per channel
            counts = xp.stack([(masks[r] & live).sum() for r in REASONS] + [(~keep & live).sum()])
            per_chan = (~keep & live).sum(axis=(0, 2))
            counts, per_chan = _host(counts), _host(per_chan)
        nlive = int((~self._flagged_stands).sum())
        st = self.flag_stats
        st["seen"] += n * self._lay["nchan"] * nlive
        for r, c in zip(REASONS, counts[:-1]):
            st["flagged"][r] += int(c)
        st["flagged_any"] += int(counts[-1])
        st["gulps"] += 1
        self._chan_flagged += per_chan.astype(np.int64)
        self._chan_seen += n * nlive
        self._add_row(per_chan / max(1, n * nlive), n)
        if counts[-1]:
            log.debug("RFIFlagBlock: gulp %d: %.3f%% of the stand-samples flagged (%s)", st["gulps"],
                      100.0 * counts[-1] / max(1, n * self._lay["nchan"] * nlive),
                      ", ".join(f"{r} {int(c)}" for r, c in zip(REASONS, counts[:-1]) if c))
        return n

    def _add_row(self, frac, n):
        """One waterfall row per gulp; past MAX_ROWS, adjacent rows merge (each then spans twice the frames)."""
        if self._row_frames is None:
            self._row_frames = n                      # a row per gulp to begin with
        if self._pending is None:
            self._pending, self._pending_n = frac * n, n
        else:
            self._pending, self._pending_n = self._pending + frac * n, self._pending_n + n
        if self._pending_n >= self._row_frames:
            self._rows.append(self._pending / self._pending_n)
            self._pending = None
            if len(self._rows) >= MAX_ROWS:
                self._rows = [(a + b) / 2 for a, b in zip(self._rows[0::2], self._rows[1::2])]
                self._row_frames *= 2

    def waterfall(self):
        """(rows, nchan) flagged fraction per time row and channel, and the frames each row spans (a row's
        frames are at least that; the first rows of a run that grew are merged in pairs)."""
        rows = list(self._rows) + ([self._pending / self._pending_n] if self._pending is not None else [])
        return (np.array(rows) if rows else np.zeros((0, len(self._static_host)))), self._row_frames or 0

    def summary(self):
        """The run's flag counts: fractions of the stand-samples seen, by reason and in all, and per channel."""
        st = self.flag_stats
        seen = max(1, st["seen"])
        return {"fraction_flagged": st["flagged_any"] / seen,
                "by_reason": {r: c / seen for r, c in st["flagged"].items()},
                "stand_samples_seen": st["seen"], "stand_samples_flagged": st["flagged_any"],
                "untested": st["untested"], "static_channels": int(self._static_host.sum()),
                "channel_fraction": (self._chan_flagged / max(1, self._chan_seen)).tolist()}


def _host(a):
    return a.get() if hasattr(a, "get") else np.asarray(a)


def rfi_flag(iring, *args, **kwargs):
    """Factory for :class:`RFIFlagBlock`."""
    return RFIFlagBlock(iring, *args, **kwargs)
