"""Bounded rings of sequences, with Bifrost's ``ring2`` names and semantics.

Model. A ring carries a series of *sequences* (one header each, see :mod:`.header`); each
sequence is a stream of *frames* (one frame = the tensor shape without its -1 axis). Frames of
all sequences are numbered on one global clock; the ring holds the last ``capacity`` of them:

* ``capacity`` = the largest of the writer's and readers' buffer requests
  (``buffer_nframe``, else ``ceil((gulp + overlap) * buffer_factor)``, factor 3), and never less
  than one write gulp + one read gulp (so a writer and a guaranteed reader always make progress).
* A writer ``reserve``s n frames, fills ``span.data`` and commits c <= n of them. ``reserve``
  blocks while any *guaranteed* reader would fall more than ``capacity`` frames behind the head
  (back-pressure: guaranteed readers lose nothing).
* *Unguaranteed* readers never slow the writer. A frame older than ``head - capacity`` is gone;
  a read that asks for gone frames jumps forward by whole strides and reports the jump in
  ``span.nframe_skipped`` (the pipeline hands it to ``on_skip``).
* Read spans are copies taken under the ring lock, so ``nframe_overwritten`` is always 0.

Storage: one circular buffer per sequence, laid out (capacity, ringlets..., frame...) in
NumPy ('system', 'cuda_host') or CuPy ('cuda'); spans are shaped ringlets + [nframe] + frame
(see :mod:`.dtypes` for the storage dtypes of complex-integer types).
"""
from __future__ import annotations

import math
import threading
from numbers import Integral

import numpy as np

from .dtypes import SPACES, storage_dtype, itemsize_bytes
from .header import validate_header, split_shape

_WAIT_S = 0.5  # condition waits re-check at least this often (belt and braces)


class PipelineShutdown(Exception):
    """Raised inside block threads when the pipeline is shutting down (not an error)."""


def _cupy_with_device():
    try:
        import cupy
        if cupy.cuda.runtime.getDeviceCount() > 0:
            return cupy
    except Exception:
        pass
    return None


def xp_for_space(space):
    """numpy for host spaces, cupy for 'cuda' (ValueError when CuPy or a GPU is missing)."""
    if space not in SPACES:
        raise ValueError(f"unknown memory space {space!r}; expected one of {SPACES}")
    if space == 'cuda':
        cp = _cupy_with_device()
        if cp is None:
            raise ValueError("space 'cuda' needs CuPy and a CUDA device, and none is available "
                             "here; use space='system'")
        return cp
    return np


def _check_nframe(n, what):
    if isinstance(n, bool) or not isinstance(n, Integral) or n < 0:
        raise ValueError(f"{what} must be an int >= 0, got {n!r}")
    return int(n)


class _Seq:
    """Ring-internal state of one sequence."""

    def __init__(self, ring, header, index, base):
        self.header = header
        self.index = index
        self.base = base            # global frame number of local frame 0
        self.nframe = 0             # frames committed so far
        self.ended = False
        self.buf = None             # circular buffer (allocated at first commit)
        t = header['_tensor']
        ringlet, frame = split_shape(t['shape'])
        sdt, extra = storage_dtype(t['dtype'], ring.space)
        self.ringlet_shape, self.frame_shape = ringlet, frame
        self.sdtype, self.extra = sdt, extra
        self.tensor = {
            'dtype': t['dtype'], 'ringlet_shape': ringlet,
            'nringlet': int(np.prod(ringlet, dtype=np.int64)), 'frame_shape': frame,
            'dtype_nbyte': itemsize_bytes(t['dtype']),
            'frame_nbyte': int(np.prod(frame, dtype=np.int64)) * itemsize_bytes(t['dtype']),
        }

    def span_shape(self, n):
        return tuple(self.ringlet_shape) + (n,) + tuple(self.frame_shape) + self.extra

    def buf_shape(self, cap):
        return (cap,) + tuple(self.ringlet_shape) + tuple(self.frame_shape) + self.extra


class Ring:
    """A bounded ring in one memory space ('system', 'cuda_host' or 'cuda')."""
    instance_count = 0

    def __init__(self, space='system', name=None, owner=None):
        self.xp = xp_for_space(space)
        self.space = space
        if name is None:
            name = 'ring_%i' % Ring.instance_count
            Ring.instance_count += 1
        self.name = name
        self.owner = owner
        self._cond = threading.Condition()
        self._seqs = []
        self._head = 0           # global frames committed
        self._tail = 0           # frames before this global number are gone (monotone)
        self._cap = 0
        self._requested = 0      # largest buffer request (frames)
        self._max_write = 0      # largest write gulp seen
        self._max_read = 0       # largest read gulp seen
        self._readers = []
        self._writing = False
        self._ended = False      # the writer has finished with this ring
        self._aborted = False

    def __repr__(self):
        return f"Ring(name={self.name!r}, space={self.space!r})"

    @property
    def capacity(self):
        """Current capacity in frames (0 until a gulp is known)."""
        return self._cap

    # -- internals (call with the lock held) ---------------------------------------------
    def _check_abort(self):
        if self._aborted:
            raise PipelineShutdown(f"ring '{self.name}' was shut down")

    def _wait(self):
        self._check_abort()
        self._cond.wait(_WAIT_S)
        self._check_abort()

    def _sync(self):
        if self.space == 'cuda':  # make device copies visible to other threads/streams
            self.xp.cuda.get_current_stream().synchronize()

    def _update_capacity(self):
        new = max(self._requested, self._max_write + self._max_read, 1)
        if new <= self._cap:
            return
        old = self._cap
        self._tail = max(self._tail, self._head - old)
        for seq in self._seqs:
            if seq.buf is None:
                continue
            nbuf = self.xp.empty(seq.buf_shape(new), seq.sdtype)
            lo = max(0, self._tail - seq.base)
            if seq.nframe > lo:
                idx = self.xp.arange(lo, seq.nframe)
                nbuf[idx % new] = seq.buf[idx % old]
            seq.buf = nbuf
        self._cap = new
        self._sync()
        self._cond.notify_all()

    def _request(self, buf_nframe=None, write_gulp=None, read_gulp=None):
        with self._cond:
            if buf_nframe:
                self._requested = max(self._requested, int(buf_nframe))
            if write_gulp:
                self._max_write = max(self._max_write, int(write_gulp))
            if read_gulp:
                self._max_read = max(self._max_read, int(read_gulp))
            self._update_capacity()

    def _copy_in(self, seq, src_frames_first):
        """Append frames (array shaped (c, ringlets..., frame...)) to ``seq``."""
        c = src_frames_first.shape[0]
        cap = self._cap
        if seq.buf is None:
            seq.buf = self.xp.empty(seq.buf_shape(cap), seq.sdtype)
        start = seq.nframe % cap
        first = min(c, cap - start)
        seq.buf[start:start + first] = src_frames_first[:first]
        if c > first:
            seq.buf[:c - first] = src_frames_first[first:]

    def _copy_out(self, seq, offset, n):
        """Frames [offset, offset + n) of ``seq`` as a fresh span-shaped array."""
        xp, cap = self.xp, self._cap
        start = offset % cap
        first = min(n, cap - start)
        if n == 0 or seq.buf is None:
            frames = xp.empty(seq.buf_shape(n), seq.sdtype)
        elif n > first:
            frames = xp.concatenate([seq.buf[start:], seq.buf[:n - first]], axis=0)
        else:
            frames = seq.buf[start:start + n].copy()
        r = len(seq.ringlet_shape)
        if r:
            frames = xp.ascontiguousarray(xp.moveaxis(frames, 0, r))
        return frames

    def _drop_old(self):
        for seq in self._seqs:
            if seq.buf is not None and seq.ended and seq.base + seq.nframe <= self._tail:
                seq.buf = None  # entirely overrun: free its memory

    # -- writer side ----------------------------------------------------------------------
    def begin_writing(self):
        """Context manager owning the write end; its ``begin_sequence`` starts sequences."""
        return RingWriter(self)

    def end_writing(self):
        with self._cond:
            self._writing = False
            self._ended = True
            for seq in self._seqs:
                seq.ended = True
            self._cond.notify_all()

    def _begin_sequence(self, header, gulp_nframe, buf_nframe):
        gulp_nframe = _check_nframe(gulp_nframe, 'gulp_nframe')
        hdr = validate_header(header, where=f"header of a sequence in ring '{self.name}'")
        with self._cond:
            if not self._writing:
                raise RuntimeError(f"ring '{self.name}': begin_sequence outside begin_writing")
            if self._seqs and not self._seqs[-1].ended:
                raise RuntimeError(f"ring '{self.name}': previous sequence "
                                   f"'{self._seqs[-1].header['name']}' was not ended")
            if any(s.header['name'] == hdr['name'] for s in self._seqs):
                raise ValueError(f"ring '{self.name}': sequence name {hdr['name']!r} is "
                                 "already used; names must be unique within a ring")
            seq = _Seq(self, hdr, len(self._seqs), self._head)
            self._seqs.append(seq)
            self._cond.notify_all()
        self._request(buf_nframe=buf_nframe, write_gulp=gulp_nframe)
        return seq

    def _end_sequence(self, seq):
        with self._cond:
            seq.ended = True
            self._cond.notify_all()

    def _reserve(self, nframe):
        with self._cond:
            if nframe > self._max_write:
                self._max_write = nframe
                self._update_capacity()
            while True:
                self._check_abort()
                held = [r.effective_pos() for r in self._readers
                        if r.guarantee and not r.closed]
                if not held or self._head + nframe - min(held) <= self._cap:
                    return
                self._wait()

    def _commit(self, seq, data, nframe):
        self._sync()  # the block's kernels that filled data must be finished
        with self._cond:
            self._check_abort()
            if nframe:
                r = len(seq.ringlet_shape)
                src = data[(slice(None),) * r + (slice(0, nframe),)]
                if r:
                    src = self.xp.moveaxis(src, r, 0)
                self._copy_in(seq, src)
                seq.nframe += nframe
                self._head += nframe
                self._tail = max(self._tail, self._head - self._cap)
                self._drop_old()
                self._sync()
            self._cond.notify_all()

    # -- reader side ----------------------------------------------------------------------
    def open_reader(self, guarantee=True):
        """Register a reader now (a guaranteed one holds frames from this moment on)."""
        with self._cond:
            rd = _Reader(self, guarantee)
            self._readers.append(rd)
            return rd

    def read(self, whence='earliest', guarantee=True):
        """Yield a :class:`ReadSequence` per sequence, in order, until the writer finishes."""
        if whence != 'earliest':
            raise ValueError("only whence='earliest' is supported by this runtime")
        rd = self.open_reader(guarantee)
        try:
            yield from rd.sequences()
        finally:
            rd.close()

    def abort(self):
        """Wake every waiter with :class:`PipelineShutdown` (used by Pipeline.shutdown)."""
        with self._cond:
            self._aborted = True
            self._cond.notify_all()


class RingWriter:
    def __init__(self, ring):
        with ring._cond:
            if ring._writing:
                raise RuntimeError(f"ring '{ring.name}' already has a writer")
            ring._writing = True
        self.ring = ring

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.ring.end_writing()

    def begin_sequence(self, header, gulp_nframe, buf_nframe=None):
        """Start a sequence (header validated; see :mod:`.header`); a context manager."""
        return WriteSequence(self.ring, header, gulp_nframe, buf_nframe or gulp_nframe)


class _SequenceBase:
    @property
    def header(self):
        return self._header

    @property
    def name(self):
        return self._seq.header['name']

    @property
    def time_tag(self):
        return self._seq.header['time_tag']

    @property
    def tensor(self):
        return self._seq.tensor

    @property
    def nringlet(self):
        return self._seq.tensor['nringlet']

    @property
    def ring(self):
        return self._ring


class WriteSequence(_SequenceBase):
    def __init__(self, ring, header, gulp_nframe, buf_nframe):
        self._ring = ring
        self._seq = ring._begin_sequence(header, gulp_nframe, buf_nframe)
        self._header = self._seq.header

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.end()

    def end(self):
        self._ring._end_sequence(self._seq)

    def reserve(self, nframe):
        """A :class:`WriteSpan` of ``nframe`` frames (blocks for back-pressure)."""
        return WriteSpan(self, _check_nframe(nframe, 'reserve nframe'))


class WriteSpan:
    """Writable span: fill ``data`` (ringlets + [nframe] + frame), then commit."""

    def __init__(self, sequence, nframe):
        self.sequence = sequence
        self.ring = sequence.ring
        self.ring._reserve(nframe)
        seq = sequence._seq
        self.frame_offset = seq.nframe
        self.nframe = nframe
        self.data = self.ring.xp.empty(seq.span_shape(nframe), seq.sdtype)
        self.commit_nframe = nframe
        self._closed = False

    @property
    def tensor(self):
        return self.sequence.tensor

    def commit(self, nframe):
        nframe = _check_nframe(nframe, 'commit nframe')
        if nframe > self.nframe:
            raise ValueError(f"cannot commit {nframe} frames of a span of {self.nframe}")
        self.commit_nframe = nframe

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None:
            self.commit_nframe = 0  # never publish a half-written span
        self.close()

    def close(self):
        if not self._closed:
            self._closed = True
            self.ring._commit(self.sequence._seq, self.data, self.commit_nframe)


class _Reader:
    """A registered reader. A guaranteed one holds every frame from ``effective_pos()`` on."""

    def __init__(self, ring, guarantee):
        self.ring = ring
        self.guarantee = bool(guarantee)
        self.pos = ring._tail     # oldest frame needed inside the open sequence
        self.current = None       # the open sequence, or None between sequences
        self.next_index = 0       # index of the next sequence to open
        self.closed = False

    def effective_pos(self):
        ring = self.ring
        if self.current is not None:
            return self.pos
        # Between sequences: the reader will need the next sequence from its start
        # (or, before that sequence exists, everything the writer writes from now on).
        if self.next_index < len(ring._seqs):
            return max(ring._seqs[self.next_index].base, ring._tail)
        return ring._head

    def close(self):
        with self.ring._cond:
            self.closed = True
            if self in self.ring._readers:
                self.ring._readers.remove(self)
            self.ring._cond.notify_all()

    def _hold(self, gpos):
        if gpos > self.pos:
            self.pos = gpos
            self.ring._cond.notify_all()

    def sequences(self):
        ring = self.ring
        while True:
            with ring._cond:
                while len(ring._seqs) <= self.next_index and not ring._ended:
                    ring._wait()
                if len(ring._seqs) <= self.next_index:
                    return
                seq = ring._seqs[self.next_index]
                self.pos = max(seq.base, ring._tail)
                self.current = seq
            yield ReadSequence(self, seq)
            with ring._cond:  # done with it: release its frames
                self.current = None
                self.next_index += 1
                ring._cond.notify_all()


class ReadSequence(_SequenceBase):
    def __init__(self, reader, seq):
        import copy
        self._reader = reader
        self._ring = reader.ring
        self._seq = seq
        self._header = copy.deepcopy(seq.header)

    @property
    def guarantee(self):
        return self._reader.guarantee

    def resize(self, gulp_nframe, buf_nframe=None, buffer_factor=None):
        """Ask for room: ``buf_nframe`` frames, else ceil(gulp_nframe * buffer_factor) (3)."""
        gulp_nframe = _check_nframe(gulp_nframe, 'gulp_nframe')
        if buf_nframe is None:
            factor = 3 if buffer_factor is None else buffer_factor
            if not factor > 0:
                raise ValueError(f"buffer_factor must be > 0, got {buffer_factor!r}")
            buf_nframe = int(math.ceil(gulp_nframe * factor))
        self._ring._request(buf_nframe=buf_nframe, read_gulp=gulp_nframe)

    def read(self, nframe, stride=None, begin=0):
        """Yield :class:`ReadSpan` s of ``nframe`` frames every ``stride`` frames.

        The last span may be short; a span that would hold only overlap frames
        (nframe - stride or fewer) is not yielded. Overrun frames (unguaranteed readers)
        are jumped in whole strides and reported in ``nframe_skipped``."""
        nframe = _check_nframe(nframe, 'nframe')
        stride = nframe if stride is None else _check_nframe(stride, 'stride')
        if stride < 1:
            raise ValueError("stride must be >= 1")
        self._ring._request(read_gulp=nframe)
        offset = begin
        while True:
            span = self._acquire(offset, nframe, stride)
            if span is None:
                return
            with span:
                yield span
            offset = span.frame_offset + stride

    def acquire(self, frame_offset, nframe):
        """One span at ``frame_offset`` (None at the end of the sequence)."""
        return self._acquire(frame_offset, nframe, nframe)

    def _acquire(self, offset, nframe, stride):
        ring, seq, rd = self._ring, self._seq, self._reader
        overlap = max(nframe - stride, 0)
        skipped = 0
        with ring._cond:
            while True:
                ring._check_abort()
                if rd.guarantee:
                    rd._hold(seq.base + offset)
                lost = ring._tail - seq.base - offset
                if lost > 0:  # overrun: jump whole strides past the lost frames
                    jump = -(-lost // stride) * stride
                    if seq.ended and offset + jump >= seq.nframe:
                        jump = max(seq.nframe - offset, 0)
                        skipped += jump
                        offset += jump
                        return (ReadSpan(self, offset, ring.xp.empty(seq.span_shape(0),
                                                                      seq.sdtype), skipped)
                                if skipped else None)
                    skipped += jump
                    offset += jump
                    continue
                avail = seq.nframe - offset
                if avail >= nframe:
                    break
                if seq.ended:
                    if avail <= overlap:
                        return (ReadSpan(self, offset, ring.xp.empty(seq.span_shape(0),
                                                                      seq.sdtype), skipped)
                                if skipped else None)
                    break
                ring._wait()
            n = min(nframe, seq.nframe - offset)
            data = ring._copy_out(seq, offset, n)
            ring._sync()
        return ReadSpan(self, offset, data, skipped)


class ReadSpan:
    """A read-only copy of frames [frame_offset, frame_offset + nframe) of a sequence."""
    nframe_overwritten = 0

    def __init__(self, sequence, frame_offset, data, nframe_skipped=0):
        self.sequence = sequence
        self.ring = sequence.ring
        self.frame_offset = frame_offset
        self.data = data
        self.nframe = data.shape[len(sequence._seq.ringlet_shape)]
        self.nframe_skipped = nframe_skipped

    @property
    def tensor(self):
        return self.sequence.tensor

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()

    def release(self):
        pass
