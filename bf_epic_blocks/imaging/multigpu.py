"""Several GPUs of one host: channels sharded across them, one :class:`~.dft.DFTOperator` per GPU.

Channels are independent in the imager (one operator per channel), so a gulp splits cleanly: GPU g
images channels ``blocks[g]`` (contiguous, as equal as possible) with its own operator, and its
images land in their channel slice of one pinned host array (no gather step). The work is issued
to every GPU before any result is waited for, so the GPUs compute concurrently.

Input: voltages on the host (NumPy: each GPU copies only its channels, as one 2-D transfer -- T rows
of its channels' bytes at the gulp's pitch -- over its own link, on a copy stream of its own), or a
CuPy array on any GPU (peer copies of the channel slices). Output: NumPy on the host, or CuPy on the
first GPU.

Several gulps in flight: :meth:`ShardedOperator.submit` returns at once with a
:class:`PendingImages`. A caller that submits gulp n+1 before taking gulp n's result keeps every
GPU busy: gulp n+1 crosses the bus while gulp n is imaged, and the host's issue and gather work
(about 0.1 ms a gulp per GPU) is hidden behind the GPUs' (``depth`` staging buffers per GPU bound
how many gulps' inputs can be ahead).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ._xp import cupy_or_none, pinned_empty
from .pixels import GridPlacement

__all__ = ["PendingImages", "ShardedOperator", "channel_blocks", "resolve_devices"]


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
    :class:`~.dft.DFTOperator` (host arrays), plus ``devices`` (GPU indices, or 'all') and ``depth``
    (gulps that may be in flight per GPU: input staging buffers each GPU keeps).

    ``weights`` (nchan|1, nant, npol|1) and ``pattern`` (nchan|1, ...) are split by channel too.

    ``scatter`` : None, or (index, n): each image is returned on an axis of n pixels, the imaged ones
    at ``index`` (flat indices, in pixel order) and NaN elsewhere -- e.g. the pixels above the horizon
    of an l, m grid placed on the whole grid. Done on the GPUs, before the images cross the bus.

    :meth:`image` returns a gulp's images; :meth:`submit` only starts them and returns a
    :class:`PendingImages`, so a caller that keeps several gulps in flight overlaps one gulp's
    transfers, host work and gather with the GPUs' imaging of the previous one.
    """

    def __init__(self, xyz_m, freq_hz, pixels_lm, devices="all", *, npol=1, weights=None, pattern=None,
                 precision="fp32", depth=2, scatter=None):
        from .dft import DFTOperator
        cp = cupy_or_none()
        self.devices = resolve_devices(devices)
        if int(depth) < 1:
            raise ValueError(f"depth (gulps in flight per GPU) must be at least 1, got {depth!r}")
        freq = np.atleast_1d(np.asarray(freq_hz, dtype=np.float64))
        self.nchan = len(freq)
        self.blocks = channel_blocks(self.nchan, len(self.devices))
        self.ops, self.lanes = [], []
        for d, cs in zip(self.devices, self.blocks):
            with cp.cuda.Device(d):
                w = None if weights is None else cp.asarray(_chan_slice(np.asarray(weights), cs, self.nchan, axis=0))
                b = None if pattern is None else cp.asarray(_chan_slice(np.asarray(pattern), cs, self.nchan, axis=0))
                op = DFTOperator(cp.asarray(xyz_m), cp.asarray(freq[cs]), cp.asarray(pixels_lm),
                                 npol=npol, weights=w, pattern=b, precision=precision)
            self.ops.append(op)
            self.lanes.append(_Lane(d, cs, op, int(depth)))
        self.npix, self.npol, self.precision = self.ops[0].npix, npol, precision
        self.npix_out = self.npix
        if scatter is not None:
            index, n = np.asarray(scatter[0]).ravel(), int(scatter[1])
            if index.size != self.npix:   # (indices and range: checked by GridPlacement)
                raise ValueError(f"scatter must be ({self.npix} integer indices in 0..n-1, n), got "
                                 f"{index.size} indices for n = {n}")
            self.npix_out = n
            for lane in self.lanes:
                with cp.cuda.Device(lane.device):
                    lane.scatter = GridPlacement(index, n, cp)
        # the operators and placements are built on each device's current stream, which the lanes'
        # non-blocking streams do not wait for by themselves: on a busy GPU the first gulp was imaged
        # with an operator still being built
        for lane in self.lanes:
            with cp.cuda.Device(lane.device):
                built = cp.cuda.get_current_stream().record()
                lane.copy.wait_event(built)
                lane.compute.wait_event(built)

    def image(self, efield, products=None, *, remove_autocorr=False, method="auto", accumulate=None,
              decode=None, out="host"):
        """Images of ``efield`` (host or device; (ntime, nchan, nant, npol[, 2])), as
        :meth:`~.dft.DFTOperator.image`, gathered in channel order.

        decode : optional function applied on each GPU to the transferred gulp before imaging (e.g.
            ``lambda b: unpack_int8_pairs(b, 'ci4')`` so packed 4-bit samples cross the bus).
        out : 'host' (NumPy, pinned), 'device' (CuPy on the first GPU), or a C-contiguous NumPy array
            of the images' shape and dtype to fill (e.g. a block's output span: no host copy at all).
        Images: (nchan, nprod, npix_out), or (ntime // N, nchan, nprod, npix_out) with ``accumulate=N``.
        """
        return self.submit(efield, products, remove_autocorr=remove_autocorr, method=method,
                           accumulate=accumulate, decode=decode, out=out).result()

    def submit(self, efield, products=None, *, remove_autocorr=False, method="auto", accumulate=None,
               decode=None, out="host"):
        """Start imaging one gulp on every GPU; returns a :class:`PendingImages` at once.

        Arguments as :meth:`image`. Each GPU copies its channels of a host gulp (one 2-D transfer,
        on a copy stream of its own, into one of ``depth`` staging buffers) while it images the
        previous gulp, then images them and copies its images straight into their channel slice of
        one pinned host array: there is no gather step. The caller must not change a host ``efield``
        until :meth:`PendingImages.release_input` (or ``result``) has returned.
        """
        from .products import resolve_products
        cp = cupy_or_none()
        if not isinstance(out, np.ndarray) and out not in ("host", "device"):
            raise ValueError(f"out must be 'host', 'device' or a NumPy array, got {out!r}")
        host_in = isinstance(efield, np.ndarray)
        if host_in:
            efield = np.ascontiguousarray(efield)
            ready = None
        else:
            with cp.cuda.Device(efield.device.id):           # the caller's writes to efield come first
                ready = cp.cuda.get_current_stream().record()
        if efield.ndim < 2 or efield.shape[1] != self.nchan:
            raise ValueError(f"expected {self.nchan} channels on axis 1 of the gulp, got shape {efield.shape}")
        nprod = len(resolve_products(self.npol, products))
        T = int(efield.shape[0])
        lead = () if accumulate is None else (T // int(accumulate),)
        shape = lead + (self.nchan, nprod, self.npix_out)
        if isinstance(out, np.ndarray):
            if out.shape != shape or out.dtype != self.ops[0].rdtype or not out.flags.c_contiguous:
                raise ValueError(f"out: expected a C-contiguous {np.dtype(self.ops[0].rdtype).name} array of shape "
                                 f"{shape}, got {out.dtype.name} {out.shape}"
                                 + ("" if out.flags.c_contiguous else " (not C-contiguous)"))
            host = out
        else:
            host = pinned_empty(shape, self.ops[0].rdtype) if out == "host" else None
        kw = dict(remove_autocorr=remove_autocorr, method=method, accumulate=accumulate)
        # issued from this thread, GPU after GPU: every call is asynchronous, so each GPU starts as soon
        # as its share is issued (not one host thread per GPU: those threads would contend for the
        # interpreter lock, which costs more host time per gulp than issuing from one thread)
        parts = [lane.issue(efield, ready, decode, products, kw, host, len(lead)) for lane in self.lanes]
        return PendingImages(self, parts, host, shape, len(lead))


class PendingImages:
    """One gulp's images, in progress on the GPUs (from :meth:`ShardedOperator.submit`)."""

    def __init__(self, sharded, parts, host, shape, axis):
        self._sharded, self._parts, self._host, self.shape, self._axis = sharded, parts, host, shape, axis
        self._result = None

    def __del__(self):
        # the GPUs may still be writing into the pinned host array, which goes back to the pool now
        try:
            if self._result is None:
                for p in self._parts:
                    p.done.synchronize()
        except Exception:  # noqa: BLE001 -- at interpreter exit the CUDA context may be gone
            pass

    def release_input(self):
        """Wait until every GPU has read its part of a host input (the caller may then reuse it)."""
        for p in self._parts:
            p.copied.synchronize()

    def result(self):
        """The images: a NumPy array (pinned host memory) or a CuPy array on the first GPU."""
        if self._result is not None:
            return self._result
        cp = cupy_or_none()
        if self._host is not None:
            for p in self._parts:
                p.done.synchronize()
            self._result = self._host
        else:
            d0 = self._sharded.devices[0]
            with cp.cuda.Device(d0):
                stream = cp.cuda.get_current_stream()
                for p in self._parts:
                    stream.wait_event(p.done)
                self._result = cp.concatenate([_to_device(p.image, d0) for p in self._parts], axis=self._axis)
        self._parts = [p._replace(image=None) for p in self._parts]
        return self._result


class _Part(NamedTuple):
    image: object        # this GPU's images (CuPy), kept alive until the result is taken
    copied: object       # event: this GPU has read its input
    done: object         # event: its images are computed (and copied to the host array)


class _Lane:
    """One GPU's share of a :class:`ShardedOperator`: its operator and channel slice, a copy stream
    and a compute stream, and ``depth`` staging buffers for host input (each with the event after
    which it may be overwritten)."""

    def __init__(self, device, chans, op, depth):
        cp = cupy_or_none()
        self.device, self.chans, self.op = device, chans, op
        with cp.cuda.Device(device):
            self.copy = cp.cuda.Stream(non_blocking=True)
            self.compute = cp.cuda.Stream(non_blocking=True)
        self.slots = [None] * depth      # (device buffer, event: the imaging that read it is done)
        self.next = 0
        self.scatter = None              # a GridPlacement on this GPU: images placed on its n cells

    def _stage(self, host):
        """Copy this lane's channels of a host gulp into the next staging buffer; (buffer, slot, event)."""
        cp = cupy_or_none()
        cs = self.chans
        shape = (host.shape[0], cs.stop - cs.start) + host.shape[2:]
        i = self.next
        self.next = (i + 1) % len(self.slots)
        slot = self.slots[i]
        if slot is None or slot[0].shape != shape or slot[0].dtype != host.dtype:
            self.compute.synchronize()             # a buffer being replaced may still be read
            with self.copy:
                slot = (cp.empty(shape, host.dtype), None)
        buf, free = slot
        if free is not None:
            self.copy.wait_event(free)             # the gulp that last used this buffer is imaged
        _copy_host_channels(buf, host, cs, self.copy)
        return buf, i, self.copy.record()

    def issue(self, efield, ready, decode, products, kw, host_out, axis):
        """Queue this GPU's share of a gulp (copy in, decode, image, place pixels, copy out); a _Part.

        ready : None for host input, else the event after which the device input ``efield`` is valid.
        host_out : the host array its images go into (channel axis ``axis``), or None (kept on device).
        """
        cp = cupy_or_none()
        with cp.cuda.Device(self.device):
            if ready is None:                      # host input: staged over this GPU's own link
                buf, i, copied = self._stage(efield)
                self.compute.wait_event(copied)
            else:
                self.compute.wait_event(ready)
                buf, i = None, None
            with self.compute:
                if buf is not None:
                    x = decode(buf) if decode is not None else buf
                else:
                    x = _to_device(efield, self.device)
                    x = (decode(x) if decode is not None else x)[:, self.chans]
                img = self.op.image(x, products, **kw)
                if self.scatter is not None:
                    img = self.scatter(img)
                if buf is not None:
                    self.slots[i] = (buf, self.compute.record())
                    copied_ev = copied
                else:
                    copied_ev = self.compute.record()
                if host_out is not None:
                    _copy_to_host_channels(host_out, img, self.chans, axis, self.compute)
                return _Part(img, copied_ev, self.compute.record())


def _chan_slice(a, cs, nchan, axis=0):
    """Channel slice of an array broadcastable along ``axis`` (length nchan or 1)."""
    if a.ndim == 1 or a.shape[axis] == 1:
        return a
    if a.shape[axis] != nchan:
        raise ValueError(f"expected {nchan} channels (or 1) on axis {axis}, got shape {a.shape}")
    return np.take(a, np.arange(cs.start, cs.stop), axis=axis)


def _copy_host_channels(dst, host, cs, stream):
    """dst[...] = host[:, cs] on ``stream``: one 2-D copy (T rows of the channels' bytes, pitched by a
    whole sample) from a C-contiguous host array (T, C, ...) to a contiguous device array."""
    cp = cupy_or_none()
    T, C = host.shape[:2]
    if dst.nbytes:
        per_c = host[0].nbytes // C
        width = per_c * (cs.stop - cs.start)
        cp.cuda.runtime.memcpy2DAsync(dst.data.ptr, width, host.ctypes.data + cs.start * per_c, per_c * C,
                                      width, T, cp.cuda.runtime.memcpyHostToDevice, stream.ptr)


def _copy_to_host_channels(host, img, cs, axis, stream):
    """host[..., cs, ...] = img (channel axis ``axis``: 0, or 1 after a leading integration axis) on
    ``stream``, one 2-D copy from the device into the (pinned) host array."""
    cp = cupy_or_none()
    want = host.shape[:axis] + (cs.stop - cs.start,) + host.shape[axis + 1:]
    if img.shape != want or img.dtype != host.dtype:
        raise RuntimeError(f"GPU images {img.shape} {img.dtype} do not fit the gathered {want} {host.dtype}")
    img = cp.ascontiguousarray(img)
    if not img.nbytes:
        return
    rows = math.prod(host.shape[:axis])
    per_c = math.prod(host.shape[axis + 1:]) * host.itemsize
    width = per_c * (cs.stop - cs.start)
    cp.cuda.runtime.memcpy2DAsync(host.ctypes.data + cs.start * per_c, per_c * host.shape[axis], img.data.ptr,
                                  width, width, rows, cp.cuda.runtime.memcpyDeviceToHost, stream.ptr)


def _to_device(a, d):
    """A CuPy array on device ``d`` (a peer copy, on d's current stream, if it lives elsewhere)."""
    cp = cupy_or_none()
    if a.device.id == d:
        return a
    with cp.cuda.Device(d):
        out = cp.empty_like(a)
        # on the current stream: a plain copy_from_device would run on the legacy default stream,
        # which a non-blocking stream does not wait for
        out.data.copy_from_device_async(a.data, a.nbytes, cp.cuda.get_current_stream())
        return out
