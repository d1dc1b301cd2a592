"""Array source and sink blocks (for tests, notebooks and small jobs).

Written against ``_compat.bfp`` only, so they run on real Bifrost and on our runtime.

* :class:`ArraySourceBlock` feeds in-memory arrays as sequences: each array is shaped
  (ntime, ...) with the FRAME AXIS FIRST, then the tensor's other axes in order (ringlets, then
  the frame shape); it is written in gulps of ``gulp_nframe`` frames, the last one short.
  The header's ``_tensor['dtype']`` decides the stored type: complex input into a 'ci4',
  'ci8' or 'ci16' ring is rounded/clipped and packed. For a 'cuda' ring the arrays are packed
  once, at construction, into page-locked host memory, and each gulp crosses the bus in that
  storage form (ci4: one byte per sample) as an asynchronous copy on the block's own stream
  (:class:`~._compat.HostToDevice`); CuPy arrays stay on the device (a device copy per gulp).
* :class:`ArraySinkBlock` collects every sequence: ``headers`` (list of dicts),
  ``result(i)`` / ``arrays`` -- NumPy arrays, frame axis first like the source's input
  (copied from the device for 'cuda'); ``result(i, as_complex=True)`` decodes complex types.
  Frames lost to overruns (``guarantee=False``) are stored as zeros and counted in
  ``nframe_skipped`` (one count per sequence).
"""
from __future__ import annotations

import copy
import time

import numpy as np

from ._compat import bfp, span_array, space_of, to_numpy, assign_storage, pack_complex, \
    unpack_complex, storage_dtype, HostToDevice, pin, stream_context, frames_overwritten

_NP_TO_BF = {np.dtype(k): v for k, v in [
    (np.int8, 'i8'), (np.int16, 'i16'), (np.int32, 'i32'), (np.int64, 'i64'),
    (np.uint8, 'u8'), (np.uint16, 'u16'), (np.uint32, 'u32'), (np.uint64, 'u64'),
    (np.float16, 'f16'), (np.float32, 'f32'), (np.float64, 'f64'),
    (np.complex64, 'cf32'), (np.complex128, 'cf64')]}


def _split(shape):
    i = list(shape).index(-1)
    return list(shape[:i]), list(shape[i + 1:])


def _is_cupy(a):
    return type(a).__module__.startswith('cupy')


def _prepare_device(array, hdr, index):
    """A CuPy array for a 'cuda' ring stays on the device, in the ring's storage form:
    complex values are packed there; ci4 bytes, plain pair arrays (..., 2) and real types
    are kept (cast to the storage dtype)."""
    import cupy as cp
    tensor = hdr['_tensor']
    if 'dtype' not in tensor:
        if np.dtype(array.dtype) not in _NP_TO_BF:
            raise ValueError(f"sequence {index}: cannot infer a Bifrost dtype from "
                             f"{array.dtype}; give header['_tensor']['dtype']")
        tensor['dtype'] = _NP_TO_BF[np.dtype(array.dtype)]
    dtype = tensor['dtype']
    sdt, extra = storage_dtype(dtype, 'cuda')
    if cp.iscomplexobj(array):
        stored = pack_complex(array, dtype, 'cuda', xp=cp)
    elif dtype == 'ci4' and array.dtype.itemsize == 1:
        stored = array.view(cp.uint8)
    else:
        stored = array.astype(sdt, copy=False)
    tensor.setdefault('shape', [-1] + list(stored.shape[1:stored.ndim - len(extra)]))
    return cp.ascontiguousarray(stored)


def _prepare(array, header, index, space):
    """Validate one (array, header) pair; return (frames_first_storage_array, header)."""
    if _is_cupy(array) and space == 'cuda':
        hdr = copy.deepcopy(header) if header is not None else {}
        if not isinstance(hdr, dict):
            raise TypeError(f"sequence {index}: header must be a dict, got "
                            f"{type(header).__name__}")
        stored = _prepare_device(array, hdr, index)
        shape = hdr['_tensor']['shape']
        if not isinstance(shape, (list, tuple)) or list(shape).count(-1) != 1:
            raise ValueError(f"sequence {index}: header['_tensor']['shape'] must contain "
                             f"exactly one -1, got {shape!r}")
        ringlet, frame = _split(shape)
        _, extra = storage_dtype(hdr['_tensor']['dtype'], 'cuda')
        expect = tuple(ringlet) + tuple(frame) + extra
        if tuple(stored.shape[1:]) != expect:
            raise ValueError(f"sequence {index}: array shape {stored.shape} does not match the "
                             f"header tensor shape {list(shape)}; expected (ntime,) + {expect}")
        hdr.setdefault('name', f'array_{index}')
        return stored, hdr
    arr = to_numpy(array)
    if arr.ndim < 1:
        raise ValueError(f"sequence {index}: the array needs a frame axis first, got a scalar")
    hdr = copy.deepcopy(header) if header is not None else {}
    if not isinstance(hdr, dict):
        raise TypeError(f"sequence {index}: header must be a dict, got {type(header).__name__}")
    tensor = hdr.setdefault('_tensor', {})
    if 'dtype' not in tensor:
        if arr.dtype not in _NP_TO_BF:
            raise ValueError(f"sequence {index}: cannot infer a Bifrost dtype from "
                             f"{arr.dtype}; give header['_tensor']['dtype']")
        tensor['dtype'] = _NP_TO_BF[arr.dtype]
    tensor.setdefault('shape', [-1] + list(arr.shape[1:]))
    dtype = tensor['dtype']
    shape = tensor['shape']
    if not isinstance(shape, (list, tuple)) or list(shape).count(-1) != 1:
        raise ValueError(f"sequence {index}: header['_tensor']['shape'] must contain exactly "
                         f"one -1, got {shape!r}")
    ringlet, frame = _split(shape)
    sdt, extra = storage_dtype(dtype, 'cuda' if space == 'cuda' else 'system')
    raw = (arr.dtype.names is not None or
           (dtype == 'ci4' and arr.dtype.itemsize == 1 and arr.dtype.kind in 'iu'))
    expect = tuple(ringlet) + tuple(frame)
    if tuple(arr.shape[1:]) != expect:
        raise ValueError(f"sequence {index}: array shape {arr.shape} does not match the "
                         f"header tensor shape {list(shape)}; expected (ntime,) + "
                         f"{expect} (frame axis first, then ringlets, then frame axes)")
    if raw:   # already in a packed/structured form: keep the bytes
        if arr.dtype.itemsize != sdt.itemsize * (2 if extra else 1):
            raise ValueError(f"sequence {index}: {arr.dtype} data cannot be {dtype!r} samples")
        stored = arr.view(np.uint8) if dtype == 'ci4' else arr
        if extra:  # structured pairs -> plain (..., 2) on 'cuda'
            stored = np.ascontiguousarray(arr).view(sdt).reshape(arr.shape + extra)
        elif stored.dtype != sdt:
            stored = np.ascontiguousarray(stored).view(sdt)
    else:
        stored = pack_complex(arr, dtype, 'cuda' if space == 'cuda' else 'system', xp=np)
    hdr.setdefault('name', f'array_{index}')
    if space == 'cuda':   # page-locked, so each gulp crosses the bus asynchronously
        stored = pin(np.ascontiguousarray(stored))
    return stored, hdr


class _ArrayReader:
    def __init__(self, frames, header):
        self.frames, self.header, self.pos = frames, header, 0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        pass


class ArraySourceBlock(bfp.SourceBlock):
    """Feed arrays as sequences.

    Args:
        arrays: one array or a list of arrays, each (ntime, ...) with the frame axis first.
        headers: one header dict or a list (one per array). Missing ``name`` -> 'array_<i>'
            (suffixed '_<i>' when one dict serves several arrays), ``time_tag`` -> the
            sequence index, ``_tensor`` -> inferred from a plain NumPy array
            (shape [-1] + array.shape[1:]).
        gulp_nframe: frames per gulp (the last gulp of a sequence may be short).
        space: output ring space, 'system' (default) or 'cuda'.
    """

    def __init__(self, arrays, headers, gulp_nframe, space='system', *args, **kwargs):
        if isinstance(arrays, (list, tuple)):
            arrays = list(arrays)
        else:
            arrays = [arrays]
        if isinstance(headers, dict) or headers is None:
            shared = headers
            headers = []
            for i in range(len(arrays)):
                h = copy.deepcopy(shared) if shared is not None else {}
                if len(arrays) > 1 and 'name' in h:
                    h['name'] = f"{h['name']}_{i}"
                headers.append(h)
        headers = list(headers)
        if len(headers) != len(arrays):
            raise ValueError(f"got {len(arrays)} arrays but {len(headers)} headers; give one "
                             "header per array or a single dict")
        super().__init__(list(range(len(arrays))), gulp_nframe, space, *args, **kwargs)
        self._items = [_prepare(a, h, i, space) for i, (a, h) in
                       enumerate(zip(arrays, headers))]
        self._h2d = HostToDevice()

    def create_reader(self, sourcename):
        frames, hdr = self._items[sourcename]
        return _ArrayReader(frames, hdr)

    def on_sequence(self, reader, sourcename):
        return [copy.deepcopy(reader.header)]

    def on_data(self, reader, ospans):
        ospan = ospans[0]
        n = min(ospan.nframe, reader.frames.shape[0] - reader.pos)
        if n <= 0:
            return [0]
        dst = span_array(ospan)
        nring = len(_split(reader.header['_tensor']['shape'])[0])
        chunk = reader.frames[reader.pos:reader.pos + n]
        index = (slice(None),) * nring + (slice(0, n),)
        if _is_cupy(chunk):        # device-resident input: a device copy on this block's stream
            import cupy as cp
            with stream_context():
                dst[index] = cp.moveaxis(chunk, 0, nring) if nring else chunk
        elif _is_cupy(dst) and not nring:
            self._h2d.copy(dst[index], chunk)   # packed bytes, pinned, asynchronous
        else:
            if nring:
                chunk = np.moveaxis(chunk, 0, nring)
            assign_storage(dst[index], np.ascontiguousarray(chunk))
        reader.pos += n
        return [n]


class ArraySinkBlock(bfp.SinkBlock):
    """Collect every sequence of ``iring`` into NumPy arrays (frame axis first).

    Args:
        iring: the input Ring or Block.
        delay_s: seconds to sleep after each gulp (to make a slow reader in tests).
        guarantee (keyword, from SinkBlock): False makes an overrunnable reader; lost frames
            become zeros in the result and are counted in ``nframe_skipped``.

    Frames are placed by their offset in the sequence (``span.frame_offset``), not by the order
    of calls, so the result is right on both runtimes: real Bifrost reports frames overwritten
    *while* ``on_data`` read them through a later ``on_skip`` (here those frames, counted by the
    span's ``nframe_overwritten`` after the copy, are zeroed), and after such an overrun it skips
    a whole further gulp without a call that says where; frames never delivered intact stay zero.
    """

    def __init__(self, iring, delay_s=0.0, *args, **kwargs):
        super().__init__(iring, *args, **kwargs)
        self.delay_s = float(delay_s)
        self.headers = []
        self._chunks = []     # per sequence: [(frame offset, array, frames zeroed at its start)]
        self._skipped_end = []  # per sequence: 1 + the last frame a skip reported
        self._nring = 0

    def on_sequence(self, iseq):
        hdr = copy.deepcopy(iseq.header)
        self.headers.append(hdr)
        self._chunks.append([])
        self._skipped_end.append(0)
        self._nring = len(_split(hdr['_tensor']['shape'])[0])

    def on_data(self, ispan):
        data = to_numpy(span_array(ispan))
        if self._nring:
            data = np.moveaxis(data, self._nring, 0)
        data = np.array(data, copy=True)
        nover = frames_overwritten(ispan, data.shape[0])   # after the copy just made
        data[:nover] = 0
        self._chunks[-1].append((int(ispan.frame_offset), data, nover))
        if self.delay_s > 0:
            time.sleep(self.delay_s)

    def on_skip(self, islices, ospans):
        # Lost frames are the gaps between placed chunks; this only extends the sequence when
        # frames are lost at its end (our runtime's slices start where the loss starts).
        islice = islices[0]
        if islice.stop is not None and islice.start is not None and islice.stop > islice.start:
            self._skipped_end[-1] = max(self._skipped_end[-1], int(islice.stop))

    def _nframe(self, i):
        ends = [off + a.shape[0] for off, a, _ in self._chunks[i]]
        return max(ends + [self._skipped_end[i]])

    @property
    def nframe_skipped(self):
        """Per sequence: frames in the result that were not delivered intact (zeros)."""
        return [self._nframe(i) - sum(a.shape[0] - z for _, a, z in self._chunks[i])
                for i in range(len(self.headers))]

    def result(self, i=0, as_complex=False):
        """Sequence ``i`` as one NumPy array, frame axis first (``as_complex``: complex64)."""
        if not -len(self.headers) <= i < len(self.headers):
            raise IndexError(f"sequence {i} not collected; have {len(self.headers)}")
        hdr = self.headers[i]
        ringlet, frame = _split(hdr['_tensor']['shape'])
        space = space_of(self.irings[0])
        sdt, extra = storage_dtype(hdr['_tensor']['dtype'], 'cuda' if space == 'cuda' else 'system')
        chunks = self._chunks[i]
        if chunks:
            sdt, shape = chunks[0][1].dtype, chunks[0][1].shape[1:]
        else:
            shape = tuple(ringlet) + tuple(frame) + extra
        out = np.zeros((self._nframe(i),) + tuple(shape), sdt)
        for off, a, _ in chunks:
            out[off:off + a.shape[0]] = a
        if as_complex:
            out = unpack_complex(out, hdr['_tensor']['dtype'], xp=np)
        return out

    @property
    def arrays(self):
        """Every sequence's array, in order."""
        return [self.result(i) for i in range(len(self.headers))]


def array_source(arrays, headers, gulp_nframe, space='system', *args, **kwargs):
    """Factory for :class:`ArraySourceBlock`."""
    return ArraySourceBlock(arrays, headers, gulp_nframe, space, *args, **kwargs)


def array_sink(iring, delay_s=0.0, *args, **kwargs):
    """Factory for :class:`ArraySinkBlock`."""
    return ArraySinkBlock(iring, delay_s, *args, **kwargs)
