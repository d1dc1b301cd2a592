"""CalFoldBlock: fold the direction-independent terms into the voltages; carry the pattern on.

Design: the block *multiplies the voltages* (cf32 out) by the cable correction A_c = exp(+2 pi i nu
tau) / sqrt(G) and the current calibration solution A_s, and zeroes flagged antennas exactly. It
writes the flags into the output header's ``station.flags`` so the imager drops those antennas
from D (and from N_A). Since sum_a D[k,a] (w_a x_a) = sum_a (D[k,a] w_a) x_a, imaging the folded
voltages equals imaging the raw ones with D * A_c * A_s (tests/test_blocks.py proves it).
Voltages are per-sample, so a solution switches at exactly the frame whose time tag reaches its
``valid_from``, inside a gulp if need be. The direction-dependent pattern (A_i) cannot be folded
into voltages, so its name goes into the header (``calibration.pattern``) for the imager.
Non-finite samples of float input (NaN/Inf) are zeroed and counted per antenna (:mod:`.nonfinite`):
the header's ``nonfinite`` names the tally, a warning is logged per gulp that had any.
"""
from __future__ import annotations

import logging

import numpy as np

from ..imaging import patterns
from ..imaging.calibration import GainTable, apply_direction_independent, cable_weights
from . import _compat
from ._compat import bfp, span_array, unpack_complex
from .headers import derived_header, efield_layout
from .nonfinite import is_float_dtype, new_tally, zero_and_count

log = logging.getLogger(__name__)


class CalFoldBlock(bfp.TransformBlock):
    """Direction-independent calibration (cable terms, time-variable gains, flags) on E-field gulps.

    Parameters
    ----------
    iring : input ring or block; E-field header as docs/HEADERS.md (labels time, freq, station, pol).
    cable : True (use the header's ``station.cable_delay_s``/``cable_gain``, shaped (nstand, npol,
            nchan)), False (none), or a complex array (nchan|1, nstand, npol|1) of weights.
    gains : None, a :class:`GainTable`, the path of an .npz gain table (time-variable A_s), or a
            :class:`~.gain_solver.LiveGainTable` a GainSolverBlock fills as the data flow (each gulp then
            waits until the solutions that reach it are decided).
    flags : None or bool (nstand, npol) / (nstand,) extra flags (True = bad).
    pattern : None, a registered pattern name ("dipole"), or a callable ``fn(pixels_lm, freq_hz,
              npol)``; it is registered and its name written to the header for the imager.
    Output: dtype 'cf32', same labels; header ``calibration`` records what was applied.
    ``stats``: frames, frames_before_first_solution, flagged antenna-pols, nonfinite (samples zeroed).
    ``nonfinite_counts``: int64 (nstand, npol), non-finite samples zeroed in the current sequence.
    """

    def __init__(self, iring, cable=True, gains=None, flags=None, pattern=None, *args, **kwargs):
        super().__init__(iring, *args, **kwargs)
        self.cable = cable
        self.gains = GainTable.load(gains) if isinstance(gains, str) else gains
        self.extra_flags = flags
        if callable(pattern):
            name = f"user:{getattr(pattern, '__module__', '')}.{getattr(pattern, '__qualname__', id(pattern))}"
            patterns.register_pattern(name, pattern)
            pattern = name
        elif pattern is not None:
            patterns.get_pattern(pattern)  # fail now for an unknown name
        self.pattern = pattern
        self.cal_stats = {"frames": 0, "frames_before_first_solution": 0, "flagged": 0, "nonfinite": 0}
        self.tally = None

    def define_valid_input_spaces(self):
        return "any"

    def on_sequence(self, iseq):
        ihdr = iseq.header
        lay = efield_layout(ihdr, "CalFoldBlock")
        nchan, nstand, npol = lay["nchan"], lay["nstand"], lay["npol"]
        flags = lay["flags"].copy()
        if self.extra_flags is not None:
            ef = np.asarray(self.extra_flags, dtype=bool)
            ef = ef[:, None] if ef.ndim == 1 else ef
            if ef.shape[0] != nstand:
                raise ValueError(f"CalFoldBlock: flags cover {ef.shape[0]} stations, the data have {nstand}")
            flags |= np.broadcast_to(ef, (nstand, npol))
        st = ihdr["station"]
        applied = {"cable": False, "gain_table": None, "pattern": self.pattern}
        if self.cable is True:
            if "cable_delay_s" not in st or "cable_gain" not in st:
                raise ValueError("CalFoldBlock: cable=True needs station.cable_delay_s and station.cable_gain "
                                 "(nstand, npol, nchan) in the header; pass cable=False or explicit weights")
            w = cable_weights(np.asarray(st["cable_delay_s"])[:, :npol], np.asarray(st["cable_gain"])[:, :npol],
                              lay["freq_hz"])
            applied["cable"] = True
        elif self.cable is False or self.cable is None:
            w = np.ones((nchan, nstand, npol), np.complex128)
        else:
            w = np.asarray(self.cable, dtype=np.complex128)
            if w.ndim != 3:
                raise ValueError(f"CalFoldBlock: explicit cable weights must be (nchan|1, nstand, npol|1), got {w.shape}")
            w = np.broadcast_to(w, (nchan, nstand, npol))
            applied["cable"] = "explicit"
        flags |= np.all(w == 0, axis=0)
        bad_w = ~np.all(np.isfinite(w), axis=0)
        if bad_w.any():  # a NaN/Inf cable term would poison every sample of that antenna
            log.warning("CalFoldBlock: non-finite cable weights for %d antenna-pols; flagging them", int(bad_w.sum()))
            flags |= bad_w
        if self.gains is not None:
            self.gains.check_shape(nchan, nstand, npol)
            flags |= self.gains.flags(nstand, npol)
            applied["gain_table"] = "live (solved from the sky as the data flow)" if hasattr(self.gains, "wait_through") \
                else {"nsol": int(len(self.gains.valid_from)),
                                     "valid_from": [int(v) for v in self.gains.valid_from]}
        xp = self._xp(iseq)
        self._w = xp.asarray(np.where(flags[None], 0, w).astype(np.complex64))
        self._live = xp.asarray(~flags)
        self._lay = lay
        self._live_table = hasattr(self.gains, "wait_through")
        self._flags_host, self._scaled = flags.copy(), {}
        self._next_frame = 0
        self.cal_stats["flagged"] = int(flags.sum())
        ohdr = derived_header(ihdr)
        ohdr["_tensor"]["dtype"] = "cf32"
        ohdr["station"]["flags"] = flags.tolist()
        for k in ("cable_delay_s", "cable_gain"):
            if applied["cable"] and k in ohdr["station"]:
                ohdr["station"].pop(k)  # applied: must not be applied twice downstream
        ohdr["calibration"] = {**ihdr.get("calibration", {}), **applied, "flagged": int(flags.sum())}
        # float input can carry NaN/Inf: zeroed and counted here (integer input cannot); the tally
        # travels by name and tells the imager that this sequence is clean
        self._float_in = is_float_dtype(lay["dtype"])
        self._seq_name = ihdr.get("name")
        self.tally = new_tally("CalFoldBlock", nstand, npol)
        ohdr["nonfinite"] = self.tally.to_header()
        log.info("CalFoldBlock %s: cable=%s, gain table=%s, %d antenna-pols flagged, pattern=%s",
                 ihdr.get("name"), applied["cable"], bool(self.gains), int(flags.sum()), self.pattern)
        return ohdr

    def _xp(self, iseq):
        return _compat.input_xp(self)

    def on_data(self, ispan, ospan):
        idata = span_array(ispan)
        n = idata.shape[0]
        first = getattr(ispan, "frame_offset", self._next_frame)
        with _compat.stream_context():
            x = unpack_complex(idata, self._lay["dtype"])
            if self._float_in:
                x = zero_and_count(x, self.tally, first, "CalFoldBlock", self._seq_name)
            out = span_array(ospan)
            if self.gains is None:
                apply_direction_independent(x, self._w, self._live, out=out[:n])
            else:
                tpf = self._lay["ticks_per_frame"]
                tag0 = self._lay["time_tag"] + first * tpf
                if self._live_table:
                    self.gains.wait_through(self._lay["time_tag"], tag0 + (n - 1) * tpf)
                for s, e, i in self.gains.segments(tag0, tpf, n):
                    if i < 0:
                        self.cal_stats["frames_before_first_solution"] += e - s
                    g = self._solution(i, x)
                    apply_direction_independent(x[s:e], self._w, self._live, g, out=out[s:e])
        self._next_frame = first + n
        self.cal_stats["frames"] += n
        self.cal_stats["nonfinite"] = self.tally.total
        return n

    def _solution(self, i, like):
        """Solution i's corrections in the namespace of ``like``; for a live table (inputs flagged after the
        sequence began) scaled by N_A(sequence) / N_A(solution), which keeps the imager's flux scale."""
        g = self.gains.solution(i, like=like)
        if not self._live_table or i < 0:
            return g
        key = (i, type(like).__module__)
        if key not in self._scaled:
            live = ~np.asarray(self._flags_host)
            scale = self.gains.solution_scale(i, live)                                  # (c, 1, p)
            xp = type(like).__module__.startswith("cupy") and __import__("cupy") or np
            self._scaled = {key: g * xp.asarray(scale.astype(np.float32))}
        return self._scaled[key]

    @property
    def nonfinite_counts(self):
        return None if self.tally is None else self.tally.counts.copy()

    def on_sequence_end(self, iseq):
        if self.tally.total:
            log.warning("CalFoldBlock: %d non-finite samples zeroed in sequence %s, on %d antenna-pols",
                        self.tally.total, iseq.header.get("name"), int((self.tally.counts > 0).sum()))
        if self.cal_stats["frames_before_first_solution"]:
            log.warning("CalFoldBlock: %d frames came before the first calibration solution and got unit gains",
                        self.cal_stats["frames_before_first_solution"])


def cal_fold(iring, cable=True, gains=None, flags=None, pattern=None, *args, **kwargs):
    """Factory for :class:`CalFoldBlock`."""
    return CalFoldBlock(iring, cable, gains, flags, pattern, *args, **kwargs)
