"""Tests of the built-in Bifrost-compatible runtime, the import layer and the array blocks."""
import copy
import math
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from bf_epic_blocks.runtime import pipeline as rtp
from bf_epic_blocks.runtime.dtypes import unpack_complex, pack_ci4, pack_complex
from bf_epic_blocks.runtime.header import validate_header, HeaderError
from bf_epic_blocks.runtime.ring import Ring
from bf_epic_blocks.blocks import _compat
from bf_epic_blocks.blocks.array_io import ArraySourceBlock, ArraySinkBlock, array_source, \
    array_sink

bfp = rtp  # the runtime under test: always ours (the array blocks must be on it too, see below)

# These tests are about OUR runtime, but the array blocks they use subclass whatever _compat
# picked. Under real Bifrost (picked once per process, at first import) they would mix Bifrost
# blocks into our Pipeline, so they are skipped here and run instead in a subprocess forced onto
# our runtime with BF_EPIC_RUNTIME=builtin (test_whole_file_on_builtin_runtime_under_bifrost).
_RUN_UNDER_BIFROST = {'test_whole_file_on_builtin_runtime_under_bifrost',
                      'test_compat_prefers_bifrost_unless_forced'}


@pytest.fixture(autouse=True)
def _builtin_runtime_only(request):
    if _compat.HAVE_BIFROST and request.node.originalname not in _RUN_UNDER_BIFROST:
        pytest.skip('real Bifrost is the runtime in this process; this file runs on ours in '
                    'test_whole_file_on_builtin_runtime_under_bifrost')


def _gpu():
    try:
        import cupy
        return cupy.cuda.runtime.getDeviceCount() > 0
    except Exception:
        return False


HAS_GPU = _gpu()


def hdr(name='seq', dtype='f32', shape=(-1, 3), time_tag=0, **extra):
    h = {'name': name, 'time_tag': time_tag,
         '_tensor': {'dtype': dtype, 'shape': list(shape)}}
    for key in ('labels', 'scales', 'units'):
        if key in extra:
            h['_tensor'][key] = extra.pop(key)
    h.update(extra)
    return h


def run_with_timeout(p, timeout=15.0):
    """Run ``p`` in a thread; fail (instead of hanging the suite) if it does not finish."""
    box = {}

    def target():
        try:
            p.run()
        except BaseException as exc:  # noqa: BLE001
            box['exc'] = exc
    t = threading.Thread(target=target, daemon=True)
    t.start()
    t.join(timeout)
    assert not t.is_alive(), "pipeline hung"
    if 'exc' in box:
        raise box['exc']


class Scale(bfp.TransformBlock):
    """out = k * in, optionally sleeping per gulp (a slow block)."""

    def __init__(self, iring, k=2, delay_s=0.0, *args, **kwargs):
        super().__init__(iring, *args, **kwargs)
        self.k, self.delay_s = k, delay_s

    def on_sequence(self, iseq):
        return copy.deepcopy(iseq.header)

    def on_data(self, ispan, ospan):
        ospan.data[...] = ispan.data if self.k == 1 else self.k * ispan.data
        if self.delay_s:
            time.sleep(self.delay_s)


class MovingSum(bfp.TransformBlock):
    """FIR-like: out[t] = sum_{k<=W-1} in[t + k] using W-1 frames of overlap (valid mode)."""

    def __init__(self, iring, window, *args, **kwargs):
        super().__init__(iring, *args, **kwargs)
        self.window = window
        self.span_sizes = []

    def define_input_overlap_nframe(self, iseq):
        return self.window - 1

    def on_sequence(self, iseq):
        return copy.deepcopy(iseq.header)

    def on_data(self, ispan, ospan):
        n, w = ispan.nframe, self.window
        self.span_sizes.append((ispan.nframe, ospan.nframe))
        acc = np.zeros_like(ispan.data[:n - w + 1])
        for k in range(w):
            acc += ispan.data[k:n - w + 1 + k]
        ospan.data[:n - w + 1] = acc
        # return None: the runtime commits span - output overlap = n - (w - 1)


class Decimate4(bfp.TransformBlock):
    """Sum every 4 frames within a gulp (a short last group sums what is there)."""

    def define_output_nframes(self, input_nframe):
        return math.ceil(input_nframe / 4)

    def on_sequence(self, iseq):
        return copy.deepcopy(iseq.header)

    def on_data(self, ispan, ospan):
        for j in range(ospan.nframe):
            ospan.data[j] = ispan.data[4 * j:4 * j + 4].sum(axis=0)


class Boom(bfp.TransformBlock):
    def __init__(self, iring, at_gulp=2, where='on_data', *args, **kwargs):
        super().__init__(iring, *args, **kwargs)
        self.at_gulp, self.where, self.count = at_gulp, where, 0

    def on_sequence(self, iseq):
        if self.where == 'on_sequence':
            raise KeyError('no such axis')
        return copy.deepcopy(iseq.header)

    def on_data(self, ispan, ospan):
        self.count += 1
        if self.count > self.at_gulp:
            raise ValueError('boom')
        ospan.data[...] = ispan.data


# --------------------------------------------------------------------------------------------
# ring behaviour
# --------------------------------------------------------------------------------------------

class TimedSource(ArraySourceBlock):
    def on_data(self, reader, ospans):
        ret = super().on_data(reader, ospans)
        if ret == [0]:
            self.t_end = time.monotonic()
        return ret


def test_guaranteed_reader_loses_nothing_and_backpressures():
    x = np.arange(400 * 4, dtype=np.int32).reshape(400, 4)
    with bfp.Pipeline() as p:
        src = TimedSource(x, hdr(dtype='i32', shape=(-1, 4)), gulp_nframe=8)
        mid = Scale(src, k=3)
        sink = ArraySinkBlock(mid, delay_s=0.004)   # 50 gulps x 4 ms >> the source's time
        t0 = time.monotonic()
        run_with_timeout(p)
        t_all = time.monotonic() - t0
    np.testing.assert_array_equal(sink.result(0), 3 * x)
    assert mid.stats['nframe_skipped'] == 0 and sink.stats['nframe_skipped'] == 0
    assert mid.stats['nframe_read'] == 400 and sink.stats['nframe_read'] == 400
    # Back-pressure: the rings hold a few gulps only, so the source cannot finish before the
    # sink has taken most of the data (unbounded buffering would end it within milliseconds).
    cap = mid.orings[0].capacity
    assert cap < 400 and src.orings[0].capacity < 400
    assert src.t_end - t0 > 0.5 * 0.004 * (50 - 2 * cap // 8 - 4), (src.t_end - t0, t_all)


def test_block_timing_counts_the_time_spent_in_on_data():
    """stats['process_s'] is the host time inside on_data (a sink that sleeps 4 ms a gulp spends at
    least 50 x 4 ms there), first/last_data_at bracket the gulps, first_done_at is the end of the first
    (one 4-ms sleep after its start), and the runner's block_timing reports them after its start; blocks
    without them (real Bifrost) are left out."""
    from bf_epic_blocks.pipeline.runner import block_timing
    x = np.arange(400 * 4, dtype=np.int32).reshape(400, 4)
    t0 = time.perf_counter()
    with bfp.Pipeline() as p:
        src = TimedSource(x, hdr(dtype='i32', shape=(-1, 4)), gulp_nframe=8)
        sink = ArraySinkBlock(src, delay_s=0.004)
        run_with_timeout(p)
    st = sink.stats
    assert st['ngulp'] == 50 and 0.2 <= st['process_s'] <= time.perf_counter() - t0
    assert t0 < st['first_data_at'] < st['last_data_at'] and st['last_data_at'] - st['first_data_at'] >= 0.196
    assert st['first_data_at'] + 0.004 <= st['first_done_at'] < st['last_data_at']
    bt = block_timing([src, sink, object()], t0)
    assert set(bt) == {src.name, sink.name}
    assert bt[sink.name]['ngulp'] == 50 and bt[sink.name]['process_s'] == round(st['process_s'], 4)
    assert 0 < bt[sink.name]['first_data_s'] < bt[sink.name]['first_done_s'] < bt[sink.name]['last_data_s']


def test_unguaranteed_reader_skips_are_counted_and_zero_filled():
    n = 400
    x = 1 + np.arange(n * 2, dtype=np.float32).reshape(n, 2)   # no zeros in the input
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(x, hdr(shape=(-1, 2)), gulp_nframe=4)
        slow = Scale(src, k=2, delay_s=0.01, guarantee=False)
        sink = ArraySinkBlock(slow)
        run_with_timeout(p)
    out = sink.result(0)
    assert out.shape == x.shape      # frame counts stay consistent: every input frame -> one
    zero = np.all(out == 0, axis=1)
    good = np.all(out == 2 * x, axis=1)
    assert np.all(zero | good)
    assert slow.stats['nframe_skipped'] > 0
    assert zero.sum() == slow.stats['nframe_skipped']
    assert good.sum() == slow.stats['nframe_read']
    assert slow.stats['nframe_written'] == n


def test_unguaranteed_sink_on_skip_records_zeros():
    n = 300
    x = 1 + np.arange(n, dtype=np.float64).reshape(n, 1)
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(x, hdr(dtype='f64', shape=(-1, 1)), gulp_nframe=5)
        sink = ArraySinkBlock(src, delay_s=0.01, guarantee=False)
        run_with_timeout(p)
    out = sink.result(0)
    assert out.shape == x.shape
    assert sink.nframe_skipped[0] == sink.stats['nframe_skipped'] > 0
    lost = out[:, 0] == 0
    assert lost.sum() == sink.nframe_skipped[0]
    np.testing.assert_array_equal(out[~lost], x[~lost])


def test_overlap_moving_sum_and_short_last_gulp():
    rng = np.random.default_rng(1)
    n, w, gulp = 55, 4, 10
    x = rng.normal(size=(n, 3))
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(x, hdr(dtype='f64'), gulp_nframe=gulp)
        fir = MovingSum(src, w)
        sink = ArraySinkBlock(fir)
        run_with_timeout(p)
    truth = np.stack([np.convolve(x[:, c], np.ones(w), mode='valid') for c in range(3)], 1)
    out = sink.result(0)
    assert out.shape == truth.shape == (n - w + 1, 3)
    np.testing.assert_allclose(out, truth, rtol=1e-12, atol=1e-12)
    # spans of gulp + overlap frames every gulp frames, the last one short
    assert fir.span_sizes == [(13, 13)] * 5 + [(5, 5)]
    assert sink.headers[0]['gulp_nframe'] == gulp
    # the reader asked for ceil((gulp + overlap) * 3) frames of ring
    assert src.orings[0].capacity >= 3 * (gulp + w - 1)


def test_several_sequences_keep_headers_and_data():
    rng = np.random.default_rng(2)
    arrays = [rng.normal(size=(17, 2)).astype(np.float32),
              rng.normal(size=(3, 5)).astype(np.float32),
              np.zeros((0, 2), np.float32),
              rng.normal(size=(40, 2, 3)).astype(np.float32)]
    headers = [hdr('a', shape=(-1, 2), time_tag=10, labels=['time', 'x'],
                   scales=[[0.0, 0.5], None], units=['s', None], extra={'k': [1, 2]}),
               hdr('b', shape=(-1, 5), time_tag=20),
               hdr('empty', shape=(-1, 2), time_tag=30),
               # a ringlet axis before the frame axis: arrays stay frame-axis-first
               hdr('c', shape=(2, -1, 3), time_tag=40)]
    arrays[3] = rng.normal(size=(40, 2, 3)).astype(np.float32)
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(arrays, headers, gulp_nframe=6)
        mid = Scale(src, k=-1)
        sink = ArraySinkBlock(mid)
        run_with_timeout(p)
    assert [h['name'] for h in sink.headers] == ['a', 'b', 'empty', 'c']
    assert [h['time_tag'] for h in sink.headers] == [10, 20, 30, 40]
    assert sink.headers[0]['extra'] == {'k': [1, 2]}
    assert sink.headers[0]['_tensor']['scales'] == [[0.0, 0.5], None]
    assert all(h['gulp_nframe'] == 6 for h in sink.headers)
    for a, got in zip(arrays, sink.arrays):
        np.testing.assert_array_equal(got, -a)
    assert mid.stats['nsequence'] == 4


def test_define_output_nframes_decimation():
    rng = np.random.default_rng(3)
    n, gulp = 50, 12
    x = rng.integers(-100, 100, size=(n, 2)).astype(np.int64)
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(x, hdr(dtype='i64', shape=(-1, 2)), gulp_nframe=gulp)
        dec = Decimate4(src)
        sink = ArraySinkBlock(dec)
        run_with_timeout(p)
    # gulps of 12 frames -> 3 outputs each; the short last gulp (2 frames) -> 1 output
    truth = np.concatenate([x[:48].reshape(12, 4, 2).sum(1), x[48:].sum(0, keepdims=True)])
    np.testing.assert_array_equal(sink.result(0), truth)
    assert sink.headers[0]['gulp_nframe'] == 3


def in_fresh_thread(fn, timeout=15.0):
    """Run ``fn`` in a new thread: it gets its own default pipeline (thread-local), so blocks
    other test modules left in this thread's default pipeline cannot interfere."""
    box = {}

    def target():
        try:
            fn()
        except BaseException as exc:  # noqa: BLE001
            box['exc'] = exc
    t = threading.Thread(target=target, daemon=True)
    t.start()
    t.join(timeout)
    assert not t.is_alive(), "hung"
    if 'exc' in box:
        raise box['exc']


def test_block_scope_and_default_pipeline():
    in_fresh_thread(_block_scope_and_default_pipeline)


def _block_scope_and_default_pipeline():
    x = np.arange(30, dtype=np.float32).reshape(30, 1)
    src = ArraySourceBlock(x, hdr(shape=(-1, 1)), gulp_nframe=10)   # default pipeline
    with bfp.block_scope(gulp_nframe=4, buffer_factor=5):
        mid = Scale(src, k=1)
    sink = array_sink(mid)
    assert mid.gulp_nframe == 4 and mid.buffer_factor == 5 and sink.gulp_nframe is None
    p = bfp.get_default_pipeline()
    assert p.blocks == [src, mid, sink]
    p.run()
    assert bfp.get_default_pipeline() is not p       # a fresh default afterwards
    np.testing.assert_array_equal(sink.result(0), x)
    assert sink.headers[0]['gulp_nframe'] == 4
    assert src.orings[0].capacity >= 20            # ceil(4 * 5)
    with pytest.raises(RuntimeError, match='already run'):
        p.run()


def test_bad_block_arguments():
    with bfp.Pipeline():
        src = array_source(np.zeros((4, 1)), hdr(dtype='f64', shape=(-1, 1)), 2)
        with pytest.raises(TypeError):
            Scale(src, bogus_keyword=1)
        with pytest.raises(ValueError, match='gulp_nframe'):
            Scale(src, gulp_nframe=0)

        class GpuOnly(Scale):
            def define_valid_input_spaces(self):
                return ('cuda',)

        class BareString(Scale):
            def define_valid_input_spaces(self):
                return 'cuda'
        with pytest.raises(ValueError, match="space 'system'"):
            GpuOnly(src)
        with pytest.raises(TypeError, match='bare string'):
            BareString(src)
        with pytest.raises(TypeError, match='Block or a Ring'):
            Scale(np.zeros(3))


# --------------------------------------------------------------------------------------------
# errors and shutdown
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize('where', ['on_data', 'on_sequence'])
def test_exception_in_block_reaches_run_without_hanging(where):
    x = np.ones((20000, 8), np.float32)   # far more than any ring: the source must be woken
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(x, hdr(shape=(-1, 8)), gulp_nframe=16)
        Boom(src, at_gulp=2, where=where, name='bad')
        ArraySinkBlock(Scale(src), delay_s=0.001)
    t0 = time.monotonic()
    with pytest.raises(rtp.PipelineError, match=r"block 'bad' \(Boom\) failed") as info:
        run_with_timeout(p)
    assert time.monotonic() - t0 < 10
    cause = info.value.__cause__
    assert isinstance(cause, ValueError if where == 'on_data' else KeyError)
    assert info.value.block_name == 'bad'


def test_exception_in_source_wakes_downstream():
    class BadSource(ArraySourceBlock):
        def on_data(self, reader, ospans):
            if reader.pos >= 8:
                raise OSError('disk gone')
            return super().on_data(reader, ospans)
    with bfp.Pipeline() as p:
        BadSource(np.ones((100, 1)), hdr(dtype='f64', shape=(-1, 1)), 4, name='src')
        ArraySinkBlock(Scale(p.blocks[0]))
    with pytest.raises(rtp.PipelineError, match=r"block 'src' \(BadSource\).*disk gone"):
        run_with_timeout(p)


def test_bad_output_header_is_reported():
    class BadHeader(Scale):
        def on_sequence(self, iseq):
            h = copy.deepcopy(iseq.header)
            h['_tensor']['shape'] = [4, 3]
            return h
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(np.ones((10, 3)), hdr(dtype='f64'), 5)
        ArraySinkBlock(BadHeader(src, name='hdr'))
    with pytest.raises(rtp.PipelineError, match="block 'hdr'.*exactly one -1") as info:
        run_with_timeout(p)
    assert isinstance(info.value.__cause__, HeaderError)


# --------------------------------------------------------------------------------------------
# headers
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize('mutate, match', [
    (lambda h: h.pop('name'), "'name'"),
    (lambda h: h.update(time_tag=-1), "time_tag"),
    (lambda h: h.update(time_tag=1.5), "time_tag"),
    (lambda h: h.update(time_tag=True), "time_tag"),
    (lambda h: h.pop('_tensor'), "_tensor"),
    (lambda h: h['_tensor'].update(dtype='c64'), "unknown Bifrost dtype"),
    (lambda h: h['_tensor'].update(shape=[3, 4]), "exactly one -1"),
    (lambda h: h['_tensor'].update(shape=[-1, -1]), "exactly one -1"),
    (lambda h: h['_tensor'].update(shape=[-1, 0]), ">= 1"),
    (lambda h: h['_tensor'].update(labels=['time']), "one entry per axis"),
    (lambda h: h['_tensor'].update(labels=['t', 't']), "unique"),
    (lambda h: h['_tensor'].update(scales=[None, [1.0]]), "offset, step"),
    (lambda h: h['_tensor'].update(units=[None, 3]), "str or None"),
    (lambda h: h.update(bad=np.arange(3)), "JSON"),
    (lambda h: h.update(gulp_nframe=-2), "gulp_nframe"),
])
def test_header_validation_errors(mutate, match):
    h = hdr(labels=['time', 'x'])
    mutate(h)
    with pytest.raises(HeaderError, match=match):
        validate_header(h)
    assert issubclass(HeaderError, ValueError)


def test_header_round_trip_is_json():
    h = hdr(scales=None, note=(1, 2))
    out = validate_header(h)
    assert out['note'] == [1, 2] and out is not h


@pytest.mark.parametrize("extra", [
    {"note": (1, 2), "nested": {"a": [(1.5, -0.0), [True, None, "s"]], "b": []}},
    {"nan": float("nan"), "inf": [float("inf"), -float("inf")], "big": 2 ** 70},
    {"station": {"cable_gain": [[[0.5, 1.0], [2.0, 3.0]]] * 3, "xyz_m": [[1.0, 2.0, 3.0]]}},
    {"np64": np.float64(0.1), "rows": [np.float64(1.5), 2.0]},      # float subclasses: plain floats after
    {1: "int key", None: "none key", True: "bool key"},                # keys JSON writes as strings
])
def test_header_copy_is_the_json_round_trip(extra):
    """validate_header and a reader's header copy give what a JSON round trip gives (tuples as lists, floats as
    floats, keys as strings), as a copy that shares nothing with the writer's dict."""
    import json
    from bf_epic_blocks.runtime.header import plain_copy
    h = hdr()
    h.update(extra)
    want = json.loads(json.dumps(h, allow_nan=True))
    got = validate_header(h)
    assert json.dumps(got, sort_keys=True) == json.dumps(want, sort_keys=True)
    assert all(type(a) is type(b) for a, b in zip(_leaves(got), _leaves(want)))
    again = plain_copy(got)
    assert json.dumps(again, sort_keys=True) == json.dumps(want, sort_keys=True)
    for copy_ in (got, again):
        for a, b in zip(_containers(copy_), _containers(h)):
            assert a is not b


def _leaves(x):
    if isinstance(x, dict):
        for k in sorted(x, key=str):
            yield from _leaves(x[k])
    elif isinstance(x, list):
        for v in x:
            yield from _leaves(v)
    else:
        yield x


def _containers(x):
    if isinstance(x, (dict, list, tuple)):
        yield x
        for v in (x.values() if isinstance(x, dict) else x):
            yield from _containers(v)


@pytest.mark.parametrize("bad", [np.float32(1.0), np.int64(3), {"k": object()}])
def test_header_values_json_cannot_write_are_refused(bad):
    with pytest.raises(HeaderError, match="not JSON-serialisable"):
        validate_header(hdr(bad=bad))


def test_a_header_that_holds_itself_is_refused():
    h = hdr()
    h["me"] = [h]
    with pytest.raises(HeaderError, match="not JSON-serialisable"):
        validate_header(h)


def test_duplicate_sequence_name_rejected():
    r = Ring()
    with r.begin_writing() as w:
        with w.begin_sequence(hdr('a'), 4):
            pass
        with pytest.raises(ValueError, match='already used'):
            w.begin_sequence(hdr('a'), 4)


# --------------------------------------------------------------------------------------------
# data types
# --------------------------------------------------------------------------------------------

CI4_TABLE = [(0x00, 0 + 0j), (0x7F, 7 - 1j), (0x80, -8 + 0j), (0x9E, -7 - 2j),
             (0x11, 1 + 1j), (0xF0, -1 + 0j), (0x0F, 0 - 1j), (0x88, -8 - 8j),
             (0x77, 7 + 7j), (0x3C, 3 - 4j)]


def test_ci4_unpack_table_and_all_forms():
    b = np.array([t[0] for t in CI4_TABLE], np.uint8)
    want = np.array([t[1] for t in CI4_TABLE], np.complex64)
    for form in (b, b.view([('re_im', 'u1')]), b.view(np.int8).view([('re_im', 'i1')])):
        got = unpack_complex(form, 'ci4')
        assert got.dtype == np.complex64
        np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(pack_ci4(want), b)


def test_ci4_round_trip_all_bytes_and_clipping():
    allb = np.arange(256, dtype=np.uint8).reshape(16, 16)
    np.testing.assert_array_equal(pack_ci4(unpack_complex(allb, 'ci4')), allb)
    # round half to even, then clip to [-8, 7]
    v = np.array([9.6 - 8.6j, -20 + 0.4j, 2.5 + 1.5j])
    np.testing.assert_array_equal(pack_ci4(v), np.array([0x78, 0x80, 0x22], np.uint8))


def test_ci8_ci16_forms():
    v = np.array([1 - 2j, -128 + 127j, 300 - 300j, 0.4 + 0.6j])
    s = pack_complex(v, 'ci8')
    assert s.dtype.names == ('re', 'im') and s.dtype['re'] == np.int8
    np.testing.assert_array_equal(s['re'], [1, -128, 127, 0])
    np.testing.assert_array_equal(s['im'], [-2, 127, -128, 1])
    want = np.array([1 - 2j, -128 + 127j, 127 - 128j, 0 + 1j], np.complex64)
    np.testing.assert_array_equal(unpack_complex(s, 'ci8'), want)
    plain = pack_complex(v, 'ci8', space='cuda', xp=np)       # CuPy form, built on host
    assert plain.shape == (4, 2) and plain.dtype == np.int8
    np.testing.assert_array_equal(unpack_complex(plain, 'ci8'), want)
    s16 = pack_complex(v, 'ci16')
    np.testing.assert_array_equal(unpack_complex(s16, 'ci16'),
                                  np.array([1 - 2j, -128 + 127j, 300 - 300j, 1j], np.complex64))
    with pytest.raises(TypeError, match='length 2'):
        unpack_complex(np.zeros((3, 3), np.int8), 'ci8')
    with pytest.raises(ValueError, match='unknown Bifrost dtype'):
        unpack_complex(s, 'ci9')


@pytest.mark.parametrize('dtype', ['ci4', 'ci8', 'cf32'])
def test_complex_through_pipeline(dtype):
    rng = np.random.default_rng(4)
    z = (rng.normal(size=(21, 3, 2)) + 1j * rng.normal(size=(21, 3, 2))) * 3
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(z, hdr(dtype=dtype, shape=(-1, 3, 2)), gulp_nframe=4)
        sink = ArraySinkBlock(src)
        run_with_timeout(p)
    got = sink.result(0, as_complex=True)
    if dtype == 'ci4':
        want = np.clip(np.rint(z.real), -8, 7) + 1j * np.clip(np.rint(z.imag), -8, 7)
    elif dtype == 'ci8':
        want = np.rint(z.real) + 1j * np.rint(z.imag)
    else:
        want = z.astype(np.complex64)
    np.testing.assert_array_equal(got, want.astype(np.complex64))
    if dtype == 'ci4':  # stored as Bifrost shows it: one byte per sample, structured 're_im'
        assert sink.result(0).dtype == np.dtype([('re_im', 'u1')])


# --------------------------------------------------------------------------------------------
# import layer
# --------------------------------------------------------------------------------------------

def test_compat_helpers_on_builtin_runtime():
    spans = {}

    class Peek(bfp.SinkBlock):
        def on_sequence(self, iseq):
            spans['seq_space'] = _compat.space_of(iseq)

        def on_data(self, ispan):
            spans['arr'] = _compat.span_array(ispan)
            spans['space'] = _compat.space_of(ispan)
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(np.ones((4, 2), np.float32), hdr(shape=(-1, 2)), 4)
        Peek(src)
        run_with_timeout(p)
    assert isinstance(spans['arr'], np.ndarray) and spans['arr'].shape == (4, 2)
    assert spans['space'] == spans['seq_space'] == 'system' == _compat.space_of(src)
    with _compat.stream_context():
        pass
    for name in ('Pipeline', 'block_scope', 'SourceBlock', 'TransformBlock', 'SinkBlock',
                 'get_default_pipeline'):
        assert hasattr(_compat.bfp, name)


_FAKE_BIFROST = {
    'bifrost/__init__.py': "",
    'bifrost/pipeline.py': "".join(f"class {n}:\n    pass\n" for n in (
        'Pipeline', 'SourceBlock', 'TransformBlock', 'SinkBlock', 'MultiTransformBlock'))
    + "def block_scope(**kw): pass\ndef get_default_pipeline(): pass\nFAKE = True\n",
}


@pytest.mark.parametrize('env, want', [('', True), ('builtin', False)])
def test_compat_prefers_bifrost_unless_forced(tmp_path, env, want):
    for rel, text in _FAKE_BIFROST.items():
        f = tmp_path / rel
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text(text)
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    # Load _compat alone (not the blocks package, whose other modules need a real Bifrost).
    code = ("import importlib.util, sys, types\n"
            "import bf_epic_blocks\n"
            "pkg = types.ModuleType('bf_epic_blocks.blocks')\n"
            f"pkg.__path__ = [{os.path.join(repo, 'bf_epic_blocks', 'blocks')!r}]\n"
            "sys.modules['bf_epic_blocks.blocks'] = pkg\n"
            "spec = importlib.util.spec_from_file_location('bf_epic_blocks.blocks._compat',"
            " pkg.__path__[0] + '/_compat.py')\n"
            "c = importlib.util.module_from_spec(spec); spec.loader.exec_module(c)\n"
            "print(c.HAVE_BIFROST, c.BIFROST_IMPORTABLE, hasattr(c.bfp, 'FAKE'))\n")
    envd = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), repo]),
                BF_EPIC_RUNTIME=env)
    out = subprocess.run([sys.executable, '-c', code], env=envd, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == [str(want), 'True', str(want)]


# --------------------------------------------------------------------------------------------
# 'cuda' space
# --------------------------------------------------------------------------------------------

@pytest.mark.skipif(HAS_GPU, reason='a GPU is present')
def test_cuda_space_without_gpu_is_a_clear_error():
    with pytest.raises(ValueError, match="space 'cuda' needs CuPy"):
        Ring(space='cuda')
    with bfp.Pipeline():
        with pytest.raises(ValueError, match="space 'cuda'"):
            ArraySourceBlock(np.zeros((2, 1)), hdr(dtype='f64', shape=(-1, 1)), 1,
                             space='cuda')


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_GPU, reason='needs CuPy and a CUDA device')
@pytest.mark.parametrize('dtype', ['ci4', 'ci8', 'cf32', 'f32'])
def test_cuda_space_pipeline(dtype):
    import cupy as cp
    rng = np.random.default_rng(5)
    z = (rng.normal(size=(37, 4)) + 1j * rng.normal(size=(37, 4))) * 3
    if dtype == 'f32':
        z = z.real

    class GpuCopy(bfp.TransformBlock):
        def define_valid_input_spaces(self):
            return ('cuda',)

        def on_sequence(self, iseq):
            return copy.deepcopy(iseq.header)

        def on_data(self, ispan, ospan):
            src, dst = _compat.span_array(ispan), _compat.span_array(ospan)
            assert isinstance(src, cp.ndarray) and isinstance(dst, cp.ndarray)
            dst[...] = src

    class ToHost(bfp.TransformBlock):
        def __init__(self, iring, *args, **kwargs):
            super().__init__(iring, *args, **kwargs)
            self.orings = [self.create_ring(space='system')]

        def on_sequence(self, iseq):
            h = copy.deepcopy(iseq.header)
            h['_tensor']['dtype'] = 'cf32'
            return h

        def on_data(self, ispan, ospan):
            ospan.data[...] = cp.asnumpy(unpack_complex(ispan.data, dtype))

    with bfp.Pipeline() as p:
        src = ArraySourceBlock(z, hdr(dtype=dtype, shape=(-1, 4)), gulp_nframe=8, space='cuda')
        g = GpuCopy(src, gpu=0)
        sink_dev = ArraySinkBlock(g)
        sink_host = ArraySinkBlock(ToHost(g))
        run_with_timeout(p, 60)
    want = pack_complex(z, dtype, space='system')
    want_c = unpack_complex(want, dtype) if dtype != 'f32' else z.astype(np.complex64)
    np.testing.assert_array_equal(sink_dev.result(0, as_complex=True), want_c)
    np.testing.assert_array_equal(sink_host.result(0), want_c)


def _ngpu():
    return __import__('cupy').cuda.runtime.getDeviceCount() if HAS_GPU else 0


@pytest.mark.gpu
@pytest.mark.skipif(_ngpu() < 2, reason='needs two CUDA devices')
def test_block_scope_gpu_puts_every_block_thread_on_that_gpu():
    """Blocks built in block_scope(gpu=1) (what `device: gpu:1` builds) allocate their 'cuda' rings
    and run their kernels on GPU 1, although each runs in its own thread."""
    import cupy as cp
    z = np.arange(64, dtype=np.float32).reshape(16, 4)
    seen = []

    class Twice(bfp.TransformBlock):
        def on_sequence(self, iseq):
            return copy.deepcopy(iseq.header)

        def on_data(self, ispan, ospan):
            src, dst = _compat.span_array(ispan), _compat.span_array(ospan)
            seen.append((src.device.id, dst.device.id, cp.cuda.Device().id))
            dst[...] = 2 * src

    with bfp.Pipeline() as p, bfp.block_scope(gpu=1):
        src = ArraySourceBlock(z, hdr(dtype='f32', shape=(-1, 4)), gulp_nframe=4, space='cuda')
        sink = ArraySinkBlock(Twice(src))
        run_with_timeout(p, 60)
    assert seen and all(s == (1, 1, 1) for s in seen)
    np.testing.assert_array_equal(sink.result(0), 2 * z)


def test_cuda_host_space_ring_is_page_locked_where_there_is_a_gpu():
    """A 'cuda_host' ring carries the data like a 'system' one; with a GPU its storage is page-locked
    (so a GPU's copy of it is asynchronous), without one it is plain host memory (CPU CI)."""
    rng = np.random.default_rng(6)
    z = (rng.normal(size=(29, 4)) + 1j * rng.normal(size=(29, 4))) * 3
    seen = []

    class Look(bfp.TransformBlock):
        def on_sequence(self, iseq):
            return copy.deepcopy(iseq.header)

        def on_data(self, ispan, ospan):
            src = _compat.span_array(ispan)
            assert isinstance(src, np.ndarray)
            if HAS_GPU:
                import cupy as cp
                attr = cp.cuda.runtime.pointerGetAttributes(src.ctypes.data)
                seen.append(attr.type)
            _compat.span_array(ospan)[...] = src

    with bfp.Pipeline() as p:
        src = ArraySourceBlock(z, hdr(dtype='ci8', shape=(-1, 4)), gulp_nframe=8, space='cuda_host')
        sink = ArraySinkBlock(Look(src))
        run_with_timeout(p, 60)
    want = unpack_complex(pack_complex(z, 'ci8', space='system'), 'ci8')
    np.testing.assert_array_equal(sink.result(0, as_complex=True), want)
    if HAS_GPU:
        import cupy as cp
        assert seen and all(t == cp.cuda.runtime.memoryTypeHost for t in seen)


def test_block_whose_constructor_raises_leaves_the_pipeline():
    class Picky(Scale):
        def __init__(self, iring, *args, **kwargs):
            super().__init__(iring, *args, **kwargs)
            raise ValueError('bad parameter')
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(np.ones((4, 1)), hdr(dtype='f64', shape=(-1, 1)), 2)
        with pytest.raises(ValueError, match='bad parameter'):
            Picky(src)
        sink = ArraySinkBlock(src)
    assert p.blocks == [src, sink]
    run_with_timeout(p)
    np.testing.assert_array_equal(sink.result(0), np.ones((4, 1)))


@pytest.mark.skipif(not _compat.HAVE_BIFROST, reason='only needed where real Bifrost is picked')
def test_whole_file_on_builtin_runtime_under_bifrost():
    """On a Bifrost machine: this file again, in a process forced onto our runtime."""
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, BF_EPIC_RUNTIME='builtin')
    out = subprocess.run([sys.executable, '-m', 'pytest', '-q', '-p', 'no:cacheprovider',
                          os.path.abspath(__file__)], cwd=repo, env=env, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
    assert ' passed' in out.stdout and ' failed' not in out.stdout


# --------------------------------------------------------------------------------------------
# zero-copy spans, wrap-around, back-pressure with views
# --------------------------------------------------------------------------------------------

def _storage(ring):
    """The storage buffer of the ring's newest sequence (runtime internals, for these tests)."""
    return ring._seqs[-1].buf


def test_guaranteed_reads_are_views_of_the_ring_and_read_only():
    seen = []

    class Check(bfp.SinkBlock):
        def on_sequence(self, iseq):
            pass

        def on_data(self, ispan):
            seen.append((np.shares_memory(ispan.data, _storage(self.iring)),
                         ispan.data.flags.writeable, ispan.data.copy(), ispan.frame_offset))

    written = []

    class Src(ArraySourceBlock):
        def on_data(self, reader, ospans):
            written.append(np.shares_memory(ospans[0].data, _storage(self.orings[0])))
            return super().on_data(reader, ospans)

    x = np.arange(50 * 3, dtype=np.float32).reshape(50, 3)
    with bfp.Pipeline() as p:
        src = Src(x, hdr(shape=(-1, 3)), gulp_nframe=8)
        Check(src)
        run_with_timeout(p)
    assert written and all(written)                      # writers fill the ring in place
    assert len(seen) == 7 and all(shared for shared, _, _, _ in seen)
    assert not any(w for _, w, _, _ in seen)             # a reader cannot scribble on the ring
    np.testing.assert_array_equal(np.concatenate([d for _, _, d, _ in seen]), x)


def _write_frames(ring, name, values, gulp, buf_nframe=None, ringlets=()):
    """Write ``values`` (frames first) as one sequence, in gulps; returns the frame shape."""
    shape = list(ringlets) + [-1] + list(values.shape[1 + len(ringlets):])
    frames = values
    with ring.begin_writing() as w:
        with w.begin_sequence(hdr(name, dtype='f64', shape=shape), gulp, buf_nframe) as s:
            for i in range(0, len(frames), gulp):
                chunk = frames[i:i + gulp]
                with s.reserve(gulp) as span:
                    r = len(ringlets)
                    dst = span.data[(slice(None),) * r + (slice(0, len(chunk)),)]
                    dst[...] = np.moveaxis(chunk, 0, r) if r else chunk
                    span.commit(len(chunk))


@pytest.mark.parametrize('ringlets', [(), (2,)])
def test_wrap_around_with_odd_sizes_and_overlap(ringlets):
    """Capacity not a multiple of the gulps, spans with overlap: every span crosses the end of
    the buffer at some point; contents must be exact and spans still views (ghost mirror)."""
    rng = np.random.default_rng(7)
    n, wgulp, rgulp, stride = 95, 7, 9, 5
    x = rng.normal(size=(n,) + tuple(ringlets) + (3,))
    ring = Ring()
    got, shared, offsets = [], [], []
    rd = ring.open_reader(guarantee=True)   # registered before the writer starts

    def reader():
        for seq in rd.sequences():
            seq.resize(rgulp, buf_nframe=17)
            for span in seq.read(rgulp, stride):
                got.append(np.array(span.data))
                shared.append(np.shares_memory(span.data, seq._seq.buf))
                offsets.append(span.frame_offset)
                time.sleep(0.001)
        rd.close()

    t = threading.Thread(target=reader, daemon=True)
    t.start()
    _write_frames(ring, 'w', x, wgulp, ringlets=ringlets)
    t.join(10)
    assert not t.is_alive()
    cap, ghost = ring.capacity, ring.ghost
    assert cap == 17 and ghost == rgulp and cap % wgulp and cap % stride
    r = len(ringlets)
    for off, d in zip(offsets, got):
        want = x[off:off + rgulp]
        np.testing.assert_array_equal(np.moveaxis(d, r, 0), want)
    assert offsets == list(range(0, n - (rgulp - stride), stride))
    wrapped = [off for off in offsets if off % cap + min(rgulp, n - off) > cap]
    assert wrapped                                # the test does exercise the wrap
    assert all(shared)                            # ... and the ghost keeps those spans views


def test_gulps_that_divide_the_capacity_never_copy_into_the_ghost(monkeypatch):
    """Writes and reads of one gulp, a capacity of three: no span crosses the end, so no frame is
    mirrored into the ghost (every write landing in the head was, costing a third of the whole band's
    image gulps a copy); the contents are exact."""
    from bf_epic_blocks.runtime import ring as ring_mod
    mirrored = []
    orig = ring_mod.Ring._sync_ghost

    def counting(self, seq, lo, hi):
        mirrored.append(max(0, min(hi, seq.buf_ghost) - lo))
        return orig(self, seq, lo, hi)
    monkeypatch.setattr(ring_mod.Ring, "_sync_ghost", counting)
    x = np.arange(48 * 2, dtype=np.float64).reshape(48, 2)
    ring = Ring()
    got = []
    rd = ring.open_reader(guarantee=True)

    def reader():
        for seq in rd.sequences():
            seq.resize(4, buf_nframe=12)
            for span in seq.read(4):
                got.append(np.array(span.data))
        rd.close()

    t = threading.Thread(target=reader, daemon=True)
    t.start()
    _write_frames(ring, 'w', x, 4)
    t.join(10)
    assert not t.is_alive() and ring.capacity == 12 and ring.ghost == 4
    np.testing.assert_array_equal(np.concatenate(got), x)
    assert sum(mirrored) == 0


def test_backpressure_holds_a_viewed_span_until_released():
    ring = Ring()
    gulp = 4
    x = np.arange(40, dtype=np.float64).reshape(40, 1)
    events = {'held': threading.Event(), 'release': threading.Event()}
    box = {}

    rd = ring.open_reader(guarantee=True)

    def reader():
        for seq in rd.sequences():
            seq.resize(gulp, buf_nframe=2 * gulp)
            for span in seq.read(gulp):
                if span.frame_offset == 0:
                    box['first'] = span.data
                    box['before'] = span.data.copy()
                    events['held'].set()
                    events['release'].wait(10)
                    box['after'] = span.data.copy()   # still intact while held
        rd.close()

    writer_done = threading.Event()

    def writer():
        _write_frames(ring, 'bp', x, gulp)
        writer_done.set()

    tr = threading.Thread(target=reader, daemon=True)
    tr.start()
    tw = threading.Thread(target=writer, daemon=True)
    tw.start()
    assert events['held'].wait(10)
    time.sleep(0.2)
    # the writer cannot get more than one buffer ahead of the held span
    assert not writer_done.is_set()
    assert ring._head <= ring.capacity
    events['release'].set()
    tw.join(10)
    tr.join(10)
    assert writer_done.is_set()
    np.testing.assert_array_equal(box['before'], x[:gulp])
    np.testing.assert_array_equal(box['after'], x[:gulp])


def test_unguaranteed_spans_are_copies_and_never_torn():
    n = 300
    x = np.repeat(np.arange(n, dtype=np.float64)[:, None], 3, axis=1)
    bad, shared = [], []

    class Slow(bfp.SinkBlock):
        def on_sequence(self, iseq):
            pass

        def on_data(self, ispan):
            shared.append(np.shares_memory(ispan.data, _storage(self.iring)))
            want = ispan.frame_offset + np.arange(ispan.nframe)
            time.sleep(0.003)    # the writer moves on meanwhile; a copy cannot change
            if not np.array_equal(ispan.data[:, 0], want):
                bad.append(ispan.frame_offset)

        def on_skip(self, islices, ospans):
            pass

    class Paced(ArraySourceBlock):
        def on_data(self, reader, ospans):
            time.sleep(0.001)
            return super().on_data(reader, ospans)

    with bfp.Pipeline() as p:
        src = Paced(x, hdr(dtype='f64', shape=(-1, 3)), gulp_nframe=4)
        slow = Slow(src, guarantee=False)
        run_with_timeout(p)
    assert slow.stats['nframe_skipped'] > 0 and slow.stats['nframe_read'] > 0
    assert slow.stats['nframe_skipped'] + slow.stats['nframe_read'] == n
    assert not bad and shared and not any(shared)


def test_capacity_growth_while_a_write_span_is_open():
    """A reader asking for more room re-lays the storage out while the writer holds a span:
    the frames of that span must land in the new storage at commit."""
    ring = Ring()
    x = np.arange(32, dtype=np.float64).reshape(32, 1)
    with ring.begin_writing() as w:
        with w.begin_sequence(hdr('g', dtype='f64', shape=(-1, 1)), 4) as s:
            rd = ring.open_reader(guarantee=True)
            seqs = rd.sequences()
            rseq = next(seqs)
            rseq.resize(4, buf_nframe=12)   # room for the first 12 frames without reading
            for i in range(0, 12, 4):
                with s.reserve(4) as span:
                    span.data[...] = x[i:i + 4]
                    if i == 8:
                        rseq.resize(6, buf_nframe=40)   # grows capacity mid-span
            assert ring.capacity == 40
            got = []
            spans = rseq.read(6)
            for i in range(12, 32, 4):
                with s.reserve(4) as span:
                    span.data[...] = x[i:i + 4]
            s.end()
            for span in spans:
                got.append(np.array(span.data))
            np.testing.assert_array_equal(np.concatenate(got), x)


@pytest.mark.parametrize('space', ['system', pytest.param('cuda', marks=[
    pytest.mark.gpu, pytest.mark.skipif(not HAS_GPU, reason='needs CuPy and a CUDA device')])])
@pytest.mark.parametrize('ringlets', [(), (2,)])
def test_growth_moves_wrapped_frames_into_the_new_storage(space, ringlets):
    """A reader asks for more room once the stored frames have wrapped round the end of the storage: they
    move to their slots in the new storage (in two runs here, one from each end) and read back exactly."""
    import importlib
    xp = importlib.import_module('cupy') if space == 'cuda' else np
    r = len(ringlets)
    x = np.random.default_rng(3).normal(size=(40,) + ringlets + (3,))

    def put(span, i):
        span.data[...] = xp.asarray(np.moveaxis(x[i:i + 4], 0, r))

    def get(span):
        d = span.data.get() if space == 'cuda' else np.array(span.data)
        return np.moveaxis(d, r, 0)

    ring, got = Ring(space=space), {}
    with ring.begin_writing() as w:
        with w.begin_sequence(hdr('g', dtype='f64', shape=list(ringlets) + [-1, 3]), 4, 8) as s:
            rseq = next(ring.open_reader(guarantee=True).sequences())
            rseq.resize(4, buf_nframe=8)
            for i in (0, 4):
                with s.reserve(4) as span:
                    put(span, i)
            with rseq.acquire(0, 4) as span:
                got[0] = get(span)
            held = rseq.acquire(4, 4)               # frames 4-7 stay held in slots 4-7
            with s.reserve(4) as span:              # frames 8-11 wrap round into slots 0-3
                put(span, 8)
            assert ring.capacity == 8
            rseq.resize(4, buf_nframe=20)           # frames 4-11 move to slots 4-11
            assert ring.capacity == 20
            with held:
                got[4] = get(held)
            for i in range(12, 40, 4):
                with s.reserve(4) as span:
                    put(span, i)
                with rseq.acquire(i - 4, 4) as span:
                    got[i - 4] = get(span)
            with rseq.acquire(36, 4) as span:
                got[36] = get(span)
    assert sorted(got) == list(range(0, 40, 4))
    for i, d in got.items():
        np.testing.assert_array_equal(d, x[i:i + 4])


# --------------------------------------------------------------------------------------------
# 'cuda' rings: ordering by events, pinned asynchronous host->device copies (GPU machine only)
# --------------------------------------------------------------------------------------------

_SPIN_SRC = r'''
extern "C" __global__ void spin(long long cycles) {
    long long t0 = clock64();
    while (clock64() - t0 < cycles) { }
}
'''


def _spin(cp, ms):
    """Queue a kernel that keeps the GPU busy ~ms on the current stream (the host returns at
    once): work queued after it on that stream runs late, as a slow GPU block's would."""
    try:
        hz = cp.cuda.Device().attributes['ClockRate'] * 1e3
    except Exception:
        hz = 2e9
    cp.RawKernel(_SPIN_SRC, 'spin')((1,), (1,), (np.int64(ms * 1e-3 * hz),))


class _SlowGpuScale(bfp.TransformBlock):
    """out = 2 * in on the GPU, each gulp queued behind a ~ms-long kernel."""

    def __init__(self, iring, ms=3, *args, **kwargs):
        super().__init__(iring, *args, **kwargs)
        self.ms = ms

    def define_valid_input_spaces(self):
        return ('cuda',)

    def on_sequence(self, iseq):
        return copy.deepcopy(iseq.header)

    def on_data(self, ispan, ospan):
        import cupy as cp
        _spin(cp, self.ms)
        ospan.data[...] = 2 * ispan.data   # reads the input only after the spin


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_GPU, reason='needs CuPy and a CUDA device')
@pytest.mark.parametrize('device_input', [False, True])
def test_cuda_slow_reader_never_sees_overwritten_data(device_input):
    """The slow block's host side returns long before its kernels run; only the release events
    stop the source (a fast second reader keeps it going) from overwriting the frames the
    queued kernels will read, and only the ready events stop them reading before the copy in."""
    import cupy as cp
    n, gulp = 200, 8
    x = (np.arange(n * 4, dtype=np.float32).reshape(n, 4) + 1) * 0.5

    def graph(space):
        with bfp.Pipeline() as p:
            arr = cp.asarray(x) if (device_input and space == 'cuda') else x
            src = ArraySourceBlock(arr, hdr(shape=(-1, 4)), gulp_nframe=gulp, space=space)
            slow = _SlowGpuScale(src) if space == 'cuda' else Scale(src, k=2)
            fast = ArraySinkBlock(src)
            sink = ArraySinkBlock(slow)
            run_with_timeout(p, 120)
        return sink.result(0), fast.result(0), src

    out, copy_out, src = graph('cuda')
    assert src.orings[0].capacity < n      # the ring really is re-used many times over
    np.testing.assert_array_equal(out, 2 * x)
    np.testing.assert_array_equal(copy_out, x)
    cpu_out, _, _ = graph('system')
    np.testing.assert_array_equal(out, cpu_out)


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_GPU, reason='needs CuPy and a CUDA device')
def test_cuda_unguaranteed_slow_reader_copies_are_exact():
    import cupy as cp
    n = 400
    x = np.repeat(np.arange(n, dtype=np.float32)[:, None], 3, axis=1)
    bad = []

    class SlowUnguaranteed(bfp.SinkBlock):
        def define_valid_input_spaces(self):
            return ('cuda',)

        def on_sequence(self, iseq):
            pass

        def on_data(self, ispan):
            _spin(cp, 2)
            got = cp.asnumpy(ispan.data[:, 0])
            if not np.array_equal(got, ispan.frame_offset + np.arange(ispan.nframe)):
                bad.append(ispan.frame_offset)

        def on_skip(self, islices, ospans):
            pass

    with bfp.Pipeline() as p:
        src = ArraySourceBlock(cp.asarray(x), hdr(shape=(-1, 3)), gulp_nframe=4, space='cuda')
        slow = SlowUnguaranteed(src, guarantee=False)
        run_with_timeout(p, 120)
    assert slow.stats['nframe_skipped'] + slow.stats['nframe_read'] == n
    assert slow.stats['nframe_read'] > 0 and not bad


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_GPU, reason='needs CuPy and a CUDA device')
def test_cuda_source_sends_packed_ci4_from_pinned_memory():
    import cupy as cp
    rng = np.random.default_rng(11)
    n, shape = 100, (3, 5, 2)
    z = rng.integers(-8, 8, (n,) + shape) + 1j * rng.integers(-8, 8, (n,) + shape)
    want = pack_ci4(z)
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(z, hdr(dtype='ci4', shape=(-1,) + shape), gulp_nframe=16,
                               space='cuda')
        sink = ArraySinkBlock(src)
        run_with_timeout(p, 60)
    stored = src._items[0][0]
    assert stored.dtype == np.uint8 and _compat.is_pinned(stored)
    # one byte per complex sample crossed the bus, straight from pinned memory
    assert src._h2d.nbytes == want.size and src._h2d.staged_bytes == 0
    np.testing.assert_array_equal(sink.result(0).view(np.uint8), want)
    # pageable host data go through the pinned staging buffers, chunk by chunk
    h2d = _compat.HostToDevice()
    dst = cp.zeros(want.shape, cp.uint8)
    with cp.cuda.Stream(non_blocking=True) as s:
        for i in range(0, n, 7):
            h2d.copy(dst[i:i + 7], want[i:i + 7])
        s.synchronize()
    np.testing.assert_array_equal(dst.get(), want)
    assert h2d.staged_bytes == want.size


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_GPU, reason='needs CuPy and a CUDA device')
def test_priority_streams_are_ordered():
    """'high' streams outrank 'low' ones (lower CUDA priority numbers); 'low' is CUDA's default, 0."""
    cupy = pytest.importorskip("cupy")
    from bf_epic_blocks.runtime.pipeline import priority_stream
    hi, lo = priority_stream(cupy, "high"), priority_stream(cupy, "low")
    if getattr(hi, "priority", None) is None:
        pytest.skip("this CuPy does not say a stream's priority")
    assert lo.priority == 0 and hi.priority < lo.priority
    with pytest.raises(ValueError, match="high' or 'low"):
        priority_stream(cupy, "urgent")


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_GPU, reason='needs CuPy and a CUDA device')
def test_block_keeps_its_own_stream_after_a_with_stream_in_its_hooks():
    """A block's kernels stay on its own stream whatever its hooks do: CuPy's get() of a non-contiguous
    array runs a `with stream:` of the current stream, whose end restores the entry below it on CuPy's
    per-thread stack -- the CUDA default stream, had the block's stream only been made current with
    use(). Two searches then shared the default stream in a whole-station run."""
    import cupy as cp
    seen = []

    class GetsStrided(bfp.SinkBlock):
        def define_valid_input_spaces(self):
            return ('cuda',)

        def on_sequence(self, iseq):
            seen.append(("sequence", cp.cuda.get_current_stream().ptr, self.stream.ptr))

        def on_data(self, ispan):
            before = cp.cuda.get_current_stream().ptr
            ispan.data[:, ::2].get()                     # not contiguous: CuPy's `with stream:` inside
            with cp.cuda.Stream(non_blocking=True):      # and a hook's own
                pass
            seen.append((before, cp.cuda.get_current_stream().ptr, self.stream.ptr))

    x = np.arange(40 * 4, dtype=np.float32).reshape(40, 4)
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(x, hdr(shape=(-1, 4)), gulp_nframe=8, space='cuda')
        GetsStrided(src)
        run_with_timeout(p, 60)
    assert len(seen) == 1 + 5
    own = seen[0][2]
    assert own != cp.cuda.Stream.null.ptr and seen[0][1] == own
    for before, after, stream in seen[1:]:
        assert (before, after, stream) == (own, own, own)


def test_sequence_after_sequence_keeps_memory_flat():
    """A service images stream after stream (each F-engine reset starts a sequence) for weeks: a ring
    forgets a sequence once every reader is past it (a station header holds ~10^5 numbers, ~8 MB a reset
    was kept before)."""
    import gc
    import tracemalloc
    r = Ring()
    rd = r.open_reader()
    it = rd.sequences()
    table = [float(i) for i in range(20000)]      # ~0.6 MB as Python objects, like a cable table

    def one(w, i):
        with w.begin_sequence(hdr(f's{i}', table=table), 4) as s:
            with s.reserve(4) as span:
                span.data[...] = i
                span.commit(4)
        rs = next(it)
        assert rs.name == f's{i}'
        got = [np.asarray(span.data).copy() for span in rs.read(4)]
        assert len(got) == 1 and (got[0] == i).all()

    tracemalloc.start()
    try:
        with r.begin_writing() as w:
            for i in range(5):
                one(w, i)
            gc.collect()
            before = tracemalloc.get_traced_memory()[0]
            for i in range(5, 45):
                one(w, i)
            gc.collect()
            grown = tracemalloc.get_traced_memory()[0] - before
            # a name stays unique for the ring's life, its sequence forgotten or not
            with pytest.raises(ValueError, match='already used'):
                w.begin_sequence(hdr('s3'), 4)
    finally:
        tracemalloc.stop()
    assert grown < 1.5e6, f"40 more sequences kept {grown / 1e6:.1f} MB"


def test_staging_buffers_are_made_once_for_the_room_asked(monkeypatch):
    """HostToDevice makes its staging buffers for ``room`` bytes (a whole gulp) at once, so chunks of other
    sizes (a stream's partial last gulp) reuse them instead of making page-locked buffers of their own."""
    made = []
    real = _compat.pinned_empty

    def counting(shape, dtype):
        made.append(int(np.prod(shape)))
        return real(shape, dtype)
    monkeypatch.setattr(_compat, "pinned_empty", counting)
    h2d = _compat.HostToDevice(nstage=2)
    for n in (37, 100, 11, 100, 33, 64):
        buf, _ = h2d.staging(n, room=100)
        assert buf.nbytes == n
    assert made == [100, 100]
    h2d.staging(150, room=100)             # larger than the room: a buffer of its own size, once
    assert made == [100, 100, 150]


_SIGTERM_WHILE_LOCKED = r'''
import os, signal, sys, threading
import numpy as np
from bf_epic_blocks.runtime import pipeline as rtp
from bf_epic_blocks.blocks.array_io import ArraySourceBlock, ArraySinkBlock
from bf_epic_blocks.pipeline.runner import execute


class Held(threading.Event):
    """The run loop's wake-up event, whose third clear() is interrupted by SIGTERM while it holds its lock."""
    n = 0

    def clear(self):
        with self._cond:
            Held.n += 1
            if Held.n == 3:
                os.kill(os.getpid(), signal.SIGTERM)
                for _ in range(100000):    # the handler runs at one of these bytecodes, the lock held
                    pass
            self._flag = False


x = np.arange(4000 * 2, dtype=np.float32).reshape(4000, 2)
with rtp.Pipeline() as p:
    src = ArraySourceBlock(x, {"name": "s", "time_tag": 0, "_tensor": {"dtype": "f32", "shape": [-1, 2]}},
                           gulp_nframe=8)
    sink = ArraySinkBlock(src, delay_s=0.004)
p._changed = Held()
stopped = execute(p)
print(stopped["signal"], sink.stats["nframe_read"], Held.n >= 3)
'''


def test_sigterm_while_the_run_loop_holds_its_lock_still_drains():
    """A signal handler runs in the main thread between two bytecodes, wherever the run loop is, even
    inside the lock of the event it waits on. SIGTERM's handler must take no lock that the interrupted
    loop may hold (it deadlocked there: the process never ended). Here SIGTERM comes inside that lock:
    the pipeline drains and ``execute`` returns, saying SIGTERM stopped it, before the data's end."""
    env = dict(os.environ, BF_EPIC_RUNTIME="builtin")
    try:
        out = subprocess.run([sys.executable, "-c", _SIGTERM_WHILE_LOCKED], capture_output=True, text=True,
                             timeout=30, env=env)
    except subprocess.TimeoutExpired as e:
        pytest.fail(f"SIGTERM inside the run loop's lock: the process did not end within 30 s ({e.stderr!r})")
    assert out.returncode == 0, out.stderr[-2000:]
    sig, nread, reached = out.stdout.split()
    assert sig == "SIGTERM" and reached == "True" and 0 < int(nread) < 4000, out.stdout
