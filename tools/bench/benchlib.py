"""What the benchmark scripts share: the array module for a device, timing, the machine named by its
hardware, the JSON writer, and how to run ``bf-epic`` as a user would.

Not part of the package API. The scripts in this folder import it as a sibling (``import benchlib``):
a script's own folder is first on ``sys.path`` when it is run as ``python tools/bench/<script>.py``,
and the test suite names this folder in setup.cfg's ``pythonpath``. The package itself is imported
from the environment (``pip install -e .``, which ``make setup`` does, or ``PYTHONPATH`` at a checkout).
"""
import datetime
import importlib.util
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: the repository's root (``pipelines/`` and ``docs/`` are found from it)
REPO = Path(__file__).resolve().parents[2]

DEVICES = ("cpu", "gpu")


def array_module(device):
    """``numpy`` for ``"cpu"``, ``cupy`` for ``"gpu"``; anything else is a ValueError."""
    if device == "gpu":
        import cupy
        return cupy
    if device == "cpu":
        return np
    raise ValueError(f"device {device!r}: expected one of {DEVICES}")


def synchronize(xp):
    """Wait for the GPU's queued work when ``xp`` is CuPy; nothing for NumPy."""
    if xp is not np:
        xp.cuda.Device().synchronize()


def timer(device):
    """run(fn, repeat) -> (median seconds, last result): one warm-up call first; CUDA events on the GPU."""
    if device == "gpu":
        import cupy as cp

        def run(fn, repeat):
            fn()
            cp.cuda.Device().synchronize()
            ts = []
            for _ in range(repeat):
                a, b = cp.cuda.Event(), cp.cuda.Event()
                a.record()
                out = fn()
                b.record()
                b.synchronize()
                ts.append(cp.cuda.get_elapsed_time(a, b) / 1e3)
            return float(np.median(ts)), out
    else:
        def run(fn, repeat):
            fn()
            ts = []
            for _ in range(repeat):
                t0 = time.perf_counter()
                out = fn()
                ts.append(time.perf_counter() - t0)
            return float(np.median(ts)), out
    return run


def cpu_model():
    """The CPU's model name (``/proc/cpuinfo``'s "model name" on Linux), else what ``platform`` says."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def gpu_names():
    """The names of the GPUs this process sees, e.g. ``["NVIDIA H100 80GB HBM3"]``; [] without any.

    CuPy answers when it is already imported (it then holds a context anyway); otherwise nvidia-smi
    does, so that a script that only times ``bf-epic`` subprocesses opens no CUDA context of its own
    (one would count in the GPU memory it samples)."""
    if "cupy" in sys.modules:
        try:
            cp = sys.modules["cupy"]
            names = []
            for d in range(cp.cuda.runtime.getDeviceCount()):
                name = cp.cuda.runtime.getDeviceProperties(d)["name"]
                names.append(name.decode() if isinstance(name, bytes) else name)
            return names
        except Exception:  # noqa: BLE001 - a label only; nvidia-smi may still answer
            pass
    if shutil.which("nvidia-smi"):
        r = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                           text=True, check=False)
        return [n.strip() for n in r.stdout.splitlines() if n.strip()]
    return []


def machine(device="cpu"):
    """The machine a result was measured on, by its hardware: a dict with ``hardware`` (one line, e.g.
    "NVIDIA H100 80GB HBM3, 16 cores" on the GPU, "AMD EPYC 7763 64-Core Processor, 2 cores" on the
    CPU), ``cpu``, ``ncpu``, ``host``, ``python``, ``numpy``, and on the GPU ``gpu`` (the first GPU's
    name), ``ngpu`` and ``cupy``."""
    info = {"cpu": cpu_model(), "ncpu": os.cpu_count(), "host": platform.node(),
            "python": platform.python_version(), "numpy": np.__version__}
    gpus = gpu_names() if device == "gpu" else []
    if gpus:
        info.update(gpu=gpus[0], ngpu=len(gpus))
        if "cupy" in sys.modules:
            info["cupy"] = sys.modules["cupy"].__version__
        count = f"{len(gpus)} x " if len(gpus) > 1 else ""
        info["hardware"] = f"{count}{gpus[0]}, {info['ncpu']} cores"
    else:
        info["hardware"] = f"{info['cpu']}, {info['ncpu']} cores"
    return info


def best(fn, repeat):
    """(shortest wall seconds of ``repeat`` calls of ``fn``, the last call's result): host-side timing."""
    times, res = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        res = fn()
        times.append(time.perf_counter() - t0)
    return min(times), res


def utc_now():
    """The time now, UTC, ISO 8601 (what each result's ``date`` holds)."""
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def write_json(path, out):
    """Write a benchmark's result dict as indented JSON (making the folder) and say so."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(out, f, indent=1, default=str)
    print(f"wrote {path}")


def bf_epic_command():
    """The command line of ``bf-epic``: this Python's own console script (a virtualenv's), else the one
    on PATH, else the module."""
    beside = Path(sys.executable).with_name("bf-epic")
    exe = str(beside) if beside.exists() else shutil.which("bf-epic")
    return [exe] if exe else [sys.executable, "-m", "bf_epic_blocks.pipeline.cli"]


#: where the runs keep Python's bytecode when the environment forbids writing it beside the sources
_PYCACHE = Path(tempfile.gettempdir()) / "bf_e2e_pycache"


#: what a GPU pipeline run imports, compiled by :func:`warm_bytecode` (a module not installed is left out)
RUN_IMPORTS = ("numpy", "yaml", "astropy.coordinates", "astropy.io.fits", "astropy.wcs", "astropy.time",
               "astropy.table", "matplotlib.figure", "scipy.linalg", "scipy.spatial", "scipy.optimize", "h5py",
               "lsl.common.stations", "bf_epic_blocks.pipeline.runner", "bf_epic_blocks.pipeline.station",
               "bf_epic_blocks.blocks", "bf_epic_blocks.io.fits", "bf_epic_blocks.io.quicklook",
               "bf_epic_blocks.search", "bf_epic_blocks.imaging", "bf_epic_blocks.sky")


def warm_bytecode(device):
    """Compile what a run imports once, as an installation does (pip compiles on install), before any run is
    timed: where the environment forbids writing bytecode, :func:`child_env`'s folder for it starts empty and
    the first timed run would compile NumPy, CuPy, astropy, SciPy and this package. Returns
    ``{"prefix", "seconds"}`` (prefix None: bytecode is written beside the sources, nothing was done)."""
    env = child_env()
    prefix = env.get("PYTHONPYCACHEPREFIX")
    if prefix is None:
        return {"prefix": None, "seconds": 0.0}
    mods = list(RUN_IMPORTS) + (["cupy", "cupyx", "cupyx.scipy.special"] if str(device).startswith("gpu") else [])
    code = ("import importlib\nfor m in %r:\n    try:\n        importlib.import_module(m)\n"
            "    except Exception:\n        pass\n" % (mods,))
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], env=env, check=False, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    return {"prefix": prefix, "seconds": round(time.perf_counter() - t0, 2)}


def child_env():
    """The environment of each timed ``bf-epic`` run: this one, with Python's bytecode caches on.

    A user's installation has them (pip compiles on install, Python writes ``__pycache__`` on first
    import); an image that sets ``PYTHONDONTWRITEBYTECODE`` and ships no ``.pyc`` makes every run
    compile NumPy, CuPy, astropy and this package from source again, which is not what a station
    pays. Such runs keep their caches under a folder of their own (``PYTHONPYCACHEPREFIX``)."""
    env = dict(os.environ)
    if env.pop("PYTHONDONTWRITEBYTECODE", None) is not None and "PYTHONPYCACHEPREFIX" not in env:
        env["PYTHONPYCACHEPREFIX"] = str(_PYCACHE)
    return env


def import_package(folder, name):
    """Import the package ``name`` from ``folder/name`` (e.g. a previous release copied aside as
    ``bf_epic_prev``) without putting ``folder`` on ``sys.path``; returns the package module."""
    init = Path(folder) / name / "__init__.py"
    if not init.is_file():
        raise FileNotFoundError(f"{init} not found: expected a package folder {name!r} inside {folder}")
    spec = importlib.util.spec_from_file_location(name, init, submodule_search_locations=[str(init.parent)])
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
