#!/usr/bin/env python
"""Benchmark: reading a whole TBX file with LSL's ``lsl.reader.tbx`` vs the package's NumPy reader.

A file is generated with :func:`bf_epic_blocks.io.tbx.write_tbx` (random ci4 voltages; LWA-NA layout
by default: 64 stands, 12-channel frames, 26 blocks = 312 channels) and read into the same result,
a complex64 (ntime, nchan, nstand, 2) grid:

* ``lsl``: ``tbx.read_frame`` frame by frame (its C reader), each payload put in the grid by
  (time tag, first channel) in Python -- the way LSL's own scripts use it;
* ``numpy``: :func:`read_tbx` (one memory-mapped header pass, payloads gathered by fancy
  indexing) then ``unpack`` to complex64;
* ``numpy packed``: :func:`read_tbx` only (packed ci4, what the pipeline's source puts on the ring);
* ``numpy gulps``: :func:`iter_tbx_gulps` in 1,024-sample gulps, packed (the source block's path).

Both results are checked equal before any time is reported. Best of ``--repeat`` runs.

    python tools/bench/bench_tbx_reader.py --ntime 2000 --json docs/bench/bench_tbx_reader_cpu.json
"""
import argparse
import os
import sys
import tempfile

import numpy as np

from bf_epic_blocks.io.tbx import iter_tbx_gulps, read_tbx, tbx_frame_bytes, write_tbx
from bf_epic_blocks.station.offline import configure_offline

from benchlib import best, machine, utc_now, write_json


def lsl_read(tbx, path):
    from lsl.reader.errors import EOFError as LSLEOF
    frames = []
    with open(path, "rb") as fh:
        while True:
            try:
                f = tbx.read_frame(fh)
            except LSLEOF:
                break
            frames.append((int(f.payload.timetag), int(f.header.first_chan), f.payload.data))
    tags = sorted({t for t, _, _ in frames})
    blocks = sorted({c for _, c, _ in frames})
    nc = frames[0][2].shape[0]
    ti, bi = {t: i for i, t in enumerate(tags)}, {c: i for i, c in enumerate(blocks)}
    out = np.zeros((len(tags), len(blocks) * nc) + frames[0][2].shape[1:], np.complex64)
    for t, c, x in frames:
        b = bi[c]
        out[ti[t], b * nc:(b + 1) * nc] = x
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ntime", type=int, default=2000, help="time samples in the generated file")
    ap.add_argument("--nstand", type=int, default=64)
    ap.add_argument("--nchan-frame", type=int, default=12)
    ap.add_argument("--nblock", type=int, default=26)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    configure_offline()
    from lsl.reader import tbx

    rng = np.random.default_rng(0)
    nchan = a.nblock * a.nchan_frame
    data = rng.integers(0, 256, (a.ntime, nchan, a.nstand, 2), dtype=np.uint8)
    tags = 337023871211995136 + 8192 * np.arange(a.ntime)
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "bench.tbx")
        nframe = write_tbx(path, data, tags, 2176, nchan_frame=a.nchan_frame)
        size = os.path.getsize(path)
        t_lsl, ref = best(lambda: lsl_read(tbx, path), a.repeat)
        t_np, mine = best(lambda: read_tbx(path).unpack(np.complex64), a.repeat)
        if not np.array_equal(mine, ref):
            raise SystemExit("the readers disagree: no timing reported")
        t_packed, packed = best(lambda: read_tbx(path), a.repeat)
        np.testing.assert_array_equal(packed.data, data)
        t_gulps, _ = best(lambda: sum(g.ntime for g in iter_tbx_gulps(path, 1024)), a.repeat)
    rows = [("lsl read_frame loop -> complex64 grid", t_lsl), ("numpy read_tbx + unpack -> complex64 grid", t_np),
            ("numpy read_tbx (packed ci4)", t_packed), ("numpy iter_tbx_gulps(1024) (packed ci4)", t_gulps)]
    print(f"TBX file: {nframe} frames of {tbx_frame_bytes(a.nchan_frame, a.nstand)} B ({size / 1e6:.1f} MB), "
          f"{a.ntime} samples x {nchan} channels x {a.nstand} stands; best of {a.repeat}")
    print(f"{'reader':44s} {'s':>8s} {'MB/s':>8s} {'frames/s':>10s} {'vs LSL':>7s}")
    for name, t in rows:
        print(f"{name:44s} {t:8.3f} {size / 1e6 / t:8.1f} {nframe / t:10.0f} {t_lsl / t:6.1f}x")
    if a.json:
        out = {"date": utc_now(), "machine": machine("cpu"), "nframe": nframe, "bytes": size, "ntime": a.ntime, "nchan": nchan,
               "nstand": a.nstand, "repeat": a.repeat, "results": [{"reader": n, "s": t} for n, t in rows]}
        write_json(a.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
