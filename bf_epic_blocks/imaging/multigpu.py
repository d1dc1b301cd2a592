"""Several GPUs of one host: channels sharded across them, one :class:`~.dft.DFTOperator` per GPU.

Channels are independent in the imager (one operator per channel), so a gulp splits cleanly: GPU g
images channels ``blocks[g]`` (contiguous, as equal as possible) with its own operator, and the
images are gathered in channel order. The work is issued to every GPU before any result is waited
for, so the GPUs compute concurrently while the host issues the next GPU's kernels.

Input: voltages on the host (NumPy: each GPU copies only its channels, as one 2-D transfer -- T rows
of its channels' bytes at the gulp's pitch -- over its own link, no host-side strided copy), or a
CuPy array on any GPU (peer copies of the channel slices). Output: NumPy on the host, or CuPy on the
first GPU.
"""
from __future__ import annotations

import numpy as np

from ._xp import cupy_or_none

__all__ = ["ShardedOperator", "channel_blocks", "resolve_devices"]


def resolve_devices(devices) -> list[int]:
    """GPU indices from 'all', an int, or a list of ints; checked against the GPUs present."""
    cp = cupy_or_none()
    n = cp.cuda.runtime.getDeviceCount() if cp is not None else 0
    if n == 0:
        raise RuntimeError("several GPUs were asked for, but CuPy or a CUDA GPU is not available here")
    if devices == "all":
        return list(range(n))
    devs = [int(devices)] if np.isscalar(devices) else [int(d) for d in devices]
    bad = [d for d in devs if not 0 <= d < n]
    if bad or not devs or len(set(devs)) != len(devs):
        raise ValueError(f"GPU indices {devs} must be distinct and in 0..{n - 1} ({n} GPU(s) here)")
    return devs


def channel_blocks(nchan: int, nblock: int) -> list[slice]:
    """``nblock`` contiguous channel slices covering 0..nchan, sizes differing by at most one."""
    if nblock < 1 or nchan < nblock:
        raise ValueError(f"cannot share {nchan} channel(s) among {nblock} GPU(s): need at least one channel each")
    edges = np.linspace(0, nchan, nblock + 1).round().astype(int)
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


class ShardedOperator:
    """One DFT operator per GPU over contiguous channel blocks; same arguments as
    :class:`~.dft.DFTOperator` (host arrays), plus ``devices`` (GPU indices, or 'all').

    ``weights`` (nchan|1, nant, npol|1) and ``pattern`` (nchan|1, ...) are split by channel too.
    """

    def __init__(self, xyz_m, freq_hz, pixels_lm, devices="all", *, npol=1, weights=None, pattern=None,
                 precision="fp32"):
        from .dft import DFTOperator
        cp = cupy_or_none()
        self.devices = resolve_devices(devices)
        freq = np.atleast_1d(np.asarray(freq_hz, dtype=np.float64))
        self.nchan = len(freq)
        self.blocks = channel_blocks(self.nchan, len(self.devices))
        self.ops = []
        for d, cs in zip(self.devices, self.blocks):
            with cp.cuda.Device(d):
                w = None if weights is None else cp.asarray(_chan_slice(np.asarray(weights), cs, self.nchan, axis=0))
                b = None if pattern is None else cp.asarray(_chan_slice(np.asarray(pattern), cs, self.nchan, axis=0))
                self.ops.append(DFTOperator(cp.asarray(xyz_m), cp.asarray(freq[cs]), cp.asarray(pixels_lm),
                                            npol=npol, weights=w, pattern=b, precision=precision))
        self.npix, self.npol, self.precision = self.ops[0].npix, npol, precision
        self.threads = True
        self._executor = None

    def _pool(self):
        if self._executor is None:
            from concurrent.futures import ThreadPoolExecutor
            self._executor = ThreadPoolExecutor(max_workers=len(self.devices), thread_name_prefix="bf-epic-gpu")
        return self._executor

    def image(self, efield, products=None, *, remove_autocorr=False, method="auto", accumulate=None,
              decode=None, out="host"):
        """Images of ``efield`` (host or device; (ntime, nchan, nant, npol[, 2])), as
        :meth:`~.dft.DFTOperator.image`, gathered in channel order.

        decode : optional function applied on each GPU to the transferred gulp before slicing (e.g.
            ``lambda b: unpack_int8_pairs(b, 'ci4')`` so packed 4-bit samples cross the bus).
        out : 'host' (NumPy) or 'device' (CuPy on the first GPU).
        """
        cp = cupy_or_none()
        axis = 0 if accumulate is None else 1     # (nchan, ...) or (ngroup, nchan, ...)

        def shard(i):
            d, cs, op = self.devices[i], self.blocks[i], self.ops[i]
            with cp.cuda.Device(d):
                if isinstance(efield, np.ndarray):
                    x = _host_channels_to_device(efield, cs)      # only this GPU's channels cross
                    x = decode(x) if decode is not None else x
                else:
                    x = _to_device(efield, d)
                    x = (decode(x) if decode is not None else x)[:, cs]
                img = op.image(x, products, remove_autocorr=remove_autocorr, method=method,
                               accumulate=accumulate)
                if out == "host":
                    return img.get()          # (waits for the stream: the host buffer is read by then)
                if isinstance(efield, np.ndarray):
                    cp.cuda.get_current_stream().synchronize()   # the caller may reuse its buffer
                return img
        if self.threads and len(self.devices) > 1:
            # one host thread per GPU: the transfers and waits release the GIL, so one GPU's copies
            # and results overlap another's kernel launches
            parts = list(self._pool().map(shard, range(len(self.devices))))
        else:
            parts = [shard(i) for i in range(len(self.devices))]
        if out == "host":
            return np.concatenate(parts, axis=axis)
        with cp.cuda.Device(self.devices[0]):
            return cp.concatenate([_to_device(p, self.devices[0]) for p in parts], axis=axis)


def _chan_slice(a, cs, nchan, axis=0):
    """Channel slice of an array broadcastable along ``axis`` (length nchan or 1)."""
    if a.ndim == 1 or a.shape[axis] == 1:
        return a
    if a.shape[axis] != nchan:
        raise ValueError(f"expected {nchan} channels (or 1) on axis {axis}, got shape {a.shape}")
    return np.take(a, np.arange(cs.start, cs.stop), axis=axis)


def _host_channels_to_device(host, cs):
    """Channels ``cs`` (axis 1) of a host array (T, C, ...) as a contiguous CuPy array on the current
    GPU: one 2-D copy (T rows of the channels' bytes, pitched by a whole sample) on the current stream."""
    cp = cupy_or_none()
    host = np.ascontiguousarray(host)
    T, C = host.shape[:2]
    per_c = host[0].nbytes // C if T else 0
    out = cp.empty((T, cs.stop - cs.start) + host.shape[2:], host.dtype)
    if out.nbytes:
        width = per_c * (cs.stop - cs.start)
        cp.cuda.runtime.memcpy2DAsync(out.data.ptr, width, host.ctypes.data + cs.start * per_c, per_c * C,
                                      width, T, cp.cuda.runtime.memcpyHostToDevice,
                                      cp.cuda.get_current_stream().ptr)
    return out


def _to_device(a, d):
    """A CuPy array on device ``d`` (peer copy if it lives elsewhere)."""
    cp = cupy_or_none()
    if a.device.id == d:
        return a
    with cp.cuda.Device(d):
        out = cp.empty_like(a)
        out.data.copy_from_device(a.data, a.nbytes)
        return out
