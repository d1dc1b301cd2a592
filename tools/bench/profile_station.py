"""Where a running pipeline's GPU time goes: every CUDA kernel and copy in a window of a `bf-epic run`.

Runs a pipeline (default ``pipelines/lwasv_sim_station.yaml`` on the GPU) in this process, and from
``--start-s`` seconds after it starts records ``--window-s`` seconds of the GPU's activity with PyTorch's
profiler (CUPTI underneath; it records the kernels of every library in the process, CuPy's included).
Nsight Systems would do the same from outside; this script is for machines that have PyTorch and not
``nsys``. Prints and writes as JSON:

* the GPU's busy fraction: the union of every kernel's and copy's time over the window (1.0: the GPU
  never idles, so only less GPU work makes the pipeline faster; less: the host or a wait leaves it idle);
* each kernel name's calls, total GPU seconds per second of window and mean microseconds, grouped into
  the pipeline's stages by name (:data:`STAGES`), largest first;
* the streams the work ran on and how much of the window each was busy;
* the GPU's idle gaps: how many, how long, and which host threads were inside a CUDA call that waits
  (a synchronize, a blocking copy) during them;
* each host thread (the pipeline's threads are named by their blocks): the CPU seconds it used per
  second of window (from ``/proc``; a thread that waits for Python's interpreter lock or for the GPU
  without spinning uses none), its CUDA calls, the seconds per second it spent inside them, and the
  streams its kernels and copies ran on (a block's thread has a stream of its own).

``--python`` instead profiles the host's Python in the window with yappi (CPU clock, every thread):
each thread's CPU seconds per second of window and the functions that used them (own time, and
time including what they called). Python runs one thread at a time (the interpreter lock): when the
threads' Python together needs about one second per second, the GPU waits for the host. A probe
thread measures that wait: how late a 0.5-ms sleep wakes, as a running thread hands the lock over.

Kernels that run side by side on different streams are each counted in full in the per-name totals, so
those can add up to more than the busy fraction. Tracing adds a few microseconds of host time to every
launch, so a run with many small launches runs a little slower while it is traced.

    python tools/bench/profile_station.py [--yaml PATH] [--set KEY=VALUE ...] [--seconds 40]
                                          [--start-s 25] [--window-s 3] [--json PATH]
"""
from __future__ import annotations

import argparse
import collections
import gzip
import json
import os
import re
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import REPO, machine, utc_now, write_json  # noqa: E402

#: (stage, regular expression on the kernel's name), the first match wins
STAGES = (("imaging: fused integer kernel", r"bf_fused|fused_power|fused_gauss"),
          ("imaging: voltage layout and quantise", r"layout|quantis|bf_pack|requant"),
          ("imaging: GEMM (cuBLAS)", r"gemm|cutlass|sm90_xmma|sm80_xmma|igemm|Kernel2"),
          ("search: tree", r"tree|fdmt|dedisp"),
          ("search: statistics", r"boxcar|snr|search|crossing|stats"),
          ("sky calibration", r"skycal|gain|solve|cal_"),
          ("interference", r"rfi|kurt|flag"),
          ("watchlist", r"watch|beam"),
          ("reductions (CuPy)", r"cupy_sum|cupy_max|cupy_min|cupy_argmax|reduce|cub"),
          ("CuPy elementwise", r"^cupy_"),
          ("copies", r"^Memcpy|^Memset|memcpy|memset"))


def stage_of(name):
    """The :data:`STAGES` entry a kernel's name matches ('other' where none does)."""
    for stage, pattern in STAGES:
        if re.search(pattern, name, re.IGNORECASE):
            return stage
    return "other"


def union_seconds(intervals):
    """Seconds covered by a list of (start, end) intervals (overlaps counted once)."""
    total, end = 0.0, None
    for a, b in sorted(intervals):
        if end is None or a > end:
            total += b - a
            end = b
        elif b > end:
            total += b - end
            end = b
    return total


#: CUDA calls that make the calling thread wait for the GPU
WAITS = re.compile(r"Synchronize|cudaMemcpy(?!Async)|cuMemcpy(?!Async)|cudaFree|cuMemFree|EventQuery|StreamQuery")


def summarise(trace, window_s, cpu=None, names=None):
    """Busy fraction, per-name and per-stage totals, per-stream busy time, idle gaps and host threads from a
    Chrome trace (a dict with ``traceEvents``, times in microseconds) of ``window_s`` seconds; ``cpu``:
    {thread id: CPU seconds used in the window}; ``names``: {thread id: name}."""
    gpu = [e for e in trace.get("traceEvents", [])
           if e.get("ph") == "X" and e.get("cat") in ("kernel", "gpu_memcpy", "gpu_memset")]
    if not gpu:
        raise SystemExit("no GPU activity was recorded in the window: is the pipeline on the GPU "
                         "(--set device=gpu), and had it started by --start-s?")
    spans = [(e["ts"] * 1e-6, (e["ts"] + e.get("dur", 0)) * 1e-6) for e in gpu]
    first, last = min(a for a, _ in spans), max(b for _, b in spans)
    span = max(last - first, 1e-9)
    per_name = collections.defaultdict(lambda: [0, 0.0])
    streams = collections.defaultdict(list)
    for e, (a, b) in zip(gpu, spans):
        name = e["name"] if e.get("cat") == "kernel" else e.get("cat").replace("gpu_", "").capitalize()
        per_name[name][0] += 1
        per_name[name][1] += b - a
        streams[str(e.get("args", {}).get("stream", e.get("tid")))].append((a, b))
    rows = [{"name": n, "stage": stage_of(n), "calls": c, "s_per_s": t / span, "mean_us": 1e6 * t / c}
            for n, (c, t) in per_name.items()]
    rows.sort(key=lambda r: -r["s_per_s"])
    stages = collections.defaultdict(float)
    for r in rows:
        stages[r["stage"]] += r["s_per_s"]
    merged = []
    for a, b in sorted(spans):
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    gaps = [(b0, a1) for (_, b0), (a1, _) in zip(merged, merged[1:])]
    calls = [e for e in trace.get("traceEvents", [])
             if e.get("ph") == "X" and e.get("cat") in ("cuda_runtime", "cuda_driver")]
    names = names or {}
    host = collections.defaultdict(lambda: {"calls": 0, "api_s": 0.0, "wait_s": 0.0, "waits": collections.Counter()})
    waiting = []
    by_corr = {e["args"]["correlation"]: int(e.get("tid", 0)) for e in calls if "correlation" in e.get("args", {})}
    launched = collections.defaultdict(collections.Counter)     # thread -> {stream: kernels and copies}
    for e in gpu:
        tid = by_corr.get(e.get("args", {}).get("correlation"))
        if tid is not None:
            launched[tid][str(e["args"].get("stream"))] += 1
    for e in calls:
        h = host[int(e.get("tid", 0))]
        d = e.get("dur", 0) * 1e-6
        h["calls"] += 1
        h["api_s"] += d
        if WAITS.search(e["name"]):
            h["wait_s"] += d
            h["waits"][e["name"]] += d
            waiting.append((e["ts"] * 1e-6, e["ts"] * 1e-6 + d, int(e.get("tid", 0))))
    # which threads were waiting inside a CUDA call while the GPU idled
    idle_waits = collections.Counter()
    idle_total = sum(b - a for a, b in gaps)
    for a, b, tid in waiting:
        for g0, g1 in gaps:
            o = min(b, g1) - max(a, g0)
            if o > 0:
                idle_waits[names.get(tid, str(tid))] += o
    lengths = sorted((b - a for a, b in gaps), reverse=True)
    threads = []
    for tid in set(host) | set(cpu or {}):
        h = host.get(tid, {"calls": 0, "api_s": 0.0, "wait_s": 0.0, "waits": collections.Counter()})
        threads.append({"thread": names.get(tid, str(tid)), "tid": tid,
                        "cpu_s_per_s": None if cpu is None or tid not in cpu else cpu[tid] / window_s,
                        "cuda_calls": h["calls"], "cuda_s_per_s": h["api_s"] / span, "wait_s_per_s": h["wait_s"] / span,
                        "waits": {k: round(v / span, 4) for k, v in h["waits"].most_common(3)},
                        "streams": dict(launched[tid].most_common(4))})
    threads.sort(key=lambda r: -((r["cpu_s_per_s"] or 0) + r["wait_s_per_s"]))
    return {"window_s": window_s, "traced_span_s": span, "busy": union_seconds(spans) / span,
            "idle": {"gaps": len(gaps), "s_per_s": idle_total / span,
                     "longest_ms": [round(1e3 * g, 3) for g in lengths[:10]],
                     "over_1ms_s_per_s": sum(g for g in lengths if g > 1e-3) / span,
                     "threads_waiting_s_per_s": {k: v / span for k, v in idle_waits.most_common(12)}},
            "cpu_s_per_s": None if cpu is None else sum(cpu.values()) / window_s,
            "threads": threads,
            "kernel_s_per_s": sum(r["s_per_s"] for r in rows),
            "stages": dict(sorted(stages.items(), key=lambda kv: -kv[1])),
            "streams": {s: union_seconds(v) / span for s, v in
                        sorted(streams.items(), key=lambda kv: -union_seconds(kv[1]))},
            "kernels": rows}


def record(start_s, window_s, out):
    """Wait ``start_s`` seconds, trace the GPU for ``window_s`` seconds and put the Chrome trace in ``out``."""
    try:
        import torch
        from torch.profiler import ProfilerActivity, profile
    except ImportError:
        out["error"] = "PyTorch is not installed: its profiler records the kernels (pip install torch)"
        return
    time.sleep(start_s)
    torch.cuda.init()
    prof = profile(activities=[ProfilerActivity.CUDA])
    prof.start()
    before = thread_cpu()
    time.sleep(window_s)
    after = thread_cpu()
    prof.stop()
    out["cpu"] = {t: after[t] - before[t] for t in after if t in before}
    out["names"] = thread_names()
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "trace.json"
        prof.export_chrome_trace(str(path))
        out["trace"] = json.loads(path.read_text())


def thread_cpu():
    """{thread id: CPU seconds used so far} for this process's threads (Linux ``/proc``; empty elsewhere)."""
    tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    out = {}
    try:
        tids = os.listdir("/proc/self/task")
    except OSError:
        return out
    for t in tids:
        try:
            with open(f"/proc/self/task/{t}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            out[int(t)] = (int(fields[11]) + int(fields[12])) / tick    # utime, stime
        except (OSError, IndexError, ValueError):
            continue
    return out


def thread_names():
    """{thread id: name}: Python's threads by their names (the pipeline's by their blocks), others by
    the kernel's name for them (``/proc``)."""
    names = {}
    try:
        for t in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{t}/comm") as f:
                    names[int(t)] = f.read().strip()
            except OSError:
                continue
    except OSError:
        pass
    for th in threading.enumerate():
        if th.native_id is not None:
            names[th.native_id] = th.name
        if th.ident is not None:
            # CUPTI names a CUDA call's thread by its pthread_t, which Python's ident is; the trace keeps its
            # low 32 bits
            names.setdefault(th.ident & 0xFFFFFFFF, th.name)
    return names


def gil_probe(stop, out):
    """Until ``stop`` is set: sleep 0.5 ms and record how much later than that the thread runs again
    (waiting for the interpreter lock, mostly); ``out['gil_wait_ms']`` gets the waits' mean, median, 90th
    and 99th percentiles."""
    waits = []
    while not stop.is_set():
        t = time.perf_counter()
        time.sleep(5e-4)
        waits.append(time.perf_counter() - t - 5e-4)
    if waits:
        w = sorted(waits)
        out["gil_wait_ms"] = {"n": len(w), "mean": 1e3 * sum(w) / len(w), "median": 1e3 * w[len(w) // 2],
                              "p90": 1e3 * w[int(0.9 * (len(w) - 1))], "p99": 1e3 * w[int(0.99 * (len(w) - 1))]}


def record_python(start_s, window_s, out, top=8):
    """Wait ``start_s`` seconds, profile every thread's Python with yappi (CPU clock) for ``window_s``
    seconds; ``out['python']``: per thread, its CPU seconds per second and its ``top`` functions."""
    try:
        import yappi
    except ImportError:
        out["error"] = "yappi is not installed: it profiles every thread's Python (pip install yappi)"
        return
    time.sleep(start_s)
    stop = threading.Event()
    probe = threading.Thread(target=gil_probe, args=(stop, out), name="gil-probe", daemon=True)
    yappi.set_clock_type("cpu")
    yappi.set_context_name_callback(lambda: threading.current_thread().name)
    yappi.start(builtins=True, profile_threads=True)
    probe.start()
    time.sleep(window_s)
    yappi.stop()
    stop.set()
    probe.join()
    threads = []
    for th in yappi.get_thread_stats():
        if th.name == "gil-probe":
            continue
        fs = yappi.get_func_stats(ctx_id=th.id)
        rows = sorted(fs, key=lambda f: -f.tsub)[:top]
        threads.append({"thread": th.name if th.name != "_MainThread" else "MainThread",
                        "cpu_s_per_s": th.ttot / window_s,
                        "own": [{"function": f"{f.module.rsplit('/', 1)[-1]}:{f.lineno} {f.name}", "calls": f.ncall,
                                 "s_per_s": f.tsub / window_s} for f in rows],
                        "inclusive": [{"function": f"{f.module.rsplit('/', 1)[-1]}:{f.lineno} {f.name}",
                                       "calls": f.ncall, "s_per_s": f.ttot / window_s}
                                      for f in sorted(fs, key=lambda f: -f.ttot)[:top]]})
    yappi.clear_stats()
    threads.sort(key=lambda r: -r["cpu_s_per_s"])
    out["python"] = {"window_s": window_s, "cpu_s_per_s": sum(t["cpu_s_per_s"] for t in threads),
                     "gil_wait_ms": out.pop("gil_wait_ms", None), "threads": threads}


def show_python(res):
    g = res["gil_wait_ms"] or {}
    print(f"Python on every thread, {res['window_s']:.1f} s window: {res['cpu_s_per_s']:.2f} CPU s per s "
          f"(yappi's CPU clock); a 0.5-ms sleep woke late by (ms) mean {g.get('mean', float('nan')):.2f}, "
          f"median {g.get('median', float('nan')):.2f}, p90 {g.get('p90', float('nan')):.2f}, "
          f"p99 {g.get('p99', float('nan')):.2f}")
    for t in res["threads"]:
        if t["cpu_s_per_s"] < 0.005:
            continue
        print(f"\n{t['thread']}: {t['cpu_s_per_s']:.3f} CPU s per s")
        print("| own time | calls | s per s | | with callees | calls | s per s |\n|---|---|---|---|---|---|---|")
        for a, b in zip(t["own"], t["inclusive"]):
            print(f"| {a['function'][:70]} | {a['calls']} | {a['s_per_s']:.4f} | | {b['function'][:70]} | "
                  f"{b['calls']} | {b['s_per_s']:.4f} |")


def show(res):
    print(f"window {res['window_s']:.1f} s, GPU activity over {res['traced_span_s']:.3f} s: "
          f"busy {100 * res['busy']:.1f}%, kernels and copies {res['kernel_s_per_s']:.3f} s per s")
    print("\n| stage | GPU s per s |\n|---|---|")
    for k, v in res["stages"].items():
        print(f"| {k} | {v:.4f} |")
    print("\n| kernel | stage | calls | GPU s per s | mean us |\n|---|---|---|---|---|")
    for r in res["kernels"][:40]:
        print(f"| {r['name'][:90]} | {r['stage']} | {r['calls']} | {r['s_per_s']:.4f} | {r['mean_us']:.1f} |")
    print("\n| stream | busy |\n|---|---|")
    for s, v in list(res["streams"].items())[:12]:
        print(f"| {s} | {100 * v:.1f}% |")
    idle = res["idle"]
    print(f"\nGPU idle: {100 * idle['s_per_s']:.1f}% in {idle['gaps']} gaps ({100 * idle['over_1ms_s_per_s']:.1f}% "
          f"in gaps over 1 ms); longest (ms): {idle['longest_ms']}")
    print("threads inside a waiting CUDA call while the GPU idled (s per s):",
          ", ".join(f"{k} {v:.3f}" for k, v in idle["threads_waiting_s_per_s"].items()) or "none")
    cpu = res.get("cpu_s_per_s")
    print(f"\nhost threads (CPU s per s in all: {'-' if cpu is None else f'{cpu:.2f}'})")
    print("| thread | CPU s per s | CUDA calls | in CUDA calls s per s | waiting s per s | longest waits | "
          "streams launched on |\n|---|---|---|---|---|---|---|")
    for r in res["threads"][:30]:
        c = "-" if r["cpu_s_per_s"] is None else f"{r['cpu_s_per_s']:.3f}"
        print(f"| {r['thread']} | {c} | {r['cuda_calls']} | {r['cuda_s_per_s']:.3f} | {r['wait_s_per_s']:.3f} | "
              f"{r['waits']} | {r['streams']} |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--yaml", type=Path, default=REPO / "pipelines" / "lwasv_sim_station.yaml")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="overrides passed to bf-epic run (device=gpu is always added)")
    ap.add_argument("--seconds", type=float, default=40.0, help="source.duration_s")
    ap.add_argument("--start-s", type=float, default=25.0, help="seconds after the start when tracing begins")
    ap.add_argument("--window-s", type=float, default=3.0, help="seconds traced")
    ap.add_argument("--out-dir", type=Path, default=None, help="the run's outputs (default: a temporary folder)")
    ap.add_argument("--json", help="write the result here")
    ap.add_argument("--python", action="store_true",
                    help="profile the host's Python (yappi) instead of the GPU's kernels")
    ap.add_argument("--trace", help="also write the window's Chrome trace here (gzip; chrome://tracing, Perfetto)")
    args = ap.parse_args(argv)

    from bf_epic_blocks.pipeline import cli
    got = {}
    t = threading.Thread(target=record_python if args.python else record, args=(args.start_s, args.window_s, got),
                         daemon=True)
    with tempfile.TemporaryDirectory() as tmp:
        out_dir = args.out_dir or Path(tmp)
        argv_run = ["run", str(args.yaml), "--no-progress", "-q", "--set", "device=gpu",
                    "--set", f"source.duration_s={args.seconds}", "--set", f"output.dir={out_dir}"]
        for s in args.set:
            argv_run += ["--set", s]
        t0 = time.perf_counter()
        t.start()
        rc = cli.main(argv_run)
        wall = time.perf_counter() - t0
        t.join(timeout=max(0.0, args.start_s + args.window_s + 60 - wall))
    if "error" in got:
        raise SystemExit(got["error"])
    if "trace" not in got and "python" not in got:
        raise SystemExit(f"the run ended after {wall:.1f} s, before the window closed: "
                         f"lower --start-s or raise --seconds")
    if args.python:
        res = got["python"]
    else:
        if args.trace:
            with gzip.open(args.trace, "wt") as f:
                json.dump(got["trace"], f)
        res = summarise(got["trace"], args.window_s, got.get("cpu"), got.get("names"))
    res.update(benchmark="profile_station", date=utc_now(), yaml=str(args.yaml.relative_to(REPO))
               if args.yaml.is_absolute() and REPO in args.yaml.parents else str(args.yaml),
               sets=["device=gpu", f"source.duration_s={args.seconds}"] + args.set, start_s=args.start_s,
               run_rc=rc, run_wall_s=wall, machine=machine("gpu"))
    show_python(res) if args.python else show(res)
    if args.json:
        write_json(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
