"""Soak: the station service left running on a replayed live stream, with F-engine resets and a stopped
sender, watched the way a station watches it.

`bf-epic run YAML --serve 127.0.0.1:PORT` (default the shipped live YAML, ``source.sequences: 0``: stream
after stream until stopped; an output budget ``output.keep_gb``) is a subprocess; `bf-epic replay`
subprocesses send it a capture file looped into a continuous stream (``--loop``) at ``--rate`` x real time,
in three phases over ``--minutes``:

1. the stream (40% of the time);
2. the sender stopped for ``--pause-s`` (longer than ``service.no_data_s``: /health goes down, and than
   ``source.idle_timeout_s``: the sequence ends), then the stream again on a new time base
   (``--shift-s``: the first reset, after a silence);
3. at 70% of the time, with no pause, a jump to another time base (the second reset, as an F-engine
   restarting mid-stream makes); ``--resets N``: N such jumps spread over the last 30%.

``--drop F`` leaves out that fraction of the second phase's packets: frames missing, which /health calls
degraded for ``service.lost_window_s`` (``--set service.lost_window_s=60`` for a short soak).

Every ``--every`` seconds (default 5) the script scrapes ``/metrics`` and parses it with
``prometheus_client``'s own parser, reads ``/health``, and samples the run's resident memory (VmRSS, and
the interval's peak VmHWM, reset after each reading). At the end it sends SIGTERM and checks:

* the run exited 0 within ``--term-s``;
* every reset was counted: the source's sequences = 2 + N (the metrics' ``bf_epic_source_sequences``);
* /health was go, then left go while the sender was stopped, and came back to go;
* memory flat: the last interval peak <= 1.1 x the first after the warm-up (the first 20% of samples);
* the output budget held: the folder's bytes (second half) at most 1.1 x (``keep_gb`` + what the run writes
  in the budget's settle time and sweep interval: files that young are never deleted), deletions counted.

Prints a table and writes JSON (``--json``); exit status 1 when a check fails. usage:
    python tools/bench/soak_service.py [--minutes 60] [--rate 0.004] [--every 5] [--json PATH] [--synthetic NCHAN]
                                       [--yaml pipelines/lwasv_udp_live.yaml] [--file CAPTURE] [--set K=V ...]

The default rate (0.4% of real time, 100 samples a second of the LWA-SV demo file's one sample) is what a
2-core machine's CPU imager and Python sender sustain; the stream is replayed slower than real time on
purpose, so ``service.behind`` is 0 (a slow stream is not "behind") and the reordering window is 0.002 s
of data (50 samples, as 0.05 s is at real time). Interference flagging is off: one time sample looped is
not noise, and its spectral kurtosis rightly flags every sample.
"""
from __future__ import annotations

import argparse
import json
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import REPO, bf_epic_command, machine, utc_now, write_json  # noqa: E402
from soak_transient import rss_mb  # noqa: E402

from bf_epic_blocks.pipeline.runner import BUDGET_EVERY_S  # noqa: E402
from bf_epic_blocks.service.budget import OutputBudget  # noqa: E402

DEMO = REPO.parent / "shared" / "data" / "lwa" / "lwasv-adp-tbf.dat"


def free_port(kind=socket.SOCK_STREAM):
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def synthetic_capture(path, nchan, ntime=25):
    """A TBF capture of LWA-SV's 256 stands: ``nchan`` channels from channel 1980 (49.5 MHz), ``ntime``
    samples of uniform 4-bit noise (seed 1), the demo file's time (2015-11-13)."""
    from bf_epic_blocks.conventions import FS_HZ
    from bf_epic_blocks.io.tbf import write_tbf
    data = np.random.default_rng(1).integers(0, 256, size=(ntime, nchan, 256, 2), dtype=np.uint8)
    write_tbf(path, data, 1980, 1447376362 * FS_HZ, frame_id=1)
    return path


def resident_by_mapping(pid, top=12):
    """{mapping name: resident MB} of the ``top`` largest, from ``/proc/<pid>/smaps`` (a shared library, a
    device file, ``[heap]``, ``[anon]`` for the anonymous rest), so that a resident set that grows says
    what grew; {} where smaps cannot be read."""
    by = {}
    name = None
    try:
        with open(f"/proc/{pid}/smaps") as fh:
            for line in fh:
                head = line.split(None, 5)
                if len(head) >= 5 and "-" in head[0] and not head[0].endswith(":"):
                    name = head[5].strip() if len(head) == 6 else "[anon]"
                elif head and head[0] == "Rss:" and name is not None:
                    by[name] = by.get(name, 0) + int(head[1])
    except (OSError, ValueError, IndexError):
        return {}
    big = sorted(by.items(), key=lambda kv: -kv[1])[:top]
    return {Path(k).name if k.startswith("/") else k: round(v / 1024, 1) for k, v in big}


def scrape(url):
    """(metrics {name: value} of the unlabelled samples, health JSON) or (None, None) while it does not answer."""
    from prometheus_client.parser import text_string_to_metric_families
    try:
        with urllib.request.urlopen(url + "/metrics", timeout=5) as r:
            text = r.read().decode()
    except OSError:
        return None, None
    metrics = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            if not s.labels:
                metrics[s.name] = s.value
    try:
        with urllib.request.urlopen(url + "/health", timeout=5) as r:
            health = json.loads(r.read().decode())
    except urllib.error.HTTPError as e:       # /health answers 503 with its JSON when down
        health = json.loads(e.read().decode())
    except OSError:
        health = None
    return metrics, health


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--rate", type=float, default=0.004, help="x real time")
    ap.add_argument("--every", type=float, default=5.0, help="seconds between scrapes")
    ap.add_argument("--pause-s", type=float, default=30.0, help="seconds the sender stops for")
    ap.add_argument("--shift-s", type=float, default=3600.0, help="each reset's jump in time base")
    ap.add_argument("--keep-gb", type=float, default=0.02, help="output.keep_gb")
    ap.add_argument("--resets", type=int, default=1,
                    help="mid-stream jumps to a new time base in the last 30%% of the time (default 1)")
    ap.add_argument("--drop", type=float, default=0.0,
                    help="fraction of the second phase's packets not sent (frames missing: /health degraded for "
                         "service.lost_window_s)")
    ap.add_argument("--term-s", type=float, default=60.0, help="seconds SIGTERM may take")
    ap.add_argument("--yaml", default=str(REPO / "pipelines" / "lwasv_udp_live.yaml"))
    ap.add_argument("--file", default=str(DEMO), help="the capture replayed")
    ap.add_argument("--synthetic", type=int, metavar="NCHAN",
                    help="replay instead a noise capture of NCHAN channels (a multiple of 12; 792 is the whole LWA-SV "
                         "band) and 25 time samples of LWA-SV's 256 stands, written to the work folder")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--workdir")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    work = Path(args.workdir or tempfile.mkdtemp(prefix="soak_service_"))
    work.mkdir(parents=True, exist_ok=True)
    if args.synthetic:
        args.file = str(synthetic_capture(work / "synthetic.tbf", args.synthetic))
    out = work / "out"
    http, udp = free_port(), free_port(socket.SOCK_DGRAM)
    url = f"http://127.0.0.1:{http}"
    sets = [f"service.listen=127.0.0.1:{http}", "service.behind=0", "service.no_data_s=10", "service.min_free_gb=0",
            f"source.port={udp}", "source.sequences=0", "source.idle_timeout_s=5", "source.start_timeout_s=600",
            # the reordering window in samples is what it is at real time (50 of them): 0.5 s at 0.4%
            "source.buffer_s=0.002",
            # one time sample looped is not noise: spectral kurtosis rightly flags all of it
            "flagging.enabled=false",
            "imager.grid.size=16", "imager.accumulate_frames=100", "source.gulp_nframe=100",
            f"output.dir={out}", f"output.keep_gb={args.keep_gb}", "output.fits=true", "output.png=true"] + args.set
    cmd = bf_epic_command() + ["run", args.yaml, "--no-progress"] + [a for s in sets for a in ("--set", s)]
    log = open(work / "run.log", "w")
    run = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=REPO)
    total = args.minutes * 60.0
    from bf_epic_blocks.io.formats import detect_format
    from bf_epic_blocks.io.udp import packet_format
    fmt = packet_format(detect_format(args.file))
    frames, tts = fmt.file_frames(args.file)
    lay = fmt.probe(bytes(frames[0]), frames.shape[1])
    samples_per_pass = len(np.unique(tts))    # the demo file holds one time sample
    sps = lay.chan_bw_hz * args.rate / samples_per_pass   # passes a wall second

    def send(seconds, shift, drop=0.0):
        n = max(1, int(round(seconds * sps)))
        return subprocess.run(bf_epic_command() + ["replay", args.file, "--to", f"127.0.0.1:{udp}", "--rate",
                                                   str(args.rate), "--loop", str(n), "--shift-s", str(shift),
                                                   "--drop", str(drop), "--seed", "1", "-q"],
                              cwd=REPO, capture_output=True, text=True)

    rows, stop = [], threading.Event()

    def watch():
        t0 = time.monotonic()
        while not stop.is_set():
            m, h = scrape(url)
            now, peak = rss_mb(run.pid)
            rows.append({"t_s": round(time.monotonic() - t0, 1), "rss_mb": now, "peak_mb": peak,
                         "mappings": resident_by_mapping(run.pid),
                         "health": None if h is None else h.get("status"),
                         "reasons": None if h is None else h.get("reasons"), "metrics": m or {}})
            stop.wait(args.every)
    th = threading.Thread(target=watch, daemon=True)
    th.start()
    t_start = time.monotonic()
    deadline = t_start + 120
    while scrape(url)[0] is None and time.monotonic() < deadline and run.poll() is None:
        time.sleep(0.5)
    phases = []
    a = 0.4 * total
    phases.append(("stream", send(a, 0.0)))
    time.sleep(args.pause_s)                                  # the sender stopped
    b = 0.7 * total - (time.monotonic() - t_start)
    phases.append(("reset after a silence", send(max(b, 60.0), args.shift_s, args.drop)))
    for k in range(args.resets):                              # mid-stream jumps, evenly over the rest
        c = (total - (time.monotonic() - t_start)) / (args.resets - k)
        phases.append((f"reset mid-stream {k + 1}", send(max(c, 30.0), (2 + k) * args.shift_s + 0.5)))
    time.sleep(2 * args.every)
    t_term = time.monotonic()
    run.send_signal(signal.SIGTERM)
    try:
        rc = run.wait(timeout=args.term_s)
    except subprocess.TimeoutExpired:
        run.kill()
        rc = None
    term_s = time.monotonic() - t_term
    stop.set()
    th.join()
    log.close()
    # ------------------------------------------------------------------ checks
    seen = [r for r in rows if r["metrics"]]
    last = seen[-1]["metrics"] if seen else {}
    seqs = last.get("bf_epic_source_sequences")
    health = [r["health"] for r in seen]
    left = next((i for i, h in enumerate(health) if h not in (None, "go")), None)
    back = left is not None and "go" in health[left:]
    peaks = [r["peak_mb"] for r in seen if r["peak_mb"]]
    warm = max(1, len(peaks) // 5)
    first, final = (peaks[warm], max(peaks[-3:])) if len(peaks) > warm + 3 else (None, None)
    # the budget never deletes a file younger than its settle time and sweeps every BUDGET_EVERY_S: the folder
    # may hold keep_gb and what the run writes in that time (the rate from the second half's bytes written)
    bud = [(r["t_s"], r["metrics"]["bf_epic_budget_folder_bytes"],
            r["metrics"]["bf_epic_budget_folder_bytes"] + r["metrics"].get("bf_epic_budget_deleted_bytes", 0.0))
           for r in seen if "bf_epic_budget_folder_bytes" in r["metrics"]]
    folder = [b[1] for b in bud]
    half = bud[len(bud) // 2:]
    rate = (half[-1][2] - half[0][2]) / (half[-1][0] - half[0][0]) if len(half) > 1 and half[-1][0] > half[0][0] else 0.0
    allowed = args.keep_gb * 1e9 + rate * (OutputBudget(work).settle_s + BUDGET_EVERY_S)
    deleted = last.get("bf_epic_budget_deleted_files", 0)
    checks = {
        "exit 0 after SIGTERM": rc == 0,
        f"{2 + args.resets} sequences ({1 + args.resets} resets) counted": seqs == 2 + args.resets,
        "health left go and came back": bool(back),
        "memory flat (last peak <= 1.1 x first)": first is not None and final <= 1.1 * first,
        "output budget held": bool(folder) and max(folder[len(folder) // 2:]) <= 1.1 * allowed and deleted > 0,
        "replays ended cleanly": all(p.returncode == 0 for _, p in phases),
    }
    on_gpu = "device=gpu" in [kv.replace(" ", "") for kv in args.set]
    res = {"benchmark": "soak_service", "date": utc_now(), "machine": machine("gpu" if on_gpu else "cpu"),
           "minutes": args.minutes,
           "rate": args.rate, "scrapes": len(seen), "sequences": seqs, "health": health,
           "left_go_reasons": seen[left]["reasons"] if left is not None else None,
           "rss_first_peak_mb": first, "rss_last_peak_mb": final, "term_s": round(term_s, 2), "exit": rc,
           "budget_folder_bytes_max_second_half": max(folder[len(folder) // 2:]) if folder else None,
           "budget_write_rate_bytes_per_s": rate, "budget_allowed_bytes": allowed,
           "budget_deleted_files": deleted, "keep_gb": args.keep_gb,
           "phases": [{"phase": n, "rc": p.returncode, "out": (p.stdout + p.stderr).strip()[-300:]} for n, p in phases],
           "final_metrics": {k: v for k, v in last.items() if k.startswith(("bf_epic_source", "bf_epic_imager",
                                                                         "bf_epic_budget", "bf_epic_health"))},
           "checks": checks, "samples": [{**{k: r[k] for k in ("t_s", "rss_mb", "peak_mb", "health", "reasons")},
                        "folder_bytes": r["metrics"].get("bf_epic_budget_folder_bytes"),
                        "mappings_mb": r["mappings"],
                        # where the resident set goes (the service's own figures: malloc, CuPy's pools)
                        "memory": {k[len("bf_epic_memory_"):]: v for k, v in r["metrics"].items()
                                   if k.startswith("bf_epic_memory_")}} for r in rows]}
    print(f"# soak: {args.minutes:g} min at {args.rate:g}x real time, {len(seen)} scrapes, workdir {work}")
    print(f"  sequences {seqs}; health {' -> '.join(h for i, h in enumerate(health) if i == 0 or h != health[i - 1])}")
    print(f"  memory: first peak {first} MB, last {final} MB; SIGTERM {term_s:.1f} s, exit {rc}")
    print(f"  budget: folder <= {res['budget_folder_bytes_max_second_half']} bytes (keep {args.keep_gb} GB; allowed "
          f"{res['budget_allowed_bytes'] / 1e9:.3f} GB with {res['budget_write_rate_bytes_per_s'] / 1e6:.1f} MB/s written), "
          f"{deleted:g} files deleted")
    for k, v in checks.items():
        print(f"  {'ok  ' if v else 'FAIL'} {k}")
    if args.json:
        write_json(args.json, res)
        print(f"wrote {args.json}")
    return 0 if all(checks.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
