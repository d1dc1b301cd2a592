#!/usr/bin/env python
"""Benchmark: sustained write rate of the HDF5 image-cube writer against the disk's own ceiling.

Case P images: 16 channels x 1 product x 3,205 pixels float32 (205 kB), one image per 16 samples
(0.64 ms) -> 1,562.5 images/s = 320.5 MB/s of images; the target is 1.5x that (481 MB/s), or, where
the disk cannot take that, the disk's ceiling measured in the same run.

"Sustained": every row writes ``--gb`` GB (more than the kernel will hold as dirty page cache,
so writeback throttles the writer to the disk's speed) and its time runs until the data are on the
disk (the file is fsync'ed before the clock stops). Rows:

* ``dd`` -- ``dd bs=4M conv=fdatasync`` of zeros: the disk's ceiling for one sequential stream;
* ``tofile`` -- the naive baseline: ``ndarray.tofile`` of the same float32 gulps, then fsync;
* ``cube f32`` / ``cube f16`` / ``cube f32 chan-avg`` -- :class:`ImageCubeWriter` (io/cube.py);
* ``block f32`` / ``block f16`` -- the same through ImageCubeWriterBlock on the ring runtime, fed by a
  source block that commits 64-image gulps (what the imager's ring delivers at a 1,024-sample gulp).

    python tools/bench/bench_cube_writer.py --gb 4 --dir /tmp --json docs/bench/cube_writer_cpu.json
"""
import argparse
import os
import shutil
import subprocess
import sys
import time

import numpy as np

from benchlib import machine, utc_now, write_json
from cases import image_header

IMAGE_RATE = 25e3 / 16          # images per second at LWA-SV, one per 16 samples
NCHAN, NPIX = 16, 3205
CASE_P_BYTES = NCHAN * NPIX * 4


def _fsync(path):
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _settle():
    """Let the previous row's writeback finish so rows do not pay for each other."""
    subprocess.run(["sync"], check=False)
    time.sleep(1.0)


def row_dd(path, nbytes):
    count = max(1, nbytes // (4 << 20))
    t0 = time.perf_counter()
    subprocess.run(["dd", "if=/dev/zero", f"of={path}", "bs=4M", f"count={count}", "conv=fdatasync"],
                   check=True, capture_output=True)
    return time.perf_counter() - t0, count * (4 << 20), None


def row_tofile(path, gulp, ngulp):
    t0 = time.perf_counter()
    with open(path, "wb") as f:
        for _ in range(ngulp):
            gulp.tofile(f)
    _fsync(path)
    return time.perf_counter() - t0, gulp.nbytes * ngulp, gulp.shape[0] * ngulp


def _writer(path, dtype, average, grid, loc):
    from bf_epic_blocks.io.cube import ImageCubeWriter
    freq = 74e6 + 25e3 * np.arange(NCHAN)
    return ImageCubeWriter(path, freq, ["I"], grid.lm, 1717236000 * 196_000_000, 16 * 7840,
                           pixel_index=np.flatnonzero(grid.mask), grid=grid, location=loc, dtype=dtype,
                           average_channels=average)


def row_cube(path, gulp, ngulp, dtype, average, grid, loc):
    t0 = time.perf_counter()
    w = _writer(path, dtype, average, grid, loc)
    for _ in range(ngulp):
        w.append(gulp)
    w.close()
    _fsync(path)
    el = time.perf_counter() - t0
    return el, os.path.getsize(path), gulp.shape[0] * ngulp


def row_block(outdir, gulp, ngulp, dtype, grid):
    """Through the ring runtime: a source committing 64-image gulps -> ImageCubeWriterBlock."""
    from bf_epic_blocks.blocks import ImageCubeWriterBlock, bfp
    from bf_epic_blocks.blocks._compat import span_array
    N = grid.size
    full = np.full((gulp.shape[0], NCHAN, 1, N * N), np.nan, np.float32)
    full[..., np.flatnonzero(grid.mask)] = gulp
    full = full.reshape(gulp.shape[0], NCHAN, 1, N, N)
    hdr = image_header(grid, 74e6 + 25e3 * np.arange(NCHAN), 16 * 40e-6)

    class Repeat(bfp.SourceBlock):
        def create_reader(self, name):
            self.left = ngulp
            return open(os.devnull)

        def on_sequence(self, reader, name):
            return [dict(hdr)]

        def on_data(self, reader, ospans):
            if self.left == 0:
                return [0]
            span_array(ospans[0])[...] = full
            self.left -= 1
            return [full.shape[0]]

    t0 = time.perf_counter()
    with bfp.Pipeline() as p:
        src = Repeat(["repeat"], full.shape[0])
        w = ImageCubeWriterBlock(src, outdir, prefix="bench", dtype=dtype)
        p.run()
    for f in w.written:
        _fsync(f)
    el = time.perf_counter() - t0
    return el, sum(os.path.getsize(f) for f in w.written), gulp.shape[0] * ngulp, w.written


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gb", type=float, default=4.0, help="GB of float32 case-P images per row")
    ap.add_argument("--dir", default="/tmp", help="directory on the disk to measure")
    ap.add_argument("--rows", nargs="*", default=None, help="subset of rows (dd tofile cube-f32 cube-f16 "
                                                             "cube-avg block-f32 block-f16)")
    ap.add_argument("--repeat", type=int, default=3, help="rounds over the rows (interleaved); median reported")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    from astropy.coordinates import EarthLocation
    from bf_epic_blocks.imaging import lm_grid
    grid = lm_grid(64)
    assert grid.npix == NPIX
    loc = EarthLocation.from_geodetic(-106.8858, 34.3484, 1477.0)
    rng = np.random.default_rng(0)
    gulp = rng.normal(10.0, 1.0, (64, NCHAN, 1, NPIX)).astype(np.float32)     # one 1,024-sample gulp of images
    ngulp = max(1, int(a.gb * 1e9 / gulp.nbytes))
    work = os.path.join(a.dir, f"bench_cube_{os.getpid()}")
    os.makedirs(work, exist_ok=True)
    rows = a.rows or ["dd", "tofile", "cube-f32", "cube-f16", "cube-avg", "block-f32", "block-f16"]
    runs = []
    try:
        for name in [r for _ in range(a.repeat) for r in rows]:
            _settle()
            path = os.path.join(work, f"{name}.bin")
            files = [path]
            if name == "dd":
                el, nbytes, nimg = row_dd(path, int(a.gb * 1e9))
            elif name == "tofile":
                el, nbytes, nimg = row_tofile(path, gulp, ngulp)
            elif name.startswith("cube"):
                dtype = "float16" if name.endswith("f16") else "float32"
                el, nbytes, nimg = row_cube(path, gulp, ngulp, dtype, name.endswith("avg"), grid, loc)
            else:
                el, nbytes, nimg, files = row_block(work, gulp, ngulp, "float16" if name.endswith("f16") else "float32",
                                                    grid)
            r = {"row": name, "seconds": el, "bytes": nbytes, "disk_MBps": nbytes / el / 1e6}
            if nimg:
                r.update(images=nimg, images_per_s=nimg / el, caseP_MBps=nimg * CASE_P_BYTES / el / 1e6,
                         realtime_factor=nimg / el / IMAGE_RATE)
            runs.append(r)
            for f in files:
                if os.path.exists(f):
                    os.remove(f)
            print(f"  {name}: {el:.1f} s", file=sys.stderr)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    results = []
    for name in rows:   # the median round of each row (by rate); the range across rounds alongside
        mine = sorted((r for r in runs if r["row"] == name), key=lambda r: r["disk_MBps"])
        med = dict(mine[len(mine) // 2])
        med["disk_MBps_range"] = [mine[0]["disk_MBps"], mine[-1]["disk_MBps"]]
        if "caseP_MBps" in med:
            med["caseP_MBps_range"] = [mine[0]["caseP_MBps"], mine[-1]["caseP_MBps"]]
        results.append(med)
    ceiling = next((r["disk_MBps"] for r in results if r["row"] == "dd"), None)
    need = IMAGE_RATE * CASE_P_BYTES / 1e6
    print(f"\nCase P image stream: {need:.1f} MB/s of float32 images ({IMAGE_RATE:.1f} images/s); "
          f"target 1.5x = {1.5 * need:.1f} MB/s; {a.gb:g} GB per row, fsync'ed, in {a.dir}")
    print(f"median of {a.repeat} interleaved rounds; [min-max] over the rounds")
    print(f"{'row':<12} {'s':>7} {'disk MB/s':>10} {'[range]':>13} {'images/s':>10} {'case-P MB/s':>12} "
          f"{'[range]':>13} {'x real time':>12} {'of dd':>7}")
    for r in results:
        frac = r["disk_MBps"] / ceiling if ceiling else float("nan")
        dr = r["disk_MBps_range"]
        cr = r.get("caseP_MBps_range", [float("nan")] * 2)
        print(f"{r['row']:<12} {r['seconds']:>7.2f} {r['disk_MBps']:>10.1f} {f'[{dr[0]:.0f}-{dr[1]:.0f}]':>13} "
              f"{r.get('images_per_s', float('nan')):>10.0f} {r.get('caseP_MBps', float('nan')):>12.1f} "
              f"{f'[{cr[0]:.0f}-{cr[1]:.0f}]':>13} {r.get('realtime_factor', float('nan')):>12.2f} {frac:>7.2f}")
    if a.json:
        out = {"date": utc_now(), "machine": machine("cpu"), "dir": a.dir, "gb_per_row": a.gb, "caseP_need_MBps": need,
               "target_MBps": 1.5 * need, "disk_ceiling_MBps": ceiling, "repeat": a.repeat, "rows": results,
               "runs": runs}
        write_json(a.json, out)


if __name__ == "__main__":
    main()
