"""The import layer: real Bifrost when it imports, else the package's own runtime.

Blocks are written once against ``bfp`` (= ``bifrost.pipeline`` or
:mod:`bf_epic_blocks.runtime.pipeline`, same names and hooks) and read/write span data only
through :func:`span_array`, so the same code runs on both.

* ``BIFROST_IMPORTABLE`` -- ``import bifrost`` works here.
* ``HAVE_BIFROST`` -- real Bifrost is the runtime in use (importable, and the environment
  variable ``BF_EPIC_RUNTIME`` is not ``builtin``; ``BF_EPIC_RUNTIME=builtin`` forces ours).
* ``bf`` -- the ``bifrost`` module when in use, else None.
* ``bfp`` -- exposes Pipeline, block_scope, get_default_pipeline, SourceBlock, TransformBlock,
  SinkBlock, MultiTransformBlock. On real Bifrost it is ``bifrost.pipeline``'s namespace with
  subclasses in place of ``Pipeline`` (``run()`` raises a failed block's error as
  :class:`bf_epic_blocks.runtime.pipeline.PipelineError`; plain Bifrost only ends that block's
  thread) and of the reading blocks (their read spans are trimmed to whole frames after an
  overrun); see :mod:`._bifrost_fixes`. ``PipelineError`` is the failure type on both runtimes.
  Importing this module changes nothing in Bifrost; :func:`enable_bifrost_compat` extends the
  read-span fix to every Bifrost block of the process, on request.

Span data forms (see :mod:`bf_epic_blocks.runtime.dtypes`): host spaces give NumPy arrays
(complex integers as Bifrost's structured dtypes), 'cuda' gives CuPy arrays ('ci4' as uint8,
'ci8'/'ci16' as the component type with a trailing (re, im) axis of 2). Always decode complex
data with :func:`unpack_complex`.
"""
from __future__ import annotations

import contextlib
import os

import numpy as np

from ..runtime.dtypes import (  # noqa: F401  (re-exported)
    unpack_complex, pack_ci4, pack_complex, storage_dtype, SUPPORTED_DTYPES,
)
from ..imaging._xp import pinned_empty, to_numpy  # noqa: F401  (re-exported)
from ..runtime import pipeline as _builtin_pipeline
from ..runtime import ring as _builtin_ring
from ._bifrost_fixes import bifrost_namespace, enable_bifrost_compat  # noqa: F401  (re-exported)

try:
    import bifrost as _bifrost  # not on PyPI; present only on Bifrost machines
    BIFROST_IMPORTABLE = True
except Exception:  # pragma: no cover - depends on the machine
    _bifrost = None
    BIFROST_IMPORTABLE = False

RUNTIME_ENV = 'BF_EPIC_RUNTIME'
HAVE_BIFROST = BIFROST_IMPORTABLE and os.environ.get(RUNTIME_ENV, '').lower() != 'builtin'

if HAVE_BIFROST:  # pragma: no cover - needs real Bifrost
    import bifrost.pipeline as _bf_pipeline
    bf = _bifrost
    bfp = bifrost_namespace(_bf_pipeline)
else:
    bfp = _builtin_pipeline
    bf = None

RUNTIME = 'bifrost' if HAVE_BIFROST else 'builtin'

_OUR_SPANS = (_builtin_ring.ReadSpan, _builtin_ring.WriteSpan)


def space_of(obj):
    """Memory space ('system', 'cuda_host', 'cuda'...) of a ring, span, sequence or block."""
    if hasattr(obj, 'orings') and getattr(obj, 'orings', None):
        obj = obj.orings[0]
    for attr in ('space',):
        val = getattr(obj, attr, None)
        if isinstance(val, str):
            return val
    ring = getattr(obj, 'ring', None)
    if ring is not None and isinstance(getattr(ring, 'space', None), str):
        return ring.space
    raise TypeError(f"cannot tell the memory space of {type(obj).__name__}; expected a ring, "
                    "span, sequence or block")


def import_now(*names):
    """Import the modules ``names`` on the calling thread: a block's constructor, which runs on the thread
    that builds the pipeline before any block thread starts. SciPy's subpackages import one another, and two
    block threads importing them for the first time at once can deadlock: Python's import then raises
    ``_DeadlockError`` in one thread and hands the other a partly made module (an ImportError)."""
    import importlib
    for name in names:
        importlib.import_module(name)


def input_xp(block):
    """The array module (CuPy or NumPy) of a block's first input ring: CuPy where it lives on a GPU
    ('cuda'), else NumPy (also for a block driven outside a pipeline, without rings)."""
    if hasattr(block, "irings") and space_of(block.irings[0]) == "cuda":
        import cupy
        return cupy
    return np


def _bf_cuda_to_cupy(data):  # pragma: no cover - needs real Bifrost and a GPU
    """Zero-copy CuPy view of a real-Bifrost 'cuda' array; structured complex-integer types
    become plain arrays (ci4 -> uint8, pairs -> trailing axis of 2) since CuPy has none."""
    import cupy as cp
    dt = np.dtype(data.dtype)
    if not dt.names:
        return data.as_cupy()
    shape, strides = tuple(data.shape), tuple(data.strides)
    comp = dt.fields[dt.names[0]][0]
    if len(dt.names) == 1:
        plain = np.dtype(np.uint8)
    else:
        plain = comp
        shape, strides = shape + (2,), strides + (comp.itemsize,)
    extent = plain.itemsize + sum((n - 1) * s for n, s in zip(shape, strides) if n > 0)
    mem = cp.cuda.UnownedMemory(int(data.ctypes.data), int(extent), data)
    return cp.ndarray(shape, plain, memptr=cp.cuda.MemoryPointer(mem, 0), strides=strides)


def span_array(span):
    """The span's data as a NumPy array (host spaces) or a CuPy array ('cuda'), zero-copy.

    Shape ringlets + [nframe] + frame (plus a trailing 2 for pair types on 'cuda'); writable
    for write spans."""
    if isinstance(span, _OUR_SPANS):
        return span.data
    space = space_of(span)  # pragma: no cover - real Bifrost spans
    if space == 'cuda':
        return _bf_cuda_to_cupy(span.data)
    return np.asarray(span.data)


class _StreamHandle:
    """A raw ``cudaStream_t`` address in the CUDA stream protocol (``__cuda_stream__`` gives
    ``(0, address)``), which is what ``cupy.cuda.Stream.from_external`` takes."""

    __slots__ = ('ptr',)

    def __init__(self, ptr):
        self.ptr = int(ptr)

    def __cuda_stream__(self):
        return (0, self.ptr)


def external_stream(cp, ptr):
    """A CuPy stream object for the CUDA stream at address ``ptr``, owned by someone else.

    ``cp.cuda.Stream.from_external`` (CuPy 14 and later, which deprecates ``ExternalStream``) when
    this CuPy has it, else ``cp.cuda.ExternalStream`` (CuPy 13). Either leaves the stream's
    life to its owner; its device is taken as unknown (-1), so use it on the current device."""
    from_external = getattr(cp.cuda.Stream, 'from_external', None)
    if from_external is not None:
        return from_external(_StreamHandle(ptr))
    return cp.cuda.ExternalStream(int(ptr))


def stream_context():
    """Context to run CuPy work on Bifrost's CUDA stream (real Bifrost with CUDA); a null
    context otherwise: our runtime has already made the block thread's own CUDA stream current
    and orders rings by CUDA events (see :mod:`bf_epic_blocks.runtime.ring`)."""
    if HAVE_BIFROST:  # pragma: no cover - needs real Bifrost
        try:
            import cupy as cp
            ptr = bf.device.get_stream()
        except Exception:  # no CuPy, or a Bifrost built without CUDA: no stream to join
            return contextlib.nullcontext()
        return external_stream(cp, ptr)
    return contextlib.nullcontext()


def _cupy():
    try:
        import cupy
        return cupy if cupy.cuda.runtime.getDeviceCount() > 0 else None
    except Exception:
        return None


def is_pinned(a):
    """True when NumPy array ``a`` lies in page-locked memory made by :func:`pinned_empty`."""
    cp = _cupy()
    if cp is None or not isinstance(a, np.ndarray):
        return False
    while isinstance(a, np.ndarray):
        a = a.base
    if isinstance(a, memoryview):  # NumPy 2's np.frombuffer keeps a memoryview of the exporter
        a = a.obj
    kinds = tuple(k for k in (getattr(cp.cuda, 'PinnedMemoryPointer', None),
                              getattr(cp.cuda, 'PinnedMemory', None)) if k is not None)
    return isinstance(a, kinds)


def pin(a):
    """A copy of NumPy array ``a`` in page-locked memory (``a`` itself when already pinned)."""
    a = np.asarray(a)
    if is_pinned(a) and a.flags.c_contiguous:
        return a
    out = pinned_empty(a.shape, a.dtype)
    out[...] = a
    return out


class HostToDevice:
    """Host->device copies of span data that cross the bus in the ring's storage form (ci4: one
    byte per sample), asynchronously, from page-locked memory.

    ``copy(dst, src)``: ``dst`` a C-contiguous CuPy array (a 'cuda' write span's data), ``src`` a
    NumPy array with the same number of bytes (the storage form; structured or plain). A pinned
    ``src`` (see :func:`pin`) is copied directly; any other is first copied into one of
    ``nstage`` pinned staging buffers, each reused only once its previous copy is done. The copy
    is queued on the current stream -- on our runtime the source block's own stream, so it
    overlaps the consumers' kernels (the ring's commit event orders them after it); on real
    Bifrost, Bifrost's stream, synchronised before returning (Bifrost's commit does not wait
    for our CuPy work). A non-contiguous ``dst`` falls back to :func:`assign_storage`.

    ``room`` (bytes; ``copy`` and ``staging``): what the staging buffers are made for at first, a
    whole gulp's, so that a partial gulp (the end of a stream, a time-base jump) does not make a
    buffer of its own size. Page-locked blocks freed are kept by CuPy's pinned pool for a request
    of exactly their size; a buffer per odd size would stay resident for the life of the process.
    """

    def __init__(self, nstage=2):
        self.nstage = int(nstage)
        self._stages = []      # [pinned buffer, event of its last copy or None]
        self._next = 0
        self.nbytes = 0        # bytes copied
        self.staged_bytes = 0  # of which went through a staging buffer

    def _slot(self, nbytes, room=None):
        """A pinned staging buffer of ``nbytes`` whose previous copy is done, and its slot; a new buffer
        is made for ``max(nbytes, room)`` bytes."""
        size = max(int(nbytes), int(room or 0))
        if len(self._stages) < self.nstage:
            self._stages.append([pinned_empty((size,), np.uint8), None])
        slot = self._stages[self._next]
        self._next = (self._next + 1) % self.nstage
        if slot[0].nbytes < nbytes:
            if slot[1] is not None:
                slot[1].synchronize()
            slot[0], slot[1] = None, None          # the old buffer goes back before the new is made
            slot[0] = pinned_empty((size,), np.uint8)
        elif slot[1] is not None:
            slot[1].synchronize()  # its previous copy must be done before we overwrite it
        return slot[0][:nbytes], slot

    def _stage(self, src, room=None):
        buf, slot = self._slot(src.nbytes, room)
        np.copyto(buf.view(src.dtype).reshape(src.shape), src)  # one host copy, any strides
        self.staged_bytes += src.nbytes
        return buf, slot

    def staging(self, nbytes, room=None):
        """A pinned buffer of ``nbytes`` to fill (a file read straight into it, say) and then hand to
        :meth:`copy_staged`; returns ``(buffer, slot)``. Its previous copy is done. Up to
        ``nstage - 1`` buffers may be filling while another one's copy is queued."""
        return self._slot(nbytes, room)

    def copy_staged(self, dst, buf, slot=None):
        """Queue the copy of the pinned ``buf`` into the C-contiguous CuPy array ``dst`` (same bytes)
        on the current stream; ``slot``: from :meth:`staging`, reusable once this copy is done."""
        import cupy as cp
        with stream_context():
            stream = cp.cuda.get_current_stream()
            cp.cuda.runtime.memcpyAsync(dst.data.ptr, buf.ctypes.data, dst.nbytes,
                                        cp.cuda.runtime.memcpyHostToDevice, stream.ptr)
            if slot is not None:
                slot[1] = stream.record(cp.cuda.Event(block=False, disable_timing=True))
            if HAVE_BIFROST:  # pragma: no cover - needs real Bifrost and a GPU
                stream.synchronize()
        self.nbytes += dst.nbytes
        return dst

    def copy(self, dst, src, room=None):
        src = np.asarray(src)
        if src.nbytes != dst.nbytes:
            raise ValueError(f"host->device copy: {src.dtype} {src.shape} ({src.nbytes} bytes) "
                             f"does not fit {dst.dtype} {dst.shape} ({dst.nbytes} bytes)")
        if not dst.flags.c_contiguous:
            return assign_storage(dst, src)
        if dst.nbytes == 0:
            return dst
        if is_pinned(src) and src.flags.c_contiguous:
            return self.copy_staged(dst, src)
        return self.copy_staged(dst, *self._stage(src, room))


# --- Overrun accounting for readers with guarantee=False that place data by sequence index ----------
# Both runtimes hand such a reader ``on_skip`` for frames an overrun took, but real Bifrost's slices
# always start at 0, and after frames are overwritten *during* ``on_data`` it calls ``on_skip`` for
# frames the block already read and then skips a further gulp without any call. What holds on both
# is the span's ``frame_offset``; these three turn it into counts.

def frames_lost_before(ispan, next_index):
    """Frames between ``next_index`` (the sequence index the block expects next) and this span's
    first: taken by an overrun before it."""
    return max(int(getattr(ispan, 'frame_offset', next_index)) - int(next_index), 0)


def frames_overwritten(ispan, n):
    """Of this span's ``n`` first frames, those the writer reached while the block read them (call
    after copying the data out; real Bifrost reads ring memory in place, our runtime hands
    unguaranteed readers copies: 0)."""
    return min(int(getattr(ispan, 'nframe_overwritten', 0) or 0), int(n))


def frames_lost_at_end(islices, next_index):
    """For ``on_skip``: frames lost after the last span of a sequence (our runtime's slices end at
    the index after them; real Bifrost's start at 0, so theirs give 0 here and its losses before
    a later span are counted by :func:`frames_lost_before`)."""
    end = islices[0].stop
    return max(int(end) - int(next_index), 0) if end is not None else 0


def assign_storage(dst, src):
    """``dst[...] = src`` for span arrays in a storage form, copying raw bytes when the two
    differ only in the structured field types (e.g. Bifrost's ci4 're_im' int8 vs uint8)."""
    if type(dst).__module__.startswith('cupy') and not type(src).__module__.startswith('cupy'):
        import cupy as cp
        src = cp.asarray(src)
    if dst.dtype == src.dtype or not (dst.dtype.names or src.dtype.names):
        dst[...] = src
        return dst
    if dst.dtype.itemsize != src.dtype.itemsize or dst.shape != src.shape:
        raise ValueError(f"cannot store {src.dtype} {src.shape} into {dst.dtype} {dst.shape}")
    dst.view(np.uint8)[...] = src.view(np.uint8)
    return dst


__all__ = ['HAVE_BIFROST', 'BIFROST_IMPORTABLE', 'RUNTIME', 'RUNTIME_ENV', 'bf', 'bfp',
           'enable_bifrost_compat', 'external_stream',
           'frames_lost_before', 'frames_overwritten', 'frames_lost_at_end',
           'span_array', 'space_of', 'stream_context', 'to_numpy', 'assign_storage',
           'is_pinned', 'pinned_empty', 'pin', 'HostToDevice',
           'unpack_complex', 'pack_ci4', 'pack_complex', 'storage_dtype', 'SUPPORTED_DTYPES']
