"""Array-namespace helpers: one code path for NumPy and CuPy.

CuPy is optional: nothing here imports it unless it is installed, and a CuPy array can only
come from a caller who has it.
"""
from __future__ import annotations

import types
import weakref

import numpy as np

try:  # CuPy is an optional extra ("gpu"); the package works without it.
    import cupy as _cupy
except Exception:  # pragma: no cover - depends on the machine
    _cupy = None


def cupy_or_none():
    """The cupy module when it imports, else None."""
    return _cupy


def gpu_available() -> bool:
    """True when CuPy imports and at least one CUDA device answers."""
    if _cupy is None:
        return False
    try:
        return _cupy.cuda.runtime.getDeviceCount() > 0
    except Exception:
        return False


def device_kind(device) -> str:
    """'cpu' or 'gpu': the kind of device named by ``device``.

    ``device``: a kind or a pipeline's device string ('cpu', 'gpu', 'gpu:1', 'gpu:all', 'gpu:0,1'), or a
    real array namespace (the ``numpy`` or ``cupy`` module). Needs no CuPy and no GPU, so a plan can be
    made for a GPU on a machine without one. Anything else is an error naming what was given: a
    stand-in object cannot pass for a namespace (a class's ``__name__`` is always its own class name,
    so a stand-in would make every GPU plan a CPU plan).
    """
    if isinstance(device, str):
        kind = device.strip().lower().split(":", 1)[0]
        if kind in ("cpu", "gpu"):
            return kind
        raise ValueError(f"device must be 'cpu' or 'gpu' (or gpu:N, gpu:all), got {device!r}")
    if isinstance(device, types.ModuleType) and device.__name__ in ("numpy", "cupy"):
        return "gpu" if device.__name__ == "cupy" else "cpu"
    raise TypeError(f"device must be 'cpu', 'gpu' or an array namespace (the numpy or cupy module), got {device!r}")


def host_all(a) -> bool:
    """``all(a)`` of a small array (flags, positions, weights), decided on the host.

    On a GPU a whole-array reduction goes to CUB, whose kernels NVRTC compiles on first use where the
    kernel cache is empty, each compile delaying a cold first image; copying a few kB to the host does
    not."""
    return bool(np.all(to_numpy(a)))


def host_any(a) -> bool:
    """``any(a)`` of a small array, decided on the host (see :func:`host_all`)."""
    return bool(np.any(to_numpy(a)))


def pinned_empty(shape, dtype):
    """An uninitialised NumPy array in page-locked host memory (CuPy's pinned pool: cheap after the
    first), from and to which the GPU copies asynchronously at full bus speed; a plain NumPy array
    when there is no CuPy or GPU."""
    dtype = np.dtype(dtype)
    shape = tuple(int(n) for n in (shape if np.ndim(shape) else (shape,)))
    count = int(np.prod(shape, dtype=np.int64))
    if not gpu_available():
        return np.empty(shape, dtype)
    mem = _cupy.cuda.alloc_pinned_memory(max(count * dtype.itemsize, 1))
    return np.frombuffer(mem, dtype, count).reshape(shape)


def release_free_pinned() -> None:
    """Hand the page-locked host blocks CuPy's pinned pool keeps free back to the system (none in use
    is touched). The pool keeps a freed block for a later request of exactly its size; a sequence
    whose sizes differ from the last's (a partial gulp, another channel count) leaves its blocks
    behind, resident, unless they are let go."""
    if _cupy is not None:
        _cupy.get_default_pinned_memory_pool().free_all_blocks()


def get_xp(*arrays):
    """The array module (numpy or cupy) that owns ``arrays`` (numpy for host arrays/scalars)."""
    if _cupy is not None:
        return _cupy.get_array_module(*arrays)
    return np


def is_device_array(a) -> bool:
    return _cupy is not None and isinstance(a, _cupy.ndarray)


def to_numpy(a):
    """Copy a CuPy array to the host (on the current stream, as ``a.get()``); pass NumPy arrays through.

    The stream is synchronised before the copy, not by it: a copy into pageable memory that has to
    wait for queued kernels waits inside the CUDA driver, and there it holds up every other thread's
    CUDA calls (a pipeline's sink would hold up the imager's thread); a synchronisation waits without
    holding them.
    """
    if is_device_array(a):
        with a.device:
            _cupy.cuda.get_current_stream().synchronize()
            return a.get()
    return np.asarray(a)


def _rows_packed(a) -> bool:
    """Whether each row (index along the first axis) of ``a`` is one run of contiguous bytes."""
    expected = a.itemsize
    for d in range(a.ndim - 1, 0, -1):
        if a.shape[d] > 1 and a.strides[d] != expected:
            return False
        expected *= a.shape[d]
    return True


def copy_rows(dst, src, stream) -> bool:
    """``dst[...] = src`` as one 2-D memcpy on ``stream`` where both are CuPy arrays of one shape, dtype and
    device whose rows (first axis) are each contiguous bytes at a fixed pitch: a whole gulp, a channel slice
    of one, a ring's frames within each ringlet. CuPy's copy of such a view is an indexing kernel, several
    times slower, and compiled for the view's rank and dtype at its first use. Returns False, having copied
    nothing, for any other pair (the caller copies another way)."""
    if (src.ndim < 2 or src.shape != dst.shape or src.dtype != dst.dtype or src.device.id != dst.device.id
            or src.shape[0] == 0):
        return False
    row = src.itemsize * int(np.prod(src.shape[1:], dtype=np.int64))
    if row == 0 or not (_rows_packed(src) and _rows_packed(dst)):
        return False
    # a single row's pitch is any stride (CuPy's stride of a length-1 axis need not be the row's length)
    spitch, dpitch = (row, row) if src.shape[0] == 1 else (src.strides[0], dst.strides[0])
    if spitch < row or dpitch < row:
        return False
    _cupy.cuda.runtime.memcpy2DAsync(dst.data.ptr, dpitch, src.data.ptr, spitch, row, src.shape[0],
                                     _cupy.cuda.runtime.memcpyDeviceToDevice, stream.ptr)
    return True


class Lease:
    """Held by whatever still reads a :class:`Workspace`'s array: while one is alive, the next
    :meth:`Workspace.take` makes a new array rather than overwrite it."""

    __slots__ = ("__weakref__",)


class Workspace:
    """Working arrays, used again by every call that needs one of at most their size.

    For a pipeline's largest per-gulp temporaries (the imager's voltage layout, the tree's working rows).
    CuPy's pool keeps each stream's freed blocks for that stream, and arrays made in between split them,
    so under a pool limit (``gpu_memory_gb``) an array made and freed each gulp can find no block of its
    size although the bytes in use are below the limit. Kept, it takes its memory once.

    :meth:`take` returns a contiguous array of the asked shape and dtype, a view of a kept buffer (its
    contents are whatever the last use left), and a :class:`Lease`. A buffer is used again only when its
    last lease is gone and the current CUDA stream (and device) is the one it was made on: work queued on
    one stream runs in order, so the next use cannot overtake the last one's kernels. Up to ``depth``
    buffers are kept: where a reader holds one call's array while the next call is made (a search reads a
    push's rows during the next push), ``depth=2`` lets the two buffers take turns.
    Where none is free, of the stream and large enough, a new buffer is made and kept in place of a free
    one, else of the oldest (which lives on in its readers until they let it go). On the host the stream
    is always the same.

    depth : buffers kept (>= 1)."""

    def __init__(self, depth: int = 1):
        if int(depth) < 1:
            raise ValueError(f"Workspace: depth must be at least 1, got {depth}")
        self.depth = int(depth)
        self._slots = []             # [buffer, stream key, weak reference to its last lease or None], oldest first

    @staticmethod
    def _stream_key(xp):
        if xp is np:
            return ("host",)
        return (xp.cuda.Device().id, xp.cuda.get_current_stream().ptr)

    @staticmethod
    def _free(slot):
        return slot[2] is None or slot[2]() is None

    def take(self, xp, shape, dtype):
        """(array of ``shape``, ``dtype`` in ``xp``, its :class:`Lease`)."""
        dtype = np.dtype(dtype)
        nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        key = self._stream_key(xp)
        slot = next((s for s in self._slots if self._free(s) and s[1] == key and get_xp(s[0]) is xp
                     and s[0].nbytes >= nbytes), None)
        if slot is None:
            if len(self._slots) >= self.depth:
                # let one go before the new one is made (its readers, if any, keep it alive)
                del self._slots[next((i for i, s in enumerate(self._slots) if self._free(s)), 0)]
            slot = [xp.empty(max(nbytes, 1), np.uint8), key, None]
            self._slots.append(slot)
        lease = Lease()
        slot[2] = weakref.ref(lease)
        return slot[0][:nbytes].view(dtype).reshape(shape), lease

    @property
    def nbytes(self) -> int:
        """Bytes of the kept buffers (0 before the first use)."""
        return sum(int(s[0].nbytes) for s in self._slots)

    def release(self) -> None:
        """Let the buffers go (the next use makes a new one)."""
        self._slots = []
