"""Live capture through `bf-epic run`, timed and checked against the file path.

Two cases, each run as an operator would: `bf-epic run pipelines/lwasv_udp_live.yaml` in its own
process, a sender in this one that starts once the run logs that it listens.

* ``table`` (issue 23's table): 2,048 samples x 24 channels of LWA-SV TBF (random 4-bit samples,
  written with io.tbf.write_tbf), 256-sample gulps, one image per 256 samples, a 32x32 grid, on the
  CPU; paced at 200 and 20,000 packets/s, in each runtime (the package's own and real Bifrost when
  it imports). Images equal to the file path's are counted; the run summary's losses are listed.
* ``rate``: one LWA-SV tuning's F-engine stream at real time, 16 ROACH boards x 25,000 chips packets
  per second of ``--nchan`` channels each (Bifrost's capture when Bifrost is the runtime), or
  24-channel TBF at 2 x 25,000 packets/s (the Python receiver), for ``--seconds`` of data on
  ``--device``. Printed: packets sent and the sender's pace, kernel drops, the capture's counts, the
  images written against those expected, the imager's steady real-time factor (its own per-gulp
  timing) and the process wall.

Senders: Bifrost's own C packet writer (``bifrost.packet_writer.UDPTransmit``) when Bifrost imports,
else `bf_epic_blocks.io.udp.replay` (TBF only, tens of thousands of packets/s at most).

    python tools/bench/bench_live.py table [--json docs/bench/live_table_cpu.json]
    python tools/bench/bench_live.py rate --format chips --nchan 132 --seconds 10 --device gpu [--json ...]
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

import numpy as np

from bf_epic_blocks.io.tbf import FS_HZ, write_tbf

from benchlib import REPO, bf_epic_command, machine, write_json


LIVE_YAML = REPO / "pipelines" / "lwasv_udp_live.yaml"
FILE_YAML = REPO / "pipelines" / "lwasv_tbf_allsky.yaml"
SYNC = 1_700_000_000


def have_bifrost():
    try:
        import bifrost.packet_writer  # noqa: F401
        return True
    except Exception:
        return False


# ---------------------------------------------------------------------------------------------- senders
def bifrost_sender(fmt, nstand, nchan, chan0):
    """A function send(data uint8 (n, nsrc, payload), seq0) through Bifrost's UDPTransmit, and nsrc."""
    import bifrost as bf
    from bifrost.address import Address
    from bifrost.packet_writer import HeaderInfo, UDPTransmit
    from bifrost.udp_socket import UDPSocket
    state = {}

    def open_(port):
        sock = UDPSocket()
        sock.connect(Address("127.0.0.1", port))
        desc = HeaderInfo()
        if fmt == "chips":
            udt = UDPTransmit(f"chips_{nchan}", sock)
            desc.set_nsrc(nstand // 16)
            desc.set_nchan(nchan)
            desc.set_chan0(chan0)
            desc.set_tuning(0)
        else:
            udt = UDPTransmit("tbf", sock)
            desc.set_nsrc(nstand)
        state.update(sock=sock, udt=udt, desc=desc)

    def prepare(payload):
        """The payloads as a Bifrost ci4 array (slices of it are sent without a copy)."""
        arr = bf.ndarray(shape=payload.shape, dtype="ci4", space="system")
        arr.view(np.uint8)[...] = payload
        return arr

    def send(arr, seq0, seq_step, src0, src_step):
        state["udt"].send(state["desc"], seq0, seq_step, src0, src_step, arr)

    return open_, prepare, send


def tbf_payloads(data):
    """(ntime, nchan, nstand, 2) uint8 -> (ntime, nblock, 12 * nstand * 2): TBF frame payloads."""
    n, nchan, nstand, _ = data.shape
    return np.ascontiguousarray(data.reshape(n, nchan // 12, 12 * nstand * 2))


def chips_payloads(data):
    n, nchan, nstand, _ = data.shape
    return np.ascontiguousarray(data.reshape(n, nchan, nstand // 16, 32).transpose(0, 2, 1, 3)
                                .reshape(n, nstand // 16, nchan * 32))


# ---------------------------------------------------------------------------------------------- runs
def start_run(yml, sets, env_extra, log_path, summary):
    cmd = [*bf_epic_command(), "run", str(yml), "--no-progress", "--summary-json", str(summary)]
    for s in sets:
        cmd += ["--set", s]
    env = dict(os.environ, **env_extra)
    err = open(log_path, "w+")
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, text=True, env=env, cwd=REPO)
    port = None
    deadline = time.monotonic() + 120
    while port is None and time.monotonic() < deadline and p.poll() is None:
        time.sleep(0.05)
        err.seek(0)
        m = re.search(r"udp 127\.0\.0\.1:(\d+) \[\w+\]: listening", err.read())
        port = int(m.group(1)) if m else None
    if port is None:
        p.kill()
        err.seek(0)
        raise RuntimeError(f"bf-epic run did not listen:\n{err.read()[-3000:]}")
    return p, port, t0, err


def finish_run(p, t0, err, summary, timeout=600):
    p.wait(timeout)
    wall = time.perf_counter() - t0
    err.seek(0)
    text = err.read()
    if p.returncode != 0:
        raise RuntimeError(f"bf-epic run failed ({p.returncode}):\n{text[-3000:]}")
    return wall, json.loads(Path(summary).read_text()), text


def fits_arrays(outdir):
    from astropy.io import fits
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for f in sorted(Path(outdir).glob("*.fits")):
            with fits.open(f) as h:
                out.append(h[0].data.copy())
    return out


def steady_rate(summary, data_s_per_gulp):
    """The imager's real-time factor over its gulps after the first (the run summary's per-block timing,
    our runtime only; None under real Bifrost, which keeps no such timing)."""
    for name, bt in (summary.get("blocks") or {}).items():
        if "DFTImager" in name and bt.get("ngulp", 0) > 1 and bt.get("last_data_s") is not None:
            span = bt["last_data_s"] - bt["first_data_s"]
            return (bt["ngulp"] - 1) * data_s_per_gulp / span if span > 0 else None
    return None


def case_table(args):
    tmp = Path(tempfile.mkdtemp(prefix="bf_live_"))
    ntime, nchan, gulp = 2048, 24, 256
    data = np.random.default_rng(1).integers(0, 256, (ntime, nchan, 256, 2), dtype=np.uint8)
    rec = tmp / "rec.tbf"
    write_tbf(rec, data, 1200, SYNC * FS_HZ, frame_id=1)
    common = ["station.name=lwasv", "output.png=false", "imager.grid.size=32", f"source.gulp_nframe={gulp}",
              f"imager.accumulate_frames={gulp}", "device=cpu"]
    ref = tmp / "ref"
    subprocess.run([*bf_epic_command(), "run", str(FILE_YAML), "--no-progress", "--set", f"source.path={rec}",
                    "--set", f"output.dir={ref}", *sum((["--set", c] for c in common), [])],
                   check=True, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                   env=dict(os.environ, BF_EPIC_RUNTIME="builtin"))
    want = fits_arrays(ref)
    runtimes = ["builtin"] + (["bifrost"] if have_bifrost() else [])
    rows = []
    for rt in runtimes:
        for pps in args.paces:
            out = tmp / f"live_{rt}_{pps}"
            summary = tmp / f"sum_{rt}_{pps}.json"
            env = {"BF_EPIC_RUNTIME": rt}
            p, port, t0, err = start_run(LIVE_YAML, common + ["source.port=0", f"output.dir={out}",
                                                              "source.idle_timeout_s=1.0"],
                                         env, tmp / f"log_{rt}_{pps}.txt", summary)
            sent, sender = send_tbf(rec, data, port, pps)
            wall, summ, log_text = finish_run(p, t0, err, summary)
            got = fits_arrays(out)
            equal = sum(np.array_equal(a, b, equal_nan=True) for a, b in zip(got, want))
            zero = sum(not np.any(np.nan_to_num(a)) for a in got)
            tb = summ.get("udp") or summ.get("tbf") or {}
            row = dict(runtime=rt, pace_pkt_s=pps, sender=sender, packets_sent=sent, images=len(got),
                       images_expected=len(want), equal_to_file=int(equal), zero_images=int(zero),
                       frames_skipped=summ.get("frames_skipped"), samples_overflow=tb.get("samples_overflow"),
                       frames_missing=tb.get("frames_missing"), kernel_drops=tb.get("kernel_drops"),
                       wall_s=round(wall, 2), failed="AssertionError" in log_text)
            rows.append(row)
            print(row, flush=True)
    return rows


def send_tbf(rec, data, port, pps):
    """Send the recording's frames at ``pps`` packets/s; Bifrost's TBF writer when it imports."""
    if have_bifrost():
        open_, prepare, send = bifrost_sender("tbf", 256, data.shape[1], 1200)
        open_(port)
        pay = prepare(tbf_payloads(data))
        nblock = pay.shape[1]
        t0 = time.perf_counter()
        for t in range(pay.shape[0]):
            due = t * nblock / pps - (time.perf_counter() - t0)
            if due > 0:
                time.sleep(due)
            send(pay[t:t + 1], SYNC * FS_HZ + t * 7840, 7840, 1200, 12)
        return pay.shape[0] * nblock, "bifrost UDPTransmit('tbf')"
    from bf_epic_blocks.io.udp import replay
    r = replay(rec, "127.0.0.1", port, rate=pps / (2 * 25_000))
    return r.sent, "bf-epic replay"


def case_rate(args):
    """One tuning's stream at real time (see the module docstring)."""
    tmp = Path(tempfile.mkdtemp(prefix="bf_live_rate_"))
    nchan = args.nchan
    nstand, bw = 256, 25e3
    block = 1000  # spectra of random data, sent over and over (new sequence numbers each time)
    data = np.random.default_rng(2).integers(0, 256, (block, nchan, nstand, 2), dtype=np.uint8)
    nspec = int(round(args.seconds * bw))
    acc = args.accumulate
    sets = ["station.name=lwasv", "output.png=false", f"imager.grid.size={args.grid}",
            f"source.gulp_nframe={args.gulp}", f"imager.accumulate_frames={acc}", f"device={args.device}",
            "source.port=0", f"output.dir={tmp / 'out'}", "source.idle_timeout_s=1.0", f"source.format={args.format}",
            f"imager.precision={args.precision}", f"imager.method={args.method}"]
    if args.core is not None:
        sets.append(f"source.core={args.core}")
    if args.rcvbuf_mb:
        sets.append(f"source.rcvbuf_mb={args.rcvbuf_mb}")
    if args.format == "chips":
        sets.append(f"source.sync_time={SYNC}")
        pay = chips_payloads(data)
        pkt_per_spec = nstand // 16
    else:
        pay = tbf_payloads(data)
        pkt_per_spec = nchan // 12
    summary = tmp / "summary.json"
    p, port, t0, err = start_run(LIVE_YAML, sets, {}, tmp / "log.txt", summary)
    time.sleep(args.settle)
    batch = args.batch
    assert block % batch == 0, "--batch must divide the 1,000-spectrum data block"
    # Bifrost's writer hands a call's packets to one sendmmsg, which takes at most 1,024 (UIO_MAXIOV)
    # and Bifrost does not send the rest
    assert batch * pkt_per_spec <= 1024, f"--batch {batch}: {batch * pkt_per_spec} packets per call > 1024"
    # Several senders, each its own writer and socket with a share of the sources (as the F-engine's
    # boards are separate senders): on loopback the sender's system call also delivers the packet,
    # so one sending thread alone cannot reach the stations' packet rates.
    nsnd = max(1, min(args.senders, pay.shape[1]))
    cuts = np.linspace(0, pay.shape[1], nsnd + 1).astype(int)
    ts = time.perf_counter()
    stats = []

    def sender(k):
        a, b = int(cuts[k]), int(cuts[k + 1])
        open_, prepare, send = bifrost_sender(args.format, nstand, nchan, 1200)
        open_(port)
        mine = prepare(np.ascontiguousarray(pay[:, a:b]))
        sent, late = 0, 0.0
        for s0 in range(0, nspec, batch):
            due = s0 / bw - (time.perf_counter() - ts)
            if due > 0:
                time.sleep(due)
            else:
                late = max(late, -due)
            i0 = s0 % block
            n = min(batch, nspec - s0, block - i0)
            if args.format == "chips":
                send(mine[i0:i0 + n], s0 + 1, 1, a, 1)  # chips seq is 1-based; board = a + j
            else:
                send(mine[i0:i0 + n], SYNC * FS_HZ + s0 * 7840, 7840, 1200 + 12 * a, 12)
            sent += n * (b - a)
        stats.append((sent, late))

    threads = [threading.Thread(target=sender, args=(k,)) for k in range(nsnd)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    sent = sum(x[0] for x in stats)
    late = max(x[1] for x in stats)
    send_s = time.perf_counter() - ts
    wall, summ, text = finish_run(p, t0, err, summary)
    if args.log_dir:
        os.makedirs(args.log_dir, exist_ok=True)
        Path(args.log_dir, f"run_{args.format}_{nchan}ch.log").write_text(text)
    tb = summ.get("udp") or summ.get("tbf") or {}
    images = summ.get("images")
    row = dict(format=args.format, device=args.device, nchan=nchan, seconds=args.seconds, senders=nsnd, packets_sent=sent,
               packets_per_s=round(sent / send_s), sender_pace=round(args.seconds / send_s, 3),
               sender_max_late_s=round(late, 4), images=images, images_expected=nspec // acc,
               capture=tb, frames_skipped=summ.get("frames_skipped"),
               imager_steady_x=steady_rate(summ, args.gulp / bw), process_wall_s=round(wall, 2),
               blocks=summ.get("blocks"))
    print({k: v for k, v in row.items() if k != "blocks"}, flush=True)
    return [row]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("case", choices=("table", "rate"))
    ap.add_argument("--paces", type=int, nargs="+", default=[200, 20000], help="table: packets/s")
    ap.add_argument("--format", choices=("chips", "tbf"), default="chips")
    ap.add_argument("--nchan", type=int, default=132)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--device", default="gpu")
    ap.add_argument("--precision", default="fp16")
    ap.add_argument("--method", default="covariance")
    ap.add_argument("--grid", type=int, default=64)
    ap.add_argument("--gulp", type=int, default=2500)
    ap.add_argument("--accumulate", type=int, default=2500)
    ap.add_argument("--rcvbuf-mb", type=float, help="rate: source.rcvbuf_mb (socket receive buffer asked for)")
    ap.add_argument("--core", type=int, help="rate: bind Bifrost's capture thread to this core (source.core)")
    ap.add_argument("--senders", type=int, default=4, help="rate: sender threads (sources split between them)")
    ap.add_argument("--batch", type=int, default=50, help="rate: spectra per send call (2 ms; <= 1,024 packets)")
    ap.add_argument("--settle", type=float, default=2.0, help="rate: seconds between listening and sending")
    ap.add_argument("--log-dir", help="rate: keep the bf-epic run's log here")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    rows = case_table(args) if args.case == "table" else case_rate(args)
    out = dict(case=args.case, args=vars(args), machine=machine(args.device),
               date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), rows=rows)
    if args.json:
        write_json(args.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
