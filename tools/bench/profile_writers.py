"""The HDF5 writers a pipeline keeps open for a whole run, alone: their native memory as the file grows.

A station's watch writer (``io.watchfile.WatchWriter``: ten targets' spectra, every 0.64-ms image, one write
a second) and its cube writer (``io.cube.ImageCubeWriter``: every band-averaged image in float16) stay open
for the whole run. Each is fed synthetic rows at one tuning's rate (1,562 images a second of data, 64 an
append) for ``--seconds`` of data, and glibc's bytes in use (``mallinfo2``: HDF5's allocations are not
Python's, so tracemalloc does not see them) are sampled every ``--every`` s of data. Printed as a table
(in use at each sample, the growth from the first sample to the last, the writer's wall time) and written
as JSON. Needs Linux with glibc 2.33 or later.

    python tools/bench/profile_writers.py [--seconds 600] [--every 60] [--watch-channels 8 784]
                                          [--watch-seconds-full 60] [--npix 3205] [--json PATH]

``--watch-channels``: the watch writer's channel counts; 784 (a whole tuning, 49 MB a second of data to
disk) runs for ``--watch-seconds-full`` s only. The chunk shape is the pipeline's at 784 channels (334 rows)
whatever the count, so a narrow run appends as many chunks a second as the whole tuning does.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import machine, utc_now, write_json  # noqa: E402
from profile_memory import malloc_in_use_mib as in_use_mib  # noqa: E402

RATE = 1562          # 0.64-ms images a second of data
GULP = 64


def feed(append, seconds, every):
    """Call ``append(n0)`` for each gulp of ``seconds`` of data; [(data s, MiB in use)] every ``every`` s."""
    samples, n, nxt = [], 0, 0.0
    while n < seconds * RATE:
        append(n)
        n += GULP
        if n / RATE >= nxt:
            samples.append((round(n / RATE, 1), round(in_use_mib(), 2)))
            nxt += every
    return samples


def run_watch(folder, nchan, seconds, every):
    from bf_epic_blocks.io.watchfile import WatchWriter
    targets = [{"name": f"T{i}", "ra_deg": 10.0 * i, "dec_deg": 20.0} for i in range(10)]
    d = np.ones((GULP, 10, nchan, 1), np.float32)
    t0 = time.perf_counter()
    with WatchWriter(Path(folder) / f"watch_{nchan}.h5", targets, 38e6 + 25e3 * np.arange(nchan), ["I"],
                     chunk_rows=334, flush_s=1.0) as w:
        samples = feed(lambda n: w.append(1.7e9 + (n + np.arange(GULP)) / RATE, d), seconds, every)
    return {"writer": "watch", "nchan": nchan, "seconds": seconds, "samples": samples,
            "wall_s": round(time.perf_counter() - t0, 2)}


def run_cube(folder, npix, seconds, every):
    from bf_epic_blocks.io.cube import ImageCubeWriter
    x = np.ones((GULP, 1, 1, npix), np.float32)
    t0 = time.perf_counter()
    with ImageCubeWriter(Path(folder) / "cube.h5", [74e6], ["I"], np.zeros((npix, 2)), 0, 1, dtype="float16") as w:
        samples = feed(lambda n: w.append(x), seconds, every)
    return {"writer": "cube", "npix": npix, "seconds": seconds, "samples": samples,
            "wall_s": round(time.perf_counter() - t0, 2)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=600.0, help="seconds of data a narrow run is fed")
    ap.add_argument("--every", type=float, default=60.0, help="seconds of data between samples")
    ap.add_argument("--watch-channels", type=int, nargs="+", default=[8, 784])
    ap.add_argument("--watch-seconds-full", type=float, default=60.0, help="seconds of data at 784 channels")
    ap.add_argument("--npix", type=int, default=3205, help="the cube's pixels (the 64x64 grid's 3,205)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    if in_use_mib() is None:
        print("profile_writers: needs glibc's mallinfo2 (Linux, glibc >= 2.33)", file=sys.stderr)
        return 2
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for nchan in a.watch_channels:
            secs = a.watch_seconds_full if nchan >= 784 else a.seconds
            rows.append(run_watch(tmp, nchan, secs, min(a.every, secs / 3)))
        rows.append(run_cube(tmp, a.npix, a.seconds, a.every))
    print(f"# profile_writers on {machine('cpu')['hardware']}")
    print(f"{'writer':<8} {'shape':>10} {'data s':>7} {'first MiB':>10} {'last MiB':>9} {'growth':>8} {'wall s':>7}")
    for r in rows:
        shape = f"{r['nchan']} ch" if r["writer"] == "watch" else f"{r['npix']} px"
        s = r["samples"]
        r["growth_mib"] = round(s[-1][1] - s[0][1], 2)
        print(f"{r['writer']:<8} {shape:>10} {r['seconds']:>7.0f} {s[0][1]:>10.1f} {s[-1][1]:>9.1f} "
              f"{r['growth_mib']:>+8.1f} {r['wall_s']:>7.1f}")
    if a.json:
        write_json(a.json, {"benchmark": "profile_writers", "date": utc_now(), "machine": machine("cpu"),
                            "rate_images_per_s": RATE, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
