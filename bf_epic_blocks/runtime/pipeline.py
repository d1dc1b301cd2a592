"""Pipelines and blocks with ``bifrost.pipeline``'s names and hook signatures.

Write a block once against this API and it runs here or inside real Bifrost::

    class Scale(TransformBlock):
        def __init__(self, iring, k, *args, **kwargs):
            super().__init__(iring, *args, **kwargs)
            self.k = k
        def on_sequence(self, iseq):
            return copy.deepcopy(iseq.header)
        def on_data(self, ispan, ospan):
            ospan.data[...] = self.k * ispan.data

    with Pipeline() as p:
        src = SomeSource(...); Scale(src, 2.0, name='scale'); ...
        p.run()

Per input sequence a TransformBlock reads spans of ``gulp + overlap`` frames every ``gulp``
frames (``gulp`` = the block's ``gulp_nframe`` or the input header's), reserves
``define_output_nframes(span.nframe)`` output frames, calls ``on_data`` and commits what it
returns (None = the span minus the output overlap ``define_output_nframes(gulp + overlap) -
define_output_nframes(gulp)``). The output header's ``gulp_nframe`` is
``define_output_nframes(gulp)``.

Runtime-only extras: ``Pipeline.run()`` raises :class:`PipelineError` (chained to the original
exception) when any block fails, after stopping every other block; ``block.stats`` counts
sequences, gulps and frames (see :class:`Block`).

GPU: a block that touches a 'cuda' ring (or is given ``gpu=N``) runs on its own non-blocking
CUDA stream, made current for its thread (``block.stream``); CuPy work in its hooks queues there.
Rings order the streams with CUDA events (see :mod:`.ring`), so blocks never synchronise the
device; a block's stream is synchronised once, when its thread ends.
"""
from __future__ import annotations

import functools
import os
import threading
import time
import warnings
from collections import defaultdict
from contextlib import ExitStack
from numbers import Integral, Real

from .ring import Ring, PipelineShutdown

__all__ = ['Pipeline', 'PipelineError', 'BlockScope', 'block_scope', 'get_default_pipeline',
           'get_current_block_scope', 'get_ring', 'Block', 'SourceBlock',
           'MultiTransformBlock', 'TransformBlock', 'SinkBlock']

_local = threading.local()


def _pipeline_stack():
    if not hasattr(_local, 'pipelines'):
        _local.pipelines = [Pipeline()]
        _local.pipelines[0]._default_of = _local.pipelines
    return _local.pipelines


def _scope_stack():
    if not hasattr(_local, 'scopes'):
        _local.scopes = []
    return _local.scopes


def get_default_pipeline():
    """The pipeline new blocks join: the innermost ``with Pipeline()``, else the default."""
    return _pipeline_stack()[-1]


def get_current_block_scope():
    stack = _scope_stack()
    return stack[-1] if stack else None


def block_scope(*args, **kwargs):
    """``with block_scope(gpu=0, gulp_nframe=...):`` -- defaults for the blocks built inside."""
    return BlockScope(*args, **kwargs)


class PipelineError(RuntimeError):
    """A block failed; ``.block`` is the block, ``__cause__`` the original exception."""

    def __init__(self, block, exc, note=''):
        self.block, self.block_name, self.original = block, block.name, exc
        super().__init__(f"block '{block.name}' ({type(block).__name__}) failed: "
                         f"{type(exc).__name__}: {exc}{note}")


def _opt_int(val, what, minimum):
    if val is None:
        return None
    if isinstance(val, bool) or not isinstance(val, Integral) or val < minimum:
        raise ValueError(f"{what} must be None or an int >= {minimum}, got {val!r}")
    return int(val)


def priority_stream(cupy, priority):
    """A non-blocking CuPy stream at the device's highest ('high') or lowest ('low', CUDA's default) stream
    priority: the GPU's scheduler starts a waiting high-priority kernel's thread blocks before a
    low-priority one's, so that short work other blocks wait for does not queue behind long kernels
    (:attr:`Block.stream_priority`). A CuPy without stream priorities gives a plain stream."""
    if priority not in ('high', 'low'):
        raise ValueError(f"stream priority must be 'high' or 'low', got {priority!r}")
    # CUDA clamps a priority to the device's range (lower is higher; 0, the default, is the least), so
    # no range query is needed (CuPy 14 has none)
    try:
        return cupy.cuda.Stream(non_blocking=True, priority=-1000 if priority == 'high' else 0)
    except TypeError:           # a CuPy without stream priorities
        return cupy.cuda.Stream(non_blocking=True)


class BlockScope:
    """Scope keywords shared by pipelines, ``block_scope`` and blocks. A value left None is
    taken from the enclosing scope (the ``block_scope`` the block was built in, then its
    pipeline). ``share_temp_storage`` and ``fuse`` are accepted for Bifrost compatibility and
    have no effect in this runtime."""
    instance_count = 0

    def __init__(self, name=None, gulp_nframe=None, buffer_nframe=None, buffer_factor=None,
                 core=None, gpu=None, share_temp_storage=False, fuse=False):
        if name is None:
            name = 'BlockScope_%i' % BlockScope.instance_count
            BlockScope.instance_count += 1
        self._name = name
        self._gulp_nframe = _opt_int(gulp_nframe, 'gulp_nframe', 1)
        self._buffer_nframe = _opt_int(buffer_nframe, 'buffer_nframe', 1)
        if buffer_factor is not None and (isinstance(buffer_factor, bool) or
                                          not isinstance(buffer_factor, Real)
                                          or not buffer_factor > 0):
            raise ValueError(f"buffer_factor must be None or a number > 0, got {buffer_factor!r}")
        self._buffer_factor = buffer_factor
        if core is not None and not (
                (isinstance(core, Integral) and not isinstance(core, bool) and core >= 0) or
                (isinstance(core, (list, tuple)) and core and
                 all(isinstance(c, Integral) and c >= 0 for c in core))):
            raise ValueError(f"core must be None, an int >= 0 or a list of them, got {core!r}")
        self._core = core
        self._gpu = _opt_int(gpu, 'gpu', 0)
        self._share_temp_storage = share_temp_storage
        self._fuse = fuse
        self._parent_scope = get_current_block_scope()
        self._children = []
        if self._parent_scope is not None:
            self._parent_scope._children.append(self)

    def _lookup(self, key):
        val = getattr(self, '_' + key)
        if val is None and self._parent_scope is not None:
            return self._parent_scope._lookup(key)
        return val

    gulp_nframe = property(lambda self: self._lookup('gulp_nframe'))
    buffer_nframe = property(lambda self: self._lookup('buffer_nframe'))
    buffer_factor = property(lambda self: self._lookup('buffer_factor'))
    core = property(lambda self: self._lookup('core'))
    gpu = property(lambda self: self._lookup('gpu'))
    share_temp_storage = property(lambda self: self._lookup('share_temp_storage'))
    fuse = property(lambda self: self._lookup('fuse'))

    @property
    def children(self):
        return self._children

    def __enter__(self):
        _scope_stack().append(self)
        return self

    def __exit__(self, *exc):
        popped = _scope_stack().pop()
        assert popped is self


class Pipeline(BlockScope):
    """A set of blocks run together, one thread each. Use as ``with Pipeline() as p: ...;
    p.run()``; blocks built outside any ``with`` join :func:`get_default_pipeline`.

    A pipeline runs once. After the default pipeline has run, a fresh default replaces it.
    """
    instance_count = 0

    def __init__(self, name=None, **kwargs):
        if name is None:
            name = 'Pipeline_%i' % Pipeline.instance_count
            Pipeline.instance_count += 1
        super().__init__(name=name, **kwargs)
        self._parent_scope = None  # a pipeline is the root scope of its blocks
        self.name = name
        self.blocks = []
        self.shutdown_timeout = 5.0
        self._failure = None
        self._changed = threading.Event()
        self._shutdown_event = threading.Event()
        self._ran = False
        self._default_of = None   # the thread's pipeline stack when this is its default
        self.threads = []

    def __enter__(self):
        _pipeline_stack().append(self)
        return self

    def __exit__(self, *exc):
        popped = _pipeline_stack().pop()
        assert popped is self

    def as_default(self):
        return self

    def _rings(self):
        rings = []
        for b in self.blocks:
            for r in list(b.irings) + list(b.orings):
                if all(r is not x for x in rings):
                    rings.append(r)
        return rings

    def _block_failed(self, block, exc):
        if self._failure is None:
            self._failure = (block, exc)
        self.shutdown(wait=False)

    def _thread_done(self):
        self._changed.set()

    def drain(self):
        """End the data gracefully: each source block ends its sequence after the gulp it is writing and
        reads no more; the blocks downstream finish what is in the rings and end their sequences as at
        the end of the data (their files closed). ``run`` then returns as after a normal end."""
        for b in self.blocks:
            ev = getattr(b, "drain_event", None)
            if ev is not None:
                ev.set()
        self._changed.set()

    def shutdown(self, wait=True):
        """Stop every block: wake all ring waits (they raise PipelineShutdown) and join."""
        self._shutdown_event.set()
        for b in self.blocks:
            b.shutdown()
        for r in self._rings():
            r.abort()
        self._changed.set()
        if wait:
            self._join(self.shutdown_timeout)

    def _join(self, timeout):
        deadline = time.monotonic() + timeout
        for t in self.threads:
            t.join(max(0.0, deadline - time.monotonic()))
        return [t for t in self.threads if t.is_alive()]

    def run(self):
        """Run every block to completion. Raises PipelineError if any block failed."""
        if self._ran:
            raise RuntimeError(f"pipeline '{self.name}' has already run; build a new Pipeline")
        self._ran = True
        stack = self._default_of
        if stack is not None and stack[0] is self:  # new blocks go to a fresh default now
            stack[0] = Pipeline()
            stack[0]._default_of = stack
        for b in self.blocks:
            b._open_readers()   # before any thread: guaranteed readers lose nothing
        self.threads = [threading.Thread(target=b._thread_main, name=b.name, daemon=True)
                        for b in self.blocks]
        try:
            for t in self.threads:
                t.start()
            while any(t.is_alive() for t in self.threads) and self._failure is None \
                    and not self._shutdown_event.is_set():
                self._changed.wait(0.2)
                self._changed.clear()
        except BaseException:   # e.g. KeyboardInterrupt: stop the blocks, then re-raise
            self.shutdown()
            raise
        if self._failure is not None or self._shutdown_event.is_set():
            alive = self._join(self.shutdown_timeout)
        else:
            alive = self._join(1e9)
        if self._failure is not None:
            block, exc = self._failure
            note = (f" [{len(alive)} block thread(s) did not stop within "
                    f"{self.shutdown_timeout} s: {[t.name for t in alive]}]" if alive else '')
            raise PipelineError(block, exc, note) from exc


def get_ring(block_or_ring):
    """A block's first output ring, or the ring itself."""
    try:
        return block_or_ring.orings[0]
    except AttributeError:
        return block_or_ring


def _space_accessible(space, valid):
    if valid == 'any':
        return True
    if isinstance(valid, str):
        raise TypeError(f"define_valid_input_spaces must return 'any' or a tuple of spaces "
                        f"such as ('{valid}',), got the bare string {valid!r}")
    valid = set(valid)
    host = {'system', 'cuda_host'}
    return space in valid or (space in host and bool(valid & host))


class Block(BlockScope):
    """Base of all blocks. ``irings``: Rings or Blocks (a Block means its first output).

    ``stats`` (runtime only) -- a dict updated as the block runs:
    ``nsequence`` sequences started, ``ngulp`` on_data calls, ``nframe_read`` input frames
    handed to on_data (overlap frames count each time they are read), ``nframe_skipped``
    input frames lost to overruns (unguaranteed readers), ``nframe_written`` frames committed
    to the outputs (including on_skip output), ``nskip`` on_skip calls; ``process_s`` seconds
    spent in on_data (host time: GPU work still queued is not in it, as in Bifrost's ``perf``
    proclog), ``first_data_at`` / ``first_done_at`` / ``last_data_at`` (``time.perf_counter()`` when
    the first on_data began, when it ended, and when the last one ended; None before any).
    """
    instance_counts = defaultdict(lambda: 0)

    #: the CUDA priority of the block's stream (runtime only): 'low' (CUDA's default) for the blocks that
    #: keep the GPU busy (the imager), 'high' for short work that others wait on (the interference flagger
    #: ahead of the imager, the gain solver whose solutions the imager waits for): the GPU then starts
    #: the short work's kernels first and the long kernels fill the rest
    stream_priority = 'low'

    def __init__(self, irings, name=None, type_=None, **kwargs):
        self.type = type_ or self.__class__.__name__
        self.name = name or '%s_%i' % (self.type, Block.instance_counts[self.type])
        Block.instance_counts[self.type] += 1
        super().__init__(name=self.name, **kwargs)
        self.pipeline = get_default_pipeline()
        self.pipeline.blocks.append(self)
        rings = [get_ring(r) for r in irings]
        for i, r in enumerate(rings):
            if not isinstance(r, Ring):
                raise TypeError(f"block '{self.name}' input {i} must be a Block or a Ring, "
                                f"got {type(irings[i]).__name__}")
        self.irings = rings
        for i, (r, valid) in enumerate(zip(rings, self._define_valid_input_spaces())):
            if not _space_accessible(r.space, valid):
                raise ValueError(f"block '{self.name}' input {i} is in space '{r.space}' but "
                                 f"must be accessible from one of: {valid}")
        self.orings = []
        self.shutdown_event = threading.Event()
        self.stats = dict(nsequence=0, ngulp=0, nframe_read=0, nframe_skipped=0,
                          nframe_written=0, nskip=0, process_s=0.0, first_data_at=None,
                          first_done_at=None, last_data_at=None)
        self._ireaders = []
        self._seq_count = 0
        self.stream = None     # the thread's CUDA stream (a block on a GPU, runtime only)

    def __init_subclass__(cls, **kwargs):
        # A block whose constructor raises must not stay in its pipeline (it would run, half
        # built, with the next run() of that pipeline -- e.g. the default one).
        super().__init_subclass__(**kwargs)
        init = cls.__dict__.get('__init__')
        if init is None:
            return

        @functools.wraps(init)
        def __init__(self, *args, **kw):
            try:
                init(self, *args, **kw)
            except BaseException:
                pipe = getattr(self, 'pipeline', None)
                if pipe is not None:
                    pipe.blocks[:] = [b for b in pipe.blocks if b is not self]
                raise
        cls.__init__ = __init__

    def _lookup(self, key):
        # block -> enclosing block_scope(s) -> the block's pipeline
        val = BlockScope._lookup(self, key)
        return self.pipeline._lookup(key) if val is None else val

    def create_ring(self, *args, **kwargs):
        """A new ring owned by this block, e.g. ``self.create_ring(space='cuda')``."""
        return Ring(*args, owner=self, **kwargs)

    def shutdown(self):
        self.shutdown_event.set()

    def num_outputs(self):
        return len(self.orings)

    # -- running ----------------------------------------------------------------------------
    def _open_readers(self):
        guarantee = getattr(self, 'guarantee', True)
        self._ireaders = [r.open_reader(guarantee) for r in self.irings]

    def _bind(self):
        core = self.core
        if core is not None and hasattr(os, 'sched_setaffinity'):
            try:  # on Linux, pid 0 = the calling thread
                os.sched_setaffinity(0, {core if isinstance(core, Integral) else core[0]})
            except OSError as exc:
                warnings.warn(f"block '{self.name}': could not bind to core {core}: {exc}")
        uses_cuda = any(r.space == 'cuda' for r in list(self.irings) + list(self.orings))
        if self.gpu is None and not uses_cuda:
            return
        try:
            import cupy
            if cupy.cuda.runtime.getDeviceCount() < 1:
                return
        except Exception:  # no CuPy or no driver: host-only blocks need neither
            return
        if self.gpu is not None:
            cupy.cuda.Device(self.gpu).use()
        # The thread's own non-blocking stream (CuPy's current stream is per thread): the
        # blocks' kernels and copies queue there and overlap; rings order them with events.
        # _thread_main enters it as a context rather than calling use(): CuPy's current stream is
        # the top of a per-thread stack, and a `with s:` anywhere in the thread (CuPy's own get()
        # of a non-contiguous array has one) ends by restoring the entry below it -- the CUDA
        # default stream, where use() leaves the block's stream off the stack.
        self.stream = priority_stream(cupy, self.stream_priority)

    def _thread_main(self):
        try:
            self._bind()
            with ExitStack() as stack:
                if self.stream is not None:
                    stack.enter_context(self.stream)
                writers = [stack.enter_context(r.begin_writing()) for r in self.orings]
                self.main(writers)
        except PipelineShutdown:
            pass
        except BaseException as exc:  # noqa: BLE001 - reported to run() with the block's name
            self.pipeline._block_failed(self, exc)
        finally:
            if self.stream is not None:
                try:  # the block's last kernels finish before run() returns
                    self.stream.synchronize()
                except Exception as exc:  # noqa: BLE001 - a device error: report, do not hang
                    self.pipeline._block_failed(self, exc)
            for rd in self._ireaders:
                rd.close()
            self.pipeline._thread_done()

    def _data_begins(self):
        t = time.perf_counter()
        if self.stats['first_data_at'] is None:
            self.stats['first_data_at'] = t
        return t

    def _data_ends(self, t0):
        st = self.stats
        st['last_data_at'] = t = time.perf_counter()
        if st['first_done_at'] is None:
            st['first_done_at'] = t
        st['process_s'] += t - t0
        st['ngulp'] += 1

    def _check_shutdown(self):
        if self.shutdown_event.is_set():
            raise PipelineShutdown()

    def _begin_sequences(self, stack, writers, oheaders, igulp_nframes, istride_nframes):
        if not isinstance(oheaders, (list, tuple)) or len(oheaders) != len(writers):
            raise TypeError(f"block '{self.name}': on_sequence must give one header per output "
                            f"({len(writers)}), got {oheaders!r}")
        ostrides = self._define_output_nframes(istride_nframes)
        ogulps = self._define_output_nframes(igulp_nframes)
        oseqs = []
        for i, (w, hdr, ost, og) in enumerate(zip(writers, oheaders, ostrides, ogulps)):
            if not isinstance(hdr, dict):
                raise TypeError(f"block '{self.name}': on_sequence returned {hdr!r} for output "
                                f"{i}; expected a header dict")
            hdr['gulp_nframe'] = ost
            oseqs.append(stack.enter_context(w.begin_sequence(hdr, og, og)))
        return oseqs, [og - ost for og, ost in zip(ogulps, ostrides)]

    def _reserve_spans(self, stack, oseqs, igulp_nframes):
        onframes = self._define_output_nframes(igulp_nframes)
        return [stack.enter_context(s.reserve(n)) for s, n in zip(oseqs, onframes)]

    def _commit_spans(self, ospans, ostrides, ooverlaps, hook='on_data'):
        if ostrides is None:
            ostrides = [None] * len(ospans)
        for span, n, ov in zip(ospans, ostrides, ooverlaps):
            if n is None:
                n = max(span.nframe - ov, 0)
            if isinstance(n, bool) or not isinstance(n, Integral) or not 0 <= n <= span.nframe:
                raise ValueError(f"block '{self.name}': {hook} returned {n!r} frames to commit; "
                                 f"expected None or an int in [0, {span.nframe}]")
            span.commit(int(n))
            self.stats['nframe_written'] += int(n)

    def _define_output_nframes(self, input_nframes):
        return self.define_output_nframes(input_nframes)

    def define_output_nframes(self, input_nframes):
        raise NotImplementedError

    def _define_valid_input_spaces(self):
        return self.define_valid_input_spaces()

    def define_valid_input_spaces(self):
        return ['any'] * len(self.irings)


class SourceBlock(Block):
    """Reads ``sourcenames`` one after another, one output sequence each.

    Hooks: ``create_reader(name)`` -> context manager; ``on_sequence(reader, name)`` -> list
    of output headers; ``on_data(reader, ospans)`` -> list of frames written per output
    (a 0 ends the sequence). ``space``: the output ring's space (default 'system')."""

    def __init__(self, sourcenames, gulp_nframe, space=None, *args, **kwargs):
        super().__init__([], *args, gulp_nframe=gulp_nframe, **kwargs)
        if self.gulp_nframe is None:
            raise ValueError(f"block '{self.name}': gulp_nframe must be an int >= 1")
        self.sourcenames = sourcenames
        self.orings = [self.create_ring(space=space or 'system')]
        # set by Pipeline.drain: end the sequence after the gulp being written and read no more, so
        # that every block downstream ends its sequence as at the end of the data (files closed)
        self.drain_event = threading.Event()

    def main(self, writers):
        for sourcename in self.sourcenames:
            self._check_shutdown()
            if self.drain_event.is_set():
                break
            with self.create_reader(sourcename) as ireader:
                oheaders = self.on_sequence(ireader, sourcename)
                if isinstance(oheaders, (list, tuple)):
                    for ohdr in oheaders:
                        if isinstance(ohdr, dict):
                            ohdr.setdefault('time_tag', self._seq_count)
                            ohdr.setdefault('name', 'unnamed-sequence-%i' % self._seq_count)
                self._seq_count += 1
                self.stats['nsequence'] += 1
                with ExitStack() as seq_stack:
                    oseqs, ooverlaps = self._begin_sequences(seq_stack, writers, oheaders, [], [])
                    while True:
                        self._check_shutdown()
                        with ExitStack() as span_stack:
                            ospans = self._reserve_spans(span_stack, oseqs, [])
                            t = self._data_begins()
                            ostrides = self.on_data(ireader, ospans)
                            self._data_ends(t)
                            if not isinstance(ostrides, (list, tuple)) or \
                                    len(ostrides) != len(ospans):
                                raise TypeError(
                                    f"block '{self.name}': SourceBlock.on_data must return a "
                                    f"list of frame counts, one per output ({len(ospans)}); "
                                    f"got {ostrides!r}")
                            self._commit_spans(ospans, ostrides, ooverlaps)
                        if any(n == 0 for n in ostrides) or self.drain_event.is_set():
                            break
        close = getattr(self.sourcenames, "close", None)   # a generator of live streams: let it clean up
        if close is not None:
            close()

    def define_output_nframes(self, _):
        return [self.gulp_nframe] * self.num_outputs()

    def define_valid_input_spaces(self):
        return []

    def create_reader(self, sourcename):
        raise NotImplementedError

    def on_sequence(self, reader, sourcename):
        raise NotImplementedError

    def on_data(self, reader, ospans):
        raise NotImplementedError


class MultiTransformBlock(Block):
    """Several inputs read in lock step; one output ring per input (in its space)."""

    def __init__(self, irings_, guarantee=True, *args, **kwargs):
        super().__init__(irings_, *args, **kwargs)
        self.guarantee = guarantee
        self.orings = [self.create_ring(space=r.space) for r in self.irings]

    def main(self, writers):
        for iseqs in zip(*[rd.sequences() for rd in self._ireaders]):
            self._check_shutdown()
            self.stats['nsequence'] += 1
            oheaders = self._on_sequence(iseqs)
            for ohdr in oheaders or []:
                if isinstance(ohdr, dict):
                    ohdr.setdefault('time_tag', self._seq_count)
            self._seq_count += 1
            istrides = []
            for iseq in iseqs:
                g = self.gulp_nframe or iseq.header.get('gulp_nframe')
                if isinstance(g, bool) or not isinstance(g, Integral) or g < 1:
                    raise ValueError(f"block '{self.name}': no gulp_nframe (the block has none "
                                     f"and the input header gives {g!r})")
                istrides.append(int(g))
            overlaps = self._define_input_overlap_nframe(iseqs)
            for o in overlaps:
                if isinstance(o, bool) or not isinstance(o, Integral) or o < 0:
                    raise ValueError(f"block '{self.name}': define_input_overlap_nframe "
                                     f"returned {o!r}; expected an int >= 0")
            igulps = [s + int(o) for s, o in zip(istrides, overlaps)]
            for iseq, ig in zip(iseqs, igulps):
                iseq.resize(ig, self.buffer_nframe, self.buffer_factor)
            with ExitStack() as seq_stack:
                oseqs, ooverlaps = self._begin_sequences(seq_stack, writers, oheaders,
                                                         igulps, istrides)
                for ispans in zip(*[iseq.read(ig, s) for iseq, ig, s
                                    in zip(iseqs, igulps, istrides)]):
                    self._check_shutdown()
                    if any(sp.nframe_skipped for sp in ispans):
                        self._skip(oseqs, ispans, istrides)
                    if all(sp.nframe == 0 for sp in ispans):
                        continue
                    with ExitStack() as span_stack:
                        ospans = self._reserve_spans(span_stack, oseqs,
                                                     [sp.nframe for sp in ispans])
                        t = self._data_begins()
                        ostrides = self._on_data(ispans, ospans)
                        self._data_ends(t)
                        self.stats['nframe_read'] += sum(sp.nframe for sp in ispans)
                        self._commit_spans(ospans, ostrides, ooverlaps)
            self._on_sequence_end(iseqs)

    def _skip(self, oseqs, ispans, istrides):
        """Lost input frames -> on_skip, one input stride at a time so output counts match."""
        nskip = [sp.nframe_skipped for sp in ispans]
        starts = [sp.frame_offset - n for sp, n in zip(ispans, nskip)]
        self.stats['nframe_skipped'] += sum(nskip)
        if not oseqs:  # sinks: one call covering everything that was lost
            self.stats['nskip'] += 1
            self._on_skip([slice(a, a + n, s) for a, n, s in zip(starts, nskip, istrides)], [])
            return
        done = [0] * len(nskip)
        while any(d < n for d, n in zip(done, nskip)):
            chunks = [min(s, n - d) for s, n, d in zip(istrides, nskip, done)]
            islices = [slice(a + d, a + d + c, s)
                       for a, d, c, s in zip(starts, done, chunks, istrides)]
            with ExitStack() as span_stack:
                ospans = self._reserve_spans(span_stack, oseqs, chunks)
                ret = self._on_skip(islices, ospans)
                self.stats['nskip'] += 1
                self._commit_spans(ospans, ret, [0] * len(ospans), hook='on_skip')
            done = [d + c for d, c in zip(done, chunks)]

    def _on_sequence(self, iseqs):
        return self.on_sequence(iseqs)

    def _on_sequence_end(self, iseqs):
        return self.on_sequence_end(iseqs)

    def _on_data(self, ispans, ospans):
        return self.on_data(ispans, ospans)

    def _on_skip(self, islices, ospans):
        return self.on_skip(islices, ospans)

    def _define_input_overlap_nframe(self, iseqs):
        return self.define_input_overlap_nframe(iseqs)

    def define_input_overlap_nframe(self, iseqs):
        return [0] * len(self.irings)

    def define_output_nframes(self, input_nframes):
        return input_nframes

    def on_sequence(self, iseqs):
        raise NotImplementedError

    def on_sequence_end(self, iseqs):
        pass

    def on_data(self, ispans, ospans):
        raise NotImplementedError

    def on_skip(self, islices, ospans):
        raise NotImplementedError(f"block '{self.name}' was overrun (guarantee=False) and "
                                  "defines no on_skip(islices, ospans)")


class _OneInput:
    """The single-input hooks TransformBlock and SinkBlock share (Bifrost's defaults)."""

    def _define_valid_input_spaces(self):
        return [self.define_valid_input_spaces()]

    def define_valid_input_spaces(self):
        return 'any'

    def _define_input_overlap_nframe(self, iseqs):
        return [self.define_input_overlap_nframe(iseqs[0])]

    def define_input_overlap_nframe(self, iseq):
        return 0

    def _on_sequence_end(self, iseqs):
        return [self.on_sequence_end(iseqs[0])]

    def on_sequence_end(self, iseq):
        pass


class TransformBlock(_OneInput, MultiTransformBlock):
    """One input, one output ring (in the input's space unless ``self.orings`` is replaced).

    Hooks: ``on_sequence(iseq)`` -> output header; ``on_data(ispan, ospan)`` -> frames to
    commit (None = all but the output overlap); ``define_output_nframes(n)``;
    ``define_input_overlap_nframe(iseq)``; ``define_valid_input_spaces()``;
    ``on_sequence_end(iseq)``; ``on_skip(islice, ospan)`` (default: zero-fill ``ospan``)."""

    def __init__(self, iring, *args, **kwargs):
        super().__init__([iring], *args, **kwargs)
        self.iring = self.irings[0]

    def _define_output_nframes(self, input_nframes):
        return [self.define_output_nframes(input_nframes[0])]

    def define_output_nframes(self, input_nframe):
        return input_nframe

    def _on_sequence(self, iseqs):
        return [self.on_sequence(iseqs[0])]

    def on_sequence(self, iseq):
        raise NotImplementedError

    def _on_data(self, ispans, ospans):
        return [self.on_data(ispans[0], ospans[0])]

    def on_data(self, ispan, ospan):
        raise NotImplementedError

    def _on_skip(self, islices, ospans):
        return [self.on_skip(islices[0], ospans[0])]

    def on_skip(self, islice, ospan):
        """Default: the output frames of skipped input are zeros."""
        ospan.data[...] = 0


class SinkBlock(_OneInput, MultiTransformBlock):
    """One input, no outputs. Hooks: ``on_sequence(iseq)``, ``on_data(ispan)``,
    ``on_sequence_end(iseq)``; with guarantee=False also ``on_skip(islices, ospans)``."""

    def __init__(self, iring, *args, **kwargs):
        super().__init__([iring], *args, **kwargs)
        self.orings = []
        self.iring = self.irings[0]

    def _define_output_nframes(self, input_nframes):
        return []

    def _on_sequence(self, iseqs):
        self.on_sequence(iseqs[0])
        return []

    def on_sequence(self, iseq):
        raise NotImplementedError

    def _on_data(self, ispans, ospans):
        self.on_data(ispans[0])
        return []

    def on_data(self, ispan):
        raise NotImplementedError
