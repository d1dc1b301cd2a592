"""Turn a validated pipeline configuration (:mod:`.config`) into a block graph, plan it, run it.

    source (TBF / TBX file | simulated sky | UDP) -> CalFoldBlock -> imager (DFT | w-stacking | MOFF) -> ImageWriterBlock

The station table from LSL is what joins the configuration to the blocks: the sources put its
positions, flags and cable terms (for the channels in use) into the sequence header, CalFoldBlock
applies the cable terms and flags, the imager builds its operator from the positions.

On a GPU, when calibration is static (no ``gains_table``) and the imager is the DFT one, there is
no CalFoldBlock: the imager folds the cable terms, flags and pattern into its operator (D A, the
same image: docs in :mod:`bf_epic_blocks.blocks.calfold`), and 4/8-bit samples go to it as integers
(exact integer covariances, one CUDA-graph replay per integration). That saves a pass that writes
and reads every sample as complex64 and a block thread's per-gulp Python (Bifrost-style blocks
share one interpreter lock). Live UDP input folds the same way: its blocks read guaranteed, and the
capture thread's bounded queue is where a pipeline that falls behind loses (counted) data. On the
CPU, CalFoldBlock's complex route is the faster one and is kept.
"""
from __future__ import annotations

import contextlib
import logging
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..imaging import cost
from ..imaging._xp import device_kind
from ..conventions import FS_HZ
from ..imaging.pixels import LMGrid, lm_grid
from ..imaging.products import resolve_products

log = logging.getLogger("bf_epic_blocks")


@dataclass
class Graph:
    """The blocks of one pipeline and what they will do."""
    pipeline: object
    source: object
    calfold: object
    imager: object
    writer: object
    nframe_total: int | None
    station: object
    outdir: str
    search: object = None
    cube: object = None
    solver: object = None
    watch: object = None
    snippets: object = None
    budget: object = None          # the output budget's sweeper while the run goes
    oims: object = None

    @property
    def sinks(self):
        return [b for b in (self.writer, self.search, self.cube, self.watch, self.snippets, self.oims)
                if b is not None]


def capture_format(src_cfg):
    """'tbf' or 'tbx' for a file source (``source.kind: file`` is told by the file's frame id); None otherwise."""
    kind = src_cfg["kind"]
    if kind == "file":
        from ..io.formats import detect_format
        return detect_format(src_cfg["path"])
    return kind if kind in ("tbf", "tbx") else None


def _scan(path, report=True, fmt="tbf"):
    """scan_tbf / scan_tbx with its warnings (a truncated last frame) sent to the log instead of stderr
    (``report=False``: not at all, when the source block will report them itself)."""
    import os
    import warnings
    from ..io.tbf import scan_tbf
    from ..io.tbx import scan_tbx
    try:                     # the same file unchanged: scanned once (run's memory check, then its graph)
        st = os.stat(path)
        key = (os.path.realpath(path), fmt, st.st_size, st.st_mtime_ns)
    except OSError:
        key = None
    hit = _SCANS.get(key) if key is not None else None
    if hit is None:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            info = (scan_tbx if fmt == "tbx" else scan_tbf)(path)
        hit = (info, [str(w.message) for w in caught])
        if key is not None:
            if len(_SCANS) >= 4:
                _SCANS.pop(next(iter(_SCANS)))
            _SCANS[key] = hit
    for m in hit[1] if report else ():
        log.warning("%s", m)
    return hit[0]


_SCANS: dict = {}


def load_station_for(cfg, info=None, per_channel=True):
    """The StationTable the configuration names, with the YAML flags added (``auto``: the TBF file's).

    For a simulated source or a capture file (``info``: its scan) the channels are known here, so the
    table comes from the station cache when an earlier run made it
    (:func:`bf_epic_blocks.station.load_station`). ``per_channel=False``: what :func:`plan` needs, the
    cached table where an earlier run made one, else LSL's without the per-channel terms, so that planning
    a configuration, even one refused for its size, neither computes nor caches them."""
    from ..station import load_station
    st_cfg, src = cfg["station"], cfg["source"]
    name = st_cfg.get("ssmif") or st_cfg.get("name")
    if name == "auto":
        name = (info or _scan(src["path"], report=False)).station_hint
    freq = channel_freqs(cfg) if src["kind"] == "simulated" else None if info is None else np.asarray(info.freq_hz)
    return load_station(name, extra_flags=st_cfg.get("flags") or None, freq_hz=freq, write_cache=per_channel)


def channel_width_hz(cfg):
    """The source's channel width in Hz: the simulated channels', a capture file's (scanned), or the NDP
    F-engine's (196 MHz / 8192) for a live stream, which learns its channels from the packets."""
    src = cfg["source"]
    if src["kind"] == "simulated":
        return float(src["channels"]["width_hz"])
    if src["kind"] == "udp":
        from ..io.udp import NDP_CHAN_BW_HZ
        return float(NDP_CHAN_BW_HZ)
    return float(_scan(src["path"], report=False, fmt=capture_format(src)).chan_bw_hz)


def channel_freqs(cfg):
    ch = cfg["source"]["channels"]
    return (ch["first"] + np.arange(ch["count"])) * ch["width_hz"]


def tracking_pixels(source, size, fov_deg, update_s, location):
    """A function time_tag -> (size*size, 2) l, m of a square patch centred on ``source``.

    The patch lies in the plane tangent to the source's direction (x towards increasing azimuth,
    i.e. East for a source in the North, y towards the zenith), cell = fov / size. The centre is
    recomputed every ``update_s`` seconds of data (time tags are quantised to that step), so the
    imager rebuilds its operator only that often. Raises ValueError when the source or part of the
    patch is below the horizon.
    """
    from ..io.tbf import time_tag_to_time
    from ..sky import resolve_source, source_directions
    src = resolve_source(source)
    step = max(1, int(round(update_s * FS_HZ)))
    cell = math.radians(fov_deg) / size
    off = (np.arange(size) - size // 2) * cell
    oy, ox = np.meshgrid(off, off, indexing="ij")
    cache = {}

    def pixels(time_tag):
        key = int(time_tag) // step
        if key in cache:
            return cache[key]
        t = time_tag_to_time(key * step)
        d = source_directions([src], t, location)
        if len(d.sources) == 0:
            raise ValueError(f"tracked source {src.name} is below the horizon at {t.isot} UTC")
        s = np.array([d.l[0], d.m[0], d.n[0]])
        e1 = np.array([s[1], -s[0], 0.0])
        e1 = e1 / np.linalg.norm(e1) if np.linalg.norm(e1) > 1e-9 else np.array([1.0, 0.0, 0.0])
        e2 = np.cross(e1, s)
        v = s[None, None, :] + ox[..., None] * e1 + oy[..., None] * e2
        v /= np.linalg.norm(v, axis=-1, keepdims=True)
        if np.any(v[..., 2] <= 0):
            raise ValueError(f"part of the {fov_deg} deg patch around {src.name} is below the horizon at {t.isot} UTC")
        lm = v[..., :2].reshape(-1, 2)
        cache.clear()
        cache[key] = lm
        return lm

    pixels.source = src
    return pixels


def channel_block_range(cfg, info):
    """(start, stop, run_index, nruns) of ``source.channel_block`` in a TBF file's channels, or None
    for all channels. Raises ValueError for a block the file does not have."""
    from ..blocks.image_writer import channel_runs
    k = cfg["source"].get("channel_block")
    if k is None:
        return None
    runs = channel_runs(info.freq_hz)
    if k >= len(runs):
        raise ValueError(f"source.channel_block: {k} asked for, but {cfg['source']['path']} has {len(runs)} "
                         f"channel block(s) (runs of evenly spaced channels: {runs})")
    return runs[k][0], runs[k][1], k, len(runs)


def _pixels(cfg, station):
    im = cfg["imager"]
    if im.get("track"):
        tr = im["track"]
        return tracking_pixels(tr["source"] if not isinstance(tr["source"], dict) else tr["source"],
                               tr["size"], tr["fov_deg"], tr["update_s"], station.location)
    g = im["grid"]
    return lm_grid(g["size"], cell=g.get("cell"), min_elevation_deg=im.get("min_elevation_deg") or 0.0)


def imager_sample_bits(cfg, dev):
    """4 when 4-bit integer voltages reach the DFT imager on one GPU (every file and live format here is
    ci4, and so is a quantised simulated sky; the calibration is folded into the operator, so no
    CalFoldBlock turns them complex), else None: what makes the fused integer modes candidates."""
    src = cfg["source"]
    if dev != "gpu" or not folds_calibration(cfg, dev):
        return None
    return 4 if src["kind"] != "simulated" or src.get("quantize") else None


def imaging_plan(cfg, npix, nstand, nchan, dev):
    """The imager's :class:`~bf_epic_blocks.imaging.plan.Plan` for this configuration on ``dev`` ('cpu',
    'gpu', or 'gpus' for several GPUs sharing the channels): :func:`bf_epic_blocks.imaging.plan.resolve`
    for ``imager.tolerance`` (and the expert overrides ``imager.method`` / ``imager.precision`` of the
    dft imager), ``npix`` pixels, ``nstand`` antennas used and ``nchan`` channels, with the input
    :func:`imager_sample_bits` says reaches the imager. Planning for a GPU needs no CuPy and no GPU."""
    from ..imaging import plan as planner
    im = cfg["imager"]
    kind = "ci4" if imager_sample_bits(cfg, dev) == 4 else "complex"
    problem = planner.Problem(npix, max(1, nstand), int(im["accumulate_frames"]), max(1, nchan), 2, im["products"])
    device = "cpu" if dev == "cpu" else "gpu"
    if im["kind"] == "dft":
        return planner.resolve(im["tolerance"], device=device, problem=problem, input_kind=kind,
                               precision=im["precision"], method=im["method"])
    return planner.resolve(im["tolerance"], device=device, problem=problem, input_kind=kind, imager=im["kind"])


def _device(cfg):
    """('cpu', None), ('gpu', index), or ('gpus', [indices]) for several GPUs (channels sharded, or the
    grid's pixels split: :func:`~.config.resolved_split`)."""
    dev = cfg["device"]
    if dev == "cpu":
        return "cpu", None
    spec = dev.split(":")[1]
    if spec == "all" or "," in spec:
        from ..imaging.multigpu import resolve_devices
        devs = resolve_devices("all" if spec == "all" else [int(i) for i in spec.split(",")])
        return ("gpus", devs) if len(devs) > 1 else ("gpu", devs[0])
    idx = int(spec)
    from ..imaging._xp import gpu_available
    if not gpu_available():
        raise RuntimeError(f"device {dev!r} asked for, but CuPy or a CUDA GPU is not available here; "
                           "use device: cpu (or --set device=cpu)")
    import cupy
    cupy.cuda.Device(idx).use()
    return "gpu", idx


def folds_calibration(cfg, dev):
    """True when the imager folds the calibration into its operator(s) and no CalFoldBlock runs:
    the DFT imager on several GPUs, or on one GPU without a gains table (static calibration, or live
    solutions from ``calibration.solve``, which the imager folds in as they come); see the module
    docstring. ``dev``: 'cpu', 'gpu' or 'gpus'."""
    if cfg["imager"]["kind"] != "dft":
        return False
    if dev == "gpus":
        return True
    return dev == "gpu" and not cfg["calibration"].get("gains_table")


def warm_live_imager(cfg, station):
    """Compile the GPU imager's route before a live source opens its socket: a live stream cannot
    wait seconds for the first gulp's kernel compilation (its packets would pile up and, with
    Bifrost's capture, be dropped by the kernel). An imager with this configuration's pixels, route,
    precision and calibration folding is built in a scratch graph that never runs, and runs one
    small integration (:meth:`DFTImagerBlock.warm_up`); kernels and libraries stay loaded for the
    real one. Returns the seconds it took."""
    from ..blocks import ArraySourceBlock, DFTImagerBlock, bfp
    from ..blocks.headers import efield_header
    im, cal = cfg["imager"], cfg["calibration"]
    fold = folds_calibration(cfg, "gpu")
    pixels = _pixels(cfg, station)
    npix = pixels.npix if hasattr(pixels, "npix") else im["track"]["size"] ** 2
    plan = imaging_plan(cfg, npix, int((~station.flags).any(axis=1).sum()), 1, "gpu")
    dtype = "ci4" if fold else "cf32"
    hdr = efield_header("warm-up", 0, [60e6, 60.025e6], 4e-5, {"xyz_m": np.zeros((8, 3))}, dtype=dtype)
    pattern = None if cal.get("pattern") in (None, "none") else cal["pattern"]
    extra = dict(cable=bool(cal["cable"]), pattern=pattern or False) if fold else {}
    with bfp.Pipeline():
        src = ArraySourceBlock(np.zeros((1, 2, 8, 2), np.uint8 if dtype == "ci4" else np.complex64), hdr, 1,
                               space="cuda")
        img = DFTImagerBlock(src, pixels, im["accumulate_frames"], plan=plan,
                             products=im["products"], remove_autocorr=im["remove_autocorr"], **extra)
    return img.warm_up(dtype)


#: ``source.gulp_nframe: auto`` for a capture file imaged on a GPU: about this many bytes of 4-bit
#: samples per gulp. There the block threads' host work per gulp (they share one interpreter lock), not
#: the GPU, sets the pace, so fewer, larger gulps run faster.
AUTO_GULP_BYTES = 64 << 20
#: ``auto`` everywhere else: live streams (latency), simulated skies and every CPU pipeline (compute
#: bound, and a CPU gulp is unpacked to 8-byte complex samples)
AUTO_GULP_FRAMES = 1024


def gulp_frames(cfg, dev, nchan=None, nstand=None):
    """Frames per source gulp: ``source.gulp_nframe``, or for ``auto`` (see :data:`AUTO_GULP_BYTES`)
    1,024, or ~64 MiB of samples (a multiple of 256 frames) for a capture file of ``nchan`` channels and
    ``nstand`` stands on a GPU (``dev`` 'gpu' or 'gpus'; several GPUs round it to whole integrations)."""
    g = cfg["source"]["gulp_nframe"]
    if g != "auto":
        return int(g)
    n = AUTO_GULP_FRAMES
    if dev in ("gpu", "gpus") and cfg["source"]["kind"] in ("tbf", "tbx", "file") and nchan and nstand:
        n = max(n, AUTO_GULP_BYTES // (2 * int(nchan) * int(nstand)) // 256 * 256)
    if dev == "gpus":
        acc = int(cfg["imager"]["accumulate_frames"])
        n = acc * max(1, round(n / acc))
    return n


def writes_through_helper(cfg):
    """Whether the image writer of ``cfg`` writes its grid images through a helper process: on a GPU
    (astropy's per-image work would hold the interpreter lock the source and imager threads share; see
    ImageWriterBlock), when there are FITS or PNG grid images to write."""
    out, im = cfg["output"], cfg["imager"]
    return (str(cfg["device"]).startswith("gpu") and bool(out["fits"] or out["png"])
            and im.get("track") is None)


def _input(cfg, dev):
    """(capture format or None, scan info or None, station table, frames per gulp) of ``cfg``'s source on
    ``dev``. A capture file is scanned once, here (the source block is handed the result), so its
    warnings are logged here."""
    fmt = capture_format(cfg["source"])
    info = _scan(cfg["source"]["path"], fmt=fmt) if fmt is not None else None
    station = load_station_for(cfg, info)
    nchan = None
    if info is not None:
        cb = channel_block_range(cfg, info)
        nchan = cb[1] - cb[0] if cb else int(info.nchan)
    return fmt, info, station, gulp_frames(cfg, dev, nchan, station.nstand)


def build_graph(cfg, progress=None, parts=None):
    """Blocks for ``cfg`` inside a new Pipeline (not yet run), built stage by stage: source,
    calibration, imaging, search, outputs.

    parts : None (what ``device`` and ``imager.split`` say), or the devices of a pixel split to build
        whatever ``device`` says: GPU indices, or None for a part on the CPU (the tests run a split of
        two CPU parts, which must give what one graph gives)."""
    from ..blocks import bfp
    from .config import resolved_split

    if cfg["imager"]["kind"] != "dft" and cfg["calibration"].get("pattern") not in (None, "none"):
        raise ValueError(f"calibration.pattern: the {cfg['imager']['kind']} imager cannot fold an antenna pattern "
                         f"({cfg['calibration']['pattern']!r}); set calibration.pattern: none or use imager.kind: dft")
    dev, devs = _device(cfg) if parts is None else ("gpu" if parts[0] is not None else "cpu", None)
    split = list(parts) if parts is not None else list(devs) if dev == "gpus" and resolved_split(cfg) == "pixels" \
        else None
    if split is not None:
        _check_pixel_split(cfg, split)
        dev = "gpu" if split[0] is not None else "cpu"    # each part is a one-device pipeline
    # several GPUs: pinned host rings ('cuda_host'), from which each GPU pulls its channels asynchronously
    space = {"gpu": "cuda", "gpus": "cuda_host"}.get(dev, "system")
    if dev == "gpus":
        if cfg["imager"]["kind"] != "dft":
            raise ValueError(f"device {cfg['device']!r}: only the dft imager shards channels over several GPUs")
        for key in ("gains_table", "solve"):
            if cfg["calibration"].get(key):
                raise ValueError(f"device {cfg['device']!r}: calibration.{key} (time-variable gains) needs "
                                 "CalFoldBlock, which runs on one device; use a single GPU")
    src_cfg, im = cfg["source"], cfg["imager"]
    fmt, info, station, gulp = _input(cfg, dev)
    if src_cfg["gulp_nframe"] == "auto":
        log.info("gulp: %d frames (source.gulp_nframe: auto)", gulp)
    if dev == "gpus" and gulp % int(im["accumulate_frames"]):
        raise ValueError(f"device {cfg['device']!r}: source.gulp_nframe ({gulp}) must "
                         f"be a multiple of imager.accumulate_frames ({im['accumulate_frames']}) "
                         "when the channels are sharded over several GPUs")
    outdir = cfg["output"]["dir"]
    # one GPU: every block's thread uses it (a device chosen here would hold in this thread only)
    scope = bfp.block_scope(gpu=devs) if dev == "gpu" and split is None else contextlib.nullcontext()
    cal = cfg["calibration"]
    pattern = None if cal.get("pattern") in (None, "none") else cal["pattern"]
    pixels = _pixels(cfg, station)
    with bfp.Pipeline() as p, scope:
        if split is not None:
            if cfg.get("watch"):
                raise ValueError("watch: the watchlist runs beside one imager; imager.split: pixels splits it "
                                 "over several GPUs (use imager.split: channels, one GPU, or watch: null)")
            if cfg["output"].get("oims"):
                raise ValueError("output.oims: the OIMS imager runs beside one imager; imager.split: pixels "
                                 "splits it over several GPUs (use one GPU, or output.oims: null)")
            return _build_pixel_split(cfg, p, split, station, gulp, fmt, info, pixels, pattern, progress)
        source, feed, nframe_total, block = _source_stage(cfg, dev, fmt, info, station, gulp, space, progress)
        feed, weights = _flagging_stage(cfg, feed)
        solver, table = _solver_stage(cfg, feed, outdir)
        gains = table if table is not None else _static_gains(cfg)     # what CalFoldBlock applies
        calfold = _calibration_stage(cfg, dev, feed, pattern, gains)
        riders = _watch_riders(cfg, dev, pixels, station)
        imager = _imaging_stage(cfg, dev, devs, calfold, pixels, station, pattern, table, weights, watch=riders)
        search = _search_stage(cfg, imager, outdir, weights if getattr(imager, "flag_weights", None) else None,
                               gains=gains)
        writer, cube, band = _output_stage(cfg, imager, pixels, block)
        watch, snippets = _watch_stage(cfg, dev, calfold, station, pattern, table, band or imager, search,
                                       rides=imager if riders is not None else None)
        oims = _oims_stage(cfg, dev, calfold, station, pattern, table)
    return Graph(p, source, calfold, imager, writer, nframe_total, station, outdir, search, cube, solver, watch,
                 snippets, oims=oims)


def _beside_kwargs(cfg, dev, products, pattern, table):
    """DFTImagerBlock keywords for an imager beside the main one on the same voltages (the watchlist's,
    OIMS's): its products, and the calibration folded in as the main imager folds it."""
    im, cal = cfg["imager"], cfg["calibration"]
    kw = dict(products=products, remove_autocorr=im["remove_autocorr"])
    if folds_calibration(cfg, dev):
        kw.update(cable=bool(cal["cable"]), pattern=pattern or False)
        if table is not None:
            kw.update(gains=table)
    return kw


def _oims_stage(cfg, dev, calfold, station, pattern, table=None):
    """``output.oims``: a DFTImagerBlock on Orville's grid (:func:`~..blocks.oims_writer.oims_pixels`) at the
    OIMS cadence, beside the main imager on the same voltages (the calibration folded in as the imager
    folds it), and the OimsWriterBlock writing its images into hourly OIMS files; or None."""
    oc = cfg["output"].get("oims")
    if not oc:
        return None
    if dev == "gpus":
        raise ValueError(f"output.oims: the OIMS imager runs on one device; device {cfg['device']!r} shards the "
                         "channels over several GPUs (use one GPU, or output.oims: null)")
    from ..blocks import DFTImagerBlock
    from ..blocks.oims_writer import OimsWriterBlock, oims_pixels
    im = cfg["imager"]
    width = float(channel_width_hz(cfg))
    acc = max(1, int(round(float(oc["seconds"]) * width)))
    lm, _ = oims_pixels(oc["ngrid"])
    common = _beside_kwargs(cfg, dev, oc["products"], pattern, table)
    sub = {**cfg, "imager": {**im, "accumulate_frames": acc, "products": list(oc["products"])}}
    plan = imaging_plan(sub, len(lm), int((~station.flags).any(axis=1).sum()),
                        len(channel_freqs(cfg)) if cfg["source"]["kind"] == "simulated" else 1, dev)
    imager = DFTImagerBlock(calfold, lm, acc, plan=plan, **common)
    log.info("output.oims: %d x %d grid (%d pixels above the horizon), %s, %.3g s integrations -> %s",
             oc["ngrid"], oc["ngrid"], len(lm), "/".join(oc["products"]), acc / width, cfg["output"]["dir"])
    return OimsWriterBlock(imager, cfg["output"]["dir"], oc["ngrid"], station=station.name,
                           lwatv=oc["lwatv"], lwatv_mhz=oc["lwatv_mhz"])


def _source_stage(cfg, dev, fmt, info, station, gulp, space, progress):
    """(source block, the block the rest reads, frames in all or None, channel block or None): a capture
    file or the simulated sky (:func:`_recorded_source`), or a live UDP stream (Bifrost's C capture, with
    its copy to the GPU, or the Python receiver)."""
    src_cfg, im = cfg["source"], cfg["imager"]
    feed = None   # a block between the source and the rest (Bifrost's copy of a capture to the GPU)
    if fmt is not None or src_cfg["kind"] != "udp":
        source, nframe_total, block = _recorded_source(cfg, fmt, info, station, gulp, space, progress)
        return source, source, nframe_total, block
    from ..blocks.udp_source import UDPSourceBlock
    if dev == "gpu" and im["kind"] == "dft":
        warm_live_imager(cfg, station)
    from ..blocks.bifrost_capture import BifrostCaptureBlock, bifrost_capture_available
    from ..io.udp import packet_format
    ok, why = bifrost_capture_available(src_cfg["format"])
    if src_cfg["engine"] == "bifrost" and not ok:
        raise ValueError(f"source.engine: bifrost: {why}; use engine: auto or python")
    if ok and src_cfg["engine"] != "python":
        log.info("live capture: Bifrost's C packet capture (%s)", src_cfg["format"])
        # the C capture writes host memory: pinned for a GPU, whose copy Bifrost's own block makes
        source = BifrostCaptureBlock(src_cfg["address"], src_cfg["port"], gulp, src_cfg["format"], station,
                                     sync_time=src_cfg["sync_time"], idle_timeout_s=src_cfg["idle_timeout_s"],
                                     sequences=src_cfg["sequences"], core=src_cfg["core"],
                                     rcvbuf_bytes=int(src_cfg["rcvbuf_mb"] * 2**20),
                                     space="cuda_host" if space == "cuda" else space)
        if space == "cuda":
            from bifrost.blocks import copy as bifrost_copy
            feed = bifrost_copy(source, space="cuda")
    else:
        log.info("live capture: the Python receiver (%s)", why if src_cfg["engine"] == "auto" else
                 "source.engine: python")
        if src_cfg["core"] is not None:
            log.warning("source.core %d is for Bifrost's capture thread; the Python receiver ignores it",
                        src_cfg["core"])
        fmt = packet_format(src_cfg["format"], **({"sync_time": src_cfg["sync_time"]}
                                                  if src_cfg["format"] == "chips" else {}))
        source = UDPSourceBlock(src_cfg["address"], src_cfg["port"], gulp, fmt=fmt, station=station,
                                buffer_s=src_cfg["buffer_s"], idle_timeout_s=src_cfg["idle_timeout_s"],
                                start_timeout_s=src_cfg["start_timeout_s"],
                                rcvbuf_bytes=int(src_cfg["rcvbuf_mb"] * 2**20),
                                sequences=src_cfg["sequences"], progress=progress, space=space)
    return source, source if feed is None else feed, None, None


def flagging_enabled(cfg) -> bool:
    """Whether ``flagging`` runs: ``on``/``off`` as set; ``auto`` for capture files and live streams (the
    real sky's interference), not for the simulated sky, which has none."""
    fl = cfg.get("flagging") or {}
    if fl.get("enabled", "auto") != "auto":
        return fl["enabled"] == "on"
    return cfg["source"].get("kind") != "simulated"


def _flagging_stage(cfg, feed, imaged=True):
    """(RFIFlagBlock on ``feed``, its FlagWeights for the imager) where :func:`flagging_enabled`, else
    (``feed``, None): every later reader (the imager, the search, the gain solver) sees the flagged
    stand-samples as zeros."""
    if not flagging_enabled(cfg):
        return feed, None
    from pathlib import Path

    from ..blocks.rfi_flag import FlagWeights, RFIFlagBlock
    from ..imaging.rfi import parse_bad_freq_list
    fl = cfg["flagging"]
    ranges = [((r[0] - 0.1) * 1e6, (r[0] + 0.1) * 1e6) if len(r) == 1 else (r[0] * 1e6, r[1] * 1e6)
              for r in fl["bad_freq_mhz"]]
    if fl.get("bad_freq_file"):
        ranges += parse_bad_freq_list(Path(fl["bad_freq_file"]))
    weights = FlagWeights(cfg["imager"]["accumulate_frames"], track_empty=bool(cfg["imager"].get("search"))) \
        if cfg["imager"]["kind"] == "dft" and imaged else None
    outdir = cfg["output"]["dir"]
    report = None if outdir is None else \
        (lambda fb: fb.write_report(outdir, cfg["output"]["prefix"], f"{cfg['name']}: interference flags so far"))
    return RFIFlagBlock(feed, far=fl["far"], block_frames=fl["block_frames"], impulse_frames=fl["impulse_frames"],
                        impulse_sigma=fl["impulse_sigma"], bad_freq_ranges=ranges, weights=weights, report=report,
                        report_every_s=fl["report_s"]), weights


def _flag_report(cfg, fb, outdir, summary):
    """The flagger's counts for the run's summary and log, and its table and waterfall in ``outdir``."""
    fs = fb.summary()
    if fs["stand_samples_seen"] and fs["fraction_flagged"] >= 1.0:
        log.warning("interference flagging: every stand-sample was flagged: the run imaged nothing")
    log.info("interference flagging: %.3f%% of %d stand-samples flagged (%s)", 100 * fs["fraction_flagged"],
             fs["stand_samples_seen"], ", ".join(f"{r} {100 * v:.3f}%" for r, v in fs["by_reason"].items()))
    if outdir is not None:
        try:
            summary["files"] += fb.write_report(outdir, cfg["output"]["prefix"], f"{cfg['name']}: interference flags")
        except Exception as e:  # noqa: BLE001 - a report must not fail a run that imaged
            log.warning("interference flag report not written: %s", e)
    out = {k: v for k, v in fs.items() if k != "channel_fraction"}
    if fb.weights is not None:      # images rescaled for the imager; channel images the search took as missing
        out.update(fb.weights.stats)
    return out


def solver_settings(sv):
    """:class:`~..imaging.skycal.SolveSettings` from a ``calibration.solve`` mapping."""
    from ..imaging.skycal import SolveSettings
    return SolveSettings(**{k: sv[k] for k in ("min_baseline_lambda", "max_iter", "tol", "deaf_below", "noisy_above",
                                                "residual_above", "smooth_channels", "max_delay_s",
                                                "min_good_fraction")})


def diffuse_mismatch(cfg):
    """A warning (str) when a simulated sky without Galactic emission (``source.diffuse`` null) is
    calibrated with a fitted diffuse term (``calibration.solve.diffuse``), else None: the term then has
    nothing to fit, and at low frequencies its fitted scale pulls one polarisation's gains astray."""
    src, sv = cfg["source"], (cfg["calibration"].get("solve") or {})
    if src.get("kind") == "simulated" and sv.get("diffuse") and not src.get("diffuse"):
        return ("calibration.solve.diffuse is true but the simulated sky (source.diffuse) has no Galactic "
                "emission: the fitted term has nothing to fit and can pull the gains astray (at low "
                "frequencies one polarisation's, with good inputs flagged noisy); set "
                "calibration.solve.diffuse: false, or give the source a diffuse sky")
    return None


def gain_solver_block(cfg, feed, table=None, table_path=None, apply_from="after"):
    """The GainSolverBlock ``calibration.solve`` describes, on ``feed`` (the raw voltages)."""
    from ..blocks.gain_solver import GainSolverBlock
    cal = cfg["calibration"]
    sv = cal.get("solve") or {}
    why = diffuse_mismatch(cfg)
    if why:
        log.warning("%s: %s", cfg["name"], why)
    pattern = sv.get("pattern") or cal.get("pattern")
    return GainSolverBlock(feed, sv["sources"], cadence_s=sv["cadence_s"], integration_s=sv["integration_s"],
                           offset_s=sv["offset_s"],
                           settings=solver_settings(sv), pattern=None if pattern in (None, "none") else pattern,
                           cable=bool(cal["cable"]), min_alt_deg=sv["min_alt_deg"], min_samples=sv["min_samples"],
                           table=table, table_path=table_path, png=sv["png"],
                           reference_stand=None if sv["reference"] == "auto" else sv["reference"],
                           apply_from=apply_from, align_frames=cfg["imager"]["accumulate_frames"],
                           diffuse=sv["diffuse"], saturated_above=sv["saturated_above"],
                           apply_delay_s=sv["apply_delay_s"] if apply_from == "after" else 0.0,
                           solutions_per_file=sv["solutions_per_file"] if apply_from == "after" else None)


def _solver_stage(cfg, feed, outdir):
    """(GainSolverBlock, LiveGainTable) when ``calibration.solve`` asks for live solving, else (None, None):
    the solver reads the raw voltages beside CalFoldBlock and writes its table to ``outdir``."""
    if not cfg["calibration"].get("solve"):
        return None, None
    from pathlib import Path

    from ..blocks.gain_solver import LiveGainTable
    table = LiveGainTable()
    path = None if outdir is None else Path(outdir) / f"{cfg['output']['prefix']}_gains.npz"
    return gain_solver_block(cfg, feed, table, path), table


def _calibration_stage(cfg, dev, feed, pattern, gains=None):
    """The block the imager reads: CalFoldBlock on ``feed`` (gains, cable terms, the pattern applied to the
    voltages; ``gains`` the loaded ``calibration.gains_table`` or the LiveGainTable the solver fills), or
    ``feed`` itself where the imager folds the calibration into its operator (:func:`folds_calibration`)."""
    from ..blocks import CalFoldBlock
    cal = cfg["calibration"]
    # Live packets never wait for the imager, yet the blocks read them *guaranteed*: the capture
    # thread keeps receiving whatever the blocks do, and its bounded queue is the one place
    # where a pipeline that cannot keep up loses data (whole gulps, written as zeros and counted
    # in udp_stats['samples_overflow']; with Bifrost's capture, the kernel's socket buffer). An
    # unguaranteed reader would lose the start of every stream (the reordering window arrives at
    # once, faster than any reader starts) and, inside real Bifrost, meet its frame-alignment
    # assertion on an overrun (see _compat).
    if folds_calibration(cfg, dev):
        return feed
    return CalFoldBlock(feed, cable=bool(cal["cable"]), gains=gains, pattern=pattern)


def _imaging_stage(cfg, dev, devs, calfold, pixels, station, pattern, table=None, flag_weights=None, watch=None):
    """The imager block on ``calfold``: DFTImagerBlock (folding the calibration where no CalFoldBlock
    runs, with the live solutions of ``table`` if there is one; channels sharded over ``devs`` on several
    GPUs; the watch directions ``watch`` imaged beside its grid, :func:`_watch_riders`), or WStackBlock
    for the gridded kinds."""
    from ..blocks import DFTImagerBlock
    im, cal = cfg["imager"], cfg["calibration"]
    common = dict(products=im["products"], remove_autocorr=im["remove_autocorr"])
    if im["kind"] == "dft":
        if folds_calibration(cfg, dev):
            common.update(cable=bool(cal["cable"]), pattern=pattern or False)
            if table is not None:          # live solutions, folded into the operator as they come
                common.update(gains=table)
        if dev == "gpus":
            common.update(gpus=devs)
        elif flag_weights is not None:
            common.update(flag_weights=flag_weights)
        if watch is not None:
            common.update(watch=watch)
        return DFTImagerBlock(calfold, pixels, im["accumulate_frames"],
                              plan=imager_plan_for(cfg, pixels, station, dev), **common)
    from ..blocks.wstack import WStackBlock
    return WStackBlock(calfold, pixels, im["accumulate_frames"], moff=(im["kind"] == "moff"),
                       plan=imager_plan_for(cfg, pixels, station, dev), **common)


def _watch_riders(cfg, dev, pixels, station):
    """The watchlist's :class:`~..blocks.watch.WatchPixels` when its directions ride in the main imager
    (``DFTImagerBlock(watch=)``), else None. They ride where the main imager is one device's dft imager of
    a grid making the products the watchlist asks: their rows then fill the grid operator's last row tile
    (or add one), so the GPU images them with the grid's voltages already laid out, where an imager of
    their own reads and lays out every voltage again (docs/benchmarks/bench_cost.md). Elsewhere a watch
    imager of their own images them (:func:`_watch_stage`)."""
    wc = cfg.get("watch")
    im = cfg["imager"]
    if not wc or dev not in ("cpu", "gpu") or im["kind"] != "dft" or not isinstance(pixels, LMGrid):
        return None
    if list(resolve_products(2, wc["products"])) != list(resolve_products(2, im["products"])):
        return None
    from ..blocks.watch import WatchPixels
    return WatchPixels(wc["targets"], station.location)


def _watch_stage(cfg, dev, calfold, station, pattern, table=None, imager=None, search=None, rides=None):
    """The watchlist (``watch:``), or (None, None): (the WatchWriterBlock writing
    ``<output.dir>/<prefix>_watch.h5`` from the main imager's watch ring when the directions ride there
    (``rides``: that DFTImagerBlock, :func:`_watch_riders`), else from a DFTImagerBlock of their own tracking
    the targets' directions on the voltages the imager reads, the calibration folded in as the imager
    folds it; the SnippetBlock on
    ``imager`` -- the imager's images, or the band mean of each that the outputs already make, which
    spares the snippets a pass over every channel's images -- that saves what the search's candidates,
    the light curves and trigger files ask)
    (:mod:`bf_epic_blocks.blocks.watch`, :mod:`bf_epic_blocks.blocks.snippets`)."""
    wc = cfg.get("watch")
    if not wc:
        return None, None
    if dev == "gpus":
        raise ValueError(f"watch: the watchlist runs on one device; device {cfg['device']!r} shards the channels "
                         "over several GPUs (use one GPU, or watch: null)")
    from ..blocks import DFTImagerBlock
    from ..blocks.watch import WatchPixels, WatchWriterBlock
    im = cfg["imager"]
    main_imager = imager
    if rides is not None:
        pixels, wring = rides.watch, rides.watch_ring
        ndir = sum(t.ndir for t in pixels.targets)
        how = "imaged beside the main imager's grid"
    else:
        pixels = WatchPixels(wc["targets"], station.location)
        common = _beside_kwargs(cfg, dev, wc["products"], pattern, table)
        ndir = sum(t.ndir for t in pixels.targets)
        plan = imaging_plan(cfg, ndir, int((~station.flags).any(axis=1).sum()),
                            len(channel_freqs(cfg)) if cfg["source"]["kind"] == "simulated" else 1, dev)
        wring = DFTImagerBlock(calfold, pixels, im["accumulate_frames"], plan=plan, **common)
        how = "by a watch imager of their own"
    out = cfg["output"]
    path = Path(out["dir"]) / f"{out['prefix']}_watch.h5"
    log.info("watch: %d targets (%d directions) at every image, %s -> %s", len(pixels.targets), ndir, how, path)
    from ..blocks.snippets import SnippetBlock, TriggerBus
    bus = TriggerBus()
    writer = WatchWriterBlock(wring, path, pixels, png_every_s=wc["png_every_s"], bus=bus,
                              trigger_sigma=wc["trigger_sigma"], ring_s=wc["ring_s"], png_process=dev != "cpu")
    snippets = None
    if main_imager is not None:
        snippets = SnippetBlock(main_imager, out["dir"], out["prefix"], bus, ring_s=wc["ring_s"],
                                after_s=wc["save_after_s"], hold_off_s=wc["hold_off_s"], trigger_dir=wc["trigger_dir"],
                                late_s=_search_latency_s(cfg))
    from ..io.alerts import AlertSender
    station_info = {"station": station.name, "npol": 2}
    if cfg["source"]["kind"] == "simulated":        # what the alerts' VOEvents say of the observation
        freq, width = channel_freqs(cfg), float(cfg["source"]["channels"]["width_hz"])
        station_info.update(freq_mhz=round(float(np.mean(freq)) / 1e6, 6),
                            bandwidth_mhz=round(freq.size * width / 1e6, 6),
                            sampling_time_ms=round(im["accumulate_frames"] * 1e3 / width, 6))
    writer.alerts = AlertSender(wc["webhook"], out["dir"])
    bus.listeners.append(lambda a: writer.alerts.send({**station_info, **a}))
    if search is not None:
        search.on_candidate = lambda row: bus.post(
            row["time_utc"].unix, f"candidate S/N {row['snr']:.1f}",
            {"ra_deg": row["ra_deg"], "dec_deg": row["dec_deg"], "snr": round(row["snr"], 2), "dm": row["dm"],
             "width_ms": round(row["width_ms"], 4), "kind": row["kind"]})
    return writer, snippets


def _search_latency_s(cfg):
    """Seconds after a burst by which the search has reported it, with room to spare: its window, the
    sweep of its largest DM across the band (the simulated source's channels, else the LWA's 10-88 MHz
    as the bound) and 1 s of the pipeline's own lag."""
    sc = cfg["imager"].get("search")
    if not sc:
        return 1.0
    from ..conventions import dispersion_delay_s
    freq = channel_freqs(cfg) if cfg["source"]["kind"] == "simulated" else np.array([10e6, 88e6])
    dm = max([float(d) for d in (sc.get("dms") or [0.0])] + [0.0])
    return float(sc["window_s"]) + float(dispersion_delay_s(dm, freq.min(), freq.max())) + 1.0


def _search_stage(cfg, imager, outdir, flag_weights=None, gains=None):
    """The transient search on the imager's images, if ``imager.search`` asks for one (else None); ``gains``:
    the gain table whose solutions restart its window."""
    return _search_block(cfg, imager, outdir, flag_weights, gains) if cfg["imager"].get("search") else None


def _static_gains(cfg):
    """``calibration.gains_table`` loaded (a GainTable), or None."""
    from ..imaging.calibration import GainTable
    path = cfg["calibration"].get("gains_table")
    return GainTable.load(path) if path else None


def _output_stage(cfg, imager, pixels, block):
    """(image writer or None, cube writer or None, band) on the imager's images, as ``output`` asks;
    band: the block of each image's band mean on the host where the outputs made one, else None."""
    files, band = imager, None
    wants = _outputs_average(cfg["output"])
    if len(wants) > 1 and all(wants):
        # the files and the cube both average the channels: the band mean of each image once (one
        # pass over the images, not one per output), brought to the host, where the integration and
        # the cube's conversion of its 1-channel images are small
        from ..blocks.integrate import ImageIntegratorBlock
        files = band = ImageIntegratorBlock(imager, nimage=1, average_channels=True, space="system")
    return _output_blocks(cfg, files, pixels, block) + (band,)


def imager_plan_for(cfg, pixels, station, dev):
    """:func:`imaging_plan` for ``pixels`` on ``dev`` ('cpu', 'gpu', 'gpus'), logged."""
    im = cfg["imager"]
    npix = pixels.npix if hasattr(pixels, "npix") else im["track"]["size"] ** 2
    plan = imaging_plan(cfg, npix, int((~station.flags).any(axis=1).sum()),
                        len(channel_freqs(cfg)) if cfg["source"]["kind"] == "simulated" else 1, dev)
    log.info("imager plan: %s", plan.describe())
    return plan


def _recorded_source(cfg, fmt, info, station, gulp, space, progress):
    """(source block, frames in all, channel block or None) for a capture file or the simulated sky."""
    from ..blocks.sources import SimSkySourceBlock, TBFSourceBlock, TBXSourceBlock
    src_cfg = cfg["source"]
    if fmt is not None:
        block = channel_block_range(cfg, info)
        cls = TBXSourceBlock if fmt == "tbx" else TBFSourceBlock
        source = cls(src_cfg["path"], gulp, station=station, progress=progress, space=space,
                     channels=block[:2] if block else None, scanned={src_cfg["path"]: info})
        return source, int(info.ntime), block
    from ..sky.corrupt import GainCorruption
    corrupt = src_cfg.get("corrupt")
    source = SimSkySourceBlock(station, channel_freqs(cfg), src_cfg["start"], src_cfg["duration_s"], src_cfg["sources"],
                               gulp, noise_power=src_cfg["noise_power"], seed=src_cfg["seed"],
                               quantize=src_cfg["quantize"], progress=progress, space=space,
                               refresh_s=src_cfg["refresh_s"],
                               transients=[{k: v for k, v in t.items() if v is not None}
                                           for t in src_cfg.get("transients") or []],
                               pattern=None if src_cfg.get("pattern", "none") == "none" else src_cfg["pattern"],
                               diffuse=src_cfg.get("diffuse"),
                               corrupt=None if corrupt is None else GainCorruption.from_config(corrupt,
                                                                                               seed=src_cfg["seed"]))
    return source, source.nframe, None


def _search_settings(sc):
    """The :class:`~..search.SearchSettings` of the YAML's ``imager.search`` section ``sc`` (validated)."""
    from ..search import SearchSettings
    return SearchSettings(threshold=sc["threshold"], window_s=sc["window_s"], dms=sc["dms"], widths=sc["widths"],
                          average_channels=sc["average_channels"], product=sc["product"],
                          dedisperse=sc["dedisperse"], tree_precision=sc["tree_precision"],
                          max_pixels=sc["max_pixels"], sky_fraction=sc["sky_fraction"],
                          sidelobe_factor=sc["sidelobe_factor"])


def _search_block(cfg, images, outdir, flag_weights=None, gains=None):
    """The TransientSearchBlock ``imager.search`` asks for, on ``images``, its candidates written to
    ``outdir`` by a :class:`~..io.candidates.CandidateWriter` (None: not written)."""
    from ..blocks.transient_search import TransientSearchBlock
    from ..io.candidates import CandidateWriter
    sc, out = cfg["imager"]["search"], cfg["output"]
    writer = CandidateWriter(outdir, out["prefix"], sc["table"], sc["png"]) if outdir is not None else None
    return TransientSearchBlock(images, _search_settings(sc), writer=writer, location=None, flag_weights=flag_weights,
                                gains=gains)


def _output_blocks(cfg, images, pixels, block):
    """(image writer or None, cube writer or None) on ``images``, as ``output`` asks."""
    from ..blocks.image_writer import ImageWriterBlock
    out = cfg["output"]
    writer = cube = None
    if out["fits"] or out["png"] or out["table"]:
        files = images
        if out.get("integrate"):
            # longer (band-averaged) images for the files: the imager's own cadence stays for the
            # search and the cube
            from ..blocks.integrate import ImageIntegratorBlock
            it = out["integrate"]
            files = ImageIntegratorBlock(images, seconds=it["seconds"], average_channels=it["average_channels"])
        # on a GPU the files are written by a helper process: astropy's per-image work would hold the
        # interpreter lock the source and imager threads need (ImageWriterBlock's docstring)
        writer = ImageWriterBlock(files, out["dir"], prefix=out["prefix"], fits=out["fits"], png=out["png"],
                                  table=out["table"], location=None,   # the header's station (this table), built in its thread
                                  pixels_fn=pixels if callable(pixels) else None,
                                  run_index=block[2] if block and block[3] > 1 else None,
                                  processes=1 if writes_through_helper(cfg) else 0)
    if out.get("cube"):
        from ..blocks.cube_writer import ImageCubeWriterBlock
        cc = out["cube"]
        cube = ImageCubeWriterBlock(images, out["dir"], prefix=f"{out['prefix']}_cube", dtype=cc["dtype"],
                                    average_channels=cc["average_channels"],
                                    images_per_file=cc["images_per_file"], location=None)
    return writer, cube


def _outputs_average(out):
    """For each output that reads the imager's images (the files, the cube) whether it averages the
    channels: ``output``'s settings."""
    wants = []
    if out["fits"] or out["png"] or out["table"]:
        wants.append(bool(out.get("integrate") and out["integrate"]["average_channels"]))
    if out.get("cube"):
        wants.append(bool(out["cube"]["average_channels"]))
    return wants


def _check_pixel_split(cfg, split):
    """A clear error where a pixel split cannot run (what config validation says for ``split: pixels``)."""
    from .config import pixel_split_problems
    why = pixel_split_problems(cfg) + (["a split needs two or more parts"] if len(split) < 2 else [])
    if why:
        raise ValueError("a pixel split (imager.split: pixels over several GPUs) cannot run here: " + "; ".join(why))


def _build_pixel_split(cfg, p, split, station, gulp, fmt, info, pixels, pattern, progress):
    """The graph of a pixel split: per part (GPU), source -> DFTImagerBlock (its part of the grid, every
    channel) -> TransientSearchBlock, and the band mean of each image to the host; PixelMergeBlock joins
    the parts' images for the files and the cube, :class:`~..blocks.search_parts.SearchParts` their
    candidates once the run is over. Nothing crosses between GPUs: each reads (or simulates) the
    whole source itself."""
    from ..blocks import DFTImagerBlock, bfp
    from ..blocks.integrate import ImageIntegratorBlock
    from ..blocks.pixel_merge import PixelMergeBlock
    from ..blocks.search_parts import SearchParts
    im, out, cal = cfg["imager"], cfg["output"], cfg["calibration"]
    n = len(split)
    dev = "gpu" if split[0] is not None else "cpu"
    # what the files and the cube are made of: the band mean of each image where every one of them
    # averages the channels (a whole band's images are far too many bytes to bring to the host)
    wants = _outputs_average(out)
    average = bool(wants) and all(wants)
    parts = [pixels.part(k, n) for k in range(n)]
    plan = imager_plan_for(cfg, parts[0], station, dev)       # the parts differ by a pixel at most: one plan
    first, searches, hosts = None, [], []
    nframe_total = block = None
    for k, (d, part) in enumerate(zip(split, parts)):
        with bfp.block_scope(gpu=d) if d is not None else contextlib.nullcontext():
            source, nframe_total, block = _recorded_source(cfg, fmt, info, station, gulp,
                                                           "cuda" if d is not None else "system",
                                                           progress if k == 0 else None)
            imager = DFTImagerBlock(source, part, im["accumulate_frames"], products=im["products"],
                                    remove_autocorr=im["remove_autocorr"], cable=bool(cal["cable"]),
                                    pattern=pattern or False, plan=plan)
            if im.get("search"):
                searches.append(_search_block(cfg, imager, None))
            if wants:
                hosts.append(ImageIntegratorBlock(imager, nimage=1, average_channels=average, space="system"))
        first = first or (source, imager)
    log.info("pixel split: %d parts (%s), %s pixels each, every channel imaged and searched where it is made",
             n, ", ".join("cpu" if d is None else f"gpu:{d}" for d in split), "/".join(str(q.npix) for q in parts))
    search = SearchParts(searches, out["dir"], out["prefix"], im["search"]["table"], im["search"]["png"]) \
        if searches else None
    merged = PixelMergeBlock(hosts) if hosts else None
    writer, cube = _output_blocks(cfg, merged, pixels, block) if merged is not None else (None, None)
    return Graph(p, first[0], first[0], first[1], writer, nframe_total, station, out["dir"], search, cube)


def block_timing(blocks, t0):
    """{block name: {ngulp, process_s, first_data_s, first_done_s, last_data_s}} from the runtime's ``stats``
    (times in seconds after ``t0``, a ``time.perf_counter()``); blocks without them (real Bifrost
    keeps its own ``perf`` proclog instead) are left out."""
    out = {}
    for b in blocks:
        st = getattr(b, "stats", None)
        if not isinstance(st, dict) or "process_s" not in st:
            continue
        rel = (lambda t: None if t is None else round(t - t0, 4))
        out[b.name] = {"ngulp": int(st["ngulp"]), "process_s": round(float(st["process_s"]), 4),
                       "first_data_s": rel(st["first_data_at"]), "first_done_s": rel(st.get("first_done_at")),
                       "last_data_s": rel(st["last_data_at"])}
    return out


#: seconds without a finished gulp anywhere before ``run`` logs where each block is (:mod:`.watchdog`)
STALL_WARN_S = 60.0
#: seconds between the output budget's sweeps (``output.keep_gb`` / ``keep_days``)
BUDGET_EVERY_S = 30.0
#: seconds a SIGTERM leaves the blocks to finish their images and close their files before they are stopped
STOP_TIMEOUT_S = 30.0


@contextlib.contextmanager
def _stop_on_sigterm(pipeline, timeout_s=STOP_TIMEOUT_S):
    """While the pipeline runs in the main thread, SIGTERM (systemd's stop) ends the data gracefully
    (``Pipeline.drain``, where the runtime has it): the blocks finish the images in their rings and close
    their files, and ``run`` returns as at the end of the data. A second SIGTERM, or ``timeout_s`` without
    an end, stops the blocks at once (KeyboardInterrupt). Yields a dict whose ``signal`` is set once one
    came."""
    import signal
    import threading
    state = {"signal": None}
    if threading.current_thread() is not threading.main_thread() or not hasattr(pipeline, "drain"):
        yield state
        return

    lock = threading.Lock()     # the run's end against the drain's timer; never taken by the handler
    state["ended"] = False

    def drain():
        log.warning("SIGTERM: ending the data; the blocks finish their images and close their files (at most "
                    "%g s)", timeout_s)
        pipeline.drain()
        import _thread
        with lock:
            if not state["ended"]:
                state["timer"] = threading.Timer(timeout_s, _thread.interrupt_main)
                state["timer"].daemon = True
                state["timer"].start()

    def stop(signum, frame):
        # The handler runs in the main thread between two bytecodes, possibly inside a lock the run loop
        # holds (its wake-up event's); draining takes such locks, so another thread does it.
        if state["signal"] is not None:
            raise KeyboardInterrupt
        state["signal"] = "SIGTERM"
        threading.Thread(target=drain, name="sigterm-drain", daemon=True).start()

    old = signal.signal(signal.SIGTERM, stop)
    try:
        yield state
    finally:
        signal.signal(signal.SIGTERM, old)
        with lock:
            state["ended"] = True
            if "timer" in state:
                state["timer"].cancel()


def _start_service(cfg, g):
    """The HTTP service (``service:``, :mod:`bf_epic_blocks.service`) on the built graph ``g``, started."""
    import os

    from ..service.monitor import Limits, Monitor
    from ..service.server import Service
    sc, src = cfg["service"], cfg["source"]
    dt = None if src["kind"] == "udp" else 1.0 / channel_width_hz(cfg)   # a live stream's comes with its packets
    solve = cfg["calibration"].get("solve")
    return Service(Monitor(g, cfg, dt, lost_window_s=sc["lost_window_s"]), sc["listen"], allow_remote=sc["allow_remote"],
                   token=sc["token"] or os.environ.get(sc["token_env"]) or None,
                   bus=getattr(g.snippets, "bus", None),
                   limits=Limits(no_data_s=sc["no_data_s"], min_free_gb=sc["min_free_gb"],
                                 behind=sc["behind"], lost_window_s=sc["lost_window_s"]),
                   cadence_s=solve["cadence_s"] if solve else None, name=cfg["name"]).start()


def seed_kernels(cfg):
    """On a GPU, the kernel store's compiled kernels into CuPy's cache (:func:`~bf_epic_blocks.cuda.seed_cupy_cache`),
    logged; returns its counts (None on the CPU)."""
    devices = {str(tc["device"]) for tc in cfg.get("tunings") or [cfg]}
    if devices == {"cpu"}:
        return None
    from ..cuda import seed_cupy_cache
    got = seed_cupy_cache()
    if got["copied"]:
        log.info("kernel store %s: %d compiled kernels put into CuPy's cache %s (%d of them as hard links; %d there "
                 "already)", got["store"], got["copied"], got["cache"], got["linked"], got["present"])
    if got["failed"]:
        log.warning("kernel store %s: %d compiled kernels could not be copied into CuPy's cache %s; they "
                    "compile when first used", got["store"], got["failed"], got["cache"])
    return got


def gpu_devices(cfg) -> list[int]:
    """The GPU indices a (station's) configuration runs on: [] on the CPU."""
    from .config import parse_device, several_gpus
    out = set()
    for tc in cfg.get("tunings") or [cfg]:
        dev = str(tc["device"])
        if several_gpus(dev):
            from ..imaging.multigpu import resolve_devices
            spec = dev.split(":")[1]
            out.update(resolve_devices("all" if spec == "all" else [int(i) for i in spec.split(",")]))
        elif dev != "cpu":
            out.add(parse_device(dev)[1])
    return sorted(out)


def limit_gpu_pools(cfg, cupy=None):
    """``gpu_memory_gb``: CuPy's default memory pool on each GPU the run uses limited to it (logged);
    returns {device: bytes} ({} without a limit or a GPU)."""
    gb = cfg.get("gpu_memory_gb")
    if gb is None:
        return {}
    devs = gpu_devices(cfg)
    if not devs:
        return {}
    if cupy is None:
        import cupy
    size = int(round(float(gb) * 1e9))
    done = {}
    for d in devs:
        with cupy.cuda.Device(d):
            cupy.get_default_memory_pool().set_limit(size=size)
        done[d] = size
    log.info("gpu_memory_gb: CuPy's memory pool limited to %.3g GB on GPU %s", gb, ", ".join(map(str, devs)))
    return done


def run(cfg, show_progress=None, parts=None, service_ready=None):
    """Build and run the pipeline; returns a summary dict (files written, frame counts, timing).
    ``parts``: see :func:`build_graph`. With ``service:``, the HTTP service runs beside it
    (:mod:`bf_epic_blocks.service`; ``service_ready(service)`` is called once it listens). A station of
    several tunings (``tunings:``) runs them together (:func:`run_station`)."""
    compiled = None
    if parts is None:
        seed_kernels(cfg)
        limit_gpu_pools(cfg)
        compiled = watch_compiles(cfg)
    if cfg.get("tunings") and parts is None:
        return _with_compiles(run_station(cfg, show_progress=show_progress, service_ready=service_ready), compiled)
    if cfg.get("service"):
        from ..service.server import check_listen, parse_listen
        check_listen(parse_listen(cfg["service"]["listen"])[0], cfg["service"]["allow_remote"])
    bar = progress_bar(cfg["name"], show_progress)
    t0, t0_unix = time.perf_counter(), time.time()
    if parts is None:
        check_fits(cfg)
    g = build_graph(cfg, progress=None if bar is None else bar.update, parts=parts)
    if bar is not None:
        bar.total = g.nframe_total
        bar.refresh()
    log_graph(cfg, g)
    service = budget = None
    try:
        budget = start_budget(cfg, g)
        if cfg.get("service"):
            service = _start_service(cfg, g)
            if service_ready is not None:
                service_ready(service)
        try:
            stopped = execute(g.pipeline)
        except Exception as e:
            if service is not None:
                service.monitor.failed = str(e)
            raise
        finish_graph(g)
    finally:
        close_graph(g)
        if budget is not None:
            budget.stop()
        if service is not None:
            service.monitor.finished = True
            summary_service = dict(service.stats, url=service.url)
            service.stop()
        if bar is not None:
            bar.close()
    summary = summarise(cfg, g, t0, time.perf_counter() - t0, stopped)
    if budget is not None:
        summary["output_budget"] = dict(budget.stats)
    if service is not None:
        summary["service"] = summary_service
    summary["started_unix_s"] = t0_unix      # the blocks' times are seconds after this (time.time())
    return _with_compiles(summary, compiled)


def watch_compiles(cfg):
    """On a GPU with ``$BF_EPIC_LOG_COMPILES`` set: every kernel CuPy compiles from now on is logged and listed in
    the run's summary (:func:`~bf_epic_blocks.cuda.record_compiles`). Returns ``(the list, its length now)``, or
    None (not asked for, a CPU run, or a CuPy whose compiler cannot be watched: logged)."""
    import os
    from ..cuda import COMPILE_LOG_ENV, record_compiles
    if os.environ.get(COMPILE_LOG_ENV, "") in ("", "0"):
        return None
    if {str(tc["device"]) for tc in cfg.get("tunings") or [cfg]} == {"cpu"}:
        return None
    rows = record_compiles(log)
    if rows is None:
        log.warning("%s: this CuPy's compiler cannot be watched; kernels compiled while running are not listed",
                    COMPILE_LOG_ENV)
        return None
    return rows, len(rows)


def _with_compiles(summary, compiled):
    """The summary with ``kernels_compiled_while_running`` (this run's part of the list) where it was asked for."""
    if compiled is not None and isinstance(summary, dict):
        rows, start = compiled
        summary["kernels_compiled_while_running"] = [dict(r) for r in rows[start:]]
        if len(rows) > start:
            log.info("%d kernels compiled while running (not in the kernel store): %s", len(rows) - start,
                     ", ".join(sorted({r["kernel"] for r in rows[start:]})))
    return summary


def run_station(cfg, show_progress=None, service_ready=None):
    """Run every tuning of ``cfg`` (a checked station configuration: ``cfg["tunings"]`` their whole
    pipelines) together; returns the station's summary: ``tunings`` (each tuning's own summary, as
    :func:`run` returns it), the events, and totals over the tunings (:mod:`.station`). With ``service:``,
    each tuning is served at its own ``service.listen`` (``service_ready(service)`` for each)."""
    from .station import Together, tuning_search, write_events
    tunings = cfg["tunings"]
    if cfg.get("service"):
        from ..service.server import check_listen, parse_listen
        for tc in tunings:
            check_listen(parse_listen(tc["service"]["listen"])[0], tc["service"]["allow_remote"])
    names = [tc["name"][len(cfg["name"]) + 1:] for tc in tunings]
    bar = progress_bar(cfg["name"], show_progress)
    t0, t0_unix = time.perf_counter(), time.time()
    check_station_fits(cfg)
    graphs = []
    for tc in tunings:
        graphs.append(build_graph(tc, progress=None if bar is None else bar.update))
        log_graph(tc, graphs[-1])
    if bar is not None:
        bar.total = sum(g.nframe_total or 0 for g in graphs) or None
        bar.refresh()
    searched = [k for k, g in enumerate(graphs) if g.search is not None]
    live = alerts = None
    if len(searched) > 1:
        from ..search.coincidence import StationEvents
        if cfg.get("watch"):            # the watchlist's alerts out: the station's events too
            from ..io.alerts import AlertSender
            alerts = AlertSender(cfg["watch"]["webhook"], cfg["output"]["dir"])
        live = StationEvents([tuning_search(names[k], tunings[k], graphs[k]) for k in searched],
                             refresh=lambda j: tuning_search(names[searched[j]], tunings[searched[j]], graphs[searched[j]]),
                             on_event=None if alerts is None else (
                                 lambda a: alerts.send({"station": cfg["station"].get("name") or "", **a})))
        for j, k in enumerate(searched):
            graphs[k].search.on_candidate = live.listener(j, graphs[k].search.on_candidate)
    log.info("station %s: %d tunings (%s) together", cfg["name"], len(tunings), ", ".join(names))
    budgets, services, served = [None] * len(graphs), [None] * len(graphs), [None] * len(graphs)
    try:
        for k, (tc, g) in enumerate(zip(tunings, graphs)):
            budgets[k] = start_budget(tc, g)
            if tc.get("service"):
                services[k] = _start_service(tc, g)
                if service_ready is not None:
                    service_ready(services[k])
        try:
            stopped = execute(Together([g.pipeline for g in graphs]))
        except Exception as e:
            for sv in services:
                if sv is not None:
                    sv.monitor.failed = str(e)
            raise
        for g in graphs:
            finish_graph(g)
    finally:
        for g in graphs:
            close_graph(g)
        for b in budgets:
            if b is not None:
                b.stop()
        for k, sv in enumerate(services):
            if sv is not None:
                sv.monitor.finished = True
                served[k] = dict(sv.stats, url=sv.url)
                sv.stop()
        if alerts is not None:
            alerts.close()
        if bar is not None:
            bar.close()
    wall = time.perf_counter() - t0
    per = {}
    for name, tc, g, b, sv in zip(names, tunings, graphs, budgets, served):
        per[name] = summarise(tc, g, t0, wall, stopped)
        if b is not None:
            per[name]["output_budget"] = dict(b.stats)
        if sv is not None:
            per[name]["service"] = sv
    summary = {"name": cfg["name"], "outdir": cfg["output"]["dir"], "wall_s": wall, "started_unix_s": t0_unix,
               "stopped_by": stopped["signal"], "tunings": per,
               "files": [f for s in per.values() for f in s["files"]]}
    for k in ("frames_read", "frames_imaged", "frames_skipped", "frames_dropped_partial", "images", "files_written"):
        summary[k] = sum(int(s[k]) for s in per.values())
    if len(searched) > 1:
        path, counts = write_events(cfg, [tuning_search(names[k], tunings[k], graphs[k]) for k in searched],
                                    [graphs[k].search for k in searched])
        summary["files"].append(str(path))
        summary["files_written"] += 1
        summary["events"] = dict(counts, joined_live=live.joined)
        if alerts is not None:
            summary["events"]["alerts"] = dict(alerts.stats)
            summary["files"] += alerts.written
            summary["files_written"] += len(alerts.written)
        log.info("station %s: %d events, %d seen by more than one tuning (%s)", cfg["name"],
                 summary["events"]["events"], summary["events"]["coincident"], path)
    return summary


def progress_bar(name, show_progress):
    """A tqdm bar of frames (``show_progress`` None: when stderr is a terminal), or None."""
    if show_progress is None:
        show_progress = sys.stderr.isatty()
    if not show_progress:
        return None
    from tqdm import tqdm
    return tqdm(total=None, unit="frame", desc=name, unit_scale=True)


def log_graph(cfg, g):
    log.info("running %s: %s source -> %s%s%s imager -> %s", cfg["name"], cfg["source"]["kind"],
             "interference flagging -> " if flagging_enabled(cfg) else "",
             "" if type(g.calfold).__name__ != "CalFoldBlock" else "calfold -> ", cfg["imager"]["kind"], g.outdir)


def start_budget(cfg, g):
    """The output budget's sweeper of ``g.outdir`` (``output.keep_gb`` / ``keep_days``), started; or None."""
    out = cfg["output"]
    if out.get("keep_gb") is None and out.get("keep_days") is None:
        return None
    from ..service.budget import OutputBudget
    g.budget = OutputBudget(g.outdir, out.get("keep_gb"), out.get("keep_days"), every_s=BUDGET_EVERY_S).start()
    return g.budget


def execute(pipeline):
    """Run a built pipeline (anything with ``blocks`` and ``run()``) under the stall watchdog and, in the
    main thread, the SIGTERM handler; returns the handler's state (``signal`` set when one came)."""
    from .watchdog import StallWatchdog
    with StallWatchdog(pipeline.blocks, STALL_WARN_S), _stop_on_sigterm(pipeline) as stopped:
        pipeline.run()
    return stopped


def finish_graph(g):
    """What a graph's sinks do once its pipeline has ended without error."""
    if hasattr(g.search, "finish"):
        g.search.finish()       # a pixel split's parts' candidates, one table
    if g.snippets is not None:
        g.snippets.finish()     # the search's last candidates, posted after the snippet block's last images
    if g.writer is not None:
        g.writer.flush()        # files its helper process still writes


def close_graph(g):
    """Close a graph's writers, however its pipeline ended."""
    if g.writer is not None:
        g.writer.close()
    if g.watch is not None:
        g.watch.close()         # the PNGs its helper process still draws


def summarise(cfg, g, t0, wall, stopped):
    """The summary of a graph that has run (``t0``: the run's ``time.perf_counter()`` at its start), logged."""
    src_stats = getattr(g.source, "tbf_stats", None) or getattr(g.source, "udp_stats", None) or {}
    img = getattr(g.imager, "img_stats", {})
    # a source stopped early (SIGTERM) wrote fewer than its total: the runtime's count where there is one
    rt = getattr(g.source, "stats", None)
    written = rt.get("nframe_written") if isinstance(rt, dict) else None
    frames_read = src_stats.get("samples", written if written is not None else g.nframe_total)
    skipped = sum(int(getattr(b, "stats", {}).get("nframe_skipped", 0) or 0)
                  for b in (g.calfold, g.imager, *g.sinks) if isinstance(getattr(b, "stats", None), dict))
    summary = {
        "name": cfg["name"], "outdir": g.outdir, "files": [f for b in g.sinks for f in b.written], "wall_s": wall,
        "frames_read": int(frames_read or 0), "frames_imaged": int(img.get("frames_imaged", 0)),
        "frames_dropped_partial": int(img.get("frames_dropped_partial", 0)), "frames_skipped": skipped,
        "images": int(img.get("images", 0)), "tbf": src_stats, "calibration": getattr(g.calfold, "cal_stats", {}),
        # how the imager's operator changed: built, solutions folded in place, tracking pixels moved
        "operator": {k: int(img.get(k, 0)) for k in ("operator_builds", "operator_reweights", "operator_moves",
                                                     "solutions_applied")},
    }
    summary["blocks"] = block_timing(g.pipeline.blocks, t0)
    summary["stopped_by"] = stopped["signal"]
    for name, bt in summary["blocks"].items():
        log.debug("block %s: %d gulps, %.3f s in on_data (%.2f ms/gulp), first data at %s s, last at %s s",
                  name, bt["ngulp"], bt["process_s"], 1e3 * bt["process_s"] / max(bt["ngulp"], 1),
                  bt["first_data_s"], bt["last_data_s"])
    if cfg["source"]["kind"] == "udp":
        summary["udp"] = summary.pop("tbf")
    if g.search is not None:
        summary["search"] = dict(g.search.search_stats)
        log.info("transient search: %d images searched, %d crossings, %d candidates",
                 g.search.search_stats["images_searched"], g.search.search_stats["crossings"],
                 g.search.search_stats["candidates"])
    if g.cube is not None:
        summary["cube"] = dict(g.cube.cube_stats)
    flaggers = [b for b in g.pipeline.blocks if type(b).__name__ == "RFIFlagBlock"]
    if flaggers and getattr(flaggers[0], "_lay", None) is not None:
        summary["flagging"] = _flag_report(cfg, flaggers[0], g.outdir, summary)
    if g.solver is not None:
        table = g.solver.table
        summary["solver"] = {**g.solver.solver_stats, "wait_s": table.stats["wait_s"],
                             "wait_timeouts": table.stats["wait_timeouts"]}
        summary["files"] += g.solver.written
        log.info("gain solver: %d solutions, %d failed; %.2f s summing covariances, %.2f s solving; the "
                 "calibration waited %.2f s for it", g.solver.solver_stats["solutions"],
                 g.solver.solver_stats["failures"], g.solver.solver_stats["sum_s"],
                 g.solver.solver_stats["solve_s"], summary["solver"]["wait_s"])
    if g.oims is not None:
        summary["oims"] = {"integrations": g.oims.integrations, "files": list(g.oims.files)}
    if g.watch is not None:
        summary["watch"] = {"images": g.watch.rows, "inactive_rows": g.watch.inactive,
                            "targets": [t.name for t in g.watch.pixels.targets],
                            "light_curve_triggers": g.watch.triggers}
        if g.snippets is not None:
            summary["watch"]["triggers"] = dict(g.snippets.trig_stats)
        summary["watch"]["png_skipped"] = g.watch.png_skipped
        alerts = getattr(g.watch, "alerts", None)
        if alerts is not None:
            alerts.close()
            summary["watch"]["alerts"] = dict(alerts.stats)
            summary["files"] += alerts.written
    # "files" lists a long run's newest (a service's image writer keeps the paths of its last KEEP_PATHS)
    summary["files_written"] = len(summary["files"]) + sum(max(int(getattr(b, "nwritten", 0)) - len(b.written), 0)
                                                           for b in g.sinks)
    log.info("%s: frames read %d, imaged %d, skipped %d, dropped (partial integration) %d; %d images, "
             "%d files in %s (%.1f s)", cfg["name"], summary["frames_read"], summary["frames_imaged"],
             summary["frames_skipped"], summary["frames_dropped_partial"], summary["images"],
             summary["files_written"], g.outdir, wall)
    if src_stats.get("frames_missing"):
        log.warning("%d %s frames were missing and zero-filled", src_stats["frames_missing"],
                    getattr(g.source, "fmt", "TBF").upper())
    return summary


def calibrate(cfg, out_path=None, show_progress=None):
    """``bf-epic calibrate``: the pipeline's source -> GainSolverBlock (``calibration.solve``), no imager.

    Writes the solved table (.npz, :mod:`..io.gaintable`) to ``out_path`` (default
    ``output.dir/<prefix>_gains.npz``) and its PNG beside it; returns a summary dict. Raises ValueError
    when no solution could be made (each failure's reason is in the message)."""
    if cfg.get("tunings"):
        raise ValueError("a station of several tunings is calibrated one tuning at a time: --set tunings=null "
                         "with that tuning's source.channels, or a pipeline of its own")
    from pathlib import Path

    from ..blocks import bfp
    if cfg["source"]["kind"] == "udp":
        raise ValueError("calibrate: a live udp source has no end; solve live with calibration.solve in "
                         "`bf-epic run`, or calibrate a capture file of the stream")
    if not cfg["calibration"].get("solve"):
        raise ValueError("calibrate: the configuration has no calibration.solve section")
    dev, devs = _device(cfg)
    if dev == "gpus":
        import cupy
        dev, devs = "gpu", devs[0]
        cupy.cuda.Device(devs).use()
    space = "cuda" if dev == "gpu" else "system"
    fmt, info, station, gulp = _input(cfg, dev)
    path = Path(out_path) if out_path else Path(cfg["output"]["dir"]) / f"{cfg['output']['prefix']}_gains.npz"
    if path.suffix != ".npz":
        raise ValueError(f"calibrate: the table is an .npz file; got {str(path)!r}")
    bar = progress = None
    if show_progress if show_progress is not None else sys.stderr.isatty():
        from tqdm import tqdm
        bar = tqdm(total=None, unit="frame", desc=f"{cfg['name']} (calibrate)", unit_scale=True)
        progress = bar.update
    t0 = time.perf_counter()
    scope = bfp.block_scope(gpu=devs) if dev == "gpu" else contextlib.nullcontext()
    with bfp.Pipeline() as p, scope:
        source, nframe_total, _ = _recorded_source(cfg, fmt, info, station, gulp, space, progress)
        feed, _ = _flagging_stage(cfg, source, imaged=False)          # solved from the unflagged data only
        solver = gain_solver_block(cfg, feed, None, path, apply_from="start")
    if bar is not None:
        bar.total = nframe_total
    try:
        p.run()
    finally:
        if bar is not None:
            bar.close()
    st = solver.solver_stats
    if solver.last_solution is None:
        raise ValueError("calibrate: no solution: " + "; ".join(st["failure_reasons"] or ["no data"]))
    last = solver.last_solution
    reasons = [str(r) for r in last.reasons.ravel() if r]
    counts = {r: reasons.count(r) for r in sorted(set(reasons))}
    log.info("calibrate: %d solutions (%d failed) in %.1f s -> %s", st["solutions"], st["failures"],
             time.perf_counter() - t0, path)
    return {"table": str(path), "png": str(path)[:-4] + ".png" if solver.png else None,
            "solutions": st["solutions"], "failures": st["failures"], "failure_reasons": st["failure_reasons"],
            "flagged": len(reasons), "flag_counts": counts, "sum_s": st["sum_s"], "solve_s": st["solve_s"],
            "wall_s": time.perf_counter() - t0, "last": last.summary()}


def plan(cfg):
    """What the pipeline would do, without running it: a dict and a printable text (a station's: each
    tuning's, under ``tunings``)."""
    if cfg.get("tunings"):
        plans = {tc["name"][len(cfg["name"]) + 1:]: plan(tc) for tc in cfg["tunings"]}
        per_device = {}
        for tc, (d, _) in zip(cfg["tunings"], plans.values()):
            per_device[tc["device"]] = per_device.get(tc["device"], 0) + sum(d.get("memory_bytes", {}).values())
        lim = cfg.get("gpu_memory_gb")
        lines = [f"station {cfg['name']}: {len(plans)} tunings; memory on {dev}: about {_gib(b)}"
                 + ("" if lim is None or dev == "cpu" else
                    f" (its pool limited to {lim:g} GB by gpu_memory_gb{'' if b <= lim * 1e9 else ': ABOVE IT'})")
                 for dev, b in per_device.items()]
        return ({"name": cfg["name"], "tunings": {k: d for k, (d, _) in plans.items()},
                 "memory_bytes_per_device": per_device},
                "\n\n".join(f"tuning {k} ({cfg['name']}_{k}):\n{text}" for k, (_, text) in plans.items())
                + "\n\n" + "\n".join(lines))
    src, im = cfg["source"], cfg["imager"]
    if src["kind"] == "udp":
        raise ValueError("plan: a udp source learns its channels from the packets; plan a capture file of the "
                         "same stream (source.kind: file) instead")
    fmt = capture_format(src)
    info = _scan(src["path"], fmt=fmt) if fmt is not None else None
    station = load_station_for(cfg, info, per_channel=False)
    if fmt is not None:
        freq, dt = np.asarray(info.freq_hz), 1.0 / info.chan_bw_hz
        block = channel_block_range(cfg, info)
        if block:
            freq = freq[block[0]:block[1]]
        ntotal = int(info.ntime)
    else:
        freq = channel_freqs(cfg)
        dt = 1.0 / src["channels"]["width_hz"]
        ntotal = int(round(src["duration_s"] / dt))
    nchan = len(freq)
    pixels = _pixels(cfg, station)
    if hasattr(pixels, "npix"):
        npix, pix_txt = pixels.npix, f"{pixels.size}x{pixels.size} grid, {pixels.npix} pixels above the horizon kept"
    else:
        npix, pix_txt = im["track"]["size"] ** 2, f"{im['track']['size']}^2 patch tracking {im['track']['source']}"
    flags = station.flags
    nant_pol = int((~flags).sum())
    nstand_any = int((~flags).any(axis=1).sum())
    from ..imaging.products import needs_cross
    prods = resolve_products(2, im["products"])
    nblk = sum([any(p in ("XX", "I", "Q") for p in prods), any(p in ("YY", "I", "Q") for p in prods),
                needs_cross(prods)])
    acc = int(im["accumulate_frames"])
    dev = device_kind(cfg["device"])
    gulp = gulp_frames(cfg, dev, nchan, station.nstand)
    from .config import resolved_split, several_gpus
    several = several_gpus(cfg["device"])
    nparts = _pixel_parts(cfg) if several and resolved_split(cfg) == "pixels" else None
    if nparts:
        # a pixel split: each GPU a whole one-GPU imager and search for its part; the figures are per GPU
        npix = -(-npix // nparts)
        pix_txt += f"; split over {nparts} GPUs: {npix} pixels each (the figures below are per GPU)"
    pick = imaging_plan(cfg, npix, nstand_any, nchan, "gpus" if several and not nparts else dev)
    method, precision = pick.method, pick.precision
    per_image = cost.route_cmacs(acc, nstand_any, npix, 2, nblk)
    per_gulp = {k: v * nchan * gulp / acc for k, v in per_image.items()}
    bytes_ = {k: v * nchan for k, v in
              cost.route_bytes(gulp, nstand_any, npix, 2, 16 if precision == "fp64" else 8).items()}
    input_bytes = gulp * nchan * station.nstand * 2  # ci4: one byte per complex sample
    chosen = method
    if im["kind"] != "dft":
        t_gulp = float("nan")
    else:
        from ..imaging import plan as planner
        rows = [r for r in planner.load_table()["rows"]
                if (r["device"], r["method"], r["precision"]) == (dev, chosen, precision)]
        t_gulp = (per_gulp[chosen] / rows[0]["rate_cmac_s"] if rows
                  else cost.predict_seconds(per_gulp[chosen], dev, chosen))
        rate_src = (f"rates measured for {chosen} x {precision}, bf_epic_blocks/imaging/measured.json" if rows else
                    f"no rate measured for {chosen} x {precision}: the {chosen} route's generic {dev} rate, "
                    "bf_epic_blocks/imaging/cost.py")
    rt = gulp * dt / t_gulp if t_gulp == t_gulp else float("nan")
    d = {"station": station.name, "stands": station.nstand, "stands_used": nstand_any, "antenna_pols_used": nant_pol,
         "flagged_antenna_pols": int(flags.sum()), "pixels": npix, "pixels_text": pix_txt, "nchan": nchan,
         "freq_mhz": [float(freq.min() / 1e6), float(freq.max() / 1e6)], "frames_total": ntotal,
         "gulp_nframe": gulp, "accumulate_frames": acc, "images": ntotal // acc, "products": list(prods),
         "cmac_per_gulp": per_gulp, "bytes_per_gulp": bytes_, "input_bytes_per_gulp": input_bytes, "method": chosen, "imager": im["kind"],
         "device": cfg["device"], "predicted_gulp_s": t_gulp, "gulp_duration_s": gulp * dt, "realtime_factor": rt}
    lines = [
        f"pipeline {cfg['name']}: {src['kind']} source, {im['kind']} imager on {cfg['device']}",
        f"  station {station.name}: {station.nstand} stands, {nstand_any} used, {int(flags.sum())} antenna-pols flagged",
        f"  channels: {nchan} ({d['freq_mhz'][0]:.3f}-{d['freq_mhz'][1]:.3f} MHz); {ntotal} frames "
        f"({ntotal * dt:.3f} s); {ntotal // acc} images of {acc} frames",
        f"  pixels: {pix_txt}",
        f"  products: {', '.join(prods)}",
        f"  per {gulp}-frame gulp (all channels): direct {per_gulp['direct']:.3e} CMAC, "
        f"covariance {per_gulp['covariance']:.3e} CMAC",
        f"  bytes per gulp: input {input_bytes / 2**20:.1f} MiB (ci4); working set direct "
        f"{bytes_['direct'] / 2**20:.1f} MiB, covariance {bytes_['covariance'] / 2**20:.1f} MiB",
        f"  method: {chosen}" + (" (auto: fewer operations)" if im["kind"] == "dft" and im["method"] == "auto"
                                 and im.get("tolerance") is None else "")
        + f", precision {precision}" + (f", gridder epsilon {pick.epsilon:.1e}" if pick.epsilon is not None else ""),
    ]
    d["plan"] = {"imager": pick.imager, **pick.header()}
    if im.get("tolerance") is not None and pick.imager == "dft":
        lines.append(f"  tolerance {im['tolerance']:.1e}: picked {pick.method} route, {pick.precision}, measured "
                     f"error bound {pick.bound:.1e} (bf_epic_blocks/imaging/measured.json)")
    elif im.get("tolerance") is not None:
        lines.append(f"  tolerance {im['tolerance']:.1e}: gridder epsilon {pick.epsilon:.1e} ({pick.method} route, "
                     "bf_epic_blocks/imaging/plan.py)")
    if im.get("tolerance") is not None:
        d["tolerance_pick"] = {"method": pick.method, "precision": pick.precision, "bound": pick.bound}
    if im["kind"] == "dft":
        lines.append(f"  predicted on {dev}: {t_gulp * 1e3:.2f} ms per gulp of {gulp * dt * 1e3:.2f} ms of data "
                     f"-> real-time factor {rt:.2f} for the imaging ({rate_src})")
    else:
        lines.append("  (run time of the w-stacking/MOFF imagers: see tools/bench/bench_wstack.py)")
    # refused before anything large is planned or allocated: the rings, the imager's working set and
    # images first (the search's own planning grows with the channels), then with the search
    # (what is allocated whole: the rings, 4 gulps each, and the search's arrays; the imager's working set
    # above is an upper bound its engines cut into chunks, so it is not counted)
    mem = {"input rings": 4 * input_bytes,
           "image rings": 4 * (gulp // acc + 1) * nchan * len(prods) * npix * 4}
    if im["kind"] == "dft":
        # the operator (held while the pipeline runs, and while a gain solution rebuilds it) and what its
        # construction adds, on one GPU of several: npix is already one GPU's share of a pixel split; a
        # channel split shares the channels
        share = _pixel_parts(cfg) if several and not nparts else 1
        per_gpu = (-(-nchan // share), npix)
        pols_differ = bool((flags[:, 0] != flags[:, 1]).any()) or bool(cfg["calibration"]["cable"])
        ob = cost.operator_bytes(per_gpu[0], per_gpu[1], nstand_any, precision, gpu=dev in ("gpu", "gpus"),
                                 nant_in=station.nstand, pols_differ=pols_differ)
        d["operator_bytes"] = ob
        mem["imager operator"] = sum(ob.values())
        vb = cost.voltage_bytes(per_gpu[0], gulp, station.nstand, precision, gpu=dev in ("gpu", "gpus"))
        if vb:
            mem["imager voltages"] = vb
    _memory_check(cfg, dev, mem)
    if im.get("search"):
        d["search"], text = _plan_search(im["search"], freq, acc * dt, npix, dev,
                                         t_gulp / (gulp * dt) if t_gulp == t_gulp else float("nan"))
        lines += text
        mem["search"] = sum(d["search"]["memory_bytes"].values())
    solve = (cfg.get("calibration") or {}).get("solve")
    if solve:
        # what it holds, and the most it adds while a solution is formed (counted: it must fit then)
        diffuse = bool(solve.get("diffuse", True))
        sb = cost.solver_bytes(nchan, station.nstand, 2, gpu=dev in ("gpu", "gpus"), diffuse=diffuse)
        d["solver_bytes"] = sb
        mem["live gain solver"] = sb["held"] + sb["working"]
        lines.append(f"  live gain solver: holds {_gib(sb['held'])} (the covariance sums, the baseline weights"
                     f"{', the diffuse model' if diffuse else ''}), up to {_gib(sb['working'])} "
                     "more while it sums an integration or forms a solution")
    have, where = _memory_check(cfg, dev, mem)
    d["memory_bytes"], d["memory_available_bytes"] = mem, have
    lines.append(f"  memory: about {_gib(sum(mem.values()))} ("
                 + ", ".join(f"{k} {_gib(v)}" for k, v in mem.items()) + ")"
                 + (f"; {_gib(have)} available on {where}" if have is not None else f"; {where}"))
    if cfg.get("watch"):
        # said, so that a figure close to the device's memory is read as a lower bound
        lines.append("  (not counted above: the watchlist's working arrays)")
    return d, "\n".join(lines)


def check_fits(cfg):
    """Refuse, before anything large is allocated, a configuration whose arrays need more memory than this
    machine (or its GPU) has: :func:`plan`'s estimates against :func:`available_memory` (a ValueError naming
    both). A live UDP source is planned from its packets, so it is not checked here."""
    if cfg["source"]["kind"] != "udp":
        plan(cfg)


def check_station_fits(cfg):
    """:func:`check_fits` for a station, in one planning pass: each tuning refused as :func:`check_fits`
    refuses it, and the tunings on one GPU together where they need more than ``gpu_memory_gb``
    (:func:`plan`'s estimates, each tuning at its most at once): a ValueError naming the device, the need
    and the limit. A live UDP tuning is not planned (as :func:`check_fits`), nor the station's total."""
    if any(tc["source"]["kind"] == "udp" for tc in cfg["tunings"]):
        for tc in cfg["tunings"]:
            check_fits(tc)
        return
    per_device = plan(cfg)[0]["memory_bytes_per_device"]
    gb = cfg.get("gpu_memory_gb")
    for dev, need in per_device.items() if gb is not None else ():
        if dev != "cpu" and need > gb * 1e9:
            raise ValueError(f"{cfg['name']}: the tunings on {dev} need about {_gib(need)} together, more than "
                             f"CuPy's pool may hold (gpu_memory_gb: {gb:g}, {_gib(gb * 1e9)}): raise gpu_memory_gb, "
                             "or put the tunings on GPUs of their own (device: gpu:all)")


def _gib(b):
    return f"{b / 2**30:.1f} GiB" if b >= 2**30 else f"{b / 2**20:.1f} MiB"


def available_memory(dev):
    """(bytes, where) the pipeline's arrays can take: on a GPU ('gpu', 'gpus') the first GPU's free memory
    (CuPy), else the host's available memory (Linux's MemAvailable); (None, why) where it cannot be told."""
    if dev in ("gpu", "gpus"):
        from ..imaging._xp import cupy_or_none
        cp = cupy_or_none()
        try:
            free, _ = cp.cuda.runtime.memGetInfo()
            return int(free), "the GPU"
        except Exception:           # no CuPy, no driver, no GPU: planning for a GPU elsewhere
            return None, "GPU memory not checked here (no GPU)"
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024, "the host"
    except OSError:
        pass
    try:
        import os
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")), "the host"
    except (AttributeError, ValueError, OSError):
        return None, "host memory not checked here"


def _memory_check(cfg, dev, mem):
    """Refuse a configuration whose arrays (``mem``: name -> bytes, estimates from :func:`plan`) need more
    memory than the device has: a clear error naming the need, its parts and what the machine has,
    before anything large is allocated. Returns (available bytes or None, where)."""
    have, where = available_memory(dev)
    gb = cfg.get("gpu_memory_gb")
    if dev in ("gpu", "gpus") and gb is not None and (have is None or gb * 1e9 < have):
        have, where = int(gb * 1e9), f"CuPy's pool (gpu_memory_gb: {gb:g})"
    need = sum(mem.values())
    if have is not None and need > have:
        parts = ", ".join(f"{k} {_gib(v)}" for k, v in sorted(mem.items(), key=lambda kv: -kv[1]) if v)
        raise ValueError(f"{cfg['name']}: this configuration needs about {_gib(need)} of memory ({parts}), and "
                         f"{where} has {_gib(have)} available: lower source.channels / source.gulp_nframe, "
                         "imager.grid.size, or the search's dms and widths")
    return have, where


def _pixel_parts(cfg):
    """How many GPUs a pixel split of ``cfg['device']`` has: the list's length, or for 'gpu:all' the
    GPUs present (2 where none can be counted: planning needs no GPU; the text says so)."""
    spec = cfg["device"].split(":", 1)[1]
    if spec != "all":
        return len(spec.split(","))
    from ..imaging._xp import cupy_or_none
    cp = cupy_or_none()
    try:
        n = cp.cuda.runtime.getDeviceCount() if cp is not None else 0
    except Exception:               # CuPy without a driver
        n = 0
    if n < 2:
        log.info("plan: device gpu:all, but %d GPU(s) can be counted here: planned for 2", n)
        return 2
    return n


def _plan_search(sc, freq, dt_img, npix, dev, imaging_s_per_s):
    """The transient search's part of :func:`plan`: its trials, the memory it holds where it runs
    (:meth:`TransientSearch.memory_bytes`, sized as the block sizes it) and, where rates were measured
    (``search`` in measured.json, tools/bench/bench_search.py), its seconds per second of data and the
    real-time factor of imaging and search together. Returns (dict, lines)."""
    from ..imaging import plan as planner
    from ..search import TransientSearch
    kw, _ = _search_settings(sc).search_keywords(freq, dt_img)
    s = TransientSearch(freq, dt_img, npix, allocate=False, **kw)
    mem = s.memory_bytes(gpu=dev == "gpu")

    def size(b):
        return f"{b / 2**30:.1f} GiB" if b >= 2**30 else f"{b / 2**20:.1f} MiB"
    rows = s.tree_rows
    how = (f"tree dedispersion, {s.nser} trials (every sweep to DM {max(sc['dms']):g}), {rows} tree rows "
           f"stored as {sc['tree_precision']}"
           if rows else f"shifted sums, {s.nser} trial(s)" if s.average else f"each of {s.nser} channels")
    d = {"dedisperse": s.dedisperse, "trials": s.nser, "tree_rows": rows, "memory_bytes": mem,
         "tree_precision": sc["tree_precision"] if rows else None,
         "history_values": s.capacity}
    lines = [f"  transient search: {how}, widths {s.widths}; holds {size(sum(mem.values()))} where it runs "
             f"(history {size(mem['history'])}: {s.capacity} values per trial; "
             + ", ".join(f"{k} {size(mem[k])}" for k in mem if k != "history") + ")"]
    rate = planner.load_table().get("search", {}).get(dev)
    ips = 1.0 / dt_img
    tree_key = "tree_fp16_s_per_row_pixel_image" if sc["tree_precision"] == "fp16" else "tree_s_per_row_pixel_image"
    if rate and rows and tree_key in rate:
        t = (rows * npix * ips * rate[tree_key]
             + s.nser * len(s.widths) * npix * ips * rate["statistics_s_per_trial_width_pixel_image"])
        both = imaging_s_per_s + t
        d.update(predicted_s_per_s=t, imaging_and_search_realtime_factor=1.0 / both if both > 0 else float("nan"))
        lines.append(f"  predicted search on {dev}: {t:.2f} s per second of data; imaging and search together "
                     f"-> real-time factor {1.0 / both:.2f} (the source and writers not counted; search rates "
                     f"measured in {rate['measured']})")
    else:
        lines.append(f"  (search time on {dev}: not measured for this dedispersion; tools/bench/bench_search.py)")
    return d, lines
