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
from ..runtime.dtypes import ci4_bytes
from . import _compat
from ._compat import bfp, span_array, to_numpy, unpack_complex
from .headers import derived_header, efield_layout
from .nonfinite import lookup_tally, register_tally

log = logging.getLogger(__name__)

#: flag reasons counted, in the order of ``flag_stats['flagged']``
REASONS = rfi.COUNTED[:-1]

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
    weights : a :class:`FlagWeights` the block fills for the imager that reads it (None: none).
    report, report_every_s : a callable ``report(block)`` run every ``report_every_s`` seconds of data (the
        runner writes the occupancy table and waterfall so far, so a live run's are never older than that).
    spread : where more than this fraction of the live stands is flagged in a (frame, channel), every
        stand is (reason ``spread``): the interference is the array's, and an image of part of the array
        would be (n / N_A)^2 of the whole's.
    Output: the voltages with flagged stand-samples zeroed; header ``flagging`` records the settings and
    the static channels.
    """

    #: the imager waits for every gulp the flagger writes: its kernels go first
    stream_priority = "high"

    def __init__(self, iring, far=1e-3, block_frames=1024, impulse_frames=16, impulse_sigma=6.0,
                 bad_freq_ranges=(), spread=0.1, weights=None, report=None, report_every_s=60.0, *args, **kwargs):
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
        if int(block_frames) % int(impulse_frames):
            raise ValueError(f"RFIFlagBlock: block_frames ({block_frames}) must be a multiple of impulse_frames "
                             f"({impulse_frames})")
        self.far, self.block_frames, self.spread = float(far), int(block_frames), float(spread)
        self.weights = weights
        self.report, self.report_every_s, self._frames_since_report = report, float(report_every_s), 0
        self.impulse_frames, self.impulse_sigma = int(impulse_frames), float(impulse_sigma)
        self.bad_freq_ranges = [tuple(map(float, r)) for r in bad_freq_ranges]
        self.flag_stats = {"seen": 0, "flagged": dict.fromkeys(REASONS, 0), "flagged_any": 0, "untested": 0,
                           "gulps": 0}
        self._rows, self._row_frames, self._pending = [], None, None
        self._chan_flagged = None
        self._which_cache = (None, None)          # (gulp shape, each short block's SK block on the device)

    def define_valid_input_spaces(self):
        return "any"

    def on_sequence(self, iseq):
        ihdr = iseq.header
        lay = efield_layout(ihdr, "RFIFlagBlock")
        self._lay = lay
        self._xp = _compat.input_xp(self)
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
        self._live = self._xp.asarray(~self._flagged_stands)
        self._nlive = int((~self._flagged_stands).sum())
        self._tag0, self._frame = int(lay["time_tag"]), 0
        if self.weights is not None:
            self.weights.begin(self._tag0)
        if self._chan_flagged is None or self._chan_flagged.shape[0] != nchan:
            self._chan_flagged = np.zeros(nchan, np.int64)
            self._chan_seen = 0
        ohdr = derived_header(ihdr)
        self.tally = new_flag_tally(lay["ticks_per_frame"])
        ohdr["flagging"] = {"far": self.far, "block_frames": self.block_frames,
                            "impulse_frames": self.impulse_frames, "impulse_sigma": self.impulse_sigma,
                            "static_channels": int(static.sum()), "tally": self.tally.id,
                            "ticks_per_frame": int(lay["ticks_per_frame"])}
        log.info("RFIFlagBlock %s: spectral kurtosis in blocks of %d frames (false-alarm rate %g, %s noise law), "
                 "impulses in %d-frame blocks at %g sigma, %d channels on the static list",
                 ihdr.get("name"), self.block_frames, self.far, "4-bit" if self._bits else "Gaussian",
                 self.impulse_frames, self.impulse_sigma, int(static.sum()))
        return ohdr

    def _bytes(self, a):
        """A span array's bytes, (n, nchan, nstand, B): B bytes per stand (its pols' samples, any format),
        so that zeroing a stand is zeroing its bytes."""
        if self._lay["dtype"] == "ci4":
            a = ci4_bytes(a)
        elif getattr(a.dtype, "names", None) or a.dtype != np.uint8:
            a = a.view(self._xp.uint8)
        return a.reshape(tuple(a.shape[:3]) + (-1,))

    def process(self, raw, out):
        """Detect, zero and count one gulp: ``raw`` the span's array (n, nchan, nstand, npol), ``out`` the
        output span's; out[:n] gets the voltages with the flagged stand-samples zeroed.

        Returns (cnt, frames, summary): cnt int32 (ns, nchan, 7) on the ring's device, the live stands
        flagged per short block j (frames [j a, (j + 1) a), a = ``impulse_frames``, the last one shorter
        where a does not divide n) and channel, by reason (:data:`~bf_epic_blocks.imaging.rfi.COUNTED`:
        REASONS, then any); frames (ns,) host int; summary the host figures of :meth:`_summarise`.

        Impulses are found first, and the short blocks they flag across the band are left out of the
        spectral-kurtosis sums (each block's SK then uses the samples left), so that a 1-ms spark costs its
        own milliseconds and not the 41 ms of every block it falls in. The gulp is first flagged as if no
        impulse were found, and the counts and the impulses come to the host in one copy; only where an
        impulse was found (rare) is the spectral kurtosis taken again without it and the gulp flagged again.
        On a GPU that is one wait a gulp and no copy from the host: a copy that waits for queued kernels
        waits inside the CUDA driver and holds up every other thread's CUDA calls (the imager's)."""
        xp, lay = self._xp, self._lay
        n, nchan, nstand = (int(v) for v in raw.shape[:3])
        m, a = self.block_frames, self.impulse_frames
        ci4 = lay["dtype"] == "ci4"
        x = ci4_bytes(raw) if ci4 else unpack_complex(raw, lay["dtype"])
        x = x.reshape(x.shape[:3] + (-1,))                                    # (n, nchan, nstand, npol)
        npol = int(x.shape[3])
        group = npol if npol <= 32 and not npol & (npol - 1) else 1
        nfull, ns = n // a, -(-n // a)
        S1, S2, Sa = rfi.block_power(x, m, a, ci4=ci4, group=group)
        P = Sa.reshape(Sa.shape[:3] + (-1,)).sum(axis=3) if Sa.shape[3] > 1 else Sa.reshape(Sa.shape[:3])
        frames = np.full(ns, a, np.int64)
        if ns > nfull:
            frames[-1] = n - nfull * a
        imp = xp.zeros(ns, bool)
        imp_st = xp.zeros((ns, nstand), bool)
        if nfull >= 3:
            if self._static_host.any():
                P = xp.where(self._static[None, :, None], xp.float32(0.0), P)  # listed channels weigh nothing
            per = rfi.broadband_flags(P, self.impulse_sigma, per_input=True)   # (nfull, nstand)
            allf = rfi.broadband_flags(rfi.band_power(P, per, self._live), self.impulse_sigma)   # (nfull,)
            imp[:nfull] = allf
            imp_st[:nfull] = per & ~allf[:, None]
        # spectral kurtosis per block of m (a last block of at least 64 samples as it is)
        nb = n // m
        blocks = [(k * m, m) for k in range(nb)]
        if n - nb * m >= rfi.MIN_M_QUANTISED:
            blocks.append((nb * m, n - nb * m))
        elif n - nb * m:
            self.flag_stats["untested"] += (n - nb * m) * nchan * nstand
        which = self._which(ns, a, m, blocks)

        def flag(code):                       # zero and count by the SK codes, the impulses and the list
            cnt = rfi.apply_flags(self._bytes(raw), self._bytes(out[:n]), code, which, imp, imp_st, self._static,
                                  self._live, a, self.spread * max(1, self._nlive))
            return cnt, self._summarise(cnt, frames, imp, imp_st)

        cnt, summary = flag(self._sk_codes(x, S1, S2, blocks, np.zeros(n, bool), None, ci4))
        if summary["impulse"] or summary["stand_spark"]:
            # found: the SK again without the impulses' samples (and each sparking stand without its own)
            both = to_numpy(xp.concatenate([imp[:, None], imp_st], axis=1))
            imp_h, st_h = both[:, 0], both[:nfull, 1:]
            hit = np.repeat(imp_h, frames)                                    # (n,) frames of band-wide impulses
            if nb and hit[:nb * m].any():                                     # the whole blocks' sums without them
                S1, S2, _ = rfi.block_power(x[:nb * m], m, a, ci4=ci4, group=group, skip=imp_h[:nb * m // a])
            cnt, summary = flag(self._sk_codes(x, S1, S2, blocks, hit, st_h, ci4))
        return cnt, frames, summary

    def _which(self, ns, a, m, blocks):
        """int32 (ns,) on the ring's device: each short block's SK block (m is a multiple of a: a short block
        lies in one), -1 past the tested frames; made once per gulp shape (a copy from the host)."""
        key = (ns, a, m, tuple(blocks))
        if self._which_cache[0] != key:
            which = np.minimum(np.arange(ns) * a // m, max(len(blocks) - 1, 0)).astype(np.int32)
            which[(np.arange(ns) * a) >= sum(mm for _, mm in blocks)] = -1
            self._which_cache = (key, self._xp.asarray(which))
        return self._which_cache[1]

    def _sk_codes(self, x, S1, S2, blocks, hit, st_h, ci4):
        """uint8 (len(blocks), nchan, nstand) SK codes (:func:`~..imaging.rfi.sk_code`) of the blocks [t0,
        t0 + mm), from the whole blocks' sums S1, S2 (without the frames ``hit`` (n,) host bool: band-wide
        impulses); a last, shorter block is summed here. ``st_h`` (nfull, nstand) host bool or None: the
        stands' own sparks, left out of each such stand's SK."""
        xp = self._xp
        nb = S1.shape[0]
        code = xp.zeros((len(blocks),) + tuple(x.shape[1:3]), xp.uint8)
        for i, (t0, mm) in enumerate(blocks):
            used = mm - int(hit[t0:t0 + mm].sum())
            if used < rfi.MIN_M_QUANTISED:
                continue                                                      # mostly impulse: flagged as such
            if i < nb:
                s1, s2 = S1[i:i + 1], S2[i:i + 1]
            else:                                                             # the last, short block
                part = x[t0:t0 + mm]
                if used < mm:
                    k = xp.asarray(~hit[t0:t0 + mm]).reshape((mm,) + (1,) * (part.ndim - 1))
                    part = xp.where(k, part, xp.zeros((), part.dtype))
                s1, s2 = rfi.power_sums(part, mm, ci4=ci4)
            code[i] = rfi.sk_code(s1, s2, used, self.far, bits=self._bits)[0]
            if st_h is not None and st_h.any():
                self._sk_without_own_sparks(code[i], x, t0, mm, hit[t0:t0 + mm], st_h, ci4)
        return code

    def _summarise(self, cnt, frames, imp, imp_st):
        """The gulp's figures on the host, in one copy from the device: a dict of ``counts`` (7,) float64 (the
        stand-samples flagged by REASONS, then any), ``per_chan`` (nchan,), ``used`` (ns, nchan) the live
        stands left per short block, ``stand_imp`` (ns,) bool (a live stand's own spark counted), ``partial``
        and ``wholly`` (some (short block, channel) kept part of the live stands / none), and ``impulse``,
        ``stand_spark``: whether any band-wide impulse, or any stand's own spark, was found."""
        xp, nl = self._xp, self._nlive
        ns, nchan = int(cnt.shape[0]), int(cnt.shape[1])
        fr = int(frames[0]) if (frames == frames[0]).all() else xp.asarray(frames)[:, None]
        used = nl - cnt[..., -1]                                             # (ns, nchan) stands left
        by_reason = (cnt.sum(axis=1, dtype=xp.int64) * fr).sum(axis=0)      # (7,): REASONS, then any
        per_chan = (cnt[..., -1].astype(xp.int64) * fr).sum(axis=0)          # (nchan,)
        flags = xp.stack([((used > 0) & (used < nl)).any(), (used == 0).any(), imp.any(), imp_st.any()])
        stand_imp = cnt[..., REASONS.index("impulse-stand")].max(axis=1) > 0  # (ns,) a stand's own spark
        host = to_numpy(xp.concatenate([by_reason.astype(xp.float64), per_chan.astype(xp.float64),
                                        stand_imp.astype(xp.float64), flags.astype(xp.float64),
                                        used.reshape(-1).astype(xp.float64)]))
        k = len(REASONS) + 1
        out = {"counts": host[:k], "per_chan": host[k:k + nchan], "stand_imp": host[k + nchan:k + nchan + ns] > 0}
        f = host[k + nchan + ns:k + nchan + ns + 4] > 0
        out.update(partial=bool(f[0]), wholly=bool(f[1]), impulse=bool(f[2]), stand_spark=bool(f[3]),
                   used=host[k + nchan + ns + 4:].reshape(ns, nchan))
        return out

    def _sk_without_own_sparks(self, code, x, t0, mm, hit, st_h, ci4):
        """A stand whose own spark was flagged in a short block of the SK block [t0, t0 + mm) has its SK
        taken again without that spark's samples (nor the band-wide impulses' ``hit``), into ``code``
        (nchan, nstand) in place: otherwise the spark raises the stand's kurtosis in every channel and the
        stand is flagged for the whole block, a step in the array's beam across the band at the block's
        edges that the search sees as a burst at DM 0. Sparks are rare, so this is a loop over the stands
        that had one (none in most gulps)."""
        a = self.impulse_frames
        j0, j1 = t0 // a, min(st_h.shape[0], -(-(t0 + mm) // a))
        sub = st_h[j0:j1]
        for s in np.flatnonzero(sub.any(axis=0)):
            bad = hit.copy()
            for j in j0 + np.flatnonzero(sub[:, s]):
                bad[max(j * a - t0, 0):min((j + 1) * a - t0, mm)] = True
            used = mm - int(bad.sum())
            if used < rfi.MIN_M_QUANTISED:
                code[:, s] = 0                                    # mostly spark: flagged as such
                continue
            keep = self._xp.asarray(~bad).reshape((mm,) + (1,) * (x.ndim - 1))
            part = x[t0:t0 + mm, :, s:s + 1]
            s1, s2 = rfi.power_sums(self._xp.where(keep, part, self._xp.zeros((), part.dtype)), mm, ci4=ci4)
            code[:, s] = rfi.sk_code(s1, s2, used, self.far, bits=self._bits)[0][:, 0]

    def on_data(self, ispan, ospan):
        raw = span_array(ispan)
        out = span_array(ospan)
        n = int(raw.shape[0])
        first = getattr(ispan, "frame_offset", self._frame)
        nl = self._nlive
        with _compat.stream_context():
            _, frames, summ = self.process(raw, out)
        counts, per_chan, stand_imp = summ["counts"], summ["per_chan"], summ["stand_imp"]
        partial, wholly, used = summ["partial"], summ["wholly"], summ["used"]
        if self.weights is not None:
            self.weights.add(self._tag0, first, used, frames, nl, partial, wholly, altered=stand_imp)
        self._frame = first + n
        nlive = nl
        st = self.flag_stats
        st["seen"] += n * self._lay["nchan"] * nlive
        for r, c in zip(REASONS, counts[:-1]):
            st["flagged"][r] += int(c)
        st["flagged_any"] += int(counts[-1])
        st["gulps"] += 1
        self.tally.add(first, n, counts[-1], n * self._lay["nchan"] * nlive)
        self._chan_flagged += per_chan.astype(np.int64)
        self._chan_seen += n * nlive
        self._add_row(per_chan / max(1, n * nlive), n)
        self._frames_since_report += n
        if self.report is not None and self._frames_since_report * self._lay["dt_s"] >= self.report_every_s:
            self._frames_since_report = 0
            try:                    # a live run's table and waterfall so far, rewritten in place
                self.report(self)
            except Exception as e:  # noqa: BLE001 - a report must not stop the flagging
                log.warning("RFIFlagBlock: the interval report was not written: %s", e)
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

    def write_report(self, outdir, prefix, title=""):
        """``<prefix>_flags.ecsv`` and ``_flags.png`` in ``outdir`` (:func:`~..io.flagreport.write_flag_report`)
        from the counts so far; returns their paths."""
        from ..io.flagreport import write_flag_report
        wf, row_frames = self.waterfall()
        return write_flag_report(outdir, prefix, self._lay["freq_hz"], self.summary(), wf,
                                 row_frames * self._lay["dt_s"], title=title)

    def summary(self):
        """The run's flag counts: fractions of the stand-samples seen, by reason and in all, and per channel."""
        st = self.flag_stats
        seen = max(1, st["seen"])
        return {"fraction_flagged": st["flagged_any"] / seen,
                "by_reason": {r: c / seen for r, c in st["flagged"].items()},
                "stand_samples_seen": st["seen"], "stand_samples_flagged": st["flagged_any"],
                "untested": st["untested"], "static_channels": int(self._static_host.sum()),
                "channel_fraction": (self._chan_flagged / max(1, self._chan_seen)).tolist()}


class FlagTally:
    """The flagged and the seen stand-samples of each gulp of one sequence (host counts the flagger has
    anyway), so that the image writer can record each image's fraction (FITS keyword FLAGFRAC). Gulp
    granularity: an image shorter than a gulp gets its gulp's fraction. The last ``MAX_ENTRIES`` gulps
    are kept (the writer lags the flagger by a few)."""

    MAX_ENTRIES = 65536

    def __init__(self, tally_id, ticks_per_frame):
        import collections
        import threading
        self.id, self.ticks_per_frame = tally_id, int(ticks_per_frame)
        self._entries = collections.deque(maxlen=self.MAX_ENTRIES)     # (frame0, nframe, flagged, seen)
        self._lock = threading.Lock()

    def add(self, frame0, nframe, flagged, seen):
        with self._lock:
            self._entries.append((int(frame0), int(nframe), float(flagged), float(seen)))

    def fraction(self, f0, f1):
        """Fraction of the stand-samples of frames [f0, f1) flagged (gulps weighted by their overlap), or
        None where no gulp of those frames is known."""
        flagged = seen = 0.0
        with self._lock:
            for a, n, fl, se in self._entries:
                over = min(a + n, f1) - max(a, f0)
                if over > 0:
                    flagged += fl * over / n
                    seen += se * over / n
        return flagged / seen if seen > 0 else None


def new_flag_tally(ticks_per_frame):
    """A :class:`FlagTally` registered under a new id (put in the header's ``flagging.tally``)."""
    return register_tally("flags", lambda tid: FlagTally(tid, ticks_per_frame))


def get_flag_tally(header):
    """The :class:`FlagTally` a sequence header names (``header['flagging']['tally']``), or None."""
    return lookup_tally(((header or {}).get("flagging") or {}).get("tally"))


class FlagWeights:
    """What each image kept of the array after flagging, handed from RFIFlagBlock to the imager.

    For image i (frames [i A, (i + 1) A) of a sequence, A the imager's ``accumulate``) and channel c,
    q(i, c) = (1 / A) sum over its frames of (n_used / N_live)^2, n_used the live stands left unflagged:
    the fraction of a point source's power the image holds. The imager divides each image by it (0 where
    nothing was left: the image is then 0, and the band and time means skip it), so that images of part
    of the array or part of the time stay in Jy. Only images that hold a partial value (0 < q < 1) are
    rescaled; the rest (q = 1, or 0 with zero data) are left as they are. ``take`` and ``take_empty``
    hand out NumPy arrays on any device: they cross from the flagger's thread and CUDA stream to the
    imager's and the search's.

    For the search (``track_empty``), an image is missing in a channel where it kept nothing, and in
    every channel where a stand's own spark took that stand out of part of it: rescaling restores a
    point source's flux, not the array's beam, so the bright sources' sidelobes change in that one
    image across the band, which is what a burst at DM 0 looks like (on a whole-band sky, dozens of
    candidates from a few false alarms a minute). Spectral-kurtosis flags change one channel's beam, one
    stand at a time, at block boundaries (a stand's spark is left out of its SK: RFIFlagBlock).
    """

    def __init__(self, accumulate, track_empty=False):
        import threading
        self.A, self.track_empty = int(accumulate), bool(track_empty)
        self._cond = threading.Condition()
        self._seq, self._chunks, self._empty, self._open = None, [], [], None
        self.stats = {"images_rescaled": 0, "channel_images_filled": 0, "images_missing_stand_spark": 0}

    def begin(self, tag0):
        with self._cond:
            self._seq, self._chunks, self._empty, self._open = tag0, [], [], None

    def add(self, tag0, first, used, frames, nlive, partial, wholly=False, altered=None):
        """The flagger's gulp at frame ``first``: ``used`` (ns, nchan) stands left per short block of
        ``frames`` (ns,) frames; ``partial``: whether any short block kept part of the array; ``wholly``:
        whether any (short block, channel) kept nothing; ``altered`` (ns,) host bool or None: the short
        blocks in which a stand's own spark took it out (their images are missing for the search)."""
        u = (to_numpy(used).astype(np.float64) / max(1, nlive)) ** 2          # (ns, nchan) per short block
        fr = np.asarray(frames, np.int64).reshape(-1)
        edges = np.concatenate([[0], np.cumsum(fr)])                          # (ns + 1,) each block's first frame
        n = int(edges[-1])
        cw = np.concatenate([np.zeros((1,) + u.shape[1:]), np.cumsum(u * fr[:, None], axis=0)])
        A = self.A
        cuts = np.array(sorted({0, n} | {t for t in range(-(-first // A) * A - first, n, A) if t > 0}), np.int64)
        # the sum of u over frames [0, t) at each cut t: whole short blocks, then part of the one t falls in
        j = np.minimum(np.searchsorted(edges, cuts, side="right") - 1, len(fr) - 1)
        upto = cw[j] + u[j] * (cuts - edges[j])[:, None]
        seg = upto[1:] - upto[:-1]                                            # (nseg, nchan)
        cuts = cuts.tolist()
        alt = np.zeros(n, bool) if altered is None else np.repeat(np.asarray(altered, bool), frames)
        with self._cond:
            if self._seq != tag0:
                return
            for j in range(len(cuts) - 1):
                t0, t1 = cuts[j], cuts[j + 1]
                img = (first + t0) // A
                a = bool(alt[t0:t1].any())
                if self._open is None or self._open[0] != img:
                    self._open = [img, seg[j], t1 - t0, partial, wholly, a]
                else:
                    self._open[1] = self._open[1] + seg[j]
                    self._open[2] += t1 - t0
                    self._open[3] = self._open[3] or partial
                    self._open[4] = self._open[4] or wholly
                    self._open[5] = self._open[5] or a
                if self._open[2] == A:
                    q = self._open[1] / A
                    self._chunks.append((img, q, self._open[3]))
                    if self.track_empty:
                        if self._open[5]:
                            self.stats["images_missing_stand_spark"] += 1
                        self._empty.append((img, (q == 0) | self._open[5], self._open[4] or self._open[5]))
                    self._open = None
            self._cond.notify_all()

    def take(self, tag0, i0, count):
        """q (count, nchan) for images i0 .. i0 + count - 1 of sequence ``tag0``, or None where none of them
        needs rescaling; those images' entries are let go."""
        mine = self._pop("_chunks", tag0, i0, count)
        if mine is None:
            return None
        self.stats["images_rescaled"] += sum(1 for c in mine if c[2])
        return np.stack([c[1] for c in mine])

    def take_empty(self, tag0, i0, count):
        """bool (count, nchan): the channel images of images i0 .. i0 + count - 1 that kept nothing (every
        stand flagged throughout), or None where none of them has such a channel; entries are let go."""
        mine = self._pop("_empty", tag0, i0, count)
        return None if mine is None else np.stack([c[1] for c in mine])

    def _pop(self, name, tag0, i0, count):
        """The entries (image, value, flag) of images i0 .. i0 + count - 1 from list ``name``, let go; None
        where the sequence differs, one is missing, or none has its flag set."""
        with self._cond:
            if self._seq != tag0:
                return None
            held = getattr(self, name)
            mine = [c for c in held if i0 <= c[0] < i0 + count]
            setattr(self, name, [c for c in held if c[0] >= i0 + count])
        return mine if len(mine) == count and any(c[2] for c in mine) else None


def _repeats(frames):
    """``repeats`` for ``xp.repeat`` from (ns,) host counts: an int where all are equal (CuPy takes an int
    or a list, not an array)."""
    frames = np.asarray(frames)
    return int(frames[0]) if frames.size and (frames == frames[0]).all() else [int(f) for f in frames]



def rfi_flag(iring, *args, **kwargs):
    """Factory for :class:`RFIFlagBlock`."""
    return RFIFlagBlock(iring, *args, **kwargs)
