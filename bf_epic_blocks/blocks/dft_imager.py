"""DFTImagerBlock: E-field gulps in, one image every ``accumulate`` frames out (exact DFT).

Thin adapter: header work in ``on_sequence``, which makes the sequence's engine (:mod:`.engines`:
the operator and route, in the input's space; made again only when the header asks for another),
and ``on_data``, one ``image_gulp`` call on it. An integration may span gulps and a gulp may hold
several integrations; a partial integration at the end of a sequence is dropped and counted
(``img_stats['frames_dropped_partial']``), never emitted as a short image.
Float input that did not pass CalFoldBlock (no ``nonfinite`` tally in its header) has its NaN/Inf
samples zeroed and counted here (:mod:`.nonfinite`), so images stay finite.
"""
from __future__ import annotations

import hashlib
import logging
import math
import time
import types

import numpy as np

from ..imaging import patterns
from ..imaging import plan as planner
from ..imaging.dft import DFTOperator
from ..imaging.pixels import GridPlacement, LMGrid, check_lm
from . import _compat
from ._compat import bfp, span_array
from .engines import DFTEngine, ImageOutput, ShardedEngine, ShardedRoute
from .headers import derived_image_header, efield_header, efield_layout, grid_pixels_header
from .nonfinite import get_tally, is_float_dtype, new_tally

log = logging.getLogger(__name__)


class DFTImagerBlock(bfp.TransformBlock):
    """Exact wide-field DFT imager (see :mod:`bf_epic_blocks.imaging.dft`).

    Parameters
    ----------
    iring : E-field ring (labels time, freq, station, pol; ci4/ci8/cf32...; docs/HEADERS.md).
    pixels : an :class:`LMGrid` (output labelled ['time','freq','pol','m','l'], NaN below the
             horizon), an (npix, 2) l, m array (['time','freq','pol','pixel']), or a callable
             ``pixels(time_tag) -> (npix, 2)`` re-evaluated at each integration (tracking; the
             operator is rebuilt when the pixels change).
    accumulate : frames (time samples) per image.
    products, remove_autocorr : as :func:`bf_epic_blocks.imaging.dirty_image`.
    tolerance : the accuracy knob, as :func:`bf_epic_blocks.imaging.dirty_image` (max |I - I_exact| /
           max I_exact; None: precision fp32 on the cheaper route). At each sequence
           :func:`bf_epic_blocks.imaging.plan.resolve` picks the route and precision for that problem on
           the device the block images on (the input ring's space, or the GPUs of ``gpus``).
    method, precision : expert overrides of the route and GEMM precision (see
           :func:`bf_epic_blocks.imaging.plan.resolve`); with a tolerance they restrict the choice.
    plan : instead of tolerance / method / precision, a :class:`~bf_epic_blocks.imaging.plan.Plan` the
           caller resolved for this problem (the pipeline runner does, so that what ``bf-epic plan``
           prints and every part of a pixel split run the same plan).
    The plan is logged, kept in ``self.plan`` and written to the header's ``imager`` section (method,
    precision, tolerance, error_bound, overrides), whoever asked for it.
    gpus : None (image where the input ring lives), or several GPU indices (a list, or 'all'): the
           channels are sharded across those GPUs, one operator each (:mod:`bf_epic_blocks.imaging.multigpu`);
           the input and output rings are then host rings (best 'cuda_host': page-locked, so each GPU's
           copy of its channels is asynchronous and at full bus speed), 4-bit samples cross the bus
           packed, and a gulp must hold whole integrations (gulp_nframe a multiple of ``accumulate``).
    weights : None or complex (nchan|1, nstand, npol|1) direction-independent weights folded into the
           operator; flags from the header are always applied.
    cable : fold the header's cable terms (``station.cable_delay_s``/``cable_gain``) into the operator,
           as CalFoldBlock would apply them to the voltages (used when no CalFoldBlock runs before).
    pattern : None (use the header's ``calibration.pattern`` if CalFoldBlock set one), False (none),
              or a pattern name / callable.
    gains : None, or a :class:`~bf_epic_blocks.imaging.calibration.GainTable` /
           :class:`~.gain_solver.LiveGainTable` of corrections folded into the operator: an integration
           is made with the solution in force at its first frame, the operator rebuilt when that changes
           (for a live table, after waiting until the solver has decided it). Zero corrections drop their
           inputs from the operator and from N_A.
    flag_weights : a :class:`~.rfi_flag.FlagWeights` from the RFIFlagBlock before: each image that kept
           only part of the array (stands flagged for interference) is divided by the fraction of a point
           source's power it holds, so that it stays in the whole array's units.
    watch : None, or a tracking pixel function ``watch(time_tag) -> (ndir, 2)`` (a watchlist's
           :class:`~.watch.WatchPixels`) of directions imaged beside an :class:`LMGrid`'s pixels, by the same
           operator and in the same kernel (their rows ride in the grid's last row tile), moved in place as
           they track. Their images go to a second output ring, ``self.orings[1]`` (:attr:`watch_ring`):
           frames (freq, pol, pixel) of the same images, header as a tracking imager's.
    Output: float32 frames of one image each; header ``imager`` and ``pixels`` say what they are.
    """

    imager_kind = "dft"

    def __init__(self, iring, pixels, accumulate, products=None, remove_autocorr=False, method="auto",
                 precision=None, pattern=None, *args, gpus=None, weights=None, cable=False, tolerance=None,
                 plan=None, gains=None, flag_weights=None, watch=None, **kwargs):
        super().__init__(iring, *args, **kwargs)
        self.watch = watch
        if watch is not None:
            if not isinstance(pixels, LMGrid) or not callable(watch) or gpus is not None:
                raise ValueError(f"{type(self).__name__}: watch directions ride beside a grid's pixels (an LMGrid) "
                                 "on one device; got " + ("several GPUs" if gpus is not None else
                                                          f"pixels {type(pixels).__name__}, watch {watch!r}"))
            self.orings.append(self.create_ring(space=self.orings[0].space))
        self.flag_weights, self._nimg, self._flag_seq = flag_weights, 0, None
        self.gpus, self.weights, self.cable = gpus, weights, cable
        if gains is not None and gpus is not None:
            raise ValueError("DFTImagerBlock: time-variable gains are folded on one device, not with gpus")
        self.gains = gains
        self._gain_index = -1
        self.tolerance = None if tolerance is None else planner.check_tolerance(tolerance)
        self._asked = (method, precision)   # the expert overrides handed to the resolver
        if plan is not None:
            if not isinstance(plan, planner.Plan) or plan.imager != self.imager_kind:
                raise TypeError(f"{type(self).__name__}: plan must be a Plan for the {self.imager_kind!r} imager "
                                f"(bf_epic_blocks.imaging.plan.resolve), got {plan!r}")
            if tolerance is not None or method not in ("auto", None) or precision is not None:
                raise ValueError(f"{type(self).__name__}: give either plan or tolerance / method / precision, "
                                 "not both (the plan already holds them)")
            self.tolerance = plan.tolerance
        self._given_plan = plan
        self.plan = plan
        if int(accumulate) != accumulate or accumulate < 1:
            raise ValueError(f"DFTImagerBlock: accumulate must be a positive integer number of frames, got {accumulate!r}")
        self.accumulate = int(accumulate)
        if not (isinstance(pixels, LMGrid) or callable(pixels)):
            pixels = check_lm(np.asarray(pixels, dtype=np.float64))
        self.pixels = pixels
        self.products, self.remove_autocorr = products, remove_autocorr
        self.pattern = pattern
        self.method = plan.method if plan is not None else method
        self.precision = plan.precision if plan is not None else precision
        self.img_stats = {"images": 0, "frames_imaged": 0, "frames_dropped_partial": 0, "operator_builds": 0,
                          "operator_moves": 0}
        self.engine = self._key = None   # the sequence's engine (.engines), and what its header was

    def define_valid_input_spaces(self):
        return ("cuda_host", "system") if getattr(self, "gpus", None) is not None else "any"

    def define_output_nframes(self, input_nframe):
        # At most ceil(n / accumulate) integrations can complete within n new frames.
        return max(1, math.ceil(input_nframe / self.accumulate))

    @property
    def watch_ring(self):
        """The ring of the watch directions' images (``watch``), or None."""
        return self.orings[1] if self.watch is not None else None

    # a second output ring (the watch directions'): the TransformBlock hooks, for every output ring
    def _define_output_nframes(self, input_nframes):
        return [self.define_output_nframes(input_nframes[0])] * len(self.orings)

    def _on_sequence(self, iseqs):
        ohdr = self.on_sequence(iseqs[0])
        return [ohdr] if self.watch is None else [ohdr, self._watch_header(ohdr)]

    def _on_data(self, ispans, ospans):
        if self.watch is not None:
            self.engine.output.xout = span_array(ospans[1])
        return [self.on_data(ispans[0], ospans[0])] * len(ospans)

    def _on_skip(self, islices, ospans):
        return [self.on_skip(islices[0], o) for o in ospans]

    # --------------------------------------------------------------- sequence set-up
    def _space_xp(self):
        if _compat.space_of(self.irings[0]) == "cuda":
            import cupy
            return cupy
        return np

    def _device(self):
        """'cpu' or 'gpu': where this block images (the input ring's space, or the GPUs of ``gpus``)."""
        return "gpu" if self.gpus is not None or _compat.space_of(self.irings[0]) == "cuda" else "cpu"

    def plan_for(self, hdr, lm=None, nant=None) -> planner.Plan:
        """The plan this block images a sequence with E-field header ``hdr`` by: the plan it was given,
        or :func:`bf_epic_blocks.imaging.plan.resolve` for that problem (``lm``: the (npix, 2) pixels,
        default this block's; ``nant``: the antennas used, default the header's unflagged stands) on this
        block's device. Needs no GPU."""
        if self._given_plan is not None:
            return self._given_plan
        lay = efield_layout(hdr, type(self).__name__)
        if lm is None:
            lm = self.pixels.lm if isinstance(self.pixels, LMGrid) else \
                check_lm(np.asarray(self.pixels(lay["time_tag"]), dtype=np.float64)) if callable(self.pixels) \
                else self.pixels
        npix = len(lm)
        if nant is None:
            nant = int((~lay["flags"]).any(axis=1).sum())
        method, precision = self._asked
        # integer voltages reach one GPU's operator as they are, which makes the fused integer modes
        # candidates; on several GPUs each decodes its channels first
        kind = planner.input_kind_of(lay["dtype"]) if self.gpus is None else "complex"
        problem = planner.Problem(npix, max(1, nant), self.accumulate, lay["nchan"], lay["npol"], self.products)
        return planner.resolve(self.tolerance, device=self._device(), problem=problem, input_kind=kind,
                               precision=precision, method=method, imager=self.imager_kind)

    def _resolve(self, hdr, lm, nant):
        plan = self.plan_for(hdr, lm, nant)
        if plan != self.plan:   # logged once, not at every rebuild of a tracking operator
            log.info("%s: %s", type(self).__name__, plan.describe())
        self.plan = plan
        self.method, self.precision = plan.method, plan.precision

    def _weights(self):
        """The direction-independent weights folded into the operator, (1|nchan, nstand, npol) complex."""
        lay = self._lay
        w = (~lay["flags"])[None].astype(np.complex128)
        if self.weights is not None:
            w = w * np.asarray(self.weights, dtype=np.complex128)
        if self.gains is not None and self._gain_index >= 0:
            g = np.asarray(self.gains.corrections(self._gain_index), dtype=np.complex128)   # (nchan|1, nstand, npol|1)
            w = w * g
        if self.cable:
            w = w * self._cable_weights()
        return w

    def _cable_weights(self):
        """The header's cable terms as weights (nchan, nstand, npol), made once a sequence: each gain solution
        folded in multiplies them again (at the whole band they are 4e5 complex exponentials, ~0.1 s of
        the imager's thread)."""
        if getattr(self, "_cable", None) is None or self._cable[0] is not self._lay:   # a new sequence
            st, lay = self._station_hdr, self._lay
            if "cable_delay_s" not in st or "cable_gain" not in st:
                raise ValueError("DFTImagerBlock: cable=True needs station.cable_delay_s and station.cable_gain "
                                 "(nstand, npol, nchan) in the header")
            from ..imaging.calibration import cable_weights
            npol = lay["npol"]
            self._cable = (lay, cable_weights(np.asarray(st["cable_delay_s"])[:, :npol],
                                             np.asarray(st["cable_gain"])[:, :npol], lay["freq_hz"]))
        return self._cable[1]

    def _operator(self, lm):
        """(operator, route) for pixels ``lm`` on this block's device (:class:`~.engines.DFTEngine`'s build)."""
        lay, xp = self._lay, self._xp
        pat = self._pattern_name
        w = self._weights()
        # the antennas the operator keeps: those with a non-zero weight somewhere
        self._resolve(self._hdr, lm, int((w != 0).any(axis=(0, 2)).sum()))
        B = None if pat is None else patterns.pattern_array(pat, xp.asarray(lm), xp.asarray(lay["freq_hz"]), lay["npol"])
        op = DFTOperator(xp.asarray(lay["xyz_m"]), xp.asarray(lay["freq_hz"]), xp.asarray(lm),
                         npol=lay["npol"], weights=xp.asarray(w), pattern=B, precision=self.precision)
        route = op.accumulator(self.products, remove_autocorr=self.remove_autocorr,
                               method=self.method, ntime_hint=self.accumulate)
        self.img_stats["operator_builds"] += 1
        return op, route

    def _repoint(self, op, lm):
        """Operator ``op`` pointed at pixels ``lm`` in place (:class:`~.engines.DFTEngine`'s repoint): the
        tracking pixels moved, nothing else did (with ``watch``, only the watch directions after the grid's
        pixels, whose rows alone are made again)."""
        lay, xp = self._lay, self._xp
        pat = self._pattern_name
        first = 0 if self.watch is None else self.pixels.lm.shape[0]
        lm = np.asarray(lm)[first:]
        B = None if pat is None else patterns.pattern_array(pat, xp.asarray(lm), xp.asarray(lay["freq_hz"]), lay["npol"])
        op.repoint(lm, pattern=B, first=first)
        self.img_stats["operator_moves"] += 1

    def _with_watch(self, time_tag):
        """The grid's pixels and the watch directions at ``time_tag`` after them, (ngrid + ndir, 2)."""
        w = check_lm(np.asarray(self.watch(time_tag), dtype=np.float64))
        return np.concatenate([self.pixels.lm, w])

    def _sharded_route(self, lm):
        """The channels over the GPUs of ``gpus`` for pixels ``lm`` (:class:`~.engines.ShardedEngine`'s build)."""
        from ..imaging.multigpu import ShardedOperator
        lay = self._lay
        pat = self._pattern_name
        w = self._weights()
        self._resolve(self._hdr, lm, int((w != 0).any(axis=(0, 2)).sum()))
        B = None if pat is None else patterns.pattern_array(pat, np.asarray(lm), lay["freq_hz"], lay["npol"])
        # images placed on the whole l, m grid (NaN below the horizon) on the GPUs, and copied from
        # there straight into the output span
        scatter = (np.flatnonzero(self.pixels.mask), self.pixels.size ** 2) if isinstance(self.pixels, LMGrid) \
            else None
        sh = ShardedOperator(lay["xyz_m"], lay["freq_hz"], lm, self.gpus, npol=lay["npol"], weights=w, pattern=B,
                             precision=self.precision, scatter=scatter)
        self.img_stats["operator_builds"] += 1
        return ShardedRoute(sh, self.products, self.method, self.remove_autocorr, self.accumulate, lay["dtype"])

    def _build(self, lm):
        """This sequence's engine (:mod:`.engines`) for pixels ``lm``."""
        fn = self._with_watch if self.watch is not None else \
            self.pixels if callable(self.pixels) and not isinstance(self.pixels, LMGrid) else None
        kw = dict(accumulate=self.accumulate, dtype=self._lay["dtype"], name=type(self).__name__, pixels_fn=fn)
        if self.gpus is not None:
            return ShardedEngine(self._sharded_route, lm, **kw)
        return DFTEngine(self._operator, lm, products=self.products, remove_autocorr=self.remove_autocorr,
                         repoint=self._repoint, **kw)

    def _engine_key(self, lm):
        """What this sequence's engine depends on in its header (and pixels): a new engine is built only
        when it differs from the last sequence's."""
        lay = self._lay
        h = hashlib.sha256()
        for a in (lay["xyz_m"], lay["freq_hz"], lay["flags"], lm):
            h.update(np.ascontiguousarray(a).tobytes())
        if self.cable:
            for k in ("cable_delay_s", "cable_gain"):
                if k in self._station_hdr:
                    h.update(np.ascontiguousarray(np.asarray(self._station_hdr[k])).tobytes())
        return (lay["dtype"], lay["nchan"], lay["nstand"], lay["npol"], np.shape(lm), self._pattern_name,
                self._xp.__name__, h.hexdigest())

    def on_sequence(self, iseq):
        ihdr = iseq.header
        lay = efield_layout(ihdr, "DFTImagerBlock")
        self._lay, self._xp, self._hdr = lay, self._space_xp(), ihdr
        self._nimg, self._flag_seq = 0, int(lay["time_tag"])
        self._station_hdr = ihdr.get("station", {})
        cal = ihdr.get("calibration", {})
        self._pattern_name = cal.get("pattern") if self.pattern is None else (self.pattern or None)
        if callable(self._pattern_name):
            fn = self._pattern_name
            self._pattern_name = f"user:{getattr(fn, '__qualname__', id(fn))}"
            patterns.register_pattern(self._pattern_name, fn)
        if self.watch is not None:
            lm = self._with_watch(lay["time_tag"])
        elif isinstance(self.pixels, LMGrid):
            lm = self.pixels.lm
        elif callable(self.pixels):
            lm = check_lm(np.asarray(self.pixels(lay["time_tag"]), dtype=np.float64))
        else:
            lm = self.pixels
        self._seq_lm = lm
        # the watch directions move, and the engine moves them in place: it depends on their count only
        key_lm = lm if self.watch is None else \
            np.concatenate([self.pixels.lm, np.zeros((len(lm) - len(self.pixels.lm), 2))])
        key = self._engine_key(key_lm)
        if self.gains is not None:
            # every sequence starts uncalibrated (solution -1) with an operator of its own
            self._gain_index, self._gains_tag0, key = -1, int(lay["time_tag"]), None
            self.gains.check_shape(lay["nchan"], lay["nstand"], lay["npol"])
        if self.engine is None or key is None or key != self._key:
            self.engine = None      # the last sequence's operator let go before the new one is made
            self.engine, self._key = self._build(lm), key
        eng = self.engine
        eng.solution_hook = self._solution_hook if self.gains is not None else None
        nprod = len(eng.products)
        dt, t0 = lay["dt_s"], lay["t0_s"]
        f = lay["freq_hz"]
        fscale = [float(f[0]), float(f[1] - f[0]) if len(f) > 1 else 0.0]
        ohdr = derived_image_header(ihdr)
        # float input not cleaned upstream: zero and count non-finite samples here
        self.tally = None
        if is_float_dtype(lay["dtype"]) and get_tally(ihdr) is None:
            self.tally = new_tally(type(self).__name__, lay["nstand"], lay["npol"])
            ohdr["nonfinite"] = self.tally.to_header()
        if isinstance(self.pixels, LMGrid):
            g = self.pixels
            shape = [-1, lay["nchan"], nprod, g.size, g.size]
            labels = ["time", "freq", "pol", "m", "l"]
            ax0 = float(g.axis[0])
            scales = [[t0, dt * self.accumulate], fscale, None, [ax0, g.cell], [ax0, g.cell]]
            units = ["s", "Hz", None, None, None]
            ohdr["pixels"] = grid_pixels_header(g.size, g.cell, g.mask)
            place = GridPlacement(np.flatnonzero(g.mask), g.size * g.size, self._xp,
                                  extra=len(lm) - len(g.lm))
            ohdr["_tensor"] = {"dtype": "f32", "shape": shape, "labels": labels, "scales": scales, "units": units}
        else:
            _pixel_list_output(ohdr, [[t0, dt * self.accumulate], fscale], lay["nchan"], nprod, lm,
                               "track" if callable(self.pixels) else "list")
            place = None
        size = self.pixels.size if isinstance(self.pixels, LMGrid) else None
        eng.begin(ImageOutput(place, size, self._count), time_tag=lay["time_tag"],
                  ticks_per_frame=lay["ticks_per_frame"], tally=self.tally, seq_name=ihdr.get("name"))
        ohdr["pol_products"] = list(eng.products)
        ohdr["imager"] = {"kind": self.imager_kind, **self.plan.header(), "method": eng.method,
                          "products": list(eng.products), "accumulate_frames": self.accumulate,
                          "remove_autocorr": bool(self.remove_autocorr), "nant_used": int(eng.nant_used),
                          "pattern": self._pattern_name,
                          "integration_ticks": self.accumulate * lay["ticks_per_frame"]}
        log.info(type(self).__name__ + " %s: %d pixels%s, %d antennas used, %s route, %s, %d frames per image",
                 ihdr.get("name"), eng.npix, "" if self.watch is None else
                 f" ({len(lm) - len(self.pixels.lm)} of them watch directions)", eng.nant_used, eng.method,
                 self.precision, self.accumulate)
        return ohdr

    def _watch_header(self, ohdr):
        """The watch ring's header: the images' (``ohdr``) with the watch directions as a tracking pixel list."""
        whdr = dict(ohdr)
        t = ohdr["_tensor"]
        _pixel_list_output(whdr, t["scales"][:2], t["shape"][1], t["shape"][2],
                           np.asarray(self._seq_lm)[len(self.pixels.lm):], "track")
        return whdr

    # --------------------------------------------------------------- per gulp
    def _solution_hook(self, eng, pos, count):
        """The engine's ``solution_hook``: rebuild the operator when the integration starting at frame ``pos``
        of this gulp needs another solution; return how many of the next ``count`` integrations share it."""
        lay = self._lay
        tpf = lay["ticks_per_frame"]
        tags = eng.time_tag + (eng.frame + pos + self.accumulate * np.arange(count, dtype=np.int64)) * tpf
        if hasattr(self.gains, "wait_through"):
            self.gains.wait_through(self._gains_tag0, int(tags[-1]))
        idx = self.gains.index(tags)
        if int(idx[0]) != self._gain_index:
            self._gain_index = int(idx[0])
            op = getattr(eng, "op", None)
            # the same inputs flagged: the solution goes into the operator in place (its route and CUDA
            # graphs kept); other flags change N_A and the antennas kept, and need a new operator
            if op is not None and hasattr(op, "reweight") and op.reweight(self._weights()):
                how = "in place"
                self.img_stats["operator_reweights"] = self.img_stats.get("operator_reweights", 0) + 1
            else:
                how = "by a new operator"
                op = None           # the old operator let go before the new is built (a whole band's: 15 GB)
                eng._rebuild(eng.lm)
            self.img_stats["solutions_applied"] = self.img_stats.get("solutions_applied", 0) + 1
            log.info("%s: gain solution %d folded into the operator %s from frame %d (%d inputs kept)",
                     type(self).__name__, self._gain_index, how, eng.frame + pos, eng.nant_used)
        same = np.flatnonzero(idx != idx[0])
        return int(same[0]) if same.size else count

    def _count(self, g):
        self.img_stats["images"] += g
        self.img_stats["frames_imaged"] += g * self.accumulate

    # --------------------------------------------------------------- before a live stream
    def warm_up(self, dtype="ci4", nchan=2, nant=8):
        """Run one small integration through this block's own route (``on_sequence`` + the per-gulp
        path) on its device, then forget it; returns the seconds it took (0 where there is nothing to
        warm: the CPU, or several GPUs).

        Why: on a GPU the first gulp of a stream pays for CuPy's kernel compilation (seconds on a
        machine whose kernel cache is empty), cuBLAS's start-up and the first CUDA-graph capture. For
        a recording that only delays the first image; for a live stream the source cannot wait, and
        what it receives meanwhile must be held (the capture's queue) or, with Bifrost's C capture
        behind a ring that fills, is dropped by the kernel. Called by the pipeline runner before a
        live source starts; the stream's own operator is still built at its first sequence."""
        xp = self._space_xp()
        if self.gpus is not None or xp is np:
            return 0.0
        t0 = time.perf_counter()
        rng = np.random.default_rng(0)
        freq = 60e6 + 25e3 * np.arange(nchan)
        station = {"xyz_m": rng.normal(0.0, 30.0, (nant, 3)), "flags": np.zeros((nant, 2), bool),
                   "cable_delay_s": np.zeros((nant, 2, nchan)), "cable_gain": np.ones((nant, 2, nchan))}
        hdr = efield_header("warm-up", 0, freq, 1.0 / 25e3, station, dtype=dtype, npol=2)
        saved = (dict(self.img_stats), self.plan, self.method, self.precision)
        hdr["_tensor"]["dtype"] = dtype
        ohdr = self.on_sequence(types.SimpleNamespace(header=hdr))
        shape = [1] + list(ohdr["_tensor"]["shape"][1:])
        if dtype == "ci4":  # its 'cuda' storage form: one byte per sample
            idata = xp.asarray(rng.integers(0, 256, (self.accumulate, nchan, nant, 2), dtype=np.uint8))
        elif dtype == "cf32":
            idata = xp.asarray((rng.normal(size=(self.accumulate, nchan, nant, 2)) + 1j).astype(np.complex64))
        else:
            raise ValueError(f"DFTImagerBlock.warm_up: dtype 'ci4' or 'cf32' (what live sources and CalFoldBlock "
                             f"write), got {dtype!r}")
        out = xp.zeros(shape, np.float32)
        if self.watch is not None:
            self.engine.output.xout = xp.zeros(shape[:3] + [self.engine.npix - len(self.pixels.lm)], np.float32)
        self.engine.image_gulp(idata, out)
        xp.cuda.get_current_stream().synchronize()
        self.img_stats, self.plan, self.method, self.precision = saved
        self.engine = self._key = None
        dt = time.perf_counter() - t0
        log.info("%s: warmed up on the GPU in %.2f s (%s, %s route, %s)", type(self).__name__, dt, dtype,
                 self.method, self.precision)
        return dt

    def on_data(self, ispan, ospan):
        out = span_array(ospan)
        nout = self.engine.image_gulp(span_array(ispan), out)
        if self.flag_weights is not None and nout:
            q = self.flag_weights.take(self._flag_seq, self._nimg, nout)
            if q is not None:          # images that kept part of the array: back to the whole array's units
                with _compat.stream_context():
                    xp = self._xp
                    inv = xp.asarray(np.where(q > 0, 1.0 / np.where(q > 0, q, 1.0), 0.0).astype(out.dtype))
                    for o in (out, self.engine.output.xout) if self.watch is not None else (out,):
                        o[:nout] *= inv.reshape(inv.shape + (1,) * (o.ndim - 2))
            self._nimg += nout
        return nout

    def on_sequence_end(self, iseq):
        dropped = self.engine.end_sequence()
        if dropped:
            self.img_stats["frames_dropped_partial"] += dropped
            log.warning("DFTImagerBlock: %d frames at the end of sequence %s did not fill an integration of %d "
                        "and were not imaged", dropped, iseq.header.get("name"), self.accumulate)


def _pixel_list_output(hdr, scales, nchan, nprod, lm, kind):
    """Set ``hdr``'s ``_tensor`` and ``pixels`` for frames of images of a pixel list: (freq, pol, pixel) of
    ``nchan`` channels, ``nprod`` products and the (npix, 2) directions ``lm``; ``scales`` the time and
    frequency axes' [start, step]; ``kind`` 'list' or 'track'."""
    hdr["_tensor"] = {"dtype": "f32", "shape": [-1, int(nchan), int(nprod), len(lm)],
                      "labels": ["time", "freq", "pol", "pixel"], "scales": list(scales) + [None, None],
                      "units": ["s", "Hz", None, None]}
    hdr["pixels"] = {"kind": kind, "lm": np.asarray(lm).tolist()}


def dft_imager(iring, pixels, accumulate, *args, **kwargs):
    """Factory for :class:`DFTImagerBlock`."""
    return DFTImagerBlock(iring, pixels, accumulate, *args, **kwargs)
