"""The one loader of the package's CUDA kernels.

Every GPU kernel the package launches is CUDA C++ in a ``.cu`` file beside the Python that launches
it (``imaging/fused.cu`` beside ``imaging/fused.py``). A module asks for a kernel by its file, its
``__global__`` name and the compile-time constants it needs::

    from ..cuda import get_kernel
    k = get_kernel("imaging/reduce.cu", "bf_row_dot")
    k = get_kernel("imaging/fused_hopper.cu", "bf_fused_power", defines={"NP": 2, "KD": 512, ...}, arch="sm_90a")

and gets the function of a ``cupy.RawModule`` compiled by NVRTC for the current device. One cache
holds every compiled module, keyed by (file, defines, options, arch, device), and the functions taken
from them, so a kernel compiles once per process; CuPy's own disk cache keeps it across processes.
Template kernels are asked for by name expression (``get_kernel(path, "bf_transpose<float>",
name_expressions=...)``); a ``.cu`` file instantiates them explicitly, so that compiling the file
alone (the compile test) compiles them too.

``#include "name.cuh"`` lines that name a file of the package are pasted in before compiling, so the
source CuPy hashes for its disk cache is the whole program (an ``-I`` path would let an edited header
reuse a stale binary). System headers (``<cuda_fp16.h>``) are left to NVRTC.

**The kernel store.** NVRTC compiles a whole-band pipeline's kernels (ours and the element-wise ones CuPy
makes for array expressions) in ~20 s the first time, which a service must not wait for at every fresh
start. ``bf-epic compile`` compiles them once, at install: it runs the pipelines named for a moment
with CuPy's kernel cache pointed at the store (:func:`kernel_store`), a folder of CuPy's own cache files.
A GPU run first puts the store's files that CuPy's cache lacks into it (:func:`seed_cupy_cache`: hard
links where it can, copies where not), so a machine whose CuPy cache is empty (a fresh account, a wiped
home) starts with every kernel compiled. A file is named by the hash of everything that made it (source,
options, architecture, NVRTC and CuPy versions), so one from another GPU or CuPy version is never used,
only put there.

Every ``.cu`` file lists the configurations a shipped path compiles in :data:`COMPILE_CHECKS`, through
:func:`register` at the import of the module that launches it (the GPU tests compile each one with
NVRTC, and a ``.cu`` file missing there fails them).
"""
from __future__ import annotations

import os
import re
import sys
from pathlib import Path

__all__ = ["get_kernel", "get_module", "register", "source", "cu_files", "COMPILE_CHECKS", "kernel_store",
           "cupy_cache_dir", "seed_cupy_cache", "KERNEL_STORE_ENV", "record_compiles", "COMPILED", "COMPILE_LOG_ENV"]

#: environment variable naming the kernel store's folder (default: ``<sys.prefix>/share/bf_epic_blocks/kernels``)
KERNEL_STORE_ENV = "BF_EPIC_KERNELS"

PACKAGE_DIR = Path(__file__).resolve().parent

_INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"\s*$', re.MULTILINE)

_MODULES: dict = {}
_FUNCTIONS: dict = {}
_FAST: dict = {}   # the same functions, keyed by get_kernel's arguments as given

#: {package-relative .cu path: [(defines, arch, options), ...]}: the configurations the GPU tests compile.
#: ``arch`` None compiles for the current device; "sm_90a" only where the device is a Hopper GPU;
#: ``options``: further NVRTC options (``--use_fast_math``).
COMPILE_CHECKS: dict = {}


def cu_files():
    """Package-relative paths of every ``.cu`` file shipped with the package, sorted."""
    return sorted(str(p.relative_to(PACKAGE_DIR)) for p in PACKAGE_DIR.rglob("*.cu"))


def source(path: str) -> str:
    """The CUDA source of package-relative ``path`` with the package's own ``#include "x"`` pasted in
    (relative to the including file; each file once)."""
    seen: set = set()

    def expand(p: Path) -> str:
        p = p.resolve()
        if p in seen:
            return ""
        seen.add(p)
        if not p.is_file():
            raise FileNotFoundError(f"CUDA source {p} not found (asked for {path!r})")
        text = p.read_text()
        return _INCLUDE.sub(lambda m: expand(p.parent / m.group(1)), text)

    return expand(PACKAGE_DIR / path)


def _options(defines, options, arch):
    opts = ["-std=c++17"]
    for k, v in sorted((defines or {}).items()):
        opts.append(f"-D{k}" if v is None else f"-D{k}={v}")
    if arch:
        opts.append(f"-arch={arch}")
    return tuple(opts) + tuple(options or ())


def get_module(path: str, *, defines: dict | None = None, options=(), arch: str | None = None,
               name_expressions=None):
    """The ``cupy.RawModule`` of package-relative ``path`` compiled with ``-D`` ``defines``, extra NVRTC
    ``options`` and ``arch`` (e.g. "sm_90a"; None: the current device's), cached per device."""
    import cupy as cp
    opts = _options(defines, options, arch)
    names = tuple(name_expressions) if name_expressions else None
    key = (path, opts, names, cp.cuda.Device().id)
    mod = _MODULES.get(key)
    if mod is None:
        mod = cp.RawModule(code=source(path), options=opts, name_expressions=names)
        _MODULES[key] = mod
    return mod


def get_kernel(path: str, name: str, *, defines: dict | None = None, options=(), arch: str | None = None,
               name_expressions=None):
    """The ``__global__`` function ``name`` of package-relative ``path`` (see :func:`get_module`), cached:
    the same ``cupy.RawKernel`` on every call, so attributes set on it (dynamic shared memory) stay.

    A template kernel is asked for by its name expression (``"bf_transpose<float>"``); pass every
    expression the caller uses as ``name_expressions`` (the same tuple each time), so that one module
    holds them all.

    Launch paths call this once per launch, so a repeat call is one dictionary lookup keyed by the
    arguments as given (no option strings are built)."""
    import cupy as cp
    dev = cp.cuda.runtime.getDevice()
    fast = (path, name, tuple(defines.items()) if defines else (), tuple(options) if options else (), arch,
            tuple(name_expressions) if name_expressions else (), dev)
    fn = _FAST.get(fast)
    if fn is not None:
        return fn
    key = (path, _options(defines, options, arch), tuple(name_expressions or ()), dev, name)
    fn = _FUNCTIONS.get(key)
    if fn is None:
        fn = get_module(path, defines=defines, options=options, arch=arch,
                        name_expressions=name_expressions).get_function(name)
        _FUNCTIONS[key] = fn
    _FAST[fast] = fn
    return fn


def register(path: str, *configs):
    """Record the configurations of ``path`` that a shipped path compiles: ``(defines, arch)`` or
    ``(defines, arch, options)`` (no configuration: the file with no defines, for the current device).
    Called by the module that launches the file's kernels, at import, so the compile test covers exactly
    what ships. Stored as (defines, arch, options) triples."""
    COMPILE_CHECKS.setdefault(path, [])
    for cfg in configs or [({}, None)]:
        defines, arch, *rest = cfg
        cfg = (dict(defines), arch, tuple(rest[0]) if rest else ())
        if cfg not in COMPILE_CHECKS[path]:
            COMPILE_CHECKS[path].append(cfg)


def kernel_store() -> Path:
    """The kernel store's folder: ``$BF_EPIC_KERNELS``, else ``<sys.prefix>/share/bf_epic_blocks/kernels``
    (inside the virtual environment the package is installed in)."""
    env = os.environ.get(KERNEL_STORE_ENV)
    return Path(env).expanduser() if env else Path(sys.prefix) / "share" / "bf_epic_blocks" / "kernels"


def cupy_cache_dir() -> Path:
    """The folder CuPy caches compiled kernels in: ``$CUPY_CACHE_DIR``, else ``~/.cupy/kernel_cache``
    (CuPy's own rule, read without importing CuPy)."""
    env = os.environ.get("CUPY_CACHE_DIR")
    return Path(env).expanduser() if env else Path("~/.cupy/kernel_cache").expanduser()


def seed_cupy_cache(store: Path | None = None, cache: Path | None = None) -> dict:
    """Put the store's compiled kernels that CuPy's cache lacks into it: a hard link where the two share a
    file system (no bytes move; CuPy replaces a cache file by renaming a new one over its name, so the
    store's file is never written through the link), else a whole copy (written beside its name and
    renamed). Returns ``{"store", "cache", "copied", "linked", "present", "failed"}``: ``copied`` the files
    put in, ``linked`` those of them linked, ``present`` the store's files the cache already had,
    ``failed`` those that could not be put in (a read-only or full cache: those kernels compile when
    first used, as without a store). No store: nothing put in."""
    import shutil
    store = kernel_store() if store is None else Path(store)
    cache = cupy_cache_dir() if cache is None else Path(cache)
    out = {"store": str(store), "cache": str(cache), "copied": 0, "linked": 0, "present": 0, "failed": 0}
    try:
        names = [e.name for e in os.scandir(store) if e.is_file() and not e.name.startswith(".")]
    except OSError:
        return out
    try:
        have = set(os.listdir(cache))
    except FileNotFoundError:
        have = set()
    except OSError:
        out["failed"] = len(names)
        return out
    for name in names:
        if name in have:
            out["present"] += 1
            continue
        try:
            cache.mkdir(parents=True, exist_ok=True)
            try:
                os.link(store / name, cache / name)
                out["linked"] += 1
            except FileExistsError:         # another process put it in meanwhile
                out["present"] += 1
                continue
            except OSError:                 # another file system, or links refused: copy
                tmp = cache / f".{name}.{os.getpid()}.tmp"
                shutil.copyfile(store / name, tmp)
                os.replace(tmp, cache / name)
            out["copied"] += 1
        except OSError:
            out["failed"] += 1
    return out


#: environment variable: set (to anything but "" or "0"), a GPU run logs every kernel CuPy compiles while it runs
COMPILE_LOG_ENV = "BF_EPIC_LOG_COMPILES"

#: kernels compiled in this process since :func:`record_compiles` first ran (dicts; see there)
COMPILED: list = []
_GLOBAL_KERNEL = re.compile(r"__global__\s+void\s+(\w+)")
# CuPy's compiler functions that run only on a cache miss: CuPy 14's, an older CuPy's, and NVCC's
_COMPILER_ENTRIES = ("_compile_using_nvrtc_no_warning", "compile_using_nvrtc", "compile_using_nvcc")


def record_compiles(log=None) -> list | None:
    """From now on, record every kernel CuPy compiles in this process (a cache miss: not found in CuPy's disk
    cache, so not in the kernel store either) in :data:`COMPILED` -- ``{"at_unix_s", "seconds", "thread",
    "kernel", "caller"}``, ``caller`` the package's own frame that asked (``file.py:line:function``) -- and
    log each to ``log`` (a :class:`logging.Logger`). Idempotent. Wraps functions of ``cupy.cuda.compiler``
    that are not CuPy's public interface: returns None, recording nothing, where this CuPy has none of them.
    What a run compiles that ``bf-epic compile`` did not is what to look at when a start is slow."""
    try:
        from cupy.cuda import compiler
    except ImportError:
        return None
    if getattr(compiler, "_bf_epic_recorded", False):
        return COMPILED
    entry = next((n for n in _COMPILER_ENTRIES[:2] if callable(getattr(compiler, n, None))), None)
    names = ([entry] if entry else []) + [n for n in _COMPILER_ENTRIES[2:] if callable(getattr(compiler, n, None))]
    if not names:
        return None
    import threading
    import time
    import traceback

    def wrap(fn):
        def compile_recorded(source, *args, **kwargs):
            t0 = time.time()
            out = fn(source, *args, **kwargs)
            if not isinstance(source, str) or not source.strip():
                return out          # CuPy's compile of an empty file: its compiler's version, not a kernel
            m = _GLOBAL_KERNEL.search(source)
            caller = ""
            for fr in reversed(traceback.extract_stack()[:-1]):
                path = Path(fr.filename)
                if PACKAGE_DIR in path.parents and path.name != "cuda.py":
                    caller = f"{path.relative_to(PACKAGE_DIR).as_posix()}:{fr.lineno}:{fr.name}"
                    break
            row = {"at_unix_s": t0, "seconds": round(time.time() - t0, 3),
                   "thread": threading.current_thread().name, "kernel": m.group(1) if m else "?", "caller": caller}
            COMPILED.append(row)
            if log is not None:
                log.info("kernel %s compiled while running (%.2f s, thread %s, asked by %s): the kernel store "
                         "does not hold it", row["kernel"], row["seconds"], row["thread"], caller or "CuPy")
            return out
        compile_recorded.__wrapped__ = fn
        return compile_recorded

    for n in names:
        setattr(compiler, n, wrap(getattr(compiler, n)))
    compiler._bf_epic_recorded = True
    return COMPILED
