"""Where a pipeline's memory goes while it runs: the host's and, on a GPU, CuPy's pool.

Runs a pipeline YAML (default the whole station) in this process and samples, beside it:

- the host, every ``--host-every`` s: the resident set (``/proc/self/status``: VmRSS, RssAnon, RssFile),
  glibc's heap (``mallinfo2``: bytes in use, free in the heap, mmapped), threads, and CuPy's pinned pool's
  free blocks; ``--trim S`` calls ``malloc_trim(0)`` every S s (does the heap's free space explain a
  growth?); at two times (``--snap T0 T1``) the garbage collector's objects by type;
- on a GPU, every ``--pool-every`` s: the pool's bytes in use and held (in use + the free blocks it keeps
  for each stream: what ``gpu_memory_gb``'s limit counts), and every allocation of ``--log-mib`` or more
  with the thread and the package's frames that asked for it (an allocator over the default pool); with
  ``--lifetimes`` also when each was freed (handed out through CuPy's ``UnownedMemory``, whose owner notes
  the free), and so what was alive, by site, when the bytes in use peaked and when the held bytes did;
- with ``--tracemalloc`` (and ``--snap``), Python's own allocations (NumPy's arrays included): their total in
  each host sample from ``--trace-from`` (default 0.8 T0: tracing a pipeline's start slows it many times
  over) with ``--trace-frames`` frames, and the tracebacks whose bytes grew most between the two snapshot
  times. A host growth that glibc shows and these do not is native: a C library's, the CUDA driver's,
  CuPy's C side.

A run that fails or is stopped (a time limit's SIGTERM, which the runner turns into ``KeyboardInterrupt`` once
it has drained) is reported with its error and what was sampled, and exits 1.

Prints the host's samples and slopes (MiB per second of wall time over the middle of the run), the pool's
peaks and the allocation sites by total, and writes all of it as JSON. Glibc's figures need Linux with
glibc 2.33 or later; elsewhere they are left out.

    python tools/bench/profile_memory.py [--yaml PIPE] [--seconds 40] [--device gpu] [--set KEY=VALUE ...]
                                         [--trim S] [--lifetimes] [--snap T0 T1 [--tracemalloc [--trace-from S]]]
                                         [--json PATH]
"""
from __future__ import annotations

import argparse
import collections
import ctypes
import gc
import os
import sys
import threading
import time
import traceback
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import REPO, machine, utc_now, write_json  # noqa: E402

MIB = 2 ** 20


class _MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks",
                                               "uordblks", "fordblks", "keepcost")]


def _libc():
    """glibc with mallinfo2 and malloc_trim, or None."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallinfo2.restype = _MallInfo2
        return libc
    except (OSError, AttributeError):
        return None


def malloc_in_use_mib(libc=None):
    """glibc's bytes in use, MiB: its heap's small blocks and the blocks it mmapped (what a C library such as
    HDF5 holds, which tracemalloc does not see); None without mallinfo2."""
    libc = libc or _libc()
    if libc is None:
        return None
    m = libc.mallinfo2()
    return (m.uordblks + m.hblkhd) / MIB


def host_sample(libc, pinned=None):
    """One sample of the host's memory (MiB): resident set and its parts, glibc's heap, threads, pinned pool."""
    s = {}
    try:
        for line in open("/proc/self/status"):
            k, _, v = line.partition(":")
            if k in ("VmRSS", "RssAnon", "RssFile", "Threads"):
                s[k] = int(v.split()[0])
    except OSError:
        pass
    out = {"rss": s.get("VmRSS", 0) / 1024, "rss_anon": s.get("RssAnon", 0) / 1024,
           "rss_file": s.get("RssFile", 0) / 1024, "threads": s.get("Threads", 0)}
    if libc is not None:
        m = libc.mallinfo2()
        out.update(malloc_in_use=m.uordblks / MIB, malloc_free=m.fordblks / MIB, malloc_mmapped=m.hblkhd / MIB)
    if pinned is not None:
        out["pinned_free_blocks"] = pinned.n_free_blocks()
    return out


def slope(t, v, lo, hi):
    """Least-squares MiB per second of v over lo <= t <= hi (None with fewer than 3 samples there)."""
    t, v = np.asarray(t, float), np.asarray(v, float)
    m = (t >= lo) & (t <= hi)
    return None if m.sum() < 3 else float(np.polyfit(t[m], v[m], 1)[0])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--yaml", default="pipelines/lwasv_sim_station.yaml")
    ap.add_argument("--seconds", type=float, default=40.0, help="seconds of data (source.duration_s)")
    ap.add_argument("--device", default="gpu")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--host-every", type=float, default=1.0)
    ap.add_argument("--pool-every", type=float, default=0.005)
    ap.add_argument("--log-mib", type=float, default=32.0)
    ap.add_argument("--trim", type=float, default=0.0, help="malloc_trim(0) every this many s (0: never)")
    ap.add_argument("--snap", type=float, nargs=2, default=None, metavar=("T0", "T1"),
                    help="wall seconds at which the garbage collector's objects are counted by type (default: not)")
    ap.add_argument("--lifetimes", action="store_true",
                    help="on a GPU, note when each logged allocation is freed: what was alive at the peaks, by site")
    ap.add_argument("--tracemalloc", action="store_true",
                    help="trace Python's allocations: their total per sample, and what grew between the --snap times")
    ap.add_argument("--trace-from", type=float, default=None,
                    help="with --tracemalloc: start tracing this many s into the run (default 0.8 x T0)")
    ap.add_argument("--trace-frames", type=int, default=6, help="with --tracemalloc: frames kept a traceback")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    if a.tracemalloc and not a.snap:
        ap.error("--tracemalloc compares two snapshots: give --snap T0 T1")

    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import ConfigError, load_config
    try:
        cfg = load_config(str(REPO / a.yaml) if not os.path.isabs(a.yaml) else a.yaml,
                          [f"device={a.device}", f"source.duration_s={a.seconds}"] + a.set)
    except (ConfigError, OSError) as e:                 # a bad --set or YAML: its message, not a traceback
        print(f"profile_memory: {e}", file=sys.stderr)
        return 2
    gpu = not str(a.device).startswith("cpu")
    cp = pool = pinned = None
    logs, pool_samples = [], []
    t0 = time.perf_counter()
    if gpu:
        import cupy as cp
        pool, pinned = cp.get_default_memory_pool(), cp.get_default_pinned_memory_pool()
        least = int(a.log_mib * MIB)

        def alloc(size):
            p = pool.malloc(size)
            if size >= least:
                st = [f"{os.path.basename(f.filename)}:{f.lineno}:{f.name}" for f in traceback.extract_stack(limit=14)[:-1]
                      if "bf_epic_blocks" in f.filename]
                entry = [round(time.perf_counter() - t0, 4), int(size), threading.current_thread().name, st[-4:], None]
                logs.append(entry)
                if a.lifetimes:
                    # the array holds this memory, which holds its owner, which holds the pool's pointer: when
                    # the array goes, the owner notes the time and the pointer returns to the pool
                    mem = cp.cuda.UnownedMemory(p.ptr, size, _Freed(p, entry, t0), device_id=p.device_id)
                    return cp.cuda.MemoryPointer(mem, 0)
            return p
        cp.cuda.set_allocator(alloc)
    libc = _libc()
    host, snaps, stop = [], {}, threading.Event()
    traced = {}
    trace_from = None if not a.tracemalloc else (0.8 * a.snap[0] if a.trace_from is None else a.trace_from)

    def counts():
        """The collector's objects by type, and its largest lists, dicts and deques with what holds them
        (an attribute's or a key's name where a dict does): a container that grows without bound shows."""
        gc.collect()
        objs = gc.get_objects()
        big = sorted((o for o in objs if type(o) in (list, dict, collections.deque)), key=len, reverse=True)[:10]
        held = []
        for o in big:
            names = []
            for ref in gc.get_referrers(o):
                if isinstance(ref, dict) and ref is not objs:
                    names += [str(k)[:40] for k, v in ref.items() if v is o][:2]
            first = next(iter(o), None)
            held.append(f"{type(o).__name__} of {len(o)} ({type(first).__name__} ...) held as {names[:3]}")
        return collections.Counter(type(o).__name__ for o in objs), held

    def sample_host():
        last_trim = 0.0
        while True:                               # one sample at least, however short the run
            t = time.perf_counter() - t0
            if a.trim and libc is not None and t - last_trim >= a.trim:
                libc.malloc_trim(0)
                last_trim = t
            if trace_from is not None and t >= trace_from and not tracemalloc.is_tracing():
                # from here on: tracing the start (catalogues, kernels, operators) slows it many times over,
                # and what grows later is what is asked
                tracemalloc.start(a.trace_frames)
            sample = {"t": round(t, 2), **host_sample(libc, pinned)}
            if tracemalloc.is_tracing():
                sample["traced"] = tracemalloc.get_traced_memory()[0] / MIB
            host.append(sample)
            if a.snap:
                for i, ts in enumerate(a.snap):
                    if t >= ts and i not in snaps:
                        snaps[i] = (t,) + counts()
                        if tracemalloc.is_tracing():
                            traced[i] = tracemalloc.take_snapshot()
            if stop.wait(a.host_every):
                break

    def sample_pool():
        while not stop.is_set():
            pool_samples.append((round(time.perf_counter() - t0, 4), pool.used_bytes(), pool.total_bytes()))
            stop.wait(a.pool_every)

    threads = [threading.Thread(target=sample_host, daemon=True)]
    if gpu:
        threads.append(threading.Thread(target=sample_pool, daemon=True))
    for th in threads:
        th.start()
    err = None
    try:
        r = runner.run(cfg, show_progress=False)
    except (Exception, KeyboardInterrupt) as e:
        # the failure is what is being profiled (out of memory), or the run was stopped (a time limit's
        # SIGTERM reaches the runner, which drains and raises KeyboardInterrupt): reported with the samples
        err, r = f"{type(e).__name__}: {str(e)[:400]}", {}
    stop.set()
    for th in threads:
        th.join()
    wall = time.perf_counter() - t0
    if tracemalloc.is_tracing():
        tracemalloc.stop()

    print(f"# profile_memory: {a.yaml} {' '.join(a.set)} on {machine(a.device)['hardware']}: {a.seconds:g} s of data "
          f"in {wall:.1f} s{'; error: ' + err if err else ''}")
    keys = [k for k in ("rss", "rss_anon", "malloc_in_use", "malloc_free", "malloc_mmapped", "traced")
            if any(k in s for s in host)]                  # (traced: from the time tracing starts)
    print("t s     " + " ".join(f"{k:>14s}" for k in keys) + "  threads  pinned free blocks")
    for s in host[:: max(1, len(host) // 16)] + host[-1:]:
        print(f"{s['t']:6.1f}  " + " ".join(f"{s[k]:14.1f}" if k in s else f"{'':14s}" for k in keys)
              + f"  {s['threads']:7d}  {s.get('pinned_free_blocks', '')}")
    lo, hi = 0.25 * wall, 0.9 * wall
    slopes = {k: slope([s["t"] for s in host if k in s], [s[k] for s in host if k in s], lo, hi) for k in keys}
    print("MiB/s over the middle (" + f"{lo:.0f}-{hi:.0f} s): "
          + ", ".join(f"{k} {v:+.2f}" for k, v in slopes.items() if v is not None))
    growth, largest = {}, []
    if len(snaps) == 2:
        growth = dict((snaps[1][1] - snaps[0][1]).most_common(12))
        print(f"objects the collector tracks, growth {snaps[0][0]:.0f} -> {snaps[1][0]:.0f} s: "
              + ", ".join(f"{k} +{n}" for k, n in growth.items()))
        for i in (0, 1):
            largest.append({"t": round(snaps[i][0], 2), "containers": snaps[i][2]})
            print(f"the largest containers at {snaps[i][0]:.1f} s:")
            for line in snaps[i][2]:
                print("  " + line)
    traced_growth = traced_growth_by_site(traced[0], traced[1]) if len(traced) == 2 else []
    if traced_growth:
        print(f"Python's allocations that grew most, {snaps[0][0]:.0f} -> {snaps[1][0]:.0f} s (MiB, blocks):")
        for x in traced_growth:
            print(f"  {x['mib']:+9.2f} {x['blocks']:+8d}  {' < '.join(x['frames'])}")
    gpu_out = None
    if gpu and pool_samples:
        k = max(range(len(pool_samples)), key=lambda i: pool_samples[i][1])
        kh = max(range(len(pool_samples)), key=lambda i: pool_samples[i][2])
        sites = collections.defaultdict(lambda: [0, 0, 0])
        for e in logs:
            s = sites[site_of(e[3])]
            s[0] += 1; s[1] += e[1]; s[2] = max(s[2], e[1])
        top = sorted(sites.items(), key=lambda kv: -kv[1][1])[:20]
        gpu_out = {"peak_in_use_gb": pool_samples[k][1] / 1e9, "peak_at_s": pool_samples[k][0],
                   "held_peak_gb": pool_samples[kh][2] / 1e9, "in_use_at_held_peak_gb": pool_samples[kh][1] / 1e9,
                   "per_second_max_gb": {str(s): round(v / 1e9, 2) for s, v in
                                         sorted(_per_second(pool_samples).items())},
                   "largest_allocations_by_site": [{"site": s, "count": v[0], "largest_mib": round(v[2] / MIB, 1),
                                                    "total_gib": round(v[1] / 2**30, 1)} for s, v in top],
                   "allocations_logged": len(logs)}
        if a.lifetimes:
            for key, i in (("live_at_in_use_peak", k), ("live_at_held_peak", kh)):
                gpu_out[key] = {"t": pool_samples[i][0], "by_site": live_by_site(logs, pool_samples[i][0])}
        print(f"GPU pool: in use at most {gpu_out['peak_in_use_gb']:.2f} GB at {gpu_out['peak_at_s']:.1f} s; held at "
              f"most {gpu_out['held_peak_gb']:.2f} GB ({gpu_out['in_use_at_held_peak_gb']:.2f} in use then); "
              f"{len(logs)} allocations of {a.log_mib:g} MiB or more, by site:")
        for x in gpu_out["largest_allocations_by_site"]:
            print(f"  {x['count']:6d} {x['total_gib']:9.1f} GiB  largest {x['largest_mib']:8.1f} MiB  {x['site']}")
        for key in ("live_at_in_use_peak", "live_at_held_peak") if a.lifetimes else ():
            live = gpu_out[key]
            print(f"alive at {live['t']:.2f} s ({key.replace('_', ' ')[8:]}), allocations of {a.log_mib:g} MiB or "
                  "more, by site:")
            for x in live["by_site"][:15]:
                print(f"  {x['count']:6d} {x['gib']:9.2f} GiB  {x['site']}")
    if a.json:
        write_json(a.json, {"benchmark": "profile_memory", "date": utc_now(), "yaml": a.yaml,
                            "sets": [f"device={a.device}", f"source.duration_s={a.seconds}"] + a.set,
                            "machine": machine(a.device), "wall_s": wall, "error": err, "trim_s": a.trim,
                            "host": {"samples": host, "slopes_mib_per_s": slopes, "object_growth": growth,
                                     "largest_containers": largest, "traced_growth": traced_growth},
                            "gpu": gpu_out, "summary_images": r.get("images") if isinstance(r, dict) else None})
    return 1 if err else 0


def traced_growth_by_site(snap0, snap1, top=15):
    """The ``top`` tracebacks whose traced bytes grew most from ``snap0`` to ``snap1`` (tracemalloc
    snapshots): [{"mib", "blocks", "frames"}], frames innermost first, as file:line (four at most; the
    import machinery's own frames left out, so that an import shows as the line that made it)."""
    out = []
    for d in snap1.compare_to(snap0, "traceback")[:top]:
        frames = [f"{os.path.basename(f.filename)}:{f.lineno}" for f in reversed(d.traceback)
                  if not f.filename.startswith("<frozen")][:4]
        out.append({"mib": round(d.size_diff / MIB, 3), "blocks": int(d.count_diff), "frames": frames})
    return out


class _Freed:
    """The owner of one logged GPU allocation (``--lifetimes``): holds the pool's pointer, and notes in the
    log entry (t, size, thread, frames, freed) the time it is let go."""

    __slots__ = ("_p", "_entry", "_t0")

    def __init__(self, p, entry, t0):
        self._p, self._entry, self._t0 = p, entry, t0

    def __del__(self):
        self._entry[4] = round(time.perf_counter() - self._t0, 4)


def site_of(frames):
    """The site an allocation is counted under: its innermost package frame, with the caller's where that is
    a helper's (a Workspace's take), which tells them apart."""
    if not frames:
        return "?"
    return " < ".join(frames[-1:-3:-1]) if frames[-1].startswith("_xp.py") else frames[-1]


def live_by_site(logs, t):
    """The logged allocations alive at time ``t`` (made at or before it, not freed by then), by site, largest
    first: [{site, count, gib}]. logs: [t_made, size, thread, frames, t_freed or None]."""
    by = collections.defaultdict(lambda: [0, 0])
    for made, size, _, frames, freed in logs:
        if made <= t and (freed is None or freed > t):
            b = by[site_of(frames)]
            b[0] += 1
            b[1] += size
    return [{"site": s, "count": v[0], "gib": round(v[1] / 2**30, 3)}
            for s, v in sorted(by.items(), key=lambda kv: -kv[1][1])]


def _per_second(samples):
    out = {}
    for t, used, _ in samples:
        out[int(t)] = max(out.get(int(t), 0), used)
    return out


if __name__ == "__main__":
    sys.exit(main())
