"""Our fixes to real Bifrost stay inside our blocks and pipelines; importing changes nothing.

Real Bifrost is not on PyPI, so these tests write a stand-in ``bifrost`` package (the parts of
``bifrost.pipeline``, ``bifrost.ring2`` and ``bifrost.libbifrost`` that the fixes touch, with the
same names, signatures and assertions as Bifrost 0.10) and run each case in a fresh Python with it
first on the path. The stand-in ring hands out scripted spans: where real Bifrost would put the
span after an overrun, and how many bytes were overwritten while the block read it.
"""
import os
import subprocess
import sys
import textwrap
import types
import warnings

import numpy as np
import pytest

from bf_epic_blocks.blocks import _compat

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

_FAKE_BIFROST = {
    'bifrost/__init__.py': "",
    'bifrost/libbifrost.py': '''
        class EndOfDataStop(Exception):
            pass


        def _check(status):
            return status


        class _Lib:
            def bfRingSpanGetSizeOverwritten(self, obj, n):
                n.value = obj.overwritten
                return 0


        _bf = _Lib()
        ''',
    'bifrost/ring2.py': '''
        import ctypes

        from bifrost.libbifrost import _bf, _check, EndOfDataStop


        class BFspan_info:
            def __init__(self, offset, size, data):
                self.offset, self.size, self.data = offset, size, data


        class _CSpan:
            """Where the ring put a span: byte offset and size, bytes overwritten during the read."""
            def __init__(self, offset, size, overwritten):
                self.offset, self.size, self.overwritten = offset, size, overwritten


        class Ring:
            """``spans``: (byte offset, byte size, bytes overwritten) of each span acquired, in turn."""
            def __init__(self, frame_nbyte, spans, space='system'):
                self.frame_nbyte, self.spans, self.space = frame_nbyte, list(spans), space
                self.header_transform = None

            def read(self, whence='earliest', guarantee=True):
                yield ReadSequence(self)


        class ReadSequence:
            def __init__(self, ring):
                self.ring = ring
                self.header = {'name': 'seq', 'time_tag': 0}
                self.tensor = {'frame_nbyte': ring.frame_nbyte}

            def acquire(self, frame_offset, nframe):
                return ReadSpan(self, frame_offset, nframe)

            def read(self, nframe, stride=None, begin=0):
                if stride is None:
                    stride = nframe
                offset = begin
                while True:
                    try:
                        with self.acquire(offset, nframe) as ispan:
                            yield ispan
                            offset += stride
                    except EndOfDataStop:
                        return


        class SpanBase:
            def __init__(self, ring, sequence, writeable):
                self._ring, self._sequence, self.writeable = ring, sequence, writeable

            def _set_base_obj(self, obj):
                self._base_obj = obj
                self._cache_info()

            def _cache_info(self):
                o = self._base_obj
                self._info = BFspan_info(o.offset, o.size, 4096 + o.offset)

            @property
            def frame_nbyte(self):
                return self._sequence.tensor['frame_nbyte']

            @property
            def _size_bytes(self):
                return int(self._info.size)

            @property
            def frame_offset(self):
                byte_offset = int(self._info.offset)
                assert(byte_offset % self.frame_nbyte == 0)
                return byte_offset // self.frame_nbyte

            @property
            def nframe(self):
                assert(self._size_bytes % self.frame_nbyte == 0)
                return self._size_bytes // self.frame_nbyte


        class ReadSpan(SpanBase):
            def __init__(self, sequence, frame_offset, nframe):
                SpanBase.__init__(self, sequence.ring, sequence, writeable=False)
                if not sequence.ring.spans:
                    raise EndOfDataStop
                self.obj = _CSpan(*sequence.ring.spans.pop(0))
                self._set_base_obj(self.obj)
                self.nframe_skipped = min(self.frame_offset - frame_offset, nframe)

            @property
            def nframe_overwritten(self):
                n = ctypes.c_ulong()
                _check(_bf.bfRingSpanGetSizeOverwritten(self.obj, n))
                assert(n.value % self.frame_nbyte == 0)
                return n.value // self.frame_nbyte

            def __enter__(self):
                return self

            def __exit__(self, *exc):
                pass
        ''',
    'bifrost/pipeline.py': '''
        import threading

        _stack = []


        class PipelineInitError(Exception):
            pass


        class Pipeline:
            def __init__(self):
                self.blocks, self.threads, self.shutdown_timeout = [], [], 5.0
                self.all_blocks_finished_initializing_event = threading.Event()

            def __enter__(self):
                _stack.append(self)
                return self

            def __exit__(self, *exc):
                _stack.pop()

            def run(self):
                self.threads = [threading.Thread(target=b.run, name=b.name) for b in self.blocks]
                for t in self.threads:
                    t.daemon = True
                    t.start()
                for t in self.threads:
                    t.join()


        def get_default_pipeline():
            return _stack[-1] if _stack else None


        def block_scope(**kwargs):
            pass


        class Block:
            def __init__(self, irings, name=None, **kwargs):
                self.name = name or type(self).__name__
                self.irings = list(irings)
                self.shutdown_event = threading.Event()
                if _stack:
                    _stack[-1].blocks.append(self)

            def shutdown(self):
                self.shutdown_event.set()

            def run(self):
                self.main([])


        class SourceBlock(Block):
            def __init__(self, sourcenames, gulp_nframe, space=None, *args, **kwargs):
                super().__init__([], *args, **kwargs)


        class MultiTransformBlock(Block):
            def __init__(self, irings, guarantee=True, *args, **kwargs):
                super().__init__(irings, *args, **kwargs)
                self.guarantee = guarantee

            def main(self, orings):
                for iseq in self.irings[0].read(guarantee=self.guarantee):
                    self.on_sequence(iseq)
                    for ispan in iseq.read(4):
                        self.on_data(ispan)


        class TransformBlock(MultiTransformBlock):
            def __init__(self, iring, *args, **kwargs):
                super().__init__([iring], *args, **kwargs)


        class SinkBlock(MultiTransformBlock):
            def __init__(self, iring, *args, **kwargs):
                super().__init__([iring], *args, **kwargs)
        ''',
}

# Frames of 64 bytes, read 4 at a time. The first span is whole; the second was asked for at
# frame 4 (byte 256), but an overrun moved the ring's tail to byte 300, inside frame 4, and 84
# bytes more were overwritten while the block read it. Whole frames: 5, 6 and 7 (bytes 320-512),
# one frame skipped (4), one overwritten (5, bytes 320-384).
_PROBE = '''
import bifrost.pipeline as bfpipe
import bifrost.ring2 as ring2

SPANS = [(0, 256, 0), (300, 212, 84)]
WHOLE_FRAMES = [(0, 4, 0, 0), (5, 3, 1, 1)]  # frame_offset, nframe, skipped, overwritten


def probe(base):
    class Probe(base):
        def __init__(self, iring, *args, **kwargs):
            super().__init__(iring, *args, guarantee=False, **kwargs)
            self.seen = []

        def on_sequence(self, iseq):
            self.header = iseq.header

        def on_data(self, ispan):
            self.seen.append((ispan.frame_offset, ispan.nframe, ispan.nframe_skipped,
                              ispan.nframe_overwritten))
    return Probe


def run_one(block_base, pipeline_cls):
    """Frames the probe saw, or the error its thread ended with."""
    ring = ring2.Ring(64, SPANS)
    with pipeline_cls() as p:
        blk = probe(block_base)(ring)
    errors = []
    plain_run = blk.run

    def run():
        try:
            plain_run()
        except AssertionError as exc:
            errors.append(exc)
    blk.run = run
    p.run()
    assert blk.irings[0] is ring, 'the block keeps its own input ring'
    return ('AssertionError' if errors else blk.seen), blk
'''


def _run(tmp_path, code):
    for rel, text in _FAKE_BIFROST.items():
        f = tmp_path / rel
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text(textwrap.dedent(text))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), REPO]))
    env.pop('BF_EPIC_RUNTIME', None)
    out = subprocess.run([sys.executable, '-c', textwrap.dedent(code)], env=env,
                         capture_output=True, text=True, timeout=120, cwd=str(tmp_path))
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    return out.stdout.split()


def test_importing_any_module_changes_nothing_in_bifrost(tmp_path):
    out = _run(tmp_path, '''
        import importlib, pkgutil, sys
        import bifrost.pipeline, bifrost.ring2, bifrost.libbifrost

        def snapshot():
            snap = {}
            for mod in (bifrost.pipeline, bifrost.ring2, bifrost.libbifrost):
                for name, obj in vars(mod).items():
                    snap[mod.__name__, name] = obj
                    if isinstance(obj, type):
                        for attr, val in vars(obj).items():
                            snap[mod.__name__, name, attr] = val
            return snap

        before = snapshot()
        import bf_epic_blocks, bf_epic_blocks.blocks
        for m in pkgutil.walk_packages(bf_epic_blocks.__path__, 'bf_epic_blocks.'):
            importlib.import_module(m.name)
        assert 'bf_epic_blocks.blocks.dft_imager' in sys.modules
        after = snapshot()
        changed = sorted(str(k) for k in before.keys() | after.keys()
                         if before.get(k, 'absent') is not after.get(k, 'absent'))
        print(bf_epic_blocks.blocks.HAVE_BIFROST, 'changed:', *changed)
        ''')
    assert out == ['True', 'changed:']


def test_our_blocks_read_frame_aligned_spans_and_bifrost_is_left_alone(tmp_path):
    out = _run(tmp_path, _PROBE + '''
from bf_epic_blocks.blocks import bfp
original = ring2.ReadSpan
seen, blk = run_one(bfp.SinkBlock, bfp.Pipeline)
assert seen == WHOLE_FRAMES, seen
assert blk.header == {'name': 'seq', 'time_tag': 0}
seen, _ = run_one(bfp.TransformBlock, bfp.Pipeline)
assert seen == WHOLE_FRAMES, seen
# a Bifrost block in the same process still reads Bifrost's own spans
seen, _ = run_one(bfpipe.SinkBlock, bfpipe.Pipeline)
assert seen == 'AssertionError', seen
assert ring2.ReadSpan is original
print('ok')
''')
    assert out == ['ok']


def test_enable_bifrost_compat_mends_every_block_once(tmp_path):
    out = _run(tmp_path, _PROBE + '''
from bf_epic_blocks.blocks import bfp, enable_bifrost_compat
original = ring2.ReadSpan
assert run_one(bfpipe.SinkBlock, bfpipe.Pipeline)[0] == 'AssertionError'
assert enable_bifrost_compat() is True
mended = ring2.ReadSpan
assert mended is not original and issubclass(mended, original)
assert run_one(bfpipe.SinkBlock, bfpipe.Pipeline)[0] == WHOLE_FRAMES
assert enable_bifrost_compat() is True and ring2.ReadSpan is mended   # idempotent
assert run_one(bfpipe.SinkBlock, bfpipe.Pipeline)[0] == WHOLE_FRAMES
assert run_one(bfp.SinkBlock, bfp.Pipeline)[0] == WHOLE_FRAMES       # not trimmed twice
print('ok')
''')
    assert out == ['ok']


def test_enable_bifrost_compat_leaves_a_ring2_without_cache_info(tmp_path):
    out = _run(tmp_path, _PROBE + '''
del ring2.SpanBase._cache_info
original = ring2.ReadSpan
from bf_epic_blocks.blocks import enable_bifrost_compat
print(enable_bifrost_compat(), ring2.ReadSpan is original)
''')
    assert out == ['False', 'True']


def test_our_pipeline_raises_a_block_failure_and_restores_run(tmp_path):
    out = _run(tmp_path, _PROBE + '''
from bf_epic_blocks.blocks import bfp
from bf_epic_blocks.runtime.pipeline import PipelineError

class Broken(bfp.SinkBlock):
    def on_sequence(self, iseq):
        raise ValueError('bad header')

with bfp.Pipeline() as p:
    blk = Broken(ring2.Ring(64, SPANS), name='broken')
try:
    p.run()
except PipelineError as exc:
    assert 'broken' in str(exc) and 'bad header' in str(exc), exc
    assert isinstance(exc.__cause__, ValueError)
else:
    raise AssertionError('no PipelineError')
print('run' in vars(blk), blk.irings[0].__class__.__name__)
''')
    assert out == ['False', 'Ring']


class _Protocol:
    """A stream object as CuPy 14 takes it: ``__cuda_stream__`` -> (version, address)."""

    def __init__(self, ptr):
        self.ptr = ptr

    def __cuda_stream__(self):
        return (0, self.ptr)


class _DeprecatedExternalStream:
    def __init__(self, ptr, device_id=-1):
        warnings.warn('ExternalStream is deprecated', DeprecationWarning, stacklevel=2)
        self.ptr = ptr


class _StreamWithProtocol:
    @classmethod
    def from_external(cls, obj):
        s = cls()
        s.version, s.ptr = obj.__cuda_stream__()
        return s


class _StreamBefore14:
    pass


@pytest.mark.parametrize('stream_cls, want', [(_StreamWithProtocol, '_StreamWithProtocol'),
                                               (_StreamBefore14, '_DeprecatedExternalStream')])
def test_external_stream_uses_the_stream_protocol_where_cupy_has_it(stream_cls, want):
    cp = types.SimpleNamespace(cuda=types.SimpleNamespace(
        Stream=stream_cls, ExternalStream=_DeprecatedExternalStream))
    with warnings.catch_warnings():
        warnings.simplefilter('error' if want == '_StreamWithProtocol' else 'ignore')
        s = _compat.external_stream(cp, 0x7f00)
    assert type(s).__name__ == want and s.ptr == 0x7f00


def test_external_stream_with_the_installed_cupy_warns_nothing():
    cp = pytest.importorskip('cupy')
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        s = _compat.external_stream(cp, 0x7f00)
    assert s.ptr == 0x7f00 and isinstance(s, (cp.cuda.Stream, cp.cuda.ExternalStream))


@pytest.mark.bifrost
@pytest.mark.skipif(not _compat.HAVE_BIFROST, reason="needs real Bifrost (import bifrost) as the runtime")
def test_real_bifrost_unguaranteed_reader_of_frames_that_straddle_the_ring_end():
    """Frames of 24 bytes (no power of two is a multiple), read without a guarantee by a slow sink:
    overruns put the ring's tail inside a frame; our sink keeps running, every frame it delivers
    equals the source's at its offset, and Bifrost's ReadSpan is untouched."""
    import bifrost.ring2 as ring2
    from bf_epic_blocks.blocks.array_io import ArraySinkBlock, ArraySourceBlock
    original = ring2.ReadSpan
    n = 20000
    data = (np.arange(n * 6, dtype=np.float32) + 1).reshape(n, 6)   # no frame is all zeros
    hdr = {'name': 'x', 'time_tag': 0, '_tensor': {'dtype': 'f32', 'shape': [-1, 6]}}
    with _compat.bfp.Pipeline() as p:
        src = ArraySourceBlock(data, hdr, gulp_nframe=16)
        sink = ArraySinkBlock(src, delay_s=0.002, guarantee=False)
        p.run()
    got = sink.result(0)
    kept = np.all(got != 0, axis=1)
    assert got.shape[0] <= n and kept.any()
    np.testing.assert_array_equal(got[kept], data[:got.shape[0]][kept])
    assert ring2.ReadSpan is original


def test_a_source_under_real_bifrost_counts_its_frames_and_drains():
    """bfp.SourceBlock under real Bifrost (CountedSource on Bifrost's class): the frames each gulp wrote,
    its times (the service's monitor reads them), and after drain_event an empty gulp, which ends the
    sequence in Bifrost's SourceBlock; a subclass calling its parent's on_data is counted once."""
    from bf_epic_blocks.blocks._bifrost_fixes import CountedSource

    class BifrostSourceBlock:                      # the part of bifrost.pipeline.SourceBlock that matters
        pass
    Base = type("SourceBlock", (CountedSource, BifrostSourceBlock), {})

    class Src(Base):
        def on_data(self, reader, ospans):
            return [len(ospans[0])]

    class Sub(Src):
        def on_data(self, reader, ospans):
            return super().on_data(reader, ospans)

    for cls in (Src, Sub):
        s = cls()
        assert s.on_data(None, [[1, 2, 3]]) == [3] and s.on_data(None, [[1, 2]]) == [2]
        st = s.stats
        assert (st["ngulp"], st["nframe_written"]) == (2, 5)
        assert st["first_data_at"] <= st["last_data_at"] and st["process_s"] >= 0
        s.drain_event.set()
        assert s.on_data(None, [[1, 2, 3], [4]]) == [0, 0] and s.stats["nframe_written"] == 5
