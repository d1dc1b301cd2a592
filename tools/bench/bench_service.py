"""The service under load: a pipeline's flowing real-time factor unwatched, and with N clients polling
its page and its metrics as fast as they are answered.

Each run is bench_wholeband's run of ``bf-epic run YAML --set service.listen=127.0.0.1:PORT`` (a
subprocess, timed from outside); the clients are threads of this process that start once the service
answers and poll ``/`` and ``/metrics`` (alternately) until the run ends. Runs alternate unwatched and
watched ``--repeat`` times; the medians are compared.

usage: python tools/bench/bench_service.py [--yaml pipelines/lwasv_sim_wholeband.yaml] [--device gpu]
                                           [--seconds 60] [--clients 200] [--interval-s 5] [--repeat 1]
                                           [--json PATH]

On a machine with few cores the clients take CPU from the pipeline (say so with the figure); the
issue's figure is for the GPU host.
"""
from __future__ import annotations

import argparse
import socket
import statistics
import sys
import threading
import time
import urllib.request
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import REPO, machine, utc_now, write_json  # noqa: E402


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def clients(url, n, stop, counts, interval_s=0.0):
    """``n`` threads polling ``url`` + '/' and '/metrics' until ``stop``, each waiting ``interval_s`` after
    each answer (0: as fast as they are answered); counts ok / failed requests and the slowest answer."""
    def one(i):
        paths = ("/", "/metrics")
        k = i
        while not stop.is_set():
            t0 = time.perf_counter()
            try:
                with urllib.request.urlopen(url + paths[k % 2], timeout=10) as r:
                    r.read()
                counts["ok"] += 1
                counts["slowest_s"] = max(counts["slowest_s"], time.perf_counter() - t0)
            except OSError:
                if not stop.is_set():              # not the run's end closing the service under them
                    counts["failed"] += 1
                time.sleep(0.1)
            k += 1
            if interval_s:
                stop.wait(interval_s)
    th = [threading.Thread(target=one, args=(i,), daemon=True) for i in range(n)]
    for t in th:
        t.start()
    return th


def run_once(args, n_clients):
    import bench_wholeband as bw
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    stop, counts = threading.Event(), {"ok": 0, "failed": 0, "slowest_s": 0.0}

    def wait_then_poll():
        t0 = time.monotonic()
        while not stop.is_set() and time.monotonic() - t0 < 600:
            try:
                urllib.request.urlopen(url + "/health", timeout=2).read()
                break
            except OSError:
                time.sleep(0.2)
        if n_clients and not stop.is_set():
            clients(url, n_clients, stop, counts, args.interval_s)
    waiter = threading.Thread(target=wait_then_poll, daemon=True)
    waiter.start()
    ns = argparse.Namespace(yaml=Path(args.yaml), device=args.device, seconds=args.seconds,
                            set=[f"service.listen=127.0.0.1:{port}"] + args.set, sample_s=5.0)
    try:
        row = bw.run(ns)["run"]
    finally:
        stop.set()
    return {"clients": n_clients, "interval_s": args.interval_s, "rt_flowing": row["rt_flowing"], "wall_s": row["wall_s"], **counts}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--yaml", default=str(REPO / "pipelines" / "lwasv_sim_wholeband.yaml"))
    ap.add_argument("--device", default="gpu")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--clients", type=int, default=200)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--interval-s", type=float, default=5.0,
                    help="seconds each client waits between requests (5: a page left open and a Prometheus "
                         "scrape; 0: as fast as answered)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    rows = []
    for _ in range(args.repeat):
        for n in (0, args.clients):
            r = run_once(args, n)
            rows.append(r)
            print(f"{n:4d} clients: x{r['rt_flowing']:.3f} real time once flowing, {r['ok']} requests answered, "
                  f"{r['failed']} failed, slowest {r['slowest_s']:.2f} s", flush=True)
    base = statistics.median(r["rt_flowing"] for r in rows if r["clients"] == 0)
    load = statistics.median(r["rt_flowing"] for r in rows if r["clients"] == args.clients)
    change = load / base - 1.0
    print(f"{args.clients} clients change the flowing real-time factor by {100 * change:+.1f}%")
    if args.json:
        write_json(args.json, {"benchmark": "bench_service", "date": utc_now(), "machine": machine(args.device),
                               "yaml": args.yaml, "seconds": args.seconds, "rows": rows, "change": change})
        print(f"wrote {args.json}")
    return rows


if __name__ == "__main__":
    main()
