"""The ``bf-epic`` command line: validate, plan and run pipeline YAMLs.

    bf-epic validate FILE [--set key=value ...]
    bf-epic plan FILE [--set key=value ...]
    bf-epic run FILE [--set key=value ...] [--no-progress] [-v|-q]
    bf-epic calibrate FILE [-o TABLE.npz] [--set key=value ...]
    bf-epic batch FILE --inputs TBF [TBF ...] [--scheduler tcp://HOST:PORT] [--workers N] [--set ...]
    bf-epic replay FILE --to 127.0.0.1:PORT [--rate R] [--drop F] [--seed N] [--format auto|tbf|tbx]
                   [--loop N] [--shift-s S]
    bf-epic movie FOLDER [-o MOVIE.mp4] [--fps 10]

Errors in the YAML (unknown keys, wrong types, missing files, impossible parameters) are reported
with the key's dotted path and exit status 2; errors while running exit with status 1 and one line
naming the block and the problem (``-v`` shows the traceback). ``batch`` runs ``run`` on every input
file x channel block on a Dask cluster (:mod:`.batch`), prints a summary table and exits with
status 1 when any task failed.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

from .. import __version__

log = logging.getLogger("bf_epic_blocks")


def build_parser():
    p = argparse.ArgumentParser(prog="bf-epic", description="Exact wide-field E-field imaging pipelines "
                                "(LWA station metadata from LSL, Bifrost-style blocks).")
    p.add_argument("--version", action="version", version=f"bf-epic {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name, help_ in (("validate", "check a pipeline YAML and print the resolved configuration"),
                        ("plan", "print what the pipeline would do: pixels, antennas, operation counts, "
                                 "method, predicted real-time factor"),
                        ("run", "run the pipeline and write FITS/PNG outputs"),
                        ("calibrate", "solve antenna gains and health from the pipeline's source against a sky "
                                      "model (calibration.solve keys) and write a gains table that "
                                      "calibration.gains_table accepts, with a PNG"),
                        ("batch", "run the pipeline on many TBF files (one task per file x channel block) "
                                  "on a Dask distributed cluster; outputs in output.dir/<file stem>/")):
        s = sub.add_parser(name, help=help_, description=help_)
        s.add_argument("file", help="pipeline YAML (see pipelines/)")
        s.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                       help="override a key, e.g. --set imager.grid.size=128 (repeatable)")
        s.add_argument("-v", "--verbose", action="store_true", help="debug logging and tracebacks")
        s.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
        if name == "calibrate":
            s.add_argument("-o", "--output", metavar="TABLE.npz",
                           help="where the table goes (default: output.dir/<prefix>_gains.npz); its PNG beside it")
        if name == "run":
            s.add_argument("--serve", metavar="HOST:PORT",
                           help="serve metrics (/metrics), health (/health) and a status page (/) while it runs; "
                                "the YAML's service: section sets the rest (guide/service.md)")
        if name in ("run", "batch", "calibrate"):
            s.add_argument("--no-progress", action="store_true", help="no progress bar")
            s.add_argument("--summary-json", metavar="PATH", help="also write the run summary as JSON")
        if name == "batch":
            s.add_argument("--inputs", nargs="+", required=True, metavar="TBF", help="TBF files to image")
            s.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                           help="a running dask.distributed scheduler (default: a LocalCluster on 127.0.0.1)")
            s.add_argument("--workers", type=int, metavar="N",
                           help="worker processes of the LocalCluster (default: one per CPU core)")
        if name in ("validate", "plan"):
            s.add_argument("--json", action="store_true", help="print JSON instead of text")
    r = sub.add_parser("replay", help="send a capture file as UDP packets at R x real time (demos, tests)",
                       description="Send the frames of a TBF/TBX capture as UDP datagrams to a live source "
                                   "(source.kind: udp), paced by their time tags at R x real time, optionally "
                                   "dropping a reproducible fraction of them. Loopback only unless --allow-remote.")
    r.add_argument("file", help="capture file (TBF or TBX; sent as its own frames, or as chips/snap2 packets)")
    r.add_argument("--to", required=True, metavar="HOST:PORT", help="destination, e.g. 127.0.0.1:4015")
    r.add_argument("--rate", type=float, default=1.0, help="speed, x real time (default 1)")
    r.add_argument("--drop", type=float, default=0.0, metavar="F",
                   help="fraction of packets not sent: exactly round(F * frames), chosen by --seed")
    r.add_argument("--seed", type=int, default=None, help="seed of the drop choice (reproducible runs)")
    r.add_argument("--format", default="auto", choices=("auto", "tbf", "tbx", "chips", "snap2"),
                   help="packets to send: the file's own frames (auto: told by the first frame's id; tbf, "
                        "tbx), or its samples as the F-engines' streams: chips (ADP, 16 stands per packet; "
                        "the sync time used is printed, give it to the receiver as source.sync_time) or "
                        "snap2 (NDP, 64 inputs per packet)")
    r.add_argument("--loop", type=int, default=1, metavar="N",
                   help="passes over the file, each one's time tags continuing the last's (0: until interrupted; "
                        "a long stream from a short file, e.g. for a soak); TBF and TBX frames")
    r.add_argument("--shift-s", type=float, default=0.0, metavar="S",
                   help="seconds added to every time tag: sent after another replay, a jump in the stream's time "
                        "base as an F-engine reset makes (the receiver starts a new sequence); TBF and TBX frames")
    r.add_argument("--allow-remote", action="store_true", help="allow a non-loopback destination")
    r.add_argument("-v", "--verbose", action="store_true", help="debug logging and tracebacks")
    r.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    c = sub.add_parser("compile", help="compile the GPU kernels of simulated pipelines into the kernel store, "
                                       "once at install, so that a run starts within seconds",
                       description="Run each pipeline (a simulated source) on the GPU for a moment, its outputs "
                                   "thrown away, with CuPy's kernel cache pointed at the kernel store "
                                   "($BF_EPIC_KERNELS, default <prefix>/share/bf_epic_blocks/kernels). Every run on "
                                   "a GPU copies the store's kernels into CuPy's cache, so even a machine whose "
                                   "cache is empty starts without compiling. The kernels depend on the shapes "
                                   "(stands, channels, grid, DM range), not on the source: compile the simulated "
                                   "pipeline that matches a live one.")
    c.add_argument("files", nargs="+", metavar="file", help="pipeline YAMLs with simulated sources")
    c.add_argument("--seconds", type=float, help="seconds of data each is run for (default: long enough for its "
                                                  "periodic steps, a live solution, an integration, to run twice)")
    c.add_argument("--store", metavar="DIR", help="the store's folder (default: $BF_EPIC_KERNELS or "
                                                  "<prefix>/share/bf_epic_blocks/kernels)")
    c.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a key in every pipeline (repeatable)")
    c.add_argument("-v", "--verbose", action="store_true", help="debug logging and tracebacks")
    c.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    mv = sub.add_parser("movie", help="a day's LWATV views (output.oims.lwatv) as one MP4",
                        description="Join the LWATV PNGs of one day's folder (<output.dir>/lwatv/<MJD>/) into an "
                                    "H.264 MP4, in time order, leaving out 'nomovie+' views (the station's daily "
                                    "LWATV movie). Needs imageio-ffmpeg (the service extra).")
    mv.add_argument("folder", help="a folder of LWATV views, e.g. output/lwasv_udp_live/lwatv/60462")
    mv.add_argument("-o", "--output", help="the movie (default: <folder>.mp4 beside the folder)")
    mv.add_argument("--fps", type=float, default=10.0, help="frames a second (default 10)")
    mv.add_argument("-v", "--verbose", action="store_true", help="debug logging and tracebacks")
    mv.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    return p


def _movie(args):
    from pathlib import Path

    from ..io.movie import movie_frames, write_movie
    folder = Path(args.folder)
    out = Path(args.output) if args.output else folder.with_suffix(".mp4")
    try:
        res = write_movie(movie_frames(folder), out, fps=args.fps)
    except ImportError:
        print("bf-epic: movie needs imageio-ffmpeg: pip install 'bf_epic_blocks[service]'", file=sys.stderr)
        return 2
    except (OSError, ValueError) as e:
        print(f"bf-epic: movie failed: {e}", file=sys.stderr)
        return 2
    print(f"wrote {res['path']}: {res['frames']} frames of {res['width']} x {res['height']} at {args.fps:g} fps")
    return 0


def compile_seconds(cfg):
    """Seconds of data ``bf-epic compile`` runs ``cfg`` for: long enough for every periodic step to run twice
    (a live solution after the first compares with it; an integration's file is written), at least 3 s."""
    need = 3.0
    for tc in cfg.get("tunings") or [cfg]:
        out, solve = tc["output"], tc["calibration"].get("solve")
        for part in ("integrate", "oims"):
            if out.get(part):
                need = max(need, 2.0 * float(out[part]["seconds"]) + 1.0)
        if solve:
            need = max(need, float(solve["cadence_s"]) + float(solve["offset_s"]) + float(solve["integration_s"])
                       + float(solve["apply_delay_s"]) + 1.0)
    return need


def _names_gpu(path, overrides):
    """Whether the pipeline ``path`` with ``--set`` ``overrides`` runs on a GPU: its top-level ``device``
    after the overrides (:func:`~.config.apply_overrides` on the file read as YAML alone, so that a file the
    CPU's checks refuse is still read). False where the file cannot be read (load_config then names the
    problem)."""
    import yaml

    from .config import apply_overrides
    try:
        raw = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError):
        return False
    if not isinstance(raw, dict):
        return False
    apply_overrides(raw, overrides)
    return str(raw.get("device", "cpu")).strip().lower().startswith("gpu")


def _compile(args):
    """``bf-epic compile``: 0 when every pipeline ran, 1 when one failed, 2 for bad arguments."""
    import os
    import subprocess
    import tempfile
    import time

    from ..cuda import kernel_store
    from .config import ConfigError, load_config
    store = Path(args.store).expanduser() if args.store else kernel_store()
    cfgs, runs = [], []
    for f in args.files:
        try:
            # the pipeline is compiled on a GPU: read as it will run there (a YAML made for the CPU with a
            # GPU-only precision set is a GPU pipeline here), unless the file or --set names a GPU already
            overrides = [*args.overrides, *([] if _names_gpu(f, args.overrides) else ["device=gpu"])]
            cfg = load_config(f, overrides)
            kinds = {tc["source"]["kind"] for tc in cfg.get("tunings") or [cfg]}
            if kinds != {"simulated"}:
                print(f"bf-epic: compile: {f} reads a {'/'.join(sorted(kinds - {'simulated'}))} source; compile "
                      f"runs simulated pipelines only: name the simulated one with its shapes (stands, channels, "
                      f"grid)", file=sys.stderr)
                return 2
            sets = [f"source.duration_s={args.seconds or compile_seconds(cfg)}", *overrides]
            cfgs.append(load_config(f, sets))
            runs.append(sets)
        except (ConfigError, OSError, ValueError) as e:
            print(f"bf-epic: compile: {e}", file=sys.stderr)
            return 2
    from ..imaging._xp import gpu_available
    if not gpu_available():
        print("bf-epic: compile needs CuPy and a CUDA GPU (pip install 'bf_epic_blocks[gpu]'); none here",
              file=sys.stderr)
        return 2
    try:
        store.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        print(f"bf-epic: compile: cannot make the kernel store {store}: {e}", file=sys.stderr)
        return 2
    env = dict(os.environ, CUPY_CACHE_DIR=str(store))
    failed = 0
    for f, cfg, sets in zip(args.files, cfgs, runs):
        n0, t0 = len(os.listdir(store)), time.perf_counter()
        with tempfile.TemporaryDirectory(prefix="bf-epic-compile-") as tmp:
            cmd = [sys.executable, "-m", "bf_epic_blocks.pipeline.cli", "run", f, "--no-progress", "-q",
                   *[a for kv in sets for a in ("--set", kv)], "--set", f"output.dir={tmp}"]
            rc = subprocess.run(cmd, env=env).returncode
        n1 = len(os.listdir(store))
        if rc:
            failed += 1
            print(f"bf-epic: compile: {f}: the run failed (exit {rc}); {n1 - n0} kernels stored before it did",
                  file=sys.stderr)
            continue
        print(f"{f}: {n1 - n0} kernels compiled into {store} in {time.perf_counter() - t0:.0f} s ({n1} there)")
    return 1 if failed else 0


def _replay(args):
    from ..io.formats import detect_format
    from ..io.udp import parse_host_port, replay
    try:
        host, port = parse_host_port(args.to)
        fmt = detect_format(args.file) if args.format == "auto" else args.format
        res = replay(args.file, host, port, rate=args.rate, drop=args.drop, seed=args.seed, fmt=fmt,
                     allow_remote=args.allow_remote, loops=args.loop, shift_s=args.shift_s)
    except KeyboardInterrupt:
        print("bf-epic: replay interrupted", file=sys.stderr)
        return 130
    except (OSError, ValueError) as e:
        print(f"bf-epic: replay failed: {e}", file=sys.stderr)
        return 2
    print(f"replayed {args.file} ({fmt.upper()}) to {host}:{port}: {res.nframe} frames, sent {res.sent}, dropped "
          f"{len(res.dropped)} (seed {args.seed}); {res.data_s:.4f} s of data in {res.wall_s:.3f} s "
          f"(asked {args.rate:g}x real time)" + (f"; sync time {res.sync_time} (source.sync_time)"
                                                 if res.sync_time is not None else ""))
    if res.dropped:
        shown = res.dropped[:100]
        print("dropped frame indices (file order" + (", over the passes" if args.loop != 1 else "") + "): "
              + " ".join(map(str, shown)) + (f" ... ({len(res.dropped) - 100} more)" if len(res.dropped) > 100 else ""))
    return 0


#: the interpreter's thread switch interval during ``bf-epic run`` (see :func:`main`), unless the environment
#: sets :data:`SWITCH_INTERVAL_ENV`
SWITCH_INTERVAL_S = 0.001
SWITCH_INTERVAL_ENV = "BF_EPIC_SWITCH_INTERVAL_S"


def switch_interval():
    """Seconds: ``$BF_EPIC_SWITCH_INTERVAL_S`` where set (a number in (0, 0.1]), else :data:`SWITCH_INTERVAL_S`;
    another value is a ValueError that names the variable."""
    raw = os.environ.get(SWITCH_INTERVAL_ENV, "").strip()
    if not raw:
        return SWITCH_INTERVAL_S
    try:
        v = float(raw)
    except ValueError:
        v = float("nan")
    if not 0 < v <= 0.1:
        raise ValueError(f"{SWITCH_INTERVAL_ENV} must be seconds in (0, 0.1], e.g. 0.0005; got {raw!r}")
    return v


def _setup_logging(args):
    level = logging.DEBUG if args.verbose else logging.WARNING if args.quiet else logging.INFO
    logging.basicConfig(level=level, format="%(asctime)s.%(msecs)03d %(levelname)s %(name)s: %(message)s", datefmt="%H:%M:%S")


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.command:
        parser.print_help()
        return 0
    _setup_logging(args)
    if args.command == "replay":
        return _replay(args)
    if args.command == "movie":
        return _movie(args)
    if args.command == "compile":
        return _compile(args)
    from .config import ConfigError, load_config
    try:
        overrides = list(args.overrides)
        if getattr(args, "serve", None):
            overrides.append(f"service.listen={json.dumps(args.serve)}")
        if args.command == "batch":  # the YAML's own source.path need not exist: validate against an input
            first = next((f for f in args.inputs if Path(f).is_file()), args.inputs[0])
            overrides.insert(0, f"source.path={json.dumps(str(Path(first).expanduser().resolve()))}")
        try:
            cfg = load_config(args.file, overrides)
        except ConfigError:
            if len(overrides) == len(args.overrides):
                raise
            cfg = load_config(args.file, args.overrides)  # the YAML's own problem, or not a TBF source (below)
        if args.command == "calibrate":
            # the solver's keys (defaults where the YAML has none); a gains table it would replace is ignored
            extra = ["calibration.gains_table=null"] + ([] if cfg["calibration"].get("solve")
                                                        else ["calibration.solve={}"])
            cfg = load_config(args.file, extra + overrides)
    except ConfigError as e:
        print(f"bf-epic: invalid pipeline: {e}", file=sys.stderr)
        return 2
    except (OSError, ValueError) as e:
        print(f"bf-epic: cannot read {args.file}: {e}", file=sys.stderr)
        return 2
    helper = False
    if args.command == "run":
        from .runner import writes_through_helper
        helper = writes_through_helper(cfg)
    if helper:
        # the image writer's helper process (see ImageWriterBlock) starts now, beside this one's set-up
        from ..blocks.image_writer import start_helper
        try:
            start_helper(png=bool(cfg["output"]["png"]))
        except Exception as e:  # noqa: BLE001 - the writer then starts its own, or writes in its thread
            log.debug("image writer helper not started ahead: %s", e)
    from ..station.offline import configure_offline
    configure_offline()      # before anything imports lsl (the config above does not)
    try:
        if args.command == "validate":
            print(json.dumps(cfg, indent=2, default=str) if args.json else f"{args.file}: valid\n" + _yaml(cfg))
            return 0
        if args.command == "plan":
            from .runner import plan
            d, text = plan(cfg)
            print(json.dumps(d, indent=2, default=float) if args.json else text)
            return 0
        if args.command == "batch":
            return _batch(args, cfg)
        if args.command == "calibrate":
            from .runner import calibrate
            summary = calibrate(cfg, args.output, show_progress=False if args.no_progress else None)
            if args.summary_json:
                with open(args.summary_json, "w") as fh:
                    json.dump(summary, fh, indent=2, default=str)
            print(f"wrote {summary['table']} ({summary['solutions']} solutions, {summary['failures']} failed; "
                  f"{summary['flagged']} inputs flagged: {summary['flag_counts']})")
            return 0
        from .runner import run
        # The block threads share one interpreter lock and give it up at every CUDA call and file read;
        # a thread taking it back waits up to the switch interval while another runs Python. 1 ms (not
        # Python's 5 ms) shortens those waits, which raises the steady real-time factor of a GPU pipeline
        # reading a capture file. A host whose blocks wait on each other more (or less) sets its own.
        sys.setswitchinterval(switch_interval())
        if cfg.get("service") or cfg["source"]["kind"] == "udp":
            # a service, a live stream: runs for weeks, a sequence per F-engine reset; large arrays go back
            from ..service.heap import fix_mmap_threshold
            fix_mmap_threshold()
        if sys.flags.dont_write_bytecode:
            log.info("Python writes no bytecode caches here (PYTHONDONTWRITEBYTECODE): where the packages carry "
                     "no .pyc, every run compiles NumPy, CuPy, astropy and bf_epic_blocks again (~1 s on a GPU "
                     "host); unset it, or set PYTHONPYCACHEPREFIX to a writable folder and run once without it")
        summary = run(cfg, show_progress=False if args.no_progress else None)
        if args.summary_json:
            with open(args.summary_json, "w") as fh:
                json.dump(summary, fh, indent=2, default=str)
        print(f"wrote {summary['files_written']} files to {summary['outdir']} "
              f"({summary['images']} images; frames read {summary['frames_read']}, imaged {summary['frames_imaged']}, "
              f"skipped {summary['frames_skipped']})"
              + (f"; stopped by {summary['stopped_by']}" if summary.get("stopped_by") else ""))
        return 0
    except KeyboardInterrupt:
        print("bf-epic: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # one clear line; the traceback with -v
        if args.verbose:
            log.exception("failed")
        print(f"bf-epic: {args.command} failed: {e}", file=sys.stderr)
        return 1
    finally:
        if helper:
            from ..blocks.image_writer import stop_helpers
            stop_helpers()


def _batch(args, cfg):
    """``bf-epic batch``: 0 when every task succeeded, 1 when one failed, 2 for bad arguments."""
    try:
        from .batch import dask_client, format_table, run_batch, summary_dict, task_configs
        import distributed  # noqa: F401  (the optional extra)
    except ImportError as e:
        print(f"bf-epic: batch needs dask.distributed ({e}): pip install 'bf_epic_blocks[batch]'", file=sys.stderr)
        return 2
    if args.workers is not None and args.workers < 1:
        print(f"bf-epic: --workers must be >= 1, got {args.workers}", file=sys.stderr)
        return 2
    try:
        task_configs(cfg, args.inputs)  # checks the source kind and the stems before any cluster starts
    except ValueError as e:
        print(f"bf-epic: batch: {e}", file=sys.stderr)
        return 2
    show = sys.stderr.isatty() and not args.no_progress
    if not args.verbose:  # dask logs every connection at INFO on its own logger level
        logging.getLogger("distributed").setLevel(logging.WARNING)
    with dask_client(args.scheduler, args.workers) as client:
        log.info("batch of %d files on %s", len(args.inputs), client.scheduler.address)
        results = run_batch(cfg, args.inputs, client, progress=show)
    if args.verbose:
        for t in results:
            if t.detail:
                log.error("%s block %s:\n%s", t.file, t.block, t.detail)
    if args.summary_json:
        with open(args.summary_json, "w") as fh:
            json.dump(summary_dict(results), fh, indent=2, default=str)
    print(format_table(results))
    print(f"outputs in {Path(cfg['output']['dir']).expanduser().resolve()}/<file stem>/")
    return 0 if all(t.ok for t in results) else 1


def _yaml(cfg):
    import yaml
    return yaml.safe_dump(cfg, sort_keys=False, default_flow_style=None)


def entry():
    """The ``bf-epic`` console script: :func:`main`, then a prompt exit with its status.

    When ``main`` returns, every block thread has joined and every output file is closed; what is
    left is interpreter teardown (CuPy's memory pools and handles, the CUDA context, module cleanup),
    a noticeable part of a short GPU run. Logging and the output streams are flushed, then
    the process ends without it. In-process callers (tests, notebooks) use :func:`main`."""
    rc = main()
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(rc if isinstance(rc, int) else 1)


if __name__ == "__main__":
    entry()
