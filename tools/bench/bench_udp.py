"""Loopback live-capture throughput: replay generated TBF captures at increasing rates into a UDPCapture.

For each layout and asked rate R (x real time) it prints and records: the rate the sender reached,
packets sent / received, packets lost in the kernel (sent - received), frames zero-filled, and the
packet and byte rates. "Sustained" = every packet received and the sender within 5% of R. Sender and
receiver run in this one process (separate threads, as ``bf-epic replay`` and a pipeline would on
one machine: the sender in a second process), so on a small machine they share its cores.

    python tools/bench/bench_udp.py [--seconds 0.2] [--json bench_udp.json]
"""
from __future__ import annotations

import argparse
import os
import tempfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from bf_epic_blocks.io.tbf import FRAME_KINDS, FS_HZ, write_tbf
from bf_epic_blocks.io.udp import UDPCapture, replay

from benchlib import machine, utc_now, write_json

LAYOUTS = {  # name: (frame id, stands, channels)
    "LWA-SV ADP, 256 stands, 60 ch": (1, 256, 60),
    "LWA-NA NDP, 64 stands, 84 ch": (5, 64, 84),
}


def one(path, rate, gulp=1024):
    cap = UDPCapture("127.0.0.1", 0, "tbf", gulp_nframe=gulp, buffer_s=0.01, idle_timeout_s=0.5,
                     start_timeout_s=10, max_sequences=1, log_interval_s=None)
    got = {"samples": 0}

    def consume():
        while True:
            ev = cap.next_event(1.0)
            if ev is None or ev[0] in ("end", "closed"):
                return
            if ev[0] == "data":
                got["samples"] += ev[2].shape[0]

    th = threading.Thread(target=consume)
    cap.start()
    th.start()
    with ProcessPoolExecutor(1) as ex:  # the sender in its own process, as `bf-epic replay` would be
        res = ex.submit(replay, path, "127.0.0.1", cap.port, rate=rate).result()
    th.join(30)
    cap.close()
    s = cap.stats
    return dict(rate_asked=rate, rate_reached=res.rate_achieved, sent=res.sent, received=s["packets"],
                lost=res.sent - s["packets"], zero_filled=s["frames_missing"], samples=s["samples"],
                overflowed=s["samples_overflow"], wall_s=res.wall_s, pkt_per_s=res.sent / res.wall_s,
                mb_per_s=res.sent * os.path.getsize(path) / res.nframe / res.wall_s / 1e6)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=0.2, help="seconds of data per capture (default 0.2)")
    ap.add_argument("--rates", default="0.05,0.1,0.2,0.3,0.5,1,2", help="comma-separated rates to try")
    ap.add_argument("--json", default="bench_udp.json")
    args = ap.parse_args(argv)
    rates = [float(r) for r in args.rates.split(",")]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, (fid, nstand, nchan) in LAYOUTS.items():
            bw = FRAME_KINDS[fid][2]
            ntime = int(args.seconds * bw)
            data = np.random.default_rng(0).integers(0, 256, (ntime, nchan, nstand, 2), dtype=np.uint8)
            path = os.path.join(tmp, "cap.tbf")
            nframe = write_tbf(path, data, 1200, 1_700_000_000 * FS_HZ, frame_id=fid)
            real_pkt_s = nframe / args.seconds
            print(f"\n{name}: {nframe} frames of {os.path.getsize(path) // nframe} B = {args.seconds} s of data; "
                  f"real time is {real_pkt_s:,.0f} packets/s")
            print(f"{'asked':>6} {'reached':>8} {'sent':>7} {'recv':>7} {'lost':>6} {'0-fill':>6} "
                  f"{'pkt/s':>9} {'MB/s':>7}  sustained")
            for r in rates:
                row = one(path, r)
                row.update(layout=name, frames=nframe, real_time_pkt_per_s=real_pkt_s)
                row["sustained"] = bool(row["lost"] == 0 and row["rate_reached"] >= 0.95 * r)
                rows.append(row)
                print(f"{r:6.2f} {row['rate_reached']:8.3f} {row['sent']:7d} {row['received']:7d} {row['lost']:6d} "
                      f"{row['zero_filled']:6d} {row['pkt_per_s']:9,.0f} {row['mb_per_s']:7.1f}  "
                      f"{'yes' if row['sustained'] else 'no'}")
                time.sleep(0.2)
            ok = [x["rate_asked"] for x in rows if x["layout"] == name and x["sustained"]]
            print(f"max sustained rate: {max(ok) if ok else 0:g} x real time")
    info = dict(date=utc_now(), machine=machine("cpu"), seconds=args.seconds, rows=rows)
    write_json(args.json, info)


if __name__ == "__main__":
    main()
