"""GainSolverBlock: antenna gains and health solved from the sky as the data flow; LiveGainTable hands
them to CalFoldBlock.

The solver reads the same raw voltages CalFoldBlock reads (a second guaranteed reader of the source's
ring), sums the covariance R = sum_t x x^H of each solution's stretch of data where the ring lives
(exact integer sums for 4-bit samples: :class:`~bf_epic_blocks.imaging.skycal.CovarianceSums`),
removes the cable terms, builds the model of the sky at the stretch's middle time
(:func:`bf_epic_blocks.sky.model.sky_model`) and solves (:func:`~bf_epic_blocks.imaging.skycal.solve_gains`).

Schedule (frames from the start of a sequence): solution k uses frames [k C, k C + I) (C = cadence,
I = integration, both in frames) and applies from frame k C + I, the first frame after its data
(rounded up to the imager's integration, ``align_frames``). So every image after a solution's data is
made with it, and a run is deterministic: the block that applies the gains -- CalFoldBlock on the
voltages, or DFTImagerBlock folding them into its operator on a GPU -- waits, before a gulp that
reaches a solution's first frame, until the solver has decided that solution
(:meth:`LiveGainTable.wait_through`). The solver never waits on anything downstream, and the
data it needs were written before the gulp CalFoldBlock holds, so the wait cannot deadlock. The block's
thread only sums: each integration's mean covariance goes to a worker thread (on a GPU, with a CUDA
stream of its own that waits for the sums' event), which solves and posts it while the block reads on,
so the source's ring never waits for a solve; ``apply_delay_s`` gives the worker its time.

A solve that fails (no model source above the horizon limit, too few good inputs, no convergence) is
counted and logged, and the last good solution stays in force; a sequence shorter than one
integration is solved from what it has if that is at least ``min_samples`` samples.
"""
from __future__ import annotations

import logging
import math
import os
import threading
import time

import numpy as np

from ..conventions import FS_HZ
from ..imaging.calibration import GainTable, cable_weights
from ..imaging._xp import to_numpy
from ..imaging.skycal import (CovarianceSums, SolveSettings, baseline_weights, clip_fraction, model_covariance,
                              solve_gains)
from ..io.gaintable import TablePart
from . import _compat
from ._compat import bfp, span_array, unpack_complex
from ._drawing import DrawingHelper
from .headers import efield_layout

__all__ = ["GainSolverBlock", "LiveGainTable", "gain_solver"]

log = logging.getLogger(__name__)


class LiveGainTable:
    """A :class:`~bf_epic_blocks.imaging.calibration.GainTable` that grows while the pipeline runs.

    The solver :meth:`post`\\ s solutions and says how far its schedule is decided (:meth:`decided`);
    CalFoldBlock reads it like a GainTable (``segments``, ``solution``) after :meth:`wait_through`.
    Before the first solution every frame gets unit gains. It has no flags of its own at the start of
    a sequence: inputs a solution flags are zeroed from that solution on, and CalFoldBlock rescales the
    rest so that the imager's 1/N_A, fixed per sequence, still gives Jy (:meth:`solution_scale`).
    ``wait_timeout_s`` bounds a wait (a solver that stopped answering): then the frames go on with
    the solutions known, and the event is counted in ``stats['wait_timeouts']``.
    """

    #: solutions held; older ones can no longer apply to data still to come
    KEEP = 8

    def __init__(self, wait_timeout_s=600.0):
        self._cond = threading.Condition()
        self._vf, self._g = [], []
        self._offset = 0          # solutions dropped from the front
        self._table = None
        self._seq = None
        self._through = -math.inf
        self._ended = set()
        self._closed = False
        self.wait_timeout_s = float(wait_timeout_s)
        self.stats = {"solutions": 0, "failures": 0, "wait_timeouts": 0, "wait_s": 0.0}

    # -- solver side
    def begin(self, seq_tag0, through_tag):
        with self._cond:
            self._seq, self._through = seq_tag0, through_tag
            self._cond.notify_all()

    def post(self, valid_from, corrections):
        """Add a solution: corrections complex (nchan, nstand, npol) from time tag ``valid_from``."""
        g = np.asarray(corrections, np.complex128)[None]
        with self._cond:
            if self._vf and valid_from <= self._vf[-1]:
                raise ValueError(f"solutions must come in time order: {valid_from} after {self._vf[-1]}")
            self._vf.append(int(valid_from))
            self._g.append(g)
            # a pipeline runs for weeks: only the last KEEP solutions are held (the consumers go forward in
            # time and lag the solver by a ring's depth, a few gulps); indices stay absolute (offset)
            drop = max(0, len(self._vf) - self.KEEP)
            if drop:
                self._vf, self._g, self._offset = self._vf[drop:], self._g[drop:], self._offset + drop
            self._table = GainTable(np.array(self._vf), np.concatenate(self._g))
            self.stats["solutions"] += 1
            self._cond.notify_all()

    def decided(self, seq_tag0, through_tag):
        with self._cond:
            if self._seq == seq_tag0:
                self._through = max(self._through, through_tag)
            self._cond.notify_all()

    def end_sequence(self, seq_tag0):
        with self._cond:
            self._ended.add(seq_tag0)
            self._cond.notify_all()

    def close(self):
        """No more solutions (the solver stopped): waits return at once."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    # -- CalFoldBlock side
    def wait_through(self, seq_tag0, tag):
        """Block until every solution that applies at or before time tag ``tag`` of the sequence that
        starts at ``seq_tag0`` is decided (or the solver has ended that sequence or stopped)."""
        t0 = time.perf_counter()
        with self._cond:
            ok = self._cond.wait_for(lambda: self._closed or seq_tag0 in self._ended
                                     or (self._seq == seq_tag0 and self._through >= tag), self.wait_timeout_s)
        self.stats["wait_s"] += time.perf_counter() - t0
        if not ok:
            self.stats["wait_timeouts"] += 1
            log.warning("LiveGainTable: no word from the solver in %.0f s; calibrating with the solutions known",
                        self.wait_timeout_s)

    @property
    def valid_from(self):
        """Time tags of the solutions held (the last :attr:`KEEP`)."""
        return np.array(self._vf, np.int64)

    def corrections(self, i):
        """Solution i's corrections, complex128 (1|nchan, nstand, npol|1)."""
        return self._table.gains[i - self._offset]

    def check_shape(self, nchan, nant, npol):
        if self._table is not None:
            self._table.check_shape(nchan, nant, npol)

    def flags(self, nant, npol):
        return np.zeros((nant, npol), bool)

    def index(self, time_tags):
        """Solution index for each time tag (int64); -1 before the first solution."""
        if self._table is None:
            return np.full(np.shape(time_tags), -1, np.int64)
        return self._absolute(self._table.index(time_tags))

    def _absolute(self, i):
        """Absolute solution indices from the held table's; before the oldest held: -1 while none was
        dropped, else the oldest held (a consumer that far behind is told so by nothing better)."""
        i = np.asarray(i)
        return np.where(i >= 0, i + self._offset, -1 if self._offset == 0 else self._offset)

    def segments(self, first_tag, ticks_per_frame, nframe):
        if self._table is None:
            return [(0, int(nframe), -1)]
        return [(a, b, int(self._absolute(i))) for a, b, i in self._table.segments(first_tag, ticks_per_frame, nframe)]

    def solution(self, i, like=None):
        if self._table is None or i < 0:
            return GainTable(np.array([0]), np.ones((1, 1, 1, 1))).solution(-1, like)
        return self._table.solution(i - self._offset, like)

    def solution_scale(self, i, live):
        """float (nchan, 1, npol): N_A of the sequence over N_A of solution i, per channel and pol (>= 1),
        so that inputs a live solution zeroes do not lower the image's flux scale. live : bool (nstand, npol)."""
        g = self.corrections(i)
        n_seq = live.sum(axis=0).astype(np.float64)                                       # (p,)
        n_sol = ((g != 0) & live[None]).sum(axis=1).astype(np.float64)                   # (c, p)
        return np.where(n_sol > 0, n_seq[None] / np.maximum(n_sol, 1), 0.0)[:, None, :]


class GainSolverBlock(bfp.SinkBlock):
    """Solve antenna gains and health from the voltages, on a schedule (module docstring).

    Parameters
    ----------
    iring : the raw E-field ring (the source's; header as docs/concepts/headers.md).
    sources : the model's sources (names like 'CygA', 'Sun', or mappings: :func:`~..sky.resolve_source`).
    cadence_s, integration_s : a solution every ``cadence_s`` from the first ``integration_s`` of it.
    offset_s : solution k sums from ``k cadence_s + offset_s`` (0 <= offset_s < cadence_s): tunings that
        share a GPU solve in turn, each solve's memory and time then at its own moment.
    settings : :class:`~bf_epic_blocks.imaging.skycal.SolveSettings`.
    pattern : the antennas' voltage pattern for the model ('dipole' or None).
    cable : remove the header's cable terms before solving (as CalFoldBlock does before applying).
    min_alt_deg : model sources lower than this are left out.
    min_samples : a sequence's last, short stretch is solved only with at least this many samples.
    table : a :class:`LiveGainTable` the solutions are posted to (CalFoldBlock reads it), or None.
    table_path : where the solved table (.npz, :mod:`bf_epic_blocks.io.gaintable`) is written after each
        solution (and its PNG beside it when ``png``), or None.
    reference_stand : stand id of the reference input, or None (auto).
    align_frames : a live solution takes effect at a multiple of this many frames (the imager's integration).
    solutions_per_file : None (one table file), or solutions per file part: a pipeline that solves for weeks
        writes ``table_path``, then ``<stem>_p001.npz``, ..., and holds only the current part in memory
        (each solution rewrites its part's file: at the whole band a solution is 3 MB of corrections).
    apply_delay_s : a live solution applies this long after the end of its data (rounded up to
        ``align_frames``): the time the solve takes, so that the imager does not wait for it.
    saturated_above : a 4-bit input whose samples clip more often than this fraction (estimated from its
        power, Gaussian voltages: :func:`~bf_epic_blocks.imaging.skycal.clip_fraction`) is flagged 'saturated'.
    diffuse : add the analytic Galactic sky to the model with a fitted scale
        (:func:`~bf_epic_blocks.sky.model.diffuse_model`), recomputed every ``diffuse_refresh_s`` of data.
    png_process : draw the PNGs in a helper process (spawned at the first; matplotlib holds the interpreter
        about a second a PNG at the whole band, which the pipeline's threads would wait for), or in the
        worker thread (False, or where the helper cannot start).
    apply_from : 'after' (live: a solution applies from the first frame after its data) or 'start'
        (offline: from the first frame of its cadence, so a table applied to the same data calibrates
        them from their start; the table's ``valid_from`` says which).
    ``part`` holds the current file part's solutions as its table holds them (:class:`~..io.gaintable.TablePart`:
    arrays made for the part's ``solutions_per_file`` at its first, so memory stays flat while it fills);
    ``last_solution`` is the newest :class:`~bf_epic_blocks.imaging.skycal.Solution` (the next solve's warm
    start); ``solver_stats`` counts solutions, failures (with reasons) and the seconds spent summing and solving.
    """

    #: the sums and the solves go ahead of the imager's kernels, which wait for their solutions
    stream_priority = "high"

    def __init__(self, iring, sources, *, cadence_s=10.0, integration_s=1.0, settings=None, pattern=None,
                 cable=True, min_alt_deg=10.0, min_samples=1000, table=None, table_path=None, png=True,
                 reference_stand=None, apply_from="after", align_frames=1, diffuse=True, diffuse_refresh_s=300.0,
                 saturated_above=0.1, apply_delay_s=0.0, solutions_per_file=None, png_process=True, offset_s=0.0,
                 **kwargs):
        super().__init__(iring, **kwargs)
        # the worker's sky model and solver import these (see import_now)
        _compat.import_now("scipy.linalg", "scipy.special")
        if not (integration_s > 0 and cadence_s >= integration_s):
            raise ValueError(f"GainSolverBlock: need 0 < integration_s <= cadence_s, got integration_s="
                             f"{integration_s}, cadence_s={cadence_s}")
        if not 0 <= offset_s < cadence_s:
            raise ValueError(f"GainSolverBlock: need 0 <= offset_s < cadence_s, got offset_s={offset_s}, "
                             f"cadence_s={cadence_s}")
        self.sources, self.cadence_s, self.integration_s = list(sources), float(cadence_s), float(integration_s)
        self.offset_s = float(offset_s)
        self.settings = settings or SolveSettings()
        self.pattern = None if pattern in (None, "none", False) else pattern
        self.cable, self.min_alt_deg, self.min_samples = cable, float(min_alt_deg), int(min_samples)
        self.table, self.table_path, self.png = table, table_path, png
        self._png_every = max(1, int(round(60.0 / cadence_s)))   # solutions between PNGs: about a minute of data
        self._png_of = self._written_of = None
        self.reference_stand = reference_stand
        if apply_from not in ("after", "start"):
            raise ValueError(f"GainSolverBlock: apply_from must be 'after' or 'start', got {apply_from!r}")
        self.apply_from = apply_from
        self.align_frames = max(1, int(align_frames))
        self.diffuse, self.diffuse_refresh_s = bool(diffuse), float(diffuse_refresh_s)
        self.saturated_above = float(saturated_above)
        if not apply_delay_s >= 0:
            raise ValueError(f"GainSolverBlock: apply_delay_s must be >= 0, got {apply_delay_s!r}")
        self.apply_delay_s = float(apply_delay_s)
        self.solutions_per_file = None if not solutions_per_file else int(solutions_per_file)
        self.part = TablePart(self.solutions_per_file)                              # this file part's
        self.valid_from, self.time_unix, self.models = [], [], []
        self.last_solution, self._part = None, 0
        self.solver_stats = {"solutions": 0, "failures": 0, "failure_reasons": [], "sum_s": 0.0, "solve_s": 0.0,
                             "samples": 0, "sum_s_each": [], "solve_s_each": [], "pngs": 0, "pngs_in_helper": 0,
                             "pngs_skipped": 0, "out_of_memory": 0}
        self._drawing = DrawingHelper("GainSolverBlock", png_process)
        self._sum_this = 0.0
        from concurrent.futures import ThreadPoolExecutor
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="gain-solver")
        self._jobs, self._worker_error, self._worker_stream, self._ev_start = [], None, None, None

    def define_valid_input_spaces(self):
        return "any"

    def on_sequence(self, iseq):
        hdr = iseq.header
        lay = efield_layout(hdr, "GainSolverBlock")
        self._lay = lay
        from ..station.tables import StationTable
        st = hdr["station"]
        self._location = StationTable.from_header(st).location if "lat_deg" in st else None
        self._station_name = st.get("name", "")
        self._stand_ids = np.asarray(st.get("stand_ids", np.arange(1, lay["nstand"] + 1)), np.int64)
        nchan, nstand, npol = lay["nchan"], lay["nstand"], lay["npol"]
        if self.cable and "cable_delay_s" in st and "cable_gain" in st:
            w = cable_weights(np.asarray(st["cable_delay_s"])[:, :npol], np.asarray(st["cable_gain"])[:, :npol],
                              lay["freq_hz"])
        else:
            w = np.ones((nchan, nstand, npol), np.complex128)
        self._flags = lay["flags"] | np.all(w == 0, axis=0)
        self._w = w
        self._xp = _compat.input_xp(self)
        self._sums = CovarianceSums(nchan, nstand, npol, self._xp)
        # after interference flagging, each baseline's mean covariance is over the samples it kept
        fl = hdr.get("flagging") or {}
        self._flag_block = int(fl.get("impulse_frames", 1)) if fl else 0
        self._device_id = self._xp.cuda.Device().id if self._xp is not np else None
        self._W = None            # baseline weights, made at the first solve of the sequence
        self._E, self._E_at = None, None   # the diffuse model term and when (unix s) it was made
        self._cadence = max(1, int(round(self.cadence_s / lay["dt_s"])))
        self._integ = max(1, min(self._cadence, int(round(self.integration_s / lay["dt_s"]))))
        self._offset = min(self._cadence - 1, int(round(self.offset_s / lay["dt_s"])))
        self._delay = int(round(self.apply_delay_s / lay["dt_s"]))
        self._tag0, self._tpf = int(lay["time_tag"]), int(lay["ticks_per_frame"])
        self._k = 0               # the solution being summed
        self._frame = 0           # frames of the sequence seen
        self._posted_in_seq = 0
        if self.table is not None:
            self.table.begin(self._tag0, self._due(0) - 1)
        self._jobs.append(self._pool.submit(self._warm_job))
        log.info("GainSolverBlock %s: a solution every %.3g s from %.3g s of data (%d frames), model %s%s",
                 hdr.get("name"), self._cadence * lay["dt_s"], self._integ * lay["dt_s"], self._integ,
                 ", ".join(str(s) if not isinstance(s, dict) else s.get("name", "?") for s in self.sources),
                 f", pattern {self.pattern}" if self.pattern else "")

    def _due(self, k):
        """Time tag of solution k's first frame in force: k C + I + the apply delay, rounded up to a
        multiple of ``align_frames`` (the imager's integration, so that it takes effect at an integration's
        start whether it is applied to the voltages or folded into the operator)."""
        a = self.align_frames
        return self._tag0 + (-(-(k * self._cadence + self._offset + self._integ + self._delay) // a) * a) * self._tpf

    def on_data(self, ispan):
        try:
            self._accumulate(ispan)
        except BaseException:
            if self.table is not None:
                self.table.close()
            raise

    def _accumulate(self, ispan):
        if self._worker_error is not None:
            self._wait_jobs()
        self._jobs = [j for j in self._jobs if not j.done()]
        x = span_array(ispan)
        n = int(x.shape[0])
        first = getattr(ispan, "frame_offset", self._frame)
        lay = self._lay
        pos = 0
        while pos < n:
            f = first + pos
            start = self._k * self._cadence + self._offset
            if f < start:                      # between integrations: skip to the next one
                pos = min(n, pos + start - f)
                continue
            end = start + self._integ
            take = min(n - pos, end - f)
            t0 = time.perf_counter()
            if self._sums.ntime == 0 and self._xp is not np:
                self._ev_start = self._xp.cuda.Event()
                self._ev_start.record()
            part = x[pos:pos + take]
            ci4 = lay["dtype"] == "ci4" and part.dtype == np.uint8
            pos += take
            try:
                used, block = self._used(part) if self._flag_block else (None, 1)
                if ci4:
                    self._sums.add(part, ci4=True, used=used, block=block)
                else:
                    self._sums.add(unpack_complex(part, lay["dtype"]), used=used, block=block)
                if self._xp is np:
                    self._sum_this += time.perf_counter() - t0
                if f + take >= end:
                    self._hand_over(self._k, self._due(self._k) if self.apply_from == "after"
                                    else self._tag0 + (self._k * self._cadence + self._offset) * self._tpf)
                    self._k += 1
                    self._sums.reset()
            except MemoryError as e:            # CuPy's OutOfMemoryError too: the imager's memory comes first
                self._drop_integration(f"out of memory while summing its data ({str(e)[:200]})")
        self._frame = first + n

    def _drop_integration(self, why):
        """Integration k cannot be summed: counted and logged as a failed solution (the last good gains stay
        in force), the live table told that nothing comes from it -- by the worker, after the solves queued
        before it, whose solutions apply earlier -- and the sums begun again at the next."""
        self.solver_stats["out_of_memory"] += 1
        self._fail(why, self._k)
        if self.table is not None:
            self._jobs.append(self._pool.submit(self.table.decided, self._tag0, self._due(self._k + 1) - 1))
        self._k += 1
        self._sums.reset()

    def _used(self, part):
        """(used, block): after interference flagging (the header's ``flagging``), float (nj, nchan, nant), 1
        where a stand's samples of a flagger's short block were kept. The flagger writes a flagged
        stand-sample as zeros in both pols for whole short blocks, and kept noise is never zero for a whole
        short block, so a block's zeros tell. Where ``part`` does not hold whole short blocks, per frame."""
        from ..runtime.dtypes import ci4_bytes
        xp = self._xp
        g = self._flag_block if part.shape[0] % self._flag_block == 0 else 1
        if self._lay["dtype"] == "ci4":
            nz = ci4_bytes(part) != 0
        else:
            v = unpack_complex(part, self._lay["dtype"])
            nz = (v.real != 0) | (v.imag != 0)
        nz = nz.reshape(part.shape[:3] + (-1,)).any(axis=3)                        # (t, c, a)
        nz = nz.reshape((part.shape[0] // g, g) + nz.shape[1:]).any(axis=1)
        return nz.astype(xp.float32), g

    def _hand_over(self, k, valid_from):
        """Integration k is summed: its mean covariance goes to the worker thread, which solves and posts it
        while this block reads on (the source's ring never waits for a solve)."""
        raw, ntime = self._sums.mean(), self._sums.ntime
        start = end = None
        if self._xp is not np:            # the worker's stream waits for the sums on this block's stream
            start, end = self._ev_start, self._xp.cuda.Event()
            end.record()
        sum_s, self._sum_this = self._sum_this, 0.0
        nxt = self._due(k + 1) - 1
        self._jobs.append(self._pool.submit(self._solve_job, k, valid_from, raw, ntime, start, end, sum_s,
                                            self._tag0, nxt))

    def _worker_stream_in_use(self):
        """On a GPU, the worker's own non-blocking stream made current (on the block's device); else nothing."""
        from contextlib import nullcontext
        if self._xp is np:
            return nullcontext()
        cp = self._xp
        cp.cuda.Device(self._device_id).use()
        if self._worker_stream is None:
            from ..runtime.pipeline import priority_stream
            self._worker_stream = priority_stream(cp, "high")
        return self._worker_stream

    def _warm_job(self):
        """The worker, while the first integration sums: the sky model's first transform (astropy loads its
        tables), the baseline weights, the diffuse term for solution 0's time and the solver's kernels (a
        solve of one channel against its own model), so that solution 0 costs what every later one does
        instead of holding the imager at its first apply time. A failure here is only logged: solution 0
        meets the same problem and reports it."""
        from ..sky.model import diffuse_model, sky_model
        t0 = time.perf_counter()
        lay, xp = self._lay, self._xp
        try:
            with self._worker_stream_in_use():
                when = self._model_time(0, self._integ)
                if self._location is None:
                    return
                model = sky_model(self.sources, when, self._location, lay["freq_hz"], pattern=self.pattern,
                                  npol=lay["npol"], min_alt_deg=self.min_alt_deg)
                self._W = baseline_weights(lay["xyz_m"], lay["freq_hz"], self.settings.min_baseline_lambda, xp=xp,
                                           dtype=self._real_dtype)
                t_model = time.perf_counter()
                cdt = np.complex128 if xp is np else xp.complex64
                if self.diffuse:
                    self._E = diffuse_model(lay["xyz_m"], lay["freq_hz"], when, self._location, pattern=self.pattern,
                                            xp=xp, dtype=cdt)
                    self._E_at = when.unix
                    if xp is not np:
                        self._worker_stream.synchronize()
                t_diffuse = time.perf_counter()
                if model.names:
                    M1 = model_covariance(lay["xyz_m"], lay["freq_hz"][:1], model.lmn, model.flux_pol[:1], xp=xp,
                                          dtype=cdt)
                    E1 = None if self._E is None else self._E[:1]
                    R1 = M1 if E1 is None else M1 + 0.5 * E1
                    solve_gains(R1, M1, lay["xyz_m"], lay["freq_hz"][:1], self._flags, self.settings,
                                weights=self._W[:1], extra=E1)
                if xp is not np:
                    self._worker_stream.synchronize()
            t1 = time.perf_counter()
            self.solver_stats["warm_s"] = {"sky_model": round(t_model - t0, 3), "diffuse": round(t_diffuse - t_model, 3),
                                           "kernels": round(t1 - t_diffuse, 3)}
            log.info("GainSolverBlock: the solver is ready in %.2f s (sky model and weights %.2f s, diffuse term "
                     "%.2f s, kernels %.2f s)", t1 - t0, t_model - t0, t_diffuse - t_model, t1 - t_diffuse)
        except Exception as e:  # noqa: BLE001 - a warm-up only; solution 0 reports a real problem
            log.info("GainSolverBlock: warming the solver up failed (%s); solution 0 will do it", e)

    def _solve_job(self, k, valid_from, raw, ntime, start, end, sum_s, tag0, decided_through):
        """The worker: solve on a stream of its own (after the sums' event), post, say how far it decided."""
        try:
            if end is None:
                self.solver_stats["sum_s"] += sum_s
                self._solve_or_skip(k, valid_from, raw, ntime, sum_s, (tag0, decided_through))
            else:
                cp = self._xp
                with self._worker_stream_in_use():
                    self._worker_stream.wait_event(end)
                    end.synchronize()
                    sum_s = cp.cuda.get_elapsed_time(start, end) / 1e3 if start is not None else sum_s
                    self.solver_stats["sum_s"] += sum_s
                    self._solve_or_skip(k, valid_from, raw, ntime, sum_s, (tag0, decided_through))
                    self._worker_stream.synchronize()
        except BaseException as e:  # noqa: BLE001 - handed to the block's thread
            self._worker_error = e
            if self.table is not None:
                self.table.close()
        finally:
            if self.table is not None:
                self.table.decided(tag0, decided_through)

    @property
    def _real_dtype(self):
        """The solve's real dtype: float32 on a GPU (its covariances are complex64), float64 on the CPU."""
        return np.float64 if self._xp is np else np.float32

    def _solve_or_skip(self, k, *args):
        """:meth:`_solve`; a solve that finds too little memory (CuPy's OutOfMemoryError is a MemoryError)
        is skipped -- counted, logged, the last good gains left in force -- rather than ending the run: the
        GPU's memory is the imager's first."""
        try:
            self._solve(k, *args)
        except MemoryError as e:
            self.solver_stats["out_of_memory"] += 1
            self._fail(f"out of memory ({str(e)[:200]})", k)

    def _wait_jobs(self):
        """Wait for the worker's pending solves; re-raise a failure of its own in this thread."""
        for job in self._jobs:
            job.result()
        self._jobs = []
        if self._worker_error is not None:
            err, self._worker_error = self._worker_error, None
            raise RuntimeError(f"GainSolverBlock: the solver's worker failed: {err}") from err

    def on_sequence_end(self, iseq):
        try:
            self._wait_jobs()
            if self._sums.ntime and not self._posted_in_seq:
                if self._sums.ntime >= self.min_samples:
                    log.warning("GainSolverBlock: the sequence ended %d samples into an integration of %d; "
                                "solving from what there is", self._sums.ntime, self._integ)
                    self._solve_or_skip(self._k, self._tag0 + (self._frame if self.apply_from == "after"
                                                               else self._k * self._cadence + self._offset) * self._tpf)
                else:
                    self._fail(f"data too short to solve: {self._sums.ntime} samples, need at least "
                               f"{self.min_samples} (calibration.solve.min_samples)")
            if self.table_path and len(self.part):
                self.write(self.part_path(self._part), final=True)   # the last solution's PNG, if not drawn
        finally:
            self.close()
            if self.table is not None:
                self.table.end_sequence(self._tag0)

    def _model_time(self, k, ntime):
        from astropy.time import Time
        mid_frame = k * self._cadence + self._offset + ntime / 2.0
        return Time(self._tag0 / FS_HZ + mid_frame * self._lay["dt_s"], format="unix", scale="utc")

    def _fail(self, why, k=None):
        self.solver_stats["failures"] += 1
        self.solver_stats["failure_reasons"].append(why)
        if self.table is not None:
            self.table.stats["failures"] += 1
        log.warning("GainSolverBlock: solution %d failed: %s%s", self._k if k is None else k, why,
                    "; the last good solution stays in force" if self.last_solution is not None
                    else "; images stay uncalibrated")

    def _solve(self, k, valid_from, raw=None, ntime=None, sum_s=None, decided=None):
        """Solve integration k (``raw``: its mean raw covariance, default the sums'; ``ntime`` its samples)
        and post it from time tag ``valid_from``; ``decided`` (sequence tag, through tag) is told to the live
        table as soon as the solution is posted."""
        from ..sky.model import sky_model
        lay, xp = self._lay, self._xp
        t0 = time.perf_counter()
        if raw is None:
            raw, ntime, sum_s = self._sums.mean(), self._sums.ntime, self._sum_this
        self.solver_stats["samples"] += ntime
        when = self._model_time(k, ntime)
        if self._location is None:
            self._fail("the header's station has no location (lat_deg, lon_deg, elev_m)", k)
            return
        model = sky_model(self.sources, when, self._location, lay["freq_hz"], pattern=self.pattern,
                          npol=lay["npol"], min_alt_deg=self.min_alt_deg)
        if not model.names:
            self._fail(f"no model source above {self.min_alt_deg:g} deg at {when.isot[:19]} UTC "
                       f"({', '.join(model.dropped) or 'no sources given'})", k)
            return
        # complex64 on a GPU: the solve's arrays (R, M and two products of them, 0.8 GB each in complex128
        # at 784 channels) share the card with the imager; the gains need ~1e-4, not 1e-15
        cdt = np.complex128 if xp is np else xp.complex64
        w = xp.asarray(self._w.transpose(0, 2, 1)).astype(cdt)                            # (c, p, a)
        saturated = None
        if lay["dtype"] == "ci4":
            # 4-bit inputs driven so hard that their samples clip lose correlation, and their gains
            # come out wrong by tens of per cent: flagged from the raw power (4-bit units^2)
            idx = xp.arange(lay["nstand"])
            praw = to_numpy(xp.median(raw[..., idx, idx].real, axis=0)).T                  # (a, p)
            saturated = clip_fraction(praw) > self.saturated_above
        R = raw.astype(cdt, copy=False)          # the sums' mean: an array of this solve's own, scaled in place
        R *= w[..., :, None]
        R *= xp.conj(w[..., None, :])
        M = model_covariance(lay["xyz_m"], lay["freq_hz"], model.lmn, model.flux_pol, xp=xp, dtype=cdt)
        E = None
        if self.diffuse:
            if self._E is None or abs(when.unix - self._E_at) >= self.diffuse_refresh_s:
                from ..sky.model import diffuse_model
                self._E = diffuse_model(lay["xyz_m"], lay["freq_hz"], when, self._location, pattern=self.pattern,
                                        xp=xp, dtype=cdt)
                self._E_at = when.unix
            E = self._E
        settings = self.settings
        if self.reference_stand is not None:
            idx = np.flatnonzero(self._stand_ids == int(self.reference_stand))
            if idx.size:
                from dataclasses import replace
                settings = replace(settings, reference=int(idx[0]))
        if self._W is None:
            self._W = baseline_weights(lay["xyz_m"], lay["freq_hz"], settings.min_baseline_lambda, xp=xp,
                                       dtype=self._real_dtype)
        try:
            last = self.last_solution
            g0 = None if last is None else last.gains.transpose(0, 2, 1)          # (c, p, a): a warm start
            s0 = None if last is None or E is None else last.info.get("extra_scale")
            # the last solution's health flags carry over (one round instead of two), re-derived from
            # scratch once a minute of data so that an input that recovers comes back
            fresh = last is None or k % max(1, int(round(60.0 / self.cadence_s))) == 0
            f0 = None if fresh else last.reasons
            sol = solve_gains(R, M, lay["xyz_m"], lay["freq_hz"], self._flags, settings, weights=self._W, extra=E,
                              g0=g0, extra_scale0=s0, saturated=saturated, flags0=f0)
        except ValueError as e:
            self._fail(str(e), k)
            return
        finally:
            self.solver_stats["solve_s"] += time.perf_counter() - t0
            self.solver_stats["solve_s_each"].append(round(time.perf_counter() - t0, 4))
            self.solver_stats["sum_s_each"].append(round(sum_s or 0.0, 4))
        if self.solutions_per_file and len(self.part) == self.solutions_per_file:
            # the part is full: the next solutions go to a new file, and memory holds one part
            self.part = TablePart(self.solutions_per_file)
            self.valid_from, self.time_unix, self.models = [], [], []
            self._part += 1
        self.part.add(sol)
        self.last_solution = sol
        self.valid_from.append(int(valid_from))
        self.time_unix.append(float(when.unix))
        md = model.to_dict()
        if sol.info.get("extra_scale") is not None:
            md["diffuse_scale_fitted"] = float(np.mean(sol.info["extra_scale"]))
        self.models.append(md)
        self._posted_in_seq += 1
        self.solver_stats["solutions"] += 1
        self.last_solution_at = time.perf_counter()          # the service's solution age
        if self.table is not None:
            self.table.post(valid_from, sol.corrections)
            if decided is not None:            # the images wait for this, never for the files below
                self.table.decided(*decided)
        log.info("gain solution %d (%s UTC, %.2f s of data, model %s%s): %s; %.2f s",
                 self.solver_stats["solutions"] - 1,
                 when.isot[:19], ntime * lay["dt_s"], model.describe(),
                 f" + the Galactic sky x{md['diffuse_scale_fitted']:.2f}" if "diffuse_scale_fitted" in md else "",
                 sol.summary(), time.perf_counter() - t0)
        if self.table_path:
            self.write(self.part_path(self._part))

    def part_path(self, part):
        """The table file of part ``part``: ``table_path`` itself for part 0, then ``<stem>_p001.npz``, ..."""
        from pathlib import Path
        p = Path(self.table_path)
        return p if part == 0 else p.with_name(f"{p.stem}_p{part:03d}{p.suffix}")

    @property
    def written(self):
        """The table files written (and their PNGs)."""
        if not self.table_path or self.last_solution is None:
            return []
        out = []
        for k in range(self._part + 1):
            p = str(self.part_path(k))
            out += [p] + ([p[:-4] + ".png"] if self.png else [])
        return out

    def provenance(self):
        return {"station": self._station_name, "model": self.models[-1] if self.models else {},
                "models": self.models, "settings": self.settings.to_dict(), "cadence_s": self.cadence_s,
                "integration_s": self.integration_s, "cable_removed": bool(self.cable), "diffuse_model": self.diffuse,
                "min_alt_deg": self.min_alt_deg}

    def write(self, path, final=False):
        """Write the solutions so far to ``path`` (.npz) and, with ``png``, the last solution's PNG beside it
        (at a part's first solution, then about every minute of data, and when ``final``)."""
        from ..io.gaintable import write_gain_table
        if not len(self.part):
            return None
        n = self.solver_stats["solutions"]
        p = path
        if self._written_of != (path, n):
            p = write_gain_table(path, self.valid_from, self.part, freq_hz=self._lay["freq_hz"],
                                 stand_ids=self._stand_ids, time_unix=self.time_unix, provenance=self.provenance())
            self._written_of = (path, n)
        due = len(self.part) == 1 or (n - 1) % self._png_every == 0 or final
        if self.png and due and self._png_of != n:
            self._png_of = n
            # the last solution's PNG, drawn from memory, about once a minute of data
            last = self.part.entry(-1)
            self._draw_png((str(p)[:-4] + ".png", {
                "gains": last["gains"][None], "flags": last["flags"][None], "flag_reason": last["flag_reason"][None],
                "freq_hz": self._lay["freq_hz"], "valid_from": self.valid_from, "provenance": self.provenance()},
                f"gain solution {n - 1} ({len(self.part)} in this table): {self._station_name}, "
                f"model {', '.join(self.models[-1].get('sources', []))}"), wait=final)
        return p

    def _draw_png(self, job, wait=False):
        """Draw ``job`` (path, table, title) in the helper process (:class:`~._drawing.DrawingHelper`), or
        here where it cannot run; a PNG asked while the last is still drawing is skipped (counted).
        ``wait``: return once it is written (a sequence's last)."""
        if not self._drawing.run(_draw_gain_png, job, self._count_png, wait=wait):
            self.solver_stats["pngs_skipped"] += 1

    def _count_png(self, drawn):
        path, pid = drawn
        if path is not None:
            self.solver_stats["pngs"] += 1
            self.solver_stats["pngs_in_helper"] += int(pid != os.getpid())

    def close(self):
        """Wait for the PNG being drawn and stop the helper process (it starts again if asked)."""
        self._drawing.close()


def _draw_gain_png(path, table, title):
    """(path or None, the drawing process's id): the gain table PNG of ``table`` (one solution); a failure is
    logged, never raised (a plot must not stop a pipeline)."""
    from ..io.gaintable import gain_table_png
    try:
        gain_table_png(path, table=table, solution=-1, title=title)
    except Exception as e:  # noqa: BLE001
        log.warning("gain table PNG %s not written: %s", path, e)
        path = None
    return path, os.getpid()


def gain_solver(iring, sources, *args, **kwargs):
    """Factory for :class:`GainSolverBlock`."""
    return GainSolverBlock(iring, sources, *args, **kwargs)
