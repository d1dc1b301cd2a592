"""Batch re-imaging of TBF archives on a Dask distributed cluster (``bf-epic batch``).

One pipeline YAML, many input files: each file is split into its channel blocks (the runs of
evenly spaced channels that ``bf-epic run`` writes to separate FITS files, ``_r<k>``; one block for
a file of contiguous channels) and each file x block is one task. A task is exactly what
``bf-epic run`` does (:func:`.runner.run`) with ``source.path`` set to the file,
``source.channel_block`` to the block and ``output.dir`` to ``<output.dir>/<file stem>``, so the
files written are those ``bf-epic run`` writes for that file, under the same names.

    inputs --(scan task per file: how many channel blocks?)--> image task per file x block --> summary

Both kinds of task run on the cluster (workers must see the input files and ``output.dir`` under
the same paths as the client: one machine, or a shared file system). A task that fails (a corrupt
file, a bad channel block, a worker that dies) becomes a row with its error; the others go on.

Needs the optional extra ``batch`` (``pip install bf_epic_blocks[batch]``: dask[distributed]).
"""
from __future__ import annotations

import copy
import logging
import os
import sys
import time
import traceback
import uuid
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

log = logging.getLogger("bf_epic_blocks")


@dataclass
class TaskResult:
    """One row of the batch summary: a file x channel block (``block`` None when its scan failed)."""
    file: str
    block: int | None = None
    nblocks: int | None = None
    images: int = 0
    frames: int = 0
    skipped: int = 0
    seconds: float = 0.0
    error: str | None = None
    outdir: str = ""
    files: list = field(default_factory=list)
    detail: str | None = None  # the worker's traceback, for -v

    @property
    def ok(self) -> bool:
        return self.error is None


# ------------------------------------------------------------------------------- worker side
def _error_text(e: BaseException) -> str:
    return f"{type(e).__name__}: {e}"


def count_channel_blocks(cfg: dict) -> dict:
    """Worker task: ``{"nblocks": n, "seconds": s}`` for ``cfg``'s TBF file, or ``{"error": ...}``."""
    t0 = time.perf_counter()
    try:
        from ..blocks.image_writer import channel_runs
        from .runner import _scan
        return {"nblocks": len(channel_runs(_scan(cfg["source"]["path"], report=False).freq_hz)),
                "seconds": time.perf_counter() - t0}
    except Exception as e:  # reported in the summary; the other files go on
        return {"error": _error_text(e), "detail": traceback.format_exc(), "seconds": time.perf_counter() - t0}


def image_block(cfg: dict) -> dict:
    """Worker task: :func:`.runner.run` on ``cfg`` (no progress bar); its summary or ``{"error": ...}``."""
    t0 = time.perf_counter()
    try:
        from ..station.offline import configure_offline
        configure_offline()
        from .runner import run
        s = run(cfg, show_progress=False)
        return {"images": s["images"], "frames": s["frames_read"], "skipped": s["frames_skipped"],
                "files": s["files"], "seconds": time.perf_counter() - t0}
    except Exception as e:
        return {"error": _error_text(e), "detail": traceback.format_exc(), "seconds": time.perf_counter() - t0}


# ------------------------------------------------------------------------------- client side
def task_configs(cfg: dict, inputs) -> list[tuple[str, dict]]:
    """(input as given, config for that file) with ``source.path`` absolute and ``output.dir`` =
    ``<output.dir>/<stem>`` (absolute, so remote workers write where the client expects).

    Raises ValueError when ``cfg`` has no TBF source or two inputs share a stem (their outputs
    would overwrite each other). Paths are resolved against the working directory.
    """
    if cfg.get("tunings"):
        raise ValueError("bf-epic batch re-images one tuning's TBF files; this pipeline has tunings: (set "
                         "tunings=null)")
    if cfg["source"]["kind"] != "tbf":
        raise ValueError(f"bf-epic batch re-images TBF files: the pipeline's source.kind must be 'tbf', "
                         f"got {cfg['source']['kind']!r}")
    stems: dict[str, str] = {}
    out = []
    root = Path(cfg["output"]["dir"]).expanduser().resolve()
    for f in inputs:
        p = Path(f).expanduser().resolve()
        if p.stem in stems:
            raise ValueError(f"inputs {stems[p.stem]!r} and {f!r} share the stem {p.stem!r}: their outputs "
                             f"would both go to {root / p.stem}; rename one or batch them separately")
        stems[p.stem] = f
        c = copy.deepcopy(cfg)
        c["source"]["path"] = str(p)
        c["source"]["channel_block"] = None
        c["output"]["dir"] = str(root / p.stem)
        out.append((f, c))
    return out


@contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None):
    """A ``distributed.Client``: to ``scheduler`` (``tcp://host:port``) when given, else to a new
    LocalCluster of ``workers`` worker processes (default: one per CPU core) of one thread each,
    listening on 127.0.0.1 only (scheduler, workers, and the HTTP/dashboard endpoint on a free
    port: several batches can run side by side). Processes, not threads: each task runs a whole
    threaded pipeline with its own CuPy device, logging and matplotlib state, which processes
    keep apart, and the work is the same as on a remote cluster (tasks and results pickled)."""
    from distributed import Client, LocalCluster
    if scheduler:
        with Client(scheduler, timeout="30s") as client:
            yield client
        return
    n = int(workers) if workers else (os.cpu_count() or 1)
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=":0") as cluster, Client(cluster) as client:
        yield client


def run_batch(cfg: dict, inputs, client, *, progress: bool = False) -> list[TaskResult]:
    """Run ``cfg`` on every input file x channel block on ``client``'s cluster.

    Returns one :class:`TaskResult` per task, in input order then block order (a file whose scan
    failed has one row, ``block`` None). Never raises for a failed task: its row has ``error``.
    """
    from distributed import as_completed
    from tqdm import tqdm

    tag = uuid.uuid4().hex[:8]  # unique task keys on a long-lived scheduler
    todo = task_configs(cfg, inputs)
    order = {f: i for i, (f, _) in enumerate(todo)}
    scans = {client.submit(count_channel_blocks, c, key=f"bf-epic-scan-{Path(f).stem}-{tag}"): (f, c)
             for f, c in todo}
    images = {}
    results: list[TaskResult] = []
    bar = tqdm(total=len(todo), unit="task", desc="bf-epic batch", disable=not progress)
    ac = as_completed(list(scans))
    try:
        for fut in ac:
            if fut in scans:
                f, c = scans.pop(fut)
                r = _outcome(fut)
                if "error" in r:
                    results.append(TaskResult(f, seconds=r.get("seconds", 0.0), error=r["error"],
                                              outdir=c["output"]["dir"], detail=r.get("detail")))
                    bar.update()
                    bar.write(f"bf-epic batch: {f}: {r['error']}", file=sys.stderr)
                    continue
                n = r["nblocks"]
                if n > 1:
                    bar.total += n - 1
                    bar.refresh()
                for k in range(n):
                    ck = copy.deepcopy(c)
                    ck["source"]["channel_block"] = k
                    im = client.submit(image_block, ck, key=f"bf-epic-image-{Path(f).stem}-b{k}-{tag}")
                    images[im] = (f, k, n, ck)
                    ac.add(im)
            else:
                f, k, n, ck = images.pop(fut)
                r = _outcome(fut)
                results.append(TaskResult(f, k, n, r.get("images", 0), r.get("frames", 0), r.get("skipped", 0),
                                          r.get("seconds", 0.0), r.get("error"), ck["output"]["dir"],
                                          r.get("files", []), r.get("detail")))
                bar.update()
                if r.get("error"):
                    bar.write(f"bf-epic batch: {f} block {k}: {r['error']}", file=sys.stderr)
    finally:
        bar.close()
    results.sort(key=lambda t: (order[t.file], -1 if t.block is None else t.block))
    return results


def _outcome(fut) -> dict:
    """A task's result dict; a task that raised anyway (a worker died, a result that did not
    unpickle) becomes ``{"error": ...}``."""
    try:
        return fut.result()
    except Exception as e:
        return {"error": _error_text(e), "detail": traceback.format_exc()}


def format_table(results: list[TaskResult]) -> str:
    """The summary as a plain-text table: file, block, images, frames, skipped, seconds, error."""
    head = ("file", "block", "images", "frames", "skipped", "seconds", "error")
    rows = []
    for t in results:
        blk = "-" if t.block is None else f"{t.block + 1}/{t.nblocks}"
        nums = ("-",) * 3 if t.block is None else (str(t.images), str(t.frames), str(t.skipped))
        rows.append((t.file, blk, *nums, f"{t.seconds:.2f}", t.error or ""))
    w = [max(len(r[i]) for r in rows + [head]) for i in range(len(head) - 1)]
    left = (True, True, False, False, False, False)

    def line(r):
        cells = [c.ljust(w[i]) if left[i] else c.rjust(w[i]) for i, c in enumerate(r[:-1])]
        return ("  ".join(cells) + "  " + r[-1]).rstrip()
    nok = sum(t.ok for t in results)
    return "\n".join([line(head)] + [line(r) for r in rows] +
                     [f"{nok} of {len(results)} tasks succeeded"])


def summary_dict(results: list[TaskResult]) -> dict:
    """The summary as JSON-ready data."""
    return {"ok": all(t.ok for t in results), "tasks": [asdict(t) for t in results]}
