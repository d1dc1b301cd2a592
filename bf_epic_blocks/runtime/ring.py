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
* *Unguaranteed* readers never slow the writer (a ring that has one gets one more write gulp of
  capacity, because the writer overwrites from its reserve on). A frame older than
  ``head - capacity`` is gone;
  a read that asks for gone frames jumps forward by whole strides and reports the jump in
  ``span.nframe_skipped`` (the pipeline hands it to ``on_skip``).

Zero copy. Spans are views of the ring's storage, as in Bifrost: a write span is the ring
memory the frames will occupy, and a guaranteed reader's span is the ring memory holding them
(read-only NumPy views on the host). Storage is one buffer per sequence laid out
(ringlets..., capacity + ghost, frame...): the ``ghost`` frames after the end can mirror the first
``ghost`` frames of the buffer (ghost = the largest write or read gulp), so a span that wraps the
end is still one contiguous view. A write span that crosses the end is written there and its part
past the end copied to the head at commit; a read span that crosses it has the head's part copied
into the ghost when it is handed out -- only then: gulps that divide the capacity never copy (an
eager mirror of every write landing in the head would copy frames that no span ever reads across
the end, a large share of the traffic for gulps of whole-band images). Unguaranteed readers
get copies taken under the ring lock (so ``nframe_overwritten`` is always 0); a write
overwrites frames only after ``reserve`` has moved the ring's tail past them.

Ordering on the GPU ('cuda' rings, CuPy). No device synchronisation: each block thread runs on
its own CUDA stream (the pipeline makes one current per thread), and the ring orders the
streams with events. A commit records a *ready* event on the writer's stream (after the
writer's kernels and the ghost copies); a reader's stream waits on it before the span is handed
out. A guaranteed reader records a *release* event on its stream when it releases a span (an
unguaranteed one after its copy); ``reserve`` makes the writer's stream wait on every reader's
latest release event before the writer may overwrite memory they read.

Spans are shaped ringlets + [nframe] + frame (see :mod:`.dtypes` for the storage dtypes of
complex-integer types).
"""
from __future__ import annotations

import math
import threading
from numbers import Integral

import numpy as np

from ..imaging._xp import copy_rows, pinned_empty
from .dtypes import SPACES, storage_dtype, itemsize_bytes
from .header import plain_copy, validate_header, split_shape

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


def _frame_rows(buf, nr, first, n):
    """Frames [first, first + n) of C-contiguous storage ``buf`` whose frame axis is ``nr``: a 2-D view,
    one row per ringlet (the ringlet axes before the frame axis), each row those frames' bytes."""
    rows = int(np.prod(buf.shape[:nr], dtype=np.int64))
    per = int(np.prod(buf.shape[nr + 1:], dtype=np.int64))
    return buf.reshape(rows, -1)[:, first * per:(first + n) * per]


class _Seq:
    """Ring-internal state of one sequence."""

    def __init__(self, ring, header, index, base):
        self.header = header
        self.index = index
        self.base = base            # global frame number of local frame 0
        self.nframe = 0             # frames committed so far
        self.ended = False
        self.buf = None             # storage (allocated at the first reserve)
        self.buf_cap = 0            # capacity and ghost the buffer was laid out for
        self.buf_ghost = 0
        t = header['_tensor']
        ringlet, frame = split_shape(t['shape'])
        sdt, extra = storage_dtype(t['dtype'], ring.space)
        self.ringlet_shape, self.frame_shape = ringlet, frame
        self.nr = len(ringlet)      # the frame axis of storage and spans
        self.sdtype, self.extra = sdt, extra
        self.tensor = {
            'dtype': t['dtype'], 'ringlet_shape': ringlet,
            'nringlet': int(np.prod(ringlet, dtype=np.int64)), 'frame_shape': frame,
            'dtype_nbyte': itemsize_bytes(t['dtype']),
            'frame_nbyte': int(np.prod(frame, dtype=np.int64)) * itemsize_bytes(t['dtype']),
        }

    def span_shape(self, n):
        return tuple(self.ringlet_shape) + (n,) + tuple(self.frame_shape) + self.extra

    def buf_shape(self, nslot):
        return tuple(self.ringlet_shape) + (nslot,) + tuple(self.frame_shape) + self.extra

    def at(self, a, b):
        """Index selecting storage/span frames [a, b) (the frame axis follows the ringlets)."""
        return (slice(None),) * self.nr + (slice(a, b),)


class Ring:
    """A bounded ring in one memory space ('system', 'cuda_host' or 'cuda')."""
    instance_count = 0

    def __init__(self, space='system', name=None, owner=None):
        self.xp = xp_for_space(space)
        self.space = space
        self.on_device = space == 'cuda'
        if name is None:
            name = 'ring_%i' % Ring.instance_count
            Ring.instance_count += 1
        self.name = name
        self.owner = owner
        self._cond = threading.Condition()
        # the sequences a reader may still open, oldest first; _seqs[0] is sequence number _seq0
        # (a service runs for weeks, a sequence per F-engine reset: past ones are forgotten)
        self._seqs = []
        self._seq0 = 0
        self._names = set()      # every sequence name used: unique for the ring's life
        self._head = 0           # global frames committed
        self._tail = 0           # frames before this global number are gone (monotone)
        self._cap = 0
        self._ghost = 0          # mirrored frames after the end of each buffer
        self._requested = 0      # largest buffer request (frames)
        self._max_write = 0      # largest write gulp seen
        self._max_read = 0       # largest read gulp seen
        self._readers = []
        self._writing = False
        self._ended = False      # the writer has finished with this ring
        self._aborted = False
        self._ready_event = None     # 'cuda': all committed data is in memory after this event
        self._retired_events = []    # 'cuda': last release events of readers that closed

    def __repr__(self):
        return f"Ring(name={self.name!r}, space={self.space!r})"

    @property
    def capacity(self):
        """Current capacity in frames (0 until a gulp is known)."""
        return self._cap

    @property
    def ghost(self):
        """Frames mirrored past the end of the buffer (spans up to this long never need a copy)."""
        return self._ghost

    # -- CUDA ordering (call with the lock held; no-ops on the host) ----------------------------
    def _stream(self):
        return self.xp.cuda.get_current_stream()

    def _new_event(self):
        ev = self.xp.cuda.Event(block=False, disable_timing=True, interprocess=False)
        ev.record(self._stream())
        return ev

    def _await_ready(self):
        """The current stream waits until every committed frame is in memory."""
        if self.on_device and self._ready_event is not None:
            self._stream().wait_event(self._ready_event)

    def _publish(self):
        """Record that the current stream's work so far (writes, ghost copies) makes the ring's
        contents; readers wait on this event. Chained: it also covers the previous one."""
        if self.on_device:
            self._await_ready()
            self._ready_event = self._new_event()

    def _await_readers(self):
        """The current (writer's) stream waits until the readers' work on released or copied
        spans is done, so the memory may be overwritten."""
        if not self.on_device:
            return
        stream = self._stream()
        for rd in self._readers:
            if rd.event is not None:
                stream.wait_event(rd.event)
        for ev in self._retired_events:
            stream.wait_event(ev)
        self._retired_events = []

    # -- storage (call with the lock held) -------------------------------------------------
    def _check_abort(self):
        if self._aborted:
            raise PipelineShutdown(f"ring '{self.name}' was shut down")

    def _wait(self):
        self._check_abort()
        self._cond.wait(_WAIT_S)
        self._check_abort()

    def _alloc(self, seq):
        shape = seq.buf_shape(self._cap + self._ghost)
        # 'cuda_host' (as in Bifrost): page-locked where there is a GPU, so a GPU reads it with
        # asynchronous copies at full bus speed
        seq.buf = pinned_empty(shape, seq.sdtype) if self.space == 'cuda_host' else self.xp.empty(shape, seq.sdtype)
        seq.buf_cap, seq.buf_ghost = self._cap, self._ghost

    def _sync_ghost(self, seq, lo, hi):
        """Mirror storage slots [lo, hi) into the ghost where they have a ghost copy."""
        hi = min(hi, seq.buf_ghost)
        if hi > lo:
            c = seq.buf_cap
            seq.buf[seq.at(c + lo, c + hi)] = seq.buf[seq.at(lo, hi)]

    def _store(self, seq, first, src):
        """Copy frames (span-shaped ``src``, frame axis after the ringlets) into the slots of
        local frames [first, first + n) of ``seq``, wrapping (the ghost is filled when read)."""
        n = src.shape[seq.nr]
        if n == 0:
            return
        cap = seq.buf_cap
        start = first % cap
        part = min(n, cap - start)
        seq.buf[seq.at(start, start + part)] = src[seq.at(0, part)]
        if n > part:
            seq.buf[seq.at(0, n - part)] = src[seq.at(part, n)]

    def _finish_write(self, seq, start, n):
        """After frames were written in place at storage slots [start, start + n): copy the
        part past the end to the head of the buffer."""
        cap = seq.buf_cap
        if start + n > cap:
            seq.buf[seq.at(0, start + n - cap)] = seq.buf[seq.at(cap, start + n)]

    def _span_view(self, seq, offset, n):
        """Frames [offset, offset + n) of ``seq``: a view of the storage when they fit in one
        contiguous run (always, for n <= ghost: a span that crosses the end has the head's part
        mirrored into the ghost first, on the reader's stream), else a copy. Host views are
        read-only. Called under the ring's lock, after the reader's stream waited for the frames."""
        if n == 0 or seq.buf is None:
            return self.xp.empty(seq.span_shape(n), seq.sdtype)
        cap = seq.buf_cap
        start = offset % cap
        if start + n <= cap + seq.buf_ghost:
            # the head's frames [0, start + n - cap) are committed and held (a guaranteed reader's
            # frames are not overwritten before it releases them; an unguaranteed one copies them now),
            # and no write can be filling their mirror: a writer's span past the end mirrors head
            # slots that hold no unreleased frame
            self._sync_ghost(seq, 0, start + n - cap)
            view = seq.buf[seq.at(start, start + n)]
            if not self.on_device:
                view.flags.writeable = False
            return view
        part = cap - start
        return self.xp.concatenate([seq.buf[seq.at(start, cap)],
                                    seq.buf[seq.at(0, n - part)]], axis=seq.nr)

    def _update_capacity(self):
        new = max(self._requested, self._max_write + self._max_read, 1)
        if any(not r.guarantee for r in self._readers):
            # the writer overwrites from its reserve on (not from its commit): one more write
            # gulp keeps an unguaranteed reader's window at the requested size
            new += self._max_write
        ghost = max(self._max_write, self._max_read)
        if new <= self._cap and ghost <= self._ghost:
            return
        new, ghost = max(new, self._cap), max(ghost, self._ghost)
        old = self._cap
        self._tail = max(self._tail, self._head - old)
        self._cap, self._ghost = new, ghost
        moved = False
        for seq in self._seqs:
            if seq.buf is None:
                continue
            obuf, ocap = seq.buf, seq.buf_cap
            self._alloc(seq)
            lo = max(0, self._tail - seq.base)
            if seq.nframe > lo:
                if not moved:
                    self._await_ready()
                    moved = True
                self._move_frames(seq, obuf, ocap, lo)
        if moved and self.on_device:
            self._publish()
            # the old buffers are freed when the last view goes: finish copying out of them
            self._stream().synchronize()
        self._cond.notify_all()

    def _move_frames(self, seq, obuf, ocap, lo):
        """Copy local frames [lo, seq.nframe) of ``seq`` from its old storage ``obuf`` (``ocap`` slots)
        into its new one, in the runs of frames contiguous in both (three at most). On a GPU each run is
        one 2-D memcpy on the current stream: a copy by index arrays would be CuPy indexing kernels,
        specialised on the ring's dtype and rank and compiled at the first growth -- which comes when a
        late reader asks for room while data flow, at a moment no kernel store can foresee."""
        new = seq.buf_cap
        i = lo
        while i < seq.nframe:
            a, b = i % ocap, i % new
            n = min(seq.nframe - i, ocap - a, new - b)
            if self.on_device:
                if not (seq.buf.flags.c_contiguous and obuf.flags.c_contiguous and
                        copy_rows(_frame_rows(seq.buf, seq.nr, b, n), _frame_rows(obuf, seq.nr, a, n),
                                  self._stream())):
                    raise ValueError("ring storage must be C-contiguous and of one dtype to be moved")
            else:
                seq.buf[seq.at(b, b + n)] = obuf[seq.at(a, a + n)]
            i += n

    def _request(self, buf_nframe=None, write_gulp=None, read_gulp=None):
        with self._cond:
            if buf_nframe:
                self._requested = max(self._requested, int(buf_nframe))
            if write_gulp:
                self._max_write = max(self._max_write, int(write_gulp))
            if read_gulp:
                self._max_read = max(self._max_read, int(read_gulp))
            self._update_capacity()

    @property
    def _nseq(self):
        """Sequences begun so far (forgotten ones included)."""
        return self._seq0 + len(self._seqs)

    def _seq_number(self, i):
        return self._seqs[i - self._seq0]

    def _drop_old(self):
        for seq in self._seqs:
            if seq.buf is not None and seq.ended and seq.base + seq.nframe <= self._tail:
                seq.buf = None  # entirely overrun: free its memory
        self._forget()

    def _forget(self):
        """Forget the oldest sequences that are ended, hold no memory and every reader is past (their
        headers go too). A ring without readers keeps them for a reader still to come."""
        while (self._seqs and self._readers and self._seqs[0].ended and self._seqs[0].buf is None
               and all(r.next_index > self._seq0 for r in self._readers)):
            self._seqs.pop(0)
            self._seq0 += 1

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
            if hdr['name'] in self._names:
                raise ValueError(f"ring '{self.name}': sequence name {hdr['name']!r} is "
                                 "already used; names must be unique within a ring")
            self._forget()
            seq = _Seq(self, hdr, self._nseq, self._head)
            self._seqs.append(seq)
            self._names.add(hdr['name'])
            self._cond.notify_all()
        self._request(buf_nframe=buf_nframe, write_gulp=gulp_nframe)
        return seq

    def _end_sequence(self, seq):
        with self._cond:
            seq.ended = True
            self._cond.notify_all()

    def _reserve(self, seq, nframe):
        """Wait for room for ``nframe`` frames after the head; returns the writable view of the
        storage they will occupy (the tail has moved past the frames it overwrites)."""
        with self._cond:
            if nframe > self._max_write:
                self._max_write = nframe
                self._update_capacity()
            while True:
                self._check_abort()
                held = [r.effective_pos() for r in self._readers
                        if r.guarantee and not r.closed]
                if not held or self._head + nframe - min(held) <= self._cap:
                    break
                self._wait()
            # from here the writer may overwrite frames older than head + nframe - capacity
            self._tail = max(self._tail, self._head + nframe - self._cap)
            self._drop_old()
            self._await_readers()
            if seq.buf is None:
                self._alloc(seq)
            start = seq.nframe % seq.buf_cap
            return seq.buf, start, seq.buf[seq.at(start, start + nframe)]

    def _commit(self, seq, span, nframe):
        with self._cond:
            self._check_abort()
            if nframe:
                if span.buf is seq.buf:
                    self._finish_write(seq, span.start, nframe)
                else:   # the buffer was re-laid out (a reader asked for more room) meanwhile
                    self._store(seq, seq.nframe, span.data[seq.at(0, nframe)])
                seq.nframe += nframe
                self._head += nframe
                self._tail = max(self._tail, self._head - self._cap)
                self._drop_old()
                self._publish()
            self._cond.notify_all()

    # -- reader side ----------------------------------------------------------------------
    def open_reader(self, guarantee=True):
        """Register a reader now (a guaranteed one holds frames from this moment on)."""
        with self._cond:
            rd = _Reader(self, guarantee)
            self._readers.append(rd)
            if not rd.guarantee:
                self._update_capacity()
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
    """Writable span: fill ``data`` (ringlets + [nframe] + frame), then commit.

    ``data`` is the ring memory the frames will occupy (zero-copy); on 'cuda' fill it with work
    queued on the current stream (the commit orders readers after it)."""

    def __init__(self, sequence, nframe):
        self.sequence = sequence
        self.ring = sequence.ring
        seq = sequence._seq
        self.buf, self.start, self.data = self.ring._reserve(seq, nframe)
        self.frame_offset = seq.nframe
        self.nframe = nframe
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
            self.ring._commit(self.sequence._seq, self, self.commit_nframe)
            self.buf = None


class _Reader:
    """A registered reader. A guaranteed one holds every frame from ``effective_pos()`` on."""

    def __init__(self, ring, guarantee):
        self.ring = ring
        self.guarantee = bool(guarantee)
        self.pos = ring._tail     # oldest frame needed inside the open sequence
        self.current = None       # the open sequence, or None between sequences
        self.next_index = ring._seq0  # number of the next sequence to open (the oldest still kept)
        self.closed = False
        self.event = None         # 'cuda': its latest release (or copy) event

    def effective_pos(self):
        ring = self.ring
        if self.current is not None:
            return self.pos
        # Between sequences: the reader will need the next sequence from its start
        # (or, before that sequence exists, everything the writer writes from now on).
        if self.next_index < ring._nseq:
            return max(ring._seq_number(self.next_index).base, ring._tail)
        return ring._head

    def close(self):
        with self.ring._cond:
            self.closed = True
            if self in self.ring._readers:
                self.ring._readers.remove(self)
                if self.event is not None:
                    self.ring._retired_events.append(self.event)
            self.ring._cond.notify_all()

    def _hold(self, gpos):
        if gpos > self.pos:
            self.pos = gpos
            self.ring._cond.notify_all()

    def sequences(self):
        ring = self.ring
        while True:
            with ring._cond:
                while ring._nseq <= self.next_index and not ring._ended:
                    ring._wait()
                if ring._nseq <= self.next_index:
                    return
                seq = ring._seq_number(self.next_index)
                self.pos = max(seq.base, ring._tail)
                self.current = seq
            yield ReadSequence(self, seq)
            with ring._cond:  # done with it: release its frames
                self.current = None
                self.next_index += 1
                ring._forget()
                ring._cond.notify_all()


class ReadSequence(_SequenceBase):
    def __init__(self, reader, seq):
        self._reader = reader
        self._ring = reader.ring
        self._seq = seq
        self._header = plain_copy(seq.header)    # each reader's own (blocks may change theirs)

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

    def _empty_span(self, offset, skipped):
        seq = self._seq
        return ReadSpan(self, offset, self._ring.xp.empty(seq.span_shape(0), seq.sdtype), skipped)

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
                        return self._empty_span(offset, skipped) if skipped else None
                    skipped += jump
                    offset += jump
                    continue
                avail = seq.nframe - offset
                if avail >= nframe:
                    break
                if seq.ended:
                    if avail <= overlap:
                        return self._empty_span(offset, skipped) if skipped else None
                    break
                ring._wait()
            n = min(nframe, seq.nframe - offset)
            ring._await_ready()
            data = ring._span_view(seq, offset, n)
            if not rd.guarantee:
                # the writer does not wait for this reader: take a copy before the lock goes
                data = data.copy()
                if ring.on_device:
                    rd.event = ring._new_event()
        return ReadSpan(self, offset, data, skipped)


class ReadSpan:
    """Frames [frame_offset, frame_offset + nframe) of a sequence: a read-only view of the
    ring's memory for a guaranteed reader (valid until the span is released), a copy for an
    unguaranteed one."""
    nframe_overwritten = 0

    def __init__(self, sequence, frame_offset, data, nframe_skipped=0):
        self.sequence = sequence
        self.ring = sequence.ring
        self.frame_offset = frame_offset
        self.data = data
        self.nframe = data.shape[len(sequence._seq.ringlet_shape)]
        self.nframe_skipped = nframe_skipped
        self._released = False

    @property
    def tensor(self):
        return self.sequence.tensor

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()

    def release(self):
        """Done with the data: on 'cuda', the writer may overwrite it once the work queued so
        far on the current stream is done (recorded as this reader's release event)."""
        if self._released:
            return
        self._released = True
        rd = self.sequence._reader
        if rd.guarantee and self.ring.on_device and self.nframe:
            with self.ring._cond:
                rd.event = self.ring._new_event()
