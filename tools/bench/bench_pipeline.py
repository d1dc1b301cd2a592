#!/usr/bin/env python
"""Benchmark: case P through the blocks against the same work called directly, and station to FITS.

Case P: 'ci4' gulps of 1,024 frames x 16 channels x 256 stands x 2 pols, explicit complex cable
weights, a 64 x 64 all-sky grid, one image per gulp, Stokes I. Two block graphs (``--graph``):

* ``folded`` -- what ``bf-epic run`` builds on a GPU when calibration is static: source ->
  DFTImagerBlock with the weights folded into its operator, the 4-bit samples imaged as integers
  (exact integer covariance, one CUDA-graph replay per image).
* ``calfold`` -- what it builds with time-variable gains (and on the CPU): source -> CalFoldBlock
  (complex64 voltages out) -> DFTImagerBlock (on the GPU one CUDA-graph replay per image, as in ``folded``).

(a) ``core``: the graph's per-gulp calls made directly on ci4 bytes already on the device (decode,
    calibrate, image, place on the grid); one stream, no rings, no threads.
(b) the same work through the blocks: ``pipe-dev`` (ArraySourceBlock of device-resident ci4 bytes:
    the runtime alone) and ``pipe-host`` (ci4 bytes in pinned host memory, one asynchronous
    host->device copy per gulp overlapped with imaging: the real case).
(c) ``overhead`` = pipeline / core - 1, from the steady-state time per gulp (the interval between
    the sink's images, after the first) and from the whole run (including start-up: threads, the
    operator built in ``on_sequence``, pipeline fill). ``--stages`` adds one more run per block with
    the block's stream synchronised after each ``on_data`` (serialises the pipeline; per-stage cost).
(d) ``fits``: station to FITS -- a pre-generated simulated sky (a point source in noise, ci4 in
    pinned host memory, made on the device so the source is not the bottleneck) -> the first graph
    (``folded`` on the GPU) with one image per second of data = 25,000 frames -> ImageWriterBlock
    (one FITS file per image): the same blocks ``bf-epic run`` builds on a GPU (see
    ``pipeline.runner.folds_calibration``), made here directly, with the array source in place of the
    file/simulated one; no LSL needed. Real-time factor =
    seconds of data / seconds of wall time (LWA-SV: 40 us per sample). Also the source alone into a
    null sink, to show it is not the bottleneck.

    python tools/bench/bench_pipeline.py --device cpu --nchan 1 --ngulp 4 --fits-seconds 2 --json out.json
    python tools/bench/bench_pipeline.py --device gpu --ngulp 200 --json docs/bench/bench_pipeline_gpu_200gulps.json
"""
import argparse
import datetime
import tempfile
import time

import numpy as np

from bf_epic_blocks import imaging
from bf_epic_blocks.blocks import (ArraySinkBlock, ArraySourceBlock, CalFoldBlock, DFTImagerBlock, bfp,
                                   efield_header)
from bf_epic_blocks.blocks import _compat
from bf_epic_blocks.conventions import FS_HZ
from bf_epic_blocks.imaging.calibration import apply_direction_independent
from bf_epic_blocks.imaging.pixels import GridPlacement
from bf_epic_blocks.runtime.dtypes import int8_pairs_decoder, pack_ci4, unpack_complex

from benchlib import array_module, machine, utc_now, write_json
from cases import lwasv_like_layout, reference_image

REALTIME_FPS = 25000.0  # LWA-SV: 40 us per sample
LWASV = {"name": "lwasv-like", "lat_deg": 34.348358, "lon_deg": -106.885783, "elev_m": 1477.0}
C_LIGHT = 299792458.0


class StampSink(ArraySinkBlock):
    """ArraySinkBlock that records when each gulp's images reached the host."""

    def __init__(self, iring, *args, **kwargs):
        super().__init__(iring, *args, **kwargs)
        self.stamps = []

    def on_data(self, ispan):
        super().on_data(ispan)   # copies the images to the host: they are finished here
        self.stamps.append(time.perf_counter())


class NullSink(bfp.SinkBlock):
    """Takes every gulp and does nothing with it (source throughput)."""

    def __init__(self, iring, *args, **kwargs):
        super().__init__(iring, *args, **kwargs)
        self.stamps = []

    def on_sequence(self, iseq):
        pass

    def on_data(self, ispan):
        self.stamps.append(time.perf_counter())


def steady_per_gulp(stamps, gulps_per_stamp=1.0):
    """Seconds per gulp between the first and the last output (pipeline fill excluded)."""
    if len(stamps) < 2:
        return float("nan")
    return (stamps[-1] - stamps[0]) / ((len(stamps) - 1) * gulps_per_stamp)


def timed_stages(blocks, sync):
    """Wrap each block's on_data: wall time per call with the block's stream synchronised."""
    times = {}
    for b in blocks:
        fn = b.on_data
        times[b.name] = []

        def wrapped(*args, _fn=fn, _t=times[b.name]):
            t0 = time.perf_counter()
            r = _fn(*args)
            sync()
            _t.append(time.perf_counter() - t0)
            return r
        b.on_data = wrapped
    return times


def make_case(a, xp):
    xyz, layout = lwasv_like_layout(256)
    freq = 74e6 + 25e3 * np.arange(a.nchan)
    grid = imaging.lm_grid(a.grid)
    rng = np.random.default_rng(0)
    nframe = a.ngulp * a.gulp
    # a few distinct gulps, repeated: a long steady-state window without generating every sample
    nd = min(a.ngulp, a.distinct) * a.gulp
    ints = rng.integers(-8, 8, (nd, a.nchan, 256, 2)) + 1j * rng.integers(-8, 8, (nd, a.nchan, 256, 2))
    packed = np.resize(pack_ci4(ints), (nframe,) + ints.shape[1:])
    w = np.exp(2j * np.pi * rng.random((a.nchan, 256, 2))).astype(np.complex64)
    hdr = efield_header("bench", 0, freq, 40e-6, {"xyz_m": xyz}, dtype="ci4")
    return dict(xyz=xyz, layout=layout, freq=freq, grid=grid, packed=packed, w=w, hdr=hdr, nframe=nframe,
                first=ints[:a.gulp])


def first_image_error(case, images):
    """Max relative error of the first image (Stokes I) against the float64 definition, on every 97th pixel."""
    grid = case["grid"]
    sub = slice(None, None, 97)
    X = case["first"] * case["w"][None].astype(np.complex128)          # calibrated voltages (T, C, A, P)
    ref = reference_image(X, case["xyz"], case["freq"], grid.lm[sub])   # (C, 2, n): XX, YY
    ref_i = ref[:, 0] + ref[:, 1]
    got = images[0, :, 0].reshape(images.shape[1], -1)[:, np.flatnonzero(grid.mask)[sub]]
    return float(np.max(np.abs(got - ref_i)) / np.max(np.abs(ref_i)))


def bench_core(a, case, xp, sync, graph):
    """(a) the blocks' per-gulp calls, made directly; returns seconds per gulp, set-up seconds, method."""
    grid, gulp = case["grid"], a.gulp
    dev = xp.asarray(case["packed"])            # ci4 bytes on the device
    t0 = time.perf_counter()
    op = imaging.DFTOperator(xp.asarray(case["xyz"]), xp.asarray(case["freq"]), xp.asarray(grid.lm), npol=2,
                             weights=xp.ones((1, 256, 2), xp.complex128), precision="fp32")
    acc = op.accumulator(("I",), method="auto", ntime_hint=gulp)
    wd, live = xp.asarray(case["w"]), xp.ones((256, 2), bool)
    place = GridPlacement(np.flatnonzero(grid.mask), grid.size * grid.size, xp)
    out = xp.empty((a.nchan, 1, grid.size * grid.size), xp.float32)
    sync()
    t_setup = time.perf_counter() - t0

    if graph == "folded":   # the weights folded into the operator; 4-bit samples imaged as integers
        op = imaging.DFTOperator(xp.asarray(case["xyz"]), xp.asarray(case["freq"]), xp.asarray(grid.lm), npol=2,
                                 weights=wd, precision="fp32")

    def run():
        sync()
        t = time.perf_counter()
        for g in range(a.ngulp):
            if graph == "folded":   # as the block: ci4 decoded inside the graph, its output placed at once
                img = op.image(dev[g * gulp:(g + 1) * gulp], ("I",), decode=int8_pairs_decoder("ci4"), static_out=True)
            else:   # as CalFoldBlock then the imager: calibrated complex voltages, one graph replay per image
                x = unpack_complex(dev[g * gulp:(g + 1) * gulp], "ci4")
                y = apply_direction_independent(x, wd, live)
                img = op.image(y, ("I",), method=acc.method, static_out=True)
            place(img, out=out)
        sync()
        return (time.perf_counter() - t) / a.ngulp

    run()  # warm-up (kernels, plans, allocator)
    method = acc.method if graph == "calfold" else op.accumulator(("I",), ntime_hint=gulp).method
    return min(run() for _ in range(a.repeat)), t_setup, method


def bench_blocks(a, case, xp, space, source_on_device, graph, stages=False, sync=None):
    """(b) through the blocks; returns (seconds per gulp steady, whole run seconds, images, stage times)."""
    src_data = xp.asarray(case["packed"]) if source_on_device else case["packed"]
    with bfp.Pipeline() as p, bfp.block_scope(buffer_factor=a.buffer_factor):
        src = ArraySourceBlock(src_data, case["hdr"], gulp_nframe=a.gulp, space=space)
        if graph == "folded":   # no CalFoldBlock: the imager folds the weights into its operator
            cal = src
            img = DFTImagerBlock(src, case["grid"], a.gulp, products=("I",), weights=case["w"])
        else:
            cal = CalFoldBlock(src, cable=case["w"])
            img = DFTImagerBlock(cal, case["grid"], a.gulp, products=("I",))
        sink = StampSink(img)
        st = timed_stages(list(dict.fromkeys([src, cal, img])), sync) if stages else None
        t0 = time.perf_counter()
        p.run()
        t_all = time.perf_counter() - t0
    n_img = sink.result(0).shape[0]
    if n_img != a.ngulp:
        raise RuntimeError(f"the pipeline made {n_img} images, expected {a.ngulp}")
    return steady_per_gulp(sink.stamps), t_all, n_img, st, sink.result(0)


# ------------------------------------------------------------------------------------------ (d)
def simulated_ci4(a, xp, nframe, xyz, freq, lm_src, power=4.0, chunk=25000):
    """Pinned host ci4 bytes (nframe, nchan, nant, 2): a point source at ``lm_src`` in unit-variance
    noise, quantised with ~2 units rms; made chunk by chunk on the device."""
    nchan, nant = len(freq), len(xyz)
    out = _compat.pinned_empty((nframe, nchan, nant, 2), np.uint8)
    l, m = lm_src
    n = np.sqrt(1 - l * l - m * m)
    phase = xp.asarray(np.exp(2j * np.pi * freq[:, None] / C_LIGHT *
                              (l * xyz[:, 0] + m * xyz[:, 1] + n * xyz[:, 2])[None, :]).astype(np.complex64))
    if xp is np:
        g = np.random.default_rng(5)
        normal, uniform = g.standard_normal, g.random
    else:
        g = xp.random.RandomState(5)
        normal, uniform = g.standard_normal, g.random_sample
    scale = 2.0 / np.sqrt(1.0 + power)
    for t0 in range(0, nframe, chunk):
        k = min(chunk, nframe - t0)
        shape = (k, nchan, nant, 2)
        noise = normal(shape, dtype=np.float32) + 1j * normal(shape, dtype=np.float32)
        s = np.sqrt(power) * xp.exp(2j * np.pi * uniform((k, nchan, 1, 1), dtype=np.float32))
        x = (noise / np.sqrt(2) + s * phase[None, :, :, None]) * scale
        packed = pack_ci4(x)
        out[t0:t0 + k] = packed.get() if xp is not np else packed
        del noise, s, x, packed
    return out


def bench_fits(a, xp, space, sync, graph):
    """(d) station to FITS through ``graph`` ('folded' or 'calfold'); returns a dict of figures."""
    from astropy.io import fits

    from bf_epic_blocks.blocks.image_writer import ImageWriterBlock
    xyz, layout = lwasv_like_layout(256)
    freq = 74e6 + 25e3 * np.arange(a.nchan)
    nframe = int(round(a.fits_seconds * REALTIME_FPS))
    accumulate = int(round(a.image_seconds * REALTIME_FPS))
    lm_src = (0.3, 0.2)
    t0 = time.perf_counter()
    raw = simulated_ci4(a, xp, nframe, xyz, freq, lm_src)
    t_gen = time.perf_counter() - t0
    tag0 = int(round(datetime.datetime(2024, 6, 1, 10, tzinfo=datetime.timezone.utc).timestamp())) * int(FS_HZ)
    station = {**LWASV, "xyz_m": xyz}
    hdr = efield_header("simulated-case-p", tag0, freq, 40e-6, station, dtype="ci4")
    grid = imaging.lm_grid(a.grid)

    # the source alone (pinned memory -> ring, one asynchronous copy per gulp) into a null sink
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(raw, hdr, gulp_nframe=a.gulp, space=space)
        NullSink(src)
        ts = time.perf_counter()
        p.run()
        t_src = time.perf_counter() - ts
    def fits_run(data, outdir):
        with bfp.Pipeline() as p:
            src = ArraySourceBlock(data, hdr, gulp_nframe=a.gulp, space=space)
            cal = src if graph == "folded" else CalFoldBlock(src, cable=False)
            img = DFTImagerBlock(cal, grid, accumulate, products=("I",))
            writer = ImageWriterBlock(img, outdir, prefix="casep", fits=True, png=False, label_sources=False)
            stamps = []
            on_data = writer.on_data

            def stamped(ispan):
                on_data(ispan)
                stamps.append(time.perf_counter())
            writer.on_data = stamped
            ts = time.perf_counter()
            p.run()
            return time.perf_counter() - ts, writer, img, stamps

    # a first run of two images compiles this route's kernels (CuPy keeps them on disk: a station's
    # later runs start warm) and imports the writers' libraries; the timed run comes after
    t_warm, *_ = fits_run(raw[:2 * accumulate], tempfile.mkdtemp(prefix="bench_fits_warm_"))
    outdir = tempfile.mkdtemp(prefix="bench_fits_")
    t_all, writer, img, stamps = fits_run(raw, outdir)
    files = [f for f in writer.written if f.endswith(".fits")]
    # sanity: the brightest pixel of the first image is the simulated source
    with fits.open(files[0]) as hl:
        im0 = np.nan_to_num(np.asarray(hl[0].data, dtype=np.float64), nan=-np.inf)
    chan_mean = im0.reshape((-1,) + im0.shape[-2:]).mean(axis=0)
    iy, ix = np.unravel_index(np.argmax(chan_mean), chan_mean.shape)
    lm_peak = (float(grid.axis[ix]), float(grid.axis[iy]))
    per_image = steady_per_gulp(stamps)
    return {
        "seconds_of_data": nframe / REALTIME_FPS, "frames": nframe, "gulp": a.gulp, "accumulate": accumulate,
        "images": len(files), "outdir": outdir, "generate_s": t_gen, "wall_s": t_all, "warm_up_s": t_warm,
        "realtime_factor": nframe / REALTIME_FPS / t_all,
        "steady_s_per_image": per_image, "realtime_factor_steady": a.image_seconds / per_image,
        "source_only_s": t_src, "source_only_realtime_factor": nframe / REALTIME_FPS / t_src,
        "source_only_GBps": raw.nbytes / t_src / 1e9, "method": img.engine.method, "graph": graph,
        "peak_lm": lm_peak, "source_lm": lm_src, "cell": grid.cell, "layout": layout,
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=["cpu", "gpu"], default="cpu")
    ap.add_argument("--nchan", type=int, default=16)
    ap.add_argument("--ngulp", type=int, default=40)
    ap.add_argument("--distinct", type=int, default=8, help="distinct gulps of random samples, repeated to --ngulp")
    ap.add_argument("--gulp", type=int, default=1024)
    ap.add_argument("--grid", type=int, default=64)
    ap.add_argument("--graph", choices=["auto", "folded", "calfold", "both"], default="auto",
                    help="block graph(s) to time (see above); auto: both on the GPU (folded first, as bf-epic builds "
                         "it), calfold on the CPU (as bf-epic builds it there)")
    ap.add_argument("--buffer-factor", type=float, default=None,
                    help="ring size in gulps for (b) (default: the runtime's, 3)")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each measurement; the best is kept")
    ap.add_argument("--stages", action="store_true", help="also time each block with its stream synchronised")
    ap.add_argument("--fits-seconds", type=float, default=10.0, help="seconds of data for (d); 0 skips it")
    ap.add_argument("--image-seconds", type=float, default=1.0)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    if 0 < a.fits_seconds < a.image_seconds:
        ap.error(f"--fits-seconds {a.fits_seconds:g} is shorter than one image (--image-seconds {a.image_seconds:g}); "
                 "give at least one image's worth, or 0 to skip station to FITS")
    xp = array_module(a.device)
    space = "cuda" if a.device == "gpu" else "system"

    def sync():
        if a.device == "gpu":
            xp.cuda.get_current_stream().synchronize()

    def device_sync():
        if a.device == "gpu":
            xp.cuda.Device().synchronize()

    graphs = {"auto": ["folded", "calfold"] if a.device == "gpu" else ["calfold"],
              "both": ["folded", "calfold"]}.get(a.graph, [a.graph])
    case = make_case(a, xp)
    rows, methods, stages = [], {}, {}
    variants = [("pipe-dev", True), ("pipe-host", False)] if a.device == "gpu" else [("pipe-host", False)]
    for graph in graphs:
        t_core, t_core_setup, methods[graph] = bench_core(a, case, xp, device_sync, graph)
        grows = [{"graph": graph, "path": "core", "s_per_gulp": t_core, "run_s": t_core * a.ngulp + t_core_setup,
                  "setup_s": t_core_setup}]
        ref = None
        for name, on_dev in variants:
            bench_blocks(a, case, xp, space, on_dev, graph)  # warm-up
            best = None
            for _ in range(a.repeat):
                r = bench_blocks(a, case, xp, space, on_dev, graph)
                if best is None or r[0] < best[0]:
                    best = r
            per, t_all, n_img, _, images = best
            if ref is None:
                ref = images
                err = first_image_error(case, images)
            elif not np.allclose(images, ref, rtol=1e-5, atol=1e-5 * np.nanmax(np.abs(ref)), equal_nan=True):
                raise RuntimeError(f"{graph} {name}: images differ from the other pipeline run")
            grows.append({"graph": graph, "path": name, "s_per_gulp": per, "run_s": t_all, "images": n_img,
                          "error": err})
        for r in grows:
            r["overhead"] = r["s_per_gulp"] / t_core - 1
            r["run_overhead"] = r["run_s"] / grows[0]["run_s"] - 1
            r["x_realtime"] = a.gulp / REALTIME_FPS / r["s_per_gulp"]
        rows += grows
        if a.stages:
            _, _, _, st, _ = bench_blocks(a, case, xp, space, a.device == "gpu", graph, stages=True, sync=sync)
            stages[graph] = {k: {"mean_ms": 1e3 * float(np.mean(v[1:] or v)), "calls": len(v)} for k, v in st.items()}
    fits_row = fits_error = None
    if a.fits_seconds > 0:
        try:
            fits_row = bench_fits(a, xp, space, sync, graphs[0])
        except ImportError as exc:   # astropy (FITS, times) missing on this machine: say so, keep (a)-(c)
            fits_error = f"station to FITS not run: {type(exc).__name__}: {exc}"

    print(f"# bench_pipeline device={a.device} nchan={a.nchan} gulps={a.ngulp}x{a.gulp} grid={a.grid} "
          f"({case['layout']}) runtime={_compat.RUNTIME} imager method={methods}")
    print(f"{'graph':<8} {'path':<10} {'ms/gulp':>9} {'overhead':>9} {'x real time':>11} {'whole run s':>12} "
          f"{'run overhead':>13} {'error':>9}")
    for r in rows:
        err = f"{r['error']:9.1e}" if "error" in r else f"{'':>9}"
        print(f"{r['graph']:<8} {r['path']:<10} {1e3 * r['s_per_gulp']:9.3f} {100 * r['overhead']:8.1f}% "
              f"{r['x_realtime']:11.2f} {r['run_s']:12.3f} {100 * r['run_overhead']:12.1f}% {err}")
    print("# error: the first image (Stokes I) against the float64 definition on every 97th pixel, max relative")
    print("# steady state = interval between the sink's images after the first; whole run includes start-up "
          "(core: " + ", ".join(f"{r['graph']} {1e3 * r['setup_s']:.1f} ms" for r in rows if r["path"] == "core")
          + " operator build)")
    for graph, st in stages.items():
        print(f"# {graph}, per stage (stream synchronised after each on_data; not overlapped):")
        for k, v in st.items():
            print(f"  {k:<24} {v['mean_ms']:8.3f} ms/gulp ({v['calls']} calls)")
    if fits_row:
        f = fits_row
        print(f"# station to FITS: {f['seconds_of_data']:.1f} s of data ({f['frames']} frames, gulp {f['gulp']}), "
              f"{f['images']} images of {a.image_seconds:g} s ({f['graph']} graph, {f['method']}), FITS in {f['outdir']}")
        print(f"{'fits run':<22} {f['wall_s']:8.3f} s  {f['realtime_factor']:7.2f} x real time "
              f"(steady {f['steady_s_per_image']:.3f} s/image = {f['realtime_factor_steady']:.2f} x; "
              f"after a {f['warm_up_s']:.1f} s warm-up run of 2 images)")
        print(f"{'source alone':<22} {f['source_only_s']:8.3f} s  {f['source_only_realtime_factor']:7.2f} x real time "
              f"({f['source_only_GBps']:.2f} GB/s of ci4)   [data generated in {f['generate_s']:.1f} s]")
        print(f"# image peak at l,m = {f['peak_lm'][0]:+.3f},{f['peak_lm'][1]:+.3f} (source {f['source_lm']}, "
              f"cell {f['cell']:.3f})")
    if fits_error:
        print("# " + fits_error)
    if a.json:
        out = {"benchmark": "bench_pipeline", "date": utc_now(), "device": a.device, "machine": machine(a.device), "nchan": a.nchan, "gulp": a.gulp, "ngulp": a.ngulp, "grid": a.grid,
               "layout": case["layout"], "runtime": _compat.RUNTIME, "method": methods, "graphs": graphs, "rows": rows,
               "stages": stages, "fits": fits_row or fits_error, "realtime_fps": REALTIME_FPS}
        write_json(a.json, out)


if __name__ == "__main__":
    main()
