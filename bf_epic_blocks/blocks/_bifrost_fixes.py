"""What our blocks change about real Bifrost, and where: only inside our own blocks and pipelines.

Nothing here runs at import. :mod:`._compat` builds its ``bfp`` namespace for real Bifrost with
:func:`bifrost_namespace`; framework users who mix our blocks into their own Bifrost pipeline may
call :func:`enable_bifrost_compat` to extend the read-span fix to every block of the process.

Two fixes:

* Frame-aligned read spans. Real Bifrost asserts in ``ring2.SpanBase.frame_offset``
  (``assert(byte_offset % self.frame_nbyte == 0)``, a case its own TODO foresees). A ring's span
  is rounded up to a power of two (``ring_impl.cpp``, ``round_up_pow2``) and an overrun moves the
  tail to ``head - span``; an unguaranteed read of overwritten data then starts at the tail, which
  lies inside a frame whenever the frame size does not divide a power of two (an LWA-SV TBF frame
  of 24 channels is 24*256*2 = 12,288 bytes = 3 * 4,096). A frame-aligned span is trimmed to the
  whole frames it holds: its start moves to the next frame boundary (data pointer and size with
  it), so the bytes before it count as skipped, and a partly overwritten frame counts as
  overwritten. Guaranteed reads are always aligned and are unchanged.
  Our ``TransformBlock``, ``SinkBlock`` and ``MultiTransformBlock`` read through such spans
  (:class:`FrameAlignedReads`); ``bifrost.ring2.ReadSpan`` itself is left alone.
* Failures raised from ``Pipeline.run()``. Real Bifrost only ends the failing block's thread.
  Our ``Pipeline`` (:func:`catching_pipeline`) raises the first failure as
  :class:`bf_epic_blocks.runtime.pipeline.PipelineError`, as our runtime does.
"""
from __future__ import annotations

import functools
import threading
import time
import types

from ..runtime import pipeline as _builtin_pipeline

_ALIGNED_MARK = '_bf_epic_aligned'
_aligned_span_cls = None
_aligned_lock = threading.Lock()


def _ring2():
    try:
        import bifrost.ring2 as ring2
    except ImportError as exc:
        raise ImportError(f"the Bifrost compatibility fixes need real Bifrost's ring2 "
                          f"(`import bifrost.ring2` failed: {exc})") from exc
    return ring2


def frame_aligned_read_span_class():
    """The frame-aligned subclass of ``bifrost.ring2.ReadSpan`` (made once), or None when this
    Bifrost's ``ReadSpan`` has no ``_cache_info`` (a ring2 without such spans has nothing to mend).

    Built from the original ``ReadSpan`` even after :func:`enable_bifrost_compat` has put the
    subclass in its place, so spans are never trimmed twice."""
    global _aligned_span_cls
    ring2 = _ring2()
    current = getattr(ring2, 'ReadSpan', None)
    if getattr(current, _ALIGNED_MARK, False):
        return current
    if not hasattr(current, '_cache_info'):
        return None
    with _aligned_lock:
        if _aligned_span_cls is None:
            _aligned_span_cls = _make_frame_aligned(ring2, current)
        return _aligned_span_cls


def _make_frame_aligned(ring2, base):
    class FrameAlignedReadSpan(base):
        def _cache_info(self):
            super()._cache_info()
            fn = self._sequence.tensor['frame_nbyte']
            off = int(self._info.offset)
            self._cut = -off % fn
            if self._cut:
                size = int(self._info.size)
                self._info.offset = off + self._cut
                if self._info.data:
                    self._info.data = int(self._info.data) + self._cut
                self._info.size = max(size - self._cut, 0) // fn * fn

        @property
        def nframe_overwritten(self):
            n = ring2.ctypes.c_ulong()
            ring2._check(ring2._bf.bfRingSpanGetSizeOverwritten(self.obj, n))
            nbyte = min(max(int(n.value) - getattr(self, '_cut', 0), 0), self._size_bytes)
            return -(-nbyte // self.frame_nbyte)

    FrameAlignedReadSpan.__name__ = FrameAlignedReadSpan.__qualname__ = 'ReadSpan'
    FrameAlignedReadSpan.__module__ = ring2.__name__
    setattr(FrameAlignedReadSpan, _ALIGNED_MARK, True)
    return FrameAlignedReadSpan


def enable_bifrost_compat():
    """Make every Bifrost block of this process read frame-aligned spans; idempotent.

    Our blocks read frame-aligned spans without this call, wherever they run. Call it when your
    own Bifrost pipeline has other blocks (Bifrost's or yours) that read a ring of ours without
    a guarantee, whose frame size does not divide a power of two (LWA TBF and TBX rings do not):
    after an overrun such a read can start inside a frame, and Bifrost's
    ``SpanBase.frame_offset`` then fails an assertion and ends that block's thread.

    What it changes, for the whole process and for good: ``bifrost.ring2.ReadSpan`` becomes a
    subclass that trims each read span to the whole frames it holds (the start moves to the next
    frame boundary; the bytes before it count as skipped, a partly overwritten frame as
    overwritten). Guaranteed reads are always aligned and behave as before. Bifrost builds
    ``ReadSpan`` by its module-level name, so there is no narrower place to put it.

    It does not change ``bifrost.pipeline``: to have a block's failure raised from ``run()``,
    build the pipeline with ``bf_epic_blocks.blocks.bfp.Pipeline`` instead of ``bifrost.Pipeline``.

    Returns True when ``ReadSpan`` is the frame-aligned class, False when this Bifrost's
    ``ReadSpan`` has no ``_cache_info`` to extend (nothing changed). Raises ImportError when
    ``bifrost.ring2`` does not import.
    """
    ring2 = _ring2()
    cls = frame_aligned_read_span_class()
    if cls is None:
        return False
    ring2.ReadSpan = cls
    return True


class _FrameAlignedRing:
    """A reader's view of a Bifrost ring whose sequences hand out frame-aligned spans; every
    other attribute is the ring's."""

    def __init__(self, ring, span_cls):
        self._bf_epic_ring = ring
        self._bf_epic_span_cls = span_cls

    def __getattr__(self, name):
        if name.startswith('_bf_epic_'):  # not set yet (a copy in the making): not the ring's
            raise AttributeError(name)
        return getattr(self._bf_epic_ring, name)

    def read(self, *args, **kwargs):
        for seq in self._bf_epic_ring.read(*args, **kwargs):
            yield _FrameAlignedSequence(seq, self._bf_epic_span_cls)


class _FrameAlignedSequence:
    """A ``ring2.ReadSequence`` whose ``acquire``/``read`` make frame-aligned spans; ``read`` is
    ``ReadSequence.read``'s loop (spans of ``nframe`` every ``stride`` from ``begin`` until the
    sequence ends). Every other attribute is the sequence's."""

    def __init__(self, seq, span_cls):
        self._bf_epic_seq = seq
        self._bf_epic_span_cls = span_cls

    def __getattr__(self, name):
        if name.startswith('_bf_epic_'):
            raise AttributeError(name)
        return getattr(self._bf_epic_seq, name)

    def acquire(self, frame_offset, nframe):
        return self._bf_epic_span_cls(self._bf_epic_seq, frame_offset, nframe)

    def read(self, nframe, stride=None, begin=0):
        end_of_data = _ring2().EndOfDataStop
        if stride is None:
            stride = nframe
        offset = begin
        while True:
            try:
                with self.acquire(offset, nframe) as ispan:
                    yield ispan
                    offset += stride
            except end_of_data:
                return


class FrameAlignedReads:
    """Mixin for Bifrost reading blocks (before the Bifrost class in the bases): while the block
    runs, its input rings are read through frame-aligned spans.

    ``main`` is Bifrost's, given views of ``self.irings`` (the rings themselves are restored
    when it returns); a Bifrost whose ``ReadSpan`` cannot be extended reads as before."""

    def main(self, orings):
        span_cls = frame_aligned_read_span_class()
        if span_cls is None:
            return super().main(orings)
        irings = self.irings
        self.irings = [_FrameAlignedRing(r, span_cls) for r in irings]
        try:
            return super().main(orings)
        finally:
            self.irings = irings


def catching_pipeline(bf_pipeline):
    """A subclass of ``bf_pipeline.Pipeline`` whose ``run()`` raises a block's failure.

    Real Bifrost only ends the failing block's thread: ``run()`` returns normally (failure after
    start-up) or raises ``PipelineInitError`` naming the block but not the error. During
    ``run()`` each block's ``run`` is wrapped (and restored afterwards): the first exception is
    kept, the other blocks are told to shut down (they poll their shutdown events), and ``run()``
    then raises our runtime's :class:`~bf_epic_blocks.runtime.pipeline.PipelineError` (block
    name + original message, original as ``__cause__``)."""

    class Pipeline(bf_pipeline.Pipeline):
        """``bifrost.pipeline.Pipeline`` whose ``run()`` raises the first block failure as
        :class:`~bf_epic_blocks.runtime.pipeline.PipelineError`."""

        def drain(self):
            """End the data gracefully, as our runtime's ``Pipeline.drain``: each source's next gulp is
            empty (:class:`CountedSource`), which ends its sequence; the blocks downstream finish what
            the rings hold and close their files."""
            for b in self.blocks:
                ev = getattr(b, "drain_event", None)
                if ev is not None:
                    ev.set()

        def run(self):
            self._bf_epic_failure = None
            lock = threading.Lock()

            def catching(block, run):
                def wrapped():
                    try:
                        run()
                    except Exception as exc:  # reported by Pipeline.run below, not the thread
                        with lock:
                            if self._bf_epic_failure is None:
                                self._bf_epic_failure = (block, exc)
                        for b in self.blocks:
                            b.shutdown()
                        # blocks still waiting for start-up to finish must see the shutdown
                        self.all_blocks_finished_initializing_event.set()
                return wrapped

            own = {}  # block -> its instance attribute 'run', if it had one
            for block in self.blocks:
                if 'run' in vars(block):
                    own[block] = vars(block)['run']
                block.run = catching(block, block.run)
            init_error = None
            try:
                try:
                    super().run()
                except getattr(bf_pipeline, 'PipelineInitError', ()) as exc:
                    init_error = exc
                for t in getattr(self, 'threads', ()):  # let the failing thread record its error
                    t.join(self.shutdown_timeout)
            finally:
                for block in self.blocks:
                    if block in own:
                        block.run = own[block]
                    else:
                        vars(block).pop('run', None)
            if self._bf_epic_failure is not None:
                block, exc = self._bf_epic_failure
                raise _builtin_pipeline.PipelineError(block, exc) from exc
            if init_error is not None:
                raise init_error

    Pipeline.__module__, Pipeline.__qualname__ = __name__, 'Pipeline'
    return Pipeline


class CountedSource:
    """A source block's ``stats`` under real Bifrost, as our runtime keeps them for every block
    (``nframe_written``, ``ngulp``, ``process_s``, ``first_data_at``, ``last_data_at``): the service's
    monitor reads how much data has come and when the last did from them. Each subclass's ``on_data``
    is wrapped where it is defined (Bifrost's SourceBlock calls it once a gulp; it returns the frames
    written, an int or one per output). Once ``drain_event`` is set (the Pipeline's ``drain``, on
    SIGTERM) the next gulp is empty, which ends the sequence as the end of the data does."""

    @property
    def drain_event(self):
        ev = self.__dict__.get("_drain_event")
        if ev is None:
            ev = self.__dict__["_drain_event"] = threading.Event()
        return ev

    @property
    def stats(self):
        st = self.__dict__.get("_counted_stats")
        if st is None:
            st = self.__dict__["_counted_stats"] = dict(ngulp=0, nframe_written=0, process_s=0.0,
                                                        first_data_at=None, last_data_at=None)
        return st

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        f = cls.__dict__.get("on_data")
        if f is None:
            return

        @functools.wraps(f)
        def on_data(self, *args, **kw):
            if self.__dict__.get("_counting"):          # a subclass's on_data calling this one: counted there
                return f(self, *args, **kw)
            if self.drain_event.is_set():                # drained: an empty gulp ends the sequence
                ospans = args[1] if len(args) > 1 else kw.get("ospans", [None])
                return [0] * len(ospans)
            t0 = time.perf_counter()
            self.__dict__["_counting"] = True
            try:
                n = f(self, *args, **kw)
            finally:
                self.__dict__["_counting"] = False
            st = self.stats
            if st["first_data_at"] is None:
                st["first_data_at"] = t0
            st["last_data_at"] = t = time.perf_counter()
            st["process_s"] += t - t0
            st["ngulp"] += 1
            first = n[0] if isinstance(n, (list, tuple)) and n else n
            st["nframe_written"] += int(first or 0)
            return n
        cls.on_data = on_data


def bifrost_namespace(bf_pipeline):
    """``bfp`` for real Bifrost: ``bf_pipeline``'s names, with ``Pipeline`` from
    :func:`catching_pipeline`, the reading block classes given :class:`FrameAlignedReads`, and
    ``SourceBlock`` given :class:`CountedSource`. Each is a subclass of Bifrost's class of the same name."""
    ns = types.ModuleType('bf_epic_blocks.blocks._compat.bfp', bf_pipeline.__doc__)
    ns.__dict__.update({k: v for k, v in vars(bf_pipeline).items() if not k.startswith('__')})
    ns.Pipeline = catching_pipeline(bf_pipeline)
    for name in ('MultiTransformBlock', 'TransformBlock', 'SinkBlock'):
        base = getattr(bf_pipeline, name)
        doc = f"``bifrost.pipeline.{name}`` reading frame-aligned spans (:class:`FrameAlignedReads`)."
        cls = type(name, (FrameAlignedReads, base), {'__module__': __name__, '__doc__': doc})
        setattr(ns, name, cls)
    ns.SourceBlock = type('SourceBlock', (CountedSource, bf_pipeline.SourceBlock),
                          {'__module__': __name__,
                           '__doc__': "``bifrost.pipeline.SourceBlock`` with ``stats`` (:class:`CountedSource`)."})
    return ns
